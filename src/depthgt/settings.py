"""Every stage's settings, built and checked from the config, and the table of the config
sections each workflow stage reads (torch-free).

Each stage's settings live beside the stage, one frozen dataclass per config section
(:func:`depthgt.settings_base.section`: its fields are the section's keys, their defaults
the config's defaults, a ``Literal`` field's type its choices):

================  ===================================================  =========================================
config            settings                                             module
================  ===================================================  =========================================
``sources[]``     :class:`SourceSettings`                              :mod:`depthgt.sources.settings`
``frameset``      :class:`FrameSetSettings`                            :mod:`depthgt.gt.settings`
``split``         :class:`SplitSettings`                               :mod:`depthgt.gt.settings`
``patches``       :class:`PatchSettings`                               :mod:`depthgt.gt.settings`
``render``        :class:`RenderSettings`                              :mod:`depthgt.gt.render.settings`
``registration``  :class:`RegistrationSettings` (its parts, presets)   :mod:`depthgt.registration.settings`
``enhance``       :class:`EnhanceSettings` (:class:`TrainSettings`)    :mod:`depthgt.enhance.settings`
``enhance.rde``   :class:`RDESettings`                                 :mod:`depthgt.gt.settings`
``evaluation``    :class:`EvaluationSettings`                          :mod:`depthgt.eval.settings`
``dataset``       :class:`DatasetSettings`                             :mod:`depthgt.gt.settings`
================  ===================================================  =========================================

This module is the builder: :func:`settings_from_config` makes every section's settings
(:data:`SECTIONS`) and :class:`Settings` holds them with the top-level ``seed``,
``device`` and ``resize``. It is the one check of a config: the Snakefile calls it when
the workflow starts, so that every section is checked before any job runs, and every job
calls it again on the sections its rule passes (:data:`STAGES`, :func:`stage_settings`).
Components never see the config dict: they take the dataclass of their stage. A bad
config raises :class:`~depthgt.errors.ConfigError` naming the key at fault
(``patches.size``, ``registration.refine_settings.iters``), every section's problem at once.

>>> s = settings_from_config({"resize": 128, "patches": {"size": 64}})
>>> s.size_hw, s.patches.count, s.registration.method
((128, 128), 6, 'given')
"""

from __future__ import annotations

import copy
import dataclasses
import json
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from functools import partial
from typing import Any

from depthgt.device import Device
from depthgt.enhance.settings import EnhanceSettings, TrainSettings, enhance_settings
from depthgt.errors import ConfigError
from depthgt.eval.settings import EvaluationSettings
from depthgt.gt.render.settings import RenderSettings
from depthgt.gt.settings import SPLITS, DatasetSettings, FrameSetSettings, PatchSettings, RDESettings, SplitSettings
from depthgt.registration.settings import (
    REGISTRATION_KEYS,
    REGISTRATION_PRESETS,
    CheckSettings,
    EncoderSettings,
    MatchingSettings,
    PretrainSettings,
    RefineSettings,
    RegistrationSettings,
    TrainingSettings,
    registration_settings,
)
from depthgt.settings_base import build, check_keys, fail, require, section
from depthgt.sources.settings import SourceSettings, check_scene_name

__all__ = [
    "Settings",
    "SECTIONS",
    "TOP_LEVEL_KEYS",
    "settings_from_config",
    "check_workflow",
    "Stage",
    "STAGES",
    "stage_config",
    "stage_settings",
    "WRITTEN_DEFAULTS",
    "config_with_defaults",
    "check_scene_name",
    # every stage's settings, from their modules (the table above)
    "SPLITS",
    "SourceSettings",
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
    "REGISTRATION_PRESETS",
    "RegistrationSettings",
    "registration_settings",
    "TrainSettings",
    "RDESettings",
    "EnhanceSettings",
    "EvaluationSettings",
    "DatasetSettings",
]

# Upper bound of the working resolution (a typo such as resize: 25600 would otherwise be
# found by the kernel's OOM killer, hours into a run).
MAX_RESIZE = 4096


@section("")
class Settings:
    """The settings of every stage, from :func:`settings_from_config`.

    Attributes:
        seed: seed of every random choice (crops, splits, registration, training).
        device: "auto" (CUDA when available, else CPU), "cpu" or "cuda"; see
            :func:`depthgt.device.resolve_device`.
        resize: working resolution (square, pixels).
    """

    seed: int = 0
    device: Device = "auto"
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
        require(self.seed >= 0, "seed", f"must be >= 0, got {self.seed}")
        require(16 <= self.resize <= MAX_RESIZE, "resize", f"must be in [16, {MAX_RESIZE}], got {self.resize}")
        names = [s.name for s in self.sources]
        dup = sorted({n for n in names if names.count(n) > 1})
        require(not dup, "sources", f"the name(s) {dup} are used twice; names must be unique")

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


