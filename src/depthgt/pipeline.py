"""The per-frame-set job: load -> resize -> align -> render GT -> patches -> write.

``process_frameset`` reads like the algorithm; each step is a small function on
tensors that the tests call on their own. Outputs (DESIGN.md layout) are written
atomically (temporary name, then rename) so that a killed job leaves no half file.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from depthgt import geometry, io
from depthgt.errors import ConfigError, FrameError
from depthgt.framesets import FrameSetSettings, stable_seed
from depthgt.patches import PatchSettings, make_patches
from depthgt.quality import error_stats
from depthgt.render import GTRender, GTRenderSettings, cloud_in_target, render_gt
from depthgt.sources.base import Scene, check_frame

log = logging.getLogger(__name__)

OUTPUT_FILES = ("gt.exr", "input.exr", "rgb.png", "poses.json", "patches.npz", "frameset.json")


def resolve_device(name: str = "auto") -> torch.device:
    """``auto`` -> CUDA when available, else CPU; ``cuda`` without a GPU is an error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("config device: cuda was asked for but no CUDA device is available")
    return torch.device(name)


@dataclass(frozen=True)
class JobSettings:
    """Everything a frame-set job needs besides the scene (built from the config)."""

    size_hw: tuple[int, int] = (256, 256)
    frameset: FrameSetSettings = field(default_factory=FrameSetSettings)
    patches: PatchSettings = field(default_factory=PatchSettings)
    render: GTRenderSettings = field(default_factory=GTRenderSettings)
    registration_method: str = "given"
    registration: dict = field(default_factory=dict)
    registration_on_failure: str = "drop_neighbours"
    seed: int = 0
    device: str = "auto"

    def __post_init__(self):
        if self.registration_on_failure not in ON_FAILURE:
            raise ConfigError(f"registration.on_failure must be one of {', '.join(ON_FAILURE)}, "
                              f"got {self.registration_on_failure!r}")


# What a frame set with failed neighbours becomes (registration.on_failure): rendered
# from the neighbours that did register, or excluded from the dataset. A set where
# fewer than min_ok_fraction of the neighbours registered is excluded either way.
ON_FAILURE = ("drop_neighbours", "exclude")


@dataclass
class FrameSetData:
    """The members of one frame set at the working resolution (target first).

    Attributes:
        rgb: (F, 3, H, W) float in [0, 1].
        depth_m: (F, 1, H, W) raw depth, 0 = invalid.
        K: (3, 3) float64 intrinsics at (H, W).
        T_world_cam: (F, 4, 4) float64 camera-to-world poses, or None.
        truth_m: (F, 1, H, W) clean depth when the source knows it, else None.
        frame_ids: the source's ids of the members.
        src_hw: (H, W) of the source's depth images before resizing.
    """

    rgb: torch.Tensor
    depth_m: torch.Tensor
    K: torch.Tensor
    T_world_cam: torch.Tensor | None
    truth_m: torch.Tensor | None
    frame_ids: list[str]
    src_hw: tuple[int, int] | None = None


def load_frameset(scene: Scene, members: list[int], size_hw: tuple[int, int], need_poses: bool, device: torch.device) -> FrameSetData:
    """Read the member frames and bring them to ``size_hw``.

    Raises:
        FrameError: a member frame is unusable (it was valid when the index was built
            only if the data changed since; the job records it and fails loudly).
    """
    frames = []
    for m in members:
        where = f"{scene.name} frame {scene.frame_id(m)}"
        frames.append(check_frame(scene.read(m), scene.image_size, where, need_pose=need_poses))
    depth = torch.from_numpy(np.stack([f.depth_m for f in frames]))[:, None].to(device)
    rgb = torch.from_numpy(np.stack([f.rgb for f in frames])).permute(0, 3, 1, 2).to(device).float() / 255.0
    truth = None
    if all(f.clean_depth_m is not None for f in frames):
        truth = geometry.resize_depth_nearest(torch.from_numpy(np.stack([f.clean_depth_m for f in frames]))[:, None].to(device), size_hw)
    poses = None
    if all(f.T_world_cam is not None for f in frames) and all(np.isfinite(f.T_world_cam).all() for f in frames):
        poses = torch.from_numpy(np.stack([f.T_world_cam for f in frames])).to(device)
    K = torch.as_tensor(geometry.scale_intrinsics(np.asarray(scene.intrinsics, dtype=np.float64), scene.image_size, size_hw), device=device)
    return FrameSetData(
        rgb=geometry.resize_rgb(rgb, size_hw),
        depth_m=geometry.resize_depth_nearest(depth, size_hw),
        K=K,
        T_world_cam=poses,
        truth_m=truth,
        frame_ids=[scene.frame_id(m) for m in members],
        src_hw=tuple(scene.image_size),
    )


