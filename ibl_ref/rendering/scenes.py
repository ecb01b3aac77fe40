"""Scenes and camera framing shared by the CLI, the experiments and the notebooks.

* :func:`ground_quad` — a square ground quad under a mesh (side 3 × the mesh's largest extent, at its lowest
  point, normal +y), the receiver of the teapot's shadow in ``ibl-ref render``.
* :func:`teapot_on_ground` — the render scene: ``[(mesh, 0), (ground, 1)]`` (material id 0 = object, 1 = ground).
* :func:`default_camera` — the one default view: a perspective camera looking at the centre of the scene's
  bounding sphere (centre c, radius R) from ``c + distance·R·view_dir`` (default ``view_dir = (0.3, 0.5, 1)``,
  ``distance = 2.6``, vertical field of view 40°, as Knuth et al. 2014 Fig. 6 is reproduced in
  ``ibl-ref experiment fig6``); ``distance="fit"`` places the eye so that the bounding sphere fits the vertical
  field of view with a 10 % margin, ``R / sin(fov/2) · 1.1``.  Explicit ``eye`` / ``target`` override the framing.

Scenes with strong self-occlusion (the cases screen-space ambient occlusion is judged on,
:mod:`ibl_ref.occlusion.gtao`), each a list of meshes, +y up, outward (counter-clockwise) faces:

* :func:`crevice_scene` — a slab with a rectangular pit cut into its top (a box cavity open to the top): one
  closed solid with flat faces.  Vertices are not shared across faces of different planes (hard edges, as engines
  export them), so trimesh's vertex normals are the face normals and a smoothly shaded G-buffer is still flat;
  merging coincident vertices gives a watertight mesh of positive volume.
* :func:`bumpy_scene` — a ground quad (open, one-sided, normal +y) with a seeded, non-overlapping arrangement of
  small icospheres sunk to various depths: many small occluders and contact creases.
* :func:`normal_mapped_scene` — a flat ground quad carrying a seeded procedural normal map
  (:mod:`ibl_ref.rendering.normal_map`): the shading normals tilt away from the geometric one, the geometry does
  not, so the only occluder is the surface's own geometric horizon — the case horizon occlusion was made for
  (Marmoset 2014).
* :data:`OCCLUSION_SCENES` names them (and the teapot); :func:`occlusion_scene` gives a scene with its camera
  factory, :func:`scene_camera` the view of each (the teapot: :func:`default_camera` framing the teapot alone).
"""

from __future__ import annotations

import numpy as np

from ..errors import IBLError
from .camera import PerspectiveCamera
from .camera import as_vec3
from .raster import mesh_list, prepare_scene

__all__ = ["ground_quad", "teapot_on_ground", "default_camera", "DEFAULT_VIEW_DIR", "DEFAULT_DISTANCE",
           "DEFAULT_FOV_Y_DEG", "crevice_scene", "bumpy_scene", "normal_mapped_scene", "scene_camera",
           "occlusion_scene", "OCCLUSION_SCENES"]

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


