"""Kautz & McCool (2000) Sec. 4–5 prefiltered 3D environment maps, and Knuth et al. (2014) Sec. 3 "combining several
lobes" (each fitted lobe looked up in the single sqrt-cos filter pyramid), plus the per-pixel exact reference.

The lobes come from :mod:`ibl_ref.kautz_mccool2000` (per view elevation θo: peak offsets ``(θ_off, φ_off)`` from the
mirror direction, tabulated radial profile ``p(γ)`` including the energy rescale, best L2 Phong fit ``P·cos^s γ``).
A lobe approximates the BRDF slice itself, ``f(wi, wo) ≈ Σ_j p_j(γ_j)`` (γ_j = angle(wi, peak_j)), so

    Lo(wo) = ∫_{H²} L(l) f(l, wo) (n·l) dl  ≈  Σ_j ∫_{S²} L(l) p_j(γ_j) (n·l) dl          (KM2000 Eq. 1)
           ≈  Σ_j c_j · E_j(peak_j; θo),   E_j(d; θo) = ∫_{S²} L(l) p_{j,θo}(angle(d, l)) dl   (KM2000 Eq. 2)

with ``c_j = n·r`` (``cos_mode="mirror"``, the paper's Eq. 2 approximation ``n·l ≈ n·r``) or ``c_j = n·peak_j``
(``cos_mode="peak"``, a variant that follows an off-specular peak).  The prefiltered maps integrate over the whole
sphere (a map cannot know the surface's horizon), exactly as in the paper; the reference clips at ``n·l > 0``.

(a) :func:`convolve_profiles` — exact convolution of a cube map with tabulated radial profiles: every source texel
    with its exact solid angle (:func:`ibl_ref.envmap.cube_solid_angles`), ``E(d) = Σ_j L_j p(angle(d, ω_j)) Ω_j``
    (unnormalised; ``L ≡ 1`` gives ``∫ p dω``, :func:`profile_integral`), float64, vectorised over output tiles ×
    candidate source texels.  Source texels beyond the profile's support are skipped exactly (``p = 0`` there);
    optionally (``tail_rtol > 0``) the profile is also cut where its continuous tail ``∫_{γ>γc} p dω`` is at most
    ``tail_rtol · ∫ p dω`` (:func:`support_angle`; neglected radiance ≈ tail · ``L_max``).  ``supersample=k``
    splits every source texel into k×k sub-texels (exact sub-solid angles, piecewise-constant radiance);
    ``supersample="auto"`` picks k per profile so that its half width spans ≥ 1.5 sub-texels
    (:func:`auto_supersample`).  This matters: a Ward α = 0.04 lobe at θo = 80° is ≈ 0.7° wide, a 64² texel
    1.8°, and with coinciding output/source grids the plain texel-centre rule then always hits the peak (the
    maps come out several times too bright; ``test_auto_supersample_fixes_narrow_lobes``).  Output texels are
    processed in small tiles whose candidate source texels come from a KD-tree ball query (cap = cut-off + tile
    radius), sorted by distance so that each profile uses only its own prefix.  Cost ∝ (out texels) × (source
    texels in the cap) × profiles; measured (``ibl-ref experiment km00-render``, 2-core machine): 48 Ward α = 0.04 profiles (16 θo ×
    3 tracks) from a 64² environment to 64² maps, auto k ≤ 5, tail_rtol = 1e-6: 21 s; the 16 single-lobe ones 17 s.
(b) :class:`LobeSet` / :func:`build_lobe_set` — the "3D maps": for the sampled elevations θo_k and every tracked lobe
    j (:func:`ibl_ref.kautz_mccool2000.track_lobes`), the environment prefiltered with lobe j's profile at θo_k,
    array ``(K, J, 6, n, n, C)``.  :meth:`LobeSet.lookup`: seam-aware bilinear in direction
    (:class:`ibl_ref.sampling.CubeSampler`) and linear in θo.  A track missing at an elevation has a zero profile
    there (its offsets are copied from the nearest elevation where it exists, so the peak moves continuously).
(c) :func:`shade_lobes` / :func:`shade_2d` — per-pixel shading.  Frame (matches :mod:`ibl_ref.kautz_mccool2000`,
    where ``n = +z`` and ``wo = (−sin θo, 0, cos θo)``, ``r = (sin θo, 0, cos θo)``): ``z = n``,
    ``x = normalize((n·wo) n − wo)`` (the tangential direction of r), ``y = z × x``; θo = angle(n, wo); the peak of
    a lobe is at polar angle ``θo + θ_off`` and azimuth ``φ_off`` in that frame (:func:`peak_direction`).  The
    offsets are interpolated linearly in θo and one peak direction indexes both bracketing slices (a 3D texture
    lookup, KM2000 Sec. 5).  At θo = 0 the frame's x is arbitrary (any vector ⟂ n): only lobes with φ_off ≠ 0 *and*
    θo + θ_off ≠ 0 depend on it.  Single 2-D lobe (Sec. 3.2 / Eq. 3): ``Lo ≈ c · k(θo) · E2D(peak)`` with one map of
    the shared unit-peak profile p̄.
(d) :func:`shade_pyramid` — the Knuth extension: lobe j ≈ ``P_j cos^{s_j} γ`` (its Phong fit), and
    ``∫ L P cos^s dω = P · (2π/(s+1)) · avg_s(L)`` where ``avg_s`` is the lobe *average* that
    :func:`ibl_ref.gloss_lookup.lookup` returns at ``g = 1 − 1/s`` (Eq. 3).  So each lobe contributes
    ``c_j · W_j · lookup(pyramid, peak_j, g_j)`` with the weight ``W_j = P_j · 2π/(s_j+1)`` (``energy="phong"``: the
    integral of the fitted Phong lobe, Meunier 2009 closed form) or ``W_j = ∫ p_j dω`` (``energy="profile"``: keeps
    the fitted profile's exact energy, i.e. KM2000's albedo rescale, and uses the Phong fit only for the shape).
    A fit with s < 1 is looked up at g = 0 (s = 1); W then still uses the fitted s.
(e) :func:`render_reference` — per-pixel exact filtering ``Lo = Σ_j L_j f(ω_j, wo) max(n·ω_j, 0) Ω_j`` over the
    environment texels (source texels optionally supersampled); **no visibility/shadows** (KM2000 has none).  For a
    narrow BRDF the gather can be restricted to a cone ``angle(ω, r) ≤ γc`` around the mirror direction; for Ward,
    :func:`ward_cut_angle` chooses γc and :func:`ward_neglected_bound` bounds what is neglected (below).
    ``supersample`` may be per sample (array): the experiment picks k from the BRDF slice's narrowest half width
    at the pixel's θo (:func:`brdf_min_hwhm`; a grazing Ward lobe is narrow out of the incidence plane).

Ward truncation bound.  ``h = normalize(wo + ω)``; the map ω ↦ h has singular values ``½`` and ``1/(2 h·ω)``, both ≥ ½
(dω_h/dω = 1/(4 h·ω)), so geodesic distances shrink at most by ½: ``θh = angle(h, n) ≥ angle(ω, r)/2`` (h(r) = n).
Outside the cone, therefore, ``f cos θi ≤ ks e^{−tan²(γc/2)/α²} √cos θi / (4π α² √cos θo)`` and the neglected
radiance is at most ``L_max · ks · e^{−tan²(γc/2)/α²} / (α² √cos θo)`` (texel solid angles summed over ≤ 4π).

Input errors raise :class:`ProfileError` (NaN/Inf/negative/malformed profile), :class:`ElevationRangeError` (θo
outside the sampled range), :class:`ibl_ref.errors.LayoutError` (wrong cube layout) — all :class:`IBLError`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from . import envmap
from .errors import IBLError, LayoutError, check_radiance

__all__ = ["ProfileError", "ElevationRangeError", "check_profile", "profile_integral", "support_angle",
           "convolve_profiles", "convolve_profile", "profile_hwhm", "auto_supersample", "LobeSet", "build_lobe_set", "build_2d_lobe",
           "Lobe2D", "local_frame", "peak_direction", "shade_lobes", "shade_2d", "shade_pyramid",
           "render_reference", "brdf_min_hwhm", "ward_cut_angle", "ward_neglected_bound", "COS_MODES", "ENERGY_MODES"]

COS_MODES = ("mirror", "peak")
ENERGY_MODES = ("phong", "profile")
#: target number of float64 elements of one (outputs × candidates) block
_BLOCK_ELEMS = 1 << 18


class ProfileError(IBLError):
    """A radial profile p(γ) is malformed: NaN/Inf, negative, wrong shape, or γ not increasing from 0."""


class ElevationRangeError(IBLError):
    """A view elevation θo lies outside the sampled range of a 3D map (or outside [0, π/2))."""


# ----------------------------------------------------------------------------------------------
# profiles
# ----------------------------------------------------------------------------------------------
def check_profile(gamma, profile):
    """Validate a tabulated radial profile; returns float64 ``gamma (G,)`` and ``profile (..., G)``.

    ``gamma`` must be finite, strictly increasing, start at 0 and end ≤ π; ``profile`` finite and ≥ 0.  Between
    nodes the profile is linear in γ; beyond ``gamma[-1]`` it is 0 (as :class:`ibl_ref.kautz_mccool2000.Lobe`).
    """
    g = np.asarray(gamma, dtype=np.float64)
    p = np.asarray(profile, dtype=np.float64)
    if g.ndim != 1 or g.size < 2:
        raise ProfileError(f"gamma must be a 1-D array of ≥ 2 angles, got shape {g.shape}")
    if not np.all(np.isfinite(g)) or g[0] != 0.0 or np.any(np.diff(g) <= 0) or g[-1] > np.pi + 1e-12:
        raise ProfileError("gamma must be finite, strictly increasing, start at 0 and end ≤ π (rad)")
    if p.shape[-1:] != g.shape:
        raise ProfileError(f"profile shape {p.shape} does not end with len(gamma) = {g.size}")
    if not np.all(np.isfinite(p)):
        raise ProfileError(f"profile contains {int((~np.isfinite(p)).sum())} NaN/Inf value(s)")
    if np.any(p < 0):
        raise ProfileError(f"profile contains negative values (min {p.min():g}); lobes must be ≥ 0")
    return g, p


def _segment_integrals(g):
    """∫ over each segment of (hat functions) × sin γ: returns (A, B) with ∫ p sin = Σ A·p_i + B·p_{i+1}."""
    g0, g1 = g[:-1], g[1:]
    h = g1 - g0
    I0 = np.cos(g0) - np.cos(g1)  # ∫ sin γ
    I1 = -h * np.cos(g1) + np.sin(g1) - np.sin(g0)  # ∫ (γ − g0) sin γ
    return I0 - I1 / h, I1 / h


def profile_integral(gamma, profile):
    """``∫_{S²} p(angle(d, ω)) dω = 2π ∫_0^π p(γ) sin γ dγ``, exact for the piecewise-linear profile.

    For ``P·cos^s γ`` sampled finely it tends to ``P·2π/(s+1)`` (clamped cosine lobe; 0 beyond π/2).
    """
    g, p = check_profile(gamma, profile)
    A, B = _segment_integrals(g)
    return 2.0 * np.pi * (p[..., :-1] @ A + p[..., 1:] @ B)


def support_angle(gamma, profile, tail_rtol: float = 0.0):
    """Cut-off angle γc of a profile and the neglected fraction of its integral.

    ``tail_rtol = 0``: γc is the first node beyond which p ≡ 0 (exact; π if p > 0 up to the end).
    ``tail_rtol > 0``: the smallest node γc with ``∫_{γ>γc} p dω ≤ tail_rtol · ∫ p dω`` (continuous integral of the
    piecewise-linear profile).  Returns ``(γc, neglected_fraction)``.
    """
    g, p = check_profile(gamma, profile)
    if p.ndim != 1:
        raise ProfileError("support_angle takes one profile")
    tail_rtol = float(tail_rtol)
    if not (0.0 <= tail_rtol < 1.0):
        raise IBLError(f"tail_rtol must be in [0, 1), got {tail_rtol!r}")
    pos = np.flatnonzero(p > 0)
    if pos.size == 0:
        return 0.0, 0.0
    last = pos[-1]
    gc_exact = float(g[min(last + 1, g.size - 1)]) if last + 1 < g.size else float(np.pi)
    if tail_rtol == 0.0:
        return gc_exact, 0.0
    A, B = _segment_integrals(g)
    seg = p[:-1] * A + p[1:] * B  # ∫ over segment i = [g_i, g_{i+1}]
    total = seg.sum()
    tail = np.concatenate([np.cumsum(seg[::-1])[::-1], [0.0]])  # tail[i] = ∫_{γ > g_i}
    ok = np.flatnonzero(tail <= tail_rtol * total)
    i = int(ok[0])
    return min(float(g[i]), gc_exact), float(tail[i] / total) if total > 0 else 0.0


# ----------------------------------------------------------------------------------------------
# (a) exact convolution with tabulated radial profiles
# ----------------------------------------------------------------------------------------------
def _check_cube(cube, name="environment cube map"):
    envmap.check_cube_shape(cube, name)
    a = np.asarray(cube)
    check_radiance(a, name)
    squeeze = a.ndim == 3
    a = np.asarray(a[..., None] if squeeze else a, dtype=np.float64)
    if a.shape[-1] < 1:
        raise LayoutError(f"{name}: zero channels in shape {np.shape(cube)}")
    return a, squeeze


def _pos_int(name, v):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
        raise IBLError(f"{name} must be a positive integer, got {v!r}")
    return int(v)


def _tile_geometry(n: int, tile: int):
    """Output texels grouped into face tiles: list of (flat indices, centre direction, radius in rad)."""
    d = envmap.texel_directions(n)
    out = []
    for f in range(6):
        for r0 in range(0, n, tile):
            for c0 in range(0, n, tile):
                rr, cc = np.meshgrid(np.arange(r0, min(n, r0 + tile)), np.arange(c0, min(n, c0 + tile)),
                                     indexing="ij")
                idx = (f * n * n + rr * n + cc).ravel()
                dd = d[f, rr, cc].reshape(-1, 3)
                cen = dd.mean(axis=0)
                cen /= np.linalg.norm(cen)
                rad = float(np.arccos(np.clip(dd @ cen, -1.0, 1.0)).max())
                out.append((idx, cen, rad))
    return out


def profile_hwhm(gamma, profile) -> float:
    """Half width at half maximum (rad) of a profile: the first γ beyond its maximum where p ≤ max/2 (π if never)."""
    g, p = check_profile(gamma, profile)
    if p.ndim != 1:
        raise ProfileError("profile_hwhm takes one profile")
    pm = p.max()
    if pm <= 0:
        return float(np.pi)
    i0 = int(np.argmax(p))
    below = np.flatnonzero(p[i0:] <= 0.5 * pm)
    if below.size == 0:
        return float(np.pi)
    i = i0 + int(below[0])
    # linear crossing between nodes i-1 and i
    p0, p1 = p[i - 1], p[i]
    t = (p0 - 0.5 * pm) / (p0 - p1) if p0 != p1 else 1.0
    return float(g[i - 1] + t * (g[i] - g[i - 1]))


def auto_supersample(n: int, hwhm: float, samples_per_hwhm: float = 1.5, max_supersample: int = 8) -> int:
    """Sub-texels per texel edge so that the largest (face-centre) sub-texel, ≈ 2/(n·k) rad, is at most
    ``hwhm / samples_per_hwhm``: ``k = clip(ceil(samples_per_hwhm · (2/n) / hwhm), 1, max_supersample)``."""
    if not (hwhm > 0):
        return 1
    return int(np.clip(math.ceil(samples_per_hwhm * (2.0 / n) / hwhm - 1e-12), 1, int(max_supersample)))


def _convolve_group(a, g, p, gc, out_size, k, tile, progress, out):
    """Core of :func:`convolve_profiles` for profiles sharing one supersampling factor k (writes ``out``)."""
    from scipy.spatial import cKDTree

    n = a.shape[1]
    C = a.shape[-1]
    m = n * k
    src = a if k == 1 else np.repeat(np.repeat(a, k, axis=1), k, axis=2)
    src_dirs = envmap.texel_directions(m).reshape(-1, 3)
    rad_w = src.reshape(-1, C) * np.asarray(envmap.cube_solid_angles(m)).reshape(-1, 1)  # L·Ω
    del src
    live = np.flatnonzero(gc > 0)
    if live.size == 0:
        return
    tree = cKDTree(src_dirs)
    dst = envmap.texel_directions(out_size).reshape(-1, 3)
    tiles = _tile_geometry(out_size, tile)
    it = tiles
    if progress:
        from tqdm import tqdm

        it = tqdm(tiles, desc=f"prefilter x{k}", unit="tile", leave=False)
    gc_max = float(gc[live].max())
    for idx, cen, trad in it:
        cap = min(gc_max + trad + 1e-9, np.pi)
        chord = 2.0 * math.sin(cap / 2.0) * (1.0 + 1e-12) + 1e-12
        cand = np.asarray(tree.query_ball_point(cen, chord), dtype=np.intp)
        if cand.size == 0:
            continue
        cc = np.clip(src_dirs[cand] @ cen, -1.0, 1.0)  # a rounded −1 − 2e-16 must not fall outside cos(π)
        o = np.argsort(-cc, kind="stable")
        cand, cc = cand[o], cc[o]  # nearest to the tile centre first
        # profile q needs only the candidates within gc[q] + tile radius: a prefix of the sorted list
        n_q = np.searchsorted(-cc, -np.cos(np.minimum(gc + trad + 1e-9, np.pi)), side="right")
        sd = src_dirs[cand]
        rw = rad_w[cand]
        rows = max(1, _BLOCK_ELEMS // cand.size)
        for b0 in range(0, idx.size, rows):
            ib = idx[b0:b0 + rows]
            nmax = int(n_q[live].max())
            gam = np.arccos(np.clip(dst[ib] @ sd[:nmax].T, -1.0, 1.0))  # γ = angle(d, ω_j)
            for q in live:
                nq = int(n_q[q])
                if nq == 0:
                    continue
                gq = gam[:, :nq]
                w = np.interp(gq, g, p[q], right=0.0)
                if gc[q] < np.pi:
                    w[gq > gc[q]] = 0.0  # the stated cut (identical for every tile)
                out[q, ib] = w @ rw[:nq]


def convolve_profiles(cube, gamma, profiles, *, out_size: int | None = None, supersample=1,
                      tail_rtol: float = 0.0, tile: int = 4, samples_per_hwhm: float = 1.5,
                      max_supersample: int = 8, progress: bool = False, return_info: bool = False):
    """Exact convolution of a cube map with tabulated radial profiles (KM2000 Eq. 2–3, unnormalised).

    ``E_k(d) = Σ_j L_j p_k(angle(d, ω_j)) Ω_j`` over every source (sub-)texel j (exact solid angles Ω_j), for
    every output texel centre d.

    Parameters
    ----------
    cube : array (6, N, N[, C])
        Finite non-negative radiance.
    gamma : array (G,)
        Profile nodes (rad), 0 = gamma[0] < … ≤ π.
    profiles : array (P, G) or (G,)
        Non-negative profile values (linear between nodes, 0 beyond gamma[-1]).
    out_size : int, optional
        Output face size (default N).
    supersample : int or "auto"
        k×k sub-texels per source texel (piecewise-constant radiance, exact sub-solid angles).  ``"auto"``: per
        profile, :func:`auto_supersample` from its half width (:func:`profile_hwhm`) — a lobe narrower than a
        texel is otherwise integrated by a midpoint rule that hits or misses its peak (gross errors when the
        output and source grids coincide).
    tail_rtol : float
        0: skip only texels where the profile is exactly 0 (exact).  > 0: also cut the profile where its
        continuous tail integral is ≤ ``tail_rtol`` × its integral (:func:`support_angle`).
    tile : int
        Output texels are processed in tile×tile blocks sharing one candidate list (KD-tree ball query).
    samples_per_hwhm, max_supersample : float, int
        Parameters of ``supersample="auto"``.
    progress : bool
        tqdm progress bar over tiles.
    return_info : bool
        Also return ``dict(cut_angle (P,), tail_fraction (P,), supersample (P,))``.

    Returns
    -------
    ndarray (P, 6, n, n, C) (or (6, n, n, C) for a 1-D ``profiles``; C dropped for a 3-d cube)[, info].
    """
    a, squeeze = _check_cube(cube)
    g, p = check_profile(gamma, profiles)
    single = p.ndim == 1
    p = np.atleast_2d(p)
    if p.ndim != 2:
        raise ProfileError(f"profiles must be (P, G) or (G,), got shape {np.shape(profiles)}")
    n = a.shape[1]
    out_size = n if out_size is None else _pos_int("out_size", out_size)
    tile = _pos_int("tile", tile)
    P = p.shape[0]
    if isinstance(supersample, str):
        if supersample != "auto":
            raise IBLError(f"supersample must be a positive integer or 'auto', got {supersample!r}")
        kmax = _pos_int("max_supersample", max_supersample)
        ks = np.array([auto_supersample(n, profile_hwhm(g, pk), float(samples_per_hwhm), kmax) for pk in p])
    else:
        ks = np.full(P, _pos_int("supersample", supersample))
    C = a.shape[-1]
    cuts = [support_angle(g, pk, tail_rtol) for pk in p]
    gc = np.array([c[0] for c in cuts])
    tails = np.array([c[1] for c in cuts])
    out = np.zeros((P, 6 * out_size * out_size, C))
    for k in np.unique(ks):
        sel = np.flatnonzero(ks == k)
        sub = np.zeros((sel.size,) + out.shape[1:])
        _convolve_group(a, g, p[sel], gc[sel], out_size, int(k), tile, progress, sub)
        out[sel] = sub
    res = out.reshape((P, 6, out_size, out_size, C))
    if squeeze:
        res = res[..., 0]
    res = res[0] if single else res
    if return_info:
        return res, dict(cut_angle=gc, tail_fraction=tails, supersample=ks)
    return res


def convolve_profile(cube, gamma, profile, **kw):
    """One profile: :func:`convolve_profiles` → (6, n, n[, C])."""
    p = np.asarray(profile, dtype=np.float64)
    if p.ndim != 1:
        raise ProfileError(f"convolve_profile takes one profile (G,), got shape {p.shape}")
    return convolve_profiles(cube, gamma, p, **kw)


# ----------------------------------------------------------------------------------------------
# (c) local frame and peak direction
# ----------------------------------------------------------------------------------------------
def _unit(v, name):
    v = np.asarray(v, dtype=np.float64)
    if v.shape[-1:] != (3,):
        raise IBLError(f"{name} must be (..., 3) directions, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise IBLError(f"{name} contains NaN/Inf")
    ln = np.linalg.norm(v, axis=-1, keepdims=True)
    if np.any(ln == 0):
        raise IBLError(f"{name} contains zero vectors")
    return v / ln


def local_frame(n, wo):
    """Per-sample frame of :mod:`ibl_ref.kautz_mccool2000`: ``(x, y, z, theta_o)``.

    ``z = n``; ``x = normalize((n·wo) n − wo)`` (the tangential part of the mirror direction r, so that
    ``r = sin θo x + cos θo z`` and ``wo = −sin θo x + cos θo z``); ``y = z × x``; ``θo = angle(n, wo)``.  Where
    wo ∥ n the frame's x is any unit vector ⟂ n (chosen deterministically).
    """
    z = _unit(n, "n")
    wo = _unit(wo, "wo")
    z, wo = np.broadcast_arrays(z, wo)
    c = np.sum(z * wo, axis=-1)
    t = c[..., None] * z - wo
    tl = np.linalg.norm(t, axis=-1, keepdims=True)
    # fallback ⟂ n for wo ∥ n
    a = np.where(np.abs(z[..., :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    fb = a - np.sum(a * z, axis=-1, keepdims=True) * z
    fb /= np.linalg.norm(fb, axis=-1, keepdims=True)
    x = np.where(tl > 1e-12, t / np.where(tl > 0, tl, 1.0), fb)
    y = np.cross(z, x)
    theta_o = np.arccos(np.clip(c, -1.0, 1.0))
    return x, y, z, theta_o


def peak_direction(n, wo, theta_off, phi_off):
    """World direction of a lobe peak: polar angle ``θo + θ_off`` from n, azimuth ``φ_off`` from the mirror
    direction's azimuth (the :class:`ibl_ref.kautz_mccool2000.Lobe` convention; :func:`local_frame`)."""
    x, y, z, th = local_frame(n, wo)
    return _peak((x, y, z), th, np.asarray(theta_off, dtype=np.float64), np.asarray(phi_off, dtype=np.float64))


