"""Sparse storage of Knuth et al. (2014) PEMs: keep only what a region's filtered copy actually covers.

Sec. 4 of the paper stores every PEM as a full cube map with MIP chain ("For each PEM we create a
plain copy of the original environment map and just blacken all texels that do not belong to the
current PEM ... This technique increases the memory consumption"), and Sec. 5 estimates that maps
covering only the used part would save ≈ 21× (1.5 GB → 70 MB).  Most of each PEM is zero: a region is
a rectangle on one face, and the pyramid's 2×2 shrink and 5-tap filter widen its support by only a
few texels per level.  This module stores, per region, per pyramid level and per face, one bounding
tile of the texels that must be kept, and reconstructs the dense levels for lookups.

Which texels are kept (``rtol``)
--------------------------------
Let FULL_l be level l of the full map's pyramid (= Σ_i PEM_i,l by linearity, to float rounding).
Texel t of PEM_i at level l is dropped only if, for every channel c,

    |PEM_i,l[t, c]| ≤ (rtol / L) · FULL_l[t, c]                                            (*)

(L = number of regions).  Everything inside a face's bounding tile of the kept texels is stored as it
is, so the dropped set is a subset of (*).  Summed over the regions, the dropped values at any texel are
≤ rtol · FULL_l[t, c]; a lookup that is a convex combination of texels (bilinear, trilinear blend,
edge blends of :class:`ibl_ref.environment.sampling.CubeSampler`) therefore changes by at most rtol × the *full*
lookup value, per channel, for the sum over all PEMs and for every single PEM.

* ``rtol = 0`` (lossless): only exact zeros are dropped; the reconstructed levels are bit-identical to
  the dense ones, so every lookup is bit-identical whatever the lookup does.
* ``rtol = 1e-6`` (the stated criterion): additionally drops texels that cannot move any lookup by
  more than 1e-6 relative to the full lookup.  The argument needs a lookup with non-negative weights
  summing to one; :class:`~ibl_ref.environment.sampling.CubeSampler` (bilinear + edge/corner blends, padding by
  positive combinations of texels) and the linear level blend of :func:`ibl_ref.knuth2014.gloss_lookup.lookup`
  are such lookups.  The tests measure the actual error over random directions and g.

Levels (``g_values``)
---------------------
With ``g_values`` given, only the pyramid levels that the glossy lookup touches for those g are kept
(found by probing the lookup with a pyramid whose level l is the constant one-hot vector e_l, so it
does not depend on how the lookup maps g to levels).  Lookups at any other g raise an error.

Memory accounting: ``nbytes`` = Σ tile data bytes + 5 int32 (face, row0, row1, col0, col1) = 20 B of
metadata per tile.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import IBLError
from .median_cut import LightSet
from .pem import iter_pem_chunks
from .pem import prepare_pem_input
from .pyramid import Pyramid

__all__ = ["Tile", "SparsePEMSet", "sparsify", "build_sparse_pems", "levels_touched", "TILE_META_BYTES"]

TILE_META_BYTES = 5 * 4


@dataclass
class Tile:
    """One face's bounding tile of kept texels: ``data`` = level[face, row0:row1, col0:col1, :]."""

    face: int
    row0: int
    row1: int
    col0: int
    col1: int
    data: np.ndarray

    @property
    def nbytes(self) -> int:
        return int(self.data.nbytes) + TILE_META_BYTES


def _tiles_of(level: np.ndarray, keep: np.ndarray) -> list:
    """Bounding tiles per face of the ``keep`` mask (6, n, n) of one PEM level (6, n, n, C)."""
    tiles = []
    for f in range(6):
        rows = np.nonzero(keep[f].any(axis=1))[0]
        if rows.size == 0:
            continue
        cols = np.nonzero(keep[f].any(axis=0))[0]
        r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
        tiles.append(Tile(f, r0, r1, c0, c1, np.ascontiguousarray(level[f, r0:r1, c0:c1])))
    return tiles


