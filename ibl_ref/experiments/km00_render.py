"""Kautz & McCool (2000) Figs. 9–18 analogue: the glossy teapot rendered with fitted lobes vs per-pixel exact filtering.

Material: Ward isotropic ``kd = 0, ks = 0.8, α = 0.04`` (the paper's Fig. 7 / 15–18 BRDF).  Environment ``sky_sun``
(smooth sky + 1e5 sun).  Camera and teapot as in :mod:`ibl_ref.experiments.fig6` (:func:`ibl_ref.rendering.scenes.default_camera`).
**No visibility** in any method (KM2000 has none): every pixel integrates the whole environment hemisphere.

Methods (:mod:`ibl_ref.lobes.prefiltered_lobes`):

* ``reference`` — per-pixel exact filtering ``Σ_j L_j f(ω_j, wo) max(n·ω_j, 0) Ω_j`` over the environment texels
  (piecewise constant), each split into k×k sub-texels with k per pixel chosen so that the BRDF slice's narrowest
  half width (:func:`~ibl_ref.lobes.prefiltered_lobes.brdf_min_hwhm`, ≈ 0.7° at θo = 80° for α = 0.04) spans
  ``ref_samples_per_hwhm`` sub-texels (:func:`~ibl_ref.lobes.profile_convolution.auto_supersample`), times a multiplier
  (``ref_k_multipliers``, 1/2/4; the last is the reference), capped at ``ref_max_supersample``; gathered in the cone
  γc = :func:`~ibl_ref.lobes.prefiltered_lobes.ward_cut_angle` (ε = 1e-12) around r; the neglected radiance is bounded
  (``meta.info.reference.neglected_bound_max``).  Successive multipliers show the quadrature convergence.
  The 3D maps use the same rule per lobe profile (``map_supersample="auto"``, 1.5 sub-texels per profile HWHM).
* ``lobes3`` — the greedy multi-lobe fit (≤ 3 lobes, tracked across elevations), one 3D map per track (Sec. 5.3),
  cosine factor n·r (Eq. 2); ``lobes3_peakcos`` the same maps with the factor n·peak_j; ``lobes3_rescaled`` the
  same lobes with one energy factor per elevation so that their albedo is the BRDF's (not in KM2000, whose greedy
  minimum-profile lobes leave the residual's energy out; :func:`ibl_ref.lobes.kautz_mccool2000.fit_multi_lobe`
  ``rescale=True``, maps scaled by :meth:`~ibl_ref.lobes.prefiltered_lobes.LobeSet.scaled`).
* ``single`` — one mean-profile lobe per elevation (Sec. 3.1 / 5.1); ``single2d`` — one shared 2-D lobe × k(θo)
  (Sec. 3.2 / 5.2).
* ``pyramid3`` — Knuth et al. 2014 extension: each of the 3 lobes replaced by its Phong fit ``P cos^s``, looked up in
  the single sqrt-cos pyramid at g = 1 − 1/s, weight ``P·2π/(s+1)``; ``pyramid3_profile`` weight ``∫ p dω``;
  ``pyramid1`` the single-lobe fit through the pyramid (separates the pyramid's error from the greedy fit's).

Elevations θo: ``n_theta`` values linear in [0°, θmax = 80°] (as :mod:`ibl_ref.experiments.km00`); pixels with
θo > θmax use the θmax lobes (clamped; counted in ``meta.pixels_clamped``) and the metrics are also given over the
pixels with θo ≤ θmax (``*_in_range`` columns).

Files: ``km00_render_metrics.csv`` (per method: rmse, rel_l1, rel_max vs the reference over covered pixels, and the
same restricted to θo ≤ θmax; time_s), ``km00_render_reference_convergence.csv`` (rel_l1 between successive
reference supersampling factors), ``km00_render_meta.json`` (settings, definitions/units, timings, fit summary, cut
angles, bounds), ``km00_render_<method>.exr`` (linear radiance), ``km00_render_mask.exr`` (coverage 1/0) and
``km00_render_theta.exr`` (θo in degrees).  Plot: ``km00_render.png`` (tone-mapped images, one exposure, and relative
error maps).  Timings are wall-clock on the 2-core machine that runs it (they vary with load).
"""

