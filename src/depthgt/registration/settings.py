"""How frame sets are registered (config ``registration``, one flat section): the
settings of every step, held as the parts each reads, the presets, and
:func:`registration_settings`, which builds them from the section (torch-free:
:mod:`depthgt.settings` builds them when the workflow starts). The methods themselves and
what each needs: :data:`depthgt.registration.methods.METHODS`."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import asdict
from typing import Any, Literal

from depthgt.registration.methods import METHODS, JobCost, RegistrationMethod
from depthgt.settings_base import build, check_keys, fail, require, section

__all__ = [
    "RefineSettings",
    "PretrainSettings",
    "EncoderSettings",
    "MatchingSettings",
    "TrainingSettings",
    "CheckSettings",
    "REGISTRATION_KEYS",
    "RegistrationSettings",
    "DEFAULT_PRESET",
    "REGISTRATION_PRESETS",
    "registration_settings",
    "MAX_CANDIDATES",
]

MAX_CANDIDATES = 1 << 16  # registration.n_candidates: matching is quadratic in it


@section("registration.refine_settings")
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
        coarse_converged_step: a scale before the finest ends after an accepted LM
            step whose largest component (metres of translation, radians of rotation)
            is under this: the next scale's first steps move the poses by more. Every
            scale also ends after ``iters`` or an iteration with no accepted trial; the
            finest ends only so (or on a step under 1e-7). 0: every scale like the finest.
    """

    scales: tuple[int, ...] = (4, 2, 1)
    iters: tuple[int, ...] = (10, 8, 6)
    pairs: Literal["all", "target", "adjacent"] = "all"
    point_stride: tuple[int, ...] = (1, 1, 2)
    geo_scale_m: tuple[float, ...] = (0.02, 0.01, 0.005)
    photo_scale: float = 0.03
    photo_weight: float = 0.3
    robust: Literal["huber", "cauchy"] = "huber"
    max_dist_m: tuple[float, ...] = (0.10, 0.05, 0.03)
    damping: float = 1e-4
    geo_ref_depth_m: float = 0.0
    coarse_converged_step: float = 1e-4

    def __post_init__(self):
        where = "registration.refine_settings"
        require(self.geo_ref_depth_m >= 0, f"{where}.geo_ref_depth_m", f"must be >= 0, got {self.geo_ref_depth_m}")
        require(
            math.isfinite(self.coarse_converged_step) and self.coarse_converged_step >= 0,
            f"{where}.coarse_converged_step",
            f"must be finite and >= 0, got {self.coarse_converged_step}",
        )
        n = len(self.scales)
        require(
            len(self.iters) == len(self.point_stride) == len(self.max_dist_m) == len(self.geo_scale_m) == n,
            where,
            "scales, iters, point_stride, max_dist_m and geo_scale_m need the same length",
        )


@section("registration.pretrain")
class PretrainSettings:
    """Stream-only pretraining of the registration encoder (config ``registration.pretrain``).

    Attributes:
        framesets: frame sets of the train split used (0 = random initialisation).
        epochs: passes over them (one Adam step per frame set).
    """

    framesets: int = 16
    epochs: int = 1

    def __post_init__(self):
        require(self.framesets >= 0, "registration.pretrain.framesets", f"must be >= 0, got {self.framesets}")
        require(self.epochs >= 1, "registration.pretrain.epochs", f"must be >= 1, got {self.epochs}")


@section("registration")
class EncoderSettings:
    """The overfit registration's RGB encoder (config keys ``registration.n_blocks``,
    ``channels``, ``feat_dim``, ``encoder_stride``, ``precision``).

    Attributes:
        n_blocks: ResNet-18 BasicBlocks at the encoder's resolution; channels: their
            width; feat_dim: the dimension of the output features.
        encoder_stride: the encoder runs on the RGB image averaged over cells of this
            many pixels a side (1: every pixel, the paper's); a candidate pixel takes its
            cell's feature. The encoder's cost falls with its square.
        precision: of the encoder's convolutions, "fp32", "bf16" (autocast; the
            features are normalised, matched and aligned in float32/64) or "auto" (bf16
            on CUDA devices that support it and on CPUs with native bf16 instructions,
            AVX512-BF16 or AMX; else fp32). On CPU the encoder runs channels-last.
    """

    n_blocks: int = 2
    channels: int = 64
    feat_dim: int = 32
    encoder_stride: int = 1
    precision: Literal["fp32", "bf16", "auto"] = "fp32"

    def __post_init__(self):
        for key in ("n_blocks", "channels", "feat_dim", "encoder_stride"):
            require(getattr(self, key) >= 1, f"registration.{key}", f"must be >= 1, got {getattr(self, key)}")


