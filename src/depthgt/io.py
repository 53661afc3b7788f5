"""Image, EXR, JSON and pose file helpers.

All readers raise :class:`~depthgt.errors.FrameError` naming the path at fault, with a
reason tag: ``"missing_file"`` (no such file), ``"unreadable"`` (the decoder failed or
the file is not an image of the expected kind), ``"size_mismatch"`` (the image's
declared size is not the size the caller expects). Writers create parent folders.

Encoded images (JPEG/PNG files, ``.sens`` payloads, a frame set's WebP colour) are untrusted input. Before any
pixel is decoded, :func:`probe_image` reads the declared format, size and mode from the
header (Pillow's lazy ``Image.open``, which decodes nothing) and the size is checked
against the caller's expectation and :data:`MAX_IMAGE_PIXELS`, so that a header
claiming 60000x60000 pixels costs nothing. A JPEG must end with its end-of-image marker,
a PNG with its ``IEND`` chunk and a WebP must hold the bytes its RIFF header declares:
libjpeg decodes a truncated JPEG with only a warning on stderr, so truncation is
detected here. OpenCV then decodes; whatever it reports
(``None`` or ``cv2.error``) becomes a FrameError.

Conventions: depth (H, W) float32 metres, 0 = invalid; colour (H, W, 3) uint8 RGB
order; poses (4, 4) float64.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import struct
import sys
import tempfile
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

# WebPImagePlugin registers WEBP with Pillow: without it the first WebP open imports every
# Pillow plugin (~0.1 s in each process, each DataLoader worker)
from PIL import Image, UnidentifiedImageError, WebPImagePlugin  # noqa: F401

from depthgt.errors import FrameError
from depthgt.shapes import check_shape

log = logging.getLogger(__name__)

__all__ = [
    "MAX_IMAGE_PIXELS",
    "MAX_IMAGE_SIDE",
    "ImageHeader",
    "probe_image",
    "probe_image_file",
    "decode_color",
    "decode_depth_png",
    "read_depth_png",
    "read_rgb",
    "write_rgb_png",
    "write_rgb_webp",
    "EXR_COMPRESSIONS",
    "fixed_point",
    "from_fixed_point",
    "on_fixed_point_grid",
    "log_quantised",
    "from_log_quantised",
    "on_log_grid",
    "write_exr",
    "read_exr",
    "decode_exr",
    "write_json",
    "read_pose_txt",
    "fit_rgb_to_depth",
]

#: Largest declared image accepted (pixels): 40 Mpx, above 8K UHD (33 Mpx). A decoded
#: 8-bit RGB image of this size takes 120 MB, so one frame stays far below 512 MiB.
MAX_IMAGE_PIXELS = 40_000_000
#: Largest declared side (pixels).
MAX_IMAGE_SIDE = 32_768
#: Largest image file read (bytes); an 8-bit RGB PNG of MAX_IMAGE_PIXELS is ~120 MB.
MAX_IMAGE_FILE_BYTES = 256 * 1024 * 1024

_PNG_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # the fixed last chunk of every PNG
_JPEG_EOI = b"\xff\xd9"  # end-of-image marker
_RIFF, _WEBP = b"RIFF", b"WEBP"  # a WebP file: RIFF, the byte count after these 8 bytes, WEBP
# What Pillow's header parsers raise on malformed input (Image.open tries its plugins
# and ends in UnidentifiedImageError, an OSError; DecompressionBombError above
# 2 * Image.MAX_IMAGE_PIXELS; the others from plugins that accepted the first bytes).
_PIL_ERRORS = (
    OSError,
    ValueError,
    TypeError,
    SyntaxError,
    EOFError,
    IndexError,
    KeyError,
    struct.error,
    Image.DecompressionBombError,
)
_COLOR_MODES = {"L", "RGB", "P"}  # 8-bit grey, 8-bit colour, 8-bit palette (PNG)


@dataclass(frozen=True)
class ImageHeader:
    """What an encoded image declares in its header (nothing decoded).

    Attributes:
        format: ``"JPEG"``, ``"PNG"`` or ``"WEBP"`` (as the caller allowed).
        width, height: declared size in pixels.
        mode: Pillow's mode, e.g. ``"L"`` (8-bit grey), ``"RGB"``, ``"RGBA"``,
            ``"I;16"`` (16-bit grey), ``"CMYK"``.
    """

    format: str
    width: int
    height: int
    mode: str

    @property
    def hw(self) -> tuple[int, int]:
        return (self.height, self.width)


def _require_file(path: Path) -> None:
    if not path.is_file():
        raise FrameError(f"{path}: file not found", "missing_file")


def _open_header(source, where: str, formats: tuple[str, ...] = ("JPEG", "PNG")) -> ImageHeader:
    kinds = " or ".join(formats)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # the size is checked by the caller
            with Image.open(source, formats=formats) as im:
                return ImageHeader(str(im.format), int(im.size[0]), int(im.size[1]), str(im.mode))
    except Image.DecompressionBombError as exc:
        raise FrameError(f"{where}: image header declares an absurd size ({exc})", "unreadable") from exc
    except UnidentifiedImageError as exc:
        raise FrameError(
            f"{where}: not a readable {kinds} image (unknown format or corrupt header)", "unreadable"
        ) from exc
    except _PIL_ERRORS as exc:
        raise FrameError(f"{where}: not a readable {kinds} image ({type(exc).__name__}: {exc})", "unreadable") from exc


def probe_image(data: bytes, where: str, formats: tuple[str, ...] = ("JPEG", "PNG")) -> ImageHeader:
    """Format, declared size and mode of an encoded image of one of ``formats`` (Pillow's
    names: ``"JPEG"``, ``"PNG"``, ``"WEBP"``), from its header only.

    Raises:
        FrameError: ("unreadable") empty data, not one of ``formats`` (TIFF, garbage), or
            a header that does not parse; the message names ``where``.
    """
    if not data:
        raise FrameError(f"{where}: empty image payload (0 bytes)", "unreadable")
    return _open_header(io.BytesIO(data), where, tuple(formats))


def probe_image_file(path: str | Path) -> ImageHeader:
    """:func:`probe_image` of a file, reading only its header.

    Raises:
        FrameError: missing file ("missing_file"), empty or unparsable file ("unreadable").
    """
    path = Path(path)
    _require_file(path)
    if path.stat().st_size == 0:
        raise FrameError(f"{path}: empty file (0 bytes)", "unreadable")
    return _open_header(path, str(path))


def _check_declared_size(header: ImageHeader, where: str, expected_hw: tuple[int, int] | None, what: str) -> None:
    w, h = header.width, header.height
    if min(w, h) <= 0 or max(w, h) > MAX_IMAGE_SIDE or w * h > MAX_IMAGE_PIXELS:
        raise FrameError(
            f"{where}: {header.format} header declares {w}x{h} pixels, beyond the limit of {MAX_IMAGE_SIDE} per side "
            f"and {MAX_IMAGE_PIXELS} in all (not decoded)",
            "unreadable",
        )
    if expected_hw is not None and header.hw != tuple(expected_hw):
        raise FrameError(
            f"{where}: {header.format} is {w}x{h}, {what} is {expected_hw[1]}x{expected_hw[0]}", "size_mismatch"
        )


def _check_complete(data: bytes, header: ImageHeader, where: str) -> None:
    """Truncation check: libjpeg decodes a cut JPEG with a warning only (grey rows)."""
    if header.format == "JPEG" and not data.rstrip(b"\x00").endswith(_JPEG_EOI):
        raise FrameError(f"{where}: truncated JPEG (no end-of-image marker after {len(data)} bytes)", "unreadable")
    if header.format == "PNG" and not data.endswith(_PNG_IEND):
        raise FrameError(f"{where}: truncated PNG (no IEND chunk after {len(data)} bytes)", "unreadable")
    if header.format == "WEBP":
        declared = int.from_bytes(data[4:8], "little") + 8 if data[:4] == _RIFF and data[8:12] == _WEBP else -1
        if declared < 0 or len(data) < declared:
            raise FrameError(
                f"{where}: truncated WebP ({len(data)} bytes, its RIFF header declares {declared})", "unreadable"
            )


@contextlib.contextmanager
def _c_stderr() -> Iterator[list[str]]:
    """What C libraries write to the process's stderr (file descriptor 2) while the
    context lasts, captured instead of printed (libpng and libjpeg print their own
    messages there); the text is in the yielded list afterwards."""
    out: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no file descriptor 2 (an embedding host): nothing to capture
        yield out
        return
    try:
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                yield out
            finally:
                os.dup2(saved, 2)
                tmp.seek(0)
                out.append(tmp.read().decode("utf-8", errors="replace").strip())
    finally:
        os.close(saved)


def _imdecode(data: bytes, header: ImageHeader, where: str) -> np.ndarray:
    """OpenCV's decode of ``data``; what the codec library says (libpng's "IDAT: CRC
    error", libjpeg's "Corrupt JPEG data") goes into the error naming ``where``, or, for
    an image decoded anyway, into a warning naming it, never bare onto the console."""
    with _c_stderr() as said:
        try:
            img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        except cv2.error as exc:
            img, err = None, exc
        else:
            err = None
    library = " ".join(line.strip() for line in "".join(said).splitlines() if line.strip())
    if err is not None:
        detail = str(err).strip().splitlines()[-1] + (f"; {library}" if library else "")
        raise FrameError(f"{where}: cannot decode {header.format} ({detail})", "unreadable") from err
    if img is None:
        detail = f" ({library})" if library else ""
        raise FrameError(f"{where}: cannot decode {header.format} image{detail}", "unreadable")
    if library:
        log.warning("%s: decoded, but the %s decoder reported: %s", where, header.format, library)
    if img.shape[:2] != header.hw:
        raise FrameError(
            f"{where}: decoded {img.shape[1]}x{img.shape[0]}, the {header.format} header declares {header.width}x{header.height}",
            "unreadable",
        )
    return img


def decode_color(
    data: bytes, where: str, expected_hw: tuple[int, int] | None = None, formats: tuple[str, ...] = ("JPEG", "PNG")
) -> np.ndarray:
    """Decode an encoded colour image to (H, W, 3) uint8 RGB.

    Accepted: 8-bit grey (expanded to three channels), 8-bit RGB and 8-bit palette
    images of ``formats`` (JPEG or PNG by default; a frame set's colour is ``("WEBP",)``).
    Rejected before decoding: empty data, other
    formats (TIFF, ...), modes with alpha, 16 bits or CMYK, declared sizes other than
    ``expected_hw`` or beyond :data:`MAX_IMAGE_PIXELS`, truncated files; after decoding:
    anything OpenCV does not return as 8-bit with 1 or 3 channels (16-bit RGB PNG).

    Args:
        data: the encoded bytes.
        where: file (and frame) named in errors.
        expected_hw: (H, W) the image must have, or None for any size within the limits.

    Raises:
        FrameError: ("unreadable") or ("size_mismatch") naming ``where``.
    """
    # JPEG and PNG are always recognised, so that a payload of the other one is named
    header = probe_image(data, where, tuple(dict.fromkeys(("JPEG", "PNG", *formats))))
    if header.format not in formats:
        raise FrameError(f"{where}: colour payload is {header.format}, expected {' or '.join(formats)}", "unreadable")
    if header.mode not in _COLOR_MODES:
        raise FrameError(
            f"{where}: colour must be 8-bit grey or RGB, the {header.format} is {header.mode!r}", "unreadable"
        )
    _check_declared_size(header, where, expected_hw, "expected colour size")
    _check_complete(data, header, where)
    img = _imdecode(data, header, where)
    channels = 1 if img.ndim == 2 else img.shape[2]
    if img.dtype != np.uint8 or channels not in (1, 3):
        raise FrameError(
            f"{where}: colour must be 8-bit grey or RGB, decoded {img.dtype} with {channels} channels", "unreadable"
        )
    return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB if channels == 1 else cv2.COLOR_BGR2RGB)


def decode_depth_png(
    data: bytes, where: str, expected_hw: tuple[int, int] | None = None, what: str = "expected depth size"
) -> np.ndarray:
    """Decode a 16-bit single-channel depth PNG to (H, W) uint16 raw units.

    Args:
        expected_hw: (H, W) the image must have (checked on the header, before
            decoding), or None for any size within :data:`MAX_IMAGE_PIXELS`.
        what: how ``expected_hw`` is named in the size-mismatch message.

    Raises:
        FrameError: ("unreadable") empty, not a PNG, truncated, not single-channel
            uint16; ("size_mismatch") declared size differs from ``expected_hw``.
    """
    header = probe_image(data, where)
    if header.format != "PNG":
        raise FrameError(f"{where}: depth must be a 16-bit PNG, got {header.format}", "unreadable")
    _check_declared_size(header, where, expected_hw, what)
    _check_complete(data, header, where)
    raw = _imdecode(data, header, where)
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise FrameError(
            f"{where}: depth must be single-channel uint16, got {raw.dtype} with shape {raw.shape}", "unreadable"
        )
    return raw


def _read_image_file(path: Path) -> bytes:
    _require_file(path)
    size = path.stat().st_size
    if size > MAX_IMAGE_FILE_BYTES:
        raise FrameError(
            f"{path}: {size} bytes, larger than any image accepted ({MAX_IMAGE_FILE_BYTES} bytes)", "unreadable"
        )
    return path.read_bytes()


def read_depth_png(
    path: str | Path, scale: float, expected_hw: tuple[int, int] | None = None, what: str = "expected depth size"
) -> np.ndarray:
    """Read a 16-bit depth PNG and convert it to metres.

    Args:
        path: uint16 single-channel PNG (e.g. millimetres for Kinect/ScanNet).
        scale: raw units per metre (1000 for millimetres, 5000 for TUM).
        expected_hw: (H, W) the image must have (checked before decoding), or None.
        what: how ``expected_hw`` is named in the size-mismatch message.

    Returns:
        (H, W) float32 depth in metres; raw value 0 stays 0 (invalid).

    Raises:
        FrameError: missing file ("missing_file"), undecodable, truncated or not a
            single-channel uint16 PNG ("unreadable"), another size ("size_mismatch").
    """
    path = Path(path)
    if not scale > 0:
        raise ValueError(f"depth scale must be > 0, got {scale} for {path}")
    raw = decode_depth_png(_read_image_file(path), str(path), expected_hw, what)
    return raw.astype(np.float32) / np.float32(scale)


def read_rgb(path: str | Path) -> np.ndarray:
    """Read a colour image (JPEG/PNG) as (H, W, 3) uint8 in RGB order.

    Grey images are expanded to three channels; 16-bit, alpha, CMYK and non-JPEG/PNG
    images are rejected, as are truncated files and declared sizes beyond
    :data:`MAX_IMAGE_PIXELS` (see :func:`decode_color`).

    Raises:
        FrameError: missing file ("missing_file") or a file that is not such an image
            ("unreadable").
    """
    path = Path(path)
    return decode_color(_read_image_file(path), str(path))


def _rgb_destination(path: str | Path, rgb: np.ndarray) -> Path:
    """``path`` with its folder made, once ``rgb`` is checked to be (H, W, 3) uint8."""
    path = Path(path)
    check_shape(rgb, "H W 3", f"{path}: rgb")
    if rgb.dtype != np.uint8:
        raise ValueError(f"{path}: rgb must be (H, W, 3) uint8, got {rgb.dtype}")
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def write_rgb_png(path: str | Path, rgb: np.ndarray) -> None:
    """Write (H, W, 3) uint8 RGB as a PNG (lossless).

    Raises:
        ValueError: wrong shape or dtype.
        OSError: the encoder could not write ``path``.
    """
    path = _rgb_destination(path, rgb)
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise OSError(f"{path}: cv2.imwrite failed")


#: libwebp's lossless effort for :func:`write_rgb_webp`: method 3 at quality 0. On 11
#: real 256x256 frames (docs/decisions.md "The stored format"): 86.3 kB in
#: 25 ms CPU, against 84.0 kB in 79 ms (method 4), 84.0 kB in 124 ms (OpenCV's lossless
#: WebP, which has no effort setting) and PNG's 116 kB in 3.5 ms.
WEBP_METHOD, WEBP_EFFORT = 3, 0


def write_rgb_webp(path: str | Path, rgb: np.ndarray) -> None:
    """Write (H, W, 3) uint8 RGB as a lossless WebP (every value kept; a quarter smaller
    than PNG on camera frames), with Pillow: OpenCV offers no effort setting for it.

    Raises:
        ValueError: wrong shape or dtype.
        OSError: the encoder could not write ``path``.
    """
    path = _rgb_destination(path, rgb)
    Image.fromarray(np.ascontiguousarray(rgb), "RGB").save(
        path, "WEBP", lossless=True, quality=WEBP_EFFORT, method=WEBP_METHOD
    )


#: EXR compressions :func:`write_exr` offers: ``zip`` (zlib, every OpenEXR reader) and
#: ``htj2k`` (lossless high-throughput JPEG 2000, OpenEXR >= 3.4: on a frame set's
#: fixed-point GT 42 % smaller than zip, docs/decisions.md "The stored format").
EXR_COMPRESSIONS = ("zip", "htj2k")
#: The header attribute that names the fixed-point channels: JSON ``{channel: units per value}``.
FIXED_POINT_ATTRIBUTE = "depthgt_fixed_point"
#: The header attribute that names the channels on a logarithmic grid: JSON
#: ``{channel: [steps per octave, smallest value]}`` (:func:`log_quantised`).
LOG_GRID_ATTRIBUTE = "depthgt_log2"
_UINT32_MAX = float(np.iinfo(np.uint32).max)


def fixed_point(values: np.ndarray, units_per_value: int, where: str = "array") -> np.ndarray:
    """(H, W) uint32 ``round(values * units_per_value)``: a non-negative float image on the
    grid of ``1 / units_per_value`` (e.g. depth in units of 2^-15 m with 32768).

    Raises:
        ValueError: a negative, non-finite or too large value (named with ``where``).
    """
    scaled = np.round(np.asarray(values, dtype=np.float64) * float(units_per_value))
    bad = ~np.isfinite(scaled) | (scaled < 0) | (scaled > _UINT32_MAX)
    if bad.any():
        y, x = np.argwhere(bad)[0]
        raise ValueError(
            f"{where}: value {values[y, x]} at pixel ({y}, {x}) is not a finite number in "
            f"[0, {_UINT32_MAX / units_per_value:g}] (fixed point, {units_per_value} units per value)"
        )
    return scaled.astype(np.uint32)


def from_fixed_point(units: np.ndarray, units_per_value: int) -> np.ndarray:
    """(H, W) float32 ``units / units_per_value``, divided in float32 as the depth
    readers divide raw sensor units (:func:`read_depth_png`), so that an image of a
    sensor's units comes back bit-identical; exact for any power-of-two divisor below
    2^24 units."""
    return units.astype(np.float32) / np.float32(units_per_value)


def on_fixed_point_grid(values: np.ndarray, units_per_value: int, where: str = "array") -> np.ndarray:
    """``values`` (float32) as a fixed-point channel of :func:`write_exr` reads back."""
    return from_fixed_point(fixed_point(values, units_per_value, where), units_per_value)


def _check_log_grid(steps_per_octave: int, smallest: float, where: str) -> None:
    if int(steps_per_octave) != steps_per_octave or not 1 <= steps_per_octave <= 1024 or not smallest > 0:
        raise ValueError(
            f"{where}: a log grid needs whole steps per octave in [1, 1024] and a smallest value > 0, "
            f"got {steps_per_octave} and {smallest}"
        )


def log_quantised(values: np.ndarray, steps_per_octave: int, smallest: float, where: str = "array") -> np.ndarray:
    """(H, W) uint32 codes of a non-negative image on a logarithmic grid: 0 for 0, else
    ``1 + round(steps_per_octave * log2(v / smallest))``: a constant relative step of
    2^(1 / steps_per_octave), so the largest relative rounding error is
    2^(1 / (2 steps_per_octave)) - 1 (4.4 % at 8 steps per octave) at any magnitude.
    Values in (0, ``smallest``] are stored as ``smallest``. Written by hand: no image
    library stores a channel on a log grid losslessly (EXR's half floats are one, at a
    fixed 1/1024-octave step that compresses poorly).

    Raises:
        ValueError: a negative or non-finite value (named with ``where``), or a bad grid.
    """
    _check_log_grid(steps_per_octave, smallest, where)
    raw = np.asarray(values)
    v = raw.astype(np.float64)
    bad = ~np.isfinite(v) | (v < 0)
    if bad.any():
        y, x = np.argwhere(bad)[0]
        raise ValueError(f"{where}: value {raw[y, x]!s} at pixel ({y}, {x}) is not a finite number >= 0 (log grid)")
    with np.errstate(divide="ignore"):  # log2(0) is masked out below
        steps = np.round(steps_per_octave * np.log2(np.maximum(v, smallest) / smallest))
    return np.where(v > 0, steps + 1, 0).astype(np.uint32)


def from_log_quantised(codes: np.ndarray, steps_per_octave: int, smallest: float) -> np.ndarray:
    """(H, W) float32 values of :func:`log_quantised` codes (0 stays 0)."""
    codes = np.asarray(codes)
    values = smallest * np.exp2((codes.astype(np.float64) - 1.0) / steps_per_octave)
    return np.where(codes > 0, values, 0.0).astype(np.float32)


def on_log_grid(values: np.ndarray, steps_per_octave: int, smallest: float, where: str = "array") -> np.ndarray:
    """``values`` (float32) as a log-grid channel of :func:`write_exr` reads back."""
    return from_log_quantised(log_quantised(values, steps_per_octave, smallest, where), steps_per_octave, smallest)


def write_exr(
    path: str | Path,
    channels: Mapping[str, np.ndarray],
    fixed: Mapping[str, int] | None = None,
    compression: str = "zip",
    log_grid: Mapping[str, tuple[int, float]] | None = None,
) -> None:
    """Write float32 channels to a scanline EXR.

    The header holds only the standard attributes (no timestamps) and, with ``fixed`` or
    ``log_grid``, their tables, so identical input gives identical bytes.

    Args:
        channels: name -> (H, W) float32 array; all of the same shape.
        fixed: name -> units per value of the channels stored as fixed point (UINT
            channels of ``round(value * units)``, :func:`fixed_point`); :func:`read_exr`
            turns them back to float32. Other channels are stored as FLOAT.
        compression: one of :data:`EXR_COMPRESSIONS`.
        log_grid: name -> (steps per octave, smallest value) of the channels stored on a
            logarithmic grid (UINT channels of :func:`log_quantised` codes), read back
            likewise.

    Raises:
        ValueError: no channel, a channel that is not 2-D float32, shapes that differ,
            an unknown compression or fixed-point channel, or a value the fixed point
            cannot hold.
    """
    import OpenEXR  # heavy binding, imported only when EXR is used

    path = Path(path)
    if not channels:
        raise ValueError(f"{path}: no channel to write")
    if compression not in EXR_COMPRESSIONS:
        raise ValueError(f"{path}: compression must be one of {', '.join(EXR_COMPRESSIONS)}, got {compression!r}")
    fixed, log_grid = dict(fixed or {}), dict(log_grid or {})
    unknown = sorted(set(fixed) - set(channels))
    if unknown:
        raise ValueError(f"{path}: fixed-point channels {unknown} are not among the channels {sorted(channels)}")
    unknown = sorted(set(log_grid) - set(channels)) + sorted(set(log_grid) & set(fixed))
    if unknown:
        raise ValueError(
            f"{path}: log-grid channels {unknown} are not among the channels {sorted(channels)} or are also fixed point"
        )
    shapes = {}
    for name, arr in channels.items():
        if not isinstance(arr, np.ndarray) or arr.ndim != 2 or arr.dtype != np.float32:
            got = (arr.shape, arr.dtype) if isinstance(arr, np.ndarray) else type(arr).__name__
            raise ValueError(f"{path}: channel {name!r} must be a (H, W) float32 array, got {got}")
        shapes[name] = arr.shape
    if len(set(shapes.values())) != 1:
        raise ValueError(f"{path}: channels differ in shape: {shapes}")
    path.parent.mkdir(parents=True, exist_ok=True)
    header = {
        "compression": OpenEXR.ZIP_COMPRESSION if compression == "zip" else OpenEXR.HTJ2K256_COMPRESSION,
        "type": OpenEXR.scanlineimage,
    }
    if fixed:
        header[FIXED_POINT_ATTRIBUTE] = json.dumps({k: int(v) for k, v in sorted(fixed.items())})
    if log_grid:
        header[LOG_GRID_ATTRIBUTE] = json.dumps({k: [int(n), float(m)] for k, (n, m) in sorted(log_grid.items())})

    def stored(name: str, arr: np.ndarray) -> np.ndarray:
        if name in fixed:
            return fixed_point(arr, fixed[name], f"{path} channel {name}")
        if name in log_grid:
            return log_quantised(arr, *log_grid[name], f"{path} channel {name}")
        return np.ascontiguousarray(arr)

    data = {name: stored(name, arr) for name, arr in sorted(channels.items())}
    with OpenEXR.File(header, data) as f:
        f.write(str(path))


def _exr_channels(source: str | io.BytesIO, where: str) -> dict[str, np.ndarray]:
    """Every channel of an EXR (a path or the bytes in a stream), fixed-point and log-grid
    channels turned back to values (see :func:`read_exr`)."""
    import OpenEXR  # heavy binding, imported only when EXR is used

    try:
        # one thread: a 256x256 image decodes faster without a pool (12 against 15 ms for gt.exr)
        with OpenEXR.File(source, separate_channels=True, num_threads=1) as f:
            chans = {name: np.array(ch.pixels) for name, ch in f.channels().items()}
            table = f.header().get(FIXED_POINT_ATTRIBUTE)
            log_table = f.header().get(LOG_GRID_ATTRIBUTE)
    except (RuntimeError, OSError, ValueError) as exc:
        raise FrameError(f"{where}: cannot read EXR ({exc})", "unreadable") from exc

    def uint_channel(name: str, what: str) -> None:
        if name not in chans or chans[name].dtype != np.uint32:
            raise FrameError(
                f"{where}: {what} channel {name!r} is not a UINT channel of the file (channels {sorted(chans)})",
                "unreadable",
            )

    if table is not None:
        try:
            fixed = {str(k): int(v) for k, v in json.loads(table).items()}
        except (ValueError, TypeError, AttributeError) as exc:
            raise FrameError(
                f"{where}: header {FIXED_POINT_ATTRIBUTE} is not a JSON table of units ({exc})", "unreadable"
            ) from exc
        for name, units in fixed.items():
            uint_channel(name, f"fixed-point ({units} units per value)")
            if units <= 0:
                raise FrameError(f"{where}: fixed-point channel {name!r} has {units} units per value", "unreadable")
            chans[name] = from_fixed_point(chans[name], units)
    if log_table is not None:
        try:
            grids = {str(k): (int(n), float(m)) for k, (n, m) in json.loads(log_table).items()}
            for name, grid in grids.items():
                _check_log_grid(*grid, f"{where} channel {name}")
        except (ValueError, TypeError, AttributeError) as exc:
            raise FrameError(
                f"{where}: header {LOG_GRID_ATTRIBUTE} is not a JSON table of log grids ({exc})", "unreadable"
            ) from exc
        for name, (steps, smallest) in grids.items():
            uint_channel(name, f"log-grid ({steps} steps per octave from {smallest:g})")
            chans[name] = from_log_quantised(chans[name], steps, smallest)
    return chans


def read_exr(path: str | Path) -> dict[str, np.ndarray]:
    """Read every channel of an EXR file.

    Returns:
        name -> (H, W) array: float32 for FLOAT channels and for the fixed-point and
        log-grid channels :func:`write_exr` wrote (turned back to values); other UINT
        or HALF channels as stored.

    Raises:
        FrameError: missing file ("missing_file") or not a readable EXR, or a
            fixed-point table that does not parse ("unreadable").
    """
    path = Path(path)
    _require_file(path)
    return _exr_channels(str(path), str(path))


def decode_exr(data: bytes, where: str) -> dict[str, np.ndarray]:
    """:func:`read_exr` of an EXR held in memory (a shard member), read from a stream
    (OpenEXR >= 3.5).

    Raises:
        FrameError: ("unreadable") naming ``where`` when the bytes are not a readable EXR.
    """
    return _exr_channels(io.BytesIO(data), where)


#: 16-bit PNG depth for other tools (``depthgt export``, ``depthgt extract``): millimetres,
#: as ScanNet and NYU-v2 store depth
PNG16_DEPTH_UNITS_PER_M = 1000
#: 16-bit PNG of the GT's expected standard deviation: units of 0.1 mm (mostly a few mm)
PNG16_SIGMA_UNITS_PER_M = 10000


def encode_png16(depth_m: np.ndarray, units_per_m: float, where: str) -> bytes:
    """(H, W) metres -> 16-bit PNG bytes of ``round(depth * units_per_m)``; 0, non-finite
    and values beyond 65535 units are written as 0 (missing)."""
    q = np.round(np.asarray(depth_m, dtype=np.float64) * units_per_m)
    q[~np.isfinite(q) | (q > 65535) | (q < 0)] = 0
    ok, buf = cv2.imencode(".png", q.astype(np.uint16))
    if not ok:
        raise OSError(f"{where}: cv2.imencode failed")
    return buf.tobytes()


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


def fit_rgb_to_depth(
    rgb: np.ndarray, depth_hw: tuple[int, int], where: str, max_aspect_change: float = 0.05
) -> np.ndarray:
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
