"""Image, EXR, JSON and pose file helpers.

All readers raise :class:`~depthgt.errors.FrameError` naming the path at fault, with a
reason tag: ``"missing_file"`` (no such file), ``"unreadable"`` (the decoder failed or
the file is not an image of the expected kind). Writers create parent folders.

Conventions: depth (H, W) float32 metres, 0 = invalid; colour (H, W, 3) uint8 RGB
order; poses (4, 4) float64.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

import cv2
import numpy as np

from depthgt.errors import FrameError

__all__ = [
    "read_depth_png",
    "read_rgb",
    "write_rgb_png",
    "write_exr",
    "read_exr",
    "write_json",
    "read_pose_txt",
    "fit_rgb_to_depth",
]


def _require_file(path: Path) -> None:
    if not path.is_file():
        raise FrameError(f"{path}: file not found", "missing_file")


def read_depth_png(path: str | Path, scale: float) -> np.ndarray:
    """Read a 16-bit depth PNG and convert it to metres.

    Args:
        path: uint16 single-channel PNG (e.g. millimetres for Kinect/ScanNet).
        scale: raw units per metre (1000 for millimetres, 5000 for TUM).

    Returns:
        (H, W) float32 depth in metres; raw value 0 stays 0 (invalid).

    Raises:
        FrameError: missing file ("missing_file"), undecodable file or not a
            single-channel uint16 image ("unreadable").
    """
    path = Path(path)
    if not scale > 0:
        raise ValueError(f"depth scale must be > 0, got {scale} for {path}")
    _require_file(path)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise FrameError(f"{path}: cannot decode depth image", "unreadable")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise FrameError(
            f"{path}: depth must be single-channel uint16, got {raw.dtype} with shape {raw.shape}", "unreadable"
        )
    return raw.astype(np.float32) / np.float32(scale)


def read_rgb(path: str | Path) -> np.ndarray:
    """Read a colour image (JPEG/PNG) as (H, W, 3) uint8 in RGB order.

    Grey images are expanded to three channels; 16-bit images are rejected.

    Raises:
        FrameError: missing file ("missing_file") or undecodable file ("unreadable").
    """
    path = Path(path)
    _require_file(path)
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FrameError(f"{path}: cannot decode colour image", "unreadable")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def write_rgb_png(path: str | Path, rgb: np.ndarray) -> None:
    """Write (H, W, 3) uint8 RGB as a PNG (lossless).

    Raises:
        ValueError: wrong shape or dtype.
        OSError: the encoder could not write ``path``.
    """
    path = Path(path)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"{path}: rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise OSError(f"{path}: cv2.imwrite failed")


def write_exr(path: str | Path, channels: Mapping[str, np.ndarray]) -> None:
    """Write float32 channels to a scanline EXR with ZIP compression.

    The header holds only the standard attributes (no timestamps), so identical
    input gives identical bytes.

    Args:
        channels: name -> (H, W) float32 array; all of the same shape.

    Raises:
        ValueError: no channel, a channel that is not 2-D float32, or shapes differ.
    """
    import OpenEXR  # heavy binding, imported only when EXR is used

    path = Path(path)
    if not channels:
        raise ValueError(f"{path}: no channel to write")
    shapes = {}
    for name, arr in channels.items():
        if not isinstance(arr, np.ndarray) or arr.ndim != 2 or arr.dtype != np.float32:
            got = (arr.shape, arr.dtype) if isinstance(arr, np.ndarray) else type(arr).__name__
            raise ValueError(f"{path}: channel {name!r} must be a (H, W) float32 array, got {got}")
        shapes[name] = arr.shape
    if len(set(shapes.values())) != 1:
        raise ValueError(f"{path}: channels differ in shape: {shapes}")
    path.parent.mkdir(parents=True, exist_ok=True)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    data = {name: np.ascontiguousarray(arr) for name, arr in sorted(channels.items())}
    with OpenEXR.File(header, data) as f:
        f.write(str(path))


def read_exr(path: str | Path) -> dict[str, np.ndarray]:
    """Read every channel of an EXR file.

    Returns:
        name -> (H, W) array (float32 for FLOAT channels).

    Raises:
        FrameError: missing file ("missing_file") or not a readable EXR ("unreadable").
    """
    import OpenEXR

    path = Path(path)
    _require_file(path)
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            return {name: np.array(ch.pixels) for name, ch in f.channels().items()}
    except (RuntimeError, OSError, ValueError) as exc:
        raise FrameError(f"{path}: cannot read EXR ({exc})", "unreadable") from exc


def write_json(path: str | Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON with sorted keys (stable bytes), numpy scalars
    and arrays converted to Python values."""

    def _default(o: Any) -> Any:
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, Path):
            return str(o)
        raise TypeError(f"{path}: object of type {type(o).__name__} is not JSON serialisable")

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(obj, sort_keys=True, indent=2, default=_default)
    path.write_text(text + "\n", encoding="utf-8")


def read_pose_txt(path: str | Path) -> np.ndarray:
    """Read a 4x4 whitespace-separated matrix (ScanNet/7-Scenes pose files).

    Non-finite entries (ScanNet writes ``-inf`` rows for lost tracking) are returned
    as they are; the caller decides (see :func:`depthgt.sources.base.check_frame`).

    Returns:
        (4, 4) float64.

    Raises:
        FrameError: missing file ("missing_file"), text that does not parse to 16
            numbers ("unreadable").
    """
    path = Path(path)
    _require_file(path)
    try:
        values = np.array(path.read_text(encoding="ascii").split(), dtype=np.float64)
    except (ValueError, UnicodeDecodeError) as exc:
        raise FrameError(f"{path}: pose does not parse as numbers ({exc})", "unreadable") from exc
    if values.size != 16:
        raise FrameError(f"{path}: pose has {values.size} numbers, expected 16 (4x4)", "unreadable")
    return values.reshape(4, 4)


def fit_rgb_to_depth(rgb: np.ndarray, depth_hw: tuple[int, int], where: str, max_aspect_change: float = 0.05) -> np.ndarray:
    """Bring a colour image to the depth resolution (cv2.INTER_AREA when sizes differ).

    Args:
        rgb: (Hc, Wc, 3) uint8.
        depth_hw: (H, W) of the depth image.
        where: file or frame named in errors.
        max_aspect_change: largest relative difference of the aspect ratios W/H that
            is resized silently (ScanNet: 1296x968 vs 640x480 differ by 0.4%).

    Returns:
        (H, W, 3) uint8.

    Raises:
        FrameError: ("size_mismatch") when the aspect ratios differ by more than
            ``max_aspect_change``: resizing would distort the image.
    """
    h, w = depth_hw
    hc, wc = rgb.shape[:2]
    if (hc, wc) == (h, w):
        return rgb
    change = abs((wc / hc) / (w / h) - 1.0)
    if change > max_aspect_change:
        raise FrameError(
            f"{where}: colour {wc}x{hc} cannot be fitted to depth {w}x{h} (aspect ratios differ by {change:.1%})",
            "size_mismatch",
        )
    return cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
