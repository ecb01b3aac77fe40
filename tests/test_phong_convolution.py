"""Tests of ibl_ref.groundtruth.phong_convolution (exact Phong-lobe convolution, Knuth et al. 2014 Eq. 4).

Reference values come from independent routes: closed forms (constant, linear-gradient environments,
2π/(s+1)), brute-force sums written in the test with np.power, and symmetry/identity arguments.
"""

import numpy as np
import pytest

from ibl_ref.environment import envmap
from ibl_ref.errors import IBLError, LayoutError, RadianceError
from ibl_ref.groundtruth.phong_convolution import convolve_exact, convolve_exact_many, phong_lobe_integral

RNG_SEED = 1234


def _gradient_cube(n, a=1.0, b=(0.3, -0.2, 0.4)):
    """L(ω) = a + b·ω at texel centres (evaluated here, independent of synthetic_envs)."""
    d = envmap.texel_directions(n)
    return (a + d @ np.asarray(b))[..., None], d


def test_lobe_integral_closed_form():
    # ∫ max(cosθ,0)^s dω = 2π ∫_0^1 μ^s dμ = 2π/(s+1); check against a 1-D numerical quadrature
    from scipy.integrate import quad

    for s in (1.0, 3.5, 40.0):
        num = 2 * np.pi * quad(lambda mu: mu**s, 0, 1)[0]
        assert phong_lobe_integral(s) == pytest.approx(num, rel=1e-8)  # quad's default epsrel 1.5e-8


@pytest.mark.parametrize("s", [1.0, 10.0, 1e3, 1e6])
def test_constant_env_exactly_constant(s):
    # the same weights appear in numerator and denominator: only rounding remains (≤ ~M·eps·0.01)
    cube = np.full((6, 8, 8, 3), 2.75)
    out = convolve_exact(cube, s)
    assert out.shape == cube.shape and out.dtype == np.float64
    np.testing.assert_allclose(out, 2.75, rtol=1e-14, atol=0)


def test_gradient_env_matches_closed_form_and_converges():
    # lobe average of a + b·ω is a + b·r (s+1)/(s+2) (∫ω cos^s / ∫cos^s = r ∫cos^{s+1}/∫cos^s).
    # Observed discretisation order (module docstring / report): ~N^-2 for s ≥ 16 once the lobe is
    # resolved, ~N^-1.5 for s = 1 (the kink of max(cos,0) at the horizon).  We assert the error drops
    # by at least 2.5x per doubling (order > 1.3) and is below a bound fitted with 3x margin.
    cases = ((1.0, 1.5e-4), (16.0, 9e-4), (64.0, 3e-3))
    errs = {s: [] for s, _ in cases}
    for n in (8, 16, 32):
        cube, d = _gradient_cube(n)
        outs = convolve_exact_many(cube, [s for s, _ in cases])[..., 0]
        for (s, _), out in zip(cases, outs):
            ref = 1.0 + (d @ np.array([0.3, -0.2, 0.4])) * (s + 1) / (s + 2)
            errs[s].append(np.abs(out - ref).max())
    for s, tol16 in cases:
        errs_s = errs[s]
        assert errs_s[1] < tol16, (s, errs_s)
        assert errs_s[0] / errs_s[1] > 2.5 and errs_s[1] / errs_s[2] > 2.5, (s, errs_s)


@pytest.mark.parametrize("s", [1.0, 8.0, 50.0])
def test_single_lit_texel_gives_normalised_lobe_shape(s):
    n = 6
    j = (2, 1, 4)  # +Y face
    cube = np.zeros((6, n, n, 1))
    cube[j] = 1.0
    out = convolve_exact(cube, s)[..., 0]
    d = envmap.texel_directions(n).reshape(-1, 3)
    om = envmap.cube_solid_angles(n).reshape(-1)
    wj = envmap.texel_directions(n)[j]
    cos = d @ d.T
    w = np.power(np.clip(cos, 0, None), s) * om[None, :]  # brute force with np.power
    ref = np.power(np.clip(d @ wj, 0, None), s) * envmap.texel_solid_angles(n)[1, 4] / w.sum(1)  # L_j Ω_j cos^s / Σ cos^s Ω
    np.testing.assert_allclose(out.reshape(-1), ref, rtol=1e-12, atol=1e-300)


def test_mirror_is_identity_and_nearest_lookup():
    rng = np.random.default_rng(RNG_SEED)
    cube = rng.random((6, 8, 8, 3))
    np.testing.assert_array_equal(convolve_exact(cube, np.inf), cube)
    # out_size = 4: each output texel centre falls into one 2x2 block of the 8² source; it is the
    # nearest texel of the source, i.e. one of the four texels of the block (row/col 2i..2i+1)
    out = convolve_exact(cube, np.inf, out_size=4)
    for f in range(6):
        for r in range(4):
            for c in range(4):
                block = cube[f, 2 * r : 2 * r + 2, 2 * c : 2 * c + 2].reshape(-1, 3)
                assert any(np.array_equal(out[f, r, c], b) for b in block)


