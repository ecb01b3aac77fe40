"""Materials of the exact renderers (``--mode reference``, ``--mode mitsuba``) and their lobe weights — defined once.

Two kinds, each a small frozen dataclass with its parameters checked on construction (one-line
:class:`ibl_ref.errors.IBLError` on bad input), both a :class:`BaseMaterial` — the one material type of the lab's
exact renderers, method shading (:mod:`ibl_ref.rendering.method_shading`, :mod:`ibl_ref.rendering.method_budget`),
occlusion images (:mod:`ibl_ref.occlusion.image`) and the experiments.  Other forms (a ``(kd, ks, g)`` tuple, a dict
with ``kind``, a text form) are turned into one at the edges by :func:`as_material` / :func:`parse_material`:

* :class:`PhongMaterial` ``(kd, ks, g)`` — Knuth et al. (2014) Eq. 4–5 as a normalised lobe average:
  ``c = kd·A_1(n) + ks·A_s(r)``, ``s = 1/(1−g)`` (Eq. 3), ``r = 2(n·v)n − v``; the BRDF is the normalised Phong
  BRDF of Kán et al. (2015), Eq. 2, ``f = kd/π + ks·(s+1)/(2π)·max(r·ω,0)^s / (n·ω)``.
* :class:`GGXMaterial` ``(roughness, f0, kd, smith)`` — the microfacet material of today's engines: Lambertian
  ``kd/π`` plus GGX (Trowbridge–Reitz) ``D·G·F / (4 (n·ω)(n·v))`` with ``α = roughness²``
  (:func:`ibl_ref.conventions.ggx_alpha`, Karis 2013), Schlick Fresnel with ``f0`` and Smith masking–shadowing in
  the form ``smith`` (``"height_correlated"``, Heitz 2014 Eq. 99, the default of Filament and UE4; or
  ``"separable"`` G1·G1, what Mitsuba 3 uses).  The BRDF is :func:`ibl_ref.lobes.brdfs.ggx` — this module only
  calls it.

**Lobes.**  Both exact renderers integrate a material as a sum of *lobes*, each with a per-pixel weight
(:meth:`PhongMaterial.lobes`, :meth:`GGXMaterial.lobes`); the reference integrates every lobe with the one
converged quadrature of :mod:`ibl_ref.rendering.reference_converged`, which asks the lobe for exactly one thing,
its weight at quadrature directions ω (:meth:`PhongLobe.weights`, :meth:`GGXLobe.weights`):

* :class:`PhongLobe` ``(s, axis)`` — the clamped cosine lobe ``max(d·ω, 0)^s`` about ``d = n`` (``axis="normal"``:
  the diffuse term, s = 1) or ``d = r`` (``axis="mirror"``: the glossy term).  Its value is the lobe *average*
  ``Σ L V max(d·ω,0)^s [n·ω>0] Ω / Σ max(d·ω,0)^s Ω`` (normalisation over the whole sphere with the same
  quadrature, so L ≡ 1 gives exactly the share of the lobe above the horizon; docs/background.md §8).  The diffuse
  term of both material kinds is this lobe with s = 1 (``kd/π`` with the quadrature's own π).
* :class:`GGXLobe` ``(alpha, f0, smith)`` — the GGX specular term ``f_s(ω, v)·(n·ω)`` with
  ``f_s = D·G·F/(4 (n·ω)(n·v))`` from :func:`ibl_ref.lobes.brdfs.ggx` (``kd=0``).  It is already normalised (its
  integral is the directional albedo), so its value is ``Σ L V f_s (n·ω) Ω`` without a discrete normalisation.
  Unlike the Phong lobes it is not radially symmetric about r: it depends on (n, v, ω), peaks near r, has
  heavy tails over the whole hemisphere of n, and at grazing view it is compressed out of the plane of incidence
  by the factor n·v (ω = 2(v·h)h − v moves by 2(v·h)|dh| when h tilts out of the plane, by 2|dh| in it), which
  :meth:`GGXLobe.width` returns so that the quadrature resolves it.

**What differs per kind** is asked of the material, never of a ``kind`` string: whether it has a diffuse part
(:attr:`~BaseMaterial.has_diffuse`, kd > 0) and a specular part (:attr:`~BaseMaterial.has_specular`: ks > 0 for
Phong, always for GGX), whether it is diffuse only (:attr:`~BaseMaterial.diffuse_only`, what an irradiance method
such as SH9 serves) or a mirror (:attr:`~BaseMaterial.mirror`), its GGX roughness (:attr:`~BaseMaterial.ggx_roughness`,
None for Phong) or Phong exponent (:attr:`PhongMaterial.s`), the material with another Fresnel F0
(:meth:`~BaseMaterial.with_fresnel`), its parameters as JSON (:meth:`~BaseMaterial.params`) and its lobes: those of
the reference renderer (``lobes()``, above) and those of the lab's adaptive texel integral
(:meth:`~BaseMaterial.unoccluded_lobes`, :meth:`~BaseMaterial.unoccluded_lobe`,
:mod:`ibl_ref.rendering.unoccluded_reference`).

**Text syntax** (:func:`parse_material`, the CLI's ``--material`` / ``--ground-material``): ``kd,ks,g`` (Phong,
as before), ``phong:kd=0.2,ks=0.8,g=0.9``, ``ggx:0.3`` (roughness 0.3, f0 0.04, kd 0) or
``ggx:roughness=0.3,f0=1,kd=0.5,smith=separable``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import ClassVar

import numpy as np

from ..conventions import ggx_alpha, lobe_half_angle, phong_exponent
from ..errors import IBLError
from ..lobes.brdfs import ggx
from ..lobes.brdfs import phong_classic

__all__ = ["BaseMaterial", "PhongMaterial", "GGXMaterial", "PhongLobe", "GGXLobe", "MATERIAL_KINDS", "SMITH_FORMS",
           "as_material", "parse_material", "MATERIAL_SYNTAX", "LOBE_TAIL_CUT"]

#: material kinds of :func:`parse_material` / :func:`as_material`
MATERIAL_KINDS = ("phong", "ggx")
#: Smith forms of :class:`GGXMaterial` (those of :func:`ibl_ref.lobes.brdfs.smith_g2`)
SMITH_FORMS = ("height_correlated", "separable")
#: lobe support of the Phong lobes: max(d·ω,0)^s below this (relative to the peak 1) is dropped from the numerator
#: and the normalisation alike (the dropped share is < 4π·1e-8/(2π/(s+1)) ≪ 1e-6 for s ≤ 100)
LOBE_TAIL_CUT = 1e-8
#: the help text of the CLI's material options
MATERIAL_SYNTAX = ("'kd,ks,g' Phong (e.g. 0.2,0.8,0.9; g in [0, 1], 0 = diffuse, 1 = mirror), or "
                   "'ggx:ROUGHNESS' / 'ggx:roughness=R,f0=F,kd=K,smith=S' GGX microfacet (roughness in (0, 1], "
                   "alpha = roughness^2; f0 in [0, 1], default 0.04; kd >= 0 Lambertian, default 0; "
                   "S = height-correlated (default) or separable)")


def _number(name, v, lo=0.0, hi=None, lo_open=False, what=None) -> float:
    try:
        if isinstance(v, (bool, np.bool_)):  # True is not a weight or a roughness (float(True) would be 1)
            raise TypeError
        x = float(v)
    except (TypeError, ValueError):
        raise IBLError(f"{name} must be a number, got {v!r}") from None
    bad = not np.isfinite(x) or (x <= lo if lo_open else x < lo) or (hi is not None and x > hi)
    if bad:
        rng = what or ((f"in {'(' if lo_open else '['}{lo:g}, {hi:g}]") if hi is not None else f">= {lo:g}")
        raise IBLError(f"{name} must be {rng}, got {v!r}")
    return x


def _check_resolved(half_width: float, n_quad: int, what: str, hint: str) -> None:
    texel = (np.pi / 2) / int(n_quad)
    if not half_width >= texel:
        raise IBLError(f"{what}: the lobe's half width {half_width:.3g} rad is narrower than one texel ({texel:.3g} rad) "
                       f"of the reference's largest quadrature level (n_quad_max = {int(n_quad)}): the reference cannot "
                       f"resolve it ({hint})")


# ------------------------------------------------------------------------------------------------
# lobes: the one definition of the weights the reference integrates
# ------------------------------------------------------------------------------------------------
def _dot(a, b):
    """Σ a·b over the last axis without BLAS (the same rounding in every process)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


