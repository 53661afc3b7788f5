"""Calibration of the registration's residual-size failure check (``max_residual_m``,
``max_residual_sigmas``).

For frame sets of the synthetic rooms (true poses; Kinect v1 and the ``coarse_stereo``
profile) and the 7-Scenes fixture (reference poses), the two statistics of each
neighbour in the target that ``refine_poses`` reports: the median point-to-plane
residual in metres (``residual_m``) and in units of the depth noise the frame set
shows (``residual_sigmas``: |residual| / (sigma_1m z^2), sigma_1m estimated from the
set's depth), at the reference poses and at the reference poses moved by a known
offset (translation along a random axis, plus the same number of tenths of a degree
of rotation). A neighbour fails when both are above their bounds: the aligned ones
must pass, the perturbed ones should fail. The last columns are the share of
neighbours the check fails with the fixed metric bound alone (``max_residual_sigmas``
0, the check before) and with both bounds (the default).

Usage::

    python3 bench/calibrate_residual.py --targets 10 20 30 --offsets-cm 0 1 2 3 5
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from kornia.geometry.liegroup import Se3

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_registration import OFFSETS, SEVEN, load_frameset  # noqa: E402

from depthgt.gt.render import estimate_noise_sigma_1m  # noqa: E402
from depthgt.registration.refine import Level, LevelSettings, target_residual_stats  # noqa: E402
from depthgt.settings import RegistrationSettings, registration_settings  # noqa: E402
from depthgt.sources.base import open_scene  # noqa: E402


def residuals(rgb, depth, K, T_j_to_t, s: RegistrationSettings):
    """(metres, sigmas) per neighbour, as refine_poses computes them at its finest scale."""
    rs = s.refine_settings
    level = Level(rgb, depth, K, rs.scales[-1], rs.point_stride[-1])
    ls = LevelSettings(rs.geo_scale_m[-1], rs.photo_scale, rs.photo_weight, rs.robust)
    T = torch.cat([torch.eye(4, dtype=torch.float64)[None], torch.as_tensor(T_j_to_t, dtype=torch.float64)])
    pairs = torch.stack([torch.zeros(len(T) - 1, dtype=torch.long), torch.arange(1, len(T))], 1)
    m, q = target_residual_stats(level, T, pairs, ls, rs.max_dist_m[-1], len(T), estimate_noise_sigma_1m(depth))
    return m[1:].numpy(), q[1:].numpy()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--targets", type=int, nargs="+", default=[10, 20, 30])
    ap.add_argument("--offsets-cm", type=float, nargs="+", default=[0, 1, 2, 3, 5])
    ap.add_argument(
        "--preset", default="fast", help="registration preset whose refinement settings and bounds are used"
    )
    a = ap.parse_args(argv)
    s = registration_settings({"preset": a.preset})
    gen = np.random.default_rng(0)
    n = max(a.targets) + 7
    data = [
        ("synthetic", open_scene("synthetic", None, "room_000", n_frames=n)),
        ("syn_stereo", open_scene("synthetic", None, "room_000", n_frames=n, sensor="coarse_stereo")),
    ]
    if SEVEN.exists():
        data.append(("7scenes", open_scene("sevenscenes", str(SEVEN), ".")))
    print(
        f"bounds: max_residual_m {s.checks.max_residual_m * 1000:g} mm, max_residual_sigmas {s.checks.max_residual_sigmas:g}"
    )
    print(
        "data       offset  median residual (mm): min / median / max | in noise sigmas: min / median / max"
        " | failed: metric bound alone / both bounds"
    )
    for name, scene in data:
        for off in a.offsets_cm:
            vals = []
            for tgt in a.targets:
                if tgt + max(OFFSETS) >= len(scene):
                    continue
                rgb, depth, K, T_true, _ = load_frameset(scene, tgt, OFFSETS, "cpu")
                T = T_true.copy()
                if off > 0:
                    axis = gen.normal(size=(len(T), 3))
                    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
                    rot = gen.normal(size=(len(T), 3))
                    rot /= np.linalg.norm(rot, axis=1, keepdims=True)
                    xi = np.concatenate([axis * off / 100, rot * np.deg2rad(off / 10)], 1)
                    dT = Se3.exp(torch.from_numpy(xi)).matrix().detach().numpy()
                    T = dT @ T
                vals.append(residuals(rgb, depth, K, T, s))
            v = np.concatenate([m for m, _ in vals]) * 1000
            q = np.concatenate([x for _, x in vals])
            fixed = ~(v <= s.checks.max_residual_m * 1000)
            both = fixed & ~(q <= s.checks.max_residual_sigmas)
            print(
                f"{name:10s} {off:4.1f}cm  {np.nanmin(v):6.2f} / {np.nanmedian(v):6.2f} / {np.nanmax(v):6.2f} | "
                f"{np.nanmin(q):5.2f} / {np.nanmedian(q):5.2f} / {np.nanmax(q):5.2f} | "
                f"{fixed.mean() * 100:3.0f} % / {both.mean() * 100:3.0f} %  ({len(v)} neighbours)"
            )


if __name__ == "__main__":
    main()
