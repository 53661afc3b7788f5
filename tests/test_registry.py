"""The registry of methods and models agrees with the baselines, the training, the
tables and the settings (adding a method = one entry + its function)."""

from __future__ import annotations

from pathlib import Path

import pytest

from depthgt import registry
from depthgt.enhance.baselines import BASELINES
from depthgt.errors import ConfigError
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
    assert set(registry.MODELS) == registry.builders()
    for m in registry.learned().values():
        assert m.trains_on in registry.TRAINS_ON and m.settings_key in registry.METHODS


def test_tables_and_settings_take_names_from_the_registry():
    assert tables._ordered(["lapden", "zzz", "input", "rgf"]) == ["input", "rgf", "lapden", "zzz"]
    assert all(registry.label(n) == m.label for n, m in registry.METHODS.items())
    assert EvaluationSettings().methods == tuple(registry.METHODS)


def test_the_settings_take_method_and_model_names_from_the_registry():
    """No copy of the names: evaluation.methods and the enhance.models entries are
    checked against the registry (tests/test_settings.py: no config schema beside it)."""
    assert set(settings_from_config({}).enhance.models) == set(registry.learned())
    with pytest.raises(ConfigError, match="evaluation.methods: unknown method"):
        settings_from_config({"evaluation": {"methods": ["input", "bilateral"]}})
    with pytest.raises(ConfigError, match="unknown config key.*enhance.models.unet"):
        settings_from_config({"enhance": {"models": {"unet": {}}}})


@pytest.mark.parametrize("name", list(registry.MODELS))
def test_each_model_entry_builds_and_its_loss_reports_its_log_terms(name):
    """One entry per model holds builder, loss and log columns: the builder makes a
    network that maps depth to depth maps, and the loss reports exactly ``total`` and the
    entry's ``log_terms`` (the loss log's columns)."""
    import torch

    from depthgt.enhance.train import build_loss, build_model

    torch.manual_seed(0)
    params = registry.METHODS[name].model_params if name in registry.METHODS else {}
    model = build_model(name, params).eval()
    depth = 1.0 + torch.rand(2, 1, 32, 32)
    K = torch.tensor([[40.0, 0, 15.5], [0, 40.0, 15.5], [0, 0, 1]]).expand(2, 3, 3)
    batch = {"gt": depth + 0.01, "K": K, "depth": depth, "rgb": torch.rand(2, 3, 32, 32)}
    with torch.no_grad():
        outputs = model(depth)
    total, terms = build_loss(name)(outputs, batch)
    assert set(terms) == {"total", *registry.MODELS[name].log_terms}
    assert registry.log_columns(name) == (
        "epoch",
        "split",
        "total",
        *registry.MODELS[name].log_terms,
        "batches",
        "seconds",
    )
    assert float(total) == pytest.approx(terms["total"])


def test_a_loss_term_outside_the_log_columns_fails_loudly():
    """A loss term the model's entry does not list would be dropped from loss_log.csv
    without a word: the training stops instead, naming the term and the entry."""
    from depthgt.enhance.train import _log_row

    terms = {"total": 1.0, "depth": 0.5, "smooth": 0.5, "batches": 3, "seconds": 0.1}
    assert _log_row(0, "train", terms, "sdd")["smooth"] == "0.5"
    with pytest.raises(ValueError, match=r"model 'sdd'.*MODELS\['sdd'\]\.log_terms.*not logged: \['edge'\]"):
        _log_row(0, "train", {**terms, "edge": 0.1}, "sdd")
    with pytest.raises(ValueError, match=r"missing: \['smooth'\]"):
        _log_row(0, "val", {k: v for k, v in terms.items() if k != "smooth"}, "sdd")


def test_a_loss_without_its_total_term_is_named():
    """A loss whose terms leave out "total" gets through an epoch and is then named by
    the loss log's check (it was a KeyError in the progress bar)."""
    import torch

    from depthgt.enhance.train import _log_row, train_epoch
    from depthgt.settings import TrainSettings

    def loss(outputs, batch):
        d = (outputs[-1] - batch["gt"]).abs().mean()
        return d, {"depth": float(d.detach()), "smooth": 0.0}

    class Net(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.conv = torch.nn.Conv2d(1, 1, 3, padding=1)

        def forward(self, x):
            return [self.conv(x)]

    model = Net()
    data = [{"input": torch.rand(1, 8, 8), "gt": torch.rand(1, 8, 8)} for _ in range(4)]
    opt = torch.optim.SGD(model.parameters(), lr=0.0)
    terms = train_epoch(
        model,
        loss,
        opt,
        data,
        TrainSettings(model="sdd", batch_size=2, flips=False, progress=False),
        0,
        torch.device("cpu"),
    )
    with pytest.raises(ValueError, match=r"missing: \['total'\]"):
        _log_row(0, "train", terms, "sdd")


def test_model_entries_are_checked():
    with pytest.raises(ValueError, match="build must be 'module:function'"):
        registry.Model("x", build="depthgt.enhance.learned.SDDUNet", loss="a:b", log_terms=(), pair_cpu_ms=1.0)
    with pytest.raises(ValueError, match="without 'total'"):
        registry.Model("x", build="a:b", loss="a:b", log_terms=("total",), pair_cpu_ms=1.0)
    with pytest.raises(ValueError, match="pair_cpu_ms must be > 0"):
        registry.Model("x", build="a:b", loss="a:b", log_terms=(), pair_cpu_ms=0.0)
    with pytest.raises(ValueError, match="builder must be one of"):
        registry.Method("x", "X", "learned", baseline="learned", trains_on="depthgt", builder="unet")
