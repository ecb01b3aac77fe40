"""Tests of ibl_ref.occlusion.shadow_filters: PCF, VSM, ESM, EVSM and MSM estimates of the per-region visibility.

Small scenes and 64²–128² maps.  Numbers measured when the tests were written (float32, 128², crevice scene, 800
points × 6 lights, solid angle 1e-8 sr → σ ≈ 0): fraction of (point, light) pairs with |VIS − exact| < 0.5 —

======  ===========  ===================
filter  all pairs    front-facing pairs
======  ===========  ===================
pcf     0.985        0.998
vsm     0.968        0.999
esm     0.966        0.999
evsm    0.968        0.999
msm     0.975        0.999
======  ===========  ===================

(at 64²: all pairs 0.934–0.980, front-facing 0.995–0.998; PCF with a constant bias only, ``receiver_plane=False``:
0.842 and 0.714 at 128²).  Light bleeding under two stacked occluders (σ = 4 texels, 41 receivers where the exact
answer is 0): mean visibility VSM 0.098, MSM 0.013 (ESM 0.003, EVSM 0.006, PCF 0.000).
"""

from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from ibl_ref.errors import IBLError
from ibl_ref.occlusion import shadow_filters as sf
from ibl_ref.occlusion.shadow_filters import (
    SHADOW_FILTERS,
    hamburger_4msm,
    region_visibility_shadow_maps,
)
from ibl_ref.rendering import vsm
from ibl_ref.rendering.camera import light_camera
from ibl_ref.rendering.raster import prepare_scene
from ibl_ref.rendering.render import light_visibilities
from ibl_ref.rendering.scenes import crevice_scene

UP = np.array([0.0, 1.0, 0.0])


def _quad(x0, x1, z0, z1, y):
    """Horizontal quad at height y, normal +y."""
    return trimesh.Trimesh([[x0, y, z0], [x1, y, z0], [x1, y, z1], [x0, y, z1]], [[0, 2, 1], [0, 3, 2]], process=False)


def _lights(directions, solid_angle=0.0):
    d = np.atleast_2d(np.asarray(directions, dtype=np.float64))
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return SimpleNamespace(directions=d, solid_angle=np.full(len(d), float(solid_angle)))


def _on_ground(xs, zs=0.0):
    xs = np.asarray(xs, dtype=np.float64)
    return np.c_[xs, np.zeros_like(xs), np.broadcast_to(zs, xs.shape)], np.tile(UP, (len(xs), 1))


# ------------------------------------------------------------------------------------------------
# one opaque square over a ground plane, light straight above
# ------------------------------------------------------------------------------------------------
SQUARE = [_quad(-2, 2, -2, 2, 0.0), _quad(-1, 1, -1, 1, 0.5)]


