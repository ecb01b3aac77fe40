"""Exact-lobe prefiltered chain: the filter pyramid's exact counterpart (a comparator; not in Knuth et al. 2014).

Knuth et al. (2014, Sec. 3.2, Fig. 2) store a MIP pyramid whose levels are *shaped* by a 5×5 low-pass filter
so that one trilinear lookup at glossiness g approximates the Phong lobe average of Eq. 4 with
``s_Phong = 1/(1−g)`` (Eq. 3).  The filters act in texel space and are normalised per texel, so the coarse
levels neither have the lobe's shape nor conserve ∫L dω (measured in :mod:`ibl_ref.knuth2014.pyramid` /
``ibl-ref experiment claims``); at s ≈ 1 the lookup of the sky + sun map is off by ≈ 25–30 % (relative L1).

This module keeps the paper's *data structure and lookup* — a chain of cube levels, one trilinear lookup at a
continuous level ℓ(s) (:func:`ibl_ref.knuth2014.gloss_lookup.lookup` with a :class:`~ibl_ref.knuth2014.gloss_lookup.Calibration`)
— but fills every level with the **exact** normalised Eq. 4 lobe average (Kán et al. 2015's per-texel
convolution, docs/background.md §2) at a chosen exponent:

* level 0 = the input (mirror, s = ∞);
* level k = 1..K: exponent ``s_k = s_min · factor^(K−k)`` (``s_K = s_min = 1``: the diffuse end), the largest
  ``s_1`` still resolved by the input: lobe half-width θ½ = arccos 2^(−1/s) (:func:`lobe_half_angle`) at least
  one input texel (2/N rad at the face centre);
* face size ``n_k``: the smallest power of two ≥ ``n_min`` with ``texels_per_halfwidth`` texels (2/n rad) per
  half-width, capped at N.  Unlike the paper's pyramid, sizes do not halve per level: a 1×1 or 2×2 face
  cannot hold a cosine lobe (bilinear lookup of the *exact* s = 1 map stored at 2² / 4² / 8² / 16² faces:
  rel. L1 10.7 % / 2.5 % / 0.69 % / 0.17 % on sky_sun 64², measured with ``/tmp`` probes, see the tests
  for the 8² bound).

The lookup blends two adjacent levels linearly in log s (the calibration table) and, above s_1, linearly in
1/s towards the mirror level (``Calibration.level_of``'s tail) — the same blending error the paper's lookup
has, now without the filter-shape error.

Exactness and cost: level k is computed by a gather over all input texels j (exact solid angles Ω_j, texel
centres ω_j)::

    A_s(d) = Σ_j L_j max(d·ω_j, 0)^s Ω_j / Σ_j max(d·ω_j, 0)^s Ω_j                    (Eq. 4, normalised)

restricted, per output tile, to the texels within the cutoff angle θc where ``cos^s θc = weight_eps`` (found
with a KD-tree on the unit directions, radius θc + tile radius, so every texel closer than θc to any output
direction of the tile is included).  The neglected part changes A_s by at most ``δ·max_j L_j`` with
``δ = 4π·weight_eps / Σ_included w`` per output texel (returned as ``truncation_bound``); a constant map stays
exactly constant (numerator and denominator use the same texels).  Region masks (PEMs, Sec. 3.1/4: "blacken
all texels that do not belong to the current PEM") are applied by summing the numerator per region
(``np.add.reduceat`` over texels sorted by label), so all regions cost one gather and
Σ_i PEM_i = the full map's chain to rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..environment.envmap import texel_directions
from ..environment.validated import as_environment
from ..errors import IBLError, LayoutError
from ..conventions import lobe_half_angle
from ..groundtruth.phong_convolution import lobe_average
from ..progress import track
from .gloss_lookup import Calibration
from .pem import PEMSet
from .pem import partial_maps
from .pem import prepare_pem_input
from .pyramid import Pyramid

__all__ = ["ChainSpec", "chain_spec", "build_lobe_chain", "build_lobe_chain_pems",
           "chain_calibration", "exponent_calibration", "lobe_average_regions"]

KERNEL_NAME = "exact-lobe"


@dataclass(frozen=True)
class ChainSpec:
    """Exponents and face sizes of the chain's levels (level 0 = input, s = ∞)."""

    s_phong: tuple  # (s_1 > s_2 > ... > s_K), levels 1..K
    face_sizes: tuple  # (N, n_1, ..., n_K)
    base_size: int
    factor: float
    texels_per_halfwidth: float
    n_min: int


