"""Milliseconds per residual evaluation of the refinement: the compiled terms (the CPU's
path, ``registration/pair_terms.py``) against the tensor path (a GPU's), on one real
frame set, at each scale of the build's ``refine`` settings.

    python3 bench/bench_pair_terms.py
    python3 bench/bench_pair_terms.py --target 30 --repeats 9
    python3 bench/bench_pair_terms.py --against /tmp/base --repeats 21   # another checkout's kernel

A 7-Scenes frame set (``../shared/data/7scenes-kitchen``, 256x256, every ordered pair of
its 7 frames) at the source's poses; one torch thread. Per scale: the points per pair,
the best of ``--repeats`` evaluations of the costs alone and of the costs with the
normal equations for each path (the compiled path computes both in one pass), and how
far the compiled sums are from the tensors' (the largest |difference| of H over the
largest |H|).

``--against DIR`` times another checkout's compiled kernel (``DIR/src/depthgt/registration/
pair_terms.py``, loaded beside this one) against this one's instead, on a 7-Scenes and a
TUM set (``../shared/data/tum-fr1-xyz-0-239``, target 60), with and without the
photometric term: the two alternate evaluation by evaluation on the same inputs (each in
the maps' layout its checkout reads), and the table gives the median milliseconds of
``--repeats`` each and whether every output is the same to the bit.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
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


def _frameset_at_source_poses(source: dict, scene_name: str, target: int):
    """One frame set of a shared recording at the build's offsets, 256x256, at its
    source's poses: its data, the poses T (F, 4, 4), the build's refine settings and
    their pairs."""
    from depthgt.jobs.common import open_source_scene
    from depthgt.registration import load_frameset, poses_from_source
    from depthgt.registration.refine import frame_pairs
    from depthgt.settings import FrameSetSettings, RefineSettings

    if not Path(source["root"]).is_dir():
        raise SystemExit(f"bench_pair_terms: {source['root']} is absent")
    scene = open_source_scene(source, scene_name, need_poses=True)
    offsets = list(FrameSetSettings().offsets)
    d = load_frameset(scene, [target + o for o in offsets], (256, 256), True, torch.device("cpu"))
    T = torch.cat([torch.eye(4, dtype=torch.float64)[None], poses_from_source(d)])
    rs = RefineSettings()
    return d, T, rs, frame_pairs(len(offsets), rs.pairs, offsets)


KITCHEN = {"kind": "sevenscenes", "root": str(SHARED / "data/7scenes-kitchen")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--target", type=int, default=30, help="the frame set's target frame")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--against", help="another checkout: its compiled kernel against this one's, alternating")
    args = ap.parse_args()
    torch.set_num_threads(1)
    if args.against:
        against(Path(args.against), args.repeats)
        return
    from depthgt.registration.refine import Level, LevelSettings, _system

    d, T, rs, pairs = _frameset_at_source_poses(KITCHEN, "7scenes-kitchen", args.target)
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


def _other_kernel(checkout: Path):
    """The other checkout's ``pair_terms`` module, loaded under its own name (it imports
    numba, numpy and torch only)."""
    path = checkout / "src/depthgt/registration/pair_terms.py"
    if not path.is_file():
        raise SystemExit(f"bench_pair_terms: {path} is absent")
    spec = importlib.util.spec_from_file_location("other_pair_terms", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _maps_for(module, level) -> object:
    """``level``'s maps in the layout ``module``'s kernel reads: two arrays
    (``kernel_maps``), or one of ten channels X, N, gray, gx, gy, validity
    (``channels_last``, before the maps were split)."""
    if hasattr(module, "kernel_maps"):
        return module.kernel_maps(level.geo, level.photo)
    ten = torch.cat([level.geo[:, :6], level.photo[:, :3], level.geo[:, 6:7]], 1)
    return module.channels_last(ten.contiguous(memory_format=torch.channels_last))


def against(checkout: Path, repeats: int) -> None:
    import numpy as np

    import depthgt.registration.pair_terms as this_kernel
    from depthgt.registration.refine import Level, LevelSettings, _gate_cost

    other = _other_kernel(checkout)
    recordings = [
        ("7-Scenes", KITCHEN, "7scenes-kitchen", 30),
        ("TUM", {"kind": "tum", "root": str(SHARED / "data/tum-fr1-xyz-0-239")}, ".", 60),
    ]
    rows = []
    for name, source, scene_name, target in recordings:
        d, T, rs, pairs = _frameset_at_source_poses(source, scene_name, target)
        T_ab = torch.linalg.inv(T)[pairs[:, 0]] @ T[pairs[:, 1]]
        for li, (scale, stride, gate) in enumerate(zip(rs.scales, rs.point_stride, rs.max_dist_m)):
            level = Level(d.rgb, d.depth_m, d.K.float(), scale, stride)
            layouts = {"this": _maps_for(this_kernel, level), "other": _maps_for(other, level)}
            for photo in (0.0, rs.photo_weight):
                ls = LevelSettings(rs.geo_scale_m[li], rs.photo_scale, photo, rs.robust, rs.geo_ref_depth_m)
                kw = dict(
                    geo_scale_m=ls.geo_scale_m, geo_ref_depth_m=ls.geo_ref_depth_m, gate=gate, photo_weight=photo,
                    photo_scale=ls.photo_scale, huber=ls.robust == "huber", gate_cost=_gate_cost(gate, ls),
                )  # fmt: skip
                args = (level.points, level.gray, level.valid)
                calls = {
                    key: functools.partial(m.pair_terms, *args, layouts[key], level.K, T_ab, pairs, **kw)
                    for key, m in (("other", other), ("this", this_kernel))
                }
                first = {key: f() for key, f in calls.items()}  # also the warm-up
                times = {key: [] for key in calls}
                for _ in range(repeats):
                    for key, f in calls.items():
                        t0 = time.perf_counter()
                        f()
                        times[key].append(time.perf_counter() - t0)
                ms = {key: float(np.median(t)) * 1e3 for key, t in times.items()}
                rows.append(
                    {
                        "recording": name,
                        "scale": f"{level.hw[0]} x {level.hw[1]}, stride {stride}",
                        "photometric": "on" if photo > 0 else "off",
                        "other ms": round(ms["other"], 2),
                        "this ms": round(ms["this"], 2),
                        "less time": f"{100 * (1 - ms['this'] / ms['other']):.1f} %",
                        "same to the bit": all(torch.equal(a, b) for a, b in zip(first["this"], first["other"])),
                    }
                )
    print(f"the compiled kernel: this checkout against {checkout}, medians of {repeats}, alternating, one thread")
    print(pd.DataFrame(rows).to_markdown(index=False))


if __name__ == "__main__":
    main()
