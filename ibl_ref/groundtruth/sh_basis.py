"""Real spherical harmonics on cube-map texel grids, with the grid's reflection symmetries (Funk–Hecke part
of the SH Phong-lobe convolution, Knuth et al. 2014 Sec. 3.2 Eq. 4; theory in :mod:`ibl_ref.groundtruth.sh_convolution`).

* :func:`real_sh`, :func:`sh_project`, :func:`sh_evaluate` — the real orthonormal SH basis (no Condon–Shortley
  phase; index ``l² + l + m``) from the fully normalised associated Legendre recurrences, a cube map's discrete
  projection ``a_lm = Σ_j L_j Y_lm(ω_j) Ω_j`` and the evaluation of a coefficient vector.
* :func:`sh_lobe_convolve` — ``Σ_l k_l Σ_m a_lm Y_lm(r)`` for several zonal kernels at once: the SH matrix in
  chunks of ≈ 128 MB, mirror pairs under z → −z (parity ``(−1)^{l+m}``) and, for grids symmetric under all
  three sign flips (every even-sized cube grid), only the positive octant (each SH row changes sign or not under
  each flip; :func:`_octant_row_classes`), one eighth of the matrix.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ..environment import envmap
from .convolution_args import check_cube
from ..errors import IBLError, LayoutError
from .sh_tables import _layout, _recurrence_coeffs, _row_layout

__all__ = ["real_sh", "sh_project", "sh_evaluate", "sh_lobe_convolve", "NumpySH", "NUMPY_SH"]

_FOUR_PI = 4.0 * np.pi

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


def _std_index(rows):
    return np.array([ell * ell + ell + (m if kind == "c" else -m) for ell, m, kind in rows], dtype=int)


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


@functools.lru_cache(maxsize=8)
def _grid_orbits(n):
    """:func:`_octant_orbits` of the texel directions of face size n (cached; read-only)."""
    orb = _octant_orbits_of(envmap.texel_directions(n).reshape(-1, 3))
    if orb is not None:
        orb.flags.writeable = False
    return orb


def _octant_orbits(dirs):
    """:func:`_octant_orbits_of`, taken from a per-size cache when ``dirs`` are the (cached) texel directions of a
    cube grid."""
    d = np.asarray(dirs)
    M = d.shape[0] if d.ndim == 2 else 0
    n = int(round(math.sqrt(M / 6))) if M else 0
    if n and 6 * n * n == M:
        grid = envmap.texel_directions(n)
        if d.base is grid or d is grid or (d.base is not None and d.base is grid.base):
            return _grid_orbits(n)
    return _octant_orbits_of(d)


def _octant_orbits_of(dirs):
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


def _evaluate_octant_values(dirs, Be, Bo, L, orb, chunks=None, blas_combine=False):
    """Values of :func:`_evaluate_octant` at the directions of the orbits ``orb`` only: ``(idx, vals)`` with
    ``vals[i]`` the value at ``dirs[idx[i]]`` (``idx = orb.T.ravel()``).  ``blas_combine``: the characters combined
    by one matrix product instead of ``einsum`` (the compiled path; the same sums of 8 terms in another order)."""
    cls = _octant_row_classes(L)
    n_oct = orb.shape[0]
    V = np.zeros((8, n_oct, Be.shape[1]))
    reps = dirs[orb[:, 0]]
    for i0, i1, Yk in chunks if chunks is not None else _octant_Y_chunks(reps, L):
        for kappa in range(8):
            rows = cls[kappa // 4][kappa % 4]
            if rows.size:
                V[kappa, i0:i1] = Yk[kappa].T @ (Be if kappa < 4 else Bo)[rows]
    if blas_combine:
        vals = (_walsh8() @ V.reshape(8, -1)).reshape(V.shape)
    else:
        vals = np.einsum("kg,kop->gop", _walsh8(), V)  # (8, n_oct, P)
    return orb.T.reshape(-1), vals.reshape(-1, Be.shape[1])


def _evaluate_octant(dirs, Be, Bo, L, orb, chunks=None):
    """:func:`_evaluate` for an octant-symmetric set: ``f(σ_g r) = Σ_κ χ_κ(g) Y_κ(r)ᵀ B_κ``."""
    idx, vals = _evaluate_octant_values(dirs, Be, Bo, L, orb, chunks)
    out = np.empty((dirs.shape[0], Be.shape[1]))
    out[idx] = vals
    return out


def _project(dirs, W, L):
    """a = Σ_j W_j Y(ω_j) in :func:`_row_layout` order: (a_even, a_odd) (octant orbits, else z-mirror pairs:
    :class:`SymmetryPlan` with one part)."""
    return project_part(dirs, W, SymmetryPlan(dirs, L, 1), 0)


def _evaluate(dirs, Be, Bo, L):
    idx, vals = evaluate_part(dirs, Be, Bo, SymmetryPlan(dirs, L, 1), 0)
    out = np.empty((dirs.shape[0], Be.shape[1]))
    out[idx] = vals
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


def funk_hecke(kernel_coeffs, ae, ao):
    """``c_l a_lm`` for every kernel (Funk–Hecke), the (even, odd) coefficients ``ae``, ``ao`` (rows, Q) of a
    projection: ``(Be, Bo)`` (rows, K·Q), kernel-major columns, ready for one evaluation pass."""
    kc = np.atleast_2d(kernel_coeffs)
    K, Q = kc.shape[0], ae.shape[1]
    ev_l, od_l = _row_layout(kc.shape[1] - 1)
    Be = (kc[:, ev_l, None] * ae[None]).transpose(1, 0, 2).reshape(-1, K * Q)
    Bo = (kc[:, od_l, None] * ao[None]).transpose(1, 0, 2).reshape(-1, K * Q)
    return Be, Bo


def sh_lobe_convolve(src_dirs, weights, out_dirs, kernel_coeffs, kernels=None) -> np.ndarray:
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
    kernels : object with the SH passes of :class:`ibl_ref.groundtruth.kernels.Kernels`, optional
        The backend of the octant-symmetric passes (default :data:`NUMPY_SH`, the SH matrix in chunks and BLAS
        products; the compiled backend generates the SH values block by block, without the matrix)

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
    kernels = kernels or NUMPY_SH
    same = src is dst or (src.shape == dst.shape and np.array_equal(src, dst))
    sym_s = SymmetryPlan(src, L, 1)
    sym_d = sym_s if same else SymmetryPlan(dst, L, 1)
    # same directions in and out (output size = input size): the SH matrix built once, where it fits
    chunks = kernels.sh_shared_chunks(src, sym_s) if same else None
    ae, ao = project_part(src, W, sym_s, 0, kernels, chunks)
    Be, Bo = funk_hecke(kc, ae, ao)
    idx, vals = evaluate_part(dst, Be, Bo, sym_d, 0, kernels, chunks)
    out = np.empty((dst.shape[0], Be.shape[1]))
    out[idx] = vals
    return out.reshape(-1, K, Q).transpose(1, 0, 2)


class NumpySH:
    """The SH passes of the kernel interface (:class:`ibl_ref.groundtruth.kernels.Kernels`) over octant-symmetric
    direction sets, in NumPy: the SH matrix in chunks (:func:`_octant_Y_chunks`) and BLAS products.  ``orb``: the
    octant orbits of the directions to use (:class:`SymmetryPlan`); ``chunks``: the SH matrix of those orbits'
    representatives, when the caller has it already (:meth:`sh_shared_chunks`)."""

    def sh_shared_chunks(self, dirs, sym):
        """The SH matrix of an octant-symmetric set's representatives, once for a projection and an evaluation of
        the same directions (None: not octant-symmetric, or above 256 MB)."""
        if sym.kind != "octant" or sym.orb.shape[0] * (sym.L + 1) ** 2 > _SH_CACHE_ELEMS:
            return None
        return list(_octant_Y_chunks(dirs[sym.orb[:, 0]], sym.L))

    def sh_project_octant(self, dirs, W, L, orb, chunks=None):
        """``(a_even, a_odd)``: the projection ``Σ_j W_j Y(ω_j)`` over the octant orbits ``orb``."""
        return _project_octant(dirs, W, L, orb, chunks)

    def sh_octant_values(self, dirs, Be, Bo, L, orb, chunks=None):
        """``(idx, vals)``: the evaluation of ``(Be, Bo)`` at the directions of the orbits ``orb``."""
        return _evaluate_octant_values(dirs, Be, Bo, L, orb, chunks)


#: the NumPy SH passes (the default backend of :func:`sh_lobe_convolve` and the part functions)
NUMPY_SH = NumpySH()


# ----------------------------------------------------------------------------------------------
# the same passes in independent parts (for parallel jobs)
# ----------------------------------------------------------------------------------------------
class SymmetryPlan:
    """The symmetry used for one direction set and its split into ``n_parts`` fixed pieces of work.

    ``kind`` is ``"octant"`` (orbits ``orb`` (M/8, 8) of :func:`_octant_orbits`) or ``"mirror"`` (``h``,
    ``mir`` of :func:`_mirror_pairs`, or every direction in ``h`` when the set is not z-symmetric).  Part
    ``i`` holds a contiguous range of orbit representatives (or of ``h``), cut at multiples of the SH chunk
    (:func:`_chunk`), so every part evaluates whole chunks of the serial pass.  The split depends only on
    the directions, L and ``n_parts`` (never on a worker count).
    """

    def __init__(self, dirs, L: int, n_parts: int):
        if n_parts < 1:
            raise IBLError(f"n_parts must be >= 1, got {n_parts}")
        self.L = int(L)
        self.n_parts = int(n_parts)
        self.orb = _octant_orbits(dirs)
        if self.orb is not None:
            self.kind = "octant"
            n_units = self.orb.shape[0]
        else:
            self.kind = "mirror"
            pairs = _mirror_pairs(dirs)
            if pairs is None:
                self.h, self.mir = np.arange(dirs.shape[0]), np.zeros(0, dtype=np.intp)
            else:
                self.h, self.mir = pairs
            n_units = self.h.size
        ch = _chunk(self.L)
        n_chunks = -(-n_units // ch)
        cuts = [min(n_units, ch * ((n_chunks * i) // self.n_parts)) for i in range(self.n_parts + 1)]
        self.ranges = [(cuts[i], cuts[i + 1]) for i in range(self.n_parts)]


def project_part(dirs, W, sym: SymmetryPlan, part: int, kernels=None, chunks=None):
    """Part ``part`` of the projection ``a = Σ_j W_j Y(ω_j)`` (:func:`_project`): ``(a_even, a_odd)``
    summed over that part's directions only.  The parts of a :class:`SymmetryPlan` add up to the whole
    projection (up to the order of the float64 sums).  Octant-symmetric sets by ``kernels``' SH passes
    (default :data:`NUMPY_SH`; ``chunks``: :meth:`NumpySH.sh_shared_chunks` of a one-part plan)."""
    L = sym.L
    u0, u1 = sym.ranges[part]
    if sym.kind == "octant":
        return (kernels or NUMPY_SH).sh_project_octant(dirs, W, L, sym.orb[u0:u1], chunks)
    ev_l, od_l = _row_layout(L)
    ae = np.zeros((ev_l.size, W.shape[1]))
    ao = np.zeros((od_l.size, W.shape[1]))
    h, mir = sym.h, sym.mir
    ch = _chunk(L)
    for i0 in range(u0, u1, ch):
        i1 = min(u1, i0 + ch)
        idx = h[i0:i1]
        Wm = np.zeros((idx.size, W.shape[1]))
        k = max(0, min(mir.size - i0, idx.size))  # the first k of this chunk have mirrors
        Wm[:k] = W[mir[i0 : i0 + k]]
        Ye, Yo = _real_sh_parity(dirs[idx], L)
        ae += Ye @ (W[idx] + Wm)
        ao += Yo @ (W[idx] - Wm)
    return ae, ao


def evaluate_part(dirs, Be, Bo, sym: SymmetryPlan, part: int, kernels=None, chunks=None):
    """Part ``part`` of the evaluation (:func:`_evaluate`): ``(idx, vals)``, the values at ``dirs[idx]``
    (``kernels``, ``chunks``: as :func:`project_part`)."""
    L = sym.L
    u0, u1 = sym.ranges[part]
    if sym.kind == "octant":
        return (kernels or NUMPY_SH).sh_octant_values(dirs, Be, Bo, L, sym.orb[u0:u1], chunks)
    h, mir = sym.h, sym.mir
    ch = _chunk(L)
    idx_all, val_all = [], []
    for i0 in range(u0, u1, ch):
        idx = h[i0 : min(u1, i0 + ch)]
        Ye, Yo = _real_sh_parity(dirs[idx], L)
        ve = Ye.T @ Be
        vo = Yo.T @ Bo
        idx_all.append(idx)
        val_all.append(ve + vo)
        k = max(0, min(mir.size - i0, idx.size))
        if k:
            idx_all.append(mir[i0 : i0 + k])
            val_all.append(ve[:k] - vo[:k])
    if not idx_all:
        return np.zeros(0, dtype=np.intp), np.zeros((0, Be.shape[1]))
    return np.concatenate(idx_all), np.concatenate(val_all)
