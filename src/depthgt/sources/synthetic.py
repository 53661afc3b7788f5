"""Synthetic RGB-D source: procedural indoor scenes seen by a simulated depth sensor.

The embedded default of the workflow and the synthetic test set (the paper's
SceneNet role): every frame comes with its exact depth (``clean_depth_m``) and pose,
so the GT's own error against the truth can be measured.

Two families, chosen by the scene name:

* ``room_000``, ``room_001``, ...: furnished rooms of 3.5-5 m
  (:func:`depthgt.synth.scene.generate_layout`) seen by a camera circling the table
  (:func:`depthgt.synth.camera.make_path`), default intrinsics of a Kinect v1;
* ``varied_000``, ``varied_001``, ...: the harder family of
  :mod:`depthgt.synth.spaces` (open rooms, corridors and offices of 3-9 m, far walls
  at 5-8 m, floors and ceilings at grazing angles, thin poles and legs of 1-3 cm,
  clutter, dark and glossy surfaces) seen by a walking camera that pans and tilts
  (:func:`depthgt.synth.camera.make_walk_path`); each scene draws its own intrinsics
  (fx from 450 to 600 at 640 px width) unless they are given, and the sensor's range
  reaches 8 m (``max_range_m`` 8, dropout ramping up over the last 2.5 m).

The number together with the ``seed`` option fixes the layout and its textures, and
with ``n_frames`` the camera path (chosen to stay clear of the furniture over the whole
sequence; it does not depend on the resolution). Any frame is rendered on demand from
closed-form poses (random access); nothing per frame is cached. ``root`` is ignored
(may be None).

Options (all optional):

* ``seed`` (int, 0), ``n_frames`` (int, 40), ``n_scenes`` (int, 3) and ``family``
  (``room`` or ``varied``) for ``list_scenes``;
* ``width``, ``height`` (640, 480), ``fx``, ``fy``, ``cx``, ``cy`` (rooms: 585, 585,
  320, 240 at the default size; when only the size is given, scaled from those);
* ``noise`` (bool, true): sensor noise on ``depth_m``; otherwise ``depth_m`` is the
  exact depth;
* ``sensor`` (``kinect_v1``): the sensor profile, one of
  :data:`depthgt.synth.noise.SENSOR_PROFILES` (``kinect_v1``: calibrated on the
  7-Scenes fixture; ``coarse_stereo``: coarser far-range quantisation, a noise law
  without the Kinect's fall-off, wider edge shadows);
* ``noise_<field>``: any field of :class:`depthgt.synth.noise.KinectNoise`, replacing
  the profile's, e.g. ``noise_sigma_disp_px``, ``noise_max_range_m``;
* ``rgb_noise`` (float, 2.0): std of the colour sensor noise in 8-bit levels;
* ``step_mm`` (float, 5): mean camera translation per frame; ``sweep_m`` (float,
  0.5): amplitude of the gaze sweep of the room family (sets the rotation per
  frame, ~0.2-1 deg).
"""

from __future__ import annotations

import logging
import re
from dataclasses import fields
from functools import cached_property
from typing import Any, NamedTuple

import cv2
import numpy as np

from depthgt.errors import ConfigError, FrameError, SourceError
from depthgt.sources.base import Frame
from depthgt.synth.camera import CameraPath, WalkPath, make_path, make_walk_path
from depthgt.synth.noise import SENSOR_PROFILES, KinectNoise, infrared_return, kinect_noise, sensor_profile
from depthgt.synth.scene import Layout, albedo, generate_layout, raycast, shade, thin_mask
from depthgt.synth.spaces import generate_space_layout

__all__ = ["SyntheticScene", "ExactView", "FAMILIES", "open_scene", "list_scenes", "frame_count", "parse_scene_name"]

log = logging.getLogger(__name__)

FAMILIES = ("room", "varied")
_NAME = re.compile(r"^(room|varied)_(\d{3,})$")
# sensor settings the varied family changes from the profile: depth out to 8 m
_FAMILY_NOISE = {"room": {}, "varied": {"max_range_m": 8.0, "far_ramp_m": 2.5}}
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
    "sensor": "kinect_v1",
    "family": "room",
    "rgb_noise": 2.0,
    "step_mm": 5.0,
    "sweep_m": 0.5,
}
# Seed-sequence stream tags: layout, path, depth noise, colour noise, intrinsics.
_STREAM_LAYOUT, _STREAM_PATH, _STREAM_DEPTH, _STREAM_RGB, _STREAM_INTRINSICS = 0, 1, 2, 3, 4
# the varied family's seed sequences carry this extra tag, so that varied_000 and
# room_000 of one seed draw independent numbers
_FAMILY_TAG = {"room": (), "varied": (1,)}


