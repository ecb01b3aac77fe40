"""Shading by method (ibl_ref.rendering.method_shading) and the per-method error budget
(ibl_ref.rendering.method_budget), against independent routes.

White furnace: for L ≡ c every split-sum method must give c·(F0·A + B) from its DFG table, and c times the GGX
directional albedo of ibl_ref.lobes.brdfs.albedo (a graded Gauss rule in l, accurate to ≈ 1e-8) up to the table's
stated interpolation error.  Eq. 5: a Phong material through the paper's PEMs + VSMs must be render_pem's image
(the renderer of the paper's method).  Budget: the walk ends exactly at the method's image, its signed biases add
up to the method's bias, and in a white furnace every step but the DFG table vanishes.
"""

import numpy as np
import pytest

from ibl_ref.errors import IBLError
from ibl_ref.lobes import brdfs
from ibl_ref.prefilter import karis2013
from ibl_ref.rendering import method_budget as mb
from ibl_ref.rendering import method_shading as ms
from ibl_ref.rendering import unoccluded_reference as ur
from ibl_ref.rendering.sphere_render import orthographic_sphere
from ibl_ref.synthetic import synthetic_envs as se

GGX_SPECS = [ms.MethodSpec("split-sum"), ms.MethodSpec("split-sum-is", {"samples": 8}),
             ms.MethodSpec("split-sum-fis", {"samples": 8}), ms.MethodSpec("ggx-phong-pem")]


def _sphere(px=10):
    mask, n, _ = orthographic_sphere(px)
    return n, np.broadcast_to([0.0, 0.0, 1.0], n.shape).copy()


def _views(m=9):
    # normals at view angles from 0 to grazing (n·v from 1 down to 0.03), view +z
    th = np.linspace(0.0, 1.54, m)
    n = np.stack([np.sin(th), np.zeros(m), np.cos(th)], axis=1)
    return n, np.broadcast_to([0.0, 0.0, 1.0], n.shape).copy()


def _one_line(exc):
    msg = str(exc.value)
    assert msg and "\n" not in msg
    return msg


@pytest.mark.parametrize("spec", GGX_SPECS, ids=lambda s: s.label)
def test_split_sum_white_furnace_through_the_render_path(spec):
    # L ≡ c: every prefilter returns c (a normalised average), so the split sum is c·(F0·A + B) from the table —
    # the true reflected radiance c·albedo (brdfs.albedo, ≈ 1e-8) up to the 64² table's error, computed here from
    # dfg_terms (the quadrature the table samples; within 5e-8 of brdfs.albedo, its own test) -> tolerance
    # |table − dfg_terms| + 1e-7; the table error itself is ≤ 1.8e-2 everywhere (the lowest n·v row; 9.4e-3 at the
    # clamped corner roughness 1, n·v → 1; karis2013's docstring)
    c = np.array([2.0, 1.0, 0.5])
    cube = np.broadcast_to(c, (6, 8, 8, 3)).copy()
    built = ms.build_method(cube, spec)
    n, v = _views()
    nv = n[:, 2]
    for rough in (0.1, 0.3, 0.6, 1.0):
        for f0 in (0.04, 1.0):
            m = {"kind": "ggx", "roughness": rough, "f0": f0}
            img = ms.shade_method(built, m, n, v)
            A, B = built.prefilter.dfg.lookup(nv, rough)
            np.testing.assert_allclose(img, (f0 * A + B)[:, None] * c, rtol=1e-12)
            alb = np.array([brdfs.albedo(brdfs.get_brdf("ggx", roughness=rough, f0=f0), np.arccos(z),
                                         width=min(0.02, rough ** 2 / 4)) for z in nv])
            At, Bt = karis2013.dfg_terms(nv, rough)
            tab = np.abs((f0 * A + B) - (f0 * At + Bt))
            assert np.all(np.abs(img - alb[:, None] * c) <= (tab + 1e-7)[:, None] * c)
            assert np.all(tab <= 1.8e-2)


