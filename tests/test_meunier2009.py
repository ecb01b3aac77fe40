"""Tests of ibl_ref.lobes.meunier2009 (Meunier et al. 2009 cosine-lobe algebra)."""

import numpy as np
import pytest
from scipy import integrate

from ibl_ref.lobes import meunier2009 as m
from ibl_ref.environment.envmap import cube_solid_angles, texel_directions
from ibl_ref.errors import IBLError


@pytest.mark.parametrize("e", [0.0, 0.37, 1.0, 7.5, 250.0, 1e5])
def test_integral_closed_form_vs_adaptive_quadrature(e):
    # independent route: scipy.integrate.quad over the polar angle, epsrel 1e-12 -> compare at 1e-9
    assert m.lobe_integral(e) == pytest.approx(m.lobe_integral_quadrature(e), rel=1e-9)


def test_integral_closed_form_vs_cube_grid():
    # second independent route: sum over a 128^2 cube grid with exact texel solid angles; the lobe (e=3) is
    # smooth except for the kink at the horizon, so a midpoint rule is good to ~1e-4 relative at N=128.
    d = texel_directions(128)
    w = cube_solid_angles(128)
    axis = np.array([0.3, -0.5, 0.81])
    val = float(np.sum(m.cosine_lobe(d, axis, 3.0, s=2.5) * w))
    assert val == pytest.approx(m.lobe_integral(3.0, s=2.5), rel=5e-4)


def test_integral_table_interpolation_error_small():
    # paper Sec. 4.2: 128 samples per decade, linear interpolation; the linear-interpolation error bound is
    # h^2/8 |f''|/f = h^2/(4(e+1)^2); at the start of a decade [d, 10d], h = 9d/127, so for large d it tends to
    # (9/127)^2/4 = 1.256e-3 relative -> assert < 1.3e-3
    tab = m.IntegralTable()
    e = np.concatenate([np.linspace(0, 1, 1001), np.geomspace(1, 1e5, 5001)])
    rel = np.abs(tab(e) / m.lobe_integral(e) - 1)
    assert rel.max() < 1.3e-3
    assert np.all(np.isfinite(rel))


def test_identical_axes_exact():
    a = np.array([0.0, 0.6, 0.8])
    axis, e_r, s_r = m.lobe_product(a, 12.5, 2.0, a * 3.0, 30.25, 0.5)
    assert e_r == 12.5 + 30.25  # exact, no fit: max(a.v,0)^e1 max(a.v,0)^e2 = max(a.v,0)^(e1+e2)
    assert s_r == 2.0 * 0.5
    np.testing.assert_allclose(axis, a, atol=1e-15)
    f = m.fit_product(3.0, 4.0, 0.0)
    assert f.exact and f.e_r == 7.0 and f.p == 1.0


def test_small_angle_product_tends_to_sum_of_exponents():
    # continuity with the exact shortcut: θ = 1e-4 for e1 = e2 = 50 -> e_r ≈ 100, p_r ≈ 1
    f = m.fit_product(50.0, 50.0, 1e-4)
    assert f.e_r == pytest.approx(100.0, rel=1e-4)
    assert f.p == pytest.approx(1.0, rel=1e-4)


@pytest.mark.parametrize("e1,e2,theta", [(1.0, 1.0, 0.5), (10.0, 20.0, 0.3), (3.0, 100.0, 1.2), (0.5, 0.5, 1.5)])
def test_product_axis_on_arc_matches_root(e1, e2, theta):
    # Nelder–Mead axis (Eq. 18) vs an independent Brent root of e1 tan t = e2 tan(θ−t); NM xatol 1e-10
    f = m.fit_product(e1, e2, theta)
    assert f.t == pytest.approx(m._axis_root(e1, e2, theta), abs=1e-7)


