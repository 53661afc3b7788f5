"""What a run says at its end (the workflow's ``onsuccess`` and ``onerror``) and checks
at its start (``onstart``): a console summary of the build, one line for a full disk or
a job over its memory, and the space check before the first job.

Reading per-frame-set statistics never opens a shard: the summary comes from
``results/dataset/summary.json`` when it is newer than every scene's table, else from the
per-scene tables (``results/scenes/DATASET/SCENE/*.parquet``, one of each per scene).
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import pandas as pd

from depthgt.gt.assemble import FRAME_COLUMNS, FRAMESET_COLUMNS, PATCH_COLUMNS, console_summary, summarise
from depthgt.gt.space import PlannedShard, disk_full_line

__all__ = ["summary_lines", "memory_failures", "end_of_run_lines"]


def summary_lines(workdir: str | Path, scenes: Sequence[tuple[str, str]], failed: bool = False) -> list[str]:
    """The build's console summary (:func:`depthgt.gt.assemble.console_summary`): from the
    dataset's summary when it is up to date with the scenes' tables, else from the
    tables of the ``scenes`` built so far (and a line saying the dataset is not
    assembled from them). Empty when no scene has been summarised."""
    results = Path(workdir).absolute() / "results"
    tables = [results / "scenes" / d / s for d, s in scenes]
    built = [t for t in tables if (t / "framesets.parquet").is_file()]
    summary_json = results / "dataset" / "summary.json"
    if summary_json.is_file() and built:
        newest = max((t / "framesets.parquet").stat().st_mtime_ns for t in built)
        if summary_json.stat().st_mtime_ns >= newest and len(built) == len(tables):
            return console_summary(json.loads(summary_json.read_text()), results / "dataset" / "summary.md")
    if not built:
        return []

    def concat(name: str, columns: list[str]) -> pd.DataFrame:
        frames = [pd.read_parquet(t / name) for t in built if (t / name).is_file()]
        frames = [f for f in frames if len(f)]
        return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=columns)

    metas = [json.loads((t / "index.json").read_text()) for t in built if (t / "index.json").is_file()]
    summary = summarise(
        concat("framesets.parquet", FRAMESET_COLUMNS),
        concat("patches.parquet", PATCH_COLUMNS),
        concat("frames.parquet", FRAME_COLUMNS),
        metas,
    )
    lines = console_summary(summary)
    lines[0] = lines[0].replace("depthgt: ", f"depthgt: so far, in {len(built)} of {len(tables)} scenes: ", 1)
    if not failed:
        lines.append(
            f"depthgt: the dataset ({results / 'dataset'}) is not assembled from these frame sets yet: "
            "`depthgt build dataset` writes it, with summary.md listing every skipped frame and frame set"
        )
    return lines


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
