"""Conventions shared by the ground truth, the paper's approximation and the renderers (no dependencies).

* Glossiness → Phong exponent, Knuth et al. (2014) Eq. 3: ``s_Phong = 1/(1 − g)``, g ∈ [0, 1]; g = 0 is the
  diffuse-like s = 1 lobe, g = 1 the mirror (s = ∞).
* Width of the clamped cosine lobe max(cos θ, 0)^s of Eq. 4: half-width at half maximum
  θ½ = arccos(2^(−1/s)) (≈ 1.18/√s for large s).
* GGX roughness → microfacet α (Karis 2013, "Real Shading in Unreal Engine 4", Sec. "Specular BRDF"; Burley 2012;
  Filament's documentation): the user-facing *perceptual roughness* r ∈ (0, 1] is squared, ``α = r²``; α is the
  Trowbridge–Reitz (GGX) width of :func:`ibl_ref.lobes.brdfs.ggx`.  r = 0 (a perfect mirror) is refused: the GGX
  NDF degenerates to a delta.

They live here so that the exact reference (:mod:`ibl_ref.rendering.reference_render`), the prefilters
(:mod:`ibl_ref.knuth2014.lobe_chain`, :mod:`ibl_ref.knuth2014.pyramid`) and the run-time look-up (:mod:`ibl_ref.knuth2014.gloss_lookup`) can all use
them without importing one another.
"""

from __future__ import annotations

import numpy as np

from .errors import IBLError

__all__ = ["phong_exponent", "lobe_half_angle", "ggx_alpha", "GGX_ROUGHNESS_MIN"]


def phong_exponent(g):
    """s_Phong = 1/(1 − g) (Eq. 3); g = 1 → ``np.inf`` (mirror) without a division warning.

    Parameters
    ----------
    g : float or array_like
        Glossiness in [0, 1] (0 = diffuse, 1 = mirror).

    Returns
    -------
    float or ndarray
        s_Phong ≥ 1, ``inf`` for g = 1.

    Raises
    ------
    IBLError
        If any g is NaN or outside [0, 1].

    Examples
    --------
    >>> from ibl_ref.conventions import phong_exponent
    >>> phong_exponent(0.5), phong_exponent(1.0)
    (2.0, inf)
    >>> phong_exponent([0.0, 0.9])
    array([ 1., 10.])
    """
    g_arr = np.asarray(g, dtype=np.float64)
    if np.any(np.isnan(g_arr)):
        raise IBLError("glossiness g is NaN; g must be in [0, 1] (0 = diffuse, 1 = mirror)")
    if np.any((g_arr < 0) | (g_arr > 1)):
        bad = g_arr[(g_arr < 0) | (g_arr > 1)].ravel()[0]
        raise IBLError(f"glossiness g must be in [0, 1] (0 = diffuse, 1 = mirror), got {bad!r}")
    one_minus = 1.0 - g_arr
    s = np.full(g_arr.shape, np.inf)
    np.divide(1.0, one_minus, out=s, where=one_minus > 0)  # Eq. 3
    return float(s) if s.ndim == 0 else s


def lobe_half_angle(s) -> np.ndarray:
    """Half-width at half maximum of max(cos θ, 0)^s: θ½ = arccos(2^(−1/s)) (≈ 1.18/√s for large s).

    Parameters
    ----------
    s : float or array_like
        Phong exponents > 0.

    Returns
    -------
    ndarray, float64
        Radians.

    Examples
    --------
    A cosine lobe (s = 1) falls to half at 60°:

    >>> import numpy as np
    >>> from ibl_ref.conventions import lobe_half_angle
    >>> float(np.degrees(lobe_half_angle(1.0)))
    60.0
    """
    s = np.asarray(s, dtype=np.float64)
    return np.arccos(np.power(2.0, -1.0 / s))


#: smallest GGX roughness accepted (α = 2^-20, α² = 2^-40): the peak of D = α²/(π((n·h)²(α²−1)+1)²) has the
#: bracket α², formed from (n·h)² whose float64 rounding near 1 is 2^-53, so its relative rounding is 2^-53/α²
#: (2^-13 ≈ 1.2e-4 at the floor); below α² = 2^-53 it rounds to 0 and D is α²/0
GGX_ROUGHNESS_MIN = 2.0 ** -10


def ggx_alpha(roughness):
    """GGX width ``α = roughness²`` (Karis 2013; the one place this convention is defined).

    Parameters
    ----------
    roughness : float or array_like
        Perceptual roughness in [:data:`GGX_ROUGHNESS_MIN`, 1].

    Returns
    -------
    float or ndarray
        α.

    Raises
    ------
    IBLError
        If any roughness is not a number, NaN, or outside [:data:`GGX_ROUGHNESS_MIN`, 1].
    """
    try:
        r = np.asarray(roughness, dtype=np.float64)
    except (TypeError, ValueError):
        raise IBLError(f"GGX roughness must be a number in (0, 1], got {roughness!r}") from None
    if r.size == 0:
        raise IBLError("roughness is empty; roughness must be in (0, 1]")
    bad = ~np.isfinite(r) | (r <= 0) | (r > 1)
    if np.any(bad):
        raise IBLError(f"GGX roughness must be in (0, 1] (0 would be a perfect mirror), got {r[bad].ravel()[0]!r}")
    if np.any(r < GGX_ROUGHNESS_MIN):
        raise IBLError(f"GGX roughness {r[r < GGX_ROUGHNESS_MIN].ravel()[0]!r} is below the floor "
                       f"{GGX_ROUGHNESS_MIN:.4g} (2^-10): float64 cannot resolve the peak of D below alpha^2 = 2^-40 "
                       "(conventions.GGX_ROUGHNESS_MIN); use the mirror (Phong g = 1) for a perfect mirror")
    a = r * r
    return float(a) if a.ndim == 0 else a
