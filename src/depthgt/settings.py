"""Every stage's settings, built and checked from the config: one frozen dataclass per
stage and one builder, :func:`settings_from_config`.

This module imports no torch (only the standard library, numpy, and yaml/jsonschema
inside :func:`check_config`): the Snakefile builds the settings when the workflow
starts, so that every section is checked before any job runs, and every job calls the
same builder on the config sections its rule passes to get its settings. Components
never see the config dict: they take the dataclass of their stage.

The field defaults of these dataclasses are the defaults of the config: a workflow run
and a library call with the same (empty) section get the same settings. The config
schema (``workflow/schemas/config.schema.yaml``) repeats some of them as ``default``
for Snakemake's validation; ``tests/test_settings.py`` checks that every one of those
equals the dataclass default.

Checks raise :class:`~depthgt.errors.ConfigError` naming the config key at fault
(``patches.size``, ``registration.refine_settings.iters``). Unknown keys are found by
:func:`check_keys`, the one place that does it.

>>> s = settings_from_config({"resize": 128, "patches": {"size": 64}})
>>> s.size_hw, s.patches.count, s.registration.method
((128, 128), 6, 'given')
"""

from __future__ import annotations

import dataclasses
import json
import re
import types
import typing
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any, TypeVar

import numpy as np

from depthgt import registry
from depthgt.errors import ConfigError

__all__ = [
    "SPLITS",
    "DEVICES",
    "ON_FAILURE",
    "REGISTRATION_METHODS",
    "REGISTRATION_PRESETS",
    "FrameSetSettings",
    "SplitSettings",
    "PatchSettings",
    "RenderSettings",
    "RefineSettings",
    "PretrainSettings",
    "EncoderSettings",
    "MatchingSettings",
    "TrainingSettings",
    "CheckSettings",
    "REGISTRATION_KEYS",
    "RegistrationSettings",
    "TrainSettings",
    "RDESettings",
    "EnhanceSettings",
    "EvaluationSettings",
    "SourceSettings",
    "Settings",
    "Stage",
    "STAGES",
    "stage_config",
    "stage_settings",
    "settings_from_config",
    "registration_settings",
    "check_keys",
    "build",
    "check_config",
    "check_scene_name",
    "check_workflow",
]

T = TypeVar("T")

SPLITS = ("train", "val", "test")
DEVICES = ("auto", "cpu", "cuda")
# What a frame set with failed neighbours becomes (registration.on_failure): rendered
# from the neighbours that did register, or excluded from the dataset. A set where
# fewer than min_ok_fraction of the neighbours registered is excluded either way.
ON_FAILURE = ("drop_neighbours", "exclude")
REGISTRATION_METHODS = ("given", "refine", "overfit")
RENDER_PLANES = ("fit", "normals", "none")  # render.plane

# Upper bounds on values that size memory (a typo such as patches.count: 60000 or
# resize: 25600 would otherwise be found by the kernel's OOM killer, hours into a run).
MAX_RESIZE = 4096
MAX_PATCH_COUNT = 1000
MAX_NEIGHBOURS = 32
MAX_COVERAGE_SPAN = 256  # frameset.coverage_span: 2 * span candidate frames are read and held at once
FRAMESET_SELECTIONS = ("window", "coverage")  # frameset.selection
MAX_CANDIDATES = 1 << 16
# frame sets one batch job builds (frameset.batch_size): a job holds one frame set at a
# time, but its time limit grows with the batch (the schema states the same maximum)
MAX_FRAMESET_BATCH = 1024
# patch pairs per training step (enhance.train.batch_size)
MAX_TRAIN_BATCH = 4096
LR_SCHEDULES = ("constant", "cosine")  # enhance.train.lr_schedule (TrainSettings)
MAX_INPUT_HOLES = 64  # enhance.train.input_holes: discs cut per training patch
MAX_INPUT_HOLE_PX = 64  # enhance.train.input_hole_max_px: their largest radius, pixels


def _fail(key: str, message: str) -> None:
    raise ConfigError(f"config key {key}: {message}")


def _require(ok: bool, key: str, message: str) -> None:
    if not ok:
        _fail(key, message)


# --------------------------------------------------------------------------- frame sets and splits


@dataclass(frozen=True)
class FrameSetSettings:
    """How frame sets are formed (config ``frameset``).

    Attributes:
        neighbours: neighbours on each side of the target (paper: 3).
        stride: frames between consecutive neighbours (paper: 2).
        target_step: a target every ``target_step`` frames.
        batch_size: frame sets one job builds in turn (a contiguous slice of one scene's
            targets, written to one shard): process start, imports and model loading are
            paid once per batch (docs/output-layout.md).
        selection: ``window`` (the paper's members only) or ``coverage``: the window as
            the core, plus up to ``coverage_views`` views from within
            +-``coverage_span`` frames chosen for the target's pixels the core leaves
            without GT (:mod:`depthgt.gt.coverage`); they fill only those pixels.
        coverage_span: frames on each side of the target a coverage view may come from.
        coverage_views: most views added per frame set.
        coverage_max_baseline_m: a candidate farther than this from the target camera
            (by the source's poses; with ``overfit``, by the poses of the chain through
            the core, :func:`depthgt.gt.coverage.chain_poses`) is not added.
        coverage_max_angle_deg: nor one whose viewing direction is turned further.
        coverage_min_fill_px: a view is added only when it would fill at least this
            many of the still-empty pixels. The span, views and these limits were
            checked on tuning data and kept (bench/README "The span, views and limits
            tuned": a wider span fills more on long recordings at some accuracy).
        coverage_mixed_margin_px, coverage_mixed_jump_rel: an added view's samples
            within ``coverage_mixed_margin_px`` pixels of a hole of its own depth or of a
            jump (the window's depth range above ``coverage_mixed_jump_rel`` times the
            depth) fill nothing: a sensor mixes fore- and background there, and nothing
            outvotes them where the core sees nothing
            (:func:`depthgt.gt.coverage.mixed_samples`; 1 px and 0.03 chosen on tuning
            data; margin 0: every sample fills, jump 0: holes only).
    """

    neighbours: int = 3
    stride: int = 2
    target_step: int = 1
    batch_size: int = 32
    selection: str = "window"
    coverage_span: int = 30
    coverage_views: int = 4
    coverage_max_baseline_m: float = 0.3
    coverage_max_angle_deg: float = 20.0
    coverage_min_fill_px: int = 50
    coverage_mixed_margin_px: int = 1
    coverage_mixed_jump_rel: float = 0.03

    def __post_init__(self):
        _require(
            1 <= self.batch_size <= MAX_FRAMESET_BATCH,
            "frameset.batch_size",
            f"must be in 1..{MAX_FRAMESET_BATCH}, got {self.batch_size}",
        )
        for key in ("neighbours", "stride", "target_step"):
            _require(getattr(self, key) >= 1, f"frameset.{key}", f"must be >= 1, got {getattr(self, key)}")
        _require(
            self.neighbours <= MAX_NEIGHBOURS,
            "frameset.neighbours",
            f"must be <= {MAX_NEIGHBOURS} (every member is held in memory at once), got {self.neighbours}",
        )
        _require(
            self.selection in FRAMESET_SELECTIONS,
            "frameset.selection",
            f"must be one of {FRAMESET_SELECTIONS}, got {self.selection!r}",
        )
        _require(
            1 <= self.coverage_span <= MAX_COVERAGE_SPAN,
            "frameset.coverage_span",
            f"must be in 1..{MAX_COVERAGE_SPAN} (the candidates are held in memory at once), got {self.coverage_span}",
        )
        _require(
            0 <= self.coverage_views <= MAX_NEIGHBOURS,
            "frameset.coverage_views",
            f"must be in 0..{MAX_NEIGHBOURS}, got {self.coverage_views}",
        )
        _require(
            self.coverage_max_baseline_m > 0,
            "frameset.coverage_max_baseline_m",
            f"must be > 0, got {self.coverage_max_baseline_m}",
        )
        _require(
            0 < self.coverage_max_angle_deg <= 180,
            "frameset.coverage_max_angle_deg",
            f"must be in (0, 180], got {self.coverage_max_angle_deg}",
        )
        _require(
            self.coverage_min_fill_px >= 1,
            "frameset.coverage_min_fill_px",
            f"must be >= 1, got {self.coverage_min_fill_px}",
        )
        _require(
            isinstance(self.coverage_mixed_margin_px, int) and 0 <= self.coverage_mixed_margin_px <= 16,
            "frameset.coverage_mixed_margin_px",
            f"must be an integer in 0..16, got {self.coverage_mixed_margin_px!r}",
        )
        _require(
            0 <= self.coverage_mixed_jump_rel <= 1,
            "frameset.coverage_mixed_jump_rel",
            f"must be in [0, 1], got {self.coverage_mixed_jump_rel}",
        )

    @property
    def offsets(self) -> list[int]:
        """Offsets of the members, target first: [0, -n*s, ..., -s, s, ..., n*s]."""
        k = np.arange(1, self.neighbours + 1) * self.stride
        return [0, *(-k[::-1]).tolist(), *k.tolist()]

    @property
    def reach(self) -> int:
        return self.neighbours * self.stride

    def targets(self, n_frames: int) -> range:
        """Candidate targets of a scene of ``n_frames`` frames (every member inside it).

        >>> list(FrameSetSettings(neighbours=1, stride=2, target_step=3).targets(10))
        [2, 5]
        """
        return range(self.reach, max(self.reach, n_frames - self.reach), self.target_step)

    def batches(self, n_frames: int) -> list[tuple[int, int]]:
        """(first, last) target of each batch of a scene, ``batch_size`` targets each.

        >>> FrameSetSettings(neighbours=1, stride=1, target_step=2, batch_size=2).batches(10)
        [(1, 3), (5, 7)]
        """
        t = self.targets(n_frames)
        return [(t[i], t[min(i + self.batch_size, len(t)) - 1]) for i in range(0, len(t), self.batch_size)]


