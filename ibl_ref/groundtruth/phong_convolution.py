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
from ..errors import IBLError, LayoutError
from ..limits import check_rtol
from .convolution_args import channel_max, check_cube, check_exponent, check_faces, check_out_size
from .kernels import check_impl, get_kernels
from .kernels.numpy_backend import ANGLE_MARGIN, column_extremes

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


def _tile_size(out_size: int, theta_c: float, m_src: int, n_bright: float, tile_overhead: float,
               cand_overhead: float) -> int:
    """Output tile width T minimising n_tiles·overhead + Σ T²·|candidates| (cost model; the overheads are the
    gather's, :class:`ibl_ref.groundtruth.kernels.numpy_backend.SparseGather`)."""
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


#: share of ``rtol`` left to the far-field term of the local bound (texels beyond the far cap θ_far, bounded
#: with the global radiance extremes); the rest goes to the near annulus and to the kernel's rounding
_FAR_SHARE = 0.1
#: the first cap of a tile aims at this fraction of its share of ``rtol`` (the a-priori estimate of the
#: gathered weight and average can be off; a tile whose bound misses ``rtol`` is gathered again, wider)
_CAP_MARGIN = 0.8


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


@dataclass(frozen=True)
class _SparseSetup:
    """What every exponent of one :func:`convolve_sparse_many` call shares: the source texels (M on the (N·k)² grid,
    ``m`` per face side), the bright set, the radiance extremes and mean of the rest, the tolerances."""

    dirs: np.ndarray
    omega: np.ndarray
    rad: np.ndarray
    m: int
    bright: np.ndarray
    l_max_out: np.ndarray
    l_min_out: np.ndarray
    l_ref: float
    eps: float
    eps_far: float
    rho: float
    tau: float
    floor: float


def _sparse_setup(a, supersample, n_bright, bright_factor, max_bright, rtol, dark_floor) -> _SparseSetup:
    src_dirs, omega, rad = _sources(a, supersample)
    M, C = rad.shape
    bright = _bright_set(rad, omega, n_bright, bright_factor, max_bright)
    rest = np.ones(M, dtype=bool)
    rest[bright] = False
    if rest.any():
        rad_rest = rad[rest] if bright.size else rad
        l_max_out, l_min_out = column_extremes(rad_rest)  # (C,)
        key = channel_max(rad_rest)
        l_ref = float(np.sum(key * omega[rest]) / np.sum(omega[rest]))
        l_top = float(key.max())
    else:
        l_max_out = l_min_out = np.zeros(C)
        l_ref = l_top = 0.0
    # the single-cap rule (local=False, or theta_c given): ε·L_max,out ≈ rtol·(typical radiance), i.e. relative
    # error ≈ rtol where P ≈ mean radiance; also the typical cap that sets the tile size
    eps = max(rtol * (min(1.0, l_ref / l_top) if l_top > 0 else 1.0), 1e-300)
    tau = rtol / (1.0 + rtol)  # abs ≤ τ·P ⇔ abs/(P − abs) ≤ rtol (the relative bound of convolve())
    floor = dark_floor * l_ref
    lo = np.maximum(l_min_out, floor)
    span = l_max_out - lo
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(span > 0, lo / np.where(span > 0, span, 1.0), np.inf)
    eps_far = max(_FAR_SHARE * tau * float(ratio.min()) if np.isfinite(ratio.min()) else 1.0, 1e-300)
    m = a.shape[1] * supersample
    return _SparseSetup(src_dirs, omega, rad, m, bright, l_max_out, l_min_out, l_ref, eps, eps_far, _texel_extent(m),
                        tau, floor)


