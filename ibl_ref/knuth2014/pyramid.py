"""Knuth et al. (2014) filter pyramid: alternating 2×2 shrink and 5×5 low-pass filter (Sec. 3.2, Fig. 2).

Level 0 is the input (the mirror, g = 1, s_Phong = ∞).  Every next level halves the face size with the
classical 2×2 mean of MIP mapping and applies a 5×5 separable filter (:mod:`ibl_ref.knuth2014.filters`), down to
1×1 faces (the diffuse end, s_Phong = 1).  The paper (Fig. 2) says the two operations alternate but not
which comes first, so both orders are offered:

``shrink_then_filter`` (default)
    level_{i+1} = F(S(level_i)).  The filter runs at the *new* level's resolution, so every level,
    including the last 1×1 one, is filtered; it is 4× cheaper than filtering before the shrink; and
    level 1 already differs from a plain MIP level (the filter shapes every stored level, which is what
    Fig. 2's caption describes: "the additional filter we introduce in between allows us to shape the
    result").
``filter_then_shrink``
    level_{i+1} = S(F(level_i)).  The filter acts on the finer level (a pre-filter for the decimation).

``kernel="none"`` gives the plain 2×2-mean MIP chain (the baseline "MIP map only" of Fig. 4/5) for both
orders.

Energy
------
∫L dω of a level is Σ L·Ω with exact texel solid angles (:func:`ibl_ref.environment.envmap.texel_solid_angles`).
The 2×2 mean is *not* solid-angle weighted (a parent texel's Ω is the sum of its four children's, but
the children enter with weight ¼ each although near the face corners their Ω differ), and the filters
are normalised in texel space, not in solid angle; so the energy drifts a little from level to level.
:func:`pyramid_energy` measures it instead of assuming zero.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..environment.envmap import check_cube_shape, texel_solid_angles
from ..environment.validated import as_environment
from ..errors import IBLError, LayoutError
from .filters import check_seam, filter_cube, kernel_taps
from ..environment import envmap
from ..environment.sampling import sample_nearest

__all__ = ["ORDERS", "SHRINKS", "Pyramid", "shrink_2x2", "shrink_2x2_solid_angle", "build_pyramid", "build_mip_chain", "pyramid_energy"]

ORDERS = ("shrink_then_filter", "filter_then_shrink")
SHRINKS = ("mean", "solid_angle")


@dataclass
class Pyramid:
    """A filter pyramid.

    Attributes
    ----------
    levels : list of arrays (6, n, n, C)
        ``levels[0]`` is the input (n = base_size), ``levels[i]`` has n = base_size / 2**i, the last n = 1.
    kernel : str
        Filter name (or ``"custom"`` for explicit taps).
    order : str
        One of :data:`ORDERS`.
    seam : str
        One of :data:`ibl_ref.knuth2014.filters.SEAM_MODES`.
    base_size : int
        Face size of level 0.
    shrink : str
        One of :data:`SHRINKS`.
    """

    levels: list
    kernel: str
    order: str
    seam: str
    base_size: int
    shrink: str = "mean"
    _samplers: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def n_levels(self) -> int:
        return len(self.levels)

    @property
    def max_level(self) -> int:
        return len(self.levels) - 1

    def sampler(self, level: int):
        """Cached seam-aware sampler of one level (``.bilinear(dirs)``, ``.nearest(dirs)``).

        :class:`ibl_ref.environment.sampling.CubeSampler` for faces of size ≥ 2; for the 1×1 level
        :class:`FaceCentreSampler` (the shared sampler pads by 2 texels, impossible on 1×1 faces).
        """
        s = self._samplers.get(level)
        if s is None:
            if self.levels[level].shape[1] == 1:
                s = FaceCentreSampler(self.levels[level])
            else:
                from ..environment.sampling import CubeSampler

                s = CubeSampler(self.levels[level])
            self._samplers[level] = s
        return s


class FaceCentreSampler:
    """Seam-aware bilinear lookup in a cube map with 1×1 faces (private; :mod:`ibl_ref.environment.sampling` pads by 2
    texels, impossible on 1×1 faces).

    Same rule as :class:`ibl_ref.environment.sampling.CubeSampler` in its half-texel edge band, which on a 1×1 face is
    the whole face: with texel coordinates x, y ∈ [−½, ½] (centre 0) and f_x = |x|, f_y = |y|, the
    face's own value has weight (1−f_x)(1−f_y) + c, the neighbour across the nearer u edge
    f_x(1−f_y) + c, the neighbour across the nearer v edge (1−f_x)f_y + c, with c = f_x f_y / 3 (the
    missing fourth face's weight shared equally).  This is what seamless hardware bilinear filtering does
    (a tent in face-plane coordinates): the face value at its centre, the ½/½ mean on an edge, ⅓/⅓/⅓ at
    a corner, continuous everywhere.
    """

    def __init__(self, cube):
        self.cube = np.asarray(cube)
        if self.cube.shape[1:3] != (1, 1):
            raise LayoutError("FaceCentreSampler needs 1x1 faces")

    def bilinear(self, dirs):

        d = np.asarray(dirs, dtype=np.float64)
        shape = d.shape[:-1]
        d = d.reshape(-1, 3)
        face, x, y = envmap.direction_to_texel_coords(d, 1)
        frames = envmap.face_frames("openexr")
        fx, fy = np.abs(x), np.abs(y)
        side_u = np.where(x < 0, -1.0, 1.0)[:, None] * frames[face, 1, :]
        side_v = np.where(y < 0, -1.0, 1.0)[:, None] * frames[face, 2, :]
        face_b, _, _ = envmap.direction_to_face_uv(side_u)
        face_c, _, _ = envmap.direction_to_face_uv(side_v)
        c = fx * fy / 3.0
        v = self.cube[:, 0, 0].reshape(6, -1).astype(np.float64)
        out = (((1 - fx) * (1 - fy) + c)[:, None] * v[face] + (fx * (1 - fy) + c)[:, None] * v[face_b]
               + ((1 - fx) * fy + c)[:, None] * v[face_c])
        out = out.reshape(shape + self.cube.shape[3:])
        return out.astype(np.result_type(self.cube.dtype, np.float32), copy=False)

    def nearest(self, dirs):

        return sample_nearest(self.cube, dirs)


def shrink_2x2(cube: np.ndarray) -> np.ndarray:
    """Classical 2×2 mean (MIP decimation) of every face.

    Parameters
    ----------
    cube : array_like, shape (6, N, N[, ...])
        N even.

    Returns
    -------
    ndarray, shape (6, N/2, N/2[, ...])

    Raises
    ------
    LayoutError
        A wrong shape or an odd N.
    """
    n = check_cube_shape(cube)
    if n % 2:
        raise LayoutError(f"2x2 shrink needs an even face size, got {n}")
    a = np.asarray(cube)
    # four strided reads: faster than reshape(...).mean(axis=(2, 4)) and exact in the same way
    out = a[:, 0::2, 0::2] + a[:, 1::2, 0::2]
    out += a[:, 0::2, 1::2]
    out += a[:, 1::2, 1::2]
    out *= a.dtype.type(0.25) if np.issubdtype(a.dtype, np.floating) else 0.25
    return out


def shrink_2x2_solid_angle(cube: np.ndarray) -> np.ndarray:
    """Solid-angle-weighted 2×2 shrink: parent = Σ Ω_c L_c / Ω_parent (conserves ∫L dω exactly).

    Not in the paper (which uses "the classical 2×2 pixel mean"); offered to quantify the energy drift
    of the plain mean (:func:`pyramid_energy`).

    Parameters
    ----------
    cube : array_like, shape (6, N, N[, ...])
        N even.

    Returns
    -------
    ndarray, shape (6, N/2, N/2[, ...])

    Raises
    ------
    LayoutError
        A wrong shape or an odd N.
    """
    n = check_cube_shape(cube)
    if n % 2:
        raise LayoutError(f"2x2 shrink needs an even face size, got {n}")
    a = np.asarray(cube)
    om = texel_solid_angles(n).astype(a.dtype if np.issubdtype(a.dtype, np.floating) else np.float64)
    om = om.reshape(om.shape + (1,) * (a.ndim - 3))
    w = a * om
    out = w[:, 0::2, 0::2] + w[:, 1::2, 0::2] + w[:, 0::2, 1::2] + w[:, 1::2, 1::2]
    parent = om[0::2, 0::2] + om[1::2, 0::2] + om[0::2, 1::2] + om[1::2, 1::2]  # = Ω_parent (additive)
    return out / parent


def _check_input(cube, dtype):
    """``(N, radiance (6, N, N, C) in the working dtype)``: the layout, a power-of-two N, the radiance (once, unless
    ``cube`` is an :class:`~ibl_ref.environment.validated.Environment`); the default dtype is the input's."""
    n = check_cube_shape(cube)
    if n & (n - 1):
        raise LayoutError(
            f"filter pyramids support power-of-two face sizes only (1, 2, 4, ..., 512, ...); got {n}. "
            "Resample the map first (e.g. ibl_ref.environment.resample)."
        )
    if dtype is None:
        dtype = getattr(cube, "dtype", None)
    env = as_environment(cube, "environment map")
    dtype = dtype if dtype is not None and np.issubdtype(dtype, np.floating) else np.float64
    return n, env.data.astype(dtype, copy=False)


def build_pyramid(cube, kernel="sqrtcos", order: str = "shrink_then_filter", seam: str = "neighbour",
                  dtype=None, shrink: str = "mean") -> Pyramid:
    """Build the filter pyramid of Fig. 2.

    Parameters
    ----------
    cube : Environment or array_like, shape (6, N, N) or (6, N, N, C)
        Radiance, finite and non-negative; N a power of two.  Checked once unless it is a validated
        :class:`~ibl_ref.environment.validated.Environment`.
    kernel : str or 5 taps
        ``none, box, gauss, cos, sqrtcos`` or ``cos^k`` (:mod:`ibl_ref.knuth2014.filters`).
    order : {"shrink_then_filter", "filter_then_shrink"}
        See module docstring.
    seam : {"neighbour", "clamp", "neighbour_repad"}
    dtype : numpy dtype, optional
        Working/storage dtype (default: the input's float dtype, float64 for integers).
    shrink : {"mean", "solid_angle"}
        ``mean``: the paper's classical 2×2 mean (default); ``solid_angle``: Ω-weighted mean
        (:func:`shrink_2x2_solid_angle`, energy-exact shrink).

    Returns
    -------
    Pyramid
        ``levels[0]`` is a copy of the input (always 4-D: a trailing channel axis is added to 3-D input).

    Raises
    ------
    LayoutError
        A wrong shape or a face size that is no power of two.
    RadianceError
        NaN/Inf/negative radiance.
    IBLError
        An unknown kernel, order, seam mode or shrink.

    Examples
    --------
    The filters are normalised, so a constant map stays constant on every level and every glossiness looks it
    up exactly; the face size halves down to 1:

    >>> from ibl_ref.knuth2014.gloss_lookup import lookup
    >>> from ibl_ref.knuth2014.pyramid import build_pyramid
    >>> from ibl_ref.synthetic.synthetic_envs import make_environment
    >>> pyr = build_pyramid(make_environment("constant", 16, value=2.0))
    >>> [level.shape[1] for level in pyr.levels]
    [16, 8, 4, 2, 1]
    >>> lookup(pyr, [[0.0, 1.0, 0.0], [1.0, 1.0, 1.0]], 0.9)
    array([[2., 2., 2.],
           [2., 2., 2.]])
    """
    taps = kernel_taps(kernel)
    if order not in ORDERS:
        raise IBLError(f"unknown pyramid order {order!r}; choose one of {', '.join(ORDERS)}")
    check_seam(seam)
    if shrink not in SHRINKS:
        raise IBLError(f"unknown shrink {shrink!r}; choose one of {', '.join(SHRINKS)}")
    n, a = _check_input(cube, dtype)
    kname = kernel if isinstance(kernel, str) else "custom"
    levels = [a.copy()]
    cur = levels[0]
    plain = np.array_equal(taps, kernel_taps("none"))
    shr = shrink_2x2 if shrink == "mean" else shrink_2x2_solid_angle
    while cur.shape[1] > 1:
        if plain:
            cur = shr(cur)
        elif order == "shrink_then_filter":
            cur = filter_cube(shr(cur), taps, seam)
        else:
            cur = shr(filter_cube(cur, taps, seam))
        levels.append(cur)
    return Pyramid(levels=levels, kernel=kname, order=order, seam=seam, base_size=n, shrink=shrink)


def build_mip_chain(cube, dtype=None) -> Pyramid:
    """Plain 2×2-mean MIP chain (the baseline; same as ``build_pyramid(cube, kernel="none")``).

    Parameters
    ----------
    cube : Environment or array_like, shape (6, N, N[, C])
    dtype : numpy dtype, optional

    Returns
    -------
    Pyramid
    """
    return build_pyramid(cube, kernel="none", dtype=dtype)


def pyramid_energy(pyr: Pyramid) -> list[dict]:
    """∫L dω = Σ L·Ω (exact solid angles) of every level, and its drift relative to level 0.

    Parameters
    ----------
    pyr : Pyramid

    Returns
    -------
    list of dict
        One per level: ``level``, ``face_size``, ``energy`` (tuple per channel, radiance×sr), ``rel_drift`` (per
        channel, (E_level − E_0)/E_0; NaN-free: 0 where E_0 = 0 and E_level = 0), ``rel_drift_step`` (relative to
        the previous level).
    """
    rows = []
    e0 = prev = None
    for i, lev in enumerate(pyr.levels):
        n = lev.shape[1]
        omega = texel_solid_angles(n)
        e = np.einsum("fijc,ij->c", lev.astype(np.float64), omega)
        if e0 is None:
            e0 = prev = e
        rows.append({
            "level": i,
            "face_size": n,
            "energy": tuple(float(x) for x in e),
            "rel_drift": tuple(float(x) for x in _rel(e, e0)),
            "rel_drift_step": tuple(float(x) for x in _rel(e, prev)),
        })
        prev = e
    return rows


def _rel(e, ref):
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(ref != 0, (e - ref) / np.where(ref != 0, ref, 1.0), np.where(e == 0, 0.0, np.inf))
    return r