@dataclass(frozen=True)
class SplitSettings:
    """Split assignment of ``split: auto`` sources (config ``split``).

    A source with ``split: train|val|test`` puts every frame set in that split. Scenes
    of ``auto`` sources are cut into blocks of ``block_frames`` consecutive frames;
    every ``round(1 / val_fraction)``-th block (with a phase drawn from the seed and the
    scene name) is validation, the rest training. A frame set whose members fall into
    blocks of different splits is skipped (``split_guard``), so no frame is shared.
    """

    val_fraction: float = 0.1
    block_frames: int = 50

    def __post_init__(self):
        _require(0.0 <= self.val_fraction < 1.0, "split.val_fraction", f"must be in [0, 1), got {self.val_fraction}")
        _require(self.block_frames >= 1, "split.block_frames", f"must be >= 1, got {self.block_frames}")


@dataclass(frozen=True)
class DatasetSettings:
    """Config ``dataset``: what the dataset assembly and the run's checks accept.

    Attributes:
        allow_empty: keep a dataset in which no frame set was built (by default the
            dataset job fails then, naming the reasons: a build that keeps nothing is
            an error, not a success).
        check_space: before the first job, refuse a run whose planned frame sets do
            not fit on the results file system (measured bytes per frame set x the
            frame sets still to build; :mod:`depthgt.space`); false: warn only.
    """

    allow_empty: bool = False
    check_space: bool = True


# --------------------------------------------------------------------------- patches


@dataclass(frozen=True)
class PatchSettings:
    """Patch crops and the missing-ratio filter (config ``patches``; paper Sec. 4.1).

    Attributes:
        count: crops drawn per frame (paper: 6).
        size: square patch side in pixels (paper: 128); at most ``resize``.
        max_missing: a pair is kept when its missing ratio is strictly below this.
        filter_on: which image's missing ratio decides ("gt", "input" or "both"; the
            paper does not say which).
        max_gt_sigma_m: GT pixels whose expected std (gt.exr channel ``S``, metres)
            exceeds this are left out of the GT patch and count as missing; None
            (default) keeps every GT pixel.
    """

    count: int = 6
    size: int = 128
    max_missing: float = 0.05
    filter_on: str = "gt"
    max_gt_sigma_m: float | None = None

    def __post_init__(self):
        _require(
            self.filter_on in ("gt", "input", "both"),
            "patches.filter_on",
            f"must be gt, input or both, got {self.filter_on!r}",
        )
        _require(
            1 <= self.count <= MAX_PATCH_COUNT, "patches.count", f"must be in [1, {MAX_PATCH_COUNT}], got {self.count}"
        )
        _require(self.size >= 8, "patches.size", f"must be >= 8 (the schema's bound), got {self.size}")
        _require(0.0 < self.max_missing <= 1.0, "patches.max_missing", f"must be in (0, 1], got {self.max_missing}")
        _require(
            self.max_gt_sigma_m is None or self.max_gt_sigma_m > 0,
            "patches.max_gt_sigma_m",
            f"must be null or > 0, got {self.max_gt_sigma_m}",
        )


# --------------------------------------------------------------------------- GT renderer


