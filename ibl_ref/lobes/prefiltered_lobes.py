"""Kautz & McCool (2000) Sec. 4–5 prefiltered 3D environment maps, and Knuth et al. (2014) Sec. 3 "combining several
lobes" (each fitted lobe looked up in the single sqrt-cos filter pyramid).

The lobes come from :mod:`ibl_ref.lobes.kautz_mccool2000` (per view elevation θo: peak offsets ``(θ_off, φ_off)`` from the
mirror direction, tabulated radial profile ``p(γ)`` including the energy rescale, best L2 Phong fit ``P·cos^s γ``).
A lobe approximates the BRDF slice itself, ``f(wi, wo) ≈ Σ_j p_j(γ_j)`` (γ_j = angle(wi, peak_j)), so

    Lo(wo) = ∫_{H²} L(l) f(l, wo) (n·l) dl  ≈  Σ_j ∫_{S²} L(l) p_j(γ_j) (n·l) dl          (KM2000 Eq. 1)
           ≈  Σ_j c_j · E_j(peak_j; θo),   E_j(d; θo) = ∫_{S²} L(l) p_{j,θo}(angle(d, l)) dl   (KM2000 Eq. 2)

with ``c_j = n·r`` (``cos_mode="mirror"``, the paper's Eq. 2 approximation ``n·l ≈ n·r``) or ``c_j = n·peak_j``
(``cos_mode="peak"``, a variant that follows an off-specular peak).  The prefiltered maps integrate over the whole
sphere (a map cannot know the surface's horizon), exactly as in the paper; the reference clips at ``n·l > 0``.

The prefiltering itself (exact convolution with radial profiles) is :mod:`ibl_ref.lobes.profile_convolution`; the
per-pixel exact reference the renders are judged by is :mod:`ibl_ref.lobes.km00_reference`.

(b) :class:`LobeSet` / :func:`build_lobe_set` — the "3D maps": for the sampled elevations θo_k and every tracked lobe
    j (:func:`ibl_ref.lobes.kautz_mccool2000.track_lobes`), the environment prefiltered with lobe j's profile at θo_k,
    array ``(K, J, 6, n, n, C)``.  :meth:`LobeSet.lookup`: seam-aware bilinear in direction
    (:class:`ibl_ref.environment.sampling.CubeSampler`) and linear in θo.  A track missing at an elevation has a zero profile
    there (its offsets are copied from the nearest elevation where it exists, so the peak moves continuously).
(c) :func:`shade_lobes` / :func:`shade_2d` — per-pixel shading.  Frame (matches :mod:`ibl_ref.lobes.kautz_mccool2000`,
    where ``n = +z`` and ``wo = (−sin θo, 0, cos θo)``, ``r = (sin θo, 0, cos θo)``): ``z = n``,
    ``x = normalize((n·wo) n − wo)`` (the tangential direction of r), ``y = z × x``; θo = angle(n, wo); the peak of
    a lobe is at polar angle ``θo + θ_off`` and azimuth ``φ_off`` in that frame (:func:`peak_direction`).  The
    offsets are interpolated linearly in θo and one peak direction indexes both bracketing slices (a 3D texture
    lookup, KM2000 Sec. 5).  At θo = 0 the frame's x is arbitrary (any vector ⟂ n): only lobes with φ_off ≠ 0 *and*
    θo + θ_off ≠ 0 depend on it.  Single 2-D lobe (Sec. 3.2 / Eq. 3): ``Lo ≈ c · k(θo) · E2D(peak)`` with one map of
    the shared unit-peak profile p̄.
(d) :func:`shade_pyramid` — the Knuth extension: lobe j ≈ ``P_j cos^{s_j} γ`` (its Phong fit), and
    ``∫ L P cos^s dω = P · (2π/(s+1)) · avg_s(L)`` where ``avg_s`` is the lobe *average* that a Phong prefilter
    (:mod:`ibl_ref.prefilter`; the paper's: the sqrt-cos filter pyramid) returns at s (g = 1 − 1/s, Eq. 3).  So
    each lobe contributes ``c_j · W_j · prefilter.lookup(peak_j, s_j)`` with the weight ``W_j = P_j · 2π/(s_j+1)`` (``energy="phong"``: the
    integral of the fitted Phong lobe, Meunier 2009 closed form) or ``W_j = ∫ p_j dω`` (``energy="profile"``: keeps
    the fitted profile's exact energy, i.e. KM2000's albedo rescale, and uses the Phong fit only for the shape).
    A fit with s < 1 is looked up at g = 0 (s = 1); W then still uses the fitted s.

Input errors raise :class:`ProfileError` (NaN/Inf/negative/malformed profile), :class:`ElevationRangeError` (θo
outside the sampled range), :class:`ibl_ref.errors.LayoutError` (wrong cube layout) — all :class:`IBLError`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from ..environment import envmap
from ..errors import IBLError
from .profile_convolution import (
    ProfileError,
    check_profile,
    convolve_profiles,
    profile_integral,
)
from ..conventions import phong_exponent

__all__ = ["ElevationRangeError", "LobeSet", "build_lobe_set",
           "build_2d_lobe", "Lobe2D", "local_frame", "peak_direction", "shade_lobes", "shade_2d", "shade_pyramid",
           "COS_MODES", "ENERGY_MODES"]

COS_MODES = ("mirror", "peak")
ENERGY_MODES = ("phong", "profile")

class ElevationRangeError(IBLError):
    """A view elevation θo lies outside the sampled range of a 3D map (or outside [0, π/2))."""




# ----------------------------------------------------------------------------------------------
# (c) local frame and peak direction
# ----------------------------------------------------------------------------------------------
def local_frame(n, wo):
    """Per-sample frame of :mod:`ibl_ref.lobes.kautz_mccool2000`: ``(x, y, z, theta_o)``.

    ``z = n``; ``x = normalize((n·wo) n − wo)`` (the tangential part of the mirror direction r, so that
    ``r = sin θo x + cos θo z`` and ``wo = −sin θo x + cos θo z``); ``y = z × x``; ``θo = angle(n, wo)``.  Where
    wo ∥ n the frame's x is any unit vector ⟂ n (chosen deterministically).
    """
    z = envmap.unit_directions(n, "n")
    wo = envmap.unit_directions(wo, "wo")
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
    direction's azimuth (the :class:`ibl_ref.lobes.kautz_mccool2000.Lobe` convention; :func:`local_frame`)."""
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
        rescale, :func:`ibl_ref.lobes.kautz_mccool2000.fit_multi_lobe` ``rescale=True``).

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
            from ..environment.sampling import CubeSampler

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
    slices : list of :class:`ibl_ref.lobes.kautz_mccool2000.SliceFit`, increasing θo, all on the same γ nodes.
    track_ids : list of lists, optional
        :func:`ibl_ref.lobes.kautz_mccool2000.track_lobes` output (default: lobe index = track id).
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
            from ..environment.sampling import CubeSampler

            self._sampler = CubeSampler(self.map)
        return self._sampler.bilinear(dirs)


