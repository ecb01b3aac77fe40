"""Kautz & McCool (2000) renders of the teapot, one method per call — the library side of ``ibl-ref km00-render``.

:func:`render_single_method` shades the teapot's G-buffer (:func:`teapot_gbuffer`, the camera of
:func:`ibl_ref.rendering.scenes.default_camera`) by one of :data:`ibl_ref.lobes.lobe_render.SINGLE_METHODS`
(:func:`ibl_ref.lobes.lobe_render.shade_single_method`: per-pixel exact reference, multi-lobe 3D maps, single lobe,
single 2D lobe, or the lobes' Phong fits in the sqrt-cos filter pyramid of Knuth et al. 2014, built here through
the prefilter registry, :func:`ibl_ref.prefilter.registry.build_prefilter`).  No visibility (KM2000 has none).
"""

from __future__ import annotations

import time

import numpy as np
from ..environment.validated import as_environment
from ..errors import IBLError
from ..lobes.brdfs import get_brdf
from ..lobes.lobe_render import check_single_method
from ..lobes.lobe_render import shade_single_method
from ..synthetic.synthetic_meshes import make_mesh
from .raster import rasterize
from .scenes import default_camera

__all__ = ["teapot_gbuffer", "render_single_method"]


def teapot_gbuffer(width: int, height: int | None = None):
    """G-buffer of the teapot alone under :func:`ibl_ref.rendering.scenes.default_camera` (``width`` px; ``height`` crops)."""
    import dataclasses


    meshes = [(make_mesh("teapot"), 0)]
    cam = default_camera(meshes, size=int(width))
    if height is not None and int(height) != int(width):
        cam = dataclasses.replace(cam, height=int(height))
    return rasterize(meshes, cam)


def render_single_method(method: str, env: np.ndarray, *, width: int = 256, height: int | None = None,
                         n_theta: int = 16, progress: bool = False, **shade_kw):
    """Render the teapot (camera of ``ibl-ref experiment fig6``, :func:`ibl_ref.rendering.scenes.default_camera`) by one
    method; returns (image (H, W, C), mask (H, W), info dict).  ``method``, ``n_theta`` and ``shade_kw`` (BRDF, lobe
    count, map and reference settings, ``rescale_lobes``) as in :func:`ibl_ref.lobes.lobe_render.shade_single_method`;
    ``pyramid`` looks the lobes up in the paper's sqrt-cos pyramid of ``env``."""

    check_single_method(method, n_theta)
    env = as_environment(env, "environment cube map")  # once: the prefilter and every method trust it

    with np.errstate(all="ignore"):  # a needle-thin lobe overflows at its peak: check_resolvable refuses it
        get_brdf(shade_kw.get("brdf", "ward"), **(shade_kw.get("brdf_params") or {}))  # a bad BRDF fails first
    t_all = time.perf_counter()
    gb = teapot_gbuffer(width, height)
    m = gb.mask
    if not m.any():
        raise IBLError("the teapot covers no pixel at this image size")
    if method == "pyramid" and shade_kw.get("prefilter") is None:
        from ..prefilter.registry import build_prefilter

        shade_kw["prefilter"] = build_prefilter(env, "pyramid", kernel="sqrtcos")
    vals, info = shade_single_method(method, env, gb.normal[m], gb.view[m], n_theta=n_theta, progress=progress,
                                     **shade_kw)
    H, W = m.shape
    img = np.zeros((H * W, vals.shape[-1]))
    img[m.reshape(-1)] = vals
    info["time_s"] = round(time.perf_counter() - t_all, 3)
    return img.reshape(H, W, -1), m, info
