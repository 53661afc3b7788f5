"""The built GT dataset as plain files other tools read (``depthgt export``).

Layout under the destination folder::

    card.json, card.md          the dataset card, copied from results/dataset/
    export.json                 format, kind, splits, units of this export
    {kind}/{split}/{dataset}/{scene}/{modality}/{stem}.{png|exr}
    SHA256SUMS                  every file above (``sha256sum -c SHA256SUMS``; ``depthgt verify``)
    index.parquet, index.csv    one row per sample: split, dataset, scene, target, patch and
                                the path of each modality (relative to the folder; truth "" when none)

``modality`` is ``rgb`` (8-bit PNG) and the depth-like images ``input``, ``gt``,
``sigma`` (the GT's expected standard deviation) and ``truth`` (synthetic sources
only); ``stem`` is ``{target:06d}`` for a frame, ``{target:06d}_{patch:02d}`` for a
patch pair. Depth-like images are

* ``png16``: single-channel 16-bit PNG as ScanNet and NYU-v2 store depth: depth in
  millimetres (:data:`DEPTH_UNITS_PER_M`), sigma in 0.1 mm (:data:`SIGMA_UNITS_PER_M`),
  0 = missing (also for depth beyond 65.535 m, which 16 bits cannot hold);
* ``exr``: float32 metres, one channel ``Y`` (what OpenCV reads as grey), 0 = missing.

The export resumes: every file is written to a temporary name and renamed, so a file
that exists is complete, and a sample whose files all exist is skipped. The index and
checksums are written last, so a folder with ``index.parquet`` is a finished export.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from torch.utils.data import DataLoader, Subset
from tqdm import tqdm

from depthgt import io
from depthgt.atomic import write_atomic
from depthgt.data.dataset import KINDS, GTDataset
from depthgt.errors import DepthGTError
from depthgt.gt.card import CHECKSUMS, sha256_file
from depthgt.gt.settings import SPLITS

__all__ = [
    "FORMATS",
    "DEPTH_UNITS_PER_M",
    "SIGMA_UNITS_PER_M",
    "CARD_FILES",
    "INDEX_COLUMNS",
    "export_dataset",
    "encode_png16",
    "read_depth",
]

FORMATS = {"png16": ".png", "exr": ".exr"}
DEPTH_UNITS_PER_M = io.PNG16_DEPTH_UNITS_PER_M  # millimetres, ScanNet's and NYU-v2's depth PNG unit
SIGMA_UNITS_PER_M = io.PNG16_SIGMA_UNITS_PER_M  # 0.1 mm: the GT's sigma is mostly a few millimetres
DEPTH_MODALITIES = ("input", "gt", "sigma", "truth")
CARD_FILES = ("card.json", "card.md")
INDEX_COLUMNS = ["split", "dataset", "scene", "target", "patch", "rgb", *DEPTH_MODALITIES]
encode_png16 = io.encode_png16


def _units(modality: str) -> int:
    return SIGMA_UNITS_PER_M if modality == "sigma" else DEPTH_UNITS_PER_M


def read_depth(path: str | Path, modality: str = "gt") -> np.ndarray:
    """Read one exported depth-like image back to (H, W) float32 metres (0 = missing)."""
    path = Path(path)
    if path.suffix == ".exr":
        return io.read_exr(path)["Y"]
    return io.read_depth_png(path, _units(modality))


def _stem(ids: dict[str, Any], kind: str) -> str:
    return f"{ids['target']:06d}" if kind == "frames" else f"{ids['target']:06d}_{ids['patch']:02d}"


def _sample_files(ids: dict[str, Any], kind: str, fmt: str, has_truth: bool) -> dict[str, str]:
    """modality -> path (relative to the export folder) of one sample's files."""
    base = Path(kind) / ids["split"] / ids["dataset"] / ids["scene"]
    stem = _stem(ids, kind)
    files = {"rgb": str(base / "rgb" / f"{stem}.png")}
    for m in DEPTH_MODALITIES:
        if m != "truth" or has_truth:
            files[m] = str(base / m / f"{stem}{FORMATS[fmt]}")
    return files


def _write_sample(dest: Path, sample: dict[str, Any], files: dict[str, str], fmt: str) -> None:
    for m in DEPTH_MODALITIES:
        if m not in files:
            continue
        if m not in sample:
            raise DepthGTError(
                f"{sample['dataset']}/{sample['scene']}/{_stem(sample, 'frames')}: no {m} in the shard, "
                "but its frame set records one"
            )
        depth = sample[m][0].numpy()
        path = dest / files[m]
        if fmt == "png16":
            write_atomic(path, Path.write_bytes, encode_png16(depth, _units(m), str(path)))
        else:
            write_atomic(path, io.write_exr, {"Y": np.ascontiguousarray(depth, dtype=np.float32)})
    rgb = np.clip(np.round(sample["rgb"].permute(1, 2, 0).numpy() * 255.0), 0, 255).astype(np.uint8)
    write_atomic(dest / files["rgb"], io.write_rgb_png, rgb)


