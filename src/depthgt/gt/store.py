"""Built frame sets on disk: the one writer and reader of frame-set shards.

A batch job builds a contiguous slice of one scene's frame sets and writes them as one
**shard**, an uncompressed zip archive ``{first:06d}-{last:06d}.zip`` whose members are
``{target:06d}/gt.exr``, ``input.exr``, ``rgb.webp``, ``poses.json``, ``patches.npz``,
``frameset.json`` per built frame set, plus ``batch.json``: every target of the slice
with its status and, for a skipped one, the reason (``framesets``), and every frame the
batch read with whether it was usable and, if not, the reason and message naming the
file (``frames``). One file per batch instead of six
per frame set keeps a ScanNet-size build (250k frame sets) at a few thousand files and
Snakemake metadata records; zip is a standard container every language and tool opens
(``unzip -l``). Image members are stored (EXR and WebP compress themselves), the JSON
members deflated.

**Format version** :data:`FORMAT_VERSION`, recorded in the archive's comment (read
with its directory, at no cost), in ``batch.json`` and in each ``frameset.json``. Every
read checks it: a shard of another version fails with a :class:`DepthGTError` that
names the shard, its version and the command that rebuilds it (nothing is misread).
Version 3 stores (:data:`CHANNELS`; version 2 had Z at 2^-15 m, S at 2^-14 m, the
fused samples' count N and weight sum W, and rgb.png; version 1 float32 images and the
patch crops themselves):

* ``gt.exr``: lossless HTJ2K, two channels as integers: ``Z`` the GT depth in fixed
  point, units of 2^-14 m (:data:`GT_UNITS`: 61 um, max rounding error 30.5 um), ``S``
  its expected standard deviation on a logarithmic grid of 8 steps per octave
  (:data:`GT_LOG_GRID`: max relative error 4.4 %);
* ``input.exr``: ZIP or HTJ2K, the smaller; ``Z`` exactly as the sensor measured it: fixed point in the
  sensor's units when the depth is a multiple of them (:data:`SENSOR_UNITS`: mm, TUM's
  1/5000 m), float32 otherwise; ``T`` (clean truth) in units of 2^-15 m;
* ``rgb.webp`` (:data:`RGB_MEMBER`): the target colour, lossless WebP;
* ``patches.npz``: the crop boxes, missing ratios and kept flags
  (:func:`depthgt.gt.patches.patch_record`); the crops are cut from the frame images
  on read (:func:`read_patches_at`), the arrays the build kept.

The readers return float32 metres (0 = invalid) and (H, W, 3) uint8 colour, the patch
crops as the build cut them.

A frame set is addressed by its **location** ``<shard path>/<target:06d>`` (the
``frameset`` column of the manifests); a member by ``<location>/<name>``. A location may
also be a plain folder holding the six files (what :func:`extract_frameset` writes).

Random access to many frame sets (a torch Dataset, an export) goes through a
:class:`ShardReader`, which keeps the shards it read open in the process that opened
them.
"""

from __future__ import annotations

import contextlib
import io as _io
import json
import os
import tempfile
import zipfile
import zlib
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from depthgt import io
from depthgt.atomic import write_atomic
from depthgt.errors import DepthGTError
from depthgt.gt.patches import CUT_KEYS, cut_patches
from depthgt.gt.sizes import MEASURED_FRAMESET_BYTES, MEASURED_FRAMESET_FIXED_BYTES, MEASURED_RESIZE
from depthgt.status import Status

__all__ = [
    "FRAMESET_FILES",
    "FrameSetRecord",
    "location",
    "shard_path",
    "write_shard",
    "shard_targets",
    "read_batch",
    "read_batch_frames",
    "ShardReader",
    "member_bytes",
    "read_json",
    "read_npz",
    "read_exr_member",
    "frameset_files",
    "find_frameset",
    "read_frameset",
    "read_frameset_at",
    "FrameImages",
    "FRAME_DEPTHS",
    "read_frame_images",
    "extract_frameset",
    "FORMAT_VERSION",
    "MEASURED_FRAMESET_BYTES",
    "MEASURED_RESIZE",
    "MEASURED_FRAMESET_FIXED_BYTES",
    "GT_UNITS",
    "GT_LOG_GRID",
    "RGB_MEMBER",
    "TRUTH_UNITS",
    "SENSOR_UNITS",
    "CHANNELS",
    "shard_format_version",
    "rebuild_command",
    "stored_gt",
    "stored_input",
    "write_gt_exr",
    "write_input_exr",
    "read_patches_at",
]

