"""``depthgt report``: one self-contained HTML page of whatever a build holds.

A dataset-only build gets its summary (frame sets and patch pairs per split, what was
skipped and why), the GT-quality table and, per source, the frame sets a person should
look at first: the worst leave-target-out error, the lowest GT completeness and the most
neighbours left out (:func:`framesets_to_look_at`), each as a panel like
``depthgt show``'s with the commands that show, extract and rebuild it. A build with the
enhancement stage adds its tables, figures and training curves. Images are embedded
(PNG, base64), so the page can be mailed or archived alone.

The frame sets are chosen from ``results/dataset/framesets.parquet`` (or the per-scene
tables of a build without a dataset): one table read whatever the number of frame sets;
only the chosen ones are opened.
"""

from __future__ import annotations

import base64
import html
import json
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd

from depthgt import __version__
from depthgt.errors import DepthGTError
from depthgt.eval import figures
from depthgt.gt import store
from depthgt.gt.assemble import console_summary, reason_counts
from depthgt.settings import SPLITS

__all__ = ["CRITERIA", "framesets_to_look_at", "write_report"]

#: (column of framesets.parquet, what a large value means): the frame sets a person
#: looks at first, per source, largest first
CRITERIA = (
    ("leave_target_out_mae_m", "worst leave-target-out error: the neighbours alone against the target's raw depth"),
    ("gt_missing", "lowest GT completeness: the largest share of pixels without GT"),
    ("neighbours_left_out", "most neighbours left out by the registration or the renderer"),
)


def framesets_to_look_at(framesets: pd.DataFrame, per_criterion: int = 2) -> pd.DataFrame:
    """The built frame sets of each source that rank first on each of :data:`CRITERIA`
    (``per_criterion`` each; NaN and, for neighbours, zero never rank), each once, with
    every criterion it was chosen for (column ``why``).

    >>> fs = pd.DataFrame({"dataset": ["a"] * 3, "scene": ["s"] * 3, "target": [1, 2, 3], "status": ["ok"] * 3,
    ...     "frameset": ["x"] * 3, "leave_target_out_mae_m": [0.01, 0.03, float("nan")], "gt_missing": [0.1, 0.0, 0.2],
    ...     "neighbours_left_out": [0, 0, 0]})
    >>> [(r.target, len(r.why)) for r in framesets_to_look_at(fs, 1).itertuples()]
    [(2, 1), (3, 1)]
    """
    ok = framesets[framesets["status"] == "ok"]
    rows: dict[tuple, dict[str, Any]] = {}
    for dataset in sorted(ok["dataset"].unique()):
        of = ok[ok["dataset"] == dataset]
        for column, meaning in CRITERIA:
            if column not in of:
                continue
            values = pd.to_numeric(of[column], errors="coerce")
            keep = values.notna() & ((values > 0) if column == "neighbours_left_out" else True)
            ranked = of.assign(rank_value=values)[keep].sort_values(
                ["rank_value", "scene", "target"], ascending=[False, True, True]
            )
            for r in ranked.head(per_criterion).itertuples():
                key = (r.dataset, r.scene, int(r.target))
                entry = rows.setdefault(
                    key,
                    {
                        "dataset": r.dataset,
                        "scene": r.scene,
                        "target": int(r.target),
                        "frameset": r.frameset,
                        "why": [],
                    },
                )
                entry["why"].append(f"{meaning} ({column} = {float(r.rank_value):.4g})")
    return pd.DataFrame(list(rows.values()), columns=["dataset", "scene", "target", "frameset", "why"])


def _read(path: Path, reader):
    """``reader(path)``, a damaged or unreadable file named in one line (DepthGTError)."""
    try:
        return reader(path)
    except (OSError, ValueError, KeyError) as err:  # pyarrow's and pandas' errors are ValueErrors
        raise DepthGTError(
            f"{path}: cannot be read for the report ({type(err).__name__}: {err}); "
            "build it again (`depthgt build`) or remove it"
        ) from err


def _framesets_table(results: Path) -> pd.DataFrame | None:
    """framesets.parquet of the dataset, else the per-scene tables concatenated."""
    path = results / "dataset" / "framesets.parquet"
    if path.is_file():
        return _read(path, pd.read_parquet)
    tables = [_read(p, pd.read_parquet) for p in sorted(results.glob("scenes/*/*/framesets.parquet"))]
    tables = [t for t in tables if len(t)]
    return pd.concat(tables, ignore_index=True) if tables else None


