"""LapDEN shapes and sizes, its losses on hand-computed cases, training and resume."""

import math

import pytest
import torch

from depthgt.depth_ops import masked_avg_pool, structure_loss
from depthgt.enhance.lapden import PRESETS, LapDEN, LapDENConfig, count_parameters, lapden_from_preset, push_pull_fill
from depthgt.enhance.losses import (
    LossConfig,
    confidence_weight,
    depth_l1,
    gradient_l1,
    lapden_loss,
    normal_l1,
)


def _expected_params(cfg: LapDENConfig) -> int:
    c = cfg.channels
    conv3 = 9 * c * c + c
    conv4 = 16 * c * c + c
    n_conv3 = sum(cfg.level_convs) + sum(cfg.encoder_convs)
    return (9 * 2 * c + c) + n_conv3 * conv3 + 4 * conv4 + 3 * (9 * c + 1)


@pytest.mark.parametrize("name", ["paper", "default"])
def test_lapden_parameter_counts_no_shared_layers(name):
    model = lapden_from_preset(name)
    n = count_parameters(model)
    assert n == _expected_params(PRESETS[name])
    # a layer registered twice would be counted once by parameters() but twice here
    assert len(list(model.named_parameters(remove_duplicate=False))) == len(list(model.parameters()))
    if name == "paper":
        assert 3.4e6 < n < 3.8e6  # the released model: ~3.6 M
    else:
        assert n < 0.5e6


def test_lapden_multiscale_shapes_and_gradients():
    torch.manual_seed(0)
    model = LapDEN(PRESETS["default"])
    depth = 1.0 + torch.rand(2, 1, 32, 48)
    depth[:, :, 5:9, 5:9] = 0.0
    outs = model(depth)
    assert [tuple(o.shape) for o in outs] == [(2, 1, 8, 12), (2, 1, 16, 24), (2, 1, 32, 48)]
    outs[-1].mean().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.parameters())
    with pytest.raises(ValueError, match="divisible by 4"):
        model(torch.rand(1, 1, 30, 32))
    with pytest.raises(ValueError, match=r"\(B, 1, H, W\)"):
        model(torch.rand(1, 2, 32, 32))


def test_lapden_starts_at_the_input_and_fills_holes_smoothly():
    torch.manual_seed(0)
    model = LapDEN(PRESETS["default"])
    u = torch.arange(48, dtype=torch.float32)
    depth = (1.0 + 0.01 * u).expand(2, 1, 32, 48).clone()  # ramp 1.00 .. 1.47 m along x
    depth[0, :, 8:20, 10:30] = 0.0  # a hole: fill must stay within the ramp's range there
    depth[1] = 0.0  # no valid pixel at all: zeros, no NaN
    outs = model(depth)
    valid = depth > 0
    assert torch.equal(outs[-1][valid], depth[valid])  # untrained: identity on valid pixels
    fill = outs[-1][0][~valid[0]]
    assert fill.min() > 1.0 and fill.max() < 1.40  # hole columns span 1.10 .. 1.29 m
    assert (fill - (1.0 + 0.01 * u[10:30]).repeat(12)).abs().max() < 0.15
    assert torch.isfinite(outs[-1]).all() and outs[-1][1].abs().max() == 0
    assert all(h.weight.abs().sum() == 0 and h.bias.abs().sum() == 0 for h in model.heads)


def test_push_pull_fill_keeps_valid_pixels_and_odd_sizes():
    d = torch.full((1, 1, 37, 51), 2.0)
    d[..., :20, :] = 0.0
    f = push_pull_fill(d, d > 0)
    assert torch.allclose(f, torch.full_like(d, 2.0))
    d2 = torch.rand(2, 1, 9, 7) + 1.0
    holes = torch.rand(d2.shape) < 0.3
    d2[holes] = 0.0
    f2 = push_pull_fill(d2, d2 > 0)
    assert torch.equal(f2[~holes], d2[~holes]) and (f2[holes] >= 1.0).all() and (f2[holes] <= 2.0).all()
    with pytest.raises(ValueError, match=r"valid must be \(B=2, 1, H=9, W=7\), got \(1, 1, 9, 7\)"):
        push_pull_fill(d2, holes[:1])