def _panel(corners, outward):
    """One planar quad (4 corners in cyclic order) as (vertices (4, 3), faces (2, 3)), wound to face ``outward``."""
    c = np.asarray(corners, dtype=np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    if np.dot(np.cross(c[1] - c[0], c[2] - c[0]), outward) < 0:
        faces = faces[:, ::-1]
    return c, faces


def _mesh_from_panels(panels, metadata=None):
    """A trimesh of planar quads (:func:`_panel`) that share no vertices (hard edges: vertex normals = face normals)."""
    import trimesh

    verts = np.concatenate([p[0] for p in panels])
    faces = np.concatenate([p[1] + 4 * k for k, p in enumerate(panels)])
    mesh = trimesh.Trimesh(verts, faces, process=False)
    mesh.metadata.update(metadata or {})
    return mesh


def _square_ground(size: float):
    """The square quad y = 0 of side ``size`` centred at the origin: 2 triangles, normal +y."""
    import trimesh

    s = size / 2
    return trimesh.Trimesh([[-s, 0.0, -s], [s, 0.0, -s], [s, 0.0, s], [-s, 0.0, s]], [[0, 2, 1], [0, 3, 2]],
                           process=False)


def crevice_scene(depth: float = 0.5, width: float = 0.5, length: float = 1.0, slab: float = 2.5) -> list:
    """A square slab with a rectangular pit cut into its top: a box cavity open to the top (module docstring).

    Parameters
    ----------
    depth : float
        Depth of the pit below the top face y = 0 (world units).
    width, length : float
        Extent of the pit along x and z (each smaller than ``slab``); the pit is centred at the origin.
    slab : float
        Side of the square top face; the slab's bottom is at y = −2·depth.

    Returns
    -------
    list of trimesh.Trimesh
        One closed solid of 28 triangles (14 planar quads, none sharing a vertex);
        ``metadata["crevice"]`` holds the parameters.  With the defaults the bottom centre of the pit sees the sky
        through the opening only: its cosine-weighted visibility is the form factor to the opening, 0.361.

    Examples
    --------
    >>> from ibl_ref.rendering.scenes import crevice_scene
    >>> (mesh,) = crevice_scene()
    >>> len(mesh.faces), mesh.bounds.tolist()
    (28, [[-1.25, -1.0, -1.25], [1.25, 0.0, 1.25]])
    """
    from ..synthetic.synthetic_meshes import _pos_param, validate_mesh

    depth, width, length, slab = (_pos_param(x, name) for x, name in
                                  ((depth, "depth"), (width, "width"), (length, "length"), (slab, "slab")))
    if not (width < slab and length < slab):
        raise IBLError(f"crevice_scene: the pit ({width:g} x {length:g}) must be smaller than the slab ({slab:g})")
    s, bottom = slab / 2, -2.0 * depth
    up = np.array([0.0, 1.0, 0.0])
    panels = []
    for e, a_in, b_in in (((1, 0), width / 2, length / 2), ((-1, 0), width / 2, length / 2),
                          ((0, 1), length / 2, width / 2), ((0, -1), length / 2, width / 2)):
        e3 = np.array([e[0], 0.0, e[1]], dtype=np.float64)  # side normal in the xz-plane
        f3 = np.array([-e[1], 0.0, e[0]], dtype=np.float64)  # tangent along that side

        def at(a, b, y, e3=e3, f3=f3):
            return a * e3 + b * f3 + y * up

        panels.append(_panel([at(s, s, 0), at(s, -s, 0), at(a_in, -b_in, 0), at(a_in, b_in, 0)], up))  # top ring
        panels.append(_panel([at(a_in, b_in, 0), at(a_in, -b_in, 0), at(a_in, -b_in, -depth),
                              at(a_in, b_in, -depth)], -e3))  # pit wall, facing into the pit
        panels.append(_panel([at(s, s, 0), at(s, -s, 0), at(s, -s, bottom), at(s, s, bottom)], e3))  # slab side
    hw, hl = width / 2, length / 2
    panels.append(_panel([[hw, -depth, hl], [hw, -depth, -hl], [-hw, -depth, -hl], [-hw, -depth, hl]], up))
    panels.append(_panel([[s, bottom, s], [s, bottom, -s], [-s, bottom, -s], [-s, bottom, s]], -up))
    mesh = _mesh_from_panels(panels, {"crevice": dict(depth=depth, width=width, length=length, slab=slab)})
    return [validate_mesh(mesh, "crevice")]


def bumpy_scene(n_bumps: int = 40, seed: int = 0, size: float = 2.0, radii=(0.06, 0.16), subdivisions: int = 2,
                gap: float = 0.01) -> list:
    """A square ground quad with ``n_bumps`` small spheres sunk into it at seeded places (module docstring).

    Parameters
    ----------
    n_bumps : int
        Number of spheres, in [1, 500] (each ``20·4^subdivisions`` triangles: 320 at the default).
    seed : int
        Seed of the arrangement (same seed → identical meshes).
    size : float
        Side of the ground quad (y = 0, centred at the origin).
    radii : (float, float)
        Range of the sphere radii (uniform), 0 < lo ≤ hi.
    subdivisions : int
        Icosphere subdivisions, in [0, 4].
    gap : float
        Least horizontal gap between two spheres (they never overlap; narrow gaps make crevices).

    Returns
    -------
    list of trimesh.Trimesh
        ``[ground, bumps]``: the ground quad (2 triangles, one-sided, open) and one mesh of ``n_bumps`` disjoint
        closed icospheres (watertight, radial vertex normals).  A sphere of radius r has its centre at height
        r·e, e uniform in [−0.5, 0.9]: from a half-buried cap to a ball sunk 5 % of its diameter.
        ``metadata["bumps"]`` holds the (n_bumps, 4) array of centres and radii.

    Raises
    ------
    IBLError
        A parameter out of range, or no room for ``n_bumps`` spheres (after 200 tries per sphere).

    Examples
    --------
    >>> from ibl_ref.rendering.scenes import bumpy_scene
    >>> ground, bumps = bumpy_scene(n_bumps=5, subdivisions=1)
    >>> len(ground.faces), len(bumps.faces), bool(bumps.is_watertight)
    (2, 400, True)
    """
    import trimesh

    from ..synthetic.synthetic_meshes import _int_param, _nonneg_param, _pos_param, validate_mesh

    n_bumps = _int_param(n_bumps, "n_bumps", 1, 500)
    subdivisions = _int_param(subdivisions, "subdivisions", 0, 4)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise IBLError(f"seed: expected a non-negative integer, got {seed!r}")
    size = _pos_param(size, "size")
    gap = _nonneg_param(gap, "gap")
    if isinstance(radii, (str, bytes)) or not hasattr(radii, "__len__") or len(radii) != 2:
        raise IBLError(f"radii: expected two positive numbers (lo, hi), got {radii!r}")
    lo, hi = (_pos_param(r, "radii") for r in radii)
    if lo > hi or 2 * hi >= size:
        raise IBLError(f"radii: need lo <= hi < size/2, got {radii!r} for size {size:g}")
    rng = np.random.default_rng(int(seed))
    placed = []  # (x, y, z, r)
    for k in range(n_bumps):
        for _ in range(200):
            r = rng.uniform(lo, hi)
            x, z = rng.uniform(-size / 2 + r, size / 2 - r, size=2)
            if all(np.hypot(x - q[0], z - q[2]) >= r + q[3] + gap for q in placed):
                placed.append((x, r * rng.uniform(-0.5, 0.9), z, r))
                break
        else:
            raise IBLError(f"bumpy_scene: no room for bump {k + 1} of {n_bumps} on a {size:g} ground "
                           f"(radii {lo:g}-{hi:g}, gap {gap:g}); use fewer or smaller bumps")
    unit = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    radial = unit.vertices / np.linalg.norm(unit.vertices, axis=1, keepdims=True)
    bumps = np.array(placed)
    nv = len(unit.vertices)
    verts = np.concatenate([b[3] * radial + b[:3] for b in bumps])
    faces = np.concatenate([unit.faces + k * nv for k in range(len(bumps))])
    sphere_mesh = trimesh.Trimesh(verts, faces, process=False)
    sphere_mesh.vertex_normals = np.tile(radial, (len(bumps), 1))
    sphere_mesh.metadata["bumps"] = bumps
    return [validate_mesh(_square_ground(size), "ground"), validate_mesh(sphere_mesh, "bumps")]


def normal_mapped_scene(max_tilt_deg: float = 45.0, n_waves: int = 3, wavelengths=(0.3, 0.8), seed: int = 0,
                        size: float = 4.0) -> list:
    """A flat square ground quad whose shading normals a seeded procedural normal map tilts (module docstring).

    Horizon occlusion (Marmoset 2014, "Horizon Occlusion for Normal Mapped Reflections";
    :mod:`ibl_ref.occlusion.horizon_occlusion`) exists for normal-mapped surfaces: the shading normal n leans away
    from the geometric normal n_g, and the mirror direction R = 2(n·v)n − v can dip below the geometric horizon,
    where the surface itself hides the environment.  Here nothing else occludes: the quad is flat and alone, so every
    bit of occlusion is the surface's own half-space below its plane (blocked by the ray caster,
    :class:`ibl_ref.rendering.raycast.ShadowRays`), seen through a tilted lobe.

    Parameters
    ----------
    max_tilt_deg : float
        Largest tilt of the mapped normal from n_g = +y, in [0, 90) degrees; never exceeded
        (:func:`ibl_ref.rendering.normal_map.procedural_normal_map`).  0: the plain quad's normals, bit for bit.
    n_waves : int
        Plane waves of the height field, in [1, 64].
    wavelengths : (float, float)
        Range of their wavelengths (world units), 0 < lo ≤ hi.
    seed : int
        Seed of the waves' directions, wavelengths and phases.
    size : float
        Side of the quad (y = 0, centred at the origin).

    Returns
    -------
    list of trimesh.Trimesh
        ``[ground]``: 2 triangles, one-sided, normal +y; ``metadata["normal_map"]`` holds the
        :class:`~ibl_ref.rendering.normal_map.NormalMap` on the plane y = 0 with tangent frame t = +x, b = −z,
        n_0 = +y.  The map reaches the pixels where the occlusion pipeline rasterizes a scene
        (:func:`ibl_ref.occlusion.image.scene_pixels`); a plain :func:`ibl_ref.rendering.raster.rasterize` ignores it.

    Raises
    ------
    IBLError
        A parameter out of range (one line naming it).

    Examples
    --------
    >>> from ibl_ref.rendering.scenes import normal_mapped_scene
    >>> (ground,) = normal_mapped_scene(max_tilt_deg=40.0, seed=2)
    >>> len(ground.faces), ground.face_normals[0].tolist(), ground.metadata["normal_map"].max_tilt_deg
    (2, [0.0, 1.0, 0.0], 40.0)
    >>> normal_mapped_scene(size=-1.0)
    Traceback (most recent call last):
    ...
    ibl_ref.errors.IBLError: size: must be a positive finite number, got -1.0
    """
    from ..synthetic.synthetic_meshes import _pos_param, validate_mesh
    from .normal_map import METADATA_KEY, procedural_normal_map

    size = _pos_param(size, "size")
    nm = procedural_normal_map(max_tilt_deg, n_waves, wavelengths, seed)
    ground = _square_ground(size)
    ground.metadata[METADATA_KEY] = nm
    return [validate_mesh(ground, "normal-mapped ground")]


#: View of each occlusion scene: (view direction from the target to the eye, eye distance in bounding radii).
_SCENE_VIEWS = {"crevice": ((0.25, 1.0, 0.55), 1.1), "bumpy": ((0.0, 1.0, 0.9), 1.9),
                "normal-mapped": ((0.0, 0.5, 1.0), 0.7)}


def scene_camera(name: str, size: int = 64, meshes=None):
    """The default camera of the occlusion scene ``name`` (a key of :data:`OCCLUSION_SCENES`).

    Parameters
    ----------
    name : str
    size : int
        Image width = height in pixels.
    meshes : the scene's meshes (default: the scene with its default parameters); they set the framing.

    Returns
    -------
    PerspectiveCamera
        ``teapot``: :func:`default_camera` framing the teapot alone (the ground left out of the bounding sphere, as
        in ``ibl-ref experiment method-zoo``).  ``crevice``: looking into the pit from above and in front
        (view direction (0.25, 1, 0.55), target the centre of the pit's mid-depth, eye 1.1 bounding radii away), so
        that its floor, back wall and a side wall are in view.  ``bumpy``: from above at ~42° off the vertical
        (view direction (0, 1, 0.9)), 1.9 bounding radii away, the ground filling the image.  ``normal-mapped``:
        toward the quad's centre from 27° above it (view direction (0, 0.5, 1)), 0.7 bounding radii away, so that
        the view elevation runs from about 13° (the far rows, where the quad's edge leaves a strip of background)
        to 46°: grazing enough for mirror directions to dip below the geometric horizon.  Vertical fov 40°.

    Examples
    --------
    >>> from ibl_ref.rendering.scenes import scene_camera
    >>> cam = scene_camera("crevice", size=16)
    >>> cam.width, cam.height, cam.target.tolist()
    (16, 16, [0.0, -0.25, 0.0])
    """
    factory = _occlusion_factory(name)
    if meshes is None:
        meshes = factory()
    if name not in _SCENE_VIEWS:  # the teapot, framed without its ground (as the method zoo frames it)
        return default_camera(mesh_list(meshes)[:1], size)
    view_dir, distance = _SCENE_VIEWS[name]
    target = None
    if name == "crevice":
        pit = mesh_list(meshes)[0][0].metadata.get("crevice", {"depth": 0.0})
        target = (0.0, -0.5 * pit["depth"], 0.0)
    return default_camera(meshes, size, view_dir=view_dir, distance=distance, target=target)


def _occlusion_factory(name):
    if name not in OCCLUSION_SCENES:
        raise IBLError(f"unknown occlusion scene {name!r}; choose one of {', '.join(OCCLUSION_SCENES)}")
    return OCCLUSION_SCENES[name]


def occlusion_scene(name: str, **params):
    """An occlusion scene and its camera factory: ``(meshes, camera_factory)``.

    Parameters
    ----------
    name : str
        A key of :data:`OCCLUSION_SCENES`: ``"teapot"``, ``"crevice"``, ``"bumpy"`` or ``"normal-mapped"``.
    **params
        Passed to the scene's function (e.g. ``depth=0.8`` for the crevice, ``seed=3`` for the bumps).

    Returns
    -------
    meshes : list
        The scene (see the scene's function; the teapot's is a list of (mesh, material id) pairs).
    camera_factory : callable
        ``camera_factory(size=64)`` → the scene's :func:`scene_camera` framing these meshes.

    Examples
    --------
    >>> from ibl_ref.rendering.scenes import occlusion_scene
    >>> meshes, camera = occlusion_scene("bumpy", n_bumps=8, subdivisions=1)
    >>> len(meshes), camera(24).width
    (2, 24)
    """
    meshes = _occlusion_factory(name)(**params)

    def camera_factory(size: int = 64):
        return scene_camera(name, size, meshes=meshes)

    return meshes, camera_factory


#: The occlusion scenes by name: a function returning the scene's meshes (parameters with defaults).
OCCLUSION_SCENES = {"teapot": teapot_on_ground, "crevice": crevice_scene, "bumpy": bumpy_scene,
                    "normal-mapped": normal_mapped_scene}
