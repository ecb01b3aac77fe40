"""Prefilters read by one trilinear look-up in a chain of cube levels (Knuth et al. 2014, Sec. 3.2, Eq. 3).

The paper's look-up: a chain of cube maps ("levels", level 0 = the environment itself, the mirror), a table
s → continuous level ℓ(s) (a :class:`ibl_ref.knuth2014.gloss_lookup.Calibration`), and per look-up the seam-aware
bilinear look-up of levels ⌊ℓ⌋ and ⌊ℓ⌋ + 1 blended linearly
(:func:`ibl_ref.knuth2014.gloss_lookup.lookup_at_level`).  The filter pyramid, the exact-lobe chain and the
per-exponent map stacks of Kautz & McCool (2000) and Kán et al. (2015) all store such a chain and differ only in
what the levels hold, so they share this base class: a method sets ``self.pyramid`` (levels, any face sizes) and
``self.calibration`` in its constructor.

:func:`exponent_stack` is the chain of maps computed at given Phong exponents s_1 > … > s_K (level k holds the
lobe at s_k, level 0 the input): its table is :func:`ibl_ref.knuth2014.lobe_chain.exponent_calibration` (linear in
log s between stored exponents, linear in 1/s from s_1 to the mirror, clamped to s_K below).
"""

from __future__ import annotations

import numpy as np

from ..errors import IBLError
from .interface import check_lobe_param
from ..knuth2014.gloss_lookup import lookup_at_level
from ..knuth2014.lobe_chain import chain_spec
from ..knuth2014.lobe_chain import exponent_calibration
from ..knuth2014.pyramid import Pyramid

__all__ = ["LevelChainPrefilter", "exponent_stack", "default_exponents", "check_exponents"]


class LevelChainPrefilter:
    """Base of the Phong prefilters whose look-up is one trilinear look-up at level ℓ(s) (module docstring).

    Subclasses set ``pyramid`` (an object with ``levels``, ``max_level``, ``sampler(k)``, ``base_size``, as
    :class:`ibl_ref.knuth2014.pyramid.Pyramid`) and ``calibration`` in ``__init__``.
    """

    lobe = "phong"
    pyramid = None
    calibration = None

    def level_of(self, s) -> np.ndarray:
        """Continuous level ℓ(s) of the look-up for Phong exponents ``s`` (≥ 1; ``inf`` → 0, the mirror)."""
        s = check_lobe_param(self.lobe, s)
        cal = self.calibration
        if cal.face_size != self.pyramid.base_size or cal.max_level != self.pyramid.max_level:
            raise IBLError(f"calibration is for face size {cal.face_size} ({cal.max_level} levels), the prefilter "
                           f"has {self.pyramid.base_size} ({self.pyramid.max_level} levels)")
        return cal.level_of(s)

    def lookup(self, directions, s) -> np.ndarray:
        """Trilinear look-up at ℓ(s) → radiance (..., C) (Knuth Sec. 3.2: "hardware trilinear interpolation")."""
        return self.lookup_at_level(directions, self.level_of(check_lobe_param(self.lobe, s, directions)))

    def lookup_at_level(self, directions, level) -> np.ndarray:
        """The look-up at a given continuous level instead of ℓ(s) (the error budget's best-level step)."""

        return lookup_at_level(self.pyramid, directions, level)

    @property
    def n_levels(self) -> int:
        return len(self.pyramid.levels)

    @property
    def nbytes(self) -> int:
        """Bytes of the stored levels."""
        return int(sum(np.asarray(lev).nbytes for lev in self.pyramid.levels))

    @property
    def error_bound(self):
        """None: interpolation between levels and texels has no proven bound against the lobe average."""
        return None


def default_exponents(face_size: int) -> tuple:
    """The exact-lobe chain's exponents for face size N (s = 1, 4, 16, … while the lobe's half width θ½ still
    spans one texel, :func:`ibl_ref.knuth2014.lobe_chain.chain_spec` with ``factor=4``), decreasing."""

    return chain_spec(int(face_size)).s_phong


def exponent_stack(cube, exponents, maps, kernel: str):
    """``(pyramid, calibration)`` of maps computed at ``exponents``: level 0 = ``cube`` (mirror), level k =
    ``maps[k-1]`` at exponent ``exponents[k-1]`` (strictly decreasing, ≥ 1)."""

    a = np.asarray(cube, dtype=np.float64)
    if a.ndim == 3:
        a = a[..., None]
    levels = [a] + [np.asarray(m, dtype=np.float64).reshape(np.shape(m)[:3] + (a.shape[3],)) for m in maps]
    pyr = Pyramid(levels=levels, kernel=kernel, order="exact", seam="exact", base_size=a.shape[1])
    return pyr, exponent_calibration(exponents, a.shape[1], kernel=kernel)


def check_exponents(exponents, face_size: int) -> tuple:
    """``exponents`` (default :func:`default_exponents`) as a strictly decreasing tuple of finite floats ≥ 1."""
    if exponents is None:
        return default_exponents(face_size)
    e = np.atleast_1d(np.asarray(exponents, dtype=np.float64))
    if e.ndim != 1 or e.size < 1 or not np.all(np.isfinite(e)) or np.any(e < 1.0):
        raise IBLError(f"exponents must be finite Phong exponents >= 1, got {exponents!r}")
    e = np.unique(e)[::-1]
    return tuple(float(x) for x in e)
