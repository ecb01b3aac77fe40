"""The orthographic unit sphere used by the sphere figures (Knuth et al. 2014 Fig. 3; the lights-vs-lobes study).

A unit sphere is viewed orthographically along −z: the camera sits on +Z, the view vector towards the camera
is v = (0, 0, 1), image row 0 is +y (top) and column 0 is −x.  A pixel of a ``px × px`` image covering
[−1, 1]² is on the sphere if its centre (x, y) has x² + y² < 1; its normal is n = (x, y, √(1 − x² − y²)) and
the mirror direction is r = 2(n·v)n − v (Eq. 3's lookup direction, unit length by construction and
renormalised against rounding).  No occlusion: a convex object does not shadow itself.
"""

from __future__ import annotations

import numpy as np
from ..knuth2014.gloss_lookup import lookup

__all__ = ["orthographic_sphere", "to_image", "render_sphere_lookup"]


def orthographic_sphere(px: int):
    """(mask (px, px) bool, normals (P, 3), reflections (P, 3)) of the unit sphere seen from +Z."""
    px = int(px)
    c = (np.arange(px) + 0.5) / px * 2 - 1
    x, y = np.meshgrid(c, -c)  # row 0 = top = +y
    rr = x * x + y * y
    mask = rr < 1.0
    n = np.stack([x[mask], y[mask], np.sqrt(np.clip(1.0 - rr[mask], 0.0, 1.0))], axis=-1)
    v = np.array([0.0, 0.0, 1.0])
    r = 2.0 * (n @ v)[:, None] * n - v
    return mask, n, r / np.linalg.norm(r, axis=-1, keepdims=True)


def to_image(mask, values) -> np.ndarray:
    """Scatter per-pixel ``values`` (P, C) into a (H, W, C) image, background 0."""
    values = np.asarray(values)
    img = np.zeros(mask.shape + values.shape[1:], dtype=np.float64)
    img[mask] = values
    return img


def render_sphere_lookup(pyramid, g: float, px: int, **lookup_kwargs) -> np.ndarray:
    """(px, px, C) image of the sphere shaded by the glossiness lookup of ``pyramid`` at (r, g)."""

    mask, _, r = orthographic_sphere(px)
    return to_image(mask, lookup(pyramid, r, g, **lookup_kwargs))
