"""Exception types of ibl_ref.

Every error a user can trigger with bad input derives from :class:`IBLError` (itself a ``ValueError``),
and its message names the file or argument and the problem.  Warnings of the library (a repaired input, a
value a file format cannot hold) derive from :class:`IBLWarning`; the command line prints each as one line.  This
module imports nothing of the package (every module may import it); the radiance check of arrays,
:func:`ibl_ref.environment.radiance_policy.check_radiance`, lives with the radiance policy it applies.
"""

from __future__ import annotations

# no numpy import here: ``ibl_ref.cli`` imports this module before it can handle Ctrl-C

__all__ = ["IBLError", "LayoutError", "RadianceError", "EnvMapFileError", "MeshError", "IBLWarning",
           "RadianceWarning", "FormatRangeWarning", "check_input_file", "as_path"]


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


class IBLWarning(UserWarning):
    """Base class of ibl_ref's warnings (the input was used, but the user should know what happened)."""


class RadianceWarning(IBLWarning):
    """A reader repaired the radiance of a file (negatives clamped, NaN/Inf replaced) under its policy."""


class FormatRangeWarning(IBLWarning, RuntimeWarning):
    """Values outside a file format's range were clamped (``clamp_half``) or, below it, rounded to 0 or lost
    precision while writing (also a ``RuntimeWarning``, the category of the clamping warning before)."""


def as_path(path, what: str = "path"):
    """``path`` (str, bytes or :class:`os.PathLike`) as a :class:`pathlib.Path`; :class:`IBLError` for anything else.

    Bytes are decoded with :func:`os.fsdecode` (file names that are not UTF-8 survive the round trip).
    """
    import os
    from pathlib import Path

    if isinstance(path, Path):
        return path
    if isinstance(path, (str, bytes)) or isinstance(path, os.PathLike):
        try:
            p = os.fsdecode(os.fspath(path))
        except (TypeError, UnicodeDecodeError) as exc:
            raise IBLError(f"{what}: cannot use {path!r} as a file name ({exc})") from None
        if p == "":
            raise IBLError(f"{what}: empty file name")
        if "\0" in p:
            raise IBLError(f"{what}: file name {p!r} contains a NUL character")
        return Path(p)
    raise IBLError(f"{what}: expected a file name (str, bytes or os.PathLike), got {type(path).__name__} {path!r}")


def check_input_file(path, expected: str, error: type = EnvMapFileError):
    """``path`` as a :class:`pathlib.Path` if it is an existing regular file, else a one-line ``error`` naming what
    was ``expected`` (e.g. ``"an OpenEXR file"``): missing, a folder, or a device / FIFO / socket (which would block
    a reader or never end)."""
    path = as_path(path, expected)
    if not path.exists():
        raise error(f"{path}: file not found")
    if path.is_dir():
        raise error(f"{path}: is a folder, expected {expected}")
    if not path.is_file():
        raise error(f"{path}: not a regular file (device, FIFO or socket), expected {expected}")
    return path
