"""Write the result pages of the documentation site from the saved run data.

Every measured number of the site lives in a data file under ``tests/data/readme_runs/<name>/`` (CSV with units in
the column names, and ``run.json``: the command, commit, date, load and wall time of the run that wrote them, and
``source`` where the numbers were transcribed from an earlier README).  This script renders each folder into
``docs/results/<name>.md`` through the template ``docs/page_templates/<name>.md``: tables are rendered from the
CSV files, numbers in the prose are ``{{key}}`` placeholders computed here from the data, and the provenance section
comes from ``run.json``.  So prose and numbers cannot drift apart: ``tests/test_docs_pages.py`` regenerates every
page and compares it with the committed file byte for byte, and ``tests/test_readme_saved_runs.py`` /
``tests/test_readme_method_zoo.py`` pin the data to the numbers as they were first published.

Usage::

    python docs/make_results.py            # rewrite docs/results/*.md and docs/concepts.md
    python docs/make_results.py --check    # exit 1 (naming the files) if a committed page differs

Standard library only (csv, json), so it runs without the package installed.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import re
import statistics
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
DATA = ROOT / "tests" / "data" / "readme_runs"
TEMPLATES = DOCS / "page_templates"
RESULTS = DOCS / "results"
CONCEPTS_CSV = DOCS / "concepts.csv"
MIB = 1024.0 * 1024.0


# ---- reading ----------------------------------------------------------------------------------------------------
def read_csv(path: Path) -> list[dict]:
    """The rows of a CSV file as dicts (``#`` comment lines skipped, as ``ibl_ref.atomic.read_csv`` reads them)."""
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(ln for ln in fh if not ln.startswith("#")))


def read_json(path: Path):
    return json.loads(Path(path).read_text(encoding="utf-8"))


# ---- formatting -------------------------------------------------------------------------------------------------
def fixed(value: float, decimals: int) -> str:
    """``value`` with ``decimals`` digits after the point."""
    return f"{value:.{decimals}f}"


def pct(frac: float, decimals: int) -> str:
    """A fraction as a percentage with ``decimals`` digits (no % sign)."""
    return fixed(100.0 * frac, decimals)


def sci(value: float, digits: int = 2) -> str:
    """``value`` in the README's scientific style: 5.9e-5 (``digits`` significant digits, no exponent padding)."""
    mantissa, exponent = f"{value:.{digits - 1}e}".split("e")
    return f"{mantissa}e{int(exponent)}"


def duration(seconds: float) -> str:
    """Whole seconds as '2 min 4 s' (or '58 s')."""
    m, s = divmod(int(round(seconds)), 60)
    return f"{m} min {s} s" if m else f"{s} s"


def signed(text: str) -> str:
    """A signed number as printed: '+0.008', '−0.003' (typographic minus)."""
    return ("−" + text[1:]) if text.startswith("-") else (text if text.startswith("+") else "+" + text)


def opt(text: str, decimals: int) -> str:
    """A CSV cell with ``decimals`` digits, or '—' where the run left it empty."""
    return fixed(float(text), decimals) if text else "—"


