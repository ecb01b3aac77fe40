"""The compiled backend's loops (numba ``@njit``) of the Phong-lobe convolution (Knuth et al. 2014, Sec. 3.2, Eq. 4).

The NumPy backend (:mod:`ibl_ref.groundtruth.kernels.numpy_backend`) is the reference; these loops compute the
same quadratures (the weights ``max(r·ω_j, 0)^s Ω_j`` of Eq. 4) without the temporaries, index matrices and
repeated passes of the array code.  Each states the rounding of its float64 arithmetic, which
:mod:`ibl_ref.groundtruth.kernels.rounding` bounds and the routes add to their rigorous bounds.  Nothing here is
called directly: :class:`ibl_ref.groundtruth.kernels.numba_backend.CompiledKernels` implements the kernel
interface with them.

Sparse route: :func:`tile_gather` (the weighted sums of every tile's cap), :func:`tile_bounds` (the averages and
the route's rigorous per-texel bound from those sums) and :func:`cone_extremes`.  Moment route: :func:`band_exact`,
:func:`band_brackets`.  SH route: :func:`point_gather`, :func:`sh_project`, :func:`sh_matrix`.  Elementary
functions (vectorisable: no calls, no branches): :func:`exp_`, :func:`log_`, :func:`powi_`.

Every function is ``numba.njit(cache=True, nogil=True, error_model="numpy")``: compiled on first use and kept in
numba's cache (``__pycache__`` next to this file, or ``$NUMBA_CACHE_DIR``).  ``IBL_REF_NUMBA_CACHE=0`` compiles
without the cache (the backend sets it when the cache cannot be written or read, after one line on stderr).
"""

from __future__ import annotations

import math
import os
import sys

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from .rounding import BRIGHT_GROUP, POINT_BLOCK, SH_BLOCK, VEC

__all__ = ["exp_", "log_", "powi_", "tile_gather", "tile_bounds", "cap_count", "cone_extremes", "band_exact",
           "band_brackets", "point_gather", "sh_project", "sh_matrix", "ggx_tree"]

#: numba's cache for these functions (``IBL_REF_NUMBA_CACHE=0``: none)
CACHE = os.environ.get("IBL_REF_NUMBA_CACHE", "1").strip() != "0"


def _jit(**kw):
    """``numba.njit(cache=CACHE, nogil=True, error_model="numpy", **kw)``; without the cache (one line on stderr) where
    numba finds no folder it can write it to."""
    global CACHE

    def deco(fn):
        global CACHE
        if CACHE:
            try:
                return numba.njit(cache=True, nogil=True, error_model="numpy", **kw)(fn)
            except RuntimeError as exc:  # "cannot cache function ...: no locator available"
                CACHE = False
                print(f"ibl_ref: no writable folder for numba's cache ({exc}); the kernels are compiled in every "
                      "process", file=sys.stderr)
        return numba.njit(cache=False, nogil=True, error_model="numpy", **kw)(fn)

    return deco


# ----------------------------------------------------------------------------------------------
# elementary functions
# ----------------------------------------------------------------------------------------------
@intrinsic
def _f2i(typingctx, x):
    """The bits of a float64 as an int64 (an LLVM bitcast: vectorisable)."""
    sig = types.int64(types.float64)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return sig, codegen


@intrinsic
def _i2f(typingctx, x):
    """An int64 read as the bits of a float64."""
    sig = types.float64(types.int64)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return sig, codegen


_LN2_HI = 6.93147180369123816490e-01  # 0x3FE62E42FEE00000: k·_LN2_HI is exact for |k| < 2^11
_LN2_LO = 1.90821492927058770002e-10
_LOG2E = 1.4426950408889634
_SQRT2 = 1.4142135623730951
#: half-angle of the cone around a face's axis that holds the face (its corners: atan √2)
_FACE_CONE = 0.9553166181245093


@_jit(fastmath={"contract"})
def exp_(u):
    """e^u for u ≤ 709 (0 below ≈ −708.4: results under 2^-1021 are returned as 0)."""
    u = min(max(u, -745.0), 709.0)
    kf = math.floor(u * _LOG2E + 0.5)
    f = (u - kf * _LN2_HI) - kf * _LN2_LO
    p = 1.0 / 6227020800.0
    p = p * f + 1.0 / 479001600.0
    p = p * f + 1.0 / 39916800.0
    p = p * f + 1.0 / 3628800.0
    p = p * f + 1.0 / 362880.0
    p = p * f + 1.0 / 40320.0
    p = p * f + 1.0 / 5040.0
    p = p * f + 1.0 / 720.0
    p = p * f + 1.0 / 120.0
    p = p * f + 1.0 / 24.0
    p = p * f + 1.0 / 6.0
    p = p * f + 0.5
    p = p * f + 1.0
    p = p * f + 1.0
    k = np.int64(kf)
    r = _i2f(_f2i(p) + (k << 52))  # p ∈ [0.70, 1.42]: 2^k·p by the exponent field
    return r if k > -1021 else 0.0


@_jit(fastmath={"contract"})
def log_(c):
    """log c for normal c > 0 (c below 2^-1022 is taken as 2^-1022)."""
    c = max(c, 2.2250738585072014e-308)
    b = _f2i(c)
    e = (b >> 52) - 1023
    m = _i2f((b & 0x000FFFFFFFFFFFFF) | 0x3FF0000000000000)  # c = 2^e m, m ∈ [1, 2)
    big = m > _SQRT2
    m = m * 0.5 if big else m
    e = e + 1 if big else e
    z = (m - 1.0) / (m + 1.0)  # m − 1 exact (Sterbenz)
    z2 = z * z
    p = 1.0 / 21.0
    p = p * z2 + 1.0 / 19.0
    p = p * z2 + 1.0 / 17.0
    p = p * z2 + 1.0 / 15.0
    p = p * z2 + 1.0 / 13.0
    p = p * z2 + 1.0 / 11.0
    p = p * z2 + 1.0 / 9.0
    p = p * z2 + 1.0 / 7.0
    p = p * z2 + 1.0 / 5.0
    p = p * z2 + 1.0 / 3.0
    ef = np.float64(e)
    return (2.0 * z + 2.0 * z * z2 * p) + (ef * _LN2_HI + ef * _LN2_LO)


@_jit(fastmath={"contract"}, inline="always")
def powi_(c, s):
    """c^s for an integer 1 ≤ s ≤ :data:`POWI_MAX` (13 fixed binary-powering steps, branch-free; no squaring
    beyond the highest bit of s, so nothing underflows needlessly)."""
    r = 1.0
    p = c
    for b in range(13):
        r = r * p if (s >> b) & 1 else r
        p = p * p if (s >> (b + 1)) != 0 else 1.0
    return r


@_jit(fastmath={"contract"}, inline="always")
def _pow2k(c, k):
    """c^(2^k) for 0 ≤ k ≤ 12 by k squarings (12 fixed steps, branch-free): the products of :func:`powi_` for
    s = 2^k in the same order, so the same weight bit for bit, at half its operations (no running product, no
    test of the bits)."""
    p = c
    for b in range(12):
        p = p * p if b < k else p
    return p


# ----------------------------------------------------------------------------------------------
# truncated-support gather (sparse route)
# ----------------------------------------------------------------------------------------------
@_jit(fastmath={"contract"})
def _interval(alpha, beta, kappa, w2):
    """``{x : α + βx ≥ κ √(w² + x²)}`` for κ > 0 (convex: a line above a convex curve), as ``(lo, hi, ok)``.

    With D = β² − κ² < 0 the set is the part of the root interval of ``D x² + 2αβ x + α² − κ²w² ≥ 0`` where
    α + βx > 0 (the other part of the squared inequality, α + βx ≤ −κ√…, is the opposite cap; the root
    interval is one or the other, told by the sign at its midpoint −αβ/D).  Near-tangent cases (D ≥ −1e-9)
    return the whole line (a superset).  A discriminant that is negative by rounding only is taken as a point.
    """
    D = beta * beta - kappa * kappa
    if D > -1e-9:
        return -1e300, 1e300, True
    disc = alpha * alpha + D * w2
    scale = alpha * alpha - D * w2
    if disc < -1e-12 * scale:
        return 0.0, 0.0, False
    xm = -alpha * beta / D
    if alpha + beta * xm <= 0.0:
        return 0.0, 0.0, False
    sq = kappa * math.sqrt(max(disc, 0.0)) / (-D)
    return xm - sq, xm + sq, True


@_jit(fastmath={"contract"})
def _index_range(lo, hi, h, n):
    """Texel indices whose centres (i + ½)·h − 1 lie in [lo, hi] widened by 1e-3 texel each side (≫ the error of
    the interval ends), clipped to [0, n − 1] (empty: first > last)."""
    lo = max(lo, -3.0)
    hi = min(hi, 3.0)
    i0 = int(math.ceil((lo + 1.0) / h - 0.5 - 1e-3))
    i1 = int(math.floor((hi + 1.0) / h - 0.5 + 1e-3))
    return max(i0, 0), min(i1, n - 1)


