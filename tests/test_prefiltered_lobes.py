"""Tests of ibl_ref.lobes.prefiltered_lobes (Kautz & McCool 2000 Sec. 4–5 3D maps, Knuth 2014 pyramid extension, reference).

Reference values come from independent routes: closed forms (2π/(s+1), linear-environment lobe averages), the Phong
convolution of ibl_ref.groundtruth.phong_convolution (a different code path), direct evaluation for a single-texel source, and
rotations of the fitting module's own frame.  Tolerances are derived in the comments.
"""

from __future__ import annotations

import numpy as np
import pytest

from ibl_ref.lobes import brdfs as B
from ibl_ref.environment import envmap
from ibl_ref.lobes import kautz_mccool2000 as km
from ibl_ref.lobes import km00_reference as kref
from ibl_ref.groundtruth import phong_convolution as pc
from ibl_ref.lobes import prefiltered_lobes as pl
from ibl_ref.lobes import profile_convolution as pconv
from ibl_ref.synthetic import synthetic_envs as se
from ibl_ref.errors import IBLError, LayoutError
from ibl_ref.knuth2014.pyramid import build_pyramid
from ibl_ref.prefilter import build_prefilter


def _cos_profile(g, s):
    c = np.cos(g)
    return np.where(c > 0, np.maximum(c, 0.0) ** s, 0.0)


def _interp_error(g, s, n_dense=200001):
    """max |linear interpolant − cos^s| on a dense grid (bounds every use of the tabulated profile)."""
    gd = np.linspace(0, np.pi, n_dense)
    return float(np.abs(np.interp(gd, g, _cos_profile(g, s)) - _cos_profile(gd, s)).max())


def _random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


# ----------------------------------------------------------------------------------------------------------------
# (a) radial-profile convolution
# ----------------------------------------------------------------------------------------------------------------
def test_profile_integral_matches_phong_closed_form():
    g = km.gamma_nodes(2048)
    for s in (1.0, 8.0, 100.0):
        p = _cos_profile(g, s)
        # |∫ p_lin − ∫ cos^s| ≤ max|p_lin − cos^s| · 4π  (the integrand error is bounded pointwise)
        tol = _interp_error(g, s) * 4 * np.pi + 1e-14
        assert abs(pconv.profile_integral(g, p) - 2 * np.pi / (s + 1)) <= tol


def test_constant_env_gives_profile_integral_and_converges():
    g = km.gamma_nodes(512)
    p = _cos_profile(g, 6.0)
    I = pconv.profile_integral(g, p)
    errs = []
    for n in (8, 16):
        E = pconv.convolve_profiles(np.full((6, n, n, 2), 3.0), g, p)
        assert E.shape == (6, n, n, 2)
        errs.append(np.abs(E / (3.0 * I) - 1).max())
    # texel-centre quadrature of a smooth lobe: O(h²) → halving h must shrink the error ≥ 3× (4× asymptotically),
    # and at n = 16 (texel ≈ 7°, lobe HWHM ≈ 27°) it is below 1 %
    assert errs[1] < 0.01
    assert errs[0] / errs[1] > 3.0


def test_cos_profile_equals_unnormalised_phong_convolution():
    env = se.make_env("sky_sun", n=8)
    g = km.gamma_nodes(1024)
    for s in (3.0, 20.0):
        E = pconv.convolve_profiles(env, g, _cos_profile(g, s))
        ref = pc.convolve_exact(env, s, normalized=False)
        # same source texels and solid angles; the only difference is the tabulated profile:
        # |ΔE| ≤ max|p_lin − cos^s| · Σ_j L_j Ω_j
        tol = _interp_error(g, s) * float((env * envmap.cube_solid_angles(8)[..., None]).sum(axis=(0, 1, 2)).max())
        assert np.abs(E - ref).max() <= tol * 1.000001 + 1e-12


def test_single_texel_source_gives_the_profile_shape():
    n = 8
    env = np.zeros((6, n, n, 1))
    env[4, 3, 5, 0] = 2.0
    g = km.gamma_nodes(256)
    p = np.maximum(0.0, 1.0 - g / 0.6)  # compact support (γ < 0.6 rad): exercises the exact truncation
    E = pconv.convolve_profiles(env, g, p)[..., 0]
    d = envmap.texel_directions(n)
    w = d[4, 3, 5]
    gam = np.arccos(np.clip(d @ w, -1, 1))
    expected = 2.0 * envmap.texel_solid_angles(n)[3, 5] * np.interp(gam, g, p, right=0.0)
    np.testing.assert_allclose(E, expected, rtol=1e-12, atol=1e-15)
    assert np.count_nonzero(E) == np.count_nonzero(expected) > 1


