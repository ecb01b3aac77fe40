"""The README's method-zoo numbers, pinned to the full run they come from.

The full run (both scenes, five environments, every method; 16.8 min on 2 workers) is too long for a test, so its
two data files are kept in ``tests/data/readme_runs/method-zoo/`` (command, commit and date in the README there).
Three checks:

* every cell of the README's two tables (mean rel. L1 and mean p99 over the environments, memory) is what the
  saved ``method_zoo.csv`` gives, to the README's rounding;
* the README's Karis statements (the n = v = r step larger than the split-sum separation in all 30 GGX cases,
  the ratio ranges) are what the saved ``method_zoo_karis.csv`` gives, to the README's rounding;
* one case of that run, re-run here at the full run's settings (sphere, city probe, the diffuse and GGX 0.3
  materials, the exact split sum and SH9), reproduces its saved rows: the experiment is deterministic, so the
  tolerance is float64 rounding (1e-9 relative, which also absorbs a different BLAS thread count).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from ibl_ref.atomic import read_csv

ROOT = Path(__file__).resolve().parent.parent
SAVED = ROOT / "tests" / "data" / "readme_runs" / "method-zoo"
MIB = 1024.0 * 1024.0


def _readme_zoo_section() -> str:
    text = (ROOT / "README.md").read_text()
    start = text.index("## The method zoo")
    return text[start:text.index("\n## ", start + 5)]


def _readme_tables():
    """{scene: {(method, material): (rel_l1 %, p99 %)}, ...} and {scene: {method: memory MiB}} from the README."""
    sec = _readme_zoo_section()
    heads = {"sphere": sec.index("**Sphere**"), "teapot": sec.index("**Teapot on the ground**")}
    cells, memory = {}, {}
    for scene, at in heads.items():
        block = sec[sec.index("| method |", at):]
        lines = block.split("\n\n")[0].splitlines()
        cols = [c.strip() for c in lines[0].strip("|").split("|")]
        cells[scene], memory[scene] = {}, {}
        for line in lines[2:]:
            row = [c.strip() for c in line.strip("|").split("|")]
            method = row[0]
            for mat, cell in zip(cols[1:8], row[1:8]):
                m = re.fullmatch(r"([\d.]+) % \(([\d.]+) %\)", cell)
                if m:
                    cells[scene][(method, mat)] = (float(m.group(1)), float(m.group(2)))
                else:
                    assert cell == "n/a", (scene, method, mat, cell)
            memory[scene][method] = float(row[cols.index("memory (MiB)")])
    return cells, memory


def _saved_means():
    acc = {}
    for q in read_csv(SAVED / "method_zoo.csv"):
        if q["applicable"] == "True":
            acc.setdefault((q["scene"], q["method"], q["material"]), []).append(
                (float(q["rel_l1_frac"]), float(q["p99_rel_error_frac"]), float(q["memory_bytes"])))
    return {k: np.mean(np.array(v), axis=0) for k, v in acc.items()}


def test_readme_tables_are_the_saved_run():
    cells, memory = _readme_tables()
    means = _saved_means()
    # the README lists every applicable (scene, method, material) of the run and nothing else
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
    sec = _readme_zoo_section()
    rows = read_csv(SAVED / "method_zoo_karis.csv")
    assert len(rows) == 30 and all(q["n_v_r_larger"] == "True" for q in rows)
    assert "holds** in all 30 GGX cases" in sec
    teapot = [float(q["n_v_r_over_split_sum"]) for q in rows if q["scene"] == "teapot"]
    sphere = [float(q["n_v_r_over_split_sum"]) for q in rows if q["scene"] == "sphere"]
    # README: "on the teapot the ratio is 1.2–7.2"; sphere: largest 26.8, smallest 1.08 (README's rounding)
    assert "the ratio is 1.2–7.2" in sec
    assert abs(min(teapot) - 1.2) <= 0.05 and abs(max(teapot) - 7.2) <= 0.05
    assert "(26.8 at roughness 0.1)" in sec and "(1.08)" in sec
    assert abs(max(sphere) - 26.8) <= 0.05 and abs(min(sphere) - 1.08) <= 0.005
    # README: teapot n = v = r step 0.3–6.8 % at roughness 0.1, 4.2–33.0 % at 0.3, 19.9–48.3 % at 0.6
    for mat, lo, hi in (("ggx0.1", 0.3, 6.8), ("ggx0.3", 4.2, 33.0), ("ggx0.6", 19.9, 48.3)):
        v = [100 * float(q["n_v_r_rel_l1_frac"]) for q in rows if q["scene"] == "teapot" and q["material"] == mat]
        assert f"{lo}–{hi} % at" in sec.replace("\n  ", " ").replace("\n", " ")
        assert abs(min(v) - lo) <= 0.05 and abs(max(v) - hi) <= 0.05, (mat, min(v), max(v))


def test_one_case_of_the_saved_run_reproduces(tmp_path):
    from ibl_ref.experiments import method_zoo

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
        for col in ("rel_l1_frac", "p99_rel_error_frac", "bias_frac", "ref_err_rel_l1_frac"):
            np.testing.assert_allclose(float(q[col]), float(old[col]), rtol=1e-9, err_msg=col)
        assert q["memory_bytes"] == old["memory_bytes"] and q["n_pixels"] == old["n_pixels"]