# ----------------------------------------------------------------------------------------------
# (b) lobe sets and 3D maps
# ----------------------------------------------------------------------------------------------
def _bracket(theta_samples, theta_o):
    """Index k and weight t with θo = (1−t) θ_k + t θ_{k+1}; ElevationRangeError outside the samples."""
    ts = np.asarray(theta_samples, dtype=np.float64)
    th = np.asarray(theta_o, dtype=np.float64)
    if not np.all(np.isfinite(th)):
        raise ElevationRangeError("theta_o contains NaN/Inf")
    tol = 1e-12
    if np.any(th < ts[0] - tol) or np.any(th > ts[-1] + tol):
        raise ElevationRangeError(
            f"theta_o outside the sampled elevations [{np.degrees(ts[0]):.3f}°, {np.degrees(ts[-1]):.3f}°] "
            f"(got {np.degrees(th.min()):.3f}°…{np.degrees(th.max()):.3f}°); clamp explicitly if intended")
    th = np.clip(th, ts[0], ts[-1])
    if ts.size == 1:
        return np.zeros(th.shape, np.intp), np.zeros(th.shape)
    k = np.clip(np.searchsorted(ts, th, side="right") - 1, 0, ts.size - 2)
    t = (th - ts[k]) / (ts[k + 1] - ts[k])
    return k, t


