"""The one device choice of the project (config ``device``), used by the frame-set job,
the registration pretraining, the training and the evaluation of learned methods.

torch is imported inside the functions that need it: :func:`cuda_device_count` is
called when the workflow starts (``device: cuda`` checked before any job), where
importing torch would cost seconds per Snakemake start.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from typing import TYPE_CHECKING

from depthgt.errors import ConfigError

if TYPE_CHECKING:
    import torch

__all__ = ["resolve_device", "cuda_device_count", "check_device_available"]

_NO_CUDA = ("config key device: cuda was asked for but no CUDA device is available "
            "(use device: auto to fall back to the CPU)")


def resolve_device(name: str = "auto") -> "torch.device":
    """``auto`` -> CUDA when available, else CPU; ``cpu``; ``cuda`` (an error when no
    CUDA device is available, rather than a silent fall-back to CPU).

    >>> resolve_device("cpu")
    device(type='cpu')
    """
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    if name == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(_NO_CUDA)
        return torch.device("cuda")
    raise ConfigError(f"config key device: must be auto, cpu or cuda, got {name!r}")


def cuda_device_count() -> int:
    """Number of CUDA devices the driver reports, without importing torch.

    Asks the CUDA driver library (``libcuda``) directly through ctypes: no Python
    package exposes a torch-free device count, and torch's import takes seconds. 0 when
    the driver is not installed or fails to initialise (no GPU, no permission).

    >>> cuda_device_count() >= 0
    True
    """
    name = ctypes.util.find_library("cuda") or "libcuda.so.1"
    try:
        lib = ctypes.CDLL(name)
    except OSError:
        return 0
    count = ctypes.c_int(0)
    if lib.cuInit(0) != 0 or lib.cuDeviceGetCount(ctypes.byref(count)) != 0:
        return 0
    return int(count.value)


def check_device_available(name: str) -> None:
    """Raise :class:`ConfigError` at workflow start when ``device: cuda`` is asked for
    and this machine has no CUDA device (local runs; on a cluster the submitting node may
    have none, and the job checks again with :func:`resolve_device` before any work).

    >>> check_device_available("cpu")
    """
    if name == "cuda" and cuda_device_count() == 0:
        raise ConfigError(_NO_CUDA)
