"""Tone mapping for PNG previews of rendered radiance images (EXR output keeps radiance; this is display only).

``exposure_srgb``: v = 2^stops · x, optional Reinhard (v / (1 + v), applied to each channel), then the sRGB
transfer function (IEC 61966-2-1) and clipping to [0, 1].  Deterministic; finite for any finite non-negative input
(e.g. a 1e5 sun) and any finite ``stops``: where 2^stops · x would leave float64 (``stops`` beyond ±1023, or a
huge x times a large scale) the product is formed as 2^(log2 x + stops), limited to float64's range, so it
saturates to white or black instead of overflowing.  ``auto_exposure`` picks the stops mapping a percentile of
the covered luminance to ``key`` (finite also for subnormal luminances).
"""

from __future__ import annotations

import numpy as np

from ..errors import IBLError
from ..atomic import atomic_path
from ..environment.sampling import sample_bilinear

__all__ = ["srgb_encode", "reinhard", "expose", "exposure_srgb", "auto_exposure", "environment_exposure", "save_png", "backdrop", "with_backdrop"]


def srgb_encode(x) -> np.ndarray:
    """Linear [0, 1] → sRGB-encoded [0, 1] (12.92·x below 0.0031308, 1.055·x^(1/2.4) − 0.055 above)."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def reinhard(x) -> np.ndarray:
    """Reinhard's global operator x / (1 + x) per channel (monotone, maps [0, ∞) to [0, 1))."""
    x = np.asarray(x, dtype=np.float64)
    return x / (1.0 + x)


def _check(img):
    a = np.asarray(img, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise IBLError("tone mapping: image contains NaN or Inf")
    return a


def auto_exposure(img, mask=None, percentile: float = 90.0, key: float = 0.8) -> float:
    """Stops such that the ``percentile`` of the covered channel-mean luminance maps to ``key`` (0 if dark)."""
    a = _check(img)
    y = a.mean(axis=-1) if a.ndim == 3 else a
    y = y[mask] if mask is not None else y.reshape(-1)
    y = y[y > 0]
    if y.size == 0:
        return 0.0
    return float(np.log2(key) - np.log2(np.percentile(y, percentile)))  # no overflow for subnormal y


def environment_exposure(mean_radiance: float, key: float = 0.5) -> float:
    """Stops such that the environment's solid-angle weighted mean radiance L̄ = ∫L dω / 4π maps to ``key`` (0 if
    L̄ ≤ 0).  A white Lambertian surface lit by a uniform environment L̄ has radiance L̄, so it maps to ``key``.  The
    exposure depends on the environment only, not on the image: previews of the same scene rendered by different
    methods (or modes) get the same exposure and can be compared by eye."""
    m = float(mean_radiance)
    if not (np.isfinite(m) and m > 0):
        return 0.0
    return float(np.log2(key) - np.log2(m))


#: float64's binary exponent range (2^-1074 … 2^1023): the exposed values are kept inside it
_LOG2_MIN, _LOG2_MAX = -1074.0, 1023.0


def expose(x, stops: float) -> np.ndarray:
    """2^stops · x for non-negative x, without overflow: exact (a power-of-two scale) where the product fits in
    float64, else 2^(log2 x + stops) limited to float64's range (saturated)."""
    stops = float(stops)
    if not np.isfinite(stops):
        raise IBLError(f"exposure must be a finite number of stops, got {stops!r}")
    a = np.asarray(x, dtype=np.float64)
    top = float(a.max()) if a.size else 0.0
    if abs(stops) <= 1000 and (top == 0.0 or np.log2(top) + stops < _LOG2_MAX):
        return a * 2.0 ** stops
    out = np.zeros_like(a)
    pos = a > 0
    with np.errstate(under="ignore"):
        out[pos] = np.exp2(np.clip(np.log2(a[pos]) + stops, _LOG2_MIN, _LOG2_MAX))
    return out


def exposure_srgb(img, stops: float = 0.0, operator: str = "reinhard") -> np.ndarray:
    """Display values in [0, 1]: sRGB(op(2^stops · x)), op = ``"reinhard"`` or ``"clip"``; any finite ``stops``."""
    a = expose(np.clip(_check(img), 0.0, None), stops)
    if operator == "reinhard":
        a = reinhard(a)
    elif operator != "clip":
        raise IBLError(f"operator must be 'reinhard' or 'clip', got {operator!r}")
    return srgb_encode(a)


def backdrop(env, camera) -> np.ndarray:
    """(H, W, C) radiance of the environment seen through every pixel of ``camera`` (bilinear, seam-aware).

    The background of a render for display: what a camera would see behind the object.
    """

    _, d = camera.pixel_rays(normalize=True)
    return sample_bilinear(np.asarray(env, dtype=np.float64), d.reshape(-1, 3)).reshape(d.shape[:2] + (-1,))


def with_backdrop(img, mask, background) -> np.ndarray:
    """``img`` where ``mask`` (covered pixels), ``background`` elsewhere (display only)."""
    return np.where(np.asarray(mask, bool)[..., None], np.asarray(img, float), np.asarray(background, float))


def save_png(path, img, stops: float | None = None, mask=None, operator: str = "reinhard"):
    """Tone-map and write an 8-bit sRGB PNG atomically (nearest code value; :func:`ibl_ref.atomic.atomic_path`)."""
    import matplotlib.image as mpimg  # writing a PNG needs no pyplot and no backend


    a = _check(img)
    if stops is None:
        stops = auto_exposure(a, mask)
    out = exposure_srgb(a, stops, operator)
    if out.ndim == 3 and out.shape[-1] == 1:
        out = out[..., 0]
    if out.ndim == 2:
        out = np.repeat(out[..., None], 3, axis=-1)
    # round to the nearest 8-bit code (matplotlib's float → uint8 conversion truncates: up to 1 code too dark)
    out8 = np.round(np.clip(out, 0.0, 1.0) * 255.0).astype(np.uint8)
    with atomic_path(path, suffix=".png") as tmp:
        mpimg.imsave(tmp, out8, format="png")
    return path
