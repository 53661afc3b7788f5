"""The outcome of registering one frame set, whatever the method (the source's poses,
their refinement, the overfit registration): the neighbours' poses in the target camera, each
neighbour's status and the record written to poses.json."""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import torch

__all__ = ["RegistrationResult"]


@dataclass
class RegistrationResult:
    """Outcome of a registration method (:class:`~depthgt.registration.frameset.Registration`).

    Attributes:
        T_j_to_t: (F-1, 4, 4) float64, neighbour j's camera points into the target camera.
        offsets: the frame offsets (``offsets[0] == 0`` is the target).
        neighbour_status: "ok" | "failed" per neighbour; ``neighbour_reasons`` the why
            ("" when ok).
        status, reason: overall "ok" | "failed" and reason.
        loss_curve: total training loss per iteration.
        pose_history: per iteration, per neighbour ``{"dt_m", "dr_deg"}`` change of
            T_j_to_t from the previous iteration.
        n_correspondences: per neighbour, target-pair matches with weight >=
            ``confident_weight`` at the final estimate.
        timings: seconds per phase.
        diagnostics: refinement cost, inlier fractions, condition numbers, chaining
            choices, poses before refinement.
        normals: (F, 3, H, W) the refinement's full-resolution normals of the members
            (:attr:`RefineResult.normals`; the GT renderer reuses them), or None. Not
            written to poses.json.
        estimated: False when the poses are the source's as they are (method
            ``given``): nothing was estimated, poses.json records the method alone.
    """

    T_j_to_t: torch.Tensor
    offsets: list[int]
    neighbour_status: list[str]
    neighbour_reasons: list[str]
    status: str
    reason: str
    loss_curve: list[float] = field(default_factory=list)
    pose_history: list[list[dict]] = field(default_factory=list)
    n_correspondences: list[int] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)
    normals: torch.Tensor | None = None
    estimated: bool = True

    def to_dict(self) -> dict:
        T = self.T_j_to_t.detach().cpu().numpy()
        return {
            "status": self.status,
            "reason": self.reason,
            "neighbours": [
                {
                    "offset": int(o),
                    "T_j_to_t": T[i].tolist(),
                    "status": self.neighbour_status[i],
                    "reason": self.neighbour_reasons[i],
                    "n_correspondences": int(self.n_correspondences[i]),
                }
                for i, o in enumerate(self.offsets[1:])
            ],
            "loss_curve": [float(x) for x in self.loss_curve],
            "pose_history": self.pose_history,
            "timings_s": {k: round(float(v), 4) for k, v in self.timings.items()},
            "diagnostics": self.diagnostics,
        }

    def to_json(self, indent: int | None = 1) -> str:
        """poses.json content: poses per neighbour, statuses, loss curve, timings."""
        return json.dumps(self.to_dict(), indent=indent)
