"""Smooth handheld-like camera paths inside a synthetic room.

A path is a closed-form function of the frame number, so that any frame's pose is
computed without the earlier ones (random access). The camera walks slowly along an
arc around the room's focus (the table) while its gaze sweeps over the furniture;
small sinusoids of a few frames' period add the shake and roll of a hand-held
sensor. Default speeds follow the 7-Scenes fixture: ~5 mm and a fraction of a
degree per frame (the fixture's median is 3.6 mm / 0.19 deg, its 95th percentile
13 mm / 0.48 deg).

Two kinds: :class:`CameraPath` (furnished rooms: an arc around the table) and
:class:`WalkPath` (the ``varied`` family: a slow walk along the room's long axis whose
gaze pans and tilts up and down, so that far walls, ceilings and floors at grazing
angles come into view).

Poses are camera-to-world (4, 4) float64 with OpenCV camera axes (x right, y down,
z forward); the world is z up.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from depthgt.synth.scene import Layout, raycast_depth

log = logging.getLogger(__name__)

__all__ = ["CameraPath", "WalkPath", "look_at", "make_path", "make_walk_path"]


def look_at(position: np.ndarray, target: np.ndarray, roll_rad: float = 0.0) -> np.ndarray:
    """Camera-to-world pose of a camera at ``position`` looking at ``target`` (world
    z up), rolled by ``roll_rad`` about its optical axis (written here: kornia has
    no look-at pose constructor).

    Returns:
        (4, 4) float64 pose, OpenCV camera axes.
    """
    position = np.asarray(position, np.float64)
    fwd = np.asarray(target, np.float64) - position
    norm = np.linalg.norm(fwd)
    if norm < 1e-9:
        raise ValueError("look_at: target coincides with the camera position")
    fwd /= norm
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-6:
        raise ValueError("look_at: camera looks straight up or down")
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    R = np.stack([right, down, fwd], 1) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = position
    return T


@dataclass(frozen=True)
class CameraPath:
    """Parameters of a path; :meth:`pose` evaluates it at a frame number.

    Attributes:
        focus: (3,) world point the path circles (metres).
        radius_m, height_m: mean distance from the focus axis and camera height.
        phase0: start angle on the arc (rad); ``step_m``: arc length per frame.
        speed_var, speed_period: relative amplitude and period (frames) of the
            variation of the walking speed.
        beyond_m: the gaze aims this far past the focus, away from the camera.
        gaze_amp_m: (3,) amplitude of the gaze target's sweep around the focus.
        gaze_period: (3,) periods of that sweep in frames; ``gaze_phase``: (3,) phases.
        shake: (k, 5) rows (amplitude_m, period_frames, phase, axis, roll_amp_rad).
        roll0_rad: mean roll.
    """

    focus: np.ndarray
    radius_m: float
    height_m: float
    phase0: float
    step_m: float
    speed_var: float
    speed_period: float
    beyond_m: float
    gaze_amp_m: np.ndarray
    gaze_period: np.ndarray
    gaze_phase: np.ndarray
    shake: np.ndarray
    roll0_rad: float

    def position_and_target(self, i: float) -> tuple[np.ndarray, np.ndarray, float]:
        """Camera centre, gaze target (world, metres) and roll (rad) at frame ``i``."""
        # arc around the focus; radius and height breathe slowly
        # speed varies by +-speed_var around step_m over speed_period frames
        walked = i + self.speed_var * self.speed_period / (2 * np.pi) * np.sin(
            2 * np.pi * i / self.speed_period + self.phase0
        )
        ang = self.phase0 + self.step_m * walked / self.radius_m
        rad = self.radius_m + 0.1 * np.sin(2 * np.pi * i / 170.0 + self.phase0)
        height = self.height_m + 0.06 * np.sin(2 * np.pi * i / 130.0 + 2 * self.phase0)
        pos = np.array([self.focus[0] + rad * np.cos(ang), self.focus[1] + rad * np.sin(ang), height])
        # gaze: across the focus to the furniture behind it, sweeping slowly
        radial = np.array([np.cos(ang), np.sin(ang), 0.0])
        target = (
            self.focus
            - self.beyond_m * radial
            + self.gaze_amp_m * np.sin(2 * np.pi * i / self.gaze_period + self.gaze_phase)
        )
        roll = self.roll0_rad
        for amp, period, phase, axis, roll_amp in self.shake:
            w = np.sin(2 * np.pi * i / period + phase)
            pos[int(axis)] += amp * w
            roll += roll_amp * w
        return pos, target, roll

    def pose(self, i: float) -> np.ndarray:
        """(4, 4) float64 camera-to-world pose at frame ``i``."""
        pos, target, roll = self.position_and_target(i)
        return look_at(pos, target, roll)


def _random_path(layout: Layout, rng: np.random.Generator, step_m: float, sweep_m: float) -> CameraPath:
    k = 4
    shake = np.stack(
        [
            rng.uniform(0.0005, 0.0015, k),  # metres
            rng.uniform(6, 25, k),  # frames
            rng.uniform(0, 2 * np.pi, k),
            rng.integers(0, 3, k).astype(np.float64),
            np.radians(rng.uniform(0.05, 0.15, k)),
        ],
        1,
    )
    focus = layout.focus.copy()
    focus[2] = rng.uniform(0.5, 0.9)
    return CameraPath(
        focus=focus,
        radius_m=float(rng.uniform(1.1, 1.6)),
        height_m=float(rng.uniform(1.2, 1.7)),
        phase0=float(rng.uniform(0, 2 * np.pi)),
        step_m=float(step_m * rng.uniform(0.8, 1.2) * rng.choice([-1, 1])),
        speed_var=float(rng.uniform(0.4, 0.7)),
        speed_period=float(rng.uniform(50, 120)),
        beyond_m=float(rng.uniform(0.0, 0.6)),
        gaze_amp_m=np.array([sweep_m, sweep_m, 0.25 * sweep_m]) * rng.uniform(0.6, 1.0, 3),
        gaze_period=rng.uniform(120, 250, 3),
        gaze_phase=rng.uniform(0, 2 * np.pi, 3),
        shake=shake,
        roll0_rad=float(np.radians(rng.uniform(-4, 4))),
    )


def _clearance_ok(layout: Layout, positions: np.ndarray, margin_m: float) -> bool:
    """All camera centres (N, 3) at least ``margin_m`` from the walls, floor, ceiling
    and from the bounding box of every primitive."""
    if ((positions < margin_m) | (positions > layout.size - margin_m)).any():
        return False
    lo = layout.aabbs[None, :, :3] - margin_m
    hi = layout.aabbs[None, :, 3:] + margin_m
    p = positions[:, None, :]
    return not ((p > lo) & (p < hi)).all(-1).any()


def make_path(
    layout: Layout,
    rng: np.random.Generator,
    n_frames: int,
    K: np.ndarray,
    hw: tuple[int, int],
    step_m: float = 0.005,
    sweep_m: float = 0.5,
    min_depth_m: float = 0.4,
    max_depth_m: float = 3.5,
    max_tries: int = 60,
) -> CameraPath:
    """Draw a path that stays clear of the furniture for frames ``0..n_frames-1``.

    A candidate is accepted when the camera centre keeps 0.3 m from every primitive's
    bounding box and from the room at 16 frames spread over the sequence, and an
    80-pixel-wide ray cast at 6 of them sees less than 3% of pixels nearer than
    ``min_depth_m`` in every view and, on average over the views, less than 5%
    farther than ``max_depth_m`` and a median depth of 1-2.2 m (the 7-Scenes
    fixture: median ~1.9 m, 99% below 3.1 m). Otherwise the candidate with the best
    score is returned. The path depends on the layout, the generator and
    ``n_frames`` (not on the resolution).

    Args:
        K: (3, 3) intrinsics at ``hw`` (only the field of view matters).
        step_m: mean translation per frame; sweep_m: gaze sweep amplitude (metres at
            the focus, which sets the rotation per frame).
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    # checks at a fixed 80-pixel width, so that the path does not depend on the resolution
    from depthgt.geometry import scale_intrinsics  # torch: imported when a path is made, not with the module

    small_hw = (max(int(round(80 * hw[0] / hw[1])), 8), 80)
    K_small = scale_intrinsics(np.asarray(K, np.float64), hw, small_hw)
    frames_pos = np.linspace(0, n_frames - 1, 16)
    frames_cast = np.linspace(0, n_frames - 1, 6)
    best, best_score = None, -np.inf
    for _ in range(max_tries):
        path = _random_path(layout, rng, step_m, sweep_m)
        if not _clearance_ok(layout, np.stack([path.position_and_target(i)[0] for i in frames_pos]), 0.3):
            continue
        near_frac, far_frac, medians = [], [], []
        for i in frames_cast:
            depth = raycast_depth(layout, path.pose(i), K_small, small_hw)
            near_frac.append(float((depth < min_depth_m).mean()))
            far_frac.append(float((depth > max_depth_m).mean()))
            medians.append(float(np.median(depth)))
        med, far = float(np.mean(medians)), float(np.mean(far_frac))
        score = -max(near_frac) - far - max(0.0, 1.0 - med) - max(0.0, med - 2.2)
        if max(near_frac) < 0.03 and far < 0.05 and 1.0 <= med <= 2.2:
            return path
        if score > best_score:
            best, best_score = path, score
    if best is None:
        raise RuntimeError("no collision-free camera path found in this room")
    log.info("camera path: no candidate met every view criterion in %d tries; using the best one", max_tries)
    return best


