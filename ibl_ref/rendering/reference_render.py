"""Ray-traced ground truth of image-based lighting with self-shadowing: Knuth et al. (2014) Eq. 5 without
approximation, for Phong (kd, ks, g) and GGX microfacet materials (Sec. 3.4, Fig. 6).

The paper's renderer approximates, per pixel,

    c = Σ_i VIS_i · (kd·PEM_i(n, g=0) + ks·PEM_i(r, g))                                     (Eq. 5, kd/ks form)

with shadow-mapped visibilities of one directional light per median-cut region and filtered partial environment
maps.  The exact quantity it approximates is the visibility-weighted Phong lobe average (Eq. 4 normalised as a
lobe average, docs/background.md §2)::

    c = kd · A_1(n) + ks · A_s(r),   A_s(d) = ∫ L V max(d·ω, 0)^s [n·ω > 0] dω / ∫ max(d·ω, 0)^s dω          (*)

with ``s = 1/(1−g)`` (Eq. 3), ``r = 2(n·v)n − v`` and V the exact binary visibility of direction ω from the
surface point.  A GGX material (:class:`ibl_ref.rendering.materials.GGXMaterial`) gives
``c = kd·A_1(n) + ∫ L V f_s(ω, v) (n·ω) [n·ω > 0] dω`` with the GGX term f_s of :func:`ibl_ref.lobes.brdfs.ggx`
(α = roughness², :func:`ibl_ref.conventions.ggx_alpha`).  :mod:`ibl_ref.rendering.materials` defines the materials
and the weight of every lobe once; :mod:`ibl_ref.rendering.reference_converged` is the one integrator: each lobe
converged to a tolerance (``render_reference(..., rtol=2e-3)``) — the radiance × lobe quadrature at the texel
centres of the face sizes the tolerance needs (graded per cell for GGX), and a stratified, adaptively refined
visibility (one shadow ray per direction cell toward a random point of the cell above the shading horizon, cells
split 2×2 where weight × possible change is largest next to a shadow edge) — with an error estimate per image
(``info["err_rel_l1"]``, a bound on the expected rel. L1) and a per-pixel bound (``ReferenceResult.error``, holding
with probability ≥ 1 − 1e-3 per pixel; its 99th percentile relative to max(pixel value, 10 % of the mean) is
``info["err_rel_p99"]``); that module's docstring gives the definitions and the memory bound.  The mirror
(g = 1) is exact: one ray along r, radiance of the map's nearest texel at r.  Shadow rays: Embree when ``embreex``
is installed (every hit re-checked in float64), the package's float64 casters otherwise
(:class:`ibl_ref.rendering.raycast.ShadowRays`).  The pixels run in fixed blocks (``workers=`` / ``executor=``:
:func:`ibl_ref.executors.map_jobs`), bit-identical wherever they run.  Conventions (docs/background.md §8):
one-sided shading (n·v ≤ 0 → black, ``sided="two"`` flips n), the lobes over the hemisphere Ω⁺ of the shading
normal n (a Phong lobe normalised over the whole sphere: the normalised Phong BRDF of Kán et al. 2015, Eq. 2),
one material per mesh.

Entry points: :func:`render_reference` (an image through a camera) and :func:`reference_shading` (given surface
points, normals and view directions with one material: what a prefilter method is compared against).

Also here, the coarse-level tools that the prefilter experiments compare against (unoccluded, V ≡ 1):
:func:`lobe_average` (the exact Eq. 4 lobe average of a coarse level at any direction), :func:`coarse_directions`,
:func:`env_size_for_exponent`, :func:`coarse_level_error`, :func:`exact_pem_lookup`, and
:func:`parallel_visibility` (the package's exact parallel-ray caster in this module's argument order).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..conventions import lobe_half_angle
from ..errors import IBLError, LayoutError
from .reference_converged import (DEFAULT_RTOL, ERR_FLOOR, check_environment, coarse_env,
                                  converged_shading)
from ..environment.envmap import cube_solid_angles
from ..environment.envmap import texel_directions
from ..environment.sampling import sample_nearest
from ..groundtruth.phong_convolution import lobe_average as _lobe_average
from ..limits import check_rtol
from .materials import as_material
from .raster import prepare_scene
from .normal_map import apply_normal_maps
from .raster import rasterize
from .raycast import ShadowRays
from .raycast import parallel_visibility as _cast
from .reference_converged import MAX_BLOCK_CELLS

__all__ = [
    "ReferenceResult",
    "coarse_directions",
    "env_size_for_exponent",
    "lobe_average",
    "parallel_visibility",
    "reference_shading",
    "render_reference",
    "coarse_level_error",
    "exact_pem_lookup",
]

DIRECTION_MODES = ("centroid", "centre")
SIDED = ("one", "two")


# ------------------------------------------------------------------------------------------------
# coarse levels (unoccluded lobe averages for the prefilter comparisons)
# ------------------------------------------------------------------------------------------------
def coarse_directions(cube, n_env: int, mode: str = "centroid") -> np.ndarray:
    """Quadrature directions ω_j (6, n, n, 3) of the coarse level: texel centres or energy centroids.

    ``"centroid"``: normalize(Σ_f Y_f Ω_f ω_f) over the fine texels f (Y = mean over channels); texels with no
    energy use the solid-angle centroid Σ_f Ω_f ω_f.
    """

    if mode not in DIRECTION_MODES:
        raise IBLError(f"directions must be one of {DIRECTION_MODES}, got {mode!r}")
    if mode == "centre":
        return np.array(texel_directions(int(n_env)))
    a = check_environment(cube)
    N = a.shape[1]
    k = N // int(n_env)
    if N % int(n_env):
        raise LayoutError(f"n_env={n_env} must divide the face size {N}")
    om = cube_solid_angles(N)
    w_dir = texel_directions(N)
    y = a.mean(axis=-1) * om
    shp = (6, int(n_env), k, int(n_env), k, 3)
    e = (y[..., None] * w_dir).reshape(shp).sum(axis=(2, 4))
    g = (om[..., None] * w_dir).reshape(shp).sum(axis=(2, 4))
    esum = y.reshape(shp[:-1]).sum(axis=(2, 4))[..., None]
    d = np.where(esum > 0, e, g)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def env_size_for_exponent(s: float, n_fine: int, texels_per_halfwidth: float = 1.0, n_min: int = 8) -> int:
    """Smallest face size n (power of two, n_min ≤ n ≤ n_fine) with centre-texel angle (π/2)/n ≤ θ½/texels.

    Returns ``n_fine`` if even the fine map cannot resolve the lobe (then the reference is limited by the map's
    resolution, as the paper notes for Fig. 5) — check with :func:`lobe_half_angle`.
    """
    if not np.isfinite(s):
        return int(n_fine)
    need = texels_per_halfwidth * (np.pi / 2) / float(lobe_half_angle(s))
    n = int(n_min)
    while n < need and n < n_fine:
        n *= 2
    return int(min(n, n_fine))


def lobe_average(cube, dirs, s, *, n_env: int | None = None, directions: str = "centre", chunk: int = 2048):
    """Unoccluded lobe average A_s(d) of (*) at arbitrary directions (..., 3) → (..., C), on the level ``n_env``.

    :func:`ibl_ref.groundtruth.phong_convolution.lobe_average` (the package's exact Eq. 4 lobe average) of
    :func:`coarse_env` with the quadrature directions of :func:`coarse_directions`; with ``n_env = N`` and
    ``directions="centre"`` it is exactly the formula of :func:`ibl_ref.groundtruth.phong_convolution.convolve_exact`
    evaluated at ``dirs`` instead of at texel centres.
    """

    a = check_environment(cube)
    n_env = a.shape[1] if n_env is None else int(n_env)
    return _lobe_average(coarse_env(a, n_env), dirs, s, texel_dirs=coarse_directions(a, n_env, directions),
                         chunk=chunk)


# ------------------------------------------------------------------------------------------------
# exact parallel-ray visibility
# ------------------------------------------------------------------------------------------------
def parallel_visibility(meshes, points, normals, dirs, *, eps: float | None = None, mask=None, progress: bool = False):
    """Exact binary visibility V (P, D) of directions ``dirs`` (D, 3) from surface points (P, 3); 1 = unoccluded.

    The reference's argument order for :func:`ibl_ref.rendering.raycast.parallel_visibility` (the package's one exact
    parallel-ray caster; ``eps`` is its blocking threshold, default 1e-6 × scene radius).  ``mask`` (P, D) bool
    selects the pairs to cast (others are returned as 1).  With ``normals``, directions at or below the receiving
    triangle's plane (ω·n ≤ 0) are occluded without casting (the ray enters the surface).
    """

    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    return _cast(meshes, np.asarray(points, dtype=np.float64).reshape(-1, 3), d, normals=normals, eps=eps,
                 mask=mask, progress=progress)


# ------------------------------------------------------------------------------------------------
# reference shading and images
# ------------------------------------------------------------------------------------------------
@dataclass
class ReferenceResult:
    """Output of :func:`render_reference`.

    Attributes
    ----------
    image : (H, W, C) — the material's exact shading with exact visibility (0 on background).
    unoccluded : (H, W, C) — same with V ≡ 1.
    mask : (H, W) bool — covered pixels.
    gbuffer : :class:`ibl_ref.rendering.raster.GBuffer`
    info : dict — n_rays, time_s, rays_per_s, sided, n_back_facing, materials, per-lobe information (``lobes``),
        rtol, err_rel_l1 (a bound on the expected Σ|error|/Σ|image|, channel means), err_rel_p99 (99th percentile
        over the shaded pixels of ``error`` / max(pixel value, 10 % of their mean)), converged, ray_backend
    error : (H, W) — per-pixel bound of the absolute error (channel mean), holding with probability ≥ 1 − 1e-3 for
        each pixel (:mod:`ibl_ref.rendering.reference_converged`)
    """

    image: np.ndarray
    unoccluded: np.ndarray
    mask: np.ndarray
    gbuffer: object
    info: dict = field(default_factory=dict)
    error: np.ndarray | None = None


def _lobe_name(lobe) -> str:
    if lobe is None:
        return "mirror"
    if lobe.kind == "ggx":
        return "ggx"
    return "diffuse" if lobe.axis == "normal" else "glossy"


def _mirror_shading(scene, P, fn, r, a, ray_backend):
    """The mirror (g = 1): the map's nearest texel along r times the visibility of one ray along r."""

    t0 = time.perf_counter()
    Lr = sample_nearest(a, r)
    caster = ShadowRays(scene, ray_backend)
    vis = caster.visibility(P, fn, r).astype(np.float64)
    info = dict(n_rays=len(P), backend=caster.backend, time_s=time.perf_counter() - t0)
    return Lr * vis[:, None], Lr, np.zeros(len(P)), np.zeros(len(P)), info


