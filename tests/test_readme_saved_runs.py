"""The numbers of the experiments whose full runs take minutes, pinned to the full runs they come from.

The full runs of ``render-error``, ``error-budget``, ``lobe-chain``, ``speed-accuracy``, ``km00-render``,
``cosine-lobes``, ``fig8`` and ``kan-table1`` take 19 s (kan-table1) to 16 min (error-budget) of wall time each, more
than half an hour together: too long for the suite.  So the data files of one full run of each are kept in
``tests/data/readme_runs/<experiment>/`` (command, commit, date, load and wall time in its ``run.json``), and the
documentation pages ``docs/results/<experiment>.md`` are generated from them (``docs/make_results.py``; regenerated
and compared byte for byte by ``tests/test_docs_pages.py``).  Two kinds of check:

* every number these experiments are quoted with (the claims table, the error-budget tables and text, as the README
  of commit 537f533 printed them) is what the saved files give, to its rounding (half a unit of the last printed
  digit, plus float slack): the numbers are written here, or for whole tables in the folder's
  ``expected_tables.csv``; data that are re-made with other numbers fail here;
* where a slice of the full run is affordable (``error-budget``: one environment × one material, 12 s;
  ``lobe-chain``: one environment, two exponents, 26 s), it is re-run here at the full
  run's settings and must reproduce its saved rows: the experiments are deterministic (seeded), so the tolerance is
  float64 rounding (1e-9 relative, which also absorbs a different BLAS thread count).

The quick versions of these experiments (``tests/test_experiments_quick.py``) check what the numbers mean
(orderings, targets, bounds) at small sizes; this file checks that the quoted numbers are those of the data.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from ibl_ref.atomic import read_csv

ROOT = Path(__file__).resolve().parent.parent
SAVED = ROOT / "tests" / "data" / "readme_runs"


def _close(quoted: float, data_value: float, decimals: int) -> bool:
    """``quoted`` is ``data_value`` rounded to ``decimals`` (half a unit of the last digit, plus float slack far
    below that unit)."""
    half_unit = 0.5 * 10.0 ** -decimals
    return abs(quoted - data_value) <= half_unit + min(1e-9, 1e-3 * half_unit)


def _decimals(text: str) -> int:
    """Decimal places of the last printed digit of ``text``: 2 for "0.05", 6 for "5.9e-5"."""
    mantissa, _, exponent = text.lower().partition("e")
    places = len(mantissa.split(".")[1]) if "." in mantissa else 0
    return places - int(exponent or 0)


def _check(text: str, value: float, what=""):
    """``text`` (a number as printed) is ``value`` to its printed rounding."""
    assert _close(float(text), value, _decimals(text)), (what, text, value)


def _same_rows(new, saved, key, skip=("time",)):
    """Every row of ``new`` equals its saved row (by ``key``): strings exactly, numbers to 1e-9 relative; columns
    whose name contains one of ``skip`` (wall-clock times) are not compared."""
    by = {tuple(q[k] for k in key): q for q in saved}
    assert new
    for q in new:
        old = by[tuple(q[k] for k in key)]
        for col, v in q.items():
            if any(w in col for w in skip):
                continue
            try:
                a, b = float(v), float(old[col])
            except ValueError:
                assert v == old[col], (col, v, old[col])
                continue
            assert a == pytest.approx(b, rel=1e-9, abs=1e-15), (tuple(q[k] for k in key), col, a, b)


class _Quoted:
    """Numbers as the README of commit 537f533 printed them, in the order of its sentence: ``group(1)`` is the
    first (the same interface as the regular-expression match that used to read them from the README)."""

    def __init__(self, *texts: str):
        self.texts = texts

    def group(self, k: int) -> str:
        return self.texts[k - 1]

    def groups(self) -> tuple:
        return self.texts


# ---- render-error ----------------------------------------------------------------------------------------------
def _render_error_rows():
    rows = read_csv(SAVED / "render-error" / "render_error.csv")
    return {q["material"]: q for q in rows if q["lights"] == "96" and q["vsm_resolution"] == "256"}


def test_render_error_row_is_the_saved_run():
    # "not met, 30.1 % (g = 0), 22.8 % (g = 0.9), 9.6 % (g = 0.99) — the pyramid lookup alone is off by 29.6 % /
    # 20.6 % / 5.9 %"; "**0.90 %** / 5.4 % / 5.3 % (chain: 153 MiB vs 36 MiB for 96 PEMs"
    data = _render_error_rows()
    m = _Quoted("30.1", "22.8", "9.6", "29.6", "20.6", "5.9")
    for k, mat in enumerate(("diffuse", "g0.9", "g0.99")):
        _check(m.group(1 + k), 100 * float(data[mat]["rel_l1_ours"]), ("ours", mat))
        _check(m.group(4 + k), 100 * float(data[mat]["rel_l1_lookup_unoccluded"]), ("lookup", mat))
    m = _Quoted("0.90", "5.4", "5.3", "153", "36")
    for k, mat in enumerate(("diffuse", "g0.9", "g0.99")):
        _check(m.group(1 + k), 100 * float(data[mat]["rel_l1_chain"]), ("chain", mat))
    _check(m.group(4), float(data["diffuse"]["chain_MiB"]), "chain memory")
    _check(m.group(5), float(data["diffuse"]["pem_MiB"]), "PEM memory")
    # the claim itself: the 5 % target is missed with the pyramid and met for diffuse with the chain
    assert float(data["diffuse"]["rel_l1_ours"]) > 0.05 > float(data["diffuse"]["rel_l1_chain"])


# ---- error-budget ----------------------------------------------------------------------------------------------
def _expected_budget_tables():
    """The README's two error-budget tables as printed (``error-budget/expected_tables.csv``)."""
    rows = read_csv(SAVED / "error-budget" / "expected_tables.csv")
    return [q for q in rows if q["table"] == "budget"], [q for q in rows if q["table"] == "texel"]


