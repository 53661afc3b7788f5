"""Issue 3 item 9: neighbours that did not register never enter the GT; per config the
frame set is rendered from the registered ones or excluded, and the reason is written."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

import depthgt.registration.overfit as overfit
from depthgt.errors import ConfigError
from depthgt.gt import store
from depthgt.gt.build import FrameSetOutputs, process_frameset
from depthgt.gt.render import fuse
from depthgt.io import read_exr
from depthgt.jobs.common import open_source_scene
from depthgt.registration import load_frameset, poses_from_source
from depthgt.registration.result import RegistrationResult
from depthgt.settings import FrameSetSettings, settings_from_config

TARGET = 12


@pytest.fixture(scope="module")
def scene_and_truth():
    scene = open_source_scene({"kind": "synthetic", "options": {"n_frames": 24, "seed": 0}}, "room_000")
    members = [TARGET + o for o in FrameSetSettings().offsets]
    data = load_frameset(scene, members, (256, 256), True, torch.device("cpu"))
    return scene, members, data, poses_from_source(data)


def _fake_registration(T_true: torch.Tensor, bad: set[int]):
    """A registration method that returns the true poses, except for the offsets in
    ``bad``: moved 0.4 m and flagged failed (what a real failure looks like)."""

    def fake(data, offsets, settings, **kwargs):
        T = T_true.clone()
        status, reasons = [], []
        for i, o in enumerate(offsets[1:]):
            if o in bad:
                T[i, :3, 3] += 0.4
                status.append("failed")
                reasons.append("high_residual(5.00cm)")
            else:
                status.append("ok")
                reasons.append("")
        return RegistrationResult(
            T_j_to_t=T,
            offsets=list(offsets),
            neighbour_status=status,
            neighbour_reasons=reasons,
            status="ok",
            reason="",
            n_correspondences=[100] * (len(offsets) - 1),
        )

    return fake


@pytest.mark.parametrize("on_failure", ["drop_neighbours", "exclude"])
def test_failed_neighbours_are_dropped_or_the_set_excluded(scene_and_truth, tmp_path, monkeypatch, on_failure):
    scene, members, data, T_true = scene_and_truth
    monkeypatch.setattr(overfit, "register_overfit", _fake_registration(T_true, {-6, 6}))
    settings = settings_from_config(
        {"device": "cpu", "registration": {"method": "overfit", "preset": "fast", "on_failure": on_failure}}
    )
    doc = process_frameset(scene, "synthetic", TARGET, members, "train", FrameSetOutputs.in_dir(tmp_path), settings)
    poses = json.loads((tmp_path / "poses.json").read_text())
    assert poses["registration"]["fused_offsets"] == [0, -4, -2, 2, 4]
    assert doc["statistics"]["neighbours_fused"] == 4
    gt = read_exr(tmp_path / "gt.exr")["Z"]
    keep = [0, 2, 3, 4, 5]  # positions of offsets 0, -4, -2, 2, 4
    expected = fuse(data, T_true, settings.render, members=keep).gt.depth[0, 0].numpy()
    np.testing.assert_allclose(gt, expected, atol=1e-6 + 0.5 / store.GT_UNITS["Z"])  # stored on the GT's grid
    T_bad = _fake_registration(T_true, {-6, 6})(None, [0, -6, -4, -2, 2, 4, 6], None).T_j_to_t
    no_check = replace(settings.render, min_frame_agreement=0.0, min_whole_frame_agreement=0.0)
    with_bad = fuse(data, T_bad, no_check).gt.depth[0, 0].numpy()
    assert np.abs(with_bad - gt).max() > 0.1  # the moved neighbours would have shown in the GT
    # (the renderer's own frame-agreement check also leaves such neighbours out)
    assert (fuse(data, T_bad, settings.render).gt.agreement[0, [1, 6]] < settings.render.min_frame_agreement).all()
    if on_failure == "exclude":
        assert doc["status"] == "failed" and "-6" in doc["reason"] and "+6" in doc["reason"]
    else:
        assert doc["status"] == "ok"


def test_unknown_on_failure_is_a_config_error():
    with pytest.raises(ConfigError, match="on_failure"):
        settings_from_config({"registration": {"on_failure": "keep"}})


def test_refine_mode_builds_a_frameset_from_the_source_poses(scene_and_truth, tmp_path):
    """``registration.method: refine`` through the frame-set job: the source's (exact)
    poses stay where they are, every neighbour is fused, poses.json records the mode,
    the photometric weight (synthetic colour is the depth's camera at its instant) and
    the corrections."""
    scene, members, data, T_true = scene_and_truth
    settings = settings_from_config({"device": "cpu", "registration": {"method": "refine"}})
    assert settings.registration.uses_source_poses
    doc = process_frameset(scene, "synthetic", TARGET, members, "train", FrameSetOutputs.in_dir(tmp_path), settings)
    poses = json.loads((tmp_path / "poses.json").read_text())
    reg = poses["registration"]
    assert doc["status"] == "ok" and reg["method"] == "refine" and reg["fused_offsets"] == [0, -6, -4, -2, 2, 4, 6]
    assert reg["photometric_weight"] == settings.registration.refine_settings.photo_weight > 0
    assert max(reg["diagnostics"]["correction_translation_m"]) < 0.005  # exact poses: at most a few mm of noise