def md_table(header: list[str], rows: list[list[str]]) -> str:
    """A markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in rows:
        assert len(r) == len(header), (header, r)
        lines.append("| " + " | ".join(str(c) for c in r) + " |")
    return "\n".join(lines)


# ---- pages ------------------------------------------------------------------------------------------------------
PAGES: dict[str, object] = {}


def page(name: str):
    """Register the function that computes the placeholders of page ``name`` from its data folder."""

    def deco(fn):
        PAGES[name] = fn
        return fn

    return deco


_NUMBERS: dict[str, object] = {}


def numbers(name: str):
    """Register the function that computes the named numbers of data folder ``name`` (used by its page and by the
    claims table)."""

    def deco(fn):
        _NUMBERS[name] = fn
        return fn

    return deco


def run_numbers(name: str) -> dict[str, str]:
    return _NUMBERS[name](DATA / name)


# ---- render-error ------------------------------------------------------------------------------------------------
def render_error_rows(folder: Path) -> dict[str, dict]:
    """The 96-light, 256² VSM rows of render_error.csv by material."""
    rows = read_csv(folder / "render_error.csv")
    return {q["material"]: q for q in rows if q["lights"] == "96" and q["vsm_resolution"] == "256"}


@numbers("render-error")
def render_error_numbers(folder: Path) -> dict[str, str]:
    data = render_error_rows(folder)
    out = {}
    for mat in ("diffuse", "g0.9", "g0.99"):
        out[f"ours_{mat}"] = pct(float(data[mat]["rel_l1_ours"]), 1)
        out[f"lookup_{mat}"] = pct(float(data[mat]["rel_l1_lookup_unoccluded"]), 1)
        out[f"chain_{mat}"] = pct(float(data[mat]["rel_l1_chain"]), 2 if mat == "diffuse" else 1)
    out["chain_MiB"] = fixed(float(data["diffuse"]["chain_MiB"]), 0)
    out["pem_MiB"] = fixed(float(data["diffuse"]["pem_MiB"]), 0)
    return out


@page("render-error")
def render_error_page(folder: Path) -> dict[str, str]:
    rows = read_csv(folder / "render_error.csv")
    table = md_table(
        ["material", "lights", "VSM", "Eq. 5 (pyramid) rel. L1", "pyramid look-up alone", "Eq. 5 with the exact-lobe chain",
         "chain look-up alone", "PEMs (MiB)", "chain (MiB)"],
        [[q["material"], q["lights"], q["vsm_resolution"] + "²", pct(float(q["rel_l1_ours"]), 1) + " %",
          pct(float(q["rel_l1_lookup_unoccluded"]), 1) + " %", pct(float(q["rel_l1_chain"]), 2) + " %",
          pct(float(q["rel_l1_chain_lookup_unoccluded"]), 2) + " %", fixed(float(q["pem_MiB"]), 1),
          fixed(float(q["chain_MiB"]), 1)] for q in rows])
    return {**render_error_numbers(folder), "claims_row": claims_text("render-error"), "table": table}


# ---- lobe-chain --------------------------------------------------------------------------------------------------
def lobe_chain_rows(folder: Path) -> dict[tuple, list[dict]]:
    out: dict[tuple, list[dict]] = {}
    for q in read_csv(folder / "lobe_chain.csv"):
        out.setdefault((q["env"], q["prefilter"]), []).append(q)
    return out


@numbers("lobe-chain")
def lobe_chain_numbers(folder: Path) -> dict[str, str]:
    data = lobe_chain_rows(folder)

    def col(env, pf, name="rel_l1"):
        return [100 * float(q[name]) for q in data[(env, pf)]]

    out = {}
    for env in ("sky_sun", "studio"):
        v = col(env, "pyramid-sqrtcos")
        out[f"pyramid_min_{env}"], out[f"pyramid_max_{env}"] = fixed(min(v), 0), fixed(max(v), 0)
        best = col(env, "pyramid-sqrtcos", "rel_l1_best_level")
        out[f"best_s1_{env}"] = fixed(best[0], 1)
        out[f"best_min_{env}"] = fixed(min(best), 1)
        for pf, key in (("chain-f2", "f2"), ("chain-f1.41", "f141")):
            out[f"chain_{key}_max_{env}"] = fixed(max(col(env, pf)), 1)
    v = col("sky_sun", "pyramid-sqrtcos-solid-angle")
    out["solid_angle_min"], out["solid_angle_max"] = fixed(min(v), 0), fixed(max(v), 0)
    pyr = float(data[("sky_sun", "pyramid-sqrtcos")][0]["memory_MiB"])
    for pf, key in (("chain-f2", "f2"), ("chain-f1.41", "f141")):
        out[f"memory_ratio_{key}"] = fixed(float(data[("sky_sun", pf)][0]["memory_MiB"]) / pyr, 1)
    return out


@page("lobe-chain")
def lobe_chain_page(folder: Path) -> dict[str, str]:
    rows = []
    for (env, pf), qs in lobe_chain_rows(folder).items():
        rel = [100 * float(q["rel_l1"]) for q in qs]
        best = [100 * float(q["rel_l1_best_level"]) for q in qs]
        rows.append([env, pf, str(len(qs)), f"{fixed(float(qs[0]['s_phong']), 0)} … {fixed(float(qs[-1]['s_phong']), 0)}",
                     f"{fixed(min(rel), 1)} … {fixed(max(rel), 1)} %", f"{fixed(min(best), 1)} … {fixed(max(best), 1)} %",
                     fixed(float(qs[0]["memory_MiB"]), 2)])
    table = md_table(["env", "prefilter", "exponents", "s", "rel. L1 (min … max over s)",
                      "best constant level (min … max)", "memory (MiB)"], rows)
    return {**lobe_chain_numbers(folder), "claims_row": claims_text("lobe-chain"), "table": table}


# ---- speed-accuracy ----------------------------------------------------------------------------------------------
@numbers("speed-accuracy")
def speed_accuracy_numbers(folder: Path) -> dict[str, str]:
    rows = read_csv(folder / "speed_accuracy.csv")
    out = {}
    for n in (32, 64, 128):
        auto = [q for q in rows if q["method"] == "auto" and int(q["face_size_texels"]) == n]
        worst = max(auto, key=lambda q: float(q["rel_err_max"]))
        out[f"worst_{n}"] = sci(float(worst["rel_err_max"]))
        out[f"worst_s_{n}"] = fixed(float(worst["s_phong"]), 0)
        out[f"worst_route_{n}"] = worst["method_used"]
        out[f"reference_texels_{n}"] = worst["n_reference_texels"]
    out["bound_violations"] = str(sum(int(q["bound_violations"]) for q in rows))
    return out


@page("speed-accuracy")
def speed_accuracy_page(folder: Path) -> dict[str, str]:
    rows = read_csv(folder / "speed_accuracy.csv")
    body = [[q["face_size_texels"] + "²", q["method"], fixed(float(q["s_phong"]), 0), q["method_used"], q["kernel"],
             sci(float(q["rel_err_max"])) if q["rel_err_max"] else "—",
             sci(float(q["rel_bound_max"])) if q.get("rel_bound_max") else "—", q["bound_violations"]]
            for q in rows]
    table = md_table(["face", "method", "s", "route", "kernel", "max rel. error", "largest bound", "texels above the bound"],
                     body)
    return {**speed_accuracy_numbers(folder), "claims_row": claims_text("speed-accuracy"), "table": table}


# ---- km00-render -------------------------------------------------------------------------------------------------
@numbers("km00-render")
def km00_render_numbers(folder: Path) -> dict[str, str]:
    q = {r["method"]: r for r in read_csv(folder / "km00_render_metrics.csv")}

    def p(method, col="rel_l1", d=1):
        return pct(float(q[method][col]), d)

    conv = {(r["k_multiplier_from"], r["k_multiplier_to"]): r
            for r in read_csv(folder / "km00_render_reference_convergence.csv")}
    return {"single": p("single", d=2), "single2d": p("single2d"), "lobes3": p("lobes3"),
            "lobes3_unfitted": pct(-float(q["lobes3"]["rel_bias_constant_env"]), 0),
            "rescaled": p("lobes3_rescaled", d=2), "rescaled_median": p("lobes3_rescaled", "rel_err_median", 2),
            "single_median": p("single", "rel_err_median", 2), "pyramid3": p("pyramid3"), "pyramid1": p("pyramid1"),
            "reference_convergence": sci(float(conv[("2", "4")]["rel_l1"]))}


@page("km00-render")
def km00_render_page(folder: Path) -> dict[str, str]:
    rows = read_csv(folder / "km00_render_metrics.csv")
    table = md_table(["method", "rel. L1", "median pixel error", "95th percentile", "rel. L1 under L ≡ 1",
                      "bias under L ≡ 1", "time (s)"],
                     [[q["method"], pct(float(q["rel_l1"]), 2) + " %", pct(float(q["rel_err_median"]), 2) + " %",
                       pct(float(q["rel_err_p95"]), 2) + " %", pct(float(q["rel_l1_constant_env"]), 2) + " %",
                       pct(float(q["rel_bias_constant_env"]), 2) + " %", fixed(float(q["time_s"]), 1)] for q in rows])
    conv = md_table(["supersampling from", "to", "rel. L1", "rel. L1 (θo ≤ 80°)"],
                    [["×" + q["k_multiplier_from"], "×" + q["k_multiplier_to"], sci(float(q["rel_l1"])),
                      sci(float(q["rel_l1_in_range"]))]
                     for q in read_csv(folder / "km00_render_reference_convergence.csv")])
    return {**km00_render_numbers(folder), "claims_row": claims_text("km00-render"), "table": table,
            "convergence_table": conv}


# ---- fig8 (sparse PEMs) ------------------------------------------------------------------------------------------
@numbers("fig8")
def fig8_numbers(folder: Path) -> dict[str, str]:
    rows = [q for q in read_csv(folder / "fig8_sparse.csv") if q["env"] == "sky_sun"]
    ratio = {(int(q["face_size"]), int(q["regions"])): float(q["ratio_lossless"]) for q in rows}
    return {f"ratio_{n}_{r}": fixed(ratio[(n, r)], 1) for n in (128, 256) for r in (12, 96)}


@page("fig8")
def fig8_page(folder: Path) -> dict[str, str]:
    rows = read_csv(folder / "fig8_sparse.csv")
    table = md_table(["env", "face", "regions", "dense (MiB)", "sparse lossless (MiB)", "lossless ×", "rtol 1e-6 ×",
                      "scene's levels only ×", "tiles"],
                     [[q["env"], q["face_size"] + "²", q["regions"], fixed(float(q["dense_MiB"]), 2),
                       fixed(float(q["sparse_lossless_MiB"]), 3), fixed(float(q["ratio_lossless"]), 1),
                       fixed(float(q["ratio_rtol1e-6"]), 1), fixed(float(q["ratio_scene_g_levels"]), 1), q["tiles"]]
                      for q in rows])
    return {**fig8_numbers(folder), "claims_row": claims_text("fig8"), "table": table}


# ---- cosine-lobes ------------------------------------------------------------------------------------------------
@numbers("cosine-lobes")
def cosine_lobes_numbers(folder: Path) -> dict[str, str]:
    pf = read_json(folder / "summary.json")["product_fit"]
    return {"product_fit_mean": sci(pf["abs_err_sr"]["mean"]), "paper_mean": sci(pf["paper_mean_abs_err"]),
            "paper_variance": sci(pf["paper_variance_abs_err"])}


@page("cosine-lobes")
def cosine_lobes_page(folder: Path) -> dict[str, str]:
    pf = read_json(folder / "summary.json")["product_fit"]
    rows = [["mean", sci(pf["abs_err_sr"]["mean"]), sci(pf["paper_mean_abs_err"])],
            ["variance", sci(pf["abs_err_sr"]["variance"]), sci(pf["paper_variance_abs_err"])],
            ["median", sci(pf["abs_err_sr"]["median"]), "0"],
            ["max", sci(pf["abs_err_sr"]["max"]), "—"]]
    table = md_table(["absolute error of the product fit (sr)", "this run", "Meunier et al. 2009, Sec. 4.1"], rows)
    return {**cosine_lobes_numbers(folder), "claims_row": claims_text("cosine-lobes"), "table": table,
            "fits": str(pf["n_fits"]), "per_interval": str(pf["per_interval"])}


# ---- kan-table1 --------------------------------------------------------------------------------------------------
@numbers("kan-table1")
def kan_table1_numbers(folder: Path) -> dict[str, str]:
    rows = {int(q["face_size_texels"]): q for q in read_csv(folder / "kan_table1.csv")}
    out = {}
    for n in (32, 64, 128, 256):
        out[f"kan_{n}"] = f"{float(rows[n]['kan2015_time_s']):.3g}"  # the published times, 3 significant digits
        out[f"auto_{n}"] = fixed(float(rows[n]["time_auto_s"]), 2)
    bound = max(float(rows[n]["auto_rel_bound_max"]) for n in (32, 64, 128, 256))
    out["bound_e4"] = fixed(math.ceil(bound * 1e5) / 10, 1)  # rounded up: "every bound ≤ …"
    out["exact_32"], out["exact_64"] = fixed(float(rows[32]["time_exact_s"]), 2), fixed(float(rows[64]["time_exact_s"]), 2)
    return out


@page("kan-table1")
def kan_table1_page(folder: Path) -> dict[str, str]:
    rows = read_csv(folder / "kan_table1.csv")
    table = md_table(["face", "exponents", "`auto` wall (s)", "`auto` CPU (s)", "exact gather wall (s)",
                      "largest bound", "routes", "Kán et al. Table 1 (s)"],
                     [[q["face_size_texels"] + "²", q["n_exponents"], opt(q["time_auto_s"], 2), opt(q["cpu_time_auto_s"], 2),
                       opt(q["time_exact_s"], 2), sci(float(q["auto_rel_bound_max"])) if q["auto_rel_bound_max"] else "—",
                       q["auto_methods"] or "—", q["kan2015_time_s"]] for q in rows])
    return {**kan_table1_numbers(folder), "claims_row": claims_text("kan-table1"), "table": table}


# ---- error-budget ------------------------------------------------------------------------------------------------
def budget_walks(folder: Path, order: str = "default") -> dict[tuple, list[dict]]:
    """The walks of error_budget.csv in one order, keyed by (env, material, regions), steps in order."""
    walks: dict[tuple, list[dict]] = {}
    for q in read_csv(folder / "error_budget.csv"):
        if q["order"] == order:
            walks.setdefault((q["env"], q["material"], q["regions"]), []).append(q)
    return {k: sorted(v, key=lambda q: int(q["step_index"])) for k, v in walks.items()}


def _step(walk: list[dict], step: str) -> dict:
    return next(q for q in walk if q["step"] == step)


def _inc_share(q: dict) -> str:
    return f"{pct(float(q['rel_l1_increment_frac']), 1)} % ({pct(float(q['share_of_increments_frac']), 0)} %)"


@numbers("error-budget")
def error_budget_numbers(folder: Path) -> dict[str, str]:
    walks = budget_walks(folder)
    swapped = budget_walks(folder, "swap vsm<->prefilter")
    out = {}

    def share(case, steps):
        return 100 * sum(float(q["share_of_increments_frac"]) for q in walks[case] if q["step"] in steps)

    a = [share(("sky_sun", t, r), ("prefilter", "gloss_lookup")) for t in ("diffuse", "g0.9") for r in ("6", "24", "96")]
    b = [share(("sky_sun", "g0.99", r), ("regions", "vsm")) for r in ("6", "24", "96")]
    out["pyramid_share_min"], out["pyramid_share_max"] = fixed(min(a), 0), fixed(max(a), 0)
    out["regions_vsm_share_min"], out["regions_vsm_share_max"] = fixed(min(b), 0), fixed(max(b), 0)
    for r in ("6", "96"):
        out[f"g099_final_{r}"] = pct(float(walks[("sky_sun", "g0.99", r)][-1]["rel_l1_vs_ref_frac"]), 1)
        out[f"probe_vsm_{r}"] = pct(float(_step(walks[("probe", "diffuse", r)], "vsm")["rel_l1_increment_frac"]), 0)
    horizon = {r: pct(float(_step(walks[("sky_sun", "g0.9", r)], "horizon")["rel_l1_increment_frac"]), 0)
               for r in ("6", "24", "96")}
    assert horizon["6"] == horizon["96"], horizon  # the text gives one number for both
    out["horizon_24"], out["horizon_6_96"] = horizon["24"], horizon["6"]
    # the swap paragraph
    for case, key in ((("sky_sun", "g0.9", "24"), "sky"), (("probe", "diffuse", "24"), "probe")):
        for walk, which in ((walks[case], "default"), (swapped[case], "swap")):
            for q in walk[1:]:
                out[f"swap_{key}_{which}_{q['step']}"] = _inc_share(q)
        out[f"swap_{key}_final"] = pct(float(walks[case][-1]["rel_l1_vs_ref_frac"]), 1)
    # the texel-limit paragraph
    trows = {(q["env"], q["material"], q["face_size_texels"]): q
             for q in read_csv(folder / "error_budget_texel_limit.csv")}
    rel = {k: 100 * float(q["rel_l1_vs_ref_frac"]) for k, q in trows.items()}
    est = {k: 100 * float(q["ref_err_estimate_frac"]) for k, q in trows.items()}
    cases = [(e, t) for e in ("sky_sun", "probe") for t in ("diffuse", "g0.9", "g0.99")]
    drop = [rel[(e, t, "32")] / rel[(e, t, "64")] for e, t in cases]
    rest = [(e, t, "64") for e, t in cases if (e, t) != ("probe", "g0.99")]
    out["texel_drop_min"], out["texel_drop_max"] = fixed(min(drop), 1), fixed(max(drop), 1)
    out["texel_64_min"], out["texel_64_max"] = fixed(min(rel[k] for k in rest), 2), fixed(max(rel[k] for k in rest), 2)
    out["texel_probe_g099_32"] = fixed(rel[("probe", "g0.99", "32")], 2)
    out["texel_probe_g099_64"] = fixed(rel[("probe", "g0.99", "64")], 2)
    out["texel_estimate_min"] = fixed(min(est[k] for k in rest), 2)
    out["texel_estimate_max"] = fixed(max(est[k] for k in rest), 2)
    return out


@page("error-budget")
def error_budget_page(folder: Path) -> dict[str, str]:
    walks = budget_walks(folder)
    steps = [q["step"] for q in next(iter(walks.values()))[1:]]
    rows = []
    for (env, mat, regions), walk in walks.items():
        total = sum(float(q["rel_l1_increment_frac"]) for q in walk[1:])
        rows.append([env, mat, regions, f"**{pct(float(walk[-1]['rel_l1_vs_ref_frac']), 1)} %**"]
                    + [_inc_share(q) for q in walk[1:]] + [pct(total, 1) + " %"])
    table = md_table(["env", "material", "regions", "Eq. 5 vs ref."] + steps + ["Σ increments"], rows)
    texel = md_table(["env", "material", "one region per texel at face size", "regions", "rel. L1 vs ref.",
                      "reference's own estimate"],
                     [[q["env"], q["material"], q["face_size_texels"] + "²", q["regions"],
                       pct(float(q["rel_l1_vs_ref_frac"]), 2) + " %", pct(float(q["ref_err_estimate_frac"]), 2) + " %"]
                      for q in read_csv(folder / "error_budget_texel_limit.csv")])
    return {**error_budget_numbers(folder), "budget_table": table, "texel_table": texel}


# ---- method-zoo --------------------------------------------------------------------------------------------------
ZOO_MATERIALS = ("diffuse", "ggx0.1", "ggx0.3", "ggx0.6", "phong1", "phong16", "phong256")


def zoo_means(folder: Path) -> dict[tuple, tuple]:
    """(scene, method, material) → mean (rel. L1, p99, memory bytes) over the environments, applicable cases only."""
    acc: dict[tuple, list] = {}
    for q in read_csv(folder / "method_zoo.csv"):
        if q["applicable"] == "True":
            acc.setdefault((q["scene"], q["method"], q["material"]), []).append(
                (float(q["rel_l1_frac"]), float(q["p99_rel_error_frac"]), float(q["memory_bytes"])))
    return {k: tuple(statistics.fmean(c) for c in zip(*v)) for k, v in acc.items()}


def mib(value_bytes: float) -> str:
    """Memory in MiB as the method-zoo tables print it: 3 significant digits, at most 4 decimals."""
    v = value_bytes / MIB
    return f"{v:.3g}" if v >= 0.01 else fixed(v, 4)


@numbers("method-zoo")
def method_zoo_numbers(folder: Path) -> dict[str, str]:
    rows = read_csv(folder / "method_zoo_karis.csv")
    teapot = [float(q["n_v_r_over_split_sum"]) for q in rows if q["scene"] == "teapot"]
    sphere = [float(q["n_v_r_over_split_sum"]) for q in rows if q["scene"] == "sphere"]
    out = {"karis_cases": str(len(rows)), "karis_holds": str(sum(q["n_v_r_larger"] == "True" for q in rows)),
           "teapot_ratio_min": fixed(min(teapot), 1), "teapot_ratio_max": fixed(max(teapot), 1),
           "sphere_ratio_max": fixed(max(sphere), 1), "sphere_ratio_min": fixed(min(sphere), 2)}
    for mat in ("ggx0.1", "ggx0.3", "ggx0.6"):
        v = [100 * float(q["n_v_r_rel_l1_frac"]) for q in rows if q["scene"] == "teapot" and q["material"] == mat]
        out[f"teapot_nvr_min_{mat}"], out[f"teapot_nvr_max_{mat}"] = fixed(min(v), 1), fixed(max(v), 1)
    return out


@page("method-zoo")
def method_zoo_page(folder: Path) -> dict[str, str]:
    means = zoo_means(folder)
    build = {(q["scene"], q["method"]): q["build_s"] for q in read_csv(folder / "build_time_as_printed.csv")}
    out = {}
    for scene in ("sphere", "teapot"):
        methods = [m for (s, m) in build if s == scene]
        rows = []
        for method in methods:
            cells = []
            for mat in ZOO_MATERIALS:
                v = means.get((scene, method, mat))
                cells.append(f"{pct(v[0], 1)} % ({pct(v[1], 0)} %)" if v else "n/a")
            mem = statistics.fmean(v[2] for (s, m, _), v in means.items() if s == scene and m == method)
            rows.append([method] + cells + [build[(scene, method)], mib(mem)])
        out[f"{scene}_table"] = md_table(["method", *ZOO_MATERIALS, "build (s)", "memory (MiB)"], rows)
    cm = [q for q in read_csv(folder / "method_zoo_cmgen.csv") if q["applicable"] == "True"]
    cells = []
    for mat in ZOO_MATERIALS:
        sel = [q for q in cm if q["method"] == "cmgen" and q["material"] == mat]
        if sel:
            cells.append(f"{mat} {pct(statistics.fmean(float(q['rel_l1_frac']) for q in sel), 1)} % "
                         f"({pct(statistics.fmean(float(q['p99_rel_error_frac']) for q in sel), 0)} %)")
    out["cmgen_sphere"] = ", ".join(cells)
    saved = {(q["scene"], q["env"], q["material"], q["method"]): float(q["rel_l1_frac"])
             for q in read_csv(folder / "method_zoo.csv") if q["applicable"] == "True"}
    gap = max(abs(float(q["rel_l1_frac"]) - saved[(q["scene"], q["env"], q["material"], q["method"])])
              for q in cm if q["method"] == "split-sum")
    out["cmgen_split_sum_agreement"] = f"{sci(gap, 1)} in rel. L1 (the tree's bound, not the dense sum)"
    return {**method_zoo_numbers(folder), **out}


# ---- method-zoo at engine size --------------------------------------------------------------------------------
ZOO_256_METHODS = ("split-sum", "split-sum-is-16", "split-sum-is-64", "split-sum-is-256", "split-sum-is-1024",
                   "split-sum-fis-16", "split-sum-fis-64", "cmgen", "ggx-phong-pem+vsm", "pyramid+vsm", "exact-lobe",
                   "sh9")
#: a cell "moved" between 32² and 256² faces when its mean rel. L1 changed by at least this many points and this share
MOVED_POINTS, MOVED_SHARE = 2.0, 0.2


def _zoo_steps(folder: Path, scene: str) -> dict[tuple, float]:
    """(method, material, step) → mean rel. L1 increment over the environments (fraction)."""
    acc: dict[tuple, list] = {}
    for q in read_csv(folder / "method_zoo_budget.csv"):
        if q["scene"] == scene:
            acc.setdefault((q["method"], q["material"], q["step"]), []).append(float(q["rel_l1_increment_frac"]))
    return {k: statistics.fmean(v) for k, v in acc.items()}


@numbers("method-zoo-256")
def method_zoo_256_numbers(folder: Path) -> dict[str, str]:
    means = zoo_means(folder)
    small = zoo_means(DATA / "method-zoo")
    steps = _zoo_steps(folder, "sphere")
    out = {}
    for method in ZOO_256_METHODS:
        for mat in ZOO_MATERIALS:
            for tag, src in (("256", means), ("32", small)):
                v = src.get(("sphere", method, mat))
                out[f"{method}_{mat}_{tag}"] = pct(v[0], 1) if v else "n/a"
    for mat in ("ggx0.1", "ggx0.3", "ggx0.6"):
        for method in ("split-sum", "split-sum-is-256", "split-sum-fis-64"):
            for step in ("split_sum", "n_v_r", "prefilter", "mip", "dfg_table"):
                v = steps.get((method, mat, step))
                if v is not None:
                    out[f"{method}_{mat}_{step}"] = pct(v, 1)
    karis = read_csv(folder / "method_zoo_karis.csv")
    out["karis_cases"] = str(len(karis))
    out["karis_holds"] = str(sum(q["n_v_r_larger"] == "True" for q in karis))
    # cmgen at 32² is a run of its own (method_zoo_cmgen.csv of the 32² folder)
    cm32: dict[str, list] = {}
    for q in read_csv(DATA / "method-zoo" / "method_zoo_cmgen.csv"):
        if q["applicable"] == "True" and q["method"] == "cmgen" and q["scene"] == "sphere":
            cm32.setdefault(q["material"], []).append(float(q["rel_l1_frac"]))
    gaps = []
    for mat in ("ggx0.1", "ggx0.3", "ggx0.6"):
        out[f"cmgen_{mat}_32"] = pct(statistics.fmean(cm32[mat]), 1)
        out[f"cmgen_{mat}_chain"] = pct(steps[("cmgen", mat, "prefilter")], 1)
        out[f"split-sum_{mat}_chain"] = pct(steps[("split-sum", mat, "prefilter")] + steps[("split-sum", mat, "mip")], 1)
        gaps.append(abs(means[("sphere", "cmgen", mat)][0] - means[("sphere", "split-sum", mat)][0]))
    out["cmgen_vs_split_sum"] = f"{100 * max(gaps):.1f}"
    return out


def _zoo_walks(folder: Path, scene: str) -> dict[tuple, list]:
    """(env, material, method) → the budget walk's rows of one scene, in their order."""
    walks: dict[tuple, list] = {}
    for q in read_csv(folder / "method_zoo_budget.csv"):
        if q["scene"] == scene:
            walks.setdefault((q["env"], q["material"], q["method"]), []).append(q)
    return walks


