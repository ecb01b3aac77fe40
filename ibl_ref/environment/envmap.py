"""Environment-map geometry: the single source of truth for every convention in ibl_ref.

This module fixes, once, how a direction on the unit sphere maps to a texel of a cube map or a
latitude-longitude map, and what solid angle every texel covers.  Everything else in the package
(resampling, filtering, convolution, median cut, rendering) calls these functions and never
re-derives a face orientation.

Conventions
-----------
**Cube-map array layout.**  A cube map is a float array ``cube[face, row, col, channel]`` of shape
``(6, N, N, C)`` (or ``(6, N, N)`` for one channel).  Faces are in OpenEXR order
``+X, -X, +Y, -Y, +Z, -Z`` (indices 0..5, :data:`FACE_NAMES`).  ``row`` 0 is the top scanline of the
face as it is stored in an OpenEXR CUBE file (a ``N x 6N`` vertical strip, faces stacked top to
bottom in that order); ``col`` 0 is the left column.

**Face orientation** (``convention="openexr"``, the default) is the one defined by the functions
``CubeMap::pixelPosition`` / ``CubeMap::direction`` in OpenEXR's ``ImfEnvmap.cpp``.  With the face-plane
coordinates ``u`` (left -1 → right +1) and ``v`` (top -1 → bottom +1) it reads::

    +X: ( 1, -v,  u)    -X: (-1, -v, -u)
    +Y: ( u,  1, -v)    -Y: ( u, -1,  v)
    +Z: (-u, -v,  1)    -Z: ( u, -v, -1)

i.e. every face is seen *from inside the cube* with +Y up on the four side faces.  The alternative
``convention="opengl"`` is the OpenGL / Direct3D cube-map layout (also used by cmft, CubeMapGen and
py360convert), in which each face is seen from outside::

    +X: ( 1, -v, -u)    -X: (-1, -v,  u)
    +Y: ( u,  1,  v)    -Y: ( u, -1, -v)
    +Z: ( u, -v,  1)    -Z: (-u, -v, -1)

The two differ by a horizontal flip of the four side faces and a vertical flip of ±Y
(:func:`convert_convention`).

**Texel addressing.**  ibl_ref addresses texel *centres*: texel ``(row, col)`` of a face of size N covers
the face-plane square ``u ∈ [-1 + 2·col/N, -1 + 2·(col+1)/N]``, ``v`` likewise with ``row``, and its
centre is ``u = (col + ½)/N·2 − 1``.  Continuous texel coordinates ``(x, y) = ((u+1)/2·N − ½, (v+1)/2·N − ½)``
put texel centres on integers, so ``x ∈ [−½, N−½]`` on a face.  OpenEXR's helper functions instead
address pixels corner to corner (``pos/(N−1)·2 − 1``); only the face order and orientation are taken
from them (the tests check that both addressings put every texel on the same face, in the same
quadrant, with the same ordering).

**Lat-long maps** (``envmap = LATLONG``, OpenEXR ``LatLongMap``): a ``H x W`` image with ``W = 2H``;
the top row is latitude +π/2, the left column is longitude +π, and
``direction = (sin λ cos φ, sin φ, cos λ cos φ)`` for latitude φ and longitude λ, so +Y is up,
(φ, λ) = (0, 0) is +Z and λ = +π/2 is +X.  Texel centres are at ``φ = π/2 − π (row+½)/H`` and
``λ = π − 2π (col+½)/W``.

**Units.**  Arrays hold radiance in arbitrary linear units (W·sr⁻¹·m⁻² if you like); solid angles are
in steradians; ∫L dω therefore has the units of radiance × sr.

Solid angles are exact (closed form): the face-plane rectangle ``[x0, x1] × [y0, y1]`` at distance 1
subtends ``A(x1,y1) − A(x0,y1) − A(x1,y0) + A(x0,y0)`` with ``A(x, y) = atan2(x·y, √(x² + y² + 1))``
(see ``docs/background.md`` §2).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from ..errors import IBLError, LayoutError
from ..limits import check_allocation

__all__ = [
    "FACE_NAMES",
    "CONVENTIONS",
    "face_uv_to_direction",
    "direction_to_face_uv",
    "uv_to_texel_coords",
    "texel_coords_to_uv",
    "texel_center_uv",
    "texel_directions",
    "texel_max_radius",
    "face_blocks",
    "direction_to_texel",
    "direction_to_texel_coords",
    "texel_solid_angles",
    "cube_solid_angles",
    "face_plane_grid",
    "convert_convention",
    "face_frames",
    "check_face_size",
    "as_directions",
    "unit_directions",
    "MipLevel",
    "mip_levels",
    "latlong_directions",
    "latlong_solid_angles",
    "direction_to_latlong",
    "check_cube_shape",
    "CROSS_LAYOUTS",
]

FACE_NAMES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
CONVENTIONS = ("openexr", "opengl")

#: cross images (:func:`ibl_ref.environment.resample.cross_to_cube`): grid cells (rows, columns) and, per face in
#: FACE_NAMES order, (cell row, cell column, rotate by 180°), OpenGL orientation
CROSS_LAYOUTS = {
    "hcross": {"cells": (3, 4), "faces": ((1, 2, False), (1, 0, False), (0, 1, False), (2, 1, False),
                                           (1, 1, False), (1, 3, False))},
    "vcross": {"cells": (4, 3), "faces": ((1, 2, False), (1, 0, False), (0, 1, False), (2, 1, False),
                                           (1, 1, False), (3, 1, True))},
}

# Face frames: direction = major * axis + u * u_axis + v * v_axis  (unnormalised, on the cube |major| = 1).
# Rows are faces in FACE_NAMES order; columns: (axis, u_axis, v_axis).
_FRAMES = {
    "openexr": np.array(
        [
            [[1, 0, 0], [0, 0, 1], [0, -1, 0]],  # +X: (1, -v, u)
            [[-1, 0, 0], [0, 0, -1], [0, -1, 0]],  # -X: (-1, -v, -u)
            [[0, 1, 0], [1, 0, 0], [0, 0, -1]],  # +Y: (u, 1, -v)
            [[0, -1, 0], [1, 0, 0], [0, 0, 1]],  # -Y: (u, -1, v)
            [[0, 0, 1], [-1, 0, 0], [0, -1, 0]],  # +Z: (-u, -v, 1)
            [[0, 0, -1], [1, 0, 0], [0, -1, 0]],  # -Z: (u, -v, -1)
        ],
        dtype=np.float64,
    ),
    "opengl": np.array(
        [
            [[1, 0, 0], [0, 0, -1], [0, -1, 0]],  # +X: (1, -v, -u)
            [[-1, 0, 0], [0, 0, 1], [0, -1, 0]],  # -X: (-1, -v, u)
            [[0, 1, 0], [1, 0, 0], [0, 0, 1]],  # +Y: (u, 1, v)
            [[0, -1, 0], [1, 0, 0], [0, 0, -1]],  # -Y: (u, -1, -v)
            [[0, 0, 1], [1, 0, 0], [0, -1, 0]],  # +Z: (u, -v, 1)
            [[0, 0, -1], [-1, 0, 0], [0, -1, 0]],  # -Z: (-u, -v, -1)
        ],
        dtype=np.float64,
    ),
}


def face_frames(convention: str) -> np.ndarray:
    """The face frames of a cube-map convention.

    Parameters
    ----------
    convention : {"openexr", "opengl"}

    Returns
    -------
    ndarray, float64, shape (6, 3, 3)
        Per face (in :data:`FACE_NAMES` order) the major axis, the u axis and the v axis: the face-plane point
        (u, v) has the unnormalised direction ``F[0] + u·F[1] + v·F[2]``.

    Raises
    ------
    LayoutError
        An unknown convention.
    """
    try:
        return _FRAMES[convention]
    except KeyError:
        raise LayoutError(
            f"unknown cube-map convention {convention!r}; choose one of {', '.join(CONVENTIONS)}"
        ) from None


def check_face_size(n) -> int:
    """A face size as an int.

    Parameters
    ----------
    n : int
        A positive integer (not a bool, not a float).

    Returns
    -------
    int

    Raises
    ------
    SizeError
        Anything else (:class:`ibl_ref.limits.SizeError`).
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or int(n) < 1:
        from ..limits import SizeError

        raise SizeError(f"face size must be a positive integer, got {n!r}")
    return int(n)


