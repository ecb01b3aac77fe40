"""Kán, Unterguggenberger & Kaufmann (2015) specular reflection maps as a prefilter (Sec. 3.2, Eq. 1–4).

Kán et al. precompute, for each shininess n of the scene, the map Esⁿ(ωr) = (n+1)/(2π) ∫ L max(ωr·ωi, 0)ⁿ dωi
(their Eq. 3–4; the irradiance map Ed is the n = 1 map) by a per-texel sum over the environment
(:func:`ibl_ref.groundtruth.kan2015.specular_maps`, exact texel solid angles; ``quadrature="literal"`` is their
sum, ``"normalized"`` divides by the discrete lobe weight).  As a prefilter the maps are computed at the
``exponents`` (default s = 1, 4, 16, … up to the largest the face still resolves,
:func:`~ibl_ref.prefilter.level_chain.default_exponents`) and stacked over the input (the mirror); a look-up
is seam-aware bilinear in direction and, between stored exponents, linear in log s (beyond the largest, linear in
1/s towards the mirror; :mod:`ibl_ref.prefilter.level_chain`).  The blend between exponents is this package's
(Kán et al. compute the maps for the scene's own shininesses): at a stored exponent the look-up is their map.

Cost: a dense gather, O(N⁴) per exponent (6N² outputs × 6N² texels).  No error bound.
"""

from __future__ import annotations

from .level_chain import LevelChainPrefilter, check_exponents, exponent_stack
from ..groundtruth.convolution_args import check_cube
from ..groundtruth.kan2015 import specular_maps

__all__ = ["Kan2015Maps"]


class Kan2015Maps(LevelChainPrefilter):
    """Kán et al. 2015 specular maps Esⁿ at a ladder of exponents, blended in log s between them.

    Parameters: ``exponents`` (Phong exponents ≥ 1; default s = 1, 4, 16, …), ``quadrature`` (``"literal"``, the
    paper's sum, or ``"normalized"``), ``supersample`` and ``out_size`` of
    :func:`~ibl_ref.groundtruth.kan2015.specular_maps`.
    """

    lobe = "phong"
    paper = "Kán, Unterguggenberger & Kaufmann 2015, Sec. 3.2, Eq. 1-4"

    def __init__(self, cube, *, exponents=None, quadrature: str = "literal", supersample: int = 1,
                 out_size=None):

        a, _ = check_cube(cube)
        self.exponents = check_exponents(exponents, a.shape[1])
        self.quadrature = quadrature
        maps = specular_maps(a, self.exponents, quadrature=quadrature, supersample=supersample, out_size=out_size)
        self.pyramid, self.calibration = exponent_stack(a, self.exponents, maps, "kan2015")
