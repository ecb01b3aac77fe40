"""Resampling between lat-long maps, cube maps of any size, crosses and face lists, conserving ∫L dω.

Not a paper concept: the input plumbing every IBL tool needs.  Knuth et al. 2014 work on cube maps
(Sec. 4); environment maps are usually distributed as lat-long images or crosses.

Two methods (``method=``)
-------------------------
**conservative** (default for lat-long ↔ cube, :class:`ConservativeKernel`).  One sparse kernel
``K[t, s] ≈ ∫_S hat_t dω`` couples cube texel t and lat-long texel s: every lat-long texel S is split into
``ks × ks`` sub-texels with exact solid angles (the texels of a ``ks·H`` lat-long map) and each
sub-texel is distributed over the cube texels by their seam-aware bilinear hat functions (a partition
of unity), so Σ_t K = Ω_s exactly and Σ_s K ≈ Ω_t.  ``iters`` (100) Sinkhorn steps balance both marginals, and
the destination side is normalised exactly on application:

    lat-long → cube:  L_t = Σ_s K[t,s] L_s / Σ_s K[t,s]      cube → lat-long:  L_s = Σ_t K[t,s] L_t / Σ_t K[t,s]

Constants are reproduced exactly, and ∫L dω is conserved *per source texel* to the remaining
imbalance (measured 2e-4 to 1e-3 after 100 steps, H = 16 … 512; :attr:`ConservativeKernel.energy_error_ll`,
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
  cube: seam-aware :class:`ibl_ref.sampling.CubeSampler`), O(h²) accurate for smooth maps;
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
+Z, −Z, in the ``openexr`` or ``opengl`` face orientation (:mod:`ibl_ref.envmap`).
"""

from __future__ import annotations

import math

import numpy as np

from . import envmap
from .errors import LayoutError, check_radiance

__all__ = [
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
    "CROSS_LAYOUTS",
    "ConservativeKernel",
    "conservative_kernel",
]

_INTERP = ("bilinear", "box")
K_MAX = 16
_CHUNK = 1 << 18  # sub-samples per evaluation chunk (memory bound)


