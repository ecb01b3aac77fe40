"""Spherical-harmonic (SH) Phong-lobe convolution with a rigorous per-texel error bound.

Implements Knuth et al. (2014), Sec. 3.2, Eq. 4 (the convolution of the environment with the clamped
cosine lobe ``max(r·ω, 0)^s``, ``s = s_Phong = 1/(1−g)``, Eq. 3) by the Funk–Hecke theorem, plus a
"hybrid" split that convolves the brightest texels (a sun) exactly.

The quadrature that is approximated
-----------------------------------
The reference (:func:`ibl_ref.phong_convolution.convolve_exact`) is the discrete sum over source texels
``N(r) = Σ_j L_j k(r·ω_j) Ω_j`` with ``k(t) = max(t, 0)^s`` and exact texel solid angles ``Ω_j``, and the
lobe average ``y(r) = N(r) / D(r)``, ``D(r) = Σ_j k(r·ω_j) Ω_j``.

Funk–Hecke / addition theorem
-----------------------------
Expand the kernel in Legendre polynomials, ``k(t) = Σ_l c_l (2l+1)/(4π) P_l(t)`` with::

    c_l = 2π ∫_{-1}^{1} k(t) P_l(t) dt = 2π ∫_0^1 x^s P_l(x) dx                     (Funk–Hecke eigenvalue)

and use ``(2l+1)/(4π) P_l(r·ω) = Σ_m Y_lm(r) Y_lm(ω)`` (addition theorem, real orthonormal SH).  With the
*discrete* projection ``a_lm = Σ_j L_j Y_lm(ω_j) Ω_j`` this gives **exactly** (no quadrature error)::

    N_L(r) = Σ_{l≤L} c_l Σ_m a_lm Y_lm(r) = Σ_j L_j k_L(r·ω_j) Ω_j,

where ``k_L`` is the degree-L truncation of the Legendre series.  The only error is the kernel
truncation ``e_L = k − k_L``.  The normalised average uses the same truncation for ``D`` (the SH of the
all-ones map), so a constant environment is reproduced to rounding.  For ``L(ω) = a + b·ω`` the
continuous average is ``a + (b·r)·c_1/c_0 = a + (b·r)(s+1)/(s+2)``.

Closed form of the zonal coefficients
-------------------------------------
For Re μ > −1 (Gradshteyn & Ryzhik 7.126.2; also Byerly, *Fourier's Series and Spherical Harmonics*)::

    ∫_0^1 x^μ P_ν(x) dx = √π · 2^{−μ−1} · Γ(1+μ) / [ Γ(1 + μ/2 − ν/2) · Γ(μ/2 + ν/2 + 3/2) ]

(checks: μ=ν=0 → 1; μ=ν=1 → 1/3; μ=0, ν=2 → 0).  It is evaluated in log space with
``math.lgamma`` (log |Γ|) and the sign of ``1/Γ(1 + μ/2 − ν/2)`` (zero at the poles; :func:`_lgamma_sign`), so
it does not overflow for s up to 1e6 and l in the hundreds.  :func:`zonal_coefficients` returns ``c_l``.

Rigorous error bound
--------------------
Write the remainder environment ``L_r`` (see *hybrid*, below) with values in ``[m, τ]``.  With ``N' = N +
ε_N`` and ``D' = D + ε_D`` the SH results, ``(y' − y) D' = ε_N − y ε_D = Σ_j (L_r,j − y) Ω_j e_L(r·ω_j)``,
hence ``|y' − y| ≤ (max(τ, y) − m) · E_L / D'`` with the **texel-envelope integral**::

    E_L = 2π ∫_0^π ê_L(θ) sin θ dθ ,   ê_L(θ) = max_{|θ' − θ| ≤ ρ} |e_L(cos θ')| ,

where ρ is the largest angle between a source texel centre and its corners.  Since every point ω of
texel j is within ρ of ω_j, ``|e_L(r·ω_j)| ≤ ê_L(angle(r, ω))`` on the whole texel and
``Σ_j Ω_j |e_L(r·ω_j)| ≤ ∫ ê_L dω = E_L`` for **every** r.  ``ê_L`` is evaluated on a fine θ grid (the
window is widened by one grid step; the only non-rigorous part is the sampling of ``|e_L|`` between
grid points, with a grid of ≥ 40 points per oscillation of ``P_L``).  Solving for y gives the absolute
bound ``A = max((τ − m) η, (y' − m) η/(1 − η))`` with ``η = E_L / D'`` and the relative bound
``A / (y' − A)`` (∞ where ``y' ≤ A``).  Unnormalised Eq. 4: ``|ε_N| ≤ τ · E_L`` (``L_r ∈ [0, τ]``).

Band limit
----------
The band limit is the smallest tabulated L (every L ≤ 24, then every 4th, up to :data:`SH_L_MAX`)
with ``E_L / (2π/(s+1)) ≤ 0.8 rtol · min(1, y_lo / (τ − m))``, where ``y_lo`` is 0.8 × the minimum of
a cheap band-4 preview of the output (or the environment minimum if larger).  The a-posteriori bound
above is what is reported (plus a rounding allowance ``4π·ε_mach·(L+1)²`` added to ``E_L``); the
a-priori choice only aims at it.  Exponents that would need L > SH_L_MAX (s ≈ 1, whose lobe has a kink at the
horizon so ``E_L`` decays only like L^−1.5, and s ≳ 500, whose lobe is narrow) are left to the other
methods by :func:`ibl_ref.convolve.convolve`.

Hybrid for bright suns
----------------------
A small 1e5 sun makes the truncated series ring over the whole sphere and makes ``τ − m`` huge.  The
environment is split as ``L = min(L, τ) + max(L − τ, 0)``: the second term is non-zero on the few
texels above the threshold τ and is convolved **exactly** (a gather from those texels for every output
texel); only the clipped remainder ``min(L, τ) ∈ [m, τ]`` goes through SH, so the bound uses τ.  τ is
chosen among the brightest-texel quantiles by a simple cost model (SH band limit needed for the bound
vs. number of gathered texels).

Real SH basis (no Condon–Shortley phase; projection and evaluation use the same basis, so the phase is
irrelevant): ``Y_l0 = P̄_l0(cos θ)``, ``Y_lm = √2 P̄_l|m|(cos θ) cos(mφ)`` (m > 0), ``√2 P̄_l|m| sin(|m|φ)``
(m < 0), index ``l² + l + m``; ``P̄_lm`` are the fully normalised associated Legendre functions from the
standard stable recurrences (sectoral ``P̄_mm = √((2m+1)/(2m)) sin θ P̄_{m−1,m−1}``, then
``P̄_lm = a_lm (x P̄_{l−1,m} − b_lm P̄_{l−2,m})``), which do not overflow for L in the hundreds (values
only underflow to 0 near the poles, where they are negligible).
"""

