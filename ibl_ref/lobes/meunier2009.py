"""Meunier et al. (2009) "Cosine Lobes for Interactive Direct Lighting in Dynamic Scenes" — lobe algebra.

Implements, from the HAL technical report hal-00401728:

* the cosine lobe ``c(v) = s·max(a·v, 0)^e`` (Eq. 4–5) and its closed-form integral over the sphere
  ``∫ c dω = 2π s/(e+1)`` (Eq. 20–21; the paper tabulates it, Sec. 4.2: 128 linearly spaced samples in each
  interval [0,1], [1,10], …, [1e4,1e5] with linear interpolation — :class:`IntegralTable`);
* the product of two lobes approximated by one lobe ``c1·c2 ≈ s1 s2 p_r max(a_r·v,0)^e_r`` (Eq. 15–19):
  axis by Nelder–Mead maximising ``c1(a_r) c2(a_r)`` (Eq. 18), partial scale and exponent by
  Levenberg–Marquardt on the L2 distance (Eq. 19), initialised with ``e_r = e1+e2`` — :func:`fit_product`,
  :func:`lobe_product`; identical axes give ``e1+e2`` and ``s1 s2`` exactly (no fit);
* the spherical cap ↔ lobe exponent L2 fit (Eq. 32–34) — :func:`cap_exponent`, :func:`cap_angle`,
  :class:`CapTable` (the paper's 1000-entry table, linear interpolation), and
  :func:`region_equivalent_lobe` (cap of solid angle Ω = 2π(1−cos α), for a median-cut region).

Conventions (choices that change numbers)
-----------------------------------------
* **Support.**  ``max(a·v,0)^e`` is taken as 0 where ``a·v ≤ 0`` for every ``e ≥ 0``: the ``e = 0`` lobe is the
  indicator of the open hemisphere, so the integral ``2π/(e+1)`` is continuous at ``e = 0``.  The paper's Eq. 40
  instead reads ``max(n·v,0)^0 = 1`` everywhere (0⁰ = 1, a constant over the whole sphere, integral 4π); that
  "unit lobe" is not a member of the family used here.
* **Quadrature frame for products.**  With the axes in the plane z = 0, ``a1`` at longitude ψ=0 and ``a2`` at
  ψ=θ, a direction ``v = (cos λ cos ψ, cos λ sin ψ, sin λ)`` gives ``a_i·v = cos λ cos(ψ−ψ_i)``: every lobe
  whose axis lies in that plane is *separable* in (λ, ψ), ``dω = cos λ dλ dψ``.  The λ-integrals are Wallis
  integrals ``W(n) = ∫cosⁿλ dλ = √π Γ((n+1)/2)/Γ(n/2+1)``; ψ-integrals are 1-D.  This is exact (not an
  approximation): it only uses the fact that the optimal axis lies on the great circle through a1 and a2.
* **Scale parametrisation.**  The fit is done on the peak-normalised product ``c1c2/M`` with
  ``M = c1(a_r)c2(a_r)`` (log-space, never underflows); ``p_r = M·q``.  ``log_p`` is always finite (or −inf for
  a product that is identically zero), ``p`` may underflow to 0 for extreme exponents — that is the true value
  in float64.  The paper initialises ``p_r = 1``; we initialise ``q = 1`` (peak match), which is the same
  start for identical axes.

Exponents are accepted in ``[0, 1e7]`` (the paper samples ``[0, 1e5]``); negative, NaN or infinite exponents and
zero axes raise :class:`~ibl_ref.errors.IBLError`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy import integrate, optimize, special

from ..errors import IBLError
from ..environment.envmap import unit_directions

__all__ = [
    "E_MAX",
    "check_exponent",
    "cosine_lobe",
    "lobe_integral",
    "lobe_integral_quadrature",
    "paper_exponent_samples",
    "IntegralTable",
    "ProductFit",
    "fit_product",
    "product_integral_exact",
    "lobe_product",
    "ProductTable",
    "cap_fit_error",
    "cap_exponent",
    "cap_angle",
    "CapTable",
    "RegionLobe",
    "region_equivalent_lobe",
]

#: Largest exponent accepted (the paper samples exponents in [0, 1e5]; we allow headroom for products).
E_MAX = 1e7
TWO_PI = 2.0 * np.pi
_LOG_TINY = -700.0


# --------------------------------------------------------------------------------------------- checks
def check_exponent(e, name: str = "exponent", e_max: float = E_MAX) -> np.ndarray:
    """Lobe exponents as a float64 array after checking ``0 ≤ e ≤ e_max`` and finiteness.

    Parameters
    ----------
    e : float or array_like
    name : str, optional
        What the argument is called in error messages.
    e_max : float, optional
        Largest exponent accepted (default :data:`E_MAX`).

    Returns
    -------
    ndarray, float64

    Raises
    ------
    IBLError
        NaN, ±Inf, negative or too large exponents.
    """
    a = np.asarray(e, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise IBLError(f"{name}: must be finite, got {e!r}")
    if np.any(a < 0):
        raise IBLError(f"{name}: cosine-lobe exponents must be >= 0, got min {a.min()!r}")
    if np.any(a > e_max):
        raise IBLError(f"{name}: exponent {a.max()!r} exceeds the supported maximum {e_max:g}")
    return a


def _check_axis(a, name: str = "axis") -> np.ndarray:
    """Unit lobe axis (..., 3); an axis shorter than 1e-12 cannot define a cosine lobe."""

    return unit_directions(a, name, min_norm=1e-12)


def _check_scale(s, name: str = "scale") -> np.ndarray:
    a = np.asarray(s, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise IBLError(f"{name}: must be finite")
    return a


def _pow_clamped(c, e):
    """``max(c,0)^e`` with the support convention of this module (0 where c ≤ 0, also for e = 0), log-space."""
    c = np.asarray(c, dtype=np.float64)
    e = np.asarray(e, dtype=np.float64)
    pos = c > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        lg = np.where(pos, e * np.log(np.where(pos, c, 1.0)), -np.inf)
    return np.exp(lg)


def _elog(e, c):
    """``e·log(c)`` for c > 0 with the convention 0·log(anything) = 0; −inf where c ≤ 0 and e > 0."""
    e = np.asarray(e, dtype=np.float64)
    c = np.asarray(c, dtype=np.float64)
    pos = c > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(pos, e * np.log(np.where(pos, c, 1.0)), np.where(e > 0, -np.inf, 0.0))
    return out


# ------------------------------------------------------------------------------------ lobe + integral
def cosine_lobe(v, axis, e, s=1.0) -> np.ndarray:
    """Cosine lobe ``c(v) = s·max(a·v, 0)^e`` (Meunier 2009, Eq. 4).

    Parameters
    ----------
    v : array (..., 3)
        Directions (need not be normalised; they are normalised here).
    axis : array (3,)
        Lobe axis ``a`` (normalised here; zero length → :class:`IBLError`).
    e : float
        Exponent ("thickness") ``e ≥ 0``.
    s : float
        Scale ``s``.

    Returns
    -------
    ndarray, shape (...)

    Raises
    ------
    IBLError
        A zero axis, an invalid exponent or scale.

    Examples
    --------
    >>> from ibl_ref.lobes.meunier2009 import cosine_lobe
    >>> cosine_lobe([[0, 0, 1], [1, 0, 1], [0, 1, -1]], axis=[0, 0, 1], e=2.0)
    array([1. , 0.5, 0. ])
    """
    a = _check_axis(axis)
    e = check_exponent(e)
    s = _check_scale(s)
    v = np.asarray(v, dtype=np.float64)
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    return s * _pow_clamped(v @ a, e)


def lobe_integral(e, s=1.0) -> np.ndarray:
    """Closed-form ``∫_S² s·max(a·v,0)^e dω = 2π s/(e+1)`` (Eq. 20–21; hemispherical support, see module doc).

    Parameters
    ----------
    e : float or array_like
        Exponents in [0, :data:`E_MAX`].
    s : float or array_like, optional
        Scales.

    Returns
    -------
    ndarray, float64
        Steradians × scale.

    Examples
    --------
    The closed form against adaptive quadrature (:func:`lobe_integral_quadrature`, an independent route):

    >>> import numpy as np
    >>> from ibl_ref.lobes.meunier2009 import lobe_integral, lobe_integral_quadrature
    >>> float(lobe_integral(3.0) / np.pi), float(lobe_integral_quadrature(3.0) / np.pi)
    (0.5, 0.5)
    """
    e = check_exponent(e)
    return TWO_PI * _check_scale(s) / (e + 1.0)


def lobe_integral_quadrature(e, epsrel: float = 1e-12) -> float:
    """Adaptive-quadrature value of ``∫_S² max(a·v,0)^e dω`` (independent of the closed form).

    Integrates over the polar angle β about the axis, ``2π ∫_0^{π/2} cos^e β sin β dβ``, with
    :func:`scipy.integrate.quad` and a break point at the lobe's width ``1/√(e+1)``.

    Parameters
    ----------
    e : float
        Exponent in [0, :data:`E_MAX`].
    epsrel : float, optional
        Relative tolerance of the quadrature.

    Returns
    -------
    float
    """
    e = float(check_exponent(e))
    w = min(1.0 / np.sqrt(e + 1.0), np.pi / 2)

    def f(b):
        return np.exp(_elog(e, np.cos(b))) * np.sin(b)

    pts = [p for p in (w / 4, w, 4 * w) if p < np.pi / 2]
    val, _ = integrate.quad(f, 0.0, np.pi / 2, points=pts, epsabs=0.0, epsrel=epsrel, limit=500)
    return TWO_PI * val


def paper_exponent_samples(per_interval: int, e_max: float = 1e5) -> np.ndarray:
    """The paper's exponent sampling: ``per_interval`` linearly spaced samples in each of
    [0,1], [1,10], …, [e_max/10, e_max] (Sec. 4.1: 16 per interval for the product table; Sec. 4.2: 128 for the
    integral table).  Shared interval ends are kept once.

    Parameters
    ----------
    per_interval : int
        At least 2.
    e_max : float, optional

    Returns
    -------
    ndarray, float64
        Sorted, unique.

    Examples
    --------
    >>> from ibl_ref.lobes.meunier2009 import paper_exponent_samples
    >>> paper_exponent_samples(3, 100.0).tolist()
    [0.0, 0.5, 1.0, 5.5, 10.0, 55.0, 100.0]
    """
    if per_interval < 2:
        raise IBLError(f"per_interval must be >= 2, got {per_interval}")
    edges = [0.0, 1.0]
    while edges[-1] < e_max * (1 - 1e-12):
        edges.append(edges[-1] * 10.0)
    parts = [np.linspace(a, b, per_interval) for a, b in zip(edges[:-1], edges[1:])]
    return np.unique(np.concatenate(parts))


class IntegralTable:
    """The paper's tabulated lobe integral with linear interpolation (Sec. 4.2).

    Nodes: :func:`paper_exponent_samples` ``(per_interval)``; values: the closed form ``2π/(e+1)`` (the paper
    used adaptive Gauss quadrature; at nodes both agree to ~1e-12).  Exponents beyond the last node raise.
    """

    def __init__(self, per_interval: int = 128, e_max: float = 1e5):
        self.nodes = paper_exponent_samples(per_interval, e_max)
        self.values = TWO_PI / (self.nodes + 1.0)

    def __call__(self, e) -> np.ndarray:
        e = check_exponent(e)
        if np.any(e > self.nodes[-1]):
            raise IBLError(f"exponent {e.max()!r} outside the table range [0, {self.nodes[-1]:g}]")
        return np.interp(e, self.nodes, self.values)


# ---------------------------------------------------------------------------------- product of lobes
_GL_X, _GL_W = np.polynomial.legendre.leggauss(8)


def _gl_rule(breaks):
    """Composite 8-point Gauss–Legendre nodes/weights on the sorted break points."""
    b = np.unique(np.asarray(breaks, dtype=np.float64))
    a0, a1 = b[:-1], b[1:]
    keep = a1 - a0 > 1e-15
    a0, a1 = a0[keep], a1[keep]
    half = 0.5 * (a1 - a0)
    mid = 0.5 * (a1 + a0)
    x = (mid[:, None] + half[:, None] * _GL_X[None, :]).ravel()
    w = (half[:, None] * _GL_W[None, :]).ravel()
    return x, w


def _graded(center, lo, hi, width, n_end=8):
    """Break points graded geometrically around ``center`` (scale ``width``) and towards the ends lo, hi."""
    pts = [lo, hi, center]
    k = np.arange(-2, 40)
    d = width * 2.0 ** k
    d = d[d < (hi - lo)]
    pts += list(center - d) + list(center + d)
    L = hi - lo
    dd = L * 2.0 ** -np.arange(1, n_end + 1)
    pts += list(lo + dd) + list(hi - dd)
    p = np.asarray(pts)
    return p[(p >= lo) & (p <= hi)]


def _log_wallis(n):
    """log W(n), W(n) = ∫_{−π/2}^{π/2} cosⁿλ dλ = √π Γ((n+1)/2)/Γ(n/2+1)."""
    n = np.asarray(n, dtype=np.float64)
    return 0.5 * np.log(np.pi) + special.gammaln((n + 1) / 2) - special.gammaln(n / 2 + 1)


@dataclass(frozen=True)
class ProductFit:
    """One-lobe approximation of ``max(a1·v,0)^e1 · max(a2·v,0)^e2`` (unit scales), Eq. 15–19.

    Attributes
    ----------
    t : float
        Angle of the fitted axis ``a_r`` from ``a1`` towards ``a2`` (rad), ``0 ≤ t ≤ θ``.
    e_r : float
        Fitted exponent.
    log_p : float
        log of the partial scale ``p_r`` (finite, or −inf for an identically zero product).
    p : float
        ``exp(log_p)`` (may underflow to 0: the product is then below float64 range).
    integral_exact : float
        ``∫ c1 c2 dω`` by adaptive quadrature (Wallis closed form in λ × :func:`scipy.integrate.quad` in ψ).
    integral_fit : float
        ``∫ c_r dω = 2π p_r/(e_r+1)``.
    l2_rel : float
        ``‖c1c2 − c_r‖₂ / ‖c1c2‖₂`` (0 for a zero product).
    exact : bool
        True when no fit was needed (identical axes, or a zero product).
    solver : str
        "exact", "lm", "varpro", or "lm->varpro" (LM ended with a worse L2 residual than variable projection,
        whose result is returned; happens for very flat problems such as e1 = e2 = 0).
    """

    e1: float
    e2: float
    theta: float
    t: float
    e_r: float
    log_p: float
    p: float
    integral_exact: float
    integral_fit: float
    l2_rel: float
    exact: bool
    solver: str = "exact"

    @property
    def abs_err(self) -> float:
        """|∫c1c2 − ∫c_r| — the error measure of the paper's Sec. 4.1 / Fig. 3 (unit scales)."""
        return abs(self.integral_exact - self.integral_fit)


