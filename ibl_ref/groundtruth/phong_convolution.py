"""Knuth et al. (2014), Sec. 3.2, Eq. 4 — exact Phong-lobe convolution of a cube-map environment.

This module is the *ground truth* of ibl_ref: the spherical convolution of an environment map with the
clamped cosine lobe ``max(r·ω, 0)^s`` (Knuth et al. 2014, Eq. 4, with ``s = s_Phong = 1/(1−g)``, Eq. 3),
evaluated as a quadrature over **every** source texel with its **exact** solid angle
(:func:`ibl_ref.environment.envmap.cube_solid_angles`), plus a truncated-support ("sparse") gather that returns a
rigorous per-texel error bound.

Two normalisations (docs/background.md §2 "Normalisation")
---------------------------------------------------
* ``normalized=False`` — the literal Eq. 4 as printed::

      E_s(r) = ∫ L(ω) max(r·ω, 0)^s dω  ≈  Σ_j L_j max(r·ω_j, 0)^s Ω_j

  whose value for ``L ≡ 1`` is ``∫ max(cos θ, 0)^s dω = 2π/(s+1)`` (:func:`phong_lobe_integral`).
* ``normalized=True`` (default) — the lobe **average**::

      Ē_s(r) = Σ_j L_j max(r·ω_j,0)^s Ω_j / Σ_j max(r·ω_j,0)^s Ω_j

  what an energy-normalised Phong BRDF (Kán et al. 2015, Eq. 2) and an energy-conserving MIP filter
  produce.  Relation: ``E_s(r) = Ē_s(r) · W_s(r)`` with ``W_s(r) = Σ_j max(r·ω_j,0)^s Ω_j ≈ 2π/(s+1)``
  (the difference is the quadrature error of the lobe, O(N⁻²) once the lobe spans several texels;
  ``convolve_exact_many(..., return_weights=True)`` returns W_s).  A constant environment comes out
  exactly constant (to rounding) in the normalised form because the same weights appear in both sums.

``s`` may be any float ≥ 1 (s < 1 is rejected; exponents up to 1e6 and beyond are supported) or ``np.inf``: the
mirror limit, implemented as a nearest-texel lookup of the source (the identity when the output size
equals the input size).  Weights are evaluated as ``exp(s·(log c − max_j log c))`` per output texel, so
nothing overflows or underflows to 0/0 even at s = 1e6.

Supersampling (``supersample=k``) splits every source texel into k×k sub-texels with exact sub-solid
angles and sub-texel-centre directions, keeping the radiance piecewise constant.  Because the k×k
sub-texels of a texel of a face of size N are exactly the texels of a face of size N·k, this is the
quadrature of the piecewise-constant environment on the (N·k)² grid.  As s → ∞ (and k → ∞) the lobe
average tends to the radiance of the texel containing r, i.e. to the mirror lookup.

Complexity: O(N_out² · (k·N_in)²) operations per exponent (every output texel sees every source
texel; ≈ 15–25 ns per texel pair, dominated by log/exp); memory is bounded by chunking output texels
(chunk × sources weight matrix, ≈ 2 MB).  Measured CPU time (``benchmarks/bench_phong_convolution.py``,
1 BLAS thread, shared machine under heavy load): s = 16 at 32² faces 0.52 s, at 64² 9.2 s; eight
exponents at once 2.6 s (32²) and 32 s (64²) — the shared dot products/logs save ≈ 2×.  128² would
take ≈ 16 × 9 s ≈ 2.5 min per exponent (N⁴ scaling); use :func:`convolve_sparse` there.

Truncated support (:func:`convolve_sparse`)
-------------------------------------------
Only source texels within the angle θc of r are gathered (plus, optionally, a set of the brightest texels
that are always gathered exactly).  The continuous neglected-weight fraction of the lobe has the closed
form ``∫_{θ>θc} cos^s dω / ∫ cos^s dω = cos^{s+1} θc``.  For the *discrete* quadrature a rigorous bound
must also account for the texel extent ρ (max angle between a texel centre and its corners): every point
ω of a neglected texel j satisfies θ(ω) ≥ θ_j − ρ, hence ``cos^s(θ_j) ≤ cos^s(max(θ(ω) − ρ, 0))`` on the
whole texel, and summing the texel integrals gives::

    W_out ≤ W_b(θc) = 2π ∫_{θc−2ρ}^{π/2} cos^s φ · sin(φ + ρ) dφ
                    = 2π [ cos ρ · cos^{s+1}(a)/(s+1) + sin ρ · ∫_a^{π/2} cos^{s+1} φ dφ ],  a = θc − 2ρ

(the last integral via the regularised incomplete beta function, or the elementary bound
``cos^{s+2}(a)/((s+2) sin a)``, whichever is smaller).  A second valid bound sums over annuli
[θ_i, θ_i + Δ) from θc: texels with centres in an annulus have weight ≤ cos^s θ_i and lie inside the
band widened by ρ, of solid angle 2π(cos(θ_i − ρ) − cos(θ_i + Δ + ρ)); it is much tighter for narrow
lobes on coarse grids.  W_b is the smaller of the two (checked against brute force in the tests:
W_b / max_r W_out = 3–16 for lobes resolved by the grid).  With the gathered weight ``W_in`` and the
gathered average ``P``, the exact average is ``E = P + f (L̄_out − P)`` with ``f = W_out/(W_in+W_out)``
and ``L̄_out`` a weighted mean of the neglected radiance, so per channel::

    |E − P| ≤ W_b/(W_in + W_b) · max(L_max,out − P, P − L_min,out)

with ``L_max,out``/``L_min,out`` the extreme radiance of the texels that may be neglected (the global
ones after removing the always-gathered bright set).  This is the returned absolute bound.  Output
texels are processed in tiles sharing one candidate list (the cap around the tile, at least ρ wider
than the tile so that it holds every texel's own source texel), so slightly more than the cap is
gathered; gathering more only shrinks the neglected set and the bound stays valid.  The caps are
found by a two-level search (cones of 8×8 source blocks, then their texels; no KD-tree, whose SciPy
import alone costs ≈ 0.4 s CPU), and tiles with similar candidate counts are gathered together by
batched matrix products (padded lists), which removes the per-tile Python overhead that dominated
narrow lobes (measured CPU of the gather, load 9–11: 128², s = 4096: 1.15 → 0.43 s; s = 1024: 1.6 →
0.87 s; 256², s = 1000, two output faces: 4.8 → 2.7 s).
**Local bound and per-tile caps** (default ``local=True``).  The neglected texels of an output texel r at angle
a from its tile's centre lie beyond q − a (q: the tile's cap around its centre).  They are split at a far cap
q_far = θ_far + (largest a) + margin, θ_far the cap whose W_b is ≤ ε_far·2π/(s+1) with
``ε_far = 0.1·τ·L_lo/(L_max,out − L_lo)`` (``L_lo = max(L_min,out, dark_floor·L_mean)``, τ = rtol/(1+rtol)):
texels between q and q_far from the centre have radiance within the *local* extremes
``L_max,loc``/``L_min,loc`` (per channel, of the non-bright texels of the 8×8 source blocks whose cone reaches
the far cap: a superset), those beyond q_far within the global ones.  With W₁ = W_b(q − a), W₂ = W_b(q_far − a)
(the near weight is ≤ W₁ − W_far, the far weight W_far ≤ min(W₁, W₂)) the bound is::

    |E − P| ≤ [min(W₁, W₂)·max(L_max,out − P, P − L_min,out) + max(W₁ − W₂, 0)·max(L_max,loc − P, P − L_min,loc)] / W_in

(plus the kernel's rounding, below).  Each tile's first cap aims at a neglected fraction 0.8·(0.9·τ − the float32
share)/κ, κ = (L_max,loc − L_min,loc)/L_min,loc its local contrast; a tile whose bound still misses rtol at some texel is gathered again with a
cap for κ ≥ 1, then with q = θ_far (per tile: only the tiles that miss).  So the cap follows the map: wide next
to a contrast, narrow in smooth regions, and no global tightening of rtol by the map's darkest/mean radiance
is needed.  ``local=False`` (or ``theta_c``) is the single global cap above.

**Float32 kernel** (``kernel="auto"``: where its rounding bound takes ≤ 20 % of τ; ``"float32"`` forces it,
``"float64"`` never).  Sources are gathered in 4×4 slabs (contiguous copies), x = 1 − r·ω is computed in
float32 from the offsets to the tile centre, a = r − t, b = ω − t, as one 5-term dot product
``[a, |a|²/2, 1]·[−b, 1, |b|²/2]`` (small cancellation), ``log(1 − x)`` by its K-term series (Horner), the weight
by float32 ``exp``, sums of 64 candidates in float32 and over the chunks in float64.  Its relative error η
(:func:`_kernel32_eta`: rounding of x, of the series and its remainder, float32 exp within 2^-20, rounding of
L·Ω and the partial sums, γ_n = nu/(1 − nu), u = 2^-24) and the absolute error of weights below 2^-126 are
propagated into the bound (W_in lowered by 1 + η, the average widened by 2η/(1 − η)).  The kernel is used only
where x ≤ 0.3, K ≤ 12 and the largest weight of every row is ≥ e^-40; it is checked against float64 sums on a
dense sample of (texel, candidate) pairs in the tests (observed errors 1–2 % of η).

The bound is worst-case: for smooth environments the actual error is typically 15–500× smaller
(the neglected radiance is not all at L_max).  Measured at 64² (sky + 1e5 sun, rtol = 1e-3, CPU):
s = 16: 3.5× faster than exact, max rel err 4.8e-5, max rel bound 6.6e-4; s = 256: 19.5×, 1.8e-5,
6.7e-4; s = 4096: 27.5×, 1.1e-6, 6.2e-4.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from ..environment import envmap
from .convolution_args import channel_max, check_cube, check_exponent, check_faces, check_out_size
from ..errors import IBLError, LayoutError

__all__ = [
    "phong_lobe_integral",
    "convolve_exact",
    "convolve_exact_many",
    "convolve_sparse",
    "convolve_sparse_many",
    "neglected_weight_fraction",
    "neglected_weight_bound",
    "cutoff_angle",
    "SparseInfo",
    "lobe_average",
    "estimate_candidates",
]

#: target size of one chunk's weight matrix, in float64 elements (2 MB: the passes stay in cache)
_CHUNK_ELEMS = 1 << 18
#: cost model of the sparse gather, in units of one weight-matrix element (≈ 40 ns under load):
#: per tile ≈ 0.7 ms, per candidate source texel ≈ 1.2 µs (least-squares fit to timings at 64²,
#: s ∈ {256, 4096}, tiles of 2…16 texels)
_TILE_OVERHEAD_ELEMS = 1.7e4
_CAND_OVERHEAD_ELEMS = 30.0
#: angular safety margin (rad) for chord/angle round-off in the cap test of the sparse gather
_ANGLE_MARGIN = 1e-7
#: below this argument np.exp returns exactly 0.0 in float64 (smallest subnormal ≈ exp(−744.4))
_EXP_UNDERFLOW = -746.0


# ----------------------------------------------------------------------------------------------
# closed forms
# ----------------------------------------------------------------------------------------------
def phong_lobe_integral(s):
    """∫_{S²} max(cos θ, 0)^s dω = 2π/(s+1) (Meunier 2009; docs/background.md §2).  0 for s = ∞."""
    s = np.asarray(s, dtype=np.float64)
    out = 2.0 * np.pi / (s + 1.0)
    return float(out) if out.ndim == 0 else out


def neglected_weight_fraction(s, theta_c):
    """Continuous fraction of the lobe weight outside the cap θ < θc: cos^{s+1} θc (0 for θc ≥ π/2).

    ∫_{θ>θc} cos_+^s dω / ∫ cos_+^s dω = [2π cos^{s+1}θc/(s+1)] / [2π/(s+1)].
    """
    s = np.asarray(s, dtype=np.float64)
    theta_c = np.asarray(theta_c, dtype=np.float64)
    c = np.cos(np.clip(theta_c, 0.0, np.pi / 2))
    with np.errstate(divide="ignore"):
        out = np.where(theta_c >= np.pi / 2, 0.0, np.exp((s + 1.0) * np.log(np.maximum(c, 1e-300))))
    return float(out) if out.ndim == 0 else out


# ----------------------------------------------------------------------------------------------
# input checks (shared ones in ibl_ref.groundtruth.convolution_args)
# ----------------------------------------------------------------------------------------------
def _check_sizes(out_size, n, supersample):
    out_size = check_out_size(out_size, n)
    if isinstance(supersample, bool) or not isinstance(supersample, (int, np.integer)) or supersample < 1:
        raise IBLError(f"supersample must be a positive integer, got {supersample!r}")
    return int(out_size), int(supersample)


def _sources(a: np.ndarray, supersample: int):
    """Flattened source directions (M,3), solid angles (M,), radiance (M,C) on the (N·k)² grid."""
    n = a.shape[1]
    m = n * supersample
    if supersample > 1:
        a = np.repeat(np.repeat(a, supersample, axis=1), supersample, axis=2)
    dirs = envmap.texel_directions(m).reshape(-1, 3)
    omega = np.ascontiguousarray(envmap.cube_solid_angles(m)).reshape(-1)
    rad = np.ascontiguousarray(a, dtype=np.float64).reshape(-1, a.shape[-1])
    return dirs, omega, rad


def _mirror(a: np.ndarray, out_size: int) -> np.ndarray:
    n = a.shape[1]
    if out_size == n:
        return np.array(a, dtype=np.float64, copy=True)
    d = envmap.texel_directions(out_size)
    f, r, c = envmap.direction_to_texel(d, n)
    return np.asarray(a[f, r, c], dtype=np.float64)


# ----------------------------------------------------------------------------------------------
# exact convolution
# ----------------------------------------------------------------------------------------------
def convolve_exact_many(
    cube,
    exponents,
    *,
    normalized: bool = True,
    supersample: int = 1,
    out_size: int | None = None,
    dtype=np.float64,
    return_weights: bool = False,
):
    """Exact Eq. 4 convolution for several Phong exponents at once (shared dot products).

    Parameters
    ----------
    cube : array (6, N, N[, C])
        Non-negative finite radiance.
    exponents : sequence of float
        Each ≥ 1 or ``np.inf`` (mirror lookup).
    normalized : bool
        Lobe average (default) or the literal, unnormalised Eq. 4 (see module docstring).
    supersample : int
        Split every source texel into k×k sub-texels (exact sub-solid angles, piecewise-constant L).
    out_size : int, optional
        Output face size (default: N).
    dtype : numpy dtype
        Working precision of the weight matrix and the matrix product (float64 for references).
    return_weights : bool
        Also return the discrete lobe weight ``W_s(r) = Σ_j max(r·ω_j,0)^s Ω_j`` (K, 6, n, n)
        (≈ 2π/(s+1); NaN-free, 0 where it underflows; ``unnormalised = average × W``; 1 for s = inf).

    Returns
    -------
    ndarray (K, 6, n, n, C) float64 (``(K, 6, n, n)`` for a 3-d input)[, weights (K, 6, n, n)].
    """
    a, squeeze = check_cube(cube)
    n = a.shape[1]
    out_size, supersample = _check_sizes(out_size, n, supersample)
    s_list = [check_exponent(s) for s in np.atleast_1d(np.asarray(exponents, dtype=object))]
    if not s_list:
        raise IBLError("no Phong exponents given")
    if not normalized and any(np.isinf(s) for s in s_list):
        raise IBLError("the unnormalised Eq. 4 integral vanishes for s = inf (2π/(s+1) → 0); use normalized=True")
    C = a.shape[-1]
    K = len(s_list)
    out = np.empty((K, 6 * out_size * out_size, C), dtype=np.float64)
    weights = np.ones((K, 6 * out_size * out_size), dtype=np.float64)

    finite = [k for k, s in enumerate(s_list) if np.isfinite(s)]
    for k, s in enumerate(s_list):
        if not np.isfinite(s):
            out[k] = _mirror(a, out_size).reshape(-1, C)

    if finite:
        src_dirs, omega, rad = _sources(a, supersample)
        M = src_dirs.shape[0]
        # Ω folded into the right-hand side: acc = w @ (Ω·[L, 1]) gives Σ w L Ω and Σ w Ω (last column)
        rad_w = (np.concatenate([rad, np.ones((M, 1))], axis=1) * omega[:, None]).astype(dtype, copy=False)
        dst = envmap.texel_directions(out_size).reshape(-1, 3)
        P = dst.shape[0]
        chunk = max(1, min(P, _CHUNK_ELEMS // M))
        src_dirs_t = np.ascontiguousarray(src_dirs.T)
        need_log = any(s_list[k] != 1.0 for k in finite)
        for i0 in range(0, P, chunk):
            i1 = min(P, i0 + chunk)
            c = dst[i0:i1] @ src_dirs_t  # cos between r and ω_j, (B, M)
            np.maximum(c, 0.0, out=c)  # max(r·ω, 0): texels behind the lobe get weight exactly 0
            accs = {}
            for k in finite:
                if s_list[k] == 1.0:  # cos^1: no log/exp needed
                    accs[k] = (c.astype(dtype, copy=False) @ rad_w, None)
            if need_log:
                with np.errstate(divide="ignore"):
                    np.log(c, out=c)  # log 0 = −inf → exp(−inf) = 0 exactly
                logc_max = c.max(axis=1, keepdims=True)  # finite: the nearest texel always has c > 0
                c -= logc_max  # log(c / c_max) ≤ 0: weights relative to the row maximum never overflow
                col_max = c.max(axis=0)  # per source texel, over the chunk's output texels
                for k in finite:
                    s = s_list[k]
                    if s == 1.0:
                        continue
                    # Source texels whose weight (c/c_max)^s underflows to exactly 0.0 for every row of
                    # the chunk (exp(x) = 0 for x < −745.2 in float64) are skipped: the sum is unchanged
                    # except for summation order (rounding level).  Saves the back hemisphere for all s
                    # and most of the sphere for large s.
                    keep = np.flatnonzero(col_max * s > _EXP_UNDERFLOW)
                    if keep.size < 0.8 * M:
                        w = c[:, keep]
                        rhs = rad_w[keep]
                    else:
                        w = np.array(c)
                        rhs = rad_w
                    w *= s
                    np.exp(w, out=w)  # (c / c_max)^s
                    accs[k] = (w.astype(dtype, copy=False) @ rhs, s * logc_max)
            for k, (acc, log_scale) in accs.items():
                num = acc[:, :C].astype(np.float64)
                den = acc[:, C:].astype(np.float64)
                scale = 1.0 if log_scale is None else np.exp(log_scale)  # c_max^s
                weights[k, i0:i1] = (den * scale)[:, 0]
                if normalized:
                    out[k, i0:i1] = num / den
                else:
                    out[k, i0:i1] = num * scale
    shape = (K, 6, out_size, out_size) + (() if squeeze else (C,))
    if return_weights:
        return out.reshape(shape), weights.reshape(K, 6, out_size, out_size)
    return out.reshape(shape)


def convolve_exact(
    cube,
    s,
    *,
    normalized: bool = True,
    supersample: int = 1,
    out_size: int | None = None,
    dtype=np.float64,
) -> np.ndarray:
    """Exact convolution of a cube map with the Phong lobe max(r·ω,0)^s (Knuth et al. 2014, Eq. 4).

    For every output texel direction r: the lobe average
    ``Σ_j L_j max(r·ω_j,0)^s Ω_j / Σ_j max(r·ω_j,0)^s Ω_j`` over all source texels j (``normalized=True``)
    or the literal sum ``Σ_j L_j max(r·ω_j,0)^s Ω_j`` (``normalized=False``; ≈ average × 2π/(s+1)).
    ``s = np.inf`` is the mirror lookup (nearest source texel).  Cost O(N_out² · (k·N)²).

    Parameters
    ----------
    cube : array (6, N, N[, C])
    s : float ≥ 1 or np.inf
    normalized, supersample, out_size, dtype
        See :func:`convolve_exact_many`.

    Returns
    -------
    ndarray (6, n, n, C) float64 (``(6, n, n)`` for a 3-d input).

    Raises
    ------
    IBLError
        s < 1 or NaN; LayoutError for a wrong shape; RadianceError for NaN/Inf/negative radiance.
    """
    return convolve_exact_many(
        cube, [s], normalized=normalized, supersample=supersample, out_size=out_size, dtype=dtype
    )[0]


# ----------------------------------------------------------------------------------------------
# truncated-support gather with a rigorous error bound
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SparseInfo:
    """Diagnostics of :func:`convolve_sparse`.

    Attributes
    ----------
    s : float
        Phong exponent.
    theta_c : float
        Cut-off angle (rad): source texels whose centre is farther than θc from r may be neglected.
    rho : float
        Texel extent used in the bound (max centre-to-corner angle of a source (sub-)texel, rad).
    eps_target : float
        Target neglected-weight fraction the cut-off was chosen for.
    log_weight_bound : float
        log W_b(θc), the bound on the neglected Σ cos^s Ω (absolute, not normalised).
    n_bright : int
        Number of brightest source texels gathered exactly for every output texel.
    gathered_fraction : float
        Mean fraction of source texels gathered per output texel (cost relative to the exact method).
    theta_c_min : float
        Smallest per-tile cap (``theta_c`` is the largest) with the local bound.
    retried_tiles : int
        Tiles gathered again with a wider cap because their bound missed ``rtol``.
    kernel : str
        ``"float32"`` or ``"float64"``: the weight kernel used.
    """

    s: float
    theta_c: float
    rho: float
    eps_target: float
    log_weight_bound: float
    n_bright: int
    gathered_fraction: float
    theta_c_min: float = float("nan")
    retried_tiles: int = 0
    kernel: str = "float64"


def _texel_extent(m: int) -> float:
    """Max angle between a texel centre and its corners on a face of size m (same for all faces), widened by
    1e-9 relative and 1e-12 rad for the rounding of :func:`ibl_ref.environment.envmap.texel_max_radius`."""
    return envmap.texel_max_radius(m) * (1.0 + 1e-9) + 1e-12


#: steps of the upper Riemann sum in :func:`_log_integral_cos_pow` and the drop of log cos^m it covers
_RIEMANN_STEPS = 4096
_RIEMANN_LOG_DROP = 46.0  # e^-46 ≈ 1e-20: the rest is bounded by one box


def _log_integral_cos_pow(m: float, a: float) -> float:
    """Upper bound on log ∫_a^{π/2} cos^m φ dφ (m ≥ 1, 0 ≤ a < π/2), within ≈ 1.2 % of the exact value.

    ``cos^m`` is decreasing on [a, π/2], so the left Riemann sum over any partition bounds the
    integral from above.  The partition is uniform in ``u = m·log cos φ`` (each step lowers the
    integrand by the factor e^(−46/4096) ≈ 0.989, so each box exceeds its slice of the integral by at
    most 1/0.989), from ``u(a)`` down to ``u(a) − 46``; the remainder up to π/2 is bounded by one box
    of height ``cos^m`` at the last point.  The elementary bound ``cos^{m+1} a / ((m+1) sin a)`` (valid
    for a > 0) is taken when smaller.  (Standard library and NumPy only: the regularised incomplete
    beta function would need ``scipy.special``, ≈ 0.1–0.3 s of start-up.)
    """
    ca = math.cos(a)
    u0 = m * math.log(ca)
    u = u0 - np.linspace(0.0, _RIEMANN_LOG_DROP, _RIEMANN_STEPS + 1)
    phi = np.arccos(np.minimum(np.exp(u / m), 1.0))
    phi[0] = a
    widths = np.diff(phi)
    # log Σ_k exp(u_k) · width_k  (+ tail box), relative to exp(u0)
    terms = np.exp(u[:-1] - u0) * widths
    tail = math.exp(u[-1] - u0) * max(math.pi / 2 - float(phi[-1]), 0.0)
    cands = [u0 + math.log(float(terms.sum()) + tail)]
    if a > 0.0:
        # ∫_a cos^m φ dφ ≤ ∫_a cos^m φ sin φ / sin a dφ = cos^{m+1} a / ((m+1) sin a)
        cands.append((m + 1.0) * math.log(ca) - math.log(m + 1.0) - math.log(math.sin(a)))
    return min(cands)


def _log_bound_integral_t1(s: float, theta_c: float, rho: float) -> float:
    """The first term of :func:`_log_bound_integral` (that bound is ≥ log 2π + this)."""
    a = max(theta_c - 2.0 * rho, 0.0)
    return math.log(math.cos(rho)) + (s + 1.0) * math.log(math.cos(a)) - math.log(s + 1.0)


def _log_bound_integral(s: float, theta_c: float, rho: float) -> float:
    """log W_b from the continuous integral with the exponent shifted by 2ρ (module docstring)."""
    a = max(theta_c - 2.0 * rho, 0.0)
    t1 = _log_bound_integral_t1(s, theta_c, rho)
    t2 = math.log(math.sin(rho)) + _log_integral_cos_pow(s + 1.0, a) if rho > 0 else -np.inf
    return math.log(2.0 * np.pi) + float(np.logaddexp(t1, t2))


def _log_bound_annuli(s: float, theta_c: float, rho: float) -> float:
    """log W_b from annuli [θ_i, θ_i+Δ): weight ≤ cos^s θ_i, texel area ≤ annulus widened by ρ.

    Texels whose centre lies in the annulus are disjoint and lie inside the band [θ_i − ρ, θ_{i+1} + ρ],
    whose solid angle is 2π(cos(θ_i − ρ) − cos(θ_{i+1} + ρ)); their weight is at most cos^s θ_i.
    The best of a few widths Δ is taken (each is a valid bound).
    """
    return float(_log_bound_annuli_many(float(s), np.array([float(theta_c)]), float(rho))[0])


#: widths of the annuli of :func:`_log_bound_annuli`, in units of ρ (each gives a valid bound; the least is taken)
_ANNULUS_FRACS = (0.25, 0.5, 1.0, 2.0)


@functools.lru_cache(maxsize=4096)
def neglected_weight_bound(s: float, theta_c: float, rho: float) -> float:
    """log of a rigorous upper bound W_b on Σ_{j: θ_j ≥ θc} max(cos θ_j, 0)^s Ω_j (module docstring).

    Minimum of two valid bounds: the shifted-exponent integral (needs θc ≥ 2ρ; tight for small s) and
    an annulus sum (tight for large s on coarse grids).  Returns −inf when θc ≥ π/2 (every neglected
    texel then has cos ≤ 0 and weight 0).
    """
    if theta_c >= np.pi / 2:
        return -np.inf
    b = _log_bound_annuli(s, theta_c, rho)
    if theta_c >= 2.0 * rho:
        b = min(b, _log_bound_integral(s, theta_c, rho))
    return b


def _arange_rows(starts: np.ndarray, stop: float, delta: float):
    """``np.arange(a, stop, delta)`` for every a in ``starts`` as the rows of one matrix (``-inf``-padded
    after each row's end; row lengths returned too), element for element the values NumPy's arange gives
    (its fill: ``a``, ``a + delta``, then ``a + i·((a + delta) − a)``)."""
    lengths = np.maximum(np.ceil((stop - starts) / delta), 0).astype(np.intp)
    w = int(lengths.max()) if lengths.size else 0
    i = np.arange(w, dtype=np.float64)
    d2 = (starts + delta) - starts
    th = starts[:, None] + i[None, :] * d2[:, None]
    if w > 1:
        th[:, 1] = starts + delta
    if w > 0:
        th[:, 0] = starts
    return th, lengths


def _log_bound_annuli_many(s: float, thetas: np.ndarray, rho: float) -> np.ndarray:
    """:func:`_log_bound_annuli` at every θ of ``thetas`` at once: per θ and width, the sum over the annuli that
    ``np.arange(θ, π/2, Δ)`` starts, each θ's terms in their order (the padding after a row's end adds −inf,
    which leaves ``logaddexp`` unchanged): the values of one sum per θ and width, bit for bit."""
    best = np.full(thetas.shape, np.inf)
    for frac in _ANNULUS_FRACS:
        delta = max(rho * frac, 1e-6)
        th, lengths = _arange_rows(thetas, np.pi / 2, delta)
        pad = np.arange(th.shape[1])[None, :] >= lengths[:, None]
        lo = np.maximum(th - rho, 0.0)
        hi = np.minimum(th + delta + rho, np.pi)
        area = 2.0 * np.pi * (np.cos(lo) - np.cos(hi))
        with np.errstate(divide="ignore", invalid="ignore"):
            terms = s * np.log(np.cos(th)) + np.log(area)
        terms[pad] = -np.inf
        best = np.minimum(best, np.logaddexp.reduce(terms, axis=1))
    best[thetas >= np.pi / 2] = -np.inf
    return best


@functools.lru_cache(maxsize=64)
def _wb_grid(s: float, rho: float, cap_min: float, top: float):
    """θ from cap_min to top in steps of ρ/4 (and π/2), and the running minimum of log W_b(s, θ, ρ) there
    (:func:`convolve_sparse_many`); cached per arguments (read-only arrays).

    Every value is :func:`neglected_weight_bound`'s: the annulus sums at all θ at once
    (:func:`_log_bound_annuli_many`), the integral bound only where it can be the smaller one (it is at
    least ``log 2π + t1``, its first term, so where that is ≥ the annulus sum the minimum is the sum)."""
    grid = np.append(np.arange(cap_min, top, max(rho / 4.0, 1e-5)), np.pi / 2)
    log_wb = _log_bound_annuli_many(float(s), grid, float(rho))
    log_2pi = math.log(2.0 * np.pi)
    for i, g in enumerate(grid):
        if g >= np.pi / 2 or g < 2.0 * rho:
            continue
        if log_2pi + _log_bound_integral_t1(s, float(g), rho) < log_wb[i]:
            log_wb[i] = min(log_wb[i], _log_bound_integral(s, float(g), rho))
    log_wb_grid = np.minimum.accumulate(log_wb)
    grid.flags.writeable = False
    log_wb_grid.flags.writeable = False
    return grid, log_wb_grid


#: :func:`cutoff_angle` stops when its bracket is narrower than this many texel extents ρ (the caps it sets are
#: used on a grid of step ρ/4; the returned end of the bracket satisfies the bound whatever the width)
_CUTOFF_TOL = 2.0 ** -8


def _wb_at_most(s: float, theta: float, rho: float, target: float) -> bool:
    """``neglected_weight_bound(s, θ, ρ) ≤ target``: the annulus sum first, the integral bound only where it can
    decide (it is ≥ log 2π + its first term, so where that exceeds the target it cannot)."""
    if theta >= np.pi / 2 or _log_bound_annuli(s, theta, rho) <= target:
        return True
    if theta < 2.0 * rho or math.log(2.0 * np.pi) + _log_bound_integral_t1(s, theta, rho) > target:
        return False
    return _log_bound_integral(s, theta, rho) <= target


@functools.lru_cache(maxsize=1024)
def cutoff_angle(s: float, eps: float, rho: float) -> float:
    """Smallest θc ∈ (0, π/2] (bisection, W_b is non-increasing) with W_b(θc) ≤ eps · 2π/(s+1), to within
    :data:`_CUTOFF_TOL`·ρ (at most 60 halvings): the returned upper end of the bracket always satisfies the
    bound (it starts at π/2, where W_b = 0, and moves only to points that satisfy it)."""
    target = math.log(eps) + math.log(2.0 * np.pi / (s + 1.0))
    lo, hi = 0.0, np.pi / 2
    if neglected_weight_bound(s, lo, rho) <= target:
        return lo
    tol = _CUTOFF_TOL * rho
    for _ in range(60):
        if hi - lo <= tol:
            break
        mid = 0.5 * (lo + hi)
        if _wb_at_most(s, mid, rho, target):
            hi = mid
        else:
            lo = mid
    return hi


#: the same two constants for the compiled gather (:func:`ibl_ref.groundtruth.compiled_kernels.tile_gather`: no
#: Python per tile; per candidate the interval search and the copy into the scratch arrays), in units of one
#: of its weights; fitted by ``python benchmarks/bench_tile_size.py --probe …/courtyard.exr`` (2026-12-05, the
#: kernels compiled ahead of time; every width T ∈ {2…16} forced in 15 cells of sky + sun 64²–256² and the courtyard
#: probe 128²–256², s = 64…4096): the model's choice costs 1.002× the best width on average, 1.03× at most; a fixed
#: T = 4, 6, 8: 1.013×, 1.08×, 1.13×.  The constants before (2000 and 8, fitted on 2026-12-04 for numba's JIT
#: functions) chose T = 6–8 in the wider of these cells, where 4 was best
_TILE_OVERHEAD_COMPILED = 1000.0
_CAND_OVERHEAD_COMPILED = 4.0


def _tile_size(out_size: int, theta_c: float, m_src: int, n_bright: int, tile_overhead: float = _TILE_OVERHEAD_ELEMS,
               cand_overhead: float = _CAND_OVERHEAD_ELEMS) -> int:
    """Output tile width T minimising n_tiles·overhead + Σ T²·|candidates| (cost model)."""
    best, best_cost = 1, np.inf
    delta = (np.pi / 2) / out_size  # texel angle at a face centre
    for T in sorted({1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, out_size}):
        if T > out_size:
            continue
        n_tiles = 6 * math.ceil(out_size / T) ** 2
        q = min(theta_c + 0.75 * T * delta, np.pi)
        cand = m_src * (1.0 - math.cos(q)) / 2.0 + n_bright
        cost = n_tiles * (tile_overhead + cand * (T * T + cand_overhead))
        if cost < best_cost:
            best, best_cost = T, cost
    return best


def _column_extremes(a: np.ndarray, ok=None, axis: int = 0):
    """``(max, min)`` of a (…, C) array over ``axis`` (not the last), one channel at a time (a contiguous
    reduction: ≈ 25× faster than over an axis followed by a short one; exact, so the same result); entries
    where ``ok`` is False are left out (−inf / +inf where none is left)."""
    mx, mn = [], []
    for c in range(a.shape[-1]):
        x = a[..., c]
        mx.append((x if ok is None else np.where(ok, x, -np.inf)).max(axis=axis))
        mn.append((x if ok is None else np.where(ok, x, np.inf)).min(axis=axis))
    return np.stack(mx, axis=-1), np.stack(mn, axis=-1)


def _bright_set(rad: np.ndarray, omega: np.ndarray, n_bright, bright_factor: float, max_bright: int) -> np.ndarray:
    key = channel_max(rad)
    M = key.shape[0]
    if n_bright == "auto":
        mean = float(np.sum(key * omega) / np.sum(omega))
        k = int(np.count_nonzero(key > bright_factor * mean)) if mean > 0 else 0
        k = min(k, max_bright, M)
    else:
        if isinstance(n_bright, bool) or not isinstance(n_bright, (int, np.integer)) or n_bright < 0:
            raise IBLError(f"n_bright must be 'auto' or a non-negative integer, got {n_bright!r}")
        k = min(int(n_bright), M)
    if k == 0:
        return np.zeros(0, dtype=np.intp)
    return np.sort(np.argpartition(-key, k - 1)[:k])


#: side (texels) of the source blocks whose bounding cones :func:`convolve_sparse_many` tests first when it
#: looks for a tile's cap (then only those blocks' texels): a two-level search in NumPy, no KD-tree.  The
#: same blocks carry the per-channel radiance extremes of the local bound.
_CAP_BLOCK = 8
#: share of ``rtol`` left to the far-field term of the local bound (texels beyond the far cap θ_far, bounded
#: with the global radiance extremes); the rest goes to the near annulus and to the float32 kernel's rounding
_FAR_SHARE = 0.1
#: share of the accuracy target τ that the first compiled attempt's left-out bright weights may take (at the mean
#: radiance; :func:`convolve_sparse_many`)
_BRIGHT_CUT_SHARE = 0.05
#: the first cap of a tile aims at this fraction of its share of ``rtol`` (the a-priori estimate of the
#: gathered weight and average can be off; a tile whose bound misses ``rtol`` is gathered again, wider)
_CAP_MARGIN = 0.8
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


@functools.lru_cache(maxsize=4)
def _tile_layout(out_size: int, faces: tuple, T: int):
    """:func:`_tile_layout_of`, cached per sizes (≈ 40 bytes per output texel: the last few face subsets only)."""
    return _tile_layout_of(out_size, faces, T)


@functools.lru_cache(maxsize=32)
def _tile_radius(out_size: int, T: int) -> float:
    """The largest tile radius of :func:`_tile_layout_of` over face 0 (all faces have the same tiles)."""
    return _tile_layout_of(out_size, (0,), T)[5]


def _tile_layout_of(out_size: int, faces: tuple, T: int):
    """Tiles of T×T output texels (row-major per face, faces in the given order; the last ones on a face
    smaller when T does not divide ``out_size``), padded to the largest tile by repeating its last texel:
    ``(IDX (n_t, B) flat output indices into the (F·n·n) output of the face subset, TD (n_t, B, 3) directions,
    CEN (n_t, 3) unit centres (normalised sums), ANG (n_t, B) angles to the centre (``atan2(|d × c|, d·c)``,
    accurate near 0), VALID (n_t, B), the largest tile radius over face 0)``, computed per tile shape at once;
    cached per sizes (read-only arrays)."""
    dst = envmap.texel_directions(out_size)
    starts = np.arange(0, out_size, T, dtype=np.intp)
    # tiles in the order (face, first row, first column); grouped by shape (h, w) (at most four shapes)
    fi_t, r0_t, c0_t = (x.ravel() for x in np.meshgrid(np.arange(len(faces), dtype=np.intp), starts, starts,
                                                       indexing="ij"))
    order = np.stack([fi_t, np.asarray(faces, dtype=np.intp).reshape(-1)[fi_t], r0_t, c0_t], axis=1)
    h_t, w_t = np.minimum(T, out_size - r0_t), np.minimum(T, out_size - c0_t)
    groups = {}
    for code in sorted(set((h_t * (T + 1) + w_t).tolist()), reverse=True):
        h, w = divmod(code, T + 1)
        groups[(h, w)] = np.flatnonzero((h_t == h) & (w_t == w))
    n_t = len(order)
    B = max(h * w for h, w in groups)
    IDX = np.empty((n_t, B), dtype=np.intp)
    TD = np.empty((n_t, B, 3))
    ANG = np.empty((n_t, B))
    CEN = np.empty((n_t, 3))
    VALID = np.zeros((n_t, B), dtype=bool)
    t_rad = 0.0
    for (h, w), members in groups.items():
        mem = np.array(members)
        fi, f, r0, c0 = (order[mem, j] for j in range(4))
        rr = r0[:, None, None] + np.arange(h)[None, :, None]
        cc = c0[:, None, None] + np.arange(w)[None, None, :]
        if len(groups) == 1:  # T divides the face: the tiles by a transposed copy (the same array as the gather)
            td = envmap.face_blocks(dst[list(faces)], T)
        else:
            td = dst[f[:, None, None], rr, cc].reshape(len(members), h * w, 3)
        idx = ((fi[:, None, None] * out_size + rr) * out_size + cc).reshape(len(members), h * w)
        cen = td.sum(axis=1)
        cen /= np.linalg.norm(cen, axis=1, keepdims=True)
        # atan2(|d × c|, d·c), by components (np.cross and norm make several temporaries: 3× slower)
        dx, dy, dz = td[..., 0], td[..., 1], td[..., 2]
        ex, ey, ez = cen[:, None, 0], cen[:, None, 1], cen[:, None, 2]
        cx, cy, cz = dy * ez - dz * ey, dz * ex - dx * ez, dx * ey - dy * ex
        ang = np.arctan2(np.sqrt(cx * cx + cy * cy + cz * cz), dx * ex + dy * ey + dz * ez)
        k = h * w
        if len(groups) == 1:  # (every tile, in order: the arrays themselves)
            IDX, TD, ANG, CEN = idx, td, ang, cen
            VALID[:] = True
            continue
        IDX[mem, :k], TD[mem, :k], ANG[mem, :k], VALID[mem, :k], CEN[mem] = idx, td, ang, True, cen
        IDX[mem, k:], TD[mem, k:], ANG[mem, k:] = idx[:, -1:], td[:, -1:], ang[:, -1:]
    if faces and faces[0] == 0:
        t_rad = float(ANG[: starts.size ** 2].max())
    else:
        t_rad = _tile_radius(out_size, T)
    for x in (IDX, TD, ANG, CEN, VALID):
        x.flags.writeable = False
    return IDX, TD, CEN, ANG, VALID, t_rad


class _Sources:
    """Source texels of one :func:`convolve_sparse_many` call, arranged for the cap searches.

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
        self.blk_max, self.blk_min = _column_extremes(r, ok, axis=1)

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

    def local_extremes_compiled(self, ck, cen, q, k=8):
        """:meth:`local_extremes` by :func:`ibl_ref.groundtruth.compiled_kernels.cone_extremes` (super-blocks of
        k × k blocks)."""
        if not hasattr(self, "_sup"):
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
            self._sup = (np.ascontiguousarray(c), sup_alpha, np.ascontiguousarray(mem.astype(np.int64)))
        sc, sa, sm = self._sup
        C = self.blk_max.shape[1]
        lmax, lmin = np.empty((len(q), C)), np.empty((len(q), C))
        ck.cone_extremes(np.array(cen, dtype=np.float64), np.array(q, dtype=np.float64), np.array(self.cen),
                         float(self.alpha), self.blk_max, self.blk_min, sc, sa, sm, lmax, lmin)  # writeable copies: one
        # compiled signature (the cached geometry is read-only)
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


