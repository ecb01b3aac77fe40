"""The GGX prefilter lobe mapped to a Phong exponent, so that Phong-lobe prefilters (the exact Phong convolution,
Knuth et al. 2014's PEMs + VSM) can shade GGX materials through the split sum.

The split sum (:mod:`ibl_ref.prefilter.karis2013`) needs the prefiltered radiance ``P(r)`` of the radially
symmetric ``n = v = r`` kernel ``K(c) = D(√((1+c)/2))·max(c, 0)``, ``c = r·l``; a Phong-lobe prefilter provides the
lobe average of ``max(c, 0)^s``.  This module chooses s per GGX roughness and measures what the substitution costs.
Both lobes are normalised on the sphere: ``K̂ = K / (2π ∫₀¹ K dc)``, ``P̂_s = (s+1)/(2π) · max(c, 0)^s``.

Mappings (``mapping=``)
-----------------------
* ``"mean_cosine"`` (first-moment matching): the Phong lobe with the same mean cosine ⟨c⟩ as K̂.
  ``⟨c⟩_Phong = ∫₀¹ c^(s+1) dc / ∫₀¹ c^s dc = (s+1)/(s+2)``, hence ``s = (2μ − 1)/(1 − μ)`` with
  ``μ = ∫₀¹ K c dc / ∫₀¹ K dc`` (:func:`kernel_mean_cosine`).  This preserves the first SH band of the
  prefiltered radiance exactly (Funk–Hecke: a radially symmetric kernel scales band l by its Legendre mean
  ⟨P_l(c)⟩; l = 1 is ⟨c⟩), so a linear environment ``L = a + b·ω`` is prefiltered identically by both lobes.
* ``"peak_curvature"``: equal second-order behaviour at the peak.  With ``cos²θh = (1 + c)/2`` and γ the angle to
  r, ``D ∝ (α² + (1 − α²) sin²θh)⁻² ≈ 1 − 2(1 − α²)θh²/α²`` and ``θh = γ/2``, so
  ``K/K(0) ≈ (1 − (1 − α²)γ²/(2α²))(1 − γ²/2) ≈ 1 − γ²/(2α²)``, while ``cos^s γ ≈ 1 − sγ²/2``: ``s = 1/α²``.
* ``"tv_optimal"`` (default): the s that minimises the total-variation distance below (Brent's method in ln s,
  started at the mean-cosine s; per roughness, cached), i.e. the smallest worst-case bound.

GGX's NDF has a heavy tail (D ∝ θh⁻⁴ away from the peak) that no single cosine power reproduces: matching the
mean cosine puts the Phong lobe's width between the GGX core and its tail, matching the peak curvature fits the
core and drops the tail; the TV-optimal lobe still differs by TV ≈ 0.17–0.18 for roughness ≤ 0.2
(``python -c "from ibl_ref.prefilter import ggx_phong_mapping as g; print(g.lobe_tv(0.1, g.phong_exponent(0.1)))"``).

At roughness 1 (α = 1) D is constant, K is exactly the cosine lobe and every mapping gives s = 1.

Lobe error
----------
:func:`lobe_tv` is the total-variation distance ``TV = ½ ∫ |K̂ − P̂_s| dω`` ∈ [0, 1].  It bounds the prefilter error
of the substitution for *every* environment: ``|P_Phong(r) − P_GGX(r)| = |∫ L (P̂_s − K̂) dω| ≤ TV·(max L − min L)``
(in the continuum; discretely with the discrete lobes).  It is computed exactly up to the crossing points of the
two lobes (found by root finding) and a Gauss–Legendre rule in ``σ = ln(α² + (1 − α²)(1 − c)/2)`` (in which the
NDF peak is smooth): the lobes' masses between crossings are integrated separately, so no kink is sampled.
:func:`brdf_lobe_tv` compares a radially symmetric lobe about r (the Phong lobe, or K itself: the ``n = v = r``
assumption) with the true normalised GGX lobe ``f(l, v)(n·l) / albedo`` at a view angle θv (sphere quadrature
:func:`ibl_ref.lobes.brdfs.hemisphere_rule`; the part of the symmetric lobe below the horizon counts as error mass).
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import optimize

from ..environment.envmap import unit_directions
from ..errors import IBLError
from ..groundtruth.convolution_args import check_cube
from ..groundtruth.phong_convolution import lobe_average
from ..lobes import brdfs
from . import karis2013
from .knuth2014_pyramid import Knuth2014Pyramid
from .interface import check_lobe_param
from .regions import build_region_set

__all__ = ["MAPPINGS", "kernel_mass", "kernel_mean_cosine", "phong_mean_cosine", "phong_exponent", "lobe_tv",
           "brdf_lobe_tv", "GGXPhongMapping"]

#: GGX roughness → Phong exponent mappings of :func:`phong_exponent` (module doc)
MAPPINGS = ("mean_cosine", "peak_curvature", "tv_optimal")

_PANELS, _NODES = 24, 16
_S_MAX = 1e9


@functools.lru_cache(maxsize=16)
def _gl(nodes):
    x, w = np.polynomial.legendre.leggauss(nodes)
    return 0.5 * (x + 1), 0.5 * w


def _rule(alpha: float, c_lo: float, c_hi: float):
    """Nodes c and weights w with ``Σ w g(c) ≈ ∫_{c_lo}^{c_hi} g(c) dc`` for integrands ``K·(smooth)``: a
    Gauss–Legendre rule in σ = ln y, ``y = α² + (1 − α²)(1 − c)/2`` (module doc); plain in c when α² > 0.9."""
    x, w = _gl(_NODES)
    k = (np.arange(_PANELS)[:, None] + x[None, :]).ravel() / _PANELS
    wk = np.tile(w, _PANELS) / _PANELS
    a2 = alpha * alpha
    if a2 > 0.9:
        return c_lo + (c_hi - c_lo) * k, (c_hi - c_lo) * wk
    b = 1.0 - a2
    s_lo, s_hi = np.log(a2 + b * (1 - c_hi) / 2), np.log(a2 + b * (1 - c_lo) / 2)
    sig = s_lo + (s_hi - s_lo) * k
    y = np.exp(sig)
    c = 1.0 - 2.0 * (y - a2) / b
    return c, (s_hi - s_lo) * wk * 2.0 * y / b  # |dc/dσ| = 2y/(1 − α²)


def _kernel(c, alpha):
    return brdfs.ndf(np.sqrt(0.5 * (1.0 + c)), alpha) * np.maximum(c, 0.0)


def _mass(alpha: float, c_lo: float, c_hi: float) -> float:
    c, w = _rule(alpha, c_lo, c_hi)
    return float(np.sum(w * _kernel(c, alpha)))


def kernel_mass(roughness, c_lo: float = 0.0, c_hi: float = 1.0) -> float:
    """``∫_{c_lo}^{c_hi} K(c) dc`` of the unnormalised kernel (``0 ≤ c_lo ≤ c_hi ≤ 1``)."""
    _, alpha = karis2013.check_scalar_roughness(roughness)
    return _mass(alpha, max(float(c_lo), 0.0), min(float(c_hi), 1.0))


def kernel_mean_cosine(roughness) -> float:
    """Mean cosine ``μ = ∫₀¹ K c dc / ∫₀¹ K dc`` of the ``n = v = r`` GGX kernel."""
    _, alpha = karis2013.check_scalar_roughness(roughness)
    c, w = _rule(alpha, 0.0, 1.0)
    k = w * _kernel(c, alpha)
    return float(np.sum(k * c) / np.sum(k))


def phong_mean_cosine(s) -> np.ndarray:
    """Mean cosine of the normalised Phong lobe ``max(c, 0)^s``: ``(s+1)/(s+2)``."""
    s = np.asarray(s, dtype=np.float64)
    return (s + 1.0) / (s + 2.0)


def _tv(alpha: float, s: float) -> float:
    """TV distance between K̂ and P̂_s (module doc), exact up to root finding and the σ rule."""
    m_total = _mass(alpha, 0.0, 1.0)

    def diff(c):  # K̂ − P̂ per unit solid angle, times 2π
        return _kernel(c, alpha) / m_total - (s + 1.0) * c ** s

    c_nodes, _ = _rule(alpha, 0.0, 1.0)
    grid = np.unique(np.concatenate([[0.0, 1.0], c_nodes, np.linspace(0, 1, 65)]))
    vals = diff(grid)
    cuts = [0.0]
    for i in np.nonzero(np.sign(vals[:-1]) * np.sign(vals[1:]) < 0)[0]:
        cuts.append(optimize.brentq(diff, grid[i], grid[i + 1], xtol=1e-15, rtol=1e-15))
    cuts.append(1.0)
    tv = 0.0
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        k_part = _mass(alpha, lo, hi) / m_total
        p_part = hi ** (s + 1.0) - lo ** (s + 1.0)  # ∫ (s+1) c^s dc
        tv += abs(k_part - p_part)
    return 0.5 * tv  # ½ ∫|K̂ − P̂| dω = ½ · 2π ∫ |·| dc / (2π)


def _check_s(s) -> float:
    try:
        s = float(s)
    except (TypeError, ValueError):
        raise IBLError(f"Phong exponent s must be finite and >= 1, got {s!r}") from None
    if not (np.isfinite(s) and s >= 1.0):
        raise IBLError(f"Phong exponent s must be finite and >= 1, got {s!r}")
    return s


def lobe_tv(roughness, s) -> float:
    """Total-variation distance ``½ ∫ |K̂ − P̂_s| dω`` between the normalised ``n = v = r`` GGX kernel and the
    normalised Phong lobe of exponent ``s ≥ 1`` (module doc)."""
    _, alpha = karis2013.check_scalar_roughness(roughness)
    return _tv(alpha, _check_s(s))


@functools.lru_cache(maxsize=4096)
def _exponent(roughness: float, mapping: str) -> float:
    alpha = roughness * roughness
    if alpha == 1.0:
        return 1.0
    if mapping == "peak_curvature":
        return max(1.0 / (alpha * alpha), 1.0)
    mu = kernel_mean_cosine(roughness)
    s_mc = max((2.0 * mu - 1.0) / (1.0 - mu), 1.0)
    if mapping == "mean_cosine":
        return s_mc
    res = optimize.minimize_scalar(lambda ls: _tv(alpha, float(np.exp(ls))),
                                   bracket=(np.log(s_mc) - 0.3, np.log(s_mc) + 0.3),
                                   bounds=None, method="brent", tol=1e-8)
    return float(np.clip(np.exp(res.x), 1.0, _S_MAX))


def phong_exponent(roughness, mapping: str = "tv_optimal"):
    """Phong exponent s (≥ 1) for GGX roughness (scalar or array) by ``mapping`` (module doc)."""
    karis2013.check_option(mapping, MAPPINGS, "mapping")
    r, _ = karis2013.check_roughness(roughness)
    if np.ndim(r) == 0:
        return _exponent(float(r), mapping)
    flat = np.asarray(r).reshape(-1)
    uniq, inv = np.unique(flat, return_inverse=True)
    return np.array([_exponent(float(u), mapping) for u in uniq])[inv].reshape(np.shape(r))


def brdf_lobe_tv(roughness, theta_v: float, s=None, *, f0: float = 1.0, smith: str = "height_correlated",
                 width: float | None = None) -> float:
    """TV distance between the true normalised GGX lobe ``f(l, v)(n·l)/albedo`` at view angle θv (n = +z) and a
    lobe about the mirror direction r: the Phong lobe P̂_s, or (``s=None``) the ``n = v = r`` kernel K̂ (the split
    sum's lobe).  ``width``: smallest feature of the quadrature (default α/4, at most 0.02 rad)."""
    r_val, alpha = karis2013.check_scalar_roughness(roughness)
    if s is not None:
        s = _check_s(s)
    f = brdfs.get_brdf("ggx", roughness=r_val, f0=karis2013.check_f0(f0), smith=smith)
    wo = brdfs.view_direction(theta_v)
    wi, w = brdfs.hemisphere_rule(theta_v, min(0.02, alpha / 4) if width is None else float(width))
    g = f(wi, wo) * wi[:, 2]
    g = g / np.sum(g * w)
    r = np.array([np.sin(theta_v), 0.0, np.cos(theta_v)])
    c = wi @ r
    if s is None:
        m = _kernel(c, alpha) / (2.0 * np.pi * _mass(alpha, 0.0, 1.0))
    else:
        m = (s + 1.0) / (2.0 * np.pi) * np.maximum(c, 0.0) ** s
    below = max(1.0 - float(np.sum(m * w)), 0.0)  # model mass under the horizon (the true lobe has none)
    return 0.5 * (float(np.sum(np.abs(g - m) * w)) + below)


class GGXPhongMapping:
    """GGX through a Phong-lobe prefilter: roughness → Phong exponent s (mapping), the Phong look-up, a DFG table.

    ``lookup(directions, roughness)`` is the Phong prefilter's look-up at ``s = phong_exponent(roughness,
    mapping)``; :meth:`shade` is the split sum ``lookup(r, roughness)·(F0·A + B)`` with the DFG table.

    ``GGXPhongMapping(cube, phong_method=Knuth2014Pyramid)`` builds the Phong prefilter ``phong_method`` (a Phong
    method class; through :func:`ibl_ref.prefilter.registry.build_prefilter` also its registry name, e.g.
    ``"exact-lobe"``) with ``phong_params`` from the whole map — with the default, the paper's filter pyramid
    (Knuth et al. 2014): the paper's method for GGX materials; its partial environment maps for Eq. 5 (one per
    median-cut region, with visibilities) are :meth:`region_prefilters`.  :meth:`build` uses the exact Phong lobe
    average of the source instead (:func:`ibl_ref.groundtruth.phong_convolution.lobe_average`), which isolates the
    mapping's error; :meth:`from_lookup` takes any look-up ``(directions, s) -> (..., C)``.  ``error_bound`` is
    None (:func:`lobe_tv` bounds the continuum error of the mapping, not the discrete look-up).
    """

    lobe = "ggx"
    paper = ("Knuth et al. 2014 (PEMs + VSM, Eq. 5) for GGX: the split sum's n = v = r lobe replaced by the Phong lobe "
             "of the same roughness (TV-optimal exponent), the paper's filter pyramid, a DFG table (Karis 2013, Eq. 9)")
    error_bound = None

    def __init__(self, cube, *, phong_method=Knuth2014Pyramid, phong_params: dict | None = None,
                 mapping: str = "tv_optimal", dfg_size=64, smith: str = "height_correlated"):
        karis2013.check_option(mapping, MAPPINGS, "mapping")
        if not (isinstance(phong_method, type) and getattr(phong_method, "lobe", None) == "phong"):
            raise IBLError(f"phong_method must be a Phong prefilter class (or its registry name through "
                           f"ibl_ref.prefilter.build_prefilter), got {phong_method!r}")
        a, _ = check_cube(cube)
        self.phong_method = phong_method
        self.phong_params = dict(phong_params or {})
        self.phong = phong_method(a, **self.phong_params)
        self._init(self.phong.lookup, mapping, self.phong.nbytes, karis2013.build_dfg_table(dfg_size, smith=smith))
        self._cube = a

    def _init(self, phong_lookup, mapping, nbytes, dfg):
        karis2013.check_option(mapping, MAPPINGS, "mapping")
        self.phong_lookup = phong_lookup
        self.mapping = mapping
        self._nbytes = int(nbytes)
        self.dfg = dfg

    @classmethod
    def from_lookup(cls, phong_lookup, *, mapping: str = "tv_optimal", nbytes: int = 0, dfg=None):
        """The mapping on any Phong look-up ``phong_lookup(directions, s) -> (..., C)``."""
        obj = cls.__new__(cls)
        obj._init(phong_lookup, mapping, nbytes, dfg)
        return obj

    @classmethod
    def build(cls, cube, *, mapping: str = "tv_optimal", dfg_size=64, smith: str = "height_correlated"):
        """The mapping on the exact Phong lobe average of ``cube`` (no prefilter error)."""
        a, _ = check_cube(cube)
        return cls.from_lookup(lambda d, s: lobe_average(a, d, s), mapping=mapping, nbytes=a.nbytes,
                               dfg=karis2013.build_dfg_table(dfg_size, smith=smith))

    def exponent(self, roughness):
        """The Phong exponent s of each roughness (:func:`phong_exponent` with this mapping)."""
        return phong_exponent(roughness, self.mapping)

    def region_prefilters(self, lights):
        """The partial environment maps of ``lights`` (median-cut regions of the same map) with this Phong method
        (:func:`ibl_ref.prefilter.registry.build_region_prefilters`); look them up by the glossiness
        ``g = 1 − 1/s`` of :meth:`exponent` (Eq. 3)."""

        cube = getattr(self, "_cube", None)
        if cube is None:
            raise IBLError("region_prefilters needs a mapping built from a cube (GGXPhongMapping(cube, ...))")
        return build_region_set(self.phong_method, cube, lights, **self.phong_params)

    @property
    def nbytes(self) -> int:
        """Bytes of the Phong prefilter and the DFG table."""
        return self._nbytes + (self.dfg.nbytes if self.dfg is not None else 0)

    def lookup(self, directions, roughness) -> np.ndarray:

        d = unit_directions(directions, "directions")
        lead = d.shape[:-1]
        d = d.reshape(-1, 3)
        r = np.broadcast_to(check_lobe_param(self.lobe, roughness, directions), lead).reshape(-1)
        out = None
        for rv in np.unique(r):
            sel = r == rv
            vals = np.asarray(self.phong_lookup(d[sel], phong_exponent(float(rv), self.mapping)), dtype=np.float64)
            if out is None:
                out = np.empty((len(d), vals.shape[-1]))
            out[sel] = vals
        if out is None:  # no directions
            out = np.empty((0, 1))
        return out.reshape(lead + (out.shape[-1],))

    def shade(self, normals, views, roughness, f0) -> np.ndarray:
        """Split-sum specular radiance with the Phong-prefiltered radiance (:func:`ibl_ref.prefilter.karis2013.shade`)."""
        return karis2013.shade(self.lookup, self.dfg, normals, views, roughness, f0)
