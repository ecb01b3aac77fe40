"""Tests of ibl_ref.prefilter.ggx_phong_mapping (GGX roughness → Phong exponent, lobe errors)."""

import warnings

import numpy as np
import pytest
from scipy import integrate, optimize

from ibl_ref.environment import envmap
from ibl_ref.errors import IBLError
from ibl_ref.groundtruth.phong_convolution import lobe_average
from ibl_ref.prefilter import ggx_phong_mapping as g, karis2013 as k
from ibl_ref.synthetic import synthetic_envs as se


def _quad(f, a, b, pts):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", integrate.IntegrationWarning)
        edges = [a] + sorted(p for p in pts if a < p < b) + [b]
        return sum(integrate.quad(f, lo, hi, epsabs=0, epsrel=1e-13, limit=500)[0]
                   for lo, hi in zip(edges[:-1], edges[1:]))


@pytest.mark.parametrize("r", [0.1, 0.3, 0.6, 0.9])
def test_kernel_integrals_against_closed_form_and_adaptive_quadrature(r):
    # ∫₀¹ K dc in closed form (x = (1+c)/2, y = (α²−1)x + 1): (2α²/(πβ²))·[2 ln(2α²/(1+α²)) + (1+α²)/α² − 2],
    # β = α² − 1 (rational integrand); the mean cosine against scipy's adaptive quadrature with breakpoints at
    # 1 − α²·{1, 10, 100}: both to 1e-10 relative
    a2 = r ** 4
    b = a2 - 1
    closed = 2 * a2 / (np.pi * b * b) * (2 * np.log(2 * a2 / (1 + a2)) + (1 + a2) / a2 - 2)
    assert g.kernel_mass(r) == pytest.approx(closed, rel=1e-10)
    pts = [1 - a2 * x for x in (1, 10, 100)]

    def kern(c):
        return float(k.prefilter_kernel(c, r))

    mu = _quad(lambda c: kern(c) * c, 0, 1, pts) / _quad(kern, 0, 1, pts)
    assert g.kernel_mean_cosine(r) == pytest.approx(mu, rel=1e-10)


def test_roughness_one_is_exactly_the_cosine_lobe():
    # α = 1: D = 1/π is constant, K(c) = max(c, 0)/π: s = 1 for every mapping and TV = 0
    for m in g.MAPPINGS:
        assert g.phong_exponent(1.0, m) == 1.0
    assert g.lobe_tv(1.0, 1.0) < 1e-12
    assert g.kernel_mean_cosine(1.0) == pytest.approx(2 / 3, rel=1e-13)  # (s+1)/(s+2) at s = 1


@pytest.mark.parametrize("r", [0.2, 0.5, 0.8])
def test_peak_curvature_mapping_against_finite_differences(r):
    # s = −d²(ln K)/dγ² at γ = 0 (a Phong lobe has ln cos^s γ = −sγ²/2 + O(γ⁴)); central differences of the
    # kernel at step h = α/100 have relative error O(h²/α²) ≈ 1e-4 -> tolerance 1e-3
    alpha = r * r
    h = alpha / 100
    lnk = [np.log(k.prefilter_kernel(np.cos(x), r)) for x in (-h, 0.0, h)]
    s_fd = -(lnk[0] - 2 * lnk[1] + lnk[2]) / h ** 2
    assert g.phong_exponent(r, "peak_curvature") == pytest.approx(s_fd, rel=1e-3)
    assert g.phong_exponent(r, "peak_curvature") == pytest.approx(1 / alpha ** 2)


@pytest.mark.parametrize("r", [0.2, 0.5])
def test_mean_cosine_mapping_preserves_a_linear_environment(r):
    # equal mean cosines: L = a + b·ω is prefiltered to a + ⟨c⟩ b·r by both lobes; the exact GGX prefilter and the
    # exact Phong lobe average of a 32² gradient map agree to the texel quadrature's O(N⁻²) (measured 1.6e-5 of
    # |b|) -> 1e-4·|b|
    s = g.phong_exponent(r, "mean_cosine")
    assert g.phong_mean_cosine(s) == pytest.approx(g.kernel_mean_cosine(r), rel=1e-12)
    b = np.array([0.2, -0.4, 0.3])
    cube = se.env_gradient(32, a=1.0, b=b, sample="center")
    d = envmap.texel_directions(2).reshape(-1, 3)
    np.testing.assert_allclose(lobe_average(cube, d, s), k.prefilter_exact(cube, r, dirs=d),
                               atol=1e-4 * np.linalg.norm(b))


