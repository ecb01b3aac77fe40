"""The exact GGX prefilter by the block-Taylor tree (ibl_ref.groundtruth.ggx_convolution) against independent routes:
the dense texel sum (karis2013.prefilter_dense, itself checked against a per-texel brute force in test_karis2013),
closed forms for the kernel, its derivatives and its integral, and brute-force sums for the tree's moments."""

import math

import numpy as np
import pytest
from scipy import integrate

from ibl_ref.conventions import GGX_ROUGHNESS_MIN, ggx_alpha
from ibl_ref.environment import envmap
from ibl_ref.errors import IBLError
from ibl_ref.groundtruth import ggx_convolution as G
from ibl_ref.groundtruth.kernels import numba_available
from ibl_ref.prefilter import karis2013
from ibl_ref.synthetic import synthetic_envs as se

KERNELS = ["numpy"] + (["compiled"] if numba_available() else [])
needs_numba = pytest.mark.skipif(not numba_available(), reason="numba is not installed (the compiled kernels)")


# ---- the kernel ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("roughness", [GGX_ROUGHNESS_MIN, 0.134, 0.5, 1.0])
def test_the_kernel_is_the_split_sums_kernel_up_to_its_constant(roughness):
    alpha = float(ggx_alpha(roughness))
    x = np.linspace(-1.0, 1.0, 401)
    k = G.GGXLobeKernel(alpha).value(x)
    ref = karis2013.prefilter_kernel(x, roughness) * math.pi / alpha ** 2  # D carries α²/π
    np.testing.assert_allclose(k, ref, rtol=1e-12, atol=0.0)


@pytest.mark.parametrize("alpha", [0.018, 0.086, 0.25, 0.7])
def test_the_derivatives_against_central_differences_and_k3_increasing(alpha):
    kern = G.GGXLobeKernel(alpha)
    x = np.linspace(0.05, 0.95, 19)
    h = 1e-4 * (1.0 - x)  # K varies on the scale of 1 − x (its pole is at x = 1 + α²/b)
    K0, K1, K2 = kern.taylor(x)
    np.testing.assert_allclose(K0, kern.value(x), rtol=1e-15)
    # central differences of the closed form: truncation ≈ (h/(1 − x))² = 1e-8 relative, rounding ≈ u/1e-5
    np.testing.assert_allclose(K1, (kern.value(x + h) - kern.value(x - h)) / (2 * h), rtol=1e-5)
    np.testing.assert_allclose(K2, (kern.taylor(x + h)[1] - kern.taylor(x - h)[1]) / (2 * h), rtol=1e-5)
    np.testing.assert_allclose(kern.d3(x), (kern.taylor(x + h)[2] - kern.taylor(x - h)[2]) / (2 * h), rtol=1e-5)
    # the remainder bound takes K''' at the upper end of an interval: K''' must be positive and increasing on [0, 1]
    xs = np.linspace(0.0, 1.0, 2001)
    d3 = kern.d3(xs)
    assert np.all(d3 > 0) and np.all(np.diff(d3) > 0)


@pytest.mark.parametrize("alpha", [2.0 ** -20, 0.018, 0.25, 1.0 - 1e-9, 1.0])
def test_the_lobe_integral_against_quadrature(alpha):
    kern = G.GGXLobeKernel(alpha)
    a, b = kern.a, kern.b
    # ∫₀¹ x/(a + b(1 − x))² dx in y = 1 − x, split at multiples of the peak's width a/b (quadrature, not the closed form)
    f = lambda y: (1.0 - y) / (a + b * y) ** 2  # noqa: E731
    w = a / b if b > 0 else 1.0
    edges = sorted({0.0, 1.0, *[min(1.0, w * 10.0 ** k) for k in range(-1, 14)]})
    total = sum(integrate.quad(f, lo, hi, epsabs=0, epsrel=1e-12, limit=200)[0]
                for lo, hi in zip(edges[:-1], edges[1:]) if hi > lo)
    assert kern.lobe_integral() == pytest.approx(2 * math.pi * total, rel=1e-9)


# ---- the tree ------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [4, 6])
def test_the_tree_moments_are_the_sums_over_each_blocks_texels(n):
    rng = np.random.default_rng(5)
    cube = rng.random((6, n, n, 2)) ** 2
    tree = G.GGXSourceTree(cube)
    P = tree.P
    om = envmap.cube_solid_angles(n)
    w = np.concatenate([cube * om[..., None], om[..., None]], axis=-1)
    d = envmap.texel_directions(n)
    for L in tree.levels[1:]:
        b, m = L.b, L.m
        for f in range(6):
            for bi in range(m):
                for bj in range(m):
                    idx = f * m * m + bi * m + bj
                    rows = slice(bi * b, min((bi + 1) * b, n))
                    cols = slice(bj * b, min((bj + 1) * b, n))
                    ww = w[f, rows, cols].reshape(-1, 3)
                    dd = d[f, rows, cols].reshape(-1, 3)
                    if not ww.size:
                        assert not L.valid[idx] and np.all(L.M0[idx] == 0)
                        continue
                    c = L.c[idx]
                    e = dd - c
                    np.testing.assert_allclose(L.M0[idx], ww.sum(0), rtol=1e-13)
                    np.testing.assert_allclose(L.U[idx], e.T @ ww, rtol=1e-9, atol=1e-12 * np.abs(e.T @ ww).max())
                    vv = np.einsum("pi,pj,pq->ijq", e, e, ww)
                    i, j = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))
                    np.testing.assert_allclose(L.V[idx], vv[i, j], rtol=1e-9, atol=1e-12 * np.abs(vv).max())
                    # the cone holds every texel centre of the block
                    assert np.all(dd @ c >= L.cos_psi[idx] - 1e-15)
    assert P >= n and tree.levels[-1].M0.shape[0] == 6


