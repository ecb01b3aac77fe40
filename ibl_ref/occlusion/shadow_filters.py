"""Per-region visibility ``VIS_i`` (Knuth et al. 2014, Eq. 5) from filtered shadow maps: PCF, VSM, ESM, EVSM, MSM.

Knuth, Altenhofen, Kuijper & Bender (2014) estimate the visible fraction ``VIS_i`` of each median-cut region with
the variance shadow map of a directional light at the region's centroid, blurred by a Gaussian whose width follows
the region's solid angle (:mod:`ibl_ref.rendering.vsm`).  This module puts the shadow-map filters that came before
and after VSM behind one pipeline, so that each can be judged against the exact per-region visibility
(:func:`ibl_ref.occlusion.oracle_inputs.region_visibility`):

=========  ==========================================================================================================
``pcf``    percentage-closer filtering: Reeves, Salesin & Cook 1987, "Rendering Antialiased Shadows with Depth Maps"
           (SIGGRAPH): the weighted fraction of depth comparisons that pass over a kernel.
``vsm``    variance shadow maps: Donnelly & Lauritzen 2006 (I3D), Eq. 5 — the paper's filter, delegated unchanged to
           :func:`ibl_ref.rendering.vsm.build_vsm` and :func:`ibl_ref.rendering.vsm.visibility`.
``esm``    exponential shadow maps: Annen, Mertens, Seidel, Flerackers & Kautz 2008, "Exponential Shadow Maps" (GI):
           store exp(c·z), filter, visibility = clamp(exp(−c·t)·filtered, 0, 1).
``evsm``   exponential variance shadow maps: Lauritzen & McCool 2008, "Layered Variance Shadow Maps" (GI), the
           exponential warp: the Chebyshev bound of VSM on a positive warp exp(c⁺z) and a negative warp
           −exp(−c⁻z), the smaller of the two.
``msm``    moment shadow mapping: Peters & Klein 2015, "Moment Shadow Mapping" (I3D), the Hamburger 4MSM algorithm:
           four moments (z, z², z³, z⁴), biased, and the sharp lower bound on the shadow intensity from them.
=========  ==========================================================================================================

Each filter is implemented from the paper's formula or algorithm description (no section or equation numbers are
quoted here for the four papers beyond VSM's: the descriptions below state what is computed).
=========  ==========================================================================================================

**Shared pipeline** (one place, :func:`region_visibility_shadow_maps` and :class:`ShadowFilter`), the same as the
paper's VSMs (:mod:`ibl_ref.rendering.vsm`, whose functions it calls): per region i, an orthographic light camera
toward the region's centroid direction, fitted to the scene's bounding sphere
(:func:`ibl_ref.rendering.camera.light_camera`, ``margin``); the depth map
(:func:`ibl_ref.rendering.raster.render_depth`) normalised to ``d = depth / far ∈ [0, 1]`` (1 where no geometry);
the filter's encoding of d written in the storage ``dtype`` (``"float16"``, ``"float32"``, ``"float64"``); a
separable Gaussian blur (``scipy.ndimage.gaussian_filter``,
``mode="nearest"``, truncated at 4σ) computed in float32 (float64 for ``dtype="float64"``) and written back in
``dtype``; at a receiver, the bilinear look-up of the blurred encoding (texel centres on integers, clamped at the
border) and the filter's visibility of the receiver depth ``t = d_receiver − depth_bias``.

**Kernel width from the region's solid angle** — for every filter, the rule of
:func:`ibl_ref.rendering.vsm.blur_sigma_texels`: the region of solid angle Ω is a disc light of the same solid angle,
half-angle θ (Ω = 2π(1 − cos θ)); a blocker ``occluder_distance`` = Δd above the receiver (default 0.25 × scene
bounding radius) spreads the edge of its shadow like the disc's 1D marginal, of standard deviation Δd·tanθ/2, so
``σ_texels = Δd · tanθ / (2 · texel_size)`` (``sigma_texels`` overrides it for every region).

**What each filter supplies** (:class:`ShadowFilter`: ``encode`` the normalised depth, ``blur`` it, ``visibility``
of the receiver depth from the filtered look-up; PCF replaces the look-up):

* ``pcf`` — stores d alone and does not blur it (a depth cannot be averaged before the comparison).  Its kernel is
  the same Gaussian (standard deviation σ) applied to the *comparisons*: a (2k+1)² grid of taps (``taps`` = k,
  default 3) spaced 3σ/k texels apart, so the taps reach ±3σ, with weights exp(−½(3i/k)²)·exp(−½(3j/k)²) (for k = 3
  the discrete weights have standard deviation 0.998σ).  Each tap is a bilinear percentage-closer look-up — the four
  texels around it compared with the receiver and the passes weighted bilinearly (what a GPU's comparison sampler
  returns).  A grid rather than a Poisson disk: deterministic, with exactly the Gaussian's weights; no rotation or
  noise.  Comparison ``t ≤ d_texel``; ``receiver_plane=True`` (default) compares each texel with the receiver's
  *plane* at that texel, ``t + ∇t·(texel − x)``, ∇t from the receiver's face normal in the light's frame
  (receiver-plane depth bias, Isidoro 2006, "Shadow Mapping: GPU-based Tips and Techniques", GDC; the normal's
  component along the light is bounded below by 0.05, i.e. slopes up to tan 87°), so that a tilted planar receiver
  does not shadow itself within the kernel; ``depth_bias`` (default 1e-3, normalised depth) is subtracted as well.
* ``vsm`` — the paper's filter, unchanged: ``min_variance`` 1e-6, ``bleed_reduction`` 0 (defaults of
  :func:`ibl_ref.rendering.vsm.build_vsm`).
* ``esm`` — stores exp(c·d); visibility ``clamp(exp(−c·t)·z̄_c, 0, 1)`` with z̄_c the filtered value, evaluated as
  exp(ln(filtered) − c·t) so that no intermediate overflows.  A lit receiver (its own depth in the whole kernel) gets
  exp(c·depth_bias) ≥ 1 → 1; a receiver Δ behind an occluder that fills the kernel gets exp(−c·(Δ − depth_bias)) — ESM's
  leak, which decays only exponentially.  ``c`` (default 80 for float32 and float64, for depth in [0, 1]) must keep
  exp(c) representable in the storage type: c ≤ ln(max) = 88.7 for float32, 11.09 for float16 (max 65504), 709.8 for
  float64.  With ``dtype="float16"`` the default is c = 11 (exp(11) = 59874); a larger ``c`` is refused with
  :class:`~ibl_ref.errors.IBLError` (log-space filtering, which lifts the limit, is not implemented).
* ``evsm`` — the depth is first mapped to d' = 2d − 1 ∈ [−1, 1] (centring the warp: the second moment then needs
  exp(2c) instead of exp(4c) for the same warp), stores (e⁺, e⁺², e⁻, e⁻²) with e⁺ = exp(c⁺d'), e⁻ = −exp(−c⁻d');
  visibility = min(p⁺, p⁻) of the two Chebyshev bounds (:func:`ibl_ref.rendering.vsm.chebyshev_upper_bound`) at the
  warped receiver depth.  The minimum variance ``min_variance`` (default 1e-6, normalised depth², as VSM's) is
  carried into each warped space by the warp's derivative at the receiver, σ²_min·(dw/dd)².  Defaults c⁺ = 40,
  c⁻ = 5 for float32 and float64 (the largest positive exponent whose second moment exp(2c⁺) fits float32 is
  44.3); c⁺ = c⁻ = 5.5 for float16 (exp(11) < 65504); larger values are refused.  Optional light-bleeding
  reduction ``bleed_reduction`` (default 0) as for VSM; ``slope_bias`` 1 (below).
* ``msm`` — stores (d, d², d³, d⁴) as they are: Peters & Klein's optimised quantization transform for 16-bit
  *fixed-point* storage is not implemented; float16 storage keeps the raw moments in half floats instead, with a larger
  default bias.  The look-up (:func:`hamburger_4msm`) biases the filtered moments, b' = (1 − α)·b + α·(½, ½, ½, ½) —
  toward the moments of ½δ₀ + ½δ₁, the two-point distribution at the ends of the depth range, which keeps the Hankel
  matrix positive definite for any b (the algorithm's first step) — with ``moment_bias`` α = 3·10⁻⁵ for float32 and
  float64 (the paper's value for 32-bit floats) and 1·10⁻² for float16, then follows the algorithm: a Cholesky (LDLᵀ)
  solve of the 3 × 3 Hankel system for c, the two roots z₂ ≤ z₃ of c₃z² + c₂z + c₁, and the three cases for the shadow
  intensity G.  Visibility 1 − G is an **upper** bound on the visible fraction of the filtered depth distribution (G is
  the sharp *lower* bound on the shadow intensity given four moments), as VSM's Chebyshev bound is given two, and never
  above VSM's bound: with the same filtered depths (and α → 0) MSM's visibility ≤ VSM's, which is why it bleeds less
  light (Peters & Klein 2015 make this their motivation, their Fig. 1).  The float16 default is measured
  (``tests/test_shadow_filters.py``, random mixtures of 1–4 depths in [0.05, 0.95], receivers at least 0.02 from every
  depth): half-float rounding of raw moments makes false shadows (visibility more than 0.05 below the true fraction) in
  0.5 % of cases at α = 3·10⁻⁵ and 0.37 % at 10⁻³, about 0.01 % at 10⁻², at the price of more light leaking (mean excess
  visibility 0.036 → 0.077); in float32 and float64 there are none at 3·10⁻⁵.  Optional ``bleed_reduction`` (default 0);
  ``slope_bias`` 1 (below).

**Slope-scaled bias** (``slope_bias`` k of ``esm``, ``evsm``, ``msm``).  Over a kernel of σ texels a receiver tilted to
the light sees its *own* plane at depths spread with standard deviation s = |∇t|·√(σ² + 1/6) (∇t the plane's
normalised-depth gradient per texel, from the face normal as for PCF's receiver plane; 1/6 texel² the bilinear
footprint's variance).  VSM's Chebyshev bound ignores that spread (t ≤ mean → 1), and so does ESM (exp is convex: the
filtered exp(c·z) ≥ exp(c·mean)); EVSM's negative warp is concave and MSM's four moments pin the spread down, so both
shadow a lit tilted plane: measured minimum visibility on a plane of slope 1 under σ = 3 texels, 0.96 (EVSM) and 0.86
(MSM), 0.84 at slope 2 (MSM).  ``t − k·s`` removes it: k = 1 gives 1.000 for every slope ≤ 2 and σ ≤ 8 tried.  Defaults:
k = 1 for ``evsm`` and ``msm`` (a standard slope-scaled depth bias, as ``glPolygonOffset``'s factor), 0 for ``esm``
(nothing to remove; the bias only lets more light leak).  On the crevice scene against the exact per-region visibility
(24 median-cut regions of a sky-and-sun map, 400 surface points, 128² maps; pairs whose region centroid lies more
than 0.2 in cosine above the receiver's plane) k = 1 lowers MSM's mean |error| from 0.048 to 0.008 and EVSM's from
0.018 to 0.011 (VSM 0.011, ESM 0.045, PCF 0.008); pass ``slope_bias=0`` for the filters exactly as published.

**Horizon.**  A shadow map holds the nearest surface along each light ray, so a receiver is shadowed only by what
lies in front of it; its *own* horizon (a light at or below the receiving triangle's plane) is not part of the map
except through the solid's other side.  ``horizon=None`` (default) returns the shadow map's answer, as
:func:`ibl_ref.rendering.render.light_visibilities` does for ``"vsm"``; ``horizon=True`` multiplies every VIS_i by
[n_face·ω_i > 0] (:func:`ibl_ref.rendering.render.horizon_term`).

Examples
--------
A receiver quad under a smaller occluder quad, one light straight above: shadowed under it, lit beside it.

>>> import numpy as np, trimesh
>>> from types import SimpleNamespace
>>> from ibl_ref.occlusion.shadow_filters import SHADOW_FILTERS, region_visibility_shadow_maps
>>> quad = lambda h, s: trimesh.Trimesh([[-s, h, -s], [s, h, -s], [s, h, s], [-s, h, s]], [[0, 2, 1], [0, 3, 2]])
>>> scene = [quad(0.0, 2.0), quad(0.6, 0.8)]
>>> lights = SimpleNamespace(directions=np.array([[0.0, 1.0, 0.0]]), solid_angle=np.array([1e-4]))
>>> pts, up = np.array([[0.0, 0.0, 0.0], [1.6, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]] * 2)
>>> list(SHADOW_FILTERS)
['pcf', 'vsm', 'esm', 'evsm', 'msm']
>>> for name in SHADOW_FILTERS:
...     v = region_visibility_shadow_maps(scene, pts, up, lights, filter=name, resolution=64)
...     print(name, np.round(v[:, 0], 2))
pcf [0. 1.]
vsm [0. 1.]
esm [0. 1.]
evsm [0. 1.]
msm [0. 1.]
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import IBLError
from ..rendering import vsm as _vsm
from ..rendering.camera import OrthographicCamera, light_camera
from ..rendering.raster import prepare_scene, render_depth
from .oracle_inputs import _vectors

__all__ = [
    "SHADOW_FILTERS",
    "ShadowFilter",
    "ShadowMap",
    "PercentageCloser",
    "VarianceFilter",
    "Exponential",
    "ExponentialVariance",
    "MomentFilter",
    "hamburger_4msm",
    "region_visibility_shadow_maps",
]

_DTYPES = {"float16": np.float16, "float32": np.float32, "float64": np.float64}
#: keyword arguments of the shared pipeline (every filter), with their defaults
_PIPELINE_DEFAULTS = {"occluder_distance": None, "sigma_texels": None, "depth_bias": 1e-3, "margin": 0.05}
#: MSM bias target: the moments (E z, E z², E z³, E z⁴) of ½δ₀ + ½δ₁ (Peters & Klein 2015, Hamburger 4MSM)
_MSM_BIAS_TARGET = (0.5, 0.5, 0.5, 0.5)


def _work(dtype: str):
    """Arithmetic precision of blur and look-up for a storage type: float64 for float64, else float32 (as a GPU)."""
    return np.float64 if dtype == "float64" else np.float32


@dataclass
class ShadowMap:
    """A filtered shadow map of one directional light (every filter but ``vsm``, which returns
    :class:`ibl_ref.rendering.vsm.VarianceShadowMap`).

    Attributes
    ----------
    camera : OrthographicCamera
        The light's view (``forward = −direction``).
    data : ndarray, shape (H, W, C), in ``dtype``
        The filter's encoding of the normalised depth, blurred (PCF: the depth itself, unblurred).
    sigma_texels : float
        Standard deviation of the Gaussian kernel in texels (blur, or PCF's tap weights).
    dtype : str
        Storage type of ``data``.
    """

    camera: OrthographicCamera
    data: np.ndarray
    sigma_texels: float
    dtype: str


@dataclass
class _Options:
    """Validated inputs of the shared pipeline (:func:`region_visibility_shadow_maps`)."""

    resolution: int
    dtype: str
    occluder_distance: float | None
    sigma_texels: float | None
    depth_bias: float
    margin: float
    params: dict = field(default_factory=dict)

    @property
    def work(self):
        return _work(self.dtype)


def _receiver(camera, points, depth_bias: float):
    """Texel coordinates (centres on integers) and biased normalised depth ``t`` of world points (P, 3)."""
    x, y, depth, _ = camera.project(points)
    return x - 0.5, y - 0.5, depth / camera.far - depth_bias


def _footprint(shape, x, y):
    """Bilinear footprint of continuous texel coordinates clamped to the map: rows, columns and weights.

    Returns ``(rows (2, P), cols (2, P), wy (2, P), wx (2, P))``: the two rows and two columns around each point and
    their linear weights (texel centres on integers; coordinates clamped to [0, size − 1], so the border repeats).
    """
    H, W = shape
    xs = np.clip(x, 0.0, W - 1.0)
    ys = np.clip(y, 0.0, H - 1.0)
    c0 = np.minimum(np.floor(xs).astype(np.int64), max(W - 2, 0))
    r0 = np.minimum(np.floor(ys).astype(np.int64), max(H - 2, 0))
    fx, fy = xs - c0, ys - r0
    cols = np.stack([c0, np.minimum(c0 + 1, W - 1)])
    rows = np.stack([r0, np.minimum(r0 + 1, H - 1)])
    return rows, cols, np.stack([1 - fy, fy]), np.stack([1 - fx, fx])


def _bilinear(img, x, y):
    """Bilinear look-up of (H, W, C) at texel coordinates x, y (P,) → (P, C) (the footprint of :func:`_footprint`)."""
    rows, cols, wy, wx = _footprint(img.shape[:2], x, y)
    out = 0.0
    for a in range(2):
        for b in range(2):
            out = out + (wy[a] * wx[b])[:, None] * img[rows[a], cols[b]]
    return out


def _check_number(value, name: str, lo: float, hi: float = np.inf, *, lo_open: bool = False) -> float:
    """``value`` as a finite float in [lo, hi] (or (lo, hi]); one-line :class:`IBLError` naming ``name``."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise IBLError(f"{name}: expected a number, got {value!r}") from None
    if not np.isfinite(x) or x > hi or x < lo or (lo_open and x == lo):
        lower = "(" if lo_open else "["
        raise IBLError(f"{name}: must be in {lower}{lo:g}, {hi:g}], got {value!r}")
    return x


def _exp_limit(dtype: str, power: int) -> float:
    """Largest exponent a with exp(power·a) finite in the storage type (ln(max) / power)."""
    return float(np.log(np.finfo(_DTYPES[dtype]).max)) / power


class ShadowFilter:
    """One shadow-map filter: what it stores, how it blurs, what visibility it reads back.

    The shared pipeline (:meth:`build`, :meth:`lookup`) renders the normalised depth map of the light, stores
    :meth:`encode` of it in the storage type, applies :meth:`blur`, and at each receiver evaluates
    :meth:`visibility` of the receiver depth from the bilinear look-up of the blurred encoding.  Subclasses override
    only what differs.

    Attributes
    ----------
    name : str
        Registry label.
    reference : str
        The paper of the filter (title, authors, year; VSM with its equation).
    defaults : dict
        Filter parameters and their defaults; a value that is a dict maps the storage dtype to the default.
    """

    name = ""
    reference = ""
    defaults: dict = {}

    def params(self, dtype: str, given: dict) -> dict:
        """The filter's parameters for ``dtype``: ``given`` over the defaults, validated (:class:`IBLError`)."""
        out = {}
        for key, default in self.defaults.items():
            value = given.get(key, default)
            out[key] = value[dtype] if isinstance(value, dict) else value
        if "slope_bias" in out:
            out["slope_bias"] = _check_number(out["slope_bias"], f"{self.name}: slope_bias", 0.0, 10.0)
        self.check(dtype, out)
        return out

    def check(self, dtype: str, params: dict) -> None:
        """Validate the parameters (raise :class:`IBLError`); nothing to check by default."""

    def encode(self, d: np.ndarray, params: dict) -> np.ndarray:
        """Channels (H, W, C) float64 to store for normalised depth d (H, W)."""
        raise NotImplementedError

    def blur(self, m: np.ndarray, sigma: float, work) -> np.ndarray:
        """Separable Gaussian blur of every channel of (H, W, C) in precision ``work`` (module docstring)."""
        from scipy.ndimage import gaussian_filter

        if sigma <= 0:
            return m
        out = m.astype(work)
        for c in range(out.shape[-1]):
            out[..., c] = gaussian_filter(out[..., c], sigma=sigma, mode="nearest", truncate=4.0)
        return out

    def visibility(self, t: np.ndarray, sample: np.ndarray, params: dict) -> np.ndarray:
        """Visibility (P,) of receivers at biased normalised depth t (P,) from the filtered look-up (P, C)."""
        raise NotImplementedError

    def build(self, scene, direction, solid_angle: float, opts: _Options, timings: dict | None = None):
        """The filtered shadow map of one directional light (shared pipeline, module docstring)."""
        t0 = time.perf_counter()
        centre, radius = scene.bounds()
        cam = light_camera(direction, centre, radius, resolution=opts.resolution, margin=opts.margin)
        depth, _ = render_depth(scene, cam, warn=False)
        t1 = time.perf_counter()
        d = np.clip(depth / cam.far, 0.0, 1.0)
        sigma = _kernel_sigma(solid_angle, cam.texel_size, radius, opts)
        store = _DTYPES[opts.dtype]
        m = self.encode(d, opts.params).astype(store)  # render-target write: quantised to the storage type
        m = self.blur(m, sigma, opts.work).astype(store)  # the blur pass writes back to the storage texture
        _add_time(timings, "shadow_maps", t1 - t0)
        _add_time(timings, "blur", time.perf_counter() - t1)
        return ShadowMap(camera=cam, data=m, sigma_texels=sigma, dtype=opts.dtype)

    def lookup(self, sm, points, face_normals, opts: _Options) -> np.ndarray:
        """Visibility (P,) in [0, 1] of world points (P, 3) in the shadow map ``sm`` of :meth:`build`."""
        x, y, t = _receiver(sm.camera, points, opts.depth_bias)
        k = opts.params.get("slope_bias", 0.0)
        if k > 0:  # the receiver plane's own depth spread over the kernel (module docstring)
            gx, gy = _receiver_plane_gradient(sm.camera, face_normals, "slope_bias > 0")
            t = t - k * np.hypot(gx, gy) * np.sqrt(sm.sigma_texels**2 + 1.0 / 6.0)
        work = opts.work
        sample = _bilinear(sm.data.astype(work), x.astype(work), y.astype(work))
        v = self.visibility(t.astype(work), sample, opts.params)
        return np.clip(np.asarray(v, dtype=np.float64), 0.0, 1.0)


def _kernel_sigma(solid_angle: float, texel_size: float, radius: float, opts: _Options) -> float:
    """Gaussian σ in texels: ``opts.sigma_texels`` or the Ω rule of :func:`ibl_ref.rendering.vsm.blur_sigma_texels`."""
    if opts.sigma_texels is not None:
        return float(opts.sigma_texels)
    dd = 0.25 * radius if opts.occluder_distance is None else opts.occluder_distance
    return _vsm.blur_sigma_texels(solid_angle, texel_size, dd)


def _add_time(timings: dict | None, key: str, seconds: float) -> None:
    if timings is not None:
        timings[key] = timings.get(key, 0.0) + seconds


class PercentageCloser(ShadowFilter):
    """Percentage-closer filtering (Reeves, Salesin & Cook 1987): Gaussian-weighted grid of bilinear comparisons.

    Parameters (``**params`` of :func:`region_visibility_shadow_maps`): ``taps`` k (default 3: a 7 × 7 grid
    reaching ±3σ), ``receiver_plane`` (default True; needs face normals).  Module docstring for the kernel.

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.occlusion.shadow_filters import PercentageCloser
    >>> PercentageCloser().tap_weights(3).round(3)
    array([0.011, 0.135, 0.607, 1.   , 0.607, 0.135, 0.011])
    """

    name = "pcf"
    reference = "Reeves, Salesin & Cook 1987, Rendering Antialiased Shadows with Depth Maps"
    defaults = {"taps": 3, "receiver_plane": True}

    def check(self, dtype, params):
        k = params["taps"]
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 0 <= k <= 16:
            raise IBLError(f"pcf: taps must be an integer in [0, 16] (a (2k+1)² grid), got {k!r}")
        if params["receiver_plane"] not in (True, False):
            raise IBLError(f"pcf: receiver_plane must be True or False, got {params['receiver_plane']!r}")

    @staticmethod
    def tap_weights(k: int) -> np.ndarray:
        """1D weights exp(−½(3i/k)²), i = −k … k, of the tap grid (k = 0: one tap of weight 1)."""
        i = np.arange(-k, k + 1, dtype=np.float64)
        return np.exp(-0.5 * (3.0 * i / max(k, 1)) ** 2)

    def encode(self, d, params):
        return d[..., None]

    def blur(self, m, sigma, work):
        return m  # the kernel is applied to the comparisons at look-up time

    def lookup(self, sm, points, face_normals, opts):
        x, y, t = _receiver(sm.camera, points, opts.depth_bias)
        gx, gy = np.zeros_like(t), np.zeros_like(t)
        if opts.params["receiver_plane"]:
            gx, gy = _receiver_plane_gradient(sm.camera, face_normals)
        depth = sm.data[..., 0].astype(opts.work)
        k = opts.params["taps"] if sm.sigma_texels > 0 else 0
        spacing = 3.0 * sm.sigma_texels / max(k, 1)
        w = self.tap_weights(k)
        acc = np.zeros_like(t)
        for i, wi in enumerate(w):
            for j, wj in enumerate(w):
                xs, ys = x + (j - k) * spacing, y + (i - k) * spacing
                acc += wi * wj * _bilinear_comparison(depth, xs, ys, x, y, t, gx, gy)
        return np.clip(acc / w.sum() ** 2, 0.0, 1.0)


def _receiver_plane_gradient(camera, face_normals, why: str = "pcf: receiver_plane=True"):
    """∂t/∂x and ∂t/∂y (normalised depth per texel) of the receivers' planes in the light's image (module docstring).

    For the plane n·p = const, in the light's frame (right, up, forward) with components (n_r, n_u, n_f):
    ∂depth/∂right = −n_r/n_f, ∂depth/∂up = −n_u/n_f; texel x grows along right, y against up, both by texel_size.
    |n_f| is bounded below by 0.05 (slopes up to tan 87°).
    """
    if face_normals is None:
        raise IBLError(f"{why} needs face_normals")
    n = face_normals @ camera.basis.T
    nf = np.where(n[:, 2] < 0, np.minimum(n[:, 2], -0.05), np.maximum(n[:, 2], 0.05))
    scale = camera.texel_size / camera.far
    return -n[:, 0] / nf * scale, n[:, 1] / nf * scale


def _bilinear_comparison(depth, xs, ys, x, y, t, gx, gy):
    """One bilinear percentage-closer tap at (xs, ys): the four texels' passes [t_plane ≤ d], weighted bilinearly.

    ``t_plane = t + gx·(column − x) + gy·(row − y)``: the receiver's plane at the texel centre (gx = gy = 0: the
    constant receiver depth t).
    """
    rows, cols, wy, wx = _footprint(depth.shape, xs, ys)
    out = np.zeros_like(t)
    for a in range(2):
        for b in range(2):
            tp = t + gx * (cols[b] - x) + gy * (rows[a] - y)
            out += wy[a] * wx[b] * (tp <= depth[rows[a], cols[b]])
    return out


class VarianceFilter(ShadowFilter):
    """Variance shadow maps, the paper's filter: :func:`ibl_ref.rendering.vsm.build_vsm` and
    :func:`ibl_ref.rendering.vsm.visibility`, unchanged (``min_variance`` 1e-6, ``bleed_reduction`` 0).

    Examples
    --------
    >>> from ibl_ref.occlusion.shadow_filters import SHADOW_FILTERS
    >>> SHADOW_FILTERS["vsm"].params("float16", {})
    {'min_variance': 1e-06, 'bleed_reduction': 0.0}
    """

    name = "vsm"
    reference = "Donnelly & Lauritzen 2006, Variance Shadow Maps, Eq. 5 (Knuth et al. 2014, Sec. 3.3)"
    defaults = {"min_variance": 1e-6, "bleed_reduction": 0.0}

    def build(self, scene, direction, solid_angle, opts, timings=None):
        return _vsm.build_vsm(scene, direction, solid_angle, resolution=opts.resolution,
                              occluder_distance=opts.occluder_distance, sigma_texels=opts.sigma_texels,
                              dtype=opts.dtype, depth_bias=opts.depth_bias, margin=opts.margin, timings=timings,
                              **opts.params)

    def lookup(self, sm, points, face_normals, opts):
        return _vsm.visibility(points, sm)


class Exponential(ShadowFilter):
    """Exponential shadow maps (Annen et al. 2008): store exp(c·d), visibility clamp(exp(−c·t)·filtered, 0, 1).

    Parameters ``c`` (default 80; 11 for float16; refused where exp(c) overflows the storage type), ``slope_bias``
    (0; module docstring).

    Examples
    --------
    A receiver 0.05 behind an occluder that fills the kernel, c = 80 and no depth bias: exp(−80·0.05) = exp(−4).

    >>> import numpy as np
    >>> from ibl_ref.occlusion.shadow_filters import Exponential
    >>> esm = Exponential()
    >>> p = esm.params("float64", {})
    >>> stored = esm.encode(np.array([[0.5]]), p)[0]
    >>> float(esm.visibility(np.array([0.55]), stored, p)[0]), float(np.exp(-4.0))
    (0.018315638888734, 0.01831563888873418)
    >>> esm.params("float16", {"c": 80})
    Traceback (most recent call last):
    ...
    ibl_ref.errors.IBLError: esm: exp(c) with c = 80 overflows float16 (c <= 11.09); choose a smaller c
    """

    name = "esm"
    reference = "Annen, Mertens, Seidel, Flerackers & Kautz 2008, Exponential Shadow Maps"
    defaults = {"c": {"float16": 11.0, "float32": 80.0, "float64": 80.0}, "slope_bias": 0.0}

    def check(self, dtype, params):
        params["c"] = _check_exponent(params["c"], "esm: c", dtype, power=1)

    def encode(self, d, params):
        return np.exp(params["c"] * d)[..., None]

    def visibility(self, t, sample, params):
        with np.errstate(divide="ignore"):
            return np.exp(np.minimum(np.log(sample[:, 0]) - params["c"] * t, 0.0))


def _check_exponent(value, name: str, dtype: str, power: int) -> float:
    """A warp exponent c > 0 whose exp(power·c) fits the storage type (module docstring)."""
    c = _check_number(value, name, 0.0, lo_open=True)
    limit = _exp_limit(dtype, power)
    if c > limit:
        what = "exp(c)" if power == 1 else f"exp({power}c)"
        raise IBLError(f"{name.split(':')[0]}: {what} with c = {value!r} overflows {dtype} (c <= {limit:.2f}); "
                       f"choose a smaller c")
    return c


class ExponentialVariance(ShadowFilter):
    """Exponential variance shadow maps (Lauritzen & McCool 2008): Chebyshev on exp(c⁺d') and −exp(−c⁻d'), the min.

    Parameters ``c_pos`` (default 40; 5.5 for float16), ``c_neg`` (default 5; 5.5 for float16), ``min_variance``
    (1e-6 in normalised depth², carried into each warp), ``bleed_reduction`` (0), ``slope_bias`` (1; module
    docstring).

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.occlusion.shadow_filters import ExponentialVariance
    >>> evsm = ExponentialVariance()
    >>> p = evsm.params("float64", {})
    >>> half = evsm.encode(np.array([[0.3, 0.7]]), p)[0].mean(axis=0)   # half the kernel at 0.3, half at 0.7
    >>> evsm.visibility(np.array([0.2, 0.5, 0.9]), np.tile(half, (3, 1)), p).round(3)  # true: 1, 0.5, 0
    array([1.   , 0.633, 0.006])
    """

    name = "evsm"
    reference = "Lauritzen & McCool 2008, Layered Variance Shadow Maps (exponential warp)"
    defaults = {"c_pos": {"float16": 5.5, "float32": 40.0, "float64": 40.0},
                "c_neg": {"float16": 5.5, "float32": 5.0, "float64": 5.0},
                "min_variance": 1e-6, "bleed_reduction": 0.0, "slope_bias": 1.0}

    def check(self, dtype, params):
        for key in ("c_pos", "c_neg"):
            params[key] = _check_exponent(params[key], f"evsm: {key}", dtype, power=2)
        params["min_variance"] = _check_number(params["min_variance"], "evsm: min_variance", 0.0, lo_open=True)
        _vsm.reduce_light_bleeding(0.5, params["bleed_reduction"])  # validates k

    @staticmethod
    def warps(d, params):
        """Positive and negative warps (exp(c⁺d'), −exp(−c⁻d')) of normalised depth d, d' = 2d − 1."""
        dc = 2.0 * d - 1.0
        return np.exp(params["c_pos"] * dc), -np.exp(-params["c_neg"] * dc)

    def encode(self, d, params):
        pos, neg = self.warps(d, params)
        return np.stack([pos, pos * pos, neg, neg * neg], axis=-1)

    def visibility(self, t, sample, params):
        tp, tn = self.warps(t, params)
        dt = t.dtype.type
        # σ²_min·(dw/dd)²: dw/dd = 2c⁺·e⁺ and 2c⁻·|e⁻|
        var_p = dt(params["min_variance"]) * (2 * params["c_pos"] * tp) ** 2
        var_n = dt(params["min_variance"]) * (2 * params["c_neg"] * tn) ** 2
        p = np.minimum(_vsm.chebyshev_upper_bound(tp, sample[:, 0], sample[:, 1], var_p),
                       _vsm.chebyshev_upper_bound(tn, sample[:, 2], sample[:, 3], var_n))
        return _vsm.reduce_light_bleeding(p, params["bleed_reduction"])


def hamburger_4msm(moments, t, moment_bias: float = 3e-5) -> np.ndarray:
    """Visibility 1 − G from four depth moments: Hamburger 4MSM (Peters & Klein 2015), vectorised.

    G is the sharp lower bound on the shadow intensity P(z < t) over all depth distributions with the (biased)
    moments, so the result is an upper bound on the visible fraction P(z ≥ t), never above VSM's Chebyshev bound
    for the same distribution (α → 0).  Steps: b' = (1 − α)·b + α·(½, ½, ½, ½); solve the Hankel system
    [[1, b'₁, b'₂], [b'₁, b'₂, b'₃], [b'₂, b'₃, b'₄]]·c = (1, t, t²) by its LDLᵀ (Cholesky) factors; z₂ ≤ z₃ the roots
    of c₃z² + c₂z + c₁; G = 0 for t ≤ z₂, G = (t·z₃ − b'₁(t + z₃) + b'₂) / ((z₃ − z₂)(t − z₂)) for z₂ < t ≤ z₃,
    G = 1 − (z₂z₃ − b'₁(z₂ + z₃) + b'₂) / ((t − z₂)(t − z₃)) for t > z₃.

    Parameters
    ----------
    moments : array_like, shape (..., 4)
        Filtered (E z, E z², E z³, E z⁴) of depth in [0, 1]; the arithmetic runs in their float type (float32 as on
        a GPU, or float64).
    t : array_like, shape (...)
        Receiver depth (bias already subtracted).
    moment_bias : float
        α ∈ [0, 1) (0 only for moments of a distribution with at least three support points: the Hankel matrix of
        fewer is singular).

    Returns
    -------
    ndarray, shape (...), in [0, 1]

    Examples
    --------
    Half the kernel at depth 0.2, half at 0.6: a receiver at 0.4 sees the half behind it, one at 0.9 nothing (VSM's
    Chebyshev bound leaks 0.4 there).

    >>> import numpy as np
    >>> from ibl_ref.occlusion.shadow_filters import hamburger_4msm
    >>> z = np.array([0.2, 0.6])
    >>> b = 0.5 * (z[:, None] ** np.arange(1, 5)).sum(axis=0)
    >>> hamburger_4msm(np.tile(b, (3, 1)), np.array([0.1, 0.4, 0.9])).round(3)
    array([1. , 0.5, 0. ])
    """
    b = np.asarray(moments)
    if not np.issubdtype(b.dtype, np.floating):
        b = b.astype(np.float64)
    ft = b.dtype.type
    z = np.asarray(t, dtype=b.dtype)
    a = ft(moment_bias)
    b = (1 - a) * b + a * np.asarray(_MSM_BIAS_TARGET, dtype=b.dtype)
    b1, b2, b3, b4 = (b[..., i] for i in range(4))
    tiny = ft(np.finfo(b.dtype).tiny)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # degenerate moments: handled below
        # LDLᵀ of the Hankel matrix: L21 = b1, L31 = b2, D22 = b2 − b1², L32 = (b3 − b1 b2) / D22,
        # D33 = b4 − b2² − L32² D22
        d22 = np.maximum(b2 - b1 * b1, tiny)
        l32 = (b3 - b1 * b2) / d22
        d33 = np.maximum(b4 - b2 * b2 - l32 * l32 * d22, tiny)
        # forward substitution of (1, t, t²), scaling by D, back substitution
        y2 = (z - b1) / d22
        c3 = (z * z - b2 - l32 * (z - b1)) / d33
        c2 = y2 - l32 * c3
        c1 = 1 - b1 * c2 - b2 * c3
        p, q = c2 / c3, c1 / c3
        r = np.sqrt(np.maximum(0.25 * p * p - q, 0))
        z2, z3 = -0.5 * p - r, -0.5 * p + r
        g_mid = (z * z3 - b1 * (z + z3) + b2) / ((z3 - z2) * (z - z2))
        g_far = 1 - (z2 * z3 - b1 * (z2 + z3) + b2) / ((z - z2) * (z - z3))
        zero, one = ft(0), ft(1)
        g = np.where(z <= z2, zero, np.where(z <= z3, g_mid, g_far))
        g = np.where(np.isfinite(g), g, np.where(z > b1, one, zero))  # degenerate roots: the side of the mean decides
    return np.clip(1 - g, 0, 1)


class MomentFilter(ShadowFilter):
    """Moment shadow maps (Peters & Klein 2015): four moments, Hamburger 4MSM (:func:`hamburger_4msm`).

    Parameters ``moment_bias`` α (default 3e-5; 1e-2 for float16), ``bleed_reduction`` (0), ``slope_bias`` (1;
    module docstring).

    Examples
    --------
    >>> from ibl_ref.occlusion.shadow_filters import SHADOW_FILTERS
    >>> SHADOW_FILTERS["msm"].params("float32", {})
    {'moment_bias': 3e-05, 'bleed_reduction': 0.0, 'slope_bias': 1.0}
    """

    name = "msm"
    reference = "Peters & Klein 2015, Moment Shadow Mapping (Hamburger 4MSM)"
    defaults = {"moment_bias": {"float16": 1e-2, "float32": 3e-5, "float64": 3e-5}, "bleed_reduction": 0.0,
                "slope_bias": 1.0}

    def check(self, dtype, params):
        params["moment_bias"] = _check_number(params["moment_bias"], "msm: moment_bias", 0.0, 0.5)
        _vsm.reduce_light_bleeding(0.5, params["bleed_reduction"])  # validates k

    def encode(self, d, params):
        return d[..., None] ** np.arange(1, 5)

    def visibility(self, t, sample, params):
        v = hamburger_4msm(sample, t, params["moment_bias"])
        return _vsm.reduce_light_bleeding(v, params["bleed_reduction"])


#: registry: filter name → :class:`ShadowFilter` (each filter's parameters: its ``defaults``)
SHADOW_FILTERS: dict[str, ShadowFilter] = {f.name: f for f in (PercentageCloser(), VarianceFilter(), Exponential(),
                                                               ExponentialVariance(), MomentFilter())}


def _options(resolution, dtype, flt: ShadowFilter, params: dict) -> _Options:
    """Validate the pipeline's and the filter's keyword arguments (:class:`IBLError` on anything unknown or bad)."""
    unknown = set(params) - set(_PIPELINE_DEFAULTS) - set(flt.defaults)
    if unknown:
        raise IBLError(f"{flt.name}: unknown parameter(s) {', '.join(sorted(unknown))}; accepted: "
                       f"{', '.join(list(_PIPELINE_DEFAULTS) + list(flt.defaults))}")
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) or resolution < 2:
        raise IBLError(f"resolution must be an integer >= 2, got {resolution!r}")
    if dtype not in _DTYPES:
        raise IBLError(f"dtype must be one of {', '.join(_DTYPES)}, got {dtype!r}")
    pipe = {k: params.get(k, v) for k, v in _PIPELINE_DEFAULTS.items()}
    for key, lo in (("occluder_distance", 0.0), ("sigma_texels", 0.0)):
        if pipe[key] is not None:
            pipe[key] = _check_number(pipe[key], key, lo)
    pipe["depth_bias"] = _check_number(pipe["depth_bias"], "depth_bias", 0.0, 1.0)
    pipe["margin"] = _check_number(pipe["margin"], "margin", 0.0, 10.0)
    return _Options(resolution=int(resolution), dtype=dtype, params=flt.params(dtype, params), **pipe)