def test_phong_methods_and_sh9_in_a_constant_environment():
    # normalised lobe averages return the constant (the pyramid's PEMs in float32: rtol 1e-6); SH9's E/π of a
    # constant is exact to rounding (the odd and l = 2 sums vanish by the cube's symmetry)
    c = 1.5
    cube = np.full((6, 8, 8, 3), c)
    n, v = _sphere()
    for spec in (ms.MethodSpec("pyramid", visibility="vsm", n_lights=6), ms.MethodSpec("exact-lobe")):
        built = ms.build_method(cube, spec)
        for m in ({"kind": "phong", "kd": 0.3, "ks": 0.6, "g": 0.9}, {"kind": "phong", "kd": 1.0, "ks": 0.0}):
            np.testing.assert_allclose(ms.shade_method(built, m, n, v), (m["kd"] + m["ks"]) * c, rtol=1e-6)
    sh = ms.build_method(cube, ms.MethodSpec("sh9"))
    np.testing.assert_allclose(ms.shade_method(sh, {"kind": "phong", "kd": 0.7, "ks": 0.0}, n, v), 0.7 * c,
                               rtol=1e-12)
    with pytest.raises(ms.MethodNotApplicable):
        ms.shade_method(sh, {"kind": "phong", "kd": 0.0, "ks": 1.0, "g": 0.5}, n, v)
    with pytest.raises(ms.MethodNotApplicable):
        ms.shade_method(sh, {"kind": "ggx", "roughness": 0.5}, n, v)
    ss = ms.build_method(cube, ms.MethodSpec("split-sum"))
    with pytest.raises(ms.MethodNotApplicable):
        ms.shade_method(ss, {"kind": "phong", "kd": 1.0, "ks": 0.0}, n, v)
    # a GGX material with a diffuse part takes it from the diffuse method (SH9 by default)
    both = ms.build_method(cube, ms.MethodSpec("split-sum"), with_diffuse=True)
    m = {"kind": "ggx", "roughness": 0.5, "f0": 0.04, "kd": 0.5}
    spec_only = ms.shade_method(ss, dict(m, kd=0.0), n, v)
    np.testing.assert_allclose(ms.shade_method(both, m, n, v), spec_only + 0.5 * c, rtol=1e-12)
    with pytest.raises(IBLError, match="with_diffuse"):
        ms.shade_method(ss, m, n, v)


def test_eq5_of_a_phong_material_is_render_pems_image():
    # the paper's renderer (render_pem: PEMs, VSMs, Eq. 5) and the method path through the same PEMs must agree on
    # every front-facing covered pixel (the same eq5_lookups → light_visibilities → shade_eq5)
    from ibl_ref.rendering.raster import prepare_scene, rasterize
    from ibl_ref.rendering.render import Material, render_pem
    from ibl_ref.rendering.scenes import default_camera, teapot_on_ground

    cube = se.env_sky_sun(8)
    meshes = teapot_on_ground()
    sc = prepare_scene(meshes, warn=False)
    cam = default_camera(meshes[:1], size=14)
    gb = rasterize(sc, cam)
    built = ms.build_method(cube, ms.MethodSpec("pyramid", visibility="vsm", n_lights=6))
    m = {"kind": "phong", "kd": 0.2, "ks": 0.8, "g": 0.9}
    k = gb.mask
    img = ms.shade_method(built, m, gb.normal[k], gb.view[k], scene=sc, points=gb.position[k],
                          face_normals=gb.face_normal[k], vsm_resolution=64)
    res = render_pem(meshes, cam, built.regions, materials=Material(0.2, 0.8, 0.9), visibility="vsm",
                     vsm_resolution=64)
    front = np.sum(gb.normal[k] * gb.view[k], axis=1) > 0
    np.testing.assert_allclose(img[front], res.image[k][front], rtol=1e-12, atol=1e-300)
    assert np.all(img[~front] == 0)  # one-sided, as the reference
    # without a scene the visibility is 1: the PEMs sum to the whole map's look-up
    un = ms.shade_method(built, m, gb.normal[k], gb.view[k])
    np.testing.assert_allclose(un[front], res.unshadowed[k][front], rtol=1e-12)


