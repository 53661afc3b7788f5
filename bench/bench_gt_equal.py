"""Is the GT of this checkout the GT of another? The same frame sets built by both, pixel by pixel.

    python3 bench/bench_gt_equal.py --against /tmp/base                      # synthetic, 7-Scenes, TUM; given, refine
    python3 bench/bench_gt_equal.py --against /tmp/base --data 7scenes --modes fast --framesets 4

Each checkout builds the same consecutive frame sets of each recording and mode in a
process of its own (``depthgt.gt.build.process_frameset`` through the batch's frame cache,
as ``bench/bench_pipeline.py`` does, one torch thread), and keeps each target's GT depth
and confidence as the renderer made them (float32, before the shard's fixed point) and
its ``frameset.json`` (consecutive targets sharing one per-frame cache, as a batch job
does). Printed per (recording, mode): the GT pixels valid in both, those
valid in one only, the share of the shared ones within the storage precision
(``--tol-m``, default 30.5 um: half the step of ``depthgt.gt.store.GT_UNITS``), the
largest difference, the neighbours' poses' largest difference and the frame sets'
statistics side by side (leave-target-out MAE on real data, error against the truth on
synthetic data). ``--against`` takes a checkout's folder (``git worktree add /tmp/base
66103d4``); its ``src/`` is imported by its process.

Data: the default config's first synthetic scene and the two shared recordings in
``../shared/data`` (7-Scenes kitchen, TUM fr1/xyz).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

if __name__ == "__main__" and "--src" in sys.argv:  # run another checkout's library (see --against)
    sys.path.insert(0, sys.argv[sys.argv.index("--src") + 1])

import numpy as np
import pandas as pd
from bench_pipeline import MODES  # the same pose modes and recordings as the pipeline bench
from bench_pipeline import sources as _sources

ROOT = Path(__file__).resolve().parents[1]
#: half the step of the shard's fixed-point depth (depthgt.gt.store.GT_UNITS["Z"] = 2^14 per metre)
STORAGE_PRECISION_M = 0.5 / 2**14


def worker(out: Path, data: str, mode: str, n: int, selection: str, config_path: Path) -> None:
    """Build the frame sets with the library on ``sys.path`` and keep the raw GT of each (npz)."""
    import torch
    import yaml

    from depthgt.gt import build
    from depthgt.gt.cache import ResizedScene
    from depthgt.jobs.common import open_source_scene
    from depthgt.settings import settings_from_config

    torch.set_num_threads(1)
    config = yaml.safe_load(config_path.read_text())
    config["device"] = "cpu"
    config["frameset"] = {**config.get("frameset", {}), "selection": selection}
    source, scene_name = _sources(config)[data]
    settings = settings_from_config({**config, "registration": MODES[mode], "sources": [source]})
    fs = settings.frameset
    need = settings.registration.uses_source_poses
    span = max(fs.reach, fs.coverage_span) if selection == "coverage" else fs.reach
    scene = ResizedScene(open_source_scene(source, scene_name, need_poses=need), settings.size_hw, keep=2 * span + 2)
    kept: dict[int, dict[str, np.ndarray]] = {}
    original = build.stored_images

    def keeping(data_, rendered, out_):  # the render before the shard's fixed point
        gt = getattr(rendered, "gt", rendered)  # a Fusion (this checkout) or a GTRender (older ones)
        kept[int(out_.gt.parent.name)] = {
            "Z": gt.depth[0, 0].detach().cpu().numpy().astype(np.float32),
            "S": gt.sigma[0, 0].detach().cpu().numpy().astype(np.float32),
        }
        return original(data_, rendered, out_)

    build.stored_images = keeping
    try:  # the batch job's per-frame cache, as the batch job keeps it (absent in older checkouts)
        from depthgt.framecache import FrameCache

        shared = {"cache": FrameCache(keep=2 * span + 2)}
    except ImportError:
        shared = {}
    for t in range(fs.reach, min(len(scene) - fs.reach, fs.reach + n)):
        target_dir = out / f"{t:06d}"
        doc = build.process_frameset(
            scene, source["name"], t, [t + o for o in fs.offsets], "train", build.FrameSetOutputs.in_dir(target_dir),
            settings, **shared,
        )  # fmt: skip
        poses = json.loads((target_dir / "poses.json").read_text())
        np.savez(
            out / f"{t:06d}.npz",
            **kept.pop(t),
            T=np.asarray([poses["T_j_to_t"][k] for k in sorted(poses["T_j_to_t"], key=int)], dtype=np.float64),
        )
        (out / f"{t:06d}.json").write_text(json.dumps(doc["statistics"]))


def _build(src: Path | None, out: Path, data: str, mode: str, a: argparse.Namespace) -> None:
    cmd = [sys.executable, __file__, "--worker", str(out), "--data", data, "--modes", mode]
    cmd += ["--framesets", str(a.framesets), "--selection", a.selection]
    env = dict(os.environ)
    if src is not None:
        cmd += ["--src", str(src / "src"), "--config", str(src / "config/config.yaml")]
        env["PYTHONPATH"] = str(src / "src")
    else:
        cmd += ["--config", str(ROOT / "config/config.yaml")]
    subprocess.run(cmd, check=True, env=env, cwd=str(src or ROOT))


def _stat(doc: dict) -> float:
    for key in ("leave_target_out", "gt_vs_truth_input_valid"):
        if key in doc:
            return 1000 * float(doc[key]["mae_m"])
    return float("nan")


def compare(this: Path, other: Path, tol_m: float) -> dict:
    both = only = within = total = 0
    worst = pose = 0.0
    mae_this, mae_other = [], []
    for f in sorted(this.glob("*.npz")):
        a, b = np.load(f), np.load(other / f.name)
        va, vb = a["Z"] > 0, b["Z"] > 0
        shared = va & vb
        d = np.abs(a["Z"][shared].astype(np.float64) - b["Z"][shared])
        both += int(shared.sum())
        only += int((va ^ vb).sum())
        within += int((d <= tol_m).sum())
        total += a["Z"].size
        worst = max(worst, float(d.max()) if d.size else 0.0)
        if a["T"].shape == b["T"].shape and a["T"].size:
            pose = max(pose, float(np.abs(a["T"] - b["T"]).max()))
        mae_this.append(_stat(json.loads(f.with_suffix(".json").read_text())))
        mae_other.append(_stat(json.loads((other / f.name).with_suffix(".json").read_text())))
    return {
        "framesets": len(mae_this),
        "pixels valid in both": both,
        "valid in one only": only,
        "share of all pixels valid in one only": only / max(total, 1),
        "share within precision": within / max(both, 1),
        "max |diff| um": 1e6 * worst,
        "max |pose diff|": pose,
        "MAE mm (this)": float(np.nanmean(mae_this)) if mae_this else float("nan"),
        "MAE mm (against)": float(np.nanmean(mae_other)) if mae_other else float("nan"),
    }


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--against", type=Path, help="the other checkout's folder (its src/ and config/ are used)")
    ap.add_argument(
        "--data", nargs="+", default=["synthetic", "7scenes", "tum"], choices=["synthetic", "7scenes", "tum"]
    )
    ap.add_argument("--modes", nargs="+", default=["given", "refine"], choices=list(MODES))
    ap.add_argument("--framesets", type=int, default=8, help="consecutive targets per recording")
    ap.add_argument("--selection", default="window", choices=["window", "coverage"])
    ap.add_argument("--tol-m", type=float, default=STORAGE_PRECISION_M, help="the storage precision (metres)")
    ap.add_argument("--worker", type=Path, help=argparse.SUPPRESS)  # internal: build into this folder
    ap.add_argument("--src", help=argparse.SUPPRESS)  # internal: the library this process runs
    ap.add_argument("--config", type=Path, default=ROOT / "config/config.yaml", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker is not None:
        a.worker.mkdir(parents=True, exist_ok=True)
        worker(a.worker, a.data[0], a.modes[0], a.framesets, a.selection, a.config)
        return
    if a.against is None:
        ap.error("--against CHECKOUT is required")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for data in a.data:
            for mode in a.modes:
                mine, theirs = Path(tmp) / f"{data}-{mode}-this", Path(tmp) / f"{data}-{mode}-against"
                _build(None, mine, data, mode, a)
                _build(a.against, theirs, data, mode, a)
                rows.append({"data": data, "mode": mode, **compare(mine, theirs, a.tol_m)})
    print(f"command: python3 bench/bench_gt_equal.py {' '.join(sys.argv[1:] if argv is None else argv)}")
    print(f"this checkout against {a.against}; tolerance {a.tol_m * 1e6:.1f} um, selection {a.selection}")
    print(pd.DataFrame(rows).to_markdown(index=False, floatfmt=".6g"))


if __name__ == "__main__":
    main()
