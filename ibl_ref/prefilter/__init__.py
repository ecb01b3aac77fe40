"""Prefilter methods: one module per method, one declared interface, one registry (``docs/prefilters.md``).

A prefilter is built from an environment (a cube map ``(6, N, N, C)`` and the method's own parameters) and then
answers ``lookup(directions, param)`` → radiance ``(..., C)`` for the lobe family it serves (``lobe = "phong"``:
param = Phong exponent s; ``lobe = "ggx"``: param = perceptual roughness); it reports ``nbytes`` and
``error_bound`` (a proven bound or ``None``).  The interface is :class:`~ibl_ref.prefilter.interface.Prefilter`;
one map per median-cut region (the partial environment maps of Knuth et al. 2014's Eq. 5) is a region set,
:class:`~ibl_ref.prefilter.interface.RegionPrefilters`.  Methods are chosen by name through
:data:`~ibl_ref.prefilter.registry.PREFILTER_METHODS` and :func:`~ibl_ref.prefilter.registry.build_prefilter` /
:func:`~ibl_ref.prefilter.registry.build_region_prefilters` — by ``ibl-ref render --prefilter``, the renderer, and
the experiments ``render-error``, ``lobe-chain`` and ``error-budget`` alike.

Adding a method (one module plus one registry entry)
----------------------------------------------------
1. Write ``ibl_ref/prefilter/<paper>.py`` (named for the paper, e.g. ``karis2013.py``; docstring: paper, section,
   equations, what is approximated) with one class::

       class Karis2013SplitSum:
           \"\"\"One line for listings.\"\"\"
           lobe = "ggx"                                     # or "phong"
           paper = "Karis 2013, Real Shading in Unreal Engine 4, Sec. ..."

           def __init__(self, cube, *, n_samples=1024, ...):  # keyword parameters with defaults
               ...                                          # build: check the cube, store what it needs
           def lookup(self, directions, param):             # (..., 3), scalar or (...) -> (..., C)
               param = check_lobe_param(self.lobe, param)   # ibl_ref.prefilter.interface
               ...
           @property
           def nbytes(self): ...                            # bytes of the stored arrays
           @property
           def error_bound(self): return None               # or a proven bound (interface docstring)

   A Phong method whose look-up is one trilinear look-up in a chain of levels can subclass
   :class:`~ibl_ref.prefilter.level_chain.LevelChainPrefilter` (set ``self.pyramid``, ``self.calibration``).
2. Register it: one line ``"karis2013": Karis2013SplitSum,`` in :data:`~ibl_ref.prefilter.registry.PREFILTER_METHODS`
   (and its import in ``registry.py``).  ``ibl-ref render --prefilter`` then offers it (Phong methods), listings
   show it, and ``tests/test_prefilter.py`` runs the interface checks on it (shape and broadcasting, bad
   parameters, a constant environment).
3. Optional: a classmethod ``build_regions(cube, lights, **params)`` returning a region set, when the regions can
   be built jointly faster than one partial map at a time (default: :class:`~ibl_ref.prefilter.regions.RegionSet`).

Methods here: the paper's filter pyramid (``pyramid``, :mod:`~ibl_ref.prefilter.knuth2014_pyramid`), the exact-lobe
chain (``exact-lobe``, :mod:`~ibl_ref.prefilter.exact_lobe_chain`), Kautz & McCool's lobe maps (``km00-lobes``,
:mod:`~ibl_ref.prefilter.kautz_mccool2000_lobes`), Kán et al.'s specular maps (``kan2015``,
:mod:`~ibl_ref.prefilter.kan2015_maps`) and the peer tool cmft run as a program (``cmft``,
:mod:`~ibl_ref.prefilter.cmft_peer`) for Phong lobes; the GGX-era methods — Karis 2013's split sum with the exact,
an importance-sampled and a filtered-importance-sampled prefilter (``split-sum``, ``split-sum-is``,
:mod:`~ibl_ref.prefilter.karis2013`; ``split-sum-fis``, Křivánek & Colbert 2008,
:mod:`~ibl_ref.prefilter.krivanek_colbert2008`), Filament's cmgen run as a program (``cmgen``,
:mod:`~ibl_ref.prefilter.cmgen_peer`), GGX through a Phong prefilter (``ggx-phong-pem``, default the
paper's pyramid and its PEMs, :mod:`~ibl_ref.prefilter.ggx_phong_mapping`) — and SH9 irradiance for the cosine lobe
(``sh9``, Ramamoorthi & Hanrahan 2001, :mod:`~ibl_ref.prefilter.ramamoorthi_hanrahan2001`).
"""

import importlib

from .interface import LOBES, Prefilter, RegionPrefilters, check_lobe_param

__all__ = ["LOBES", "Prefilter", "RegionPrefilters", "check_lobe_param", "PREFILTER_METHODS", "build_prefilter",
           "build_region_prefilters", "prefilter_methods"]

#: the registry's names, imported on first use (the registry imports every method and SciPy: a command that needs
#: one module of the package, e.g. ``ibl-ref prefilter``'s karis2013, does not pay for them at start-up)
_REGISTRY_NAMES = ("PREFILTER_METHODS", "build_prefilter", "build_region_prefilters", "prefilter_methods")


def __getattr__(name):
    if name in _REGISTRY_NAMES:
        return getattr(importlib.import_module(".registry", __name__), name)
    if not name.startswith("__"):  # a method module not imported yet: as when the registry had imported it
        try:
            return importlib.import_module(f".{name}", __name__)
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.{name}":
                raise
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_REGISTRY_NAMES))
