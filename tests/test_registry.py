"""The registry of methods and models agrees with the baselines, the training, the
tables, the settings and the config schema (adding a method = one entry + its function)."""

from __future__ import annotations

from pathlib import Path

import yaml

from depthgt import registry
from depthgt.enhance.baselines import BASELINES
from depthgt.enhance.train import MODELS
from depthgt.eval import tables
from depthgt.settings import EvaluationSettings, settings_from_config

REPO = Path(__file__).resolve().parents[1]


def test_every_method_runs_through_a_registered_baseline():
    for m in registry.METHODS.values():
        assert m.baseline in BASELINES, m
        if m.kind in ("input", "filter"):
            assert m.baseline == m.name  # a filter baseline is registered under the method's name
        else:
            assert m.baseline == "learned"
    assert set(BASELINES) - {"learned"} == {m.name for m in registry.METHODS.values() if m.kind != "learned"}


def test_training_builders_are_the_registry_builders():
    assert set(MODELS) == registry.builders()
    for m in registry.learned().values():
        assert m.trains_on in registry.TRAINS_ON and m.settings_key in registry.METHODS


def test_tables_and_settings_take_names_from_the_registry():
    assert tables._ordered(["lapden", "zzz", "input", "rgf"]) == ["input", "rgf", "lapden", "zzz"]
    assert all(registry.label(n) == m.label for n, m in registry.METHODS.items())
    assert EvaluationSettings().methods == tuple(registry.METHODS)


def test_schema_has_no_copy_of_the_method_names():
    schema = yaml.safe_load((REPO / "workflow/schemas/config.schema.yaml").read_text())
    methods = schema["properties"]["evaluation"]["properties"]["methods"]
    assert "enum" not in methods["items"] and "default" not in methods
    models = schema["properties"]["enhance"]["properties"]["models"]
    assert "properties" not in models  # per-model entries are checked against the registry by the settings
    assert set(settings_from_config({}).enhance.models) == set(registry.learned())