def test_square_occluder_umbra_and_lit():
    sc = prepare_scene(SQUARE)
    lights = _lights(UP, 1e-6)  # σ ≈ 0.01 texel: hard shadows
    pts, up = _on_ground([0.0, 0.3, -0.5, 1.6, -1.7, 1.8], [0.0, -0.4, 0.5, 1.6, 0.2, -1.8])
    umbra, lit = slice(0, 3), slice(3, 6)
    # normalised depths of the receivers and of the occluder above them (one camera for all: light_camera is fixed
    # by the scene's bounding sphere); Δ = t − z is the receiver's distance behind the occluder, less the bias
    cam = light_camera(UP, *sc.bounds(), resolution=64)
    bias = 1e-3
    t = cam.project(pts)[2] / cam.far - bias
    z = cam.project(pts + 0.5 * UP)[2] / cam.far
    delta = t[umbra] - z[umbra]
    assert np.all(delta > 0.08)
    tol = {
        "pcf": np.zeros(3),  # every comparison fails
        # Chebyshev with the variance floor σ²_min = 1e-6 of a single depth: σ²/(σ² + Δ²) ≈ 1.4e-4
        "vsm": 1e-6 / (1e-6 + delta**2),
        # ESM's leak exp(−c·Δ) (c = 80): 1.5e-3 — exact up to float32 rounding (see the ESM test)
        "esm": np.exp(-80 * delta),
        # the smaller of the two warps' bounds; the negative warp's (c⁻ = 5, floor σ²_min·(2c⁻e⁻)²) is
        # σ²_min·(2c⁻)² / (exp(2c⁻Δ) − 1)² ≈ 1.1e-4
        "evsm": 1e-6 * (2 * 5.0) ** 2 / np.expm1(2 * 5.0 * delta) ** 2,
        # a flat umbra holds the moments of one depth z: the pipeline returns exactly 4MSM of that delta
        # (α = 3e-5 leaks ≈ 1e-3 at Δ ≈ 0.08, below α/Δ² = 4.4e-3)
        "msm": hamburger_4msm(z[umbra, None] ** np.arange(1, 5), t[umbra], 3e-5),
    }
    for name in SHADOW_FILTERS:
        v = region_visibility_shadow_maps(sc, pts, up, lights, filter=name, resolution=64)[:, 0]
        assert np.all(v[umbra] <= 1.01 * tol[name] + 1e-7), (name, v[umbra], tol[name])
        if name == "pcf":
            np.testing.assert_array_equal(v[lit], 1.0)
        else:  # t ≤ mean in every bound (MSM: t ≤ z₂, up to its bias's 1.5e-5)
            assert np.all(v[lit] >= 1 - 1e-4), (name, v[lit])
    # ESM and MSM at the umbra are not just bounded: they equal their closed forms
    np.testing.assert_allclose(region_visibility_shadow_maps(sc, pts[umbra], up[umbra], lights, filter="esm",
                                                             resolution=64)[:, 0], tol["esm"], rtol=1e-4)
    np.testing.assert_allclose(region_visibility_shadow_maps(sc, pts[umbra], up[umbra], lights, filter="msm",
                                                             resolution=64)[:, 0], tol["msm"], rtol=0.02)


def test_esm_planar_receiver_behind_planar_occluder_is_exact():
    # Annen et al. 2008: with one occluder depth z in the whole (blurred) kernel the filtered value is
    # exp(c·z) and the visibility exactly exp(−c·(t − z)); it decays to 0 as c·(t − z) grows.
    sc = prepare_scene(SQUARE)
    lights = _lights(UP)
    pts, up = _on_ground([0.0, 0.2, -0.3], [0.1, -0.2, 0.0])  # ≥ 0.7 from the occluder's edge: > 3σ = 3 texels
    cam = light_camera(UP, *sc.bounds(), resolution=64)
    gap = (cam.project(pts)[2] - cam.project(pts + 0.5 * UP)[2]) / cam.far - 1e-3
    prev = np.ones(len(pts))
    for c in (5.0, 20.0, 80.0):
        v = region_visibility_shadow_maps(sc, pts, up, lights, filter="esm", resolution=64, sigma_texels=1.0, c=c)
        np.testing.assert_allclose(v[:, 0], np.exp(-c * gap), rtol=1e-4)
        assert np.all(v[:, 0] < prev)
        prev = v[:, 0]
    assert prev.max() < 2e-3


# ------------------------------------------------------------------------------------------------
# against exact ray-cast visibility of the same directional lights
# ------------------------------------------------------------------------------------------------
CREVICE_DIRS = np.array([[0.3, 1, 0.2], [-0.5, 0.8, 0.4], [0.1, 0.6, -0.8], [0.9, 0.4, 0.1], [0.07, 1, 0.04],
                         [-0.2, 0.3, -0.9]])


@pytest.fixture(scope="module")
def crevice_case():
    sc = prepare_scene(crevice_scene())
    pts, fid = trimesh.sample.sample_surface(sc.to_trimesh(), 800, seed=0)
    fn = sc.face_normals[fid]
    lights = _lights(CREVICE_DIRS, 1e-8)  # σ ≈ 1e-4 texel: the hard-shadow limit of every filter
    # other geometry only (horizon=False), like a shadow map
    exact = light_visibilities(sc, pts, fn, lights, method="raycast", horizon=False).T
    return sc, pts, fn, lights, exact


