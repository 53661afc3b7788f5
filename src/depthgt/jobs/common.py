"""What every job entry point shares: its log file and opening a source's scene."""

from __future__ import annotations

import logging
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from depthgt.errors import ConfigError
from depthgt.sources.base import open_scene

__all__ = ["logging_to", "open_source_scene"]

log = logging.getLogger("depthgt")


@contextmanager
def logging_to(path: str | Path | None, level: int = logging.INFO) -> Iterator[None]:
    """Send depthgt's log records (and warnings) to ``path`` for the duration."""
    if path is None:
        yield
        return
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(path, mode="w")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    old = root.level
    root.setLevel(level)
    logging.captureWarnings(True)
    try:
        yield
    except Exception:
        log.exception("job failed")
        raise
    finally:
        root.removeHandler(handler)
        root.setLevel(old)
        handler.close()


POSE_OPTIONAL_KINDS = ("scannet", "sevenscenes", "tum")


def open_source_scene(source: dict[str, Any], scene: str, need_poses: bool = True):
    """Open ``scene`` of a config source entry (name, kind, root, options).

    When the registration does not need the source's poses, real sources are opened
    with ``require_pose=False`` so that frames with non-finite poses (ScanNet has them)
    stay usable.
    """
    options = dict(source.get("options") or {})
    if not need_poses and source["kind"] in POSE_OPTIONAL_KINDS:
        options.setdefault("require_pose", False)
    try:
        return open_scene(source["kind"], source.get("root"), scene, **options)
    except TypeError as err:
        raise ConfigError(f"config sources entry {source.get('name')!r} (kind {source['kind']}): bad options: {err}") from err
