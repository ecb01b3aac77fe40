"""Sphinx configuration of the ibl_ref documentation site.

Build (warnings are errors, as in CI)::

    pip install ".[docs]"
    python -m sphinx -W --keep-going -b html docs /tmp/ibl_ref_docs

Why Sphinx with MyST: the API pages come from the package's NumPy-style docstrings (autodoc + autosummary +
numpydoc, the scientific-Python norm), the existing Markdown pages and the generated result pages are read as they
are (myst-parser), and the notebooks are rendered by myst-nb without pandoc.  Nothing is fetched at build time (no
intersphinx); the notebooks run locally (see ``nb_execution_mode`` below).
"""

from __future__ import annotations

import filecmp
import re
import shutil
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path.insert(0, str(ROOT))  # the checkout's package, also without an installation


def _sync_notebooks() -> None:
    """Copy ``notebooks/*.ipynb`` into ``docs/notebooks/`` (git-ignored): Sphinx reads sources only below ``docs/``.
    A copy is written only when its content differs, and copies of notebooks that no longer exist are removed, so
    an unchanged notebook keeps its execution cache."""
    src, dst = ROOT / "notebooks", DOCS / "notebooks"
    dst.mkdir(exist_ok=True)
    wanted = {p.name: p for p in sorted(src.glob("*.ipynb"))}
    for old in dst.glob("*.ipynb"):
        if old.name not in wanted:
            old.unlink()
    for name, path in wanted.items():
        target = dst / name
        if not target.exists() or not filecmp.cmp(path, target, shallow=False):
            shutil.copyfile(path, target)


_sync_notebooks()
# autosummary writes one stub per module into docs/api/ (git-ignored) and only adds missing ones: stubs of modules
# that were renamed or removed since the last build would fail to import, so the folder is made anew every build
shutil.rmtree(DOCS / "api", ignore_errors=True)

project = "ibl_ref"
author = "the ibl_ref authors"
copyright = "the ibl_ref authors"
release = version = "0.1.0"

extensions = [
    "myst_nb",  # Markdown (MyST) pages and Jupyter notebooks
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "numpydoc",
]

exclude_patterns = ["_build", "page_templates", "notebooks/.ipynb_checkpoints", "**/.ipynb_checkpoints"]
templates_path = ["_templates"]
source_suffix = {".rst": "restructuredtext", ".md": "myst-nb", ".ipynb": "myst-nb"}  # .rst first: autosummary's stubs
root_doc = "index"
html_theme = "alabaster"
html_static_path: list[str] = []
suppress_warnings = ["misc.highlighting_failure"]

# ---- MyST ------------------------------------------------------------------------------------------------------
myst_heading_anchors = 3  # links like background.md#2-conventions-and-definitions, as GitHub renders them
myst_enable_extensions = ["dollarmath"]

# ---- notebooks (myst-nb) ---------------------------------------------------------------------------------------
nb_execution_mode = "cache"  # executed at build time (quick sizes); cached in OUTDIR/../.jupyter_cache
nb_execution_timeout = 900
nb_execution_raise_on_error = True
nb_output_stderr = "remove"  # progress lines on stderr are for a live session, not for the rendered page
nb_merge_streams = True

# ---- API reference ---------------------------------------------------------------------------------------------
autosummary_generate = True
autosummary_imported_members = False
autodoc_default_options = {"members": True, "undoc-members": False, "show-inheritance": False}
autodoc_typehints = "none"  # numpydoc's Parameters sections say the types
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_validation_checks: set[str] = set()
numpydoc_xref_param_type = False


# ---- the package's docstrings are plain text with math -----------------------------------------------------------
# They write absolute values and norms as |x| (never an RST substitution: the package defines none) and underline
# section titles by eye.  Two mechanical readings make them render as written: every '|' outside an inline literal
# is a literal bar, and a dashed or '=' underline shorter than its title is lengthened to it.  Any other markup
# problem in a docstring stays a warning (and so an error under -W).
_LITERAL = re.compile(r"(``.*?``)")
_UNDERLINE = re.compile(r"^(\s*)([-=~^])\2{2,}\s*$")
_GRID_BORDER = re.compile(r"^\s*\+[-=+]+\+\s*$")


def _plain_text_docstring(app, what, name, obj, options, lines):
    grid = any(_GRID_BORDER.match(line) for line in lines)  # a grid table: its bars are markup
    for i, line in enumerate(lines):
        m = _UNDERLINE.match(line)
        if m and i > 0 and lines[i - 1].strip() and not _UNDERLINE.match(lines[i - 1]):
            title = lines[i - 1].rstrip()
            if len(line.rstrip()) < len(title):
                lines[i] = m.group(1) + m.group(2) * (len(title) - len(m.group(1)))
            continue
        if "|" in line and not (grid and line.lstrip().startswith(("|", "+"))):
            parts = _LITERAL.split(line)
            lines[i] = "".join(p if p.startswith("``") else p.replace("|", r"\|") for p in parts)


def setup(app):
    app.connect("autodoc-process-docstring", _plain_text_docstring)