def chain_spec(base_size: int, *, s_min: float = 1.0, factor: float = 4.0, texels_per_halfwidth: float = 2.0,
               n_min: int = 8) -> ChainSpec:
    """Level exponents and sizes for an input of face size ``base_size`` (module docstring).

    Parameters
    ----------
    base_size : int  input face size N (≥ 1)
    s_min : float  exponent of the last (broadest) level, ≥ 1
    factor : float  ratio of consecutive exponents (> 1)
    texels_per_halfwidth : float  texels (2/n rad each) per lobe half-width θ½ (> 0)
    n_min : int  smallest face size (power of two ≥ 1)
    """
    N = int(base_size)
    if N < 1:
        raise LayoutError(f"face size must be >= 1, got {base_size}")
    for name, v, lo in (("s_min", s_min, 1.0), ("factor", factor, 1.0)):
        if not np.isfinite(v) or v < lo or (name == "factor" and v == 1.0):
            raise IBLError(f"{name} must be {'> 1' if name == 'factor' else '>= 1'} and finite, got {v!r}")
    if not (np.isfinite(texels_per_halfwidth) and texels_per_halfwidth > 0):
        raise IBLError(f"texels_per_halfwidth must be > 0, got {texels_per_halfwidth!r}")
    if n_min < 1 or (n_min & (n_min - 1)):
        raise IBLError(f"n_min must be a power of two >= 1, got {n_min!r}")
    texel = 2.0 / N
    s_list = [float(s_min)]
    while float(lobe_half_angle(s_list[-1] * factor)) >= texel and len(s_list) < 64:
        s_list.append(s_list[-1] * factor)
    s_list = s_list[::-1]
    sizes = [N]
    for s in s_list:
        need = texels_per_halfwidth * 2.0 / float(lobe_half_angle(s))
        n = int(n_min)
        while n < need and n < N:
            n *= 2
        sizes.append(int(min(n, N)))
    return ChainSpec(tuple(s_list), tuple(sizes), N, float(factor), float(texels_per_halfwidth), int(n_min))


def chain_calibration(spec: ChainSpec):
    """The g → level table of a chain: s_k ↔ level k (log-linear between, 1/s-linear to the mirror)."""
    return exponent_calibration(spec.s_phong, spec.base_size)


def exponent_calibration(s_phong, base_size: int, kernel: str = KERNEL_NAME):
    """The s → level table of levels 1..K holding lobes at the decreasing exponents ``s_phong`` = (s_1, …, s_K)
    over level 0 = the input (face size ``base_size``): level k at s_k, linear in log s between them, linear in 1/s
    from s_1 to the mirror (level 0 at s = ∞), level K for s ≤ s_K (:meth:`~ibl_ref.knuth2014.gloss_lookup.Calibration.level_of`)."""

    K = len(s_phong)
    s = np.asarray(tuple(s_phong)[::-1], dtype=np.float64)  # increasing: s_K .. s_1
    lev = np.arange(K, 0, -1, dtype=np.float64)  # K .. 1
    return Calibration(s, lev, kernel, "exact", "exact", int(base_size), "exact", "lobe_chain", K)


def _tile_angles(n: int, tile: int):
    """Output directions grouped in tiles: list of (flat indices, centre (3,), radius rad)."""
    d = np.asarray(texel_directions(n)).reshape(6, n, n, 3)
    idx = np.arange(6 * n * n).reshape(6, n, n)
    out = []
    t = max(1, min(tile, n))
    for f in range(6):
        for i in range(0, n, t):
            for j in range(0, n, t):
                dd = d[f, i:i + t, j:j + t].reshape(-1, 3)
                c = dd.sum(axis=0)
                c /= np.linalg.norm(c)
                r = float(np.arccos(np.clip(dd @ c, -1.0, 1.0)).max())
                out.append((idx[f, i:i + t, j:j + t].reshape(-1), c, r))
    return out


