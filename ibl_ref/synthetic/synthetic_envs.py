"""Deterministic synthetic environment maps with known answers.

Test inputs for the whole lab (Knuth et al. 2014, Sec. 3.2 Eq. 4 and Sec. 5 Fig. 4/5 use "a black
environment map with one white pixel"; the median-cut / PEM stages need suns and area lights).
Every generator returns a cube map in the conventions of :mod:`ibl_ref.environment.envmap`: shape ``(6, n, n, 3)``,
float64, faces ``+X,-X,+Y,-Y,+Z,-Z`` in OpenEXR orientation, +Y up, linear radiance (arbitrary units).
No generator uses random numbers, so every output is bit-for-bit reproducible.

Generators (``make_env(name, n, **params)``):

``constant``   L ≡ ``value`` (per channel).

``delta``      one lit texel (``texel=(face,row,col)`` or ``direction``); ``normalize=True`` makes
               ∫L dω = ``radiance`` exactly (value = radiance / Ω_texel).

``gradient``   L(ω) = a + b·ω, stored as the **exact texel average** (closed form, see
               :func:`texel_mean_directions`) or at texel centres (``sample="center"``).
               :func:`gradient_lobe_average` is the closed-form normalised Phong lobe average.

``sky_sun``    smooth sky (zenith→horizon blend, darker ground) plus a sun disc (spherical cap of
               ``sun_solid_angle`` sr, ``sun_radiance``) whose texel coverage is supersampled with exact
               sub-texel solid angles; :func:`sun_coverage_relative_error` reports the achieved error.

``studio``     dark room with rectangular area lights (gnomonic rectangles: exact solid angle
               :func:`rect_light_solid_angle`), coverage supersampled.

``checker``    two-level checkerboard, either in latitude/longitude cells (supersampled texel
               average) or in face-texel blocks (exact).

Coverage supersampling: a texel is split into ``k × k`` sub-cells of its face-plane square; each
sub-cell's solid angle is exact (the ``A(x, y) = atan2(xy, √(x²+y²+1))`` primitive of
``envmap``/docs/background.md §2, re-implemented privately here as :func:`_subcell_solid_angles` for local
sub-grids) and the indicator is evaluated at the sub-cell centre; the coverage fraction is
Σ Ω_sub·1[inside] / Ω_texel.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import json
import os
from pathlib import Path

import numpy as np

from ..environment import envmap
from ..environment.radiance_policy import apply_policy
from ..environment.validated import adopt
from ..errors import IBLError
from ..atomic import atomic_path

__all__ = [
    "ENV_NAMES",
    "SCENE_ENV_NAMES",
    "scene_environment",
    "GENERATOR_VERSION",
    "DEFAULT_SUN_DIRECTION",
    "SUN_NEAR_CORNER",
    "SUN_SOLID_ANGLE",
    "make_env",
    "make_environment",
    "env_constant",
    "env_delta",
    "env_gradient",
    "env_sky_sun",
    "env_studio",
    "env_checker",
    "texel_mean_directions",
    "gradient_lobe_average",
    "sun_disc_coverage",
    "sun_coverage_relative_error",
    "rect_light_solid_angle",
    "rect_light_coverage",
    "DEFAULT_STUDIO_LIGHTS",
    "cached_env",
    "cache_dir",
    "generator_help",
]

#: bump when a generator's output changes (invalidates :func:`cached_env` files)
GENERATOR_VERSION = 1


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


#: solid angle of the real sun seen from Earth, π·(0.2666°)² ≈ 6.8e-5 sr
SUN_SOLID_ANGLE = 6.8e-5
#: default sun: elevation 45°, azimuth 30° from +Z towards +X
DEFAULT_SUN_DIRECTION = _unit(
    [np.cos(np.pi / 4) * np.sin(np.pi / 6), np.sin(np.pi / 4), np.cos(np.pi / 4) * np.cos(np.pi / 6)]
)
#: 0.00125 rad from the cube corner (1,1,1)/√3 (elevation 35.3°): a real-size sun disc (radius
#: 0.00465 rad) straddles the +X, +Y and +Z faces
SUN_NEAR_CORNER = _unit([1.0, 1.002, 0.999])


# ----------------------------------------------------------------------------------------------
# parameter helpers
# ----------------------------------------------------------------------------------------------
def _rgb(value, name: str, allow_zero: bool = True) -> np.ndarray:
    """Scalar or length-1/3 sequence → (3,) float64, finite and ≥ 0."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise IBLError(f"{name}: expected a number or 3 numbers (RGB), got {value!r}") from None
    if a.ndim == 0:
        a = np.full(3, float(a))
    elif a.shape == (1,):
        a = np.full(3, float(a[0]))
    elif a.shape != (3,):
        raise IBLError(f"{name}: expected a number or 3 numbers (RGB), got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise IBLError(f"{name}: values must be finite, got {a.tolist()}")
    if np.any(a < 0):
        raise IBLError(f"{name}: radiance must be non-negative, got {a.tolist()}")
    if not allow_zero and np.all(a == 0):
        raise IBLError(f"{name}: must not be zero")
    return a


def _direction(value, name: str) -> np.ndarray:
    try:
        d = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise IBLError(f"{name}: expected 3 numbers (a direction), got {value!r}") from None
    if d.shape != (3,) or not np.all(np.isfinite(d)):
        raise IBLError(f"{name}: expected 3 finite numbers (a direction), got {value!r}")
    nrm = np.linalg.norm(d)
    if nrm == 0:
        raise IBLError(f"{name}: zero-length direction")
    return d / nrm


def _positive(value, name: str, upper: float | None = None) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise IBLError(f"{name}: expected a number, got {value!r}") from None
    if not np.isfinite(x) or x <= 0 or (upper is not None and x > upper):
        rng = f"(0, {upper}]" if upper is not None else "(0, inf)"
        raise IBLError(f"{name}: must be in {rng}, got {value!r}")
    return x


def _int_param(value, name: str, lo: int, hi: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        else:
            raise IBLError(f"{name}: expected an integer, got {value!r}")
    value = int(value)
    if value < lo or (hi is not None and value > hi):
        raise IBLError(f"{name}: must be in [{lo}, {hi if hi is not None else 'inf'}], got {value}")
    return value


def _face_size(n) -> int:
    return _int_param(n, "n (face size)", 1, 8192)


def _fill(n: int, rgb: np.ndarray) -> np.ndarray:
    return np.broadcast_to(rgb, (6, n, n, 3)).astype(np.float64, copy=True)


# ----------------------------------------------------------------------------------------------
# exact geometry helpers
# ----------------------------------------------------------------------------------------------
def _subcell_solid_angles(x0, y0, x1, y1, k: int):
    """Exact solid angles and centre (x, y) of the k×k sub-cells of face-plane rectangles.

    ``x0..x1, y0..y1`` have shape (T,); returns ``omega`` (T, k, k) [row=y, col=x] and centre
    coordinates ``xc, yc`` (T, k, k).
    """
    t = np.linspace(0.0, 1.0, k + 1)
    xe = x0[:, None] + (x1 - x0)[:, None] * t[None, :]  # (T, k+1)
    ye = y0[:, None] + (y1 - y0)[:, None] * t[None, :]
    a = envmap.area_primitive(xe[:, None, :], ye[:, :, None])  # (T, k+1 [y], k+1 [x])
    omega = a[:, 1:, 1:] - a[:, 1:, :-1] - a[:, :-1, 1:] + a[:, :-1, :-1]
    xc = 0.5 * (xe[:, 1:] + xe[:, :-1])
    yc = 0.5 * (ye[:, 1:] + ye[:, :-1])
    return omega, np.broadcast_to(xc[:, None, :], omega.shape), np.broadcast_to(yc[:, :, None], omega.shape)


def _coverage(n: int, faces, rows, cols, inside, k: int, max_samples: int = 2_000_000) -> np.ndarray:
    """Solid-angle-weighted fraction of each listed texel for which ``inside(dirs)`` is true.

    ``inside`` maps unit directions (..., 3) to a float array (...) (0/1 indicator or a value);
    returns the per-texel average (T,) = Σ Ω_sub·inside / Σ Ω_sub.  Processed in chunks.
    """
    faces, rows, cols = (np.asarray(a, dtype=np.intp).ravel() for a in (faces, rows, cols))
    out = np.empty(faces.shape, dtype=np.float64)
    chunk = max(1, max_samples // (k * k))
    for s in range(0, faces.size, chunk):
        f, r, c = faces[s : s + chunk], rows[s : s + chunk], cols[s : s + chunk]
        u0 = -1.0 + 2.0 * c / n
        v0 = -1.0 + 2.0 * r / n
        omega, uc, vc = _subcell_solid_angles(u0, v0, u0 + 2.0 / n, v0 + 2.0 / n, k)
        d = envmap.face_uv_to_direction(f[:, None, None], uc, vc)
        val = np.asarray(inside(d), dtype=np.float64)
        out[s : s + chunk] = np.einsum("tij,tij->t", omega, val) / omega.sum(axis=(1, 2))
    return out


def texel_mean_directions(n: int) -> np.ndarray:
    """Exact solid-angle average of the direction ω over every texel, ``∫_texel ω dω / Ω_texel``.

    Closed form (the "vector irradiance" of a spherical polygon; Arvo 1995, Stokes' theorem):
    for a spherical polygon with vertices v_1..v_m traversed counter-clockwise seen from outside,
    ``∫ ω dω = ½ Σ_i Θ_i · unit(v_i × v_{i+1})`` with Θ_i the arc length of edge i.  Texel edges are
    straight lines on the face plane, hence great-circle arcs on the sphere, so the formula is exact.
    Dividing by the exact texel solid angle (:func:`ibl_ref.environment.envmap.texel_solid_angles`) gives the mean.

    Parameters
    ----------
    n : int
        Face size.

    Returns
    -------
    ndarray, float64, shape (6, n, n, 3)
        Its norm is < 1 (≈ 1 − O(1/n²)): the mean of unit vectors over a texel.

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.synthetic.synthetic_envs import texel_mean_directions
    >>> norms = np.linalg.norm(texel_mean_directions(8), axis=-1)
    >>> bool(0.99 < norms.min() and norms.max() < 1.0)
    True
    """
    n = _face_size(n)
    e = np.linspace(-1.0, 1.0, n + 1)
    v_e, u_e = np.meshgrid(e, e, indexing="ij")  # [row edge, col edge]
    p = envmap.face_uv_to_direction(np.arange(6)[:, None, None], u_e[None], v_e[None])  # (6, n+1, n+1, 3)

    def arc(a, b):
        cr = np.cross(a, b)
        s = np.linalg.norm(cr, axis=-1, keepdims=True)
        theta = np.arctan2(s, np.sum(a * b, axis=-1, keepdims=True))
        return theta * cr / s  # Θ · unit(a × b)

    h = arc(p[:, :, :-1], p[:, :, 1:])  # (6, n+1, n, 3): edge (i, j) → (i, j+1)
    v = arc(p[:, :-1, :], p[:, 1:, :])  # (6, n, n+1, 3): edge (i, j) → (i+1, j)
    # loop (i,j) → (i,j+1) → (i+1,j+1) → (i+1,j) → (i,j)
    loop = h[:, :-1, :, :] + v[:, :, 1:, :] - h[:, 1:, :, :] - v[:, :, :-1, :]
    vec = 0.5 * loop
    centre = envmap.texel_directions(n)
    sign = np.sign(np.sum(vec * centre, axis=-1, keepdims=True))  # orientation of the loop per face
    return sign * vec / envmap.texel_solid_angles(n)[None, :, :, None]


# ----------------------------------------------------------------------------------------------
# generators
# ----------------------------------------------------------------------------------------------
def env_constant(n: int = 64, value=1.0) -> np.ndarray:
    """Constant environment L(ω) = ``value``.

    Parameters
    ----------
    n : int
        Face size.
    value : float or 3 floats
        Radiance per channel (≥ 0).  ∫L dω = 4π·value.

    Returns
    -------
    ndarray, float64, shape (6, n, n, 3)
        Radiance in the OpenEXR cube layout (:mod:`ibl_ref.environment.envmap`).
    """
    return _fill(_face_size(n), _rgb(value, "value"))


def env_delta(n: int = 64, texel=None, direction=None, radiance=1.0, normalize: bool = False) -> np.ndarray:
    """Black environment with exactly one lit texel (the paper's Fig. 4 probe: "one white pixel").

    Parameters
    ----------
    n : int
        Face size.
    texel : (face, row, col), optional
        The lit texel.  Default: the +Z face texel ``(4, n//2, n//2)``.
    direction : 3 floats, optional
        Alternative to ``texel``: light the texel containing this direction
        (:func:`ibl_ref.environment.envmap.direction_to_texel`).
    radiance : float or 3 floats
        Texel value, or with ``normalize=True`` the target ∫L dω.
    normalize : bool
        If True the texel value is ``radiance / Ω_texel`` (exact texel solid angle), so ∫L dω = radiance.

    Returns
    -------
    ndarray, float64, shape (6, n, n, 3)
        Radiance in the OpenEXR cube layout (:mod:`ibl_ref.environment.envmap`).

    Raises
    ------
    IBLError
        Both ``texel`` and ``direction``, or a texel outside the cube.
    """
    n = _face_size(n)
    rgb = _rgb(radiance, "radiance")
    if texel is not None and direction is not None:
        raise IBLError("delta: give either texel=(face,row,col) or direction, not both")
    if direction is not None:
        f, r, c = (int(x) for x in envmap.direction_to_texel(_direction(direction, "direction"), n))
    elif texel is not None:
        try:
            f, r, c = (int(x) for x in texel)
        except (TypeError, ValueError):
            raise IBLError(f"delta: texel must be (face, row, col), got {texel!r}") from None
        if not (0 <= f < 6 and 0 <= r < n and 0 <= c < n):
            raise IBLError(f"delta: texel {texel!r} outside a cube of face size {n}")
    else:
        f, r, c = 4, n // 2, n // 2
    cube = np.zeros((6, n, n, 3))
    cube[f, r, c] = rgb / envmap.texel_solid_angles(n)[r, c] if normalize else rgb
    return cube


def env_gradient(n: int = 64, a=1.0, b=(0.0, 0.5, 0.0), sample: str = "average") -> np.ndarray:
    """Linear environment L(ω) = a + b·ω (per channel), a first-order spherical-harmonic field.

    Parameters
    ----------
    n : int
        Face size.
    a : float or 3 floats
        Constant term per channel.
    b : 3 floats or (3, 3)
        Gradient vector (the same for all channels) or one 3-vector per channel (rows = R, G, B).
        Must satisfy |b_c| ≤ a_c so that L ≥ 0 everywhere.
    sample : {"average", "center"}
        ``"average"`` (default): exact texel average a + b·ω̄ with ω̄ from
        :func:`texel_mean_directions` (closed form, exact to rounding).  ``"center"``: value at the
        texel-centre direction (differs from the average by O(1/n²)).

    Returns
    -------
    ndarray, float64, shape (6, n, n, 3)
        Radiance in the OpenEXR cube layout (:mod:`ibl_ref.environment.envmap`).

    Raises
    ------
    IBLError
        A gradient longer than the constant term, |b_c| > a_c (negative radiance somewhere); an unknown
        ``sample``.

    Notes
    -----
    ∫L dω = 4π·a (the linear part integrates to zero); the normalised Phong lobe average has the
    closed form :func:`gradient_lobe_average`.
    """
    n = _face_size(n)
    a_rgb = _rgb(a, "a")
    b_arr = _gradient_b(b)
    if np.any(np.linalg.norm(b_arr, axis=1) > a_rgb * (1 + 1e-12)):
        raise IBLError(
            f"gradient: |b| must be ≤ a per channel so that a + b·ω ≥ 0; got |b| = "
            f"{np.linalg.norm(b_arr, axis=1).tolist()}, a = {a_rgb.tolist()}"
        )
    if sample == "average":
        w = texel_mean_directions(n)
    elif sample == "center":
        w = envmap.texel_directions(n)
    else:
        raise IBLError(f"gradient: sample must be 'average' or 'center', got {sample!r}")
    return np.maximum(a_rgb + np.einsum("fijk,ck->fijc", w, b_arr), 0.0)


def _gradient_b(b) -> np.ndarray:
    try:
        b_arr = np.asarray(b, dtype=np.float64)
    except (TypeError, ValueError):
        raise IBLError(f"gradient: b must be a 3-vector or a (3, 3) array, got {b!r}") from None
    if b_arr.shape == (3,):
        b_arr = np.broadcast_to(b_arr, (3, 3))
    if b_arr.shape != (3, 3) or not np.all(np.isfinite(b_arr)):
        raise IBLError(f"gradient: b must be a finite 3-vector or (3, 3) array (one row per channel), got {b!r}")
    return np.array(b_arr)


def gradient_lobe_average(r, s, a=1.0, b=(0.0, 0.5, 0.0)) -> np.ndarray:
    """Closed-form normalised Phong lobe average of the linear environment L(ω) = a + b·ω.

    ``∫ L(ω) max(r·ω, 0)^s dω / ∫ max(r·ω, 0)^s dω = a + (b·r)·(s+1)/(s+2)``  (Knuth 2014 Eq. 4,
    normalised as in docs/background.md §2).

    Derivation: write ω = (r·ω) r + ω⊥.  Over the hemisphere around r the lobe weight cosˢθ depends only
    on θ = ∠(r, ω), so the ω⊥ part integrates to zero by rotational symmetry and
    ``∫ ω cosˢθ dω = r ∫ cos^{s+1}θ dω = r · 2π/(s+2)``, while ``∫ cosˢθ dω = 2π/(s+1)``.  Hence the
    average of ω under the lobe is r (s+1)/(s+2), and the average of a + b·ω is a + b·r (s+1)/(s+2).
    s = ∞ (mirror) gives a + b·r; s = 0 (uniform hemisphere) gives a + b·r/2.

    Parameters
    ----------
    r : array (..., 3)
        Lobe axes (normalised internally).
    s : float or array broadcastable to r.shape[:-1]
        Phong exponent(s) ≥ 0; ``np.inf`` allowed.
    a, b : float or 3 floats, 3 floats or (3, 3)
        As in :func:`env_gradient`.

    Returns
    -------
    ndarray, float64, shape (..., 3)
        One value per channel.

    Raises
    ------
    IBLError
        Non-finite or zero-length axes, a negative or NaN exponent.

    Examples
    --------
    Looking straight up the default gradient (b = 0.5 +Y) with s = 2: 1 + 0.5·3/4:

    >>> from ibl_ref.synthetic.synthetic_envs import gradient_lobe_average
    >>> gradient_lobe_average([0.0, 1.0, 0.0], 2.0)
    array([1.375, 1.375, 1.375])
    """
    a_rgb = _rgb(a, "a")
    b_arr = _gradient_b(b)
    r = np.asarray(r, dtype=np.float64)
    if r.shape[-1:] != (3,) or not np.all(np.isfinite(r)):
        raise IBLError(f"gradient_lobe_average: r must be finite directions (..., 3), got shape {r.shape}")
    nr = np.linalg.norm(r, axis=-1, keepdims=True)
    if np.any(nr == 0):
        raise IBLError("gradient_lobe_average: zero-length direction r")
    r = r / nr
    s = np.asarray(s, dtype=np.float64)
    if np.any(np.isnan(s)) or np.any(s < 0):
        raise IBLError("gradient_lobe_average: exponent s must be ≥ 0 (np.inf allowed)")
    factor = np.where(np.isinf(s), 1.0, (s + 1.0) / (np.where(np.isinf(s), 1.0, s) + 2.0))
    return a_rgb + np.asarray(factor)[..., None] * np.einsum("...k,ck->...c", r, b_arr)


# -------------------------------------------------------------------------- sky and sun
def _sun_cos_radius(sun_solid_angle: float) -> float:
    # spherical cap: Ω = 2π (1 − cos θ_s)
    return 1.0 - sun_solid_angle / (2.0 * np.pi)


def sun_disc_coverage(n: int, sun_direction=None, sun_solid_angle: float = SUN_SOLID_ANGLE, samples_across: int = 32,
                      max_subdivision: int = 256) -> np.ndarray:
    """Fraction of every texel covered by a sun disc (a spherical cap), shape (6, n, n).

    Texels whose centre lies within θ_s + 2/n rad of the sun direction (θ_s the cap radius; 2/n exceeds
    the angular half-diagonal √2/n of any texel) are split into k × k sub-cells with exact solid angles;
    k = clip(ceil(samples_across / (2θ_s·n/2)), 2, max_subdivision), i.e. about ``samples_across``
    sub-cells across the disc diameter at the face centre.  The achieved ∫cov dω vs Ω is reported by
    :func:`sun_coverage_relative_error`.

    Parameters
    ----------
    n : int
        Face size.
    sun_direction : 3 floats, optional
        Default :data:`DEFAULT_SUN_DIRECTION`.
    sun_solid_angle : float
        Ω_sun in sr (≤ 2π).
    samples_across : int
        Sub-cells across the disc's diameter (≥ 2).
    max_subdivision : int
        Largest k.

    Returns
    -------
    ndarray, float64, shape (6, n, n)
        Coverage fractions in [0, 1].
    """
    n = _face_size(n)
    s_dir = DEFAULT_SUN_DIRECTION if sun_direction is None else _direction(sun_direction, "sun_direction")
    omega_s = _positive(sun_solid_angle, "sun_solid_angle", upper=2 * np.pi)
    samples_across = _int_param(samples_across, "samples_across", 2)
    max_subdivision = _int_param(max_subdivision, "max_subdivision", 1, 4096)
    cos_s = _sun_cos_radius(omega_s)
    theta_s = np.arccos(cos_s)
    diam_texels = 2.0 * theta_s * n / 2.0
    k = int(np.clip(np.ceil(samples_across / diam_texels), 2, max_subdivision))
    dirs = envmap.texel_directions(n)
    cand = dirs @ s_dir >= np.cos(min(np.pi, theta_s + 2.0 / n))
    cov = np.zeros((6, n, n))
    f, r, c = np.nonzero(cand)
    if f.size:
        cov[f, r, c] = _coverage(n, f, r, c, lambda d: (d @ s_dir) >= cos_s, k)
    return cov


def sun_coverage_relative_error(n: int, sun_direction=None, sun_solid_angle: float = SUN_SOLID_ANGLE, **kw) -> float:
    """The quadrature error of :func:`sun_disc_coverage`, (Σ coverage·Ω_texel − Ω_sun) / Ω_sun.

    Parameters
    ----------
    n, sun_direction, sun_solid_angle, **kw
        As :func:`sun_disc_coverage`.

    Returns
    -------
    float

    Examples
    --------
    >>> from ibl_ref.synthetic.synthetic_envs import sun_coverage_relative_error
    >>> abs(sun_coverage_relative_error(32)) < 2e-3
    True
    """
    cov = sun_disc_coverage(n, sun_direction, sun_solid_angle, **kw)
    return float((np.sum(cov * envmap.cube_solid_angles(n)) - sun_solid_angle) / sun_solid_angle)


def env_sky_sun(
    n: int = 64,
    sun_direction=None,
    sun_solid_angle: float = SUN_SOLID_ANGLE,
    sun_radiance=1.0e5,
    sky_zenith=(0.25, 0.45, 0.9),
    sky_horizon=(0.8, 0.85, 0.9),
    ground=(0.12, 0.1, 0.08),
    horizon_width: float = 0.05,
    samples_across: int = 32,
) -> np.ndarray:
    """Outdoor sky with a small, very bright sun.

    Sky (y = ω_y ≥ 0, +Y up): ``L = horizon + (zenith − horizon)·(1 − (1 − y)²)``;
    ground (y < 0): ``L = ground + (horizon − ground)·exp(y / horizon_width)`` (continuous at the horizon).
    Both are evaluated at texel centres (smooth).  The sun is a spherical cap of ``sun_solid_angle`` sr
    around ``sun_direction`` with radiance ``sun_radiance``; it replaces the sky where it covers:
    ``L = (1 − cov)·L_sky + cov·L_sun`` with the supersampled coverage of :func:`sun_disc_coverage`,
    so the sun contributes ``sun_radiance · Ω_sun`` to ∫L dω up to the reported coverage error.

    Parameters
    ----------
    n : int
    sun_direction : 3 floats
        Default :data:`DEFAULT_SUN_DIRECTION` (45° elevation); :data:`SUN_NEAR_CORNER` puts the disc
        across the +X/+Y/+Z corner.
    sun_solid_angle : float
        sr, default 6.8e-5 (the real sun).  Must be ≤ 2π.
    sun_radiance : float or 3 floats
        Default 1e5 (above the fp16 maximum 65504 on purpose).
    sky_zenith, sky_horizon, ground : float or 3 floats
    horizon_width : float
        e-folding width of the ground's brightening towards the horizon (in ω_y).
    samples_across : int
        Sub-cells across the sun's diameter for the coverage supersampling.

    Returns
    -------
    ndarray, float64, shape (6, n, n, 3)
        Radiance in the OpenEXR cube layout (:mod:`ibl_ref.environment.envmap`).
    """
    n = _face_size(n)
    zen, hor, gnd = _rgb(sky_zenith, "sky_zenith"), _rgb(sky_horizon, "sky_horizon"), _rgb(ground, "ground")
    sun = _rgb(sun_radiance, "sun_radiance")
    hw = _positive(horizon_width, "horizon_width")
    y = envmap.texel_directions(n)[..., 1:2]
    t_sky = 1.0 - (1.0 - np.clip(y, 0.0, 1.0)) ** 2
    sky = np.where(y >= 0, hor + (zen - hor) * t_sky, gnd + (hor - gnd) * np.exp(np.minimum(y, 0.0) / hw))
    cov = sun_disc_coverage(n, sun_direction, sun_solid_angle, samples_across)[..., None]
    return (1.0 - cov) * sky + cov * sun


# -------------------------------------------------------------------------- studio
DEFAULT_STUDIO_LIGHTS = (
    {"direction": (1.0, 0.6, 1.0), "width_deg": 30.0, "height_deg": 20.0, "radiance": (20.0, 18.0, 15.0)},  # key
    {"direction": (-1.0, 0.2, 0.8), "width_deg": 40.0, "height_deg": 30.0, "radiance": (3.0, 3.2, 3.5)},  # fill
    {"direction": (0.1, 1.0, -0.3), "width_deg": 50.0, "height_deg": 50.0, "radiance": (5.0, 5.0, 5.0)},  # top
    {"direction": (-0.3, 0.3, -1.0), "width_deg": 10.0, "height_deg": 60.0, "radiance": (40.0, 40.0, 40.0)},  # strip rim
)


def _rect_frame(direction):
    c = _direction(direction, "light direction")
    ref = np.array([0.0, 1.0, 0.0]) if abs(c[1]) < 0.99 else np.array([1.0, 0.0, 0.0])
    t = _unit(np.cross(ref, c))  # horizontal axis (width)
    bt = np.cross(c, t)  # vertical axis (height)
    return c, t, bt


def rect_light_solid_angle(width_deg: float, height_deg: float) -> float:
    """Exact solid angle (sr) of a gnomonic rectangle: 4·A(tan(w/2), tan(h/2)), A(x,y)=atan2(xy, √(x²+y²+1)).

    Parameters
    ----------
    width_deg, height_deg : float
        Angular width and height through the centre, degrees.

    Returns
    -------
    float

    Examples
    --------
    A 90° × 90° rectangle is one cube face, a sixth of the sphere:

    >>> import numpy as np
    >>> from ibl_ref.synthetic.synthetic_envs import rect_light_solid_angle
    >>> rect_light_solid_angle(90.0, 90.0) / np.pi
    0.6667
    """
    tw, th = np.tan(np.radians(width_deg) / 2), np.tan(np.radians(height_deg) / 2)
    return float(4.0 * envmap.area_primitive(tw, th))


def _rect_light_params(light: dict):
    if not isinstance(light, dict):
        raise IBLError(f"studio: each light must be a dict with direction, width_deg, height_deg, radiance; got {light!r}")
    unknown = set(light) - {"direction", "width_deg", "height_deg", "radiance"}
    if unknown or "direction" not in light:
        raise IBLError(f"studio: light needs 'direction' (+ width_deg, height_deg, radiance); bad keys {sorted(unknown)}")
    w = _positive(light.get("width_deg", 20.0), "light width_deg", upper=170.0)
    h = _positive(light.get("height_deg", 20.0), "light height_deg", upper=170.0)
    return _rect_frame(light["direction"]), w, h, _rgb(light.get("radiance", 10.0), "light radiance")


@functools.lru_cache(maxsize=8)
def _texel_corner_directions(n: int) -> np.ndarray:
    """Unit directions of the texel corners (face-plane edge grid), shape (6, n+1, n+1, 3), read-only."""
    e = np.linspace(-1.0, 1.0, n + 1)
    v_e, u_e = np.meshgrid(e, e, indexing="ij")
    p = envmap.face_uv_to_direction(np.arange(6)[:, None, None], u_e[None], v_e[None])
    p.setflags(write=False)
    return p


def rect_light_coverage(n: int, direction, width_deg: float, height_deg: float, supersample: int = 8) -> np.ndarray:
    """Fraction (6, n, n) of each texel inside a rectangular light.

    The light is the set of directions ω with |ω·t| ≤ tan(w/2)·ω·c and |ω·b| ≤ tan(h/2)·ω·c,
    c = ``direction``, t horizontal (⊥ c and +Y; +X if c ∥ Y), b = c × t: a planar rectangle seen from the
    centre, i.e. the intersection of four hemispheres (a convex spherical quadrilateral).  Texel edges are
    great-circle arcs, so a texel whose four corners are all inside is fully inside (coverage 1), and one
    whose corners are all outside the same bounding hemisphere is fully outside (0), exactly; only the
    remaining texels (those the light's edges cross) are supersampled k × k.

    Parameters
    ----------
    n : int
        Face size.
    direction : 3 floats
        Centre c of the light.
    width_deg, height_deg : float
        Angular size through the centre, degrees (< 170).
    supersample : int
        k.

    Returns
    -------
    ndarray, float64, shape (6, n, n)
        Coverage fractions in [0, 1].
    """
    n = _face_size(n)
    k = _int_param(supersample, "supersample", 1, 256)
    (c, t, bt), w, h, _ = _rect_light_params({"direction": direction, "width_deg": width_deg, "height_deg": height_deg})
    tw, th = np.tan(np.radians(w) / 2), np.tan(np.radians(h) / 2)
    # the four bounding planes: (tw·c ∓ t)·ω ≥ 0, (th·c ∓ b)·ω ≥ 0
    planes = np.stack([tw * c - t, tw * c + t, th * c - bt, th * c + bt])  # (4, 3)

    def inside(d):
        return np.all(d @ planes.T >= 0.0, axis=-1)

    side = _texel_corner_directions(n) @ planes.T >= 0.0  # (6, n+1, n+1, 4)
    corners = np.stack([side[:, :-1, :-1], side[:, :-1, 1:], side[:, 1:, :-1], side[:, 1:, 1:]], axis=0)
    full = np.all(corners, axis=(0, 4))  # all corners inside all planes
    empty = np.any(np.all(~corners, axis=0), axis=-1)  # all corners outside one plane
    cov = full.astype(np.float64)
    f, r, cc = np.nonzero(~full & ~empty)
    if f.size:
        cov[f, r, cc] = _coverage(n, f, r, cc, inside, k)
    return cov


def env_studio(n: int = 64, lights=None, background=0.02, floor=0.05, supersample: int = 8) -> np.ndarray:
    """Dark studio with rectangular area lights.

    Parameters
    ----------
    n : int
    lights : list of dict, optional
        Each ``{"direction": (x,y,z), "width_deg": w, "height_deg": h, "radiance": L}`` (L scalar or RGB);
        default :data:`DEFAULT_STUDIO_LIGHTS` (key, fill, top softbox, rim strip).  Overlapping lights add.
    background : float or 3 floats
        Radiance of the walls/ceiling (ω_y ≥ 0).
    floor : float or 3 floats
        Radiance of the floor (ω_y < 0, decided at the texel centre).
    supersample : int
        k for the k × k coverage supersampling of the light edges.

    Returns
    -------
    ndarray, float64, shape (6, n, n, 3)
        Radiance in the OpenEXR cube layout (:mod:`ibl_ref.environment.envmap`).

    Notes
    -----
    Each light adds ``radiance · Ω_rect`` to ∫L dω with Ω_rect = :func:`rect_light_solid_angle`
    (up to the supersampling error at the edges).
    """
    n = _face_size(n)
    bg, fl = _rgb(background, "background"), _rgb(floor, "floor")
    y = envmap.texel_directions(n)[..., 1:2]
    cube = np.where(y >= 0, bg, fl) * np.ones((6, n, n, 3))
    if lights is None:
        lights = DEFAULT_STUDIO_LIGHTS
    if isinstance(lights, dict):
        lights = [lights]
    for light in lights:
        (c, _, _), w, h, rgb = _rect_light_params(light)
        cov = rect_light_coverage(n, c, w, h, supersample)
        cube += cov[..., None] * rgb
    return cube


# -------------------------------------------------------------------------- checker
def env_checker(n: int = 64, cells: int = 16, low=0.1, high=1.0, mode: str = "latlong", supersample: int = 4,
                cell_texels: int = 4) -> np.ndarray:
    """Two-level checkerboard (a high-frequency test pattern).

    Parameters
    ----------
    n : int
    cells : int
        ``mode="latlong"``: number of cells along latitude (−90°..90°); there are 2·cells along longitude,
        each π/cells wide.  Cell (i, j) with i = ⌊(φ+π/2)/Δ⌋, j = ⌊(λ+π)/Δ⌋ (φ latitude = asin ω_y,
        λ longitude = atan2(ω_x, ω_z), the envmap lat-long convention) is ``high`` if i + j is odd.
        Texel values are supersampled texel averages (k × k, exact sub-cell solid angles).
    low, high : float or 3 floats
    mode : {"latlong", "face"}
        ``"face"``: blocks of ``cell_texels`` × ``cell_texels`` texels per face, ``high`` where
        ⌊row/cell_texels⌋ + ⌊col/cell_texels⌋ + face is odd (exact, no supersampling).
    supersample : int
        k for ``mode="latlong"``.
    cell_texels : int
        Block size for ``mode="face"``.

    Returns
    -------
    ndarray, float64, shape (6, n, n, 3)
        Radiance in the OpenEXR cube layout (:mod:`ibl_ref.environment.envmap`).
    """
    n = _face_size(n)
    lo, hi = _rgb(low, "low"), _rgb(high, "high")
    if mode == "face":
        ct = _int_param(cell_texels, "cell_texels", 1)
        f, r, c = np.meshgrid(np.arange(6), np.arange(n), np.arange(n), indexing="ij")
        frac = ((r // ct + c // ct + f) % 2).astype(np.float64)
    elif mode == "latlong":
        cells = _int_param(cells, "cells", 1, 100000)
        k = _int_param(supersample, "supersample", 1, 64)
        delta = np.pi / cells

        def odd(d):
            lat = np.arcsin(np.clip(d[..., 1], -1.0, 1.0))
            lon = np.arctan2(d[..., 0], d[..., 2])
            i = np.floor((lat + np.pi / 2) / delta)
            j = np.floor((lon + np.pi) / delta)
            return np.mod(i + j, 2.0)

        f, r, c = (a.ravel() for a in np.meshgrid(np.arange(6), np.arange(n), np.arange(n), indexing="ij"))
        frac = _coverage(n, f, r, c, odd, k).reshape(6, n, n)
    else:
        raise IBLError(f"checker: mode must be 'latlong' or 'face', got {mode!r}")
    return lo + frac[..., None] * (hi - lo)


# ----------------------------------------------------------------------------------------------
# dispatch, help, cache
# ----------------------------------------------------------------------------------------------
_GENERATORS = {
    "constant": env_constant,
    "delta": env_delta,
    "gradient": env_gradient,
    "sky_sun": env_sky_sun,
    "studio": env_studio,
    "checker": env_checker,
}
ENV_NAMES = tuple(_GENERATORS)


def _generator(name: str):
    try:
        return _GENERATORS[name]
    except (KeyError, TypeError):
        raise IBLError(f"unknown synthetic environment {name!r}; choose one of {', '.join(ENV_NAMES)}") from None


def _param_names(fn) -> list[str]:
    return [p for p in inspect.signature(fn).parameters if p != "n"]


def _make(name: str, n, params: dict):
    """``(cube (6, n, n, 3) float64, RadianceReport)`` of generator ``name``: the work of :func:`make_env`."""
    fn = _generator(name)
    n = _face_size(n)
    allowed = _param_names(fn)
    unknown = sorted(set(params) - set(allowed))
    if unknown:
        raise IBLError(f"{name}: unknown parameter(s) {unknown}; allowed: {', '.join(allowed)}")
    cube = np.ascontiguousarray(fn(n, **params), dtype=np.float64)
    assert cube.shape == (6, n, n, 3)
    _, rep = apply_policy(cube, f"synthetic environment {name!r}", negative="error", nonfinite="error")
    return cube, rep


def make_env(name: str, n: int = 64, **params) -> np.ndarray:
    """Generate the synthetic environment ``name`` as a (6, n, n, 3) float64 cube map.

    Parameters
    ----------
    name : str
        One of :data:`ENV_NAMES`: ``"constant"``, ``"delta"``, ``"gradient"``, ``"sky_sun"``, ``"studio"``,
        ``"checker"`` (module docstring).
    n : int, optional
        Face size (default 64).
    **params
        The keyword parameters of the generator ``env_<name>`` (their docstrings, or :func:`generator_help`).

    Returns
    -------
    ndarray, float64, shape (6, n, n, 3)
        Radiance in the OpenEXR cube layout (:mod:`ibl_ref.environment.envmap`), checked finite and non-negative.
        :func:`make_environment` returns the same map as a validated
        :class:`~ibl_ref.environment.validated.Environment`.

    Raises
    ------
    IBLError
        An unknown name or parameter, an invalid value.

    Examples
    --------
    A constant map: its integral over the sphere, Σ L·Ω with the exact texel solid angles, is 4π·L:

    >>> import numpy as np
    >>> from ibl_ref.environment.envmap import texel_solid_angles
    >>> from ibl_ref.synthetic.synthetic_envs import make_env
    >>> cube = make_env("constant", 8, value=2.0)
    >>> cube.shape
    (6, 8, 8, 3)
    >>> np.einsum("fijc,ij->c", cube, texel_solid_angles(8)) / np.pi
    array([8., 8., 8.])

    A normalised one-texel light carries exactly the radiance asked for, whatever texel it lands on:

    >>> delta = make_env("delta", 8, direction=(0.3, 1.0, 0.2), radiance=5.0, normalize=True)
    >>> float(np.einsum("fijc,ij->", delta[..., :1], texel_solid_angles(8)))
    5.0
    """
    return _make(name, n, params)[0]


def make_environment(name: str, n: int = 64, **params):
    """:func:`make_env` as a validated :class:`~ibl_ref.environment.validated.Environment` (checked once, when made).

    Parameters
    ----------
    name, n, **params
        As :func:`make_env`.

    Returns
    -------
    Environment
        Read-only float64 ``(6, n, n, 3)`` radiance, trusted by every stage that takes an environment.

    Raises
    ------
    IBLError
        As :func:`make_env`.

    Examples
    --------
    >>> from ibl_ref.synthetic.synthetic_envs import make_environment
    >>> env = make_environment("sky_sun", 16)
    >>> env
    Environment(face_size=16, channels=3, name="synthetic environment 'sky_sun'")
    >>> env.data.flags.writeable
    False
    """
    return adopt(*_make(name, n, params))


#: environments of the renders and experiments: the synthetic generators plus ``"probe"``
SCENE_ENV_NAMES = ENV_NAMES + ("probe",)


def scene_environment(name: str, n: int) -> np.ndarray:
    """The environment of a render case: a :func:`make_env` map, or ``"probe"`` — the probe-like
    lat-long map of :func:`ibl_ref.environment.probe_files.probe_cube` (sky gradient, textured ground with a
    black strip, a 1.5° sun of 3e4) resampled to the cube with the integral-preserving kernel.

    Parameters
    ----------
    name : str
        One of :data:`SCENE_ENV_NAMES`.
    n : int
        Face size.

    Returns
    -------
    ndarray, float64, shape (6, n, n, 3)

    Raises
    ------
    IBLError
        An unknown name.
    """
    if name == "probe":
        from ..environment.probe_files import probe_cube

        return probe_cube(n)
    if name not in ENV_NAMES:
        raise IBLError(f"unknown environment {name!r}; choose from {', '.join(SCENE_ENV_NAMES)}")
    return make_env(name, n=n)


def generator_help(name: str | None = None) -> str:
    """Parameter list with defaults and the first docstring paragraph of one or all generators.

    Parameters
    ----------
    name : str, optional
        One of :data:`ENV_NAMES` (default: all).

    Returns
    -------
    str
    """
    names = ENV_NAMES if name is None else (name,)
    out = []
    for nm in names:
        fn = _generator(nm)
        sig = inspect.signature(fn)
        params = ", ".join(f"{p.name}={p.default!r}" for p in sig.parameters.values() if p.name != "n")
        first = (inspect.getdoc(fn) or "").split("\n\n")[0].replace("\n", " ")
        out.append(f"{nm}: {first}\n    params: {params}")
    return "\n".join(out)


def cache_dir() -> Path:
    """The cache folder of :func:`cached_env`.

    Returns
    -------
    pathlib.Path
        ``$IBL_REF_CACHE`` if set, else ``data_synthetic/cache`` under the current directory.
    """
    return Path(os.environ.get("IBL_REF_CACHE") or Path("data_synthetic") / "cache")


def _cache_key(name: str, n: int, params: dict) -> str:
    def norm(v):
        if isinstance(v, np.ndarray):
            return v.tolist()
        if isinstance(v, (tuple, list)):
            return [norm(x) for x in v]
        if isinstance(v, dict):
            return {str(k): norm(x) for k, x in sorted(v.items())}
        if isinstance(v, np.generic):
            return v.item()
        return v

    blob = json.dumps({"v": GENERATOR_VERSION, "name": name, "n": n, "params": norm(params)}, sort_keys=True)
    return hashlib.sha1(blob.encode()).hexdigest()[:16]


def cached_env(name: str, n: int = 64, cache: str | os.PathLike | None = None, **params) -> np.ndarray:
    """:func:`make_env` with an on-disk ``.npy`` cache (atomic writes).

    The file name ``<name>_n<n>_<hash>.npy`` hashes the generator version, name, size and parameters.
    A cached file with the wrong shape is regenerated.

    Parameters
    ----------
    name, n, **params
        As :func:`make_env`.
    cache : str or os.PathLike, optional
        The folder (default :func:`cache_dir`).

    Returns
    -------
    ndarray, float64, shape (6, n, n, 3)
    """

    _generator(name)
    n = _face_size(n)
    folder = Path(cache) if cache is not None else cache_dir()
    path = folder / f"{name}_n{n}_{_cache_key(name, n, params)}.npy"
    if path.is_file():
        try:
            arr = np.load(path, allow_pickle=False)
            if arr.shape == (6, n, n, 3) and arr.dtype == np.float64:
                return arr
        except (OSError, ValueError):
            pass
    cube = make_env(name, n, **params)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, cube, allow_pickle=False)
    return cube