# ----------------------------------------------------------------------------------------------
# face plane <-> direction
# ----------------------------------------------------------------------------------------------
def face_uv_to_direction(face, u, v, convention: str = "openexr", normalize: bool = True) -> np.ndarray:
    """Direction through the point (u, v) of a face plane.

    Parameters
    ----------
    face : int or array of int
        Face index 0..5 in :data:`FACE_NAMES` order.
    u, v : float or array
        Face-plane coordinates (u left→right, v top→bottom, both in [-1, 1] on the face; values
        outside describe the face's extended plane).
    convention : {"openexr", "opengl"}
    normalize : bool
        Return unit vectors (default) or the point on the cube surface / extended plane.

    Returns
    -------
    ndarray, float64, shape ``broadcast(face, u, v).shape + (3,)``

    Raises
    ------
    LayoutError
        A face index outside 0..5 or an unknown convention.

    Examples
    --------
    The centre of the +Z face (index 4) looks along +Z; a point of the +X face, on the cube's surface:

    >>> from ibl_ref.environment.envmap import face_uv_to_direction
    >>> face_uv_to_direction(4, 0.0, 0.0)
    array([0., 0., 1.])
    >>> face_uv_to_direction(0, 0.5, -0.5, normalize=False)
    array([1. , 0.5, 0.5])
    """
    frames = face_frames(convention)
    face = np.asarray(face)
    if face.size and (np.any(face < 0) or np.any(face > 5) or not np.issubdtype(face.dtype, np.integer)):
        raise LayoutError("face indices must be integers in 0..5")
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if face.ndim == 0:  # one face: its frame's rows, no (..., 3, 3) gather (the same operations, the same numbers)
        u, v = np.broadcast_arrays(u, v)
        return _plane_directions(frames[int(face)], u, v, normalize)
    face, u, v = np.broadcast_arrays(face, u, v)
    f = frames[face]  # (..., 3, 3)
    d = f[..., 0, :] + u[..., None] * f[..., 1, :] + v[..., None] * f[..., 2, :]
    if normalize:
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return d


