"""Tests of ibl_ref.rendering.render (Eq. 5 composition) on top of the rasterizer, VSM and ray-cast visibility."""

from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from ibl_ref.rendering.camera import PerspectiveCamera
from ibl_ref.errors import IBLError
from ibl_ref.rendering.render import render_pem

R_SPHERE = 0.6


def _sphere_on_plane():
    s = trimesh.creation.icosphere(subdivisions=3, radius=R_SPHERE)
    s.apply_translation([0, R_SPHERE + 0.02, 0])
    q = trimesh.Trimesh([[-2, 0, -2], [2, 0, -2], [2, 0, 2], [-2, 0, 2]], [[0, 2, 1], [0, 3, 2]], process=False)
    return [(s, 0), (q, 1)]


class FakePEMs:
    """Closed-form stand-in for ibl_ref.knuth2014.pem.PEMSet: PEM_i(r, g) = rgb_i · max(r·ω_i, 0) · (1 + g)."""

    def __init__(self, dirs, rgb, omega):
        d = np.asarray(dirs, float)
        self.lights = SimpleNamespace(directions=d / np.linalg.norm(d, axis=1, keepdims=True),
                                      rgb=np.asarray(rgb, float), solid_angle=np.asarray(omega, float))

    def lookup_all(self, dirs, g):
        cos = np.maximum(np.asarray(dirs) @ self.lights.directions.T, 0)  # (n, L)
        val = cos[..., None] * self.lights.rgb[None] * (1 + np.asarray(g))[..., None, None]
        return np.moveaxis(val, -2, 0)


CAM = PerspectiveCamera(eye=[0.0, 2.2, 3.2], target=[0, 0.4, 0], up=[0, 1, 0], fov_y_deg=45, width=48, height=40)


@pytest.mark.parametrize("backend", ["binned", "trimesh"])
def test_eq5_with_exact_visibility_closed_form(backend):
    # one light straight up: a point on the (convex, polyhedral) sphere is lit iff its facet normal has n_y > 0,
    # a ground point iff it lies outside the sphere's vertical shadow, the convex hull of the sphere's vertices
    # projected on the ground (exact, scipy's Delaunay point location).  Excluded: vertical facets (n_y = 0: the
    # ray runs in the facet's plane, undefined).  The binned caster (no origin offset) matches everywhere else;
    # the trimesh route casts from an origin offset 1e-4·R along the normal and the ray, which lifts points of
    # down-facing facets next to the silhouette out of the sphere: there it also excludes |n_y| < 0.1 and the
    # equator band |y − y_c| < 0.1·R (measured: 12 such pixels, 3 of them on vertical facets).
    from scipy.spatial import Delaunay

    scene = _sphere_on_plane()
    pems = FakePEMs([[0, 1, 0]], [[2.0, 1.0, 0.5]], [0.1])
    res = render_pem(scene, CAM, pems, {0: 0.5, 1: 0.0}, visibility="raycast", exact_backend=backend)
    g = res.gbuffer
    m = res.mask
    P = g.position
    on_sphere = g.material_id == 0
    fn_y = g.face_normal[..., 1]
    in_shadow = Delaunay(scene[0][0].vertices[:, [0, 2]]).find_simplex(P[..., [0, 2]]) >= 0
    lit = np.where(on_sphere, fn_y > 0, ~in_shadow)
    clear = m & ~(on_sphere & (fn_y == 0))
    if backend == "trimesh":
        band = np.abs(P[..., 1] - (R_SPHERE + 0.02)) < 0.1 * R_SPHERE
        clear &= ~(on_sphere & ((np.abs(fn_y) < 0.1) | band))
    assert clear.sum() > 0.97 * m.sum()
    np.testing.assert_array_equal(res.visibility[0][clear], lit[clear].astype(float))
    # Eq. 5 with the closed-form PEM
    gl = np.where(on_sphere, 0.5, 0.0)
    expect = lit[..., None] * np.maximum(g.reflect[..., 1], 0)[..., None] * np.array([2.0, 1.0, 0.5]) * (1 + gl)[..., None]
    np.testing.assert_allclose(res.image[clear], expect[clear], atol=1e-12)
    assert np.all(res.image[~m] == 0)
    assert res.image[clear].max() > 0.5 and (~lit[clear]).sum() > 20


