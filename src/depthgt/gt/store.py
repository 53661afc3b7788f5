"""Built frame sets on disk: the one writer and reader of frame-set shards.

A batch job builds a contiguous slice of one scene's frame sets and writes them as one
**shard**, an uncompressed zip archive ``{first:06d}-{last:06d}.zip`` whose members are
``{target:06d}/gt.exr``, ``input.exr``, ``rgb.png``, ``poses.json``, ``patches.npz``,
``frameset.json`` per built frame set, plus ``batch.json``: every target of the slice
with its status and, for a skipped one, the reason (``framesets``), and every frame the
batch read with whether it was usable and, if not, the reason and message naming the
file (``frames``). One file per batch instead of six
per frame set keeps a ScanNet-size build (250k frame sets) at a few thousand files and
Snakemake metadata records; zip is a standard container every language and tool opens
(``unzip -l``), and members are stored, not compressed (EXR and PNG already are).

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
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, NamedTuple

import numpy as np

from depthgt import io
from depthgt.atomic import write_atomic
from depthgt.errors import DepthGTError
from depthgt.status import Status

__all__ = ["FRAMESET_FILES", "FrameSetRecord", "location", "shard_path", "write_shard", "shard_targets", "read_batch",
           "read_batch_frames", "ShardReader", "member_bytes", "read_json", "read_npz", "read_exr_member",
           "frameset_files", "find_frameset", "read_frameset", "read_frameset_at", "FrameImages", "FRAME_DEPTHS",
           "read_frame_images",
           "extract_frameset"]

FRAMESET_FILES = ("gt.exr", "input.exr", "rgb.png", "poses.json", "patches.npz", "frameset.json")
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
    return Path(text[:cut + 4]), text[cut + len(marker):]


def write_shard(path: str | Path, built: dict[int, Path], batch: list[dict[str, Any]],
                frames: list[dict[str, Any]] | None = None) -> Path:
    """Write a shard atomically: the files of each built frame set (``target -> folder``,
    e.g. holding :data:`FRAMESET_FILES`) as ``{target:06d}/<name>`` and ``batch.json``
    (one record per target of the slice; with ``frames``, one record per frame the
    batch read, :meth:`depthgt.gt.cache.FrameCheck.to_dict`).
    """
    def member(name: str) -> zipfile.ZipInfo:
        # a fixed time stamp: the same frame sets give the same bytes (reruns compare equal)
        info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
        info.compress_type = zipfile.ZIP_STORED
        return info

    def _write(tmp: Path) -> None:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as z:
            for target in sorted(built):
                for f in sorted(p for p in Path(built[target]).iterdir() if p.is_file()):
                    z.writestr(member(f"{int(target):06d}/{f.name}"), f.read_bytes())
            doc = {"framesets": batch} if frames is None else {"framesets": batch, "frames": list(frames)}
            z.writestr(member(BATCH_MEMBER), json.dumps(doc, indent=1, sort_keys=True))

    return write_atomic(path, _write)


def _zip(path: Path) -> zipfile.ZipFile:
    if not path.is_file():
        raise DepthGTError(f"frame-set shard {path} does not exist (not built yet?)")
    try:
        return zipfile.ZipFile(path)
    except zipfile.BadZipFile as exc:
        raise DepthGTError(f"frame-set shard {path} is not a readable zip archive ({exc}): rebuild it") from exc


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
        raise DepthGTError(f"frame-set shard {archive} is corrupt: member {inner} does not read back ({exc}); "
                           "rebuild the shard (`depthgt verify` lists every damaged one)") from exc


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

    def __enter__(self) -> "ShardReader":
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
    """Every array of an ``.npz`` member, loaded."""
    with np.load(_io.BytesIO(member_bytes(member))) as z:
        return {k: z[k] for k in z.files}


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
            raise DepthGTError(f"{archive} holds no frame set {inner} (skipped or not in this batch; see its batch.json)")
        for n in names:
            dest = Path(tmp) / n[len(inner.rstrip('/')) + 1:]
            dest.parent.mkdir(parents=True, exist_ok=True)
            dest.write_bytes(z.read(n))
        yield Path(tmp)


@dataclass
class FrameSetRecord:
    """The outputs of one built frame set.

    Attributes:
        gt_m: (H, W) float32 GT depth in metres (0 = none).
        gt_sigma_m: (H, W) float32 expected standard deviation of the GT in metres.
        gt_weight: (H, W) float32 weight sum of the fused samples.
        gt_count: (H, W) float32 number of fused samples.
        input_m: (H, W) float32 resized raw target depth (0 = none).
        truth_m: (H, W) float32 clean depth (synthetic sources) or None.
        rgb: (H, W, 3) uint8 target colour.
        poses: poses.json's content.
        meta: frameset.json's content (split, frame ids, K, statistics, status).
        patches: patches.npz's arrays.
    """

    gt_m: np.ndarray
    gt_sigma_m: np.ndarray
    gt_weight: np.ndarray
    gt_count: np.ndarray
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

    gt = io.decode_exr(*member("gt.exr"))
    inp = io.decode_exr(*member("input.exr"))
    with np.load(_io.BytesIO(member("patches.npz")[0])) as z:
        patches = {k: z[k] for k in z.files}
    return FrameSetRecord(
        gt_m=gt["Z"], gt_sigma_m=gt.get("S", np.zeros_like(gt["Z"])), gt_weight=gt["W"], gt_count=gt["N"],
        input_m=inp["Z"], truth_m=inp.get("T"), rgb=io.decode_color(*member("rgb.png"), formats=("PNG",)),
        poses=json.loads(member("poses.json")[0]), meta=json.loads(member("frameset.json")[0]),
        patches=patches)


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


def read_frame_images(loc: str | Path) -> FrameImages:
    """The images of the frame set at ``loc`` (what the evaluation, the figures and the
    RDE GT read); see :class:`FrameImages`.

    Raises:
        ValueError: a depth image without its Z channel, or images of different sizes.
    """
    with frameset_files(loc) as d:
        inp = io.read_exr(d / "input.exr")
        gt = io.read_exr(d / "gt.exr")
        rgb = io.read_rgb(d / "rgb.png")
    d = Path(str(loc))
    for path, chans in ((d / "input.exr", inp), (d / "gt.exr", gt)):
        if "Z" not in chans:
            raise ValueError(f"{path}: no channel 'Z' (has {sorted(chans)})")
    frame = FrameImages(input_m=inp["Z"].astype(np.float32), gt_m=gt["Z"].astype(np.float32),
                        truth_m=inp["T"].astype(np.float32) if "T" in inp else None, rgb=rgb)
    if rgb.shape[:2] != frame.input_m.shape or frame.gt_m.shape != frame.input_m.shape:
        raise ValueError(f"{d}: image sizes differ: input {frame.input_m.shape}, gt {frame.gt_m.shape}, rgb {rgb.shape}")
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
                        raise DepthGTError(f"frame set {dataset}/{scene}/{target:06d} was not built: "
                                           f"{rec['status']} ({rec.get('reason', '')}) [{shard}]")
                    return location(shard, target)
    raise DepthGTError(f"frame set {dataset}/{scene}/{target:06d} not built: no shard in {folder} holds it")


def read_frameset(results: str | Path, dataset: str, scene: str, target: int) -> FrameSetRecord:
    """Read one built frame set of a scene (see :func:`find_frameset`)."""
    return read_frameset_at(find_frameset(results, dataset, scene, target))


def extract_frameset(results: str | Path, dataset: str, scene: str, target: int, dest: str | Path) -> list[Path]:
    """Write one built frame set's files (gt.exr, input.exr, rgb.png, poses.json,
    patches.npz, frameset.json) into ``dest``; returns the written paths."""
    loc = find_frameset(results, dataset, scene, target)
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    written = []
    for name in FRAMESET_FILES:
        (dest / name).write_bytes(member_bytes(f"{loc}/{name}"))
        written.append(dest / name)
    return written
