"""The enhancement defaults' selection protocol (issue 8): how many training rooms and
how many LapDEN epochs, chosen on VALIDATION frames only, then reported once on test.

    python3 bench/bench_enhance_protocol.py                        # rooms 3 5 8 x epochs 10 20 30 45
    python3 bench/bench_enhance_protocol.py --rooms 8 --train-only # fill one room count's cache (parallel runs)
    python3 bench/bench_enhance_protocol.py --model ddrnet --rooms 8 --epochs 2 5 10 20 30
    python3 bench/bench_enhance_protocol.py --model sdd --rooms 8 --epochs 3 5 10 20 30

``--model`` picks the trained model whose epochs are chosen (LapDEN by default; DDRNet and
SDD, the learned baselines, on the training rooms chosen for LapDEN, so that every learned
method of Table 3 has its epochs chosen by the same rule on the same validation frames).

Training runs sharing the cache of one room count must not run at the same time (one
run folder per room count); different room counts may.

Steps (every expensive result is cached under ``--work``, default /tmp/depthgt_enhance_protocol):

1. Dataset: the workflow's ``dataset`` target (``snakemake -s Snakefile -d WORK/build
   --cores 2 dataset``) on config/config.yaml with the ``synthetic`` source set to the
   largest candidate (room_000 .. room_007); everything else as in the config. The
   ``split: auto`` source cuts each room into train and val blocks (config ``split``),
   and the per-room splits do not depend on which rooms are built, so the candidates
   with fewer rooms are the first N rooms' rows of its manifests (what a build with N
   rooms writes).
2. Training: for each room count, :func:`depthgt.enhance.train.train` with the config's
   LapDEN settings (``enhance.train`` + ``enhance.models.lapden``) on the first N rooms'
   training patches, validation loss on their val patches (what the workflow's
   ``train_model`` rule does). The run is taken to each epoch candidate in turn,
   resuming from ``last.pt`` (identical to an uninterrupted run: the shuffling of an
   epoch depends only on the seed and the epoch; tests/test_enhance.py
   ``test_train_resume_equals_uninterrupted``), and ``best.pt`` is copied after each
   stage: the checkpoint a build with that many epochs evaluates.
3. Validation score (the only input of the choice): each candidate's ``best.pt`` on the
   full 256x256 frames of the val-split frame sets of ALL candidate rooms (the same
   frames for every candidate; rooms a candidate did not train on measure
   generalisation; with the default 48 frames and 24-frame blocks, rooms whose val
   phase falls beyond the second block have none), against the clean synthetic truth
   with the project's evaluation (:func:`depthgt.eval.evaluate.evaluate_frames`, Table
   3's conventions: mean over frames of per-frame RMSE with missing pixels counted).
   The val blocks are disjoint from every training patch. The test source is built by
   the ``dataset`` target like every source but not read before the choice.
4. Choice: the lowest mean validation RMSE (missing counted); a cheaper candidate
   (rooms x epochs) within ``--tolerance`` (1 %) of it is preferred.
5. Test, reported and not chosen on: the chosen setting (and the config's current
   default, and ``--also-report`` ones, when they differ) on the test source's frames
   (room_100) against the truth, as Table 3 (:func:`depthgt.eval.tables.table3`).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pandas as pd
import torch
import yaml

from depthgt.enhance.train import TrainOutputs, train
from depthgt.eval.evaluate import evaluate_frames, method_spec
from depthgt.eval.tables import table3
from depthgt.settings import settings_from_config

REPO = Path(__file__).resolve().parents[1]
SOURCE = "synthetic"  # the config's training source (split: auto)
ROOMS = [f"room_{i:03d}" for i in range(8)]
SCORES = ["rmse_missing_counted_m", "mae_missing_counted_m", "rmse_m", "mae_m", "completeness"]
PRIMARY = "rmse_missing_counted_m"


# ---------------------------------------------------------------------------- dataset


def build_config(n_rooms: int) -> dict:
    """config/config.yaml with the training source holding the first ``n_rooms`` of ROOMS."""
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    src = next((s for s in cfg["sources"] if s["name"] == SOURCE), None)
    if src is None or src.get("split") != "auto":
        raise SystemExit(f"config/config.yaml: no source {SOURCE!r} with split: auto")
    src["scenes"] = ROOMS[:n_rooms]
    return cfg


def build_dataset(work: Path, n_rooms: int) -> tuple[dict, Path]:
    """Run the workflow's ``dataset`` target in ``work/build`` (a no-op when up to date)."""
    wd = work / "build"
    cfg = build_config(n_rooms)
    (wd / "config").mkdir(parents=True, exist_ok=True)
    path = wd / "config" / "config.yaml"
    text = yaml.safe_dump(cfg, sort_keys=False)
    if not path.is_file() or path.read_text() != text:
        path.write_text(text)
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "-d", str(wd), "--cores", "2", "dataset"]
    env = dict(os.environ, PYTHONPATH=str(REPO / "src"))
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"snakemake failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    print(f"dataset: {' '.join(cmd[1:])} ({time.perf_counter() - t0:.0f} s)")
    return cfg, wd / "results" / "dataset"