#: the version of the shard format this code writes and reads (module docstring)
FORMAT_VERSION = 3
#: gt.exr's fixed-point channel, units per metre: Z in units of 2^-14 m (61 um; max
#: rounding error 30.5 um, 20x below the smallest median GT sigma seen on real data,
#: 0.6 mm; up to 262 km)
GT_UNITS = {"Z": 2**14}
#: gt.exr's log-grid channel, (steps per octave, smallest value in m): S at 8 steps per
#: octave (a relative step of 2^(1/8), max relative rounding error 4.4 %, well below
#: the spread of a sigma estimated from a few dozen samples; values below 2^-20 m,
#: 0.95 um, are stored as 2^-20 m). The sigma spans 0.3 mm to 0.14 m on real data, so
#: a relative grid keeps its small values as well as its large ones
#: (docs/decisions.md "The stored format").
GT_LOG_GRID = {"S": (8, 2.0**-20)}
#: the frame set's colour member: lossless WebP (:func:`depthgt.io.write_rgb_webp`)
RGB_MEMBER = "rgb.webp"
#: input.exr's clean truth (synthetic sources), units per metre
TRUTH_UNITS = 2**15
#: raw depth units per metre of the sensors whose depth input.exr stores as integers
#: when it is exactly a multiple of them: millimetres (ScanNet, 7-Scenes, most PNG
#: depth) and TUM's 1/5000 m
SENSOR_UNITS = (1000, 5000)
_COMMENT = b"depthgt frame-set shard, format version "
#: every stored channel's meaning, unit and precision (the dataset card's ``encoding``)
CHANNELS = {
    "gt.exr": {
        "Z": "GT depth, m, 0 = none; fixed point in units of 2^-14 m (max rounding error 3.05e-05 m)",
        "S": "expected standard deviation of Z, m, 0 = none; log grid of 8 steps per octave from 2^-20 m "
        "(max relative rounding error 4.4 %)",
    },
    "input.exr": {
        "Z": "resized raw sensor depth, m, 0 = none; exact (integers in the sensor's units, mm or 1/5000 m, "
        "or float32)",
        "T": "clean truth depth of synthetic sources, m, 0 = none; fixed point in units of 2^-15 m "
        "(max rounding error 1.53e-05 m)",
    },
    RGB_MEMBER: {"RGB": "target colour, 8-bit sRGB, lossless WebP (every value exact)"},
    "patches.npz": {
        "boxes": "crop boxes (y0, x0, h, w) in pixels, with missing ratios and kept flags; "
        "the crops are cut from the images above on read"
    },
}

# MEASURED_FRAMESET_BYTES, MEASURED_RESIZE, MEASURED_FRAMESET_FIXED_BYTES: the format's
# measured size, defined in the import-free depthgt.gt.sizes (the space check's) and
# exported here too

FRAMESET_FILES = ("gt.exr", "input.exr", RGB_MEMBER, "poses.json", "patches.npz", "frameset.json")
BATCH_MEMBER = "batch.json"


def shard_path(results: str | Path, dataset: str, scene: str, first: int, last: int) -> Path:
    """The shard of the batch of targets ``first``..``last`` of a scene."""
    return Path(results) / "framesets" / dataset / scene / f"{int(first):06d}-{int(last):06d}.zip"


def location(shard: str | Path, target: int) -> str:
    """The location of frame set ``target`` in ``shard``."""
    return f"{shard}/{int(target):06d}"