def test_lapden_config_rejects_odd_blocks():
    with pytest.raises(ValueError, match="even"):
        LapDENConfig(level_convs=(1, 2, 2))
    with pytest.raises(ValueError, match="unknown LapDEN preset"):
        lapden_from_preset("huge")


def test_masked_avg_pool_ignores_holes():
    d = torch.tensor([[[[1.0, 0.0], [3.0, 0.0]]]])
    out, valid = masked_avg_pool(d, d > 0, 2)
    assert out.item() == pytest.approx(2.0) and valid.item()
    out, valid = masked_avg_pool(torch.zeros(1, 1, 2, 2), torch.zeros(1, 1, 2, 2, dtype=torch.bool), 2)
    assert out.item() == 0.0 and not valid.item()


def test_depth_and_gradient_l1_hand_computed():
    pred = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]]])
    gt = torch.tensor([[[[1.0, 0.0], [2.0, 5.0]]]])
    # valid GT: errors 0, 1, 1
    assert depth_l1(pred, gt, gt > 0).item() == pytest.approx(2.0 / 3.0)
    # x-ramp against a flat GT: |dx| = 1 on the 2 valid columns of differences, dy = 0
    ramp = torch.arange(3.0).repeat(3, 1)[None, None]
    flat = torch.ones(1, 1, 3, 3)
    assert gradient_l1(ramp, flat, flat > 0).item() == pytest.approx(1.0)
    # a hole kills the differences that touch it: only row 0 and 2 remain, still 1
    holed = flat.clone()
    holed[0, 0, 1, 1] = 0
    assert gradient_l1(ramp, holed, holed > 0).item() == pytest.approx(1.0)


def test_structure_loss_hand_computed():
    pred = torch.ones(1, 1, 4, 4)
    pred[..., 2:] = 2.0
    flat = torch.ones(1, 1, 4, 4)
    valid = flat > 0
    assert structure_loss(pred, flat, valid, 5).item() == pytest.approx(1.0, rel=1e-5)
    assert structure_loss(pred, flat, valid, 3).item() == pytest.approx(0.75, rel=1e-5)
    # symmetric in the sense of eq. 6 (squared difference)
    assert structure_loss(flat, pred, valid, 3).item() == pytest.approx(0.75, rel=1e-5)


def _tilted_plane(s: float, n: int = 12, f: float = 100.0):
    """Depth of the plane Z = 1 + s * X seen by a camera with fx = fy = f."""
    K = torch.tensor([[[f, 0.0, (n - 1) / 2], [0.0, f, (n - 1) / 2], [0.0, 0.0, 1.0]]])
    u = torch.arange(n, dtype=torch.float32) - K[0, 0, 2]
    z = 1.0 / (1.0 - s * u / f)
    return z.repeat(n, 1)[None, None], K


def test_normal_l1_hand_computed():
    flat, K = _tilted_plane(0.0)
    tilted, _ = _tilted_plane(1.0)
    valid = flat > 0
    # normals (0,0,1) and (-1,0,1)/sqrt(2): L1 = 1/sqrt(2) + 1 - 1/sqrt(2) = 1
    assert normal_l1(tilted, flat, valid, K).item() == pytest.approx(1.0, abs=1e-3)
    # scaling a plane's depth keeps its normal
    assert normal_l1(2.0 * tilted, tilted, valid, K).item() == pytest.approx(0.0, abs=1e-4)
    with pytest.raises(ValueError, match="K must be"):
        normal_l1(flat, flat, valid, K[0])


def test_lapden_loss_multiscale_zero_at_gt_and_masks_holes():
    gt, K = _tilted_plane(0.5, n=16)
    gt = gt.clone()
    gt[..., :4, :4] = 0.0  # GT hole
    pooled2, _ = masked_avg_pool(gt, gt > 0, 2)
    pooled4, _ = masked_avg_pool(gt, gt > 0, 4)
    # predicting the (pooled) GT, anything in the hole, costs nothing
    fine = torch.where(gt > 0, gt, torch.full_like(gt, 7.0))
    outs = [pooled4.clone(), pooled2.clone(), fine]
    outs[1][..., :2, :2] = 5.0  # the hole at 1/2
    total, terms = lapden_loss(outs, {"gt": gt, "K": K})
    assert total.item() == pytest.approx(0.0, abs=1e-5)
    # a constant offset of 0.1 m at full scale only: depth term 0.1, others 0
    outs2 = [pooled4, pooled2, gt + 0.1]
    total2, terms2 = lapden_loss(outs2, {"gt": gt, "K": K}, LossConfig(w_normal=0.0))
    assert terms2["depth"] == pytest.approx(0.1, rel=1e-4)
    assert terms2["grad"] == pytest.approx(0.0, abs=1e-6)
    assert terms2["structure"] == pytest.approx(0.0, abs=1e-8)
    assert total2.item() == pytest.approx(0.1, rel=1e-4)


