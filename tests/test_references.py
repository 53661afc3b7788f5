"""The references of real frames that no method was trained on (depthgt.gt.references),
on the real 7-Scenes fixture (skipped when ../shared/data/7scenes-kitchen is absent):
the neighbours-only render is the build's leave-target-out render, with the build's own
(refined) poses, at every pixel; it is empty where no neighbour is fused."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from depthgt.eval.evaluate import evaluate_frames
from depthgt.gt.build import FrameSetOutputs, process_frameset
from depthgt.gt.cache import ResizedScene
from depthgt.gt.references import (
    fused_neighbours,
    neighbours_only_render,
    read_reference_table,
    reference_key,
    scene_references,
)
from depthgt.gt.render import fuse
from depthgt.jobs.common import open_source_scene
from depthgt.metric_vocabulary import depth_errors
from depthgt.registration import load_frameset
from depthgt.settings import FrameSetSettings, settings_from_config

FIXTURE = Path(__file__).resolve().parents[2] / "shared/data/7scenes-kitchen"
pytestmark = pytest.mark.skipif(not FIXTURE.is_dir(), reason="../shared/data/7scenes-kitchen is absent")
TARGET = 20


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """One kitchen frame set built as the batch job builds it (refined poses: the stored
    poses are not the source's), its settings and the scene at the working resolution."""
    settings = settings_from_config({"device": "cpu", "registration": {"method": "refine"}})
    scene = ResizedScene(
        open_source_scene({"kind": "sevenscenes", "root": str(FIXTURE)}, "7scenes-kitchen"), settings.size_hw, keep=16
    )
    members = [TARGET + o for o in FrameSetSettings().offsets]
    out = tmp_path_factory.mktemp("fs") / f"{TARGET:06d}"
    doc = process_frameset(scene, "kitchen", TARGET, members, "test", FrameSetOutputs.in_dir(out), settings)
    return scene, settings, out, doc


def test_neighbours_only_is_the_builds_leave_target_out_render(built):
    scene, settings, out, doc = built
    poses = json.loads((out / "poses.json").read_text())
    assert poses["T_j_to_t"] != poses["T_j_to_t_reference"]  # the refined poses, not the source's
    ref = neighbours_only_render(scene, doc, poses, settings.render, settings.size_hw)
    assert ref.shape == settings.size_hw and ref.dtype == np.float32
    # the build's check: the neighbours alone rendered beside the GT at every 2nd row/column
    data = load_frameset(scene, doc["members"], settings.size_hw, need_poses=False, device=torch.device("cpu"))
    _, T = fused_neighbours(doc, poses, str(out))
    lto = fuse(data, T, settings.render, leave_target_out=True).left_out.depth[0, 0].numpy()
    k = settings.render.leave_target_out_stride
    a, b = ref[::k, ::k], lto[::k, ::k]
    assert np.array_equal(a > 0, b > 0)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=0)
    # ... and the statistics the build wrote from it
    stats = depth_errors(a, data.depth_m[0, 0].numpy()[::k, ::k])
    for metric in ("mae_m", "rmse_m", "completeness"):
        assert stats[metric] == pytest.approx(doc["statistics"]["leave_target_out"][metric], rel=1e-4), metric
    # every pixel, not only the check's; a few mm from the target's raw depth, which it never saw
    assert (ref[1::2, 1::2] > 0).mean() > 0.9
    assert stats["mae_m"] < 0.012
    # without the target's depth: not the GT
    assert not np.allclose(ref, data.depth_m[0, 0].numpy())
    # no neighbour fused (a registration that kept none): empty everywhere
    none = {**poses, "registration": {**poses["registration"], "fused_offsets": [0]}}
    assert not neighbours_only_render(scene, doc, none, settings.render, settings.size_hw).any()
    with pytest.raises(ValueError, match="poses.json: T_j_to_t has no pose for offset"):
        neighbours_only_render(scene, doc, {"T_j_to_t": {}}, settings.render, settings.size_hw, where="here")


def test_scene_references_and_their_scoring(built, tmp_path):
    """scene_references writes the neighbours-only render (and the TSDF GT where the RDE
    table has one) of the split's frame sets; the evaluation scores against them."""
    scene, settings, out, doc = built
    rde = tmp_path / "rde" / f"{TARGET:06d}"
    rde.mkdir(parents=True)
    tsdf = np.full(settings.size_hw, 2.0, np.float32)
    from depthgt.io import read_exr, write_exr

    write_exr(rde / "gt.exr", {"Z": tsdf})
    fs = pd.DataFrame(
        [
            {
                "dataset": "kitchen",
                "scene": "7scenes-kitchen",
                "target": TARGET,
                "split": "test",
                "status": "ok",
                "frameset": str(out),
            },
            {
                "dataset": "kitchen",
                "scene": "7scenes-kitchen",
                "target": TARGET + 2,
                "split": "train",
                "status": "ok",
                "frameset": "not/evaluated",
            },
        ]
    )
    rde_fs = pd.DataFrame([{"frameset": str(out), "status": "ok", "rde": str(rde)}])
    npz = tmp_path / "refs" / "references.npz"
    table = scene_references(scene, fs, rde_fs, settings.render, settings.size_hw, "test", npz)
    assert list(table["reference"]) == ["neighbours", "tsdf"] and (table["target"] == TARGET).all()
    with np.load(npz) as z:
        assert sorted(z.files) == [reference_key(TARGET, "neighbours"), reference_key(TARGET, "tsdf")]
        np.testing.assert_array_equal(z[reference_key(TARGET, "tsdf")], tsdf)
        neighbours = z[reference_key(TARGET, "neighbours")]
    table.to_parquet(tmp_path / "refs.parquet")
    files = read_reference_table([tmp_path / "refs.parquet"])
    ev = evaluate_frames(
        fs, {"input": {"image": "input"}}, references=("gt", "neighbours", "tsdf"), split="test", reference_files=files
    )
    assert set(ev["reference"]) == {"gt", "neighbours", "tsdf"}
    got = ev[(ev["reference"] == "neighbours")].set_index("metric")["value"]
    inp = read_exr(out / "input.exr")["Z"]
    expected = depth_errors(inp, neighbours, mask=inp > 0)
    assert got["mae_input_valid_m"] == pytest.approx(expected["mae_m"], rel=1e-5)
