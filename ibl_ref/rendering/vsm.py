"""Variance shadow maps (Donnelly & Lauritzen 2006) as used by Knuth et al. (2014), Sec. 3.3 and 4.

Knuth et al. compute the visibility ``VIS_i`` of each median-cut region (Eq. 5) with a variance shadow map of a
directional light placed at the region's centroid direction, "softened by applying a Gaussian filter over the
entire depth texture [whose] size depends on the area of the corresponding PEM" (Sec. 4); the maps are stored
as ``GL_RG16F`` (Fig. 8), i.e. half floats.

Pipeline implemented here (every choice is an explicit parameter):

1. Depth map from the light's orthographic camera (:func:`ibl_ref.rendering.camera.light_camera`, fitted to the scene's
   bounding sphere) with the rasterizer (:func:`ibl_ref.rendering.raster.render_depth`).  Depth is **normalised** to
   ``d = depth / far ∈ [0, 1]`` (``far = 2R``), as a GPU stores it; texels that see no geometry hold ``d = 1``.
2. Moments ``M1 = d``, ``M2 = d²`` stored in ``dtype`` (``"float16"`` = the paper's RG16F, ``"float32"``,
   ``"float64"``).
3. Separable Gaussian blur of both moments (``scipy.ndimage.gaussian_filter``, ``mode="nearest"``, truncated at
   4σ), computed in float32 (float64 for ``dtype="float64"``) and stored back in ``dtype`` — as a GPU blur pass
   reads and writes the RG16F texture.
4. Look-up: bilinear filtering of the moments at the receiver's light-space position (texel centres on
   integers, clamped at the border), then Chebyshev's one-sided bound (Donnelly & Lauritzen 2006, Eq. 5)::

       σ² = max(M2 − M1², σ²_min),  p_max = σ² / (σ² + (t − M1)²)  for t > M1, else 1,

   with receiver depth ``t = d_receiver − depth_bias``, and the light-bleeding reduction
   ``clamp((p_max − k)/(1 − k), 0, 1)`` (Lauritzen, GPU Gems 3 ch. 8; ``k = 0`` disables it).

**Blur width from the region's solid angle.**  A region of solid angle Ω is treated as a disc light of angular
radius θ with the same solid angle, Ω = 2π(1 − cos θ) (for small Ω, θ ≈ √(Ω/π), docs/background.md §4).  A blocker at
distance Δd above a receiver casts a penumbra of total width ≈ 2·Δd·tanθ: the light's disc projected to the
receiver has radius ρ = Δd·tanθ.  Across a straight shadow edge the visibility is the cumulative 1D marginal
of that uniform disc, whose standard deviation is ρ/2; the Gaussian blur is given the same standard deviation::

    σ_texels = Δd · tanθ / (2 · texel_size)

``Δd = occluder_distance`` is a scene-dependent parameter (one value per map: the paper's fixed-size blur cannot
follow the actual blocker distance; that is PCSS's job) with default ``0.25 × scene bounding radius``.
Pass ``sigma_texels`` to override the mapping.

Precision (``dtype="float16"``): M2 − M1² cancels catastrophically.  With d ≈ 0.5, the half-float spacing of
M2 ≈ 0.25 is 2⁻¹³ ≈ 1.2e-4, so variances below ~1e-4 (depth spreads below ~1 % of the depth range) are
noise; ``benchmarks/bench_raster.py`` and the tests measure the resulting visibility error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import OrthographicCamera, light_camera
from ..errors import IBLError
from .raster import prepare_scene
from .raster import render_depth

__all__ = [
    "VarianceShadowMap",
    "cap_half_angle",
    "blur_sigma_texels",
    "chebyshev_upper_bound",
    "reduce_light_bleeding",
    "build_vsm",
    "visibility",
]

_DTYPES = {"float16": np.float16, "float32": np.float32, "float64": np.float64}


def cap_half_angle(solid_angle) -> np.ndarray:
    """Half-angle θ (rad) of the spherical cap with solid angle Ω: Ω = 2π(1 − cos θ).  Ω ∈ [0, 4π]."""
    om = np.asarray(solid_angle, dtype=np.float64)
    if np.any(~np.isfinite(om)) or np.any(om < 0) or np.any(om > 4 * np.pi + 1e-12):
        raise IBLError(f"solid angle must be in [0, 4π] sr, got {solid_angle!r}")
    return np.arccos(np.clip(1.0 - om / (2.0 * np.pi), -1.0, 1.0))


def blur_sigma_texels(solid_angle, texel_size: float, occluder_distance: float) -> float:
    """Gaussian σ in shadow-map texels for a region of solid angle Ω (see module docstring).

    ``σ = Δd · tanθ / (2 · texel_size)``; θ is capped at 80° (tanθ ≤ 5.7) so that half-sphere regions give a
    finite, very wide blur instead of an infinite one.
    """
    theta = np.minimum(cap_half_angle(solid_angle), np.radians(80.0))
    if not (texel_size > 0 and occluder_distance >= 0):
        raise IBLError(f"need texel_size > 0 and occluder_distance >= 0, got {texel_size}, {occluder_distance}")
    return float(occluder_distance * np.tan(theta) / (2.0 * texel_size))


def chebyshev_upper_bound(t, m1, m2, min_variance: float):
    """One-sided Chebyshev bound p_max (Donnelly & Lauritzen 2006, Eq. 5); 1 where t ≤ m1."""
    var = np.maximum(m2 - m1 * m1, min_variance)
    dt = t - m1
    p = var / (var + dt * dt)
    return np.where(dt > 0, p, 1.0)


def reduce_light_bleeding(p, k: float):
    """Light-bleeding reduction clamp((p − k)/(1 − k), 0, 1); k = 0 returns p."""
    if not (0.0 <= k < 1.0):
        raise IBLError(f"light-bleeding reduction k must be in [0, 1), got {k}")
    if k == 0:
        return p
    return np.clip((p - k) / (1.0 - k), 0.0, 1.0)


@dataclass
class VarianceShadowMap:
    """A filtered moment map of one directional light.

    Attributes
    ----------
    camera : OrthographicCamera — the light's view (``forward = −direction``).
    moments : (H, W, 2) array in ``dtype`` — blurred (M1, M2) of normalised depth.
    direction : (3,) unit vector toward the light.
    solid_angle : float — Ω of the region (sr).
    sigma_texels : float — blur used.
    dtype : str
    depth_bias, min_variance, bleed_reduction : float — look-up parameters (normalised depth units).
    coverage : (H, W) bool — texels that saw geometry.
    """

    camera: OrthographicCamera
    moments: np.ndarray
    direction: np.ndarray
    solid_angle: float
    sigma_texels: float
    dtype: str
    depth_bias: float
    min_variance: float
    bleed_reduction: float
    coverage: np.ndarray


def build_vsm(
    meshes,
    direction,
    solid_angle: float = 0.0,
    *,
    resolution: int = 512,
    occluder_distance: float | None = None,
    sigma_texels: float | None = None,
    dtype: str = "float32",
    depth_bias: float = 1e-3,
    min_variance: float = 1e-6,
    bleed_reduction: float = 0.0,
    margin: float = 0.05,
    timings: dict | None = None,
) -> VarianceShadowMap:
    """Render and filter the variance shadow map of one directional light.

    Parameters
    ----------
    meshes : occluders/receivers (see :func:`ibl_ref.rendering.raster.prepare_scene`)
    direction : (3,) direction toward the light (e.g. ``PEMSet.lights.directions[i]``)
    solid_angle : Ω of the light's region in sr (0 → hard shadows)
    resolution : shadow-map size (square)
    occluder_distance : Δd of the blur mapping (world units); default 0.25 × scene bounding radius
    sigma_texels : explicit blur σ in texels (overrides the Ω mapping)
    dtype : ``"float16"`` (paper's RG16F), ``"float32"`` (default) or ``"float64"``
    depth_bias : subtracted from the receiver's normalised depth (units of the depth range ``2R``)
    min_variance : σ²_min of the Chebyshev bound (normalised depth²)
    bleed_reduction : k of the light-bleeding reduction (0 = off)
    margin : relative enlargement of the bounding sphere for the light camera
    timings : dict, optional
        Adds the wall-clock seconds of the two stages to ``timings["shadow_maps"]`` (depth rendering) and
        ``timings["blur"]`` (moments + Gaussian blur), for the cost split of Fig. 7.
    """
    import time

    from scipy.ndimage import gaussian_filter


    if dtype not in _DTYPES:
        raise IBLError(f"dtype must be one of {sorted(_DTYPES)}, got {dtype!r}")
    if not (depth_bias >= 0 and min_variance > 0):
        raise IBLError(f"need depth_bias >= 0 and min_variance > 0, got {depth_bias}, {min_variance}")
    reduce_light_bleeding(0.5, bleed_reduction)  # validates k
    scene = prepare_scene(meshes)
    centre, radius = scene.bounds()
    t0 = time.perf_counter()
    cam = light_camera(direction, centre, radius, resolution=resolution, margin=margin)
    depth, cov = render_depth(scene, cam)
    t1 = time.perf_counter()
    d = np.clip(depth / cam.far, 0.0, 1.0)
    if sigma_texels is None:
        dd = 0.25 * radius if occluder_distance is None else float(occluder_distance)
        sigma_texels = blur_sigma_texels(solid_angle, cam.texel_size, dd)
    else:
        cap_half_angle(solid_angle)  # validates Ω
    sigma_texels = float(sigma_texels)
    if not (sigma_texels >= 0 and np.isfinite(sigma_texels)):
        raise IBLError(f"sigma_texels must be finite and >= 0, got {sigma_texels}")
    store = _DTYPES[dtype]
    work = np.float64 if dtype == "float64" else np.float32
    m = np.stack([d, d * d], axis=-1).astype(store)  # render target write (quantised to the storage type)
    if sigma_texels > 0:
        m = m.astype(work)
        for c in range(2):
            m[..., c] = gaussian_filter(m[..., c], sigma=sigma_texels, mode="nearest", truncate=4.0)
        m = m.astype(store)  # blur pass writes back to the storage texture
    if timings is not None:
        timings["shadow_maps"] = timings.get("shadow_maps", 0.0) + (t1 - t0)
        timings["blur"] = timings.get("blur", 0.0) + (time.perf_counter() - t1)
    return VarianceShadowMap(
        camera=cam,
        moments=m,
        direction=-cam.forward,
        solid_angle=float(solid_angle),
        sigma_texels=sigma_texels,
        dtype=dtype,
        depth_bias=float(depth_bias),
        min_variance=float(min_variance),
        bleed_reduction=float(bleed_reduction),
        coverage=cov,
    )


def _bilinear(img, x, y):
    """Bilinear sample of (H, W, C) at continuous texel coordinates (centres on integers), clamped to the edge."""
    H, W = img.shape[:2]
    x = np.clip(x, 0.0, W - 1.0)
    y = np.clip(y, 0.0, H - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), W - 2) if W > 1 else np.zeros(x.shape, np.int64)
    y0 = np.minimum(np.floor(y).astype(np.int64), H - 2) if H > 1 else np.zeros(y.shape, np.int64)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    x1 = np.minimum(x0 + 1, W - 1)
    y1 = np.minimum(y0 + 1, H - 1)
    return (
        (1 - fy) * ((1 - fx) * img[y0, x0] + fx * img[y0, x1])
        + fy * ((1 - fx) * img[y1, x0] + fx * img[y1, x1])
    )


def visibility(points_world, vsm: VarianceShadowMap) -> np.ndarray:
    """VSM visibility in [0, 1] of world points (..., 3) for one light (Sec. 3.3, ``VIS_i`` of Eq. 5)."""
    p = np.asarray(points_world, dtype=np.float64)
    if p.shape[-1:] != (3,):
        raise IBLError(f"points: expected (..., 3), got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise IBLError("points: contains NaN or Inf")
    cam = vsm.camera
    x, y, depth, _ = cam.project(p)
    work = np.float64 if vsm.dtype == "float64" else np.float32
    mom = _bilinear(vsm.moments.astype(work), (x - 0.5).astype(work), (y - 0.5).astype(work))
    t = (depth / cam.far - vsm.depth_bias).astype(work)
    pm = chebyshev_upper_bound(t, mom[..., 0], mom[..., 1], work(vsm.min_variance))
    pm = reduce_light_bleeding(pm, vsm.bleed_reduction)
    return np.clip(pm.astype(np.float64), 0.0, 1.0)
