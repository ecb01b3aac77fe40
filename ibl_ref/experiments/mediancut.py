"""Median-cut regions and lights on the unfolded cube (Knuth et al. 2014 Sec. 3.1/4; Debevec 2008).

For the sky+sun and studio maps and 6, 12, 24, 48, 96 lights, each variant (``per-face`` = the paper,
``global``, ``variance``) is run; the region rectangles and lights are written to ``mediancut_lights.csv``,
the energy spread (max/min, coefficient of variation of region energies: the paper's "equally
important" requirement) and partition residuals (Eq. 1) to ``mediancut_summary.csv``, and the maps'
log-luminance on the horizontal cross to ``mediancut_maps.json`` (plot input).  Each light also gets
its region's equivalent cosine lobe (Meunier et al. 2009 Eq. 32–34, :meth:`ibl_ref.knuth2014.median_cut.LightSet.equivalent_lobes`):
cap half-angle of the region's solid angle, lobe exponent and energy scale; the summary gives their range.

Maps and regions are drawn on the horizontal cross of :func:`ibl_ref.environment.resample.cube_to_cross` (the
library's unfolding and face orientation, see :mod:`ibl_ref.environment.resample`); region rectangles and
light positions are carried onto it by the per-face index map of that same function (:func:`cross_placement`),
so the plot and the maps cannot disagree about orientation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import Param, resolve_params
from ..atomic import read_csv
from ..atomic import write_csv
from ..atomic import write_json
from ..environment.envmap import direction_to_texel_coords
from ..environment.resample import cube_to_cross
from ..figures import plain_log_ticks
from ..figures import pyplot
from ..figures import save_figure
from ..knuth2014.median_cut import VARIANTS
from ..knuth2014.median_cut import check_partition
from ..knuth2014.median_cut import energy_spread
from ..knuth2014.median_cut import luminance
from ..knuth2014.median_cut import median_cut
from ..synthetic.synthetic_envs import make_env

NAME = "mediancut"
DESCRIPTION = "median-cut regions and lights (per-face/global/variance) on the unfolded cube, energy spread"
PAPER = "Knuth et al. 2014, Sec. 3.1 (median cut, Debevec 2008) and Meunier et al. 2009, Eq. 32-34 (equivalent lobes)"
IN_QUICK_REPRODUCE = True
PARAMS = (Param("face_size", 128, 64, "environment cube face size N"),
          Param("light_counts", (6, 12, 24, 48, 96), None, "numbers of lights (regions)"))
RUNTIME = {"quick": "2.1 s (load 0.3)", "full": "23 s (load 11; 7 s CPU)"}
OUTPUTS = ("mediancut_lights.csv", "mediancut_summary.csv", "mediancut_maps.json", "mediancut_<variant>.png",
           "mediancut_energy_spread.png")

LIGHT_COUNTS = (6, 12, 24, 48, 96)
ENVS = ("sky_sun", "studio")


def cross_placement(n: int, layout: str = "hcross") -> dict:
    """face → (A, b): cross pixel (Y, X) = A @ (row, col) + b for texel coordinates of that face (centres integer).

    Read off :func:`ibl_ref.environment.resample.cube_to_cross` applied to an index cube, so it is that function's layout and
    orientation; each face lands as a rotated/flipped copy, an affine map of its texel indices.
    """

    idx = (np.arange(6 * n * n, dtype=np.float64) + 1.0).reshape(6, n, n, 1)
    cross = cube_to_cross(idx, layout)[..., 0]
    where = {int(v) - 1: (yy, xx) for (yy, xx), v in np.ndenumerate(cross) if v > 0}
    out = {}
    for f in range(6):
        p00 = np.array(where[f * n * n], float)
        p10 = np.array(where[f * n * n + n], float) if n > 1 else p00 + (1, 0)
        p01 = np.array(where[f * n * n + 1], float) if n > 1 else p00 + (0, 1)
        A = np.column_stack([p10 - p00, p01 - p00])
        out[f] = (A, p00)
    return out


def log_luminance_cross(y, layout: str = "hcross") -> np.ndarray:
    """log10 luminance (6, n, n) on the cross of :func:`ibl_ref.environment.resample.cube_to_cross`; −99 where no face."""

    img = cube_to_cross(np.log10(np.maximum(y, 1e-6))[..., None], layout)[..., 0]
    inside = cube_to_cross(np.ones(y.shape + (1,)), layout)[..., 0] > 0
    return np.where(inside, img, -99.0)


def run(out_dir: Path, quick: bool = False, **params) -> dict:

    out_dir = Path(out_dir)
    p = resolve_params(__name__, quick, params)
    n = p["face_size"]
    light_rows, summary, maps = [], [], {}
    for env in ENVS:
        cube = make_env(env, n)
        y = luminance(cube)
        maps[env] = {"face_size": n, "layout": "hcross (ibl_ref.environment.resample.cube_to_cross)",
                     "log10_luminance_cross": np.round(log_luminance_cross(y), 4).tolist()}
        for variant in VARIANTS:
            for L in p["light_counts"]:
                ls = median_cut(cube, L, variant)
                chk = check_partition(ls, cube)
                sp = energy_spread(ls)
                summary.append({"env": env, "face_size": n, "variant": variant, "lights": L,
                                "energy_max_over_min": sp["max_over_min"], "energy_cv": sp["cv"],
                                "zero_energy_regions": sp["n_zero_energy"],
                                "solid_angle_max_over_min": float(ls.solid_angle.max() / ls.solid_angle.min()),
                                "uncovered_texels": chk["uncovered"], "overlapping_texels": chk["overlapping"],
                                "rgb_sum_rel_err": chk["rgb_sum_rel_err"]})
                face, x, yy = direction_to_texel_coords(ls.directions, n)
                power = ls.energy / ls.energy.sum()
                lobe = ls.equivalent_lobes()
                summary[-1].update({"lobe_exponent_min": float(lobe.exponent.min()),
                                    "lobe_exponent_median": float(np.median(lobe.exponent)),
                                    "lobe_exponent_max": float(lobe.exponent.max())})
                for i in range(L):
                    f, r0, r1, c0, c1 = (int(v) for v in ls.regions[i])
                    light_rows.append({"env": env, "variant": variant, "lights": L, "index": i, "face": f,
                                       "row0": r0, "row1": r1, "col0": c0, "col1": c1,
                                       "dir_x": ls.directions[i, 0], "dir_y": ls.directions[i, 1],
                                       "dir_z": ls.directions[i, 2], "tex_x": float(x[i]), "tex_y": float(yy[i]),
                                       "r": ls.rgb[i, 0], "g": ls.rgb[i, 1], "b": ls.rgb[i, 2],
                                       "energy_fraction": float(power[i]), "solid_angle_sr": ls.solid_angle[i],
                                       "cap_half_angle_deg": float(np.degrees(lobe.alpha[i])),
                                       "equivalent_lobe_exponent": float(lobe.exponent[i]),
                                       "equivalent_lobe_scale": float(lobe.scale_energy[i])})
    write_csv(out_dir / "mediancut_lights.csv", light_rows, comment=(
        "Median-cut lights: region (face,row0:row1,col0:col1, exclusive ends), unit direction, rgb = integral of L "
        "over the region (radiance*sr), energy_fraction = luminance*sr share, tex_x/tex_y = continuous texel coords; "
        "equivalent lobe (Meunier 2009 Eq. 32-34): the cap of the region's solid angle, Omega = 2*pi*(1 - cos alpha), "
        "fitted in L2 by max(a.v,0)^e; scale = Omega*(e+1)/(2*pi) makes the lobe carry Omega (dimensionless)."))
    write_csv(out_dir / "mediancut_summary.csv", summary, comment=(
        "Energy spread of the regions (Rec.709 luminance * exact solid angle) and Eq. 1 partition residuals; "
        "lobe_exponent_*: range of the regions' equivalent cosine-lobe exponents (Meunier 2009 Eq. 32-34)."))
    write_json(out_dir / "mediancut_maps.json", maps)
    per_face = [r for r in summary if r["variant"] == "per-face"]
    return {"max_rgb_sum_rel_err": max(r["rgb_sum_rel_err"] for r in summary),
            "partition_ok": all(r["uncovered_texels"] == 0 and r["overlapping_texels"] == 0 for r in summary),
            "per_face_cv_at_96": {r["env"]: r["energy_cv"] for r in per_face if r["lights"] == 96}}


def plot(out_dir: Path) -> list:
    import json


    plt = pyplot()
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Rectangle


    out_dir = Path(out_dir)
    maps = json.loads((out_dir / "mediancut_maps.json").read_text())
    lights = read_csv(out_dir / "mediancut_lights.csv")
    summary = read_csv(out_dir / "mediancut_summary.csv")
    paths = []
    counts = sorted({int(r["lights"]) for r in summary})
    for variant in ("per-face", "global", "variance"):
        fig, axes = plt.subplots(len(counts), len(ENVS), figsize=(11, 2.9 * len(counts)), squeeze=False,
                                 layout="constrained")
        for j, env in enumerate(ENVS):
            n = maps[env]["face_size"]
            place = cross_placement(n)
            img = np.array(maps[env]["log10_luminance_cross"])
            img = np.ma.masked_less(img, -98)
            # the cells outside the cross get a tint no luminance has (white would read as "very bright")
            cmap = plt.get_cmap("gray").with_extremes(bad="#dce6f2")
            for i, L in enumerate(counts):
                ax = axes[i, j]
                im = ax.imshow(img, cmap=cmap, interpolation="nearest", vmin=np.percentile(img.compressed(), 1),
                               vmax=np.percentile(img.compressed(), 99.5))
                sel = [r for r in lights if r["env"] == env and r["variant"] == variant and int(r["lights"]) == L]
                rects, xs, ys, sz = [], [], [], []
                for r in sel:
                    A, b = place[int(r["face"])]
                    r0, r1, c0, c1 = (int(r[k]) for k in ("row0", "row1", "col0", "col1"))
                    corners = A @ np.array([[r0 - 0.5, r1 - 0.5], [c0 - 0.5, c1 - 0.5]]) + b[:, None]
                    (y0, y1), (x0, x1) = np.sort(corners, axis=1)
                    rects.append(Rectangle((x0, y0), x1 - x0, y1 - y0))
                    ys_, xs_ = A @ np.array([float(r["tex_y"]), float(r["tex_x"])]) + b
                    xs.append(xs_)
                    ys.append(ys_)
                    sz.append(4 + 300 * float(r["energy_fraction"]))
                ax.add_collection(PatchCollection(rects, facecolor="none", edgecolor="tab:orange", linewidth=0.6))
                ax.scatter(xs, ys, s=sz, c="red", edgecolors="white", linewidths=0.3)
                srow = [s for s in summary if s["env"] == env and s["variant"] == variant and int(s["lights"]) == L][0]
                ax.set_title(f"{env}, {L} lights ({variant}); energy CV {float(srow['energy_cv']):.2f}", fontsize=8)
                ax.set_xticks([])
                ax.set_yticks([])
            fig.colorbar(im, ax=axes[:, j].tolist(), shrink=0.25, aspect=15, extend="both",
                         label=f"{env}: log10 luminance")
        fig.suptitle("Median cut on the cube (horizontal cross of resample.cube_to_cross: +Y on top, "
                     "−X +Z +X −Z across, −Y below);\nlog luminance (1st–99.5th percentile); regions in orange; "
                     "dot area ∝ light power", fontsize=9)
        p = out_dir / f"mediancut_{variant}.png"
        save_figure(fig, p, dpi=110)
        paths.append(p)

    fig, ax = plt.subplots(figsize=(7.5, 4), layout="constrained")
    for env, mk in (("sky_sun", "o"), ("studio", "s")):
        for variant, ls in (("per-face", "-"), ("global", "--"), ("variance", ":")):
            sel = [s for s in summary if s["env"] == env and s["variant"] == variant]
            ax.plot([int(s["lights"]) for s in sel], [float(s["energy_cv"]) for s in sel], ls, marker=mk,
                    label=f"{env} {variant}")
    ax.set_xscale("log", base=2)
    ax.set_xticks(counts, [str(c) for c in counts])  # light counts are integers
    ax.minorticks_off()
    ax.set_yscale("log")
    plain_log_ticks(ax.yaxis, minor=(2, 3, 5))
    ax.set_xlabel("lights (regions)")
    ax.set_ylabel("CV of region energies (0 = equally important)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    p = out_dir / "mediancut_energy_spread.png"
    save_figure(fig, p, dpi=120)
    paths.append(p)
    return paths
