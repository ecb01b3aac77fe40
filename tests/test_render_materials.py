"""Tests of the kd/ks/g materials and g maps of ibl_ref.rendering.render (Knuth et al. 2014, Eq. 5 with a diffuse term)."""

from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from ibl_ref.rendering.camera import PerspectiveCamera
from ibl_ref.errors import IBLError
from ibl_ref.rendering.render import Material, render_pem, sample_g_map

R_SPHERE = 0.6


def _sphere_on_plane():
    s = trimesh.creation.icosphere(subdivisions=3, radius=R_SPHERE)
    s.apply_translation([0, R_SPHERE + 0.02, 0])
    q = trimesh.Trimesh([[-2, 0, -2], [2, 0, -2], [2, 0, 2], [-2, 0, 2]], [[0, 2, 1], [0, 3, 2]], process=False)
    return [(s, 0), (q, 1)]


def _quad(with_uv=True):
    """Unit-normal (+y) quad [-1, 1]² in x-z; UVs u = (x+1)/2, v = (z+1)/2 (same as the planar_xz fallback)."""
    V = [[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]]
    kw = {}
    if with_uv:
        kw["visual"] = trimesh.visual.TextureVisuals(uv=np.array([[0, 0], [1, 0], [1, 1], [0, 1.0]]))
    return trimesh.Trimesh(V, [[0, 2, 1], [0, 3, 2]], process=False, **kw)


class FakePEMs:
    """Closed-form stand-in for a PEMSet: PEM_i(d, g) = rgb_i · max(d·ω_i, 0) · (1 + g)."""

    def __init__(self, dirs, rgb, omega):
        d = np.asarray(dirs, float)
        self.lights = SimpleNamespace(directions=d / np.linalg.norm(d, axis=1, keepdims=True),
                                      rgb=np.asarray(rgb, float), solid_angle=np.asarray(omega, float))

    def lookup_all(self, dirs, g):
        cos = np.maximum(np.asarray(dirs) @ self.lights.directions.T, 0)  # (n, L)
        val = cos[..., None] * self.lights.rgb[None] * (1 + np.asarray(g))[..., None, None]
        return np.moveaxis(val, -2, 0)


CAM = PerspectiveCamera(eye=[0.0, 2.2, 3.2], target=[0, 0.4, 0], up=[0, 1, 0], fov_y_deg=45, width=40, height=32)
# straight down onto the quad, slightly tilted so that +x is to the right and +z downwards in the image
CAM_TOP = PerspectiveCamera(eye=[0.0, 3.0, 0.3], target=[0, 0, 0], up=[0, 0, -1], fov_y_deg=50, width=40, height=40)


@pytest.fixture(scope="module")
def sky_pems():
    from ibl_ref.knuth2014 import pem as pem_mod
    from ibl_ref.synthetic import synthetic_envs as envs
    return pem_mod.build_pems(envs.make_env("sky_sun", n=16, sun_radiance=50.0), n_lights=6)


def test_constant_environment_gives_kd_plus_ks():
    # L ≡ c, no shadows: every PEM lookup is a lobe *average* of normalised filters, so Σ_i PEM_i(·, g) = c for
    # every g and c_pixel = (kd + ks)·c per channel.  Tolerance 1e-6 relative: the PEMs are stored in float32.
    from ibl_ref.knuth2014 import pem as pem_mod
    from ibl_ref.synthetic import synthetic_envs as envs
    c = np.array([0.7, 1.3, 2.0])
    pems = pem_mod.build_pems(envs.make_env("constant", n=16, value=c), n_lights=6)
    mats = {0: Material(kd=[0.2, 0.3, 0.1], ks=[0.5, 0.1, 0.6], g=0.7), 1: Material(kd=0.25, ks=0.0, g=0.3)}
    res = render_pem(_sphere_on_plane(), CAM, pems, materials=mats, visibility="none")
    mid = res.gbuffer.material_id
    assert (mid == 0).sum() > 50 and (mid == 1).sum() > 50
    expect0 = np.array([0.2 + 0.5, 0.3 + 0.1, 0.1 + 0.6]) * c  # (kd + ks)·c per channel
    np.testing.assert_allclose(res.image[mid == 0], np.broadcast_to(expect0, ((mid == 0).sum(), 3)), rtol=1e-6)
    np.testing.assert_allclose(res.image[mid == 1], np.broadcast_to(0.25 * c, ((mid == 1).sum(), 3)), rtol=1e-6)
    np.testing.assert_array_equal(res.image[~res.mask], 0.0)