@dataclass(frozen=True)
class WalkPath:
    """A walk along a heading with a panning and tilting gaze; :meth:`pose` evaluates it.

    Attributes:
        start: (3,) camera centre at frame 0 (metres).
        heading: walking direction (rad, world yaw about z); ``step_m`` arc length per
            frame, varying by +-``speed_var`` over ``speed_period`` frames.
        yaw0, yaw_amp, yaw_period, yaw_phase: gaze yaw relative to the heading,
            ``yaw0 + yaw_amp sin(2 pi i / yaw_period + yaw_phase)`` (rad, frames).
        pitch0, pitch_amp, pitch_period, pitch_phase: gaze elevation (rad, positive
            looks up), same form.
        shake: (k, 5) rows (amplitude_m, period_frames, phase, axis, roll_amp_rad).
        roll0_rad: mean roll.
    """

    start: np.ndarray
    heading: float
    step_m: float
    speed_var: float
    speed_period: float
    yaw0: float
    yaw_amp: float
    yaw_period: float
    yaw_phase: float
    pitch0: float
    pitch_amp: float
    pitch_period: float
    pitch_phase: float
    shake: np.ndarray
    roll0_rad: float

    def position_and_target(self, i: float) -> tuple[np.ndarray, np.ndarray, float]:
        """Camera centre, a gaze target 1 m ahead (world, metres) and roll (rad) at frame ``i``."""
        walked = i + self.speed_var * self.speed_period / (2 * np.pi) * np.sin(
            2 * np.pi * i / self.speed_period + self.yaw_phase
        )
        direction = np.array([np.cos(self.heading), np.sin(self.heading), 0.0])
        pos = self.start + self.step_m * walked * direction
        yaw = self.heading + self.yaw0 + self.yaw_amp * np.sin(2 * np.pi * i / self.yaw_period + self.yaw_phase)
        pitch = self.pitch0 + self.pitch_amp * np.sin(2 * np.pi * i / self.pitch_period + self.pitch_phase)
        roll = self.roll0_rad
        for amp, period, phase, axis, roll_amp in self.shake:
            w = np.sin(2 * np.pi * i / period + phase)
            pos[int(axis)] += amp * w
            roll += roll_amp * w
        gaze = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
        return pos, pos + gaze, roll

    def pose(self, i: float) -> np.ndarray:
        """(4, 4) float64 camera-to-world pose at frame ``i``."""
        pos, target, roll = self.position_and_target(i)
        return look_at(pos, target, roll)


