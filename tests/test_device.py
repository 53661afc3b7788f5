"""The one device choice (config ``device``)."""

import pytest
import torch

from depthgt.device import resolve_device
from depthgt.errors import ConfigError


def test_auto_cpu_and_cuda(monkeypatch):
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    with pytest.raises(ConfigError, match="no CUDA device"):
        resolve_device("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("cuda") == torch.device("cuda")
    with pytest.raises(ConfigError, match="device"):
        resolve_device("tpu")
