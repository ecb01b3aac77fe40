"""Tests of the Mitsuba 3 renderer (ibl_ref.rendering.mitsuba_render): Mitsuba's own envmap emitter and integrator are the
independent route; the lab's cube lookup and G-buffer are what they are compared with.

Mitsuba is in the ``test`` extra; the tests that render need its llvm_ad_rgb variant (libLLVM >= 17, the
``mitsuba_llvm`` fixture of ``conftest.py``): skipped with the reason where it is missing, a failure in CI
(``IBL_REF_REQUIRE_MITSUBA=1`` in ``.ci/run``).
"""

import numpy as np
import pytest
import trimesh

from ibl_ref.rendering import mitsuba_render as mr
from ibl_ref.rendering.camera import PerspectiveCamera
from ibl_ref.errors import IBLError
from ibl_ref.environment.sampling import sample_nearest


def _random_dirs(n, seed=0):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _patch_env(n=8, face=4, row=3, col=5, value=50.0, background=0.5):
    cube = np.full((6, n, n, 3), background)
    cube[face, row, col] = value * np.array([1.0, 0.5, 0.25])
    return cube


def test_find_libllvm_rejects_old_versions(monkeypatch, tmp_path):
    old = tmp_path / "libLLVM-15.so"
    old.write_bytes(b"")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(old))
    assert mr.find_libllvm() is None  # 15 aborts Dr.Jit at the first kernel compile: never selected
    new = tmp_path / "libLLVM-19.so"
    new.write_bytes(b"")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(new))
    assert mr.find_libllvm() == str(new)


def test_envmap_directions_follow_mitsuba_addressing():
    # u = (i+1/2)/W, v = j/(H-1): row 0 is exactly +Y, the last row exactly -Y; u = 1/4 is +X, u = 1/2 is +Z
    d = mr.envmap_directions(9)
    np.testing.assert_allclose(d[0, :, 1], 1.0, atol=1e-12)
    np.testing.assert_allclose(d[-1, :, 1], -1.0, atol=1e-12)
    mid = d[4]  # equator (v = 1/2)
    W = mid.shape[0]
    u = (np.arange(W) + 0.5) / W
    np.testing.assert_allclose(mid[:, 0], np.sin(2 * np.pi * u), atol=1e-12)
    np.testing.assert_allclose(mid[:, 2], -np.cos(2 * np.pi * u), atol=1e-12)


@pytest.mark.usefixtures("mitsuba_llvm")
def test_mitsuba_envmap_reproduces_cube_lookup():
    # Mitsuba's own emitter.eval vs the lab's nearest-texel lookup at random directions
    rng = np.random.default_rng(3)
    cube = rng.uniform(0.1, 3.0, size=(6, 8, 8, 3))
    H = 512
    d = _random_dirs(20000, 1)
    got = mr.envmap_radiance(cube, d, height=H, energy="none")
    want = sample_nearest(cube, d)
    same = np.all(np.abs(got - want) <= 1e-6 * want, axis=1)  # float32 bitmap: bit-identical texel values
    # bilinear interpolation differs only within one lat-long pixel of a texel border: a band of relative width
    # ≈ 2·(π/H)/(π/2/8) ≈ 6 % of a texel on each axis → ≥ 80 % identical (measured 90 % at H = 512)
    assert same.mean() > 0.8
    # every other direction gets a value between the cube values found within two lat-long pixels of it
    # (a test independent of the addressing formula: it only uses the cube lookup and angles)
    bad = d[~same]
    r = 2 * np.pi / (H - 1)
    a = np.cross(bad, [0.3, 0.9, 0.1])
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(bad, a)
    vals = [sample_nearest(cube, bad)]
    for t in np.linspace(0, 2 * np.pi, 24, endpoint=False):
        dd = bad + r * (np.cos(t) * a + np.sin(t) * b)
        vals.append(sample_nearest(cube, dd / np.linalg.norm(dd, axis=1, keepdims=True)))
    vals = np.stack(vals)
    lo, hi = vals.min(axis=0), vals.max(axis=0)
    g = got[~same]
    assert np.all(g >= lo * (1 - 1e-5)) and np.all(g <= hi * (1 + 1e-5))