def _log_peak(e1, e2, theta, t):
    return float(_elog(e1, np.cos(t)) + _elog(e2, np.cos(theta - t)))


def _find_axis(e1, e2, theta, xatol=1e-10):
    """Eq. 18 with Nelder–Mead on the sphere, parametrised by (ψ, λ) in the frame of the module doc, started at
    the bisector (a1+a2)/|a1+a2| as in the paper.  Maximises log(c1 c2) (no underflow)."""

    def neg_log(x):
        psi, lam = x
        c1 = np.cos(lam) * np.cos(psi)
        c2 = np.cos(lam) * np.cos(psi - theta)
        v = _elog(e1, c1) + _elog(e2, c2)
        if not np.isfinite(v) or c1 <= 0 or c2 <= 0:
            return 1e300
        return -float(v)

    x0 = np.array([theta / 2, 0.0])
    scale = max(min(theta / 4, 0.5), 1e-6)
    simplex = np.array([x0, x0 + [scale, 0.0], x0 + [0.0, scale]])
    res = optimize.minimize(
        neg_log, x0, method="Nelder-Mead",
        options=dict(xatol=xatol, fatol=1e-14, initial_simplex=simplex, maxiter=4000),
    )
    psi = float(np.clip(res.x[0], 0.0, theta))
    return psi


