"""Room on the results file system: the check before a run's first job, and the line a
full disk ends with.

The planned output is estimated from the format's measured bytes per frame set
(:data:`depthgt.gt.sizes.MEASURED_FRAMESET_BYTES`, scaled with the pixels of the
working resolution) times the frame sets of the batches whose shard does not exist yet;
everything else a build writes (manifests, models, tables) is small beside them.

Torch-, NumPy- and OpenCV-free (the standard library, :mod:`depthgt.errors` and the
constants of :mod:`depthgt.gt.sizes`): the workflow's ``onstart`` imports it before the
first job.
"""

from __future__ import annotations

import errno
import os
import shutil
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from depthgt.errors import DepthGTError
from depthgt.gt import sizes

__all__ = [
    "PlannedShard",
    "missing_shards",
    "frameset_bytes",
    "free_bytes",
    "SpaceNeed",
    "space_need",
    "check_space",
    "is_disk_full",
    "disk_full_line",
]


@dataclass(frozen=True)
class PlannedShard:
    """One frame-set batch of the plan: its shard (relative to the working directory),
    how many frame sets it holds and whether its source is synthetic."""

    path: str
    framesets: int
    synthetic: bool


def frameset_bytes(resize: int, synthetic: bool) -> int:
    """Bytes on disk of one frame set at working resolution ``resize``: the measured
    size, its images scaled with the pixel count (the JSON members and the patch
    record, :data:`depthgt.gt.sizes.MEASURED_FRAMESET_FIXED_BYTES`, do not scale).

    >>> frameset_bytes(256, False), frameset_bytes(128, True)
    (235000, 78250)
    """
    measured = sizes.MEASURED_FRAMESET_BYTES["synthetic" if synthetic else "real"]
    fixed = sizes.MEASURED_FRAMESET_FIXED_BYTES
    return int(round(fixed + (measured - fixed) * (resize / sizes.MEASURED_RESIZE) ** 2))


def free_bytes(path: str | Path) -> int:
    """Bytes free to this user on the file system of ``path`` (its nearest existing
    folder when it does not exist yet)."""
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return shutil.disk_usage(p).free


@dataclass(frozen=True)
class SpaceNeed:
    """What the rest of a build needs: the frame sets still to build, their bytes, and
    the bytes free on the results file system."""

    folder: Path
    framesets: int
    needed: int
    free: int

    @property
    def fits(self) -> bool:
        return self.needed <= self.free

    def figures(self) -> str:
        return (
            f"{self.folder} has {_size(self.free)} free; the rest of the build needs about {_size(self.needed)} "
            f"({self.framesets} frame sets still to build at the format's measured size)"
        )


def missing_shards(workdir: str | Path, plan: Iterable[PlannedShard]) -> list[PlannedShard]:
    """The shards of ``plan`` that are not a file under ``workdir`` (not built yet), in
    the plan's order.

    One directory listing per folder of the plan (a scene's
    ``results/framesets/DATASET/SCENE/``) rather than one ``stat`` per shard: a ScanNet
    build plans ~9,000 shards in ~1,500 folders. A listed entry counts as a file as
    :meth:`pathlib.Path.is_file` decides it (a link to a file is one); a folder that
    cannot be listed but may be searched is asked shard by shard.
    """
    wd = Path(workdir).absolute()
    plan = list(plan)
    by_folder: dict[str, list[PlannedShard]] = {}
    for shard in plan:
        by_folder.setdefault(os.path.dirname(shard.path), []).append(shard)
    built: set[str] = set()
    for folder, shards in by_folder.items():
        names = {os.path.basename(s.path) for s in shards}
        try:
            with os.scandir(wd / folder) as entries:
                files = {e.name for e in entries if e.name in names and _is_file(e)}
        except (FileNotFoundError, NotADirectoryError):
            continue  # no folder: none of its shards is built
        except OSError:  # e.g. a folder that may be searched but not listed
            built.update(s.path for s in shards if (wd / s.path).is_file())
            continue
        built.update(s.path for s in shards if os.path.basename(s.path) in files)
    return [s for s in plan if s.path not in built]


def _is_file(entry: os.DirEntry) -> bool:
    try:
        return entry.is_file()
    except OSError:  # a link whose target cannot be asked: as Path.is_file answers it
        return Path(entry.path).is_file()


def space_need(workdir: str | Path, plan: Iterable[PlannedShard], resize: int) -> SpaceNeed:
    """The frame sets of ``plan`` whose shard is not built yet (:func:`missing_shards`),
    their estimated bytes, and the space free on the file system of ``workdir/results``."""
    wd = Path(workdir).absolute()
    todo = missing_shards(wd, plan)
    needed = sum(s.framesets * frameset_bytes(resize, s.synthetic) for s in todo)
    results = wd / "results"
    return SpaceNeed(results, sum(s.framesets for s in todo), needed, free_bytes(results))


def check_space(workdir: str | Path, plan: Iterable[PlannedShard], resize: int, refuse: bool = True) -> str | None:
    """Before a run's first job: whether its planned frame sets fit on the results file
    system.

    Returns:
        None when they fit, else the warning (with ``refuse=False``).

    Raises:
        DepthGTError: they do not fit and ``refuse`` (config ``dataset.check_space``).
    """
    need = space_need(workdir, plan, resize)
    if need.fits:
        return None
    message = f"not enough space for the planned frame sets: {need.figures()}"
    if refuse:
        raise DepthGTError(
            message
            + ". Free space there (or build elsewhere with -d), or set dataset.check_space: false to start anyway"
        )
    return "depthgt: warning: " + message


def is_disk_full(exc: BaseException) -> bool:
    """Whether an exception is the file system running out of space (or quota).

    >>> is_disk_full(RuntimeError('Failed to write pixel data to image file "gt.exr". No space left on device.'))
    True
    """
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    # pyarrow's and some libraries' OSErrors carry no errno, and OpenEXR's writer raises a
    # RuntimeError (the first write of a frame set is its gt.exr): only the system's message
    return isinstance(exc, (OSError, RuntimeError)) and "No space left on device" in str(exc)


def disk_full_line(workdir: str | Path, plan: Iterable[PlannedShard] | None = None, resize: int | None = None) -> str:
    """The one line a full disk ends a run with: the folder, the bytes free and (with the
    plan) the bytes the rest of the build needs."""
    wd = Path(workdir).absolute()
    if plan is not None and resize is not None:
        figures = space_need(wd, plan, resize).figures()
    else:
        figures = f"{wd / 'results'} has {_size(free_bytes(wd / 'results'))} free"
    return (
        f"depthgt: error: no space left on the device of {wd / 'results'}: {figures}. Free space and run the "
        "same command again: the finished jobs are kept and nothing half-written is used"
    )


def _size(n: int) -> str:
    """Bytes in a person's units, exact count beside.

    >>> _size(3_145_728)
    '3.1 MB (3145728 bytes)'
    """
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.1f} {unit} ({n} bytes)"
    return f"{n} bytes"
