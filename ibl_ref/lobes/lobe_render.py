"""Kautz & McCool (2000) shading by one method per call — the lobe side of ``ibl-ref km00-render``.

:func:`shade_single_method` shades given normals and view vectors with an analytic BRDF (:mod:`ibl_ref.lobes.brdfs`)
by one of :data:`SINGLE_METHODS`, all from :mod:`ibl_ref.lobes.prefiltered_lobes`: ``reference`` (per-pixel exact
filtering Σ_j L_j f(ω_j, wo) max(n·ω_j, 0) Ω_j with per-pixel supersampling, :func:`reference_supersample`),
``lobes`` (greedy multi-lobe fit in 3D maps, KM2000 Sec. 5.3), ``single`` (one lobe per elevation, Sec. 5.1),
``2d`` (one shared 2D lobe × k(θo), Sec. 5.2) and ``pyramid`` (the lobes' Phong fits looked up in a Phong
prefilter, the sqrt-cos pyramid of Knuth et al. 2014, given by the caller).  View elevations θo are sampled in
[0°, :data:`THETA_MAX_DEG`]; no visibility (KM2000 has none).  The teapot render around it is
:func:`ibl_ref.rendering.km00_render.render_single_method`; the experiment ``ibl-ref experiment km00-render``
(:mod:`ibl_ref.experiments.km00_render`) compares all of them.
"""

from __future__ import annotations

import numpy as np
from . import brdfs as B
from . import kautz_mccool2000 as km
from . import km00_reference
from . import prefiltered_lobes as pl
from ..environment.validated import as_environment
from ..errors import IBLError
from ..progress import step
from .kautz_mccool2000 import gamma_nodes
from .profile_convolution import auto_supersample

__all__ = ["THETA_MAX_DEG", "MIN_SUBTEXELS_PER_HWHM", "SINGLE_METHODS", "reference_supersample", "check_single_method",
           "check_resolvable", "shade_single_method"]

#: largest sampled view elevation θo (degrees); pixels beyond use the lobes of θmax
THETA_MAX_DEG = 80.0
#: smallest lobe half width, in sub-texels of the environment at the supersampling cap, that a method accepts
#: (:func:`check_resolvable`)
MIN_SUBTEXELS_PER_HWHM = 0.25

SINGLE_METHODS = ("reference", "lobes", "single", "2d", "pyramid")


def reference_supersample(f, env_size: int, n, wo, samples_per_hwhm: float, max_supersample: int) -> np.ndarray:
    """Per-sample source supersampling k of the per-pixel reference: the BRDF slice's narrowest half width at the
    sample's θo (:func:`~ibl_ref.lobes.prefiltered_lobes.brdf_min_hwhm`, tabulated every 0.5°, the smaller of the two
    bracketing entries) spans ``samples_per_hwhm`` sub-texels (:func:`~ibl_ref.lobes.profile_convolution.auto_supersample`),
    capped at ``max_supersample``.  Returns (P,) integers."""

    th = np.arccos(np.clip(np.sum(n * wo, axis=1), 0.0, 1.0))
    th_tab = np.radians(np.arange(0.0, 90.0, 0.5))
    hw_tab = km00_reference.brdf_min_hwhm(f, th_tab)
    i = np.clip((th / np.radians(0.5)).astype(int), 0, th_tab.size - 2)
    hw = np.minimum(hw_tab[i], hw_tab[i + 1])
    return np.array([auto_supersample(int(env_size), h, float(samples_per_hwhm), int(max_supersample))
                     for h in hw], dtype=np.intp)


