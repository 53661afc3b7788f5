"""Milliseconds per residual evaluation of the refinement: the compiled terms (the CPU's
path, ``registration/pair_terms.py``) against the tensor path (a GPU's), on one real
frame set, at each scale of the build's ``refine`` settings.

    python3 bench/bench_pair_terms.py
    python3 bench/bench_pair_terms.py --target 30 --repeats 9

A 7-Scenes frame set (``../shared/data/7scenes-kitchen``, 256x256, every ordered pair of
its 7 frames) at the source's poses; one torch thread. Per scale: the points per pair,
the best of ``--repeats`` evaluations of the costs alone and of the costs with the
normal equations for each path (the compiled path computes both in one pass), and how
far the compiled sums are from the tensors' (the largest |difference| of H over the
largest |H|).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import pandas as pd
import torch

ROOT = Path(__file__).resolve().parents[1]
SHARED = next((p for p in (ROOT.parent / "shared", ROOT.parents[1] / "shared") if p.is_dir()), ROOT.parent / "shared")


def _best(f, repeats: int) -> float:
    f()  # warm-up (the compiled kernel loads from its cache on the first call)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return min(times) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--target", type=int, default=30, help="the frame set's target frame")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    torch.set_num_threads(1)
    from depthgt.jobs.common import open_source_scene
    from depthgt.registration import load_frameset, poses_from_source
    from depthgt.registration.refine import Level, LevelSettings, _system, frame_pairs
    from depthgt.settings import FrameSetSettings, RefineSettings

    root = SHARED / "data/7scenes-kitchen"
    if not root.is_dir():
        raise SystemExit(f"bench_pair_terms: {root} is absent")
    scene = open_source_scene({"kind": "sevenscenes", "root": str(root)}, "7scenes-kitchen", need_poses=True)
    offsets = list(FrameSetSettings().offsets)
    d = load_frameset(scene, [args.target + o for o in offsets], (256, 256), True, torch.device("cpu"))
    T = torch.cat([torch.eye(4, dtype=torch.float64)[None], poses_from_source(d)])
    rs = RefineSettings()
    pairs = frame_pairs(len(offsets), rs.pairs, offsets)
    rows = []
    for li, (scale, stride, gate) in enumerate(zip(rs.scales, rs.point_stride, rs.max_dist_m)):
        level = Level(d.rgb, d.depth_m, d.K.float(), scale, stride)
        ls = LevelSettings(rs.geo_scale_m[li], rs.photo_scale, rs.photo_weight, rs.robust, rs.geo_ref_depth_m)

        def costs(compiled: bool, level=level, ls=ls, gate=gate):
            return _system(level, T, pairs, ls, gate, compiled).pair_cost

        def normal(compiled: bool, level=level, ls=ls, gate=gate):
            return _system(level, T, pairs, ls, gate, compiled).H_rel

        H_t, H_c = normal(False), normal(True)
        rows.append(
            {
                "scale": scale,
                "points per pair": level.points.shape[2],
                "pairs": len(pairs),
                "tensor costs ms": round(_best(lambda: costs(False), args.repeats), 1),
                "tensor + normal eq. ms": round(_best(lambda: normal(False), args.repeats), 1),
                "compiled (both) ms": round(_best(lambda: normal(True), args.repeats), 1),
                "H rel. difference": f"{float((H_c - H_t).abs().max() / H_t.abs().max()):.1e}",
            }
        )
    print(f"7-Scenes target {args.target}, {len(pairs)} pairs, one torch thread, best of {args.repeats}")
    print(pd.DataFrame(rows).to_markdown(index=False))


if __name__ == "__main__":
    main()
