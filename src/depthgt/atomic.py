"""Atomic file writes: a killed job leaves no half-written output behind.

Every output of the frame-set job, the RDE GT and the training is written with
:func:`write_atomic`: the writer fills a temporary file beside the target, which is
then renamed over it (``os.replace`` is atomic on POSIX file systems).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable

import numpy as np

__all__ = ["write_atomic", "save_npz"]


def write_atomic(path: str | Path, writer: Callable[..., Any], *args: Any) -> Path:
    """Call ``writer(tmp_path, *args)`` and rename ``tmp_path`` to ``path``.

    The temporary file keeps the suffix of ``path`` (``.{name}.tmp{suffix}``), so that
    writers choosing the format by suffix (OpenEXR, OpenCV) work. Parent folders are
    created.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{path.suffix}")
    writer(tmp, *args)
    os.replace(tmp, path)
    return path


def save_npz(path: str | Path, arrays: dict[str, np.ndarray]) -> None:
    """Compressed ``.npz`` at exactly ``path`` (numpy would append ``.npz`` to a name
    without it)."""
    with open(path, "wb") as fh:
        np.savez_compressed(fh, **arrays)