from __future__ import annotations

import functools
import math
import time

import numpy as np

from . import envmap
from .convolution_args import check_cube, check_exponent, check_out_size
from .errors import IBLError, LayoutError

__all__ = [
    "zonal_coefficients",
    "legendre_series_truncation_envelope",
    "texel_max_radius",
    "real_sh",
    "sh_project",
    "sh_evaluate",
    "sh_lobe_convolve",
    "choose_band_limit",
    "convolve_sh",
    "convolve_sh_many",
    "plan_sh",
    "sh_cost",
    "bright_cost",
    "SH_L_MAX",
]

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
def texel_max_radius(n: int) -> float:
    """Largest angle (rad) between a texel centre and one of its corners on a cube face of size n."""
    c = envmap.texel_center_uv(n)
    e = np.linspace(-1.0, 1.0, n + 1)
    centre = envmap.face_uv_to_direction(0, c[None, :], c[:, None])  # (n, n, 3)
    corners = envmap.face_uv_to_direction(0, e[None, :], e[:, None])  # (n+1, n+1, 3)
    best = 0.0
    for dr in (0, 1):
        for dc in (0, 1):
            k = corners[dr : dr + n, dc : dc + n]
            cosang = np.clip(np.sum(centre * k, axis=-1), -1.0, 1.0)
            best = max(best, float(np.max(np.arccos(cosang))))
    return best


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


def choose_band_limit(s: float, eta_target: float, rho: float, L_max: int = SH_L_MAX):
    """Smallest tabulated L ≤ L_max with ``E_L / (2π/(s+1)) ≤ eta_target``; None if none qualifies."""
    levels, tab = _envelope_table(float(s), SH_L_MAX, float(round(rho, 12)))
    d0 = 2.0 * np.pi / (s + 1.0)
    for L in levels:
        if L > L_max:
            break
        if tab[L] / d0 <= eta_target:
            return int(L)
    return None


# ----------------------------------------------------------------------------------------------
# real spherical harmonics
# ----------------------------------------------------------------------------------------------
def _polar(dirs):
    d = np.asarray(dirs, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    x = np.clip(d[..., 2], -1.0, 1.0)  # cos θ, polar axis +z
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - x * x))
    rho_xy = np.hypot(d[..., 0], d[..., 1])
    safe = rho_xy > 0
    eiphi = np.where(safe, (d[..., 0] + 1j * d[..., 1]) / np.where(safe, rho_xy, 1.0), 1.0 + 0j)
    return x, sin_t, eiphi


#: working-set size of one chunk of the SH matrix, in float64 elements (128 MB)
_SH_CHUNK_ELEMS = 1 << 24


