"""The declared interface of a prefilter method, and of a set of them, one per median-cut region (PEMs).

A **prefilter** turns an environment into something that answers "the radiance of lobe p around direction d" fast:
built once from a cube map ``(6, N, N, C)`` (float, finite, ≥ 0) and the method's own parameters, then looked up as
often as needed.  Every method of :mod:`ibl_ref.prefilter` is a class that satisfies :class:`Prefilter`:

* ``Method(cube, **params)`` builds it (keyword-only parameters, each with a default);
* ``lobe``: the lobe family it serves, one of :data:`LOBES`, which fixes what the look-up parameter means:

  ======== ================================================= ==================================================
  lobe     ``param`` of :meth:`Prefilter.lookup`              target of the look-up
  ======== ================================================= ==================================================
  phong    Phong exponent s ≥ 1 (``np.inf``: the mirror);     the lobe average ∫ L max(d·ω, 0)^s dω /
           from a glossiness g: s = 1/(1 − g),                 ∫ max(d·ω, 0)^s dω (Knuth et al. 2014, Eq. 4
           :func:`ibl_ref.conventions.phong_exponent`          normalised; Kán et al. 2015, Eq. 2–4)
  ggx      perceptual roughness r ∈ (0, 1]; α = r²,           the method's GGX prefilter lobe (stated by the
           :func:`ibl_ref.conventions.ggx_alpha`               method, e.g. the n = v = r lobe of the split sum)
  cosine   none: 1 (the cosine lobe's Phong exponent) or       the irradiance E(n)/π, E(n) = Σ_j L_j max(n·ω_j, 0)
           ``None``; a Lambertian surface: kd·lookup(n)        Ω_j (Kán et al. 2015, Eq. 3; the diffuse methods)
  ======== ================================================= ==================================================

* ``lookup(directions, param)``: directions ``(..., 3)`` (need not be normalised), ``param`` a scalar or an array
  broadcastable to ``directions.shape[:-1]`` → radiance ``(..., C)``;
* ``nbytes``: bytes of what it stores (the arrays a renderer would keep in memory);
* ``error_bound``: ``None``, or a number B ≥ 0 (radiance units) with |lookup(d, p) − target_p(d)| ≤ B for every
  direction and parameter it accepts, the target computed from the cube it was built from with exact texel solid
  angles.  A method states ``None`` unless it can prove such a bound; a bound that holds only at some samples (at
  the stored exponents, at texel centres) is not an ``error_bound``;
* ``paper`` (class attribute): where the method comes from (paper, section, equations), for listings.

A **region set** is the paper's partial environment maps (Knuth et al. 2014, Sec. 3 step 2, Sec. 3.1, Sec. 4): one
prefiltered map per median-cut region, so that Eq. 5 can weight each by its own visibility,
c = Σ_i VIS_i · PEM_i.  It satisfies :class:`RegionPrefilters`: ``lights`` (the
:class:`ibl_ref.knuth2014.median_cut.LightSet` of the regions), ``lobe``, ``nbytes``, ``error_bound`` (per region)
and ``lookup_all(directions, g) → (L, ..., C)``, the look-ups of every region.  Region sets are looked up by the
**glossiness g** of Eq. 5's material system (Knuth Eq. 3; s = 1/(1 − g)), as every renderer of the package calls
them; a region set of Phong prefilters answers ``lookup_all(d, g)`` with its members' ``lookup(d, s(g))``.
:class:`ibl_ref.prefilter.regions.RegionSet` builds one from any Phong method (the method on each partial map);
:class:`ibl_ref.knuth2014.pem.PEMSet` and :class:`ibl_ref.knuth2014.sparse_pem.SparsePEMSet` are the paper's own
(all regions in one stacked pyramid).

The two protocols are :func:`typing.runtime_checkable`: ``isinstance(x, Prefilter)`` checks that the members exist
(not their types); :func:`check_lobe_param` is the one check of a look-up parameter.
"""

from __future__ import annotations

from typing import ClassVar, Protocol, runtime_checkable

import numpy as np

from ..errors import IBLError
from ..conventions import ggx_alpha

__all__ = ["LOBES", "Prefilter", "RegionPrefilters", "check_lobe_param"]

#: the lobe families a prefilter can serve (the meaning of its look-up parameter: module docstring)
LOBES = ("phong", "ggx", "cosine")


