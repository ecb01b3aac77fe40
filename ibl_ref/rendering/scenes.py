"""Scenes and camera framing shared by the CLI, the experiments and the notebooks.

* :func:`ground_quad` — a square ground quad under a mesh (side 3 × the mesh's largest extent, at its lowest
  point, normal +y), the receiver of the teapot's shadow in ``ibl-ref render``.
* :func:`teapot_on_ground` — the render scene: ``[(mesh, 0), (ground, 1)]`` (material id 0 = object, 1 = ground).
* :func:`default_camera` — the one default view: a perspective camera looking at the centre of the scene's
  bounding sphere (centre c, radius R) from ``c + distance·R·view_dir`` (default ``view_dir = (0.3, 0.5, 1)``,
  ``distance = 2.6``, vertical field of view 40°, as Knuth et al. 2014 Fig. 6 is reproduced in
  ``ibl-ref experiment fig6``); ``distance="fit"`` places the eye so that the bounding sphere fits the vertical
  field of view with a 10 % margin, ``R / sin(fov/2) · 1.1``.  Explicit ``eye`` / ``target`` override the framing.
"""

from __future__ import annotations

import numpy as np

from ..errors import IBLError
from .camera import PerspectiveCamera
from .camera import as_vec3
from .raster import prepare_scene

__all__ = ["ground_quad", "teapot_on_ground", "default_camera", "DEFAULT_VIEW_DIR", "DEFAULT_DISTANCE",
           "DEFAULT_FOV_Y_DEG"]

DEFAULT_VIEW_DIR = (0.3, 0.5, 1.0)
DEFAULT_DISTANCE = 2.6
DEFAULT_FOV_Y_DEG = 40.0


def ground_quad(mesh, scale: float = 1.5):
    """Square quad (2 triangles, normal +y) at the lowest point of ``mesh``, half-side ``scale`` × its extent."""
    import trimesh

    lo, hi = np.asarray(mesh.bounds, dtype=np.float64)
    s = float(scale) * float((hi - lo).max())
    y0 = float(lo[1])
    c = 0.5 * (lo + hi)
    return trimesh.Trimesh(
        [[c[0] - s, y0, c[2] - s], [c[0] + s, y0, c[2] - s], [c[0] + s, y0, c[2] + s], [c[0] - s, y0, c[2] + s]],
        [[0, 2, 1], [0, 3, 2]], process=False)


def teapot_on_ground(mesh="teapot", ground: bool = True) -> list:
    """``[(mesh, 0), (ground_quad(mesh), 1)]``; ``mesh`` a trimesh or a name/path for
    :func:`ibl_ref.synthetic.synthetic_meshes.load_mesh` (default the Utah teapot)."""
    if isinstance(mesh, (str, bytes)) or hasattr(mesh, "__fspath__"):
        from ..synthetic.synthetic_meshes import load_mesh

        mesh = load_mesh(mesh)
    out = [(mesh, 0)]
    if ground:
        out.append((ground_quad(mesh), 1))
    return out


def default_camera(meshes, size: int = 64, view_dir=DEFAULT_VIEW_DIR, fov_y_deg: float = DEFAULT_FOV_Y_DEG,
                   distance=DEFAULT_DISTANCE, *, width: int | None = None, height: int | None = None, eye=None,
                   target=None, up=(0.0, 1.0, 0.0)):
    """Perspective camera framing ``meshes`` (module docstring).

    Parameters
    ----------
    meshes : the meshes that define the framing (bounding sphere c, R; see :func:`ibl_ref.rendering.raster.prepare_scene`)
    size : image width = height in pixels, unless ``width`` / ``height`` are given
    view_dir : direction from the target to the eye (used when ``eye`` is None)
    fov_y_deg : vertical field of view in degrees, in (0, 180)
    distance : eye distance in units of R, or ``"fit"`` (bounding sphere fits the vertical fov, 10 % margin)
    eye, target : explicit eye position and look-at point (default target: c)
    up : up hint

    Clip planes: near = 1e-3·R, far = 100·R for the framed view, 100·(|eye − target| + R) with an explicit eye.
    """

    c, R = prepare_scene(meshes, warn=False).bounds()
    if not (0 < float(fov_y_deg) < 180):
        raise IBLError(f"field of view must be in (0, 180) degrees, got {fov_y_deg}")
    w = int(size if width is None else width)
    h = int(size if height is None else height)

    tgt = c if target is None else as_vec3(target, "target")  # checked first: the eye is placed from it
    if eye is None:
        d = np.asarray(view_dir, dtype=np.float64)
        if d.shape != (3,) or not np.all(np.isfinite(d)) or np.linalg.norm(d) == 0:
            raise IBLError(f"view direction must be a finite non-zero 3-vector, got {view_dir!r}")
        d = d / np.linalg.norm(d)
        if isinstance(distance, str):
            if distance != "fit":
                raise IBLError(f"distance must be a number of radii or 'fit', got {distance!r}")
            dist = R / np.sin(np.radians(float(fov_y_deg)) / 2) * 1.1
        else:
            dist = float(distance) * R
        from .camera import MAX_COORDINATE

        with np.errstate(over="ignore"):
            e = tgt + dist * d
        if not (np.isfinite(dist) and dist > 0 and np.all(np.abs(e) <= MAX_COORDINATE)):
            raise IBLError(f"distance={distance!r} (bounding radii of {R:.3g}) puts the eye at {e.tolist()}, beyond "
                           f"what the camera can use (|coordinate| <= {MAX_COORDINATE:g}); choose a smaller distance")
        far = 100 * R
    else:
        e = as_vec3(eye, "eye")
        far = 100 * (float(np.linalg.norm(e - tgt)) + R)
    return PerspectiveCamera(eye=e, target=tgt, up=list(up), fov_y_deg=fov_y_deg, width=w, height=h,
                             near=1e-3 * R, far=far)
