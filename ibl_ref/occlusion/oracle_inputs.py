"""Exact ("oracle") inputs of occlusion methods: binary visibility of stratified directions, traced once per view.

Occlusion methods (ambient occlusion, bent normals, visibility cones, SH transfer, the per-region visibility
``VIS_i`` of Knuth et al. 2014, Eq. 5) each approximate an integral of the binary visibility V(x, ω) of a surface
point x.  This module computes those integrals from the lab's own ray caster
(:class:`ibl_ref.rendering.raycast.ShadowRays`), each with an estimated error, from ONE set of traced rays per
(scene, view) that every quantity reuses (:class:`VisibilitySamples`, optionally cached on disk).

**Directions.**  The sphere is cut into the K = 6·n² cells of a cube of face size n = ``n_face`` (the lab's cube
layout, :mod:`ibl_ref.environment.envmap`; cell k is texel k of ``texel_directions(n).reshape(-1, 3)``), each with
its exact solid angle Ω_c (:func:`ibl_ref.environment.envmap.cube_solid_angles`).  A *set* holds one direction ω_c
per cell, drawn uniformly **in solid angle** inside the cell (exact inversion of the cell's solid-angle
distribution, :func:`jittered_directions`), so that Ω_c·f(ω_c) is an unbiased estimate of ∫_cell f dω and
Σ_c Ω_c f(ω_c) a stratified estimate of ∫ f dω.  ``n_sets`` independent sets (seeded: set s is drawn from
``numpy.random.default_rng([seed, s])``, so the first sets of a larger ``n_sets`` are the same) give independent
estimates; every reported error is the standard error of their mean, from their spread.  With the default 2 sets
that is a rough (one degree of freedom) estimate; more sets give a better one.  The directions of a set are shared
by all pixels (as the reference shares a cell's point within a block).

**Rays and horizons** (the conventions of the converged reference,
:mod:`ibl_ref.rendering.reference_converged`, whose shadow rays are the same :class:`ShadowRays`):

* a direction at or below the pixel's *shading* horizon (n·ω ≤ 0, n the shading normal) carries zero weight in
  every quantity here (the reference's integrands hold the factor [n·ω > 0]); it is not cast and its bit is 0;
* a direction above the shading horizon but at or below the *geometric* horizon (n_f·ω ≤ 0, n_f the face normal)
  is blocked by the point's own surface, not cast, bit 0 (``ShadowRays`` does the same for n_f·ω < 0);
* every other direction is one shadow ray of :class:`ShadowRays`: from ``x + eps·n_f + eps·ω`` with
  eps = :data:`ibl_ref.rendering.raycast.VISIBILITY_EPS` × scene radius = 1e-6 R, any hit of any triangle (both
  sides: Embree and the float64 checks are two-sided) blocks; with Embree every hit is re-checked in float64.

The reference, which multiplies a cell's whole weight by one ray, redraws that ray above the shading horizon in a
cell the horizon cuts (a ray below it would count the cell's lit weight as shadowed).  Here each sample carries its
own integrand value f(ω_c) — zero below the horizon — times Ω_c, which is unbiased as it is; no redraw is needed.

**Control variates.**  The unoccluded integrals are known in closed form, so every cosine-weighted quantity is
computed as (unoccluded exact value) − (estimate of the blocked part): with B = 1 − V and c = max(n·ω, 0),

* ambient occlusion  ao = 1 − ∫ B c/π dω;
* bent vector        ∫ V ω c dω = (2π/3) n − ∫ B ω c dω       (∫_{n·ω>0} ω (n·ω) dω = (2π/3) n);
* SH transfer        T_k = A_l Y_k(n)/π − ∫ B c/π Y_k dω      (Funk–Hecke for the clamped cosine, Ramamoorthi &
  Hanrahan 2001: A_0 = π, A_1 = 2π/3, A_l = 0 for odd l > 1, A_l = 2π (−1)^(l/2−1) / ((l+2)(l−1)) ·
  l! / (2^l ((l/2)!)²) for even l ≥ 2, i.e. A_2 = π/4, A_4 = −π/24; :func:`clamped_cosine_coefficients`).

An unoccluded point therefore gets exactly ao = 1, b = n and the closed-form transfer, with zero error; only the
cells that hold blocked directions carry sampling error.  The price: a fully occluded point gets ao = 0 only up to
the stratified estimate of ∫ c/π dω = 1 (ao is clipped to [0, 1]; measured inside a closed box, 20 normals:
RMS 1.6e-3, max 3.5e-3 at n_face 16, RMS 2.6e-4 at 32), and its bent normal is defined as n (below).

**Accuracy** (measured, ``tests/test_oracle_inputs.py``'s coaxial disk R = h, n_face 16, 2 sets, 800 seeds): ao
errs by 2.4e-3 RMS against the exact form factor, with no detectable bias (mean 1.6e-5 ± 8.5e-5), and the reported
error is 2.5e-3 RMS: the estimate is calibrated on average, although each 2-set value is only a rough one.

**SH transfer matrix** (Sloan, Kautz & Snyder 2002, Sec. 5, glossy transfer; :func:`sh_transfer_matrix`):
M_ij = ∫ V(ω) Y_i(ω) Y_j(ω) dω with V the bits above, so V = 0 at and below the shading horizon (as in every
quantity here: the reference's integrands hold [n·ω > 0], light from behind the shading surface does not reach
it).  M is therefore never the identity, not even at an unoccluded point (there it is the projection of the
hemisphere n·ω > 0).  No control variate (the rotated hemisphere's matrix has no closed form here): per set the
plain stratified sum Σ_c Ω_c V_c Y_i(ω_c) Y_j(ω_c), every error from the spread of the sets.

**Region visibility** (the paper's per-region visibility made exact, Knuth et al. 2014, Eq. 5: ``VIS_i`` of
region i): per cell c and region i, w_ci = Σ_{texels t ∈ c, label i} Y_t Ω_t (Rec. 709 luminance Y,
:func:`ibl_ref.knuth2014.median_cut.luminance`; exact texel solid angles), and per set
``VIS_i = Σ_c V_c w_ci [n·ω_c > 0] / Σ_c w_ci [n·ω_c > 0]``: the radiance-weighted visible fraction of the part of
region i above the shading horizon (ω_c the set's direction of cell c), 1 where that part is empty or dark.

Storage: V packed with :func:`numpy.packbits` along the cells — P pixels × 6n² cells × n_sets bits (2·1536/8 =
384 bytes per pixel at the defaults).  Cache: :func:`trace_visibility` with ``cache_dir`` stores the bits in an
``.npz`` named by a SHA-256 of everything they depend on, written atomically (:func:`ibl_ref.atomic.atomic_path`).
"""

