"""Atomic file writes: a killed job leaves no half-written output behind.

Every output of the frame-set job, the RDE GT and the training is written with
:func:`write_atomic`: the writer fills a temporary file beside the target, which is
then renamed over it (``os.replace`` is atomic on POSIX file systems). Files an output
is assembled from (the frame sets of a shard) go to :func:`work_dir`, a scratch folder
of a fixed name that the next run of the same job clears.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

__all__ = ["write_atomic", "work_dir", "save_npz"]


def write_atomic(path: str | Path, writer: Callable[..., Any], *args: Any) -> Path:
    """Call ``writer(tmp_path, *args)`` and rename ``tmp_path`` to ``path``.

    The temporary file keeps the suffix of ``path`` (``.{name}.tmp{suffix}``), so that
    writers choosing the format by suffix (OpenEXR, OpenCV) work. Parent folders are
    created. A writer or a rename that fails (a full disk) leaves no temporary file
    taking space; the error is raised as it came. Standard library only (numpy is
    imported by :func:`save_npz` alone): :mod:`depthgt.buildconfig` writes with it while
    the Snakefile parses.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{path.suffix}")
    try:
        writer(tmp, *args)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


@contextlib.contextmanager
def work_dir(path: str | Path) -> Iterator[Path]:
    """A scratch folder beside output ``path`` while the context lasts: ``.{name}.work``,
    emptied on entry (a killed run of the job that writes ``path`` leaves it behind;
    only that job uses the name, so the next run clears it) and removed on exit.

    >>> import tempfile
    >>> out = Path(tempfile.mkdtemp()) / "000006-000037.zip"
    >>> (out.parent / ".000006-000037.zip.work").mkdir()  # left by a killed run
    >>> _ = (out.parent / ".000006-000037.zip.work" / "half.exr").write_bytes(b"EXR")
    >>> with work_dir(out) as scratch:
    ...     print(scratch.name, list(scratch.iterdir()))
    .000006-000037.zip.work []
    >>> sorted(p.name for p in out.parent.iterdir())
    []
    """
    path = Path(path)
    scratch = path.with_name(f".{path.name}.work")
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir(parents=True)
    try:
        yield scratch
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def save_npz(path: str | Path, arrays: dict[str, np.ndarray], level: int = 1) -> None:
    """Compressed ``.npz`` at exactly ``path`` (numpy would append ``.npz`` to a name
    without it), readable by :func:`numpy.load`, deflated at zlib ``level``; the same
    arrays give the same bytes (the members carry a fixed date, not the time of writing).

    numpy's ``savez_compressed`` always deflates at level 6 and stamps the time: on a
    frame set's patches (float depth, colour) level 1 writes files 2.7 % larger in a
    third less time (23 ms against 34 ms; stored uncompressed they would be 55 % larger).
    So the archive is written with :mod:`zipfile` and numpy's own ``.npy`` writer.
    """
    import io
    import zipfile

    import numpy as np

    with open(path, "wb") as fh, zipfile.ZipFile(fh, "w") as zf:
        for name, value in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(value), allow_pickle=False)
            member = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            zf.writestr(member, buf.getbuffer(), compress_type=zipfile.ZIP_DEFLATED, compresslevel=level)