@functools.lru_cache(maxsize=8)
def _direction_columns(m: int):
    """The texel directions of the m² grid as three contiguous read-only columns X, Y, Z (M,)."""
    d = envmap.texel_directions(m).reshape(-1, 3)
    cols = tuple(np.ascontiguousarray(d[:, i]) for i in range(3))
    for x in cols:
        x.flags.writeable = False
    return cols


def _compiled_sources(m, rad, omega, bright):
    """Source arrays of :func:`ibl_ref.groundtruth.compiled_kernels.tile_gather`: directions X, Y, Z (M,) of the
    m² grid (read-only, cached), and the weight rows ``[L·Ω, Ω]`` in groups of ≤ 3 channels plus Ω, padded to 4
    rows (zero for the bright texels ``bright``): ``[(rows (4, M), (output columns, input columns)), …]`` and the
    bright texels' rows (nb, 4·groups).  (The products L·Ω are those of the NumPy path's ``[L, 1]·Ω``.)"""
    M, C = rad.shape
    X, Y, Z = _direction_columns(m)
    groups = []
    for g0 in range(0, max(C, 1), 3):
        ch = list(range(g0, min(g0 + 3, C))) + [C]
        rws = np.zeros((4, M))
        for j, c in enumerate(ch):
            if c < C:
                np.multiply(rad[:, c], omega, out=rws[j])
            else:
                rws[j] = omega
        rws[:, bright] = 0.0
        groups.append((rws, (ch, slice(4 * len(groups), 4 * len(groups) + 4))))
    bright_rw = np.zeros((len(bright), 4 * len(groups)))
    for gi, (_rws, (ch, _sl)) in enumerate(groups):
        for j, c in enumerate(ch):
            bright_rw[:, 4 * gi + j] = rad[bright, c] * omega[bright] if c < C else omega[bright]
    return X, Y, Z, groups, bright_rw


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


