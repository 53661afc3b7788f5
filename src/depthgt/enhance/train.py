"""Training and inference of the depth-enhancement networks (small step functions).

A model is chosen by name from :data:`depthgt.registry.MODELS` (``lapden``, ``ddrnet``,
``sdd``: the ``builder`` names of the learned methods); each entry names a builder (plain
keyword parameters -> ``nn.Module``), its loss (``loss(outputs, batch, **loss_params) ->
(total, terms)``, see :mod:`depthgt.enhance.losses`) and the loss terms its log records.
Every model maps depth (B, 1, H, W) metres to a list of depth maps, finest last.

:func:`train` reads the patch manifests (``results/dataset/{train,val}.parquet``: one
row per kept patch pair with ``frameset`` (its ``patches.npz`` lies there) and ``patch`` (its index
there)), trains with Adam and random flips, validates each epoch and writes the files
of :class:`TrainOutputs` (in the workflow: ``results/models/{model}/``)::

    last           model + optimiser state after the last finished epoch (resume point)
    best           the checkpoint with the lowest validation loss
    log            loss_log.csv: epoch, split, total, the model's loss terms, batches,
                   seconds (:func:`depthgt.registry.log_columns`)
    meta           train.json: resolved settings, parameter count, best epoch, versions
    resume         optional folder of the resume state (``last.pt``, ``best.pt``, written
                   every epoch; ``last`` and ``best`` are then written when training ends)

An interrupted run resumes from ``resume`` (or, without one, from ``last``); with the
same seed it ends with the same weights as an uninterrupted one (the shuffling and flips
of epoch e depend only on ``(seed, e)``). The workflow keeps the resume state in
``results/models/{model}/resume/``, which is not an output of the rule, because
Snakemake deletes the outputs of a killed job before it runs the job again.
"""

from __future__ import annotations

import csv
import importlib
import inspect
import json
import logging
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict
from functools import partial
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd
import torch
import torch.nn as nn
from torch.utils.data import Dataset

from depthgt import registry
from depthgt.atomic import write_atomic
from depthgt.data import GTDataset, training_fields
from depthgt.device import resolve_device
from depthgt.enhance.settings import TrainSettings
from depthgt.errors import ConfigError
from depthgt.shapes import check_shape
from depthgt.testhook import hold

__all__ = [
    "TrainOutputs",
    "build_model",
    "build_loss",
    "learning_rate",
    "patch_dataset",
    "collate",
    "flip_batch",
    "train_epoch",
    "evaluate",
    "train",
    "load_model",
    "predict",
    "predict_depth",
    "memory_layout",
]

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- models


def _function(path: str) -> Callable:
    module, name = path.split(":")
    return getattr(importlib.import_module(module), name)


def _model(name: str) -> registry.Model:
    if name not in registry.MODELS:
        raise ConfigError(f"train.model: unknown model {name!r}; known: {sorted(registry.MODELS)}")
    return registry.MODELS[name]


def build_model(name: str, params: dict | None = None, where: str | None = None) -> nn.Module:
    """Model ``name`` of :data:`depthgt.registry.MODELS` built with keyword ``params``.

    Raises:
        ConfigError: a parameter the builder does not take, or a value it rejects
            (ValueError), named with ``where`` (default: the config key
            ``enhance.models.NAME.model_params``; the settings layer is torch-free and
            cannot check these).
    """
    fn = _function(_model(name).build)
    params = dict(params or {})
    where = where or f"enhance.models.{name}.model_params"
    try:
        inspect.signature(fn).bind(**params)
    except TypeError as err:
        raise ConfigError(f"{where} {params}: {err}") from None
    try:
        return fn(**params)
    except ValueError as err:
        raise ConfigError(f"{where} {params}: {err}") from None


def build_loss(name: str, params: dict | None = None) -> Callable:
    """Loss of model ``name``: ``loss(outputs, batch) -> (total, terms)``.

    ``params`` are checked now, not at the first batch: against the loss's keyword
    parameters, and by its ``check_params`` when it has one (a loss taking ``**params``).

    Raises:
        ConfigError: a parameter the loss does not take or rejects.
    """
    fn = _function(_model(name).loss)
    params = dict(params or {})
    try:
        inspect.signature(fn).bind(None, None, **params)
        check = getattr(fn, "check_params", None)
        if check is not None:
            check(**params)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"enhance.models.{name}.loss_params {params}: {err}") from None
    return partial(fn, **params)