def manifests(dataset_dir: Path, rooms: list[str]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The training and val patch manifests of the training source restricted to ``rooms``."""
    out = []
    for split in ("train", "val"):
        t = pd.read_parquet(dataset_dir / f"{split}.parquet")
        out.append(t[(t["dataset"] == SOURCE) & t["scene"].isin(rooms)].reset_index(drop=True))
    return out[0], out[1]


# ---------------------------------------------------------------------------- training


def train_stages(
    cfg: dict, dataset_dir: Path, n_rooms: int, epochs: list[int], work: Path, device: str, model: str = "lapden"
) -> dict[int, Path]:
    """``best.pt`` of a ``model`` run on the first ``n_rooms`` rooms after each epoch count
    (cached: ``work/models/rooms{N}/e{E}/`` for LapDEN, ``work/models/{model}/rooms{N}/...``
    for the others)."""
    base = settings_from_config(cfg).train(model)
    train_m, val_m = manifests(dataset_dir, ROOMS[:n_rooms])
    root = work / "models" / (f"rooms{n_rooms}" if model == "lapden" else f"{model}/rooms{n_rooms}")
    run = TrainOutputs.in_dir(root / "run")
    snaps = {}
    for e in sorted(epochs):
        snap = root / f"e{e:03d}"
        if (snap / "best.pt").is_file():
            snaps[e] = snap / "best.pt"
            continue
        if run.last.is_file() and torch.load(run.last, map_location="cpu", weights_only=False)["epoch"] + 1 > e:
            shutil.rmtree(root / "run")  # the run went past this stage without a copy: start again
        t0 = time.perf_counter()
        res = train(train_m, val_m, run, replace(base, epochs=e, device=device, progress=False))
        snap.mkdir(parents=True, exist_ok=True)
        for p in run:
            shutil.copy2(p, snap / p.name)
        print(
            f"trained {model} rooms={n_rooms} to epoch {e}: {res['epochs_run']} epochs in {time.perf_counter() - t0:.0f} s, "
            f"{len(train_m)} train / {len(val_m)} val patches, best epoch {res['best_epoch'] + 1} "
            f"(val loss {res['best_val']:.5f})",
            flush=True,
        )
        snaps[e] = snap / "best.pt"
    return snaps


# ---------------------------------------------------------------------------- scoring


def _digest(path: Path) -> str:
    return hashlib.sha1(path.read_bytes()).hexdigest()[:16]


def score(
    frames: pd.DataFrame, split: str, checkpoint: Path | None, work: Path, device: str, model: str = "lapden"
) -> pd.DataFrame:
    """Long evaluation table of ``model``'s ``checkpoint`` (None: the raw input) on the
    ``split`` frames of ``frames``, against the truth (cached by checkpoint content)."""
    tag = _digest(checkpoint) if checkpoint is not None else "input"
    keys = "-".join(sorted(frames["dataset"].unique()))
    cache = work / "scores" / f"{split}-{keys}-{tag}.parquet"
    if cache.is_file():
        return pd.read_parquet(cache)
    name = model if checkpoint is not None else "input"
    spec = method_spec(model, checkpoint, device=device) if checkpoint is not None else {"image": "input"}
    ev = evaluate_frames(frames, {name: spec}, references=("truth",), split=split)
    cache.parent.mkdir(parents=True, exist_ok=True)
    ev.to_parquet(cache, index=False)
    return ev


def frame_means(ev: pd.DataFrame, by: list[str] | None = None) -> pd.DataFrame:
    """Mean over frames of per-frame values of :data:`SCORES` (Table 3's convention)."""
    ev = ev[ev["metric"].isin(SCORES)]
    keys = list(dict.fromkeys((by or []) + ["dataset", "scene", "target"]))
    wide = ev.pivot_table(index=keys, columns="metric", values="value").reset_index()
    if by:
        out = wide.groupby(by)[SCORES].mean()
        out["frames"] = wide.groupby(by).size()
        return out.reset_index()
    return pd.DataFrame([{**wide[SCORES].mean().to_dict(), "frames": len(wide)}])


def choose(table: pd.DataFrame, tolerance: float, primary: str = PRIMARY) -> pd.Series:
    """The candidate with the lowest ``primary`` score; the cheapest (rooms x epochs)
    within ``tolerance`` (relative) of it is preferred."""
    best = table[primary].min()
    near = table[table[primary] <= best * (1 + tolerance)].copy()
    near["cost"] = near["rooms"] * near["epochs"]
    return near.sort_values(["cost", primary]).iloc[0]


# ---------------------------------------------------------------------------- main


def _markdown(table: pd.DataFrame) -> str:
    """Markdown with integers as integers and other numbers to 4 decimals."""

    def cell(v):
        return f"{v:.4f}" if isinstance(v, float) else str(v)

    return table.astype(object).map(cell).to_markdown(index=False, disable_numparse=True)


def _pair(text: str) -> tuple[int, int]:
    rooms, _, epochs = text.partition(":")
    return int(rooms), int(epochs)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--rooms", type=int, nargs="+", default=[3, 5, 8], help="training room counts (first N of room_000..007)"
    )
    ap.add_argument(
        "--model",
        default="lapden",
        choices=["lapden", "ddrnet", "sdd"],
        help="the trained model whose epochs (and with --rooms, training rooms) are chosen",
    )
    ap.add_argument("--epochs", type=int, nargs="+", default=[10, 20, 30, 45], help="epoch candidates")
    ap.add_argument(
        "--extra",
        nargs="*",
        default=[],
        metavar="ROOMS:EPOCHS",
        help="candidates beyond the grid --rooms x --epochs (e.g. 8:45 when time allows one long run)",
    )
    ap.add_argument(
        "--score",
        default=PRIMARY,
        choices=SCORES[:4],
        help="the validation score chosen on (lower is better). The default, RMSE with missing pixels "
        "counted, suits methods that fill holes; for one that keeps the input's holes (DDRNet) it "
        "equals the input's whatever the training, so use rmse_m, the RMSE where it has depth",
    )
    ap.add_argument(
        "--tolerance",
        type=float,
        default=0.01,
        help="prefer the cheapest candidate within this relative margin of the best validation score",
    )
    ap.add_argument(
        "--also-report",
        nargs="*",
        default=None,
        metavar="ROOMS:EPOCHS",
        help="settings reported on test next to the choice (not chosen on); default: 8:30 for LapDEN "
        "(its previous default), none for the others (the config default is always reported)",
    )
    ap.add_argument(
        "--train-only", action="store_true", help="train and cache the checkpoints of --rooms, score nothing"
    )
    ap.add_argument("--work", type=Path, default=Path("/tmp/depthgt_enhance_protocol"))
    ap.add_argument("--threads", type=int, default=2, help="torch threads (the train rule's 2)")
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args(argv)
    print(
        f"command: python3 bench/bench_enhance_protocol.py {' '.join(sys.argv[1:] if argv is None else argv)}",
        flush=True,
    )
    torch.set_num_threads(a.threads)
    if max(a.rooms) > len(ROOMS) or min(a.rooms) < 1:
        raise SystemExit(f"--rooms must be in 1..{len(ROOMS)}")

    a.work = a.work.resolve()
    cfg, dataset_dir = build_dataset(a.work, len(ROOMS))
    os.chdir(dataset_dir.parents[1])  # the manifests hold frame-set locations relative to the build folder
    default_cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    default_rooms = len(next(s for s in default_cfg["sources"] if s["name"] == SOURCE)["scenes"])
    default_epochs = settings_from_config(default_cfg).train(a.model).epochs
    if a.also_report is None:
        a.also_report = ["8:30"] if a.model == "lapden" else []
    reported = {(default_rooms, default_epochs)} | {_pair(r) for r in a.also_report}
    candidates = sorted({(n, e) for n in a.rooms for e in a.epochs} | {_pair(r) for r in a.extra})
    stages: dict[int, set[int]] = {}
    for n, e in set(candidates) | reported:
        stages.setdefault(n, set()).add(e)
    if a.train_only:
        for n in dict.fromkeys(a.rooms):
            train_stages(cfg, dataset_dir, n, sorted(stages[n]), a.work, a.device, a.model)
        return
    checkpoints = {
        (n, e): p
        for n in sorted(stages)
        for e, p in train_stages(cfg, dataset_dir, n, sorted(stages[n]), a.work, a.device, a.model).items()
    }

    # ---- validation: the val frame sets of every candidate room, nothing else
    fs = pd.read_parquet(dataset_dir / "framesets.parquet")
    val_frames = fs[
        (fs["dataset"] == SOURCE) & fs["scene"].isin(ROOMS[: max(n for n, _ in candidates)]) & (fs["split"] == "val")
    ]
    rows, per_room = [], []
    inp = frame_means(score(val_frames, "val", None, a.work, a.device))
    for n, e in candidates:
        ckpt = checkpoints[(n, e)]
        ev = score(val_frames, "val", ckpt, a.work, a.device, a.model)
        best_epoch = torch.load(ckpt, map_location="cpu", weights_only=False)["best_epoch"] + 1
        rows.append({"rooms": n, "epochs": e, "best_epoch": best_epoch, **frame_means(ev).iloc[0].to_dict()})
        room = frame_means(ev, ["scene"]).set_index("scene")[a.score]
        per_room.append(
            {"rooms": n, "epochs": e, **{sc: f"{v:.4f}{'*' if sc in ROOMS[:n] else ''}" for sc, v in room.items()}}
        )
    val = pd.DataFrame(rows).astype({"rooms": int, "epochs": int, "best_epoch": int, "frames": int})
    pd.set_option("display.width", 250)
    scenes = sorted(val_frames["scene"].unique())
    print(
        f"\nVALIDATION ({len(val_frames[val_frames['status'] == 'ok'])} val frame sets of {', '.join(scenes)}; "
        f"full 256x256 frames vs the clean truth; means over frames; best_epoch: the epoch of best.pt, "
        f"chosen by the patch validation loss as in the workflow). Raw input: RMSE missing counted "
        f"{inp[PRIMARY].iloc[0]:.4f} m, MAE missing counted {inp['mae_missing_counted_m'].iloc[0]:.4f} m, "
        f"RMSE {inp['rmse_m'].iloc[0]:.4f} m"
    )
    print(_markdown(val))
    print(
        f"\nvalidation {a.score} (m) per room (* = the candidate trained on that room's train blocks; "
        "rooms without a column have no val block):"
    )
    print(_markdown(pd.DataFrame(per_room)))
    pick = choose(val, a.tolerance, a.score)
    chosen = (int(pick["rooms"]), int(pick["epochs"]))
    print(
        f"\nCHOICE (lowest validation {a.score}, cheapest within {a.tolerance:.0%}): rooms={chosen[0]} "
        f"(room_000..{ROOMS[chosen[0] - 1]}), {a.model} epochs={chosen[1]} ({pick[a.score]:.4f} m)"
    )

    # ---- test, reported once, after the choice
    tests = {d["name"]: d["kind"] for d in cfg["sources"] if d.get("split") == "test"}
    test_frames = fs[fs["dataset"].isin(list(tests))]
    default = (default_rooms, default_epochs)
    settings = [(chosen, "chosen on validation" + (" (= config default)" if chosen == default else ""))] + [
        (r, "config default, reported not chosen" if r == default else "reported, not chosen")
        for r in sorted(reported - {chosen})
    ]
    out = []
    for (n, e), label in settings:
        ev = score(test_frames, "test", checkpoints[(n, e)], a.work, a.device, a.model)
        t3 = table3(ev.assign(method=f"{a.model} rooms={n} epochs={e}"), tests)
        out.append(t3.assign(setting=label))
    inp_t = table3(score(test_frames, "test", None, a.work, a.device).assign(method="input"), tests)
    out.append(inp_t.assign(setting="raw input"))
    print(
        f"\nTEST (Table 3 style: {', '.join(sorted(test_frames['scene'].unique()))} vs the clean truth; "
        f"reported, never used for the choice)"
    )
    print(_markdown(pd.concat(out, ignore_index=True)))


if __name__ == "__main__":
    main()
