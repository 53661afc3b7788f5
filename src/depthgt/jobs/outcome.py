"""What a run says at its end (the workflow's ``onsuccess`` and ``onerror``) and checks
at its start (``onstart``): a console summary of the build, one line for a full disk or
a job over its memory, and the space check before the first job.

Reading per-frame-set statistics never opens a shard: the summary comes from
``results/dataset/summary.json`` when it is newer than every scene's table, else from the
per-scene tables (``results/scenes/DATASET/SCENE/*.parquet``, one of each per scene),
counted scene by scene from the columns the lines need (:data:`SUMMARY_COLUMNS`).
"""

from __future__ import annotations

import json
import os
import re
import stat
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from depthgt.gt.assemble import console_lines, console_summary, reason_tag, scenes_without_framesets
from depthgt.gt.settings import SPLITS
from depthgt.gt.space import PlannedShard, disk_full_line
from depthgt.status import Status

__all__ = ["summary_lines", "memory_failures", "end_of_run_lines"]


def summary_lines(workdir: str | Path, scenes: Sequence[tuple[str, str]], failed: bool = False) -> list[str]:
    """The build's console summary (:func:`depthgt.gt.assemble.console_summary`): from the
    dataset's summary when it is up to date with the scenes' tables, else from the
    tables of the ``scenes`` built so far (and a line saying the dataset is not
    assembled from them). Empty when no scene has been summarised.

    The tables are counted scene by scene (:class:`_Counts`), each read for the columns
    the lines need only: a ScanNet build's tables hold millions of frame sets and tens of
    millions of patch rows."""
    results = Path(workdir).absolute() / "results"
    tables = [results / "scenes" / d / s for d, s in scenes]
    built, newest = [], None
    for t in tables:  # one stat per scene
        try:
            st = os.stat(t / "framesets.parquet")
        except (FileNotFoundError, NotADirectoryError):
            continue
        if stat.S_ISREG(st.st_mode):
            built.append(t)
            newest = st.st_mtime_ns if newest is None else max(newest, st.st_mtime_ns)
    summary_json = results / "dataset" / "summary.json"
    if summary_json.is_file() and built:
        if summary_json.stat().st_mtime_ns >= newest and len(built) == len(tables):
            return console_summary(json.loads(summary_json.read_text()), results / "dataset" / "summary.md")
    if not built:
        return []
    counts = _Counts()
    for t in built:
        counts.add_scene(t)
    lines = counts.lines()
    lines[0] = lines[0].replace("depthgt: ", f"depthgt: so far, in {len(built)} of {len(tables)} scenes: ", 1)
    if not failed:
        lines.append(
            f"depthgt: the dataset ({results / 'dataset'}) is not assembled from these frame sets yet: "
            "`depthgt build dataset` writes it, with summary.md listing every skipped frame and frame set"
        )
    return lines


#: the columns of a scene's tables the console summary reads
#: (:func:`depthgt.gt.assemble.summarise` and :func:`~depthgt.gt.assemble.console_summary`
#: on the concatenated tables give the same lines)
SUMMARY_COLUMNS = {
    "framesets.parquet": ["dataset", "scene", "target", "split", "status", "reason"],
    "patches.parquet": ["split", "kept"],
    "frames.parquet": ["valid"],
}
#: scenes without a frame set the console names (:func:`depthgt.gt.assemble.console_lines`)
_SCENES_NAMED = 3


class _Counts:
    """What the console summary says of the scenes' tables, added scene by scene (in the
    order :func:`depthgt.gt.assemble.summarise` reads the concatenated tables): counts per
    split, the skip reasons' tags with their counts and first frame set, and the first
    scenes without a frame set. Nothing is kept per frame set."""

    def __init__(self) -> None:
        self.framesets = dict.fromkeys(SPLITS, 0)
        self.pairs = dict.fromkeys(SPLITS, 0)
        self.skipped = 0
        self.reasons: dict[str, list] = {}  # tag -> [count, first record], first seen first
        self.frames_read = 0
        self.frames_unusable = 0
        self.patches_drawn = 0
        self.patches_kept = 0
        self.scenes_without: list[dict] = []

    def add_scene(self, folder: Path) -> None:
        fs = _read(folder / "framesets.parquet")
        ok = (fs["status"] == Status.OK).to_numpy(dtype=bool)
        split = fs["split"]
        for s in SPLITS:
            self.framesets[s] += int(((split == s).to_numpy(dtype=bool) & ok).sum())
        skipped = fs[~ok]
        self.skipped += len(skipped)
        self._add_reasons(skipped)
        if not ok.any() and len(self.scenes_without) < _SCENES_NAMED and (folder / "index.json").is_file():
            # a scene with a built frame set is not one of them: index.json only for the others
            meta = json.loads((folder / "index.json").read_text())
            self.scenes_without += scenes_without_framesets(fs, [meta])
        patches = _read(folder / "patches.parquet")
        if patches is not None:
            kept = patches["kept"].astype(bool).to_numpy(dtype=bool)
            self.patches_drawn += len(patches)
            self.patches_kept += int(kept.sum())
            kept_split = patches["split"][kept]
            for s in SPLITS:
                self.pairs[s] += int((kept_split == s).sum())
        frames = _read(folder / "frames.parquet")
        if frames is not None:
            self.frames_read += len(frames)
            self.frames_unusable += int((~frames["valid"].astype(bool)).sum())

    def _add_reasons(self, skipped: pd.DataFrame) -> None:
        """The skipped frame sets' reasons by tag (:func:`depthgt.gt.assemble.reason_tag`,
        asked once per distinct reason), each tag's first frame set kept."""
        if not len(skipped):
            return
        codes, uniques = pd.factorize(skipped["reason"], use_na_sentinel=False)
        per_code = np.bincount(codes, minlength=len(uniques))
        _, first_row = np.unique(codes, return_index=True)  # codes count up in order of first appearance
        for code, reason in enumerate(uniques):
            tag = reason_tag(str(reason))
            entry = self.reasons.get(tag)
            if entry is None:
                r = skipped.iloc[int(first_row[code])]
                entry = self.reasons[tag] = [
                    0,
                    {"dataset": r["dataset"], "scene": r["scene"], "target": int(r["target"]), "reason": r["reason"]},
                ]
            entry[0] += int(per_code[code])

    def lines(self) -> list[str]:
        ranked = sorted(self.reasons.items(), key=lambda kv: (-kv[1][0], kv[0]))[:3]
        return console_lines(
            self.framesets,
            self.skipped,
            [(tag, n, first) for tag, (n, first) in ranked],
            self.frames_unusable,
            self.frames_read,
            self.pairs,
            self.patches_drawn - self.patches_kept,
            self.scenes_without,
        )


