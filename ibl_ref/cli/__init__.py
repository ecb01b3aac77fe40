"""The ``ibl-ref`` command line: a thin layer over library functions.

Sub-commands live in modules ``ibl_ref/cli/cmd_*.py``; each defines ``register(subparsers)`` which
adds one or more sub-parsers and sets ``func`` (called with the parsed arguments, returns an exit
code).  Modules are discovered automatically, in alphabetical order.

Errors (this module, for every command):

* argparse usage errors print **one line** ``ibl-ref CMD: error: argument --flag: …`` (plus a pointer
  to ``--help``) and exit with 2;
* every numeric option is validated once, here, right after parsing (:func:`validate_args`): integer
  options must be >= 1 (seeds >= 0) and, if they are sizes, their float64 cube map must fit in memory
  (:mod:`ibl_ref.limits`); float options must be finite.  A bad value is one line naming the flag,
  exit code 1 (like every other bad input);
* an :class:`~ibl_ref.errors.IBLError` prints one line and returns 1; Python parameter hints in library
  messages (``variant='global'``) are rewritten to the command's flags (``--variant global``);
* library hints ``(Python: …)`` are dropped (the flags are named already);
* warnings are one line each: ``ibl-ref CMD: warning: …`` (:class:`~ibl_ref.errors.IBLWarning` and ibl_ref's
  own); a warning of another package (numpy, scipy, trimesh) that reaches the command is one line naming the
  package and asking for a report — the known cases are checked where they arise and named by their flag;
* Ctrl-C at any moment: ``ibl-ref CMD: interrupted``, exit code 130, no partial output; ``kill`` (SIGTERM):
  ``ibl-ref CMD: terminated``, exit code 143; worker processes stop with the command (:mod:`ibl_ref.cli.interrupts`);
* last resort: an unexpected ``OSError`` / ``MemoryError`` prints one line asking for a report instead
  of a traceback (known cases are translated where they happen, not here).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import math
import os
import re
import sys

from ..errors import IBLError, IBLWarning
from .interrupts import handling  # stdlib only: installed first thing in main()

__all__ = ["main", "build_parser", "validate_args"]

#: int options whose value is an array size (checked against memory as a cube face size)
SIZE_DESTS = ("size", "input_size", "env_size", "vsm_res")
#: integer options for which 0 is meaningful (random seeds): they must be >= 0 instead of >= 1
NONNEGATIVE_DESTS = ("seed",)


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors are a single line naming the flag."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``ibl-ref`` parser.  With ``command`` (the first word of the command line) only the module
    ``cmd_<command>`` is imported and registered when it defines that command — start-up of e.g.
    ``ibl-ref convolve`` then skips the other commands' imports (the experiment registry, ≈ 0.1 s) —
    otherwise every command (``--help``, unknown commands, commands of another module)."""
    if command and not command.startswith("-"):
        mod = "cmd_" + command.replace("-", "_")
        # (find_spec, not pkgutil.iter_modules: that imports inspect, ≈ 5 ms of every command's start-up)
        if re.fullmatch(r"cmd_\w+", mod) and importlib.util.find_spec(f"{__name__}.{mod}") is not None:
            parser, sub = _root_parser()
            importlib.import_module(f"{__name__}.{mod}").register(sub)
            if command in sub.choices:
                return parser
    import pkgutil

    parser, sub = _root_parser()
    for mod in sorted(m.name for m in pkgutil.iter_modules(__path__) if m.name.startswith("cmd_")):
        importlib.import_module(f"{__name__}.{mod}").register(sub)
    return parser


