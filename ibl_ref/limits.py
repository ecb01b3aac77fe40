"""Input validation shared by the library and the CLI: integer sizes, allocation limits and tolerances.

Every size a user passes (a face size, an image height, a shadow-map resolution, a size claimed by a
file header) is checked here *before* anything is allocated:

* :func:`as_size` — a true integer (``2.5``, ``True``, ``"8"`` are errors, ``8.0`` is accepted) that is
  at least ``minimum``;
* :func:`check_allocation` — the bytes an array would take are compared with the machine's physical
  memory (``os.sysconf``; the environment variable ``IBL_REF_MAX_BYTES`` lowers the limit, e.g. for
  tests), so ``--size 1000000000`` fails at once instead of after minutes of swapping;
* :func:`positive_int` — a count that must be a true positive integer (no ``8.0``: counts of sets, orders, tiles);
* :func:`check_cube_size` — both, for one float64 RGB cube map ``(6, N, N, 3)`` (24·6·N² bytes);
* :func:`check_rtol` — a relative tolerance in [:data:`RTOL_MIN`, 1): the floor is what float64 quadrature sums can
  verify (the constant's comment gives the derivation).

Errors are :class:`SizeError` (an :class:`~ibl_ref.errors.IBLError`) naming the parameter or flag.
"""

from __future__ import annotations

import math
import numbers
import os

from .errors import IBLError

__all__ = ["SizeError", "as_size", "positive_int", "memory_limit_bytes", "check_allocation", "check_cube_size", "cube_nbytes",
           "RTOL_MIN", "ToleranceError", "check_rtol"]


class SizeError(IBLError):
    """A size that is not a positive integer or whose array would not fit in memory."""


def as_size(value, name: str, minimum: int = 1) -> int:
    """``value`` as an ``int`` ≥ ``minimum``; :class:`SizeError` naming ``name`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise SizeError(f"{name}: expected an integer, got {value!r}")
    if isinstance(value, numbers.Integral):
        v = int(value)
    else:
        f = float(value)
        if not math.isfinite(f) or f != math.floor(f):
            raise SizeError(f"{name}: expected an integer, got {value!r}")
        v = int(f)
    if v < minimum:
        raise SizeError(f"{name}: must be >= {minimum}, got {v}")
    return v


def positive_int(name: str, value) -> int:
    """``value`` as an ``int`` ≥ 1, an integer type only (``8.0`` and ``True`` are errors);
    :class:`~ibl_ref.errors.IBLError` naming ``name`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or int(value) < 1:
        raise IBLError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def memory_limit_bytes() -> int:
    """Largest allocation accepted: physical memory, or ``$IBL_REF_MAX_BYTES`` if set and smaller."""
    try:
        phys = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        phys = 2**40
    env = os.environ.get("IBL_REF_MAX_BYTES")
    if env:
        try:
            phys = min(phys, int(float(env)))
        except ValueError:
            raise SizeError(f"$IBL_REF_MAX_BYTES: expected a number of bytes, got {env!r}") from None
    return int(phys)


def _fmt(nbytes: float) -> str:
    for unit, scale in (("EiB", 2**60), ("PiB", 2**50), ("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20)):
        if nbytes >= scale:
            return f"{nbytes / scale:.3g} {unit}"
    return f"{nbytes:.0f} B"


def check_allocation(nbytes, what: str, name: str) -> None:
    """:class:`SizeError` if an array of ``nbytes`` bytes (``what``) cannot fit in memory."""
    limit = memory_limit_bytes()
    if nbytes > limit:
        raise SizeError(f"{name}: {what} would need {_fmt(float(nbytes))}, more than this machine's memory "
                        f"({_fmt(limit)})")


def cube_nbytes(n: int, channels: int = 3, itemsize: int = 8) -> int:
    """Bytes of one ``(6, n, n, channels)`` array."""
    return 6 * int(n) * int(n) * int(channels) * int(itemsize)


def check_cube_size(value, name: str, channels: int = 3) -> int:
    """A cube face size: :func:`as_size` and one float64 cube map must fit in memory."""
    n = as_size(value, name)
    check_allocation(cube_nbytes(n, channels), f"a {n}x{n}-face float64 cube map", name)
    return n


#: smallest relative tolerance accepted anywhere (2^-26 ≈ 1.5e-8): the float64 rounding of a quadrature sum of K
#: non-negative terms is bounded by γ_K ≈ K·2^-53 (Higham 2002, Accuracy and Stability of Numerical Algorithms,
#: §4.2, recursive summation), and the lab's largest sums hold up to 2^27 terms (the reference's GGX quadrature cap,
#: 6·4096² texels): a tolerance below K·2^-53 = 2^-26 cannot be verified by the sums that estimate the error
RTOL_MIN = 2.0 ** -26


class ToleranceError(IBLError):
    """A relative tolerance that is not a number in [:data:`RTOL_MIN`, 1)."""


def check_rtol(value, name: str = "rtol") -> float:
    """A relative tolerance in [:data:`RTOL_MIN`, 1) as a float; a one-line :class:`ToleranceError` naming ``name``
    otherwise (not a number, NaN, ≤ 0, below the float64 floor, ≥ 1: a relative error of 100 % checks nothing)."""
    if isinstance(value, bool):
        raise ToleranceError(f"{name}: expected a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ToleranceError(f"{name}: expected a number, got {value!r}") from None
    if not (math.isfinite(v) and 0 < v < 1):
        raise ToleranceError(f"{name}: a relative tolerance must be a number in (0, 1), got {value!r}")
    if v < RTOL_MIN:
        raise ToleranceError(f"{name}: {v:g} is below {RTOL_MIN:.2g} (2^-26), the float64 rounding of the lab's largest "
                        "quadrature sums (2^27 terms x 2^-53): a smaller tolerance cannot be verified")
    return v
