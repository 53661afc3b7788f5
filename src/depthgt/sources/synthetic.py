"""Synthetic RGB-D source: procedural furnished rooms seen by a simulated Kinect v1.

The embedded default of the workflow and the synthetic test set (the paper's
SceneNet role): every frame comes with its exact depth (``clean_depth_m``) and pose,
so the GT's own error against the truth can be measured.

Scenes are named ``room_000``, ``room_001``, ...; the number together with the
``seed`` option fixes the room layout and its textures, and with ``n_frames`` the
camera path (chosen to stay clear of the furniture over the whole sequence; it does
not depend on the resolution). Any frame is
rendered on demand from closed-form poses (random access); nothing per frame is
cached. ``root`` is ignored (may be None).

Options (all optional):

* ``seed`` (int, 0), ``n_frames`` (int, 40), ``n_scenes`` (int, 3; for ``list_scenes``);
* ``width``, ``height`` (640, 480), ``fx``, ``fy``, ``cx``, ``cy`` (585, 585, 320,
  240 at the default size; when only the size is given, scaled from those);
* ``noise`` (bool, true): Kinect v1 noise on ``depth_m``; otherwise ``depth_m`` is
  the exact depth;
* ``noise_<field>``: any field of :class:`depthgt.synth.noise.KinectNoise`, e.g.
  ``noise_sigma_disp_px``, ``noise_max_range_m``, ``noise_jitter_px``;
* ``rgb_noise`` (float, 2.0): std of the colour sensor noise in 8-bit levels;
* ``step_mm`` (float, 5): mean camera translation per frame; ``sweep_m`` (float,
  0.5): amplitude of the gaze sweep (sets the rotation per frame, ~0.2-1 deg).
"""

from __future__ import annotations

import logging
import re
from dataclasses import fields
from typing import Any

import cv2
import numpy as np

from depthgt.errors import ConfigError, FrameError, SourceError
from depthgt.sources.base import Frame
from depthgt.synth.camera import CameraPath, make_path
from depthgt.synth.noise import KinectNoise, kinect_noise
from depthgt.synth.scene import Layout, albedo, generate_layout, raycast, shade

__all__ = ["SyntheticScene", "open_scene", "list_scenes", "parse_scene_name"]

log = logging.getLogger(__name__)

_NAME = re.compile(r"^room_(\d{3,})$")
_NOISE_FIELDS = {f.name for f in fields(KinectNoise)}
_DEFAULTS: dict[str, Any] = {
    "seed": 0,
    "n_frames": 40,
    "n_scenes": 3,
    "width": 640,
    "height": 480,
    "fx": None,
    "fy": None,
    "cx": None,
    "cy": None,
    "noise": True,
    "rgb_noise": 2.0,
    "step_mm": 5.0,
    "sweep_m": 0.5,
}
# Seed-sequence stream tags: layout, path, depth noise, colour noise.
_STREAM_LAYOUT, _STREAM_PATH, _STREAM_DEPTH, _STREAM_RGB = 0, 1, 2, 3


def parse_scene_name(scene: str) -> int:
    """Room number of a scene name ``room_NNN``; raises SourceError naming it."""
    m = _NAME.match(str(scene))
    if m is None:
        raise SourceError(f"synthetic scene name {scene!r} is not of the form room_000, room_001, ...")
    return int(m.group(1))


def _int_option(opts, key, lo):
    v = opts[key]
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
        raise ConfigError(f"synthetic option {key!r} must be an integer >= {lo}, got {v!r}")
    return int(v)


def _float_option(opts, key, lo, strict=True):
    v = opts[key]
    if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) or not np.isfinite(v) or (v <= lo if strict else v < lo):
        raise ConfigError(f"synthetic option {key!r} must be a number {'>' if strict else '>='} {lo}, got {v!r}")
    return float(v)


def _resolve_options(options: dict[str, Any]) -> tuple[dict[str, Any], KinectNoise]:
    noise_kw = {}
    opts = dict(_DEFAULTS)
    for key, value in options.items():
        if key.startswith("noise_") and key[6:] in _NOISE_FIELDS:
            noise_kw[key[6:]] = value
        elif key in _DEFAULTS:
            opts[key] = value
        else:
            known = sorted(_DEFAULTS) + sorted("noise_" + f for f in _NOISE_FIELDS)
            raise ConfigError(f"unknown synthetic option {key!r}; known options: {', '.join(known)}")
    for key, lo in (("seed", 0), ("n_frames", 1), ("n_scenes", 1), ("width", 32), ("height", 32)):
        opts[key] = _int_option(opts, key, lo)
    w, h = opts["width"], opts["height"]
    defaults = {"fx": 585.0 * w / 640, "fy": 585.0 * h / 480, "cx": (320.0 + 0.5) * w / 640 - 0.5, "cy": (240.0 + 0.5) * h / 480 - 0.5}
    for key in ("fx", "fy", "cx", "cy"):
        if opts[key] is None:
            opts[key] = defaults[key]
        opts[key] = _float_option(opts, key, 0.0)
    if not isinstance(opts["noise"], (bool, np.bool_)):
        raise ConfigError(f"synthetic option 'noise' must be true or false, got {opts['noise']!r}")
    opts["rgb_noise"] = _float_option(opts, "rgb_noise", 0.0, strict=False)
    opts["step_mm"] = _float_option(opts, "step_mm", 0.0)
    opts["sweep_m"] = _float_option(opts, "sweep_m", 0.0, strict=False)
    try:
        noise = KinectNoise(**noise_kw)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"synthetic noise options: {e}") from e
    return opts, noise