def _check_rtol(rtol) -> float:
    """``rtol`` (default :data:`DEFAULT_RTOL`) checked by :func:`ibl_ref.limits.check_rtol`: in [2^-26, 1)."""

    return check_rtol(DEFAULT_RTOL if rtol is None else rtol, "rtol")


def reference_shading(scene, points, normals, face_normals, views, cube, material, *, rtol: float | None = None,
                      **kw):
    """The exact shading of one material at given surface points: ``(occluded (P, C), unoccluded (P, C), err_mean
    (P,), err_bound (P,), info)``.

    ``material``: :class:`ibl_ref.rendering.materials.PhongMaterial`, :class:`ibl_ref.rendering.materials.GGXMaterial`
    or anything :func:`ibl_ref.rendering.materials.as_material` accepts (e.g. ``(kd, ks, g)`` or
    ``"ggx:0.3"``); ``points``, ``normals`` (shading normals n), ``face_normals``, ``views`` (unit directions toward
    the viewer) are (P, 3); one-sided: points with n·v ≤ 0 get what the BRDF gives there (0 for GGX; the caller
    decides, as :func:`render_reference` does).  Every lobe of the material is converged to ``rtol`` with
    :func:`ibl_ref.rendering.reference_converged.converged_shading` (keywords ``**kw`` are passed on: ``n_vis_max``,
    ``max_cells``, ``seed``, ``workers``, ``progress``, …); the errors of the lobes add.  ``info["lobes"]`` holds
    each lobe's information.
    """

    mat = as_material(material)
    rtol = _check_rtol(rtol)
    a = check_environment(cube)
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    fn = np.asarray(face_normals, dtype=np.float64).reshape(-1, 3)
    v = np.asarray(views, dtype=np.float64).reshape(-1, 3)
    ray_backend = kw.pop("backend", kw.pop("ray_backend", "auto"))
    C = a.shape[-1]
    occ, un = np.zeros((len(P), C)), np.zeros((len(P), C))
    em, eb = np.zeros(len(P)), np.zeros(len(P))
    lobes = []
    for k, lobe in mat.lobes():
        if lobe is None:
            r = 2.0 * np.sum(n * v, axis=1, keepdims=True) * n - v
            o, u, e, b, inf = _mirror_shading(scene, P, fn, r, a, ray_backend)
        else:
            o, u, e, b, inf = converged_shading(scene, P, n, fn, v, a, lobe, rtol=rtol, backend=ray_backend, **kw)
        occ += k * o
        un += k * u
        em += k * e
        eb += k * b
        lobes.append(dict(lobe=_lobe_name(lobe), weight=k, **(lobe.describe() if lobe is not None else {}),
                          **{kk: vv for kk, vv in inf.items() if kk != "time_s"}, time_s=round(inf["time_s"], 3)))
    return occ, un, em, eb, dict(material=mat.describe(), rtol=rtol, lobes=lobes)


