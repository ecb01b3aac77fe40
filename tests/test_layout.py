"""The package layout: every concept has one home, the README's concept table matches the code, old names work.

The README's table "Where each concept lives" lists, per paper concept, the module file and its public entry
points; this test parses that table and checks that each file exists, each entry point is defined *in that
module* (not re-exported from elsewhere), and that the pre-layout short module names
(``ibl_ref.convolve``, ``ibl_ref.pyramid``, …) are the very same module objects.
"""

import importlib
import re
import subprocess
import sys
from pathlib import Path

import pytest

import ibl_ref

ROOT = Path(__file__).resolve().parent.parent


def _concept_rows():
    text = (ROOT / "README.md").read_text()
    start = text.index("## Where each concept lives")
    end = text.index("\n## ", start + 5)
    rows = []
    for line in text[start:end].splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 4 or not cells[2].startswith("`ibl_ref/"):
            continue
        paths = re.findall(r"`(ibl_ref/[\w/]+\.py)`", cells[2])
        names = re.findall(r"`([A-Za-z_][A-Za-z0-9_]*)`", cells[3])
        rows.append((cells[0], paths, names))
    return rows


ROWS = _concept_rows()


def test_concept_table_is_not_empty():
    assert len(ROWS) >= 25


@pytest.mark.parametrize("concept,paths,names", ROWS, ids=[r[0][:40] for r in ROWS])
def test_concept_table_matches_code(concept, paths, names):
    assert paths and names, f"{concept}: no module or no entry point named"
    mods = []
    for path in paths:
        assert (ROOT / path).is_file(), f"{concept}: {path} does not exist"
        mods.append(importlib.import_module(path[:-3].replace("/", ".")))
    for name in names:
        homes = [m for m in mods if getattr(getattr(m, name, None), "__module__", None) == m.__name__]
        assert homes, f"{concept}: {name} is not defined in {', '.join(paths)}"


@pytest.mark.parametrize("short", sorted(ibl_ref.MOVED))
def test_short_module_names_are_the_same_modules(short):
    old = importlib.import_module(f"ibl_ref.{short}")
    new = importlib.import_module(f"ibl_ref.{ibl_ref.MOVED[short]}")
    assert old is new
    assert getattr(ibl_ref, short) is new


def test_import_ibl_ref_is_cheap():
    # a fresh interpreter: importing the package loads no sub-module and no numpy
    code = ("import sys, ibl_ref; mods = [m for m in sys.modules if m.startswith('ibl_ref.') or m == 'numpy'];"
            "print(','.join(mods))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ""


def test_ground_truth_does_not_import_the_approximation():
    # dependencies follow the data flow: nothing in groundtruth/ or environment/ imports knuth2014/ or rendering/
    bad = []
    for sub in ("environment", "groundtruth"):
        for p in (ROOT / "ibl_ref" / sub).glob("*.py"):
            src = p.read_text()
            for other in ("knuth2014", "rendering", "experiments", "cli"):
                if re.search(rf"from \.\.{other}\b|from \.\.{other} import|ibl_ref\.{other}\b.*import|import ibl_ref\.{other}", src):
                    bad.append(f"{p.relative_to(ROOT)} -> {other}")
    assert not bad, bad