def check_resolvable(f, method: str, env_size: int, thetas, n_gamma: int = 256, max_supersample: int = 8) -> float:
    """Refuse a BRDF lobe narrower than ``method`` can represent; returns its narrowest half width (rad).

    The narrowest half width at half maximum of the BRDF slices over the sampled elevations
    (:func:`~ibl_ref.lobes.prefiltered_lobes.brdf_min_hwhm`) must span at least :data:`MIN_SUBTEXELS_PER_HWHM`
    of a sub-texel of the environment at the supersampling cap, ≈ (2/N)/k_max rad (the prefiltered maps of
    ``lobes`` / ``single`` / ``2d`` and the per-pixel ``reference``).  Below it the lobe falls between the
    sub-texels: prefiltering a constant map with single-lobe Ward fits at N = 8 (``convolve_profiles``, auto
    supersampling, cap 8) is off by 3.5 % at 0.39 sub-texel per half width, 20 % at 0.2, 50 % at 0.1 and
    black (−100 %) at 0.05 — Ward α = 1e-4 gave an all-black ``lobes`` image with exit 0.  The lobe fits of every
    method but ``reference`` also need it to span two nodes of the profile grid
    (:func:`ibl_ref.lobes.kautz_mccool2000.gamma_nodes`; narrower lobes fit to no lobe at all).  The message names
    the BRDF parameter that sets the width (``alpha=…`` / ``s=…``).
    """

    with np.errstate(all="ignore"):  # a needle-thin lobe overflows the BRDF at its peak: judged below instead
        hws = np.atleast_1d(km00_reference.brdf_min_hwhm(f, thetas))
    hw = float(np.min(hws))
    limits = []
    if method != "pyramid":
        limits.append((MIN_SUBTEXELS_PER_HWHM * (2.0 / env_size) / max_supersample,
                       f"the {env_size}² environment at {max_supersample} x {max_supersample} sub-texels per texel"))
    if method != "reference":
        limits.append((float(gamma_nodes(n_gamma)[2]), f"the lobe fits' profile grid ({n_gamma} nodes)"))
    limit, why = max(limits)
    if not hw >= limit:
        # a slice that is narrow because it is unbounded at the horizon (Ward at large alpha) is a different
        # problem: the fit of that slice names it (and the reference integrates such a peak as it is)
        import warnings

        from .kautz_mccool2000 import fit_single_lobe

        for t in np.atleast_1d(thetas)[hws < limit]:
            try:
                with warnings.catch_warnings(), np.errstate(all="ignore"):
                    warnings.simplefilter("ignore")
                    fit_single_lobe(f, float(t), n_gamma=64, n_phi=16)
            except IBLError:
                if method == "reference":
                    return hw
                raise
        knob = next((k for k in ("alpha", "s") if k in f.params), None)
        what = f"{knob}={f.params[knob]:g}" if knob else "these parameters"
        wider = {"alpha": " (a larger alpha)", "s": " (a smaller s)"}.get(knob, "")
        larger = " or a larger environment" if why.startswith("the ") and "environment" in why else ""
        raise IBLError(f"{f.name} lobe with {what} is too narrow for method={method!r}: its narrowest half width "
                       f"is {hw:.2g} rad, {why} resolves half widths down to {limit:.2g} rad; use a wider "
                       f"lobe{wider}{larger}")
    return hw


def check_single_method(method: str, n_theta) -> None:
    """One-line :class:`~ibl_ref.errors.IBLError` for an unknown method or a bad number of elevations."""

    if method not in SINGLE_METHODS:
        raise IBLError(f"method must be one of {', '.join(SINGLE_METHODS)}, got {method!r}")
    if isinstance(n_theta, bool) or not isinstance(n_theta, (int, np.integer)) or n_theta < 2:
        raise IBLError(f"n_theta must be an integer >= 2 (elevations from 0 to {THETA_MAX_DEG:g} deg), got {n_theta!r}")


