"""Knuth et al. (2014) filter pyramid as a prefilter: Sec. 3.2, Eq. 3, Fig. 2 (the calibration of Sec. 5).

Levels: alternating 2×2 shrink and 5×5 low-pass filter (:func:`ibl_ref.knuth2014.pyramid.build_pyramid`); look-up:
one trilinear look-up at the calibrated level ℓ(s) (:mod:`ibl_ref.knuth2014.gloss_lookup`; the lobe-volume tables
shipped in ``ibl_ref/data``, or one passed as ``calibration=``).  Its region set is the paper's PEMs,
:func:`ibl_ref.knuth2014.pem.build_pems` (all regions in one stacked pyramid), or their sparse storage
(``storage="sparse"``, :func:`ibl_ref.knuth2014.sparse_pem.build_sparse_pems`).  No error bound: the filters only
approximate the lobe's shape (``ibl-ref experiment lobe-chain`` measures the error).
"""

from __future__ import annotations

import numpy as np

from ..errors import IBLError
from .level_chain import LevelChainPrefilter
from ..knuth2014.gloss_lookup import get_calibration
from ..knuth2014.pyramid import build_pyramid

__all__ = ["Knuth2014Pyramid", "STORAGES"]

#: region-set storage: ``dense`` (one stacked pyramid, :class:`~ibl_ref.knuth2014.pem.PEMSet`) or ``sparse``
#: (bounding tiles of what each region covers, :class:`~ibl_ref.knuth2014.sparse_pem.SparsePEMSet`)
STORAGES = ("dense", "sparse")


class Knuth2014Pyramid(LevelChainPrefilter):
    """The paper's filter pyramid (2×2 shrink + 5×5 filter per level) read at the calibrated level ℓ(s).

    Parameters: ``kernel``, ``order``, ``seam``, ``shrink``, ``dtype`` of
    :func:`~ibl_ref.knuth2014.pyramid.build_pyramid`; ``calibration`` (default: the shipped table of this
    configuration, :func:`~ibl_ref.knuth2014.gloss_lookup.get_calibration` with ``volume``).
    """

    lobe = "phong"
    paper = "Knuth et al. 2014, Sec. 3.2, Eq. 3, Fig. 2 (calibration Sec. 5)"

    def __init__(self, cube, *, kernel="sqrtcos", order: str = "shrink_then_filter", seam: str = "neighbour",
                 shrink: str = "mean", dtype=None, calibration=None, volume: str = "integral"):

        self.pyramid = build_pyramid(cube, kernel=kernel, order=order, seam=seam, dtype=dtype, shrink=shrink)
        self.calibration = calibration if calibration is not None else get_calibration(self.pyramid, volume)

    @classmethod
    def build_regions(cls, cube, lights, *, kernel="sqrtcos", order: str = "shrink_then_filter",
                      seam: str = "neighbour", dtype=np.float32, calibration=None, storage: str = "dense",
                      rtol: float = 1e-6, g_values=None, progress: bool = False):
        """The paper's PEMs of ``lights`` (:func:`~ibl_ref.knuth2014.pem.build_pems`; ``storage="sparse"``:
        :func:`~ibl_ref.knuth2014.sparse_pem.build_sparse_pems` with ``rtol``, ``g_values``)."""
        kw = dict(kernel=kernel, order=order, seam=seam, dtype=dtype, calibration=calibration, progress=progress)
        if storage == "dense":
            from ..knuth2014.pem import build_pems

            return build_pems(cube, lights, **kw)
        if storage == "sparse":
            from ..knuth2014.sparse_pem import build_sparse_pems

            return build_sparse_pems(cube, lights, rtol=rtol, g_values=g_values, **kw)
        raise IBLError(f"unknown PEM storage {storage!r}; choose one of {', '.join(STORAGES)}")
