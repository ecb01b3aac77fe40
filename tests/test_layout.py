"""The package layout: every concept has one home, the concept table matches the code, no old names linger.

The concept table "Where each concept lives" (``docs/concepts.csv``, rendered into ``docs/concepts.md``) lists, per
paper concept, the module file and its public entry points; this test reads that table and checks that each file
exists, each entry point is defined *in that module* (not re-exported from elsewhere), and that the package keeps no
aliases of old module names.
"""

import ast
import importlib
import re
import subprocess
import sys
from pathlib import Path

import pytest

import ibl_ref
from ibl_ref.atomic import read_csv

ROOT = Path(__file__).resolve().parent.parent


def _concept_rows():
    rows = []
    for q in read_csv(ROOT / "docs" / "concepts.csv"):
        if not q["module"].startswith("`ibl_ref/"):
            continue
        paths = re.findall(r"`(ibl_ref/[\w/]+\.py)`", q["module"])
        names = re.findall(r"`([A-Za-z_][A-Za-z0-9_]*)`", q["entry_points"])
        rows.append((q["concept"], paths, names))
    return rows


ROWS = _concept_rows()


#: optional dependencies (extras of pyproject.toml) whose modules the concept table may name
_OPTIONAL = {"numba", "llvmlite", "embreex", "mitsuba", "dask", "flip_evaluator"}


def test_concept_table_is_not_empty():
    assert len(ROWS) >= 25


@pytest.mark.parametrize("concept,paths,names", ROWS, ids=[r[0][:40] for r in ROWS])
def test_concept_table_matches_code(concept, paths, names):
    assert paths and names, f"{concept}: no module or no entry point named"
    mods = []
    for path in paths:
        assert (ROOT / path).is_file(), f"{concept}: {path} does not exist"
        try:
            mods.append(importlib.import_module(path[:-3].replace("/", ".")))
        except ModuleNotFoundError as exc:  # a module of an optional extra (the numba kernels without `fast`)
            if exc.name not in _OPTIONAL:
                raise
            pytest.skip(f"{path} needs {exc.name}, an optional dependency that is not installed")
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


def _imports(path: Path, root: Path = ROOT):
    """Every ``ibl_ref`` module a file imports (module level and inside functions: lazy imports count too), as
    (absolute module name, enclosing function or ``"<module>"``); relative imports resolved, ``from m import x``
    reported as both ``m`` and ``m.x`` (as ``m.x`` only when every x is a sub-module of package m)."""
    rel = path.relative_to(root).with_suffix("")
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
            subs = [f"{base}.{a.name}" for a in node.names]
            # ``from p import m, n`` of sub-modules imports m and n (p's __init__ runs first, as for every import of
            # a sub-module, ``from p.m import x`` too: not an import of p); otherwise p and p.x are both reported
            mods = all((root.joinpath(*s.split(".")).with_suffix(".py")).is_file()
                       or (root.joinpath(*s.split(".")) / "__init__.py").is_file() for s in subs)
            names = subs if mods else [base] + subs
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
    f = ROOT / "ibl_ref" / "knuth2014" / "pem.py"
    found = _imports(f)
    assert ("ibl_ref.environment.validated.as_environment", "<module>") in found
    assert ("ibl_ref.knuth2014.pyramid", "iter_pem_chunks") in found


def test_ground_truth_does_not_import_the_approximation():
    # dependencies follow the data flow: nothing in groundtruth/ or environment/ imports the paper's approximation,
    # rendering or the lobe papers, and the ray-traced reference renderer (the ground truth of a render) does not
    # import the approximation either
    files = _library_files("environment", "groundtruth")
    bad = _violations(files, ["ibl_ref.knuth2014", "ibl_ref.prefilter", "ibl_ref.rendering", "ibl_ref.lobes",
                              "ibl_ref.experiments", "ibl_ref.cli"])
    bad += _violations([ROOT / "ibl_ref" / "rendering" / "reference_render.py"],
                       ["ibl_ref.knuth2014", "ibl_ref.prefilter"])
    assert not bad, bad