def supersample_factor(p_dst: float, p_src: float, k_max: int = K_MAX) -> int:
    """``k = clip(ceil(2·p_dst/p_src), 2, k_max)`` sub-texels per destination texel edge."""
    return int(min(max(math.ceil(2.0 * p_dst / p_src - 1e-9), 2), k_max))


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
        from .sampling import CubeSampler

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
    """Rows r0..r1-1 of :func:`ibl_ref.envmap.latlong_directions` (h, w) without building the whole grid."""
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

    Bilinear weights on the face grid padded by one texel (:func:`ibl_ref.sampling.padding_tables`,
    neighbour-face unfolding, corner texels shared by three faces); weights are ≥ 0 and sum to 1.
    """
    from .sampling import padding_tables

    face, x, y = envmap.direction_to_texel_coords(d, n)
    m = n + 2
    xp, yp = x + 1.0, y + 1.0
    x0 = np.clip(np.floor(xp), 0, m - 2).astype(np.intp)
    y0 = np.clip(np.floor(yp), 0, m - 2).astype(np.intp)
    fx, fy = np.clip(xp - x0, 0, 1), np.clip(yp - y0, 0, 1)
    base = face * m * m + y0 * m + x0
    p = np.stack([base, base + 1, base + m, base + m + 1], -1)
    wp = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1)
    src, w = padding_tables(n, 1)
    src, w = src.reshape(-1, 3), w.reshape(-1, 3)
    idx = src[p].reshape(p.shape[:-1] + (12,))
    wt = (wp[..., None] * w[p]).reshape(p.shape[:-1] + (12,))
    return idx, wt


class ConservativeKernel:
    """Overlap kernel between an ``h × 2h`` lat-long grid and an ``n``-face cube grid.

    ``K[t, s] = Σ_{sub ∈ S} ω_sub · hat_t(ω_sub)``: every lat-long texel S is split into ``ks × ks``
    sub-texels with exact solid angles ω_sub (the texels of a ``ks·h`` lat-long map), and each sub-texel
    centre is distributed over the cube texels t by the seam-aware bilinear hat functions of the cube
    grid (which sum to 1).  So Σ_t K[t, s] = Ω_s exactly and Σ_s K[t, s] ≈ Ω_t (up to the aliasing of
    the sampled hats, a few %).  Lat-long texels, which become arbitrarily small near the poles, are
    therefore never skipped: the energy of every source texel (e.g. a sun) is accounted for.

    The kernel is then balanced by ``iters`` Sinkhorn (iterative proportional fitting) steps,
    ``K ← diag(r) K diag(c)``, towards both marginals Ω_t and Ω_s, and every application normalises the
    destination side exactly:

    * lat-long → cube: ``L_t = Σ_s K[t,s] L_s / Σ_s K[t,s]`` (constants exact; ∫L dω exact up to the
      remaining column imbalance, :attr:`energy_error_ll`);
    * cube → lat-long: ``L_s = Σ_t K[t,s] L_t / Σ_t K[t,s]`` (constants exact; ∫L dω exact up to
      :attr:`energy_error_cube`).

    The residual imbalances are the worst-case relative change of ∫L dω for a map that is zero except
    in one source texel (measured 2e-4 … 1e-3 after 100 steps for H = 16 … 512).
    """

    def __init__(self, h: int, n: int, ks: int, iters: int = 100):
        import scipy.sparse as sp

        self.h, self.w, self.n, self.ks = h, 2 * h, n, ks
        w = self.w
        hk, wk = h * ks, w * ks
        om_sub = envmap.latlong_solid_angles(hk, wk)[:, 0]
        parts = []
        rows_per = max(1, _CHUNK // wk // ks) * ks  # whole lat-long rows per chunk: disjoint columns
        cols_src = np.arange(wk) // ks
        for r0 in range(0, hk, rows_per):
            r1 = min(hk, r0 + rows_per)
            d = _latlong_rows(hk, wk, r0, r1)
            idx, wt = _cube_hat_taps(d, n)
            wt = wt * om_sub[r0:r1, None, None]
            s_idx = (np.arange(r0, r1) // ks)[:, None] * w + cols_src[None, :]
            s_idx = np.broadcast_to(s_idx[..., None], idx.shape)
            keep = wt > 0
            part = sp.csr_matrix((wt[keep], (idx[keep], s_idx[keep])), shape=(6 * n * n, h * w)).tocoo()
            parts.append((part.row, part.col, part.data))  # duplicates summed within the chunk
        k_mat = sp.csr_matrix(
            (np.concatenate([q[2] for q in parts]), (np.concatenate([q[0] for q in parts]),
                                                     np.concatenate([q[1] for q in parts]))),
            shape=(6 * n * n, h * w),
        )
        self.om_t = np.broadcast_to(envmap.texel_solid_angles(n), (6, n, n)).ravel().copy()
        self.om_s = np.broadcast_to(envmap.latlong_solid_angles(h, w), (h, w)).ravel().copy()
        if np.any(np.asarray(k_mat.sum(axis=1)).ravel() <= 0):
            raise _Undersampled
        r, c = np.ones(k_mat.shape[0]), np.ones(k_mat.shape[1])
        kt = k_mat.T.tocsr()
        for _ in range(iters):  # Sinkhorn: rows -> Ω_t, columns -> Ω_s
            r = self.om_t / (k_mat @ c)
            c = self.om_s / (kt @ r)
        self.k = (sp.diags(r) @ k_mat @ sp.diags(c)).tocsr()
        self.kt = self.k.T.tocsr()
        self.row = np.asarray(self.k.sum(axis=1)).ravel()
        self.col = np.asarray(self.k.sum(axis=0)).ravel()
        # ll -> cube uses K / row: source texel s contributes Σ_t K[t,s] Ω_t / row_t instead of Ω_s
        self.energy_error_ll = float(np.abs((self.kt @ (self.om_t / self.row)) / self.om_s - 1).max())
        self.energy_error_cube = float(np.abs((self.k @ (self.om_s / self.col)) / self.om_t - 1).max())
        self.iters = iters

    def to_cube(self, img: np.ndarray) -> np.ndarray:
        flat = img.reshape(self.h * self.w, -1)
        return (self.k @ flat / self.row[:, None]).reshape(6, self.n, self.n, -1)

    def to_latlong(self, cube: np.ndarray) -> np.ndarray:
        flat = cube.reshape(6 * self.n * self.n, -1)
        return (self.kt @ flat / self.col[:, None]).reshape(self.h, self.w, -1)


class _Undersampled(Exception):
    pass


_KERNELS: dict = {}


def conservative_kernel(h: int, n: int, ks: int | None = None, iters: int = 100) -> ConservativeKernel:
    """The (cached) :class:`ConservativeKernel` between an ``h × 2h`` lat-long grid and face size ``n``.

    ``ks`` default: ``clip(ceil(2·p_latlong/p_cube), 2, 16)`` lat-long sub-texels per edge, doubled until
    every cube texel receives samples.
    """
    if ks is None:
        ks = supersample_factor(_pitch_latlong(h), _pitch_cube(n))
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


def _prep(a, what: str, ndim_img: int):
    a = np.asarray(a, dtype=np.float64)
    squeeze = a.ndim == ndim_img - 1
    if squeeze:
        a = a[..., None]
    check_radiance(a, what)
    return a, squeeze


def _check_interp(interpolation):
    if interpolation not in _INTERP:
        raise ValueError(f"unknown interpolation {interpolation!r}; choose one of {_INTERP}")


def _finish(out, src_int, dst_int_fn, conserve, squeeze):
    if conserve:
        dst = dst_int_fn(out)
        scale = np.where(dst > 0, src_int / np.where(dst > 0, dst, 1.0), 1.0)
        out = out * scale
    return out[..., 0] if squeeze else out


_METHODS = ("conservative", "gather")


def _check_method(method):
    if method not in _METHODS:
        raise ValueError(f"unknown resampling method {method!r}; choose one of {_METHODS}")


def latlong_to_cube(img, n: int, *, method: str = "conservative", k: int | None = None,
                    interpolation: str = "bilinear", conserve: bool = False, iters: int = 100):
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
    iters : int
        Sinkhorn balancing steps of the ``conservative`` kernel.
    """
    a, squeeze = _prep(img, "lat-long map", 3)
    h, w = a.shape[:2]
    if w != 2 * h:
        raise LayoutError(f"lat-long map must have shape (H, 2H[, C]), got {np.shape(img)}")
    _check_interp(interpolation)
    _check_method(method)
    n = envmap._check_face_size(n)
    if method == "conservative":
        out = _finite(conservative_kernel(h, n, k, iters).to_cube(a))
    else:
        k = k or supersample_factor(_pitch_cube(n), _pitch_latlong(h))
        out = _to_cube(_LatLongSampler(a, interpolation), n, k, a.shape[2])
    return _finish(out, integral_latlong(a) if conserve else None, integral_cube, conserve, squeeze)