@dataclass(frozen=True)
class RenderSettings:
    """Settings of :func:`depthgt.gt.render.render_gt` (config ``render``; paper eq. 5
    with surface selection by geometry).

    The renderer reasons in inverse depth, where a disparity sensor's noise is about
    constant (its depth noise grows as z^2) and planes are affine in screen space.
    Every depth sample carries an expected standard deviation
    ``sigma_z = sqrt(noise_sigma_abs_m^2 + (noise_sigma_1m * z^2)^2)``, i.e.
    ``sigma_z / z^2`` in inverse depth.

    Defaults were chosen on the TUNING set of bench/bench_gt_protocol.py (synthetic
    ``room`` and ``varied`` scenes of seed 0, Kinect v1 profile) and are reported on its
    disjoint EVALUATION set (docs/gt-renderer.md, bench/README.md).

    Attributes:
        m: at most this many samples of the chosen surface per pixel, nearest to the
            sample position first (7 frames put ~34 samples within R = 1.25 px).
        radius_px: R, radius in output pixels of a pixel's neighbourhood and scale of
            the spatial weights exp(-d / R^2) (d squared pixel distance).
        noise_sigma_1m: sigma of one depth sample at 1 m in metres (the z^2 law). None:
            estimated from the depth images being fused
            (:func:`depthgt.gt.render.estimate_noise_sigma_1m`, done by
            :func:`depthgt.gt.render.cloud_in_target`), so that
            the tolerances follow the sensor at hand; :func:`~depthgt.gt.render.render_gt` called
            with bare points uses :data:`depthgt.gt.render.KINECT_SIGMA_1M`.
        noise_sigma_abs_m: floor of the per-sample sigma in metres (millimetre
            rounding of depth files, residual pose error).
        gap_sigmas: samples of a pixel sorted by inverse depth form one surface while
            consecutive samples differ by at most ``gap_sigmas`` times the std of their
            difference; a wider gap separates two surfaces. A gap criterion (not a band
            from the nearest sample) keeps a slanted or grazing surface, whose samples
            spread over a wide but densely filled depth range, in one piece.
        gap_slope_rel: the tolerance grows by this fraction of the inverse depth per
            pixel between the two samples: consecutive samples of a slanted surface
            differ by its slope times their distance, and a surface at 78 deg
            incidence (fx ~ 230 px) changes depth by ~2% per pixel. Matters where the
            noise is small (clean depth) and normals are unknown.
        min_frames: a surface hides the ones behind it only when samples of at least
            this many frames support it (a lone frame's outliers or misregistered
            samples do not punch into the GT; a thin pole that several frames see is
            kept). A pixel where no surface has that support takes the nearest one.
        edge_margin_px: a surface covers the sample position when its samples reach at
            least this far beyond it, measured opposite their centroid (the position
            is inside the sampled footprint, also for a pole 1-3 px wide), or when one
            of its samples lies within 0.05 px of it (the target's own sample). The front
            surface takes a pixel it covers; otherwise the surface behind does when it
            covers it; when neither does (a gap between the two), the one with the
            sample nearest to the position.
        edge_vote: where a surface's edge lies, with frame ids: each frame's reach is
            measured on its own samples, and the surface reaches as far as at least this
            share of its frames do (0.5: the median edge). A real sensor's edges jitter
            and fatten from frame to frame; the farthest frame (0: the union of the
            frames, the behaviour before) puts the foreground outside its edge. Chosen
            on the real tuning data (bench/bench_real.py: 7-Scenes leave-target-out
            8.49 -> 7.92 mm, TUM refined 6.85 -> 6.09 mm) and checked on the synthetic
            tuning set (unchanged within 0.01 mm), see bench/README.md.
        edge_vote_slack_px: added to each frame's reach: one frame's samples lie about
            1 px apart, so its farthest sample falls short of its edge by up to 1 px
            (half of it on average); without it the vote shrinks thin structures of
            clean depth (not tuned: half the sample spacing).
        ambiguous_px: a pixel where the front surface's edge passes within this of
            ``edge_margin_px`` and a surface lies behind it is ambiguous (its side
            cannot be decided): its sigma grows by half the depth step between the two
            surfaces, and with ``drop_ambiguous`` it is left empty.
        drop_ambiguous: leave ambiguous pixels empty (see ``ambiguous_px``).
        target_resolves_ambiguous: with the target's own depth fused, a pixel left
            undecided (ambiguous, or empty) where the target has its own sample takes
            the surface of that sample when at least ``min_frames`` frames support it.
            Off by default: it fills 1 % more of the 7-Scenes fixture (95.4 -> 96.5 %)
            but on the synthetic tuning set the pixels it adds are wrong about half the
            time (the target's own edges jitter): MAE where both have depth 2.06 -> 2.12 mm.
        extend_uncovered: a pixel not covered by the front surface with nothing behind
            it (the border of what any frame saw) keeps the front surface (True) or
            stays empty (False).
        min_points: pixels with fewer kept samples get no GT.
        plane: how the depth at the sample position is estimated from the kept
            samples: ``fit`` (weighted least-squares plane in inverse depth, with the
            samples' normals as a weak prior on its slope), ``normals`` (each sample
            moved along its own tangent plane, then averaged) or ``none`` (plain
            weighted average).
        slope_prior: weight (in px^2) of the normals' slope in the ``fit`` plane: the
            slope shrinks towards it where the samples' spread determines it poorly.
        min_cos_incidence, max_correction_rel: a sample's normal is not used when its
            |cos| with the viewing ray is below ``min_cos_incidence`` or its tangent
            plane changes depth by more than ``max_correction_rel`` within R.
        max_sigma_m: GT pixels whose expected std (the ``sigma`` output, metres) exceeds
            this get no GT (depth 0, sigma kept); None keeps all.
        min_frame_agreement: with the target's own depth fused (``target_frame``), a
            frame is left out when fewer than this share of its samples next to the
            target's samples agree with them (gap rule above): a misregistered
            neighbour. 0 disables the check. With ``agreement_tile_px`` the share is
            judged per tile of each frame (pooled over its 3x3 tile neighbourhood), so a
            frame that agrees on most of the image contributes where it agrees.
        agreement_edge_px: samples within this many px of a depth edge or a hole of
            the target are not compared (real sensors' edges move between frames by more
            than their noise); 0 compares them all.
        agreement_tile_px: size (px at the working resolution) of the square tiles the
            agreement is judged on; 0 judges whole frames.
        min_whole_frame_agreement: with tiles, a frame whose share over the whole image
            is below this is left out everywhere (a misregistered neighbour).
        min_depth_m: points at or nearer than this (metres) are ignored.
        leave_target_out_stride: the leave-target-out check of real data (frameset.json
            ``leave_target_out``: the neighbours fused alone against the target's raw
            depth) is rendered at every this-th pixel of every this-th row only. Each
            pixel's estimate depends on its own candidates alone, so those pixels hold
            the full render's values (to float rounding); the statistics are taken over a
            quarter of the pixels (2), which cuts the render's second pass by ~3/4
            (issue 20). 1 renders every pixel (bench/bench_real.py does). The GT is not
            affected.
    """

    m: int = 64
    radius_px: float = 1.25
    noise_sigma_1m: float | None = None
    noise_sigma_abs_m: float = 0.001
    gap_sigmas: float = 4.0
    gap_slope_rel: float = 0.02
    min_frames: int = 2
    edge_margin_px: float = -0.05
    edge_vote: float = 0.5
    edge_vote_slack_px: float = 0.5
    ambiguous_px: float = 0.4
    drop_ambiguous: bool = True
    target_resolves_ambiguous: bool = False
    extend_uncovered: bool = True
    min_points: int = 1
    plane: str = "fit"
    slope_prior: float = 0.01
    min_cos_incidence: float = 0.15
    max_correction_rel: float = 0.05
    max_sigma_m: float | None = None
    min_frame_agreement: float = 0.95
    agreement_edge_px: int = 2
    agreement_tile_px: int = 32
    min_whole_frame_agreement: float = 0.5
    min_depth_m: float = 1e-3
    leave_target_out_stride: int = 2

    def __post_init__(self) -> None:
        _require(
            self.leave_target_out_stride >= 1,
            "render.leave_target_out_stride",
            f"must be >= 1, got {self.leave_target_out_stride}",
        )
        _require(self.m >= 1, "render.m", f"must be >= 1, got {self.m}")
        _require(self.radius_px > 0, "render.radius_px", f"must be > 0, got {self.radius_px}")
        _require(
            self.noise_sigma_1m is None or self.noise_sigma_1m > 0,
            "render.noise_sigma_1m",
            f"must be null or > 0, got {self.noise_sigma_1m}",
        )
        _require(self.noise_sigma_abs_m >= 0, "render.noise_sigma_abs_m", f"must be >= 0, got {self.noise_sigma_abs_m}")
        _require(self.gap_sigmas > 0, "render.gap_sigmas", f"must be > 0, got {self.gap_sigmas}")
        _require(self.gap_slope_rel >= 0, "render.gap_slope_rel", f"must be >= 0, got {self.gap_slope_rel}")
        _require(self.min_frames >= 1, "render.min_frames", f"must be >= 1, got {self.min_frames}")
        _require(self.min_points >= 1, "render.min_points", f"must be >= 1, got {self.min_points}")
        _require(0.0 <= self.edge_vote <= 1.0, "render.edge_vote", f"must be in [0, 1], got {self.edge_vote}")
        _require(
            self.edge_vote_slack_px >= 0, "render.edge_vote_slack_px", f"must be >= 0, got {self.edge_vote_slack_px}"
        )
        _require(self.ambiguous_px >= 0, "render.ambiguous_px", f"must be >= 0, got {self.ambiguous_px}")
        _require(self.slope_prior >= 0, "render.slope_prior", f"must be >= 0, got {self.slope_prior}")
        _require(
            self.plane in RENDER_PLANES,
            "render.plane",
            f"must be one of {', '.join(RENDER_PLANES)}, got {self.plane!r}",
        )
        _require(
            0.0 <= self.min_frame_agreement <= 1.0,
            "render.min_frame_agreement",
            f"must be in [0, 1], got {self.min_frame_agreement}",
        )
        _require(
            0.0 <= self.min_whole_frame_agreement <= 1.0,
            "render.min_whole_frame_agreement",
            f"must be in [0, 1], got {self.min_whole_frame_agreement}",
        )
        _require(
            isinstance(self.agreement_edge_px, int) and self.agreement_edge_px >= 0,
            "render.agreement_edge_px",
            f"must be an integer >= 0, got {self.agreement_edge_px!r}",
        )
        _require(
            isinstance(self.agreement_tile_px, int) and self.agreement_tile_px >= 0,
            "render.agreement_tile_px",
            f"must be an integer >= 0, got {self.agreement_tile_px!r}",
        )
        _require(
            self.max_sigma_m is None or self.max_sigma_m > 0,
            "render.max_sigma_m",
            f"must be null or > 0, got {self.max_sigma_m}",
        )
        _require(
            0 < self.min_cos_incidence < 1,
            "render.min_cos_incidence",
            f"must be in (0, 1), got {self.min_cos_incidence}",
        )
        _require(
            self.max_correction_rel > 0, "render.max_correction_rel", f"must be > 0, got {self.max_correction_rel}"
        )
        _require(self.min_depth_m > 0, "render.min_depth_m", f"must be > 0, got {self.min_depth_m}")


# --------------------------------------------------------------------------- registration


@dataclass(frozen=True)
class RefineSettings:
    """Settings of the joint SE(3) refinement (:func:`depthgt.registration.refine.refine_poses`).

    Attributes:
        scales: image downscale factors, coarse to fine (4 -> 64x64 for 256x256 input).
        iters: LM iterations per scale.
        pairs: "all" (every ordered pair, eq. 4), "target" (target-neighbour only) or
            "adjacent" (target pairs plus pairs of frames next to each other in the set).
        point_stride: source pixel stride per scale (1 = every valid pixel).
        geo_scale_m: robust scale of point-to-plane residuals (metres), per scale: wide
            at coarse scales so that large initial errors still pull with full weight.
        photo_scale: robust scale of intensity residuals (intensity in [0, 1]).
        photo_weight: weight of the photometric term relative to the geometric one
            (0 disables it, e.g. for sensors whose colour is not registered to depth).
        robust: "huber" or "cauchy".
        max_dist_m: association gate for point-to-plane and depth differences (metres),
            per scale.
        damping: initial Levenberg-Marquardt damping (relative to the diagonal).
        geo_ref_depth_m: beyond this depth (metres) the robust scale and the gate of
            the point-to-plane residuals grow as (z / geo_ref_depth_m)^2, like the depth
            noise and quantisation of disparity sensors; 0 keeps them constant.
    """

    scales: tuple[int, ...] = (4, 2, 1)
    iters: tuple[int, ...] = (10, 8, 6)
    pairs: str = "all"
    point_stride: tuple[int, ...] = (1, 1, 2)
    geo_scale_m: tuple[float, ...] = (0.02, 0.01, 0.005)
    photo_scale: float = 0.03
    photo_weight: float = 0.3
    robust: str = "huber"
    max_dist_m: tuple[float, ...] = (0.10, 0.05, 0.03)
    damping: float = 1e-4
    geo_ref_depth_m: float = 0.0

    def __post_init__(self):
        where = "registration.refine_settings"
        _require(self.geo_ref_depth_m >= 0, f"{where}.geo_ref_depth_m", f"must be >= 0, got {self.geo_ref_depth_m}")
        n = len(self.scales)
        _require(
            len(self.iters) == len(self.point_stride) == len(self.max_dist_m) == len(self.geo_scale_m) == n,
            where,
            "scales, iters, point_stride, max_dist_m and geo_scale_m need the same length",
        )
        _require(
            self.pairs in ("all", "target", "adjacent"),
            f"{where}.pairs",
            f"must be all|target|adjacent, got {self.pairs!r}",
        )
        _require(self.robust in ("huber", "cauchy"), f"{where}.robust", f"must be huber|cauchy, got {self.robust!r}")


