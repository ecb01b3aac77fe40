"""Float64 range of ibl_ref.groundtruth.convolve.convolve: no overflow near 1e308, rigorous bounds where exact values underflow.

References are independent of the code under test: the lobe average of a constant map is the constant
(a convex combination), and for a map with a single lit texel j the exact lobe average has the closed
form ``L_j w_j Ω_j / Σ_k w_k Ω_k`` (w = max(r·ω, 0)^s), evaluated here in log space so that values far
below the float64 range (subnormal or < 1e-324) are still known exactly in logarithm.
"""

import numpy as np
import pytest

from ibl_ref.environment import envmap
from ibl_ref.groundtruth.convolve import convolve
from ibl_ref.errors import IBLError

N = 16


@pytest.mark.parametrize("method,s", [("exact", 1.0), ("moment", 1.0), ("sh", 4.0), ("sparse", 64.0),
                                      ("auto", 1.0), ("auto", 64.0), ("exact", np.inf)])
def test_near_max_float_stays_finite(method, s):
    cube = np.full((6, N, N, 3), 1e308)
    res = convolve(cube, [s], method=method, workers=1)
    m = res.maps[s]
    assert np.all(np.isfinite(m))
    # a lobe average of a constant is that constant; float64 rounding of ≤ 6N² terms ≲ 1e-13
    assert np.max(np.abs(m / 1e308 - 1.0)) < 1e-13
    assert np.all(res.error_bound[s] <= 1e-3)


def test_unnormalized_sum_beyond_float_range_is_a_clear_error():
    cube = np.full((6, N, N), 1e308)
    # literal Eq. 4 for L ≡ 1e308, s = 1: ≈ π·1e308 > 1.8e308 — not representable
    with pytest.raises(IBLError, match="exceeds the float64 range"):
        convolve(cube, [1.0], method="exact", normalized=False, workers=1)
    # s = 100: 2π/101·1e308 ≈ 6.2e306 is representable (the lobe spans ≈ 2 texels at 16²: quadrature
    # error of the discrete lobe weight a few %)
    res = convolve(cube, [100.0], method="exact", normalized=False, workers=1)
    assert np.all(np.isfinite(res.maps[100.0]))
    assert np.allclose(res.maps[100.0], 2 * np.pi / 101 * 1e308, rtol=0.05)


def _log_exact_single_texel(n, j, value, s):
    d = envmap.texel_directions(n).reshape(-1, 3)
    om = envmap.cube_solid_angles(n).reshape(-1)
    c = d @ d.T
    with np.errstate(divide="ignore"):
        lw = np.where(c > 0, s * np.log(np.where(c > 0, c, 1.0)), -np.inf) + np.log(om)[None, :]
    mx = lw.max(axis=1, keepdims=True)
    lden = mx[:, 0] + np.log(np.exp(lw - mx).sum(axis=1))
    return np.log(value) + lw[:, j] - lden  # −inf where the texel is behind the lobe (exactly 0)


@pytest.mark.parametrize("method,exponents", [("exact", [64.0, 1000.0]), ("sparse", [64.0, 1000.0, 1e4]),
                                              ("sh", [16.0]), ("moment", [1.0, 2.0]),
                                              ("auto", [1.0, 16.0, 1000.0, 1e4])])
def test_bound_holds_where_exact_values_underflow(method, exponents):
    # a zero map plus one 1e6 texel: at s ≥ 1000 most exact lobe averages are far below 1e-308
    cube = np.zeros((6, N, N))
    f, r, c = 0, 3, 5
    cube[f, r, c] = 1e6
    j = (f * N + r) * N + c
    res = convolve(cube, exponents, method=method, workers=1)
    for s in exponents:
        log_e = _log_exact_single_texel(N, j, 1e6, s)
        approx = res.maps[s].reshape(-1)
        bound = res.error_bound[s].reshape(-1)
        lit = np.isfinite(log_e)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.abs(np.expm1(np.log(approx[lit]) - log_e[lit]))  # 1 where approx = 0
        rel = np.where(approx[lit] == 0, 1.0, rel)
        # the reported bound holds (rounding allowance 1e-9 relative on the bound itself)
        assert np.all(rel <= bound[lit] * (1 + 1e-9)), (s, float(rel.max()))
        # texels behind every lit direction: exactly 0
        assert np.all(approx[~lit] == 0.0)