def _plane_directions(f, u, v, normalize: bool, out=None) -> np.ndarray:
    """Directions ``f[0] + u·f[1] + v·f[2]`` (optionally unit) of one face's frame ``f`` (3, 3) at the points
    ``u``, ``v`` (same shape), into ``out`` if given: the expression of :func:`face_uv_to_direction`, evaluated
    in the same order."""
    d = f[0] + u[..., None] * f[1] + v[..., None] * f[2]
    if normalize:
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
    if out is None:
        return d
    out[...] = d
    return out


def unit_directions(v, name: str = "directions", min_norm: float = 0.0) -> np.ndarray:
    """Directions normalised to unit length.

    Parameters
    ----------
    v : array_like, shape (..., 3)
    name : str, optional
        What the argument is called in error messages.
    min_norm : float, optional
        Vectors of this length or shorter are refused (default 0: only exactly zero ones).

    Returns
    -------
    ndarray, float64, shape (..., 3)

    Raises
    ------
    IBLError
        A wrong shape, NaN/Inf, or a vector of length ≤ ``min_norm``.
    """
    v = np.asarray(v, dtype=np.float64)
    if v.shape[-1:] != (3,):
        raise IBLError(f"{name} must be (..., 3) directions, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise IBLError(f"{name} contains NaN/Inf")
    ln = np.linalg.norm(v, axis=-1, keepdims=True)
    if np.any(ln <= min_norm):
        raise IBLError(f"{name} contains zero-length vectors" + (f" (length <= {min_norm:g})" if min_norm else ""))
    return v / ln


def as_directions(d) -> np.ndarray:
    """Directions as a float64 array of finite non-zero 3-vectors (not normalised).

    Parameters
    ----------
    d : array_like, shape (..., 3)

    Returns
    -------
    ndarray, float64, shape (..., 3)

    Raises
    ------
    LayoutError
        No trailing axis of length 3.
    IBLError
        Not numeric, NaN/Inf, or a zero vector.
    """
    try:
        d = np.asarray(d, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise IBLError(f"directions must be a numeric (..., 3) array ({exc})") from None
    if d.shape[-1:] != (3,):
        raise LayoutError(f"directions must have a trailing axis of length 3, got shape {d.shape}")
    if not np.all(np.isfinite(d)):
        raise IBLError("directions contain NaN or Inf")
    if np.any(np.all(d == 0, axis=-1)):
        raise IBLError("zero-length direction")
    return d


def direction_to_face_uv(d, convention: str = "openexr"):
    """Face index and face-plane coordinates of directions.

    The face is the one of the dominant axis; ties (directions exactly on an edge or corner) go to the
    first face in the order x, y, z, positive before negative — the same rule as OpenEXR's
    ``faceAndPixelPosition``.

    Parameters
    ----------
    d : array_like, shape (..., 3)
        Directions, need not be normalised.
    convention : {"openexr", "opengl"}

    Returns
    -------
    face : int array, shape (...)
    u, v : float64 arrays, shape (...), in [-1, 1]

    Examples
    --------
    >>> from ibl_ref.environment.envmap import direction_to_face_uv
    >>> face, u, v = direction_to_face_uv([0.5, 0.25, 1.0])
    >>> int(face), float(u), float(v)
    (4, -0.5, -0.25)
    """
    frames = face_frames(convention)
    d = as_directions(d)
    a = np.abs(d)
    ax = np.where((a[..., 0] >= a[..., 1]) & (a[..., 0] >= a[..., 2]), 0, np.where(a[..., 1] >= a[..., 2], 1, 2))
    comp = np.take_along_axis(d, ax[..., None], axis=-1)[..., 0]
    face = 2 * ax + (comp < 0)
    p = d / np.abs(comp)[..., None]  # point on the cube surface
    f = frames[face]
    u = np.einsum("...i,...i->...", p, f[..., 1, :])
    v = np.einsum("...i,...i->...", p, f[..., 2, :])
    return face.astype(np.intp), np.clip(u, -1.0, 1.0), np.clip(v, -1.0, 1.0)


# ----------------------------------------------------------------------------------------------
# texel addressing
# ----------------------------------------------------------------------------------------------
def uv_to_texel_coords(u, v, n: int):
    """Continuous texel coordinates of face-plane points.

    Parameters
    ----------
    u, v : float or array_like
        Face-plane coordinates, [-1, 1] on the face.
    n : int
        Face size.

    Returns
    -------
    x, y : float64 arrays
        Column and row, texel centres on integers: ``x = (u + 1)/2·n − ½``.
    """
    n = check_face_size(n)
    return (np.asarray(u) + 1.0) * 0.5 * n - 0.5, (np.asarray(v) + 1.0) * 0.5 * n - 0.5


def texel_coords_to_uv(x, y, n: int):
    """Face-plane coordinates of continuous texel coordinates (the inverse of :func:`uv_to_texel_coords`).

    Parameters
    ----------
    x, y : float or array_like
        Column and row, texel centres on integers.
    n : int
        Face size.

    Returns
    -------
    u, v : float64 arrays
    """
    n = check_face_size(n)
    return (np.asarray(x, dtype=np.float64) + 0.5) / n * 2.0 - 1.0, (np.asarray(y, dtype=np.float64) + 0.5) / n * 2.0 - 1.0


def texel_center_uv(n: int) -> np.ndarray:
    """Face-plane coordinate of the texel centres 0..n−1, ``(i + ½)/n·2 − 1``.

    Parameters
    ----------
    n : int
        Face size.

    Returns
    -------
    ndarray, float64, shape (n,)

    Examples
    --------
    >>> from ibl_ref.environment.envmap import texel_center_uv
    >>> texel_center_uv(4)
    array([-0.75, -0.25,  0.25,  0.75])
    """
    n = check_face_size(n)
    return (np.arange(n, dtype=np.float64) + 0.5) / n * 2.0 - 1.0


def face_plane_grid(n: int):
    """Face-plane coordinates of the texel centres of one face.

    Parameters
    ----------
    n : int
        Face size.

    Returns
    -------
    u, v : float64 arrays, shape (n, n)
        Indexed ``[row, col]``.
    """
    c = texel_center_uv(n)
    v, u = np.meshgrid(c, c, indexing="ij")
    return u, v


def face_blocks(a, b: int) -> np.ndarray:
    """The b×b blocks of texels of every face (a copy; no gather).

    Parameters
    ----------
    a : array_like, shape (F, m, m, ...)
        Faces of size m.
    b : int
        Block size; must divide m.

    Returns
    -------
    ndarray, shape (F·(m/b)², b², ...)
        Blocks in the order (face, block row, block column), the texels of a block row-major.

    Raises
    ------
    LayoutError
        ``b`` does not divide the faces, or the faces are not square.
    """
    a = np.asarray(a)
    F, m = a.shape[0], a.shape[1]
    if m % b or a.shape[2] != m:
        raise LayoutError(f"face_blocks: blocks of {b} do not tile faces of {a.shape[1]}x{a.shape[2]}")
    nb, rest = m // b, a.shape[3:]
    t = a.reshape((F, nb, b, nb, b) + rest).transpose((0, 1, 3, 2, 4) + tuple(range(5, 5 + len(rest))))
    return t.reshape((F * nb * nb, b * b) + rest)


@functools.lru_cache(maxsize=32)
def texel_max_radius(n: int) -> float:
    """Largest angle (rad) between a texel centre and one of its corners on a cube face of size n (the same on
    every face: the faces are rotations of one another).

    Parameters
    ----------
    n : int
        Face size.

    Returns
    -------
    float
        Radians; the corner texels of n = 1 reach the cube corners: ``atan(√2) ≈ 0.9553``.

    Notes
    -----
    In the face plane a centre (1, u, v) and a corner (1, u', v') make the angle ``atan2(|p × q|, p·q)`` with
    ``p × q = (u v' − v u', v − v', u' − u)`` and ``p·q = 1 + u u' + v v'`` (no normalisation; accurate for small
    angles, unlike an arccos of the dot product).  The face is symmetric under u → −u, v → −v, so the texels with
    u, v ≥ 0 (and the middle row and column) hold the maximum; only they are evaluated."""
    n = check_face_size(n)
    e = np.linspace(-1.0, 1.0, n + 1)
    c = texel_center_uv(n)
    k = (n - 1) // 2  # texels k…n−1: the mirror image m−1−j of every texel j < k is among them
    u, v = c[None, k:], c[k:, None]
    worst = 0.0
    for dr in (0, 1):
        for dc in (0, 1):
            u2, v2 = e[k + dc : n + dc][None, :], e[k + dr : n + dr][:, None]
            cx, cy, cz = u * v2 - v * u2, v - v2, u2 - u
            ang = np.arctan2(np.sqrt(cx * cx + cy * cy + cz * cz), 1.0 + u * u2 + v * v2)
            worst = max(worst, float(ang.max()))
    return worst


@functools.lru_cache(maxsize=32)
def _texel_directions_cached(n: int, convention: str, normalize: bool) -> np.ndarray:
    u, v = face_plane_grid(n)
    frames = face_frames(convention)
    d = np.empty((6, n, n, 3))
    for k in range(6):  # face by face (≈ 7× faster than one (6, n, n, 3, 3) gather at 256²; the same numbers)
        _plane_directions(frames[k], u, v, normalize, out=d[k])
    d.setflags(write=False)
    return d


def _check_grid(n, per_texel_bytes: int, what: str) -> int:
    """:func:`check_face_size`, and the grid of ``per_texel_bytes`` per texel must fit in memory (SizeError)."""

    n = check_face_size(n)
    check_allocation(per_texel_bytes * n * n, f"the {what} of {n}x{n} faces", "face size")
    return n


def texel_directions(n: int, convention: str = "openexr", normalize: bool = True) -> np.ndarray:
    """Directions of the centres of every texel of a cube map.

    Parameters
    ----------
    n : int
        Face size.
    convention : {"openexr", "opengl"}
    normalize : bool
        Unit vectors (default) or the points on the cube's surface.

    Returns
    -------
    ndarray, float64, shape (6, n, n, 3)
        ``[face, row, col]``; read-only and cached (copy it to change it).

    Raises
    ------
    SizeError
        ``n`` not a positive integer, or the array would not fit in memory.

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.environment.envmap import texel_directions
    >>> d = texel_directions(4)
    >>> d.shape
    (6, 4, 4, 3)
    >>> d[4, 1, 2]  # +Z face, row 1, column 2: up (+Y) and to the left (−X)
    array([-0.2357,  0.2357,  0.9428])
    >>> bool(np.allclose(np.linalg.norm(d, axis=-1), 1.0))
    True
    """
    return _texel_directions_cached(_check_grid(n, 6 * 3 * 8 * 3, "texel directions"), convention, bool(normalize))


def direction_to_texel_coords(d, n: int, convention: str = "openexr"):
    """Face and continuous texel coordinates of directions.

    Parameters
    ----------
    d : array_like, shape (..., 3)
        Directions, need not be normalised.
    n : int
        Face size.
    convention : {"openexr", "opengl"}

    Returns
    -------
    face : int array, shape (...)
    x, y : float64 arrays, shape (...)
        Column and row in [−½, n−½]; integers are texel centres.
    """
    face, u, v = direction_to_face_uv(d, convention)
    x, y = uv_to_texel_coords(u, v, n)
    return face, x, y


def direction_to_texel(d, n: int, convention: str = "openexr"):
    """Face, row and column of the texel containing each direction (nearest-texel addressing).

    Parameters
    ----------
    d : array_like, shape (..., 3)
        Directions, need not be normalised.
    n : int
        Face size.
    convention : {"openexr", "opengl"}

    Returns
    -------
    face, row, col : int arrays, shape (...)

    Examples
    --------
    +X lies on face 0, −Y on face 3, both at the centre of their face:

    >>> from ibl_ref.environment.envmap import direction_to_texel
    >>> face, row, col = direction_to_texel([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], 8)
    >>> face.tolist(), row.tolist(), col.tolist()
    ([0, 3], [4, 4], [4, 4])
    """
    face, x, y = direction_to_texel_coords(d, n, convention)
    col = np.clip(np.floor(x + 0.5), 0, n - 1).astype(np.intp)
    row = np.clip(np.floor(y + 0.5), 0, n - 1).astype(np.intp)
    return face, row, col


# ----------------------------------------------------------------------------------------------
# exact solid angles
# ----------------------------------------------------------------------------------------------
def area_primitive(x, y):
    """A(x, y) = atan2(x·y, √(x² + y² + 1)): solid angle (sr) of the rectangle [0,x]×[0,y] of the plane at
    distance 1 seen from the origin (signed: odd in x and in y).

    Every exact solid angle of the package is a sum of four of these (:func:`rect_solid_angle`).

    Parameters
    ----------
    x, y : float or array_like
        Plane coordinates (arrays broadcast).

    Returns
    -------
    float64 or ndarray
        Steradians; ``A(1, 1) = π/6``, a quarter of one face.
    """
    return np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))