def render_reference(meshes, camera, cube, *, kd: float = 0.0, ks: float = 1.0, g: float = 0.9, material=None,
                     rtol: float | None = None, materials: dict | None = None, sided: str = "one",
                     n_vis_start: int = 16, n_vis_max: int = 16384, n_quad_max: int | None = None,
                     n_quad_min: int | None = None, max_cells: int | None = None, pixel_rtol: float | None = None, ray_backend: str = "auto",
                     seed: int = 0, block_pixels: int = 256, workers: int = 1, executor=None,
                     smooth_normals: bool = True, gbuffer=None, progress: bool = False) -> ReferenceResult:
    """Ground-truth image of the scene's materials (module docstring: (*) and its GGX form) with exact ray-cast
    visibility.

    Parameters
    ----------
    meshes, camera : scene and view (same as :func:`ibl_ref.rendering.render.render_pem`; same G-buffer)
    cube : (6, N, N, C) fine environment map (radiance), or a list of maps of one shape (a sweep over
        environments: one set of visibility cells, rays and quadrature weights serves them all, each image held to
        ``rtol`` and ``pixel_rtol`` on its own — :func:`ibl_ref.rendering.reference_converged.converged_shading`'s
        ``groups`` — and a list of results is returned, one per map)
    kd, ks, g : the Phong material of every mesh when neither ``material`` nor ``materials`` is given (kd, ks ≥ 0;
        g = 1 → exact mirror)
    material : one material for every mesh (:func:`ibl_ref.rendering.materials.as_material`: a
        :class:`~ibl_ref.rendering.materials.PhongMaterial`, a :class:`~ibl_ref.rendering.materials.GGXMaterial`,
        ``(kd, ks, g)``, ``"ggx:0.3"``, …)
    materials : {material_id: material} per mesh material (any form ``material`` takes)
    rtol : converge to this estimated relative L1 of the image (default :data:`DEFAULT_RTOL` = 2e-3; must be > 0);
        the estimate is in ``info`` (``err_rel_l1``, ``err_rel_p99``) and ``ReferenceResult.error``
    sided : ``"one"`` (default; pixels with n·v ≤ 0 are black, as a one-sided BSDF in Mitsuba) or ``"two"``
        (such pixels are shaded with n, its face normal and r flipped toward the viewer)
    n_vis_start, n_vis_max : smallest base and finest face size of the visibility cells
    n_quad_max : largest quadrature face size (default: the lobe's, 256 for Phong, 4096 for GGX)
    n_quad_min : smallest quadrature face size (default: the visibility base level's; the map's N puts every
        quadrature texel inside one map texel: :func:`~ibl_ref.rendering.reference_converged.converged_shading`)
    max_cells : cells of one block at most (default
        :data:`ibl_ref.rendering.reference_converged.MAX_BLOCK_CELLS`: the memory bound per worker)
    pixel_rtol : also refine pixels whose error bound exceeds ``pixel_rtol`` × max(pixel value, 10 % of the mean)
        (default 15 × ``rtol``), so ``info["err_rel_p99"]`` stays below it where the visibility limits it
    ray_backend : shadow rays: ``"auto"`` (Embree when ``embreex`` is installed), ``"embree"`` or ``"exact"`` (the
        package's float64 casters); :class:`ibl_ref.rendering.raycast.ShadowRays`
    seed : random points of the visibility cells (the image is a deterministic function of it)
    block_pixels : pixels per block (round-robin; the image depends on it, never on where the blocks run)
    workers, executor : where the blocks run (:func:`ibl_ref.executors.map_jobs`: ``workers`` local processes or
        any Executor / Dask client); the image is bit-identical to a serial run
    gbuffer : a precomputed :class:`ibl_ref.rendering.raster.GBuffer` of the same camera (optional; without it the
        G-buffer is rasterised here and a mesh that carries a normal map, ``mesh.metadata["normal_map"]``, is shaded
        with its perturbed normals: :func:`ibl_ref.rendering.normal_map.apply_normal_maps`)
    progress : progress reports, and the predicted cost of each lobe before most of it runs

    Returns
    -------
    ReferenceResult, or a list of them for a list of maps
        ``image``, ``unoccluded``, ``mask``, ``gbuffer``, ``info`` (tolerance, error estimates, rays, times, per
        lobe; for a list of maps the times and rays are those of the whole sweep), ``error`` (per-pixel bound).

    Raises
    ------
    IBLError
        A bad material, environment, tolerance (:func:`ibl_ref.limits.check_rtol`: in [2^-26, 1)), ``sided`` or
        size parameter; a material id without a material; a GGX lobe narrower than one texel of the finest
        quadrature level (:meth:`ibl_ref.rendering.materials.GGXLobe.check_resolved`).

    Examples
    --------
    A plane facing up under a constant environment L = 1: the diffuse lobe lies wholly above the horizon and nothing
    occludes it, so every pixel is exactly 1 (the quadrature's own normalisation):

    >>> import numpy as np, trimesh
    >>> from ibl_ref.rendering.camera import PerspectiveCamera
    >>> from ibl_ref.rendering.reference_render import render_reference
    >>> quad = trimesh.Trimesh([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], [[0, 2, 1], [0, 3, 2]],
    ...                        process=False)
    >>> cam = PerspectiveCamera(eye=[0, 2, 0.5], target=[0, 0, 0], up=[0, 1, 0], fov_y_deg=30, width=4, height=4)
    >>> res = render_reference([(quad, 0)], cam, np.ones((6, 8, 8, 3)), material=(1.0, 0.0, 0.5), rtol=1e-2)
    >>> int(res.mask.sum()), np.allclose(res.image[res.mask], 1.0), res.info["converged"]
    (16, True, True)
    >>> render_reference([(quad, 0)], cam, np.ones((6, 8, 8, 3)), rtol=0)
    Traceback (most recent call last):
    ...
    ibl_ref.limits.ToleranceError: rtol: a relative tolerance must be a number in (0, 1), got 0
    """

    if sided not in SIDED:
        raise IBLError(f"sided must be one of {SIDED}, got {sided!r}")
    rtol = _check_rtol(rtol)
    several = isinstance(cube, (list, tuple))
    a, E = _stack_environments(cube)
    scene = prepare_scene(meshes, warn=False)
    ids = sorted(int(x) for x in np.unique(scene.material_id))
    if materials is None:
        default = as_material((kd, ks, g) if material is None else material)
        mats = {i: default for i in ids}
    else:
        mats = {int(k): as_material(vv, f"material {k}") for k, vv in dict(materials).items()}
    for mid in ids:
        if mid not in mats:
            raise IBLError(f"no material for material id {mid} (have {sorted(mats)})")
    if gbuffer is None:  # a mesh's normal map (metadata["normal_map"]) perturbs its shading normals
        gb = apply_normal_maps(meshes, scene, rasterize(scene, camera, smooth_normals=smooth_normals))
    else:
        gb = gbuffer
    m = gb.mask
    P, n, fn, v = gb.position[m], gb.normal[m], gb.face_normal[m], gb.view[m]
    mat_px = gb.material_id[m]
    ndv = np.sum(n * v, axis=1)
    back = ndv <= 0  # n·v ≤ 0: seen from behind the shading normal
    if sided == "two" and back.any():
        n, fn = n.copy(), fn.copy()
        n[back] *= -1
        fn[back] *= -1
    r = 2.0 * np.sum(n * v, axis=1, keepdims=True) * n - v
    C = a.shape[-1]
    occ = np.zeros((len(P), C))
    unocc = np.zeros((len(P), C))
    err = np.zeros((len(P), E))
    bound = np.zeros((len(P), E))
    first = mats[ids[0]] if ids else as_material((kd, ks, g))
    info = dict(n_pixels=int(m.sum()), n_rays=0, time_s=0.0, sided=sided, n_back_facing=int(back.sum()),
                quadrature="converged", rtol=rtol, materials={str(k): vv.describe() for k, vv in mats.items()})
    if first.kind == "phong":
        info.update(kd=first.kd, ks=first.ks, g=first.g)
    shade = np.ones(len(P), dtype=bool) if sided == "two" else ~back
    groups = {}  # lobe → per-pixel weight; one integration per lobe over all materials that have it
    for mid in ids:
        sel = shade & (mat_px == mid)
        if not sel.any():
            continue
        for k, lobe in mats[mid].lobes():
            groups.setdefault(lobe, np.zeros(len(P)))[sel] = k
    kw = dict(rtol=rtol, n_vis_start=n_vis_start, n_vis_max=n_vis_max, n_quad_max=n_quad_max, n_quad_min=n_quad_min,
              max_cells=MAX_BLOCK_CELLS if max_cells is None else max_cells, pixel_rtol=pixel_rtol,
              backend=ray_backend, seed=seed, block_pixels=block_pixels, workers=workers, executor=executor,
              progress=progress, groups=E)
    per_lobe = []
    for lobe, kpx in groups.items():
        sel = kpx > 0
        k = kpx[sel][:, None]
        name = _lobe_name(lobe)
        if lobe is None:
            o, u, e, eb, inf = _mirror_shading(scene, P[sel], fn[sel], r[sel], a, ray_backend)
        else:
            o, u, e, eb, inf = converged_shading(scene, P[sel], n[sel], fn[sel], v[sel], a, lobe, **kw)
        err[sel] += k * np.reshape(e, (len(k), -1))  # (n, E), or (n, 1) broadcast (the mirror: exact)
        bound[sel] += k * np.reshape(eb, (len(k), -1))
        occ[sel] += k * o
        unocc[sel] += k * u
        if lobe is not None and lobe.kind == "phong":
            info[f"s_{name}"] = lobe.s
        info[f"time_{name}_s"] = info.get(f"time_{name}_s", 0.0) + inf["time_s"]
        info["n_rays"] += inf["n_rays"]
        info["time_s"] += inf["time_s"]
        per_lobe.append(dict(lobe=name, **(lobe.describe() if lobe is not None else {}),
                             **{kk: vv for kk, vv in inf.items() if kk != "time_s"}, time_s=round(inf["time_s"], 3)))
    info["lobes"] = per_lobe
    info["rays_per_s"] = info["n_rays"] / info["time_s"] if info["time_s"] > 0 else float("nan")
    info["ray_backend"] = per_lobe[0].get("backend") if per_lobe else None
    Cg = C // E
    out = []
    for ei in range(E):
        ch = slice(ei * Cg, (ei + 1) * Cg)
        inf = dict(info, lobes=[dict(lb, est_rel_l1=lb["est_rel_l1"][ei]) if isinstance(lb.get("est_rel_l1"), list)
                                else lb for lb in per_lobe])
        if several:
            inf.update(environment=ei, environments=E)
        out.append(_result(m, gb, occ[:, ch], unocc[:, ch], err[:, ei], bound[:, ei], shade, rtol, inf))
    return out if several else out[0]


