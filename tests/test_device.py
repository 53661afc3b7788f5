"""The one device choice (config ``device``)."""

import math
import re
import subprocess
import sys

import pytest
import torch
from conftest import make_workdir, snakemake, synthetic_source

from depthgt.device import resolve_device
from depthgt.errors import ConfigError
from depthgt.gt import batch, resources
from depthgt.settings import settings_from_config


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


_FAULTS = """
import resource, sys
import numpy as np
from depthgt.device import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "keep" else None
np.ones(1 << 22)  # first use of the heap
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    blocks = [np.ones(2 << 20) for _ in range(6)]  # 6 x 16 MiB, allocated and freed again
    del blocks
print(applied, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc thresholds")
def test_keep_freed_memory_stops_the_page_faults_of_large_blocks():
    """Blocks of tens of MiB freed and allocated again (the renderer's candidates, per
    frame set) page-fault anew each time under glibc's defaults; kept in the heap they do
    not (the results are the same: the frame-set job just spends no system time)."""
    runs = {
        mode: subprocess.run(
            [sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True, check=True
        ).stdout.split()
        for mode in ("default", "keep")
    }
    if runs["keep"][0] != "True":
        pytest.skip("not glibc: mallopt is not available")
    default, kept = int(runs["default"][1]), int(runs["keep"][1])
    assert default > 10 * 2000  # pages of 4 KiB faulted again in every round
    assert kept < default / 5


def test_plain_cpu_convolutions_agree_with_onednn_and_restore_the_flag():
    """kornia's gradient filters give the same normals without oneDNN (to float rounding),
    and the global flag is back afterwards, also after an error."""
    import torch
    from kornia.geometry.depth import depth_to_normals

    from depthgt.device import plain_cpu_convolutions

    g = torch.Generator().manual_seed(0)
    depth = 1.0 + torch.rand(3, 1, 40, 50, generator=g)
    K = torch.tensor([[40.0, 0, 25], [0, 40, 20], [0, 0, 1]]).expand(3, 3, 3)
    before = torch.backends.mkldnn.enabled
    with plain_cpu_convolutions():
        assert not torch.backends.mkldnn.enabled
        plain = depth_to_normals(depth, K)
    assert torch.backends.mkldnn.enabled == before
    torch.testing.assert_close(plain, depth_to_normals(depth, K), rtol=1e-5, atol=1e-6)
    with pytest.raises(RuntimeError), plain_cpu_convolutions():
        raise RuntimeError("inside")
    assert torch.backends.mkldnn.enabled == before


def _frameset_mem_mb(config: dict) -> int:
    return resources.frameset_mem_mb(settings_from_config(config))


@pytest.mark.parametrize("extra", [{}, {"frameset": {"selection": "coverage"}}, {"registration": {"preset": "paper"}}])
def test_a_gpu_batch_declares_the_memory_of_its_group(extra):
    """On a GPU a batch job builds GPU_GROUP frame sets together, held in host memory
    together: device cuda (and auto, a GPU where the node has one) declares the group's
    frames and outputs on top of one frame set's memory; device cpu declares one set's,
    as before (the method's JobCost; 4000 MB at least with coverage)."""
    assert batch.GPU_GROUP is resources.GPU_GROUP  # the group the job builds is the one it is sized by
    base = {"sources": [synthetic_source("syn", ["room_000"], "train", 20, 80, 60)], **extra}
    cpu = _frameset_mem_mb({**base, "device": "cpu"})
    cuda = _frameset_mem_mb({**base, "device": "cuda"})
    one = settings_from_config({**base, "device": "cpu"}).registration.job_cost.mem_mb
    assert cpu == (max(one, 4000) if extra.get("frameset") else one)
    assert cpu in (2000, 4000, 8000)
    # 15 more sets at 256x256: 9 frames at 48 bytes a pixel (7 members, the frame kept
    # for each set, rounded up) and 64 for the outputs
    assert cuda == cpu + math.ceil(15 * (8 * 48 + 64) * 256 * 256 / 1e6) == cpu + 441
    assert _frameset_mem_mb({**base, "device": "auto"}) == cuda
    # the group's share grows with the pixels and the members
    assert _frameset_mem_mb({**base, "device": "cuda", "resize": 512}) == cpu + math.ceil(15 * 448 * 512 * 512 / 1e6)
    wider = {**base, "device": "cuda", "frameset": {**extra.get("frameset", {}), "neighbours": 5}}
    assert _frameset_mem_mb(wider) == cpu + math.ceil(15 * (12 * 48 + 64) * 256 * 256 / 1e6)
    # and with the targets apart: each set of the group brings target_step frames to the caches
    apart = {**base, "device": "cuda", "frameset": {**extra.get("frameset", {}), "target_step": 4}}
    assert _frameset_mem_mb(apart) == cpu + math.ceil(15 * (11 * 48 + 64) * 256 * 256 / 1e6)


def test_the_frameset_rule_asks_for_the_groups_memory_on_a_gpu(tmp_path):
    """What the workflow's frameset_batch jobs ask the scheduler for (SLURM's --mem):
    the dry run's resources with device cpu and cuda."""
    asked = {}
    for device in ("cpu", "cuda"):
        config = {
            "device": device,
            "resize": 64,
            "sources": [synthetic_source("syn", ["room_000"], "train", 14, 80, 60)],
            "frameset": {"neighbours": 3, "stride": 2, "target_step": 1, "batch_size": 1},
            "patches": {"count": 2, "size": 32},
        }
        wd = make_workdir(tmp_path / device, config)
        out = snakemake(wd, "-n", "framesets").stdout
        jobs = re.findall(r"^rule frameset_batch:\n(?:\s+.*\n)*?\s+resources: (.*)$", out, re.M)
        assert jobs, out[-3000:]
        mem = {int(re.search(r"\bmem_mb=(\d+)", r).group(1)) for r in jobs}
        assert len(mem) == 1, jobs
        asked[device] = mem.pop()
        assert asked[device] == _frameset_mem_mb(config)
    assert asked["cpu"] == 2000 and asked["cuda"] == 2000 + math.ceil(15 * 448 * 64 * 64 / 1e6) == 2028