def test_library_does_not_import_experiments_or_cli():
    # experiments and the CLI are thin layers on top: no library module imports them (not even lazily)
    files = _library_files("environment", "groundtruth", "knuth2014", "prefilter", "rendering", "lobes", "synthetic")
    files += [p for p in sorted((ROOT / "ibl_ref").glob("*.py")) if p.name not in ("__init__.py", "__main__.py")]
    assert not _violations(files, ["ibl_ref.experiments", "ibl_ref.cli"])


def test_run_time_lookup_does_not_import_the_analysis():
    # the glossiness lookup reads calibration tables; the Sec. 5 analysis that builds them
    # (knuth2014.lobe_analysis, knuth2014.gloss_calibration) is imported by no run-time module of the library, not
    # even lazily
    files = _library_files("environment", "groundtruth", "knuth2014", "prefilter", "rendering", "lobes", "synthetic")
    files = [p for p in files if p.name not in ("lobe_analysis.py", "gloss_calibration.py")]
    bad = _violations(files, ["ibl_ref.knuth2014.lobe_analysis", "ibl_ref.knuth2014.gloss_calibration"])
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
            "from ibl_ref.prefilter import build_prefilter\n"
            "build_prefilter(c, 'pyramid').lookup(d, 3.0)\n"
            "print(','.join(m for m in sys.modules if 'lobe_analysis' in m or 'gloss_calibration' in m))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ""


# ---- the import graph: no cycles between files, none between sub-packages -------------------------------------------

def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _import_graph(root: Path = ROOT) -> dict:
    """module → set of the package's modules it imports (lazy imports too), from the source with ``ast``."""
    files = {_module_name(p, root): p for p in sorted((root / "ibl_ref").rglob("*.py"))}
    return {m: {n for n, _ in _imports(p, root) if n in files and n not in (m, "ibl_ref")} for m, p in files.items()}


