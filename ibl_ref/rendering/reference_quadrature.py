"""The radiance × lobe quadrature of the converged reference (Knuth et al. 2014, Eq. 4–5; the GGX term of Sec. 3.4):
block sums of ``L·weight·Ω`` over texels, with a NumPy and a compiled implementation.

:mod:`ibl_ref.rendering.reference_converged` weights each (pixel, direction cell) pair by the exact sum over the
texels of face size M that the cell holds (its module docstring, "Quadrature")::

    W_s = Σ_{t ∈ block s} L_t · weight(ω_t; n_s, v_s, d_s) · Ω_t        (C channels)
    S_s = Σ_{t ∈ block s} norm(ω_t; d_s) · Ω_t                         (a Phong lobe's normalisation, whole sphere)

where block s is the k×k texels of face size M starting at row ``r0``, column ``c0`` of face ``f``, ω_t the texel
centre's direction, Ω_t its exact solid angle (:func:`ibl_ref.environment.envmap.rect_solid_angle`) and L_t the
map's piecewise-constant radiance on that texel.  The lobe's ``weight`` and ``norm`` are defined once, by
:meth:`ibl_ref.rendering.materials.PhongLobe.weights` and :meth:`ibl_ref.rendering.materials.GGXLobe.weights`.

These sums are most of a reference render's time (a GGX render spends ≈ 85 % of it here:
``benchmarks/bench_reference_quadrature.py``), so they have two implementations of one interface,
:class:`Quadrature`, chosen like the convolution's kernels (:func:`ibl_ref.groundtruth.kernels.resolve_kernel`:
``IBL_REF_KERNEL`` = ``auto`` | ``numpy`` | ``compiled``):

``"numpy"``
    :class:`NumpyQuadrature` — array expressions through the lobe's own ``weights`` (the definition); pairs that
    share a texel block share its directions, solid angles and radiance.
``"compiled"``
    :class:`CompiledQuadrature` — one numba loop per lobe kind (:mod:`ibl_ref.rendering.reference_quadrature_loops`,
    the lobe names its loop and parameters: ``lobe.kind``, :meth:`~ibl_ref.rendering.materials.GGXLobe.loop_params`)
    that walks each block's texels without temporaries.  The same sums in float64, in another order of the
    roundings: they agree with the NumPy ones to ≈ 1e-15 relative (``tests/test_reference_quadrature.py``), far
    inside the reference's tolerances (≥ 1e-4), not bit for bit.  A render is bit-identical wherever its blocks run
    for either implementation (every process uses the one resolved by the caller).

The interface also holds the reference's per-pixel sums of cell weights, :meth:`Quadrature.sums_by` (one
``np.bincount`` per column, the definition; the compiled implementation adds every column in one pass, in the same
order), the mask of pairs that carry weight, :meth:`Quadrature.positive_rows`, and the per-environment channel
means of a sweep's weights, :meth:`Quadrature.relative_means`; :class:`CompiledQuadrature` adds
:meth:`~CompiledQuadrature.dirty_sums`, a refinement round's per-pixel sums in one pass (the NumPy implementation
leaves them to :meth:`ibl_ref.rendering.reference_converged._Block.pixel_sums`' array expressions).  All give the
same values bit for bit, so this part of a render does not depend on the implementation.
"""

from __future__ import annotations

import numpy as np

from ..environment.envmap import face_frames
from ..errors import IBLError
from ..groundtruth.kernels import resolve_kernel

__all__ = ["Quadrature", "NumpyQuadrature", "CompiledQuadrature", "QUADRATURE_METHODS", "get_quadrature", "group_means"]

#: (pair, texel) elements of one NumPy step (bounds its memory: ~30 float64 temporaries per element for GGX)
CHUNK_ELEMENTS = 1 << 18