@dataclass(frozen=True)
class PretrainSettings:
    """Stream-only pretraining of the registration encoder (config ``registration.pretrain``).

    Attributes:
        framesets: frame sets of the train split used (0 = random initialisation).
        epochs: passes over them (one Adam step per frame set).
    """

    framesets: int = 16
    epochs: int = 1

    def __post_init__(self):
        _require(self.framesets >= 0, "registration.pretrain.framesets", f"must be >= 0, got {self.framesets}")
        _require(self.epochs >= 1, "registration.pretrain.epochs", f"must be >= 1, got {self.epochs}")


@dataclass(frozen=True)
class EncoderSettings:
    """The overfit registration's RGB encoder (config keys ``registration.n_blocks``,
    ``channels``, ``feat_dim``, ``precision``).

    Attributes:
        n_blocks: ResNet-18 BasicBlocks at full resolution; channels: their width;
            feat_dim: the dimension of the output features.
        precision: of the encoder's convolutions, "fp32", "bf16" (autocast; the
            features are normalised, matched and aligned in float32/64) or "auto" (bf16
            on CUDA devices that support it and on CPUs with native bf16 instructions,
            AVX512-BF16 or AMX; else fp32). On CPU the encoder runs channels-last.
    """

    n_blocks: int = 2
    channels: int = 64
    feat_dim: int = 32
    precision: str = "fp32"

    def __post_init__(self):
        for key in ("n_blocks", "channels", "feat_dim"):
            _require(getattr(self, key) >= 1, f"registration.{key}", f"must be >= 1, got {getattr(self, key)}")
        _require(
            self.precision in ("auto", "fp32", "bf16"),
            "registration.precision",
            f"must be auto, fp32 or bf16, got {self.precision!r}",
        )


@dataclass(frozen=True)
class MatchingSettings:
    """Correspondences and their alignment (config keys ``registration.n_candidates``,
    ``top_k``, ``knn_block``, ``n_subsets``, ``subset_fraction``).

    Attributes:
        n_candidates: random valid pixels per frame; top_k: matches per direction;
            knn_block: entries of a block of the similarity matrix at most.
        n_subsets: random subsets of ``subset_fraction`` of the matches, each aligned by
            weighted Procrustes (the one of the lowest weighted residual is kept).
    """

    n_candidates: int = 2048
    top_k: int = 200
    knn_block: int = 1 << 25
    n_subsets: int = 10
    subset_fraction: float = 0.2

    def __post_init__(self):
        _require(self.top_k >= 3, "registration.top_k", f"must be >= 3, got {self.top_k}")
        _require(self.n_candidates >= 3, "registration.n_candidates", f"must be >= 3, got {self.n_candidates}")
        _require(
            self.n_candidates <= MAX_CANDIDATES,
            "registration.n_candidates",
            f"must be <= {MAX_CANDIDATES} (matching is quadratic in it), got {self.n_candidates}",
        )
        for key in ("n_subsets", "knn_block"):
            _require(getattr(self, key) >= 1, f"registration.{key}", f"must be >= 1, got {getattr(self, key)}")
        _require(
            0.0 < self.subset_fraction <= 1.0,
            "registration.subset_fraction",
            f"must be in (0, 1], got {self.subset_fraction}",
        )


@dataclass(frozen=True)
class TrainingSettings:
    """The overfit training of the encoder on one frame set (config keys
    ``registration.lr``, ``iterations``, ``weight_decay``, ``w_depth``, ``w_photo``,
    ``w_corr``, ``pairs``, ``render_radius_px``, ``render_max_points``,
    ``render_stride``, ``pose_from``).

    Attributes:
        lr, iterations, weight_decay: Adam's (``iterations`` = the paper's epochs on a
            single batch).
        w_depth, w_photo, w_corr: loss weights (per metre, -, per m^2).
        pairs: "all" (every pair, eq. 4) or "target".
        render_radius_px, render_max_points, render_stride: the soft splatting of the
            render losses: radius (pixels), points per pixel, source pixel stride.
        pose_from: the poses of the "last" or the "best" (lowest loss) iteration.
    """

    lr: float = 1e-4
    iterations: int = 30
    weight_decay: float = 0.0
    w_depth: float = 1.0
    w_photo: float = 1.0
    w_corr: float = 0.1
    pairs: str = "all"
    render_radius_px: float = 2.0
    render_max_points: int = 16
    render_stride: int = 1
    pose_from: str = "last"

    def __post_init__(self):
        _require(self.iterations >= 0, "registration.iterations", f"must be >= 0, got {self.iterations}")
        _require(
            self.pairs in ("all", "target"), "registration.pairs", f"must be 'all' or 'target', got {self.pairs!r}"
        )
        _require(
            self.pose_from in ("last", "best"),
            "registration.pose_from",
            f"must be 'last' or 'best', got {self.pose_from!r}",
        )
        for key in ("render_max_points", "render_stride"):
            _require(getattr(self, key) >= 1, f"registration.{key}", f"must be >= 1, got {getattr(self, key)}")


@dataclass(frozen=True)
class CheckSettings:
    """The failure checks of a registered frame set, every method's
    (:mod:`depthgt.registration.checks`; config keys ``registration.<field>``).

    A neighbour fails with fewer than ``min_confident`` target-pair matches of weight >=
    ``confident_weight``; a final motion above ``max_translation_m`` /
    ``max_rotation_deg``; a correction of the source's pose (method ``refine``) beyond
    ``max_correction_m`` / ``max_correction_deg``; an inlier fraction below
    ``min_inlier_fraction``; an information matrix condition number above
    ``max_condition`` (no texture/geometry); a median point-to-plane residual in the
    target above ``max_residual_m`` (settled off the surface) that the sensor's noise
    does not explain: also above ``max_residual_sigmas`` in units of the depth noise the
    frame set shows (median of |residual| / (sigma_1m z^2), sigma_1m estimated from the
    set's depth as the renderer does; aligned neighbours sit at 0.4-0.8 on both synthetic
    sensor profiles, up to 1.06 on the 7-Scenes fixture; 0 = the fixed metric bound
    alone). The set fails when fewer than ``min_ok_fraction`` of its neighbours are ok,
    or (the overfit registration without refinement) when the training loss does not
    decrease.
    """

    confident_weight: float = 0.1
    min_confident: int = 20
    max_translation_m: float = 0.3
    max_rotation_deg: float = 20.0
    min_inlier_fraction: float = 0.3
    max_condition: float = 1e5
    max_residual_m: float = 0.008
    max_residual_sigmas: float = 1.0
    max_correction_m: float = 0.05
    max_correction_deg: float = 3.0
    min_ok_fraction: float = 0.5

    def __post_init__(self):
        _require(
            self.max_correction_m > 0, "registration.max_correction_m", f"must be > 0, got {self.max_correction_m}"
        )
        _require(
            self.max_correction_deg > 0,
            "registration.max_correction_deg",
            f"must be > 0, got {self.max_correction_deg}",
        )
        _require(
            self.max_residual_sigmas >= 0,
            "registration.max_residual_sigmas",
            f"must be >= 0, got {self.max_residual_sigmas}",
        )
        _require(
            0.0 <= self.min_ok_fraction <= 1.0,
            "registration.min_ok_fraction",
            f"must be in [0, 1], got {self.min_ok_fraction}",
        )


#: The parts of :class:`RegistrationSettings` whose fields are flat keys of the config's
#: ``registration`` section.
_REGISTRATION_PARTS = {
    "encoder": EncoderSettings,
    "matching": MatchingSettings,
    "training": TrainingSettings,
    "checks": CheckSettings,
}

#: The keys of the config's ``registration`` section, in the order frameset.json and the
#: dataset card record them.
REGISTRATION_KEYS = (
    "method",
    "on_failure",
    "preset",
    "pretrain",
    "n_blocks",
    "channels",
    "feat_dim",
    "n_candidates",
    "top_k",
    "knn_block",
    "n_subsets",
    "subset_fraction",
    "lr",
    "iterations",
    "weight_decay",
    "w_depth",
    "w_photo",
    "w_corr",
    "pairs",
    "render_radius_px",
    "render_max_points",
    "render_stride",
    "pose_from",
    "chaining",
    "refine",
    "refine_settings",
    "confident_weight",
    "min_confident",
    "max_translation_m",
    "max_rotation_deg",
    "min_inlier_fraction",
    "max_condition",
    "max_residual_m",
    "max_residual_sigmas",
    "max_correction_m",
    "photometric",
    "max_correction_deg",
    "min_ok_fraction",
    "num_threads",
    "precision",
)


