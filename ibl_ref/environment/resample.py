"""Resampling between lat-long maps, cube maps of any size, crosses and face lists, conserving ∫L dω.

Not a paper concept: the input plumbing every IBL tool needs.  Knuth et al. 2014 work on cube maps
(Sec. 4); environment maps are usually distributed as lat-long images or crosses.

Two methods (``method=``)
-------------------------
**conservative** (default for lat-long ↔ cube, :class:`ConservativeKernel`).  One sparse kernel
``K[t, s] ≈ ∫_S hat_t dω`` couples cube texel t and lat-long texel s: every lat-long texel S is split into
``ks × ks`` sub-texels with exact solid angles (the texels of a ``ks·H`` lat-long map) and each
sub-texel is distributed over the cube texels by their seam-aware bilinear hat functions (a partition
of unity), so Σ_t K = Ω_s exactly and Σ_s K ≈ Ω_t.  ``iters`` (100; 50 above H = 1024) over-relaxed Sinkhorn steps balance both marginals, and
the destination side is normalised exactly on application:

    lat-long → cube:  L_t = Σ_s K[t,s] L_s / Σ_s K[t,s]      cube → lat-long:  L_s = Σ_t K[t,s] L_t / Σ_t K[t,s]

Constants are reproduced exactly, and ∫L dω is conserved *per source texel* to the remaining
imbalance (measured ≤ 4.6e-5 for H = 16 … 512, 1.0e-4 at H = 1024, 1.8e-4 at H = 2048 with 50 steps, N = H/2:
``python benchmarks/bench_probe_sizes.py --kernels``; :attr:`ConservativeKernel.energy_error_ll`,
``energy_error_cube``), so even a one-texel sun keeps its energy wherever it lies — including the tiny
lat-long texels near the poles,
which a destination-side supersampler skips or over-counts (the ``gather`` method changes the energy of
a single bright lat-long texel by up to 100 % at k = 2; measured in ``benchmarks/bench_resample.py``).

**gather** (also used by :func:`cube_to_cube` for non-integer ratios).  A destination texel T receives
the area-weighted average of the interpolated source over T, L_T = ∫_T L dω / Ω_T, evaluated with
``k × k`` sub-texels: for a cube destination of face size N these are exactly the texels of a face of
size kN (exact solid angles, summing exactly to Ω_T), for a lat-long destination of height H the texels
of a ``kH × 2kH`` map.  The source is evaluated at every sub-texel centre with

* ``interpolation="bilinear"``: bilinear interpolation of the source texel centres
  (lat-long: wrapping in longitude and continuing across the poles to the opposite longitude;
  cube: seam-aware :class:`ibl_ref.environment.sampling.CubeSampler`), O(h²) accurate for smooth maps;
* ``interpolation="box"``: the value of the source texel containing the sub-texel centre.

Constants are exact; ∫L dω is conserved only up to the aliasing of the sampled interpolation weights
(O(h²) for smooth maps, but O(1) for a single bright texel).

For both methods, ``conserve=True`` additionally rescales each channel by the exact ratio of the two
integrals (optional, off by default).

Supersampling rule: ``k = clip(ceil(2·p_a/p_b), 2, 16)`` with p the angular texel pitch at the equator /
face centre (lat-long H: π/H; cube N: π/(2N)); ``gather`` sub-samples the destination (p_a =
destination, p_b = source pitch), ``conservative`` the lat-long grid (p_a = lat-long, p_b = cube pitch;
doubled until every cube texel receives samples).  That places ≥ 2 sub-samples per texel pitch of the other grid.

Accuracy (texel averages of a smooth function, ``benchmarks/bench_resample.py``): mean round-trip
error O(h²); the maximum error is first order near the lat-long poles (a lat-long texel's value is
treated as constant over a sliver whose centroid is not its centre) and, for ``conservative``, in the
cube-corner texels (the hat of the corner is shared by three faces).

Crosses (:func:`cross_to_cube`, :func:`cube_to_cross`)
-------------------------------------------------------
The common unfolding used by cmft, CubeMapGen and most skybox images.  The faces are stored as images
in the **OpenGL** orientation (docs/background.md §2: +X:(−z,−y), −X:(+z,−y), +Y:(+x,+z), −Y:(+x,−z),
+Z:(+x,−y), −Z:(−x,−y) for (u→, v↓)), placed as follows (each cell N × N)::

    horizontal cross, 4N wide x 3N high      vertical cross, 3N wide x 4N high
        .   +Y   .   .                            .   +Y   .
       -X   +Z  +X  -Z                           -X   +Z  +X
        .   -Y   .   .                            .   -Y   .
                                                  .   -Z*  .      (* -Z rotated by 180°)

With this placement every edge shared by two neighbouring cells of the cross is the same cube edge,
traversed in the same direction (the tests check continuity across every internal cross edge and the
direction of every texel).  Empty cells are zero.

Face lists (:func:`faces_to_cube`, :func:`cube_to_faces`): six N × N images in order +X, −X, +Y, −Y,
+Z, −Z, in the ``openexr`` or ``opengl`` face orientation (:mod:`ibl_ref.environment.envmap`).
"""

from __future__ import annotations

import math

import numpy as np

from . import envmap
from ..errors import IBLError, LayoutError
from .radiance_policy import check_radiance
from .validated import environment_array
from .sampling import CubeSampler
from .sampling import padding_tables

__all__ = [
    "latlong_to_cube_cost",
    "CONSERVATIVE_COST",
    "supersample_factor",
    "latlong_to_cube",
    "cube_to_latlong",
    "cube_to_cube",
    "latlong_to_latlong",
    "integral_cube",
    "integral_latlong",
    "cross_to_cube",
    "cube_to_cross",
    "faces_to_cube",
    "cube_to_faces",
    "ConservativeKernel",
    "conservative_kernel",
    "latlong_block_reduce",
    "prereduce_factor",
]

_INTERP = ("bilinear", "box")
K_MAX = 16
_CHUNK = 1 << 18