def rect_solid_angle(u0, u1, v0, v1):
    """Exact solid angle (sr) of the face-plane rectangle [u0, u1] × [v0, v1] (any face).

    Parameters
    ----------
    u0, u1, v0, v1 : float or array_like
        The rectangle's edges in face-plane coordinates (arrays broadcast).

    Returns
    -------
    float64 or ndarray
        Steradians.

    Examples
    --------
    One whole face is a sixth of the sphere:

    >>> import numpy as np
    >>> from ibl_ref.environment.envmap import rect_solid_angle
    >>> float(rect_solid_angle(-1.0, 1.0, -1.0, 1.0) / np.pi)
    0.6667
    """
    return area_primitive(u1, v1) - area_primitive(u0, v1) - area_primitive(u1, v0) + area_primitive(u0, v0)


@functools.lru_cache(maxsize=32)
def _texel_solid_angles_cached(n: int) -> np.ndarray:
    e = np.linspace(-1.0, 1.0, n + 1)  # texel edges in the face plane
    # exact edges: linspace gives ±1 exactly at the ends and symmetric interior points
    a = area_primitive(e[None, :], e[:, None])  # [row_edge, col_edge]
    omega = a[1:, 1:] - a[1:, :-1] - a[:-1, 1:] + a[:-1, :-1]
    omega.setflags(write=False)
    return omega


