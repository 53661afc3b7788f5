"""Benchmark of the frame-set registration (issue 3): accuracy, time, memory.

Measures, on the same 256x256 frame sets:

* ours at the presets ``paper`` (R&R overfit + chaining + joint SE(3) refinement),
  ``paper_only`` (the paper's pipeline alone) and ``fast``;
* Open3D's multi-scale colored ICP and RGB-D odometry (hybrid term), when ``open3d``
  is importable (``pip install depthgt[bench]``; needs Debian's libusb-1.0-0), started
  from the identity like ours;

against the true poses (synthetic rooms) or the reference poses (7-Scenes fixture):
rotation error (deg) and translation error (cm) per neighbour distance, time per frame
set and peak memory; on synthetic rooms also the GT's MAE against the clean depth with
estimated vs true poses (valid-only and missing-counted).

Usage (2 CPU threads by default)::

    python bench/bench_registration.py --data synthetic --targets 10 20 30 --methods paper fast o3d_icp o3d_odom
    python bench/bench_registration.py --data 7scenes --targets 10 20 30 40 50
    python bench/bench_registration.py --device cuda --methods paper

Writes a tidy CSV (dataset, target, offset, method, metric, unit, value) to ``--out``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import resource
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from depthgt.eval.metrics import pose_errors
from depthgt.geometry import resize_depth_nearest, resize_rgb, scale_intrinsics
from depthgt.registration.overfit import register_frameset
from depthgt.settings import registration_settings

# the shared fixture beside the checkout (main) or two levels up (a git worktree under wt/)
SEVEN = next(
    (p for p in (Path(__file__).resolve().parents[i] / "shared/data/7scenes-kitchen" for i in (2, 3)) if p.is_dir()),
    Path(__file__).resolve().parents[2] / "shared/data/7scenes-kitchen",
)
OFFSETS = [0, -6, -4, -2, 2, 4, 6]
SIZE = (256, 256)
COLUMNS = ["dataset", "target", "offset", "method", "metric", "unit", "value"]


def load_frameset(scene, target: int, offsets, device):
    """Frames of a set at 256x256: rgb (F,3,H,W), depth (F,1,H,W), K (3,3), true T_j_to_t, clean depth."""
    rgbs, deps, poses, clean = [], [], [], []
    for o in offsets:
        fr = scene.read(target + o)
        rgb = np.asarray(fr.rgb)
        rgb = rgb.astype(np.float32) / 255.0 if rgb.dtype == np.uint8 else rgb.astype(np.float32)
        rgbs.append(torch.from_numpy(rgb).permute(2, 0, 1))
        deps.append(torch.from_numpy(np.asarray(fr.depth_m, np.float32))[None])
        poses.append(fr.T_world_cam)
        if fr.clean_depth_m is not None:
            clean.append(torch.from_numpy(np.asarray(fr.clean_depth_m, np.float32))[None])
    hw = tuple(scene.image_size)
    rgb = resize_rgb(torch.stack(rgbs), SIZE)
    depth = resize_depth_nearest(torch.stack(deps), SIZE)
    K = torch.from_numpy(scale_intrinsics(np.asarray(scene.intrinsics, np.float64), hw, SIZE)).float()
    T_true = np.stack([np.linalg.inv(poses[0]) @ p for p in poses[1:]]) if poses[0] is not None else None
    clean_t = resize_depth_nearest(torch.stack(clean), SIZE) if clean else None
    return rgb.to(device), depth.to(device), K.to(device), T_true, clean_t


def run_open3d(rgb, depth, K, kind: str) -> np.ndarray:
    """Open3D colored ICP (multi-scale) or RGB-D odometry of each neighbour to the target."""
    import open3d as o3d

    H, W = depth.shape[-2:]
    Kn = K.cpu().numpy().astype(np.float64)
    intr = o3d.camera.PinholeCameraIntrinsic(W, H, Kn[0, 0], Kn[1, 1], Kn[0, 2], Kn[1, 2])

    def rgbd(i):
        col = o3d.geometry.Image(np.ascontiguousarray((rgb[i].permute(1, 2, 0).cpu().numpy() * 255).astype(np.uint8)))
        dep = o3d.geometry.Image(np.ascontiguousarray(depth[i, 0].cpu().numpy().astype(np.float32)))
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            col, dep, depth_scale=1.0, depth_trunc=10.0, convert_rgb_to_intensity=(kind == "o3d_odom")
        )

    tgt = rgbd(0)
    out = []
    if kind == "o3d_odom":
        opt = o3d.pipelines.odometry.OdometryOption()
        for j in range(1, rgb.shape[0]):
            ok, T, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
                rgbd(j), tgt, intr, np.eye(4), o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm(), opt
            )
            out.append(T if ok else np.full((4, 4), np.nan))
        return np.stack(out)
    pc_t = o3d.geometry.PointCloud.create_from_rgbd_image(tgt, intr)
    for j in range(1, rgb.shape[0]):
        pc_s = o3d.geometry.PointCloud.create_from_rgbd_image(rgbd(j), intr)
        T = np.eye(4)
        for voxel, it in ((0.04, 50), (0.02, 30), (0.01, 14)):  # Open3D's tutorial schedule
            s = pc_s.voxel_down_sample(voxel)
            t = pc_t.voxel_down_sample(voxel)
            for pc in (s, t):
                pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 2, max_nn=30))
            try:
                res = o3d.pipelines.registration.registration_colored_icp(
                    s,
                    t,
                    voxel,
                    T,
                    o3d.pipelines.registration.TransformationEstimationForColoredICP(),
                    o3d.pipelines.registration.ICPConvergenceCriteria(1e-6, 1e-6, it),
                )
                T = res.transformation
            except RuntimeError:
                break
        out.append(T)
    return np.stack(out)


def gt_mae(rgb, depth, K, T_j_to_t, clean_t):
    """MAE (m) of the frame-set GT against the clean target depth: valid-only and missing-counted."""
    from depthgt.geometry import backproject
    from depthgt.gt.render import render_gt
    from depthgt.settings import RenderSettings

    Fn = depth.shape[0]
    T = torch.cat([torch.eye(4, dtype=torch.float64)[None], torch.as_tensor(T_j_to_t, dtype=torch.float64)]).to(
        depth.device
    )
    pts = backproject(depth, K.expand(Fn, 3, 3))
    pts_t = (pts.double() @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]).float()
    valid = (depth > 0).flatten(1)
    out = render_gt(pts_t.reshape(1, -1, 3), K[None], SIZE, valid.reshape(1, -1), RenderSettings())
    gt = out.depth[0, 0].cpu()
    ref = clean_t[0, 0].cpu()
    m = ref > 0
    err = (gt - ref).abs()
    valid_only = float(err[m & (gt > 0)].mean())
    missing = float(torch.where(gt > 0, err, ref)[m].mean())
    return valid_only, missing


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", choices=["synthetic", "7scenes"], default="synthetic")
    ap.add_argument("--scene", default="room_000")
    ap.add_argument("--targets", type=int, nargs="+", default=[10, 20, 30])
    ap.add_argument("--methods", nargs="+", default=["paper", "paper_only", "fast", "o3d_icp", "o3d_odom"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--gt", action="store_true", help="also the GT's MAE against clean depth (synthetic)")
    ap.add_argument("--out", default="/tmp/bench_registration.csv")
    ap.add_argument(
        "--set",
        nargs="*",
        default=[],
        help="setting overrides key=value (python literal); refine.key=value for RefineSettings",
    )
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(a.threads)
    from depthgt.sources.base import open_scene

    if a.data == "synthetic":
        scene = open_scene("synthetic", None, a.scene, n_frames=max(a.targets) + 7)
    else:
        scene = open_scene("sevenscenes", str(SEVEN), ".")
    import ast

    kvs = [kv.split("=", 1) for kv in a.set]
    overrides = {k: ast.literal_eval(v) for k, v in kvs if not k.startswith("refine.")}
    refine_over = {k[len("refine.") :]: ast.literal_eval(v) for k, v in kvs if k.startswith("refine.")}
    rows = []
    for tgt in a.targets:
        rgb, depth, K, T_true, clean_t = load_frameset(scene, tgt, OFFSETS, a.device)
        for method in a.methods:
            if a.device.startswith("cuda"):
                torch.cuda.synchronize()
                torch.cuda.reset_peak_memory_stats()
            t0 = time.perf_counter()
            c0 = time.process_time()
            status = "ok"
            if method.startswith("o3d"):
                try:
                    T_est = run_open3d(rgb, depth, K, method)
                except ImportError:
                    continue
            else:
                st = registration_settings({"preset": method, **overrides})
                if refine_over:
                    st = dataclasses.replace(st, refine_settings=dataclasses.replace(st.refine_settings, **refine_over))
                res = register_frameset(rgb, depth, K, OFFSETS, st, seed=a.seed)
                T_est = res.T_j_to_t.numpy()
                status = res.status + ":" + ",".join(s for s in res.neighbour_status)
            if a.device.startswith("cuda"):
                torch.cuda.synchronize()
            dt = time.perf_counter() - t0
            cpu = time.process_time() - c0
            r, t = pose_errors(T_est, T_true)
            for o, ri, ti in zip(OFFSETS[1:], r, t):
                rows += [
                    (a.data, tgt, o, method, "rot_err", "deg", float(ri)),
                    (a.data, tgt, o, method, "trans_err", "cm", float(ti)),
                ]
            if not method.startswith("o3d") and (st.refine or st.chaining):
                # the same run's poses before chaining and refinement (the paper's output)
                r0, t0_ = pose_errors(np.array(res.diagnostics["poses_paper"]), T_true)
                for o, ri, ti in zip(OFFSETS[1:], r0, t0_):
                    rows += [
                        (a.data, tgt, o, method + ":before_refine", "rot_err", "deg", float(ri)),
                        (a.data, tgt, o, method + ":before_refine", "trans_err", "cm", float(ti)),
                    ]
            rows.append((a.data, tgt, 0, method, "time", "s", dt))
            rows.append((a.data, tgt, 0, method, "cpu_time", "s", cpu))
            mem = (
                torch.cuda.max_memory_allocated() / 2**20
                if a.device.startswith("cuda")
                else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            )
            rows.append((a.data, tgt, 0, method, "peak_mem", "MiB", mem))
            line = f"{a.data} t={tgt} {method:10s} {dt:6.1f}s (cpu {cpu:6.1f}s, load {os.getloadavg()[0]:.1f}) rot med {np.median(r):.3f} deg trans med {np.median(t):.3f} cm  [{status}]"
            if a.gt and clean_t is not None and a.data == "synthetic":
                v_est, m_est = gt_mae(rgb, depth, K, T_est, clean_t)
                v_true, m_true = gt_mae(rgb, depth, K, T_true, clean_t)
                rows += [
                    (a.data, tgt, 0, method, "gt_mae_valid", "m", v_est),
                    (a.data, tgt, 0, method, "gt_mae_missing", "m", m_est),
                    (a.data, tgt, 0, "true_poses", "gt_mae_valid", "m", v_true),
                    (a.data, tgt, 0, "true_poses", "gt_mae_missing", "m", m_true),
                ]
                line += f" GT MAE valid {v_est * 1000:.2f} mm (true poses {v_true * 1000:.2f}), missing-counted {m_est * 1000:.2f} ({m_true * 1000:.2f})"
            print(line, flush=True)
            pd.DataFrame(rows, columns=COLUMNS).to_csv(a.out, index=False)  # partial results survive a kill
    df = pd.DataFrame(rows, columns=COLUMNS)
    df.to_csv(a.out, index=False)
    err = df[df.metric.isin(["rot_err", "trans_err"])].copy()
    err["distance"] = err.offset.abs()
    print("\nmedian errors per method and neighbour distance:")
    print(err.pivot_table(index=["method", "distance"], columns="metric", values="value", aggfunc="median").round(3))
    print("\nmedian over all neighbours:")
    print(err.pivot_table(index="method", columns="metric", values="value", aggfunc="median").round(3))
    print("\nmedian time per frame set (s):")
    print(
        df[df.metric.isin(["time", "cpu_time"])]
        .pivot_table(index="method", columns="metric", values="value", aggfunc="median")
        .round(2)
    )


if __name__ == "__main__":
    main()