def build_2d_lobe(slices_2d, p_bar, k_weights, cube=None, **conv_kw) -> Lobe2D:
    """:class:`Lobe2D` from :func:`ibl_ref.lobes.kautz_mccool2000.fit_single_2d_lobe` output (and its map of ``cube``)."""
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


def shade_pyramid(lobes: LobeSet, prefilter, n, wo, *, energy: str = "phong", cos_mode: str = "mirror",
                  clamp_theta: bool = True, tracks=None) -> np.ndarray:
    """Knuth 2014 extension: ``Lo ≈ Σ_j c_j W_j(θo) · prefilter.lookup(peak_j, s_j(θo))``; (P, C).

    ``prefilter``: any Phong prefilter of the environment (:class:`ibl_ref.prefilter.interface.Prefilter`, e.g.
    the paper's sqrt-cos pyramid ``build_prefilter(cube, "pyramid")`` of :mod:`ibl_ref.prefilter.registry`), looked
    up at the lobe's Phong exponent through its glossiness, s_j = 1/(1 − g_j) with ``g_j = 1 − 1/s_j`` clipped to
    [0, 1] (Eq. 3; s < 1 → g = 0, i.e. s = 1); ``W_j = P_j 2π/(s_j+1)`` (``energy="phong"``) or ``∫ p_j dω``
    (``energy="profile"``), both interpolated linearly in θo (module docstring (d)).
    """

    if getattr(prefilter, "lobe", None) != "phong" or not hasattr(prefilter, "lookup"):
        raise IBLError("shade_pyramid needs a Phong prefilter (an ibl_ref.prefilter method with lobe 'phong', e.g. "
                       "ibl_ref.prefilter.build_prefilter(cube, 'pyramid'))")
    if energy not in ENERGY_MODES:
        raise IBLError(f"energy must be one of {ENERGY_MODES}, got {energy!r}")
    if cos_mode not in COS_MODES:
        raise IBLError(f"cos_mode must be one of {COS_MODES}, got {cos_mode!r}")
    frame, th, th_l, valid = _prep_shading(n, wo, (lobes.theta_o[0], lobes.theta_o[-1]), clamp_theta)
    if energy == "phong":
        W_all = np.where(lobes.phong_P > 0, lobes.phong_P * 2 * np.pi / (lobes.phong_s + 1.0), 0.0)
    else:
        W_all = lobes.integral
    out = None
    for j in (range(lobes.n_tracks) if tracks is None else tracks):
        W, g = lobes.interp(W_all, j, th_l), lobes.interp("glossiness", j, th_l)
        to, po = lobes.offsets(j, th_l)
        d = _peak(frame, th, to, po)
        c = _cos_factor(cos_mode, frame[2], th, d)
        live = (W > 0) & valid
        if np.any(live):
            v = np.asarray(prefilter.lookup(d[live], phong_exponent(np.clip(g[live], 0.0, 1.0))), dtype=np.float64)
            if out is None:
                out = np.zeros(th.shape + (v.shape[-1],))
            out[live] += (c[live] * W[live])[:, None] * v
    if out is None:  # nothing looked up: the channel count from one look-up
        C = np.asarray(prefilter.lookup(np.array([[0.0, 0.0, 1.0]]), 1.0)).shape[-1]
        out = np.zeros(th.shape + (C,))
    return np.where(valid[..., None], out, 0.0)
