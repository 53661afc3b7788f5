"""`refine` with other refinement settings against the default, on synthetic frame sets
with a known truth: the GT's error and the poses, paired per frame set.

    python3 bench/bench_refine_variants.py --sets tuning --variant "point_stride=(1,2,2)"
    python3 bench/bench_refine_variants.py --sets evaluation --variant "point_stride=(1,2,2)"
    python3 bench/bench_refine_variants.py --sets tuning --variant "point_stride=(1,2,2)" --perturb 0.5 1.0

The frame sets are ``bench_gt_protocol.py``'s (its TUNING set to choose on, its EVALUATION
set to report on; generated once and cached in ``--cache``). Each is registered by
``registration.method: refine`` from the source's (exact) poses, or with ``--perturb DEG
CM`` from those poses moved, each neighbour by a random rotation of DEG degrees and
translation of CM centimetres (the start an overfit registration hands on); once with the
default ``refine_settings`` and once with ``--variant`` (``key=value``, python literals,
over the defaults). Printed per metric: both means and the paired difference (variant
minus default) with its 95 % bootstrap interval over the frame sets:

* ``mae_mm``: the GT (rendered as the build renders it) against the truth where both have
  depth; ``completeness``: the truth's pixels the GT has;
* ``rot_deg`` / ``trans_cm``: the median pose error of the set's neighbours against the
  exact poses; ``kept``: neighbours the registration fused;

and over all neighbours: the share within 0.1 deg and 0.5 cm of the truth and the 90th
percentiles of the pose errors. One torch thread.
"""

from __future__ import annotations

import argparse
import ast
import math
import sys
from pathlib import Path

import numpy as np
import torch
from kornia.geometry.liegroup import Se3

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_gt_protocol as gp  # noqa: E402  (the protocol's frame sets)

from depthgt.gt.render import fuse  # noqa: E402
from depthgt.metric_vocabulary import pose_errors  # noqa: E402
from depthgt.registration import align, poses_from_source  # noqa: E402
from depthgt.settings import FrameSetSettings, RenderSettings, registration_settings  # noqa: E402


def _variant(items: list[str]) -> dict:
    out = {}
    for item in items:
        k, _, v = item.partition("=")
        out[k] = ast.literal_eval(v)
    return out


def _moved(ref: torch.Tensor, rot_deg: float, trans_cm: float, g: torch.Generator) -> torch.Tensor:
    """``ref`` (F-1, 4, 4) each moved by a random rotation of ``rot_deg`` and translation of ``trans_cm``."""
    axis = torch.randn(ref.shape[0], 3, generator=g, dtype=torch.float64)
    shift = torch.randn(ref.shape[0], 3, generator=g, dtype=torch.float64)
    twist = torch.cat(
        [
            shift / shift.norm(dim=1, keepdim=True) * (trans_cm / 100.0),
            axis / axis.norm(dim=1, keepdim=True) * math.radians(rot_deg),
        ],
        1,
    )
    return Se3.exp(twist).matrix().to(torch.float64) @ ref


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", nargs="+", default=["tuning"], choices=list(gp.SETS))
    ap.add_argument("--variant", nargs="+", required=True, help="refine_settings key=value (python literals)")
    ap.add_argument("--perturb", nargs=2, type=float, metavar=("DEG", "CM"), help="start from moved source poses")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/depthgt_protocol"))
    ap.add_argument("--seed", type=int, default=7)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    variants = {
        "default": registration_settings({"method": "refine"}),
        "variant": registration_settings({"method": "refine", "refine_settings": _variant(a.variant)}),
    }
    offsets = list(FrameSetSettings().offsets)
    rng = np.random.default_rng(0)
    g = torch.Generator().manual_seed(a.seed)
    print(f"command: python3 bench/bench_refine_variants.py {' '.join(sys.argv[1:] if argv is None else argv)}")
    for set_name in a.sets:
        rows: dict[str, list[dict]] = {v: [] for v in variants}
        errs: dict[str, list] = {v: [] for v in variants}
        for group in gp.SETS[set_name]:
            for k in group["scenes"]:
                for t in gp.TARGETS:
                    d = gp.load_cached(a.cache, group, k, t)["data"]
                    truth = d.truth_m[0, 0]
                    ref = poses_from_source(d)
                    start = None if a.perturb is None else _moved(ref, *a.perturb, g)
                    data = d if start is None else _with_poses(d, start)
                    for name, reg in variants.items():
                        al = align(data, offsets, reg, seed=t)
                        gt = fuse(d, al.T_j_to_t, RenderSettings(), members=al.fused).gt.depth[0, 0]
                        both = (gt > 0) & (truth > 0)
                        e = pose_errors(al.T_j_to_t.numpy(), ref.numpy())
                        errs[name].append((np.asarray(e.rot_err_deg), np.asarray(e.trans_err_cm)))
                        rows[name].append(
                            dict(
                                mae_mm=1000 * float((gt - truth).abs()[both].mean()),
                                completeness=float(both.sum() / (truth > 0).sum()),
                                rot_deg=float(np.median(e.rot_err_deg)),
                                trans_cm=float(np.median(e.trans_err_cm)),
                                kept=len(al.fused) - 1,
                            )
                        )
        n = len(rows["default"])
        print(
            f"\n{set_name}: {n} frame sets"
            + ("" if a.perturb is None else f", starts moved {a.perturb[0]} deg / {a.perturb[1]} cm")
        )
        for key in rows["default"][0]:
            x = np.array([r[key] for r in rows["default"]])
            y = np.array([r[key] for r in rows["variant"]])
            diff = y - x
            boots = [rng.choice(diff, n).mean() for _ in range(4000)]
            lo, hi = np.percentile(boots, [2.5, 97.5])
            print(
                f"  {key}: default {x.mean():.5f}, variant {y.mean():.5f}, diff {diff.mean():+.5f} [{lo:+.5f}, {hi:+.5f}]"
            )
        for name in variants:
            rot = np.concatenate([r for r, _ in errs[name]])
            tr = np.concatenate([c for _, c in errs[name]])
            print(
                f"  {name}: {len(rot)} neighbours, within 0.1 deg and 0.5 cm {((rot < 0.1) & (tr < 0.5)).mean():.3f}, "
                f"p90 {np.percentile(rot, 90):.4f} deg / {np.percentile(tr, 90):.4f} cm"
            )


def _with_poses(d, T_j_to_t: torch.Tensor):
    """``d`` with its source poses replaced so that the neighbours' poses in the target
    camera are ``T_j_to_t`` (F-1, 4, 4): what ``refine`` starts from."""
    T_world = d.T_world_cam.clone()
    T_world[1:] = T_world[0] @ T_j_to_t.to(T_world.dtype)
    return type(d)(**{**d.__dict__, "T_world_cam": T_world})


if __name__ == "__main__":
    main()
