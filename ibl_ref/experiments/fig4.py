"""Knuth et al. (2014) Fig. 4: polar cross-sections of the s_Phong = 1 lobe for the five filters.

A white texel at the centre of face +Z is filtered into the pyramid of each filter (none = "MIP map
only", gauss, cos, box, sqrtcos); the level is fitted by lobe volume (:mod:`ibl_ref.knuth2014.lobe_analysis`, both
volume definitions) and the trilinear response is read along the great circle through the texel's
direction d0 and the face's horizontal axis, θ ∈ [−180°, 180°].  Both lobes are peak-normalised (the
response by its maximum over the level-0 sampling grid, as in the volume fit); the target is
max(cos θ, 0).

Files: ``fig4_cross_sections.csv`` (kernel, volume, level, theta_deg, response, target), ``fig4_levels.csv``;
plot ``fig4.png`` (rows: volume definition; columns: filters; polar axes).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomic import read_csv, write_csv
from . import Param, resolve_params
from ..figures import pyplot
from ..figures import save_figure
from ..knuth2014.lobe_analysis import LobeResponse
from ..knuth2014.lobe_analysis import target_lobe

NAME = "fig4"
DESCRIPTION = "Knuth 2014 Fig. 4: polar cross-sections of the s=1 lobe for MIP-only/gauss/cos/box/sqrtcos"
PAPER = "Knuth et al. 2014, Fig. 4 (s = 1 lobe of each 5x5 filter's MIP pyramid vs the cosine target)"
IN_QUICK_REPRODUCE = True
PARAMS = (Param("face_size", 256, 64, "cube face size N of the pyramid (texels)"),)
RUNTIME = {"quick": "1.0 s (load 0.3)", "full": "11 s (load 3.5)"}
OUTPUTS = ("fig4_cross_sections.csv", "fig4_levels.csv", "fig4.png")

KERNELS = ("none", "gauss", "cos", "box", "sqrtcos")
TITLES = {"none": "MIP map only", "gauss": "Gaussian", "cos": "cosine", "box": "box", "sqrtcos": "sqrt cosine"}


def run(out_dir: Path, quick: bool = False, **params) -> dict:

    n = resolve_params(__name__, quick, params)["face_size"]
    s = 1.0
    theta = np.deg2rad(np.linspace(-180.0, 180.0, 721))
    rows, lev_rows = [], []
    for k in KERNELS:
        resp = LobeResponse(n, k, position="centre")
        d0 = resp.d0
        e = np.array([-1.0, 0.0, 0.0])  # +Z face's u axis in OpenEXR orientation (horizontal)
        e = e - e.dot(d0) * d0
        e /= np.linalg.norm(e)
        dirs = np.cos(theta)[:, None] * d0 + np.sin(theta)[:, None] * e
        for vol in ("integral", "radial"):
            ell, clipped = resp.fit_level(s, vol)
            peak = resp.at_level(ell).max()
            f = resp.evaluate(dirs, ell) / peak
            t = target_lobe(np.cos(theta), s)
            err = resp.errors(s, ell, vol)
            lev_rows.append({"kernel": k, "volume": vol, "face_size": n, "level": round(ell, 6),
                             "fit_clipped": clipped, "err_symdiff_pct": 100 * err["symdiff"]})
            rows += [{"kernel": k, "volume": vol, "level": round(ell, 6), "theta_deg": round(float(np.rad2deg(a)), 3),
                      "response": float(fv), "target": float(tv)} for a, fv, tv in zip(theta, f, t)]
    write_csv(Path(out_dir) / "fig4_cross_sections.csv", rows,
              comment=f"Knuth 2014 Fig. 4 reproduction; s_Phong=1, face size {n}, white texel at +Z face centre")
    write_csv(Path(out_dir) / "fig4_levels.csv", lev_rows)
    return {"face_size": n, "levels": {f"{r['kernel']}/{r['volume']}": r["level"] for r in lev_rows},
            "err_symdiff_pct": {f"{r['kernel']}/{r['volume']}": round(r["err_symdiff_pct"], 2) for r in lev_rows}}


def plot(out_dir: Path) -> list[Path]:

    plt = pyplot()

    rows = read_csv(Path(out_dir) / "fig4_cross_sections.csv")
    levs = {(r["kernel"], r["volume"]): r for r in read_csv(Path(out_dir) / "fig4_levels.csv")}
    vols = ("integral", "radial")
    fig, axes = plt.subplots(len(vols), len(KERNELS), subplot_kw={"projection": "polar"},
                             figsize=(3.0 * len(KERNELS), 3.6 * len(vols)), layout="constrained")
    for i, vol in enumerate(vols):
        for j, k in enumerate(KERNELS):
            rr = [r for r in rows if r["kernel"] == k and r["volume"] == vol]
            th = np.deg2rad([float(r["theta_deg"]) for r in rr])
            ax = axes[i, j]
            ax.plot(th, [float(r["target"]) for r in rr], color="blue", lw=1.2)
            ax.plot(th, [float(r["response"]) for r in rr], color="red", lw=1.0)
            ax.set_theta_zero_location("N")
            ax.set_thetagrids([0, 45, 90, 135, 180, 225, 270, 315],
                              ["0°", "45°", "90°", "135°", "±180°", "−135°", "−90°", "−45°"], fontsize=7)
            ax.set_ylim(0, 1.05)
            ax.set_rticks([0.25, 0.5, 0.75, 1.0])
            ax.set_yticklabels(["", "0.5", "", "1"], fontsize=6)
            ax.set_rlabel_position(112.5)
            lv = levs[(k, vol)]
            ax.set_title(f"{TITLES[k]} ({vol})\nlevel {float(lv['level']):.2f}, err {float(lv['err_symdiff_pct']):.1f}%",
                         fontsize=8, pad=10)
    fig.suptitle("Fig. 4 reproduction: s = 1 target max(cos θ, 0) (blue) vs pyramid lobe (red), both peak-normalised "
                 "(radius: relative response); θ = angle from the lit texel's direction", fontsize=9)
    p = Path(out_dir) / "fig4.png"
    save_figure(fig, p, dpi=100)
    return [p]