@dataclass(frozen=True)
class PhongLobe:
    """Clamped cosine lobe ``max(d·ω,0)^s`` about ``d = n`` (``axis="normal"``) or ``d = r`` (``"mirror"``)."""

    s: float
    axis: str = "mirror"
    kind: ClassVar[str] = "phong"
    #: the value is Σ num / Σ norm (a lobe average), not Σ num
    normalised: ClassVar[bool] = True
    #: default largest quadrature face size of the converged reference
    n_quad_max: ClassVar[int] = 256
    #: split cells holding more than a share of the lobe before looking for shadow edges (no: the base level
    #: already has ≥ 2 cells across the half width)
    presplit: ClassVar[bool] = False

    def __post_init__(self):
        s = float(self.s)
        if not (np.isfinite(s) and s >= 1.0):
            raise IBLError(f"Phong exponent s must be finite and >= 1, got {self.s!r}")
        if self.axis not in ("normal", "mirror"):
            raise IBLError(f"Phong lobe axis must be 'normal' or 'mirror', got {self.axis!r}")
        object.__setattr__(self, "s", s)

    def direction(self, n, v):
        """Lobe axis d per pixel: n or r = 2(n·v)n − v."""
        n = np.asarray(n, dtype=np.float64)
        if self.axis == "normal":
            return n
        return 2.0 * _dot(n, v)[..., None] * n - v

    def support(self, n, v, d):
        """(axis (P, 3), half-angle (P,)) of a cone holding every direction with a weight kept (LOBE_TAIL_CUT)."""
        return d, np.full(len(d), float(np.arccos(LOBE_TAIL_CUT ** (1.0 / self.s))))

    def base_half_angle(self) -> float:
        """Half width θ½ (rad) that sets the visibility base level and the first quadrature level."""
        return float(lobe_half_angle(self.s))

    def width(self, n, v, d):
        """Narrowest half width of the lobe per pixel (rad): θ½ for every pixel (radially symmetric)."""
        return np.full(len(d), self.base_half_angle())

    def check_resolved(self, n_quad: int) -> None:
        """One-line :class:`IBLError` if the half width θ½ is narrower than one texel (π/2)/n_quad of the largest
        quadrature level (the converged reference raises its level to the lobe's own start, so this holds there)."""
        _check_resolved(self.base_half_angle(), n_quad, f"Phong s = {self.s:g}", "a larger n_quad_max")

    def weights(self, n, v, d, w, om):
        """Quadrature weights at directions ``w`` (..., 3) of solid angles ``om`` (...): ``(norm, num)`` with
        ``norm = max(d·ω,0)^s Ω`` (the normalisation, whole sphere) and ``num = norm·[n·ω > 0]``; ``n``, ``v``,
        ``d`` broadcast against ``w`` (per pixel)."""
        c = np.maximum(_dot(d, w), 0.0)
        with np.errstate(divide="ignore", under="ignore"):
            f = (c if self.s == 1.0 else np.power(c, self.s)) * om
        return f, f * (_dot(n, w) > 0)

    def loop_params(self) -> np.ndarray:
        """Parameters of the compiled quadrature loop of this kind
        (:func:`ibl_ref.rendering.reference_quadrature_loops.phong_blocks`): ``[s]``."""
        return np.array([self.s], dtype=np.float64)

    def describe(self) -> dict:
        return dict(kind="phong", s=self.s, axis=self.axis)


