"""A torch Dataset over the built GT dataset, read straight from the frame-set shards.

``GTDataset(results, split)`` lists the samples of a split manifest and reads each on
demand from its shard (:mod:`depthgt.gt.store`; nothing is extracted):

* ``kind="patches"``: one sample per kept patch pair of ``results/dataset/{split}.parquet``
  (cut from the frame set's images at the boxes of ``patches.npz``; 128x128 by default).
* ``kind="frames"``: one sample per built frame set of the split in
  ``results/dataset/framesets.parquet`` (the full frame at the working resolution,
  256x256 by default: ``gt.exr``, ``input.exr``, ``rgb.webp``).

A sample is a dict::

    input   (1, H, W) float32  raw sensor depth, metres, 0 = missing
    gt      (1, H, W) float32  GT depth, metres, 0 = missing
    sigma   (1, H, W) float32  the GT's expected standard deviation, metres, 0 where the GT is missing
                               (absent from manifests of GT without one: the RDE's)
    rgb     (3, H, W) float32  colour in [0, 1]
    truth   (1, H, W) float32  clean depth, metres; only where the source knows it (synthetic scenes)
    K       (3, 3)    float32  intrinsics of the sample's pixels (a patch's: shifted by its crop box)
    dataset, scene, split (str), target, patch (int; -1 for a frame)

Shards stay open per process (:class:`depthgt.gt.store.ShardReader`), so the dataset
works with ``DataLoader(num_workers > 0)`` under fork and spawn alike.
"""

from __future__ import annotations

import json
from collections import OrderedDict
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from torch.utils.data import Dataset

from depthgt.errors import DepthGTError
from depthgt.gt import store
from depthgt.gt.settings import SPLITS
from depthgt.status import Status

__all__ = ["KINDS", "GTDataset", "manifest_path", "training_fields"]

KINDS = ("patches", "frames")
ID_COLUMNS = ("dataset", "scene", "split", "target", "patch")
_PATCH_ARRAYS = ("input", "gt", "rgb", "boxes")  # every frame set's patches have these
_OPTIONAL_ARRAYS = ("gt_sigma", "truth")
_RECENT = 8  # frame sets kept decoded without `cache` (consecutive samples of one frame set)


def manifest_path(results: str | Path, split: str, kind: str = "patches") -> Path:
    """The manifest of a split: ``{split}.parquet`` (patches) or ``framesets.parquet``."""
    _check_choice("split", split, SPLITS)
    _check_choice("kind", kind, KINDS)
    return Path(results) / "dataset" / (f"{split}.parquet" if kind == "patches" else "framesets.parquet")


def _check_choice(what: str, value: str, allowed: Sequence[str]) -> None:
    if value not in allowed:
        raise DepthGTError(f"GTDataset: {what} must be one of {', '.join(allowed)}, got {value!r}")


def training_fields(sample: dict[str, Any]) -> dict[str, torch.Tensor]:
    """The tensors the enhancement trainer uses: ``input``, ``gt``, ``rgb``, ``K`` and,
    where the GT has one, ``sigma`` (a loss may weight by it) (a ``transform``; module
    level so that it pickles for spawned workers)."""
    return {k: sample[k] for k in ("input", "gt", "rgb", "K", "sigma") if k in sample}


