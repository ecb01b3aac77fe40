"""Tests of the ray-traced reference (ibl_ref.rendering.reference_render)."""

import numpy as np
import pytest
import trimesh

from ibl_ref.rendering import reference_render as rr
from ibl_ref.rendering.camera import PerspectiveCamera
from ibl_ref.environment.envmap import cube_solid_angles, texel_directions
from ibl_ref.errors import IBLError, LayoutError, RadianceError


def _quad(size=2.0):
    s = size / 2
    v = [[-s, 0, -s], [s, 0, -s], [s, 0, s], [-s, 0, s]]
    return trimesh.Trimesh(v, [[0, 2, 1], [0, 3, 2]], process=False)  # normal +y


CAM = PerspectiveCamera(eye=[0.0, 2.0, 0.3], target=[0, 0, 0], up=[0, 1, 0], fov_y_deg=40, width=10, height=10)


def test_lobe_average_equals_convolve_exact_at_texel_centres():
    # independent route: the exact convolution of ibl_ref.groundtruth.phong_convolution evaluates the same formula at texel centres
    from ibl_ref.groundtruth.phong_convolution import convolve_exact

    rng = np.random.default_rng(1)
    cube = rng.uniform(0.1, 2.0, size=(6, 4, 4, 3))
    for s in (1.0, 7.0):
        ref = convolve_exact(cube, s)
        got = rr.lobe_average(cube, texel_directions(4), s, n_env=4, directions="centre")
        np.testing.assert_allclose(got, ref, rtol=1e-12)  # same sums, only summation order differs


def test_coarse_env_keeps_integral():
    rng = np.random.default_rng(2)
    cube = rng.uniform(0, 5, size=(6, 16, 16, 3))
    c = rr.coarse_env(cube, 4)
    i_fine = (cube * cube_solid_angles(16)[..., None]).sum(axis=(0, 1, 2))
    i_coarse = (c * cube_solid_angles(4)[..., None]).sum(axis=(0, 1, 2))
    np.testing.assert_allclose(i_coarse, i_fine, rtol=1e-12)  # exact by construction (texels nest)


def test_coarse_quadrature_converges_on_linear_env():
    # closed form (synthetic_envs.gradient_lobe_average): a + (b·r)(s+1)/(s+2)
    from ibl_ref.synthetic.synthetic_envs import gradient_lobe_average, make_env

    b = (0.2, 0.5, -0.3)
    env = make_env("gradient", n=32, a=1.0, b=b)
    d = np.random.default_rng(0).normal(size=(100, 3))
    ex = gradient_lobe_average(d, 1.0, a=1.0, b=b)
    e8 = np.abs(rr.lobe_average(env, d, 1.0, n_env=8) - ex).max()
    e16 = np.abs(rr.lobe_average(env, d, 1.0, n_env=16) - ex).max()
    # midpoint-type quadrature on a smooth integrand: O(h²); h = 1/8 of a face → < 1 % and ~4× per halving
    assert e8 < 1e-2
    assert e16 < e8 / 3


def test_parallel_visibility_matches_trimesh():
    from ibl_ref.rendering.raycast import visibility_to_directions

    mesh = trimesh.util.concatenate([_quad(4.0), trimesh.creation.icosphere(1, 0.5).apply_translation([0, 0.6, 0])])
    rng = np.random.default_rng(3)
    pts = np.c_[rng.uniform(-1.5, 1.5, 60), np.zeros(60), rng.uniform(-1.5, 1.5, 60)]
    nrm = np.tile([0.0, 1.0, 0.0], (60, 1))
    dirs = rng.normal(size=(16, 3))
    dirs[:, 1] = np.abs(dirs[:, 1]) + 0.2  # upper hemisphere (plus a few that graze less)
    dirs[-2:] = [[0.0, -1.0, 0.0], [0.3, -0.5, 0.1]]  # into the plane: must be occluded by it
    got = rr.parallel_visibility(mesh, pts, nrm, dirs)
    ref = visibility_to_directions(mesh, pts, nrm, dirs)  # independent algorithm (trimesh intersects_any)
    assert ref.min() == 0 and ref[:, :-2].max() == 1  # the test has both outcomes
    np.testing.assert_array_equal(got, ref)