#: GGX lobe: cosine of the view below which the width stops shrinking (the quadrature cap takes over)
GGX_MIN_COS_VIEW = 1.0 / 64.0


@dataclass(frozen=True)
class GGXLobe:
    """GGX specular term ``f_s(ω, v)·(n·ω)`` of :func:`ibl_ref.lobes.brdfs.ggx` (``kd = 0``; module docstring)."""

    roughness: float
    f0: float = 0.04
    smith: str = "height_correlated"
    kind: ClassVar[str] = "ggx"
    normalised: ClassVar[bool] = False
    n_quad_max: ClassVar[int] = 4096
    presplit: ClassVar[bool] = True

    def __post_init__(self):
        r = _number("GGX roughness", self.roughness, 0.0, 1.0, lo_open=True,
                    what="in (0, 1] (alpha = roughness^2; 0 would be a perfect mirror)")
        ggx_alpha(r)  # the convention's own check
        object.__setattr__(self, "roughness", r)
        object.__setattr__(self, "f0", _number("GGX f0", self.f0, 0.0, 1.0))
        if self.smith not in SMITH_FORMS:
            raise IBLError(f"GGX smith must be one of {', '.join(SMITH_FORMS)}, got {self.smith!r}")

    @property
    def alpha(self) -> float:
        return float(ggx_alpha(self.roughness))

    def direction(self, n, v):
        """Peak direction per pixel: the mirror direction r = 2(n·v)n − v (h = n maximises D)."""
        n = np.asarray(n, dtype=np.float64)
        return 2.0 * _dot(n, v)[..., None] * n - v

    def support(self, n, v, d):
        """The hemisphere of n (the GGX tails reach the horizon: for α ≥ 3e-4 the tail beyond any cone around r
        carries more than 1e-7 of the lobe)."""
        return np.asarray(n, dtype=np.float64), np.full(len(n), np.pi / 2)

    def half_angle_h(self) -> float:
        """Half width at half maximum of D in θh: cos²θh = (1 − √2 α²)/(1 − α²) (π/4 for α ≥ 2^(−1/4))."""
        a2 = self.alpha ** 2
        if a2 >= 1.0 / np.sqrt(2.0):
            return np.pi / 4
        return float(np.arccos(np.sqrt((1.0 - np.sqrt(2.0) * a2) / (1.0 - a2))))

    def base_half_angle(self) -> float:
        """The visibility base level and the block's first quadrature level follow the tails (like a diffuse lobe);
        the core is resolved per cell (:meth:`width`, graded quadrature and pre-split cells)."""
        return np.pi / 3

    def width(self, n, v, d):
        """Narrowest half width (rad) of the lobe in ω per pixel: 2θh½ in the plane of incidence, 2θh½·(n·v) out of
        it (module docstring); n·v is floored at :data:`GGX_MIN_COS_VIEW`."""
        ndv = np.clip(_dot(np.asarray(n, dtype=np.float64), v), GGX_MIN_COS_VIEW, 1.0)
        return 2.0 * self.half_angle_h() * ndv

    @staticmethod
    def roughness_for_width(w: float) -> float:
        """The roughness whose in-plane half width 2θh½ is ``w`` (rad): sin²θh½ = (√2 − 1)α²/(1 − α²) inverted."""
        s2 = np.sin(0.5 * w) ** 2
        return float((s2 / (np.sqrt(2.0) - 1.0 + s2)) ** 0.25)

    def check_resolved(self, n_quad: int) -> None:
        """One-line :class:`IBLError` if the in-plane half width 2θh½ (the lobe's widest core, at n·v = 1) is narrower
        than one texel (π/2)/n_quad of the largest quadrature level: the quadrature's texel centres can then miss
        the peak of D altogether and its change from n_quad/2 to n_quad says nothing (at the default n_quad 4096:
        roughness < 0.0173)."""
        texel = (np.pi / 2) / int(n_quad)
        _check_resolved(2.0 * self.half_angle_h(), n_quad, f"GGX roughness {self.roughness:g}",
                        f"roughness >= {self.roughness_for_width(texel):.3g} at this level, or a larger n_quad_max")

    def weights(self, n, v, d, w, om):
        """``(None, f_s(ω, v)·max(n·ω, 0)·Ω)`` at directions ``w`` (..., 3); no discrete normalisation."""

        with np.errstate(divide="ignore", invalid="ignore", under="ignore", over="ignore"):
            f = ggx(w, v, n, roughness=self.roughness, f0=self.f0, kd=0.0, smith=self.smith)
        return None, f * np.maximum(_dot(n, w), 0.0) * om

    def loop_params(self) -> np.ndarray:
        """Parameters of the compiled quadrature loop of this kind
        (:func:`ibl_ref.rendering.reference_quadrature_loops.ggx_blocks`): ``[α, f0, height-correlated (1/0)]``."""
        return np.array([self.alpha, self.f0, float(self.smith == "height_correlated")], dtype=np.float64)

    def describe(self) -> dict:
        return dict(kind="ggx", roughness=self.roughness, alpha=self.alpha, f0=self.f0, smith=self.smith)


