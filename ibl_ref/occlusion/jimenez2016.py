"""Multi-bounce ambient occlusion and cone–cone specular occlusion (GTSO): Jimenez, Wu, Pesce & Jarabo 2016,
"Practical Real-Time Strategies for Accurate Indirect Occlusion", Activision technical report ATVI-TR-16-01
(SIGGRAPH 2016 course "Physically Based Shading in Theory and Practice"): its multi-bounce approximation and its
specular occlusion.

**Multi-bounce AO** (``multibounce-ao``, :func:`multibounce_ao`).  The report fits the occlusion of a surface that
also receives the light its occluders reflect (occluders of the same albedo ρ) as a cubic in the visibility V = ao
with coefficients linear in ρ, per colour channel:

    f_d = max(V, ((a·V + b)·V + c)·V),  a = 2.0404ρ − 0.3324,  b = −4.7951ρ + 0.6417,  c = 2.7552ρ + 0.6903,

and f_s = 1.  At V = 1 the cubic is a + b + c = 0.9996 + 0.0005ρ, so the fit itself overshoots 1 by up to 1e-4 for
ρ > 0.8 at V → 1 (the formula is kept as published, not clamped).

**GTSO** (``gtso-*`` and ``filament-gtso``, :func:`gtso`).  The visible directions are modelled as a cone about the
bent normal b whose cosine-weighted solid angle fraction is ao, cos θ_v = √(1 − ao); the specular lobe as a cone
about the mirror direction R = reflect(−v, n) with cos θ_s = 2^(−3.32193·x²) (= 10^(−x²)), x = α (Filament's
roughness, ``roughness_input="alpha"``) or x = r (Unity's, ``"perceptual"``).  The specular occlusion is the
fraction of the specular cone inside the visibility cone,

    SO = Ω(cap_v ∩ cap_s) / Ω(cap_s),  Ω(cap_s) = 2π(1 − cos θ_s),

with the caps' intersection either Oat & Sander 2007's smoothstep approximation (``intersection="smoothstep"``, what
engines evaluate) or its exact closed form (``"exact"``), both from
:mod:`ibl_ref.occlusion.spherical_caps`.  Filament fades the result out for near-mirror lobes,
SO → mix(1, SO, smoothstep(0.01, 0.09, α)) (``fade_alpha=(0.01, 0.09)``: ``filament-gtso``; ``None``: no fade).
At x = 0 the specular cone is a point, and SO is its limit, the indicator of R inside the visibility cone (its
boundary counted inside).  f_d = ao, as for every occluding method of the registry.

Examples
--------
>>> import numpy as np
>>> from ibl_ref.occlusion.interface import OcclusionInputs
>>> from ibl_ref.occlusion.jimenez2016 import gtso, multibounce_ao
>>> z = np.array([[0.0, 0.0, 1.0]])
>>> inp = OcclusionInputs(normal=z, view=z, roughness=0.5, ao=np.array([1.0]), albedo=np.array([0.0, 1.0]),
...                       bent_normal=z)
>>> multibounce_ao(inp).diffuse_factor  # a + b + c at V = 1
array([[1.    , 1.0001]])
>>> gtso(inp, intersection="exact").specular_factor  # the whole specular cone is visible
array([1.])
"""

from __future__ import annotations

import numpy as np

from ..errors import IBLError
from .interface import OcclusionInputs, OcclusionResult, choice, reflect_view, roughness_value, smoothstep
from .spherical_caps import cap_intersection_exact, cap_intersection_smoothstep

__all__ = ["multibounce_ao", "gtso", "specular_cone_cosine", "INTERSECTIONS"]

#: ``intersection`` → the solid angle of two caps' intersection from (cos θ1, cos θ2, cos d)
INTERSECTIONS = {"smoothstep": cap_intersection_smoothstep, "exact": cap_intersection_exact}


