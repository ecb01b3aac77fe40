"""Tests of ibl_ref.lobes.kautz_mccool2000 (greedy radially symmetric lobe fitting)."""

import numpy as np
import pytest

from ibl_ref.lobes import brdfs as b
from ibl_ref.lobes import kautz_mccool2000 as km
from ibl_ref.errors import IBLError

WARD = dict(ks=0.8, alpha=0.04)


@pytest.mark.parametrize("theta_o", [0.0, 0.7, 1.3])
def test_phong_fitted_exactly_by_one_lobe(theta_o):
    # the normalised Phong slice IS a radially symmetric lobe about r: peak at r, profile ks(s+2)/(2π)cosˢγ.
    # Remaining error = linear interpolation of cosˢγ on the γ nodes: h²/8·s ≈ 1.5e-4 (n_gamma=256) -> 1e-3
    s, ks = 40.0, 0.9
    fit = km.fit_single_lobe(b.get_brdf("phong", ks=ks, s=s), theta_o)
    lb = fit.lobes[0]
    assert np.sqrt(fit.err2_after[0] / fit.f2) < 1e-3
    assert abs(lb.theta_off) < 1e-6
    assert lb.scale == pytest.approx(1.0, abs=1e-3)
    assert lb.profile[0] == pytest.approx(ks * (s + 2) / (2 * np.pi), rel=1e-3)
    assert lb.phong_exponent == pytest.approx(s, rel=1e-3)  # best Phong fit recovers the exponent


@pytest.mark.parametrize("theta_o", [0.2, 0.9, 1.3])
def test_single_lobe_energy_matches_albedo_on_independent_rule(theta_o):
    # rescale makes ∫ lobe cos θi = albedo on the fitting rule (width 0.01); check on a 3x finer rule: the two
    # quadratures differ by < 1e-3 relative for these smooth lobes (measured rule error ~1e-5)
    f = b.get_brdf("ward", **WARD)
    lb = km.fit_single_lobe(f, theta_o).lobes[0]
    alb = b.albedo(f, theta_o, width=0.003)
    assert km.lobe_energy(lb, theta_o, width=0.003) == pytest.approx(alb, rel=1e-3)


@pytest.mark.parametrize("theta_o", [0.2, 0.9, 1.3])
def test_multi_lobe_rescale_energy_matches_albedo(theta_o):
    # without rescale the minimum-profile lobes stay below the BRDF, so their energy is at most the albedo; with
    # rescale=True the lobe sum carries the albedo (checked on a 3x finer rule than the fit's, as above), the
    # lobes keep their peaks and shapes (one common factor) and the factor is > 1 (energy was missing)
    f = b.get_brdf("ward", **WARD)
    plain = km.fit_multi_lobe(f, theta_o, 3)
    resc = km.fit_multi_lobe(f, theta_o, 3, rescale=True)
    alb = b.albedo(f, theta_o, width=0.003)
    e_plain = sum(km.lobe_energy(lb, theta_o, width=0.003) for lb in plain.lobes)
    e_resc = sum(km.lobe_energy(lb, theta_o, width=0.003) for lb in resc.lobes)
    assert e_plain < alb * (1 + 1e-3)
    assert e_resc == pytest.approx(alb, rel=1e-3)
    k = resc.lobes[0].scale
    assert k > 1.0 and all(lb.scale == k for lb in resc.lobes)
    for a, c in zip(plain.lobes, resc.lobes):
        np.testing.assert_allclose(c.peak, a.peak, rtol=0, atol=0)
        np.testing.assert_allclose(c.profile, k * a.profile, rtol=1e-15)
        assert c.phong_exponent == pytest.approx(a.phong_exponent, rel=1e-9)


def test_single_2d_lobe_weights_match_albedo():
    f = b.get_brdf("blinn_phong", ks=0.7, s=80)
    ths = np.radians([0.0, 30.0, 60.0])
    slices, p_bar, k = km.fit_single_2d_lobe(f, ths)
    assert p_bar[0] == pytest.approx(1.0)
    for s in slices:
        assert km.lobe_energy(s.lobes[0], s.theta_o, width=0.003) == pytest.approx(
            b.albedo(f, s.theta_o, width=0.003), rel=1e-3)
    assert np.all(k > 0)