@runtime_checkable
class Prefilter(Protocol):
    """A prefiltered environment: ``Method(cube, **params)``, then ``lookup(directions, param) → (..., C)``.

    Members: module docstring (``lobe``, ``paper``, ``lookup``, ``nbytes``, ``error_bound``).
    """

    lobe: ClassVar[str]
    paper: ClassVar[str]

    def lookup(self, directions, param) -> np.ndarray:
        """Radiance (..., C) of the lobe ``param`` (Phong exponent s, or GGX roughness) around ``directions``."""
        ...

    @property
    def nbytes(self) -> int:
        """Bytes of the stored arrays."""
        ...

    @property
    def error_bound(self) -> float | None:
        """A proven bound of |lookup − target| over every accepted direction and parameter, or None."""
        ...


@runtime_checkable
class RegionPrefilters(Protocol):
    """One prefiltered map per median-cut region (PEMs): ``lights`` and ``lookup_all(directions, g) → (L, ..., C)``."""

    lights: object
    lobe: str

    def lookup_all(self, directions, g) -> np.ndarray:
        """Look-ups of every region at glossiness ``g`` (Knuth Eq. 3), shape (L, ..., C)."""
        ...

    @property
    def nbytes(self) -> int:
        """Bytes of the stored maps of all regions."""
        ...

    @property
    def error_bound(self) -> float | None:
        """A proven bound of every region's look-up error, or None."""
        ...


def _leading_shape(directions) -> tuple:
    """``directions.shape[:-1]`` of a direction array (..., 3); a one-line :class:`IBLError` for anything else."""
    try:
        d = np.asarray(directions, dtype=np.float64)
    except (TypeError, ValueError):
        raise IBLError(f"directions must be an array of shape (..., 3), got {type(directions).__name__}") from None
    if d.ndim == 0 or d.shape[-1] != 3:
        raise IBLError(f"directions must have shape (..., 3), got {d.shape}")
    return d.shape[:-1]


def check_lobe_param(lobe: str, param, directions=None) -> np.ndarray:
    """The look-up parameter of lobe family ``lobe`` as a float64 array, or a one-line :class:`IBLError`.

    ``"phong"``: Phong exponents s ≥ 1 (``np.inf`` allowed: the mirror); ``"ggx"``: perceptual roughness in (0, 1]
    above :data:`ibl_ref.conventions.GGX_ROUGHNESS_MIN` (:func:`ibl_ref.conventions.ggx_alpha` checks it);
    ``"cosine"``: 1 or ``None`` (the lobe has no parameter).  With ``directions`` (..., 3), the parameter must also
    broadcast to their leading shape (a scalar, or one value per direction); the array is returned as given.
    """
    if lobe not in LOBES:
        raise IBLError(f"unknown lobe family {lobe!r}; choose one of {', '.join(LOBES)}")
    value = 1.0 if lobe == "cosine" and param is None else param
    try:
        if isinstance(value, (bool, np.bool_)) or (isinstance(value, np.ndarray) and value.dtype == bool):
            raise TypeError
        p = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise IBLError(f"the {lobe} look-up parameter must be a number or an array of numbers, got {param!r}") from None
    if directions is not None:
        lead = _leading_shape(directions)
        try:
            ok = np.broadcast_shapes(p.shape, lead) == lead
        except ValueError:
            ok = False
        if not ok:
            raise IBLError(f"the {lobe} look-up parameter has shape {p.shape}, which does not broadcast to the "
                           f"directions' leading shape {lead} (give one value, or one per direction)")
    if lobe == "cosine":
        if np.any(p != 1.0):
            bad = p[p != 1.0].ravel()[0]
            raise IBLError(f"the cosine lobe (irradiance) has no parameter: pass 1 (its Phong exponent) or None, "
                           f"got {bad!r}")
        return p
    if lobe == "phong":
        if np.any(np.isnan(p)) or np.any(p < 1.0):
            bad = p[np.isnan(p) | (p < 1.0)].ravel()[0]
            raise IBLError(f"Phong exponent s must be >= 1 (np.inf: mirror; from a glossiness g: s = 1/(1 - g)), "
                           f"got {bad!r}")
        return p

    ggx_alpha(p)
    return p
