"""The one device choice (config ``device``)."""

import subprocess
import sys

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