def load_frameset_cached(cache_dir: str | Path, scene: Scene, members: list[int], size_hw: tuple[int, int],
                         device: torch.device) -> FrameSetData:
    """Same as :func:`load_frameset`, from the scene's frame cache (see depthgt.cache)."""
    from depthgt.cache import read_cached

    arr = read_cached(cache_dir, members)
    if arr["depth"].shape[1:] != tuple(size_hw):
        raise ValueError(f"frame cache {cache_dir} holds {arr['depth'].shape[1:]} frames, the job works at {tuple(size_hw)}")
    poses = arr["poses"]
    K = torch.as_tensor(geometry.scale_intrinsics(np.asarray(scene.intrinsics, dtype=np.float64), scene.image_size, size_hw), device=device)
    return FrameSetData(
        rgb=torch.from_numpy(arr["rgb"]).permute(0, 3, 1, 2).to(device).float() / 255.0,
        depth_m=torch.from_numpy(arr["depth"])[:, None].to(device),
        K=K,
        T_world_cam=torch.from_numpy(poses).to(device) if np.isfinite(poses).all() else None,
        truth_m=torch.from_numpy(arr["truth"])[:, None].to(device) if "truth" in arr else None,
        frame_ids=[scene.frame_id(m) for m in members],
        src_hw=tuple(scene.image_size),
    )


def poses_from_source(data: FrameSetData) -> torch.Tensor:
    """``T_j_to_t`` (F-1, 4, 4) float64 of each neighbour from the source's poses."""
    if data.T_world_cam is None:
        raise FrameError("registration.method 'given' needs poses, but this source provides none or some are non-finite",
                         "missing_pose")
    T = data.T_world_cam
    return torch.linalg.inv(T[:1]) @ T[1:]


def fuse(data: FrameSetData, T_j_to_t: torch.Tensor, settings: GTRenderSettings, depth_m: torch.Tensor | None = None,
         members: slice | list[int] = slice(None)) -> GTRender:
    """Render the aligned members into the target view (paper eq. 5).

    Args:
        T_j_to_t: (F-1, 4, 4) poses of the neighbours (the target's is the identity).
        depth_m: (F, 1, H, W) depth to fuse (default: the raw depth of the members).
        members: which members to use (``slice(1, None)`` leaves the target out; a
            list of positions, 0 = the target, keeps those).
    """
    depth = (data.depth_m if depth_m is None else depth_m)[members]
    eye = torch.eye(4, dtype=T_j_to_t.dtype, device=T_j_to_t.device)[None]
    T = torch.cat([eye, T_j_to_t], dim=0)[members]
    K = data.K[None].expand(depth.shape[0], 3, 3)
    cloud = cloud_in_target(depth, K, T, src_hw=data.src_hw, noise_sigma_1m=settings.noise_sigma_1m,
                            noise_sigma_abs_m=settings.noise_sigma_abs_m)
    h, w = data.depth_m.shape[-2:]
    chosen = list(range(len(data.depth_m)))[members] if isinstance(members, slice) else list(members)
    with_target = bool(chosen) and chosen[0] == 0  # the target's own depth is fused, as frame 0 of the cloud
    return render_gt(cloud.points, data.K[None].to(depth.dtype), (h, w), cloud.valid, settings, normals_cam=cloud.normals,
                     sigma_m=cloud.sigma_m, frame=cloud.frame, src_hw=data.src_hw, target_frame=0 if with_target else None)


def _atomic(path: Path, writer, *args) -> None:
    tmp = path.with_name(f".{path.name}.tmp{path.suffix}")
    writer(tmp, *args)
    os.replace(tmp, path)


def _save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    with open(path, "wb") as fh:
        np.savez_compressed(fh, **arrays)