def test_supersampling_converges_to_mirror_as_s_grows():
    # piecewise-constant radiance, sub-texels: as s → ∞ the lobe collapses onto the sub-texels nearest
    # to r, which belong to the source texel CONTAINING r → the mirror lookup.  Without sub-texels it
    # collapses onto the nearest texel *centre*, which is a different texel for some r when the output
    # grid (7²) does not align with the source grid (5²) (no r lies on a texel boundary for 5 vs 7).
    rng = np.random.default_rng(RNG_SEED)
    cube = rng.random((6, 5, 5, 1)) + 0.1
    mirror = convolve_exact(cube, np.inf, out_size=7)
    exps = [1e3, 1e5, 1e7]
    e1 = [np.abs(o - mirror).max() for o in convolve_exact_many(cube, exps, out_size=7)]
    assert e1[-1] > 0.1  # k = 1 does not reach the mirror lookup
    for k in (2, 4):
        errs = [np.abs(o - mirror).max() for o in convolve_exact_many(cube, exps, supersample=k, out_size=7)]
        assert errs[0] > errs[1] > errs[2] or errs[2] < 1e-12, errs
        assert errs[-1] < 1e-12, errs  # only the nearest sub-texels (all inside one texel) survive
    # supersampled total lobe weight → 2π/(s+1) better than without (quadrature refinement)
    one = np.ones((6, 4, 4, 1))
    e1 = np.abs(convolve_exact(one, 16.0, normalized=False) / phong_lobe_integral(16.0) - 1).max()
    e4 = np.abs(convolve_exact(one, 16.0, normalized=False, supersample=4) / phong_lobe_integral(16.0) - 1).max()
    assert e4 < e1 / 4


@pytest.mark.parametrize("s", [1.0, 4.0, 16.0])
def test_unnormalised_constant_is_lobe_integral(s):
    # Σ cos^s Ω → 2π/(s+1) with an O(N^-2) (s=1: ~N^-1.6) quadrature error; observed at N=16:
    # 1.6e-4 (s=1), 2.6e-3 (s=16); tolerance 5e-3 and refinement 8 → 16 must reduce the error 2.5x
    errs = []
    for n in (8, 16):
        out = convolve_exact(np.ones((6, n, n, 2)), s, normalized=False)
        errs.append(np.abs(out / (2 * np.pi / (s + 1)) - 1).max())
    assert errs[1] < 5e-3 and errs[0] / errs[1] > 2.5, errs
    # relation unnormalised = average × Σ cos^s Ω, for a non-constant environment
    cube, _ = _gradient_cube(8)
    w = convolve_exact(np.ones((6, 8, 8, 1)), s, normalized=False)
    np.testing.assert_allclose(convolve_exact(cube, s, normalized=False), convolve_exact(cube, s) * w, rtol=1e-12)
    avg, W = convolve_exact_many(cube, [s], return_weights=True)
    np.testing.assert_allclose(W[0], w[..., 0], rtol=1e-12)
    np.testing.assert_allclose(avg[0], convolve_exact(cube, s), rtol=1e-14)


def test_many_equals_single():
    rng = np.random.default_rng(RNG_SEED)
    cube = rng.random((6, 5, 5, 3))
    exps = [1.0, 2.5, 30.0, np.inf]
    many = convolve_exact_many(cube, exps, out_size=3)
    for k, s in enumerate(exps):
        np.testing.assert_allclose(many[k], convolve_exact(cube, s, out_size=3), rtol=1e-13, atol=0)


@pytest.mark.parametrize("n", [1, 2])
@pytest.mark.parametrize("scale", [1e-6, 1e6])
def test_extremes_tiny_faces_huge_exponent_and_radiance(n, scale):
    rng = np.random.default_rng(RNG_SEED)
    cube = scale * (rng.random((6, n, n, 3)) + 0.5)
    out = convolve_exact(cube, 1e6)
    assert np.all(np.isfinite(out))
    # at s = 1e6 every other texel centre is ≥ 35° away: cos^1e6 underflows → exactly the input
    np.testing.assert_allclose(out, cube, rtol=1e-15)
    out1 = convolve_exact(cube, 1.0)
    assert np.all(np.isfinite(out1))
    if n == 1:
        # face centres: the 4 side faces have cos = 0 and the opposite face cos = −1 → identity
        np.testing.assert_allclose(out1, cube, rtol=1e-15)
    # linearity in the radiance scale (no overflow/underflow in the weights)
    np.testing.assert_allclose(out1, scale * convolve_exact(cube / scale, 1.0), rtol=1e-13)
    # unnormalised at s = 1e6: Σ L cosˢ Ω keeps only the texel itself, L·Ω (exact solid angle); its own cos is
    # d·d = 1 − O(ε) in float64, and (1 − 2.2e-16)^1e6 = 1 − 2.2e-10, so rtol 1e-9
    un = convolve_exact(cube, 1e6, normalized=False)
    np.testing.assert_allclose(un, cube * envmap.cube_solid_angles(n)[..., None], rtol=1e-9, atol=0)