# ------------------------------------------------------------------------------------------------
# materials
# ------------------------------------------------------------------------------------------------
def _unoccluded_reference():
    """:mod:`ibl_ref.rendering.unoccluded_reference`, imported on first use: it loads the prefilters (about 0.4 s),
    which parsing a ``--material`` or the reference renderer need not."""
    from . import unoccluded_reference

    return unoccluded_reference


class BaseMaterial:
    """What every material answers (module docstring): :class:`PhongMaterial` and :class:`GGXMaterial` are the two
    kinds; code that takes a material asks it these questions instead of testing its ``kind``.

    Attributes
    ----------
    kind : str
        ``"phong"`` or ``"ggx"`` (:data:`MATERIAL_KINDS`): the name of the kind in messages, JSON and the text form.
    kd : float
        Weight of the diffuse (Lambertian, clamped-cosine) lobe, ≥ 0.
    """

    kind: ClassVar[str]
    kd: float

    @property
    def has_diffuse(self) -> bool:
        """Whether the material has a diffuse part: kd > 0."""
        return self.kd > 0

    @property
    def has_specular(self) -> bool:
        """Whether the material has a specular part (Phong: ks > 0; GGX: always)."""
        raise NotImplementedError

    @property
    def diffuse_only(self) -> bool:
        """No specular part: all an irradiance method (E(n)/π, e.g. SH9) needs to shade it."""
        return not self.has_specular

    @property
    def mirror(self) -> bool:
        """Whether the specular part is a perfect mirror (a Phong material with g = 1; never GGX: roughness > 0)."""
        return False

    @property
    def ggx_roughness(self) -> float | None:
        """The GGX roughness r (α = r²) of the specular part; None for a Phong material (its lobe has none)."""
        return None

    def with_fresnel(self, f0: float) -> BaseMaterial:
        """This material with Fresnel reflectance ``f0`` at normal incidence, where it has a Fresnel term (GGX);
        a Phong material has none and is returned as it is."""
        return self

    def params(self) -> dict:
        """``{"kind": …, parameter: value, …}`` — the constructor's arguments in their order, JSON-ready; what
        :func:`as_material` takes back (unlike ``describe()``, no derived values such as GGX's alpha)."""
        return {"kind": self.kind, **{f.name: getattr(self, f.name) for f in fields(self)}}

    def _unoccluded_specular(self):
        """``(weight, lobe)`` of the specular part for :mod:`ibl_ref.rendering.unoccluded_reference`."""
        raise NotImplementedError

    def unoccluded_lobes(self) -> dict:
        """The lobes of the lab's adaptive texel integral (:func:`ibl_ref.rendering.unoccluded_reference.integrate`)
        that the material has, with their weights.

        Returns
        -------
        dict
            ``"diffuse"``: ``(kd, PhongLobe(1, "normal"))`` if :attr:`has_diffuse` — the lobe average
            A_1(n) = ∫ L max(n·ω, 0)/π dω; ``"specular"``: ``(weight, lobe)`` if :attr:`has_specular` — Phong:
            ``(ks, PhongLobe(s, "mirror"))``, the lobe average about r clipped to n's hemisphere; GGX:
            ``(1.0, GGXSpecularLobe(roughness, f0, smith))``, f_s(ω, v)(n·ω)⁺ with the Fresnel term in the lobe.
        """
        ur = _unoccluded_reference()
        out = {"diffuse": (self.kd, ur.PhongLobe(1.0, "normal"))} if self.has_diffuse else {}
        if self.has_specular:
            out["specular"] = self._unoccluded_specular()
        return out

    def unoccluded_lobe(self):
        """The one lobe of a material that has at most one (not both a diffuse and a specular part), unweighted:
        the specular lobe of :meth:`unoccluded_lobes` if it has one, else the diffuse lobe (also for a black Phong
        material, kd = ks = 0).  One-line :class:`IBLError` for a material with two lobes."""
        if self.has_diffuse and self.has_specular:
            raise IBLError(f"a {self.kind} material with both a diffuse and a specular part has two lobes, not one: "
                           f"{self.params()}")
        ur = _unoccluded_reference()
        return self.unoccluded_lobes().get("specular", (None, ur.PhongLobe(1.0, "normal")))[1]


