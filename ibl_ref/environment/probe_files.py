"""Probe-like lat-long files made the way published light probes are, for tests and benchmarks.

Not a paper concept.  Published outdoor probes are 2:1 lat-long OpenEXR files (float32 or half RGB,
often **DWAB**, PIZ or ZIP compressed, usually without an ``envmap`` attribute) or Radiance ``.hdr``
files (RLE), with a small sun of 1e4–1e5 (docs/background.md "Real light probes").
:func:`sky_sun_latlong` builds such a map with a **closed-form** ∫L dω, and :func:`write_probe_exr`
writes it the way a third-party tool would (chosen compression, no ``envmap`` attribute, half overflow to
Inf) through the one OpenEXR writer :func:`ibl_ref.environment.exr_io.write_exr`, bypassing the checks of
:func:`ibl_ref.environment.exr_io.write_envmap` (which always writes ZIP with the attribute).

The map (H × 2H, rows = latitude bands of the OpenEXR LATLONG layout, ``ibl_ref.environment.envmap``)
-----------------------------------------------------------------------------------------
* sky (upper hemisphere, y > 0): every texel holds the exact texel *average* of
  ``a + b·y`` (y = sin latitude), i.e. ``a + b·(sin²φ1 − sin²φ0) / (2(sinφ1 − sinφ0))`` for the band
  φ0 < φ < φ1;
* ground (lower hemisphere): ``g`` times a deterministic texture in [0.2, 1] (seeded), with one
  black strip (exact zeros, where lossy codecs ring below zero);
* sun: the texels whose centre lies within ``sun_radius_deg`` of ``sun_dir`` hold ``sun``
  (replacing the sky).

With H even no band straddles the horizon, so ∫ sky dω = a·2π + b·π exactly, minus what the sun texels
replace; :func:`sky_sun_latlong` returns the exact integral of the map it built (per channel) computed
from these closed forms (texel solid angle Δλ·(sin φ1 − sin φ0)), not from :mod:`ibl_ref.environment.resample`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import IBLError
from .exr_io import ExrPart
from .exr_io import write_exr
from .resample import latlong_to_cube

__all__ = ["sky_sun_latlong", "probe_cube", "write_probe_exr"]


def sky_sun_latlong(h: int, a: float = 0.4, b: float = 1.2, g: float = 0.05, sun: float = 3e4,
                    sun_dir=(0.3, 0.55, -0.78), sun_radius_deg: float = 1.5, colour=(1.0, 0.9, 0.75),
                    seed: int = 0, dtype=np.float64):
    """``(image (h, 2h, 3), exact ∫L dω per channel (3,))`` of the probe described in the module docstring.

    ``h`` must be even.  The sun covers at least the one texel nearest to ``sun_dir``.
    """
    if h < 2 or h % 2:
        raise IBLError(f"h must be an even integer >= 2, got {h}")
    w = 2 * h
    edges = np.pi / 2 - np.pi * np.arange(h + 1) / h  # latitude of the row edges, top first
    s0, s1 = np.sin(edges[1:]), np.sin(edges[:-1])  # sin φ0 < sin φ1 per row
    dlon = 2 * np.pi / w
    om_row = dlon * (s1 - s0)  # exact texel solid angle per row
    sky_row = a + b * (s1**2 - s0**2) / (2 * (s1 - s0))
    rng = np.random.default_rng(seed)
    lum = np.empty((h, w), dtype=np.float64)
    up = h // 2
    lum[:up] = sky_row[:up, None]
    tex = 0.2 + 0.8 * rng.random((h - up, w))
    lum[up:] = g * tex
    lum[up + (h - up) // 3 : up + (h - up) // 3 + max(1, h // 16), : w // 4] = 0.0  # black strip
    # sun texels by their centre direction (OpenEXR LATLONG: left column longitude +π, (0,0) = +Z)
    lat_c = 0.5 * (edges[1:] + edges[:-1])
    lon_c = np.pi - (np.arange(w) + 0.5) * dlon
    d = np.asarray(sun_dir, dtype=np.float64)
    d = d / np.linalg.norm(d)
    cosang = (np.cos(lat_c)[:, None] * (np.sin(lon_c)[None, :] * d[0] + np.cos(lon_c)[None, :] * d[2])
              + np.sin(lat_c)[:, None] * d[1])
    in_sun = cosang >= np.cos(np.radians(sun_radius_deg))
    if not in_sun.any():
        in_sun[np.unravel_index(np.argmax(cosang), cosang.shape)] = True
    img = lum[..., None] * np.ones(3)
    img[in_sun] = sun * np.asarray(colour, dtype=np.float64)
    # exact integral per channel, from the closed forms above (not from the image sum)
    om = np.broadcast_to(om_row[:, None], (h, w))
    sky_int = a * 2 * np.pi + b * np.pi  # ∫ over y > 0 of a + b·y
    ground_int = float(np.sum(lum[up:] * om[up:]))  # a sum of stored values × closed-form texel areas
    replaced = float(np.sum(lum[in_sun] * om[in_sun]))
    sun_int = float(np.sum(om[in_sun])) * sun * np.asarray(colour)
    exact = (sky_int + ground_int - replaced) + sun_int
    return img.astype(dtype), exact


def probe_cube(n: int, h: int | None = None, **kw) -> np.ndarray:
    """The probe of :func:`sky_sun_latlong` (height ``h``, default 4n: the lat-long texels are finer than the cube's)
    as a (6, n, n, 3) float64 cube map, resampled with the conservative kernel that keeps ∫L dω
    (:func:`ibl_ref.environment.resample.latlong_to_cube`) — a probe-like environment with a small bright sun,
    a textured ground and a black strip, for renders and experiments.  ``kw`` go to :func:`sky_sun_latlong`.
    """

    img, _ = sky_sun_latlong(4 * int(n) if h is None else int(h), **kw)
    return np.asarray(latlong_to_cube(img, int(n)), dtype=np.float64)


def write_probe_exr(path, img, compression: str = "dwab", pixel_type: str = "float",
                    envmap_attribute: bool = False) -> Path:
    """Write an ``(H, W, 3)`` image as an RGB scanline EXR the way published probes are made (atomically).

    ``compression`` ∈ :data:`COMPRESSIONS`; ``pixel_type`` ``"float"`` or ``"half"`` (values above
    65504 become Inf in half, as in any tool that does not clamp); no ``envmap`` attribute unless
    ``envmap_attribute=True`` (then LATLONG).  No radiance checks (a test/benchmark fixture).
    """
    import OpenEXR as ox


    if pixel_type not in ("float", "half"):
        raise IBLError(f"{path}: pixel_type must be 'float' or 'half', got {pixel_type!r}")
    a = np.asarray(img)
    dt = {"float": np.float32, "half": np.float16}[pixel_type]
    with np.errstate(over="ignore"):
        pix = a[..., :3].astype(dt)
    attrs = {"envmap": ox.ENVMAP_LATLONG} if envmap_attribute else {}
    return write_exr(path, ExrPart(pix, ("R", "G", "B"), attrs), compression=compression)