def test_unoccluded_diffuse_on_plane_constant_env_is_exact():
    # a plane is not occluded inside the s=1 lobe around its normal: image = constant exactly
    env = np.full((6, 8, 8, 3), 0.7)
    res = rr.render_reference([(_quad(), 0)], CAM, env, kd=1.0, ks=0.0, g=0.0)
    assert res.mask.sum() > 20
    np.testing.assert_allclose(res.image[res.mask], 0.7, rtol=1e-12)


def test_reference_unoccluded_is_exact_lobe_average():
    from ibl_ref.synthetic.synthetic_envs import make_env

    env = make_env("sky_sun", n=16)
    mesh = trimesh.util.concatenate([_quad(4.0), trimesh.creation.icosphere(1, 0.5).apply_translation([0, 0.6, 0])])
    res = rr.render_reference(mesh, CAM, env, kd=0.3, ks=0.7, g=0.5, directions="centre", n_env_diffuse=8,
                              n_env_glossy=8, rtol=0)
    m = res.mask
    n, r = res.gbuffer.normal[m], res.gbuffer.reflect[m]
    want = 0.3 * rr.lobe_average(env, n, 1.0, n_env=8) + 0.7 * rr.lobe_average(env, r, 2.0, n_env=8)
    np.testing.assert_allclose(res.unoccluded[m], want, rtol=1e-10)
    # occlusion only removes light
    assert np.all(res.image[m] <= res.unoccluded[m] * (1 + 1e-12))
    assert (res.image[m] < res.unoccluded[m] * 0.99).any()  # the sphere shadows the plane somewhere


def test_mirror_reference_on_plane():
    from ibl_ref.environment.sampling import sample_nearest

    rng = np.random.default_rng(4)
    env = rng.uniform(0.1, 1.0, size=(6, 8, 8, 3))
    res = rr.render_reference([(_quad(), 0)], CAM, env, kd=0.0, ks=1.0, g=1.0)
    m = res.mask
    np.testing.assert_allclose(res.image[m], sample_nearest(env, res.gbuffer.reflect[m]), rtol=1e-12)


def test_env_size_for_exponent_and_limit():
    sizes = [rr.env_size_for_exponent(s, 256) for s in (1, 10, 100, 1000)]
    assert sizes == sorted(sizes) and sizes[0] == 8
    # lobe half-width must cover ≥ 1 texel of the chosen level (unless capped at the fine size)
    for s, n in zip((1, 10, 100, 1000), sizes):
        assert rr.lobe_half_angle(s) >= (np.pi / 2) / n or n == 256
    assert rr.env_size_for_exponent(1e6, 32) == 32
    np.testing.assert_allclose(rr.lobe_half_angle(1.0), np.pi / 3)  # cos θ = 1/2


def test_coarse_level_error_zero_at_full_resolution():
    rng = np.random.default_rng(5)
    env = rng.uniform(0.1, 1.0, size=(6, 8, 8, 3))
    e = rr.coarse_level_error(env, rng.normal(size=(20, 3)), 3.0, 8, directions="centre")
    assert e["rel_l1"] < 1e-14


def test_bad_inputs():
    env = np.ones((6, 8, 8, 3))
    with pytest.raises(LayoutError):
        rr.coarse_env(env, 3)
    with pytest.raises(IBLError):
        rr.render_reference([(_quad(), 0)], CAM, env, g=1.5)
    with pytest.raises(IBLError):
        rr.render_reference([(_quad(), 0)], CAM, env, kd=-1)
    bad = env.copy()
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(RadianceError):
        rr.render_reference([(_quad(), 0)], CAM, bad)
    with pytest.raises(IBLError):
        rr.parallel_visibility(_quad(), np.zeros((2, 3)), None, np.zeros((1, 3)))


