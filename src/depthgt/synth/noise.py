"""Kinect v1 (structured light) depth-sensor model applied to exact synthetic depth.

The model, in the order applied by :func:`kinect_noise`:

1. Lateral jitter: depth is resampled (nearest, so depths never mix) through a smooth
   random displacement field of ``jitter_px`` pixels, which makes edges ragged.
2. Projector shadows: the IR projector sits ``baseline_m`` to the right (+x) of the IR
   camera. A point is unlit, hence without depth, when a nearer point hides it from the
   projector. With projector column ``u_p = u - fx * b / z`` a pixel is shadowed when
   some pixel to its right on the same row has a smaller ``u_p``; a reverse running
   minimum along each row finds them all at once. This gives the bands on the left of
   foreground objects seen in real Kinect frames; they are widened by
   ``shadow_grow_px`` on both sides, as the matcher's correlation window fails when
   part of it is unlit.
3. Unmatched pattern next to depth discontinuities (``edge_band_px``, dropped with
   ``edge_drop_prob``), on surfaces
   seen at grazing angles (``grazing_cos``), on dark / low-IR surfaces (``dark_level``),
   below ``min_range_m`` and towards ``max_range_m``; random small dropout blobs.
   Probabilistic drops are decided against a spatially smooth random field so that
   they form patches, not salt noise.
4. Disparity noise and quantisation: disparity ``fx * b / z`` gets Gaussian noise
   (``sigma_disp_px`` at 1 m, an i.i.d. and a spatially correlated part), is
   quantised to 1/8 pixel and converted back, so that the depth takes the discrete
   Kinect levels (step ~2.85e-3 z^2 m at fx = 585, b = 7.5 cm, as the 7-Scenes
   fixture shows) and its error grows as z^2; then rounded to millimetres as in the
   uint16 PNGs. The disparity noise std falls slowly, as z^-1/4 (fitted on the
   fixture, whose residual at 2.5-3.5 m is little more than the quantisation's own
   while at 1-1.5 m it is ~1.3x larger: a constant std overshoots the far bins by
   ~1.4x, a 1/sqrt(z) fall-off leaves far fronto-parallel walls undithered and
   undershoots the 3-3.5 m bin by up to 1.5x).
5. The sensor's invalid right border (``border_right_px`` columns).

Defaults are calibrated against the 7-Scenes kitchen fixture with the estimator of
:mod:`depthgt.synth.calibration` (bench/calibrate_noise.py). The procedure is written
here because no installed library simulates a structured-light sensor; OpenCV does
the filtering and resampling.

Sensor profiles (:data:`SENSOR_PROFILES`, the synthetic source's ``sensor`` option):

* ``kinect_v1``: the defaults above (calibrated on the fixture);
* ``coarse_stereo``: an active-stereo-like sensor with a different noise law, so that
  nothing downstream is tuned to one model: a shorter baseline (5.5 cm) and coarser
  sub-pixel disparity (1/5 px), i.e. depth levels 2.2x the Kinect's spacing
  (~6.2e-3 z^2 m at fx = 585: 10 cm at 4 m, 22 cm at 6 m), disparity noise that does
  not fall with range (std constant in disparity, so depth noise grows exactly as
  z^2), wider edge shadows and unmatched bands (6 and 2 px), more lateral jitter.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import cv2
import numpy as np

from depthgt.shapes import check_shape

__all__ = ["KinectNoise", "SENSOR_PROFILES", "sensor_profile", "infrared_return", "kinect_noise", "smooth_field"]


@dataclass(frozen=True)
class KinectNoise:
    """Settings of the Kinect v1 model (units in the names). Pixel-sized settings
    (``*_px``) are given at the Kinect's 640-pixel width and scaled with the image
    width, so that noise, quantisation levels and hole patterns do not depend on
    the rendering resolution; ``sigma_disp_*`` are the stds at 1 m, falling as
    z^-``sigma_disp_falloff`` (0: constant disparity noise)."""

    baseline_m: float = 0.075
    disparity_step_px: float = 0.125
    sigma_disp_px: float = 0.035
    sigma_disp_smooth_px: float = 0.015
    sigma_disp_falloff: float = 0.25
    jitter_px: float = 0.6
    shadow_tol_px: float = 0.5
    shadow_grow_px: int = 3
    edge_band_px: int = 1
    edge_rel_jump: float = 0.04
    edge_drop_prob: float = 0.9
    grazing_cos: float = 0.2
    dark_level: float = 0.015
    min_range_m: float = 0.45
    max_range_m: float = 3.8
    far_ramp_m: float = 0.3
    blob_fraction: float = 0.012
    border_right_px: int = 8
    round_mm: bool = True

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool):
                continue
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"KinectNoise.{f.name} must be a finite number >= 0, got {v!r}")
        if self.disparity_step_px <= 0 or self.baseline_m <= 0:
            raise ValueError("KinectNoise.baseline_m and disparity_step_px must be > 0")
        if self.max_range_m <= self.min_range_m:
            raise ValueError(
                f"KinectNoise.max_range_m ({self.max_range_m}) must exceed min_range_m ({self.min_range_m})"
            )


SENSOR_PROFILES: dict[str, KinectNoise] = {
    "kinect_v1": KinectNoise(),
    "coarse_stereo": KinectNoise(
        baseline_m=0.055,
        disparity_step_px=0.2,
        sigma_disp_px=0.05,
        sigma_disp_smooth_px=0.02,
        sigma_disp_falloff=0.0,
        jitter_px=1.0,
        shadow_grow_px=6,
        edge_band_px=2,
        edge_rel_jump=0.03,
        grazing_cos=0.25,
        blob_fraction=0.015,
        border_right_px=12,
    ),
}


def sensor_profile(name: str, **overrides) -> KinectNoise:
    """The settings of sensor profile ``name`` (see :data:`SENSOR_PROFILES`) with
    fields replaced by ``overrides``; ValueError naming an unknown profile."""
    if name not in SENSOR_PROFILES:
        raise ValueError(f"unknown sensor profile {name!r}; known: {', '.join(SENSOR_PROFILES)}")
    return replace(SENSOR_PROFILES[name], **overrides)


def infrared_return(
    albedo_gray: np.ndarray,
    ir_return: np.ndarray,
    gloss: np.ndarray,
    cos_incidence: np.ndarray,
    saturate_cos: float = 0.97,
) -> np.ndarray:
    """Infrared reflectance seen by the sensor, the ``ir_reflectance`` of :func:`kinect_noise`.

    The matte share ``1 - gloss`` returns ``albedo * ir_return`` at any angle; the
    glossy share comes back only near normal incidence (a cos^8 lobe), where it
    saturates the sensor: pixels of glossy surfaces (gloss >= 0.3) with the viewing
    ray within acos(``saturate_cos``) of their normal return 0 (no depth).

    Args:
        albedo_gray, ir_return, gloss, cos_incidence: (H, W) arrays; cos_incidence is
            |cos| of the angle between the viewing ray and the surface normal.

    Returns:
        (H, W) float32 reflectance in [0, 1].
    """
    lobe = np.clip(cos_incidence, 0.0, 1.0) ** 8
    out = albedo_gray * ir_return * (1.0 - gloss + gloss * lobe)
    return np.where((gloss >= 0.3) & (cos_incidence > saturate_cos), 0.0, out).astype(np.float32)


def smooth_field(rng: np.random.Generator, hw: tuple[int, int], sigma_px: float) -> np.ndarray:
    """Gaussian random field of unit standard deviation, correlated over ``sigma_px``.

    Returns:
        (H, W) float32.
    """
    h, w = hw
    f = rng.standard_normal((h, w), dtype=np.float32)
    if sigma_px > 0:
        f = cv2.GaussianBlur(f, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)
    return f / max(float(f.std()), 1e-6)


def _uniform_field(rng, hw, sigma_px):
    # a smooth field mapped through a logistic approximation of the normal CDF:
    # marginally ~uniform in (0, 1), spatially coherent
    return 1.0 / (1.0 + np.exp(-1.702 * smooth_field(rng, hw, sigma_px)))


def kinect_noise(
    depth_m: np.ndarray,
    K: np.ndarray,
    rng: np.random.Generator,
    settings: KinectNoise = KinectNoise(),
    normals_cam: np.ndarray | None = None,
    ir_reflectance: np.ndarray | None = None,
) -> np.ndarray:
    """Simulate a Kinect v1 depth image from exact depth.

    Args:
        depth_m: (H, W) float32 exact z-depth in metres, 0 = no surface.
        K: (3, 3) intrinsics of the depth camera.
        rng: generator (seed it per frame for independent, reproducible noise).
        settings: model parameters.
        normals_cam: (H, W, 3) unit surface normals in the camera frame, for the
            grazing-angle dropout (skipped when None).
        ir_reflectance: (H, W) infrared reflectance in [0, 1] (albedo times the
            material's IR return), for the dark-surface dropout (skipped when None).

    Returns:
        (H, W) float32 noisy depth in metres, 0 = invalid.

    Long because it is one sequence of draws from ``rng`` in the order the sensor's
    effects apply; split, the order that every frame's noise depends on would be spread
    over functions.
    """
    depth_m = np.asarray(depth_m, np.float32)
    sizes = check_shape(depth_m, "H W", "depth_m")
    h, w = depth_m.shape
    if normals_cam is not None:
        check_shape(normals_cam, "H W 3", "normals_cam", sizes)
    if ir_reflectance is not None:
        check_shape(ir_reflectance, "H W", "ir_reflectance", sizes)
    s = settings
    px = w / 640.0  # pixel-sized settings are given at the Kinect's 640-pixel width
    fx = float(K[0, 0])
    fb = fx * s.baseline_m  # disparity (px) = fb / z

    # 1. lateral jitter of the whole image (visible at edges only)
    u = np.arange(w, dtype=np.float32)[None, :].repeat(h, 0)
    v = np.arange(h, dtype=np.float32)[:, None].repeat(w, 1)
    map_x = u + s.jitter_px * px * smooth_field(rng, (h, w), 3.0 * px)
    map_y = v + s.jitter_px * px * smooth_field(rng, (h, w), 3.0 * px)
    z = cv2.remap(depth_m, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    if normals_cam is not None:
        normals_cam = cv2.remap(
            np.ascontiguousarray(normals_cam, np.float32),
            map_x,
            map_y,
            cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_REPLICATE,
        )
    if ir_reflectance is not None:
        ir_reflectance = cv2.remap(
            np.ascontiguousarray(ir_reflectance, np.float32),
            map_x,
            map_y,
            cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_REPLICATE,
        )
    valid = z > 0
    zs = np.where(valid, z, np.float32(np.inf))

    # 2. projector shadows: u_p must increase strictly to the right of every lit pixel
    u_p = u - fb / zs
    right_min = np.minimum.accumulate(u_p[:, ::-1], axis=1)[:, ::-1]
    right_min = np.concatenate([right_min[:, 1:], np.full((h, 1), np.inf, np.float32)], 1)
    drop = right_min < u_p - s.shadow_tol_px * px
    grow = int(round(s.shadow_grow_px * px))
    if grow > 0:
        # the block matcher's window fails when part of it falls into the shadow
        drop = cv2.dilate(drop.astype(np.uint8), np.ones((1, 2 * grow + 1), np.uint8)).astype(bool)

    # 3a. pattern not matched at depth discontinuities
    band = int(round(s.edge_band_px * px))
    if s.edge_band_px > 0 and band > 0:
        k = 2 * band + 1
        kernel = np.ones((k, k), np.uint8)
        hi = cv2.dilate(z, kernel)
        lo = cv2.erode(np.where(valid, z, np.float32(1e6)), kernel)
        edge = (hi - lo) > s.edge_rel_jump * np.where(valid, z, 1.0)
        drop |= edge & (rng.random((h, w), dtype=np.float32) < s.edge_drop_prob)
    # 3b. probabilistic dropouts, decided against a coherent field
    p = np.zeros((h, w), np.float32)
    if normals_cam is not None:
        # cosine between the viewing ray and the normal
        x_n = (u - K[0, 2]) / fx
        y_n = (v - K[1, 2]) / K[1, 1]
        ray_norm = np.sqrt(x_n * x_n + y_n * y_n + 1)
        cos = np.abs(normals_cam[..., 0] * x_n + normals_cam[..., 1] * y_n + normals_cam[..., 2]) / ray_norm
        p = np.maximum(p, np.clip((s.grazing_cos - cos) / max(s.grazing_cos, 1e-6), 0, 1))
    if ir_reflectance is not None and s.dark_level > 0:
        # the returned IR falls off with distance squared
        signal = ir_reflectance / np.maximum(z, 0.3) ** 2
        p = np.maximum(p, np.clip(1.0 - signal / s.dark_level, 0, 1))
    if s.far_ramp_m > 0:
        p = np.maximum(p, np.clip((z - (s.max_range_m - s.far_ramp_m)) / s.far_ramp_m, 0, 1))
    drop |= _uniform_field(rng, (h, w), 2.0 * px) < p
    drop |= z > s.max_range_m
    drop |= z < s.min_range_m
    if s.blob_fraction > 0:
        blobs = smooth_field(rng, (h, w), 5.0 * px)
        drop |= blobs > np.quantile(blobs[::4, ::4], 1.0 - s.blob_fraction)

    # 4. disparity noise and 1/8-pixel quantisation
    disp = fb / zs
    scale = np.maximum(zs, 0.5) ** -s.sigma_disp_falloff  # Kinect: std falls as z^-1/4 (see above)
    disp = disp + s.sigma_disp_px * px * scale * rng.standard_normal((h, w), dtype=np.float32)
    if s.sigma_disp_smooth_px > 0:
        disp = disp + s.sigma_disp_smooth_px * px * scale * smooth_field(rng, (h, w), 4.0 * px)
    step = s.disparity_step_px * px  # same depth levels at any image width
    disp = np.round(disp / step) * step
    out = np.where(disp > 0, fb / np.maximum(disp, 1e-6), 0).astype(np.float32)
    if s.round_mm:
        out = np.round(out * 1000) / 1000
    out[drop | ~valid] = 0
    # 5. the sensor's invalid right border
    border = int(round(s.border_right_px * px))
    if border > 0:
        out[:, w - border :] = 0
    return out.astype(np.float32)
