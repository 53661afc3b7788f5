"""ResizedScene satisfies the Scene protocol, reads each frame of a window once, and the
one frame loader gives the same frame set from it as from the source."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from depthgt.errors import FrameError
from depthgt.gt.cache import ResizedScene
from depthgt.jobs.common import open_source_scene
from depthgt.registration import load_frameset
from depthgt.sources.base import Scene


class Counting:
    """A scene that counts its reads (and plays frame 4 as unreadable)."""

    def __init__(self, scene):
        self._scene = scene
        self.reads = 0
        for name in ("name", "intrinsics", "image_size", "has_poses", "has_clean_depth"):
            setattr(self, name, getattr(scene, name))

    def __len__(self):
        return len(self._scene)

    def frame_id(self, i):
        return self._scene.frame_id(i)

    def read(self, i):
        self.reads += 1
        if i == 4:
            raise FrameError("frame 4: unreadable (test)", "unreadable")
        return self._scene.read(i)


@pytest.fixture(scope="module")
def scenes():
    torch.set_num_threads(1)
    source = open_source_scene(
        {"kind": "synthetic", "options": {"n_frames": 9, "width": 160, "height": 120}}, "room_001"
    )
    return source, Counting(source)


def test_resized_scene_is_a_scene(scenes):
    source, counting = scenes
    small = ResizedScene(counting, (64, 64), keep=3)
    assert isinstance(small, Scene)
    assert len(small) == len(source) and small.frame_id(3) == source.frame_id(3) and small.name == source.name
    assert small.image_size == (64, 64) and small.source_size == (120, 160)
    fr = small.read(2)
    assert fr.depth_m.shape == (64, 64) and fr.rgb.shape == (64, 64, 3) and fr.rgb.dtype == np.uint8
    assert fr.clean_depth_m.shape == (64, 64)
    np.testing.assert_array_equal(fr.T_world_cam, source.read(2).T_world_cam)
    with pytest.raises(FrameError, match="unreadable"):
        small.read(4)


def test_a_window_of_frames_is_read_once(scenes):
    _, counting = scenes
    small = ResizedScene(counting, (64, 64), keep=3)
    before = counting.reads
    for i in (0, 1, 2, 1, 0, 2):
        small.read(i)
    assert counting.reads - before == 3
    small.read(3)  # frame 1, the least recently used, leaves the window of 3
    small.read(0)
    assert counting.reads - before == 4
    small.read(1)
    assert counting.reads - before == 5


def test_one_loader_for_resized_and_source(scenes):
    source, _ = scenes
    small = ResizedScene(source, (64, 64))
    members = [3, 1, 5]
    a = load_frameset(source, members, (64, 64), need_poses=True, device=torch.device("cpu"))
    b = load_frameset(small, members, (64, 64), need_poses=True, device=torch.device("cpu"))
    assert torch.equal(a.depth_m, b.depth_m) and torch.equal(a.truth_m, b.truth_m)
    assert torch.equal(a.K, b.K) and torch.equal(a.T_world_cam, b.T_world_cam)
    assert a.src_hw == b.src_hw == (120, 160) and a.frame_ids == b.frame_ids
    # colour is kept as uint8: at most half a grey level apart
    assert (a.rgb - b.rgb).abs().max() <= 0.5 / 255 + 1e-6
