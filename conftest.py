"""Session settings shared by the test suite and the doctests of the package.

``[tool.pytest.ini_options]`` of ``pyproject.toml`` runs ``--doctest-modules`` over ``ibl_ref/`` beside ``tests/``, so
every Examples section of a docstring runs in CI (``python -m pytest -n 2``, the README's command).  Collecting
doctests imports every module of the package; this file

* runs the doctests of the package only (the modules under ``ibl_ref/``: the test modules hold none), and
* skips, with the reason, the doctests of a module whose import needs an optional dependency that is not installed
  (numba, Mitsuba, dask, embreex, flip: the extras of ``pyproject.toml``): one rule, *the missing module is none of
  the package's required dependencies* (``importlib.metadata.requires("ibl_ref")`` without an ``extra`` marker),
  so no list of modules is kept by hand.  A missing required dependency or a missing module of ``ibl_ref`` itself
  stays a collection error.

The defaults of ``tests/conftest.py`` are set here too, before the doctests import any module of the package:
figures are written, never shown (a non-interactive matplotlib backend); progress lines are silenced; the
convolution kernel is the NumPy reference unless set (an example never waits for the compiled kernels' first build).
"""

import importlib.metadata
import os
import re
from pathlib import Path

import pytest
from _pytest.doctest import DoctestModule

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("IBL_REF_PROGRESS", "0")
os.environ.setdefault("IBL_REF_KERNEL", "numpy")

_PACKAGE = Path(__file__).resolve().parent / "ibl_ref"


def required_modules() -> frozenset:
    """Lower-case top-level names of the package's required dependencies (and ``ibl_ref`` itself), from the
    installed metadata: the distributions ``requires`` lists without an ``extra == ...`` marker (``OpenEXR`` →
    ``openexr``; each of them imports under its own name)."""
    try:
        reqs = importlib.metadata.requires("ibl_ref") or []
    except importlib.metadata.PackageNotFoundError:  # not installed: every missing module is an error
        return frozenset()
    names = {re.match(r"[A-Za-z0-9._-]+", r).group(0).lower().replace("-", "_") for r in reqs if "extra ==" not in r}
    return frozenset(names | {"ibl_ref"})


def optional_missing(exc: BaseException):
    """The top-level name of the module whose absence caused ``exc`` (an import failure while collecting), if it is
    an optional dependency; None for any other failure."""
    while exc is not None and not isinstance(exc, ModuleNotFoundError):
        exc = exc.__cause__  # pytest >= 8 wraps the import error in a CollectError
    if exc is None or not exc.name:
        return None
    required = required_modules()
    top = exc.name.split(".")[0]
    return top if required and top.lower() not in required else None


class PackageDoctests(DoctestModule):
    """The doctests of one module of ``ibl_ref``, skipped with the reason when its import needs a missing optional
    dependency."""

    def collect(self):
        try:
            yield from super().collect()
        except (ImportError, pytest.Collector.CollectError) as exc:  # pytest 7 raises the first, 8+ the second
            top = optional_missing(exc)
            if top is None:
                raise
            pytest.skip(f"{self.path.relative_to(_PACKAGE.parent)}: its import needs {top!r}, an optional "
                        "dependency that is not installed")


@pytest.hookimpl(hookwrapper=True)
def pytest_collect_file(file_path, parent):
    """Doctests of ``ibl_ref/`` only, each module as a :class:`PackageDoctests`."""
    outcome = yield
    out = []
    for node in outcome.get_result() or []:
        if type(node) is DoctestModule:
            if _PACKAGE not in Path(file_path).resolve().parents:
                continue
            node = PackageDoctests.from_parent(parent, path=file_path)
        out.append(node)
    outcome.force_result(out)