def process_frameset(scene: Scene, dataset: str, target: int, members: list[int], split: str, out_dir: str | Path,
                     settings: JobSettings, encoder_state: dict | None = None, cache_dir: str | Path | None = None) -> dict[str, Any]:
    """Build every output of one frame set in ``out_dir`` and return frameset.json's content.

    Frames come from the scene's frame cache when ``cache_dir`` is given (the
    workflow's case), else they are read from ``scene`` and resized here.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    device = resolve_device(settings.device)
    timings: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[name] = round(now - clock, 4)
        clock = now

    method = settings.registration_method
    if cache_dir is not None:
        data = load_frameset_cached(cache_dir, scene, members, settings.size_hw, device)
    else:
        data = load_frameset(scene, members, settings.size_hw, need_poses=(method == "given"), device=device)
    lap("load_resize")

    registration_info: dict[str, Any] = {"method": method}
    status, reason = "ok", ""
    fused = list(range(len(members)))  # positions of the members rendered into the GT
    if method == "given":
        T_j_to_t = poses_from_source(data)
    elif method == "overfit":
        from depthgt.registration import make_settings, register_frameset

        offsets = [m - target for m in members]
        reg = {k: v for k, v in settings.registration.items() if k != "pretrain"}
        result = register_frameset(data.rgb, data.depth_m, data.K, offsets, make_settings(**reg),
                                   encoder_state=encoder_state, seed=stable_seed(settings.seed, dataset, scene.name, target))
        T_j_to_t = torch.as_tensor(result.T_j_to_t, dtype=torch.float64, device=device)
        registration_info.update(result.to_dict())
        status, reason = result.status, result.reason
        failed = [o for o, st in zip(offsets[1:], result.neighbour_status) if st != "ok"]
        if failed and status == "ok" and settings.registration_on_failure == "exclude":
            status, reason = "failed", f"neighbours_not_registered(offsets {','.join(f'{o:+d}' for o in failed)})"
        # a neighbour that did not register never enters the GT
        fused = [0] + [i + 1 for i, st in enumerate(result.neighbour_status) if st == "ok"]
        registration_info["fused_offsets"] = [offsets[i] for i in fused]
    else:
        raise ValueError(f"registration.method must be 'given' or 'overfit', got {method!r}")
    lap("align")

    gt = fuse(data, T_j_to_t, settings.render, members=fused if len(fused) < len(members) else slice(None))
    lap("render")

    depth_in = data.depth_m[0, 0].cpu().numpy().astype(np.float32)
    gt_depth = gt.depth[0, 0].detach().cpu().numpy().astype(np.float32)
    gt_sigma = gt.sigma[0, 0].detach().cpu().numpy().astype(np.float32)
    truth = data.truth_m[0, 0].cpu().numpy().astype(np.float32) if data.truth_m is not None else None
    rgb8 = (data.rgb[0].permute(1, 2, 0).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)

    stats: dict[str, Any] = {
        "input_missing": float((depth_in <= 0).mean()),
        "gt_missing": float((gt_depth <= 0).mean()),
        "gt_mean_points": float(gt.count[0, 0].float().mean()),
        "gt_median_sigma_m": float(np.median(gt_sigma[gt_depth > 0])) if (gt_depth > 0).any() else float("nan"),
        "neighbours_fused": len(fused) - 1,
    }
    # neighbours the renderer left out: too few of their samples agree with the target's depth
    offsets_fused = [members[i] - target for i in fused]
    share = gt.agreement[0].cpu().numpy()
    stats["render_agreement"] = {f"{o:+d}": round(float(a), 4) for o, a in zip(offsets_fused, share) if np.isfinite(a)}
    stats["render_left_out"] = [o for o, a in zip(offsets_fused, share) if np.isfinite(a) and a < settings.render.min_frame_agreement
                                and o != 0]
    if truth is None:
        # Leave-target-out consistency: fuse the neighbours alone and compare with the
        # target's raw valid depth -- the only accuracy check possible on real data
        # (where a clean truth exists, the GT is compared with it instead).
        if len(fused) > 1:
            lto = fuse(data, T_j_to_t, settings.render, members=fused[1:]).depth[0, 0].detach().cpu().numpy()
            stats["leave_target_out"] = error_stats(lto.astype(np.float32), depth_in)
    else:
        stats["gt_vs_truth"] = error_stats(gt_depth, truth)
        stats["input_vs_truth"] = error_stats(depth_in, truth)
        # the fair accuracy comparison: only where the sensor has data
        stats["gt_vs_truth_input_valid"] = error_stats(gt_depth, truth, mask=depth_in > 0)
    lap("quality")

    rng = np.random.default_rng(stable_seed(settings.seed, dataset, scene.name, target, "patches"))
    patches = make_patches(depth_in, gt_depth, rgb8, settings.patches, rng, truth_m=truth, gt_sigma_m=gt_sigma)
    stats["patches_drawn"] = int(len(patches["kept"]))
    stats["patches_kept"] = int(patches["kept"].sum())
    lap("patches")

    input_channels = {"Z": depth_in}
    if truth is not None:
        input_channels["T"] = truth
    _atomic(out / "gt.exr", io.write_exr, {"Z": gt_depth, "W": gt.weight_sum[0, 0].detach().cpu().numpy().astype(np.float32),
                                          "N": gt.count[0, 0].cpu().numpy().astype(np.float32), "S": gt_sigma})
    _atomic(out / "input.exr", io.write_exr, input_channels)
    _atomic(out / "rgb.png", io.write_rgb_png, rgb8)
    _atomic(out / "patches.npz", _save_npz, patches)
    T_np = T_j_to_t.detach().cpu().numpy().astype(np.float64)
    offsets = [m - target for m in members]
    poses_doc = {
        "T_j_to_t": {str(o): T_np[i].tolist() for i, o in enumerate(offsets[1:])},
        "registration": registration_info,
    }
    if data.T_world_cam is not None:
        ref = poses_from_source(data).cpu().numpy()
        poses_doc["T_j_to_t_reference"] = {str(o): ref[i].tolist() for i, o in enumerate(offsets[1:])}
    lap("write")
    poses_doc["timings_s"] = timings
    _atomic(out / "poses.json", io.write_json, poses_doc)
    doc = {
        "dataset": dataset,
        "scene": scene.name,
        "target": target,
        "members": members,
        "offsets": offsets,
        "frame_ids": data.frame_ids,
        "split": split,
        "status": status,
        "reason": reason,
        "K": data.K.cpu().numpy().tolist(),
        "size_hw": list(settings.size_hw),
        "statistics": stats,
        "settings": _settings_doc(settings),
    }
    _atomic(out / "frameset.json", io.write_json, doc)
    return doc


def _settings_doc(settings: JobSettings) -> dict:
    doc = asdict(settings)
    doc["size_hw"] = list(settings.size_hw)
    return doc