def test_vsm_visibility_equals_exact_away_from_shadow_edges():
    # VSM vs exact ray casting, pixel by pixel, wherever the exact answer cannot change within the VSM's filter
    # footprint.  The moments are blurred with a Gaussian of σ = Δd·tanθ/2 world units (vsm.blur_sigma_texels:
    # Δd = 0.25 × scene radius, Ω = 0.02 sr), truncated at 4σ, then read bilinearly (±1 texel).  A pixel is
    # "clear" when parallel rays toward the light from 25 points of its receiver's tangent plane within
    # ρ = 4σ + 2 texels of it (centre, 8 at ρ/2, 16 at ρ; moved along the light direction onto the tangent plane)
    # all agree, and the light is not grazing (|n·ω| ≥ 0.2).  There the VSM must give the exact answer:
    # * lit: the receiver is the nearest surface over the whole footprint and its depth is linear (ground) or
    #   convex (sphere) there, so the blurred mean depth is ≥ the receiver's (Jensen) and Chebyshev's bound is 1
    #   exactly (t ≤ M1);
    # * shadowed: the blockers are far in front, so σ²/(σ² + (t − M1)²) ≪ 1; |Δ| < 0.05 as before (measured
    #   ≤ 1.8e-3).
    # Penumbra pixels (soft vs hard shadow by design) and grazing terminator pixels are the rest; they are not
    # compared.
    from ibl_ref.rendering.camera import light_camera
    from ibl_ref.rendering.raster import prepare_scene
    from ibl_ref.rendering.raycast import parallel_visibility
    from ibl_ref.rendering.vsm import blur_sigma_texels

    dirs = np.array([[0, 1, 0], [0.5, 0.8, 0.3], [-0.6, 0.5, -0.2]], float)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    omega, res = 0.02, 256
    pems = FakePEMs(dirs, np.ones((3, 3)), [omega] * 3)
    scene = _sphere_on_plane()
    a = render_pem(scene, CAM, pems, 0.3, visibility="vsm", vsm_resolution=res)
    b = render_pem(scene, CAM, pems, 0.3, visibility="raycast")
    np.testing.assert_allclose(a.unshadowed, b.unshadowed)
    assert np.all(a.image <= a.unshadowed + 1e-12)
    m = a.mask
    P, fn = a.gbuffer.position[m], a.gbuffer.face_normal[m]
    centre, radius = prepare_scene(scene, warn=False).bounds()
    for i, w in enumerate(dirs):
        texel = light_camera(w, centre, radius, resolution=res, margin=0.05).texel_size
        rho = 4 * blur_sigma_texels(omega, texel, 0.25 * radius) * texel + 2 * texel
        u = np.cross(w, [1.0, 0.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(w, u)
        offsets = [np.zeros(3)] + [r * (np.cos(t) * u + np.sin(t) * v) for r, k in ((rho / 2, 8), (rho, 16))
                                   for t in np.arange(k) * 2 * np.pi / k]
        wn = fn @ w
        steep = np.abs(wn) >= 0.2
        vis = np.stack([parallel_visibility(scene, P + o - ((fn @ o) / np.where(steep, wn, 1.0))[:, None] * w, w)
                        for o in offsets])
        lit = steep & np.all(vis == 1, axis=0)
        dark = steep & np.all(vis == 0, axis=0)
        va, vb = a.visibility[i][m], b.visibility[i][m]
        np.testing.assert_array_equal(vb[lit], 1.0)
        np.testing.assert_array_equal(vb[dark], 0.0)
        np.testing.assert_array_equal(va[lit], 1.0)
        assert np.all(va[dark] < 0.05), va[dark].max()
        # not vacuous: most of the image is clear, and every light has a clear shadow (measured 24 / 26 / 109)
        assert lit.sum() + dark.sum() > 0.7 * m.sum() and dark.sum() >= 20, (lit.sum(), dark.sum(), m.sum())


def test_constant_environment_unshadowed_is_constant():
    # with ibl_ref.knuth2014.pem's PEMSet of a constant map, Σ_i PEM_i is the lobe average of a constant = the constant
    # (normalised filters), for every glossiness; float32 PEM storage → tolerance 1e-6
    from ibl_ref.knuth2014 import pem as pem_mod
    from ibl_ref.synthetic import synthetic_envs as envs
    pems = pem_mod.build_pems(envs.make_env("constant", n=16) * 0.7, n_lights=6)
    res = render_pem(_sphere_on_plane(), CAM, pems, {0: 0.9, 1: 0.2}, visibility="none")
    np.testing.assert_allclose(res.image[res.mask], 0.7, rtol=1e-6)
    np.testing.assert_array_equal(res.visibility, 1.0)


def test_render_bad_inputs():
    pems = FakePEMs([[0, 1, 0]], [[1, 1, 1]], [0.1])
    with pytest.raises(IBLError, match="visibility"):
        render_pem(_sphere_on_plane(), CAM, pems, 0.5, visibility="exact")
    with pytest.raises(IBLError, match=r"\[0, 1\]"):
        render_pem(_sphere_on_plane(), CAM, pems, 1.5, visibility="none")
    with pytest.raises(IBLError, match="material"):
        render_pem(_sphere_on_plane(), CAM, pems, {0: 0.5}, visibility="none")
    with pytest.raises(IBLError, match="PEMSet"):
        render_pem(_sphere_on_plane(), CAM, object(), 0.5)


def test_cli_render_smoke(tmp_path):
    from ibl_ref.cli import main

    out = tmp_path / "r.npz"
    rc = main(["render", "--synthetic", "constant", "--env-size", "16", "--mesh", "torus", "--lights", "6",
               "--size", "24", "--vsm-res", "64", "--visibility", "none", "--out", str(out)])
    assert rc == 0
    d = np.load(out)
    assert d["image"].shape == (24, 24, 3) and d["mask"].any()
    # constant map (value 1), no shadows: every covered pixel is 1 (normalised lobes; float32 PEMs)
    np.testing.assert_allclose(d["image"][d["mask"]], 1.0, rtol=1e-6)
    assert main(["render", "--mesh", "no_such_mesh", "--out", str(out)]) == 1


def test_horizon_term():
    # a light from below the ground: the ground (open quad) is its own first surface, so the shadow map and the
    # paper-semantics exact route say "visible" on the ground away from the sphere; horizon=True blocks it
    # (n_face·ω = −1 < 0) for every method.
    pems = FakePEMs([[0.0, -1.0, 0.0]], [[1.0, 1.0, 1.0]], [0.05])
    scene = _sphere_on_plane()
    for method in ("vsm", "raycast", "none"):
        a = render_pem(scene, CAM, pems, 0.5, visibility=method, vsm_resolution=128)
        b = render_pem(scene, CAM, pems, 0.5, visibility=method, vsm_resolution=128, horizon=True)
        ground = a.mask & (a.gbuffer.material_id == 1)
        rho = np.hypot(a.gbuffer.position[..., 0], a.gbuffer.position[..., 2])
        away = ground & (rho > R_SPHERE + 0.1)
        assert away.sum() > 100
        np.testing.assert_array_equal(a.visibility[0][away], 1.0)
        np.testing.assert_array_equal(b.visibility[0][ground], 0.0)
