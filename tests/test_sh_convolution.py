"""Tests of ibl_ref.groundtruth.sh_convolution (SH / Funk–Hecke Phong-lobe convolution with a rigorous bound)."""

import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import eval_legendre, sph_harm_y

from ibl_ref.environment import envmap
from ibl_ref.groundtruth import sh_convolution as shc
from ibl_ref.groundtruth import sh_basis as shbasis
from ibl_ref.groundtruth import sh_bounds as shb
from ibl_ref.errors import IBLError, LayoutError, RadianceError


def _brute_force(cube, s, normalized=True):
    """Independent tiny reference: Σ L max(r·ω,0)^s Ω (/ Σ max(r·ω,0)^s Ω) over all texel pairs."""
    n = cube.shape[1]
    d = envmap.texel_directions(n).reshape(-1, 3)
    om = envmap.cube_solid_angles(n).reshape(-1)
    k = np.maximum(d @ d.T, 0.0) ** s * om[None, :]
    num = k @ cube.reshape(-1, cube.shape[-1])
    if normalized:
        num = num / k.sum(axis=1, keepdims=True)
    return num.reshape(cube.shape)


def _sky_with_sun(n, sun_radiance=1e5):
    d = envmap.texel_directions(n)
    sky = 0.6 + 0.3 * d[..., 1:2] * np.array([1.0, 1.1, 1.25]) + 0.05 * np.sin(3 * d[..., 0:1])
    cube = np.array(sky)
    sun = np.array([1.0, 1.002, 0.999]) / np.linalg.norm([1.0, 1.002, 0.999])  # near the (1,1,1) corner
    f, r, c = envmap.direction_to_texel(sun, n)
    cube[f, r, c] = sun_radiance
    return cube


# ------------------------------------------------------------------------------------------------
# zonal coefficients
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("s", [1.0, 2.5, 16.0, 100.0])
def test_zonal_coefficients_match_quadrature(s):
    c = shb.zonal_coefficients(s, 12)
    ref = [2 * np.pi * quad(lambda x: x**s * eval_legendre(ell, x), 0, 1, epsabs=1e-13, epsrel=1e-12)[0]
           for ell in range(13)]
    # quad's requested accuracy (1e-13 abs on the integral, ×2π)
    np.testing.assert_allclose(c, ref, rtol=0, atol=1e-11)


def test_zonal_coefficients_closed_forms_and_large_s():
    for s in (1.0, 7.0, 1e3, 1e6):
        c = shb.zonal_coefficients(s, 200)
        assert np.all(np.isfinite(c))
        # c_0 = 2π/(s+1), c_1 = 2π/(s+2) (∫_0^1 x^s dx, ∫_0^1 x^{s+1} dx)
        assert c[0] == pytest.approx(2 * np.pi / (s + 1), rel=1e-10)
        assert c[1] == pytest.approx(2 * np.pi / (s + 2), rel=1e-10)
    # odd l ≥ 3 vanish for s = 1 (x·P_l integrates to 0 on [0,1] for odd l ≥ 3)
    c1 = shb.zonal_coefficients(1.0, 9)
    np.testing.assert_allclose(c1[3::2], 0.0, atol=1e-15)
    with pytest.raises(IBLError, match=r"zonal_coefficients needs a finite exponent s"):
        shb.zonal_coefficients(float("nan"), 3)


# ------------------------------------------------------------------------------------------------
# real SH basis
# ------------------------------------------------------------------------------------------------
def test_real_sh_matches_scipy():
    rng = np.random.default_rng(3)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    L = 10
    Y = shbasis.real_sh(d, L)
    theta, phi = np.arccos(d[:, 2]), np.arctan2(d[:, 1], d[:, 0])
    for ell in range(L + 1):
        for m in range(-ell, ell + 1):
            c = sph_harm_y(ell, abs(m), theta, phi)
            # real SH from complex ones, Condon–Shortley phase removed: (−1)^m
            ref = c.real if m == 0 else math.sqrt(2) * (-1) ** m * (c.real if m > 0 else c.imag)
            np.testing.assert_allclose(Y[:, ell * ell + ell + m], ref, rtol=0, atol=1e-12)


def test_real_sh_high_band_addition_theorem():
    # Σ_m Y_lm(d)² = (2l+1)/(4π) for every l (addition theorem) — checks stability up to L = 150
    rng = np.random.default_rng(4)
    d = rng.normal(size=(50, 3))
    d[0] = [0, 0, 1]  # pole
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    L = 150
    Y = shbasis.real_sh(d, L)
    assert np.all(np.isfinite(Y))
    for ell in (0, 1, 17, 80, 150):
        band = (Y[:, ell * ell : (ell + 1) ** 2] ** 2).sum(axis=1)
        np.testing.assert_allclose(band, (2 * ell + 1) / (4 * np.pi), rtol=1e-9)


