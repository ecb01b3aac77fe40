"""Tests of ibl_ref.synthetic.synthetic_envs against closed forms and independent quadratures."""

import numpy as np
import pytest

from ibl_ref.environment import envmap
from ibl_ref.synthetic import synthetic_envs as se
from ibl_ref.environment.radiance_policy import check_radiance
from ibl_ref.errors import IBLError


def integral(cube):
    """∫L dω per channel with the exact texel solid angles of envmap."""
    n = cube.shape[1]
    return np.einsum("fij,fijc->c", envmap.cube_solid_angles(n), cube)


def brute_texel_average(fun, n, k):
    """Texel averages of fun(dirs) by midpoint supersampling at resolution n·k (exact sub-texel weights)."""
    d = envmap.texel_directions(n * k)
    w = envmap.texel_solid_angles(n * k)[None, :, :, None]
    vals = fun(d) * w
    c = vals.shape[-1]
    return vals.reshape(6, n, k, n, k, c).sum(axis=(2, 4)) / envmap.texel_solid_angles(n)[None, :, :, None]


# ------------------------------------------------------------------------------ basics
@pytest.mark.parametrize("name", se.ENV_NAMES)
def test_every_generator_shape_finite_nonnegative_deterministic(name):
    a = se.make_env(name, 6)
    b = se.make_env(name, 6)
    assert a.shape == (6, 6, 6, 3) and a.dtype == np.float64
    check_radiance(a)  # raises on NaN/Inf/negative
    assert np.array_equal(a, b)  # no randomness anywhere


def test_constant_is_constant_and_integrates_to_4pi_value():
    c = se.make_env("constant", 8, value=(1.0, 2.0, 3.0))
    assert np.all(c == np.array([1.0, 2.0, 3.0]))
    # reference: closed form 4π·value; exact solid angles sum to 4π to rounding → 1e-12
    np.testing.assert_allclose(integral(c), 4 * np.pi * np.array([1.0, 2.0, 3.0]), rtol=1e-12)


def test_delta_single_texel_value_and_integral():
    n = 8
    c = se.make_env("delta", n, texel=(2, 3, 5), radiance=(1.0, 2.0, 3.0), normalize=True)
    lit = np.argwhere(np.any(c > 0, axis=-1))
    assert lit.tolist() == [[2, 3, 5]]
    # normalised: ∫L dω equals the requested radiance exactly (value = radiance / Ω_texel)
    np.testing.assert_allclose(integral(c), [1.0, 2.0, 3.0], rtol=1e-12)
    raw = se.make_env("delta", n, texel=(2, 3, 5), radiance=4.0)
    assert raw[2, 3, 5, 0] == 4.0 and np.count_nonzero(raw) == 3


def test_delta_by_direction_lights_the_containing_texel():
    d = np.array([0.3, -0.2, -0.9])
    c = se.make_env("delta", 16, direction=d)
    f, r, col = envmap.direction_to_texel(d, 16)
    assert c[f, r, col, 0] == 1.0 and np.count_nonzero(c[..., 0]) == 1


# ------------------------------------------------------------------------------ gradient
def test_subcell_solid_angles_match_envmap_solid_angles():
    # sub-cells of every texel of a 4-face at k=3 must sum to envmap's exact texel solid angle
    n, k = 4, 3
    r, c = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    u0, v0 = -1 + 2.0 * c.ravel() / n, -1 + 2.0 * r.ravel() / n
    om, _, _ = se._subcell_solid_angles(u0, v0, u0 + 2.0 / n, v0 + 2.0 / n, k)
    np.testing.assert_allclose(om.sum(axis=(1, 2)).reshape(n, n), envmap.texel_solid_angles(n), rtol=1e-12)
    # and equal the envmap texels of the n·k face
    np.testing.assert_allclose(om[0], envmap.texel_solid_angles(n * k)[:k, :k], rtol=1e-12)


