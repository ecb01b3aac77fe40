"""The compiled backend of the convolution kernels: :class:`CompiledKernels`, the operations of
:class:`ibl_ref.groundtruth.kernels.Kernels` by the numba loops of :mod:`ibl_ref.groundtruth.kernels.numba_loops`
(Knuth et al. 2014, Sec. 3.2, Eq. 4).

Operations without a compiled loop (the SH route's bounds, the moment route with more than 3 colour channels) are
the NumPy backend's, which this class extends.  The sums are the NumPy backend's quadratures in another order (and
the sparse gather in float64 where the NumPy one may use float32): results agree within the sum of the two bounds,
each of which holds (every compiled loop's rounding is part of its bound, :mod:`~ibl_ref.groundtruth.kernels.rounding`).

Compilation and numba's cache
    numba compiles every loop on its first use and keeps the machine code in its cache (``__pycache__`` next to
    :mod:`~ibl_ref.groundtruth.kernels.numba_loops`, or ``$NUMBA_CACHE_DIR``); :meth:`CompiledKernels.warm_up` does
    that for the loops of the routes a call takes, on tiny inputs, before any worker is forked.  A cache entry that
    does not load is never fatal: after each warm-up the entries are recorded (size and CRC-32) in
    ``ibl_ref_kernels.json`` beside them; an entry that no longer matches its record is removed before numba reads it,
    one not recorded yet is first loaded in a child process, and an entry whose load fails (or kills the child) is
    removed and compiled again — each with one line on stderr.  Where the cache cannot be written (a full disk, a
    read-only folder) the loops are compiled without it (``IBL_REF_NUMBA_CACHE=0``), again with one line.
"""

from __future__ import annotations

import functools
import importlib
import json
import math
import os
import subprocess
import sys
import threading
import time
import zlib
from pathlib import Path

import numpy as np

from ...atomic import atomic_write
from ...environment import envmap
from ...errors import IBLError
from .. import sh_basis
from ..ggx_convolution import GGXLobeKernel, GGXSourceTree
from ..sh_tables import _row_layout, compiled_tables
from . import numba_loops
from .numpy_backend import NumpyKernels, Sources, SparseGather
from .rounding import BRIGHT_GROUP, POWI_MAX, SH_BLOCK, sum_error, weight_error

__all__ = ["CompiledKernels", "STAGES"]

#: the stages of :meth:`CompiledKernels.warm_up`: the loops of each route
STAGES = ("sparse", "moment", "sh", "ggx")
#: the record of numba's cache entries of the loops, beside them
MANIFEST = "ibl_ref_kernels.json"
#: tile-width cost model of the compiled gather (no Python per tile; per candidate the interval search and the copy
#: into the scratch arrays), in units of one of its weights; fitted by ``python benchmarks/bench_tile_size.py --probe
#: …/courtyard.exr`` (2026-12-06, commit e5e4bcc, load ≈ 1: every width T ∈ {2…16} forced in 15 cells of sky + sun
#: 64²–256² and the courtyard probe 128²–256², s = 64…4096): the model's choice costs 1.012× the best width on average,
#: 1.12× at most (the constants fitted for the ahead-of-time kernels' 512-bit code, 1000 and 4: 1.031×, 1.20×)
TILE_OVERHEAD = 2000.0
CAND_OVERHEAD = 8.0
#: share of the accuracy target τ that the first attempt's left-out bright weights may take (at the mean radiance)
BRIGHT_CUT_SHARE = 0.05
#: fewest tiles per thread of the threaded gather
TILES_PER_THREAD_MIN = 32
#: working-set size of one chunk of the compiled SH matrix (float64 elements, 16 MB: the products read it from L3)
SH_CHUNK_ELEMS = 1 << 21


# ----------------------------------------------------------------------------------------------------------------
# sparse route
# ----------------------------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=8)
def _direction_columns(m: int):
    """The texel directions of the m² grid as three contiguous read-only columns X, Y, Z (M,)."""
    d = envmap.texel_directions(m).reshape(-1, 3)
    cols = tuple(np.ascontiguousarray(d[:, i]) for i in range(3))
    for x in cols:
        x.flags.writeable = False
    return cols


