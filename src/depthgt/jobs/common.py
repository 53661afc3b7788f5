"""What every job entry point shares: its log file and opening a source's scene."""

from __future__ import annotations

import logging
import shutil
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from depthgt.errors import ConfigError, DepthGTError
from depthgt.gt.space import disk_full_line, is_disk_full
from depthgt.sources.base import open_scene, source_kind
from depthgt.testhook import hold

__all__ = ["logging_to", "failure_line", "open_source_scene"]

log = logging.getLogger("depthgt")


class _ConsoleFormatter(logging.Formatter):
    """``depthgt: warning: <message>`` (the level in lower case, no time: the console
    line of a skipped frame set is depthgt's sentence naming the file)."""

    def format(self, record: logging.LogRecord) -> str:
        return f"depthgt: {record.levelname.lower()}: {record.getMessage()}"


def failure_line(exc: BaseException, job: Any = None) -> str | None:
    """The one line a job ends with for a failure it explains (no traceback): a full
    disk (the folder and the bytes free), memory exhausted (the rule and the ``mem_mb``
    to raise), or a :class:`~depthgt.errors.DepthGTError` (its message names the file or
    key at fault); None for anything else (a bug: its traceback is kept).

    Args:
        job: Snakemake's ``snakemake`` object of the script (its ``rule`` and
            ``resources``), when there is one.
    """
    rule = getattr(job, "rule", None)
    if is_disk_full(exc):
        where = f" (writing {exc.filename})" if getattr(exc, "filename", None) else ""
        return disk_full_line(".") + where
    if isinstance(exc, MemoryError):
        mem = getattr(getattr(job, "resources", None), "mem_mb", None) if job is not None else None
        ask = f"mem_mb={mem}" if mem else "its mem_mb"
        raise_to = (
            f" --set-resources {rule}:mem_mb={2 * int(mem)}" if rule and mem else " --set-resources RULE:mem_mb=N"
        )
        return (
            f"depthgt: error: job {rule or '?'} ran out of memory ({ask}): raise its memory, e.g.{raise_to} "
            "(or set-resources in the profile), or lower what it holds at once"
        )
    if isinstance(exc, DepthGTError):
        return f"depthgt: error: {exc}"
    return None


@contextmanager
def logging_to(
    path: str | Path | None, level: int = logging.INFO, keep: str | Path | None = None, job: Any = None
) -> Iterator[None]:
    """Send depthgt's log records (and warnings) to ``path`` for the duration; depthgt's
    warnings also go to the console (stderr), one line each.

    A failure the job explains (:func:`failure_line`: a full disk, memory exhausted, a
    :class:`~depthgt.errors.DepthGTError`) ends the job with that one line in the log and
    on the console and exit status 1, without a traceback; any other exception is logged
    with its traceback and raised.

    Args:
        keep: a second copy of the log, appended to, where Snakemake does not delete it
            (Snakemake removes a job's log before running the job again): the records
            of earlier attempts found there are copied into ``path`` first, so that a
            resumed job's log shows what the killed one did.
        job: the script's ``snakemake`` object (names the rule and its ``mem_mb`` in a
            memory failure).
    """
    if path is None:
        yield
        return
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    mode = "w"
    if keep is not None and Path(keep).is_file():
        shutil.copyfile(keep, path)
        mode = "a"
    handlers: list[logging.Handler] = [logging.FileHandler(path, mode=mode)]
    if keep is not None:
        Path(keep).parent.mkdir(parents=True, exist_ok=True)
        handlers.append(logging.FileHandler(keep, mode="a"))
    for handler in handlers:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    console = logging.StreamHandler(sys.stderr)
    console.setLevel(logging.WARNING)
    console.addFilter(lambda record: record.name.startswith("depthgt") and not record.exc_info)
    console.setFormatter(_ConsoleFormatter())
    handlers.append(console)
    root = logging.getLogger()
    for handler in handlers:
        root.addHandler(handler)
    old = root.level
    root.setLevel(level)
    logging.captureWarnings(True)
    try:
        hold(f"job:{path}")  # a pause point for tests that kill a running job (depthgt.testhook)
        yield
    except Exception as exc:
        line = failure_line(exc, job)
        if line is None:
            log.exception("job failed")
            raise
        # one line in the log (Snakemake shows the log of a failed job: show-failed-logs) and
        # on the console; the run's end names what it needs (depthgt.jobs.outcome)
        console.setLevel(logging.CRITICAL + 1)
        log.error(line.removeprefix("depthgt: error: "))
        print(line, file=sys.stderr)
        raise SystemExit(1) from None
    finally:
        for handler in handlers:
            root.removeHandler(handler)
            handler.close()
        root.setLevel(old)


def open_source_scene(source: dict[str, Any], scene: str, need_poses: bool = True):
    """Open ``scene`` of a config source entry (name, kind, root, options,
    colour_matches_depth).

    When the registration does not need the source's poses, a kind whose poses are
    optional (:class:`depthgt.sources.base.SourceKind`) is opened with
    ``require_pose=False`` so that frames with non-finite poses (ScanNet has them) stay
    usable. A ``colour_matches_depth: true|false`` overrides the kind's (``auto``).
    """
    options = dict(source.get("options") or {})
    if not need_poses and source_kind(source["kind"]).poses_optional:
        options.setdefault("require_pose", False)
    try:
        opened = open_scene(source["kind"], source.get("root"), scene, **options)
    except TypeError as err:
        raise ConfigError(
            f"config sources entry {source.get('name')!r} (kind {source['kind']}): bad options: {err}"
        ) from err
    colour = source.get("colour_matches_depth")
    if isinstance(colour, bool):
        opened.colour_matches_depth = colour
    return opened
