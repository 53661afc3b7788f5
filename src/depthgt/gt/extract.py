"""``depthgt extract``: one built frame set as files any tool reads.

The shard stores the GT as fixed-point integers whose meaning lives in a depthgt header
attribute (:mod:`depthgt.gt.store`); what a person extracts is converted instead:

* depth-like images as float32 EXR in metres (one channel ``Y``, 0 = none; OpenEXR's
  own Python module reads them) and/or 16-bit PNG in millimetres (0 = none; any image
  reader): the GT (``gt_depth``), its expected standard deviation (``gt_sigma``, the
  confidence: PNG in units of 0.1 mm), the resized raw input (``input_depth``) and, for
  synthetic sources, the clean truth (``truth_depth``); the unit is in each file's name
  (``gt_depth_m.exr``, ``gt_depth_mm.png``, ``gt_sigma_100um.png``);
* ``rgb.png``: the target colour, 8-bit sRGB;
* ``poses.json``, ``patches.npz``, ``frameset.json`` as the shard holds them;
* ``units.json``: every file written, with its meaning, unit, scale and missing value.

``raw=True`` writes the shard's members as they are stored instead
(:func:`depthgt.gt.store.extract_frameset`: what depthgt's own readers open as a
frame-set folder).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from depthgt import io
from depthgt.atomic import write_atomic
from depthgt.errors import DepthGTError
from depthgt.gt import store

__all__ = ["EXTRACT_FORMATS", "IMAGES", "planned_files", "extract_plain"]

#: the depth file formats of ``depthgt extract --format``
EXTRACT_FORMATS = ("exr", "png16", "both")
#: name -> (what it is, PNG units per metre): the depth-like images extracted
IMAGES = {
    "gt_depth": ("GT depth", io.PNG16_DEPTH_UNITS_PER_M),
    "gt_sigma": (
        "expected standard deviation of the GT depth (its confidence: smaller is surer)",
        io.PNG16_SIGMA_UNITS_PER_M,
    ),
    "input_depth": ("the resized raw sensor depth the GT was built for", io.PNG16_DEPTH_UNITS_PER_M),
    "truth_depth": ("the clean truth depth (synthetic sources only)", io.PNG16_DEPTH_UNITS_PER_M),
}
_PNG_UNIT = {io.PNG16_DEPTH_UNITS_PER_M: "mm", io.PNG16_SIGMA_UNITS_PER_M: "100um"}
_COPIED = ("poses.json", "patches.npz", "frameset.json")


def _formats(fmt: str) -> tuple[str, ...]:
    if fmt not in EXTRACT_FORMATS:
        raise DepthGTError(f"extract: format must be one of {', '.join(EXTRACT_FORMATS)}, got {fmt!r}")
    return ("exr", "png16") if fmt == "both" else (fmt,)


def planned_files(fmt: str = "both", truth: bool = True) -> list[str]:
    """The names :func:`extract_plain` writes (``truth``: the frame set has a clean truth).

    >>> planned_files("exr", truth=False)[:3]
    ['gt_depth_m.exr', 'gt_sigma_m.exr', 'input_depth_m.exr']
    """
    names = []
    for f in _formats(fmt):
        for name, (_, units) in IMAGES.items():
            if name == "truth_depth" and not truth:
                continue
            names.append(f"{name}_m.exr" if f == "exr" else f"{name}_{_PNG_UNIT[units]}.png")
    return [*names, "rgb.png", *_COPIED, "units.json"]


def extract_plain(
    results: str | Path, dataset: str, scene: str, target: int, dest: str | Path, fmt: str = "both"
) -> list[Path]:
    """Write one built frame set into ``dest`` as plain files (module docstring).

    Returns:
        The paths written, ``units.json`` last.

    Raises:
        DepthGTError: the frame set was not built (with the reason), a bad ``fmt``.
    """
    formats = _formats(fmt)
    loc = store.find_frameset(results, dataset, scene, target)
    rec = store.read_frameset_at(loc)
    images = {"gt_depth": rec.gt_m, "gt_sigma": rec.gt_sigma_m, "input_depth": rec.input_m}
    if rec.truth_m is not None:
        images["truth_depth"] = rec.truth_m
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    units: dict[str, Any] = {}
    for name, image in images.items():
        what, png_units = IMAGES[name]
        image = np.ascontiguousarray(np.where(np.isfinite(image) & (image > 0), image, 0), dtype=np.float32)
        if "exr" in formats:
            path = dest / f"{name}_m.exr"
            write_atomic(path, io.write_exr, {"Y": image})
            units[path.name] = {"what": what, "unit": "m", "channel": "Y", "dtype": "float32", "missing": 0}
            written.append(path)
        if "png16" in formats:
            path = dest / f"{name}_{_PNG_UNIT[png_units]}.png"
            write_atomic(path, Path.write_bytes, io.encode_png16(image, png_units, str(path)))
            units[path.name] = {
                "what": what,
                "unit": {1000: "mm", 10000: "0.1 mm"}.get(png_units, f"1/{png_units} m"),
                "metres_per_unit": 1.0 / png_units,
                "dtype": "uint16",
                "missing": 0,
                "note": f"0 also where the value exceeds {65535 / png_units:g} m",
            }
            written.append(path)
    path = dest / "rgb.png"
    write_atomic(path, io.write_rgb_png, rec.rgb)
    units[path.name] = {"what": "target colour", "unit": "8-bit sRGB", "dtype": "uint8"}
    written.append(path)
    for name in _COPIED:
        path = dest / name
        write_atomic(path, Path.write_bytes, store.member_bytes(f"{loc}/{name}"))
        written.append(path)
    units["poses.json"] = {"what": "camera-to-world poses (4x4, metres) of the frame set's members"}
    units["frameset.json"] = {"what": "the frame set's record: members, split, status, statistics with their units"}
    units["patches.npz"] = {"what": "the patch crop boxes (y0, x0, h, w) in pixels, missing ratios, kept flags"}
    doc = {
        "frameset": f"{dataset}/{scene}/{int(target):06d}",
        "size_hw": list(rec.gt_m.shape),
        "depth": "distance along the camera's optical axis (Z), metres once the unit is applied; 0 = no value",
        "files": units,
    }
    path = dest / "units.json"
    write_atomic(path, io.write_json, doc)
    written.append(path)
    return written