def test_agreement_with_exact_visibility(crevice_case):
    # Measured (module docstring): all pairs ≥ 0.966, front-facing (n·ω > 0.1) ≥ 0.998; the thresholds leave
    # 1.6 and 0.8 points of room.  The misses inspected are grazing lights (|n·ω| < 0.1) on the slab's sides, where
    # the receiver lies within a texel (0.03 here) of the silhouette and the bilinear footprint reaches past it, and
    # points within a texel of the pit's concave corners, where it mixes the two faces' depths.
    sc, pts, fn, lights, exact = crevice_case
    front = fn @ lights.directions.T > 0.1
    for name in SHADOW_FILTERS:
        v = region_visibility_shadow_maps(sc, pts, fn, lights, filter=name, resolution=128)
        assert v.shape == exact.shape and v.min() >= 0 and v.max() <= 1
        ok = np.abs(v - exact) < 0.5
        assert ok.mean() > 0.95, (name, ok.mean())
        assert ok[front].mean() > 0.99, (name, ok[front].mean())


def test_pcf_receiver_plane_bias_removes_self_shadowing(crevice_case):
    # with a constant bias only, a bilinear PCF tap on a receiver tilted to the light compares neighbouring texels
    # of its own plane, up to tan θ / 128 nearer (≫ the bias): the crevice's tilted receivers shadow themselves
    sc, pts, fn, lights, exact = crevice_case
    plane = region_visibility_shadow_maps(sc, pts, fn, lights, filter="pcf", resolution=128)
    const = region_visibility_shadow_maps(sc, pts, fn, lights, filter="pcf", resolution=128, receiver_plane=False)
    assert (np.abs(plane - exact) < 0.5).mean() > (np.abs(const - exact) < 0.5).mean() + 0.1
    # a tilted plane under a wide kernel: lit everywhere with the receiver plane
    tilt = trimesh.Trimesh([[-2, -1, -2], [2, 1, -2], [2, 1, 2], [-2, -1, 2]], [[0, 2, 1], [0, 3, 2]])
    n = np.array([[-1.0, 2.0, 0.0]]) / np.sqrt(5)
    p = np.array([[0.0, 0.0, 0.0], [0.5, 0.25, 0.3]])
    v = region_visibility_shadow_maps(tilt, p, np.repeat(n, 2, 0), _lights(UP), filter="pcf", resolution=64,
                                      sigma_texels=3.0)
    np.testing.assert_array_equal(v, 1.0)


def test_slope_bias_removes_self_shadowing_of_tilted_receivers():
    # A lit plane of slope 1 under a wide kernel (σ = 3 texels): its own depths spread over the kernel.  VSM (t ≤
    # mean) and ESM (convex warp) stay at 1; EVSM's concave negative warp and MSM's four moments see the spread as
    # occluders (measured minima 0.96 and 0.86) unless the receiver depth moves k·s in front, s the spread's
    # standard deviation (module docstring); k = 1, the default, gives 1.
    tilt = trimesh.Trimesh([[-2, -2, -2], [2, 2, -2], [2, 2, 2], [-2, -2, 2]], [[0, 2, 1], [0, 3, 2]])
    xs = np.linspace(-1, 1, 9)
    p, n = np.c_[xs, xs, 0 * xs], np.tile([-1.0, 1.0, 0.0], (9, 1)) / np.sqrt(2)
    kw = dict(resolution=64, sigma_texels=3.0)
    for name in SHADOW_FILTERS:
        v = region_visibility_shadow_maps(tilt, p, n, _lights(UP), filter=name, **kw)
        assert v.min() > 0.999, (name, v.min())
    for name, below in (("evsm", 0.98), ("msm", 0.9)):
        v = region_visibility_shadow_maps(tilt, p, n, _lights(UP), filter=name, slope_bias=0.0, **kw)
        assert v.min() < below, (name, v.min())