@page("method-zoo-256")
def method_zoo_256_page(folder: Path) -> dict[str, str]:
    means = zoo_means(folder)
    small = zoo_means(DATA / "method-zoo")
    build: dict[tuple, list] = {}
    for q in read_csv(folder / "method_zoo.csv"):
        if q["applicable"] == "True":
            build.setdefault((q["scene"], q["method"]), []).append(float(q["build_time_s"]))
    out, moved = {}, []
    for scene in ("sphere", "teapot"):
        rows = []
        for method in ZOO_256_METHODS:
            if not any((scene, method, mat) in means for mat in ZOO_MATERIALS):
                continue
            cells = []
            for mat in ZOO_MATERIALS:
                v = means.get((scene, method, mat))
                cells.append(f"{pct(v[0], 1)} % ({pct(v[1], 0)} %)" if v else "n/a")
                w = small.get((scene, method, mat))
                if v and w and abs(v[0] - w[0]) * 100 >= MOVED_POINTS and abs(v[0] - w[0]) >= MOVED_SHARE * w[0]:
                    moved.append([scene, method, mat, pct(w[0], 1) + " %", pct(v[0], 1) + " %",
                                  signed(f"{100 * (v[0] - w[0]):+.1f}")])
            mem = statistics.fmean(v[2] for (s, m, _), v in means.items() if s == scene and m == method)
            rows.append([method] + cells + [f"{statistics.fmean(build[(scene, method)]):.3g}", mib(mem)])
        out[f"{scene}_table"] = md_table(["method", *ZOO_MATERIALS, "build (s)", "memory (MiB)"], rows)
    steps = _zoo_steps(folder, "sphere")
    names = ("split_sum", "n_v_r", "prefilter", "mip", "dfg_table")
    walk = []
    for method in ("split-sum", "split-sum-is-16", "split-sum-is-64", "split-sum-is-256", "split-sum-is-1024",
                   "split-sum-fis-16", "split-sum-fis-64"):
        for mat in ("ggx0.1", "ggx0.3", "ggx0.6"):
            if (method, mat, "n_v_r") in steps:
                walk.append([method, mat] + [pct(steps[(method, mat, k)], 1) + " %" if (method, mat, k) in steps
                                             else "—" for k in names]
                            + [pct(means[("sphere", method, mat)][0], 1) + " %"])
    # the teapot: which step of each walk is the largest (the 32² run: missing visibility in 160 of 225)
    walks = _zoo_walks(folder, "teapot")
    largest = [max(w, key=lambda q: float(q["rel_l1_increment_frac"]))["step"] for w in walks.values()]
    vis = {}
    for (env, mat, method), w in walks.items():
        for q in w:
            if q["step"] == "visibility":
                vis.setdefault(mat, []).append(float(q["bias_increment_frac"]))
    out.update(teapot_walks=str(len(largest)), teapot_vis_largest=str(largest.count("visibility")),
               teapot_vis_bias=", ".join(f"{mat} {signed(pct(statistics.fmean(v), 1))} %" for mat, v in vis.items()))
    out.update({f"{scene}_moved": str(sum(r[0] == scene for r in moved)) for scene in ("sphere", "teapot")})
    return {**method_zoo_256_numbers(folder), **out,
            "moved_table": md_table(["scene", "method", "material", "32² faces", "256² faces", "change (points)"],
                                    moved),
            "walk_table": md_table(["method", "material", *names, "total rel. L1"], walk)}