def parse_scene_name(scene: str) -> tuple[str, int]:
    """(family, number) of a scene name ``room_NNN`` or ``varied_NNN``; raises
    SourceError naming it."""
    m = _NAME.match(str(scene))
    if m is None:
        raise SourceError(
            f"synthetic scene name {scene!r} is not of the form room_000, room_001, ... or varied_000, varied_001, ..."
        )
    return m.group(1), int(m.group(2))


def _int_option(opts, key, lo):
    v = opts[key]
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
        raise ConfigError(f"synthetic option {key!r} must be an integer >= {lo}, got {v!r}")
    return int(v)


def _float_option(opts, key, lo, strict=True):
    v = opts[key]
    if (
        isinstance(v, bool)
        or not isinstance(v, (int, float, np.floating, np.integer))
        or not np.isfinite(v)
        or (v <= lo if strict else v < lo)
    ):
        raise ConfigError(f"synthetic option {key!r} must be a number {'>' if strict else '>='} {lo}, got {v!r}")
    return float(v)


def _resolve_options(options: dict[str, Any], family: str = "room") -> tuple[dict[str, Any], KinectNoise]:
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
    for key in ("fx", "fy", "cx", "cy"):
        if opts[key] is not None:
            opts[key] = _float_option(opts, key, 0.0)
    if not isinstance(opts["noise"], (bool, np.bool_)):
        raise ConfigError(f"synthetic option 'noise' must be true or false, got {opts['noise']!r}")
    if opts["sensor"] not in SENSOR_PROFILES:
        raise ConfigError(
            f"synthetic option 'sensor' must be one of {', '.join(SENSOR_PROFILES)}, got {opts['sensor']!r}"
        )
    if opts["family"] not in FAMILIES:
        raise ConfigError(f"synthetic option 'family' must be one of {', '.join(FAMILIES)}, got {opts['family']!r}")
    opts["rgb_noise"] = _float_option(opts, "rgb_noise", 0.0, strict=False)
    opts["step_mm"] = _float_option(opts, "step_mm", 0.0)
    opts["sweep_m"] = _float_option(opts, "sweep_m", 0.0, strict=False)
    try:
        noise = sensor_profile(opts["sensor"], **{**_FAMILY_NOISE[family], **noise_kw})
    except (TypeError, ValueError) as e:
        raise ConfigError(f"synthetic noise options: {e}") from e
    return opts, noise


def _intrinsics(opts: dict[str, Any], family: str, rng: np.random.Generator) -> np.ndarray:
    """(3, 3) intrinsics at the option's size: the given values, else the family's
    (rooms: Kinect v1, fx = 585 at 640 px; varied: fx drawn from 450-600 at 640 px,
    fy within 1% of it, principal point within 8 px of the centre)."""
    w, h = opts["width"], opts["height"]
    if family == "varied":
        fx = rng.uniform(450.0, 600.0)
        fy = fx * rng.uniform(0.99, 1.01)
        cx, cy = 319.5 + rng.uniform(-8.0, 8.0), 239.5 + rng.uniform(-6.0, 6.0)
    else:
        fx, fy, cx, cy = 585.0, 585.0, 320.0, 240.0
    defaults = {
        "fx": fx * w / 640,
        "fy": fy * h / 480,
        "cx": (cx + 0.5) * w / 640 - 0.5,
        "cy": (cy + 0.5) * h / 480 - 0.5,
    }
    v = {k: (opts[k] if opts[k] is not None else defaults[k]) for k in defaults}
    return np.array([[v["fx"], 0.0, v["cx"]], [0.0, v["fy"], v["cy"]], [0.0, 0.0, 1.0]])


class ExactView(NamedTuple):
    """The exact geometry of one view of a synthetic scene (:meth:`SyntheticScene.exact_view`).

    depth_m: (H, W) float32 exact z-depth at the pixel centres.
    cos_incidence: (H, W) float32 |cos| of the angle between the viewing ray and the
        surface normal (1 = seen head-on; incidence above 65 deg is cos < 0.423).
    thin: (H, W) bool, the pixel sees a thin structure (a pole, leg or rod at most
        3 cm wide, :attr:`depthgt.synth.scene.Primitive.thin`).
    """

    depth_m: np.ndarray
    cos_incidence: np.ndarray
    thin: np.ndarray