def _walks(rows, order="default"):
    walks = {}
    for q in rows:
        if q["order"] == order:
            walks.setdefault((q["env"], q["material"], q["regions"]), []).append(q)
    return {k: sorted(v, key=lambda q: int(q["step_index"])) for k, v in walks.items()}


def test_error_budget_tables_are_the_saved_run():
    saved = SAVED / "error-budget"
    walks = _walks(read_csv(saved / "error_budget.csv"))
    budget, texel = _expected_budget_tables()
    steps = [c[len("step_"):] for c in budget[0] if c.startswith("step_")]
    assert len(budget) == len(walks) == 18
    for cells in budget:
        case = (cells["env"], cells["material"], cells["regions"])
        walk = walks[case]
        assert [q["step"] for q in walk[1:]] == steps
        _check(cells["eq5_vs_ref_pct"], 100 * float(walk[-1]["rel_l1_vs_ref_frac"]), case)
        for step, q in zip(steps, walk[1:]):
            m = re.fullmatch(r"([\d.]+) % \((\d+) %\)", cells["step_" + step])
            assert m, cells["step_" + step]
            _check(m.group(1), 100 * float(q["rel_l1_increment_frac"]), (case, q["step"]))
            _check(m.group(2), 100 * float(q["share_of_increments_frac"]), (case, q["step"], "share"))
        _check(cells["sum_increments_pct"], 100 * sum(float(q["rel_l1_increment_frac"]) for q in walk[1:]), case)

    trows = {(q["env"], q["material"], q["face_size_texels"]): q
             for q in read_csv(saved / "error_budget_texel_limit.csv")}
    assert len(texel) == len(trows) == 12
    for cells in texel:
        key = (cells["env"], cells["material"], cells["face_size_texels"])
        q = trows[key]
        assert cells["regions"] == q["regions"]
        _check(cells["rel_l1_vs_ref_pct"], 100 * float(q["rel_l1_vs_ref_frac"]), key)
        _check(cells["ref_err_estimate_pct"], 100 * float(q["ref_err_estimate_frac"]), (key, "estimate"))
    # the paragraph above it: "the error drops 1.9–4.1× from 32² to 64² copies, to at most 0.15 % except `probe`,
    # g = 0.99 (3.60 % → 0.87 % …); at 64² the remaining 0.06–0.15 % is of the order of the reference's own
    # estimate (0.05–0.14 %)"
    m = _Quoted("1.9", "4.1", "0.15", "3.60", "0.87", "0.06", "0.15", "0.05", "0.14")
    rel = {k: 100 * float(q["rel_l1_vs_ref_frac"]) for k, q in trows.items()}
    est = {k: 100 * float(q["ref_err_estimate_frac"]) for k, q in trows.items()}
    cases = [(e, t) for e in ("sky_sun", "probe") for t in ("diffuse", "g0.9", "g0.99")]
    drop = [rel[(e, t, "32")] / rel[(e, t, "64")] for e, t in cases]
    rest = [(e, t, "64") for e, t in cases if (e, t) != ("probe", "g0.99")]
    _check(m.group(1), min(drop), "drop min")
    _check(m.group(2), max(drop), "drop max")
    _check(m.group(3), max(rel[k] for k in rest), "64² max")
    _check(m.group(4), rel[("probe", "g0.99", "32")], "probe g0.99 32²")
    _check(m.group(5), rel[("probe", "g0.99", "64")], "probe g0.99 64²")
    _check(m.group(6), min(rel[k] for k in rest), "64² min")
    _check(m.group(7), max(rel[k] for k in rest), "64² max")
    _check(m.group(8), min(est[k] for k in rest), "estimate min")
    _check(m.group(9), max(est[k] for k in rest), "estimate max")


