"""The NumPy backend of the convolution kernels: the reference implementation of every operation of
:class:`ibl_ref.groundtruth.kernels.Kernels` (Knuth et al. 2014, Sec. 3.2, Eq. 4).

Array expressions in NumPy/SciPy: every test, bound and number of the routes was first established on them; the
compiled backend (:mod:`ibl_ref.groundtruth.kernels.numba_backend`) computes the same quadratures and is checked
against this one.

Sparse route (:func:`ibl_ref.groundtruth.phong_convolution.convolve_sparse_many`): :class:`SparseGather` gathers the
sums of every tile's cap — the **float32 kernel** (:func:`_gather_batch32`: sources in 4×4 slabs, x = 1 − r·ω from
offsets to the tile centre, ``log(1 − x)`` by its series, float32 ``exp``, partial sums of 64; its rounding bound
:func:`_kernel32_eta`) where its bound takes ≤ 20 % of τ, else the **float64 kernel** (:func:`_gather_batch64`:
cap lists from the 8×8 source blocks of :class:`Sources`, ``exp(s·log c)``) — and :func:`tile_bounds` turns them
into averages and the route's rigorous per-texel bound.  Moment route: :func:`band_exact`, :func:`band_brackets`.
SH route: the octant-symmetric passes of :class:`ibl_ref.groundtruth.sh_basis.NumpySH` and :func:`bright_gather`.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ...environment import envmap
from ...errors import IBLError
from ..sh_basis import NumpySH
from . import Kernels
from .rounding import sum_error, weight_error

__all__ = ["NumpyKernels", "SparseGather", "Sources", "tile_bounds", "band_exact", "band_brackets", "bright_gather",
           "ggx_tree_pass", "quad_children", "SYM_PAIRS", "ANGLE_MARGIN", "MOMENT_CHUNK_PAIRS",
           "column_extremes"]


# ----------------------------------------------------------------------------------------------------------------
# sparse route: the sources, the float32 and float64 gathers
# ----------------------------------------------------------------------------------------------------------------
#: target size of one chunk's weight matrix, in float64 elements (2 MB: the passes stay in cache)
_CHUNK_ELEMS = 1 << 18


#: cost model of the sparse gather, in units of one weight-matrix element (≈ 40 ns under load):
#: per tile ≈ 0.7 ms, per candidate source texel ≈ 1.2 µs (least-squares fit to timings at 64²,
#: s ∈ {256, 4096}, tiles of 2…16 texels)
_TILE_OVERHEAD_ELEMS = 1.7e4


_CAND_OVERHEAD_ELEMS = 30.0


def column_extremes(a: np.ndarray, ok=None, axis: int = 0):
    """``(max, min)`` of a (…, C) array over ``axis`` (not the last), one channel at a time (a contiguous
    reduction: ≈ 25× faster than over an axis followed by a short one; exact, so the same result); entries
    where ``ok`` is False are left out (−inf / +inf where none is left)."""
    mx, mn = [], []
    for c in range(a.shape[-1]):
        x = a[..., c]
        mx.append((x if ok is None else np.where(ok, x, -np.inf)).max(axis=axis))
        mn.append((x if ok is None else np.where(ok, x, np.inf)).min(axis=axis))
    return np.stack(mx, axis=-1), np.stack(mn, axis=-1)



#: side (texels) of the source blocks whose bounding cones the sparse gather tests first when it
#: looks for a tile's cap (then only those blocks' texels): a two-level search in NumPy, no KD-tree.  The
#: same blocks carry the per-channel radiance extremes of the local bound.
_CAP_BLOCK = 8


#: float32 lobe kernel (:func:`_kernel32`): unit roundoff, relative error allowed for one float32 ``np.exp`` —
#: NumPy's SIMD float32 exp states a largest relative error of 2.13e-7 measured over every float32 input
#: (``numpy/_core/src/umath/loops_exponent_log.dispatch.c.src``), a libm ``expf`` is within one ulp
#: (1.2e-7); 2^-20 = 9.5e-7 is 4.5× that (checked on a dense sample in the tests)
_U32 = 2.0 ** -24


_EXP32_REL = 2.0 ** -20


#: candidates per float32 partial sum of the float32 kernel (relative error ≤ γ_kc each; summed in float64)
_KC = 64


#: the float32 kernel is used only where every pair has x = 1 − cos θ ≤ this (the series of −log(1 − x) is
#: then short), where the series needs at most :data:`_SERIES_MAX` terms for a relative weight error
#: ≤ :data:`_SERIES_TOL`, and where no output texel's largest weight is below e^:data:`_OWN_LOG_MIN`
_X32_MAX = 0.3


_SERIES_MAX = 12


_SERIES_TOL = 2.0 ** -15


_OWN_LOG_MIN = -40.0


#: float32 kernel: elements of one batch's weight array (4 MB)
_CHUNK32 = 1 << 20


def _gamma(n: int, u: float) -> float:
    """γ_n = n·u/(1 − n·u): relative error bound of a sum or dot product of n terms in any order."""
    return n * u / (1.0 - n * u)


def _source_blocks(src_dirs, m, b=_CAP_BLOCK):
    """Blocks of b×b source texels per face (the last ones partial): unit centres (nb, 3), flat texel
    indices (nb, b²; −1 = none) and the largest angle between a block's centre and its texel centres
    (with a 1e-9 rad margin for the arccos).  Cached per (m, b) (read-only arrays): ``src_dirs`` is always the
    texel grid of m."""
    return _source_blocks_cached(m, b)


@functools.lru_cache(maxsize=16)
def _source_blocks_cached(m, b):
    src = envmap.texel_directions(m)
    nbk = -(-m // b)
    idx = np.full((6, nbk * b, nbk * b), -1, dtype=np.intp)
    idx[:, :m, :m] = np.arange(6 * m * m).reshape(6, m, m)
    tex = envmap.face_blocks(idx, b)
    if m % b == 0:  # whole blocks: the same array by a transposed copy (a gather and a select cost 3× more)
        d = envmap.face_blocks(src, b)
    else:
        d = np.where((tex >= 0)[..., None], src.reshape(-1, 3)[np.maximum(tex, 0)], 0.0)
    c = d.sum(axis=1)
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    dots = np.einsum("bjk,bk->bj", d, c)
    if m % b:
        dots = np.where(tex >= 0, dots, 1.0)
    alpha = float(np.arccos(np.clip(dots.min(), -1.0, 1.0))) + 1e-9
    c.flags.writeable = False
    tex.flags.writeable = False
    return c, tex, alpha


class Sources:
    """Source texels of one :func:`~ibl_ref.groundtruth.phong_convolution.convolve_sparse_many` call, arranged for the cap searches.

    ``blk_dirs`` (nb, b², 3): directions of the texels of every block (NaN for the block's missing texels and
    for the bright set, so that no cap test selects them); ``blk_max``/``blk_min`` (nb, C): per-channel
    radiance extremes of the block's texels outside the bright set (−inf/+inf when there are none).
    """

    def __init__(self, src_dirs, rad, is_bright, m):
        self.dirs = src_dirs
        self.cen, self.tex, self.alpha = _source_blocks(src_dirs, m)
        ok = (self.tex >= 0) & ~is_bright[np.maximum(self.tex, 0)]
        self._ok = ok
        r = rad[np.maximum(self.tex, 0)]  # (nb, b², C)
        self.blk_max, self.blk_min = column_extremes(r, ok, axis=1)

    @functools.cached_property
    def blk_dirs(self):
        return np.where(self._ok[..., None], self.dirs[np.maximum(self.tex, 0)], np.nan)

    def hits(self, cen, q):
        """(tile, block) index pairs, tile-major: blocks whose cone reaches the cap of radius q[i] around
        cen[i] (the block's centre within q + α)."""
        cos_qb = np.cos(np.minimum(q + self.alpha, np.pi))
        return np.nonzero((cen @ self.cen.T) >= cos_qb[:, None])

    def local_extremes(self, cen, q, rows=256):
        """Per-channel max and min of the non-bright radiance over the blocks that reach the caps (cen[i],
        q[i]): a superset of the texels within q[i] of cen[i]."""
        n_t = len(q)
        C = self.blk_max.shape[1]
        lmax, lmin = np.empty((n_t, C)), np.empty((n_t, C))
        for i0 in range(0, n_t, rows):
            ti, bi = self.hits(cen[i0 : i0 + rows], q[i0 : i0 + rows])
            starts = np.flatnonzero(np.r_[True, ti[1:] != ti[:-1]])
            # every cap holds the block of its own centre (q ≥ 0, α > 0): no tile is without hits
            lmax[i0 : i0 + rows] = np.maximum.reduceat(self.blk_max[bi], starts, axis=0)
            lmin[i0 : i0 + rows] = np.minimum.reduceat(self.blk_min[bi], starts, axis=0)
        return lmax, lmin

    def cap_lists(self, cen, q, pad, multiple=1):
        """Non-bright source texels within q[i] of cen[i] for every tile i (block order), as a padded index
        matrix (g, m) (m a multiple of ``multiple``; pads = ``pad``) and the counts (g,)."""
        ti, bi = self.hits(cen, q)
        dots = np.einsum("hkj,hj->hk", self.blk_dirs[bi], cen[ti])  # NaN (missing, bright) compares False
        sel = dots >= np.cos(np.minimum(q, np.pi))[ti, None]
        tex = self.tex[bi][sel]
        tile = np.repeat(ti, sel.sum(axis=1))
        counts = np.bincount(tile, minlength=len(q))
        m = int(counts.max()) if counts.size else 0
        m = max(multiple, -(-m // multiple) * multiple)
        ii = np.full((len(q), m), pad, dtype=np.intp)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        ii[tile, np.arange(tex.size) - starts[tile]] = tex
        return ii, counts


#: the float32 kernel gathers whole slabs of b×b source texels (contiguous copies, no per-texel indexing),
#: found by a two-level cone search (super-blocks of :data:`_SLAB_SUPER` × :data:`_SLAB_SUPER` slabs)
_SLAB = 4


_SLAB_SUPER = 4


class _Slabs:
    """Source texels in slabs of b×b (b = :data:`_SLAB`) for the float32 kernel.

    ``dirs`` (ns + 1, b², 3) float64 directions and ``rw`` (ns + 1, b², Q) float32 rows [L·Ω, Ω] per slab, zero
    for missing texels (partial slabs), for the bright set (gathered separately) and for the padding slab ns;
    slab centres ``cen`` and the largest centre-to-texel angle ``alpha``; super-blocks of slabs (``sup_cen``,
    ``sup_alpha``, member slabs ``sup_mem`` (nsup, k²), −1 = none).
    """

    def __init__(self, src_dirs, rad_w, is_bright, m, b=_SLAB, k=_SLAB_SUPER):
        self.cen, tex, self.alpha = _source_blocks(src_dirs, m, b)
        ok = (tex >= 0) & ~is_bright[np.maximum(tex, 0)]
        ns = len(self.cen)
        self.pad = ns
        self.dirs = np.zeros((ns + 1, b * b, 3))
        self.dirs[:ns] = np.where((tex >= 0)[..., None], src_dirs[np.maximum(tex, 0)], 0.0)
        self.rw = np.zeros((ns + 1, b * b, rad_w.shape[1]), dtype=np.float32)
        self.rw[:ns] = np.where(ok[..., None], rad_w[np.maximum(tex, 0)], 0.0)
        nb = -(-m // b)  # slabs per face side
        nk = -(-nb // k)
        mem = np.full((6, nk * k, nk * k), -1, dtype=np.intp)
        mem[:, :nb, :nb] = np.arange(ns).reshape(6, nb, nb)
        self.sup_mem = envmap.face_blocks(mem, k)
        # super-block centre: normalised mean of its slab centres; radius: farthest texel of its slabs
        valid = self.sup_mem >= 0
        c = np.where(valid[..., None], self.cen[np.maximum(self.sup_mem, 0)], 0.0).sum(axis=1)
        self.sup_cen = c / np.linalg.norm(c, axis=1, keepdims=True)
        dots = np.where(valid, np.einsum("skj,sj->sk", self.cen[np.maximum(self.sup_mem, 0)], self.sup_cen), 1.0)
        self.sup_alpha = float(np.arccos(np.clip(dots.min(), -1.0, 1.0))) + self.alpha + 1e-9

    def cap_slabs(self, cen, q):
        """Slabs whose centre lies within q[i] + α of cen[i] (so every texel within q[i] is in one) for every
        tile i, in super-block then member order: ``(slabs of all tiles (concatenated), counts (g,))``."""
        ti, si = np.nonzero((cen @ self.sup_cen.T) >= np.cos(np.minimum(q + self.sup_alpha, np.pi))[:, None])
        mem = self.sup_mem[si]  # (h, k²)
        d = np.einsum("hkj,hj->hk", self.cen[np.maximum(mem, 0)], cen[ti])
        sel = (mem >= 0) & (d >= np.cos(np.minimum(q + self.alpha, np.pi))[ti, None])
        return mem[sel], np.bincount(np.repeat(ti, sel.sum(axis=1)), minlength=len(q))


def _padded(flat, counts, rows, width, pad):
    """Rows ``rows`` of a ragged list (``flat`` concatenated, ``counts`` per row) as a (len(rows), width) matrix
    filled with ``pad``."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    c = counts[rows]
    out = np.full((rows.size, width), pad, dtype=flat.dtype)
    r = np.repeat(np.arange(rows.size), c)
    j = np.arange(r.size) - np.repeat(np.cumsum(c) - c, c)
    out[r, j] = flat[np.repeat(starts[rows], c) + j]
    return out


def _series_terms(s, x_max):
    """Terms K of the series −log(1 − x) = Σ_k x^k/k whose remainder bound s·x^{K+1}/((K+1)(1 − x)) is
    ≤ :data:`_SERIES_TOL` for x ≤ x_max (array; 0 where more than :data:`_SERIES_MAX` terms or x_max ≥ 1)."""
    x = np.minimum(np.asarray(x_max, dtype=np.float64), 0.999)
    out = np.zeros(x.shape, dtype=np.intp)
    for K in range(_SERIES_MAX, 1, -1):
        ok = (s * x ** (K + 1) / ((K + 1) * (1.0 - x)) <= _SERIES_TOL) & (np.asarray(x_max) < 1.0)
        out = np.where(ok, K, out)
    return out


def _kernel32_eta(s, K, r_a, r_b, ang_max):
    """Relative error bound η of the float32 kernel's sums Σ w_j L_j Ω_j and Σ w_j Ω_j (arrays broadcast).

    x = 1 − r·ω = |a|²/2 + |b|²/2 − a·b with a = r − t, b = ω − t (t the tile centre: |a| ≤ r_a, |b| ≤ r_b,
    angles bounding chords), every pair within the angle ang_max.
    Error sources (u = 2^-24, γ_n = nu/(1 − nu)):

    * x in float32 from float32-rounded a, b, |a|²/2, |b|²/2 by one 5-term dot product:
      |x̂ − x| ≤ γ_8·(|a| + |b|)²/2 =: Δx;
    * u = −s·p(x̂), p the K-term series of −log(1 − x), by Horner in float32: |û + s·p(x̂)| ≤ γ_{2K+1}·s·p(X)
      with X = 1 − cos(ang_max) + Δx ≥ |x̂|; |p(x̂) − p(x)| ≤ Δx/(1 − X); the series remainder
      0 ≤ −log(1 − x) − p(x) ≤ X^{K+1}/((K+1)(1 − X));
    * float32 exp: relative :data:`_EXP32_REL` (weights ≥ 2^-126; smaller ones: the absolute term of
      :func:`_kernel32_underflow`);
    * L·Ω and Ω rounded to float32 (u), partial sums of :data:`_KC` non-negative terms (γ_kc), their float64
      sum (≤ 1e-12).
    """
    dx = _gamma(8, _U32) * (r_a + r_b) ** 2 / 2.0
    X = 1.0 - np.cos(np.minimum(ang_max, np.pi)) + dx
    p = -np.log1p(-np.minimum(X, 0.999))
    # first Horner stage c_K·x + c_{K−1} from its own 5-term product (|c_k| = s/k), propagated by x^{K−1}
    e1 = (_gamma(7, _U32) * (s / K * (r_a + r_b) ** 2 / 2.0 + s / (K - 1)) + s / K * dx) * X ** (K - 1)
    du = s * (_gamma(2 * K + 1, _U32) * p + dx / (1.0 - X) + X ** (K + 1) / ((K + 1) * (1.0 - X))) + e1
    delta = np.expm1(du) * (1.0 + _EXP32_REL) + _EXP32_REL
    return (1.0 + delta) * (1.0 + _U32) * (1.0 + _gamma(_KC, _U32)) * (1.0 + 1e-12) - 1.0


def _kernel32_underflow(m, own_log, omega_ratio):
    """Absolute error of the float32 kernel's average from weights below 2^-126 (float32 exp returns them
    as subnormals or 0: each off by < 2^-125), relative to the largest neglected-or-gathered radiance:
    m·2^-125 / (smallest own weight e^{own_log} · Ω_min/Ω_max)."""
    return m * 2.0 ** -125 * math.exp(-own_log) * omega_ratio


def _gather_batch32(cen, TD, si, slabs, coef):
    """Float32 kernel for tiles with centres ``cen`` (g, 3), rows ``TD`` (g, B, 3) and slab matrix ``si``
    (g, ms) (:meth:`_Slabs.cap_slabs`, ms·b² a multiple of :data:`_KC`).

    With a = r − t, b = ω − t (t the tile centre): x = 1 − r·ω = [a, |a|²/2, 1]·[−b, 1, |b|²/2] in float32,
    u = x·(c_1 + x·(c_2 + …)) by Horner (``coef`` = −s/k, the series of s·log(1 − x)), w = exp(u); sums of
    :data:`_KC` candidates in float32 (matrix products over chunks), added over the chunks in float64.
    Zero rows (missing texels, the bright set, pads) add exactly 0.  Returns the sums (g, B, Q) float64
    (:func:`_kernel32_eta` bounds their relative error)."""
    g = si.shape[0]
    a = TD - cen[:, None, :]  # (g, B, 3)
    B = a.shape[1]
    ha = 0.5 * np.einsum("gbk,gbk->gb", a, a)
    # rows 0…B−1 give x, rows B…2B−1 the first Horner stage c_K·x + c_{K−1} directly
    cK, cK1 = float(coef[-1]), float(coef[-2])
    TA = np.empty((g, 1, 2 * B, 5), dtype=np.float32)
    TA[:, 0, :B, :3] = a
    TA[:, 0, :B, 3] = ha
    TA[:, 0, :B, 4] = 1.0
    TA[:, 0, B:, :3] = cK * a
    TA[:, 0, B:, 3] = cK * ha + cK1
    TA[:, 0, B:, 4] = cK
    b = slabs.dirs[si].reshape(g, -1, 3) - cen[:, None, :]  # (g, m, 3)
    m = b.shape[1]
    nch = m // _KC
    DB = np.empty((g, nch, 5, _KC), dtype=np.float32)
    DB[:, :, :3] = -b.reshape(g, nch, _KC, 3).transpose(0, 1, 3, 2)
    DB[:, :, 3] = 1.0
    DB[:, :, 4] = (0.5 * np.einsum("gmk,gmk->gm", b, b)).reshape(g, nch, _KC)
    xu = np.matmul(TA, DB)  # (g, nch, 2B, kc)
    x, u = xu[:, :, :B], xu[:, :, B:]
    u *= x
    for c in coef[-3::-1]:
        u += c
        u *= x
    np.exp(u, out=u)
    part = np.matmul(u, slabs.rw[si].reshape(g, nch, _KC, -1))  # (g, nch, B, Q) float32 partial sums
    return np.add.reduce(part.astype(np.float64), axis=1)


def _gather_batch64(tb, ii, TD, src_dirs_pad, rad_w_pad, s, rowmax):
    """Float64 kernel (log/exp of the cosines) for the tiles ``tb`` with candidates ``ii`` (g, m): returns
    the sums (g, B, Q) and the per-row log of the reference cosine (0 unless ``rowmax``)."""
    c = np.matmul(TD[tb], src_dirs_pad[:, ii].transpose(1, 0, 2))  # (g, B, m) cosines
    np.maximum(c, 0.0, out=c)
    with np.errstate(divide="ignore"):
        np.log(c, out=c)  # −inf behind the lobe (and at the pads) → weight exactly 0
    if rowmax:
        mx = c.max(axis=2, keepdims=True)
        c -= mx
    else:
        mx = np.zeros(c.shape[:2] + (1,))
    c *= s
    np.exp(c, out=c)  # (c / c_ref)^s ≤ 1
    return np.matmul(c, rad_w_pad[ii]), mx  # Ω folded into rad_w: [Σ w L Ω, Σ w Ω]


def _bright_sums(TD_tb, bright_dirs_t, rad_w_bright, s):
    """Exact float64 sums of the bright set for the rows TD_tb (g, B, 3): (g, B, Q), weights relative to 1."""
    c = np.matmul(TD_tb, bright_dirs_t)
    np.maximum(c, 0.0, out=c)
    with np.errstate(divide="ignore"):
        np.log(c, out=c)
    c *= s
    np.exp(c, out=c)
    return np.matmul(c, rad_w_bright)


def _tile_batches(order, counts, B, chunk, key):
    """Batches of tile indices (consecutive in ``order``, with equal ``key``; ``counts`` an estimate of each
    tile's candidate count) whose weight arrays (g·B·m) stay within ``chunk`` elements (at least one tile)."""
    k0 = 0
    while k0 < len(order):
        g = max(1, chunk // (B * max(int(counts[order[k0]]), 1)))
        tb = order[k0 : k0 + g]
        tb = tb[key[tb] == key[tb[0]]]  # (order is sorted by key: a prefix)
        while tb.size > 1 and tb.size * B * int(counts[tb].max()) > chunk:
            tb = tb[: max(1, tb.size // 2)]
        yield tb
        k0 += tb.size

#: angular safety margin (rad) for chord/angle round-off in the cap tests of the sparse route
ANGLE_MARGIN = 1e-7


class SparseGather:
    """The sums of :func:`~ibl_ref.groundtruth.phong_convolution.convolve_sparse_many` — one object per call, its
    source texels arranged for this backend — and their bound (:meth:`bounds`).

    The route calls, per exponent: :meth:`bright_cut` and :meth:`tile_costs` (the tile width), :meth:`prepare`
    (the kernel's share of the accuracy target), :meth:`local_extremes`, then per attempt :meth:`gather` and
    :meth:`bounds`.  ``src_dirs`` (M, 3), ``omega`` (M,), ``rad`` (M, C): the source texels of the grid of face size
    ``m``; ``bright``: indices of the bright set (gathered by every tile); ``kernel``: ``"auto"``, ``"float32"``
    or ``"float64"`` (:func:`_gather_batch32` / :func:`_gather_batch64`).  ``gathered``: the (output, source texel)
    pairs computed so far.
    """

    #: tile-width cost model (:func:`~ibl_ref.groundtruth.phong_convolution._tile_size`), per tile and per candidate
    tile_overhead = _TILE_OVERHEAD_ELEMS
    cand_overhead = _CAND_OVERHEAD_ELEMS
    #: the name :class:`~ibl_ref.groundtruth.phong_convolution.SparseInfo` reports for this kernel
    label = "float64"

    def __init__(self, src_dirs, omega, rad, bright, m, kernel="auto", threads=1):
        if kernel not in ("auto", "float32", "float64"):
            raise IBLError(f"kernel must be 'auto', 'float32' or 'float64', got {kernel!r}")
        self.src_dirs, self.omega, self.rad, self.bright, self.m, self.kernel = src_dirs, omega, rad, bright, m, kernel
        self.threads = threads
        M, C = rad.shape
        self.is_bright = np.zeros(M, dtype=bool)
        self.is_bright[bright] = True
        self.omega_ratio = float(omega.max() / omega.min())
        self.gathered = 0
        self._slabs = None
        self._init_arrays()

    def _init_arrays(self):
        rad, omega, src_dirs, bright = self.rad, self.omega, self.src_dirs, self.bright
        M, C = rad.shape
        self.rad_w = np.concatenate([rad, np.ones((M, 1))], axis=1) * omega[:, None]
        # source directions and weights with one dummy entry (index M: direction 0 → weight 0) for the pads
        src_dirs_pad = np.concatenate([src_dirs, np.zeros((1, 3))])
        self.src_dirs_pad_t = np.ascontiguousarray(src_dirs_pad.T)
        self.rad_w_pad = np.concatenate([self.rad_w, np.zeros((1, C + 1))])
        self.bright_dirs_t = np.ascontiguousarray(src_dirs[bright].T)
        self.rad_w_bright = self.rad_w[bright]

    @functools.cached_property
    def sources(self) -> "Sources":
        """The source blocks of the cap searches and the local radiance extremes."""
        return Sources(self.src_dirs, self.rad, self.is_bright, self.m)

    def bright_cut(self, s, rho, l_ref, tau, single) -> float:
        """log δ0: the first attempt may leave out pairs whose weight is below δ0 (−700: none)."""
        return -700.0

    def tile_costs(self, s, th, log_d0):
        """``(bright texels a tile gathers, cost per tile, cost per candidate)`` of the tile-width model."""
        return int(self.bright.size), self.tile_overhead, self.cand_overhead

    def prepare(self, s, th, th_far, t_rad, rho, tau, own_log) -> float:
        """Set up exponent ``s`` (``th``/``th_far`` the typical and far caps, ``t_rad`` the largest tile radius,
        ``own_log`` the log of a row's own weight): choose the float32 kernel where its rounding bound at the typical
        cap takes ≤ 20 % of τ (decided from bounds valid for every face subset); returns the share of τ the kernel's
        rounding takes (the caps leave it out)."""
        m = self.m
        self.s, self.own_log, self.gathered = s, own_log, 0
        # a row and a candidate are within a + q, q ≤ θ_far + t_rad (slab texels lie within the slab's plane
        # diagonal (b−1)·√2·2/m of each other: the gnomonic map from the face plane to the sphere shortens distances)
        al_slab = (_SLAB - 1) * math.sqrt(2.0) * 2.0 / m
        q_top = th_far + t_rad + ANGLE_MARGIN + 2.0 * al_slab
        x_glob = 1.0 - math.cos(min(q_top + t_rad, np.pi))
        n_terms = int(_series_terms(s, x_glob + _gamma(8, _U32) * (q_top + t_rad) ** 2))
        kernel = self.kernel
        use32 = kernel != "float64" and n_terms > 0 and x_glob <= _X32_MAX and own_log >= _OWN_LOG_MIN
        if use32:  # its rounding bound at the typical cap (first attempt) takes ≤ 20 % of rtol
            q_typ = th + t_rad + ANGLE_MARGIN + 2.0 * al_slab
            eta_typ = float(_kernel32_eta(s, n_terms, t_rad, q_typ, t_rad + q_typ))
            use32 = kernel == "float32" or 2.2 * eta_typ <= 0.2 * tau
        if kernel == "float32" and not use32:
            raise IBLError(f"the float32 kernel cannot bound s = {s:g} on this grid (cap too wide or lobe narrower "
                           "than a texel); use kernel='auto'")
        if use32 and self._slabs is None:
            self._slabs = _Slabs(self.src_dirs, self.rad_w, self.is_bright, m)
        self.use32 = use32
        self.rowmax = (not use32) and own_log < -600.0
        # the float64 kernel's weights exp(s·log c) (relative to the row's largest cosine with ``rowmax``): NumPy's
        # log and exp are within the compiled kernels' stated bounds (checked in the tests), so the same model
        self.eta64, self.eps64 = weight_error(s, False, self.rowmax)
        self.label = "float32" if use32 else "float64"
        return 2.2 * eta_typ if use32 else 0.0

    def local_extremes(self, cen, q):
        """Per-channel max and min of the non-bright radiance within the caps (cen[i], q[i]) (a superset)."""
        return self.sources.local_extremes(cen, q)

    def gather(self, todo, att, log_cut, CEN, TD, q_t, a_max):
        """The sums of the tiles ``todo`` (caps ``q_t``, centres ``CEN``, rows ``TD``, radii ``a_max``) in attempt
        ``att``: ``(acc (g, B, C+1) [Σ w L Ω, Σ w Ω], log_mx (g, B) the rows' reference log weights, eta (g,) the
        sums' relative rounding bound, und (g,) the absolute allowance of the weights below the kernel's range, l_u
        the radiance und is relative to)``.  ``log_cut``: pairs below e^log_cut may be left out (not here)."""
        s, M = self.s, self.src_dirs.shape[0]
        n_t, B = TD.shape[0], TD.shape[1]
        C = self.rad.shape[1]
        bright = self.bright
        acc = np.empty((todo.size, B, C + 1))
        log_mx = np.zeros((todo.size, B))
        eta = np.full(todo.size, 1e-12)
        und = np.zeros(todo.size)
        pos = np.empty(n_t, dtype=np.intp)
        pos[todo] = np.arange(todo.size)
        est = np.minimum(M, (1.0 - np.cos(np.minimum(q_t + self.sources.alpha, np.pi))) / 2.0 * M * 1.5 + _KC)
        if self.use32:
            # series terms per tile (from the tile's own largest x: the same in every face subset); a batch
            # holds tiles with the same number of terms
            slabs = self._slabs
            r_all = a_max + q_t + 2.0 * slabs.alpha
            terms = _series_terms(s, 1.0 - np.cos(np.minimum(r_all, np.pi)) + _gamma(8, _U32) * r_all**2)
        else:
            terms = np.zeros(n_t, dtype=np.intp)
        order = todo[np.lexsort((est[todo], terms[todo]))]
        if self.use32:
            # groups of tiles with the same number of series terms: their slab lists, then batches of tiles
            # with similar list lengths (the batch pads to its longest list)
            per = _KC // _SLAB**2
            for grp in _tile_batches(order, est, 1, 512 * int(est.max()), terms):
                flat, cnt = slabs.cap_slabs(CEN[grp], q_t[grp])
                width = -(-cnt // per) * per
                srt = np.argsort(width, kind="stable")
                kt = int(terms[grp[0]])
                coef = (-s / np.arange(1, kt + 1)).astype(np.float32)
                i0 = 0
                while i0 < grp.size:
                    w = int(width[srt[i0]])
                    g = max(1, _CHUNK32 // (B * w * _SLAB**2))
                    sel = srt[i0 : i0 + g]
                    wmax = int(width[sel].max())
                    while sel.size > 1 and sel.size * B * wmax * _SLAB**2 > _CHUNK32:
                        sel = sel[: sel.size // 2]
                        wmax = int(width[sel].max())
                    tb = grp[sel]
                    r = pos[tb]
                    si = _padded(flat, cnt, sel, wmax, slabs.pad)
                    acc[r] = _gather_batch32(CEN[tb], TD[tb], si, slabs, coef)
                    r_b = q_t[tb] + 2.0 * slabs.alpha
                    eta[r] = _kernel32_eta(s, kt, a_max[tb], r_b, a_max[tb] + r_b)
                    und[r] = _kernel32_underflow(wmax * _SLAB**2 + bright.size, self.own_log, self.omega_ratio)
                    if bright.size:
                        acc[r] += _bright_sums(TD[tb], self.bright_dirs_t, self.rad_w_bright, s)
                    self.gathered += si.size * _SLAB**2 * B
                    i0 += sel.size
        else:
            # (batches sized by the texels within q at the mean density: the lists are built per batch)
            est64 = np.maximum((1.0 - np.cos(np.minimum(q_t, np.pi))) / 2.0 * M, 1.0)
            for tb in _tile_batches(order, est64, B, _CHUNK_ELEMS, terms):
                r = pos[tb]
                ii, _cnt = self.sources.cap_lists(CEN[tb], q_t[tb], M)
                if self.rowmax and bright.size:  # the row maxima include the bright set
                    ii = np.concatenate([ii, np.broadcast_to(bright, (tb.size, bright.size))], axis=1)
                acc[r], mx = _gather_batch64(tb, ii, TD, self.src_dirs_pad_t, self.rad_w_pad, s, self.rowmax)
                log_mx[r] = s * mx[..., 0]
                m = ii.shape[1]
                if bright.size and not self.rowmax:
                    acc[r] += _bright_sums(TD[tb], self.bright_dirs_t, self.rad_w_bright, s)
                    m += bright.size
                # the weights' rounding (relative η for r·ω ≥ C0, absolute ε per pair below, against W_in ≥ the own
                # texel's weight · Ω_min) and the sums' (γ_m, any order)
                eta[r] = self.eta64 + sum_error(m)
                und[r] = m * self.eps64 * math.exp(-(0.0 if self.rowmax else self.own_log)) * self.omega_ratio
                self.gathered += ii.size * B
        # (the float32 kernel's allowance is relative to the tiles' local radiance maxima, the float64 kernel's to
        # the largest radiance: its pairs include the bright set)
        return acc, log_mx, eta, und, None if self.use32 else float(self.rad.max())

    def bounds(self, sums, tt, ANG, q_t, q_far, half_margin, grid, log_wb_grid, lmax2, lmin2, l_max_out, l_min_out,
               VALID, IDX, maps, bounds):
        """:func:`tile_bounds` of :meth:`gather`'s ``sums`` for the tiles ``tt``."""
        acc, log_mx, eta, und, l_und = sums
        l_u = lmax2[tt][:, None, :] if l_und is None else l_und
        return tile_bounds(acc, log_mx, eta, und, l_u, ANG[tt], q_t[tt], q_far[tt], half_margin,
                           grid, log_wb_grid, lmax2[tt], lmin2[tt], l_max_out, l_min_out, VALID[tt], IDX[tt], maps,
                           bounds)


def tile_bounds(acc, log_mx, eta, und, l_u, ang, q_t, q_far, half_margin, grid, log_wb_grid, lmax, lmin, l_max_out,
                l_min_out, valid, idx, maps, bounds):
    """The averages and the rigorous per-texel bounds of gathered tiles (the sparse route's formula, module docstring
    of :mod:`ibl_ref.groundtruth.phong_convolution`): ``P = Σ w L Ω / Σ w Ω`` (``acc``), ``log W_in = log_mx +
    log Σ w Ω − log1p(η + und)``; the neglected texels of a row at angle a lie beyond ``q − a`` (local extremes
    ``lmax``/``lmin`` up to ``q_far − a``) and beyond ``q_far − a`` (global extremes), ``f = W_b(θ)/W_in`` from the
    tabulated ``log W_b`` (the grid angle ≤ θ); ``e_fp = 2η/(1−η)·P + und·(l_u + P)``;
    ``b = min(f1, f2)·d_glob + max(f1 − f2, 0)·d_loc + e_fp + 1e-12·P``.  Valid rows are written to
    ``maps``/``bounds`` at the flat output rows ``idx``; returns the largest b/P of every tile's valid entries."""
    C = acc.shape[-1] - 1

    def log_wb_at(theta):
        gi = np.searchsorted(grid, theta, side="right") - 1
        return np.where(gi >= 0, log_wb_grid[np.maximum(gi, 0)], 0.0 * theta + np.inf)

    p_avg = acc[..., :C] / acc[..., C:]
    # log W_in (absolute Σ cos^s Ω over the gathered set), lowered by the kernel's error bound
    log_win = log_mx + np.log(acc[..., C]) - np.log1p(eta + und)[:, None]
    e_fp = (2.0 * eta / (1.0 - eta))[:, None, None] * p_avg + und[:, None, None] * (l_u + p_avg)
    lw1 = log_wb_at(q_t[:, None] - half_margin - ang)
    lw2 = log_wb_at(q_far[:, None] - half_margin - ang)
    with np.errstate(over="ignore", invalid="ignore"):
        f1 = np.where(np.isneginf(lw1), 0.0, np.exp(np.minimum(lw1 - log_win, 700.0)))
        f2 = np.where(np.isneginf(lw2), 0.0, np.exp(np.minimum(lw2 - log_win, 700.0)))
    d_loc = np.maximum(np.maximum(lmax[:, None, :] - p_avg, p_avg - lmin[:, None, :]), 0.0) + e_fp
    d_glob = np.maximum(np.maximum(l_max_out - p_avg, p_avg - l_min_out), 0.0) + e_fp
    b_abs = (np.minimum(f1, f2)[..., None] * d_glob + np.maximum(f1 - f2, 0.0)[..., None] * d_loc
             + e_fp + 1e-12 * p_avg)
    maps[idx[valid]] = p_avg[valid]
    bounds[idx[valid]] = b_abs[valid]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(valid[..., None], b_abs / p_avg, 0.0).reshape(acc.shape[0], -1).max(axis=1)


# ----------------------------------------------------------------------------------------------------------------
# moment route: the horizon band
# ----------------------------------------------------------------------------------------------------------------
#: bound on the (tile, source texel) pairs one chunk of output tiles may hold in the band gather of ``leaf = 1``
#: (≈ 10 float64/bool arrays of this length: ≈ 0.3 GB); the chunks are fixed by the sizes alone, so every worker
#: count computes the same pieces
MOMENT_CHUNK_PAIRS = 1 << 22

#: index pairs of the 6 distinct entries of the symmetric second moment ω ωᵀ
SYM_PAIRS = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def band_exact(Rc, tiles, blk, bdT, bw_pad, s_list, num, chunk_elems):
    """Exact gather of the straddling texels ``blk`` for their tiles (``leaf = 1``), into ``num``.

    ``bdT`` (3, M+1) and ``bw_pad`` (M+1, Q): source directions and weights with a zero dummy last entry.
    """
    for tc, idx in _padded_batches(tiles, blk, Rc.shape[0], Rc.shape[1], chunk_elems, 1):
        R = Rc[tc]
        # segments of the band small enough for the cache (the gather is memory-bound)
        seg = max(64, chunk_elems // (len(tc) * Rc.shape[1]))
        acc = {s_: 0.0 for s_ in s_list}
        for m0 in range(0, idx.shape[1], seg):
            ii = idx[:, m0 : m0 + seg]
            dzT = np.stack([bdT[k][ii] for k in range(3)], axis=1)  # (tc, 3, m), pads → 0
            wz = bw_pad[ii]  # (tc, m, Q)
            X = np.matmul(R, dzT)  # (tc, t², m)
            np.maximum(X, 0.0, out=X)
            for s in s_list:
                if s == 1.0:
                    acc[s] = acc[s] + np.matmul(X, wz)
                else:
                    np.multiply(X, X, out=X)  # s = 2 last (sorted)
                    acc[s] = acc[s] + np.matmul(X, wz)
        for s in s_list:
            num[s][tc] += acc[s]


def band_brackets(Rc, tiles, blk, cb_leaf, ab_leaf, M0, M1, M2, s_list, num, err, chunk_elems):
    """Linear brackets of the clamped kernel on the straddling leaf blocks (``leaf > 1``), per output texel.

    For an output texel ``r`` and a leaf block (cone ``(c, α)`` around its texel centres) every
    ``x = r·ω_j`` lies in ``[x_lo, x_hi] = [cos(θ+α), cos(max(θ−α, 0))]``, θ = ∠(r, c).  With
    ``x_lo < 0 < x_hi`` and ``A = x_hi/(x_hi − x_lo)``:

    * s = 1:  ``A x ≤ max(x,0) ≤ A x + B``, ``B = −A x_lo`` (a line through 0 below, the chord above);
    * s = 2:  ``a x − a²/4 ≤ max(x,0)² ≤ a (x − x_lo)``, ``a = x_hi²/(x_hi − x_lo)`` (the tangent of
      slope a below, the chord above),

    so summed over the block's texels with weights ``L Ω`` the contribution lies in an interval whose
    ends are linear in the block moments ``W = Σ L Ω`` and ``y = r·Σ L Ω ω``: the midpoint and the
    half-width accumulate into ``num``/``err`` by matrix products.  Blocks entirely on the positive
    side of this ``r`` (``x_lo ≥ 0``) are exact (``y``, or ``rᵀ M2 r`` for s = 2), those on the negative
    side contribute 0.  The half-width is at most ``W sin α / 4`` (s = 1), ``≈ 0.28 W sin² α`` (s = 2).
    """
    Q = M0.shape[1]
    if ab_leaf.size and float(ab_leaf.max()) >= 0.25 * math.pi:
        raise IBLError("leaf blocks too large for the bracket band (cone half-angle ≥ π/4); use a smaller leaf")
    # With α < π/4: θ < α ⇒ x_lo = cos(θ+α) > 0 (exact), θ > π − α ⇒ x_hi < 0 (zero), so
    # cos(θ ∓ α) = X cos α ± sin θ sin α needs no case split.  ``1e-12`` (in v) covers the rounding
    # of X, sin θ and the products (≲ 1e-15).
    cz_all = np.concatenate([cb_leaf, np.array([[0.0, 0.0, 1.0]])])
    ca_all = np.concatenate([np.cos(ab_leaf), [1.0]])
    sa_all = np.concatenate([np.sin(ab_leaf), [0.0]])
    M0z = np.concatenate([M0, np.zeros((1, Q))])
    M1z = np.concatenate([M1.reshape(-1, 3 * Q), np.zeros((1, 3 * Q))])
    M2z = None if M2 is None else np.concatenate([M2.reshape(-1, 6 * Q), np.zeros((1, 6 * Q))])
    wts = np.array([1.0, 2.0, 2.0, 1.0, 2.0, 1.0])

    def rsum(Z, RR, k):  # Σ_k r_k Z_kq per texel: (tc, t², k·Q) → (tc, t², Q)
        return np.einsum("cik,cikq->ciq", RR, Z.reshape(Z.shape[0], Z.shape[1], k, Q))

    for tc, idx in _padded_batches(tiles, blk, Rc.shape[0], Rc.shape[1], chunk_elems, 4):
        R = Rc[tc]
        X = np.matmul(R, cz_all[idx].transpose(0, 2, 1))  # (tc, t², m): r·c = cos θ
        ca, sa = ca_all[idx][:, None, :], sa_all[idx][:, None, :]
        v = np.multiply(X, X)
        np.subtract(1.0, v, out=v)
        np.maximum(v, 0.0, out=v)
        np.sqrt(v, out=v)
        v *= sa
        v += 1e-12  # v = sin θ sin α + slack:  x_lo = u − v,  x_hi = u + v
        X *= ca  # u = X cos α
        # A = x_hi/(x_hi − x_lo) clipped to [0, 1]: 1 on positive pairs, 0 on negative ones
        A = np.add(X, v)
        A /= 2.0 * v
        np.clip(A, 0.0, 1.0, out=A)
        nlo = np.subtract(v, X)  # −x_lo
        W = M0z[idx]  # (tc, m, Q)
        Y1 = M1z[idx]  # (tc, m, 3Q)
        for s in s_list:
            if s == 1.0:
                H = np.maximum(nlo, 0.0)
                H *= A
                H *= 0.5  # B/2 = A·(−x_lo)/2 (0 unless straddling)
                HW = np.matmul(H, W)
                num[s][tc] += rsum(np.matmul(A, Y1), R, 3) + HW
                err[s][tc] += HW
            else:
                # a = x_hi²/(x_hi − x_lo) = A²·(x_hi − x_lo) = 2v·A² on straddling pairs (0 ≤ A < 1;
                # A = 0 gives 0), 0 on positive ones (A = 1: exact by rᵀ M2 r)
                P = A >= 1.0
                a = np.multiply(A, A)
                a *= v
                a *= 2.0
                a[P] = 0.0
                av = a * nlo  # a·(−x_lo)
                a2 = np.multiply(a, a)
                a2 *= 0.25
                a2 += av  # 2·half-width = a·(−x_lo) + a²/4;  midpoint = a·(−x_lo) − half-width
                half_W = 0.5 * np.matmul(a2, W)
                RR = R[..., SYM_PAIRS[0]] * R[..., SYM_PAIRS[1]] * wts
                num[s][tc] += (rsum(np.matmul(a, Y1), R, 3) + np.matmul(av, W) - half_W
                               + rsum(np.matmul(P.astype(float), M2z[idx]), RR, 6))
                err[s][tc] += half_W


def _padded_batches(tiles, blk, T, tt, chunk_elems, per_elem):
    """Yield ``(tile indices, padded index matrix)`` batches of tiles sorted by band size (pads = −1)."""
    order = np.argsort(tiles, kind="stable")
    tiles, blk = tiles[order], blk[order]
    counts = np.bincount(tiles, minlength=T)
    starts = np.concatenate([[0], np.cumsum(counts)])
    tord = np.argsort(counts, kind="stable")
    if not T or int(counts.max()) == 0:
        return
    k0 = 0
    while k0 < T:
        k1 = k0 + 1
        # grow the batch while the padded working set fits
        while k1 < T and (k1 - k0 + 1) * max(int(counts[tord[k1]]), 1) * tt * per_elem <= chunk_elems:
            k1 += 1
        tc = tord[k0:k1]
        mmax = int(counts[tc].max())
        k0 = k1
        if mmax == 0:
            continue
        ar = np.arange(mmax)
        okm = ar[None, :] < counts[tc][:, None]
        pos_ = np.where(okm, starts[tc][:, None] + ar[None, :], 0)
        yield tc, np.where(okm, blk[pos_], -1)


# ----------------------------------------------------------------------------------------------------------------
# SH route: the exact gather from the bright texels
# ----------------------------------------------------------------------------------------------------------------
def bright_gather(out_dirs, b_dirs, b_w, s_list, chunk_elems=1 << 22):
    """Exact ``Σ_b b_w[b]·max(r·ω_b, 0)^s`` for every output direction r and exponent s: (K, P, C) (float64,
    ``exp(s·log c)``)."""
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


# ----------------------------------------------------------------------------------------------------------------
# GGX n = v = r prefilter: the block-Taylor tree (ibl_ref.groundtruth.ggx_convolution states the tests and the bound).
# The (tile, block) pairs are refined round by round as arrays (ggx_refine), then the final ones summed per
# output texel (ggx_evaluate); numba_loops.ggx_tree makes the same decisions depth first per tile.
# ----------------------------------------------------------------------------------------------------------------
#: angular margin (rad) of the tile cones (arccos rounding)
GGX_ANGLE_EPS = 1e-9
#: absolute margin of δ (the rounding of x_B = r·ĉ)
GGX_DELTA_EPS = 1e-15
#: largest (pair × texel-of-tile × channel) elements evaluated at once
GGX_CHUNK_ELEMS = 1 << 20
#: output tiles classified at once (× t² texels ≤ this)
GGX_CHUNK_TEXELS = 4096
#: the weights of the 6 entries of a symmetric 3×3 matrix (:data:`SYM_PAIRS`) in rᵀVr
GGX_SYM_W = np.array([1.0, 2.0, 2.0, 1.0, 2.0, 1.0])


def quad_children(blk, m):
    """Flat child indices (4 per parent) of blocks ``blk`` on a 6×m×m grid → grid 6×2m×2m."""
    f, rem = np.divmod(blk, m * m)
    i, j = np.divmod(rem, m)
    m2 = 2 * m
    base = f * m2 * m2 + 2 * i * m2 + 2 * j
    return (base[:, None] + np.array([0, 1, m2, m2 + 1])[None, :]).ravel()


def _ggx_span(ct, st, c_b, s_b):
    """``(x_max, x_min, sin_max)`` over the angles [θ − β, θ + β] ∩ [0, π] (cos θ = ct, sin θ = st ≥ 0):
    cos(θ ∓ β) = cos θ cos β ± sin θ sin β."""
    inside = ct >= c_b  # θ ≤ β
    x_max = np.where(inside, 1.0, ct * c_b + st * s_b)
    s_lo = np.where(inside, 0.0, st * c_b - ct * s_b)
    beyond = ct <= -c_b  # θ + β ≥ π
    x_min = np.where(beyond, -1.0, ct * c_b - st * s_b)
    s_hi = np.where(beyond, 0.0, st * c_b + ct * s_b)
    return x_max, x_min, np.where((x_max >= 0.0) & (x_min <= 0.0), 1.0, np.maximum(s_lo, s_hi))


def ggx_pairs(L, kern, cT, cone, dcone, hshare, tiles, blk):
    """Tests of the (tile, block) pairs ``(tiles, blk)`` of level ``L`` (module docstring of
    :mod:`ibl_ref.groundtruth.ggx_convolution`): ``(live, e, k_centre)`` — whether some texel of the block may be above
    some output texel's horizon (over the tile's whole cone, ``cone`` = (cos β, sin β) per tile: rigorous); the
    per-channel bound estimates ``e`` (pairs, Q): where K is smooth on the pair for every texel of the tile, over its
    decision cone ``dcone`` the smaller of the zero-order bracket's half-width ½K(x_top)·M0 and the Taylor remainder
    K'''(x_top)/6 · δ · min(δ² M0, tr V), elsewhere the bracket's half-width over the whole cone (which some texel
    takes); K at the tile's axis (the block's share of the tile's estimate)."""
    ct = np.clip(np.einsum("pk,pk->p", cT[tiles], L.c[blk]), -1.0, 1.0)
    st = np.sqrt(np.maximum(1.0 - ct * ct, 0.0))
    cp, sp = L.cos_psi[blk], L.sin_psi[blk]
    x_max, x_min, sin_max = _ggx_span(ct, st, cone[0][tiles], cone[1][tiles])
    delta = (1.0 - cp) * np.maximum(np.abs(x_min), np.abs(x_max)) + sp * sin_max + GGX_DELTA_EPS
    live = x_max + delta > 0.0
    M0 = L.M0[blk]
    # near some texel's horizon that texel takes the bracket (≤ ½K(x_top)·M0 over the whole cone): a share hshare of
    # it joins the estimate, so that a zero estimate always means a zero bound
    h_full = np.where(x_min - delta <= 0.0, hshare * 0.5 * kern.value(np.minimum(x_max + delta, 1.0)), 0.0)
    x_max, x_min, sin_max = _ggx_span(ct, st, dcone[0][tiles], dcone[1][tiles])
    delta = (1.0 - cp) * np.maximum(np.abs(x_min), np.abs(x_max)) + sp * sin_max + GGX_DELTA_EPS
    x_top = np.minimum(x_max + delta, 1.0)
    e = 0.5 * kern.value(x_top)[:, None] * M0
    smooth = x_min - delta > 0.0
    if smooth.any():
        c3 = kern.d3(x_top[smooth]) * delta[smooth] / 6.0
        eT = c3[:, None] * np.minimum((delta[smooth] ** 2)[:, None] * M0[smooth], L.trV[blk[smooth]])
        e[smooth] = np.minimum(e[smooth], eT)
    return live, e + h_full[:, None] * M0, kern.value(ct)


def _tile_sums(tiles, x, T):
    """Per tile the column sums of ``x`` (pairs, k) → (T, k)."""
    return np.stack([np.bincount(tiles, weights=x[:, q], minlength=T) for q in range(x.shape[1])], axis=1)


def _split_threshold(tiles, metric, total, thr, target, split_gain):
    """Per tile the split threshold of :func:`~ibl_ref.groundtruth.kernels.numba_loops.ggx_tree`: ``thr`` (half the
    mean share) doubled while the pairs at or above twice it hold at least ``(total − target)/split_gain``."""
    T = total.size
    with np.errstate(invalid="ignore"):
        need = (total - target) / split_gain
        active = (total > target) & (need < total)
    thr = thr.copy()
    while active.any():
        thr2 = 2.0 * thr
        held = np.bincount(tiles, weights=np.where(metric >= thr2[tiles], metric, 0.0), minlength=T)
        active &= held >= need
        thr = np.where(active, thr2, thr)
    return thr


def ggx_refine(levels, kern, cT, betaT, target, beta_share, hshare, split_gain=1.0):
    """Greedy refinement of one chunk of output tiles (:func:`ibl_ref.groundtruth.kernels.numba_loops.ggx_tree`
    states the rule), as arrays over all the chunk's tiles at once, round by round: ``{level: (tiles, blocks)}`` of
    the final pairs, level 0 the texels."""
    T = cT.shape[0]
    top = len(levels) - 1
    Q = levels[0].M0.shape[1]
    C = Q - 1
    beta = betaT + GGX_ANGLE_EPS
    cone, dcone = (np.cos(beta), np.sin(beta)), (np.cos(beta_share * beta), np.sin(beta_share * beta))
    final = {li: [] for li in range(top + 1)}
    ex = np.zeros((T, Q))

    def enter(tiles, blk, li):
        """The live pairs at level ``li``: (tiles, blk, level, e, s)."""
        L = levels[li]
        ok = L.valid[blk]
        tiles, blk = tiles[ok], blk[ok]
        live, e, kc = ggx_pairs(L, kern, cT, cone, dcone, hshare, tiles, blk)
        return tiles[live], blk[live], np.full(int(live.sum()), li), e[live], kc[live][:, None] * L.M0[blk[live]]

    state = enter(np.repeat(np.arange(T), 6), np.tile(np.arange(6), T), top)
    while state[0].size:
        tiles, blk, lev, e, s = state
        nh = ex + _tile_sums(tiles, s, T)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.where(e > 0.0, e / nh[tiles], 0.0)
        metric = rel[:, :C].max(axis=1) + rel[:, C]
        total = np.bincount(tiles, weights=metric, minlength=T)
        count = np.bincount(tiles, minlength=T)
        thr = _split_threshold(tiles, metric, total, total / np.maximum(2.0 * count, 1.0), target, split_gain)
        done = (total <= target)[tiles]
        split = ~done & (metric >= thr[tiles])
        for li in np.unique(lev[done]):
            sel = done & (lev == li)
            final[li].append((tiles[sel], blk[sel]))
        stay = ~done & ~split
        parts = [tuple(x[stay] for x in state)]
        for li in np.unique(lev[split]):
            sel = split & (lev == li)
            ct_, cb_ = np.repeat(tiles[sel], 4), quad_children(blk[sel], levels[li].m)
            if li == 1:  # texels: exact, their share of the estimate fixed
                ok = levels[0].valid[cb_]
                ct_, cb_ = ct_[ok], cb_[ok]
                final[0].append((ct_, cb_))
                kc = kern.value(np.einsum("pk,pk->p", cT[ct_], levels[0].c[cb_]))
                ex += _tile_sums(ct_, kc[:, None] * levels[0].M0[cb_], T)
                continue
            parts.append(enter(ct_, cb_, li - 1))
        state = tuple(np.concatenate([p[k] for p in parts]) for k in range(5))
    # the final 2×2 blocks as their four texels, exactly (cheaper per output texel than the Taylor sum)
    if final.get(1):
        last = final.pop(1)
        tl, bk = (np.concatenate([c[k] for c in last]) for k in range(2))
        ct_, cb_ = np.repeat(tl, 4), quad_children(bk, levels[1].m)
        ok = levels[0].valid[cb_]
        final[0].append((ct_[ok], cb_[ok]))
    return {li: tuple(np.concatenate([c[k] for c in chunks]) for k in range(2))
            for li, chunks in final.items() if chunks}


def _scatter_add(out, idx, vals):
    """``out[idx[k]] += vals[k]`` (indices may repeat), by a stable sort and a segmented sum."""
    if not idx.size:
        return
    order = np.argsort(idx, kind="stable")
    idx_s = idx[order]
    starts = np.flatnonzero(np.r_[True, idx_s[1:] != idx_s[:-1]])
    out[idx_s[starts]] += np.add.reduceat(vals[order], starts, axis=0)


def ggx_evaluate(levels, kern, R, accepted, num, err):
    """Add the final pairs' sums and absolute bounds to ``num``/``err`` ((tiles, t², Q)) of the chunk, per output
    texel r and channel the better of two rigorous brackets of the block's sum: the Taylor sum
    ``K(x_B) M0 + K'(x_B) r·U + ½K''(x_B) rᵀVr`` with the remainder bound ``K'''(x_B + δ)/6 · δ · rᵀVr`` (where
    x_B − δ > 0) or the zero-order bracket, midpoint and half-width ``½K(x_B + δ)·M0``; texels exactly."""
    t2, Q = R.shape[1], num.shape[-1]
    step = max(1, GGX_CHUNK_ELEMS // (t2 * Q))
    i, j = SYM_PAIRS
    for li, (tiles, blk) in accepted.items():
        L = levels[li]
        for k0 in range(0, tiles.size, step):
            tl, bk = tiles[k0:k0 + step], blk[k0:k0 + step]
            Rt = R[tl]  # (p, t², 3)
            M0 = L.M0[bk][:, None, :]  # (p, 1, Q)
            x = np.einsum("pik,pk->pi", Rt, L.c[bk])
            if li == 0:  # single texels: the exact term
                _scatter_add(num, tl, kern.value(x)[..., None] * M0)
                continue
            delta = ((1.0 - L.cos_psi[bk])[:, None] * np.abs(x)
                     + L.sin_psi[bk][:, None] * np.sqrt(np.maximum(1.0 - x * x, 0.0)) + GGX_DELTA_EPS)
            x_top = np.minimum(x + delta, 1.0)
            smooth = x - delta > 0.0
            hm = 0.5 * kern.value(x_top)[..., None] * M0
            K0, K1, K2 = kern.taylor(np.where(smooth, x, 1.0))
            s2 = np.matmul(Rt[..., i] * Rt[..., j] * GGX_SYM_W, L.V[bk])  # Σ w (x − x_B)² = rᵀVr
            with np.errstate(invalid="ignore"):
                eT = np.where(smooth, kern.d3(np.where(smooth, x_top, 0.0)) * delta / 6.0, np.inf)[..., None] * s2
            use_t = eT < hm
            est = K0[..., None] * M0 + K1[..., None] * np.matmul(Rt, L.U[bk]) + 0.5 * K2[..., None] * s2
            _scatter_add(num, tl, np.where(use_t, est, hm))
            _scatter_add(err, tl, np.where(use_t, eT, hm))


def ggx_tree_pass(tree, kern, R, cT, betaT, sel, target, beta_share, hshare, split_gain=1.0):
    """``(num, err, pairs)``: the sums and absolute bounds ((len(sel), t², Q)) of the output tiles ``sel``, each refined
    until its summed relative bound estimate is at most ``target[k]`` (:func:`ggx_refine`), and the final pairs per
    level; in chunks of :data:`GGX_CHUNK_TEXELS` output texels."""
    levels = tree.levels
    t2, Q = R.shape[1], levels[0].M0.shape[1]
    num = np.zeros((sel.size, t2, Q))
    err = np.zeros((sel.size, t2, Q))
    pairs = np.zeros(len(levels), np.int64)
    step = max(1, GGX_CHUNK_TEXELS // t2)
    for c0 in range(0, sel.size, step):
        ch = sel[c0:c0 + step]
        acc = ggx_refine(levels, kern, cT[ch], betaT[ch], target[c0:c0 + step], beta_share, hshare, split_gain)
        for li, (tl, _) in acc.items():
            pairs[li] += tl.size
        ggx_evaluate(levels, kern, R[ch], acc, num[c0:c0 + step], err[c0:c0 + step])
    return num, err, pairs


# ----------------------------------------------------------------------------------------------------------------
# the backend
# ----------------------------------------------------------------------------------------------------------------
class NumpyKernels(Kernels, NumpySH):
    """The NumPy implementation of :class:`ibl_ref.groundtruth.kernels.Kernels` (the reference)."""

    name = "numpy"
    #: whether the sparse gather shares one call's tiles between threads (``threads=``)
    gather_threads = False

    def moment_chunk_pairs(self, Q) -> int:
        """(tile, texel) pairs of one chunk of output tiles of the moment route's band (:data:`MOMENT_CHUNK_PAIRS`)."""
        return MOMENT_CHUNK_PAIRS

    def warm_up(self, stages=()) -> float:
        """Nothing to compile or load: 0 seconds."""
        return 0.0

    def loaded(self) -> bool:
        return True

    def sparse_gather(self, src_dirs, omega, rad, bright, m, kernel="auto", threads=1) -> SparseGather:
        """The sums and bounds of one call of the sparse route (:class:`SparseGather`)."""
        return SparseGather(src_dirs, omega, rad, bright, m, kernel, threads)

    def band_sources(self, bdT, bw_pad):
        """The band's source texels as :meth:`band_exact` takes them: directions (3, M+1), weights (M+1, Q), the last
        entry a zero-weight dummy (the index of the pads)."""
        return bdT, bw_pad

    def band_exact(self, Rc, tiles, blk, src, s_list, num, chunk_elems):
        """Exact gather of the straddling texels ``blk`` of the output tiles ``tiles`` (rows ``Rc``): ``num[s] +=
        Σ max(r·ω, 0)^s·w`` for s ∈ {1, 2} (:func:`band_exact`)."""
        band_exact(Rc, tiles, blk, *src, s_list, num, chunk_elems)

    def brackets_prep(self, cb_leaf, ab_leaf, M0, M1, M2):
        """The leaf blocks' cones (centres, half-angles) and moments as :meth:`band_brackets` takes them."""
        return cb_leaf, ab_leaf, M0, M1, M2

    def band_brackets(self, Rc, tiles, blk, prep, s_list, num, err, chunk_elems):
        """Linear brackets of the clamped kernel on the straddling leaf blocks ``blk`` (:func:`band_brackets`): the
        midpoints into ``num``, the half-widths into ``err``."""
        band_brackets(Rc, tiles, blk, *prep, s_list, num, err, chunk_elems)

    def bright_gather(self, out_dirs, b_dirs, b_w, s_list):
        """Exact sums of the bright texels (:func:`bright_gather`)."""
        return bright_gather(out_dirs, b_dirs, b_w, s_list)

    def bright_gather_error(self, nb, b_w, s_list):
        """Absolute rounding allowance of :meth:`bright_gather`'s sums ``nb`` beyond the 1e-12 every SH bound carries
        (None: nothing to add)."""
        return None

    def ggx_tree_pass(self, tree, kern, R, cT, betaT, sel, target, beta_share, hshare, split_gain=1.0, threads=1):
        """``(num, err, pairs)`` of the GGX tree route for the output tiles ``sel`` (:func:`ggx_tree_pass`; one
        thread)."""
        return ggx_tree_pass(tree, kern, R, cT, betaT, sel, target, beta_share, hshare, split_gain)