def _stack_environments(cube):
    """One validated map (6, N, N, C), or a list of them stacked along the channels → ((6, N, N, E·C), E)."""
    if not isinstance(cube, (list, tuple)):
        return check_environment(cube), 1
    if not cube:
        raise IBLError("the list of environments is empty")
    maps = [check_environment(c) for c in cube]
    if any(x.shape != maps[0].shape for x in maps):
        raise LayoutError(f"the environments of a sweep must have one shape, got {sorted({x.shape for x in maps})}")
    return np.concatenate(maps, axis=-1), len(maps)


def _result(m, gb, occ, unocc, err, bound, shade, rtol, info) -> ReferenceResult:
    """One environment's image, unoccluded image, error estimates and bound (rel. L1, 99th percentile)."""
    info = dict(info)
    y = occ.mean(axis=-1)
    tot = float(np.abs(y).sum())
    info["err_rel_l1"] = float(err.sum() / tot) if tot > 0 else 0.0
    info["err_rel_p99"] = 0.0
    if shade.any():  # relative to max(pixel value, ERR_FLOOR × mean): absolute in deep shadow
        den = np.maximum(y[shade], ERR_FLOOR * max(float(np.abs(y[shade]).mean()), 1e-300))
        info["err_rel_p99"] = float(np.percentile(bound[shade] / den, 99))
    info["converged"] = bool(info["err_rel_l1"] <= rtol and all(lb.get("converged", True) for lb in info["lobes"]))
    H, W = m.shape
    C = occ.shape[-1]
    img = np.zeros((H, W, C))
    img[m] = occ
    un = np.zeros((H, W, C))
    un[m] = unocc
    er = np.zeros((H, W))
    er[m] = bound
    if not (np.all(np.isfinite(img)) and np.all(np.isfinite(un))):
        raise IBLError("reference produced non-finite values")
    return ReferenceResult(image=img, unoccluded=un, mask=m, gbuffer=gb, info=info, error=er)


