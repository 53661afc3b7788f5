"""The registration methods by their ``registration.method`` name: one
:class:`RegistrationMethod` entry each, with what the settings, the workflow's rules and
the GT build ask of a method (torch-free: an entry names its function, imported when it
is first called; :mod:`depthgt.settings` checks the config's name against this table when
the workflow starts).

Adding a method = its module in ``registration/`` with one
:class:`~depthgt.registration.frameset.Registration` function + one entry here
(docs/development.md).
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

__all__ = ["JobCost", "RegistrationMethod", "METHODS"]


@dataclass(frozen=True)
class JobCost:
    """What one frame set costs a frame-set job, as its rule declares it to the
    scheduler: peak memory (MB, with headroom) and CPU seconds on one core."""

    mem_mb: int
    cpu_s: int


@dataclass(frozen=True)
class RegistrationMethod:
    """One registration method.

    Attributes:
        name: its ``registration.method`` name.
        register: ``"module:function"``, a
            :class:`~depthgt.registration.frameset.Registration`; calling the entry calls
            it (imported then, and looked up at every call, so that a test can replace it).
        uses_source_poses: it starts from the source's poses: a frame set's members need
            usable poses (a source whose poses are optional is opened requiring them),
            and coverage views are registered by the method itself.
        pretrained_encoder: it starts from the encoder the rule ``pretrain_registration``
            pretrains (``registration.pretrain``), an input of every frame-set job.
        cost: a frame set's :class:`JobCost` (the frame-set rule's ``mem_mb`` and
            ``runtime``); ``preset_cost``: the cost under a ``registration.preset`` that
            changes it.
        together: ``"module:function"`` registering several frame sets of one camera at
            once, ``(datas, offsets, settings) -> [RegistrationResult]`` with one result
            per set as ``register`` gives it (what a GPU batch uses:
            :func:`~depthgt.registration.align.align_many`), or None.
    """

    name: str
    register: str
    uses_source_poses: bool
    pretrained_encoder: bool = False
    cost: JobCost = JobCost(mem_mb=2000, cpu_s=60)
    preset_cost: Mapping[str, JobCost] = field(default_factory=dict)
    together: str | None = None

    def __post_init__(self):
        for key, value in (("register", self.register), ("together", self.together)):
            if value is not None and value.count(":") != 1:
                raise ValueError(f"registration method {self.name!r}: {key} must be 'module:function', got {value!r}")

    def __call__(self, *args: Any, **kwargs: Any):
        module, function = self.register.split(":")
        return getattr(importlib.import_module(module), function)(*args, **kwargs)

    def register_together(self, *args: Any, **kwargs: Any):
        """Call ``together`` (the method registers several frame sets at once)."""
        if self.together is None:
            raise ValueError(f"registration method {self.name!r} registers one frame set at a time")
        module, function = self.together.split(":")
        return getattr(importlib.import_module(module), function)(*args, **kwargs)

    def job_cost(self, preset: str | None) -> JobCost:
        """The cost of a frame set under the preset ``preset``."""
        return self.preset_cost.get(preset, self.cost) if preset is not None else self.cost


# Costs: peak RSS (benchmarks/*.tsv, max_rss) and CPU time on one core at 256x256: the
# source's poses 0.6 GB / 5 s (7-Scenes), overfit fast 0.7 GB / 9 s, overfit paper
# 5.9 GB / 830 s (issue 9); declared with headroom.
METHODS: dict[str, RegistrationMethod] = {
    m.name: m
    for m in (
        # the source's poses as they are
        RegistrationMethod("given", "depthgt.registration.given:register_given", uses_source_poses=True),
        # the source's poses refined on the frame set (joint SE(3) refinement)
        RegistrationMethod(
            "refine",
            "depthgt.registration.local:register_refine",
            uses_source_poses=True,
            together="depthgt.registration.local:refine_source_poses_many",
        ),
        # the paper's registration (Sec. 3.2): no poses needed
        RegistrationMethod(
            "overfit",
            "depthgt.registration.overfit:register_overfit",
            uses_source_poses=False,
            pretrained_encoder=True,
            cost=JobCost(mem_mb=8000, cpu_s=1800),
            preset_cost={"fast": JobCost(mem_mb=2000, cpu_s=60)},
        ),
    )
}
