"""Knuth et al. (2014) 5×5 separable low-pass filters of the filter pyramid.

Paper: Knuth, Altenhofen, Kuijper, Bender, *Efficient Self-Shadowing Using Image-Based Lighting on
Glossy Surfaces* (VMV 2014), Sec. 3.2 (Fig. 2: an additional 5×5 low-pass filter between the 2×2
shrinks of a MIP chain) and Sec. 4 ("For the cosine-based filters we used exponents of
[cos(−60), cos(−30), cos(0), cos(30), cos(60)] divided by the sum of the single elements for generating
the 1D filters"; "applying a 1D filter separately for rows and subsequently for the columns of a face.
At edges, the neighboring face needs to be taken into account").

Kernels (1D, 5 taps, sum 1; the 2D filter is the outer product)
-----------------------------------------------------------------
::

    none     [0, 0, 1, 0, 0] (identity: the plain MIP chain)
    box      [1, 1, 1, 1, 1] / 5
    gauss    exp(−t²/(2σ²)) at t = −2..2 taps, σ = GAUSS_SIGMA_TAPS = 1.0 tap (the paper gives no σ;
             1 tap makes the 5 taps span ±2σ, the usual truncation of a 5-tap Gaussian)
    cos      cos([−60, −30, 0, 30, 60]°) normalised
    sqrtcos  √cos([−60, −30, 0, 30, 60]°) normalised (the paper's choice)
    cos^k    cos([−60, −30, 0, 30, 60]°)^k normalised, any real k ≥ 0 (cos^0 = box, cos^0.5 = sqrtcos)

Seam modes (an explicit enum, never an accident)
------------------------------------------------
``neighbour`` (the paper's): each face is padded by 2 texels read from the neighbouring faces
(:func:`ibl_ref.environment.sampling.pad_faces`: edge strips are exact copies of the neighbour's texels unfolded
about the shared edge; the 2×2 corner blocks, where only three faces meet, are filled geometrically).
The row pass runs over *all* N+4 padded rows (so it reads the corner blocks), then the column pass
reads the row-filtered padded rows.  This is exactly the 5×5 outer-product filter applied in each
face's unfolded frame.

Why not re-pad between the row and the column pass?  The obvious alternative (row-filter the N×N faces,
pad the row-filtered cube, column-filter) avoids the corner blocks but is *wrong* on the 4 edges where a
face's rows are not parallel to its neighbour's (in the OpenEXR orientation: ±Y against ±X).  E.g. the
+X/+Y edge is a row of +X but a column of +Y, so the padded texels +X reads from +Y were filtered
*across* the edge by +Y's row pass, and +X's column pass filters across the edge a second time while
nothing filters along it (measured: a lit +Y texel next to +X reaches 2 texels of +X instead of 5×2).
The single-pad scheme has only the (small, documented) corner-block approximation, affecting texels within
2 texels of the 8 cube corners.  Both are available (``neighbour_repad`` for the alternative) so that
:mod:`ibl_ref.knuth2014.seam_metric` can show the difference.

``clamp``: per face, the edge texel is repeated (what tools that filter faces independently do).

Faces of size 1 (the last pyramid level) cannot be padded by 2 texels from their neighbours
(a 2-texel unfolding of a 1-texel face would reach the opposite face): they are padded by 1 texel from
the neighbours and the outer ring is a copy of that ring (taps ±2 read the neighbour face again).
"""

from __future__ import annotations

import functools
import re

import numpy as np

from ..environment.envmap import check_cube_shape
from ..errors import IBLError, LayoutError
from ..environment.sampling import padding_tables

__all__ = [
    "KERNELS",
    "KERNEL_NAMES",
    "SEAM_MODES",
    "GAUSS_SIGMA_TAPS",
    "COS_TAP_ANGLES_DEG",
    "kernel_taps",
    "check_seam",
    "pad_cube",
    "filter_cube",
]

#: tap angles of the cosine-based filters (Sec. 4)
COS_TAP_ANGLES_DEG = np.array([-60.0, -30.0, 0.0, 30.0, 60.0])
#: σ of the ``gauss`` kernel, in taps (not given in the paper)
GAUSS_SIGMA_TAPS = 1.0
SEAM_MODES = ("neighbour", "clamp", "neighbour_repad")


