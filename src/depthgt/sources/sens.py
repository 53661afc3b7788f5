"""Lazy reader of ScanNet's raw ``.sens`` RGB-D stream files (format version 4).

Layout (little-endian; ScanNet ``SensReader/c++/src/sensorData.h``)::

    uint32  version (= 4)
    uint64  strlen, then strlen bytes of sensor name
    float32 4x4 intrinsic_color, extrinsic_color, intrinsic_depth, extrinsic_depth (row-major)
    int32   color_compression_type  (-1 unknown, 0 raw, 1 png, 2 jpeg)
    int32   depth_compression_type  (-1 unknown, 0 raw_ushort, 1 zlib_ushort, 2 occi_ushort)
    uint32  color_width, color_height, depth_width, depth_height
    float32 depth_shift             (raw depth units per metre, typically 1000)
    uint64  num_frames
    num_frames x {
        float32 4x4 camera_to_world
        uint64  timestamp_color, timestamp_depth, color_size_bytes, depth_size_bytes
        color_size_bytes of colour payload, depth_size_bytes of depth payload
    }
    uint64  num_imu_frames, then num_imu_frames x 128 bytes (five float64 3-vectors and
            a uint64 timestamp); not used, and absent in some files

Opening a file parses the header and walks the frame headers once with seeks, building
an offset table; no payload is decoded or held. Whatever follows the announced frames
must be that IMU block (or nothing): anything else is recorded in ``problems`` with the
number of further frame records it appears to hold, since a header whose frame count is
too low would otherwise drop those frames without a word.

Every payload is untrusted: a size beyond what a frame of the header's size can take is
rejected before reading, images are checked by :func:`depthgt.io.decode_color` (header
size, format, truncation, bit depth) and zlib depth is inflated to at most the
``h * w * 2`` bytes it must hold. :meth:`SensFile.read_color` and
:meth:`SensFile.read_depth_m` seek to one frame and decode it. The per-frame header
walk is a Python loop over frames (not pixels): each frame's position depends on the
previous frame's payload sizes, so it cannot be vectorised.

Python's :mod:`struct` and :mod:`zlib` and OpenCV's ``imdecode`` do the decoding; no
library reads this container, hence this module.
"""

from __future__ import annotations

import logging
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from depthgt.errors import FrameError, SourceError
from depthgt.io import MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE, decode_color

__all__ = ["SensHeader", "SensFile", "COLOR_COMPRESSION", "DEPTH_COMPRESSION"]

log = logging.getLogger(__name__)

COLOR_COMPRESSION = {-1: "unknown", 0: "raw", 1: "png", 2: "jpeg"}
DEPTH_COMPRESSION = {-1: "unknown", 0: "raw_ushort", 1: "zlib_ushort", 2: "occi_ushort"}
SUPPORTED_COLOR = {"raw", "png", "jpeg"}
SUPPORTED_DEPTH = {"raw_ushort", "zlib_ushort"}

_VERSION = 4
_MAX_NAME = 1 << 16  # a longer sensor name means the header is not a .sens header
_MATS = struct.Struct("<64f")  # four 4x4 float32 calibration matrices
_TAIL = struct.Struct("<iiIIIIfQ")  # compressions, sizes, depth_shift, num_frames
_FRAME = struct.Struct("<16fQQQQ")  # pose, timestamps, payload sizes (96 bytes)
_IMU_COUNT = struct.Struct("<Q")
_IMU_FRAME_BYTES = 5 * 3 * 8 + 8  # rotation rate, acceleration, magnetic field, attitude, gravity; timestamp
_PAYLOAD_SLACK = 64 * 1024  # headers and tables of an encoded image beyond its pixels
_FORMAT_OF = {"png": "PNG", "jpeg": "JPEG"}


def max_payload_bytes(compression: str, hw: tuple[int, int], bytes_per_pixel: int) -> int:
    """Largest payload a frame of ``hw`` pixels can need (bytes).

    Raw: exactly ``h * w * bytes_per_pixel``. zlib: deflate's worst case adds 5 bytes
    per 16 KiB block. PNG/JPEG: twice the raw size plus headers (uniform noise at
    640x480 takes 1.37x raw as a quality-100 4:4:4 JPEG, 1.002x as an uncompressed PNG).
    """
    h, w = hw
    raw = h * w * bytes_per_pixel
    if compression in ("raw", "raw_ushort"):
        return raw
    if compression == "zlib_ushort":
        return raw + raw // 1000 + 1024
    return 2 * raw + _PAYLOAD_SLACK


