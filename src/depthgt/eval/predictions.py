"""Scoring a folder of a user's predictions with the tables' protocol (``depthgt evaluate``).

A prediction folder ``PRED_DIR`` holds one depth image per test frame, named like the
test split of a ``depthgt export --kind frames``: the export's
``frames/test/{dataset}/{scene}/input/{target:06d}.png`` is predicted as
``PRED_DIR/{dataset}/{scene}/{target:06d}.png`` (16-bit PNG, millimetres, 0 = missing)
or ``.exr`` (float32 metres in the single channel ``Y`` as the export writes it, or
``Z``; 0, NaN or +inf = missing, a negative depth is an error), at the frame's working
resolution.

The references are the frames of the test split, read either from a build's results
(:func:`frames_from_results`: the frame sets through :mod:`depthgt.gt.store`, exactly
what the workflow scores) or from an export (:func:`frames_from_export`; an ``exr``
export holds the same float32 images, a ``png16`` export rounds them to 1 mm). Every
prediction is scored by :func:`depthgt.eval.evaluate.score_rows` against depthgt's GT
and, where the frame has one, the clean truth, with the raw input as the denoising
mask, and :func:`evaluate_folder` writes the tables of :mod:`depthgt.eval.tables`
(same masks, metrics, bootstrap intervals and captions): Table 3 for the datasets with
a truth, Table 2 for the others.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd

from depthgt import io
from depthgt.data.export import read_depth
from depthgt.errors import DepthGTError
from depthgt.eval import tables
from depthgt.eval.evaluate import EVAL_COLUMNS, score_rows
from depthgt.gt import store
from depthgt.status import Status

__all__ = [
    "TestFrame",
    "TestFrames",
    "frames_from_results",
    "frames_from_export",
    "prediction_path",
    "read_prediction",
    "score_predictions",
    "evaluate_folder",
    "PREDICTION_SUFFIXES",
]

log = logging.getLogger(__name__)

PREDICTION_SUFFIXES = (".exr", ".png")
PNG_UNITS_PER_M = 1000  # millimetres, as the export's png16 depth


class TestFrame(NamedTuple):
    """One test frame to score a prediction on.

    Attributes:
        dataset, scene, target: its ids (the export's and the tables' names).
        input_m: (H, W) float32 raw input depth in metres (the denoising mask).
        references: name (``gt``, ``truth``) -> (H, W) float32 metres.
    """

    dataset: str
    scene: str
    target: int
    input_m: np.ndarray
    references: dict[str, np.ndarray]


class TestFrames:
    """The test frames of a build or an export: their ids, known before any image is
    read (so that every missing prediction is named at once), and, iterated, the frames
    with their images, read one at a time."""

    def __init__(self, ids: list[tuple[str, str, int]], read: Callable[[int], TestFrame]):
        self.ids, self._read = ids, read

    def __len__(self) -> int:
        return len(self.ids)

    def __iter__(self) -> Iterator[TestFrame]:
        return (self._read(i) for i in range(len(self.ids)))


def frames_from_results(directory: str | Path, split: str = "test") -> TestFrames:
    """The ``split`` frames of a build in the working directory ``directory`` (its
    ``results/dataset/framesets.parquet``; locations relative to ``directory``)."""
    directory = Path(directory)
    table_path = directory / "results" / "dataset" / "framesets.parquet"
    if not table_path.is_file():
        raise DepthGTError(f"{table_path}: no built dataset (run `depthgt build dataset` in {directory})")
    table = _read_table(table_path)
    table = table[(table["split"] == split) & (table["status"] == Status.OK) & (table["frameset"] != "")]
    if table.empty:
        raise DepthGTError(f"{table_path}: no runnable frame set in the split {split!r}")
    recs = list(table.itertuples())

    def read(i: int) -> TestFrame:
        rec = recs[i]
        loc = rec.frameset if Path(str(rec.frameset)).is_absolute() else str(directory / str(rec.frameset))
        frame = store.read_frame_images(loc)
        refs = {r: frame.depth(r) for r in ("gt", "truth") if frame.depth(r) is not None}
        return TestFrame(str(rec.dataset), str(rec.scene), int(rec.target), frame.input_m, refs)

    return TestFrames([(str(r.dataset), str(r.scene), int(r.target)) for r in recs], read)


def frames_from_export(export_dir: str | Path, split: str = "test") -> TestFrames:
    """The ``split`` frames of a ``depthgt export --kind frames`` in ``export_dir``."""
    export_dir = Path(export_dir)
    meta_path, index_path = export_dir / "export.json", export_dir / "index.parquet"
    if not meta_path.is_file() or not index_path.is_file():
        raise DepthGTError(f"{export_dir}: not a finished export (no export.json or index.parquet)")
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DepthGTError(f"{meta_path}: not readable ({type(err).__name__}: {err})") from None
    if not isinstance(meta, dict) or meta.get("kind") != "frames" or split not in (meta.get("splits") or []):
        kind, splits = (meta.get("kind"), meta.get("splits")) if isinstance(meta, dict) else (None, None)
        raise DepthGTError(
            f"{meta_path}: an export of {kind} of the splits {splits}; "
            f"scoring needs `depthgt export --kind frames --split {split}`"
        )
    index = _read_table(index_path)
    missing = sorted({"split", "dataset", "scene", "target", "input", "gt", "truth"} - set(index.columns))
    if missing:
        raise DepthGTError(f"{index_path}: not an export's index (no columns {missing})")
    recs = list(index[index["split"] == split].itertuples())

    def read(i: int) -> TestFrame:
        rec = recs[i]
        refs = {m: read_depth(export_dir / getattr(rec, m), m) for m in ("gt", "truth") if getattr(rec, m)}
        return TestFrame(
            str(rec.dataset), str(rec.scene), int(rec.target), read_depth(export_dir / rec.input, "input"), refs
        )

    return TestFrames([(str(r.dataset), str(r.scene), int(r.target)) for r in recs], read)


def _read_table(path: Path) -> pd.DataFrame:
    try:
        return pd.read_parquet(path)
    except Exception as err:  # pyarrow raises its own types for a corrupt or foreign file
        raise DepthGTError(f"{path}: not a readable parquet table ({type(err).__name__}: {err})") from None


def prediction_path(pred_dir: str | Path, dataset: str, scene: str, target: int) -> Path:
    """The prediction file of one frame: ``{pred_dir}/{dataset}/{scene}/{target:06d}``
    with the first suffix of :data:`PREDICTION_SUFFIXES` that exists.

    Raises:
        DepthGTError: none exists, or both do (which one to score would be a guess).
    """
    stem = Path(pred_dir) / dataset / scene / f"{int(target):06d}"
    found = [stem.with_suffix(s) for s in PREDICTION_SUFFIXES if stem.with_suffix(s).is_file()]
    if not found:
        raise DepthGTError(f"no prediction {stem}.exr or {stem}.png for the test frame {dataset}/{scene}/{target}")
    if len(found) > 1:
        raise DepthGTError(f"two predictions for the test frame {dataset}/{scene}/{target}: {found[0]} and {found[1]}")
    return found[0]


def read_prediction(path: str | Path, shape_hw: tuple[int, int]) -> np.ndarray:
    """(H, W) float32 metres of one prediction file (see the module docstring).

    Raises:
        DepthGTError: an EXR without a single depth channel, a PNG that is not 16-bit
            single-channel (:class:`~depthgt.errors.FrameError`), or an image of another
            size than ``shape_hw`` (the file named).
    """
    path = Path(path)
    if path.suffix == ".exr":
        chans = io.read_exr(path)
        names = [c for c in ("Y", "Z") if c in chans] or (list(chans) if len(chans) == 1 else [])
        if len(names) != 1:
            raise DepthGTError(f"{path}: a prediction EXR needs one depth channel 'Y' (or 'Z'), has {sorted(chans)}")
        depth = np.asarray(chans[names[0]], dtype=np.float32)
    else:  # a FrameError (a DepthGTError) names the file: not 16-bit single-channel, truncated, another size
        depth = io.read_depth_png(path, PNG_UNITS_PER_M, expected_hw=tuple(shape_hw), what="the test frame's size")
    if depth.shape != tuple(shape_hw):
        raise DepthGTError(f"{path}: prediction of shape {depth.shape}, the test frame is {tuple(shape_hw)}")
    negative = int((depth < 0).sum())  # -inf included
    if negative:
        raise DepthGTError(
            f"{path}: {negative} pixels of negative depth (min {float(np.nanmin(depth)):.4g}); "
            "a prediction holds depth in metres (EXR) or millimetres (PNG), 0 or NaN where it has none"
        )
    return depth


def score_predictions(
    pred_dir: str | Path, frames: Iterable[TestFrame], method: str, progress: bool = False
) -> pd.DataFrame:
    """Every frame's prediction of ``pred_dir`` scored as ``method`` (long table,
    :data:`EVAL_COLUMNS`); an unreadable prediction raises, naming it, and with
    :class:`TestFrames` every missing one is named before any is scored. NaN and +inf
    pixels count as missing (as 0 does); how many, and in which files, is logged.

    Raises:
        DepthGTError: predictions missing (all listed), unreadable or of negative depth.
    """
    from tqdm import tqdm

    if isinstance(frames, TestFrames):
        absent = []
        for d, sc, t in frames.ids:
            try:
                prediction_path(pred_dir, d, sc, t)
            except DepthGTError as err:
                absent.append(str(err))
        expected = {Path(d) / sc / f"{int(t):06d}{x}" for d, sc, t in frames.ids for x in PREDICTION_SUFFIXES}
        unused = sorted(
            str(q.relative_to(pred_dir))
            for q in Path(pred_dir).rglob("*")
            if q.is_file() and q.relative_to(pred_dir) not in expected
        )
        if unused:  # a typo in a scene's name would otherwise go unnoticed beside the error below
            log.warning(
                "%d files of %s are no test frame's prediction and are not scored: %s",
                len(unused),
                pred_dir,
                ", ".join(unused[:5]) + (" ..." if len(unused) > 5 else ""),
            )
        if absent:
            raise DepthGTError(
                f"{pred_dir}: {len(absent)} of the {len(frames)} test frames have no single prediction:\n  "
                + "\n  ".join(absent[:10])
                + (f"\n  ... and {len(absent) - 10} more" if len(absent) > 10 else "")
            )
    rows, non_finite = [], []
    total = len(frames) if isinstance(frames, TestFrames) else None
    for f in tqdm(frames, total=total, desc=f"scoring {method}", unit="frame", disable=not progress):
        path = prediction_path(pred_dir, f.dataset, f.scene, f.target)
        pred = read_prediction(path, f.input_m.shape)
        bad = ~np.isfinite(pred)
        if bad.any():
            non_finite.append((path, int(bad.sum())))
            pred = np.where(bad, np.float32(0.0), pred)
        rows += score_rows(f.dataset, f.scene, f.target, method, pred, f.input_m, f.references)
    if non_finite:
        log.warning(
            "%d predictions hold NaN or inf pixels, scored as missing (the completeness column counts them): %s",
            len(non_finite),
            ", ".join(f"{p} ({n} px)" for p, n in non_finite[:5]) + (" ..." if len(non_finite) > 5 else ""),
        )
    return pd.DataFrame(rows, columns=EVAL_COLUMNS)


def evaluate_folder(
    pred_dir: str | Path,
    out_dir: str | Path,
    frames: Iterable[TestFrame],
    method: str = "user",
    compare: Sequence[pd.DataFrame] = (),
    progress: bool = False,
) -> dict[str, Path]:
    """Score ``pred_dir`` on ``frames`` and write the tables into ``out_dir``.

    Args:
        method: the name the predictions get in the tables.
        compare: the workflow's evaluation long tables (``results/eval/*.parquet``) to
            put beside the predictions on the same frames; with them the paired tables
            compare ``method`` with every one of their methods.

    Returns:
        name -> path of what was written: ``eval`` (the long table, parquet),
        ``table2``/``table3`` (Markdown; the CSV beside it) and, with ``compare``,
        ``table2_paired``/``table3_paired``.
    """
    out_dir = Path(out_dir)
    if method in {m for c in compare for m in c["method"].unique()}:
        raise DepthGTError(f"the predictions' name {method!r} is a method of the build: pick another (--name)")
    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)  # before the scoring: a bad destination fails at once
    try:
        ev = score_predictions(pred_dir, frames, method, progress=progress)
    except BaseException:
        if created and not any(out_dir.iterdir()):  # leave no empty folder behind
            out_dir.rmdir()
        raise
    if ev.empty:
        raise DepthGTError(f"{pred_dir}: no test frame to score")
    keys = ["dataset", "scene", "target", "reference"]
    scored = ev[keys].drop_duplicates()
    both = [c.merge(scored, on=keys) for c in compare]  # the build's rows on the frames scored here
    ev_all = pd.concat([ev, *both], ignore_index=True)
    with_truth = set(ev.loc[ev["reference"] == "truth", "dataset"])
    kinds = {d: ("synthetic" if d in with_truth else "real") for d in ev["dataset"].unique()}
    written = {"eval": out_dir / "eval.parquet"}
    ev_all.to_parquet(written["eval"], index=False)
    table2 = tables.table2(ev_all, kinds)
    built = {
        "table2": (table2, tables.table2_caption(tables.references_in(table2))),
        "table3": (tables.table3(ev_all, kinds), tables.TABLE3_CAPTION),
    }
    if compare:
        datasets = {
            True: [d for d, k in kinds.items() if k == "synthetic"],
            False: [d for d, k in kinds.items() if k != "synthetic"],
        }
        for key, synthetic, ref, note, caption in (
            ("table2_paired", False, "gt", tables.NO_REAL_NOTE, tables.TABLE2_PAIRED_CAPTION),
            ("table3_paired", True, "truth", tables.NO_SYNTH_NOTE, tables.TABLE3_PAIRED_CAPTION),
        ):
            table = tables.paired_table(ev_all, sorted(datasets[synthetic]), ref, note, base=method)
            if key == "table2_paired":
                caption = tables.table2_caption(tables.references_in(table), paired=True, base=method)
            built[key] = (table, caption.replace("LapDEN", method))
    for key, (table, caption) in built.items():
        _, written[key] = tables.write_table(table, out_dir / f"{key}.csv", out_dir / f"{key}.md", caption)
    log.info("scored %s: %d frames -> %s", pred_dir, len(scored.drop_duplicates(keys[:3])), out_dir)
    return written