@pytest.mark.usefixtures("mitsuba_llvm")
def test_envmap_holds_every_texels_energy_in_mitsubas_own_sampling():
    # Mitsuba's importance-sampled estimate of ∫L dω (the mean weight of emitter.sample_direction from one point,
    # 4M samples; with luminance-proportional sampling the weights are nearly constant, so the MC error is ~1e-5)
    # against the cube's exact Σ L Ω: a probe-like 1.5° sun of 3e4 alone, where plain nearest-texel pixels lose
    # 2.2 % to the pixel staircase at the texel borders and the default per-texel energy scaling must not
    import drjit as dr

    from ibl_ref.environment.envmap import cube_solid_angles
    from ibl_ref.environment.probe_files import probe_cube

    mr.select_variant("auto")
    import mitsuba as mi

    sun = np.maximum(probe_cube(32) - probe_cube(32, sun=0.0), 0.0)
    exact = (sun * cube_solid_angles(32)[..., None]).sum(axis=(0, 1, 2))
    u = mi.Point2f(*np.random.default_rng(1).random((2, 1 << 22)).astype(np.float32))
    got = {}
    for energy in ("none", "texel"):
        bm, info = mr.mitsuba_envmap(sun, 1024, energy=energy, return_info=True)
        assert info["texels_without_pixel"] == 0
        _, w = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(bm)}).sample_direction(
            dr.zeros(mi.Interaction3f), u)
        got[energy] = np.array(w, dtype=np.float64).reshape(3, -1).T.mean(axis=0) / exact - 1
    assert np.all(np.abs(got["none"]) > 0.01)  # the defect this guards against is visible at this size
    assert np.all(np.abs(got["texel"]) < 2e-4)
    # the scaling changes radiance only by the staircase ratio of each texel (a few %, not a redistribution)
    a, b = mr.mitsuba_envmap(sun, 1024, energy="none"), mr.mitsuba_envmap(sun, 1024, energy="texel")
    lit = a[..., 0] > 0
    assert np.all(np.abs(b[lit][:, 0] / a[lit][:, 0] - 1) < 0.1)


@pytest.mark.usefixtures("mitsuba_llvm")
def test_bright_patch_energy_and_direction():
    # a single bright texel: Mitsuba's emitter integrated over the sphere (equal-area grid, 2M directions) holds
    # the cube's ∫L dω of the patch, and the patch's energy centroid is the texel's
    from ibl_ref.environment.envmap import cube_solid_angles, texel_directions

    cube = _patch_env(n=8, background=0.0)
    nt, nph = 1000, 2000
    cth = 1 - 2 * (np.arange(nt) + 0.5) / nt
    ph = 2 * np.pi * (np.arange(nph) + 0.5) / nph
    sth = np.sqrt(1 - cth ** 2)
    d = np.stack(np.broadcast_arrays(sth[:, None] * np.cos(ph), cth[:, None], sth[:, None] * np.sin(ph)), -1)
    d = d.reshape(-1, 3)
    L = mr.envmap_radiance(cube, d, height=1024)
    dw = 4 * np.pi / len(d)
    e_mi = L.sum(axis=0) * dw
    om = cube_solid_angles(8)[4, 3, 5]
    e_cube = cube[4, 3, 5] * om
    # the grid's own quadrature error on a texel-sized patch (~0.05 rad across, 2M cells) is < 1 %
    np.testing.assert_allclose(e_mi, e_cube, rtol=0.01)
    c = (L[:, 0:1] * d).sum(axis=0)
    c /= np.linalg.norm(c)
    assert np.degrees(np.arccos(np.clip(c @ texel_directions(8)[4, 3, 5], -1, 1))) < 0.5