def test_vsm_is_the_paper_pipeline(crevice_case):
    # "vsm" delegates to ibl_ref.rendering.vsm: the same numbers as the renderer's own VSM route
    sc, pts, fn, _, _ = crevice_case
    lights = _lights(CREVICE_DIRS[:3], 0.05)
    ours = region_visibility_shadow_maps(sc, pts, fn, lights, filter="vsm", resolution=64, dtype="float16")
    theirs = light_visibilities(sc, pts, fn, lights, method="vsm", vsm_resolution=64, vsm_dtype="float16").T
    np.testing.assert_array_equal(ours, theirs)


# ------------------------------------------------------------------------------------------------
# light bleeding: two stacked occluders
# ------------------------------------------------------------------------------------------------
def test_msm_bleeds_less_than_vsm_under_two_occluders():
    # Ground (y = 0) under occluder B (y = 0.4, |x|, |z| ≤ 1) and, over half of it, occluder A (y = 1, x ≤ 0).
    # Every receiver with |x| ≤ 0.4 is in B's umbra (exact VIS = 0), but near x = 0 the kernel (σ = 4 texels of
    # 0.047) holds both occluder depths.  VSM's Chebyshev bound then leaks ("light bleeding", Lauritzen, GPU Gems 3, ch. 8);
    # four moments of the two-depth mixture pin it down, and 4MSM returns ≈ 0 (Peters & Klein 2015,
    # Fig. 1: MSM's reconstruction is sharper than VSM's and bleeds less).  Measured: VSM 0.098 mean, 0.19 max;
    # MSM 0.013 mean, 0.015 max.
    scene = [_quad(-2, 2, -2, 2, 0.0), _quad(-1, 1, -1, 1, 0.4), _quad(-1.5, 0.0, -1.5, 1.5, 1.0)]
    pts, up = _on_ground(np.linspace(-0.4, 0.4, 41))
    err = {}
    for name in SHADOW_FILTERS:
        v = region_visibility_shadow_maps(scene, pts, up, _lights(UP), filter=name, resolution=128, sigma_texels=4.0)
        err[name] = v[:, 0].mean()
    assert err["vsm"] > 0.03  # the configuration does make VSM bleed
    assert err["msm"] <= err["vsm"], err
    assert err["msm"] < 0.5 * err["vsm"], err


# ------------------------------------------------------------------------------------------------
# MSM reconstruction on known distributions
# ------------------------------------------------------------------------------------------------
def _moments(z, w):
    """(E z, E z², E z³, E z⁴) of Σ w_k δ(z_k), along the last axis of z and w."""
    return np.stack([(w * z**k).sum(axis=-1) for k in range(1, 5)], axis=-1)


@pytest.mark.parametrize("alpha", [0.0, 3e-5])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_msm_single_depth(alpha, dtype):
    # one depth z0: lit in front (t ≤ z₂), shadowed behind; the bias leaks at most ~α/ε² behind it (measured: 3e-3
    # at ε = 0.05 with α = 3e-5, 5e-6 with α = 0 in float32) and costs ≤ α in front
    z0 = np.linspace(0.05, 0.95, 91)
    b = (z0[:, None] ** np.arange(1, 5)).astype(dtype)
    eps = 0.05
    front = hamburger_4msm(b, (z0 - eps).astype(dtype), alpha)
    back = hamburger_4msm(b, (z0 + eps).astype(dtype), alpha)
    assert front.dtype == dtype
    assert np.all(front >= 1 - alpha - 1e-6)
    assert np.all(back <= alpha / eps**2 + 1e-5)


