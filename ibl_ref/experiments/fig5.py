"""Knuth et al. (2014) Fig. 5: relative lobe error vs s_Phong for the five 5×5 filters.

For every filter (none = MIP only, gauss, cos, box, sqrtcos), face size, white-texel position and volume
definition, :func:`ibl_ref.knuth2014.lobe_analysis.analyse` fits the continuous level whose lobe volume equals the
cosˢ target's and reports the remaining error in percent of the target volume, for s from 1 up to
:func:`ibl_ref.knuth2014.lobe_analysis.s_texel_limit` (lobe narrower than a level-0 texel).

Sizes: quick = N 64 (centre, edge, corner) + N 128 (centre), 24 exponents; full = N 64, 128, 256 (three
positions) + N 512 (centre), 32 exponents.  Pyramid order shrink_then_filter, seam neighbour.

Files: ``fig5_errors.csv`` (one row per configuration and s; both error definitions and both
centrings), ``fig5_meta.json``; plots ``fig5_<N>.png`` (rows: volume definition, columns: position;
error = symmetric-difference volume, target centred on the white texel) and ``fig5_<N>_centroid.png``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..atomic import read_csv, write_csv, write_json
from . import Param, resolve_params
from ..executors import map_jobs
from ..figures import pyplot
from ..figures import save_figure
from ..knuth2014.lobe_analysis import CENTRINGS
from ..knuth2014.lobe_analysis import LobeResponse
from ..knuth2014.lobe_analysis import analyse
from ..knuth2014.lobe_analysis import s_grid

NAME = "fig5"
DESCRIPTION = "Knuth 2014 Fig. 5: relative lobe error vs s_Phong for none/gauss/cos/box/sqrtcos filters"
PAPER = "Knuth et al. 2014, Fig. 5 (relative lobe error vs s_Phong of the five filters, Sec. 5)"
IN_QUICK_REPRODUCE = True
PARAMS = (
    Param("face_sizes", (64, 128, 256), (64,), "face sizes N with all three white-texel positions (centre, edge, corner)"),
    Param("centre_only_sizes", (512,), (128,), "further face sizes with the face-centre position only"),
    Param("exponents", 32, 24, "number of s_Phong values from 1 to the texel limit (log spaced)"),
)
RUNTIME = {"quick": "7.9 s (load 0.3)", "full": "4 min 30 s (load 3.3; 4 min 18 s CPU; 1.0 GB)"}
OUTPUTS = ("fig5_errors.csv", "fig5_meta.json", "fig5_<N>.png", "fig5_<N>_centroid.png")

KERNELS = ("none", "gauss", "cos", "box", "sqrtcos")
# the paper's colours/styles (Fig. 5 caption)
STYLE = {"none": dict(color="darkviolet", ls=":"), "gauss": dict(color="black", ls="-"),
         "box": dict(color="red", ls="-"), "cos": dict(color="green", ls="-"),
         "sqrtcos": dict(color="blue", ls="-")}


def configs(quick: bool, **params):
    """(face_size, position, s-count) combinations of the quick and the full run."""
    p = resolve_params(__name__, quick, params)
    k = p["exponents"]
    return ([(n, pos, k) for n in p["face_sizes"] for pos in ("centre", "edge", "corner")]
            + [(n, "centre", k) for n in p["centre_only_sizes"]])


def compute_rows(n, position, count, kernels=KERNELS, order="shrink_then_filter", seam="neighbour"):

    rows = []
    s_values = s_grid(n, count)
    for k in kernels:
        resp = LobeResponse(n, k, order=order, seam=seam, position=position)
        rows += analyse(n, k, s_values, response=resp, centrings=CENTRINGS)
        del resp
    return rows


def config_job(config) -> tuple:
    """One configuration ``(face_size, position, s-count)`` → (its rows, seconds): an independent job."""
    t = time.perf_counter()
    rows = compute_rows(*config)
    return rows, round(time.perf_counter() - t, 3)


def run(out_dir: Path, quick: bool = False, executor=None, workers: int = 1, **params) -> dict:

    out_dir = Path(out_dir)
    t0 = time.perf_counter()
    cfgs = configs(quick, **params)
    rows, timing = [], []
    # cost ∝ N (measured: 41 / 86 / 206 / 409 s at N = 64 … 512, centre): the N = 512 job must not start last
    results = map_jobs(config_job, cfgs, executor=executor, workers=workers, desc="fig5 configurations",
                       unit="config", cost=[c[0] for c in cfgs])
    for (n, pos, _), (r, dt) in zip(cfgs, results):
        rows += r
        timing.append({"face_size": n, "position": pos, "time_s": dt})
    cols = ["face_size", "kernel", "order", "seam", "position", "volume", "centring", "s_phong", "level",
            "fit_clipped", "err_symdiff_pct", "err_voldiff_pct", "target_quad_rel_err_pct"]
    write_csv(out_dir / "fig5_errors.csv", rows, cols,
              comment="Knuth 2014 Fig. 5 reproduction; errors in percent of the analytic target lobe volume")
    at_s1 = {f"{r['kernel']}/{r['volume']}/N{r['face_size']}/{r['position']}": round(r["err_symdiff_pct"], 2)
             for r in rows if r["s_phong"] == 1.0 and r["centring"] == "texel"}
    meta = {"quick": quick, "total_time_s": round(time.perf_counter() - t0, 2), "timing": timing,
            "err_symdiff_pct_at_s1_texel_centring": at_s1,
            "order": "shrink_then_filter", "seam": "neighbour"}
    write_json(out_dir / "fig5_meta.json", meta)
    return {"total_time_s": meta["total_time_s"], "err_at_s1": at_s1}


def plot(out_dir: Path) -> list[Path]:

    plt = pyplot()

    out_dir = Path(out_dir)
    rows = read_csv(out_dir / "fig5_errors.csv")
    groups: dict = {}
    for r in rows:
        key = (int(r["face_size"]), r["centring"], r["volume"], r["position"], r["kernel"])
        groups.setdefault(key, ([], []))
        groups[key][0].append(float(r["s_phong"]))
        groups[key][1].append(float(r["err_symdiff_pct"]))
    figs = []
    for centring in ("texel", "centroid"):
        for n in sorted({k[0] for k in groups}):
            positions = [p for p in ("centre", "edge", "corner") if any(k[0] == n and k[3] == p for k in groups)]
            vols = ("integral", "radial")
            fig, axes = plt.subplots(len(vols), len(positions),
                                     figsize=(max(4.4 * len(positions), 7.0), 3.4 * len(vols)),
                                     squeeze=False, sharex=True, layout="constrained")
            for i, vol in enumerate(vols):
                # the y range of a row shows every curve (the unfiltered "none" pyramid reaches ~170 %)
                top = max((max(groups[key][1]) for key in groups
                           if key[0] == n and key[1] == centring and key[2] == vol), default=100.0)
                for j, pos in enumerate(positions):
                    ax = axes[i, j]
                    for k in KERNELS:
                        g = groups.get((n, centring, vol, pos, k))
                        if g:
                            ax.plot(np.array(g[0]), np.array(g[1]), label=k, **STYLE[k])
                    ax.set_xscale("log")
                    ax.set_ylim(0, 1.05 * top)
                    ax.axhline(10, color="0.7", lw=0.6)
                    ax.set_title(f"N = {n}, lit texel at face {pos}, volume = {vol}", fontsize=9)
                    if i == len(vols) - 1:
                        ax.set_xlabel("Phong exponent s")
                    if j == 0:
                        ax.set_ylabel("error, % of target volume")
            axes[0, -1].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0), title="filter")
            fig.suptitle(f"Fig. 5 reproduction: symmetric-difference error\n(target axis: {centring}; grey line: 10 %)",
                         fontsize=10)
            suffix = "" if centring == "texel" else "_centroid"
            p = out_dir / f"fig5_{n}{suffix}.png"
            save_figure(fig, p, dpi=110)
            figs.append(p)
    return figs
