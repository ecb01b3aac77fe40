"""Test-session settings: figures are written, never shown (a non-interactive matplotlib backend chosen
through the environment, as the library itself never switches backends); progress lines silenced unless a
test asks for them; the convolution kernel pinned to the NumPy reference (``IBL_REF_KERNEL=numpy`` unless set:
the tests of the compiled kernels ask for ``kernel="compiled"`` themselves, ``tests/test_compiled_kernels.py``);
the ``mitsuba_llvm`` fixture for tests that run Mitsuba; the ``cmft`` fixture for tests that run the peer tool
cmft (``$IBL_REF_CMFT``, by default ``../shared/peers/cmft/cmft`` beside the project, where CI keeps it); the
``cmgen`` fixture for tests that run Filament's cmgen (``$IBL_REF_CMGEN`` or ``cmgen`` on PATH)."""

import os
from pathlib import Path

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("IBL_REF_PROGRESS", "0")
os.environ.setdefault("IBL_REF_KERNEL", "numpy")
_CMFT = Path(__file__).resolve().parent.parent.parent / "shared" / "peers" / "cmft" / "cmft"
if "IBL_REF_CMFT" not in os.environ and _CMFT.is_file():
    os.environ["IBL_REF_CMFT"] = str(_CMFT)


def _refuse_if_same_without_tools(request, what):
    """A test marked ``same_without_tools`` (pyproject.toml) promises the NumPy path only: one that ``what``
    (asks for Mitsuba or the compiled kernels) would be skipped without being run in .ci/run's second run of the
    suite without the optional tools, so it fails here instead."""
    if request.node.get_closest_marker("same_without_tools") is not None:
        pytest.fail(f"{request.node.nodeid} is marked same_without_tools but {what}")


def pytest_collection_modifyitems(config, items):
    """A ``same_without_tools`` test may not ask for the compiled kernels in its own code (the switch of
    ``IBL_REF_KERNEL`` stays on the NumPy reference set above); Mitsuba is refused by the fixture."""
    import inspect
    import re

    asks = re.compile(r"""kernel\s*=\s*["']compiled|IBL_REF_KERNEL|numba_available|import numba""")
    for item in items:
        fn = getattr(item, "function", None)
        if fn is not None and item.get_closest_marker("same_without_tools") is not None \
                and asks.search(inspect.getsource(fn)):
            raise pytest.UsageError(f"{item.nodeid} is marked same_without_tools but asks for the compiled kernels")


@pytest.fixture
def cmft():
    """The cmft binary (:func:`ibl_ref.prefilter.cmft_peer.cmft_binary`); the test is skipped with the reason
    where there is none."""
    from ibl_ref.prefilter.cmft_peer import CmftUnavailable, cmft_binary

    try:
        return cmft_binary()
    except CmftUnavailable as exc:
        pytest.skip(str(exc))


@pytest.fixture
def cmgen():
    """The cmgen binary (:func:`ibl_ref.prefilter.cmgen_peer.cmgen_binary`).  Where there is none the test is
    skipped with the reason, or fails when ``IBL_REF_REQUIRE_CMGEN=1`` (set by ``.ci/run``, which installs
    ``libfilament-tools``, so that CI runs the cmgen tests for real and never skips them silently)."""
    from ibl_ref.prefilter.cmgen_peer import CmgenUnavailable, cmgen_binary

    try:
        return cmgen_binary()
    except CmgenUnavailable as exc:
        if os.environ.get("IBL_REF_REQUIRE_CMGEN") == "1":
            pytest.fail(f"IBL_REF_REQUIRE_CMGEN=1, but: {exc}")
        pytest.skip(str(exc))


@pytest.fixture
def mitsuba_llvm(request):
    """Mitsuba's llvm_ad_rgb variant, the only one the lab's Mitsuba code runs on (it needs libLLVM >= 17).
    Where it cannot run, the test is skipped with the reason, or fails when ``IBL_REF_REQUIRE_MITSUBA=1``
    (set by ``.ci/run``, so that CI cross-validates with Mitsuba for real and never skips silently)."""
    from ibl_ref.rendering import mitsuba_render as mr

    _refuse_if_same_without_tools(request, "runs Mitsuba")
    try:
        return mr.select_variant()
    except mr.MitsubaUnavailable as exc:
        if os.environ.get("IBL_REF_REQUIRE_MITSUBA") == "1":
            pytest.fail(f"IBL_REF_REQUIRE_MITSUBA=1, but: {exc}")
        pytest.skip(str(exc))


@pytest.fixture(scope="session")
def run_quick():
    """``run_quick(module, out, **kw) → (summary, figures, {file name: layout problems})``: an experiment's quick run
    and its plots, with the layout of every figure it saves checked (:func:`ibl_ref.figures.layout_problems`)."""
    from ibl_ref import figures

    def run(mod, out, **kw):
        problems = {}

        def hook(fig, path):
            problems[path.name] = figures.layout_problems(fig)

        figures.add_save_hook(hook)
        try:
            summary = mod.run(out, quick=True, **kw)
            figs = mod.plot(out)
        finally:
            figures.remove_save_hook(hook)
        return summary, figs, problems

    return run