def test_tail_truncation_is_within_stated_fraction():
    env = se.make_env("sky_sun", n=8, sun_radiance=10.0)
    g = km.gamma_nodes(512)
    p = _cos_profile(g, 40.0)
    full = pconv.convolve_profiles(env, g, p)
    cut, info = pconv.convolve_profiles(env, g, p, tail_rtol=1e-3, return_info=True)
    assert info["cut_angle"][0] < np.pi / 2 and 0 < info["tail_fraction"][0] <= 1e-3
    # neglected ≤ L_max · (discrete tail weight); the continuous tail ≤ 1e-3 ∫p, the discrete one on 8² texels
    # may exceed it by the quadrature error of the tail (allow 3×)
    bound = env.max() * 3e-3 * pconv.profile_integral(g, p)
    assert np.all(full - cut >= -1e-12) and (full - cut).max() <= bound


def test_auto_supersample_fixes_narrow_lobes():
    # a lobe much narrower than a texel, output grid = source grid: the midpoint rule hits the peak every time
    g = km.gamma_nodes(512)
    s = 3000.0
    p = _cos_profile(g, s)
    n = 8
    env = np.ones((6, n, n, 1))
    plain = pconv.convolve_profiles(env, g, p)
    auto = pconv.convolve_profiles(env, g, p, supersample="auto", max_supersample=64)
    exact = 2 * np.pi / (s + 1)
    assert np.abs(plain / exact - 1).max() > 1.0  # grossly wrong without supersampling
    # HWHM-based k puts ≥ 1.5 sub-texels per half width: Gaussian-like lobe, midpoint error ≪ 1 % (measured
    # analytically for a uniform grid: exp(−2π²σ²/h²)); cube-grid non-uniformity and the profile table → 2 %
    assert np.abs(auto / exact - 1).max() < 0.02


# ----------------------------------------------------------------------------------------------------------------
# (c) frames and peak directions
# ----------------------------------------------------------------------------------------------------------------
def test_peak_direction_matches_fit_convention_under_rotation():
    rng = np.random.default_rng(3)
    f = B.get_brdf("ward", kd=0.0, ks=0.8, alpha=0.04)
    for t in np.radians([15.0, 55.0, 75.0]):
        sl = km.fit_multi_lobe(f, t, 3, n_gamma=96, n_phi=16)
        R = _random_rotation(rng)
        n_w = R @ np.array([0.0, 0.0, 1.0])
        wo_w = R @ B.view_direction(t)
        x, y, z, th = pl.local_frame(n_w, wo_w)
        assert abs(th - t) < 1e-12
        # r = sin θo x + cos θo z is the mirror direction 2(n·wo)n − wo
        np.testing.assert_allclose(np.sin(t) * x + np.cos(t) * z, 2 * np.dot(n_w, wo_w) * n_w - wo_w, atol=1e-12)
        for lb in sl.lobes:
            d = pl.peak_direction(n_w, wo_w, lb.theta_off, lb.phi_off)
            np.testing.assert_allclose(d, R @ lb.peak, atol=1e-12)
            # the BRDF (isotropic) has the same value at the rotated peak
            assert abs(f(d, wo_w, n_w) - f(lb.peak, B.view_direction(t))) <= 1e-9 * abs(f(lb.peak, B.view_direction(t)))


def test_ward_half_vector_bound():
    # θh ≥ angle(ω, r)/2 (module docstring), brute force on random pairs
    rng = np.random.default_rng(0)
    wo = rng.normal(size=(20000, 3))
    wi = rng.normal(size=(20000, 3))
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo[:, 2] = np.abs(wo[:, 2])
    wi[:, 2] = np.abs(wi[:, 2])
    h = wi + wo
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    r = 2 * wo[:, 2:3] * np.array([0, 0, 1.0]) - wo
    th_h = np.arccos(np.clip(h[:, 2], -1, 1))
    gam = np.arccos(np.clip(np.sum(wi * r, 1), -1, 1))
    assert np.all(th_h >= gam / 2 - 1e-9)


# ----------------------------------------------------------------------------------------------------------------
# (b) 3D maps
# ----------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ward_lobes():
    f = B.get_brdf("ward", kd=0.0, ks=0.8, alpha=0.04)
    th = np.radians([0.0, 30.0, 60.0])
    multi = [km.fit_multi_lobe(f, t, 3, n_gamma=96, n_phi=16) for t in th]
    env = se.make_env("gradient", n=8)
    return pl.build_lobe_set(multi, km.track_lobes(multi), cube=env, tail_rtol=1e-6), env


