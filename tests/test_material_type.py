"""The one material type (issue 42, item 0): what a PhongMaterial / GGXMaterial answers, against its definition.

Code that takes a material asks it (``has_diffuse``, ``has_specular``, ``diffuse_only``, ``mirror``,
``ggx_roughness``, ``with_fresnel``, ``params``, ``unoccluded_lobes``, ``unoccluded_lobe``) instead of testing a
``kind`` string; every old form (tuple, dict, text, the Eq. 5 renderer's scalar Material) becomes the same instance
through ``as_material``.
"""

from __future__ import annotations

import json

import pytest

from ibl_ref.errors import IBLError
from ibl_ref.experiments import method_zoo as mz
from ibl_ref.experiments import occlusion_zoo as oz
from ibl_ref.rendering import materials as mt
from ibl_ref.rendering import method_shading as ms
from ibl_ref.rendering import unoccluded_reference as ur
from ibl_ref.rendering.render import Material

DIFFUSE_LOBE = ur.PhongLobe(1.0, "normal")


def test_phong_without_ks_is_diffuse_only():
    m = mt.PhongMaterial(kd=0.7, ks=0.0, g=0.3)
    assert (m.has_diffuse, m.has_specular, m.diffuse_only, m.mirror) == (True, False, True, False)
    assert m.ggx_roughness is None  # a Phong lobe has no GGX roughness
    assert m.with_fresnel(1.0) is m  # and no Fresnel term
    assert m.unoccluded_lobes() == {"diffuse": (0.7, DIFFUSE_LOBE)}
    assert m.unoccluded_lobe() == DIFFUSE_LOBE
    assert ms.serves("cosine", m) and ms.serves("phong", m) and not ms.serves("ggx", m)


def test_phong_glossy_lobe_is_eq3_about_r_clipped():
    m = mt.PhongMaterial(kd=0.0, ks=0.8, g=0.9375)
    assert (m.has_diffuse, m.has_specular, m.diffuse_only) == (False, True, False)
    (w, lobe), = m.unoccluded_lobes().values()
    assert w == 0.8 and lobe == ur.PhongLobe(1.0 / (1.0 - 0.9375), "mirror", clip=True)  # s = 1/(1 - g) = 16
    assert lobe.s == m.s == 16.0
    assert m.unoccluded_lobe() == lobe  # one lobe, unweighted
    assert not ms.serves("cosine", m)


def test_phong_with_both_lobes_and_the_black_and_mirror_edges():
    both = mt.PhongMaterial(kd=0.3, ks=0.6, g=0.5)
    assert both.unoccluded_lobes() == {"diffuse": (0.3, DIFFUSE_LOBE), "specular": (0.6, ur.PhongLobe(2.0, "mirror"))}
    with pytest.raises(IBLError, match="two lobes"):
        both.unoccluded_lobe()
    black = mt.PhongMaterial(kd=0.0, ks=0.0, g=0.5)
    assert (black.has_diffuse, black.has_specular, black.diffuse_only) == (False, False, True)
    assert black.unoccluded_lobes() == {} and black.unoccluded_lobe() == DIFFUSE_LOBE
    mirror = mt.PhongMaterial(kd=0.0, ks=1.0, g=1.0)
    assert mirror.mirror and mirror.has_specular
    with pytest.raises(IBLError, match=r"g must be in \[0, 1\)"):  # no prefilter has the mirror
        ms.shading_material(mirror)


def test_ggx_always_has_a_specular_part():
    m = mt.GGXMaterial(roughness=0.4, f0=0.0, kd=0.5, smith="separable")
    assert (m.has_diffuse, m.has_specular, m.diffuse_only, m.mirror) == (True, True, False, False)
    assert m.ggx_roughness == 0.4
    assert m.unoccluded_lobes() == {"diffuse": (0.5, DIFFUSE_LOBE),
                                    "specular": (1.0, ur.GGXSpecularLobe(0.4, 0.0, "separable"))}  # Fresnel in it
    with pytest.raises(IBLError, match="two lobes"):
        m.unoccluded_lobe()
    bare = mt.GGXMaterial(roughness=0.2, f0=1.0)
    assert not bare.has_diffuse and bare.unoccluded_lobe() == ur.GGXSpecularLobe(0.2, 1.0, "height_correlated")
    assert ms.serves("ggx", m) and not ms.serves("phong", m) and not ms.serves("cosine", m)