def bright_groups(bdirs):
    """The groups of :data:`~ibl_ref.groundtruth.kernels.rounding.BRIGHT_GROUP` consecutive bright texels (rows of
    ``bdirs`` (nb, 3), unit vectors) that :func:`~ibl_ref.groundtruth.kernels.numba_loops.tile_gather` skips whole
    when out of reach: unit centres (G, 3) and the largest angle from each centre to a member (+1e-9 rad)."""
    nb = bdirs.shape[0]
    G = -(-nb // BRIGHT_GROUP)
    pad = np.zeros((G * BRIGHT_GROUP, 3))
    pad[:nb] = bdirs
    grp = pad.reshape(G, BRIGHT_GROUP, 3)
    cen = grp.sum(axis=1)
    norm = np.linalg.norm(cen, axis=1, keepdims=True)
    cen = np.where(norm > 0, cen / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 1.0]))
    real = (np.arange(G * BRIGHT_GROUP) < nb).reshape(G, BRIGHT_GROUP)
    dots = np.where(real, np.einsum("gkj,gj->gk", grp, cen), 1.0)
    alpha = np.arccos(np.clip(dots.min(axis=1), -1.0, 1.0)) + 1e-9 if G else np.zeros(0)
    return np.ascontiguousarray(cen), np.ascontiguousarray(alpha)