def test_multi_lobe_greedy_error_decreases_and_lobes_below_residual():
    f = b.get_brdf("ward", **WARD)
    fit = km.fit_multi_lobe(f, 1.0, n_lobes=4)
    assert len(fit.lobes) == 4
    e = np.array(fit.err2_after)
    # minimum profiles: 0 ≤ lobe ≤ residual on the profiles, so each subtraction reduces the squared error
    assert np.all(np.diff(e) < 0) and e[0] < fit.f2
    wi, _ = b.hemisphere_rule(1.0, 0.01)
    approx = fit(wi)
    fv = f(wi, b.view_direction(1.0))
    # lobes are ≤ residual only on the sampled azimuths; between them (64 azimuths) overshoot stays < 5 % of peak
    assert np.max(approx - fv) < 0.05 * fv.max()


def test_multi_lobe_on_radially_symmetric_slice_needs_one_lobe():
    # Ward at normal view is radially symmetric around n -> the minimum profile equals the slice
    f = b.get_brdf("ward", **WARD)
    fit = km.fit_multi_lobe(f, 0.0, n_lobes=3)
    assert np.sqrt(fit.err2_after[0] / fit.f2) < 2e-3  # profile interpolation error only


def test_track_lobes_follows_offsets():
    g = km.gamma_nodes(16)
    prof = np.cos(np.minimum(g, np.pi / 2)) ** 4

    def lobe(t, off):
        return km.Lobe(t, b.direction_from_angles(t + off, 0.0), g, prof)

    s0 = km.SliceFit(0.5, [lobe(0.5, 0.0), lobe(0.5, 0.2)], 1.0, [0.0, 0.0], 1.0)
    s1 = km.SliceFit(0.6, [lobe(0.6, 0.21), lobe(0.6, 0.01)], 1.0, [0.0, 0.0], 1.0)
    ids = km.track_lobes([s0, s1])
    assert ids == [[0, 1], [1, 0]]


@pytest.mark.parametrize("s", [0.0, 1e-3, 1e5])
def test_extreme_phong_exponents_against_closed_forms(s):
    # modified Phong ks(s+2)/(2π)·max(r·ωi, 0)^s at θo = 0.4, ks = 0.5, against closed forms:
    # * albedo: s = 0 is ks/π on the intersection of the hemispheres of n and r, whose projected solid angle is
    #   π(1 + cos θo)/2 (the r-horizon projects to a half ellipse of semi-axes 1 and cos θo), so the albedo is
    #   ks(1 + cos θo)/2; s = 1e5 is a lobe far above the horizon, ∫cosˢα cos θi dω = cos θo·2π/(s+2) exactly
    #   (the term linear in sin α integrates to 0 over the azimuth), so the albedo is ks·cos θo.  s = 1e-3 differs
    #   from s = 0 by (s+2)/2 and cosˢα: ≤ s·(½ + max E|ln cos α|) < 1.5e-3 relative.  Rule error of the
    #   hemisphere quadrature on the discontinuity along the r-horizon: 2.2e-4 measured (s = 0), so 1e-3; for the
    #   smooth narrow lobe 3e-11 measured, so 1e-6.
    # * peak: the slice's maximum is at r (s > 0) with value ks(s+2)/(2π); offsets within the peak search's
    #   tolerance (Nelder–Mead xatol 1e-7; for s = 1e-3 the peak is so flat that fatol 1e-12 on a value 0.16 allows
    #   ~1e-4 rad); s = 0 is flat: any peak, value ks/π.
    # * energy: the rescale makes the lobe's ∫p cos θi dω equal the albedo on the same rule (to rounding).
    ks, th = 0.5, 0.4
    fit = km.fit_single_lobe(b.get_brdf("phong", ks=ks, s=s), th, n_gamma=256 if s > 1 else 64, n_phi=16)
    lb = fit.lobes[0]
    if s == 0.0:
        assert fit.albedo == pytest.approx(ks * (1 + np.cos(th)) / 2, rel=1e-3)
    elif s < 1:
        assert fit.albedo == pytest.approx(ks * (1 + np.cos(th)) / 2, rel=1.5e-3 + 1e-3)
        assert abs(lb.theta_off) < 1e-4 and abs(lb.phi_off) < 1e-4
    else:
        assert fit.albedo == pytest.approx(ks * np.cos(th), rel=1e-6)
        assert abs(lb.theta_off) < 1e-6 and abs(lb.phi_off) < 1e-6
    assert lb.profile[0] / lb.scale == pytest.approx(ks * (s + 2) / (2 * np.pi), rel=1e-9)
    assert km.lobe_energy(lb, th) == pytest.approx(fit.albedo, rel=1e-12)
    if s > 1:
        # the slice IS a radially symmetric lobe about r (as in test_phong_fitted_exactly_by_one_lobe), so the fit
        # recovers the exponent and needs no rescale up to the profile's linear interpolation, h²·s/8 relative
        # with node spacing h = 8.2e-4 rad where γ ≈ 1/√s (n_gamma = 256): 0.8 %, so 3 % (measured 1.6 %, 1.3 %)
        assert lb.phong_exponent == pytest.approx(s, rel=0.03)
        assert lb.scale == pytest.approx(1.0, rel=0.03)


