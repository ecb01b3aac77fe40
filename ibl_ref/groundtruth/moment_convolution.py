"""Hierarchical moment convolution of a cube map with broad Phong lobes (Knuth et al. 2014, Sec. 3.2, Eq. 4).

For an integer exponent ``s ∈ {1, 2}`` the kernel ``max(r·ω, 0)^s`` equals the polynomial ``(r·ω)^s``
wherever ``r·ω ≥ 0``.  So a block ``b`` of source texels lying entirely in the positive hemisphere of
``r`` contributes EXACTLY (Eq. 4 restricted to the block)

    s = 1:  Σ_{j∈b} L_j Ω_j (r·ω_j)     = r · M_b^(1),           M_b^(1) = Σ L_j Ω_j ω_j
    s = 2:  Σ_{j∈b} L_j Ω_j (r·ω_j)^2   = r^T M_b^(2) r,         M_b^(2) = Σ L_j Ω_j ω_j ω_j^T

and a block entirely in the negative hemisphere contributes 0.  Blocks are the nodes of a quadtree per
face (texel-centre bounding cones ``(c_b, α_b)``); output texels are grouped in ``t×t`` tiles with
cones ``(c_T, β_T)``.  A (tile, block) pair is positive for every ``r`` in the tile when
``∠(c_T, c_b) + β_T + α_b ≤ π/2`` and negative when ``∠(c_T, c_b) − β_T − α_b ≥ π/2``; otherwise the
block is split, down to the leaf size ``leaf``.  The straddling leaf blocks (a band around each
tile's horizon) are handled per output texel:

``leaf = 1`` (default)
    exact gather of those texels (``max(r·ω_j,0)^s`` at the texel centres; the split stops at blocks
    of ``gather`` texels, whose texels are all gathered): the result equals the exact lobe average up
    to float64 rounding.  Measured (2-core machine, 1 BLAS thread): s = 1 and 2 together at 128² faces
    3.4 s CPU in one call vs ≈ 54 s per exponent for the dense gather (extrapolated in
    ``ibl-ref experiment speed-accuracy``); max relative difference to
    :func:`ibl_ref.groundtruth.phong_convolution.convolve_exact_many` 1.9e-14 at 64² (sky + 1e5 sun near a cube
    corner, ``benchmarks/bench_convolution.py``).  Its band holds O(N) texels per output texel, so its
    cost grows as N³ (4.2 s CPU per output face at 256², ≈ 8× that at 512²).
``leaf > 1``
    linear brackets of the kernel per (output texel, straddling leaf block), see :func:`_band_brackets`:
    with ``x = r·ω ∈ [x_lo, x_hi]`` on the block (from its cone) and ``A = x_hi/(x_hi − x_lo)``,

        s = 1:  A x  ≤  max(x,0)   ≤  A x − A x_lo          (a line through 0 below, the chord above)
        s = 2:  a x − a²/4  ≤  max(x,0)²  ≤  a (x − x_lo),   a = x_hi²/(x_hi − x_lo)   (tangent, chord)

    so the block's contribution lies in an interval whose ends are linear in ``W = Σ L Ω`` and
    ``r·M_b^(1)``: midpoint and half-width accumulate by matrix products, and a block on the positive
    side of this texel (``x_lo ≥ 0``) is exact.  The half-width is ≤ ``W sin α / 4`` (s = 1), so the
    band's error is ≈ 2 L sin² α in total, independent of N for a fixed cone angle α: the leaf grows with
    N (:func:`moment_leaf`, leaf/N = 1/64 at rtol 1e-3) and the band keeps O(1/α) blocks per output texel
    instead of O(N) texels.  Texels brighter than ``bright_factor`` × the solid-angle-weighted mean
    luminance (e.g. a sun) are left out of the leaf blocks' interval moments and gathered exactly where
    their leaf block straddles (they stay in the exact moments of positive blocks).  With ``rtol``, the
    output tiles whose bound exceeds it are done again with half the leaf (down to 2).  Measured (one
    output face, s = 1 and 2, sky + 1e5 sun, shared machine at load 8–10, ``/tmp``-script timings with 1
    BLAS thread): 256², leaf 4: 2.5 s CPU (exact band 4.2 s), bound ≤ 3.9e-4 on face +X (1.8e-3 on the
    ground face −Y, whose tiles the refinement redoes); 512², leaf 8: 7.1 s CPU, bound 5.7e-4, max error
    4.6e-5.  The bound held at every checked texel (tests compare with the exact gather); observed
    max error / bound 0.2–0.5 (bound 2–26× the worst error, the larger ratios on tiny maps).

Memory.  The output tiles are processed in chunks of :func:`moment_tiles_per_chunk` tiles, so that
one chunk's (tile, texel) band pairs stay below :data:`MOMENT_CHUNK_PAIRS`; the chunks depend only on
the sizes (never on the worker count).  Peak memory then grows with the source moments and the
output, not with the band.  With ``leaf > 1`` no per-texel moment arrays are built (the leaf moments
come from one small matrix product per block, :func:`_leaf_moments`): estimate
:func:`moment_peak_bytes` 0.69 GB per one-face job at 512², 1.7 GB at 1024².

The per-texel bound returned is ``max(approx − lo, hi − approx)/lo`` on the relative error (max over
channels) plus :data:`ROUNDING_REL` for float64 rounding of the sums.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..environment import envmap
from ..errors import IBLError
from .convolution_args import channel_max, check_cube, check_faces, check_out_size
from .kernels import check_impl, get_kernels
from .kernels.numpy_backend import MOMENT_CHUNK_PAIRS, SYM_PAIRS, quad_children

__all__ = ["convolve_moment_many", "convolve_moment", "moment_leaf", "SUPPORTED_EXPONENTS", "ROUNDING_REL"]

#: exponents with an exact polynomial moment representation implemented here
SUPPORTED_EXPONENTS = (1.0, 2.0)
#: relative allowance added to every bound for float64 rounding of sums over ≤ 6N² non-negative terms
ROUNDING_REL = 1e-12
#: angular safety margin (rad) added to every cone half-angle (arccos rounding)
_ANGLE_EPS = 1e-9
#: diagnostics of the last call (stage times, number of band pairs)
LAST_INFO: dict = {}


def _cones(dirs, real, b):
    """Bounding cones of b×b blocks of a padded (6,P,P,3) direction grid; returns (centres, half-angles, valid)."""
    P = dirs.shape[1]
    m = P // b
    d = np.where(real[..., None], dirs, 0.0).reshape(6, m, b, m, b, 3)
    c = d.sum(axis=(2, 4))
    nrm = np.linalg.norm(c, axis=-1)
    valid = real.reshape(6, m, b, m, b).any(axis=(2, 4))
    c = c / np.where(nrm > 0, nrm, 1.0)[..., None]
    cb = np.broadcast_to(c[:, :, None, :, None, :], d.shape)
    dots = np.einsum("...k,...k->...", d, cb)
    dots = np.where(real.reshape(6, m, b, m, b), dots, 1.0).min(axis=(2, 4))
    alpha = np.arccos(np.clip(dots, -1.0, 1.0)) + _ANGLE_EPS
    return c.reshape(-1, 3), alpha.ravel(), valid.ravel()


def _block_sums(x, b):
    """Sum a padded (6,P,P,K) array over b×b blocks → (6·(P/b)², K)."""
    P = x.shape[1]
    m = P // b
    return x.reshape(6, m, b, m, b, x.shape[-1]).sum(axis=(2, 4)).reshape(6 * m * m, x.shape[-1])


def _kernel(x, s):
    x = np.maximum(x, 0.0)
    return x if s == 1.0 else x * x




def moment_band_pairs_per_tile(n: int, out_size: int, tile: int, stop: int, leaf: int = 1) -> float:
    """Estimate of the (tile, texel) pairs of one output tile's horizon band at the gather level.

    A tile of ``tile``² output texels (cone half-angle β ≈ tile·Δ_out/√2, Δ = π/(2·size) the texel angle
    at a face centre) straddles every block of ``stop``² source texels (half-angle α ≈ stop·Δ_src/√2)
    within β + α of its horizon: a band of solid angle ≈ 2π·2(β + α) holding that / (4π/(6m²)) blocks of
    ``stop²`` texels (m = n/stop blocks per face side).  Used only to size the chunks (measured: 3–8× the
    pairs left after the per-texel test at 32²–128²; the ×2 in w covers the non-uniform texel density).
    With ``leaf > 1`` the band's pairs are (tile, leaf block) pairs (``stop = leaf``), one per block instead
    of ``stop²`` (counting texels there cut the chunks to 1–4 tiles at 512²–1024², whose per-chunk Python
    work then dominated: one output face of 1024², s = 1 and 2, 16 384 chunks; measured: 2.2× the pairs left
    at 512², leaf 8).
    """
    d_out, d_src = math.pi / (2 * out_size), math.pi / (2 * n)
    w = 2.0 * (tile * d_out + stop * d_src) / math.sqrt(2.0) * 2.0
    m = max(n / stop, 1.0)
    return 3.0 * w * m * m * (stop * stop if leaf == 1 else 1)


def moment_tiles_per_chunk(n: int, out_size: int, tile: int, stop: int, pairs: int = MOMENT_CHUNK_PAIRS,
                           leaf: int = 1) -> int:
    """Output tiles per chunk of :func:`convolve_moment_many`: the band working set ≤ ``pairs``
    (:data:`MOMENT_CHUNK_PAIRS`)."""
    return max(1, int(pairs // max(moment_band_pairs_per_tile(n, out_size, tile, stop, leaf), 1.0)))


#: the bracket band (``leaf > 1``) is used by :func:`moment_leaf` only from this leaf size on: at leaf 2
#: it is no faster than the exact band (128², s = 1 and 2: 6.1–7.0 s vs 3.5 s CPU; leaf 4 at 256², one
#: output face: 2.5 s vs 4.2 s; leaf 8 at 512²: 7.1 s per face)
MIN_BRACKET_LEAF = 4
#: leaf-block side / face size of :func:`moment_leaf` at rtol = 1e-3: the bracket half-width sums to
#: ≈ 2 L sin² α over the horizon band, α ∝ leaf/N; measured max bound on the sky + 1e5 sun (s = 1; s = 2
#: is 20× tighter) at leaf/N = 1/64: 6.6e-4 (128², leaf 2), 3.9e-4 (256², 4), 5.7e-4 (512², 8)
LEAF_FRACTION_AT_1E3 = 1.0 / 64.0


def moment_leaf(n: int, rtol: float) -> int:
    """Leaf size for :func:`convolve_moment_many` at tolerance ``rtol`` (1: the exact band).

    The largest power of two ≤ ``n · LEAF_FRACTION_AT_1E3 · √(rtol/1e-3)`` (the bound scales as
    (leaf/N)²), or 1 when that is below :data:`MIN_BRACKET_LEAF`.  A priori only: the returned bound is
    rigorous whatever the leaf, and :func:`ibl_ref.groundtruth.convolve.convolve` halves the leaf when
    it misses ``rtol``.
    """
    x = n * LEAF_FRACTION_AT_1E3 * math.sqrt(max(rtol, 1e-300) / 1e-3)
    leaf = 1 << max(int(math.floor(math.log2(x))), 0) if x >= 1 else 1
    return leaf if leaf >= MIN_BRACKET_LEAF else 1


def moment_peak_bytes(n: int, out_size: int, n_faces: int = 6, channels: int = 3, need2: bool = True,
                      leaf: int = 1) -> float:
    """Estimated peak memory (bytes) of one :func:`convolve_moment_many` call.

    ``leaf = 1``: per-texel moments (6·P²·(3 + 6)·Q float64, P = n rounded up to a power of two) and
    their block sums (≈ ⅓ more); ``leaf > 1``: per-texel weights, directions and their padded copies
    (≈ 6·P²·(2Q + 9) float64) and the leaf-block moments (two sets).  Plus the output accumulators (2 per
    exponent, (tiles·t², Q)) and one chunk's band working set (:data:`MOMENT_CHUNK_PAIRS` × ≈ 10 arrays
    of 8 bytes).
    """
    P = 1 << max(int(math.ceil(math.log2(max(n, 1)))), 0)
    Q = channels + 1
    nk = 3 * Q + (6 * Q if need2 else 0)
    if leaf > 1:  # fitted: 1024², leaf 16, one output face, s = 1 and 2: 3.0 GB peak RSS of a one-job script
        src = 6 * P * P * (2 * Q + 9 + 6 + 2.0 * nk / (leaf * leaf)) * 8.0 * 2.0
    else:
        src = 6 * P * P * (nk * (1.0 + 1.0 / 3.0) + Q + 3 + 1) * 8.0
    out = n_faces * out_size * out_size * Q * 8.0 * 2 * (2 if need2 else 1) * 1.5
    return src + out + MOMENT_CHUNK_PAIRS * 10 * 8.0


def _texel_moments(dP, wP, Q, need2):
    """Per-texel moments (6,P,P,3Q[+6Q]): ω L Ω (and the 6 entries of ω ωᵀ L Ω), channel Q−1 with L ≡ 1."""
    P = dP.shape[1]
    F = [(dP[..., :, None] * wP[..., None, :]).reshape(6, P, P, 3 * Q)]
    if need2:
        dd = dP[..., SYM_PAIRS[0]] * dP[..., SYM_PAIRS[1]]  # (6,P,P,6)
        F.append((dd[..., :, None] * wP[..., None, :]).reshape(6, P, P, 6 * Q))
    return np.concatenate(F, axis=-1)


def _leaf_moments(dP, wP, Q, need2, b, drop=None):
    """Moments of b×b blocks, (6, P/b, P/b, 3Q[+6Q]) like :func:`_block_sums` of :func:`_texel_moments`
    (same column layout), by one small matrix product per block instead of per-texel arrays; one face
    at a time (bounded temporaries).  ``drop`` (6,P,P) bool: texels whose radiance channels (not the
    last, L ≡ 1) are left out."""
    P = dP.shape[1]
    m = P // b
    C = wP.shape[-1] - 1

    def blocks(x):  # (P,P,k) → (m,m,b²,k)
        return x.reshape(m, b, m, b, x.shape[-1]).transpose(0, 2, 1, 3, 4).reshape(m, m, b * b, -1)

    out = np.empty((6, m, m, 3 * Q + (6 * Q if need2 else 0)))
    for f in range(6):
        w = wP[f] if drop is None else np.where(drop[f][..., None] & (np.arange(Q) < C), 0.0, wP[f])
        wB = blocks(w)
        out[f, ..., : 3 * Q] = np.matmul(blocks(dP[f]).swapaxes(-1, -2), wB).reshape(m, m, 3 * Q)
        if need2:
            dd = dP[f][..., SYM_PAIRS[0]] * dP[f][..., SYM_PAIRS[1]]
            out[f, ..., 3 * Q :] = np.matmul(blocks(dd).swapaxes(-1, -2), wB).reshape(m, m, 6 * Q)
    return out


def _block_levels(dP, real, F, P, stop):
    """Per quadtree level b = P, P/2, …, stop: (b, m, cone centres, half-angles, valid, sin α, cos α, moments).

    ``F``: moments per texel (6,P,P,K) or per block of ``P // F.shape[1]`` texels (:func:`_leaf_moments`).
    """
    levels = []
    b = P
    f = P // F.shape[1]
    while True:
        cb, ab, vb = _cones(dP, real, b)
        levels.append((b, P // b, cb, ab, vb, np.sin(ab), np.cos(ab), _block_sums(F, b // f)))
        if b == stop:
            return levels
        b //= 2


def _classify(levels, cT, betaT, sinB, cosB, nK, stop, leaf, dP, real, F, P, n):
    """Quadtree classification of (tile, block) pairs for one chunk of output tiles.

    Returns ``(S, tiles, blk)``: per-tile sums of the moments of blocks (or, at the gather level, texels)
    positive for the whole tile, and the straddling pairs left for the band: (tile, leaf block) for
    ``leaf > 1``, (tile, source texel) for ``leaf = 1``.
    """
    import scipy.sparse as sp  # lazily: ≈ 0.1–0.2 s of start-up that other routes do not need

    T = cT.shape[0]
    S = np.zeros((T, nK))
    tiles = np.repeat(np.arange(T), 6)
    blk = np.tile(np.arange(6), T)
    for li, (b, m, cb, ab, vb, sinA, cosA, mom) in enumerate(levels):
        # θ + reach ≤ π/2  ⟺  cos θ ≥ sin(reach);  θ − reach ≥ π/2  ⟺  cos θ ≤ −sin(reach)  (reach < π/2);
        # sin(β+α) by the addition theorem (no arccos per pair); 1e-15 absorbs the dot's rounding
        cos_t = np.einsum("pk,pk->p", cT[tiles], cb[blk])
        sin_r = sinB[tiles] * cosA[blk] + cosB[tiles] * sinA[blk]
        small = (betaT[tiles] + ab[blk]) < 0.5 * math.pi
        vbb = vb[blk]
        pos = vbb & small & (cos_t >= sin_r + 1e-15)
        neg = ~vbb | (small & (cos_t <= -sin_r - 1e-15))
        if pos.any():
            A = sp.csr_matrix((np.ones(int(pos.sum())), (tiles[pos], blk[pos])), shape=(T, 6 * m * m))
            S += A @ mom
        strad = ~(pos | neg)
        tiles, blk = tiles[strad], blk[strad]
        if li == len(levels) - 1:
            break
        tiles = np.repeat(tiles, 4)
        blk = quad_children(blk, m)
    if leaf == 1 and stop > 1:  # straddling blocks of size `stop` → all their texels (exact gather)
        band_d = dP.reshape(-1, 3)
        mg = P // stop
        off = (np.arange(stop)[:, None] * P + np.arange(stop)[None, :]).ravel()
        allb = np.arange(6 * mg * mg)
        f, rem = np.divmod(allb, mg * mg)
        i, j = np.divmod(rem, mg)
        texel_of = (f * P * P + stop * i * P + stop * j)[:, None] + off[None, :]  # (blocks, stop²)
        # per-texel test against the tile cone: texels positive for the whole tile
        # (c_T·ω ≥ sin β_T) join the tile's exact moment sums, negative ones are dropped.
        # Block-major layout: one contiguous row of stop² texels per (tile, block) pair.
        cTt = cT[tiles]
        cdot = band_d[texel_of, 0][blk] * cTt[:, 0:1]
        cdot += band_d[texel_of, 1][blk] * cTt[:, 1:2]
        cdot += band_d[texel_of, 2][blk] * cTt[:, 2:3]
        sb = (sinB[tiles] + 1e-15)[:, None]
        pos = cdot >= sb
        keep = ~pos & (cdot > -sb)
        if P != n:  # padding texels (face size not a power of two) carry no weight
            ok = real.ravel()[texel_of][blk]
            pos &= ok
            keep &= ok
        tex = texel_of[blk]
        til = np.broadcast_to(tiles[:, None], tex.shape)
        if pos.any():
            A = sp.csr_matrix((np.ones(int(pos.sum())), (til[pos], tex[pos])), shape=(T, 6 * P * P))
            S += A @ F.reshape(6 * P * P, -1)
        tiles, blk = til[keep], tex[keep]
    return S, tiles, blk


def _ratio_bound(N_, E_, C, normalized):
    """Value and per-channel relative bound from sums ``N_`` (…, Q) and their absolute bounds ``E_``
    (channel Q−1: the denominator, L ≡ 1): ``max(approx − lo, hi − approx)/lo`` (inf where lo = 0)."""
    Nn, En = N_[..., :C], E_[..., :C]
    with np.errstate(divide="ignore", invalid="ignore"):
        if normalized:
            D, ED = N_[..., C:], E_[..., C:]
            approx = Nn / D
            lo = np.maximum(Nn - En, 0.0) / (D + ED)
            hi = (Nn + En) / np.maximum(D - ED, 0.0)
        else:
            approx, lo, hi = Nn, np.maximum(Nn - En, 0.0), Nn + En
        r = np.maximum(approx - lo, hi - approx) / lo
        exact_here = (En == 0) & (E_[..., C:] == 0) if normalized else (En == 0)
        r = np.where(exact_here, 0.0, r)
        r = np.where(np.isfinite(r), r, np.inf)
    return approx, r


def convolve_moment_many(
    cube,
    exponents,
    *,
    out_size: int | None = None,
    normalized: bool = True,
    leaf: int = 1,
    tile: int | None = None,
    gather: int | None = None,
    bright_factor: float = 50.0,
    chunk_elems: int = 1 << 16,
    faces=None,
    rtol: float | None = None,
    impl: str = "numpy",
):
    """Lobe average (or Eq. 4 sum) for ``s ∈ {1, 2}`` by hierarchical moments, with a rigorous bound.

    Parameters
    ----------
    cube : array (6, N, N[, C])
        Non-negative finite radiance.
    exponents : sequence of float
        Each 1 or 2.
    out_size : int, optional
        Output face size (default N).
    normalized : bool
        Lobe average (default) or the literal Eq. 4 sum.
    leaf : int
        Leaf block size (power of two). 1: exact gather of the horizon band (bound = rounding);
        > 1: convexity intervals on straddling leaf blocks (faster, bound > 0).
    tile : int
        Output tile size (texels per side) sharing one classification (default 8 for output faces
        ≥ 128, else 4: fastest measured at 64² / 128²).
    gather : int
        With ``leaf = 1``: straddling blocks of this size (power of two) are gathered texel by texel
        (exactly) instead of being split further (default 4 for faces ≥ 128, else 2).
    bright_factor : float
        With ``leaf > 1``: texels with luminance > bright_factor × mean are gathered exactly.
    chunk_elems : int
        Working-set size (elements) of the band gather (512 KB: the gather is memory-bound; at 128²
        faces 1 << 16 and 1 << 17 measured equal within run-to-run noise, 1.6–2.1 s for s = 1, 2).
    rtol : float, optional
        With ``leaf > 1``: output tiles whose bound exceeds ``rtol`` after a pass are computed again
        with half the leaf size, down to 2 (the bound returned is rigorous either way; None: one pass).
    faces : sequence of int, optional
        Compute only these output faces (indices 0…5, OpenEXR order; default all six, in order).
        The output tiles of one face never share work with another face's, so a face subset is the
        same computation restricted to those tiles (used by :func:`ibl_ref.groundtruth.convolve.convolve` to
        split the work between workers; results agree with the full call up to float64 rounding of
        the band sums, whose batching depends on the tile set).
    impl : {"numpy", "compiled"}
        The kernel backend of the horizon band (exact gather or brackets, and the bright texels of straddling
        leaf blocks; :mod:`ibl_ref.groundtruth.kernels`): the compiled one sums the same terms in another order
        (equal to the NumPy path up to float64 rounding).

    Returns
    -------
    maps : ndarray (K, F, n, n, C) (``(K, F, n, n)`` for a 3-d input), F = number of faces (6)
    rel_bound : ndarray (K, F, n, n)
        Rigorous bound on ``|approx − exact|/exact`` (max over channels; inf where exact may be 0).
    """
    a4, squeeze = check_cube(cube)
    n = a4.shape[1]
    s_in = [float(s) for s in np.atleast_1d(np.asarray(exponents, dtype=float))]
    s_list = sorted(set(s_in))  # s = 1 before s = 2 (the band gather squares in place)
    if not s_list or any(s not in SUPPORTED_EXPONENTS for s in s_list):
        raise IBLError(f"moment convolution supports Phong exponents {SUPPORTED_EXPONENTS}, got {exponents!r}")
    out_size = check_out_size(out_size, n)
    if tile is None:
        tile = 8 if out_size >= 128 else 4
    if gather is None:
        gather = 4 if n >= 128 else 2
    for name, v in (("leaf", leaf), ("tile", tile), ("gather", gather)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1 or (v & (v - 1)):
            raise IBLError(f"{name} must be a positive power of two, got {v!r}")
    leaf, tile, gather = int(leaf), int(tile), int(gather)
    faces = check_faces(faces)
    mp = _MomentPasses(a4, s_list, out_size, faces, tile, gather, leaf, bright_factor, chunk_elems,
                       get_kernels(check_impl(impl)))
    todo = np.arange(mp.T)
    lf = leaf
    while True:
        mp.run(lf, todo)
        if lf == 1 or rtol is None or lf // 2 < 2:
            break
        # tiles whose bound misses rtol are done again with half the leaf (down to 2)
        worst = np.zeros(todo.size)
        for s_ in s_list:
            worst = np.maximum(worst, _ratio_bound(mp.num[s_][todo], mp.err[s_][todo], mp.C,
                                                   normalized)[1].max(axis=(1, 2)))
        todo = todo[~(worst <= rtol)]
        if not todo.size:
            break
        lf //= 2
    # ---- assemble, ratio bound ---------------------------------------------------------------------
    nF, t, nt, C = len(faces), tile, mp.nt, mp.C
    maps = np.empty((len(s_in), nF, out_size, out_size, C))
    rel = np.empty((len(s_in), nF, out_size, out_size))

    def untile(x):
        x = x.reshape(nF, nt, nt, t, t, -1).transpose(0, 1, 3, 2, 4, 5).reshape(nF, nt * t, nt * t, -1)
        return x[:, :out_size, :out_size]

    for k, s in enumerate(s_in):
        approx, r = _ratio_bound(untile(mp.num[s]), untile(mp.err[s]), C, normalized)
        if not np.all(np.isfinite(approx)):
            raise IBLError("moment convolution: zero lobe weight (cannot happen for a valid cube map)")
        maps[k] = approx
        rel[k] = channel_max(r) + ROUNDING_REL
    if squeeze:
        maps = maps[..., 0]
    return maps, rel


class _MomentPasses:
    """The sources (padded grid, power of two ≥ N and ≥ leaf; weights L Ω; bright texels), the output tiles and
    the sums ``num``/``err`` (per exponent, (tiles, t², Q)) of :func:`convolve_moment_many`; :meth:`run` fills the
    sums of a set of tiles with one leaf size."""

    def __init__(self, a4, s_list, out_size, faces, tile, gather, leaf, bright_factor, chunk_elems, kern):
        n = a4.shape[1]
        self.n, self.s_list, self.out_size, self.tile, self.gather, self.chunk_elems = n, s_list, out_size, tile, \
            gather, chunk_elems
        self.kern, self.need2 = kern, 2.0 in s_list
        self.C = a4.shape[-1]
        Q = self.Q = self.C + 1  # channel Q-1: L ≡ 1 (denominator)
        # ---- source: padded grid, weights L Ω, bright texels ---------------------------------------------
        P = self.P = 1 << max(int(math.ceil(math.log2(n))), int(math.log2(leaf)), 0)
        omega = envmap.cube_solid_angles(n)
        wL = np.concatenate([a4 * omega[..., None], omega[..., None]], axis=-1)  # (6,n,n,Q)
        self.br = None
        if leaf > 1:  # bright texels (e.g. a sun): gathered exactly where their leaf block straddles
            lum = a4.max(axis=-1)
            mean = float(np.sum(lum * omega) / np.sum(omega))
            self.br = lum > bright_factor * max(mean, 1e-300)
        self.pad = ((0, 0), (0, P - n), (0, P - n), (0, 0))
        self.wP = np.pad(wL, self.pad)
        self.dP = np.pad(envmap.texel_directions(n), self.pad)
        self.real = np.pad(np.ones((6, n, n), bool), self.pad[:3])
        # ---- output tiles --------------------------------------------------------------------------------
        t = tile
        nt = self.nt = -(-out_size // t)
        od = envmap.texel_directions(out_size)[list(faces)]
        od = np.pad(od, ((0, 0), (0, nt * t - out_size), (0, nt * t - out_size), (0, 0)), mode="edge")
        R = self.R = envmap.face_blocks(od, t)
        self.T = R.shape[0]
        cT = self.cT = R.sum(axis=1)
        cT /= np.linalg.norm(cT, axis=-1, keepdims=True)
        self.betaT = np.arccos(np.clip(np.einsum("tik,tk->ti", R, cT).min(axis=1), -1.0, 1.0)) + _ANGLE_EPS
        self.sinB, self.cosB = np.sin(self.betaT), np.cos(self.betaT)
        self.nK = 3 * Q + (6 * Q if self.need2 else 0)
        self.num = {s_: np.zeros((self.T, t * t, Q)) for s_ in s_list}
        self.err = {s_: np.zeros((self.T, t * t, Q)) for s_ in s_list}
        LAST_INFO.clear()
        LAST_INFO.update(classify_s=0.0, band_s=0.0, band_pairs=0, tile_chunks=0, leaf_tiles={})
        brP = self.brP = (np.flatnonzero(np.pad(self.br, self.pad[:3]).ravel()) if self.br is not None
                          else np.zeros(0, np.int64))
        if brP.size:
            LAST_INFO["bright_texels"] = int(brP.size)
        bdT = bw_pad = bw_bright = None
        if leaf == 1 or brP.size:  # source texels with one zero-weight dummy entry at the end (index −1: the pads)
            bdT = np.ascontiguousarray(np.concatenate([self.dP.reshape(-1, 3), np.zeros((1, 3))]).T)
            bw_pad = np.concatenate([self.wP.reshape(-1, Q), np.zeros((1, Q))])
        if brP.size:  # the bright texels' own weights; the denominator (L ≡ 1) stays in the blocks
            bw_bright = np.zeros_like(bw_pad)
            bw_bright[brP, : self.C] = bw_pad[brP, : self.C]
        self.band_src = kern.band_sources(bdT, bw_pad) if bdT is not None else None
        self.bright_src = kern.band_sources(bdT, bw_bright) if bw_bright is not None else None

    def _leaves(self, lf):
        """The block levels of a pass with leaf ``lf`` and, for ``lf > 1``, the bracket band's leaf-block moments
        without the bright texels (those are gathered exactly) and the bright texels per leaf block (CSR)."""
        dP, wP, P, Q, C, need2, brP = self.dP, self.wP, self.P, self.Q, self.C, self.need2, self.brP
        stop = lf if lf > 1 else min(self.gather, P)
        if lf == 1:
            F = _texel_moments(dP, wP, Q, need2)
            return stop, F, _block_levels(dP, self.real, F, P, stop), None
        levels = _block_levels(dP, self.real, _leaf_moments(dP, wP, Q, need2, lf), P, stop)
        brp = np.pad(self.br, self.pad[:3])
        M0 = _block_sums(wP, lf)
        if brP.size:
            M0 = _block_sums(np.where(brp[..., None] & (np.arange(Q) < C), 0.0, wP), lf)
        FD = _leaf_moments(dP, wP, Q, need2, lf, drop=brp if brP.size else None).reshape(M0.shape[0], -1)
        M1 = FD[:, : 3 * Q]
        M2 = FD[:, 3 * Q :] if need2 else None
        f_, rem_ = np.divmod(brP, P * P)
        i_, j_ = np.divmod(rem_, P)
        mg = P // lf
        blk_of = f_ * mg * mg + (i_ // lf) * mg + (j_ // lf)
        order_ = np.argsort(blk_of, kind="stable")
        bright = (brP[order_], np.searchsorted(blk_of[order_], np.arange(6 * mg * mg + 1)))
        return stop, None, levels, (self.kern.brackets_prep(levels[-1][2], levels[-1][3], M0, M1, M2), bright)

    def run(self, lf, tsel):
        """``num``/``err`` of the output tiles ``tsel`` with leaf size ``lf`` (1: exact band), in chunks of tiles
        of bounded working set (independent of the worker count)."""
        LAST_INFO["leaf_tiles"][lf] = int(tsel.size)
        stop, F, levels, brackets = self._leaves(lf)
        Q, s_list, kern, chunk_elems = self.Q, self.s_list, self.kern, self.chunk_elems
        per_chunk = moment_tiles_per_chunk(self.n, self.out_size, self.tile, stop, kern.moment_chunk_pairs(Q), lf)
        for c0 in range(0, tsel.size, per_chunk):
            ch = tsel[c0 : c0 + per_chunk]
            nc = ch.size
            _t0 = time.perf_counter()
            S, tiles, blk = _classify(levels, self.cT[ch], self.betaT[ch], self.sinB[ch], self.cosB[ch], self.nK,
                                      stop, lf, self.dP, self.real, F, self.P, self.n)
            LAST_INFO["classify_s"] += time.perf_counter() - _t0
            LAST_INFO["band_pairs"] += int(tiles.size)
            LAST_INFO["tile_chunks"] += 1
            Rc = self.R[ch]
            # per output texel: positive-block moments (exact polynomial)
            num_c, err_c = {}, {}
            S1 = S[:, : 3 * Q].reshape(nc, 3, Q)
            for s_ in s_list:
                if s_ == 1.0:
                    num_c[s_] = np.einsum("tik,tkq->tiq", Rc, S1)
                else:
                    S2 = S[:, 3 * Q :].reshape(nc, 6, Q)
                    rr = Rc[..., SYM_PAIRS[0]] * Rc[..., SYM_PAIRS[1]] * np.array([1.0, 2.0, 2.0, 1.0, 2.0, 1.0])
                    num_c[s_] = np.einsum("tik,tkq->tiq", rr, S2)
                err_c[s_] = np.zeros_like(num_c[s_])
            _t0 = time.perf_counter()
            if lf == 1:
                kern.band_exact(Rc, tiles, blk, self.band_src, s_list, num_c, chunk_elems)
            else:
                prep, (bright_sorted, bright_start) = brackets
                kern.band_brackets(Rc, tiles, blk, prep, s_list, num_c, err_c, chunk_elems)
                nb = bright_start[blk + 1] - bright_start[blk]
                if nb.any():  # bright texels of straddling leaf blocks: exact gather
                    sel = np.flatnonzero(nb)
                    bt = np.repeat(tiles[sel], nb[sel])
                    first = np.repeat(bright_start[blk[sel]], nb[sel])
                    within = np.arange(bt.size) - np.repeat(np.cumsum(nb[sel]) - nb[sel], nb[sel])
                    kern.band_exact(Rc, bt, bright_sorted[first + within], self.bright_src, s_list, num_c,
                                    chunk_elems)
            for s_ in s_list:
                self.num[s_][ch] = num_c[s_]
                self.err[s_][ch] = err_c[s_]
            LAST_INFO["band_s"] += time.perf_counter() - _t0


def convolve_moment(cube, s, **kwargs):
    """Single-exponent form of :func:`convolve_moment_many`; returns ``(map, rel_bound)``."""
    maps, rel = convolve_moment_many(cube, [s], **kwargs)
    return maps[0], rel[0]