@dataclass(frozen=True)
class RegistrationSettings:
    """How frame sets are aligned (config ``registration``, one flat section; defaults:
    the paper / R&R values; presets in :data:`REGISTRATION_PRESETS`), held as the parts
    each step reads: ``encoder`` (:class:`EncoderSettings`), ``matching``
    (:class:`MatchingSettings`), ``training`` (:class:`TrainingSettings`), ``checks``
    (:class:`CheckSettings`). Build it from config keys with :meth:`from_keys` (or
    :func:`registration_settings`, which applies the preset); :meth:`as_config` gives the
    section back.

    Attributes:
        method: "given" (the source's poses), "refine" (the source's poses refined on the
            frame set by the joint SE(3) refinement, ``refine_settings``; a correction
            beyond the checks' ``max_correction_m`` / ``max_correction_deg`` fails the
            neighbour) or "overfit" (the paper's registration).
        on_failure: :data:`ON_FAILURE`.
        preset: the preset the values came from (None: the field defaults).
        pretrain: :class:`PretrainSettings`.
        chaining: (overfit, beyond the paper) compose far neighbours through nearer ones
            when that aligns better.
        refine: (overfit, beyond the paper) refine the poses with ``refine_settings``.
        photometric: the refinement's photometric term "on", "off" or "auto" (on only
            where the source's colour is the depth's camera at the depth's instant,
            ``Scene.colour_matches_depth``).
        num_threads: torch threads of the overfit registration (None: torch's default).

    Every field is checked whatever the method.
    """

    method: str = "given"
    on_failure: str = "drop_neighbours"
    preset: str | None = None
    pretrain: PretrainSettings = PretrainSettings()
    encoder: EncoderSettings = EncoderSettings()
    matching: MatchingSettings = MatchingSettings()
    training: TrainingSettings = TrainingSettings()
    checks: CheckSettings = CheckSettings()
    chaining: bool = True
    refine: bool = True
    refine_settings: RefineSettings = RefineSettings()
    photometric: str = "auto"
    num_threads: int | None = None

    @property
    def uses_source_poses(self) -> bool:
        """Whether the frame sets need the source's poses (``given``, ``refine``)."""
        return self.method in ("given", "refine")

    @classmethod
    def from_keys(cls, keys: Mapping[str, Any], where: str = "registration") -> RegistrationSettings:
        """The settings of the flat config keys ``keys`` (:data:`REGISTRATION_KEYS`; a
        key not given takes its default, no preset is applied); an unknown key or a bad
        value raises :class:`ConfigError` naming ``where.key``.

        >>> RegistrationSettings.from_keys({"top_k": 50, "max_residual_m": 0.01}).matching.top_k
        50
        """
        if not isinstance(keys, Mapping):
            _fail(where, f"must be a mapping, got {type(keys).__name__} {keys!r}")
        check_keys(keys, REGISTRATION_KEYS, where)
        parts, top = {}, dict(keys)
        for name, part in _REGISTRATION_PARTS.items():
            names = [f.name for f in dataclasses.fields(part)]
            parts[name] = build(part, {k: top.pop(k) for k in names if k in top}, where)
        return build(cls, {**top, **parts}, where)

    def with_keys(self, **keys: Any) -> RegistrationSettings:
        """A copy with the flat config keys ``keys`` changed (checked as in :meth:`from_keys`).

        >>> RegistrationSettings().with_keys(max_correction_m=0.01).checks.max_correction_m
        0.01
        """
        return RegistrationSettings.from_keys({**self.as_config(), **keys})

    def as_config(self) -> dict[str, Any]:
        """The flat config section these settings are (:data:`REGISTRATION_KEYS`, in
        their order; ``pretrain`` and ``refine_settings`` as nested dicts)."""
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in _REGISTRATION_PARTS}
        for name in _REGISTRATION_PARTS:
            values.update(asdict(getattr(self, name)))
        return {k: asdict(values[k]) if dataclasses.is_dataclass(values[k]) else values[k] for k in REGISTRATION_KEYS}

    def __post_init__(self):
        _require(
            self.method in REGISTRATION_METHODS,
            "registration.method",
            f"must be {' or '.join(REGISTRATION_METHODS)}, got {self.method!r}",
        )
        _require(
            self.on_failure in ON_FAILURE,
            "registration.on_failure",
            f"must be one of {', '.join(ON_FAILURE)}, got {self.on_failure!r}",
        )
        _require(
            self.preset is None or self.preset in REGISTRATION_PRESETS,
            "registration.preset",
            f"unknown preset {self.preset!r}; known: {', '.join(REGISTRATION_PRESETS)}",
        )
        _require(
            self.photometric in ("auto", "on", "off"),
            "registration.photometric",
            f"must be auto, on or off, got {self.photometric!r}",
        )
        _require(
            self.num_threads is None or self.num_threads >= 1,
            "registration.num_threads",
            f"must be >= 1 or null, got {self.num_threads}",
        )


# Presets of the overfit registration, as config values (nested sections merge with
# the user's: registration: {preset: fast, refine_settings: {iters: [4, 4, 2]}} keeps
# the preset's other refinement values).
REGISTRATION_PRESETS: dict[str, dict[str, Any]] = {
    # The paper: R&R encoder and matching, Adam 1e-4 for 30 iterations, plus refinement;
    # bf16 convolutions where the hardware has them (2.3x faster encoder on AVX512-BF16).
    "paper": {"precision": "auto"},
    # The paper without the beyond-the-paper steps (for the with/without comparison).
    "paper_only": {"chaining": False, "refine": False, "precision": "auto"},
    # CPU-friendly: one pass of a small encoder (pretrained weights when given) for the
    # correspondence initialisation, no overfit iterations, then chaining and a
    # sparser refinement, its point-to-plane scale growing as z^2 beyond 1.5 m and a
    # stronger photometric term (chosen on bench_gt_protocol.py's tuning sets: pose
    # error vs the source's poses and GT error; bench/README.md).
    "fast": {
        "n_blocks": 1,
        "channels": 32,
        "n_candidates": 1024,
        "iterations": 0,
        "render_stride": 2,
        "refine_settings": {
            "scales": (4, 2, 1),
            "iters": (8, 5, 3),
            "point_stride": (1, 2, 4),
            "geo_ref_depth_m": 1.5,
            "photo_weight": 1.0,
        },
    },
}


def registration_settings(
    section: Mapping[str, Any] | None = None, where: str = "registration"
) -> RegistrationSettings:
    """:class:`RegistrationSettings` of a ``registration`` config section: the preset's
    values (default ``paper``), overridden by the section's other keys.

    >>> registration_settings({"preset": "fast", "iterations": 2}).encoder.channels
    32
    """
    values = dict(section or {})
    preset = values.pop("preset", "paper")
    if preset not in REGISTRATION_PRESETS:
        _fail(f"{where}.preset", f"unknown preset {preset!r}; known: {', '.join(REGISTRATION_PRESETS)}")
    merged = dict(REGISTRATION_PRESETS[preset])
    for key, value in values.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = {**merged[key], **value}
        else:
            merged[key] = value
    return RegistrationSettings.from_keys({**merged, "preset": preset}, where)


# --------------------------------------------------------------------------- enhancement