def product_integral_exact(e1, e2, theta, epsrel: float = 1e-10) -> float:
    """``∫_S² max(a1·v,0)^e1 max(a2·v,0)^e2 dω`` for axes at angle θ (adaptive quadrature reference).

    Uses the separable frame of the module doc: Wallis closed form in λ times an adaptive
    :func:`scipy.integrate.quad` over ψ ∈ [θ−π/2, π/2] (the overlap of the two supports), evaluated in log space
    relative to the peak so that it never overflows.

    Parameters
    ----------
    e1, e2 : float
        Exponents in [0, :data:`E_MAX`].
    theta : float
        Angle between the axes, in [0, π] (rad).
    epsrel : float, optional
        Relative tolerance of the quadrature.

    Returns
    -------
    float
        0.0 when the supports do not overlap (θ ≥ π).

    Raises
    ------
    IBLError
        Invalid exponents, θ outside [0, π].
    """
    e1 = float(check_exponent(e1, "e1"))
    e2 = float(check_exponent(e2, "e2"))
    theta = float(theta)
    if not (0.0 <= theta <= np.pi):
        raise IBLError(f"theta must be in [0, π], got {theta!r}")
    lo, hi = theta - np.pi / 2, np.pi / 2
    if hi - lo <= 0:
        return 0.0
    t = _axis_root(e1, e2, theta)
    log_m = _log_peak(e1, e2, theta, t)

    def f(psi):
        return np.exp(_elog(e1, np.cos(psi)) + _elog(e2, np.cos(psi - theta)) - log_m)

    wpsi = 1.0 / np.sqrt(e1 + e2 + 1.0)
    pts = sorted({p for p in (t - 4 * wpsi, t - wpsi, t, t + wpsi, t + 4 * wpsi) if lo < p < hi})
    val, _ = integrate.quad(f, lo, hi, points=pts or None, epsabs=0.0, epsrel=epsrel, limit=1000)
    log_i = log_m + _log_wallis(e1 + e2 + 1.0) + np.log(val) if val > 0 else -np.inf
    return float(np.exp(log_i))