def _chunk(L):
    return max(512, _SH_CHUNK_ELEMS // (L + 1) ** 2)


@functools.lru_cache(maxsize=64)
def _layout(L):
    """Internal row order of the SH matrix, split by parity of l+m.

    Band-major: for each l, the rows of orders m ≡ l (mod 2) go to the *even* matrix (cos rows, then
    sin rows for m > 0), the others to the *odd* matrix.  Returns (even, odd) lists of (l, m, kind)
    with kind 'c' (Y_lm, m ≥ 0) or 's' (Y_l,−m).
    """
    even, odd = [], []
    for ell in range(L + 1):
        me = range(ell % 2, ell + 1, 2)
        mo = range((ell + 1) % 2, ell + 1, 2)
        even += [(ell, m, "c") for m in me] + [(ell, m, "s") for m in me if m > 0]
        odd += [(ell, m, "c") for m in mo] + [(ell, m, "s") for m in mo if m > 0]
    return tuple(even), tuple(odd)


def _row_layout(L):
    """Band l of every row of the (even, odd) SH matrices."""
    ev, od = _layout(L)
    return np.array([r[0] for r in ev], dtype=int), np.array([r[0] for r in od], dtype=int)


def _std_index(rows):
    return np.array([ell * ell + ell + (m if kind == "c" else -m) for ell, m, kind in rows], dtype=int)


@functools.lru_cache(maxsize=512)
def _recurrence_coeffs(ell):
    m = np.arange(ell - 1, dtype=np.float64)
    a = np.sqrt((4.0 * ell * ell - 1.0) / (ell * ell - m * m))
    b = np.sqrt(((ell - 1.0) ** 2 - m * m) / (4.0 * (ell - 1.0) ** 2 - 1.0))
    return a[:, None], b[:, None]


def _real_sh_parity(dirs, L):
    """SH matrix rows split by parity: (Y_even (n_e, n), Y_odd (n_o, n)) in :func:`_layout` order.

    Under z → −z, Y_even is unchanged and Y_odd changes sign (P̄_lm(−x) = (−1)^{l+m} P̄_lm(x)).
    The associated Legendre recurrences run band by band, vectorised over all orders m.
    """
    x, sin_t, eiphi = _polar(dirs)
    n = x.shape[0]
    ev, od = _layout(L)
    Ye = np.empty((len(ev), n))
    Yo = np.empty((len(od), n))
    sqrt2 = math.sqrt(2.0)
    cosm = np.empty((L + 1, n))
    sinm = np.empty((L + 1, n))
    em = np.ones(n, dtype=complex)
    cosm[0] = 1.0
    sinm[0] = 0.0
    for m in range(1, L + 1):
        em = em * eiphi
        cosm[m] = sqrt2 * em.real
        sinm[m] = sqrt2 * em.imag
    ie = io = 0
    p1 = p2 = None  # P̄_{l−1,·}, P̄_{l−2,·}
    for ell in range(L + 1):
        P = np.empty((ell + 1, n))
        if ell == 0:
            P[0] = 1.0 / math.sqrt(_FOUR_PI)
        else:
            P[ell] = math.sqrt((2 * ell + 1) / (2 * ell)) * sin_t * p1[ell - 1]  # sectoral
            P[ell - 1] = math.sqrt(2 * ell + 1) * x * p1[ell - 1]
            if ell >= 2:  # P̄_lm = a (x P̄_{l−1,m} − b P̄_{l−2,m}), all m ≤ l−2 at once
                a, b = _recurrence_coeffs(ell)
                np.multiply(x, p1[: ell - 1], out=P[: ell - 1])
                P[: ell - 1] -= b * p2[: ell - 1]
                P[: ell - 1] *= a
        for par, (Y, i0) in enumerate(((Ye, ie), (Yo, io))):
            m0 = (ell + par) % 2
            cnt = len(range(m0, ell + 1, 2))
            if cnt == 0:
                continue
            np.multiply(P[m0::2], cosm[m0 : ell + 1 : 2], out=Y[i0 : i0 + cnt])
            m1 = m0 if m0 > 0 else 2  # sin rows only for m > 0
            cs = len(range(m1, ell + 1, 2))
            if cs:
                np.multiply(P[m1::2], sinm[m1 : ell + 1 : 2], out=Y[i0 + cnt : i0 + cnt + cs])
            if par == 0:
                ie += cnt + cs
            else:
                io += cnt + cs
        p2, p1 = p1, P
    return Ye, Yo


def _mirror_pairs(dirs):
    """Split a direction set that is symmetric under z → −z: (upper ∪ equator idx, mirror idx of upper).

    Returns None if the set is not exactly symmetric (then no parity speed-up is used).
    """
    z = dirs[:, 2]
    up = np.nonzero(z > 0)[0]
    eq = np.nonzero(z == 0)[0]
    lo = np.nonzero(z < 0)[0]
    if up.size != lo.size:
        return None
    r = np.round(dirs[:, :2], 9)  # symmetric texels agree to rounding; sort on rounded keys
    key_up = np.lexsort((r[up, 1], r[up, 0]))
    key_lo = np.lexsort((r[lo, 1], r[lo, 0]))
    u, l_ = up[key_up], lo[key_lo]
    if not np.allclose(dirs[u, :2], dirs[l_, :2], rtol=0, atol=1e-12) or not np.allclose(
        dirs[u, 2], -dirs[l_, 2], rtol=0, atol=1e-12
    ):
        return None
    return np.concatenate([u, eq]), l_


# ----------------------------------------------------------------------------------------------
# octahedral reflection symmetry of the cube texel grid (x → −x, y → −y, z → −z)
# ----------------------------------------------------------------------------------------------
#: largest SH matrix (rows × octant directions, float64 elements) kept in memory between the
#: projection and the evaluation when both use the same directions (256 MB)
_SH_CACHE_ELEMS = 1 << 25


def _octant_orbits(dirs):
    """Orbits of a direction set under the 8 sign flips of (x, y, z), or None if it is not closed.

    Returns ``idx`` (M/8, 8) with ``dirs[idx[o, g]] = σ_g · dirs[idx[o, 0]]``, where bit 0/1/2 of the
    group element ``g`` flips x/y/z and ``dirs[idx[o, 0]]`` lies in the open positive octant.  Every
    even-sized cube texel grid qualifies (no texel centre lies on a coordinate plane); sets with a
    direction on a coordinate plane (odd face sizes) or not exactly symmetric return None.
    """
    d = np.asarray(dirs)
    M = d.shape[0]
    if M == 0 or M % 8 or np.any(d == 0.0):
        return None
    code = (d[:, 0] < 0).astype(np.intp) + 2 * (d[:, 1] < 0) + 4 * (d[:, 2] < 0)
    ab = np.abs(d)
    key = np.round(ab, 9)
    idx = np.lexsort((code, key[:, 2], key[:, 1], key[:, 0])).reshape(-1, 8)
    if not np.array_equal(code[idx], np.broadcast_to(np.arange(8), idx.shape)):
        return None
    if not np.allclose(ab[idx], ab[idx[:, :1]], rtol=0.0, atol=1e-12):
        return None
    return idx


@functools.lru_cache(maxsize=1)
def _walsh8():
    """Characters χ_κ(g) = (−1)^popcount(κ & g) of the group of sign flips (8 × 8, symmetric)."""
    k = np.arange(8)
    bits = np.bitwise_and(k[:, None], k[None, :])
    pc = (bits & 1) + ((bits >> 1) & 1) + ((bits >> 2) & 1)
    return np.where(pc % 2 == 0, 1.0, -1.0)


@functools.lru_cache(maxsize=64)
def _octant_row_classes(L):
    """Row indices of the (even, odd) SH matrices per character class κ = bx + 2·by + 4·bz.

    Under x → −x (φ → π − φ): ``cos mφ → (−1)^m cos mφ``, ``sin mφ → (−1)^{m+1} sin mφ``; under
    y → −y (φ → −φ): cos rows even, sin rows odd; under z → −z: ``(−1)^{l+m}`` (even / odd matrix).
    bx, by, bz = 1 where the row changes sign.
    """
    out = []
    for bz, rows in enumerate(_layout(L)):
        cls = [[] for _ in range(4)]
        for i, (_ell, m, kind) in enumerate(rows):
            bx = (m % 2) if kind == "c" else ((m + 1) % 2)
            by = 0 if kind == "c" else 1
            cls[bx + 2 * by].append(i)
        out.append(tuple(np.array(c, dtype=np.intp) for c in cls))
    return tuple(out)  # (even classes κ = 0..3, odd classes κ = 4..7)


def _octant_Y_chunks(reps, L):
    """Yield ``(i0, i1, [Y_κ for κ = 0..7])``: SH rows of class κ at the octant representatives."""
    cls = _octant_row_classes(L)
    ch = _chunk(L)
    for i0 in range(0, reps.shape[0], ch):
        i1 = min(reps.shape[0], i0 + ch)
        Ye, Yo = _real_sh_parity(reps[i0:i1], L)
        yield i0, i1, [Ye[c] for c in cls[0]] + [Yo[c] for c in cls[1]]


def _project_octant(dirs, W, L, orb, chunks=None):
    """:func:`_project` for an octant-symmetric set: ``a_κ = Y_κ(reps) · Σ_g χ_κ(g) W(σ_g reps)``."""
    ev_l, od_l = _row_layout(L)
    cls = _octant_row_classes(L)
    acc = [np.zeros((ev_l.size, W.shape[1])), np.zeros((od_l.size, W.shape[1]))]
    Wk = np.einsum("kg,ogq->koq", _walsh8(), W[orb])  # (8, n_oct, Q) class-projected weights
    reps = dirs[orb[:, 0]]
    for i0, i1, Yk in chunks if chunks is not None else _octant_Y_chunks(reps, L):
        for kappa in range(8):
            rows = cls[kappa // 4][kappa % 4]
            if rows.size:
                acc[kappa // 4][rows] += Yk[kappa] @ Wk[kappa, i0:i1]
    return acc[0], acc[1]


def _evaluate_octant(dirs, Be, Bo, L, orb, chunks=None):
    """:func:`_evaluate` for an octant-symmetric set: ``f(σ_g r) = Σ_κ χ_κ(g) Y_κ(r)ᵀ B_κ``."""
    cls = _octant_row_classes(L)
    n_oct = orb.shape[0]
    V = np.zeros((8, n_oct, Be.shape[1]))
    reps = dirs[orb[:, 0]]
    for i0, i1, Yk in chunks if chunks is not None else _octant_Y_chunks(reps, L):
        for kappa in range(8):
            rows = cls[kappa // 4][kappa % 4]
            if rows.size:
                V[kappa, i0:i1] = Yk[kappa].T @ (Be if kappa < 4 else Bo)[rows]
    vals = np.einsum("kg,kop->gop", _walsh8(), V)  # (8, n_oct, P)
    out = np.empty((dirs.shape[0], Be.shape[1]))
    out[orb.T.reshape(-1)] = vals.reshape(-1, Be.shape[1])
    return out


def _project(dirs, W, L):
    """a = Σ_j W_j Y(ω_j) in :func:`_row_layout` order: (a_even, a_odd)."""
    orb = _octant_orbits(dirs)
    if orb is not None:
        return _project_octant(dirs, W, L, orb)
    ev_l, od_l = _row_layout(L)
    ae = np.zeros((ev_l.size, W.shape[1]))
    ao = np.zeros((od_l.size, W.shape[1]))
    pairs = _mirror_pairs(dirs)
    if pairs is None:
        h, mir = np.arange(dirs.shape[0]), np.zeros(0, dtype=int)
    else:
        h, mir = pairs
    Wm = np.zeros((h.size, W.shape[1]))
    Wm[: mir.size] = W[mir]
    We, Wo = W[h] + Wm, W[h] - Wm
    ch = _chunk(L)
    for i0 in range(0, h.size, ch):
        Ye, Yo = _real_sh_parity(dirs[h[i0 : i0 + ch]], L)
        ae += Ye @ We[i0 : i0 + ch]
        ao += Yo @ Wo[i0 : i0 + ch]
    return ae, ao


def _evaluate(dirs, Be, Bo, L):
    orb = _octant_orbits(dirs)
    if orb is not None:
        return _evaluate_octant(dirs, Be, Bo, L, orb)
    out = np.empty((dirs.shape[0], Be.shape[1]))
    pairs = _mirror_pairs(dirs)
    if pairs is None:
        h, mir = np.arange(dirs.shape[0]), np.zeros(0, dtype=int)
    else:
        h, mir = pairs
    ch = _chunk(L)
    for i0 in range(0, h.size, ch):
        idx = h[i0 : i0 + ch]
        Ye, Yo = _real_sh_parity(dirs[idx], L)
        ve = Ye.T @ Be
        vo = Yo.T @ Bo
        out[idx] = ve + vo
        k = max(0, min(mir.size - i0, idx.size))  # the first k of this chunk have mirrors
        if k:
            out[mir[i0 : i0 + k]] = ve[:k] - vo[:k]
    return out


def _to_standard(ae, ao, L):
    """Convert (a_even, a_odd) in internal row order to the standard l²+l+m order."""
    ev, od = _layout(L)
    std = np.empty(((L + 1) ** 2,) + ae.shape[1:])
    std[_std_index(ev)] = ae
    if od:
        std[_std_index(od)] = ao
    return std


def _from_standard(std, L):
    ev, od = _layout(L)
    return std[_std_index(ev)], std[_std_index(od)] if od else std[:0]


def real_sh(dirs, L: int) -> np.ndarray:
    """Real orthonormal SH ``Y_lm(d)`` for l ≤ L, shape ``dirs.shape[:-1] + ((L+1)²,)``, index l²+l+m.

    ``Y_l0 = P̄_l0``, ``Y_lm = √2 P̄_lm cos(mφ)``, ``Y_l,−m = √2 P̄_lm sin(mφ)`` (m > 0), polar axis +z,
    no Condon–Shortley phase.
    """
    d = np.asarray(dirs, dtype=np.float64)
    L = int(L)
    Ye, Yo = _real_sh_parity(d.reshape(-1, 3), L)
    Y = _to_standard(Ye, Yo, L)
    return np.moveaxis(Y, 0, -1).reshape(d.shape[:-1] + ((L + 1) ** 2,))


def sh_project(cube, L: int) -> np.ndarray:
    """Discrete SH projection ``a_lm = Σ_j L_j Y_lm(ω_j) Ω_j`` with exact texel solid angles.

    Returns
    -------
    ndarray ((L+1)², C) float64, index l² + l + m
    """
    a, _ = check_cube(cube)
    n = a.shape[1]
    L = int(L)
    dirs = envmap.texel_directions(n).reshape(-1, 3)
    w = a.reshape(-1, a.shape[-1]) * envmap.cube_solid_angles(n).reshape(-1, 1)
    ae, ao = _project(dirs, w, L)
    return _to_standard(ae, ao, L)


def sh_evaluate(coeffs, dirs) -> np.ndarray:
    """Evaluate ``Σ_lm a_lm Y_lm(d)``; ``coeffs`` ((L+1)², C) in l²+l+m order → (..., C)."""
    coeffs = np.asarray(coeffs, dtype=np.float64)
    if coeffs.ndim == 1:
        coeffs = coeffs[:, None]
    L = int(round(math.sqrt(coeffs.shape[0]))) - 1
    if (L + 1) ** 2 != coeffs.shape[0]:
        raise LayoutError(f"SH coefficient array must have (L+1)^2 rows, got {coeffs.shape[0]}")
    d = np.asarray(dirs, dtype=np.float64)
    be, bo = _from_standard(coeffs, L)
    return _evaluate(d.reshape(-1, 3), be, bo, L).reshape(d.shape[:-1] + (coeffs.shape[1],))


def sh_lobe_convolve(src_dirs, weights, out_dirs, kernel_coeffs) -> np.ndarray:
    """``Σ_l k_l Σ_m a_lm Y_lm(r)`` with ``a_lm = Σ_j weights_j Y_lm(ω_j)``, for several kernels at once.

    The SH matrix is built in chunks of directions (≈ 128 MB) for the projection and again for the
    evaluation; all kernels share both passes (one matrix product with K·Q columns).  Direction sets
    symmetric under z → −z (every cube texel grid) are processed as mirror pairs, halving the work
    (parity ``(−1)^{l+m}`` of the real SH); sets symmetric under all three sign flips x → −x, y → −y,
    z → −z (every even-sized cube texel grid) use only the positive octant, one eighth of the SH
    matrix (each row of the real SH changes sign or not under each flip, see
    :func:`_octant_row_classes`).  When ``src_dirs`` and ``out_dirs`` are the same set, the SH matrix
    is built once (if ≤ 256 MB) for both passes.

    Parameters
    ----------
    src_dirs : (M, 3) unit directions ω_j
    weights : (M, Q) values × solid angle
    out_dirs : (P, 3) output directions r
    kernel_coeffs : (K, L+1) Funk–Hecke eigenvalues per kernel

    Returns
    -------
    ndarray (K, P, Q) float64
    """
    kc = np.atleast_2d(np.asarray(kernel_coeffs, dtype=np.float64))
    K, L1 = kc.shape
    L = L1 - 1
    W = np.asarray(weights, dtype=np.float64)
    Q = W.shape[1]
    src = np.asarray(src_dirs, dtype=np.float64)
    dst = np.asarray(out_dirs, dtype=np.float64)
    chunks = None
    same = src is dst or (src.shape == dst.shape and np.array_equal(src, dst))
    orb = _octant_orbits(src) if same else None
    if orb is not None and orb.shape[0] * (L + 1) ** 2 <= _SH_CACHE_ELEMS:
        # same directions in and out (output size = input size): build the SH matrix once
        chunks = list(_octant_Y_chunks(src[orb[:, 0]], L))
    if chunks is not None:
        ae, ao = _project_octant(src, W, L, orb, chunks)
    else:
        ae, ao = _project(src, W, L)
    ev_l, od_l = _row_layout(L)
    Be = (kc[:, ev_l, None] * ae[None]).transpose(1, 0, 2).reshape(-1, K * Q)  # Funk–Hecke: c_l a_lm
    Bo = (kc[:, od_l, None] * ao[None]).transpose(1, 0, 2).reshape(-1, K * Q)
    if chunks is not None:
        out = _evaluate_octant(dst, Be, Bo, L, orb, chunks)
    else:
        out = _evaluate(dst, Be, Bo, L)
    return out.reshape(-1, K, Q).transpose(1, 0, 2)


# ----------------------------------------------------------------------------------------------
# hybrid SH convolution with bound
# ----------------------------------------------------------------------------------------------
def _bright_gather(out_dirs, b_dirs, b_w, s_list, chunk_elems=1 << 22):
    """Exact Σ_b w_b max(r·ω_b, 0)^s for every r (K, P, C)."""
    P = out_dirs.shape[0]
    K = len(s_list)
    C = b_w.shape[1]
    res = np.zeros((K, P, C))
    nb = b_dirs.shape[0]
    if nb == 0:
        return res
    chunk = max(1, chunk_elems // nb)
    for i0 in range(0, P, chunk):
        i1 = min(P, i0 + chunk)
        c = out_dirs[i0:i1] @ b_dirs.T
        pos = c > 0
        logc = np.full(c.shape, -np.inf)
        np.log(c, out=logc, where=pos)
        for k, s in enumerate(s_list):
            res[k, i0:i1] = np.exp(s * logc) @ b_w
    return res


def _threshold_candidates(lum):
    order = np.sort(lum.ravel())[::-1]
    cands = []
    for k in (0, 8, 32, 128, 512, 2048):
        if k < order.size:
            tau = float(order[k])  # texels strictly above tau are gathered: at most k of them
            cands.append((int(np.count_nonzero(lum > tau)), tau))
    return cands


def _plan(rad, omega, src, n_out, s_list, rtol, rho, hybrid, tau, L_max, estimate=False):
    """Choose the sun threshold τ and band limit L from the a-priori bound and a cost model.

    Returns dict with ``L`` (joint band limit; None if no candidate meets rtol within L_max and
    ``estimate`` is False), ``tau``, ``L_per_s`` (band limit each exponent needs for the rigorous bound,
    None if > L_max), ``L_est`` (exponent → band limit used in estimate mode) and ``cost``.
    """
    C = rad.shape[1]
    lum = rad.max(axis=1)
    m_min = float(rad.min())
    if not hybrid:
        cands = [(0, float(rad.max()))]
    elif tau is not None:
        cands = [(int(np.count_nonzero(lum > tau)), float(tau))]
    else:
        cands = _threshold_candidates(lum)
    # a-priori lower estimate of the output: a cheap low-order preview of the clipped remainder
    tau_p = cands[-1][1]
    rem = np.minimum(rad, tau_p)
    sub = slice(None, None, max(1, src.shape[0] // 2000))
    prev = sh_lobe_convolve(src, np.concatenate([rem, np.ones((rem.shape[0], 1))], 1) * omega[:, None],
                            src[sub], zonal_coefficients(float(np.median(s_list)), 4)[None])[0]
    y_lo = max(m_min, 0.8 * float(np.min(prev[:, :C] / np.maximum(prev[:, C:], 1e-300))), 1e-300)
    best = None
    K = len(s_list)
    for nb, tau_k in cands:
        eta_t = 0.8 * rtol * min(1.0, y_lo / max(tau_k - m_min, 1e-300))
        Ls = [choose_band_limit(s, eta_t, rho, L_max) for s in s_list]
        L_est = {s: _estimate_band_limit(s, rtol, rho) for s, x in zip(s_list, Ls) if x is None} if estimate else {}
        feas = [x for x in Ls if x is not None] + list(L_est.values())
        if not feas:
            continue
        Lk = max(feas + [1])
        cost = sh_cost(Lk, src.shape[0], n_out, len(feas) + len(L_est), C + 1) + bright_cost(nb, n_out, len(feas))
        key = (-len(feas), cost)  # serve as many exponents as possible, then cheapest
        if best is None or key < best[0]:
            best = (key, Lk, nb, tau_k, Ls, L_est)
    if best is None:
        return {"L": None, "tau": cands[-1][1], "L_per_s": [None] * K, "L_est": {}, "cost": np.inf}
    return {"L": best[1], "tau": best[3], "L_per_s": best[4], "L_est": best[5], "cost": best[0][1]}


#: largest band limit used for exponents whose rigorous bound cannot meet rtol (estimate mode)
SH_L_EST_MAX = 64


def _estimate_band_limit(s, rtol, rho):
    """Band limit for the estimate mode: E_L/D ≤ rtol/2 (spread ≈ output), within [16, SH_L_EST_MAX]."""
    L = choose_band_limit(s, 0.5 * rtol, rho, SH_L_EST_MAX)
    return int(min(max(L if L is not None else SH_L_EST_MAX, 16), SH_L_EST_MAX))


#: seconds per cost unit of :func:`sh_cost` (fitted: 128² faces, K = 8, Q = 4, L = 40 / 80 on the shared
#: 2-core machine, 1 BLAS thread: 1.2 s / 6.2 s)
SECONDS_PER_UNIT = 8e-10

#: fixed cost of one SH call (planning preview, bound tables), in units (≈ 0.04 s)
SH_OVERHEAD_UNITS = 5e7


def sh_cost(L, n_src, n_out, K, Q):
    """Cost model of :func:`sh_lobe_convolve` (units of :data:`SECONDS_PER_UNIT`).

    Refitted after the octant-symmetric SH matrix (one eighth of the directions, built once for
    projection and evaluation).  Measured wall time of :func:`sh_lobe_convolve`, 128² faces, Q = 4, 1 BLAS
    thread, K = 1 … 8 kernels: 0.12–0.19 s at L = 40, 0.58–0.90 s at L = 80 (nearly independent of K, as the
    small K·Q term says; the model is conservative and used for routing and job order only).
    """
    return (L + 1) ** 2 * (n_src + n_out) * 0.5 * (4.0 + 0.03 * K * Q)


def bright_cost(n_bright, n_out, K):
    """Cost model of the exact gather from the bright texels (same units as :func:`sh_cost`)."""
    return n_bright * n_out * (3.0 + 15.0 * K)


def plan_sh(cube, exponents, *, rtol=1e-3, out_size=None, hybrid=True, L_max=SH_L_MAX, estimate=False):
    """A-priori plan of the hybrid SH route: band limit each exponent needs and the model cost.

    Returns dict ``L`` (joint band limit or None), ``tau``, ``L_per_s`` (list, None = would need more
    than L_max), ``cost`` (model units, comparable with :func:`sh_cost`).
    """
    a, _ = check_cube(cube)
    n = a.shape[1]
    out_size = check_out_size(out_size, n)
    s_list = [check_exponent(s) for s in np.atleast_1d(np.asarray(exponents, dtype=object))]
    src = envmap.texel_directions(n).reshape(-1, 3)
    omega = np.ascontiguousarray(envmap.cube_solid_angles(n)).reshape(-1)
    rad = a.reshape(-1, a.shape[-1])
    return _plan(rad, omega, src, 6 * out_size * out_size, s_list, rtol, texel_max_radius(n), hybrid, None, L_max,
                 estimate)



def convolve_sh_many(
    cube,
    exponents,
    *,
    rtol: float = 1e-3,
    L: int | None = None,
    hybrid: bool = True,
    tau: float | None = None,
    out_size: int | None = None,
    normalized: bool = True,
    L_max: int = SH_L_MAX,
    estimate: bool = False,
    plan: dict | None = None,
):
    """SH (optionally hybrid) convolution for several exponents sharing one SH pass.

    Parameters
    ----------
    cube : array (6, N, N[, C])
    exponents : sequence of float ≥ 1 (finite)
    rtol : float
        Target relative error used to choose the band limit and the sun threshold (not guaranteed:
        check the returned bound).
    L : int, optional
        Force the band limit (otherwise chosen from the bound).
    hybrid : bool
        Convolve texels above the threshold τ exactly (default True).
    tau : float, optional
        Force the threshold (radiance, compared with the per-texel channel maximum).
    out_size : int, optional
    normalized : bool
        Lobe average (default) or literal Eq. 4.
    L_max : int
        Cap for the automatically chosen band limit (rigorous mode).
    estimate : bool
        For exponents whose rigorous bound cannot meet rtol within L_max (broad lobes with a kinked
        horizon, s ≈ 1), also evaluate the band-limit-L/2 result and report the **estimate**
        ``|y_L − y_{L/2}| / y_L`` (the error of the coarser result, which over-estimates the error of
        y_L when the truncation error decreases with L).  Not a proof; flagged in ``info["bound_kind"]``.
        Default False: measured on the sky+sun environment at 32² (s = 1, L = 32…96) the true error
        exceeded this estimate by up to ~2000× at single texels, so :func:`ibl_ref.convolve.convolve`
        never relies on it.
    plan : dict, optional
        Result of :func:`plan_sh` for the same cube/exponents/rtol (avoids planning twice).

    Returns
    -------
    maps : ndarray (K, 6, n, n, C)
    rel_bound : ndarray (K, 6, n, n) — per-texel relative error bound (max over channels; inf where the
        bound is useless, e.g. zero output); rigorous unless ``info["bound_kind"][k] == "estimate"``
    info : dict (L, tau, n_bright, bound_kind list, timings)
    """
    t0 = time.perf_counter()
    a, squeeze = check_cube(cube)
    n = a.shape[1]
    out_size = check_out_size(out_size, n)
    s_list = [check_exponent(s) for s in np.atleast_1d(np.asarray(exponents, dtype=object))]
    if not s_list:
        raise IBLError("no Phong exponents given")
    if any(not np.isfinite(s) for s in s_list):
        raise IBLError("the SH route cannot represent the mirror (s = inf); use method='exact'")
    if not (isinstance(rtol, (int, float, np.floating)) and rtol > 0 and np.isfinite(rtol)):
        raise IBLError(f"rtol must be a positive finite number, got {rtol!r}")
    C = a.shape[-1]
    src = envmap.texel_directions(n).reshape(-1, 3)
    omega = np.ascontiguousarray(envmap.cube_solid_angles(n)).reshape(-1)
    rad = a.reshape(-1, C)
    out_dirs = src if out_size == n else envmap.texel_directions(out_size).reshape(-1, 3)
    rho = texel_max_radius(n)

    # --- threshold / band limit -----------------------------------------------------------
    if L is None:
        if plan is None:
            plan = _plan(rad, omega, src, out_dirs.shape[0], s_list, rtol, rho, hybrid, tau, L_max, estimate)
        L_use, tau_use = plan["L"], plan["tau"]
        est_idx = [k for k, x in enumerate(plan["L_per_s"]) if x is None] if estimate else []
        if L_use is None:  # nothing meets rtol within L_max: use L_max with the largest bright set
            L_use = L_max
    else:
        L_use = int(L)
        if not hybrid:
            tau_use = float(rad.max())
        elif tau is not None:
            tau_use = float(tau)
        else:
            tau_use = _threshold_candidates(rad.max(axis=1))[-1][1]
        est_idx = list(range(len(s_list))) if estimate else []
    t_plan = time.perf_counter()

    # --- split and convolve -----------------------------------------------------------------
    bright = rad.max(axis=1) > tau_use
    rem = np.minimum(rad, tau_use)
    excess = rad[bright] - rem[bright]
    kcoef = np.stack([zonal_coefficients(s, L_use) for s in s_list])
    if est_idx:  # the same kernels truncated at L/2 (estimate mode)
        half = kcoef[est_idx].copy()
        half[:, L_use // 2 + 1 :] = 0.0
        kcoef = np.concatenate([kcoef, half])
    Wq = np.concatenate([rem, np.ones((rem.shape[0], 1))], axis=1) * omega[:, None]
    shq = sh_lobe_convolve(src, Wq, out_dirs, kcoef)  # (K, P, C+1)
    t_sh = time.perf_counter()
    nb = _bright_gather(out_dirs, src[bright], excess * omega[bright][:, None], s_list)  # exact part
    t_gather = time.perf_counter()

    # --- bound --------------------------------------------------------------------------------
    K = len(s_list)
    P = out_dirs.shape[0]
    maps = np.empty((K, P, C))
    rel = np.empty((K, P))
    kinds = []
    m_rem = float(rem.min())
    tau_eff = float(rem.max())
    for k, s in enumerate(s_list):
        E_L = legendre_series_truncation_envelope(s, L_use, rho)
        E_L += _FOUR_PI * np.finfo(float).eps * (L_use + 1) ** 2  # rounding of the O(L²) SH sums
        num = shq[k, :, :C] + nb[k]
        den = shq[k, :, C:]
        if normalized:
            ok_den = den > E_L
            # den ≤ E_L: the truncated lobe weight is not even positive-definite there; the value is
            # kept (num/den, or 0 if den ≤ 0) but its bound is inf
            y = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
            eta = np.where(ok_den, E_L / np.where(ok_den, den, 1.0), np.inf)
            with np.errstate(invalid="ignore", divide="ignore"):
                A = np.maximum((tau_eff - m_rem) * eta, np.maximum(y - m_rem, 0.0) * eta / np.maximum(1.0 - eta, 1e-300))
                A = np.where(eta < 1.0, A, np.inf)
        else:
            y = num
            A = np.full_like(y, tau_eff * E_L)
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.where(y > A, A / np.maximum(y - A, 1e-300), np.inf)
        maps[k] = y
        rel[k] = r.max(axis=1)
        kinds.append("rigorous")
        if k in est_idx and not float(rel[k].max()) <= rtol:
            j = K + est_idx.index(k)
            y_half = (shq[j, :, :C] + nb[k]) / (shq[j, :, C:] if normalized else 1.0)
            with np.errstate(invalid="ignore", divide="ignore"):
                est = np.abs(y - y_half) + 1e-12 * np.abs(y)
                est = np.where(y > est, est / np.maximum(y - est, 1e-300), np.inf)
            rel[k] = est.max(axis=1)
            kinds[-1] = "estimate"
    maps = maps.reshape((K, 6, out_size, out_size, C))
    if squeeze:
        maps = maps[..., 0]
    info = {
        "L": int(L_use),
        "tau": float(tau_use),
        "n_bright": int(np.count_nonzero(bright)),
        "texel_radius_rad": rho,
        "bound_kind": kinds,
        "time_plan_s": t_plan - t0,
        "time_sh_s": t_sh - t_plan,
        "time_bright_s": t_gather - t_sh,
        "time_total_s": time.perf_counter() - t0,
    }
    return maps, rel.reshape((K, 6, out_size, out_size)), info


def convolve_sh(cube, s, **kwargs):
    """Single-exponent :func:`convolve_sh_many`; returns ``(maps (6,n,n,C), rel_bound (6,n,n), info)``."""
    maps, rel, info = convolve_sh_many(cube, [s], **kwargs)
    return maps[0], rel[0], info
