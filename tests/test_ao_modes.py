"""Tests of the Fig. 6 comparison modes (ibl_ref.rendering.ao_modes)."""

import numpy as np
import pytest
import trimesh

from ibl_ref.rendering import ao_modes as am
from ibl_ref.rendering.camera import PerspectiveCamera
from ibl_ref.environment.envmap import cube_solid_angles
from ibl_ref.errors import IBLError

CAM = PerspectiveCamera(eye=[0.0, 2.0, 0.3], target=[0, 0, 0], up=[0, 1, 0], fov_y_deg=40, width=12, height=12)


def _quad(size=2.0):
    s = size / 2
    v = [[-s, 0, -s], [s, 0, -s], [s, 0, s], [-s, 0, s]]
    return trimesh.Trimesh(v, [[0, 2, 1], [0, 3, 2]], process=False)  # normal +y


def _one_light_pems(env):
    """One region = the whole sphere, light straight above (+y)."""
    from ibl_ref.knuth2014.median_cut import LightSet
    from ibl_ref.knuth2014.pem import build_pems

    n = env.shape[1]
    om = cube_solid_angles(n)
    lights = LightSet(directions=np.array([[0.0, 1.0, 0.0]]),
                      rgb=(env * om[..., None]).sum(axis=(0, 1, 2))[None],
                      solid_angle=np.array([4 * np.pi]), energy=np.array([1.0]),
                      regions=np.array([[0, 0, n, 0, n]]), labels=np.zeros((6, n, n), np.int32),
                      variant="per-face", face_size=n)
    return build_pems(env, lights=lights)


def test_one_light_whole_sphere_no_occluder_modes_agree():
    env = np.full((6, 8, 8, 3), 0.6)
    pems = _one_light_pems(env)
    res = am.render_modes([(_quad(), 0)], CAM, env, am.MODES, pems=pems, kd=1.0, ks=0.0, g=0.0,
                          vsm_resolution=32)
    m = res.mask
    assert m.sum() > 30
    # constant environment through normalised filters and lobe averages stays 0.6 (float32 PEM storage: 1e-6)
    for k in am.MODES:
        np.testing.assert_allclose(res.images[k][m], 0.6, rtol=1e-5, err_msg=k)


def test_no_occlusion_equals_full_pyramid_lookup():
    from ibl_ref.knuth2014.gloss_lookup import lookup
    from ibl_ref.knuth2014.pem import build_pems
    from ibl_ref.knuth2014.pyramid import build_pyramid
    from ibl_ref.synthetic.synthetic_envs import make_env

    env = make_env("studio", n=16)
    pems = build_pems(env, n_lights=12)
    res = am.render_modes([(_quad(), 0)], CAM, env, ("no-occlusion",), pems=pems, kd=0.4, ks=0.6, g=0.7)
    m = res.mask
    pyr = build_pyramid(env)
    want = 0.4 * lookup(pyr, res.gbuffer.normal[m], 0.0) + 0.6 * lookup(pyr, res.gbuffer.reflect[m], 0.7)
    # linearity of the pyramid (Sec. 3.1); PEMs are stored in float32 → relative 1e-5
    np.testing.assert_allclose(res.images["no-occlusion"][m], want, rtol=1e-5, atol=1e-6 * want.max())


def test_ours_equals_render_pem_and_ao_bounds():
    from ibl_ref.knuth2014.pem import build_pems
    from ibl_ref.rendering.render import render_pem
    from ibl_ref.synthetic.synthetic_envs import make_env

    mesh = trimesh.util.concatenate([_quad(4.0), trimesh.creation.icosphere(1, 0.5).apply_translation([0, 0.6, 0])])
    env = make_env("sky_sun", n=16)
    pems = build_pems(env, n_lights=12)
    res = am.render_modes(mesh, CAM, env, ("ours", "no-occlusion", "ao", "ao-color"), pems=pems, kd=0.0, ks=1.0,
                          g=0.8, vsm_resolution=64)
    f = render_pem(mesh, CAM, pems, 0.8, vsm_resolution=64)  # ibl_ref.rendering.render's Eq. 5 (glossy only)
    np.testing.assert_allclose(res.images["ours"], f.image, rtol=1e-12, atol=0)
    m = res.mask
    un = res.images["no-occlusion"][m]
    for k in ("ao", "ao-color", "ours"):  # occlusion only removes light
        assert np.all(res.images[k][m] <= un * (1 + 1e-9) + 1e-12), k
    assert (res.images["ao"][m] < 0.95 * un).any()  # the sphere occludes part of the plane


def test_render_mode_and_bad_inputs():
    env = np.full((6, 8, 8, 3), 1.0)
    with pytest.raises(IBLError, match=r"mode must be one of \('ours'"):
        am.render_mode([(_quad(), 0)], env, "magic", camera=CAM)
    with pytest.raises(IBLError, match=r"kd, ks must be finite and"):
        am.render_modes([(_quad(), 0)], CAM, env, ("ours",), kd=-1.0)
    with pytest.raises(IBLError, match=r"g must be in \[0, 1\]"):
        am.render_modes([(_quad(), 0)], CAM, env, ("ours",), g=2.0)
    with pytest.raises(IBLError, match=r"ao_color_variant must be one of \('modulate'"):
        am.render_modes([(_quad(), 0)], CAM, env, ("ao-color",), ao_color_variant="tint")
    bad = env.copy()
    bad[1, 2, 3, 0] = np.inf
    with pytest.raises(IBLError, match=r"environment: 1 non\-finite value\(s\) \(first: Inf"):
        am.render_modes([(_quad(), 0)], CAM, bad, ("no-occlusion",))


def test_fig7_fit_line_recovers_known_line():
    from ibl_ref.experiments.fig7 import fit_line

    x = np.array([6, 12, 24, 48.0])
    f = fit_line(x, 0.3 + 0.05 * x)  # exact line → exact coefficients, R² = 1
    assert f["slope_s_per_light"] == pytest.approx(0.05) and f["intercept_s"] == pytest.approx(0.3)
    assert f["r2"] == pytest.approx(1.0)