def lobe_average_regions(cube, labels, n_regions: int, s: float, out_size: int, *, weight_eps: float = 1e-12,
                         tile: int = 8):
    """Exact per-region lobe averages on an output cube of face size ``out_size``.

    Returns ``(avg (6, n, n, R, C), truncation_bound (6, n, n))`` with avg[..., i, :] = Σ_{j∈region i}
    L_j w_j / Σ_j w_j, w_j = max(d·ω_j,0)^s Ω_j over the included texels (module docstring), and the bound δ on
    the neglected weight fraction (|error| ≤ δ·max L).
    """

    env = as_environment(cube, "environment")
    C = env.channels
    s = float(s)
    if not (np.isfinite(s) and s >= 1.0):
        raise IBLError(f"Phong exponent must be finite and >= 1, got {s!r}")
    if not (0.0 < weight_eps < 1.0):
        raise IBLError(f"weight_eps must be in (0, 1), got {weight_eps!r}")
    n = int(out_size)
    t = max(1, min(tile, n))
    tiles = [ids for ids, _, _ in _tile_angles(n, t)]  # output texels in tiles of t × t (one candidate cap each)
    ids = np.concatenate(tiles)
    dst = np.asarray(texel_directions(n)).reshape(-1, 3)[ids]
    out = np.zeros((6 * n * n, n_regions, C))
    bound = np.zeros(6 * n * n)
    out[ids], bound[ids] = lobe_average(env, dst, s, labels=labels, n_regions=n_regions, weight_eps=weight_eps,
                                        group=t * t, return_bound=True)  # the exact Eq. 4 lobe average
    return out.reshape(6, n, n, n_regions, C), bound.reshape(6, n, n)


def _chain_levels(env, labels, R, spec, weight_eps, tile, progress):
    levels = [None]
    bounds = []

    for s, n in track(list(zip(spec.s_phong, spec.face_sizes[1:])), "exact-lobe chain", unit="level",
                      enabled=progress):
        lev, b = lobe_average_regions(env, labels, R, s, n, weight_eps=weight_eps, tile=tile)
        levels.append(lev)
        bounds.append(float(b.max()))
    return levels, bounds


def build_lobe_chain(cube, *, s_min: float = 1.0, factor: float = 4.0, texels_per_halfwidth: float = 2.0,
                     n_min: int = 8, weight_eps: float = 1e-12, dtype=np.float64, progress: bool = False):
    """Exact-lobe chain of one map → ``(pyramid, calibration)`` for :func:`ibl_ref.knuth2014.gloss_lookup.lookup`.

    ``pyramid.levels[k]`` (6, n_k, n_k, C) as in :func:`chain_spec`; ``pyramid.kernel == "exact-lobe"``;
    ``pyramid.truncation_bounds`` lists δ per level (max over texels).
    """

    env = as_environment(cube, "environment")
    N = env.face_size
    spec = chain_spec(N, s_min=s_min, factor=factor, texels_per_halfwidth=texels_per_halfwidth, n_min=n_min)
    labels = np.zeros((6, N, N), dtype=np.intp)
    levels, bounds = _chain_levels(env, labels, 1, spec, weight_eps, 8, progress)
    levels = [env.data.astype(dtype)] + [lev[:, :, :, 0, :].astype(dtype) for lev in levels[1:]]
    pyr = Pyramid(levels=levels, kernel=KERNEL_NAME, order="exact", seam="exact", base_size=N)
    pyr.truncation_bounds = bounds
    pyr.spec = spec
    return pyr, chain_calibration(spec)


def build_lobe_chain_pems(cube, lights=None, *, n_lights: int | None = None, variant: str = "per-face",
                          s_min: float = 1.0, factor: float = 4.0, texels_per_halfwidth: float = 2.0, n_min: int = 8,
                          weight_eps: float = 1e-12, dtype=np.float32, progress: bool = False):
    """Partial environment maps (Sec. 3.1) whose levels are exact lobe averages → :class:`ibl_ref.knuth2014.pem.PEMSet`.

    Drop-in for :func:`ibl_ref.knuth2014.pem.build_pems` (same regions, same ``lookup_all``, ``kernel = "exact-lobe"``),
    so every renderer and experiment can swap the paper's filter pyramid for the exact chain.
    """

    N, env, lights = prepare_pem_input(cube, lights, n_lights, variant, "build_lobe_chain_pems")
    dt = np.dtype(dtype)
    if not np.issubdtype(dt, np.floating):
        raise IBLError(f"PEM dtype must be a float type, got {dt}")
    spec = chain_spec(N, s_min=s_min, factor=factor, texels_per_halfwidth=texels_per_halfwidth, n_min=n_min)
    R = len(lights)
    levels, bounds = _chain_levels(env, lights.labels, R, spec, weight_eps, 8, progress)
    levels[0] = partial_maps(env.data, lights.labels, 0, R)  # level 0: the masked copies themselves (mirror)
    for lev in levels:
        if dt.itemsize < 8 and np.any(np.abs(lev) > np.finfo(dt).max):
            raise IBLError(f"PEM values exceed the range of {dt}; use a wider dtype")
    pems = PEMSet(lights, [lev.astype(dt) for lev in levels], KERNEL_NAME, "exact", "exact",
                  calibration=chain_calibration(spec))
    pems.truncation_bounds = bounds
    pems.spec = spec
    return pems