def test_confidence_weight_lowers_the_pull_of_uncertain_gt():
    pred = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]]])
    gt = torch.tensor([[[[1.0, 0.0], [2.0, 5.0]]]])
    sigma = torch.tensor([[[[0.001, 0.0], [0.001, 0.001]]]])
    w = confidence_weight(sigma, 0.001)
    assert torch.allclose(w, torch.tensor([[[[0.5, 1.0], [0.5, 0.5]]]]))
    # equal weights: the plain mean over valid GT (the hole's weight does not count)
    assert depth_l1(pred, gt, gt > 0, w).item() == pytest.approx(2.0 / 3.0)
    # a very uncertain pixel (error 1 at (1, 0)) pulls ~nothing: mean of 0 and 1 over weights 1, ~0, 1
    sigma[0, 0, 1, 0] = 10.0
    w = confidence_weight(sigma, 0.001)
    assert depth_l1(pred, gt, gt > 0, w).item() == pytest.approx(1.0 / 2.0, rel=1e-6)

    # in the loss: GT off by 0.1 m on the uncertain half only -> the weighted depth term ~0
    plane, K = _tilted_plane(0.5, n=16)
    gt = plane.clone()
    gt[..., :8] += 0.1
    sig = torch.full_like(gt, 0.0005)
    sig[..., :8] = 0.5
    outs = [plane]
    _, plain = lapden_loss(outs, {"gt": gt, "K": K}, LossConfig(scale_weights=(1.0,)))
    _, weighted = lapden_loss(
        outs, {"gt": gt, "K": K, "sigma": sig}, LossConfig(scale_weights=(1.0,), sigma_ref_m=0.002)
    )
    assert plain["depth"] == pytest.approx(0.05, rel=1e-3)
    assert weighted["depth"] < 1e-4
    # the coarser levels take the mean weight of their pixels
    _, multi = lapden_loss(
        [masked_avg_pool(plane, plane > 0, 4)[0], masked_avg_pool(plane, plane > 0, 2)[0], plane],
        {"gt": gt, "K": K, "sigma": sig},
        LossConfig(sigma_ref_m=0.002),
    )
    assert multi["depth"] < 3e-4
    with pytest.raises(ValueError, match="sigma_ref_m is set but the batch has no 'sigma'"):
        lapden_loss(outs, {"gt": gt, "K": K}, LossConfig(scale_weights=(1.0,), sigma_ref_m=0.002))
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="sigma_ref_m"):
            LossConfig(sigma_ref_m=bad)


def test_hole_weight_pulls_harder_where_the_input_has_no_depth():
    # 16x16 plane; the prediction is off by 0.1 m on the 4 columns where the input has no depth
    # and by 0.02 m on the 12 where it has: plain mean (4*0.1 + 12*0.02) / 16 = 0.04 m
    plane, K = _tilted_plane(0.5, n=16)
    inp = plane.clone()
    inp[..., :4] = 0.0
    pred = plane + 0.02
    pred[..., :4] = plane[..., :4] + 0.1
    batch = {"gt": plane, "K": K, "input": inp}
    _, plain = lapden_loss([pred], batch, LossConfig(scale_weights=(1.0,)))
    _, weighted = lapden_loss([pred], batch, LossConfig(scale_weights=(1.0,), hole_weight=4.0))
    assert plain["depth"] == pytest.approx(0.04, rel=1e-4)
    # weights 4 on the 4 hole columns, 1 on the 12 others: (16*0.1 + 12*0.02) / 28
    assert weighted["depth"] == pytest.approx((16 * 0.1 + 12 * 0.02) / 28, rel=1e-4)
    # with the confidence weight: the product (sigma_ref = sigma -> 1/2 everywhere: the same mean)
    sig = torch.full_like(plane, 0.002)
    _, both = lapden_loss(
        [pred], {**batch, "sigma": sig}, LossConfig(scale_weights=(1.0,), hole_weight=4.0, sigma_ref_m=0.002)
    )
    assert both["depth"] == pytest.approx(weighted["depth"], rel=1e-4)
    with pytest.raises(ValueError, match="hole_weight is set but the batch has no 'input'"):
        lapden_loss([pred], {"gt": plane, "K": K}, LossConfig(scale_weights=(1.0,), hole_weight=4.0))
    for bad in (0.0, -1.0, math.nan, True, "4"):
        with pytest.raises(ValueError, match="hole_weight"):
            LossConfig(hole_weight=bad)