def test_error_budget_swap_paragraph_is_the_saved_run():
    rows = read_csv(SAVED / "error-budget" / "error_budget.csv")
    default, swapped = _walks(rows), _walks(rows, "swap vsm<->prefilter")
    # "moves `sky_sun`, g = 0.9, 24 regions from A to B, and `probe`, diffuse, 24 regions from C to D; the final
    # error (26.8 %, 26.0 %) is the same"
    m = _Quoted("regions 14.4 % (24 %) · vsm 7.6 % (13 %) · horizon 11.1 % (18 %) · prefilter 13.6 % (22 %)",
                "regions 14.4 % (24 %) · prefilter 13.6 % (23 %) · horizon 8.8 % (15 %) · vsm 8.8 % (15 %)",
                "vsm 12.3 % (36 %) · prefilter 19.5 % (57 %)", "prefilter 14.2 % (45 %) · vsm 14.8 % (47 %)",
                "26.8", "26.0")
    cases = [(("sky_sun", "g0.9", "24"), m.group(1), m.group(2)), (("probe", "diffuse", "24"), m.group(3), m.group(4))]
    for case, before, after in cases:
        for walk, text in ((default[case], before), (swapped[case], after)):
            by_step = {q["step"]: q for q in walk}
            items = re.findall(r"(\w+) ([\d.]+) % \((\d+) %\)", text)
            assert len(items) >= 2, text
            for step, rel, share in items:
                _check(rel, 100 * float(by_step[step]["rel_l1_increment_frac"]), (case, step))
                _check(share, 100 * float(by_step[step]["share_of_increments_frac"]), (case, step, "share"))
    for k, (case, _, _) in enumerate(cases):
        final = [float(w[case][-1]["rel_l1_vs_ref_frac"]) for w in (default, swapped)]
        assert final[0] == pytest.approx(final[1], rel=1e-12)  # the order does not change the end point
        _check(m.group(5 + k), 100 * final[0], case)