class SyntheticScene:
    """One procedural room and its camera path (see the module docstring).

    Attributes follow :class:`depthgt.sources.base.Scene`; in addition ``layout``
    (the room), ``path`` (the camera path) and ``noise_settings``.
    """

    has_poses = True
    has_clean_depth = True

    def __init__(self, scene: str, **options: Any):
        self.room = parse_scene_name(scene)
        self.name = scene
        opts, self.noise_settings = _resolve_options(options)
        self.options = opts
        self.seed = opts["seed"]
        self.n_frames = opts["n_frames"]
        self.image_size = (opts["height"], opts["width"])
        self.intrinsics = np.array([[opts["fx"], 0.0, opts["cx"]], [0.0, opts["fy"], opts["cy"]], [0.0, 0.0, 1.0]])
        self.layout: Layout = generate_layout(self._rng(_STREAM_LAYOUT))
        self.path: CameraPath = make_path(
            self.layout, self._rng(_STREAM_PATH), self.n_frames, self.intrinsics, self.image_size,
            step_m=opts["step_mm"] / 1000.0, sweep_m=opts["sweep_m"],
        )
        self._ir_return = np.array([m.ir_return for m in self.layout.materials], np.float32)
        log.debug("opened synthetic %s (seed %d): room %s m, %d primitives", scene, self.seed,
                  self.layout.size.round(2).tolist(), len(self.layout.primitives))

    def _rng(self, stream: int, frame: int = 0) -> np.random.Generator:
        return np.random.default_rng([self.seed, self.room, stream, frame])

    def __len__(self) -> int:
        return self.n_frames

    def frame_id(self, i: int) -> str:
        self._check_index(i)
        return f"{int(i):06d}"

    def _check_index(self, i: int) -> None:
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not 0 <= i < self.n_frames:
            raise FrameError(f"synthetic {self.name}: frame {i!r} out of range 0..{self.n_frames - 1}", "out_of_range")

    def pose(self, i: int) -> np.ndarray:
        """(4, 4) float64 camera-to-world pose of frame ``i``."""
        self._check_index(i)
        return self.path.pose(int(i))

    def read(self, i: int) -> Frame:
        """Render frame ``i``: noisy depth, exact depth, colour and pose."""
        T_world_cam = self.pose(i)
        hits = raycast(self.layout, T_world_cam, self.intrinsics, self.image_size)
        alb = albedo(self.layout, hits)
        rgb = shade(self.layout, hits, alb)
        # colour camera: slight optical blur and sensor noise
        rgb = cv2.GaussianBlur(rgb, (0, 0), 0.6)
        if self.options["rgb_noise"] > 0:
            rng = self._rng(_STREAM_RGB, int(i))
            rgb = rgb + (self.options["rgb_noise"] / 255.0) * rng.standard_normal(rgb.shape, dtype=np.float32)
        rgb_u8 = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
        clean = hits.depth_m
        if self.options["noise"]:
            normals_cam = hits.normals_world @ T_world_cam[:3, :3].astype(np.float32)
            ir = alb.mean(-1) * self._ir_return[hits.material]
            depth = kinect_noise(clean, self.intrinsics, self._rng(_STREAM_DEPTH, int(i)), self.noise_settings, normals_cam, ir)
        else:
            depth = clean.copy()
        return Frame(rgb=rgb_u8, depth_m=depth, T_world_cam=T_world_cam, clean_depth_m=clean)


def open_scene(root: str | None, scene: str, **options: Any) -> SyntheticScene:
    """Open synthetic scene ``scene`` (``room_NNN``); ``root`` is ignored.

    Raises:
        SourceError: the name is not ``room_NNN``.
        ConfigError: an option is unknown or invalid (the message names it).
    """
    return SyntheticScene(scene, **options)


def list_scenes(root: str | None, **options: Any) -> list[str]:
    """``room_000`` .. ``room_{n_scenes-1}`` (option ``n_scenes``, default 3)."""
    opts, _ = _resolve_options(options)
    return [f"room_{k:03d}" for k in range(opts["n_scenes"])]
