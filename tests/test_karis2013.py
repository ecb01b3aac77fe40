"""Tests of ibl_ref.prefilter.karis2013 (split sum: DFG table, n = v = r prefilters, roughness chain, shading).

Every reference comes from another route: brdfs.albedo (a graded Gauss–Legendre rule in l), a 1-D adaptive
quadrature at normal view, Monte Carlo with its own standard error, a brute-force double loop with the GGX NDF
written out here, the continuum prefilter of a linear map, and closed-form limits.
"""

import warnings

import numpy as np
import pytest
from scipy import integrate

from ibl_ref.environment import envmap
from ibl_ref.environment.sampling import sample_bilinear
from ibl_ref.errors import IBLError
from ibl_ref.lobes import brdfs
from ibl_ref.prefilter import ggx_phong_mapping, karis2013 as k
from ibl_ref.synthetic import synthetic_envs as se

GRID = [(1.0, 0.05), (0.9, 0.1), (0.5, 0.3), (0.2, 0.6), (0.05, 0.9), (0.02, 0.2), (0.7, 1.0), (0.999, 0.5)]


# ------------------------------------------------------------------------------------------- DFG terms
@pytest.mark.parametrize("mu,r", GRID)
def test_dfg_terms_match_the_independent_albedo(mu, r):
    # F0·A + B is the directional albedo with Fresnel F0 (Schlick is linear in F0): A + B = albedo(F0 = 1),
    # B = albedo(F0 = 0), both from brdfs.albedo's graded rule in l.  That rule is accurate to ≈ 1e-8 at low
    # roughness (at normal view it is 8.6e-9 off the 1-D adaptive quadrature of the next test, which agrees with
    # dfg_terms to 2e-10) -> tolerance 5e-8.
    A, B = k.dfg_terms(mu, r)
    th, w = np.arccos(mu), min(0.02, r * r / 4)
    a1 = brdfs.albedo(brdfs.get_brdf("ggx", roughness=r, f0=1.0), th, width=w)
    a0 = brdfs.albedo(brdfs.get_brdf("ggx", roughness=r, f0=0.0), th, width=w)
    assert A + B == pytest.approx(a1, abs=5e-8)
    assert B == pytest.approx(a0, abs=5e-8)
    for f0 in (0.04, 0.5):
        af = brdfs.albedo(brdfs.get_brdf("ggx", roughness=r, f0=f0), th, width=w)
        assert f0 * A + B == pytest.approx(af, abs=5e-8)


@pytest.mark.parametrize("r", [0.05, 0.3, 0.8])
def test_dfg_at_normal_view_against_one_dimensional_quadrature(r):
    # v = n: the integrand is radially symmetric, albedo(F0=1) = ∫ D(cos θ/2) G2(cos θ, 1)/4 · 2π sin θ dθ over
    # θ ∈ [0, π/2] (f·n·l = D G/(4 n·v), h at θ/2).  Adaptive quadrature with breakpoints at multiples of α: its
    # own estimate < 1e-13 -> tolerance 1e-9 (the default rule's measured accuracy, 7.5e-9 worst over the table).
    a = r * r

    def f(th):
        return float(brdfs.ndf(np.cos(th / 2), a) * brdfs.smith_g2(np.cos(th), 1.0, a) / 4 * np.sin(th) * 2 * np.pi)

    pts = sorted({min(a * x, np.pi / 2 - 1e-4) for x in (0.5, 1, 2, 5, 10, 50, 100, 500)} | {np.pi / 2 - 1e-5})
    edges = [0.0] + pts + [np.pi / 2]
    with warnings.catch_warnings():  # quad's round-off note at the 1e-13 request
        warnings.simplefilter("ignore", integrate.IntegrationWarning)
        ref = sum(integrate.quad(f, lo, hi, epsabs=1e-15, epsrel=1e-13, limit=500)[0]
                  for lo, hi in zip(edges[:-1], edges[1:]))
    A, B = k.dfg_terms(1.0, r)
    assert A + B == pytest.approx(ref, abs=1e-9)