def _axis_root(e1, e2, theta):
    """Independent route to the product's peak angle: root of d/dt[e1 log cos t + e2 log cos(θ−t)] = 0,
    i.e. e1 tan t = e2 tan(θ−t), by Brent's method (used for the quadrature reference and the tests)."""
    if theta <= 0:
        return 0.0
    if e1 == 0 and e2 == 0:
        return theta / 2
    if e1 == 0:  # c1 is an indicator: peak of c2 inside the support of c1 (ψ < π/2)
        return min(theta, np.pi / 2)
    if e2 == 0:
        return max(0.0, theta - np.pi / 2)

    def g(t):
        return -e1 * np.tan(t) + e2 * np.tan(theta - t)

    eps = 1e-15
    lo = max(0.0, theta - np.pi / 2 + eps)
    hi = min(theta, np.pi / 2 - eps)
    return float(optimize.brentq(g, lo, hi, xtol=1e-15, rtol=1e-15))


def _product_rule(e1, e2, theta, t, e_guess):
    """Tensor quadrature (λ-nodes, ψ-nodes, weights) covering the support of c_r ⊇ support of c1c2."""
    w_lam = 1.0 / np.sqrt(max(e1 + e2, e_guess) + 1.0)
    lam, wl = _gl_rule(_graded(0.0, 0.0, np.pi / 2, w_lam, n_end=10))
    wl = 2.0 * wl * np.cos(lam)  # symmetric in λ; measure cos λ dλ
    curv = e1 / max(np.cos(t), 1e-300) ** 2 + e2 / max(np.cos(theta - t), 1e-300) ** 2
    w_psi = 1.0 / np.sqrt(max(curv, e_guess) + 1.0)
    lo, hi = t - np.pi / 2, t + np.pi / 2
    br = list(_graded(t, lo, hi, w_psi))
    flo, fhi = theta - np.pi / 2, np.pi / 2  # kinks of the product's support
    for c in (flo, fhi):
        d = (hi - lo) * 2.0 ** -np.arange(2, 8)
        br += [c] + list(c - d) + list(c + d)
    br = np.asarray(br)
    psi, wp = _gl_rule(br[(br >= lo) & (br <= hi)])
    return lam, wl, psi, wp