def test_bad_materials_and_parameters_are_one_line_errors():
    for m, word in (({"kind": "ggx", "roughness": 0.0}, "roughness"), ({"kind": "ggx", "roughness": 1.5}, "roughness"),
                    ({"kind": "ggx", "roughness": np.nan}, "roughness"), ({"kind": "ggx", "roughness": 0.3,
                                                                            "f0": -0.1}, "F0"),
                    ({"kind": "ggx", "roughness": 0.3, "f0": 1.1}, "F0"),
                    ({"kind": "ggx", "roughness": 0.3, "smith": "x"}, "smith"),
                    ({"kind": "phong", "g": 1.0}, "g"), ({"kind": "phong", "kd": -1}, "kd"),
                    ({"kind": "lambert"}, "kind")):
        with pytest.raises(IBLError) as e:
            ms.shading_material(m)
        assert word.lower() in _one_line(e).lower()
    cube = se.env_constant(4)
    for call, word in ((lambda: ms.build_method(cube, ms.MethodSpec("split-sum-is", {"samples": 0})), "N >= 1"),
                       (lambda: ms.build_method(cube, ms.MethodSpec("split-sum-fis", {"samples": -2})), "N >= 1"),
                       (lambda: ms.MethodSpec("split-sum", visibility="vsm"), "partial environment maps"),
                       (lambda: ms.MethodSpec("nope"), "unknown prefilter"),
                       (lambda: ms.MethodSpec("pyramid", visibility="rays"), "visibility"),
                       (lambda: ms.MethodSpec("pyramid", n_lights=0), "n_lights")):
        with pytest.raises(IBLError) as e:
            call()
        assert word in _one_line(e)


@pytest.mark.parametrize("label", ["split-sum", "split-sum-is", "split-sum-fis", "ggx-phong-pem"])
def test_budget_walk_ends_at_the_method_and_its_biases_add_up(label):
    cube = se.env_sky_sun(8)
    n, v = _sphere(8)
    spec = ms.MethodSpec(label, {"samples": 16} if label in ("split-sum-is", "split-sum-fis") else {},
                         visibility="vsm" if label == "ggx-phong-pem" else "none", n_lights=6)
    built = ms.build_method(cube, spec)
    m = {"kind": "ggx", "roughness": 0.4, "f0": 1.0}
    ref = ur.integrate(cube, ur.GGXSpecularLobe(0.4, 1.0), n, v, rtol=4e-3).value
    walk = mb.budget_walk(built, m, cube, n, v, exact_unoccluded=ref, rtol=4e-3)
    steps = [s for s, _ in walk]
    want = ["split_sum", "n_v_r"] + (["phong_lobe"] if label == "ggx-phong-pem" else []) + ["prefilter"] + (
        [] if label == "ggx-phong-pem" else ["mip"]) + ["dfg_table"]
    assert steps == want
    np.testing.assert_allclose(walk[-1][1], ms.shade_method(built, m, n, v), rtol=1e-5)  # PEMs float32 vs whole map
    rows = mb.budget_table_rows(ref, walk)
    assert sum(q["bias_increment_frac"] for q in rows) == pytest.approx(rows[-1]["bias_vs_ref_frac"], abs=1e-12)
    assert abs(sum(q["share_of_increments_frac"] for q in rows) - 1) < 1e-12


def test_budget_in_a_white_furnace_leaves_only_the_dfg_table():
    # L ≡ 1: every prefilter and both split-sum factors are exact, so the split_sum, n_v_r, prefilter and mip
    # increments are the exact integrals' own error (≤ their estimate, rtol 1e-3 of the image) and the dfg_table
    # increment is the table's interpolation error, computed here from dfg_terms at the pixels' n·v
    cube = np.ones((6, 8, 8, 3))
    n, v = _views()
    m = {"kind": "ggx", "roughness": 0.3, "f0": 0.04}
    built = ms.build_method(cube, ms.MethodSpec("split-sum"))
    ref = ur.integrate(cube, ur.GGXSpecularLobe(0.3, 0.04), n, v, rtol=1e-3)
    rows = {q["step"]: q for q in mb.budget_table_rows(ref.value, mb.budget_walk(built, m, cube, n, v,
                                                                               exact_unoccluded=ref.value, rtol=1e-3))}
    # split_sum: P = 1 (a normalised average of 1, to the integral's rounding) times dfg_terms vs the adaptive GGX
    # integral: their difference is the integral's error, within its estimate
    assert rows["split_sum"]["rel_l1_increment_frac"] <= ref.info["err_rel_l1"]
    for step in ("n_v_r", "prefilter", "mip"):
        assert rows[step]["rel_l1_increment_frac"] < 1e-12, (step, rows[step])
    A, B = karis2013.dfg_terms(n[:, 2], 0.3)
    a, b = built.prefilter.dfg.lookup(n[:, 2], 0.3)
    table_err = np.abs((0.04 * a + b) - (0.04 * A + B)).sum() / np.abs(ref.value[:, 0]).sum()
    assert rows["dfg_table"]["rel_l1_increment_frac"] == pytest.approx(table_err, rel=1e-3)