@dataclass
class LobeSet:
    """Tracked lobes over sampled elevations, optionally with their prefiltered 3D maps.

    Attributes
    ----------
    theta_o : (K,) sampled view elevations (rad, increasing).
    theta_off, phi_off : (K, J) peak offsets (rad) of track j at elevation k.
    gamma : (G,) profile nodes; profiles : (K, J, G) (zero where the track is absent).
    phong_s, phong_P : (K, J) Phong fit ``P cos^s γ`` (0 where absent); integral : (K, J) ``∫ p dω``.
    maps : (K, J, 6, n, n, C) or None — E_{k,j}(d), unnormalised (KM2000 Eq. 2 without the cosine factor).
    cut_angle, tail_fraction, supersample : (K, J) convolution cut-offs (rad), neglected tail fractions and
    source supersampling factors.
    """

    theta_o: np.ndarray
    theta_off: np.ndarray
    phi_off: np.ndarray
    gamma: np.ndarray
    profiles: np.ndarray
    phong_s: np.ndarray
    phong_P: np.ndarray
    integral: np.ndarray
    maps: np.ndarray | None = None
    cut_angle: np.ndarray | None = None
    tail_fraction: np.ndarray | None = None
    supersample: np.ndarray | None = None
    _samplers: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def n_tracks(self) -> int:
        return self.profiles.shape[1]

    def offsets(self, j: int, theta_o):
        """Peak offsets (θ_off, φ_off) of track j, linear in θo (φ interpolated on the unwrapped track)."""
        k, t = _bracket(self.theta_o, theta_o)
        th = self.theta_off[:, j]
        ph = np.unwrap(self.phi_off[:, j])
        if self.theta_o.size == 1:
            return th[k], ph[k]
        return (1 - t) * th[k] + t * th[k + 1], (1 - t) * ph[k] + t * ph[k + 1]

    def interp(self, name, j: int, theta_o):
        """A per-(k, j) quantity (``phong_s``, ``phong_P``, ``integral``, ``glossiness``, or a (K, J) array)
        linear in θo."""
        v = name if isinstance(name, np.ndarray) else self.glossiness if name == "glossiness" else getattr(self, name)
        k, t = _bracket(self.theta_o, theta_o)
        if self.theta_o.size == 1:
            return v[k, j]
        return (1 - t) * v[k, j] + t * v[k + 1, j]

    @property
    def glossiness(self) -> np.ndarray:
        s = self.phong_s
        return np.where(s > 1.0, 1.0 - 1.0 / np.where(s > 1.0, s, 1.0), 0.0)

    def scaled(self, factors) -> "LobeSet":
        """The same lobes with the profiles of elevation k multiplied by ``factors[k]`` (e.g. an energy
        rescale, :func:`ibl_ref.kautz_mccool2000.fit_multi_lobe` ``rescale=True``).

        Convolution is linear, so the prefiltered maps are scaled too instead of recomputed; the Phong fit
        keeps its exponent and scales its ``P``; cut angles, tail fractions and supersampling are relative
        and stay.  ``factors``: (K,) finite, non-negative.
        """
        f = np.asarray(factors, dtype=np.float64)
        if f.shape != self.theta_o.shape or not np.all(np.isfinite(f)) or np.any(f < 0):
            raise IBLError(f"factors must be {self.theta_o.size} finite non-negative numbers, got {factors!r}")
        return dataclasses.replace(
            self, profiles=self.profiles * f[:, None, None], phong_P=self.phong_P * f[:, None],
            integral=self.integral * f[:, None],
            maps=None if self.maps is None else self.maps * f.reshape((-1,) + (1,) * (self.maps.ndim - 1)),
            _samplers={})

    def _sampler(self, k: int, j: int):
        key = (k, j)
        s = self._samplers.get(key)
        if s is None:
            from .sampling import CubeSampler

            s = CubeSampler(self.maps[k, j])
            self._samplers[key] = s
        return s

    def lookup(self, j: int, dirs, theta_o) -> np.ndarray:
        """3D-map lookup of track j: seam-aware bilinear at ``dirs`` in slices k, k+1, linear in θo → (..., C)."""
        if self.maps is None:
            raise IBLError("this LobeSet has no prefiltered maps (build_lobe_set(..., cube=...))")
        if not (0 <= int(j) < self.n_tracks):
            raise IBLError(f"track index {j} outside 0…{self.n_tracks - 1}")
        d = np.asarray(dirs, dtype=np.float64)
        if d.shape[-1:] != (3,):
            raise IBLError(f"dirs must be (..., 3), got shape {d.shape}")
        lead = d.shape[:-1]
        th = np.broadcast_to(np.asarray(theta_o, dtype=np.float64), lead).reshape(-1)
        d = d.reshape(-1, 3)
        k, t = _bracket(self.theta_o, th)
        C = self.maps.shape[-1]
        out = np.zeros((d.shape[0], C))
        for kk in np.unique(k):
            sel = k == kk
            v = self._sampler(int(kk), j).bilinear(d[sel])
            tt = t[sel]
            bl = tt > 0
            if np.any(bl):
                v1 = self._sampler(int(kk) + 1, j).bilinear(d[sel][bl])
                v[bl] = v[bl] + (v1 - v[bl]) * tt[bl, None]
            out[sel] = v
        return out.reshape(lead + (C,))


