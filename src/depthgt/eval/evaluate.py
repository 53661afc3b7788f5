"""Full-frame evaluation of enhancement methods on frame sets (paper Tables 1-3).

A frame set's location gives the images of one test frame
(:func:`depthgt.gt.store.read_frame_images`): ``input`` (input.exr Z, the resized
raw depth), ``gt`` (gt.exr Z, depthgt's GT), ``truth`` (input.exr T, the clean depth
of synthetic sources, when present) and ``rgb`` (rgb.webp).

A method is a mapping ``{"baseline": name, "params": {...}}`` (a baseline of
:mod:`depthgt.enhance.baselines`, e.g. ``{"baseline": "learned", "params":
{"checkpoint": ".../best.pt"}}``) or ``{"image": "gt"}`` (an image of the frame set
taken as the prediction, e.g. the GT itself against the input for Table 1).
:func:`evaluate_frames` runs every method on every frame and returns a tidy long
table; it is what the workflow runs (one method per job).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from depthgt import registry
from depthgt.enhance.baselines import run_baseline
from depthgt.eval.metrics import depth_metrics, unit_of
from depthgt.gt import store
from depthgt.gt.references import REFERENCES
from depthgt.status import Status

__all__ = ["run_method", "method_spec", "evaluate_frames", "score_rows", "EVAL_COLUMNS"]

log = logging.getLogger(__name__)

EVAL_COLUMNS = ["dataset", "scene", "target", "method", "reference", "metric", "unit", "value"]


def run_method(method: Mapping, frame: store.FrameImages) -> np.ndarray:
    """Prediction (H, W) float32 metres of ``method`` on ``frame`` (see module docstring)."""
    if "image" in method:
        img = frame.depth(method["image"])
        if img is None:
            raise ValueError(f"method {dict(method)}: the frame has no image {method['image']!r}")
        return np.asarray(img, dtype=np.float32)
    if "baseline" not in method:
        raise ValueError(f"method {dict(method)} needs a 'baseline' or an 'image' key")
    return run_baseline(method["baseline"], frame.input_m, frame.rgb, **dict(method.get("params", {})))


def score_rows(
    dataset: str,
    scene: str,
    target: int,
    method: str,
    pred_m: np.ndarray,
    input_m: np.ndarray,
    references: Mapping[str, np.ndarray],
) -> list[dict]:
    """Long-table rows (:data:`EVAL_COLUMNS`) of one prediction (H, W) float32 metres
    against each reference image (name -> (H, W) metres) with the raw input ``input_m``
    as the denoising mask (:func:`depthgt.eval.metrics.depth_metrics`): the scoring of
    the workflow's evaluation and of ``depthgt evaluate`` alike."""
    rows = []
    for reference, ref_m in references.items():
        for metric, value in depth_metrics(pred_m, ref_m, input_m).items():
            rows.append(
                {
                    "dataset": dataset,
                    "scene": scene,
                    "target": int(target),
                    "method": method,
                    "reference": reference,
                    "metric": metric,
                    "unit": unit_of(metric),
                    "value": float(value),
                }
            )
    return rows


def method_spec(name: str, checkpoint: str | Path | None = None, device: str | None = None) -> dict:
    """The method mapping of a registry method (:mod:`depthgt.registry`): its baseline,
    and for a learned one the trained ``checkpoint`` and the ``device`` to run it on."""
    if name not in registry.METHODS:
        raise ValueError(f"unknown method {name!r}; known: {', '.join(registry.METHODS)}")
    m = registry.METHODS[name]
    if m.kind != "learned":
        return {"baseline": m.baseline}
    if checkpoint is None:
        raise ValueError(f"method {name!r} is learned: it needs the checkpoint of its trained model")
    params = {"checkpoint": str(checkpoint)}
    if device is not None:
        params["device"] = device
    return {"baseline": m.baseline, "params": params}


