"""Knuth et al. (2014) Sec. 5 "Filter Quality": lobe-volume analysis of the filter pyramid (Fig. 4, Fig. 5).

The paper's procedure: a black environment map with one white texel is filtered into the pyramid; the
response read back through the glossiness lookup (trilinear: bilinear in two neighbouring levels +
linear blend) is a lobe around the white texel's direction d0.  For a Phong exponent s the target lobe
is t(ω) = max(d0·ω, 0)^s (Eq. 4 for a delta light).  "To compare the generated lobes we fit their
volumes by finding the corresponding MIP map level for a given glossiness.  The remaining differences in
the volumes are then used to compute the relative error" (in percent of the target lobe's volume).

The text leaves three things open; each is an explicit, named option here:

``volume`` — what "lobe volume" means (both lobes peak-normalised to max 1 first, as in the radial
plots of Fig. 4)::

    ``"integral"``  V = ∫ f dω  (target: 2π/(s+1))
    ``"radial"``    V = ⅓ ∫ f³ dω, the volume enclosed by the 3D radial plot r(ω) = f(ω)
                    (target: 2π/(3(3s+1)))

``error`` — what "remaining differences in the volumes" means::

    ``"symdiff"``   volume of the symmetric difference of the two solids, relative to the target
                    volume: ∫|f − t| dω / V_t ("integral") or ⅓∫|f³ − t³| dω / V_t ("radial").
                    This is the reading that gives the non-zero, level-dependent curves of Fig. 5.
    ``"voldiff"``   |V(f) − V_t| / V_t: zero wherever a level matching the volume exists, non-zero
                    only where the fit is clipped (the lobe is wider than the coarsest level or
                    narrower than level 0 can represent).

``centring`` — where the target lobe points::

    ``"texel"``     the white texel's direction d0 (the error then includes the *position* error of the
                    pyramid: a level-ℓ texel's centre is up to half a level-ℓ texel away from d0, e.g.
                    ~14° at 4×4 faces);
    ``"centroid"``  the response lobe's own axis, normalize(∫ f ω dω) (shape error only, as when
                    radial plots are overlaid by their axes, Fig. 4).

``position`` — where the white texel sits: ``"centre"`` (face +Z, texel (N/2, N/2)), ``"edge"``
(face +Z, texel (N/2, N−1), on the seam with the neighbouring face), ``"corner"`` (face +Z, texel
(0, 0), at a cube corner where three faces meet).

Quadrature: the response and the target are sampled at the texel centres of a cube grid of face
size ``sample_size`` (default: the pyramid's level-0 size N) and integrated with the exact texel solid
angles (:func:`ibl_ref.environment.envmap.cube_solid_angles`).  The target volume V_t is the analytic one; the
quadrature error of the sampled target (which grows once the lobe gets narrower than a texel: the
resolution limit of Sec. 5) is reported as ``target_quad_rel_err``.
"""

from __future__ import annotations

import functools

import numpy as np

from ..environment.envmap import cube_solid_angles, texel_directions
from ..errors import IBLError
from .pyramid import build_pyramid

__all__ = [
    "VOLUME_DEFS",
    "CENTRINGS",
    "ERROR_DEFS",
    "POSITIONS",
    "lit_texel",
    "target_lobe",
    "target_volume",
    "lobe_volume",
    "s_texel_limit",
    "s_grid",
    "LobeResponse",
    "lobe_response",
    "analyse",
]

VOLUME_DEFS = ("integral", "radial")
CENTRINGS = ("texel", "centroid")
ERROR_DEFS = ("symdiff", "voldiff")
POSITIONS = ("centre", "edge", "corner")


def _check(name, value, options):
    if value not in options:
        raise IBLError(f"unknown {name} {value!r}; choose one of {', '.join(options)}")
    return value


def lit_texel(n: int, position: str = "centre") -> tuple[int, int, int]:
    """(face, row, col) of the white texel for a position name (module docstring)."""
    _check("lit-texel position", position, POSITIONS)
    face = 4  # +Z
    if position == "centre":
        return face, n // 2, n // 2
    if position == "edge":
        return face, n // 2, n - 1
    return face, 0, 0


