"""The one device choice of the project (config ``device``), used by the frame-set job,
the registration pretraining, the training and the evaluation of learned methods."""

from __future__ import annotations

import torch

from depthgt.errors import ConfigError

__all__ = ["resolve_device"]


def resolve_device(name: str = "auto") -> torch.device:
    """``auto`` -> CUDA when available, else CPU; ``cpu``; ``cuda`` (an error when no
    CUDA device is available, rather than a silent fall-back to CPU).

    >>> resolve_device("cpu")
    device(type='cpu')
    """
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    if name == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError("config key device: cuda was asked for but no CUDA device is available "
                              "(use device: auto to fall back to the CPU)")
        return torch.device("cuda")
    raise ConfigError(f"config key device: must be auto, cpu or cuda, got {name!r}")
