"""Tests that need an optional tool the README's commands do not install skip with the reason.

Mitsuba 3's ``llvm_ad_rgb`` variant needs libLLVM >= 17, which stock Debian 12 (Python 3.11) does not ship.  Every
test that renders with Mitsuba must request the ``mitsuba_llvm`` fixture of ``conftest.py`` (skip with the reason,
or fail under ``IBL_REF_REQUIRE_MITSUBA=1``); ``.ci/run`` proves it by running the whole suite a second time with
Mitsuba made unavailable.  This test keeps a new Mitsuba test from bypassing the fixture (an ``importorskip`` of
the package is not enough: the package imports, its variant then cannot run).
"""

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parent
#: source text that means a test runs Mitsuba (directly or through an experiment / the CLI)
MITSUBA_MARKERS = ("render_mitsuba", "mitsuba_envmap", "select_variant(", "import mitsuba", "cross-validate",
                   "cross_validate", "--mode\", \"mitsuba", "mode=\"mitsuba\"", "'mitsuba'")
#: tests that mention Mitsuba but are written to run without it (they check the behaviour when it is missing)
RUN_WITHOUT_MITSUBA_OK = "# runs without Mitsuba"


def _test_functions():
    for path in sorted(TESTS.glob("test_*.py")):
        if path.name == Path(__file__).name:
            continue
        src = path.read_text()
        tree = ast.parse(src)
        module_uses = "mitsuba_llvm" in "".join(ast.get_source_segment(src, n) or "" for n in tree.body
                                                if isinstance(n, ast.Assign)
                                                and any(getattr(t, "id", "") == "pytestmark" for t in n.targets))
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.name.startswith("test_"):
                seg = ast.get_source_segment(src, node) or ""
                deco = "".join(ast.get_source_segment(src, d) or "" for d in node.decorator_list)
                yield path.name, node.name, seg, deco, module_uses


def test_every_mitsuba_test_goes_through_the_fixture():
    offenders = []
    for fname, name, seg, deco, module_uses in _test_functions():
        if not any(m in seg for m in MITSUBA_MARKERS) or RUN_WITHOUT_MITSUBA_OK in seg:
            continue
        if not (module_uses or "mitsuba_llvm" in seg or "mitsuba_llvm" in deco):
            offenders.append(f"{fname}::{name}")
    assert offenders == [], ("these tests use Mitsuba without the mitsuba_llvm fixture (they would fail instead "
                             f"of skipping on a machine without libLLVM >= 17): {offenders}")


def test_the_scan_sees_the_known_mitsuba_tests():
    # the check above is only as good as its markers: the known Mitsuba tests must be recognised
    seen = {(f, n) for f, n, seg, _, _ in _test_functions() if any(m in seg for m in MITSUBA_MARKERS)}
    assert ("test_experiment_jobs.py", "test_cross_validate_cases_on_dask_match_serial") in seen
    assert any(f == "test_mitsuba_render.py" for f, _ in seen)