# ---- transcribed runs: tables as printed -------------------------------------------------------------------------
@page("reference-renderer")
def reference_renderer_page(folder: Path) -> dict[str, str]:
    est = md_table(["case", "rel. L1 estimated", "actual", "p99 estimated", "actual p99", "pixels above their bound"],
                   [[q["case"], q["rel_l1_estimated_pct"] + " %", q["rel_l1_actual_pct"] + " %",
                     q["p99_estimated_pct"] + " %", q["p99_actual_pct"] + " %", q["pixels_above_bound_pct"] + " %"]
                    for q in read_csv(folder / "estimate_check.csv")])
    cost = md_table(["case", "wall", "CPU", "rays", "finest cells per face", "quadrature M per block", "est. rel. L1",
                     "p99", "peak memory main (cumulative) / worker", "load"],
                    [[q["case"], q["wall_s"] + " s", q["cpu_s"] + " s", q["rays_millions"] + " M",
                      q["finest_cells_per_face"], q["quadrature_M_per_block"], q["est_rel_l1_pct"] + " %",
                      q["p99_pct"] + " %", f"{q['peak_memory_main_MB']} / {q['peak_memory_worker_MB']} MB",
                      q["load_1min"]] for q in read_csv(folder / "cost.csv")])
    eq = read_csv(folder / "equal_error.csv")
    equal = md_table(_equal_columns(False), [_equal_row(q, False) for q in eq])
    ratios = [float(q["ratio_ref_to_mitsuba"]) for q in eq]
    total = sum(float(q["ref_wall_s"]) for q in eq) / sum(float(q["mitsuba_wall_s"]) for q in eq)
    # the same benchmark matched to the reference's actual error (two runs: the narrow GGX lobes, then the others)
    act = [q for f in ("equal_error_actual_narrow.csv", "equal_error_actual_wide.csv") if (folder / f).is_file()
           for q in read_csv(folder / f)]
    actual = md_table(_equal_columns(True), [_equal_row(q, True) for q in act])
    a_ratios = [float(q["ratio_ref_to_mitsuba"]) for q in act]
    over = [float(q["ref_est_rel_l1"]) / float(q["ref_actual_rel_l1"]) for q in act]
    by_est = {q["material"]: int(q["mitsuba_spp"]) for q in eq}
    spp = [int(q["mitsuba_spp"]) / by_est[q["material"]] for q in act if q["material"] in by_est]
    sweep = {**_sweep_numbers(folder, "sweep.csv", "sweep"), **_sweep_numbers(folder, "sweep_128.csv", "sweep128")}
    return {**sweep, "estimate_table": est, "cost_table": cost, "equal_error_table": equal,
            "equal_error_total": f"{total:.2f}×", "equal_error_range": f"{min(ratios):.2f}–{max(ratios):.2f}×",
            "equal_error_slower": str(sum(r > 1.0 for r in ratios)), "equal_error_cases": str(len(ratios)),
            "equal_actual_table": actual, "equal_actual_cases": str(len(act)),
            "equal_actual_total": f"{sum(float(q['ref_wall_s']) for q in act) / sum(float(q['mitsuba_wall_s']) for q in act):.2f}×",
            "equal_actual_range": f"{min(a_ratios):.2f}–{max(a_ratios):.2f}×",
            "equal_actual_verdict": ("faster in every case: **the target holds**" if max(a_ratios) <= 1.0 else
                                     f"slower in {sum(r > 1.0 for r in a_ratios)} of them: the target is not met"),
            "spp_ratio": f"{min(spp):.1f}–{max(spp):.1f}×",
            "estimate_over_actual": f"{min(over):.1f}–{max(over):.1f}×"}


def _equal_columns(actual: bool) -> list[str]:
    """Columns of bench_equal_error.py's tables (``actual``: matched to the actual error, its column added)."""
    return ["material", "reference wall", "est. rel. L1", *(["actual rel. L1 (± finer run's est.)"] if actual else []),
            "Mitsuba spp", "Mitsuba wall", "Mitsuba noise", "reference − Mitsuba (rel. L1)", "reference / Mitsuba time"]


def _equal_row(q: dict, actual: bool) -> list[str]:
    """One row of bench_equal_error.py's CSV for :func:`_equal_columns`."""
    act = [f"{pct(float(q['ref_actual_rel_l1']), 3)} ± {pct(float(q['finer_run_est_rel_l1']), 3)} %"] if actual else []
    return [q["material"], f"{float(q['ref_wall_s']):.1f} s", f"{pct(float(q['ref_est_rel_l1']), 3)} %", *act,
            q["mitsuba_spp"], f"{float(q['mitsuba_wall_s']):.1f} s", f"{pct(float(q['mitsuba_noise_rel_l1']), 3)} %",
            f"{pct(float(q['ref_vs_mitsuba_rel_l1']), 3)} %", f"{float(q['ratio_ref_to_mitsuba']):.2f}×"]


def _sweep_numbers(folder: Path, name: str, key: str) -> dict[str, str]:
    """Issue 40's sweep (benchmarks/bench_reference_quadrature.py's CSV ``name``): per material the three ways' times
    (repeated on the material's rows), totals and ratios, as ``{key}_…`` template keys."""
    sw = read_csv(folder / name)
    per_mat = {q["material"]: q for q in sw}
    ways = ("numpy_single", "compiled_single", "compiled_sweep")
    tot = {(w, u): sum(float(q[f"{w}_{u}_s"]) for q in per_mat.values()) for w in ways for u in ("wall", "cpu")}
    by_mat = {k: float(q["numpy_single_wall_s"]) / float(q["compiled_sweep_wall_s"]) for k, q in per_mat.items()}
    lo, hi = min(by_mat, key=by_mat.get), max(by_mat, key=by_mat.get)
    within = max(float(q["diff_rel_l1"]) / (float(q["est_rel_l1_baseline"]) + float(q["est_rel_l1_sweep"])) for q in sw)
    sweep = {f"{key}_images": str(len(sw)), f"{key}_materials": str(len(per_mat)), f"{key}_size": sw[0]["size_px"],
             **{f"{key}_{w}_{u}": f"{tot[(w, u)]:.0f} s" for w in ways for u in ("wall", "cpu")},
             f"{key}_ratio_wall": f"{tot[('numpy_single', 'wall')] / tot[('compiled_sweep', 'wall')]:.1f}×",
             f"{key}_ratio_cpu": f"{tot[('numpy_single', 'cpu')] / tot[('compiled_sweep', 'cpu')]:.1f}×",
             f"{key}_ratio_compiled": f"{tot[('numpy_single', 'wall')] / tot[('compiled_single', 'wall')]:.1f}×",
             f"{key}_mat_lo": f"{by_mat[lo]:.1f}× ({lo})", f"{key}_mat_hi": f"{by_mat[hi]:.1f}× ({hi})",
             f"{key}_converged_cap": "Every" if all(q["sweep_converged"] == "True" for q in sw) else "Not every",
             f"{key}_run": next(f"commit {r['commit']}, load {r['load']}" for r in read_json(folder / "run.json")["runs"]
                               if name in r["files"]),
             f"{key}_est_max": f"{pct(max(float(q['est_rel_l1_sweep']) for q in sw), 2)} %",
             f"{key}_within": f"{within:.2f}"}
    return sweep


@page("cross-validate")
def cross_validate_page(folder: Path) -> dict[str, str]:
    rows = []
    for q in read_csv(folder / "cross_validate.csv"):
        rows.append([q["scene"], q["env"], q["material"], q["mitsuba_bsdf"], q["smith"], q["rel_l1_pct"] + " %",
                     signed(q["bias_pct"]) + " %", q["mitsuba_noise_pct"] + " %", signed(q["excess_pct"]) + " %",
                     q["ref_err_estimate_pct"] + " %", q["smith_term_pct"] + " %" if q["smith_term_pct"] else "",
                     q["ref_time_s"] or "(same)"])
    return {"table": md_table(["scene", "env", "material", "Mitsuba BSDF", "Smith", "rel. L1 ref vs Mitsuba", "bias",
                               "Mitsuba noise", "excess", "reference's own estimate", "Smith term", "ref. time (s)"],
                              rows)}


@page("big-probes")
def big_probes_page(folder: Path) -> dict[str, str]:
    rows = []
    for q in read_csv(folder / "probe_sizes.csv"):
        rss = (q["peak_rss_MiB"] + " MiB" if q["peak_rss_MiB"] else q["peak_rss_GiB"] + " GiB" if q["peak_rss_GiB"]
               else "—")
        if q["peak_rss_times_input"]:
            rss += f" ({q['peak_rss_times_input']}× input)"
        rows.append([f"{q['probe']} {q['input']}", q["step"], q["load_1min"] or "11.7–16.4 (the whole run)", q["wall_s"],
                     q["cpu_s"] or "—", rss, q["goal"] or "—"])
    return {"table": md_table(["probe (lat-long, float32 RGB, DWAB)", "step", "load", "wall s", "CPU s",
                               "peak RSS (process)", "goal"], rows)}


def _cell(q: dict | None, err: bool = False) -> str:
    """One tool's cell of the bench_peer tables as the bench prints it."""
    if q is None:
        return "—"
    if q["status"] == "killed":
        return "—" if err else "> 60 (killed)"
    return q["max_rel_err"] if err else f"{q['wall_s']} / {q['cpu_s']}"


def bench_peer_values(folder: Path) -> dict[str, str]:
    """The tables and numbers of one bench_peer.py run (``benchmarks/bench_peer.py --save-dir``)."""
    cells = {(q["scene"], q["face_size_texels"], q["exponents"], q["tool"], q["mode"]): q
             for q in read_csv(folder / "cells.csv")}
    out = {}
    for scene, key in (("sky + sun", "sky"), ("courtyard", "courtyard")):
        rows = []
        for v in read_csv(folder / "verdicts.csv"):
            if v["scene"] != scene:
                continue
            k = (scene, v["face_size_texels"], v["exponents"])

            def c(tool, mode="process", err=False):
                return _cell(cells.get(k + (tool, mode)), err)

            rows.append([v["face_size_texels"] + "²", "8 exponents" if v["exponents"] == "set8" else v["exponents"],
                         c("lab numpy", "in-process"), c("lab numpy"), c("lab numpy", "in-process", True),
                         c("lab compiled", "in-process"), c("lab compiled"), c("lab compiled", "in-process", True),
                         c("cmft"), c("cmft", err=True), c("cmft fixed"), c("cmft fixed", err=True),
                         v["in_process_compiled_le_cmft"], v["process_better_kernel_le_cmft"]])
        out[f"{key}_table"] = md_table(
            ["face", "s", "lab numpy in-process", "lab numpy process", "lab numpy err", "lab compiled in-process",
             "lab compiled process", "lab compiled err", "cmft", "cmft err", "cmft fixed", "cmft fixed err",
             "in-process (compiled) ≤ cmft", "process (better kernel) ≤ cmft"], rows)
    out["startup_floor"] = "; ".join(f"{q['what']} {q['wall_s']} s wall / {q['cpu_s']} s CPU"
                                     for q in read_csv(folder / "startup_floor.csv"))
    cc = {q["run"]: q for q in read_csv(folder / "compile_cost.csv")}
    out["compile_cost"] = (f"cold {cc['cold']['wall_s']} s wall / {cc['cold']['cpu_s']} s CPU; warm "
                           f"{cc['warm 1']['wall_s']} / {cc['warm 1']['cpu_s']} s and "
                           f"{cc['warm 2']['wall_s']} / {cc['warm 2']['cpu_s']} s")
    out["native_table"] = md_table(
        ["face", "kernel", "wall s", "CPU s", "peak RSS (largest process) GiB", "routes", "largest bound"],
        [[q["face_size_texels"] + "²", q["kernel"], q["wall_s"], q["cpu_s"], q["peak_rss_largest_process_GiB"],
          q["routes"], q["largest_bound"]] for q in read_csv(folder / "native_8_exponents.csv")])
    out["interpreter_floor"] = "; ".join(f"{q['scene']} {q['face_size_texels']}² {q['wall_s']} s"
                                         for q in read_csv(folder / "interpreter_floor.csv"))
    peak = {q["what"]: q["giga_per_s"] for q in read_csv(folder / "machine_peak.csv")}
    out["peak_tight"], out["peak_dot"] = peak["multiply-adds, tight loop"], peak["multiply-adds, dot product in L1"]
    out["pairs_per_second"] = "; ".join(
        f"{q['scene']} {q['face_size_texels']}² s={'8 exponents' if q['exponents'] == 'set8' else q['exponents']} "
        f"{q['kernel']} {q['giga_pairs_per_s_per_core']} G" for q in read_csv(folder / "pairs_per_second.csv"))
    return out