def test_error_budget_bullets_are_the_saved_run():
    walks = _walks(read_csv(SAVED / "error-budget" / "error_budget.csv"))

    def share(case, steps):
        return 100 * sum(float(q["share_of_increments_frac"]) for q in walks[case] if q["step"] in steps)

    def inc(case, step):
        return 100 * float(next(q for q in walks[case] if q["step"] == step)["rel_l1_increment_frac"])

    # "together are 45–92 % of the summed increments for the diffuse and g = 0.9 materials; for g = 0.99 the
    # regions and the VSMs are the largest (together 57–74 %"
    m = _Quoted("45", "92", "57", "74")
    a = [share(("sky_sun", t, r), ("prefilter", "gloss_lookup")) for t in ("diffuse", "g0.9") for r in ("6", "24", "96")]
    b = [share(("sky_sun", "g0.99", r), ("regions", "vsm")) for r in ("6", "24", "96")]
    for text, v in zip(m.groups(), (min(a), max(a), min(b), max(b))):
        _check(text, v, "shares")
    # "more regions help (30.1 % → 14.9 % from 6 to 96 regions). Under `probe` the VSMs dominate at 6 regions (44 %
    # for diffuse) and fade with more regions (2 % at 96)"
    m = _Quoted("30.1", "14.9", "44", "2")
    final = {r: 100 * float(walks[("sky_sun", "g0.99", r)][-1]["rel_l1_vs_ref_frac"]) for r in ("6", "96")}
    _check(m.group(1), final["6"], "g0.99, 6 regions")
    _check(m.group(2), final["96"], "g0.99, 96 regions")
    _check(m.group(3), inc(("probe", "diffuse", "6"), "vsm"), "probe vsm at 6")
    _check(m.group(4), inc(("probe", "diffuse", "96"), "vsm"), "probe vsm at 96")
    # "The horizon term matters with 24 per-face regions (11 % of the g = 0.9 image under `sky_sun`, 1 % with 6 or 96)"
    m = _Quoted("11", "1")
    _check(m.group(1), inc(("sky_sun", "g0.9", "24"), "horizon"), "horizon at 24")
    for r in ("6", "96"):
        _check(m.group(2), inc(("sky_sun", "g0.9", r), "horizon"), ("horizon", r))


@pytest.mark.same_without_tools
def test_one_error_budget_case_reproduces(tmp_path):
    from ibl_ref.experiments import error_budget

    error_budget.run(tmp_path, quick=False, envs=["sky_sun"], materials=["diffuse"], texel_factors=[])
    new = read_csv(tmp_path / "error_budget.csv")
    assert len(new) == 3 * 2 * 8  # three region counts × two walk orders × eight images
    _same_rows(new, read_csv(SAVED / "error-budget" / "error_budget.csv"),
               ("env", "material", "regions", "order", "step"))


# ---- lobe-chain ------------------------------------------------------------------------------------------------
def _chain_rows():
    rows = read_csv(SAVED / "lobe-chain" / "lobe_chain.csv")
    out = {}
    for q in rows:
        out.setdefault((q["env"], q["prefilter"]), []).append(q)
    return out


def test_lobe_chain_row_is_the_saved_run():
    data = _chain_rows()

    def pct(env, pf, col="rel_l1"):
        return [100 * float(q[col]) for q in data[(env, pf)]]

    # "paper's sqrt-cos pyramid: 20–52 % rel. L1 (sky+sun), 8–22 % (studio); solid-angle shrink: 19–51 %"
    m = _Quoted("20", "52", "8", "22", "19", "51")
    for k, env in enumerate(("sky_sun", "studio")):
        v = pct(env, "pyramid-sqrtcos")
        _check(m.group(1 + 2 * k), min(v), (env, "min"))
        _check(m.group(2 + 2 * k), max(v), (env, "max"))
    v = pct("sky_sun", "pyramid-sqrtcos-solid-angle")
    _check(m.group(5), min(v), "solid angle min")
    _check(m.group(6), max(v), "solid angle max")
    # "does not fix it: 28.9 % / 20.0 % at s = 1, ≥ 18.7 % / ≥ 7.0 % at every s"
    m = _Quoted("28.9", "20.0", "18.7", "7.0")
    for k, env in enumerate(("sky_sun", "studio")):
        best = pct(env, "pyramid-sqrtcos", "rel_l1_best_level")
        _check(m.group(1 + k), best[0], (env, "best level at s = 1"))
        assert float(data[(env, "pyramid-sqrtcos")][0]["s_phong"]) == 1.0
        _check(m.group(3 + k), min(best), (env, "best level, every s"))
    # "ratio 2: ≤ 3.1 % / ≤ 1.9 % (ratio √2: ≤ 1.6 % / ≤ 1.2 %), at 4.3× (7.7×) the memory"
    m = _Quoted("3.1", "1.9", "1.6", "1.2", "4.3", "7.7")
    for k, pf in enumerate(("chain-f2", "chain-f1.41")):
        for j, env in enumerate(("sky_sun", "studio")):
            _check(m.group(1 + 2 * k + j), max(pct(env, pf)), (env, pf))
        mem = float(data[("sky_sun", pf)][0]["memory_MiB"]) / float(data[("sky_sun", "pyramid-sqrtcos")][0]["memory_MiB"])
        _check(m.group(5 + k), mem, (pf, "memory ratio"))


