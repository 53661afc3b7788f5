"""References on real data that no method was trained to imitate (Table 2).

Real recordings have no clean truth. The paper scores every method against depthgt's own
GT, which favours the method trained on it; beside it the evaluation scores against two
references built differently:

* ``neighbours``: the neighbours-only render of the target, the frame set's fused
  neighbours rendered into the target view *without* the target's own depth (the
  leave-target-out check of :func:`depthgt.gt.build.quality_statistics`, but at every
  pixel: the build renders that check at every ``render.leave_target_out_stride``-th
  row and column only and stores none of it). It re-uses the build's alignment exactly:
  the poses ``T_j_to_t`` of ``poses.json`` and the fused members (``fused_offsets`` of
  its registration record, else every member), the frames read at the working
  resolution as the batch job read them (:class:`depthgt.gt.cache.ResizedScene`), the
  renderer of :func:`depthgt.gt.render.fuse`. It holds none of the target's sensor noise;
  where no neighbour sees, it is empty (0 m).
* ``tsdf``: the global-reconstruction GT of the frame (a TSDF of the whole stream
  ray-cast at the target; the RDE baseline's GT, :mod:`depthgt.gt.rde`), copied from
  the RDE shard so that the evaluation reads one file per scene.

:func:`scene_references` builds both for the frame sets of one scene in the evaluated
split and writes them to one ``.npz`` (keys ``{target:06d}/{reference}``, float32
(H, W) metres) with a table of what it holds (:data:`REFERENCE_COLUMNS`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from depthgt.atomic import save_npz, write_atomic
from depthgt.gt import store
from depthgt.gt.render import fuse
from depthgt.gt.render.settings import RenderSettings
from depthgt.registration import load_frameset
from depthgt.sources.base import Scene
from depthgt.status import Status

__all__ = [
    "REFERENCES",
    "REFERENCE_COLUMNS",
    "fused_neighbours",
    "neighbours_only_render",
    "scene_references",
    "reference_key",
    "read_reference_table",
]

log = logging.getLogger(__name__)

REFERENCES = ("neighbours", "tsdf")
REFERENCE_COLUMNS = ["dataset", "scene", "target", "reference", "file", "key", "completeness"]


def reference_key(target: int, reference: str) -> str:
    """The key of a reference image in a scene's references ``.npz``."""
    return f"{int(target):06d}/{reference}"


def fused_neighbours(meta: Mapping[str, Any], poses: Mapping[str, Any], where: str) -> tuple[list[int], torch.Tensor]:
    """The positions (in ``meta["members"]``, 0 = the target) of the neighbours the
    build fused, and the (F-1, 4, 4) float64 ``T_j_to_t`` of every neighbour it stored.

    Args:
        meta: the frame set's ``frameset.json``; poses: its ``poses.json``.
        where: the frame set's location, named in errors.

    Raises:
        ValueError: a key is missing or the poses do not match the members.
    """
    for doc, name, keys in ((meta, "frameset.json", ("members", "offsets")), (poses, "poses.json", ("T_j_to_t",))):
        missing = [k for k in keys if k not in doc]
        if missing:
            raise ValueError(f"{where}/{name}: missing key(s) {missing}")
    offsets = [int(o) for o in meta["offsets"]]
    if len(offsets) != len(meta["members"]) or not offsets or offsets[0] != 0:
        raise ValueError(
            f"{where}/frameset.json: offsets {offsets} do not start with the target (0) or do not "
            f"match members {meta['members']}"
        )
    stored = poses["T_j_to_t"]
    absent = [o for o in offsets[1:] if str(o) not in stored]
    if absent:
        raise ValueError(f"{where}/poses.json: T_j_to_t has no pose for offset(s) {absent} (has {sorted(stored)})")
    T = torch.tensor(np.array([stored[str(o)] for o in offsets[1:]], dtype=np.float64))
    if T.shape != (len(offsets) - 1, 4, 4):
        raise ValueError(f"{where}/poses.json: T_j_to_t must hold 4x4 matrices, got shape {tuple(T.shape)}")
    fused = (poses.get("registration") or {}).get("fused_offsets", offsets)  # `given` fuses every member
    return [offsets.index(int(o)) for o in fused if int(o) != 0 and int(o) in offsets], T


