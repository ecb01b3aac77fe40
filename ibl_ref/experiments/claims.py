"""Knuth et al. (2014) Sec. 3.2 / Sec. 5 claims about the filter pyramid, checked one by one.

Each statement of the paper about Fig. 4/5 is turned into a measurable criterion (stated in the table)
and evaluated under every interpretation of the ambiguous error measure (:mod:`ibl_ref.knuth2014.lobe_analysis`):
pyramid order ∈ {shrink_then_filter (stf), filter_then_shrink (fts)} × volume ∈ {integral, radial} ×
target axis ∈ {texel, centroid}; error = symmetric-difference volume in percent of the target volume.
White texel at a face centre, seam neighbour.

s ranges used by the criteria: ``s = 1``; the *mid* range 2 ≤ s with a fitted level ≥ 1 (all levels
above the finest, i.e. before the level 0/1 blend, where the mirror texel enters); the *high* range where
the fitted level is < 1 (up to the lobe being narrower than a texel).

Files: ``claims.csv``, ``claims.json``; plot ``claims.png`` (the table).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..progress import track
from ..atomic import read_csv, write_csv, write_json
from . import Param, resolve_params
from ..figures import pyplot
from ..figures import save_figure
from ..knuth2014.pyramid import build_pyramid
from ..knuth2014.pyramid import pyramid_energy
from .fig5 import compute_rows

NAME = "claims"
DESCRIPTION = "Knuth 2014 Sec. 5 filter claims (box ~4% at s=1, spikes, Gauss stable, cos <10%, sqrt-cos) checked"
PAPER = "Knuth et al. 2014, Sec. 3.2 and Sec. 5 (the statements about Figs. 4 and 5, and energy conservation)"
IN_QUICK_REPRODUCE = True
PARAMS = (Param("face_size", 128, 64, "cube face size N (texels)"),
          Param("exponents", 40, 24, "number of s_Phong values from 1 to the texel limit"))
RUNTIME = {"quick": "2.4 s (load 0.3)", "full": "105 s (load 3.5-6.9)"}
OUTPUTS = ("claims.csv", "claims.json", "claims.png")

ORDER_CODES = {"stf": "shrink_then_filter", "fts": "filter_then_shrink"}
INTERPRETATIONS = [(o, v, c) for o in ORDER_CODES for v in ("integral", "radial") for c in ("texel", "centroid")]
FILTERS = ("none", "gauss", "cos", "box", "sqrtcos")


def _curves(rows, order, volume, centring):
    out = {}
    for k in FILTERS:
        rr = sorted((r for r in rows if r["kernel"] == k and r["volume"] == volume and r["centring"] == centring
                     and r["order"] == ORDER_CODES[order]),
                    key=lambda r: r["s_phong"])
        out[k] = (np.array([r["s_phong"] for r in rr]), np.array([r["err_symdiff_pct"] for r in rr]),
                  np.array([r["level"] for r in rr]))
    return out


def _evaluate(c):
    """All criteria for one interpretation: name → (measured text, reproduced bool)."""
    e1 = {k: c[k][1][0] for k in FILTERS}  # s = 1 is the first grid point

    def rng(k, which):
        s, e, lev = c[k]
        if which == "mid":
            m = (s >= 2) & (lev >= 1)
        elif which == "high":
            m = lev < 1
        else:
            m = np.ones_like(s, bool)
        return e[m] if m.any() else np.array([np.nan])

    res = {}
    best = min(FILTERS, key=lambda k: e1[k])
    res["box_best_s1"] = (f"box {e1['box']:.1f}%, best={best} {e1[best]:.1f}%", best == "box")
    res["box_about_4pct_s1"] = (f"box {e1['box']:.1f}%", 2.0 <= e1["box"] <= 8.0)
    res["none_bad_s1"] = (f"none {e1['none']:.1f}% vs filtered max {max(e1[k] for k in FILTERS[1:]):.1f}%",
                          e1["none"] > max(e1[k] for k in FILTERS[1:]))
    peak = {k: float(np.nanmax(rng(k, "mid"))) for k in FILTERS}
    res["none_box_spike"] = (", ".join(f"{k} {peak[k]:.0f}%" for k in FILTERS),
                             min(peak["none"], peak["box"]) > max(peak["gauss"], peak["cos"], peak["sqrtcos"]))
    sd = {k: float(np.nanstd(rng(k, "mid"))) for k in FILTERS}
    med = {k: float(np.nanmean(rng(k, "mid"))) for k in FILTERS}  # mean: spikes count
    res["gauss_stable_high"] = (
        f"std gauss {sd['gauss']:.1f} none {sd['none']:.1f} box {sd['box']:.1f}; mean gauss {med['gauss']:.1f} "
        f"cos {med['cos']:.1f} sqrtcos {med['sqrtcos']:.1f}",
        sd["gauss"] <= min(sd["none"], sd["box"]) and med["gauss"] >= max(med["cos"], med["sqrtcos"]))
    s_cos = c["cos"][0]
    mx_all = float(np.nanmax(c["cos"][1][s_cos >= 2]))
    mx_mid = float(np.nanmax(rng("cos", "mid")))
    res["cos_below_10_all"] = (f"max cos {mx_all:.1f}% over all s >= 2", mx_all < 10.0)
    res["cos_below_10_mid"] = (f"max cos {mx_mid:.1f}% over the mid range", mx_mid < 10.0)
    res["cos_weak_s1"] = (f"cos {e1['cos']:.1f}% vs box {e1['box']:.1f}%, sqrtcos {e1['sqrtcos']:.1f}%",
                          e1["cos"] > max(e1["box"], e1["sqrtcos"]))
    res["sqrtcos_near_box_s1"] = (f"sqrtcos {e1['sqrtcos']:.1f}% vs box {e1['box']:.1f}%",
                                  e1["sqrtcos"] <= 1.5 * e1["box"])
    res["sqrtcos_better_high"] = (f"mean (mid s) sqrtcos {med['sqrtcos']:.1f}% vs box {med['box']:.1f}%",
                                  med["sqrtcos"] < med["box"])
    hi = float(np.nanmedian(rng("sqrtcos", "high")))
    res["sqrtcos_degrades_resolution"] = (f"median sqrtcos high-s {hi:.1f}% vs mean mid {med['sqrtcos']:.1f}%",
                                          hi > med["sqrtcos"])
    return res


STATEMENTS = {
    "box_best_s1": ("'In our test the box filter performed best' (s=1)",
                    "box has the smallest s=1 error of the five"),
    "box_about_4pct_s1": ("box s=1 error 'of roughly 4%'", "box s=1 error in [2, 8]% (4% within a factor 2)"),
    "none_bad_s1": ("'MIP maps alone ... strong deviations', esp. at s=1 (Fig. 4)",
                    "none has a larger s=1 error than every filtered pyramid"),
    "none_box_spike": ("'no filtering and the box filter both introduce high spikes of relative error when s rises'",
                       "peak error over the mid range of none and of box above those of gauss, cos, sqrtcos"),
    "gauss_stable_high": ("'The Gauss filter is stable, but has a high overall error rate'",
                          "gauss std over mid range <= none's and box's, and its mean >= cos's and sqrtcos's"),
    "cos_below_10_all": ("cosine filter 'always below 10%' (apart from the diffuse case)",
                         "max cos error over all s >= 2 (up to the texel limit) < 10%"),
    "cos_below_10_mid": ("cosine filter 'always below 10%' (apart from the diffuse case), levels >= 1 only",
                         "max cos error over the mid range < 10%"),
    "cos_weak_s1": ("cosine filter 'has a strong deviation for the important diffuse reflection case'",
                    "cos s=1 error above box's and sqrtcos's"),
    "sqrtcos_near_box_s1": ("sqrt-cos 'performs nearly as good as the box filter for the diffuse case'",
                            "sqrtcos s=1 error <= 1.5 x box's"),
    "sqrtcos_better_high": ("sqrt-cos 'has a much better behavior when increasing s_Phong'",
                            "mean error over the mid range: sqrtcos < box"),
    "sqrtcos_degrades_resolution": ("sqrt-cos 'tends to introduce high deviations when the exponent gets into high "
                                    "regions' (resolution limit)", "median error at level < 1 > mean over mid range"),
}


def _energy_claim(n):
    """'no additional energy is introduced as long as the 5×5 filters are normalized' (Sec. 3.2).

    Returns, per map/kernel/seam, the relative energy drift of largest magnitude over the levels.
    """

    rng = np.random.default_rng(7)
    cube = rng.random((6, n, n, 1))
    out = {}
    for k in ("none", "sqrtcos", "box"):
        for seam in ("neighbour", "clamp"):
            rows = pyramid_energy(build_pyramid(cube, k, seam=seam))
            out[f"random/{k}/{seam}"] = max((r["rel_drift"][0] for r in rows), key=abs)
    for pos, (r0, c0) in {"centre_texel": (n // 2, n // 2), "corner_texel": (0, 0)}.items():
        for k in ("none", "sqrtcos"):
            one = np.zeros((6, n, n, 1))
            one[4, r0, c0, 0] = 1.0
            rows = pyramid_energy(build_pyramid(one, k))
            out[f"{pos}/{k}/neighbour"] = max((r["rel_drift"][0] for r in rows), key=abs)
    return out


def run(out_dir: Path, quick: bool = False, **params) -> dict:

    p = resolve_params(__name__, quick, params)
    t0 = time.perf_counter()
    n = p["face_size"]
    rows = []
    for order in track(list(ORDER_CODES.values()), "claims: pyramid orders", unit="order"):
        rows += compute_rows(n, "centre", p["exponents"], FILTERS, order=order)
    table = []
    evals = {ic: _evaluate(_curves(rows, *ic)) for ic in INTERPRETATIONS}
    for key, (statement, criterion) in STATEMENTS.items():
        row = {"claim": key, "statement": statement, "criterion": criterion}
        oks = []
        for o, vol, cen in INTERPRETATIONS:
            text, ok = evals[(o, vol, cen)][key]
            row[f"measured_{o}_{vol}_{cen}"] = text
            row[f"reproduced_{o}_{vol}_{cen}"] = "yes" if ok else "no"
            oks.append(ok)
        row["reproduced"] = "yes" if all(oks) else ("partly" if any(oks) else "no")
        row["reason_if_not"] = "" if all(oks) else "criterion fails under the interpretations marked 'no' (see measured)"
        table.append(row)
    en = _energy_claim(n)
    inc = max(en.values())
    table.append({"claim": "energy_not_increased",
                  "statement": "'no additional energy is introduced as long the 5x5 filters are normalized'",
                  "criterion": "max relative energy gain over levels < 1% (exact solid angles)",
                  **{f"measured_{o}_{v}_{c}": "; ".join(f"{k} {100 * x:+.3f}%" for k, x in en.items())
                     for o, v, c in INTERPRETATIONS},
                  **{f"reproduced_{o}_{v}_{c}": "yes" if inc < 0.01 else "no" for o, v, c in INTERPRETATIONS},
                  "reproduced": "yes" if inc < 0.01 else "no",
                  "reason_if_not": "" if inc < 0.01 else (
                      "the 5x5 taps and the 2x2 mean are normalised per texel (gather), not per solid angle "
                      "(scatter): energy of a lit texel near a cube corner (small solid angle) is spread onto "
                      "larger texels and grows; smooth/random maps drift < 0.1%")})
    cols = ["claim", "statement", "criterion"] + [f"measured_{o}_{v}_{c}" for o, v, c in INTERPRETATIONS] + \
        [f"reproduced_{o}_{v}_{c}" for o, v, c in INTERPRETATIONS] + ["reproduced", "reason_if_not"]
    write_csv(Path(out_dir) / "claims.csv", table, cols,
              comment=f"Knuth 2014 claims; face size {n}, white texel at face centre, symmetric-difference error")
    summary = {"face_size": n, "time_s": round(time.perf_counter() - t0, 2),
               "outcome": {r["claim"]: r["reproduced"] for r in table}}
    write_json(Path(out_dir) / "claims.json", {**summary, "table": table})
    return summary


def plot(out_dir: Path) -> list[Path]:

    plt = pyplot()

    rows = read_csv(Path(out_dir) / "claims.csv")
    cells = [[r["claim"]] + [r[f"reproduced_{o}_{v}_{c}"] for o, v, c in INTERPRETATIONS] + [r["reproduced"]]
             for r in rows]
    fig, ax = plt.subplots(figsize=(9.5, 0.2 * (len(rows) + 1) + 0.55))
    ax.axis("off")
    t = ax.table(cellText=cells, colLabels=["claim"] + [f"{o}/{v[:3]}/{c[:3]}" for o, v, c in INTERPRETATIONS]
                 + ["overall"],
                 loc="upper center", cellLoc="left")
    t.auto_set_font_size(False)
    t.set_fontsize(8)
    t.auto_set_column_width(list(range(len(cells[0]))))  # every label fits its cell
    colour = {"yes": "#d9f0d3", "no": "#f4cccc", "partly": "#fff2cc"}
    for (i, j), cell in t.get_celld().items():
        if i > 0 and j > 0:
            cell.set_facecolor(colour.get(cell.get_text().get_text(), "white"))
    ax.set_title("Knuth 2014 claims reproduced? Columns: pyramid order (stf = shrink_then_filter, fts = "
                 "filter_then_shrink) /\nlobe volume (int = ∫f dω, rad = ⅓∫f³ dω) / target axis (tex = lit texel, "
                 "cen = response centroid)", fontsize=9)
    fig.tight_layout()
    p = Path(out_dir) / "claims.png"
    save_figure(fig, p, dpi=110)
    return [p]
