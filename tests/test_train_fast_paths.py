"""The training's fast paths give what the plain ones gave: depthgt's normals against
kornia's, push-pull without its data-dependent stop, the loss terms read in one go."""

import math

import pytest
import torch
import torch.nn.functional as F
from kornia.geometry.depth import depth_to_normals

from depthgt.depth_ops import depth_normals, valid_avg_pool, window_max
from depthgt.enhance.lapden import push_pull_fill
from depthgt.enhance.losses import LossConfig, lapden_loss, normal_l1


def _surface(B=2, H=24, W=20, seed=0, holes=True):
    """Smooth depth (1-4 m) with rectangular holes, and the (B, 3, 3) intrinsics."""
    g = torch.Generator().manual_seed(seed)
    depth = 1.0 + 3.0 * F.interpolate(torch.rand(B, 1, 4, 4, generator=g), size=(H, W), mode="bilinear")
    if holes:
        depth[0, :, 3:8, 4:9] = 0.0
        depth[-1, :, H - 6 :, 2:5] = 0.0
    K = torch.tensor([[30.0, 0.0, W / 2 - 0.3], [0.0, 28.0, H / 2 + 0.2], [0.0, 0.0, 1.0]]).expand(B, 3, 3).clone()
    return depth, K


def _nondegenerate(normals_ref):
    # where kornia's cross product is far from 0; where it is 0 analytically (a hole's
    # points, or a 3x3 window with one point) both return rounding noise or 0
    return normals_ref.norm(dim=1) > 0.5


def test_depth_normals_match_kornia_values_and_gradients():
    depth, K = _surface()
    ref = depth_to_normals(depth, K)
    ours = depth_normals(depth, K)
    assert ours.shape == ref.shape == (2, 3, 24, 20)
    # rank-deficient windows at the holes' rims: the only pixels that may differ
    full = 1.0 - F.max_pool2d(1.0 - (depth > 0).float(), 3, stride=1, padding=1) > 0.5
    mask = full.expand_as(ref)
    torch.testing.assert_close(ours[mask], ref[mask], rtol=0, atol=1e-5)
    # unit length where defined, 0 inside the holes (their points are all the origin)
    assert torch.allclose(ours.norm(dim=1)[full[:, 0]], torch.ones(()), atol=1e-5)
    assert ours[0, :, 5, 6].abs().max() == 0

    # the backward: the gradient of a weighted sum of the normals, away from degenerate pixels
    d1 = depth.clone().requires_grad_()
    d2 = depth.clone().requires_grad_()
    w = torch.randn(ref.shape, generator=torch.Generator().manual_seed(1)) * mask
    (depth_to_normals(d1, K) * w).sum().backward()
    (depth_normals(d2, K) * w).sum().backward()
    torch.testing.assert_close(d2.grad, d1.grad, rtol=1e-4, atol=1e-4 * float(d1.grad.abs().max()))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_depth_normals_without_gradients_take_the_compiled_cross_with_the_same_values(dtype, monkeypatch):
    depth, K = _surface()
    depth = depth.to(dtype) * (
        1 + 0.01 * torch.rand(depth.shape, generator=torch.Generator().manual_seed(2), dtype=dtype)
    )
    with_grad = depth_normals(depth.clone().requires_grad_(), K).detach()  # torch's cross kernel

    def refuse(*args, **kwargs):
        raise AssertionError("torch.linalg.cross called without gradients")

    monkeypatch.setattr(torch.linalg, "cross", refuse)
    plain = depth_normals(depth, K)  # no gradient wanted: the compiled cross
    with torch.no_grad():
        assert torch.equal(depth_normals(depth.clone().requires_grad_(), K), plain)
    assert plain.dtype == dtype and plain.shape == with_grad.shape
    # the same products and differences (on an FMA machine to the bit); where the cross
    # product is rounding noise (a hole's rim) its direction is noise: only the defined
    # pixels are compared
    full = (1.0 - F.max_pool2d(1.0 - (depth > 0).float(), 3, stride=1, padding=1) > 0.5).expand_as(plain)
    torch.testing.assert_close(plain[full], with_grad[full], rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-12)
    assert plain[0, :, 5, 6].abs().max() == 0  # a hole's point: 0, as torch's