def _normalised(w) -> np.ndarray:
    w = np.asarray(w, dtype=np.float64)
    w = w / w.sum()
    w.setflags(write=False)
    return w


def _cos_power(k: float) -> np.ndarray:
    # Sec. 4: cos of [-60,-30,0,30,60] degrees (raised to a power), divided by the sum of the elements
    return _normalised(np.cos(np.deg2rad(COS_TAP_ANGLES_DEG)) ** k)


#: registry name → 5 taps (float64, sum 1)
KERNELS: dict[str, np.ndarray] = {
    "none": _normalised([0.0, 0.0, 1.0, 0.0, 0.0]),
    "box": _normalised([1.0, 1.0, 1.0, 1.0, 1.0]),
    "gauss": _normalised(np.exp(-(np.arange(-2, 3) ** 2) / (2.0 * GAUSS_SIGMA_TAPS**2))),
    "cos": _cos_power(1.0),
    "sqrtcos": _cos_power(0.5),
}
#: the five filters of the paper's Fig. 4/5
KERNEL_NAMES = ("none", "gauss", "cos", "box", "sqrtcos")

_COSK = re.compile(r"^cos\^([0-9]*\.?[0-9]+)$")


def kernel_taps(kernel) -> np.ndarray:
    """The 5 normalised taps of a kernel.

    Parameters
    ----------
    kernel : str or array-like of 5 floats
        A name in :data:`KERNELS`, ``"cos^k"`` (k ≥ 0 real), or explicit non-negative taps (normalised
        here).

    Raises
    ------
    IBLError
        Unknown name (message lists the options) or bad explicit taps.
    """
    if isinstance(kernel, str):
        if kernel in KERNELS:
            return KERNELS[kernel]
        m = _COSK.match(kernel.strip())
        if m:
            return _cos_power(float(m.group(1)))
        raise IBLError(
            f"unknown filter kernel {kernel!r}; choose one of {', '.join(KERNELS)} or 'cos^k' with a real k >= 0"
        )
    w = np.asarray(kernel, dtype=np.float64)
    if w.shape != (5,) or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise IBLError(f"explicit kernel taps must be 5 finite non-negative numbers with a positive sum, got {kernel!r}")
    return _normalised(w)


def check_seam(seam: str) -> str:
    """``seam`` if it is one of :data:`SEAM_MODES`, else IBLError."""
    if seam not in SEAM_MODES:
        raise IBLError(f"unknown seam mode {seam!r}; choose one of {', '.join(SEAM_MODES)}")
    return seam


@functools.lru_cache(maxsize=64)
def _border_tables(n: int, k: int):
    """Border-only gather tables built from :func:`ibl_ref.environment.sampling.padding_tables`."""

    src, w = padding_tables(n, k)
    m = n + 2 * k
    border = np.ones((m, m), dtype=bool)
    border[k : k + n, k : k + n] = False
    rows, cols = np.nonzero(border)
    bsrc = src[:, rows, cols, :]  # (6, B, 3)
    bw = w[:, rows, cols, :]
    exact = np.all(bw[..., 1:] == 0, axis=(0, 2)) & np.all(bw[..., 0] == 1, axis=0)  # (B,) copy-only positions
    return rows, cols, bsrc, bw, exact