#: a peak within this angle (rad) of the normal has no meaningful azimuth (the peak search stops ≈ 1e-8 rad away)
_AZIMUTH_UNDEFINED = 1e-6


def _defined_azimuth(lb) -> float:
    """φ_off of a fitted lobe, or NaN where its peak is (numerically) on the normal and φ is noise."""
    return float("nan") if abs(math.sin(lb.theta_o + lb.theta_off)) < _AZIMUTH_UNDEFINED else float(lb.phi_off)


def _fill_azimuths(theta_o, phi):
    """Undefined (NaN) azimuths of one track take the value at the nearest elevation where it is defined (0 if
    nowhere): the peak then moves in one plane towards the normal, and interpolating φ_off between elevations
    cannot swing it out of that plane (a noise azimuth of −179° at θo = 0 would)."""
    phi = np.array(phi, dtype=np.float64)
    ok = np.flatnonzero(np.isfinite(phi))
    bad = np.flatnonzero(~np.isfinite(phi))
    if bad.size:
        phi[bad] = phi[ok[np.argmin(np.abs(theta_o[ok][None, :] - theta_o[bad][:, None]), axis=1)]] if ok.size else 0.0
    return phi


def build_lobe_set(slices, track_ids=None, cube=None, **conv_kw) -> LobeSet:
    """Collect per-elevation lobe fits into tracks (and prefilter ``cube`` with every (k, j) profile).

    Parameters
    ----------
    slices : list of :class:`ibl_ref.kautz_mccool2000.SliceFit`, increasing θo, all on the same γ nodes.
    track_ids : list of lists, optional
        :func:`ibl_ref.kautz_mccool2000.track_lobes` output (default: lobe index = track id).
    cube : (6, N, N[, C]) array, optional
        Environment to prefilter (:func:`convolve_profiles` with ``conv_kw``).
    """
    if not slices:
        raise IBLError("no lobe fits given")
    th = np.array([s.theta_o for s in slices], dtype=np.float64)
    if np.any(np.diff(th) <= 0):
        raise ElevationRangeError("slices must have strictly increasing theta_o")
    if track_ids is None:
        track_ids = [list(range(len(s.lobes))) for s in slices]
    if len(track_ids) != len(slices) or any(len(t) != len(s.lobes) for t, s in zip(track_ids, slices)):
        raise IBLError("track_ids must give one id per lobe of every slice")
    lobes = [lb for s in slices for lb in s.lobes]
    if not lobes:
        raise IBLError("the fits contain no lobe")
    gamma = np.asarray(lobes[0].gamma, dtype=np.float64)
    if any(lb.gamma.shape != gamma.shape or not np.array_equal(lb.gamma, gamma) for lb in lobes):
        raise ProfileError("all lobes must share the same γ nodes")
    J = max(max(t) for t in track_ids if t) + 1
    K = th.size
    G = gamma.size
    prof = np.zeros((K, J, G))
    toff = np.full((K, J), np.nan)
    poff = np.full((K, J), np.nan)
    ps = np.zeros((K, J))
    pP = np.zeros((K, J))
    for k, (s, tid) in enumerate(zip(slices, track_ids)):
        for lb, j in zip(s.lobes, tid):
            prof[k, j] = lb.profile
            toff[k, j] = lb.theta_off
            poff[k, j] = _defined_azimuth(lb)
            ps[k, j] = lb.phong_exponent
            pP[k, j] = lb.phong_scale
    for j in range(J):  # absent: copy offsets from the nearest elevation where the track exists
        have = np.flatnonzero(np.isfinite(toff[:, j]))
        for k in np.flatnonzero(~np.isfinite(toff[:, j])):
            src = have[np.argmin(np.abs(th[have] - th[k]))]
            toff[k, j], poff[k, j] = toff[src, j], poff[src, j]
        poff[:, j] = _fill_azimuths(th, poff[:, j])
    check_profile(gamma, prof)
    ls = LobeSet(th, toff, poff, gamma, prof, ps, pP, profile_integral(gamma, prof))
    if cube is not None:
        maps, info = convolve_profiles(cube, gamma, prof.reshape(K * J, G), return_info=True, **conv_kw)
        if maps.ndim == 4:  # 3-d cube input
            maps = maps[..., None]
        ls.maps = maps.reshape((K, J) + maps.shape[1:])
        ls.cut_angle = info["cut_angle"].reshape(K, J)
        ls.tail_fraction = info["tail_fraction"].reshape(K, J)
        ls.supersample = info["supersample"].reshape(K, J)
    return ls