@section("registration")
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
        require(self.top_k >= 3, "registration.top_k", f"must be >= 3, got {self.top_k}")
        require(self.n_candidates >= 3, "registration.n_candidates", f"must be >= 3, got {self.n_candidates}")
        require(
            self.n_candidates <= MAX_CANDIDATES,
            "registration.n_candidates",
            f"must be <= {MAX_CANDIDATES} (matching is quadratic in it), got {self.n_candidates}",
        )
        for key in ("n_subsets", "knn_block"):
            require(getattr(self, key) >= 1, f"registration.{key}", f"must be >= 1, got {getattr(self, key)}")
        require(
            0.0 < self.subset_fraction <= 1.0,
            "registration.subset_fraction",
            f"must be in (0, 1], got {self.subset_fraction}",
        )


@section("registration")
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
    pairs: Literal["all", "target"] = "all"
    render_radius_px: float = 2.0
    render_max_points: int = 16
    render_stride: int = 1
    pose_from: Literal["last", "best"] = "last"

    def __post_init__(self):
        require(self.iterations >= 0, "registration.iterations", f"must be >= 0, got {self.iterations}")
        for key in ("render_max_points", "render_stride"):
            require(getattr(self, key) >= 1, f"registration.{key}", f"must be >= 1, got {getattr(self, key)}")


