"""Benchmark of the renderers in :mod:`depthgt.gt.render`: time, peak memory, GT accuracy.

* Speed: ``render_gt`` on the merged cloud of a 7-frame set (7 x 256x256 points), its
  two parts alone (``rasterise_gt``: the candidates; ``composite_gt``: the GT from
  candidates made once beforehand) and
  ``splat_soft`` of 7 views x 65,536 points with RGB features (forward, and forward +
  backward), on the CPU with 1 and 2 threads (median wall time and process CPU time of
  ``--repeat`` runs) and on CUDA when available. Peak memory: the growth of the peak
  RSS of a fresh subprocess running one call (CPU), ``torch.cuda.max_memory_allocated``
  (CUDA).
* Accuracy (synthetic rooms, exact poses): the GT of target 8 rendered from the 6
  neighbours (8 -+ 2, 4, 6) or all 7 frames, from clean or from Kinect-noised depth,
  with points at their exact source-pixel positions (``src_hw``) or at the 256x256
  pixel centres, and a naive splat (every point within R averaged, no guard, no plane
  correction). MAE in millimetres over pixels valid in both, against the
  nearest-resized clean target depth (``near``) and against the exact depth ray cast
  at the 256x256 pixel centres (``exact``); ``ref_own`` is the MAE of ``near`` itself
  against ``exact`` (its resampling error), ``input`` the MAE of the resized input
  target depth against ``exact``.

Usage::

    python bench/bench_render.py                       # everything, tidy CSV to /tmp/bench_render.csv
    python bench/bench_render.py --skip-accuracy --repeat 5
    python bench/bench_render.py --rooms room_000 room_001 room_002 --set m=8 radius_px=1.0

Writes a tidy CSV (bench, case, metric, unit, value).
"""

from __future__ import annotations

import argparse
import ast
import json
import resource
import statistics
import subprocess
import sys
import time

import numpy as np
import pandas as pd
import torch

from depthgt.geometry import resize_depth_nearest, scale_intrinsics
from depthgt.gt.render import cloud_in_target, composite_gt, rasterise_gt, render_gt, splat_soft
from depthgt.settings import RenderSettings

SIZE = (256, 256)
IDS = [2, 4, 6, 8, 10, 12, 14]  # target 8 and its neighbours -+ 2, 4, 6
TARGET = 3
NEIGHBOURS = [0, 1, 2, 4, 5, 6]


def load_room(room: str) -> dict:
    """Clean and noisy depth at 256x256, K, T_j_to_t and the exact target depth of a synthetic room."""
    from depthgt.sources.base import open_scene
    from depthgt.synth.scene import raycast

    scene = open_scene("synthetic", None, room, n_frames=20)
    frames = [scene.read(i) for i in IDS]
    hw = tuple(scene.image_size)
    K = scale_intrinsics(torch.tensor(scene.intrinsics), hw, SIZE)
    Ts = np.stack([f.T_world_cam for f in frames])
    to256 = lambda a: resize_depth_nearest(torch.from_numpy(np.stack(a))[:, None], SIZE)  # noqa: E731
    exact = raycast(scene.layout, Ts[TARGET], K.numpy(), SIZE).depth_m
    return {
        "hw": hw,
        "K": K.float(),
        "T": torch.from_numpy(np.linalg.inv(Ts[TARGET])[None] @ Ts).float(),
        "clean": to256([f.clean_depth_m for f in frames]),
        "noisy": to256([f.depth_m for f in frames]),
        "exact": torch.from_numpy(exact),
    }


def render_case(
    data: dict, frames: list[int], depth_kind: str, exact_pos: bool, settings: RenderSettings, device: str = "cpu"
) -> torch.Tensor:
    d = data[depth_kind][frames].to(device)
    src_hw = data["hw"] if exact_pos else None
    cloud = cloud_in_target(
        d,
        data["K"].to(device).expand(len(frames), 3, 3),
        data["T"][frames].to(device),
        src_hw=src_hw,
        noise_sigma_1m=settings.noise_sigma_1m,
        noise_sigma_abs_m=settings.noise_sigma_abs_m,
    )
    return (
        render_gt(
            cloud.points,
            data["K"][None].to(device),
            SIZE,
            cloud.valid,
            settings,
            normals_cam=cloud.normals,
            sigma_m=cloud.sigma_m,
            frame=cloud.frame,
            src_hw=src_hw,
        )
        .depth[0, 0]
        .cpu()
    )


