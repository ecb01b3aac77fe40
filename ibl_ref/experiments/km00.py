"""Kautz & McCool (2000) lobe fitting: RMS error vs number of lobes (Fig. 7 analogue), fitted lobes per elevation.

BRDFs: Ward isotropic ``kd=0, ks=0.8, α=0.04`` (the paper's Fig. 7/15–18 material) and Cook–Torrance GGX
``α=0.15, F0=0.9`` (a second glossy BRDF).  View elevations θo: ``n_theta`` values linear in [0°, 80°] (Ward's
``1/√cos θi`` makes the slice peak at the horizon beyond ≈ 85°, where a peak-centred lobe is meaningless).

Outputs: ``rms_vs_lobes.csv`` (method ∈ multi/single/single2d, relative RMS over the hemisphere and all θo, see
:func:`ibl_ref.lobes.kautz_mccool2000.rms_error`), ``lobes.csv`` (every fitted lobe: offsets, track id, Phong fit),
``profiles.csv`` (single-lobe mean profile vs the BRDF's in-plane cut through the peak), ``summary.json``.
Rendering the teapot with the fitted BRDF (paper Figs. 15–18) needs the renderer and is not done here.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..progress import track
from ..atomic import read_csv, write_csv, write_json
from . import Param, resolve_params
from ..figures import integer_ticks
from ..figures import pyplot
from ..figures import save_figure
from ..lobes import brdfs as B
from ..lobes import kautz_mccool2000 as km

NAME = "km00"
DESCRIPTION = "Kautz & McCool 2000 greedy lobe fits: RMS error vs number of lobes (Fig. 7), lobes per elevation"
PAPER = "Kautz & McCool 2000, Fig. 7 (RMS error of the greedy lobe fit vs number of lobes), Sec. 4-5"
IN_QUICK_REPRODUCE = True
PARAMS = (
    Param("n_theta", 16, 5, "view elevations in [0, 80] degrees"),
    Param("n_lobes", 8, 5, "maximum number of greedy lobes"),
    Param("n_gamma", 256, 192, "BRDF samples in the polar angle"),
    Param("n_phi", 64, 48, "BRDF samples in azimuth"),
)
RUNTIME = {"quick": "2.3 s (load 0.3)", "full": "58 s (load 10; 19 s CPU)"}
OUTPUTS = ("rms_vs_lobes.csv", "lobes.csv", "profiles.csv", "summary.json", "km00_rms_vs_lobes.png", "km00_lobes.png")

BRDFS = {
    "ward_ks0.8_a0.04": ("ward", dict(kd=0.0, ks=0.8, alpha=0.04)),
    "ggx_a0.15_f0.9": ("cook_torrance", dict(alpha=0.15, f0=0.9, distribution="ggx")),
}


def run(out_dir: Path, quick: bool = False, **params) -> dict:

    out_dir = Path(out_dir)
    p = resolve_params(__name__, quick, params)
    n_theta, n_lobes, n_gamma, n_phi = p["n_theta"], p["n_lobes"], p["n_gamma"], p["n_phi"]
    thetas = np.radians(np.linspace(0.0, 80.0, n_theta))
    rms_rows, lobe_rows, prof_rows = [], [], []
    summary: dict = {"quick": quick, "n_theta": n_theta, "theta_o_deg": np.degrees(thetas).tolist(),
                     "n_gamma": n_gamma, "n_phi": n_phi, "brdfs": {}}
    for key, (name, params) in track(list(BRDFS.items()), "km00: BRDF fits", unit="BRDF"):
        t0 = time.perf_counter()
        f = B.get_brdf(name, **params)
        single = [km.fit_single_lobe(f, t, n_gamma=n_gamma, n_phi=n_phi) for t in thetas]
        multi = [km.fit_multi_lobe(f, t, n_lobes, n_gamma=n_gamma, n_phi=n_phi) for t in thetas]
        d2, p_bar, kw = km.fit_single_2d_lobe(f, thetas, n_gamma=n_gamma, n_phi=n_phi)
        tracks = km.track_lobes(multi)
        dt = time.perf_counter() - t0
        rms_multi = [km.rms_error(multi, k) for k in range(1, n_lobes + 1)]
        for k, r in enumerate(rms_multi, 1):
            rms_rows.append(dict(brdf=key, method="multi", n_lobes=k, rel_rms=r,
                                 mean_slice_rel_rms=float(np.mean(km.slice_rel_rms(multi, k)))))
        rms_rows.append(dict(brdf=key, method="single", n_lobes=1, rel_rms=km.rms_error(single),
                             mean_slice_rel_rms=float(np.mean(km.slice_rel_rms(single)))))
        rms_rows.append(dict(brdf=key, method="single2d", n_lobes=1, rel_rms=km.rms_error(d2),
                             mean_slice_rel_rms=float(np.mean(km.slice_rel_rms(d2)))))
        for method, slices, tr in (("single", single, None), ("multi", multi, tracks), ("single2d", d2, None)):
            for j, sl in enumerate(slices):
                for i, lb in enumerate(sl.lobes):
                    d = lb.as_dict()
                    d.update(brdf=key, method=method, lobe_index=i, track_id=(tr[j][i] if tr else 0),
                             albedo=sl.albedo, weight_k=(kw[j] if method == "single2d" else 1.0))
                    lobe_rows.append(d)
        for sl in single:
            lb = sl.lobes[0]
            th_p = lb.theta_o + lb.theta_off
            wo = B.view_direction(sl.theta_o)
            g = lb.gamma[lb.gamma <= np.radians(30.0)]
            for sign, tag in ((1.0, "toward_horizon"), (-1.0, "toward_normal")):
                thi = th_p + sign * g
                ok = thi < np.pi / 2
                wi = B.direction_from_angles(np.where(ok, thi, 0.0), 0.0)
                fv = np.where(ok, f(wi, wo), np.nan)
                for gg, pv, fvv in zip(g, lb.profile[: len(g)], fv):
                    if np.isfinite(fvv):
                        prof_rows.append(dict(brdf=key, theta_o_deg=float(np.degrees(sl.theta_o)), cut=tag,
                                              gamma_deg=float(np.degrees(gg)), lobe=float(pv), brdf_value=float(fvv)))
        summary["brdfs"][key] = dict(
            model=name, params=params, fit_time_s=round(dt, 2),
            rel_rms_multi=rms_multi, rel_rms_single=km.rms_error(single), rel_rms_single2d=km.rms_error(d2),
            slice_rel_rms_single=km.slice_rel_rms(single).tolist(),
            slice_rel_rms_multi_all=km.slice_rel_rms(multi).tolist(),
            n_lobes_used=[len(s.lobes) for s in multi],
            albedo=[s.albedo for s in single],
            single_phong_exponent=[s.lobes[0].phong_exponent for s in single],
            single_theta_off_deg=[float(np.degrees(s.lobes[0].theta_off)) for s in single],
            single_energy_scale=[s.lobes[0].scale for s in single],
            weight_k_2d=np.asarray(kw).tolist())
    write_csv(out_dir / "rms_vs_lobes.csv", rms_rows,
              comment="rel_rms: sqrt(sum w (f - f_approx)^2 / sum w f^2) pooled over the hemisphere (solid-angle "
                      "weights) and all sampled view elevations; mean_slice_rel_rms: the same per elevation, "
                      "averaged")
    write_csv(out_dir / "lobes.csv", lobe_rows, comment="fitted radially symmetric lobes (Kautz & McCool 2000)")
    write_csv(out_dir / "profiles.csv", prof_rows,
              comment="single-lobe mean profile vs the BRDF cut in the incidence plane through the peak")
    write_json(out_dir / "summary.json", summary)
    return summary


def plot(out_dir: Path) -> list[Path]:

    plt = pyplot()

    out_dir = Path(out_dir)
    rows = read_csv(out_dir / "rms_vs_lobes.csv")
    keys = sorted({r["brdf"] for r in rows})
    figs = []
    fig, ax = plt.subplots(1, len(keys), figsize=(5 * len(keys), 4), squeeze=False, layout="constrained")
    for a, key in zip(ax[0], keys):
        rr = [r for r in rows if r["brdf"] == key]
        mk = [(int(r["n_lobes"]), float(r["rel_rms"])) for r in rr if r["method"] == "multi"]
        a.plot([m[0] for m in mk], [m[1] for m in mk], "o-", label="multi-lobe (greedy, min profiles)")
        for r in rr:
            if r["method"] != "multi":
                a.plot([1], [float(r["rel_rms"])], "s" if r["method"] == "single" else "^", ms=9,
                       label=f"{r['method']} lobe")
        a.set(xlabel="number of lobes", ylabel="relative RMS error of the BRDF fit", title=key, ylim=(0, None))
        integer_ticks(a.xaxis)
        a.legend(fontsize=8)
    p = out_dir / "km00_rms_vs_lobes.png"
    save_figure(fig, p, dpi=110)
    figs.append(p)

    prof = read_csv(out_dir / "profiles.csv")
    lobes = read_csv(out_dir / "lobes.csv")
    fig, ax = plt.subplots(2, len(keys), figsize=(5.5 * len(keys), 8.5), squeeze=False, layout="constrained")
    for j, key in enumerate(keys):
        pr = [r for r in prof if r["brdf"] == key]
        ths = sorted({float(r["theta_o_deg"]) for r in pr})
        peak = max(max(float(r["brdf_value"]), float(r["lobe"])) for r in pr)
        for i, t in enumerate(ths):
            col = plt.cm.viridis(i / max(1, len(ths) - 1))
            cuts = {}
            for cut, ls in (("toward_horizon", "-"), ("toward_normal", ":")):
                sel = [r for r in pr if float(r["theta_o_deg"]) == t and r["cut"] == cut]
                cuts[cut] = sel
                g = [float(r["gamma_deg"]) for r in sel]
                # a cut that ends at the horizon right at the peak is one point: a marker, not an invisible line
                ax[0, j].plot(g, [float(r["brdf_value"]) for r in sel], ls, color=col, lw=0.8,
                              marker="o" if len(sel) == 1 else None, ms=3)
            # the lobe is radially symmetric: draw it along the longer cut (near grazing, the one toward the
            # horizon can end at the peak)
            sel = max(cuts.values(), key=len)
            ax[0, j].plot([float(r["gamma_deg"]) for r in sel], [float(r["lobe"]) for r in sel], "--", color=col,
                          lw=1.6, label=f"θo={t:.0f}°")
        # log scale: the grazing (θo = 80°) lobes peak 10-50x above the others, which a linear axis flattens
        ax[0, j].set(xlabel="γ from peak (deg)", ylabel="f (1/sr)", xlim=(-0.3, 15), yscale="log",
                     ylim=(peak * 1e-3, peak * 2.0),
                     title=f"{key}:\nlobe (dashed) vs BRDF in-plane cuts (solid: toward horizon, dotted: normal)")
        ax[0, j].title.set_fontsize(9)
        if j == len(keys) - 1:  # one legend (the colours are the same in every panel), beside the data
            ax[0, j].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), title="view elevation",
                            title_fontsize=7)
        lm = [r for r in lobes if r["brdf"] == key and r["method"] == "multi"]
        for tid in sorted({int(r["track_id"]) for r in lm}):
            sel = sorted([r for r in lm if int(r["track_id"]) == tid], key=lambda r: float(r["theta_o_deg"]))
            ax[1, j].plot([float(r["theta_o_deg"]) for r in sel], [float(r["theta_off_deg"]) for r in sel], "o-",
                          ms=3, lw=0.8)
        ls = [r for r in lobes if r["brdf"] == key and r["method"] == "single"]
        ax[1, j].plot([float(r["theta_o_deg"]) for r in ls], [float(r["theta_off_deg"]) for r in ls], "k^--",
                      label="single lobe peak offset")
        ax[1, j].set(xlabel="θo (deg)", ylabel="peak elevation offset θ_off (deg)",
                     title="multi-lobe tracks (one colour per track)")
        ax[1, j].title.set_fontsize(9)
        ax[1, j].legend(fontsize=7)
    p = out_dir / "km00_lobes.png"
    save_figure(fig, p, dpi=110)
    figs.append(p)
    return figs
