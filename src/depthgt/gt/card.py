"""The dataset card: what a built GT dataset holds, how it was made, and the checksums
that let a copy be verified (``results/dataset/card.json`` and ``card.md``, written by
the ``dataset`` rule; ``depthgt verify``).

card.json holds:

* ``depthgt``: version and git commit of the code that built it (null outside a checkout);
* ``sources``: every source (name, kind, root, split, options) with its scenes;
* ``splits``: per split the scenes, built frame sets and kept patch pairs;
* ``framesets`` / ``frames`` / ``patches``: kept and skipped frame sets (each skipped
  one with its reason), frames read and found unusable, patches drawn and kept;
* ``settings``: the resolved config sections that decide the GT;
* ``quality``: GT and input completeness, the GT's confidence (median expected std),
  and the GT quality table (leave-target-out, error against the truth where known);
* ``files``: bytes and sha256 of every shard and every manifest, paths relative to
  the results folder;
* ``format_version``: the shards' format (:data:`depthgt.gt.store.FORMAT_VERSION`) and
  ``encoding``: the unit and precision of every stored channel
  (:data:`depthgt.gt.store.CHANNELS`).

A results folder verifies when every file of ``files`` has its recorded size and
checksum; an export (:mod:`depthgt.data.export`) verifies against its ``SHA256SUMS``
and its index against the card's counts.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

import depthgt
from depthgt import io
from depthgt.atomic import write_atomic
from depthgt.errors import DepthGTError
from depthgt.gt import store
from depthgt.gt.settings import SPLITS
from depthgt.status import Status

__all__ = [
    "CARD_VERSION",
    "CHECKSUMS",
    "code_version",
    "sha256_file",
    "build_card",
    "card_markdown",
    "write_card",
    "Verification",
    "verify",
]

CARD_VERSION = 1
CHECKSUMS = "SHA256SUMS"  # an export's checksum list, in the format of `sha256sum -c`
_QUALITY_METRICS = ("completeness", "mae_m", "rmse_m", "mae_missing_counted_m")


def code_version(root: str | Path | None = None) -> dict[str, Any]:
    """``version`` of depthgt and ``commit`` / ``dirty`` of the git checkout at ``root``
    (default: the one depthgt is installed from); None when it is not a git checkout or
    git is not installed."""
    root = Path(depthgt.__file__).resolve().parents[2] if root is None else Path(root)

    def git(*args: str) -> str | None:
        try:
            proc = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.SubprocessError):
            return None
        return proc.stdout.strip() if proc.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no") if commit else None
    return {"version": depthgt.__version__, "commit": commit, "dirty": None if status is None else bool(status)}


def sha256_file(path: str | Path) -> str:
    """Hex sha256 of a file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with Path(path).open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _mean(series: pd.Series) -> float | None:
    values = pd.to_numeric(series, errors="coerce").dropna()
    return float(values.mean()) if len(values) else None