def _check_settings(dest: Path, settings: dict[str, Any]) -> None:
    """export.json of this export; an unfinished export of other settings is not mixed in."""
    path = dest / "export.json"
    if path.is_file():
        try:
            before = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise DepthGTError(
                f"{path}: not readable as an export's settings ({type(err).__name__}: {err}); "
                "export into an empty folder or remove it"
            ) from None
        if before != settings:
            diff = sorted(k for k in set(before) | set(settings) if before.get(k) != settings.get(k))
            raise DepthGTError(
                f"{path}: {dest} holds an export with other settings ({diff}); export into an empty folder or remove it"
            )
    else:
        # files without export.json are no unfinished export of ours (it is written first):
        # resuming would keep foreign files at the samples' paths and checksum them
        # hidden files (.DS_Store, lost+found's kin, a temporary export.json of a killed run) do not count
        present = sorted(p.name for p in dest.iterdir() if not p.name.startswith(".")) if dest.is_dir() else []
        if present:
            raise DepthGTError(
                f"export: {dest} holds files but no export.json ({', '.join(present[:5])}"
                f"{', ...' if len(present) > 5 else ''}): export into an empty or new folder"
            )
        write_atomic(path, io.write_json, settings)


def export_dataset(
    results: str | Path,
    dest: str | Path,
    fmt: str = "png16",
    splits: Sequence[str] = SPLITS,
    kind: str = "patches",
    workers: int = 0,
    progress: bool = True,
) -> pd.DataFrame:
    """Export the samples of ``splits`` (:class:`~depthgt.data.GTDataset` of ``kind``) to
    plain files in ``dest`` (layout in the module docstring), resuming an unfinished
    export there.

    Args:
        results: the results folder of a build (with ``dataset/`` and ``framesets/``).
        fmt: ``png16`` or ``exr``.
        workers: DataLoader workers reading the shards (0: this process).

    Returns:
        The index (one row per sample, :data:`INDEX_COLUMNS`).

    Raises:
        DepthGTError: an unknown format, kind or split; no dataset card (a build before
            cards: run the ``dataset`` rule again); ``dest`` holding an export with
            other settings; a shard missing or corrupt (named).

    Long for its docstring; its code is 76 lines: the checks, the resume and one pass
    over the samples that writes, lists and checksums them.
    """
    results, dest = Path(results), Path(dest)
    if fmt not in FORMATS:
        raise DepthGTError(f"export: format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if kind not in KINDS:
        raise DepthGTError(f"export: kind must be one of {', '.join(KINDS)}, got {kind!r}")
    bad = [s for s in splits if s not in SPLITS]
    if bad or not splits:
        raise DepthGTError(f"export: splits must be among {', '.join(SPLITS)}, got {list(splits)}")
    splits = list(dict.fromkeys(splits))  # a split named twice is exported once
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise DepthGTError(f"export: workers must be an integer >= 0, got {workers!r}")
    if not (results / "dataset").is_dir():
        raise DepthGTError(
            f"export: {results.parent} holds no built dataset ({results / 'dataset'} is missing): "
            "pass the build's working directory (-d), or build it first (`depthgt build dataset`)"
        )
    cards = [results / "dataset" / name for name in CARD_FILES]
    for card in cards:
        if not card.is_file():
            raise DepthGTError(
                f"export: no dataset card {card} (built before cards existed?): run `depthgt build dataset` again"
            )
    dest.mkdir(parents=True, exist_ok=True)
    settings = {
        "format": fmt,
        "kind": kind,
        "splits": list(splits),
        "units_per_m": (
            {
                "input": DEPTH_UNITS_PER_M,
                "gt": DEPTH_UNITS_PER_M,
                "truth": DEPTH_UNITS_PER_M,
                "sigma": SIGMA_UNITS_PER_M,
            }
            if fmt == "png16"
            else {m: 1 for m in DEPTH_MODALITIES}
        ),
    }
    _check_settings(dest, settings)
    for card in cards:
        write_atomic(dest / card.name, lambda tmp, src=card: shutil.copyfile(src, tmp))

    framesets = pd.read_parquet(results / "dataset" / "framesets.parquet")
    has_truth = dict(zip(framesets["frameset"].astype(str), framesets["has_truth"].astype(bool)))
    rows, todo = [], []
    for split in splits:
        ds = GTDataset(results, split, kind)
        pending = []
        for i, loc in enumerate(ds.table["frameset"].astype(str)):
            ids = ds.ids(i)
            files = _sample_files(ids, kind, fmt, has_truth.get(loc, False))
            rows.append({**ids, **{m: files.get(m, "") for m in ("rgb", *DEPTH_MODALITIES)}})
            if not all((dest / f).is_file() for f in files.values()):
                pending.append((i, files))
        todo.append((ds, pending))
    with tqdm(
        total=sum(len(p) for _, p in todo), desc=f"export {kind} ({fmt})", unit="sample", disable=not progress
    ) as bar:
        for ds, pending in todo:
            if not pending:
                continue
            loader = DataLoader(Subset(ds, [i for i, _ in pending]), batch_size=None, num_workers=workers)
            for (_, files), sample in zip(pending, loader):
                _write_sample(dest, sample, files, fmt)
                bar.update()
    for tmp in (dest / kind).rglob(".*.tmp*"):  # left by a killed export; every file is complete now
        tmp.unlink()

    index = pd.DataFrame(rows, columns=INDEX_COLUMNS)
    listed = [*CARD_FILES, "export.json", *(f for m in ("rgb", *DEPTH_MODALITIES) for f in index[m] if f)]
    sums = "".join(f"{sha256_file(dest / f)}  {f}\n" for f in listed)
    write_atomic(dest / CHECKSUMS, Path.write_text, sums)
    write_atomic(dest / "index.csv", lambda tmp: index.to_csv(tmp, index=False))
    write_atomic(dest / "index.parquet", lambda tmp: index.to_parquet(tmp, index=False))
    return index