@pytest.mark.parametrize("t", [0.35, 0.5, 0.65])
def test_msm_two_depths(t):
    # w at 0.3 and 1 − w at 0.7: a receiver between them sees 1 − w.  4MSM is the sharp lower bound on the shadow
    # intensity, i.e. an upper bound on the visible fraction: 1 − w ≤ v, and the bias adds at most α/ε² (ε the
    # distance from t to the nearer depth; measured 4.1e-3 at t = 0.35)
    w = np.linspace(0.05, 0.95, 19)
    b = _moments(np.array([0.3, 0.7]), np.c_[w, 1 - w])
    for alpha in (0.0, 3e-5):
        v = hamburger_4msm(b, np.full(len(w), t), alpha)
        eps = min(t - 0.3, 0.7 - t)
        assert np.all(v >= 1 - w - 1e-9) and np.all(v >= 0)
        assert np.all(v <= 1 - w + alpha / eps**2 + 1e-9)


def _random_mixtures(n, seed):
    rng = np.random.default_rng(seed)
    k = rng.integers(1, 5, n)
    z = rng.uniform(0.05, 0.95, (n, 4))
    w = rng.dirichlet(np.ones(4), n) * (np.arange(4) < k[:, None])
    w /= w.sum(axis=1, keepdims=True)
    t = rng.uniform(0.05, 0.95, n)
    gap = np.where(w > 0, np.abs(z - t[:, None]), np.inf).min(axis=1)
    return z, w, t, (w * (z >= t[:, None])).sum(axis=1), gap


def test_msm_bounds_the_visible_fraction_and_is_sharper_than_chebyshev():
    # Random mixtures of 1–4 depths: 4MSM's visibility lies between the true visible fraction P(z ≥ t) and VSM's
    # Chebyshev bound of the same distribution (two moments constrain less than four)
    z, w, t, true, _ = _random_mixtures(4000, 3)
    b = _moments(z, w)
    v = hamburger_4msm(b, t, 0.0)
    cheb = vsm.chebyshev_upper_bound(t, b[:, 0], b[:, 1], 1e-12)
    assert np.all(v >= true - 1e-7)
    assert np.all(v <= cheb + 1e-7)
    assert np.mean(v < cheb - 0.05) > 0.3  # and it is strictly sharper in a good share of cases


def test_msm_float16_default_bias():
    # raw moments rounded to half floats: the float16 default α = 1e-2 keeps false shadows (visibility > 0.05 below
    # the true fraction, receivers ≥ 0.02 from every depth) rare; measured 0.5 % at α = 3e-5, ~0.01 % at 1e-2
    z, w, t, true, gap = _random_mixtures(4000, 5)
    b16 = _moments(z, w).astype(np.float16).astype(np.float32)
    far = gap > 0.02
    alpha = sf.MomentFilter().params("float16", {})["moment_bias"]
    false_shadow = lambda a: np.mean((true - hamburger_4msm(b16, t.astype(np.float32), a))[far] > 0.05)
    assert false_shadow(alpha) <= 0.001
    assert false_shadow(3e-5) > 3 * max(false_shadow(alpha), 1 / far.sum())


# ------------------------------------------------------------------------------------------------
# conventions, determinism, bad input
# ------------------------------------------------------------------------------------------------
def test_horizon_and_shapes():
    sc = prepare_scene(SQUARE)
    pts, up = _on_ground([1.6, 1.7])
    lights = _lights([[0.0, 1, 0], [0.2, -1, 0]], 0.01)
    for name in SHADOW_FILTERS:
        v = region_visibility_shadow_maps(sc, pts, up, lights, filter=name, resolution=32)
        h = region_visibility_shadow_maps(sc, pts, up, lights, filter=name, resolution=32, horizon=True)
        assert v.shape == (2, 2)
        np.testing.assert_array_equal(h, v * [1.0, 0.0])
    assert region_visibility_shadow_maps(sc, pts[:0], up[:0], lights).shape == (0, 2)


@pytest.mark.parametrize("dtype", ["float16", "float32", "float64"])
def test_deterministic(dtype):
    sc = prepare_scene(SQUARE)
    pts, up = _on_ground(np.linspace(-1.5, 1.5, 15), 0.3)
    lights = _lights([[0.3, 1, 0.1], [-0.2, 1, 0.4]], 0.05)
    for name in SHADOW_FILTERS:
        a = region_visibility_shadow_maps(sc, pts, up, lights, filter=name, resolution=32, dtype=dtype)
        b = region_visibility_shadow_maps(sc, pts, up, lights, filter=name, resolution=32, dtype=dtype)
        np.testing.assert_array_equal(a, b)
        assert np.all(np.isfinite(a)) and a.min() >= 0 and a.max() <= 1