def _relax(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Over-relaxed Sinkhorn update ``x^(1−ω)·t^ω`` with ω = 1.75, as ``t·(t/x)^¾`` (two square roots, no pow)."""
    z = np.sqrt(t / x)
    return t * z * np.sqrt(z)  # sub-samples per evaluation chunk (memory bound)


def supersample_factor(p_dst: float, p_src: float, k_max: int = K_MAX, k_min: int = 2) -> int:
    """``k = clip(ceil(2·p_dst/p_src), k_min, k_max)`` sub-texels per destination texel edge."""
    return int(min(max(math.ceil(2.0 * p_dst / p_src - 1e-9), k_min), k_max))


def _pitch_cube(n: int) -> float:
    return math.pi / (2 * n)


def _pitch_latlong(h: int) -> float:
    return math.pi / h


# ----------------------------------------------------------------------------------------------
# integrals
# ----------------------------------------------------------------------------------------------
def integral_cube(cube) -> np.ndarray:
    """∫L dω of a cube map per channel (exact texel solid angles), shape (C,) or scalar."""
    n = envmap.check_cube_shape(cube)
    w = envmap.texel_solid_angles(n)
    a = np.asarray(cube, dtype=np.float64)
    return np.einsum("fij...,ij->...", a, w)


def integral_latlong(img) -> np.ndarray:
    """∫L dω of an H × 2H lat-long map per channel (exact texel solid angles)."""
    a = np.asarray(img, dtype=np.float64)
    h, w = a.shape[:2]
    om = envmap.latlong_solid_angles(h, w)[:, 0]
    return np.einsum("ij...,i->...", a, om)


# ----------------------------------------------------------------------------------------------
# source samplers
# ----------------------------------------------------------------------------------------------
class _LatLongSampler:
    def __init__(self, img: np.ndarray, interpolation: str):
        self.img = img
        self.h, self.w = img.shape[:2]
        self.interpolation = interpolation

    def __call__(self, d: np.ndarray) -> np.ndarray:
        x, y = envmap.direction_to_latlong(d, self.h, self.w)
        if self.interpolation == "box":
            col = np.floor(x + 0.5).astype(np.intp) % self.w
            row = np.clip(np.floor(y + 0.5), 0, self.h - 1).astype(np.intp)
            return self.img[row, col]
        x0 = np.floor(x)
        y0 = np.floor(y)
        fx = (x - x0)[..., None]
        fy = (y - y0)[..., None]
        c0 = x0.astype(np.intp) % self.w
        c1 = (c0 + 1) % self.w
        r0 = y0.astype(np.intp)
        r1 = r0 + 1
        im = self.img

        def row(r, c):
            # across a pole, row -1 is row 0 and row H is row H-1, half a turn away in longitude
            over = (r < 0) | (r >= self.h)
            rr = np.clip(r, 0, self.h - 1)
            cc = np.where(over, (c + self.w // 2) % self.w, c)
            return im[rr, cc]

        top = row(r0, c0) * (1 - fx) + row(r0, c1) * fx
        bot = row(r1, c0) * (1 - fx) + row(r1, c1) * fx
        return top * (1 - fy) + bot * fy


class _CubeSourceSampler:
    def __init__(self, cube: np.ndarray, interpolation: str):

        self.s = CubeSampler(cube)
        self.interpolation = interpolation

    def __call__(self, d: np.ndarray) -> np.ndarray:
        if self.interpolation == "box":
            return self.s.nearest(d)
        # directions exactly on a cube edge make CubeSampler divide by zero for a neighbour whose
        # blend weight is 0 (harmless, the result is finite); silence that warning only
        with np.errstate(divide="ignore"):
            return np.maximum(self.s.bilinear(d), 0.0)


# ----------------------------------------------------------------------------------------------
# destination grids
# ----------------------------------------------------------------------------------------------
def _to_cube(sampler, n: int, k: int, c: int) -> np.ndarray:
    nk = n * k
    w = envmap.texel_solid_angles(nk)  # exact sub-texel solid angles
    omega = w.reshape(n, k, n, k).sum(axis=(1, 3))
    cen = envmap.texel_center_uv(nk)
    out = np.empty((6, n, n, c))
    rows = max(1, _CHUNK // (nk * k))  # destination rows per chunk
    for f in range(6):
        for r0 in range(0, n, rows):
            r1 = min(n, r0 + rows)
            v = cen[r0 * k : r1 * k]
            d = envmap.face_uv_to_direction(f, cen[None, :], v[:, None])  # (rows*k, nk, 3)
            val = sampler(d) * w[r0 * k : r1 * k, :, None]
            out[f, r0:r1] = val.reshape(r1 - r0, k, n, k, c).sum(axis=(1, 3))
    out /= omega[None, :, :, None]
    return _finite(out)


def _latlong_rows(h: int, w: int, r0: int, r1: int) -> np.ndarray:
    """Rows r0..r1-1 of :func:`ibl_ref.environment.envmap.latlong_directions` (h, w) without building the whole grid."""
    lat, lon = envmap.latlong_angles(h, w)
    lat = lat[r0:r1, None]
    cl = np.cos(lat)
    return np.stack(np.broadcast_arrays(np.sin(lon)[None, :] * cl, np.sin(lat), np.cos(lon)[None, :] * cl), axis=-1)


def _to_latlong(sampler, h: int, k: int, c: int) -> np.ndarray:
    hk, wk = h * k, 2 * h * k
    om_sub = envmap.latlong_solid_angles(hk, wk)[:, 0]  # per sub-row, exact
    om = envmap.latlong_solid_angles(h, 2 * h)[:, 0]
    out = np.empty((h, 2 * h, c))
    rows = max(1, _CHUNK // (wk * k))
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        d = _latlong_rows(hk, wk, r0 * k, r1 * k)
        val = sampler(d) * om_sub[r0 * k : r1 * k, None, None]
        out[r0:r1] = val.reshape(r1 - r0, k, 2 * h, k, c).sum(axis=(1, 3))
    out /= om[:, None, None]
    return _finite(out)


# ----------------------------------------------------------------------------------------------
# conservative lat-long <-> cube kernel (method="conservative")
# ----------------------------------------------------------------------------------------------
def _cube_hat_taps(d: np.ndarray, n: int):
    """Seam-aware bilinear "hat" taps of cube texels at directions d: flat texel indices and weights (..., 12).

    Bilinear weights on the face grid padded by one texel (:func:`ibl_ref.environment.sampling.padding_tables`,
    neighbour-face unfolding, corner texels shared by three faces; evaluated by :func:`_padded_taps`);
    weights are ≥ 0 and sum to 1.
    """
    face, x, y = envmap.direction_to_texel_coords(d, n)
    m = n + 2
    xp, yp = x + 1.0, y + 1.0
    x0 = np.clip(np.floor(xp), 0, m - 2).astype(np.intp)
    y0 = np.clip(np.floor(yp), 0, m - 2).astype(np.intp)
    fx, fy = np.clip(xp - x0, 0, 1), np.clip(yp - y0, 0, 1)
    base = face * m * m + y0 * m + x0
    p = np.stack([base, base + 1, base + m, base + m + 1], -1)
    wp = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1)
    pf, rem = np.divmod(p, m * m)
    src, w = _padded_taps(pf, rem // m, rem % m, n)
    idx = src.reshape(p.shape[:-1] + (12,))
    wt = (wp[..., None] * w).reshape(p.shape[:-1] + (12,))
    return idx, wt


def _default_iters(n_domain: int) -> int:
    """Sinkhorn steps: 100, or 50 when the fundamental domain holds more than 2^18 texels (H > 1024)."""
    return 100 if n_domain <= 1 << 18 else 50


# The 8 symmetries shared by both grids when H is even: rotations by q·90° about +Y (longitude − q·π/2,
# lat-long columns shift by q·W/4) and the mirror y → −y (rows flip).  g = (q, m).
_GROUP = tuple((q, m) for m in (0, 1) for q in range(4))
_ROT = ((1, 0), (0, 1), (-1, 0), (0, -1))  # (cos β, sin β) for β = q·π/2, exact


def _apply_g(d: np.ndarray, q: int, m: int, inverse: bool = False) -> np.ndarray:
    """Direction map of g = (q, m): rotate longitude by −q·π/2, then mirror y if m (or the inverse map)."""
    c, s_ = _ROT[(-q) % 4] if inverse else _ROT[q]
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    y = -y if m else y
    return np.stack([x * c - z * s_, y, z * c + x * s_], axis=-1)


_DIHEDRAL = (
    lambda a: a, lambda a: np.rot90(a, 1), lambda a: np.rot90(a, 2), lambda a: np.rot90(a, 3),
    lambda a: np.swapaxes(a, 0, 1), lambda a: np.rot90(np.swapaxes(a, 0, 1), 1),
    lambda a: np.rot90(np.swapaxes(a, 0, 1), 2), lambda a: np.rot90(np.swapaxes(a, 0, 1), 3),
)
_FACE_OPS: dict = {}


def _face_ops(q: int, m: int, inverse: bool) -> tuple:
    """Per destination face f': ``(f, k)`` with ``out[f'] = _DIHEDRAL[k](src[f])`` meaning
    ``out[t'] = src[texel containing map(centre of t')]`` (map = g or its inverse).

    Derived once numerically on a 5² cube (odd, so every dihedral operation is distinguishable) and
    valid for every face size, because g maps the texel grid onto itself.
    """
    key = (q, m, inverse)
    if key not in _FACE_OPS:
        k5 = 5
        d = _apply_g(envmap.texel_directions(k5), q, m, inverse=inverse)
        face, x, y = envmap.direction_to_texel_coords(d, k5)
        col, row = np.rint(x).astype(int), np.rint(y).astype(int)
        ref = np.arange(k5 * k5).reshape(k5, k5)
        ops = []
        for fp in range(6):
            fs = np.unique(face[fp])
            if fs.size != 1:  # pragma: no cover - the maps are cube symmetries
                raise AssertionError("cube symmetry does not map faces to faces")
            local = row[fp] * k5 + col[fp]
            k = next(i for i, op in enumerate(_DIHEDRAL) if np.array_equal(op(ref), local))
            ops.append((int(fs[0]), k))
        _FACE_OPS[key] = tuple(ops)
    return _FACE_OPS[key]


def _gather_faces(src: np.ndarray, ops) -> np.ndarray:
    """``out[f'] = _DIHEDRAL[k](src[f])`` for the (6, n, n, ...) array ``src``."""
    return np.stack([_DIHEDRAL[k](src[f]) for f, k in ops])


_RING: dict = {}
_N0 = 5  # size the ring pattern is read at (odd: t and n−1−t differ)


def _ring_pattern():
    """Where the one-texel ring of padding around each face reads from, as size-independent rules.

    Read once from :func:`ibl_ref.environment.sampling.padding_tables` at face size 5: for an edge cell at position t
    along side ``side`` (0: row −1, 1: row n, 2: column −1, 3: column n) of face f the source is texel
    (f', r', c') of weight 1 with r', c' each one of {0, n−1, t, n−1−t} (codes 0…3); a corner cell
    reads three texels with r, c ∈ {0, n−1} and weight ⅓ each.  These rules hold at every n because
    the unfolding maps face edges onto face edges.
    """
    if "edge" in _RING:
        return _RING

    n, m = _N0, _N0 + 2
    src, w = padding_tables(n, 1)
    forms = lambda t: (0, n - 1, t, n - 1 - t)  # noqa: E731
    edge = np.zeros((6, 4, 3), np.int64)  # f', row code, col code
    corner = np.zeros((6, 4, 3, 3), np.int64)  # 3 × (f', row is n−1, col is n−1)
    cw = np.zeros((6, 4, 3))
    for f in range(6):
        for side, cells in enumerate(((0, None), (m - 1, None), (None, 0), (None, m - 1))):
            codes = set()
            for t in range(n):
                yp, xp = (cells[0], t + 1) if cells[0] is not None else (t + 1, cells[1])
                if not np.isclose(w[f, yp, xp, 0], 1.0):  # pragma: no cover - k = 1 edges read one texel
                    raise AssertionError("unexpected padding weights")
                fq, rq, cq = np.unravel_index(src[f, yp, xp, 0], (6, n, n))
                rc = tuple(k for k, v in enumerate(forms(t)) if v == rq)
                cc = tuple(k for k, v in enumerate(forms(t)) if v == cq)
                codes.add((int(fq), rc, cc))
            common = (None, set.intersection(*[set(c[1]) for c in codes]), set.intersection(*[set(c[2]) for c in codes]))
            fqs = {c[0] for c in codes}
            if len(fqs) != 1 or not common[1] or not common[2]:  # pragma: no cover
                raise AssertionError("padding ring is not an affine edge map")
            edge[f, side] = (fqs.pop(), min(common[1]), min(common[2]))
        for ci, (yp, xp) in enumerate(((0, 0), (0, m - 1), (m - 1, 0), (m - 1, m - 1))):
            for k in range(3):
                fq, rq, cq = np.unravel_index(src[f, yp, xp, k], (6, n, n))
                corner[f, ci, k] = (fq, rq == n - 1, cq == n - 1)
                cw[f, ci, k] = w[f, yp, xp, k]
    _RING.update(edge=edge, corner=corner, cw=cw)
    return _RING


def _padded_taps(face, yp, xp, n: int):
    """``(src (..., 3), w (..., 3))`` of padded-grid cells (face, yp, xp) of a face of size n padded by one
    texel — the entries :func:`ibl_ref.environment.sampling.padding_tables` (n, 1) holds — without building that
    (6, n+2, n+2, 3) table (2.6 GB of temporaries at n = 2048)."""
    pat = _ring_pattern()
    i, j = yp - 1, xp - 1
    src = np.zeros(face.shape + (3,), np.int64)
    w = np.zeros(face.shape + (3,))
    out_i, out_j = (i < 0) | (i >= n), (j < 0) | (j >= n)
    inside = ~out_i & ~out_j
    src[inside, 0] = face[inside] * n * n + i[inside] * n + j[inside]
    w[inside, 0] = 1.0
    ed = out_i ^ out_j
    if ed.any():
        f, ii, jj = face[ed], i[ed], j[ed]
        side = np.where(ii < 0, 0, np.where(ii >= n, 1, np.where(jj < 0, 2, 3)))
        t = np.where(side < 2, jj, ii)
        fq, rcode, ccode = (pat["edge"][f, side, k] for k in range(3))
        vals = np.stack([np.zeros_like(t), np.full_like(t, n - 1), t, n - 1 - t])
        rq = np.take_along_axis(vals, rcode[None], 0)[0]
        cq = np.take_along_axis(vals, ccode[None], 0)[0]
        src[ed, 0] = fq * n * n + rq * n + cq
        w[ed, 0] = 1.0
    co = out_i & out_j
    if co.any():
        f = face[co]
        ci = 2 * (i[co] >= n) + (j[co] >= n)
        c = pat["corner"][f, ci]  # (k, 3, 3)
        src[co] = c[..., 0] * n * n + c[..., 1] * (n - 1) * n + c[..., 2] * (n - 1)
        w[co] = pat["cw"][f, ci]
    return src, w


def _cube_hat_taps_flat(d: np.ndarray, n: int):
    """:func:`_cube_hat_taps` as flat ``(sample, texel, weight)`` triples with weight > 0.

    Samples whose 4 bilinear taps lie inside their face (all but a ring of half a texel along the face
    borders) take the direct 4 taps; only the others go through the 12-tap seam tables.
    """
    face, x, y = envmap.direction_to_texel_coords(d.reshape(-1, 3), n)
    x0f, y0f = np.floor(x), np.floor(y)
    inner = (x0f >= 0) & (x0f <= n - 2) & (y0f >= 0) & (y0f <= n - 2)
    si = np.flatnonzero(inner)
    fx, fy = x[si] - x0f[si], y[si] - y0f[si]
    base = face[si] * n * n + y0f[si].astype(np.intp) * n + x0f[si].astype(np.intp)
    idx_i = np.stack([base, base + 1, base + n, base + n + 1], -1)
    wt_i = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1)
    se = np.flatnonzero(~inner)
    idx_e, wt_e = _cube_hat_taps(d.reshape(-1, 3)[se], n)
    samp = np.concatenate([np.repeat(si, 4), np.repeat(se, 12)])
    idx = np.concatenate([idx_i.ravel(), idx_e.ravel()])
    wt = np.concatenate([wt_i.ravel(), wt_e.ravel()])
    keep = wt > 0
    return samp[keep], idx[keep], wt[keep]