@section("registration")
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
        require(self.max_correction_m > 0, "registration.max_correction_m", f"must be > 0, got {self.max_correction_m}")
        require(
            self.max_correction_deg > 0,
            "registration.max_correction_deg",
            f"must be > 0, got {self.max_correction_deg}",
        )
        require(
            self.max_residual_sigmas >= 0,
            "registration.max_residual_sigmas",
            f"must be >= 0, got {self.max_residual_sigmas}",
        )
        require(
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
    "encoder_stride",
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


@section("registration")
class RegistrationSettings:
    """How frame sets are aligned (config ``registration``, one flat section; defaults:
    the paper / R&R values; presets in :data:`REGISTRATION_PRESETS`), held as the parts
    each step reads: ``encoder`` (:class:`EncoderSettings`), ``matching``
    (:class:`MatchingSettings`), ``training`` (:class:`TrainingSettings`), ``checks``
    (:class:`CheckSettings`). Build it from config keys with :meth:`from_keys` (or
    :func:`registration_settings`, which applies the preset); :meth:`as_config` gives the
    section back.

    Attributes:
        method: a name of :data:`depthgt.registration.methods.METHODS`: "given" (the
            source's poses), "refine" (the source's poses refined on the frame set by the
            joint SE(3) refinement, ``refine_settings``; a correction beyond the checks'
            ``max_correction_m`` / ``max_correction_deg`` fails the neighbour) or
            "overfit" (the paper's registration).
        on_failure: what a frame set with failed neighbours becomes: rendered from the
            neighbours that did register (``drop_neighbours``), or excluded from the
            dataset (``exclude``). A set where fewer than ``min_ok_fraction`` of the
            neighbours registered is excluded either way.
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
    on_failure: Literal["drop_neighbours", "exclude"] = "drop_neighbours"
    preset: str | None = None
    pretrain: PretrainSettings = PretrainSettings()
    encoder: EncoderSettings = EncoderSettings()
    matching: MatchingSettings = MatchingSettings()
    training: TrainingSettings = TrainingSettings()
    checks: CheckSettings = CheckSettings()
    chaining: bool = True
    refine: bool = True
    refine_settings: RefineSettings = RefineSettings()
    photometric: Literal["auto", "on", "off"] = "auto"
    num_threads: int | None = None

    @property
    def method_entry(self) -> RegistrationMethod:
        """The method's entry of :data:`depthgt.registration.methods.METHODS` (what it needs
        and costs)."""
        return METHODS[self.method]

    @property
    def uses_source_poses(self) -> bool:
        """Whether the frame sets need the source's poses (the method's
        :attr:`~depthgt.registration.methods.RegistrationMethod.uses_source_poses`)."""
        return self.method_entry.uses_source_poses

    @property
    def job_cost(self) -> JobCost:
        """What a frame set costs a frame-set job with this method and preset."""
        return self.method_entry.job_cost(self.preset)

    @classmethod
    def from_keys(cls, keys: Mapping[str, Any], where: str = "registration") -> RegistrationSettings:
        """The settings of the flat config keys ``keys`` (:data:`REGISTRATION_KEYS`; a
        key not given takes its default, no preset is applied); an unknown key or a bad
        value raises :class:`ConfigError` naming ``where.key``.

        >>> RegistrationSettings.from_keys({"top_k": 50, "max_residual_m": 0.01}).matching.top_k
        50
        """
        if not isinstance(keys, Mapping):
            fail(where, f"must be a mapping, got {type(keys).__name__} {keys!r}")
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
        require(
            self.method in METHODS,
            "registration.method",
            f"must be one of {', '.join(METHODS)} (depthgt.registration.methods), got {self.method!r}",
        )
        require(
            self.preset is None or self.preset in REGISTRATION_PRESETS,
            "registration.preset",
            f"unknown preset {self.preset!r}; known: {', '.join(REGISTRATION_PRESETS)}",
        )
        require(
            self.num_threads is None or self.num_threads >= 1,
            "registration.num_threads",
            f"must be >= 1 or null, got {self.num_threads}",
        )


#: The preset of a ``registration`` section without one.
DEFAULT_PRESET = "paper"

# Presets of the overfit registration, as config values (nested sections merge with
# the user's: registration: {preset: fast, refine_settings: {iters: [4, 4, 2]}} keeps
# the preset's other refinement values).
REGISTRATION_PRESETS: dict[str, dict[str, Any]] = {
    # The paper: R&R encoder and matching, Adam 1e-4 for 30 iterations, plus refinement;
    # bf16 convolutions where the hardware has them (2.3x faster encoder on AVX512-BF16).
    "paper": {"precision": "auto"},
    # The paper without the beyond-the-paper steps (for the with/without comparison).
    "paper_only": {"chaining": False, "refine": False, "precision": "auto"},
    # CPU-friendly: one pass of a small encoder (pretrained weights when given) on
    # 2 x 2 cells for the correspondence initialisation, no overfit iterations, then
    # chaining and a sparser refinement, its point-to-plane scale growing as z^2 beyond
    # 1.5 m and a stronger photometric term (chosen on bench_gt_protocol.py's tuning
    # sets: pose error vs the source's poses and GT error; docs/decisions.md "The fast
    # preset's refinement" and "The fast preset's encoder on 2 x 2 cells").
    "fast": {
        "n_blocks": 1,
        "channels": 32,
        "encoder_stride": 2,
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
    values (default :data:`DEFAULT_PRESET`), overridden by the section's other keys.

    >>> registration_settings({"preset": "fast", "iterations": 2}).encoder.channels
    32
    """
    if section is not None and not isinstance(section, Mapping):
        fail(where, f"must be a mapping, got {type(section).__name__} {section!r}")
    values = dict(section or {})
    preset = values.pop("preset", DEFAULT_PRESET)
    if preset not in REGISTRATION_PRESETS:
        fail(f"{where}.preset", f"unknown preset {preset!r}; known: {', '.join(REGISTRATION_PRESETS)}")
    merged = dict(REGISTRATION_PRESETS[preset])
    for key, value in values.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = {**merged[key], **value}
        else:
            merged[key] = value
    return RegistrationSettings.from_keys({**merged, "preset": preset}, where)