def texel_solid_angles(n: int) -> np.ndarray:
    """Exact solid angle (sr) of every texel of one face.

    The same for all six faces and both conventions.  Σ over 6 faces = 4π to rounding (the sum
    telescopes to 6 · 4 · atan2(1, √3) = 4π).

    Parameters
    ----------
    n : int
        Face size.

    Returns
    -------
    ndarray, float64, shape (n, n)
        ``[row, col]``, read-only and cached.

    Raises
    ------
    SizeError
        ``n`` not a positive integer, or the array would not fit in memory.

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.environment.envmap import texel_solid_angles
    >>> om = texel_solid_angles(4)
    >>> float(6 * om.sum() / np.pi)  # the six faces cover the sphere, 4π sr
    4.0
    >>> float(om.max() / om.min())  # a centre texel against a corner texel
    2.472
    """
    return _texel_solid_angles_cached(_check_grid(n, 8 * 4, "texel solid angles"))


def cube_solid_angles(n: int) -> np.ndarray:
    """Exact texel solid angles of a whole cube map (a read-only broadcast view of :func:`texel_solid_angles`).

    Parameters
    ----------
    n : int
        Face size.

    Returns
    -------
    ndarray, float64, shape (6, n, n)
    """
    om = texel_solid_angles(n)
    return np.broadcast_to(om, (6,) + om.shape)