class TrainOutputs(NamedTuple):
    """The files a training run writes (every path given by the caller); ``resume``
    (optional) is the folder of the per-epoch resume state."""

    best: Path
    last: Path
    log: Path
    meta: Path
    resume: Path | None = None

    @classmethod
    def in_dir(cls, out_dir: str | Path, resume: bool = False) -> TrainOutputs:
        """``best.pt``, ``last.pt``, ``loss_log.csv`` and ``train.json`` in ``out_dir``
        (and the resume folder ``resume/`` there, when ``resume``)."""
        d = Path(out_dir)
        return cls(d / "best.pt", d / "last.pt", d / "loss_log.csv", d / "train.json", d / "resume" if resume else None)


# --------------------------------------------------------------------------- data


def patch_dataset(manifest: str | Path | pd.DataFrame) -> GTDataset:
    """The patch pairs listed in a manifest, as the trainer reads them: items are dicts of
    tensors ``input`` (1, h, w) raw depth m, ``gt`` (1, h, w) GT depth m, ``rgb`` (3, h, w)
    float in [0, 1], ``K`` (3, 3) intrinsics of the crop (the frame set's ``K`` shifted
    by the crop box) and, where the GT has one, ``sigma`` (1, h, w) its expected std in
    metres. Read through :class:`depthgt.data.GTDataset` (the one reader of
    patches), every frame set's arrays kept in memory after the first read (~11 bytes
    per pixel: ~360 MB for 2000 pairs of 128x128).

    Args:
        manifest: parquet path or DataFrame with columns ``frameset`` (the frame set's
            location, :mod:`depthgt.gt.store`, relative to the working directory) and
            ``patch``: the split manifests of the GT or of the RDE.
    """
    return GTDataset.from_manifest(manifest, kind="patches", transform=training_fields, cache=True)


