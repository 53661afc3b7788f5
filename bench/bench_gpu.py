"""Frame sets per second on a GPU: a batch's sets built one at a time against together.

    python3 bench/bench_gpu.py                                   # 7-Scenes and synthetic; given, refine, fast
    python3 bench/bench_gpu.py --data synthetic --modes given --framesets 32 --group 16
    python3 bench/bench_gpu.py --device cpu --framesets 4 --group 2  # the same paths on the CPU (a dry run)

As a frame-set batch job builds them (``depthgt.gt.build.process_framesets`` on
consecutive targets through the batch's frame cache, ``depthgt.framecache.FrameCache``):
once one set per call (every set read, aligned, rendered and written on its own), once
``--group`` sets per call (their GTs rendered in one pass of the rasteriser and the
compositor, ``depthgt.gt.render.fusion.fuse_sets``; ``refine`` registers them together,
``depthgt.registration.refine.refine_poses_many``). Printed per (recording, mode): wall
seconds per set and sets per second of the whole build and of its render step alone
(from poses.json's timings), the share of the two paths' GT pixels within the storage
precision (30.5 um), those valid in one only and the largest difference, and, with
``--compare-cpu``, the same share against the sets built on the CPU. Each timing
follows a warm-up group.

Data: the 7-Scenes fixture (``--shared``/data/7scenes-kitchen, default ../shared) and the
default config's first synthetic scene.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
import yaml

from depthgt.framecache import FrameCache
from depthgt.gt import build
from depthgt.gt.cache import ResizedScene
from depthgt.jobs.common import open_source_scene
from depthgt.settings import settings_from_config

ROOT = Path(__file__).resolve().parents[1]
MODES = {"given": {"method": "given"}, "refine": {"method": "refine"}, "fast": {"method": "overfit", "preset": "fast"}}
STORAGE_PRECISION_M = 0.5 / 2**14


def _source(data: str, config: dict, shared: Path) -> tuple[dict, str]:
    if data == "7scenes":
        return {
            "name": "7scenes",
            "kind": "sevenscenes",
            "root": str(shared / "data/7scenes-kitchen"),
        }, "7scenes-kitchen"
    default = config["sources"][0]
    return default, default["scenes"][0]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def run(data: str, mode: str, device: str, n: int, group: int, config: dict, shared: Path, keep: dict) -> dict:
    config = {**config, "device": device}
    source, scene_name = _source(data, config, shared)
    settings = settings_from_config({**config, "registration": MODES[mode], "sources": [source]})
    fs = settings.frameset
    need = settings.registration.uses_source_poses
    scene = ResizedScene(
        open_source_scene(source, scene_name, need_poses=need), settings.size_hw, keep=2 * fs.reach + 2 + group
    )
    targets = list(range(fs.reach, min(len(scene) - fs.reach, fs.reach + group + n)))
    warm, timed = targets[:group], targets[group:]
    fids = {t: build.FrameSetId(source["name"], scene.name, t, [t + o for o in fs.offsets], "train") for t in targets}
    row: dict = {"data": data, "mode": mode, "sets": len(timed)}
    with tempfile.TemporaryDirectory() as tmp:
        for label, size in (("one at a time", 1), ("together", group)):
            cache = FrameCache(keep=2 * fs.reach + 1 + group)

            def go(ts: list[int], size: int = size, label: str = label, cache: FrameCache = cache) -> None:
                for i in range(0, len(ts), size):
                    part = [fids[t] for t in ts[i : i + size]]
                    outs = [build.FrameSetOutputs.in_dir(Path(tmp) / label / f"{f.target:06d}") for f in part]
                    build.process_framesets(scene, part, outs, settings, None, None, cache)

            go(warm)
            _sync(torch.device(device))
            t0 = time.perf_counter()
            go(timed)
            _sync(torch.device(device))
            wall = (time.perf_counter() - t0) / max(len(timed), 1)
            render = np.mean(
                [
                    json.loads((Path(tmp) / label / f"{t:06d}" / "poses.json").read_text())["timings_s"]["render"]
                    for t in timed
                ]
            )
            row[f"{label}: s/set"] = wall
            row[f"{label}: sets/s"] = 1.0 / wall
            row[f"{label}: render sets/s"] = 1.0 / max(render, 1e-9)
        diff, within, only = 0.0, [], 0
        for t in targets:
            a = keep.setdefault((data, mode, device, t), _gt(Path(tmp) / "one at a time" / f"{t:06d}"))
            b = _gt(Path(tmp) / "together" / f"{t:06d}")
            both = (a > 0) & (b > 0)
            d = np.abs(a - b)[both]
            diff = max(diff, float(d.max()) if d.size else 0.0)
            within.append(d <= STORAGE_PRECISION_M)
            only += int(((a > 0) ^ (b > 0)).sum())
        row["one vs together: share within 30.5 um"] = float(np.concatenate(within).mean()) if within else float("nan")
        row["one vs together: valid in one only"] = only
        row["one vs together: max |diff| um"] = 1e6 * diff
    return row


#: each target's GT depth as rendered (float32, before the shard's fixed point), by output folder
_RAW: dict[str, np.ndarray] = {}
_stored_images = build.stored_images


def _keeping(data, fusion, out):
    _RAW[str(out.gt.parent)] = fusion.gt.depth[0, 0].detach().cpu().numpy().astype(np.float64)
    return _stored_images(data, fusion, out)


build.stored_images = _keeping


def _gt(folder: Path) -> np.ndarray:
    return _RAW.pop(str(folder))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", nargs="+", default=["7scenes", "synthetic"], choices=["7scenes", "synthetic"])
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    ap.add_argument("--framesets", type=int, default=32, help="timed frame sets per (recording, mode)")
    ap.add_argument("--group", type=int, default=16, help="frame sets built together")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--compare-cpu", action="store_true", help="also build the sets on the CPU, GTs compared")
    ap.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    ap.add_argument("--out", type=Path, help="write the table as CSV here too")
    a = ap.parse_args(argv)
    config = yaml.safe_load((ROOT / "config/config.yaml").read_text())
    keep: dict = {}
    rows = []
    for data in a.data:
        for mode in a.modes:
            rows.append(run(data, mode, a.device, a.framesets, a.group, config, a.shared, keep))
            print(pd.DataFrame(rows[-1:]).to_markdown(index=False, floatfmt=".4g"), flush=True)
            if a.compare_cpu and a.device != "cpu":
                run(data, mode, "cpu", min(a.framesets, 4), 1, config, a.shared, keep)
                within = []
                for (d, m, dev, t), gt in list(keep.items()):
                    other = keep.get((d, m, "cpu", t))
                    if d == data and m == mode and dev != "cpu" and other is not None:
                        both = (gt > 0) & (other > 0)
                        within.append(
                            (
                                float((np.abs(gt - other)[both] <= STORAGE_PRECISION_M).mean()),
                                int(((gt > 0) ^ (other > 0)).sum()),
                            )
                        )
                rows[-1]["GPU vs CPU: share within 30.5 um"] = min(w for w, _ in within) if within else float("nan")
                rows[-1]["GPU vs CPU: valid in one only"] = max(v for _, v in within) if within else -1
    print(f"command: python3 bench/bench_gpu.py {' '.join(sys.argv[1:] if argv is None else argv)}")
    if torch.cuda.is_available():
        print(f"device: {torch.cuda.get_device_name()}, torch {torch.__version__}")
    table = pd.DataFrame(rows)
    print(table.to_markdown(index=False, floatfmt=".4g"))
    if a.out:
        table.to_csv(a.out, index=False)


if __name__ == "__main__":
    main()
