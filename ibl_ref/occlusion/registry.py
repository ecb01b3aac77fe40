"""The occlusion methods by name: :data:`OCCLUSION_METHODS` (label →
:class:`~ibl_ref.occlusion.interface.OcclusionMethod`) and :func:`get`.

Each label is a formula of a method module with named parameters; variants of one formula are labels with other
parameter values.  Every label except ``none`` and the PRT and region labels occludes the diffuse term the same
way, f_d = ao (``multibounce-ao``: the multi-bounce ao), so that labels differ only in their specular model.

==================== ======================================== ==================================================
label                f_d / f_s (or what it returns)            module
==================== ======================================== ==================================================
none                 1 / 1                                     :mod:`~ibl_ref.occlusion.ambient_occlusion`
ao-diffuse           ao / 1                                    :mod:`~ibl_ref.occlusion.ambient_occlusion`
ao-both              ao / ao                                   :mod:`~ibl_ref.occlusion.ambient_occlusion`
multibounce-ao       cubic(ao, ρ) per channel / 1              :mod:`~ibl_ref.occlusion.jimenez2016`
lagarde2014-alpha    ao / Frostbite's fit, x = α               :mod:`~ibl_ref.occlusion.lagarde2014`
lagarde2014-r        ao / Frostbite's fit, x = r               :mod:`~ibl_ref.occlusion.lagarde2014`
unreal-so            ao / Unreal's fit (exponent α)            :mod:`~ibl_ref.occlusion.lagarde2014`
horizon-k1.1         ao / saturate(1 + 1.1 R·n_g)²             :mod:`~ibl_ref.occlusion.horizon_occlusion`
horizon-k1.3         ao / saturate(1 + 1.3 R·n_g)²             :mod:`~ibl_ref.occlusion.horizon_occlusion`
godot-horizon        ao / min(1 + R'·n, 1)²                    :mod:`~ibl_ref.occlusion.horizon_occlusion`
gtso-smoothstep-*    ao / cone–cone SO, smoothstep caps        :mod:`~ibl_ref.occlusion.jimenez2016`
gtso-exact-*         ao / cone–cone SO, exact caps             :mod:`~ibl_ref.occlusion.jimenez2016`
filament-gtso        ao / smoothstep SO, x = α, faded          :mod:`~ibl_ref.occlusion.jimenez2016`
prt-3, prt-5         diffuse radiance T·L / 1                  :mod:`~ibl_ref.occlusion.sloan2002`
prt-glossy-3, -5     T·L / lobe average of M·L (radiance)      :mod:`~ibl_ref.occlusion.sloan2002_glossy`
regions-exact        region weights VIS_i                      :mod:`~ibl_ref.occlusion.knuth2014_regions`
==================== ======================================== ==================================================

Adding a method: its module (docstring: paper, section, equation) with a function ``compute(inputs, **params) →
OcclusionResult`` that reads only the inputs it declares, and one :class:`OcclusionMethod` entry below
(``reads_roughness=False`` where the formula never reads the roughness: such a method can also shade a Phong
glossy material, which has no GGX roughness).

Examples
--------
>>> from ibl_ref.occlusion.registry import OCCLUSION_METHODS, get
>>> list(OCCLUSION_METHODS)[:3]
['none', 'ao-diffuse', 'ao-both']
>>> get("filament-gtso").needs, dict(get("filament-gtso").params)["fade_alpha"]
(('ao', 'bent_normal'), (0.01, 0.09))
>>> get("gtao")
Traceback (most recent call last):
...
ibl_ref.errors.IBLError: unknown occlusion method 'gtao'; choose one of none, ao-diffuse, ...
"""

from __future__ import annotations

from ..errors import IBLError
from .ambient_occlusion import ao_factors, no_occlusion
from .horizon_occlusion import godot_horizon_occlusion, horizon_occlusion
from .interface import OcclusionMethod
from .jimenez2016 import gtso, multibounce_ao
from .knuth2014_regions import region_visibility_weights
from .lagarde2014 import specular_occlusion_from_ao
from .sloan2002 import prt_diffuse
from .sloan2002_glossy import prt_glossy

