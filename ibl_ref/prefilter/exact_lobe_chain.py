"""The exact-lobe chain as a prefilter (not in a paper: Knuth et al. 2014's look-up, Sec. 3.2, on exact Eq. 4 levels).

The data structure and trilinear look-up of the filter pyramid, but level k holds the exact normalised Phong lobe
average at s_k = s_min · factor^(K−k) on a face large enough for the lobe (:mod:`ibl_ref.knuth2014.lobe_chain`,
which documents the level sizes and the truncation bound of each level).  Its region set is
:func:`ibl_ref.knuth2014.lobe_chain.build_lobe_chain_pems` (one gather for all regions).  ``level_bounds``: the
truncation bound δ of every level (|stored − exact| ≤ δ · max L at the stored texels); the look-up itself still
interpolates between texels and levels, so ``error_bound`` is None.
"""

from __future__ import annotations

import numpy as np

from .level_chain import LevelChainPrefilter
from ..knuth2014.lobe_chain import build_lobe_chain
from ..knuth2014.lobe_chain import build_lobe_chain_pems

__all__ = ["ExactLobeChain"]


class ExactLobeChain(LevelChainPrefilter):
    """Levels holding the exact Phong lobe average at s = 1, factor, factor², … (the pyramid's exact counterpart).

    Parameters: ``s_min``, ``factor``, ``texels_per_halfwidth``, ``n_min``, ``weight_eps``, ``dtype`` of
    :func:`~ibl_ref.knuth2014.lobe_chain.build_lobe_chain`.
    """

    lobe = "phong"
    paper = "not in a paper: Knuth et al. 2014 Sec. 3.2 look-up on levels holding the exact Eq. 4 lobe average"

    def __init__(self, cube, *, s_min: float = 1.0, factor: float = 4.0, texels_per_halfwidth: float = 2.0,
                 n_min: int = 8, weight_eps: float = 1e-12, dtype=np.float64, progress: bool = False):

        self.pyramid, self.calibration = build_lobe_chain(
            cube, s_min=s_min, factor=factor, texels_per_halfwidth=texels_per_halfwidth, n_min=n_min,
            weight_eps=weight_eps, dtype=dtype, progress=progress)

    @property
    def level_bounds(self) -> list:
        """Truncation bound δ per level 1..K (max over texels; |stored − exact| ≤ δ · max L)."""
        return list(self.pyramid.truncation_bounds)

    @classmethod
    def build_regions(cls, cube, lights, *, s_min: float = 1.0, factor: float = 4.0,
                      texels_per_halfwidth: float = 2.0, n_min: int = 8, weight_eps: float = 1e-12,
                      dtype=np.float32, progress: bool = False):
        """PEMs whose levels are exact per-region lobe averages (:func:`~ibl_ref.knuth2014.lobe_chain.build_lobe_chain_pems`)."""

        return build_lobe_chain_pems(cube, lights, s_min=s_min, factor=factor,
                                     texels_per_halfwidth=texels_per_halfwidth, n_min=n_min, weight_eps=weight_eps,
                                     dtype=dtype, progress=progress)
