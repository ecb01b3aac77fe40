"""Kán, Unterguggenberger & Kaufmann (2015) — irradiance and specular reflection maps (Sec. 3.2, Eq. 1–4).

Kán et al. use the *modified, energy-normalised Phong BRDF* (their Eq. 2)::

    f_r = kd / π + ks · (n+1)/(2π) · cosⁿ(α) / |n·ωi|

with α the angle between ωi and the mirrored view direction ωr and n the shininess.  Inserting it into
the distant-light rendering equation (their Eq. 1, ``Lo ≈ 2π/N Σ f_r L_i |n·ωi|``) the ``|n·ωi|`` of the
specular term cancels and the sum splits (their Eq. 3) into two pre-computable maps (their Eq. 4)::

    Lo = kd · Ed(n) + ks · Esⁿ(ωr)
    Ed(n)   = (1/π)       ∫ L(ωi) max(n·ωi, 0)   dωi          (diffuse / irradiance map)
    Esⁿ(ωr) = (n+1)/(2π)  ∫ L(ωi) max(ωr·ωi, 0)ⁿ dωi          (specular map, shininess n)

Normalisation found from the paper's definitions: the 1/π of the Lambert term stays in Ed, so Ed is the
irradiance divided by π (a radiance), and the (n+1)/(2π) stays in Esⁿ.  Both are therefore *lobe
averages* of the Phong lobe with exponent s = 1 and s = n (Knuth et al. 2014, Eq. 4 normalised)::

    ∫ max(cos θ, 0)^s dω = 2π/(s+1)   ⇒   Ed(n) = Ē_1(n)   (2π/(1+1) = π)
                                         Esⁿ(ωr) = Ē_n(ωr)

For a constant environment L ≡ c both maps equal c: Ed = c·π/π and Esⁿ = c·(n+1)/(2π)·2π/(n+1).

Two departures from the paper, both explicit:

* Kán's Eq. 1 weights every pixel by 2π/N (a uniform solid angle); here every source texel carries its
  **exact** solid angle (:func:`ibl_ref.environment.envmap.cube_solid_angles`).
* The specular integral runs over the lobe's own hemisphere (ωr·ωi > 0), not clipped by the surface
  normal's hemisphere — that is what makes Esⁿ a function of ωr alone, as in the paper.

``quadrature="literal"`` (default) evaluates the literal integrals: the unnormalised Eq. 4 sum of
:func:`ibl_ref.groundtruth.phong_convolution.convolve_exact` times the constant 1/π or (n+1)/(2π); a constant
environment then comes out as c·W_n/(2π/(n+1)), i.e. with the quadrature error of the lobe weight
(measured max relative error at N = 16: 1.6e-4 for n = 1, 2.6e-3 for n = 16, 2.6e-2 for n = 256; O(N⁻²)
once the lobe spans several texels; ``experiments/convergence``).
``quadrature="normalized"`` divides by the discrete lobe weight instead, i.e. returns the lobe average,
which is exactly c for a constant environment; the two agree as N → ∞.
"""

from __future__ import annotations

import numpy as np

from ..errors import IBLError
from .phong_convolution import convolve_exact_many

__all__ = ["phong_brdf", "irradiance_map", "specular_map", "specular_maps", "reflected_radiance"]

_QUADRATURES = ("literal", "normalized")


def _check_quadrature(quadrature: str) -> None:
    if quadrature not in _QUADRATURES:
        raise IBLError(f"quadrature must be one of {_QUADRATURES}, got {quadrature!r}")