def _png(path: Path) -> str:
    return f'<img src="data:image/png;base64,{base64.b64encode(path.read_bytes()).decode()}" style="max-width:100%">'


def _table(df: pd.DataFrame) -> str:
    return df.to_html(index=False, border=0, float_format=lambda v: f"{v:.4g}", na_rep="", classes="t")


def _section(title: str, body: str) -> str:
    return f"<h2>{html.escape(title)}</h2>\n{body}\n"


def _commands(wd: Path, dataset: str, scene: str, target: int) -> str:
    d = f"-d {wd}"
    return "<br>".join(
        html.escape(c)
        for c in (
            f"depthgt show {d} {dataset} {scene} {target}",
            f"depthgt extract {d} {dataset} {scene} {target} DEST",
            f"depthgt rebuild {d} {dataset} {scene}",
        )
    )


def _summary_doc(doc: Any) -> dict:
    """The dataset's summary.json, its keys the report reads checked (KeyError names one)."""
    keys = (("framesets", dict), ("pairs", dict), ("framesets_skipped", list), ("frames_skipped", list))
    keys += (("frames_read", int), ("patches_rejected", int))
    for key, kind in keys:
        if not isinstance(doc, dict) or not isinstance(doc.get(key), kind):
            raise KeyError(f"{key!r} missing or not a {kind.__name__}")
    for key in ("framesets", "pairs"):
        for split in SPLITS:
            if not isinstance(doc[key].get(split), int):
                raise KeyError(f"{key}.{split} missing or not a count")
    return doc


def _summary_section(results: Path) -> str:
    summary_json = results / "dataset" / "summary.json"
    if not summary_json.is_file():
        return _section(
            "Dataset",
            "<p>No dataset yet (results/dataset/summary.json is missing): <code>depthgt build dataset</code> "
            "assembles it from the frame sets.</p>",
        )
    summary = _read(summary_json, lambda p: _summary_doc(json.loads(p.read_text())))
    counts = pd.DataFrame(
        [{"split": s, "frame sets": summary["framesets"][s], "patch pairs": summary["pairs"][s]} for s in SPLITS]
    )
    lines = [html.escape(line.removeprefix("depthgt: ").strip()) for line in console_summary(summary)]
    body = _table(counts) + "<p>" + "<br>".join(lines) + "</p>"
    top = reason_counts(summary["framesets_skipped"], top=10)
    if top:
        body += "<h3>Frame sets skipped, by reason</h3>" + _table(
            pd.DataFrame(
                [
                    {
                        "reason": tag,
                        "frame sets": n,
                        "example": f"{e['dataset']}/{e['scene']}/{int(e['target']):06d}: {e['reason']}",
                    }
                    for tag, n, e in top
                ]
            )
        )
    md = results / "dataset" / "summary.md"
    if md.is_file():
        body += (
            f"<details><summary>summary.md ({html.escape(str(md))}): every skipped frame and frame set</summary>"
            f"<pre>{html.escape(md.read_text())}</pre></details>"
        )
    return _section("Dataset", body)


def _quality_section(results: Path) -> str:
    path = results / "dataset" / "gt_quality.csv"
    if not path.is_file():
        return ""
    q = _read(path, pd.read_csv)
    if not len(q):
        return _section("GT quality", "<p>No GT-quality statistics (no frame set built).</p>")
    wide = q.pivot_table(index=["dataset", "estimate", "reference"], columns="metric", values="value", aggfunc="mean")
    wide.columns.name = None
    return _section(
        "GT quality (mean over scenes; metres, completeness as a fraction)", _table(wide.round(5).reset_index())
    )


def _look_first_section(wd: Path, results: Path, per_criterion: int, tmp: Path) -> str:
    fs = _framesets_table(results)
    if fs is None:
        return ""
    chosen = framesets_to_look_at(fs, per_criterion)
    if not len(chosen):
        return _section("Frame sets to look at first", "<p>No built frame set.</p>")
    body = [
        "<p>Per source, the frame sets that rank first on: "
        + "; ".join(html.escape(m) for _, m in CRITERIA)
        + ". Each panel: RGB | input | GT | confidence (| truth), as <code>depthgt show</code> draws it.</p>"
    ]
    for dataset in sorted(chosen["dataset"].unique()):
        body.append(f"<h3>{html.escape(str(dataset))}</h3>")
        for i, r in enumerate(chosen[chosen["dataset"] == dataset].itertuples()):
            title = f"{r.dataset}/{r.scene}/{r.target:06d}"
            try:
                rec = store.read_frameset_at(wd / r.frameset if not Path(r.frameset).is_absolute() else r.frameset)
                png = figures.frameset_panel(rec, tmp / f"{dataset}_{i}.png", title=title)
                image = _png(png)
            except (DepthGTError, OSError, ValueError) as err:
                image = f"<p>(cannot draw it: {html.escape(str(err))})</p>"
            body.append(
                f"<div class='fs'><b>{html.escape(title)}</b>: {html.escape('; '.join(r.why))}<br>{image}"
                f"<div class='cmd'>{_commands(wd, r.dataset, r.scene, r.target)}</div></div>"
            )
    return _section("Frame sets to look at first", "\n".join(body))