def fit_product(e1, e2, theta, *, method: str = "lm") -> ProductFit:
    """Fit one cosine lobe to the product of two unit-scale lobes with exponents e1, e2 and axes at angle θ.

    Eq. 17–19 of Meunier et al. (2009): axis ``a_r`` by Nelder–Mead maximising ``c1(a_r)c2(a_r)`` (Eq. 18);
    then ``(p_r, e_r)`` minimising ``∫(c1c2 − c_r)² dω`` (Eq. 19).

    Parameters
    ----------
    e1, e2 : float
        Exponents in [0, :data:`E_MAX`].
    theta : float
        Angle between the axes, in [0, π] (rad).
    method : {"lm", "varpro"}
        ``"lm"``: Levenberg–Marquardt (:func:`scipy.optimize.least_squares` ``method="lm"``) on (log q, log e_r)
        with residuals sampled on a tensor Gauss–Legendre rule, as in the paper.  ``"varpro"``: the same L2
        problem solved by eliminating the scale in closed form and a bounded 1-D search on log e_r — an
        independent route used to check the LM result.

    Returns
    -------
    ProductFit
        Identical axes (θ = 0) return ``e_r = e1+e2``, ``p_r = 1`` exactly (``exact=True``).

    Raises
    ------
    IBLError
        Invalid exponents, θ outside [0, π], an unknown method.

    Examples
    --------
    Two lobes 0.3 rad apart: the fitted axis lies between them, nearer the sharper one, and the fitted lobe's
    integral matches the exact product's (quadrature, :func:`product_integral_exact`) to 2e-4 relative:

    >>> from ibl_ref.lobes.meunier2009 import fit_product
    >>> fit = fit_product(10.0, 20.0, 0.3)
    >>> 0.15 < fit.t < 0.3, round(fit.e_r, 1)
    (True, 30.3)
    >>> bool(fit.abs_err < 2e-4 * fit.integral_exact)
    True
    """
    e1 = float(check_exponent(e1, "e1"))
    e2 = float(check_exponent(e2, "e2"))
    theta = float(theta)
    if not np.isfinite(theta) or not (0.0 <= theta <= np.pi):
        raise IBLError(f"theta must be in [0, π], got {theta!r}")
    if method not in ("lm", "varpro"):
        raise IBLError(f"method must be 'lm' or 'varpro', got {method!r}")
    if theta == 0.0:  # c1 c2 = max(a·v,0)^(e1+e2) exactly
        integ = float(TWO_PI / (e1 + e2 + 1.0))
        return ProductFit(e1, e2, 0.0, 0.0, e1 + e2, 0.0, 1.0, integ, integ, 0.0, True)
    if theta >= np.pi - 1e-12:  # supports touch on a great circle only: product ≡ 0
        return ProductFit(e1, e2, theta, theta / 2, e1 + e2, -np.inf, 0.0, 0.0, 0.0, 0.0, True)

    t = _find_axis(e1, e2, theta)
    log_m = _log_peak(e1, e2, theta, t)
    if log_m < _LOG_TINY:  # product < 1e-304 everywhere: float64 zero; the cheap route gives the same L2 fit
        method = "varpro"
    e0 = max(e1 + e2, 0.5)  # paper: e1+e2; floored (e1 = e2 = 0 would start LM on a flat ridge)
    lam, wl, psi, wp = _product_rule(e1, e2, theta, t, e0)
    cl = np.cos(lam)
    # separable factors of the peak-normalised product f̂ = c1c2/M
    f_lam = np.exp(_elog(e1 + e2, cl))
    in_f = (np.cos(psi) > 0) & (np.cos(psi - theta) > 0)
    log_f_psi = _elog(e1, np.cos(psi)) + _elog(e2, np.cos(psi - theta)) - (
        _elog(e1, np.cos(t)) + _elog(e2, np.cos(theta - t)))
    f_psi = np.exp(np.minimum(np.where(in_f, log_f_psi, -np.inf), 0.0))  # ≤ 1 by construction of t
    c_lam = np.log(cl)
    c_psi_cos = np.cos(psi - t)
    c_psi = np.where(c_psi_cos > 0, np.log(np.where(c_psi_cos > 0, c_psi_cos, 1.0)), -np.inf)
    sw = np.sqrt(wl[:, None] * wp[None, :])
    F = sw * (f_lam[:, None] * f_psi[None, :])
    norm_f = float(np.sqrt(np.sum(F * F)))
    if norm_f == 0.0 or not np.isfinite(norm_f):
        raise IBLError(f"product quadrature failed for e1={e1}, e2={e2}, θ={theta}")  # pragma: no cover

    def g_hat(e_r):
        with np.errstate(invalid="ignore"):
            gl = np.exp(e_r * c_lam)
            gp = np.where(np.isfinite(c_psi), np.exp(e_r * np.where(np.isfinite(c_psi), c_psi, 0.0)), 0.0)
        return sw * (gl[:, None] * gp[None, :])

    c_sum = c_lam[:, None] + np.where(np.isfinite(c_psi), c_psi, 0.0)[None, :]
    solver = method
    if method == "lm":
        def resid(x):
            return (F - np.exp(x[0]) * g_hat(np.exp(x[1]))).ravel() / norm_f

        def jac(x):  # analytic: d r/d log q = −qG, d r/d log e = −q e G·(log cos λ + log cos(ψ−t))
            qG = np.exp(x[0]) * g_hat(np.exp(x[1]))
            return -np.stack([qG.ravel(), (np.exp(x[1]) * qG * c_sum).ravel()], axis=1) / norm_f

        sol = optimize.least_squares(resid, x0=[0.0, np.log(e0)], jac=jac, method="lm", xtol=1e-12,
                                     ftol=1e-12, gtol=1e-12, max_nfev=200)
        log_q, e_r = float(sol.x[0]), float(np.exp(sol.x[1]))
        if not (np.isfinite(log_q) and np.isfinite(e_r)) or float(np.sum(sol.fun**2)) > 0.04:
            # LM stuck (e.g. ran to the e_r → ∞ plateau): compare with the variable-projection solution
            alt = fit_product(e1, e2, theta, method="varpro")
            if not np.isfinite(log_q) or alt.l2_rel ** 2 < float(np.sum(sol.fun**2)) - 1e-12:
                return dataclasses.replace(alt, solver="lm->varpro")
    else:
        def obj(u):
            G = g_hat(np.exp(u))
            gg = np.sum(G * G)
            return 1.0 - np.sum(F * G) ** 2 / (gg * norm_f**2) if gg > 0 else 1.0

        u0 = np.log(e0)
        r = optimize.minimize_scalar(obj, bounds=(u0 - 12.0, u0 + 12.0), method="bounded",
                                     options=dict(xatol=1e-10))
        e_r = float(np.exp(r.x))
        G = g_hat(e_r)
        log_q = float(np.log(np.sum(F * G) / np.sum(G * G)))
    e_r = float(min(max(e_r, 0.0), E_MAX))
    G = g_hat(e_r)
    l2_rel = float(np.sqrt(np.sum((F - np.exp(log_q) * G) ** 2)) / norm_f)
    log_p = log_m + log_q
    p = float(np.exp(log_p))
    integ_exact = product_integral_exact(e1, e2, theta)
    integ_fit = float(TWO_PI * p / (e_r + 1.0))
    return ProductFit(e1, e2, theta, t, e_r, float(log_p), p, integ_exact, integ_fit, l2_rel, False, solver)