def test_importance_sampling_term_falls_with_n():
    # the budget's prefilter step of split-sum-is is the sampling error alone (noise and its O(1/N) ratio bias):
    # it must fall as N grows (Hammersley points: faster than N^-1/2).  Its limit is the n = v = r average of the
    # source's bilinear interpolant (Karis reads the samples bilinearly), not of the piecewise-constant map: on
    # these 8² faces that difference stays (4.3 % at N = 256 against 1.0 % for the exact texel sum's step)
    cube = se.env_sky_sun(8)
    n, v = _sphere(8)
    m = {"kind": "ggx", "roughness": 0.5, "f0": 1.0}
    ref = ur.integrate(cube, ur.GGXSpecularLobe(0.5, 1.0), n, v, rtol=4e-3).value
    cache = {}
    err = []
    for N in (4, 32, 256):
        built = ms.build_method(cube, ms.MethodSpec("split-sum-is", {"samples": N}))
        rows = {q["step"]: q for q in mb.budget_table_rows(ref, mb.budget_walk(built, m, cube, n, v, exact_unoccluded=ref,
                                                                             rtol=4e-3, cache=cache))}
        err.append(rows["prefilter"]["rel_l1_increment_frac"])
    assert err[0] > err[1] > err[2]


def test_budget_refuses_two_lobes_at_once():
    cube = se.env_constant(4)
    n, v = _sphere(6)
    built = ms.build_method(cube, ms.MethodSpec("exact-lobe"))
    with pytest.raises(IBLError, match="one lobe at a time"):
        mb.budget_walk(built, {"kind": "phong", "kd": 0.5, "ks": 0.5, "g": 0.5}, cube, n, v)


@pytest.mark.parametrize("smith", ["separable", "height_correlated"])
def test_exact_dfg_weight_is_the_albedo_of_the_materials_smith_form(smith):
    # dfg_weight(None, …) is the directional albedo of the material's own GGX lobe: against brdfs.albedo of the
    # BRDF with that Smith form (an independent graded Gauss rule, ≈ 1e-8; dfg_terms within 5e-8 of it, karis2013's
    # tests) -> 1e-6; the two Smith forms differ by far more than that at grazing views (checked, so a Smith form
    # ignored would fail), and the occlusion zoo's glossy-PRT weight is the same function
    from ibl_ref.occlusion.image import specular_weight
    from ibl_ref.rendering.materials import GGXMaterial

    n, v = _views()
    nv = n[:, 2]
    m = GGXMaterial(0.4, f0=0.3, smith=smith)
    w = ms.dfg_weight(None, nv, m.roughness, m.f0, m.smith)[:, 0]
    alb = np.array([brdfs.albedo(brdfs.get_brdf("ggx", roughness=0.4, f0=0.3, smith=smith), np.arccos(z),
                                 width=0.02) for z in nv])
    np.testing.assert_allclose(w, alb, atol=1e-6)
    other = "height_correlated" if smith == "separable" else "separable"
    assert np.abs(ms.dfg_weight(None, nv, 0.4, 0.3, other)[:, 0] - w).max() > 1e-3

    class _Pixels:
        normal, view, n_pixels = n, v, len(n)

    np.testing.assert_array_equal(specular_weight(m, _Pixels()), w)
    # edges: n·v ≤ 0 gives 0, n·v a hair above 1 is 1, NaN is a one-line error (not a silent 0)
    np.testing.assert_array_equal(ms.dfg_weight(None, [0.0, -0.5], 0.4, 0.3, smith)[:, 0], [0.0, 0.0])
    np.testing.assert_array_equal(ms.dfg_weight(None, [1.0 + 1e-15], 0.4, 0.3, smith),
                                  ms.dfg_weight(None, [1.0], 0.4, 0.3, smith))
    with pytest.raises(IBLError) as e:
        ms.dfg_weight(None, [0.5, np.nan], 0.4, 0.3, smith)
    assert "NaN" in _one_line(e)