def pad_cube(cube: np.ndarray, k: int, seam: str = "neighbour") -> np.ndarray:
    """Pad every face by ``k`` texels: neighbour faces (``neighbour*``) or edge repetition (``clamp``).

    Equivalent to :func:`ibl_ref.environment.sampling.pad_faces` for the neighbour modes, but gathers only the
    border (the interior is a slice copy), which matters for the pyramid's speed.

    Parameters
    ----------
    cube : array (6, N, N) or (6, N, N, C)
    k : int, 0 ≤ k ≤ N
    seam : {"neighbour", "neighbour_repad", "clamp"}
    """
    n = check_cube_shape(cube)
    check_seam(seam)
    cube = np.asarray(cube)
    extra = cube.shape[3:]
    if seam == "clamp":
        return np.pad(cube, [(0, 0), (k, k), (k, k)] + [(0, 0)] * len(extra), mode="edge")
    if k > n:
        raise LayoutError(f"cannot pad {n}x{n} faces by {k} texels from their neighbours (k must be <= N)")
    m = n + 2 * k
    out = np.empty((6, m, m) + extra, dtype=cube.dtype)
    out[:, k : k + n, k : k + n] = cube
    if k == 0:
        return out
    rows, cols, bsrc, bw, exact = _border_tables(n, k)
    flat = cube.reshape((6 * n * n,) + extra)
    vals = np.empty((6, rows.size) + extra, dtype=cube.dtype)
    vals[:, exact] = flat[bsrc[:, exact, 0]]
    mix = ~exact
    if mix.any():
        g = flat[bsrc[:, mix, :]]  # (6, Bm, 3, ...)
        wm = bw[:, mix, :].reshape(bw[:, mix, :].shape + (1,) * len(extra))
        vals[:, mix] = (g * wm).sum(axis=2).astype(cube.dtype, copy=False)
    out[:, rows, cols] = vals
    return out


def _taps_along(p: np.ndarray, w: np.ndarray, axis: int, n: int) -> np.ndarray:
    """Valid 5-tap correlation along ``axis`` (1 = rows/vertical, 2 = columns/horizontal) of a 2-padded array."""
    dt = p.dtype

    def sl(t):
        idx = [slice(None)] * p.ndim
        idx[axis] = slice(t, t + n)
        return p[tuple(idx)]

    # symmetric kernels (all registered ones): 3 multiplies instead of 5
    if w[0] == w[4] and w[1] == w[3]:
        out = sl(2) * dt.type(w[2]) if w[2] != 1.0 else sl(2).copy()
        if w[1] != 0.0:
            out += (sl(1) + sl(3)) * dt.type(w[1])
        if w[0] != 0.0:
            out += (sl(0) + sl(4)) * dt.type(w[0])
        return out
    out = sl(0) * dt.type(w[0])
    for t in range(1, 5):
        out += sl(t) * dt.type(w[t])
    return out


def filter_cube(cube: np.ndarray, kernel="sqrtcos", seam: str = "neighbour") -> np.ndarray:
    """Apply the separable 5×5 filter (rows, then columns) to every face of a cube map.

    Parameters
    ----------
    cube : array (6, N, N) or (6, N, N, C), float
    kernel : str or 5 taps
        See :func:`kernel_taps`.
    seam : {"neighbour", "clamp", "neighbour_repad"}
        Border handling (module docstring).  ``neighbour`` is the paper's.

    Returns
    -------
    array of the same shape and (floating) dtype.
    """
    n = check_cube_shape(cube)
    w = kernel_taps(kernel)
    check_seam(seam)
    cube = np.asarray(cube)
    if not np.issubdtype(cube.dtype, np.floating):
        cube = cube.astype(np.float64)
    if np.array_equal(w, KERNELS["none"]):
        return cube.copy()
    k = 2
    if seam == "neighbour_repad":
        # row pass on the face rows only, re-pad, column pass (see module docstring for why this is worse)
        p = _pad2(cube, n, "neighbour")
        r = _taps_along(p[:, k : k + n], w, axis=2, n=n)
        p2 = _pad2(r, n, "neighbour")
        return _taps_along(p2[:, :, k : k + n], w, axis=1, n=n)
    p = _pad2(cube, n, seam)
    r = _taps_along(p, w, axis=2, n=n)  # (6, N+4, N, ...): all padded rows, incl. corner blocks
    return _taps_along(r, w, axis=1, n=n)


def _pad2(cube, n, seam):
    if seam == "clamp" or n >= 2:
        return pad_cube(cube, 2, seam)
    # 1×1 faces: 1 texel from the neighbours, then repeat that ring (module docstring)
    p1 = pad_cube(cube, 1, seam)
    return np.pad(p1, [(0, 0), (1, 1), (1, 1)] + [(0, 0)] * (cube.ndim - 3), mode="edge")