from __future__ import annotations

import hashlib
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..environment.envmap import cube_solid_angles
from ..environment.envmap import face_frames
from ..environment.envmap import rect_solid_angle
from ..errors import IBLError, IBLWarning, as_path
from ..limits import check_allocation
from ..limits import positive_int
from ..progress import track
from ..rendering.raster import prepare_scene
from ..rendering.raycast import ShadowRays
from ..rendering.raycast import resolve_shadow_backend

__all__ = [
    "VisibilitySamples",
    "trace_visibility",
    "jittered_directions",
    "ambient_occlusion",
    "bent_normal",
    "visibility_cone",
    "sh_transfer",
    "clamped_cosine_coefficients",
    "sh_transfer_matrix",
    "region_visibility",
    "CACHE_VERSION",
    "UNIT_TOL",
]

#: part of every cache key: bump when the traced bits for the same inputs change (sampling, conventions)
CACHE_VERSION = "ibl_ref.occlusion.oracle_inputs/1"
#: normals must have unit length within this (they are renormalised exactly before use)
UNIT_TOL = 1e-6
#: (pixel, cell) pairs per vectorised step when tracing and when integrating (bounds the temporaries)
_PAIRS_PER_STEP = 1 << 19
#: bisection steps of the inverse solid-angle distribution (the interval shrinks below float64 spacing)
_BISECT_STEPS = 64


