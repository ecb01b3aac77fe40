"""Tests of ibl_ref.rendering.image_metrics on hand-computed arrays."""

import numpy as np
import pytest

from ibl_ref.rendering import image_metrics as im
from ibl_ref.errors import IBLError

A = np.array([[1.0, 2.0], [3.0, 4.0]])
B = np.array([[1.0, 1.0], [1.0, 1.0]])


def test_known_values():
    # differences 0, 1, 2, 3 (by hand)
    assert im.rmse(A, B) == pytest.approx(np.sqrt((0 + 1 + 4 + 9) / 4))
    assert im.rel_l1(A, B) == pytest.approx((0 + 1 + 2 + 3) / 4)
    assert im.rel_max(A, B) == pytest.approx(3.0)
    mask = np.array([[True, True], [False, False]])
    assert im.rmse(A, B, mask) == pytest.approx(np.sqrt(0.5))
    assert im.rel_l1(A, B, mask) == pytest.approx(0.5)
    np.testing.assert_allclose(im.error_map(A, B, mask), [[0, 1], [0, 0]])


def test_colour_images_and_identity():
    rng = np.random.default_rng(0)
    a = rng.uniform(0.1, 1, (5, 4, 3))
    assert im.rmse(a, a) == 0 and im.rel_l1(a, a) == 0 and im.rel_max(a, a) == 0
    # rel_l1 sums over channels: scaling the test image by 1.1 gives exactly 10 %
    assert im.rel_l1(1.1 * a, a) == pytest.approx(0.1)
    assert im.rel_max(1.1 * a, a) == pytest.approx(0.1)


def test_flip_optional():
    val, note = im.flip(A, B)
    if im.flip_available():
        assert val is not None and val >= 0
    else:
        assert val is None and "flip_evaluator" in note


def test_bad_inputs():
    with pytest.raises(IBLError, match="shape"):
        im.rmse(A, np.ones((3, 2)))
    bad = A.copy()
    bad[0, 0] = np.nan
    with pytest.raises(IBLError, match="NaN"):
        im.rel_l1(bad, B)
    with pytest.raises(IBLError, match=r"reference image is zero on the"):
        im.rel_l1(A, np.zeros_like(B))
    with pytest.raises(IBLError, match="mask"):
        im.rmse(A, B, np.zeros((2, 2), bool))
    with pytest.raises(IBLError, match="mask shape"):
        im.rmse(A, B, np.ones((3, 3), bool))
