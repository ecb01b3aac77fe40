"""Shading a material by one IBL method of the prefilter registry — the GGX-era methods beside the paper's Eq. 5.

A *method* (:class:`MethodSpec`) is a registered prefilter (:data:`ibl_ref.prefilter.registry.PREFILTER_METHODS`)
with its parameters, a visibility model and, for the GGX methods, the method of the diffuse part.  Per pixel with
shading normal n, view v (unit, toward the viewer) and r = 2(n·v)n − v:

* **GGX material** (roughness, F0, kd, Smith form) with a GGX method (``split-sum``, ``split-sum-is``,
  ``split-sum-fis``, ``ggx-phong-pem``): the split sum of Karis (2013), Eq. 7 —
  ``c = kd·D(n) + P(r, roughness)·(F0·A + B)(n·v, roughness)``, P the method's prefiltered radiance, A and B from
  the method's DFG table (:func:`ibl_ref.prefilter.karis2013.split_sum`), D the diffuse method's irradiance E/π
  (default ``sh9``, Ramamoorthi & Hanrahan 2001, as engines pair them);
* **Phong material** (kd, ks, g; s = 1/(1 − g)) with a Phong method (``pyramid``, ``exact-lobe``, ``km00-lobes``,
  ``kan2015``, ``cmft``): ``c = kd·P_1(n) + ks·P_s(r)``, the normalised lobe averages (Knuth et al. 2014, Eq. 4–5);
* **diffuse material** (a Phong material with ks = 0) also with the irradiance method ``sh9``: ``c = kd·E(n)/π``.

Visibility (``MethodSpec.visibility``): ``"none"`` — the method has none (its error against an occluded reference
contains the *missing visibility*); ``"vsm"`` — Knuth et al.'s Eq. 5, ``c = Σ_i VIS_i · (kd·PEM_i(n, 0) +
w_s·PEM_i(r, g))`` with one partial environment map per median-cut region (``n_lights``) and one variance shadow map
per region's light, through the one Eq. 5 path of :mod:`ibl_ref.rendering.render` (:func:`~ibl_ref.rendering.render.eq5_lookups`
→ :func:`~ibl_ref.rendering.render.light_visibilities` → :func:`~ibl_ref.rendering.render.shade_eq5`).  For a
Phong material w_s = ks and g its glossiness; for a GGX material through ``ggx-phong-pem`` (the paper's method for
GGX) w_s = F0·A + B per pixel and g = 1 − 1/s(roughness), the mapped Phong exponent
(:func:`ibl_ref.prefilter.ggx_phong_mapping.phong_exponent`).  Without a scene (the unoccluded sphere) VIS ≡ 1.

One-sided, as the reference: pixels with n·v ≤ 0 are black.  A method that does not serve a material kind raises
:class:`MethodNotApplicable` (the experiment's table marks the cell n/a).

Materials are those of the exact renderers (:mod:`ibl_ref.rendering.materials`: ``GGXMaterial(roughness, f0, kd,
smith)``, ``PhongMaterial(kd, ks, g)``); the functions here also take their tuple, dict and text forms, turned into
one by :func:`shading_material`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import IBLError
from ..environment.envmap import unit_directions
from ..knuth2014.median_cut import median_cut
from ..knuth2014.memory_model import library_vsm_bytes
from ..prefilter.karis2013 import split_sum
from ..prefilter.registry import build_prefilter
from ..prefilter.registry import build_region_prefilters
from ..prefilter.registry import get_method
from .materials import BaseMaterial
from .materials import as_material
from .render import eq5_lookups
from .render import light_visibilities
from .render import shade_eq5

__all__ = ["MethodSpec", "BuiltMethod", "MethodNotApplicable", "VISIBILITIES", "shading_material", "serves",
           "build_method", "shade_method", "dfg_weight", "method_nbytes"]

#: visibility models of a method (module docstring)
VISIBILITIES = ("none", "vsm")


class MethodNotApplicable(IBLError):
    """The method does not shade this material kind."""


def shading_material(material) -> BaseMaterial:
    """The :class:`~ibl_ref.rendering.materials.GGXMaterial` or :class:`~ibl_ref.rendering.materials.PhongMaterial`
    of anything :func:`ibl_ref.rendering.materials.as_material` accepts (one of them, a dict with ``kind``,
    ``"ggx:0.3"``, ``(kd, ks, g)``, …), its parameters checked there (roughness in (0, 1], F0 in [0, 1], kd, ks ≥ 0,
    the Smith form); not a mirror (a Phong material needs g < 1 here: a finite exponent; the mirror is no
    prefilter's)."""

    m = as_material(material)
    if m.mirror:
        raise IBLError(f"g must be in [0, 1) (a finite Phong exponent s = 1/(1 - g)), got {m.g!r}")
    return m


@dataclass(frozen=True)
class MethodSpec:
    """One method: ``prefilter`` (registry name) with ``params``, ``visibility`` (``"none"`` / ``"vsm"`` with
    ``n_lights`` median-cut regions), ``diffuse`` (registry name of the diffuse part of GGX materials), ``label``."""

    prefilter: str
    params: dict = field(default_factory=dict)
    visibility: str = "none"
    n_lights: int = 24
    diffuse: str = "sh9"
    label: str = ""

    def __post_init__(self):

        get_method(self.prefilter)
        get_method(self.diffuse)
        if self.visibility not in VISIBILITIES:
            raise IBLError(f"visibility must be one of {', '.join(VISIBILITIES)}, got {self.visibility!r}")
        if self.visibility == "vsm" and not (get_method(self.prefilter).lobe == "phong"
                                             or hasattr(get_method(self.prefilter), "region_prefilters")):
            raise IBLError(f"prefilter {self.prefilter!r} has no partial environment maps for Eq. 5's visibility")
        if isinstance(self.n_lights, bool) or not isinstance(self.n_lights, (int, np.integer)) or self.n_lights < 1:
            raise IBLError(f"n_lights must be an integer >= 1, got {self.n_lights!r}")
        if not self.label:
            object.__setattr__(self, "label", self.prefilter)

    @property
    def lobe(self) -> str:

        return get_method(self.prefilter).lobe


def serves(lobe: str, material) -> bool:
    """Whether a method of lobe family ``lobe`` shades ``material`` (module docstring): a GGX or Phong method the
    materials of its own kind, an irradiance method (``"cosine"``) the diffuse-only materials."""
    m = shading_material(material)
    if lobe in ("ggx", "phong"):
        return m.kind == lobe
    return m.diffuse_only


@dataclass
class BuiltMethod:
    """A method built from one environment: the prefilter, the diffuse method (or None), the PEMs (or None),
    build time (s) and bytes stored."""

    spec: MethodSpec
    prefilter: object
    diffuse: object | None
    regions: object | None
    build_time_s: float
    cube_shape: tuple


def build_method(cube, spec: MethodSpec, *, with_diffuse: bool = False) -> BuiltMethod:
    """Build ``spec`` from ``cube`` (6, N, N, C): the prefilter, its PEMs for ``visibility="vsm"`` (median cut of
    the same map), and the diffuse method when ``with_diffuse`` (GGX materials with kd > 0)."""

    t0 = time.perf_counter()
    a = np.asarray(cube, dtype=np.float64)
    pf = build_prefilter(a, spec.prefilter, **spec.params)
    regions = None
    if spec.visibility == "vsm":
        lights = median_cut(a, spec.n_lights)
        if hasattr(pf, "region_prefilters"):
            regions = pf.region_prefilters(lights)
        else:
            regions = build_region_prefilters(a, lights, spec.prefilter, **spec.params)
    diffuse = build_prefilter(a, spec.diffuse) if (with_diffuse and spec.lobe == "ggx") else None
    return BuiltMethod(spec, pf, diffuse, regions, time.perf_counter() - t0, a.shape)


def dfg_weight(dfg, n_dot_v, roughness, f0, smith: str = "height_correlated") -> np.ndarray:
    """``F0·A + B`` (P, 1) of the split sum at each pixel, 0 where n·v ≤ 0: from a DFG table (the engine's table,
    whatever Smith form it tabulates), or, with ``dfg=None``, the exact quadrature
    (:func:`ibl_ref.prefilter.karis2013.dfg_terms`) of the material's Smith form ``smith`` — the directional albedo
    of its GGX lobe."""

    nv = np.asarray(n_dot_v, dtype=np.float64).reshape(-1)
    return split_sum(np.ones((len(nv), 1)), nv, roughness, f0, dfg, smith=smith)


def _reflect(n, v):
    return 2.0 * np.sum(n * v, axis=1, keepdims=True) * n - v


def method_nbytes(built: BuiltMethod, vsm_resolution: int, vsm_dtype: str = "float32") -> int:
    """Bytes a renderer keeps: the prefilter (or its PEMs, for Eq. 5), the diffuse method, the shadow maps."""

    b = built.regions.nbytes if built.regions is not None else built.prefilter.nbytes
    if built.regions is not None and built.spec.lobe == "ggx":
        b += built.prefilter.dfg.nbytes
    if built.diffuse is not None:
        b += built.diffuse.nbytes
    if built.regions is not None:
        b += library_vsm_bytes(len(built.regions.lights), vsm_resolution, np.dtype(vsm_dtype))
    return int(b)


def shade_method(built: BuiltMethod, material, normals, views, *, scene=None, points=None, face_normals=None,
                 vsm_resolution: int = 256, vsm_dtype: str = "float32", vsm_kw: dict | None = None,
                 timings: dict | None = None) -> np.ndarray:
    """Radiance (P, C) of ``material`` at pixels (normals, views: (P, 3) unit) by the built method (module
    docstring); ``scene`` (prepared meshes), ``points`` and ``face_normals`` (P, 3) give Eq. 5's shadow maps
    (``visibility="vsm"``; without a scene VIS ≡ 1).  :class:`MethodNotApplicable` if the method does not shade
    this material kind."""

    spec = built.spec
    m = shading_material(material)
    if not serves(spec.lobe, m):
        raise MethodNotApplicable(f"method {spec.label!r} ({spec.lobe} lobes) does not shade a {m.kind} material"
                                  + (" with ks > 0" if spec.lobe == "cosine" else ""))
    t0 = time.perf_counter()
    n = unit_directions(np.asarray(normals, dtype=np.float64).reshape(-1, 3), "normals")
    v = unit_directions(np.asarray(views, dtype=np.float64).reshape(-1, 3), "views")
    nv = np.sum(n * v, axis=1)
    front = nv > 0
    r = _reflect(n, v)
    C = built.cube_shape[-1]
    P = len(n)
    out = np.zeros((P, C))
    if spec.lobe == "cosine":
        out = m.kd * built.prefilter.lookup(n, 1.0)
    elif spec.visibility == "vsm":
        out = _shade_eq5(built, m, n, v, nv, r, scene, points, face_normals, vsm_resolution, vsm_dtype,
                         vsm_kw or {})
    elif spec.lobe == "phong":
        if m.has_diffuse:
            out = out + m.kd * built.prefilter.lookup(n, 1.0)
        if m.has_specular:
            out = out + m.ks * built.prefilter.lookup(r, m.s)
    else:  # GGX through the split sum
        w = dfg_weight(built.prefilter.dfg, nv, m.roughness, m.f0, m.smith)
        out = out + w * built.prefilter.lookup(r, m.roughness)
        if m.has_diffuse:
            out = out + m.kd * _diffuse(built).lookup(n, 1.0)
    out = np.where(front[:, None], out, 0.0)
    if not np.all(np.isfinite(out)):
        raise IBLError(f"method {spec.label!r} produced non-finite radiance")
    if timings is not None:
        timings["shade_s"] = timings.get("shade_s", 0.0) + time.perf_counter() - t0
    return out


def _diffuse(built):
    if built.diffuse is None:
        raise IBLError("the GGX material has kd > 0: build the method with with_diffuse=True")
    return built.diffuse


def _shade_eq5(built, m, n, v, nv, r, scene, points, face_normals, vsm_resolution, vsm_dtype, vsm_kw):
    """Eq. 5 through the PEMs: Σ_i VIS_i (kd·PEM_i(n, 0) + w_s·PEM_i(r, g)) (module docstring).  The weights are
    the method's: a Phong method reads the material's own ks and g, a GGX method (through a Phong prefilter) its
    DFG weight and its roughness → exponent mapping (a method serves only materials of its kind, :func:`serves`)."""

    pems = built.regions
    P = len(n)
    kd = m.kd
    if built.spec.lobe == "phong":
        ks, g = m.ks, np.full(P, m.g)
    else:
        s = built.prefilter.exponent(m.roughness)
        ks = dfg_weight(built.prefilter.dfg, nv, m.roughness, m.f0, m.smith)
        g = np.full(P, 1.0 - 1.0 / float(s))
    pem_n, pem_r = eq5_lookups(pems, n, r, g, kd, ks)
    if scene is None:
        vis = np.ones((len(pems.lights), P))
    else:
        if points is None or face_normals is None:
            raise IBLError("Eq. 5's shadow maps need the pixels' points and face normals")
        vis = light_visibilities(scene, points, face_normals, pems.lights, method="vsm",
                                 vsm_resolution=vsm_resolution, vsm_dtype=vsm_dtype, horizon=False, **vsm_kw)
    return shade_eq5(vis, pem_n, pem_r, kd, ks)