@pytest.mark.same_without_tools
def test_one_lobe_chain_case_reproduces(tmp_path):
    from ibl_ref.experiments import lobe_chain

    lobe_chain.run(tmp_path, quick=False, envs=["studio"], s_values=[1, 100])
    new = read_csv(tmp_path / "lobe_chain.csv")
    assert len(new) == 2 * len(lobe_chain.PREFILTERS)
    _same_rows(new, read_csv(SAVED / "lobe-chain" / "lobe_chain.csv"), ("env", "prefilter", "s_phong"))


# ---- speed-accuracy --------------------------------------------------------------------------------------------
def test_speed_accuracy_row_is_the_saved_run():
    rows = read_csv(SAVED / "speed-accuracy" / "speed_accuracy.csv")
    assert all(int(q["bound_violations"]) == 0 for q in rows)  # "0 texels anywhere above a method's bound"
    # "max rel. error 5.9e-5 over every s in {1 … 4096} at 128² (2000 random texels vs the exact sum; s = 256,
    # `sparse`), 2.7e-6 at 64² (s = 1024, `sparse`), 8.9e-7 at 32² (every texel; s = 256, `sparse`)"
    m = _Quoted("5.9e-5", "2000", "256", "sparse", "2.7e-6", "1024", "sparse", "8.9e-7", "256", "sparse")
    for k, n in enumerate((128, 64, 32)):
        g = m.groups()[(0, 4, 7)[k]:]
        auto = [q for q in rows if q["method"] == "auto" and int(q["face_size_texels"]) == n]
        worst = max(auto, key=lambda q: float(q["rel_err_max"]))
        _check(g[0], float(worst["rel_err_max"]), (n, worst))
        assert float(worst["rel_err_max"]) <= 1e-3  # the requested rtol
        s, route = (g[2], g[3]) if n == 128 else (g[1], g[2])
        assert float(worst["s_phong"]) == float(s) and worst["method_used"] == route, (n, worst)
        # "auto ran the NumPy kernels at 32² and 64² and the compiled ones at 128²"
        assert {q["kernel"] for q in auto} == {"compiled" if n == 128 else "numpy"}, n
        if n == 128:
            assert int(worst["n_reference_texels"]) == int(g[1])
        else:
            assert int(worst["n_reference_texels"]) == 6 * n * n


# ---- km00-render -----------------------------------------------------------------------------------------------
def test_km00_render_row_is_the_saved_run():
    saved = SAVED / "km00-render"
    q = {r["method"]: r for r in read_csv(saved / "km00_render_metrics.csv")}

    def pct(method, col="rel_l1"):
        return 100 * float(q[method][col])

    # "single lobe 1.07 %, single 2D lobe 3.2 %, 3 lobes 7.8 % (the greedy minimum-profile lobes leave 11 % of the
    # energy unfitted: −11 % under L ≡ 1"
    m = _Quoted("1.07", "3.2", "7.8", "11", "11")
    for text, method in zip(m.groups()[:3], ("single", "single2d", "lobes3")):
        _check(text, pct(method), method)
    _check(m.group(4), -pct("lobes3", "rel_bias_constant_env"), "unfitted energy")
    _check(m.group(5), -pct("lobes3", "rel_bias_constant_env"), "bias under L = 1")
    # "and 1.04 % with one energy factor per elevation …, median pixel error 0.47 % vs 0.52 % for the single lobe …,
    # 3 lobes via the sqrt-cos pyramid 14.7 %, single lobe via the pyramid 10.3 %; reference converged (rel. L1
    # between supersampling ×2 and ×4: 4.2e-4)"
    m = _Quoted("1.04", "0.47", "0.52", "14.7", "10.3", "4.2e-4")
    _check(m.group(1), pct("lobes3_rescaled"), "rescaled")
    _check(m.group(2), pct("lobes3_rescaled", "rel_err_median"), "rescaled median")
    _check(m.group(3), pct("single", "rel_err_median"), "single median")
    _check(m.group(4), pct("pyramid3"), "pyramid3")
    _check(m.group(5), pct("pyramid1"), "pyramid1")
    conv = {(r["k_multiplier_from"], r["k_multiplier_to"]): r for r in read_csv(saved / "km00_render_reference_convergence.csv")}
    _check(m.group(6), float(conv[("2", "4")]["rel_l1"]), "reference convergence")
    meta = json.loads((saved / "km00_render_meta.json").read_text())
    assert meta["brdf"] == {"model": "ward", "kd": 0.0, "ks": 0.8, "alpha": 0.04}  # "Ward kd 0, ks 0.8, α 0.04"


