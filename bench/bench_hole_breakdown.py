"""Where the methods' filling errors come from (issue 27 item 5): Table 3's filling
column split by how far a pixel lies from the raw input's depth, and what each training GT
offers there.

    # a default build first (python3 -m snakemake --cores 2), then
    python3 bench/bench_hole_breakdown.py -d WORKDIR                  # LapDEN against RDE, SDD, input
    python3 bench/bench_hole_breakdown.py -d WORKDIR --methods lapden rde --against rde
    python3 bench/bench_hole_breakdown.py -d WORKDIR --reference tsdf   # real test frames (Table 2's references)

On every test frame set of the build (``results/dataset/framesets.parquet``, split
``test``), each truth-valid pixel goes to one class: ``input valid`` (the denoising
mask), or a hole of the raw input, by its distance to the nearest input pixel with depth
(``cv2.distanceTransform``, L2): ``hole <= 3 px``, ``hole 4-10 px``, ``hole > 10 px``. Per
class and method (the saved predictions, ``results/eval/predictions/METHOD``, scored against
the clean truth as Table 3 scores them, or with ``--reference`` against the frame set's
GT or a real frame's neighbours-only or TSDF reference as Table 2 scores them: a pixel
without a prediction counts as its reference depth): pixels, pooled RMSE and MAE (mm), and the share off by more than 0.1 m; and per
frame the mean squared and absolute errors of the class, the first method minus
``--against`` (and every other method) paired over the frames that have pixels of the class
(95 % percentile bootstrap over frames, 2000 resamples, seed 0,
:func:`depthgt.eval.bootstrap.bootstrap_means`). Per class also how much of it the
frame set's own GT (``gt``, the window's render) covers and its MAE there, and, over the
training rooms' frame sets, how much the window GT and the global-reconstruction GT of RDE
(``results/rde``) cover: what each method could learn there.

Writes ``--out``/classes.csv and prints Markdown tables. Nothing here is a test.
"""

from __future__ import annotations

import argparse
import glob
import os
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from depthgt.eval.bootstrap import bootstrap_means
from depthgt.gt import store
from depthgt.gt.references import read_reference_table

CLASSES = ("input valid", "hole <= 3 px", "hole 4-10 px", "hole > 10 px")


def classes(truth: np.ndarray, input_m: np.ndarray) -> dict[str, np.ndarray]:
    """Truth-valid pixels by class (see module docstring): name -> (H, W) bool."""
    valid = truth > 0
    has = input_m > 0
    # distance of every pixel to the nearest input pixel with depth (0 on them)
    dist = cv2.distanceTransform((~has).astype(np.uint8), cv2.DIST_L2, 3)
    hole = valid & ~has
    return {
        "input valid": valid & has,
        "hole <= 3 px": hole & (dist <= 3),
        "hole 4-10 px": hole & (dist > 3) & (dist <= 10),
        "hole > 10 px": hole & (dist > 10),
    }


def test_rows(workdir: Path, methods: list[str], reference: str = "truth") -> pd.DataFrame:
    """One row per test frame, class and method: pixels, sum of squared and absolute
    errors (m), pixels off by > 0.1 m, and the frame's GT coverage of the class; scored
    against ``reference`` (``truth``, ``gt``, or a real frame's ``neighbours`` / ``tsdf``)."""
    refs = read_reference_table(glob.glob(str(workdir / "results/references/*/*/references.parquet")))
    fs = pd.read_parquet(workdir / "results/dataset/framesets.parquet")
    fs = fs[(fs["split"] == "test") & (fs["status"] == "ok") & (fs["frameset"] != "")]
    if fs.empty:
        raise SystemExit(f"{workdir}: no test frame sets in results/dataset/framesets.parquet")
    rows, skipped = [], []
    for rec in fs.itertuples():
        frame = store.read_frame_images(str(workdir / rec.frameset))
        gt = frame.depth("gt")
        if reference in ("truth", "gt"):
            truth = frame.depth(reference)
        else:
            where = refs.get((str(rec.dataset), str(rec.scene), int(rec.target)), {}).get(reference)
            truth = np.load(workdir / where[0])[where[1]] if where else None
        if truth is None:
            skipped.append(f"{rec.scene}/{int(rec.target)}")
            continue
        if truth.shape != frame.input_m.shape:
            raise SystemExit(f"{rec.frameset}: reference {reference} {truth.shape}, input {frame.input_m.shape}")
        cls = classes(truth, frame.input_m)
        preds = {}
        for m in methods:
            f = (
                workdir
                / "results/eval/predictions"
                / m
                / str(rec.dataset)
                / str(rec.scene)
                / f"{int(rec.target):06d}.npy"
            )
            if not f.is_file():
                raise SystemExit(f"{f}: no saved prediction of {m} (run the build's evaluation first)")
            p = np.load(f)
            if p.shape != truth.shape:
                raise SystemExit(f"{f}: prediction {p.shape}, the frame's {reference} {truth.shape}")
            preds[m] = np.where(p > 0, p - truth, truth)  # a missing prediction counts as its truth depth
        for c, sel in cls.items():
            n = int(sel.sum())
            if not n:
                continue
            g = sel & (gt > 0) if gt is not None else np.zeros_like(sel)
            base = dict(frame=f"{rec.scene}/{int(rec.target)}", cls=c, n=n, gt_px=int(g.sum()))
            base["gt_ae"] = float(np.abs(gt - truth)[g].sum()) if g.any() else 0.0
            for m, err in preds.items():
                e = err[sel]
                rows.append(
                    dict(
                        base,
                        method=m,
                        se=float((e**2).sum()),
                        ae=float(np.abs(e).sum()),
                        big=int((np.abs(e) > 0.1).sum()),
                    )
                )
    if skipped:
        print(f"{len(skipped)} test frames without the reference {reference!r}, not scored: {', '.join(skipped[:10])}")
    return pd.DataFrame(rows)