def multibounce_ao(inputs: OcclusionInputs) -> OcclusionResult:
    """f_d = max(V, ((a·V + b)·V + c)·V) per channel (module docstring), f_s = 1.

    Parameters
    ----------
    inputs : OcclusionInputs
        Reads ``ao`` (P,) and ``albedo`` (C,) or (P, C).

    Returns
    -------
    OcclusionResult
        ``diffuse_factor`` (P, C) and ``specular_factor`` (P,) = 1.

    Examples
    --------
    Black occluders reflect nothing: the cubic stays below V and f_d = V.

    >>> import numpy as np
    >>> from ibl_ref.occlusion.interface import OcclusionInputs
    >>> z = np.array([[0.0, 0.0, 1.0]])
    >>> inp = OcclusionInputs(normal=z, view=z, roughness=0.5, ao=np.array([0.5]), albedo=np.array([0.0, 0.8]))
    >>> multibounce_ao(inp).diffuse_factor
    array([[0.5     , 0.811125]])
    """
    V = inputs.ao[:, None]
    rho = inputs.albedo
    a = 2.0404 * rho - 0.3324
    b = -4.7951 * rho + 0.6417
    c = 2.7552 * rho + 0.6903
    f_d = np.maximum(V, ((a * V + b) * V + c) * V)
    return OcclusionResult(diffuse_factor=f_d, specular_factor=np.ones(len(V)))


def specular_cone_cosine(x) -> np.ndarray:
    """cos θ_s = 2^(−3.32193·x²) of the specular cone for the roughness x (α or r, per the engine).

    Examples
    --------
    >>> specular_cone_cosine(np.array([0.0, 1.0]))
    array([1.        , 0.09999987])
    """
    x = np.asarray(x, dtype=np.float64)
    return np.exp2(-3.32193 * x * x)


def _fade(fade_alpha):
    """``fade_alpha`` as (lo, hi) with finite lo < hi, or None."""
    if fade_alpha is None:
        return None
    try:
        lo, hi = (float(e) for e in fade_alpha)
    except (TypeError, ValueError):
        raise IBLError(f"parameter fade_alpha must be None or a pair (lo, hi) of α values, got {fade_alpha!r}") \
            from None
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise IBLError(f"parameter fade_alpha must be a pair of finite α values lo < hi, got {fade_alpha!r}")
    return lo, hi


def gtso(inputs: OcclusionInputs, *, intersection: str = "smoothstep", roughness_input: str = "alpha",
         fade_alpha=None) -> OcclusionResult:
    """Cone–cone specular occlusion SO = Ω(cap_v ∩ cap_s)/Ω(cap_s) (module docstring), f_d = ao.

    Parameters
    ----------
    inputs : OcclusionInputs
        Reads ``ao`` (P,) and ``bent_normal`` (P, 3) besides n, v and the roughness.
    intersection : {"smoothstep", "exact"}
        The caps' intersection: Oat & Sander 2007's approximation or the exact closed form.
    roughness_input : {"alpha", "perceptual"}
        The specular cone's x: α = r² (Filament) or r (Unity).
    fade_alpha : (float, float) or None
        Filament's fade SO → mix(1, SO, smoothstep(lo, hi, α)); ``None``: none.

    Returns
    -------
    OcclusionResult
        ``diffuse_factor`` = ao and ``specular_factor`` = SO, each (P,) in [0, 1].

    Examples
    --------
    Filament's fade leaves a near-mirror lobe unoccluded:

    >>> import numpy as np
    >>> from ibl_ref.occlusion.interface import OcclusionInputs
    >>> z = np.array([[0.0, 0.0, 1.0]])
    >>> side = np.array([[1.0, 0.0, 0.0]])
    >>> inp = OcclusionInputs(normal=z, view=z, roughness=0.05, ao=np.array([0.1]), bent_normal=side)
    >>> gtso(inp).specular_factor, gtso(inp, fade_alpha=(0.01, 0.09)).specular_factor
    (array([0.]), array([1.]))
    """
    area = INTERSECTIONS[choice(intersection, "intersection", tuple(INTERSECTIONS))]
    fade = _fade(fade_alpha)
    ao = inputs.ao
    R = reflect_view(inputs.normal, inputs.view)
    cos_v = np.sqrt(1.0 - ao)
    cos_s = specular_cone_cosine(roughness_value(inputs, roughness_input))
    cos_d = np.clip(np.einsum("pi,pi->p", inputs.bent_normal, R), -1.0, 1.0)
    omega_s = 2.0 * np.pi * (1.0 - cos_s)
    cone = omega_s > 0
    so = (cos_d >= cos_v).astype(np.float64)  # the point-cone limit (cos θ_s rounds to 1)
    so[cone] = area(cos_v[cone], cos_s[cone], cos_d[cone]) / omega_s[cone]
    so = np.clip(so, 0.0, 1.0)
    if fade is not None:
        t = smoothstep(fade[0], fade[1], roughness_value(inputs, "alpha"))
        so = (1.0 - t) + t * so
    return OcclusionResult(diffuse_factor=ao.copy(), specular_factor=so)