def region_visibility_shadow_maps(scene, points, face_normals, lights, *, filter: str = "vsm", resolution: int = 256,
                                  dtype: str = "float32", horizon: bool | None = None, timings: dict | None = None,
                                  **params) -> np.ndarray:
    """Estimated per-region visibility VIS_i (P, R) of Knuth et al. 2014, Eq. 5: one filtered shadow map per region.

    Parameters
    ----------
    scene : meshes or a prepared :class:`ibl_ref.rendering.raster.Scene`
        Occluders and receivers.
    points : array_like, shape (P, 3)
        Receiver points (world space).
    face_normals : array_like, shape (P, 3), or None
        Geometric normals of the points' triangles: ``horizon=True`` and PCF's receiver-plane bias use them.
    lights : LightSet
        Anything with ``.directions`` (R, 3) toward each region's centroid and ``.solid_angle`` (R,) in sr (a
        median-cut :class:`ibl_ref.knuth2014.median_cut.LightSet`).
    filter : {"pcf", "vsm", "esm", "evsm", "msm"}
        :data:`SHADOW_FILTERS` (module docstring).
    resolution : int
        Shadow-map size (square), ≥ 2.
    dtype : {"float16", "float32", "float64"}
        Storage type of the maps (float16 = the paper's RG16F for VSM).
    horizon : bool or None
        None or False: the shadow map's answer (no receiver horizon); True: times [n_face·ω_i > 0].
    timings : dict, optional
        Adds seconds to ``shadow_maps`` (depth rendering), ``blur`` (encoding and blur) and ``visibility`` (look-ups).
    **params
        Pipeline: ``occluder_distance`` (Δd of the Ω → σ rule; default 0.25 × scene bounding radius),
        ``sigma_texels`` (σ for every region instead of the rule), ``depth_bias`` (default 1e-3, normalised depth),
        ``margin`` (0.05, light camera).  Filter: ``pcf`` — ``taps`` (3), ``receiver_plane`` (True); ``vsm`` —
        ``min_variance`` (1e-6), ``bleed_reduction`` (0); ``esm`` — ``c`` (80; float16 11), ``slope_bias`` (0);
        ``evsm`` — ``c_pos`` (40; float16 5.5), ``c_neg`` (5; float16 5.5), ``min_variance`` (1e-6),
        ``bleed_reduction`` (0), ``slope_bias`` (1); ``msm`` — ``moment_bias`` (3e-5; float16 1e-2),
        ``bleed_reduction`` (0), ``slope_bias`` (1).  ``slope_bias`` > 0 needs ``face_normals``.

    Returns
    -------
    ndarray, float64, shape (P, R)
        VIS_i in [0, 1] per point and region (the layout of
        :func:`ibl_ref.occlusion.oracle_inputs.region_visibility`).

    Raises
    ------
    IBLError
        Unknown filter (the message lists the names) or parameter, resolution < 2, unknown dtype, points or normals
        of the wrong shape or with NaN, directions and solid angles that disagree in length, a solid angle outside
        [0, 4π], an exponent that overflows the storage type.

    Examples
    --------
    >>> import numpy as np, trimesh
    >>> from types import SimpleNamespace
    >>> from ibl_ref.occlusion.shadow_filters import region_visibility_shadow_maps
    >>> floor = trimesh.Trimesh([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], [[0, 2, 1], [0, 3, 2]])
    >>> lights = SimpleNamespace(directions=np.array([[0.0, 1, 0], [0.0, -1, 0]]), solid_angle=np.array([0.1, 0.1]))
    >>> region_visibility_shadow_maps(floor, [[0, 0, 0]], [[0, 1, 0]], lights, filter="msm", resolution=16)
    array([[1., 1.]])
    >>> region_visibility_shadow_maps(floor, [[0, 0, 0]], [[0, 1, 0]], lights, filter="msm", horizon=True,
    ...                               resolution=16)
    array([[1., 0.]])
    >>> region_visibility_shadow_maps(floor, [[0, 0, 0]], [[0, 1, 0]], lights, filter="gauss")
    Traceback (most recent call last):
    ...
    ibl_ref.errors.IBLError: unknown shadow filter 'gauss'; choose one of pcf, vsm, esm, evsm, msm
    """
    if not isinstance(filter, str) or filter not in SHADOW_FILTERS:
        raise IBLError(f"unknown shadow filter {filter!r}; choose one of {', '.join(SHADOW_FILTERS)}")
    if horizon not in (None, False, True):
        raise IBLError(f"horizon must be None, False or True, got {horizon!r}")
    flt = SHADOW_FILTERS[filter]
    opts = _options(resolution, dtype, flt, params)
    pts = _vectors("points", points, None, unit=False)
    fn = None if face_normals is None else _vectors("face_normals", face_normals, len(pts), unit=False)
    if horizon and fn is None:
        raise IBLError("horizon=True needs face_normals")
    try:
        dirs = _vectors("lights.directions", np.atleast_2d(np.asarray(lights.directions, dtype=np.float64)), None,
                        unit=False)
        omega = np.atleast_1d(np.asarray(lights.solid_angle, dtype=np.float64))
    except AttributeError as exc:
        raise IBLError(f"lights: expected .directions (R, 3) and .solid_angle (R,), got {type(lights).__name__}") \
            from exc
    if len(omega) != len(dirs):
        raise IBLError(f"lights: {len(dirs)} directions but {len(omega)} solid angles")
    _vsm.cap_half_angle(omega)  # validates Ω ∈ [0, 4π]
    if np.any(np.linalg.norm(dirs, axis=1) == 0):
        raise IBLError("lights.directions: zero vector")
    vis = np.ones((len(pts), len(dirs)))
    if len(pts) == 0 or len(dirs) == 0:
        return vis
    sc = prepare_scene(scene, warn=False)
    for i in range(len(dirs)):
        sm = flt.build(sc, dirs[i], omega[i], opts, timings)
        t0 = time.perf_counter()
        vis[:, i] = flt.lookup(sm, pts, fn, opts)
        _add_time(timings, "visibility", time.perf_counter() - t0)
    if horizon:
        from ..rendering.render import horizon_term

        vis *= horizon_term(fn, dirs).T
    return vis