def _split(loc: str | Path) -> tuple[Path | None, str]:
    """(archive, path inside it) of a location or member path; (None, loc) outside any."""
    text = str(loc)
    marker = ".zip/"
    cut = text.find(marker)
    if cut < 0:
        return None, text
    return Path(text[: cut + 4]), text[cut + len(marker) :]


def write_shard(
    path: str | Path, built: dict[int, Path], batch: list[dict[str, Any]], frames: list[dict[str, Any]] | None = None
) -> Path:
    """Write a shard atomically: the files of each built frame set (``target -> folder``,
    e.g. holding :data:`FRAMESET_FILES`) as ``{target:06d}/<name>`` and ``batch.json``
    (one record per target of the slice; with ``frames``, one record per frame the
    batch read, :meth:`depthgt.gt.cache.FrameCheck.to_dict`).
    """

    def member(name: str) -> zipfile.ZipInfo:
        # a fixed time stamp: the same frame sets give the same bytes (reruns compare equal)
        info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
        # JSON deflates to a third; EXR, PNG and npz compress themselves
        info.compress_type = zipfile.ZIP_DEFLATED if name.endswith(".json") else zipfile.ZIP_STORED
        return info

    def _write(tmp: Path) -> None:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as z:
            z.comment = _COMMENT + str(FORMAT_VERSION).encode()
            for target in sorted(built):
                for f in sorted(p for p in Path(built[target]).iterdir() if p.is_file()):
                    z.writestr(member(f"{int(target):06d}/{f.name}"), f.read_bytes())
            doc = {"format_version": FORMAT_VERSION, "framesets": batch}
            if frames is not None:
                doc["frames"] = list(frames)
            z.writestr(member(BATCH_MEMBER), json.dumps(doc, indent=1, sort_keys=True))

    return write_atomic(path, _write)


def shard_format_version(z: zipfile.ZipFile) -> int:
    """The format version an open shard records in its comment (1: written before
    versions were recorded)."""
    comment = z.comment
    if comment.startswith(_COMMENT) and comment[len(_COMMENT) :].isdigit():
        return int(comment[len(_COMMENT) :])
    return 1


def rebuild_command(path: str | Path) -> str:
    """How to build a shard again: ``depthgt rebuild DATASET SCENE`` for a frame-set
    shard (``.../framesets/DATASET/SCENE/*.zip``); an RDE shard
    (``.../rde/DATASET/SCENE/frames.zip``) is removed and built again by name; a frame
    set elsewhere (a folder) is extracted again from its rebuilt shard."""
    parts = Path(path).parts
    if len(parts) >= 4 and parts[-4] == "framesets":
        return f"depthgt rebuild {parts[-3]} {parts[-2]}"
    if len(parts) >= 4 and parts[-4] == "rde":
        return f"rm {Path(path)} && depthgt build {Path(path)}"
    return "depthgt rebuild DATASET SCENE, then depthgt extract DATASET SCENE TARGET DEST"


def _old_format(where: str | Path, version: int, shard: str | Path) -> DepthGTError:
    return DepthGTError(
        f"{where} is in frame-set format version {version}; this depthgt reads version "
        f"{FORMAT_VERSION} only: rebuild it (`{rebuild_command(shard)}`)"
    )


def _zip(path: Path) -> zipfile.ZipFile:
    if not path.is_file():
        raise DepthGTError(f"frame-set shard {path} does not exist (not built yet?)")
    try:
        z = zipfile.ZipFile(path)
    except zipfile.BadZipFile as exc:
        raise DepthGTError(f"frame-set shard {path} is not a readable zip archive ({exc}): rebuild it") from exc
    version = shard_format_version(z)
    if version != FORMAT_VERSION:
        z.close()
        raise _old_format(f"frame-set shard {path}", version, path)
    return z


def _batch_doc(shard: str | Path) -> dict[str, Any]:
    with _zip(Path(shard)) as z:
        return json.loads(z.read(BATCH_MEMBER))