@_jit(fastmath={"contract"})
def _cone_cos(k):
    """cos(acos(k) + atan √2) (π at most): the cap ``d·t ≥ k`` reaches a face only if t·axis is at least this."""
    return math.cos(min(math.acos(k) + _FACE_CONE, math.pi))


@_jit(fastmath={"contract"})
def _face_rows(t, k, f, frames, h, n, k_cone):
    """Row range of face f touched by the cap ``{d : d·t ≥ k}`` and the numbers (a, b, c) = t·(axis, u, v):
    ``(i0, i1, a, b, c, full)`` (``full``: every column of those rows, for caps reaching the face plane's
    horizon); i1 < i0 when the cap misses the face.  ``k_cone`` = :func:`_cone_cos` of k."""
    a = t[0] * frames[f, 0, 0] + t[1] * frames[f, 0, 1] + t[2] * frames[f, 0, 2]
    b = t[0] * frames[f, 1, 0] + t[1] * frames[f, 1, 1] + t[2] * frames[f, 1, 2]
    c = t[0] * frames[f, 2, 0] + t[1] * frames[f, 2, 1] + t[2] * frames[f, 2, 2]
    if k <= 1e-9:
        return 0, n - 1, a, b, c, True
    # the cap misses the face's bounding cone (half-angle atan √2 around the axis)
    if a < k_cone:
        return 0, -1, a, b, c, False
    K = k * k - b * b
    if K <= 1e-9:
        return 0, n - 1, a, b, c, True
    vlo, vhi, ok = _interval(a, c, math.sqrt(K), 1.0)
    if not ok:
        return 0, -1, a, b, c, False
    i0, i1 = _index_range(vlo, vhi, h, n)
    return i0, i1, a, b, c, False


@_jit(fastmath={"contract"})
def _row_cols(a, b, c, k, v, h, n, full):
    """Column range of the row at face-plane v touched by the cap (see :func:`_face_rows`)."""
    if full:
        return 0, n - 1
    lo, hi, ok = _interval(a + c * v, b, k, 1.0 + v * v)
    if not ok:
        return 0, -1
    return _index_range(lo, hi, h, n)


@_jit(fastmath={"contract"})
def cap_count(t, q, frames, n):
    """Number of source texels :func:`tile_gather` collects for the cap of angle q around the unit vector t."""
    h = 2.0 / n
    k = math.cos(min(q + 1e-6, 0.5 * math.pi)) if q + 1e-6 < 0.5 * math.pi else 0.0
    m = 0
    k_cone = _cone_cos(k) if k > 1e-9 else -2.0
    for f in range(6):
        i0, i1, a, b, c, full = _face_rows(t, k, f, frames, h, n, k_cone)
        for i in range(i0, i1 + 1):
            j0, j1 = _row_cols(a, b, c, k, (i + 0.5) * h - 1.0, h, n, full)
            if j1 >= j0:
                m += j1 - j0 + 1
    return m


#: above this many entries the scratch size is counted (:func:`cap_count`) instead of bounded
_SCRATCH_BOUND_MAX = 1 << 20
#: caps below this angle (rad) collect only texels of the cap itself (:func:`_scratch_size`)
_SCRATCH_BOUND_CAP = 0.3


@_jit()
def _scratch_size(caps, frames, n, cen):
    """Entries enough for the texels of every cap of :func:`tile_gather`, without counting them: a texel whose
    centre is within the widened cap (q + 1e-6 rad, ends widened by 1e-3 texel ≤ 2e-3/n rad) lies inside the
    cap grown by its centre-to-corner angle (≤ the half-diagonal √2/n of the face plane: the gnomonic map
    shortens distances), and the texels are disjoint with solid angle ≥ h²/3^{3/2} (h = 2/n; the
    Jacobian (1 + u² + v²)^{-3/2} ≥ 3^{-3/2}), so the count is ≤ cap area / that.  That holds while the
    collected texels are the cap's: caps narrower than :data:`_SCRATCH_BOUND_CAP` rad (no face-plane horizon or
    near-tangent row, whose whole rows or faces :func:`_face_rows` takes, lies within reach of them: that needs
    t·axis ≤ sin q and t·axis ≥ cos(q + atan √2), i.e. q ≥ (π/2 − atan √2)/2 ≈ 0.308).  Wider caps, and caps
    whose bound exceeds :data:`_SCRATCH_BOUND_MAX`, are counted instead (the bound is up to ≈ 5× the count)."""
    h = 2.0 / n
    q = 0.0
    for i in range(caps.shape[0]):
        q = max(q, caps[i])
    grow = 1e-6 + 1e-3 * h + 0.7072 * h
    area = 2.0 * math.pi * (1.0 - math.cos(min(q + grow, math.pi)))
    bound = min(int(area * 5.197 / (h * h)) + 1, 6 * n * n)
    if q + 1e-6 < _SCRATCH_BOUND_CAP and bound <= _SCRATCH_BOUND_MAX:
        return bound
    m = 0
    for i in range(caps.shape[0]):
        m = max(m, cap_count(cen[i], caps[i], frames, n))
    return m


@_jit(fastmath={"contract"}, inline="always")
def _put7(SX, SY, SZ, S0, S1, S2, S3, m, x, y, z, w0, w1, w2, w3):
    """Entry m of the scratch arrays; returns m + 1."""
    SX[m] = x
    SY[m] = y
    SZ[m] = z
    S0[m] = w0
    S1[m] = w1
    S2[m] = w2
    S3[m] = w3
    return m + 1