@dataclass
class Lobe2D:
    """Single 2-D lobe (KM2000 Sec. 3.2): shared unit-peak profile ``p_bar``, weights ``k(θo)``, peak offsets,
    and its prefiltered 2-D map (Eq. 3) ``map (6, n, n, C)``."""

    theta_o: np.ndarray
    theta_off: np.ndarray
    phi_off: np.ndarray
    k: np.ndarray
    gamma: np.ndarray
    p_bar: np.ndarray
    map: np.ndarray | None = None
    cut_angle: float = np.pi
    tail_fraction: float = 0.0
    supersample: int = 1
    _sampler: object = field(default=None, repr=False, compare=False)

    def weight(self, theta_o):
        k, t = _bracket(self.theta_o, theta_o)
        return self.k[k] if self.theta_o.size == 1 else (1 - t) * self.k[k] + t * self.k[k + 1]

    def offsets(self, theta_o):
        k, t = _bracket(self.theta_o, theta_o)
        if self.theta_o.size == 1:
            return self.theta_off[k], self.phi_off[k]
        ph = np.unwrap(self.phi_off)
        return ((1 - t) * self.theta_off[k] + t * self.theta_off[k + 1], (1 - t) * ph[k] + t * ph[k + 1])

    def lookup(self, dirs) -> np.ndarray:
        if self.map is None:
            raise IBLError("this Lobe2D has no prefiltered map")
        if self._sampler is None:
            from .sampling import CubeSampler

            self._sampler = CubeSampler(self.map)
        return self._sampler.bilinear(dirs)