# ---- fig8 (sparse PEMs), cosine-lobes (Meunier), kan-table1 ----------------------------------------------------
def test_sparse_pem_row_is_the_saved_run():
    rows = [q for q in read_csv(SAVED / "fig8" / "fig8_sparse.csv") if q["env"] == "sky_sun"]
    ratio = {(int(q["face_size"]), int(q["regions"])): float(q["ratio_lossless"]) for q in rows}
    # "lossless 10.8× (12 regions) … 64.5× (96) at 128², 11.4× … 80.5× at 256²"
    m = _Quoted("10.8", "64.5", "11.4", "80.5")
    for text, key in zip(m.groups(), ((128, 12), (128, 96), (256, 12), (256, 96))):
        _check(text, ratio[key], key)
    assert min(ratio.values()) > 10  # the goal the row names
    assert sorted({r for _, r in ratio}) == [12, 24, 48, 96]  # 12 and 96 are the ends of the sweep


def test_meunier_row_is_the_saved_run():
    pf = json.loads((SAVED / "cosine-lobes" / "summary.json").read_text())["product_fit"]
    m = _Quoted("9.9", "4")  # "9.9e-4 sr (coarser sampling"
    _check(m.group(1), pf["abs_err_sr"]["mean"] * 10 ** int(m.group(2)), "product-fit mean")
    assert pf["per_interval"] == 6  # the full run's sampling (the paper's)
    # "the paper's own statistics are inconsistent: median 0 with variance 1.2e-8 < mean²"
    assert pf["paper_variance_abs_err"] < pf["paper_mean_abs_err"] ** 2
    _check("1.2e-8", pf["paper_variance_abs_err"], "the paper's variance")


def test_kan_table1_row_is_the_saved_run():
    rows = {int(q["face_size_texels"]): q for q in read_csv(SAVED / "kan-table1" / "kan_table1.csv")}
    # "(0.04 / 1.45 / 6.36 / 28.1 s) | 0.19 / 0.62 / 1.38 / 5.31 s at 32² / 64² / 128² / 256² faces (… every bound
    # ≤ 9.9e-4); exact gather 0.77 s / 9.31 s"
    m = _Quoted("0.04", "1.45", "6.36", "28.1", "0.19", "0.62", "1.38", "5.31", "9.9", "0.77", "9.31")
    sizes = (32, 64, 128, 256)
    for k, n in enumerate(sizes):
        _check(m.group(1 + k), float(rows[n]["kan2015_time_s"]), ("Kán", n))  # the published Table 1
        _check(m.group(5 + k), float(rows[n]["time_auto_s"]), ("auto", n))
    bound = max(float(rows[n]["auto_rel_bound_max"]) for n in sizes)
    assert bound <= 1e-3  # the requested rtol
    assert bound * 1e4 <= float(m.group(9)) and _close(float(m.group(9)), bound * 1e4, 1)
    _check(m.group(10), float(rows[32]["time_exact_s"]), "exact 32²")
    _check(m.group(11), float(rows[64]["time_exact_s"]), "exact 64²")


def test_equal_error_run_is_consistent():
    # benchmarks/bench_equal_error.py's saved run (docs/results/reference-renderer.md): every reference converged,
    # every timed Mitsuba render's noise is the reference's estimated error (the search stops within 15 % on its last
    # try; the timed repeat, another seed, has its own noise estimate: 20 % allowed), and the ratio is the two times'
    rows = read_csv(SAVED / "reference-renderer" / "equal_error.csv")
    assert [q["material"] for q in rows] == ["ggx0.1", "ggx0.3", "ggx0.6", "g0.9"]
    for q in rows:
        assert q["ref_converged"] == "True" and float(q["ref_est_rel_l1"]) <= 2e-3
        assert abs(float(q["mitsuba_noise_rel_l1"]) / float(q["ref_est_rel_l1"]) - 1.0) <= 0.2, q["material"]
        assert abs(float(q["ratio_ref_to_mitsuba"]) - float(q["ref_wall_s"]) / float(q["mitsuba_wall_s"])) <= 1e-3