@page("bench-peer")
def bench_peer_page(folder: Path) -> dict[str, str]:
    out = bench_peer_values(folder)
    verdicts = read_csv(folder / "verdicts.csv")
    for col, key in (("in_process_compiled_le_cmft", "inproc"), ("process_better_kernel_le_cmft", "proc")):
        v = [q[col] for q in verdicts]
        out[f"{key}_targets"] = str(sum(not x.startswith("no target") for x in v))
        out[f"{key}_met"] = str(sum(x.startswith("yes") for x in v))
        out[f"{key}_missed"] = "; ".join(
            f"{q['scene']} {q['face_size_texels']}², s = {q['exponents']}: {q[col]}" for q in verdicts
            if q[col].startswith("no ") and not q[col].startswith("no target")) or "none"
    out["cells"] = str(len(verdicts))
    return out


@page("bench-peer-aot")
def bench_peer_aot_page(folder: Path) -> dict[str, str]:
    out = bench_peer_values(folder)
    out["native_quiet_table"] = md_table(
        ["face", "kernel", "wall", "CPU (user + sys)", "peak RSS", "routes", "largest bound"],
        [[q["face_size_texels"] + "²", q["kernel"], q["wall"], q["cpu_user_plus_sys"], q["peak_rss"], q["routes"],
          q["largest_bound"]] for q in read_csv(folder / "native_8_exponents_2026-12-02.csv")])
    out["probes_table"] = md_table(
        ["probe", "`auto` NumPy wall / CPU s", "`auto` compiled", "forced `sh` (misses rtol) NumPy / compiled wall",
         "split NumPy / compiled wall", "auto ÷ split", "auto ÷ forced sh"],
        [[q["probe"], f"{q['auto_numpy_wall_s']} / {q['auto_numpy_cpu_s']}",
          f"{q['auto_compiled_wall_s']} / {q['auto_compiled_cpu_s']}",
          f"{q['forced_sh_numpy_wall_s']} / {q['forced_sh_compiled_wall_s']} ({q['forced_sh_bound']})",
          f"{q['split_numpy_wall_s']} / {q['split_compiled_wall_s']}",
          f"{q['auto_over_split_numpy']} / {q['auto_over_split_compiled']}",
          f"{q['auto_over_forced_sh_numpy']} / {q['auto_over_forced_sh_compiled']}"]
         for q in read_csv(folder / "probes_native_2026-12-02.csv")])
    return out


# ---- occlusion-zoo -----------------------------------------------------------------------------------------------
OCC_INPUTS = ("oracle", "screen-space")


def _occ_mean(rows, key, **match) -> float | None:
    vals = [float(q[key]) for q in rows if all(q[k] == v for k, v in match.items())]
    return statistics.fmean(vals) if vals else None


def _occ_cell(rows, key, decimals=1, **match) -> str:
    v = _occ_mean(rows, key, **match)
    return pct(v, decimals) if v is not None else "n/a"


#: the scenes of the occlusion zoo as the page names them
OCC_SCENE_NAMES = {"teapot": "the teapot on the ground", "crevice": "a crevice", "bumpy": "a bumpy cluster",
                   "normal-mapped": "a normal-mapped quad"}
#: scenes whose only occluder is the surface's own geometric horizon (a normal map tilts the shading normal): their
#: missing visibility is small on wide lobes (2.4 % on the diffuse material), so shares of it swing by hundreds of
#: percent; the page's means of shares over scenes leave them out (their rows are in the per-scene tables)
OCC_HORIZON_ONLY = ("normal-mapped",)
#: the per-cost pick of a scene and material: the cheapest method (input bytes per pixel) on the Pareto front whose
#: share given back is within this many points (a fraction) of the most any method gives back there
OCC_PICK_MARGIN = 0.10


def _occ_front(rows, methods, inputs=("oracle",), **match) -> list[tuple[int, float, str]]:
    """The Pareto front of (input bytes per pixel ↓, mean share given back ↑) over ``methods`` fed each of
    ``inputs`` on the rows matching ``match``: (bytes, given back, label), cheapest first; the label is the method,
    with the input kind in brackets where ``inputs`` has several.  ``none`` (0 B, 0 %) is a point: where every method
    is worse than no occlusion the front is ``none`` alone."""
    pts = [(0, 0.0, "none")]
    for m in methods:
        for kind in inputs:
            v = _occ_mean(rows, "given_back_frac", method=m, inputs=kind, **match)
            if v is not None and m != "none":
                label = m if len(inputs) == 1 else f"{m} ({kind.replace('shadow-map:', '')})"
                pts.append((int(_occ_mean(rows, "input_bytes_per_pixel", method=m, inputs=kind, **match)), v,
                            label))
    pts.sort(key=lambda t: (t[0], -t[1], t[2]))
    front, best = [], -math.inf
    for b, v, m in pts:
        if v > best:
            front.append((b, v, m))
            best = v
    return front


def _occ_pick(front) -> tuple[int, float, str]:
    """The cheapest point (bytes, given back, method) of a front within :data:`OCC_PICK_MARGIN` of its most given
    back."""
    top = max(v for _, v, _ in front)
    return next(t for t in front if t[1] >= top - OCC_PICK_MARGIN)


def _occ_pick_cell(t) -> str:
    b, v, m = t
    return f"`{m}` ({b} B, {pct(v, 0)} %)"


def _occ_scale_check(rows, big) -> dict[str, str]:
    """The same cases at 24² and 64² px: the missing visibility, the shares given back and the method that gives back
    most (oracle inputs) per scene, environment and material."""
    key = ("scene", "env", "material", "method", "inputs")
    small = {tuple(q[k] for k in key): q for q in rows}
    pairs = [(small[tuple(q[k] for k in key)], q) for q in big]
    miss = [abs(float(b["missing_visibility_rel_l1_frac"]) - float(a["missing_visibility_rel_l1_frac"]))
            for a, b in pairs if (b["method"], b["inputs"]) == ("none", "oracle")]
    gap = sorted(abs(float(b["given_back_frac"]) - float(a["given_back_frac"])) for a, b in pairs
                 if b["method"] != "none")

    def best(side):
        out = {}
        for q in (p[side] for p in pairs):
            if q["inputs"] == "oracle" and q["method"] != "none":
                c = (q["scene"], q["env"], q["material"])
                out[c] = max(out.get(c, (-math.inf, "")), (float(q["given_back_frac"]), q["method"]))
        return out

    b24, b64 = best(0), best(1)
    moved = [c for c in b24 if b24[c][1] != b64[c][1]]
    return {"scale_cases": ", ".join(sorted({f"{q['scene']}/{q['env']}" for q in big})),
            "scale_missing": pct(max(miss), 1),
            "scale_median": pct(statistics.median(gap), 1), "scale_p90": pct(gap[int(0.9 * len(gap))], 1),
            "scale_best": f"{len(b24) - len(moved)} of {len(b24)}",
            "scale_moved": "; ".join(f"{'/'.join(c)}: `{b24[c][1]}` {pct(b24[c][0], 0)} % at 24², "
                                     f"`{b64[c][1]}` {pct(b64[c][0], 0)} % at 64²" for c in sorted(moved)) or "none"}


@page("occlusion-zoo")
def occlusion_zoo_page(folder: Path) -> dict[str, str]:
    rows = [q for q in read_csv(folder / "occlusion_zoo.csv") if q["applicable"] == "True"]
    meta = read_json(folder / "occlusion_zoo_meta.json")
    mats = [m for m in meta["settings"]["materials"] if any(q["material"] == m for q in rows)]
    scenes = meta["scenes_run"]
    methods = list(dict.fromkeys(q["method"] for q in rows))
    plain = [m for m in methods if not m.startswith("regions")]
    shares = [q for q in rows if q["scene"] not in OCC_HORIZON_ONLY]  # means of shares: OCC_HORIZON_ONLY
    occluded = [sc for sc in scenes if sc not in OCC_HORIZON_ONLY]
    out = {}
    out["given_back_table"] = md_table(
        ["method", *mats], [[m] + [" / ".join(_occ_cell(shares, "given_back_frac", method=m, material=mat, inputs=k)
                                              for k in OCC_INPUTS) for mat in mats] for m in plain])
    out["rel_l1_table"] = md_table(
        ["method", *scenes], [[m] + [_occ_cell(rows, "rel_l1_frac", method=m, scene=sc, inputs="oracle")
                                     for sc in scenes] for m in methods])
    region = sorted({(q["method"], q["inputs"]) for q in rows if q["method"].startswith("regions")})
    out["region_table"] = md_table(
        ["method", "visible fractions", *mats],
        [[m, k] + [_occ_cell(shares, "given_back_frac", method=m, material=mat, inputs=k) for mat in mats]
         for m, k in region])
    dis = read_csv(folder / "occlusion_zoo_disagreements.csv")
    out["disagreement_table"] = md_table(
        ["choice", "inputs", "a", "b", "rel. L1 a / b", "cases a closer / b closer", "closer",
         "largest gap b − a (at)"],
        [[q["choice"], q["inputs"], f"`{q['method_a']}`", f"`{q['method_b']}`",
          f"{pct(float(q['mean_rel_l1_a_frac']), 2)} / {pct(float(q['mean_rel_l1_b_frac']), 2)} %",
          f"{q['a_closer_cases']} / {q['b_closer_cases']} of {q['n_cases']}",
          q["closer"] if q["closer"] == "tie" else f"`{q['closer']}`",
          f"{signed(pct(float(q['worst_case_gap_frac']), 2))} % ({q['worst_case']})"] for q in dis])
    missing = {sc: _occ_mean(rows, "missing_visibility_rel_l1_frac", method="none", inputs="oracle", scene=sc)
               for sc in scenes}
    out["missing_by_scene"] = ", ".join(f"{sc} {pct(v, 1)} %" for sc, v in missing.items())
    out["missing_range"] = (f"{pct(min(missing[sc] for sc in occluded), 0)}–{pct(max(missing[sc] for sc in occluded), 0)}"
                            f" % on the scenes with occluders")
    out["regions_diffuse"] = _occ_cell(shares, "given_back_frac", 0, method="regions-exact-6", material="diffuse",
                                       inputs="oracle") + " %"
    lag = next(q for q in read_csv(folder / "occlusion_zoo_disagreements.csv")
               if (q["method_a"], q["method_b"], q["inputs"]) == ("lagarde2014-alpha", "lagarde2014-r", "oracle"))
    out["lagarde_alpha_closer"] = (f"{lag['a_closer_cases']} of the "
                                   f"{int(lag['a_closer_cases']) + int(lag['b_closer_cases'])}")
    best = {}
    for mat in mats:
        cand = [(_occ_mean(shares, "given_back_frac", method=m, material=mat, inputs="oracle"),
                 -(_occ_mean(shares, "input_bytes_per_pixel", method=m, material=mat, inputs="oracle") or 0.0), m)
                for m in plain if m != "none"]
        cand = [c for c in cand if c[0] is not None]
        v, _, m = max(cand)  # a tie (glossy PRT is diffuse PRT on a diffuse lobe) goes to the fewer bytes
        best[mat] = f"{mat}: `{m}` {pct(v, 0)} %"
    out["best_plain"] = "; ".join(best.values())
    best_rows = []
    for sc in scenes:
        for mat in mats:
            cells = [sc, mat]
            for kind in OCC_INPUTS:
                cand = []
                for m in methods:
                    v = _occ_mean(rows, "given_back_frac", method=m, material=mat, scene=sc, inputs=kind)
                    if v is not None and m != "none":
                        b = _occ_mean(rows, "input_bytes_per_pixel", method=m, material=mat, scene=sc, inputs=kind)
                        cand.append((v, -b, m))
                v, nb, m = max(cand)
                cells.append(f"`{m}` {pct(v, 0)} % ({int(-nb)} B/px)")
            best_rows.append(cells)
    out["best_table"] = md_table(["scene", "material", "most given back, oracle inputs (input bytes per pixel)",
                                  "most given back, screen-space inputs"], best_rows)
    reg = [q for q in read_csv(folder / "occlusion_zoo_regions.csv") if q["applicable"] == "True"]
    rmats = list(dict.fromkeys(q["material"] for q in reg))
    counts = sorted({int(q["method"].rsplit("-", 1)[1]) for q in reg if q["method"].startswith("regions")})
    kinds = list(dict.fromkeys(q["inputs"] for q in reg if q["method"].startswith("regions")))
    out["regions_table"] = md_table(
        ["visible fractions", *[f"{mat}, {r} regions" for mat in rmats for r in counts]],
        [[k] + [_occ_cell(reg, "given_back_frac", method=f"regions-exact-{r}", material=mat, inputs=k)
                for mat in rmats for r in counts] for k in kinds])
    est_kinds = sorted({q["inputs"] for q in rows} - {"oracle"})
    fronts = {(sc, mat): (_occ_front(rows, methods, scene=sc, material=mat),
                          _occ_front(rows, methods, tuple(est_kinds), scene=sc, material=mat))
              for sc in scenes for mat in mats}
    out["front_table"] = md_table(
        ["scene", "material", "Pareto front, exact (baked) inputs: method bytes per pixel → % given back",
         f"pick: the cheapest within {pct(OCC_PICK_MARGIN, 0)} points of the most",
         "pick with run-time estimates (GTAO, shadow maps)"],
        [[sc, mat, " · ".join(f"`{m}` {b} B → {pct(v, 0)} %" for b, v, m in fr),
          _occ_pick_cell(_occ_pick(fr)), _occ_pick_cell(_occ_pick(fe))] for (sc, mat), (fr, fe) in fronts.items()])
    for key, i in (("pick_counts", 0), ("pick_counts_estimated", 1)):
        picks = [_occ_pick(f[i])[2] for f in fronts.values()]
        out[key] = ", ".join(f"`{m}` {picks.count(m)}" for m in sorted(set(picks), key=lambda m: (-picks.count(m), m)))
    out["n_fronts"] = str(len(fronts))
    baked = [_occ_pick(f[0]) for f in fronts.values()]
    run_time = [_occ_pick(f[1]) for f in fronts.values()]
    out["pick_regions"] = f"{sum(m.startswith('regions') for _, _, m in baked)} of {len(fronts)}"
    out["pick_4b_run_time"] = f"{sum(b == 4 for b, _, _ in run_time)} of {len(fronts)}"
    out["pick_margin"] = pct(OCC_PICK_MARGIN, 0)
    out.update(_occ_scale_check(rows, [q for q in read_csv(folder / "occlusion_zoo_64px.csv")
                                       if q["applicable"] == "True"]))
    out["n_scenes"] = str(len(scenes))
    out["occluded_scenes"] = ", ".join(occluded)
    out["horizon_only"] = ", ".join(sc for sc in scenes if sc in OCC_HORIZON_ONLY) or "none"
    out["scene_list"] = ", ".join(OCC_SCENE_NAMES.get(sc, sc) for sc in scenes)
    out["n_cases"] = str(len({(q["scene"], q["env"], q["material"]) for q in rows}))
    out["n_rows"] = str(len(rows))
    return out


