"""The README's stated format facts against the code's constants: the GT's precision, the
bytes a frame set takes and what that makes for ScanNet, the versions it names; and the
docs claim no reader the pinned packages lack (issue 42)."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest

from depthgt.gt import store

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()
DOCS = [p.read_text() for p in sorted((REPO / "docs").glob("*.md"))]
PROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
# ScanNet v2's frames (docs/output-layout.md "Bytes on disk, and at ScanNet scale")
SCANNET_FRAMES = 2.5e6


def _one(pattern: str, text: str = README) -> re.Match:
    found = list(re.finditer(pattern, text))
    assert len(found) == 1, f"{pattern!r}: {len(found)} matches"
    return found[0]


def test_the_gt_precision_is_the_stored_fixed_point():
    m = _one(r"The GT is stored\s+to ([\d.]+) µm \(fixed point in units of 2\^-(\d+) m")
    assert store.GT_UNITS["Z"] == 2 ** int(m.group(2))
    assert float(m.group(1)) == round(0.5 / store.GT_UNITS["Z"] * 1e6, 1)  # the largest rounding error
    assert f"{0.5 / store.GT_UNITS['Z']:.2e}" in store.CHANNELS["gt.exr"]["Z"]


def test_bytes_per_frame_set_and_scannet_follow_the_measured_size():
    real = store.MEASURED_FRAMESET_BYTES["real"]
    m = _one(r"takes about ([\d.]+)-([\d.]+) MB on disk \(([\d.]+)-([\d.]+) MiB;")
    lo, hi, lo_mib, hi_mib = map(float, m.groups())
    assert lo <= real / 1e6 <= hi and hi - lo <= 0.02
    assert lo_mib <= real / 2**20 <= hi_mib
    tb = float(_one(r"([\d.]+) TB for every frame of ScanNet").group(1))
    assert tb == round(SCANNET_FRAMES * real / 1e12, 2)
    # the docs' table of bytes at ScanNet scale says the same (wherever the docs keep it)
    assert any(f"{tb} TB" in d and f"{real / 1e6:.3f} MB" in d for d in DOCS), "no doc holds the ScanNet figures"


@pytest.mark.parametrize("package", ["OpenEXR", "torch"])
def test_the_versions_the_readme_names_are_pyprojects(package):
    (requirement,) = [r for r in PROJECT["dependencies"] if re.match(rf"{package}\b", r)]
    if package == "OpenEXR":
        assert f"OpenEXR {requirement.removeprefix('OpenEXR').strip().replace('>=', '>= ')}" in README
    else:
        assert f"`{requirement}` is pinned" in README
    python = PROJECT["requires-python"].removeprefix(">=")
    assert f"Python {python}+" in README


def test_no_doc_says_opencv_reads_the_exported_exr():
    import cv2

    for path in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        assert "OPENCV_IO_ENABLE_OPENEXR" not in path.read_text(), path
    # the reason: the pinned wheel has no EXR codec (were it to gain one, the docs may say so)
    assert not cv2.haveImageReader(str(REPO / "README.md").replace("README.md", "x.exr"))


def test_gt_quality_rows_are_columns_not_tuples(tiny_build):
    for name in ("summary.md", "card.md"):
        text = (tiny_build / "results" / "dataset" / name).read_text()
        rows = [line for line in text.splitlines() if line.startswith("| syn")]
        assert rows and not any("('" in line for line in rows), (name, rows)
        assert re.search(r"^\| dataset +\| estimate +\| reference +\|", text, re.M), name
