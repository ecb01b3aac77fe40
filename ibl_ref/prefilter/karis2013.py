"""Karis (2013), "Real Shading in Unreal Engine 4" — the split-sum approximation of GGX image-based lighting.

SIGGRAPH 2013 course "Physically Based Shading in Theory and Practice", course notes, section "Image-Based
Lighting".  Equation numbers are those of the course-notes PDF as we know them: Eq. 6 the importance-sampled
estimator, Eq. 7 the split sum, Eq. 8 the n·l-weighted prefilter ("we found weighting by cos θ_lk achieves better
results"), Eq. 9 the factorisation of F0 into a scale and a bias.  Every formula is written out below, so nothing
depends on the numbering.

The material
------------
The GGX material of :func:`ibl_ref.lobes.brdfs.ggx`: ``f = D·G·F / (4 (n·l)(n·v))`` with the Trowbridge–Reitz NDF
``D`` (:func:`~ibl_ref.lobes.brdfs.ndf`), ``α = roughness²`` (:func:`ibl_ref.conventions.ggx_alpha`), Smith
masking–shadowing ``G`` (:func:`~ibl_ref.lobes.brdfs.smith_g2`, height-correlated by default; Karis uses a separable
Schlick–Smith approximation, the lab uses its one BRDF definition instead) and Schlick's
``F = F0 + (1 − F0)(1 − v·h)⁵``.  The specular radiance towards ``v`` under a distant environment L is
``Lo(v) = ∫_{H²} L(l) f(l, v) (n·l) dl``.

The split sum (Eq. 7)
---------------------
``Lo(v) ≈ P(r, roughness) · (F0·A(n·v, roughness) + B(n·v, roughness))``, ``r = 2(n·v)n − v``:

* **Prefiltered radiance** (Eq. 8, the ``n = v = r`` assumption): GGX half vectors ``h`` sampled about ``n = v = r``
  give ``l = 2(r·h)h − r`` with the pdf ``p(l) = D(h)(n·h) / (4 v·h) = D(θh)/4`` (Walter et al. 2007, Eq. 14 and 24:
  the reflection Jacobian ``1/(4 v·h)``), weighted by ``n·l = r·l``.  In the continuum that is the normalised
  average of L under the radially symmetric kernel

      K(r·l) = D(cos θh) · max(r·l, 0),      cos θh = √((1 + r·l)/2)        (the constant ¼ cancels)

      P(r) = ∫ L(l) K(r·l) dl / ∫ K(r·l) dl.

  Three quadratures of the same P:

  - :func:`prefilter_exact` — the deterministic sum over **every source texel** j with its exact solid angle Ω_j,
    ``P(r) = Σ_j L_j K(r·ω_j) Ω_j / Σ_j K(r·ω_j) Ω_j`` (a constant map stays constant exactly);
  - :func:`prefilter_importance` — Karis's ``PrefilterEnvMap``: N GGX samples per output texel,
    ``P ≈ Σ_k L(l_k)(r·l_k) / Σ_k (r·l_k)`` over the samples with ``r·l_k > 0``, L read by the seam-aware bilinear
    lookup of the source (:class:`ibl_ref.environment.sampling.CubeSampler`, Karis's ``SampleLevel(…, 0)``);
    ``sequence="hammersley"`` (Karis's listing: the same 2-D Hammersley points ``(k/N, radical inverse of k)``
    for every texel, rotated into the texel's frame) or ``"random"`` (independent uniform points per texel from a
    seeded generator: plain Monte Carlo, error ∝ 1/√N);
  - filtered importance sampling (Křivánek & Colbert 2008) in :mod:`ibl_ref.prefilter.krivanek_colbert2008`.

  GGX sampling of ``h`` (Walter et al. 2007, Eq. 35–36; Karis's ``ImportanceSampleGGX``):
  ``cos²θh = (1 − u_θ) / (1 + (α² − 1) u_θ)``, ``φh = 2π u_φ``.
* **The DFG table** (Eq. 9): with ``f/F`` the BRDF without its Fresnel factor,

      A = ∫ (f/F) (1 − (1 − v·h)⁵) (n·l) dl,      B = ∫ (f/F) (1 − v·h)⁵ (n·l) dl,

  so ``F0·A + B = ∫ f (n·l) dl`` is the directional albedo with Fresnel F0, exactly (Schlick is linear in F0).
  :func:`dfg_terms` evaluates A and B by a deterministic quadrature (below); :func:`build_dfg_table` tabulates them
  on a ``size × size`` grid of texel centres ``n·v = (i + ½)/size``, ``roughness = (j + ½)/size`` (a GPU texture
  with clamp-to-edge), :meth:`DFGTable.lookup` interpolates bilinearly.
* **Roughness → MIP level** (:func:`build_chain`, :class:`PrefilteredChain`): a chain of ``n_levels`` prefiltered
  cubes, level ℓ of face size ``max(N >> ℓ, min_face_size)`` prefiltered at the roughness the engine's mapping
  stores there (``mapping``, one of :data:`~ibl_ref.prefilter.mip_mappings.ROUGHNESS_MAPPINGS`: ``"linear"``
  ``roughness_ℓ = ℓ / (n_levels − 1)``, ``"filament"``, ``"unity"``, ``"unreal"``, ``"threejs"``); a level of
  roughness 0 (level 0 of every mapping but ``unreal``) is the unfiltered source: roughness 0 is the mirror, whose
  kernel is a delta.  The lookup is trilinear: seam-aware bilinear within the two levels bracketing the mapping's
  fractional level ``ℓ(r)`` (``linear``: ``r·(n_levels − 1)``), linear between them.
* **Shading**: :func:`shade` (and :meth:`SplitSum.shade`) evaluate ``P(r)·(F0·A + B)``; 0 where ``n·v ≤ 0``.

White furnace: for ``L ≡ c`` every quadrature of P returns c (each is a normalised average), so the split sum gives
``c·(F0·A + B) = c·∫ f (n·l) dl`` — the true reflected radiance; the split sum is exact for a constant environment.

The DFG quadrature
------------------
In the half vector ``h = (sin θh cos φ, sin θh sin φ, cos θh)`` about n, with ``v = (sin θv, 0, cos θv)``:
``∫ g(l) (n·l) f dl = ∫ (f (n·l) 4 v·h / (D cos θh)) D cos θh dh``, and ``D cos θh dh = dξ dφ/(2π)`` with the GGX
cumulative ``ξ = q/(1+q)``, ``q = tan²θh / α²``.  The integration variable is ``ρ = ln tan θh``
(``dξ/dρ = ½ sech²(ρ − ln α)``, a smooth bump of width ≈ 1 around ``ln α``), which resolves the NDF peak for every α.
The integrand is ``G·F·(v·h) / ((n·v) cos θh)``.  ``l`` is above the horizon iff ``cos φ > c*`` with
``c* = −cot θv · cot 2θh``, so rings with ``θh < (π/2 − θv)/2`` are entirely valid, rings with
``θh > (π/2 + θv)/2`` entirely invalid, and in between ``|φ| < arccos c*``.  Both pieces get ``panels`` equal
Gauss–Legendre panels of ``nodes`` points in ρ over ``[ln α − 12, ln α + 12]`` (the neglected GGX mass outside is
< 1e-10); near the horizon cut the Smith factor changes on the scale n·l ~ α, so the panels at the breakpoints are
split geometrically down to α/2, in ρ and (partial rings, ``|φ| < arccos c*``) in φ.  φ runs over ``[0, π]`` (the
integrand is even in φ).

Accuracy (measured; ``tests/test_karis2013.py``): the default rule is within 7.5e-9 of a rule with twice the panels
and phi nodes and 1.5× the nodes (:attr:`DFGTable.quadrature_error`), within 2e-10 of a 1-D adaptive quadrature at
normal view and within 5e-8 of :func:`ibl_ref.lobes.brdfs.albedo` (an independent rule in l, itself ≈ 1e-8 off at
low roughness).  The 64² table's bilinear interpolation dominates: at the midpoints between its texel centres
``|Δ(F0·A + B)|`` ≤ 2.9e-4 for n·v ≥ 0.2 (O(h²)), mean 1.4e-4, max 1.8e-2 in the lowest n·v row (n·v ≈ 1/64, where
the albedo of a near-mirror changes on the scale of n·v itself; not reduced by a larger table).  Beyond the last
texel centre (n·v or roughness above 1 − 1/128) the look-up is clamped to the edge: the diffuse-like corner
roughness 1, n·v → 1 is then 9.4e-3 off for F0 = 1 (5.5e-4 for F0 = 0.04; ≤ 2.8e-4 on the rest of
n·v ∈ [0.2, 1]; a 101 × 161 grid of roughness and n·v).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from ..conventions import ggx_alpha
from ..environment import envmap
from ..environment.sampling import CubeSampler
from ..errors import IBLError
from ..groundtruth.convolution_args import check_cube
from ..groundtruth.ggx_convolution import convolve_ggx, convolve_ggx_levels
from ..limits import check_rtol
from ..lobes import brdfs
from .interface import check_lobe_param
from .mip_mappings import ROUGHNESS_MAPPINGS, MipMapping

__all__ = [
    "SEQUENCES", "STORAGE_DTYPES",
    "check_roughness", "check_scalar_roughness", "check_f0", "check_samples", "check_option", "check_sequence",
    "output_directions", "check_finite", "importance_sum",
    "prefilter_kernel", "prefilter_exact", "prefilter_dense", "EXACT_RTOL", "prefilter_importance",
    "ggx_half_vectors", "sample_pdf", "tangent_frames", "sample_points",
    "dfg_terms", "DFGTable", "build_dfg_table",
    "roughness_of_level", "level_of_roughness", "PrefilteredChain", "build_chain",
    "reflect", "split_sum", "shade", "SplitSum", "SplitSumImportance",
]

#: sample sequences of :func:`prefilter_importance`
SEQUENCES = ("hammersley", "random")
#: storage types of a prefiltered chain (float16 as engines store it; values above 65504 are refused)
STORAGE_DTYPES = ("float64", "float32", "float16")

_FP16_MAX = 65504.0
_DFG_TAIL = 12.0  # ρ range ln α ± 12: GGX mass outside = 1/(1 + e^24) on each side < 4e-11
_TEXEL_BLOCK = 256  # texels per block of random numbers (fixed: results do not depend on the chunk size)


# ----------------------------------------------------------------------------------------------
# argument checks (shared by the prefilter modules)
# ----------------------------------------------------------------------------------------------
def check_roughness(roughness, name: str = "roughness"):
    """``(roughness, α)`` as float64 arrays (or floats); IBLError unless every value is in (0, 1]."""
    try:
        r = np.asarray(roughness, dtype=np.float64)
    except (TypeError, ValueError):
        raise IBLError(f"{name} must be a number in (0, 1], got {roughness!r}") from None
    alpha = ggx_alpha(r)  # the one place α = roughness² and the (0, 1] range are defined
    return (float(r) if r.ndim == 0 else r), alpha


def check_f0(f0):
    """F0 as float64 (array or float); IBLError unless finite and in [0, 1]."""
    try:
        a = np.asarray(f0, dtype=np.float64)
    except (TypeError, ValueError):
        raise IBLError(f"F0 must be a number in [0, 1], got {f0!r}") from None
    bad = ~np.isfinite(a) | (a < 0) | (a > 1)
    if a.size == 0 or np.any(bad):
        raise IBLError(f"F0 must be in [0, 1], got {a[bad].ravel()[0] if a.size else a!r}")
    return float(a) if a.ndim == 0 else a


def check_samples(samples, name: str = "samples") -> int:
    """A sample count N as an int ≥ 1 (not a bool or a float); IBLError otherwise."""
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or int(samples) < 1:
        raise IBLError(f"{name} must be an integer N >= 1, got {samples!r}")
    return int(samples)


def check_option(value, options, name: str):
    """``value`` if it is one of ``options`` (a named choice that changes numbers), else a one-line IBLError."""
    if value not in options:
        raise IBLError(f"{name} must be one of {', '.join(options)}, got {value!r}")
    return value


def check_sequence(sequence: str) -> str:
    return check_option(sequence, SEQUENCES, "sequence")


def check_scalar_roughness(roughness):
    """``(roughness, α)`` as floats for one roughness in (0, 1]; IBLError otherwise (arrays included)."""
    r, alpha = check_roughness(roughness)
    if np.ndim(r):
        raise IBLError(f"one roughness at a time, got an array of shape {np.shape(r)}")
    return float(r), float(alpha)


def _check_dirs(dirs, name="directions"):
    d = envmap.unit_directions(dirs, name)
    return d.reshape(-1, 3), d.shape[:-1]


def output_directions(cube_n, out_size, dirs):
    """Output directions (M, 3) and the shape to give the result: the texel centres of a face of ``out_size``
    (default: the source size) or the given directions."""
    if dirs is not None:
        return _check_dirs(dirs)
    try:
        m = cube_n if out_size is None else envmap.check_face_size(out_size)
    except ValueError:
        raise IBLError(f"out_size must be a positive integer, got {out_size!r}") from None
    return envmap.texel_directions(m).reshape(-1, 3), (6, m, m)


def check_finite(out, what):
    if not np.all(np.isfinite(out)):
        raise IBLError(f"{what}: non-finite result (overflow of the input radiance?)")
    return out


# ----------------------------------------------------------------------------------------------
# the n = v = r kernel and its exact quadrature over the source texels
# ----------------------------------------------------------------------------------------------
def prefilter_kernel(cos_gamma, roughness) -> np.ndarray:
    """Unnormalised prefilter kernel ``K(r·l) = D(√((1 + r·l)/2)) · max(r·l, 0)`` (module doc, Eq. 8 with
    ``n = v = r``) at ``cos_gamma = r·l``; ``roughness`` a scalar in (0, 1]."""
    _, alpha = check_scalar_roughness(roughness)
    c = np.clip(np.asarray(cos_gamma, dtype=np.float64), -1.0, 1.0)
    return brdfs.ndf(np.sqrt(0.5 * (1.0 + c)), alpha) * np.maximum(c, 0.0)


#: relative tolerance of :func:`prefilter_exact` and of the exact level chains (:func:`build_chain`): ten times below
#: the smallest error the method zoo reports (the split sum's n = v = r step, ≥ 1e-3 relative)
EXACT_RTOL = 1e-4


def prefilter_exact(cube, roughness, *, out_size=None, dirs=None, rtol: float = EXACT_RTOL, kernel=None,
                    return_bound: bool = False):
    """The ``n = v = r`` GGX prefilter ``P(r) = Σ_j L_j K(r·ω_j) Ω_j / Σ_j K(r·ω_j) Ω_j`` over every texel j of
    ``cube`` (module doc), within a rigorous relative bound ``rtol`` at every output texel and channel
    (:func:`ibl_ref.groundtruth.ggx_convolution.convolve_ggx`: the block-Taylor tree, whose cost grows far slower
    than the texel sum's; :func:`prefilter_dense` is that sum, the test oracle).

    Parameters
    ----------
    cube : (6, N, N[, C]) finite, non-negative radiance
    roughness : float in (0, 1]
    out_size : face size of the output cube (default N); ignored when ``dirs`` is given
    dirs : (..., 3) directions r to evaluate at instead of texel centres
    rtol : largest relative error (default :data:`EXACT_RTOL`)
    kernel : ``"auto"``, ``"numpy"`` or ``"compiled"`` (:func:`ibl_ref.groundtruth.kernels.resolve_kernel`)
    return_bound : also return the per-texel bound

    Returns
    -------
    (6, M, M, C) or (..., C) float64 (a 3-d cube gives no channel axis); with ``return_bound`` also the bound
    ((6, M, M) or (...)), ≤ ``rtol``.

    Examples
    --------
    >>> import numpy as np
    >>> cube = np.ones((6, 8, 8, 3))
    >>> p, bound = prefilter_exact(cube, 0.5, out_size=4, kernel="numpy", return_bound=True)
    >>> p.shape, bool(np.allclose(p, 1.0)), bool(bound.max() <= EXACT_RTOL)
    ((6, 4, 4, 3), True, True)
    """
    check_scalar_roughness(roughness)  # (this module's message for a roughness out of range)
    maps, bound = convolve_ggx(cube, roughness, rtol=rtol, out_size=out_size, dirs=dirs, kernel=kernel)
    return (maps, bound) if return_bound else maps


def prefilter_dense(cube, roughness, *, out_size=None, dirs=None, chunk_elems: int = 1 << 22) -> np.ndarray:
    """The ``n = v = r`` GGX prefilter as the dense texel sum: ``P(r) = Σ_j L_j K(r·ω_j) Ω_j / Σ_j K(r·ω_j) Ω_j``
    over every texel j of ``cube`` for every output direction (texel centres ω_j, exact solid angles Ω_j; module
    doc), exact to float64 rounding — the test oracle of :func:`prefilter_exact` (its cost grows as the product of
    the source and output texel counts: 43 s at 128² faces).

    Parameters
    ----------
    cube : (6, N, N[, C]) finite, non-negative radiance
    roughness : float in (0, 1]
    out_size : face size of the output cube (default N); ignored when ``dirs`` is given
    dirs : (..., 3) directions r to evaluate at instead of texel centres
    chunk_elems : output × source pairs per step (memory ≈ 3 × 8 bytes × chunk_elems)

    Returns
    -------
    (6, M, M, C) or (..., C) float64 (a 3-d cube gives no channel axis).  Cost O(6N² · outputs): a dense gather.
    """
    a, squeeze = check_cube(cube)
    _, alpha = check_scalar_roughness(roughness)
    n = a.shape[1]
    out_d, lead = output_directions(n, out_size, dirs)
    src = envmap.texel_directions(n).reshape(-1, 3)
    om = envmap.cube_solid_angles(n).reshape(-1)
    rad = a.reshape(-1, a.shape[-1])
    step = max(1, int(chunk_elems) // len(src))
    out = np.empty((len(out_d), rad.shape[1]))
    for i in range(0, len(out_d), step):
        c = np.clip(out_d[i:i + step] @ src.T, -1.0, 1.0)
        w = brdfs.ndf(np.sqrt(0.5 * (1.0 + c)), alpha) * np.maximum(c, 0.0) * om  # K(r·ω_j) Ω_j
        out[i:i + step] = (w @ rad) / w.sum(axis=1, keepdims=True)
    out = check_finite(out, "prefilter_dense").reshape(lead + (rad.shape[1],))
    return out[..., 0] if squeeze else out


# ----------------------------------------------------------------------------------------------
# GGX importance sampling (Karis's PrefilterEnvMap)
# ----------------------------------------------------------------------------------------------
def ggx_half_vectors(u_theta, u_phi, alpha) -> np.ndarray:
    """GGX half vectors in the local frame (z = n): ``cos²θh = (1 − u_θ)/(1 + (α² − 1) u_θ)``, ``φ = 2π u_φ``
    (Walter et al. 2007, Eq. 35–36); shape ``broadcast(u_theta, u_phi).shape + (3,)``."""
    u_theta, u_phi = np.broadcast_arrays(np.asarray(u_theta, np.float64), np.asarray(u_phi, np.float64))
    a2 = float(alpha) ** 2
    cos2 = (1.0 - u_theta) / (1.0 + (a2 - 1.0) * u_theta)
    cos_t = np.sqrt(cos2)
    sin_t = np.sqrt(np.maximum(1.0 - cos2, 0.0))
    phi = 2.0 * np.pi * u_phi
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)


def sample_pdf(cos_theta_h, alpha) -> np.ndarray:
    """Solid-angle pdf of the reflected direction l for ``n = v = r``: ``p(l) = D(h)(n·h)/(4 v·h) = D(θh)/4``."""
    return brdfs.ndf(cos_theta_h, alpha) / 4.0


def tangent_frames(normals):
    """Orthonormal tangents ``(t1, t2)`` (each (..., 3)) with ``t1 × t2 = n`` for unit normals (..., 3): the
    branch-free basis of Duff et al. 2017, "Building an Orthonormal Basis, Revisited", Listing 3."""
    n = np.asarray(normals, dtype=np.float64)
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    sign = np.where(z >= 0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    t1 = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=-1)
    t2 = np.stack([b, sign + y * y * a, -y], axis=-1)
    return t1, t2


def _radical_inverse2(k: np.ndarray) -> np.ndarray:
    """Van der Corput radical inverse in base 2 of non-negative integers (bit reversal of 32 bits)."""
    k = np.asarray(k, dtype=np.uint64) & np.uint64(0xFFFFFFFF)
    out = np.zeros(k.shape, dtype=np.float64)
    f = 0.5
    for _ in range(32):
        out += f * (k & np.uint64(1))
        k = k >> np.uint64(1)
        f *= 0.5
    return out


def sample_points(sequence: str, samples: int, start: int, count: int, seed=0):
    """``(u_theta, u_phi)``, each (count, samples), for output texels ``start … start+count−1``.

    ``"hammersley"``: the 2-D Hammersley set ``u_φ = k/N``, ``u_θ = radical inverse of k`` (Karis's listing), the
    same for every texel.  ``"random"``: uniform numbers from ``numpy.random.default_rng`` seeded with
    ``(seed…, block)`` per block of :data:`_TEXEL_BLOCK` texels, so the numbers of a texel do not depend on how
    the work is chunked.  ``seed`` is an int or a tuple of ints.
    """
    check_sequence(sequence)
    samples = check_samples(samples)
    if sequence == "hammersley":
        k = np.arange(samples)
        u_t = np.broadcast_to(_radical_inverse2(k), (count, samples))
        u_p = np.broadcast_to(k / samples, (count, samples))
        return u_t, u_p
    seeds = tuple(int(s) for s in np.atleast_1d(seed))
    u = np.empty((count, samples, 2))
    b0, b1 = start // _TEXEL_BLOCK, (start + count - 1) // _TEXEL_BLOCK
    for b in range(b0, b1 + 1):
        block = np.random.default_rng(seeds + (b,)).random((_TEXEL_BLOCK, samples, 2))
        lo, hi = max(start, b * _TEXEL_BLOCK), min(start + count, (b + 1) * _TEXEL_BLOCK)
        u[lo - start:hi - start] = block[lo - b * _TEXEL_BLOCK:hi - b * _TEXEL_BLOCK]
    return u[..., 0], u[..., 1]


def importance_sum(out_d, alpha, samples, sequence, seed, chunk_elems, lookup, channels):
    """Shared loop of the sampled prefilters: for every output direction r (n = v = r), GGX samples l_k with
    weights ``w_k = max(r·l_k, 0)`` and values ``lookup(l, cos_theta_h) -> (M, C)``; returns ``Σ w L / Σ w`` (M, C)
    and the count of directions without a valid sample (they take ``lookup`` at r itself, the kernel's peak)."""
    step = max(1, int(chunk_elems) // samples)
    out = np.empty((len(out_d), channels))
    n_empty = 0
    for i in range(0, len(out_d), step):
        r = out_d[i:i + step]
        u_t, u_p = sample_points(sequence, samples, i, len(r), seed)
        h_loc = ggx_half_vectors(u_t, u_p, alpha)  # (m, S, 3) about z = r
        t1, t2 = tangent_frames(r)
        h = h_loc[..., 0:1] * t1[:, None] + h_loc[..., 1:2] * t2[:, None] + h_loc[..., 2:3] * r[:, None]
        rh = h_loc[..., 2]  # r·h = cos θh
        l_dir = 2.0 * rh[..., None] * h - r[:, None]  # Karis: L = 2 (V·H) H − V with V = R
        w = np.maximum(2.0 * rh * rh - 1.0, 0.0)  # n·l = r·l = cos 2θh
        ok = w > 0
        vals = np.zeros(w.shape + (channels,))
        if np.any(ok):
            vals[ok] = lookup(l_dir[ok], rh[ok])
        wsum = w.sum(axis=1)
        empty = wsum <= 0
        res = np.einsum("ms,msc->mc", w, vals) / np.where(empty, 1.0, wsum)[:, None]
        if np.any(empty):
            n_empty += int(empty.sum())
            res[empty] = lookup(r[empty], np.ones(int(empty.sum())))
        out[i:i + step] = res
    return out, n_empty


def prefilter_importance(cube, roughness, *, samples: int = 1024, sequence: str = "hammersley", seed=0,
                         out_size=None, dirs=None, chunk_elems: int = 1 << 20, return_info: bool = False):
    """Karis's ``PrefilterEnvMap``: N GGX samples about ``n = v = r`` per output direction,
    ``P ≈ Σ_k L(l_k)(r·l_k) / Σ_k (r·l_k)`` (samples with ``r·l_k ≤ 0`` have weight 0), L by seam-aware bilinear
    lookup of the full-resolution source (module doc).

    A direction whose N samples all fall below (possible for small N at high roughness) takes the bilinear value at
    r itself (counted in ``info["empty"]``; never a 0/0).

    Parameters
    ----------
    cube : (6, N, N[, C]) radiance;  roughness : float in (0, 1];  samples : N ≥ 1
    sequence : ``"hammersley"`` (Karis) or ``"random"`` (seeded, independent per texel)
    seed : int or tuple of ints (``"random"`` only)
    out_size, dirs : as in :func:`prefilter_exact`
    return_info : also return ``{"empty": count}``
    """
    a, squeeze = check_cube(cube)
    _, alpha = check_scalar_roughness(roughness)
    samples = check_samples(samples)
    check_sequence(sequence)
    out_d, lead = output_directions(a.shape[1], out_size, dirs)
    sampler = CubeSampler(a)
    out, n_empty = importance_sum(out_d, alpha, samples, sequence, seed, chunk_elems,
                                    lambda l, _c: sampler.bilinear(l), a.shape[-1])
    out = check_finite(out, "prefilter_importance").reshape(lead + (a.shape[-1],))
    out = out[..., 0] if squeeze else out
    return (out, {"empty": n_empty}) if return_info else out


# ----------------------------------------------------------------------------------------------
# the DFG terms A (scale) and B (bias) — Eq. 9
# ----------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=32)
def _gl01(nodes: int):
    """Gauss–Legendre rule on [0, 1]."""
    u, w = np.polynomial.legendre.leggauss(nodes)
    return 0.5 * (u + 1.0), 0.5 * w


@functools.lru_cache(maxsize=256)
def _graded_rule(panels: int, depth: int, at_start: bool, at_end: bool, nodes: int):
    """Composite Gauss–Legendre rule on [0, 1]: ``panels`` equal panels, the first and/or last one split
    geometrically ``depth`` times towards the end point (widths halving), ``nodes`` points per panel."""
    e = np.linspace(0.0, 1.0, panels + 1)
    fine = 2.0 ** -np.arange(1, depth + 1) / panels
    extra = []
    if at_start:
        extra.append(fine)
    if at_end:
        extra.append(1.0 - fine)
    e = np.unique(np.concatenate([e] + extra))
    x, w = _gl01(nodes)
    h = np.diff(e)
    return (e[:-1, None] + h[:, None] * x).ravel(), (h[:, None] * w).ravel()


def _depth(width, feature) -> int:
    """Halvings of a panel of ``width`` down to ``feature``: the geometric grading of :func:`_graded_rule`."""
    return int(np.clip(np.ceil(np.log2(max(width, feature) / feature)), 0, 40))


def _dfg_piece(mu, alpha, lo, hi, partial, panels, nodes, phi_nodes, smith):
    """A, B contributions (E,) of the rings ρ ∈ [lo, hi] (per entry) (module doc).  The Smith factor changes on
    the scale n·l ~ α near the horizon cut: the rules are graded down to α/2 in ρ and in φ at the cuts."""
    depth = _depth(2.0 * _DFG_TAIL / panels, 0.5 * alpha)
    x, w = _graded_rule(panels, depth, partial, True, nodes)
    rho = lo[:, None] + (hi - lo)[:, None] * x
    w_rho = (hi - lo)[:, None] * w
    tan_h = np.exp(rho)
    t = 1.0 / np.sqrt(1.0 + tan_h * tan_h)  # cos θh
    s_h = tan_h * t
    jac = 0.5 / np.cosh(rho - np.log(alpha)) ** 2  # dξ/dρ
    mu3 = mu[:, None]
    s_v = np.sqrt(np.maximum(1.0 - mu3 * mu3, 0.0))
    if partial:
        with np.errstate(divide="ignore", invalid="ignore"):
            c_star = -mu3 * (1.0 - tan_h * tan_h) / (2.0 * tan_h * s_v)  # −cot θv · cot 2θh
        c_star = np.where(s_v > 0, c_star, 1.0)
        phi_max = np.arccos(np.clip(c_star, -1.0, 1.0))
        xp, wp = _graded_rule(4, _depth(np.pi / 4, 0.5 * alpha), False, True, max(phi_nodes // 4, 2))
        phi = phi_max[..., None] * xp
        w_phi = phi_max[..., None] * wp
    else:
        xp, wp = _gl01(phi_nodes)
        phi = np.pi * xp
        w_phi = np.broadcast_to(np.pi * wp, rho.shape + (phi_nodes,))
    vh = s_v[..., None] * s_h[..., None] * np.cos(phi) + mu3[..., None] * t[..., None]
    vh = np.clip(vh, 0.0, 1.0)
    nl = 2.0 * vh * t[..., None] - mu3[..., None]
    valid = nl > 0
    G = brdfs.smith_g2(np.where(valid, nl, 1.0), mu3[..., None], alpha, smith=smith)
    g = np.where(valid, G * vh / (mu3[..., None] * t[..., None]), 0.0)  # G F (v·h)/((n·v) cos θh) without F
    fc = (1.0 - vh) ** 5
    gw = g * ((w_rho * jac)[..., None] * w_phi / np.pi)  # φ ∈ [0, π] is half the ring: 2/(2π)
    return np.sum(gw * (1.0 - fc), axis=(1, 2)), np.sum(gw * fc, axis=(1, 2))


def _dfg_one_alpha(mu, alpha, panels, nodes, phi_nodes, smith):
    theta_v = np.arccos(mu)
    ln_a = np.log(alpha)
    lo = np.full(mu.shape, ln_a - _DFG_TAIL)
    hi = np.full(mu.shape, ln_a + _DFG_TAIL)
    with np.errstate(divide="ignore"):
        rho1 = np.clip(np.log(np.tan(0.5 * (0.5 * np.pi - theta_v))), lo, hi)  # θh1 = (π/2 − θv)/2
        rho2 = np.clip(np.log(np.tan(np.minimum(0.5 * (0.5 * np.pi + theta_v), 0.5 * np.pi - 1e-16))), lo, hi)
    a_f, b_f = _dfg_piece(mu, alpha, lo, rho1, False, panels, nodes, phi_nodes, smith)
    a_p, b_p = _dfg_piece(mu, alpha, rho1, rho2, True, panels, nodes, phi_nodes, smith)
    # GGX mass below ρ = ln α − 12 (ξ < 4e-11): h ≈ n, l ≈ mirror of v: integrand G(μ, μ) and Fresnel (1 − μ)⁵
    xi_lo = 1.0 / (1.0 + np.exp(2 * _DFG_TAIL))
    head = np.where(rho1 > lo, xi_lo * brdfs.smith_g2(mu, mu, alpha, smith=smith), 0.0)
    fc0 = (1.0 - mu) ** 5
    return a_f + a_p + head * (1 - fc0), b_f + b_p + head * fc0


def dfg_terms(n_dot_v, roughness, *, smith: str = "height_correlated", panels: int = 12, nodes: int = 8,
              phi_nodes: int = 24, chunk: int = 256):
    """Scale A and bias B of Eq. 9 at any ``n·v ∈ (0, 1]`` and roughness ∈ (0, 1] (arrays broadcast), by the
    deterministic quadrature of the module doc; ``F0·A + B`` is the directional albedo with Fresnel F0.

    Returns ``(A, B)`` float64 of the broadcast shape.  Accuracy with the defaults: |ΔA|, |ΔB| < 1e-8 against the
    refined rule for n·v ≥ 1/128 (module doc; ``tests/test_karis2013.py``).
    """
    nv = np.asarray(n_dot_v, dtype=np.float64)
    if nv.size == 0 or not np.all(np.isfinite(nv)) or np.any((nv <= 0) | (nv > 1)):
        raise IBLError("n·v must be in (0, 1] (the split sum is 0 for views below the surface)")
    r, _ = check_roughness(roughness)
    nv, r = np.broadcast_arrays(nv, np.asarray(r, dtype=np.float64))
    check_option(smith, brdfs.SMITH_FORMS, "smith")
    A = np.empty(nv.shape)
    B = np.empty(nv.shape)
    fa, fb, fnv, fr = A.reshape(-1), B.reshape(-1), nv.reshape(-1), r.reshape(-1)
    for rv in np.unique(fr):
        idx = np.nonzero(fr == rv)[0]
        for j in range(0, len(idx), chunk):
            sel = idx[j:j + chunk]
            fa[sel], fb[sel] = _dfg_one_alpha(fnv[sel], float(ggx_alpha(rv)), panels, nodes, phi_nodes, smith)
    if A.ndim == 0:
        return float(A), float(B)
    return A, B


def _grid_coords(x, m: int):
    """Bilinear taps on a grid of texel centres (i + ½)/m with clamp-to-edge: (i0, i1, frac)."""
    t = np.clip(np.asarray(x, dtype=np.float64) * m - 0.5, 0.0, m - 1.0)
    i0 = np.minimum(np.floor(t).astype(np.intp), max(m - 2, 0))
    i1 = np.minimum(i0 + 1, m - 1)
    return i0, i1, t - i0


@dataclass(frozen=True)
class DFGTable:
    """The 2-D DFG table of Eq. 9 (module doc).

    Attributes
    ----------
    n_dot_v, roughness : (M_v,), (M_r,) grid of texel centres ``(i + ½)/M``
    scale, bias : (M_v, M_r) A and B
    smith : the Smith form of the BRDF tabulated
    quadrature_error : max |ΔA|, |ΔB| against the refined rule (module doc) on every 4th node of each axis
    """

    n_dot_v: np.ndarray
    roughness: np.ndarray
    scale: np.ndarray
    bias: np.ndarray
    smith: str = "height_correlated"
    quadrature_error: float = float("nan")

    @property
    def nbytes(self) -> int:
        return int(self.scale.nbytes + self.bias.nbytes)

    def lookup(self, n_dot_v, roughness):
        """``(A, B)`` by bilinear interpolation (clamp to the first/last texel centre, like a GPU texture with
        clamp-to-edge); ``n·v`` in [0, 1], roughness in (0, 1], arrays broadcast."""
        nv = np.asarray(n_dot_v, dtype=np.float64)
        if not np.all(np.isfinite(nv)) or np.any((nv < 0) | (nv > 1)):
            raise IBLError("n·v must be in [0, 1] for the DFG table lookup")
        r, _ = check_roughness(roughness)
        nv, r = np.broadcast_arrays(nv, np.asarray(r, dtype=np.float64))
        i0, i1, fx = _grid_coords(nv, len(self.n_dot_v))
        j0, j1, fy = _grid_coords(r, len(self.roughness))

        def interp(t):
            return ((1 - fx) * (1 - fy) * t[i0, j0] + fx * (1 - fy) * t[i1, j0]
                    + (1 - fx) * fy * t[i0, j1] + fx * fy * t[i1, j1])

        return interp(self.scale), interp(self.bias)


@functools.lru_cache(maxsize=8)
def _dfg_table_cached(size_v: int, size_r: int, smith: str, estimate_error: bool) -> DFGTable:
    nv = (np.arange(size_v) + 0.5) / size_v
    r = (np.arange(size_r) + 0.5) / size_r
    NV, R = np.meshgrid(nv, r, indexing="ij")
    A, B = dfg_terms(NV, R, smith=smith)
    err = float("nan")
    if estimate_error:  # the refined rule on every 4th node per axis (and the last): +30 % cost
        sub = (np.unique(np.r_[0:size_v:4, size_v - 1])[:, None], np.unique(np.r_[0:size_r:4, size_r - 1])[None, :])
        A2, B2 = dfg_terms(NV[sub], R[sub], smith=smith, panels=24, nodes=12, phi_nodes=48)
        err = float(max(np.max(np.abs(A[sub] - A2)), np.max(np.abs(B[sub] - B2))))
    for arr in (nv, r, A, B):
        arr.setflags(write=False)
    return DFGTable(nv, r, A, B, smith, err)


def build_dfg_table(size=64, *, smith: str = "height_correlated", estimate_error: bool = True) -> DFGTable:
    """The DFG table on ``size`` (or ``(size_nv, size_roughness)``) texel centres per axis (cached; read-only
    arrays).  ``estimate_error`` also evaluates the refined rule on a sub-grid for
    :attr:`DFGTable.quadrature_error` (+30 % cost).  64² took 1.9 s on one core (load 1.1)."""
    sv, sr = (size, size) if np.ndim(size) == 0 else tuple(size)
    sv, sr = check_samples(sv, "DFG table size"), check_samples(sr, "DFG table size")
    if sv < 2 or sr < 2:
        raise IBLError(f"DFG table size must be >= 2 per axis, got {size!r}")
    check_option(smith, brdfs.SMITH_FORMS, "smith")
    return _dfg_table_cached(sv, sr, smith, bool(estimate_error))


# ----------------------------------------------------------------------------------------------
# roughness → MIP level and the prefiltered chain
# ----------------------------------------------------------------------------------------------
def _check_levels(n_levels) -> int:
    n_levels = check_samples(n_levels, "n_levels")
    if n_levels < 2:
        raise IBLError(f"n_levels must be >= 2 (level 0 is the mirror), got {n_levels}")
    return n_levels


def _check_mapping(mapping) -> MipMapping:
    """The :class:`~ibl_ref.prefilter.mip_mappings.MipMapping` of a name of :data:`ROUGHNESS_MAPPINGS` (or a
    mapping object); a one-line IBLError listing the names otherwise."""
    if isinstance(mapping, MipMapping):
        return mapping
    return ROUGHNESS_MAPPINGS[check_option(mapping, ROUGHNESS_MAPPINGS, "mapping")]


def roughness_of_level(level, n_levels: int, mapping: str = "linear"):
    """Roughness prefiltered into MIP level ``level`` of ``n_levels`` under ``mapping`` (a name of
    :data:`~ibl_ref.prefilter.mip_mappings.ROUGHNESS_MAPPINGS`, :meth:`MipMapping.roughness
    <ibl_ref.prefilter.mip_mappings.MipMapping.roughness>`; levels outside [0, n_levels − 1] are clamped): with
    ``lod = ℓ/(n_levels − 1)``, ``"linear"`` r = lod (glTF-IBL-Sampler), ``"filament"`` r = 1 − √(1 − lod)
    (Filament's cmgen, the inverse of its run-time lod = r(2 − r)), ``"unity"``, ``"unreal"``, ``"threejs"``.

    Examples
    --------
    >>> roughness_of_level([0, 1, 2, 3, 4], 5).tolist()
    [0.0, 0.25, 0.5, 0.75, 1.0]
    >>> [round(r, 3) for r in roughness_of_level([0, 1, 2, 3, 4], 5, "filament").tolist()]
    [0.0, 0.134, 0.293, 0.5, 1.0]
    >>> [round(r, 3) for r in roughness_of_level([0, 4, 5, 6, 7], 8, "unreal").tolist()]
    [0.056, 0.561, 1.0, 1.0, 1.0]
    """
    m = _check_mapping(mapping)
    return m.roughness(level, _check_levels(n_levels))


def level_of_roughness(roughness, n_levels: int, mapping: str = "linear"):
    """Fractional MIP level the engine of ``mapping`` reads for a roughness in (0, 1] (:meth:`MipMapping.level
    <ibl_ref.prefilter.mip_mappings.MipMapping.level>`; the inverse of :func:`roughness_of_level` where that is
    invertible): ``"linear"`` ℓ = r·(n_levels − 1), ``"filament"`` ℓ = r(2 − r)·(n_levels − 1), …

    Examples
    --------
    >>> float(level_of_roughness(0.6, 5)), round(float(level_of_roughness(0.5, 7, "unity")), 12)
    (2.4, 4.05)
    """
    m = _check_mapping(mapping)
    n_levels = _check_levels(n_levels)
    r, _ = check_roughness(roughness)
    return m.level(r, n_levels)


def _check_dtype(dtype) -> np.dtype:
    try:
        dt = np.dtype(dtype)
    except TypeError:
        raise IBLError(f"storage dtype must be one of {', '.join(STORAGE_DTYPES)}, got {dtype!r}") from None
    if dt.name not in STORAGE_DTYPES:
        raise IBLError(f"storage dtype must be one of {', '.join(STORAGE_DTYPES)}, got {dt.name}")
    return dt


def _store(level: np.ndarray, dt: np.dtype, what: str) -> np.ndarray:
    if dt == np.float16 and np.max(level, initial=0.0) > _FP16_MAX:
        raise IBLError(f"{what}: value {float(np.max(level)):.6g} overflows float16 (max {_FP16_MAX:g}); "
                       "store the chain as float32")
    out = np.ascontiguousarray(level, dtype=dt)
    out.setflags(write=False)
    return out


@dataclass
class PrefilteredChain:
    """A MIP chain of GGX-prefiltered cubes over roughness (module doc).

    Attributes
    ----------
    levels : list of (6, N_ℓ, N_ℓ, C) arrays (storage dtype), level 0 the source (or, under ``"unreal"``, the
        prefilter at its roughness)
    roughness : per-level roughness (``roughness_of_level``)
    mapping : the roughness ↔ level mapping of the look-up (a name of
        :data:`~ibl_ref.prefilter.mip_mappings.ROUGHNESS_MAPPINGS`, or a mapping object); a chain built under
        one mapping and read under another is an engine's mismatch
    prefilter : name of the quadrature that built levels 1…
    info : build parameters (samples, sequence, seed, …)
    """

    levels: list
    roughness: tuple
    mapping: str = "linear"
    prefilter: str = "exact"
    info: dict = field(default_factory=dict)
    _samplers: dict = field(default_factory=dict, repr=False)

    @property
    def n_levels(self) -> int:
        return len(self.levels)

    @property
    def face_sizes(self) -> tuple:
        return tuple(int(lv.shape[1]) for lv in self.levels)

    @property
    def nbytes(self) -> int:
        return int(sum(lv.nbytes for lv in self.levels))

    def _sampler(self, k: int) -> CubeSampler:
        if k not in self._samplers:
            self._samplers[k] = CubeSampler(self.levels[k])
        return self._samplers[k]

    def level_values(self, directions) -> list:
        """Every level's seam-aware bilinear look-up at ``directions``: a list of (M, C) float64 arrays (M the
        number of directions), for :meth:`lookup` ``(…, level_values=…)`` at many roughnesses."""
        d, _ = _check_dirs(directions)
        return [self._sampler(k).bilinear(d).astype(np.float64) for k in range(self.n_levels)]

    def lookup(self, directions, roughness, *, level_values=None) -> np.ndarray:
        """Trilinear lookup ``P(r, roughness)`` (..., C) float64: seam-aware bilinear in the two levels around
        ``ℓ = level_of_roughness(roughness)`` under :attr:`mapping`, linear between them; roughness scalar or
        broadcastable to ``directions.shape[:-1]``.  ``level_values``: :meth:`level_values` of the same
        directions (the bilinear look-ups, computed once for many roughnesses; the result is the same)."""
        d, lead = _check_dirs(directions)
        if level_values is not None and (len(level_values) != self.n_levels
                                         or any(np.shape(v)[0] != len(d) for v in level_values)):
            raise IBLError("level_values must be level_values(directions) of this chain and these directions")
        x = level_of_roughness(roughness, self.n_levels, self.mapping)
        x = np.broadcast_to(np.asarray(x, dtype=np.float64), lead).reshape(-1)
        l0 = np.clip(np.floor(x).astype(np.intp), 0, self.n_levels - 2)
        t = x - l0
        c = self.levels[0].shape[-1]
        out = np.zeros((len(d), c))
        for k in np.unique(l0):
            sel = l0 == k
            if level_values is None:
                lo = self._sampler(int(k)).bilinear(d[sel]).astype(np.float64)
                hi = self._sampler(int(k) + 1).bilinear(d[sel]).astype(np.float64)
            else:
                lo, hi = level_values[k][sel], level_values[k + 1][sel]
            out[sel] = (1.0 - t[sel, None]) * lo + t[sel, None] * hi
        return out.reshape(lead + (c,))


_PREFILTERS = ("exact", "importance")


def build_chain(cube, *, n_levels=None, prefilter="exact", samples: int = 1024, sequence: str = "hammersley",
                seed: int = 0, min_face_size: int = 1, mapping: str = "linear", dtype="float64",
                name: str | None = None, rtol: float = EXACT_RTOL) -> PrefilteredChain:
    """The prefiltered MIP chain: level ℓ = 0…n_levels−1 at face size ``max(N >> ℓ, min_face_size)`` holding
    ``P(·, roughness_of_level(ℓ, n_levels, mapping))``, every level filtered from the full-resolution source; a
    level of roughness 0 (level 0 of every mapping but ``"unreal"``) is the source itself.

    Parameters
    ----------
    cube : (6, N, N, C) radiance (3 channels or any C; a 3-d cube gets one channel)
    n_levels : default ``floor(log2 N) + 1`` (down to a 1×1 face), ≥ 2
    prefilter : ``"exact"`` (:func:`prefilter_exact` at ``rtol``, the levels from one source tree),
        ``"importance"`` (:func:`prefilter_importance` with ``samples``, ``sequence`` and per-level seeds
        ``(seed, ℓ)``), or a callable
        ``f(cube, roughness, out_size, level) -> (6, M, M, C)`` (e.g. filtered importance sampling,
        :func:`ibl_ref.prefilter.krivanek_colbert2008.build_fis_chain`); ``name`` labels a callable
    mapping : a name of :data:`~ibl_ref.prefilter.mip_mappings.ROUGHNESS_MAPPINGS` (or a mapping object)
    dtype : storage type, ``"float64"``, ``"float32"`` or ``"float16"`` (refused if a value exceeds 65504)
    rtol : the ``"exact"`` prefilter's largest relative error per texel (default :data:`EXACT_RTOL`;
        ``info["bound_max"]``: the largest bound of each filtered level)
    """
    a, squeeze = check_cube(cube)
    n = a.shape[1]
    n_levels = _check_levels(int(np.floor(np.log2(n))) + 1 if n_levels is None else n_levels)
    if n_levels < 2:
        n_levels = 2
    _check_mapping(mapping)
    dt = _check_dtype(dtype)
    min_face_size = check_samples(min_face_size, "min_face_size")
    if callable(prefilter):
        fn, label = prefilter, name or getattr(prefilter, "__name__", "custom")
        info = {}
    elif prefilter in _PREFILTERS:
        label = prefilter
        if prefilter == "exact":
            rtol = check_rtol(rtol)
            fn, info = None, {"rtol": rtol}
        else:
            samples = check_samples(samples)
            check_sequence(sequence)

            def fn(c, rough, out_size, level):
                return prefilter_importance(c, rough, samples=samples, sequence=sequence, seed=(seed, level),
                                            out_size=out_size)
            info = {"samples": samples, "sequence": sequence, "seed": int(seed)}
    else:
        raise IBLError(f"prefilter must be one of {', '.join(_PREFILTERS)} or a callable, got {prefilter!r}")
    rough = tuple(float(x) for x in roughness_of_level(np.arange(n_levels), n_levels, mapping))
    sizes = [max(n >> lv, min_face_size, 1) for lv in range(n_levels)]
    levels = [_store(a, dt, "level 0")] if rough[0] == 0.0 else []  # roughness 0: the mirror, the source itself
    if fn is None:  # the exact levels from one source tree (ibl_ref.groundtruth.ggx_convolution)
        first = len(levels)
        out = convolve_ggx_levels(a, list(zip(rough[first:], sizes[first:])), rtol=rtol)
        info["bound_max"] = [float(b.max()) for _, b in out]
        levels += [_store(check_finite(m, f"level {lv}"), dt, f"level {lv}") for lv, (m, _) in enumerate(out, first)]
    for lv in range(len(levels), n_levels):
        levels.append(_store(fn(a, rough[lv], sizes[lv], lv), dt, f"level {lv}"))
    info = dict(info, min_face_size=min_face_size, dtype=dt.name, source_face_size=n, squeezed=squeeze)
    return PrefilteredChain(levels, rough, mapping, label, info)


# ----------------------------------------------------------------------------------------------
# shading
# ----------------------------------------------------------------------------------------------
def reflect(views, normals) -> np.ndarray:
    """Mirror direction ``r = 2(n·v)n − v`` of unit views v about unit normals n (arrays broadcast)."""
    v = envmap.unit_directions(views, "views")
    n = envmap.unit_directions(normals, "normals")
    return 2.0 * np.sum(n * v, axis=-1, keepdims=True) * n - v


def split_sum(prefiltered, n_dot_v, roughness, f0, dfg: DFGTable | None = None,
              smith: str = "height_correlated") -> np.ndarray:
    """Eq. 7: ``P·(F0·A + B)`` for prefiltered radiance ``P`` (..., C) and per-point ``n·v`` (...), roughness and
    F0 (scalars or (...)); A, B from ``dfg`` (table lookup, whatever Smith form it tabulates) or, when ``dfg`` is
    None, from :func:`dfg_terms` of the Smith form ``smith`` (no table error).  Points with ``n·v ≤ 0`` give 0."""
    p = np.asarray(prefiltered, dtype=np.float64)
    f0 = check_f0(f0)
    nv = np.asarray(n_dot_v, dtype=np.float64)
    r, _ = check_roughness(roughness)
    nv, r, f0b = np.broadcast_arrays(nv, np.asarray(r, dtype=np.float64), np.asarray(f0, dtype=np.float64))
    if not np.all(np.isfinite(nv)):
        raise IBLError("n·v contains NaN/Inf")
    up = nv > 0
    scale = np.zeros(nv.shape)
    if np.any(up):
        nvu = np.minimum(nv[up], 1.0)
        A, B = dfg.lookup(nvu, r[up]) if dfg is not None else dfg_terms(nvu, r[up], smith=smith)
        scale[up] = f0b[up] * A + B
    return p * scale[..., None]


def shade(lookup, dfg: DFGTable | None, normals, views, roughness, f0) -> np.ndarray:
    """Split-sum specular radiance (..., C) at unit normals and views (..., 3) (v points away from the surface):
    ``lookup(r, roughness)·(F0·A + B)`` with ``r = 2(n·v)n − v``, 0 where ``n·v ≤ 0``.  ``lookup`` is any
    prefiltered-radiance lookup ``(directions, roughness) -> (..., C)`` (e.g. :meth:`PrefilteredChain.lookup`, or
    :func:`prefilter_exact` at the mirror directions for the split sum without MIP error); ``dfg`` as in
    :func:`split_sum`."""
    n = envmap.unit_directions(normals, "normals")
    v = envmap.unit_directions(views, "views")
    n, v = np.broadcast_arrays(n, v)
    nv = np.sum(n * v, axis=-1)
    r = 2.0 * nv[..., None] * n - v
    p = lookup(r, np.broadcast_to(np.asarray(roughness, dtype=np.float64), nv.shape))
    return split_sum(p, nv, roughness, f0, dfg)


class SplitSum:
    """Karis 2013 split sum: n = v = r GGX prefilter (exact texel sum per level) + DFG table, trilinear roughness MIP look-up."""

    lobe = "ggx"
    paper = "Karis 2013, Real Shading in Unreal Engine 4, Image-Based Lighting: split sum (Eq. 7-9), exact prefilter"
    error_bound = None

    def __init__(self, cube, *, n_levels=None, min_face_size: int = 1, dfg_size=64,
                 smith: str = "height_correlated", dtype="float64"):
        self._init(build_chain(cube, n_levels=n_levels, prefilter="exact", min_face_size=min_face_size, dtype=dtype),
                   build_dfg_table(dfg_size, smith=smith))

    def _init(self, chain: PrefilteredChain, dfg: DFGTable):
        self.chain = chain
        self.dfg = dfg

    @classmethod
    def from_parts(cls, chain: PrefilteredChain, dfg: DFGTable) -> "SplitSum":
        """The split sum of a given chain (:func:`build_chain`, any quadrature) and DFG table."""
        obj = cls.__new__(cls)
        obj._init(chain, dfg)
        return obj

    @classmethod
    def build(cls, cube, *, prefilter="exact", n_levels=None, samples: int = 1024, sequence: str = "hammersley",
              seed: int = 0, dfg_size=64, smith: str = "height_correlated", dtype="float64", **chain_kw):
        """Build the chain (:func:`build_chain` with any ``prefilter``) and the table (:func:`build_dfg_table`)."""
        chain = build_chain(cube, n_levels=n_levels, prefilter=prefilter, samples=samples, sequence=sequence,
                            seed=seed, dtype=dtype, **chain_kw)
        return cls.from_parts(chain, build_dfg_table(dfg_size, smith=smith))

    @property
    def nbytes(self) -> int:
        """Bytes of the chain's levels and the DFG table."""
        return self.chain.nbytes + self.dfg.nbytes

    def lookup(self, directions, roughness) -> np.ndarray:
        """Prefiltered radiance ``P(r, roughness)`` (..., C): the chain's trilinear look-up."""

        return self.chain.lookup(directions, check_lobe_param(self.lobe, roughness, directions))

    def direct(self, cube, roughness, dirs) -> np.ndarray:
        """This method's quadrature of the prefilter at ``dirs`` and one roughness, from the full-resolution
        ``cube`` without the chain's levels (the error budget's ``prefilter`` step): the exact texel sum."""
        return prefilter_exact(cube, roughness, dirs=dirs)

    def shade(self, normals, views, roughness, f0) -> np.ndarray:
        """Specular radiance of Eq. 7, ``P(r, roughness)·(F0·A + B)`` (:func:`shade`)."""
        return shade(self.lookup, self.dfg, normals, views, roughness, f0)


class SplitSumImportance(SplitSum):
    """Karis 2013 split sum with the chain prefiltered by GGX importance sampling (N samples per texel)."""

    paper = ("Karis 2013, Real Shading in Unreal Engine 4, Image-Based Lighting: split sum (Eq. 7-9), "
             "importance-sampled prefilter (PrefilterEnvMap)")

    def __init__(self, cube, *, samples: int = 1024, sequence: str = "hammersley", seed: int = 0, n_levels=None,
                 min_face_size: int = 1, dfg_size=64, smith: str = "height_correlated", dtype="float64"):
        self._init(build_chain(cube, n_levels=n_levels, prefilter="importance", samples=samples, sequence=sequence,
                               seed=seed, min_face_size=min_face_size, dtype=dtype),
                   build_dfg_table(dfg_size, smith=smith))

    def direct(self, cube, roughness, dirs) -> np.ndarray:
        """The chain's importance sampling (same samples, sequence and seed) at ``dirs`` from the full-resolution
        ``cube``."""
        info = self.chain.info
        return prefilter_importance(cube, roughness, samples=info["samples"], sequence=info["sequence"],
                                    seed=(info["seed"], 0), dirs=dirs)
