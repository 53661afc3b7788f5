"""What every job entry point shares: its log file and opening a source's scene."""

from __future__ import annotations

import logging
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from depthgt.errors import ConfigError
from depthgt.sources.base import open_scene, source_kind
from depthgt.testhook import hold

__all__ = ["logging_to", "open_source_scene"]

log = logging.getLogger("depthgt")


@contextmanager
def logging_to(path: str | Path | None, level: int = logging.INFO, keep: str | Path | None = None) -> Iterator[None]:
    """Send depthgt's log records (and warnings) to ``path`` for the duration.

    Args:
        keep: a second copy of the log, appended to, where Snakemake does not delete it
            (Snakemake removes a job's log before running the job again): the records
            of earlier attempts found there are copied into ``path`` first, so that a
            resumed job's log shows what the killed one did.
    """
    if path is None:
        yield
        return
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    mode = "w"
    if keep is not None and Path(keep).is_file():
        shutil.copyfile(keep, path)
        mode = "a"
    handlers = [logging.FileHandler(path, mode=mode)]
    if keep is not None:
        Path(keep).parent.mkdir(parents=True, exist_ok=True)
        handlers.append(logging.FileHandler(keep, mode="a"))
    root = logging.getLogger()
    for handler in handlers:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        root.addHandler(handler)
    old = root.level
    root.setLevel(level)
    logging.captureWarnings(True)
    try:
        hold(f"job:{path}")  # a pause point for tests that kill a running job (depthgt.testhook)
        yield
    except Exception:
        log.exception("job failed")
        raise
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