def test_timings():
    timings = {}
    pts, up = _on_ground([0.0])
    region_visibility_shadow_maps(SQUARE, pts, up, _lights(UP), filter="evsm", resolution=16, timings=timings)
    assert set(timings) == {"shadow_maps", "blur", "visibility"}


@pytest.mark.parametrize("kwargs, match", [
    (dict(filter="gauss"), "unknown shadow filter 'gauss'; choose one of pcf, vsm, esm, evsm, msm"),
    (dict(filter=None), "unknown shadow filter"),
    (dict(resolution=1), "resolution must be an integer >= 2"),
    (dict(resolution=2.5), "resolution must be an integer >= 2"),
    (dict(dtype="float8"), "dtype must be one of"),
    (dict(horizon="yes"), "horizon must be"),
    (dict(filter="esm", dtype="float16", c=80), "overflows float16"),
    (dict(filter="evsm", c_pos=50), "overflows float32"),
    (dict(filter="esm", c=-1), "esm: c"),
    (dict(filter="msm", moment_bias=0.7), "moment_bias"),
    (dict(filter="evsm", slope_bias=-1), "evsm: slope_bias"),
    (dict(filter="vsm", slope_bias=1), "unknown parameter"),
    (dict(filter="pcf", taps=2.0), "taps"),
    (dict(filter="vsm", min_variance=0.0), "min_variance"),
    (dict(filter="evsm", bleed_reduction=1.0), "light-bleeding"),
    (dict(filter="pcf", c=80), "unknown parameter"),
    (dict(sigma_texels=-1.0), "sigma_texels"),
    (dict(depth_bias=float("nan")), "depth_bias"),
])
def test_bad_parameters(kwargs, match):
    pts, up = _on_ground([0.0])
    with pytest.raises(IBLError, match=match):
        region_visibility_shadow_maps(SQUARE, pts, up, _lights(UP), **kwargs)


def test_bad_arrays():
    pts, up = _on_ground([0.0, 1.0])
    lights = _lights(UP)
    cases = [
        (dict(points=[[0.0, np.nan, 0.0]], face_normals=up[:1]), "points: contains NaN"),
        (dict(points=pts[:, :2]), r"points: expected shape \(P, 3\)"),
        (dict(face_normals=up[:1]), "face_normals: 1 rows for 2 points"),
        (dict(face_normals=None, horizon=True), "horizon=True needs face_normals"),
        (dict(face_normals=None, filter="pcf"), "receiver_plane=True needs face_normals"),
        (dict(face_normals=None, filter="msm"), "slope_bias > 0 needs face_normals"),
        (dict(lights=SimpleNamespace(directions=np.array([UP, UP]), solid_angle=np.array([0.1]))),
         "2 directions but 1 solid angles"),
        (dict(lights=SimpleNamespace(directions=np.array([UP]), solid_angle=np.array([13.0]))), "solid angle"),
        (dict(lights=SimpleNamespace(directions=np.zeros((1, 3)), solid_angle=np.array([0.1]))), "zero vector"),
        (dict(lights=UP), "lights: expected .directions"),
    ]
    for kwargs, match in cases:
        args = dict(points=pts, face_normals=up, lights=lights) | kwargs
        with pytest.raises(IBLError, match=match):
            region_visibility_shadow_maps(SQUARE, args.pop("points"), args.pop("face_normals"), args.pop("lights"),
                                          **args)
    # without normals, the filters that do not need them still run
    for name, kw in (("vsm", {}), ("esm", {}), ("msm", {"slope_bias": 0.0}), ("pcf", {"receiver_plane": False})):
        v = region_visibility_shadow_maps(SQUARE, pts, None, lights, filter=name, resolution=16, **kw)
        assert v.shape == (2, 1)