def _read(path: Path) -> pd.DataFrame | None:
    """The columns of :data:`SUMMARY_COLUMNS` of one of a scene's tables; None when
    there is no such file."""
    try:
        return pd.read_parquet(path, columns=SUMMARY_COLUMNS[path.name])
    except FileNotFoundError:
        return None


# what Snakemake's log says of a job that was killed for its memory: the kernel's OOM
# killer (SIGKILL, exit status 137), SLURM's OUT_OF_MEMORY state, a MemoryError
_MEMORY = re.compile(
    r"SIGKILL|signal 9|exit status 137|returned non-zero exit status -9|OUT_OF_MEMORY|out of memory|MemoryError",
    re.I,
)


def memory_failures(snakemake_log: str, mem_mb: Mapping[str, int | None]) -> list[str]:
    """One line per rule whose job failed in a way that points at its memory (killed by
    signal 9, SLURM's OUT_OF_MEMORY, a MemoryError), naming the rule and the ``mem_mb``
    to raise; read from the text of Snakemake's log of the run.

    Args:
        mem_mb: rule -> the memory its jobs ask for (None where the rule declares none).

    >>> text = "RuleException:\\nCalledProcessError ... died with <Signals.SIGKILL: 9>.\\nError in rule train_model:\\n"
    >>> memory_failures(text, {"train_model": 16000})[0][:60]
    'depthgt: error: job train_model was killed, most likely over'
    """
    out = []
    seen = set()
    for record in _failure_records(snakemake_log):
        m = re.search(r"^Error in rule (\w+):", record, re.M)
        # a GPU's memory is not the job's mem_mb: its out-of-memory error is not one of these
        if not m or m.group(1) in seen or not _MEMORY.search(record) or "CUDA out of memory" in record:
            continue
        rule = m.group(1)
        seen.add(rule)
        mem = mem_mb.get(rule)
        now = f"mem_mb={mem}" if mem else "mem_mb not declared"
        raise_to = f"{rule}:mem_mb={2 * int(mem)}" if mem else f"{rule}:mem_mb=N"
        out.append(
            f"depthgt: error: job {rule} was killed, most likely over its memory ({now}): raise it, "
            f"e.g. --set-resources {raise_to} (or set-resources in the profile; on a cluster a job asks "
            "SLURM for exactly this), then run the same command again"
        )
    return out


def _failure_records(text: str) -> list[str]:
    """Snakemake's log cut into one piece per failed job: its ``RuleException`` (how the
    job's process ended), its ``Error in rule`` block and the details after it."""
    records, start, has_error = [], None, False
    for m in re.finditer(r"^(RuleException|Error in rule)", text, re.M):
        if m.group(1) == "RuleException" or has_error or start is None:
            if start is not None:
                records.append(text[start : m.start()])
            start = m.start()
            has_error = m.group(1) == "Error in rule"
        else:
            has_error = True
    if start is not None:
        records.append(text[start:])
    return records


def end_of_run_lines(
    workdir: str | Path,
    scenes: Sequence[tuple[str, str]],
    plan: Iterable[PlannedShard],
    resize: int,
    snakemake_log: str | Path | Sequence[str | Path] | None = None,
    mem_mb: Mapping[str, int | None] | None = None,
    failed: bool = False,
) -> list[str]:
    """Every line a run ends with: the summary (:func:`summary_lines`) and, for a failed
    run, one line for a full disk (the folder, its bytes free and what the rest of the
    build needs) and one per job that ran out of memory (:func:`memory_failures`), read
    from Snakemake's log of the run (``snakemake_log``: a path or the paths Snakemake's
    ``onerror`` gets)."""
    lines = summary_lines(workdir, scenes, failed=failed)
    if not failed:
        return lines
    logs = [snakemake_log] if isinstance(snakemake_log, (str, Path)) else list(snakemake_log or [])
    text = "".join(Path(p).read_text(errors="replace") for p in logs if p and Path(p).is_file())
    plan = list(plan)
    # only a run the log shows meeting a full disk (a tight disk does not make every
    # failure a full one; the next run's space check warns about it before any job)
    if "No space left on device" in text or "no space left on the device" in text:
        lines.append(disk_full_line(workdir, plan, resize))
    lines += memory_failures(text, mem_mb or {})
    empty = re.search(r"the dataset is empty: .*", text)
    if empty:
        lines.append(f"depthgt: error: {empty.group(0).strip()}")
    return lines