def test_product_integral_exact_vs_sphere_quadrature():
    # the separable Wallis × quad reference vs a brute-force 2-D scipy dblquad in ordinary spherical coordinates
    e1, e2, th = 2.0, 5.0, 0.7
    a1 = np.array([0.0, 0.0, 1.0])
    a2 = np.array([np.sin(th), 0.0, np.cos(th)])

    def f(phi, beta):
        v = np.array([np.sin(beta) * np.cos(phi), np.sin(beta) * np.sin(phi), np.cos(beta)])
        return max(a1 @ v, 0) ** e1 * max(a2 @ v, 0) ** e2 * np.sin(beta)

    ref, _ = integrate.dblquad(f, 0, np.pi / 2, 0, 2 * np.pi, epsabs=1e-10, epsrel=1e-8)
    assert m.product_integral_exact(e1, e2, th) == pytest.approx(ref, rel=1e-6)


@pytest.mark.parametrize("e1,e2,theta", [(1.0, 1.0, 0.5), (3.0, 100.0, 1.2), (1e4, 10.0, 0.2)])
def test_lm_and_varpro_agree(e1, e2, theta):
    # same L2 problem (Eq. 19) by two optimisers: LM on (log p, log e) vs closed-form scale + 1-D search
    a = m.fit_product(e1, e2, theta, method="lm")
    b = m.fit_product(e1, e2, theta, method="varpro")
    assert a.e_r == pytest.approx(b.e_r, rel=1e-5)
    assert a.log_p == pytest.approx(b.log_p, abs=1e-5)
    assert a.l2_rel <= b.l2_rel * (1 + 1e-6) + 1e-12 or abs(a.l2_rel - b.l2_rel) < 1e-8


def test_flat_lune_product_lm_not_stuck():
    # e1 = e2 = 0: the product is the lune of two hemispheres; plain LM from e_r = e1+e2 can run to the
    # e_r → ∞ plateau (l2 = 1).  The returned fit must be as good as the variable-projection optimum.
    a = m.fit_product(0.0, 0.0, 1.8849555921538759)
    b = m.fit_product(0.0, 0.0, 1.8849555921538759, method="varpro")
    assert a.l2_rel < 0.9 and a.l2_rel <= b.l2_rel + 1e-9


def test_product_fit_residual_vs_brute_force_grid():
    # the fit's l2_rel is recomputed on an independent 256^2 cube grid with exact texel solid angles
    e1, e2, th = 4.0, 9.0, 0.6
    f = m.fit_product(e1, e2, th)
    a1 = np.array([1.0, 0.0, 0.0])
    a2 = np.array([np.cos(th), np.sin(th), 0.0])
    ar = np.array([np.cos(f.t), np.sin(f.t), 0.0])
    d = texel_directions(256)
    w = cube_solid_angles(256)
    prod = m.cosine_lobe(d, a1, e1) * m.cosine_lobe(d, a2, e2)
    fit = m.cosine_lobe(d, ar, f.e_r, s=f.p)
    l2 = np.sqrt(np.sum((prod - fit) ** 2 * w) / np.sum(prod**2 * w))
    assert l2 == pytest.approx(f.l2_rel, rel=2e-2)  # midpoint grid error ~1e-3 relative on the norms
    assert float(np.sum(prod * w)) == pytest.approx(f.integral_exact, rel=2e-3)


@pytest.mark.parametrize("e1,e2,theta", [(0.0, 0.0, 1.0), (0.0, 1e5, 0.3), (1e5, 1e5, 0.5), (1e5, 0.0, 2.5),
                                         (0.0, 0.0, np.pi), (1e5, 1e5, 3.1), (1e-6, 1e5, 1.0)])