@dataclass(frozen=True)
class TrainSettings:
    """Settings of one training run (:func:`depthgt.enhance.train.train`).

    Attributes:
        model: builder name (a learned method's ``builder`` in :mod:`depthgt.registry`).
        model_params: keyword arguments of the builder (``lapden``: ``preset`` and
            LapDENConfig overrides).
        loss_params: keyword arguments of the model's loss (``lapden``: LossConfig fields).
        epochs: number of epochs; batch_size: patches per step; lr: Adam learning rate
            (defaults 6, 8, 1e-3: the config's ``enhance.train``, docs/configuration.md).
        lr_schedule: ``constant`` (``lr`` at every step) or ``cosine`` (``lr`` at the first
            step, decaying along half a cosine to 0 after the last step of ``epochs``:
            :func:`depthgt.enhance.train.learning_rate`). With ``cosine`` the epochs are part
            of the run's identity (a run cannot be extended by more epochs).
        weight_decay: Adam weight decay.
        seed: seeds the initial weights, the shuffling and the flips.
        flips: random horizontal and vertical flips (intrinsics flipped too).
        input_holes: holes cut into each training patch's input depth (0: none, the
            paper's training): discs of radius uniform in ``input_hole_min_px`` ..
            ``input_hole_max_px`` pixels at uniform centres, the GT left as it is, so the
            network is taught to fill hole interiors far from any input depth, which the
            sensor's own holes rarely give a target for
            (:func:`depthgt.enhance.train.cut_input_holes`). Drawn from the epoch's
            generator after the flips: a resumed run cuts the same holes.
        max_batches_per_epoch: cap on training steps per epoch (None: all).
        device: "auto" (CUDA when available), "cpu" or "cuda".
        progress: show a tqdm bar per epoch.
    """

    model: str = "lapden"
    model_params: dict = field(default_factory=lambda: {"preset": "default"})
    loss_params: dict = field(default_factory=dict)
    epochs: int = 6
    batch_size: int = 8
    lr: float = 1e-3
    lr_schedule: str = "constant"
    weight_decay: float = 0.0
    seed: int = 0
    flips: bool = True
    input_holes: int = 0
    input_hole_min_px: int = 4
    input_hole_max_px: int = 16
    max_batches_per_epoch: int | None = None
    device: str = "auto"
    progress: bool = True

    def __post_init__(self):
        builders = registry.builders()
        _require(self.model in builders, "train.model", f"unknown model {self.model!r}; known: {sorted(builders)}")
        for key in ("epochs", "batch_size"):
            _require(int(getattr(self, key)) >= 1, f"train.{key}", f"must be >= 1, got {getattr(self, key)}")
        _require(
            self.batch_size <= MAX_TRAIN_BATCH,
            "train.batch_size",
            f"must be <= {MAX_TRAIN_BATCH}, got {self.batch_size}",
        )
        _require(self.lr > 0, "train.lr", f"must be > 0, got {self.lr}")
        _require(
            self.lr_schedule in LR_SCHEDULES,
            "train.lr_schedule",
            f"must be one of {', '.join(LR_SCHEDULES)}, got {self.lr_schedule!r}",
        )
        _require(self.device in DEVICES, "train.device", f"must be auto, cpu or cuda, got {self.device!r}")
        _require(
            isinstance(self.input_holes, int) and 0 <= self.input_holes <= MAX_INPUT_HOLES,
            "train.input_holes",
            f"must be an integer in 0..{MAX_INPUT_HOLES}, got {self.input_holes!r}",
        )
        _require(
            isinstance(self.input_hole_min_px, int)
            and isinstance(self.input_hole_max_px, int)
            and 1 <= self.input_hole_min_px <= self.input_hole_max_px <= MAX_INPUT_HOLE_PX,
            "train.input_hole_min_px/input_hole_max_px",
            f"must be integers with 1 <= min <= max <= {MAX_INPUT_HOLE_PX}, got {self.input_hole_min_px!r}, "
            f"{self.input_hole_max_px!r}",
        )
        _require(
            self.max_batches_per_epoch is None or self.max_batches_per_epoch >= 1,
            "train.max_batches_per_epoch",
            f"must be >= 1 or null, got {self.max_batches_per_epoch}",
        )
        _require(
            isinstance(self.model_params, Mapping) and isinstance(self.loss_params, Mapping),
            "train.model_params/loss_params",
            "must be mappings",
        )

    def identity(self) -> dict:
        """The settings that define the result (a resumed run must match them)."""
        d = asdict(self)
        for key in ("progress", "device"):
            d.pop(key)
        if self.lr_schedule == "constant":
            # a constant-rate run is the same run whatever its length (it can be extended);
            # the key is left out so that checkpoints from before the schedule existed resume
            del d["epochs"], d["lr_schedule"]
        if self.input_holes == 0:
            # no holes cut: the radii do not matter, and checkpoints from before the option resume
            del d["input_holes"], d["input_hole_min_px"], d["input_hole_max_px"]
        return json.loads(json.dumps(d))


@dataclass(frozen=True)
class RDESettings:
    """The global reconstruction behind the RDE GT (config ``enhance.rde``; :mod:`depthgt.gt.rde`).

    Attributes:
        voxel_m: voxel edge in metres.
        trunc_voxels: truncation distance in voxels (trunc_m = voxel_m * trunc_voxels).
        frame_step: fuse every N-th frame of the stream (1: all).
        max_depth_m: depth beyond this is ignored (fusion and ray range).
        max_voxels: refuse volumes larger than this (memory guard: two float32 grids).
        backend: ``torch`` (built in), ``open3d`` or ``auto`` (Open3D when importable, else torch).
        max_missing: RDE patch pairs are kept when the RDE GT crop misses less than this.
    """

    voxel_m: float = 0.02
    trunc_voxels: float = 4.0
    frame_step: int = 2
    max_depth_m: float = 8.0
    max_voxels: int = 48_000_000
    backend: str = "torch"
    max_missing: float = 0.05

    def __post_init__(self):
        _require(
            self.voxel_m > 0 and self.trunc_voxels >= 1 and self.max_depth_m > 0,
            "enhance.rde",
            f"voxel_m and max_depth_m must be > 0 and trunc_voxels >= 1, got {self.voxel_m}, {self.max_depth_m}, "
            f"{self.trunc_voxels}",
        )
        _require(
            self.frame_step >= 1 and self.max_voxels >= 1,
            "enhance.rde",
            f"frame_step and max_voxels must be >= 1, got {self.frame_step}, {self.max_voxels}",
        )
        _require(
            self.backend in ("auto", "open3d", "torch"),
            "enhance.rde.backend",
            f"must be auto, open3d or torch, got {self.backend!r}",
        )
        _require(0 < self.max_missing <= 1, "enhance.rde.max_missing", f"must be in (0, 1], got {self.max_missing}")

    @property
    def trunc_m(self) -> float:
        return self.voxel_m * self.trunc_voxels


@dataclass(frozen=True)
class EnhanceSettings:
    """Config ``enhance``: the resolved training settings of every trainable model of
    the registry (``enhance.train`` overridden by ``enhance.models[settings_key]``) and
    the RDE reconstruction."""

    models: dict[str, TrainSettings] = field(default_factory=dict)
    rde: RDESettings = RDESettings()


def _enhance_settings(section: Mapping[str, Any] | None, seed: int, device: str) -> EnhanceSettings:
    section = dict(section or {})
    check_keys(section, ("train", "models", "rde"), "enhance")
    shared = dict(section.get("train") or {})
    per_model = dict(section.get("models") or {})
    trainable = registry.learned()
    own_keys = sorted({m.settings_key for m in trainable.values()})
    check_keys(per_model, own_keys, "enhance.models")
    # the shared section on its own: a bad value there is named there, even where every
    # model's entry overrides it; checks across keys ("a/b") are left to the merged entries,
    # whose other key may come from the model's own entry
    try:
        _train_settings({"seed": seed, "device": device, "progress": False, **shared}, "enhance.train")
    except ConfigError as err:
        if "/" not in str(err).removeprefix("config key ").split(":", 1)[0]:
            raise
    models = {}
    for name, spec in trainable.items():
        entry = dict(per_model.get(spec.settings_key) or {})
        if entry.get("model", spec.builder) != spec.builder:
            _fail(
                f"enhance.models.{spec.settings_key}.model",
                f"must be {spec.builder!r} (the registry's builder), got {entry['model']!r}",
            )
        values = {
            "seed": seed,
            "device": device,
            "progress": False,
            "model_params": dict(spec.model_params),
            **shared,
            "model": spec.builder,
            **entry,
        }
        where = f"enhance.models.{spec.settings_key}" if spec.settings_key in per_model else "enhance.train"
        models[name] = _train_settings(values, where)
    return EnhanceSettings(models=models, rde=build(RDESettings, section.get("rde"), "enhance.rde"))


def _train_settings(values: Mapping[str, Any], where: str) -> TrainSettings:
    """:class:`TrainSettings` whose own checks (which name ``train.KEY``) name ``where.KEY``."""
    try:
        return build(TrainSettings, values, where)
    except ConfigError as err:
        msg = str(err)
        if msg.startswith("config key train."):
            raise ConfigError(msg.replace("config key train.", f"config key {where}.", 1)) from None
        raise


@dataclass(frozen=True)
class EvaluationSettings:
    """Config ``evaluation``.

    Attributes:
        split: the frame sets evaluated.
        methods: names of the registry's methods (:mod:`depthgt.registry`), evaluated
            and tabulated.
        figure_frames_per_scene: rows of the comparison figure per scene.
        rde_synthetic_test: build the RDE GT (a TSDF per scene) also for synthetic scenes
            of sources whose split is the evaluated one. Off by default: no method
            needs it (RDE trains on the train/val scenes; Table 2's TSDF reference is
            built for real scenes only); it adds those frames to Table 1 and the
            GT-quality table at ~40 CPU s per 25 frame sets.
    """

    split: str = "test"
    methods: tuple[str, ...] = tuple(registry.METHODS)
    figure_frames_per_scene: int = 2
    rde_synthetic_test: bool = False

    def __post_init__(self):
        _require(self.split in SPLITS, "evaluation.split", f"must be one of {', '.join(SPLITS)}, got {self.split!r}")
        unknown = [m for m in self.methods if m not in registry.METHODS]
        _require(
            not unknown, "evaluation.methods", f"unknown method(s) {unknown}; known: {', '.join(registry.METHODS)}"
        )
        _require(
            len(set(self.methods)) == len(self.methods), "evaluation.methods", f"duplicates in {list(self.methods)}"
        )
        _require(len(self.methods) >= 1, "evaluation.methods", "needs at least one method")
        _require(
            self.figure_frames_per_scene >= 1,
            "evaluation.figure_frames_per_scene",
            f"must be >= 1, got {self.figure_frames_per_scene}",
        )

    @property
    def models(self) -> list[str]:
        """The learned methods among :attr:`methods` (trained by the default target)."""
        return [m for m in self.methods if registry.METHODS[m].kind == "learned"]