class SyntheticScene:
    """One procedural scene and its camera path (see the module docstring).

    Attributes follow :class:`depthgt.sources.base.Scene`; in addition ``family``,
    ``layout`` (the room), ``path`` (the camera path) and ``noise_settings``. The room
    and the path are built on first use (the first frame read): the metadata (frame
    count and ids, intrinsics, size) costs nothing, as a scene index needs only those.
    """

    has_poses = True
    has_clean_depth = True

    def __init__(self, scene: str, **options: Any):
        self.family, self.room = parse_scene_name(scene)
        self.name = scene
        opts, self.noise_settings = _resolve_options(options, self.family)
        self.options = opts
        self.seed = opts["seed"]
        self.n_frames = opts["n_frames"]
        self.image_size = (opts["height"], opts["width"])
        self.intrinsics = _intrinsics(opts, self.family, self._rng(_STREAM_INTRINSICS))

    @cached_property
    def layout(self) -> Layout:
        """The room (its geometry and textures)."""
        gen = generate_space_layout if self.family == "varied" else generate_layout
        layout = gen(self._rng(_STREAM_LAYOUT))
        log.debug(
            "built synthetic %s (seed %d): room %s m, %d primitives",
            self.name,
            self.seed,
            layout.size.round(2).tolist(),
            len(layout.primitives),
        )
        return layout

    @cached_property
    def path(self) -> CameraPath | WalkPath:
        """The camera path over the ``n_frames`` frames."""
        step_m = self.options["step_mm"] / 1000.0
        if self.family == "varied":
            return make_walk_path(
                self.layout, self._rng(_STREAM_PATH), self.n_frames, self.intrinsics, self.image_size, step_m=step_m
            )
        return make_path(
            self.layout,
            self._rng(_STREAM_PATH),
            self.n_frames,
            self.intrinsics,
            self.image_size,
            step_m=step_m,
            sweep_m=self.options["sweep_m"],
        )

    @cached_property
    def _ir_return(self) -> np.ndarray:
        return np.array([m.ir_return for m in self.layout.materials], np.float32)

    @cached_property
    def _gloss(self) -> np.ndarray:
        return np.array([m.gloss for m in self.layout.materials], np.float32)

    def _rng(self, stream: int, frame: int = 0) -> np.random.Generator:
        return np.random.default_rng([self.seed, self.room, stream, frame, *_FAMILY_TAG[self.family]])

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
            if self._gloss.any():  # glossy surfaces return little at oblique angles, saturate head-on
                cos = _cos_incidence(normals_cam, self.intrinsics, self.image_size)
                ir = infrared_return(alb.mean(-1), self._ir_return[hits.material], self._gloss[hits.material], cos)
            depth = kinect_noise(
                clean, self.intrinsics, self._rng(_STREAM_DEPTH, int(i)), self.noise_settings, normals_cam, ir
            )
        else:
            depth = clean.copy()
        return Frame(rgb=rgb_u8, depth_m=depth, T_world_cam=T_world_cam, clean_depth_m=clean)

    def exact_view(self, i: int, K: np.ndarray | None = None, size_hw: tuple[int, int] | None = None) -> ExactView:
        """Exact depth, incidence and thin-structure mask of frame ``i``'s view, ray cast
        at the pixel centres of intrinsics ``K`` (3, 3) at ``size_hw`` (default: the
        scene's own); e.g. the truth at the working resolution for per-pixel categories."""
        K = self.intrinsics if K is None else np.asarray(K, np.float64)
        hw = self.image_size if size_hw is None else tuple(size_hw)
        T_world_cam = self.pose(i)
        hits = raycast(self.layout, T_world_cam, K, hw)
        normals_cam = hits.normals_world @ T_world_cam[:3, :3].astype(np.float32)
        return ExactView(hits.depth_m, _cos_incidence(normals_cam, K, hw), thin_mask(self.layout, hits))


def _cos_incidence(normals_cam: np.ndarray, K: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """(H, W) float32 |cos| between the pixel rays of ``K`` and the (H, W, 3) camera-frame normals."""
    h, w = hw
    u = np.arange(w, dtype=np.float32)[None, :]
    v = np.arange(h, dtype=np.float32)[:, None]
    x_n = (u - np.float32(K[0, 2])) / np.float32(K[0, 0])
    y_n = (v - np.float32(K[1, 2])) / np.float32(K[1, 1])
    norm = np.sqrt(x_n * x_n + y_n * y_n + 1)
    return (np.abs(normals_cam[..., 0] * x_n + normals_cam[..., 1] * y_n + normals_cam[..., 2]) / norm).astype(
        np.float32
    )


def open_scene(root: str | None, scene: str, **options: Any) -> SyntheticScene:
    """Open synthetic scene ``scene`` (``room_NNN`` or ``varied_NNN``); ``root`` is ignored.

    Raises:
        SourceError: the name is neither ``room_NNN`` nor ``varied_NNN``.
        ConfigError: an option is unknown or invalid (the message names it).
    """
    return SyntheticScene(scene, **options)


def frame_count(root: str | None, scene: str, **options: Any) -> int:
    """``n_frames`` (option, default 40) without building the scene."""
    parse_scene_name(scene)
    opts, _ = _resolve_options(options)
    return int(opts["n_frames"])


def list_scenes(root: str | None, **options: Any) -> list[str]:
    """``{family}_000`` .. ``{family}_{n_scenes-1}`` (options ``family``, default ``room``,
    and ``n_scenes``, default 3)."""
    opts, _ = _resolve_options(options)
    return [f"{opts['family']}_{k:03d}" for k in range(opts["n_scenes"])]
