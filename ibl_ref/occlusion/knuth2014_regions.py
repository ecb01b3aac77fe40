"""Per-region visibility weights: Knuth, Altenhofen, Kuijper & Bender 2014, "Efficient Self-Shadowing Using
Image-Based Lighting on Glossy Surfaces", Sec. 3, Eq. 5, with exact visible fractions.

Eq. 5 shades a pixel as c = Σ_i VIS_i · PEM_i: the environment is cut into regions (median cut), each region's
partial environment map is prefiltered on its own, and each look-up is weighted by the visible fraction VIS_i of its
region.  The paper estimates VIS_i with variance shadow maps; ``regions-exact`` (:func:`region_visibility_weights`)
takes the visible fractions as given (``region_visibility``, e.g. traced), so it measures the error of Eq. 5's
factorisation itself — the visibility assumed constant over each region's part of the lobe — and nothing of the
shadow maps.  :func:`~ibl_ref.occlusion.interface.shade` applies the weights to the unoccluded per-region terms:
Σ_i w_i (kd·A_1,i + S_i).

Examples
--------
>>> import numpy as np
>>> from ibl_ref.occlusion.interface import OcclusionInputs
>>> from ibl_ref.occlusion.knuth2014_regions import region_visibility_weights
>>> z = np.array([[0.0, 0.0, 1.0]])
>>> inp = OcclusionInputs(normal=z, view=z, roughness=0.5, region_visibility=np.array([[1.0, 0.25]]))
>>> region_visibility_weights(inp).region_weights
array([[1.  , 0.25]])
"""

from __future__ import annotations

from .interface import OcclusionInputs, OcclusionResult

__all__ = ["region_visibility_weights"]


def region_visibility_weights(inputs: OcclusionInputs) -> OcclusionResult:
    """Region weights w_i = VIS_i (P, R): the visible fraction of each region, as given.

    Parameters
    ----------
    inputs : OcclusionInputs
        Reads ``region_visibility`` (P, R).

    Returns
    -------
    OcclusionResult
        ``region_weights`` (P, R) only.
    """
    return OcclusionResult(region_weights=inputs.region_visibility.copy())
