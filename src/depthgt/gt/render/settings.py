"""The GT renderer's settings (config ``render``), beside the renderer they set
(torch-free: :mod:`depthgt.settings` builds them when the workflow starts)."""

from __future__ import annotations

from typing import Literal

from depthgt.settings_base import require, section

__all__ = ["RenderSettings"]


@section("render")
class RenderSettings:
    """Settings of the GT renderer, :func:`depthgt.gt.render.fuse` (config ``render``; paper eq. 5
    with surface selection by geometry).

    The renderer reasons in inverse depth, where a disparity sensor's noise is about
    constant (its depth noise grows as z^2) and planes are affine in screen space.
    Every depth sample carries an expected standard deviation
    ``sigma_z = sqrt(noise_sigma_abs_m^2 + (noise_sigma_1m * z^2)^2)``, i.e.
    ``sigma_z / z^2`` in inverse depth.

    Defaults were chosen on the TUNING set of bench/bench_gt_protocol.py (synthetic
    ``room`` and ``varied`` scenes of seed 0, Kinect v1 profile) and are reported on its
    disjoint EVALUATION set (docs/gt-renderer.md, docs/decisions.md).

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
            tuning set (unchanged within 0.01 mm), see docs/decisions.md "The edge vote".
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
    plane: Literal["fit", "normals", "none"] = "fit"
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
        require(
            self.leave_target_out_stride >= 1,
            "render.leave_target_out_stride",
            f"must be >= 1, got {self.leave_target_out_stride}",
        )
        require(self.m >= 1, "render.m", f"must be >= 1, got {self.m}")
        require(self.radius_px > 0, "render.radius_px", f"must be > 0, got {self.radius_px}")
        require(
            self.noise_sigma_1m is None or self.noise_sigma_1m > 0,
            "render.noise_sigma_1m",
            f"must be null or > 0, got {self.noise_sigma_1m}",
        )
        require(self.noise_sigma_abs_m >= 0, "render.noise_sigma_abs_m", f"must be >= 0, got {self.noise_sigma_abs_m}")
        require(self.gap_sigmas > 0, "render.gap_sigmas", f"must be > 0, got {self.gap_sigmas}")
        require(self.gap_slope_rel >= 0, "render.gap_slope_rel", f"must be >= 0, got {self.gap_slope_rel}")
        require(self.min_frames >= 1, "render.min_frames", f"must be >= 1, got {self.min_frames}")
        require(self.min_points >= 1, "render.min_points", f"must be >= 1, got {self.min_points}")
        require(0.0 <= self.edge_vote <= 1.0, "render.edge_vote", f"must be in [0, 1], got {self.edge_vote}")
        require(
            self.edge_vote_slack_px >= 0, "render.edge_vote_slack_px", f"must be >= 0, got {self.edge_vote_slack_px}"
        )
        require(self.ambiguous_px >= 0, "render.ambiguous_px", f"must be >= 0, got {self.ambiguous_px}")
        require(self.slope_prior >= 0, "render.slope_prior", f"must be >= 0, got {self.slope_prior}")
        require(
            0.0 <= self.min_frame_agreement <= 1.0,
            "render.min_frame_agreement",
            f"must be in [0, 1], got {self.min_frame_agreement}",
        )
        require(
            0.0 <= self.min_whole_frame_agreement <= 1.0,
            "render.min_whole_frame_agreement",
            f"must be in [0, 1], got {self.min_whole_frame_agreement}",
        )
        require(
            isinstance(self.agreement_edge_px, int) and self.agreement_edge_px >= 0,
            "render.agreement_edge_px",
            f"must be an integer >= 0, got {self.agreement_edge_px!r}",
        )
        require(
            isinstance(self.agreement_tile_px, int) and self.agreement_tile_px >= 0,
            "render.agreement_tile_px",
            f"must be an integer >= 0, got {self.agreement_tile_px!r}",
        )
        require(
            self.max_sigma_m is None or self.max_sigma_m > 0,
            "render.max_sigma_m",
            f"must be null or > 0, got {self.max_sigma_m}",
        )
        require(
            0 < self.min_cos_incidence < 1,
            "render.min_cos_incidence",
            f"must be in (0, 1), got {self.min_cos_incidence}",
        )
        require(self.max_correction_rel > 0, "render.max_correction_rel", f"must be > 0, got {self.max_correction_rel}")
        require(self.min_depth_m > 0, "render.min_depth_m", f"must be > 0, got {self.min_depth_m}")