# ------------------------------------------------------------------------------------------------
# unoccluded checks of the coarse levels and the exact PEMs of Eq. 5
# ------------------------------------------------------------------------------------------------
def coarse_level_error(cube, dirs, s: float, n_env: int, directions: str = "centroid") -> dict:
    """Error of the coarse-level quadrature with V ≡ 1 at lobe directions ``dirs`` (P, 3).

    Compares :func:`lobe_average` at level ``n_env`` against the exact lobe average of the full-resolution map
    (the formula of :func:`ibl_ref.groundtruth.phong_convolution.convolve_exact`, evaluated at ``dirs``).  Returns
    ``rel_l1`` (Σ|a−b|/Σ|b| over all pixels and channels) and ``rel_max`` (max |a−b|/b over pixel luminance).
    """
    a = check_environment(cube)
    coarse = lobe_average(a, dirs, s, n_env=n_env, directions=directions)
    exact = lobe_average(a, dirs, s, n_env=a.shape[1], directions="centre")
    err = np.abs(coarse - exact)
    yb = exact.mean(axis=-1)
    return dict(rel_l1=float(err.sum() / max(np.abs(exact).sum(), 1e-300)),
                rel_max=float((err.mean(axis=-1) / np.maximum(yb, 1e-300)).max()),
                n_env=int(n_env), n_fine=int(a.shape[1]), s=float(s), directions=directions)


def exact_pem_lookup(cube, labels, dirs, s: float, n_regions: int | None = None, chunk: int = 256) -> np.ndarray:
    """Exact per-region lobe averages (L, P, C): the PEMs of Eq. 5 without the filter pyramid.

    PEM_i(d) = Σ_{j ∈ region i} L_j max(d·ω_j,0)^s Ω_j / Σ_{all j} max(d·ω_j,0)^s Ω_j over the full-resolution
    texels j (``labels`` (6, N, N) from :func:`ibl_ref.knuth2014.median_cut.median_cut`), so Σ_i PEM_i = the exact lobe
    average.  Used to separate the filter-pyramid error from the visibility error of Eq. 5.
    """

    a = check_environment(cube)
    N = a.shape[1]
    lab = np.asarray(labels).reshape(-1)
    if lab.shape[0] != 6 * N * N:
        raise LayoutError(f"labels must have shape (6, {N}, {N})")
    L = int(lab.max()) + 1 if n_regions is None else int(n_regions)
    out = _lobe_average(a, dirs, s, labels=lab.reshape(6, N, N), n_regions=L, chunk=chunk)  # (P, L, C)
    return np.moveaxis(out.reshape(-1, L, a.shape[-1]), 1, 0)