#: fewest tiles per thread of :func:`_tile_gather_threads`
_TILES_PER_THREAD_MIN = 32


def _tile_gather_threads(ck, threads, cen, rows, caps, arad, frames, m, X, Y, Z, rws, bdirs, brw, groups, s, s_int,
                         rowmax, c_floor, acc, logmx, count, pairs):
    """:func:`ibl_ref.groundtruth.compiled_kernels.tile_gather` on ``threads`` threads: the tiles in runs of
    consecutive ones (views of the inputs and outputs: nothing copied), which each thread takes in turn as it
    becomes free (tiles differ in work, e.g. near the bright texels).  Every tile is computed by the same code on
    the same inputs as in one call: the result does not depend on ``threads`` or on which thread took a run."""
    nt = cen.shape[0]
    # (a few tiles, e.g. a later attempt's: starting a thread costs more than their gather)
    threads = max(1, min(int(threads), nt // _TILES_PER_THREAD_MIN))
    if threads <= 1:
        ck.tile_gather(cen, rows, caps, arad, frames, m, X, Y, Z, rws, bdirs, brw, s, s_int, rowmax, c_floor, acc,
                       logmx, count, groups, pairs)
        return
    import threading

    run_len = max(2 * _TILES_PER_THREAD_MIN, -(-nt // (8 * threads)))  # ≈ 8 runs per thread
    starts = list(range(0, nt, run_len))
    lock = threading.Lock()
    nxt = [0]
    errors = []

    def work():
        try:
            while True:
                with lock:
                    if errors or nxt[0] >= len(starts):
                        return
                    a = starts[nxt[0]]
                    nxt[0] += 1
                b = min(a + run_len, nt)
                ck.tile_gather(cen[a:b], rows[a:b], caps[a:b], arad[a:b], frames, m, X, Y, Z, rws, bdirs, brw, s,
                               s_int, rowmax, c_floor, acc[a:b], logmx[a:b], count[a:b], groups, pairs[a:b])
        except BaseException as exc:  # re-raised on the calling thread
            with lock:
                errors.append(exc)

    # plain threads (no executor: concurrent.futures costs a process ≈ 1–5 ms of imports)
    others = [threading.Thread(target=work, name=f"ibl_tiles_{j}", daemon=True) for j in range(1, threads)]
    for th in others:  # the other threads …
        th.start()
    try:
        work()  # … and this one
    finally:
        for th in others:
            th.join()
    if errors:
        raise errors[0]


def convolve_sparse_many(
    cube,
    exponents,
    *,
    rtol: float = 1e-3,
    out_size: int | None = None,
    supersample: int = 1,
    n_bright="auto",
    bright_factor: float = 8.0,
    max_bright: int = 2048,
    theta_c: float | None = None,
    return_info: bool = False,
    faces=None,
    local: bool = True,
    kernel: str = "auto",
    dark_floor: float = 1e-6,
    impl: str = "numpy",
    threads: int = 1,
    _sample: int = 0,
):
    """Truncated-support gather of the normalised Eq. 4 lobe average, several exponents.

    Returns ``(maps (K,F,n,n,C), bounds (K,F,n,n,C))`` (plus a list of :class:`SparseInfo` with
    ``return_info=True``); see :func:`convolve_sparse`.  ``faces`` (sequence of output face indices
    0…5, default all six, F = their number) restricts the output to those faces: every tile is
    computed independently, so the result on a face is bit-for-bit the same as in the full call
    (used by :func:`ibl_ref.groundtruth.convolve.convolve` to split the work between workers).

    ``impl="compiled"`` runs the gather of every tile (its cap's texels found by face-row intervals, the
    weights, the bright set) in :func:`ibl_ref.groundtruth.compiled_kernels.tile_gather` (float64; its rounding
    bound, :func:`~ibl_ref.groundtruth.kernel_spec.weight_error`, replaces the float32 kernel's in the
    bound); tiles, caps, attempts and the bound are the same code as for ``impl="numpy"``, except that the first
    attempt leaves out the bright texels whose weight from every row of the tile is below δ0 (and sets gathered weights
    below δ0 to 0), an absolute error ≤ δ0 per (row, texel) pair that the bound charges like the rounding allowance
    (δ0 from :data:`_BRIGHT_CUT_SHARE`; every later attempt, and every tile whose bound then misses, uses e^-700).
    ``threads`` > 1 (compiled
    only): the tiles are gathered by that many threads (the kernel releases the GIL; every tile's sums are computed
    by one thread exactly as in a serial call, so the result is bit-for-bit the same for every thread count).

    ``_sample > 0`` (used by the planner of :func:`ibl_ref.groundtruth.convolve.convolve`, see
    :func:`estimate_candidates`): no gather; the first attempt's caps of that many evenly spaced tiles only,
    returned as the mean number of source texels per output texel, one per exponent.
    """
    a, squeeze = check_cube(cube)
    n = a.shape[1]
    out_size, supersample = _check_sizes(out_size, n, supersample)
    s_list = [check_exponent(s) for s in np.atleast_1d(np.asarray(exponents, dtype=object))]
    if not s_list:
        raise IBLError("no Phong exponents given")
    try:
        rtol = float(rtol)
    except (TypeError, ValueError):
        raise IBLError(f"rtol must be a positive number, got {rtol!r}") from None
    if not (0.0 < rtol < 1.0):
        raise IBLError(f"rtol must be in (0, 1), got {rtol!r}")
    if kernel not in ("auto", "float32", "float64"):
        raise IBLError(f"kernel must be 'auto', 'float32' or 'float64', got {kernel!r}")
    if impl not in ("numpy", "compiled"):
        raise IBLError(f"impl must be 'numpy' or 'compiled', got {impl!r}")
    if impl == "compiled" and kernel == "float32":
        raise IBLError("kernel='float32' is the NumPy path's kernel; the compiled gather is float64 (kernel='auto')")
    compiled = impl == "compiled"
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise IBLError(f"threads must be an integer ≥ 1, got {threads!r}")
    ck = None
    if compiled:
        from .kernel_choice import compiled
        from .kernel_spec import POWI_MAX, sum_error, weight_error

        ck = compiled()
    try:
        dark_floor = float(dark_floor)
    except (TypeError, ValueError):
        raise IBLError(f"dark_floor must be a number in [0, 1], got {dark_floor!r}") from None
    if not (0.0 <= dark_floor <= 1.0):
        raise IBLError(f"dark_floor must be in [0, 1], got {dark_floor!r}")
    C = a.shape[-1]
    K = len(s_list)
    faces = check_faces(faces)
    nF = len(faces)
    P = nF * out_size * out_size
    maps = np.empty((K, P, C))
    bounds = np.zeros((K, P, C))
    infos = []

    src_dirs, omega, rad = _sources(a, supersample)
    M = src_dirs.shape[0]
    bright = _bright_set(rad, omega, n_bright, bright_factor, max_bright)
    rest = np.ones(M, dtype=bool)
    rest[bright] = False
    if rest.any():
        rad_rest = rad[rest] if bright.size else rad
        l_max_out, l_min_out = _column_extremes(rad_rest)  # (C,)
        key = channel_max(rad_rest)
        l_ref = float(np.sum(key * omega[rest]) / np.sum(omega[rest]))
        l_top = float(key.max())
    else:
        l_max_out = l_min_out = np.zeros(C)
        l_ref = l_top = 0.0
    # the single-cap rule (local=False, or theta_c given): ε·L_max,out ≈ rtol·(typical radiance), i.e. relative
    # error ≈ rtol where P ≈ mean radiance; also the typical cap that sets the tile size
    eps = rtol * (min(1.0, l_ref / l_top) if l_top > 0 else 1.0)
    eps = max(eps, 1e-300)
    rho = _texel_extent(n * supersample)
    tau = rtol / (1.0 + rtol)  # abs ≤ τ·P ⇔ abs/(P − abs) ≤ rtol (the relative bound of convolve())
    floor = dark_floor * l_ref
    lo = np.maximum(l_min_out, floor)
    span = l_max_out - lo
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(span > 0, lo / np.where(span > 0, span, 1.0), np.inf)
    eps_far = max(_FAR_SHARE * tau * float(ratio.min()) if np.isfinite(ratio.min()) else 1.0, 1e-300)

    geometry = {}  # tile size → per-tile output indices, directions, centre, angles
    is_bright = np.zeros(M, dtype=bool)
    is_bright[bright] = True
    sources = slabs = None
    if not compiled:
        rad_w = np.concatenate([rad, np.ones((M, 1))], axis=1) * omega[:, None]
        # source directions and weights with one dummy entry (index M: direction 0 → weight 0) for the pads
        src_dirs_pad = np.concatenate([src_dirs, np.zeros((1, 3))])
        src_dirs_pad_t = np.ascontiguousarray(src_dirs_pad.T)
        rad_w_pad = np.concatenate([rad_w, np.zeros((1, C + 1))])
        bright_dirs_t = np.ascontiguousarray(src_dirs[bright].T)
        rad_w_bright = rad_w[bright]
    omega_ratio = float(omega.max() / omega.min())

    for k, s in enumerate(s_list):
        if not np.isfinite(s):
            if _sample:
                infos.append(1.0)
                continue
            maps[k] = _mirror(a, out_size)[list(faces)].reshape(-1, C)
            infos.append(SparseInfo(s, 0.0, rho, 0.0, -np.inf, 0, 1.0 / M))
            continue
        single = theta_c is not None or not local
        if theta_c is None:
            th = cutoff_angle(s, eps, rho)
        else:
            th = float(min(max(theta_c, 0.0), np.pi / 2))
        if (1.0 - math.cos(min(th, np.pi))) / 2.0 > 0.4:
            # the cap covers most of the lobe's hemisphere: the dense exact gather is cheaper
            if _sample:
                infos.append(float(M))
                continue
            ex = convolve_exact_many(a, [s], supersample=supersample, out_size=out_size)[0][list(faces)].reshape(-1, C)
            maps[k] = ex
            bounds[k] = 1e-12 * ex
            infos.append(SparseInfo(s, np.pi / 2, rho, eps, -np.inf, int(bright.size), 1.0))
            continue
        # tiles of T×T output texels sharing one candidate list
        if compiled:
            # the compiled gather's first attempt leaves out the bright texels whose weight from every row of the
            # tile is below δ0 = e^log_d0 (beyond acos(δ0^(1/s)) + the tile radius; gathered weights below δ0 are 0):
            # an absolute weight error ≤ δ0 per pair, charged in the allowance `und` with the rounding (below); δ0
            # keeps that term ≤ _BRIGHT_CUT_SHARE·τ for a texel as bright as the mean radiance l_ref even if every
            # source texel were a pair.  Tiles whose bound still misses (darker ones) are gathered again, as every
            # later attempt, with e^-700
            log_d0 = -700.0
            own0 = s * math.log(max(math.cos(min(rho, np.pi / 2)), 1e-300))
            if own0 >= -600.0 and l_ref > 0.0 and not single:  # (one cap: no second attempt)
                l_all = float(rad.max())
                log_d0 = max(math.log(_BRIGHT_CUT_SHARE * tau * l_ref / ((l_all + l_ref) * M * omega_ratio)) + own0,
                             -700.0)
            a_b = math.acos(math.exp(log_d0 / s)) + th
            nb_eff = bright.size * (1.0 - math.cos(min(a_b, np.pi))) / 2.0
            T = _tile_size(out_size, th, M, nb_eff, _TILE_OVERHEAD_COMPILED, _CAND_OVERHEAD_COMPILED)
        else:
            T = _tile_size(out_size, th, M, int(bright.size))
        IDX, TD, CEN, ANG, VALID, t_rad0 = (_tile_layout_of if _sample else _tile_layout)(out_size, tuple(faces), T)
        if _sample:
            # (sorted distinct indices; not np.unique, whose first call imports numpy.ma: ≈ 10 ms of a process)
            pick = np.array(sorted(set(np.linspace(0, len(CEN) - 1, min(_sample, len(CEN))).astype(np.intp).tolist())),
                            dtype=np.intp)
            IDX, TD, CEN, ANG, VALID = IDX[pick], TD[pick], CEN[pick], ANG[pick], VALID[pick]
        n_t, B = IDX.shape
        a_max = ANG.max(axis=1)
        # the largest tile radius, from face 0 whatever the face subset (all faces have the same tiles): the kernel
        # choice below is the same for every subset
        t_rad = t_rad0 * (1.0 + 1e-9)
        # every cap reaches ρ beyond its tile's texels: each row's own source texel (within ρ) is gathered
        cap_min = rho + _ANGLE_MARGIN
        th_far = max(th if single else cutoff_angle(s, eps_far, rho), cap_min)
        log_lobe = math.log(2.0 * np.pi / (s + 1.0))
        # W_b tabulated from cap_min to beyond every θ a bound looks up (step ρ/4), made non-increasing by a
        # running minimum (W_b(θ') bounds every texel beyond θ ≥ θ': valid); a texel uses the grid angle ≤ its θ
        top = min(th_far + t_rad + 2.0 * _ANGLE_MARGIN, np.pi / 2)
        grid, log_wb_grid = _wb_grid(float(s), float(rho), float(cap_min), float(top))

        def cap_for(eps_t):
            i = np.searchsorted(-log_wb_grid, -(np.log(eps_t) + log_lobe), side="left")
            return np.minimum(grid[np.minimum(i, grid.size - 1)], th_far)

        def log_wb_at(theta):
            gi = np.searchsorted(grid, theta, side="right") - 1
            return np.where(gi >= 0, log_wb_grid[np.maximum(gi, 0)], 0.0 * theta + np.inf)

        if sources is None:
            sources = _Sources(src_dirs, rad, is_bright, n * supersample)
        # kernel: float32 where its rounding bound is small (decided from bounds valid for every face subset):
        # a row and a candidate are within a + q, q ≤ θ_far + t_rad
        # (slab texels lie within the slab's plane diagonal (b−1)·√2·2/m of each other: the gnomonic map from
        # the face plane to the sphere shortens distances)
        al_slab = (_SLAB - 1) * math.sqrt(2.0) * 2.0 / (n * supersample)
        q_top = th_far + t_rad + _ANGLE_MARGIN + 2.0 * al_slab
        x_glob = 1.0 - math.cos(min(q_top + t_rad, np.pi))
        own_log = s * math.log(max(math.cos(min(rho, np.pi / 2)), 1e-300))
        n_terms = int(_series_terms(s, x_glob + _gamma(8, _U32) * (q_top + t_rad) ** 2))
        use32 = (not compiled and kernel != "float64" and n_terms > 0 and x_glob <= _X32_MAX
                 and own_log >= _OWN_LOG_MIN)
        if use32:  # its rounding bound at the typical cap (first attempt) takes ≤ 20 % of rtol
            q_typ = th + t_rad + _ANGLE_MARGIN + 2.0 * al_slab
            eta_typ = float(_kernel32_eta(s, n_terms, t_rad, q_typ, t_rad + q_typ))
            use32 = kernel == "float32" or 2.2 * eta_typ <= 0.2 * tau
        if kernel == "float32" and not use32:
            raise IBLError(f"the float32 kernel cannot bound s = {s:g} on this grid (cap too wide or lobe narrower "
                           "than a texel); use kernel='auto'")
        fp_share = 2.2 * eta_typ if use32 else 0.0
        if use32 and slabs is None:
            slabs = _Slabs(src_dirs, rad_w, is_bright, n * supersample)
        rowmax = (not use32) and own_log < -600.0
        if compiled:
            # c^s by binary powering for integer exponents (own weight ≥ e^-600: no reference needed), else
            # exp(s·log c), relative to the row's largest cosine where the own weight may underflow
            s_int = int(s) if (float(s).is_integer() and s <= POWI_MAX and own_log >= -600.0) else 0
            eta_w, eps_w = weight_error(s, bool(s_int), rowmax)
            if ("rw4",) not in geometry:
                geometry[("rw4",)] = _compiled_sources(n * supersample, rad, omega, bright)
            l_und = float(rad.max()) if rad.size else 0.0

        # caps per attempt: local (radiance extremes within the far cap), then local with κ ≥ 1 (an average
        # above the local maximum, e.g. next to the bright set), then the far cap
        q_far = th_far + a_max + _ANGLE_MARGIN
        if single:
            lmax2, lmin2 = np.broadcast_to(l_max_out, (n_t, C)), np.broadcast_to(l_min_out, (n_t, C))
            attempts = [np.full(n_t, th_far)]
        else:
            lmax2, lmin2 = (sources.local_extremes_compiled(ck, CEN, q_far) if compiled
                            else sources.local_extremes(CEN, q_far))
            with np.errstate(invalid="ignore", divide="ignore"):
                kap = np.where(lmax2 > lmin2, (lmax2 - lmin2) / np.maximum(lmin2, max(floor, 1e-300)), 0.0).max(axis=1)
            tau_near = max(tau * (1.0 - _FAR_SHARE) - fp_share, 1e-3 * tau)
            with np.errstate(divide="ignore"):
                eps1 = np.minimum(_CAP_MARGIN * tau_near / np.maximum(kap, 1e-12), 0.5)
                eps2 = np.minimum(_CAP_MARGIN * tau_near / np.maximum(kap, 1.0), 0.5)
            attempts = [cap_for(eps1), cap_for(eps2), np.full(n_t, th_far)]
        if _sample:
            q0 = attempts[0] + a_max + _ANGLE_MARGIN
            infos.append(float(np.mean((1.0 - np.cos(np.minimum(q0, np.pi))) / 2.0 * M)) + bright.size)
            continue
        todo = np.arange(n_t)
        prev = np.full(n_t, -1.0)
        gathered = 0
        retried = 0
        caps_used = np.zeros(n_t)
        for att, caps in enumerate(attempts):
            # a tile is gathered again when its cap grows, or (attempt 1) when attempt 0 left out weights below δ0
            todo = todo[(caps[todo] > prev[todo]) | (att == 1 and compiled and log_d0 > -700.0)]
            if todo.size == 0:
                break
            if att > 0:
                retried += todo.size
            prev[todo] = caps[todo]
            caps_used[todo] = caps[todo]
            q_t = caps + a_max + _ANGLE_MARGIN
            acc = np.empty((todo.size, B, C + 1))
            log_mx = np.zeros((todo.size, B))
            eta = np.full(todo.size, 1e-12)
            und = np.zeros(todo.size)
            pos = np.empty(n_t, dtype=np.intp)
            pos[todo] = np.arange(todo.size)
            est = np.minimum(M, (1.0 - np.cos(np.minimum(q_t + sources.alpha, np.pi))) / 2.0 * M * 1.5 + _KC)
            if use32:
                # series terms per tile (from the tile's own largest x: the same in every face subset); a batch
                # holds tiles with the same number of terms
                r_all = a_max + q_t + 2.0 * slabs.alpha
                terms = _series_terms(s, 1.0 - np.cos(np.minimum(r_all, np.pi)) + _gamma(8, _U32) * r_all**2)
            else:
                terms = np.zeros(n_t, dtype=np.intp)
            order = todo[np.lexsort((est[todo], terms[todo]))]
            if compiled:
                log_cut = log_d0 if att == 0 else -700.0
                X, Y, Z, groups, bright_rw = geometry[("rw4",)]
                if ("bright_groups",) not in geometry:  # the bright texels' directions and groups, once per call
                    bdirs = np.ascontiguousarray(src_dirs[bright])
                    geometry[("bright_groups",)] = bdirs, ck.bright_groups(bdirs)
                bdirs, bgroups = geometry[("bright_groups",)]
                for rws, cols in groups:
                    acc_g = np.empty((todo.size, B, 4))
                    lm_g = np.empty((todo.size, B))
                    cnt = np.empty(todo.size, dtype=np.int64)
                    pairs = np.empty(todo.size, dtype=np.int64)
                    _tile_gather_threads(ck, threads, CEN[todo], TD[todo], q_t[todo], a_max[todo],
                                         envmap.face_frames("openexr"), n * supersample, X, Y, Z, rws,
                                         bdirs, bright_rw[:, cols[1]], bgroups,
                                         float(s), s_int, rowmax, math.exp(log_cut / s), acc_g, lm_g, cnt, pairs)
                    acc[..., cols[0]] = acc_g[..., : len(cols[0])]
                    log_mx = lm_g
                m_t = cnt.astype(np.float64)
                eta = eta_w + sum_error(cnt)
                # absolute errors of the smallest weights and of the weights left out below e^-700 (per pair ≤
                # eps_w, relative to the weight scale 1: the row maximum or c^s with c ≤ 1) and, in attempt 0, of
                # those left out or set to 0 below δ0 (≤ δ0 more per pair), against W_in ≥ the own texel's
                # weight · Ω_min
                eps_pair = eps_w + (math.exp(log_cut) if log_cut > -700.0 else 0.0)
                und = m_t * eps_pair * math.exp(-(0.0 if rowmax else own_log)) * omega_ratio
                gathered += int(pairs.sum()) * B  # (the pairs computed: the bright texels left out are not)
            elif use32:
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
                        und[r] = _kernel32_underflow(wmax * _SLAB**2 + bright.size, own_log, omega_ratio)
                        if bright.size:
                            acc[r] += _bright_sums(TD[tb], bright_dirs_t, rad_w_bright, s)
                        gathered += si.size * _SLAB**2 * B
                        i0 += sel.size
            else:
                # (batches sized by the texels within q at the mean density: the lists are built per batch)
                est64 = np.maximum((1.0 - np.cos(np.minimum(q_t, np.pi))) / 2.0 * M, 1.0)
                for tb in _tile_batches(order, est64, B, _CHUNK_ELEMS, terms):
                    r = pos[tb]
                    ii, _cnt = sources.cap_lists(CEN[tb], q_t[tb], M)
                    if rowmax and bright.size:  # the row maxima include the bright set
                        ii = np.concatenate([ii, np.broadcast_to(bright, (tb.size, bright.size))], axis=1)
                    acc[r], mx = _gather_batch64(tb, ii, TD, src_dirs_pad_t, rad_w_pad, s, rowmax)
                    log_mx[r] = s * mx[..., 0]
                    if bright.size and not rowmax:
                        acc[r] += _bright_sums(TD[tb], bright_dirs_t, rad_w_bright, s)
                    gathered += ii.size * B
            # per-texel bounds of the attempt's tiles; tiles whose bound misses rtol go to the next attempt
            tt = todo
            if compiled:  # the same formula as below, in one compiled pass
                worst = np.empty(tt.size)
                ck.tile_bounds(acc, log_mx, np.broadcast_to(eta, tt.shape).astype(np.float64),
                               np.broadcast_to(und, tt.shape).astype(np.float64), l_und, ANG[tt], q_t[tt], q_far[tt],
                               0.5 * _ANGLE_MARGIN, grid, log_wb_grid, np.ascontiguousarray(lmax2[tt]),
                               np.ascontiguousarray(lmin2[tt]), np.asarray(l_max_out, dtype=np.float64),
                               np.asarray(l_min_out, dtype=np.float64), VALID[tt], IDX[tt], maps[k], bounds[k], worst)
                todo = np.sort(tt[~(worst <= tau)])
                continue
            p_avg = acc[..., :C] / acc[..., C:]
            # log W_in (absolute Σ cos^s Ω over the gathered set), lowered by the kernel's error bound
            log_win = log_mx + np.log(acc[..., C]) - np.log1p(eta + und)[:, None]
            l_u = lmax2[tt][:, None, :]
            e_fp = (2.0 * eta / (1.0 - eta))[:, None, None] * p_avg + und[:, None, None] * (l_u + p_avg)
            # neglected texels of a row at angle a from the centre: beyond q − a (the near annulus up to
            # q_far − a: local extremes) and beyond q_far − a (global extremes)
            ang = ANG[tt]
            lw1 = log_wb_at(q_t[tt][:, None] - 0.5 * _ANGLE_MARGIN - ang)
            lw2 = log_wb_at(q_far[tt][:, None] - 0.5 * _ANGLE_MARGIN - ang)
            with np.errstate(over="ignore", invalid="ignore"):
                f1 = np.where(np.isneginf(lw1), 0.0, np.exp(np.minimum(lw1 - log_win, 700.0)))
                f2 = np.where(np.isneginf(lw2), 0.0, np.exp(np.minimum(lw2 - log_win, 700.0)))
            d_loc = np.maximum(np.maximum(lmax2[tt][:, None, :] - p_avg, p_avg - lmin2[tt][:, None, :]), 0.0) + e_fp
            d_glob = np.maximum(np.maximum(l_max_out - p_avg, p_avg - l_min_out), 0.0) + e_fp
            b_abs = (np.minimum(f1, f2)[..., None] * d_glob + np.maximum(f1 - f2, 0.0)[..., None] * d_loc
                     + e_fp + 1e-12 * p_avg)
            vt = VALID[tt]
            maps[k, IDX[tt][vt]] = p_avg[vt]
            bounds[k, IDX[tt][vt]] = b_abs[vt]
            with np.errstate(divide="ignore", invalid="ignore"):
                worst = np.where(vt[..., None], b_abs / p_avg, 0.0).reshape(tt.size, -1).max(axis=1)
            todo = np.sort(tt[~(worst <= tau)])
        infos.append(SparseInfo(s, float(caps_used.max()), rho, eps_far if not single else eps,
                                float(neglected_weight_bound(s, float(caps_used.max()), rho)), int(bright.size),
                                gathered / (P * M), float(caps_used.min()), int(retried),
                                "compiled" if compiled else ("float32" if use32 else "float64")))
    if _sample:
        return infos
    shape = (K, nF, out_size, out_size) + (() if squeeze else (C,))
    out = (maps.reshape(shape), bounds.reshape(shape))
    return out + (infos,) if return_info else out


def estimate_candidates(cube, exponents, *, rtol: float = 1e-3, out_size: int | None = None, impl: str = "numpy",
                        sample: int = 256) -> list:
    """Per exponent, the mean number of source texels per output texel the sparse gather collects in its first
    attempt (its own cap rule — local radiance extremes, per-tile caps — on ``sample`` evenly spaced tiles of every
    face): what its cost grows with, for the planner.  Retries (tiles whose bound misses rtol) are not included."""
    return convolve_sparse_many(cube, exponents, rtol=rtol, out_size=out_size, impl=impl, _sample=sample)


def convolve_sparse(
    cube,
    s,
    *,
    rtol: float = 1e-3,
    out_size: int | None = None,
    supersample: int = 1,
    n_bright="auto",
    bright_factor: float = 8.0,
    max_bright: int = 2048,
    theta_c: float | None = None,
    return_info: bool = False,
    local: bool = True,
    kernel: str = "auto",
    dark_floor: float = 1e-6,
):
    """Truncated-support gather of the normalised Phong-lobe average, with a rigorous error bound.

    Every output texel gathers the source texels within a cap around its tile of output texels (found by
    a two-level cone search, so slightly more than the cap is gathered) plus the ``n_bright`` brightest
    source texels, which are always gathered exactly.  With ``local=True`` (default) every tile chooses
    its cap from the radiance extremes around it and is gathered again, wider, where its bound misses
    ``rtol`` (module docstring, "Local bound and per-tile caps"); with ``local=False`` or ``theta_c`` one
    cap θc serves every tile: the smallest angle for which the rigorous neglected-weight bound W_b(θc) is
    ≤ ε·2π/(s+1), ``ε = rtol · min(1, L_mean,rest / L_max,rest)`` (rest = all but the bright set).  The
    *reported* bound is what counts; it is exact mathematics (including the float32 kernel's rounding),
    not an estimate; it may exceed ``rtol`` where no cap reaches it (black texels, lobes narrower than a
    texel), which :func:`ibl_ref.groundtruth.convolve.convolve` then handles.  When the cap would cover more
    than 40% of the sphere (wide lobes: small s or tight rtol) the dense exact gather is used instead
    (bound = the rounding allowance only).

    Parameters
    ----------
    cube : array (6, N, N[, C])
    s : float ≥ 1 or np.inf
    rtol : float in (0, 1)
        Accuracy target (see above).
    out_size, supersample
        As in :func:`convolve_exact` (the bound refers to the exact result with the same parameters).
    n_bright : "auto" or int
        Bright texels gathered for every output texel.  "auto": texels whose max-channel radiance
        exceeds ``bright_factor`` × the solid-angle-weighted mean, at most ``max_bright``.
    theta_c : float, optional
        Force the cut-off angle (rad).
    return_info : bool
        Also return a :class:`SparseInfo`.
    local : bool
        Per-tile caps from local radiance extremes (default) or one global cap.
    kernel : {"auto", "float32", "float64"}
        Weight kernel: float32 (rounding propagated into the bound) where its bound is small, or forced;
        ``"float32"`` raises :class:`IBLError` where its rounding cannot be bounded.
    dark_floor : float in [0, 1]
        Radiance floor (× the mean) for the far cap's contrast: texels darker than that (e.g. black ones)
        do not widen the far cap of the whole map; their relative bound may then exceed ``rtol``.

    Returns
    -------
    maps : ndarray (6, n, n, C)
        Approximate lobe average P.
    error_bound : ndarray (6, n, n, C)
        Per texel and channel: ``|P − convolve_exact(cube, s, ...)| ≤ error_bound`` (absolute; the module
        docstring gives its terms).  The relative bound is
        ``error_bound / maps`` where ``maps > 0``.
    """
    res = convolve_sparse_many(
        cube,
        [s],
        rtol=rtol,
        out_size=out_size,
        supersample=supersample,
        n_bright=n_bright,
        bright_factor=bright_factor,
        max_bright=max_bright,
        theta_c=theta_c,
        return_info=return_info,
        local=local,
        kernel=kernel,
        dark_floor=dark_floor,
    )
    if return_info:
        return res[0][0], res[1][0], res[2][0]
    return res[0][0], res[1][0]


# ----------------------------------------------------------------------------------------------
# exact Eq. 4 lobe average at arbitrary directions (optionally per region, optionally truncated)
# ----------------------------------------------------------------------------------------------
def lobe_average(cube, dirs, s, *, texel_dirs=None, labels=None, n_regions: int | None = None,
                 weight_eps: float = 0.0, group: int = 64, chunk: int = 2048, return_bound: bool = False,
                 normals=None):
    """Normalised Eq. 4 lobe average Ē_s(d) at arbitrary unit directions ``dirs`` (..., 3) → (..., C).

    The one exact lobe average of the package (the formula of :func:`convolve_exact`, at any directions)::

        Ē_s(d) = Σ_j L_j max(d·ω_j, 0)^s Ω_j / Σ_j max(d·ω_j, 0)^s Ω_j

    over the texels j of ``cube`` (6, N, N, C) with exact solid angles Ω_j.  The reference renderer, the
    exact-lobe chain prefilter and the exact PEM look-ups all call it.

    Parameters
    ----------
    cube : (6, N, N[, C]) radiance
    dirs : (..., 3) directions (normalised here)
    s : finite Phong exponent ≥ 1
    texel_dirs : (6, N, N, 3), optional — quadrature directions ω_j instead of the texel centres (e.g. the energy
        centroids of a coarse level, :func:`ibl_ref.rendering.reference_render.coarse_directions`)
    labels : (6, N, N) int, optional — region of every texel; the result is then per region,
        (..., R, C) with R = ``n_regions`` (default labels.max() + 1): the numerator summed over the texels of
        region i, the denominator over all texels, so the regions sum to Ē_s (partial environment maps, Sec. 3.1)
    weight_eps : 0 (default: every texel, dense) or in (0, 1): only texels within θc of d, cos^s θc =
        ``weight_eps``, are summed (a KD-tree cap around each ``group`` of consecutive directions, so every texel
        closer than θc to a direction of the group is included); numerator and denominator use the same texels,
        so a constant map stays constant
    group : directions sharing one candidate cap in the truncated mode (pass them in spatially coherent order)
    chunk : directions per dense step (memory ≈ chunk × 6N² floats)
    return_bound : also return δ (...,): the neglected weight fraction bound 4π·weight_eps / Σ_included w
        (|error| ≤ δ·max L; 0 where every texel was summed)
    normals : (..., 3), optional — one normal n per direction: the numerator is clipped to the hemisphere
        Ω⁺ of n (texels with n·ω_j ≤ 0 left out), the normalisation Σ_j max(d·ω_j, 0)^s Ω_j is not — the lobe of
        the reference renderer (docs/background.md §8: a lobe cut by the horizon loses energy)

    Raises
    ------
    IBLError
        s not finite or < 1, weight_eps outside [0, 1), a lobe with zero total weight, bad labels.
    """
    a, _ = check_cube(cube)
    a = np.asarray(a, dtype=np.float64)
    N, C = a.shape[1], a.shape[-1]
    try:
        s = float(s)
    except (TypeError, ValueError):
        raise IBLError(f"Phong exponent must be a finite number >= 1, got {s!r}") from None
    if not (np.isfinite(s) and s >= 1.0):
        raise IBLError(f"Phong exponent must be finite and >= 1, got {s!r}")
    weight_eps = float(weight_eps)
    if not (0.0 <= weight_eps < 1.0):
        raise IBLError(f"weight_eps must be in [0, 1), got {weight_eps!r}")
    src = np.asarray(envmap.texel_directions(N) if texel_dirs is None else texel_dirs, dtype=np.float64)
    if src.shape != (6, N, N, 3):
        raise LayoutError(f"texel_dirs must have shape (6, {N}, {N}, 3), got {src.shape}")
    src = src.reshape(-1, 3)
    om = np.asarray(envmap.cube_solid_angles(N)).reshape(-1)
    rad = a.reshape(-1, C)
    R = None
    if labels is not None:
        lab = np.asarray(labels).reshape(-1)
        if lab.shape[0] != 6 * N * N:
            raise LayoutError(f"labels must have shape (6, {N}, {N}), got {np.asarray(labels).shape}")
        R = int(lab.max()) + 1 if n_regions is None else int(n_regions)
        if R < 1 or lab.min() < 0 or lab.max() >= R:
            raise IBLError(f"labels must lie in [0, {R})")
        order = np.argsort(lab, kind="stable")  # texels sorted by region: candidates in label order
        lab, src, om, rad = lab[order], src[order], om[order], rad[order]
    d = np.asarray(dirs, dtype=np.float64)
    if d.shape[-1:] != (3,) or not np.all(np.isfinite(d)):
        raise IBLError(f"dirs must be finite directions (..., 3), got shape {d.shape}")
    shape = d.shape[:-1]
    d = d.reshape(-1, 3)
    nd = np.linalg.norm(d, axis=1, keepdims=True)
    if np.any(nd == 0):
        raise IBLError("dirs: zero-length direction")
    d = d / nd
    nrm = None
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float64)
        if nrm.shape[-1:] != (3,) or nrm.reshape(-1, 3).shape[0] != len(d) or not np.all(np.isfinite(nrm)):
            raise IBLError(f"normals must be finite (..., 3) with one normal per direction, got shape {nrm.shape}")
        nrm = nrm.reshape(-1, 3)
    out = np.zeros((len(d), C) if R is None else (len(d), R, C))
    bound = np.zeros(len(d))

    def _gather(ids, cand):
        c = np.clip(d[ids] @ (src if cand is None else src[cand]).T, 0.0, None)
        with np.errstate(divide="ignore", under="ignore"):
            w = np.power(c, s) * (om if cand is None else om[cand])[None, :]  # Eq. 4 weights
        ws = w.sum(axis=1)
        if np.any(ws <= 0):
            raise IBLError("a lobe has zero total weight on this map (lobe narrower than a texel, or weight_eps "
                           "too large): use a finer map")
        L = rad if cand is None else rad[cand]
        if nrm is not None:  # hemisphere Ω⁺ of n: numerator only
            w = w * ((nrm[ids] @ (src if cand is None else src[cand]).T) > 0)
        if R is None:
            out[ids] = (w @ L) / ws[:, None]
        else:
            lc = lab if cand is None else lab[cand]
            starts = np.flatnonzero(np.r_[True, lc[1:] != lc[:-1]])
            part = np.add.reduceat(w[:, :, None] * L[None], starts, axis=1)  # (P, regions present, C)
            out[ids[:, None], lc[starts][None, :], :] = part / ws[:, None, None]
        return ws

    if weight_eps == 0.0:
        for i in range(0, len(d), max(1, int(chunk))):
            _gather(np.arange(i, min(i + max(1, int(chunk)), len(d))), None)
    else:
        from scipy.spatial import cKDTree

        tree = cKDTree(src)
        theta_c = float(np.arccos(weight_eps ** (1.0 / s)))
        gsz = max(1, int(group))
        for i in range(0, len(d), gsz):
            ids = np.arange(i, min(i + gsz, len(d)))
            cvec = d[ids].sum(axis=0)
            cn = np.linalg.norm(cvec)
            cvec = cvec / cn if cn > 0 else d[ids[0]]
            ang = theta_c + float(np.arccos(np.clip(d[ids] @ cvec, -1.0, 1.0)).max())
            if ang >= np.pi:
                cand = np.arange(len(src))
            else:
                cand = np.asarray(tree.query_ball_point(cvec, 2.0 * np.sin(ang / 2.0) + 1e-12), dtype=np.intp)
                cand.sort()
            ws = _gather(ids, cand)
            missing = len(src) - cand.size
            bound[ids] = 0.0 if missing == 0 else 4.0 * np.pi * weight_eps / ws
    out = out.reshape(shape + out.shape[1:])
    return (out, bound.reshape(shape)) if return_bound else out
