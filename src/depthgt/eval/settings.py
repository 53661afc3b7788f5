"""The evaluation's settings (config ``evaluation``), torch-free: :mod:`depthgt.settings`
builds them when the workflow starts."""

from __future__ import annotations

from depthgt import registry
from depthgt.gt.settings import Split
from depthgt.settings_base import require, section

__all__ = ["EvaluationSettings"]


@section("evaluation")
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

    split: Split = "test"
    methods: tuple[str, ...] = tuple(registry.METHODS)
    figure_frames_per_scene: int = 2
    rde_synthetic_test: bool = False

    def __post_init__(self):
        unknown = [m for m in self.methods if m not in registry.METHODS]
        require(not unknown, "evaluation.methods", f"unknown method(s) {unknown}; known: {', '.join(registry.METHODS)}")
        require(
            len(set(self.methods)) == len(self.methods), "evaluation.methods", f"duplicates in {list(self.methods)}"
        )
        require(len(self.methods) >= 1, "evaluation.methods", "needs at least one method")
        require(
            self.figure_frames_per_scene >= 1,
            "evaluation.figure_frames_per_scene",
            f"must be >= 1, got {self.figure_frames_per_scene}",
        )

    @property
    def models(self) -> list[str]:
        """The learned methods among :attr:`methods` (trained by the default target)."""
        return [m for m in self.methods if registry.METHODS[m].kind == "learned"]
