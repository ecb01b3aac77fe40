"""The compiled loops (numba) of the converged reference's quadrature (Knuth et al. 2014, Eq. 4–5; GGX, Sec. 3.4).

Each loop computes, for every pair s, the block sums of :mod:`ibl_ref.rendering.reference_quadrature`::

    W[s, c] = Σ_t L_t,c · weight(ω_t) · Ω_t,     S[s] = Σ_t norm(ω_t) · Ω_t

over the k×k texels t of face size M starting at row ``r0[s]``, column ``c0[s]`` of face ``f[s]``: ω_t the texel
centre's direction ``F0 + u F1 + v F2`` normalised (u, v the centre's face-plane coordinates, F the face frame),
Ω_t the exact solid angle ``A(u1, v1) − A(u0, v1) − A(u1, v0) + A(u0, v0)``, ``A(x, y) = atan2(x y, √(x² + y² +
1))`` (:func:`ibl_ref.environment.envmap.rect_solid_angle`), L_t = ``rad[f, R // q, C // q]``.  The weights are
those of :mod:`ibl_ref.rendering.materials` written out per texel (the NumPy implementation calls them; the tests
compare the two):

``phong`` (params ``[s]``)
    norm = max(d·ω, 0)^s Ω, weight = norm·[n·ω > 0].
``ggx`` (params ``[α, f0, height_correlated]``)
    weight = D·G·F / (4 (n·ω)(n·v)) · (n·ω) · Ω = D·G·F / (4 n·v) · Ω where n·ω > 0 and n·v > 0 (else 0),
    h = (ω + v)/|ω + v|,
    D = α² / (π ((n·h)² (α² − 1) + 1)²), G1(c) = 2c / (c + √(α² + (1 − α²) c²)), G = 1/(1/G1(n·ω) + 1/G1(n·v) − 1)
    (height-correlated, Heitz 2014 Eq. 99) or G1(n·ω)·G1(n·v) (separable), F = f0 + (1 − f0)(1 − h·ω)^5
    (:func:`ibl_ref.lobes.brdfs.cook_torrance`).

The pairs come grouped by block (``order``, ``starts``): a block's directions, solid angles and radiance are
computed once for all the pixels that read it, its corners' A once for the up to four texels that share them; pair
p reads its pixel's normal, view and lobe axis at row ``pix[p]`` of per-pixel arrays (no gathered copies).  Serial
loops (the reference's blocks already run on separate processes) in a fixed order: the same result in every
process.

The reference's bookkeeping in compiled form, each with the values of its NumPy definition bit for bit (the same
operations in the same order; the methods of :class:`ibl_ref.rendering.reference_quadrature.Quadrature`):
:func:`sums_by` (per-pixel sums of cell weights, ``np.bincount``'s order), :func:`positive_rows` (the rows that
carry weight, deciding most rows without the mean), :func:`relative_means3` (channel means of groups of three),
:func:`max_ratio` (a sweep's driving weight) and :func:`dirty_sums` (a refinement round's per-pixel sums).  Compiled on first use and kept in numba's cache (the
convolution kernels' policy: :mod:`ibl_ref.groundtruth.kernels.numba_loops`).
"""

from __future__ import annotations

import math

import numpy as np

from ..groundtruth.kernels.numba_loops import _jit

__all__ = ["phong_blocks", "ggx_blocks", "sums_by", "positive_rows", "relative_means3", "dirty_sums", "max_ratio",
           "LOOPS"]


@_jit()
def _area(x, y):
    return math.atan2(x * y, math.sqrt(x * x + y * y + 1.0))


