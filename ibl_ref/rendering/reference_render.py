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

Default: converged to a tolerance (``render_reference(..., rtol=2e-3)``, :func:`converged_shading`).  Two
discretisations are refined separately until each one's estimated share of the image's relative L1 error is
≤ rtol/2: the radiance × lobe quadrature (the map's exact piecewise-constant radiance summed at texel centres of a
face size M = N·2^k, compared with M/2 → 2M) and the visibility (one exact ray per direction cell along the cell's
energy centroid, applied to the exact weight of the whole cell; cells split 2×2 where a shadow edge crosses the
pixel's lobe, compared level to level; a pixel may leave its dimmest edge cells unrefined within
``VIS_SKIP_SHARE``·rtol, which is added to its estimate).  Conventions (docs/background.md §8): one-sided shading
(n·v ≤ 0 → black, ``sided="two"`` flips n), both lobes over the hemisphere Ω⁺ of the shading normal n with the lobe
normalised over the whole sphere (the normalised Phong BRDF of Kán et al. 2015, Eq. 2), one material per mesh.
Scattered refinement rays are cast one by one against a two-level bounding-sphere hierarchy (:class:`_LeafBVH`,
Möller–Trumbore), dense ones with the projection caster below.

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
from ..errors import IBLError, LayoutError, check_radiance

__all__ = [
    "ReferenceResult",
    "coarse_env",
    "coarse_directions",
    "lobe_half_angle",
    "env_size_for_exponent",
    "lobe_average",
    "parallel_visibility",
    "reference_shading",
    "render_reference",
    "coarse_level_error",
    "estimate_reference_rays",
    "exact_pem_lookup",
]

DIRECTION_MODES = ("centroid", "centre")
BACKENDS = ("project", "trimesh")


# ------------------------------------------------------------------------------------------------
# environment quadrature
# ------------------------------------------------------------------------------------------------
def _check_env(cube) -> np.ndarray:
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

    a = _check_env(cube)
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
    a = _check_env(cube)
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

    a = _check_env(cube)
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
        rtol, err_rel_l1 (estimated Σ|error|/Σ|image|), err_rel_p99 (99th percentile of the per-pixel relative
        estimate over lit pixels), converged; fixed quadrature: n_env_diffuse, n_env_glossy, neglected_weight_max
    error : (H, W) or None — estimated absolute error per pixel (channel mean) of the converged reference
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
    a = _check_env(cube)
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
                     n_vis_max: int = 64, n_quad_max: int = 256,
                     n_env_diffuse: int | None = 8, n_env_glossy: int | None = None, directions: str = "centroid",
                     texels_per_halfwidth: float = 1.0, weight_cutoff: float = 1e-6, backend: str = "project",
                     smooth_normals: bool = True, gbuffer=None, progress: bool = False) -> ReferenceResult:
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
    n_vis_max, n_quad_max : caps of the visibility and quadrature levels of the converged reference
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
    a = _check_env(cube)
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
            o, u, e, inf = converged_shading(scene, P[sel], n[sel], fn[sel], dl[sel], a, s, rtol=rtol,
                                             n_vis_max=n_vis_max, n_quad_max=n_quad_max, progress=progress)
            err[sel] += k[:, 0] * e
        else:
            ne = (min(N, n_env_diffuse or 8) if s == 1.0 else
                  min(N, n_env_glossy or env_size_for_exponent(s, N, texels_per_halfwidth)))
            if np.isfinite(s) and ne >= N and lobe_half_angle(s) < texels_per_halfwidth * (np.pi / 2) / N:
                warnings.warn(f"{name} lobe s={s:g} is narrower than {texels_per_halfwidth} texels of the {N}² map: "
                              "the reference is limited by the map's resolution", UserWarning, stacklevel=2)
            if backend == "trimesh":
                from .raycast import _check_rays_budget

                _check_rays_budget(estimate_reference_rays(int(sel.sum()), ne), len(scene.faces))
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
        lit = y > 1e-3 * max(float(np.abs(y).mean()), 1e-300)
        info["err_rel_p99"] = float(np.percentile(err[lit] / y[lit], 99)) if lit.any() else 0.0
        info["converged"] = bool(info["err_rel_l1"] <= rtol)  # per lobe: vis_converged, quad_converged (≤ rtol/2)
    H, W = m.shape
    img = np.zeros((H, W, C))
    img[m] = occ
    un = np.zeros((H, W, C))
    un[m] = unocc
    er = np.zeros((H, W))
    er[m] = err
    if not (np.all(np.isfinite(img)) and np.all(np.isfinite(un))):
        raise IBLError("reference produced non-finite values")
    return ReferenceResult(image=img, unoccluded=un, mask=m, gbuffer=gb, info=info, error=er if converged else None)


