"""The adaptive texel integral (ibl_ref.rendering.unoccluded_reference) against independent routes: uniform
supersampling of the cube (nearest-texel copies, a dense sum written out here), the white furnace (L ≡ 1 gives the
GGX directional albedo of ibl_ref.lobes.brdfs.albedo, a graded Gauss rule in l), the Phong lobe average of a linear
environment in closed form (synthetic_envs.gradient_lobe_average), and its own refinement."""

import numpy as np
import pytest

from ibl_ref.environment import envmap
from ibl_ref.errors import IBLError
from ibl_ref.lobes import brdfs
from ibl_ref.rendering import unoccluded_reference as ur
from ibl_ref.synthetic import synthetic_envs as se


def _pixels(m=9, seed=0):
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(m, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t = rng.normal(size=(m, 3))
    t -= np.sum(t * n, axis=1, keepdims=True) * n
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    theta = np.linspace(0.05, 1.45, m)  # view angles from normal to grazing
    v = np.cos(theta)[:, None] * n + np.sin(theta)[:, None] * t
    return n, v


def _uniform(cube, lobe, n, v, k):
    # dense sum over the texel centres of the cube's nearest-texel copy at k x its face size
    a = np.repeat(np.repeat(cube, k, axis=1), k, axis=2)
    m = a.shape[1]
    d = envmap.texel_directions(m).reshape(-1, 3)
    om = envmap.cube_solid_angles(m).reshape(-1)
    rad = a.reshape(-1, a.shape[-1])
    out = []
    for p in range(len(n)):
        wn, wd = lobe.weights(np.broadcast_to(n[p], d.shape), np.broadcast_to(v[p], d.shape), d)
        val = (wn * om) @ rad
        out.append(val / np.sum(wd * om) if wd is not None else val)
    return np.array(out)


@pytest.mark.parametrize("lobe", [ur.GGXSpecularLobe(0.6, 0.04), ur.GGXSpecularLobe(0.35, 1.0),
                                  ur.PhongLobe(8.0, "mirror", clip=True), ur.SplitSumLobe(0.5),
                                  ur.NVRKernelLobe(0.5), ur.PhongLobe(1.0, "normal")],
                         ids=["ggx0.6", "ggx0.35", "phong8", "splitsum", "nvr", "diffuse"])
def test_against_uniform_supersampling(lobe):
    # the map: a studio with bright area lights (4² faces, so the copies can be fine); the uniform sums at k = 32
    # and 64 differ by their own error e_u; the adaptive value must be within its estimate + 2 e_u of k = 64
    cube = se.env_studio(4)
    n, v = _pixels()
    res = ur.integrate(cube, lobe, n, v, rtol=2e-4)
    u32, u64 = _uniform(cube, lobe, n, v, 32), _uniform(cube, lobe, n, v, 64)
    e_u = np.abs(u64 - u32).mean(axis=1)
    got = np.abs(res.value - u64).mean(axis=1)
    assert np.all(got <= res.err + 2 * e_u + 1e-12 * np.abs(u64).mean(axis=1)), (got, res.err, e_u)
    # and the estimate means something: the summed error is small against the image
    assert res.info["err_rel_l1"] < 2e-3 and res.info["converged"]


@pytest.mark.parametrize("rough", [0.1, 0.3, 0.6, 1.0])
def test_white_furnace_gives_the_ggx_albedo(rough):
    # L ≡ 1: the GGX term's integral is the directional albedo (F0 = 1 and 0.04); brdfs.albedo is accurate to
    # ≈ 1e-8 (its own test) -> the difference must be within the integral's own estimate
    n, v = _pixels(7, seed=3)
    one = np.ones((6, 8, 8, 1))
    for f0 in (1.0, 0.04):
        res = ur.integrate(one, ur.GGXSpecularLobe(rough, f0), n, v, rtol=1e-4)
        theta = np.arccos(np.clip(np.sum(n * v, axis=1), -1, 1))
        alb = np.array([brdfs.albedo(brdfs.get_brdf("ggx", roughness=rough, f0=f0), t,
                                     width=min(0.02, rough ** 2 / 4)) for t in theta])
        assert np.all(np.abs(res.value[:, 0] - alb) <= res.err + 1e-7), (res.value[:, 0] - alb, res.err)


def test_phong_lobe_of_a_linear_environment_has_the_closed_form():
    # L = a + b·ω is not piecewise constant; its nearest-texel cube at 64² faces is within 1e-3 of it, and the
    # unclipped lobe average of the linear function is a + (s+1)/(s+2) b·r (Funk–Hecke band 1)
    a, b = 1.0, np.array([0.3, 0.5, -0.2])
    cube = se.env_gradient(64, a=a, b=b, sample="average")[..., :1]
    n, v = _pixels(5, seed=1)
    for s in (1.0, 20.0):
        res = ur.integrate(cube, ur.PhongLobe(s, "mirror", clip=False), n, v, rtol=1e-4)
        r = 2 * np.sum(n * v, axis=1, keepdims=True) * n - v
        ref = a + (s + 1) / (s + 2) * (r @ b)
        np.testing.assert_allclose(res.value[:, 0], ref, atol=2e-3)


def test_refinement_converges_and_the_estimate_bounds_the_change():
    # a narrow GGX lobe (roughness 0.1) under a small bright sun: halving rtol changes the image by less than the
    # coarser run's own estimate
    cube = se.env_sky_sun(8)
    n, v = _pixels(6, seed=2)
    lobe = ur.GGXSpecularLobe(0.1, 1.0)
    c = ur.integrate(cube, lobe, n, v, rtol=1e-3)
    f = ur.integrate(cube, lobe, n, v, rtol=2.5e-4)
    d = np.abs(c.value - f.value).mean(axis=1)
    assert d.sum() <= c.err.sum()
    assert f.info["cells_per_pixel"] > c.info["cells_per_pixel"]


def test_bad_input():
    n, v = _pixels(2)
    for bad in ((lambda: ur.GGXSpecularLobe(0.0)), (lambda: ur.GGXSpecularLobe(1.2)),
                (lambda: ur.GGXSpecularLobe(0.5, f0=1.5)), (lambda: ur.GGXSpecularLobe(0.5, f0=-0.1)),
                (lambda: ur.PhongLobe(0.5)), (lambda: ur.integrate(np.ones((6, 4, 4, 3)), ur.PhongLobe(2), n, v, rtol=0)),
                (lambda: ur.integrate(np.ones((6, 4, 5, 3)), ur.PhongLobe(2), n, v))):
        with pytest.raises(IBLError) as e:
            bad()
        assert "\n" not in str(e.value)