def test_eq5_with_materials_closed_form_and_visibility():
    # closed-form PEMs and exact visibility:
    # c = Σ_i VIS_i (kd·rgb_i·max(n·ω_i,0)·1 + ks·rgb_i·max(r·ω_i,0)·(1+g))
    # — diffuse through the shading normal at g = 0, glossy through r at the material's g.  Computed here from
    # the G-buffer, independently of the renderer's composition; float64 throughout → atol 1e-12.
    dirs = [[0, 1, 0], [0.5, 0.8, 0.3], [-0.6, 0.5, -0.2]]
    rgb = [[1.0, 0.5, 0.2], [0.3, 0.9, 0.4], [0.2, 0.2, 1.0]]
    pems = FakePEMs(dirs, rgb, [0.05, 0.05, 0.05])
    kd0, ks0, g0 = np.array([0.3, 0.2, 0.1]), 0.6, 0.8
    mats = {0: Material(kd=kd0, ks=ks0, g=g0), 1: Material(kd=0.5, ks=0.25, g=0.1)}
    res = render_pem(_sphere_on_plane(), CAM, pems, materials=mats, visibility="raycast")
    gb, m = res.gbuffer, res.mask
    D, C = pems.lights.directions, pems.lights.rgb
    cos_n = np.maximum(gb.normal[m] @ D.T, 0)  # (n, L)
    cos_r = np.maximum(gb.reflect[m] @ D.T, 0)
    on0 = (gb.material_id[m] == 0)[:, None]
    kd = np.where(on0, kd0, 0.5)
    ks = np.where(on0, ks0, 0.25)
    g = np.where(on0[:, 0], g0, 0.1)
    V = res.visibility[:, m].T  # (n, L)
    diffuse = kd * ((V * cos_n) @ C)
    specular = ks * ((V * cos_r) @ C) * (1 + g)[:, None]
    np.testing.assert_allclose(res.diffuse[m], diffuse, atol=1e-12)
    np.testing.assert_allclose(res.specular[m], specular, atol=1e-12)
    np.testing.assert_allclose(res.image[m], diffuse + specular, atol=1e-12)
    assert (V == 0).sum() > 20 and diffuse.max() > 0.1  # shadows and a diffuse term are really exercised


def test_diffuse_term_is_g0_lookup_at_normal(sky_pems):
    # real PEMs (sky + sun): the diffuse term is kd·Σ_i PEM_i(n, 0) (PEMSet.full_lookup), not a lookup at r;
    # same float32 lookups summed in float64 here and in the renderer → rtol 1e-12
    res = render_pem(_sphere_on_plane(), CAM, sky_pems, materials=Material(kd=0.6, ks=0.0, g=0.9), visibility="none")
    m = res.mask
    n = res.gbuffer.normal[m]
    expect = 0.6 * np.asarray(sky_pems.lookup_all(n, 0.0), dtype=np.float64).sum(axis=0)
    np.testing.assert_allclose(res.image[m], expect, rtol=1e-12)
    at_r = 0.6 * sky_pems.full_lookup(res.gbuffer.reflect[m], 0.0).astype(np.float64)
    assert np.abs(at_r - expect).max() > 0.05 * expect.max()  # the test can tell n from r


