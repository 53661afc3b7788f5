"""The status of a frame set (and of a registered neighbour) in every table and record.

A ``str`` enum: written to JSON and parquet as its plain value (``"ok"``), compared
equal to it, so records written before it existed read the same.
"""

from __future__ import annotations

from enum import StrEnum

__all__ = ["Status"]


class Status(StrEnum):
    """``planned`` (scene index: to be built once its member frames read fine), ``ok``
    (built), ``skipped`` (not built; the reason says why: split guard, an unusable member
    frame, ...), ``failed`` (registration failed: neighbours not registered with
    ``registration.on_failure: exclude``, or the whole set)."""

    PLANNED = "planned"
    OK = "ok"
    SKIPPED = "skipped"
    FAILED = "failed"