@pytest.mark.parametrize("r", [0.1, 0.3, 0.6])
def test_total_variation_against_adaptive_quadrature(r):
    # TV = π ∫₀¹ |K̂ − P̂_s| dc by scipy's adaptive quadrature in c, split at the crossings of the two lobes (sign
    # changes on a fine grid, refined by brentq) and at 1 − α²·{1, 10, 100}; measured agreement 1e-12 -> 1e-10
    s = g.phong_exponent(r, "mean_cosine")
    a2 = r ** 4
    m = g.kernel_mass(r)

    def diff(c):
        return float(k.prefilter_kernel(c, r)) / (2 * np.pi * m) - (s + 1) / (2 * np.pi) * c ** s

    grid = np.unique(np.r_[1 - np.geomspace(1e-12, 1, 4000), np.linspace(0, 1, 4001)])
    sign = np.sign([diff(c) for c in grid])
    kinks = [optimize.brentq(diff, grid[i], grid[i + 1], xtol=1e-15) for i in np.nonzero(sign[:-1] != sign[1:])[0]]
    pts = kinks + [1 - a2 * x for x in (1, 10, 100)]
    ref = np.pi * _quad(lambda c: abs(diff(c)), 0, 1, pts)
    assert g.lobe_tv(r, s) == pytest.approx(ref, abs=1e-10)


def test_tv_optimal_is_the_minimum_and_the_default():
    for r in (0.1, 0.3, 0.6):
        s = g.phong_exponent(r)
        assert s == g.phong_exponent(r, "tv_optimal")
        tv = g.lobe_tv(r, s)
        for other in (s * 0.97, s * 1.03, g.phong_exponent(r, "mean_cosine"), g.phong_exponent(r, "peak_curvature")):
            assert tv <= g.lobe_tv(r, other) + 1e-12
    # measured lobe errors (TV of the best single Phong lobe): ≈ 0.18 at roughness ≤ 0.2 (GGX's θh⁻⁴ tail), 0.073
    # at 0.6, 0.028 at 0.8
    assert 0.17 < g.lobe_tv(0.1, g.phong_exponent(0.1)) < 0.19
    assert 0.06 < g.lobe_tv(0.6, g.phong_exponent(0.6)) < 0.085
    np.testing.assert_allclose(g.phong_exponent(np.array([[0.3, 0.6]])), [[g.phong_exponent(0.3),
                                                                             g.phong_exponent(0.6)]])


def test_tv_bounds_the_prefilter_error_of_the_substitution():
    # |P_Phong − P_GGX| ≤ TV·(max L − min L) in the continuum; on a 32² studio map the discrete lobes differ from the
    # continuum by the texel quadrature, so a 10 % margin is allowed on the bound (measured ratio ≤ 0.15: the bound
    # is attained only by an environment that is max L exactly where K̂ > P̂_s and min L elsewhere)
    cube = se.env_studio(32)
    d = envmap.texel_directions(4).reshape(-1, 3)
    spread = cube.max(axis=(0, 1, 2)) - cube.min(axis=(0, 1, 2))
    for r in (0.4, 0.7):
        s = g.phong_exponent(r)
        err = np.abs(lobe_average(cube, d, s) - k.prefilter_exact(cube, r, dirs=d))
        assert np.all(err <= 1.1 * g.lobe_tv(r, s) * spread)


def test_split_sum_lobe_against_the_true_ggx_lobe():
    # the n = v = r kernel vs the true normalised lobe f(l, v)(n·l)/albedo: at normal view they differ only by the
    # weight G·F against n·l (TV 1.1e-3 at roughness 0.1, 0.10 at 0.6); away from the normal the true lobe is
    # stretched and moves off the mirror direction ("no stretched reflections", Karis): TV grows with θv to ≈ 0.5
    # at 75°.  The quadrature is converged: halving its finest panel changes TV by < 1e-4.
    for r in (0.1, 0.3, 0.6):
        tvs = [g.brdf_lobe_tv(r, np.radians(t)) for t in (0, 45, 75)]
        assert tvs[0] < tvs[1] < tvs[2] and 0.45 < tvs[2] < 0.55
        assert abs(g.brdf_lobe_tv(r, np.radians(45), width=r * r / 8) - tvs[1]) < 1e-4
        # a Phong lobe about r is further from the true lobe than K itself at every view angle here
        s = g.phong_exponent(r)
        assert all(g.brdf_lobe_tv(r, np.radians(t), s) > tv for t, tv in zip((0, 45, 75), tvs))
    assert g.brdf_lobe_tv(0.1, 0.0) < 2e-3
    assert 0 <= g.brdf_lobe_tv(0.9, np.radians(80), 2.0) <= 1