def evaluate_frames(
    frames: pd.DataFrame | str | Path,
    methods: Mapping[str, Mapping],
    references: Sequence[str] = ("gt", "truth"),
    split: str | None = "test",
    pred_dirs: Mapping[str, str | Path] | None = None,
    reference_files: Mapping[tuple[str, str, int], Mapping[str, tuple[str, str]]] | None = None,
) -> pd.DataFrame:
    """Run every method on every frame set and score it against each reference.

    The one evaluation of the project: the workflow's ``evaluate_method`` job calls it
    with one method.

    Args:
        frames: the frame-level table (or its parquet path) with ``dataset``,
            ``scene``, ``target``, ``frameset`` and optionally ``split`` and
            ``status`` (only "ok" rows with a frame-set folder are used when present).
        methods: name -> method mapping (see module docstring; :func:`method_spec`).
        references: images scored against, among ``gt``, ``truth`` and ``input`` of the
            frame set and the references of real frames built apart
            (:data:`depthgt.gt.references.REFERENCES`: ``neighbours``, ``tsdf``, found
            through ``reference_files``); a frame without one (e.g. a real frame and
            ``truth``) is not scored against it.
        split: keep only this split (None: all rows).
        pred_dirs: method name -> folder; each prediction is saved as
            ``{pred_dirs[name]}/{dataset}/{scene}/{target:06d}.npy`` (float32 m) for the
            figures. Methods not in it are not saved.
        reference_files: (dataset, scene, target) -> {reference: (npz file, key)}
            (:func:`depthgt.gt.references.read_reference_table`).

    Returns:
        Long table with columns :data:`EVAL_COLUMNS` (metrics of
        :func:`depthgt.eval.metrics.depth_metrics`, units of
        :data:`depthgt.metric_vocabulary.METRIC_UNITS`), rows by frame, method, reference.

    Long for its docstring (every argument); its code is 67 lines.
    """
    table = frames if isinstance(frames, pd.DataFrame) else pd.read_parquet(frames)
    missing = {"dataset", "scene", "target", "frameset"} - set(table.columns)
    if missing:
        raise ValueError(
            f"frame table {frames if not isinstance(frames, pd.DataFrame) else ''}: missing columns {sorted(missing)}"
        )
    known = (*store.FRAME_DEPTHS, *REFERENCES)
    bad = [r for r in references if r not in known]
    if bad or not references:
        raise ValueError(f"reference must be among {', '.join(known)}, got {list(references)}")
    if split is not None and "split" in table.columns:
        table = table[table["split"] == split]
    if "status" in table.columns:
        table = table[table["status"] == Status.OK]
    table = table[table["frameset"] != ""]
    pred_dirs = dict(pred_dirs or {})
    reference_files = reference_files or {}
    npz: dict[str, Any] = {}  # open reference files (numpy reads each member when asked)
    rows = []
    seconds = {name: 0.0 for name in methods}
    for rec in table.itertuples():
        frame = store.read_frame_images(rec.frameset)
        ref_images = {r: frame.depth(r) for r in references if r in store.FRAME_DEPTHS and frame.depth(r) is not None}
        for r, (file, key) in reference_files.get((str(rec.dataset), str(rec.scene), int(rec.target)), {}).items():
            if r in references:
                if file not in npz:
                    npz[file] = np.load(file)
                if key not in npz[file].files:
                    raise ValueError(f"{file}: no reference image {key!r} (reference {r} of {rec.frameset})")
                ref_images[r] = np.asarray(npz[file][key], dtype=np.float32)
                if ref_images[r].shape != frame.input_m.shape:
                    raise ValueError(
                        f"{file}[{key}]: shape {ref_images[r].shape}, the frame's input has {frame.input_m.shape}"
                    )
        refs = [r for r in references if r in ref_images]
        if not refs:
            log.info("%s: none of the references %s, skipped", rec.frameset, list(references))
            continue
        for name, method in methods.items():
            t0 = time.perf_counter()
            pred = run_method(method, frame)
            seconds[name] += time.perf_counter() - t0
            if name in pred_dirs:
                out = Path(pred_dirs[name]) / str(rec.dataset) / str(rec.scene) / f"{int(rec.target):06d}.npy"
                out.parent.mkdir(parents=True, exist_ok=True)
                np.save(out, pred.astype(np.float32))
            rows += score_rows(
                rec.dataset, rec.scene, int(rec.target), name, pred, frame.input_m, {r: ref_images[r] for r in refs}
            )
    for name, s in seconds.items():
        log.info(
            "method %s: %.2f s on %d frame sets (wall clock, not in the table: results stay deterministic)",
            name,
            s,
            len(table),
        )
    for f in npz.values():
        f.close()
    return pd.DataFrame(rows, columns=EVAL_COLUMNS)
