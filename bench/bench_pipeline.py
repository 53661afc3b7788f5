"""Per-stage time and peak memory of the per-frame-set job (everything but registration).

    python3 bench/bench_pipeline.py [--framesets 10] [--device cpu] [--threads 1]

As the workflow does it: the scene index job reads and checks every frame of the first
default synthetic scene (config/config.yaml) and writes the frame cache (timed per
frame); then ``depthgt.gt.build.process_frameset`` with ``registration.method: given``
runs on frame sets from that cache. Prints the per-stage mean time, the total per frame
set, and the peak resident memory of the process. Target (issue 2): <= 2 s per frame
set on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import yaml

from depthgt.gt.cache import CachedScene, FrameCacheWriter
from depthgt.gt.build import FrameSetOutputs, process_frameset
from depthgt.gt.index import build_index
from depthgt.jobs.common import open_source_scene
from depthgt.settings import settings_from_config

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--framesets", type=int, default=10)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (the workflow runs one frame-set job per core, 1 thread each)")
    ap.add_argument("--config", default=str(ROOT / "config/config.yaml"))
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    config = yaml.safe_load(Path(args.config).read_text())
    config["device"] = args.device
    settings = settings_from_config(config)
    fs = settings.frameset
    src = config["sources"][0]
    scene = open_source_scene(src, src["scenes"][0])
    targets = list(range(fs.reach, len(scene) - fs.reach, max(1, (len(scene) - 2 * fs.reach) // args.framesets)))[: args.framesets]
    stages: dict[str, list[float]] = {}
    totals = []
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        cache = FrameCacheWriter(Path(tmp) / "frames", scene, settings.size_hw)
        build_index(scene, src["name"], "train", True, fs, settings.split, 0, cache=cache)
        cache.close()
        index_s = time.perf_counter() - start
        cached = CachedScene(Path(tmp) / "frames")
        for t in targets:
            members = [t + o for o in fs.offsets]
            start = time.perf_counter()
            process_frameset(cached, src["name"], t, members, "train", FrameSetOutputs.in_dir(Path(tmp) / f"{t:06d}"), settings)
            totals.append(time.perf_counter() - start)
            timings = json.loads((Path(tmp) / f"{t:06d}" / "poses.json").read_text())["timings_s"]
            for k, v in timings.items():
                stages.setdefault(k, []).append(v)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"command: {' '.join([Path(sys.argv[0]).name] + sys.argv[1:])}")
    print(f"device {args.device}, torch threads {args.threads}, {len(targets)} frame sets of {src['name']}/{src['scenes'][0]}")
    print("| stage | mean s | max s |\n|---|---:|---:|")
    for k, v in stages.items():
        print(f"| {k} | {np.mean(v):.3f} | {np.max(v):.3f} |")
    print(f"| total per frame set (first excluded: warm-up) | {np.mean(totals[1:] or totals):.3f} | {np.max(totals):.3f} |")
    print(f"scene index + frame cache: {index_s / len(scene):.3f} s per frame ({len(scene)} frames, source read included)")
    print(f"peak RSS: {peak_mb:.0f} MiB")


if __name__ == "__main__":
    main()