def _slerp_axis(a1, a2, t):
    """Unit vector at angle t from a1 towards a2 on their great circle."""
    c = float(np.clip(a1 @ a2, -1.0, 1.0))
    perp = a2 - c * a1
    n = np.linalg.norm(perp)
    if n < 1e-15:  # parallel or antiparallel: any perpendicular
        perp = np.cross(a1, [1.0, 0.0, 0.0] if abs(a1[0]) < 0.9 else [0.0, 1.0, 0.0])
        n = np.linalg.norm(perp)
    perp = perp / n
    return np.cos(t) * a1 + np.sin(t) * perp


def lobe_product(axis1, e1, s1, axis2, e2, s2, *, method: str = "lm"):
    """Product of two cosine lobes as one lobe (Eq. 16).

    Parameters
    ----------
    axis1, axis2 : array_like, shape (3,)
        Lobe axes (normalised here).
    e1, e2 : float
        Exponents in [0, :data:`E_MAX`].
    s1, s2 : float
        Scales.
    method : {"lm", "varpro"}
        As :func:`fit_product`.

    Returns
    -------
    axis_r : ndarray, shape (3,)
    e_r : float
    s_r : float
        ``s1 s2 p_r``; identical axes give ``e1+e2`` and ``s1·s2`` exactly, antiparallel axes ``s_r = 0``.

    Raises
    ------
    IBLError
        Zero axes, invalid exponents or scales.

    Examples
    --------
    >>> from ibl_ref.lobes.meunier2009 import lobe_product
    >>> axis, e, s = lobe_product([0, 0, 1], 10.0, 2.0, [0, 0, 1], 20.0, 3.0)
    >>> axis.tolist(), e, s
    ([0.0, 0.0, 1.0], 30.0, 6.0)
    """
    a1 = _check_axis(axis1, "axis1")
    a2 = _check_axis(axis2, "axis2")
    s1 = float(_check_scale(s1, "s1"))
    s2 = float(_check_scale(s2, "s2"))
    c = float(np.clip(a1 @ a2, -1.0, 1.0))
    theta = float(np.arctan2(np.linalg.norm(np.cross(a1, a2)), c))
    if theta < 1e-12:
        e1c = float(check_exponent(e1, "e1"))
        e2c = float(check_exponent(e2, "e2"))
        return a1.copy(), e1c + e2c, s1 * s2
    fit = fit_product(e1, e2, theta, method=method)
    return _slerp_axis(a1, a2, fit.t), fit.e_r, s1 * s2 * fit.p