# ------------------------------------------------------------------------------------------------
# the samples
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class VisibilitySamples:
    """Binary visibility of P surface points toward ``n_sets`` stratified sets of 6·n² directions (module docstring).

    Attributes
    ----------
    bits : ndarray, uint8, shape (n_sets, P, ceil(6 n² / 8))
        V packed along the cells (:func:`numpy.packbits`, big-endian bit order): 1 = the ray is free; 0 = blocked,
        below the geometric horizon, or below the shading horizon (not cast: zero weight everywhere).
    normals, face_normals : ndarray, float64, shape (P, 3)
        Unit shading and geometric normals of the points (renormalised copies of the inputs).
    directions : ndarray, float64, shape (n_sets, 6 n², 3)
        The unit direction of every cell per set (:func:`jittered_directions`, regenerated from the seed).
    solid_angles : ndarray, float64, shape (6 n²,)
        The exact solid angle of every cell (sr; sums to 4π).
    n_face, n_sets, seed : int
    backend : str
        The ray caster that traced the bits (``"embree"`` or ``"exact"``).
    n_rays : int
        Shadow rays cast by the call that returned this object (0 when it came from the cache).
    from_cache : bool
    key : str
        SHA-256 (hex) of the inputs the bits depend on (the cache file's name).
    """

    bits: np.ndarray
    normals: np.ndarray
    face_normals: np.ndarray
    directions: np.ndarray
    solid_angles: np.ndarray
    n_face: int
    n_sets: int
    seed: int
    backend: str
    n_rays: int
    from_cache: bool
    key: str

    @property
    def n_pixels(self) -> int:
        """P, the number of surface points."""
        return int(self.bits.shape[1])

    @property
    def n_cells(self) -> int:
        """K = 6·n_face², the number of direction cells."""
        return int(self.solid_angles.shape[0])

    def visibility(self, s: int, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Unpacked V of set ``s`` for pixels ``start:stop``: uint8 (stop − start, K)."""
        return np.unpackbits(self.bits[s, start:stop], axis=-1, count=self.n_cells)


# ------------------------------------------------------------------------------------------------
# directions: one uniform-in-solid-angle point per cube cell
# ------------------------------------------------------------------------------------------------
def _cell_rects(n: int, k: np.ndarray):
    """Face, and face-plane rectangle (u0, u1, v0, v1) of cells ``k`` (texel order) of face size n."""
    f, i, j = k // (n * n), (k // n) % n, k % n
    e = np.linspace(-1.0, 1.0, n + 1)  # the texel edges of texel_solid_angles
    return f, e[j], e[j + 1], e[i], e[i + 1]


def _uniform_in_cells(n: int, xi: np.ndarray, cells: np.ndarray | None = None) -> np.ndarray:
    """Unit directions (M, 3), uniform in solid angle inside cells ``cells`` (M,) of face size n (default: every
    cell once, in texel order), from uniforms xi (M, 2).

    The solid-angle density on a face plane is (1 + u² + v²)^(−3/2) du dv.  u is drawn by inverting its marginal,
    Ω([u0, u] × [v0, v1]) / Ω_cell (bisection on the exact rectangle solid angle); v given u by inverting the
    conditional in closed form: with a² = 1 + u², ∫ (a² + v²)^(−3/2) dv = v / (a² √(a² + v²)), so
    g = v/√(a² + v²) is uniform between its values at v0 and v1 and v = a g / √(1 − g²).
    """
    f, u0, u1, v0, v1 = _cell_rects(n, np.arange(6 * n * n) if cells is None else np.asarray(cells))
    target = xi[:, 0] * rect_solid_angle(u0, u1, v0, v1)
    lo, hi = u0.copy(), u1.copy()
    for _ in range(_BISECT_STEPS):
        mid = 0.5 * (lo + hi)
        below = rect_solid_angle(u0, mid, v0, v1) < target
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    u = 0.5 * (lo + hi)
    a = np.sqrt(1.0 + u * u)
    g0, g1 = v0 / np.sqrt(a * a + v0 * v0), v1 / np.sqrt(a * a + v1 * v1)
    g = g0 + xi[:, 1] * (g1 - g0)
    v = np.clip(a * g / np.sqrt(1.0 - g * g), v0, v1)
    F = face_frames("openexr")[f]
    d = F[:, 0, :] + u[:, None] * F[:, 1, :] + v[:, None] * F[:, 2, :]
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def jittered_directions(n_face: int = 16, n_sets: int = 2, seed: int = 0) -> np.ndarray:
    """The stratified direction sets of :func:`trace_visibility`: one direction per cube cell per set.

    Parameters
    ----------
    n_face : int
        Face size of the cell cube (K = 6·n_face² cells, in the texel order of
        :func:`ibl_ref.environment.envmap.texel_directions`).
    n_sets : int
        Independent sets; set s is drawn from ``numpy.random.default_rng([seed, s])``.
    seed : int
        Non-negative.

    Returns
    -------
    ndarray, float64, shape (n_sets, K, 3)
        Unit directions, each uniform in solid angle inside its cell.

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.environment.envmap import direction_to_texel
    >>> from ibl_ref.occlusion.oracle_inputs import jittered_directions
    >>> d = jittered_directions(4, n_sets=2, seed=7)
    >>> d.shape
    (2, 96, 3)
    >>> f, r, c = direction_to_texel(d[0], 4)  # every direction lies in its own cell
    >>> bool(np.array_equal((f * 4 + r) * 4 + c, np.arange(96)))
    True
    """
    n_face = positive_int("n_face", n_face)
    n_sets = positive_int("n_sets", n_sets)
    seed = _seed(seed)
    K = 6 * n_face * n_face
    out = np.empty((n_sets, K, 3))
    for s in range(n_sets):
        out[s] = _uniform_in_cells(n_face, np.random.default_rng([seed, s]).random((K, 2)))
    return out


# ------------------------------------------------------------------------------------------------
# input checks
# ------------------------------------------------------------------------------------------------
def _seed(v) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or int(v) < 0:
        raise IBLError(f"seed must be a non-negative integer, got {v!r}")
    return int(v)


def _vectors(name: str, x, P: int | None, unit: bool) -> np.ndarray:
    try:
        a = np.array(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise IBLError(f"{name}: not an array of numbers ({exc})") from None
    if a.ndim != 2 or a.shape[1] != 3:
        raise IBLError(f"{name}: expected shape (P, 3), got {a.shape}")
    if P is not None and len(a) != P:
        raise IBLError(f"{name}: {len(a)} rows for {P} points")
    if not np.all(np.isfinite(a)):
        raise IBLError(f"{name}: contains NaN or Inf")
    if unit and len(a):
        ln = np.linalg.norm(a, axis=1)
        dev = float(np.max(np.abs(ln - 1.0)))
        if dev > UNIT_TOL:
            raise IBLError(f"{name}: not unit vectors (largest | |n| - 1 | = {dev:.3g} > {UNIT_TOL:g})")
        a = a / ln[:, None]
    return a


def _check_samples(vs) -> VisibilitySamples:
    if not isinstance(vs, VisibilitySamples):
        raise IBLError(f"expected VisibilitySamples (from trace_visibility), got {type(vs).__name__}")
    return vs


# ------------------------------------------------------------------------------------------------
# tracing and the cache
# ------------------------------------------------------------------------------------------------
def _cache_key(scene, points, normals, face_normals, n_face, n_sets, seed) -> str:
    h = hashlib.sha256()
    h.update(CACHE_VERSION.encode())
    for a in (scene.vertices, scene.faces, points, normals, face_normals):
        a = np.ascontiguousarray(a, dtype=np.int64 if a.dtype.kind in "iu" else np.float64)
        h.update(repr(a.shape).encode())
        h.update(a.tobytes())
    h.update(f"n_face={n_face};n_sets={n_sets};seed={seed}".encode())
    return h.hexdigest()


def _cache_file(cache_dir, key: str) -> Path:
    return as_path(cache_dir, "cache_dir") / f"oracle_visibility_{key}.npz"


def _load_cached(path: Path, key: str, shape) -> tuple | None:
    """(bits, backend) from a cache file written for ``key``; None (with a warning) if it is unreadable."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                raise IBLError("its key differs from its name")
            bits = np.array(z["bits"])
            backend = str(z["backend"])
        if bits.shape != shape or bits.dtype != np.uint8:
            raise IBLError(f"bits of shape {bits.shape} ({bits.dtype}), expected {shape} (uint8)")
    except Exception as exc:  # any unreadable file: trace again, never crash on the cache
        warnings.warn(f"oracle visibility cache {path}: unreadable ({exc}); tracing again", IBLWarning, stacklevel=3)
        return None
    return bits, backend


def _save_cached(path: Path, key: str, bits: np.ndarray, backend: str, n_face: int, n_sets: int, seed: int) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, key=np.array(key), bits=bits, backend=np.array(backend), n_face=n_face, n_sets=n_sets,
                     seed=seed, version=np.array(CACHE_VERSION))


