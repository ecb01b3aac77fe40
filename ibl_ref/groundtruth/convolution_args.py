"""Argument checks shared by every Phong-lobe convolution route (Knuth et al. 2014, Sec. 3.2, Eq. 4).

One definition each, used by :mod:`ibl_ref.groundtruth.convolve`, :mod:`ibl_ref.groundtruth.phong_convolution` (exact and
sparse gathers), :mod:`ibl_ref.groundtruth.sh_convolution`, :mod:`ibl_ref.groundtruth.moment_convolution` and
:mod:`ibl_ref.lobes.prefiltered_lobes`.  Every failure is an :class:`~ibl_ref.errors.IBLError` subclass
naming the argument.

* Phong exponent ``s = s_Phong = 1/(1−g)`` (Eq. 3, g ∈ [0, 1]): a number ≥ 1, or ``inf`` (mirror, g = 1).
* Cube map: shape ``(6, N, N[, C])``, finite non-negative radiance, at least one channel, checked once
  (:mod:`ibl_ref.environment.validated`: an :class:`~ibl_ref.environment.validated.Environment` passes through).
* Output face subsets ``faces``: distinct indices 0…5 in OpenEXR face order.
"""

from __future__ import annotations

import math

import numpy as np

from ..environment.validated import environment_array
from ..errors import IBLError

__all__ = ["check_exponent", "check_exponents", "check_cube", "check_faces", "check_out_size", "channel_max",
           "channel_min"]


#: largest finite Phong exponent of the convolution: the float64 rounding of a weight c^s grows as s·u (the cosine's
#: rounding Δ ≈ 5.6e-16 raised to the s-th power, :func:`ibl_ref.groundtruth.kernels.rounding.weight_error`), ≈ 1.6e-5
#: relative at 2^30, so a larger exponent could not be bounded at rtol 1e-4; its lobe (half width ≈ 1.18/√s <
#: 3.6e-5 rad) is narrower than a texel of any face up to 16384² (9.6e-5 rad), where the mirror s = inf gives the map
S_MAX = 2.0 ** 30


def check_exponent(s) -> float:
    """A Phong exponent as a float in [1, :data:`S_MAX`] or ``inf``; IBLError otherwise (NaN, < 1, not a number,
    too large to bound)."""
    if isinstance(s, bool):
        raise IBLError(f"Phong exponent must be a number >= 1 or inf, got {s!r}")
    try:
        s = float(s)
    except (TypeError, ValueError):
        raise IBLError(f"Phong exponent must be a number >= 1 or inf, got {s!r}") from None
    if math.isnan(s) or s < 1.0:
        raise IBLError(f"Phong exponent s must be >= 1 (s_Phong = 1/(1-g) with g in [0,1]) or inf, got {s!r}")
    if S_MAX < s < math.inf:
        raise IBLError(f"Phong exponent s = {s:g} is above 2^30: its weights' float64 rounding cannot be bounded and "
                       "its lobe is narrower than any texel; use s = inf (the mirror)")
    return s


def check_exponents(exponents) -> list[float]:
    """Validated exponents (a scalar or a sequence), duplicates dropped, order kept; at least one."""
    ex = np.atleast_1d(np.asarray(exponents, dtype=object)).ravel()
    if ex.size == 0:
        raise IBLError("no Phong exponents given")
    out = []
    for s in ex:
        v = check_exponent(s)
        if v not in out:
            out.append(v)
    return out


def check_cube(cube, name: str = "environment cube map") -> tuple[np.ndarray, bool]:
    """``(read-only float64 array (6, N, N, C), squeezed)`` of an environment argument: a 3-d input gets a channel
    axis (``squeezed = True``); a plain array is validated once (layout, radiance) and copied, an
    :class:`~ibl_ref.environment.validated.Environment` passes through unchecked
    (:func:`~ibl_ref.environment.validated.environment_array`)."""
    return environment_array(cube, name)


def check_faces(faces) -> tuple[int, ...]:
    """Validated tuple of output face indices (default ``None``: all six, in order)."""
    if faces is None:
        return tuple(range(6))
    try:
        out = tuple(int(f) for f in faces)
    except (TypeError, ValueError):
        raise IBLError(f"faces must be a sequence of face indices 0..5, got {faces!r}") from None
    if not out or any(f < 0 or f > 5 for f in out) or len(set(out)) != len(out):
        raise IBLError(f"faces must be distinct face indices 0..5, got {faces!r}")
    return out


def check_out_size(out_size, n: int) -> int:
    """Output face size: a positive integer, default (``None``) the input face size ``n``."""
    if out_size is None:
        return int(n)
    if isinstance(out_size, bool) or not isinstance(out_size, (int, np.integer)) or out_size < 1:
        raise IBLError(f"out_size must be a positive integer, got {out_size!r}")
    return int(out_size)


def channel_max(a: np.ndarray) -> np.ndarray:
    """``a.max(axis=-1)`` of a (…, C) array of a convolution route (maps, bounds, radiance: C is 1–4), as C − 1
    elementwise maxima: NumPy reduces a short last axis ≈ 15× slower, and max is exact, so the result is the
    same, bit for bit (NaN propagates as in ``max``)."""
    out = np.array(a[..., 0], dtype=a.dtype, copy=True)
    for c in range(1, a.shape[-1]):
        np.maximum(out, a[..., c], out=out)
    return out


def channel_min(a: np.ndarray) -> np.ndarray:
    """``a.min(axis=-1)``, as :func:`channel_max`."""
    out = np.array(a[..., 0], dtype=a.dtype, copy=True)
    for c in range(1, a.shape[-1]):
        np.minimum(out, a[..., c], out=out)
    return out