# --------------------------------------------------------------------------- sources


_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


def check_scene_name(scene: str, where: str) -> None:
    """A scene name must be usable as one path component."""
    if not isinstance(scene, str) or scene in ("", ".", "..") or "/" in scene:
        _fail(where, f"scene name {scene!r} cannot be a path component; name the sequence folder (or use scenes: all)")


@dataclass(frozen=True)
class SourceSettings:
    """One entry of config ``sources``: an RGB-D source of the adapter ``kind``.

    ``colour_matches_depth``: ``auto`` (the kind's, :data:`depthgt.sources.base.KINDS`:
    synthetic only), ``true`` or ``false``: whether the source's colour is taken by the
    depth's camera at the depth's instant, which decides ``registration.photometric:
    auto`` (e.g. ``true`` for synthetic or pre-registered data in ScanNet's layout).
    """

    name: str
    kind: str
    root: str | None = None
    scenes: str | tuple[str, ...] = "all"
    split: str = "auto"
    options: dict = field(default_factory=dict)
    colour_matches_depth: bool | str = "auto"

    def __post_init__(self):
        from depthgt.sources.base import known_kinds

        where = f"sources[{self.name}]"
        _require(bool(_NAME.match(self.name)), f"{where}.name", "must match [A-Za-z0-9_.-]+ (it names output folders)")
        _require(
            self.kind in known_kinds(),
            f"{where}.kind",
            f"unknown kind {self.kind!r}; known: {', '.join(known_kinds())}",
        )
        _require(
            self.split in (*SPLITS, "auto"), f"{where}.split", f"must be auto, train, val or test, got {self.split!r}"
        )
        if self.scenes != "all":
            _require(
                isinstance(self.scenes, tuple) and len(self.scenes) >= 1,
                f"{where}.scenes",
                "must be 'all' or a non-empty list of scene names",
            )
            for scene in self.scenes:
                check_scene_name(scene, f"{where}.scenes")
        _require(
            isinstance(self.colour_matches_depth, bool) or self.colour_matches_depth == "auto",
            f"{where}.colour_matches_depth",
            f"must be auto, true or false, got {self.colour_matches_depth!r}",
        )
        _require(isinstance(self.options, Mapping), f"{where}.options", "must be a mapping")
        from depthgt.sources.base import check_options  # numpy only

        check_options(self.kind, self.options, f"config key {where}.options")


# --------------------------------------------------------------------------- everything


@dataclass(frozen=True)
class Settings:
    """The settings of every stage, from :func:`settings_from_config`.

    Attributes:
        seed: seed of every random choice (crops, splits, registration, training).
        device: "auto" (CUDA when available, else CPU), "cpu" or "cuda"; see
            :func:`depthgt.device.resolve_device`.
        resize: working resolution (square, pixels).
    """

    seed: int = 0
    device: str = "auto"
    resize: int = 256
    sources: tuple[SourceSettings, ...] = ()
    frameset: FrameSetSettings = FrameSetSettings()
    split: SplitSettings = SplitSettings()
    patches: PatchSettings = PatchSettings()
    render: RenderSettings = RenderSettings()
    registration: RegistrationSettings = RegistrationSettings()
    enhance: EnhanceSettings = EnhanceSettings()
    evaluation: EvaluationSettings = EvaluationSettings()
    dataset: DatasetSettings = DatasetSettings()

    def __post_init__(self):
        _require(self.seed >= 0, "seed", f"must be >= 0, got {self.seed}")
        _require(self.device in DEVICES, "device", f"must be auto, cpu or cuda, got {self.device!r}")
        _require(16 <= self.resize <= MAX_RESIZE, "resize", f"must be in [16, {MAX_RESIZE}], got {self.resize}")
        names = [s.name for s in self.sources]
        dup = sorted({n for n in names if names.count(n) > 1})
        _require(not dup, "sources", f"the name(s) {dup} are used twice; names must be unique")

    @property
    def size_hw(self) -> tuple[int, int]:
        return (self.resize, self.resize)

    def source(self, name: str) -> SourceSettings:
        for s in self.sources:
            if s.name == name:
                return s
        raise ConfigError(f"config sources: no source named {name!r}; known: {[s.name for s in self.sources]}")

    def train(self, model: str) -> TrainSettings:
        """The :class:`TrainSettings` of a trainable model of the registry."""
        if model not in self.enhance.models:
            raise ConfigError(f"no training settings for {model!r}; trainable models: {sorted(self.enhance.models)}")
        return self.enhance.models[model]

    def doc(self, *sections: str) -> dict:
        """JSON-ready dict of the named sections (all when none), e.g. for the resolved
        settings written beside outputs."""
        names = sections or tuple(f.name for f in dataclasses.fields(self))
        return json.loads(json.dumps({k: _section_doc(getattr(self, k)) for k in names}, default=list))


def _section_doc(value: Any) -> Any:
    """A section of :meth:`Settings.doc` as the config writes it (the registration's
    parts as its flat keys)."""
    if isinstance(value, RegistrationSettings):
        return value.as_config()
    return asdict(value) if dataclasses.is_dataclass(value) else value


@dataclass(frozen=True)
class Stage:
    """The config a workflow stage reads: what its rule passes to its job (the rule's
    ``config`` param: Snakemake's params rerun trigger re-runs exactly the jobs a change
    affects) and all its job builds its settings from (:func:`stage_config`).

    Attributes:
        sections: dotted config paths, in the order the rule's param lists them
            (``enhance.models.{model}``: the entry of the model the job trains).
        except_keys: dotted paths inside ``sections`` that do not decide the stage's
            outputs (``frameset.batch_size``: how the jobs are cut, not what they build).
    """

    sections: tuple[str, ...]
    except_keys: tuple[str, ...] = ()

    @property
    def top(self) -> tuple[str, ...]:
        """The top-level sections (e.g. for :meth:`Settings.doc`)."""
        return tuple(dict.fromkeys(p.split(".")[0] for p in self.sections))


_FRAMESET_SECTIONS = ("seed", "device", "frameset", "resize", "registration", "render", "patches")

#: The one table of the config sections each stage reads (the Snakefile's rules pass
#: exactly these to their jobs; the jobs narrow whatever they get to them). The index
#: reads no frame: neither the registration, the working resolution nor the batch size
#: decide it. The dataset records the sections that decide the GT in its card.
STAGES: dict[str, Stage] = {
    "index": Stage(("seed", "split", "frameset"), except_keys=("frameset.batch_size",)),
    "frameset": Stage(_FRAMESET_SECTIONS),
    "pretrain": Stage(_FRAMESET_SECTIONS),
    "dataset": Stage((*_FRAMESET_SECTIONS, "split")),
    "rde": Stage(("resize", "enhance.rde")),
    "train": Stage(("seed", "device", "enhance.train", "enhance.models.{model}")),
    "evaluate": Stage(("device", "evaluation.split")),
    # Table 2's independent references of real test frame sets: the frame sets' sections
    # (the neighbours-only render re-renders with the build's settings) and the split evaluated
    "references": Stage((*_FRAMESET_SECTIONS, "evaluation.split")),
}


def stage_config(config: Mapping[str, Any], stage: str, **names: str) -> dict[str, Any]:
    """The part of ``config`` that stage ``stage`` reads (:data:`STAGES`), nested as in
    the config; a path the config does not hold is left out (its default applies).

    Args:
        names: values of the placeholders of the stage's paths (``model``: the
            ``enhance.models`` entry of the model a training job trains).

    >>> stage_config({"seed": 1, "resize": 64, "frameset": {"stride": 3, "batch_size": 4}}, "index")
    {'seed': 1, 'frameset': {'stride': 3}}
    >>> stage_config({"enhance": {"models": {"sdd": {"epochs": 2}, "ddrnet": {}}}}, "train", model="sdd")
    {'enhance': {'models': {'sdd': {'epochs': 2}}}}
    """
    if stage not in STAGES:
        raise KeyError(f"unknown stage {stage!r}; known: {', '.join(STAGES)}")
    if not isinstance(config, Mapping):
        raise ConfigError(f"the configuration must be a mapping, got {type(config).__name__}")
    spec = STAGES[stage]
    out: dict[str, Any] = {}
    for path in spec.sections:
        keys = path.format(**names).split(".")
        node, value = out, config
        for depth, key in enumerate(keys):
            if not isinstance(value, Mapping) or key not in value:
                break
            value = value[key]
            if depth == len(keys) - 1:
                node[key] = value
            else:
                node = node.setdefault(key, {})
    for path in spec.except_keys:
        out = _without(out, path.split("."))
    return out