def test_depth_normals_of_bfloat16_depth_keep_torch_cross_kernel():
    # numpy has no bfloat16: such depth takes torch's kernel, gradients or not
    depth, K = _surface()
    d16 = depth.to(torch.bfloat16)
    n = depth_normals(d16, K)
    assert n.dtype == torch.bfloat16 and n.shape == (2, 3, 24, 20)
    full = (1.0 - F.max_pool2d(1.0 - (depth > 0).float(), 3, stride=1, padding=1) > 0.5).expand_as(n)
    ref = depth_normals(d16.float(), K)
    torch.testing.assert_close(n.float()[full], ref[full], rtol=0, atol=0.1)


def test_depth_normals_of_a_tilted_plane():
    # z = a + b u in pixels: the points lie on a plane; its normal is (n_x, 0, n_z)
    H, W = 12, 16
    K = torch.tensor([[[20.0, 0.0, 8.0], [0.0, 20.0, 6.0], [0.0, 0.0, 1.0]]])
    x = (torch.arange(W, dtype=torch.float32) - 8.0) / 20.0
    z = 2.0 / (1.0 - 0.5 * x)  # the plane Z = 2 + 0.5 X in camera coordinates
    depth = z.expand(1, 1, H, W).clone()
    n = depth_normals(depth, K)[0, :, 1:-1, 1:-1]
    expected = torch.tensor([-0.5, 0.0, 1.0]) / math.sqrt(1.25)
    torch.testing.assert_close(n, expected.view(3, 1, 1).expand_as(n), rtol=0, atol=1e-5)


def test_normal_l1_is_zero_at_the_gt_and_positive_off_it():
    depth, K = _surface(holes=False)
    valid = depth > 0
    assert float(normal_l1(depth, depth, valid, K)) == 0.0
    bumped = depth.clone()
    bumped[:, :, 10:14, 8:12] += 0.05
    assert float(normal_l1(bumped, depth, valid, K)) > 1e-3


def _push_pull_with_early_stop(depth_m, valid):
    """push_pull_fill as it was before: stop going down at the first level without holes."""
    w = valid.to(depth_m.dtype)
    levels = [(depth_m * w, w)]
    while min(levels[-1][0].shape[-2:]) > 1 and bool((levels[-1][1] <= 0).any()):
        d, w = levels[-1]
        d_c, ok = valid_avg_pool(d, w, 2, ceil_mode=True)
        levels.append((d_c, ok.to(d.dtype)))
    filled = levels[-1][0]
    for d, w in reversed(levels[:-1]):
        up = F.interpolate(filled, size=tuple(d.shape[-2:]), mode="bilinear", align_corners=False)
        filled = torch.where(w > 0, d, up)
    return filled


def test_push_pull_without_the_early_stop_is_bit_identical():
    for H, W in ((24, 20), (9, 13), (32, 32)):
        depth, _ = _surface(B=3, H=H, W=W)
        depth[1] = 0.0  # an image without a valid pixel
        depth[2, :, :2, :] = 0.0  # holes that vanish after one level
        for image in (depth, depth[2:]):
            assert torch.equal(push_pull_fill(image, image > 0), _push_pull_with_early_stop(image, image > 0))


def test_lapden_loss_terms_are_the_per_level_sums():
    torch.manual_seed(0)
    depth, K = _surface(B=2, H=32, W=32, holes=True)
    outs = [
        F.avg_pool2d(depth, 4) + 0.01 * torch.randn(2, 1, 8, 8),
        F.avg_pool2d(depth, 2) + 0.01 * torch.randn(2, 1, 16, 16),
        depth + 0.01 * torch.randn(2, 1, 32, 32),
    ]
    config = LossConfig(scale_weights=(0.5, 1.0, 2.0))
    total, terms = lapden_loss(outs, {"gt": depth, "K": K}, config)
    assert terms["total"] == float(total)
    # the terms of each level alone, weighted and summed as the log's columns
    per_level = [lapden_loss([o], {"gt": depth, "K": K}, LossConfig(scale_weights=(1.0,)))[1] for o in outs]
    for k in ("depth", "grad", "normal", "structure"):
        expected = 0.0
        for w_l, t in zip(config.scale_weights, per_level):
            expected += w_l * t[k]
        assert terms[k] == expected


