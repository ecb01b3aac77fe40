"""Seam-aware sampling of cube maps: neighbour-face padding, nearest and bilinear lookup.

A cube map is one continuous function on the sphere cut into six faces.  Everything here reads across
face borders instead of clamping at them, so lookups are continuous across all 12 edges and 8 corners
(the requirement of Knuth et al. 2014, Sec. 4: "at the edges the filter reads the neighbouring faces").

Padding (:func:`pad_faces`)
---------------------------
Each face is extended by ``k`` texels on every side; the result has shape ``(6, N+2k, N+2k, ...)``.

* **Edge strips** (beyond one face edge): the extended face plane is *unfolded* about the shared edge
  onto the neighbouring face, so the padded texel at depth ``a`` (1 = adjacent) beyond the edge is the
  neighbour's texel at depth ``a`` inside its edge, at the same position along the edge.  These are exact
  copies of neighbour texels (the usual "seamless cube map" unfolding).
* **Corner blocks** (beyond two edges, i.e. near a cube corner where only three faces meet, so there is
  no fourth face to unfold): the texel at depths ``(a, b)`` with ``a ≠ b`` takes the nearest texel of the
  direction through the padded texel's centre on the extended plane (it falls on one of the two
  neighbours); on the diagonal ``a = b`` that direction lies exactly on the seam between the two
  neighbours, and the texel is the mean of three texels: the two neighbours' texels there and the face's
  own texel at depths ``(a−1, a−1)`` from the corner.  For ``a = b = 1`` this is the mean of the three
  texels that meet at the cube corner, which makes bilinear interpolation continuous at the corner
  (all three faces then interpolate the same four values there).

Both padding modes and every lookup are fixed positive linear combinations of input texels: linear
(so Σ lookups of partial maps = lookup of the sum) and never outside the input range.

Padding is a gather with precomputed, cached index/weight tables: O(N·k) work per call.

Bilinear lookup (:class:`CubeSampler`, :func:`sample_bilinear`)
---------------------------------------------------------------
A direction is mapped to (face, x, y) with texel centres on integers (:mod:`ibl_ref.environment.envmap`) and
interpolated bilinearly on the face's *geometrically* padded grid (padded texels hold the neighbour's
interpolation at their true direction, so the grid samples the sphere where bilinear interpolation
assumes).  In the half-texel band along an edge the two faces' interpolations are blended so that both
sides compute the same value on the edge (and the three faces the same value at a corner): the lookup is
continuous everywhere on the sphere and O(h²) accurate for smooth functions, h = 2/N, also at edges and
corners (see :class:`CubeSampler`).
"""

from __future__ import annotations

import functools

import numpy as np

from . import envmap
from .envmap import check_cube_shape
from ..errors import IBLError

__all__ = ["pad_faces", "padding_tables", "CubeSampler", "sample_nearest", "sample_bilinear"]