def collate(items: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Stack a list of dataset items into a batch dict: the keys every item has (a GT
    without a ``sigma`` image mixed with one that has it gives batches without
    ``sigma``; a loss that needs it says so)."""
    keys = [k for k in items[0] if all(k in it for it in items[1:])]
    return {k: torch.stack([it[k] for it in items]) for k in keys}


def flip_batch(batch: dict[str, torch.Tensor], flip_h: torch.Tensor, flip_v: torch.Tensor) -> dict[str, torch.Tensor]:
    """Flip the images of the samples selected by ``flip_h`` / ``flip_v`` ((B,) bool).

    A flipped image is the image of the mirrored scene, so the intrinsics follow:
    cx -> W - 1 - cx (horizontal), cy -> H - 1 - cy (vertical).
    """
    out = dict(batch)
    H, W = batch["gt"].shape[-2:]
    for key, t in batch.items():
        if key == "K" or t.ndim != 4:
            continue
        t = torch.where(flip_h.view(-1, 1, 1, 1), t.flip(-1), t)
        out[key] = torch.where(flip_v.view(-1, 1, 1, 1), t.flip(-2), t)
    K = batch["K"].clone()
    K[:, 0, 2] = torch.where(flip_h, (W - 1) - K[:, 0, 2], K[:, 0, 2])
    K[:, 1, 2] = torch.where(flip_v, (H - 1) - K[:, 1, 2], K[:, 1, 2])
    out["K"] = K
    return out


def cut_input_holes(
    batch: dict[str, torch.Tensor], count: int, min_px: int, max_px: int, generator: torch.Generator
) -> dict[str, torch.Tensor]:
    """Cut ``count`` disc-shaped holes into each sample's ``input`` depth (set to 0).

    Centres uniform over the image, radii uniform in ``min_px`` .. ``max_px`` pixels, all
    drawn from ``generator`` in one call ((B, count, 3) uniforms); the GT and the other
    images are left as they are. Written by hand: kornia's random erasing cuts rectangles
    and draws from torch's global generator, which a resumed epoch could not replay.
    """
    inp = batch["input"]
    B, _, H, W = inp.shape
    u = torch.rand(B, count, 3, generator=generator)
    cy, cx = (u[..., 0] * H).view(B, count, 1, 1), (u[..., 1] * W).view(B, count, 1, 1)
    r = (min_px + u[..., 2] * (max_px - min_px)).view(B, count, 1, 1)
    yy = torch.arange(H, dtype=u.dtype).view(1, 1, H, 1)
    xx = torch.arange(W, dtype=u.dtype).view(1, 1, 1, W)
    inside = ((yy - cy) ** 2 + (xx - cx) ** 2 <= r**2).any(dim=1, keepdim=True)  # (B, 1, H, W)
    return {**batch, "input": inp.masked_fill(inside.to(inp.device), 0.0)}


def learning_rate(settings: TrainSettings, step: int, steps_per_epoch: int) -> float:
    """The learning rate of training step ``step`` (0-based, counted over all epochs).

    ``constant``: ``settings.lr``. ``cosine``: ``lr * (1 + cos(pi * step / total)) / 2``
    with ``total = epochs * steps_per_epoch``, i.e. ``lr`` at the first step and close to 0
    at the last (SGDR's annealing without restarts, Loshchilov & Hutter 2017). Computed
    from the step alone, so a resumed run takes the same rates as an uninterrupted one.
    Written out rather than ``torch.optim.lr_scheduler.CosineAnnealingLR``: that keeps its
    position as state of its own, which the resume would have to save and restore too.
    """
    if settings.lr_schedule == "constant":
        return settings.lr
    total = settings.epochs * steps_per_epoch
    return settings.lr * 0.5 * (1.0 + math.cos(math.pi * min(step, total) / total))


def _epoch_generator(seed: int, epoch: int) -> torch.Generator:
    return torch.Generator().manual_seed(int(seed) * 100_003 + int(epoch))


def _batches(n: int, batch_size: int, order: torch.Tensor | None):
    idx = order if order is not None else torch.arange(n)
    return [idx[i : i + batch_size].tolist() for i in range(0, n, batch_size)]


def _to(batch: dict, device: torch.device) -> dict:
    return {k: v.to(device) for k, v in batch.items()}


def memory_layout(device: torch.device) -> torch.memory_format:
    """Channels-last on CPU, oneDNN's fast layout for convolutions; the default layout
    elsewhere. LapDEN default preset, 2 cores: 0.6-0.9 s vs 1.9-2.2 s per step of 8
    128x128 pairs with a second job on the machine, but only ~13 vs ~15 s per epoch of
    474 pairs in the idle default build (the loss terms and batching do not gain)."""
    return torch.channels_last if device.type == "cpu" else torch.contiguous_format


def _net_input(batch: dict, device: torch.device) -> torch.Tensor:
    return batch["input"].contiguous(memory_format=memory_layout(device))


# --------------------------------------------------------------------------- steps


def train_epoch(
    model: nn.Module,
    loss_fn: Callable,
    optimizer: torch.optim.Optimizer,
    dataset: Dataset,
    settings: TrainSettings,
    epoch: int,
    device: torch.device,
) -> dict[str, float]:
    """One epoch of training; returns the mean loss terms (plus batches, seconds)."""
    from tqdm import tqdm

    model.train()
    g = _epoch_generator(settings.seed, epoch)
    order = torch.randperm(len(dataset), generator=g)
    batches = _batches(len(dataset), settings.batch_size, order)
    if settings.max_batches_per_epoch is not None:
        batches = batches[: settings.max_batches_per_epoch]
    sums: dict[str, float] = {}
    t0 = time.perf_counter()
    bar = tqdm(batches, desc=f"epoch {epoch}", disable=not settings.progress, leave=False)
    for i, idx in enumerate(bar):
        lr = learning_rate(settings, epoch * len(batches) + i, len(batches))
        for group in optimizer.param_groups:
            group["lr"] = lr
        batch = collate([dataset[i] for i in idx])
        if settings.flips:
            flips = torch.rand(len(idx), 2, generator=g) < 0.5
            batch = flip_batch(batch, flips[:, 0], flips[:, 1])
        if settings.input_holes:
            batch = cut_input_holes(
                batch, settings.input_holes, settings.input_hole_min_px, settings.input_hole_max_px, g
            )
        batch = _to(batch, device)
        optimizer.zero_grad(set_to_none=True)
        total, terms = loss_fn(model(_net_input(batch, device)), batch)
        if not torch.isfinite(total):
            raise FloatingPointError(f"epoch {epoch}: non-finite training loss {terms}")
        total.backward()
        optimizer.step()
        for k, v in terms.items():
            sums[k] = sums.get(k, 0.0) + v
        # the loss tensor, not terms["total"]: a loss that leaves that term out is named by
        # _log_row at the end of the epoch, not a KeyError here
        bar.set_postfix(loss=f"{float(total.detach()):.4f}")
    n = max(len(batches), 1)
    return {**{k: v / n for k, v in sums.items()}, "batches": len(batches), "seconds": time.perf_counter() - t0}


@torch.no_grad()
def evaluate(
    model: nn.Module, loss_fn: Callable, dataset: Dataset, batch_size: int, device: torch.device
) -> dict[str, float]:
    """Mean loss terms over a dataset (no flips, eval mode)."""
    model.eval()
    batches = _batches(len(dataset), batch_size, None)
    sums: dict[str, float] = {}
    t0 = time.perf_counter()
    for idx in batches:
        batch = _to(collate([dataset[i] for i in idx]), device)
        _, terms = loss_fn(model(_net_input(batch, device)), batch)
        for k, v in terms.items():
            sums[k] = sums.get(k, 0.0) + v * len(idx)
    n = max(len(dataset), 1)
    return {**{k: v / n for k, v in sums.items()}, "batches": len(batches), "seconds": time.perf_counter() - t0}


def _save_atomic(obj: dict, path: Path) -> None:
    write_atomic(path, lambda tmp: torch.save(obj, tmp))


def _read_log(path: Path, upto_epoch: int) -> list[dict]:
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        return [r for r in csv.DictReader(f) if int(r["epoch"]) <= upto_epoch]


def _copy_atomic(src: Path, dst: Path) -> None:
    write_atomic(dst, lambda tmp: shutil.copyfile(src, tmp))


def _write_log(path: Path, rows: list[dict], columns: tuple[str, ...]) -> None:
    def write(tmp: Path) -> None:
        with tmp.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
            w.writeheader()
            for r in rows:
                w.writerow({k: r.get(k, "") for k in columns})

    write_atomic(path, write)


def _log_row(epoch: int, split: str, terms: dict, model: str) -> dict:
    """One row of the loss log of ``model`` (:func:`depthgt.registry.log_columns`).

    Raises:
        ValueError: the loss reported a term the model's log has no column for (it would
            be dropped without a word), or not one it has.
    """
    columns = registry.log_columns(model)
    extra = sorted(set(terms) - set(columns))
    missing = sorted(set(columns[2:]) - set(terms))
    if extra or missing:
        raise ValueError(
            f"model {model!r}: its loss reported the terms {sorted(terms)}; the loss log's columns are "
            f"{list(columns[2:])} (depthgt.registry.MODELS[{model!r}].log_terms): "
            + "; ".join(f"{what} {names}" for what, names in (("not logged:", extra), ("missing:", missing)) if names)
        )
    row = {"epoch": epoch, "split": split}
    for k in columns[2:]:
        row[k] = f"{terms[k]:.6g}" if k != "batches" else int(terms[k])
    return row


def train(
    manifest_train: str | Path | pd.DataFrame,
    manifest_val: str | Path | pd.DataFrame | None,
    out: TrainOutputs,
    settings: TrainSettings = TrainSettings(),
    model: nn.Module | None = None,
    loss_fn: Callable | None = None,
) -> dict:
    """Train a depth-enhancement model on the patch manifests, resuming if possible.

    Args:
        manifest_train, manifest_val: parquet paths (or DataFrames) of the splits;
            ``manifest_val`` may be None or empty (then the last epoch is the best).
        out: the output files (:class:`TrainOutputs`; ``TrainOutputs.in_dir(d)`` for one folder).
        settings: :class:`TrainSettings`.
        model, loss_fn: override the model and loss built from ``settings`` (then the
            checkpoint stores ``settings.model``/``model_params`` for :func:`load_model`,
            which must rebuild the same architecture).

    Returns:
        dict with ``best`` and ``last`` checkpoint paths, ``best_epoch``,
        ``best_val`` (validation total), ``log`` (CSV path), ``epochs_run``.

    Long because the resume (checkpoint identity, loss-log rows) and the epoch loop
    share the model, the optimiser and the best-epoch state; each epoch's work is
    :func:`train_epoch` and :func:`evaluate`.
    """
    out = TrainOutputs(*(None if p is None else Path(p) for p in out))
    for p in out[:4]:
        p.parent.mkdir(parents=True, exist_ok=True)
    device = resolve_device(settings.device)
    train_set = patch_dataset(manifest_train)
    if len(train_set) == 0:
        raise ValueError(f"training manifest {manifest_train}: no patch pairs")
    val_set = patch_dataset(manifest_val) if manifest_val is not None else None
    if val_set is not None and len(val_set) == 0:
        val_set = None

    torch.manual_seed(settings.seed)
    if model is None:
        model = build_model(settings.model, settings.model_params)
    model = model.to(device).to(memory_format=memory_layout(device))
    if loss_fn is None:
        loss_fn = build_loss(settings.model, settings.loss_params)
    optimizer = torch.optim.Adam(model.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)

    # the resume state: in its own folder when given (the workflow's), else last/best
    if out.resume is not None:
        out.resume.mkdir(parents=True, exist_ok=True)
        last_path, best_path = out.resume / "last.pt", out.resume / "best.pt"
    else:
        last_path, best_path = out.last, out.best
    log_path = out.log
    start, best_val, best_epoch, rows = 0, float("inf"), -1, []
    if last_path.is_file():
        ckpt = torch.load(last_path, map_location=device, weights_only=False)
        if ckpt["identity"] != settings.identity():
            now = settings.identity()
            diff = sorted(k for k in now.keys() | ckpt["identity"].keys() if ckpt["identity"].get(k) != now.get(k))
            if out.resume is None:
                raise ConfigError(
                    f"{last_path}: checkpoint was trained with other settings ({diff}); "
                    f"remove {out.last} (and {out.best}) or restore the settings"
                )
            log.warning("%s: resume state of other settings (%s): training starts anew", last_path, diff)
            ckpt = None
        if ckpt is not None:
            model.load_state_dict(ckpt["model_state"])
            optimizer.load_state_dict(ckpt["optimizer_state"])
            start, best_val, best_epoch = ckpt["epoch"] + 1, ckpt["best_val"], ckpt["best_epoch"]
            # the loss log of the finished epochs travels in the checkpoint (older ones: the CSV)
            rows = ckpt["log_rows"] if "log_rows" in ckpt else _read_log(log_path, start - 1)
            log.info("resuming %s from epoch %d (epochs 0-%d done, best %d)", last_path, start, start - 1, best_epoch)

    n_params = sum(p.numel() for p in model.parameters() if p.requires_grad)
    for epoch in range(start, settings.epochs):
        tr = train_epoch(model, loss_fn, optimizer, train_set, settings, epoch, device)
        rows.append(_log_row(epoch, "train", tr, settings.model))
        if val_set is not None:
            va = evaluate(model, loss_fn, val_set, settings.batch_size, device)
            rows.append(_log_row(epoch, "val", va, settings.model))
            score = va["total"]
        else:
            score = tr["total"]
        log.info("epoch %d: train %.5f val %.5f", epoch, tr["total"], score)
        ckpt = {
            "epoch": epoch,
            "model": settings.model,
            "model_params": settings.model_params,
            "identity": settings.identity(),
            "model_state": model.state_dict(),
            "optimizer_state": optimizer.state_dict(),
            "best_val": best_val,
            "best_epoch": best_epoch,
            "log_rows": list(rows),
        }
        if score < best_val or val_set is None:
            best_val, best_epoch = score, epoch
            ckpt["best_val"], ckpt["best_epoch"] = best_val, best_epoch
            _save_atomic(ckpt, best_path)
        _write_log(log_path, rows, registry.log_columns(settings.model))
        _save_atomic(ckpt, last_path)
        hold(f"train:{last_path}:epoch={epoch}")  # a pause point for tests that kill training (depthgt.testhook)

    if out.resume is not None:
        if start >= settings.epochs:
            _write_log(
                log_path, rows, registry.log_columns(settings.model)
            )  # every epoch was done before: the outputs from the state
        _copy_atomic(best_path, out.best)
        _copy_atomic(last_path, out.last)

    result = {
        "best": str(out.best),
        "last": str(out.last),
        "best_epoch": best_epoch,
        "best_val": best_val,
        "log": str(log_path),
        "epochs_run": settings.epochs - start,
    }
    meta = {
        "settings": {**asdict(settings)},
        "parameters": n_params,
        "best_epoch": best_epoch,
        "best_val": best_val,
        "train_pairs": len(train_set),
        "val_pairs": len(val_set) if val_set is not None else 0,
        "versions": {"torch": torch.__version__, "numpy": np.__version__},
        "device": str(device),
    }
    out.meta.write_text(json.dumps(meta, indent=2, sort_keys=True, default=str) + "\n")
    return result


# --------------------------------------------------------------------------- inference


def load_model(checkpoint: str | Path, device: str | torch.device = "cpu") -> nn.Module:
    """Rebuild the model stored in a checkpoint written by :func:`train` (eval mode), in
    the memory layout of its device (:func:`memory_layout`: channels-last on CPU, the
    layout it was trained in and :func:`predict` feeds it; with the weights in the
    default layout the CPU convolutions take the slower plain path)."""
    path = Path(checkpoint)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint not found")
    ckpt = torch.load(path, map_location=device, weights_only=False)
    for key in ("model", "model_params", "model_state"):
        if key not in ckpt:
            raise ValueError(f"{path}: not a depthgt checkpoint (missing key {key!r})")
    model = build_model(ckpt["model"], ckpt["model_params"], where=f"{path}: model_params").to(device)
    model.load_state_dict(ckpt["model_state"])
    return model.to(memory_format=memory_layout(torch.device(device))).eval()


@torch.no_grad()
def predict(model: nn.Module, depth_m: torch.Tensor, chunk: int = 8) -> torch.Tensor:
    """Enhanced depth of full frames.

    Args:
        model: a model of :data:`depthgt.registry.MODELS` (any input size that is a multiple of its
            ``size_multiple`` attribute, default 4; other sizes are padded by
            replication and cropped back).
        depth_m: (B, 1, H, W) metres, 0 = invalid; on any device (the model's is used).
        chunk: frames per forward pass.

    Returns:
        (B, 1, H, W) metres on the input's device, negatives clamped to 0.
    """
    check_shape(depth_m, "B 1 H W", "predict: depth_m")
    model.eval()
    dev = next(model.parameters()).device
    H, W = depth_m.shape[-2:]
    m = int(getattr(model, "size_multiple", 4))
    ph, pw = (-H) % m, (-W) % m
    outs = []
    for i in range(0, depth_m.shape[0], chunk):
        x = depth_m[i : i + chunk].to(dev).float()
        if ph or pw:
            x = torch.nn.functional.pad(x, (0, pw, 0, ph), mode="replicate")
        y = model(x.contiguous(memory_format=memory_layout(dev)))
        y = y[-1] if isinstance(y, (list, tuple)) else y
        outs.append(y[..., :H, :W].clamp_min(0.0).contiguous().to(depth_m.device))
    return torch.cat(outs)


def predict_depth(model: nn.Module, depth_m: np.ndarray) -> np.ndarray:
    """:func:`predict` for one (H, W) float32 depth image in metres -> (H, W) float32."""
    d = np.asarray(depth_m, dtype=np.float32)
    check_shape(d, "H W", "predict_depth: depth_m")
    return predict(model, torch.from_numpy(d)[None, None])[0, 0].numpy()
