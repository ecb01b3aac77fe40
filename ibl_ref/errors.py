"""Exception types of ibl_ref.

Every error a user can trigger with bad input derives from :class:`IBLError` (itself a ``ValueError``),
and its message names the file or argument and the problem.
"""

from __future__ import annotations

import numpy as np

__all__ = ["IBLError", "LayoutError", "RadianceError", "EnvMapFileError", "MeshError", "check_radiance"]


class IBLError(ValueError):
    """Base class of ibl_ref's input errors."""


class LayoutError(IBLError):
    """An array or image has the wrong shape, aspect ratio or channel set."""


class RadianceError(IBLError):
    """Radiance values that are NaN, infinite or negative."""


class EnvMapFileError(IBLError):
    """A file could not be read or written as an environment map (message names the file)."""


class MeshError(IBLError):
    """A mesh is empty, degenerate or contains non-finite vertices."""


def check_radiance(values, name: str = "radiance") -> np.ndarray:
    """Return ``values`` as an array after checking it is finite and non-negative.

    Raises :class:`RadianceError` naming ``name``, the count of offending values and the first index.
    """
    a = np.asarray(values)
    if not np.issubdtype(a.dtype, np.number):
        raise RadianceError(f"{name}: expected a numeric array, got dtype {a.dtype}")
    bad_nan = ~np.isfinite(a)
    if bad_nan.any():
        idx = tuple(int(i) for i in np.argwhere(bad_nan)[0])
        kind = "NaN" if np.isnan(a[idx]) else "Inf"
        raise RadianceError(f"{name}: {int(bad_nan.sum())} non-finite value(s) (first: {kind} at index {idx})")
    neg = a < 0
    if neg.any():
        idx = tuple(int(i) for i in np.argwhere(neg)[0])
        raise RadianceError(
            f"{name}: {int(neg.sum())} negative radiance value(s) (first: {a[idx]!r} at index {idx})"
        )
    return a