def test_exact_pem_lookup_sums_to_lobe_average():
    # Σ_i PEM_i = the exact lobe average of the full map (regions partition the sphere)
    from ibl_ref.knuth2014.median_cut import median_cut
    from ibl_ref.synthetic.synthetic_envs import make_env

    env = make_env("sky_sun", n=8)
    lights = median_cut(env, 12)
    d = np.random.default_rng(6).normal(size=(30, 3))
    pem = rr.exact_pem_lookup(env, lights.labels, d, 4.0, len(lights))
    assert pem.shape == (12, 30, 3) and pem.min() >= 0
    np.testing.assert_allclose(pem.sum(axis=0), rr.lobe_average(env, d, 4.0), rtol=1e-12)


# ------------------------------------------------------------------------------------------------
# converged reference (rtol), conventions
# ------------------------------------------------------------------------------------------------
def _sphere_on_quad(subdiv=1):
    # low-poly occluder over a ground quad: cheap enough for fine runs
    return [(_quad(4.0), 0), (trimesh.creation.icosphere(subdiv, 0.5).apply_translation([0, 0.7, 0]), 1)]


CAM_SHADOW = PerspectiveCamera(eye=[0.0, 3.0, 2.0], target=[0, 0.2, 0], up=[0, 1, 0], fov_y_deg=50, width=14,
                               height=14)


CAM_SMALL = PerspectiveCamera(eye=[0.0, 3.0, 2.0], target=[0, 0.2, 0], up=[0, 1, 0], fov_y_deg=60, width=10, height=10)