def build_2d_lobe(slices_2d, p_bar, k_weights, cube=None, **conv_kw) -> Lobe2D:
    """:class:`Lobe2D` from :func:`ibl_ref.kautz_mccool2000.fit_single_2d_lobe` output (and its map of ``cube``)."""
    th = np.array([s.theta_o for s in slices_2d], dtype=np.float64)
    if np.any(np.diff(th) <= 0):
        raise ElevationRangeError("slices must have strictly increasing theta_o")
    lbs = [s.lobes[0] for s in slices_2d]
    gamma, pb = check_profile(lbs[0].gamma, p_bar)
    toff = np.array([lb.theta_off for lb in lbs])
    poff = _fill_azimuths(th, np.array([_defined_azimuth(lb) for lb in lbs]))
    out = Lobe2D(th, toff, poff, np.asarray(k_weights, dtype=np.float64), gamma, pb)
    if cube is not None:
        m, info = convolve_profiles(cube, gamma, pb[None], return_info=True, **conv_kw)
        out.map = m[0] if m.ndim == 5 else m[0][..., None]
        out.cut_angle, out.tail_fraction = float(info["cut_angle"][0]), float(info["tail_fraction"][0])
        out.supersample = int(info["supersample"][0])
    return out


# ----------------------------------------------------------------------------------------------
# (c), (d) shading
# ----------------------------------------------------------------------------------------------
def _prep_shading(n, wo, theta_range, clamp_theta):
    """Frame, θo (clamped to the sampled range if asked) and the valid mask (n·wo > 0)."""
    if clamp_theta not in (True, False):
        raise IBLError("clamp_theta must be True or False")
    x, y, z, th = local_frame(n, wo)
    valid = th < np.pi / 2
    lo, hi = theta_range
    th_l = np.where(valid, th, lo)
    if clamp_theta:
        th_l = np.clip(th_l, lo, hi)
    return (x, y, z), th, th_l, valid


