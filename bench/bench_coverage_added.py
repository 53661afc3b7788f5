"""The error of the pixels ``frameset.selection: coverage`` adds, against the synthetic
truth, for several ``coverage_mixed_margin_px`` and ``coverage_mixed_jump_rel``, or for
any ``coverage_*`` settings given as ``--variant`` (issue 30).

The frame sets of bench_gt_protocol.py's sets (targets 8, 20, 32 of 40-frame sequences,
256x256, source poses, the 40 frames as candidates): the core is rendered as with
``window``; the views are added with each margin; scored are the pixels the core leaves
without GT and the added views fill, against the truth (the nearest-resized clean target
depth): how many, their mean, median and share of errors beyond 5 cm (in front of or
behind the truth), and by the number of samples fused in the pixel and by whether the target's own input has depth there.
The pooled MAE of each variant carries a 95 % percentile bootstrap interval over frame sets,
and its difference to the first variant a paired one (the same resampled frame sets;
2000 resamples, seed 0, ``depthgt.eval.bootstrap.resample_counts``).

Usage::

    python3 bench/bench_coverage_added.py --sets tuning --margins 0 1 2 --jumps 0 0.03      # choose on this
    python3 bench/bench_coverage_added.py --sets evaluation --margins 0 1                   # report this
    python3 bench/bench_coverage_added.py --sets tuning --variant default views2:coverage_views=2 \
        wide:coverage_max_baseline_m=0.5,coverage_max_angle_deg=30   # any FrameSetSettings coverage_* fields

With ``--variant NAME[:KEY=VALUE,...]`` (the first is the one the others are paired with;
``NAME`` alone is the defaults) the margins and jumps are not swept. The share of the
core's empty truth pixels each variant fills is printed beside its error.

Frame sets are cached as bench_gt_protocol.py caches them (``--cache``).
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_gt_protocol as protocol  # noqa: E402  (the sets and the frame-set cache)

from depthgt.eval.bootstrap import BOOTSTRAP_LEVEL, BOOTSTRAP_RESAMPLES, BOOTSTRAP_SEED, resample_counts  # noqa: E402
from depthgt.gt.cache import ResizedScene  # noqa: E402
from depthgt.gt.coverage import add_coverage_views  # noqa: E402
from depthgt.gt.planning import coverage_candidates  # noqa: E402
from depthgt.gt.render import fuse  # noqa: E402
from depthgt.registration import Alignment, poses_from_source  # noqa: E402
from depthgt.settings import FrameSetSettings, RenderSettings, registration_settings  # noqa: E402
from depthgt.sources.base import open_scene  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", nargs="+", default=["tuning"], choices=list(protocol.SETS))
    ap.add_argument("--margins", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--jumps", type=float, nargs="+", default=[FrameSetSettings().coverage_mixed_jump_rel])
    ap.add_argument("--scenes", type=int, default=None, help="the first N scenes of each group")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/depthgt_protocol"))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--variant",
        nargs="+",
        default=None,
        help="NAME[:KEY=VALUE,...] FrameSetSettings coverage_* overrides (values as Python literals); replaces --margins/--jumps",
    )
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    render, reg = RenderSettings(), registration_settings({"method": "given"})
    if a.variant:
        variants = {name: FrameSetSettings(selection="coverage", **kw) for name, kw in map(parse_variant, a.variant)}
    else:
        variants = {
            (m, j): FrameSetSettings(selection="coverage", coverage_mixed_margin_px=m, coverage_mixed_jump_rel=j)
            for m in a.margins
            for j in (a.jumps if m > 0 else a.jumps[:1])  # margin 0: no sample is mixed, whatever the jump
        }
    vlabel = "variant" if a.variant else "margin, jump"
    span = max(fs.coverage_span for fs in variants.values())
    for set_name in a.sets:
        errors: dict[tuple, list[np.ndarray]] = {v: [] for v in variants}
        counts: dict[tuple, list[np.ndarray]] = {v: [] for v in variants}
        measured: dict[tuple, list[np.ndarray]] = {v: [] for v in variants}  # the target's input has depth there
        empty_total = 0
        for group in protocol.SETS[set_name]:
            for k in list(group["scenes"])[: a.scenes]:
                name = f"{group['family']}_{k:03d}"
                scene = open_scene(
                    "synthetic", None, name, seed=group["seed"], sensor=group["sensor"], n_frames=protocol.N_FRAMES
                )
                frames = ResizedScene(scene, protocol.SIZE, keep=2 * span + 2, need_pose=True)
                for t in protocol.TARGETS:
                    item = protocol.load_cached(a.cache, group, k, t)
                    data = item["data"]
                    T = poses_from_source(data)
                    core = fuse(data, T, render)
                    ref = data.truth_m[0, 0].numpy()
                    core_z = core.gt.depth[0, 0].numpy()
                    empty_total += int(((core_z <= 0) & (ref > 0)).sum())
                    splits = np.full(protocol.N_FRAMES, "train", dtype=object)
                    for m, fs in variants.items():
                        cands = coverage_candidates(splits, t, item["members"], fs)
                        members = list(range(len(item["members"])))
                        cov = add_coverage_views(frames, t, cands, data, Alignment(T, members), core, fs, reg, render)
                        z = cov.render.gt.depth[0, 0].numpy()
                        added = (core_z <= 0) & (z > 0) & (ref > 0)
                        errors[m].append((z - ref)[added])
                        counts[m].append(cov.render.gt.count[0, 0].numpy()[added])
                        measured[m].append(data.depth_m[0, 0].numpy()[added] > 0)
                print(f"{set_name} {name} s{group['seed']} {group['sensor']}: done", file=sys.stderr, flush=True)
        print(f"\n{set_name}: {empty_total} truth pixels the core leaves without GT")
        head = "| variant |" if a.variant else "| margin px | jump |"
        print(head + " pixels added | share of empty | MAE mm | median mm | > 5 cm | in front > 5 cm | behind > 5 cm |")
        print("|---" * (head.count("|") - 1) + "|---:|---:|---:|---:|---:|---:|---:|")
        for m in variants:
            e = np.concatenate(errors[m]) if errors[m] else np.zeros(0)
            cells = f"| {m} |" if a.variant else f"| {m[0]} | {m[1]} |"
            if e.size == 0:
                print(cells + " 0 | | | | | | |")
                continue
            ae = np.abs(e)
            print(
                f"{cells} {e.size} | {100 * e.size / max(empty_total, 1):.1f} % | {1000 * ae.mean():.1f} | {1000 * np.median(ae):.1f} "
                f"| {100 * (ae > 0.05).mean():.1f} % | {100 * (e < -0.05).mean():.1f} % | {100 * (e > 0.05).mean():.1f} % |"
            )
        # pooled MAE per resample of frame sets: (draws @ per-set sums) / (draws @ per-set pixels)
        keys = list(variants)
        sums = np.array([[np.abs(e).sum() for e in errors[m]] for m in keys])  # (variants, frame sets)
        pixels = np.array([[e.size for e in errors[m]] for m in keys], dtype=np.float64)
        draws = resample_counts(sums.shape[1], BOOTSTRAP_RESAMPLES, BOOTSTRAP_SEED)
        with np.errstate(invalid="ignore", divide="ignore"):
            mae = 1000 * (draws @ sums.T) / (draws @ pixels.T)  # (resamples, variants), mm
        q = [(1 - BOOTSTRAP_LEVEL) / 2 * 100, (1 + BOOTSTRAP_LEVEL) / 2 * 100]
        for j, m in enumerate(keys):
            lo, hi = np.nanpercentile(mae[:, j], q)
            line = f"{vlabel} {m}: pooled MAE 95 % interval over frame sets [{lo:.1f}, {hi:.1f}] mm"
            if j:
                dlo, dhi = np.nanpercentile(mae[:, j] - mae[:, 0], q)
                line += f"; minus {keys[0]}: [{dlo:.1f}, {dhi:.1f}] mm (paired)"
            print(line)
        for m in variants:
            if not errors[m]:
                continue
            ae, c = np.abs(np.concatenate(errors[m])), np.concatenate(counts[m])
            parts = []
            for lo, hi in ((1, 1), (2, 2), (3, 5), (6, None)):
                sel = (c >= lo) & (c <= hi if hi is not None else True)
                if sel.any():
                    label = f"{lo}" if lo == hi else (f"{lo}-{hi}" if hi else f">={lo}")
                    parts.append(f"{label} samples: {int(sel.sum())} px, MAE {1000 * ae[sel].mean():.1f} mm")
            print(f"{vlabel} {m}, by samples fused: " + "; ".join(parts))
            own = np.concatenate(measured[m])
            for label, sel in (("with", own), ("without", ~own)):
                if sel.any():
                    print(
                        f"{vlabel} {m}, where the target's input is {label} depth: {int(sel.sum())} px, MAE {1000 * ae[sel].mean():.1f} mm"
                    )


def parse_variant(text: str) -> tuple[str, dict]:
    """``NAME[:KEY=VALUE,...]`` -> (NAME, {KEY: literal}); KEYs must be FrameSetSettings fields."""
    name, _, rest = text.partition(":")
    known = set(FrameSetSettings.__dataclass_fields__)
    kw = {}
    for item in filter(None, rest.split(",")):
        key, eq, value = item.partition("=")
        if not eq or key not in known:
            raise SystemExit(f"--variant {text!r}: {item!r} is not KEY=VALUE of a FrameSetSettings field")
        kw[key] = ast.literal_eval(value)
    return name, kw


if __name__ == "__main__":
    main()
