"""Occlusion methods for image-based lighting: one module per method family, one declared interface, one registry.

An occlusion method turns per-pixel visibility data (an ambient-occlusion value, a bent normal, a geometric normal,
visible fractions of environment regions, a PRT transfer vector) and the shading frame (normal, view, roughness)
into what multiplies or replaces the unoccluded image-based lighting: diffuse and specular factors, region weights
(Knuth et al. 2014, Eq. 5) or an occluded diffuse radiance (PRT).  Each is a pure NumPy formula, float64, vectorised
over pixels; engines' variants of one formula are registry labels with other parameter values.

* :mod:`~ibl_ref.occlusion.interface` — :class:`OcclusionInputs`, :class:`OcclusionResult`,
  :class:`UnoccludedTerms`, :class:`OcclusionMethod` and :func:`shade`;
* :mod:`~ibl_ref.occlusion.registry` — :data:`OCCLUSION_METHODS` (label → method) and :func:`get`;
* the methods: :mod:`~ibl_ref.occlusion.ambient_occlusion` (none, glTF's occlusion map),
  :mod:`~ibl_ref.occlusion.jimenez2016` (multi-bounce AO, GTSO), :mod:`~ibl_ref.occlusion.lagarde2014`
  (specular occlusion from AO, Frostbite and Unreal), :mod:`~ibl_ref.occlusion.horizon_occlusion` (Marmoset,
  Godot), :mod:`~ibl_ref.occlusion.sloan2002` (PRT diffuse transfer), :mod:`~ibl_ref.occlusion.knuth2014_regions`
  (Eq. 5's region weights); :mod:`~ibl_ref.occlusion.spherical_caps` (solid angle of two caps' intersection,
  exact and smoothstep).

Adding a method: its module and one entry in :mod:`~ibl_ref.occlusion.registry` (that module's docstring).

The image of one method (:mod:`~ibl_ref.occlusion.image`): :func:`occlusion_image` shades a scene seen by a camera
under an environment cube with a material by one registered method — the exact unoccluded terms, the inputs the
method declares (``inputs="oracle"``: ray-cast; ``"screen-space"``: GTAO), the method — and returns an
:class:`OcclusionImage` (the image, the unoccluded image, the per-pixel inputs, the timings); ``ibl-ref render
--occlusion METHOD`` is its command line, the occlusion zoo calls the same steps.

Examples
--------
>>> import numpy as np
>>> from ibl_ref.occlusion import OcclusionInputs, get
>>> z = np.array([[0.0, 0.0, 1.0]])
>>> res = get("lagarde2014-alpha")(OcclusionInputs(normal=z, view=z, roughness=0.5, ao=np.array([1.0])))
>>> res.diffuse_factor, res.specular_factor
(array([1.]), array([1.]))
"""

from .image import OcclusionImage, OcclusionRequestError, occlusion_image
from .interface import OcclusionInputs, OcclusionMethod, OcclusionResult, UnoccludedTerms, shade
from .registry import OCCLUSION_METHODS, get

__all__ = ["OcclusionInputs", "OcclusionResult", "UnoccludedTerms", "OcclusionMethod", "shade", "OCCLUSION_METHODS",
           "get", "occlusion_image", "OcclusionImage", "OcclusionRequestError"]