def test_leaf_bvh_matches_parallel_caster():
    # two algorithms (per-ray Möller–Trumbore over bounding-sphere leaves vs per-direction projection) agree
    from ibl_ref.rendering.raster import prepare_scene

    sc = prepare_scene([(_quad(4.0), 0), (trimesh.creation.icosphere(2, 0.5).apply_translation([0, 0.6, 0]), 1)])
    rng = np.random.default_rng(7)
    pts = np.c_[rng.uniform(-1.5, 1.5, 80), np.zeros(80), rng.uniform(-1.5, 1.5, 80)]
    nrm = np.tile([0.0, 1.0, 0.0], (80, 1))
    dirs = rng.normal(size=(30, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    want = rr.parallel_visibility(sc, pts, nrm, dirs)
    pix, cell = np.nonzero(np.ones(want.shape, bool))
    got = rr._cast_pairs(sc, pts, nrm, dirs, pix, cell, None, bvh=rr._LeafBVH(sc, leaf=16)).reshape(want.shape)
    assert 0 < want.mean() < 1
    np.testing.assert_array_equal(got, want)


def test_converged_constant_env_plane_is_exact():
    # closed form: unoccluded plane under L ≡ 0.7: diffuse → 0.7; glossy lobe around r clipped to Ω⁺(n):
    # equal to (s+1)/(2π)∫_{Ω⁺} cos^s α dω ≤ 0.7 (< where the lobe dips below the horizon)
    env = np.full((6, 8, 8, 3), 0.7)
    res = rr.render_reference([(_quad(), 0)], CAM, env, kd=1.0, ks=0.0, g=0.0)
    assert res.info["quadrature"] == "converged"
    np.testing.assert_allclose(res.image[res.mask], 0.7, rtol=1e-12)
    assert res.info["err_rel_l1"] < 1e-12  # nothing to refine: the estimate sees no error either
    gl = rr.render_reference([(_quad(), 0)], CAM, env, kd=0.0, ks=1.0, g=0.9)
    v = gl.image[gl.mask]
    assert np.all(v <= 0.7 * (1 + 1e-9)) and v.max() > 0.69


def test_converged_estimate_bounds_difference_to_finer_run():
    # a small bright sun (sky_sun: 1e5 over 6.8e-5 sr) casts the sphere's shadow edge across the ground in view;
    # the error estimate of a run at rtol 1e-2 must bound its actual difference to a much finer run (rtol 1e-5,
    # finer visibility level), per image (rel. L1); the finer run's own estimate is below the coarse one
    from ibl_ref.synthetic.synthetic_envs import SUN_NEAR_CORNER, make_env

    meshes = _sphere_on_quad()
    default_sun = make_env("sky_sun", n=16)
    corner_sun = make_env("sky_sun", n=16, sun_direction=SUN_NEAR_CORNER)  # the sun across a cube corner
    for env, (kd, ks, g) in ((default_sun, (1.0, 0.0, 0.0)), (default_sun, (0.0, 1.0, 0.9)),
                             (corner_sun, (1.0, 0.0, 0.0))):
        a = rr.render_reference(meshes, CAM_SMALL, env, kd=kd, ks=ks, g=g, rtol=1e-2)
        b = rr.render_reference(meshes, CAM_SMALL, env, kd=kd, ks=ks, g=g, rtol=1e-5, n_vis_max=64)
        assert b.info["lobes"][0]["n_vis"] > a.info["lobes"][0]["n_vis"]  # a much finer visibility level
        m = a.mask
        ya, yb = a.image[m].mean(-1), b.image[m].mean(-1)
        actual = np.abs(ya - yb).sum() / np.abs(yb).sum()
        shadowed = (a.image[m].mean(-1) < 0.8 * a.unoccluded[m].mean(-1)).mean()
        assert shadowed > 0.01  # a (sun) shadow is in view
        assert actual <= a.info["err_rel_l1"], (kd, ks, g, actual, a.info["err_rel_l1"])
        assert b.info["err_rel_l1"] < a.info["err_rel_l1"]


def test_one_and_two_sided_conventions():
    # a quad seen from below (n·v < 0): one-sided → black (as a one-sided BSDF), two-sided → shaded like the same
    # quad flipped toward the viewer
    env = np.random.default_rng(8).uniform(0.2, 1.0, size=(6, 8, 8, 3))
    cam = PerspectiveCamera(eye=[0.0, -2.0, 0.3], target=[0, 0, 0], up=[0, 1, 0], fov_y_deg=40, width=8, height=8)
    one = rr.render_reference([(_quad(), 0)], cam, env, kd=1.0, ks=0.0, g=0.0)
    assert one.info["n_back_facing"] == one.mask.sum() > 10
    assert np.all(one.image[one.mask] == 0)
    two = rr.render_reference([(_quad(), 0)], cam, env, kd=1.0, ks=0.0, g=0.0, sided="two")
    flipped = trimesh.Trimesh(_quad().vertices, _quad().faces[:, ::-1], process=False)  # normal −y
    want = rr.render_reference([(flipped, 0)], cam, env, kd=1.0, ks=0.0, g=0.0)
    np.testing.assert_allclose(two.image[two.mask], want.image[two.mask], rtol=1e-9)
    with pytest.raises(IBLError, match="sided"):
        rr.render_reference([(_quad(), 0)], cam, env, sided="both")


def test_materials_per_mesh():
    # each material id gets its own (kd, ks, g); equal to rendering each material alone on its pixels
    env = np.random.default_rng(9).uniform(0.2, 1.0, size=(6, 8, 8, 3))
    meshes = _sphere_on_quad(0)
    both = rr.render_reference(meshes, CAM_SHADOW, env, materials={0: (1.0, 0.0, 0.0), 1: (0.0, 1.0, 0.5)},
                               rtol=1e-2)
    ground = rr.render_reference(meshes, CAM_SHADOW, env, kd=1.0, ks=0.0, g=0.0, rtol=1e-2)
    mid = both.gbuffer.material_id
    sel = both.mask & (mid == 0)
    assert sel.sum() > 10 and (both.mask & (mid == 1)).sum() > 5
    np.testing.assert_allclose(both.image[sel], ground.image[sel], rtol=2e-2)  # both within their rtol of exact
    with pytest.raises(IBLError, match="material id"):
        rr.render_reference(meshes, CAM_SHADOW, env, materials={0: (1.0, 0.0, 0.0)})
