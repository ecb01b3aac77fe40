"""The converged reference's quadrature (ibl_ref.rendering.reference_quadrature): the compiled loops against the NumPy
definition, both against an independent integral, and a render with either giving the same image."""

import numpy as np
import pytest
from scipy import integrate

from ibl_ref.errors import IBLError
from ibl_ref.groundtruth.kernels import numba_available
from ibl_ref.rendering.materials import GGXLobe, PhongLobe
from ibl_ref.rendering.reference_converged import _Env
from ibl_ref.rendering.reference_quadrature import get_quadrature

needs_numba = pytest.mark.skipif(not numba_available(), reason="numba is not installed (the compiled kernels)")
KERNELS = ["numpy"] + (["compiled"] if numba_available() else [])

LOBES = [PhongLobe(1.0, "normal"), PhongLobe(16.0, "mirror"), PhongLobe(256.0, "mirror"), GGXLobe(0.1),
         GGXLobe(0.3, f0=1.0), GGXLobe(0.6, smith="separable"), GGXLobe(1.0, f0=0.5)]


def _pairs(rng, S, nb, k, M):
    """S random (pixel, block) pairs: normals, views toward the upper side mostly, blocks of k×k texels of face
    size M inside base cells of face size nb (several pixels per block, as in a render)."""
    n = rng.normal(size=(S, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = n + rng.normal(scale=0.8, size=(S, 3))  # some views below the horizon (n·v ≤ 0: weight 0)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    cells = rng.integers(0, 6 * nb * nb, size=S // 3)[rng.integers(0, S // 3, size=S)]
    f, i, j = cells // (nb * nb), (cells // nb) % nb, cells % nb
    return n, v, f, i * k, j * k


def _env(rng, N, nb, C=3):
    a = rng.gamma(0.5, 1.0, size=(6, N, N, C))
    a[2, :2, :2] *= 1e3  # a small bright source
    return _Env(a, nb)


@needs_numba
@pytest.mark.parametrize("lobe", LOBES, ids=lambda lb: f"{lb.kind}-{getattr(lb, 's', getattr(lb, 'roughness', 0))}")
@pytest.mark.parametrize("N,nb,M", [(8, 4, 16), (16, 4, 16), (12, 4, 32)])  # M a multiple of N, N = M, neither
def test_compiled_matches_numpy(lobe, N, nb, M):
    """The same float64 sums in another order of the roundings: each sum of k² ≤ 64 non-negative terms agrees to
    a few ulps per term (bound 64 × 4 × 2^-53 ≈ 3e-14 relative; 1e-12 leaves room for the loops' pow and the
    weights' rearranged algebra, e.g. D·G·F/(4 n·ω n·v)·n·ω written as D·G·F/(4 n·v)), except where GGX's D is
    ill-conditioned (below)."""
    rng = np.random.default_rng(7)
    env = _env(rng, N, nb)
    k = M // nb
    n, v, f, r0, c0 = _pairs(rng, 300, nb, k, M)
    d = lobe.direction(n, v)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    Wn, Sn = get_quadrature("numpy").block_sums(env, lobe, n, v, d, f, r0, c0, k, M)
    Wc, Sc = get_quadrature("compiled").block_sums(env, lobe, n, v, d, f, r0, c0, k, M)
    assert (Wn > 0).any()
    # GGX near its peak: D's denominator (n·h)²(α² − 1) + 1 cancels to ≈ α², so an ulp of n·h (computed in another
    # order) moves D by ≈ 4ε/α² relative (2.6e-12 at roughness 0.1): the tolerance takes 8ε/α² where that is larger
    rtol = max(1e-12, 8 * np.finfo(float).eps / lobe.alpha ** 2) if lobe.kind == "ggx" else 1e-12
    np.testing.assert_allclose(Wc, Wn, rtol=rtol, atol=1e-300)
    if lobe.normalised:
        np.testing.assert_allclose(Sc, Sn, rtol=1e-12)
    else:
        assert Sn is None and Sc is None


def _ggx_albedo(lobe, mu):
    """∫ f_s(ω, v)(n·ω) dω over the hemisphere for n·v = μ, by scipy's adaptive quadrature in spherical coordinates
    about n (an independent route: no texels, no cube map)."""
    from ibl_ref.lobes.brdfs import ggx

    v = np.array([np.sqrt(1 - mu * mu), 0.0, mu])
    n = np.array([0.0, 0.0, 1.0])

    def f(phi, theta):
        w = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
        return float(ggx(w, v, n, roughness=lobe.roughness, f0=lobe.f0, smith=lobe.smith)) * np.cos(theta) \
            * np.sin(theta)

    # split at the peak's polar angle (the lobe is narrow there): φ symmetric → 2 ∫_0^π
    th_r = np.arccos(mu)
    tot = 0.0
    for a, b in ((0.0, th_r), (th_r, np.pi / 2)):
        tot += 2 * integrate.dblquad(f, a, b, 0.0, np.pi, epsabs=1e-10, epsrel=1e-8)[0]
    return tot


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("roughness,mu", [(0.6, 0.7), (0.4, 0.95)])
def test_ggx_sums_give_the_directional_albedo(kernel, roughness, mu):
    """With L ≡ 1 the block sums over the whole sphere are the directional albedo ∫ f_s (n·ω) dω: against scipy's
    adaptive quadrature.  Tolerance: the midpoint rule at face size 128 on a lobe ≥ 10 texels across (α ≥ 0.16):
    measured ≈ 1e-5 relative; 2e-4 bounds it."""
    lobe = GGXLobe(roughness, f0=1.0)
    M, nb = 128, 4
    env = _Env(np.ones((6, 2, 2, 1)), nb)
    K = 6 * nb * nb
    cells = np.arange(K)
    n = np.tile([[0.0, 0.0, 1.0]], (K, 1))
    v = np.tile([[np.sqrt(1 - mu * mu), 0.0, mu]], (K, 1))
    d = lobe.direction(n, v)
    k = M // nb
    W, _ = get_quadrature(kernel).block_sums(env, lobe, n, v, d, cells // (nb * nb), ((cells // nb) % nb) * k,
                                             (cells % nb) * k, k, M)
    np.testing.assert_allclose(W.sum(), _ggx_albedo(lobe, mu), rtol=2e-4)


@pytest.mark.parametrize("kernel", KERNELS)
def test_phong_normalisation_is_the_lobe_integral(kernel):
    """A Phong lobe's normalisation Σ max(d·ω,0)^s Ω over the sphere is 2π/(s+1) (closed form); the midpoint rule at
    face size 64 for s = 16 (θ½ ≈ 16°, ~12 texels across) is within 1e-4."""
    lobe, M, nb = PhongLobe(16.0, "mirror"), 64, 4
    env = _Env(np.ones((6, 2, 2, 1)), nb)
    K = 6 * nb * nb
    cells = np.arange(K)
    d = np.tile(np.array([[0.3, -0.5, 0.8]]) / np.linalg.norm([0.3, -0.5, 0.8]), (K, 1))
    k = M // nb
    _, S = get_quadrature(kernel).block_sums(env, lobe, d, d, d, cells // (nb * nb), ((cells // nb) % nb) * k,
                                             (cells % nb) * k, k, M)
    np.testing.assert_allclose(S.sum(), 2 * np.pi / 17.0, rtol=1e-4)


@needs_numba
@pytest.mark.parametrize("material", ["ggx:0.3", (0.0, 1.0, 0.9375)])
def test_render_is_the_same_with_either_quadrature(material):
    """A render's refinement decisions compare sums that differ by ≈ 1e-15 between the two: the images agree to
    float64 rounding (1e-9), and info says which quadrature ran."""
    from ibl_ref.rendering.reference_render import render_reference
    from ibl_ref.rendering.scenes import default_camera, teapot_on_ground
    from ibl_ref.synthetic.synthetic_envs import env_sky_sun

    env = env_sky_sun(8)
    meshes = teapot_on_ground()
    cam = default_camera(meshes, 12)
    out = {}
    for kernel in ("numpy", "compiled"):
        with pytest.MonkeyPatch.context() as mp:  # the render resolves its quadrature from $IBL_REF_KERNEL
            mp.setenv("IBL_REF_KERNEL", kernel)
            res = render_reference(meshes, cam, env, material=material, rtol=1e-2)
        out[kernel] = res
        assert {lb["quadrature"] for lb in res.info["lobes"]} == {kernel}
    np.testing.assert_allclose(out["compiled"].image, out["numpy"].image, rtol=1e-9, atol=1e-12)


def test_unknown_or_unavailable_quadrature_is_one_line(monkeypatch):
    with pytest.raises(IBLError, match="must be one of"):
        get_quadrature("fortran")
    monkeypatch.setenv("NUMBA_DISABLE_JIT", "1")
    with pytest.raises(IBLError, match="compiled.*needs numba"):
        get_quadrature("compiled")


@needs_numba
@pytest.mark.parametrize("C", [1, 2, 3, 4, 5, 7, 8, 15])
def test_compiled_channel_sums_are_running_sums_in_texel_order(C):
    """The compiled loops' accumulation runs several channels' sums side by side (four, then three, then one at a
    time): each channel's sum is still the plain running sum over the texels in order, bit for bit."""
    from ibl_ref.rendering.reference_quadrature_loops import _accumulate

    rng = np.random.default_rng(C)
    kk = 97
    wb = rng.random(kk) * 10.0 ** rng.integers(-8, 3, kk)
    Lb = rng.random((C, kk)) * 10.0 ** rng.integers(-5, 5, (C, kk))
    W = np.full((3, C), np.nan)
    _accumulate(wb, Lb, W, 1)
    for ch in range(C):
        acc = 0.0
        for t in range(kk):
            acc += float(wb[t]) * float(Lb[ch, t])
        assert W[1, ch] == acc
    assert np.isnan(W[0]).all() and np.isnan(W[2]).all()


@needs_numba
@pytest.mark.parametrize("lobe", [PhongLobe(16.0, "mirror"), GGXLobe(0.1)], ids=["phong16", "ggx0.1"])
def test_corner_table_gives_the_same_sums(lobe, monkeypatch):
    """The compiled quadrature's table of the corners' A (``CompiledQuadrature.area_table``) changes no bit: block
    sums with the table empty, filled by other blocks (another face and overlapping blocks: a corner computed for
    one block is read by the next) and without a table are equal; the table holds A(u, v) where it was filled."""
    from ibl_ref.rendering import reference_quadrature as rq
    from ibl_ref.rendering.reference_quadrature import CompiledQuadrature

    rng = np.random.default_rng(3)
    nb, M = 4, 32
    env = _env(rng, 16, nb)
    k = M // nb
    n, v, f, r0, c0 = _pairs(rng, 200, nb, k, M)
    d = lobe.direction(n, v)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    quad = CompiledQuadrature()
    W1, S1 = quad.block_sums(env, lobe, n, v, d, f, r0, c0, k, M)  # the table filled by these blocks
    tab = quad.area_table(M)
    assert np.isfinite(tab).any() and np.isnan(tab).any()
    half = k // 2  # blocks straddling the first ones, on the next face: corners read from the table
    W2, S2 = quad.block_sums(env, lobe, n, v, d, (f + 1) % 6, np.minimum(r0 + half, M - k),
                             np.minimum(c0 + half, M - k), k, M)
    monkeypatch.setattr(rq, "AREA_TABLE_MAX", 0)
    plain = CompiledQuadrature()
    assert len(plain.area_table(M)) == 0
    W1p, S1p = plain.block_sums(env, lobe, n, v, d, f, r0, c0, k, M)
    W2p, S2p = plain.block_sums(env, lobe, n, v, d, (f + 1) % 6, np.minimum(r0 + half, M - k),
                                np.minimum(c0 + half, M - k), k, M)
    assert np.array_equal(W1, W1p) and np.array_equal(W2, W2p)
    if lobe.normalised:
        assert np.array_equal(S1, S1p) and np.array_equal(S2, S2p)
    h = 2.0 / M
    ij = np.flatnonzero(np.isfinite(tab))
    r, c = ij // (M + 1), ij % (M + 1)
    x, y = c * h - 1.0, r * h - 1.0
    np.testing.assert_allclose(tab[ij], np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0)), rtol=1e-15, atol=1e-300)