def _peak(frame, theta, theta_off, phi_off):
    x, y, z = frame
    tp = theta + theta_off
    st = np.sin(tp)
    return (st * np.cos(phi_off))[..., None] * x + (st * np.sin(phi_off))[..., None] * y + np.cos(tp)[..., None] * z


def _cos_factor(cos_mode, z, theta, peak):
    if cos_mode == "mirror":
        return np.cos(theta)  # n·r = cos θo (KM2000 Eq. 2)
    if cos_mode == "peak":
        return np.maximum(np.sum(z * peak, axis=-1), 0.0)
    raise IBLError(f"cos_mode must be one of {COS_MODES}, got {cos_mode!r}")


def shade_lobes(lobes: LobeSet, n, wo, *, cos_mode: str = "mirror", clamp_theta: bool = True,
                tracks=None) -> np.ndarray:
    """``Lo ≈ Σ_j c_j E_j(peak_j(θo); θo)`` from the 3D maps (KM2000 Sec. 5.1/5.3); (P, C).

    ``n``, ``wo``: (P, 3) unit normals / view vectors (toward the viewer).  Samples with n·wo ≤ 0 get 0.
    ``clamp_theta``: θo beyond the sampled range is clamped to it (explicit; False raises ElevationRangeError).
    The peak direction uses the (clamped) θo's offsets but the sample's true frame and θo.
    """
    if cos_mode not in COS_MODES:
        raise IBLError(f"cos_mode must be one of {COS_MODES}, got {cos_mode!r}")
    frame, th, th_l, valid = _prep_shading(n, wo, (lobes.theta_o[0], lobes.theta_o[-1]), clamp_theta)
    C = lobes.maps.shape[-1] if lobes.maps is not None else 0
    out = np.zeros(th.shape + (C,))
    for j in (range(lobes.n_tracks) if tracks is None else tracks):
        to, po = lobes.offsets(j, th_l)
        d = _peak(frame, th, to, po)
        c = _cos_factor(cos_mode, frame[2], th, d)
        out += c[..., None] * lobes.lookup(j, d, th_l)
    return np.where(valid[..., None], out, 0.0)


def shade_2d(lobe2d: Lobe2D, n, wo, *, cos_mode: str = "mirror", clamp_theta: bool = True) -> np.ndarray:
    """Single 2-D lobe: ``Lo ≈ c · k(θo) · E2D(peak(θo))`` (KM2000 Sec. 5.2, Eq. 3); (P, C)."""
    if cos_mode not in COS_MODES:
        raise IBLError(f"cos_mode must be one of {COS_MODES}, got {cos_mode!r}")
    frame, th, th_l, valid = _prep_shading(n, wo, (lobe2d.theta_o[0], lobe2d.theta_o[-1]), clamp_theta)
    to, po = lobe2d.offsets(th_l)
    d = _peak(frame, th, to, po)
    c = _cos_factor(cos_mode, frame[2], th, d)
    out = (c * lobe2d.weight(th_l))[..., None] * lobe2d.lookup(d)
    return np.where(valid[..., None], out, 0.0)


def shade_pyramid(lobes: LobeSet, pyramid, n, wo, *, energy: str = "phong", cos_mode: str = "mirror",
                  clamp_theta: bool = True, calibration=None, tracks=None) -> np.ndarray:
    """Knuth 2014 extension: ``Lo ≈ Σ_j c_j W_j(θo) · lookup(pyramid, peak_j, g_j(θo))``; (P, C).

    ``g_j = 1 − 1/s_j`` (Eq. 3; s < 1 → g = 0) and ``W_j = P_j 2π/(s_j+1)`` (``energy="phong"``) or ``∫ p_j dω``
    (``energy="profile"``), both interpolated linearly in θo (module docstring (d)).
    """
    from .gloss_lookup import lookup as gloss_lookup

    if energy not in ENERGY_MODES:
        raise IBLError(f"energy must be one of {ENERGY_MODES}, got {energy!r}")
    if cos_mode not in COS_MODES:
        raise IBLError(f"cos_mode must be one of {COS_MODES}, got {cos_mode!r}")
    frame, th, th_l, valid = _prep_shading(n, wo, (lobes.theta_o[0], lobes.theta_o[-1]), clamp_theta)
    if energy == "phong":
        W_all = np.where(lobes.phong_P > 0, lobes.phong_P * 2 * np.pi / (lobes.phong_s + 1.0), 0.0)
    else:
        W_all = lobes.integral
    C = pyramid.levels[0].shape[-1]
    out = np.zeros(th.shape + (C,))
    for j in (range(lobes.n_tracks) if tracks is None else tracks):
        W, g = lobes.interp(W_all, j, th_l), lobes.interp("glossiness", j, th_l)
        to, po = lobes.offsets(j, th_l)
        d = _peak(frame, th, to, po)
        c = _cos_factor(cos_mode, frame[2], th, d)
        live = (W > 0) & valid
        if np.any(live):
            v = np.asarray(gloss_lookup(pyramid, d[live], np.clip(g[live], 0.0, 1.0), calibration),
                           dtype=np.float64)
            out[live] += (c[live] * W[live])[:, None] * v
    return np.where(valid[..., None], out, 0.0)


# ----------------------------------------------------------------------------------------------
# (e) per-pixel exact reference
# ----------------------------------------------------------------------------------------------
def ward_cut_angle(alpha: float, eps: float = 1e-12) -> float:
    """Cone half-angle γc around r outside which Ward's exponential factor is ≤ eps (θh ≥ γ/2, module doc)."""
    alpha, eps = float(alpha), float(eps)
    if not (alpha > 0 and np.isfinite(alpha)) or not (0 < eps < 1):
        raise IBLError(f"need alpha > 0 and 0 < eps < 1, got alpha={alpha!r}, eps={eps!r}")
    return float(min(2.0 * math.atan(alpha * math.sqrt(math.log(1.0 / eps))), np.pi))


def ward_neglected_bound(alpha: float, ks: float, gamma_c: float, cos_theta_o, L_max: float):
    """Bound on the radiance neglected by the cone cut γc for Ward's specular term (module docstring): per sample.

    The diffuse term ``kd/π`` is not covered (it is not concentrated around r): with ``kd > 0`` gather without a
    cut (:func:`ibl_ref.experiments.km00_render.render_single_method` does)."""
    e = math.exp(-math.tan(min(gamma_c, np.pi - 1e-9) / 2.0) ** 2 / alpha**2) if gamma_c < np.pi else 0.0
    co = np.maximum(np.asarray(cos_theta_o, dtype=np.float64), 1e-300)
    return L_max * ks * e / (alpha**2 * np.sqrt(co))