@_jit()
def _block_geometry(F, fs, M, r0, c0, k, A, G, At):
    """Directions (x, y, z) and exact solid angles of the k×k texels of face fs, face size M, from row r0, column c0
    into G (4, k²) (one row per quantity, texels row-major); A ((k+1)², scratch) holds the corners' A(u, v), each
    shared by up to four texels.  A corner's A depends on its row and column at face size M only (not on the face):
    with a table At ((M+1)², NaN where not computed yet; :func:`area_table`) each corner is computed once and read
    from At after that — the same value (the same function of the same arguments); At empty: no table."""
    h = 2.0 / M
    tab = len(At) > 0
    for a in range(k + 1):
        ve = (r0 + a) * h - 1.0
        row = (r0 + a) * (M + 1) + c0
        for b in range(k + 1):
            if tab:
                x = At[row + b]
                if x != x:
                    x = _area((c0 + b) * h - 1.0, ve)
                    At[row + b] = x
                A[a * (k + 1) + b] = x
            else:
                A[a * (k + 1) + b] = _area((c0 + b) * h - 1.0, ve)
    for a in range(k):
        v = (r0 + a + 0.5) / M * 2.0 - 1.0
        for b in range(k):
            u = (c0 + b + 0.5) / M * 2.0 - 1.0
            x = F[fs, 0, 0] + u * F[fs, 1, 0] + v * F[fs, 2, 0]
            y = F[fs, 0, 1] + u * F[fs, 1, 1] + v * F[fs, 2, 1]
            z = F[fs, 0, 2] + u * F[fs, 1, 2] + v * F[fs, 2, 2]
            ln = math.sqrt(x * x + y * y + z * z)
            t = a * k + b
            G[0, t] = x / ln
            G[1, t] = y / ln
            G[2, t] = z / ln
            c = a * (k + 1) + b
            G[3, t] = A[c + k + 2] - A[c + k + 1] - A[c + 1] + A[c]


@_jit()
def _block_radiance(rad, q, fs, r0, c0, k, Lb, cols):
    """The radiance of the block's k×k texels into Lb (C, k²) (one row per channel: the pairs' dot products run
    along contiguous memory), channel by channel (contiguous writes); the map's column of each block column found
    once into ``cols`` (k, scratch), its row once per block row (no integer division per texel)."""
    for b in range(k):
        cols[b] = (c0 + b) // q
    for ch in range(Lb.shape[0]):
        for a in range(k):
            R = (r0 + a) // q
            for b in range(k):
                Lb[ch, a * k + b] = rad[fs, R, cols[b], ch]


@_jit()
def _accumulate(wb, Lb, W, p):
    """W[p, c] = Σ_t wb[t] Lb[c, t], each channel's sum a running sum in texel order (t = 0, 1, …); four channels'
    sums at a time side by side (independent additions: one running sum alone waits on each addition's latency;
    past the last channel a group repeats it, written once)."""
    C = Lb.shape[0]
    for ch in range(0, C, 4):
        r1, r2, r3 = min(ch + 1, C - 1), min(ch + 2, C - 1), min(ch + 3, C - 1)
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        a3 = 0.0
        for t in range(len(wb)):
            w = wb[t]
            a0 += w * Lb[ch, t]
            a1 += w * Lb[r1, t]
            a2 += w * Lb[r2, t]
            a3 += w * Lb[r3, t]
        W[p, ch] = a0
        W[p, r1] = a1
        W[p, r2] = a2
        W[p, r3] = a3


@_jit()
def phong_blocks(n, v, d, pix, order, starts, f, r0, c0, k, M, rad, q, F, params, W, S, rows, At):
    """Phong lobe (module docstring): rows ``rows[p]`` of W and S filled in place; pair p reads the normal, view and
    axis of row ``pix[p]`` of n, v, d; the pairs ``order[starts[g]:starts[g+1]]`` share one block (its geometry and radiance
    gathered once; its corners' A read from and added to the table ``At`` of face size M, :func:`_block_geometry`)."""
    s = params[0]
    kk = k * k
    A = np.empty((k + 1) * (k + 1))
    G = np.empty((4, kk))
    Lb = np.empty((rad.shape[3], kk))
    wb = np.empty(kk)
    cols = np.empty(k, np.int64)
    for g in range(len(starts) - 1):
        p0 = order[starts[g]]
        fs = f[p0]
        _block_geometry(F, fs, M, r0[p0], c0[p0], k, A, G, At)
        _block_radiance(rad, q, fs, r0[p0], c0[p0], k, Lb, cols)
        for e in range(starts[g], starts[g + 1]):
            p = order[e]
            x = pix[p]
            dx, dy, dz = d[x, 0], d[x, 1], d[x, 2]
            nx, ny, nz = n[x, 0], n[x, 1], n[x, 2]
            acc = 0.0
            for t in range(kk):
                c = max(dx * G[0, t] + dy * G[1, t] + dz * G[2, t], 0.0)
                w = (c if s == 1.0 else c ** s) * G[3, t]
                acc += w
                wb[t] = w if nx * G[0, t] + ny * G[1, t] + nz * G[2, t] > 0.0 else 0.0
            S[rows[p]] = acc
            _accumulate(wb, Lb, W, rows[p])


