"""Exact visibility by ray casting — the ground truth for the shadow maps of Knuth et al. (2014), Sec. 3.3.

The paper approximates the visibility ``VIS_i(x, y)`` of Eq. 5 with filtered variance shadow maps of
directional lights (:mod:`ibl_ref.rendering.vsm`).  Here the same quantity is computed exactly (for point/direction
pairs) by casting rays with ``trimesh``; it also renders primary rays through the camera's pixel centres so the
rasterizer (:mod:`ibl_ref.rendering.raster`) can be checked against an independent algorithm.

Backend: ``trimesh`` uses Embree (package ``embreex``) automatically when it is installed, otherwise its pure
NumPy/rtree intersector, which is ~3 orders of magnitude slower (docs/background.md §4: ~0.5–1 M rays/s with Embree,
< 1 k rays/s without; measured here: ~100 rays/s on the 16k-triangle teapot, see
``benchmarks/bench_raster.py`` and :data:`FALLBACK_TESTS_PER_S`).  :func:`backend` reports which one is
used; casting more than :data:`WARN_RAYS` rays without Embree emits a warning with an estimated run time.

For a *directional* light all shadow rays are parallel, and :func:`parallel_visibility` answers them exactly
without trimesh: points and triangles are projected onto the plane perpendicular to the light, triangles are
binned on a uniform grid over that plane, and each point is tested (2D edge functions, then the triangle's
height toward the light at that spot) against the triangles of its bin only.  It is the same geometric
predicate as a ray cast (a triangle blocks the ray iff the point's projection lies in the triangle's
projection and the triangle is nearer the light), vectorised like the rasterizer, and 10²–10⁴ × faster than
the trimesh fallback.

Self-intersection.  :func:`parallel_visibility` (the package's one exact caster of parallel shadow rays, used
by the Eq. 5 renderer's exact route and by the reference) tests the geometric predicate itself: a triangle
blocks a point iff the point's projection lies in the triangle's projection and the triangle is more than
``eps`` nearer the light there, with ``eps`` = :data:`VISIBILITY_EPS` × scene radius = 1e-6 R.  The point lies
on its own triangle (the G-buffer interpolates the triangle's vertices), so that triangle's height differs from
the point's by rounding only (~1e-16 R): 1e-6 R removes this self-hit with a wide margin ("no acne"), and on a
convex tessellated surface every neighbouring triangle lies below the point's plane, so it cannot block either.
The earlier reference caster instead moved the ray origin 1e-4 R along the normal and along the ray (the usual
ray-tracing offset): any occluder within 1e-4 R of the surface was then skipped, i.e. light leaked under thin
objects lying on a surface (a sheet 5e-5 R above a floor casts no shadow under it:
``tests/test_raycast.py::test_thin_sheet_contact_shadow_no_leak``), for no gain, because the predicate needs no
offset.  The two now agree; the change moved 6 of 73 855 (pixel, direction) pairs of a 48² teapot-on-ground
reference at n_env = 8 (half each way, all at grazing incidence or at contacts).

:func:`visibility_to_directions` (trimesh) keeps the origin offset (default ``eps = 1e-4 × scene radius``, along the
surface normal and along the ray), because trimesh's fallback intersector accepts hits up to 1e-6 *behind* the
origin.  Occluders closer than ``eps`` to the surface are missed there; this is the usual ray-tracing bias.

Shadow rays in any directions (the converged reference, :mod:`ibl_ref.rendering.reference_converged`):
:class:`ShadowRays` casts (point, direction) pairs from ``p + eps·n_f + eps·ω`` with eps = 1e-6 R — with Embree
(:class:`EmbreeCaster`, ``embreex``: the scene in float32, centred and scaled to unit radius, and every hit Embree
reports re-tested in float64, so that a float32 artefact can only make a ray free, never blocked), or with the
float64 casters above (:func:`parallel_visibility` for directions shared by many rays, :class:`LeafBVH` ray by ray).
On the teapot scene the two agree on every ray tested (``tests/test_raycast.py``); with Embree the converged
reference at 128² takes 41 s CPU instead of 545 s (README, "Reference renderer").
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from ..errors import IBLError
from .raster import Scene, prepare_scene
from ..progress import track
from .camera import look_at_basis

__all__ = [
    "backend",
    "warn_rays_budget",
    "estimate_time_s",
    "FALLBACK_RAYS_PER_S",
    "FALLBACK_TESTS_PER_S",
    "WARN_RAYS",
    "any_hit",
    "visibility_to_directions",
    "directional_visibility",
    "primary_rays",
    "measure_rays_per_s",
    "parallel_visibility",
    "VISIBILITY_EPS",
    "LeafBVH",
    "EmbreeCaster",
    "ShadowRays",
    "SHADOW_BACKENDS",
    "has_embreex",
    "resolve_shadow_backend",
]

#: Ray–triangle tests per second of trimesh's pure-NumPy intersector, measured in this project (one core, under
#: load): 102 rays/s on the 16k-triangle teapot, i.e. ~1.7e6 triangle tests/s, because it tests every triangle
#: whose box meets the ray's box.  Used only for run-time estimates in warnings.
FALLBACK_TESTS_PER_S = 1.7e6
#: Fallback rays/s on small meshes (measured: ~1.7e4 rays/s on a 14-triangle box-on-plane scene).
FALLBACK_RAYS_PER_S = 2.0e4
#: Without Embree, warn when more rays than this are cast.
WARN_RAYS = 200_000


def backend() -> str:
    """``"embree"`` if trimesh will use Embree (embreex installed), else ``"triangle"`` (pure NumPy + rtree)."""
    try:
        from trimesh.ray import has_embree
    except ImportError:  # pragma: no cover - trimesh always has it
        has_embree = False
    return "embree" if has_embree else "triangle"


def estimate_time_s(n_rays: int, n_faces: int = 1, rays_per_s: float | None = None) -> float:
    """Estimated seconds to cast ``n_rays`` at a mesh of ``n_faces`` triangles with the current backend.

    Embree: ~5e5 rays/s (docs/background.md §4); fallback: ``min(FALLBACK_RAYS_PER_S, FALLBACK_TESTS_PER_S / n_faces)``.
    """
    if rays_per_s is None:
        if backend() == "embree":
            rays_per_s = 5e5
        else:
            rays_per_s = min(FALLBACK_RAYS_PER_S, FALLBACK_TESTS_PER_S / max(1, int(n_faces)))
    return float(n_rays) / rays_per_s


def warn_rays_budget(n: int, n_faces: int):
    """Warn when ``n`` rays are about to be cast at ``n_faces`` triangles without Embree (the fallback is slow)."""
    if backend() != "embree" and n > WARN_RAYS:
        warnings.warn(
            f"casting {n} rays at {n_faces} triangles without Embree (pip install embreex): trimesh's fallback "
            f"intersector is slow here, estimated {estimate_time_s(n, n_faces):.0f} s",
            UserWarning,
            stacklevel=3,
        )


def _scene_and_mesh(meshes):
    scene = prepare_scene(meshes, warn=False)
    mesh = scene.to_trimesh()
    return scene, mesh


def _points(a, name) -> np.ndarray:
    p = np.asarray(a, dtype=np.float64)
    if p.ndim < 1 or p.shape[-1] != 3:
        raise IBLError(f"{name}: expected (..., 3) array, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise IBLError(f"{name}: contains NaN or Inf")
    return p


#: Candidate (ray, triangle) pairs per chunk for the fallback intersector.  It tests every triangle whose box
#: meets the ray's box, which for rays crossing the scene is most of the mesh: memory ~ rays × faces.
PAIR_BUDGET = 2_000_000


def _chunk_size(mesh, chunk):
    if chunk is not None:
        return max(1, int(chunk))
    if backend() == "embree":
        return 200_000
    return max(8, PAIR_BUDGET // max(1, len(mesh.faces)))


def any_hit(meshes, origins, directions, chunk: int | None = None, progress: bool = False) -> np.ndarray:
    """Boolean (N,): does the ray ``origin + t·direction``, t > ~0, hit any triangle?  (trimesh ``intersects_any``).

    ``chunk`` rays are cast per call (default: all at once with Embree, ``PAIR_BUDGET / n_faces`` otherwise,
    to bound the fallback's memory).
    """
    if isinstance(meshes, tuple) and len(meshes) == 2 and isinstance(meshes[0], Scene):
        mesh = meshes[1]
    else:
        mesh = _scene_and_mesh(meshes)[1]
    o = _points(origins, "origins").reshape(-1, 3)
    d = _points(directions, "directions").reshape(-1, 3)
    if len(o) != len(d):
        raise IBLError(f"origins ({len(o)}) and directions ({len(d)}) differ in length")
    warn_rays_budget(len(o), len(mesh.faces))
    out = np.zeros(len(o), dtype=bool)
    chunk = _chunk_size(mesh, chunk)

    for a in track(range(0, len(o), chunk), f"rays ({backend()})", unit="chunk", enabled=progress):
        out[a : a + chunk] = mesh.ray.intersects_any(o[a : a + chunk], d[a : a + chunk])
    return out


def visibility_to_directions(meshes, points, normals, dirs, eps: float | None = None, progress: bool = False):
    """Exact binary visibility of directions from surface points.

    Parameters
    ----------
    meshes : occluders (see :func:`ibl_ref.rendering.raster.prepare_scene`)
    points : (P, 3) world points
    normals : (P, 3) unit normals used for the origin offset, or None (offset along the ray only)
    dirs : (D, 3) or (3,) directions toward the light (normalised here)
    eps : origin offset in world units; default ``1e-4 × scene bounding radius``

    Returns
    -------
    (P, D) float64 array: 1 = unoccluded, 0 = occluded.
    """
    scene, mesh = _scene_and_mesh(meshes)
    p = _points(points, "points").reshape(-1, 3)
    d = _points(dirs, "dirs").reshape(-1, 3)
    nd = np.linalg.norm(d, axis=1, keepdims=True)
    if np.any(nd == 0):
        raise IBLError("dirs: zero-length direction")
    d = d / nd
    if eps is None:
        eps = 1e-4 * scene.bounds()[1]
    o = p[:, None, :] + eps * d[None, :, :]
    if normals is not None:
        n = _points(normals, "normals").reshape(-1, 3)
        if len(n) != len(p):
            raise IBLError(f"normals ({len(n)}) and points ({len(p)}) differ in length")
        o = o + eps * n[:, None, :]
    D = np.broadcast_to(d[None], o.shape)
    hit = any_hit((scene, mesh), o.reshape(-1, 3), D.reshape(-1, 3), progress=progress)
    return (~hit).astype(np.float64).reshape(len(p), len(d))


def directional_visibility(meshes, points, normals, direction, eps: float | None = None) -> np.ndarray:
    """Exact visibility (P,) of one direction (a directional light) from points (P, 3)."""
    return visibility_to_directions(meshes, points, normals, np.asarray(direction, float)[None], eps=eps)[:, 0]


def primary_rays(meshes, camera):
    """Ray-cast the camera's pixel centres: ``(depth (H, W), triangle_id (H, W))``.

    Triangle ids index ``prepare_scene(meshes).faces`` (same as :func:`ibl_ref.rendering.raster.rasterize`); misses are
    ``camera.far`` / −1.  Depth is the distance along the view axis of the nearest hit.
    """
    scene, mesh = _scene_and_mesh(meshes)
    o, d = camera.pixel_rays()
    o = o.reshape(-1, 3)
    d = d.reshape(-1, 3)
    warn_rays_budget(len(o), len(mesh.faces))
    chunk = _chunk_size(mesh, None)
    parts = []
    for a in range(0, len(o), chunk):
        t_, r_, l_ = mesh.ray.intersects_id(
            o[a : a + chunk], d[a : a + chunk], multiple_hits=True, return_locations=True
        )
        parts.append(
            (np.asarray(t_, dtype=np.int64), np.asarray(r_, dtype=np.int64) + a, np.asarray(l_, float).reshape(-1, 3))
        )
    tri = np.concatenate([q[0] for q in parts])
    ray = np.concatenate([q[1] for q in parts])
    loc = np.concatenate([q[2] for q in parts])
    H, W = camera.height, camera.width
    depth = np.full(H * W, camera.far)
    tid = np.full(H * W, -1, dtype=np.int64)
    if len(ray):
        z = (loc - o[ray]) @ camera.basis[2]
        ok = (z >= camera.near) & (z <= camera.far)
        tri, ray, z = tri[ok], ray[ok], z[ok]
        order = np.lexsort((tri, z, ray))
        rs = ray[order]
        first = np.ones(len(rs), dtype=bool)
        first[1:] = rs[1:] != rs[:-1]
        w = order[first]
        depth[ray[w]] = z[w]
        tid[ray[w]] = tri[w]
    return depth.reshape(H, W), tid.reshape(H, W)


def measure_rays_per_s(mesh, n_rays: int = 20_000, seed: int = 0) -> float:
    """Rays per second of the current backend for random any-hit rays from the bounding sphere toward the mesh."""
    scene, tm = _scene_and_mesh(mesh)
    c, r = scene.bounds()
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n_rays, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    o = c + 1.5 * r * u
    tgt = c + 0.5 * r * rng.uniform(-1, 1, size=(n_rays, 3))
    d = tgt - o
    t0 = time.perf_counter()
    any_hit((scene, tm), o, d)
    return n_rays / (time.perf_counter() - t0)


def parallel_visibility(meshes, points, direction, normals=None, eps: float | None = None, bins: int | None = None,
                        chunk_pairs: int = 2_000_000, *, mask=None, progress: bool = False) -> np.ndarray:
    """Exact visibility of directional lights from points, by binned 2D point-in-triangle tests.

    The one exact caster of parallel shadow rays in the package: the Eq. 5 renderer's exact route
    (:func:`ibl_ref.rendering.render.light_visibilities`) and the ray-traced reference
    (:mod:`ibl_ref.rendering.reference_render`, many directions per point) both call it.

    Parameters
    ----------
    meshes : occluders (see :func:`ibl_ref.rendering.raster.prepare_scene`)
    points : (..., 3) world points
    direction : (3,) direction toward the light, or (D, 3) directions (one parallel-ray set-up each)
    normals : (..., 3) geometric normals of the points' surfaces, or None.  If given, a light at or below a
        point's tangent plane (n·ω ≤ 0) is blocked by the point's own surface (as a ray cast from the surface
        finds it); without normals only *other* geometry blocks (the point's own triangle never does).
    eps : a triangle blocks a point only if it is more than ``eps`` nearer the light at the point's projection;
        default :data:`VISIBILITY_EPS` ``× scene bounding radius`` = 1e-6 R (module docstring: why this and not an
        origin offset)
    bins : grid size per axis; default ``clip(2·√min(F, P), 1, 1024)`` over the region where points and the
        triangles that can block them overlap (any grid gives the same answer; this one only sets the speed)
    chunk_pairs : bound on (point, candidate triangle) pairs per vectorised step
    mask : (P, D) bool, optional — only these (point, direction) pairs are cast; the others are returned as 1
        (0 where ``normals`` put the light below the receiver's plane)
    progress : report progress over directions (:mod:`ibl_ref.progress`)

    Returns
    -------
    (...) float64 for one direction, (..., D) for (D, 3) directions; 1 = lit, 0 = blocked.  A point exactly on a
    blocker's projected edge counts as blocked (edge tests are inclusive).
    """
    scene = prepare_scene(meshes, warn=False)
    p = _points(points, "points")
    shape = p.shape[:-1]
    p = p.reshape(-1, 3)
    w_all = _points(direction, "direction")
    one = w_all.ndim == 1
    w_all = w_all.reshape(-1, 3)
    nw = np.linalg.norm(w_all, axis=1)
    if np.any(nw == 0):
        raise IBLError("direction: zero vector")
    w_all = w_all / nw[:, None]
    eps = VISIBILITY_EPS * scene.bounds()[1] if eps is None else float(eps)
    nrm = None
    if normals is not None:
        nrm = _points(normals, "normals").reshape(-1, 3)
        if len(nrm) != len(p):
            raise IBLError(f"normals ({len(nrm)}) and points ({len(p)}) differ in length")
    D = len(w_all)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (len(p), D):
            raise IBLError(f"mask shape {mask.shape} != ({len(p)}, {D})")
    out = np.ones((len(p), D))

    it = track(range(D), "exact visibility", unit="dir", enabled=progress)
    if nrm is not None:  # the receiver's own surface blocks lights at or below its plane, cast or not
        out[(nrm @ w_all.T) <= 0] = 0.0
    for j in it:
        sel = None if mask is None else np.flatnonzero(mask[:, j])
        pj = p if sel is None else p[sel]
        nj = None if nrm is None else (nrm if sel is None else nrm[sel])
        vj = _parallel_one(scene, pj, w_all[j], nj, eps, bins, chunk_pairs)
        if sel is None:
            out[:, j] = vj
        else:
            out[sel, j] = vj
    return out[:, 0].reshape(shape) if one else out.reshape(shape + (D,))


#: Default blocking threshold of :func:`parallel_visibility`, in units of the scene's bounding radius.
VISIBILITY_EPS = 1e-6


def _min3(x):
    return np.minimum(np.minimum(x[:, 0], x[:, 1]), x[:, 2])


def _max3(x):
    return np.maximum(np.maximum(x[:, 0], x[:, 1]), x[:, 2])


def _parallel_one(scene, p, w, nrm, eps, bins, chunk_pairs) -> np.ndarray:
    """Visibility (P,) of one unit direction ``w`` from points p (P, 3) (see :func:`parallel_visibility`)."""

    up = np.array([0.0, 1.0, 0.0]) if abs(w[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    basis = look_at_basis(-w, up)  # rows: right, up, forward (= −ω)
    vis = np.ones(len(p))
    if nrm is not None:
        vis[nrm @ w <= 0] = 0.0
    if len(p) == 0:
        return vis
    V = scene.vertices @ basis.T  # (u, v, −height)
    F = scene.faces
    tu, tv, th = V[F, 0], V[F, 1], -V[F, 2]  # (F, 3); th = height toward the light
    P = p @ basis.T
    pu, pv, ph = P[:, 0], P[:, 1], -P[:, 2]
    area2 = (tu[:, 1] - tu[:, 0]) * (tv[:, 2] - tv[:, 0]) - (tu[:, 2] - tu[:, 0]) * (tv[:, 1] - tv[:, 0])
    lo_u, hi_u = _min3(tu), _max3(tu)
    lo_v, hi_v = _min3(tv), _max3(tv)
    # a triangle can block a point only if it is not edge-on (measure zero), its projection meets the points'
    # bounding box and it rises above the lowest point by more than eps: culling the others changes no result
    keep = ((area2 != 0) & (_max3(th) > ph.min() + eps) & (hi_u >= pu.min()) & (lo_u <= pu.max())
            & (hi_v >= pv.min()) & (lo_v <= pv.max()))
    tu, tv, th, area2 = tu[keep], tv[keep], th[keep], area2[keep]
    lo_u, hi_u, lo_v, hi_v = lo_u[keep], hi_u[keep], lo_v[keep], hi_v[keep]
    if len(tu) == 0:
        return vis
    # grid over the part of the plane where both points and candidate triangles are (exact for any grid)
    G = int(bins) if bins is not None else int(np.clip(2 * np.sqrt(min(len(tu), len(p))), 1, 1024))
    u0, u1 = max(lo_u.min(), pu.min()), min(hi_u.max(), pu.max())
    v0, v1 = max(lo_v.min(), pv.min()), min(hi_v.max(), pv.max())
    su = max(u1 - u0, 1e-300) / G
    sv = max(v1 - v0, 1e-300) / G
    bu0 = np.clip(np.floor((lo_u - u0) / su), 0, G - 1).astype(np.int64)
    bu1 = np.clip(np.floor((hi_u - u0) / su), 0, G - 1).astype(np.int64)
    bv0 = np.clip(np.floor((lo_v - v0) / sv), 0, G - 1).astype(np.int64)
    bv1 = np.clip(np.floor((hi_v - v0) / sv), 0, G - 1).astype(np.int64)
    nbu = bu1 - bu0 + 1
    cnt = nbu * (bv1 - bv0 + 1)
    tri = np.repeat(np.arange(len(tu)), cnt)
    k = np.arange(len(tri)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    binid = (bv0[tri] + k // nbu[tri]) * G + bu0[tri] + k % nbu[tri]
    order = np.argsort(binid, kind="stable")
    tri_sorted = tri[order]
    bin_count = np.bincount(binid, minlength=G * G)
    bin_start = np.concatenate([[0], np.cumsum(bin_count)])
    # points → bins by the triangles' own (monotone, clipped) formula, so a triangle covering a point always
    # lists the point's bin; points outside the grid see no triangle
    qu = np.clip(np.floor((pu - u0) / su), 0, G - 1)
    qv = np.clip(np.floor((pv - v0) / sv), 0, G - 1)
    inside = (pu >= u0) & (pu <= u1) & (pv >= v0) & (pv <= v1)
    idx = np.nonzero(inside & (vis > 0))[0]
    pb = (qv[idx] * G + qu[idx]).astype(np.int64)
    pc = bin_count[pb]
    s_ = np.sign(area2)
    cum = np.cumsum(pc)
    a = 0
    while a < len(idx):
        base = cum[a - 1] if a > 0 else 0
        b = max(int(np.searchsorted(cum, base + chunk_pairs, side="right")), a + 1)
        c = pc[a:b]
        n = int(c.sum())
        if n:
            pl = np.repeat(np.arange(a, b), c)
            kk = np.arange(n) - np.repeat(np.cumsum(c) - c, c)
            t = tri_sorted[bin_start[pb[pl]] + kk]
            x, y = pu[idx[pl]], pv[idx[pl]]
            e0 = (tu[t, 2] - tu[t, 1]) * (y - tv[t, 1]) - (tv[t, 2] - tv[t, 1]) * (x - tu[t, 1])
            e1 = (tu[t, 0] - tu[t, 2]) * (y - tv[t, 2]) - (tv[t, 0] - tv[t, 2]) * (x - tu[t, 2])
            e2 = (tu[t, 1] - tu[t, 0]) * (y - tv[t, 0]) - (tv[t, 1] - tv[t, 0]) * (x - tu[t, 0])
            st = s_[t]
            hit = (e0 * st >= 0) & (e1 * st >= 0) & (e2 * st >= 0)
            h = (e0 * th[t, 0] + e1 * th[t, 1] + e2 * th[t, 2]) / area2[t]  # barycentric height (Σ e_k = area2)
            blocked = hit & (h > ph[idx[pl]] + eps)
            occ = np.bincount(pl - a, weights=blocked, minlength=b - a) > 0
            vis[idx[a:b][occ]] = 0.0
        a = b
    return vis


# ------------------------------------------------------------------------------------------------
# scattered shadow rays: (point, direction) pairs with any directions
# ------------------------------------------------------------------------------------------------
def _moller_trumbore(o, d, v0, e1, e2, valid=None):
    """Float64 Möller–Trumbore any-hit predicate (broadcasting): does the ray o + t·d, t > 0, meet the triangle
    (v0, v0 + e1, v0 + e2)?  Inclusive edges (barycentric tolerance 1e-12).  ``o``, ``d``: (..., 3); triangles
    (..., 3) broadcast against them."""
    ox, oy, oz = o[..., 0], o[..., 1], o[..., 2]
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    ax_, ay_, az_ = e1[..., 0], e1[..., 1], e1[..., 2]
    bx, by, bz = e2[..., 0], e2[..., 1], e2[..., 2]
    tx, ty, tz = ox - v0[..., 0], oy - v0[..., 1], oz - v0[..., 2]
    px, py, pz = dy * bz - dz * by, dz * bx - dx * bz, dx * by - dy * bx  # d × e2
    det = ax_ * px + ay_ * py + az_ * pz
    ok = np.abs(det) > 1e-300
    if valid is not None:
        ok = ok & valid
    inv = 1.0 / np.where(ok, det, 1.0)
    u = (tx * px + ty * py + tz * pz) * inv
    qx, qy, qz = ty * az_ - tz * ay_, tz * ax_ - tx * az_, tx * ay_ - ty * ax_  # t × e1
    v = (dx * qx + dy * qy + dz * qz) * inv
    t = (bx * qx + by * qy + bz * qz) * inv
    tol = -1e-12
    return ok & (u >= tol) & (v >= tol) & (u + v <= 1 - tol) & (t > 0)


class LeafBVH:
    """Two-level bounding-sphere hierarchy of a scene's triangles for any-hit tests of scattered rays (float64).

    Triangles are split recursively at the median centroid of the longest bounding-box axis into leaves of at
    most ``leaf`` triangles; each leaf has a bounding sphere, and runs of ``group`` consecutive leaves
    (neighbouring subtrees) one more.  A ray is tested against the spheres and against the triangles of the leaves
    it passes (:func:`_moller_trumbore`: inclusive edges, t > 0).  Exact up to float64 rounding; ≈ 40 µs per ray on
    the 16k-triangle teapot for rays from the ground toward it (one core; 48-triangle leaves: 90 µs),
    so it serves directions with few rays, where one projection set-up of :func:`parallel_visibility` per
    direction (≈ 3–5 ms) costs more.
    """

    def __init__(self, scene, leaf: int = 16, group: int = 16):
        tri = scene.vertices[scene.faces]
        cen = tri.mean(axis=1)
        groups, stack = [], [np.arange(len(tri))]
        while stack:
            idx = stack.pop()
            if len(idx) <= leaf:
                groups.append(idx)
                continue
            c = cen[idx]
            ax = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
            o = idx[np.argsort(c[:, ax], kind="stable")]
            h = len(o) // 2
            stack += [o[:h], o[h:]]
        K = len(groups)
        self.v0 = np.zeros((K, leaf, 3))
        self.e1 = np.zeros((K, leaf, 3))
        self.e2 = np.zeros((K, leaf, 3))
        self.valid = np.zeros((K, leaf), dtype=bool)
        self.centre = np.zeros((K, 3))
        self.radius = np.zeros(K)
        for k, g in enumerate(groups):
            t = tri[g]
            self.v0[k, :len(g)] = t[:, 0]
            self.e1[k, :len(g)] = t[:, 1] - t[:, 0]
            self.e2[k, :len(g)] = t[:, 2] - t[:, 0]
            self.valid[k, :len(g)] = True
            pts = t.reshape(-1, 3)
            c = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
            self.centre[k] = c
            self.radius[k] = np.linalg.norm(pts - c, axis=1).max() * (1 + 1e-9) + 1e-12
        self.group = group
        G = -(-K // group)
        self.top_centre = np.zeros((G, 3))
        self.top_radius = np.zeros(G)
        for gi in range(G):
            c0, r0 = self.centre[gi * group:(gi + 1) * group], self.radius[gi * group:(gi + 1) * group]
            c = 0.5 * ((c0 - r0[:, None]).min(axis=0) + (c0 + r0[:, None]).max(axis=0))
            self.top_centre[gi] = c
            self.top_radius[gi] = (np.linalg.norm(c0 - c, axis=1) + r0).max() * (1 + 1e-9)
        self.n_leaves = K

    @staticmethod
    def _sphere_hits(o, d, centre, radius):
        """(ray, sphere) index pairs whose ray o + t·d (t > 0) meets the sphere."""
        oc = centre[None, :, :] - o[:, None, :]
        tca = np.einsum("rkc,rc->rk", oc, d)
        d2 = np.einsum("rkc,rkc->rk", oc, oc) - tca ** 2
        return np.nonzero((d2 <= radius[None, :] ** 2) & (tca + radius[None, :] > 0))

    def any_hit(self, o, d, ray_chunk: int = 4096, pair_chunk: int = 8192) -> np.ndarray:
        """hit (R,) bool of the rays o + t·d, t > 0 (d unit)."""
        R = len(o)
        hit = np.zeros(R, dtype=bool)
        for i in range(0, R, ray_chunk):
            oo, dd = o[i:i + ray_chunk], d[i:i + ray_chunk]
            tr, tg = self._sphere_hits(oo, dd, self.top_centre, self.top_radius)
            # expand each (ray, group) pair to its leaves and test the leaf spheres
            lf = (tg[:, None] * self.group + np.arange(self.group)[None, :]).reshape(-1)
            rr0 = np.repeat(tr, self.group)
            ok = lf < self.n_leaves
            rr0, lf = rr0[ok], lf[ok]
            oc = self.centre[lf] - oo[rr0]
            tca = np.einsum("kc,kc->k", oc, dd[rr0])
            d2 = np.einsum("kc,kc->k", oc, oc) - tca ** 2
            hs = (d2 <= self.radius[lf] ** 2) & (tca + self.radius[lf] > 0)
            ray, lf = rr0[hs], lf[hs]
            for j in range(0, len(ray), pair_chunk):
                rr_, kk = ray[j:j + pair_chunk], lf[j:j + pair_chunk]
                keep = ~hit[i + rr_]
                rr_, kk = rr_[keep], kk[keep]
                if len(rr_) == 0:
                    continue
                h = _moller_trumbore(oo[rr_][:, None, :], dd[rr_][:, None, :], self.v0[kk], self.e1[kk],
                                     self.e2[kk], self.valid[kk])
                hit[i + rr_[h.any(axis=1)]] = True
        return hit


def has_embreex() -> bool:
    """True if the ``embreex`` package (Embree; extra ``fast``) can be imported."""
    try:
        import embreex.rtcore_scene  # noqa: F401
        from embreex.mesh_construction import TriangleMesh  # noqa: F401
    except ImportError:
        return False
    return True


#: a ray whose Embree hit fails the float64 test is cast again from beyond that hit, stepping
#: EMBREE_STEP·R·4^k along the ray on the k-th retry; after EMBREE_RETRIES retries :class:`LeafBVH` decides
EMBREE_STEP = 1e-6
EMBREE_RETRIES = 4
#: rays per Embree call (bounds the float32/float64 copies: ~100 B per ray)
EMBREE_CHUNK = 1 << 18


class EmbreeCaster:
    """Any-hit shadow rays with Embree (``embreex``, float32) and a float64 check of every reported hit.

    The scene is handed to Embree centred on its bounding sphere and scaled to unit radius (float32 spacing there
    is ≤ 1.2e-7 R).  Embree returns the nearest triangle a ray meets; that triangle is tested again in float64
    (:func:`_moller_trumbore` from the same float64 origin).  A hit that fails (a float32 artefact: a triangle the
    ray only grazes, or one at the origin) is cast again from just beyond it, and after
    :data:`EMBREE_RETRIES` such steps the ray goes to :class:`LeafBVH`.  So every ray reported blocked is blocked
    in float64; a ray Embree reports free could only be blocked by a triangle it passes within float32 rounding
    of an edge (~1e-7 R), which the tests compare against the float64 casters (``tests/test_reference_render.py``).
    """

    def __init__(self, scene):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        self.scene = scene
        c, R = scene.bounds()
        self.centre, self.R = np.asarray(c, dtype=np.float64), float(R)
        v32 = ((scene.vertices - self.centre) / self.R).astype(np.float32)
        self._es = rtcore_scene.EmbreeScene()
        self._mesh = TriangleMesh(scene=self._es, vertices=v32, indices=scene.faces.astype(np.int32))
        tri = scene.vertices[scene.faces]
        self.v0 = tri[:, 0]
        self.e1 = tri[:, 1] - tri[:, 0]
        self.e2 = tri[:, 2] - tri[:, 0]
        self._bvh = None
        self.n_retried = 0
        self.n_bvh = 0

    def _first(self, o, d):
        """(triangle id or −1, distance in world units) of the nearest Embree hit."""
        res = self._es.run(((o - self.centre) / self.R).astype(np.float32), d.astype(np.float32), output=1)
        return np.asarray(res["primID"], dtype=np.int64), np.asarray(res["tfar"], dtype=np.float64) * self.R

    def any_hit(self, o, d) -> np.ndarray:
        """hit (R,) bool of the rays o + t·d, t > 0 (o, d float64, d unit)."""
        o = np.ascontiguousarray(o, dtype=np.float64)
        d = np.ascontiguousarray(d, dtype=np.float64)
        hit = np.zeros(len(o), dtype=bool)
        todo = np.arange(len(o))
        start = o.copy()
        for k in range(EMBREE_RETRIES + 1):
            if len(todo) == 0:
                break
            tri, t = self._first(start[todo], d[todo])
            got = tri >= 0
            idx, tri, t = todo[got], tri[got], t[got]
            ok = _moller_trumbore(o[idx], d[idx], self.v0[tri], self.e1[tri], self.e2[tri])
            hit[idx[ok]] = True
            todo = idx[~ok]  # float32 artefacts: cast again from beyond the hit (t is measured from start)
            if len(todo) and k < EMBREE_RETRIES:
                self.n_retried += len(todo)
                start[todo] += (t[~ok] + EMBREE_STEP * self.R * 4.0 ** k)[:, None] * d[todo]
        if len(todo):
            if self._bvh is None:
                self._bvh = LeafBVH(self.scene)
            self.n_bvh += len(todo)
            hit[todo] = self._bvh.any_hit(o[todo], d[todo])
        return hit


#: Embree scenes kept per process (:func:`embree_caster`): the last few meshes
EMBREE_CACHE_SIZE = 2
_EMBREE_CACHE: list = []


def embree_caster(scene) -> EmbreeCaster:
    """The :class:`EmbreeCaster` of ``scene`` (a :class:`~ibl_ref.rendering.raster.Scene`), built once per process
    for each mesh set: a scene with the same vertices and faces (compared value by value: the reference's blocks
    each get their own copy of the scene on worker processes) reuses the Embree scene built for it — its rays are
    the same rays (the build is deterministic; a query reads the scene only).  The last :data:`EMBREE_CACHE_SIZE`
    mesh sets are kept."""
    v, f = np.asarray(scene.vertices), np.asarray(scene.faces)
    for k, (vc, fc, caster) in enumerate(_EMBREE_CACHE):
        if vc.shape == v.shape and fc.shape == f.shape and np.array_equal(vc, v) and np.array_equal(fc, f):
            if k:
                _EMBREE_CACHE.insert(0, _EMBREE_CACHE.pop(k))
            return caster
    caster = EmbreeCaster(scene)
    _EMBREE_CACHE.insert(0, (v.copy(), f.copy(), caster))
    del _EMBREE_CACHE[EMBREE_CACHE_SIZE:]
    return caster


SHADOW_BACKENDS = ("auto", "embree", "exact")
#: exact backend: directions with fewer rays than this are cast ray by ray (:class:`LeafBVH`, ≈ 40 µs per ray on
#: the 16k-triangle teapot) instead of with one projection set-up per direction (≈ 3–5 ms per direction)
BVH_MAX_RAYS_PER_DIRECTION = 100


def resolve_shadow_backend(backend: str = "auto") -> str:
    """``"embree"`` or ``"exact"`` for ``backend`` ∈ :data:`SHADOW_BACKENDS` (``"auto"``: Embree when installed)."""
    if backend not in SHADOW_BACKENDS:
        raise IBLError(f"ray backend must be one of {SHADOW_BACKENDS}, got {backend!r}")
    if backend == "auto":
        return "embree" if has_embreex() else "exact"
    if backend == "embree" and not has_embreex():
        raise IBLError("ray backend 'embree' needs the embreex package: pip install \".[fast]\"")
    return backend


class ShadowRays:
    """Exact binary visibility of (surface point, direction) pairs: the shadow rays of the reference renderer.

    A direction below the receiving triangle's plane (n_f·ω < 0) is occluded without casting (the ray enters the
    surface).  The others are cast from ``p + eps·n_f + eps·ω`` (``eps`` = :data:`VISIBILITY_EPS` × scene radius =
    1e-6 R: the point lies on its own triangle, so the offset removes that self-hit; module docstring) and are
    occluded if they meet any triangle:

    * ``backend="embree"``: :class:`EmbreeCaster` (float32 Embree, every hit re-checked in float64);
    * ``backend="exact"``: the package's float64 casters — per direction shared by at least
      :data:`BVH_MAX_RAYS_PER_DIRECTION` rays (``groups``) one projection set-up of :func:`parallel_visibility`
      (same predicate without the offset: a triangle blocks when it is more than ``eps`` nearer the light),
      otherwise :class:`LeafBVH` ray by ray;
    * ``"auto"``: Embree when ``embreex`` is installed, else exact.

    The two backends disagree only on rays that pass within rounding of a triangle edge or start within ~eps of an
    occluder (measured in ``tests/test_reference_render.py``).
    """

    def __init__(self, scene, backend: str = "auto", eps: float | None = None):
        self.scene = prepare_scene(scene, warn=False)
        self.backend = resolve_shadow_backend(backend)
        self.eps = VISIBILITY_EPS * self.scene.bounds()[1] if eps is None else float(eps)
        self._embree = embree_caster(self.scene) if self.backend == "embree" else None
        self._bvh = None
        self.n_rays = 0

    def visibility(self, points, face_normals, dirs, groups=None) -> np.ndarray:
        """uint8 (K,): 1 = the ray from ``points[k]`` along ``dirs[k]`` (unit) is free.  ``groups`` (K,) int: rays
        with equal group share their direction exactly (used by the exact backend's per-direction caster)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(face_normals, dtype=np.float64).reshape(-1, 3)
        w = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        out = np.ones(len(p), dtype=np.uint8)
        if len(p) == 0:
            return out
        below = np.einsum("kc,kc->k", f, w) < 0
        out[below] = 0
        up = np.flatnonzero(~below)
        self.n_rays += len(up)
        e = self.eps
        if self._embree is not None:
            for a in range(0, len(up), EMBREE_CHUNK):
                k = up[a:a + EMBREE_CHUNK]
                out[k] = ~self._embree.any_hit(p[k] + e * f[k] + e * w[k], w[k])
            return out
        scattered = up
        if groups is not None and len(up):
            g = np.asarray(groups).reshape(-1)[up]
            order = np.argsort(g, kind="stable")
            gs = g[order]
            starts = np.flatnonzero(np.r_[True, gs[1:] != gs[:-1]])
            ends = np.r_[starts[1:], len(gs)]
            big = (ends - starts) >= BVH_MAX_RAYS_PER_DIRECTION
            for a0, a1 in zip(starts[big], ends[big]):
                k = up[order[a0:a1]]
                out[k] = parallel_visibility(self.scene, p[k], w[k[0]], eps=e) > 0.5
            scattered = up[np.concatenate([order[a0:a1] for a0, a1 in zip(starts[~big], ends[~big])] or
                                          [np.zeros(0, dtype=np.int64)])]
        if len(scattered):
            if self._bvh is None:
                self._bvh = LeafBVH(self.scene)
            k = scattered
            out[k] = ~self._bvh.any_hit(p[k] + e * f[k] + e * w[k], w[k])
        return out