class ProductTable:
    """The paper's product table (Sec. 4.1): fitted ``(t/θ, e_r, log p_r)`` on a grid of (e1, e2, θ), read back by
    trilinear interpolation (linear in e1, e2 and θ, as the paper's "table fetching and linear interpolations").

    Parameters
    ----------
    exponents : 1-D array
        Sorted exponent nodes used for both e1 and e2 (e.g. :func:`paper_exponent_samples`).
    thetas : 1-D array
        Sorted angle nodes in [0, π].
    interp_p : {"log", "linear"}
        Interpolate ``log p_r`` (our default: p_r varies exponentially with θ for large exponents) or ``p_r``.
    method : str
        Passed to :func:`fit_product`.

    Products with supports that do not overlap have ``log p = −inf``; they are stored as −745 (exp → 0).
    """

    def __init__(self, exponents, thetas, *, interp_p: str = "log", method: str = "lm"):
        from scipy.interpolate import RegularGridInterpolator

        if interp_p not in ("log", "linear"):
            raise IBLError(f"interp_p must be 'log' or 'linear', got {interp_p!r}")
        self.exponents = np.asarray(check_exponent(exponents, "exponents"), dtype=np.float64)
        self.thetas = np.asarray(thetas, dtype=np.float64)
        self.interp_p = interp_p
        ne, nt = len(self.exponents), len(self.thetas)
        frac = np.zeros((ne, ne, nt))
        er = np.zeros((ne, ne, nt))
        lp = np.zeros((ne, ne, nt))
        for i in range(ne):
            for j in range(i, ne):
                for k, th in enumerate(self.thetas):
                    f = fit_product(self.exponents[i], self.exponents[j], th, method=method)
                    fr = f.t / th if th > 0 else 0.5
                    for a, b, fr_ab in ((i, j, fr), (j, i, 1.0 - fr)):
                        frac[a, b, k] = fr_ab
                        er[a, b, k] = f.e_r
                        lp[a, b, k] = max(f.log_p, -745.0)
        grid = (self.exponents, self.exponents, self.thetas)
        self._frac = RegularGridInterpolator(grid, frac)
        self._er = RegularGridInterpolator(grid, er)
        pv = lp if interp_p == "log" else np.exp(lp)
        self._p = RegularGridInterpolator(grid, pv)

    def __call__(self, e1, e2, theta):
        """Interpolated ``(t, e_r, p_r)`` for arrays of (e1, e2, θ) inside the table range (else IBLError)."""
        pts = np.stack(np.broadcast_arrays(np.asarray(e1, float), np.asarray(e2, float), np.asarray(theta, float)),
                       axis=-1)
        try:
            frac, er, pv = self._frac(pts), self._er(pts), self._p(pts)
        except ValueError as exc:
            raise IBLError(f"ProductTable: point outside the table range: {exc}") from exc
        shp = pts.shape[:-1]
        frac, er, pv = (np.reshape(x, shp) for x in (frac, er, pv))
        p = np.exp(pv) if self.interp_p == "log" else np.maximum(pv, 0.0)
        return frac * pts[..., 2], er, p


# ------------------------------------------------------------------------------- spherical cap ↔ lobe
def _one_minus_cos(alpha):
    return 2.0 * np.sin(alpha / 2.0) ** 2


def cap_fit_error(e, alpha) -> np.ndarray:
    """``∫_S² (f_cap − max(a·v,0)^e)² dω`` (Eq. 32–34) in closed form.

    With μ = cos β and m = cos α: for α ≤ π/2,
    ``2π[(1−m) − 2(1−m^{e+1})/(e+1) + 1/(2e+1)]``; for α > π/2 the cross term is ``1/(e+1)``.

    Parameters
    ----------
    e : float or array_like
        Lobe exponents.
    alpha : float or array_like
        Cap half-angles (rad).

    Returns
    -------
    ndarray, float64
    """
    e = np.asarray(e, dtype=np.float64)
    alpha = np.asarray(alpha, dtype=np.float64)
    m = np.cos(alpha)
    one_m = _one_minus_cos(alpha)
    m_pos = np.clip(m, 0.0, 1.0)
    with np.errstate(divide="ignore"):
        m_pow = np.where(m_pos > 0, np.exp((e + 1) * np.log(np.where(m_pos > 0, m_pos, 1.0))), 0.0)
    cross = (1.0 - m_pow) / (e + 1.0)
    return TWO_PI * (one_m - 2.0 * cross + 1.0 / (2.0 * e + 1.0))


def _cap_dE(e, alpha):
    """d/de of :func:`cap_fit_error` / 2π (for α < π/2)."""
    ln_m = np.log1p(-_one_minus_cos(alpha))
    m_pow = np.exp((e + 1) * ln_m)
    return 2 * (1 - m_pow) / (e + 1) ** 2 + 2 * m_pow * ln_m / (e + 1) - 2 / (2 * e + 1) ** 2


def cap_exponent(alpha) -> np.ndarray:
    """Exponent ``e_cap`` of the unit-scale lobe closest in L2 to the cap of half-angle α (Eq. 32–34).

    Solved exactly (root of the derivative of the closed-form error, Brent's method in log e).  Non-increasing
    in α; ``e_cap = 0`` for α ≥ π/2 (no lobe of this family is wider than a hemisphere); for small α,
    ``e_cap → 2y*/α²`` with ``(1+y*)e^{−y*} = 3/4`` (y* ≈ 0.9613, Gaussian limit).

    Parameters
    ----------
    alpha : float or array_like
        Cap half-angles in (0, π] (rad).

    Returns
    -------
    float or ndarray

    Raises
    ------
    IBLError
        An angle outside (0, π].

    Examples
    --------
    A small cap approaches the Gaussian limit α²·e_cap → 2y* ≈ 1.9226:

    >>> from ibl_ref.lobes.meunier2009 import cap_exponent
    >>> round(0.01**2 * cap_exponent(0.01), 4), cap_exponent(2.0)
    (1.9225, 0.0)
    """
    alpha = np.asarray(alpha, dtype=np.float64)
    if not np.all(np.isfinite(alpha)) or np.any(alpha <= 0) or np.any(alpha > np.pi):
        raise IBLError("cap half-angle alpha must be in (0, π] rad")
    out = np.zeros(alpha.shape)
    flat = out.reshape(-1)
    for i, a in enumerate(alpha.reshape(-1)):
        if a >= np.pi / 2:
            flat[i] = 0.0
            continue
        lo, hi = -40.0, np.log(50.0 / a**2)
        glo = _cap_dE(np.exp(lo), a)
        if glo >= 0:
            flat[i] = 0.0
            continue
        flat[i] = np.exp(optimize.brentq(lambda u: _cap_dE(np.exp(u), a), lo, hi, xtol=1e-14, rtol=1e-14))
    return out if out.ndim else float(out)