def test_lapden_loss_gradients_flow():
    torch.manual_seed(0)
    model = LapDEN(LapDENConfig(channels=8, level_convs=(2, 2, 2), encoder_convs=(0, 0)))
    gt, K = _tilted_plane(0.3, n=16)
    noisy = gt + 0.01 * torch.randn_like(gt)
    total, terms = lapden_loss(model(noisy), {"gt": gt, "K": K})
    total.backward()
    assert math.isfinite(terms["total"])
    assert all(torch.isfinite(p.grad).all() for p in model.parameters())


# --------------------------------------------------------------------------- training

import json  # noqa: E402
from dataclasses import replace  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

import depthgt.enhance.train as train_module  # noqa: E402
from depthgt.atomic import save_npz  # noqa: E402
from depthgt.enhance.train import (  # noqa: E402
    TrainOutputs,
    build_loss,
    build_model,
    collate,
    cut_input_holes,
    flip_batch,
    learning_rate,
    load_model,
    patch_dataset,
    predict,
    predict_depth,
    train,
)
from depthgt.errors import ConfigError, DepthGTError  # noqa: E402
from depthgt.gt import store  # noqa: E402
from depthgt.gt.patches import crop_pairs, patch_record  # noqa: E402
from depthgt.io import write_rgb_webp  # noqa: E402
from depthgt.settings import TrainSettings  # noqa: E402