def convert_convention(cube: np.ndarray, src: str, dst: str) -> np.ndarray:
    """Re-orient the faces of a cube map from convention ``src`` to ``dst``.

    The result holds, at every texel of the ``dst`` layout, the radiance of the same direction.

    Parameters
    ----------
    cube : array_like, shape (6, N, N) or (6, N, N, C)
    src, dst : {"openexr", "opengl"}

    Returns
    -------
    ndarray
        A copy, shaped as ``cube``.

    Raises
    ------
    LayoutError
        A wrong shape or an unknown convention.

    Examples
    --------
    Each texel keeps its direction: the value of the texel containing a direction is the same in both layouts.

    >>> import numpy as np
    >>> from ibl_ref.environment.envmap import convert_convention, direction_to_texel
    >>> cube = np.arange(6 * 4 * 4, dtype=float).reshape(6, 4, 4)
    >>> gl = convert_convention(cube, "openexr", "opengl")
    >>> d = [0.2, 0.9, -0.3]
    >>> float(cube[direction_to_texel(d, 4)]), float(gl[direction_to_texel(d, 4, "opengl")])
    (42.0, 42.0)
    """
    check_cube_shape(cube)
    face_frames(src), face_frames(dst)
    if src == dst:
        return np.array(cube, copy=True)
    out = np.array(cube, copy=True)
    # openexr <-> opengl: side faces flip horizontally, ±Y flip vertically (an involution).
    for f in (0, 1, 4, 5):
        out[f] = cube[f][:, ::-1]
    for f in (2, 3):
        out[f] = cube[f][::-1, :]
    return out


