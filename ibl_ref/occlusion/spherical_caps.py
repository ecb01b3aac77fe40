"""Solid angle of the intersection of two spherical caps: the exact closed form and the smoothstep approximation.

A spherical cap of half-angle θ about a unit axis is the set of directions within θ of the axis; its solid angle is
2π(1 − cos θ).  Both functions take the cosines of the two half-angles θ1, θ2 and of the angle d between the axes
(any θ ∈ [0, π], so caps larger than a hemisphere too) and return the solid angle of the intersection in sr.

**Exact** (:func:`cap_intersection_exact`; the closed form of Mazonka 2012, "Solid angle of conical surfaces,
polyhedral cones, and intersecting spherical caps", arXiv:1205.1396, section on intersecting spherical caps —
derived here independently).  Four cases:

* containment, d ≤ |θ1 − θ2|: the smaller cap, 2π(1 − max(cos θ1, cos θ2));
* disjoint, d ≥ θ1 + θ2: 0;
* covering, d ≥ 2π − θ1 − θ2 (the complements, caps of half-angles π − θ_i about the opposite axes, are disjoint, so
  the union is the whole sphere): Ω1 + Ω2 − 4π = −2π(cos θ1 + cos θ2);
* otherwise the two boundary circles cross at two points P, P' and the intersection is a lens bounded by one arc of
  each circle.  The Gauss–Bonnet theorem on the lens (geodesic curvature cot θ_i on circle i, so ∫ k_g ds over an
  arc of azimuthal span 2φ_i is 2φ_i cos θ_i; interior angle π − γ at P and P') gives

      Ω = 2(π − γ) − 2φ1 cos θ1 − 2φ2 cos θ2 = 2 [φ1 (1 − cos θ1) + φ2 (1 − cos θ2) − E],

  where φ1, φ2, γ are the angles at the axes a1, a2 and at P of the spherical triangle (a1, a2, P) with sides
  θ2 (a2P), θ1 (a1P), d (a1a2), and E = φ1 + φ2 + γ − π its spherical excess.  (The second form reads: two cap
  sectors of azimuthal spans 2φ_i less the kite a1 P a2 P'.)

Evaluation for float64 accuracy: angles from cosines as θ = 2 atan2(√(1 − c), √(1 + c)) (1 ∓ c are exact near
c = ±1, unlike arccos); the triangle's angles by the half-angle formulas
tan(φ1/2) = √(sin(s − θ1) sin(s − d) / (sin s sin(s − θ2))), s = (θ1 + θ2 + d)/2 (and cyclically), and E by
L'Huilier's theorem tan(E/4) = √(tan(s/2) tan((s − θ1)/2) tan((s − θ2)/2) tan((s − d)/2)), both free of the
cancellation of arccos of the cosine rule for thin or small triangles.  In the lens case the strict inequalities
make every sine positive and s < π.  The lens tends to the containment and disjoint values at tangency, so the
result is continuous across the case boundaries.

**Smoothstep** (:func:`cap_intersection_smoothstep`; Oat & Sander 2007, "Ambient aperture lighting", I3D, Sec. on
the spherical cap intersection; the form engines use for Jimenez et al. 2016's cone–cone specular occlusion):
exact in the containment and disjoint cases (the same values as above, decided by the same angle comparisons), and
between them the smaller cap's solid angle times the smoothstep polynomial x²(3 − 2x) of
x = 1 − saturate((d − |θ1 − θ2|)/(θ1 + θ2 − |θ1 − θ2|)).  It has no covering case.

Examples
--------
Two hemispheres whose axes are d apart meet in a lune of 2(π − d):

>>> import numpy as np
>>> from ibl_ref.occlusion.spherical_caps import cap_intersection_exact, cap_intersection_smoothstep
>>> d = np.pi / 3
>>> float(cap_intersection_exact(0.0, 0.0, np.cos(d))), 2 * (np.pi - d)
(4.18879020478639..., 4.18879020478639...)
>>> float(cap_intersection_smoothstep(0.0, 0.0, np.cos(d)))
4.65421133865155...
"""

from __future__ import annotations

import numpy as np

from ..errors import IBLError

__all__ = ["cap_intersection_exact", "cap_intersection_smoothstep", "cap_solid_angle", "COSINE_SLACK"]

_TWO_PI = 2.0 * np.pi
#: rounding accepted outside [−1, 1] for a cosine (then clipped)
COSINE_SLACK = 1e-12


def _cosines(cos1, cos2, cos_d):
    """The three cosines as broadcast float64 arrays, checked (finite, in [−1, 1] up to rounding) and clipped."""
    out = []
    for name, c in (("cos1", cos1), ("cos2", cos2), ("cos_d", cos_d)):
        try:
            a = np.asarray(c, dtype=np.float64)
        except (TypeError, ValueError):
            raise IBLError(f"cap intersection: {name} must be a number or an array of numbers, got {c!r}") from None
        bad = ~np.isfinite(a) | (np.abs(a) > 1.0 + COSINE_SLACK)
        if np.any(bad):
            raise IBLError(f"cap intersection: {name} must be a cosine in [-1, 1], got {a[bad].ravel()[0]!r}")
        out.append(np.clip(a, -1.0, 1.0))
    try:
        return np.broadcast_arrays(*out)
    except ValueError:
        raise IBLError("cap intersection: cos1, cos2 and cos_d do not broadcast to one shape "
                       f"({', '.join(str(a.shape) for a in out)})") from None


def _angle(c: np.ndarray) -> np.ndarray:
    """arccos(c) ∈ [0, π], accurate to relative rounding also near c = ±1."""
    return 2.0 * np.arctan2(np.sqrt(1.0 - c), np.sqrt(1.0 + c))