def read_batch(shard: str | Path) -> list[dict[str, Any]]:
    """``batch.json`` of a shard: target, status, reason (and members, split) per target."""
    return _batch_doc(shard)["framesets"]


def read_batch_frames(shard: str | Path) -> list[dict[str, Any]]:
    """The frames a shard's batch read: position, frame_id, valid, reason, message each
    (none for an RDE shard)."""
    return _batch_doc(shard).get("frames", [])


def shard_targets(shard: str | Path) -> list[int]:
    """Targets of the frame sets built into a shard."""
    with _zip(Path(shard)) as z:
        return sorted({int(n.split("/")[0]) for n in z.namelist() if n.endswith("/frameset.json")})


def _read_member(z: zipfile.ZipFile, archive: Path, inner: str) -> bytes:
    try:
        return z.read(inner)
    except KeyError:
        raise DepthGTError(f"{archive} has no member {inner} (frame set not built in this shard)") from None
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError) as exc:
        # a stored member whose bytes changed fails its CRC-32 check here
        raise DepthGTError(
            f"frame-set shard {archive} is corrupt: member {inner} does not read back ({exc}); "
            "rebuild the shard (`depthgt verify` lists every damaged one)"
        ) from exc


def member_bytes(member: str | Path) -> bytes:
    """The bytes of ``<location>/<name>`` (inside a shard or in a folder)."""
    archive, inner = _split(member)
    if archive is None:
        path = Path(inner)
        if not path.is_file():
            raise DepthGTError(f"{path} does not exist")
        return path.read_bytes()
    with _zip(archive) as z:
        return _read_member(z, archive, inner)


class ShardReader:
    """Reads members of frame-set shards (and of plain frame-set folders), keeping the
    shards open between reads: random access to frame sets spread over thousands of
    shards without opening and parsing a zip directory per read.

    Handles belong to the process that opened them. A forked process (a DataLoader
    worker) shares its parent's file offsets, so reading through the parent's handles
    would interleave seeks; the reader notices the new process id and opens its own.
    Pickling (spawn) carries no handle. At most ``max_open`` shards stay open, the least
    recently read closed first (file-descriptor limits).

    >>> reader = ShardReader()
    >>> reader.read("/nonexistent/000006-000007.zip/000006/frameset.json")
    Traceback (most recent call last):
    ...
    depthgt.errors.DepthGTError: frame-set shard /nonexistent/000006-000007.zip does not exist (not built yet?)
    """

    def __init__(self, max_open: int = 64):
        if max_open < 1:
            raise ValueError(f"ShardReader: max_open must be >= 1, got {max_open}")
        self.max_open = int(max_open)
        self._pid = os.getpid()
        self._open: OrderedDict[Path, zipfile.ZipFile] = OrderedDict()

    def __getstate__(self) -> dict[str, Any]:
        return {"max_open": self.max_open}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["max_open"])

    def __enter__(self) -> ShardReader:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        """Close the shards this process opened."""
        if self._pid == os.getpid():
            for z in self._open.values():
                z.close()
        self._open.clear()

    @property
    def open_shards(self) -> list[Path]:
        """The shards this process holds open, least recently read first."""
        return list(self._open) if self._pid == os.getpid() else []

    def _archive(self, path: Path) -> zipfile.ZipFile:
        if self._pid != os.getpid():
            # the parent's handles share its file offsets: never read through them here
            # (dropping them closes only this process's copies of the descriptors)
            self._open = OrderedDict()
            self._pid = os.getpid()
        z = self._open.get(path)
        if z is None:
            z = self._open[path] = _zip(path)
            while len(self._open) > self.max_open:
                self._open.popitem(last=False)[1].close()
        else:
            self._open.move_to_end(path)
        return z

    def read(self, member: str | Path) -> bytes:
        """The bytes of ``<location>/<name>`` (:func:`member_bytes`, with open shards kept).

        Raises:
            DepthGTError: naming the shard when it is missing, not a zip archive, lacks
                the member or the member fails its checksum; naming the file for a folder.
        """
        archive, inner = _split(member)
        if archive is None:
            return member_bytes(member)
        return _read_member(self._archive(archive), archive, inner)