def build_card(
    results: str | Path,
    summary: Mapping[str, Any],
    framesets: pd.DataFrame,
    quality: pd.DataFrame,
    index_metas: Sequence[Mapping[str, Any]],
    settings: Mapping[str, Any],
    files: Sequence[str | Path],
) -> dict[str, Any]:
    """The card's content (see the module docstring).

    Args:
        results: the results folder; ``files`` are recorded relative to it.
        summary: :func:`depthgt.gt.assemble.assemble`'s summary.
        framesets: the dataset's frame-set table (``framesets.parquet``).
        quality: the GT quality table per scene (``gt_quality.csv``).
        index_metas: every scene's ``index.json``.
        settings: the resolved config sections that decide the GT.
        files: the shards and manifests to checksum.

    Raises:
        DepthGTError: a file that is missing or outside ``results``.

    Long because the card's nested record is written out key by key, each section next
    to the few lines that count it.
    """
    results = Path(results).resolve()
    sources: dict[str, dict[str, Any]] = {}
    for meta in index_metas:
        src = dict(meta.get("source") or {"name": meta["dataset"]})
        entry = sources.setdefault(src["name"], {k: v for k, v in src.items() if k != "scenes"} | {"scenes": []})
        entry["scenes"].append(meta["scene"])
    ok = framesets[framesets["status"] == Status.OK]
    splits = {}
    for s in SPLITS:
        in_split = framesets[framesets["split"] == s]
        splits[s] = {
            "scenes": sorted({f"{r.dataset}/{r.scene}" for r in in_split.itertuples()}),
            "framesets": int(summary["framesets"][s]),
            "pairs": int(summary["pairs"][s]),
        }
    skipped = summary["framesets_skipped"]
    by_reason: dict[str, int] = {}
    for r in skipped:
        tag = str(r["reason"]).split(":")[0].strip() or "unknown"
        by_reason[tag] = by_reason.get(tag, 0) + 1
    gt_sigma = pd.to_numeric(ok.get("gt_median_sigma_m", pd.Series(dtype=float)), errors="coerce").dropna()
    quality_rows = []
    if len(quality):
        table = quality[quality["metric"].isin(_QUALITY_METRICS)]
        means = table.groupby(["dataset", "estimate", "reference", "metric", "unit"], as_index=False)["value"].mean()
        quality_rows = [
            {k: (float(v) if k == "value" else str(v)) for k, v in r.items()} for r in means.to_dict("records")
        ]
    file_entries = {}
    for f in sorted({Path(p).resolve() for p in files}):
        if not f.is_file():
            raise DepthGTError(f"dataset card: {f} does not exist")
        try:
            rel = f.relative_to(results)
        except ValueError:
            raise DepthGTError(f"dataset card: {f} is not inside the results folder {results}") from None
        file_entries[rel.as_posix()] = {"bytes": f.stat().st_size, "sha256": sha256_file(f)}
    return {
        "card_version": CARD_VERSION,
        "format_version": store.FORMAT_VERSION,
        "encoding": store.CHANNELS,
        "depthgt": code_version(),
        "sources": [sources[k] for k in sorted(sources)],
        "splits": splits,
        "framesets": {
            "total": int(len(framesets)),
            "kept": int(len(ok)),
            "skipped": len(skipped),
            "skipped_by_reason": dict(sorted(by_reason.items())),
            "skipped_list": list(skipped),
        },
        "frames": {
            "read": int(summary["frames_read"]),
            "skipped": len(summary["frames_skipped"]),
            "skipped_list": list(summary["frames_skipped"]),
        },
        "patches": {
            "drawn": int(summary["patches_drawn"]),
            "kept": int(summary["patches_kept"]),
            "rejected": int(summary["patches_rejected"]),
        },
        "scene_problems": list(summary.get("scene_problems", [])),
        "settings": dict(settings),
        "quality": {
            "gt_completeness": None if ok.empty else _mean(1.0 - ok["gt_missing"]),
            "input_completeness": None if ok.empty else _mean(1.0 - ok["input_missing"]),
            "gt_median_sigma_m": float(np.median(gt_sigma)) if len(gt_sigma) else None,
            "by_dataset": quality_rows,
            "units": {
                "completeness": "fraction of pixels",
                "gt_median_sigma_m": "m (median over frame sets of the per-frame median expected std of the GT)",
                "value": "see each row's unit",
            },
        },
        "files": file_entries,
    }