@functools.lru_cache(maxsize=64)
def padding_tables(n: int, k: int, convention: str = "openexr"):
    """Index and weight tables of :func:`pad_faces`.

    Returns
    -------
    src : int array (6, n+2k, n+2k, 3)
        Flat indices ``face*n*n + row*n + col`` of up to three source texels.
    w : float64 array (6, n+2k, n+2k, 3)
        Their weights (sum 1).
    """
    if k < 0 or k > n:
        raise IBLError(f"padding width must be in 0..N (N={n}), got {k}")
    frames = envmap.face_frames(convention)
    m = n + 2 * k
    idx = np.arange(-k, n + k)
    f, i, j = np.meshgrid(np.arange(6), idx, idx, indexing="ij")  # (6, m, m)
    u, v = envmap.texel_coords_to_uv(j, i, n)
    out_u = (j < 0) | (j >= n)
    out_v = (i < 0) | (i >= n)

    src = np.zeros((6, m, m, 3), dtype=np.intp)
    w = np.zeros((6, m, m, 3), dtype=np.float64)

    def flat(face, row, col):
        return face * n * n + row * n + col

    # inside the face: identity
    inside = ~out_u & ~out_v
    src[inside, 0] = flat(f[inside], i[inside], j[inside])
    w[inside, 0] = 1.0

    # edge strips: unfold about the shared edge, Q = E - t * axis_f
    def unfold(sel, coord_u: bool):
        ff, uu, vv = f[sel], u[sel], v[sel]
        if coord_u:
            t = np.abs(uu) - 1.0
            e = envmap.face_uv_to_direction(ff, np.sign(uu), vv, convention, normalize=False)
        else:
            t = np.abs(vv) - 1.0
            e = envmap.face_uv_to_direction(ff, uu, np.sign(vv), convention, normalize=False)
        q = e - t[:, None] * frames[ff, 0, :]
        fq, rq, cq = envmap.direction_to_texel(q, n, convention)
        return flat(fq, rq, cq)

    sel = out_u & ~out_v
    src[sel, 0] = unfold(sel, True)
    w[sel, 0] = 1.0
    sel = out_v & ~out_u
    src[sel, 0] = unfold(sel, False)
    w[sel, 0] = 1.0

    # corner blocks
    corner = out_u & out_v
    if corner.any():
        ff, uu, vv = f[corner], u[corner], v[corner]
        ii, jj = i[corner], j[corner]
        depth_u = np.where(jj < 0, -jj, jj - n + 1)  # 1 = adjacent to the face
        depth_v = np.where(ii < 0, -ii, ii - n + 1)
        p = envmap.face_uv_to_direction(ff, uu, vv, convention, normalize=False)
        s0 = np.empty(ff.shape, dtype=np.intp)
        s1 = np.empty_like(s0)
        s2 = np.empty_like(s0)
        ww = np.zeros(ff.shape + (3,))
        off = depth_u != depth_v
        fq, rq, cq = envmap.direction_to_texel(p[off], n, convention)
        s0[off], s1[off], s2[off] = flat(fq, rq, cq), 0, 0
        ww[off, 0] = 1.0
        diag = ~off
        if diag.any():
            fd, pd, ud, vd, a = ff[diag], p[diag], uu[diag], vv[diag], depth_u[diag]
            eps = 1e-9
            q1 = pd + eps * np.sign(ud)[:, None] * frames[fd, 1, :]
            q2 = pd + eps * np.sign(vd)[:, None] * frames[fd, 2, :]
            own_col = np.where(ud < 0, a - 1, n - a)
            own_row = np.where(vd < 0, a - 1, n - a)
            s0[diag] = flat(*envmap.direction_to_texel(q1, n, convention))
            s1[diag] = flat(*envmap.direction_to_texel(q2, n, convention))
            s2[diag] = flat(fd, own_row, own_col)
            ww[diag] = 1.0 / 3.0
        src[corner] = np.stack([s0, s1, s2], axis=-1)
        w[corner] = ww
    src.setflags(write=False)
    w.setflags(write=False)
    return src, w


def pad_faces(cube: np.ndarray, k: int, convention: str = "openexr", mode: str = "unfold") -> np.ndarray:
    """Pad every face with ``k`` texels read from its neighbours (see module docstring).

    Parameters
    ----------
    cube : array (6, N, N) or (6, N, N, C)
    k : int
        Padding width in texels, 0 ≤ k ≤ N.
    mode : {"unfold", "geometric"}
        ``unfold``: padded texels are copies of the neighbours' texels (corner blocks as in the module
        docstring) — what a filter that "reads the neighbouring face" does.  ``geometric``: every padded
        texel holds the neighbour's bilinear interpolation at the true direction of the padded texel's
        centre on the extended face plane, so the padded grid samples the sphere function at exactly the
        positions a bilinear lookup assumes (O(h²) accurate, used by :class:`CubeSampler`).

    Returns
    -------
    array (6, N+2k, N+2k[, C]) of the input's dtype.
    """
    n = check_cube_shape(cube)
    cube = np.asarray(cube)
    if mode == "unfold":
        src, w = padding_tables(n, int(k), convention)
        flat = cube.reshape((6 * n * n,) + cube.shape[3:])
    elif mode == "geometric":
        src, w = _geometric_tables(n, int(k), convention)
        flat = pad_faces(cube, 1, convention, "unfold")
        flat = flat.reshape((6 * (n + 2) * (n + 2),) + cube.shape[3:])
    else:
        raise IBLError(f"unknown padding mode {mode!r}; choose 'unfold' or 'geometric'")
    if cube.ndim == 3:
        out = (flat[src] * w).sum(axis=-1)
    else:
        out = np.einsum("...kc,...k->...c", flat[src], w)
    return out.astype(cube.dtype, copy=False)


