"""Index tables of the real spherical harmonics of :mod:`ibl_ref.groundtruth.sh_basis`.

The row layout of the SH matrices (split by the parity of l+m), the associated-Legendre recurrence
coefficients and the tables that the compiled SH passes of :mod:`ibl_ref.groundtruth.kernels.numba_loops`
take.  Pure index bookkeeping, no numerics beyond the recurrence coefficients

    a_lm = sqrt((4l² − 1) / (l² − m²)),   b_lm = sqrt(((l − 1)² − m²) / (4(l − 1)² − 1)),

of the standard three-term recurrence P_l^m = a_lm (x P_{l−1}^m − b_lm P_{l−2}^m) of the orthonormalised
associated Legendre functions.  It sits below both modules so that neither imports the other at load time.
"""
from __future__ import annotations

import functools

import numpy as np


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


@functools.lru_cache(maxsize=512)
def _recurrence_coeffs(ell):
    m = np.arange(ell - 1, dtype=np.float64)
    a = np.sqrt((4.0 * ell * ell - 1.0) / (ell * ell - m * m))
    b = np.sqrt(((ell - 1.0) ** 2 - m * m) / (4.0 * (ell - 1.0) ** 2 - 1.0))
    return a[:, None], b[:, None]


@functools.lru_cache(maxsize=16)
def compiled_tables(L):
    """Tables of the compiled SH passes (:func:`ibl_ref.groundtruth.kernels.numba_loops.sh_project` /
    ``sh_matrix``): ``row_of[ℓ, m, kind]`` (the row in the even or odd matrix of :func:`_layout`; kind 0 =
    cos, 1 = sin), ``cls_of[ℓ, m, kind]`` (its octant class κ, :func:`_octant_row_classes`) and the Legendre
    recurrence coefficients ``a[ℓ, m]``, ``b[ℓ, m]`` (:func:`_recurrence_coeffs`)."""
    row_of = np.full((L + 1, L + 1, 2), -1, dtype=np.int64)
    cls_of = np.full((L + 1, L + 1, 2), -1, dtype=np.int64)
    for bz, rows in enumerate(_layout(L)):
        for i, (ell, m, kind) in enumerate(rows):
            k = 0 if kind == "c" else 1
            bx = (m % 2) if kind == "c" else ((m + 1) % 2)
            row_of[ell, m, k] = i
            cls_of[ell, m, k] = bx + 2 * k + 4 * bz
    a_tab = np.zeros((L + 1, max(L, 1)))
    b_tab = np.zeros((L + 1, max(L, 1)))
    for ell in range(2, L + 1):
        a, b = _recurrence_coeffs(ell)
        a_tab[ell, : ell - 1] = a[:, 0]
        b_tab[ell, : ell - 1] = b[:, 0]
    return row_of, cls_of, a_tab, b_tab
