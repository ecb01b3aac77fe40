"""Kautz & McCool (2000) prefiltered lobe maps for the Phong lobe family (Sec. 4–5, Eq. 2).

Kautz & McCool approximate a BRDF by radially symmetric lobes p(γ) around peak directions and prefilter the
environment with each lobe, E(d) = ∫ L(l) p(angle(d, l)) dl (their Eq. 2; the exact convolution with tabulated
radial profiles is :func:`ibl_ref.lobes.profile_convolution.convolve_profiles`: exact texel solid angles, source
supersampling, the profile's tail cut at ``tail_rtol``).  The Phong lobe max(cos γ, 0)^s is radially symmetric
about the mirror direction and the same at every view elevation, so their fit is that one lobe and the 3-D map
(Sec. 5: elevation as the third texture coordinate) degenerates to one 2-D map per exponent.  This prefilter
tabulates p_s(γ) = max(cos γ, 0)^s on their γ nodes (:func:`ibl_ref.lobes.kautz_mccool2000.gamma_nodes`, linear
between nodes), convolves, and divides by the tabulated lobe's exact integral
(:func:`~ibl_ref.lobes.profile_convolution.profile_integral`), which gives the lobe average; the maps at the
``exponents`` are stacked over the input (mirror), and a look-up is bilinear in direction (KM2000 Sec. 5) and
linear in log s between exponents (:mod:`ibl_ref.prefilter.level_chain`; the exponent replaces the elevation as the
third coordinate).  For BRDF-specific lobe sets (Ward, Cook–Torrance, off-specular peaks) use
:mod:`ibl_ref.lobes.prefiltered_lobes` directly.  No error bound (profile tabulation, quadrature and the tail cut
are measured in the tests, not bounded).
"""

from __future__ import annotations

import numpy as np

from .level_chain import LevelChainPrefilter, check_exponents, exponent_stack
from ..groundtruth.convolution_args import check_cube
from ..lobes.kautz_mccool2000 import gamma_nodes
from ..lobes.profile_convolution import convolve_profiles
from ..lobes.profile_convolution import profile_integral

__all__ = ["KautzMcCool2000Lobes", "phong_profiles"]


def phong_profiles(exponents, n_gamma: int = 256):
    """``(gamma (G,), profiles (K, G))``: max(cos γ, 0)^s tabulated on the Kautz & McCool γ nodes."""

    gamma = gamma_nodes(int(n_gamma))
    c = np.maximum(np.cos(gamma), 0.0)
    return gamma, np.stack([c ** float(s) for s in exponents])


class KautzMcCool2000Lobes(LevelChainPrefilter):
    """Kautz & McCool 2000 maps of the Phong lobe (one radial profile per exponent), blended in log s.

    Parameters: ``exponents`` (default s = 1, 4, 16, …), ``n_gamma`` (profile nodes), ``supersample`` (int or
    ``"auto"``), ``tail_rtol``, ``out_size`` of :func:`~ibl_ref.lobes.profile_convolution.convolve_profiles`.
    """

    lobe = "phong"
    paper = "Kautz & McCool 2000, Sec. 4-5, Eq. 2 (radially symmetric lobes; one per Phong exponent)"

    def __init__(self, cube, *, exponents=None, n_gamma: int = 256, supersample="auto", tail_rtol: float = 1e-6,
                 out_size=None, progress: bool = False):

        a, _ = check_cube(cube)
        self.exponents = check_exponents(exponents, a.shape[1])
        gamma, prof = phong_profiles(self.exponents, n_gamma)
        maps = convolve_profiles(a, gamma, prof, out_size=out_size, supersample=supersample,
                                 tail_rtol=float(tail_rtol), progress=progress)
        w = profile_integral(gamma, prof)  # ∫ p_s dω of the tabulated lobe
        maps = maps / np.asarray(w, dtype=np.float64).reshape((-1,) + (1,) * (maps.ndim - 1))
        self.pyramid, self.calibration = exponent_stack(a, self.exponents, maps, "km00-lobes")
