"""What the peers run as outside programs share (cmft, :mod:`~ibl_ref.prefilter.cmft_peer`; Filament's cmgen,
:mod:`~ibl_ref.prefilter.cmgen_peer`): the bound on one run of the program and the check of what a run returned.

Both raise one-line errors: a bad timeout value is the user's :class:`~ibl_ref.errors.IBLError` naming where the
value came from (the argument or the environment variable); output that is NaN/Inf, negative, or black for a
non-black input is the program's, raised as the peer's own "unavailable" error naming the binary.
"""

from __future__ import annotations

import math
import os

import numpy as np

from ..errors import IBLError

__all__ = ["run_timeout", "check_returned"]


def run_timeout(timeout, env_var: str, default: float, program: str) -> float:
    """Seconds one run of ``program`` may take: ``timeout``, else ``$env_var``, else ``default``; a finite number
    > 0, or a one-line :class:`IBLError` naming where the value came from.

    Examples
    --------
    >>> from ibl_ref.prefilter.peer_programs import run_timeout
    >>> run_timeout(2, "NOT_SET_ANYWHERE", 600.0, "cmgen")
    2.0
    >>> run_timeout(0, "NOT_SET_ANYWHERE", 600.0, "cmgen")
    Traceback (most recent call last):
    ...
    ibl_ref.errors.IBLError: timeout: the cmgen timeout must be a finite number of seconds > 0, got 0
    """
    where, value = "timeout", timeout
    if timeout is None:
        where, value = f"${env_var}", os.environ.get(env_var, "")
        if value.strip() == "":
            return float(default)
    if isinstance(value, bool):
        value = None  # True is not a number of seconds
    try:
        t = float(value)
    except (TypeError, ValueError):
        t = float("nan")
    if not (math.isfinite(t) and t > 0):
        raise IBLError(f"{where}: the {program} timeout must be a finite number of seconds > 0, got {value!r}")
    return t


def check_returned(got, source, *, program: str, exe, where: str, error: type, what: str = "map") -> None:
    """One array read back from ``program``: finite, non-negative, and not black where ``source`` (its input) is
    not; otherwise ``error`` (one line naming the binary ``exe`` and ``where``, e.g. "at s = 4" or "at level 1":
    NaN, Inf or black output is the program's, not a matter of the cube convention)."""
    bad = ~np.isfinite(got)
    if bad.any():
        raise error(f"{program} {str(exe)!r} wrote {int(bad.sum())} NaN/Inf value(s) {where} (a broken build, a "
                    f"wrong binary or an overflow of its file format; the lab refuses its {what})")
    if np.min(got) < 0:
        raise error(f"{program} {str(exe)!r} wrote negative radiance (down to {float(np.min(got)):g}) {where}; the "
                    f"lab refuses its {what}")
    if np.max(got) == 0 and np.max(source) > 0:
        raise error(f"{program} {str(exe)!r} wrote a black map {where} from a non-black input; the lab refuses it")