def check_cube_shape(cube, name: str = "cube map") -> int:
    """The face size of a cube map after checking its layout (no value is read).

    Parameters
    ----------
    cube : array_like
        Expected shape (6, N, N) or (6, N, N, C).
    name : str, optional
        What the array is called in the error message.

    Returns
    -------
    int
        N.

    Raises
    ------
    LayoutError
        Any other shape (one line, naming ``name`` and the shape).
    """
    shape = np.shape(cube)
    if len(shape) not in (3, 4) or shape[0] != 6 or shape[1] != shape[2] or shape[1] < 1:
        raise LayoutError(f"{name}: expected an array of shape (6, N, N) or (6, N, N, C), got {shape}")
    return int(shape[1])


# ----------------------------------------------------------------------------------------------
# MIP pyramid description
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MipLevel:
    """One level of a cube-map MIP pyramid.

    Attributes
    ----------
    level : int
        0 is the full-resolution input.
    face_size : int
        N / 2**level (for a power-of-two N).
    texel_angle : float
        Angular width (rad) of a texel at the face centre, 2·atan(1/face_size).
    mean_texel_solid_angle : float
        4π / (6 · face_size²) sr.
    """

    level: int
    face_size: int
    texel_angle: float
    mean_texel_solid_angle: float

    def directions(self, convention: str = "openexr") -> np.ndarray:
        """:func:`texel_directions` of this level."""
        return texel_directions(self.face_size, convention)

    def solid_angles(self) -> np.ndarray:
        """:func:`texel_solid_angles` of this level."""
        return texel_solid_angles(self.face_size)


def mip_levels(n: int) -> list[MipLevel]:
    """The levels N, N/2, …, 1 of a cube-map pyramid.

    Parameters
    ----------
    n : int
        Face size of level 0, a power of two.

    Returns
    -------
    list of MipLevel

    Raises
    ------
    LayoutError
        ``n`` is not a power of two.

    Examples
    --------
    >>> from ibl_ref.environment.envmap import mip_levels
    >>> [level.face_size for level in mip_levels(8)]
    [8, 4, 2, 1]
    """
    n = check_face_size(n)
    if n & (n - 1):
        raise LayoutError(f"MIP pyramids need a power-of-two face size, got {n}")
    out = []
    lvl, m = 0, n
    while True:
        out.append(MipLevel(lvl, m, float(2.0 * np.arctan(1.0 / m)), 4.0 * np.pi / (6.0 * m * m)))
        if m == 1:
            break
        m //= 2
        lvl += 1
    return out


