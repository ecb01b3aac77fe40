"""Cameras of the renderer: a perspective eye camera and an orthographic light camera.

Knuth et al. (2014), Sec. 3.3–3.4: the scene is rendered once from the eye (a G-buffer, Eq. 5 is evaluated per
pixel) and once per median-cut light from a *directional* light (shadow maps).  This module fixes the pixel
mapping that the rasterizer (:mod:`ibl_ref.rendering.raster`) and the ray-cast reference (:mod:`ibl_ref.rendering.raycast`) share.

Conventions
-----------
* Right-handed world space.  A camera looks along its ``forward`` axis; its image ``right`` and ``up`` axes are
  built by a look-at (``right = normalize(forward × up_hint)``, ``up = right × forward``), as in OpenGL's
  ``gluLookAt`` (camera space ``x`` right, ``y`` up, looking down ``−z``).
* **Depth** is the distance along ``forward`` from the camera's eye point (view-space ``−z``), in world units.
  It is linear in world space, so it is exact under perspective-correct interpolation.
* **Pixel mapping.**  An image has ``width`` W columns and ``height`` H rows, row 0 at the top.  Pixel ``(i, j)``
  (row i, column j) has its centre at normalised screen position ``((j + ½)/W, (i + ½)/H)``; continuous pixel
  coordinates ``(x, y)`` put that centre at ``(j + ½, i + ½)``.  ``x`` grows to the right, ``y`` downwards.
* :class:`PerspectiveCamera` takes a **vertical** field of view ``fov_y_deg`` in degrees; the horizontal extent
  follows from the aspect ratio ``W / H`` (square pixels).
* :class:`OrthographicCamera` is a light's view: parallel rays along ``forward`` (the direction the light travels,
  i.e. ``−ω_light``), an image rectangle of half extents ``half_width × half_height`` world units.
  :func:`light_camera` fits one to a scene's bounding sphere.

Every camera offers ``project(points) -> (x, y, depth, w)`` (continuous pixel coordinates, depth, and the
homogeneous ``w`` used for perspective-correct interpolation: ``w = depth`` for perspective, ``w = 1`` for
orthographic) and ``pixel_rays() -> (origins, directions)`` through the same pixel centres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import IBLError

__all__ = ["CameraError", "PerspectiveCamera", "OrthographicCamera", "look_at_basis", "light_camera", "scene_bounds",
           "as_vec3", "MAX_COORDINATE"]


class CameraError(IBLError):
    """A camera is ill-defined (eye on target, up parallel to the view direction, bad size or fov)."""


#: largest |coordinate| of an eye, target or up vector (as for meshes: products of a few stay in float64)
MAX_COORDINATE = 1e100


def as_vec3(v, name: str) -> np.ndarray:
    """``v`` as a finite float64 3-vector of coordinates <= :data:`MAX_COORDINATE`; :class:`CameraError` naming ``name``."""
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,):
        raise CameraError(f"{name}: expected 3 numbers, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise CameraError(f"{name}: contains NaN or Inf ({a.tolist()})")
    if np.abs(a).max() > MAX_COORDINATE:
        raise CameraError(f"{name}: coordinates up to {np.abs(a).max():.3g}; the camera's products of coordinates "
                          f"would overflow float64 (|coordinate| <= {MAX_COORDINATE:g})")
    return a


def _check_size(width, height) -> tuple[int, int]:
    try:
        w, h = int(width), int(height)
    except (TypeError, ValueError) as exc:
        raise CameraError(f"image size must be integers, got {width!r} x {height!r}") from exc
    if w != width or h != height or w < 1 or h < 1:
        raise CameraError(f"image size must be positive integers, got {width!r} x {height!r}")
    return w, h


def _clip_planes(near, far, *, near_may_be_zero: bool) -> tuple[float, float]:
    """Checked depth range ``(near, far)``: ``0 < near < far < ∞`` (``0 ≤ near`` where allowed)."""
    n, f = float(near), float(far)
    if not ((0.0 <= n if near_may_be_zero else 0.0 < n) and n < f and np.isfinite(f)):
        lower = "<=" if near_may_be_zero else "<"
        raise CameraError(f"need 0 {lower} near < far < inf, got near={near!r}, far={far!r}")
    return n, f


def _freeze(camera, **values) -> None:
    """Store validated values on a frozen camera dataclass."""
    for name, value in values.items():
        object.__setattr__(camera, name, value)


class _CameraFrame:
    """What both cameras share: the world → camera transform and the pixel-centre grid (module conventions)."""

    def to_camera(self, points) -> np.ndarray:
        """Camera-space coordinates (right, up, depth) of world points (..., 3)."""
        p = np.asarray(points, dtype=np.float64)
        return (p - self.eye) @ self.basis.T

    def _pixel_centres_ndc(self):
        """Normalised device coordinates of the pixel centres: x (W,) left → right, y (H,) top → bottom, in (−1, 1)."""
        j = (np.arange(self.width) + 0.5) / self.width
        i = (np.arange(self.height) + 0.5) / self.height
        return 2.0 * j - 1.0, 1.0 - 2.0 * i


def look_at_basis(forward, up_hint) -> np.ndarray:
    """Orthonormal camera basis ``(right, up, forward)`` as rows of a (3, 3) matrix.

    Raises :class:`CameraError` when ``forward`` is zero or ``up_hint`` is (nearly) parallel to it
    (|sin| < 1e-6), since the image orientation is then undefined.
    """
    f = as_vec3(forward, "forward")
    u = as_vec3(up_hint, "up")
    nf = np.linalg.norm(f)
    if nf == 0:
        raise CameraError("view direction is zero (eye == target?)")
    f = f / nf
    nu = np.linalg.norm(u)
    if nu == 0:
        raise CameraError("up vector is zero")
    r = np.cross(f, u / nu)
    nr = np.linalg.norm(r)
    if nr < 1e-6:
        raise CameraError(f"up vector {u.tolist()} is parallel to the view direction {f.tolist()}; choose another up")
    r = r / nr
    up = np.cross(r, f)
    return np.stack([r, up, f])


@dataclass(frozen=True)
class PerspectiveCamera(_CameraFrame):
    """Pinhole camera from a look-at.

    Parameters
    ----------
    eye, target, up : array_like (3,)
        Eye position, a point it looks at, and an up hint (need not be orthogonal to the view direction).
    fov_y_deg : float
        **Vertical** full field of view in degrees, in (0, 180).
    width, height : int
        Image size in pixels; the aspect ratio is ``width / height``.
    near, far : float
        Depth range (distance along the view axis).  Triangles with a vertex in front of ``near`` are
        rejected by the rasterizer (see :mod:`ibl_ref.rendering.raster`); fragments beyond ``far`` are discarded.
    """

    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov_y_deg: float
    width: int
    height: int
    near: float = 1e-3
    far: float = 1e6
    basis: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        eye = as_vec3(self.eye, "eye")
        target = as_vec3(self.target, "target")
        up = as_vec3(self.up, "up")
        if np.linalg.norm(target - eye) <= 1e-12 * max(1.0, np.abs(eye).max()):
            raise CameraError(f"eye {eye.tolist()} coincides with target {target.tolist()}")
        w, h = _check_size(self.width, self.height)
        fov = float(self.fov_y_deg)
        if not (0.0 < fov < 180.0):
            raise CameraError(f"fov_y_deg must be in (0, 180) degrees, got {self.fov_y_deg!r}")
        near, far = _clip_planes(self.near, self.far, near_may_be_zero=False)
        _freeze(self, eye=eye, target=target, up=up, width=w, height=h, fov_y_deg=fov, near=near, far=far,
                basis=look_at_basis(target - eye, up))

    is_orthographic = False

    @property
    def forward(self) -> np.ndarray:
        return self.basis[2]

    @property
    def tan_half_fov_y(self) -> float:
        return float(np.tan(np.radians(self.fov_y_deg) / 2))

    @property
    def aspect(self) -> float:
        return self.width / self.height

    def view_matrix(self) -> np.ndarray:
        """4x4 world → camera matrix (OpenGL convention: camera looks down −z, y up)."""
        r, u, f = self.basis
        m = np.eye(4)
        m[0, :3], m[1, :3], m[2, :3] = r, u, -f
        m[:3, 3] = -m[:3, :3] @ self.eye
        return m

    def projection_matrix(self) -> np.ndarray:
        """4x4 OpenGL-style perspective projection (clip space, NDC z in [−1, 1] over [near, far])."""
        t = self.tan_half_fov_y
        n, f = self.near, self.far
        p = np.zeros((4, 4))
        p[0, 0] = 1.0 / (t * self.aspect)
        p[1, 1] = 1.0 / t
        p[2, 2] = -(f + n) / (f - n)
        p[2, 3] = -2.0 * f * n / (f - n)
        p[3, 2] = -1.0
        return p

    def project(self, points):
        """Continuous pixel coordinates of world points.

        Returns ``(x, y, depth, w)``; ``x = (ndc_x + 1)/2 · W``, ``y = (1 − ndc_y)/2 · H`` with
        ``ndc = (right, up) / (depth · tan(fov_y/2) · (aspect, 1))``; ``w = depth``.  Points with
        depth ≤ 0 give meaningless x, y (the caller rejects them).
        """
        c = self.to_camera(points)
        depth = c[..., 2]
        t = self.tan_half_fov_y
        with np.errstate(divide="ignore", invalid="ignore"):
            ndc_x = c[..., 0] / (depth * t * self.aspect)
            ndc_y = c[..., 1] / (depth * t)
        x = (ndc_x + 1.0) * 0.5 * self.width
        y = (1.0 - ndc_y) * 0.5 * self.height
        return x, y, depth, depth

    def pixel_rays(self, normalize: bool = False):
        """Rays through every pixel centre, shape (H, W, 3).

        With ``normalize=False`` (default) the direction has unit component along ``forward``, so the ray
        parameter of a hit *is* its depth.  Origins are all ``eye``.
        """
        ndc_x, ndc_y = self._pixel_centres_ndc()
        t = self.tan_half_fov_y
        cx = ndc_x[None, :] * t * self.aspect
        cy = ndc_y[:, None] * t
        r, u, f = self.basis
        d = cx[..., None] * r + cy[..., None] * u + f
        if normalize:
            d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        o = np.broadcast_to(self.eye, d.shape).copy()
        return o, d

    def view_vectors(self, points) -> np.ndarray:
        """Unit vectors from world points toward the eye (the paper's view vector v)."""
        v = self.eye - np.asarray(points, dtype=np.float64)
        n = np.linalg.norm(v, axis=-1, keepdims=True)
        return v / np.where(n > 0, n, 1.0)


@dataclass(frozen=True)
class OrthographicCamera(_CameraFrame):
    """Parallel projection, e.g. a directional light's shadow-map camera.

    Parameters
    ----------
    eye : array_like (3,)
        Centre of the image plane; depth is measured from it along ``forward``.
    forward : array_like (3,)
        Projection direction (for a light: the direction the light *travels*, ``−ω_light``).
    up : array_like (3,)
        Up hint for the image orientation.
    half_width, half_height : float
        Half extents of the image rectangle in world units.
    width, height : int
        Image size in pixels; texel size is ``2·half_width/width`` (keep it equal to ``2·half_height/height``).
    near, far : float
        Depth range; ``near`` may be 0 (no perspective divide).
    """

    eye: np.ndarray
    forward: np.ndarray
    up: np.ndarray
    half_width: float
    half_height: float
    width: int
    height: int
    near: float = 0.0
    far: float = 1.0
    basis: np.ndarray = field(init=False, repr=False, compare=False)

    is_orthographic = True

    def __post_init__(self):
        eye = as_vec3(self.eye, "eye")
        w, h = _check_size(self.width, self.height)
        hw, hh = float(self.half_width), float(self.half_height)
        if not (hw > 0 and hh > 0 and np.isfinite(hw) and np.isfinite(hh)):
            raise CameraError(
                f"half extents must be positive and finite, got {self.half_width!r}, {self.half_height!r}"
            )
        near, far = _clip_planes(self.near, self.far, near_may_be_zero=True)
        basis = look_at_basis(self.forward, self.up)
        _freeze(self, eye=eye, forward=basis[2].copy(), up=as_vec3(self.up, "up"), half_width=hw, half_height=hh,
                width=w, height=h, near=near, far=far, basis=basis)

    @property
    def texel_size(self) -> float:
        """World size of one texel (horizontal)."""
        return 2.0 * self.half_width / self.width

    def project(self, points):
        """Continuous pixel coordinates ``(x, y, depth, w=1)`` (same pixel mapping as the perspective camera)."""
        c = self.to_camera(points)
        x = (c[..., 0] / self.half_width + 1.0) * 0.5 * self.width
        y = (1.0 - c[..., 1] / self.half_height) * 0.5 * self.height
        depth = c[..., 2]
        return x, y, depth, np.ones_like(depth)

    def pixel_rays(self, normalize: bool = True):
        """Parallel rays from the image plane through every pixel centre: origins (H, W, 3), directions (H, W, 3)."""
        ndc_x, ndc_y = self._pixel_centres_ndc()
        cx, cy = ndc_x * self.half_width, ndc_y * self.half_height
        r, u, f = self.basis
        o = self.eye + cx[None, :, None] * r + cy[:, None, None] * u
        d = np.broadcast_to(f, o.shape).copy()
        return o, d

    def view_vectors(self, points) -> np.ndarray:
        """Unit vectors toward the viewer: ``−forward`` everywhere."""
        p = np.asarray(points, dtype=np.float64)
        return np.broadcast_to(-self.forward, p.shape).copy()


def scene_bounds(vertices) -> tuple[np.ndarray, float]:
    """Bounding sphere ``(centre, radius)`` of points: centre of the axis-aligned box, radius to the farthest point."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    if len(v) == 0:
        raise CameraError("cannot fit bounds to an empty point set")
    c = 0.5 * (v.min(axis=0) + v.max(axis=0))
    r = float(np.sqrt(((v - c) ** 2).sum(axis=1).max()))
    return c, max(r, 1e-12)


def light_camera(direction, centre, radius, resolution: int = 512, margin: float = 0.05) -> OrthographicCamera:
    """Orthographic shadow camera for a directional light, fitted to a bounding sphere.

    Parameters
    ----------
    direction : array_like (3,)
        Direction **toward** the light (an environment-map direction ω, as in ``PEMSet.lights``).
    centre, radius
        Bounding sphere of the scene (see :func:`scene_bounds`).
    resolution : int
        Shadow map size (square).
    margin : float
        Relative enlargement of the sphere (default 5 %), so silhouettes never touch the map border.

    Notes
    -----
    With ``R = radius·(1 + margin)`` the image plane sits at ``centre + R·ω`` looking along ``−ω``;
    ``near = 0``, ``far = 2R`` (the whole sphere lies in [0, 2R] depth), half extents ``R``, so the texel size
    is ``2R / resolution``.  The up hint is +Y, or +Z when ω is within ~0.06° of ±Y.
    """
    w = as_vec3(direction, "light direction")
    n = np.linalg.norm(w)
    if n == 0:
        raise CameraError("light direction is zero")
    w = w / n
    R = float(radius) * (1.0 + float(margin))
    if not (R > 0 and np.isfinite(R)):
        raise CameraError(f"radius must be positive and finite, got {radius!r}")
    up = np.array([0.0, 1.0, 0.0]) if abs(w[1]) < 1 - 5e-7 else np.array([0.0, 0.0, 1.0])
    return OrthographicCamera(
        eye=as_vec3(centre, "centre") + R * w,
        forward=-w,
        up=up,
        half_width=R,
        half_height=R,
        width=resolution,
        height=resolution,
        near=0.0,
        far=2.0 * R,
    )