# ---- mip-mappings ------------------------------------------------------------------------------------------------
MAPPING_ORDER = ("linear", "filament", "unity", "unreal", "threejs")


def _mip_mean(rows, **match) -> float:
    return statistics.fmean(float(q["rel_l1_frac"]) for q in rows if all(q[k] == v for k, v in match.items()))


@page("occlusion-zoo-normal-mapped")
def occlusion_zoo_normal_mapped_page(folder: Path) -> dict[str, str]:
    rows = [q for q in read_csv(folder / "occlusion_zoo.csv") if q["inputs"] == "oracle"]
    meta = read_json(folder / "occlusion_zoo_meta.json")
    st = meta["settings"]

    def q(env, mat, method, col="rel_l1_frac"):
        (r,) = [r for r in rows if (r["env"], r["material"], r["method"]) == (env, mat, method)]
        return float(r[col])

    cases = [(e, m) for e in st["envs"] for m in st["materials"]]
    table = []
    for env, mat in cases:
        cells = [f"{pct(q(env, mat, m), 1)} ({signed(pct(q(env, mat, m, 'bias_frac'), 1))})"
                 for m in ("none", "horizon-k1.1", "horizon-k1.3")]
        closer = "k = 1.1" if q(env, mat, "horizon-k1.1") < q(env, mat, "horizon-k1.3") else "k = 1.3"
        table.append([env, mat, *cells, closer, pct(q(env, mat, "horizon-k1.3", "given_back_frac"), 0)])
    dis = next(r for r in read_csv(folder / "occlusion_zoo_disagreements.csv")
               if (r["method_a"], r["method_b"], r["inputs"]) == ("horizon-k1.1", "horizon-k1.3", "oracle"))
    godot = sum(q(e, m, "godot-horizon") == q(e, m, "ao-diffuse") for e, m in cases)
    return {"table": md_table(["environment", "material", "no occlusion", "horizon-k1.1", "horizon-k1.3", "closer",
                               "given back by k = 1.3 (%)"], table),
            "n_pixels": str(meta["n_pixels"]["normal-mapped"]),
            "k13_closer": f"{dis['b_closer_cases']} of the {dis['n_cases']} cases",
            "k13_mean": pct(float(dis["mean_rel_l1_b_frac"]), 1), "k11_mean": pct(float(dis["mean_rel_l1_a_frac"]), 1),
            "none_court_m01": pct(q("courtyard", "metal0.1", "none"), 1),
            "k13_court_m01": pct(q("courtyard", "metal0.1", "horizon-k1.3"), 1),
            "none_sky_m06": pct(q("sky_sun", "metal0.6", "none"), 1),
            "k11_sky_m06": pct(q("sky_sun", "metal0.6", "horizon-k1.1"), 1),
            "k13_sky_m06": pct(q("sky_sun", "metal0.6", "horizon-k1.3"), 1),
            "godot_equal": str(godot), "n_cases": str(len(cases))}


@page("mip-mappings")
def mip_mappings_page(folder: Path) -> dict[str, str]:
    rows = [q for q in read_csv(folder / "mip_mappings.csv") if q["kind"] == "grid"]
    bases = sorted({q["base_face_size_texels"] for q in rows}, key=int)
    maps = [m for m in MAPPING_ORDER if any(q["stored_mapping"] == m for q in rows)]
    out, worst_all = {}, []
    for b in bases:
        sel = [q for q in rows if q["base_face_size_texels"] == b]
        own = []
        for m in maps:
            eq = [q for q in sel if q["layout"] == "equal-memory" and q["stored_mapping"] == m == q["lookup_mapping"]]
            by_r = {}
            for q in eq:
                by_r.setdefault(q["roughness"], []).append(float(q["rel_l1_frac"]))
            worst_r, worst = max(((r, statistics.fmean(v)) for r, v in by_r.items()), key=lambda t: t[1])
            eng = [q for q in sel if q["layout"] == "engine" and q["stored_mapping"] == m == q["lookup_mapping"]]
            own.append([f"`{m}`", f"{pct(_mip_mean(eq), 2)} %", f"{pct(worst, 1)} % at r = {worst_r}",
                        eng[0]["n_levels"], f"{pct(_mip_mean(eng), 2)} %"])
        out[f"own_{b}"] = md_table(["mapping", "equal memory: mean rel. L1", "its worst roughness", "engine's N",
                                    "engine's own chain: mean rel. L1"], own)
        mis = []
        for a in maps:
            cells = []
            for c in maps:
                v = _mip_mean(sel, layout="equal-memory", stored_mapping=a, lookup_mapping=c)
                cells.append(f"**{pct(v, 1)} %**" if a == c else f"{pct(v, 1)} %")
                if a != c:
                    worst_all.append((v, a, c, b))
            mis.append([f"`{a}`"] + cells)
        out[f"mismatch_{b}"] = md_table(["stored \\ read as", *maps], mis)
        out[f"n_equal_{b}"] = next(q["n_levels"] for q in sel if q["layout"] == "equal-memory")
    v, a, c, b = max(worst_all)
    out["worst_mismatch"] = f"a `{a}` chain read as `{c}` at {b}²: {pct(v, 1)} %"
    fil = [q for q in rows if q["layout"] == "engine" and q["stored_mapping"] == "filament" == q["lookup_mapping"]
           and q["base_face_size_texels"] == "256"]
    out["filament_256"] = f"{pct(_mip_mean(fil), 1)} %" if fil else "not run"
    return out


# ---- manson-sloan ------------------------------------------------------------------------------------------------
MS_NORMS = (("mae_radiance", "MAE, radiance units"), ("rel_l1_frac", "relative L1"),
            ("mae_env_mean_frac", "MAE, environment at mean 1"), ("mean_rel_err_frac", "mean per-texel rel. error"))
MS_PAPER_FIS32, MS_PAPER_OWN, MS_MATCH_TOL = 0.4201, 0.0848, 0.10


def _ms_chain(rows, col: str, **match) -> float:
    """Mean of ``col`` over a chain's levels (the rows matching ``match``, one environment or all of them)."""
    return statistics.fmean(float(q[col]) for q in rows if all(q[k] == v for k, v in match.items()))


def _ms_env_mean(rows, envs, col: str, **match) -> float:
    """The mean over environments of each environment's chain error."""
    return statistics.fmean(_ms_chain(rows, col, env=e, **match) for e in envs)


def _g(v: float) -> str:
    return f"{v:.3g}"