def cube_to_latlong(cube, h: int, *, method: str = "conservative", k: int | None = None,
                    interpolation: str = "bilinear", conserve: bool = False, iters: int = 100):
    """Resample a ``(6, N, N[, C])`` cube map to an ``(h, 2h[, C])`` lat-long map.

    Parameters as :func:`latlong_to_cube`; the ``conservative`` method applies the transpose of the same
    balanced kernel (each lat-long texel is the hat-weighted average of the cube over the texel).
    """
    n = envmap.check_cube_shape(cube)
    a, squeeze = _prep(cube, "cube map", 4)
    _check_interp(interpolation)
    _check_method(method)
    h = envmap._check_face_size(h)
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
    big = envmap.check_cube_shape(cube)
    a, squeeze = _prep(cube, "cube map", 4)
    _check_interp(interpolation)
    n = envmap._check_face_size(n)
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
    k = k or supersample_factor(_pitch_latlong(h), _pitch_latlong(a.shape[0]))
    out = _to_latlong(_LatLongSampler(a, interpolation), envmap._check_face_size(h), k, a.shape[2])
    return out[..., 0] if squeeze else out


# ----------------------------------------------------------------------------------------------
# crosses and face lists
# ----------------------------------------------------------------------------------------------
# (cell row, cell column, rotate by 180°) of each face, faces in FACE_NAMES order, OpenGL orientation
CROSS_LAYOUTS = {
    "hcross": {"cells": (3, 4), "faces": ((1, 2, False), (1, 0, False), (0, 1, False), (2, 1, False),
                                           (1, 1, False), (1, 3, False))},
    "vcross": {"cells": (4, 3), "faces": ((1, 2, False), (1, 0, False), (0, 1, False), (2, 1, False),
                                           (1, 1, False), (3, 1, True))},
}


def _cross_spec(layout):
    try:
        return CROSS_LAYOUTS[layout]
    except KeyError:
        raise LayoutError(f"unknown cross layout {layout!r}; choose one of {tuple(CROSS_LAYOUTS)}") from None


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
