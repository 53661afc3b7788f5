"""depthgt.shapes.check_shape: the one shape check (names bind, integers are fixed, * and ... any)."""

import numpy as np
import pytest
import torch

from depthgt.shapes import check_shape


def test_names_bind_within_and_across_calls():
    sizes = check_shape(torch.zeros(2, 1, 4, 6), "B 1 H W", "depth_m")
    assert sizes == {"B": 2, "H": 4, "W": 6}
    assert check_shape(torch.zeros(2, 3, 4, 6), "(B, 3, H, W)", "rgb", sizes) == sizes
    with pytest.raises(ValueError, match=r"^rgb must be \(B=2, 3, H=4, W=6\), got \(2, 3, 4, 5\)$"):
        check_shape(torch.zeros(2, 3, 4, 5), "B 3 H W", "rgb", sizes)
    with pytest.raises(ValueError, match=r"^T must be \(N, N\), got \(3, 4\)$"):
        check_shape(np.zeros((3, 4)), "N N", "T")
    given = {"J": 3}
    assert check_shape(np.zeros((3, 4, 4)), "J 4 4", "T_j_to_t", given) == {"J": 3}
    with pytest.raises(ValueError, match=r"T_j_to_t must be \(J=3, 4, 4\), got \(2, 4, 4\)"):
        check_shape(np.zeros((2, 4, 4)), "J 4 4", "T_j_to_t", given)
    assert given == {"J": 3}  # the caller's sizes are not modified


def test_fixed_sizes_wildcards_and_alternatives():
    with pytest.raises(ValueError, match=r"^depth_m must be \(B, 1, H, W\), got \(2, 2, 4, 6\)$"):
        check_shape(torch.zeros(2, 2, 4, 6), "B 1 H W", "depth_m")
    with pytest.raises(ValueError, match=r"got \(1, 4, 6\)$"):
        check_shape(torch.zeros(1, 4, 6), "B 1 H W", "depth_m")
    assert check_shape(np.zeros((5, 7)), "* C", "x") == {"C": 7}
    assert check_shape(np.zeros((4, 4)), "... 4 4", "T") == {}
    assert check_shape(np.zeros((2, 5, 4, 4)), "... 4 4", "T") == {}
    assert check_shape(np.zeros((2, 5, 4, 4)), "B ... 4", "T") == {"B": 2}
    with pytest.raises(ValueError, match=r"T must be \(\.\.\., 4, 4\), got \(4,\)"):
        check_shape(np.zeros(4), "... 4 4", "T")
    assert check_shape(np.zeros(3), "N", "v") == {"N": 3}
    with pytest.raises(ValueError, match=r"v must be \(2,\), got \(3,\)"):
        check_shape(np.zeros(3), "2", "v")
    assert check_shape(np.zeros((1, 1, 2, 3)), "H W | B 1 H W", "d") == {"B": 1, "H": 2, "W": 3}
    with pytest.raises(ValueError, match=r"d must be \(H, W\) or \(B, 1, H, W\), got \(3,\)"):
        check_shape(np.zeros(3), "H W | B 1 H W", "d")


def test_bad_specs_and_inputs():
    with pytest.raises(ValueError, match="'-1' is not a name"):
        check_shape(np.zeros(3), "-1", "x")
    with pytest.raises(ValueError, match="'...' may appear once"):
        check_shape(np.zeros(3), "... N ...", "x")
    with pytest.raises(TypeError, match=r"x must be an array or tensor of shape H W, got list"):
        check_shape([[1.0]], "H W", "x")