def shade_single_method(method: str, env: np.ndarray, n, wo, *, brdf: str = "ward", brdf_params: dict | None = None,
                        n_lobes: int = 3, n_theta: int = 16, n_gamma: int = 256, n_phi: int = 64,
                        map_supersample="auto", map_out_size=None, tail_rtol: float = 1e-6, cos_mode: str = "mirror",
                        energy: str = "phong", ref_samples_per_hwhm: float = 3.0, ref_max_supersample: int = 16,
                        rescale_lobes: bool = False, prefilter=None, progress: bool = False):
    """Outgoing radiance (P, C) at unit normals ``n`` (P, 3) and view vectors ``wo`` (P, 3) by one method, and an
    info dict.  ``method`` ∈ :data:`SINGLE_METHODS` (``lobes``: ``n_lobes`` greedy lobes in 3D maps, ``pyramid``:
    the same lobes via their Phong fits in ``prefilter``, a Phong prefilter of ``env``
    (:class:`ibl_ref.prefilter.interface.Prefilter`); ``rescale_lobes``: the greedy lobes with one energy factor
    per elevation, :func:`ibl_ref.lobes.kautz_mccool2000.fit_multi_lobe` ``rescale=True``).  θo sampled in
    [0°, 80°]."""

    check_single_method(method, n_theta)
    env = as_environment(env, "environment cube map")  # checked once here; the maps and the reference trust it
    if method == "pyramid" and prefilter is None:
        raise IBLError("method 'pyramid' looks the lobes up in a Phong prefilter of env: pass prefilter= "
                       "(e.g. ibl_ref.prefilter.build_prefilter(env, 'pyramid', kernel='sqrtcos'))")
    with np.errstate(all="ignore"):  # a needle-thin lobe overflows at its peak: check_resolvable refuses it below
        f = B.get_brdf(brdf, **(brdf_params or {}))
    thetas = np.radians(np.linspace(0.0, THETA_MAX_DEG, int(n_theta)))
    check_resolvable(f, method, int(env.shape[1]), thetas, n_gamma=int(n_gamma),
                     max_supersample=ref_max_supersample if method == "reference" else 8)
    fk = dict(n_gamma=int(n_gamma), n_phi=int(n_phi))
    ck = dict(supersample=map_supersample, tail_rtol=float(tail_rtol), progress=progress,
              out_size=int(map_out_size or env.shape[1]))
    info: dict = dict(method=method, brdf=brdf, brdf_params=dict(brdf_params or {}))
    if method == "reference":
        # the cone cut and its bound cover Ward's specular term only: with a diffuse term gather everything
        cut = km00_reference.ward_cut_angle(f.params.get("alpha", 0.04), 1e-12) if brdf == "ward" and not f.params.get("kd", 0.0) else None
        kpix = reference_supersample(f, env.shape[1], n, wo, ref_samples_per_hwhm, ref_max_supersample)
        vals = km00_reference.render_reference(env, n, wo, f, supersample=kpix, cut_angle=cut, progress=progress)
        info.update(cut_angle_deg=None if cut is None else float(np.degrees(cut)), max_supersample=int(kpix.max()))
    elif method in ("lobes", "pyramid"):
        with step(f"{n_lobes}-lobe fits at {len(thetas)} elevations", enabled=progress):
            multi = [km.fit_multi_lobe(f, t, int(n_lobes), rescale=bool(rescale_lobes), **fk) for t in thetas]
        ls = pl.build_lobe_set(multi, km.track_lobes(multi), cube=env if method == "lobes" else None,
                               **(ck if method == "lobes" else {}))
        if method == "lobes":
            vals = pl.shade_lobes(ls, n, wo, cos_mode=cos_mode)
        else:
            vals = pl.shade_pyramid(ls, prefilter, n, wo, energy=energy, cos_mode=cos_mode)
        info.update(n_tracks=ls.n_tracks, rel_rms_brdf=km.rms_error(multi, int(n_lobes)))
    elif method == "single":
        single = [km.fit_single_lobe(f, t, **fk) for t in thetas]
        vals = pl.shade_lobes(pl.build_lobe_set(single, None, cube=env, **ck), n, wo, cos_mode=cos_mode)
        info.update(rel_rms_brdf=km.rms_error(single))
    else:
        s2d, p_bar, kw = km.fit_single_2d_lobe(f, thetas, **fk)
        vals = pl.shade_2d(pl.build_2d_lobe(s2d, p_bar, kw, cube=env, **ck), n, wo, cos_mode=cos_mode)
        info.update(rel_rms_brdf=km.rms_error(s2d))
    return vals, info