def _sources(value: Any, top: Settings) -> tuple[SourceSettings, ...]:
    if value is None:
        return ()
    if not isinstance(value, list):
        fail("sources", f"must be a list, got {type(value).__name__}")
    return tuple(build(SourceSettings, s, f"sources[{i}]") for i, s in enumerate(value))


def _registration(value: Any, top: Settings) -> RegistrationSettings:
    return registration_settings(value)


def _enhance(value: Any, top: Settings) -> EnhanceSettings:
    return enhance_settings(value, top.seed, top.device)


#: The config's sections: the settings class each is built as (:func:`build`), or the
#: function that builds it from the section's value (None when the section is absent:
#: its defaults apply) and the top-level ``seed``, ``device`` and ``resize``
#: (:class:`Settings`, the trainings' defaults). A new section is one entry here and one
#: field of :class:`Settings`.
SECTIONS: dict[str, type | Callable[[Any, Settings], Any]] = {
    "sources": _sources,
    "frameset": FrameSetSettings,
    "split": SplitSettings,
    "patches": PatchSettings,
    "render": RenderSettings,
    "registration": _registration,
    "enhance": _enhance,
    "evaluation": EvaluationSettings,
    "dataset": DatasetSettings,
}


def _section(name: str, value: Any, top: Settings) -> Any:
    make = SECTIONS[name]
    return build(make, value, name) if isinstance(make, type) else make(value, top)


#: The config's top-level keys: the fields of :class:`Settings`, the sections and the
#: top-level values.
TOP_LEVEL_KEYS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(Settings))


def settings_from_config(config: Mapping[str, Any], sections: tuple[str, ...] | None = None) -> Settings:
    """Every stage's settings from a config mapping (the config of a workflow, or the
    sections of it that a rule passes to its job; missing sections take their defaults).

    Args:
        sections: the top-level sections the caller reads (a stage's,
            :func:`stage_settings`): a check between two sections runs only when it
            reads both (the RDE job reads ``resize`` and not ``patches``, whose default
            size need not fit a small ``resize``); None: every check.

    Raises:
        ConfigError: an unknown key (at any level), a bad value or an inconsistency
            between sections (``patches.size > resize``); the message names the key, and
            every section's problem when several sections have one.
    """
    if not isinstance(config, Mapping):
        raise ConfigError(f"the configuration must be a mapping, got {type(config).__name__}")
    errors: list[ConfigError] = []

    def checked(make: Callable[[], Any]) -> Any:
        try:
            return make()
        except ConfigError as err:
            errors.append(err)
            return None

    checked(lambda: check_keys(config, TOP_LEVEL_KEYS, ""))
    values = {k: v for k, v in config.items() if k in TOP_LEVEL_KEYS and k not in SECTIONS}
    top = checked(lambda: build(Settings, values, "")) or Settings()
    built = {name: checked(partial(_section, name, config.get(name), top)) for name in SECTIONS}
    settings = None if errors else checked(lambda: dataclasses.replace(top, **built))
    if errors:
        if len(errors) == 1:
            raise errors[0]
        raise ConfigError("invalid configuration:\n" + "\n".join(f"  {err}" for err in errors))
    if sections is None or {"patches", "resize"} <= set(sections):
        require(
            settings.patches.size <= settings.resize,
            "patches.size",
            f"{settings.patches.size} does not fit in the {settings.resize}x{settings.resize} working resolution "
            "(resize)",
        )
    return settings