def target_lobe(cos_theta, s) -> np.ndarray:
    """Peak-normalised target lobe max(cos θ, 0)^s (Eq. 4 integrand); s = inf gives the delta's 0/1."""
    c = np.clip(np.asarray(cos_theta, dtype=np.float64), 0.0, 1.0)
    if np.isinf(s):
        return (c >= 1.0).astype(np.float64)
    return c**s


def target_volume(s, volume: str = "integral"):
    """Analytic volume of the clamped cosˢ lobe: 2π/(s+1) (integral) or 2π/(3(3s+1)) (radial)."""
    _check("volume definition", volume, VOLUME_DEFS)
    s = np.asarray(s, dtype=np.float64)
    if volume == "integral":
        return 2.0 * np.pi / (s + 1.0)
    return 2.0 * np.pi / (3.0 * (3.0 * s + 1.0))


def _wsum(w, x) -> float:
    """Σ w·x by NumPy's pairwise summation, not BLAS: a BLAS dot splits its sum by the number of BLAS threads, so its
    last digits would depend on where the job runs (a worker process holds BLAS at one thread)."""
    return float(np.sum(np.asarray(w) * np.asarray(x)))


def _dir_dot(dirs, d):
    """dirs · d over the last axis (three products, the same rounding in every process)."""
    return dirs[..., 0] * d[0] + dirs[..., 1] * d[1] + dirs[..., 2] * d[2]


def lobe_volume(f_hat, omega, volume: str = "integral") -> float:
    """Volume of a peak-normalised lobe sampled with solid angles ``omega`` (same shape)."""
    _check("volume definition", volume, VOLUME_DEFS)
    if volume == "integral":
        return _wsum(f_hat, omega)
    return _wsum(f_hat**3, omega) / 3.0


def s_texel_limit(n: int) -> float:
    """Phong exponent whose lobe (full width at half maximum) equals the centre texel angle 2·atan(1/n).

    cos^s θ_h = ½ with θ_h = atan(1/n)  ⇒  s = ln 2 / (−ln cos atan(1/n)) = 2 ln 2 / ln(1 + 1/n²) ≈ 1.39 n².
    """
    return float(2.0 * np.log(2.0) / np.log1p(1.0 / n**2))


def s_grid(n: int, count: int = 40, s_max: float | None = None) -> np.ndarray:
    """Log-spaced Phong exponents from 1 to ``s_max`` (default :func:`s_texel_limit`)."""
    s_max = s_texel_limit(n) if s_max is None else s_max
    return np.geomspace(1.0, s_max, count)