class CompiledSources(Sources):
    """:class:`~ibl_ref.groundtruth.kernels.numpy_backend.Sources` whose local extremes come from
    :func:`~ibl_ref.groundtruth.kernels.numba_loops.cone_extremes` (super-blocks of k × k blocks)."""

    @functools.cached_property
    def _sup(self, k=8):
        nb = len(self.cen)
        nside = int(round(math.sqrt(nb / 6)))
        nk = -(-nside // k)
        mem = np.full((6, nk * k, nk * k), -1, dtype=np.intp)
        mem[:, :nside, :nside] = np.arange(nb).reshape(6, nside, nside)
        mem = envmap.face_blocks(mem, k)
        mem = mem[(mem >= 0).any(axis=1)]
        valid = mem >= 0
        c = np.where(valid[..., None], self.cen[np.maximum(mem, 0)], 0.0).sum(axis=1)
        c /= np.linalg.norm(c, axis=1, keepdims=True)
        dots = np.where(valid, np.einsum("skj,sj->sk", self.cen[np.maximum(mem, 0)], c), 1.0)
        sup_alpha = float(np.arccos(np.clip(dots.min(), -1.0, 1.0))) + self.alpha + 1e-9
        return np.ascontiguousarray(c), sup_alpha, np.ascontiguousarray(mem.astype(np.int64))

    def local_extremes(self, cen, q):
        sc, sa, sm = self._sup
        C = self.blk_max.shape[1]
        lmax, lmin = np.empty((len(q), C)), np.empty((len(q), C))
        # writeable copies: one compiled signature (the cached geometry is read-only)
        numba_loops.cone_extremes(np.array(cen, dtype=np.float64), np.array(q, dtype=np.float64), np.array(self.cen),
                                  float(self.alpha), self.blk_max, self.blk_min, sc, sa, sm, lmax, lmin)
        return lmax, lmin


class CompiledSparseGather(SparseGather):
    """The sparse gather by :func:`~ibl_ref.groundtruth.kernels.numba_loops.tile_gather` (float64; its rounding,
    :func:`~ibl_ref.groundtruth.kernels.rounding.weight_error` and γ_m, replaces the float32 kernel's in the bound).

    Tiles, caps, attempts and the bound are the route's, except that the first attempt leaves out the bright texels
    whose weight from every row of the tile is below δ0 (and sets gathered weights below δ0 to 0): an absolute error
    ≤ δ0 per (row, texel) pair that the bound charges like the rounding allowance (δ0 from :data:`BRIGHT_CUT_SHARE`;
    every later attempt, and every tile whose bound then misses, uses e^-700).  ``threads`` > 1: the tiles are
    gathered by that many threads (the loop releases the GIL; every tile's sums are computed by one thread exactly as
    in a serial call, so the result is bit-for-bit the same for every thread count)."""

    tile_overhead = TILE_OVERHEAD
    cand_overhead = CAND_OVERHEAD
    label = "compiled"

    def __init__(self, src_dirs, omega, rad, bright, m, kernel="auto", threads=1):
        if kernel == "float32":
            raise IBLError("kernel='float32' is the NumPy path's kernel; the compiled gather is float64 "
                           "(kernel='auto')")
        super().__init__(src_dirs, omega, rad, bright, m, "float64", threads)

    def _init_arrays(self):
        """The weight rows ``[L·Ω, Ω]`` in groups of ≤ 3 channels plus Ω, padded to 4 rows (zero for the bright
        texels): ``groups = [(rows (4, M), (output columns, input columns)), …]``, the bright texels' rows
        (nb, 4·groups), their directions and groups.  (The products L·Ω are those of the NumPy path's ``[L, 1]·Ω``.)"""
        rad, omega, bright = self.rad, self.omega, self.bright
        M, C = rad.shape
        self.groups = []
        for g0 in range(0, max(C, 1), 3):
            ch = list(range(g0, min(g0 + 3, C))) + [C]
            rws = np.zeros((4, M))
            for j, c in enumerate(ch):
                if c < C:
                    np.multiply(rad[:, c], omega, out=rws[j])
                else:
                    rws[j] = omega
            rws[:, bright] = 0.0
            self.groups.append((rws, (ch, slice(4 * len(self.groups), 4 * len(self.groups) + 4))))
        self.bright_rw = np.zeros((len(bright), 4 * len(self.groups)))
        for gi, (_rws, (ch, _sl)) in enumerate(self.groups):
            for j, c in enumerate(ch):
                self.bright_rw[:, 4 * gi + j] = rad[bright, c] * omega[bright] if c < C else omega[bright]
        self.bdirs = np.ascontiguousarray(self.src_dirs[bright])
        self.bgroups = bright_groups(self.bdirs)
        self.l_und = float(rad.max()) if rad.size else 0.0

    @functools.cached_property
    def sources(self) -> CompiledSources:
        return CompiledSources(self.src_dirs, self.rad, self.is_bright, self.m)

    def bright_cut(self, s, rho, l_ref, tau, single) -> float:
        """log δ0 (class docstring): it keeps the left-out weights ≤ :data:`BRIGHT_CUT_SHARE`·τ for a texel as bright
        as the mean radiance ``l_ref`` even if every source texel were a pair (−700 with one cap: no second
        attempt)."""
        own0 = s * math.log(max(math.cos(min(rho, np.pi / 2)), 1e-300))
        if own0 < -600.0 or l_ref <= 0.0 or single:
            return -700.0
        M = self.src_dirs.shape[0]
        l_all = float(self.rad.max())
        return max(math.log(BRIGHT_CUT_SHARE * tau * l_ref / ((l_all + l_ref) * M * self.omega_ratio)) + own0, -700.0)

    def tile_costs(self, s, th, log_d0):
        # the bright texels within reach of a tile: beyond acos(δ0^(1/s)) + its cap they are left out
        a_b = math.acos(math.exp(log_d0 / s)) + th
        return self.bright.size * (1.0 - math.cos(min(a_b, np.pi))) / 2.0, self.tile_overhead, self.cand_overhead

    def prepare(self, s, th, th_far, t_rad, rho, tau, own_log) -> float:
        """c^s by binary powering for integer exponents (own weight ≥ e^-600: no reference needed), else
        exp(s·log c), relative to the row's largest cosine where the own weight may underflow."""
        self.s, self.own_log, self.gathered = s, own_log, 0
        self.rowmax = own_log < -600.0
        self.s_int = int(s) if (float(s).is_integer() and s <= POWI_MAX and own_log >= -600.0) else 0
        self.eta_w, self.eps_w = weight_error(s, bool(self.s_int), self.rowmax)
        return 0.0

    def gather(self, todo, att, log_cut, CEN, TD, q_t, a_max):
        C = self.rad.shape[1]
        B = TD.shape[1]
        X, Y, Z = _direction_columns(self.m)
        acc = np.empty((todo.size, B, C + 1))
        for rws, cols in self.groups:
            acc_g = np.empty((todo.size, B, 4))
            lm_g = np.empty((todo.size, B))
            cnt = np.empty(todo.size, dtype=np.int64)
            pairs = np.empty(todo.size, dtype=np.int64)
            _tile_gather_threads(self.threads, CEN[todo], TD[todo], q_t[todo], a_max[todo],
                                 envmap.face_frames("openexr"), self.m, X, Y, Z, rws, self.bdirs,
                                 np.ascontiguousarray(self.bright_rw[:, cols[1]]), *self.bgroups, float(self.s),
                                 self.s_int, self.rowmax, math.exp(log_cut / self.s), acc_g, lm_g, cnt, pairs)
            acc[..., cols[0]] = acc_g[..., : len(cols[0])]
        m_t = cnt.astype(np.float64)
        eta = self.eta_w + sum_error(cnt)
        # absolute errors of the smallest weights and of the weights left out below e^-700 (per pair ≤ eps_w,
        # relative to the weight scale 1: the row maximum or c^s with c ≤ 1) and, in attempt 0, of those left out or
        # set to 0 below δ0 (≤ δ0 more per pair), against W_in ≥ the own texel's weight · Ω_min
        eps_pair = self.eps_w + (math.exp(log_cut) if log_cut > -700.0 else 0.0)
        und = m_t * eps_pair * math.exp(-(0.0 if self.rowmax else self.own_log)) * self.omega_ratio
        self.gathered += int(pairs.sum()) * B  # (the pairs computed: the bright texels left out are not)
        return acc, lm_g, eta, und, self.l_und

    def bounds(self, sums, tt, ANG, q_t, q_far, half_margin, grid, log_wb_grid, lmax2, lmin2, l_max_out, l_min_out,
               VALID, IDX, maps, bounds):
        """The same formula in one compiled pass; the allowance ``und`` is relative to the largest radiance."""
        acc, log_mx, eta, und, l_und = sums
        worst = np.empty(tt.size)
        numba_loops.tile_bounds(acc, log_mx, np.broadcast_to(eta, tt.shape).astype(np.float64),
                                np.broadcast_to(und, tt.shape).astype(np.float64), l_und, ANG[tt], q_t[tt], q_far[tt],
                                half_margin, grid, log_wb_grid, np.ascontiguousarray(lmax2[tt]),
                                np.ascontiguousarray(lmin2[tt]), np.asarray(l_max_out, dtype=np.float64),
                                np.asarray(l_min_out, dtype=np.float64), VALID[tt], IDX[tt], maps, bounds, worst)
        return worst


def _tile_gather_threads(threads, cen, rows, *args):
    """:func:`~ibl_ref.groundtruth.kernels.numba_loops.tile_gather` on ``threads`` threads: the tiles in runs of
    consecutive ones (views of the inputs and outputs: nothing copied), which each thread takes in turn as it becomes
    free (tiles differ in work, e.g. near the bright texels).  Every tile is computed by the same code on the same
    inputs as in one call: the result does not depend on ``threads`` or on which thread took a run."""
    caps, arad, shared, outs = args[0], args[1], args[2:-4], args[-4:]
    nt = cen.shape[0]
    # (a few tiles, e.g. a later attempt's: starting a thread costs more than their gather)
    threads = max(1, min(int(threads), nt // TILES_PER_THREAD_MIN))
    run_len = nt if threads == 1 else max(2 * TILES_PER_THREAD_MIN, -(-nt // (8 * threads)))  # ≈ 8 runs per thread

    def run(_k, a, b):
        numba_loops.tile_gather(cen[a:b], rows[a:b], caps[a:b], arad[a:b], *shared, *(o[a:b] for o in outs))

    _in_threads(run, nt, run_len, threads, "ibl_tiles")


def _in_threads(run, n, run_len, threads, name):
    """``run(k, a, b)`` for the consecutive runs ``[a, b)`` of ``range(n)`` (k the run's index) on ``threads`` threads,
    this one included, each taking the next run as it becomes free; the first exception is re-raised here."""
    if n <= 0:
        return
    runs = iter(enumerate(range(0, n, run_len)))
    lock = threading.Lock()
    errors = []

    def work():
        try:
            while True:
                with lock:
                    item = None if errors else next(runs, None)
                if item is None:
                    return
                k, a = item
                run(k, a, min(a + run_len, n))
        except BaseException as exc:  # re-raised on the calling thread
            with lock:
                errors.append(exc)

    others = [threading.Thread(target=work, name=f"{name}_{j}", daemon=True) for j in range(1, threads)]
    for th in others:  # the other threads …
        th.start()
    work()  # … and this one
    for th in others:
        th.join()
    if errors:
        raise errors[0]


# ----------------------------------------------------------------------------------------------------------------
# moment route and SH route
# ----------------------------------------------------------------------------------------------------------------
def _csr(tiles, items, T):
    """``(starts (T+1,), items sorted by tile)``: the (tile, item) pairs grouped per tile (stable order)."""
    order = np.argsort(tiles, kind="stable")
    counts = np.bincount(tiles, minlength=T)
    return np.concatenate([[0], np.cumsum(counts)]).astype(np.int64), np.ascontiguousarray(items[order], dtype=np.int64)


def _pad4(x, Q):
    """The last axis (Q ≤ 4 channels, the last one L ≡ 1) padded with zeros to 4."""
    if Q == 4:
        return np.ascontiguousarray(x)
    out = np.zeros(x.shape[:-1] + (4,))
    out[..., :Q] = x
    return out


class _Band4(tuple):
    """Band sources or bracket moments padded to 4 channels (Q ≤ 4): what the compiled band loops take."""


@functools.lru_cache(maxsize=16)
def _class_destinations(L):
    """Row destinations that make the rows of every octant class contiguous (even classes κ = 0..3, then odd
    4..7): ``(dest (2, rows), [(start, stop) per κ])`` for :func:`~ibl_ref.groundtruth.kernels.numba_loops.sh_matrix`."""
    cls = sh_basis._octant_row_classes(L)
    n_e, n_o = (r.size for r in _row_layout(L))
    dest = np.zeros((2, max(n_e, n_o)), dtype=np.int64)
    spans, pos = [], 0
    for par in range(2):
        for c in cls[par]:
            dest[par, c] = pos + np.arange(c.size)
            spans.append((pos, pos + c.size))
            pos += c.size
    return dest, tuple(spans)


def _octant_Y_chunks(reps, L):
    """The SH matrix chunks of :func:`ibl_ref.groundtruth.sh_basis._octant_Y_chunks`, generated by
    :func:`~ibl_ref.groundtruth.kernels.numba_loops.sh_matrix` straight into class-contiguous rows (views, no
    copies), in chunks of ≈ 16 MB."""
    tabs = compiled_tables(L)
    dest, spans = _class_destinations(L)
    rows = (L + 1) ** 2
    ch = max(SH_BLOCK, (SH_CHUNK_ELEMS // rows) // SH_BLOCK * SH_BLOCK)
    for i0 in range(0, reps.shape[0], ch):
        i1 = min(reps.shape[0], i0 + ch)
        Y = np.empty((rows, i1 - i0))
        numba_loops.sh_matrix(np.ascontiguousarray(reps[i0:i1]), L, *tabs, dest, Y)
        yield i0, i1, [Y[a:b] for a, b in spans]


# ----------------------------------------------------------------------------------------------------------------
# GGX tree route
# ----------------------------------------------------------------------------------------------------------------
class _FlatTree:
    """The levels of a :class:`~ibl_ref.groundtruth.ggx_convolution.GGXSourceTree` as the flat, contiguous arrays
    :func:`~ibl_ref.groundtruth.kernels.numba_loops.ggx_tree` takes (levels ≥ 1 stacked, ``off[ℓ]`` their first
    rows; the texels apart)."""

    def __init__(self, levels):
        nodes = levels[1:]
        counts = [lv.c.shape[0] for lv in nodes]
        self.off = np.concatenate([[0, 0], np.cumsum(counts)[:-1]]).astype(np.int64)
        self.grid_m = np.array([levels[0].m] + [lv.m for lv in nodes], dtype=np.int64)
        self.top = len(levels) - 1

        def cat(name):
            return np.ascontiguousarray(np.concatenate([getattr(lv, name) for lv in nodes]))

        self.nodes = (cat("c"), cat("cos_psi"), cat("sin_psi"), cat("valid"), cat("M0"), cat("U"), cat("V"),
                      cat("trV"))
        t = levels[0]
        self.texels = (np.ascontiguousarray(t.c), np.ascontiguousarray(t.M0), np.ascontiguousarray(t.valid))


def _ggx_tree_threads(threads, tiles, target, num, err, pairs, shared):
    """:func:`~ibl_ref.groundtruth.kernels.numba_loops.ggx_tree` on ``threads`` threads, runs of consecutive tiles
    taken in turn (each tile computed by one call as in a serial run: the result does not depend on ``threads``)."""
    nt = tiles.size
    threads = max(1, min(int(threads), nt // GGX_TILES_PER_RUN))
    run_len = nt if threads == 1 else max(GGX_TILES_PER_RUN, -(-nt // (8 * threads)))
    counts = np.zeros((-(-nt // max(run_len, 1)), pairs.size), np.int64)

    def run(k, a, b):
        numba_loops.ggx_tree(tiles[a:b], *shared[:3], target[a:b], *shared[3:], num[a:b], err[a:b], counts[k])

    _in_threads(run, nt, run_len, threads, "ibl_ggx")
    pairs += counts.sum(axis=0)


#: tiles per run of a thread of the GGX tree (a run is ≥ a few ms of work)
GGX_TILES_PER_RUN = 8


# ----------------------------------------------------------------------------------------------------------------
# the backend
# ----------------------------------------------------------------------------------------------------------------
class CompiledKernels(NumpyKernels):
    """The compiled implementation of :class:`ibl_ref.groundtruth.kernels.Kernels` (module docstring)."""

    name = "compiled"
    gather_threads = True

    def __init__(self):
        self._warm = set()
        self._lock = threading.Lock()

    def moment_chunk_pairs(self, Q):
        # no NumPy temporaries of the band to amortise: smaller chunks, less memory (4 MB of pairs)
        return 1 << 19 if Q <= 4 else super().moment_chunk_pairs(Q)

    def sparse_gather(self, src_dirs, omega, rad, bright, m, kernel="auto", threads=1) -> CompiledSparseGather:
        return CompiledSparseGather(src_dirs, omega, rad, bright, m, kernel, threads)

    def band_sources(self, bdT, bw_pad):
        Q = bw_pad.shape[1]
        if Q > 4:
            return super().band_sources(bdT, bw_pad)
        return _Band4((np.ascontiguousarray(bdT.T), _pad4(bw_pad, Q)))

    def band_exact(self, Rc, tiles, blk, src, s_list, num, chunk_elems):
        if not isinstance(src, _Band4):
            return super().band_exact(Rc, tiles, blk, src, s_list, num, chunk_elems)
        D, W4 = src
        T, B = Rc.shape[0], Rc.shape[1]
        Q = next(iter(num.values())).shape[-1]
        starts, items = _csr(tiles, np.where(blk < 0, D.shape[0] - 1, blk), T)
        n1, n2 = np.zeros((T, B, 4)), np.zeros((T, B, 4))
        numba_loops.band_exact(np.ascontiguousarray(Rc), starts, items, D, W4, 1.0 in s_list, 2.0 in s_list, n1, n2)
        for s, acc in ((1.0, n1), (2.0, n2)):
            if s in num:
                num[s] += acc[..., :Q]

    def brackets_prep(self, cb_leaf, ab_leaf, M0, M1, M2):
        Q = M0.shape[1]
        if Q > 4:
            return super().brackets_prep(cb_leaf, ab_leaf, M0, M1, M2)
        if ab_leaf.size and float(ab_leaf.max()) >= 0.25 * math.pi:
            raise IBLError("leaf blocks too large for the bracket band (cone half-angle ≥ π/4); use a smaller leaf")
        nbk = M0.shape[0]
        m1 = _pad4(M1.reshape(nbk, 3, Q), Q)
        m2 = _pad4(M2.reshape(nbk, 6, Q), Q) if M2 is not None else np.zeros((nbk, 6, 4))
        return _Band4((np.ascontiguousarray(cb_leaf), np.cos(ab_leaf), np.sin(ab_leaf), _pad4(M0, Q), m1, m2, Q))

    def band_brackets(self, Rc, tiles, blk, prep, s_list, num, err, chunk_elems):
        if not isinstance(prep, _Band4):
            return super().band_brackets(Rc, tiles, blk, prep, s_list, num, err, chunk_elems)
        T, B = Rc.shape[0], Rc.shape[1]
        Q = prep[-1]
        starts, items = _csr(tiles, blk, T)
        acc = [np.zeros((T, B, 4)) for _ in range(4)]
        numba_loops.band_brackets(np.ascontiguousarray(Rc), starts, items, *prep[:-1], 1.0 in s_list, 2.0 in s_list,
                                  *acc)
        for s, (nn, ee) in ((1.0, acc[:2]), (2.0, acc[2:])):
            if s in num:
                num[s] += nn[..., :Q]
                err[s] += ee[..., :Q]

    def sh_shared_chunks(self, dirs, sym):
        return None  # the SH values are generated where they are used

    def sh_project_octant(self, dirs, W, L, orb, chunks=None):
        ev_l, od_l = _row_layout(L)
        Q = W.shape[1]
        Wk = (sh_basis._walsh8() @ W[orb].transpose(1, 2, 0).reshape(8, -1)).reshape(8, Q, -1)  # (8, Q, n_oct)
        reps = np.ascontiguousarray(dirs[orb[:, 0]])
        ae, ao = np.zeros((ev_l.size, Q)), np.zeros((od_l.size, Q))
        tabs = compiled_tables(L)
        for q0 in range(0, Q, 4):
            q1 = min(Q, q0 + 4)
            W4 = np.zeros((8, 4, reps.shape[0]))
            W4[:, : q1 - q0] = Wk[:, q0:q1]
            acc_e, acc_o = np.zeros((ev_l.size, 4)), np.zeros((max(od_l.size, 1), 4))
            numba_loops.sh_project(reps, W4, L, *tabs, acc_e, acc_o)
            ae[:, q0:q1] = acc_e[:, : q1 - q0]
            ao[:, q0:q1] = acc_o[: od_l.size, : q1 - q0]
        return ae, ao

    def sh_octant_values(self, dirs, Be, Bo, L, orb, chunks=None):
        return sh_basis._evaluate_octant_values(dirs, Be, Bo, L, orb, _octant_Y_chunks(dirs[orb[:, 0]], L),
                                                blas_combine=True)

    def bright_gather(self, out_dirs, b_dirs, b_w, s_list):
        P, K, C = out_dirs.shape[0], len(s_list), b_w.shape[1]
        res = np.zeros((K, P, C))
        nb = b_dirs.shape[0]
        if nb == 0:
            return res
        s_int = np.array([int(s) if float(s).is_integer() and s <= POWI_MAX else 0 for s in s_list], dtype=np.int64)
        for c0 in range(0, C, 4):
            c1 = min(C, c0 + 4)
            bw4 = np.zeros((nb, 4))
            bw4[:, : c1 - c0] = b_w[:, c0:c1]
            acc = np.zeros((K, 4, P))
            numba_loops.point_gather(np.ascontiguousarray(out_dirs), np.ascontiguousarray(b_dirs), bw4,
                                     np.array(s_list, dtype=np.float64), s_int, acc)
            res[:, :, c0:c1] = acc[:, : c1 - c0].transpose(0, 2, 1)
        return res

    def bright_gather_error(self, nb, b_w, s_list):
        """Rounding of :meth:`bright_gather`: relative η for r·ω ≥ C0, absolute ε per weight below
        (:func:`~ibl_ref.groundtruth.kernels.rounding.weight_error`)."""
        if not b_w.shape[0]:
            return None
        bw = np.abs(b_w).sum(axis=0)
        out = np.empty_like(nb)
        for k, s in enumerate(s_list):
            e_r, e_a = weight_error(s, float(s).is_integer() and s <= POWI_MAX)
            out[k] = e_r * nb[k] + e_a * bw
        return out

    def ggx_tree_pass(self, tree, kern, R, cT, betaT, sel, target, beta_share, hshare, split_gain=1.0, threads=1):
        """``(num, err, pairs)`` of the GGX tree route for the output tiles ``sel`` by
        :func:`~ibl_ref.groundtruth.kernels.numba_loops.ggx_tree` (the refinement of the NumPy loops, per tile), the
        tiles shared between ``threads`` threads."""
        flat = tree.flat(_FlatTree)
        t2, Q = R.shape[1], flat.texels[1].shape[1]
        sel = np.ascontiguousarray(sel, dtype=np.int64)
        num = np.zeros((sel.size, t2, Q))
        err = np.zeros((sel.size, t2, Q))
        pairs = np.zeros(flat.top + 1, np.int64)
        shared = (np.ascontiguousarray(R), np.ascontiguousarray(cT), np.ascontiguousarray(betaT), float(beta_share),
                  float(hshare), float(split_gain), kern.a, kern.b,
                  flat.off, flat.grid_m, flat.top, *flat.nodes, *flat.texels)
        _ggx_tree_threads(threads, sel, np.ascontiguousarray(target, dtype=np.float64), num, err, pairs, shared)
        return num, err, pairs

    # ------------------------------------------------------------------------------------------------------------
    # compiling and loading
    # ------------------------------------------------------------------------------------------------------------
    def loaded(self) -> bool:
        return bool(self._warm)

    def warm_up(self, stages=STAGES) -> float:
        """Compile (or load from numba's cache) the loops of ``stages`` on tiny inputs, once per process, guarding
        against damaged cache entries (module docstring); returns the seconds it took."""
        t0 = time.perf_counter()
        with self._lock:
            todo = [st for st in STAGES if st in stages and st not in self._warm]
            if todo:
                _warm_up_guarded(todo)
                self._warm.update(todo)
        return time.perf_counter() - t0


def _exercise(stages):
    """Run the loops of ``stages`` once on tiny inputs (every signature the backend calls them with)."""
    n = 2
    d = envmap.texel_directions(n).reshape(-1, 3)
    cube = np.ones((6, n, n, 1))
    if "sparse" in stages:
        om = envmap.cube_solid_angles(n).reshape(-1)
        for bright, s in ((np.array([0]), 2.0), (np.zeros(0, dtype=np.intp), 2.5)):
            g = CompiledSparseGather(d, om, cube.reshape(-1, 1), bright, n)
            for own_log in (0.0, -700.0):  # c^s, then exp(s·log c) relative to the row maximum
                g.prepare(s, 0.5, 0.5, 0.1, 0.6, 1e-3, own_log)
                cen, tiles = d[:2].copy(), np.arange(2)
                sums = g.gather(tiles, 0, -700.0, cen, d[:2].reshape(2, 1, 3).copy(), np.full(2, 0.5), np.zeros(2))
                g.bounds(sums, tiles, np.zeros((2, 1)), np.ones(2), np.ones(2), 5e-8, np.array([0.0, 1.0]),
                         np.array([0.0, -1.0]), *g.local_extremes(cen, np.full(2, 0.5)), np.ones(1), np.ones(1),
                         np.ones((2, 1), dtype=bool), np.zeros((2, 1), dtype=np.intp), np.zeros((2, 1)),
                         np.zeros((2, 1)))
            numba_loops.cap_count(d[0].copy(), 0.5, np.ascontiguousarray(envmap.face_frames("openexr")), n)
    if "moment" in stages:
        k = CompiledKernels()
        R, tiles, blk = d[:2].reshape(2, 1, 3).copy(), np.array([0, 1]), np.array([0, 1])
        num = {1.0: np.zeros((2, 1, 2)), 2.0: np.zeros((2, 1, 2))}
        k.band_exact(R, tiles, blk, k.band_sources(d.T.copy(), np.ones((d.shape[0], 2))), [1.0, 2.0], num, 1)
        prep = k.brackets_prep(d.copy(), np.full(d.shape[0], 0.1), np.ones((d.shape[0], 2)),
                               np.ones((d.shape[0], 6)), np.ones((d.shape[0], 12)))
        k.band_brackets(R, tiles, blk, prep, [1.0, 2.0], num, {1.0: num[1.0] * 0, 2.0: num[2.0] * 0}, 1)
    if "sh" in stages:
        k = CompiledKernels()
        sym = sh_basis.SymmetryPlan(d, 2, 1)
        ae, ao = k.sh_project_octant(d, np.ones((d.shape[0], 2)), 2, sym.orb)
        k.sh_octant_values(d, ae, ao, 2, sym.orb)
        k.bright_gather(d, d[:2].copy(), np.ones((2, 2)), [2.0, 2.5])
    if "ggx" in stages:
        tree = GGXSourceTree(cube)
        R = d.reshape(-1, 1, 3).copy()
        CompiledKernels().ggx_tree_pass(tree, GGXLobeKernel(0.5), R, d.copy(), np.zeros(d.shape[0]),
                                        np.arange(d.shape[0]), np.full(d.shape[0], 1e-3), 0.0, 0.1, 0.875)


def _warm_up_guarded(stages):
    """:func:`_exercise` ``stages`` with numba's cache entries checked first (:func:`_check_cache`), an entry that fails
    to load removed and compiled again, and no cache at all where it cannot be written; each with one line."""
    folder = _cache_folder()
    given = os.environ.get("NUMBA_CACHE_DIR", "").strip()
    if folder is not None and given and Path(given).resolve() not in folder.resolve().parents and not _NOTED:
        _NOTED.append(given)  # (numba passes over a folder it cannot write: say where the cache went, once)
        _note(f"NUMBA_CACHE_DIR={given} cannot be written; numba keeps the kernels' cache in {folder}")
    if folder is not None and numba_loops.CACHE:
        _check_cache(folder, stages)
    try:
        _exercise(stages)
    except IBLError:
        raise
    except Exception as exc:  # noqa: BLE001 - a cache entry numba cannot read, or a cache it cannot write
        if folder is None or not numba_loops.CACHE:
            raise IBLError(f"the compiled kernels could not be built ({type(exc).__name__}: {exc}); "
                           "use kernel 'numpy'") from None
        removed = _remove_entries(folder)
        try:
            _note(f"numba's cache of the kernels in {folder} failed ({type(exc).__name__}: {exc}); removed "
                  f"{removed} entries, compiling again")
            _exercise(stages)
        except Exception as exc2:  # noqa: BLE001 - the cache cannot be written (full disk, read-only folder)
            _note(f"numba's cache in {folder} cannot be written ({type(exc2).__name__}: {exc2}); the kernels are "
                  "compiled without it in this process")
            os.environ["IBL_REF_NUMBA_CACHE"] = "0"
            importlib.reload(numba_loops)
            _exercise(stages)
    if folder is not None and numba_loops.CACHE:
        _record(folder)


#: the notes printed once per process
_NOTED: list = []


def _note(msg: str) -> None:
    print(f"ibl_ref: {msg}", file=sys.stderr)


def _cache_folder() -> Path | None:
    """The folder of numba's cache entries of the loops (None: no cache)."""
    if not numba_loops.CACHE:
        return None
    try:
        return Path(numba_loops.tile_gather.stats.cache_path)
    except (AttributeError, TypeError):  # (a numba without the attribute: no guard, numba's own behaviour)
        return None


def _entries(folder: Path) -> dict:
    """``{file name: [size, CRC-32]}`` of the loops' cache entries in ``folder``."""
    out = {}
    for p in sorted(folder.glob("numba_loops.*.nb[ic]")):
        try:
            data = p.read_bytes()
        except OSError:
            continue
        out[p.name] = [len(data), zlib.crc32(data)]
    return out


def _remove_entries(folder: Path) -> int:
    n = 0
    for p in list(folder.glob("numba_loops.*.nb[ic]")) + [folder / MANIFEST]:
        try:
            p.unlink()
            n += p.suffix != ".json"
        except OSError:
            pass
    return n


def _record(folder: Path) -> None:
    """Write the record of the entries (atomically; skipped where nothing changed or the folder is read-only)."""
    entries = _entries(folder)
    path = folder / MANIFEST
    try:
        if path.is_file() and json.loads(path.read_text()) == entries:
            return
        with atomic_write(path) as fh:
            json.dump(entries, fh, sort_keys=True)
    except (OSError, ValueError, IBLError):
        pass


def _check_cache(folder: Path, stages) -> None:
    """Where the loops' cache entries differ from their record (new, changed or damaged), load them in a child
    process first (a damaged entry can kill the process that loads it): they are recorded if that works, else
    removed (one line on stderr)."""
    entries = _entries(folder)
    try:
        record = json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError):
        record = {}
    if all(record.get(k) == v for k, v in entries.items()):
        return
    code = f"from ibl_ref.groundtruth.kernels import numba_backend as b; b._exercise({list(stages)!r})"
    try:
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=600)
    except (OSError, subprocess.SubprocessError) as exc:
        why = f"the check could not run ({exc})"
    else:
        if r.returncode == 0:
            _record(folder)
            return
        last = (r.stderr.decode(errors="replace").strip().splitlines() or ["no message"])[-1]
        why = f"loading them failed in a child process (exit {r.returncode}: {last[:200]})"
    _note(f"numba's cache of the kernels in {folder} is damaged ({why}); removed {_remove_entries(folder)} "
          "entries, compiling again")
