"""Writer of ScanNet ``.sens`` files (version 4) from numpy arrays, for tests only.

It writes the layout documented in :mod:`depthgt.sources.sens` independently of the
reader (plain ``struct.pack`` of each field in order), so that a round trip checks the
reader against the format and not against itself.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np

_COLOR_CODES = {"raw": 0, "png": 1, "jpeg": 2}
_DEPTH_CODES = {"raw_ushort": 0, "zlib_ushort": 1}


def encode_color(rgb: np.ndarray, compression: str) -> bytes:
    """(H, W, 3) uint8 RGB -> payload bytes."""
    if compression == "raw":
        return np.ascontiguousarray(rgb, dtype=np.uint8).tobytes()
    ext = {"png": ".png", "jpeg": ".jpg"}[compression]
    ok, buf = cv2.imencode(ext, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok
    return buf.tobytes()


def encode_depth(depth_raw: np.ndarray, compression: str) -> bytes:
    """(H, W) uint16 -> payload bytes."""
    data = np.ascontiguousarray(depth_raw, dtype="<u2").tobytes()
    return zlib.compress(data) if compression == "zlib_ushort" else data


def write_sens(
    path: str | Path,
    rgbs: list[np.ndarray],
    depths_raw: list[np.ndarray],
    poses: list[np.ndarray],
    K_color: np.ndarray,
    K_depth: np.ndarray,
    depth_shift: float = 1000.0,
    color_compression: str = "jpeg",
    depth_compression: str = "zlib_ushort",
    sensor_name: str = "test-sensor",
    num_frames: int | None = None,
    color_payloads: list[bytes] | None = None,
    depth_payloads: list[bytes] | None = None,
    imu_frames: int | None = 0,
) -> Path:
    """Write a ``.sens`` file.

    Args:
        rgbs: per frame (Hc, Wc, 3) uint8 RGB.
        depths_raw: per frame (Hd, Wd) uint16 in units of 1/depth_shift metres.
        poses: per frame (4, 4) camera-to-world (stored as float32).
        K_color, K_depth: (3, 3) or (4, 4) intrinsics (stored as 4x4 float32).
        num_frames: the count written in the header (defaults to the true count; a
            larger value imitates a file cut short by a download).
        color_payloads, depth_payloads: raw payloads replacing the encoded ones (to
            inject corrupt data), or None.
        imu_frames: number of IMU records written after the frames (ScanNet's writer
            always writes their count, 0 included; each record is 128 bytes: five
            float64 3-vectors and a uint64 timestamp); None writes no IMU block at all.

    Returns:
        ``path``.
    """
    path = Path(path)
    n = len(rgbs) if num_frames is None else num_frames

    def mat4(K):
        M = np.eye(4, dtype=np.float32)
        K = np.asarray(K, dtype=np.float32)
        M[: K.shape[0], : K.shape[1]] = K
        return M.astype("<f4").tobytes()

    hc, wc = rgbs[0].shape[:2]
    hd, wd = depths_raw[0].shape
    name = sensor_name.encode()
    out = bytearray()
    out += struct.pack("<I", 4)
    out += struct.pack("<Q", len(name)) + name
    out += mat4(K_color) + mat4(np.eye(4)) + mat4(K_depth) + mat4(np.eye(4))
    out += struct.pack("<ii", _COLOR_CODES[color_compression], _DEPTH_CODES[depth_compression])
    out += struct.pack("<IIII", wc, hc, wd, hd)
    out += struct.pack("<f", depth_shift)
    out += struct.pack("<Q", n)
    for k, (rgb, d, T) in enumerate(zip(rgbs, depths_raw, poses)):
        c = color_payloads[k] if color_payloads is not None else encode_color(rgb, color_compression)
        z = depth_payloads[k] if depth_payloads is not None else encode_depth(d, depth_compression)
        out += np.asarray(T, dtype="<f4").reshape(16).tobytes()
        out += struct.pack("<QQQQ", 1000 * k, 1000 * k + 1, len(c), len(z))
        out += c + z
    if imu_frames is not None:
        out += struct.pack("<Q", imu_frames)
        for k in range(imu_frames):
            out += np.linspace(0.0, 1.0, 15).astype("<f8").tobytes() + struct.pack("<Q", 500 * k)
    path.write_bytes(bytes(out))
    return path
