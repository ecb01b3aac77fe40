"""Tests of the exact renderers' materials and lobe weights (ibl_ref.rendering.materials)."""

import numpy as np
import pytest

from ibl_ref.errors import IBLError
from ibl_ref.rendering import materials as mt


def _unit(x):
    x = np.asarray(x, dtype=np.float64)
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def test_parse_forms():
    assert mt.parse_material("0.2,0.8,0.9") == mt.PhongMaterial(0.2, 0.8, 0.9)
    assert mt.parse_material("phong:kd=0.2,ks=0.8,g=0.9") == mt.PhongMaterial(0.2, 0.8, 0.9)
    assert mt.parse_material("ggx:0.3") == mt.GGXMaterial(roughness=0.3)
    m = mt.parse_material(" GGX: roughness=0.3, f0=1, kd=0.5, smith=separable ")
    assert m == mt.GGXMaterial(0.3, 1.0, 0.5, "separable") and m.alpha == pytest.approx(0.09)
    assert mt.parse_material("ggx:0.6,1,0.25").kd == 0.25  # positional: roughness, f0, kd
    assert mt.parse_material("ggx:0.3,smith=height-correlated").smith == "height_correlated"


@pytest.mark.parametrize("text,match", [
    ("ggx:0", r"roughness must be in \(0, 1\]"), ("ggx:1.5", "roughness"), ("ggx:nan", "roughness"),
    ("ggx:roughness=0.3,f0=1.5", r"f0 must be in \[0, 1\]"), ("ggx:0.3,f0=-0.1", "f0"),
    ("ggx:0.3,kd=-1", "kd must be finite"), ("ggx:0.3,smith=foo", "smith"), ("ggx:f0=0.3", "needs a roughness"),
    ("ggx:0.3,alpha=0.1", "unknown ggx parameter"), ("ggx:0.3,0.3,0.3,0.3,0.3", "too many"),
    ("ggx:0.3,,", "empty item"), ("ggx:0.3,roughness=0.4", "twice"), ("ggx:x", "must be a number"),
    ("ward:0.3", "unknown material kind"), ("0.2,0.8", "expected"), ("0.2,0.8,1.5", r"g must be in \[0, 1\]"),
    ("-1,0,0", "kd must be finite")])
def test_parse_errors_are_one_line(text, match):
    with pytest.raises(IBLError, match=match) as e:
        mt.parse_material(text, "--material")
    assert "\n" not in str(e.value) and str(e.value).startswith("--material")


def test_as_material_forms():
    from ibl_ref.rendering.render import Material

    p = mt.PhongMaterial(0.3, 0.7, 0.5)
    assert mt.as_material((0.3, 0.7, 0.5)) == p
    assert mt.as_material(Material(kd=0.3, ks=0.7, g=0.5)) == p
    assert mt.as_material(p.describe()) == p
    gm = mt.GGXMaterial(0.4, 0.5, 0.1, "separable")
    assert mt.as_material(gm.describe()) == gm and mt.as_material("ggx:0.4,0.5,0.1,smith=separable") == gm
    with pytest.raises(IBLError, match="RGB"):
        mt.as_material(Material(kd=(0.1, 0.2, 0.3), ks=0.5, g=0.5))
    with pytest.raises(IBLError, match="kind"):
        mt.as_material({"kind": "ward"})
    with pytest.raises(IBLError, match=r"\(kd, ks, g\)"):
        mt.as_material((1.0, 2.0))


def test_lobes_of_the_materials():
    (k1, l1), (k2, l2) = mt.PhongMaterial(0.3, 0.7, 0.9).lobes()
    assert (k1, l1, k2, l2.axis) == (0.3, mt.PhongLobe(1.0, "normal"), 0.7, "mirror")
    assert l2.s == pytest.approx(10.0)  # Eq. 3
    assert mt.PhongMaterial(0.0, 1.0, 1.0).lobes() == [(1.0, None)]  # the mirror: one ray
    assert mt.GGXMaterial(0.3, 1.0, 0.0).lobes() == [(1.0, mt.GGXLobe(0.3, 1.0))]
    assert [lb.kind for _, lb in mt.GGXMaterial(0.3, 1.0, 0.5).lobes()] == ["phong", "ggx"]


