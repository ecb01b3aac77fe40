"""Zonal (Funk–Hecke) coefficients of the clamped Phong lobe and the rigorous truncation envelope of its
Legendre series (Knuth et al. 2014 Sec. 3.2 Eq. 4; derivation and use in :mod:`ibl_ref.groundtruth.sh_convolution`).

* :func:`zonal_coefficients` — ``c_l = 2π ∫_0^1 x^s P_l(x) dx`` in closed form (Gradshteyn & Ryzhik 7.126.2),
  in log space.
* :func:`legendre_series_truncation_envelope` — ``E_L = 2π ∫ ê_L(θ) sin θ dθ``, the texel-envelope integral of
  the truncation error ``|k − k_L|`` widened by the texel radius ρ (:func:`texel_max_radius`);
  :func:`choose_band_limit` the smallest tabulated L meeting a target.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ..environment import envmap
from ..errors import IBLError

__all__ = ["zonal_coefficients", "legendre_series_truncation_envelope", "texel_max_radius", "choose_band_limit",
           "SH_L_MAX"]

#: largest band limit the SH route will use on its own (cost grows as (L+1)²)
SH_L_MAX = 160

_FOUR_PI = 4.0 * np.pi

# ----------------------------------------------------------------------------------------------
# zonal (Funk–Hecke) coefficients of the clamped cosine lobe
# ----------------------------------------------------------------------------------------------
def _lgamma_sign(x):
    """``(log|Γ(x)|, sign Γ(x))`` elementwise for x not a pole (standard library ``math.lgamma``:
    importing ``scipy.special`` costs ≈ 0.1–0.3 s of start-up for ≤ 3·(L+1) values).  Γ > 0 on
    x > 0; on (−k−1, −k) its sign is (−1)^(k+1), i.e. negative where ⌊x⌋ is odd."""
    x = np.asarray(x, dtype=np.float64)
    lg = np.array([math.lgamma(v) for v in x.ravel().tolist()]).reshape(x.shape)
    sgn = np.where(x > 0, 1.0, np.where(np.mod(np.floor(x), 2.0) == 1.0, -1.0, 1.0))
    return lg, sgn


def zonal_coefficients(s: float, L: int) -> np.ndarray:
    """Funk–Hecke eigenvalues ``c_l = 2π ∫_0^1 x^s P_l(x) dx`` of ``max(cos θ, 0)^s``, l = 0..L.

    Closed form (Gradshteyn & Ryzhik 7.126.2)
    ``∫_0^1 x^s P_l dx = √π 2^{−s−1} Γ(1+s) / (Γ(1 + s/2 − l/2) Γ(s/2 + l/2 + 3/2))``, evaluated with
    log-gamma functions (no overflow for large s and l).  ``c_0 = 2π/(s+1)``.

    Parameters
    ----------
    s : float
        Phong exponent (> −1 for the formula; the library uses s ≥ 1).
    L : int
        Highest band.

    Returns
    -------
    ndarray (L+1,) float64
    """
    s = float(s)
    if not s > -1.0 or not np.isfinite(s):
        raise IBLError(f"zonal_coefficients needs a finite exponent s > -1, got {s!r}")
    L = int(L)
    if L < 0:
        raise IBLError(f"band limit L must be >= 0, got {L}")
    ell = np.arange(L + 1, dtype=np.float64)
    a = 1.0 + s / 2.0 - ell / 2.0
    pole = (a <= 0) & (a == np.round(a))  # 1/Γ(a) = 0 at non-positive integers
    a_safe = np.where(pole, 0.5, a)
    lg_a, sgn_a = _lgamma_sign(a_safe)
    log_mag = (
        0.5 * np.log(np.pi)
        - (s + 1.0) * np.log(2.0)
        + math.lgamma(1.0 + s)
        - lg_a
        - _lgamma_sign(s / 2.0 + ell / 2.0 + 1.5)[0]
    )
    c = np.where(pole, 0.0, sgn_a * np.exp(log_mag))
    return 2.0 * np.pi * c


# ----------------------------------------------------------------------------------------------
# truncation-error envelope
# ----------------------------------------------------------------------------------------------
#: largest angle (rad) between a texel centre and one of its corners on a cube face of size n: the texel radius ρ
#: of the envelope, :func:`ibl_ref.environment.envmap.texel_max_radius` itself (cached there)
texel_max_radius = envmap.texel_max_radius


def _sliding_max(a: np.ndarray, half: int) -> np.ndarray:
    """``out[i] = max(a[i−half : i+half+1])`` (window clipped at the ends), O(n log half)."""
    n = a.size
    w = 2 * half + 1
    pad = np.concatenate([np.full(half, a[0]), a, np.full(half, a[-1])])
    m = pad.copy()  # m[i] = max(pad[i : i + width])
    width = 1
    while 2 * width <= w:
        m = np.maximum(m[:-width], m[width:])
        width *= 2
    # window [i, i+w) = [i, i+width) ∪ [i+w−width, i+w)
    return np.maximum(m[:n], m[w - width : w - width + n])


def _envelope_levels(L_max: int):
    """Band limits at which the envelope integral is tabulated (all L ≤ 24, then every 4th)."""
    return sorted(set(range(0, min(L_max, 24) + 1)) | set(range(24, L_max + 1, 4)) | {L_max})


@functools.lru_cache(maxsize=512)
def _envelope_table(s: float, L_max: int, rho: float):
    s = float(s)
    levels = _envelope_levels(L_max)
    # ≥ 40 grid points per half-oscillation of P_L and per lobe width 1/√s, ≥ 4 points per ρ
    n_grid = int(min(400_000, max(8_000, 40 * L_max, 40 * math.pi * math.sqrt(s), 4 * math.pi / max(rho, 1e-9))))
    theta = np.linspace(0.0, np.pi, n_grid)
    h = theta[1] - theta[0]
    t = np.cos(theta)
    k = np.where(t > 0, np.exp(s * np.log(np.maximum(t, 1e-300))), 0.0)
    c = zonal_coefficients(s, L_max)
    half = int(math.ceil(rho / h)) + 1  # window widened by one grid step
    w = np.sin(theta)
    out = {}
    p_prev = np.ones_like(t)
    p_cur = t.copy()
    kL = c[0] / _FOUR_PI * p_prev
    want = set(levels)
    for ell in range(L_max + 1):
        if ell == 1:
            kL = kL + c[1] * 3.0 / _FOUR_PI * p_cur
        elif ell >= 2:
            p_prev, p_cur = p_cur, ((2 * ell - 1) * t * p_cur - (ell - 1) * p_prev) / ell
            kL = kL + c[ell] * (2 * ell + 1) / _FOUR_PI * p_cur
        if ell in want:
            env = _sliding_max(np.abs(k - kL), half)
            # trapezoid integral + a small allowance for the sampling of |e| between grid points
            out[ell] = 2.0 * np.pi * np.trapezoid(env * w, theta) + 2.0 * np.pi * h * env.max() * 1e-3
    return levels, out


def legendre_series_truncation_envelope(s: float, L: int, rho: float) -> float:
    """Texel-envelope integral ``E_L = 2π ∫ ê_L(θ) sin θ dθ`` (see module docstring).

    ``ê_L(θ) = max_{|θ'−θ| ≤ ρ} |k(cos θ') − k_L(cos θ')|`` with ``k = max(cos, 0)^s`` and ``k_L`` its
    degree-L Legendre truncation.  Bounds ``Σ_j Ω_j |e_L(r·ω_j)|`` for every r when ρ ≥ the texel
    radius (:func:`texel_max_radius`).
    """
    L = int(L)
    levels, tab = _envelope_table(float(s), max(L, SH_L_MAX) if L > SH_L_MAX else SH_L_MAX, float(round(rho, 12)))
    if L in tab:
        return float(tab[L])
    _, tab1 = _envelope_table(float(s), L, float(round(rho, 12)))  # table ending exactly at L
    return float(tab1[L])


def band_limit_lower_bound(s: float, eta_target: float, L_max: int = SH_L_MAX):
    """A band limit that :func:`choose_band_limit` never goes below, from the zonal coefficients alone (no
    tables): the truncation error ``e_L = k − k_L`` has ``∫ e_L P_m dω = c_m`` for every m > L (Funk–Hecke,
    orthogonality) and ``|P_m| ≤ 1``, so ``E_L ≥ ∫|e_L| dω ≥ max_{m>L} |c_m|``.  Returns the smallest L ≤ L_max
    with ``max_{L<m≤L_max+1} |c_m| / (2π/(s+1)) ≤ 2·eta_target`` (the factor 2 covers the tables' quadrature),
    or None when there is none (then :func:`choose_band_limit` returns None too)."""
    d0 = 2.0 * np.pi / (float(s) + 1.0)
    c = np.abs(zonal_coefficients(float(s), L_max + 1)) / d0
    tail = np.maximum.accumulate(c[::-1])[::-1]  # tail[m] = max_{m' ≥ m} |c_m'| / d0 (m' ≤ L_max + 1)
    ok = np.flatnonzero(tail[1:] <= 2.0 * eta_target)  # index L: max over m > L
    return int(ok[0]) if ok.size else None


def choose_band_limit(s: float, eta_target: float, rho: float, L_max: int = SH_L_MAX):
    """Smallest tabulated L ≤ L_max with ``E_L / (2π/(s+1)) ≤ eta_target``; None if none qualifies.

    The levels are those of the table to :data:`SH_L_MAX`; for ``L_max`` < SH_L_MAX the table is computed only to
    ``L_max`` (cheaper): its grid does not depend on its last level (40·L ≤ 8 000 grid points for L ≤ 200) and its
    values at a level are computed by the same operations, so the answer is the one of the full table."""
    L_tab = SH_L_MAX if L_max >= SH_L_MAX else max(int(L_max), 0)
    _, tab = _envelope_table(float(s), L_tab, float(round(rho, 12)))
    levels = _envelope_levels(SH_L_MAX)
    d0 = 2.0 * np.pi / (s + 1.0)
    for L in levels:
        if L > L_max:
            break
        if tab[L] / d0 <= eta_target:
            return int(L)
    return None