def _keep_mask(pem_level: np.ndarray, full_level: np.ndarray, rtol: float, n_regions: int) -> np.ndarray:
    """Texels that criterion (*) does not allow to drop, (6, n, n)."""
    a = np.abs(pem_level.astype(np.float64, copy=False))
    if rtol == 0:
        return np.any(a > 0, axis=-1)
    return np.any(a > (rtol / n_regions) * np.abs(full_level), axis=-1)


def levels_touched(g_values, base_size: int, lookup_fn: Callable | None = None, calibration=None,
                   kernel="sqrtcos", order="shrink_then_filter", seam="neighbour") -> tuple:
    """Pyramid levels the glossy lookup reads for the glossiness values ``g_values``.

    Probe: a pyramid whose level l holds the constant vector e_l (one-hot over levels) returns, for any
    direction, the weight the lookup gives each level.
    """

    if lookup_fn is None:
        from .gloss_lookup import lookup as lookup_fn
    g = np.atleast_1d(np.asarray(g_values, dtype=np.float64)).ravel()
    n_lev = int(np.log2(base_size)) + 1
    levels = []
    for l in range(n_lev):
        m = base_size >> l
        lev = np.zeros((6, m, m, n_lev))
        lev[..., l] = 1.0
        levels.append(lev)
    probe = Pyramid(levels=levels, kernel=kernel, order=order, seam=seam, base_size=base_size)
    dirs = np.broadcast_to(np.array([0.3, 0.5, 0.8]), g.shape + (3,))
    w = lookup_fn(probe, dirs, g, calibration=calibration)
    return tuple(int(l) for l in np.nonzero(np.any(np.abs(w) > 0, axis=0))[0])