def coarse_level_error(cube, dirs, s: float, n_env: int, directions: str = "centroid") -> dict:
    """Error of the coarse-level quadrature with V ≡ 1 at lobe directions ``dirs`` (P, 3).

    Compares :func:`lobe_average` at level ``n_env`` against the exact lobe average of the full-resolution map
    (the formula of :func:`ibl_ref.groundtruth.phong_convolution.convolve_exact`, evaluated at ``dirs``).  Returns
    ``rel_l1`` (Σ|a−b|/Σ|b| over all pixels and channels) and ``rel_max`` (max |a−b|/b over pixel luminance).
    """
    a = _check_env(cube)
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

    a = _check_env(cube)
    N = a.shape[1]
    lab = np.asarray(labels).reshape(-1)
    if lab.shape[0] != 6 * N * N:
        raise LayoutError(f"labels must have shape (6, {N}, {N})")
    L = int(lab.max()) + 1 if n_regions is None else int(n_regions)
    out = _lobe_average(a, dirs, s, labels=lab.reshape(6, N, N), n_regions=L, chunk=chunk)  # (P, L, C)
    return np.moveaxis(out.reshape(-1, L, a.shape[-1]), 1, 0)


# ------------------------------------------------------------------------------------------------
# converged reference: radiance-exact quadrature, adaptively refined visibility, error estimate
# ------------------------------------------------------------------------------------------------
#: default tolerance of :func:`render_reference` (relative L1 of the image, estimated)
DEFAULT_RTOL = 2e-3
#: lobe support of the converged quadrature: max(d·ω,0)^s below this (relative to the peak 1) is dropped (from the
#: numerator and the normalisation alike; the dropped share is < 4π·1e-8/(2π/(s+1)) ≪ 1e-6 for s ≤ 100)
LOBE_TAIL_CUT = 1e-8


def _cube_neighbours(n: int, k: int = 8) -> np.ndarray:
    """Indices (6n², k) of the k nearest other cells of level n by direction (across face borders)."""
    from scipy.spatial import cKDTree

    from ..environment.envmap import texel_directions

    w = np.asarray(texel_directions(n)).reshape(-1, 3)
    _, idx = cKDTree(w).query(w, k=k + 1)
    return idx[:, 1:]


def _children(V: np.ndarray, n: int) -> np.ndarray:
    """Cell values (P, 6n²) of level n repeated onto the 2×2 children of level 2n → (P, 6(2n)²)."""
    P = V.shape[0]
    v = V.reshape(P, 6, n, 1, n, 1)
    return np.broadcast_to(v, (P, 6, n, 2, n, 2)).reshape(P, 6 * 4 * n * n)


