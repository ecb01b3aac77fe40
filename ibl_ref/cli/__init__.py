"""The ``ibl-ref`` command line: a thin layer over library functions.

Sub-commands live in modules ``ibl_ref/cli/cmd_*.py``; each defines ``register(subparsers)`` which
adds one or more sub-parsers and sets ``func`` (called with the parsed arguments, returns an exit
code).  Modules are discovered automatically, in alphabetical order.
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys

from ..errors import IBLError

__all__ = ["main", "build_parser"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ibl-ref",
        description=(
            "ibl_ref: exact references and measured approximations for image-based lighting of glossy "
            "surfaces (Knuth et al. 2014). Run 'ibl-ref COMMAND --help' for the options of a command; "
            "'ibl-ref reproduce --quick' regenerates every figure on synthetic data."
        ),
    )
    parser.add_argument("--version", action="version", version=f"ibl_ref {__import__('ibl_ref').__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in sorted(m.name for m in pkgutil.iter_modules(__path__) if m.name.startswith("cmd_")):
        importlib.import_module(f"{__name__}.{mod}").register(sub)
    return parser


def main(argv=None) -> int:
    # the command line only writes figure files: a non-interactive backend unless the user chose one
    os.environ.setdefault("MPLBACKEND", "Agg")
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except IBLError as exc:
        print(f"ibl-ref {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