from __future__ import annotations

import json

import time
from pathlib import Path

import numpy as np

from ..atomic import read_csv, write_csv, write_json
from ..lobes.lobe_render import THETA_MAX_DEG, reference_supersample
from ..rendering.km00_render import teapot_gbuffer as _gbuffer
from . import params_from_settings, settings_with, power_of_two
from ..figures import pyplot
from ..figures import save_figure
from ..lobes import brdfs as B
from ..lobes import kautz_mccool2000 as km
from ..lobes import km00_reference
from ..lobes import prefiltered_lobes as pl
from ..lobes.profile_convolution import profile_integral
from ..prefilter.registry import build_prefilter
from ..progress import step
from ..rendering.image_io import read_image_exr
from ..rendering.image_io import write_image_exr
from ..rendering.image_metrics import error_map
from ..rendering.image_metrics import rel_l1
from ..rendering.image_metrics import rel_max
from ..rendering.image_metrics import rmse
from ..rendering.scenes import default_camera
from ..rendering.tonemap import auto_exposure
from ..rendering.tonemap import backdrop
from ..rendering.tonemap import exposure_srgb
from ..rendering.tonemap import with_backdrop
from ..synthetic.synthetic_envs import make_env
from ..synthetic.synthetic_meshes import make_mesh

NAME = "km00-render"
DESCRIPTION = ("Kautz & McCool 2000 renders: Ward teapot by per-pixel exact filtering vs 3 lobes / single lobe / "
               "single 2D lobe / pyramid lookup of the lobes' Phong fits")
PAPER = "Kautz & McCool 2000, Figs. 9-18 analogue (Ward teapot: per-pixel exact vs fitted lobes), Sec. 3 and 5"
IN_QUICK_REPRODUCE = True
RUNTIME = {"quick": "16 s (load 0.3)", "full": "12 min 49 s (load 12; 6 min 2 s CPU)"}
OUTPUTS = ("km00_render_metrics.csv", "km00_render_reference_convergence.csv", "km00_render_meta.json",
           "km00_render_<method>.exr", "km00_render_mask.exr", "km00_render_theta.exr", "km00_render_background.exr",
           "km00_render.png")

METHODS = ("reference", "lobes3", "lobes3_peakcos", "lobes3_rescaled", "single", "single2d", "pyramid3",
           "pyramid3_profile",
           "pyramid1")
LABELS = {"reference": "per-pixel exact", "lobes3": "3 lobes (3D maps)", "lobes3_peakcos": "3 lobes, n·peak",
          "lobes3_rescaled": "3 lobes, energy rescaled",
          "single": "single lobe", "single2d": "single 2D lobe", "pyramid3": "3 lobes via pyramid",
          "pyramid3_profile": "pyramid, ∫p weight", "pyramid1": "single lobe via pyramid"}
BRDF = ("ward", dict(kd=0.0, ks=0.8, alpha=0.04))


def settings(quick: bool) -> dict:
    if quick:
        return dict(size=48, env="sky_sun", env_size=32, n_theta=6, n_lobes=3, n_gamma=128, n_phi=32,
                    map_supersample="auto", map_out_size=32, tail_rtol=1e-6,
                    ref_samples_per_hwhm=1.0, ref_k_multipliers=[1, 2], ref_max_supersample=16, ref_eps=1e-12)
    return dict(size=256, env="sky_sun", env_size=64, n_theta=16, n_lobes=3, n_gamma=256, n_phi=64,
                map_supersample="auto", map_out_size=64, tail_rtol=1e-6,
                ref_samples_per_hwhm=1.0, ref_k_multipliers=[1, 2, 4], ref_max_supersample=16, ref_eps=1e-12)