@pytest.mark.parametrize("mu,r", [(0.5, 0.3), (0.2, 0.8), (0.9, 0.6)])
def test_dfg_terms_against_monte_carlo(mu, r):
    # cosine-weighted hemisphere sampling of l, estimator f·π per sample (pdf n·l/π), 4e5 samples, seed 7; the
    # tolerance is 5 standard errors estimated from the samples themselves (false-failure odds ~6e-7)
    rng = np.random.default_rng(7)
    n = 400_000
    u1, u2 = rng.random(n), rng.random(n)
    rr, ph = np.sqrt(u1), 2 * np.pi * u2
    wi = np.stack([rr * np.cos(ph), rr * np.sin(ph), np.sqrt(1 - u1)], axis=-1)
    wo = np.array([np.sqrt(1 - mu * mu), 0.0, mu])
    A, B = k.dfg_terms(mu, r)
    for f0, ref in ((1.0, A + B), (0.0, B)):
        x = brdfs.ggx(wi, wo, roughness=r, f0=f0) * np.pi
        assert abs(x.mean() - ref) < 5 * x.std(ddof=1) / np.sqrt(n)


@pytest.mark.parametrize("mu", [1.0, 0.7, 0.3, 0.1])
def test_dfg_smooth_limit(mu):
    # roughness → 0: the BRDF tends to a mirror (G → 1, h → n, v·h → n·v): A + B → 1 for F0 = 1 and
    # B → (1 − n·v)⁵, A → 1 − (1 − n·v)⁵; the error falls monotonically (measured ≈ r⁴, 1 − (A+B) ≈ 1e-8 .. 5e-7
    # at r = 0.01)
    rs = [0.2, 0.1, 0.05, 0.02, 0.01]
    errs = []
    for r in rs:
        A, B = k.dfg_terms(mu, r)
        errs.append((abs(1 - (A + B)), abs(B - (1 - mu) ** 5)))
        assert A + B <= 1.0 + 1e-12  # energy conservation of the single-scattering BRDF
    e1, e2 = np.array(errs).T
    assert np.all(np.diff(e1) < 0) and np.all(np.diff(e2) < 0)
    assert e1[-1] < 1e-6 and e2[-1] < 3e-6


def test_dfg_broadcasting_and_shapes():
    nv = np.array([[0.3], [0.8]])
    r = np.array([0.2, 0.5, 0.9])
    A, B = k.dfg_terms(nv, r)
    assert A.shape == B.shape == (2, 3)
    for i in range(2):
        for j in range(3):
            a, b = k.dfg_terms(float(nv[i, 0]), float(r[j]))
            assert A[i, j] == pytest.approx(a, abs=1e-14) and B[i, j] == pytest.approx(b, abs=1e-14)
    assert isinstance(k.dfg_terms(0.5, 0.5)[0], float)


def test_dfg_table_accuracy():
    # quadrature: against the refined rule (2x panels and phi nodes, 1.5x nodes) on a sub-grid: < 1e-8 (measured
    # 7.5e-9).  Interpolation: bilinear between texel centres, worst at the midpoints; against dfg_terms at all
    # midpoints of the 64² table: max |Δ(F0·A + B)| 1.8e-2, always in the lowest n·v row (n·v = 1/64: at grazing
    # view the albedo of a near-mirror changes on the scale of n·v itself, so that error does not shrink with the
    # table size); for n·v ≥ 0.2 at most 2.9e-4 (F0 = 0.04) and 2.4e-4 (F0 = 1), O(h²): 3.7x smaller than at 32²;
    # mean 7.8e-5 / 1.4e-4
    T = k.build_dfg_table(64)
    assert T.quadrature_error < 1e-8
    errs = {}
    for size in (32, 64):
        tab = k.build_dfg_table(size, estimate_error=False)
        mid = np.arange(1, size) / size
        NV, R = np.meshgrid(mid, mid, indexing="ij")
        A, B = k.dfg_terms(NV, R)
        a, b = tab.lookup(NV, R)
        for f0 in (0.04, 1.0):
            e = np.abs(f0 * a + b - (f0 * A + B))
            errs[size, f0] = (e.max(), e[mid >= 0.2].max(), e.mean())
    for f0 in (0.04, 1.0):
        e_max, e_02, e_mean = errs[64, f0]
        assert e_max < 2e-2 and e_02 < 4e-4 and e_mean < 2e-4
        assert errs[32, f0][1] > 3 * e_02
    # at the texel centres the table is its own quadrature
    a, b = T.lookup(T.n_dot_v[:, None], T.roughness[None, :])
    np.testing.assert_allclose(a, T.scale, atol=1e-15)
    np.testing.assert_allclose(b, T.bias, atol=1e-15)
    assert T.nbytes == 2 * 64 * 64 * 8


