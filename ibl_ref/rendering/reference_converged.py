"""The converged reference of Knuth et al. (2014) Eq. 4–5: visibility-weighted Phong lobe averages to a tolerance.

Per surface point x (shading normal n, face normal n_f) and lobe axis d (n for the diffuse term, r for the glossy
one, ``s = 1/(1−g)``, Eq. 3), :mod:`ibl_ref.rendering.reference_render` defines the exact value::

    A_s = ∫ L(ω) V(x, ω) max(d·ω, 0)^s [n·ω > 0] dω  /  ∫ max(d·ω, 0)^s dω                                (*)

(the lobe average of Eq. 4 with exact visibility V; docs/background.md §8 for the conventions: the hemisphere
Ω⁺ of n clips the numerator only, as the normalised Phong BRDF of Kán et al. 2015, Eq. 2).  L is the map's
piecewise-constant radiance (each texel constant over its exact solid angle).  :func:`converged_shading`
computes (*) to a requested estimated relative L1 error ``rtol`` of the image (and, per pixel, to ``pixel_rtol``
where the visibility limits it), with two discretisations:

**Quadrature** (radiance × lobe).  The integrand without V is summed at the texel centres of a face size M
(a power-of-two multiple of the visibility base level and of the map's N, ≥ 4 texels across the lobe's half
width): ``w_q = L_q max(d·ω_q,0)^s [n·ω_q>0] Ω_q`` (the midpoint rule inside the map's texels; the normalisation
Σ_q max(d·ω_q,0)^s Ω_q is the same sum over the whole sphere, so L ≡ 1 without occluders gives exactly the share
of the lobe above the horizon).  Estimate per pixel: |Σ_c V̄_c (W_c(M) − W_c(M/2))| over the base cells c with
their visible fractions V̄_c — the change from M/2 to M of the visibility-weighted average (for a smooth lobe the
error of M is ≈ ⅓ of it; where the horizon or a cell edge cuts the lobe, about it).  M doubles (the cells and
their rays stay) while this change, with the base cells' rays, exceeds :data:`QUAD_SHARE` of rtol for the block
or of ``pixel_rtol`` for more than :data:`QUAD_PIXEL_SHARE` of its pixels (up to ``n_quad_max``).

**Visibility** (stratified, adaptive).  The sphere is cut into cells: the six faces at a base size n_b
(≥ ``n_vis_start`` and ≥ 2 cells across the lobe's half width), each cell splittable 2×2 down to face size
``n_vis_max``.  A cell c carries the exact quadrature weight W_c = Σ_{q∈c} w_q (cells finer than M split their
parent's weight in proportion to max(d·ω,0)^s [n·ω>0] Ω at their centres) and ONE shadow ray toward a random
point of the cell (drawn uniformly in the cell, or in proportion to the map's energy L·Ω where the cell spans
several map texels, so that a sun inside a coarse cell is aimed at).  The pixel's value is Σ_c W_c V_c / Σ w.
A cell whose ray differs from the ray of a neighbouring cell (the 8 cells around it at its own level, across
face borders; a shadow edge passes near it) is an *edge* cell: its visible fraction q_c is unknown, its ray is
an unbiased one-sample estimate of it, with error e_c = W_c (V_c − q_c), |e_c| ≤ W_c and variance
W_c² q_c (1 − q_c) ≤ W_c²/4 (q_c measured with the density the point is drawn from, not with the lobe's weight
inside the cell: a second-order difference that shrinks as edge cells are split).  The errors of different cells
are independent (independent points), so per pixel, taking the final cells as given (weights relative to Σ w,
channel means)

    E|e| ≤ √(Σ_edge W_c² q_c(1 − q_c)) ≤ σ = ½ √(Σ_edge W_c²)      (Jensen)
    P(|e| > t σ) ≤ 2 exp(−t²/2)                                      (Hoeffding: e_c lies in an interval of length W_c)

Cells that agree with all neighbours are taken as fully lit / fully shadowed: a feature thinner than the cells
between two agreeing rays is missed, which the model does not count (hence the base level's ≥ 2 cells per lobe
half width and ``n_vis_start``; the tests measure it against finer runs).

**Refinement** (where weight × possible change is largest).  Each round splits the edge cells with the largest
weights: for the image, the fewest whose split is predicted (a split cell's W² shrinks ≈ 8×: four children of
W/4, about half of them edges) to bring the block's Σ E|e| below rtol·ΣA minus the quadrature estimate; for every
pixel whose bound (below) exceeds ``pixel_rtol`` × max(A, :data:`ERR_FLOOR` × mean A), its largest edge cells until
its predicted bound fits (not where the quadrature estimate alone exceeds it: that is M's job).  The child that
holds its parent's point keeps the parent's ray (it is a uniform point of the child too); the others get their
own.  New children are compared with their siblings and with the 12 cells around their 2×2 block (a neighbour
that differs from a child becomes an edge too; edge flags of older cells only grow).  The estimate falls from
round to round (up to the re-measured κ̂ below), and the loop stops when both targets are met or no wanted edge
cell can be split any more (the finest level ``n_vis_max``).  ``converged`` says whether the image target was met;
the per-pixel target is best effort (its outcome is ``err_rel_p99``).

**Reported error.**  Per pixel: ``err_mean`` = √(κ̂ Σ_edge W_c²/4) + quadrature estimate, the estimate of E|e| used
for the image's rel. L1 ``err_rel_l1`` = Σ err_mean / Σ A.  κ̂ ≤ 1 is the share of the worst-case variance the edge
cells actually carry, measured in the block on the cells split so far (each split gives an estimate of its
q(1−q) from its four children, biased high: q̂(1−q̂)·n/(n−1) of stratified points); 1 until
:data:`KAPPA_MIN_SPLITS` cells were split.  ``err_bound`` = min(Σ_edge W_c, t σ) + quadrature estimate with the
worst case σ and t = √(2 ln(2/δ)), δ = :data:`BOUND_DELTA`: a per-pixel bound that holds with probability ≥ 1 − δ,
so its 99th percentile bounds the actual error's up to a δ share of the pixels.  ``tests/test_reference_render.py``
checks both against closed forms, brute force and much finer runs.

**Blocks and determinism.**  Pixels are dealt to blocks round-robin (block b holds pixels b, b + B, b + 2B, …, so
every block is a sample of the whole image and meets the image's tolerance on its own); blocks run independently
(:func:`ibl_ref.executors.map_jobs`: serially, on local processes or any executor) and each block's random points
come from a counter-based hash of (seed, block, cell), so the image is bit-identical wherever the blocks ran.
Memory is O(block pixels × cells), never (all pixels × all cells); the refined cells are kept as leaves of a
quadtree per pixel, sorted by Morton key for the neighbour look-ups.

Shadow rays: :class:`ibl_ref.rendering.raycast.ShadowRays` (Embree with a float64 check of every hit when
``embreex`` is installed, the package's float64 casters otherwise).
"""

from __future__ import annotations

import time

import numpy as np

from ..conventions import lobe_half_angle
from ..errors import IBLError