def test_single_channel_input_shape():
    cube = np.ones((6, 4, 4))
    assert convolve_exact(cube, 3.0).shape == (6, 4, 4)
    assert convolve_exact(cube, 3.0, out_size=2).shape == (6, 2, 2)


def test_bad_input_raises_clear_errors():
    good = np.ones((6, 4, 4, 3))
    with pytest.raises(IBLError, match="s must be >= 1"):
        convolve_exact(good, 0.5)
    with pytest.raises(IBLError, match=r"Phong exponent s must be >="):
        convolve_exact(good, float("nan"))
    with pytest.raises(IBLError, match=r"Phong exponent must be a number"):
        convolve_exact(good, "shiny")
    bad = good.copy()
    bad[1, 2, 3, 0] = np.nan
    with pytest.raises(RadianceError, match="NaN"):
        convolve_exact(bad, 4.0)
    with pytest.raises(RadianceError, match=r"environment cube map: 288 negative radiance"):
        convolve_exact(-good, 4.0)
    with pytest.raises(LayoutError, match=r"environment cube map: expected an array"):
        convolve_exact(np.ones((5, 4, 4, 3)), 4.0)
    with pytest.raises(LayoutError, match=r"environment cube map: expected an array"):
        convolve_exact(np.ones((6, 4, 5, 3)), 4.0)
    with pytest.raises(IBLError, match=r"supersample must be a positive integer"):
        convolve_exact(good, 4.0, supersample=0)
    with pytest.raises(IBLError, match=r"out_size must be a positive integer"):
        convolve_exact(good, 4.0, out_size=0)
    with pytest.raises(IBLError, match="inf"):
        convolve_exact(good, np.inf, normalized=False)


def test_lobe_average_at_texel_centres_is_convolve_exact_and_regions_sum():
    # independent route: convolve_exact evaluates the weights as exp(s·(log c − max log c)) over the texels; at the
    # texel centres both are the same quadrature → rounding only (1e-12)
    from ibl_ref.environment.envmap import texel_directions
    from ibl_ref.groundtruth.phong_convolution import convolve_exact, lobe_average
    from ibl_ref.synthetic.synthetic_envs import make_env

    env = make_env("sky_sun", n=8)
    for s in (1.0, 7.5, 64.0):
        got = lobe_average(env, texel_directions(8), s)
        np.testing.assert_allclose(got, convolve_exact(env, s), rtol=1e-12, atol=0)
        lab = (np.arange(6 * 64).reshape(6, 8, 8) % 5)
        reg = lobe_average(env, texel_directions(8), s, labels=lab)
        assert reg.shape == (6, 8, 8, 5, 3)
        np.testing.assert_allclose(reg.sum(axis=-2), got, rtol=1e-12)
        # truncated gather: within its own bound δ·max L of the dense sum, and the bound is not vacuous
        tr, b = lobe_average(env, texel_directions(8), s, weight_eps=1e-6, return_bound=True)
        assert np.all(np.abs(tr - got) <= b[..., None] * env.max() * (1 + 1e-9) + 1e-12)
        assert b.max() < 1e-3


def test_lobe_average_closed_form_and_errors():
    # gradient map L = a + b·ω: Ē_1(d) = a + (b·d)(s+1)/(s+2) (synthetic_envs.gradient_lobe_average, a closed form);
    # the cube quadrature is second-order, 64² faces → 2e-3
    from ibl_ref.groundtruth.phong_convolution import lobe_average
    from ibl_ref.synthetic.synthetic_envs import gradient_lobe_average, make_env

    env = make_env("gradient", n=64)
    d = np.random.default_rng(0).normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(lobe_average(env, d, 1.0), gradient_lobe_average(d, 1.0), atol=2e-3)
    with pytest.raises(IBLError, match=r"Phong exponent must be finite and"):
        lobe_average(env, d, 0.5)
    with pytest.raises(IBLError, match=r"Phong exponent must be finite and"):
        lobe_average(env, d, np.inf)
    with pytest.raises(IBLError, match=r"dirs: zero\-length direction"):
        lobe_average(env, np.zeros((2, 3)), 1.0)
