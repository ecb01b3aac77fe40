"""The package layout: every concept has one home, the README's concept table matches the code, old names work.

The README's table "Where each concept lives" lists, per paper concept, the module file and its public entry
points; this test parses that table and checks that each file exists, each entry point is defined *in that
module* (not re-exported from elsewhere), and that the package keeps no aliases of old module names.
"""

import ast
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


@pytest.mark.parametrize("short", ["convolve", "pyramid", "render", "envmap", "exr_io", "tonemap"])
def test_no_aliases_of_old_module_names(short):
    # the short module names of earlier versions were dropped with their import hook: one name per module
    assert not any(type(f).__module__ == "ibl_ref" for f in sys.meta_path)
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module(f"ibl_ref.{short}")
    with pytest.raises(AttributeError):
        getattr(ibl_ref, short)


def test_import_ibl_ref_is_cheap():
    # a fresh interpreter: importing the package loads no sub-module and no numpy
    code = ("import sys, ibl_ref; mods = [m for m in sys.modules if m.startswith('ibl_ref.') or m == 'numpy'];"
            "print(','.join(mods))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ""


def _imports(path: Path):
    """Every ``ibl_ref`` module a file imports (module level and inside functions: lazy imports count too), as
    (absolute module name, enclosing function or ``"<module>"``); relative imports resolved, ``from m import x``
    reported as both ``m`` and ``m.x``."""
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    pkg = parts[:-1] if parts[-1] != "__init__" else parts[:-1]
    if parts[-1] == "__init__":
        parts = parts[:-1]
    tree = ast.parse(path.read_text())
    parent = {c: n for n in ast.walk(tree) for c in ast.iter_child_nodes(n)}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = ".".join(pkg[:len(pkg) - node.level + 1] + ([node.module] if node.module else [])) \
                if node.level else node.module
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        fn = node
        while fn in parent and not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            fn = parent[fn]
        where = fn.name if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)) else "<module>"
        out += [(n, where) for n in names if n and (n == "ibl_ref" or n.startswith("ibl_ref."))]
    return out


def _library_files(*subs):
    return [p for sub in subs for p in sorted((ROOT / "ibl_ref" / sub).glob("*.py"))]


def _violations(files, forbidden, allow=()):
    bad = []
    for p in files:
        for name, where in _imports(p):
            if any(name == f or name.startswith(f + ".") for f in forbidden) and (p.name, where) not in allow:
                bad.append(f"{p.relative_to(ROOT)} ({where}) -> {name}")
    return sorted(set(bad))


def test_import_scan_sees_lazy_and_relative_imports(tmp_path):
    # the scanner itself: a function-level relative import is found and resolved
    f = ROOT / "ibl_ref" / "knuth2014" / "gloss_lookup.py"
    found = _imports(f)
    assert ("ibl_ref.conventions.phong_exponent", "<module>") in found
    assert ("ibl_ref.knuth2014.gloss_calibration", "__getattr__") in found


def test_ground_truth_does_not_import_the_approximation():
    # dependencies follow the data flow: nothing in groundtruth/ or environment/ imports the paper's approximation,
    # rendering or the lobe papers, and the ray-traced reference renderer (the ground truth of a render) does not
    # import the approximation either
    files = _library_files("environment", "groundtruth")
    bad = _violations(files, ["ibl_ref.knuth2014", "ibl_ref.rendering", "ibl_ref.lobes", "ibl_ref.experiments",
                              "ibl_ref.cli"])
    bad += _violations([ROOT / "ibl_ref" / "rendering" / "reference_render.py"], ["ibl_ref.knuth2014"])
    assert not bad, bad


def test_library_does_not_import_experiments_or_cli():
    # experiments and the CLI are thin layers on top: no library module imports them (not even lazily)
    files = _library_files("environment", "groundtruth", "knuth2014", "rendering", "lobes", "synthetic")
    files += [p for p in sorted((ROOT / "ibl_ref").glob("*.py")) if p.name not in ("__init__.py", "__main__.py")]
    assert not _violations(files, ["ibl_ref.experiments", "ibl_ref.cli"])


def test_run_time_lookup_does_not_import_the_analysis():
    # the glossiness lookup reads calibration tables; the Sec. 5 analysis that builds them
    # (knuth2014.lobe_analysis, knuth2014.gloss_calibration) is imported by no run-time module of the library —
    # only gloss_lookup's __getattr__ re-exports the builder's old names, when a caller asks for one of them
    files = _library_files("environment", "groundtruth", "knuth2014", "rendering", "lobes", "synthetic")
    files = [p for p in files if p.name not in ("lobe_analysis.py", "gloss_calibration.py")]
    bad = _violations(files, ["ibl_ref.knuth2014.lobe_analysis", "ibl_ref.knuth2014.gloss_calibration"],
                      allow={("gloss_lookup.py", "__getattr__")})
    assert not bad, bad
    # and at run time: PEM lookups, the Eq. 5 lookups and the pyramid lookup leave the analysis unloaded
    code = ("import sys, numpy as np\n"
            "from ibl_ref.knuth2014.pyramid import build_pyramid\n"
            "from ibl_ref.knuth2014.gloss_lookup import lookup\n"
            "from ibl_ref.knuth2014.median_cut import median_cut\n"
            "from ibl_ref.knuth2014.pem import build_pems\n"
            "c = np.random.default_rng(0).random((6, 8, 8, 3)) + 0.1\n"
            "d = np.array([[0.3, 0.4, 0.8]])\n"
            "lookup(build_pyramid(c), d, 0.7)\n"
            "build_pems(c, median_cut(c, 6)).lookup_all(d, 0.7)\n"
            "print(','.join(m for m in sys.modules if 'lobe_analysis' in m or 'gloss_calibration' in m))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ""