def _random_walk(layout: Layout, rng: np.random.Generator, step_m: float) -> WalkPath:
    size = layout.size
    margin = 0.45
    start = np.array(
        [rng.uniform(margin, size[0] - margin), rng.uniform(margin, size[1] - margin), rng.uniform(1.15, 1.8)]
    )
    # walk along the long axis, towards its farther end, so that the far wall is in view
    axis = 0 if size[0] >= size[1] else 1
    towards = 1.0 if start[axis] < size[axis] / 2 else -1.0
    heading = (0.0 if towards > 0 else np.pi) if axis == 0 else towards * np.pi / 2
    heading += rng.uniform(-0.5, 0.5)
    k = 4
    shake = np.stack(
        [
            rng.uniform(0.0005, 0.0015, k),
            rng.uniform(6, 25, k),
            rng.uniform(0, 2 * np.pi, k),
            rng.integers(0, 3, k).astype(np.float64),
            np.radians(rng.uniform(0.05, 0.15, k)),
        ],
        1,
    )
    return WalkPath(
        start=start,
        heading=float(heading),
        step_m=float(step_m * rng.uniform(0.8, 1.2)),
        speed_var=float(rng.uniform(0.3, 0.6)),
        speed_period=float(rng.uniform(50, 120)),
        yaw0=float(rng.uniform(-0.6, 0.6)),
        yaw_amp=float(rng.uniform(0.15, 0.5)),
        yaw_period=float(rng.uniform(160, 320)),
        yaw_phase=float(rng.uniform(0, 2 * np.pi)),
        pitch0=float(rng.uniform(-0.45, 0.3)),
        pitch_amp=float(rng.uniform(0.1, 0.35)),
        pitch_period=float(rng.uniform(150, 300)),
        pitch_phase=float(rng.uniform(0, 2 * np.pi)),
        shake=shake,
        roll0_rad=float(np.radians(rng.uniform(-4, 4))),
    )


