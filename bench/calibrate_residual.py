"""Calibration of the registration's residual-size failure check (``max_residual_m``).

For frame sets of the synthetic rooms (true poses) and the 7-Scenes fixture
(reference poses), the median point-to-plane residual of each neighbour in the
target (the statistic ``refine_poses`` reports as ``residual_m``) at the reference
poses and at the reference poses moved by a known offset (translation along a
random axis, plus the same number of tenths of a degree of rotation): the bound
must sit above the first and below the perturbed ones.

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

from depthgt.registration.refine import Level, LevelSettings, target_residuals  # noqa: E402
from depthgt.settings import RefineSettings  # noqa: E402
from depthgt.sources.base import open_scene  # noqa: E402


def residuals(rgb, depth, K, T_j_to_t, rs: RefineSettings):
    level = Level(rgb, depth, K, rs.scales[-1], rs.point_stride[-1])
    ls = LevelSettings(rs.geo_scale_m[-1], rs.photo_scale, rs.photo_weight, rs.robust)
    T = torch.cat([torch.eye(4, dtype=torch.float64)[None], torch.as_tensor(T_j_to_t, dtype=torch.float64)])
    pairs = torch.stack([torch.zeros(len(T) - 1, dtype=torch.long), torch.arange(1, len(T))], 1)
    return target_residuals(level, T, pairs, ls, rs.max_dist_m[-1], len(T))[1:].numpy()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--targets", type=int, nargs="+", default=[10, 20, 30])
    ap.add_argument("--offsets-cm", type=float, nargs="+", default=[0, 1, 2, 3, 5])
    a = ap.parse_args(argv)
    rs = RefineSettings()
    gen = np.random.default_rng(0)
    data = [("synthetic", open_scene("synthetic", None, "room_000", n_frames=max(a.targets) + 7))]
    if SEVEN.exists():
        data.append(("7scenes", open_scene("sevenscenes", str(SEVEN), ".")))
    print("data       offset  median residual (mm) per neighbour: min / median / max")
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
                vals.append(residuals(rgb, depth, K, T, rs))
            v = np.concatenate(vals) * 1000
            print(f"{name:10s} {off:4.1f}cm  {np.nanmin(v):6.2f} / {np.nanmedian(v):6.2f} / {np.nanmax(v):6.2f}")


if __name__ == "__main__":
    main()
