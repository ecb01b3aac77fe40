"""Tests of ibl_ref.knuth2014.pyramid (Knuth et al. 2014 Fig. 2 filter pyramid) and its energy bookkeeping."""

import numpy as np
import pytest

from ibl_ref.errors import IBLError, LayoutError
from ibl_ref.knuth2014.pyramid import ORDERS, build_mip_chain, build_pyramid, pyramid_energy, shrink_2x2
from ibl_ref.knuth2014.filters import SEAM_MODES


@pytest.mark.parametrize("order", ORDERS)
@pytest.mark.parametrize("seam", SEAM_MODES)
@pytest.mark.parametrize("kernel", ["none", "gauss", "cos", "box", "sqrtcos"])
def test_constant_map_constant_at_every_level(order, seam, kernel):
    c = np.full((6, 16, 16, 3), 0.7, dtype=np.float64)
    p = build_pyramid(c, kernel, order, seam)
    assert [lev.shape[1] for lev in p.levels] == [16, 8, 4, 2, 1]
    for lev in p.levels:
        # convex combinations of 0.7 only: rounding error of a few ulp per operation, ~20 operations
        assert np.allclose(lev, 0.7, rtol=0, atol=1e-13)


def test_level0_is_input_copy_and_dtype():
    rng = np.random.default_rng(0)
    c = rng.random((6, 8, 8, 3)).astype(np.float32)
    p = build_pyramid(c)
    assert np.array_equal(p.levels[0], c) and p.levels[0] is not c
    assert all(lev.dtype == np.float32 for lev in p.levels)


def test_shrink_is_2x2_mean():
    rng = np.random.default_rng(3)
    c = rng.random((6, 4, 4, 1))
    s = shrink_2x2(c)
    assert np.isclose(s[2, 1, 0, 0], c[2, 2:4, 0:2, 0].mean(), rtol=1e-15)


def test_non_power_of_two_rejected_with_message():
    with pytest.raises(LayoutError, match="power-of-two"):
        build_pyramid(np.ones((6, 12, 12, 3)))


def test_bad_names():
    c = np.ones((6, 4, 4, 1))
    with pytest.raises(IBLError, match="shrink_then_filter"):
        build_pyramid(c, order="random")
    with pytest.raises(IBLError, match="box"):
        build_pyramid(c, kernel="mystery")
    with pytest.raises(IBLError, match="clamp"):
        build_pyramid(c, seam="mirror")


def test_energy_drift_one_hot_matches_closed_form():
    # independent computation: texel solid angle from the arctan formula written out here
    def omega(n, r, c):
        A = lambda x, y: np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))
        x0, x1 = -1 + 2 * c / n, -1 + 2 * (c + 1) / n
        y0, y1 = -1 + 2 * r / n, -1 + 2 * (r + 1) / n
        return A(x1, y1) - A(x0, y1) - A(x1, y0) + A(x0, y0)

    n = 8
    c = np.zeros((6, n, n, 1))
    c[1, 0, 0, 0] = 1.0  # a corner texel: where 2x2 averaging is least solid-angle fair
    p = build_mip_chain(c)
    rows = pyramid_energy(p)
    e0 = omega(n, 0, 0)
    e1 = 0.25 * omega(n // 2, 0, 0)  # parent holds 1/4, covers its own solid angle
    assert np.isclose(rows[0]["energy"][0], e0, rtol=1e-12)
    assert np.isclose(rows[1]["energy"][0], e1, rtol=1e-12)
    assert np.isclose(rows[1]["rel_drift"][0], e1 / e0 - 1.0, rtol=1e-10)
    assert abs(rows[1]["rel_drift"][0]) > 1e-3  # the drift is real, not zero


def test_radiance_check():
    c = np.ones((6, 4, 4, 1))
    c[0, 0, 0, 0] = np.nan
    with pytest.raises(IBLError, match=r"environment map: 1 non\-finite value\(s\) \(first"):
        build_pyramid(c)


def test_solid_angle_shrink_conserves_energy_mean_shrink_does_not():
    # independent route: energy = Σ L·Ω with Ω from envmap, compared level by level
    from ibl_ref.environment.envmap import cube_solid_angles

    rng = np.random.default_rng(8)
    c = np.zeros((6, 16, 16, 1))
    c[2, 1, 14, 0] = 5.0  # a bright texel near a corner of +Y
    c += 0.01 * rng.random(c.shape)
    e0 = float((c[..., 0] * cube_solid_angles(16)).sum())
    exact = build_pyramid(c, "none", shrink="solid_angle")
    plain = build_pyramid(c, "none", shrink="mean")
    for lev_a, lev_b in zip(exact.levels, plain.levels):
        n = lev_a.shape[1]
        ea = float((lev_a[..., 0] * cube_solid_angles(n)).sum())
        # the Ω-weighted shrink is exact up to rounding (sums of ~1e3 terms: 1e-13 relative)
        assert abs(ea / e0 - 1) < 1e-12
    eb = float((plain.levels[-1][..., 0] * cube_solid_angles(1)).sum())
    assert abs(eb / e0 - 1) > 0.05  # the paper's plain 2x2 mean drifts measurably for this map
    with pytest.raises(IBLError, match="solid_angle"):
        build_pyramid(c, shrink="median")