def make_walk_path(
    layout: Layout,
    rng: np.random.Generator,
    n_frames: int,
    K: np.ndarray,
    hw: tuple[int, int],
    step_m: float = 0.005,
    min_depth_m: float = 0.4,
    max_tries: int = 60,
) -> WalkPath:
    """Draw a :class:`WalkPath` that stays clear of the walls and the furniture.

    A candidate is accepted when the camera centre keeps 0.3 m from every primitive's
    bounding box and from the room at 16 frames spread over the sequence, and an
    80-pixel-wide ray cast at 6 of them sees less than 3% of pixels nearer than
    ``min_depth_m`` in every view, and the 90th depth percentile, averaged over the
    views, reaches ``min(4.5 m, 0.6 x the room's longest side)`` (the far range is in
    view). Otherwise the candidate with the best score is returned. Depends on the
    layout, the generator and ``n_frames`` (not on the resolution).
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    from depthgt.geometry import scale_intrinsics  # torch: imported when a path is made, not with the module

    small_hw = (max(int(round(80 * hw[0] / hw[1])), 8), 80)
    K_small = scale_intrinsics(np.asarray(K, np.float64), hw, small_hw)
    frames_pos = np.linspace(0, n_frames - 1, 16)
    frames_cast = np.linspace(0, n_frames - 1, 6)
    want_far = min(4.5, 0.6 * float(layout.size[:2].max()))
    best, best_score = None, -np.inf
    for _ in range(max_tries):
        path = _random_walk(layout, rng, step_m)
        if not _clearance_ok(layout, np.stack([path.position_and_target(i)[0] for i in frames_pos]), 0.3):
            continue
        near_frac, far = [], []
        for i in frames_cast:
            depth = raycast_depth(layout, path.pose(i), K_small, small_hw)
            near_frac.append(float((depth < min_depth_m).mean()))
            far.append(float(np.quantile(depth, 0.9)))
        p90 = float(np.mean(far))
        score = -10 * max(near_frac) - max(0.0, want_far - p90)
        if max(near_frac) < 0.03 and p90 >= want_far:
            return path
        if score > best_score:
            best, best_score = path, score
    if best is None:
        raise RuntimeError("no collision-free walk path found in this space")
    log.info("walk path: no candidate met every view criterion in %d tries; using the best one", max_tries)
    return best