def test_with_fresnel_is_a_checked_copy():
    m = mt.GGXMaterial(roughness=0.3, kd=0.1)
    m1 = m.with_fresnel(1.0)
    assert m1 == mt.GGXMaterial(0.3, 1.0, 0.1) and m.f0 == 0.04  # frozen: the original is unchanged
    with pytest.raises(IBLError, match="f0"):
        m.with_fresnel(1.5)


@pytest.mark.parametrize("m", [mt.PhongMaterial(0.2, 0.8, 0.9), mt.PhongMaterial(1.0, 0.0, 0.0),
                               mt.GGXMaterial(0.3, 1.0, 0.0), mt.GGXMaterial(0.6, 0.04, 0.5, "separable")])
def test_params_is_the_json_form_as_material_takes_back(m):
    p = m.params()
    assert list(p) == {"phong": ["kind", "kd", "ks", "g"], "ggx": ["kind", "roughness", "f0", "kd", "smith"]}[m.kind]
    assert p["kind"] == m.kind and json.loads(json.dumps(p)) == p
    assert mt.as_material(p) == m
    # the form the experiments wrote before materials were one type: describe() without the derived alpha
    assert p == {k: v for k, v in m.describe().items() if k != "alpha"}


@pytest.mark.parametrize("want,forms", [
    (mt.PhongMaterial(0.2, 0.8, 0.9), [(0.2, 0.8, 0.9), [0.2, 0.8, 0.9], "0.2,0.8,0.9", "phong:kd=0.2,ks=0.8,g=0.9",
                                       {"kind": "phong", "kd": 0.2, "ks": 0.8, "g": 0.9},
                                       {"kd": 0.2, "ks": 0.8, "g": 0.9},
                                       Material(kd=0.2, ks=0.8, g=0.9)]),
    (mt.GGXMaterial(0.3, 1.0, 0.0), ["ggx:0.3,1", "ggx:roughness=0.3,f0=1,kd=0,smith=height-correlated",
                                     {"kind": "ggx", "roughness": 0.3, "f0": 1.0},
                                     {"kind": "ggx", "roughness": 0.3, "alpha": 0.09, "f0": 1.0, "kd": 0.0}])])
def test_every_old_shape_gives_the_same_instance(want, forms):
    for form in forms:
        got = mt.as_material(form)
        assert type(got) is type(want) and got == want and hash(got) == hash(want), form
        assert ms.shading_material(form) == want
    assert mt.as_material(want) is want and isinstance(want, mt.BaseMaterial)


def test_the_zoos_registries_hold_materials_in_their_old_json_form():
    assert all(isinstance(m, mt.BaseMaterial) for m in (*mz.MATERIALS.values(), *oz.MATERIALS.values()))
    assert list(mz.MATERIALS) == ["diffuse", "ggx0.1", "ggx0.3", "ggx0.6", "phong1", "phong16", "phong256"]
    assert mz.material("ggx0.1", 1.0).params() == {"kind": "ggx", "roughness": 0.1, "f0": 1.0, "kd": 0.0,
                                                   "smith": "height_correlated"}
    assert mz.material("phong16", 1.0).params() == {"kind": "phong", "kd": 0.0, "ks": 1.0, "g": 0.9375}
    assert mz.material("diffuse", 1.0).params() == {"kind": "phong", "kd": 1.0, "ks": 0.0, "g": 0.0}
    assert oz.material("dielectric0.3").params() == {"kind": "ggx", "roughness": 0.3, "f0": 0.04,
                                                     "kd": oz.DIELECTRIC_KD, "smith": "height_correlated"}
    assert oz.material("metal0.6") == mt.GGXMaterial(0.6, 1.0, 0.0)