def test_rms_error_definition():
    s = km.SliceFit(0.1, [], 1.0, [4.0, 1.0], 16.0)
    assert km.rms_error([s], 1) == pytest.approx(0.5)
    assert km.rms_error([s]) == pytest.approx(0.25)


def test_bad_inputs():
    f = b.get_brdf("phong", ks=0.5, s=10)
    with pytest.raises(IBLError, match=r"theta_o must be in \[0, π"):
        km.fit_single_lobe(f, np.pi / 2)
    with pytest.raises(IBLError, match=r"n_lobes must be >= 1, got"):
        km.fit_multi_lobe(f, 0.3, n_lobes=0)
    with pytest.raises(IBLError, match=r"n_gamma must be >= 8, got"):
        km.gamma_nodes(2)


def test_unbounded_slice_at_the_horizon_is_a_clear_error():
    # Ward's 1/sqrt(cos θi) makes the slice unbounded at the horizon; at α = 0.2, θo = 60° its maximum is there
    # (f → ∞), so no radially symmetric lobe fits: a clear error, not a lobe with a peak of 1e8
    f = b.get_brdf("ward", ks=0.8, alpha=0.2)
    wo = b.view_direction(np.radians(60.0))
    ang = np.radians([89.9, 89.99, 89.9999])
    vals = f(np.stack([np.sin(ang), 0 * ang, np.cos(ang)], axis=1), wo)
    assert np.all(np.diff(vals) > 0) and vals[-1] > 50 * f((wo * [-1, 1, 1])[None], wo)[0]  # above the mirror
    with pytest.raises(IBLError, match="horizon"):
        km.fit_single_lobe(f, np.radians(60.0))
    with pytest.raises(IBLError, match="horizon"):
        km.fit_multi_lobe(f, np.radians(60.0), 3)
    # a bounded grazing peak is fitted as usual: GGX Cook–Torrance (Smith masking) at θo = 75° has its maximum on
    # the horizon but finite (≈ 53 vs 42 at the mirror direction)
    ct = km.fit_single_lobe(b.get_brdf("cook_torrance", alpha=0.15, f0=0.9, distribution="ggx"), np.radians(75.0))
    assert np.isfinite(ct.lobes[0].profile).all() and ct.lobes[0].profile[0] < 1e3
    # the paper's α = 0.04 peaks near r up to θo = 80° (its horizon singularity is far below the peak): fits
    fit = km.fit_multi_lobe(b.get_brdf("ward", **WARD), np.radians(80.0), 3)
    assert fit.lobes and all(np.isfinite(lb.profile).all() for lb in fit.lobes)
