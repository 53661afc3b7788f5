"""The frame cache: CachedScene satisfies the Scene protocol, and the one frame loader
gives the same frame set from the cache as from the source."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from depthgt.errors import FrameError
from depthgt.gt.cache import CachedScene, FrameCacheWriter
from depthgt.gt.frameset import load_frameset
from depthgt.jobs.common import open_source_scene
from depthgt.sources.base import Scene


@pytest.fixture(scope="module")
def cached(tmp_path_factory):
    torch.set_num_threads(1)
    scene = open_source_scene({"kind": "synthetic", "options": {"n_frames": 9, "width": 160, "height": 120}}, "room_001")
    d = tmp_path_factory.mktemp("cache") / "frames"
    writer = FrameCacheWriter(d, scene, (64, 64))
    for i in range(len(scene)):
        if i != 4:  # frame 4 plays an invalid frame: never cached
            writer.put(i, scene.read(i))
    writer.close()
    return scene, CachedScene(d)


def test_cached_scene_is_a_scene(cached):
    source, cache = cached
    assert isinstance(cache, Scene)
    assert len(cache) == len(source) and cache.frame_id(3) == source.frame_id(3) and cache.name == source.name
    assert cache.image_size == (64, 64) and cache.source_size == (120, 160)
    fr = cache.read(2)
    assert fr.depth_m.shape == (64, 64) and fr.rgb.shape == (64, 64, 3) and fr.rgb.dtype == np.uint8
    assert fr.clean_depth_m.shape == (64, 64)
    np.testing.assert_array_equal(fr.T_world_cam, source.read(2).T_world_cam)
    with pytest.raises(FrameError, match="not in the cache"):
        cache.read(4)
    with pytest.raises(FrameError, match="out of range"):
        cache.read(9)


def test_one_loader_for_cache_and_source(cached):
    source, cache = cached
    members = [3, 1, 5]
    a = load_frameset(source, members, (64, 64), need_poses=True, device=torch.device("cpu"))
    b = load_frameset(cache, members, (64, 64), need_poses=True, device=torch.device("cpu"))
    assert torch.equal(a.depth_m, b.depth_m) and torch.equal(a.truth_m, b.truth_m)
    assert torch.equal(a.K, b.K) and torch.equal(a.T_world_cam, b.T_world_cam)
    assert a.src_hw == b.src_hw == (120, 160) and a.frame_ids == b.frame_ids
    # the cache stores colour as uint8: at most half a grey level apart
    assert (a.rgb - b.rgb).abs().max() <= 0.5 / 255 + 1e-6