def test_load_model_is_channels_last_on_cpu_and_predicts_as_before(tmp_path):
    from depthgt.enhance.train import build_model, load_model, predict

    torch.manual_seed(0)
    model = build_model("ddrnet", {"channels": 4})
    for p in model.parameters():  # weights away from their initial state
        p.data.add_(0.01 * torch.randn_like(p))
    path = tmp_path / "ckpt.pt"
    torch.save({"model": "ddrnet", "model_params": {"channels": 4}, "model_state": model.state_dict()}, path)
    loaded = load_model(path)
    assert all(p.is_contiguous(memory_format=torch.channels_last) for p in loaded.parameters() if p.ndim == 4)
    depth, _ = _surface(B=2, H=24, W=32)
    plain = predict(model.eval(), depth)  # the weights in the default layout
    torch.testing.assert_close(predict(loaded, depth), plain, rtol=1e-5, atol=1e-6)


def _outputs_and_grads(model, depth):
    model.zero_grad(set_to_none=True)
    outs = model(depth)
    sum((o * torch.linspace(0.5, 1.5, o.numel()).view_as(o)).sum() for o in outs).backward()
    return [o.detach() for o in outs], [p.grad.clone() for p in model.parameters()]


def test_sdd_skipping_the_identity_mask_products_changes_no_bit(monkeypatch):
    from depthgt.enhance.learned import PartialConv2d, SDDUNet

    torch.manual_seed(0)
    model = SDDUNet(channels=4).to(memory_format=torch.channels_last)
    depth, _ = _surface(B=2, H=32, W=24)
    fast = _outputs_and_grads(model, depth)
    plain_forward = PartialConv2d.forward
    monkeypatch.setattr(PartialConv2d, "forward", lambda self, x, mask, masked=False: plain_forward(self, x, mask))
    plain = _outputs_and_grads(model, depth)
    assert all(torch.equal(a, b) for a, b in zip(fast[0], plain[0]))
    assert all(torch.equal(a, b) for a, b in zip(fast[1], plain[1]))


def test_lapden_in_place_activations_change_no_bit(monkeypatch):
    from depthgt.enhance.lapden import LapDEN, LapDENConfig

    torch.manual_seed(0)
    model = LapDEN(LapDENConfig(channels=4)).to(memory_format=torch.channels_last)
    for head in model.heads:  # non-zero heads, so that every level's gradient reaches the weights
        torch.nn.init.normal_(head.weight, std=0.1)
    depth, _ = _surface(B=2, H=32, W=24)
    fast = _outputs_and_grads(model, depth)
    leaky = F.leaky_relu
    monkeypatch.setattr(F, "leaky_relu", lambda x, slope, inplace=False: leaky(x, slope))
    plain = _outputs_and_grads(model, depth)
    assert all(torch.equal(a, b) for a, b in zip(fast[0], plain[0]))
    assert all(torch.equal(a, b) for a, b in zip(fast[1], plain[1]))


def test_window_max_is_max_pool_to_the_bit_and_keeps_its_gradient():
    g = torch.Generator().manual_seed(0)
    for shape, dtype in (
        ((2, 1, 17, 12), torch.float32),
        ((1, 3, 5, 9), torch.float32),
        ((3, 1, 2, 2), torch.float32),
        ((2, 1, 17, 12), torch.float64),
    ):
        x = torch.rand(shape, generator=g, dtype=dtype) * (torch.rand(shape, generator=g) > 0.3)
        x[0, 0, 0, 0] = float("nan")  # propagated by both
        x[-1, 0, -1, 0], x[-1, 0, 0, -1] = float("inf"), -float("inf")  # the renderer's edge scores
        for window in (1, 3, 5, 9):
            expected = F.max_pool2d(x, window, stride=1, padding=window // 2)
            assert torch.equal(window_max(x, window).nan_to_num(-1.0), expected.nan_to_num(-1.0))
    # with autograd: max_pool2d's gradient, one element per window max
    x = torch.rand(2, 1, 9, 7, generator=g).requires_grad_()
    w = torch.rand(2, 1, 9, 7, generator=g)
    (window_max(x, 5) * w).sum().backward()
    ours = x.grad.clone()
    x.grad = None
    (F.max_pool2d(x, 5, stride=1, padding=2) * w).sum().backward()
    assert torch.equal(ours, x.grad)
    with torch.no_grad():  # the fast path, the same values
        assert torch.equal(window_max(x, 5), F.max_pool2d(x, 5, stride=1, padding=2))