__all__ = ["OCCLUSION_METHODS", "get"]

_GLTF = "Khronos glTF 2.0 specification, Sec. 3.9.3 (occlusionTexture)"
_JIMENEZ = ("Jimenez, Wu, Pesce & Jarabo 2016, Practical Real-Time Strategies for Accurate Indirect Occlusion "
            "(ATVI-TR-16-01)")
_LAGARDE = "Lagarde & de Rousiers 2014, Moving Frostbite to Physically Based Rendering (computeSpecOcclusion)"
_MARMOSET = "Marmoset 2014, Horizon Occlusion for Normal Mapped Reflections"
#: cap-intersection parameter → where its formula comes from
_CAP_SOURCES = {"smoothstep": "Oat & Sander 2007, Ambient Aperture Lighting",
                "exact": "Mazonka 2012, arXiv:1205.1396 (exact)"}
_SLOAN = "Sloan, Kautz & Snyder 2002, Precomputed Radiance Transfer, Sec. 4 (shadowed diffuse transfer)"
_SLOAN_GLOSSY = ("Sloan, Kautz & Snyder 2002, Precomputed Radiance Transfer, Sec. 4 and 5 (shadowed diffuse and "
                 "glossy transfer); Kautz, Sloan & Snyder 2002 (arbitrary BRDFs); GGX as the lab's TV-optimal Phong "
                 "lobe")


def _prt_glossy(order: int) -> OcclusionMethod:
    K = order * order
    return OcclusionMethod(
        f"prt-glossy-{order}", ("sh_transfer", "sh_transfer_matrix", "env_sh"), prt_glossy, {"order": order},
        _SLOAN_GLOSSY,
        f"diffuse radiance = {K}-coefficient transfer · environment SH; specular = Phong lobe (GGX → Phong "
        f"exponent) convolved with the {K}x{K} transfer matrix · environment SH, evaluated at R")


def _gtso(name: str, intersection: str, roughness_input: str, fade_alpha, engines: str) -> OcclusionMethod:
    x = {"alpha": "α", "perceptual": "r"}[roughness_input]
    return OcclusionMethod(
        name, ("ao", "bent_normal"), gtso,
        {"intersection": intersection, "roughness_input": roughness_input, "fade_alpha": fade_alpha},
        f"{_JIMENEZ}, specular occlusion (GTSO); cap intersection: {_CAP_SOURCES[intersection]}{engines}",
        f"f_d = ao; f_s = visible fraction of the specular cone (x = {x}) in the bent-normal visibility cone, "
        f"{intersection} cap intersection" + (", faded for near-mirror α" if fade_alpha else ""))