def test_texel_mean_directions_closed_form_vs_supersampling():
    # midpoint supersampling converges as O(h²): errors at k=16 and k=32 shrink ≈ 4×, and the closed
    # form lies within the k=32 error (≈ 1e-5 at n=4)
    n = 4
    m = se.texel_mean_directions(n)
    e16 = np.abs(brute_texel_average(lambda d: d, n, 16) - m).max()
    e32 = np.abs(brute_texel_average(lambda d: d, n, 32) - m).max()
    assert e32 < 3e-5
    assert 3.0 < e16 / e32 < 5.0  # second-order convergence towards the closed form
    # ∫ω dω over the whole sphere is 0 by symmetry
    tot = np.einsum("fij,fijk->k", envmap.cube_solid_angles(n), m)
    np.testing.assert_allclose(tot, 0.0, atol=1e-13)


def test_gradient_center_and_average_sampling():
    n = 8
    a, b = (1.0, 2.0, 0.5), np.array([[0.3, -0.4, 0.5], [1.0, 0.5, -1.0], [0.0, 0.0, 0.5]])
    cen = se.make_env("gradient", n, a=a, b=b, sample="center")
    d = envmap.texel_directions(n)
    np.testing.assert_allclose(cen, np.array(a) + np.einsum("fijk,ck->fijc", d, b), rtol=0, atol=1e-14)
    avg = se.make_env("gradient", n, a=a, b=b)
    ref = brute_texel_average(lambda dd: np.array(a) + dd @ b.T, n, 32)
    # tolerance: midpoint error of the k=32 reference, |b| ≤ 1.5 × 3e-5 (see previous test)
    np.testing.assert_allclose(avg, ref, atol=5e-5)
    # the linear part integrates to zero exactly: ∫L dω = 4π a
    np.testing.assert_allclose(integral(avg), 4 * np.pi * np.array(a), rtol=1e-12)


