"""The rounding of the compiled kernels of the Phong-lobe convolution (Knuth et al. 2014, Sec. 3.2, Eq. 4), which
the routes add to their rigorous bounds, and the block sizes the kernels share with their callers.

:mod:`ibl_ref.groundtruth.kernels.numba_loops` holds the kernels; this module imports neither numba nor them, so
the routes compute their bounds the same way whether or not numba is installed.

Rounding
    The kernels compute the weights ``max(r·ω, 0)^s`` with their own elementary functions (``exp_``, ``log_``,
    ``powi_``) and sum them in an order chosen by the compiler (vectorised reductions); the routes add the
    rounding stated here to their rigorous bounds.

Elementary functions
    ``exp_`` — Cody–Waite reduction ``u = k ln 2 + f``, ``|f| ≤ ln2/2``, the Taylor polynomial of degree 13
    (remainder ≤ 0.347^14/14! < 4.5e-18), ``2^k`` put into the exponent field; 0 below 2^-1021.  Relative
    error ≤ :data:`EXP_REL` (measured: 1.22 ulp over 2·10⁶ arguments in [−745, 709]).
    ``log_`` — ``c = 2^e m``, ``m ∈ [√½, √2)``, ``log m = 2 atanh z``, ``z = (m−1)/(m+1)`` (|z| ≤ 0.1716, the
    odd series to z^21, remainder < 2e-18); absolute error ≤ :data:`LOG_ABS` + |log c|·:data:`LOG_REL`
    (measured 3.2e-16 relative).
    ``powi_`` — ``c^s`` for integers ``1 ≤ s ≤ 8191`` by binary powering (13 fixed steps): every result
    is a product of s factors c formed by s − 1 roundings, relative error ≤ γ_{s−1} (Higham, *Accuracy and
    Stability of Numerical Algorithms*, 2nd ed., Lemma 3.1 applied to the multiplication tree).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["VEC", "BRIGHT_GROUP", "SH_BLOCK", "POINT_BLOCK", "EXP_REL", "LOG_ABS", "LOG_REL", "POWI_MAX", "U64", "C0",
           "weight_error", "sum_error"]

#: the candidate lists of the gathers are padded to a multiple of this many entries (zero weight), so that the
#: vectorised loops never fall back to their scalar remainder (8 lanes × 4-way interleave)
VEC = 32
#: bright texels per group of the sparse gather's bright list (one bounding cone per group: a tile skips the groups
#: out of its reach without testing their texels)
BRIGHT_GROUP = 32
#: directions per block of the fused SH passes (the Legendre rows of one block, (L+1) × 3 × 128 float64, stay in
#: the L2 cache)
SH_BLOCK = 128
#: output directions per block of the bright-texel gather of the SH route (their sums stay in the cache)
POINT_BLOCK = 256

#: relative error bound of :func:`ibl_ref.groundtruth.kernels.numba_loops.exp_` for results ≥ 2^-1021 (Taylor remainder 4.5e-18/e^-0.347, Horner
#: rounding γ_26·e^{0.694} ≈ 5.8e-15, the reduction's f off by ≤ 2u·|f| + |k|·2^-60: together < 8e-15)
EXP_REL = 8e-15
#: absolute / relative parts of the error bound of :func:`ibl_ref.groundtruth.kernels.numba_loops.log_` (the series ≤ 6u relative to |log m| ≤ 0.35,
#: e·ln 2 with ln 2 split hi + lo: ≤ 2u·|e ln 2|; the final sums: u·|log c|)
LOG_ABS = 4e-16
LOG_REL = 4.5e-16
#: largest integer exponent of :func:`ibl_ref.groundtruth.kernels.numba_loops.powi_` (13 binary digits)
POWI_MAX = 8191
#: unit roundoff of float64
U64 = 2.0 ** -53

#: the weights' error bound is relative for pairs with r·ω ≥ this and absolute below it
C0 = 0.05


def weight_error(s: float, integer: bool, reference: bool = False):
    """``(η, ε)``: the rounding of one computed weight ``max(r·ω, 0)^s`` of :func:`ibl_ref.groundtruth.kernels.numba_loops.tile_gather` (``(c/c_max)^s``
    with ``reference``) is ≤ η·w for pairs with c = r·ω ≥ :data:`C0` and ≤ ε in absolute terms (the weight
    scale is 1: c ≤ 1, or the row's largest cosine) below, including the weights left out or returned as 0
    (below e^-700 / 2^-1021).

    The cosine from two float64 unit vectors is off by Δ ≤ γ_3 + 2u (each vector's own rounding u), i.e. by
    the factor (1 ± Δ/c)^s ≤ (1 + Δ/C0)^s in the weight; the power adds γ_{s−1} (:func:`ibl_ref.groundtruth.kernels.numba_loops.powi_`) or, for
    ``exp(s·log c)``, an exponent off by ≤ 2s·(:data:`LOG_ABS` + |log C0|·:data:`LOG_REL`) + 745·2u (log of c and of
    the reference; arguments below −745 give weights below e^-745, counted in ε) and :data:`EXP_REL`.  Below C0:
    |ĉ^s − c^s| ≤ s·Δ·(C0 + Δ)^{s−1} (mean value theorem, s ≥ 1) plus η·(C0 + Δ)^s; ĉ ≤ 0 gives 0 where the
    true weight is ≤ Δ^s."""
    gam3 = 3 * U64 / (1 - 3 * U64)
    d = gam3 + 2 * U64
    if integer:
        n = max(int(s) - 1, 0)
        e_f = n * U64 / (1 - n * U64)
    else:
        du = 2.0 * s * (LOG_ABS + abs(math.log(C0)) * LOG_REL) + 745.0 * 2 * U64
        e_f = math.expm1(du) * (1 + EXP_REL) + EXP_REL
    eta = math.exp(s * math.log1p(d / C0)) * (1 + e_f) - 1
    eps = s * d * (C0 + d) ** (s - 1) * (1 + e_f) + e_f * (C0 + d) ** s + d ** s + math.exp(-700.0)
    return eta, eps


def sum_error(m):
    """γ_m: relative error of a float64 sum of m non-negative terms, in any order (the kernels' reductions are
    vectorised, so their order is the compiler's); ``m`` a number or an array."""
    m = np.asarray(m, dtype=np.float64)
    return m * U64 / (1 - m * U64)