def brdf_min_hwhm(brdf, theta_o, n_phi: int = 24, n_gamma: int = 400) -> np.ndarray:
    """Smallest half width at half maximum (rad) of the slice ``f(·, wo(θo))`` over great circles through the
    mirror direction r (``n = +z``; :func:`ibl_ref.brdfs.view_direction`).

    Along each of ``n_phi`` azimuths the first γ where ``f < max f / 2`` (max over all samples) is the half width;
    the minimum over azimuths is returned (an off-specular peak makes one side narrower: conservative).  Used to
    choose the reference's supersampling (an anisotropic grazing Ward lobe is narrow out of the incidence plane).
    """
    from .brdfs import view_direction

    th = np.atleast_1d(np.asarray(theta_o, dtype=np.float64))
    gam = 0.5 * np.pi * (np.arange(n_gamma) / (n_gamma - 1)) ** 2
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    out = np.empty(th.shape)
    for i, t in enumerate(th):
        wo = view_direction(t)
        r = np.array([np.sin(t), 0.0, np.cos(t)])
        u = np.array([np.cos(t), 0.0, -np.sin(t)])  # ⟂ r in the incidence plane
        v = np.array([0.0, 1.0, 0.0])
        d = (np.cos(gam)[:, None, None] * r + np.sin(gam)[:, None, None]
             * (np.cos(phi)[None, :, None] * u + np.sin(phi)[None, :, None] * v))
        f = np.where(d[..., 2] > 0, brdf(d, wo), 0.0)
        fmax = f.max()
        if not fmax > 0:
            out[i] = np.pi
            continue
        below = f < 0.5 * fmax
        first = np.where(below.any(axis=0), below.argmax(axis=0), n_gamma - 1)
        out[i] = float(gam[np.maximum(first, 1)].min())
    return out if np.ndim(theta_o) else float(out[0])


def render_reference(cube, n, wo, brdf, *, supersample: int = 1, cut_angle: float | None = None,
                     bucket_size: int = 16, progress: bool = False) -> np.ndarray:
    """Per-pixel exact filtering ``Lo = Σ_j L_j f(ω_j, wo, n) max(n·ω_j, 0) Ω_j`` (no visibility); (P, C).

    Parameters
    ----------
    cube : (6, N, N[, C]) radiance; supersample : k×k sub-texels per texel (piecewise-constant L).
    n, wo : (P, 3) unit normals and view directions.
    brdf : callable ``f(wi, wo, n)`` (:func:`ibl_ref.brdfs.get_brdf`), 0 below either horizon.
    cut_angle : float, optional
        Gather only source texels within this angle of the mirror direction r (None: all texels; for Ward see
        :func:`ward_cut_angle` / :func:`ward_neglected_bound`).  Texels outside the cone may be included (whole
        buckets share a candidate list); that only adds exact terms.
    bucket_size : int
        Samples are bucketed by the cube texel (face size ``bucket_size``) of r to share candidate lists.
    """
    from scipy.spatial import cKDTree

    a, squeeze = _check_cube(cube)
    nb = _pos_int("bucket_size", bucket_size)
    nn = _unit(n, "n").reshape(-1, 3)
    vv = _unit(wo, "wo").reshape(-1, 3)
    if nn.shape != vv.shape:
        raise IBLError(f"n and wo must have the same shape, got {np.shape(n)} and {np.shape(wo)}")
    ks = np.asarray(supersample)
    if ks.ndim == 0:
        ks = np.full(nn.shape[0], _pos_int("supersample", int(ks) if np.issubdtype(ks.dtype, np.integer) else ks))
    elif ks.shape != (nn.shape[0],) or not np.issubdtype(ks.dtype, np.integer) or np.any(ks < 1):
        raise IBLError("supersample must be a positive integer or a (P,) array of positive integers")
    C = a.shape[-1]
    cdot = np.sum(nn * vv, axis=1)
    r = 2.0 * cdot[:, None] * nn - vv
    out = np.zeros((nn.shape[0], C))
    f, row, col = envmap.direction_to_texel(r, nb)
    for k in np.unique(ks):
        m = a.shape[1] * int(k)
        src = a if k == 1 else np.repeat(np.repeat(a, int(k), axis=1), int(k), axis=2)
        sd = envmap.texel_directions(m).reshape(-1, 3)
        rw = src.reshape(-1, C) * np.asarray(envmap.cube_solid_angles(m)).reshape(-1, 1)
        del src
        tree = cKDTree(sd) if cut_angle is not None else None
        ok = (cdot > 0) & (ks == k)
        key = np.where(ok, (f * nb + row) * nb + col, -1)
        order = np.argsort(key, kind="stable")
        ks_sorted = key[order]
        starts = np.flatnonzero(np.r_[True, ks_sorted[1:] != ks_sorted[:-1]])
        ends = np.r_[starts[1:], ks_sorted.size]
        groups = [order[s0:e0] for s0, e0 in zip(starts, ends) if ks_sorted[s0] >= 0]
        it = groups
        if progress:
            from tqdm import tqdm

            it = tqdm(groups, desc=f"reference x{k}", unit="bucket", leave=False)
        for idx in it:
            if tree is None:
                cand = np.arange(sd.shape[0])
            else:
                rr = r[idx]
                cen = rr.mean(axis=0)
                cen /= np.linalg.norm(cen)
                rad = float(np.arccos(np.clip(rr @ cen, -1.0, 1.0)).max())
                cap = min(float(cut_angle) + rad + 1e-9, np.pi)
                cand = np.asarray(tree.query_ball_point(cen, 2.0 * math.sin(cap / 2.0) * (1 + 1e-12) + 1e-12),
                                  dtype=np.intp)
            if cand.size == 0:
                continue
            wi = sd[cand]
            rwc = rw[cand]
            rows = max(1, _BLOCK_ELEMS // cand.size)
            for b0 in range(0, idx.size, rows):
                ib = idx[b0:b0 + rows]
                fv = brdf(wi[None, :, :], vv[ib][:, None, :], nn[ib][:, None, :])
                ci = np.maximum(nn[ib] @ wi.T, 0.0)
                out[ib] = (fv * ci) @ rwc
    if not np.all(np.isfinite(out)):
        raise IBLError("reference render produced NaN/Inf (check the BRDF parameters)")
    return out[:, 0] if squeeze else out