def training_coverage(workdir: Path) -> pd.DataFrame:
    """Per class, over the training rooms' RDE frame sets: pixels, and the share and MAE
    of the window GT and of the global-reconstruction (RDE) GT there."""
    acc: dict[str, dict[str, float]] = {}
    for f in sorted(glob.glob(str(workdir / "results/rde/*/*/framesets.parquet"))):
        d = pd.read_parquet(f)
        for rec in d[d["status"] == "ok"].itertuples():
            w, r = store.read_frame_images(str(workdir / rec.frameset)), store.read_frame_images(str(workdir / rec.rde))
            truth = w.depth("truth")
            if truth is None:
                continue
            for c, sel in classes(truth, w.input_m).items():
                a = acc.setdefault(c, dict(pixels=0, window_px=0, window_ae=0.0, rde_px=0, rde_ae=0.0))
                a["pixels"] += int(sel.sum())
                for k, g in (("window", w.depth("gt")), ("rde", r.depth("gt"))):
                    s = sel & (g > 0)
                    a[f"{k}_px"] += int(s.sum())
                    a[f"{k}_ae"] += float(np.abs(g - truth)[s].sum())
    out = []
    for c in CLASSES:
        if c in acc:
            a = acc[c]
            out.append(
                {
                    "class": c,
                    "pixels": a["pixels"],
                    "window GT covers": f"{100 * a['window_px'] / max(a['pixels'], 1):.1f} %",
                    "window GT MAE mm": round(1000 * a["window_ae"] / max(a["window_px"], 1), 1),
                    "RDE GT covers": f"{100 * a['rde_px'] / max(a['pixels'], 1):.1f} %",
                    "RDE GT MAE mm": round(1000 * a["rde_ae"] / max(a["rde_px"], 1), 1),
                }
            )
    return pd.DataFrame(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-d", "--workdir", type=Path, required=True, help="a default build (results/dataset, results/eval)")
    ap.add_argument("--methods", nargs="+", default=["lapden", "rde", "sdd", "input"], help="the first is compared")
    ap.add_argument("--against", default=None, help="method the first is paired with (default: every other)")
    ap.add_argument(
        "--reference", default="truth", choices=["truth", "gt", "neighbours", "tsdf"], help="scored against"
    )
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_hole_breakdown"))
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    os.chdir(a.workdir)
    df = test_rows(Path("."), a.methods, a.reference)
    if df.empty:
        raise SystemExit(f"{a.workdir}: no test frame has the reference {a.reference!r}")
    df.to_csv(a.out / "classes.csv", index=False)
    first = a.methods[0]
    others = [a.against] if a.against else a.methods[1:]
    print(
        f"command: python3 bench/bench_hole_breakdown.py -d {a.workdir} --methods {' '.join(a.methods)} "
        f"--reference {a.reference}"
    )
    frames = df[df.method == first].groupby("cls")
    print(f"\nTEST frames: classes of the {a.reference}-valid pixels, and the frame sets' own (window) GT there")
    gt = frames.agg(frames=("frame", "nunique"), pixels=("n", "sum"), gt_px=("gt_px", "sum"), gt_ae=("gt_ae", "sum"))
    gt["GT covers"] = (100 * gt.gt_px / gt.pixels).map("{:.1f} %".format)
    gt["GT MAE mm"] = (1000 * gt.gt_ae / gt.gt_px.clip(lower=1)).round(1)
    print(
        gt.reindex([c for c in CLASSES if c in gt.index])[["frames", "pixels", "GT covers", "GT MAE mm"]].to_markdown()
    )
    pooled = df.groupby(["cls", "method"]).sum(numeric_only=True)
    pooled["RMSE mm"] = (1000 * np.sqrt(pooled.se / pooled.n)).round(1)
    pooled["MAE mm"] = (1000 * pooled.ae / pooled.n).round(1)
    pooled["> 0.1 m"] = (100 * pooled.big / pooled.n).map("{:.1f} %".format)
    print(f"\nPooled over the pixels of each class (a missing prediction counts as its {a.reference} depth):")
    print(pooled[["n", "RMSE mm", "MAE mm", "> 0.1 m"]].reindex(CLASSES, level=0).to_markdown())
    print(f"\nPer frame, {first} minus each, paired over the frames with pixels of the class (95 % bootstrap):")
    lines = []
    for c in CLASSES:
        sub = df[df.cls == c]
        if sub.empty:
            continue
        wide = sub.pivot_table(index="frame", columns="method", values=["se", "ae", "n"], aggfunc="sum")
        for o in others:
            mse = 1e6 * (wide["se"][first] - wide["se"][o]) / wide["n"][first]
            mae = 1e3 * (wide["ae"][first] - wide["ae"][o]) / wide["n"][first]
            m = bootstrap_means(np.stack([mse.to_numpy(), mae.to_numpy()], axis=1))
            lines.append(
                {
                    "class": c,
                    "minus": o,
                    "frames": int(m.frames[0]),
                    "MSE (mm^2)": f"{m.mean[0]:+.0f} [{m.low[0]:+.0f}, {m.high[0]:+.0f}]",
                    "MAE (mm)": f"{m.mean[1]:+.2f} [{m.low[1]:+.2f}, {m.high[1]:+.2f}]",
                }
            )
    print(pd.DataFrame(lines).to_markdown(index=False))
    tc = training_coverage(Path("."))
    if not tc.empty:
        print("\nTRAINING rooms (the RDE GT's frame sets): what each training GT covers per class")
        print(tc.to_markdown(index=False))


if __name__ == "__main__":
    main()
