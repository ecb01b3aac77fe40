"""Every notebook in notebooks/ executes top to bottom (quick sizes), shows every figure it makes, leaves
nothing behind in notebooks/, and is stored without outputs.

The kernel runs with the notebook's own default backend (the inline backend of ipykernel: MPLBACKEND is
removed from its environment), so a plot function that switched the backend, or a figure that is written
but not displayed, makes the image count below fail.
"""

import os
import re
import shutil
import time
from pathlib import Path

import pytest

#: slow and the same in every installation (NumPy path, no optional tool): phase 2+3 of .ci/run skips it
pytestmark = pytest.mark.same_without_tools

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NB_DIR = Path(__file__).resolve().parent.parent / "notebooks"
NOTEBOOKS = sorted(NB_DIR.glob("*.ipynb"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_is_stripped(path):
    nb = nbformat.read(path, as_version=4)
    for cell in nb.cells:
        if cell.cell_type == "code":
            assert not cell.get("outputs"), f"{path.name}: commit notebooks with outputs stripped"
            assert cell.get("execution_count") is None


def _images(cell) -> int:
    return sum(1 for o in cell.get("outputs", []) if "image/png" in o.get("data", {}))


def _stdout(cell) -> str:
    return "".join(o.get("text", "") for o in cell.get("outputs", []) if o.get("name") == "stdout")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_executes_and_shows_every_figure(path, monkeypatch):
    nb = nbformat.read(path, as_version=4)
    monkeypatch.delenv("MPLBACKEND", raising=False)  # the notebook's default (inline) backend
    monkeypatch.delenv("IBL_REF_NOTEBOOK_OUT", raising=False)  # the default: a temporary results folder
    # the kernel imports the checkout under test (the same code as the installed package in CI)
    root = str(NB_DIR.parent)
    monkeypatch.setenv("PYTHONPATH", root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    before = sorted(p.name for p in NB_DIR.iterdir())
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(NB_DIR)}})
    t0 = time.perf_counter()
    client.execute()
    print(f"{path.name}: {time.perf_counter() - t0:.1f} s")
    # executing in notebooks/ (as a user would) creates nothing there
    assert sorted(p.name for p in NB_DIR.iterdir()) == before
    m = re.search(r"results in (\S+)", _stdout(nb.cells[[c.cell_type for c in nb.cells].index("code")]))
    assert m, "the set-up cell prints its results folder"
    out = Path(m.group(1))
    try:
        shown = [_images(c) for c in nb.cells if c.cell_type == "code" and "experiments.show(" in c.source]
        plotted = [c for c in nb.cells if c.cell_type == "code" and "plt.show()" in c.source]
        pngs = sorted(out.glob("*/*.png"))
        if shown:
            # every PNG an experiment wrote is displayed, once
            assert sum(shown) == len(pngs) > 0, (shown, [p.name for p in pngs])
            assert all(k > 0 for k in shown)
        for c in plotted:  # notebooks drawing their own figures show each of them
            assert _images(c) == c.source.count("plt.show()"), c.source[:80]
        assert shown or plotted, "a notebook without a figure"
    finally:
        shutil.rmtree(out, ignore_errors=True)