def test_project_evaluate_roundtrip_band_limited():
    rng = np.random.default_rng(5)
    a = rng.normal(size=(49, 2))
    d = envmap.texel_directions(8).reshape(-1, 3)
    v = shbasis.sh_evaluate(a, d)
    np.testing.assert_allclose(v, shbasis.real_sh(d, 6) @ a, atol=1e-12)  # parity split == direct
    with pytest.raises(LayoutError, match=r"SH coefficient array must have \(L\+1\)\^2"):
        shbasis.sh_evaluate(np.zeros((10, 1)), d)


# ------------------------------------------------------------------------------------------------
# convolution: constant / linear environments
# ------------------------------------------------------------------------------------------------
def test_constant_environment_is_reproduced():
    cube = np.full((6, 16, 16, 3), 2.5)
    for s in (1.0, 4.0, 64.0):
        maps, rel, info = shc.convolve_sh(cube, s, L=12)
        # same truncated kernel in numerator and denominator → exact to rounding
        np.testing.assert_allclose(maps, 2.5, rtol=1e-12)


def test_linear_environment_closed_form():
    # L(ω) = a + b·ω → lobe average a + (b·r)(s+1)/(s+2) (continuous Funk–Hecke, c_1/c_0)
    n = 64
    d = envmap.texel_directions(n)
    a, b = 2.0, np.array([0.3, -0.5, 0.8])
    cube = (a + d @ b)[..., None]
    for s in (1.0, 8.0):
        maps, rel, info = shc.convolve_sh(cube, s, L=24, hybrid=False)
        ref = a + (d @ b) * (s + 1) / (s + 2)
        # the SH result equals the *discrete* texel-centre quadrature; its deviation from the continuous
        # closed form is the quadrature error, O((2/N)²) ≈ 1e-3 relative at N = 64
        np.testing.assert_allclose(maps[..., 0], ref, rtol=2e-3)
        # and it equals the discrete brute force of a coarser map within the rigorous bound (below)


# ------------------------------------------------------------------------------------------------
# rigorous bound vs an exact reference (brute force and ibl_ref.groundtruth.phong_convolution's exact)
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [8, 16])
def test_hybrid_bound_holds_with_sun(n):
    cube = _sky_with_sun(n)
    S = [1.0, 4.0, 16.0, 64.0]
    ref = np.stack([_brute_force(cube, s) for s in S])
    for L in (4, 12, 40):  # small L → large errors: the bound must still cover them
        maps, rel, info = shc.convolve_sh_many(cube, S, L=L)
        err = (np.abs(maps - ref) / ref).max(axis=-1)
        assert np.all(err <= rel), (L, float((err / rel).max()))
    # with L = 4 the errors are large, so the test above is not vacuous
    maps, rel, info = shc.convolve_sh_many(cube, [4.0], L=4)
    assert (np.abs(maps[0] - ref[1]) / ref[1]).max() > 1e-3


def test_pure_sh_bound_holds_without_hybrid():
    cube = _sky_with_sun(8, sun_radiance=1e3)
    ref = _brute_force(cube, 8.0)
    maps, rel, info = shc.convolve_sh(cube, 8.0, L=6, hybrid=False)
    assert info["n_bright"] == 0
    err = (np.abs(maps - ref) / ref).max(axis=-1)
    assert np.all(err <= rel)
    assert err.max() > 1e-3  # the sun rings through the truncated series: a real test of the bound


def test_unnormalized_bound_and_other_out_size():
    cube = _sky_with_sun(8)
    n_out = 5
    from ibl_ref.groundtruth import phong_convolution as pc
    for normalized in (True, False):
        ref = pc.convolve_exact(cube, 16.0, normalized=normalized, out_size=n_out)
        maps, rel, info = shc.convolve_sh(cube, 16.0, L=16, normalized=normalized, out_size=n_out)
        assert maps.shape == (6, n_out, n_out, 3)
        err = (np.abs(maps - ref) / ref).max(axis=-1)
        assert np.all(err <= rel)


def test_auto_plan_meets_rtol_against_c1_exact():
    from ibl_ref.groundtruth import phong_convolution as pc
    cube = _sky_with_sun(16)
    S = [4.0, 16.0, 64.0]
    maps, rel, info = shc.convolve_sh_many(cube, S, rtol=1e-3)
    ref = pc.convolve_exact_many(cube, S)
    err = (np.abs(maps - ref) / ref).max(axis=-1)
    assert np.all(err <= rel)
    assert rel.max() <= 1e-3
    assert info["n_bright"] >= 1  # the sun is gathered exactly


