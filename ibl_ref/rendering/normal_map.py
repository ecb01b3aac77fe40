"""A procedural, seeded normal map: a height field on a surface's tangent plane whose gradient tilts the shading
normal, and its application to the pixels of a view.

Normal mapping changes the shading normal n and nothing else: the surface (its positions, its face normal n_g, and
so what occludes what) stays where it is.  That is the regime horizon occlusion was made for (Marmoset 2014,
"Horizon Occlusion for Normal Mapped Reflections", :mod:`ibl_ref.occlusion.horizon_occlusion`): once n tilts away
from n_g, the mirror direction R = 2(n·v)n − v can point below the geometric horizon, where the surface itself hides
the environment.

**The height field.**  On the plane through ``origin`` with unit tangent t and unit normal n_0 (the surface's),
a point p has the coordinates u = (p − origin)·t and w = (p − origin)·b along t and the bitangent b = n_0 × t (so
(t, b, n_0) is right-handed), and the height is a seeded sum of K plane waves,

    h(u, w) = Σ_k a_k sin(2π (u cos φ_k + w sin φ_k) / λ_k + δ_k),

with directions φ_k and phases δ_k uniform in [0, 2π) and wavelengths λ_k uniform in [λ_lo, λ_hi]
(``numpy.random.default_rng(seed)``, drawn in that order per wave).  The amplitudes give every wave the same largest
slope, a_k = λ_k tan θ_max / (2π K), so that |∇h| ≤ Σ_k 2π a_k / λ_k = tan θ_max.

**The normal.**  The surface p + h(u, w) n_0 of a plane (Blinn 1978, "Simulation of Wrinkled Surfaces": the bump
map's normal, here exact because the base surface is flat) has the tangent-space normal

    m = (−∂h/∂u, −∂h/∂w, 1) / √(1 + |∇h|²)     in the frame (t, b, n_0),

tilted from n_0 by atan|∇h| ≤ θ_max: the stated maximum tilt, never exceeded (reached only where every wave's slope
points the same way).  :meth:`NormalMap.perturb` turns m into world space about the pixel's shading normal n_s (the
rasterizer's interpolated vertex normal): n = m_t t' + m_b b' + m_n n_s, t' = t with its n_s component removed and
normalised, b' = n_s × t' — the tangent frame engines build per pixel.  With θ_max = 0 every m is exactly (0, 0, 1)
and n = n_s bit for bit.

**Where it is applied.**  A mesh carries its map in ``mesh.metadata["normal_map"]`` (:data:`METADATA_KEY`);
:func:`apply_normal_maps` replaces the shading normal (and the reflection vector r = 2(n·v)n − v) of the G-buffer's
pixels on such meshes, leaving the position, the depth and the face normal as they are.  The occlusion pipeline
calls it when it rasterizes a scene (:func:`ibl_ref.occlusion.image.scene_pixels`), so the methods, the oracle inputs,
GTAO's cosine weighting and the exact reference all see the perturbed n; the ray caster's rule that a direction below
the face's plane is blocked by the surface itself (n_g·ω < 0, :class:`ibl_ref.rendering.raycast.ShadowRays`) then
removes the part of a tilted lobe that dips under the geometric horizon.

Examples
--------
>>> import numpy as np
>>> from ibl_ref.rendering.normal_map import procedural_normal_map
>>> nm = procedural_normal_map(max_tilt_deg=30.0, seed=1)
>>> p = np.random.default_rng(0).uniform(-2, 2, (1000, 3)) * [1, 0, 1]
>>> n = nm.perturb(p, np.tile([0.0, 1.0, 0.0], (1000, 1)))
>>> bool(np.allclose(np.linalg.norm(n, axis=1), 1.0)), bool(np.degrees(np.arccos(n[:, 1].min())) <= 30.0)
(True, True)
>>> procedural_normal_map(max_tilt_deg=90)
Traceback (most recent call last):
...
ibl_ref.errors.IBLError: max_tilt_deg: expected a number in [0, 90), got 90
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import IBLError

__all__ = ["METADATA_KEY", "NormalMap", "procedural_normal_map", "apply_normal_maps", "mesh_normal_maps"]

#: the key of a mesh's ``metadata`` that holds its :class:`NormalMap`
METADATA_KEY = "normal_map"


def _unit(x, name):
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) == 0:
        raise IBLError(f"{name}: expected a finite non-zero 3-vector, got {x!r}")
    return a / np.linalg.norm(a)


@dataclass(frozen=True, eq=False)
class NormalMap:
    """A height field h(u, w) = Σ_k a_k sin(2π (u cos φ_k + w sin φ_k)/λ_k + δ_k) on a plane (module docstring).

    Attributes
    ----------
    origin : ndarray (3,)
        A point of the plane: u = w = 0 there.
    normal : ndarray (3,)
        Unit normal n_0 of the plane (the surface's geometric normal).
    tangent : ndarray (3,)
        Unit tangent t, ⊥ n_0; the bitangent is b = n_0 × t.
    direction : ndarray (K,)
        Wave directions φ_k (radians, in the (t, b) plane, from t).
    wavelength : ndarray (K,)
        λ_k (world units).
    phase : ndarray (K,)
        δ_k (radians).
    amplitude : ndarray (K,)
        a_k (world units).
    max_tilt_deg : float
        θ_max: the tilt of n from n_0 never exceeds it.
    seed : int or None
        The seed the waves were drawn from (:func:`procedural_normal_map`).
    """

    origin: np.ndarray
    normal: np.ndarray
    tangent: np.ndarray
    direction: np.ndarray
    wavelength: np.ndarray
    phase: np.ndarray
    amplitude: np.ndarray
    max_tilt_deg: float
    seed: int | None = None

    @property
    def bitangent(self) -> np.ndarray:
        """b = n_0 × t."""
        return np.cross(self.normal, self.tangent)

    def coordinates(self, points) -> np.ndarray:
        """(P, 2): (u, w) = ((p − origin)·t, (p − origin)·b) of points (P, 3)."""
        d = np.asarray(points, dtype=np.float64).reshape(-1, 3) - self.origin
        return np.stack([d @ self.tangent, d @ self.bitangent], axis=1)

    def _argument(self, uw):
        k = np.stack([np.cos(self.direction), np.sin(self.direction)], axis=1) / self.wavelength[:, None]  # (K, 2)
        return 2.0 * np.pi * (uw @ k.T) + self.phase, k

    def height(self, points) -> np.ndarray:
        """h at points (P, 3) (projected onto the plane), (P,)."""
        arg, _ = self._argument(self.coordinates(points))
        return np.sin(arg) @ self.amplitude

    def gradient(self, points) -> np.ndarray:
        """(P, 2): (∂h/∂u, ∂h/∂w) = Σ_k 2π a_k cos(·) (cos φ_k, sin φ_k)/λ_k."""
        arg, k = self._argument(self.coordinates(points))
        return (np.cos(arg) * self.amplitude) @ (2.0 * np.pi * k)

    def tangent_normals(self, points) -> np.ndarray:
        """(P, 3): the unit normal m = (−∂h/∂u, −∂h/∂w, 1)/√(1 + |∇h|²) in the frame (t, b, n_0)."""
        g = self.gradient(points)
        m = np.concatenate([-g, np.ones((len(g), 1))], axis=1)
        return m / np.linalg.norm(m, axis=1, keepdims=True)

    def perturb(self, points, normals) -> np.ndarray:
        """(P, 3): the mapped shading normals n = m_t t' + m_b b' + m_n n_s about the shading normals n_s
        (``normals``, (P, 3) unit) at ``points`` (module docstring)."""
        n_s = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        m = self.tangent_normals(points)
        t = self.tangent - (n_s @ self.tangent)[:, None] * n_s
        t_len = np.linalg.norm(t, axis=1, keepdims=True)
        if np.any(t_len < 1e-6):
            raise IBLError("normal map: a shading normal is parallel to the map's tangent; no tangent frame there")
        t = t / t_len
        b = np.cross(n_s, t)
        n = m[:, :1] * t + m[:, 1:2] * b + m[:, 2:] * n_s
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def params(self) -> dict:
        """JSON-ready description."""
        return dict(max_tilt_deg=self.max_tilt_deg, seed=self.seed, origin=self.origin.tolist(),
                    normal=self.normal.tolist(), tangent=self.tangent.tolist(),
                    waves=[dict(direction_rad=float(d), wavelength=float(lam), phase_rad=float(ph),
                                amplitude=float(a))
                           for d, lam, ph, a in zip(self.direction, self.wavelength, self.phase, self.amplitude)])


def procedural_normal_map(max_tilt_deg: float = 45.0, n_waves: int = 3, wavelengths=(0.3, 0.8), seed: int = 0,
                          *, origin=(0.0, 0.0, 0.0), normal=(0.0, 1.0, 0.0),
                          tangent=(1.0, 0.0, 0.0)) -> NormalMap:
    """A seeded :class:`NormalMap` of ``n_waves`` plane waves whose tilt never exceeds ``max_tilt_deg``
    (module docstring).

    Parameters
    ----------
    max_tilt_deg : float
        θ_max in [0, 90): the largest tilt of the mapped normal from the plane's normal (0: no perturbation).
    n_waves : int
        K in [1, 64].
    wavelengths : (float, float)
        Range (λ_lo, λ_hi) of the wavelengths, 0 < λ_lo ≤ λ_hi (world units).
    seed : int
        Seed of the directions, wavelengths and phases (same seed → the same map).
    origin, normal, tangent : 3-vectors
        The plane: a point of it, its normal n_0 (normalised) and the tangent t (its n_0 component removed,
        normalised); the bitangent is n_0 × t.  Default: the plane y = 0 with t = +x, b = −z.

    Returns
    -------
    NormalMap

    Raises
    ------
    IBLError
        A parameter out of range (one line naming it).
    """
    from ..synthetic.synthetic_meshes import _int_param, _pos_param

    try:
        theta = float(max_tilt_deg)
    except (TypeError, ValueError):
        theta = float("nan")
    if isinstance(max_tilt_deg, bool) or not (0.0 <= theta < 90.0):
        raise IBLError(f"max_tilt_deg: expected a number in [0, 90), got {max_tilt_deg!r}")
    K = _int_param(n_waves, "n_waves", 1, 64)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise IBLError(f"seed: expected a non-negative integer, got {seed!r}")
    if isinstance(wavelengths, (str, bytes)) or not hasattr(wavelengths, "__len__") or len(wavelengths) != 2:
        raise IBLError(f"wavelengths: expected two positive numbers (lo, hi), got {wavelengths!r}")
    lo, hi = (_pos_param(x, "wavelengths") for x in wavelengths)
    if lo > hi:
        raise IBLError(f"wavelengths: need lo <= hi, got {wavelengths!r}")
    n0 = _unit(normal, "normal")
    t = _unit(tangent, "tangent")
    t = t - (t @ n0) * n0
    if np.linalg.norm(t) < 1e-6:
        raise IBLError(f"tangent: must not be parallel to the normal, got {tangent!r}")
    t = t / np.linalg.norm(t)
    o = np.asarray(origin, dtype=np.float64)
    if o.shape != (3,) or not np.all(np.isfinite(o)):
        raise IBLError(f"origin: expected a finite 3-vector, got {origin!r}")
    rng = np.random.default_rng(int(seed))
    waves = np.array([[rng.uniform(0.0, 2 * np.pi), rng.uniform(lo, hi), rng.uniform(0.0, 2 * np.pi)]
                      for _ in range(K)])
    phi, lam, delta = waves.T
    amplitude = lam * np.tan(np.radians(theta)) / (2.0 * np.pi * K)
    return NormalMap(origin=o, normal=n0, tangent=t, direction=phi, wavelength=lam, phase=delta,
                     amplitude=amplitude, max_tilt_deg=theta, seed=int(seed))


def mesh_normal_maps(meshes) -> dict:
    """{mesh index: ``mesh.metadata["normal_map"]``} of the meshes that carry one (any form
    :func:`ibl_ref.rendering.raster.prepare_scene` accepts; a prepared ``Scene`` carries no metadata: {})."""
    from .raster import mesh_list

    items = mesh_list(meshes)
    if not isinstance(items, list):  # a prepared Scene
        return {}
    return {k: m.metadata.get(METADATA_KEY) for k, (m, _) in enumerate(items)
            if getattr(m, "metadata", None) and m.metadata.get(METADATA_KEY) is not None}


def apply_normal_maps(meshes, scene, gbuffer):
    """The G-buffer with the shading normals of every mesh that carries a :class:`NormalMap` perturbed by it.

    Parameters
    ----------
    meshes : the scene as given to :func:`ibl_ref.rendering.raster.prepare_scene` (a mesh, a list of meshes or of
        (mesh, material id) pairs; a prepared ``Scene`` carries no metadata and is returned unchanged)
    scene : Scene
        ``prepare_scene(meshes)`` (its ``mesh_index`` says which mesh each triangle came from).
    gbuffer : GBuffer
        :func:`ibl_ref.rendering.raster.rasterize` of ``scene``.

    Returns
    -------
    GBuffer
        ``gbuffer`` itself when no mesh has a map; else a copy whose ``normal`` and ``reflect`` = 2(n·v)n − v
        differ on the covered pixels of mapped meshes (position, depth, face normal and the rest unchanged; a map
        of zero amplitude changes nothing, not even the rounding of n).
    """
    maps = mesh_normal_maps(meshes)
    if not maps:
        return gbuffer
    normal, reflect = gbuffer.normal.copy(), gbuffer.reflect.copy()
    tri = gbuffer.triangle_id
    for k, nm in maps.items():
        if not isinstance(nm, NormalMap):
            raise IBLError(f"mesh {k}: metadata[{METADATA_KEY!r}] must be a NormalMap, got {type(nm).__name__}")
        if not np.any(nm.amplitude):  # θ_max = 0: the map changes nothing (not even the rounding of n)
            continue
        sel = gbuffer.mask & (scene.mesh_index[np.where(tri >= 0, tri, 0)] == k)
        if not sel.any():
            continue
        n = nm.perturb(gbuffer.position[sel], gbuffer.normal[sel])
        v = gbuffer.view[sel]
        normal[sel] = n
        reflect[sel] = 2.0 * np.sum(n * v, axis=1, keepdims=True) * n - v
    return replace(gbuffer, normal=normal, reflect=reflect)