def cap_angle(e) -> np.ndarray:
    """Inverse of :func:`cap_exponent`: the cap half-angle α (rad) whose best-fit lobe has exponent ``e``.

    Parameters
    ----------
    e : float or array_like
        Exponents in [0, :data:`E_MAX`].

    Returns
    -------
    float or ndarray
        Radians; ``e = 0`` → π/2; monotone decreasing in e.
    """
    e = check_exponent(e)
    out = np.zeros(e.shape)
    flat = out.reshape(-1)
    for i, ei in enumerate(e.reshape(-1)):
        if ei == 0:
            flat[i] = np.pi / 2
            continue
        # bracket: cap_exponent(α) ≈ 1.92/α² for small α; search α in (tiny, π/2)
        f = lambda a: np.log(cap_exponent(a) + 1e-300) - np.log(ei)  # noqa: E731
        lo = min(1e-6, 0.1 / np.sqrt(ei))
        flat[i] = optimize.brentq(f, lo, np.pi / 2 - 1e-12, xtol=1e-14, rtol=1e-13)
    return out if out.ndim else float(out)


class CapTable:
    """The paper's cap-exponent table: ``n`` values, linear interpolation (Sec. 5.2).

    The paper does not say how the 1000 entries are spaced; we use α linearly spaced in
    ``[α_max/n, α_max]`` with ``α_max = π/2`` (``mode="alpha"``, paper-like).  ``mode="alpha2e"`` tabulates
    ``α²·e_cap(α)`` instead (nearly constant, ≈ 1.92 → 0 at π/2) — our improvement, far smaller error.
    Angles below the first node raise.
    """

    def __init__(self, n: int = 1000, mode: str = "alpha"):
        if mode not in ("alpha", "alpha2e"):
            raise IBLError(f"mode must be 'alpha' or 'alpha2e', got {mode!r}")
        self.mode = mode
        self.alpha = np.linspace(np.pi / 2 / n, np.pi / 2, n)
        e = cap_exponent(self.alpha)
        self.values = e if mode == "alpha" else e * self.alpha**2

    def __call__(self, alpha) -> np.ndarray:
        alpha = np.asarray(alpha, dtype=np.float64)
        if np.any(alpha < self.alpha[0]) or np.any(alpha > np.pi) or not np.all(np.isfinite(alpha)):
            raise IBLError(f"alpha outside the table range [{self.alpha[0]:.4g}, π]")
        v = np.interp(np.minimum(alpha, np.pi / 2), self.alpha, self.values)
        return v if self.mode == "alpha" else v / np.minimum(alpha, np.pi / 2) ** 2


@dataclass(frozen=True)
class RegionLobe:
    """Equivalent cosine lobe of a region of solid angle Ω (a cap of the same solid angle).

    ``alpha``: cap half-angle (rad); ``exponent``: :func:`cap_exponent` (Eq. 32–34, unit peak);
    ``scale_energy``: scale making the lobe's integral equal Ω, ``Ω(e+1)/(2π)`` (so a region of radiance L
    becomes the lobe ``L·scale_energy·max(a·v,0)^e`` carrying the region's ``L·Ω``).
    """

    solid_angle: np.ndarray
    alpha: np.ndarray
    exponent: np.ndarray
    scale_energy: np.ndarray


def region_equivalent_lobe(solid_angle) -> RegionLobe:
    """Equivalent lobe of (median-cut) regions: cap half-angle from ``Ω = 2π(1 − cos α)``, then Eq. 32–34.

    Parameters
    ----------
    solid_angle : float or array
        Ω in sr, ``0 < Ω ≤ 4π``.

    Returns
    -------
    RegionLobe

    Raises
    ------
    IBLError
        Ω outside (0, 4π].

    Examples
    --------
    One of 24 equal regions: the energy-scaled lobe carries the region's solid angle exactly:

    >>> import numpy as np
    >>> from ibl_ref.lobes.meunier2009 import lobe_integral, region_equivalent_lobe
    >>> lobe = region_equivalent_lobe(4 * np.pi / 24)
    >>> round(float(lobe.exponent), 3), float(lobe_integral(lobe.exponent, lobe.scale_energy) / (4 * np.pi / 24))
    (10.757, 1.0)
    """
    om = np.asarray(solid_angle, dtype=np.float64)
    if not np.all(np.isfinite(om)) or np.any(om <= 0) or np.any(om > 4 * np.pi * (1 + 1e-12)):
        raise IBLError("solid_angle must be in (0, 4π] sr")
    alpha = 2.0 * np.arcsin(np.sqrt(np.clip(om / (4 * np.pi), 0.0, 1.0)))  # stable form of arccos(1−Ω/2π)
    e = np.asarray(cap_exponent(alpha))
    return RegionLobe(om, alpha, e, om * (e + 1.0) / TWO_PI)