@dataclass(frozen=True)
class PhongMaterial(BaseMaterial):
    """``kd·A_1(n) + ks·A_s(r)`` (module docstring); ``kd, ks ≥ 0``, ``g ∈ [0, 1]`` (g = 1: the mirror).

    Examples
    --------
    >>> from ibl_ref.rendering.materials import PhongMaterial
    >>> m = PhongMaterial(kd=0.5, ks=0.0, g=0.0)
    >>> m.has_diffuse, m.has_specular, m.diffuse_only, m.ggx_roughness
    (True, False, True, None)
    >>> PhongMaterial(0.0, 1.0, 0.75).s, PhongMaterial(0.0, 1.0, 0.75).params()
    (4.0, {'kind': 'phong', 'kd': 0.0, 'ks': 1.0, 'g': 0.75})
    """

    kd: float = 0.0
    ks: float = 1.0
    g: float = 0.9
    kind: ClassVar[str] = "phong"

    def __post_init__(self):
        object.__setattr__(self, "kd", _number("kd", self.kd, what="finite and >= 0"))
        object.__setattr__(self, "ks", _number("ks", self.ks, what="finite and >= 0"))
        try:
            if isinstance(self.g, (bool, np.bool_)):
                raise TypeError
            g = float(self.g)
        except (TypeError, ValueError):
            raise IBLError(f"g must be a number in [0, 1], got {self.g!r}") from None
        if not (0.0 <= g <= 1.0):
            raise IBLError(f"g must be in [0, 1] (0 = diffuse, 1 = mirror), got {self.g!r}")
        object.__setattr__(self, "g", g)

    @property
    def s(self) -> float:
        """Phong exponent 1/(1−g) (Eq. 3; inf for the mirror)."""
        return float(phong_exponent(self.g))

    @property
    def mirror(self) -> bool:
        """g = 1: the glossy lobe is one ray along r."""
        return self.g == 1.0

    @property
    def has_specular(self) -> bool:
        """ks > 0."""
        return self.ks > 0

    def _unoccluded_specular(self):
        ur = _unoccluded_reference()
        return self.ks, ur.PhongLobe(self.s, "mirror")

    def lobes(self):
        """[(weight, lobe)]: the diffuse lobe (s = 1 about n) and the glossy lobe (s about r); ``None`` for the
        glossy lobe of the mirror (g = 1: one ray along r)."""
        out = []
        if self.has_diffuse:
            out.append((self.kd, PhongLobe(1.0, "normal")))
        if self.has_specular:
            out.append((self.ks, None if self.mirror else PhongLobe(self.s, "mirror")))
        return out

    def brdf(self, wi, wo, n):
        """f(wi, wo) of Kán et al. (2015) Eq. 2 (``wi`` toward the light, ``wo`` toward the viewer), one-sided."""

        return phong_classic(wi, wo, n, ks=self.ks, s=self.s, kd=self.kd)

    def describe(self) -> dict:
        return dict(kind="phong", kd=self.kd, ks=self.ks, g=self.g)


