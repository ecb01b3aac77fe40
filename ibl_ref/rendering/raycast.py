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
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from ..errors import IBLError
from .raster import Scene, prepare_scene

__all__ = [
    "backend",
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


def _check_rays_budget(n: int, n_faces: int):
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
    _check_rays_budget(len(o), len(mesh.faces))
    out = np.zeros(len(o), dtype=bool)
    chunk = _chunk_size(mesh, chunk)
    from ..progress import track

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
    _check_rays_budget(len(o), len(mesh.faces))
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
    from ..progress import track

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
    from .camera import look_at_basis

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