def _bilinear_taps(face, x, y, n: int, pad: int):
    """Flat indices (…, 4) into a ``pad``-padded cube and bilinear weights (…, 4) at texel coords x, y."""
    m = n + 2 * pad
    xp = np.asarray(x, dtype=np.float64) + pad
    yp = np.asarray(y, dtype=np.float64) + pad
    x0 = np.clip(np.floor(xp), 0, m - 2).astype(np.intp)
    y0 = np.clip(np.floor(yp), 0, m - 2).astype(np.intp)
    fx = np.clip(xp - x0, 0.0, 1.0)
    fy = np.clip(yp - y0, 0.0, 1.0)
    base = face * m * m + y0 * m + x0
    idx = np.stack([base, base + 1, base + m, base + m + 1], axis=-1)
    w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=-1)
    return idx, w


def _extended_coords(d, face, n: int, convention: str):
    """Texel coordinates of directions ``d`` on the (extended) plane of ``face``."""
    frames = envmap.face_frames(convention)
    fr = frames[face]
    along = np.einsum("...i,...i->...", d, fr[..., 0, :])
    u = np.einsum("...i,...i->...", d, fr[..., 1, :]) / along
    v = np.einsum("...i,...i->...", d, fr[..., 2, :]) / along
    return envmap.uv_to_texel_coords(u, v, n)