def _radiance_at(a: np.ndarray, n: int) -> np.ndarray:
    """The map's piecewise-constant radiance as exact area averages on face size n (any n ≥ 1)."""
    import math

    N = a.shape[1]
    if n % N == 0:
        return _upsample(a, n)
    if N % n == 0:
        return coarse_env(a, n)
    return coarse_env(_upsample(a, N * n // math.gcd(N, n)), n)


def _level_cells(a: np.ndarray, n: int):
    """Cell directions ω_c (6n², 3), solid angles Ω_c (6n²,) and energies E_c = ∫_c Y dω (6n²,) of level n.

    Cells coarser than the map: exact area averages and energy centroids (:func:`coarse_env`,
    :func:`coarse_directions`); finer: sub-texels of constant radiance, directions at their centres.
    """
    import math

    from ..environment.envmap import cube_solid_angles, texel_directions

    N = a.shape[1]
    om = np.asarray(cube_solid_angles(n)).reshape(-1)
    Lc = _radiance_at(a, n)
    if n % N == 0:
        w = np.asarray(texel_directions(n)).reshape(-1, 3)
    else:
        src = a if N % n == 0 else _upsample(a, N * n // math.gcd(N, n))
        w = coarse_directions(src, n, "centroid").reshape(-1, 3)
    return w, om, Lc.mean(axis=-1).reshape(-1) * om


def _upsample(a: np.ndarray, M: int) -> np.ndarray:
    """Nearest-texel (piecewise-constant) radiance of the (6, N, N, C) map on face size M (a multiple of N)."""
    N = a.shape[1]
    k = M // N
    return np.repeat(np.repeat(a, k, axis=1), k, axis=2)


def _lobe(d, nrm, w, s, hemisphere: bool):
    """max(d·ω, 0)^s (P, J), times [n·ω > 0] (the hemisphere Ω⁺ of the shading normal) if ``hemisphere``."""
    c = np.maximum(d @ w.T, 0.0)
    with np.errstate(divide="ignore", under="ignore"):
        f = c if s == 1.0 else np.power(c, s)
    if hemisphere:
        f = f * ((nrm @ w.T) > 0)
    return f


#: directions with fewer rays than this are cast ray by ray (:class:`_LeafBVH`, ≈ 0.15 ms per ray on the
#: 16k-triangle teapot) instead of with one projection set-up per direction (≈ 3 ms per direction)
BVH_MAX_RAYS_PER_DIRECTION = 20


class _LeafBVH:
    """Two-level bounding-sphere hierarchy of a scene's triangles for any-hit tests of scattered rays.

    Triangles are split recursively at the median centroid of the longest bounding-box axis into leaves of at
    most ``leaf`` triangles; each leaf has a bounding sphere.  A ray is tested against every leaf sphere, and
    against the triangles (Möller–Trumbore, inclusive edges, t > 0) of the leaves it passes.  Exact up to float
    rounding, like :func:`_cast_one_direction`; it is cheaper when a direction has few rays (sparse refinement).
    """

    def __init__(self, scene, leaf: int = 48):
        tri = scene.vertices[scene.faces]
        cen = tri.mean(axis=1)
        groups, stack = [], [np.arange(len(tri))]
        while stack:
            idx = stack.pop()
            if len(idx) <= leaf:
                groups.append(idx)
                continue
            c = cen[idx]
            ax = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
            o = idx[np.argsort(c[:, ax], kind="stable")]
            h = len(o) // 2
            stack += [o[:h], o[h:]]
        K = len(groups)
        self.v0 = np.zeros((K, leaf, 3))
        self.e1 = np.zeros((K, leaf, 3))
        self.e2 = np.zeros((K, leaf, 3))
        self.valid = np.zeros((K, leaf), dtype=bool)
        self.centre = np.zeros((K, 3))
        self.radius = np.zeros(K)
        for k, g in enumerate(groups):
            t = tri[g]
            self.v0[k, :len(g)] = t[:, 0]
            self.e1[k, :len(g)] = t[:, 1] - t[:, 0]
            self.e2[k, :len(g)] = t[:, 2] - t[:, 0]
            self.valid[k, :len(g)] = True
            pts = t.reshape(-1, 3)
            c = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
            self.centre[k] = c
            self.radius[k] = np.linalg.norm(pts - c, axis=1).max() * (1 + 1e-9) + 1e-12
        # top level: runs of ``group`` consecutive leaves (depth-first order: neighbouring subtrees) in one sphere
        group = 16
        self.group = group
        G = -(-K // group)
        self.top_centre = np.zeros((G, 3))
        self.top_radius = np.zeros(G)
        for gi in range(G):
            c0, r0 = self.centre[gi * group:(gi + 1) * group], self.radius[gi * group:(gi + 1) * group]
            c = 0.5 * ((c0 - r0[:, None]).min(axis=0) + (c0 + r0[:, None]).max(axis=0))
            self.top_centre[gi] = c
            self.top_radius[gi] = (np.linalg.norm(c0 - c, axis=1) + r0).max() * (1 + 1e-9)
        self.n_leaves = K

    @staticmethod
    def _sphere_hits(o, d, centre, radius):
        """(ray, sphere) index pairs whose ray o + t·d (t > 0) meets the sphere."""
        oc = centre[None, :, :] - o[:, None, :]
        tca = np.einsum("rkc,rc->rk", oc, d)
        d2 = np.einsum("rkc,rkc->rk", oc, oc) - tca ** 2
        return np.nonzero((d2 <= radius[None, :] ** 2) & (tca + radius[None, :] > 0))

    def any_hit(self, o, d, ray_chunk: int = 4096, pair_chunk: int = 8192) -> np.ndarray:
        """hit (R,) bool of the rays o + t·d, t > 0 (d unit)."""
        R = len(o)
        hit = np.zeros(R, dtype=bool)
        for i in range(0, R, ray_chunk):
            oo, dd = o[i:i + ray_chunk], d[i:i + ray_chunk]
            tr, tg = self._sphere_hits(oo, dd, self.top_centre, self.top_radius)
            # expand each (ray, group) pair to its leaves and test the leaf spheres
            lf = (tg[:, None] * self.group + np.arange(self.group)[None, :]).reshape(-1)
            rr0 = np.repeat(tr, self.group)
            ok = lf < self.n_leaves
            rr0, lf = rr0[ok], lf[ok]
            oc = self.centre[lf] - oo[rr0]
            tca = np.einsum("kc,kc->k", oc, dd[rr0])
            d2 = np.einsum("kc,kc->k", oc, oc) - tca ** 2
            hs = (d2 <= self.radius[lf] ** 2) & (tca + self.radius[lf] > 0)
            ray, lf = rr0[hs], lf[hs]
            for j in range(0, len(ray), pair_chunk):
                rr_, kk = ray[j:j + pair_chunk], lf[j:j + pair_chunk]
                keep = ~hit[i + rr_]
                rr_, kk = rr_[keep], kk[keep]
                if len(rr_) == 0:
                    continue
                ox, oy, oz = (oo[rr_, c][:, None] for c in range(3))
                dx, dy, dz = (dd[rr_, c][:, None] for c in range(3))
                ax_, ay_, az_ = (self.e1[kk, :, c] for c in range(3))
                bx, by, bz = (self.e2[kk, :, c] for c in range(3))
                tx, ty, tz = (o_ - self.v0[kk, :, c] for c, o_ in enumerate((ox, oy, oz)))
                px, py, pz = dy * bz - dz * by, dz * bx - dx * bz, dx * by - dy * bx  # d × e2
                det = ax_ * px + ay_ * py + az_ * pz
                ok = self.valid[kk] & (np.abs(det) > 1e-300)
                inv = 1.0 / np.where(ok, det, 1.0)
                u = (tx * px + ty * py + tz * pz) * inv
                qx, qy, qz = ty * az_ - tz * ay_, tz * ax_ - tx * az_, tx * ay_ - ty * ax_  # t × e1
                v = (dx * qx + dy * qy + dz * qz) * inv
                t = (bx * qx + by * qy + bz * qz) * inv
                tol = -1e-12
                h = ok & (u >= tol) & (v >= tol) & (u + v <= 1 - tol) & (t > 0)
                hit[i + rr_[h.any(axis=1)]] = True
        return hit


def _cast_pairs(scene, P, fn, w, pix, cell, eps, bvh=None):
    """Exact visibility (K,) uint8 of the (point ``pix[k]``, direction ``w[cell[k]]``) pairs (directions below the
    receiving triangle's plane are occluded without casting).  With ``bvh`` (:class:`_LeafBVH`) the rays are
    tested one by one from p + eps·n_f + eps·ω; otherwise one projection set-up per distinct direction with the
    package's exact caster :func:`ibl_ref.rendering.raycast.parallel_visibility` (a triangle blocks when it is more than eps
    nearer the light; no origin offset).  Default eps: :data:`ibl_ref.rendering.raycast.VISIBILITY_EPS` × scene radius."""
    from .raycast import VISIBILITY_EPS
    from .raycast import parallel_visibility as _parallel

    out = np.ones(len(pix), dtype=np.uint8)
    if len(pix) == 0:
        return out
    e = VISIBILITY_EPS * scene.bounds()[1] if eps is None else eps
    dj = w[cell]
    f = fn[pix]
    below = np.einsum("kc,kc->k", f, dj) < 0
    out[below] = 0
    up = np.flatnonzero(~below)
    cu = cell[up]
    order = np.argsort(cu, kind="stable")
    cs = cu[order]
    starts = np.flatnonzero(np.r_[True, cs[1:] != cs[:-1]])
    ends = np.r_[starts[1:], len(cs)]
    scattered = []
    for a0, a1 in zip(starts, ends):
        k = up[order[a0:a1]]
        if bvh is not None and len(k) < BVH_MAX_RAYS_PER_DIRECTION:
            scattered.append(k)
            continue
        out[k] = _parallel(scene, P[pix[k]], w[cs[a0]], eps=e) > 0.5
    if scattered:
        k = np.concatenate(scattered)
        out[k] = ~bvh.any_hit(P[pix[k]] + e * f[k] + e * dj[k], dj[k])
    return out


def _visibility_cells(scene, P, fn, w, mask, eps):
    """Exact visibility (P, J) uint8 of cell directions ``w`` for the masked pairs (others 1)."""
    V = np.ones(mask.shape, dtype=np.uint8)
    pix, cell = np.nonzero(mask)
    V[pix, cell] = _cast_pairs(scene, P, fn, w, pix, cell, eps)
    return V


#: share of rtol a pixel may leave unrefined in its dimmest shadow-edge cells (their possible change is bounded by
#: their weight and is added to the estimate)
VIS_SKIP_SHARE = 0.25


def converged_shading(scene, points, normals, face_normals, d_lobe, cube, s: float, *, rtol: float = DEFAULT_RTOL,
                      n_vis_start: int = 8, n_vis_max: int = 64, n_quad_max: int = 256, weight_cutoff: float = 1e-4,
                      eps: float | None = None, chunk: int = 256, progress: bool = False):
    """Visibility-weighted lobe averages A_s(d) of (*) converged to ``rtol`` → (occluded, unoccluded, error, info).

    Two independent discretisations, each refined until its estimated share of the image error is ≤ rtol/2:

    * **quadrature** (radiance × lobe): the map's piecewise-constant radiance (each texel constant over its exact
      solid angle, nearest-texel upsampled) times max(d·ω,0)^s [n·ω > 0] summed at texel centres of face size M
      (a power-of-two multiple of N, ≥ 4 texels across the lobe's half width).  Estimate: |U_M − U_{M/2}| of the
      unoccluded average (midpoint rule: the error of M is ≈ ⅓ of that difference for smooth lobes, so this is
      conservative); M doubles while the image-level estimate exceeds rtol/2.
    * **visibility**: one exact ray per visibility cell (face size n, ray along the cell's energy centroid), applied
      to the exact radiance-lobe weight of the whole cell.  Starting at ``n_vis_start`` the cells are split 2×2
      where the visibility differs from one of the 8 nearest cells (a shadow edge crosses the lobe) and the lobe
      weight is above ``weight_cutoff`` × the pixel's largest; the others inherit their parent's value.  Estimate:
      |A(n) − A(n/2)| per pixel (first-order convergence at shadow edges: the error of level n is about that
      difference); n doubles while the image-level estimate exceeds rtol/2, up to ``n_vis_max``.

    The normalisation Σ max(d·ω,0)^s Ω runs over the whole sphere at level M (→ 2π/(s+1)); the hemisphere Ω⁺ of
    the shading normal n clips the numerator only, so L ≡ 1 without occluders gives (s+1)/(2π)∫_{Ω⁺} cos^s α dω
    ≤ 1, the same as the one-sided BRDF of :mod:`ibl_ref.rendering.mitsuba_render`.  ``error`` (P,) is the estimated absolute
    error of the occluded value (channel mean): quadrature + visibility estimates.
    """
    from scipy import sparse

    from ..environment.envmap import cube_solid_angles, direction_to_texel, texel_directions
    from .raster import prepare_scene

    a = _check_env(cube)
    N = a.shape[1]
    C = a.shape[-1]
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    fn = np.asarray(face_normals, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(d_lobe, dtype=np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    s = float(s)
    if not (np.isfinite(s) and s >= 1.0):
        raise IBLError(f"Phong exponent s must be finite and >= 1 for the converged reference, got {s}")
    rtol = float(rtol)
    if not (rtol > 0):
        raise IBLError(f"rtol must be > 0, got {rtol}")
    t0 = time.perf_counter()
    nP = len(P)
    hemi = True

    # ---- visibility: adaptive refinement with approximate (cell-level) weights ----------------------------------
    n = int(n_vis_start)
    if n < 1 or int(n_vis_max) < 2 * n:
        raise IBLError(f"need 1 <= n_vis_start and n_vis_max >= 2 * n_vis_start, got {n_vis_start}, {n_vis_max}")
    w_c, om_c, E_c = _level_cells(a, n)
    f = _lobe(d, nrm, w_c, s, hemi)
    lobe_w = f * om_c
    relevant = lobe_w > weight_cutoff * lobe_w.max(axis=1, keepdims=True)
    scene = prepare_scene(scene, warn=False)
    V = _visibility_cells(scene, P, fn, w_c, relevant, eps)
    n_rays = int(relevant.sum())
    vis_est = None
    bvh = None
    levels = [dict(n_vis=n, rays=n_rays)]
    while True:
        if 2 * n > n_vis_max:
            break
        nbr = _cube_neighbours(n)
        n2 = 2 * n
        w2, om2, E2 = _level_cells(a, n2)
        Vin = _children(V, n)
        est = np.zeros(nP)
        ref = np.zeros(nP)
        skipped = np.zeros(nP)
        pairs_p, pairs_c = [], []
        for i in range(0, nP, 4 * chunk):
            sl = slice(i, min(i + 4 * chunk, nP))
            Vi = V[sl]
            edge = (Vi[:, nbr] != Vi[:, :, None]).any(axis=2)  # (p, 6n²): a shadow edge crosses or touches the cell
            f2 = _lobe(d[sl], nrm[sl], w2, s, hemi) * om2
            rel2 = f2 > weight_cutoff * f2.max(axis=1, keepdims=True)
            cand = _children(edge.astype(np.uint8), n).astype(bool) & rel2
            W2 = f2 * (E2 / om2)[None, :]  # ≈ ∫_cell L·lobe dω (lobe at the cell direction)
            ws2 = f2.sum(axis=1) + 1e-300
            A2 = (Vin[sl] * W2).sum(axis=1) / ws2
            # leave the dimmest candidates of each pixel unrefined while their summed weight is within the budget
            pp, cc = np.nonzero(cand)
            wv = W2[pp, cc] / ws2[pp]
            o = np.lexsort((wv, pp))
            pp, cc, wv = pp[o], cc[o], wv[o]
            if len(pp):
                first = np.r_[0, np.flatnonzero(pp[1:] != pp[:-1]) + 1]
                csum = np.cumsum(wv)
                cum = csum - np.repeat(csum[first] - wv[first], np.diff(np.r_[first, len(pp)]))
                skip = cum <= VIS_SKIP_SHARE * rtol * A2[pp]
            else:
                skip = np.zeros(0, dtype=bool)
            np.add.at(skipped[sl], pp[skip], wv[skip])
            pairs_p.append(pp[~skip] + i)
            pairs_c.append(cc[~skip])
        pix = np.concatenate(pairs_p)
        cell = np.concatenate(pairs_c)
        V2 = Vin.copy()
        if bvh is None:
            bvh = _LeafBVH(scene)
        V2[pix, cell] = _cast_pairs(scene, P, fn, w2, pix, cell, eps, bvh=bvh)
        new_rays = len(pix)
        for i in range(0, nP, 4 * chunk):
            sl = slice(i, min(i + 4 * chunk, nP))
            f2 = _lobe(d[sl], nrm[sl], w2, s, hemi) * om2
            W2 = f2 * (E2 / om2)[None, :]
            ws2 = f2.sum(axis=1) + 1e-300
            est[sl] = np.abs(((V2[sl].astype(float) - Vin[sl]) * W2).sum(axis=1)) / ws2 + skipped[sl]
            ref[sl] = (V2[sl] * W2).sum(axis=1) / ws2
        n_rays += new_rays
        V, n = V2, n2
        vis_est = est
        rel = float(est.sum() / max(ref.sum(), 1e-300))
        levels.append(dict(n_vis=n, rays=new_rays, est_rel_l1=rel))
        if progress:
            from ..progress import say

            say(f"reference: visibility level {n}: {new_rays} rays, estimated rel. L1 {rel:.2e}")
        if rel <= rtol / 2:
            break
    n_vis = n

    # ---- quadrature: exact radiance × lobe at level M, cells summed onto the visibility level ------------------
    need = 4.0 * (np.pi / 2) / float(lobe_half_angle(s))  # ≥ 4 texels across the half width
    M = N
    while M < n_vis or M % n_vis or (M < need and M < n_quad_max):
        M *= 2

    # pixels in lobe-direction order, so that a chunk's lobes overlap and the support cut below is tight
    fo, ro, co = direction_to_texel(d, 8)
    order = np.argsort((np.asarray(fo) * 8 + ro) * 8 + co, kind="stable")
    cos_cut = LOBE_TAIL_CUT ** (1.0 / s)  # texels with max(d·ω,0)^s < LOBE_TAIL_CUT are outside the support

    def _quad(Mq):
        """occluded (P, C) (None if level Mq is not nested in the visibility cells) and unoccluded (P, C)."""
        wq = np.asarray(texel_directions(Mq)).reshape(-1, 3)
        oq = np.asarray(cube_solid_angles(Mq)).reshape(-1)
        Lq = _radiance_at(a, Mq).reshape(-1, C)
        nested = Mq >= n_vis and Mq % n_vis == 0
        k = Mq // n_vis if nested else 1
        # cell (visibility level) of every quadrature texel
        f_, i_, j_ = np.meshgrid(np.arange(6), np.arange(Mq) // k, np.arange(Mq) // k, indexing="ij")
        cell = ((f_ * n_vis + i_) * n_vis + j_).reshape(-1) if nested else None
        occ = np.zeros((nP, C)) if nested else None
        un = np.zeros((nP, C))
        for i in range(0, nP, chunk):
            idx = order[i:i + chunk]
            c = d[idx] @ wq.T
            cols = np.flatnonzero(c.max(axis=0) > cos_cut)
            c = np.maximum(c[:, cols], 0.0)
            with np.errstate(divide="ignore", under="ignore"):
                lob = (c if s == 1.0 else np.power(c, s)) * oq[cols]
            ws = lob.sum(axis=1)
            wv = lob * ((nrm[idx] @ wq[cols].T) > 0)
            un[idx] = (wv @ Lq[cols]) / ws[:, None]
            if nested:
                # Σ over the texels of each visibility cell as a sparse (texel → cell) matrix product per channel
                St = sparse.csr_matrix((np.ones(len(cols)), (cell[cols], np.arange(len(cols)))),
                                       shape=(6 * n_vis * n_vis, len(cols)))
                Vi = V[idx]
                for ch in range(C):
                    Wc = (St @ (wv * Lq[cols, ch][None, :]).T).T  # (p, cells)
                    occ[idx, ch] = (Vi * Wc).sum(axis=1) / ws
        return occ, un

    quad_levels = []
    occ_c, un_c = _quad(M)
    while True:
        # the map's radiance is exact at every M ≥ N (piecewise constant); what M changes is the lobe sampling
        # inside texels: compare M with 2M and keep the finer one (estimate = their difference, conservative for
        # the midpoint rule, whose error at 2M is about a quarter of the error at M)
        occ, un = _quad(2 * M)
        q_est = np.abs(un - un_c).mean(axis=-1)
        q_rel = float(q_est.sum() / max(np.abs(un).mean(axis=-1).sum(), 1e-300))
        M *= 2
        quad_levels.append(dict(n_quad=M, est_rel_l1=q_rel))
        if q_rel <= rtol / 2 or 2 * M > n_quad_max:
            break
        un_c = un
    err = q_est + (vis_est if vis_est is not None else 0.0)
    info = dict(n_vis=int(n_vis), n_quad=int(M), n_rays=int(n_rays), visibility_levels=levels,
                quadrature_levels=quad_levels, weight_cutoff=float(weight_cutoff), rtol=rtol,
                vis_converged=bool(vis_est is not None and levels[-1].get("est_rel_l1", 1.0) <= rtol / 2),
                quad_converged=bool(q_rel <= rtol / 2), time_s=time.perf_counter() - t0)
    return occ, un, err, info
