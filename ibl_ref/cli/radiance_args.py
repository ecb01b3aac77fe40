"""CLI flags of the radiance policy (:mod:`ibl_ref.environment.radiance_policy`), shared by every command that reads an
environment map: ``--negative auto|clamp|error`` and ``--nonfinite error|zero``.

Not a command module (no ``cmd_`` prefix): the ``cmd_*`` modules call :func:`add_radiance_args` on their
parsers and :func:`load_env` to read a file; the report goes to stderr and into the command's JSON sidecar.
"""

from __future__ import annotations

import sys

NEGATIVE_HELP = ("negative radiance in the file: auto (default) clamps them to 0 when they carry at most 1e-4 of "
                 "the integral of |L| domega (the tiny negatives of lossy DWAB compression) and refuses the file "
                 "otherwise; clamp: always clamp to 0; error: refuse any. Clamping is reported on stderr and in "
                 "the JSON sidecar")
NONFINITE_HELP = "NaN/Inf values in the file: error (default) refuses the file; zero: replace them by 0 (reported)"


def add_radiance_args(p) -> None:
    """Add ``--negative`` and ``--nonfinite`` to an argparse parser."""
    p.add_argument("--negative", choices=("auto", "clamp", "error"), default="auto", help=NEGATIVE_HELP)
    p.add_argument("--nonfinite", choices=("error", "zero"), default="error", help=NONFINITE_HELP)


def policy(args) -> dict:
    """``negative=`` / ``nonfinite=`` keyword arguments from parsed args (defaults if a parser lacks them)."""
    return {"negative": getattr(args, "negative", "auto"), "nonfinite": getattr(args, "nonfinite", "error")}


def tell(rep) -> dict | None:
    """Print a report's one-line summary on stderr (if anything was found); return its dict for a sidecar."""
    if rep is None:
        return None
    line = rep.summary()
    if line:
        print(f"note: {line}", file=sys.stderr)
    return rep.to_dict()


def load_env(args, path, size=None):
    """:func:`ibl_ref.environment.exr_io.load_cube` under the command's policy → ``(cube, report dict)``; reports on stderr."""
    from ..environment.exr_io import load_cube
    from ..progress import step

    with step(f"reading {path}" + (f" (to {size}² faces)" if size else "")):  # 16K probes take many seconds
        cube, rep = load_cube(path, size=size, return_report=True, **policy(args))
    return cube, tell(rep)