@functools.lru_cache(maxsize=64)
def _geometric_tables(n: int, k: int, convention: str = "openexr"):
    """Tables of ``pad_faces(mode="geometric")``: up to 4 taps into the 1-unfold-padded cube.

    Edge-strip texels: the 4 bilinear taps of the neighbour face at the padded texel's true direction.
    Corner blocks: the texel adjacent to the cube corner (depths (1, 1)) sees a direction on the seam
    between the two neighbours, between the pair of the neighbours' corner texels (mirror images across
    the seam) and the next pair along the seam; it takes the linear interpolation along the seam between
    the two pairs' midpoints (positive weights, exact for functions linear in position up to the
    sphere's curvature, hence O(h²)).  Deeper corner-block texels — read
    by lookups only with O(h) weight — take the nearest texel of their direction.  Every value is a
    fixed positive linear combination of input texels, so padding (and :class:`CubeSampler`) is linear
    and never leaves the input's range.
    """
    if k < 0 or k > n:
        raise IBLError(f"padding width must be in 0..N (N={n}), got {k}")
    frames = envmap.face_frames(convention)
    mp = n + 2
    idx = np.arange(-k, n + k)
    f, i, j = np.meshgrid(np.arange(6), idx, idx, indexing="ij")
    u, v = envmap.texel_coords_to_uv(j, i, n)
    d = envmap.face_uv_to_direction(f, u, v, convention, normalize=False)
    out_u = (j < 0) | (j >= n)
    out_v = (i < 0) | (i >= n)
    corner = out_u & out_v
    face_d, _, _ = envmap.direction_to_face_uv(d, convention)
    face_d = np.where(corner, f, np.where(out_u | out_v, face_d, f))
    x, y = _extended_coords(d, face_d, n, convention)
    x = np.where(corner, np.clip(x, 0, n - 1), x)
    y = np.where(corner, np.clip(y, 0, n - 1), y)
    src, w = _bilinear_taps(face_d, x, y, n, 1)  # (6, m, m, 4) into the 1-padded cube
    src, w = src.copy(), w.copy()

    def padded_index(face, row, col):
        return face * mp * mp + (row + 1) * mp + (col + 1)

    centres = envmap.texel_directions(n, convention)
    for fc, ic, jc in zip(*np.nonzero(corner)):
        du = -idx[jc] if idx[jc] < 0 else idx[jc] - n + 1
        dv = -idx[ic] if idx[ic] < 0 else idx[ic] - n + 1
        su = -1.0 if idx[jc] < 0 else 1.0
        sv = -1.0 if idx[ic] < 0 else 1.0
        p = d[fc, ic, jc]
        if du == 1 and dv == 1:
            # p lies on the seam between the neighbours B (across u) and C (across v), just beyond the
            # pair of corner texels (B_c, C_c) — mirror images across the seam — and before the next
            # pair (B_c2, C_c2) along the seam: interpolate linearly along the seam between the pairs.
            kc = frames[fc, 0] + su * frames[fc, 1] + sv * frames[fc, 2]  # the cube corner
            away = kc - (3.0 / n) * frames[fc, 0]  # 1.5 texels along the seam, away from the corner
            ax_b, ax_c = su * frames[fc, 1], sv * frames[fc, 2]
            taps = [envmap.direction_to_texel(q + 1e-9 * ax, n, convention)
                    for q in (kc, away) for ax in (ax_b, ax_c)]
            c4 = np.array([centres[t] for t in taps])
            m1, m2 = c4[:2].mean(axis=0), c4[2:].mean(axis=0)
            pn = p / np.linalg.norm(p)
            t_seam = float(np.clip((pn - m1) @ (m2 - m1) / ((m2 - m1) @ (m2 - m1)), 0.0, 1.0))
            src[fc, ic, jc] = [padded_index(*t) for t in taps]
            w[fc, ic, jc] = [(1 - t_seam) / 2, (1 - t_seam) / 2, t_seam / 2, t_seam / 2]
        else:
            # nearest texel of the direction; exact diagonal ties go to the u-side neighbour
            t = envmap.direction_to_texel(p + 1e-9 * su * frames[fc, 1], n, convention)
            src[fc, ic, jc] = padded_index(*t)
            w[fc, ic, jc] = [1.0, 0.0, 0.0, 0.0]
    for arr in (src, w):
        arr.setflags(write=False)
    return src, w


