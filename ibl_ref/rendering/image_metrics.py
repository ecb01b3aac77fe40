"""Image error metrics for renderer validation (Knuth et al. 2014, Fig. 6 comparisons against a reference).

All metrics compare a test image ``a`` with a reference ``b`` (both (H, W[, C]) radiance, linear) over the covered
pixels ``mask`` (default: all pixels):

* ``rmse`` = sqrt(mean over covered pixels and channels of (a − b)²);
* ``rel_l1`` = Σ|a − b| / Σ|b| (covered pixels, all channels) — the usual "relative L1";
* ``rel_max`` = max over covered pixels of |Y_a − Y_b| / Y_b with Y = channel mean (pixels with Y_b ≤
  ``floor`` × mean(Y_b) are excluded so that black reference pixels do not produce Inf);
* ``flip`` = mean HDR-FLIP (NVIDIA's ``flip_evaluator`` package) when importable, else None with a message.
"""

from __future__ import annotations

import numpy as np

from ..errors import IBLError

__all__ = ["check_pair", "rmse", "rel_l1", "rel_max", "error_map", "flip", "flip_available", "all_metrics"]


def check_pair(a, b, mask=None):
    """Validate two images (same shape, finite) and a mask; returns (a, b, mask) as float64 / bool arrays."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise IBLError(f"image shapes differ: {a.shape} vs {b.shape}")
    if a.ndim not in (2, 3):
        raise IBLError(f"expected (H, W) or (H, W, C) images, got shape {a.shape}")
    for name, x in (("test image", a), ("reference image", b)):
        if not np.all(np.isfinite(x)):
            raise IBLError(f"{name} contains NaN or Inf ({int((~np.isfinite(x)).sum())} values)")
    if mask is None:
        mask = np.ones(a.shape[:2], dtype=bool)
    else:
        mask = np.asarray(mask)
        if mask.shape != a.shape[:2]:
            raise IBLError(f"mask shape {mask.shape} != image shape {a.shape[:2]}")
        mask = mask.astype(bool)
    if not mask.any():
        raise IBLError("mask covers no pixel")
    return a, b, mask


def rmse(a, b, mask=None) -> float:
    """Root-mean-square error over covered pixels and channels."""
    a, b, m = check_pair(a, b, mask)
    return float(np.sqrt(np.mean((a[m] - b[m]) ** 2)))


def rel_l1(a, b, mask=None) -> float:
    """Σ|a − b| / Σ|b| over covered pixels and channels."""
    a, b, m = check_pair(a, b, mask)
    den = np.abs(b[m]).sum()
    if den <= 0:
        raise IBLError("reference image is zero on the covered pixels: relative L1 undefined")
    return float(np.abs(a[m] - b[m]).sum() / den)


def _lum(x):
    return x.mean(axis=-1) if x.ndim == 3 else x


def rel_max(a, b, mask=None, floor: float = 1e-3) -> float:
    """max |Y_a − Y_b| / Y_b over covered pixels with Y_b > floor·mean(Y_b) (Y = channel mean)."""
    a, b, m = check_pair(a, b, mask)
    ya, yb = _lum(a)[m], _lum(b)[m]
    ok = yb > floor * max(float(yb.mean()), 0.0)
    if not ok.any():
        raise IBLError("reference image is zero on the covered pixels: relative error undefined")
    return float((np.abs(ya[ok] - yb[ok]) / yb[ok]).max())


def error_map(a, b, mask=None, kind: str = "relative", floor: float = 1e-3) -> np.ndarray:
    """Per-pixel error (H, W): ``"relative"`` |Y_a − Y_b| / max(Y_b, floor·mean Y_b) or ``"absolute"`` |Y_a − Y_b|;
    0 outside the mask."""
    a, b, m = check_pair(a, b, mask)
    ya, yb = _lum(a), _lum(b)
    e = np.abs(ya - yb)
    if kind == "relative":
        e = e / np.maximum(yb, floor * max(float(yb[m].mean()), 1e-300))
    elif kind != "absolute":
        raise IBLError(f"kind must be 'relative' or 'absolute', got {kind!r}")
    return np.where(m, e, 0.0)


def flip_available() -> bool:
    """True when the ``flip_evaluator`` package (NVIDIA FLIP) can be imported."""
    try:
        import flip_evaluator  # noqa: F401
    except Exception:
        return False
    return True


def flip(a, b, mask=None):
    """Mean HDR-FLIP error of ``a`` against reference ``b`` (``flip_evaluator.evaluate``), or None when unavailable.

    Uncovered pixels are set to 0 in both images (FLIP has no mask); returns (value or None, message).
    """
    a, b, m = check_pair(a, b, mask)
    if not flip_available():
        return None, "FLIP skipped: package 'flip_evaluator' is not installed"
    import flip_evaluator as fe

    if a.ndim == 2:
        a, b = a[..., None].repeat(3, -1), b[..., None].repeat(3, -1)
    a = np.where(m[..., None], a, 0.0).astype(np.float32)
    b = np.where(m[..., None], b, 0.0).astype(np.float32)
    _, mean_err, _ = fe.evaluate(b, a, "HDR")
    return float(mean_err), "HDR-FLIP (flip_evaluator)"


def all_metrics(a, b, mask=None) -> dict:
    """{rmse, rel_l1, rel_max, flip (None if unavailable), flip_note}."""
    f, note = flip(a, b, mask)
    return dict(rmse=rmse(a, b, mask), rel_l1=rel_l1(a, b, mask), rel_max=rel_max(a, b, mask), flip=f, flip_note=note)