class Quadrature:
    """The interface: ``block_sums(env, lobe, n, v, d, f, r0, c0, k, M, pix=None) -> (W (S, C), S (S,) or None)``,
    and the reference's bookkeeping :meth:`sums_by`, :meth:`positive_rows`, :meth:`relative_means`, :meth:`max_ratio`
    (defined here by their NumPy expressions).

    ``env`` is the reference's environment (``texels(f, r0, c0, k, M)`` → directions, solid angles, radiance of
    k×k blocks; ``level(M)`` → (radiance array, q) with texel (R, C) of face size M reading ``array[f, R//q,
    C//q]``); ``n, v, d`` (S, 3) the pixels' normals, view directions and lobe axes — or, with ``pix`` (S,) given,
    per-pixel arrays (P, 3) of which pair s reads row ``pix[s]`` (no gathered copies); ``f, r0, c0`` (S,) the
    blocks; ``k`` and ``M`` ints.  ``S`` is None for a lobe without a discrete normalisation (``lobe.normalised``
    False).  With ``out=(W_out, S_out)`` and ``rows`` (S,), pair s's sums go to row ``rows[s]`` of those arrays
    (``S_out`` untouched for a lobe without normalisation), which are returned.
    """

    name = ""

    def block_sums(self, env, lobe, n, v, d, f, r0, c0, k: int, M: int, pix=None, out=None,
                   rows=None):  # pragma: no cover - interface
        raise NotImplementedError

    def sums_by(self, idx, W, n: int, m=None):
        """Per index the sums of the rows of W (S, C) (× m (S,), bool or float, where given) → (n, C): column c is
        ``np.bincount(idx, weights=W[:, c] * m, minlength=n)`` (the weights added in input order), the reference's
        sums over each pixel's cells.  This is that definition; :class:`CompiledQuadrature` gives the same values
        bit for bit in one pass."""
        W = np.asarray(W)
        return np.stack([np.bincount(idx, weights=W[:, c] if m is None else W[:, c] * m, minlength=n)
                         for c in range(W.shape[1])], -1)

    def positive_rows(self, W):
        """``W.mean(axis=-1) > 0`` for weights W (S, C): the pairs that carry weight.  This is that definition;
        :class:`CompiledQuadrature` decides the rows of non-negative weights without the mean (the same mask)."""
        return W.mean(axis=-1) > 0

    def max_ratio(self, Ye, T):
        """``(Ye / T).max(axis=1)`` for Ye (S, E), T (E,): the maximum over environments of the weights relative to
        their scales, taken column by column with ``np.maximum`` (the value of the reduction: a maximum does not
        round); :class:`CompiledQuadrature` in one pass."""
        t = Ye / T
        m = t[:, 0].copy()
        for e in range(1, t.shape[1]):
            np.maximum(m, t[:, e], out=m)
        return m

    def relative_means(self, W, E: int, w):
        """Per group of C/E channels (an environment of a sweep) the mean of each row of W (S, C), divided by w (S,)
        → (S, E): ``W.reshape(S, E, C // E).mean(axis=-1) / w[:, None]`` bit for bit (:func:`group_means`);
        :class:`CompiledQuadrature` computes groups of three in one pass, in the same order."""
        Ye = group_means(W, E)
        Ye /= w[:, None]
        return Ye