# ------------------------------------------------------------------------------------------- prefilters
def _brute_force_prefilter(cube, r_dir, roughness):
    # P(r) = Σ L K Ω / Σ K Ω with K = D(cos θh) max(r·ω, 0), D written out: α²/(π (cos²θh (α² − 1) + 1)²)
    n = cube.shape[1]
    a2 = roughness ** 4
    dirs = envmap.texel_directions(n)
    om = envmap.texel_solid_angles(n)
    num = np.zeros(cube.shape[-1])
    den = 0.0
    for f in range(6):
        for i in range(n):
            for j in range(n):
                c = float(np.dot(r_dir, dirs[f, i, j]))
                if c <= 0:
                    continue
                cos2 = 0.5 * (1 + c)
                d = a2 / (np.pi * (cos2 * (a2 - 1) + 1) ** 2)
                num += cube[f, i, j] * d * c * om[i, j]
                den += d * c * om[i, j]
    return num / den


@pytest.mark.parametrize("roughness", [0.3, 0.7, 1.0])
def test_exact_prefilter_against_brute_force(roughness):
    rng = np.random.default_rng(3)
    cube = rng.random((6, 4, 4, 2)) ** 3
    dirs = rng.normal(size=(7, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ref = np.array([_brute_force_prefilter(cube, d, roughness) for d in dirs])
    # the dense texel sum (the oracle) to rounding; the tree within its own rigorous bound
    np.testing.assert_allclose(k.prefilter_dense(cube, roughness, dirs=dirs), ref, rtol=1e-12)
    got, bound = k.prefilter_exact(cube, roughness, dirs=dirs, return_bound=True)
    assert np.all(np.abs(got - ref) <= bound[:, None] * ref) and bound.max() <= k.EXACT_RTOL
    full = k.prefilter_dense(cube, roughness)
    assert full.shape == (6, 4, 4, 2)
    np.testing.assert_allclose(full[2, 1, 3], _brute_force_prefilter(cube, envmap.texel_directions(4)[2, 1, 3],
                                                                     roughness), rtol=1e-12)


@pytest.mark.parametrize("roughness", [0.5, 0.8])
def test_exact_prefilter_of_a_linear_map_converges_to_the_continuum(roughness):
    # L = a + b·ω: a radially symmetric kernel keeps a and scales b·r by its mean cosine μ (Funk–Hecke, band 1), so
    # P(r) = a + μ b·r with μ from a 1-D quadrature of the kernel (ggx_phong_mapping.kernel_mean_cosine).  The texel
    # sum is a midpoint rule: error O(N⁻²) -> it must fall ≥ 3x from N = 8 to 16 and be < 2e-3·|b| at 16.
    a, b = 1.0, np.array([0.3, 0.5, -0.2])
    mu = ggx_phong_mapping.kernel_mean_cosine(roughness)
    errs = []
    for n in (8, 16):
        cube = se.env_gradient(n, a=a, b=b, sample="center")[..., :1]
        r = envmap.texel_directions(4).reshape(-1, 3)
        got = k.prefilter_exact(cube, roughness, dirs=r)[:, 0]
        errs.append(np.max(np.abs(got - (a + mu * r @ b))))
    assert errs[1] < errs[0] / 3
    assert errs[1] < 2e-3 * np.linalg.norm(b)


def test_every_prefilter_returns_a_constant_exactly():
    # white furnace, first factor: each quadrature of P is a normalised average of L
    c = np.array([1.5, 0.7, 0.2])
    cube = np.broadcast_to(c, (6, 8, 8, 3)).copy()
    for p in (k.prefilter_exact(cube, 0.4),
              k.prefilter_importance(cube, 0.9, samples=3, sequence="random"),
              k.prefilter_importance(cube, 0.2, samples=64)):
        np.testing.assert_allclose(p, np.broadcast_to(c, p.shape), rtol=1e-14)
    chain = k.build_chain(cube, n_levels=4)
    d = np.random.default_rng(0).normal(size=(50, 3))
    rough = np.linspace(0.01, 1.0, 50)
    np.testing.assert_allclose(chain.lookup(d, rough), np.broadcast_to(c, (50, 3)), rtol=1e-14)


def test_split_sum_is_exact_in_a_white_furnace():
    # L ≡ c: P = c for every prefilter, so the split sum gives c·(F0·A + B) = c·∫ f (n·l) dl, the true reflected
    # radiance.  Reference: c·brdfs.albedo (independent rule; accurate to ≈ 1e-8) -> tolerance 5e-8·c.  With the
    # DFG table instead of dfg_terms the only difference is the table's interpolation (pinned above).
    c = np.array([2.0, 1.0, 0.5])
    cube = np.broadcast_to(c, (6, 8, 8, 3)).copy()
    chain = k.build_chain(cube, n_levels=3)
    for theta, rough, f0 in [(0.2, 0.3, 0.04), (1.0, 0.6, 0.9), (1.3, 0.15, 1.0), (0.0, 1.0, 0.5)]:
        n = np.array([0.3, -0.2, 0.9])
        n /= np.linalg.norm(n)
        t1, _ = k.tangent_frames(n)
        v = np.cos(theta) * n + np.sin(theta) * t1
        got = k.shade(chain.lookup, None, n, v, rough, f0)
        alb = brdfs.albedo(brdfs.get_brdf("ggx", roughness=rough, f0=f0), theta, width=min(0.02, rough ** 2 / 4))
        np.testing.assert_allclose(got, c * alb, atol=5e-8 * c.max())
        T = k.build_dfg_table(32)
        A, B = T.lookup(np.cos(theta), rough)
        np.testing.assert_allclose(k.shade(chain.lookup, T, n, v, rough, f0), c * (f0 * A + B), rtol=1e-13)


# ------------------------------------------------------------------------------------------- sampling
def test_hammersley_points_and_ggx_half_vectors():
    # radical inverse base 2: 0, 1/2, 1/4, 3/4, 1/8, 5/8, 3/8, 7/8 (van der Corput)
    u_t, u_p = k.sample_points("hammersley", 8, 0, 2)
    np.testing.assert_array_equal(u_t[0], [0, .5, .25, .75, .125, .625, .375, .875])
    np.testing.assert_array_equal(u_p[1], np.arange(8) / 8)
    # GGX sampling: the cumulative of D cos θh is ξ = tan²θh/(α² + tan²θh); θh(u) must invert it exactly
    alpha = 0.3
    u = np.linspace(0.0, 0.999, 50)
    h = k.ggx_half_vectors(u, 0.25, alpha)
    tan2 = (1 - h[..., 2] ** 2) / h[..., 2] ** 2
    np.testing.assert_allclose(tan2 / (alpha ** 2 + tan2), u, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(h, axis=-1), 1.0, atol=1e-15)
    assert np.all(np.abs(h[1:, 0]) < 1e-15)  # φ = 2π·0.25: in the y-z plane


def test_tangent_frames_are_orthonormal():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(1000, 3))
    n[:3] = [[0, 0, 1], [0, 0, -1], [1e-9, 0, -1]]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t1, t2 = k.tangent_frames(n)
    for a, b in ((t1, t2), (t1, n), (t2, n)):
        assert np.max(np.abs(np.sum(a * b, axis=1))) < 1e-12
    np.testing.assert_allclose(np.cross(t1, t2), n, atol=1e-12)


def test_random_samples_do_not_depend_on_chunking():
    cube = se.env_studio(8)
    a = k.prefilter_importance(cube, 0.5, samples=16, sequence="random", seed=5, out_size=4)
    b = k.prefilter_importance(cube, 0.5, samples=16, sequence="random", seed=5, out_size=4, chunk_elems=16 * 7)
    np.testing.assert_array_equal(a, b)
    c = k.prefilter_importance(cube, 0.5, samples=16, sequence="random", seed=6, out_size=4)
    assert not np.array_equal(a, c)


def test_importance_sampling_noise_falls_as_one_over_sqrt_n():
    # plain Monte Carlo (independent uniform points per texel): the RMS error against the exact prefilter falls as
    # N^-1/2.  Slope of log RMS vs log N over N = 16 … 4096, 4 seeds (measured −0.514 ± 0.022).  Tolerance: 3
    # standard errors of the mean slope (from the spread over seeds) + 0.01 for the bias floor (the bilinear
    # source lookup vs the texel sum and the ratio estimator's O(1/N) bias: < 1.6e-3 relative, measured with
    # Hammersley points at N = 4096, against RMS noise ≥ 3e-2)
    cube = se.env_sky_sun(32, sun_solid_angle=0.02, sun_radiance=30.0)
    exact = k.prefilter_exact(cube, 0.5, out_size=8)
    scale = np.sqrt(np.mean(exact ** 2))
    ns = np.array([16, 64, 256, 1024, 4096])
    slopes = []
    for seed in range(4):
        e = [np.sqrt(np.mean((k.prefilter_importance(cube, 0.5, samples=int(n), sequence="random", seed=seed,
                                                     out_size=8) - exact) ** 2)) / scale for n in ns]
        slopes.append(np.polyfit(np.log(ns), np.log(e), 1)[0])
    se_mean = np.std(slopes, ddof=1) / np.sqrt(len(slopes))
    assert abs(np.mean(slopes) + 0.5) < 3 * se_mean + 0.01
    # Karis's Hammersley points converge faster than N^-1/2 and reach the floor: < 5e-3 at N = 4096
    h = k.prefilter_importance(cube, 0.5, samples=4096, out_size=8)
    assert np.sqrt(np.mean((h - exact) ** 2)) / scale < 5e-3


def test_empty_samples_fall_back_to_the_mirror_value():
    # N = 1 at roughness 1: half the samples have θh > π/4 (l below the lobe's horizon); such texels take the
    # bilinear value at r, never 0/0
    cube = se.env_studio(8)
    out, info = k.prefilter_importance(cube, 1.0, samples=1, sequence="random", return_info=True)
    assert 0 < info["empty"] < 6 * 64
    assert np.all(np.isfinite(out))


# ------------------------------------------------------------------------------------------- chain, shading
def test_chain_levels_and_trilinear_lookup():
    cube = se.env_studio(16)
    chain = k.build_chain(cube)  # 16 -> 5 levels: faces 16, 8, 4, 2, 1
    assert chain.n_levels == 5 and chain.face_sizes == (16, 8, 4, 2, 1)
    assert chain.roughness == (0.0, 0.25, 0.5, 0.75, 1.0)
    np.testing.assert_array_equal(chain.levels[0], cube)  # level 0: the mirror = the source
    # at a level's roughness and its texel centres the lookup is that level's texel, and the level is the exact
    # prefilter (the dense texel sum) within the chain's tolerance EXACT_RTOL (a rigorous bound)
    d = envmap.texel_directions(8).reshape(-1, 3)
    np.testing.assert_allclose(chain.lookup(d, 0.25), chain.levels[1].reshape(-1, 3), rtol=1e-12)
    np.testing.assert_allclose(chain.levels[1], k.prefilter_dense(cube, 0.25, out_size=8), rtol=k.EXACT_RTOL)
    assert max(chain.info["bound_max"]) <= k.EXACT_RTOL
    # between levels: the linear blend of the two bilinear lookups (ℓ = 4·r)
    rng = np.random.default_rng(2)
    q = rng.normal(size=(20, 3))
    got = chain.lookup(q, 0.6)
    lo, hi = sample_bilinear(chain.levels[2], q), sample_bilinear(chain.levels[3], q)
    np.testing.assert_allclose(got, 0.6 * lo + 0.4 * hi, rtol=1e-12)
    assert chain.nbytes == sum(lv.nbytes for lv in chain.levels)
    assert k.level_of_roughness(0.6, 5) == pytest.approx(2.4)
    assert k.roughness_of_level(3, 5) == pytest.approx(0.75)


def test_float32_and_float16_storage_paths():
    # float32: each stored value rounds with relative error ≤ 2⁻²⁴ and the bilinear/linear blends of positive
    # values keep it below a few 2⁻²⁴ -> rtol 1e-6.  float16: 2⁻¹¹ per value -> rtol 2e-3.
    cube = se.env_studio(8)
    c64 = k.build_chain(cube, n_levels=3)
    d = np.random.default_rng(4).normal(size=(40, 3))
    r = np.linspace(0.05, 1.0, 40)
    ref = c64.lookup(d, r)
    for dt, tol in (("float32", 1e-6), ("float16", 2e-3)):
        ch = k.build_chain(cube, n_levels=3, dtype=dt)
        assert all(lv.dtype == np.dtype(dt) for lv in ch.levels)
        assert ch.nbytes == c64.nbytes * np.dtype(dt).itemsize // 8
        got = ch.lookup(d, r)
        assert got.dtype == np.float64
        np.testing.assert_allclose(got, ref, rtol=tol)
    sun = cube.copy()
    sun[4, 3, 3] = 1e5  # a sun texel above the float16 maximum 65504: refused, never stored as inf
    with pytest.raises(IBLError, match="overflows float16"):
        k.build_chain(sun, n_levels=2, dtype="float16")


def test_split_sum_class_interface():
    cube = se.env_studio(8)
    m = k.SplitSum.build(cube, dfg_size=16, n_levels=3)
    assert m.lobe == "ggx" and m.error_bound is None
    assert m.nbytes == m.chain.nbytes + 2 * 16 * 16 * 8
    d = np.random.default_rng(5).normal(size=(4, 5, 3))
    assert m.lookup(d, 0.3).shape == (4, 5, 3)
    n = np.array([0.0, 1.0, 0.0])
    below = m.shade(n, [0.0, -0.5, 1.0], 0.5, 0.04)
    assert np.all(below == 0)
    v = np.array([0.0, 0.8, 0.6])
    r = 2 * 0.8 * n - v
    T = m.dfg
    A, B = T.lookup(0.8, 0.5)
    np.testing.assert_allclose(m.shade(n, v, 0.5, 0.04), m.lookup(r, 0.5) * (0.04 * A + B), rtol=1e-13)
    imp = k.SplitSum.build(cube, prefilter="importance", samples=8, n_levels=2, dfg_size=16)
    assert imp.chain.prefilter == "importance" and imp.chain.info["samples"] == 8


# ------------------------------------------------------------------------------------------- bad input
def _one_line(exc):
    msg = str(exc.value)
    assert msg and "\n" not in msg
    return msg


@pytest.mark.parametrize("rough", [0.0, -0.1, 1.5, np.nan, np.inf])
def test_bad_roughness(rough):
    cube = se.env_constant(4)
    for call in (lambda: k.prefilter_exact(cube, rough), lambda: k.prefilter_importance(cube, rough, samples=4),
                 lambda: k.dfg_terms(0.5, rough), lambda: k.build_dfg_table(4).lookup(0.5, rough)):
        with pytest.raises(IBLError) as e:
            call()
        assert "roughness" in _one_line(e)


@pytest.mark.parametrize("f0", [-0.1, 1.1, np.nan])
def test_bad_f0(f0):
    with pytest.raises(IBLError) as e:
        k.split_sum(np.ones(3), 0.5, 0.5, f0)
    assert "F0" in _one_line(e)


@pytest.mark.parametrize("n", [0, -3, 2.5, True, "8"])
def test_bad_sample_count(n):
    with pytest.raises(IBLError) as e:
        k.prefilter_importance(se.env_constant(4), 0.5, samples=n)
    assert "N >= 1" in _one_line(e)


@pytest.mark.parametrize("bad", [np.nan, -1.0, np.inf])
def test_bad_radiance(bad):
    cube = se.env_constant(4)
    cube[2, 1, 1, 0] = bad
    for call in (lambda: k.prefilter_exact(cube, 0.5), lambda: k.prefilter_importance(cube, 0.5, samples=4),
                 lambda: k.build_chain(cube)):
        with pytest.raises(IBLError) as e:
            call()
        _one_line(e)


def test_other_bad_arguments():
    cube = se.env_constant(4)
    for call, word in ((lambda: k.dfg_terms(0.0, 0.5), "n·v"), (lambda: k.dfg_terms(1.2, 0.5), "n·v"),
                       (lambda: k.prefilter_importance(cube, 0.5, sequence="sobol"), "sequence"),
                       (lambda: k.build_chain(cube, n_levels=1), "n_levels"),
                       (lambda: k.build_chain(cube, prefilter="box"), "prefilter"),
                       (lambda: k.build_chain(cube, dtype="int8"), "dtype"),
                       (lambda: k.prefilter_exact(cube, 0.5, out_size=0), "out_size"),
                       (lambda: k.prefilter_exact(cube, 0.5, dirs=[[0.0, 0.0, 0.0]]), "zero-length"),
                       (lambda: k.prefilter_exact(np.ones((6, 4, 5, 3)), 0.5), "shape"),
                       (lambda: k.build_dfg_table(1), "size")):
        with pytest.raises(IBLError) as e:
            call()
        assert word in _one_line(e)