def test_product_extreme_exponents_closed_forms(e1, e2, theta):
    f = m.fit_product(e1, e2, theta)
    for v in (f.t, f.e_r, f.p, f.integral_exact, f.integral_fit, f.l2_rel):
        assert np.isfinite(v)
    assert not np.isnan(f.log_p)
    assert 0 <= f.t <= theta and f.e_r >= 0 and f.p >= 0
    # the exact integral of the product in closed form at the extremes:
    # e = 0 lobes are hemispheres; two of them with axes θ apart overlap in a lune of 2(π − θ) sr
    if e1 == 0.0 and e2 == 0.0:
        assert f.integral_exact == pytest.approx(2 * (np.pi - theta), abs=1e-9)
    # a 1e5 lobe is a near-delta of weight 2π/(e+1) at its axis: times the other (wide, e ≤ 1e-6) lobe's value
    # there, max(cos θ, 0)^e (1 for a hemisphere containing it, 0 outside); relative tolerance 1e-3 from the
    # lobe's width (≈ 0.3°) against the hemisphere's edge or the other lobe's slope.  The product peaks at the
    # narrow lobe's axis (t = θ or 0) to within that width
    if max(e1, e2) == 1e5 and min(e1, e2) <= 1e-6:
        other = min(e1, e2)
        value = np.maximum(np.cos(theta), 0.0) ** other if theta < np.pi / 2 else 0.0
        assert f.integral_exact == pytest.approx(2 * np.pi / (1e5 + 1) * value, rel=1e-3, abs=1e-12)
        if value > 0:
            assert f.t == pytest.approx(theta if e2 == 1e5 else 0.0, abs=1e-3)
    # two equal 1e5 lobes θ ≥ 0.5 apart: by symmetry the product peaks on the bisector, t = θ/2, where it is
    # cos(θ/2)^(2e5) ≤ e^(−6316): the exact integral is 0 in float64
    if e1 == e2 == 1e5:
        assert f.t == pytest.approx(theta / 2, rel=1e-6)
        assert f.integral_exact == 0.0


def test_cap_exponent_closed_form_error_matches_quadrature():
    # Eq. 32 evaluated in closed form vs scipy.quad over μ = cos β
    e, alpha = 7.3, 0.6
    mu0 = np.cos(alpha)
    val, _ = integrate.quad(lambda mu: ((mu >= mu0) - max(mu, 0.0) ** e) ** 2, -1, 1, points=[0.0, mu0],
                            epsabs=1e-13)
    assert m.cap_fit_error(e, alpha) == pytest.approx(2 * np.pi * val, rel=1e-9)


def test_cap_exponent_is_the_minimiser():
    # independent route: brute-force minimisation of the closed-form error over a dense log grid of e
    for alpha in (0.05, 0.3, 1.0, 1.5):
        e_star = m.cap_exponent(alpha)
        grid = np.geomspace(e_star / 1.2, e_star * 1.2, 20001)
        e_grid = grid[np.argmin(m.cap_fit_error(grid, alpha))]
        assert e_star == pytest.approx(e_grid, rel=2e-5)  # grid spacing 1.8e-5 relative


def test_cap_exponent_monotone_and_limits():
    alpha = np.linspace(1e-3, np.pi, 400)
    e = m.cap_exponent(alpha)
    assert np.all(np.diff(e) <= 0)
    assert np.all(e[alpha < np.pi / 2 - 1e-9] > 0) and np.all(e[alpha >= np.pi / 2] == 0)
    # small-cap Gaussian limit: e ≈ 2y/α², (1+y)e^{-y} = 3/4  (y = 0.961279...) ; O(α²) correction
    from scipy.optimize import brentq

    y = brentq(lambda y: (1 + y) * np.exp(-y) - 0.75, 0.1, 5)
    assert m.cap_exponent(1e-3) * 1e-6 == pytest.approx(2 * y, rel=1e-5)


def test_cap_angle_inverts_cap_exponent():
    for e in (0.01, 1.0, 50.0, 1e5):
        assert m.cap_exponent(m.cap_angle(e)) == pytest.approx(e, rel=1e-8)
    assert m.cap_angle(0.0) == pytest.approx(np.pi / 2)


def test_cap_table_error_and_improved_table():
    alpha = np.linspace(0.01, np.pi / 2, 3001)
    exact = m.cap_exponent(alpha)
    better = m.CapTable(1000, mode="alpha2e")(alpha)
    ok = alpha <= 1.5
    # α²e is smooth and ~2 -> interpolation error O(h²) ~ 1e-6; assert 1e-4 relative (α ≤ 1.5); near π/2, e → 0
    # with a log-type singularity: assert absolute error < 1e-3 there (e itself is < 0.15 on that range)
    assert np.max(np.abs(better[ok] / exact[ok] - 1)) < 1e-4
    assert np.max(np.abs(better - exact)[~ok]) < 1e-3


