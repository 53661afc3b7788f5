"""The trainings' settings (config ``enhance``: ``train`` shared by every model, one
``models`` entry per trainable model of :mod:`depthgt.registry`, and ``rde``), torch-free:
:mod:`depthgt.settings` builds them when the workflow starts."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, field
from typing import Any, Literal

from depthgt import registry
from depthgt.device import Device
from depthgt.errors import ConfigError
from depthgt.gt.settings import RDESettings
from depthgt.settings_base import build, check_keys, fail, mapping, require, section

__all__ = ["TrainSettings", "EnhanceSettings", "enhance_settings", "MAX_TRAIN_BATCH"]

MAX_TRAIN_BATCH = 4096  # patch pairs per training step (enhance.train.batch_size)
MAX_INPUT_HOLES = 64  # enhance.train.input_holes: discs cut per training patch
MAX_INPUT_HOLE_PX = 64  # enhance.train.input_hole_max_px: their largest radius, pixels


@section("train")
class TrainSettings:
    """Settings of one training run (:func:`depthgt.enhance.train.train`).

    Attributes:
        model: builder name (a learned method's ``builder`` in :mod:`depthgt.registry`).
        model_params: keyword arguments of the builder (``lapden``: ``preset`` and
            LapDENConfig overrides).
        loss_params: keyword arguments of the model's loss (``lapden``: LossConfig fields).
        epochs: number of epochs; batch_size: patches per step; lr: Adam learning rate
            (the default config sets them in ``enhance.train``, docs/configuration.md).
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
    lr_schedule: Literal["constant", "cosine"] = "constant"
    weight_decay: float = 0.0
    seed: int = 0
    flips: bool = True
    input_holes: int = 0
    input_hole_min_px: int = 4
    input_hole_max_px: int = 16
    max_batches_per_epoch: int | None = None
    device: Device = "auto"
    progress: bool = True

    def __post_init__(self):
        builders = registry.builders()
        require(self.model in builders, "train.model", f"unknown model {self.model!r}; known: {sorted(builders)}")
        for key in ("epochs", "batch_size"):
            require(int(getattr(self, key)) >= 1, f"train.{key}", f"must be >= 1, got {getattr(self, key)}")
        require(
            self.batch_size <= MAX_TRAIN_BATCH,
            "train.batch_size",
            f"must be <= {MAX_TRAIN_BATCH}, got {self.batch_size}",
        )
        require(self.lr > 0, "train.lr", f"must be > 0, got {self.lr}")
        require(
            isinstance(self.input_holes, int) and 0 <= self.input_holes <= MAX_INPUT_HOLES,
            "train.input_holes",
            f"must be an integer in 0..{MAX_INPUT_HOLES}, got {self.input_holes!r}",
        )
        require(
            isinstance(self.input_hole_min_px, int)
            and isinstance(self.input_hole_max_px, int)
            and 1 <= self.input_hole_min_px <= self.input_hole_max_px <= MAX_INPUT_HOLE_PX,
            "train.input_hole_min_px/input_hole_max_px",
            f"must be integers with 1 <= min <= max <= {MAX_INPUT_HOLE_PX}, got {self.input_hole_min_px!r}, "
            f"{self.input_hole_max_px!r}",
        )
        require(
            self.max_batches_per_epoch is None or self.max_batches_per_epoch >= 1,
            "train.max_batches_per_epoch",
            f"must be >= 1 or null, got {self.max_batches_per_epoch}",
        )
        require(
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


@section("enhance")
class EnhanceSettings:
    """Config ``enhance``: the resolved training settings of every trainable model of
    the registry (``enhance.train`` overridden by ``enhance.models[settings_key]``) and
    the RDE reconstruction."""

    models: dict[str, TrainSettings] = field(default_factory=dict)
    rde: RDESettings = RDESettings()


def enhance_settings(section: Mapping[str, Any] | None, seed: int, device: str) -> EnhanceSettings:
    """:class:`EnhanceSettings` of the config section ``enhance``: each trainable model's
    :class:`TrainSettings` is ``enhance.train`` overridden by its ``enhance.models`` entry,
    with the top-level ``seed`` and ``device`` unless those set them."""
    section = mapping(section, "enhance")
    check_keys(section, ("train", "models", "rde"), "enhance")
    shared = mapping(section.get("train"), "enhance.train")
    per_model = mapping(section.get("models"), "enhance.models")
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
        entry = mapping(per_model.get(spec.settings_key), f"enhance.models.{spec.settings_key}")
        if entry.get("model", spec.builder) != spec.builder:
            fail(
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
