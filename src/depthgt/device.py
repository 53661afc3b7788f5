"""The one device choice of the project (config ``device``), used by the frame-set job,
the registration pretraining, the training and the evaluation of learned methods.

torch is imported inside the functions that need it: :func:`cuda_device_count` is
called when the workflow starts (``device: cuda`` checked before any job), where
importing torch would cost seconds per Snakemake start.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Literal, get_args

from depthgt.errors import ConfigError

if TYPE_CHECKING:
    import torch

__all__ = [
    "Device",
    "DEVICES",
    "resolve_device",
    "cuda_device_count",
    "check_device_available",
    "keep_freed_memory",
    "plain_cpu_convolutions",
]

#: The device choices (config ``device``, ``enhance.train.device``).
Device = Literal["auto", "cpu", "cuda"]
DEVICES: tuple[str, ...] = get_args(Device)

_NO_CUDA = (
    "config key device: cuda was asked for but no CUDA device is available (use device: auto to fall back to the CPU)"
)


def resolve_device(name: str = "auto") -> torch.device:
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
    raise ConfigError(f"config key device: must be one of {', '.join(DEVICES)}, got {name!r}")


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


#: glibc mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def keep_freed_memory(max_block_mib: int = 32, trim_mib: int = 1024) -> bool:
    """Let glibc's malloc keep freed blocks of up to ``max_block_mib`` in the heap
    instead of handing them back to the system (up to ``trim_mib`` unused at its top).

    The frame-set job allocates and frees tensors of tens of megabytes (the renderer's
    ~2 million candidates) many times per frame set. By default glibc maps each block
    over 128 KiB afresh and unmaps it when freed, so every allocation page-faults anew:
    measured on the 7-Scenes fixture, 0.23 s of system time per frame set (126,000 minor
    faults) on top of 0.91 s of user time; with this, 0.002 s. The results are the same; the process keeps its peak memory instead of
    returning it between frame sets. Called by the frame-set batch job, the training and
    the evaluation jobs (each a process of its own; a training step of LapDEN's default
    preset page-faulted 23,000 times, 44 ms of system time on 0.33 s of user time, without
    it). Written by hand: no library sets malloc's thresholds (glibc's ``mallopt``, by
    ctypes). Elsewhere (macOS, musl) nothing happens.

    Returns:
        whether both thresholds were set.
    """
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, int(max_block_mib) << 20) == 1
    return ok and mallopt(_M_TRIM_THRESHOLD, int(trim_mib) << 20) == 1


@contextmanager
def plain_cpu_convolutions() -> Iterator[None]:
    """Run the CPU convolutions inside without oneDNN (mkldnn), torch's own kernels.

    For the 3x3 gradient filters of one or two output channels that kornia applies to
    depth and grey images (:func:`kornia.geometry.depth.depth_to_normals`,
    :func:`kornia.filters.spatial_gradient`), oneDNN is ~8x slower on one thread than
    torch's plain convolution: measured on 7 images of 256x256, 63 ms against 7.7 ms for
    ``spatial_gradient``, 86 ms against 32 ms for ``depth_to_normals`` (the results agree
    to float rounding, 1.5e-7). The networks' convolutions (many channels) keep oneDNN:
    this is only entered around those filters. It sets torch's global flag, so it is not
    for threads running convolutions side by side (the jobs run one frame set at a
    time). GPU tensors are not affected.
    """
    import torch

    before = torch.backends.mkldnn.enabled
    torch.backends.mkldnn.enabled = False
    try:
        yield
    finally:
        torch.backends.mkldnn.enabled = before
