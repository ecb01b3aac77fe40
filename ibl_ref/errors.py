"""Exception types of ibl_ref.

Every error a user can trigger with bad input derives from :class:`IBLError` (itself a ``ValueError``),
and its message names the file or argument and the problem.  This module imports nothing of the package (every
module may import it); the radiance check of arrays, :func:`ibl_ref.environment.radiance_policy.check_radiance`,
lives with the radiance policy it applies.
"""

from __future__ import annotations

import numpy as np

__all__ = ["IBLError", "LayoutError", "RadianceError", "EnvMapFileError", "MeshError", "check_input_file"]


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


def check_input_file(path, expected: str, error: type = EnvMapFileError):
    """``path`` as a :class:`pathlib.Path` if it is an existing regular file, else a one-line ``error`` naming what
    was ``expected`` (e.g. ``"an OpenEXR file"``): missing, a folder, or a device / FIFO / socket (which would block
    a reader or never end)."""
    from pathlib import Path

    path = Path(path)
    if not path.exists():
        raise error(f"{path}: file not found")
    if path.is_dir():
        raise error(f"{path}: is a folder, expected {expected}")
    if not path.is_file():
        raise error(f"{path}: not a regular file (device, FIFO or socket), expected {expected}")
    return path
