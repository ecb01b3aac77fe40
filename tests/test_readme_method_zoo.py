"""The method-zoo numbers, pinned to the full run they come from.

The full run (both scenes, five environments, every method; 16.8 min on 2 workers) is too long for a test, so its
two data files are kept in ``tests/data/readme_runs/method-zoo/`` (command, commit and date in its ``run.json``); the
page ``docs/results/method-zoo.md`` is generated from them.  Three checks:

* every cell of the two tables as the README of commit 537f533 printed them (mean rel. L1 and mean p99 over the
  environments, memory; transcribed in ``expected_tables.csv``) is what the saved ``method_zoo.csv`` gives, to
  their rounding;
* the Karis statements (the n = v = r step larger than the split-sum separation in all 30 GGX cases, the ratio
  ranges) are what the saved ``method_zoo_karis.csv`` gives, to their rounding;
* one case of that run, re-run here at the full run's settings (sphere, city probe, the diffuse and GGX 0.3
  materials, the exact split sum and SH9), reproduces its saved rows: the experiment is deterministic, so the
  tolerance is float64 rounding (1e-9 relative, which also absorbs a different BLAS thread count).

The zoo at engine size (256² faces, both scenes; ``tests/data/readme_runs/method-zoo-256/``, two runs of 33 and 48
minutes): the run is complete, its budget walks add up, and the README row is what its files give.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ibl_ref.atomic import read_csv

ROOT = Path(__file__).resolve().parent.parent
SAVED = ROOT / "tests" / "data" / "readme_runs" / "method-zoo"
MIB = 1024.0 * 1024.0


def _expected_tables():
    """{scene: {(method, material): (rel_l1 %, p99 %)}, ...} and {scene: {method: memory MiB}} as printed."""
    cells, memory = {}, {}
    for q in read_csv(SAVED / "expected_tables.csv"):
        cells.setdefault(q["scene"], {})[(q["method"], q["material"])] = (float(q["rel_l1_pct"]), float(q["p99_pct"]))
        memory.setdefault(q["scene"], {})[q["method"]] = float(q["memory_MiB"])
    return cells, memory


def _saved_means():
    acc = {}
    for q in read_csv(SAVED / "method_zoo.csv"):
        if q["applicable"] == "True":
            acc.setdefault((q["scene"], q["method"], q["material"]), []).append(
                (float(q["rel_l1_frac"]), float(q["p99_rel_error_frac"]), float(q["memory_bytes"])))
    return {k: np.mean(np.array(v), axis=0) for k, v in acc.items()}


def test_readme_tables_are_the_saved_run():
    cells, memory = _expected_tables()
    means = _saved_means()
    # the tables list every applicable (scene, method, material) of the run and nothing else
    assert {(s, meth, mat) for s in cells for (meth, mat) in cells[s]} == set(means)
    assert sum(len(v) for v in cells.values()) == 2 * 45  # 7 split-sum variants × 3 GGX, 3 + 4 + 4 × 4 + 1 others
    for scene, tab in cells.items():
        for (method, mat), (rel, p99) in tab.items():
            r, p, _ = means[(scene, method, mat)]
            # README rounding: rel. L1 to 0.1 %-point, p99 to 1 %-point (half a unit, plus float slack)
            assert abs(100 * r - rel) <= 0.05 + 1e-9, (scene, method, mat, 100 * r, rel)
            assert abs(100 * p - p99) <= 0.5 + 1e-9, (scene, method, mat, 100 * p, p99)
        for method, mib in memory[scene].items():
            mem = [v[2] for (s, meth, _), v in means.items() if s == scene and meth == method]
            # memory is the mean over the environments and materials (the same for each); 3 significant digits
            assert mem and abs(np.mean(mem) / MIB - mib) <= 0.005 * max(mib, 0.001) + 5e-5, (scene, method)


def test_readme_karis_statements_are_the_saved_run():
    rows = read_csv(SAVED / "method_zoo_karis.csv")
    # "Karis's "n = v = r is the larger error" holds in all 30 GGX cases"
    assert len(rows) == 30 and all(q["n_v_r_larger"] == "True" for q in rows)
    teapot = [float(q["n_v_r_over_split_sum"]) for q in rows if q["scene"] == "teapot"]
    sphere = [float(q["n_v_r_over_split_sum"]) for q in rows if q["scene"] == "sphere"]
    # "on the teapot the ratio is 1.2–7.2"; sphere: largest 26.8, smallest 1.08 (to their rounding)
    assert abs(min(teapot) - 1.2) <= 0.05 and abs(max(teapot) - 7.2) <= 0.05
    assert abs(max(sphere) - 26.8) <= 0.05 and abs(min(sphere) - 1.08) <= 0.005
    # teapot n = v = r step "0.3–6.8 % at roughness 0.1, 4.2–33.0 % at 0.3, 19.9–48.3 % at 0.6"
    for mat, lo, hi in (("ggx0.1", 0.3, 6.8), ("ggx0.3", 4.2, 33.0), ("ggx0.6", 19.9, 48.3)):
        v = [100 * float(q["n_v_r_rel_l1_frac"]) for q in rows if q["scene"] == "teapot" and q["material"] == mat]
        assert abs(min(v) - lo) <= 0.05 and abs(max(v) - hi) <= 0.05, (mat, min(v), max(v))


@pytest.mark.same_without_tools
def test_one_case_of_the_saved_run_reproduces(tmp_path):
    from ibl_ref.experiments import method_zoo
    from ibl_ref.prefilter import karis2013

    probe = method_zoo.probe_dir() / "city.exr"
    if not probe.exists():
        pytest.skip(f"the city probe is not at {probe} (set IBL_REF_PROBE_DIR)")
    with pytest.warns(Warning):  # the probe's few DWAB negatives are clamped and reported
        method_zoo.run(tmp_path, quick=False, scenes=["sphere"], envs=["city"], materials=["diffuse", "ggx0.3"],
                       methods=["split-sum", "sh9"])
    key = ("scene", "env", "material", "method")
    saved = {tuple(q[k] for k in key): q for q in read_csv(SAVED / "method_zoo.csv")}
    new = [q for q in read_csv(tmp_path / "method_zoo.csv") if q["applicable"] == "True"]
    assert len(new) == 2  # split-sum on GGX 0.3, SH9 on the diffuse material
    for q in new:
        old = saved[tuple(q[k] for k in key)]
        # the saved run's split sum used the dense texel sum as its exact chain; the chain is now the tree, within
        # EXACT_RTOL of it at every texel, so a pixel's value moves by ≤ EXACT_RTOL of itself and an error statistic
        # e by ≤ EXACT_RTOL·(1 + e) (the reference, the SH9 method and everything else are as they were: 1e-9)
        atol = (lambda v: karis2013.EXACT_RTOL * (1.0 + abs(v))) if q["method"] == "split-sum" else (lambda v: 0.0)
        for col in ("rel_l1_frac", "p99_rel_error_frac", "bias_frac", "ref_err_rel_l1_frac"):
            np.testing.assert_allclose(float(q[col]), float(old[col]), rtol=1e-9, atol=atol(float(old[col])),
                                       err_msg=col)
        assert q["memory_bytes"] == old["memory_bytes"] and q["n_pixels"] == old["n_pixels"]


def test_the_cmgen_row_is_its_saved_run_and_that_runs_split_sum_is_the_tables():
    # the cmgen row of the results page comes from a run of its own (sphere, five environments); its exact split
    # sum, run beside it, must agree with the main run's: the chain is the tree now (within EXACT_RTOL = 1e-4 of the
    # dense sum at every texel), so a rel. L1 moves by at most EXACT_RTOL·(1 + rel. L1)
    from ibl_ref.prefilter import karis2013

    key = ("scene", "env", "material", "method")
    main = {tuple(q[k] for k in key): q for q in read_csv(SAVED / "method_zoo.csv") if q["applicable"] == "True"}
    rows = [q for q in read_csv(SAVED / "method_zoo_cmgen.csv") if q["applicable"] == "True"]
    ss = [q for q in rows if q["method"] == "split-sum"]
    assert len(ss) == 15
    for q in ss:
        old = float(main[tuple(q[k] for k in key)]["rel_l1_frac"])
        assert abs(float(q["rel_l1_frac"]) - old) <= karis2013.EXACT_RTOL * (1 + old)
    # the page's numbers: cmgen at roughness 0.1 / 0.3 / 0.6, mean over the environments, to the printed 0.1 %
    cm = {mat: np.mean([float(q["rel_l1_frac"]) for q in rows if (q["method"], q["material"]) == ("cmgen", mat)])
          for mat in ("ggx0.1", "ggx0.3", "ggx0.6")}
    for mat, printed in (("ggx0.1", 25.0), ("ggx0.3", 15.4), ("ggx0.6", 20.6)):
        assert abs(100 * cm[mat] - printed) <= 0.05 + 1e-9, (mat, cm[mat])
    # and it is worse than the exact split sum on the same pixels in every GGX material (sampling noise on top)
    for mat in cm:
        exact = np.mean([float(q["rel_l1_frac"]) for q in ss if q["material"] == mat])
        assert cm[mat] > exact



# ---- the zoo at engine size (256² faces, sphere): tests/data/readme_runs/method-zoo-256 ----------------------------
SAVED_256 = ROOT / "tests" / "data" / "readme_runs" / "method-zoo-256"


def _means_256(scene="sphere"):
    acc = {}
    for q in read_csv(SAVED_256 / "method_zoo.csv"):
        if q["applicable"] == "True" and q["scene"] == scene:
            acc.setdefault((q["method"], q["material"]), []).append(float(q["rel_l1_frac"]))
    return {k: float(np.mean(v)) for k, v in acc.items()}


def test_the_256_run_is_complete_and_its_walks_add_up():
    rows = read_csv(SAVED_256 / "method_zoo.csv")
    # 2 scenes × 12 methods × 7 materials × 5 environments, each environment read at 256² faces; n_pixels: the
    # pixels of the scene's image, the same for every row of a scene
    assert len(rows) == 2 * 12 * 7 * 5 and {q["env"] for q in rows} == {"sky_sun", "city", "courtyard", "forest",
                                                                         "studio"}
    for scene in ("sphere", "teapot"):
        assert len({q["n_pixels"] for q in rows if q["scene"] == scene}) == 1
    # every reference converged to its target (estimated rel. L1 ≤ rtol = 2e-3)
    assert max(float(q["ref_err_rel_l1_frac"]) for q in rows) <= 2e-3
    # the increments of each walk add up to its last image's error against the reference (bias exactly, rel. L1 as a
    # triangle inequality: the sum of the steps' rel. L1 is at least the total)
    walks = {}
    for q in read_csv(SAVED_256 / "method_zoo_budget.csv"):
        walks.setdefault((q["scene"], q["env"], q["material"], q["method"]), []).append(q)
    assert len(walks) == sum(q["applicable"] == "True" for q in rows)
    for key, w in walks.items():
        total = float(w[-1]["bias_vs_ref_frac"])
        assert abs(sum(float(q["bias_increment_frac"]) for q in w) - total) <= 1e-12 * max(1.0, abs(total)), key
        assert sum(float(q["rel_l1_increment_frac"]) for q in w) >= float(w[-1]["rel_l1_vs_ref_frac"]) - 1e-12, key


def test_readme_256_headline_is_the_saved_run():
    import re

    row = next(ln for ln in (ROOT / "README.md").read_text().splitlines() if "method-zoo-256.md" in ln)
    means, small = _means_256(), _saved_means()
    steps = {}
    for q in read_csv(SAVED_256 / "method_zoo_budget.csv"):
        if q["scene"] == "sphere":
            steps.setdefault((q["method"], q["material"], q["step"]), []).append(float(q["rel_l1_increment_frac"]))
    mip = 100 * float(np.mean(steps[("split-sum", "ggx0.1", "mip")]))
    m = re.search(r"roughness 0\.1 falls from \*\*([\d.]+) %\*\* \(32²\) to \*\*([\d.]+) %\*\*", row)
    # 20.0 % is the 32² page's MIP step (docs/results/method-zoo.md), 7.7 % this run's, to their rounding
    assert m and float(m.group(1)) == 20.0 and abs(mip - float(m.group(2))) <= 0.05 + 1e-9, (mip, row)
    m = re.search(r"256 samples at roughness 0\.6: ([\d.]+) % → \*\*([\d.]+) %\*\*", row)
    is32 = 100 * small[("sphere", "split-sum-is-256", "ggx0.6")][0]
    is256 = 100 * means[("split-sum-is-256", "ggx0.6")]
    assert m and abs(is32 - float(m.group(1))) <= 0.05 + 1e-9 and abs(is256 - float(m.group(2))) <= 0.05 + 1e-9
    karis = read_csv(SAVED_256 / "method_zoo_karis.csv")
    m = re.search(r"holds in \*\*(\d+) of (\d+)\*\* GGX cases", row)
    assert m and int(m.group(2)) == len(karis) == 30
    assert int(m.group(1)) == sum(q["n_v_r_larger"] == "True" for q in karis)
    # the teapot: the visibility step is the largest of its walk in 127 of the 180 walks
    walks = {}
    for q in read_csv(SAVED_256 / "method_zoo_budget.csv"):
        if q["scene"] == "teapot":
            walks.setdefault((q["env"], q["material"], q["method"]), []).append(q)
    largest = [max(w, key=lambda q: float(q["rel_l1_increment_frac"]))["step"] for w in walks.values()]
    m = re.search(r"largest step in \*\*(\d+) of the (\d+)\*\* walks", row)
    assert m and (int(m.group(1)), int(m.group(2))) == (largest.count("visibility"), len(walks)) == (127, 180)