# ---- the maps and their bound against the dense texel sum ----------------------------------------------------------
def _envs(n):
    rng = np.random.default_rng(11)
    return {"sky+sun": se.env_sky_sun(n), "random": rng.random((6, n, n, 3)) ** 4 + 1e-3,
            "delta": se.env_delta(n, texel=(4, n // 3, n // 2), radiance=1e4) + 0.01}


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("env", ["sky+sun", "random", "delta"])
@pytest.mark.parametrize("roughness, out_size", [(0.134, 16), (0.3, 8), (0.6, 16), (1.0, 4)])
def test_the_bound_holds_against_the_dense_texel_sum(kernel, env, roughness, out_size):
    cube = _envs(16)[env]
    maps, bound = G.convolve_ggx(cube, roughness, rtol=1e-3, out_size=out_size, kernel=kernel)
    ref = karis2013.prefilter_dense(cube, roughness, out_size=out_size)
    err = (np.abs(maps - ref) / ref).max(axis=-1)
    assert maps.shape == ref.shape and bound.shape == ref.shape[:-1]
    assert bound.max() <= 1e-3
    assert np.all(err <= bound), f"largest error/bound {np.max(err / bound):.3f}"


@pytest.mark.parametrize("kernel", KERNELS)
def test_a_face_size_that_is_no_power_of_two_and_tight_tolerances(kernel):
    cube = se.env_sky_sun(12)
    ref = karis2013.prefilter_dense(cube, 0.2, out_size=12)
    for rtol in (1e-2, 1e-5):
        maps, bound = G.convolve_ggx(cube, 0.2, rtol=rtol, kernel=kernel)
        err = (np.abs(maps - ref) / ref).max(axis=-1)
        assert bound.max() <= rtol and np.all(err <= bound)


@pytest.mark.parametrize("kernel", KERNELS)
def test_a_constant_environment_comes_out_constant(kernel):
    # numerator and denominator see the same kernel approximation block by block, so L ≡ c gives c to rounding
    c = np.array([2.5, 0.5, 1e-3])
    cube = np.broadcast_to(c, (6, 16, 16, 3)).copy()
    for r in (0.134, 0.5, 1.0):
        maps, bound = G.convolve_ggx(cube, r, rtol=1e-3, out_size=8, kernel=kernel)
        np.testing.assert_allclose(maps, np.broadcast_to(c, maps.shape), rtol=1e-12)


@pytest.mark.parametrize("kernel", KERNELS)
def test_directions_faces_and_levels_agree_with_the_dense_sum(kernel):
    cube = se.env_sky_sun(16)
    rng = np.random.default_rng(2)
    d = rng.normal(size=(3, 5, 3))
    maps, bound = G.convolve_ggx(cube, 0.4, rtol=1e-4, dirs=d, kernel=kernel)
    ref = karis2013.prefilter_dense(cube, 0.4, dirs=d)
    assert maps.shape == (3, 5, 3) and bound.shape == (3, 5)
    assert np.all(np.abs(maps - ref) <= bound[..., None] * ref)
    part, pb = G.convolve_ggx(cube, 0.4, rtol=1e-4, out_size=8, faces=[4, 1], kernel=kernel)
    ref8 = karis2013.prefilter_dense(cube, 0.4, out_size=8)
    assert part.shape == (2, 8, 8, 3) and np.all(np.abs(part - ref8[[4, 1]]) <= pb[..., None] * ref8[[4, 1]])
    out = G.convolve_ggx_levels(cube[..., 0], [(0.25, 8), (0.75, 4)], rtol=1e-4, kernel=kernel)
    for (m, b), (r, s) in zip(out, [(0.25, 8), (0.75, 4)]):
        ref = karis2013.prefilter_dense(cube[..., 0], r, out_size=s)
        assert m.shape == (6, s, s) and np.all(np.abs(m - ref) <= b * ref)


@needs_numba
def test_compiled_and_numpy_make_the_same_decisions_and_agree_to_rounding():
    cube = se.env_sky_sun(16)
    res = {}
    for k in ("numpy", "compiled"):
        maps, bound = G.convolve_ggx(cube, 0.3, rtol=1e-3, out_size=16, kernel=k, threads=1)
        res[k] = maps, bound, dict(G.LAST_INFO["levels"][0]["pairs"])
    assert res["numpy"][2] == res["compiled"][2]  # the same pairs at every level
    np.testing.assert_allclose(res["compiled"][0], res["numpy"][0], rtol=1e-12)
    np.testing.assert_allclose(res["compiled"][1], res["numpy"][1], rtol=1e-9)


@needs_numba
def test_the_thread_count_does_not_change_a_bit():
    cube = se.env_sky_sun(32)
    a = G.convolve_ggx(cube, 0.2, rtol=1e-3, out_size=16, kernel="compiled", threads=1)
    b = G.convolve_ggx(cube, 0.2, rtol=1e-3, out_size=16, kernel="compiled", threads=2)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


# ---- bad input: one line, nothing computed ------------------------------------------------------------------------
@pytest.mark.parametrize("call, what", [
    (lambda c: G.convolve_ggx(c, 0.0), "roughness"),
    (lambda c: G.convolve_ggx(c, 1.5), "roughness"),
    (lambda c: G.convolve_ggx(c, [0.2, 0.3]), "one roughness"),
    (lambda c: G.convolve_ggx(c, 0.3, rtol=0.0), "rtol"),
    (lambda c: G.convolve_ggx(c, 0.3, rtol=1e-300), "rtol"),
    (lambda c: G.convolve_ggx(c, 0.3, tile=3), "tile"),
    (lambda c: G.convolve_ggx(c, 0.3, out_size=0), "out_size"),
    (lambda c: G.convolve_ggx(c, 0.3, dirs=[[0.0, 0.0, 0.0]]), "zero"),
    (lambda c: G.convolve_ggx(c, 0.3, kernel="gpu"), "kernel"),
    (lambda c: G.convolve_ggx_levels(c, []), "levels"),
    (lambda c: G.convolve_ggx_levels(c, [0.3]), "levels"),
    (lambda c: G.convolve_ggx(np.full((6, 4, 4), np.nan), 0.3), "NaN"),
    (lambda c: G.convolve_ggx(np.ones((6, 4, 5)), 0.3), "shape"),
])
def test_bad_input_is_one_line(call, what):
    with pytest.raises(IBLError) as exc:
        call(np.ones((6, 4, 4, 3)))
    msg = str(exc.value)
    assert "\n" not in msg and what.lower() in msg.lower(), msg


@pytest.mark.parametrize("dtype", [np.float32, np.float16])
def test_float32_and_float16_input_is_summed_in_float64(dtype):
    # the sums run in float64 whatever the input: the result for a float32/float16 map equals the result for the same
    # values given as float64 (bit for bit: the same decisions on the same numbers)
    cube = se.env_sky_sun(8).astype(dtype)
    got = G.convolve_ggx(cube, 0.4, rtol=1e-3, kernel="numpy")
    ref = G.convolve_ggx(cube.astype(np.float64), 0.4, rtol=1e-3, kernel="numpy")
    assert got[0].dtype == np.float64
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[1], ref[1])


def test_radiance_that_overflows_the_sums_is_an_error_not_inf():
    # K peaks at 1/α⁴ and K‴ at ≈ 3/α¹⁰ (2^80 and 3·2^200 at the smallest roughness): L = 1e300 overflows float64, and
    # so does 1e250 at the smallest roughness (K‴ ≈ 5e60 there); refused before any work, with one line, no RuntimeWarning
    import warnings

    k = G.GGXLobeKernel(ggx_alpha(GGX_ROUGHNESS_MIN))
    assert k.peak_factor() == pytest.approx(18 * k.b ** 2 / k.a ** 4 + 24 * k.b ** 3 / k.a ** 5, rel=1e-12)
    for level, rough in ((1e300, 0.5), (1e250, GGX_ROUGHNESS_MIN)):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(IBLError) as exc:
                G.convolve_ggx(np.full((6, 4, 4), level), rough, kernel="numpy")
        assert "\n" not in str(exc.value) and "overflows" in str(exc.value)
    # a bright but representable map at the smallest roughness is summed (within its bound)
    cube = se.env_sky_sun(8) * 1e200
    maps, bound = G.convolve_ggx(cube, GGX_ROUGHNESS_MIN, rtol=1e-3, kernel="numpy")
    assert np.all(np.isfinite(maps)) and bound.max() <= 1e-3


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("n", [1, 2, 3])
def test_the_smallest_faces_against_the_dense_sum(kernel, n):
    # a 1² face has no block above its texel: the tree pads every face to at least 2² (padding of zero weight)
    cube = np.random.default_rng(n).random((6, n, n, 3)) + 0.1
    for roughness in (GGX_ROUGHNESS_MIN, 0.5, 1.0):
        maps, bound = G.convolve_ggx(cube, roughness, rtol=1e-3, kernel=kernel)
        ref = karis2013.prefilter_dense(cube, roughness)
        assert bound.max() <= 1e-3 and np.all((np.abs(maps - ref) / ref).max(axis=-1) <= bound)