def _cases(c1, c2, cd):
    """Angles and the containment / disjoint masks shared by both functions (so that they agree exactly there)."""
    t1, t2, d = _angle(c1), _angle(c2), _angle(cd)
    inside = d <= np.abs(t1 - t2)
    apart = ~inside & (d >= t1 + t2)
    return t1, t2, d, inside, apart


def _result(x: np.ndarray):
    return x[()] if x.ndim == 0 else x


def cap_solid_angle(cos_theta):
    """Solid angle 2π(1 − cos θ) of a cap of half-angle θ (sr).

    Examples
    --------
    >>> float(cap_solid_angle(0.0)) / np.pi
    2.0
    """
    return _TWO_PI * (1.0 - np.asarray(cos_theta, dtype=np.float64))


def cap_intersection_exact(cos1, cos2, cos_d):
    """Solid angle (sr) of the intersection of two spherical caps, in closed form (module docstring).

    Parameters
    ----------
    cos1, cos2 : float or array_like
        Cosines of the caps' half-angles θ1, θ2 ∈ [0, π] (so in [−1, 1]; rounding of 1e-12 beyond is clipped).
    cos_d : float or array_like
        Cosine of the angle d ∈ [0, π] between the caps' axes.  The three broadcast together.

    Returns
    -------
    ndarray or numpy.float64
        The solid angle, in [0, min(Ω1, Ω2)], of the broadcast shape.

    Raises
    ------
    IBLError
        A cosine outside [−1, 1], NaN or infinite; shapes that do not broadcast.

    Examples
    --------
    Containment (the smaller cap), disjoint caps (0), and two caps larger than a hemisphere about opposite axes,
    whose union is the whole sphere (Ω1 + Ω2 − 4π):

    >>> import numpy as np
    >>> from ibl_ref.occlusion.spherical_caps import cap_intersection_exact
    >>> cap_intersection_exact([0.9, 0.9, -0.5], [0.0, 0.9, -0.5], [1.0, -1.0, -1.0]) / np.pi
    array([0.2, 0. , 2. ])
    """
    c1, c2, cd = _cosines(cos1, cos2, cos_d)
    t1, t2, d, inside, apart = _cases(c1, c2, cd)
    cover = ~inside & ~apart & (d >= 2.0 * np.pi - t1 - t2)
    lens = ~(inside | apart | cover)
    out = np.zeros(c1.shape)
    out[inside] = _TWO_PI * (1.0 - np.maximum(c1, c2)[inside])
    out[cover] = -_TWO_PI * (c1 + c2)[cover]
    if np.any(lens):
        a1, a2, ad = t1[lens], t2[lens], d[lens]
        s = 0.5 * (a1 + a2 + ad)
        sin_s, sin_1, sin_2, sin_d = np.sin(s), np.sin(s - a1), np.sin(s - a2), np.sin(s - ad)
        phi1 = 2.0 * np.arctan2(np.sqrt(sin_1 * sin_d), np.sqrt(sin_s * sin_2))
        phi2 = 2.0 * np.arctan2(np.sqrt(sin_2 * sin_d), np.sqrt(sin_s * sin_1))
        excess = 4.0 * np.arctan(np.sqrt(np.tan(0.5 * s) * np.tan(0.5 * (s - a1)) * np.tan(0.5 * (s - a2))
                                         * np.tan(0.5 * (s - ad))))
        lens_area = 2.0 * (phi1 * (1.0 - c1[lens]) + phi2 * (1.0 - c2[lens]) - excess)
        # rounding may step a hair outside [0, the smaller cap]
        out[lens] = np.clip(lens_area, 0.0, _TWO_PI * (1.0 - np.maximum(c1, c2)[lens]))
    return _result(out)


def cap_intersection_smoothstep(cos1, cos2, cos_d):
    """Solid angle (sr) of the intersection of two spherical caps, Oat & Sander 2007's smoothstep approximation.

    Parameters
    ----------
    cos1, cos2, cos_d : float or array_like
        As in :func:`cap_intersection_exact`.

    Returns
    -------
    ndarray or numpy.float64
        Containment: the smaller cap's solid angle; disjoint: 0 (both exactly as :func:`cap_intersection_exact`);
        otherwise the smaller cap's solid angle times x²(3 − 2x), x = 1 − saturate((d − |θ1 − θ2|) /
        (θ1 + θ2 − |θ1 − θ2|)).

    Raises
    ------
    IBLError
        As :func:`cap_intersection_exact`.

    Examples
    --------
    Halfway between touching inside and touching outside, the smoothstep gives half the smaller cap:

    >>> import numpy as np
    >>> from ibl_ref.occlusion.spherical_caps import cap_intersection_smoothstep
    >>> t1, t2 = 0.6, 0.2
    >>> float(cap_intersection_smoothstep(np.cos(t1), np.cos(t2), np.cos(0.6)) / (2 * np.pi * (1 - np.cos(t2))))
    0.5
    """
    c1, c2, cd = _cosines(cos1, cos2, cos_d)
    t1, t2, d, inside, apart = _cases(c1, c2, cd)
    small = _TWO_PI * (1.0 - np.maximum(c1, c2))
    lo, hi = np.abs(t1 - t2), t1 + t2
    span = np.where(hi > lo, hi - lo, 1.0)  # hi == lo only where every d is inside or apart
    x = 1.0 - np.clip((d - lo) / span, 0.0, 1.0)
    out = np.where(inside, small, np.where(apart, 0.0, small * x * x * (3.0 - 2.0 * x)))
    return _result(out)
