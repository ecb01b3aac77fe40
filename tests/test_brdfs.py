"""Tests of ibl_ref.lobes.brdfs (analytic isotropic BRDFs, albedo quadrature)."""

import numpy as np
import pytest

from ibl_ref.lobes import brdfs as b
from ibl_ref.errors import IBLError

ALL = [("lambert", dict(kd=0.5)), ("phong", dict(ks=0.7, s=30, kd=0.1)), ("phong_classic", dict(ks=0.5, s=20)),
       ("blinn_phong", dict(ks=0.6, s=50)), ("ward", dict(ks=0.8, alpha=0.1, kd=0.05)),
       ("cook_torrance", dict(alpha=0.3, f0=0.5)), ("cook_torrance", dict(alpha=0.3, distribution="beckmann")),
       ("cook_torrance", dict(alpha=0.3, f0=0.5, smith="height_correlated")), ("ggx", dict(roughness=0.6, f0=0.04, kd=0.2))]


def _rand_dirs(rng, n):
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 2] = np.abs(d[:, 2]) + 1e-3
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("name,params", [p for p in ALL if p[0] != "phong_classic"])
def test_reciprocity_and_finiteness(name, params):
    rng = np.random.default_rng(1)
    f = b.get_brdf(name, **params)
    wi, wo = _rand_dirs(rng, 500), _rand_dirs(rng, 500)
    a, c = f(wi, wo), f(wo, wi)
    assert np.all(np.isfinite(a)) and np.all(a >= 0)
    np.testing.assert_allclose(a, c, rtol=1e-12, atol=1e-300)  # Helmholtz reciprocity, exact up to rounding


@pytest.mark.parametrize("name,params", ALL)
def test_zero_below_horizon_and_broadcasting(name, params):
    f = b.get_brdf(name, **params)
    wo = b.view_direction(0.4)
    wi = b.direction_from_angles(np.linspace(0, np.pi, 7)[:, None], np.linspace(0, 6, 5)[None, :])
    out = f(wi, wo)
    assert out.shape == (7, 5)
    assert np.all(out[wi[..., 2] <= 0] == 0)


def test_albedo_closed_forms():
    # Lambert: kd exactly; normalised Phong and classic Phong at normal view: ks exactly (∫cosˢα cos θ dω =
    # 2π/(s+2) and ∫cosˢα dω = 2π/(s+1) on the hemisphere around n). Gauss–Legendre -> 1e-9.
    assert b.albedo(b.get_brdf("lambert", kd=0.7), 0.9) == pytest.approx(0.7, rel=1e-12)
    assert b.albedo(b.get_brdf("phong", ks=0.8, s=37.0), 0.0) == pytest.approx(0.8, rel=1e-9)
    assert b.albedo(b.get_brdf("phong_classic", ks=0.8, s=37.0), 0.0) == pytest.approx(0.8, rel=1e-9)
    # classic Phong stays ks while the whole lobe is above the horizon (cosˢα ≤ 1e-12 beyond ~ 0.9 rad at s=37)
    assert b.albedo(b.get_brdf("phong_classic", ks=0.8, s=37.0), 0.3) == pytest.approx(0.8, rel=1e-8)


@pytest.mark.parametrize("dist", ["ggx", "beckmann"])
@pytest.mark.parametrize("alpha", [0.05, 0.3, 0.9])
def test_ndf_normalised_and_weak_white_furnace(dist, alpha):
    # ∫ D cos θh dωh = 1; and the Smith identity ∫ G1(wo) max(wo·h,0) D(h) dωh = cos θo (exact for Smith G1 of
    # the same distribution; Heitz 2014).  Quadrature graded around n -> 1e-6 for the normalisation; the kink
    # of max(wo·h, 0) is not on a panel edge, which limits the second integral to ~1e-5 -> tolerance 1e-4.
    h, w = b.hemisphere_rule(0.0, width=alpha / 8)
    D = b.ndf(h[:, 2], alpha, dist)
    assert np.sum(D * h[:, 2] * w) == pytest.approx(1.0, abs=1e-6)
    for tho in (0.3, 1.2):
        wo = np.array([np.sin(tho), 0.0, np.cos(tho)])
        g1 = b.smith_g1(np.cos(tho), alpha, dist)
        val = g1 * np.sum(np.maximum(h @ wo, 0) * D * w)
        assert val == pytest.approx(np.cos(tho), rel=1e-4)


def test_ward_albedo_normal_incidence_close_to_ks():
    # Ward's normalisation is exact only as α → 0 (Ward 1992); at α = 0.04 the deficit is O(α²)~ below 1 %
    a = b.albedo(b.get_brdf("ward", ks=0.8, alpha=0.04), 0.0)
    assert abs(a / 0.8 - 1) < 0.01