def _root_parser():
    parser = _Parser(
        prog="ibl-ref",
        description=(
            "ibl_ref: exact references and measured approximations for image-based lighting of glossy "
            "surfaces (Knuth et al. 2014). Run 'ibl-ref COMMAND --help' for the options of a command; "
            "'ibl-ref reproduce --quick' regenerates every figure on synthetic data."
        ),
    )
    parser.add_argument("--version", action="version", version=f"ibl_ref {__import__('ibl_ref').__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    return parser, sub


def _subparser(parser, command):
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            return a.choices.get(command)
    return None


def validate_args(parser, args) -> None:
    """Check every int/float option of the chosen command (see module docstring).

    Raises :class:`~ibl_ref.limits.SizeError` naming the flag (``main`` prints it as one line, exit code 1).
    """
    from ..limits import SizeError, check_cube_size

    sp = _subparser(parser, getattr(args, "command", None))
    while sp is not None:  # nested sub-commands (``synth env``): validate the innermost parser
        nested = next((a for a in sp._actions if isinstance(a, argparse._SubParsersAction)), None)
        inner = nested.choices.get(getattr(args, nested.dest, None)) if nested is not None and nested.dest else None
        if inner is None:
            break
        sp = inner
    if sp is None:
        return
    for a in sp._actions:
        value = getattr(args, a.dest, None)
        if a.type not in (int, float) or value is None:
            continue
        flag = max(a.option_strings, key=len) if a.option_strings else a.dest
        for v in value if isinstance(value, list) else [value]:
            if a.type is float and not math.isfinite(v):
                raise SizeError(f"argument {flag}: must be a finite number, got {v!r}")
            if a.type is int:
                if a.dest in NONNEGATIVE_DESTS:
                    if v < 0:
                        raise SizeError(f"argument {flag}: must be a non-negative integer, got {v}")
                elif v < 1:
                    raise SizeError(f"argument {flag}: must be a positive integer, got {v}")
                if a.dest in SIZE_DESTS:
                    check_cube_size(v, f"argument {flag}")


#: library parameter -> CLI flags that set it, where the names differ (the first flag the command has wins)
PARAM_FLAGS = {"n_lights": ("--lights",), "variant": ("--variant", "--median-cut"), "n_lobes": ("--lobes",),
               "out_size": ("--size",), "vsm_resolution": ("--vsm-res",), "uv_fallback": ("--gmap-fallback",)}


def _flag_hints(message: str, sp) -> str:
    """Rewrite ``name='value'`` / ``name=value`` hints of library messages to this command's flags."""
    if sp is None:
        return message
    flags = {s for a in sp._actions for s in a.option_strings}

    def flag_of(name):
        for f in PARAM_FLAGS.get(name, ()) + ("--" + name.replace("_", "-"),):
            if f in flags:
                return f
        return None

    def repl(m):
        flag = flag_of(m.group(1))
        if flag is None:
            return m.group(0)
        val = m.group(3)
        return f"{flag}" if val in ("True",) else f"{flag} {val}"

    message = re.sub(r"\s*\(Python: [^()]*\)", "", message)  # the CLI names its flags; the Python hint is noise
    message = re.sub(r"\b([a-z][a-z_]*)=(['\"]?)([\w.+-]+)\2", repl, message)
    m = re.match(r"([a-z][a-z_]*) must\b", message)  # "rtol must be in (0, 1)" -> "--rtol: rtol must ..."
    if m and flag_of(m.group(1)):
        message = flag_of(m.group(1)) + ": " + message
    if "--size" in flags:
        message = message.replace("Resample the map first (e.g. ibl_ref.environment.resample)", "Resample it with --size")
    return message


def _one_line_warnings(prog: str):
    """A ``warnings.showwarning`` that prints every warning as one line (module docstring)."""

    def show(message, category, filename, lineno, file=None, line=None):
        text = " ".join(str(message).split())
        mod = filename.replace(os.sep, "/")
        # ibl_ref's own: IBLWarning, or a UserWarning it issues; anything else (numpy's RuntimeWarnings, wherever
        # the arithmetic is) is a case the checks did not foresee
        ours = issubclass(category, IBLWarning) or (category is UserWarning and "/ibl_ref/" in mod)
        if not ours:
            where = ("ibl_ref." + mod.rsplit("/ibl_ref/", 1)[1].removesuffix(".py").replace("/", ".")
                     if "/ibl_ref/" in mod else next((p for p in ("numpy", "scipy", "trimesh", "matplotlib",
                                                                  "OpenEXR", "mitsuba", "drjit") if f"/{p}/" in mod),
                                                     "a library"))
            text = f"{category.__name__} in {where}: {text} (unexpected; please report the command)"
        print(f"{prog}: warning: {text}", file=sys.stderr if file is None else file)

    return show


def main(argv=None) -> int:
    rc = None
    try:  # a Ctrl-C before the handler is installed lands here too (Python's default handler raises)
        try:
            with handling():  # Ctrl-C from here on: one line, exit code 130 (ibl_ref.cli.interrupts)
                rc = _main(argv)
        finally:
            if argv is None:  # the program itself: what follows is the interpreter's shutdown, the work is done
                import signal

                signal.signal(signal.SIGINT, signal.SIG_IGN)
                signal.signal(signal.SIGTERM, signal.SIG_IGN)
    except KeyboardInterrupt:
        rc = None
    if rc is not None:
        return rc
    import signal

    from .interrupts import received_signal

    words = sys.argv[1:] if argv is None else [str(a) for a in argv]
    command = words[0] if words and not str(words[0]).startswith("-") else ""
    term = received_signal() == signal.SIGTERM
    print(f"ibl-ref{' ' + command if command else ''}: {'terminated' if term else 'interrupted'}", file=sys.stderr)
    return 143 if term else 130  # 128 + the signal's number, the shell's convention


def _main(argv=None) -> int:
    import warnings

    from .interrupts import interrupted

    # the command line only writes figure files: a non-interactive backend unless the user chose one
    os.environ.setdefault("MPLBACKEND", "Agg")
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv[0] if argv else None)
    args = parser.parse_args(argv)  # usage errors / --help raise SystemExit, as argparse does
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    prog = f"ibl-ref {args.command}"
    import logging

    logging.getLogger("trimesh").setLevel(logging.ERROR)  # its fallback notices are internals (with tracebacks)
    with warnings.catch_warnings():
        warnings.showwarning = _one_line_warnings(prog)
        try:
            validate_args(parser, args)  # numeric flags, before any work
            rc = int(args.func(args) or 0)
        except IBLError as exc:
            if interrupted():  # an interrupt that a library turned into another error
                raise KeyboardInterrupt from None
            msg = " ".join(str(exc).split("\n"))
            print(f"{prog}: error: {_flag_hints(msg, _subparser(parser, args.command))}", file=sys.stderr)
            return 1
        except MemoryError:  # last resort: sizes are checked up front, this is a case we did not foresee
            print(f"{prog}: error: out of memory (try smaller sizes; please report the command that caused this)",
                  file=sys.stderr)
            return 1
        except OSError as exc:  # last resort: known cases are OutputError / EnvMapFileError at their source
            where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
            print(f"{prog}: error: {where}{exc.strerror or exc} (unexpected system error; please report it)",
                  file=sys.stderr)
            return 1
    if interrupted():  # the interrupt was swallowed somewhere (an outside ``except BaseException``)
        raise KeyboardInterrupt
    return rc