def _write_frameset(folder, seed, n_patches=4, size=16, sigma=False):
    """A frame set folder (store format): a noisy slanted plane (gt.exr, input.exr,
    rgb.webp), ``n_patches`` crop boxes in patches.npz, and frameset.json; with
    ``sigma`` gt.exr has a confidence channel S (1 mm, 0.2 m on the left third)."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True)
    yy, xx = np.mgrid[0:48, 0:48]
    channels = {"Z": (1.5 + rng.random() + 0.01 * xx + 0.005 * yy).astype(np.float32)}
    if sigma:
        channels["S"] = np.where(xx < 16, 0.2, 0.001).astype(np.float32)
    channels = store.stored_gt(channels)
    gt = channels["Z"]
    inp = (gt + rng.normal(0, 0.02, gt.shape)).astype(np.float32)
    inp[rng.random(gt.shape) < 0.05] = 0.0
    rgb = np.zeros((*gt.shape, 3), np.uint8)
    boxes = np.array([[4 * i, 2 * i, size, size] for i in range(n_patches)])
    store.write_gt_exr(folder / "gt.exr", channels)
    store.write_input_exr(folder / "input.exr", inp)
    write_rgb_webp(folder / store.RGB_MEMBER, rgb)
    pairs = crop_pairs(inp, gt, rgb, boxes, max_missing=1.0, gt_sigma_m=channels.get("S"))
    save_npz(folder / "patches.npz", patch_record(pairs))
    K = [[100.0, 0.0, 127.5], [0.0, 100.0, 127.5], [0.0, 0.0, 1.0]]
    (folder / "frameset.json").write_text(json.dumps({"K": K}))
    return folder


@pytest.fixture()
def manifests(tmp_path):
    paths = [_write_frameset(tmp_path / "fs" / f"{i:06d}", i) for i in range(3)]
    rows = [
        {"frameset": str(p), "patch": j, "split": "train" if i < 2 else "val"}
        for i, p in enumerate(paths)
        for j in range(4)
    ]
    table = pd.DataFrame(rows)
    table[table.split == "train"].to_parquet(tmp_path / "train.parquet")
    table[table.split == "val"].to_parquet(tmp_path / "val.parquet")
    return tmp_path / "train.parquet", tmp_path / "val.parquet"


def _settings(epochs):
    return TrainSettings(
        model="lapden",
        model_params={"preset": "default", "channels": 4, "level_convs": [2, 2, 2], "encoder_convs": [0, 0]},
        epochs=epochs,
        batch_size=3,
        lr=1e-3,
        seed=3,
        progress=False,
    )


def test_patch_dataset_shifts_intrinsics_by_crop(manifests):
    ds = patch_dataset(manifests[0])
    assert len(ds) == 8
    item = ds[1]  # box (y0, x0) = (4, 2)
    assert item["input"].shape == (1, 16, 16) and item["rgb"].shape == (3, 16, 16)
    assert item["K"][0, 2].item() == pytest.approx(127.5 - 2) and item["K"][1, 2].item() == pytest.approx(127.5 - 4)
    with pytest.raises(DepthGTError, match="missing columns"):
        patch_dataset(pd.DataFrame({"path": [], "patch": []}))


def test_flip_batch_flips_images_and_intrinsics(manifests):
    ds = patch_dataset(manifests[0])
    b = collate([ds[0], ds[1]])
    f = flip_batch(b, torch.tensor([True, False]), torch.tensor([False, True]))
    assert torch.equal(f["gt"][0], b["gt"][0].flip(-1)) and torch.equal(f["gt"][1], b["gt"][1].flip(-2))
    assert f["K"][0, 0, 2].item() == pytest.approx(15 - b["K"][0, 0, 2].item())
    assert f["K"][1, 1, 2].item() == pytest.approx(15 - b["K"][1, 1, 2].item())
    assert f["K"][1, 0, 2].item() == pytest.approx(b["K"][1, 0, 2].item())


def test_train_resume_equals_uninterrupted(manifests, tmp_path):
    full = train(*manifests, TrainOutputs.in_dir(tmp_path / "full"), _settings(3))
    assert full["epochs_run"] == 3 and 0 <= full["best_epoch"] <= 2
    log = pd.read_csv(full["log"])
    assert list(log["split"]) == ["train", "val"] * 3
    assert {"depth", "grad", "normal", "structure", "total"} <= set(log.columns)

    # an interrupted run: 2 epochs, then resumed to 3
    part = train(*manifests, TrainOutputs.in_dir(tmp_path / "part"), _settings(2))
    assert part["epochs_run"] == 2
    resumed = train(*manifests, TrainOutputs.in_dir(tmp_path / "part"), _settings(3))
    assert resumed["epochs_run"] == 1
    a = torch.load(full["last"], weights_only=False)["model_state"]
    b = torch.load(resumed["last"], weights_only=False)["model_state"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    pd.testing.assert_frame_equal(pd.read_csv(resumed["log"]).drop(columns="seconds"), log.drop(columns="seconds"))
    # a finished run does nothing more
    assert train(*manifests, TrainOutputs.in_dir(tmp_path / "part"), _settings(3))["epochs_run"] == 0

    with pytest.raises(ConfigError, match="other settings"):
        train(
            *manifests, TrainOutputs.in_dir(tmp_path / "part"), TrainSettings(**{**_settings(3).__dict__, "lr": 5e-4})
        )

    model = load_model(full["best"])
    depth = 1.0 + torch.rand(2, 1, 30, 34)
    out = predict(model, depth)
    assert out.shape == depth.shape and (out >= 0).all()
    assert predict_depth(model, depth[0, 0].numpy()).shape == (30, 34)


def test_learning_rate_schedules():
    const = TrainSettings(epochs=4, lr=2e-3)
    assert learning_rate(const, 0, 10) == learning_rate(const, 39, 10) == 2e-3
    cos = TrainSettings(epochs=4, lr=2e-3, lr_schedule="cosine")
    rates = [learning_rate(cos, step, 10) for step in range(40)]
    assert rates[0] == 2e-3 and math.isclose(rates[20], 1e-3)  # halfway: half the rate
    assert all(a > b for a, b in zip(rates, rates[1:])) and 0 < rates[-1] < 2e-3 * 0.01


def _killed_in_the_third_epoch_and_resumed(manifests, out, settings, monkeypatch):
    """Train into ``out`` with ``settings``, killed at the start of the third epoch, then
    resume; returns the resumed run's result (after asserting it ran one epoch)."""
    real_epoch = train_module.train_epoch

    def killed_in_the_third(model, loss_fn, optimizer, dataset, settings, epoch, device):
        if epoch == 2:
            raise KeyboardInterrupt
        return real_epoch(model, loss_fn, optimizer, dataset, settings, epoch, device)

    monkeypatch.setattr(train_module, "train_epoch", killed_in_the_third)
    with pytest.raises(KeyboardInterrupt):
        train(*manifests, out, settings)
    monkeypatch.setattr(train_module, "train_epoch", real_epoch)
    resumed = train(*manifests, out, settings)
    assert resumed["epochs_run"] == 1
    return resumed