def _sparse_args(exponents, rtol, dark_floor, threads):
    """The checked exponents, rtol and dark floor of :func:`convolve_sparse_many`."""
    s_list = [check_exponent(s) for s in np.atleast_1d(np.asarray(exponents, dtype=object))]
    if not s_list:
        raise IBLError("no Phong exponents given")
    rtol = check_rtol(rtol)
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise IBLError(f"threads must be an integer ≥ 1, got {threads!r}")
    try:
        dark_floor = float(dark_floor)
    except (TypeError, ValueError):
        raise IBLError(f"dark_floor must be a number in [0, 1], got {dark_floor!r}") from None
    if not (0.0 <= dark_floor <= 1.0):
        raise IBLError(f"dark_floor must be in [0, 1], got {dark_floor!r}")
    return s_list, rtol, dark_floor


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

    ``impl``: the kernel backend of the gather (:mod:`ibl_ref.groundtruth.kernels`): ``"numpy"`` (the float32 or
    float64 kernel, ``kernel``) or ``"compiled"`` (:class:`ibl_ref.groundtruth.kernels.numba_backend.CompiledSparseGather`:
    float64, its rounding bound replacing the float32 kernel's; its first attempt may leave out far bright texels,
    charged in the bound).  Tiles, caps, attempts and the bound are the same for both.  ``threads`` > 1 (compiled
    only): the tiles are gathered by that many threads; the result is bit-for-bit the same for every thread count.

    ``_sample > 0`` (used by the planner of :func:`ibl_ref.groundtruth.convolve.convolve`, see
    :func:`estimate_candidates`): no gather; the first attempt's caps of that many evenly spaced tiles only,
    returned as the mean number of source texels per output texel, one per exponent.
    """
    a, squeeze = check_cube(cube)
    n = a.shape[1]
    out_size, supersample = _check_sizes(out_size, n, supersample)
    s_list, rtol, dark_floor = _sparse_args(exponents, rtol, dark_floor, threads)
    if kernel not in ("auto", "float32", "float64"):
        raise IBLError(f"kernel must be 'auto', 'float32' or 'float64', got {kernel!r}")
    kern = get_kernels(check_impl(impl))
    C, K = a.shape[-1], len(s_list)
    faces = check_faces(faces)
    P = len(faces) * out_size * out_size
    maps = np.empty((K, P, C))
    bounds = np.zeros((K, P, C))
    infos = []
    src = _sparse_setup(a, supersample, n_bright, bright_factor, max_bright, rtol, dark_floor)
    gather = kern.sparse_gather(src.dirs, src.omega, src.rad, src.bright, src.m, kernel, threads)
    M = src.dirs.shape[0]
    for k, s in enumerate(s_list):
        if not np.isfinite(s):
            if _sample:
                infos.append(1.0)
                continue
            maps[k] = _mirror(a, out_size)[list(faces)].reshape(-1, C)
            infos.append(SparseInfo(s, 0.0, src.rho, 0.0, -np.inf, 0, 1.0 / M))
            continue
        single = theta_c is not None or not local
        th = cutoff_angle(s, src.eps, src.rho) if theta_c is None else float(min(max(theta_c, 0.0), np.pi / 2))
        if (1.0 - math.cos(min(th, np.pi))) / 2.0 > 0.4:
            # the cap covers most of the lobe's hemisphere: the dense exact gather is cheaper
            if _sample:
                infos.append(float(M))
                continue
            ex = convolve_exact_many(a, [s], supersample=supersample, out_size=out_size)[0][list(faces)].reshape(-1, C)
            maps[k] = ex
            bounds[k] = 1e-12 * ex
            infos.append(SparseInfo(s, np.pi / 2, src.rho, src.eps, -np.inf, int(src.bright.size), 1.0))
            continue
        infos.append(_sparse_exponent(gather, src, s, th, single, out_size, faces, maps[k], bounds[k], _sample))
    if _sample:
        return infos
    shape = (K, len(faces), out_size, out_size) + (() if squeeze else (C,))
    out = (maps.reshape(shape), bounds.reshape(shape))
    return out + (infos,) if return_info else out


def _sparse_exponent(gather, src: _SparseSetup, s, th, single, out_size, faces, maps_k, bounds_k, sample):
    """One exponent of :func:`convolve_sparse_many`: the tiles and their caps per attempt (local radiance extremes,
    then local with κ ≥ 1 — an average above the local maximum, e.g. next to the bright set —, then the far cap),
    the gathers and bounds into ``maps_k``/``bounds_k``; returns its :class:`SparseInfo` (with ``sample``: the
    first attempt's mean candidates per output texel)."""
    M, C, rho, tau = src.dirs.shape[0], src.rad.shape[1], src.rho, src.tau
    # tiles of T×T output texels sharing one candidate list
    log_d0 = gather.bright_cut(s, rho, src.l_ref, tau, single)
    T = _tile_size(out_size, th, M, *gather.tile_costs(s, th, log_d0))
    IDX, TD, CEN, ANG, VALID, t_rad0 = (_tile_layout_of if sample else _tile_layout)(out_size, tuple(faces), T)
    if sample:
        # (sorted distinct indices; not np.unique, whose first call imports numpy.ma: ≈ 10 ms of a process)
        pick = np.array(sorted(set(np.linspace(0, len(CEN) - 1, min(sample, len(CEN))).astype(np.intp).tolist())),
                        dtype=np.intp)
        IDX, TD, CEN, ANG, VALID = IDX[pick], TD[pick], CEN[pick], ANG[pick], VALID[pick]
    n_t = IDX.shape[0]
    a_max = ANG.max(axis=1)
    # the largest tile radius, from face 0 whatever the face subset (all faces have the same tiles): the kernel
    # choice below is the same for every subset
    t_rad = t_rad0 * (1.0 + 1e-9)
    # every cap reaches ρ beyond its tile's texels: each row's own source texel (within ρ) is gathered
    cap_min = rho + ANGLE_MARGIN
    th_far = max(th if single else cutoff_angle(s, src.eps_far, rho), cap_min)
    log_lobe = math.log(2.0 * np.pi / (s + 1.0))
    # W_b tabulated from cap_min to beyond every θ a bound looks up (step ρ/4), made non-increasing by a
    # running minimum (W_b(θ') bounds every texel beyond θ ≥ θ': valid); a texel uses the grid angle ≤ its θ
    top = min(th_far + t_rad + 2.0 * ANGLE_MARGIN, np.pi / 2)
    grid, log_wb_grid = _wb_grid(float(s), float(rho), float(cap_min), float(top))
    own_log = s * math.log(max(math.cos(min(rho, np.pi / 2)), 1e-300))
    fp_share = gather.prepare(s, th, th_far, t_rad, rho, tau, own_log)
    q_far = th_far + a_max + ANGLE_MARGIN
    if single:
        lmax2, lmin2 = np.broadcast_to(src.l_max_out, (n_t, C)), np.broadcast_to(src.l_min_out, (n_t, C))
        attempts = [np.full(n_t, th_far)]
    else:
        lmax2, lmin2 = gather.local_extremes(CEN, q_far)
        with np.errstate(invalid="ignore", divide="ignore"):
            kap = np.where(lmax2 > lmin2, (lmax2 - lmin2) / np.maximum(lmin2, max(src.floor, 1e-300)), 0.0).max(axis=1)
        tau_near = max(tau * (1.0 - _FAR_SHARE) - fp_share, 1e-3 * tau)
        with np.errstate(divide="ignore"):
            eps1 = np.minimum(_CAP_MARGIN * tau_near / np.maximum(kap, 1e-12), 0.5)
            eps2 = np.minimum(_CAP_MARGIN * tau_near / np.maximum(kap, 1.0), 0.5)
        i1 = np.searchsorted(-log_wb_grid, -(np.log(eps1) + log_lobe), side="left")
        i2 = np.searchsorted(-log_wb_grid, -(np.log(eps2) + log_lobe), side="left")
        attempts = [np.minimum(grid[np.minimum(i, grid.size - 1)], th_far) for i in (i1, i2)] + [np.full(n_t, th_far)]
    if sample:
        q0 = attempts[0] + a_max + ANGLE_MARGIN
        return float(np.mean((1.0 - np.cos(np.minimum(q0, np.pi))) / 2.0 * M)) + src.bright.size
    todo = np.arange(n_t)
    prev = np.full(n_t, -1.0)
    retried = 0
    caps_used = np.zeros(n_t)
    for att, caps in enumerate(attempts):
        # a tile is gathered again when its cap grows, or (attempt 1) when attempt 0 left out weights below δ0
        todo = todo[(caps[todo] > prev[todo]) | (att == 1 and log_d0 > -700.0)]
        if todo.size == 0:
            break
        if att > 0:
            retried += todo.size
        prev[todo] = caps[todo]
        caps_used[todo] = caps[todo]
        q_t = caps + a_max + ANGLE_MARGIN
        sums = gather.gather(todo, att, log_d0 if att == 0 else -700.0, CEN, TD, q_t, a_max)
        # per-texel bounds of the attempt's tiles; tiles whose bound misses rtol go to the next attempt
        worst = gather.bounds(sums, todo, ANG, q_t, q_far, 0.5 * ANGLE_MARGIN, grid, log_wb_grid, lmax2, lmin2,
                              src.l_max_out, src.l_min_out, VALID, IDX, maps_k, bounds_k)
        todo = np.sort(todo[~(worst <= tau)])
    P = len(faces) * out_size * out_size
    return SparseInfo(s, float(caps_used.max()), rho, src.eps_far if not single else src.eps,
                      float(neglected_weight_bound(s, float(caps_used.max()), rho)), int(src.bright.size),
                      gather.gathered / (P * M), float(caps_used.min()), int(retried), gather.label)


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
