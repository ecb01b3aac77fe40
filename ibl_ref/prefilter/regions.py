"""Partial environment maps from any Phong prefilter: the method applied to each region (Knuth et al. 2014, Sec. 3
step 2, Sec. 3.1, Sec. 4).

"For each PEM we create a plain copy of the original environment map and just blacken all texels that do not belong
to the current PEM before we start filtering" (Sec. 4): :meth:`RegionSet.build` does exactly that with any method
of :mod:`ibl_ref.prefilter` (:func:`ibl_ref.knuth2014.pem.partial_maps`, then ``Method(partial map, **params)``
per region), and :meth:`RegionSet.lookup_all` is built on the :class:`~ibl_ref.prefilter.interface.Prefilter`
interface alone: region i at glossiness g is ``members[i].lookup(d, s(g))`` with s = 1/(1 − g) (Eq. 3).  A linear
prefilter (every method here) then satisfies Σ_i PEM_i = the prefilter of the whole map (Sec. 3.1: "It is
equivalent whether we filter the sum of the single regions or whether we sum up the filtered regions").

This is the default region set of a method; a method may build its regions jointly and faster (a classmethod
``build_regions(cube, lights, **params)``, e.g. the paper's pyramid stacks all regions in one pyramid,
:class:`ibl_ref.knuth2014.pem.PEMSet`).  When every member is a level chain
(:class:`~ibl_ref.prefilter.level_chain.LevelChainPrefilter`) the set also offers the look-ups at a given level
(:meth:`RegionSet.lookup_all_at_level`) that the error budget's best-level step reads.
"""

from __future__ import annotations

import numpy as np

from ..environment.validated import adopt
from ..errors import IBLError
from ..conventions import phong_exponent
from ..knuth2014.pem import partial_maps
from ..knuth2014.pem import prepare_pem_input

__all__ = ["RegionSet", "build_region_set"]


def build_region_set(method, cube, lights, **params):
    """The region set of a Phong method class on ``lights``: its joint ``build_regions`` if it has one, else
    :meth:`RegionSet.build` (the method on every partial map)."""
    build = getattr(method, "build_regions", None)
    if build is not None:
        return build(cube, lights, **params)
    return RegionSet.build(method, cube, lights, **params)


class RegionSet:
    """One prefilter per median-cut region: ``members[i]`` prefilters the partial map of region i.

    Attributes
    ----------
    lights : :class:`ibl_ref.knuth2014.median_cut.LightSet`
    members : list of prefilters (one lobe family, Phong)
    """

    lobe = "phong"

    def __init__(self, lights, members):
        self.lights = lights
        self.members = list(members)
        if len(self.members) != len(lights):
            raise IBLError(f"a region set needs one prefilter per region: {len(lights)} regions, "
                           f"{len(self.members)} prefilters")
        lobes = {m.lobe for m in self.members}
        if lobes != {"phong"}:
            raise IBLError(f"partial environment maps are looked up by Eq. 5's glossiness g: their prefilters must "
                           f"serve Phong lobes, got {sorted(lobes)}")

    @classmethod
    def build(cls, method, cube, lights, **params) -> "RegionSet":
        """``method(partial map i, **params)`` for every region of ``lights`` (the masked copies of Sec. 4)."""

        _, a, lights = prepare_pem_input(cube, lights, None, "per-face", f"{method.__name__} regions")
        # (a masked copy of a validated map is valid by construction: no check per region)
        return cls(lights, [method(adopt(partial_maps(a, lights.labels, i, i + 1)[:, :, :, 0, :], name="partial map"),
                                   **params) for i in range(len(lights))])

    @property
    def n_regions(self) -> int:
        return len(self.members)

    def __len__(self) -> int:
        return self.n_regions

    @property
    def nbytes(self) -> int:
        """Bytes stored by all members."""
        return int(sum(m.nbytes for m in self.members))

    @property
    def error_bound(self):
        """The largest member bound (each region's look-up is within it), or None if a member has none."""
        b = [m.error_bound for m in self.members]
        return None if any(x is None for x in b) else float(max(b))

    def lookup_all(self, directions, g) -> np.ndarray:
        """Look-ups of every region at glossiness ``g`` (scalar or per direction), (L, ..., C)."""

        s = phong_exponent(g)  # Eq. 3
        return np.stack([np.asarray(m.lookup(directions, s), dtype=np.float64) for m in self.members])

    def full_lookup(self, directions, g) -> np.ndarray:
        """Σ_i PEM_i: the unoccluded lighting."""
        return self.lookup_all(directions, g).sum(axis=0)

    # -- level chains (the error budget's best-level step) ----------------------------------------------
    def _chains(self):
        if not all(hasattr(m, "lookup_at_level") for m in self.members):
            raise IBLError("these prefilters are not level chains (no look-up at a given level)")
        return self.members

    @property
    def n_levels(self) -> int:
        return int(self._chains()[0].n_levels)

    @property
    def calibration(self):
        """The members' s → level table (they share one: same method, same parameters)."""
        return self._chains()[0].calibration

    def lookup_all_at_level(self, directions, level) -> np.ndarray:
        """Look-ups of every region at a given continuous level, (L, ..., C)."""
        return np.stack([np.asarray(m.lookup_at_level(directions, level), dtype=np.float64)
                         for m in self._chains()])