class LobeResponse:
    """Response lobes of a pyramid to one white texel, at all integer levels, on a sampling grid.

    Parameters
    ----------
    n : int
        Level-0 face size (power of two).
    kernel, order, seam, shrink :
        Passed to :func:`ibl_ref.knuth2014.pyramid.build_pyramid`.
    position : {"centre", "edge", "corner"}
    sample_size : int, optional
        Face size of the sampling grid (default n).

    Attributes
    ----------
    pyramid : Pyramid of the one-texel map (1 channel, float64)
    d0 : (3,) direction of the white texel
    dirs : (P, 3), omega : (P,), cos_theta : (P,)
    R : (n_levels, P) bilinear responses of every level at ``dirs``
    """

    def __init__(self, n: int, kernel="sqrtcos", order="shrink_then_filter", seam="neighbour",
                 position="centre", sample_size: int | None = None, shrink: str = "mean"):

        self.n = int(n)
        self.kernel, self.order, self.seam, self.position, self.shrink = kernel, order, seam, position, shrink
        face, row, col = lit_texel(self.n, position)
        cube = np.zeros((6, self.n, self.n, 1))
        cube[face, row, col, 0] = 1.0
        self.pyramid = build_pyramid(cube, kernel=kernel, order=order, seam=seam, dtype=np.float64, shrink=shrink)
        self.d0 = texel_directions(self.n)[face, row, col].copy()
        m = self.n if sample_size is None else int(sample_size)
        self.sample_size = m
        self.dirs = texel_directions(m).reshape(-1, 3)
        self.omega = np.ascontiguousarray(cube_solid_angles(m)).reshape(-1)
        self.cos_theta = _dir_dot(self.dirs, self.d0)
        self.R = np.stack([self.pyramid.sampler(L).bilinear(self.dirs)[:, 0] for L in range(self.pyramid.n_levels)])
        self.max_level = self.pyramid.max_level
        self._curves = {}
        self._moment_cache = {}

    # -- lobe at a continuous level -------------------------------------------------------------
    def at_level(self, ell: float) -> np.ndarray:
        """Unnormalised response at continuous level ``ell`` (linear blend of the two neighbours)."""
        ell = float(np.clip(ell, 0.0, self.max_level))
        L0 = min(int(np.floor(ell)), self.max_level)
        t = ell - L0
        if t == 0.0:
            return self.R[L0]
        return (1.0 - t) * self.R[L0] + t * self.R[L0 + 1]

    def evaluate(self, dirs, ell: float) -> np.ndarray:
        """Unnormalised response at arbitrary directions (..., 3) and continuous level (trilinear)."""
        ell = float(np.clip(ell, 0.0, self.max_level))
        L0 = min(int(np.floor(ell)), self.max_level)
        t = ell - L0
        v = self.pyramid.sampler(L0).bilinear(dirs)[..., 0]
        if t > 0.0:
            v = (1.0 - t) * v + t * self.pyramid.sampler(L0 + 1).bilinear(dirs)[..., 0]
        return v

    def normalised(self, ell: float) -> np.ndarray:
        """Peak-normalised response (max 1)."""
        f = self.at_level(ell)
        return f / f.max()

    def _interval(self, ell: float):
        ell = float(np.clip(ell, 0.0, self.max_level))
        if self.max_level == 0:
            return 0, 0.0
        L0 = min(int(np.floor(ell)), self.max_level - 1)
        return L0, ell - L0

    def _sums(self, L0: int):
        """Per-interval moments Σ Ω a^i b^j (i+j ∈ {1, 3}) and peak candidates (cached)."""
        if L0 not in self._moment_cache:
            a = self.R[L0]
            b = self.R[min(L0 + 1, self.max_level)]
            w = self.omega
            k = min(64, a.size)
            cand = np.union1d(np.argpartition(a, -k)[-k:], np.argpartition(b, -k)[-k:])
            mom = {"a": _wsum(w, a), "b": _wsum(w, b), "aaa": _wsum(w, a**3), "aab": _wsum(w, a * a * b),
                   "abb": _wsum(w, a * b * b), "bbb": _wsum(w, b**3)}
            self._moment_cache[L0] = (mom, a[cand], b[cand])
        return self._moment_cache[L0]

    def volume(self, ell: float, volume: str = "integral") -> float:
        """Volume of the peak-normalised lobe at continuous level ``ell``.

        Fast route: the lobe is (1−t)·a + t·b (a, b the responses of the two levels), so ∫f dω and ∫f³ dω are
        polynomials in t whose coefficients are precomputed moments, and the peak max((1−t)a + tb) is
        taken over the candidates that are in the top 64 of a or of b (the peak is one lobe maximum; the
        test suite checks this route against :meth:`volume_exact`).
        """
        _check("volume definition", volume, VOLUME_DEFS)
        L0, t = self._interval(ell)
        mom, ca, cb = self._sums(L0)
        peak = float(np.max((1.0 - t) * ca + t * cb))
        u = 1.0 - t
        if volume == "integral":
            return (u * mom["a"] + t * mom["b"]) / peak
        cube = u**3 * mom["aaa"] + 3 * u * u * t * mom["aab"] + 3 * u * t * t * mom["abb"] + t**3 * mom["bbb"]
        return cube / (3.0 * peak**3)

    def volume_exact(self, ell: float, volume: str = "integral") -> float:
        """Volume from the full peak-normalised lobe (reference for :meth:`volume`)."""
        return lobe_volume(self.normalised(ell), self.omega, volume)

    def volume_curve(self, volume: str = "integral", per_level: int = 32):
        """Volumes on a grid of continuous levels (cached): returns (ell, V)."""
        key = (volume, per_level)
        if key not in self._curves:
            ell = np.linspace(0.0, self.max_level, self.max_level * per_level + 1)
            self._curves[key] = (ell, np.array([self.volume(e, volume) for e in ell]))
        return self._curves[key]

    def fit_level(self, s: float, volume: str = "integral", per_level: int = 32, iters: int = 40):
        """Continuous level whose lobe volume equals the target's; returns (ell, clipped).

        ``clipped`` is ``"narrow"`` if even level 0 is too wide (V(0) > V_t), ``"wide"`` if the coarsest
        level is too narrow, else ``""``.  Within the bracketing interval (first crossing of the cached
        volume curve) the level is refined by bisection.
        """
        vt = float(target_volume(s, volume))
        ell, V = self.volume_curve(volume, per_level)
        if vt <= V[0]:
            return 0.0, ("narrow" if vt < V[0] else "")
        above = np.nonzero(V >= vt)[0]
        if above.size == 0:
            return float(self.max_level), "wide"
        j = int(above[0])
        lo, hi = ell[j - 1], ell[j]
        for _ in range(iters):
            mid = 0.5 * (lo + hi)
            if self.volume(mid, volume) < vt:
                lo = mid
            else:
                hi = mid
        ell_fit = 0.5 * (lo + hi)
        if abs(self.volume_exact(ell_fit, volume) / vt - 1.0) > 1e-6:  # peak not among the candidates
            lo, hi = ell[j - 1], ell[j]
            for _ in range(iters):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if self.volume_exact(mid, volume) < vt else (lo, mid)
            ell_fit = 0.5 * (lo + hi)
        return ell_fit, ""

    def axis(self, ell: float, centring: str = "texel") -> np.ndarray:
        """Target axis: d0 (``texel``) or the response's normalised first moment (``centroid``)."""
        _check("centring", centring, CENTRINGS)
        if centring == "texel":
            return self.d0
        f = self.at_level(ell)
        m = np.sum((f * self.omega)[:, None] * self.dirs, axis=0)
        return m / np.linalg.norm(m)

    def errors(self, s: float, ell: float, volume: str = "integral", centring: str = "texel") -> dict:
        """Relative errors (fractions of the analytic target volume) of the lobe at ``ell`` vs cosˢ."""
        vt = float(target_volume(s, volume))
        f = self.normalised(ell)
        t = target_lobe(_dir_dot(self.dirs, self.axis(ell, centring)), s)
        if volume == "integral":
            sym = _wsum(np.abs(f - t), self.omega)
        else:
            sym = _wsum(np.abs(f**3 - t**3), self.omega) / 3.0
        vf = lobe_volume(f, self.omega, volume)
        vq = lobe_volume(t, self.omega, volume)
        return {"symdiff": sym / vt, "voldiff": abs(vf - vt) / vt, "target_quad_rel_err": (vq - vt) / vt}