def card_markdown(card: Mapping[str, Any]) -> str:
    """card.md: the card for a person (checksums stay in card.json).

    Long because it writes card.md line by line, one markdown table after the other.
    """
    code = card["depthgt"]
    lines = [
        "# Dataset card",
        "",
        f"Built by depthgt {code['version']}, commit {code['commit'] or 'unknown (not a git checkout)'}"
        + (" (uncommitted changes)" if code.get("dirty") else "")
        + ".",
        "",
        "## Sources",
        "",
        "| source | kind | split | scenes |",
        "|---|---|---|---|",
    ]
    for s in card["sources"]:
        lines.append(f"| {s['name']} | {s.get('kind', '')} | {s.get('split', '')} | {', '.join(s['scenes'])} |")
    lines += ["", "## Splits", "", "| split | scenes | frame sets | patch pairs |", "|---|---:|---:|---:|"]
    for name, s in card["splits"].items():
        lines.append(f"| {name} | {len(s['scenes'])} | {s['framesets']} | {s['pairs']} |")
    fs, fr, pa = card["framesets"], card["frames"], card["patches"]
    lines += [
        "",
        f"Frame sets: {fs['total']}, kept {fs['kept']}, skipped {fs['skipped']}"
        + (f" ({', '.join(f'{k}: {v}' for k, v in fs['skipped_by_reason'].items())})" if fs["skipped"] else "")
        + f". Frames read: {fr['read']}, unusable: {fr['skipped']}. Patch pairs drawn: {pa['drawn']}, "
        f"kept: {pa['kept']}, rejected by the missing filter: {pa['rejected']}.",
        "",
    ]
    if fs["skipped_list"]:
        lines += ["| dataset | scene | target | reason |", "|---|---|---:|---|"]
        lines += [
            f"| {r['dataset']} | {r['scene']} | {r['target']} | {str(r['reason']).replace('|', '/')} |"
            for r in fs["skipped_list"]
        ] + [""]
    q = card["quality"]

    def num(v: float | None, unit: str = "") -> str:
        return "n/a" if v is None else f"{v:.4f}{unit}"

    lines += [
        "## GT quality",
        "",
        f"GT completeness {num(q['gt_completeness'])} "
        f"(input {num(q['input_completeness'])}); GT confidence: median expected std "
        f"{num(q['gt_median_sigma_m'], ' m')}.",
        "",
    ]
    if q["by_dataset"]:
        wide = pd.DataFrame(q["by_dataset"]).pivot_table(
            index=["dataset", "estimate", "reference"], columns="metric", values="value", aggfunc="mean"
        )
        lines += [
            "Mean over scenes (metres; completeness as a fraction); reference `truth`: the clean depth of "
            "synthetic sources, `target_raw`: the target's own sensor depth left out of the GT.",
            "",
            wide.round(4).reset_index().to_markdown(index=False),
            "",
        ]
    lines += [
        "## Format",
        "",
        f"Frame-set shards in format version {card.get('format_version', 1)}; "
        "what each stored channel holds, its unit and precision:",
        "",
        "| file | channel | content |",
        "|---|---|---|",
    ]
    lines += [f"| {f} | {c} | {text} |" for f, chans in card.get("encoding", {}).items() for c, text in chans.items()]
    lines += [
        "",
        "## Settings",
        "",
        "```yaml",
        yaml.safe_dump(card["settings"], sort_keys=True).rstrip(),
        "```",
        "",
        f"## Files\n\n{len(card['files'])} files (shards and manifests) with their sha256 in card.json; "
        "check a copy with `depthgt verify DIR`.",
        "",
    ]
    return "\n".join(lines)


def write_card(card: Mapping[str, Any], card_json: str | Path, card_md: str | Path) -> None:
    """Write card.json and card.md atomically."""
    write_atomic(card_json, io.write_json, card)
    write_atomic(card_md, Path.write_text, card_markdown(card))


@dataclass
class Verification:
    """The outcome of :func:`verify`: what was checked and every problem found (each
    naming the file at fault)."""

    folder: Path
    kind: str  # "results" or "export"
    checked: int = 0
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def _check_file(
    path: Path, sha256: str, size: int | None, what: str, report: Verification, card: Path | None = None
) -> None:
    """One file against its checksum; ``card``: the build's card, when a file written
    after it (a scene rebuilt, the dataset not assembled again) is to be told apart
    from a changed or corrupt one."""
    report.checked += 1
    if not path.is_file():
        report.problems.append(f"{path}: missing ({what})")
        return
    differs = None
    if size is not None and path.stat().st_size != size:
        differs = f"{path}: {path.stat().st_size} bytes, the {what} records {size}"
    elif sha256_file(path) != sha256:
        differs = f"{path}: sha256 differs from the {what}"
    if differs is None:
        return
    if card is not None and path.stat().st_mtime_ns > card.stat().st_mtime_ns:
        report.problems.append(
            f"{differs}; it is newer than the card: if its scene was rebuilt (`depthgt rebuild`), run "
            "`depthgt build dataset` to assemble the dataset and its card again; otherwise it was changed or is corrupt"
        )
    else:
        report.problems.append(f"{differs} (changed or corrupt)")