def test_cosine_run_resumed_equals_uninterrupted_and_takes_the_rates(manifests, tmp_path, monkeypatch):
    """A killed cosine run resumes with the rates of its steps (they depend on the step
    alone) and ends with the uninterrupted run's weights; its epochs are part of its
    identity, so the same folder with other epochs starts anew."""

    def cos(epochs):
        return replace(_settings(epochs), lr_schedule="cosine")

    full = train(*manifests, TrainOutputs.in_dir(tmp_path / "full"), cos(3))
    ckpt = torch.load(full["last"], weights_only=False)
    steps = int(pd.read_csv(full["log"]).query("split == 'train'")["batches"].iloc[0])
    # the optimiser's rate is the one of the last step taken
    assert math.isclose(ckpt["optimizer_state"]["param_groups"][0]["lr"], learning_rate(cos(3), 3 * steps - 1, steps))
    out = TrainOutputs.in_dir(tmp_path / "part", resume=True)
    resumed = _killed_in_the_third_epoch_and_resumed(manifests, out, cos(3), monkeypatch)
    b = torch.load(resumed["last"], weights_only=False)["model_state"]
    assert all(torch.equal(ckpt["model_state"][k], b[k]) for k in b)
    # differs from a constant-rate run of the same seed
    const = train(*manifests, TrainOutputs.in_dir(tmp_path / "const"), _settings(3))
    c = torch.load(const["last"], weights_only=False)["model_state"]
    assert not all(torch.equal(c[k], b[k]) for k in b)
    assert train(*manifests, out, cos(4))["epochs_run"] == 4  # another schedule: starts anew


def test_input_holes_are_discs_cut_into_the_input_alone():
    g = torch.Generator().manual_seed(7)
    batch = {"input": torch.ones(4, 1, 64, 64), "gt": torch.ones(4, 1, 64, 64), "K": torch.eye(3).expand(4, 3, 3)}
    out = cut_input_holes(batch, 3, 5, 9, g)
    assert torch.equal(out["gt"], batch["gt"]) and torch.equal(out["K"], batch["K"])
    assert torch.equal(batch["input"], torch.ones(4, 1, 64, 64))  # the caller's batch is not changed
    holes = out["input"] == 0
    assert torch.equal(out["input"][~holes], torch.ones(int((~holes).sum())))
    # the same draws as cut_input_holes makes: every hole pixel lies in one of the sample's discs,
    # every disc of radius 5..9 px is cut in full (within the image)
    u = torch.rand(4, 3, 3, generator=torch.Generator().manual_seed(7))
    yy, xx = torch.meshgrid(torch.arange(64.0), torch.arange(64.0), indexing="ij")
    for b in range(4):
        discs = torch.zeros(64, 64, dtype=torch.bool)
        for cy, cx, r in zip(u[b, :, 0] * 64, u[b, :, 1] * 64, 5 + u[b, :, 2] * 4):
            assert 5 <= r <= 9
            discs |= (yy - cy) ** 2 + (xx - cx) ** 2 <= r**2
        assert torch.equal(holes[b, 0], discs) and discs.sum() >= math.floor(math.pi * 4**2)
    # the generator decides: the same seed cuts the same holes, another seed others
    again = cut_input_holes(batch, 3, 5, 9, torch.Generator().manual_seed(7))
    other = cut_input_holes(batch, 3, 5, 9, torch.Generator().manual_seed(8))
    assert torch.equal(again["input"], out["input"]) and not torch.equal(other["input"], out["input"])