class NumpyQuadrature(Quadrature):
    """The sums through the lobe's own ``weights`` (the definition), in chunks of :data:`CHUNK_ELEMENTS`; pairs
    with the same block share its texels."""

    name = "numpy"

    def block_sums(self, env, lobe, n, v, d, f, r0, c0, k: int, M: int, pix=None, out=None, rows=None):
        if out is not None:
            W, ns = self.block_sums(env, lobe, n, v, d, f, r0, c0, k, M, pix=pix)
            out[0][rows] = W
            if ns is not None:
                out[1][rows] = ns
            return out
        S = len(f)
        W = np.zeros((S, env.C))
        ns = np.zeros(S) if lobe.normalised else None
        if S == 0:
            return W, ns
        if pix is not None:
            n, v, d = n[pix], v[pix], d[pix]
        key = (f.astype(np.int64) * M + r0) * M + c0
        order = np.argsort(key, kind="stable")  # pairs of one block together: its texels once per chunk
        step = max(1, CHUNK_ELEMENTS // (k * k))
        for a0 in range(0, S, step):
            s_ = order[a0:a0 + step]
            uk, first, inv = np.unique(key[s_], return_index=True, return_inverse=True)
            b = s_[first]
            dq, oq, Lq = env.texels(f[b], r0[b], c0[b], k, int(M))
            dq, oq = dq[inv], oq[inv]
            norm, num = lobe.weights(n[s_][:, None, :], v[s_][:, None, :], d[s_][:, None, :], dq, oq)
            W[s_] = np.einsum("kt,ktc->kc", num, Lq[inv])
            if ns is not None:
                ns[s_] = norm.sum(axis=1)
        return W, ns


class CompiledQuadrature(Quadrature):
    """The sums by the lobe's numba loop (:mod:`ibl_ref.rendering.reference_quadrature_loops`)."""

    name = "compiled"

    def __init__(self):
        from . import reference_quadrature_loops as loops

        self._loops = loops.LOOPS
        self._sums_by = loops.sums_by
        self._positive_rows = loops.positive_rows
        self._relative_means3 = loops.relative_means3
        self._dirty_sums = loops.dirty_sums
        self._max_ratio = loops.max_ratio
        self._area_tables: dict = {}

    def area_table(self, M: int) -> np.ndarray:
        """This process's table of the corners' A(u, v) at face size M (:func:`~ibl_ref.rendering.
        reference_quadrature_loops._block_geometry`: (M+1)² float64, NaN until a block reads the corner; the same
        for every face), for M ≤ :data:`AREA_TABLE_MAX`; an empty array (no table) above.  Kept for the process's
        life: a block, a render and the next render read the corners computed before (each block sum evaluated
        ``atan2`` at its (k+1)² corners: for small lobes as much time as the lobe's weights)."""
        M = int(M)
        if M > AREA_TABLE_MAX:
            return _NO_TABLE
        t = self._area_tables.get(M)
        if t is None:
            t = self._area_tables[M] = np.full((M + 1) * (M + 1), np.nan)
        return t

    def dirty_sums(self, D, bp, bV, bsplit, bY, bYe, bdY, rp, rbi, rV, rY, rYe, A, q):
        """The reference's per-pixel sums of a block (:meth:`ibl_ref.rendering.reference_converged._Block.pixel_sums`:
        lit weight A and quadrature estimate q, (P, E)) recomputed in place for the pixels D, in one pass over the
        base pairs (``bp`` … ``bdY``) and the refined cells (``rp`` … ``rYe``), each sum in the order of that method's
        NumPy expressions: the same values bit for bit (the renders' tests compare both kernels)."""
        self._dirty_sums(D, np.ascontiguousarray(bp, dtype=np.int64), bV, bsplit, bY, np.ascontiguousarray(bYe),
                         np.ascontiguousarray(bdY), np.ascontiguousarray(rp, dtype=np.int64),
                         np.ascontiguousarray(rbi, dtype=np.int64), rV, rY, np.ascontiguousarray(rYe), A, q)

    def relative_means(self, W, E: int, w):
        if W.shape[1] != 3 * E:
            return super().relative_means(W, E, w)
        out = np.empty((len(W), E))
        self._relative_means3(np.ascontiguousarray(W, dtype=np.float64), np.ascontiguousarray(w, dtype=np.float64),
                              out)
        return out

    def max_ratio(self, Ye, T):
        out = np.empty(len(Ye))
        self._max_ratio(np.ascontiguousarray(Ye, dtype=np.float64), np.ascontiguousarray(T, dtype=np.float64), out)
        return out

    def positive_rows(self, W):
        code = np.empty(len(W), np.int8)
        self._positive_rows(np.ascontiguousarray(W, dtype=np.float64), code)
        if (code == 2).any():  # a row this cannot decide: the definition, for every row
            return W.mean(axis=-1) > 0
        return code == 1

    def sums_by(self, idx, W, n: int, m=None):
        out = np.zeros((n, W.shape[1]))
        if len(idx):
            m = np.zeros(0) if m is None else np.ascontiguousarray(m, dtype=np.float64)
            self._sums_by(np.ascontiguousarray(idx, dtype=np.int64), np.ascontiguousarray(W, dtype=np.float64), m,
                          out)
        return out

    def block_sums(self, env, lobe, n, v, d, f, r0, c0, k: int, M: int, pix=None, out=None, rows=None):
        S = len(f)
        if out is None:
            W, ns, rows = np.zeros((S, env.C)), np.zeros(S), np.arange(S)
        else:
            (W, ns), rows = out, np.ascontiguousarray(rows, dtype=np.int64)
        if S == 0:
            return out if out is not None else (W, (ns if lobe.normalised else None))
        pix = np.arange(S) if pix is None else np.ascontiguousarray(pix, dtype=np.int64)
        rad, q = env.level(int(M))
        f, r0, c0 = (np.ascontiguousarray(x, dtype=np.int64) for x in (f, r0, c0))
        key = (f * M + r0) * M + c0
        # the pairs of one block together; the order of the blocks and of the pairs in a block changes no sum (each
        # pair's row is its own sum over its block's texels), so NumPy's default sort (several times faster than the
        # stable one on int64)
        order = np.argsort(key)
        starts = np.flatnonzero(np.diff(key[order], prepend=-1, append=-1) != 0)  # group boundaries, and S
        self._loops[lobe.kind](np.ascontiguousarray(n, dtype=np.float64), np.ascontiguousarray(v, dtype=np.float64),
                               np.ascontiguousarray(d, dtype=np.float64), pix, order, starts, f, r0, c0, int(k), int(M),
                               np.ascontiguousarray(rad), int(q), FRAMES, lobe.loop_params(), W, ns, rows,
                               self.area_table(M))
        return out if out is not None else (W, (ns if lobe.normalised else None))


#: largest face size M whose corners' A the compiled quadrature keeps in a table (:meth:`CompiledQuadrature.area_table`:
#: (M+1)² float64, 8.4 MB at 1024; all the tables of M = n_b·2^k up to it < 4/3 of that, ≈ 11 MB per process, within
#: the measured base of :func:`ibl_ref.rendering.reference_converged.memory_bound_mb`, which does not count them;
#: 2048 would add 34 MB more for the rare lobes that reach it, which compute their corners as before)
AREA_TABLE_MAX = 1024
_NO_TABLE = np.zeros(0)

#: the face frames of the package's cube convention (:func:`ibl_ref.environment.envmap.face_frames`)
FRAMES = np.ascontiguousarray(face_frames("openexr"), dtype=np.float64)

#: the implementations, by the names of :func:`ibl_ref.groundtruth.kernels.resolve_kernel`
QUADRATURE_METHODS = {"numpy": NumpyQuadrature, "compiled": CompiledQuadrature}
_LOADED: dict = {}


def group_means(W, E: int):
    """``W.reshape(n, E, C/E).mean(axis=-1)`` (n, E) of weights W (n, C), bit for bit: for groups of three channels
    (a sweep of RGB maps) the sum ((W₀ + W₁) + W₂) / 3 written out — NumPy's mean over a short last axis adds the
    channels in their order (``tests/test_reference_exact_helpers.py`` checks the equality), and these three array
    operations are several times faster than its reduction."""
    n = len(W)
    Cg = W.shape[1] // E
    if Cg != 3:
        return W.reshape(n, E, Cg).mean(axis=-1)
    W3 = W.reshape(n, E, 3)
    s = W3[..., 0] + W3[..., 1]
    s += W3[..., 2]
    s /= 3.0
    return s


def get_quadrature(kernel=None) -> Quadrature:
    """The implementation for the switch value ``kernel`` (None: ``$IBL_REF_KERNEL`` or ``"auto"``: compiled where
    numba's JIT is available), one instance per process.

    Examples
    --------
    >>> from ibl_ref.rendering.reference_quadrature import get_quadrature
    >>> get_quadrature("numpy").name
    'numpy'
    """
    name = kernel if isinstance(kernel, str) and kernel in QUADRATURE_METHODS else resolve_kernel(kernel)
    if name not in QUADRATURE_METHODS:  # pragma: no cover - resolve_kernel returns one of them
        raise IBLError(f"unknown quadrature {name!r}")
    if name == "compiled":
        name = resolve_kernel("compiled")  # one-line error where numba's JIT is unavailable
    if name not in _LOADED:
        _LOADED[name] = QUADRATURE_METHODS[name]()
    return _LOADED[name]
