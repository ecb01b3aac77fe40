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
    # a plane point iff it lies outside the sphere's vertical shadow, the disc x² + z² > R² up to the polyhedron's
    # inscribed-sphere gap.  Excluded: facets with |n_y| < 0.03, the disc rim ±0.03, and the equator band
    # |y − y_c| < 0.1·R (there the shadow-ray origin offset eps·n moves the origin outside the silhouette).
    pems = FakePEMs([[0, 1, 0]], [[2.0, 1.0, 0.5]], [0.1])
    res = render_pem(_sphere_on_plane(), CAM, pems, {0: 0.5, 1: 0.0}, visibility="raycast", exact_backend=backend)
    g = res.gbuffer
    m = res.mask
    P = g.position
    on_sphere = g.material_id == 0
    fn_y = g.face_normal[..., 1]
    rho = np.hypot(P[..., 0], P[..., 2])
    lit = np.where(on_sphere, fn_y > 0, rho > R_SPHERE)
    band = np.abs(P[..., 1] - (R_SPHERE + 0.02)) < 0.1 * R_SPHERE
    clear = m & np.where(on_sphere, (np.abs(fn_y) > 0.03) & ~band, np.abs(rho - R_SPHERE) > 0.03)
    np.testing.assert_array_equal(res.visibility[0][clear], lit[clear].astype(float))
    # Eq. 5 with the closed-form PEM
    gl = np.where(on_sphere, 0.5, 0.0)
    expect = lit[..., None] * np.maximum(g.reflect[..., 1], 0)[..., None] * np.array([2.0, 1.0, 0.5]) * (1 + gl)[..., None]
    np.testing.assert_allclose(res.image[clear], expect[clear], atol=1e-12)
    assert np.all(res.image[~m] == 0)
    assert res.image[clear].max() > 0.5 and (~lit[clear]).sum() > 20


def test_vsm_visibility_close_to_exact_away_from_edges():
    # same lights, VSM vs exact: agree (|Δ| < 0.05) on ≥ 90 % of covered pixels; penumbra pixels (soft vs hard)
    # and self-shadowing terminator pixels make the rest
    pems = FakePEMs([[0, 1, 0], [0.5, 0.8, 0.3], [-0.6, 0.5, -0.2]], np.ones((3, 3)), [0.02, 0.02, 0.02])
    a = render_pem(_sphere_on_plane(), CAM, pems, 0.3, visibility="vsm", vsm_resolution=256)
    b = render_pem(_sphere_on_plane(), CAM, pems, 0.3, visibility="raycast")
    d = np.abs(a.visibility - b.visibility)[:, a.mask]
    assert np.mean(d < 0.05) > 0.9
    np.testing.assert_allclose(a.unshadowed, b.unshadowed)
    assert np.all(a.image <= a.unshadowed + 1e-12)


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