def test_run_with_input_holes_resumes_to_the_uninterrupted_weights(manifests, tmp_path, monkeypatch):
    """Holes drawn from the epoch's generator: a killed run resumes with the same holes
    and ends with the uninterrupted run's weights; it is another run than one without
    holes (identity), whose result it does not equal."""

    def holes(epochs):
        return replace(_settings(epochs), input_holes=2, input_hole_min_px=2, input_hole_max_px=5)

    full = train(*manifests, TrainOutputs.in_dir(tmp_path / "full"), holes(3))
    out = TrainOutputs.in_dir(tmp_path / "part", resume=True)
    resumed = _killed_in_the_third_epoch_and_resumed(manifests, out, holes(3), monkeypatch)
    a = torch.load(full["last"], weights_only=False)["model_state"]
    b = torch.load(resumed["last"], weights_only=False)["model_state"]
    assert all(torch.equal(a[k], b[k]) for k in b)
    plain = train(*manifests, TrainOutputs.in_dir(tmp_path / "plain"), _settings(3))
    c = torch.load(plain["last"], weights_only=False)["model_state"]
    assert not all(torch.equal(c[k], b[k]) for k in b)
    assert train(*manifests, out, _settings(3))["epochs_run"] == 3  # no holes: another run, starts anew


def test_train_resumes_from_its_resume_folder_when_the_outputs_are_gone(manifests, tmp_path):
    """The workflow's case: the resume state lies in its own folder, and Snakemake has
    deleted the outputs (best, last, loss log) of the killed job before running it again."""
    full = train(*manifests, TrainOutputs.in_dir(tmp_path / "full"), _settings(3))
    out = TrainOutputs.in_dir(tmp_path / "wf", resume=True)
    assert out.resume == tmp_path / "wf" / "resume"
    train(*manifests, out, _settings(2))
    assert (out.resume / "last.pt").is_file() and (out.resume / "best.pt").is_file()
    for p in out[:4]:
        p.unlink()
    resumed = train(*manifests, out, _settings(3))
    assert resumed["epochs_run"] == 1 and resumed["last"] == str(out.last)
    a = torch.load(full["last"], weights_only=False)["model_state"]
    b = torch.load(out.last, weights_only=False)["model_state"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert torch.load(out.best, weights_only=False)["best_epoch"] == full["best_epoch"]
    # the loss log of the epochs before the kill came back from the resume state
    pd.testing.assert_frame_equal(
        pd.read_csv(out.log).drop(columns="seconds"), pd.read_csv(full["log"]).drop(columns="seconds")
    )
    # resume state of other settings is not an error here: training starts anew
    other = train(*manifests, out, TrainSettings(**{**_settings(1).__dict__, "lr": 5e-4}))
    assert other["epochs_run"] == 1


def test_training_with_the_gt_confidence_as_loss_weight(tmp_path):
    paths = [_write_frameset(tmp_path / "fs" / f"{i:06d}", i, sigma=i > 0) for i in range(3)]
    table = pd.DataFrame([{"frameset": str(p), "patch": j} for p in paths for j in range(4)])
    ds = patch_dataset(table)
    item = ds[7]  # box (y0, x0) = (12, 6) of the second frame set: columns 6..21, uncertain below 16
    assert "sigma" not in ds[0] and item["sigma"].shape == (1, 16, 16)
    assert item["sigma"][0, 0, 0].item() == pytest.approx(0.2, rel=0.05)  # sigma is stored on a log grid
    assert item["sigma"][0, 0, 15].item() == pytest.approx(0.001, rel=0.05)
    # a batch mixing a GT with and without confidence has none; one of confident GTs has it
    assert "sigma" not in collate([ds[0], ds[4]]) and collate([ds[4], ds[8]])["sigma"].shape == (2, 1, 16, 16)

    table.iloc[4:8].to_parquet(tmp_path / "train.parquet")
    table.iloc[8:].to_parquet(tmp_path / "val.parquet")
    s = _settings(1)
    weighted = TrainSettings(**{**s.__dict__, "loss_params": {"sigma_ref_m": 0.005}})
    a = train(tmp_path / "train.parquet", tmp_path / "val.parquet", TrainOutputs.in_dir(tmp_path / "w"), weighted)
    b = train(tmp_path / "train.parquet", tmp_path / "val.parquet", TrainOutputs.in_dir(tmp_path / "p"), s)
    la, lb = pd.read_csv(a["log"]), pd.read_csv(b["log"])
    assert la["depth"].notna().all() and not np.allclose(la["depth"], lb["depth"])
    # training on frame sets without a confidence image with the weight set: the loss says why
    table.iloc[:4].to_parquet(tmp_path / "plain.parquet")
    with pytest.raises(ValueError, match="no 'sigma'"):
        train(tmp_path / "plain.parquet", tmp_path / "val.parquet", TrainOutputs.in_dir(tmp_path / "x"), weighted)


def test_model_and_loss_params_are_checked_before_training_naming_the_key():
    for model, params, match in (
        ("lapden", {"bogus": 1}, r"enhance\.models\.lapden\.model_params .*bogus"),
        ("lapden", {"preset": "huge"}, r"enhance\.models\.lapden\.model_params .*unknown LapDEN preset"),
        ("ddrnet", {"bogus": 1}, r"enhance\.models\.ddrnet\.model_params .*bogus"),
    ):
        with pytest.raises(ConfigError, match=match):
            build_model(model, params)
    for model, params, match in (
        ("lapden", {"bogus": 1}, r"enhance\.models\.lapden\.loss_params .*unknown LapDEN loss parameters \['bogus'\]"),
        ("lapden", {"hole_weight": 0}, r"enhance\.models\.lapden\.loss_params .*hole_weight must be"),
        ("sdd", {"w_bogus": 1.0}, r"enhance\.models\.sdd\.loss_params .*w_bogus"),
    ):
        with pytest.raises(ConfigError, match=match):
            build_loss(model, params)
    # good parameters pass and reach the loss
    loss = build_loss("lapden", {"hole_weight": 2.0, "scale_weights": [1.0]})
    assert loss.keywords == {"hole_weight": 2.0, "scale_weights": [1.0]}


def test_train_settings_are_checked():
    with pytest.raises(ConfigError, match="train.model"):
        TrainSettings(model="unet3000")
    with pytest.raises(ConfigError, match="train.epochs"):
        TrainSettings(epochs=0)


def test_lapden_learns_to_denoise_and_fill_planes():
    g = torch.Generator().manual_seed(1)
    torch.manual_seed(0)
    model = lapden_from_preset("default")
    from depthgt.enhance.train import build_loss

    loss_fn = build_loss("lapden")
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)

    def planes(b, n, gen):
        u = torch.arange(n, dtype=torch.float32)
        z0 = 1.5 + 1.5 * torch.rand(b, 1, 1, 1, generator=gen)
        sx, sy = (0.02 * torch.rand(b, 2, 1, 1, generator=gen) - 0.01).unbind(1)
        truth = z0 + sx[:, None] * u.view(1, 1, 1, n) + sy[:, None] * u.view(1, 1, n, 1)
        noisy = truth + 0.05 * torch.randn(truth.shape, generator=gen)
        holes = torch.rand(truth.shape, generator=gen) < 0.05
        K = torch.tensor([[50.0, 0, (n - 1) / 2], [0, 50.0, (n - 1) / 2], [0, 0, 1]]).expand(b, 3, 3)
        return truth, torch.where(holes, torch.zeros_like(noisy), noisy), holes, K

    for _ in range(200):
        truth, noisy, _, K = planes(4, 16, g)
        total, _ = loss_fn(model(noisy), {"gt": truth, "K": K})
        opt.zero_grad()
        total.backward()
        opt.step()
    truth, noisy, holes, _ = planes(4, 16, torch.Generator().manual_seed(99))
    pred = predict(model, noisy)
    err_in = (noisy - truth)[~holes].pow(2).mean().sqrt()
    # starts at the noisy input (identity on valid pixels): 5 cm noise in, ~2.7 cm out after 200 steps
    assert (pred - truth)[~holes].pow(2).mean().sqrt() < 0.6 * err_in
    assert (pred - truth)[holes].abs().mean() < 0.05  # holes filled


def test_paper_preset_runs_a_training_step():
    torch.manual_seed(0)
    model = lapden_from_preset("paper")
    gt, K = _tilted_plane(0.2, n=16)
    noisy = gt + 0.01 * torch.randn_like(gt)
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    before = model.heads[2].weight.detach().clone()
    total, terms = lapden_loss(model(noisy), {"gt": gt, "K": K})
    opt.zero_grad()
    total.backward()
    opt.step()
    assert math.isfinite(terms["total"])
    assert not torch.equal(before, model.heads[2].weight)