def mae_mm(a: torch.Tensor, b: torch.Tensor) -> float:
    m = (a > 0) & (b > 0)
    return float((a - b).abs()[m].mean()) * 1000


def accuracy(rooms: list[str], settings: RenderSettings) -> list[dict]:
    rows = []
    naive = RenderSettings(
        m=10_000,
        radius_px=settings.radius_px,
        gap_sigmas=1e9,
        gap_slope_rel=0.0,
        min_frames=1,
        plane="none",
        drop_ambiguous=False,
        extend_uncovered=True,
    )
    for room in rooms:
        data = load_room(room)
        near, exact = data["clean"][TARGET, 0], data["exact"]
        rows.append(
            dict(bench="accuracy", case=f"{room}/reference", metric="ref_own", unit="mm", value=mae_mm(near, exact))
        )
        rows.append(
            dict(
                bench="accuracy",
                case=f"{room}/input_noisy",
                metric="input",
                unit="mm",
                value=mae_mm(data["noisy"][TARGET, 0], near),
            )
        )
        cases = [
            ("6nb/clean/exact_pos", NEIGHBOURS, "clean", True, settings),
            ("6nb/clean/centre_pos", NEIGHBOURS, "clean", False, settings),
            ("7fr/clean/exact_pos", list(range(7)), "clean", True, settings),
            ("6nb/noisy/exact_pos", NEIGHBOURS, "noisy", True, settings),
            ("7fr/noisy/exact_pos", list(range(7)), "noisy", True, settings),
            ("6nb/clean/naive", NEIGHBOURS, "clean", False, naive),
            ("7fr/noisy/naive", list(range(7)), "noisy", False, naive),
        ]
        for name, frames, kind, exact_pos, st in cases:
            gt = render_case(data, frames, kind, exact_pos, st)
            case = f"{room}/{name}"
            rows.append(dict(bench="accuracy", case=case, metric="near", unit="mm", value=mae_mm(gt, near)))
            rows.append(dict(bench="accuracy", case=case, metric="exact", unit="mm", value=mae_mm(gt, exact)))
            rows.append(
                dict(
                    bench="accuracy",
                    case=case,
                    metric="coverage",
                    unit="fraction",
                    value=float(((gt > 0) & (exact > 0)).sum() / (exact > 0).sum()),
                )
            )
    return rows


def speed_inputs(device: str):
    """A 7-frame synthetic-like cloud: depth of slanted planes with noise, and RGB features."""
    g = torch.Generator().manual_seed(0)
    K = torch.tensor([[234.0, 0, 127.5], [0, 312.0, 127.5], [0, 0, 1]])
    v, u = torch.meshgrid(torch.arange(256.0), torch.arange(256.0), indexing="ij")
    depth = (2.0 + 0.004 * u + 0.006 * v)[None, None].repeat(7, 1, 1, 1)
    depth = depth * (1 + 0.003 * torch.randn(depth.shape, generator=g))
    T = torch.eye(4).repeat(7, 1, 1)
    T[:, 0, 3] = torch.linspace(-0.03, 0.03, 7)
    cloud = cloud_in_target(depth, K.expand(7, 3, 3), T)
    feats = torch.rand(7, 256 * 256, 3, generator=g)
    per_view = cloud.points.reshape(7, -1, 3)
    return {
        k: v.to(device)
        for k, v in dict(
            K=K,
            points=cloud.points,
            normals=cloud.normals,
            valid=cloud.valid,
            sigma=cloud.sigma_m,
            frame=cloud.frame,
            per_view=per_view,
            feats=feats,
        ).items()
    }


def run_one(fn: str, x: dict):
    if fn == "render_gt":
        return render_gt(
            x["points"],
            x["K"][None],
            SIZE,
            x["valid"],
            RenderSettings(),
            normals_cam=x["normals"],
            sigma_m=x["sigma"],
            frame=x["frame"],
        )
    if fn == "rasterise_gt":
        return rasterise_gt(
            x["points"],
            x["K"][None],
            SIZE,
            RenderSettings(),
            valid=x["valid"],
            normals_cam=x["normals"],
            sigma_m=x["sigma"],
            frame=x["frame"],
        )
    if fn == "composite_gt":
        if "cands" not in x:  # made once: the compositor alone is timed
            x["cands"] = run_one("rasterise_gt", x)
        return composite_gt(x["cands"], RenderSettings())
    if fn == "splat_soft":
        return splat_soft(x["per_view"], x["feats"], x["K"].expand(7, 3, 3), SIZE)
    if fn == "splat_soft_fwd_bwd":
        p = x["per_view"].clone().requires_grad_()
        f = x["feats"].clone().requires_grad_()
        out = splat_soft(p, f, x["K"].expand(7, 3, 3), SIZE)
        (out.features.sum() + out.depth.sum()).backward()
        return out
    raise ValueError(fn)


