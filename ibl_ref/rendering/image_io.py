"""Plain image files of the renderer: radiance images (OpenEXR) and glossiness maps.

Rendered images of Knuth et al. (2014), Eq. 5, are radiance (linear, unbounded) and are stored as plain
scanline OpenEXR images, channels ``R, G, B`` (or ``Y`` for one channel), 32-bit float, ZIP compression, no
``envmap`` attribute (they are not environment maps; use :mod:`ibl_ref.environment.exr_io` for those).  Written and
read by the one OpenEXR writer and reader (:func:`ibl_ref.environment.exr_io.write_exr`,
:func:`ibl_ref.environment.exr_io.read_exr`), atomically (:func:`ibl_ref.atomic.atomic_path`).

Glossiness maps (the per-texel g of :class:`ibl_ref.rendering.render.Material`) are read from ``.npy`` (a 2D float
array), ``.exr`` (channel ``Y``, or the mean of ``R, G, B``) or ``.png`` (8/16-bit, values / max → [0, 1];
the mean of ``R, G, B`` for colour images; alpha ignored).  Row 0 of the file is the *top* of the map (v = 1).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..environment.radiance_policy import check_radiance
from ..errors import IBLError, as_path, check_input_file
from ..environment.exr_io import ExrPart
from ..environment.exr_io import read_image
from ..environment.exr_io import to_pixel_type
from ..environment.exr_io import write_exr

__all__ = ["write_image_exr", "read_image_exr", "read_g_map"]

_FLOAT32_MAX = float(np.finfo(np.float32).max)


def write_image_exr(path, img, *, signed: bool = False) -> Path:
    """Write a radiance image (H, W), (H, W, 1) or (H, W, 3) as a float32 OpenEXR file (atomically).

    Through the one OpenEXR writer :func:`ibl_ref.environment.exr_io.write_exr` (same header policy as the
    environment maps, without an ``envmap`` attribute).  ``signed=True`` accepts negative values: difference
    images (e.g. the error budget's per-step differences, ``ibl_ref.rendering.error_budget``), which are not
    radiance; read them with any EXR reader that keeps the sign.

    Raises
    ------
    IBLError
        NaN/Inf, negative values, values beyond float32, values below float32's normal range that carry more
        than 1e-4 of the image's sum, or an unsupported shape (checked before writing).
    EnvMapFileError
        The OpenEXR library cannot write the file.
    """

    path = as_path(path, "OpenEXR image")
    a = np.asarray(img, dtype=np.float64)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in (1, 3) or a.shape[0] < 1 or a.shape[1] < 1:
        raise IBLError(f"{path}: image must be (H, W), (H, W, 1) or (H, W, 3), got shape {np.shape(img)}")
    if signed:  # signed data (difference images): only NaN / Inf are refused
        if not np.all(np.isfinite(a)):
            raise IBLError(f"{path}: image contains NaN or Inf; refusing to write")
        if np.any(np.abs(a) > _FLOAT32_MAX):
            raise IBLError(f"{path}: values exceed the float32 range")
        pix = a.astype(np.float32)
    else:
        check_radiance(a, f"{path}: image")  # NaN / Inf / negative radiance: refuse to write
        pix = to_pixel_type(a, "float", False, str(path))[0]  # overflow refused, underflow measured
    write_exr(path, ExrPart(pix, ("R", "G", "B") if pix.shape[2] == 3 else ("Y",)))
    return path


def read_image_exr(path) -> np.ndarray:
    """Read an OpenEXR image written by :func:`write_image_exr` (or any RGB/Y EXR) → (H, W, C) float64."""

    return read_image(path)[0]


def read_g_map(path) -> np.ndarray:
    """A glossiness map (h, w) float64 in [0, 1] from ``.npy``, ``.exr`` or ``.png`` (module docstring).

    Raises
    ------
    IBLError
        Unknown extension, unreadable file, not 2D, or values outside [0, 1].
    """
    path = check_input_file(path, "a g map (.npy, .exr or .png)", IBLError)
    ext = path.suffix.lower()
    if ext == ".npy":
        try:
            a = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise IBLError(f"{path}: cannot read .npy g map: {exc}") from exc
        a = np.asarray(a, dtype=np.float64)
    elif ext == ".exr":
        a = read_image_exr(path)
        a = a[..., 0] if a.shape[2] == 1 else a[..., :3].mean(axis=2)
    elif ext == ".png":
        import matplotlib.image as mpimg

        try:
            a = np.asarray(mpimg.imread(str(path), format="png"), dtype=np.float64)  # floats in [0, 1]
        except Exception as exc:  # PIL/matplotlib raise many types for bad files
            raise IBLError(f"{path}: cannot read PNG g map: {exc}") from exc
        if a.ndim == 3:
            a = a[..., 0] if a.shape[2] in (1, 2) else a[..., :3].mean(axis=2)
    else:
        raise IBLError(f"{path}: g map must be .npy, .exr or .png, got {ext or 'no extension'!r}")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim != 2 or a.size == 0:
        raise IBLError(f"{path}: g map must be a 2D image, got shape {a.shape}")
    if np.any(~np.isfinite(a)) or np.any(a < 0) or np.any(a > 1):
        raise IBLError(f"{path}: g map values must be in [0, 1] (0 = diffuse, 1 = mirror)")
    return a