def _tables_section(results: Path) -> str:
    tables = sorted((results / "tables").glob("*.csv"))
    if not tables:
        return _section(
            "Tables", "<p>No tables yet: <code>depthgt build tables</code> trains and evaluates the methods.</p>"
        )
    body = []
    for path in tables:
        body.append(f"<h3>{html.escape(path.stem)}</h3>" + _table(_read(path, pd.read_csv)))
    return _section("Tables", "\n".join(body))


def _figures_section(results: Path, tmp: Path) -> str:
    pngs = sorted((results / "figures").glob("*.png"))
    drawn = {p.stem.removeprefix("training_") for p in pngs if p.stem.startswith("training_")}
    for log in sorted(results.glob("models/*/loss_log.csv")):  # trained, but no figures job yet
        model = log.parent.name
        if model not in drawn and model != "registration":
            try:
                pngs.append(figures.training_curve(log, tmp / f"training_{model}.png", title=model))
            except (ValueError, KeyError, OSError, pd.errors.ParserError):
                continue
    if not pngs:
        return ""
    return _section("Figures and training curves", "\n".join(f"<h3>{html.escape(p.stem)}</h3>{_png(p)}" for p in pngs))


def _config_section(config: Mapping[str, Any] | None, source: str) -> str:
    if config is None:
        return ""
    import yaml  # PyYAML: only for this section

    text = yaml.safe_dump(json.loads(json.dumps(config, default=str)), sort_keys=False)
    return _section(
        "Configuration", f"<details><summary>{html.escape(source)}</summary><pre>{html.escape(text)}</pre></details>"
    )


_STYLE = (
    "body{font-family:sans-serif;max-width:1400px;margin:auto;padding:1em}"
    "table.t{border-collapse:collapse;margin:.5em 0}table.t td,table.t th{border:1px solid #ccc;padding:2px 6px;"
    "font-size:90%}.fs{margin:1em 0;padding:.5em;border-top:1px solid #ddd}"
    ".cmd{font-family:monospace;font-size:85%;color:#333;margin-top:.3em}"
)


def write_report(
    workdir: str | Path,
    out: str | Path,
    config: Mapping[str, Any] | None = None,
    config_source: str = "",
    per_criterion: int = 2,
) -> Path:
    """Write the HTML report of the build in ``workdir`` to ``out`` (module docstring).

    Args:
        config: the config the build runs with (shown collapsed), or None.
        per_criterion: frame sets per source and criterion among those to look at first.

    Raises:
        DepthGTError: ``workdir`` holds no build (no ``results/framesets``).
    """
    wd = Path(workdir).absolute()
    results = wd / "results"
    if not (results / "framesets").is_dir():
        raise DepthGTError(
            f"{wd} holds no build ({results / 'framesets'} is missing): check -d, or run `depthgt build`"
        )
    out = Path(out).absolute()
    with tempfile.TemporaryDirectory(prefix="depthgt-report-") as tmp:
        parts = [
            f"<h1>depthgt build {html.escape(str(wd))}</h1>",
            f"<p>depthgt {html.escape(__version__)}; every path below is in {html.escape(str(wd))}.</p>",
            _summary_section(results),
            _quality_section(results),
            _look_first_section(wd, results, per_criterion, Path(tmp)),
            _tables_section(results),
            _figures_section(results, Path(tmp)),
            _config_section(config, config_source),
        ]
        page = (
            "<!DOCTYPE html><html><head><meta charset='utf-8'><title>depthgt report</title>"
            f"<style>{_STYLE}</style></head><body>\n" + "\n".join(p for p in parts if p) + "\n</body></html>\n"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp_out = out.with_name(f".{out.name}.tmp")
    tmp_out.write_text(page, encoding="utf-8")
    tmp_out.replace(out)
    return out
