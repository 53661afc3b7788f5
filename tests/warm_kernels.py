"""Compiles the library's numba kernels into their on-disk cache (``cache=True``): one
synthetic frame set built as a batch job builds it (``refine`` poses, ``coverage``
views, the frame cache). The test session runs this first in its workflow lane
(conftest ``pytest_collection_finish``), so that the workflow jobs and the in-process tests that start
beside each other load the kernels instead of each compiling them (~45 s of CPU apiece)
in a fresh checkout.

    python3 tests/warm_kernels.py OUT_DIR
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from depthgt.framecache import FrameCache
from depthgt.gt.build import FrameSetOutputs, process_frameset
from depthgt.gt.cache import ResizedScene
from depthgt.jobs.common import open_source_scene
from depthgt.settings import settings_from_config


def main(out_dir: Path) -> None:
    torch.set_num_threads(1)
    source = {"kind": "synthetic", "options": {"n_frames": 14, "seed": 1, "width": 160, "height": 120}}
    settings = settings_from_config(
        {
            "device": "cpu",
            "resize": 64,
            "frameset": {"neighbours": 3, "stride": 2, "target_step": 1, "selection": "coverage", "coverage_span": 6},
            "registration": {"method": "refine"},
            "patches": {"count": 1, "size": 32, "max_missing": 1.0},
        }
    )
    scene = ResizedScene(open_source_scene(source, "room_000"), settings.size_hw, keep=16)
    target = 6
    members = [target + o for o in settings.frameset.offsets]
    out = FrameSetOutputs.in_dir(out_dir / "frameset")
    process_frameset(scene, "warm", target, members, "train", out, settings, cache=FrameCache(keep=16))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
