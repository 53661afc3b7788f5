"""The GT stage's settings (torch-free): how frame sets are formed (config
``frameset``), the split of ``auto`` sources (``split``), the patch crops (``patches``),
what the dataset assembly and the run's checks accept (``dataset``) and the global
reconstruction of the RDE GT (``enhance.rde``, :mod:`depthgt.gt.rde`).
The renderer's are beside it, :mod:`depthgt.gt.render.settings`."""

from __future__ import annotations

from typing import Literal

import numpy as np

from depthgt.settings_base import choices, require, section

__all__ = [
    "Split",
    "SPLITS",
    "PatchFilter",
    "FrameSetSettings",
    "SplitSettings",
    "PatchSettings",
    "DatasetSettings",
    "RDESettings",
    "MAX_PATCH_COUNT",
    "MAX_NEIGHBOURS",
    "MAX_COVERAGE_SPAN",
    "MAX_FRAMESET_BATCH",
]

#: The splits of a dataset (a source's ``split``, ``evaluation.split``, the manifests).
Split = Literal["train", "val", "test"]
SPLITS: tuple[str, ...] = choices(Split)
#: Which image's missing ratio decides whether a patch pair is kept (``patches.filter_on``).
PatchFilter = Literal["gt", "input", "both"]

# Upper bounds on values that size memory (a typo such as patches.count: 60000 would
# otherwise be found by the kernel's OOM killer, hours into a run).
MAX_PATCH_COUNT = 1000
MAX_NEIGHBOURS = 32
MAX_COVERAGE_SPAN = 256  # frameset.coverage_span: 2 * span candidate frames are read and held at once
# frame sets one batch job builds (frameset.batch_size): a job holds one frame set at a
# time, but its time limit grows with the batch
MAX_FRAMESET_BATCH = 1024


@section("frameset")
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
            checked on tuning data and kept (docs/decisions.md "The span, views and limits
            of coverage": a wider span fills more on long recordings at some accuracy).
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
    selection: Literal["window", "coverage"] = "window"
    coverage_span: int = 30
    coverage_views: int = 4
    coverage_max_baseline_m: float = 0.3
    coverage_max_angle_deg: float = 20.0
    coverage_min_fill_px: int = 50
    coverage_mixed_margin_px: int = 1
    coverage_mixed_jump_rel: float = 0.03

    def __post_init__(self):
        require(
            1 <= self.batch_size <= MAX_FRAMESET_BATCH,
            "frameset.batch_size",
            f"must be in 1..{MAX_FRAMESET_BATCH}, got {self.batch_size}",
        )
        for key in ("neighbours", "stride", "target_step"):
            require(getattr(self, key) >= 1, f"frameset.{key}", f"must be >= 1, got {getattr(self, key)}")
        require(
            self.neighbours <= MAX_NEIGHBOURS,
            "frameset.neighbours",
            f"must be <= {MAX_NEIGHBOURS} (every member is held in memory at once), got {self.neighbours}",
        )
        require(
            1 <= self.coverage_span <= MAX_COVERAGE_SPAN,
            "frameset.coverage_span",
            f"must be in 1..{MAX_COVERAGE_SPAN} (the candidates are held in memory at once), got {self.coverage_span}",
        )
        require(
            0 <= self.coverage_views <= MAX_NEIGHBOURS,
            "frameset.coverage_views",
            f"must be in 0..{MAX_NEIGHBOURS}, got {self.coverage_views}",
        )
        require(
            self.coverage_max_baseline_m > 0,
            "frameset.coverage_max_baseline_m",
            f"must be > 0, got {self.coverage_max_baseline_m}",
        )
        require(
            0 < self.coverage_max_angle_deg <= 180,
            "frameset.coverage_max_angle_deg",
            f"must be in (0, 180], got {self.coverage_max_angle_deg}",
        )
        require(
            self.coverage_min_fill_px >= 1,
            "frameset.coverage_min_fill_px",
            f"must be >= 1, got {self.coverage_min_fill_px}",
        )
        require(
            isinstance(self.coverage_mixed_margin_px, int) and 0 <= self.coverage_mixed_margin_px <= 16,
            "frameset.coverage_mixed_margin_px",
            f"must be an integer in 0..16, got {self.coverage_mixed_margin_px!r}",
        )
        require(
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


@section("split")
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
        require(0.0 <= self.val_fraction < 1.0, "split.val_fraction", f"must be in [0, 1), got {self.val_fraction}")
        require(self.block_frames >= 1, "split.block_frames", f"must be >= 1, got {self.block_frames}")


@section("patches")
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
    filter_on: PatchFilter = "gt"
    max_gt_sigma_m: float | None = None

    def __post_init__(self):
        require(
            1 <= self.count <= MAX_PATCH_COUNT, "patches.count", f"must be in [1, {MAX_PATCH_COUNT}], got {self.count}"
        )
        require(self.size >= 8, "patches.size", f"must be >= 8, got {self.size}")
        require(0.0 < self.max_missing <= 1.0, "patches.max_missing", f"must be in (0, 1], got {self.max_missing}")
        require(
            self.max_gt_sigma_m is None or self.max_gt_sigma_m > 0,
            "patches.max_gt_sigma_m",
            f"must be null or > 0, got {self.max_gt_sigma_m}",
        )


@section("dataset")
class DatasetSettings:
    """What the dataset assembly and the run's checks accept (config ``dataset``).

    Attributes:
        allow_empty: keep a dataset in which no frame set was built (by default the
            dataset job fails then, naming the reasons: a build that keeps nothing is
            an error, not a success).
        check_space: before the first job, refuse a run whose planned frame sets do
            not fit on the results file system (measured bytes per frame set x the
            frame sets still to build; :mod:`depthgt.gt.space`); false: warn only.
    """

    allow_empty: bool = False
    check_space: bool = True


@section("enhance.rde")
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
    trunc_voxels: float = 4  # written 4: the workflow writes it into its config, as it always did
    frame_step: int = 2
    max_depth_m: float = 8.0
    max_voxels: int = 48_000_000
    backend: Literal["torch", "open3d", "auto"] = "torch"
    max_missing: float = 0.05

    def __post_init__(self):
        require(
            self.voxel_m > 0 and self.trunc_voxels >= 1 and self.max_depth_m > 0,
            "enhance.rde",
            f"voxel_m and max_depth_m must be > 0 and trunc_voxels >= 1, got {self.voxel_m}, {self.max_depth_m}, "
            f"{self.trunc_voxels}",
        )
        require(
            self.frame_step >= 1 and self.max_voxels >= 1,
            "enhance.rde",
            f"frame_step and max_voxels must be >= 1, got {self.frame_step}, {self.max_voxels}",
        )
        require(0 < self.max_missing <= 1, "enhance.rde.max_missing", f"must be in (0, 1], got {self.max_missing}")

    @property
    def trunc_m(self) -> float:
        return self.voxel_m * self.trunc_voxels
