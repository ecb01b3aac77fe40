"""Kautz & McCool (2000) "Approximation of Glossy Reflection with Prefiltered Environment Maps" — lobe fitting.

Implements the BRDF-approximation part (Sec. 3) of the paper, per view elevation θo (``n = +z``,
``wo = brdfs.view_direction(θo)``, mirror direction ``r = (sin θo, 0, cos θo)``):

* :func:`fit_single_lobe` — Sec. 3.1: find the peak of the slice ``f_θo(wi)``, take *profile curves* along
  great circles through the peak (``n_phi`` azimuths), average them into a mean profile ``p_θo(γ)`` (γ = angle
  from the peak), rotate it around the peak (radially symmetric lobe), and rescale it so that its
  hemispherical reflectivity ``∫ p cos θi dωi`` equals the BRDF's directional albedo.
* :func:`fit_single_2d_lobe` — Sec. 3.2: one average shape ``p(γ)`` for all elevations with a weight ``k(θo)``
  (``f ≈ k(θo) p(γ)``); ``k`` matches the albedo per elevation.
* :func:`fit_multi_lobe` — Sec. 3.3: greedy: peak of the residual, *minimum* profile (so the lobe never exceeds
  the residual along the sampled profiles), subtract (both sampled), repeat up to ``n_lobes``.
* :func:`track_lobes` — Sec. 3.3 / Fig. 5: consistent lobe ordering across elevations (Hungarian assignment on
  the peak offsets ``(θ_off, φ_off)``).
* Each :class:`Lobe` stores the peak direction and its offsets from ``r``, the tabulated profile ``p(γ)`` (scale
  included), the energy scale applied, and its best L2 Phong fit ``P·cos^s γ`` (``phong_exponent``,
  ``glossiness = 1 − 1/s``, Knuth 2014 Eq. 3) so that it can be looked up in a Phong-prefiltered pyramid later.
* :func:`rms_error` — relative RMS of the approximation over the hemisphere and the sampled elevations
  (analogue of the paper's Fig. 7).

Choices that change numbers (explicit parameters)
-------------------------------------------------
* Profiles are sampled at ``n_gamma`` angles ``γ_k = π (k/(n_gamma−1))²`` (dense near the peak) and ``n_phi``
  azimuths; a profile sample below the horizon (``n·wi ≤ 0``, where the BRDF is not defined) is *missing*: the
  mean/minimum is taken over the azimuths that are above the horizon (0 if none).  A lobe is evaluated by linear
  interpolation in γ and is compared with the BRDF only on the upper hemisphere.
* Peaks: arg-max of the (residual) slice on the evaluation rule, refined by Nelder–Mead in (θi, φi).
* Energies and errors use :func:`ibl_ref.lobes.brdfs.hemisphere_rule` (Gauss–Legendre graded around ``r``, ``width``).
* RMS error: ``sqrt(Σ w (f − f̂)² / Σ w f²)`` summed over the rule's solid-angle weights ``w`` and all sampled
  θo (BRDF values, no cosine weighting; the paper does not define its "relative mean square error").
* For the single 2-D lobe the shared shape is the mean of the per-elevation mean profiles normalised to unit peak,
  centred on each elevation's peak direction.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

from .brdfs import direction_from_angles, hemisphere_rule, view_direction
from ..errors import IBLError

__all__ = ["Lobe", "SliceFit", "gamma_nodes", "fit_single_lobe", "fit_multi_lobe", "fit_single_2d_lobe",
           "track_lobes", "rms_error", "slice_rel_rms", "phong_fit", "lobe_energy", "slice_albedo"]


def gamma_nodes(n_gamma: int = 256) -> np.ndarray:
    """Profile sample angles ``γ_k = π (k/(n−1))²`` (rad): dense near the peak.

    Parameters
    ----------
    n_gamma : int, optional
        At least 8.

    Returns
    -------
    ndarray, float64, shape (n_gamma,)
        From 0 to π.
    """
    if n_gamma < 8:
        raise IBLError(f"n_gamma must be >= 8, got {n_gamma}")
    return np.pi * (np.arange(n_gamma) / (n_gamma - 1)) ** 2


def _frame(p):
    """Orthonormal (u, v) perpendicular to unit p."""
    a = np.array([0.0, 0.0, 1.0]) if abs(p[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(a, p)
    u /= np.linalg.norm(u)
    return u, np.cross(p, u)


def _angles(d):
    return float(np.arccos(np.clip(d[2], -1, 1))), float(np.arctan2(d[1], d[0]))


def phong_fit(gamma, profile):
    """Best L2 Phong lobe ``P·max(cos γ,0)^s`` to a radial profile over the sphere.

    Minimises ``∫ (p(γ) − P cos^s γ)² 2π sin γ dγ`` (trapezoid on the profile nodes, refined ×8 by linear
    interpolation); ``P`` in closed form, ``s`` by a bounded search on log s ∈ [log 1e-3, log 1e7].

    Parameters
    ----------
    gamma : array_like, shape (G,)
        Profile angles (rad), increasing from 0.
    profile : array_like, shape (G,)
        Profile values.

    Returns
    -------
    s, P : float
        ``(0, 0)`` for a zero profile.

    Examples
    --------
    A profile that is a Phong lobe is fitted by itself:

    >>> import numpy as np
    >>> from ibl_ref.lobes.kautz_mccool2000 import gamma_nodes, phong_fit
    >>> g = gamma_nodes(256)
    >>> s, P = phong_fit(g, 3.0 * np.maximum(np.cos(g), 0.0) ** 50)
    >>> round(s, 1), round(P, 3)
    (50.0, 3.0)
    """
    g = np.interp(np.linspace(0, 1, 8 * len(gamma)), np.linspace(0, 1, len(gamma)), gamma)
    p = np.interp(g, gamma, profile)
    w = np.gradient(g) * 2 * np.pi * np.sin(g)
    if not np.any(p * w > 0):
        return 0.0, 0.0
    cg = np.cos(g)
    lc = np.where(cg > 0, np.log(np.where(cg > 0, cg, 1.0)), -np.inf)

    def basis(s):
        return np.where(cg > 0, np.exp(s * np.where(cg > 0, lc, 0.0)), 0.0)

    def obj(u):
        b = basis(np.exp(u))
        bb = np.sum(w * b * b)
        return -np.sum(w * p * b) ** 2 / bb if bb > 0 else 0.0

    r = optimize.minimize_scalar(obj, bounds=(np.log(1e-3), np.log(1e7)), method="bounded",
                                 options=dict(xatol=1e-9))
    s = float(np.exp(r.x))
    b = basis(s)
    return s, float(np.sum(w * p * b) / np.sum(w * b * b))


@dataclass
class Lobe:
    """A radially symmetric lobe ``p(γ)``, γ = angle between ``wi`` and ``peak``.

    ``theta_off``/``phi_off``: peak elevation minus the mirror elevation θo, and peak azimuth (the mirror
    direction has azimuth 0).  ``profile`` includes ``scale`` (the energy rescale factor that was applied).
    ``phong_exponent``/``phong_scale``: best L2 Phong approximation (:func:`phong_fit`); ``glossiness`` =
    ``1 − 1/s`` (Knuth 2014 Eq. 3, clipped at 0).
    """

    theta_o: float
    peak: np.ndarray
    gamma: np.ndarray
    profile: np.ndarray
    scale: float = 1.0
    kind: str = "mean"
    theta_off: float = field(init=False)
    phi_off: float = field(init=False)
    phong_exponent: float = field(init=False)
    phong_scale: float = field(init=False)

    def __post_init__(self):
        th, ph = _angles(self.peak)
        self.theta_off = th - self.theta_o
        self.phi_off = ph
        self.phong_exponent, self.phong_scale = phong_fit(self.gamma, self.profile)

    @property
    def glossiness(self) -> float:
        s = self.phong_exponent
        return max(0.0, 1.0 - 1.0 / s) if s > 0 else 0.0

    def __call__(self, wi) -> np.ndarray:
        wi = np.asarray(wi, dtype=np.float64)
        gam = np.arccos(np.clip(wi @ self.peak, -1.0, 1.0))
        return np.interp(gam, self.gamma, self.profile, right=0.0)

    def as_dict(self) -> dict:
        return dict(theta_o_deg=np.degrees(self.theta_o), theta_off_deg=np.degrees(self.theta_off),
                    phi_off_deg=np.degrees(self.phi_off), peak_value=float(self.profile[0]), scale=self.scale,
                    kind=self.kind, phong_exponent=self.phong_exponent, phong_scale=self.phong_scale,
                    glossiness=self.glossiness)


@dataclass
class SliceFit:
    """Lobes fitted at one view elevation, with the albedo and the RMS after each lobe."""

    theta_o: float
    lobes: list
    albedo: float
    err2_after: list  # Σ w (f − f̂)² after 1..len(lobes) lobes
    f2: float  # Σ w f²

    def __call__(self, wi, n_lobes=None):
        lobes = self.lobes if n_lobes is None else self.lobes[:n_lobes]
        wi = np.asarray(wi, dtype=np.float64)
        out = np.zeros(wi.shape[:-1])
        for lb in lobes:
            out = out + lb(wi)
        return np.where(wi[..., 2] > 0, out, 0.0)


def _check_theta(theta_o):
    t = float(theta_o)
    if not np.isfinite(t) or not (0.0 <= t < np.pi / 2):
        raise IBLError(f"theta_o must be in [0, π/2) rad, got {theta_o!r}")
    return t


def slice_albedo(brdf, theta_o, width: float = 0.01) -> float:
    """Directional albedo ``∫ f(wi, wo) cos θi dωi`` of the slice at elevation θo (same rule as the fits).

    Parameters
    ----------
    brdf : callable ``f(wi, wo)``
    theta_o : float
        View elevation (rad), in [0, π/2).
    width : float, optional
        Finest panel of :func:`ibl_ref.lobes.brdfs.hemisphere_rule` (rad).

    Returns
    -------
    float
    """
    t = _check_theta(theta_o)
    wi, w = hemisphere_rule(t, width)
    return float(np.sum(brdf(wi, view_direction(t)) * wi[:, 2] * w))


def lobe_energy(lobe_or_fn, theta_o, width: float = 0.01) -> float:
    """``∫_{H²} p(wi) cos θi dωi`` of a lobe (or any function of wi) on :func:`~ibl_ref.lobes.brdfs.hemisphere_rule`.

    Parameters
    ----------
    lobe_or_fn : Lobe or callable ``p(wi)``
    theta_o : float
        View elevation (rad) whose rule is used.
    width : float, optional

    Returns
    -------
    float
    """
    wi, w = hemisphere_rule(_check_theta(theta_o), width)
    return float(np.sum(lobe_or_fn(wi) * np.where(wi[:, 2] > 0, wi[:, 2], 0.0) * w))


def _find_peak(resid_fn, wi_grid, theta_o):
    vals = resid_fn(wi_grid)
    k = int(np.argmax(vals))
    th0, ph0 = _angles(wi_grid[k])

    def neg(x):
        th, ph = x
        if not (0.0 <= th < np.pi / 2):
            return 1e300
        return -float(resid_fn(direction_from_angles(th, ph)[None, :])[0])

    res = optimize.minimize(neg, [th0, ph0], method="Nelder-Mead",
                            options=dict(xatol=1e-7, fatol=1e-12, maxiter=400,
                                         initial_simplex=[[th0, ph0], [th0 + 0.003, ph0], [th0, ph0 + 0.003]]))
    th, ph = res.x if -res.fun >= vals[k] else (th0, ph0)
    return direction_from_angles(th, ph), float(max(-res.fun, vals[k]))


#: a peak this close to the horizon (rad) is checked for a singularity there (Ward's 1/√cos θi at large α)
_HORIZON_MARGIN = 1e-3


def _horizon_error(resid_fn, theta_o, peak) -> IBLError | None:
    """An error if the peak sits at the horizon because the slice is unbounded there, else None.

    A bounded grazing peak (e.g. GGX Cook–Torrance at θo = 75°, whose maximum is on the horizon but finite) is
    fitted as usual.  Unbounded: the value grows by more than 3× from 1e-3 to 1e-6 rad above the horizon along the
    peak's azimuth (a 1/√cos θi singularity grows √1000 ≈ 32×; a bounded smooth slice changes by ≈ 1e-3).
    """
    th, ph = _angles(peak)
    if th < np.pi / 2 - _HORIZON_MARGIN:
        return None
    v = resid_fn(np.stack([direction_from_angles(np.pi / 2 - e, ph) for e in (1e-3, 1e-6)]))
    if not (v[1] > 3.0 * v[0]):
        return None
    return IBLError(f"the BRDF slice at theta_o = {np.degrees(theta_o):.2f} deg peaks at the horizon, where it is "
                    f"unbounded ({v[0]:.3g} at 1e-3 rad above it, {v[1]:.3g} at 1e-6 rad; e.g. Ward's "
                    "1/sqrt(cos theta_i) at large alpha), so no radially symmetric lobe fits it; use a smaller "
                    "roughness, a smaller theta_o or a BRDF with a masking term")


def _profiles(resid_fn, peak, gamma, n_phi):
    u, v = _frame(peak)
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    d = (np.cos(gamma)[:, None, None] * peak
         + np.sin(gamma)[:, None, None] * (np.cos(phi)[None, :, None] * u + np.sin(phi)[None, :, None] * v))
    vals = resid_fn(d.reshape(-1, 3)).reshape(len(gamma), n_phi)
    above = d[..., 2] > 0
    return vals, above


def _masked_mean(vals, above):
    cnt = above.sum(axis=1)
    s = np.where(above, vals, 0.0).sum(axis=1)
    return np.where(cnt > 0, s / np.maximum(cnt, 1), 0.0)


def _masked_min(vals, above):
    m = np.where(above, vals, np.inf).min(axis=1)
    return np.where(np.isfinite(m), m, 0.0)


def fit_single_lobe(brdf, theta_o, *, n_gamma: int = 256, n_phi: int = 64, width: float = 0.01,
                    rescale: bool = True) -> SliceFit:
    """Single radially symmetric lobe at elevation θo (Sec. 3.1): peak, mean profile, energy rescale.

    Parameters
    ----------
    brdf : callable ``f(wi, wo)``
        e.g. :func:`ibl_ref.lobes.brdfs.get_brdf`.
    theta_o : float
        View elevation (rad), ``0 ≤ θo < π/2``; ``θo = n·r`` angle.
    n_gamma, n_phi : int
        Profile sampling (module doc).
    width : float
        Finest panel of the hemisphere rule (rad).
    rescale : bool
        Apply the energy rescale (paper: yes).

    Returns
    -------
    SliceFit
        One :class:`Lobe`; with ``rescale`` its energy equals the slice's albedo.

    Raises
    ------
    IBLError
        θo outside [0, π/2), or a BRDF whose maximum lies at the horizon (unbounded there).

    Examples
    --------
    A Phong BRDF of exponent 20 seen at 30°: the lobe peaks at the mirror direction, its best Phong fit has
    exponent ≈ 20 (glossiness 1 − 1/s ≈ 0.95, Knuth 2014 Eq. 3) and it carries the slice's albedo:

    >>> import numpy as np
    >>> from ibl_ref.lobes.brdfs import get_brdf
    >>> from ibl_ref.lobes.kautz_mccool2000 import fit_single_lobe, lobe_energy
    >>> theta_o = np.radians(30.0)
    >>> fit = fit_single_lobe(get_brdf("phong", s=20.0), theta_o, n_gamma=64, n_phi=16)
    >>> lobe = fit.lobes[0]
    >>> abs(lobe.theta_off) < 1e-5, round(lobe.phong_exponent, 1), round(lobe.glossiness, 2)
    (True, 19.9, 0.95)
    >>> round(lobe_energy(lobe, theta_o) / fit.albedo, 12)
    1.0
    """
    t = _check_theta(theta_o)
    wo = view_direction(t)
    wi_grid, w = hemisphere_rule(t, width)
    f_grid = brdf(wi_grid, wo)
    gamma = gamma_nodes(n_gamma)

    def f_fn(wi):
        return np.where(wi[..., 2] > 0, brdf(wi, wo), 0.0)

    peak, _ = _find_peak(f_fn, wi_grid, t)
    err = _horizon_error(f_fn, t, peak)
    if err is not None:
        raise err
    vals, above = _profiles(f_fn, peak, gamma, n_phi)
    prof = _masked_mean(vals, above)
    alb = float(np.sum(f_grid * wi_grid[:, 2] * w))
    lobe0 = Lobe(t, peak, gamma, prof, 1.0, "mean")
    e0 = float(np.sum(lobe0(wi_grid) * wi_grid[:, 2] * w))
    scale = alb / e0 if (rescale and e0 > 0) else 1.0
    lobe = Lobe(t, peak, gamma, prof * scale, scale, "mean")
    err2 = float(np.sum(w * (f_grid - lobe(wi_grid)) ** 2))
    return SliceFit(t, [lobe], alb, [err2], float(np.sum(w * f_grid**2)))


def fit_multi_lobe(brdf, theta_o, n_lobes: int = 4, *, n_gamma: int = 256, n_phi: int = 64,
                   width: float = 0.01, stop_rel: float = 1e-3, rescale: bool = False) -> SliceFit:
    """Greedy multi-lobe fit at elevation θo (Sec. 3.3): peak of the residual, minimum profile, subtract.

    Parameters
    ----------
    brdf : callable ``f(wi, wo)``
    theta_o : float
        View elevation (rad), in [0, π/2).
    n_lobes : int
        Largest number of lobes (≥ 1).
    n_gamma, n_phi, width
        As :func:`fit_single_lobe`.
    stop_rel : float
        Relative residual maximum below which no further lobe is fitted.
    rescale : bool
        Scale the lobe sum to the slice's albedo (below; not in the paper).

    Returns
    -------
    SliceFit

    Raises
    ------
    IBLError
        θo outside [0, π/2), ``n_lobes < 1``, or a first residual maximum at the horizon.

    Notes
    -----
    Stops early when the residual's maximum falls below ``stop_rel`` × the slice's maximum (a residual made of
    profile-interpolation noise is not fitted), or lies at the horizon (an unbounded BRDF such as Ward at large α;
    raises :class:`~ibl_ref.errors.IBLError` if that happens for the first lobe, as :func:`fit_single_lobe` does).  ``err2_after[k]`` is the squared error after ``k+1`` lobes.

    ``rescale`` (not in the paper, default off): Sec. 3.3 keeps the minimum-profile lobes as they are, so the
    energy of the residual they leave is lost (for Ward α = 0.04 about 11 % of the albedo over the teapot,
    ``ibl-ref experiment km00-render``).  With ``rescale=True`` every lobe is scaled by the single factor
    ``albedo / Σ_j ∫ p_j cos θi dω`` (the Sec. 3.1 energy rescale applied to the lobe sum; ``Lobe.scale``),
    so that the fit's directional albedo equals the BRDF's; ``err2_after`` is then that of the rescaled lobes.
    """
    t = _check_theta(theta_o)
    if int(n_lobes) < 1:
        raise IBLError(f"n_lobes must be >= 1, got {n_lobes}")
    wo = view_direction(t)
    wi_grid, w = hemisphere_rule(t, width)
    f_grid = brdf(wi_grid, wo)
    gamma = gamma_nodes(n_gamma)
    lobes: list[Lobe] = []

    def resid_fn(wi):
        out = np.where(wi[..., 2] > 0, brdf(wi, wo), 0.0)
        for lb in lobes:
            out = out - lb(wi)
        return np.where(wi[..., 2] > 0, out, 0.0)

    err2 = []
    for _ in range(int(n_lobes)):
        r_grid = resid_fn(wi_grid)
        if not np.any(r_grid > stop_rel * max(float(f_grid.max()), 1e-300)):
            break
        peak, _ = _find_peak(resid_fn, wi_grid, t)
        err = _horizon_error(resid_fn, t, peak)
        if err is not None:
            if not lobes:
                raise err
            break  # the residual's maximum is the horizon singularity: keep the lobes fitted so far
        vals, above = _profiles(resid_fn, peak, gamma, n_phi)
        prof = np.maximum(_masked_min(vals, above), 0.0)
        if prof[0] <= 0:
            break
        lobes.append(Lobe(t, peak, gamma, prof, 1.0, "min"))
        err2.append(float(np.sum(w * (f_grid - sum(lb(wi_grid) for lb in lobes)) ** 2)))
    alb = float(np.sum(f_grid * wi_grid[:, 2] * w))
    if rescale and lobes:
        e0 = float(np.sum(sum(lb(wi_grid) for lb in lobes) * wi_grid[:, 2] * w))
        if e0 > 0:
            k = alb / e0
            lobes = [Lobe(t, lb.peak, gamma, lb.profile * k, k, "min") for lb in lobes]
            err2 = [float(np.sum(w * (f_grid - sum(lb(wi_grid) for lb in lobes[: j + 1])) ** 2))
                    for j in range(len(lobes))]
    return SliceFit(t, lobes, alb, err2, float(np.sum(w * f_grid**2)))


def fit_single_2d_lobe(brdf, theta_os, *, n_gamma: int = 256, n_phi: int = 64, width: float = 0.01):
    """Single 2-D lobe with weight k(θo) (Sec. 3.2): ``f ≈ k(θo) p(γ)``.

    Parameters
    ----------
    brdf : callable ``f(wi, wo)``
    theta_os : sequence of float
        View elevations (rad), each in [0, π/2).
    n_gamma, n_phi, width
        As :func:`fit_single_lobe`.

    Returns
    -------
    slices : list of SliceFit
        One lobe each, profile ``k(θo)·p̄``.
    p_bar : ndarray, shape (n_gamma,)
        The shared unit-peak profile on :func:`gamma_nodes`.
    k : ndarray, shape (len(theta_os),)
        The weights (albedo match).

    Raises
    ------
    IBLError
        A BRDF that is zero at every elevation, or as :func:`fit_single_lobe`.
    """
    singles = [fit_single_lobe(brdf, t, n_gamma=n_gamma, n_phi=n_phi, width=width, rescale=False)
               for t in theta_os]
    shapes = [s.lobes[0].profile / s.lobes[0].profile[0] for s in singles if s.lobes[0].profile[0] > 0]
    if not shapes:
        raise IBLError("BRDF is zero at every sampled elevation")
    p_bar = np.mean(shapes, axis=0)
    gamma = gamma_nodes(n_gamma)
    out, ks = [], []
    for s in singles:
        t = s.theta_o
        wi_grid, w = hemisphere_rule(t, width)
        f_grid = brdf(wi_grid, view_direction(t))
        base = Lobe(t, s.lobes[0].peak, gamma, p_bar, 1.0, "2d")
        e = float(np.sum(base(wi_grid) * wi_grid[:, 2] * w))
        k = s.albedo / e if e > 0 else 0.0
        lb = Lobe(t, s.lobes[0].peak, gamma, p_bar * k, k, "2d")
        ks.append(k)
        out.append(SliceFit(t, [lb], s.albedo, [float(np.sum(w * (f_grid - lb(wi_grid)) ** 2))], s.f2))
    return out, p_bar, np.array(ks)


def track_lobes(slices) -> list[list[int]]:
    """Consistent lobe ordering across elevations (Fig. 5): for consecutive elevations, assign lobes by minimum
    total distance between peak offsets (``|Δθ_off| + |Δφ_off|·sin θ_peak``, Hungarian algorithm).

    Parameters
    ----------
    slices : sequence of SliceFit
        In order of elevation.

    Returns
    -------
    list of list of int
        For each slice, the track id of each of its lobes (new ids for unmatched lobes).
    """
    ids: list[list[int]] = []
    next_id = 0
    prev = None
    for sl in slices:
        cur = sl.lobes
        if prev is None or not prev or not cur:
            tid = list(range(next_id, next_id + len(cur)))
            next_id += len(cur)
        else:
            pl, pid = prev
            C = np.array([[abs(a.theta_off - b.theta_off)
                           + abs(np.angle(np.exp(1j * (a.phi_off - b.phi_off)))) * np.sin(a.theta_o + a.theta_off)
                           for b in cur] for a in pl])
            ri, ci = optimize.linear_sum_assignment(C)
            tid = [-1] * len(cur)
            for r, c in zip(ri, ci):
                tid[c] = pid[r]
            for j in range(len(cur)):
                if tid[j] < 0:
                    tid[j] = next_id
                    next_id += 1
        ids.append(tid)
        prev = (cur, tid)
    return ids


def slice_rel_rms(slices, n_lobes=None) -> np.ndarray:
    """Per-slice relative RMS ``sqrt(err²/Σ w f²)`` after ``n_lobes`` lobes.

    Parameters
    ----------
    slices : sequence of SliceFit
    n_lobes : int, optional
        All lobes if None; a slice with fewer uses its last value.

    Returns
    -------
    ndarray, float64, shape (len(slices),)
    """
    out = []
    for s in slices:
        if not s.err2_after:
            out.append(1.0 if s.f2 > 0 else 0.0)
            continue
        k = len(s.err2_after) if n_lobes is None else min(int(n_lobes), len(s.err2_after))
        out.append(float(np.sqrt(s.err2_after[k - 1] / s.f2)) if s.f2 > 0 else 0.0)
    return np.array(out)


def rms_error(slices, n_lobes=None) -> float:
    """Relative RMS ``sqrt(Σ err² / Σ f²)`` over all slices (the analogue of the paper's Fig. 7).

    Parameters
    ----------
    slices : sequence of SliceFit
    n_lobes : int, optional
        All lobes if None; a slice that stopped with fewer lobes uses its last value.

    Returns
    -------
    float
    """
    num = den = 0.0
    for s in slices:
        if not s.err2_after:
            num += s.f2
        else:
            k = len(s.err2_after) if n_lobes is None else min(int(n_lobes), len(s.err2_after))
            num += s.err2_after[k - 1]
        den += s.f2
    return float(np.sqrt(num / den)) if den > 0 else 0.0