class CubeSampler:
    """Nearest and seam-aware bilinear lookups in one cube map (pads once, samples many times).

    Bilinear lookup: inside a face (between texel centres) it is plain bilinear interpolation on the
    face's geometrically padded grid (:func:`pad_faces` ``mode="geometric"``).  In the half-texel band
    along an edge the face's own interpolation ``V_A`` is blended with the neighbour's ``V_B`` (the
    neighbour's bilinear interpolation, on its own extended plane, at the same direction) with weights
    ``1 − f`` and ``f``, ``f`` ∈ [0, ½] the distance beyond the last texel centre in texels; in a corner
    cell the tensor-product weights of the two edges are used and the weight of the missing fourth face
    is shared equally by the three.  At an edge every side therefore computes the same ½/½ blend, and at
    a corner the same ⅓/⅓/⅓ blend: the lookup is continuous on the whole sphere, and since every
    ``V_F`` is an O(h²) interpolation of the sphere function, so is the blend.

    Parameters
    ----------
    cube : array (6, N, N) or (6, N, N, C)
    convention : {"openexr", "opengl"}
    """

    _PAD = 2

    def __init__(self, cube: np.ndarray, convention: str = "openexr"):
        self.n = check_cube_shape(cube)
        self.cube = np.asarray(cube)
        self.convention = convention
        # 2 texels of padding cover the extended-plane reads of the seam blend; a 1x1 face has only 1
        self._pad = min(self._PAD, self.n)
        self.padded = pad_faces(self.cube, self._pad, convention, mode="geometric")
        m = self.n + 2 * self._pad
        self._flat = self.padded.reshape((6 * m * m,) + self.cube.shape[3:])

    def nearest(self, dirs) -> np.ndarray:
        """Value of the texel containing each direction; shape ``dirs.shape[:-1] + (C,)``."""
        face, row, col = envmap.direction_to_texel(dirs, self.n, self.convention)
        return self.cube[face, row, col]

    def _interp(self, face, x, y):
        idx, w = _bilinear_taps(face, x, y, self.n, self._pad)
        vals = self._flat[idx]
        if self.cube.ndim == 4:
            return np.einsum("...kc,...k->...c", vals, w)
        return (vals * w).sum(axis=-1)

    def bilinear(self, dirs) -> np.ndarray:
        """Seam-aware, continuous bilinear interpolation of texel-centre values at each direction."""
        n = self.n
        frames = envmap.face_frames(self.convention)
        d = envmap.as_directions(dirs)
        lead = d.shape[:-1]
        d = d.reshape(-1, 3)
        face, x, y = envmap.direction_to_texel_coords(d, n, self.convention)
        out = self._interp(face, x, y)
        fx = np.maximum(np.maximum(x - (n - 1), -x), 0.0)  # distance beyond the last texel centre
        fy = np.maximum(np.maximum(y - (n - 1), -y), 0.0)
        band = (fx > 0) | (fy > 0)
        if np.any(band):
            db, fb, xb, yb = d[band], face[band], x[band], y[band]
            fxb, fyb = fx[band], fy[band]
            # the neighbours across the u edge (B) and the v edge (C)
            side_u = np.where(xb < 0, -1.0, 1.0)[:, None] * frames[fb, 1, :]
            side_v = np.where(yb < 0, -1.0, 1.0)[:, None] * frames[fb, 2, :]
            face_b, _, _ = envmap.direction_to_face_uv(side_u, self.convention)
            face_c, _, _ = envmap.direction_to_face_uv(side_v, self.convention)
            corner = fxb * fyb / 3.0
            w_a = (1 - fxb) * (1 - fyb) + corner
            w_b = fxb * (1 - fyb) + corner
            w_c = (1 - fxb) * fyb + corner
            nc = (1,) * (self.cube.ndim - 3)  # a trailing channel axis, if any
            res = w_a.reshape(w_a.shape + nc) * out[band]
            # each neighbour is evaluated only where its weight is non-zero (elsewhere the direction may
            # be parallel to that neighbour's plane)
            for w_n, face_n in ((w_b, face_b), (w_c, face_c)):
                sel = w_n > 0
                if np.any(sel):
                    val = self._interp(face_n[sel], *_extended_coords(db[sel], face_n[sel], n, self.convention))
                    res[sel] += w_n[sel].reshape((-1,) + nc) * val
            out[band] = res
        out = out.reshape(lead + self.cube.shape[3:])
        return out.astype(np.result_type(self.cube.dtype, np.float32), copy=False)


def sample_nearest(cube, dirs, convention: str = "openexr") -> np.ndarray:
    """Nearest-texel lookup of ``cube`` at directions ``dirs`` (..., 3)."""
    n = check_cube_shape(cube)
    face, row, col = envmap.direction_to_texel(dirs, n, convention)
    return np.asarray(cube)[face, row, col]


def sample_bilinear(cube, dirs, convention: str = "openexr") -> np.ndarray:
    """Seam-aware bilinear lookup (see :class:`CubeSampler`; build one to sample a map repeatedly)."""
    return CubeSampler(cube, convention).bilinear(dirs)