def timing(device: str, threads: int, repeat: int) -> list[dict]:
    torch.set_num_threads(threads)
    x = speed_inputs(device)
    rows = []
    for fn in ["render_gt", "rasterise_gt", "composite_gt", "splat_soft", "splat_soft_fwd_bwd"]:
        run_one(fn, x)  # warm-up
        walls, cpus = [], []
        for _ in range(repeat):
            if device == "cuda":
                torch.cuda.synchronize()
            t, c = time.perf_counter(), time.process_time()
            run_one(fn, x)
            if device == "cuda":
                torch.cuda.synchronize()
            walls.append(time.perf_counter() - t)
            cpus.append(time.process_time() - c)
        case = f"{fn}/{device}/{threads}thr" if device == "cpu" else f"{fn}/{device}"
        rows.append(dict(bench="speed", case=case, metric="wall_median", unit="s", value=statistics.median(walls)))
        rows.append(dict(bench="speed", case=case, metric="wall_min", unit="s", value=min(walls)))
        if device == "cpu":
            rows.append(dict(bench="speed", case=case, metric="cpu_median", unit="s", value=statistics.median(cpus)))
        else:
            torch.cuda.reset_peak_memory_stats()
            base = torch.cuda.memory_allocated()
            run_one(fn, x)
            rows.append(
                dict(
                    bench="memory",
                    case=case,
                    metric="peak_alloc",
                    unit="MiB",
                    value=(torch.cuda.max_memory_allocated() - base) / 2**20,
                )
            )
    return rows


def _status_kib(key: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    raise KeyError(key)


def peak_rss_child(fn: str) -> float:
    """Run in a fresh process: MiB of peak RSS above the RSS before one call of ``fn``
    (Linux: the peak is reset through /proc/self/clear_refs; else ru_maxrss growth)."""
    torch.set_num_threads(1)
    x = speed_inputs("cpu")
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # reset VmHWM to the current RSS
        before = _status_kib("VmRSS")
        run_one(fn, x)
        return (_status_kib("VmHWM") - before) / 1024
    except OSError:
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        run_one(fn, x)
        return (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rooms", nargs="+", default=["room_000", "room_001", "room_002"])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--skip-accuracy", action="store_true")
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument("--set", nargs="*", default=[], help="RenderSettings overrides key=value (python literals)")
    ap.add_argument("--out", default="/tmp/bench_render.csv")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(peak_rss_child(a.child)))
        return
    settings = RenderSettings(**{k: ast.literal_eval(v) for k, v in (s.split("=", 1) for s in a.set)})
    rows: list[dict] = []
    if not a.skip_speed:
        for t in a.threads:
            rows += timing("cpu", t, a.repeat)
        if torch.cuda.is_available():
            rows += timing("cuda", 1, a.repeat)
        for fn in ["render_gt", "splat_soft", "splat_soft_fwd_bwd"]:
            out = subprocess.run([sys.executable, __file__, "--child", fn], capture_output=True, text=True, check=True)
            rows.append(
                dict(
                    bench="memory",
                    case=f"{fn}/cpu",
                    metric="peak_rss_growth",
                    unit="MiB",
                    value=float(out.stdout.strip().splitlines()[-1]),
                )
            )
    if not a.skip_accuracy:
        torch.set_num_threads(min(a.threads))
        rows += accuracy(a.rooms, settings)
    df = pd.DataFrame(rows)
    df.to_csv(a.out, index=False)
    with pd.option_context("display.max_rows", None, "display.width", 160):
        if (df.bench == "accuracy").any():
            acc = df[df.bench == "accuracy"]
            print(acc.pivot_table(index="case", columns="metric", values="value").round(3))
        if (df.bench != "accuracy").any():
            print(df[df.bench != "accuracy"].round(4).to_string(index=False))


if __name__ == "__main__":
    main()