@dataclass(frozen=True)
class GGXMaterial(BaseMaterial):
    """``kd/π + GGX`` (module docstring); roughness ∈ (0, 1], f0 ∈ [0, 1], kd ≥ 0, smith ∈ :data:`SMITH_FORMS`.

    Examples
    --------
    >>> from ibl_ref.rendering.materials import GGXMaterial
    >>> m = GGXMaterial(roughness=0.3, kd=0.2)
    >>> m.has_diffuse, m.has_specular, m.diffuse_only, m.ggx_roughness
    (True, True, False, 0.3)
    >>> m.with_fresnel(1.0).params()
    {'kind': 'ggx', 'roughness': 0.3, 'f0': 1.0, 'kd': 0.2, 'smith': 'height_correlated'}
    """

    roughness: float = 0.5
    f0: float = 0.04
    kd: float = 0.0
    smith: str = "height_correlated"
    kind: ClassVar[str] = "ggx"

    def __post_init__(self):
        spec = GGXLobe(self.roughness, self.f0, self.smith)  # checks roughness, f0, smith
        object.__setattr__(self, "roughness", spec.roughness)
        object.__setattr__(self, "f0", spec.f0)
        object.__setattr__(self, "kd", _number("kd", self.kd, what="finite and >= 0"))

    @property
    def alpha(self) -> float:
        return float(ggx_alpha(self.roughness))

    @property
    def has_specular(self) -> bool:
        """Always: the GGX term (its directional albedo is > 0 for every f0, Smith's B term)."""
        return True

    @property
    def ggx_roughness(self) -> float:
        """The roughness r."""
        return self.roughness

    def with_fresnel(self, f0: float) -> GGXMaterial:
        """This material with Fresnel F0 = ``f0`` (checked)."""
        return replace(self, f0=f0)

    def _unoccluded_specular(self):
        ur = _unoccluded_reference()
        return 1.0, ur.GGXSpecularLobe(self.roughness, self.f0, self.smith)

    def lobes(self):
        """[(weight, lobe)]: the Lambertian lobe (s = 1 about n, weight kd) and the GGX term (weight 1)."""
        out = [(self.kd, PhongLobe(1.0, "normal"))] if self.has_diffuse else []
        return out + [(1.0, GGXLobe(self.roughness, self.f0, self.smith))]

    def brdf(self, wi, wo, n):
        """f(wi, wo) = :func:`ibl_ref.lobes.brdfs.ggx` (one-sided)."""

        return ggx(wi, wo, n, roughness=self.roughness, f0=self.f0, kd=self.kd, smith=self.smith)

    def describe(self) -> dict:
        return dict(kind="ggx", roughness=self.roughness, alpha=self.alpha, f0=self.f0, kd=self.kd,
                    smith=self.smith)