def check_workflow(settings: Settings) -> None:
    """Checks of a whole workflow's settings that no single section decides (run when
    the workflow starts, before any job; a job gets only its sections).

    * the workflow builds from at least one source (a library call may have none);
    * a registration method that starts from the pretrained encoder
      (:attr:`~depthgt.registration.methods.RegistrationMethod.pretrained_encoder`:
      ``overfit``) pretrains it on frame sets of the ``train`` split
      (``registration.pretrain.framesets`` > 0): some source must put frame sets there
      (``split: train`` or ``auto``), or the pretraining job would fail after the run
      started.

    >>> check_workflow(settings_from_config({"registration": {"method": "overfit"},
    ...     "sources": [{"name": "t", "kind": "synthetic", "split": "test"}]}))
    Traceback (most recent call last):
    ...
    depthgt.errors.ConfigError: config key registration.pretrain.framesets: ...
    """
    require(
        len(settings.sources) > 0,
        "sources",
        "the workflow builds from at least one source: a list of {name, kind, root, scenes, split, options} "
        "(docs/configuration.md)",
    )
    reg = settings.registration
    if reg.method_entry.pretrained_encoder and reg.pretrain.framesets > 0:
        if not any(s.split in ("train", "auto") for s in settings.sources):
            splits = ", ".join(f"sources[{i}].split: {s.split}" for i, s in enumerate(settings.sources))
            fail(
                "registration.pretrain.framesets",
                f"{reg.pretrain.framesets} frame sets of the train split pretrain the registration's encoder "
                f"(registration.method: {reg.method}), but no source puts frame sets in the train split ({splits}); "
                "give a source split: train or auto, or set registration.pretrain.framesets: 0 (random initial "
                "weights)",
            )


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


# --------------------------------------------------------------------------- the config's defaults

#: The defaults the workflow writes into its config before the rules read it (the rules'
#: ``config`` params and the source entries that index.json and the dataset card record):
#: under each path (``""`` the top level, ``sources[]`` every source), these keys in this
#: order, each with the value :func:`settings_from_config` gives an empty config; a path
#: of this table is a section, written as ``{}`` and then filled with its own keys. The
#: list is the one the config's JSON schema filled in before the settings became the one
#: check of the config, kept as it was: a build made before keeps its params (Snakemake's
#: rerun trigger) and its records. A key added later is not written: an older build's
#: params stay as they were, and its default applies either way.
WRITTEN_DEFAULTS: dict[str, tuple[str, ...]] = {
    "": ("seed", "device", "frameset", "resize", "registration", "render", "patches", "split", "enhance", "evaluation"),
    "sources[]": ("root", "scenes", "split", "options"),
    "frameset": (
        "neighbours",
        "stride",
        "target_step",
        "batch_size",
        "selection",
        "coverage_span",
        "coverage_views",
        "coverage_max_baseline_m",
        "coverage_max_angle_deg",
        "coverage_min_fill_px",
        "coverage_mixed_margin_px",
        "coverage_mixed_jump_rel",
    ),
    "registration": ("method", "preset", "on_failure", "pretrain"),
    "registration.pretrain": ("framesets", "epochs"),
    "render": (),
    "patches": ("count", "size", "max_missing", "filter_on", "max_gt_sigma_m"),
    "split": ("val_fraction", "block_frames"),
    "enhance": ("train", "models", "rde"),
    "enhance.train": (),
    "enhance.models": (),
    "enhance.rde": ("voxel_m", "trunc_voxels", "frame_step", "max_depth_m", "max_voxels", "backend", "max_missing"),
    "evaluation": ("split", "figure_frames_per_scene", "rde_synthetic_test"),
}


def config_with_defaults(config: Mapping[str, Any]) -> dict[str, Any]:
    """``config`` (a valid one: checked by :func:`settings_from_config`) with the
    defaults of :data:`WRITTEN_DEFAULTS` written in where it has no value: a key the
    config gives keeps its place and value, the others follow in the table's order.

    >>> config_with_defaults({"sources": [{"name": "s", "kind": "synthetic"}], "split": {"block_frames": 9}})["split"]
    {'block_frames': 9, 'val_fraction': 0.1}
    """
    top = settings_from_config({})
    defaults = {
        **top.doc(*(k for k in TOP_LEVEL_KEYS if k != "sources")),
        "sources[]": {
            f.name: f.default if f.default_factory is dataclasses.MISSING else f.default_factory()
            for f in dataclasses.fields(SourceSettings)
            if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING
        },
    }
    out = copy.deepcopy(dict(config))
    _write_defaults(out, "", defaults)
    for source in out.get("sources") or []:
        _write_defaults(source, "sources[]", defaults["sources[]"])
    return out


def _write_defaults(node: dict[str, Any], path: str, defaults: Mapping[str, Any]) -> None:
    keys = WRITTEN_DEFAULTS[path]
    for key in keys:
        child = f"{path}.{key}" if path else key
        node.setdefault(key, {} if child in WRITTEN_DEFAULTS else copy.deepcopy(defaults[key]))
    for key in keys:
        child = f"{path}.{key}" if path else key
        if child in WRITTEN_DEFAULTS and isinstance(node[key], dict):
            _write_defaults(node[key], child, defaults.get(key) or {})