def verify(folder: str | Path) -> Verification:
    """Check a built dataset or an export against its card.

    ``folder`` is a working directory (holding ``results/``), a results folder, or an
    export (holding ``card.json``, ``export.json`` and ``SHA256SUMS``).

    Raises:
        DepthGTError: ``folder`` holds no card.
    """
    folder = Path(folder)
    for results in (folder / "results", folder):
        card_path = results / "dataset" / "card.json"
        if card_path.is_file():
            report = Verification(results, "results")
            card = _read_json(card_path, report)
            if card is None:
                return report
            try:
                version = card.get("format_version", 1)
                if version != store.FORMAT_VERSION:
                    report.problems.append(
                        f"{card_path}: shards in format version {version}, this depthgt reads version "
                        f"{store.FORMAT_VERSION}: rebuild every scene (`depthgt rebuild DATASET SCENE`) and the dataset (`depthgt build dataset`)"
                    )
                for rel, entry in card["files"].items():
                    _check_file(
                        results / rel, entry["sha256"], entry.get("bytes"), f"card {card_path}", report, card_path
                    )
            except (KeyError, TypeError, AttributeError) as err:  # a card edited or written by something else
                report.problems.append(f"{card_path}: not a dataset card ({type(err).__name__}: {err})")
            return report
    if (folder / "card.json").is_file() and (folder / "export.json").is_file():
        return _verify_export(folder, folder / CHECKSUMS)
    raise DepthGTError(
        f"verify: {folder} holds no dataset card (results/dataset/card.json, dataset/card.json, "
        "or the card.json and export.json of an export)"
    )


def _verify_export(folder: Path, sums: Path) -> Verification:
    report = Verification(folder, "export")
    if not sums.is_file():
        report.problems.append(f"{sums}: missing (the export did not finish: run it again to resume)")
        return report
    listed = set()
    try:
        lines = sums.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as err:
        report.problems.append(f"{sums}: not a text checksum list ({err})")
        return report
    for n, line in enumerate(lines, 1):
        digest, sep, rel = line.partition("  ")
        if not sep or len(digest) != 64:
            report.problems.append(f"{sums}:{n}: not a sha256sum line")
            continue
        listed.add(rel)
        _check_file(folder / rel, digest, None, f"checksum list {sums}", report)
    index = folder / "index.parquet"
    if not index.is_file():
        report.problems.append(f"{index}: missing (the export did not finish: run it again to resume)")
        return report
    unlisted = sorted(
        str(p.relative_to(folder))
        for p in folder.rglob("*")
        if p.is_file()
        and p.name not in (CHECKSUMS, "index.parquet", "index.csv")
        and not p.name.startswith(".")  # hidden: .DS_Store, a killed re-run's temporary file
        and str(p.relative_to(folder)) not in listed
    )
    if unlisted:
        report.problems.append(
            f"{folder}: {len(unlisted)} files not in {sums.name} (not written by this export): "
            + ", ".join(unlisted[:5])
            + (" ..." if len(unlisted) > 5 else "")
        )
    card, settings = _read_json(folder / "card.json", report), _read_json(folder / "export.json", report)
    if card is None or settings is None:
        return report
    try:
        rows = pd.read_parquet(index)
    except Exception as err:  # pyarrow raises its own types for a corrupt file
        report.problems.append(f"{index}: not a readable parquet table ({type(err).__name__}: {err})")
        return report
    try:
        count = "framesets" if settings["kind"] == "frames" else "pairs"
        for split in settings["splits"]:
            got, want = int((rows["split"] == split).sum()), card["splits"][split][count]
            if got != want:
                report.problems.append(f"{index}: {got} {settings['kind']} of split {split}, the card records {want}")
    except (KeyError, TypeError, AttributeError) as err:
        report.problems.append(
            f"{folder}: card.json, export.json or index.parquet not as an export writes them ({type(err).__name__}: {err})"
        )
    return report


def _read_json(path: Path, report: Verification) -> dict | None:
    """``path``'s JSON object, or None with the problem recorded."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        report.problems.append(f"{path}: not readable JSON ({type(err).__name__}: {err})")
        return None
    if not isinstance(doc, dict):
        report.problems.append(f"{path}: not a JSON object (a {type(doc).__name__})")
        return None
    return doc
