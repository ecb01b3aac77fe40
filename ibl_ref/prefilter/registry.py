"""The prefilter methods by name, and the one dispatcher that builds them.

:data:`PREFILTER_METHODS` maps a method name to its class (:class:`~ibl_ref.prefilter.interface.Prefilter`);
:func:`build_prefilter` builds one from a cube map, :func:`build_region_prefilters` builds one per median-cut
region (the PEMs of Eq. 5), :func:`prefilter_methods` lists them (lobe family, paper, parameters) for ``--help``
and experiments.  Adding a method: its module in this package and one line here (package docstring).

Examples
--------
>>> from ibl_ref.prefilter.registry import PREFILTER_METHODS, prefilter_methods
>>> list(PREFILTER_METHODS)[:3]
['pyramid', 'exact-lobe', 'km00-lobes']
>>> sorted({m.lobe for m in prefilter_methods()})
['cosine', 'ggx', 'phong']
"""

from __future__ import annotations

import inspect
from typing import NamedTuple

from ..environment.validated import as_environment
from ..errors import IBLError
from .cmft_peer import CmftRadiance
from .cmgen_peer import CmgenPrefilter
from .exact_lobe_chain import ExactLobeChain
from .ggx_phong_mapping import GGXPhongMapping
from .kan2015_maps import Kan2015Maps
from .karis2013 import SplitSum, SplitSumImportance
from .kautz_mccool2000_lobes import KautzMcCool2000Lobes
from .knuth2014_pyramid import Knuth2014Pyramid
from .krivanek_colbert2008 import FilteredImportanceSampling
from .ramamoorthi_hanrahan2001 import SH9Irradiance
from .interface import LOBES
from .regions import build_region_set

__all__ = ["PREFILTER_METHODS", "PrefilterMethod", "prefilter_methods", "get_method", "region_params",
           "build_prefilter", "build_region_prefilters", "resolve_method_params"]

#: method name → prefilter class (each satisfies :class:`~ibl_ref.prefilter.interface.Prefilter`; its ``lobe``
#: says what the look-up parameter means: Phong exponent s, GGX roughness, or none for the cosine lobe)
PREFILTER_METHODS = {
    "pyramid": Knuth2014Pyramid,
    "exact-lobe": ExactLobeChain,
    "km00-lobes": KautzMcCool2000Lobes,
    "kan2015": Kan2015Maps,
    "cmft": CmftRadiance,
    "split-sum": SplitSum,
    "split-sum-is": SplitSumImportance,
    "split-sum-fis": FilteredImportanceSampling,
    "cmgen": CmgenPrefilter,
    "ggx-phong-pem": GGXPhongMapping,
    "sh9": SH9Irradiance,
}


class PrefilterMethod(NamedTuple):
    """One registered method: name, lobe family, paper, one-line summary, its parameters (name → default)."""

    name: str
    lobe: str
    paper: str
    summary: str
    params: dict


def get_method(method: str):
    """The class registered as ``method``, or a one-line :class:`IBLError` naming the choices."""
    try:
        return PREFILTER_METHODS[method]
    except (KeyError, TypeError):
        raise IBLError(f"unknown prefilter method {method!r}; choose one of {', '.join(PREFILTER_METHODS)}") from None


def _params(fn) -> dict:
    names = {cls: name for name, cls in PREFILTER_METHODS.items()}
    return {p.name: names.get(p.default, p.default) if isinstance(p.default, type) else p.default
            for p in inspect.signature(fn).parameters.values() if p.kind is p.KEYWORD_ONLY}


