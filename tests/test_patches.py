import numpy as np
import pytest

from depthgt.patches import PatchSettings, crop, crop_boxes, make_patches


def test_crop_matches_slicing():
    img = np.arange(20 * 30).reshape(20, 30)
    boxes = np.array([[0, 0, 5, 5], [15, 25, 5, 5], [3, 7, 5, 5]])
    out = crop(img, boxes)
    for b, p in zip(boxes, out):
        np.testing.assert_array_equal(p, img[b[0]:b[0] + 5, b[1]:b[1] + 5])


def test_boxes_inside_and_deterministic():
    s = PatchSettings(count=50, size=128)
    b1 = crop_boxes((256, 256), s, np.random.default_rng(3))
    b2 = crop_boxes((256, 256), s, np.random.default_rng(3))
    np.testing.assert_array_equal(b1, b2)
    assert (b1[:, :2] >= 0).all() and (b1[:, :2] + 128 <= 256).all()
    with pytest.raises(ValueError, match="does not fit"):
        crop_boxes((100, 256), s, np.random.default_rng(0))


@pytest.mark.parametrize("filter_on", ["gt", "input", "both"])
def test_missing_filter(filter_on):
    h = w = 64
    gt = np.ones((h, w), np.float32)
    inp = np.ones((h, w), np.float32)
    gt[:, :32] = 0          # left half of GT missing
    inp[:32, :] = 0         # top half of input missing
    rgb = np.zeros((h, w, 3), np.uint8)
    s = PatchSettings(count=200, size=16, max_missing=0.05, filter_on=filter_on)
    out = make_patches(inp, gt, rgb, s, np.random.default_rng(0), truth_m=gt)
    assert len(out["kept"]) == 200 and out["kept"].sum() == len(out["gt"]) == len(out["truth"])
    assert (out["missing_gt"] < 0.05).all() if filter_on in ("gt", "both") else True
    assert (out["missing_input"] < 0.05).all() if filter_on in ("input", "both") else True
    # every rejected crop violates the rule
    rej = ~out["kept"]
    if filter_on == "gt":
        assert (out["all_missing_gt"][rej] >= 0.05).all()
    elif filter_on == "input":
        assert (out["all_missing_input"][rej] >= 0.05).all()
    else:
        assert ((out["all_missing_gt"][rej] >= 0.05) | (out["all_missing_input"][rej] >= 0.05)).all()
    # crops are the right pixels
    for p, b in zip(out["gt"], out["boxes"]):
        np.testing.assert_array_equal(p, gt[b[0]:b[0] + 16, b[1]:b[1] + 16])


def test_settings_validation():
    with pytest.raises(ValueError, match="filter_on"):
        PatchSettings(filter_on="rgb")


def test_confidence_filter_leaves_out_uncertain_gt():
    h = w = 64
    gt = np.full((h, w), 2.0, np.float32)
    sigma = np.full((h, w), 0.002, np.float32)
    sigma[:, 40:] = 0.05  # an uncertain band on the right
    inp = np.ones((h, w), np.float32)
    rgb = np.zeros((h, w, 3), np.uint8)
    s = PatchSettings(count=100, size=16, max_gt_sigma_m=0.01)
    out = make_patches(inp, gt, rgb, s, np.random.default_rng(0), gt_sigma_m=sigma)
    # crops reaching into the band lose those pixels (set to 0, counted as missing) and are rejected
    rej = ~out["kept"]
    assert rej.any() and out["kept"].any()
    assert ((out["all_boxes"][rej, 1] + 16) > 40).all() and ((out["boxes"][:, 1] + 16) <= 40 + 0).all()
    assert (out["gt_sigma"] <= 0.01).all() and (out["gt"] == 2.0).all()
    # without the option every crop is kept, and the sigma patches come along
    out = make_patches(inp, gt, rgb, PatchSettings(count=100, size=16), np.random.default_rng(0), gt_sigma_m=sigma)
    assert out["kept"].all() and out["gt_sigma"].shape == (100, 16, 16)
    with pytest.raises(ValueError, match="max_gt_sigma_m"):
        make_patches(inp, gt, rgb, s, np.random.default_rng(0))
    with pytest.raises(ValueError, match="max_gt_sigma_m"):
        PatchSettings(max_gt_sigma_m=0)