__all__ = ["converged_shading", "DEFAULT_RTOL", "LOBE_TAIL_CUT", "BOUND_DELTA", "base_level", "quadrature_start"]

#: default tolerance of :func:`ibl_ref.rendering.reference_render.render_reference` (relative L1 of the image,
#: estimated)
DEFAULT_RTOL = 2e-3
#: lobe support of the quadrature: max(d·ω,0)^s below this (relative to the peak 1) is dropped (from the numerator
#: and the normalisation alike; the dropped share is < 4π·1e-8/(2π/(s+1)) ≪ 1e-6 for s ≤ 100)
LOBE_TAIL_CUT = 1e-8
#: per-pixel failure probability of ``err_bound`` (Hoeffding): t = √(2 ln(2/δ)) ≈ 3.9
BOUND_DELTA = 1e-3
#: a split cell's Σ W² is predicted to shrink by this factor (4 children of W/4, about half of them edges)
SPLIT_GAIN = 1.0 / 8.0
#: a round aims at this fraction of the visibility budget (fewer rounds, a little more refinement)
ROUND_AIM = 0.7
MAX_ROUNDS = 80
#: share of rtol (and of pixel_rtol) the quadrature may take: M doubles until the M/2 → M change of the average
#: (with the base cells' visibility) is below it for the image and for all but QUAD_PIXEL_SHARE of the pixels
QUAD_SHARE = 0.5
QUAD_PIXEL_SHARE = 0.01
#: elements of the (pixels, cells, texels) arrays of one quadrature step
QUAD_CHUNK_ELEMENTS = 1 << 20
#: per-pixel bound: t = √(2 ln(2/δ)) standard deviations (Hoeffding)
T_BOUND = float(np.sqrt(2.0 * np.log(2.0 / BOUND_DELTA)))
#: default ``pixel_rtol`` = this × rtol (3 % at the default rtol 2e-3)
PIXEL_RTOL_FACTOR = 15.0
#: per-pixel relative errors are relative to max(pixel value, ERR_FLOOR × the image's mean value): a pixel in deep
#: shadow is held to an absolute accuracy, not to a share of its tiny value
ERR_FLOOR = 0.1
#: κ̂ is used once this many cells were split, and never below KAPPA_FLOOR
KAPPA_MIN_SPLITS = 200
KAPPA_FLOOR = 0.1
#: κ used to plan the first split, before κ̂ can be measured (the estimate itself uses 1 until then)
KAPPA_PLAN = 0.3
_MORTON_BITS = 21  # coordinates at the finest level < 2^21 per face side
_HASH_MUL = np.uint64(0x9E3779B97F4A7C15)