PARAMS = params_from_settings(settings, {
    "env": "synthetic environment", "n_theta": "sampled view elevations", "n_lobes": "greedy lobes",
    "n_gamma": "BRDF samples in the polar angle", "n_phi": "BRDF samples in azimuth",
    "map_supersample": "3D-map supersampling ('auto' or an integer)", "map_out_size": "3D-map face size",
    "tail_rtol": "profile tail cut", "ref_samples_per_hwhm": "reference sub-texels per BRDF half width",
    "ref_k_multipliers": "reference supersampling multipliers (last = reference)",
    "ref_max_supersample": "reference supersampling cap", "ref_eps": "reference cone cut (epsilon)"},
    checks={"env_size": power_of_two})


def render_all(st: dict, env: np.ndarray, progress: bool = False) -> dict:
    """Fit, prefilter and render every method for settings ``st``; returns images, mask, θo map, timings, info."""

    T: dict = {}
    t0 = time.perf_counter()
    gb = _gbuffer(int(st["size"]))
    T["raster"] = time.perf_counter() - t0
    m = gb.mask
    n, wo = gb.normal[m], gb.view[m]
    f = B.get_brdf(BRDF[0], **BRDF[1])
    thetas = np.radians(np.linspace(0.0, THETA_MAX_DEG, int(st["n_theta"])))
    fk = dict(n_gamma=int(st["n_gamma"]), n_phi=int(st["n_phi"]))
    ck = dict(supersample=st["map_supersample"], tail_rtol=float(st["tail_rtol"]), progress=progress,
              out_size=int(st.get("map_out_size", env.shape[1])))

    t0 = time.perf_counter()

    with step(f"km00-render: lobe fits at {len(thetas)} elevations", enabled=progress):
        multi = [km.fit_multi_lobe(f, t, int(st["n_lobes"]), **fk) for t in thetas]
        tracks = km.track_lobes(multi)
        # the same greedy lobes with one energy factor per elevation (fit_multi_lobe rescale=True; not in KM2000)
        k_rescale = [s.lobes[0].scale if s.lobes else 1.0
                     for s in (km.fit_multi_lobe(f, t, int(st["n_lobes"]), rescale=True, **fk) for t in thetas)]
        single = [km.fit_single_lobe(f, t, **fk) for t in thetas]
        s2d, p_bar, kw = km.fit_single_2d_lobe(f, thetas, **fk)
    T["fit"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    L3 = pl.build_lobe_set(multi, tracks, cube=env, **ck)
    T["maps_lobes3"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    L1 = pl.build_lobe_set(single, None, cube=env, **ck)
    T["maps_single"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    L2 = pl.build_2d_lobe(s2d, p_bar, kw, cube=env, **ck)
    T["maps_single2d"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pyr = build_prefilter(env, "pyramid", kernel="sqrtcos")
    T["pyramid_build"] = time.perf_counter() - t0

    vals: dict = {}
    t0 = time.perf_counter()
    vals["lobes3"] = pl.shade_lobes(L3, n, wo)
    T["shade_lobes3"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    vals["lobes3_peakcos"] = pl.shade_lobes(L3, n, wo, cos_mode="peak")
    T["shade_lobes3_peakcos"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    L3r = L3.scaled(k_rescale)  # convolution is linear: the 3D maps scale with the profiles
    vals["lobes3_rescaled"] = pl.shade_lobes(L3r, n, wo)
    T["shade_lobes3_rescaled"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    vals["single"] = pl.shade_lobes(L1, n, wo)
    T["shade_single"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    vals["single2d"] = pl.shade_2d(L2, n, wo)
    T["shade_single2d"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    vals["pyramid3"] = pl.shade_pyramid(L3, pyr, n, wo, energy="phong")
    T["shade_pyramid3"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    vals["pyramid3_profile"] = pl.shade_pyramid(L3, pyr, n, wo, energy="profile")
    T["shade_pyramid3_profile"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    vals["pyramid1"] = pl.shade_pyramid(L1, pyr, n, wo, energy="phong")
    T["shade_pyramid1"] = time.perf_counter() - t0

    # reference with a supersampling sweep (the last one is the reference): per pixel, k sub-texels per texel edge
    # so that the slice's narrowest half width (brdf_min_hwhm at the pixel's θo) spans ≥ spw sub-texels, × multiplier
    alpha, ks = BRDF[1]["alpha"], BRDF[1]["ks"]
    gc = km00_reference.ward_cut_angle(alpha, float(st["ref_eps"]))
    cos_o = np.sum(n * wo, axis=1)
    t0 = time.perf_counter()
    k_base = reference_supersample(f, env.shape[1], n, wo, st["ref_samples_per_hwhm"], st["ref_max_supersample"])
    T["reference_hwhm_table"] = time.perf_counter() - t0
    refs, k_counts = [], []
    for mult in st["ref_k_multipliers"]:
        kpix = np.minimum(k_base * int(mult), int(st["ref_max_supersample"]))
        t0 = time.perf_counter()
        refs.append(km00_reference.render_reference(env, n, wo, f, supersample=kpix, cut_angle=gc, progress=progress))
        T[f"reference_x{mult}"] = time.perf_counter() - t0
        u, c = np.unique(kpix[cos_o > 0], return_counts=True)
        k_counts.append({int(a): int(b) for a, b in zip(u, c)})
    vals["reference"] = refs[-1]
    bound = km00_reference.ward_neglected_bound(alpha, ks, gc, cos_o[cos_o > 0], float(env.max()))

    # the same methods under a constant environment L ≡ 1 (no map/pyramid resolution error): the reference is the
    # albedo a(θo) (brdfs.albedo, Gauss–Legendre), each method gives cos-factor × its lobe weights — isolates the
    # BRDF-approximation (energy) error from the environment-discretisation error
    t0 = time.perf_counter()
    energy = _constant_env_images(L3, L3r, L1, L2, f, n, wo)
    T["constant_env_pass"] = time.perf_counter() - t0

    H, W = m.shape
    C = env.shape[-1]

    def img(v):
        out = np.zeros((H * W, C))
        out[m.reshape(-1)] = v
        return out.reshape(H, W, C)

    theta = np.zeros((H, W))
    theta[m] = np.degrees(np.arccos(np.clip(cos_o, -1.0, 1.0)))
    info = dict(
        n_pixels=int(m.sum()), pixels_clamped=int((theta[m] > THETA_MAX_DEG).sum()),
        pixels_backfacing=int((cos_o <= 0).sum()),
        theta_o_deg=np.degrees(thetas).tolist(),
        reference=dict(cut_angle_deg=float(np.degrees(gc)), eps=float(st["ref_eps"]),
                       neglected_bound_max=float(bound.max()) if bound.size else 0.0,
                       neglected_bound_median=float(np.median(bound)) if bound.size else 0.0,
                       samples_per_hwhm=float(st["ref_samples_per_hwhm"]),
                       k_multiplier=int(st["ref_k_multipliers"][-1]),
                       pixels_per_supersample=k_counts, unresolved_note=(
                           f"pixels whose k hit ref_max_supersample={st['ref_max_supersample']} have fewer "
                           "sub-texels per half width than asked (grazing)")),
        lobes3_rescaled=dict(energy_factor=np.round(k_rescale, 6).tolist()),
        lobes3=dict(n_tracks=L3.n_tracks, theta_off_deg=np.degrees(L3.theta_off).round(4).tolist(),
                    phi_off_deg=np.degrees(L3.phi_off).round(3).tolist(), phong_s=L3.phong_s.round(2).tolist(),
                    phong_P=L3.phong_P.round(4).tolist(), integral_sr=L3.integral.round(6).tolist(),
                    cut_angle_deg=np.degrees(L3.cut_angle).round(3).tolist(),
                    tail_fraction_max=float(L3.tail_fraction.max()), map_shape=list(L3.maps.shape),
                    map_supersample=L3.supersample.tolist(),
                    track_ids=tracks, rel_rms_brdf=km.rms_error(multi, 3)),
        single=dict(phong_s=L1.phong_s[:, 0].round(2).tolist(), rel_rms_brdf=km.rms_error(single),
                    theta_off_deg=np.degrees(L1.theta_off[:, 0]).round(4).tolist()),
        single2d=dict(k=np.asarray(kw).round(6).tolist(), rel_rms_brdf=km.rms_error(s2d),
                      cut_angle_deg=float(np.degrees(L2.cut_angle))),
    )
    ref_conv = [(int(k), img(r)) for k, r in zip(st["ref_k_multipliers"], refs)]
    return dict(images={k: img(v) for k, v in vals.items()}, mask=m, theta=theta, timings=T, info=info,
                ref_sweep=ref_conv, constant_env={k: img(np.repeat(v, C, axis=1)) for k, v in energy.items()})


def _constant_env_images(L3, L3r, L1, L2, f, n, wo) -> dict:
    """Per-sample radiance of every method for L ≡ 1 (see :func:`render_all`); (P, 1) arrays."""
    import dataclasses


    def const_maps(ls):
        K, J = ls.integral.shape
        maps = np.broadcast_to(ls.integral[:, :, None, None, None, None], (K, J, 6, 2, 2, 1)).copy()
        return dataclasses.replace(ls, maps=maps, _samplers={})

    out = {}
    cos_o = np.sum(n * wo, axis=1)
    th = np.arccos(np.clip(cos_o, 0.0, 1.0))
    th_tab = np.radians(np.arange(0.0, 90.0, 0.5))
    out["reference"] = np.where(cos_o > 0, np.interp(th, th_tab, B.albedo(f, th_tab)), 0.0)[:, None]
    c3 = const_maps(L3)
    out["lobes3"] = pl.shade_lobes(c3, n, wo)
    out["lobes3_peakcos"] = pl.shade_lobes(c3, n, wo, cos_mode="peak")
    out["lobes3_rescaled"] = pl.shade_lobes(const_maps(L3r), n, wo)
    out["single"] = pl.shade_lobes(const_maps(L1), n, wo)
    c2 = dataclasses.replace(L2, map=np.full((6, 2, 2, 1), float(profile_integral(L2.gamma, L2.p_bar))),
                             _sampler=None)
    out["single2d"] = pl.shade_2d(c2, n, wo)
    pyr1 = build_prefilter(np.ones((6, 16, 16, 1)), "pyramid")
    out["pyramid3"] = pl.shade_pyramid(L3, pyr1, n, wo, energy="phong")
    out["pyramid3_profile"] = pl.shade_pyramid(L3, pyr1, n, wo, energy="profile")
    out["pyramid1"] = pl.shade_pyramid(L1, pyr1, n, wo, energy="phong")
    return out


def run(out_dir: Path, quick: bool = False, **params) -> dict:
    return run_with(out_dir, settings_with(__name__, quick, params), quick=quick, progress=True)


def run_with(out_dir: Path, st: dict, quick: bool = False, progress: bool = False) -> dict:
    """:func:`run` with explicit settings (see :func:`settings`)."""

    out_dir = Path(out_dir)
    t_all = time.perf_counter()
    env = make_env(st["env"], n=int(st["env_size"]))
    res = render_all(st, env, progress=progress)
    ims, m, T = res["images"], res["mask"], res["timings"]
    ref = ims["reference"]
    m_in = m & (res["theta"] <= THETA_MAX_DEG)
    rows = []
    time_of = {"reference": T[f"reference_x{st['ref_k_multipliers'][-1]}"],
               "pyramid1": T["pyramid_build"] + T["shade_pyramid1"],
               "lobes3": T["maps_lobes3"] + T["shade_lobes3"],
               "lobes3_peakcos": T["maps_lobes3"] + T["shade_lobes3_peakcos"],
               "lobes3_rescaled": T["maps_lobes3"] + T["shade_lobes3_rescaled"],
               "single": T["maps_single"] + T["shade_single"],
               "single2d": T["maps_single2d"] + T["shade_single2d"],
               "pyramid3": T["pyramid_build"] + T["shade_pyramid3"],
               "pyramid3_profile": T["pyramid_build"] + T["shade_pyramid3_profile"]}
    ce = res["constant_env"]
    for k in METHODS:
        rows.append(dict(method=k, rmse=rmse(ims[k], ref, m), rel_l1=rel_l1(ims[k], ref, m),
                         rel_max=rel_max(ims[k], ref, m), rmse_in_range=rmse(ims[k], ref, m_in),
                         rel_l1_in_range=rel_l1(ims[k], ref, m_in),
                         rel_err_median=float(np.median(error_map(ims[k], ref, m)[m])),
                         rel_err_p95=float(np.percentile(error_map(ims[k], ref, m)[m], 95)),
                         rel_l1_constant_env=rel_l1(ce[k], ce["reference"], m),
                         rel_bias_constant_env=float(ce[k][m].sum() / ce["reference"][m].sum() - 1.0),
                         time_s=round(time_of[k], 3)))
    write_csv(out_dir / "km00_render_metrics.csv", rows,
              ["method", "rmse", "rel_l1", "rel_max", "rmse_in_range", "rel_l1_in_range", "rel_err_median",
               "rel_err_p95", "rel_l1_constant_env",
               "rel_bias_constant_env", "time_s"],
              comment=("errors vs the per-pixel exact reference over covered pixels (radiance units of the "
                       "environment): rmse = sqrt(mean (a-b)^2) over pixels and RGB; rel_l1 = sum|a-b|/sum|b|; "
                       "rel_max = max |Y_a-Y_b|/Y_b (Y = RGB mean, pixels with Y_b > 1e-3 mean); *_in_range: "
                       f"pixels with theta_o <= {THETA_MAX_DEG} deg only; rel_err_median/p95: median / 95th percentile "
                       "over covered pixels of |Y_a-Y_b|/max(Y_b, 1e-3 mean Y_b) (robust to the few sun-highlight "
                       "pixels that dominate rel_l1 and rmse); *_constant_env: the same pixels under L = 1 "
                       "(reference = Ward albedo; isolates the BRDF-approximation energy error; bias = sum a / "
                       "sum ref - 1); time_s: prefilter/pyramid build + "
                       "shading (reference: its render), wall clock (varies with load)"))
    conv = []
    sweep = res["ref_sweep"]
    for (k0, a), (k1, b) in zip(sweep[:-1], sweep[1:]):
        conv.append(dict(k_multiplier_from=k0, k_multiplier_to=k1, rel_l1=rel_l1(a, b, m),
                         rmse=rmse(a, b, m), rel_l1_in_range=rel_l1(a, b, m_in)))
    write_csv(out_dir / "km00_render_reference_convergence.csv", conv,
              ["k_multiplier_from", "k_multiplier_to", "rel_l1", "rmse", "rel_l1_in_range"],
              comment="reference render with per-pixel k x k sub-texels per environment texel, k = multiplier x "
                      "k_base (k_base from the BRDF slice's narrowest half width, ref_samples_per_hwhm; capped at "
                      "ref_max_supersample) vs the next multiplier; the differences shrink ~4x per doubling "
                      "(O(h^2) quadrature) except for capped grazing pixels")
    for k in METHODS:
        write_image_exr(out_dir / f"km00_render_{k}.exr", ims[k])
    write_image_exr(out_dir / "km00_render_mask.exr", m.astype(np.float64))
    write_image_exr(out_dir / "km00_render_theta.exr", res["theta"])

    # display only: the environment behind the teapot (the camera of teapot_gbuffer)
    cam = default_camera([(make_mesh("teapot"), 0)], size=int(st["size"]))
    write_image_exr(out_dir / "km00_render_background.exr", backdrop(env, cam))
    meta = dict(quick=quick, settings=st, brdf=dict(model=BRDF[0], **BRDF[1]), scene="teapot",
                camera="ibl_ref.rendering.scenes.default_camera (as fig6)", visibility="none (KM2000 has no shadows)",
                theta_max_deg=THETA_MAX_DEG, timings_s={k: round(v, 3) for k, v in T.items()},
                total_time_s=round(time.perf_counter() - t_all, 2), info=res["info"],
                definitions=dict(
                    units="radiance in the environment's units (sky ~1, sun 1e5)",
                    rmse="sqrt(mean over covered pixels and RGB of (a - ref)^2)",
                    rel_l1="sum |a - ref| / sum |ref| over covered pixels and RGB",
                    rel_max="max over covered pixels of |Y_a - Y_ref| / Y_ref, Y = RGB mean, Y_ref > 1e-3 mean",
                    lobes_cos="lobes3/single/single2d/pyramid3 use n.r for n.l (KM2000 Eq. 2); lobes3_peakcos n.peak",
                    pyramid_weight="pyramid3: P*2pi/(s+1) of the lobe's Phong fit; pyramid3_profile: integral of p",
                    constant_env="rel_l1_constant_env / rel_bias_constant_env: L = 1, reference = albedo a(theta_o) "
                                 "(brdfs.albedo), methods = cosine factor x lobe weights (no map resolution error)"),
                timing_note="wall clock on the machine that ran it (varies with load)")
    write_json(out_dir / "km00_render_meta.json", meta)
    return dict(metrics={r["method"]: r["rel_l1"] for r in rows}, time_s=meta["total_time_s"])


def plot(out_dir: Path) -> list:

    plt = pyplot()


    out_dir = Path(out_dir)
    ims = {k: read_image_exr(out_dir / f"km00_render_{k}.exr") for k in METHODS}
    mask = read_image_exr(out_dir / "km00_render_mask.exr")[..., 0] > 0.5
    bg_file = out_dir / "km00_render_background.exr"
    bg = read_image_exr(bg_file) if bg_file.exists() else None
    rows = {r["method"]: r for r in read_csv(out_dir / "km00_render_metrics.csv")}
    st = json.loads((out_dir / "km00_render_meta.json").read_text())["settings"]
    stops = auto_exposure(ims["reference"], mask)
    fig, ax = plt.subplots(2, len(METHODS), figsize=(2.3 * len(METHODS), 5.0))
    fig.subplots_adjust(left=0.01, right=0.9, top=0.86, bottom=0.09, wspace=0.05, hspace=0.2)
    im = th_im = None
    for j, k in enumerate(METHODS):
        ax[0, j].imshow(exposure_srgb(ims[k] if bg is None else with_backdrop(ims[k], mask, bg), stops))
        ax[0, j].set_title(LABELS[k], fontsize=8)
        if k == "reference":  # its own error is 0 by definition: show the view elevation the lobes depend on
            th = read_image_exr(out_dir / "km00_render_theta.exr")[..., 0]
            th_im = ax[1, j].imshow(np.where(mask, th, np.nan), cmap="viridis", vmin=0, vmax=90)
            ax[1, j].set_title(f"view elevation θo (lobes fitted up to {THETA_MAX_DEG:g}°)", fontsize=7)
        else:
            e = error_map(ims[k], ims["reference"], mask)
            im = ax[1, j].imshow(np.where(mask, e, np.nan), cmap="magma", vmin=0, vmax=0.5)
            ax[1, j].set_title(f"rel L1 {float(rows[k]['rel_l1']):.3f}, median "
                               f"{float(rows[k]['rel_err_median']):.3f}", fontsize=7)
        for a in ax[:, j]:
            a.set_xticks([])
            a.set_yticks([])
    cax = fig.add_axes([0.915, 0.09, 0.012, 0.33])
    fig.colorbar(im, cax=cax, extend="max", label="|ΔY| / Y_ref (≥ 0.5 at the top)")
    if th_im is not None:  # the θo map's scale, under its panel
        cb = fig.colorbar(th_im, ax=ax[1, 0], orientation="horizontal", fraction=0.06, pad=0.02,
                          ticks=[0, 30, 60, 90])
        cb.ax.tick_params(labelsize=6)
        cb.set_label("θo (deg)", fontsize=7)
    b = BRDF[1]
    fig.suptitle(f"Kautz & McCool 2000 renders: Ward teapot (kd = {b['kd']:g}, ks = {b['ks']:g}, α = {b['alpha']:g}) "
                 f"under {st['env']} ({st['env_size']}² faces), no visibility; {st['size']}² px, one exposure for all; "
                 "errors against the per-pixel exact image", fontsize=9)
    p = out_dir / "km00_render.png"
    save_figure(fig, p, dpi=100)
    return [p]