def read_json(member: str | Path) -> Any:
    return json.loads(member_bytes(member))


def read_npz(member: str | Path) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` member, loaded (a patches.npz holds the record of the
    patches, :data:`depthgt.gt.patches.RECORD_KEYS`; the crops: :func:`read_patches_at`)."""
    with np.load(_io.BytesIO(member_bytes(member))) as z:
        return {k: z[k] for k in z.files}


def stored_gt(channels: dict[str, np.ndarray], where: str = "gt.exr") -> dict[str, np.ndarray]:
    """gt.exr's channels (``Z``, optionally ``S``) as :func:`write_gt_exr` stores them
    and every reader gets them back: float32 on the grids of :data:`GT_UNITS` and
    :data:`GT_LOG_GRID`. The build cuts its patches from these, so that the crops a
    reader cuts again are the ones the build kept.

    Raises:
        ValueError: an unknown channel, or a negative or non-finite value (named).
    """
    unknown = sorted(set(channels) - set(GT_UNITS) - set(GT_LOG_GRID))
    if unknown:
        raise ValueError(f"{where}: unknown GT channels {unknown} (known: {sorted({*GT_UNITS, *GT_LOG_GRID})})")

    def grid(k: str, v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, dtype=np.float32)
        if k in GT_UNITS:
            return io.on_fixed_point_grid(v, GT_UNITS[k], f"{where} channel {k}")
        return io.on_log_grid(v, *GT_LOG_GRID[k], f"{where} channel {k}")

    return {k: grid(k, v) for k, v in channels.items()}


def write_gt_exr(path: str | Path, channels: dict[str, np.ndarray]) -> None:
    """Write gt.exr: the channels (:func:`stored_gt`'s names) on their grids, HTJ2K."""
    unknown = sorted(set(channels) - set(GT_UNITS) - set(GT_LOG_GRID))
    if unknown:
        raise ValueError(f"{path}: unknown GT channels {unknown} (known: {sorted({*GT_UNITS, *GT_LOG_GRID})})")
    io.write_exr(
        path,
        {k: np.asarray(v, dtype=np.float32) for k, v in channels.items()},
        fixed={k: u for k, u in GT_UNITS.items() if k in channels},
        log_grid={k: g for k, g in GT_LOG_GRID.items() if k in channels},
        compression="htj2k",
    )


def _sensor_units(depth_m: np.ndarray) -> int | None:
    """The first of :data:`SENSOR_UNITS` of which every depth value is exactly a
    multiple (as the depth readers divide raw units); None when there is none."""
    if not (np.isfinite(depth_m).all() and (depth_m >= 0).all()):
        return None
    for units in SENSOR_UNITS:
        if np.array_equal(io.on_fixed_point_grid(depth_m, units), depth_m):
            return units
    return None


def stored_input(
    input_m: np.ndarray, truth_m: np.ndarray | None = None, where: str = "input.exr"
) -> tuple[np.ndarray, np.ndarray | None]:
    """(input depth, clean truth) as :func:`write_input_exr` stores them: the input
    exactly, the truth on the grid of :data:`TRUTH_UNITS` (float32 metres)."""
    truth = (
        None
        if truth_m is None
        else io.on_fixed_point_grid(np.asarray(truth_m, dtype=np.float32), TRUTH_UNITS, f"{where} channel T")
    )
    return np.asarray(input_m, dtype=np.float32), truth


def write_input_exr(path: str | Path, input_m: np.ndarray, truth_m: np.ndarray | None = None) -> None:
    """Write input.exr: ``Z`` the resized raw depth, exactly (integers in the sensor's
    units when it has them, :data:`SENSOR_UNITS`, else float32), ``T`` the clean truth
    of synthetic sources in units of 2^-15 m; ZIP or HTJ2K, whichever is smaller (ZIP
    for sensor depth alone, 37 kB against 54 kB on a TUM frame; HTJ2K beside the smooth
    truth, which it holds in half ZIP's bytes)."""
    path = Path(path)
    channels = {"Z": np.asarray(input_m, dtype=np.float32)}
    units = _sensor_units(channels["Z"])
    fixed = {} if units is None else {"Z": units}
    if truth_m is not None:
        channels["T"] = np.asarray(truth_m, dtype=np.float32)
        fixed["T"] = TRUTH_UNITS
    io.write_exr(path, channels, fixed=fixed, compression="zip")
    other = path.with_name(f".{path.name}.htj2k")
    try:
        io.write_exr(other, channels, fixed=fixed, compression="htj2k")
        if other.stat().st_size < path.stat().st_size:
            os.replace(other, path)
    finally:
        other.unlink(missing_ok=True)


def _patch_record(data: bytes, loc: str | Path, keys: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """patches.npz's record (only ``keys``, when given: each array costs a header parse);
    a file of the old format (the crops themselves) is refused."""
    where = f"{loc}/patches.npz"
    try:
        with np.load(_io.BytesIO(data)) as z:
            if "has_truth" not in z.files:
                if "input" in z.files:  # format 1 stored the crops
                    raise _old_format(where, 1, _split(loc)[0] or loc)
                raise DepthGTError(f"{where}: not a patch record (arrays {sorted(z.files)})")
            return {k: z[k] for k in (z.files if keys is None else keys) if k in z.files}
    except (ValueError, OSError, zipfile.BadZipFile, EOFError) as exc:
        raise DepthGTError(f"{where}: not a readable npz file ({exc})") from exc


def _refuse_old_folder(loc: str | Path) -> None:
    """Raise the old-format error for a frame-set folder of an older format (its colour
    in rgb.png): the version its frameset.json records (1 when none)."""
    archive, inner = _split(loc)
    folder = Path(inner)
    if archive is not None or not (folder / "rgb.png").is_file():
        return
    try:
        version = int(json.loads((folder / "frameset.json").read_text()).get("format_version", 1))
    except (OSError, ValueError, TypeError, AttributeError):
        version = 1
    raise _old_format(f"frame-set folder {folder}", version, folder)


def _colour(reader: ShardReader, loc: str | Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of the frame set at ``loc`` (:data:`RGB_MEMBER`)."""
    where = f"{loc}/{RGB_MEMBER}"
    try:
        data = reader.read(where)
    except DepthGTError:
        _refuse_old_folder(loc)
        raise
    return io.decode_color(data, where, formats=("WEBP",))


def _cut(
    record: dict[str, np.ndarray],
    gt: dict[str, np.ndarray],
    inp: dict[str, np.ndarray],
    rgb: np.ndarray,
    loc: str | Path,
) -> dict[str, np.ndarray]:
    try:
        return cut_patches(
            record, inp["Z"], gt["Z"], rgb, truth_m=inp.get("T"), gt_sigma_m=gt.get("S"), where=f"{loc}/patches.npz"
        )
    except ValueError as exc:
        raise DepthGTError(str(exc)) from exc


def read_patches_at(
    loc: str | Path, reader: ShardReader | None = None, with_record: bool = True
) -> dict[str, np.ndarray]:
    """The patches of the frame set at ``loc``: the crops cut from its images at the
    recorded boxes (``input``, ``gt``, ``rgb``[, ``gt_sigma``, ``truth``]), their
    ``boxes``, and with ``with_record`` the rest of the record (``missing_input``,
    ``missing_gt``, ``all_boxes``, ``all_missing_input``, ``all_missing_gt``, ``kept``,
    ...): what patches.npz held in format 1.

    Raises:
        DepthGTError: naming the frame set: a shard or patch file of an old format, a
            missing member, a record that does not match the images.
    """
    if reader is None:
        with ShardReader(max_open=1) as own:
            return read_patches_at(loc, own, with_record)
    record = _patch_record(reader.read(f"{loc}/patches.npz"), loc, None if with_record else CUT_KEYS)
    gt = io.decode_exr(reader.read(f"{loc}/gt.exr"), f"{loc}/gt.exr")
    inp = io.decode_exr(reader.read(f"{loc}/input.exr"), f"{loc}/input.exr")
    return _cut(record, gt, inp, _colour(reader, loc), loc)


@contextlib.contextmanager
def frameset_files(loc: str | Path) -> Iterator[Path]:
    """A folder holding the files of the frame set at ``loc`` while the context lasts
    (the folder itself for a plain folder; a temporary copy for a shard member): for
    readers that need file paths (OpenEXR)."""
    archive, inner = _split(loc)
    if archive is None:
        yield Path(inner)
        return
    with _zip(archive) as z, tempfile.TemporaryDirectory(prefix="depthgt-fs-") as tmp:
        names = [n for n in z.namelist() if n.startswith(inner.rstrip("/") + "/")]
        if not names:
            raise DepthGTError(
                f"{archive} holds no frame set {inner} (skipped or not in this batch; see its batch.json)"
            )
        for n in names:
            dest = Path(tmp) / n[len(inner.rstrip("/")) + 1 :]
            dest.parent.mkdir(parents=True, exist_ok=True)
            dest.write_bytes(z.read(n))
        yield Path(tmp)


@dataclass
class FrameSetRecord:
    """The outputs of one built frame set.

    Attributes:
        gt_m: (H, W) float32 GT depth in metres (0 = none).
        gt_sigma_m: (H, W) float32 expected standard deviation of the GT in metres.
        input_m: (H, W) float32 resized raw target depth (0 = none).
        truth_m: (H, W) float32 clean depth (synthetic sources) or None.
        rgb: (H, W, 3) uint8 target colour.
        poses: poses.json's content.
        meta: frameset.json's content (split, frame ids, K, statistics, status).
        patches: the patch crops and their record (:func:`read_patches_at`).
    """

    gt_m: np.ndarray
    gt_sigma_m: np.ndarray
    input_m: np.ndarray
    truth_m: np.ndarray | None
    rgb: np.ndarray
    poses: dict[str, Any]
    meta: dict[str, Any]
    patches: dict[str, np.ndarray]


def read_frameset_at(loc: str | Path, reader: ShardReader | None = None) -> FrameSetRecord:
    """Read the frame set at a location (``<shard>/<target>`` or a folder).

    Args:
        reader: keeps the shard open for later reads (default: opened for this read).
    """
    if reader is None:
        with ShardReader(max_open=1) as own:
            return read_frameset_at(loc, own)

    def member(name: str) -> tuple[bytes, str]:
        return reader.read(f"{loc}/{name}"), f"{loc}/{name}"

    record = _patch_record(member("patches.npz")[0], loc)
    gt = io.decode_exr(*member("gt.exr"))
    inp = io.decode_exr(*member("input.exr"))
    rgb = _colour(reader, loc)
    return FrameSetRecord(
        gt_m=gt["Z"],
        gt_sigma_m=gt.get("S", np.zeros_like(gt["Z"])),
        input_m=inp["Z"],
        truth_m=inp.get("T"),
        rgb=rgb,
        poses=json.loads(member("poses.json")[0]),
        meta=json.loads(member("frameset.json")[0]),
        patches=_cut(record, gt, inp, rgb, loc),
    )


class FrameImages(NamedTuple):
    """The images of one frame set that a method runs on and is scored against.

    Attributes:
        input_m: (H, W) float32 resized raw target depth in metres (input.exr Z; 0 = none).
        gt_m: (H, W) float32 GT depth in metres (gt.exr Z; 0 = none).
        truth_m: (H, W) float32 clean depth of synthetic sources (input.exr T) or None.
        rgb: (H, W, 3) uint8 target colour.
    """

    input_m: np.ndarray
    gt_m: np.ndarray
    truth_m: np.ndarray | None
    rgb: np.ndarray

    def depth(self, name: str) -> np.ndarray | None:
        """The depth image that methods and references call ``name``: ``input``, ``gt``
        or ``truth`` (None when the frame set has no truth)."""
        if name not in FRAME_DEPTHS:
            raise ValueError(f"no depth image {name!r} in a frame set; known: {', '.join(FRAME_DEPTHS)}")
        return getattr(self, f"{name}_m")


FRAME_DEPTHS = ("input", "gt", "truth")


def read_frame_images(loc: str | Path, reader: ShardReader | None = None) -> FrameImages:
    """The images of the frame set at ``loc`` (what the evaluation, the figures and the
    RDE GT read); see :class:`FrameImages`.

    Args:
        reader: keeps the shard open for later reads (default: opened for this read).

    Raises:
        DepthGTError: a shard or folder of another format version, a missing member.
        ValueError: a depth image without its Z channel, or images of different sizes.
    """
    if reader is None:
        with ShardReader(max_open=1) as own:
            return read_frame_images(loc, own)
    inp = io.decode_exr(reader.read(f"{loc}/input.exr"), f"{loc}/input.exr")
    gt = io.decode_exr(reader.read(f"{loc}/gt.exr"), f"{loc}/gt.exr")
    rgb = _colour(reader, loc)
    d = Path(str(loc))
    for path, chans in ((d / "input.exr", inp), (d / "gt.exr", gt)):
        if "Z" not in chans:
            raise ValueError(f"{path}: no channel 'Z' (has {sorted(chans)})")
    frame = FrameImages(
        input_m=inp["Z"].astype(np.float32),
        gt_m=gt["Z"].astype(np.float32),
        truth_m=inp["T"].astype(np.float32) if "T" in inp else None,
        rgb=rgb,
    )
    if rgb.shape[:2] != frame.input_m.shape or frame.gt_m.shape != frame.input_m.shape:
        raise ValueError(
            f"{d}: image sizes differ: input {frame.input_m.shape}, gt {frame.gt_m.shape}, rgb {rgb.shape}"
        )
    return frame


def read_exr_member(member: str | Path) -> dict[str, np.ndarray]:
    """Every channel of an EXR member ``<location>/<name>`` (in a shard or a folder),
    e.g. ``read_exr_member(f"{loc}/gt.exr")["Z"]``."""
    archive, inner = _split(member)
    if archive is None:
        return io.read_exr(inner)
    return io.decode_exr(member_bytes(member), str(member))


def find_frameset(results: str | Path, dataset: str, scene: str, target: int) -> str:
    """The location of frame set ``target`` of a scene under the results folder.

    Raises:
        DepthGTError: no shard of the scene covers the target, or it was skipped (the
            message gives the reason recorded in the shard).
    """
    folder = Path(results) / "framesets" / dataset / scene
    target = int(target)
    for shard in sorted(folder.glob("*.zip")):
        first, last = (int(x) for x in shard.stem.split("-"))
        if first <= target <= last:
            for rec in read_batch(shard):
                if int(rec["target"]) == target:
                    if rec["status"] != Status.OK:
                        raise DepthGTError(
                            f"frame set {dataset}/{scene}/{target:06d} was not built: "
                            f"{rec['status']} ({rec.get('reason', '')}) [{shard}]"
                        )
                    return location(shard, target)
    raise DepthGTError(f"frame set {dataset}/{scene}/{target:06d} not built: no shard in {folder} holds it")


def read_frameset(results: str | Path, dataset: str, scene: str, target: int) -> FrameSetRecord:
    """Read one built frame set of a scene (see :func:`find_frameset`)."""
    return read_frameset_at(find_frameset(results, dataset, scene, target))


def extract_frameset(results: str | Path, dataset: str, scene: str, target: int, dest: str | Path) -> list[Path]:
    """Write one built frame set's files (:data:`FRAMESET_FILES`: gt.exr, input.exr,
    rgb.webp, poses.json, patches.npz, frameset.json) into ``dest``; returns the
    written paths."""
    loc = find_frameset(results, dataset, scene, target)
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    written = []
    for name in FRAMESET_FILES:
        (dest / name).write_bytes(member_bytes(f"{loc}/{name}"))
        written.append(dest / name)
    return written