@_jit(fastmath={"contract"})
def _collect(t, q, frames, n, X, Y, Z, RW, bdirs, brw, gcen, galpha, a_cut, SX, SY, SZ, S0, S1, S2, S3):
    """Copy the source texels of the cap (angle q around t) and then the bright texels within the angle ``a_cut`` of
    t (``t·ω ≥ cos a_cut``; every one when ``a_cut ≥ π``) into the scratch arrays; pad with zero entries to a
    multiple of :data:`~ibl_ref.groundtruth.kernels.rounding.VEC`.  The bright texels come in groups of
    :data:`~ibl_ref.groundtruth.kernels.rounding.BRIGHT_GROUP` (``bdirs`` rows g·BRIGHT_GROUP…) with the unit centre
    ``gcen[g]`` and the largest angle ``galpha[g]`` from it to a member: a group farther than
    ``a_cut + galpha[g] + 1e-9`` rad from t holds no texel the test would keep, and is skipped whole (the
    margin is ≫ the rounding of the dot products, so the texels kept, and their order, are the per-texel test's).
    Returns ``(entries (padding included), bright texels left out)``."""
    h = 2.0 / n
    nn = n * n
    k = math.cos(min(q + 1e-6, 0.5 * math.pi)) if q + 1e-6 < 0.5 * math.pi else 0.0
    m = 0
    k_cone = _cone_cos(k) if k > 1e-9 else -2.0
    for f in range(6):
        i0, i1, a, b, c, full = _face_rows(t, k, f, frames, h, n, k_cone)
        for i in range(i0, i1 + 1):
            j0, j1 = _row_cols(a, b, c, k, (i + 0.5) * h - 1.0, h, n, full)
            if j1 < j0:
                continue
            lo = f * nn + i * n + j0 - m
            # one copy loop per row interval (vectorisable: no running counter)
            for j in range(m, m + j1 - j0 + 1):
                SX[j] = X[lo + j]
                SY[j] = Y[lo + j]
                SZ[j] = Z[lo + j]
                S0[j] = RW[0, lo + j]
                S1[j] = RW[1, lo + j]
                S2[j] = RW[2, lo + j]
                S3[j] = RW[3, lo + j]
            m += j1 - j0 + 1
    out = 0
    nb = bdirs.shape[0]
    kb = math.cos(a_cut) if a_cut < math.pi else -2.0
    for g in range(gcen.shape[0]):
        j0 = g * BRIGHT_GROUP
        j1 = min(j0 + BRIGHT_GROUP, nb)
        a_g = a_cut + galpha[g] + 1e-9
        if a_g < math.pi and t[0] * gcen[g, 0] + t[1] * gcen[g, 1] + t[2] * gcen[g, 2] < math.cos(a_g):
            out += j1 - j0
            continue
        for j in range(j0, j1):
            if t[0] * bdirs[j, 0] + t[1] * bdirs[j, 1] + t[2] * bdirs[j, 2] < kb:
                out += 1
                continue
            m = _put7(SX, SY, SZ, S0, S1, S2, S3, m, bdirs[j, 0], bdirs[j, 1], bdirs[j, 2], brw[j, 0], brw[j, 1],
                      brw[j, 2], brw[j, 3])
    while m % VEC:
        m = _put7(SX, SY, SZ, S0, S1, S2, S3, m, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    return m, out


@_jit(fastmath={"contract"}, inline="always")
def _weight(c, s, s_int, c_floor, lref):
    """``c^s`` by :func:`powi_` for ``s_int > 0`` (0 for c < c_floor: weights < e^-700, no subnormal arithmetic),
    else ``exp(s·(log c − lref))`` (0 for c ≤ 0 and below 2^-1021)."""
    if s_int > 0:
        w = powi_(max(c, c_floor), s_int)
        return w if c >= c_floor else 0.0
    w = exp_(s * (log_(max(c, 1e-300)) - lref))
    return w if c > 0.0 else 0.0


@_jit(fastmath={"contract", "reassoc"}, inline="always")
def _sums2_pow2(x0, y0, z0, x1, y1, z1, SX, SY, SZ, S0, S1, S2, S3, m, c_floor, k):
    """The sums of :func:`_sums2` for s = 2^k: weights by :func:`_pow2k`."""
    a00 = a01 = a02 = a03 = a10 = a11 = a12 = a13 = 0.0
    for j in range(m):
        sx, sy, sz = SX[j], SY[j], SZ[j]
        u0, u1, u2, u3 = S0[j], S1[j], S2[j], S3[j]
        c = x0 * sx + y0 * sy + z0 * sz
        w = _pow2k(max(c, c_floor), k)
        w = w if c >= c_floor else 0.0
        a00, a01, a02, a03 = a00 + w * u0, a01 + w * u1, a02 + w * u2, a03 + w * u3
        c = x1 * sx + y1 * sy + z1 * sz
        w = _pow2k(max(c, c_floor), k)
        w = w if c >= c_floor else 0.0
        a10, a11, a12, a13 = a10 + w * u0, a11 + w * u1, a12 + w * u2, a13 + w * u3
    return a00, a01, a02, a03, a10, a11, a12, a13


@_jit(fastmath={"contract", "reassoc"}, inline="always")
def _sums2(R, b0, b1, SX, SY, SZ, S0, S1, S2, S3, m, s, s_int, c_floor, l0, l1):
    """``(Σ_j w_0j·S_k[j] for k = 0…3, Σ_j w_1j·S_k[j] for k = 0…3)`` over the m scratch entries for the two rows
    ``R[b0], R[b1]`` (reference logs ``l0``, ``l1``), w = :func:`_weight` of c = r·ω_j: one pass, each entry loaded
    once for both rows (a one-row loop is bound by loading the 7 scratch streams, not by the arithmetic); one loop
    per kind of weight (a branch inside the loop would evaluate both powers): ``exp(s·log c)``, :func:`powi_`,
    and for s = 2^k :func:`_pow2k` (the same weights; k ≥ 6 a constant of its own loop, so the squarings unroll
    without selects: 1.5–1.9× faster gathers at s = 256…4096).  The order of the vectorised sums is the
    compiler's (:func:`ibl_ref.groundtruth.kernels.rounding.sum_error` covers any order)."""
    x0, y0, z0 = R[b0, 0], R[b0, 1], R[b0, 2]
    x1, y1, z1 = R[b1, 0], R[b1, 1], R[b1, 2]
    a00 = a01 = a02 = a03 = a10 = a11 = a12 = a13 = 0.0
    if s_int > 0 and (s_int & (s_int - 1)) == 0:
        k2 = 0
        while (1 << k2) < s_int:
            k2 += 1
        # one loop per k (a constant: the squarings unrolled, no selects)
        if k2 == 12:
            return _sums2_pow2(x0, y0, z0, x1, y1, z1, SX, SY, SZ, S0, S1, S2, S3, m, c_floor, 12)
        if k2 == 11:
            return _sums2_pow2(x0, y0, z0, x1, y1, z1, SX, SY, SZ, S0, S1, S2, S3, m, c_floor, 11)
        if k2 == 10:
            return _sums2_pow2(x0, y0, z0, x1, y1, z1, SX, SY, SZ, S0, S1, S2, S3, m, c_floor, 10)
        if k2 == 9:
            return _sums2_pow2(x0, y0, z0, x1, y1, z1, SX, SY, SZ, S0, S1, S2, S3, m, c_floor, 9)
        if k2 == 8:
            return _sums2_pow2(x0, y0, z0, x1, y1, z1, SX, SY, SZ, S0, S1, S2, S3, m, c_floor, 8)
        if k2 == 7:
            return _sums2_pow2(x0, y0, z0, x1, y1, z1, SX, SY, SZ, S0, S1, S2, S3, m, c_floor, 7)
        if k2 == 6:
            return _sums2_pow2(x0, y0, z0, x1, y1, z1, SX, SY, SZ, S0, S1, S2, S3, m, c_floor, 6)
        return _sums2_pow2(x0, y0, z0, x1, y1, z1, SX, SY, SZ, S0, S1, S2, S3, m, c_floor, k2)
    if s_int > 0:
        for j in range(m):
            sx, sy, sz = SX[j], SY[j], SZ[j]
            u0, u1, u2, u3 = S0[j], S1[j], S2[j], S3[j]
            w = _weight(x0 * sx + y0 * sy + z0 * sz, s, s_int, c_floor, l0)
            a00, a01, a02, a03 = a00 + w * u0, a01 + w * u1, a02 + w * u2, a03 + w * u3
            w = _weight(x1 * sx + y1 * sy + z1 * sz, s, s_int, c_floor, l1)
            a10, a11, a12, a13 = a10 + w * u0, a11 + w * u1, a12 + w * u2, a13 + w * u3
    else:
        for j in range(m):
            sx, sy, sz = SX[j], SY[j], SZ[j]
            u0, u1, u2, u3 = S0[j], S1[j], S2[j], S3[j]
            w = _weight(x0 * sx + y0 * sy + z0 * sz, s, 0, c_floor, l0)
            a00, a01, a02, a03 = a00 + w * u0, a01 + w * u1, a02 + w * u2, a03 + w * u3
            w = _weight(x1 * sx + y1 * sy + z1 * sz, s, 0, c_floor, l1)
            a10, a11, a12, a13 = a10 + w * u0, a11 + w * u1, a12 + w * u2, a13 + w * u3
    return a00, a01, a02, a03, a10, a11, a12, a13


@_jit(fastmath={"contract", "reassoc"}, inline="always")
def _max_cos(rx, ry, rz, SX, SY, SZ, m):
    mx = -2.0
    for j in range(m):
        mx = max(mx, rx * SX[j] + ry * SY[j] + rz * SZ[j])
    return mx


@_jit(fastmath={"contract", "reassoc"})
def tile_gather(cen, rows, caps, arad, frames, n, X, Y, Z, RW, bdirs, brw, gcen, galpha, s, s_int, rowmax, c_floor,
                acc, logmx, count, pairs):
    """Truncated-support gather of tiles of output texels: tile i's rows ``rows[i]`` (B, 3) gather every source
    texel within the angle ``caps[i]`` of the tile centre ``cen[i]`` (plus 1e-6 rad and 1e-3 texel of slack)
    and the bright texels ``bdirs``/``brw``: ``acc[i, b] = Σ_j w_bj RW[:, j]``.

    The cap's texels are found without a search structure: on each face (frame rows: axis, u, v) that the cap
    reaches, the cap ``{(u, v) : a + bu + cv ≥ k √(1 + u² + v²)}`` (a, b, c = t·axis, t·u, t·v; k = cos cap) is
    convex: its rows are the interval of v where ``a + cv ≥ √(k² − b²) √(1 + v²)`` (the maximum over u), on
    each row the columns an interval (:func:`_interval`).  The interval ends are computed to ≈ 1e-12 in
    face-plane units, far within the 1e-3-texel widening (2e-3/n ≥ 5e-7 for n ≤ 4096), so no texel of the cap
    is missed (brute-force check in the tests).  The texels are copied to contiguous scratch arrays (7 rows, with
    the bright texels, padded with zero entries to a multiple of :data:`~ibl_ref.groundtruth.kernels.rounding.VEC`;
    sized by :func:`_scratch_size`), then
    every pair of rows runs one vectorised loop over them (:func:`_sums2`: each entry loaded once for two rows).

    Weights: ``s_int > 0`` — ``c^s`` by :func:`powi_` (0 for c < ``c_floor``, whose weight is below e^-700;
    callers count that as underflow); else ``exp(s·(log c − log c_max))`` with ``c_max`` the row's largest
    cosine when ``rowmax`` (``logmx[i, b] = s·log c_max``), else ``c_max = 1``.  ``RW`` (4, 6n²): the rows
    ``[L·Ω, …, Ω]`` padded to 4, zero for the bright texels.  ``arad[i]``: the largest angle between tile i's rows
    and its centre; bright texels farther than ``acos(c_floor) + arad[i]`` from the centre are left out (every
    row's weight of them is 0, or below e^-700 by ``exp``: within the allowance ε of :func:`ibl_ref.groundtruth.kernels.rounding.weight_error`).
    ``count[i]``: entries of tile i's list (the bright texels and the padding included: the pairs computed per
    row) plus the bright texels left out — the pairs the callers' error allowance counts; ``pairs[i]``: the entries
    alone (what each row computed).  ``gcen``/``galpha``: the bright texels' groups (:func:`_collect`).
    """
    nt = rows.shape[0]
    B = rows.shape[1]
    scratch = np.empty((7, _scratch_size(caps, frames, n, cen) + bdirs.shape[0] + VEC))
    SX, SY, SZ, S0, S1, S2, S3 = scratch[0], scratch[1], scratch[2], scratch[3], scratch[4], scratch[5], scratch[6]
    for i in range(nt):
        # bright texels beyond acos(c_floor) + the tile radius (+1e-9 rad) of the centre: below c_floor from every
        # row, weight 0 (or < e^-700 by exp), so left out; counted in count[i], which sets the error allowance
        a_cut = 10.0  # (≥ π: keep every bright texel)
        if not rowmax and c_floor > 0.0:
            a_cut = math.acos(min(c_floor, 1.0)) + arad[i] + 1e-9
        m, out = _collect(cen[i], caps[i], frames, n, X, Y, Z, RW, bdirs, brw, gcen, galpha, a_cut, SX, SY, SZ, S0, S1,
                          S2, S3)
        count[i] = m + out
        pairs[i] = m
        for b in range(0, B, 2):
            b1 = min(b + 1, B - 1)  # an odd last row is paired with itself
            l0 = l1 = 0.0
            if s_int <= 0 and rowmax:
                l0 = log_(max(_max_cos(rows[i, b, 0], rows[i, b, 1], rows[i, b, 2], SX, SY, SZ, m), 1e-300))
                l1 = log_(max(_max_cos(rows[i, b1, 0], rows[i, b1, 1], rows[i, b1, 2], SX, SY, SZ, m), 1e-300))
            a00, a01, a02, a03, a10, a11, a12, a13 = _sums2(rows[i], b, b1, SX, SY, SZ, S0, S1, S2, S3, m, s, s_int,
                                                            c_floor, l0, l1)
            logmx[i, b] = s * l0
            acc[i, b, 0], acc[i, b, 1], acc[i, b, 2], acc[i, b, 3] = a00, a01, a02, a03
            if b1 > b:
                logmx[i, b1] = s * l1
                acc[i, b1, 0], acc[i, b1, 1], acc[i, b1, 2], acc[i, b1, 3] = a10, a11, a12, a13


@_jit(fastmath={"contract"})
def cone_extremes(cen, q, blk_cen, alpha, blk_max, blk_min, sup_cen, sup_alpha, sup_mem, lmax, lmin):
    """Per-channel max and min of ``blk_max``/``blk_min`` over the blocks whose centre lies within q[i] + α of
    cen[i] (the blocks whose cone reaches the cap), for every tile i: the same set as the NumPy path's
    ``_Sources.hits``, found through super-blocks (members ``sup_mem`` (ns, k²), −1 = none; every member
    centre within ``sup_alpha`` − α of the super-block centre, so a super-block is skipped only when none of
    its blocks can qualify)."""
    nt = cen.shape[0]
    C = blk_max.shape[1]
    for i in range(nt):
        tx = cen[i, 0]
        ty = cen[i, 1]
        tz = cen[i, 2]
        c_sup = math.cos(min(q[i] + sup_alpha, math.pi))
        c_blk = math.cos(min(q[i] + alpha, math.pi))
        for ch in range(C):
            lmax[i, ch] = -np.inf
            lmin[i, ch] = np.inf
        for sb in range(sup_cen.shape[0]):
            if tx * sup_cen[sb, 0] + ty * sup_cen[sb, 1] + tz * sup_cen[sb, 2] < c_sup:
                continue
            for k in range(sup_mem.shape[1]):
                b = sup_mem[sb, k]
                if b < 0:
                    continue
                if tx * blk_cen[b, 0] + ty * blk_cen[b, 1] + tz * blk_cen[b, 2] >= c_blk:
                    for ch in range(C):
                        lmax[i, ch] = max(lmax[i, ch], blk_max[b, ch])
                        lmin[i, ch] = min(lmin[i, ch], blk_min[b, ch])


@_jit(inline="always")
def _log_wb_at(grid, log_wb_grid, theta):
    """The tabulated log W_b at the largest grid angle ≤ θ (+inf below the grid)."""
    gi = np.searchsorted(grid, theta, side="right") - 1
    return log_wb_grid[gi] if gi >= 0 else np.inf


@_jit()
def tile_bounds(acc, log_mx, eta, und, l_u, ang, q_t, q_far, half_margin, grid, log_wb_grid, lmax, lmin, l_max_out,
                l_min_out, valid, idx, maps, bounds, worst):
    """The averages and the rigorous per-texel bounds of gathered tiles, in one pass (the same formula, term
    for term, as the NumPy expression in :func:`ibl_ref.groundtruth.kernels.numpy_backend.tile_bounds`):
    ``P = Σ w L Ω / Σ w Ω`` (``acc``), ``log W_in = log_mx + log Σ w Ω − log1p(η + und)``; the neglected texels
    of a row at angle a beyond ``q − a`` (local extremes ``lmax``/``lmin`` up to ``q_far − a``) and beyond
    ``q_far − a`` (global extremes), ``f = W_b(θ)/W_in`` from the tabulated ``log W_b``;
    ``e_fp = 2η/(1−η)·P + und·(l_u + P)``;  ``b = min(f1, f2)·d_glob + max(f1 − f2, 0)·d_loc + e_fp + 1e-12·P``.
    Valid rows are written to ``maps``/``bounds`` at ``idx`` (flat output rows); ``worst[i]`` = the largest
    b/P of tile i's valid entries (+inf for an undefined ratio, so that the tile is retried)."""
    nt = ang.shape[0]
    B = ang.shape[1]
    C = acc.shape[2] - 1
    for i in range(nt):
        e1 = 2.0 * eta[i] / (1.0 - eta[i])
        l1p = math.log1p(eta[i] + und[i])
        w = 0.0
        for b in range(B):
            win = acc[i, b, C]
            log_win = log_mx[i, b] + math.log(win) - l1p
            lw1 = _log_wb_at(grid, log_wb_grid, q_t[i] - half_margin - ang[i, b])
            lw2 = _log_wb_at(grid, log_wb_grid, q_far[i] - half_margin - ang[i, b])
            f1 = 0.0 if lw1 == -np.inf else math.exp(min(lw1 - log_win, 700.0))
            f2 = 0.0 if lw2 == -np.inf else math.exp(min(lw2 - log_win, 700.0))
            f_min = min(f1, f2)
            f_gap = max(f1 - f2, 0.0)
            ok = valid[i, b]
            o = idx[i, b]
            for c in range(C):
                p = acc[i, b, c] / win
                e_fp = e1 * p + und[i] * (l_u + p)
                d_loc = max(max(lmax[i, c] - p, p - lmin[i, c]), 0.0) + e_fp
                d_glob = max(max(l_max_out[c] - p, p - l_min_out[c]), 0.0) + e_fp
                bb = f_min * d_glob + f_gap * d_loc + e_fp + 1e-12 * p
                if ok:
                    maps[o, c] = p
                    bounds[o, c] = bb
                    r = bb / p
                    if not (r <= w):
                        w = r if r == r else np.inf
        worst[i] = w


# ----------------------------------------------------------------------------------------------
# horizon band of the moment route (s = 1, 2)
# ----------------------------------------------------------------------------------------------
@_jit(fastmath={"contract"}, inline="always")
def _add4(arr, i, b, x0, x1, x2, x3):
    """``arr[i, b, 0:4] += (x0, x1, x2, x3)``."""
    arr[i, b, 0] += x0
    arr[i, b, 1] += x1
    arr[i, b, 2] += x2
    arr[i, b, 3] += x3


@_jit(inline="always")
def _longest(starts):
    """The longest list of a CSR ``starts`` array."""
    m = 0
    for i in range(starts.shape[0] - 1):
        m = max(m, starts[i + 1] - starts[i])
    return m


@_jit(fastmath={"contract"}, inline="always")
def _bracket(X, ca, sa):
    """For x = r·c = X and a block cone of half-angle α (cos, sin): the half-width v = sin θ sin α (+1e-12 slack),
    the centre u = X cos α of [x_lo, x_hi] = [u − v, u + v], and A = x_hi/(x_hi − x_lo) clipped to [0, 1]."""
    v = math.sqrt(max(1.0 - X * X, 0.0)) * sa + 1e-12
    u = X * ca
    return v, u, min(max((u + v) / (2.0 * v), 0.0), 1.0)


@_jit(fastmath={"contract", "reassoc"})
def band_exact(R, starts, texels, D, Wt, do1, do2, num1, num2):
    """Exact gather of the horizon band (``leaf = 1`` of :mod:`ibl_ref.groundtruth.moment_convolution`): tile i's
    rows ``R[i]`` (t², 3) and its straddling source texels ``texels[starts[i]:starts[i+1]]`` (directions ``D``
    (M, 3), weights ``Wt`` (M, 4): ``[L·Ω, …, Ω]`` padded to 4): ``num1[i, b] += Σ max(r·ω, 0)·w`` (``do1``),
    ``num2[i, b] += Σ max(r·ω, 0)²·w`` (``do2``).  Float64; relative error of each sum ≤ γ_{m+2} (non-negative
    terms, any order; the products r·ω are off by ≤ γ_3, entering x and x² to first and second order)."""
    nt = R.shape[0]
    B = R.shape[1]
    scratch = np.empty((7, _longest(starts) + VEC))
    SX, SY, SZ, S0, S1, S2, S3 = scratch[0], scratch[1], scratch[2], scratch[3], scratch[4], scratch[5], scratch[6]
    for i in range(nt):
        m = 0
        for k in range(starts[i], starts[i + 1]):
            j = texels[k]
            m = _put7(SX, SY, SZ, S0, S1, S2, S3, m, D[j, 0], D[j, 1], D[j, 2], Wt[j, 0], Wt[j, 1], Wt[j, 2], Wt[j, 3])
        if m == 0:
            continue
        while m % VEC:
            m = _put7(SX, SY, SZ, S0, S1, S2, S3, m, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        for b in range(B):
            rx = R[i, b, 0]
            ry = R[i, b, 1]
            rz = R[i, b, 2]
            a0 = a1 = a2 = a3 = 0.0
            c0 = c1 = c2 = c3 = 0.0
            for j in range(m):
                x = max(rx * SX[j] + ry * SY[j] + rz * SZ[j], 0.0)
                a0 += x * S0[j]
                a1 += x * S1[j]
                a2 += x * S2[j]
                a3 += x * S3[j]
                xx = x * x
                c0 += xx * S0[j]
                c1 += xx * S1[j]
                c2 += xx * S2[j]
                c3 += xx * S3[j]
            if do1:
                _add4(num1, i, b, a0, a1, a2, a3)
            if do2:
                _add4(num2, i, b, c0, c1, c2, c3)


@_jit(fastmath={"contract", "reassoc"})
def band_brackets(R, starts, blocks, cb, ca, sa, M0, M1, M2, do1, do2, num1, err1, num2, err2):
    """Linear brackets of the clamped kernel on straddling leaf blocks (``leaf > 1`` of
    :mod:`ibl_ref.groundtruth.moment_convolution`, :func:`~ibl_ref.groundtruth.moment_convolution._band_brackets`
    for the formulas): tile i's rows ``R[i]`` and its blocks ``blocks[starts[i]:starts[i+1]]`` with cone centres
    ``cb``, cos/sin of their half-angles ``ca``/``sa`` and moments ``M0`` (n, 4) = Σ L Ω, ``M1`` (n, 3, 4) =
    Σ L Ω ω, ``M2`` (n, 6, 4) = Σ L Ω ω_k ω_l (pairs (0,0), (0,1), (0,2), (1,1), (1,2), (2,2)); adds the midpoint
    and the half-width of each block's interval to ``num``/``err``.  Float64 sums of ≤ m terms of bounded
    condition (the midpoints are differences only through the −a²/4 of s = 2, within the half-width).  The
    NumPy path's 1e-12 slack in v keeps the intervals valid under rounding; this kernel computes the same
    expressions."""
    nt = R.shape[0]
    B = R.shape[1]
    scratch = np.empty((45, _longest(starts) + VEC))
    CX = scratch[0]
    CY = scratch[1]
    CZ = scratch[2]
    CA = scratch[3]
    SA = scratch[4]
    W = scratch[5:9]
    Y = scratch[9:21]
    Z2 = scratch[21:45]
    for i in range(nt):
        m = 0
        for k in range(starts[i], starts[i + 1]):
            j = blocks[k]
            CX[m] = cb[j, 0]
            CY[m] = cb[j, 1]
            CZ[m] = cb[j, 2]
            CA[m] = ca[j]
            SA[m] = sa[j]
            for q in range(4):
                W[q, m] = M0[j, q]
                for kk in range(3):
                    Y[kk * 4 + q, m] = M1[j, kk, q]
                for kk in range(6):
                    Z2[kk * 4 + q, m] = M2[j, kk, q]
            m += 1
        if m == 0:
            continue
        while m % VEC:  # zero entries: (z-axis cone, α = 0, no weight) contribute exactly 0
            CX[m] = 0.0
            CY[m] = 0.0
            CZ[m] = 1.0
            CA[m] = 1.0
            SA[m] = 0.0
            for q in range(4):
                W[q, m] = 0.0
            for q in range(12):
                Y[q, m] = 0.0
            for q in range(24):
                Z2[q, m] = 0.0
            m += 1
        for b in range(B):
            rx = R[i, b, 0]
            ry = R[i, b, 1]
            rz = R[i, b, 2]
            if do1:
                n0 = n1 = n2 = n3 = 0.0
                e0 = e1 = e2 = e3 = 0.0
                for j in range(m):
                    v, u, A = _bracket(rx * CX[j] + ry * CY[j] + rz * CZ[j], CA[j], SA[j])
                    H = max(v - u, 0.0) * A * 0.5
                    n0 += A * (rx * Y[0, j] + ry * Y[4, j] + rz * Y[8, j]) + H * W[0, j]
                    n1 += A * (rx * Y[1, j] + ry * Y[5, j] + rz * Y[9, j]) + H * W[1, j]
                    n2 += A * (rx * Y[2, j] + ry * Y[6, j] + rz * Y[10, j]) + H * W[2, j]
                    n3 += A * (rx * Y[3, j] + ry * Y[7, j] + rz * Y[11, j]) + H * W[3, j]
                    e0 += H * W[0, j]
                    e1 += H * W[1, j]
                    e2 += H * W[2, j]
                    e3 += H * W[3, j]
                _add4(num1, i, b, n0, n1, n2, n3)
                _add4(err1, i, b, e0, e1, e2, e3)
            if do2:
                r00 = rx * rx
                r01 = 2.0 * rx * ry
                r02 = 2.0 * rx * rz
                r11 = ry * ry
                r12 = 2.0 * ry * rz
                r22 = rz * rz
                n0 = n1 = n2 = n3 = 0.0
                e0 = e1 = e2 = e3 = 0.0
                for j in range(m):
                    v, u, A = _bracket(rx * CX[j] + ry * CY[j] + rz * CZ[j], CA[j], SA[j])
                    nlo = v - u
                    P = 1.0 if A >= 1.0 else 0.0
                    a = 0.0 if A >= 1.0 else 2.0 * v * A * A
                    av = a * nlo
                    hw = 0.5 * (0.25 * a * a + av)
                    n0 += (a * (rx * Y[0, j] + ry * Y[4, j] + rz * Y[8, j]) + (av - hw) * W[0, j]
                           + P * (r00 * Z2[0, j] + r01 * Z2[4, j] + r02 * Z2[8, j] + r11 * Z2[12, j] + r12 * Z2[16, j]
                                  + r22 * Z2[20, j]))
                    n1 += (a * (rx * Y[1, j] + ry * Y[5, j] + rz * Y[9, j]) + (av - hw) * W[1, j]
                           + P * (r00 * Z2[1, j] + r01 * Z2[5, j] + r02 * Z2[9, j] + r11 * Z2[13, j] + r12 * Z2[17, j]
                                  + r22 * Z2[21, j]))
                    n2 += (a * (rx * Y[2, j] + ry * Y[6, j] + rz * Y[10, j]) + (av - hw) * W[2, j]
                           + P * (r00 * Z2[2, j] + r01 * Z2[6, j] + r02 * Z2[10, j] + r11 * Z2[14, j] + r12 * Z2[18, j]
                                  + r22 * Z2[22, j]))
                    n3 += (a * (rx * Y[3, j] + ry * Y[7, j] + rz * Y[11, j]) + (av - hw) * W[3, j]
                           + P * (r00 * Z2[3, j] + r01 * Z2[7, j] + r02 * Z2[11, j] + r11 * Z2[15, j] + r12 * Z2[19, j]
                                  + r22 * Z2[23, j]))
                    e0 += hw * W[0, j]
                    e1 += hw * W[1, j]
                    e2 += hw * W[2, j]
                    e3 += hw * W[3, j]
                _add4(num2, i, b, n0, n1, n2, n3)
                _add4(err2, i, b, e0, e1, e2, e3)


@_jit(fastmath={"contract"}, inline="always")
def _acc4(a0, a1, a2, a3, i, w, w0, w1, w2, w3):
    """``a_k[i] += w·w_k`` for the four accumulators."""
    a0[i] += w * w0
    a1[i] += w * w1
    a2[i] += w * w2
    a3[i] += w * w3


@_jit(fastmath={"contract"})
def point_gather(out_dirs, b_dirs, b_w, s_arr, s_int, res):
    """Exact ``res[k, q, p] += Σ_b b_w[b, q]·max(r_p·ω_b, 0)^{s_k}`` (absolute weights: ``c^s`` by :func:`powi_` where
    ``s_int[k] > 0``, else ``exp(s·log c)``) — the SH route's gather from its few bright texels; blocks of 256
    outputs, their sums in the cache.  Relative error of every term ≤
    :func:`ibl_ref.groundtruth.kernels.rounding.weight_error` (η for c ≥ C0, ε absolute below)."""
    P = out_dirs.shape[0]
    nb = b_dirs.shape[0]
    K = s_arr.shape[0]
    BL = POINT_BLOCK
    scratch = np.empty((4, BL))
    acc = np.empty((K, 4, BL))
    X = scratch[0]
    Y = scratch[1]
    Z = scratch[2]
    c = scratch[3]
    for p0 in range(0, P, BL):
        m = min(BL, P - p0)
        for i in range(m):
            X[i] = out_dirs[p0 + i, 0]
            Y[i] = out_dirs[p0 + i, 1]
            Z[i] = out_dirs[p0 + i, 2]
        acc[:] = 0.0
        for b in range(nb):
            bx = b_dirs[b, 0]
            by = b_dirs[b, 1]
            bz = b_dirs[b, 2]
            for i in range(m):
                c[i] = X[i] * bx + Y[i] * by + Z[i] * bz
            for k in range(K):
                s = s_arr[k]
                si = s_int[k]
                w0 = b_w[b, 0]
                w1 = b_w[b, 1]
                w2 = b_w[b, 2]
                w3 = b_w[b, 3]
                a0 = acc[k, 0]
                a1 = acc[k, 1]
                a2 = acc[k, 2]
                a3 = acc[k, 3]
                if si > 0:  # (one loop per kind of weight, see _sums2)
                    for i in range(m):
                        _acc4(a0, a1, a2, a3, i, _weight(c[i], s, si, 0.0, 0.0), w0, w1, w2, w3)
                else:
                    for i in range(m):
                        _acc4(a0, a1, a2, a3, i, _weight(c[i], s, 0, 0.0, 0.0), w0, w1, w2, w3)
        for k in range(K):
            for q in range(4):
                for i in range(m):
                    res[k, q, p0 + i] += acc[k, q, i]


# ----------------------------------------------------------------------------------------------
# spherical harmonics: projection and evaluation without the SH matrix
# ----------------------------------------------------------------------------------------------
@_jit(fastmath={"contract"})
def _sh_block_setup(reps, c0, ch, L, x, st, cm, sm):
    """cos θ, sin θ and √2·cos mφ, √2·sin mφ (m ≥ 1; cm[0] = 1, sm[0] = 0) of ``reps[c0:c0+ch]`` (polar axis +z),
    the same recurrences as :func:`ibl_ref.groundtruth.sh_basis._real_sh_parity` (e^{imφ} by repeated
    multiplication with e^{iφ})."""
    sqrt2 = math.sqrt(2.0)
    for d in range(ch):
        vx = reps[c0 + d, 0]
        vy = reps[c0 + d, 1]
        vz = reps[c0 + d, 2]
        nrm = math.sqrt(vx * vx + vy * vy + vz * vz)
        vx /= nrm
        vy /= nrm
        vz /= nrm
        z = min(max(vz, -1.0), 1.0)
        x[d] = z
        st[d] = math.sqrt(max(0.0, 1.0 - z * z))
        rxy = math.hypot(vx, vy)
        if rxy > 0.0:
            ec = vx / rxy
            es = vy / rxy
        else:
            ec = 1.0
            es = 0.0
        re = 1.0
        im = 0.0
        cm[0, d] = 1.0
        sm[0, d] = 0.0
        for m in range(1, L + 1):
            re, im = re * ec - im * es, re * es + im * ec
            cm[m, d] = sqrt2 * re
            sm[m, d] = sqrt2 * im


@_jit(fastmath={"contract"})
def _legendre_band(ell, x, st, ch, p1, p2, pc, a_tab, b_tab):
    """Fully normalised P̄_{ℓ,m}(x), m ≤ ℓ, into pc from P̄_{ℓ−1,·} (p1) and P̄_{ℓ−2,·} (p2) (the recurrences of
    :func:`ibl_ref.groundtruth.sh_basis._real_sh_parity`; ``a_tab``/``b_tab`` its coefficients)."""
    if ell == 0:
        v = 1.0 / math.sqrt(4.0 * math.pi)
        for d in range(ch):
            pc[0, d] = v
        return
    cs = math.sqrt((2 * ell + 1) / (2.0 * ell))
    cl = math.sqrt(2.0 * ell + 1.0)
    for d in range(ch):
        pc[ell, d] = cs * st[d] * p1[ell - 1, d]
        pc[ell - 1, d] = cl * x[d] * p1[ell - 1, d]
    for m in range(ell - 1):
        a = a_tab[ell, m]
        b = b_tab[ell, m]
        for d in range(ch):
            pc[m, d] = a * (x[d] * p1[m, d] - b * p2[m, d])


@_jit(fastmath={"contract", "reassoc"})
def _sh_rows(reps, L, row_of, cls_of, a_tab, b_tab, Wk, acc_e, acc_o, dest, out, project, blk, P):
    """Every real SH row (ℓ ≤ L, m, cos/sin) at the directions ``reps``, block by block of :data:`~ibl_ref.groundtruth.kernels.rounding.SH_BLOCK`
    directions (the Legendre recurrences of :func:`_legendre_band`): ``project`` — projected at once on the
    class-projected weights (:func:`sh_project`), else written to the matrix ``out`` (:func:`sh_matrix`).  Work
    arrays of one block: ``blk`` (2L + 4, SH_BLOCK) — cos θ, sin θ, √2 cos mφ, √2 sin mφ — and ``P`` (3, L + 1,
    SH_BLOCK), three Legendre bands, zeroed."""
    n = reps.shape[0]
    B = SH_BLOCK
    x = blk[0]
    st = blk[1]
    cm = blk[2 : L + 3]
    sm = blk[L + 3 : 2 * L + 4]
    for c0 in range(0, n, B):
        ch = min(B, n - c0)
        _sh_block_setup(reps, c0, ch, L, x, st, cm, sm)
        for ell in range(L + 1):
            pc = P[ell % 3]
            _legendre_band(ell, x, st, ch, P[(ell + 2) % 3], P[(ell + 1) % 3], pc, a_tab, b_tab)
            for m in range(ell + 1):
                for kind in range(2):
                    if kind == 1 and m == 0:
                        continue
                    row = row_of[ell, m, kind]
                    tr = cm[m] if kind == 0 else sm[m]
                    if not project:
                        o = out[dest[(ell + m) % 2, row]]
                        for d in range(ch):
                            o[c0 + d] = pc[m, d] * tr[d]
                        continue
                    k = cls_of[ell, m, kind]
                    w0 = Wk[k, 0]
                    w1 = Wk[k, 1]
                    w2 = Wk[k, 2]
                    w3 = Wk[k, 3]
                    s0 = s1 = s2 = s3 = 0.0
                    for d in range(ch):
                        y = pc[m, d] * tr[d]
                        s0 += y * w0[c0 + d]
                        s1 += y * w1[c0 + d]
                        s2 += y * w2[c0 + d]
                        s3 += y * w3[c0 + d]
                    acc = acc_e if (ell + m) % 2 == 0 else acc_o
                    acc[row, 0] += s0
                    acc[row, 1] += s1
                    acc[row, 2] += s2
                    acc[row, 3] += s3


@_jit(inline="always")
def _sh_blocks(L):
    """Work arrays of one block of :func:`_sh_rows` (zeroed)."""
    return np.zeros((2 * L + 4, SH_BLOCK)), np.zeros((3, L + 1, SH_BLOCK))


@_jit()
def sh_project(reps, Wk, L, row_of, cls_of, a_tab, b_tab, acc_e, acc_o):
    """``acc[row, q] += Σ_d Y_row(reps[d]) · Wk[κ(row), q, d]`` for every real SH row of band ≤ L (even rows —
    ℓ + m even — into ``acc_e``, odd ones into ``acc_o``, at the row order of
    :func:`ibl_ref.groundtruth.sh_basis._layout`, given by ``row_of[ℓ, m, kind]``; ``cls_of`` the row's octant
    class κ; ``Wk`` (8, 4, n) the class-projected weights of the octant orbits).  The SH values are generated
    block by block and used at once: no SH matrix in memory.  Float64; each row's sum has relative error ≤ γ_n in
    the magnitudes (any order)."""
    blk, P = _sh_blocks(L)
    _sh_rows(reps, L, row_of, cls_of, a_tab, b_tab, Wk, acc_e, acc_o, row_of[0], acc_e, True, blk, P)


@_jit()
def sh_matrix(reps, L, row_of, cls_of, a_tab, b_tab, dest, out):
    """The real SH values of band ≤ L at ``reps`` as rows of ``out`` (rows, n): row (ℓ, m, kind) goes to
    ``out[dest[(ℓ + m) % 2, row_of[ℓ, m, kind]]]`` (so the rows of each octant class can be contiguous)."""
    blk, P = _sh_blocks(L)
    _sh_rows(reps, L, row_of, cls_of, a_tab, b_tab, P, out, out, dest, out, False, blk, P)


# ----------------------------------------------------------------------------------------------
# GGX n = v = r prefilter: the block-Taylor tree (ibl_ref.groundtruth.ggx_convolution)
# ----------------------------------------------------------------------------------------------
@_jit(fastmath={"contract"}, inline="always")
def _ggx_k(x, a, b):
    """K(x) = x / (a + b(1 − x))², 0 for x ≤ 0."""
    if x <= 0.0:
        return 0.0
    iu = 1.0 / (a + b * (1.0 - x))
    return x * iu * iu


@_jit(fastmath={"contract"}, inline="always")
def _ggx_d3(x, a, b):
    """K'''(x) = 18 b² u⁻⁴ + 24 b³ x u⁻⁵, u = a + b(1 − x) (x ≥ 0)."""
    iu = 1.0 / (a + b * (1.0 - x))
    iu4 = (iu * iu) * (iu * iu)
    return 18.0 * b * b * iu4 + 24.0 * b * b * b * x * iu4 * iu


@_jit(fastmath={"contract"}, inline="always")
def _ggx_span(ct, st, cb, sb):
    """``(x_max, x_min, sin_max)`` over the angles [θ − β, θ + β] ∩ [0, π] (cos θ = ct, sin θ = st ≥ 0; cos β, sin β):
    cos(θ ∓ β) = cos θ cos β ± sin θ sin β, no trigonometric calls (rounding ≤ 1e-15, inside the margins)."""
    if ct >= cb:  # θ ≤ β
        x_max = 1.0
        s_lo = 0.0
    else:
        x_max = ct * cb + st * sb
        s_lo = st * cb - ct * sb
    if ct <= -cb:  # θ + β ≥ π
        x_min = -1.0
        s_hi = 0.0
    else:
        x_min = ct * cb - st * sb
        s_hi = st * cb + ct * sb
    return x_max, x_min, (1.0 if x_max >= 0.0 >= x_min else max(s_lo, s_hi))


@_jit(fastmath={"contract"}, inline="always")
def _ggx_pair(node, cx, cy, cz, cb, sb, cd, sd, hshare, a, b, NC, NCOS, NSIN, NM0, NTR, e):
    """Tests of one (tile, block) pair (:func:`ibl_ref.groundtruth.kernels.numpy_backend.ggx_pairs`): ``(live,
    k_centre)`` and the per-channel bound estimates in ``e``.  ``live`` (some texel of the block may be above some
    output texel's horizon) and whether K is smooth on the pair for every texel use the tile's whole cone (cos β,
    sin β = cb, sb); the estimates of a smooth pair its decision cone (cd, sd); ``k_centre`` = K at the tile's axis
    (the block's share of the tile's estimate)."""
    Q = NM0.shape[1]
    ct = min(max(cx * NC[node, 0] + cy * NC[node, 1] + cz * NC[node, 2], -1.0), 1.0)
    st = math.sqrt(max(1.0 - ct * ct, 0.0))
    cp = NCOS[node]
    spsi = NSIN[node]
    x_max, x_min, sin_max = _ggx_span(ct, st, cb, sb)
    delta = (1.0 - cp) * max(abs(x_min), abs(x_max)) + spsi * sin_max + 1e-15
    if x_max + delta <= 0.0:
        return False, 0.0
    # near some texel's horizon that texel takes the bracket (≤ ½K(x_top)·M0 over the whole cone): a share hshare
    # of it joins the estimate, so that a zero estimate always means a zero bound
    h_full = hshare * 0.5 * _ggx_k(min(x_max + delta, 1.0), a, b) if x_min - delta <= 0.0 else 0.0
    x_max, x_min, sin_max = _ggx_span(ct, st, cd, sd)
    delta = (1.0 - cp) * max(abs(x_min), abs(x_max)) + spsi * sin_max + 1e-15
    x_top = min(x_max + delta, 1.0)
    half = 0.5 * _ggx_k(x_top, a, b)
    c3 = _ggx_d3(x_top, a, b) * delta / 6.0 if x_min - delta > 0.0 else np.inf
    for q in range(Q):
        m0 = NM0[node, q]
        e[q] = min(half * m0, c3 * min(delta * delta * m0, NTR[node, q])) + h_full * m0
    return True, _ggx_k(ct, a, b)


@_jit(inline="always")
def _ggx_first_child(idx, m):
    """``(first child, child grid side 2m)``: block ``idx`` of a 6×m×m grid → the flat index of its first child on the
    6×2m×2m grid (the others at +1, +2m, +2m+1)."""
    f = idx // (m * m)
    rem = idx - f * m * m
    bi = rem // m
    bj = rem - bi * m
    m2 = 2 * m
    return f * m2 * m2 + 2 * bi * m2 + 2 * bj, m2


@_jit(inline="always")
def _ggx_add_texel(tex, nt, ci):
    """Append texel ``ci`` to the list ``tex[:nt]`` (grown by doubling): ``(tex, nt + 1)``."""
    if nt >= tex.shape[0]:
        t_new = np.empty(2 * tex.shape[0], np.int64)
        t_new[:nt] = tex[:nt]
        tex = t_new
    tex[nt] = ci
    return tex, nt + 1


@_jit(fastmath={"contract"})
def ggx_tree(tiles, R, cT, betaT, target, beta_share, hshare, split_gain, a, b, off, grid_m, top, NC, NCOS, NSIN, NVALID,
             NM0, NU, NV, NTR, TC, TW, TVALID, num, err, pairs):
    """The sums of the tiles ``tiles`` (indices into ``R`` (T, t², 3), ``cT``, ``betaT``; row k of ``target``,
    ``num``/``err`` (len(tiles), t², Q) belongs to ``tiles[k]``) over the source quadtree.

    Per tile, greedy refinement in rounds: the live (tile, block) pairs, starting from the six faces, each with its
    tile-level bound e_q (:func:`_ggx_pair`: Taylor remainder or zero-order half-width) and its estimate K(c_T·ĉ)·M0_q;
    while the summed relative bound ``Σ_B max_q e_q/N̂_q + e_Ω/N̂_Ω`` (N̂ the estimates' sums) exceeds
    ``target[k]``, every pair whose share is at least the threshold θ is split (a 2×2 block into its texels, summed
    exactly; so are the 2×2 blocks left at the end): θ = half the mean share, doubled while the pairs at or above 2θ
    hold at least (total − target)/split_gain (split_gain: the share of a split pair's bound the split is expected to
    remove; the doubling keeps the last rounds from splitting far more than the excess needs).  Then every output
    texel of the tile sums the final pairs (Taylor sum or bracket midpoint, bound into ``err``) and the texels.
    Nodes of level ℓ ≥ 1 are rows ``off[ℓ] + index`` of the N* arrays (grid 6 × m × m, ``m = grid_m[ℓ]``); texels are rows of TC/TW.  ``pairs[ℓ]`` counts the final pairs per level.  Float64; each
    tile is computed in a fixed order (independent of how the tiles are shared out); the loops over the tile's
    texels are straight-line code over structure-of-arrays copies (vectorisable)."""
    Q = NM0.shape[1]
    C = Q - 1
    t2 = R.shape[1]
    cap = 1024
    cur_l = np.empty(cap, np.int64)
    cur_i = np.empty(cap, np.int64)
    cur_e = np.empty((cap, Q))
    cur_s = np.empty((cap, Q))
    nxt_l = np.empty(cap, np.int64)
    nxt_i = np.empty(cap, np.int64)
    nxt_e = np.empty((cap, Q))
    nxt_s = np.empty((cap, Q))
    metric = np.empty(cap)
    tcap = 4096
    tex = np.empty(tcap, np.int64)
    e = np.empty(Q)
    nh = np.empty(Q)
    ex = np.empty(Q)
    rx = np.empty(t2)
    ry = np.empty(t2)
    rz = np.empty(t2)
    rr = np.empty((6, t2))
    xk = np.empty(t2)
    k0 = np.empty(t2)
    k1 = np.empty(t2)
    k2 = np.empty(t2)
    hw = np.empty(t2)
    c3v = np.empty(t2)
    acc_n = np.empty((Q, t2))
    acc_e = np.empty((Q, t2))
    for k in range(tiles.shape[0]):
        T = tiles[k]
        cx, cy, cz = cT[T, 0], cT[T, 1], cT[T, 2]
        beta = betaT[T] + 1e-9
        cb = math.cos(beta)
        sb = math.sin(beta)
        cd = math.cos(beta_share * beta)
        sd = math.sin(beta_share * beta)
        n = 0
        nt = 0
        ex[:] = 0.0
        for f in range(6):
            node = off[top] + f
            if not NVALID[node]:
                continue
            live, kc = _ggx_pair(node, cx, cy, cz, cb, sb, cd, sd, hshare, a, b, NC, NCOS, NSIN, NM0, NTR, e)
            if live:
                cur_l[n] = top
                cur_i[n] = f
                for q in range(Q):
                    cur_e[n, q] = e[q]
                    cur_s[n, q] = kc * NM0[node, q]
                n += 1
        # ---- greedy refinement ------------------------------------------------------------------------------------
        while n > 0:
            for q in range(Q):
                nh[q] = ex[q]
            for j in range(n):
                for q in range(Q):
                    nh[q] += cur_s[j, q]
            total = 0.0
            for j in range(n):
                mt = 0.0
                for q in range(C):
                    if cur_e[j, q] > 0.0:
                        v = cur_e[j, q] / nh[q] if nh[q] > 0.0 else np.inf
                        if v > mt:
                            mt = v
                if cur_e[j, C] > 0.0:
                    mt += cur_e[j, C] / nh[C] if nh[C] > 0.0 else np.inf
                metric[j] = mt
                total += mt
            if total <= target[k]:
                break
            thr = total / (2.0 * n)
            need = (total - target[k]) / split_gain
            if need < total:
                while True:
                    thr2 = 2.0 * thr
                    held = 0.0
                    for j in range(n):
                        if metric[j] >= thr2:
                            held += metric[j]
                    if held < need:
                        break
                    thr = thr2
            # the next list: kept pairs and the children of the split ones (at most 4 per pair)
            if 4 * n > nxt_l.shape[0]:
                m_ = 4 * n
                nxt_l = np.empty(m_, np.int64)
                nxt_i = np.empty(m_, np.int64)
                nxt_e = np.empty((m_, Q))
                nxt_s = np.empty((m_, Q))
            n2 = 0
            for j in range(n):
                li = cur_l[j]
                if metric[j] < thr:
                    nxt_l[n2] = li
                    nxt_i[n2] = cur_i[j]
                    for q in range(Q):
                        nxt_e[n2, q] = cur_e[j, q]
                        nxt_s[n2, q] = cur_s[j, q]
                    n2 += 1
                    continue
                base, m2 = _ggx_first_child(cur_i[j], grid_m[li])
                for c in range(4):
                    ci = base + (c & 1) + (c >> 1) * m2
                    if li == 1:  # a texel: exact, its share of the estimate fixed
                        if not TVALID[ci]:
                            continue
                        tex, nt = _ggx_add_texel(tex, nt, ci)
                        kc = _ggx_k(cx * TC[ci, 0] + cy * TC[ci, 1] + cz * TC[ci, 2], a, b)
                        for q in range(Q):
                            ex[q] += kc * TW[ci, q]
                        continue
                    node = off[li - 1] + ci
                    if not NVALID[node]:
                        continue
                    live, kc = _ggx_pair(node, cx, cy, cz, cb, sb, cd, sd, hshare, a, b, NC, NCOS, NSIN, NM0, NTR, e)
                    if live:
                        nxt_l[n2] = li - 1
                        nxt_i[n2] = ci
                        for q in range(Q):
                            nxt_e[n2, q] = e[q]
                            nxt_s[n2, q] = kc * NM0[node, q]
                        n2 += 1
            cur_l, nxt_l = nxt_l, cur_l
            cur_i, nxt_i = nxt_i, cur_i
            cur_e, nxt_e = nxt_e, cur_e
            cur_s, nxt_s = nxt_s, cur_s
            n = n2
            if metric.shape[0] < n:
                metric = np.empty(2 * n)
        # ---- every output texel of the tile: the final pairs and the texels ------------------------------------
        for i in range(t2):
            x0, x1, x2 = R[T, i, 0], R[T, i, 1], R[T, i, 2]
            rx[i] = x0
            ry[i] = x1
            rz[i] = x2
            rr[0, i] = x0 * x0
            rr[1, i] = 2.0 * x0 * x1
            rr[2, i] = 2.0 * x0 * x2
            rr[3, i] = x1 * x1
            rr[4, i] = 2.0 * x1 * x2
            rr[5, i] = x2 * x2
        acc_n[:] = 0.0
        acc_e[:] = 0.0
        # the final 2×2 blocks as their four texels, exactly (cheaper per output texel than the Taylor sum)
        n_b = 0
        for j in range(n):
            if cur_l[j] != 1:
                cur_l[n_b] = cur_l[j]
                cur_i[n_b] = cur_i[j]
                n_b += 1
                continue
            base, m2 = _ggx_first_child(cur_i[j], grid_m[1])
            for c in range(4):
                ci = base + (c & 1) + (c >> 1) * m2
                if TVALID[ci]:
                    tex, nt = _ggx_add_texel(tex, nt, ci)
        n = n_b
        for j in range(n):
            li = cur_l[j]
            node = off[li] + cur_i[j]
            pairs[li] += 1
            cp = NCOS[node]
            spsi = NSIN[node]
            nx, ny, nz = NC[node, 0], NC[node, 1], NC[node, 2]
            # per output texel: the bracket 0 ≤ K ≤ K(x + δ) (half-width hw) and, where K is smooth on [x − δ, x + δ],
            # the Taylor coefficients and the remainder per unit of rᵀVr (c3; inf where not smooth)
            # (straight-line selects, no branches: the loops vectorise)
            cp1 = 1.0 - cp
            for i in range(t2):
                x = rx[i] * nx + ry[i] * ny + rz[i] * nz
                s1 = 1.0 - x * x
                s1 = s1 if s1 > 0.0 else 0.0
                ax = x if x > 0.0 else -x
                dl = cp1 * ax + spsi * math.sqrt(s1) + 1e-15
                xt = x + dl
                xt = xt if xt < 1.0 else 1.0
                ut = 1.0 / (a + b * (1.0 - xt))
                ut2 = ut * ut
                hw[i] = 0.5 * (xt if xt > 0.0 else 0.0) * ut2
                smooth = x - dl > 0.0
                xs = x if smooth else 1.0
                iu = 1.0 / (a + b * (1.0 - xs))
                iu2 = iu * iu
                k0[i] = xs * iu2
                k1[i] = iu2 + 2.0 * b * xs * iu2 * iu
                k2[i] = b * iu2 * iu * (2.0 + 3.0 * b * xs * iu)  # ½K''
                c3 = b * b * (ut2 * ut2) * (3.0 + 4.0 * b * xt * ut) * dl  # K'''(x_top)/6 · δ
                c3v[i] = c3 if smooth else np.inf
            for q in range(Q):
                u0, u1, u2 = NU[node, 0, q], NU[node, 1, q], NU[node, 2, q]
                v0, v1, v2 = NV[node, 0, q], NV[node, 1, q], NV[node, 2, q]
                v3, v4, v5 = NV[node, 3, q], NV[node, 4, q], NV[node, 5, q]
                mq = NM0[node, q]
                an = acc_n[q]
                ae = acc_e[q]
                for i in range(t2):
                    s2 = (rr[0, i] * v0 + rr[1, i] * v1 + rr[2, i] * v2 + rr[3, i] * v3 + rr[4, i] * v4
                          + rr[5, i] * v5)
                    et = c3v[i] * s2
                    hm = hw[i] * mq
                    tv = k0[i] * mq + k1[i] * (rx[i] * u0 + ry[i] * u1 + rz[i] * u2) + k2[i] * s2
                    use = et < hm
                    an[i] += tv if use else hm
                    ae[i] += et if use else hm
        pairs[0] += nt
        for j in range(nt):
            ti = tex[j]
            tx, ty, tz = TC[ti, 0], TC[ti, 1], TC[ti, 2]
            for i in range(t2):
                x = max(rx[i] * tx + ry[i] * ty + rz[i] * tz, 0.0)
                iu = 1.0 / (a + b * (1.0 - x))
                xk[i] = x * iu * iu
            for q in range(Q):
                w = TW[ti, q]
                for i in range(t2):
                    acc_n[q, i] += xk[i] * w
        for i in range(t2):
            for q in range(Q):
                num[k, i, q] = acc_n[q, i]
                err[k, i, q] = acc_e[q, i]