@page("manson-sloan")
def manson_sloan_page(folder: Path) -> dict[str, str]:
    rows = read_csv(folder / "manson_sloan.csv")
    meta = read_json(folder / "manson_sloan_meta.json")
    st = meta["settings"]
    envs = list(dict.fromkeys(q["env"] for q in rows))
    fis32 = dict(method="fis", samples="32", sequence="hammersley", at="level-texels")
    disc = dict(method="exact", at="finer-texels")
    out = {"base": str(st["base_size"]), "n_levels": str(st["n_levels"]), "mapping": st["mapping"],
           "n_envs": str(len(envs)), "smallest": str(st["base_size"] >> (st["n_levels"] - 1)),
           "roughness": ", ".join(f"{r:.3f}" for _, r, _ in meta["levels"]),
           "fis_samples": ", ".join(str(s) for s in st["fis_samples"]), "seed": str(st["seed"]),
           "rtol": sci(st["rtol"], 1)}
    table, env_ratios = [], []
    for e in envs + ["mean"]:
        sel = envs if e == "mean" else [e]
        vals = [_ms_env_mean(rows, sel, c, **fis32) for c, _ in MS_NORMS]
        d = _ms_env_mean(rows, sel, "rel_l1_frac", **disc)
        mean_l = statistics.fmean(float(next(q["env_mean_radiance"] for q in rows if q["env"] == x)) for x in sel)
        name = "**mean**" if e == "mean" else f"`{e}`"
        if e != "mean":
            env_ratios.append((vals[1] / d, e))
        table.append([name, _g(mean_l)] + [_g(v) for v in vals] + [_g(d), f"{vals[1] / d:.2f}"])
    lo, hi = min(env_ratios), max(env_ratios)
    paper_ratio = MS_PAPER_FIS32 / MS_PAPER_OWN
    near5 = [f"`{e}` ({v:.1f}×)" for v, e in env_ratios if abs(v / paper_ratio - 1) <= 0.25]
    out["near_paper_ratio"] = ", ".join(near5) if near5 else "no environment"
    others = [v for v, e in env_ratios if abs(v / paper_ratio - 1) > 0.25]
    out["others_ratio"] = f"{min(others):.1f}–{max(others):.1f}×" if others else "—"
    out["ratio_range"] = f"{lo[0]:.1f}× (`{lo[1]}`) to {hi[0]:.1f}× (`{hi[1]}`)"
    out["fis32_table"] = md_table(["environment", "mean radiance", *[lab for _, lab in MS_NORMS],
                                   "exact chain between texels (rel. L1)", "FIS-32 / exact (rel. L1)"], table)
    keys = list(dict.fromkeys((q["method"], q["samples"], q["sequence"]) for q in rows if q["method"] != "exact"))
    mt = []
    for m, s, seq in keys:
        sel = dict(method=m, samples=s, sequence=seq)
        mt.append([f"{m.upper()}-{s}", seq]
                  + [_g(_ms_env_mean(rows, envs, c, at="level-texels", **sel)) for c in ("rel_l1_frac",
                                                                                        "mae_env_mean_frac",
                                                                                        "mean_rel_err_frac")]
                  + [_g(_ms_env_mean(rows, envs, "rel_l1_frac", at="finer-texels", **sel))])
    mt.append(["exact chain", "—", "0 (the reference)", "0", "0", _g(_ms_env_mean(rows, envs, "rel_l1_frac", **disc))])
    out["methods_table"] = md_table(["method", "sequence", "rel. L1 at the level's texels", "MAE at mean 1",
                                     "mean per-texel rel. error", "rel. L1 between texels (bilinear)"], mt)
    levels = sorted({(int(q["level"]), q["roughness"], q["level_face_size_texels"]) for q in rows})
    lt = []
    for lv, r, s in levels:
        cell = lambda **m: _g(statistics.fmean(float(q["rel_l1_frac"]) for q in rows  # noqa: E731
                                                if q["level"] == str(lv) and all(q[k] == v for k, v in m.items())))
        lt.append([str(lv), f"{float(r):.3f}", f"{s}²", cell(method="fis", samples="16", sequence="hammersley",
                                                              at="level-texels"),
                   cell(**fis32), cell(method="fis", samples="256", sequence="hammersley", at="level-texels"),
                   cell(method="is", samples="32", sequence="hammersley", at="level-texels"), cell(**disc)])
    out["levels_table"] = md_table(["level", "roughness", "faces", "FIS-16", "FIS-32", "FIS-256", "IS-32",
                                    "exact chain between texels"], lt)
    # the verdict on 0.4201: every normalisation of every 32-sample method, the mean over environments and each one
    m32 = [("fis", "hammersley"), ("fis", "random"), ("is", "hammersley"), ("is", "random")]
    means = {(m, q, c): _ms_env_mean(rows, envs, c, method=m, samples="32", sequence=q, at="level-texels")
             for m, q in m32 for c, _ in MS_NORMS}
    vt, matches, env_matches = [], [], []
    for c, lab in MS_NORMS:
        cells = []
        for m, q in m32:
            v = means[(m, q, c)]
            hit = abs(v / MS_PAPER_FIS32 - 1) <= MS_MATCH_TOL
            cells.append(f"**{_g(v)}** ({v / MS_PAPER_FIS32:.2f}×)" if hit else f"{_g(v)} ({v / MS_PAPER_FIS32:.2f}×)")
            if hit:
                matches.append(f"{m.upper()}-32 ({q}) under the {lab} ({_g(v)})")
            for e in envs:
                if abs(_ms_chain(rows, c, env=e, method=m, samples="32", sequence=q, at="level-texels")
                       / MS_PAPER_FIS32 - 1) <= MS_MATCH_TOL:
                    env_matches.append((m, q, lab, e))
        vt.append([lab] + cells)
    out["verdict_table"] = md_table(["normalisation", *[f"{m.upper()}-32, {q}" for m, q in m32]], vt)
    out["matches"] = "; ".join(matches) if matches else "none"
    fis_h = [f"`{e}` ({lab})" for m, q, lab, e in env_matches if (m, q) == ("fis", "hammersley")]
    out["fis_h_env_matches"] = ", ".join(fis_h) if fis_h else "none"
    out["match_tol"] = pct(MS_MATCH_TOL, 0)
    means = {c: means[("fis", "hammersley", c)] for c, _ in MS_NORMS}
    out["fis32_per_texel"] = _g(means["mean_rel_err_frac"])
    l1 = ("mae_radiance", "rel_l1_frac")
    factors = [MS_PAPER_FIS32 / means[c] for c in l1]
    out["l1_factors"] = f"{min(factors):.1f}–{max(factors):.1f}×"
    worst = max(_ms_chain(rows, c, env=e, **fis32) for c in l1 for e in envs)
    out["l1_worst_env"] = _g(worst)
    ratios = []
    for lv, _, _ in levels[1:]:
        sel = [q for q in rows if q["level"] == str(lv) and q["sequence"] == "hammersley" and q["samples"] == "32"
               and q["at"] == "level-texels"]
        f = statistics.fmean(float(q["rel_l1_frac"]) for q in sel if q["method"] == "fis")
        i = statistics.fmean(float(q["rel_l1_frac"]) for q in sel if q["method"] == "is")
        ratios.append(i / f)
    lods = [statistics.fmean(float(q["fis_lod_mean"]) for q in rows if q["level"] == str(lv) and q["method"] == "fis"
                             and q["samples"] == "32" and q["sequence"] == "hammersley" and q["at"] == "level-texels")
            for lv, _, _ in levels]
    out["lod_first"], out["lod_last"] = f"{lods[0]:.1f}", f"{lods[-1]:.1f}"
    out["first_level"], out["last_level"] = str(levels[0][0]), str(levels[-1][0])
    out["is_over_fis_above"] = f"{min(ratios):.1f}–{max(ratios):.1f}×"
    out["level1_is_over_fis"] = f"{statistics.fmean(float(q['rel_l1_frac']) for q in rows if q['level'] == str(levels[0][0]) and q['method'] == 'is' and q['samples'] == '32' and q['sequence'] == 'hammersley' and q['at'] == 'level-texels') / statistics.fmean(float(q['rel_l1_frac']) for q in rows if q['level'] == str(levels[0][0]) and q['method'] == 'fis' and q['samples'] == '32' and q['sequence'] == 'hammersley' and q['at'] == 'level-texels'):.2f}×"
    out["fis32_mae"] = _g(means["mae_radiance"])
    rel = means["rel_l1_frac"]
    d = _ms_env_mean(rows, envs, "rel_l1_frac", **disc)
    fine = _ms_env_mean(rows, envs, "rel_l1_frac", method="fis", samples="32", sequence="hammersley",
                        at="finer-texels")
    out["fis32_rel_l1"] = _g(rel)
    out["disc_rel_l1"] = _g(d)
    out["ratio_level"] = f"{rel / d:.2f}"
    out["ratio_finer"] = f"{fine / d:.2f}"
    out["paper_ratio"] = f"{MS_PAPER_FIS32 / MS_PAPER_OWN:.2f}"
    out["fis32_fine"] = _g(fine)
    out["fis32_random"] = _g(_ms_env_mean(rows, envs, "rel_l1_frac", method="fis", samples="32", sequence="random",
                                          at="level-texels"))
    out["is32"] = _g(_ms_env_mean(rows, envs, "rel_l1_frac", method="is", samples="32", sequence="hammersley",
                                  at="level-texels"))
    out["fis256"] = _g(_ms_env_mean(rows, envs, "rel_l1_frac", method="fis", samples="256", sequence="hammersley",
                                    at="level-texels"))
    out["rgb_sum"] = _g(3 * means["mae_env_mean_frac"])
    out["total_time"] = duration(meta["total_time_s"])
    return out


@page("ggx-chain")
def ggx_chain_page(folder: Path) -> dict[str, str]:
    cells = read_csv(folder / "cells.csv")
    levels = read_csv(folder / "levels.csv")
    dense = read_csv(folder / "dense.csv")
    dl = read_csv(folder / "dense_levels.csv")
    cell_table = md_table(
        ["map", "faces", "levels", "cmgen wall s (CPU)", "lab wall s (CPU)", "lab / cmgen", "lab: source tree s",
         "load"],
        [[q["env"], q["face_size_texels"] + "²", q["levels"], f"{float(q['cmgen_wall_s']):.2f} "
          f"({float(q['cmgen_cpu_s']):.2f})", f"{float(q['lab_wall_s']):.2f} ({float(q['lab_cpu_s']):.2f})",
          f"{float(q['lab_over_cmgen_wall']):.2f}×", f"{float(q['lab_tree_s']):.2f}", f"{float(q['load_1min']):.2f}"]
         for q in cells])
    level_table = md_table(
        ["map", "faces", "level", "roughness", "level faces", "lab bound (max)", "lab s", "cmgen err max", "p99",
         "mean"],
        [[q["env"], q["face_size_texels"] + "²", q["level"], f"{float(q['roughness']):.3f}",
          q["level_face_size_texels"] + "²", sci(float(q["lab_rel_bound_max"])), f"{float(q['lab_level_s']):.2f}",
          pct(float(q["cmgen_rel_err_max"]), 1) + " %", pct(float(q["cmgen_rel_err_p99"]), 1) + " %",
          pct(float(q["cmgen_rel_err_mean"]), 2) + " %"] for q in levels])
    dense_table = md_table(
        ["map", "faces", "levels", "dense sum s", "tree s", "dense / tree", "load"],
        [[q["env"], q["face_size_texels"] + "²", q["levels_below_0"], f"{float(q['dense_s']):.2f}",
          f"{float(q['tree_s']):.2f}", f"{float(q['dense_over_tree']):.0f}×", f"{float(q['load_1min']):.2f}"]
         for q in dense])
    dense_level_table = md_table(
        ["map", "faces", "roughness", "level faces", "bound (max)", "error against the dense sum (max)", "within"],
        [[q["env"], q["face_size_texels"] + "²", f"{float(q['roughness']):.3f}", q["level_face_size_texels"] + "²",
          sci(float(q["tree_rel_bound_max"])), sci(float(q["tree_rel_err_vs_dense_max"])),
          "yes" if q["within_bound"] == "True" else "**no**"] for q in dl])
    ratios = [float(q["lab_over_cmgen_wall"]) for q in cells]
    largest = max(int(q["face_size_texels"]) for q in cells)
    at_largest = [float(q["lab_over_cmgen_wall"]) for q in cells if int(q["face_size_texels"]) == largest]
    dn = max(int(q["face_size_texels"]) for q in dense)
    speed = [float(q["dense_over_tree"]) for q in dense if int(q["face_size_texels"]) == dn]
    return {"cells_table": cell_table, "levels_table": level_table, "dense_table": dense_table,
            "dense_levels_table": dense_level_table, "ratio_min": f"{min(ratios):.2f}", "ratio_max": f"{max(ratios):.2f}",
            "largest": str(largest), "ratio_largest": " and ".join(f"{r:.2f}×" for r in at_largest),
            "dense_size": str(dn), "dense_speedup": f"{min(speed):.0f}–{max(speed):.0f}×",
            "within": f"{sum(q['within_bound'] == 'True' for q in dl)} of {len(dl)}",
            "bound_max": sci(max(float(q["lab_rel_bound_max"]) for q in levels))}