def neighbours_only_render(
    scene: Scene,
    meta: Mapping[str, Any],
    poses: Mapping[str, Any],
    settings: RenderSettings,
    size_hw: tuple[int, int],
    where: str = "frame set",
    device: torch.device = torch.device("cpu"),
) -> np.ndarray:
    """The target's neighbours-only render (H, W) float32 metres, 0 where no neighbour
    sees: the build's fused neighbours with its stored poses (:func:`fused_neighbours`)
    rendered into the target view by :func:`depthgt.gt.render.fuse` without the target.

    Args:
        scene: the frame set's scene at the working resolution
            (:class:`depthgt.gt.cache.ResizedScene`, as the batch job read it).
        settings: the renderer's settings of the build.
        size_hw: the working resolution.
        where: the frame set's location, named in errors.
        device: where the render runs.
    """
    neighbours, T_j_to_t = fused_neighbours(meta, poses, where)
    h, w = int(size_hw[0]), int(size_hw[1])
    if not neighbours:
        return np.zeros((h, w), np.float32)
    members = [int(m) for m in meta["members"]]
    data = load_frameset(scene, members, (h, w), need_poses=False, device=device)
    out = fuse(data, T_j_to_t.to(data.depth_m.device), settings, members=neighbours)
    return out.gt.depth[0, 0].detach().cpu().numpy().astype(np.float32)


def scene_references(
    scene: Scene,
    framesets: pd.DataFrame,
    rde_framesets: pd.DataFrame | None,
    settings: RenderSettings,
    size_hw: tuple[int, int],
    split: str,
    out_npz: str | Path,
    device: torch.device = torch.device("cpu"),
) -> pd.DataFrame:
    """Build the references of one scene's ``split`` frame sets (status ok) and write
    them to ``out_npz`` (:func:`reference_key` -> (H, W) float32 metres).

    Args:
        framesets: the scene's frame-set table (``results/scenes/.../framesets.parquet``).
        rde_framesets: the scene's RDE table (``frameset``, ``rde``: location of the
            TSDF GT), or None: no ``tsdf`` reference.
        device: where the neighbours-only renders run.

    Returns:
        The table of what was written (:data:`REFERENCE_COLUMNS`; ``file`` is
        ``out_npz``, ``completeness`` the reference-valid share of the image).
    """
    need = {"dataset", "scene", "target", "split", "status", "frameset"}
    missing = need - set(framesets.columns)
    if missing:
        raise ValueError(f"frame-set table: missing columns {sorted(missing)}")
    ok = framesets[(framesets["split"] == split) & (framesets["status"] == Status.OK) & (framesets["frameset"] != "")]
    tsdf = {}
    if rde_framesets is not None and len(rde_framesets):
        if not {"frameset", "status", "rde"} <= set(rde_framesets.columns):
            raise ValueError(
                f"RDE frame-set table: needs columns frameset, status, rde (has {list(rde_framesets.columns)})"
            )
        good = rde_framesets[(rde_framesets["status"] == Status.OK) & (rde_framesets["rde"] != "")]
        tsdf = dict(zip(good["frameset"], good["rde"]))
    arrays: dict[str, np.ndarray] = {}
    rows = []
    for rec in ok.itertuples():
        meta = store.read_json(f"{rec.frameset}/frameset.json")
        poses = store.read_json(f"{rec.frameset}/poses.json")
        images = {
            "neighbours": neighbours_only_render(
                scene, meta, poses, settings, size_hw, where=rec.frameset, device=device
            )
        }
        if rec.frameset in tsdf:
            images["tsdf"] = store.read_exr_member(f"{tsdf[rec.frameset]}/gt.exr")["Z"].astype(np.float32)
        for name, img in images.items():
            if img.shape != tuple(size_hw):
                raise ValueError(f"{rec.frameset}: reference {name} has shape {img.shape}, expected {tuple(size_hw)}")
            key = reference_key(rec.target, name)
            arrays[key] = img
            rows.append(
                {
                    "dataset": rec.dataset,
                    "scene": rec.scene,
                    "target": int(rec.target),
                    "reference": name,
                    "file": str(out_npz),
                    "key": key,
                    "completeness": float((img > 0).mean()),
                }
            )
        log.info(
            "%s: references %s",
            rec.frameset,
            ", ".join(f"{n} {float((i > 0).mean()):.3f} valid" for n, i in images.items()),
        )
    Path(out_npz).parent.mkdir(parents=True, exist_ok=True)
    write_atomic(out_npz, save_npz, arrays)
    return pd.DataFrame(rows, columns=REFERENCE_COLUMNS)


def read_reference_table(paths: list[str | Path]) -> dict[tuple[str, str, int], dict[str, tuple[str, str]]]:
    """(dataset, scene, target) -> {reference: (npz file, key)} from the tables that
    :func:`scene_references` wrote (parquet paths)."""
    out: dict[tuple[str, str, int], dict[str, tuple[str, str]]] = {}
    for p in paths:
        t = pd.read_parquet(p)
        missing = set(REFERENCE_COLUMNS) - set(t.columns)
        if missing:
            raise ValueError(f"{p}: not a references table, missing columns {sorted(missing)}")
        for rec in t.itertuples():
            out.setdefault((str(rec.dataset), str(rec.scene), int(rec.target)), {})[str(rec.reference)] = (
                rec.file,
                rec.key,
            )
    return out