def test_ggx_phong_mapping_class():
    cube = se.env_studio(8)
    m = g.GGXPhongMapping.build(cube, dfg_size=16)
    assert m.lobe == "ggx" and m.error_bound is None and m.mapping == "tv_optimal"
    assert m.nbytes == cube.nbytes + 2 * 16 * 16 * 8
    d = np.random.default_rng(3).normal(size=(2, 5, 3))
    rough = np.array([[0.3] * 5, [0.7] * 5])
    got = m.lookup(d, rough)
    assert got.shape == (2, 5, 3)
    np.testing.assert_allclose(got[1], lobe_average(cube, d[1], g.phong_exponent(0.7)), rtol=1e-13)
    n = np.array([0.0, 0.0, 1.0])
    v = np.array([0.6, 0.0, 0.8])
    A, B = m.dfg.lookup(0.8, 0.3)
    np.testing.assert_allclose(m.shade(n, v, 0.3, 0.04), m.lookup(2 * 0.8 * n - v, 0.3) * (0.04 * A + B), rtol=1e-13)
    calls = []
    m2 = g.GGXPhongMapping.from_lookup(lambda dd, s: calls.append(s) or np.ones(dd.shape[:-1] + (1,)),
                                       mapping="mean_cosine")
    m2.lookup(d, 0.5)
    assert calls == [g.phong_exponent(0.5, "mean_cosine")]


def test_ggx_phong_mapping_on_a_registered_phong_prefilter():
    # the registry entry ggx-phong-pem: the paper's pyramid (default) or any Phong method by name; its look-up is
    # that method's look-up at s(roughness), its regions the method's PEMs (Σ_i PEM_i = the whole map, Sec. 3.1)
    from ibl_ref.knuth2014.median_cut import median_cut
    from ibl_ref.prefilter import build_prefilter
    from ibl_ref.prefilter.knuth2014_pyramid import Knuth2014Pyramid

    cube = se.env_studio(8)
    m = build_prefilter(cube, "ggx-phong-pem", dfg_size=16)
    assert m.phong_method is Knuth2014Pyramid
    d = np.random.default_rng(4).normal(size=(30, 3))
    for r in (0.1, 0.45, 1.0):
        np.testing.assert_allclose(m.lookup(d, r), Knuth2014Pyramid(cube).lookup(d, g.phong_exponent(r)),
                                   rtol=1e-13)
    assert m.nbytes == m.phong.nbytes + 2 * 16 * 16 * 8
    pems = m.region_prefilters(median_cut(cube, 6))
    s = g.phong_exponent(0.3)
    np.testing.assert_allclose(pems.lookup_all(d, 1 - 1 / s).sum(axis=0), m.lookup(d, 0.3), rtol=2e-6)
    ex = build_prefilter(cube, "ggx-phong-pem", phong_method="exact-lobe", phong_params={"factor": 2.0},
                         dfg_size=16)
    assert ex.phong.lookup(d, 5.0).shape == (30, 3) and ex.phong_params == {"factor": 2.0}
    with pytest.raises(IBLError, match="Phong prefilter class"):
        g.GGXPhongMapping(cube, phong_method="pyramid")  # names are resolved by build_prefilter
    with pytest.raises(IBLError, match="Phong prefilter class"):
        build_prefilter(cube, "ggx-phong-pem", phong_method="split-sum")


def test_mapping_bad_input():
    for call, word in ((lambda: g.phong_exponent(0.0), "roughness"), (lambda: g.phong_exponent(1.2), "roughness"),
                       (lambda: g.phong_exponent(0.5, "blinn"), "mapping"), (lambda: g.lobe_tv(0.5, 0.5), ">= 1"),
                       (lambda: g.lobe_tv(0.5, np.nan), ">= 1"), (lambda: g.kernel_mean_cosine(np.nan), "roughness"),
                       (lambda: g.brdf_lobe_tv(0.5, 0.3, f0=2.0), "F0"),
                       (lambda: g.brdf_lobe_tv(0.5, 2.0), "theta_o"),
                       (lambda: g.GGXPhongMapping(None, mapping="x"), "mapping"),
                       (lambda: g.GGXPhongMapping.from_lookup(None, mapping="x"), "mapping")):
        with pytest.raises(IBLError) as e:
            call()
        assert word in str(e.value) and "\n" not in str(e.value)
