"""The documentation's result pages are generated from the saved run data and cannot drift from it.

* Every page of ``docs/results/`` (and ``docs/concepts.md``) is what ``docs/make_results.py`` writes from
  ``tests/data/readme_runs/<name>/`` and its template today, byte for byte: a data file, a template or the script
  changed without regenerating the pages fails here.
* Every data folder says where its numbers come from (``run.json``: each file listed once, with its command or its
  source) and has a page.
* The tables transcribed from the README of commit 537f533 (no data file had been kept for them) are checked for
  what their own columns imply: a verdict against the times it was computed from, a sum against its terms, each to
  the rounding of the printed digits.  A mistyped cell fails.
* The README is a front door of at most 250 lines whose headline numbers are on the pages they link to.
"""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import pytest

from ibl_ref.atomic import read_csv

#: slow and the same in every installation (NumPy path, no optional tool): phase 2+3 of .ci/run skips it
pytestmark = pytest.mark.same_without_tools

ROOT = Path(__file__).resolve().parent.parent
SAVED = ROOT / "tests" / "data" / "readme_runs"


def _make_results():
    spec = importlib.util.spec_from_file_location("make_results", ROOT / "docs" / "make_results.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


MR = _make_results()


# ---- generated pages ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("path", sorted(MR.outputs()), ids=lambda p: p.name)
def test_page_is_regenerated_byte_for_byte(path):
    want = MR.outputs()[path]
    assert path.exists(), f"{path.relative_to(ROOT)} is missing: run python docs/make_results.py"
    assert path.read_text(encoding="utf-8") == want, f"{path.relative_to(ROOT)} is stale: run python docs/make_results.py"


def test_no_stray_result_pages():
    # a page whose data folder was removed would otherwise linger, no longer checked
    assert {p.name for p in (ROOT / "docs" / "results").glob("*.md")} == {f"{n}.md" for n in MR.PAGES}


def test_a_missing_placeholder_value_is_an_error():
    with pytest.raises(KeyError, match="nothing"):
        MR.fill("a {{nothing}} b", {}, "test")
    assert MR.fill("a {{x}} b {{ x }}", {"x": "1"}, "test") == ("a 1 b 1", {"x"})


def test_every_data_folder_has_its_provenance_and_a_page():
    folders = sorted(p for p in SAVED.iterdir() if p.is_dir())
    assert {p.name for p in folders} == set(MR.PAGES)
    for folder in folders:
        meta = json.loads((folder / "run.json").read_text(encoding="utf-8"))
        listed = [f for run in meta["runs"] for f in run["files"]]
        assert len(listed) == len(set(listed)), folder.name
        assert set(listed) == {p.name for p in folder.iterdir() if p.name != "run.json"}, folder.name
        for run in meta["runs"]:
            # a run is described by its command (and commit or date) or by where its numbers were transcribed from
            assert run.get("source") or (run.get("command") and (run.get("commit") or run.get("date"))), (folder, run)


def test_claims_rows_name_existing_runs():
    for q in MR.claims_rows():
        assert q["statement"] and q["measured"] and q["command"], q
        if q["data_run"]:
            assert (SAVED / q["data_run"] / "run.json").exists(), q["data_run"]
        else:
            assert "{{" not in q["measured"] + q["statement"], q  # placeholders only where a run fills them


# ---- transcribed tables: what their own columns imply --------------------------------------------------------------
def _half(text: str) -> float:
    """Half a unit of the last printed digit of ``text``."""
    return 0.5 * 10.0 ** -(len(text.split(".")[1]) if "." in text else 0)


def _ratio_range(a: str, b: str) -> tuple[float, float]:
    """The range of a / b for the printed a and b (each within half a unit of its last digit)."""
    da, db = _half(a), _half(b)
    return (float(a) - da) / (float(b) + db), (float(a) + da) / max(float(b) - db, 1e-12)


def _within(printed: str, lo: float, hi: float) -> bool:
    return lo - _half(printed) - 1e-12 <= float(printed) <= hi + _half(printed) + 1e-12


def test_bench_peer_verdicts_follow_from_the_cells():
    folder = SAVED / "bench-peer-aot"
    cells = {(q["scene"], q["face_size_texels"], q["exponents"], q["tool"], q["mode"]): q
             for q in read_csv(folder / "cells.csv")}
    floor = {(q["scene"], q["face_size_texels"]): q["wall_s"] for q in read_csv(folder / "interpreter_floor.csv")}
    verdicts = read_csv(folder / "verdicts.csv")
    assert len(verdicts) == 56 and len(cells) == 56 * 6
    for v in verdicts:
        k = (v["scene"], v["face_size_texels"], v["exponents"])
        cmft = cells[k + ("cmft", "process")]
        lab_in = cells[k + ("lab compiled", "in-process")]
        lab_proc = min((cells[k + (t, "process")] for t in ("lab numpy", "lab compiled")), key=lambda q: float(q["wall_s"]))
        inproc, proc = v["in_process_compiled_le_cmft"], v["process_better_kernel_le_cmft"]
        if cmft["status"] == "killed":
            assert inproc == proc == "yes (cmft killed)", k
            continue
        m = re.fullmatch(r"(yes|no) \(([\d.]+)×\)", inproc)
        assert m, inproc
        lo, hi = _ratio_range(lab_in["wall_s"], cmft["wall_s"])
        assert _within(m.group(2), lo, hi), (k, inproc, lab_in["wall_s"], cmft["wall_s"])
        assert (m.group(1) == "yes") == (float(m.group(2)) <= 1.0), (k, inproc)
        m = re.fullmatch(r"(yes|no) \(([\d.]+)×\)", proc)
        if m:  # cmft ≥ 0.5 s: the ratio to cmft's whole run
            assert float(cmft["wall_s"]) >= 0.5 - 0.005, (k, proc)
            lo, hi = _ratio_range(lab_proc["wall_s"], cmft["wall_s"])
            assert _within(m.group(2), lo, hi), (k, proc)
            assert (m.group(1) == "yes") == (float(m.group(2)) <= 1.0), (k, proc)
            continue
        m = re.fullmatch(r"(yes|no) \(([\d.]+) s vs cmft \+ floor ([\d.]+) s\)", proc)
        assert m, (k, proc)  # below 0.5 s of cmft: against cmft + the cell's interpreter floor
        assert float(cmft["wall_s"]) < 0.5, (k, proc)
        assert m.group(2) == lab_proc["wall_s"], (k, proc, lab_proc)
        target = float(cmft["wall_s"]) + float(floor[k[:2]])
        assert abs(float(m.group(3)) - target) <= 0.01 + 1e-9, (k, proc, target)  # two rounded terms
        assert (m.group(1) == "yes") == (float(m.group(2)) <= float(m.group(3))), (k, proc)


def test_cross_validate_excess_is_rel_l1_minus_noise():  # runs without Mitsuba (the saved run's data only)
    rows = read_csv(SAVED / "cross-validate" / "cross_validate.csv")
    assert len(rows) == 24
    for q in rows:
        excess = float(q["rel_l1_pct"]) - float(q["mitsuba_noise_pct"])
        assert abs(float(q["excess_pct"]) - excess) <= 0.0015 + 1e-9, q  # three numbers rounded to 0.001
        assert float(q["excess_pct"]) <= 0.5  # the lab's target: excess ≤ 0.5 % on every row


def test_small_cells_targets_add_up():
    rows = read_csv(SAVED / "bench-small-cells" / "small_cells.csv")
    assert len(rows) == 16
    for q in rows:
        target = float(q["cmft_ms"]) + float(q["io_floor_ms"])
        assert abs(float(q["process_target_ms"]) - target) <= 0.1 + 1e-9, q  # two rounded terms
        assert q["floor_exceeds_target"] == ("yes" if float(q["lab_floor_ms"]) > float(q["process_target_ms"]) else "no")
        python = float(q["repeated_call_ms"]) - float(q["kernels_ms"])
        assert abs(float(q["python_ms"]) - python) <= 0.15 + 1e-9, q  # three rounded numbers


def test_quick_start_runs_are_complete():
    rows = {q["run"]: q for q in read_csv(SAVED / "quick-start" / "runs.csv")}
    phases = [rows[f"CI phase {k}: {what}"] for k, what in ((1, "with Mitsuba"), (2, "without Mitsuba"),
                                                              (3, "without numba"))]
    # the whole .ci/run is longer than its three test phases together
    assert float(rows["CI: the whole .ci/run"]["wall_s"]) > sum(float(q["wall_s"]) for q in phases)
    assert int(phases[1]["skipped"]) - int(phases[0]["skipped"]) == 16  # the 16 Mitsuba tests


# ---- the README: a front door ------------------------------------------------------------------------------------
def _readme() -> str:
    return (ROOT / "README.md").read_text(encoding="utf-8")


def test_readme_is_a_front_door():
    assert len(_readme().splitlines()) <= 250


def test_readme_links_exist():
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", _readme()):
        if "://" not in target:
            assert (ROOT / target).exists(), target


def test_headline_numbers_are_on_their_pages():
    # every row of the README's headline table links to a generated page that states the row's bold number
    text = _readme()
    start = text.index("## Headline findings")
    rows = [ln for ln in text[start:text.index("\n## ", start + 5)].splitlines() if ln.startswith("| ")][1:]
    assert len(rows) >= 8
    for row in rows:
        link = re.search(r"\]\((docs/results/[\w-]+\.md)\)", row)
        numbers = re.findall(r"\*\*([^*]+)\*\*", row)
        assert link and numbers, row
        page = (ROOT / link.group(1)).read_text(encoding="utf-8")
        for number in numbers:
            assert number in page, (number, link.group(1))