def test_materials_match_glossiness_path(sky_pems):
    # the specular term with ks = 0.4 is 0.4 × the old pure-glossy render (glossiness=, kd = 0, ks = 1) —
    # an independent code path through render_pem; float64 arithmetic on the same lookups → rtol 1e-12
    a = render_pem(_sphere_on_plane(), CAM, sky_pems, {0: 0.8, 1: 0.3}, visibility="vsm", vsm_resolution=64)
    mats = {0: Material(0.2, 0.4, 0.8), 1: Material(0.2, 0.4, 0.3)}
    b = render_pem(_sphere_on_plane(), CAM, sky_pems, materials=mats, visibility="vsm", vsm_resolution=64)
    np.testing.assert_allclose(b.specular, 0.4 * a.image, rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(b.image, b.diffuse + b.specular, rtol=1e-12)
    np.testing.assert_array_equal(a.visibility, b.visibility)
    # kd = 0, ks = 1 is bit-identical to the glossiness path
    c = render_pem(_sphere_on_plane(), CAM, sky_pems, materials={0: (0, 1, 0.8), 1: (0, 1, 0.3)}, visibility="none")
    d = render_pem(_sphere_on_plane(), CAM, sky_pems, {0: 0.8, 1: 0.3}, visibility="none")
    np.testing.assert_array_equal(c.image, d.image)


@pytest.mark.parametrize("split", ["columns", "rows"])
def test_g_map_two_halves(sky_pems, split):
    # a g map whose halves hold g1 and g2: pixels whose texture coordinate is ≥ 1.5 texels from the split line
    # and from the (repeat-wrapped) border get exactly the scalar-g render of g1 resp. g2 (bilinear weights
    # within one half are a convex combination of equal values; rtol 1e-12).
    g1, g2 = 0.2, 0.95
    h, w = 16, 16
    gm = np.full((h, w), g1)
    if split == "columns":
        gm[:, w // 2:] = g2  # u ≥ 0.5 → g2
    else:
        gm[: h // 2, :] = g2  # top rows = v ≥ 0.5 (v runs bottom → top) → g2
    res = render_pem(_quad(), CAM_TOP, sky_pems, materials=Material(kd=0, ks=1, g=0.5, g_map=gm), visibility="none")
    ref1 = render_pem(_quad(), CAM_TOP, sky_pems, g1, visibility="none").image
    ref2 = render_pem(_quad(), CAM_TOP, sky_pems, g2, visibility="none").image
    P = res.gbuffer.position
    t = (P[..., 0] + 1) / 2 if split == "columns" else (P[..., 2] + 1) / 2  # u or v (quad UVs)
    margin = 1.5 / w
    inner = res.mask & (t > margin) & (t < 1 - margin)
    lo = inner & (t < 0.5 - margin)
    hi = inner & (t > 0.5 + margin)
    assert lo.sum() > 100 and hi.sum() > 100
    np.testing.assert_allclose(res.image[lo], ref1[lo], rtol=1e-12)
    np.testing.assert_allclose(res.image[hi], ref2[hi], rtol=1e-12)
    np.testing.assert_allclose(res.glossiness[lo], g1)
    np.testing.assert_allclose(res.glossiness[hi], g2)
    assert np.abs(ref1[hi] - ref2[hi]).max() > 1e-3  # the two g values give different images
    # the planar_xz fallback (no UVs) reproduces the same u = (x+1)/2, v = (z+1)/2 on this quad
    fb = render_pem(_quad(with_uv=False), CAM_TOP, sky_pems, materials=Material(0, 1, 0.5, g_map=gm), visibility="none")
    np.testing.assert_allclose(fb.glossiness[inner], res.glossiness[inner], atol=1e-12)
    with pytest.raises(IBLError, match="texture coordinates"):
        render_pem(_quad(with_uv=False), CAM_TOP, sky_pems,
                   materials=Material(0, 1, 0.5, g_map=gm, uv_fallback="error"), visibility="none")


def test_sample_g_map_conventions():
    # 2×2 map, rows top → bottom; texel centres at u ∈ {¼, ¾}, v ∈ {¾ (top row), ¼ (bottom row)}
    gm = np.array([[0.0, 0.2], [0.6, 1.0]])
    uv = np.array([[0.25, 0.75], [0.75, 0.75], [0.25, 0.25], [0.75, 0.25], [0.5, 0.75], [0.5, 0.5]])
    np.testing.assert_allclose(sample_g_map(gm, uv), [0.0, 0.2, 0.6, 1.0, 0.1, 0.45], atol=1e-15)
    np.testing.assert_allclose(sample_g_map(gm, uv[:4], filter="nearest"), [0.0, 0.2, 0.6, 1.0])
    # repeat: u = 0 is halfway between the last and first column; clamp: the first column
    np.testing.assert_allclose(sample_g_map(gm, [[0.0, 0.75]]), [0.1])
    np.testing.assert_allclose(sample_g_map(gm, [[0.0, 0.75]], wrap="clamp"), [0.0])


@pytest.mark.parametrize("kw, match", [
    (dict(g=1.5), r"\[0, 1\]"), (dict(g=-0.1), r"\[0, 1\]"), (dict(g=float("nan")), r"\[0, 1\]"),
    (dict(kd=-0.1), ">= 0"), (dict(ks=[0.1, -0.2, 0.3]), ">= 0"), (dict(kd=[0.1, float("nan"), 0]), "finite"),
    (dict(ks=float("inf")), "finite"), (dict(kd=[0.1, 0.2]), "RGB"), (dict(kd="red"), "number"),
    (dict(g_map=np.full((4, 4), 1.2)), r"\[0, 1\]"), (dict(g_map=np.full((4, 4), np.nan)), r"\[0, 1\]"),
    (dict(g_map=np.zeros(4)), "2D"), (dict(uv_fallback="cylinder"), "uv_fallback"),
])
def test_material_validation(kw, match):
    with pytest.raises(IBLError, match=match):
        Material(**kw)


def test_render_material_errors():
    pems = FakePEMs([[0, 1, 0]], [[1, 1, 1]], [0.1])
    with pytest.raises(IBLError, match="not both"):
        render_pem(_sphere_on_plane(), CAM, pems, 0.5, materials=Material(), visibility="none")
    with pytest.raises(IBLError, match=r"material id\(s\) \[1\]"):
        render_pem(_sphere_on_plane(), CAM, pems, materials={0: Material()}, visibility="none")
    with pytest.raises(IBLError, match="Material"):
        render_pem(_sphere_on_plane(), CAM, pems, materials={0: "shiny", 1: Material()}, visibility="none")
    one_channel = FakePEMs([[0, 1, 0]], [[1.0]], [0.1])
    with pytest.raises(IBLError, match="3-channel"):
        render_pem(_sphere_on_plane(), CAM, one_channel, materials=Material(kd=[0.1, 0.2, 0.3]), visibility="none")
