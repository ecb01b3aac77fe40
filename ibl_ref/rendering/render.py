"""Final lighting computation of Knuth et al. (2014), Sec. 3.4, Eq. 5: c = Σ_i VIS_i(x, y) · PEM_i(x, y).

Per pixel the G-buffer (:mod:`ibl_ref.rendering.raster`) gives the world position, the normal and the reflection vector
r = 2(n·v)n − v; "we can use the same sample vector for each PEM" (Sec. 3.4), so every partial environment map
``PEM_i`` is looked up at (r, g) with the material's glossiness g (``lookup_all`` of a region set,
:class:`ibl_ref.prefilter.interface.RegionPrefilters`: the paper's :class:`ibl_ref.knuth2014.pem.PEMSet` or the PEMs
of any Phong prefilter, :func:`ibl_ref.prefilter.registry.build_region_prefilters`), and weighted by the visibility
``VIS_i`` of light i (the region's centroid direction):

* ``visibility="vsm"`` — the paper's method: one variance shadow map per light, blurred according to the
  region's solid angle (:mod:`ibl_ref.rendering.vsm`, Sec. 3.3/4);
* ``visibility="raycast"`` — exact binary visibility of the same directional lights (:mod:`ibl_ref.rendering.raycast`):
  ``exact_backend="binned"`` (default, :func:`ibl_ref.rendering.raycast.parallel_visibility`, fast) or ``"trimesh"``
  (:func:`ibl_ref.rendering.raycast.visibility_to_directions`; slow without Embree).  The difference to "vsm" is the
  shadow-map error alone;
* ``visibility="none"`` — VIS_i = 1, the unshadowed image Σ_i PEM_i (= the full map's lookup, by linearity).

**One Eq. 5 path.**  The pieces are public and every renderer of the package uses them: :func:`eq5_lookups`
(PEM_i(n, 0) and PEM_i(r, g)), :func:`light_visibilities` (VIS_i by any method), :func:`eq5_terms` /
:func:`shade_eq5` (the sum) and :func:`unshadowed_eq5`; :func:`render_pem` composes them, and so do the
comparison modes of Fig. 6 (:func:`ibl_ref.rendering.ao_modes.render_modes`), which differ only in the occlusion model.

**Horizon.**  A light below the tangent plane of the receiving triangle is physically blocked by the surface
itself.  A shadow map does not see this for open surfaces (a ground quad is its own first occluder, so t ≈ μ
and the light counts as visible), and Eq. 5 as printed has no such term.  ``horizon=False`` (default) keeps the
paper's semantics for every method (the binned exact route then only counts *other* geometry, like a shadow map
would); ``horizon=True`` multiplies every VIS_i by [n_face·ω_i > 0] for all methods.  The trimesh route always
includes the receiver's own surface (its rays start on it).  On the teapot-on-ground scene of
``benchmarks/bench_raster.py --render`` this term alone changes the image by ~10 % (mean |Δ| / mean).

**Materials (Eq. 5 with a diffuse and a glossy term).**  With ``materials={id: Material(kd, ks, g)}`` every
pixel is shaded as

    c = Σ_i VIS_i · (kd · PEM_i(n, g = 0) + ks · PEM_i(r, g)),

the diffuse part looked up through the shading normal n at s_Phong = 1 (g = 0, Eq. 3) and the glossy part
through the reflection vector r with the material's g (the paper's "material system" embedded in the PEMs,
Sec. 3.2/3.4).  kd and ks are scalars or RGB triples (per-channel weights); with normalised lobes (the filter
pyramid is a lobe *average*) a constant environment L ≡ c gives exactly (kd + ks)·c.  ``glossiness=`` keeps
its old meaning, kd = 0 and ks = 1 (pure glossy, the paper's Fig. 6 material).

**Glossiness maps** (the paper's garments with varying yarns): ``Material.g_map`` is a 2D image (h, w) of g
values indexed by the mesh's texture coordinates (trimesh ``mesh.visual.uv``, one (u, v) per vertex,
interpolated perspective-correctly with the G-buffer's barycentrics).  Texture convention (OpenGL / trimesh):
u runs left → right over the image columns, v bottom → top over the rows (v = 0 is the *last* row), texel
centres at ((j+½)/w, 1 − (i+½)/h); ``g_map_filter`` ``"bilinear"`` (default) or ``"nearest"``;
``g_map_wrap`` ``"repeat"`` (default, u, v mod 1) or ``"clamp"``.  Meshes **without UVs** (all of
:mod:`ibl_ref.synthetic.synthetic_meshes`) use ``Material.uv_fallback``: ``"planar_xz"`` (default; u = (x − x_min) /
(x_max − x_min), v = (z − z_min) / (z_max − z_min) over the mesh's own bounding box, a top-down projection of
the world position), ``"spherical"`` (u = ½ + atan2(x', z')/2π, v = ½ + asin(y'/|p'|)/π of p' = p − bbox
centre, computed per pixel so there is no interpolation seam) or ``"error"`` (raise :class:`IBLError`).
A prepared :class:`ibl_ref.rendering.raster.Scene` carries no UVs, so it always uses the fallback.

Background pixels (no geometry) are flagged in ``RenderResult.mask``; in ``image`` they are 0
(``background="black"``, default) or the environment seen along the camera ray (``background="env"``: the same
look-up a mirror reflection of that direction gets, :func:`background_image`).  Normals are used as given by the
mesh (not flipped toward the viewer).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import IBLError
from .raster import mesh_list
from .raster import prepare_scene
from .normal_map import apply_normal_maps
from .raster import rasterize

__all__ = ["RenderResult", "Material", "glossiness_image", "material_images", "surface_uv", "mesh_uv", "sample_g_map",
           "render_pem", "resolve_materials", "light_visibilities", "horizon_term", "eq5_lookups", "eq5_terms", "shade_eq5",
           "unshadowed_eq5", "background_image", "apply_background", "VISIBILITY_METHODS", "UV_FALLBACKS",
           "BACKGROUNDS"]

VISIBILITY_METHODS = ("vsm", "raycast", "none")


@dataclass
class RenderResult:
    """Output of :func:`render_pem`.

    Attributes
    ----------
    image : (H, W, C) float64 — Eq. 5 (0 on background).
    unshadowed : (H, W, C) float64 — Σ_i PEM_i (VIS ≡ 1); with materials Σ_i (kd·PEM_i(n, 0) + ks·PEM_i(r, g)).
    visibility : (L, H, W) float64 — VIS_i per light (1 on background).
    mask : (H, W) bool — pixels covered by geometry.
    gbuffer : :class:`ibl_ref.rendering.raster.GBuffer`
    glossiness : (H, W) float64 — g per pixel of the glossy lobe (0 on background).
    method : str — visibility method.
    diffuse, specular : (H, W, C) float64 or None — the two terms of Eq. 5 with materials,
        Σ_i VIS_i·kd·PEM_i(n, 0) and Σ_i VIS_i·ks·PEM_i(r, g) (``image`` is their sum); None when rendered with
        ``glossiness=`` (then ``image`` is the glossy term alone).
    materials : {material_id: Material} used, or None.
    """

    image: np.ndarray
    unshadowed: np.ndarray
    visibility: np.ndarray
    mask: np.ndarray
    gbuffer: object
    glossiness: np.ndarray
    method: str
    diffuse: np.ndarray | None = None
    specular: np.ndarray | None = None
    materials: dict | None = None


def glossiness_image(material_id: np.ndarray, glossiness) -> np.ndarray:
    """Per-pixel g from per-pixel material ids.

    Parameters
    ----------
    material_id : int array, shape (H, W)
        Material id per pixel, negative on background.
    glossiness : float or dict
        One g for all materials, or ``{material_id: g}`` covering every id present on screen; values in [0, 1]
        (g = 1: mirror, Eq. 3).

    Returns
    -------
    ndarray, float64, shape (H, W)
        0 on background.

    Raises
    ------
    IBLError
        A missing material id, a value outside [0, 1].
    """
    mid = np.asarray(material_id)
    out = np.zeros(mid.shape, dtype=np.float64)
    cov = mid >= 0
    if isinstance(glossiness, dict):
        present = np.unique(mid[cov])
        missing = [int(m) for m in present if int(m) not in glossiness]
        if missing:
            raise IBLError(f"glossiness: no value for material id(s) {missing}")
        for m in present:
            out[mid == m] = float(glossiness[int(m)])
    else:
        out[cov] = float(glossiness)
    if np.any(~np.isfinite(out)) or np.any(out < 0) or np.any(out > 1):
        raise IBLError(f"glossiness must be in [0, 1], got {glossiness!r}")
    return out


UV_FALLBACKS = ("planar_xz", "spherical", "error")
G_MAP_FILTERS = ("bilinear", "nearest")
G_MAP_WRAPS = ("repeat", "clamp")


def _weight(x, name: str):
    """kd / ks: a finite non-negative scalar (float) or RGB triple ((3,) float64)."""
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise IBLError(f"Material.{name} must be a number or an RGB triple, got {x!r}") from exc
    if a.ndim == 1 and a.shape == (1,):
        a = a[0]
    if a.ndim not in (0, 1) or (a.ndim == 1 and a.shape != (3,)):
        raise IBLError(f"Material.{name} must be a number or an RGB triple, got shape {a.shape}")
    if np.any(np.isnan(a)) or np.any(~np.isfinite(a)):
        raise IBLError(f"Material.{name} must be finite (no NaN/Inf), got {x!r}")
    if np.any(a < 0):
        raise IBLError(f"Material.{name} must be >= 0, got {x!r}")
    return float(a) if a.ndim == 0 else a


@dataclass
class Material:
    """A material of Eq. 5: diffuse weight ``kd``, glossy weight ``ks``, glossiness ``g`` (Eq. 3), optional g map.

    Parameters
    ----------
    kd, ks : float or RGB triple, >= 0
        Weights of the diffuse lobe (PEM lookup at the normal n with g = 0, s_Phong = 1) and of the glossy lobe
        (lookup at the reflection vector r with glossiness g).  kd + ks <= 1 conserves energy (not enforced).
    g : float in [0, 1]
        Glossiness of the glossy lobe; 0 = diffuse-like (s = 1), 1 = mirror.  Used where there is no g map.
    g_map : array (h, w) or (h, w, 1) in [0, 1], optional
        Per-texel glossiness, indexed by texture coordinates (module docstring: UV convention and fallback).
    g_map_filter : ``"bilinear"`` (default) or ``"nearest"``
    g_map_wrap : ``"repeat"`` (default) or ``"clamp"``
    uv_fallback : ``"planar_xz"`` (default), ``"spherical"`` or ``"error"`` — UVs for meshes that have none.

    Raises
    ------
    IBLError
        g outside [0, 1] or NaN, negative / NaN / Inf kd or ks, a g map that is not 2D or has values outside
        [0, 1], an unknown option.
    """

    kd: object = 0.0
    ks: object = 1.0
    g: float = 0.5
    g_map: np.ndarray | None = field(default=None, repr=False)
    g_map_filter: str = "bilinear"
    g_map_wrap: str = "repeat"
    uv_fallback: str = "planar_xz"

    def __post_init__(self):
        self.kd = _weight(self.kd, "kd")
        self.ks = _weight(self.ks, "ks")
        try:
            g = float(self.g)
        except (TypeError, ValueError) as exc:
            raise IBLError(f"Material.g must be a number in [0, 1], got {self.g!r}") from exc
        if not (0.0 <= g <= 1.0):  # also rejects NaN
            raise IBLError(f"Material.g must be in [0, 1] (0 = diffuse, 1 = mirror), got {self.g!r}")
        self.g = g
        if self.g_map is not None:
            gm = np.asarray(self.g_map, dtype=np.float64)
            if gm.ndim == 3 and gm.shape[2] == 1:
                gm = gm[..., 0]
            if gm.ndim != 2 or gm.size == 0:
                raise IBLError(f"Material.g_map must be a non-empty 2D image (h, w), got shape {gm.shape}")
            if np.any(np.isnan(gm)) or np.any(gm < 0) or np.any(gm > 1):
                bad = gm[np.isnan(gm) | (gm < 0) | (gm > 1)].ravel()[0]
                raise IBLError(f"Material.g_map values must be in [0, 1], got {bad!r}")
            self.g_map = gm
        if self.g_map_filter not in G_MAP_FILTERS:
            raise IBLError(f"Material.g_map_filter must be one of {G_MAP_FILTERS}, got {self.g_map_filter!r}")
        if self.g_map_wrap not in G_MAP_WRAPS:
            raise IBLError(f"Material.g_map_wrap must be one of {G_MAP_WRAPS}, got {self.g_map_wrap!r}")
        if self.uv_fallback not in UV_FALLBACKS:
            raise IBLError(f"Material.uv_fallback must be one of {UV_FALLBACKS}, got {self.uv_fallback!r}")

    @property
    def channels(self) -> int:
        """1 if kd and ks are scalars, 3 if either is an RGB triple."""
        return 3 if (np.ndim(self.kd) or np.ndim(self.ks)) else 1


def _as_material(m, key) -> Material:
    if isinstance(m, Material):
        return m
    if isinstance(m, dict):
        return Material(**m)
    if isinstance(m, (tuple, list)) and len(m) == 3:
        return Material(*m)
    raise IBLError(f"materials[{key!r}]: expected a Material, a (kd, ks, g) tuple or a dict, got {m!r}")


def resolve_materials(materials) -> dict:
    """Materials as ``{material_id: Material}``.

    Parameters
    ----------
    materials : Material, (kd, ks, g) tuple, dict of Material parameters, or mapping
        A single material applies to every id (key None); a mapping ``{material_id: material}`` names each.

    Returns
    -------
    dict

    Raises
    ------
    IBLError
        Keys that are not integers, values that are not materials, invalid material parameters.
    """
    if isinstance(materials, (Material, tuple, list)) or (isinstance(materials, dict) and "g" in materials):
        return {None: _as_material(materials, "*")}
    if not isinstance(materials, dict):
        raise IBLError("materials must be a Material or a mapping material id → Material, "
                       f"got {type(materials).__name__}")
    out = {}
    for k, v in materials.items():
        try:
            kk = int(k)
        except (TypeError, ValueError) as exc:
            raise IBLError(f"materials: keys must be integer material ids, got {k!r}") from exc
        out[kk] = _as_material(v, k)
    return out


def _wrap_index(i, n, wrap):
    return np.mod(i, n) if wrap == "repeat" else np.clip(i, 0, n - 1)


def sample_g_map(g_map, uv, filter: str = "bilinear", wrap: str = "repeat") -> np.ndarray:
    """Sample a 2D g map at texture coordinates.

    Convention (OpenGL / trimesh): u → columns left to right, v → rows bottom to top; texel (i, j) centre at
    (u, v) = ((j+½)/w, 1 − (i+½)/h).  A bilinear blend of values in [0, 1] stays in [0, 1].

    Parameters
    ----------
    g_map : array_like, shape (h, w) or (h, w, 1)
    uv : array_like, shape (..., 2)
    filter : {"bilinear", "nearest"}
    wrap : {"repeat", "clamp"}

    Returns
    -------
    ndarray, float64, shape (...)

    Raises
    ------
    IBLError
        A g map that is not 2D, an unknown filter.

    Examples
    --------
    The bottom row of a 2 × 2 map is v = 0.25, its left column u = 0.25:

    >>> from ibl_ref.rendering.render import sample_g_map
    >>> sample_g_map([[0.0, 0.2], [0.6, 1.0]], [[0.25, 0.25], [0.5, 0.25], [0.75, 0.75]])
    array([0.6, 0.8, 0.2])
    """
    gm = np.asarray(g_map, dtype=np.float64)
    if gm.ndim == 3 and gm.shape[2] == 1:
        gm = gm[..., 0]
    if gm.ndim != 2:
        raise IBLError(f"g map must be 2D, got shape {gm.shape}")
    h, w = gm.shape
    uv = np.asarray(uv, dtype=np.float64)
    x = uv[..., 0] * w - 0.5  # continuous column coordinate (texel centres at integers)
    y = (1.0 - uv[..., 1]) * h - 0.5  # continuous row coordinate, v = 1 at the top row
    if filter == "nearest":
        return gm[_wrap_index(np.floor(y + 0.5).astype(np.int64), h, wrap),
                  _wrap_index(np.floor(x + 0.5).astype(np.int64), w, wrap)]
    if filter != "bilinear":
        raise IBLError(f"g map filter must be one of {G_MAP_FILTERS}, got {filter!r}")
    x0, y0 = np.floor(x), np.floor(y)
    tx, ty = x - x0, y - y0
    j0, i0 = x0.astype(np.int64), y0.astype(np.int64)
    j0, j1 = _wrap_index(j0, w, wrap), _wrap_index(j0 + 1, w, wrap)
    i0, i1 = _wrap_index(i0, h, wrap), _wrap_index(i0 + 1, h, wrap)
    top = gm[i0, j0] * (1 - tx) + gm[i0, j1] * tx
    bot = gm[i1, j0] * (1 - tx) + gm[i1, j1] * tx
    return np.clip(top * (1 - ty) + bot * ty, 0.0, 1.0)  # clip: rounding only


def mesh_uv(mesh, name="mesh 0"):
    """Per-vertex texture coordinates of a trimesh mesh.

    Parameters
    ----------
    mesh : trimesh.Trimesh
    name : str, optional
        Names the mesh in messages.

    Returns
    -------
    ndarray, float64, shape (V, 2), or None
        None when the mesh has no (complete) UVs.

    Raises
    ------
    IBLError
        NaN/Inf UVs (broken data, not missing UVs: no silent fallback).
    """
    uv = getattr(getattr(mesh, "visual", None), "uv", None)
    if uv is None:
        return None
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape != (len(mesh.vertices), 2):
        return None
    bad = int(np.sum(~np.all(np.isfinite(uv), axis=1)))
    if bad:
        raise IBLError(f"{name}: {bad} of its {len(uv)} texture coordinates are NaN or Inf, so its g map cannot "
                       "be looked up; fix the mesh's UVs (or remove them to use uv_fallback='planar_xz' or "
                       "uv_fallback='spherical')")
    return uv


def surface_uv(meshes, scene, gbuffer, pixels, fallback: str = "planar_xz") -> np.ndarray:
    """Texture coordinates of covered pixels.

    Meshes with UVs (trimesh ``visual.uv``): perspective-correct interpolation of the per-vertex UVs with the
    G-buffer's barycentrics.  Others: ``fallback`` (module docstring) from the pixel's world position, with the
    bounding box of the mesh the pixel belongs to.

    Parameters
    ----------
    meshes : mesh(es) as given to :func:`render_pem`
    scene : :class:`ibl_ref.rendering.raster.Scene`
        The prepared scene of ``meshes``.
    gbuffer : :class:`ibl_ref.rendering.raster.GBuffer`
    pixels : bool array, shape (H, W)
        Pixels inside ``gbuffer.mask``.
    fallback : {"planar_xz", "spherical", "error"}

    Returns
    -------
    ndarray, float64, shape (n, 2)
        In row-major order of ``pixels``.

    Raises
    ------
    IBLError
        A mesh without UVs with ``fallback="error"``, NaN UVs, an unknown fallback.
    """

    if fallback not in UV_FALLBACKS:
        raise IBLError(f"uv fallback must be one of {UV_FALLBACKS}, got {fallback!r}")
    items = mesh_list(meshes)
    meshes_of = None if hasattr(items, "faces") and hasattr(items, "mesh_index") else [m for m, _ in items]
    tri = gbuffer.triangle_id[pixels]
    lam = gbuffer.barycentric[pixels]
    P = gbuffer.position[pixels]
    midx = scene.mesh_index[tri]
    uv = np.full((len(tri), 2), np.nan)
    for k in np.unique(midx):
        sel = midx == k
        mesh = meshes_of[k] if meshes_of is not None else None
        muv = mesh_uv(mesh, f"mesh {int(k)}") if mesh is not None else None
        if muv is not None:
            fv = np.asarray(mesh.faces)[scene.source_face[tri[sel]]]  # same vertex order as scene.faces
            uv[sel] = np.einsum("nk,nkc->nc", lam[sel], muv[fv])
            continue
        if fallback == "error":
            raise IBLError(f"mesh {int(k)} has no texture coordinates (mesh.visual.uv) for its g map; "
                           "give the mesh UVs or choose uv_fallback='planar_xz' or uv_fallback='spherical'")
        if mesh is not None:
            V = np.asarray(mesh.vertices, dtype=np.float64)
        else:
            V = scene.vertices[np.unique(scene.faces[scene.mesh_index == k])]
        lo, hi = V.min(axis=0), V.max(axis=0)
        p = P[sel]
        if fallback == "planar_xz":
            ext = np.where(hi - lo > 0, hi - lo, 1.0)
            uv[sel, 0] = (p[:, 0] - lo[0]) / ext[0]
            uv[sel, 1] = (p[:, 2] - lo[2]) / ext[2]
        else:  # spherical, around the bounding-box centre, per pixel (no interpolation seam)
            q = p - 0.5 * (lo + hi)
            rho = np.linalg.norm(q, axis=1)
            uv[sel, 0] = 0.5 + np.arctan2(q[:, 0], q[:, 2]) / (2 * np.pi)
            uv[sel, 1] = 0.5 + np.arcsin(np.clip(q[:, 1] / np.where(rho > 0, rho, 1.0), -1, 1)) / np.pi
    return uv


def material_images(meshes, scene, gbuffer, materials: dict):
    """Per-pixel material weights and glossiness of the covered pixels, in ``gbuffer.mask`` order.

    Parameters
    ----------
    meshes, scene, gbuffer
        As :func:`surface_uv`.
    materials : dict
        As returned by :func:`resolve_materials` (key None = every material id).

    Returns
    -------
    kd, ks : ndarray, shape (n, K)
        K = 1, or 3 when a material has RGB weights.
    g : ndarray, shape (n,)

    Raises
    ------
    IBLError
        A material id on screen without a material.
    """
    m = gbuffer.mask
    mid = gbuffer.material_id[m]
    n = len(mid)
    K = max([mat.channels for mat in materials.values()] + [1])
    kd = np.zeros((n, K))
    ks = np.zeros((n, K))
    g = np.zeros(n)
    present = np.unique(mid)
    if None not in materials:
        missing = [int(x) for x in present if int(x) not in materials]
        if missing:
            raise IBLError(f"materials: no Material for material id(s) {missing}")
    for x in present:
        mat = materials.get(None, materials.get(int(x)))
        sel = mid == x
        kd[sel] = mat.kd
        ks[sel] = mat.ks
        if mat.g_map is None:
            g[sel] = mat.g
        else:
            pix = np.zeros_like(m)
            idx = np.flatnonzero(m.ravel())[sel]
            pix.ravel()[idx] = True
            uv = surface_uv(meshes, scene, gbuffer, pix, mat.uv_fallback)
            # pixels of ``pix`` in row-major order == order of ``idx`` (both follow the flattened mask)
            g[sel] = sample_g_map(mat.g_map, uv, mat.g_map_filter, mat.g_map_wrap)
    return kd, ks, g


BACKGROUNDS = ("black", "env")


def light_visibilities(scene, points, face_normals, lights, *, method: str = "vsm", vsm_resolution: int = 256,
                       vsm_dtype: str = "float32", horizon: bool | None = None, exact_backend: str = "binned",
                       timings: dict | None = None, progress: bool = False, **vsm_kw) -> np.ndarray:
    """VIS_i (L, P) of Eq. 5 for every light at surface points: ``"vsm"`` (Sec. 3.3), ``"raycast"`` or ``"none"``.

    Parameters
    ----------
    scene : meshes or a prepared :class:`ibl_ref.rendering.raster.Scene`
    points, face_normals : array_like, shape (P, 3)
        Surface points and the geometric normals of their triangles.
    lights : LightSet
        Anything with ``.directions`` (L, 3) and ``.solid_angle`` (L,) (a median-cut ``LightSet``).
    method : {"vsm", "raycast", "none"}
        ``"vsm"`` — one variance shadow map per light, blurred from its solid angle
        (:func:`ibl_ref.rendering.vsm.build_vsm`, ``vsm_resolution``, ``vsm_dtype`` and ``**vsm_kw``: ``occluder_distance``,
        ``depth_bias``, ``min_variance``, ``bleed_reduction``); ``"raycast"`` — exact binary visibility of the same
        directional lights (``exact_backend="binned"``: :func:`ibl_ref.rendering.raycast.parallel_visibility`;
        ``"trimesh"``: :func:`ibl_ref.rendering.raycast.visibility_to_directions`); ``"none"`` — VIS_i = 1.
    vsm_resolution : int
        Shadow-map size.
    vsm_dtype : str
        Shadow-map storage dtype.
    exact_backend : {"binned", "trimesh"}
        Ray caster of ``"raycast"``.
    horizon : bool or None
        The receiver's own surface (a light at or below the receiving triangle's plane, n_face·ω_i ≤ 0).
        ``None`` (default): each method's own behaviour — the exact casters include it (a ray from the surface
        finds the surface), a shadow map and ``"none"`` do not; ``True``: multiply every VIS_i by
        [n_face·ω_i > 0] for every method; ``False``: the binned caster counts only *other* geometry, like a
        shadow map (the trimesh route always includes the receiver: its rays start on it).
    timings : dict, optional
        Adds seconds per stage: ``shadow_maps`` (depth rendering), ``blur`` (moments and Gaussian blur),
        ``visibility`` (look-ups or ray casts).
    progress : bool
        Report progress over lights (:mod:`ibl_ref.progress`).
    **vsm_kw
        ``occluder_distance``, ``depth_bias``, ``min_variance``, ``bleed_reduction`` of
        :func:`ibl_ref.rendering.vsm.build_vsm`.

    Returns
    -------
    ndarray, float64, shape (L, P)
        VIS_i at every point, in [0, 1].

    Raises
    ------
    IBLError
        An unknown method or backend.
    """
    import time

    if method not in VISIBILITY_METHODS:
        raise IBLError(f"visibility method must be one of {VISIBILITY_METHODS}, got {method!r}")
    if exact_backend not in ("binned", "trimesh"):
        raise IBLError(f"exact_backend must be 'binned' or 'trimesh', got {exact_backend!r}")
    dirs = np.asarray(lights.directions, dtype=np.float64).reshape(-1, 3)
    omega = np.asarray(lights.solid_angle, dtype=np.float64).reshape(-1)
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    fn = None if face_normals is None else np.asarray(face_normals, dtype=np.float64).reshape(-1, 3)
    L = len(dirs)
    V = np.ones((L, len(P)))
    if len(P) == 0:
        return V

    def _tick(key, t0):
        if timings is not None:
            timings[key] = timings.get(key, 0.0) + time.perf_counter() - t0

    if method == "raycast":
        t0 = time.perf_counter()
        if exact_backend == "trimesh":
            from .raycast import visibility_to_directions

            V = visibility_to_directions(scene, P, fn, dirs, progress=progress).T
        else:
            from .raycast import parallel_visibility

            V = parallel_visibility(scene, P, dirs, normals=None if horizon is False else fn, progress=progress).T
        _tick("visibility", t0)
    elif method == "vsm":
        from . import vsm as _vsm
        from .raster import prepare_scene

        sc = prepare_scene(scene, warn=False)
        from ..progress import track

        for i in track(range(L), "shadow maps", unit="light", enabled=progress):
            sm = _vsm.build_vsm(sc, dirs[i], omega[i], resolution=vsm_resolution, dtype=vsm_dtype, timings=timings,
                                **vsm_kw)
            t0 = time.perf_counter()
            V[i] = _vsm.visibility(P, sm)
            _tick("visibility", t0)
    if horizon:
        V = V * horizon_term(fn, dirs)
    return V


def horizon_term(face_normals, directions) -> np.ndarray:
    """[n_face·ω_i > 0]: 1 where light i is above the receiving triangle's plane (``horizon=True`` of
    :func:`light_visibilities` multiplies every VIS_i by it; module docstring "Horizon").

    Parameters
    ----------
    face_normals : array_like, shape (P, 3)
    directions : array_like, shape (L, 3)

    Returns
    -------
    ndarray, float64, shape (L, P)
    """
    fn = np.asarray(face_normals, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    return (fn @ d.T > 0).T.astype(np.float64)


def eq5_lookups(pems, normals, reflect, g, kd, ks):
    """The PEM look-ups of Eq. 5: ``(PEM_i(n, g=0), PEM_i(r, g))``, each (L, P, C) float64 or None.

    "We can use the same sample vector for each PEM" (Sec. 3.4): the diffuse lobe through the normal n at
    g = 0 (s_Phong = 1, Eq. 3), the glossy lobe through the reflection vector r at the material's g.  A term is
    looked up only where its weight is non-zero somewhere; with kd = ks = 0 the glossy one is looked up anyway
    (black image, but the channel count is kept).

    Parameters
    ----------
    pems : region set
        ``.lights`` and ``.lookup_all(dirs, g) -> (L, P, C)`` (:class:`ibl_ref.prefilter.interface.RegionPrefilters`).
    normals, reflect : array_like, shape (P, 3)
        Shading normals n and reflection vectors r.
    g : float or array_like, shape (P,)
        Glossiness of the glossy lobe.
    kd, ks : float or array_like, shape (P, K)
        Material weights.

    Returns
    -------
    pem_n, pem_r : ndarray, shape (L, P, C), or None
        None for a term that is not looked up.

    Raises
    ------
    IBLError
        ``lookup_all`` returned another shape.
    """
    L = len(np.asarray(pems.lights.directions).reshape(-1, 3))
    n_px = len(np.asarray(reflect).reshape(-1, 3))

    def _lookup(dirs, gg):
        vals = np.asarray(pems.lookup_all(dirs, gg), dtype=np.float64)  # (L, P, C)
        if vals.ndim != 3 or vals.shape[:2] != (L, n_px):
            raise IBLError(f"pems.lookup_all returned shape {vals.shape}, expected ({L}, {n_px}, C)")
        return vals

    pem_n = _lookup(normals, 0.0) if np.any(np.asarray(kd) > 0) else None
    pem_r = _lookup(reflect, g) if (np.any(np.asarray(ks) > 0) or pem_n is None) else None
    return pem_n, pem_r


def eq5_terms(vis, pem_n, pem_r, kd, ks):
    """The two terms of Eq. 5, Σ_i VIS_i·kd·PEM_i(n, 0) and Σ_i VIS_i·ks·PEM_i(r, g), each (P, C) or None.

    The weights do not depend on the light, so kd·Σ_i VIS_i PEM_i = Σ_i VIS_i kd PEM_i.

    Parameters
    ----------
    vis : array_like, shape (L, P)
        VIS_i per light and pixel.
    pem_n, pem_r : array_like, shape (L, P, C), or None
        The look-ups (:func:`eq5_lookups`); None: the term is absent.
    kd, ks : float or array_like, shape (P, K)
        Material weights (K = 1 or C).

    Returns
    -------
    diffuse, specular : ndarray, shape (P, C), or None
    """
    diffuse = None if pem_n is None else kd * np.einsum("lp,lpc->pc", vis, pem_n)
    specular = None if pem_r is None else ks * np.einsum("lp,lpc->pc", vis, pem_r)
    return diffuse, specular


def shade_eq5(vis, pem_n, pem_r, kd, ks) -> np.ndarray:
    """Eq. 5 with a kd/ks material: c = Σ_i VIS_i · (kd·PEM_i(n, 0) + ks·PEM_i(r, g)).

    The one implementation of Eq. 5: :func:`render_pem` and every mode of :mod:`ibl_ref.rendering.ao_modes` call it.

    Parameters
    ----------
    vis : array_like, shape (L, P)
        Visibility VIS_i of light i at pixel p, in [0, 1].
    pem_n, pem_r : array_like, shape (L, P, C), or None
        PEM_i(n, 0) and PEM_i(r, g) (:func:`eq5_lookups`); a term whose weight is 0 may be None.
    kd, ks : float or array_like, shape (P, K)
        Diffuse and glossy weights (K = 1 or C).

    Returns
    -------
    ndarray, shape (P, C)
        The shaded colour c.

    Examples
    --------
    Two lights, three pixels; the first pixel sees both lights, the others one each:

    >>> import numpy as np
    >>> from ibl_ref.rendering.render import shade_eq5
    >>> vis = np.array([[1.0, 0.0, 1.0],
    ...                 [1.0, 1.0, 0.0]])
    >>> pem_n = np.full((2, 3, 1), 0.5)  # the diffuse look-up of each light's PEM
    >>> pem_r = np.full((2, 3, 1), 2.0)  # the glossy look-up
    >>> shade_eq5(vis, pem_n, pem_r, kd=0.2, ks=0.8)  # per light 0.2·0.5 + 0.8·2 = 1.7
    array([[3.4],
           [1.7],
           [1.7]])
    """
    kd_on = pem_n is not None and np.any(np.asarray(kd) > 0)
    ks_on = pem_r is not None and np.any(np.asarray(ks) > 0)
    diffuse, specular = eq5_terms(vis, pem_n if kd_on else None, pem_r if ks_on else None, kd, ks)
    if diffuse is None and specular is None:
        ref = pem_r if pem_r is not None else pem_n
        return np.zeros(ref.shape[1:])
    return specular if diffuse is None else (diffuse if specular is None else diffuse + specular)


def unshadowed_eq5(pem_n, pem_r, kd, ks) -> np.ndarray:
    """Eq. 5 with VIS ≡ 1: kd·Σ_i PEM_i(n, 0) + ks·Σ_i PEM_i(r, g) (= the full map's look-ups, Sec. 3.1).

    Parameters
    ----------
    pem_n, pem_r, kd, ks
        As :func:`shade_eq5`.

    Returns
    -------
    ndarray, shape (P, C)
    """
    parts = [w * p.sum(axis=0) for w, p in ((kd, pem_n), (ks, pem_r)) if p is not None and np.any(np.asarray(w) > 0)]
    if not parts:
        ref = pem_r if pem_r is not None else pem_n
        return np.zeros(ref.shape[1:])
    return parts[0] if len(parts) == 1 else parts[0] + parts[1]


def background_image(camera, source, shape=None) -> np.ndarray:
    """The environment seen behind the scene: radiance (H, W, C) along every camera ray.

    ``source`` is a radiance cube (6, N, N, C) (seam-aware bilinear look-up, :func:`ibl_ref.environment.sampling.sample_bilinear`)
    or a PEM set (Σ_i PEM_i(d, g = 1): the pyramid's mirror look-up, level 0 bilinear, which by linearity is the
    same look-up of the full map).  Either way it is the look-up a mirror (g = 1) reflection of that direction
    gets, so a mirror ball reflects exactly the backdrop.

    Parameters
    ----------
    camera : camera of :mod:`ibl_ref.rendering.camera`
    source : Environment, array_like (6, N, N[, C]) or region set
    shape : tuple, optional
        Unused (the camera's size is the image's).

    Returns
    -------
    ndarray, float64, shape (H, W, C)
    """
    _, d = camera.pixel_rays()
    H, W = d.shape[:2]
    d = d.reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    if hasattr(source, "lookup_all"):
        vals = np.asarray(source.lookup_all(d, 1.0), dtype=np.float64).sum(axis=0)
    else:
        from ..environment.sampling import sample_bilinear

        cube = np.asarray(source, dtype=np.float64)
        if cube.ndim == 3:
            cube = cube[..., None]
        vals = sample_bilinear(cube, d)
    return vals.reshape(H, W, -1)


def apply_background(image, mask, camera, source, background: str = "black") -> np.ndarray:
    """Fill the pixels outside ``mask`` with a backdrop.

    Parameters
    ----------
    image : ndarray, shape (H, W, C)
        Changed in place.
    mask : bool array, shape (H, W)
        Pixels covered by geometry (left as they are).
    camera, source
        As :func:`background_image`.
    background : {"black", "env"}
        ``"black"``: leave 0; ``"env"``: :func:`background_image` of ``source``.

    Returns
    -------
    ndarray
        ``image``.

    Raises
    ------
    IBLError
        An unknown background, a channel mismatch.
    """
    if background not in BACKGROUNDS:
        raise IBLError(f"background must be one of {BACKGROUNDS}, got {background!r}")
    if background == "env" and not np.all(mask):
        bg = background_image(camera, source)
        if bg.shape[-1] not in (1, image.shape[-1]):
            raise IBLError(f"background has {bg.shape[-1]} channels, the image {image.shape[-1]}")
        image[~mask] = np.broadcast_to(bg, image.shape)[~mask]
    return image


def render_pem(
    meshes,
    camera,
    pems,
    glossiness=None,
    *,
    materials=None,
    visibility: str = "vsm",
    vsm_resolution: int = 512,
    vsm_dtype: str = "float32",
    occluder_distance: float | None = None,
    depth_bias: float = 1e-3,
    min_variance: float = 1e-6,
    bleed_reduction: float = 0.0,
    smooth_normals: bool = True,
    exact_backend: str = "binned",
    horizon: bool = False,
    background: str = "black",
    progress: bool = False,
) -> RenderResult:
    """Render Eq. 5 for a scene lit by a set of partial environment maps.

    Parameters
    ----------
    meshes : trimesh.Trimesh, list of meshes or Scene
        See :func:`ibl_ref.rendering.raster.prepare_scene`; a mesh that carries a normal map
        (``mesh.metadata["normal_map"]``) is shaded with its perturbed normals and their reflections
        (:func:`ibl_ref.rendering.normal_map.apply_normal_maps`), the shadows are those of its geometry.
    camera : PerspectiveCamera or OrthographicCamera
        :mod:`ibl_ref.rendering.camera`.
    pems : region set
        ``.lights`` with ``directions`` (L, 3) and ``solid_angle`` (L,), ``.lookup_all(dirs, g) -> (L, ..., C)``
        (:class:`ibl_ref.prefilter.interface.RegionPrefilters`): the paper's PEMs
        (:func:`ibl_ref.knuth2014.pem.build_pems`, or ``build_region_prefilters(cube, method="pyramid",
        n_lights=24)`` of :mod:`ibl_ref.prefilter.registry`) or any other ``--prefilter`` method.
    glossiness : float or {material_id: g}, default 0.5
        Pure glossy material (kd = 0, ks = 1) with this g: c = Σ_i VIS_i · PEM_i(r, g).  Not with ``materials``.
    materials : Material, (kd, ks, g) tuple, or {material_id: Material}, optional
        Eq. 5 with a diffuse and a glossy term, c = Σ_i VIS_i · (kd·PEM_i(n, 0) + ks·PEM_i(r, g)), optional
        per-texel g maps (module docstring).  A single Material applies to every material id.
    visibility : {"vsm", "raycast", "none"}
        The paper's variance shadow maps, exact binary visibility of the same lights, or none.
    vsm_resolution, vsm_dtype, occluder_distance, depth_bias, min_variance, bleed_reduction
        Passed to :func:`ibl_ref.rendering.vsm.build_vsm` (one map per light, blur from its solid angle).
    smooth_normals : bool
        Interpolated vertex normals (True) or face normals.
    exact_backend : {"binned", "trimesh"}
        Ray caster of ``visibility="raycast"``.
    horizon : bool
        Multiply VIS_i by [n_face·ω_i > 0] (see module docstring); default False (paper).
    background : {"black", "env"}
        ``"black"`` (default: 0 outside the geometry) or the environment seen along each camera ray
        (:func:`background_image`: the PEMs' mirror look-up), only in ``image``.
    progress : bool
        Report progress over lights (:mod:`ibl_ref.progress`).

    Returns
    -------
    RenderResult

    Raises
    ------
    IBLError
        An unknown option, both ``glossiness`` and ``materials``, invalid materials, a render that overflows.
    MeshError
        Invalid meshes.

    Examples
    --------
    A sphere on a plane under a constant sky L ≡ 2, six PEMs, exact visibility.  The filtered lobes are
    normalised, so the unshadowed image is the constant itself (to the float32 storage of the PEMs), and the
    shadows only take light away:

    >>> import numpy as np
    >>> from ibl_ref.knuth2014.pem import build_pems
    >>> from ibl_ref.rendering.camera import PerspectiveCamera
    >>> from ibl_ref.rendering.render import render_pem
    >>> from ibl_ref.synthetic.synthetic_envs import make_environment
    >>> from ibl_ref.synthetic.synthetic_meshes import make_mesh
    >>> pems = build_pems(make_environment("constant", 16, value=2.0), n_lights=6)
    >>> scene = make_mesh("sphere_on_plane", subdivisions=2, plane_res=4)
    >>> camera = PerspectiveCamera(eye=(0.0, 3.0, 6.0), target=(0.0, 0.8, 0.0), up=(0.0, 1.0, 0.0),
    ...                            fov_y_deg=40.0, width=32, height=24)
    >>> result = render_pem(scene, camera, pems, glossiness=0.7, visibility="raycast")
    >>> result.image.shape, result.visibility.shape
    ((24, 32, 3), (6, 24, 32))
    >>> m = result.mask
    >>> bool(np.allclose(result.unshadowed[m], 2.0, rtol=1e-6)), bool(np.all(result.image[m] <= result.unshadowed[m]))
    (True, True)
    """

    if visibility not in VISIBILITY_METHODS:
        raise IBLError(f"visibility must be one of {VISIBILITY_METHODS}, got {visibility!r}")
    if exact_backend not in ("binned", "trimesh"):
        raise IBLError(f"exact_backend must be 'binned' or 'trimesh', got {exact_backend!r}")
    if background not in BACKGROUNDS:
        raise IBLError(f"background must be one of {BACKGROUNDS}, got {background!r}")
    lights = getattr(pems, "lights", None)
    if lights is None or not hasattr(pems, "lookup_all"):
        raise IBLError("pems: expected partial environment maps, an ibl_ref.knuth2014.pem.PEMSet or any region set "
                       "of ibl_ref.prefilter (RegionPrefilters: .lights and .lookup_all), e.g. "
                       "ibl_ref.prefilter.build_region_prefilters(cube, n_lights=24)")
    L = len(np.asarray(lights.directions, dtype=np.float64).reshape(-1, 3))
    scene = prepare_scene(meshes)
    if materials is not None and glossiness is not None:
        raise IBLError("give either glossiness= (pure glossy, kd = 0, ks = 1) or materials=, not both")
    mats = resolve_materials(materials) if materials is not None else None
    if glossiness is None:
        glossiness = 0.5
    g = apply_normal_maps(meshes, scene, rasterize(scene, camera, smooth_normals=smooth_normals))
    H, W = g.mask.shape
    m = g.mask
    P = g.position[m]
    if mats is None:  # pure glossy: kd = 0, ks = 1
        gl = glossiness_image(g.material_id, glossiness)
        kd_px, ks_px, g_px = 0.0, 1.0, gl[m]
    else:
        kd_px, ks_px, g_px = material_images(meshes, scene, g, mats)
        gl = np.zeros((H, W))
        gl[m] = g_px
    pem_n, pem_r = eq5_lookups(pems, g.normal[m], g.reflect[m], g_px, kd_px, ks_px)
    C = (pem_r if pem_r is not None else pem_n).shape[2]
    if np.ndim(kd_px) == 2 and kd_px.shape[1] not in (1, C):
        raise IBLError(f"RGB material weights need 3-channel PEMs, the PEMs have {C} channel(s)")
    vsm_kw = dict(occluder_distance=occluder_distance, depth_bias=depth_bias, min_variance=min_variance,
                  bleed_reduction=bleed_reduction)
    vis = light_visibilities(scene, P, g.face_normal[m], lights, method=visibility, vsm_resolution=vsm_resolution,
                             vsm_dtype=vsm_dtype, horizon=bool(horizon), exact_backend=exact_backend,
                             progress=progress, **vsm_kw)
    diffuse, specular = eq5_terms(vis, pem_n, pem_r, kd_px, ks_px)  # Eq. 5, term by term
    c = specular if diffuse is None else (diffuse if specular is None else diffuse + specular)
    image = np.zeros((H, W, C))
    image[m] = c
    unshadowed = np.zeros((H, W, C))
    unshadowed[m] = unshadowed_eq5(pem_n, pem_r, kd_px, ks_px) if mats is not None else pem_r.sum(axis=0)
    vis_img = np.ones((L, H, W))
    vis_img[:, m] = vis
    if not np.all(np.isfinite(image)):
        big = max(float(np.max(t[np.isfinite(t)], initial=0.0)) for t in (diffuse, specular) if t is not None)
        raise IBLError(f"render produced non-finite values: material weight x radiance overflows float64 (largest "
                       f"finite shaded term {big:g}); use smaller material weights kd, ks (--material) or a dimmer map")
    parts = {}
    if mats is not None:
        for name, vals in (("diffuse", diffuse), ("specular", specular)):
            img = np.zeros((H, W, C))
            if vals is not None:
                img[m] = vals
            parts[name] = img
    apply_background(image, m, camera, pems, background)
    return RenderResult(image=image, unshadowed=unshadowed, visibility=vis_img, mask=m, gbuffer=g,
                        glossiness=gl, method=visibility, materials=mats, **parts)