@_jit()
def ggx_blocks(n, v, d, pix, order, starts, f, r0, c0, k, M, rad, q, F, params, W, S, rows, At):
    """GGX specular term (module docstring): rows ``rows[p]`` of W filled in place (S unused: no discrete
    normalisation); pair p reads row ``pix[p]`` of n, v; the pairs ``order[starts[g]:starts[g+1]]`` share one block (its geometry and
    radiance gathered once; corners' A through the table ``At``, as in :func:`phong_blocks`).  The texel loop has no branches (selects only), so that it runs on the processor's
    vector lanes."""
    alpha, f0, sep = params[0], params[1], 1.0 - params[2]
    a2 = alpha * alpha
    kk = k * k
    A = np.empty((k + 1) * (k + 1))
    G = np.empty((4, kk))
    Lb = np.empty((rad.shape[3], kk))
    wb = np.empty(kk)
    cols = np.empty(k, np.int64)
    for g in range(len(starts) - 1):
        p0 = order[starts[g]]
        fs = f[p0]
        _block_geometry(F, fs, M, r0[p0], c0[p0], k, A, G, At)
        _block_radiance(rad, q, fs, r0[p0], c0[p0], k, Lb, cols)
        for e in range(starts[g], starts[g + 1]):
            p = order[e]
            x0 = pix[p]
            nx, ny, nz = n[x0, 0], n[x0, 1], n[x0, 2]
            vx, vy, vz = v[x0, 0], v[x0, 1], v[x0, 2]
            co = nx * vx + ny * vy + nz * vz
            if co <= 0.0:
                for ch in range(W.shape[1]):
                    W[rows[p], ch] = 0.0
                continue
            inv_g1o = (co + math.sqrt(a2 + (1.0 - a2) * co * co)) / (2.0 * co)
            for t in range(kk):
                x, y, z = G[0, t], G[1, t], G[2, t]
                ci = nx * x + ny * y + nz * z
                cis = max(ci, 1e-300)
                hx, hy, hz = x + vx, y + vy, z + vz
                ih = 1.0 / math.sqrt(max(hx * hx + hy * hy + hz * hz, 1e-300))
                ch = (nx * hx + ny * hy + nz * hz) * ih
                tt = ch * ch * (a2 - 1.0) + 1.0
                D = a2 / (math.pi * tt * tt)
                inv_g1i = (cis + math.sqrt(a2 + (1.0 - a2) * cis * cis)) / (2.0 * cis)
                # 1/G = 1/G1i + 1/G1o − 1 (height-correlated) or (1/G1i)(1/G1o) (separable: sep = 1), branch-free
                Gs = 1.0 / (inv_g1i + inv_g1o - 1.0 + sep * (inv_g1i - 1.0) * (inv_g1o - 1.0))
                m = 1.0 - min(max((hx * x + hy * y + hz * z) * ih, 0.0), 1.0)
                Fr = f0 + (1.0 - f0) * (m * m * m * m * m)
                w = D * Gs * Fr / (4.0 * co) * G[3, t]
                wb[t] = w if ci > 0.0 else 0.0
            _accumulate(wb, Lb, W, rows[p])


@_jit()
def sums_by(idx, W, m, out):
    """out[idx[s], c] += W[s, c] · m[s] for s = 0, 1, … in turn (m empty: W[s, c] alone): per column the sums of
    ``np.bincount(idx, weights=W[:, c] * m)`` — which adds its weights in input order to 0 — bit for bit, all
    columns in one pass (:meth:`ibl_ref.rendering.reference_quadrature.Quadrature.sums_by`)."""
    C = W.shape[1]
    if len(m):
        for s in range(len(idx)):
            p = idx[s]
            f = m[s]
            for c in range(C):
                out[p, c] += W[s, c] * f
    else:
        for s in range(len(idx)):
            p = idx[s]
            for c in range(C):
                out[p, c] += W[s, c]