class SparsePEMSet:
    """Sparse PEMs: same interface as :class:`ibl_ref.knuth2014.pem.PEMSet` for ``lights``, ``lookup``, ``lookup_all``
    (the region-set interface :class:`ibl_ref.prefilter.interface.RegionPrefilters`).

    Attributes
    ----------
    tiles : list (regions) of dict level → list of :class:`Tile`
    stored_levels : tuple of int
    rtol : float
    """

    lobe = "phong"
    #: no proven bound of a look-up against the exact lobe average (``rtol`` bounds the change from the dense PEMs)
    error_bound = None

    def __init__(self, lights: LightSet, tiles: list, level_sizes: list, channels: int, dtype, stored_levels,
                 rtol: float, kernel, order, seam, calibration=None, lookup_fn=None, g_values=None):
        self.lights = lights
        self.tiles = tiles
        self.level_sizes = list(level_sizes)
        self.channels = int(channels)
        self.dtype = np.dtype(dtype)
        self.stored_levels = tuple(stored_levels)
        self.rtol = float(rtol)
        self.kernel, self.order, self.seam = kernel, order, seam
        self.base_size = int(level_sizes[0])
        self._calibration = calibration
        self._lookup_fn = lookup_fn
        self.g_values = None if g_values is None else np.asarray(g_values, dtype=np.float64)

    @property
    def n_regions(self) -> int:
        return len(self.tiles)

    def __len__(self) -> int:
        return self.n_regions

    @property
    def n_tiles(self) -> int:
        return sum(len(t) for reg in self.tiles for t in reg.values())

    @property
    def nbytes(self) -> int:
        """Tile data + 20 B metadata per tile."""
        return int(sum(t.nbytes for reg in self.tiles for ts in reg.values() for t in ts))

    @property
    def dense_nbytes(self) -> int:
        """Bytes of the dense :class:`~ibl_ref.knuth2014.pem.PEMSet` with the same regions, dtype and all levels."""
        item = self.dtype.itemsize
        return int(self.n_regions * sum(6 * m * m for m in self.level_sizes) * self.channels * item)

    def bytes_per_level(self) -> dict:
        out = {}
        for reg in self.tiles:
            for l, ts in reg.items():
                out[l] = out.get(l, 0) + sum(t.nbytes for t in ts)
        return out

    # -- reconstruction and lookups ----------------------------------------------------------------
    def _dense_levels(self, regions) -> list:
        """Dense levels (6, n, n, k, C) for the given region indices (zeros where nothing is stored)."""
        k = len(regions)
        out = []
        for l, m in enumerate(self.level_sizes):
            lev = np.zeros((6, m, m, k, self.channels), dtype=self.dtype)
            if l in self.stored_levels:
                for j, i in enumerate(regions):
                    for t in self.tiles[i].get(l, ()):
                        lev[t.face, t.row0:t.row1, t.col0:t.col1, j, :] = t.data
            out.append(lev)
        return out

    def dense_region(self, i: int) -> list:
        """Dense pyramid levels (6, n, n, C) of PEM ``i`` rebuilt from the tiles."""
        return [lev[:, :, :, 0, :] for lev in self._dense_levels([self._check_index(i)])]

    def _check_index(self, i) -> int:
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not -self.n_regions <= int(i) < self.n_regions:
            raise IBLError(f"PEM index must be an integer in [0, {self.n_regions}), got {i!r}")
        return int(i) % self.n_regions

    @property
    def calibration(self):
        if self._calibration is None:
            from .gloss_lookup import get_calibration
            from .pyramid import Pyramid

            probe = Pyramid(levels=[np.zeros((6, m, m, 1)) for m in self.level_sizes], kernel=self.kernel,
                            order=self.order, seam=self.seam, base_size=self.base_size)
            self._calibration = get_calibration(probe)
        return self._calibration

    def _check_g(self, g):
        if len(self.stored_levels) == len(self.level_sizes):
            return
        key = tuple(np.unique(np.asarray(g, dtype=np.float64)).tolist())
        cache = self.__dict__.setdefault("_touched_cache", {})
        if key not in cache:
            cache[key] = levels_touched(key, self.base_size, self._lookup_fn, self.calibration, self.kernel,
                                        self.order, self.seam)
        need = cache[key]
        missing = sorted(set(need) - set(self.stored_levels))
        if missing:
            raise IBLError(
                f"sparse PEMs store levels {self.stored_levels} only (built for g = {self.g_values}); "
                f"this lookup needs level(s) {missing}"
            )

    def _lookup_stack(self, regions, dirs, g):

        k, C = len(regions), self.channels
        levels = [lev.reshape(lev.shape[:3] + (k * C,)) for lev in self._dense_levels(regions)]
        pyr = Pyramid(levels=levels, kernel=self.kernel, order=self.order, seam=self.seam, base_size=self.base_size)
        if self._lookup_fn is not None:
            out = self._lookup_fn(pyr, dirs, g, calibration=self._calibration)
        else:
            from .gloss_lookup import lookup

            out = lookup(pyr, dirs, g, calibration=self.calibration)
        return np.moveaxis(out.reshape(dirs.shape[:-1] + (k, C)), -2, 0)

    def lookup(self, i: int, dirs, g) -> np.ndarray:
        """Glossy lookup in PEM ``i``; → (..., C)."""
        dirs = np.asarray(dirs, dtype=np.float64)
        self._check_g(g)
        return self._lookup_stack([self._check_index(i)], dirs, g)[0]

    def lookup_all(self, dirs, g, chunk: int = 16) -> np.ndarray:
        """Lookups of every PEM, shape (L, ..., C) (dense levels rebuilt ``chunk`` regions at a time)."""
        dirs = np.asarray(dirs, dtype=np.float64)
        self._check_g(g)
        parts = [self._lookup_stack(list(range(a, min(a + chunk, self.n_regions))), dirs, g)
                 for a in range(0, self.n_regions, chunk)]
        return np.concatenate(parts, axis=0)

    def full_lookup(self, dirs, g) -> np.ndarray:
        return self.lookup_all(dirs, g).sum(axis=0)