@page("kernel-ops")
def kernel_ops_page(folder: Path) -> dict[str, str]:
    rows = read_csv(folder / "kernel_ops.csv")
    what = {"numpy": "the NumPy backend, every operation", "tile_gather": "the sparse gather's sums",
            "tile_bounds": "the sparse route's averages and bounds", "local_extremes": "the sparse route's local "
            "radiance extremes", "band": "the moment route's horizon band", "sh_passes": "the SH projection and "
            "evaluation", "bright_gather": "the SH route's bright-texel gather"}
    summary = []
    for v, label in what.items():
        r = [float(q["ratio_to_all_compiled"]) for q in rows if q["variant"] == v]
        routes = sorted({q["route"] for q in rows if q["variant"] == v})
        summary.append([f"`{v}`", label, ", ".join(routes), str(len(r)), f"{min(r):.2f}–{max(r):.2f}×"])
    table = md_table(["scene", "face", "route", "s", "leaf", "variant", "wall s", "× all compiled",
                      "maps within the bounds"],
                     [[q["scene"], q["face_size_texels"] + "²", q["route"], q["exponents"], q["leaf"], q["variant"],
                       q["wall_s"], q["ratio_to_all_compiled"], q["maps_within_bounds"]] for q in rows])
    ok = sum(q["maps_within_bounds"] == "yes" for q in rows)
    return {"summary": md_table(["handed back to NumPy", "what", "routes", "cells", "slower by"], summary),
            "table": table, "all_within": f"{ok} of {len(rows)} rows"}


@page("startup")
def startup_page(folder: Path) -> dict[str, str]:
    rows = read_csv(folder / "startup.csv")
    imports = {q["checkout"]: q for q in read_csv(folder / "imports.csv")}
    order = list(imports)  # this version first, then the earlier ones
    by = {(q["command"], q["checkout"]): q for q in rows}
    commands = list(dict.fromkeys(q["command"] for q in rows))
    table = md_table(["command"] + [f"{c} (s; modules)" for c in order],
                     [[c] + [f"{by[c, v]['wall_s_median']}; {by[c, v]['ibl_ref_modules']}" for v in order]
                      for c in commands])
    table += "\n\n" + md_table(["version", "internal imports", "inside functions", "share"],
                                 [[v, q["internal_imports"], q["inside_functions"], q["share_inside_functions"]]
                                  for v, q in imports.items()])
    this, before_imports, before_all = order[0], order[1], order[-1]

    def ratio(cmd_prefix, a, b):
        c = next(x for x in commands if x.startswith(cmd_prefix))
        return f"{float(by[c, a]['wall_s_median']) / float(by[c, b]['wall_s_median']):.2f}"

    comp = next(x for x in commands if "compiled" in x)
    return {"table": table, "repeat": rows[0]["repeat"], "share": imports[this]["share_inside_functions"],
            "help_ratio": ratio("ibl-ref --help", this, before_imports),
            "numpy_ratio": ratio("ibl-ref convolve (32²", this, before_imports),
            "compiled_now": by[comp, this]["wall_s_median"], "compiled_aot": by[comp, before_all]["wall_s_median"],
            "compiled_ratio": ratio(comp, this, before_all)}


@page("bench-small-cells")
def bench_small_cells_page(folder: Path) -> dict[str, str]:
    out = {}
    for scene, key in (("sky + sun", "sky"), ("courtyard", "courtyard")):
        out[f"{key}_table"] = md_table(
            ["face", "s", "cmft", "IO floor", "process target", "lab floor", "floor > target", "lab process",
             "first call", "repeated call", "kernels", "Python"],
            [[q["face_size_texels"] + "²", q["s_phong"], q["cmft_ms"], q["io_floor_ms"], q["process_target_ms"],
              q["lab_floor_ms"], q["floor_exceeds_target"], q["lab_process_ms"], q["first_call_ms"],
              q["repeated_call_ms"], q["kernels_ms"], q["python_ms"]]
             for q in read_csv(folder / "small_cells.csv") if q["scene"] == scene])
    return out


@page("quick-start")
def quick_start_page(folder: Path) -> dict[str, str]:
    rows = read_csv(folder / "runs.csv")
    table = md_table(["run", "command", "commit", "date", "wall", "load at the start", "peak", "passed", "skipped",
                      "note"],
                     [[q["run"], f"`{q['command']}`", f"`{q['commit']}`", q["date"] or "—", duration(float(q["wall_s"])),
                       q["load_1min"] or "—", q["peak_GB"] + " GB" if q["peak_GB"] else "—", q["passed"] or "—",
                       q["skipped"] or "—", q["note"]] for q in rows])
    by = {q["run"]: q for q in rows}
    rep, suite, whole = by["reproduce --quick"], by["test suite"], by["CI: the whole .ci/run"]
    out = {"table": table, "reproduce_wall": duration(float(rep["wall_s"])), "reproduce_load": rep["load_1min"],
           "reproduce_peak": rep["peak_GB"], "reproduce_commit": rep["commit"], "reproduce_date": rep["date"],
           "suite_passed": suite["passed"], "suite_skipped": suite["skipped"],
           "suite_wall": duration(float(suite["wall_s"])), "suite_load": suite["load_1min"],
           "suite_commit": suite["commit"], "ci_commit": whole["commit"], "ci_date": whole["date"],
           "ci_wall": duration(float(whole["wall_s"]))}
    for k in (1, 2, 3):
        q = next(r for r in rows if r["run"].startswith(f"CI phase {k}"))
        out[f"ci{k}_passed"], out[f"ci{k}_skipped"], out[f"ci{k}_wall"] = (q["passed"], q["skipped"],
                                                                           duration(float(q["wall_s"])))
    return out


@page("cluster-sweeps")
def cluster_sweeps_page(folder: Path) -> dict[str, str]:
    rows = read_csv(folder / "runs.csv")

    def t(v):
        return duration(float(v)) if v and float(v) >= 60 else (v + " s" if v else "—")

    table = md_table(["command", "jobs", "wall", "CPU", "load", "peak", "note"],
                     [[f"`{q['command']}`", q["jobs"], t(q["wall_s"]), t(q["cpu_s"]), q["load_1min"],
                       q["peak_GB"] + " GB" if q["peak_GB"] else "—", q["note"]] for q in rows])
    return {"table": table}


# ---- the claims table --------------------------------------------------------------------------------------------
_PLACEHOLDER = re.compile(r"\{\{\s*([\w.\-]+)\s*\}\}")


def fill(text: str, values: dict[str, str], where: str) -> tuple[str, set[str]]:
    """Replace every ``{{key}}`` of ``text``; a key without a value is an error.  Returns the text and the keys
    used."""
    used = set()

    def sub(m):
        key = m.group(1)
        if key not in values:
            raise KeyError(f"{where}: no value for {{{{{key}}}}}")
        used.add(key)
        return values[key]

    return _PLACEHOLDER.sub(sub, text), used


def claims_rows() -> list[dict]:
    return read_csv(DATA / "claims" / "claims.csv")


def claims_text(run: str) -> str:
    """The 'measured' cell of the claims row whose numbers come from run folder ``run``, filled from its data."""
    rows = [q for q in claims_rows() if q["data_run"] == run]
    assert len(rows) == 1, (run, len(rows))
    return fill(rows[0]["measured"], run_numbers(run), f"claims.csv ({run})")[0]


@page("claims")
def claims_page(folder: Path) -> dict[str, str]:
    rows = []
    for q in claims_rows():
        values = run_numbers(q["data_run"]) if q["data_run"] else {}
        statement, measured = (fill(q[c], values, f"claims.csv ({q['data_run'] or q['statement'][:30]})")[0]
                               for c in ("statement", "measured"))
        where = f"[{q['data_run']}]({q['data_run']}.md)" if q["data_run"] else "—"
        rows.append([statement, measured, q["command"], where])
    return {"table": md_table(["statement", "measured", "command", "page (data)"], rows)}


# ---- the concept table ---------------------------------------------------------------------------------------------
def concept_rows() -> list[dict]:
    """The rows of ``docs/concepts.csv`` (also read by ``tests/test_layout.py``)."""
    return read_csv(CONCEPTS_CSV)


def concepts_page() -> str:
    head = (TEMPLATES / "concepts.md").read_text(encoding="utf-8")
    table = md_table(["concept", "paper, equation", "module", "entry points"],
                     [[q["concept"], q["paper_equation"], q["module"], q["entry_points"]] for q in concept_rows()])
    text, _ = fill(head, {"table": table}, "concepts.md")
    return GENERATED.format(source="docs/concepts.csv", template="docs/page_templates/concepts.md") + text


# ---- assembling a page -------------------------------------------------------------------------------------------
GENERATED = ("<!-- Generated by docs/make_results.py from {source} and {template}: edit those and run "
             "`python docs/make_results.py`; tests/test_docs_pages.py checks that this file is up to date. -->\n\n")


def provenance(name: str) -> str:
    """The 'where these numbers come from' section of a page, from the folder's ``run.json``."""
    meta = read_json(DATA / name / "run.json")
    parts = ["## Where these numbers come from", ""]
    for run in meta["runs"]:
        files = ", ".join(f"[`{f}`](../../tests/data/readme_runs/{name}/{f})" for f in run["files"])
        parts.append(f"**{files}**" + (f" — {run['what']}" if run.get("what") else ""))
        parts.append("")
        if run.get("command"):
            parts += ["```bash", run["command"], "```", ""]
        facts = [(k, run[k]) for k in ("commit", "date", "wall", "cpu", "peak_memory", "load", "machine")
                 if run.get(k)]
        label = {"commit": "commit", "date": "date", "wall": "wall time", "cpu": "CPU time",
                 "peak_memory": "peak memory", "load": "load average", "machine": "machine"}
        parts += [f"- {label[k]}: {f'`{v}`' if k == 'commit' else v}" for k, v in facts]
        if run.get("note"):
            parts.append(f"- {run['note']}")
        if run.get("source"):
            parts.append(f"- source: {run['source']}")
        parts.append("")
    return "\n".join(parts).rstrip() + "\n"


def build_page(name: str) -> str:
    """The markdown of ``docs/results/<name>.md``."""
    template = (TEMPLATES / f"{name}.md").read_text(encoding="utf-8")
    values = PAGES[name](DATA / name)
    text, used = fill(template, values, f"{name}.md")
    shared = set(run_numbers(name)) if name in _NUMBERS else set()  # a folder's numbers may serve the claims only
    unused = set(values) - used - shared
    if unused:
        raise KeyError(f"{name}.md: values computed but not used in the template: {sorted(unused)}")
    head = GENERATED.format(source=f"tests/data/readme_runs/{name}/", template=f"docs/page_templates/{name}.md")
    return head + text.rstrip() + "\n\n" + provenance(name)


def outputs() -> dict[Path, str]:
    """Every generated file and its text."""
    out = {RESULTS / f"{name}.md": build_page(name) for name in PAGES}
    out[DOCS / "concepts.md"] = concepts_page()
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="only compare with the committed pages")
    args = parser.parse_args(argv)
    stale = []
    for path, text in outputs().items():
        old = path.read_text(encoding="utf-8") if path.exists() else None
        if old != text:
            stale.append(path.relative_to(ROOT))
            if not args.check:
                path.parent.mkdir(parents=True, exist_ok=True)
                tmp = path.with_name(f".{path.name}.tmp")
                tmp.write_text(text, encoding="utf-8")
                tmp.replace(path)
    if args.check and stale:
        print("out of date (run python docs/make_results.py): " + ", ".join(map(str, stale)), file=sys.stderr)
        return 1
    for p in stale if not args.check else ():
        print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