def test_region_equivalent_lobe():
    om = np.array([1e-4, 0.05, 1.0, 2 * np.pi])
    r = m.region_equivalent_lobe(om)
    np.testing.assert_allclose(4 * np.pi * np.sin(r.alpha / 2) ** 2, om, rtol=1e-12)  # = 2π(1 − cos α)
    np.testing.assert_allclose(m.lobe_integral(r.exponent, r.scale_energy), om, rtol=1e-12)
    assert np.all(np.diff(r.exponent) <= 0)


def test_bad_inputs_raise():
    with pytest.raises(IBLError, match=">= 0"):
        m.lobe_integral(-1.0)
    with pytest.raises(IBLError, match="zero-length"):
        m.cosine_lobe([[0, 0, 1.0]], [0, 0, 0], 2.0)
    with pytest.raises(IBLError, match=r"e2: must be finite, got nan"):
        m.fit_product(1.0, np.nan, 0.3)
    with pytest.raises(IBLError, match=r"theta must be in \[0, π\]"):
        m.fit_product(1.0, 1.0, 4.0)
    with pytest.raises(IBLError, match=r"cap half\-angle alpha must be in"):
        m.cap_exponent(0.0)
    with pytest.raises(IBLError, match=r"solid_angle must be in \(0, 4π\]"):
        m.region_equivalent_lobe(-1.0)
    with pytest.raises(IBLError, match=r"axis2 contains zero\-length vectors \(length <="):
        m.lobe_product([0, 0, 1], 1.0, 1.0, [0, 0, 0], 1.0, 1.0)


def test_product_table_nodes_and_symmetry():
    es = np.array([0.0, 2.0, 20.0])
    th = np.array([0.0, 0.8, 1.6])
    T = m.ProductTable(es, th, method="varpro")
    # at a node the table returns the fit itself (interpolation weights are 0/1)
    f = m.fit_product(2.0, 20.0, 0.8, method="varpro")
    t, er, p = T(2.0, 20.0, 0.8)
    assert float(t) == pytest.approx(f.t, abs=1e-12) and float(er) == pytest.approx(f.e_r, rel=1e-12)
    assert float(p) == pytest.approx(f.p, rel=1e-12)
    # swapping the lobes mirrors the axis: t(e2, e1) = θ − t(e1, e2), same e_r and p (off-node too)
    t1, er1, p1 = T(5.0, 13.0, 1.1)
    t2, er2, p2 = T(13.0, 5.0, 1.1)
    assert float(t1 + t2) == pytest.approx(1.1, abs=1e-8)  # diagonal e1 = e2 nodes: t/θ = ½ ± NM xatol (1e-10)
    assert float(er1) == pytest.approx(float(er2), rel=1e-12) and float(p1) == pytest.approx(float(p2), rel=1e-12)
    with pytest.raises(IBLError, match=r"ProductTable: point outside the table range"):
        T(50.0, 1.0, 0.3)


def test_lobe_product_3d_axis_is_product_maximum():
    # general 3-D axes: the returned axis maximises c1·c2 (checked against a 128^2-per-face direction grid:
    # no grid direction may exceed the value at the returned axis), and s_r = s1 s2 p_r
    rng = np.random.default_rng(7)
    a1 = rng.normal(size=3)
    a2 = a1 / np.linalg.norm(a1) + 0.8 * rng.normal(size=3)
    ar, e_r, s_r = m.lobe_product(a1, 6.0, 2.0, a2, 15.0, 0.25)
    assert np.linalg.norm(ar) == pytest.approx(1.0, abs=1e-12)
    d = texel_directions(128).reshape(-1, 3)
    prod = m.cosine_lobe(d, a1, 6.0) * m.cosine_lobe(d, a2, 15.0)
    at_axis = float(m.cosine_lobe(ar[None], a1, 6.0)[0] * m.cosine_lobe(ar[None], a2, 15.0)[0])
    assert at_axis >= prod.max() * (1 - 1e-12)
    th = np.arccos(np.clip(a1 @ a2 / np.linalg.norm(a1) / np.linalg.norm(a2), -1, 1))
    assert s_r == pytest.approx(0.5 * m.fit_product(6.0, 15.0, th).p, rel=1e-6)
