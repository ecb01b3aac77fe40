"""The unoccluded sphere that ``ibl-ref judge`` shades a user's prefiltered chain on
(:func:`ibl_ref.prefilter.judge.judge`, its ``shading`` argument): the pixels of the orthographic unit sphere seen
from +Z and the lab's exact unoccluded shading of them (:func:`ibl_ref.rendering.unoccluded_reference.integrate`).

It lives in ``rendering`` because the sphere and the exact integral do; :mod:`ibl_ref.prefilter.judge` receives it
as an argument (``prefilter`` does not import ``rendering``).
"""

from __future__ import annotations

import numpy as np

from .sphere_render import orthographic_sphere
from .unoccluded_reference import GGXSpecularLobe, PhongLobe, integrate

__all__ = ["SphereShading"]


class SphereShading:
    """The judge's sphere (:func:`ibl_ref.prefilter.judge.shading_rows`): pixels of the orthographic unit sphere
    seen from +Z and the exact unoccluded shading of a GGX (``lobe="ggx"``: F0, height-correlated Smith) or
    Phong material (``lobe="phong"``: the normalised lobe about the mirror direction, on the normal's hemisphere)."""

    def pixels(self, size: int):
        _, normals, _ = orthographic_sphere(size)
        return normals, np.broadcast_to(np.array([0.0, 0.0, 1.0]), normals.shape).copy()

    def reference(self, env, lobe: str, param: float, normals, views, *, f0: float = 1.0, rtol: float = 2e-3):
        shape = GGXSpecularLobe(param, f0) if lobe == "ggx" else PhongLobe(param, "mirror", clip=True)
        res = integrate(env, shape, normals, views, rtol=rtol)
        return res.value, res.info["err_rel_l1"]
