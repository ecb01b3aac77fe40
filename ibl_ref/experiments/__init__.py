"""Experiments that reproduce the papers' figures and measure the lab's speed/accuracy trades.

Each experiment is a module of this package defining

``NAME`` (str)
    the name used by ``ibl-ref experiment NAME``;
``DESCRIPTION`` (str)
    one line for ``--help``;
``run(out_dir: Path, quick: bool) -> dict``
    computes the data and writes CSV/JSON into ``out_dir`` (units in column names or metadata);
``plot(out_dir: Path) -> list[Path]``
    reads only those files and writes PNG/PDF figures.
``IN_QUICK_REPRODUCE`` (bool, default True)
    whether ``ibl-ref reproduce --quick`` (the README's first command) runs it.

Data flows one way: ``run`` never plots and ``plot`` never computes.
"""

from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType

__all__ = ["available", "get"]


def available() -> dict[str, ModuleType]:
    """Map experiment name → module, discovered from this package."""
    out = {}
    for m in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if m.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{__name__}.{m.name}")
        name = getattr(mod, "NAME", None)
        if name:
            out[name] = mod
    return out


def get(name: str) -> ModuleType:
    exps = available()
    if name not in exps:
        from ..errors import IBLError

        raise IBLError(f"unknown experiment {name!r}; available: {', '.join(sorted(exps)) or '(none yet)'}")
    return exps[name]
