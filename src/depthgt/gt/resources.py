"""What a frame-set batch job asks the scheduler for (the workflow's ``frameset_batch``
rule): its memory, from the registration method's cost of one frame set
(:class:`~depthgt.registration.methods.JobCost`), the frame-set selection and the
device.

Torch-free (the settings only): the workflow computes it while it parses. The batch job
builds one frame set at a time on the CPU and :data:`GPU_GROUP` at once on a GPU
(:func:`depthgt.gt.batch.build_batch`).
"""

from __future__ import annotations

import math

from depthgt.settings import Settings

__all__ = [
    "GPU_GROUP",
    "COVERAGE_MEM_MB",
    "FRAME_HOST_BYTES_PER_PX",
    "OUTPUT_HOST_BYTES_PER_PX",
    "may_use_gpu",
    "group_host_mb",
    "frameset_mem_mb",
]

#: frame sets rendered together on a GPU (about 0.3 GB of device memory each at 256x256)
GPU_GROUP = 16

#: a batch job with ``frameset.selection: coverage`` on the CPU: the batch keeps the
#: span's frames and the candidates' clouds; measured 1.7 GB peak RSS (7-Scenes, given and
#: refine, bench_pipeline.py --selection coverage), declared with headroom
COVERAGE_MEM_MB = 4000

#: host bytes per pixel of one member frame of a frame set of a GPU group, a bound from the
#: data's sizes: colour (float32 x 3 = 12; the host holds it as uint8, 3), raw depth and
#: clean truth (float32, 8), and the per-frame results the batch's frame cache keeps
#: (points and normals, float32 x 3 each = 24; sigma, 4) -- 48, each counted as if on the
#: host although on a GPU the float copies and the frame cache's results are on the device
FRAME_HOST_BYTES_PER_PX = 48
#: host bytes per pixel of one frame set's outputs waiting to be written: gt.exr's
#: channels (float32 x 4 = 16), input.exr's depth and truth (8), the colour (uint8 x 3),
#: and the EXR and WebP encoders' buffers as large again (2 x 27 = 54), rounded up
OUTPUT_HOST_BYTES_PER_PX = 64


def may_use_gpu(device: str) -> bool:
    """Whether a job with config ``device`` may build on a GPU: ``cuda``, and ``auto``
    (a GPU wherever the job runs on a node that has one).

    >>> may_use_gpu("cpu"), may_use_gpu("auto"), may_use_gpu("cuda")
    (False, True, True)
    """
    return device != "cpu"


def group_host_mb(settings: Settings) -> int:
    """Host memory (MB, 10^6 bytes) that a GPU group adds to a batch job over one frame
    set at a time: the other :data:`GPU_GROUP` - 1 frame sets of the group held together,
    each with its members' frames (:data:`FRAME_HOST_BYTES_PER_PX`, ``2 * neighbours + 1``
    of them, and ``target_step`` more: the frames the batch's caches keep for each set of
    the group, :func:`depthgt.gt.batch.frames_kept`) and its outputs (:data:`OUTPUT_HOST_BYTES_PER_PX`)
    at the working resolution. With ``frameset.selection: coverage`` a group's sets take
    their views one set at a time (depthgt.gt.build.process_framesets), from the frames the
    batch keeps anyway: the one-set figure holds them.

    A bound from the data's sizes, not a measurement: the peak RSS of a GPU batch job has
    not been measured, nor the host memory of the CUDA runtime itself (its libraries and
    context), which the one-set figure's headroom has to hold.

    >>> from depthgt.settings import Settings
    >>> group_host_mb(Settings(device="cuda"))  # 256x256, 3 neighbours each side
    441
    """
    h, w = settings.size_hw
    frames = 2 * settings.frameset.neighbours + 1 + settings.frameset.target_step
    per_set = (frames * FRAME_HOST_BYTES_PER_PX + OUTPUT_HOST_BYTES_PER_PX) * h * w
    return math.ceil((GPU_GROUP - 1) * per_set / 1e6)


def frameset_mem_mb(settings: Settings) -> int:
    """The ``mem_mb`` of a frame-set batch job: one frame set's memory (the registration
    method's :class:`~depthgt.registration.methods.JobCost`; at least
    :data:`COVERAGE_MEM_MB` with ``frameset.selection: coverage``), plus
    :func:`group_host_mb` when the device may be a GPU (:func:`may_use_gpu`). A job
    handles its frame sets in turn (in groups on a GPU): the memory does not grow with
    ``frameset.batch_size``.

    >>> from depthgt.settings import Settings
    >>> frameset_mem_mb(Settings(device="cpu")), frameset_mem_mb(Settings(device="cuda"))
    (2000, 2441)
    """
    one = settings.registration.job_cost.mem_mb
    if settings.frameset.selection == "coverage":
        one = max(one, COVERAGE_MEM_MB)
    return one + group_host_mb(settings) if may_use_gpu(settings.device) else one
