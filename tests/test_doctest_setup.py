"""The doctest set-up of the root ``conftest.py`` and ``[tool.pytest.ini_options]``: the README's command
(``python -m pytest``) runs the Examples of ``ibl_ref/``; a module whose import needs a missing optional dependency
is skipped with the reason, by the one rule of the conftest (the missing module is none of the required
dependencies), while a missing required or package module stays an error.

End to end, in a subprocess: a throw-away package named ``ibl_ref`` in a temporary folder (it shadows the real one
there: ``python -m pytest`` puts the working folder first on ``sys.path``) with the project's own ``conftest.py`` and
``pyproject.toml``, so the real configuration is what runs.
"""

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

_GOOD = {
    "good.py": '''
def third():
    """One third, shown to four digits (NUMBER); a long list elided (ELLIPSIS).

    >>> third()
    0.3333
    >>> list(range(30))
    [0,  1, 2, ..., 29]
    """
    return 1 / 3
''',
    "wrong.py": '''
def two():
    """>>> two()
    3
    """
    return 2
''',
    "needs_optional.py": '"""Needs an extra."""\nimport no_such_optional_dependency_xyz\n',
}
#: a missing module of the package itself, a missing part of a required dependency: errors, never skips
_BROKEN = {
    "needs_package.py": "import ibl_ref.no_such_module_of_the_package\n",
    "needs_required.py": "import numpy.no_such_submodule_xyz\n",
}


def _run(tmp_path, modules, *args):
    pkg = tmp_path / "ibl_ref"
    pkg.mkdir()
    for name, text in {"__init__.py": '"""A stand-in package."""\n', **modules}.items():
        (pkg / name).write_text(text)
    shutil.copy(ROOT / "conftest.py", tmp_path / "conftest.py")
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "test_nothing.py").write_text("def test_nothing():\n    pass\n")
    r = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-p", "no:xdist", "-rs", "-v",
                        *args], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    return r.returncode, r.stdout + r.stderr


def test_readme_command_runs_doctests_and_skips_missing_optional_dependencies(tmp_path):
    rc, out = _run(tmp_path, _GOOD)
    assert rc == 1, out  # the wrong example fails the run
    assert "ibl_ref/good.py::ibl_ref.good.third PASSED" in out, out
    assert "tests/test_nothing.py::test_nothing PASSED" in out, out  # the tests run as before
    assert "ibl_ref/wrong.py::ibl_ref.wrong.two FAILED" in out, out
    assert ("ibl_ref/needs_optional.py: its import needs 'no_such_optional_dependency_xyz', an optional dependency "
            "that is not installed") in out, out
    assert "1 failed, 2 passed, 1 skipped" in out, out


@pytest.mark.parametrize("module", sorted(_BROKEN))
def test_missing_package_or_required_module_is_an_error(tmp_path, module):
    rc, out = _run(tmp_path, {module: _BROKEN[module]})
    assert rc == 2 and f"ERROR collecting ibl_ref/{module}" in out and "skipped" not in out, out


def test_doctests_of_the_package_only(tmp_path):
    rc, out = _run(tmp_path, _GOOD, "--collect-only", "-qq")
    items = [ln for ln in out.splitlines() if "::" in ln]
    assert items == ["tests/test_nothing.py::test_nothing", "ibl_ref/good.py::ibl_ref.good.third",
                     "ibl_ref/wrong.py::ibl_ref.wrong.two"], out


def _root_conftest():
    spec = importlib.util.spec_from_file_location("ibl_ref_root_conftest", ROOT / "conftest.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("name, expect", [("numba", "numba"), ("mitsuba", "mitsuba"), ("flip_evaluator",
                                                                                       "flip_evaluator"),
                                          ("dask.distributed", "dask"), ("numpy", None), ("scipy.special", None),
                                          ("OpenEXR", None), ("ibl_ref.groundtruth.gone", None)])
def test_optional_rule(name, expect):
    # the rule itself: an optional dependency is any module that is not a required one (nor the package); the
    # wrapping of pytest >= 8 (a CollectError caused by the import error) is looked through
    c = _root_conftest()
    exc = ModuleNotFoundError(f"No module named {name!r}", name=name)
    assert c.optional_missing(exc) == expect
    try:
        raise RuntimeError("collect error") from exc
    except RuntimeError as wrapped:
        assert c.optional_missing(wrapped) == expect
    assert c.optional_missing(ImportError("numba present but broken")) is None