def as_material(m, where: str = "material"):
    """A :class:`PhongMaterial` or :class:`GGXMaterial` from any accepted form: one of them; a ``(kd, ks, g)``
    triple; a dict with ``kind`` (``"phong"`` / ``"ggx"``) and the parameters; an object with scalar ``kd``,
    ``ks``, ``g`` attributes and no g map (:class:`ibl_ref.rendering.render.Material`); or a
    :func:`parse_material` string."""
    if isinstance(m, BaseMaterial):
        return m
    try:
        if isinstance(m, str):
            return parse_material(m, where)
        if isinstance(m, dict):
            d = dict(m)
            kind = d.pop("kind", "phong")
            d.pop("alpha", None)  # derived, in describe()
            if kind == "phong":
                return PhongMaterial(**d)
            if kind == "ggx":
                return GGXMaterial(**d)
            raise IBLError(f"kind must be one of {', '.join(MATERIAL_KINDS)}, got {kind!r}")
        if all(hasattr(m, k) for k in ("kd", "ks", "g")):
            if getattr(m, "g_map", None) is not None or np.ndim(m.kd) or np.ndim(m.ks):
                raise IBLError("the exact renderers take scalar kd, ks and one g (no RGB weights, no g map)")
            return PhongMaterial(float(m.kd), float(m.ks), float(m.g))
        vals = tuple(m)
    except TypeError as exc:
        raise IBLError(f"{where}: expected a material (kd, ks, g), a dict with 'kind' or a material object, got "
                       f"{m!r} ({exc})") from None
    except IBLError as exc:
        raise IBLError(f"{where}: {exc}") from None
    if len(vals) != 3:
        raise IBLError(f"{where}: a Phong material is (kd, ks, g), got {m!r}")
    try:
        return PhongMaterial(*vals)
    except IBLError as exc:
        raise IBLError(f"{where}: {exc}") from None