def test_phong_lobe_weights_are_the_definition():
    # max(d·ω,0)^s Ω and the same × [n·ω > 0], broadcast per pixel against many directions
    rng = np.random.default_rng(0)
    n, v = _unit(rng.normal(size=(5, 1, 3))), _unit(rng.normal(size=(5, 1, 3)))
    w, om = _unit(rng.normal(size=(5, 7, 3))), rng.uniform(0.1, 1.0, size=(5, 7))
    lobe = mt.PhongLobe(6.0, "mirror")
    d = lobe.direction(n, v)
    norm, num = lobe.weights(n, v, d, w, om)
    want = np.maximum(np.sum(d * w, axis=-1), 0.0) ** 6.0 * om
    np.testing.assert_allclose(norm, want, rtol=1e-13)
    np.testing.assert_allclose(num, want * (np.sum(n * w, axis=-1) > 0), rtol=1e-13)
    np.testing.assert_allclose(d, 2 * np.sum(n * v, -1, keepdims=True) * n - v, rtol=1e-13)


def test_ggx_lobe_weight_is_the_lab_brdf_and_its_albedo():
    # f_s(ω, v)·(n·ω)·Ω of brdfs.ggx; with Ω of a fine sphere quadrature the weights sum to the directional albedo
    from ibl_ref.lobes.brdfs import albedo, get_brdf, ggx, view_direction

    rng = np.random.default_rng(1)
    n = np.array([[[0.0, 0.0, 1.0]]])
    w = _unit(rng.normal(size=(1, 50, 3)))
    v = view_direction(0.7)[None, None]
    lobe = mt.GGXLobe(0.5, 0.3, "separable")
    norm, num = lobe.weights(n, v, lobe.direction(n, v), w, np.ones((1, 50)))
    assert norm is None
    want = ggx(w, v, n, roughness=0.5, f0=0.3, smith="separable") * np.maximum(w[..., 2], 0)
    np.testing.assert_allclose(num, want, rtol=1e-13)
    from ibl_ref.environment.envmap import cube_solid_angles, texel_directions

    t, om = texel_directions(256).reshape(1, -1, 3), np.asarray(cube_solid_angles(256)).reshape(1, -1)
    _, f = lobe.weights(n, v, lobe.direction(n, v), t, om)
    a = albedo(get_brdf("ggx", roughness=0.5, f0=0.3, smith="separable"), 0.7)
    assert f.sum() == pytest.approx(a, rel=2e-4)  # midpoint rule on 6·256² texels


def test_ggx_lobe_width_narrows_at_grazing_view():
    # half width of D in θh: D(θh½)/D(0) = ½ (closed form), and the ω lobe narrows by n·v out of the plane
    from ibl_ref.lobes.brdfs import ndf

    lobe = mt.GGXLobe(0.3)
    th = lobe.half_angle_h()
    assert ndf(np.cos(th), lobe.alpha) / ndf(1.0, lobe.alpha) == pytest.approx(0.5, rel=1e-9)
    n = np.array([[0.0, 0.0, 1.0]] * 3)
    v = _unit([[0.0, 0.0, 1.0], [np.sin(1.2), 0.0, np.cos(1.2)], [1.0, 0.0, 1e-6]])
    w = lobe.width(n, v, lobe.direction(n, v))
    np.testing.assert_allclose(w[:2], 2 * th * np.array([1.0, np.cos(1.2)]), rtol=1e-12)
    assert w[2] == pytest.approx(2 * th * mt.GGX_MIN_COS_VIEW)
    assert mt.GGXLobe(1.0).half_angle_h() == pytest.approx(np.pi / 4)  # α = 1: D is constant


def test_bad_lobes():
    with pytest.raises(IBLError, match="Phong exponent"):
        mt.PhongLobe(0.5)
    with pytest.raises(IBLError, match="Phong exponent"):
        mt.PhongLobe(np.inf)
    with pytest.raises(IBLError, match="axis"):
        mt.PhongLobe(2.0, "view")
    with pytest.raises(IBLError, match="roughness"):
        mt.GGXLobe(0.0)