def test_texel_radius():
    # centre texel of a 1×1 face: centre (0,0,1)-like, corner at angle atan(√2)
    assert shb.texel_max_radius(1) == pytest.approx(math.atan(math.sqrt(2)), rel=1e-12)
    assert shb.texel_max_radius(64) < shb.texel_max_radius(32)


def test_bad_inputs():
    cube = np.ones((6, 4, 4, 3))
    with pytest.raises(IBLError, match=r"Phong exponent s must be >="):
        shc.convolve_sh(cube, 0.5)
    with pytest.raises(IBLError, match=r"Phong exponent s must be >="):
        shc.convolve_sh(cube, float("nan"))
    with pytest.raises(IBLError, match=r"the SH route cannot represent the"):
        shc.convolve_sh(cube, float("inf"))
    with pytest.raises(LayoutError, match=r"environment cube map: expected an array"):
        shc.convolve_sh(np.ones((5, 4, 4, 3)), 2.0)
    bad = cube.copy()
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(RadianceError, match=r"environment cube map: 1 non\-finite value\(s"):
        shc.convolve_sh(bad, 2.0)


def test_sliding_max_matches_loop():
    rng = np.random.default_rng(6)
    for n, h in ((1, 0), (7, 3), (100, 0), (100, 9), (57, 40)):
        a = rng.random(n)
        ref = np.array([a[max(0, i - h) : i + h + 1].max() for i in range(n)])
        np.testing.assert_array_equal(shb._sliding_max(a, h), ref)


@pytest.mark.parametrize("s,L", [(1.0, 8), (4.0, 12), (30.0, 20)])
def test_envelope_integral_bounds_discrete_error_sum(s, L):
    # the heart of the bound: Σ_j Ω_j |k(r·ω_j) − k_L(r·ω_j)| ≤ E_L for every direction r
    n = 8
    d = envmap.texel_directions(n).reshape(-1, 3)
    om = envmap.cube_solid_angles(n).reshape(-1)
    c = shb.zonal_coefficients(s, L)
    rng = np.random.default_rng(7)
    r = rng.normal(size=(40, 3))
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    t = np.clip(r @ d.T, -1, 1)
    kL = sum(c[ell] * (2 * ell + 1) / (4 * np.pi) * eval_legendre(ell, t) for ell in range(L + 1))
    lhs = (om * np.abs(np.maximum(t, 0) ** s - kL)).sum(axis=1)
    E = shb.legendre_series_truncation_envelope(s, L, shb.texel_max_radius(n))
    assert lhs.max() <= E
    assert lhs.max() > 0.05 * E  # and not absurdly loose


def test_band_limit_lower_bound_never_exceeds_the_tabulated_choice():
    """The planner's table-free lower bound on the SH band limit (orthogonality: E_L ≥ max_{m>L} |c_m|) is never
    above what the truncation tables choose, and says None only where the tables do: skipping the tables with it
    changes no routing decision."""
    from ibl_ref.groundtruth.sh_bounds import band_limit_lower_bound, choose_band_limit, texel_max_radius

    for n in (16, 64, 256):
        rho = texel_max_radius(n)
        for s in (1.0, 2.0, 5.0, 16.0, 64.0, 100.0, 256.0, 1000.0, 1024.0, 4096.0):
            for eta in (1e-2, 8e-4, 1e-5):
                lo, L = band_limit_lower_bound(s, eta), choose_band_limit(s, eta, rho)
                if lo is None:
                    assert L is None, (n, s, eta)
                else:
                    assert L is None or L >= lo, (n, s, eta, lo, L)


def test_band_limit_with_a_cap_is_the_full_tables_choice_capped():
    """``choose_band_limit(…, L_max=cap)`` computes the truncation tables only up to ``cap`` (the router's test of
    whether SH can pay); its answer must be the full table's answer where that is ≤ cap, else None."""
    from ibl_ref.groundtruth.sh_bounds import SH_L_MAX, choose_band_limit, texel_max_radius

    for n in (16, 64, 256):
        rho = texel_max_radius(n)
        for s in (1.0, 5.0, 16.0, 100.0, 256.0, 1024.0, 4096.0):
            for eta in (1e-2, 8e-4, 1e-5):
                full = choose_band_limit(s, eta, rho, SH_L_MAX)
                for cap in (0, 3, 23, 24, 26, 47, 100, SH_L_MAX - 1):
                    want = full if full is not None and full <= cap else None
                    assert choose_band_limit(s, eta, rho, cap) == want, (n, s, eta, cap)