def test_sweep_run_is_consistent():
    # benchmarks/bench_reference_quadrature.py's saved run (docs/results/reference-renderer.md): 7 materials x 5
    # environments, each sweep image converged within the default tolerance, and each lies within the sum of its own
    # and its NumPy render's estimates (both are converged references of one image); the per-material times are
    # repeated on the material's rows
    rows = read_csv(SAVED / "reference-renderer" / "sweep.csv")
    assert len(rows) == 35 and len({q["material"] for q in rows}) == 7 and len({q["env"] for q in rows}) == 5
    for q in rows:
        est_b, est_s = float(q["est_rel_l1_baseline"]), float(q["est_rel_l1_sweep"])
        assert q["sweep_converged"] == "True" and max(est_b, est_s) <= 2e-3, q
        assert float(q["diff_rel_l1"]) <= est_b + est_s, q
    for mat in {q["material"] for q in rows}:
        assert len({q["compiled_sweep_wall_s"] for q in rows if q["material"] == mat}) == 1


def test_equal_error_runs_matched_to_the_actual_error_are_consistent():
    # the same benchmark with --match actual (docs/results/reference-renderer.md): each reference converged and its
    # estimate bounds its actual error against the 10x finer run (which is itself converged to a tenth of it), the
    # timed Mitsuba render's noise is that actual error (the search's 15 %, 20 % for the timed repeat's own noise),
    # and the ratio is the two times'
    folder = SAVED / "reference-renderer"
    rows = [q for f in sorted(folder.glob("equal_error_actual_*.csv")) for q in read_csv(f)]
    assert {q["material"] for q in rows} >= {"ggx0.1", "ggx0.3"}
    for q in rows:
        est, act, fine = float(q["ref_est_rel_l1"]), float(q["ref_actual_rel_l1"]), float(q["finer_run_est_rel_l1"])
        assert q["matched_to"] == "actual" and q["ref_converged"] == "True" and est <= 2e-3
        assert act <= est and fine <= est / 5, q["material"]
        assert abs(float(q["mitsuba_noise_rel_l1"]) / act - 1.0) <= 0.2, q["material"]
        assert abs(float(q["ratio_ref_to_mitsuba"]) - float(q["ref_wall_s"]) / float(q["mitsuba_wall_s"])) <= 1e-3


def test_readme_ggx_chain_row_is_the_saved_run():
    # "**0.80–0.97×** the wall time of Filament's `cmgen` at 256² and 512² faces (faster on all 4 maps and
    # sizes …), **75–83×** faster than the dense sum at 128²; cmgen's own chain is 3–10 % off on average per level"
    row = next(ln for ln in (ROOT / "README.md").read_text().splitlines() if ln.startswith("| Exact GGX (n = v = r)"))
    m = re.search(r"\*\*([\d.]+)–([\d.]+)×\*\* the wall time of Filament's `cmgen`", row)
    cells = read_csv(SAVED / "ggx-chain" / "cells.csv")
    ratios = [float(q["lab_over_cmgen_wall"]) for q in cells]
    assert m and len(ratios) == 4
    _check(m.group(1), min(ratios), "fastest lab / cmgen")
    _check(m.group(2), max(ratios), "slowest lab / cmgen")
    assert "faster on all 4 maps and sizes" in row and sum(r < 1 for r in ratios) == 4
    dense = [float(q["dense_over_tree"]) for q in read_csv(SAVED / "ggx-chain" / "dense.csv")
             if q["face_size_texels"] == "128"]
    m = re.search(r"\*\*(\d+)–(\d+)×\*\* faster than the dense sum at 128²", row)
    assert m and len(dense) == 2
    _check(m.group(1), min(dense), "dense / tree")
    _check(m.group(2), max(dense), "dense / tree")
    errs = [100 * float(q["cmgen_rel_err_mean"]) for q in read_csv(SAVED / "ggx-chain" / "levels.csv")]
    assert "cmgen's own chain is 3–10 % off on average per level" in row
    assert round(min(errs)) == 3 and round(max(errs)) == 10
