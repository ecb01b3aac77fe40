"""Ray-traced ground truth for Knuth et al. (2014), Eq. 5 with kd/ks Phong materials (Sec. 3.4, Fig. 6).

The paper's renderer approximates, per pixel,

    c = Σ_i VIS_i · (kd·PEM_i(n, g=0) + ks·PEM_i(r, g))                                     (Eq. 5, kd/ks form)

with shadow-mapped visibilities of one directional light per median-cut region and filtered partial environment
maps.  The exact quantity it approximates is the visibility-weighted Phong lobe average (Eq. 4 normalised as a
lobe average, docs/background.md §2)::

    c = kd · A_1(n) + ks · A_s(r),   A_s(d) = Σ_j L_j V_j max(d·ω_j, 0)^s Ω_j / Σ_j max(d·ω_j, 0)^s Ω_j     (*)

with ``s = 1/(1−g)`` (Eq. 3), ``r = 2(n·v)n − v``, V_j the exact binary visibility of direction ω_j from the
surface point, and the sums over **all** texels j of an environment level (the normalisation includes occluded
and below-horizon texels, so V ≡ 1 reproduces :func:`ibl_ref.groundtruth.phong_convolution.convolve_exact`).

Default: converged to a tolerance (``render_reference(..., rtol=2e-3)``,
:func:`ibl_ref.rendering.reference_converged.converged_shading`, re-exported here): the radiance × lobe quadrature
at texel centres of a face size M = N·2^k that the tolerance needs, and a stratified, adaptively refined
visibility — one shadow ray per direction cell toward a random point of the cell, cells split 2×2 where weight ×
possible change is largest next to a shadow edge — with an error estimate per image (``info["err_rel_l1"]``,
a bound on the expected rel. L1) and a per-pixel bound (``ReferenceResult.error``, holding with probability
≥ 1 − 1e-3 per pixel; its 99th percentile relative to max(pixel value, 10 % of the mean) is
``info["err_rel_p99"]``); that module's docstring gives the definitions.  Shadow rays: Embree when ``embreex``
is installed (every hit re-checked in float64), the package's float64 casters otherwise
(:class:`ibl_ref.rendering.raycast.ShadowRays`).  The pixels run in fixed blocks (``workers=`` / ``executor=``:
:func:`ibl_ref.executors.map_jobs`), bit-identical wherever they run.  Conventions (docs/background.md §8):
one-sided shading (n·v ≤ 0 → black, ``sided="two"`` flips n), both lobes over the hemisphere Ω⁺ of the shading
normal n with the lobe normalised over the whole sphere (the normalised Phong BRDF of Kán et al. 2015, Eq. 2),
one material per mesh.

Fixed quadrature (``rtol=0``; choices that change numbers, all explicit parameters):

* ``n_env`` — face size of the COARSE level used for (*): L_j is the exact solid-angle-weighted area average of
  the fine texels inside coarse texel j, so ∫L dω is kept exactly; Ω_j is the exact coarse solid angle.
* ``directions`` — ω_j is the coarse texel **centre** (``"centre"``; reproduces the exact convolution of the
  coarse map) or the luminance-weighted **energy centroid** of its fine texels (``"centroid"``, default;
  a sun inside a coarse texel then casts its shadow from its true direction).
* The coarse level can only resolve lobes wider than a few coarse texels: :func:`env_size_for_exponent` picks
  the smallest level whose texel angle is ≤ the lobe's half-width at half maximum / ``texels_per_halfwidth``
  (θ½ = arccos 2^(−1/s) ≈ 1.18/√s).  The reference is NOT valid for narrower lobes at a given level.
  ``g = 1`` (mirror) is handled exactly: one ray along r, radiance = the fine map's nearest texel at r.
* Lobe truncation for glossy lobes: texels with max(d·ω,0)^s < ``weight_cutoff`` × (lobe peak) are skipped for the
  visibility (they still count in the normalisation); the neglected weight fraction is reported.

Visibility: the package's exact parallel-ray caster :func:`ibl_ref.rendering.raycast.parallel_visibility` (re-exported here
as :func:`parallel_visibility` with the reference's argument order): for each direction ω the triangles and the
surface points are projected onto the plane ⟂ ω, binned on a 2D grid, and every candidate (point, triangle) pair
is tested with exact 2D edge functions and the height along ω; a triangle blocks when it is more than
``eps`` = 1e-6 × scene radius nearer the light (rounding only; no origin offset, so contact shadows of thin
occluders are kept — :mod:`ibl_ref.rendering.raycast` explains the choice).  It is cross-checked against trimesh's
``intersects_any`` in the tests; ``backend="trimesh"`` uses :func:`ibl_ref.rendering.raycast.visibility_to_directions`
instead (slow without Embree: ~100 rays/s on the 16k-triangle teapot, docs/background.md §4), whose ray origins
are offset by ``eps`` (default 1e-4 × scene radius) along the face normal and along the ray.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..conventions import lobe_half_angle, phong_exponent  # noqa: F401  (re-exported, old names)
from ..environment.radiance_policy import check_radiance
from ..errors import IBLError, LayoutError

__all__ = [
    "ReferenceResult",
    "check_environment",
    "radiance_at_face_size",
    "coarse_env",
    "coarse_directions",
    "lobe_half_angle",
    "env_size_for_exponent",
    "lobe_average",
    "parallel_visibility",
    "reference_shading",
    "render_reference",
    "converged_shading",
    "DEFAULT_RTOL",
    "coarse_level_error",
    "estimate_reference_rays",
    "exact_pem_lookup",
]

DIRECTION_MODES = ("centroid", "centre")
BACKENDS = ("project", "trimesh")


# ------------------------------------------------------------------------------------------------
# environment quadrature
# ------------------------------------------------------------------------------------------------
def check_environment(cube) -> np.ndarray:
    """The environment of a render as validated float64 radiance (6, N, N, C): layout checked, NaN/Inf/negative
    radiance refused with a clear :class:`ibl_ref.errors.RadianceError` (:func:`ibl_ref.environment.radiance_policy.check_radiance`);
    a (6, N, N) map gets one channel."""
    from ..environment.envmap import check_cube_shape

    check_cube_shape(cube, "environment")
    a = np.asarray(check_radiance(cube, "environment"), dtype=np.float64)
    if a.ndim == 3:
        a = a[..., None]
    return a


def coarse_env(cube, n_env: int) -> np.ndarray:
    """Exact area average of a cube map onto face size ``n_env`` (must divide N).

    L_coarse = Σ_f L_f Ω_f / Σ_f Ω_f over the k×k fine texels f of each coarse texel (k = N / n_env); since the
    coarse texel is exactly the union of its fine texels, L_coarse·Ω_coarse = Σ L_f Ω_f and ∫L dω is kept.
    """
    from ..environment.envmap import cube_solid_angles

    a = check_environment(cube)
    N = a.shape[1]
    n_env = int(n_env)
    if n_env < 1 or N % n_env:
        raise LayoutError(f"n_env={n_env} must divide the face size {N}")
    k = N // n_env
    om = cube_solid_angles(N)[..., None]
    num = (a * om).reshape(6, n_env, k, n_env, k, -1).sum(axis=(2, 4))
    den = om.reshape(6, n_env, k, n_env, k, 1).sum(axis=(2, 4))
    return num / den


def coarse_directions(cube, n_env: int, mode: str = "centroid") -> np.ndarray:
    """Quadrature directions ω_j (6, n, n, 3) of the coarse level: texel centres or energy centroids.

    ``"centroid"``: normalize(Σ_f Y_f Ω_f ω_f) over the fine texels f (Y = mean over channels); texels with no
    energy use the solid-angle centroid Σ_f Ω_f ω_f.
    """
    from ..environment.envmap import cube_solid_angles, texel_directions

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


def _lobe_weights(d, omega_dirs, omega_sa, s):
    """max(d·ω,0)^s Ω (P, J) and their row sums (P,)."""
    c = np.clip(d @ omega_dirs.T, 0.0, None)
    with np.errstate(divide="ignore", under="ignore"):
        w = np.power(c, s) * omega_sa[None, :]
    return w, w.sum(axis=1)


def lobe_average(cube, dirs, s, *, n_env: int | None = None, directions: str = "centre", chunk: int = 2048):
    """Unoccluded lobe average A_s(d) of (*) at arbitrary directions (..., 3) → (..., C), on the level ``n_env``.

    :func:`ibl_ref.groundtruth.phong_convolution.lobe_average` (the package's exact Eq. 4 lobe average) of
    :func:`coarse_env` with the quadrature directions of :func:`coarse_directions`; with ``n_env = N`` and
    ``directions="centre"`` it is exactly the formula of :func:`ibl_ref.groundtruth.phong_convolution.convolve_exact`
    evaluated at ``dirs`` instead of at texel centres.
    """
    from ..groundtruth.phong_convolution import lobe_average as _lobe_average

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
    from .raycast import parallel_visibility as _cast

    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    return _cast(meshes, np.asarray(points, dtype=np.float64).reshape(-1, 3), d, normals=normals, eps=eps,
                 mask=mask, progress=progress)


# ------------------------------------------------------------------------------------------------
# reference image
# ------------------------------------------------------------------------------------------------
@dataclass
class ReferenceResult:
    """Output of :func:`render_reference`.

    Attributes
    ----------
    image : (H, W, C) — c = kd·A_1(n) + ks·A_s(r) with exact visibility (0 on background).
    unoccluded : (H, W, C) — same with V ≡ 1.
    mask : (H, W) bool — covered pixels.
    gbuffer : :class:`ibl_ref.rendering.raster.GBuffer`
    info : dict — n_rays, time_s, rays_per_s, sided, n_back_facing, per-lobe levels (``lobes``); converged:
        rtol, err_rel_l1 (a bound on the expected Σ|error|/Σ|image|, channel means), err_rel_p99 (99th percentile
        over the shaded pixels of ``error`` / max(pixel value, 10 % of their mean)), converged, ray_backend;
        fixed quadrature: n_env_diffuse, n_env_glossy, neglected_weight_max
    error : (H, W) or None — per-pixel bound of the absolute error (channel mean) of the converged reference, holding
        with probability ≥ 1 − 1e-3 for each pixel (:mod:`ibl_ref.rendering.reference_converged`)
    """

    image: np.ndarray
    unoccluded: np.ndarray
    mask: np.ndarray
    gbuffer: object
    info: dict = field(default_factory=dict)
    error: np.ndarray | None = None


def estimate_reference_rays(n_pixels: int, n_env: int, s: float = 1.0) -> int:
    """Upper bound of rays for one lobe: covered pixels × 6·n_env² directions (glossy lobes cast fewer)."""
    return int(n_pixels) * 6 * int(n_env) ** 2


def reference_shading(meshes, points, face_normals, d_lobe, cube, s, *, n_env: int, directions: str = "centroid",
                      weight_cutoff: float = 1e-6, backend: str = "project", eps: float | None = None,
                      progress: bool = False):
    """Exact visibility-weighted lobe averages A_s(d) of (*) at surface points → (occluded (P, C), unoccluded (P, C), info).

    ``s = np.inf`` is the mirror: one ray along d, radiance of the fine map's nearest texel.
    """
    from ..environment.envmap import cube_solid_angles

    if backend not in BACKENDS:
        raise IBLError(f"backend must be one of {BACKENDS}, got {backend!r}")
    a = check_environment(cube)
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(d_lobe, dtype=np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    s = float(s)
    if not (s >= 1.0):
        raise IBLError(f"Phong exponent s must be >= 1 (or inf), got {s}")
    t0 = time.perf_counter()
    if np.isinf(s):
        from ..environment.sampling import sample_nearest

        Lr = sample_nearest(a, d)
        vis = _visibility(meshes, P, face_normals, d, backend, eps, pairwise=True)
        info = dict(n_env=a.shape[1], n_rays=len(P), neglected_weight_max=0.0)
        info["time_s"] = time.perf_counter() - t0
        return Lr * vis[:, None], Lr, info
    Lc = coarse_env(a, n_env).reshape(-1, a.shape[-1])
    om_d = coarse_directions(a, n_env, directions).reshape(-1, 3)
    om = np.array(cube_solid_angles(n_env)).reshape(-1)
    w, ws = _lobe_weights(d, om_d, om, s)
    if np.any(ws <= 0):
        raise IBLError("a lobe has zero total weight at this env level (lobe narrower than a texel): use a finer n_env")
    peak = w.max(axis=1, keepdims=True)
    cast = w > weight_cutoff * peak
    neglected = float(((w * ~cast).sum(axis=1) / ws).max())
    if backend == "project":
        V = parallel_visibility(meshes, P, face_normals, om_d, eps=eps, mask=cast, progress=progress)
    else:
        V = np.ones_like(w)
        Vt = _visibility(meshes, P, face_normals, om_d, backend, eps, pairwise=False)
        V[cast] = Vt[cast]
    V[~cast] = 0.0  # neglected lobe tail: treated as occluded (bounded by neglected_weight_max)
    occl = ((w * V) @ Lc) / ws[:, None]
    unocc = (w @ Lc) / ws[:, None]
    info = dict(n_env=int(n_env), n_rays=int(cast.sum()), neglected_weight_max=neglected,
                time_s=time.perf_counter() - t0)
    return occl, unocc, info


def _visibility(meshes, P, normals, dirs, backend, eps, pairwise):
    if pairwise:  # one direction per point
        if backend == "project":
            # group-free: cast each point's own direction (mirror case, one ray per pixel)
            from .raycast import any_hit
            from .raster import prepare_scene

            scene = prepare_scene(meshes, warn=False)
            e = 1e-4 * scene.bounds()[1] if eps is None else eps
            o = P + e * np.asarray(normals).reshape(-1, 3) + e * dirs
            return (~any_hit((scene, scene.to_trimesh()), o, dirs)).astype(float)
        from .raycast import visibility_to_directions

        return np.array([visibility_to_directions(meshes, P[i:i + 1], normals[i:i + 1], dirs[i])[0, 0]
                         for i in range(len(P))])
    from .raycast import visibility_to_directions

    return visibility_to_directions(meshes, P, normals, dirs, eps=eps)


SIDED = ("one", "two")


def render_reference(meshes, camera, cube, *, kd: float = 0.0, ks: float = 1.0, g: float = 0.9,
                     rtol: float | None = None, materials: dict | None = None, sided: str = "one",
                     n_vis_start: int = 16, n_vis_max: int = 16384, n_quad_max: int = 256,
                     n_env_diffuse: int | None = 8, n_env_glossy: int | None = None, directions: str = "centroid",
                     texels_per_halfwidth: float = 1.0, weight_cutoff: float = 1e-6, backend: str = "project",
                     pixel_rtol: float | None = None, ray_backend: str = "auto", seed: int = 0,
                     block_pixels: int = 256, workers: int = 1,
                     executor=None, smooth_normals: bool = True, gbuffer=None,
                     progress: bool = False) -> ReferenceResult:
    """Ground-truth image c = kd·A_1(n) + ks·A_s(r) of (*) with exact ray-cast visibility.

    Parameters
    ----------
    meshes, camera : scene and view (same as :func:`ibl_ref.rendering.render.render_pem`; same G-buffer)
    cube : (6, N, N, C) fine environment map (radiance)
    kd, ks : diffuse and glossy weights (≥ 0)
    g : glossiness of the ks term (s = 1/(1−g), Eq. 3; g = 1 → exact mirror)
    rtol : converge to this estimated relative L1 of the image (default :data:`DEFAULT_RTOL` = 2e-3) with
        :func:`converged_shading`; the estimate is in ``info`` (``err_rel_l1``, ``err_rel_p99``) and
        ``ReferenceResult.error``.  ``rtol=0`` selects the fixed
        coarse-level quadrature of :func:`reference_shading` (``n_env_*``, ``directions``, … below; no estimate).
    materials : {material_id: (kd, ks, g)} per mesh material (default: every mesh gets kd, ks, g)
    sided : ``"one"`` (default; pixels with n·v ≤ 0 are black, as a one-sided BSDF in Mitsuba) or ``"two"``
        (such pixels are shaded with n, its face normal and r flipped toward the viewer)
    n_vis_start, n_vis_max : smallest base and finest face size of the converged reference's visibility cells
    n_quad_max : largest quadrature face size of the converged reference
    pixel_rtol : the converged reference also refines pixels whose error bound exceeds ``pixel_rtol`` × max(pixel
        value, 10 % of the mean) (default 15 × ``rtol``), so ``info["err_rel_p99"]`` stays below it where the
        visibility limits it
    ray_backend : shadow rays of the converged reference: ``"auto"`` (Embree when ``embreex`` is installed),
        ``"embree"`` or ``"exact"`` (the package's float64 casters); :class:`ibl_ref.rendering.raycast.ShadowRays`
    seed : random points of the converged reference's visibility cells (the image is a deterministic function
        of it)
    block_pixels : pixels per block of the converged reference (round-robin; the image depends on it, never on
        where the blocks run)
    workers, executor : where the blocks run (:func:`ibl_ref.executors.map_jobs`: ``workers`` local processes or
        any Executor / Dask client); the image is bit-identical to a serial run
    n_env_diffuse : coarse face size for the s = 1 term (fixed quadrature; default 8)
    n_env_glossy : coarse face size for the glossy term (fixed quadrature; default :func:`env_size_for_exponent`)
    directions, texels_per_halfwidth, weight_cutoff, backend : fixed quadrature, see module docstring
    gbuffer : a precomputed :class:`ibl_ref.rendering.raster.GBuffer` of the same camera (optional)

    Returns
    -------
    ReferenceResult
    """
    from .raster import prepare_scene, rasterize

    if sided not in SIDED:
        raise IBLError(f"sided must be one of {SIDED}, got {sided!r}")
    if rtol is None:
        rtol = DEFAULT_RTOL
    rtol = float(rtol)
    if not (rtol >= 0 and np.isfinite(rtol)):
        raise IBLError(f"rtol must be finite and >= 0, got {rtol}")
    a = check_environment(cube)
    N = a.shape[1]
    scene = prepare_scene(meshes, warn=False)
    ids = sorted(int(x) for x in np.unique(scene.material_id))
    mats = {i: (kd, ks, g) for i in ids} if materials is None else dict(materials)
    for mid in ids:
        if mid not in mats:
            raise IBLError(f"no material for material id {mid} (have {sorted(mats)})")
        mk, ms, mg = (float(x) for x in mats[mid])
        if not (mk >= 0 and ms >= 0 and np.isfinite(mk) and np.isfinite(ms)):
            raise IBLError(f"kd, ks must be finite and >= 0, got {mk}, {ms}")
        if not (0.0 <= mg <= 1.0):
            raise IBLError(f"g must be in [0, 1], got {mg}")
        mats[mid] = (mk, ms, mg)
    gb = rasterize(scene, camera, smooth_normals=smooth_normals) if gbuffer is None else gbuffer
    m = gb.mask
    P, n, fn, r, v = gb.position[m], gb.normal[m], gb.face_normal[m], gb.reflect[m], gb.view[m]
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
    err = np.zeros(len(P))
    bound = np.zeros(len(P))
    converged = rtol > 0
    info = dict(n_pixels=int(m.sum()), backend=backend, kd=kd, ks=ks, g=g, n_rays=0, time_s=0.0,
                neglected_weight_max=0.0, sided=sided, n_back_facing=int(back.sum()),
                quadrature="converged" if converged else "fixed", rtol=rtol if converged else None,
                materials={str(k): dict(kd=vv[0], ks=vv[1], g=vv[2]) for k, vv in mats.items()})
    if not converged:
        info["directions"] = directions
    shade = np.ones(len(P), dtype=bool) if sided == "two" else ~back
    groups = {}  # (name, s) → per-pixel weight k; one call per lobe kind and exponent over all materials
    for mid in ids:
        mk, ms, mg = mats[mid]
        sel = shade & (mat_px == mid)
        if not sel.any():
            continue
        for name, k, s in (("diffuse", mk, 1.0), ("glossy", ms, float(phong_exponent(mg)))):
            if k > 0:
                groups.setdefault((name, s), np.zeros(len(P)))[sel] = k
    per_lobe = []
    for (name, s), kpx in groups.items():
        sel = kpx > 0
        k = kpx[sel][:, None]
        dl = n if name == "diffuse" else r
        if converged and np.isfinite(s):
            o, u, e, eb, inf = converged_shading(scene, P[sel], n[sel], fn[sel], dl[sel], a, s, rtol=rtol,
                                                 n_vis_start=n_vis_start, n_vis_max=n_vis_max,
                                                 n_quad_max=n_quad_max, pixel_rtol=pixel_rtol,
                                                 backend=ray_backend, seed=seed,
                                                 block_pixels=block_pixels, workers=workers, executor=executor,
                                                 progress=progress)
            err[sel] += k[:, 0] * e
            bound[sel] += k[:, 0] * eb
        else:
            ne = (min(N, n_env_diffuse or 8) if s == 1.0 else
                  min(N, n_env_glossy or env_size_for_exponent(s, N, texels_per_halfwidth)))
            if np.isfinite(s) and ne >= N and lobe_half_angle(s) < texels_per_halfwidth * (np.pi / 2) / N:
                warnings.warn(f"{name} lobe s={s:g} is narrower than {texels_per_halfwidth} texels of the {N}² map: "
                              "the reference is limited by the map's resolution", UserWarning, stacklevel=2)
            if backend == "trimesh":
                from .raycast import warn_rays_budget

                warn_rays_budget(estimate_reference_rays(int(sel.sum()), ne), len(scene.faces))
            o, u, inf = reference_shading(scene, P[sel], fn[sel], dl[sel], a, s, n_env=ne, directions=directions,
                                          weight_cutoff=weight_cutoff, backend=backend, progress=progress)
            info[f"n_env_{name}"] = inf["n_env"]
            info["neglected_weight_max"] = max(info["neglected_weight_max"], inf["neglected_weight_max"])
        occ[sel] += k * o
        unocc[sel] += k * u
        info[f"s_{name}"] = s
        info[f"time_{name}_s"] = info.get(f"time_{name}_s", 0.0) + inf["time_s"]
        info["n_rays"] += inf["n_rays"]
        info["time_s"] += inf["time_s"]
        per_lobe.append(dict(lobe=name, s=s, **{kk: vv for kk, vv in inf.items() if kk != "time_s"},
                             time_s=round(inf["time_s"], 3)))
    info["lobes"] = per_lobe
    info["rays_per_s"] = info["n_rays"] / info["time_s"] if info["time_s"] > 0 else float("nan")
    if converged:
        y = occ.mean(axis=-1)
        tot = float(np.abs(y).sum())
        info["err_rel_l1"] = float(err.sum() / tot) if tot > 0 else 0.0
        info["err_rel_p99"] = 0.0
        if shade.any():  # relative to max(pixel value, ERR_FLOOR × mean): absolute in deep shadow
            den = np.maximum(y[shade], ERR_FLOOR * max(float(np.abs(y[shade]).mean()), 1e-300))
            info["err_rel_p99"] = float(np.percentile(bound[shade] / den, 99))
        info["converged"] = bool(info["err_rel_l1"] <= rtol and all(lb.get("converged", True) for lb in per_lobe))
        info["ray_backend"] = per_lobe[0].get("backend") if per_lobe else None
    H, W = m.shape
    img = np.zeros((H, W, C))
    img[m] = occ
    un = np.zeros((H, W, C))
    un[m] = unocc
    er = np.zeros((H, W))
    er[m] = bound
    if not (np.all(np.isfinite(img)) and np.all(np.isfinite(un))):
        raise IBLError("reference produced non-finite values")
    return ReferenceResult(image=img, unoccluded=un, mask=m, gbuffer=gb, info=info, error=er if converged else None)


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
    from ..groundtruth.phong_convolution import lobe_average as _lobe_average

    a = check_environment(cube)
    N = a.shape[1]
    lab = np.asarray(labels).reshape(-1)
    if lab.shape[0] != 6 * N * N:
        raise LayoutError(f"labels must have shape (6, {N}, {N})")
    L = int(lab.max()) + 1 if n_regions is None else int(n_regions)
    out = _lobe_average(a, dirs, s, labels=lab.reshape(6, N, N), n_regions=L, chunk=chunk)  # (P, L, C)
    return np.moveaxis(out.reshape(-1, L, a.shape[-1]), 1, 0)


# ------------------------------------------------------------------------------------------------
# converged reference (:mod:`ibl_ref.rendering.reference_converged`) and the radiance levels it samples
# ------------------------------------------------------------------------------------------------
from .reference_converged import DEFAULT_RTOL, ERR_FLOOR, LOBE_TAIL_CUT, converged_shading  # noqa: E402,F401


def radiance_at_face_size(a: np.ndarray, n: int) -> np.ndarray:
    """The map's piecewise-constant radiance as exact area averages on face size n (any n ≥ 1)."""
    import math

    N = a.shape[1]
    if n % N == 0:
        return _upsample(a, n)
    if N % n == 0:
        return coarse_env(a, n)
    return coarse_env(_upsample(a, N * n // math.gcd(N, n)), n)


def _upsample(a: np.ndarray, M: int) -> np.ndarray:
    """Nearest-texel (piecewise-constant) radiance of the (6, N, N, C) map on face size M (a multiple of N)."""
    N = a.shape[1]
    k = M // N
    return np.repeat(np.repeat(a, k, axis=1), k, axis=2)