def test_cook_torrance_mirror_limit_energy():
    # F0 = 1, small roughness: almost all energy reflected at normal incidence (Smith loss ~ α²)
    a = b.albedo(b.get_brdf("cook_torrance", alpha=0.02, f0=1.0), 0.0, width=0.002)
    assert 0.995 < a <= 1.0 + 1e-9


def test_bad_inputs():
    with pytest.raises(IBLError, match=r"ks must be a finite non\-negative"):
        b.get_brdf("phong", ks=-1.0)
    with pytest.raises(IBLError, match=r"alpha must be a finite number in \[2\^-20, 1\]"):
        b.get_brdf("ward", alpha=0.0)
    with pytest.raises(IBLError, match=r"unknown BRDF 'nope'; available: lambert, phong"):
        b.get_brdf("nope")
    with pytest.raises(IBLError, match=r"distribution must be 'ggx' or 'beckmann'"):
        b.get_brdf("cook_torrance", distribution="blinn")
    with pytest.raises(IBLError, match=r"view angle theta_o must be in"):
        b.view_direction(np.pi / 2)
    with pytest.raises(IBLError, match=r"wi, wo and n must be"):
        b.lambert(np.zeros((3, 2)), np.zeros(3))


def test_ggx_alpha_is_roughness_squared_and_refuses_outside_unit_interval():
    from ibl_ref.conventions import ggx_alpha

    assert ggx_alpha(0.5) == 0.25 and ggx_alpha(1.0) == 1.0
    np.testing.assert_array_equal(ggx_alpha(np.array([0.1, 0.3])), np.array([0.1, 0.3]) ** 2)
    for bad in (0.0, -0.1, 1.0 + 1e-12, np.nan, np.inf):
        with pytest.raises(IBLError, match=r"roughness must be in \(0, 1\]"):
            ggx_alpha(bad)
    with pytest.raises(IBLError, match="roughness must be in"):
        b.get_brdf("ggx", roughness=0.0)
    with pytest.raises(IBLError, match=r"f0 must be in \[0, 1\]"):
        b.get_brdf("ggx", roughness=0.5, f0=1.5)
    with pytest.raises(IBLError, match="smith must be one of"):
        b.get_brdf("ggx", roughness=0.5, smith="uncorrelated")


@pytest.mark.parametrize("alpha", [0.01, 0.09, 0.36, 1.0])
def test_height_correlated_smith_against_the_lambda_closed_form(alpha):
    # GGX Λ(θ) = (−1 + √(1 + α² tan²θ))/2 (Heitz 2014 Eq. 72), written out independently of smith_g1;
    # correlated G = 1/(1 + Λi + Λo) (Eq. 99) is never below the separable product (1−G1i)(1−G1o) ≥ 0
    c = np.linspace(0.02, 1.0, 50)
    ci, co = np.meshgrid(c, c, indexing="ij")

    def lam(x):
        return 0.5 * (-1.0 + np.sqrt(1.0 + alpha**2 * (1.0 - x * x) / (x * x)))

    hc = b.smith_g2(ci, co, alpha, smith="height_correlated")
    np.testing.assert_allclose(hc, 1.0 / (1.0 + lam(ci) + lam(co)), rtol=1e-12)
    np.testing.assert_allclose(b.smith_g2(ci, co, alpha, smith="separable"),
                               1.0 / ((1.0 + lam(ci)) * (1.0 + lam(co))), rtol=1e-12)
    assert np.all(hc >= b.smith_g2(ci, co, alpha, smith="separable") * (1 - 1e-14))


def test_ggx_is_cook_torrance_with_alpha_roughness_squared():
    rng = np.random.default_rng(3)
    wi, wo = _rand_dirs(rng, 200), _rand_dirs(rng, 200)
    a = b.ggx(wi, wo, roughness=0.4, f0=0.9, kd=0.1, smith="separable")
    c = b.cook_torrance(wi, wo, alpha=0.4 ** 2, f0=0.9, kd=0.1, distribution="ggx")
    np.testing.assert_array_equal(a, c)


def test_ggx_height_correlated_white_furnace_below_one_and_mirror_limit():
    # F = 1: the directional albedo is the fraction of light not lost to masking: ≤ 1 (energy conservation),
    # → 1 as roughness → 0 at normal view (the loss is O(α²))
    for r in (0.05, 0.3, 0.7, 1.0):
        for tho in (0.0, 0.8, 1.3):
            a = b.albedo(b.get_brdf("ggx", roughness=r, f0=1.0), tho, width=min(0.02, r * r / 4))
            assert 0.0 < a <= 1.0 + 1e-6
    assert b.albedo(b.get_brdf("ggx", roughness=0.1, f0=1.0), 0.0, width=0.002) > 0.998