def _lobe_average_quadrature(r, s, a, b, n_mu=400, n_phi=64):
    """∫L cosˢ / ∫cosˢ on the hemisphere around r by Gauss–Legendre in μ=cosθ × trapezoid in φ."""
    r = r / np.linalg.norm(r)
    e1 = np.cross(r, [1.0, 0.0, 0.0] if abs(r[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(r, e1)
    x, w = np.polynomial.legendre.leggauss(n_mu)
    mu, wmu = 0.5 * (x + 1), 0.5 * w
    phi = 2 * np.pi * np.arange(n_phi) / n_phi
    st = np.sqrt(1 - mu**2)
    om = mu[:, None, None] * r + st[:, None, None] * (np.cos(phi)[None, :, None] * e1 + np.sin(phi)[None, :, None] * e2)
    L = np.asarray(a) + om @ np.asarray(b).T  # (n_mu, n_phi, C)
    wt = (wmu * mu**s)[:, None, None]
    return (L * wt).sum(axis=(0, 1)) / (wt.sum() * n_phi)


@pytest.mark.parametrize("s", [0.0, 1.0, 3.5, 16.0, 100.0])
def test_gradient_lobe_average_vs_spherical_quadrature(s):
    rng = np.random.default_rng(7)
    r = rng.normal(size=3)
    a = np.array([1.0, 2.0, 3.0])
    b = rng.uniform(-0.5, 0.5, size=(3, 3))
    ref = _lobe_average_quadrature(r, s, a, b)
    # tolerance: 400-node Gauss–Legendre is exact to rounding for μ^s·μ with s ≤ 100
    np.testing.assert_allclose(se.gradient_lobe_average(r, s, a, b), ref, rtol=1e-10)


def test_gradient_lobe_average_limits_and_broadcast():
    r = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    out = se.gradient_lobe_average(r, np.array([np.inf, 0.0]), a=1.0, b=(0.0, 0.0, 0.6))
    np.testing.assert_allclose(out[0], 1.6)  # mirror: a + b·r
    np.testing.assert_allclose(out[1], 1.0)  # b ⊥ r
    with pytest.raises(IBLError, match=r"gradient_lobe_average: exponent s must be ≥"):
        se.gradient_lobe_average(r, -1.0)


@pytest.mark.parametrize("s", [1.0, 10.0])
def test_gradient_cube_convolution_matches_closed_form(s):
    # the cube map and the formula together: Σ Ω L cosˢ / Σ Ω cosˢ over the n=64 cube
    n = 64
    a, b = 1.0, (0.2, 0.5, -0.3)
    cube = se.make_env("gradient", n, a=a, b=b)
    d = envmap.texel_directions(n)
    w = envmap.cube_solid_angles(n)
    r = np.array([0.4, 0.8, -0.2]) / np.linalg.norm([0.4, 0.8, -0.2])
    lobe = np.maximum(d @ r, 0.0) ** s * w
    got = np.einsum("fij,fijc->c", lobe, cube) / lobe.sum()
    # tolerance: texel-resolution quadrature of the lobe at n=64 (lobe width ≫ texel) → 1e-3
    np.testing.assert_allclose(got, se.gradient_lobe_average(r, s, a, b), rtol=1e-3)


def test_gradient_rejects_negative_radiance_and_bad_input():
    with pytest.raises(IBLError, match="a \\+ b"):
        se.make_env("gradient", 4, a=0.5, b=(0.0, 0.6, 0.0))
    with pytest.raises(IBLError, match=r"gradient: sample must be 'average' or"):
        se.make_env("gradient", 4, sample="corner")
    with pytest.raises(IBLError, match="unknown parameter"):
        se.make_env("constant", 4, valu=1.0)
    with pytest.raises(IBLError, match="unknown synthetic environment"):
        se.make_env("sunset", 4)
    with pytest.raises(IBLError, match=r"n \(face size\): must be in"):
        se.make_env("constant", 0)
    with pytest.raises(IBLError, match=r"value: radiance must be non\-negative, got"):
        se.make_env("constant", 4, value=-1.0)
    with pytest.raises(IBLError, match=r"value: values must be finite, got"):
        se.make_env("constant", 4, value=float("nan"))
    with pytest.raises(IBLError, match=r"delta: texel \(6, 0, 0\) outside"):
        se.make_env("delta", 4, texel=(6, 0, 0))


# ------------------------------------------------------------------------------ sky and sun
@pytest.mark.parametrize("n", [16, 32, 64])
@pytest.mark.parametrize("sun_dir", [se.DEFAULT_SUN_DIRECTION, se.SUN_NEAR_CORNER])
def test_sun_integral_and_position(n, sun_dir):
    omega_s, L_s = se.SUN_SOLID_ANGLE, 1.0e5
    cube = se.make_env("sky_sun", n, sun_direction=sun_dir, sun_radiance=L_s, sun_solid_angle=omega_s,
                       sky_zenith=0.0, sky_horizon=0.0, ground=0.0)
    check_radiance(cube)
    # tolerance: ~32 sub-cells across the disc; boundary-cell statistics √(N_boundary)/N_disc ≈ 1e-2
    np.testing.assert_allclose(integral(cube), L_s * omega_s, rtol=1e-2)
    lum = cube[..., 0]
    f, r, c = np.unravel_index(np.argmax(lum), lum.shape)
    ang = np.arccos(np.clip(envmap.texel_directions(n)[f, r, c] @ sun_dir, -1, 1))
    theta_s = np.arccos(1 - omega_s / (2 * np.pi))
    assert ang <= theta_s + np.sqrt(2) / n  # brightest texel within one texel of the sun
    ft, rt, ct = envmap.direction_to_texel(sun_dir, n)
    assert lum[ft, rt, ct] > 0  # the texel containing the sun's centre is lit
    assert lum.max() <= L_s


def test_sun_near_corner_straddles_three_faces():
    cov = se.sun_disc_coverage(64, se.SUN_NEAR_CORNER)
    lit_faces = sorted(set(np.nonzero(cov)[0].tolist()))
    assert lit_faces == [0, 2, 4]  # +X, +Y, +Z


@pytest.mark.parametrize("n", [32, 64, 128])
def test_sun_coverage_error_reported_is_small(n):
    # independent check of the reported number: ∫ coverage dω with envmap solid angles
    err = se.sun_coverage_relative_error(n, se.SUN_NEAR_CORNER)
    cov = se.sun_disc_coverage(n, se.SUN_NEAR_CORNER)
    direct = (np.sum(cov * envmap.cube_solid_angles(n)) - se.SUN_SOLID_ANGLE) / se.SUN_SOLID_ANGLE
    assert err == pytest.approx(direct, abs=1e-15)
    assert abs(err) < 5e-3  # same tolerance origin as test_sun_integral_and_position, measured ≤ 1.4e-3


def test_large_sun_cap_area():
    # a big cap (0.3 sr) exercises many texels per face: compare with Ω exactly
    # tolerance: ~32 sub-cells across the disc as in test_sun_integral_and_position (measured 3e-3)
    cov = se.sun_disc_coverage(32, [0.2, 0.9, 0.1], 0.3)
    np.testing.assert_allclose(np.sum(cov * envmap.cube_solid_angles(32)), 0.3, rtol=1e-2)
    # more sub-cells across the disc → smaller error (measured 3e-3 → < 1e-3)
    cov = se.sun_disc_coverage(32, [0.2, 0.9, 0.1], 0.3, samples_across=128)
    np.testing.assert_allclose(np.sum(cov * envmap.cube_solid_angles(32)), 0.3, rtol=1e-3)


def test_sky_is_brighter_above_and_continuous_at_horizon():
    n = 256
    cube = se.make_env("sky_sun", n, sun_radiance=0.0)
    d = envmap.texel_directions(n)
    up, down = cube[d[..., 1] > 0.2], cube[d[..., 1] < -0.2]
    assert up[:, 2].mean() > 3 * down[:, 2].mean()
    near = np.abs(d[..., 1]) < 0.005
    # continuous: within ±0.005 of the horizon the ground ramp (slope 0.82/0.05 per unit ω_y) moves
    # by ≤ 0.082, far below the zenith-to-ground jump 0.82 a discontinuity would show
    assert np.ptp(cube[near][:, 2]) < 0.1


def test_sky_sun_validation():
    with pytest.raises(IBLError, match=r"sun_solid_angle: must be in \(0, 6\.283185307179586\]"):
        se.make_env("sky_sun", 8, sun_solid_angle=0.0)
    with pytest.raises(IBLError, match=r"sun_direction: zero\-length direction"):
        se.make_env("sky_sun", 8, sun_direction=(0, 0, 0))
    with pytest.raises(IBLError, match=r"sun_radiance: values must be finite, got"):
        se.make_env("sky_sun", 8, sun_radiance=float("inf"))


# ------------------------------------------------------------------------------ studio, checker
def test_rect_light_solid_angle_closed_form():
    # a 90°×90° gnomonic rectangle is exactly one cube face: 4π/6
    assert se.rect_light_solid_angle(90.0, 90.0) == pytest.approx(4 * np.pi / 6, rel=1e-14)
    # small rectangles: Ω → w·h (rad²)
    w, h = np.radians(0.2), np.radians(0.1)
    assert se.rect_light_solid_angle(0.2, 0.1) == pytest.approx(w * h, rel=1e-5)


def test_studio_light_that_is_a_cube_face():
    n = 8
    light = {"direction": (0, 0, 1), "width_deg": 90.0, "height_deg": 90.0, "radiance": 2.0}
    c = se.make_env("studio", n, lights=[light], background=0.0, floor=0.0)
    np.testing.assert_allclose(c[4], 2.0, rtol=1e-13)  # coverage 1 up to rounding of Σ Ω_sub / Ω
    assert np.all(c[[0, 1, 2, 3, 5]] == 0.0)


def test_studio_lights_integral():
    n = 32
    lights = [dict(ld, radiance=1.0) for ld in se.DEFAULT_STUDIO_LIGHTS]
    for ld in lights:
        c = se.make_env("studio", n, lights=[ld], background=0.0, floor=0.0)
        ref = se.rect_light_solid_angle(ld["width_deg"], ld["height_deg"])
        # tolerance: 8×8 supersampling of the edge texels, measured ≤ 2.2e-3 at n=16
        np.testing.assert_allclose(integral(c), ref, rtol=3e-3)
    with pytest.raises(IBLError, match=r"light width_deg: must be in \(0"):
        se.make_env("studio", 8, lights=[{"direction": (0, 0, 1), "width_deg": 200}])


def test_checker_levels_and_mean():
    c = se.make_env("checker", 16, cells=8, low=0.2, high=1.0)
    assert c.min() >= 0.2 - 1e-12 and c.max() <= 1.0 + 1e-12
    # by symmetry half of the sphere is high: mean = (low + high)/2; tolerance: 4×4 supersampling
    assert integral(c)[0] / (4 * np.pi) == pytest.approx(0.6, abs=2e-3)
    f = se.make_env("checker", 8, mode="face", cell_texels=2, low=0.0, high=1.0)
    assert set(np.unique(f).tolist()) == {0.0, 1.0}
    assert f[0, 0, 0, 0] != f[0, 0, 2, 0] and f[0, 0, 0, 0] == f[0, 1, 1, 0]
    assert f[..., 0].mean() == 0.5


# ------------------------------------------------------------------------------ cache
def test_cached_env_roundtrip(tmp_path, monkeypatch):
    monkeypatch.setenv("IBL_REF_CACHE", str(tmp_path / "cache"))
    a = se.cached_env("gradient", 4, b=(0.1, 0.2, 0.3))
    files = list((tmp_path / "cache").glob("gradient_n4_*.npy"))
    assert len(files) == 1
    np.testing.assert_array_equal(np.load(files[0]), a)
    b = se.cached_env("gradient", 4, b=(0.1, 0.2, 0.3))
    np.testing.assert_array_equal(a, b)
    se.cached_env("gradient", 4, b=(0.1, 0.2, 0.4))
    assert len(list((tmp_path / "cache").glob("gradient_n4_*.npy"))) == 2
    with pytest.raises(IBLError, match=r"unknown synthetic environment 'nope'; choose one"):
        se.cached_env("nope", 4)


def test_rect_light_corner_classification_equals_full_supersampling():
    # texels classified fully inside/outside from their corners must equal brute-force supersampling
    n, k = 12, 4
    ld = se.DEFAULT_STUDIO_LIGHTS[0]
    fast = se.rect_light_coverage(n, ld["direction"], ld["width_deg"], ld["height_deg"], supersample=k)
    (c, t, bt), w, h, _ = se._rect_light_params(ld)
    tw, th = np.tan(np.radians(w) / 2), np.tan(np.radians(h) / 2)

    def inside(d):
        dc = d @ c
        return (dc > 0) & (np.abs(d @ t) <= tw * dc) & (np.abs(d @ bt) <= th * dc)

    f, r, col = (a.ravel() for a in np.meshgrid(np.arange(6), np.arange(n), np.arange(n), indexing="ij"))
    brute = se._coverage(n, f, r, col, inside, k).reshape(6, n, n)
    np.testing.assert_allclose(fast, brute, atol=1e-13)
    assert 0 < np.count_nonzero((fast > 0) & (fast < 1)) < np.count_nonzero(fast)  # some edge texels