def _trace(scene, backend, points, normals, face_normals, dirs, progress) -> tuple:
    """Packed bits (S, P, ⌈K/8⌉) and the number of rays cast (module docstring: which directions are cast)."""
    S, K, _ = dirs.shape
    P = len(points)
    bits = np.zeros((S, P, -(-K // 8)), dtype=np.uint8)
    caster = ShadowRays(scene, backend)
    B = max(1, _PAIRS_PER_STEP // K)
    steps = [(s, a) for s in range(S) for a in range(0, P, B)]
    for s, a in track(steps, "oracle visibility", unit="chunk", enabled=progress):
        p_, d = points[a:a + B], dirs[s]
        cast = (normals[a:a + B] @ d.T > 0) & (face_normals[a:a + B] @ d.T > 0)
        pi, ci = np.nonzero(cast)
        V = np.zeros(cast.shape, dtype=np.uint8)
        if len(pi):
            V[pi, ci] = caster.visibility(p_[pi], face_normals[a:a + B][pi], d[ci], groups=ci)
        bits[s, a:a + B] = np.packbits(V, axis=1)
    return bits, int(caster.n_rays)


def trace_visibility(scene, points, normals, face_normals, *, n_face: int = 16, n_sets: int = 2, seed: int = 0,
                     ray_backend: str = "auto", cache_dir=None, progress: bool = False) -> VisibilitySamples:
    """Trace the binary visibility of surface points toward stratified direction sets (module docstring).

    Parameters
    ----------
    scene : Scene or trimesh.Trimesh or list of meshes
        The occluders: what :func:`ibl_ref.rendering.raster.prepare_scene` returns, or anything it accepts.
    points : array_like, shape (P, 3)
        Surface points (world units), finite.
    normals, face_normals : array_like, shape (P, 3)
        Unit shading normals n (weights, shading horizon) and unit geometric normals n_f (geometric horizon, ray
        offset), finite, unit length within :data:`UNIT_TOL`.
    n_face : int
        Face size of the cell cube: 6·n_face² directions per set.
    n_sets : int
        Independent stratified sets (the errors are their standard error; ≥ 2 for an error estimate).
    seed : int
        Seed of the sets (:func:`jittered_directions`).
    ray_backend : {"auto", "embree", "exact"}
        :class:`ibl_ref.rendering.raycast.ShadowRays` backend.
    cache_dir : str or os.PathLike, optional
        Folder of the ``.npz`` cache: the file ``oracle_visibility_<key>.npz`` (key: SHA-256 of the scene's
        vertices and faces, the points, normals and face normals, ``n_face``, ``n_sets``, ``seed`` and
        :data:`CACHE_VERSION`) is reused when it exists; a corrupt one is traced again with a warning and
        replaced; where the file cannot be written (a read-only folder, a file in the folder's place) the traced
        visibility is used with a warning, uncached.  No other file is written.
    progress : bool
        Report progress (:func:`ibl_ref.progress.track`).

    Returns
    -------
    VisibilitySamples

    Raises
    ------
    IBLError
        Non-finite or mis-shaped points or normals, non-unit normals, ``n_face``/``n_sets`` < 1, a bad seed or
        backend; :class:`ibl_ref.errors.MeshError` for a bad scene.

    Examples
    --------
    A point on an open floor sees its whole upper hemisphere:

    >>> import trimesh
    >>> from ibl_ref.occlusion.oracle_inputs import trace_visibility, ambient_occlusion
    >>> floor = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    >>> vs = trace_visibility(floor, [[0, 0, 0]], [[0, 0, 1]], [[0, 0, 1]], n_face=4)
    >>> vs.bits.shape  # 2 sets, 1 point, 96 cells in 12 bytes
    (2, 1, 12)
    >>> ao, err = ambient_occlusion(vs)
    >>> ao.tolist(), err.tolist()
    ([1.0], [0.0])
    """
    n_face = positive_int("n_face", n_face)
    n_sets = positive_int("n_sets", n_sets)
    seed = _seed(seed)
    backend = resolve_shadow_backend(ray_backend)
    pts = _vectors("points", points, None, unit=False)
    nrm = _vectors("normals", normals, len(pts), unit=True)
    fn = _vectors("face_normals", face_normals, len(pts), unit=True)
    sc = prepare_scene(scene, warn=False)
    key = _cache_key(sc, pts, np.asarray(normals, dtype=np.float64), np.asarray(face_normals, dtype=np.float64),
                     n_face, n_sets, seed)
    dirs = jittered_directions(n_face, n_sets, seed)
    omega = np.ascontiguousarray(cube_solid_angles(n_face)).reshape(-1)
    K = 6 * n_face * n_face
    shape = (n_sets, len(pts), -(-K // 8))
    check_allocation(math.prod(shape), f"the visibility bits of {len(pts)} points x {K} cells x {n_sets} sets",
                     "trace_visibility")
    path = None if cache_dir is None else _cache_file(cache_dir, key)
    got = _load_cached(path, key, shape) if path is not None and path.is_file() else None
    if got is not None:
        bits, used, n_rays, cached = got[0], got[1], 0, True
    else:
        bits, n_rays = _trace(sc, backend, pts, nrm, fn, dirs, progress)
        used, cached = backend, False
        if path is not None:
            try:
                _save_cached(path, key, bits, backend, n_face, n_sets, seed)
            except (OSError, IBLError) as exc:  # an unwritable cache folder: keep the traced bits, say so once
                warnings.warn(f"oracle visibility cache: not written ({exc}); the traced visibility is used "
                              f"uncached", IBLWarning, stacklevel=2)
    for a in (bits, nrm, fn, dirs, omega):
        a.setflags(write=False)
    return VisibilitySamples(bits=bits, normals=nrm, face_normals=fn, directions=dirs, solid_angles=omega,
                             n_face=n_face, n_sets=n_sets, seed=seed, backend=used, n_rays=n_rays,
                             from_cache=cached, key=key)


# ------------------------------------------------------------------------------------------------
# integrals
# ------------------------------------------------------------------------------------------------
def _chunks(vs):
    B = max(1, _PAIRS_PER_STEP // vs.n_cells)
    return [(a, min(a + B, vs.n_pixels)) for a in range(0, vs.n_pixels, B)]


def _blocked(vs, s: int, a: int, b: int):
    """Per (pixel, cell) of set s, pixels a:b: the blocked cosine weight Ω_c (1 − V) max(n·ω_c, 0) and the
    visible one Ω_c V max(n·ω_c, 0)."""
    c = np.maximum(vs.normals[a:b] @ vs.directions[s].T, 0.0) * vs.solid_angles[None, :]
    V = vs.visibility(s, a, b).astype(bool)
    return np.where(V, 0.0, c), np.where(V, c, 0.0)


def _mean_and_stderr(per_set: np.ndarray):
    """Mean over axis 0 and its standard error from the spread of the sets (NaN for one set)."""
    S = per_set.shape[0]
    mean = per_set.mean(axis=0)
    if S < 2:
        return mean, np.full(mean.shape, np.nan)
    return mean, per_set.std(axis=0, ddof=1) / math.sqrt(S)


def ambient_occlusion(vs: VisibilitySamples):
    """Ambient occlusion ao = ∫ V max(n·ω, 0)/π dω, as 1 − (the blocked part) (control variate, module docstring).

    Parameters
    ----------
    vs : VisibilitySamples

    Returns
    -------
    ao : ndarray, float64, shape (P,)
        Mean over the sets, clipped to [0, 1]; exactly 1 where no weighted direction is blocked.
    err : ndarray, float64, shape (P,)
        Standard error of the mean from the spread of the sets (NaN with one set; 0 where every set agrees).

    Examples
    --------
    A point on the floor inside a closed box sees nothing: ao is 0 up to the stratified estimate of
    ∫ max(n·ω, 0)/π dω = 1 (the control variate's price, module docstring):

    >>> import trimesh
    >>> from ibl_ref.occlusion.oracle_inputs import trace_visibility, ambient_occlusion
    >>> box = trimesh.creation.box(extents=(2, 2, 2))
    >>> ao, err = ambient_occlusion(trace_visibility(box, [[0, 0, -1]], [[0, 0, 1]], [[0, 0, 1]], n_face=16))
    >>> bool(ao[0] < 0.005)
    True
    """
    vs = _check_samples(vs)
    per = np.empty((vs.n_sets, vs.n_pixels))
    for s in range(vs.n_sets):
        for a, b in _chunks(vs):
            per[s, a:b] = 1.0 - _blocked(vs, s, a, b)[0].sum(axis=1) / np.pi
    ao, err = _mean_and_stderr(per)
    return np.clip(ao, 0.0, 1.0), err


def _bent_vectors(vs):
    """Per set: the bent vector (2π/3) n − ∫ B ω c dω (S, P, 3) and whether the set saw any weighted visible
    direction."""
    vec = np.empty((vs.n_sets, vs.n_pixels, 3))
    seen = np.zeros((vs.n_sets, vs.n_pixels), dtype=bool)
    for s in range(vs.n_sets):
        for a, b in _chunks(vs):
            blk, vis = _blocked(vs, s, a, b)
            vec[s, a:b] = (2.0 * np.pi / 3.0) * vs.normals[a:b] - blk @ vs.directions[s]
            seen[s, a:b] = (vis > 0).any(axis=1)
    return vec, seen


def _unit(v, fallback):
    ln = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(ln > 0, v / np.where(ln > 0, ln, 1.0), fallback)


def bent_normal(vs: VisibilitySamples):
    """Bent normal b = normalize(∫ V ω max(n·ω, 0) dω), the cosine-weighted mean visible direction.

    The integral is (2π/3) n − ∫ (1 − V) ω max(n·ω, 0) dω (control variate: an unoccluded point gets exactly n;
    ∫_{n·ω>0} ω (n·ω) dω = (2π/3) n).  A set in which no weighted direction of a pixel is visible gives that pixel
    b = n (a fully occluded point has no visible direction to average; n is the convention), as does a vector of zero
    length.

    Parameters
    ----------
    vs : VisibilitySamples

    Returns
    -------
    b : ndarray, float64, shape (P, 3)
        Unit bent normals: the normalised mean of the sets' vectors.
    err_angle_rad : ndarray, float64, shape (P,)
        Standard error of the direction: √(Σ_s θ_s² / (S (S − 1))), θ_s the angle between set s's direction and b
        (NaN with one set).

    Examples
    --------
    Inside a closed box no direction is visible, and the bent normal is n by convention:

    >>> import trimesh
    >>> from ibl_ref.occlusion.oracle_inputs import trace_visibility, bent_normal
    >>> box = trimesh.creation.box(extents=(2, 2, 2))
    >>> b, err = bent_normal(trace_visibility(box, [[0, 0, -1]], [[0.6, 0, 0.8]], [[0, 0, 1]], n_face=4))
    >>> b.tolist(), err.tolist()
    ([[0.6, 0.0, 0.8]], [0.0])
    """
    vs = _check_samples(vs)
    vec, seen = _bent_vectors(vs)
    n = vs.normals
    per = np.where(seen[..., None], _unit(vec, n[None]), n[None])
    b = _unit(per.mean(axis=0), n)
    S = vs.n_sets
    if S < 2:
        return b, np.full(vs.n_pixels, np.nan)
    theta = np.arccos(np.clip(np.einsum("spc,pc->sp", per, b), -1.0, 1.0))
    return b, np.sqrt((theta ** 2).sum(axis=0) / (S * (S - 1)))


def visibility_cone(vs: VisibilitySamples):
    """Visibility cone: axis = bent normal, cos θ_v = √(1 − ao).

    The convention of Jimenez et al. (2016, GTSO): a cone of half-angle θ about n holds the cosine-weighted
    visibility ∫_cone (n·ω)/π dω = sin²θ, so the cone with the point's ambient occlusion has cos θ = √(1 − ao).

    Parameters
    ----------
    vs : VisibilitySamples

    Returns
    -------
    axis : ndarray, float64, shape (P, 3)
        :func:`bent_normal`.
    cos_aperture : ndarray, float64, shape (P,)
        √(1 − ao) with ao of :func:`ambient_occlusion` (0 for an unoccluded point: the hemisphere).

    Examples
    --------
    >>> import trimesh
    >>> from ibl_ref.occlusion.oracle_inputs import trace_visibility, visibility_cone
    >>> floor = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    >>> vs = trace_visibility(floor, [[0, 0, 0]], [[0, 0, 1]], [[0, 0, 1]], n_face=4)
    >>> axis, cos_ap = visibility_cone(vs)
    >>> axis.tolist(), cos_ap.tolist()
    ([[0.0, 0.0, 1.0]], [0.0])
    """
    axis, _ = bent_normal(vs)
    ao, _ = ambient_occlusion(vs)
    return axis, np.sqrt(np.clip(1.0 - ao, 0.0, 1.0))


def clamped_cosine_coefficients(order: int) -> np.ndarray:
    """Â_l = 2π ∫_0^1 t P_l(t) dt, l < ``order``: ∫ max(n·ω, 0) Y_lm(ω) dω = Â_l Y_lm(n) (Funk–Hecke).

    Ramamoorthi & Hanrahan (2001): Â_0 = π, Â_1 = 2π/3, Â_l = 0 for odd l > 1 and, for even l ≥ 2,
    Â_l = 2π (−1)^(l/2 − 1) / ((l + 2)(l − 1)) · l! / (2^l ((l/2)!)²).

    Parameters
    ----------
    order : int
        Number of SH bands (l = 0 … order − 1).

    Returns
    -------
    ndarray, float64, shape (order,)

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.occlusion.oracle_inputs import clamped_cosine_coefficients
    >>> (clamped_cosine_coefficients(5) / np.pi).round(6).tolist()
    [1.0, 0.666667, 0.25, 0.0, -0.041667]
    """
    order = positive_int("order", order)
    A = np.zeros(order)
    for ell in range(order):
        if ell == 0:
            A[ell] = np.pi
        elif ell == 1:
            A[ell] = 2.0 * np.pi / 3.0
        elif ell % 2 == 0:
            A[ell] = (2.0 * np.pi * (-1) ** (ell // 2 - 1) / ((ell + 2) * (ell - 1))
                      * math.factorial(ell) / (2 ** ell * math.factorial(ell // 2) ** 2))
    return A


def sh_transfer(vs: VisibilitySamples, order: int):
    """Shadowed diffuse transfer T_k = ∫ V max(n·ω, 0)/π Y_k(ω) dω in the lab's real SH basis.

    Basis: :func:`ibl_ref.groundtruth.sh_basis.real_sh` (real orthonormal, no Condon–Shortley phase, index
    k = l² + l + m, l < ``order``).  Computed as the unoccluded transfer Â_l Y_k(n)/π
    (:func:`clamped_cosine_coefficients`) minus the blocked part (control variate, module docstring).  Lighting
    with SH coefficients L_k then gives ∫ L V max(n·ω, 0)/π dω = Σ_k L_k T_k (the irradiance / π).

    Parameters
    ----------
    vs : VisibilitySamples
    order : int
        Number of bands: 3 → 9 coefficients, 5 → 25.

    Returns
    -------
    T : ndarray, float64, shape (P, order²)
    err : ndarray, float64, shape (P, order²)
        Standard error of the mean from the spread of the sets (NaN with one set).

    Examples
    --------
    Unoccluded, normal +z: T_00 = Y_00 = 1/(2√π), T_10 (∝ z) = (2/3)·√(3/(4π)):

    >>> import trimesh
    >>> from ibl_ref.occlusion.oracle_inputs import trace_visibility, sh_transfer
    >>> floor = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    >>> vs = trace_visibility(floor, [[0, 0, 0]], [[0, 0, 1]], [[0, 0, 1]], n_face=4)
    >>> T, err = sh_transfer(vs, 3)
    >>> T[0, :4].round(6).tolist(), float(err.max())
    ([0.282095, 0.0, 0.325735, 0.0], 0.0)
    """
    from ..groundtruth.sh_basis import real_sh

    vs = _check_samples(vs)
    order = positive_int("order", order)
    L = order - 1
    A = clamped_cosine_coefficients(order)
    band = np.repeat(np.arange(order), 2 * np.arange(order) + 1)
    T0 = real_sh(vs.normals, L) * (A[band] / np.pi)[None, :]
    per = np.empty((vs.n_sets, vs.n_pixels, order * order))
    for s in range(vs.n_sets):
        Y = real_sh(vs.directions[s], L)  # (K, order²)
        for a, b in _chunks(vs):
            per[s, a:b] = T0[a:b] - _blocked(vs, s, a, b)[0] @ Y / np.pi
    return _mean_and_stderr(per)


def sh_transfer_matrix(vs: VisibilitySamples, order: int):
    """Glossy transfer matrix M_ij = ∫ V(ω) Y_i(ω) Y_j(ω) dω (Sloan, Kautz & Snyder 2002, Sec. 5), lab's real SH.

    V is the traced visibility of the module docstring: 0 at and below the shading horizon (n·ω ≤ 0) and below the
    geometric horizon, the shadow ray's bit above both.  Per set the stratified sum Σ_c Ω_c V_c Y_i(ω_c) Y_j(ω_c)
    (no control variate); the mean over the sets.  With radiance coefficients L_j, (M L)_i are the coefficients of
    the visible incident radiance V·L projected onto the first ``order`` bands (exact when L lies in them).  Each
    set's M is symmetric positive semi-definite (a sum of Ω_c V_c y_c y_cᵀ); the exact M's eigenvalues lie in [0, 1]
    (it is the band-limited projection of multiplying by V ∈ {0, 1}), the estimate's largest exceeds 1 by the cells'
    quadrature error (measured at an unoccluded point, order 5, 3 seeds: 1.008 at n_face 16, 1.05-1.065 at 8).
    The leading k² × k² block is the matrix of order k.

    Parameters
    ----------
    vs : VisibilitySamples
    order : int
        Number of bands: 3 → 9 × 9, 5 → 25 × 25.

    Returns
    -------
    M : ndarray, float64, shape (P, order², order²)
    err : ndarray, float64, shape (P, order², order²)
        Standard error of the mean from the spread of the sets (NaN with one set).

    Examples
    --------
    An unoccluded point with normal +z sees the upper hemisphere: M_00 = ∫_{z>0} Y_00² dω = 1/2, and
    M_01 (Y_00 against Y_1,0 ∝ z) = ∫_{z>0} z dω √3/(4π) = √3/4:

    >>> import trimesh
    >>> from ibl_ref.occlusion.oracle_inputs import trace_visibility, sh_transfer_matrix
    >>> floor = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    >>> vs = trace_visibility(floor, [[0, 0, 0]], [[0, 0, 1]], [[0, 0, 1]], n_face=16)
    >>> M, err = sh_transfer_matrix(vs, 3)
    >>> M.shape, round(float(M[0, 0, 0]), 2), round(float(M[0, 0, 2]), 2)
    ((1, 9, 9), 0.5, 0.43)
    """
    from ..groundtruth.sh_basis import real_sh

    vs = _check_samples(vs)
    order = positive_int("order", order)
    K = order * order
    check_allocation(vs.n_sets * vs.n_pixels * K * K * 8, "the SH transfer matrices", "sh_transfer_matrix")
    per = np.empty((vs.n_sets, vs.n_pixels, K, K))
    for s in range(vs.n_sets):
        Y = real_sh(vs.directions[s], order - 1)  # (cells, K)
        YY = (Y[:, :, None] * Y[:, None, :]).reshape(vs.n_cells, K * K)
        for a, b in _chunks(vs):
            W = vs.visibility(s, a, b) * vs.solid_angles[None, :]  # Ω_c V_c
            per[s, a:b] = (W @ YY).reshape(b - a, K, K)
    return _mean_and_stderr(per)


def _region_weights(cube, labels, n_face: int):
    """Sparse (K, R) matrix w_ci = Σ_{texels t ∈ cell c, label i} Y_t Ω_t, and R."""
    import scipy.sparse as sp

    from ..environment.validated import as_environment
    from ..knuth2014.median_cut import luminance

    a = as_environment(cube, "region radiance").data
    N = a.shape[1]
    if N % n_face:
        raise IBLError(f"region radiance: face size {N} is not a multiple of n_face={n_face} (every texel must lie "
                       "in one visibility cell, so that each cell's weight per region is an exact texel sum)")
    lab = np.asarray(labels)
    if lab.shape != (6, N, N):
        raise IBLError(f"labels: expected shape (6, {N}, {N}) like the radiance, got {lab.shape}")
    if lab.size and not np.issubdtype(lab.dtype, np.integer):
        raise IBLError(f"labels: expected integer region indices, got dtype {lab.dtype}")
    if lab.min() < 0:
        raise IBLError(f"labels: region indices must be >= 0, got {int(lab.min())}")
    R = int(lab.max()) + 1
    k = N // n_face
    f, r, c = np.meshgrid(np.arange(6), np.arange(N), np.arange(N), indexing="ij")
    cell = ((f * n_face + r // k) * n_face + c // k).reshape(-1)
    w = (luminance(a) * cube_solid_angles(N)).reshape(-1)
    K = 6 * n_face * n_face
    m = sp.coo_matrix((w, (cell, lab.reshape(-1).astype(np.int64))), shape=(K, R)).tocsr()
    m.sum_duplicates()
    return m, R


def region_visibility(vs: VisibilitySamples, cube, labels):
    """Per-region visibility VIS_i: the paper's per-region visibility made exact (Knuth et al. 2014, Eq. 5).

    Over the sets s, ``VIS_i = Σ_s Σ_c V_sc w_ci [n·ω_sc > 0] / Σ_s Σ_c w_ci [n·ω_sc > 0]`` with w_ci = Σ_{texels t ∈ cell c, label i}
    Y_t Ω_t (Rec. 709 luminance, :func:`ibl_ref.knuth2014.median_cut.luminance`; exact texel solid angles): the
    radiance-weighted visible fraction of the part of region i above the shading horizon, 1 where that part is
    empty or has no energy.  Not cosine-weighted (the lobe of Eq. 5 is applied by the method, not here).

    Parameters
    ----------
    vs : VisibilitySamples
    cube : array_like, shape (6, N, N, C) or (6, N, N)
        Environment radiance (validated: finite, non-negative); N a multiple of ``vs.n_face`` (a texel must lie in
        exactly one visibility cell).
    labels : array_like of int, shape (6, N, N)
        Region index ≥ 0 of every texel (e.g. :attr:`ibl_ref.knuth2014.median_cut.LightSet.labels`); R = max + 1.

    Returns
    -------
    vis : ndarray, float64, shape (P, R)
        The ratio of the sums over the sets.
    err : ndarray, float64, shape (P, R)
        Its standard error from the spread of the sets (delta method; NaN with one set).

    Raises
    ------
    IBLError
        N not a multiple of n_face, labels of the wrong shape, type or sign; bad radiance
        (:class:`ibl_ref.errors.RadianceError`, :class:`ibl_ref.errors.LayoutError`).

    Examples
    --------
    Two regions split at the horizon of an unoccluded point: what lies above it is visible, the lower region
    has no part above the horizon (1 by definition):

    >>> import numpy as np, trimesh
    >>> from ibl_ref.environment.envmap import texel_directions
    >>> from ibl_ref.occlusion.oracle_inputs import trace_visibility, region_visibility
    >>> floor = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    >>> vs = trace_visibility(floor, [[0, 0, 0]], [[0, 0, 1]], [[0, 0, 1]], n_face=4)
    >>> labels = (texel_directions(8)[..., 2] < 0).astype(int)
    >>> vis, err = region_visibility(vs, np.ones((6, 8, 8, 3)), labels)
    >>> vis.tolist(), err.tolist()
    ([[1.0, 1.0]], [[0.0, 0.0]])
    """
    vs = _check_samples(vs)
    w, R = _region_weights(cube, labels, vs.n_face)
    wT = w.T.tocsr()
    num = np.empty((vs.n_sets, vs.n_pixels, R))
    den = np.empty((vs.n_sets, vs.n_pixels, R))
    for s in range(vs.n_sets):
        for a, b in _chunks(vs):
            up = (vs.normals[a:b] @ vs.directions[s].T > 0).astype(np.float64)
            V = vs.visibility(s, a, b)
            num[s, a:b] = np.asarray(wT @ (up * V).T).T
            den[s, a:b] = np.asarray(wT @ up.T).T
    # the ratio of the sums over the sets, not the mean of the per-set ratios: a region inside one cell that the
    # horizon cuts has den = 0 in the sets whose point fell below the horizon, and a per-set ratio would count those
    # as 1 (a biased mean); the ratio of sums is consistent, its standard error by the delta method
    N, D = num.sum(axis=0), den.sum(axis=0)
    vis = np.where(D > 0, N / np.where(D > 0, D, 1.0), 1.0)
    S = vs.n_sets
    if S < 2:
        return vis, np.full(vis.shape, np.nan)
    Dm = np.where(D > 0, D / S, 1.0)
    resid = (num - vis[None] * den) / Dm[None]
    return vis, np.where(D > 0, resid.std(axis=0, ddof=1) / math.sqrt(S), 0.0)
