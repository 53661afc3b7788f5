"""Compare the synthetic Kinect model with the real 7-Scenes kitchen frames.

Applies one estimator (depthgt.synth.calibration.sensor_statistics: hole fractions,
robust std of the local-plane residual binned by depth) to the real fixture's raw
depth and to the noisy depth of synthetic rooms, and prints the table real vs
synthetic with the ratio (target: every comparable ratio within [1/1.5, 1.5]).

    python bench/calibrate_noise.py [--fixture ../shared/data/7scenes-kitchen]
        [--scenes 4] [--frames 6] [--seed 0] [--csv out.csv] [--set noise_sigma_disp_px=0.04 ...]
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from depthgt.sources.synthetic import list_scenes, open_scene
from depthgt.synth.calibration import compare_statistics, sensor_statistics

REPO = Path(__file__).resolve().parents[1]


def real_depths(folder: Path) -> list[np.ndarray]:
    files = sorted(folder.glob("frame-*.depth.png"))
    if not files:
        raise SystemExit(f"no frame-*.depth.png in {folder}")
    out = []
    for f in files:
        d = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if d is None:
            raise SystemExit(f"cannot read {f}")
        out.append(d.astype(np.float32) / 1000.0)
    return out


def synthetic_depths(n_scenes: int, n_frames: int, seed: int, **options) -> list[np.ndarray]:
    out = []
    for name in list_scenes(None, n_scenes=n_scenes):
        scene = open_scene(None, name, seed=seed, n_frames=max(n_frames * 7, 40), **options)
        for i in np.linspace(0, len(scene) - 1, n_frames).round().astype(int):
            out.append(scene.read(int(i)).depth_m)
    return out


def _parse_set(items):
    opts = {}
    for item in items:
        key, _, value = item.partition("=")
        try:
            opts[key] = int(value)
        except ValueError:
            opts[key] = float(value)
    return opts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fixture", type=Path, default=REPO.parent / "shared/data/7scenes-kitchen")
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--csv", type=Path)
    ap.add_argument("--set", nargs="*", default=[], help="synthetic options key=value")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    t0 = time.perf_counter()
    real = sensor_statistics(real_depths(args.fixture))
    t1 = time.perf_counter()
    synth = sensor_statistics(synthetic_depths(args.scenes, args.frames, args.seed, **_parse_set(args.set)))
    t2 = time.perf_counter()
    table = compare_statistics(real, synth)
    table["within_1.5"] = (table["ratio"] <= 1.5) & (table["ratio"] >= 1 / 1.5)
    pd.set_option("display.width", 160)
    fmt = table.copy()
    for col in ("real", "synthetic"):
        fmt[col] = [f"{v * 1000:.2f} mm" if u == "m" else f"{v * 100:.2f} %" for v, u in zip(table[col], table["unit"])]
    fmt["ratio"] = table["ratio"].round(3)
    print(fmt.drop(columns=["unit"]).to_string(index=False))
    print(
        f"real: {args.fixture} ({t1 - t0:.1f} s); synthetic: {args.scenes} rooms x {args.frames} frames, seed {args.seed} ({t2 - t1:.1f} s)"
    )
    bad = table[table["comparable"] & ~table["within_1.5"]]
    print("all comparable ratios within a factor 1.5" if bad.empty else f"{len(bad)} ratio(s) outside a factor 1.5")
    if args.csv:
        table.to_csv(args.csv, index=False)
    return 0 if bad.empty else 1


if __name__ == "__main__":
    sys.exit(main())