def _without(tree: Any, keys: list[str]) -> Any:
    """A copy of the nested mapping ``tree`` without the key at the path ``keys`` (the
    config itself is not changed; the other keys keep their order)."""
    if not isinstance(tree, Mapping) or keys[0] not in tree:
        return tree
    if len(keys) == 1:
        return {k: v for k, v in tree.items() if k != keys[0]}
    return {**tree, keys[0]: _without(tree[keys[0]], keys[1:])}


def stage_settings(config: Mapping[str, Any], stage: str, **names: str) -> Settings:
    """The settings a stage's job works with: :func:`settings_from_config` of
    :func:`stage_config` (the sections the stage reads; every other section takes its
    defaults, the same whether the job gets the rule's sections or the whole config)."""
    return settings_from_config(stage_config(config, stage, **names), sections=STAGES[stage].top)


TOP_LEVEL_KEYS = (
    "seed",
    "device",
    "resize",
    "sources",
    "frameset",
    "split",
    "patches",
    "render",
    "registration",
    "enhance",
    "evaluation",
    "dataset",
)


def settings_from_config(config: Mapping[str, Any], sections: tuple[str, ...] | None = None) -> Settings:
    """Every stage's settings from a config mapping (the validated config, or the
    sections of it that a rule passes to its job; missing sections take their defaults).

    Args:
        sections: the top-level sections the caller reads (a stage's,
            :func:`stage_settings`): a check between two sections runs only when it
            reads both (the RDE job reads ``resize`` and not ``patches``, whose default
            size need not fit a small ``resize``); None: every check.

    Raises:
        ConfigError: an unknown key (at any level), a bad value or an inconsistency
            between sections (``patches.size > resize``); the message names the key.
    """
    if not isinstance(config, Mapping):
        raise ConfigError(f"the configuration must be a mapping, got {type(config).__name__}")
    check_keys(config, TOP_LEVEL_KEYS, "")
    seed = _typed(config.get("seed", 0), int, "seed")
    device = _typed(config.get("device", "auto"), str, "device")
    sources = config.get("sources") or []
    if not isinstance(sources, list):
        _fail("sources", f"must be a list, got {type(sources).__name__}")
    settings = Settings(
        seed=seed,
        device=device,
        resize=_typed(config.get("resize", 256), int, "resize"),
        sources=tuple(build(SourceSettings, s, f"sources[{i}]") for i, s in enumerate(sources)),
        frameset=build(FrameSetSettings, config.get("frameset"), "frameset"),
        split=build(SplitSettings, config.get("split"), "split"),
        patches=build(PatchSettings, config.get("patches"), "patches"),
        render=build(RenderSettings, config.get("render"), "render"),
        registration=registration_settings(config.get("registration")),
        enhance=_enhance_settings(config.get("enhance"), seed, device),
        evaluation=build(EvaluationSettings, config.get("evaluation"), "evaluation"),
        dataset=build(DatasetSettings, config.get("dataset"), "dataset"),
    )
    if sections is None or {"patches", "resize"} <= set(sections):
        _require(
            settings.patches.size <= settings.resize,
            "patches.size",
            f"{settings.patches.size} does not fit in the {settings.resize}x{settings.resize} working resolution "
            "(resize)",
        )
    return settings


def check_workflow(settings: Settings) -> None:
    """Checks of a whole workflow's settings that no single section decides (run when
    the workflow starts, before any job; a job gets only its sections).

    * ``registration.method: overfit`` pretrains the encoder on frame sets of the
      ``train`` split (``registration.pretrain.framesets`` > 0): some source must put
      frame sets there (``split: train`` or ``auto``), or the pretraining job would
      fail after the run started.

    >>> check_workflow(settings_from_config({"registration": {"method": "overfit"},
    ...     "sources": [{"name": "t", "kind": "synthetic", "split": "test"}]}))
    Traceback (most recent call last):
    ...
    depthgt.errors.ConfigError: config key registration.pretrain.framesets: ...
    """
    reg = settings.registration
    if reg.method == "overfit" and reg.pretrain.framesets > 0 and settings.sources:
        if not any(s.split in ("train", "auto") for s in settings.sources):
            splits = ", ".join(f"sources[{i}].split: {s.split}" for i, s in enumerate(settings.sources))
            _fail(
                "registration.pretrain.framesets",
                f"{reg.pretrain.framesets} frame sets of the train split pretrain the overfit registration's encoder "
                f"(registration.method: overfit), but no source puts frame sets in the train split ({splits}); "
                "give a source split: train or auto, or set registration.pretrain.framesets: 0 (random initial "
                "weights)",
            )


# --------------------------------------------------------------------------- the builder


def check_keys(section: Mapping[str, Any], allowed, where: str) -> None:
    """Raise :class:`ConfigError` naming every key of ``section`` not in ``allowed``.

    The one unknown-key check of the project (every settings class goes through it).
    """
    unknown = sorted(set(section) - set(allowed))
    if unknown:
        prefix = f"{where}." if where else ""
        raise ConfigError(
            f"unknown config key(s) {', '.join(prefix + str(k) for k in unknown)}; "
            f"allowed{' in ' + where if where else ''}: {', '.join(sorted(map(str, allowed)))}"
        )


def build(cls: type[T], section: Mapping[str, Any] | T | None, where: str) -> T:
    """``cls`` from a config mapping: unknown keys rejected, nested settings built,
    lists turned into tuples where the field is a tuple, scalar types checked; every
    error names ``where.key``.

    >>> build(PatchSettings, {"count": 3}, "patches").count
    3
    """
    if section is None:
        section = {}
    if isinstance(section, cls):
        return section
    if not isinstance(section, Mapping):
        _fail(where, f"must be a mapping, got {type(section).__name__} {section!r}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls) if f.init]
    check_keys(section, names, where)
    values = {k: _coerce(hints[k], v, f"{where}.{k}") for k, v in section.items()}
    try:
        return cls(**values)
    except ConfigError:
        raise
    except (TypeError, ValueError) as err:
        raise ConfigError(f"config key {where}: {err}") from err


def _options(hint) -> tuple:
    """The alternatives of a type hint (``int | None`` -> (int, NoneType))."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return typing.get_args(hint)
    return (hint,)


def _coerce(hint, value, where: str):
    options = _options(hint)
    if value is None:
        if type(None) in options:
            return None
        _fail(where, "must not be null")
    for opt in options:
        if dataclasses.is_dataclass(opt) and isinstance(value, Mapping):
            return build(opt, value, where)
        if typing.get_origin(opt) is tuple and isinstance(value, (list, tuple)):
            return _tuple_of(opt, value, where)
    scalars = [o for o in options if o in (int, float, bool, str)]
    structured = [o for o in options if dataclasses.is_dataclass(o) or typing.get_origin(o) is tuple]
    if structured and not scalars and not any(isinstance(value, o) for o in options if isinstance(o, type)):
        kinds = " or ".join("a mapping" if dataclasses.is_dataclass(o) else "a list" for o in structured)
        _fail(where, f"must be {kinds}, got {type(value).__name__} {value!r}")
    if scalars and not any(_is(value, o) for o in scalars):
        _fail(where, f"must be {' or '.join(o.__name__ for o in scalars)}, got {type(value).__name__} {value!r}")
    if float in scalars and not isinstance(value, float) and _is(value, float) and int not in scalars:
        return float(value)
    return value


def _tuple_of(hint, value, where: str) -> tuple:
    """``value`` as a tuple, its items checked where the hint gives them one scalar type
    (``tuple[int, ...]``); nested settings and other item types are left to their checks."""
    args = [a for a in typing.get_args(hint) if a is not Ellipsis]
    if len(set(args)) == 1 and args[0] in (int, float, bool, str):
        for i, item in enumerate(value):
            if not _is(item, args[0]):
                _fail(f"{where}[{i}]", f"must be {args[0].__name__}, got {type(item).__name__} {item!r}")
    return tuple(value)


def _is(value, kind) -> bool:
    if kind is bool:
        return isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if kind is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, kind)


def _typed(value, kind, where: str):
    if not _is(value, kind):
        _fail(where, f"must be {kind.__name__}, got {type(value).__name__} {value!r}")
    return value


# --------------------------------------------------------------------------- schema


def check_config(config: dict[str, Any], schema_path: str) -> None:
    """Validate ``config`` against the JSON schema and raise one :class:`ConfigError`
    listing every problem as ``key.path: message`` (Snakemake's own validation, run
    afterwards to fill defaults, reports only the first error with the whole schema)."""
    import jsonschema
    import yaml

    with open(schema_path) as fh:
        schema = yaml.safe_load(fh)
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(config), key=lambda e: list(map(str, e.absolute_path)))
    if errors:
        lines = []
        for err in errors:
            path = (
                "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in err.absolute_path).lstrip(".")
                or "(top level)"
            )
            lines.append(f"  config key {path}: {err.message}")
        raise ConfigError("invalid configuration:\n" + "\n".join(lines))