_METHODS = (
    OcclusionMethod("none", (), no_occlusion, {}, "unoccluded image-based lighting", "f_d = f_s = 1",
                    reads_roughness=False),
    OcclusionMethod("ao-diffuse", ("ao",), ao_factors, {"specular": "none"}, _GLTF,
                    "f_d = ao, f_s = 1: the occlusion map on the diffuse term only", reads_roughness=False),
    OcclusionMethod("ao-both", ("ao",), ao_factors, {"specular": "ao"}, _GLTF, "f_d = f_s = ao",
                    reads_roughness=False),
    OcclusionMethod("multibounce-ao", ("ao", "albedo"), multibounce_ao, {}, f"{_JIMENEZ}, multi-bounce fit",
                    "f_d = max(V, cubic in V with albedo-linear coefficients) per channel, f_s = 1",
                    reads_roughness=False),
    OcclusionMethod("lagarde2014-alpha", ("ao",), specular_occlusion_from_ao,
                    {"exponent": "frostbite", "roughness_input": "alpha"}, f"{_LAGARDE}; Filament, Unity HDRP, Bevy",
                    "f_d = ao, f_s = saturate((n·v + ao)^(2^(-16α - 1)) - 1 + ao)"),
    OcclusionMethod("lagarde2014-r", ("ao",), specular_occlusion_from_ao,
                    {"exponent": "frostbite", "roughness_input": "perceptual"}, f"{_LAGARDE}; three.js",
                    "f_d = ao, f_s = saturate((n·v + ao)^(2^(-16r - 1)) - 1 + ao)"),
    OcclusionMethod("unreal-so", ("ao",), specular_occlusion_from_ao,
                    {"exponent": "unreal", "roughness_input": "alpha"},
                    "Unreal Engine 4, GetSpecularOcclusion (after " + _LAGARDE + ")",
                    "f_d = ao, f_s = saturate((n·v + ao)^α - 1 + ao)"),
    OcclusionMethod("horizon-k1.1", ("geo_normal", "ao"), horizon_occlusion, {"k": 1.1}, _MARMOSET,
                    "f_d = ao, f_s = saturate(1 + 1.1 R·n_g)^2 (R mirror of v about n, n_g geometric normal)",
                    reads_roughness=False),
    OcclusionMethod("horizon-k1.3", ("geo_normal", "ao"), horizon_occlusion, {"k": 1.3}, _MARMOSET,
                    "f_d = ao, f_s = saturate(1 + 1.3 R·n_g)^2 (R mirror of v about n, n_g geometric normal)",
                    reads_roughness=False),
    OcclusionMethod("godot-horizon", ("ao",), godot_horizon_occlusion, {}, f"Godot's variant of {_MARMOSET}",
                    "f_d = ao, f_s = min(1 + R'·n, 1)^2, R' = R bent toward n by r^2"),
    _gtso("gtso-smoothstep-alpha", "smoothstep", "alpha", None, ""),
    _gtso("gtso-smoothstep-r", "smoothstep", "perceptual", None, "; x = r as Unity"),
    _gtso("gtso-exact-alpha", "exact", "alpha", None, ""),
    _gtso("gtso-exact-r", "exact", "perceptual", None, ""),
    _gtso("filament-gtso", "smoothstep", "alpha", (0.01, 0.09), "; Filament's fade smoothstep(0.01, 0.09, α)"),
    OcclusionMethod("prt-3", ("sh_transfer", "env_sh"), prt_diffuse, {"order": 3, "specular": "none"}, _SLOAN,
                    "diffuse radiance = 9-coefficient transfer · environment SH, f_s = 1",
                    param_needs=(("specular", "ao", ("ao",)),), reads_roughness=False),
    OcclusionMethod("prt-5", ("sh_transfer", "env_sh"), prt_diffuse, {"order": 5, "specular": "none"}, _SLOAN,
                    "diffuse radiance = 25-coefficient transfer · environment SH, f_s = 1",
                    param_needs=(("specular", "ao", ("ao",)),), reads_roughness=False),
    _prt_glossy(3),
    _prt_glossy(5),
    OcclusionMethod("regions-exact", ("region_visibility",), region_visibility_weights, {},
                    "Knuth, Altenhofen, Kuijper & Bender 2014, Eq. 5, with exact per-region visible fractions",
                    "region weights = the visible fraction of each environment region", reads_roughness=False),
)

#: label → :class:`~ibl_ref.occlusion.interface.OcclusionMethod`, in the order of the module's table
OCCLUSION_METHODS: dict[str, OcclusionMethod] = {m.name: m for m in _METHODS}


def get(name: str) -> OcclusionMethod:
    """The method registered as ``name``, or a one-line :class:`IBLError` listing the choices.

    Examples
    --------
    >>> from ibl_ref.occlusion.registry import get
    >>> get("ao-both").params["specular"]
    'ao'
    """
    try:
        return OCCLUSION_METHODS[name]
    except (KeyError, TypeError):
        raise IBLError(f"unknown occlusion method {name!r}; choose one of {', '.join(OCCLUSION_METHODS)}") from None