def test_3d_lookup_at_sampled_theta_equals_map(ward_lobes):
    ls, _ = ward_lobes
    d = envmap.texel_directions(8).reshape(-1, 3)
    for k in range(ls.theta_o.size):
        for j in range(ls.n_tracks):
            v = ls.lookup(j, d, np.full(d.shape[0], ls.theta_o[k]))
            # bilinear weights at a texel centre are (1, 0, 0, 0): the stored texel exactly
            np.testing.assert_allclose(v, ls.maps[k, j].reshape(-1, ls.maps.shape[-1]), rtol=1e-12, atol=1e-14)
    # between samples: the linear blend of the two slices
    mid = 0.5 * (ls.theta_o[0] + ls.theta_o[1])
    v = ls.lookup(0, d, mid)
    np.testing.assert_allclose(v, 0.5 * (ls.maps[0, 0] + ls.maps[1, 0]).reshape(v.shape), rtol=1e-12)


def test_scaled_lobe_set_equals_reconvolution(ward_lobes):
    # independent route: convolve the environment again with the scaled profiles
    ls, env = ward_lobes
    f = np.array([1.3, 0.0, 2.5])
    sc = ls.scaled(f)
    K, J, G = ls.profiles.shape
    again = pconv.convolve_profiles(env, ls.gamma, (ls.profiles * f[:, None, None]).reshape(K * J, G), tail_rtol=1e-6)
    np.testing.assert_allclose(sc.maps, np.asarray(again).reshape(sc.maps.shape), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(sc.integral, pconv.profile_integral(ls.gamma, sc.profiles), rtol=1e-12, atol=1e-300)
    np.testing.assert_array_equal(sc.phong_s, ls.phong_s)
    d = envmap.texel_directions(8).reshape(-1, 3)
    np.testing.assert_allclose(sc.lookup(0, d, ls.theta_o[2]), 2.5 * ls.lookup(0, d, ls.theta_o[2]), rtol=1e-12)
    with pytest.raises(IBLError, match=r"factors must be 3 finite non\-negative"):
        ls.scaled([1.0, np.nan, 1.0])
    with pytest.raises(IBLError, match=r"factors must be 3 finite non\-negative"):
        ls.scaled([1.0, 1.0])


def test_peak_on_the_normal_takes_the_neighbouring_azimuth(ward_lobes):
    # at θo = 0 the peak search stops ≈ 1e-8 rad from the normal, where its azimuth is noise (−179° was seen);
    # isotropic Ward is symmetric about the incidence plane, so every interpolated peak must lie in it (y = 0)
    ls, _ = ward_lobes
    assert ls.phi_off[0, 0] == ls.phi_off[1, 0]
    n = np.array([0.0, 0.0, 1.0])
    for t in np.radians([1.0, 2.67, 4.0, 15.0]):
        wo = B.view_direction(t)
        th, ph = ls.offsets(0, t)
        d = pl.peak_direction(n, wo, th, ph)
        assert abs(d[..., 1]) < 1e-6, t  # peak search tolerance (xatol 1e-7 rad); the noise azimuth gave ≈ 0.05


def test_whole_sphere_profile_keeps_the_antipodal_texel():
    # p ≡ 1 over γ ∈ [0, π]: E(d) = Σ L_j Ω_j at every d (closed form); the texel opposite a tile centre has a
    # dot product that rounds below −1 and must still be gathered
    g = km.gamma_nodes(64)
    for n, tile in ((2, 1), (3, 4)):
        cube = np.ones((6, n, n))
        cube[1, n // 2, n // 2] = 1e6
        E = pconv.convolve_profiles(cube, g, np.ones_like(g), tile=tile)
        np.testing.assert_allclose(E, np.sum(cube * envmap.cube_solid_angles(n)), rtol=1e-13)


def test_missing_track_has_zero_profile(ward_lobes):
    ls, _ = ward_lobes
    # at θo = 0 the Ward slice is fitted by one lobe (the greedy fit stops), so tracks ≥ 1 are absent there
    assert ls.n_tracks >= 2
    assert np.all(ls.profiles[0, 1:] == 0) and np.all(ls.maps[0, 1:] == 0)
    assert np.all(np.isfinite(ls.theta_off)) and np.all(np.isfinite(ls.phi_off))


# ----------------------------------------------------------------------------------------------------------------
# (c)(d)(e) the whole chain on a Phong BRDF (fitted exactly by one lobe)
# ----------------------------------------------------------------------------------------------------------------
def test_phong_brdf_chain_agrees():
    s = 200.0
    f = B.get_brdf("phong", ks=1.0, s=s, kd=0.0)
    th = np.radians(np.linspace(0, 75, 6))
    fits = [km.fit_single_lobe(f, t, n_gamma=128, n_phi=8) for t in th]
    env = se.make_env("gradient", n=32)
    ls = pl.build_lobe_set(fits, cube=env, tail_rtol=1e-8, supersample="auto")
    rng = np.random.default_rng(1)
    P = 120
    n = rng.normal(size=(P, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    tho = np.radians(rng.uniform(0, 60, P))
    tmp = rng.normal(size=(P, 3))
    tmp -= np.sum(tmp * n, 1, keepdims=True) * n
    tmp /= np.linalg.norm(tmp, axis=1, keepdims=True)
    wo = np.cos(tho)[:, None] * n + np.sin(tho)[:, None] * tmp
    ref = kref.render_reference(env, n, wo, f, supersample=2, cut_angle=np.arccos(1e-12 ** (1 / s)))
    lobes = pl.shade_lobes(ls, n, wo)
    pyr = pl.shade_pyramid(ls, build_prefilter(env, "pyramid"), n, wo)
    # Phong: the fitted lobe is the BRDF; what remains is the KM2000 cosine approximation n·l ≈ n·r, whose
    # relative effect on ∫cos^s(γ)(n·l) is (s+2)/(s+1) − 1 = 0.5 % (Meunier closed forms 2π/(s+1), 2π/(s+2)),
    # the energy rescale/Phong fit on 128 γ nodes (≤ 0.3 %), horizon clipping (θo ≤ 60°, lobe ≈ 4°: none) and
    # the 32² quadrature of a smooth environment (< 0.5 %) → 1.5 %
    assert np.abs(lobes / ref - 1).max() < 0.015
    # pyramid: additionally the sqrt-cos pyramid's lobe shape at level ≈ 3 (volume-matched, not shape-matched);
    # on a linear environment a symmetric unit-weight lobe changes only the (b·r)·E[cos γ] term → 3 %
    assert np.abs(pyr / ref - 1).max() < 0.03
    # both energy conventions agree for an exact Phong lobe: P·2π/(s+1) vs ∫p dω (profile table, ≤ 0.5 %)
    W_phong = ls.phong_P * 2 * np.pi / (ls.phong_s + 1)
    np.testing.assert_allclose(W_phong, ls.integral, rtol=5e-3)


def test_reference_constant_env_is_albedo():
    # L ≡ 1: Lo = ∫ f cos θi dωi = directional albedo (brdfs.albedo, Gauss–Legendre, an independent quadrature)
    f = B.get_brdf("phong", ks=0.7, s=10.0, kd=0.2)
    t = np.radians([0.0, 35.0, 70.0])
    n = np.tile([0.0, 0.0, 1.0], (3, 1))
    wo = np.stack([B.view_direction(x) for x in t])
    ref = kref.render_reference(np.ones((6, 16, 16, 1)), n, wo, f, supersample=4)[:, 0]
    # texel quadrature at 64² sub-texels of a lobe of HWHM ≈ 21° plus the horizon discontinuity: < 0.5 %
    np.testing.assert_allclose(ref, B.albedo(f, t), rtol=5e-3)


def test_ward_cut_bound_holds():
    env = se.make_env("sky_sun", n=8, sun_radiance=50.0)
    f = B.get_brdf("ward", kd=0.0, ks=0.8, alpha=0.3)  # wide lobe: the cut matters
    rng = np.random.default_rng(5)
    n = np.tile([0.0, 0.0, 1.0], (40, 1))
    t = rng.uniform(0, 1.3, 40)
    ph = rng.uniform(0, 2 * np.pi, 40)
    wo = np.stack([np.sin(t) * np.cos(ph), np.sin(t) * np.sin(ph), np.cos(t)], 1)
    full = kref.render_reference(env, n, wo, f)
    gc = kref.ward_cut_angle(0.3, 1e-3)
    cut = kref.render_reference(env, n, wo, f, cut_angle=gc)
    bound = kref.ward_neglected_bound(0.3, 0.8, gc, np.cos(t), float(env.max()))
    assert np.all(np.abs(full - cut).max(axis=1) <= bound)
    assert np.abs(full - cut).max() > 0  # the cut did neglect something


# ----------------------------------------------------------------------------------------------------------------
# bad input
# ----------------------------------------------------------------------------------------------------------------
def test_bad_input_raises_clear_errors(ward_lobes):
    ls, env = ward_lobes
    g = km.gamma_nodes(64)
    p = _cos_profile(g, 5.0)
    with pytest.raises(pconv.ProfileError, match="NaN"):
        pconv.convolve_profiles(env, g, np.where(g > 1, np.nan, p))
    with pytest.raises(pconv.ProfileError, match="negative"):
        pconv.convolve_profiles(env, g, p - 0.5)
    with pytest.raises(pconv.ProfileError, match=r"gamma must be finite, strictly increasing"):
        pconv.convolve_profiles(env, g[::-1], p)
    with pytest.raises(LayoutError, match=r"environment cube map: expected an array"):
        pconv.convolve_profiles(np.ones((6, 8, 9, 3)), g, p)
    with pytest.raises(IBLError, match=r"supersample must be a positive integer"):
        pconv.convolve_profiles(env, g, p, supersample="fast")
    d = np.array([[0.0, 0.0, 1.0]])
    with pytest.raises(pl.ElevationRangeError, match=r"theta_o outside the sampled elevations \[0\.000°"):
        ls.lookup(0, d, np.radians(70.0))  # sampled range is [0°, 60°]
    with pytest.raises(pl.ElevationRangeError, match=r"theta_o contains NaN"):
        ls.lookup(0, d, np.nan)
    wo = np.array([[np.sin(1.3), 0.0, np.cos(1.3)]])  # θo ≈ 74.5° > 60°
    with pytest.raises(pl.ElevationRangeError, match=r"theta_o outside the sampled elevations \[0\.000°"):
        pl.shade_lobes(ls, d, wo, clamp_theta=False)
    assert np.all(np.isfinite(pl.shade_lobes(ls, d, wo, clamp_theta=True)))
    with pytest.raises(IBLError, match=r"cos_mode must be one of \('mirror'"):
        pl.shade_lobes(ls, d, wo, cos_mode="normal")
    with pytest.raises(IBLError, match=r"energy must be one of \('phong'"):
        pl.shade_pyramid(ls, build_prefilter(env, "pyramid"), d, wo, energy="volume")
    with pytest.raises(IBLError, match="Phong prefilter"):  # a bare pyramid has no look-up of its own
        pl.shade_pyramid(ls, build_pyramid(env), d, wo)
    assert issubclass(pconv.ProfileError, IBLError) and issubclass(pl.ElevationRangeError, IBLError)


def test_hwhm_helpers_match_closed_forms():
    # cos^s γ = ½ at γ = acos(2^(−1/s)) (closed form); the profile table is linear between nodes (γ spacing at
    # 30° on 2048 quadratic nodes ≈ 0.07° → tolerance 0.1°), brdf_min_hwhm's grid (400 quadratic nodes to 90°)
    # returns the first node below half: between the crossing and one node beyond it (≤ 0.5° there)
    s = 60.0
    exact = np.arccos(2 ** (-1 / s))
    g = km.gamma_nodes(2048)
    assert abs(pconv.profile_hwhm(g, _cos_profile(g, s)) - exact) < np.radians(0.1)
    f = B.get_brdf("phong", ks=1.0, s=s)
    h = kref.brdf_min_hwhm(f, 0.3)  # θo = 0.3 rad: the lobe (≈ 9° HWHM) is clear of the horizon
    assert exact - 1e-12 <= h <= exact + np.radians(0.5)
    # auto_supersample: the face-centre sub-texel 2/(n k) must not exceed hwhm / samples_per_hwhm
    for n_, hw, q in ((8, 0.01, 1.5), (64, 0.02, 3.0), (16, 1.0, 1.5)):
        k = pconv.auto_supersample(n_, hw, q, 1000)
        assert 2 / (n_ * k) <= hw / q + 1e-15 and (k == 1 or 2 / (n_ * (k - 1)) > hw / q)


def test_reference_per_sample_supersample_equals_separate_calls():
    env = se.make_env("sky_sun", n=4, sun_radiance=20.0)
    f = B.get_brdf("ward", kd=0.1, ks=0.8, alpha=0.2)
    n = np.tile([0.0, 0.0, 1.0], (4, 1))
    wo = np.stack([B.view_direction(t) for t in (0.1, 0.5, 0.9, 1.2)])
    ks = np.array([1, 3, 1, 2])
    mixed = kref.render_reference(env, n, wo, f, supersample=ks, cut_angle=1.5)
    for i, k in enumerate(ks):
        one = kref.render_reference(env, n[i:i + 1], wo[i:i + 1], f, supersample=int(k), cut_angle=1.5)
        np.testing.assert_allclose(mixed[i], one[0], rtol=1e-12)
    with pytest.raises(IBLError, match=r"supersample must be a positive integer"):
        kref.render_reference(env, n, wo, f, supersample=np.array([1, 0, 1, 1]))