def _stored_levels(g_values, base_size, n_levels, lookup_fn, calibration, kernel, order, seam):
    if g_values is None:
        return tuple(range(n_levels))
    return levels_touched(g_values, base_size, lookup_fn, calibration, kernel, order, seam)


def sparsify(pems, rtol: float = 1e-6, g_values=None, full_levels=None) -> SparsePEMSet:
    """Sparse copy of a dense :class:`ibl_ref.knuth2014.pem.PEMSet` (criterion (*) of the module docstring).

    ``full_levels`` (the full map's pyramid levels) default to Σ_i PEM_i (float64 sum of the stored PEMs).
    """
    rtol = _check_rtol(rtol)
    L = pems.n_regions
    if full_levels is None:
        full_levels = [lev.sum(axis=3, dtype=np.float64) for lev in pems.levels]
    stored = _stored_levels(g_values, pems.base_size, pems.n_levels, pems._lookup_fn, pems._calibration,
                            pems.kernel, pems.order, pems.seam)
    tiles = [dict() for _ in range(L)]
    for l in stored:
        lev = pems.levels[l]
        for i in range(L):
            tiles[i][l] = _tiles_of(lev[:, :, :, i, :], _keep_mask(lev[:, :, :, i, :], full_levels[l], rtol, L))
    return SparsePEMSet(pems.lights, tiles, [lev.shape[1] for lev in pems.levels], pems.channels, pems.dtype, stored,
                        rtol, pems.kernel, pems.order, pems.seam, pems._calibration, pems._lookup_fn, g_values)


def _check_rtol(rtol) -> float:
    rtol = float(rtol)
    if not (0 <= rtol < 1) or not np.isfinite(rtol):
        raise IBLError(f"rtol must be in [0, 1), got {rtol!r}")
    return rtol


def build_sparse_pems(cube, lights: LightSet | None = None, *, n_lights: int | None = None, variant="per-face",
                      rtol: float = 1e-6, g_values=None, kernel="sqrtcos", order="shrink_then_filter",
                      seam="neighbour", dtype=np.float32, calibration=None, pyramid_builder=None, lookup_fn=None,
                      chunk: int | None = None, progress: bool = False) -> SparsePEMSet:
    """Build sparse PEMs directly (never holds the dense set: chunks of regions are filtered and tiled).

    FULL (criterion (*)) is the pyramid of the full map, built once in float64 (equal to Σ_i PEM_i by
    linearity of the pyramid).
    """

    rtol = _check_rtol(rtol)
    n, env, lights = prepare_pem_input(cube, lights, n_lights, variant, "build_sparse_pems")
    if pyramid_builder is None:
        from .pyramid import build_pyramid as pyramid_builder
    full = pyramid_builder(env, kernel=kernel, order=order, seam=seam)
    full_levels = [np.asarray(lev, dtype=np.float64) for lev in full.levels]
    dt = np.dtype(dtype)
    stored = _stored_levels(g_values, n, len(full_levels), lookup_fn, calibration, kernel, order, seam)
    L = len(lights)
    tiles = [dict() for _ in range(L)]
    for a, b, levs in iter_pem_chunks(env, lights.labels, L, kernel=kernel, order=order, seam=seam,
                                      pyramid_builder=pyramid_builder, chunk=chunk, progress=progress):
        for l in stored:
            src = levs[l]
            if dt.itemsize < 8 and np.any(np.abs(src) > np.finfo(dt).max):
                raise IBLError(f"PEM values exceed the range of {dt}; use a wider dtype")
            stored_l = src.astype(dt)
            for j, i in enumerate(range(a, b)):
                tiles[i][l] = _tiles_of(stored_l[:, :, :, j, :], _keep_mask(stored_l[:, :, :, j, :], full_levels[l], rtol, L))
    kname = kernel if isinstance(kernel, str) else "custom"
    return SparsePEMSet(lights, tiles, [lev.shape[1] for lev in full_levels], env.channels, dt, stored, rtol,
                        kname, order, seam, calibration, lookup_fn, g_values)