@functools.lru_cache(maxsize=4)
def lobe_response(n, kernel="sqrtcos", order="shrink_then_filter", seam="neighbour", position="centre",
                  sample_size=None) -> LobeResponse:
    """Cached :class:`LobeResponse` (``maxsize`` 4: one N=512 response holds ~120 MB)."""
    return LobeResponse(n, kernel, order, seam, position, sample_size)


def analyse(n: int, kernel="sqrtcos", s_values=None, *, order="shrink_then_filter", seam="neighbour",
            position="centre", volumes=VOLUME_DEFS, centrings=("texel",), sample_size=None,
            response: LobeResponse | None = None) -> list[dict]:
    """Fit level and errors for every s in ``s_values`` and every volume definition.

    Returns
    -------
    list of dict
        Rows with keys ``face_size, kernel, order, seam, position, volume, centring, s_phong, level, fit_clipped,
        err_symdiff_pct, err_voldiff_pct, target_quad_rel_err_pct``.
    """
    for v in volumes:
        _check("volume definition", v, VOLUME_DEFS)
    resp = response or LobeResponse(n, kernel, order, seam, position, sample_size)
    s_values = s_grid(n) if s_values is None else np.asarray(s_values, dtype=np.float64)
    rows = []
    for volume in volumes:
        for s in s_values:
            ell, clipped = resp.fit_level(float(s), volume)
            for centring in centrings:
                e = resp.errors(float(s), ell, volume, centring)
                rows.append({
                    "face_size": n, "kernel": resp.kernel if isinstance(resp.kernel, str) else "custom",
                    "order": resp.order, "seam": resp.seam, "position": resp.position, "volume": volume,
                    "centring": centring, "s_phong": float(s), "level": round(float(ell), 6),
                    "fit_clipped": clipped, "err_symdiff_pct": 100.0 * e["symdiff"],
                    "err_voldiff_pct": 100.0 * e["voldiff"],
                    "target_quad_rel_err_pct": 100.0 * e["target_quad_rel_err"],
                })
    return rows