def phong_brdf(kd, ks, n, cos_alpha, n_dot_wi):
    """Modified energy-normalised Phong BRDF of Kán et al. 2015, Eq. 2.

    ``f_r = kd/π + ks (n+1)/(2π) max(cos α, 0)ⁿ / |n·ωi|`` (sr⁻¹).  ``n_dot_wi`` must be non-zero where
    the specular lobe is non-zero.
    """
    n = float(n)
    if not n >= 0:
        raise IBLError(f"shininess n must be >= 0, got {n!r}")
    cos_alpha = np.asarray(cos_alpha, dtype=np.float64)
    n_dot_wi = np.abs(np.asarray(n_dot_wi, dtype=np.float64))
    lobe = np.maximum(cos_alpha, 0.0) ** n
    if np.any((lobe > 0) & (n_dot_wi == 0)):
        raise IBLError("phong_brdf: |n·ωi| = 0 where the specular lobe is non-zero (division by zero)")
    with np.errstate(divide="ignore", invalid="ignore"):
        spec = np.where(lobe > 0, lobe / np.where(n_dot_wi > 0, n_dot_wi, 1.0), 0.0)
    return np.asarray(kd) / np.pi + np.asarray(ks) * (n + 1.0) / (2.0 * np.pi) * spec


def specular_maps(cube, exponents, *, quadrature: str = "literal", supersample: int = 1, out_size=None) -> np.ndarray:
    """Specular reflection maps Esⁿ(ωr) = (n+1)/(2π) ∫ L max(ωr·ωi,0)ⁿ dωi for several shininesses.

    Kán et al. 2015, Eq. 3–4 (computed together, like their multiple-render-target pass).

    Parameters
    ----------
    cube : array (6, N, N[, C])
    exponents : sequence of float ≥ 1 (shininess n; ``np.inf`` → mirror, only with "normalized")
    quadrature : {"literal", "normalized"}
        See the module docstring.
    supersample, out_size
        As in :func:`ibl_ref.groundtruth.phong_convolution.convolve_exact`.

    Returns
    -------
    ndarray (K, 6, n, n, C) float64.
    """
    _check_quadrature(quadrature)
    exps = [float(e) for e in np.atleast_1d(np.asarray(exponents, dtype=np.float64))]
    if quadrature == "normalized":
        return convolve_exact_many(cube, exps, normalized=True, supersample=supersample, out_size=out_size)
    raw = convolve_exact_many(cube, exps, normalized=False, supersample=supersample, out_size=out_size)
    scale = np.array([(e + 1.0) / (2.0 * np.pi) for e in exps]).reshape((-1,) + (1,) * (raw.ndim - 1))
    return raw * scale  # Eq. 3: (n+1)/(2π) Σ L cosⁿα Ω


def specular_map(cube, n, *, quadrature: str = "literal", supersample: int = 1, out_size=None) -> np.ndarray:
    """One specular map Esⁿ (Kán et al. 2015, Eq. 3–4); see :func:`specular_maps`."""
    return specular_maps(cube, [n], quadrature=quadrature, supersample=supersample, out_size=out_size)[0]


def irradiance_map(cube, *, quadrature: str = "literal", supersample: int = 1, out_size=None) -> np.ndarray:
    """Diffuse map Ed(n) = (1/π) ∫ L(ωi) max(n·ωi, 0) dωi (Kán et al. 2015, Eq. 3–4).

    Equals the normalised Phong-lobe average at s = 1 (in the continuum; in ``"normalized"``
    quadrature exactly), i.e. irradiance / π.  Shape (6, n, n, C).
    """
    _check_quadrature(quadrature)
    if quadrature == "normalized":
        return convolve_exact_many(cube, [1.0], normalized=True, supersample=supersample, out_size=out_size)[0]
    raw = convolve_exact_many(cube, [1.0], normalized=False, supersample=supersample, out_size=out_size)[0]
    return raw / np.pi  # Eq. 3: kd/π Σ L |n·ωi| Ω


def reflected_radiance(ed, es, kd, ks):
    """Lo = kd·Ed(n) + ks·Esⁿ(ωr) (Kán et al. 2015, Eq. 4); ``ed``, ``es`` looked-up map values."""
    return np.asarray(kd) * np.asarray(ed) + np.asarray(ks) * np.asarray(es)
