"""The GT renderer (paper eq. 5), composed of parts as PyTorch3D's points renderer:

* :mod:`~depthgt.gt.render.cloud`: the members of a frame set back-projected at their
  source pixels' positions and moved into the target camera, with normals and each
  point's noise sigma (:func:`cloud_in_target`);
* :mod:`~depthgt.gt.render.rasteriser`: every (point, pixel) pair within the radius,
  sorted by pixel and front first (:func:`rasterise_gt` -> :class:`RenderCandidates`);
* :mod:`~depthgt.gt.render.agreement`: frames, or regions of them, that disagree with
  the target's own depth;
* :mod:`~depthgt.gt.render.compositor`: candidates -> surfaces, visibility, a weighted
  plane per pixel and the confidence (:func:`composite_gt` -> :class:`GTRender`); on
  the CPU pixel by pixel, compiled (:mod:`~depthgt.gt.render.pixelwise`);
* :mod:`~depthgt.gt.render.fusion`: the one entry the build runs, :func:`fuse` (cloud ->
  rasterise -> composite -> leave-target-out -> :class:`Fusion`).

:func:`render_gt` is the rasteriser and the compositor in a row on a given cloud (tests,
benchmarks); the build fuses frame sets with :func:`fuse`. The rule, step by step:
docs/gt-renderer.md. No Python loop runs over points or pixels; ``tests/render_reference.py``
holds the plain loop versions (test oracles).

Layouts: points (B, N, 3) metres in the camera frame, intrinsics (B, 3, 3) at the
output resolution, images (B, C, H, W), depth (B, 1, H, W) metres with 0 = nothing.
"""

from typing import TYPE_CHECKING

from depthgt.lazy import lazy_names

if TYPE_CHECKING:  # the package's names, each imported on first use (below)
    from depthgt.gt.render.cloud import TargetCloud, cloud_in_target
    from depthgt.gt.render.compositor import GTRender, composite_gt, render_gt
    from depthgt.gt.render.fusion import (
        Fusion,
        SetGeometry,
        frames_left_out_whole,
        fuse,
        fuse_sets,
        whole_frame_threshold,
    )
    from depthgt.gt.render.rasteriser import RenderCandidates, rasterise_gt
    from depthgt.noise_law import KINECT_SIGMA_1M, depth_sigma_m, estimate_noise_sigma_1m
    from depthgt.rasterise import resampled_positions
    from depthgt.splatting import SoftSplat, splat_soft  # re-exported: the renderer's public names

__all__ = [
    "SoftSplat",
    "splat_soft",
    "GTRender",
    "RenderCandidates",
    "render_gt",
    "rasterise_gt",
    "composite_gt",
    "TargetCloud",
    "cloud_in_target",
    "Fusion",
    "fuse",
    "fuse_sets",
    "SetGeometry",
    "frames_left_out_whole",
    "whole_frame_threshold",
    "depth_sigma_m",
    "estimate_noise_sigma_1m",
    "resampled_positions",
    "KINECT_SIGMA_1M",
]

__getattr__, __dir__ = lazy_names(__name__, __file__)
