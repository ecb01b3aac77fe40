"""The declared interface of an occlusion method for image-based lighting: its inputs, its result, and how a result
shades the unoccluded terms.

An **occlusion method** is the per-pixel formula an engine uses to darken its unoccluded image-based lighting: from
a shading frame (normal n, view v, perceptual roughness r) and whatever visibility data the method reads (an
ambient-occlusion value, a bent normal, a geometric normal, visible fractions of environment regions, a PRT
transfer vector) it returns factors that multiply the unoccluded diffuse and specular terms, or weights of
per-region terms, or a diffuse radiance that replaces the unoccluded one.  Every method is an
:class:`OcclusionMethod`: pure NumPy, float64, vectorised over P pixels.

* :class:`OcclusionInputs` — what a method can read (field comments below; ``needs`` names the fields it reads
  beyond ``normal``, ``view`` and ``roughness``);
* :class:`OcclusionResult` — what it returns (only the fields it sets are not ``None``);
* :class:`UnoccludedTerms` — the unoccluded diffuse and specular terms (V ≡ 1) the result is applied to;
* :func:`shade` — the shaded radiance ``(P, C)``:

  ============================== ===============================================================
  result holds                   shaded radiance
  ============================== ===============================================================
  factors (f_d, f_s)             kd·f_d·A_1 + f_s·S (a ``None`` factor means 1)
  ``region_weights`` w           Σ_i w_i (kd·A_1,i + S_i) (Knuth et al. 2014, Eq. 5)
  ``diffuse_radiance`` D         kd·D + f_s·S (PRT: D replaces A_1)
  D and ``specular_radiance`` G  kd·D + w_s·G (glossy PRT: w_s = ``UnoccludedTerms.specular_weight``)
  ============================== ===============================================================

Conventions: directions are unit vectors (within 1e-6); the roughness is the perceptual r ∈ [0, 1] and
α = r² (the convention of :func:`ibl_ref.conventions.ggx_alpha`; r = 0 is accepted here, these formulas have a
mirror limit and never evaluate the GGX NDF whose peak that function's floor protects); ``ao`` is the
cosine-weighted visibility ∫ V max(n·ω, 0)/π dω; SH coefficients use the lab's real SH basis
(:func:`ibl_ref.groundtruth.sh_basis.real_sh`: orthonormal, index l² + l + m, no Condon–Shortley phase).

Examples
--------
>>> import numpy as np
>>> from ibl_ref.occlusion.interface import OcclusionResult, UnoccludedTerms, shade
>>> terms = UnoccludedTerms(kd=0.5, diffuse=np.array([[2.0, 4.0]]), specular=np.array([[1.0, 1.0]]))
>>> shade(OcclusionResult(diffuse_factor=np.array([0.5]), specular_factor=np.array([0.25])), terms)
array([[0.75, 1.25]])
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from types import MappingProxyType
from collections.abc import Callable

import numpy as np

from ..errors import IBLError

__all__ = ["OcclusionInputs", "OcclusionResult", "UnoccludedTerms", "OcclusionMethod", "shade", "alpha_of",
           "reflect_view", "roughness_value", "choice", "smoothstep",
           "INPUT_FIELDS", "UNIT_TOLERANCE", "RANGE_SLACK"]

#: largest accepted deviation from 1 of the length of a direction given as a unit vector
UNIT_TOLERANCE = 1e-6
#: rounding accepted outside [0, 1] for visibilities and albedo (the values are then clipped to [0, 1])
RANGE_SLACK = 1e-12


@dataclass(frozen=True, eq=False)
class OcclusionInputs:
    """Per-pixel inputs of an occlusion method (P pixels); a method reads only the fields its ``needs`` names.

    Parameters
    ----------
    normal, view : array (P, 3)
        Unit shading normal n and unit direction toward the viewer v.
    roughness : float
        Perceptual roughness r ∈ [0, 1] (α = r²); a per-pixel array (P,) is accepted too.
    geo_normal : array (P, 3), optional
        Unit geometric (face) normal n_g.
    ao : array (P,), optional
        Cosine-weighted visibility ∫ V max(n·ω, 0)/π dω ∈ [0, 1].
    bent_normal : array (P, 3), optional
        Unit bent normal, normalize(∫ V ω max(n·ω, 0) dω).
    albedo : array (C,) or (P, C), optional
        Diffuse albedo ρ ∈ [0, 1] (multi-bounce AO).
    region_visibility : array (P, R), optional
        Visible fraction of each environment region ∈ [0, 1].
    sh_transfer : array (P, K), optional
        K = order²: T_k = ∫ V(ω) max(n·ω, 0)/π Y_k(ω) dω (the lab's real SH basis).
    env_sh : array (K', C), optional
        SH coefficients of the radiance, L_k = ∫ L Y_k dω.
    sh_transfer_matrix : array (P, K, K), optional
        K = order²: M_ij = ∫ V(ω) Y_i(ω) Y_j(ω) dω, V = 0 below the shading horizon (glossy PRT).
    """

    normal: np.ndarray
    view: np.ndarray
    roughness: float
    geo_normal: np.ndarray | None = None
    ao: np.ndarray | None = None
    bent_normal: np.ndarray | None = None
    albedo: np.ndarray | None = None
    region_visibility: np.ndarray | None = None
    sh_transfer: np.ndarray | None = None
    env_sh: np.ndarray | None = None
    sh_transfer_matrix: np.ndarray | None = None


#: the optional inputs a method can name in its ``needs`` (every field beyond normal, view and roughness)
INPUT_FIELDS = tuple(f.name for f in dataclasses.fields(OcclusionInputs))[3:]


@dataclass(frozen=True, eq=False)
class OcclusionResult:
    """What a method returns; the fields it does not set stay ``None`` (:func:`shade` says how each is applied).

    Parameters
    ----------
    diffuse_factor, specular_factor : array (P,) or (P, C), optional
        Multiply the unoccluded diffuse / specular term (``None``: 1).
    region_weights : array (P, R), optional
        Weights of the per-region unoccluded terms (Knuth et al. 2014, Eq. 5).
    diffuse_radiance : array (P, C), optional
        Replaces the unoccluded diffuse lobe average A_1(n) (PRT).
    specular_radiance : array (P, C), optional
        The occluded specular lobe average G (the lobe normalised to 1), weighted by
        ``UnoccludedTerms.specular_weight`` in place of the specular term (glossy PRT; only with
        ``diffuse_radiance``).
    """

    diffuse_factor: np.ndarray | None = None
    specular_factor: np.ndarray | None = None
    region_weights: np.ndarray | None = None
    diffuse_radiance: np.ndarray | None = None
    specular_radiance: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class UnoccludedTerms:
    """The unoccluded (V ≡ 1) terms an occlusion result is applied to.

    Parameters
    ----------
    kd : float
        Diffuse weight (0 for a pure specular material).
    diffuse : array (P, C) or None
        A_1(n) = ∫ L max(n·ω, 0)/π dω (unweighted); may be ``None`` only when kd = 0.
    specular : array (P, C)
        The unoccluded specular term (weighted).
    diffuse_regions, specular_regions : array (P, R, C), optional
        The same terms of each region's partial environment (for ``region_weights``); ``diffuse_regions`` may be
        ``None`` only when kd = 0.
    specular_weight : float or array (P,) or (P, 1), optional
        w_s, the weight of the specular lobe average in ``specular`` (Phong: ks; GGX: the directional albedo
        F0·A + B); needed for a result with ``specular_radiance``.
    """

    kd: float
    diffuse: np.ndarray | None
    specular: np.ndarray
    diffuse_regions: np.ndarray | None = None
    specular_regions: np.ndarray | None = None
    specular_weight: np.ndarray | float | None = None


# ----------------------------------------------------------------------------------------------
# helpers shared by the methods
# ----------------------------------------------------------------------------------------------
def alpha_of(roughness):
    """GGX α = r² of perceptual roughness r (the convention of :func:`ibl_ref.conventions.ggx_alpha`, r = 0 allowed).

    Examples
    --------
    >>> alpha_of(0.5)
    0.25
    """
    return roughness * roughness


def roughness_value(inputs: OcclusionInputs, roughness_input: str) -> np.ndarray:
    """The roughness a formula is written in, per pixel (P,): α = r² (``"alpha"``) or r itself (``"perceptual"``).

    Examples
    --------
    >>> import numpy as np
    >>> inp = OcclusionInputs(normal=np.zeros((2, 3)), view=np.zeros((2, 3)), roughness=0.5)
    >>> roughness_value(inp, "alpha"), roughness_value(inp, "perceptual")
    (array([0.25, 0.25]), array([0.5, 0.5]))
    """
    r = np.broadcast_to(np.asarray(inputs.roughness, dtype=np.float64), (len(inputs.normal),))
    return _ROUGHNESS_INPUTS[choice(roughness_input, "roughness_input", tuple(_ROUGHNESS_INPUTS))](r).copy()


def reflect_view(normal: np.ndarray, view: np.ndarray) -> np.ndarray:
    """Mirror direction R = reflect(−v, n) = 2(n·v) n − v, shape (P, 3).

    Examples
    --------
    >>> import numpy as np
    >>> reflect_view(np.array([[0.0, 0.0, 1.0]]), np.array([[0.6, 0.0, 0.8]]))
    array([[-0.6,  0. ,  0.8]])
    """
    nv = np.einsum("pi,pi->p", normal, view)
    return 2.0 * nv[:, None] * normal - view


def choice(value, name: str, choices: tuple):
    """``value`` if it is one of ``choices``, else a one-line :class:`IBLError` naming them (parameter checks)."""
    if not isinstance(value, str) or value not in choices:
        raise IBLError(f"parameter {name} must be one of {', '.join(map(repr, choices))}, got {value!r}")
    return value


def smoothstep(edge0: float, edge1: float, x) -> np.ndarray:
    """GLSL's smoothstep: t²(3 − 2t), t = saturate((x − edge0)/(edge1 − edge0)) (edge0 < edge1).

    Examples
    --------
    >>> smoothstep(0.0, 2.0, np.array([-1.0, 1.0, 3.0]))
    array([0. , 0.5, 1. ])
    """
    t = np.clip((np.asarray(x, dtype=np.float64) - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


#: ``roughness_input`` → the roughness a formula is written in, from perceptual r
_ROUGHNESS_INPUTS = {"alpha": alpha_of, "perceptual": lambda r: r}


# ----------------------------------------------------------------------------------------------
# shading
# ----------------------------------------------------------------------------------------------
def _array(x, what: str, ndim: int, shape: tuple) -> np.ndarray:
    """``x`` as a finite float64 array of ``ndim`` dimensions whose shape matches ``shape`` where it is not None."""
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise IBLError(f"{what} must be an array of numbers, got {type(x).__name__}") from None
    want = "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"
    if a.ndim != ndim or any(s is not None and s != t for s, t in zip(shape, a.shape)):
        raise IBLError(f"{what} has shape {a.shape}, expected {want}")
    if not np.all(np.isfinite(a)):
        raise IBLError(f"{what} holds NaN or infinite values")
    return a


def _factor(f, what: str, P: int, C: int) -> np.ndarray | float:
    """A factor (P,) or (P, C) as an array broadcasting against (P, C); ``None`` → 1."""
    if f is None:
        return 1.0
    a = np.asarray(f, dtype=np.float64)
    if a.ndim == 1:
        return _array(a, what, 1, (P,))[:, None]
    return _array(a, what, 2, (P, C))


def shade(result: OcclusionResult, terms: UnoccludedTerms) -> np.ndarray:
    """The occluded radiance (P, C) of a method's result applied to the unoccluded terms.

    Parameters
    ----------
    result : OcclusionResult
        Factors (``diffuse_factor``, ``specular_factor``; ``None`` means 1), or ``region_weights`` alone, or
        ``diffuse_radiance`` (with an optional ``specular_factor``).
    terms : UnoccludedTerms
        kd, A_1 (P, C), S (P, C); for region weights the per-region terms (P, R, C).

    Returns
    -------
    ndarray (P, C)
        factors: kd·f_d·A_1 + f_s·S; region weights: Σ_i w_i (kd·A_1,i + S_i); diffuse radiance D:
        kd·D + f_s·S.

    Raises
    ------
    IBLError
        A result that mixes region weights with factors, or a diffuse radiance with a diffuse factor; a missing
        term (a diffuse term is needed unless kd = 0, region terms for region weights); shapes that disagree;
        NaN or infinite values.

    Examples
    --------
    One region of weight 1 is the unoccluded radiance:

    >>> import numpy as np
    >>> from ibl_ref.occlusion.interface import OcclusionResult, UnoccludedTerms, shade
    >>> d, s = np.array([[1.0, 2.0]]), np.array([[0.5, 0.5]])
    >>> terms = UnoccludedTerms(kd=1.0, diffuse=d, specular=s, diffuse_regions=d[:, None], specular_regions=s[:, None])
    >>> shade(OcclusionResult(region_weights=np.array([[1.0]])), terms)
    array([[1.5, 2.5]])
    >>> shade(OcclusionResult(diffuse_radiance=np.array([[3.0, 3.0]])), terms)
    array([[3.5, 3.5]])
    """
    if not isinstance(result, OcclusionResult):
        raise IBLError(f"shade: result must be an OcclusionResult, got {type(result).__name__}")
    if not isinstance(terms, UnoccludedTerms):
        raise IBLError(f"shade: terms must be UnoccludedTerms, got {type(terms).__name__}")
    try:
        kd = float(terms.kd)
    except (TypeError, ValueError):
        raise IBLError(f"shade: kd must be a number, got {terms.kd!r}") from None
    if not math.isfinite(kd) or kd < 0:
        raise IBLError(f"shade: kd must be a finite number >= 0, got {kd!r}")
    S = _array(terms.specular, "shade: specular term", 2, (None, None))
    P, C = S.shape

    if result.region_weights is not None:
        if any(f is not None for f in (result.diffuse_factor, result.specular_factor, result.diffuse_radiance,
                                       result.specular_radiance)):
            raise IBLError("shade: a result with region_weights must hold nothing else (no factors, no diffuse "
                           "radiance)")
        if terms.specular_regions is None or (kd != 0 and terms.diffuse_regions is None):
            raise IBLError("shade: region_weights need the region terms specular_regions and diffuse_regions "
                           "(diffuse_regions may be None only when kd = 0)")
        w = _array(result.region_weights, "shade: region_weights", 2, (P, None))
        R = w.shape[1]
        Si = _array(terms.specular_regions, "shade: specular_regions", 3, (P, R, C))
        per_region = Si if kd == 0 else kd * _array(terms.diffuse_regions, "shade: diffuse_regions", 3, (P, R, C)) + Si
        return np.einsum("pr,prc->pc", w, per_region)

    if result.specular_radiance is not None:
        if result.diffuse_radiance is None or result.specular_factor is not None or result.diffuse_factor is not None:
            raise IBLError("shade: a result with specular_radiance must hold diffuse_radiance and no factors")
        if terms.specular_weight is None:
            raise IBLError("shade: specular_radiance needs UnoccludedTerms.specular_weight")
        w = np.asarray(terms.specular_weight, dtype=np.float64)
        w = _factor(w.reshape(-1) if w.ndim else np.full(P, float(w)), "shade: specular_weight", P, C)
        G = _array(result.specular_radiance, "shade: specular_radiance", 2, (P, C))
        D = _array(result.diffuse_radiance, "shade: diffuse_radiance", 2, (P, C))
        return kd * D + w * G
    f_s = _factor(result.specular_factor, "shade: specular_factor", P, C)
    if result.diffuse_radiance is not None:
        if result.diffuse_factor is not None:
            raise IBLError("shade: a result with diffuse_radiance must not hold a diffuse_factor (the radiance "
                           "replaces the diffuse term)")
        D = _array(result.diffuse_radiance, "shade: diffuse_radiance", 2, (P, C))
        return kd * D + f_s * S
    f_d = _factor(result.diffuse_factor, "shade: diffuse_factor", P, C)
    if kd == 0:
        return f_s * S
    if terms.diffuse is None:
        raise IBLError("shade: the diffuse term is None but kd != 0")
    return kd * f_d * _array(terms.diffuse, "shade: diffuse term", 2, (P, C)) + f_s * S


# ----------------------------------------------------------------------------------------------
# input checks
# ----------------------------------------------------------------------------------------------
def _unit_vectors(x, what: str, P: int | None) -> np.ndarray:
    a = _array(x, what, 2, (P, 3))
    err = np.abs(np.linalg.norm(a, axis=1) - 1.0)
    if np.any(err > UNIT_TOLERANCE):
        i = int(np.argmax(err))
        raise IBLError(f"{what} must hold unit vectors (within {UNIT_TOLERANCE:g}); row {i} has length "
                       f"{np.linalg.norm(a[i]):.9g}")
    return a


def _unit_interval(x, what: str, ndim: int, shape: tuple) -> np.ndarray:
    a = _array(x, what, ndim, shape)
    bad = (a < -RANGE_SLACK) | (a > 1.0 + RANGE_SLACK)
    if np.any(bad):
        raise IBLError(f"{what} must lie in [0, 1], got {a[bad].ravel()[0]!r}")
    return np.clip(a, 0.0, 1.0)


def _albedo(x, what: str, P: int) -> np.ndarray:
    shape = (P, None) if np.ndim(x) == 2 else (None,)
    return _unit_interval(x, what + " (shape (C,) or (P, C))", len(shape), shape)


def _sh_coefficients(a: np.ndarray, what: str, axis: int) -> np.ndarray:
    k = a.shape[axis]
    if k < 1 or math.isqrt(k) ** 2 != k:
        raise IBLError(f"{what} holds {k} SH coefficients; expected order² of them (1, 4, 9, 16, 25, ...)")
    return a


def _roughness(r, who: str, P: int):
    try:
        if isinstance(r, (bool, np.bool_)):
            raise TypeError
        a = np.asarray(r, dtype=np.float64)
    except (TypeError, ValueError):
        raise IBLError(f"{who}: roughness must be a number in [0, 1], got {r!r}") from None
    if a.ndim > 1 or (a.ndim == 1 and a.shape != (P,)):
        raise IBLError(f"{who}: roughness must be a number or an array of shape (P,) = ({P},), got shape {a.shape}")
    bad = ~np.isfinite(a) | (a < 0) | (a > 1)
    if np.any(bad):
        raise IBLError(f"{who}: perceptual roughness must lie in [0, 1], got {a[bad].ravel()[0]!r}")
    return float(a) if a.ndim == 0 else a


#: the check of each optional input: (value, message prefix, P) → checked float64 array
_INPUT_CHECKS = {
    "geo_normal": lambda x, what, P: _unit_vectors(x, what, P),
    "bent_normal": lambda x, what, P: _unit_vectors(x, what, P),
    "ao": lambda x, what, P: _unit_interval(x, what, 1, (P,)),
    "region_visibility": lambda x, what, P: _unit_interval(x, what, 2, (P, None)),
    "albedo": _albedo,
    "sh_transfer": lambda x, what, P: _sh_coefficients(_array(x, what, 2, (P, None)), what, 1),
    "env_sh": lambda x, what, P: _sh_coefficients(_array(x, what, 2, (None, None)), what, 0),
    "sh_transfer_matrix": lambda x, what, P: _sh_coefficients(_array(x, what, 3, (P, None, None)), what, 1),
}


def _checked(inputs: OcclusionInputs, needed: tuple, who: str) -> OcclusionInputs:
    """The inputs a method reads, checked and as float64 arrays; every field it does not read set to ``None``."""
    if not isinstance(inputs, OcclusionInputs):
        raise IBLError(f"{who}: inputs must be an OcclusionInputs, got {type(inputs).__name__}")
    for name in needed:
        if getattr(inputs, name) is None:
            raise IBLError(f"{who} needs the input {name} (OcclusionInputs.{name} is None)")
    normal = _unit_vectors(inputs.normal, f"{who}: input normal", None)
    P = normal.shape[0]
    view = _unit_vectors(inputs.view, f"{who}: input view", P)
    values = {name: _INPUT_CHECKS[name](getattr(inputs, name), f"{who}: input {name}", P) for name in needed}
    return OcclusionInputs(normal=normal, view=view, roughness=_roughness(inputs.roughness, who, P), **values)


# ----------------------------------------------------------------------------------------------
# the method record
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class OcclusionMethod:
    """One registered occlusion method: a formula (``compute``) with its named parameters.

    Parameters
    ----------
    name : str
        Registry label.
    needs : tuple of str
        The :class:`OcclusionInputs` fields it reads at its default parameters beyond normal, view and roughness.
    compute : callable
        ``compute(inputs, **params) → OcclusionResult``; receives checked float64 inputs in which every field not
        needed is ``None``.
    params : dict
        Default parameters (name → value); calls may override them, never add new names (stored read-only).
    citation : str
        Paper or engine, with section / equation.
    summary : str
        One line for listings.
    param_needs : tuple of (param, value, inputs)
        Inputs needed in addition when a parameter takes a value other than its default (e.g. PRT's
        ``specular="ao"`` reads ``ao``).
    reads_roughness : bool
        Whether the formula reads the roughness (the GGX perceptual r of :class:`OcclusionInputs`; default True).
        A method that does cannot serve a material without one, a Phong glossy lobe
        (:func:`ibl_ref.occlusion.image.check_request`).

    Calling the method, ``method(inputs, **overrides)``, checks the parameters and the inputs (every needed input
    present, P consistent, unit vectors, visibilities in [0, 1], no NaN or infinity; one-line :class:`IBLError`)
    and returns ``compute``'s :class:`OcclusionResult`.

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.occlusion.interface import OcclusionInputs, OcclusionMethod, OcclusionResult
    >>> def constant(inp, *, f):
    ...     return OcclusionResult(specular_factor=np.full(len(inp.normal), f))
    >>> half = OcclusionMethod("half", (), constant, {"f": 0.5}, "none", "a constant factor")
    >>> inp = OcclusionInputs(normal=np.array([[0.0, 0.0, 1.0]]), view=np.array([[0.0, 0.0, 1.0]]), roughness=0.5)
    >>> half(inp).specular_factor, half(inp, f=0.25).specular_factor
    (array([0.5]), array([0.25]))
    >>> half(inp, g=1)
    Traceback (most recent call last):
    ...
    ibl_ref.errors.IBLError: occlusion method 'half': unknown parameter(s) 'g'; it takes f
    """

    name: str
    needs: tuple
    compute: Callable[..., OcclusionResult]
    params: dict = field(default_factory=dict)
    citation: str = ""
    summary: str = ""
    param_needs: tuple = ()
    reads_roughness: bool = True

    def __post_init__(self):
        object.__setattr__(self, "needs", tuple(self.needs))
        object.__setattr__(self, "params", MappingProxyType(dict(self.params)))
        names = set(self.needs) | {n for _p, _v, extra in self.param_needs for n in extra}
        unknown = sorted(names - set(INPUT_FIELDS))
        if unknown:
            raise IBLError(f"occlusion method {self.name!r}: needs names no OcclusionInputs field: "
                           f"{', '.join(unknown)} (fields: {', '.join(INPUT_FIELDS)})")
        for param, value, _extra in self.param_needs:
            if param not in self.params or self.params[param] == value:
                raise IBLError(f"occlusion method {self.name!r}: param_needs rule on {param}={value!r} must name a "
                               "parameter whose default is another value (needs lists what the defaults read)")

    def __hash__(self):  # params are a read-only mapping (unhashable); equal methods share these three
        return hash((self.name, self.needs, self.compute))

    def inputs_needed(self, **overrides) -> tuple:
        """The input fields read with these parameter overrides: ``needs`` plus those of matching ``param_needs``."""
        params = self._params(overrides)
        extra = tuple(n for p, v, names in self.param_needs if params[p] == v for n in names)
        return tuple(dict.fromkeys(self.needs + extra))

    def _params(self, overrides: dict) -> dict:
        unknown = sorted(set(overrides) - set(self.params))
        if unknown:
            raise IBLError(f"occlusion method {self.name!r}: unknown parameter(s) {', '.join(map(repr, unknown))}; "
                           f"it takes {', '.join(self.params) or 'no parameters'}")
        return {**self.params, **overrides}

    def __call__(self, inputs: OcclusionInputs, **overrides) -> OcclusionResult:
        params = self._params(overrides)
        who = f"occlusion method {self.name!r}"
        checked = _checked(inputs, self.inputs_needed(**overrides), who)
        try:
            result = self.compute(checked, **params)
        except IBLError as exc:
            raise IBLError(f"{who}: {exc}") from None
        if not isinstance(result, OcclusionResult):
            raise IBLError(f"{who}: compute returned {type(result).__name__}, not an OcclusionResult")
        return result