@pytest.mark.usefixtures("mitsuba_llvm")
def test_mirror_sphere_shows_the_cube():
    # Mitsuba renders a perfect mirror (its own conductor BSDF) through the lab's pixel centres: every pixel shows
    # L(r) of the lab's G-buffer reflection vector, except where r lies within a lat-long pixel of a texel border
    from ibl_ref.rendering.raster import rasterize

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    cam = PerspectiveCamera(eye=[0.4, 0.6, 4.0], target=[0, 0, 0], up=[0, 1, 0], fov_y_deg=35, width=40, height=40)
    cube = _patch_env(n=8, face=4, row=3, col=4, value=50.0)
    res = mr.render_mitsuba([(sphere, 0)], cam, cube, materials={0: {"type": "conductor", "material": "none"}},
                            spp=2, envmap_height=1024, envmap_energy="none")
    gb = rasterize(sphere, cam)
    assert (res.mask == gb.mask).mean() > 0.99  # same rays, same triangles: coverage agrees up to float32 edges
    m = res.mask & gb.mask
    r = gb.reflect[m]
    want = sample_nearest(cube, r)
    got = res.image[m]
    same = np.all(np.abs(got - want) <= 1e-4 * want, axis=1)
    # "clear" pixels: the cube's nearest texel is the same for every direction 2 lat-long pixel heights
    # (2π/1024 rad, twice Mitsuba's bilinear footprint at envmap_height 1024) around r; there Mitsuba's value must
    # be the texel's, at every pixel (measured: all 812 covered pixels are clear and agree)
    delta = 2 * np.pi / 1024
    a = np.cross(r, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(r, a)
    clear = np.ones(len(r), bool)
    for t in np.arange(8) * np.pi / 4:
        q = np.cos(delta) * r + np.sin(delta) * (np.cos(t) * a + np.sin(t) * b)
        clear &= np.all(sample_nearest(cube, q) == want, axis=1)
    assert clear.mean() > 0.9 and np.all(same[clear])
    # the bright patch is seen at the same pixels (overlap of the > half-peak sets)
    pa, pb = got[:, 0] > 25, want[:, 0] > 25
    assert pb.sum() >= 3
    assert (pa & pb).sum() / (pa | pb).sum() > 0.7


@pytest.mark.usefixtures("mitsuba_llvm")
def test_diffuse_plane_under_constant_sky_is_albedo():
    # closed form: an unoccluded one-sided Lambert plane under L ≡ 1 reflects exactly kd (1/π ∫_{Ω+} cos = 1)
    plane = trimesh.Trimesh([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], [[0, 2, 1], [0, 3, 2]], process=False)
    cube = np.ones((6, 8, 8, 3))
    cam = PerspectiveCamera(eye=[0, 2, 0.5], target=[0, 0, 0], up=[0, 1, 0], fov_y_deg=30, width=12, height=12)
    res = mr.render_mitsuba([(plane, 0)], cam, cube, kd=0.7, ks=0.0, spp=64, envmap_height=256)
    v = res.image[res.mask]
    assert res.mask.sum() > 50
    # MIS of emitter and cosine sampling is not zero-variance: the mean over pixels is within 5σ of its noise
    assert abs(v.mean() - 0.7) < 5 * res.info["noise_rmse"] / np.sqrt(v.size) + 1e-5


@pytest.mark.usefixtures("mitsuba_llvm")
def test_phong_lobe_is_normalised():
    # closed form: a Phong lobe (s = 10) around r of a plane under L ≡ 1 everywhere integrates to
    # (s+1)/(2π)∫_{Ω+} cos^s α dω ≤ 1; for a viewer at the zenith, r = n and the whole lobe is above the plane: 1
    plane = trimesh.Trimesh([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], [[0, 2, 1], [0, 3, 2]], process=False)
    cube = np.ones((6, 8, 8, 3))
    cam = PerspectiveCamera(eye=[0, 30, 1e-3], target=[0, 0, 0], up=[0, 0, -1], fov_y_deg=2, width=6, height=6)
    res = mr.render_mitsuba([(plane, 0)], cam, cube, kd=0.0, ks=1.0, g=0.9, spp=256, envmap_height=256)
    v = res.image[res.mask]
    assert res.mask.all()
    np.testing.assert_allclose(v.mean(), 1.0, atol=5 * res.info["noise_rmse"] / np.sqrt(v.size) + 1e-3)


def test_bad_arguments():  # runs without Mitsuba: argument checks come before the variant is selected
    plane = trimesh.Trimesh([[-1, 0, -1], [1, 0, -1], [1, 0, 1]], [[0, 2, 1]], process=False)
    cam = PerspectiveCamera(eye=[0, 2, 0.5], target=[0, 0, 0], up=[0, 1, 0], fov_y_deg=30, width=4, height=4)
    cube = np.ones((6, 4, 4, 3))
    with pytest.raises(IBLError, match="spp"):
        mr.render_mitsuba([(plane, 0)], cam, cube, spp=3)
    with pytest.raises(IBLError, match="mirror"):
        mr.render_mitsuba([(plane, 0)], cam, cube, g=1.0, spp=2)
    with pytest.raises(IBLError, match="material id"):
        mr.render_mitsuba([(plane, 3)], cam, cube, materials={0: (1, 0, 0)}, spp=2)


def test_envmap_too_coarse_for_the_cube_is_refused_not_silently_dark():  # runs without Mitsuba (the bitmap only)
    # a 64² cube on a 128-row bitmap: many texels get no pixel, and "texel" mode would drop their energy; the
    # error names a height that works, and with it every texel's energy is there (trapezoid sum = Σ L Ω)
    from ibl_ref.environment.envmap import cube_solid_angles

    cube = np.random.default_rng(2).uniform(0.1, 2.0, size=(6, 64, 64, 3))
    with pytest.raises(IBLError, match="too coarse .* use a height of at least 512"):
        mr.mitsuba_envmap(cube, 128)
    _, info = mr.mitsuba_envmap(cube, 128, energy="none", return_info=True)  # plain samples: reported only
    assert info["texels_without_pixel"] > 0 and info["energy_lost_frac"] > 0
    for n, h in ((1, 64), (64, 512)):
        c = cube[:, :n, :n]
        bm, info = mr.mitsuba_envmap(c, h, return_info=True)
        assert info["texels_without_pixel"] == 0
        got = (bm.astype(np.float64) * mr.envmap_grid_weights(h)[:, None, None]).sum(axis=(0, 1))
        np.testing.assert_allclose(got, (c * cube_solid_angles(n)[..., None]).sum(axis=(0, 1, 2)), rtol=1e-6)


def test_without_a_new_libllvm_mitsuba_is_a_clear_error_not_a_typeerror(tmp_path):  # runs without Mitsuba
    # the scalar variants take single values, not arrays: before, a missing libLLVM >= 17 silently selected
    # scalar_rgb and every render died with "TypeError: mitsuba.Point3f.__init__(): Item assignment failed".
    # A fresh process (the variant is chosen once per process) with DRJIT_LIBLLVM_PATH at an old library name
    import os
    import subprocess
    import sys

    old = tmp_path / "libLLVM-15.so"
    old.write_bytes(b"")
    env = dict(os.environ, DRJIT_LIBLLVM_PATH=str(old))
    code = ("from ibl_ref.rendering import mitsuba_render as mr\n"
            "assert not mr.mitsuba_available()\n"
            "try:\n    mr.select_variant()\nexcept mr.MitsubaUnavailable as e:\n    print(e)\n")
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "libLLVM >= 17" in p.stdout and "apt-get install libllvm19" in p.stdout
    with pytest.raises(IBLError, match="auto or llvm"):
        mr.select_variant("scalar")


def _bsdf_eval(bsdf_dict, wi, wo):
    """Mitsuba's ``bsdf.eval`` (= f·cos θo) at view directions ``wi`` and light directions ``wo`` (K, 3) in a z-up
    shading frame, and ``pdf``."""
    import drjit as dr
    import mitsuba as mi

    b = mi.load_dict(bsdf_dict)
    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.wi = mi.Vector3f(*wi.T.astype(np.float32))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    ctx = mi.BSDFContext()
    w = mi.Vector3f(*wo.T.astype(np.float32))
    return np.array(b.eval(ctx, si, w), dtype=np.float64)[0], np.array(b.pdf(ctx, si, w), dtype=np.float64)


def _hemi(n, seed):
    d = _random_dirs(n, seed)
    d[:, 2] = np.abs(d[:, 2]) + 0.02
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.usefixtures("mitsuba_llvm")
@pytest.mark.parametrize("mat,routes", [
    ("ggx:roughness=0.3,f0=1,smith=separable", ("lab", "builtin")),
    ("ggx:roughness=0.6,f0=1,kd=0.4,smith=separable", ("lab", "builtin")),  # builtin: blendbsdf ½·(2kd diffuse, 2×GGX)
    ("ggx:roughness=0.1,f0=1,smith=separable", ("lab", "builtin")),
    ("ggx:roughness=0.3,f0=0.04,kd=0.2", ("lab",)),  # height-correlated, Schlick F0 < 1: the lab's BSDF only
])
def test_ggx_bsdfs_evaluate_the_labs_formula(mat, routes):
    # Mitsuba's eval of both GGX routes against ibl_ref.lobes.brdfs.ggx × cos θo at random direction pairs: the same
    # function to float32 rounding (Mitsuba's built-in: its own D, separable G1·G1 and Fresnel of material='none')
    from ibl_ref.rendering.materials import parse_material

    m = parse_material(mat)
    wi, wo = (_hemi(4000, k).astype(np.float32).astype(np.float64) for k in (1, 2))  # what Mitsuba gets
    wi, wo = (w / np.linalg.norm(w, axis=1, keepdims=True) for w in (wi, wo))
    want = np.asarray(m.brdf(wo, wi, np.array([0.0, 0.0, 1.0]))) * wo[:, 2]
    # float32 arithmetic: D's denominator cos²θh(α²−1)+1 cancels to ~α² near the peak, so its relative rounding is
    # ~1e-7/α² (1e-3 at roughness 0.1, α² = 1e-4)
    rtol = max(2e-4, 10 * 1e-7 / m.alpha ** 2)
    for route in routes:
        got, pdf = _bsdf_eval(mr.bsdf_dict(m, route), wi, wo)
        np.testing.assert_allclose(got, want, rtol=rtol, atol=1e-6 * want.max(), err_msg=route)
        assert np.all(pdf >= 0) and np.all(pdf[want > 1e-3 * want.max()] > 0)


@pytest.mark.usefixtures("mitsuba_llvm")
def test_lab_ggx_sampling_is_unbiased():
    # statistical test (Mitsuba's own style): the mean sample weight f·cos/pdf of the lab's GGX BSDF estimates the
    # directional albedo (ibl_ref.lobes.brdfs.albedo, independent quadrature) within 5 standard errors
    import drjit as dr
    import mitsuba as mi

    from ibl_ref.lobes.brdfs import albedo, get_brdf, view_direction

    for rough, kd in ((0.3, 0.0), (0.6, 0.5)):
        b = mi.load_dict(mr.bsdf_dict(f"ggx:roughness={rough},f0=0.5,kd={kd}", "lab"))
        K = 400_000
        wi = view_direction(0.9)  # Mitsuba's si.wi points toward the viewer: the lab's wo
        si = dr.zeros(mi.SurfaceInteraction3f, K)
        si.wi = mi.Vector3f(*np.tile(wi, (K, 1)).T.astype(np.float32))
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        rng = np.random.default_rng(4)
        s1 = mi.Float(rng.random(K).astype(np.float32))
        s2 = mi.Point2f(*rng.random((2, K)).astype(np.float32))
        _, w = b.sample(mi.BSDFContext(), si, s1, s2)
        w = np.array(w, dtype=np.float64)[0]
        want = albedo(get_brdf("ggx", roughness=rough, f0=0.5, kd=kd), 0.9)
        assert abs(w.mean() - want) < 5 * w.std() / np.sqrt(K), (rough, w.mean(), want)


def test_builtin_ggx_route_needs_separable_smith_and_fresnel_one():
    with pytest.raises(IBLError, match="separable"):
        mr.bsdf_dict("ggx:0.3,1", "builtin")  # height-correlated by default
    with pytest.raises(IBLError, match="f0=1"):
        mr.bsdf_dict("ggx:roughness=0.3,f0=0.04,smith=separable", "builtin")
    with pytest.raises(IBLError, match="ggx_route"):
        mr.bsdf_dict("ggx:0.3", "cycles")
    assert mr.bsdf_dict("ggx:roughness=0.3,f0=1,smith=separable", "builtin")["alpha"] == pytest.approx(0.09)
