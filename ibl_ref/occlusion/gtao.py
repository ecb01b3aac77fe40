"""Screen-space ambient occlusion and bent normals by a horizon search (GTAO) from the rasterizer's G-buffer.

Jimenez, Wu, Pesce & Jarabo (2016), *Practical Real-Time Strategies for Accurate Indirect Occlusion*, Activision
technical report ATVI-TR-16-01, section "Ground-Truth based Ambient Occlusion (GTAO)": the way engines estimate
the ambient occlusion and the bent normal of each pixel from the depth buffer alone.  This module evaluates the
paper's formulation with NumPy in float64 (no denoising, no temporal accumulation), so that it can be measured
against a ray-cast reference (``tests/test_gtao.py``).

Formulation (the paper's slice decomposition)
---------------------------------------------
Ambient occlusion of a point x with unit normal n, viewed along the unit vector v toward the eye, is the
cosine-weighted visibility

    A(x) = 1/π ∫_Ω V(ω) (n·ω)⁺ dω .

Directions are parametrised by *slices*: planes containing v, at azimuth ψ ∈ [0, π) about v, with in-plane unit
tangent t(ψ) ⊥ v, and a signed angle θ ∈ (−π, π] from v inside the slice, ω = cos θ v + sin θ t, so that
dω = |sin θ| dθ dψ.  With n_p the normal projected into the slice plane and γ = atan2(n·t, n·v) its signed angle
from v, n·ω = |n_p| cos(θ − γ).  The depth buffer is a heightfield: on each side of v the directions from v
up to the highest point found (the horizon) are visible and everything beyond it is occluded.  With the two
horizon angles h₋, h₊ ∈ [0, π] measured from v on the −t and +t sides, clamped to the normal's hemisphere,

    h1 = max(−h₋, γ − π/2),   h2 = min(h₊, γ + π/2),

the paper's inner integral is

    â(h1, h2, γ) = ∫_{h1}^{h2} cos(θ − γ) |sin θ| dθ
                 = ¼(−cos(2h1 − γ) + cos γ + 2h1 sin γ) + ¼(−cos(2h2 − γ) + cos γ + 2h2 sin γ),

and A = 1/π ∫₀^π |n_p(ψ)| â dψ.  Unoccluded (h1 = γ − π/2, h2 = γ + π/2) a slice gives â = cos γ + γ sin γ,
and the ψ-integral of |n_p| (cos γ + γ sin γ) is π: A = 1.

Bent normal (derived here, the same slice decomposition).  The bent normal is the direction of the
cosine-weighted mean visible direction, b ∝ 1/π ∫_Ω V(ω) (n·ω)⁺ ω dω.  Per slice, the visible directions
contribute |n_p| ∫_{h1}^{h2} cos(θ − γ) |sin θ| (sin θ t + cos θ v) dθ = |n_p| (c_t t + c_v v) with

    c_t = F_t(h1) + F_t(h2) − 2 F_t(0),   F_t(θ) = cos γ sin³θ / 3 + sin γ (cos³θ / 3 − cos θ),
    c_v = F_v(h1) + F_v(h2) − 2 F_v(0),   F_v(θ) = (sin γ sin³θ − cos γ cos³θ) / 3,

F_t and F_v being antiderivatives of cos(θ − γ) sin²θ and cos(θ − γ) sin θ cos θ (the sign of |sin θ| flips at
θ = 0, hence the split at 0; the slice normal v × t receives nothing).  Unoccluded, the ψ-integral gives
1/π ∫_Ω (n·ω)⁺ ω dω = (2/3) n.

Estimator
---------
* **Slices.**  ``n_slices`` azimuths ψ_k = π (k + ξ) / n_slices, stratified, with one uniform rotation ξ per pixel
  drawn from ``seed`` (the paper's per-pixel rotation; no spatial or temporal filter).  Slices are uniform in
  azimuth *about v*, as the integral above requires; each slice's screen direction is the projection of its
  tangent t (for a perspective camera it differs from a uniform screen angle away from the optical axis, where a
  uniform screen angle would weight the azimuths unevenly).  The screen line through the pixel in that direction
  is exactly the slice plane's image.
* **Horizon search.**  On each side, ``n_steps`` samples at screen distances r_px · ((j + ζ)/n_steps)^step_power,
  j = 0 … n_steps − 1, with one uniform jitter ζ per (pixel, slice), where r_px is the projected ``radius``:
  radius · f / depth (f the focal length in pixels) for a perspective camera, radius · H / (2 half_height) for an
  orthographic one.  A sample takes the nearest pixel.  That pixel's point lies up to ~½ pixel off the slice
  plane, and on a tilted surface such an offset alone can raise the horizon (a flat floor would occlude itself),
  so the point is moved inside the pixel's tangent plane (G-buffer position and geometric normal) the least
  distance onto the slice plane: exact on planar faces; not moved when the move exceeds 4 pixel footprints (a
  tangent plane within ~10° of the slice plane).  Moving along the view ray instead (intersecting the sample's
  ray with the tangent plane) fails on faces seen edge-on, whose plane it extends far beyond the face.
  ``reconstruct="nearest"`` uses the pixel's point as it is (a point-sampled depth buffer).  The horizon cosine is the
  largest c = (w·v)/|w| of the sample vectors w = sample − x.  Samples outside the image, on uncovered
  (background) pixels or in the pixel itself are skipped: **what the image does not show does not occlude**.
* **Falloff.**  A sample at distance d = |w| has weight 1 for d ≤ (1 − falloff)·radius, falling linearly to 0 at
  d = radius (``falloff = 0``: a hard cut at ``radius``); its cosine is blended toward the hemisphere boundary's,
  c_low + weight·(c − c_low), so a sample beyond ``radius`` never occludes.
* **Thickness** (``thickness = β``, off by default).  A thin-occluder heuristic in the spirit of the paper's
  thickness heuristic: a sample below the running horizon pulls it down, c ← c − β (c − c_sample), so that a
  horizon raised by a thin object relaxes behind it.  β = None keeps the plain maximum (every surface of the
  depth buffer is a solid heightfield, as the formulation assumes).
* **Control variate** (default).  Both integrals are known for an unoccluded pixel (1 and (2/3) n), so the slices
  estimate only what is *missing*: A = 1 − 1/K Σ_k |n_p| (â_unoccluded − â), b = (2/3) n − 1/K Σ_k |n_p| (b_unoccluded −
  b_k).  The expectation over the rotation ξ is that of the paper's plain average 1/K Σ_k |n_p| â
  (``control_variate=False``), the variance lower, and an unoccluded pixel gives exactly A = 1, b = n whatever
  ``n_slices``.  ``ao`` is clipped to [0, 1]; a bent vector of length < 1e-12 (nothing visible) falls back to n.
* **Normals.**  The shading normal of the G-buffer is used; where it faces away from the eye (n·v < 0.01, at the
  silhouettes of smooth normals) it is first rotated toward v until n·v = 0.01 (engine practice), so |γ| < π/2.

What a screen-space estimate misses
-----------------------------------
Only what the depth buffer shows occludes, and it occludes as if solid all the way behind: a surface hidden from the
eye (the near wall of a pit seen from above, the ground under a teapot) casts no occlusion, an object's silhouette
casts occlusion as if it extended away from the eye without end, and an edge is located to within a pixel
footprint.  With a radius that covers every occluder GTAO agrees with a ray-cast reference to a mean 0.006 on the
crevice scene of :mod:`ibl_ref.rendering.scenes` and within 0.007 of the closed form beside a wall; the measured
numbers and their settings are in ``tests/test_gtao.py``.

Conventions
-----------
All computation is in the camera's view space (right, up, depth, as ``camera.to_camera``); ``radius`` is in world
units; ``bent_normal`` is returned in world space.  Outside ``gbuffer.mask``: ``ao`` is NaN and ``bent_normal`` is 0
(as ``GBuffer.normal``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import IBLError

__all__ = ["GTAOResult", "gtao", "slice_integrals", "RECONSTRUCT_MODES"]

#: How a sample's point is reconstructed from the nearest pixel (module docstring, "Horizon search").
RECONSTRUCT_MODES = ("plane", "nearest")

#: Shading normals are rotated toward the eye until n·v is at least this (module docstring, "Normals").
MIN_NDOTV = 0.01

#: A sample point is moved onto its slice plane only if that moves it at most this many pixel footprints.
PLANE_REACH_PX = 4.0


@dataclass
class GTAOResult:
    """Output of :func:`gtao`.

    Attributes
    ----------
    ao : (H, W) float64 — cosine-weighted visibility in [0, 1] (1 = unoccluded); NaN outside ``mask``.
    bent_normal : (H, W, 3) float64 — unit world-space bent normal; 0 outside ``mask``.
    mask : (H, W) bool — the pixels evaluated: the G-buffer's coverage (and ``where``).
    info : dict — the settings used (radius, n_slices, n_steps, …) and the number of pixels.
    """

    ao: np.ndarray
    bent_normal: np.ndarray
    mask: np.ndarray
    info: dict = field(default_factory=dict)


def slice_integrals(h1, h2, gamma):
    """The per-slice integrals of the module docstring: ``(â, c_t, c_v)``.

    Parameters
    ----------
    h1, h2 : array_like
        Clamped horizon angles (radians), h1 ≤ 0 ≤ h2, inside [γ − π/2, γ + π/2].
    gamma : array_like
        Signed angle of the projected normal from v (radians), |γ| < π/2.

    Returns
    -------
    a, c_t, c_v : ndarray
        ``a`` = ∫ cos(θ − γ)|sin θ| dθ over [h1, h2] (the paper's inner integral); ``c_t``, ``c_v`` the tangent and
        view components of ∫ cos(θ − γ)|sin θ| ω(θ) dθ (the slice's unnormalised bent vector, before |n_p|).

    Examples
    --------
    An unoccluded slice through the normal (γ = 0) gives â = 1 and the bent vector (2/3) v:

    >>> import numpy as np
    >>> a, ct, cv = slice_integrals(-np.pi / 2, np.pi / 2, 0.0)
    >>> round(float(a), 12), round(float(ct), 12), round(float(cv), 12)
    (1.0, 0.0, 0.666666666667)
    """
    h1, h2, g = (np.asarray(x, dtype=np.float64) for x in (h1, h2, gamma))
    cg, sg = np.cos(g), np.sin(g)

    def f_a(h):
        return -0.25 * np.cos(2.0 * h - g) + 0.5 * h * sg

    def f_t(h):
        s, c = np.sin(h), np.cos(h)
        return cg * s**3 / 3.0 + sg * (c**3 / 3.0 - c)

    def f_v(h):
        return (sg * np.sin(h) ** 3 - cg * np.cos(h) ** 3) / 3.0

    a = f_a(h1) + f_a(h2) + 0.5 * cg  # − 2 f_a(0) = +½ cos γ
    c_t = f_t(h1) + f_t(h2) + (4.0 / 3.0) * sg  # − 2 f_t(0) = +⁴⁄₃ sin γ
    c_v = f_v(h1) + f_v(h2) + (2.0 / 3.0) * cg  # − 2 f_v(0) = +⅔ cos γ
    return a, c_t, c_v


def _int_setting(value, name: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= int(value) <= hi:
        raise IBLError(f"gtao: {name} must be an integer in [{lo}, {hi}], got {value!r}")
    return int(value)


def _float_setting(value, name: str, lo: float, hi: float, lo_open: bool) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise IBLError(f"gtao: {name} must be a number, got {value!r}") from None
    ok = np.isfinite(x) and (x > lo if lo_open else x >= lo) and x <= hi
    if not ok:
        raise IBLError(f"gtao: {name} must be in {'(' if lo_open else '['}{lo:g}, {hi:g}], got {value!r}")
    return x


def _check_gbuffer(gbuffer, camera):
    """The G-buffer's arrays, checked against the camera's image size; IBLError otherwise."""
    try:
        H, W = int(camera.height), int(camera.width)
        basis = np.asarray(camera.basis, dtype=np.float64)
    except AttributeError:
        raise IBLError(f"gtao: camera must be a PerspectiveCamera or OrthographicCamera, got "
                       f"{type(camera).__name__}") from None
    try:
        mask = np.asarray(gbuffer.mask, dtype=bool)
        pos = np.asarray(gbuffer.position, dtype=np.float64)
        nrm = np.asarray(gbuffer.normal, dtype=np.float64)
        fn = np.asarray(gbuffer.face_normal, dtype=np.float64)
    except AttributeError:
        raise IBLError(f"gtao: gbuffer must be a GBuffer (mask, position, normal, face_normal), got "
                       f"{type(gbuffer).__name__}") from None
    if mask.shape != (H, W) or pos.shape != (H, W, 3) or nrm.shape != (H, W, 3) or fn.shape != (H, W, 3):
        raise IBLError(f"gtao: G-buffer of shape {mask.shape} does not match the camera's {H}x{W} image")
    if not mask.any():
        raise IBLError("gtao: the G-buffer's mask is empty (nothing covered)")
    if not (np.all(np.isfinite(pos[mask])) and np.all(np.isfinite(nrm[mask])) and np.all(np.isfinite(fn[mask]))):
        raise IBLError("gtao: G-buffer position/normal contain NaN or Inf on covered pixels")
    if not np.all(np.linalg.norm(nrm[mask], axis=-1) > 0):
        raise IBLError("gtao: G-buffer normal is zero on a covered pixel")
    return H, W, basis, mask, pos, nrm, fn


class _Frame:
    """The camera's projection in view space (right, up, depth): pixel footprint, screen direction of a vector."""

    def __init__(self, camera, H, W):
        self.H, self.W = H, W
        self.ortho = bool(getattr(camera, "is_orthographic", False))
        if self.ortho:
            self.hx, self.hy = float(camera.half_width), float(camera.half_height)
        else:
            t = float(camera.tan_half_fov_y)
            self.hx, self.hy = t * W / H, t  # half extents of the image plane at depth 1

    def pixel_size(self, depth):
        """World size of one pixel at view depth ``depth``."""
        return 2.0 * self.hy / self.H * (1.0 if self.ortho else depth)

    def screen_direction(self, p, t):
        """Unit screen direction (pixels, y down) of the image of p + s·t at s = 0 (p, t: (M, 3) view space)."""
        if self.ortho:
            dx, dy = t[:, 0] / self.hx * self.W, -t[:, 1] / self.hy * self.H
        else:
            z = p[:, 2]
            dx = (t[:, 0] - p[:, 0] * t[:, 2] / z) / self.hx * self.W
            dy = -(t[:, 1] - p[:, 1] * t[:, 2] / z) / self.hy * self.H
        ln = np.hypot(dx, dy)
        return dx / ln, dy / ln


def gtao(gbuffer, camera, *, radius: float = 0.5, n_slices: int = 8, n_steps: int = 16, step_power: float = 2.0,
         falloff: float = 0.0, thickness: float | None = None, control_variate: bool = True,
         reconstruct: str = "plane", seed: int = 0, bent_normals: bool = True, where=None) -> GTAOResult:
    """Ambient occlusion and bent normals of every covered pixel by GTAO's horizon search (module docstring).

    Parameters
    ----------
    gbuffer : GBuffer
        From :func:`ibl_ref.rendering.raster.rasterize` with the same ``camera`` (uses ``mask``, ``position``,
        ``normal``, ``face_normal``).
    camera : PerspectiveCamera | OrthographicCamera
    radius : float
        World-space radius of the search (> 0); samples farther than this from the pixel's point never occlude.
        Engines use about half a metre.
    n_slices : int
        Slices (azimuths about v) per pixel, ≥ 1.  Engines use 2–4 per frame with temporal accumulation.
    n_steps : int
        Samples per side of each slice, ≥ 1 (engines: 4–16).
    step_power : float
        Sample distribution along the slice, distance ∝ ((j + ζ)/n_steps)^step_power (> 0; 2 concentrates samples
        near the pixel, where the horizon matters most, as engines do).
    falloff : float
        Fraction of ``radius`` over which a sample's weight falls to 0, in [0, 1]; 0 = hard cut at ``radius``
        (engines use ~0.6 to hide the cut).
    thickness : float or None
        Thin-occluder heuristic β in (0, 1] (module docstring), None = off (the heightfield assumption).
    control_variate : bool
        Estimate the missing part against the known unoccluded integrals (default; exact for unoccluded pixels), or
        the paper's plain slice average (False).  Same expectation.
    reconstruct : {"plane", "nearest"}
        Sample point from the nearest pixel's tangent plane (exact on planar faces) or its position.
    seed : int
        Seed of the per-pixel slice rotations and step jitters (same seed → identical result).
    bent_normals : bool
        Compute ``bent_normal`` (else it is the shading normal, rotated toward the eye where it faces away).
    where : (H, W) bool, optional
        Evaluate only these covered pixels (the others are left NaN / 0 as if uncovered, but every covered pixel
        still occludes); default all of ``gbuffer.mask``.  Results do not depend on it: a pixel's rotation and
        jitters are drawn per pixel position.

    Returns
    -------
    GTAOResult
        ``ao`` (H, W) in [0, 1], NaN outside the mask (and ``where``); ``bent_normal`` (H, W, 3) unit world-space,
        0 outside; ``info`` the settings.

    Raises
    ------
    IBLError
        Empty mask (or ``where`` selecting no covered pixel), a G-buffer that does not match the camera, or a
        setting out of range.

    Examples
    --------
    A floor seen from above is its own horizon everywhere: no occlusion, and the bent normal is the normal.

    >>> import numpy as np, trimesh
    >>> from ibl_ref.rendering.camera import PerspectiveCamera
    >>> from ibl_ref.rendering.raster import rasterize
    >>> floor = trimesh.Trimesh([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], [[0, 2, 1], [0, 3, 2]],
    ...                         process=False)
    >>> cam = PerspectiveCamera(eye=[0.2, 1.5, 0.4], target=[0, 0, 0], up=[0, 1, 0], fov_y_deg=40, width=12,
    ...                         height=12)
    >>> res = gtao(rasterize(floor, cam), cam, radius=0.4, n_slices=3, n_steps=4)
    >>> bool(res.mask.all()), float(np.abs(res.ao - 1).max()) < 1e-9
    (True, True)
    >>> float(np.abs(res.bent_normal - [0, 1, 0]).max()) < 1e-9
    True
    """
    H, W, basis, mask, pos, nrm, fn = _check_gbuffer(gbuffer, camera)
    radius = _float_setting(radius, "radius", 0.0, np.inf, lo_open=True)
    n_slices = _int_setting(n_slices, "n_slices", 1, 4096)
    n_steps = _int_setting(n_steps, "n_steps", 1, 4096)
    step_power = _float_setting(step_power, "step_power", 0.0, 16.0, lo_open=True)
    falloff = _float_setting(falloff, "falloff", 0.0, 1.0, lo_open=False)
    if thickness is not None:
        thickness = _float_setting(thickness, "thickness", 0.0, 1.0, lo_open=True)
    if reconstruct not in RECONSTRUCT_MODES:
        raise IBLError(f"gtao: reconstruct must be one of {RECONSTRUCT_MODES}, got {reconstruct!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise IBLError(f"gtao: seed must be a non-negative integer, got {seed!r}")

    todo = mask
    if where is not None:
        where = np.asarray(where)
        if where.shape != mask.shape or where.dtype != bool:
            raise IBLError(f"gtao: where must be a ({H}, {W}) bool array, got {where.dtype} {where.shape}")
        todo = mask & where
        if not todo.any():
            raise IBLError("gtao: where selects no covered pixel")

    frame = _Frame(camera, H, W)
    rng = np.random.default_rng(int(seed))
    xi_img = rng.random((H, W))  # slice rotation per pixel
    zeta_img = rng.random((n_slices, H, W))  # step jitter per (slice, pixel)
    P_img = (pos - np.asarray(camera.eye, dtype=np.float64)) @ basis.T  # view space (right, up, depth)
    ii, jj = np.nonzero(todo)
    search = _HorizonSearch(frame, mask, P_img, None if reconstruct == "nearest" else fn @ basis.T, ii, jj, radius,
                            falloff, thickness)
    n = _facing_normals(nrm[ii, jj] @ basis.T, search.v)
    v = search.v
    # orthonormal frame about v: x_v from the camera's right axis (never parallel to v: fov < 180°)
    x_v = np.array([1.0, 0.0, 0.0]) - v[:, :1] * v
    x_v /= np.linalg.norm(x_v, axis=1, keepdims=True)
    y_v = np.cross(v, x_v)
    fractions = np.arange(n_steps)[:, None]

    ao_sum = np.zeros(len(ii))
    bent_sum = np.zeros((len(ii), 3))
    for k in range(n_slices):
        psi = np.pi * (k + xi_img[ii, jj]) / n_slices
        t = np.cos(psi)[:, None] * x_v + np.sin(psi)[:, None] * y_v
        nt, nv = np.einsum("mc,mc->m", n, t), np.einsum("mc,mc->m", n, v)
        np_len, gamma = np.hypot(nt, nv), np.arctan2(nt, nv)
        offsets = search.r_px * ((fractions + zeta_img[k, ii, jj]) / n_steps) ** step_power
        h_plus = search.horizon(t, offsets, -np.sin(gamma))
        h_minus = search.horizon(-t, offsets, np.sin(gamma))
        a_hat, c_t, c_v = slice_integrals(np.maximum(-h_minus, gamma - np.pi / 2),
                                          np.minimum(h_plus, gamma + np.pi / 2), gamma)
        if control_variate:
            a_u, ct_u, cv_u = slice_integrals(gamma - np.pi / 2, gamma + np.pi / 2, gamma)
            a_hat, c_t, c_v = a_u - a_hat, ct_u - c_t, cv_u - c_v  # the missing (occluded) part
        ao_sum += np_len * a_hat
        if bent_normals:
            bent_sum += np_len[:, None] * (c_t[:, None] * t + c_v[:, None] * v)
    if control_variate:
        ao_m, bent_m = 1.0 - ao_sum / n_slices, (2.0 / 3.0) * n - bent_sum / n_slices
    else:
        ao_m, bent_m = ao_sum / n_slices, bent_sum / n_slices
    if bent_normals:
        ln = np.linalg.norm(bent_m, axis=1, keepdims=True)
        bent_m = np.where(ln > 1e-12, bent_m / np.where(ln > 0, ln, 1.0), n)
    else:
        bent_m = n
    ao = np.full((H, W), np.nan)
    ao[ii, jj] = np.clip(ao_m, 0.0, 1.0)
    bent = np.zeros((H, W, 3))
    bent[ii, jj] = bent_m @ basis  # view → world
    info = dict(method="gtao", radius=radius, n_slices=n_slices, n_steps=n_steps, step_power=step_power,
                falloff=falloff, thickness=thickness, control_variate=bool(control_variate), reconstruct=reconstruct,
                seed=int(seed), bent_normals=bool(bent_normals), n_pixels=int(len(ii)),
                projection="orthographic" if frame.ortho else "perspective")
    return GTAOResult(ao=ao, bent_normal=bent, mask=todo.copy(), info=info)


def _facing_normals(n, v):
    """Unit normals (M, 3) rotated toward v where n·v < :data:`MIN_NDOTV` (module docstring, "Normals")."""
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    nv = np.einsum("mc,mc->m", n, v)
    low = nv < MIN_NDOTV
    if low.any():
        tang = n[low] - nv[low, None] * v[low]
        tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-300)
        n[low] = np.sqrt(1.0 - MIN_NDOTV**2) * tang + MIN_NDOTV * v[low]
    return n


class _HorizonSearch:
    """The horizon search of the pixels (ii, jj) over the G-buffer (module docstring, "Horizon search")."""

    def __init__(self, frame, mask, P_img, F_img, ii, jj, radius, falloff, thickness):
        self.frame, self.mask, self.P_img, self.F_img = frame, mask, P_img, F_img
        self.ii, self.jj = ii, jj
        self.radius, self.falloff, self.thickness = radius, falloff, thickness
        self.P = P_img[ii, jj]
        H = mask.shape[0]
        if frame.ortho:
            self.v = np.broadcast_to([0.0, 0.0, -1.0], self.P.shape).copy()
            self.r_px = np.full(len(ii), radius * H / (2.0 * frame.hy))
        else:
            self.v = -self.P / np.linalg.norm(self.P, axis=1, keepdims=True)
            self.r_px = radius * H / (2.0 * frame.hy * self.P[:, 2])

    def horizon(self, t, offsets, c_low):
        """Horizon angle from v (M,) on the side t (M, 3) of each slice, samples at ``offsets`` (n_steps, M) pixels;
        ``c_low`` (M,) the cosine of that side's hemisphere boundary (the horizon when nothing occludes)."""
        ux, uy = self.frame.screen_direction(self.P, t)
        qx = self.jj + 0.5 + offsets * ux
        qy = self.ii + 0.5 + offsets * uy
        a = np.cross(self.v, t)  # unit normal of the slice plane
        c = c_low.copy()
        for s in range(len(offsets)):
            sel, S = self._samples(qx[s], qy[s], a)
            if len(sel):
                c[sel] = self._update(c[sel], c_low[sel], S - self.P[sel], self.v[sel])
        return np.arccos(np.clip(c, -1.0, 1.0))

    def _samples(self, qx, qy, a):
        """Pixels with a usable sample at screen points (qx, qy) (M,): their indices and view-space sample points."""
        H, W = self.mask.shape
        si = np.floor(qy).astype(np.int64)
        sj = np.floor(qx).astype(np.int64)
        sel = np.flatnonzero((si >= 0) & (si < H) & (sj >= 0) & (sj < W) & ((si != self.ii) | (sj != self.jj)))
        sel = sel[self.mask[si[sel], sj[sel]]]
        X = self.P_img[si[sel], sj[sel]]
        if self.F_img is None or len(sel) == 0:
            return sel, X
        reach = PLANE_REACH_PX * self.frame.pixel_size(X[:, 2])
        return sel, _onto_slice(X, self.F_img[si[sel], sj[sel]], self.P[sel], a[sel], reach)

    def _update(self, c, c_low, w, v):
        """Running horizon cosines c after one sample vector w each (falloff, thickness: module docstring)."""
        d = np.linalg.norm(w, axis=1)
        cs = np.einsum("mc,mc->m", w, v) / np.where(d > 0, d, 1.0)
        if self.falloff > 0:
            wgt = np.clip((self.radius - d) / (self.falloff * self.radius), 0.0, 1.0)
        else:
            wgt = (d <= self.radius).astype(np.float64)
        cs = np.where(d > 0, c_low + wgt * (cs - c_low), c_low)
        if self.thickness is None:
            return np.maximum(c, cs)
        return np.where(cs > c, cs, c - self.thickness * (c - cs))


def _onto_slice(X, m, p, a, reach):
    """Sample points X (M, 3) with tangent-plane normals m moved, inside their tangent planes, the least distance onto
    the slice planes through p with unit normals a (module docstring); left where they are if that move is longer
    than ``reach`` (M,) or undefined (tangent plane parallel to the slice plane)."""
    u = a - np.einsum("mc,mc->m", a, m)[:, None] * m  # a projected into the tangent plane
    uu = np.einsum("mc,mc->m", u, u)
    off = np.einsum("mc,mc->m", a, X - p)  # signed distance of X from the slice plane
    with np.errstate(divide="ignore", invalid="ignore"):
        step = off / uu
    delta = -step[:, None] * u
    ok = (uu > 1e-12) & (np.linalg.norm(delta, axis=1) <= reach)
    return np.where(ok[:, None], X + delta, X)