def parse_material(text: str, option: str = "--material"):
    """A material from its text form (module docstring): ``kd,ks,g``, ``phong:kd=..,ks=..,g=..``, ``ggx:R`` or
    ``ggx:roughness=R,f0=F,kd=K,smith=S`` (smith: ``height-correlated`` / ``height_correlated`` or
    ``separable``).  One-line :class:`IBLError` naming ``option`` on anything else."""
    t = str(text).strip()
    kind, sep, rest = t.partition(":")
    kind = kind.strip().lower()
    try:
        if not sep:  # plain numbers: the Phong triple
            parts = [p.strip() for p in t.split(",")]
            try:
                vals = [float(p) for p in parts]
            except ValueError:
                vals = None
            if vals is None or len(vals) != 3:
                raise IBLError(f"expected {MATERIAL_SYNTAX}; got {text!r}")
            return PhongMaterial(*vals)
        if kind not in MATERIAL_KINDS:
            raise IBLError(f"unknown material kind {kind!r} (use phong: or ggx:)")
        keys = {"phong": ("kd", "ks", "g"), "ggx": ("roughness", "f0", "kd", "smith")}[kind]
        params = {}
        for i, item in enumerate(p.strip() for p in rest.split(",")):
            if not item:
                raise IBLError(f"empty item in {text!r}")
            k, eq, val = item.partition("=")
            if not eq:  # bare value: positional
                if i >= len(keys):
                    raise IBLError(f"too many values in {text!r}")
                k, val = keys[i], item
            k = k.strip().lower().replace("-", "_")
            if k not in keys:
                raise IBLError(f"unknown {kind} parameter {k!r} (have {', '.join(keys)})")
            if k in params:
                raise IBLError(f"{k} given twice in {text!r}")
            val = val.strip()
            if k == "smith":
                params[k] = val.lower().replace("-", "_")
            else:
                try:
                    params[k] = float(val)
                except ValueError:
                    raise IBLError(f"{k} must be a number, got {val!r}") from None
        if kind == "ggx" and "roughness" not in params:
            raise IBLError("ggx needs a roughness, e.g. ggx:0.3 or ggx:roughness=0.3")
        return (PhongMaterial if kind == "phong" else GGXMaterial)(**params)
    except IBLError as exc:
        raise IBLError(f"{option} {text!r}: {exc}") from None