class ConservativeKernel:
    """Overlap kernel between an ``h × 2h`` lat-long grid and an ``n``-face cube grid.

    ``K[t, s] = Σ_{sub ∈ S} ω_sub · hat_t(ω_sub)``: every lat-long texel S is split into ``ks × ks``
    sub-texels with exact solid angles ω_sub (the texels of a ``ks·h`` lat-long map), and each sub-texel
    centre is distributed over the cube texels t by the seam-aware bilinear hat functions of the cube
    grid (which sum to 1).  So Σ_t K[t, s] = Ω_s exactly and Σ_s K[t, s] ≈ Ω_t (up to the aliasing of
    the sampled hats, a few %).  Lat-long texels, which become arbitrarily small near the poles, are
    therefore never skipped: the energy of every source texel (e.g. a sun) is accounted for.

    The kernel is then balanced by ``iters`` Sinkhorn (iterative proportional fitting) steps,
    ``K ← diag(r) K diag(c)``, towards both marginals Ω_t and Ω_s, over-relaxed in the log domain
    (``r ← r^(1−ω)·(Ω_t / K c)^ω``, the same for c, ω = 1.75: plain steps (ω = 1) converge like 1/steps,
    measured imbalance after 100 steps 1.0e-3 at H = 512 against 2.4e-5 with ω = 1.8; ω ≥ 1.9 oscillates), and every
    application normalises the destination side exactly:

    * lat-long → cube: ``L_t = Σ_s K[t,s] L_s / Σ_s K[t,s]`` (constants exact; ∫L dω exact up to the
      remaining column imbalance, :attr:`energy_error_ll`);
    * cube → lat-long: ``L_s = Σ_t K[t,s] L_t / Σ_t K[t,s]`` (constants exact; ∫L dω exact up to
      :attr:`energy_error_cube`).

    The residual imbalances are the worst-case relative change of ∫L dω for a map that is zero except
    in one source texel (measured with ``benchmarks/bench_probe_sizes.py --kernels``; see there).

    **Symmetry (speed and memory).**  For even ``h`` both grids are invariant under the 8 maps g of
    ``_GROUP`` (4 rotations about +Y × the equator mirror), so only the columns of K whose source texel
    lies in the fundamental domain D (upper hemisphere, first quarter of the columns, ``h/2 × h/2``
    texels) are built and stored (``k0``); the full kernel is ``K[τ_g(t), σ_g(s)] = K0[t, s]``
    (σ_g, τ_g the texel maps of g), and the Sinkhorn steps and applications run on ``k0`` with 8
    face-permuted copies of a cube-sized vector.  The balanced kernel is symmetric by construction,
    ``1/8`` of the sub-samples and of the memory of the unsymmetrised kernel.  Odd ``h`` uses the
    whole grid (D = all texels, identity only), as does ``symmetric=False`` (the independent route the
    tests compare with).
    """

    def __init__(self, h: int, n: int, ks: int, iters: int | None = None, symmetric: bool = True):
        import scipy.sparse as sp

        self.h, self.w, self.n, self.ks = h, 2 * h, n, ks
        w = self.w
        self.sym = symmetric and h % 2 == 0
        self.group = _GROUP if self.sym else ((0, 0),)
        hd, wd = (h // 2, w // 4) if self.sym else (h, w)  # fundamental domain D (rows, cols)
        self.hd, self.wd = hd, wd
        iters = _default_iters(hd * wd) if iters is None else int(iters)
        hk, wk = h * ks, w * ks
        om_sub = envmap.latlong_solid_angles(hk, wk)[:, 0]
        ptrs, inds, vals = [np.zeros(1, np.int64)], [], []
        rows_per = max(1, _CHUNK // (wd * ks) // ks) * ks  # whole source rows per chunk: disjoint columns
        cols_src = np.arange(wd * ks) // ks
        for r0 in range(0, hd * ks, rows_per):
            r1 = min(hd * ks, r0 + rows_per)
            d = _latlong_rows(hk, wk, r0, r1)[:, : wd * ks]
            samp, idx, wt = _cube_hat_taps_flat(d, n)
            c0 = (r0 // ks) * wd  # first source texel (column of K0) of the chunk
            s_idx = ((np.arange(r0, r1) // ks)[:, None] * wd + cols_src[None, :] - c0).ravel()[samp]
            wt *= np.repeat(om_sub[r0:r1], wd * ks)[samp]
            ncol = ((r1 - 1) // ks + 1) * wd - c0
            part = sp.csc_matrix((wt, (idx, s_idx)), shape=(6 * n * n, ncol))  # sums duplicates
            ptrs.append(part.indptr[1:].astype(np.int64) + ptrs[-1][-1])
            inds.append(part.indices.astype(np.int32))
            vals.append(part.data)
            del d, samp, idx, wt, s_idx, part
        indptr = np.concatenate(ptrs)
        indices = np.concatenate(inds)
        del ptrs, inds
        data = np.concatenate(vals)
        del vals
        self.om_t = np.broadcast_to(envmap.texel_solid_angles(n), (6, n, n)).ravel().copy()
        self.om_d = np.broadcast_to(envmap.latlong_solid_angles(h, w)[:hd], (hd, wd)).ravel().copy()
        # K0 restricted to the cube texels S that D's sub-samples reach (stored as CSC, rows = positions in S)
        hit = np.zeros(6 * n * n, bool)
        hit[indices] = True
        S = np.flatnonzero(hit)
        del hit
        lookup = np.zeros(6 * n * n, np.int32)
        lookup[S] = np.arange(S.size, dtype=np.int32)
        indices = lookup[indices]
        del lookup
        k0 = sp.csc_matrix((data, indices, indptr), shape=(S.size, hd * wd))
        del data, indices, indptr
        self.S = S
        if np.any(self._sym_rows(self._full(k0 @ np.ones(k0.shape[1]))) <= 0):
            raise _Undersampled
        # Sinkhorn on S: (K c)[S] = Σ_g (K0 c)[τ_g⁻¹(S)], where τ_g⁻¹(S) outside S contributes 0 (a padded zero)
        pos = self._support_maps(S)
        om_s = self.om_t[S]
        c = np.ones(k0.shape[1])
        r = None
        for _ in range(iters):  # rows -> Ω_t, columns -> Ω_s (on D; symmetric by construction)
            kc = k0 @ c
            base = kc.copy()
            for dst, src in pos:  # g ≠ identity: only where τ_g⁻¹(S) meets S (the seams of D's image)
                kc[dst] += base[src]
            r = om_s / kc if r is None else _relax(r, om_s / kc)
            c = _relax(c, self.om_d / (k0.T @ r))
        del pos
        step = max(1, _CHUNK // 8)
        for j0 in range(0, k0.shape[1], step):  # K0 ← diag(r) K0 diag(c), in place and in column chunks
            j1 = min(k0.shape[1], j0 + step)
            a, b = k0.indptr[j0], k0.indptr[j1]
            k0.data[a:b] *= r[k0.indices[a:b]] * np.repeat(c[j0:j1], np.diff(k0.indptr[j0 : j1 + 1]))
        self.k0 = k0
        self.row = self._sym_rows(self._full(self.k0 @ np.ones(self.k0.shape[1])))
        self.col_d = np.asarray(self.k0.sum(axis=0)).ravel()
        # ll -> cube uses K / row: source texel s contributes Σ_t K[t,s] Ω_t / row_t instead of Ω_s
        self.energy_error_ll = float(np.abs((self.k0.T @ (self.om_t / self.row)[S]) / self.om_d - 1).max())
        self.energy_error_cube = float(np.abs(self._sym_rows(self._full(self.k0 @ (self.om_d / self.col_d)))
                                              / self.om_t - 1).max())
        self.iters = iters

    def _full(self, y_s: np.ndarray) -> np.ndarray:
        """A vector on the support S (rows of k0) as a full cube-length vector (zeros elsewhere)."""
        out = np.zeros((6 * self.n * self.n,) + y_s.shape[1:])
        out[self.S] = y_s
        return out

    def _support_maps(self, S: np.ndarray) -> list:
        """For each g ≠ identity: ``(dst, src)`` positions in S with τ_g⁻¹(S[dst]) = S[src] (the overlaps only)."""
        n = self.n
        if not self.sym:
            return []
        lookup = np.full(6 * n * n, -1, dtype=np.int32)
        lookup[S] = np.arange(S.size, dtype=np.int32)
        ids = np.arange(6 * n * n, dtype=np.int32).reshape(6, n, n)
        out = []
        for q, m in self.group[1:]:
            inv = np.empty_like(ids)
            for fp, (f, k) in enumerate(_face_ops(q, m, inverse=True)):
                inv[fp] = _DIHEDRAL[k](ids[f])
            src = lookup[inv.ravel()[S]]
            dst = np.flatnonzero(src >= 0)
            out.append((dst, src[dst]))
        return out

    def _sym_rows(self, y: np.ndarray) -> np.ndarray:
        """Σ_g of ``y`` (cube-length, from the D columns) moved to the cube texels of g(D): the full K product."""
        if not self.sym:
            return y
        n = self.n
        y3 = y.reshape((6, n, n) + y.shape[1:])
        out = np.zeros_like(y3)
        for q, m in self.group:
            for fp, (f, k) in enumerate(_face_ops(q, m, inverse=True)):
                out[fp] += _DIHEDRAL[k](y3[f])
        return out.reshape(y.shape)

    def _block(self, img: np.ndarray, q: int, m: int) -> np.ndarray:
        """Source texels σ_g(D) of an (h, w, C) image, in the order of D (rows, then columns)."""
        if not self.sym:
            return img.reshape(self.h * self.w, -1)
        rows = img[::-1][: self.hd] if m else img[: self.hd]
        return np.ascontiguousarray(rows[:, q * self.wd : (q + 1) * self.wd]).reshape(self.hd * self.wd, -1)

    def to_cube(self, img: np.ndarray) -> np.ndarray:
        n, c = self.n, img.shape[-1]
        out = np.zeros((6, n, n, c))
        # sparse products for several source blocks at once (columns g·C … g·C + C−1), at most ~256 MB each
        per = max(1, min(len(self.group), (1 << 25) // max(1, self.hd * self.wd * c)))
        y = np.zeros((6 * n * n, c))
        for i, (q, m) in enumerate(self.group):
            if i % per == 0:
                grp = self.group[i : i + per]
                ys = self.k0 @ np.concatenate([self._block(img, qq, mm).astype(np.float64) for qq, mm in grp], axis=1)
            j = i % per
            y[self.S] = ys[:, j * c : (j + 1) * c]
            if not self.sym:
                out += y.reshape(6, n, n, c)
                continue
            y3 = y.reshape(6, n, n, c)
            for fp, (f, k) in enumerate(_face_ops(q, m, inverse=True)):
                out[fp] += _DIHEDRAL[k](y3[f])
        out /= self.row.reshape(6, n, n, 1)
        return out

    def to_latlong(self, cube: np.ndarray) -> np.ndarray:
        n, c = self.n, cube.shape[-1]
        out = np.empty((self.h, self.w, c))
        cube = cube.reshape(6, n, n, c)
        for q, m in self.group:
            z = _gather_faces(cube, _face_ops(q, m, inverse=False)) if self.sym else cube
            vals = (self.k0.T @ z.reshape(6 * n * n, c)[self.S]) / self.col_d[:, None]
            if not self.sym:
                return vals.reshape(self.h, self.w, c)
            blk = vals.reshape(self.hd, self.wd, c)
            if m:
                out[self.h - 1 : self.h - 1 - self.hd : -1, q * self.wd : (q + 1) * self.wd] = blk
            else:
                out[: self.hd, q * self.wd : (q + 1) * self.wd] = blk
        return out


class _Undersampled(Exception):
    pass


_KERNELS: dict = {}


def conservative_kernel(h: int, n: int, ks: int | None = None, iters: int | None = None) -> ConservativeKernel:
    """The (cached) :class:`ConservativeKernel` between an ``h × 2h`` lat-long grid and face size ``n``.

    ``ks`` default: ``clip(ceil(2·p_latlong/p_cube), 2, 16)`` lat-long sub-texels per edge, doubled until
    every cube texel receives samples; ``ks = 1`` when the lat-long grid is already at least twice as
    fine as the cube (H ≥ 4N: big probes reduced to a working cube, 4× fewer sub-samples).
    """
    if ks is None:
        ks = supersample_factor(_pitch_latlong(h), _pitch_cube(n), k_min=1 if h >= 4 * n else 2)
    key = (h, n, ks, iters)
    if key not in _KERNELS:
        while True:
            try:
                kern = ConservativeKernel(h, n, ks, iters)
                break
            except _Undersampled:
                if ks >= 64:
                    raise FloatingPointError(f"cannot cover a {n}-face cube from a {h}-row lat-long grid") from None
                ks *= 2
        if len(_KERNELS) >= 4:
            _KERNELS.pop(next(iter(_KERNELS)))
        _KERNELS[key] = kern
    return _KERNELS[key]


def _finite(out):
    if not np.all(np.isfinite(out)):  # never emit silent NaN/Inf
        raise FloatingPointError("resampling produced non-finite values (internal error)")
    return out


def _prep(a, what: str, ndim_img: int, keep_float32: bool = False):
    a = np.asarray(a)
    check_radiance(a, what)  # NaN/Inf/negative, and complex/integer/boolean dtypes, before any cast
    if not (keep_float32 and a.dtype == np.float32):
        a = a.astype(np.float64, copy=False)
    squeeze = a.ndim == ndim_img - 1
    if squeeze:
        a = a[..., None]
    if a.ndim != ndim_img or any(d < 1 for d in a.shape):  # (0, 0, 3) and friends: nothing to resample
        raise LayoutError(f"{what}: expected a non-empty array of {ndim_img - 1} or {ndim_img} dimensions, got "
                          f"shape {np.shape(a)}")
    return a, squeeze


def _check_interp(interpolation):
    if interpolation not in _INTERP:
        raise IBLError(f"unknown interpolation {interpolation!r}; choose one of {_INTERP}")


def _finish(out, src_int, dst_int_fn, conserve, squeeze):
    if conserve:
        dst = dst_int_fn(out)
        scale = np.where(dst > 0, src_int / np.where(dst > 0, dst, 1.0), 1.0)
        out = out * scale
    return out[..., 0] if squeeze else out


_METHODS = ("conservative", "gather")


def _check_method(method):
    if method not in _METHODS:
        raise IBLError(f"unknown resampling method {method!r}; choose one of {_METHODS}")


def latlong_block_reduce(img, r: int, dtype=np.float64) -> np.ndarray:
    """Exact area-weighted average of ``r × r`` texel blocks of an ``(H, 2H, C)`` lat-long map (r divides H).

    A block of rows i0 … i0+r−1 and columns j0 … j0+r−1 gets ``Σ Ω_i L_ij / Σ Ω_i`` (Ω_i the exact
    texel solid angle of row i, the same for every column), so ∫L dω of every block — hence of the map —
    is kept to rounding and constants stay exact.  Works in row blocks (float64 temporaries of
    ~``_CHUNK`` values); sums are accumulated in float64 and stored as ``dtype``.
    """
    a = np.asarray(img)
    h, w, c = a.shape
    if h % r or w % r:
        raise LayoutError(f"block reduction by {r} needs H and W divisible by {r}, got {w} x {h}")
    om = envmap.latlong_solid_angles(h, w)[:, 0]
    out = np.empty((h // r, w // r, c), dtype=dtype)
    per = max(1, _CHUNK // max(1, r * w * c))
    for b0 in range(0, h // r, per):
        b1 = min(h // r, b0 + per)
        blk = a[b0 * r : b1 * r].astype(np.float64) * om[b0 * r : b1 * r, None, None]
        num = blk.reshape(b1 - b0, r, w // r, r, c).sum(axis=(1, 3))
        out[b0:b1] = num / (om[b0 * r : b1 * r].reshape(b1 - b0, r).sum(axis=1) * r)[:, None, None]
    return out


def prereduce_factor(h: int, n: int) -> int:
    """Largest ``r`` dividing ``h`` with ``h / r ≥ 2n`` (1 if none): the block reduction applied before the
    conservative kernel when the lat-long map is finer than the cube (the reduced map keeps the cube's
    texel density at the face centres, π/(2n), and the kernel samples it with 2 × 2 sub-texels)."""
    best = 1
    for r in range(2, h // (2 * n) + 1):
        if h % r == 0:
            best = r
    return best


#: cost model of the ``conservative`` lat-long → cube resampling (:func:`latlong_to_cube_cost`): seconds and bytes
#: per kernel sub-sample and per input texel, plus a constant, fitted by least squares to ``ibl-ref convert
#: pH.exr o.exr --layout cube --size N`` (whole command: start-up, read, resample, write) for H = 256 … 2048,
#: N = H/2 and H/4 (8 runs, 2-core machine at load 1.9–3.7): 1.0–11.8 s, 68–826 MB peak; the model is within
#: 10 % of every measured time and, from H = 512 up, within 25 % of the peak memory (50 % at H = 256).
CONSERVATIVE_COST = {"s_per_sample": 2.95e-7, "s_per_texel": 9.1e-8, "s_fixed": 1.1,
                     "bytes_per_sample": 17.6, "bytes_per_texel": 19.0, "bytes_fixed": 1.0e8}


def latlong_to_cube_cost(h: int, n: int) -> dict:
    """Predicted cost of :func:`latlong_to_cube` (``conservative``, defaults) from an ``h``-row lat-long map to face
    size ``n``: ``{"samples", "seconds", "bytes"}`` (:data:`CONSERVATIVE_COST`; a lower bound where the kernel has to
    double its sub-sampling)."""
    h, n = envmap.check_face_size(h), envmap.check_face_size(n)
    hr = h // prereduce_factor(h, n)
    ks = supersample_factor(_pitch_latlong(hr), _pitch_cube(n), k_min=1 if hr >= 4 * n else 2)
    samples = hr * 2 * hr * ks * ks
    c = CONSERVATIVE_COST
    texels = 2 * h * h
    return {"samples": int(samples),
            "seconds": c["s_fixed"] + c["s_per_sample"] * samples + c["s_per_texel"] * texels,
            "bytes": c["bytes_fixed"] + c["bytes_per_sample"] * samples + c["bytes_per_texel"] * texels}


def latlong_to_cube(img, n: int, *, method: str = "conservative", k: int | None = None,
                    interpolation: str = "bilinear", conserve: bool = False, iters: int | None = None,
                    prereduce: bool = True):
    """Resample an ``(H, 2H[, C])`` lat-long map to a ``(6, n, n[, C])`` cube map (module docstring).

    Parameters
    ----------
    img : array (H, 2H) or (H, 2H, C)
    n : int
        Destination face size.
    method : {"conservative", "gather"}
        ``conservative`` (default): balanced overlap kernel (:class:`ConservativeKernel`), every source
        texel's energy is distributed; ``gather``: destination supersampling of the interpolated source.
    k : int, optional
        Sub-texels per texel edge (source texels for ``conservative``, destination texels for
        ``gather``); default :func:`supersample_factor`.
    interpolation : {"bilinear", "box"}
        Source interpolation of the ``gather`` method.
    conserve : bool
        Rescale each channel so that ∫L dω matches the source exactly.
    iters : int, optional
        Sinkhorn balancing steps of the ``conservative`` kernel (default 100; 50 above H = 1024).
    prereduce : bool
        ``conservative`` only: when H ≥ 4n, first average ``r × r`` blocks exactly
        (:func:`latlong_block_reduce`, r = :func:`prereduce_factor`: the reduced map keeps H/r ≥ 2n rows,
        the cube's texel density at the face centres), so that a big probe reduced to a smaller working
        cube costs memory of the order of the input plus the cube (the kernel of a 16384 × 8192 input
        and 2048² faces has 6 entries per texel of the 8192 × 4096 reduced map instead of 4 per input
        texel).  ∫L dω is kept exactly by the reduction.
    """
    a, squeeze = _prep(img, "lat-long map", 3, keep_float32=method == "conservative")
    h, w = a.shape[:2]
    if w != 2 * h:
        raise LayoutError(f"lat-long map must have shape (H, 2H[, C]), got {np.shape(img)}")
    _check_interp(interpolation)
    _check_method(method)
    n = envmap.check_face_size(n)
    if method == "conservative":
        from ..limits import check_allocation

        cost = latlong_to_cube_cost(h, n)  # the kernel's memory, before any of it is allocated
        check_allocation(cost["bytes"], f"resampling a {h}-row lat-long map to {n}² cube faces "
                         f"({cost['samples'] / 1e6:.0f} M kernel samples)", "face size")
        src_int = integral_latlong(a) if conserve else None
        r = prereduce_factor(h, n) if prereduce else 1
        if r > 1:
            a = latlong_block_reduce(a, r, dtype=a.dtype)
        out = _finite(conservative_kernel(a.shape[0], n, k, iters).to_cube(a))
        return _finish(out, src_int, integral_cube, conserve, squeeze)
    k = k or supersample_factor(_pitch_cube(n), _pitch_latlong(h))
    out = _to_cube(_LatLongSampler(a, interpolation), n, k, a.shape[2])
    return _finish(out, integral_latlong(a) if conserve else None, integral_cube, conserve, squeeze)


def cube_to_latlong(cube, h: int, *, method: str = "conservative", k: int | None = None,
                    interpolation: str = "bilinear", conserve: bool = False, iters: int | None = None):
    """Resample a ``(6, N, N[, C])`` cube map to an ``(h, 2h[, C])`` lat-long map.

    Parameters as :func:`latlong_to_cube`; the ``conservative`` method applies the transpose of the same
    balanced kernel (each lat-long texel is the hat-weighted average of the cube over the texel).
    """
    a, squeeze = environment_array(cube, "cube map")
    n = a.shape[1]
    _check_interp(interpolation)
    _check_method(method)
    h = envmap.check_face_size(h)
    if method == "conservative":
        out = _finite(conservative_kernel(h, n, k, iters).to_latlong(a))
    else:
        k = k or supersample_factor(_pitch_latlong(h), _pitch_cube(n))
        out = _to_latlong(_CubeSourceSampler(a, interpolation), h, k, a.shape[3])
    return _finish(out, integral_cube(a) if conserve else None, integral_latlong, conserve, squeeze)


def cube_to_cube(cube, n: int, *, k: int | None = None, interpolation: str = "bilinear", conserve: bool = False):
    """Resample a cube map to face size ``n``.

    When ``n`` divides the source size N the result is the exact area-weighted block average
    (Σ Ω_s L_s / Σ Ω_s over each block of (N/n)² texels), which conserves ∫L dω to rounding.
    """
    a, squeeze = environment_array(cube, "cube map")
    big = a.shape[1]
    _check_interp(interpolation)
    n = envmap.check_face_size(n)
    if n == big:
        out = a.copy()
    elif big % n == 0:
        r = big // n
        w = envmap.texel_solid_angles(big)
        num = (a * w[None, :, :, None]).reshape(6, n, r, n, r, -1).sum(axis=(2, 4))
        out = num / w.reshape(n, r, n, r).sum(axis=(1, 3))[None, :, :, None]
        return out[..., 0] if squeeze else out
    else:
        k = k or supersample_factor(_pitch_cube(n), _pitch_cube(big))
        out = _to_cube(_CubeSourceSampler(a, interpolation), n, k, a.shape[3])
    return _finish(out, integral_cube(a) if conserve else None, integral_cube, conserve, squeeze)


def latlong_to_latlong(img, h: int, *, k: int | None = None, interpolation: str = "bilinear"):
    """Resample a lat-long map to height ``h`` (area-weighted supersampling)."""
    a, squeeze = _prep(img, "lat-long map", 3)
    _check_interp(interpolation)
    h = envmap.check_face_size(h)
    k = k or supersample_factor(_pitch_latlong(h), _pitch_latlong(a.shape[0]))
    out = _to_latlong(_LatLongSampler(a, interpolation), h, k, a.shape[2])
    return out[..., 0] if squeeze else out


# ----------------------------------------------------------------------------------------------
# crosses and face lists
# ----------------------------------------------------------------------------------------------


def _cross_spec(layout):
    try:
        return envmap.CROSS_LAYOUTS[layout]
    except KeyError:
        raise LayoutError(f"unknown cross layout {layout!r}; choose one of {tuple(envmap.CROSS_LAYOUTS)}") from None


def cross_to_cube(img, layout: str = "hcross") -> np.ndarray:
    """Cut a horizontal (4N × 3N) or vertical (3N × 4N) cross into a ``(6, N, N[, C])`` cube map.

    Layout and face orientation: module docstring.  The result is in OpenEXR orientation.
    """
    spec = _cross_spec(layout)
    a = np.asarray(img)
    rows, cols = spec["cells"]
    if a.ndim not in (2, 3) or a.shape[0] * cols != a.shape[1] * rows or a.shape[0] % rows:
        raise LayoutError(
            f"{layout}: expected an image {cols}N wide x {rows}N high, got {a.shape[1] if a.ndim > 1 else '?'} "
            f"wide x {a.shape[0]} high"
        )
    n = a.shape[0] // rows
    faces = []
    for r, c, rot in spec["faces"]:
        f = a[r * n : (r + 1) * n, c * n : (c + 1) * n]
        faces.append(f[::-1, ::-1] if rot else f)
    return envmap.convert_convention(np.stack(faces), "opengl", "openexr")


def cube_to_cross(cube, layout: str = "hcross") -> np.ndarray:
    """Unfold an OpenEXR-oriented cube map into a cross image (inverse of :func:`cross_to_cube`)."""
    spec = _cross_spec(layout)
    n = envmap.check_cube_shape(cube)
    gl = envmap.convert_convention(np.asarray(cube), "openexr", "opengl")
    rows, cols = spec["cells"]
    out = np.zeros((rows * n, cols * n) + gl.shape[3:], dtype=gl.dtype)
    for f, (r, c, rot) in enumerate(spec["faces"]):
        out[r * n : (r + 1) * n, c * n : (c + 1) * n] = gl[f][::-1, ::-1] if rot else gl[f]
    return out


def faces_to_cube(faces, convention: str = "opengl") -> np.ndarray:
    """Stack six N × N face images (+X, −X, +Y, −Y, +Z, −Z) given in ``convention`` into an OpenEXR cube."""
    faces = [np.asarray(f) for f in faces]
    if len(faces) != 6:
        raise LayoutError(f"need 6 face images (+X, -X, +Y, -Y, +Z, -Z), got {len(faces)}")
    shapes = {f.shape for f in faces}
    if len(shapes) != 1:
        raise LayoutError(f"face images must all have the same shape, got {sorted(shapes)}")
    cube = np.stack(faces)
    envmap.check_cube_shape(cube, "face list")
    return envmap.convert_convention(cube, convention, "openexr")


def cube_to_faces(cube, convention: str = "opengl") -> list:
    """Six face images of an OpenEXR-oriented cube, re-oriented to ``convention``."""
    return list(envmap.convert_convention(np.asarray(cube), "openexr", convention))
