"""The converged reference's bookkeeping helpers that replace NumPy expressions by faster ones with the same values,
bit for bit (issue 40's sweep): the compiled per-pixel sums against ``np.bincount`` per column, the channel means of
a sweep's weights against NumPy's mean, the face-plane directions against the row-wise expression, and the
quadrature's ``pix=`` rows against gathered copies."""

import numpy as np
import pytest

from ibl_ref.environment.envmap import face_frames
from ibl_ref.groundtruth.kernels import numba_available
from ibl_ref.rendering.materials import GGXLobe, PhongLobe
from ibl_ref.rendering.reference_converged import _dirs, _Env, _group_means
from ibl_ref.rendering.reference_quadrature import get_quadrature

KERNELS = ["numpy"] + (["compiled"] if numba_available() else [])


def _weights(rng, S, C):
    """Non-negative weights over many magnitudes, with zeros and subnormals (a narrow lobe's far tails)."""
    W = rng.random((S, C)) * np.exp(rng.normal(scale=30.0, size=(S, C)))
    W[rng.random((S, C)) < 0.1] = 0.0
    W[rng.random((S, C)) < 0.02] = 5e-324 * rng.integers(1, 50, size=None)
    return W


def _pixels(rng, P, lobe):
    """P random normals, views (some below the horizon) and the lobe's axes."""
    n = rng.normal(size=(P, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = n + rng.normal(scale=0.8, size=(P, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    d = lobe.direction(n, v)
    return n, v, d / np.linalg.norm(d, axis=1, keepdims=True)


def _blocks(rng, S, nb, k):
    """S random blocks (f, r0, c0) of k×k texels, one per base cell of face size nb."""
    cells = rng.integers(0, 6 * nb * nb, size=S)
    return cells // (nb * nb), ((cells // nb) % nb) * k, (cells % nb) * k


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("C", [1, 3, 5, 15])
@pytest.mark.parametrize("mask", [None, "bool", "float"])
def test_sums_by_is_bincount(kernel, C, mask):
    """Quadrature.sums_by: column c is np.bincount(idx, weights=W[:, c] · m) (the weights added in input order), bit
    for bit, for both implementations; unsorted and int32 indices, pixels without rows, no rows at all."""
    rng = np.random.default_rng(C)
    q = get_quadrature(kernel)
    for S, P in ((0, 4), (1, 3), (2000, 37)):
        idx = rng.integers(0, P - 1, size=S).astype(np.int32)  # the last pixel gets no row
        W = _weights(rng, S, C)
        m = {None: None, "bool": rng.random(S) < 0.6, "float": rng.random(S).clip(0.3) - 0.3}[mask]
        want = np.stack([np.bincount(idx, weights=W[:, c] if m is None else W[:, c] * m, minlength=P)
                         for c in range(C)], -1)
        got = q.sums_by(idx, W, P, m)
        assert got.shape == (P, C)
        assert np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))


@pytest.mark.parametrize("E,Cg", [(1, 3), (2, 3), (5, 3), (1, 1), (3, 1), (2, 4), (1, 15)])
def test_group_means_is_numpy_mean(E, Cg):
    """_group_means: W.reshape(n, E, Cg).mean(axis=-1) bit for bit (groups of three written out as ((W₀ + W₁) + W₂) / 3,
    NumPy's order of the additions over a short last axis; other group sizes are that mean itself)."""
    rng = np.random.default_rng(E * 16 + Cg)
    for n in (0, 1, 2, 7, 100, 20001):
        W = _weights(rng, n, E * Cg)
        W[: n // 2] = rng.normal(size=(n // 2, E * Cg))  # signs too (cancellations: the order shows)
        want = W.reshape(n, E, Cg).mean(axis=-1)
        got = _group_means(W, E)
        assert got.shape == (n, E) and np.array_equal(got, want)
        sub = W[rng.random(n) < 0.5]  # a masked copy, as the reference's kept pairs
        assert np.array_equal(_group_means(sub, E), sub.reshape(len(sub), E, Cg).mean(axis=-1))


def test_dirs_is_rowwise_expression():
    """_dirs: the component-wise (F₀ + u F₁) + v F₂ (and its normalisation) equals the row-wise expression over
    gathered frames bit for bit, signs of zeros included."""
    rng = np.random.default_rng(3)
    F = face_frames("openexr")
    for n in (0, 1, 5000):
        f = rng.integers(0, 6, size=n)
        u, v = rng.uniform(-1, 1, size=n), rng.uniform(-1, 1, size=n)
        u[: n // 10], v[n // 20: n // 10] = 0.0, -0.0
        Ff = F[f]
        d = Ff[:, 0, :] + u[:, None] * Ff[:, 1, :] + v[:, None] * Ff[:, 2, :]
        ln = np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2])
        for normalize, want in ((False, d), (True, d / ln[:, None])):
            got = _dirs(f, u, v, normalize=normalize)
            assert got.shape == (n, 3) and got.flags.c_contiguous
            assert np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("lobe", [PhongLobe(16.0, "mirror"), GGXLobe(0.3, f0=1.0)], ids=["phong16", "ggx0.3"])
def test_block_sums_pix_rows(kernel, lobe):
    """block_sums with per-pixel arrays and ``pix`` (pair s reads row pix[s]) gives the sums of the gathered
    per-pair arrays bit for bit."""
    rng = np.random.default_rng(11)
    nb, M, P, S = 4, 16, 40, 500
    k = M // nb
    env = _Env(rng.gamma(0.5, 1.0, size=(6, 8, 8, 6)), nb)
    n, v, d = _pixels(rng, P, lobe)
    pix = rng.integers(0, P, size=S)
    f, r0, c0 = _blocks(rng, S, nb, k)
    q = get_quadrature(kernel)
    W1, S1 = q.block_sums(env, lobe, n[pix], v[pix], d[pix], f, r0, c0, k, M)
    W2, S2 = q.block_sums(env, lobe, n, v, d, f, r0, c0, k, M, pix=pix)
    assert (W1 > 0).any() and np.array_equal(W1, W2)
    assert (S1 is None and S2 is None) or np.array_equal(S1, S2)


@pytest.mark.parametrize("kernel", KERNELS)
def test_positive_rows_is_mean_positive(kernel):
    """Quadrature.positive_rows: W.mean(axis=-1) > 0, for rows of zeros, ordinary weights, subnormal ones (whose mean
    can round to 0) and, for the fallback to the mean, negative and NaN entries."""
    rng = np.random.default_rng(5)
    q = get_quadrature(kernel)
    for C in (3, 15):
        W = _weights(rng, 3000, C)
        W[:300] = 0.0
        W[300:400] = 0.0
        W[300:400, 0] = 5e-324 * rng.integers(1, 40, size=100)  # mean rounds to 0 for the smallest
        assert np.array_equal(q.positive_rows(W), W.mean(axis=-1) > 0)
        for bad in (-1.0, np.nan):
            W2 = W.copy()
            W2[17, 1] = bad
            assert np.array_equal(q.positive_rows(W2), W2.mean(axis=-1) > 0)
    assert q.positive_rows(np.zeros((0, 3))).shape == (0,)


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("E,Cg", [(1, 3), (5, 3), (2, 1), (2, 4)])
def test_relative_means_is_definition(kernel, E, Cg):
    """Quadrature.relative_means: W.reshape(n, E, Cg).mean(axis=-1) / w[:, None] bit for bit (compiled: groups of
    three in one pass)."""
    rng = np.random.default_rng(E + 7 * Cg)
    q = get_quadrature(kernel)
    for n in (0, 1, 5000):
        W = _weights(rng, n, E * Cg)
        W[: n // 2] = rng.normal(size=(n // 2, E * Cg))
        w = rng.random(n) * 3.0 + 1e-3
        want = W.reshape(n, E, Cg).mean(axis=-1) / w[:, None]
        got = q.relative_means(W, E, w)
        assert got.shape == (n, E) and np.array_equal(got, want)


@pytest.mark.skipif(not numba_available(), reason="numba is not installed (the compiled kernels)")
@pytest.mark.parametrize("material", ["ggx:0.3", (0.0, 1.0, 0.9)], ids=["ggx0.3", "phong10"])
def test_compiled_pixel_sums_match_numpy_path(monkeypatch, material):
    """CompiledQuadrature.dirty_sums (the per-pixel sums of a block's refinement rounds in one compiled pass) gives a
    sweep bit-identical to the same render through _Block.pixel_sums' NumPy expressions (dirty_sums hidden)."""
    from ibl_ref.rendering import reference_quadrature as rq
    from ibl_ref.rendering.reference_render import render_reference
    from ibl_ref.rendering.scenes import default_camera, teapot_on_ground
    from ibl_ref.synthetic.synthetic_envs import SUN_NEAR_CORNER, make_env

    monkeypatch.setenv("IBL_REF_KERNEL", "compiled")
    meshes = teapot_on_ground()
    cam = default_camera(meshes[:1], size=12)
    envs = [make_env("sky_sun", n=16), make_env("sky_sun", n=16, sun_direction=SUN_NEAR_CORNER)]
    a = render_reference(meshes, cam, envs, material=material, rtol=5e-3)
    monkeypatch.delattr(rq.CompiledQuadrature, "dirty_sums")
    b = render_reference(meshes, cam, envs, material=material, rtol=5e-3)
    assert a[0].info["lobes"][0]["rounds_max"] > 1  # rounds ran (pixel_sums recomputed dirty pixels)
    for x, y in zip(a, b):
        assert np.array_equal(x.image, y.image) and np.array_equal(x.error, y.error)
        assert x.info["err_rel_l1"] == y.info["err_rel_l1"] and x.info["n_rays"] == y.info["n_rays"]


def test_by_pixel_is_stable_argsort():
    """_by_pixel: np.argsort(pix, kind="stable") (16-bit radix for small pixel counts, the int64 sort above)."""
    from ibl_ref.rendering.reference_converged import _by_pixel

    rng = np.random.default_rng(2)
    for P in (1, 256, 1 << 16, (1 << 16) + 5):
        pix = rng.integers(0, P, size=5000)
        assert np.array_equal(_by_pixel(pix, P), np.argsort(pix, kind="stable"))


@pytest.mark.parametrize("kernel", KERNELS)
def test_max_ratio_is_definition(kernel):
    """Quadrature.max_ratio: (Ye / T).max(axis=1) bit for bit (zeros of both signs, ties and NaN included)."""
    rng = np.random.default_rng(9)
    q = get_quadrature(kernel)
    for E in (2, 5):
        Ye = _weights(rng, 4000, E)
        Ye[:100] = 0.0
        Ye[100:200, 0] = -0.0
        Ye[200:300] = Ye[200:300, :1]  # ties
        Ye[300, 1] = np.nan
        Ye[301, 0] = np.nan
        T = rng.random(E) + 0.5
        T[0] = 1.0
        want = (Ye / T).max(axis=1)
        got = q.max_ratio(Ye, T)
        assert np.array_equal(got, want, equal_nan=True) and np.array_equal(np.signbit(got), np.signbit(want))


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("lobe", [PhongLobe(16.0, "mirror"), GGXLobe(0.3, f0=1.0)], ids=["phong16", "ggx0.3"])
def test_block_sums_into_rows(kernel, lobe):
    """block_sums with out=(W, S) and rows writes pair s's sums into row rows[s] (the other rows untouched; S only
    for a normalised lobe): the values of the returned arrays scattered, bit for bit."""
    rng = np.random.default_rng(13)
    nb, M, S = 4, 16, 300
    k = M // nb
    env = _Env(rng.gamma(0.5, 1.0, size=(6, 8, 8, 15)), nb)
    n, v, d = _pixels(rng, S, lobe)
    f, r0, c0 = _blocks(rng, S, nb, k)
    q = get_quadrature(kernel)
    W1, S1 = q.block_sums(env, lobe, n, v, d, f, r0, c0, k, M)
    rows = rng.permutation(2 * S)[:S]
    W2, S2 = np.full((2 * S, 15), 7.0), np.full(2 * S, 7.0)
    out = q.block_sums(env, lobe, n, v, d, f, r0, c0, k, M, out=(W2, S2), rows=rows)
    assert out[0] is W2 and out[1] is S2
    rest = np.setdiff1d(np.arange(2 * S), rows)
    assert np.array_equal(W2[rows], W1) and (W2[rest] == 7.0).all()
    assert np.array_equal(S2[rows], S1) if S1 is not None else (S2 == 7.0).all()
