"""bench/bench_real.py's completeness bound (``--ceiling``) on a scene with a known answer:
a fronto-parallel wall at 2 m seen by cameras that step sideways, the target's left
quarter without depth; every other camera stands to the target's right, so it sees the
target's left columns only beyond its own shift of f * b / z pixels."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from depthgt.settings import FrameSetSettings
from depthgt.sources.base import Frame

REPO = Path(__file__).resolve().parents[1]
HW = (64, 64)
F_PX, Z_M, STEP_M = 60.0, 2.0, 0.1  # a camera |i - 6| steps to the right: shift 3 px per step
TARGET, N_FRAMES, HOLE_COLS = 6, 13, 16


def _bench_real():
    spec = importlib.util.spec_from_file_location("bench_real", REPO / "bench/bench_real.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


class WallScene:
    name, image_size, has_poses, has_clean_depth, colour_matches_depth = "wall", HW, True, False, True
    intrinsics = np.array([[F_PX, 0, 31.5], [0, F_PX, 31.5], [0, 0, 1]])

    def __len__(self) -> int:
        return N_FRAMES

    def frame_id(self, i: int) -> str:
        return f"{i:03d}"

    def read(self, i: int) -> Frame:
        T = np.eye(4)
        T[0, 3] = abs(i - TARGET) * STEP_M
        depth = np.full(HW, Z_M, np.float32)
        if i == TARGET:
            depth[:, :HOLE_COLS] = 0.0
        return Frame(np.full((*HW, 3), 128, np.uint8), depth, T)


def test_ceiling_counts_the_pixels_the_other_frames_reach():
    fs = FrameSetSettings(coverage_span=1)  # the core: +-2, 4, 6 (shift >= 6 px); the span: +-1 (3 px)
    (row,) = _bench_real().ceiling(WallScene(), "wall", 1, None, fs, size=HW)
    cols = HW[1]
    assert row["target"] == TARGET
    assert row["input_completeness"] == pytest.approx((cols - HOLE_COLS) / cols)
    assert row["ceiling_core"] == pytest.approx((cols - 6) / cols)
    assert row["ceiling_core_d1"] == pytest.approx((cols - 5) / cols)
    assert row["ceiling_span"] == pytest.approx((cols - 3) / cols)
    assert row["ceiling_all"] == pytest.approx((cols - 3) / cols)
    assert row["ceiling_all_d1"] == pytest.approx((cols - 2) / cols)
