import numpy as np
import pytest

from depthgt.errors import ConfigError
from depthgt.gt.patches import crop, crop_boxes, crop_pairs, make_patches, missing_ratio, passes_missing_filter
from depthgt.settings import PatchSettings


def test_crop_matches_slicing():
    img = np.arange(20 * 30).reshape(20, 30)
    boxes = np.array([[0, 0, 5, 5], [15, 25, 5, 5], [3, 7, 5, 5]])
    out = crop(img, boxes)
    for b, p in zip(boxes, out):
        np.testing.assert_array_equal(p, img[b[0] : b[0] + 5, b[1] : b[1] + 5])


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
    gt[:, :32] = 0  # left half of GT missing
    inp[:32, :] = 0  # top half of input missing
    rgb = np.zeros((h, w, 3), np.uint8)
    s = PatchSettings(count=200, size=16, max_missing=0.05, filter_on=filter_on)
    out = make_patches(inp, gt, rgb, s, np.random.default_rng(0), truth_m=gt)
    assert len(out["kept"]) == 200 and out["kept"].sum() == len(out["gt"]) == len(out["truth"])
    # the recorded ratios are those of the images at the drawn boxes ...
    for key, img in (("all_missing_gt", gt), ("all_missing_input", inp)):
        direct = [(img[y : y + 16, x : x + 16] <= 0).mean() for y, x, _, _ in out["all_boxes"]]
        np.testing.assert_allclose(out[key], direct)
    # ... and the kept crops are exactly those whose decisive ratios are all below the bound
    decisive = {
        "gt": ["all_missing_gt"],
        "input": ["all_missing_input"],
        "both": ["all_missing_gt", "all_missing_input"],
    }
    expected = np.logical_and.reduce([out[k] < 0.05 for k in decisive[filter_on]])
    np.testing.assert_array_equal(out["kept"], expected)
    assert 0 < out["kept"].sum() < 200  # the half-missing images reject some crops and keep others
    # crops are the right pixels
    for p, b in zip(out["gt"], out["boxes"]):
        np.testing.assert_array_equal(p, gt[b[0] : b[0] + 16, b[1] : b[1] + 16])


def test_settings_validation():
    with pytest.raises(ConfigError, match="patches.filter_on"):
        PatchSettings(filter_on="rgb")
    with pytest.raises(ConfigError, match="patches.count"):
        PatchSettings(count=10**6)  # would exhaust memory


def test_missing_filter_functions_hand_computed():
    p = np.ones((2, 4, 4), np.float32)
    p[0, 0, :] = 0  # 4 of 16 missing
    np.testing.assert_allclose(missing_ratio(p), [0.25, 0.0])
    np.testing.assert_array_equal(passes_missing_filter(0.25, missing_ratio(p)), [False, True])
    np.testing.assert_array_equal(passes_missing_filter(0.3, missing_ratio(p), np.array([0.5, 0.1])), [False, True])


def test_crop_pairs_at_given_boxes():
    gt = np.ones((8, 8), np.float32)
    gt[:4, :4] = 0
    boxes = np.array([[0, 0, 4, 4], [4, 4, 4, 4]])
    out = crop_pairs(np.ones_like(gt), gt, np.zeros((8, 8, 3), np.uint8), boxes, 0.05)
    np.testing.assert_array_equal(out["kept"], [False, True])
    np.testing.assert_array_equal(out["boxes"], boxes[1:])
    assert out["gt"].shape == (1, 4, 4) and out["all_missing_gt"].tolist() == [1.0, 0.0]


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
    with pytest.raises(ConfigError, match="patches.max_gt_sigma_m"):
        PatchSettings(max_gt_sigma_m=0)
