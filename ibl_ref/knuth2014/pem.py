"""Knuth et al. (2014) partial environment maps (PEMs), Sec. 3 step 2, Sec. 3.1 and Sec. 4.

"For each PEM we create a plain copy of the original environment map and just blacken all texels that
do not belong to the current PEM before we start filtering" (Sec. 4).  Each masked copy is filtered
into the filter pyramid of Fig. 2 (:func:`ibl_ref.knuth2014.pyramid.build_pyramid`) and read with the glossy
lookup (:func:`ibl_ref.knuth2014.gloss_lookup.lookup`).  Because the pyramid (2×2 mean + 5×5 filter) and the
trilinear lookup are linear, Σ_i lookup(PEM_i) = lookup(pyramid of the full map) for every direction
and g (Sec. 3.1: "It is equivalent whether we filter the sum of the single regions or whether we sum
up the filtered regions"); :meth:`PEMSet.full_lookup` and the tests check it.

Storage
-------
``PEMSet.levels[l]`` is one array of shape ``(6, n_l, n_l, L, C)`` per pyramid level (regions stacked
in front of the channels), so the L·C channels of all PEMs can be looked up in one pass.  Default dtype
**float32** (the paper stores RGBA16F; float16 would overflow a 1e5 sun, float64 doubles the memory):
the pyramids are computed in float64 and rounded once on storage.  ``nbytes`` is the true size of
these arrays (Fig. 8's "measured" column, :mod:`ibl_ref.knuth2014.memory_model`).

Calibration: all PEMs share the pyramid configuration (kernel, order, seam, base size) of the full map,
so one :class:`ibl_ref.knuth2014.gloss_lookup.Calibration` (g → level) is used for every PEM; it is computed once
(lazily) unless given.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..environment.validated import adopt, as_environment
from ..errors import IBLError, LayoutError
from .median_cut import LightSet, median_cut
from ..progress import track
from .gloss_lookup import lookup
from .gloss_lookup import lookup_at_level
from .pyramid import Pyramid

__all__ = ["PEMSet", "build_pems", "iter_pem_chunks", "default_chunk", "partial_maps"]


def default_chunk(n_regions: int, channels: int, max_channels: int = 48) -> int:
    """Regions built per pyramid call: at most ``max_channels`` stacked channels (memory bound).

    Parameters
    ----------
    n_regions, channels : int
        L and C.
    max_channels : int, optional

    Returns
    -------
    int
        Between 1 and ``n_regions``.
    """
    return max(1, min(n_regions, max_channels // max(channels, 1)))


def partial_maps(cube, labels, a: int, b: int) -> np.ndarray:
    """The partial environment maps of regions a..b−1, stacked: (6, N, N, b−a, C) (Sec. 4: "a plain copy of the
    original environment map" with "all texels that do not belong to the current PEM" blackened).

    Parameters
    ----------
    cube : array_like or Environment, shape (6, N, N, C)
    labels : int array, shape (6, N, N)
        Region index per texel (:attr:`~ibl_ref.knuth2014.median_cut.LightSet.labels`).
    a, b : int
        The regions a..b−1.

    Returns
    -------
    ndarray, shape (6, N, N, b−a, C)
    """
    mask = np.asarray(labels)[..., None] == np.arange(a, b)[None, None, None, :]  # (6, N, N, k)
    return np.asarray(cube)[:, :, :, None, :] * mask[..., None]


def iter_pem_chunks(cube, labels, n_regions, *, kernel="sqrtcos", order="shrink_then_filter", seam="neighbour",
                    pyramid_builder: Callable | None = None, chunk: int | None = None, progress: bool = False):
    """Yield ``(a, b, levels)`` for regions a..b−1: the filtered masked copies, levels (6, n, n, b−a, C) float64.

    The masked copies of a chunk are stacked along the channel axis and filtered in one pyramid call
    (the pyramid filters every channel independently), each chunk handed to ``pyramid_builder`` as an
    :class:`~ibl_ref.environment.validated.Environment` (masked copies of a valid map are valid: not checked again).

    Parameters
    ----------
    cube : Environment or array (6, N, N[, C])
        The environment (checked once here unless it is an :class:`~ibl_ref.environment.validated.Environment`).
    labels : int array (6, N, N)
        Region index of every texel (:attr:`ibl_ref.knuth2014.median_cut.LightSet.labels`).
    n_regions : int
        Number of regions L.
    kernel, order, seam : pyramid configuration (:func:`ibl_ref.knuth2014.pyramid.build_pyramid`).
    pyramid_builder : callable(cube, kernel=, order=, seam=) → object with ``.levels``, optional
        Default :func:`ibl_ref.knuth2014.pyramid.build_pyramid`.
    chunk : int, optional
        Regions per pyramid call (default :func:`default_chunk`).
    progress : bool
        Report progress over the chunks (:mod:`ibl_ref.progress`).
    """
    if pyramid_builder is None:
        from .pyramid import build_pyramid as pyramid_builder
    cube = as_environment(cube, "PEM input").data
    n, C = cube.shape[1], cube.shape[3]
    chunk = default_chunk(n_regions, C) if chunk is None else int(chunk)

    for a in track(range(0, n_regions, chunk), "PEM pyramids", unit="chunk", enabled=progress):
        b = min(a + chunk, n_regions)
        k = b - a
        masked = adopt(partial_maps(cube, labels, a, b).reshape(6, n, n, k * C), name="PEM input")
        pyr = pyramid_builder(masked, kernel=kernel, order=order, seam=seam)
        yield a, b, [np.asarray(lev, dtype=np.float64).reshape(lev.shape[:3] + (k, C)) for lev in pyr.levels]


class PEMSet:
    """Partial environment maps of one environment map, one per median-cut region.

    Build with :func:`build_pems`.  Renderers use ``lights`` (for the shadow maps) and
    :meth:`lookup_all` (for Eq. 5, c = Σ_i VIS_i · PEM_i): the region-set interface
    :class:`ibl_ref.prefilter.interface.RegionPrefilters` (Phong lobes, looked up by glossiness g; no error bound).

    Attributes
    ----------
    lights : LightSet
    levels : list of arrays (6, n_l, n_l, L, C)
    kernel, order, seam : pyramid configuration (Fig. 2; see :mod:`ibl_ref.knuth2014.pyramid`)
    base_size : int
    dtype : numpy dtype of the stored levels (float32 by default)
    """

    lobe = "phong"
    #: no proven bound of a look-up against the exact lobe average (the region-set interface's ``error_bound``)
    error_bound = None

    def __init__(self, lights: LightSet, levels: list, kernel, order, seam, calibration=None, lookup_fn=None):
        self.lights = lights
        self.levels = levels
        self.kernel, self.order, self.seam = kernel, order, seam
        self.base_size = int(levels[0].shape[1])
        self.dtype = levels[0].dtype
        self._calibration = calibration
        self._lookup_fn = lookup_fn
        self._all_pyr = None

    # -- basic properties ------------------------------------------------------------------------
    @property
    def n_regions(self) -> int:
        return int(self.levels[0].shape[3])

    def __len__(self) -> int:
        return self.n_regions

    @property
    def channels(self) -> int:
        return int(self.levels[0].shape[4])

    @property
    def n_levels(self) -> int:
        return len(self.levels)

    @property
    def nbytes(self) -> int:
        """Bytes of the stored PEM pyramids (all regions, all levels)."""
        return int(sum(lev.nbytes for lev in self.levels))

    @property
    def directions(self) -> np.ndarray:
        return self.lights.directions

    @property
    def rgb(self) -> np.ndarray:
        return self.lights.rgb

    @property
    def solid_angle(self) -> np.ndarray:
        return self.lights.solid_angle

    @property
    def regions(self) -> np.ndarray:
        return self.lights.regions

    # -- pyramids and lookups -----------------------------------------------------------------------
    def _pyramid(self, levels):

        return Pyramid(levels=list(levels), kernel=self.kernel, order=self.order, seam=self.seam,
                       base_size=self.base_size)

    def pyramid(self, i: int):
        """The filter pyramid of PEM ``i`` (:class:`ibl_ref.knuth2014.pyramid.Pyramid`, levels are copies)."""
        i = self._check_index(i)
        return self._pyramid([np.ascontiguousarray(lev[:, :, :, i, :]) for lev in self.levels])

    @property
    def calibration(self):
        """g → level table shared by all PEMs (lazily :func:`ibl_ref.knuth2014.gloss_lookup.get_calibration`)."""
        if self._calibration is None:
            from .gloss_lookup import get_calibration

            probe = self._pyramid([lev[:, :, :, :1, 0] for lev in self.levels])
            self._calibration = get_calibration(probe)
        return self._calibration

    def _lookup(self, pyr, dirs, g):
        if self._lookup_fn is not None:
            return self._lookup_fn(pyr, dirs, g, calibration=self._calibration)

        return lookup(pyr, dirs, g, calibration=self.calibration)

    def _check_index(self, i) -> int:
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not -self.n_regions <= int(i) < self.n_regions:
            raise IBLError(f"PEM index must be an integer in [0, {self.n_regions}), got {i!r}")
        return int(i) % self.n_regions

    def lookup(self, i: int, dirs, g) -> np.ndarray:
        """Glossy lookup in PEM ``i`` at directions ``dirs`` (..., 3) and glossiness ``g``; → (..., C)."""
        return self._lookup(self.pyramid(i), dirs, g)

    def _stacked_pyramid(self):
        if self._all_pyr is None:
            L, C = self.n_regions, self.channels
            self._all_pyr = self._pyramid([lev.reshape(lev.shape[:3] + (L * C,)) for lev in self.levels])
        return self._all_pyr

    def lookup_all(self, dirs, g) -> np.ndarray:
        """Lookups of every PEM at once, shape (L, ..., C).  Caches the padded samplers (:meth:`clear_cache`)."""
        dirs = np.asarray(dirs, dtype=np.float64)
        out = self._lookup(self._stacked_pyramid(), dirs, g)
        out = out.reshape(dirs.shape[:-1] + (self.n_regions, self.channels))
        return np.moveaxis(out, -2, 0)

    def lookup_all_at_level(self, dirs, level) -> np.ndarray:
        """:meth:`lookup_all` at a given continuous pyramid level instead of the calibrated ℓ(g), (L, ..., C)
        (:func:`ibl_ref.knuth2014.gloss_lookup.lookup_at_level`; the error budget's best-level step)."""

        dirs = np.asarray(dirs, dtype=np.float64)
        out = lookup_at_level(self._stacked_pyramid(), dirs, level)
        out = out.reshape(dirs.shape[:-1] + (self.n_regions, self.channels))
        return np.moveaxis(out, -2, 0)

    def full_lookup(self, dirs, g) -> np.ndarray:
        """Σ_i lookup(PEM_i): the unoccluded lighting (by linearity = lookup of the full map's pyramid)."""
        return self.lookup_all(dirs, g).sum(axis=0)

    def clear_cache(self) -> None:
        """Drop the cached samplers of :meth:`lookup_all` (they hold a padded copy of the levels)."""
        self._all_pyr = None


def prepare_pem_input(cube, lights, n_lights, variant, caller: str):
    """The map as an :class:`~ibl_ref.environment.validated.Environment` (checked once, as ``"PEM input"``, unless it
    is one) and its lights: ``(N, env, lights)``, median-cutting it into ``n_lights`` regions when no ``lights`` are
    given (shared by the dense, sparse and lobe-chain builders)."""
    env = as_environment(cube, "PEM input")
    n = env.face_size
    if lights is None:
        if n_lights is None:
            raise IBLError(f"{caller}: give either lights (a LightSet) or n_lights")
        lights = median_cut(env, n_lights, variant)
    if lights.labels.shape != (6, n, n):
        raise LayoutError(f"lights were made for face size {lights.face_size}, map has {n}")
    return n, env, lights


def build_pems(cube, lights: LightSet | None = None, *, n_lights: int | None = None, variant: str = "per-face",
               kernel="sqrtcos", order: str = "shrink_then_filter", seam: str = "neighbour", dtype=np.float32,
               calibration=None, pyramid_builder: Callable | None = None, lookup_fn: Callable | None = None,
               chunk: int | None = None, progress: bool = False) -> PEMSet:
    """Median-cut the map (unless ``lights`` is given) and build one filter pyramid per region.

    Parameters
    ----------
    cube : Environment or array_like, shape (6, N, N, C) or (6, N, N)
        Radiance; N a power of two (pyramid requirement).  Checked once (as ``"PEM input"``) unless it is a
        validated :class:`~ibl_ref.environment.validated.Environment`.
    lights : LightSet, optional
        Regions to use (from :func:`ibl_ref.knuth2014.median_cut.median_cut` on the same map).
    n_lights, variant : int, str
        Passed to :func:`~ibl_ref.knuth2014.median_cut.median_cut` when ``lights`` is None.
    kernel, order, seam : str
        Filter-pyramid configuration (:func:`ibl_ref.knuth2014.pyramid.build_pyramid`).
    dtype : numpy dtype
        Storage dtype (default float32).
    calibration : :class:`ibl_ref.knuth2014.gloss_lookup.Calibration`, optional
    pyramid_builder : callable(cube, kernel=, order=, seam=) → object with ``.levels``, optional
        Default :func:`ibl_ref.knuth2014.pyramid.build_pyramid` (must be linear for the PEM identity to hold); it
        receives each chunk of masked copies as an :class:`~ibl_ref.environment.validated.Environment`.
    lookup_fn : callable(pyramid, dirs, g, calibration=) → (..., C), optional
        Default :func:`ibl_ref.knuth2014.gloss_lookup.lookup`.
    chunk : int, optional
        Regions per pyramid call (default: ≤ 48 stacked channels).
    progress : bool
        Report progress over the pyramid calls (:mod:`ibl_ref.progress`: a bar on a terminal, status lines in a
        log).

    Returns
    -------
    PEMSet

    Raises
    ------
    LayoutError, RadianceError
        A wrong shape (or a face size that is no power of two); NaN/Inf/negative radiance; lights of another
        face size.
    IBLError
        Neither ``lights`` nor ``n_lights``; a non-float dtype; values beyond the storage dtype's range.

    Examples
    --------
    Six PEMs of a sky (one region per face).  The pyramid and the lookup are linear, so the PEMs' lookups sum to
    the lookup of the whole map's pyramid (Sec. 3.1), here to the float32 rounding of the stored levels:

    >>> import numpy as np
    >>> from ibl_ref.knuth2014.gloss_lookup import lookup
    >>> from ibl_ref.knuth2014.pem import build_pems
    >>> from ibl_ref.knuth2014.pyramid import build_pyramid
    >>> from ibl_ref.synthetic.synthetic_envs import make_environment
    >>> sky = make_environment("sky_sun", 16)
    >>> pems = build_pems(sky, n_lights=6)
    >>> pems.n_regions, pems.n_levels, pems.levels[0].shape, pems.levels[0].dtype
    (6, 5, (6, 16, 16, 6, 3), dtype('float32'))
    >>> dirs = [[0.0, 1.0, 0.0], [0.3, 0.2, 0.9]]
    >>> per_region = pems.lookup_all(dirs, 0.8)  # (L, directions, C)
    >>> per_region.shape
    (6, 2, 3)
    >>> bool(np.allclose(per_region.sum(axis=0), lookup(build_pyramid(sky), dirs, 0.8), rtol=1e-6))
    True
    """
    n, env, lights = prepare_pem_input(cube, lights, n_lights, variant, "build_pems")
    dt = np.dtype(dtype)
    if not np.issubdtype(dt, np.floating):
        raise IBLError(f"PEM dtype must be a float type, got {dt}")
    L, C = len(lights), env.channels
    levels = None
    for a, b, levs in iter_pem_chunks(env, lights.labels, L, kernel=kernel, order=order, seam=seam,
                                      pyramid_builder=pyramid_builder, chunk=chunk, progress=progress):
        if levels is None:
            levels = [np.empty(lev.shape[:3] + (L, C), dtype=dt) for lev in levs]
        for dst, src in zip(levels, levs):
            if dt.itemsize < 8 and np.any(np.abs(src) > np.finfo(dt).max):
                raise IBLError(f"PEM values exceed the range of {dt} (max {np.finfo(dt).max:g}); use a wider dtype")
            dst[:, :, :, a:b, :] = src
    kname = kernel if isinstance(kernel, str) else "custom"
    return PEMSet(lights, levels, kname, order, seam, calibration=calibration, lookup_fn=lookup_fn)