class GTDataset(Dataset):
    """The samples of one split of a built GT dataset (see the module docstring).

    Args:
        results: the results folder (``<workdir>/results``); the manifests' locations
            are relative to its parent, the working directory.
        split: ``train``, ``val`` or ``test``.
        kind: ``"patches"`` (kept patch pairs) or ``"frames"`` (whole frame sets).
        datasets: keep only these sources (the config's source names); None: all.
        transform: ``sample -> sample``, applied last (picklable for spawned workers).
        cache: keep every frame set's decoded arrays after the first read (memory:
            ~19 bytes per patch pixel with truth and sigma); otherwise the last few.

    Raises:
        DepthGTError: naming the manifest when it is missing or lacks a column, a
            ``datasets`` name it does not hold, or (when a sample is read) the shard
            that is missing or corrupt.
    """

    def __init__(
        self,
        results: str | Path,
        split: str,
        kind: str = "patches",
        datasets: Sequence[str] | None = None,
        transform: Callable[[dict], dict] | None = None,
        *,
        cache: bool = False,
    ):
        path = manifest_path(results, split, kind)
        if not path.is_file():
            raise DepthGTError(f"GTDataset: no manifest {path} (build the dataset first: `depthgt build dataset`)")
        table = pd.read_parquet(path)
        if kind == "frames":
            _require_columns(table, ("split", "status", "frameset"), path)
            table = table[(table["split"] == split) & (table["status"] == Status.OK) & (table["frameset"] != "")]
        if datasets is not None:
            _require_columns(table, ("dataset",), path)
            unknown = sorted(set(datasets) - set(table["dataset"]))
            if unknown:
                raise DepthGTError(
                    f"GTDataset: {path} holds no {kind} of dataset(s) {unknown} in split {split!r}; "
                    f"it has {sorted(set(table['dataset']))}"
                )
            table = table[table["dataset"].isin(list(datasets))]
        self._setup(table.reset_index(drop=True), kind, Path(results).parent, transform, cache, str(path))

    @classmethod
    def from_manifest(
        cls,
        manifest: str | Path | pd.DataFrame,
        kind: str = "patches",
        root: str | Path | None = None,
        transform: Callable[[dict], dict] | None = None,
        *,
        cache: bool = False,
    ) -> GTDataset:
        """A dataset over any manifest table with columns ``frameset`` (a location,
        :mod:`depthgt.gt.store`) and, for patches, ``patch``: the split manifests, the
        RDE manifests, a user's selection of rows.

        Args:
            manifest: parquet path or DataFrame.
            root: the folder relative locations start from (None: the current one).
        """
        _check_choice("kind", kind, KINDS)
        name = "<DataFrame>" if isinstance(manifest, pd.DataFrame) else str(manifest)
        if isinstance(manifest, pd.DataFrame):
            table = manifest
        elif Path(manifest).is_file():
            table = pd.read_parquet(manifest)
        else:
            raise DepthGTError(f"GTDataset: no manifest {manifest}")
        self = cls.__new__(cls)
        self._setup(table.reset_index(drop=True), kind, None if root is None else Path(root), transform, cache, name)
        return self

    def _setup(self, table: pd.DataFrame, kind: str, root: Path | None, transform, cache: bool, name: str) -> None:
        _require_columns(table, ("frameset", "patch") if kind == "patches" else ("frameset",), name)
        self.kind, self.transform, self.cache, self.manifest = kind, transform, cache, name
        self.table = table
        locs = [str(p) for p in table["frameset"]]
        self.locations = [loc if root is None or Path(loc).is_absolute() else str(root / loc) for loc in locs]
        n = len(table)
        self.patch = table["patch"].astype(int).to_numpy() if kind == "patches" else np.full(n, -1)
        self._ids = {c: (table[c].tolist() if c in table.columns else [""] * n) for c in ("dataset", "scene", "split")}
        self._ids["target"] = table["target"].astype(int).tolist() if "target" in table.columns else [-1] * n
        self._reader = store.ShardReader()
        self._decoded: OrderedDict[str, dict[str, np.ndarray]] = OrderedDict()

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_decoded"] = OrderedDict()  # each process decodes its own
        return state

    def __len__(self) -> int:
        return len(self.locations)

    def ids(self, i: int) -> dict[str, Any]:
        """``dataset``, ``scene``, ``split``, ``target``, ``patch`` of sample ``i`` (nothing read)."""
        return {
            "dataset": self._ids["dataset"][i],
            "scene": self._ids["scene"][i],
            "split": self._ids["split"][i],
            "target": self._ids["target"][i],
            "patch": int(self.patch[i]),
        }

    def _arrays(self, loc: str) -> dict[str, np.ndarray]:
        arrays = self._decoded.get(loc)
        if arrays is not None:
            self._decoded.move_to_end(loc)
            return arrays
        arrays = self._read_patches(loc) if self.kind == "patches" else self._read_frame(loc)
        self._decoded[loc] = arrays
        if not self.cache:
            while len(self._decoded) > _RECENT:
                self._decoded.popitem(last=False)
        return arrays

    def _intrinsics(self, loc: str, doc: dict) -> np.ndarray:
        K = np.asarray(doc.get("K", []), dtype=np.float32)
        if K.shape != (3, 3):
            raise DepthGTError(f"{loc}/frameset.json: key 'K' must be 3x3, got shape {K.shape}")
        return K

    def _read_patches(self, loc: str) -> dict[str, np.ndarray]:
        # the crops are cut from the frame set's images on read (the shard stores the boxes)
        patches = store.read_patches_at(loc, self._reader, with_record=False)
        arrays = {k: patches[k] for k in (*_PATCH_ARRAYS, *_OPTIONAL_ARRAYS) if k in patches}
        doc = json.loads(self._reader.read(f"{loc}/frameset.json"))
        arrays["K"] = self._intrinsics(loc, doc)
        return arrays

    def _read_frame(self, loc: str) -> dict[str, np.ndarray]:
        rec = store.read_frameset_at(loc, self._reader)
        arrays = {
            "input": rec.input_m[None],
            "gt": rec.gt_m[None],
            "gt_sigma": rec.gt_sigma_m[None],
            "rgb": rec.rgb[None],
            "K": self._intrinsics(loc, rec.meta),
        }
        if rec.truth_m is not None:
            arrays["truth"] = rec.truth_m[None]
        return arrays

    def __getitem__(self, i: int) -> dict[str, Any]:
        if not -len(self) <= i < len(self):
            raise IndexError(f"GTDataset: index {i} out of range ({len(self)} samples of {self.manifest})")
        i = int(i) % len(self)
        loc = self.locations[i]
        a = self._arrays(loc)
        j = int(self.patch[i]) if self.kind == "patches" else 0
        if not 0 <= j < len(a["input"]):
            raise IndexError(f"{loc}/patches.npz: patch {j} out of range ({len(a['input'])} patches)")
        K = a["K"].copy()
        if self.kind == "patches":
            y0, x0 = int(a["boxes"][j][0]), int(a["boxes"][j][1])
            K[0, 2] -= x0
            K[1, 2] -= y0

        def depth(name: str) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(a[name][j], dtype=np.float32))[None]

        sample: dict[str, Any] = {"input": depth("input"), "gt": depth("gt")}
        if "gt_sigma" in a:
            sample["sigma"] = torch.where(sample["gt"] > 0, depth("gt_sigma"), 0.0)
        sample["rgb"] = torch.from_numpy(np.ascontiguousarray(a["rgb"][j])).permute(2, 0, 1).float() / 255.0
        if "truth" in a:
            sample["truth"] = depth("truth")
        sample["K"] = torch.from_numpy(K)
        sample.update(self.ids(i))
        return self.transform(sample) if self.transform is not None else sample


def _require_columns(table: pd.DataFrame, columns: Sequence[str], name: str) -> None:
    missing = sorted(set(columns) - set(table.columns))
    if missing:
        raise DepthGTError(f"manifest {name}: missing columns {missing}")