def _cycles(graph: dict) -> list:
    """The strongly connected components with more than one node (Tarjan, iterative), each sorted."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return sorted(out)


def _unit(module: str) -> str:
    """The sub-package of a module (``ibl_ref.knuth2014.pem`` → ``ibl_ref.knuth2014``); a top-level module is its
    own unit (``ibl_ref.errors``)."""
    parts = module.split(".")
    return module if len(parts) <= 2 and not (ROOT / "ibl_ref" / parts[-1]).is_dir() else ".".join(parts[:2])


def test_cycle_finder_finds_a_lazy_cycle(tmp_path):
    # the graph machinery itself: a cycle through a function-level relative import is found, a chain is not
    pkg = tmp_path / "ibl_ref" / "sub"
    pkg.mkdir(parents=True)
    (tmp_path / "ibl_ref" / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from .b import x\n")
    (pkg / "b.py").write_text("def x():\n    from . import a\n")
    (pkg / "c.py").write_text("from ibl_ref.sub.a import x\n")
    graph = _import_graph(tmp_path)
    assert graph["ibl_ref.sub.b"] == {"ibl_ref.sub.a"}
    assert _cycles(graph) == [["ibl_ref.sub.a", "ibl_ref.sub.b"]]
    assert _cycles({"p": {"q"}, "q": {"r"}, "r": set()}) == []


def test_no_import_cycles_between_files():
    # every module can be read (and imported) without its importers: no file imports one of its own importers,
    # not even lazily inside a function
    cycles = _cycles(_import_graph())
    assert not cycles, cycles


def test_no_import_cycles_between_sub_packages():
    # the sub-packages form layers (environment → ground truth → lobe papers → the paper's approximation →
    # prefilter methods → rendering → experiments, CLI); a top-level module (errors, conventions, …) counts as a
    # unit of its own
    units = {}
    for m, deps in _import_graph().items():
        units.setdefault(_unit(m), set()).update(_unit(d) for d in deps if _unit(d) != _unit(m))
    assert "ibl_ref.prefilter" in units and "ibl_ref.errors" in units
    assert not _cycles(units), _cycles(units)


def test_lobe_papers_do_not_import_the_approximation_or_rendering():
    # the lobe papers (BRDFs, Kautz & McCool fits and maps, Meunier's algebra) sit below the paper's approximation,
    # the prefilter methods and the renderers, which all use them (the renderers use lobes.brdfs)
    bad = _violations(_library_files("lobes"), ["ibl_ref.knuth2014", "ibl_ref.prefilter", "ibl_ref.rendering"])
    assert not bad, bad


def test_errors_module_imports_nothing_of_the_package():
    # every module raises IBLError: errors.py is the bottom of the graph
    assert _import_graph()["ibl_ref.errors"] == set()


def _module_level_names(tree):
    defined, imported = set(), set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            defined.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            defined |= {n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)}
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            imported |= {a.asname or a.name.split(".")[0] for a in node.names}
    return defined, imported


def _public_api_back_doors(root: Path = ROOT / "ibl_ref") -> list:
    """Modules (not package ``__init__`` files, which gather their sub-modules' names on purpose) that pass another
    module's names off as their own: ``__all__`` entries defined elsewhere, a module ``__getattr__`` that forwards
    names, or an import kept only to be re-exported (``# noqa: F401``)."""
    found = []
    for path in sorted(root.rglob("*.py")):
        if path.name == "__init__.py":
            continue
        src = path.read_text()
        tree = ast.parse(src)
        defined, _ = _module_level_names(tree)
        for node in tree.body:
            if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets):
                found += [f"{path.name}: __all__ lists {n!r}, defined elsewhere"
                          for n in ast.literal_eval(node.value) if n not in defined]
            if isinstance(node, ast.FunctionDef) and node.name == "__getattr__":
                found.append(f"{path.name}: module __getattr__")
        for i, line in enumerate(src.splitlines(), 1):
            if re.search(r"^\s*(from|import)\b.*noqa:[^#]*F401", line) and not line.startswith((" ", "\t")):
                found.append(f"{path.name}:{i}: module-level import kept for re-export")
    return found


def test_no_back_doors_in_the_public_api():
    # one home per name: a caller imports a name from where it is defined (an optional-dependency probe inside a
    # function, `import embreex  # noqa: F401`, is not a re-export and is not flagged)
    assert _public_api_back_doors() == []


def test_back_door_finder_finds_each_kind(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "a.py").write_text("from .b import f  # noqa: F401\n__all__ = ['f', 'g']\n\ndef g():\n    pass\n")
    (pkg / "c.py").write_text("def __getattr__(name):\n    raise AttributeError(name)\n")
    (pkg / "__init__.py").write_text("from .a import g\n__all__ = ['g']\n")
    found = _public_api_back_doors(pkg)
    assert len(found) == 3 and any("'f'" in f for f in found) and any("__getattr__" in f for f in found)


# ---- names that only fail when the line runs ------------------------------------------------------------------------
#: pyflakes' checks (as implemented by ruff) for a name that is used but bound nowhere in reach: a function-local
#: import removed or a module-level name moved elsewhere breaks only the code path that runs the line, which a test of
#: another path never sees
_UNDEFINED_NAME_RULES = "F821,F822,F823"


def _undefined_names(*paths) -> tuple[int, str]:
    pytest.importorskip("ruff")  # in the test extra
    r = subprocess.run([sys.executable, "-m", "ruff", "check", "--isolated", "--no-cache", "--output-format", "concise",
                        "--select", _UNDEFINED_NAME_RULES, *map(str, paths)],
                       capture_output=True, text=True, timeout=300, cwd=ROOT)
    return r.returncode, r.stdout


def test_no_undefined_names():
    rc, out = _undefined_names("ibl_ref", "experiments", "benchmarks", "tests")
    assert rc == 0, out


def test_undefined_name_check_finds_a_function_local_name(tmp_path):
    (tmp_path / "m.py").write_text("def f():\n    return SH_L_MAX\n")
    rc, out = _undefined_names(tmp_path / "m.py")
    assert rc != 0 and "SH_L_MAX" in out