@dataclass(frozen=True)
class SensHeader:
    """The fixed header of a ``.sens`` file.

    Matrices are (4, 4) float64 (stored as float32). Sizes are ``(H, W)`` in pixels.
    ``depth_shift`` is raw depth units per metre.
    """

    version: int
    sensor_name: str
    intrinsic_color: np.ndarray
    extrinsic_color: np.ndarray
    intrinsic_depth: np.ndarray
    extrinsic_depth: np.ndarray
    color_compression: str
    depth_compression: str
    color_hw: tuple[int, int]
    depth_hw: tuple[int, int]
    depth_shift: float
    num_frames: int
    header_bytes: int


def _read_exact(f, n: int, path: Path, what: str) -> bytes:
    data = f.read(n)
    if len(data) != n:
        raise SourceError(f"{path}: truncated .sens header (while reading {what}: {len(data)} of {n} bytes)")
    return data


def read_header(path: str | Path) -> SensHeader:
    """Parse the fixed header of a ``.sens`` file.

    Raises:
        SourceError: file missing, truncated header, wrong version, nonsensical sizes
            or unsupported compression types; the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise SourceError(f"{path}: .sens file not found")
    with path.open("rb") as f:
        (version,) = struct.unpack("<I", _read_exact(f, 4, path, "version"))
        if version != _VERSION:
            raise SourceError(f"{path}: .sens version {version} is not supported (expected {_VERSION})")
        (strlen,) = struct.unpack("<Q", _read_exact(f, 8, path, "sensor name length"))
        if strlen > _MAX_NAME:
            raise SourceError(f"{path}: corrupt .sens header (sensor name length {strlen})")
        name = _read_exact(f, strlen, path, "sensor name").decode("utf-8", errors="replace")
        mats = np.array(_MATS.unpack(_read_exact(f, _MATS.size, path, "calibration")), dtype=np.float64)
        mats = mats.reshape(4, 4, 4)
        c_comp, d_comp, cw, ch, dw, dh, shift, n = _TAIL.unpack(_read_exact(f, _TAIL.size, path, "image format"))
        header_bytes = f.tell()
    color_compression = COLOR_COMPRESSION.get(c_comp, f"invalid({c_comp})")
    depth_compression = DEPTH_COMPRESSION.get(d_comp, f"invalid({d_comp})")
    if color_compression not in SUPPORTED_COLOR:
        raise SourceError(
            f"{path}: colour compression {color_compression!r} is not supported ({sorted(SUPPORTED_COLOR)})"
        )
    if depth_compression not in SUPPORTED_DEPTH:
        raise SourceError(
            f"{path}: depth compression {depth_compression!r} is not supported ({sorted(SUPPORTED_DEPTH)})"
        )
    if min(cw, ch, dw, dh) == 0 or max(cw, ch, dw, dh) > MAX_IMAGE_SIDE or max(cw * ch, dw * dh) > MAX_IMAGE_PIXELS:
        raise SourceError(
            f"{path}: corrupt .sens header (colour {cw}x{ch}, depth {dw}x{dh}; at most {MAX_IMAGE_SIDE} pixels per "
            f"side and {MAX_IMAGE_PIXELS} in all)"
        )
    if not (np.isfinite(shift) and shift > 0):
        raise SourceError(f"{path}: corrupt .sens header (depth_shift {shift})")
    return SensHeader(
        version=version,
        sensor_name=name,
        intrinsic_color=mats[0],
        extrinsic_color=mats[1],
        intrinsic_depth=mats[2],
        extrinsic_depth=mats[3],
        color_compression=color_compression,
        depth_compression=depth_compression,
        color_hw=(int(ch), int(cw)),
        depth_hw=(int(dh), int(dw)),
        depth_shift=float(shift),
        num_frames=int(n),
        header_bytes=header_bytes,
    )


class SensFile:
    """Random access to the frames of one ``.sens`` file.

    Attributes:
        path: the file.
        header: :class:`SensHeader`.
        poses: (N, 4, 4) float64 camera-to-world (may hold -inf/NaN where ScanNet's
            tracking was lost).
        timestamps_color, timestamps_depth: (N,) uint64.
        color_offsets, color_sizes, depth_offsets, depth_sizes: (N,) int64 byte
            positions and lengths of each payload.
        problems: human-readable notes on what could not be indexed (e.g. a
            truncated file); empty when the file is complete.

    ``N = len(self)`` is the number of frames that could be indexed; it is smaller
    than ``header.num_frames`` for a truncated file (a warning is logged).
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.header = read_header(self.path)
        self.problems: list[str] = []
        self._index()

    def _index(self) -> None:
        h = self.header
        file_size = self.path.stat().st_size
        n = h.num_frames
        # num_frames comes from the file: never pre-allocate more than could fit.
        cap = min(n, max(0, (file_size - h.header_bytes) // _FRAME.size))
        poses = np.empty((cap, 16), dtype=np.float64)
        ts = np.empty((cap, 2), dtype=np.uint64)
        sizes = np.empty((cap, 2), dtype=np.int64)
        offsets = np.empty(cap, dtype=np.int64)  # start of the colour payload
        found = 0
        reason = ""
        with self.path.open("rb") as f:
            pos = h.header_bytes
            for i in range(cap):
                frame = _read_frame_header(f, pos, file_size)
                if isinstance(frame, str):
                    reason = f"frame {i} {frame}"
                    break
                vals, end = frame
                poses[i] = vals[:16]
                ts[i] = vals[16:18]
                sizes[i] = (vals[18], vals[19])
                offsets[i] = pos + _FRAME.size
                pos = end
                found += 1
            else:
                if cap < n:
                    reason = f"file of {file_size} bytes cannot hold frame {cap}"
            if found < n:
                self._problem(f"{self.path}: truncated .sens: header announces {n} frames, {found} found ({reason})")
            else:
                self._check_trailing(f, pos, file_size)
        self.poses = poses[:found].reshape(found, 4, 4)
        self.timestamps_color = ts[:found, 0].copy()
        self.timestamps_depth = ts[:found, 1].copy()
        self.color_offsets = offsets[:found].copy()
        self.color_sizes = sizes[:found, 0].copy()
        self.depth_offsets = self.color_offsets + self.color_sizes
        self.depth_sizes = sizes[:found, 1].copy()

    def _problem(self, msg: str) -> None:
        log.warning("%s", msg)
        self.problems.append(msg)

    def _check_trailing(self, f, pos: int, file_size: int) -> None:
        """After the announced frames only the IMU block may follow (or nothing)."""
        rest = file_size - pos
        if rest == 0:
            return
        if rest >= _IMU_COUNT.size:
            f.seek(pos)
            (n_imu,) = _IMU_COUNT.unpack(f.read(_IMU_COUNT.size))
            if rest == _IMU_COUNT.size + n_imu * _IMU_FRAME_BYTES:
                return
        more = _count_frame_records(f, pos, file_size)
        hint = (
            (
                f"it holds {more} more frame record(s): the header's frame count ({self.header.num_frames}) is "
                "probably too low and those frames are not read"
            )
            if more
            else "it is not a valid IMU block"
        )
        self._problem(
            f"{self.path}: {rest} unexpected bytes after the {self.header.num_frames} announced frames ({hint})"
        )

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def _check_index(self, i: int) -> int:
        if not 0 <= i < len(self):
            raise IndexError(f"{self.path}: frame {i} out of range 0..{len(self) - 1}")
        return int(i)

    def _payload(self, offset: int, size: int, where: str, limit: int) -> bytes:
        if size == 0:
            raise FrameError(f"{where}: empty payload (0 bytes)", "unreadable")
        if size > limit:
            raise FrameError(
                f"{where}: payload of {size} bytes, more than a frame of this size can take ({limit})", "unreadable"
            )
        with self.path.open("rb") as f:
            f.seek(offset)
            data = f.read(size)
        if len(data) != size:
            raise FrameError(f"{where}: payload at byte {offset} is cut short", "unreadable")
        return data

    def read_color(self, i: int) -> np.ndarray:
        """Colour of frame ``i`` as (H, W, 3) uint8 RGB at ``header.color_hw``.

        Raises:
            FrameError: empty, oversized, truncated or corrupt payload, a payload that is
                not the header's format or not 8-bit grey/RGB ("unreadable"), or a
                declared size differing from the header ("size_mismatch"); the message
                names file and frame.
        """
        i = self._check_index(i)
        h, w = self.header.color_hw
        comp = self.header.color_compression
        where = f"{self.path} frame {i} colour"
        data = self._payload(
            int(self.color_offsets[i]), int(self.color_sizes[i]), where, max_payload_bytes(comp, (h, w), 3)
        )
        if comp == "raw":
            if len(data) != h * w * 3:
                raise FrameError(f"{where}: raw payload has {len(data)} bytes, expected {h * w * 3}", "unreadable")
            return np.frombuffer(data, dtype=np.uint8).reshape(h, w, 3).copy()
        return decode_color(data, where, expected_hw=(h, w), formats=(_FORMAT_OF[comp],))

    def read_depth_raw(self, i: int) -> np.ndarray:
        """Depth of frame ``i`` as (H, W) uint16 raw units (``header.depth_shift`` per metre).

        Raises:
            FrameError: empty or oversized payload, corrupt or truncated zlib stream, a
                stream inflating beyond ``h * w * 2`` bytes, or a wrong length
                ("unreadable").
        """
        i = self._check_index(i)
        h, w = self.header.depth_hw
        expected = h * w * 2
        comp = self.header.depth_compression
        where = f"{self.path} frame {i} depth"
        data = self._payload(
            int(self.depth_offsets[i]), int(self.depth_sizes[i]), where, max_payload_bytes(comp, (h, w), 2)
        )
        if comp == "zlib_ushort":
            data = _inflate_bounded(data, expected, where)
        if len(data) != expected:
            raise FrameError(f"{where}: {len(data)} bytes of depth, expected {expected} ({w}x{h} uint16)", "unreadable")
        return np.frombuffer(data, dtype="<u2").reshape(h, w).astype(np.uint16)

    def read_depth_m(self, i: int) -> np.ndarray:
        """Depth of frame ``i`` as (H, W) float32 metres, 0 = invalid."""
        return self.read_depth_raw(i).astype(np.float32) / np.float32(self.header.depth_shift)


def _read_frame_header(f, pos: int, file_size: int) -> tuple[tuple, int] | str:
    """The frame record at byte ``pos``: (unpacked header fields, end of its payloads),
    or why there is none (a string)."""
    f.seek(pos)
    raw = f.read(_FRAME.size)
    if len(raw) != _FRAME.size:
        return f"header cut at byte {pos + len(raw)}"
    vals = _FRAME.unpack(raw)
    end = pos + _FRAME.size + vals[18] + vals[19]
    if end > file_size:
        return f"payload ends at byte {end} beyond the file size {file_size}"
    return vals, end


def _count_frame_records(f, pos: int, file_size: int, limit: int = 1_000_000) -> int:
    """How many consecutive frame records fit from ``pos`` to the end of the file,
    each with a non-empty colour and depth payload (a walk over headers, no payload read)."""
    count = 0
    while count < limit:
        frame = _read_frame_header(f, pos, file_size)
        if isinstance(frame, str) or frame[0][18] == 0 or frame[0][19] == 0:
            break
        pos = frame[1]
        count += 1
    return count


def _inflate_bounded(data: bytes, expected: int, where: str) -> bytes:
    """zlib-inflate ``data`` into at most ``expected`` bytes (a "zlib bomb" stops there).

    Raises:
        FrameError: ("unreadable") corrupt stream, a stream that would inflate beyond
            ``expected`` bytes, or one that ends early.
    """
    inflater = zlib.decompressobj()
    try:
        out = inflater.decompress(data, expected)
        # input left over once ``expected`` bytes are out: only the stream's end may remain
        if inflater.unconsumed_tail and inflater.decompress(inflater.unconsumed_tail, 1):
            raise FrameError(
                f"{where}: zlib payload inflates beyond the {expected} bytes of a depth image", "unreadable"
            )
    except zlib.error as exc:
        raise FrameError(f"{where}: corrupt zlib payload ({exc})", "unreadable") from exc
    if not inflater.eof:
        raise FrameError(f"{where}: truncated zlib payload ({len(out)} of {expected} bytes inflated)", "unreadable")
    return out
