"""Analytic isotropic BRDFs (vectorised) and their directional albedo by quadrature.

Every BRDF is a function ``f(wi, wo, n=(0,0,1), **params) -> (...)`` of unit vectors (``(..., 3)`` arrays that
broadcast against each other; ``n`` may also be per-sample).  Only dot products are used, so no tangent frame is
needed (all models here are isotropic).  Every BRDF is 0 when ``n·wi ≤ 0`` or ``n·wo ≤ 0`` (the reflection
hemisphere).  ``kd`` is the Lambertian albedo (``kd/π`` term) everywhere.

Models and their exact definitions (``cos θi = n·wi``, ``cos θo = n·wo``, ``r = 2(n·wo)n − wo`` the mirror
direction of ``wo``, ``cos α = max(r·wi, 0)``, ``h = (wi+wo)/|wi+wo|``, ``cos θh = n·h``):

* ``lambert``:            ``kd/π``.
* ``phong`` (physically normalised, "modified Phong", Lewis 1994):
  ``kd/π + ks·(s+2)/(2π)·cosˢα``.  At normal view its specular albedo is exactly ``ks``; the lobe is radially
  symmetric about ``r`` (this is the BRDF a single Kautz–McCool lobe represents exactly).
* ``phong_classic`` (Phong 1975 intensity model written as a BRDF, normalised as in Kán 2015 Eq. 2):
  ``kd/π + ks·(s+1)/(2π)·cosˢα / cos θi`` — the reflected lobe *times the cosine* is the pure cosine lobe about r
  (not reciprocal; energy can exceed ks near grazing).
* ``blinn_phong``: ``kd/π + ks·(s+8)/(8π)·cosˢθh`` (the usual (s+8)/(8π) approximate normalisation).
* ``ward`` (Ward 1992, isotropic): ``kd/π + ks·exp(−tan²θh/α²) / (4π α² √(cos θi cos θo))``.
* ``cook_torrance`` (Cook & Torrance 1982 microfacet form): ``kd/π + D(θh)·G·F / (4 cos θi cos θo)`` with

  - ``distribution="ggx"``: ``D = α² / (π (cos²θh (α²−1) + 1)²)``; Smith ``G1(w) = 2 cos θ / (cos θ +
    √(α² + (1−α²) cos²θ))``;
  - ``distribution="beckmann"``: ``D = exp(−tan²θh/α²) / (π α² cos⁴θh)``; Smith ``G1 = 1/(1+Λ)``,
    ``Λ(a) = (erf(a) − 1)/2 + exp(−a²)/(2a√π)``, ``a = 1/(α tan θ)`` (exact, not the rational approximation);
  - Smith masking–shadowing, ``smith="separable"`` (default of ``cook_torrance``; what Mitsuba 3's microfacet
    plugins use): ``G = G1(wi)·G1(wo)``; ``smith="height_correlated"`` (Heitz 2014, "Understanding the
    Masking-Shadowing Function in Microfacet-Based BRDFs", Eq. 99; what Filament and UE4 ship):
    ``G = 1 / (1 + Λ(wi) + Λ(wo))`` with ``G1 = 1/(1 + Λ)``, i.e. ``G = 1 / (1/G1(wi) + 1/G1(wo) − 1)``;
  - Schlick Fresnel ``F = F0 + (1−F0)(1 − h·wi)⁵``.
* ``ggx`` (Trowbridge–Reitz microfacet material of the method comparisons): ``cook_torrance`` with
  ``distribution="ggx"``, ``α = roughness²`` (:func:`ibl_ref.conventions.ggx_alpha`, Karis 2013), Schlick F0 and
  height-correlated Smith by default, plus the Lambertian ``kd/π``.  F0 = 1 makes F ≡ 1 (a conductor with
  Mitsuba's ``material='none'``).

:func:`albedo` integrates ``∫ f(wi, wo) cos θi dωi`` over the hemisphere with a tensor Gauss–Legendre rule in
(θi, φi) graded around the mirror direction.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import special

from ..conventions import GGX_ROUGHNESS_MIN, ggx_alpha
from ..errors import IBLError

__all__ = ["lambert", "phong", "phong_classic", "blinn_phong", "ward", "cook_torrance", "ggx", "ndf", "smith_g1", "smith_g2",
           "SMITH_FORMS", "get_brdf",
           "BRDF_NAMES", "albedo", "hemisphere_rule", "direction_from_angles", "view_direction"]

_Z = np.array([0.0, 0.0, 1.0])


def _dot(a, b):
    return np.sum(a * b, axis=-1)


def _prep(wi, wo, n):
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    n = _Z if n is None else np.asarray(n, dtype=np.float64)
    if wi.shape[-1:] != (3,) or wo.shape[-1:] != (3,) or n.shape[-1:] != (3,):
        raise IBLError("wi, wo and n must be (..., 3) arrays of directions")
    ci = _dot(n, wi)
    co = _dot(n, wo)
    valid = (ci > 0) & (co > 0)
    return wi, wo, n, ci, co, valid


def _pos(name, v, allow_zero=True):
    v = float(v)
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise IBLError(f"{name} must be a finite {'non-negative' if allow_zero else 'positive'} number, got {v!r}")
    return v


ALPHA_MIN = GGX_ROUGHNESS_MIN ** 2
"""Smallest lobe width α of Ward and Cook–Torrance, 2^-20: the GGX floor (roughness 2^-10) squared; below it
float64 no longer resolves the peak (α² under 2^-40).  The largest is 1, the roughest lobe of the engines'
parametrisation (roughness 1)."""


def _alpha(v):
    v = float(v)
    if not np.isfinite(v) or not ALPHA_MIN <= v <= 1.0:
        raise IBLError(f"alpha must be a finite number in [2^-20, 1] (brdfs.ALPHA_MIN, the GGX roughness floor squared), "
                       f"got {v!r}")
    return v


def lambert(wi, wo, n=None, *, kd=1.0):
    """Lambertian BRDF ``kd/π``."""
    kd = _pos("kd", kd)
    *_, valid = _prep(wi, wo, n)
    return np.where(valid, kd / np.pi, 0.0)


def _mirror_cos(wi, wo, n, co):
    r = 2.0 * co[..., None] * n - wo
    return np.maximum(_dot(r, wi), 0.0)


def _powc(c, s):
    with np.errstate(divide="ignore"):
        return np.where(c > 0, np.exp(s * np.log(np.where(c > 0, c, 1.0))), 0.0)


def phong(wi, wo, n=None, *, ks=1.0, s=10.0, kd=0.0):
    """Physically normalised (modified) Phong: ``kd/π + ks (s+2)/(2π) cosˢα``."""
    ks, s, kd = _pos("ks", ks), _pos("s", s), _pos("kd", kd)
    wi, wo, n, ci, co, valid = _prep(wi, wo, n)
    val = kd / np.pi + ks * (s + 2) / (2 * np.pi) * _powc(_mirror_cos(wi, wo, n, co), s)
    return np.where(valid, val, 0.0)


def phong_classic(wi, wo, n=None, *, ks=1.0, s=10.0, kd=0.0):
    """Classic Phong as a BRDF: ``kd/π + ks (s+1)/(2π) cosˢα / cos θi`` (Kán 2015 Eq. 2 normalisation)."""
    ks, s, kd = _pos("ks", ks), _pos("s", s), _pos("kd", kd)
    wi, wo, n, ci, co, valid = _prep(wi, wo, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        spec = ks * (s + 1) / (2 * np.pi) * _powc(_mirror_cos(wi, wo, n, co), s) / np.where(valid, ci, 1.0)
    return np.where(valid, kd / np.pi + spec, 0.0)


def _cos_h(wi, wo, n):
    h = wi + wo
    hn = np.linalg.norm(h, axis=-1, keepdims=True)
    h = h / np.where(hn > 0, hn, 1.0)
    return h, _dot(n, h)


def blinn_phong(wi, wo, n=None, *, ks=1.0, s=10.0, kd=0.0):
    """Blinn–Phong ``kd/π + ks (s+8)/(8π) cosˢθh``."""
    ks, s, kd = _pos("ks", ks), _pos("s", s), _pos("kd", kd)
    wi, wo, n, ci, co, valid = _prep(wi, wo, n)
    _, ch = _cos_h(wi, wo, n)
    return np.where(valid, kd / np.pi + ks * (s + 8) / (8 * np.pi) * _powc(ch, s), 0.0)


def ward(wi, wo, n=None, *, ks=0.8, alpha=0.04, kd=0.0):
    """Isotropic Ward (1992): ``kd/π + ks exp(−tan²θh/α²) / (4π α² √(cos θi cos θo))``."""
    ks, kd = _pos("ks", ks), _pos("kd", kd)
    alpha = _alpha(alpha)
    wi, wo, n, ci, co, valid = _prep(wi, wo, n)
    _, ch = _cos_h(wi, wo, n)
    ch = np.where(valid & (ch > 0), ch, 1.0)
    tan2 = (1.0 - ch * ch) / (ch * ch)
    denom = 4 * np.pi * alpha**2 * np.sqrt(np.where(valid, ci * co, 1.0))
    return np.where(valid, kd / np.pi + ks * np.exp(-tan2 / alpha**2) / denom, 0.0)


def _g1_ggx(c, a):
    return 2 * c / (c + np.sqrt(a * a + (1 - a * a) * c * c))


def _g1_beckmann(c, a):
    c = np.clip(c, 1e-300, 1.0)
    tan = np.sqrt(np.maximum(1 - c * c, 0.0)) / c
    with np.errstate(divide="ignore"):
        x = np.where(tan > 0, 1.0 / (a * np.where(tan > 0, tan, 1.0)), np.inf)
    xs = np.where(np.isfinite(x), x, 1.0)
    lam = np.where(np.isfinite(x), (special.erf(xs) - 1) / 2 + np.exp(-xs * xs) / (2 * xs * np.sqrt(np.pi)), 0.0)
    return 1.0 / (1.0 + lam)


def ndf(cos_h, alpha, distribution="ggx"):
    """Microfacet normal distribution D(θh) of :func:`cook_torrance` (normalised: ∫ D cos θh dωh = 1)."""
    ch = np.asarray(cos_h, dtype=np.float64)
    a2 = float(alpha) ** 2
    if distribution == "ggx":
        return np.where(ch > 0, a2 / (np.pi * (ch * ch * (a2 - 1) + 1) ** 2), 0.0)
    if distribution == "beckmann":
        c = np.where(ch > 0, ch, 1.0)
        return np.where(ch > 0, np.exp(-(1 - c * c) / (c * c) / a2) / (np.pi * a2 * c**4), 0.0)
    raise IBLError(f"distribution must be 'ggx' or 'beckmann', got {distribution!r}")


def smith_g1(cos_theta, alpha, distribution="ggx"):
    """Smith masking G1 of :func:`cook_torrance` for a direction with ``cos θ`` to the normal."""
    c = np.asarray(cos_theta, dtype=np.float64)
    if distribution == "ggx":
        return _g1_ggx(c, float(alpha))
    if distribution == "beckmann":
        return _g1_beckmann(c, float(alpha))
    raise IBLError(f"distribution must be 'ggx' or 'beckmann', got {distribution!r}")


#: Smith masking–shadowing forms of :func:`smith_g2` (module doc)
SMITH_FORMS = ("separable", "height_correlated")


def smith_g2(cos_i, cos_o, alpha, distribution="ggx", smith="height_correlated"):
    """Smith masking–shadowing ``G(wi, wo)`` from ``cos θi``, ``cos θo`` (module doc: both forms)."""
    if smith not in SMITH_FORMS:
        raise IBLError(f"smith must be one of {', '.join(SMITH_FORMS)}, got {smith!r}")
    g1_i = smith_g1(cos_i, alpha, distribution)
    g1_o = smith_g1(cos_o, alpha, distribution)
    if smith == "separable":
        return g1_i * g1_o
    with np.errstate(divide="ignore"):
        return 1.0 / (1.0 / g1_i + 1.0 / g1_o - 1.0)  # Heitz 2014 Eq. 99: 1/(1 + Λi + Λo), 1/G1 = 1 + Λ


def cook_torrance(wi, wo, n=None, *, alpha=0.2, f0=0.04, kd=0.0, distribution="ggx", smith="separable"):
    """Cook–Torrance microfacet BRDF with GGX or Beckmann D, Smith G (separable or height-correlated), Schlick F
    (module doc)."""
    alpha = _alpha(alpha)
    kd = _pos("kd", kd)
    f0 = _pos("f0", f0)
    if f0 > 1:
        raise IBLError(f"f0 must be in [0, 1], got {f0!r}")
    if distribution not in ("ggx", "beckmann"):
        raise IBLError(f"distribution must be 'ggx' or 'beckmann', got {distribution!r}")
    if smith not in SMITH_FORMS:
        raise IBLError(f"smith must be one of {', '.join(SMITH_FORMS)}, got {smith!r}")
    wi, wo, n, ci, co, valid = _prep(wi, wo, n)
    h, ch = _cos_h(wi, wo, n)
    ch = np.where(valid & (ch > 0), ch, 1.0)
    cis = np.where(valid, ci, 1.0)
    cos_ = np.where(valid, co, 1.0)
    D = ndf(ch, alpha, distribution)
    G = smith_g2(cis, cos_, alpha, distribution, smith)
    F = f0 + (1 - f0) * (1 - np.clip(_dot(h, wi), 0.0, 1.0)) ** 5
    return np.where(valid, kd / np.pi + D * G * F / (4 * cis * cos_), 0.0)


def ggx(wi, wo, n=None, *, roughness=0.5, f0=0.04, kd=0.0, smith="height_correlated"):
    """GGX material: ``kd/π + D·G·F / (4 cos θi cos θo)`` with ``α = roughness²`` (module doc)."""
    return cook_torrance(wi, wo, n, alpha=ggx_alpha(roughness), f0=f0, kd=kd, distribution="ggx", smith=smith)


_REGISTRY = {
    "lambert": lambert,
    "phong": phong,
    "phong_classic": phong_classic,
    "blinn_phong": blinn_phong,
    "ward": ward,
    "cook_torrance": cook_torrance,
    "ggx": ggx,
}
BRDF_NAMES = tuple(_REGISTRY)


def get_brdf(name: str, **params):
    """A BRDF ``f(wi, wo, n=None)`` with its parameters bound (``functools.partial``), e.g.
    ``get_brdf("ward", ks=0.8, alpha=0.04)``; ``.name`` and ``.params`` describe it."""
    if name not in _REGISTRY:
        raise IBLError(f"unknown BRDF {name!r}; available: {', '.join(BRDF_NAMES)}")
    f = functools.partial(_REGISTRY[name], **params)
    f.name = name  # type: ignore[attr-defined]
    f.params = dict(params)  # type: ignore[attr-defined]
    # validate parameters once
    f(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0]))
    return f


def direction_from_angles(theta, phi):
    """Unit vector with polar angle θ from +z and azimuth φ from +x."""
    theta, phi = np.broadcast_arrays(np.asarray(theta, dtype=np.float64), np.asarray(phi, dtype=np.float64))
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=-1)


def view_direction(theta_o):
    """``wo`` at elevation θo (from the normal +z) in the x–z plane at azimuth π, so the mirror direction
    ``r`` has azimuth 0: ``r = (sin θo, 0, cos θo)``."""
    t = float(theta_o)
    if not (0.0 <= t < np.pi / 2):
        raise IBLError(f"view angle theta_o must be in [0, π/2), got {t!r}")
    return np.array([-np.sin(t), 0.0, np.cos(t)])


_GX, _GW = np.polynomial.legendre.leggauss(8)


def _gl(breaks):
    b = np.unique(np.asarray(breaks, dtype=np.float64))
    a0, a1 = b[:-1], b[1:]
    half, mid = 0.5 * (a1 - a0), 0.5 * (a1 + a0)
    return (mid[:, None] + half[:, None] * _GX).ravel(), (half[:, None] * _GW).ravel()


def _graded(center, lo, hi, width):
    d = width * 2.0 ** np.arange(-3, 30)
    p = np.concatenate([[lo, hi, center], center - d, center + d, lo + (hi - lo) * np.linspace(0, 1, 9)])
    return p[(p >= lo) & (p <= hi)]


def hemisphere_rule(theta_o, width: float = 0.02):
    """Tensor Gauss–Legendre rule over the upper hemisphere, graded around the mirror direction of θo.

    Returns ``(wi (M,3), weights (M,))`` with weights = solid angle (``sin θ dθ dφ``), φ ∈ [−π, π].
    ``width`` (rad) is the smallest feature to resolve (panels double in size away from the mirror direction).
    """
    th, wth = _gl(_graded(float(theta_o), 0.0, np.pi / 2, width))
    ph, wph = _gl(_graded(0.0, -np.pi, np.pi, width))
    T, P = np.meshgrid(th, ph, indexing="ij")
    W = (wth * np.sin(th))[:, None] * wph[None, :]
    return direction_from_angles(T, P).reshape(-1, 3), W.reshape(-1)


def albedo(brdf, theta_o, width: float = 0.02) -> np.ndarray:
    """Directional albedo ``a(θo) = ∫_{H²} f(wi, wo) cos θi dωi`` (n = +z) for each θo (quadrature,
    :func:`hemisphere_rule`)."""
    th = np.atleast_1d(np.asarray(theta_o, dtype=np.float64))
    out = np.empty(th.shape)
    for i, t in enumerate(th):
        wi, w = hemisphere_rule(t, width)
        out[i] = np.sum(brdf(wi, view_direction(t)) * wi[:, 2] * w)
    return out if np.ndim(theta_o) else float(out[0])