# ------------------------------------------------------------------------------------------------
# levels
# ------------------------------------------------------------------------------------------------
def _pow2_multiples(N: int):
    """Face sizes N·2^k (k ∈ ℤ, N/2^k only while integral), ascending."""
    lo = [N]
    while lo[-1] % 2 == 0:
        lo.append(lo[-1] // 2)
    return sorted(lo)[:-1] + [N * 2 ** k for k in range(0, 16)]


def base_level(s: float, N: int, n_vis_start: int = 16) -> int:
    """Visibility base face size n_b = N·2^k (k ∈ ℤ): the smallest ≥ ``n_vis_start`` with ≥ 2 cells across the lobe's
    half width θ½ (cell angle (π/2)/n_b ≤ θ½/2)."""
    need = max(float(n_vis_start), np.pi / float(lobe_half_angle(s)))
    for n in _pow2_multiples(int(N)):
        if n >= need:
            return int(n)
    return int(N) * 2 ** 15


def quadrature_start(s: float, N: int, nb: int) -> int:
    """First quadrature face size M: a power-of-two multiple of max(N, n_b), ≥ 2 n_b (so M/2 nests in the cells)
    and with ≥ 4 texels across the lobe's half width ((π/2)/M ≤ θ½/4)."""
    need = max(2 * nb, 2 * np.pi / float(lobe_half_angle(s)))
    M = max(int(N), int(nb))
    while M < need:
        M *= 2
    return M


# ------------------------------------------------------------------------------------------------
# cell addressing: Morton keys, neighbours across faces, counter-based random points
# ------------------------------------------------------------------------------------------------
def _spread_table():
    t = np.arange(1 << 16, dtype=np.uint64)
    x = t
    for sh, mask in ((8, 0x00FF00FF), (4, 0x0F0F0F0F), (2, 0x33333333), (1, 0x55555555)):
        x = (x | (x << np.uint64(sh))) & np.uint64(mask)
    return x


_SPREAD16 = _spread_table()


def _spread(x):
    """Bits of x (< 2^32) moved to the even bit positions (Morton interleave), by a 16-bit table."""
    x = x.astype(np.uint64)
    return _SPREAD16[x & np.uint64(0xFFFF)] | (_SPREAD16[(x >> np.uint64(16)) & np.uint64(0xFFFF)] << np.uint64(32))


def _keys(p, f, lvl, i, j, depth):
    """Morton range start (int64) of cell (level ``lvl``, face f, row i, col j) of pixel p at the finest level."""
    sh = (depth - lvl).astype(np.uint64)
    m = (_spread(i.astype(np.uint64) << sh) << np.uint64(1)) | _spread(j.astype(np.uint64) << sh)
    return ((((p.astype(np.uint64) * np.uint64(6)) + f.astype(np.uint64)) << np.uint64(2 * _MORTON_BITS)) | m).astype(
        np.int64)


def _hash(x):
    """SplitMix64 finaliser (uint64 → uint64), vectorised."""
    with np.errstate(over="ignore"):
        x = (x + _HASH_MUL)
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return x ^ (x >> np.uint64(31))


def _uniforms(seed: int, block: int, lvl, f, i, j, k: int = 3):
    """(K, k) uniforms in [0, 1) from a hash of (seed, block, level, face, row, col) — a pure function of the cell."""
    with np.errstate(over="ignore"):
        h = _hash(np.uint64(seed & 0xFFFFFFFF) * np.uint64(0x100000001B3) + np.uint64(block & 0xFFFFFFFF))
        c = _hash(h ^ _hash(lvl.astype(np.uint64) * np.uint64(8) + f.astype(np.uint64)))
        c = _hash(c ^ (i.astype(np.uint64) << np.uint64(32)) ^ j.astype(np.uint64))
        out = np.empty((len(c), k))
        for m in range(k):
            c = _hash(c + np.uint64(m + 1))
            out[:, m] = (c >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)
    return out


#: the 8 cells around a cell (row, col offsets)
_OFFS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


def _neighbours(f, i, j, n: int):
    """The 8 cells around cells (f, i, j) of face size n (rows i ↔ v, cols j ↔ u), across face borders:
    (f, i, j) arrays of shape (K, 8)."""
    di = np.array([o[0] for o in _OFFS])
    dj = np.array([o[1] for o in _OFFS])
    I = i[:, None] + di[None, :]
    F, I, J = _neighbour_of(np.broadcast_to(f[:, None], I.shape).reshape(-1), I.reshape(-1),
                            (j[:, None] + dj[None, :]).reshape(-1), np.full(I.size, n, dtype=np.int64))
    return F.reshape(-1, 8), I.reshape(-1, 8), J.reshape(-1, 8)


def _direction_to_texel_n(d, n):
    """:func:`ibl_ref.environment.envmap.direction_to_texel` with a per-direction face size ``n`` (array)."""
    from ..environment.envmap import direction_to_face_uv

    face, u, v = direction_to_face_uv(d)
    col = np.clip(np.floor((u + 1.0) * 0.5 * n), 0, n - 1).astype(np.int64)
    row = np.clip(np.floor((v + 1.0) * 0.5 * n), 0, n - 1).astype(np.int64)
    return face.astype(np.int64), row, col


def _rect(i, j, n):
    """Face-plane rectangle (u0, u1, v0, v1) of cells (row i, col j) of face size n."""
    h = 2.0 / n
    return j * h - 1.0, (j + 1) * h - 1.0, i * h - 1.0, (i + 1) * h - 1.0


def _rect_solid_angle(u0, u1, v0, v1):
    from ..environment.envmap import _area_primitive as A

    return A(u1, v1) - A(u0, v1) - A(u1, v0) + A(u0, v0)


def _dirs(f, u, v, normalize: bool = True):
    """Directions through face-plane points (u, v) of faces f (:func:`ibl_ref.environment.envmap.face_uv_to_direction`
    without its argument checks: f, u, v are the module's own arrays)."""
    from ..environment.envmap import face_frames

    F = face_frames("openexr")[f]
    d = F[:, 0, :] + u[:, None] * F[:, 1, :] + v[:, None] * F[:, 2, :]
    return d / np.sqrt(_dot(d, d))[:, None] if normalize else d


def _dot(a, b):
    """Σ a·b over the last axis without BLAS (the same rounding in every process)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


# ------------------------------------------------------------------------------------------------
# the per-block computation
# ------------------------------------------------------------------------------------------------
class _Env:
    """The map's radiance on the levels the block needs (cell-major with respect to the base level)."""

    def __init__(self, a, nb):
        from ..environment.envmap import cube_solid_angles

        self.a = a
        self.N = a.shape[1]
        self.C = a.shape[-1]
        self.nb = nb
        om = cube_solid_angles(self.N)
        self.energy = a.mean(axis=-1).clip(min=0.0) * om  # (6, N, N): where to aim rays inside coarse cells
        self._q = {}

    def quad(self, M):
        """Cell-major arrays of level M: directions (K_b, k², 3), solid angles (K_b, k²), radiance (K_b, k², C)."""
        if M not in self._q:
            from ..environment.envmap import texel_directions, texel_solid_angles
            from .reference_render import _radiance_at

            nb, k = self.nb, M // self.nb

            def cm(x):
                t = x.reshape((6, nb, k, nb, k) + x.shape[3:])
                t = np.moveaxis(t, 3, 2)
                return np.ascontiguousarray(t.reshape((6 * nb * nb, k * k) + x.shape[3:]))

            d = cm(np.asarray(texel_directions(M)))
            o = cm(np.broadcast_to(texel_solid_angles(M), (6, M, M)))
            L = cm(_radiance_at(self.a, M))
            self._q[M] = (d, o, L)
        return self._q[M]

    def samples(self, seed, block, lvl, f, i, j, n):
        """Random points (u, v) in cells (f, i, j) of face sizes n (arrays): uniform in the cell's face-plane square,
        or — where the cell spans several map texels — a texel drawn in proportion to its energy L·Ω first."""
        r = _uniforms(seed, block, lvl, f, i, j, 3)
        u0, u1, v0, v1 = _rect(i, j, n)
        fine = n >= self.N
        u = u0 + r[:, 0] * (u1 - u0)
        v = v0 + r[:, 1] * (v1 - v0)
        coarse = np.flatnonzero(~fine)
        if len(coarse):
            N = self.N
            for kk in np.unique(N // n[coarse]):
                sel = coarse[(N // n[coarse]) == kk]
                rows = (i[sel] * kk)[:, None] + np.arange(kk)[None, :]
                cols = (j[sel] * kk)[:, None] + np.arange(kk)[None, :]
                E = self.energy[f[sel][:, None, None], rows[:, :, None], cols[:, None, :]].reshape(len(sel), -1)
                tot = E.sum(axis=1)
                E = np.where(tot[:, None] > 0, E, 1.0)
                cum = np.cumsum(E, axis=1)
                t = np.minimum((r[sel, 2:3] * cum[:, -1:] >= cum).sum(axis=1), kk * kk - 1)
                a_, b_ = t // kk, t % kk
                h = 2.0 / N
                u[sel] = (j[sel] * kk + b_ + r[sel, 0]) * h - 1.0
                v[sel] = (i[sel] * kk + a_ + r[sel, 1]) * h - 1.0
        return u, v


def _lobe_weights(d, nrm, w, om, s):
    """max(d·ω,0)^s Ω (normalisation) and the same × [n·ω > 0] (numerator) for pixel-aligned arrays."""
    c = np.maximum(_dot(d, w), 0.0)
    with np.errstate(divide="ignore", under="ignore"):
        f = (c if s == 1.0 else np.power(c, s)) * om
    return f, f * (_dot(nrm, w) > 0)


def _level_weights(env, M, d, nrm, s):
    """Base-cell weights of every pixel at quadrature level M: the pairs (pixel, cell) with W > 0 (``key`` =
    pixel·K + cell, ascending), their weights ``W`` (n, C), and per pixel the normalisation ``ws`` = Σ max(d·ω,0)^s Ω
    and the unoccluded average ``U`` (P, C)."""
    from ..environment.envmap import direction_to_texel, texel_directions

    nb = env.nb
    K = 6 * nb * nb
    dq, oq, Lq = env.quad(M)
    cen = np.asarray(texel_directions(nb)).reshape(-1, 3)
    k = dq.shape[1]
    kk = int(round(np.sqrt(k)))
    # angular radius of every cell around its centre direction (a corner is farthest), plus a texel of margin
    corner = dq.reshape(K, kk, kk, 3)[:, [0, 0, -1, -1], [0, -1, 0, -1]]
    rad = np.arccos(np.clip(_dot(corner, cen[:, None, :]), -1.0, 1.0)).max(axis=1) + 2.0 * np.pi / M
    cut = np.arccos(LOBE_TAIL_CUT ** (1.0 / s))
    P = len(d)
    fo, ro, co = direction_to_texel(d, 8)
    order = np.argsort((np.asarray(fo) * 8 + ro) * 8 + co, kind="stable")  # lobes of a chunk overlap
    C = env.C
    ws = np.zeros(P)
    U = np.zeros((P, C))
    chunk = int(np.clip(QUAD_CHUNK_ELEMENTS // (K * k), 1, 64))
    keys, Ws = [], []
    for a0 in range(0, P, chunk):
        idx = order[a0:a0 + chunk]
        ang = np.arccos(np.clip(_dot(d[idx][:, None, :], cen[None, :, :]), -1.0, 1.0))
        cells = np.flatnonzero((ang <= cut + rad[None, :]).any(axis=0))
        f, fh = _lobe_weights(d[idx][:, None, None, :], nrm[idx][:, None, None, :], dq[cells][None],
                              oq[cells][None], s)  # (p, cells, k)
        ws[idx] = f.sum(axis=(1, 2))
        W = np.stack([(fh * Lq[cells][None, :, :, ch]).sum(axis=2) for ch in range(C)], axis=-1)  # (p, cells, C)
        U[idx] = W.sum(axis=1)
        pl, cl = np.nonzero(W.mean(axis=-1) > 0)
        keys.append(idx[pl] * K + cells[cl])
        Ws.append(W[pl, cl])
    key = np.concatenate(keys)
    o = np.argsort(key, kind="stable")
    ws = np.where(ws > 0, ws, 1.0)
    return dict(key=key[o], W=np.concatenate(Ws)[o], ws=ws, U=U / ws[:, None], K=K)


def _child_weights(env, M, d, nrm, s, p, f, lvl, i, j, Wpar):
    """Weights (4K, C) of the 4 children of K parent cells (level lvl → lvl + 1), children in order (a, b) =
    (0,0), (0,1), (1,0), (1,1) per parent: exact sums of the level-M texels they hold, or — finer than M — the
    parent's weight split in proportion to max(d·ω,0)^s [n·ω>0] Ω at the children's centres."""
    nb = env.nb
    C = env.C
    K = len(p)
    a = np.array([0, 0, 1, 1])
    b = np.array([0, 1, 0, 1])
    ci = (2 * i[:, None] + a[None, :]).reshape(-1)
    cj = (2 * j[:, None] + b[None, :]).reshape(-1)
    cl = np.repeat(lvl + 1, 4)
    cf = np.repeat(f, 4)
    cp = np.repeat(p, 4)
    n_c = nb * (2 ** cl)
    W = np.zeros((4 * K, C))
    coarse = n_c <= M
    if coarse.any():
        dq, oq, Lq = env.quad(M)
        k = M // nb
        sel_all = np.flatnonzero(coarse)
        for kc in np.unique(M // n_c[sel_all]):
            ar = np.arange(kc)
            sel_k = sel_all[(M // n_c[sel_all]) == kc]
            step = max(1, QUAD_CHUNK_ELEMENTS // (4 * kc * kc))
            for a0 in range(0, len(sel_k), step):  # bounded memory
                sel = sel_k[a0:a0 + step]
                L_ = cl[sel]
                cb = (cf[sel] * nb + (ci[sel] >> L_)) * nb + (cj[sel] >> L_)
                r0 = (ci[sel] & ((1 << L_) - 1)) * kc
                c0 = (cj[sel] & ((1 << L_) - 1)) * kc
                sub = ((r0[:, None, None] + ar[None, :, None]) * k + c0[:, None, None]
                       + ar[None, None, :]).reshape(len(sel), -1)
                _, fh = _lobe_weights(d[cp[sel]][:, None, :], nrm[cp[sel]][:, None, :], dq[cb[:, None], sub],
                                      oq[cb[:, None], sub], s)
                W[sel] = np.einsum("kt,ktc->kc", fh, Lq[cb[:, None], sub])
    fine = np.flatnonzero(~coarse)
    if len(fine):
        u0, u1, v0, v1 = _rect(ci[fine], cj[fine], n_c[fine])
        om = _rect_solid_angle(u0, u1, v0, v1)
        w = _dirs(cf[fine], 0.5 * (u0 + u1), 0.5 * (v0 + v1))
        _, g = _lobe_weights(d[cp[fine]], nrm[cp[fine]], w, om, s)
        g4 = np.zeros(4 * K)
        g4[fine] = g
        om4 = np.zeros(4 * K)
        om4[fine] = om
        gs = g4.reshape(K, 4).sum(axis=1)
        os_ = om4.reshape(K, 4).sum(axis=1)
        ratio = np.where(gs[:, None] > 0, g4.reshape(K, 4) / np.where(gs > 0, gs, 1.0)[:, None],
                         om4.reshape(K, 4) / np.where(os_ > 0, os_, 1.0)[:, None]).reshape(-1)
        W[fine] = np.repeat(Wpar, 4, axis=0)[fine] * ratio[fine, None]
    return cp, cf, cl, ci, cj, W


def _kappa(num: float, den: float, n: int) -> float:
    """κ̂: the share of the worst-case variance W²/4 that edge cells carry, measured on the cells split so far (each
    split gives a stratified estimate of its q(1−q) from its children, biased high); 1 until KAPPA_MIN_SPLITS."""
    if n < KAPPA_MIN_SPLITS or den <= 0:
        return 1.0
    return float(min(1.0, max(KAPPA_FLOOR, num / den)))


def _select_pixels(pix, Y, idx, need, S, strict, q, target, P):
    """Cells (``idx``, sorted by Y descending; ``pix`` their pixels) to split so that each pixel of ``need`` gets its
    predicted bound min(Σ W, t·½√ΣW²) + q below ``target``: per pixel its largest cells, fewest first."""
    want = np.zeros(P, bool)
    want[need] = True
    sel = np.flatnonzero(want[pix])
    if len(sel) == 0:
        return np.zeros(0, np.int64)
    o = sel[np.argsort(pix[sel], kind="stable")]  # by pixel, Y still descending inside a pixel
    pp, yy = pix[o], Y[o]
    first = np.r_[0, np.flatnonzero(pp[1:] != pp[:-1]) + 1]
    seg = np.repeat(first, np.diff(np.r_[first, len(pp)]))
    c1 = np.cumsum(yy)
    c2 = np.cumsum(yy ** 2)
    done1 = c1 - (c1[seg] - yy[seg])  # Σ Y over this pixel's cells up to and including this one
    done2 = c2 - (c2[seg] - yy[seg] ** 2)
    # predicted bound after splitting the cells before this one (split cells: Σ W halves, Σ W² shrinks 8×)
    prev1, prev2 = done1 - yy, done2 - yy ** 2
    pred = np.minimum(strict[pp] - 0.5 * prev1, T_BOUND * 0.5 * np.sqrt(np.maximum(S[pp] - (1 - SPLIT_GAIN) * prev2,
                                                                                    0.0))) + q[pp]
    return idx[o[pred > target[pp]]]


def _match(keys, values, query):
    """values[keys == query] for sorted ``keys`` (0 where a query key is absent)."""
    if len(keys) == 0:
        return np.zeros(len(query))
    at = np.minimum(np.searchsorted(keys, query), len(keys) - 1)
    return np.where(keys[at] == query, values[at], 0.0)


def _select(pix, Y, S, budget, min_split, kappa=1.0):
    """How many of the cells (sorted by Y, descending) to split: the fewest whose predicted Σ_p ½√(κ S_p) ≤ budget."""
    n = len(Y)
    if n == 0:
        return 0
    P = len(S)

    def predicted(k):
        red = np.bincount(pix[:k], weights=(1.0 - SPLIT_GAIN) * Y[:k] ** 2, minlength=P)
        return 0.5 * np.sqrt(kappa * np.maximum(S - red, 0.0)).sum()

    if predicted(n) > budget:
        return n
    lo, hi = 0, n  # predicted(hi) <= budget
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if predicted(mid) <= budget:
            hi = mid
        else:
            lo = mid
    return max(hi, min(n, min_split))


_FIELDS = (("p", np.int32), ("f", np.int8), ("l", np.int8), ("i", np.int32), ("j", np.int32), ("Y", np.float64),
           ("V", np.int8), ("edge", bool), ("su", np.float64), ("sv", np.float64), ("bi", np.int32),
           ("key", np.int64))


class _Cells:
    """The refined cells of a block (descendants of split base cells; only leaves are kept), with a Morton-sorted
    index for region look-ups."""

    def __init__(self, C):
        self.d = {k: np.zeros(0, t) for k, t in _FIELDS}
        self.W = np.zeros((0, C))
        self.order = np.zeros(0, np.int64)
        self.skeys = np.zeros(0, np.int64)

    def __len__(self):
        return len(self.W)

    def __getitem__(self, k):
        return self.d[k]

    def replace(self, keep, new, W_new):
        """Keep the cells ``keep`` (bool), append ``new`` (dict of arrays) → index of the appended cells."""
        n0 = int(keep.sum())
        for k, t in _FIELDS:  # one field at a time: the old copy is freed before the next is built
            self.d[k] = np.concatenate([self.d[k][keep], np.asarray(new[k]).astype(t)])
        self.W = np.concatenate([self.W[keep], W_new])
        self.order = np.argsort(self.d["key"], kind="stable")
        self.skeys = self.d["key"][self.order]
        return np.arange(n0, len(self.W))


def _converge_block(job: dict) -> dict:
    """One block of pixels: quadrature level, base rays, adaptive refinement → occluded, unoccluded, errors."""
    from .raycast import ShadowRays

    t0, c0 = time.perf_counter(), time.process_time()
    a, s, rtol = job["env"], float(job["s"]), float(job["rtol"])
    P_, nrm, fn, d = job["points"], job["normals"], job["face_normals"], job["d"]
    nb, depth, seed, blk = int(job["nb"]), int(job["depth"]), int(job["seed"]), int(job["block"])
    Pn = len(P_)
    C = a.shape[-1]
    env = _Env(a, nb)
    caster = ShadowRays(job["scene"], job["backend"], job["eps"])

    # ---- base cells: one random point each, shared by the block's pixels; weights at quadrature level M --------
    K = 6 * nb * nb
    cells = np.arange(K)
    cf, ci, cj = cells // (nb * nb), (cells // nb) % nb, cells % nb
    su_c, sv_c = env.samples(seed, blk, np.zeros(K, np.int64), cf, ci, cj, np.full(K, nb))
    sdir = _dirs(cf, su_c, sv_c)
    prtol = float(job["pixel_rtol"])
    M = int(job["M0"])
    half = _level_weights(env, M // 2, d, nrm, s)
    Q = _level_weights(env, M, d, nrm, s)
    vis_key = np.zeros(0, np.int64)  # (pixel·K + cell) pairs cast so far, ascending, and their visibility
    vis_val = np.zeros(0, np.int8)
    n_rays = 0
    while True:
        ws = Q["ws"]
        bp, bc, bW = Q["key"] // K, Q["key"] % K, Q["W"]
        bY = bW.mean(axis=-1) / ws[bp]
        bYh = _match(half["key"], half["W"].mean(axis=-1), Q["key"]) / half["ws"][bp]  # the same cells at M/2
        # rays for the pairs not cast yet (a finer M can give weight to a few more cells)
        known = _match(vis_key, np.ones(len(vis_key)), Q["key"]) > 0
        new = np.flatnonzero(~known)
        if len(new):
            v_new = caster.visibility(P_[bp[new]], fn[bp[new]], sdir[bc[new]], groups=bc[new]).astype(np.int8)
            n_rays += len(new)
            vis_key = np.concatenate([vis_key, Q["key"][new]])
            vis_val = np.concatenate([vis_val, v_new])
            o = np.argsort(vis_key, kind="stable")
            vis_key, vis_val = vis_key[o], vis_val[o]
        bV = _match(vis_key, vis_val.astype(np.float64), Q["key"]).astype(np.int8)
        # quadrature estimate with the base visibility: image share ≤ QUAD_SHARE·rtol, and ≤ 1 % of the pixels above
        # QUAD_SHARE·pixel_rtol of their value; else M doubles (the cells and their rays stay)
        A0 = np.bincount(bp, weights=bY * (bV > 0), minlength=Pn)
        q0 = np.abs(np.bincount(bp, weights=(bV > 0) * (bY - bYh), minlength=Pn))
        over = (q0 > QUAD_SHARE * prtol * np.maximum(A0, ERR_FLOOR * A0.mean())).mean() if Pn else 0.0
        if ((q0.sum() <= QUAD_SHARE * rtol * max(A0.sum(), 1e-300) and over <= QUAD_PIXEL_SHARE)
                or 2 * M > job["n_quad_max"]):
            break
        M, half, Q = 2 * M, Q, _level_weights(env, 2 * M, d, nrm, s)
    del half, vis_key, vis_val
    nB = len(bp)
    pidx = np.full((Pn, K), -1, dtype=np.int32)
    pidx[bp, bc] = np.arange(nB)
    Vd = np.full((Pn, K), -1, dtype=np.int8)
    Vd[bp, bc] = bV
    nF, nI, nJ = _neighbours(cf, ci, cj, nb)
    nbr = (nF * nb + nI) * nb + nJ  # (K, 8)
    Vn = Vd[bp[:, None], nbr[bc]]
    bedge = ((Vn >= 0) & (Vn != bV[:, None])).any(axis=1)
    del Vn
    bsplit = np.zeros(nB, dtype=bool)
    R = _Cells(C)
    ctx = dict(bV=bV, bedge=bedge, bsplit=bsplit, pidx=pidx, Vd=Vd, nb=nb, depth=depth)

    def quad_est(vb):
        """per-pixel |Σ_c V̄_c (Y_c(M) − Y_c(M/2))| (channel mean, relative to ws)."""
        return np.abs(np.bincount(bp, weights=vb * (bY - bYh), minlength=Pn))

    def vbar():
        """visible fraction of each base pair from its leaves."""
        vb = bV.astype(np.float64).clip(min=0.0)
        if len(R):
            num = np.bincount(R["bi"], weights=R["Y"] * (R["V"] > 0), minlength=nB)
            vb = np.where(bsplit, num / np.where(bY > 0, bY, 1.0), vb)
        return vb

    def uncertain():
        ub = np.flatnonzero(bedge & ~bsplit & (bV >= 0))
        ur = np.flatnonzero(R["edge"])
        return ub, ur, np.concatenate([bp[ub], R["p"][ur]]), np.concatenate([bY[ub], R["Y"][ur]])

    rounds = []
    converged = False
    kap_num = kap_den = 0.0  # Σ W² q̂(1−q̂) n/(n−1) and Σ W²/4 over split cells (→ κ̂)
    n_kap = 0
    for rnd in range(MAX_ROUNDS):
        ub, ur, pix, Yu = uncertain()
        S = np.bincount(pix, weights=Yu ** 2, minlength=Pn)
        strict = np.bincount(pix, weights=Yu, minlength=Pn)
        A = (np.bincount(bp, weights=bY * ((bV > 0) & ~bsplit), minlength=Pn)
             + np.bincount(R["p"], weights=R["Y"] * (R["V"] > 0), minlength=Pn))
        q = quad_est(vbar())
        kap = _kappa(kap_num, kap_den, n_kap)
        sig = 0.5 * np.sqrt(kap * S)
        tot_A = max(A.sum(), 1e-300)
        est = (sig.sum() + q.sum()) / tot_A
        # per pixel: the bound should stay within pixel_rtol of the pixel's value (lit pixels; best effort: pixels
        # whose quadrature estimate alone exceeds it, or whose edge cells are at the finest level, stay over)
        bound = np.minimum(strict, T_BOUND * 0.5 * np.sqrt(S)) + q
        den = np.maximum(A, ERR_FLOOR * A.mean()) if Pn else A
        target = ROUND_AIM * prtol * den
        viol = np.flatnonzero((bound > prtol * den) & (q < target))
        rounds.append(dict(round=rnd, rays=int(n_rays), est_rel_l1=float(est), vis_rel_l1=float(sig.sum() / tot_A),
                           quad_rel_l1=float(q.sum() / tot_A), kappa=float(kap), edge_cells=int(len(pix)),
                           cells=int(nB + len(R)), pixels_over=int(len(viol))))
        if est <= rtol and len(viol) == 0:
            converged = True
            break
        # candidates: edge cells that can still be split, largest weight first
        lv = np.concatenate([np.zeros(len(ub), np.int64), R["l"][ur].astype(np.int64)])
        can = np.flatnonzero(lv < depth)
        o = can[np.argsort(-Yu[can], kind="stable")]
        chosen = np.zeros(0, np.int64)
        if est > rtol and len(o):
            budget = ROUND_AIM * max(rtol * tot_A - q.sum(), 0.25 * rtol * tot_A)
            k_plan = kap if n_kap >= KAPPA_MIN_SPLITS else KAPPA_PLAN  # planning only; the estimate keeps κ̂ = 1
            chosen = o[:_select(pix[o], Yu[o], S, budget, min_split=64, kappa=k_plan)]
        if len(viol) and len(o):
            pick = np.zeros(len(pix), bool)
            pick[chosen] = True
            pick[_select_pixels(pix[o], Yu[o], o, viol, S, strict, q, target, Pn)] = True
            chosen = np.flatnonzero(pick)
        if len(chosen) == 0:
            converged = est <= rtol
            break
        bsel = ub[chosen[chosen < len(ub)]]
        rsel = ur[chosen[chosen >= len(ub)] - len(ub)]
        cb_ = bc[bsel]
        par = dict(p=np.concatenate([bp[bsel], R["p"][rsel]]).astype(np.int64),
                   f=np.concatenate([cb_ // (nb * nb), R["f"][rsel]]).astype(np.int64),
                   l=np.concatenate([np.zeros(len(bsel), np.int64), R["l"][rsel]]).astype(np.int64),
                   i=np.concatenate([(cb_ // nb) % nb, R["i"][rsel]]).astype(np.int64),
                   j=np.concatenate([cb_ % nb, R["j"][rsel]]).astype(np.int64),
                   V=np.concatenate([bV[bsel], R["V"][rsel]]),
                   su=np.concatenate([su_c[cb_], R["su"][rsel]]),
                   sv=np.concatenate([sv_c[cb_], R["sv"][rsel]]),
                   bi=np.concatenate([bsel, R["bi"][rsel]]).astype(np.int64))
        Wpar = np.concatenate([bW[bsel], R.W[rsel]])
        bsplit[bsel] = True
        cp, cf2, cl2, ci2, cj2, cW = _child_weights(env, M, d, nrm, s, par["p"], par["f"], par["l"], par["i"],
                                                    par["j"], Wpar)
        nc = nb * (2 ** cl2)
        cY = cW.mean(axis=-1) / ws[cp]
        # the child holding its parent's point keeps point and ray; the others get their own
        u0, u1, v0, v1 = _rect(ci2, cj2, nc)
        psu, psv = np.repeat(par["su"], 4), np.repeat(par["sv"], 4)
        inherit = (psu >= u0) & (psu < u1) & (psv >= v0) & (psv < v1)
        su2, sv2 = env.samples(seed, blk, cl2, cf2, ci2, cj2, nc)
        su2 = np.where(inherit, psu, su2)
        sv2 = np.where(inherit, psv, sv2)
        cV = np.where(inherit, np.repeat(par["V"], 4), -1).astype(np.int8)
        relevant = cY > 0
        cast = np.flatnonzero(relevant & ~inherit)
        if len(cast):
            grp = None
            if caster.backend == "exact":  # rays toward one cell share their direction: one projection set-up each
                ck = _keys(np.zeros(len(cast), np.int64), cf2[cast], cl2[cast], ci2[cast], cj2[cast], depth)
                grp = np.unique(ck, return_inverse=True)[1]
            cV[cast] = caster.visibility(P_[cp[cast]], fn[cp[cast]], _dirs(cf2[cast], su2[cast], sv2[cast]),
                                         groups=grp)
            n_rays += len(cast)
        cV[~relevant] = -1
        # siblings: a child differing from one of its three siblings is an edge
        v4 = cV.reshape(-1, 4)
        nrel = (v4 >= 0).sum(axis=1)
        ok = nrel >= 2
        if ok.any():
            qh = (v4 > 0).sum(axis=1)[ok] / nrel[ok]
            wp = (Wpar.mean(axis=-1) / ws[par["p"]])[ok] ** 2
            kap_num += float((wp * qh * (1 - qh) * nrel[ok] / (nrel[ok] - 1)).sum())
            kap_den += float((wp / 4).sum())
            n_kap += int(ok.sum())
        has1 = ((v4 == 1).any(axis=1))[:, None]
        has0 = ((v4 == 0).any(axis=1))[:, None]
        sib = ((v4 == 1) & has0) | ((v4 == 0) & has1)
        keep = np.ones(len(R), dtype=bool)
        keep[rsel] = False
        new = dict(p=cp, f=cf2, l=cl2, i=ci2, j=cj2, Y=cY, V=cV, edge=sib.reshape(-1), su=su2, sv=sv2,
                   bi=np.repeat(par["bi"], 4), key=_keys(cp, cf2, cl2, ci2, cj2, depth))
        inew = R.replace(keep, new, cW)
        # the new children against the 12 cells around their 2×2 block (edge flags of older cells only grow)
        _classify_children(R, inew, ctx)

    # ---- results ---------------------------------------------------------------------------------------------------
    lit_b = (bV > 0) & ~bsplit
    occ = (np.stack([np.bincount(bp, weights=bW[:, ch] * lit_b, minlength=Pn) for ch in range(C)], -1)
           + np.stack([np.bincount(R["p"], weights=R.W[:, ch] * (R["V"] > 0), minlength=Pn) for ch in range(C)], -1))
    occ = occ / ws[:, None]
    _, _, pix, Yu = uncertain()
    S = np.bincount(pix, weights=Yu ** 2, minlength=Pn)
    strict = np.bincount(pix, weights=Yu, minlength=Pn)
    q = quad_est(vbar())
    kap = _kappa(kap_num, kap_den, n_kap)
    return dict(occ=occ, un=Q["U"], err_mean=0.5 * np.sqrt(kap * S) + q,
                err_bound=np.minimum(strict, T_BOUND * 0.5 * np.sqrt(S)) + q, kappa=float(kap),
                n_rays=int(n_rays), n_quad=int(M), converged=converged, rounds=rounds,
                max_level=int(nb * 2 ** (int(R["l"].max()) if len(R) else 0)),
                n_cells=int(nB + len(R)), time_s=time.perf_counter() - t0, cpu_s=time.process_time() - c0,
                peak_rss_mb=_peak_rss_mb())


def _peak_rss_mb() -> float:
    """Peak resident set size of this process (MB; 0 where the platform does not report it)."""
    try:
        import resource
        import sys

        r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return r / 2 ** 20 if sys.platform == "darwin" else r / 1024
    except (ImportError, OSError):
        return 0.0


_XMASK = np.int64(0x0000015555555555)  # col bits of the 42-bit Morton code
_YMASK = np.int64(0x000002AAAAAAAAAA)  # row bits
#: region queries per vectorised step of :func:`_classify_children` (bounds its memory, ~150 B per query)
CLASSIFY_CHUNK = 1 << 17


#: the 12 cells around a 2×2 block of children (offsets from the block's first child), and which of the four
#: children (a, b) each one touches
_RING = np.array([(-1, -1), (-1, 0), (-1, 1), (-1, 2), (0, -1), (0, 2), (1, -1), (1, 2), (2, -1), (2, 0), (2, 1), (2, 2)])
_RING_ADJ = np.array([[abs(dr - a) <= 1 and abs(dc - b) <= 1 for dr, dc in _RING] for a in (0, 1) for b in (0, 1)])


def _classify_children(R, inew, ctx):
    """Edge flags of new children (``inew``: groups of 4 siblings, order (0,0), (0,1), (1,0), (1,1)): each child
    against the regions of the 12 same-level cells around its 2×2 block that it touches (its siblings were compared
    already); a region cell (base or refined) that differs from a child it touches becomes an edge too."""
    K = len(inew) // 4
    for a0 in range(0, K, CLASSIFY_CHUNK // 12):
        g = inew[4 * a0:4 * min(K, a0 + CLASSIFY_CHUNK // 12)]
        _classify_children_chunk(R, g, ctx)


def _classify_children_chunk(R, g, ctx):
    nb, depth = ctx["nb"], ctx["depth"]
    first = g[0::4]
    K = len(first)
    V4 = R["V"][g].reshape(K, 4)
    if not (V4 >= 0).any():
        return
    lvl = R["l"][first].astype(np.int64)
    p = R["p"][first].astype(np.int64)
    f0 = R["f"][first].astype(np.int64)
    i0 = R["i"][first].astype(np.int64)
    j0 = R["j"][first].astype(np.int64)
    key = R["key"][first]
    n = nb << lvl
    sh = 2 * (depth - lvl)
    inc = np.int64(1) << sh
    high = key & ~(_XMASK | _YMASK)
    x0, y0 = key & _XMASK, key & _YMASK
    has0 = np.zeros((K, 12), bool)
    has1 = np.zeros((K, 12), bool)
    split_any = []
    for r, (dr, dc) in enumerate(_RING):
        I, J, F = i0 + dr, j0 + dc, f0
        x = ((x0 | _YMASK) + dc * inc) & _XMASK if dc > 0 else ((x0 - inc) & _XMASK if dc < 0 else x0)
        y = ((y0 | _XMASK) + dr * (inc << 1)) & _YMASK if dr > 0 else ((y0 - (inc << 1)) & _YMASK if dr < 0 else y0)
        k0 = high | x | y
        out = (I < 0) | (I >= n) | (J < 0) | (J >= n)
        if out.any():
            o = np.flatnonzero(out)
            F, I, J = F.copy(), I.copy(), J.copy()
            F[o], I[o], J[o] = _neighbour_of(F[o], I[o], J[o], n[o])
            k0[o] = _keys(p[o], F[o], lvl[o], I[o], J[o], depth)
        cb = (F * nb + (I >> lvl)) * nb + (J >> lvl)
        vd = ctx["Vd"][p, cb]
        pi_ = ctx["pidx"][p, cb]
        valid = vd >= 0
        split = valid & ctx["bsplit"][np.maximum(pi_, 0)]
        base = valid & ~split
        has0[:, r] = base & (vd == 0)
        has1[:, r] = base & (vd == 1)
        # a base cell that differs from a child it touches becomes an edge
        touch = V4[:, _RING_ADJ[:, r]]
        rev_b = base & (((vd == 0) & (touch == 1).any(axis=1)) | ((vd == 1) & (touch == 0).any(axis=1)))
        ctx["bedge"][pi_[rev_b]] = True
        sp = np.flatnonzero(split)
        if len(sp):
            split_any.append((r, sp, k0[sp], I[sp], J[sp], F[sp], out[sp]))
    # regions inside split base cells: look them up among the refined cells (Morton ranges)
    sk, order = R.skeys, R.order
    Vs = R["V"][order]
    crel = np.r_[0, np.cumsum(Vs >= 0, dtype=np.int32)]
    cvis = np.r_[0, np.cumsum(Vs > 0, dtype=np.int32)]
    marks = []
    for r, sp, k0, I, J, F, out in split_any:
        dr, dc = _RING[r]
        L_ = lvl[sp]
        k1 = k0 + (np.int64(1) << (2 * (depth - L_)))
        lo = np.searchsorted(sk, k0, side="right") - 1
        lo_c = np.maximum(lo, 0)
        cover = (lo >= 0) & (sk[lo_c] + (np.int64(1) << (2 * (depth - R["l"][order[lo_c]].astype(np.int64)))) > k0)
        start = np.where(cover, lo, lo + 1)
        hi = np.searchsorted(sk, k1, side="left")
        nrel = crel[hi] - crel[start]
        nvis = cvis[hi] - cvis[start]
        h1 = nvis > 0
        h0 = nrel > nvis
        has0[sp, r] = h0
        has1[sp, r] = h1
        touch = V4[sp][:, _RING_ADJ[:, r]]
        rv = np.flatnonzero((h0 & (touch == 1).any(axis=1)) | (h1 & (touch == 0).any(axis=1)))
        if len(rv):
            # the refined cell of the region nearest to the block (middle of the shared side, or the corner)
            w = np.int64(1) << (depth - L_[rv])
            pos = [np.where(out[rv], X[rv] * w + w // 2,
                            X[rv] * w + (w - 1 if d_ < 0 else 0 if d_ > 1 else w // 2))
                   for X, d_ in ((I, dr), (J, dc))]
            kp = _keys(p[sp[rv]], F[rv], np.full(len(rv), depth), pos[0], pos[1], depth)
            at = np.searchsorted(sk, kp, side="right") - 1
            Vr = Vs[at]
            tv = touch[rv]
            diff = ((Vr == 0) & (tv == 1).any(axis=1)) | ((Vr == 1) & (tv == 0).any(axis=1))
            marks.append(order[at[diff]])
    for m in marks:
        R["edge"][m] = True
    # children: an edge if a region they touch holds the other value
    e = np.zeros((K, 4), bool)
    for c in range(4):
        adj = _RING_ADJ[c]
        e[:, c] = np.where(V4[:, c] == 1, has0[:, adj].any(axis=1),
                           np.where(V4[:, c] == 0, has1[:, adj].any(axis=1), False))
    R["edge"][g] |= e.reshape(-1)


def _neighbour_of(f, I, J, n):
    """Cells (f, I, J) of face sizes n, with rows/cols one step outside a face mapped onto the adjacent face."""
    out = (I < 0) | (I >= n) | (J < 0) | (J >= n)
    if out.any():
        f, I, J = f.copy(), I.copy(), J.copy()
        nn = n[out].astype(np.float64)
        d = _dirs(f[out], (J[out] + 0.5) / nn * 2.0 - 1.0, (I[out] + 0.5) / nn * 2.0 - 1.0, normalize=False)
        f[out], I[out], J[out] = _direction_to_texel_n(d, n[out])
    return f, I, J


# ------------------------------------------------------------------------------------------------
# public entry
# ------------------------------------------------------------------------------------------------
def converged_shading(scene, points, normals, face_normals, d_lobe, cube, s: float, *, rtol: float = DEFAULT_RTOL,
                      n_vis_start: int = 16, n_vis_max: int = 16384, n_quad_max: int = 256, eps: float | None = None,
                      backend: str = "auto", seed: int = 0, block_pixels: int = 256, pixel_rtol: float | None = None,
                      workers: int = 1,
                      executor=None, progress: bool = False):
    """Visibility-weighted lobe averages A_s(d) of (*) converged to ``rtol`` (module docstring).

    Parameters
    ----------
    scene : occluders (:func:`ibl_ref.rendering.raster.prepare_scene`)
    points, normals, face_normals, d_lobe : (P, 3) surface points, shading normals, face normals, lobe axes
    cube : (6, N, N, C) radiance
    s : Phong exponent (finite, ≥ 1)
    rtol : target estimated relative L1 (Σ err_mean / Σ A)
    n_vis_start : smallest visibility base face size; n_vis_max : finest visibility face size
    n_quad_max : largest quadrature face size
    eps : shadow-ray offset (default 1e-6 × scene radius); backend : ray caster (``"auto"``, ``"embree"``,
        ``"exact"``; :class:`ibl_ref.rendering.raycast.ShadowRays`)
    seed : random points of the visibility cells; block_pixels : pixels per block (the blocks, hence the image,
        depend on it, never on ``workers``/``executor``)
    workers, executor : where the blocks run (:func:`ibl_ref.executors.map_jobs`); the result is bit-identical

    Returns
    -------
    occluded (P, C), unoccluded (P, C), err_mean (P,), err_bound (P,), info
    """
    from ..executors import map_jobs
    from .raster import prepare_scene
    from .raycast import resolve_shadow_backend
    from .reference_render import _check_env

    a = _check_env(cube)
    N = a.shape[1]
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    fn = np.asarray(face_normals, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(d_lobe, dtype=np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    s = float(s)
    if not (np.isfinite(s) and s >= 1.0):
        raise IBLError(f"Phong exponent s must be finite and >= 1 for the converged reference, got {s}")
    rtol = float(rtol)
    if not (rtol > 0 and np.isfinite(rtol)):
        raise IBLError(f"rtol must be a finite number > 0, got {rtol}")
    for name, v in (("n_vis_start", n_vis_start), ("n_vis_max", n_vis_max), ("n_quad_max", n_quad_max),
                    ("block_pixels", block_pixels)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise IBLError(f"{name} must be a positive integer, got {v!r}")
    backend = resolve_shadow_backend(backend)
    t0 = time.perf_counter()
    scene = prepare_scene(scene, warn=False)
    nb = base_level(s, N, n_vis_start)
    depth = 0
    while nb * 2 ** (depth + 1) <= n_vis_max and nb * 2 ** (depth + 1) < 2 ** _MORTON_BITS:
        depth += 1
    M0 = quadrature_start(s, N, nb)
    n_quad_max = max(int(n_quad_max), M0)
    nP = len(P)
    nblk = max(1, -(-nP // int(block_pixels)))
    jobs = []
    for b in range(nblk):
        idx = np.arange(b, nP, nblk)
        jobs.append(dict(env=a, s=s, rtol=rtol, points=P[idx], normals=nrm[idx], face_normals=fn[idx], d=d[idx],
                         nb=nb, depth=depth, seed=int(seed), block=b, M0=M0, n_quad_max=n_quad_max, scene=scene,
                         pixel_rtol=PIXEL_RTOL_FACTOR * rtol if pixel_rtol is None else float(pixel_rtol),
                         backend=backend, eps=eps))
    res = map_jobs(_converge_block, jobs, executor=executor, workers=workers,
                   desc=f"reference s={s:g} ({nblk} blocks)" if progress else None, what="reference block")
    C = a.shape[-1]
    occ = np.zeros((nP, C))
    un = np.zeros((nP, C))
    em = np.zeros(nP)
    eb = np.zeros(nP)
    for b, r in enumerate(res):
        idx = np.arange(b, nP, nblk)
        occ[idx], un[idx], em[idx], eb[idx] = r["occ"], r["un"], r["err_mean"], r["err_bound"]
    y = occ.mean(axis=-1)
    tot = max(float(np.abs(y).sum()), 1e-300)
    info = dict(n_vis_base=int(nb), n_vis_finest=int(max(r["max_level"] for r in res)),
                n_quad=sorted({int(r["n_quad"]) for r in res}), n_rays=int(sum(r["n_rays"] for r in res)),
                n_cells=int(sum(r["n_cells"] for r in res)), blocks=nblk, backend=backend, rtol=rtol,
                est_rel_l1=float(em.sum() / tot), block_converged=int(sum(r["converged"] for r in res)),
                converged=bool(all(r["converged"] for r in res)),
                rounds_max=int(max(len(r["rounds"]) for r in res)),
                block_rounds=[r["rounds"] for r in res[:1]], time_s=time.perf_counter() - t0,
                block_time_s=float(sum(r["time_s"] for r in res)), block_cpu_s=float(sum(r["cpu_s"] for r in res)),
                worker_peak_rss_mb=float(max(r["peak_rss_mb"] for r in res)))
    return occ, un, em, eb, info