# ----------------------------------------------------------------------------------------------
# latitude-longitude maps (OpenEXR LatLongMap)
# ----------------------------------------------------------------------------------------------
def _check_latlong_size(h, w):
    h = check_face_size(h)
    w = check_face_size(w)
    if w != 2 * h:
        raise LayoutError(f"lat-long maps must be 2H x H (width = 2 x height), got {w} x {h}")
    return h, w


def latlong_angles(h: int, w: int):
    """Latitude (per row) and longitude (per column) of the texel centres of a lat-long map.

    Parameters
    ----------
    h, w : int
        Height and width, ``w = 2h``.

    Returns
    -------
    lat : ndarray, float64, shape (h,)
        Radians, from near +π/2 (top row) down.
    lon : ndarray, float64, shape (w,)
        Radians, from near +π (left column) down.

    Raises
    ------
    LayoutError
        ``w ≠ 2h``.
    """
    h, w = _check_latlong_size(h, w)
    lat = np.pi / 2 - np.pi * (np.arange(h) + 0.5) / h
    lon = np.pi - 2 * np.pi * (np.arange(w) + 0.5) / w
    return lat, lon


def latlong_directions(h: int, w: int) -> np.ndarray:
    """Unit directions of the texel centres of a lat-long map.

    Parameters
    ----------
    h, w : int
        Height and width, ``w = 2h``.

    Returns
    -------
    ndarray, float64, shape (h, w, 3)

    Raises
    ------
    LayoutError
        ``w ≠ 2h``.
    """
    lat, lon = latlong_angles(h, w)
    cl = np.cos(lat)[:, None]
    return np.stack(
        [np.sin(lon)[None, :] * cl, np.broadcast_to(np.sin(lat)[:, None], (h, w)), np.cos(lon)[None, :] * cl], axis=-1
    )


def latlong_solid_angles(h: int, w: int) -> np.ndarray:
    """Exact solid angle (sr) of every lat-long texel.

    A row between latitudes φ0 < φ1 and a column of width Δλ subtends Δλ·(sin φ1 − sin φ0).

    Parameters
    ----------
    h, w : int
        Height and width, ``w = 2h``.

    Returns
    -------
    ndarray, float64, shape (h, 1)
        Constant along a row (broadcasts against an (h, w) image).

    Raises
    ------
    LayoutError
        ``w ≠ 2h``.

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.environment.envmap import latlong_solid_angles
    >>> om = latlong_solid_angles(4, 8)
    >>> om.shape, float(8 * om.sum() / np.pi)
    ((4, 1), 4.0)
    """
    h, w = _check_latlong_size(h, w)
    edges = np.pi / 2 - np.pi * np.arange(h + 1) / h
    s = np.sin(edges)
    return ((s[:-1] - s[1:]) * (2 * np.pi / w))[:, None]


def direction_to_latlong(d, h: int, w: int):
    """Continuous lat-long texel coordinates of directions (texel centres on integers).

    Parameters
    ----------
    d : array_like, shape (..., 3)
        Directions, need not be normalised.
    h, w : int
        Height and width of the map, ``w = 2h``.

    Returns
    -------
    x, y : float64 arrays, shape (...)
        Column x ∈ [−½, w−½) (wraps around in longitude) and row y ∈ [−½, h−½].

    Examples
    --------
    +Z is longitude 0 on the equator, the middle of the map:

    >>> from ibl_ref.environment.envmap import direction_to_latlong
    >>> x, y = direction_to_latlong([0.0, 0.0, 1.0], 4, 8)
    >>> float(x), float(y)
    (3.5, 1.5)
    """
    h, w = _check_latlong_size(h, w)
    d = as_directions(d)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    lat = np.arcsin(np.clip(d[..., 1], -1.0, 1.0))
    lon = np.arctan2(d[..., 0], d[..., 2])
    x = (np.pi - lon) / (2 * np.pi) * w - 0.5
    y = (np.pi / 2 - lat) / np.pi * h - 0.5
    return x, y