@_jit()
def positive_rows(W, out):
    """out[s] = 1 where the mean of row s of W is surely > 0 (every entry ≥ 0, one above 1e-300: the sum is at least
    that entry whatever the order of the additions, so the mean is a normal number > 0), 0 where every entry is 0
    (the mean is 0), 2 where this does not decide (tiny, negative or NaN entries: the caller takes the mean)."""
    for s in range(W.shape[0]):
        mx = 0.0
        undecided = False
        for c in range(W.shape[1]):
            x = W[s, c]
            if not (x >= 0.0):
                undecided = True
            elif x > mx:
                mx = x
        out[s] = 2 if undecided else (1 if mx > 1e-300 else (0 if mx == 0.0 else 2))


@_jit()
def relative_means3(W, w, out):
    """out[s, e] = ((W[s, 3e] + W[s, 3e+1]) + W[s, 3e+2]) / 3 / w[s]: the channel means of groups of three, relative to
    w, in the order of :func:`ibl_ref.rendering.reference_quadrature.group_means` (NumPy's), bit for bit."""
    for s in range(W.shape[0]):
        ws = w[s]
        for e in range(out.shape[1]):
            out[s, e] = (W[s, 3 * e] + W[s, 3 * e + 1] + W[s, 3 * e + 2]) / 3.0 / ws


@_jit()
def dirty_sums(D, bp, bV, bsplit, bY, bYe, bdY, rp, rbi, rV, rY, rYe, A, q):
    """:meth:`ibl_ref.rendering.reference_quadrature.CompiledQuadrature.dirty_sums`: for the pixels p with D[p], A[p] =
    Σ_base bYe·lit + Σ_refined rYe·[rV > 0] (two sums, then added) and q[p] = |Σ_base bdY·V̄| (V̄ a base pair's ray,
    or the lit share of its leaves' weight where it was split), every sum over the rows in their order."""
    nB = len(bp)
    P, E = A.shape
    have_r = len(rp) > 0
    num = np.zeros(nB)
    for s in range(len(rp)):
        if D[rp[s]]:
            num[rbi[s]] += rY[s] * (1.0 if rV[s] > 0 else 0.0)
    Ab = np.zeros((P, E))
    Ar = np.zeros((P, E))
    qs = np.zeros((P, E))
    for s in range(nB):
        p = bp[s]
        if D[p]:
            lit = 1.0 if (bV[s] > 0 and not bsplit[s]) else 0.0
            if have_r and bsplit[s]:
                y = bY[s]
                vb = num[s] / (y if y > 0 else 1.0)
            else:
                vb = max(float(bV[s]), 0.0)
            for e in range(E):
                Ab[p, e] += bYe[s, e] * lit
                qs[p, e] += bdY[s, e] * vb
    for s in range(len(rp)):
        p = rp[s]
        if D[p]:
            f = 1.0 if rV[s] > 0 else 0.0
            for e in range(E):
                Ar[p, e] += rYe[s, e] * f
    for p in range(P):
        if D[p]:
            for e in range(E):
                A[p, e] = Ab[p, e] + Ar[p, e]
                q[p, e] = abs(qs[p, e])


@_jit()
def max_ratio(Ye, T, out):
    """out[s] = max_e Ye[s, e] / T[e], the maximum taken as ``np.maximum`` does column by column (of equal values the
    later one, so −0 and +0 as NumPy orders them; a NaN carried on), bit for bit."""
    for s in range(Ye.shape[0]):
        m = Ye[s, 0] / T[0]
        for e in range(1, Ye.shape[1]):
            x = Ye[s, e] / T[e]
            if not (m > x or m != m):
                m = x
        out[s] = m


#: the loop of each lobe kind (``lobe.kind`` of :mod:`ibl_ref.rendering.materials`)
LOOPS = {"phong": phong_blocks, "ggx": ggx_blocks}