def prefilter_methods(lobe: str | None = None) -> list:
    """The registered methods (optionally of one lobe family) as :class:`PrefilterMethod` rows, in registry order.

    Parameters
    ----------
    lobe : str, optional
        Only the methods of this lobe family (``"phong"``, ``"ggx"`` or ``"cosine"``); default: every method.

    Returns
    -------
    list of PrefilterMethod
        ``(name, lobe, paper, summary, params)``; ``params`` are the keyword parameters of the full-map build
        (``Method(cube, **params)``) with their defaults.

    Raises
    ------
    IBLError
        If ``lobe`` is not a lobe family.

    Examples
    --------
    >>> from ibl_ref.prefilter.registry import prefilter_methods
    >>> [m.name for m in prefilter_methods("cosine")]
    ['sh9']
    >>> pyramid = prefilter_methods("phong")[0]
    >>> pyramid.name, pyramid.params["kernel"]
    ('pyramid', 'sqrtcos')
    """

    if lobe is not None and lobe not in LOBES:
        raise IBLError(f"unknown lobe family {lobe!r}; choose one of {', '.join(LOBES)}")
    rows = []
    for name, cls in PREFILTER_METHODS.items():
        if lobe is None or cls.lobe == lobe:
            summary = (cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else ""
            rows.append(PrefilterMethod(name, cls.lobe, cls.paper, summary, _params(cls.__init__)))
    return rows


def region_params(method: str) -> dict:
    """Keyword parameters (name → default) of a method's region build (its ``build_regions``, else its own)."""
    cls = get_method(method)
    return _params(getattr(cls, "build_regions", cls.__init__))


def resolve_method_params(params: dict) -> dict:
    """``params`` with the value of every parameter named ``*_method`` given as a registry name replaced by its
    class (a method built on another method, e.g. ``ggx-phong-pem``'s ``phong_method="exact-lobe"``)."""
    return {k: (get_method(v) if k.endswith("_method") and isinstance(v, str) else v) for k, v in params.items()}


def _check_params(method: str, accepted: dict, params: dict, what: str) -> None:
    """A one-line :class:`IBLError` for a keyword the method's build does not take (instead of Python's TypeError)."""
    unknown = sorted(set(params) - set(accepted))
    if unknown:
        raise IBLError(f"prefilter {method!r}: unknown parameter(s) {', '.join(map(repr, unknown))} of its {what}; "
                       f"it takes {', '.join(accepted) or 'no parameters'}")


def build_prefilter(cube, method: str = "pyramid", **params):
    """The prefilter ``PREFILTER_METHODS[method](cube, **params)`` of a cube map.

    Parameters
    ----------
    cube : array (6, N, N, C)
        Radiance of the environment (finite, ≥ 0; the radiance policy of
        :func:`ibl_ref.environment.radiance_policy.check_radiance` applies).
    method : str
        A name of :data:`PREFILTER_METHODS` (default ``"pyramid"``, the paper's filter pyramid).
    **params
        The method's own keyword parameters (:func:`prefilter_methods` lists them with their defaults); a
        parameter ``*_method`` may name a registered method (:func:`resolve_method_params`).

    Returns
    -------
    Prefilter
        The built method: ``lookup(directions, param)``, ``nbytes``, ``error_bound``, ``lobe``, ``paper``
        (:class:`~ibl_ref.prefilter.interface.Prefilter`).

    Raises
    ------
    IBLError
        An unknown method or parameter, a bad cube, or a bad parameter value (one line each).

    Examples
    --------
    A constant environment is its own lobe average, for every lobe:

    >>> import numpy as np
    >>> from ibl_ref.prefilter.registry import build_prefilter
    >>> cube = np.full((6, 8, 8, 3), 0.5)
    >>> pf = build_prefilter(cube, "exact-lobe")
    >>> pf.lobe
    'phong'
    >>> np.round(pf.lookup(np.array([[0.0, 0.0, 1.0]]), 16.0), 6)
    array([[0.5, 0.5, 0.5]])
    >>> build_prefilter(cube, "sh9", order=2)
    Traceback (most recent call last):
    ...
    ibl_ref.errors.IBLError: prefilter 'sh9': unknown parameter(s) 'order' of its build; it takes no parameters
    """
    cls = get_method(method)
    _check_params(method, _params(cls.__init__), params, "build")
    # checked once here (the method's own check passes an Environment through)
    return cls(as_environment(cube, "environment cube map"), **resolve_method_params(params))


def build_region_prefilters(cube, lights=None, method: str = "pyramid", *, n_lights: int | None = None,
                            variant: str = "per-face", **params):
    """One prefiltered map per median-cut region (the PEMs of Eq. 5) → a region set
    (:class:`~ibl_ref.prefilter.interface.RegionPrefilters`).

    ``lights``: the regions (:func:`ibl_ref.knuth2014.median_cut.median_cut` of the same map), or ``n_lights``
    and ``variant`` to cut them here.  The method's ``build_regions`` if it has one (a joint build), else
    :meth:`ibl_ref.prefilter.regions.RegionSet.build` (the method on every partial map).
    """
    cls = get_method(method)
    if cls.lobe != "phong":
        raise IBLError(f"prefilter {method!r} serves {cls.lobe} lobes; partial environment maps (Eq. 5) are looked "
                       "up by glossiness g and need a Phong prefilter")
    if lights is None:
        if n_lights is None:
            raise IBLError("build_region_prefilters: give either lights (a LightSet) or n_lights")
        from ..knuth2014.median_cut import median_cut

        lights = median_cut(cube, n_lights, variant)
    _check_params(method, region_params(method), params, "region build")

    return build_region_set(cls, as_environment(cube, "environment cube map"), lights, **params)
