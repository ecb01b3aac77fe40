"""Vectorised CPU triangle rasterizer with a G-buffer (the geometry pass of Knuth et al. 2014, Sec. 3.3–3.4).

Knuth et al. render the scene on the GPU: a G-buffer from the eye (position, normal, reflection vector
r = 2(n·v)n − v used as the lookup direction of every PEM in Eq. 5) and a depth map per directional light for
the variance shadow maps (Sec. 3.3, 4).  This module does the same with NumPy, with float64 throughout so that
it can be compared against exact ray casting (:mod:`ibl_ref.rendering.raycast`).

Algorithm
---------
1. All vertices are projected with the camera (:mod:`ibl_ref.rendering.camera`): continuous pixel coordinates ``(x, y)``
   (pixel (i, j) centre at (j+½, i+½), row 0 at the top), depth along the view axis, and ``w`` (= depth for a
   perspective camera, 1 for an orthographic one).
2. **Near-plane clipping.**  A triangle wholly in front of the near plane (depth < ``near``) is dropped; one that
   straddles it is clipped in world space (Sutherland–Hodgman against the single plane depth = ``near``) into one
   or two sub-triangles that keep the face's id, and whose barycentrics are mapped back to the face, so the
   G-buffer attributes are those of the original face (count in ``GBuffer.n_clipped_near``).  Cut points are
   computed from the edge's endpoints in a canonical order, so neighbouring faces stay watertight.  Fragments
   deeper than ``far`` are discarded (no far clipping; the camera is used inside large scenes, e.g. a ground
   plane that extends behind the eye).
3. Optional back-face culling (``cull_backfaces=False`` by default): a triangle is a back face when its
   vertices appear clockwise on screen for a counter-clockwise (trimesh/outward-normal) winding, i.e. when its
   outward normal points away from the viewer.
4. Triangles are processed in batches of at most ``batch_fragments`` candidate pixels (the pixels of their
   clipped screen bounding boxes, expanded with ``np.repeat``/``arange``); a batch is one vectorised
   evaluation of the three edge functions at every candidate pixel centre.  There is no Python loop per
   pixel or per triangle, only per batch.
5. **Fill rule.**  Each edge function is evaluated from a *canonical* copy of the edge (endpoints ordered
   lexicographically by screen position), so two triangles that share an edge compute bit-identical values of
   opposite sign.  A pixel centre exactly on an edge (edge function exactly 0) belongs to the triangle for
   which that edge, oriented with the triangle's interior on its positive side, points towards +y (or +x when
   horizontal).  The rule is antisymmetric, so a shared edge is drawn exactly once: no gaps, no double
   coverage (the top-left rule of GPUs, expressed for y-down pixel coordinates).
6. **Perspective-correct interpolation.**  Screen-space barycentrics ``b_k`` are divided by the vertices' ``w``:
   ``λ_k = (b_k / w_k) / Σ_m (b_m / w_m)``.  ``λ`` are the exact world-space barycentrics of the surface point
   seen through the pixel centre, so any attribute that is linear over the triangle in world space (position,
   depth, normals before normalisation) is interpolated exactly.
7. **Z-buffer.**  Per batch, candidate fragments are sorted by (pixel, depth, triangle id) with ``np.lexsort``;
   the first per pixel competes with the buffer (strictly smaller depth wins, so equal depths go to the lower
   triangle id — unclipped faces before clipped pieces — deterministically).

Normals are per-vertex (``smooth_normals=True``: trimesh's ``vertex_normals`` interpolated with λ and
renormalised) or per-face.  Normals are **not** flipped toward the viewer; use ``GBuffer.face_normal`` and
``view`` to detect back faces.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from ..errors import MeshError
from .camera import scene_bounds

__all__ = [
    "Scene",
    "mesh_list",
    "GBuffer",
    "prepare_scene",
    "rasterize",
    "render_depth",
    "count_fragments",
    "interpolate_vertex_attribute",
]

#: Relative area threshold below which a triangle is degenerate: |cross| <= 1e-14 * (bbox diagonal)².
DEGENERATE_REL_AREA = 1e-14


@dataclass(frozen=True)
class Scene:
    """Concatenated triangle soup of one or more meshes.

    Attributes
    ----------
    vertices : (V, 3) float64
    faces : (F, 3) int64 — indices into ``vertices``; degenerate triangles already removed.
    vertex_normals : (V, 3) float64 — unit (trimesh ``vertex_normals``).
    face_normals : (F, 3) float64 — unit, from the winding (right-hand rule).
    material_id : (F,) int64 — per-face material id.
    mesh_index : (F,) int64 — which input mesh the face came from.
    source_face : (F,) int64 — face index inside that input mesh.
    n_degenerate : int — number of degenerate triangles dropped.
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray
    face_normals: np.ndarray
    material_id: np.ndarray
    mesh_index: np.ndarray
    source_face: np.ndarray
    n_degenerate: int = 0

    @property
    def triangles(self) -> np.ndarray:
        """(F, 3, 3) vertex positions of every face."""
        return self.vertices[self.faces]

    def bounds(self):
        """Bounding sphere ``(centre, radius)`` of the used vertices."""

        return scene_bounds(self.vertices[np.unique(self.faces)])

    def to_trimesh(self):
        """One ``trimesh.Trimesh`` with the same faces in the same order (triangle ids agree)."""
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False, validate=False)


def mesh_list(meshes):
    """Accept a mesh, a list of meshes, or a list of (mesh, material_id) pairs."""
    if isinstance(meshes, Scene):
        return meshes
    if hasattr(meshes, "vertices") and hasattr(meshes, "faces"):
        return [(meshes, 0)]
    try:
        items = list(meshes)
    except TypeError as exc:
        raise MeshError(
            f"expected a trimesh.Trimesh or a list of (mesh, material_id), got {type(meshes).__name__}"
        ) from exc
    if not items:
        raise MeshError("empty mesh list: nothing to render")
    out = []
    for k, it in enumerate(items):
        if isinstance(it, tuple):
            if len(it) != 2:
                raise MeshError(f"mesh list item {k}: expected (mesh, material_id), got a tuple of length {len(it)}")
            m, mat = it
        else:
            m, mat = it, k
        if not (hasattr(m, "vertices") and hasattr(m, "faces")):
            raise MeshError(f"mesh list item {k}: not a mesh ({type(m).__name__})")
        try:
            mat = int(mat)
        except (TypeError, ValueError) as exc:
            raise MeshError(f"mesh list item {k}: material id must be an integer, got {mat!r}") from exc
        out.append((m, mat))
    return out


def prepare_scene(meshes, warn: bool = True) -> Scene:
    """Validate and concatenate meshes into a :class:`Scene`.

    Parameters
    ----------
    meshes : trimesh.Trimesh | list of Trimesh | list of (Trimesh, material_id) | Scene
        A bare list gives material ids 0, 1, 2, …
    warn : bool
        Warn (``UserWarning``) with the count of dropped degenerate triangles.

    Raises
    ------
    MeshError
        Empty mesh (no faces), non-finite vertices, out-of-range face indices, or all triangles degenerate.
    """
    items = mesh_list(meshes)
    if isinstance(items, Scene):
        return items
    verts, faces, vnorm, mats, mesh_idx, src = [], [], [], [], [], []
    offset = 0
    for k, (m, mat) in enumerate(items):
        v = np.asarray(m.vertices, dtype=np.float64)
        f = np.asarray(m.faces)
        if f.size == 0 or v.size == 0:
            raise MeshError(f"mesh {k}: empty (no faces)")
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise MeshError(f"mesh {k}: expected (V,3) vertices and (F,3) triangle faces, got {v.shape}, {f.shape}")
        if not np.all(np.isfinite(v)):
            bad = np.unique(np.argwhere(~np.isfinite(v))[:, 0])
            raise MeshError(f"mesh {k}: {len(bad)} vertex(es) with NaN/Inf coordinates (first: vertex {int(bad[0])})")
        if f.min() < 0 or f.max() >= len(v):
            raise MeshError(f"mesh {k}: face indices out of range [0, {len(v)})")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            vn = np.asarray(m.vertex_normals, dtype=np.float64)
        if vn.shape != v.shape or not np.all(np.isfinite(vn)):
            vn = np.zeros_like(v)
        verts.append(v)
        faces.append(f.astype(np.int64) + offset)
        vnorm.append(vn)
        mats.append(np.full(len(f), mat, dtype=np.int64))
        mesh_idx.append(np.full(len(f), k, dtype=np.int64))
        src.append(np.arange(len(f), dtype=np.int64))
        offset += len(v)
    V = np.concatenate(verts)
    F = np.concatenate(faces)
    tri = V[F]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    diag2 = float(((V.max(axis=0) - V.min(axis=0)) ** 2).sum())
    keep = area2 > DEGENERATE_REL_AREA * max(diag2, np.finfo(float).tiny)
    n_deg = int((~keep).sum())
    if not keep.any():
        raise MeshError(f"all {len(F)} triangles are degenerate (zero area)")
    if n_deg and warn:
        warnings.warn(f"dropped {n_deg} degenerate (zero-area) triangle(s) of {len(F)}", UserWarning, stacklevel=2)
    fn = cross[keep] / area2[keep, None]
    VN = np.concatenate(vnorm)
    # vertices without a usable normal (e.g. only touched by degenerate faces) fall back to 0; flat normals still work
    return Scene(
        vertices=V,
        faces=F[keep],
        vertex_normals=VN,
        face_normals=fn,
        material_id=np.concatenate(mats)[keep],
        mesh_index=np.concatenate(mesh_idx)[keep],
        source_face=np.concatenate(src)[keep],
        n_degenerate=n_deg,
    )


@dataclass
class GBuffer:
    """Per-pixel geometry of one view.  Arrays are (H, W, …); uncovered pixels hold the fill values below.

    Attributes
    ----------
    depth : (H, W) float64 — distance along the view axis (world units); ``camera.far`` where uncovered.
    position : (H, W, 3) — world position (0 where uncovered).
    normal : (H, W, 3) — unit shading normal (smooth or flat; 0 where uncovered).
    face_normal : (H, W, 3) — unit geometric normal of the triangle.
    view : (H, W, 3) — unit vector toward the camera (v).
    reflect : (H, W, 3) — r = 2(n·v)n − v (the PEM lookup direction of Eq. 5).
    triangle_id : (H, W) int64 — index into ``scene.faces``; −1 where uncovered.
    material_id : (H, W) int64 — −1 where uncovered.
    barycentric : (H, W, 3) — perspective-correct world-space barycentrics λ.
    mask : (H, W) bool — coverage.
    n_clipped_near : int — triangles clipped by the near plane (partly in front of it).
    """

    depth: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    face_normal: np.ndarray
    view: np.ndarray
    reflect: np.ndarray
    triangle_id: np.ndarray
    material_id: np.ndarray
    barycentric: np.ndarray
    mask: np.ndarray
    n_clipped_near: int = 0


def _edge_setup(ax, ay, bx, by, s):
    """Canonical edge data for edge a→b of triangles with orientation sign s (all (F,) arrays).

    Returns (cx, cy, cdx, cdy, f, owner): E(p) = f·(cdx·(py − cy) − cdy·(px − cx)) is > 0 inside.
    """
    swap = (ax > bx) | ((ax == bx) & (ay > by))
    cx = np.where(swap, bx, ax)
    cy = np.where(swap, by, ay)
    cdx = np.where(swap, ax - bx, bx - ax)
    cdy = np.where(swap, ay - by, by - ay)
    f = np.where(swap, -1.0, 1.0) * s
    # oriented direction (interior on the positive side): (f·cdx, f·cdy); tie owner if it points to +y (or +x)
    ex, ey = f * cdx, f * cdy
    owner = (ey > 0) | ((ey == 0) & (ex > 0))
    return cx, cy, cdx, cdy, f, owner


def _clip_near(scene, camera):
    """Per-triangle screen data after clipping against the near plane.

    Returns ``(tx, ty, tz, tw, src, bary, n_clipped)``: (T, 3) arrays of the (sub-)triangles to rasterize,
    ``src`` (T,) the scene face each came from and ``bary`` (T, 3, 3) the barycentrics of its vertices in that
    face (rows = sub-triangle vertices), or ``None`` when nothing was clipped.  The cut point of an edge is
    computed from its endpoints in a canonical order (lower vertex index first), so two faces sharing a clipped
    edge get bit-identical vertices there.
    """
    V, F = scene.vertices, scene.faces
    x, y, z, w = camera.project(V)
    near = camera.near
    zf = z[F]
    inside = zf >= near
    n_in = inside.sum(axis=1)
    full = np.nonzero(n_in == 3)[0]
    part = np.nonzero((n_in == 1) | (n_in == 2))[0]
    tx, ty, tz, tw = x[F[full]], y[F[full]], z[F[full]], w[F[full]]
    if len(part) == 0:
        return tx, ty, tz, tw, full, None, 0
    eye3 = np.eye(3)
    # rotate each partial face cyclically (keeps the winding): lone inside vertex first (n_in = 1) or lone
    # outside vertex last (n_in = 2)
    ins = inside[part]
    one = n_in[part] == 1
    first = np.where(one, np.argmax(ins, axis=1), (np.argmin(ins, axis=1) + 1) % 3)
    rot = (first[:, None] + np.arange(3)[None, :]) % 3  # local vertex order
    Fi = np.take_along_axis(F[part], rot, axis=1)  # (n, 3) global vertex ids, rotated
    zl = z[Fi]

    def cut(a, b):
        """Barycentrics (in rotated local order, (n, 3)) and world point of the near-plane cut of edge a–b."""
        ia, ib = Fi[:, a], Fi[:, b]
        swap = ia > ib
        lo_l = np.where(swap, b, a)
        hi_l = np.where(swap, a, b)
        z_lo = zl[np.arange(len(Fi)), lo_l]
        z_hi = zl[np.arange(len(Fi)), hi_l]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # edges not crossing the plane
            t = (near - z_lo) / (z_hi - z_lo)                                  # (t = ±inf / nan) are unused
            B = (1 - t)[:, None] * eye3[lo_l] + t[:, None] * eye3[hi_l]
            P = (1 - t)[:, None] * V[np.minimum(ia, ib)] + t[:, None] * V[np.maximum(ia, ib)]
        return B, P

    B01, P01 = cut(0, 1)
    B12, P12 = cut(1, 2)
    B20, P20 = cut(2, 0)
    E0, E1 = np.broadcast_to(eye3[0], B01.shape), np.broadcast_to(eye3[1], B01.shape)
    Pv = V[Fi]
    # n_in = 1: (v0, cut01, cut20); n_in = 2: (v0, v1, cut12) and (v0, cut12, cut20)
    tris_B, tris_P, tris_src = [], [], []
    o = np.nonzero(one)[0]
    if len(o):
        tris_B.append(np.stack([E0[o], B01[o], B20[o]], 1))
        tris_P.append(np.stack([Pv[o, 0], P01[o], P20[o]], 1))
        tris_src.append(o)
    t2 = np.nonzero(~one)[0]
    if len(t2):
        tris_B.append(np.stack([E0[t2], E1[t2], B12[t2]], 1))
        tris_P.append(np.stack([Pv[t2, 0], Pv[t2, 1], P12[t2]], 1))
        tris_src.append(t2)
        tris_B.append(np.stack([E0[t2], B12[t2], B20[t2]], 1))
        tris_P.append(np.stack([Pv[t2, 0], P12[t2], P20[t2]], 1))
        tris_src.append(t2)
    Bl = np.concatenate(tris_B)  # barycentrics in rotated local order
    Pw = np.concatenate(tris_P)
    k = np.concatenate(tris_src)
    # back to the face's own vertex order: local column j is face vertex rot[k, j]
    B = np.zeros_like(Bl)
    rk = rot[k]
    for j in range(3):
        B[np.arange(len(k))[:, None], np.arange(3)[None, :], rk[:, j][:, None]] = Bl[:, :, j]
    cx, cy, cz, cw = camera.project(Pw)
    # cut vertices lie on the near plane up to rounding; pin their depth so no fragment is lost to d < near
    cz = np.maximum(cz, near)
    if not camera.is_orthographic:
        cw = cz
    n_full = len(full)
    src = np.concatenate([full, part[k]])
    bary = np.concatenate([np.broadcast_to(eye3, (n_full, 3, 3)), B])
    return (np.concatenate([tx, cx]), np.concatenate([ty, cy]), np.concatenate([tz, cz]),
            np.concatenate([tw, cw]), src, bary, len(part))


def _rasterize_core(tx, ty, tz, tw, width, height, near, far, cull_backfaces, batch_fragments, count_buf=None):
    """Rasterize (T, 3) screen-space triangles; return (zbuf, index into T, λ within that triangle)."""
    finite = np.all(np.isfinite(tx) & np.isfinite(ty), axis=1)
    in_front = np.all(tz >= near, axis=1)
    area2 = (tx[:, 1] - tx[:, 0]) * (ty[:, 2] - ty[:, 0]) - (tx[:, 2] - tx[:, 0]) * (ty[:, 1] - ty[:, 0])
    ok = in_front & finite & (area2 != 0) & np.any(tz <= far, axis=1)  # wholly beyond far: skip
    if cull_backfaces:
        # y points down in pixel coordinates, so a counter-clockwise front face has negative area2
        ok &= area2 < 0
    with np.errstate(invalid="ignore"):
        x0 = np.ceil(tx.min(axis=1) - 0.5)
        x1 = np.floor(tx.max(axis=1) - 0.5)
        y0 = np.ceil(ty.min(axis=1) - 0.5)
        y1 = np.floor(ty.max(axis=1) - 0.5)
    ok &= (x1 >= 0) & (x0 <= width - 1) & (y1 >= 0) & (y0 <= height - 1)
    ok &= (x1 >= x0) & (y1 >= y0)  # bounding box contains at least one pixel centre
    ids = np.nonzero(ok)[0]
    zbuf = np.full(height * width, np.inf)
    tbuf = np.full(height * width, -1, dtype=np.int64)
    lbuf = np.zeros((height * width, 3))
    if len(ids) == 0:
        return zbuf, tbuf, lbuf
    x0 = np.clip(x0[ids], 0, width - 1).astype(np.int64)
    x1 = np.clip(x1[ids], 0, width - 1).astype(np.int64)
    y0 = np.clip(y0[ids], 0, height - 1).astype(np.int64)
    y1 = np.clip(y1[ids], 0, height - 1).astype(np.int64)
    nx = x1 - x0 + 1
    ny = y1 - y0 + 1
    # split tall bounding boxes into row bands of at most batch_fragments pixels (bounded memory per batch)
    rps = np.maximum(1, batch_fragments // nx)
    nseg = -(-ny // rps)
    seg_tri = np.repeat(np.arange(len(ids)), nseg)
    seg_k = np.arange(len(seg_tri)) - np.repeat(np.cumsum(nseg) - nseg, nseg)
    sy0 = y0[seg_tri] + seg_k * rps[seg_tri]
    sy1 = np.minimum(sy0 + rps[seg_tri] - 1, y1[seg_tri])
    counts = nx[seg_tri] * (sy1 - sy0 + 1)
    s = np.sign(area2[ids])
    tx, ty, tz, tw = tx[ids], ty[ids], tz[ids], tw[ids]
    # edge k is opposite vertex k: e0 = v1→v2, e1 = v2→v0, e2 = v0→v1
    edges = [
        _edge_setup(tx[:, 1], ty[:, 1], tx[:, 2], ty[:, 2], s),
        _edge_setup(tx[:, 2], ty[:, 2], tx[:, 0], ty[:, 0], s),
        _edge_setup(tx[:, 0], ty[:, 0], tx[:, 1], ty[:, 1], s),
    ]
    inv_w = 1.0 / tw
    # batches: consecutive bands whose candidate-pixel total stays under the budget
    cum = np.cumsum(counts)
    starts = [0]
    while starts[-1] < len(seg_tri):
        base = cum[starts[-1] - 1] if starts[-1] > 0 else 0
        end = int(np.searchsorted(cum, base + batch_fragments, side="right"))
        starts.append(max(end, starts[-1] + 1))
    for a, b in zip(starts[:-1], starts[1:]):
        c = counts[a:b]
        n = int(c.sum())
        s_loc = np.repeat(np.arange(a, b), c)
        t_loc = seg_tri[s_loc]
        k = np.arange(n) - np.repeat(np.cumsum(c) - c, c)
        j = x0[t_loc] + k % nx[t_loc]
        i = sy0[s_loc] + k // nx[t_loc]
        del s_loc, k
        px = j + 0.5
        py = i + 0.5
        E = np.empty((3, n))
        inside = np.ones(n, dtype=bool)
        for e, (cx, cy, cdx, cdy, f, owner) in enumerate(edges):
            Ee = f[t_loc] * (cdx[t_loc] * (py - cy[t_loc]) - cdy[t_loc] * (px - cx[t_loc]))
            inside &= (Ee > 0) | ((Ee == 0) & owner[t_loc])
            E[e] = Ee
        if not inside.any():
            continue
        E = E[:, inside]
        t_loc = t_loc[inside]
        pix = (i * width + j)[inside]
        if count_buf is not None:
            count_buf += np.bincount(pix, minlength=width * height)
        bsum = E.sum(axis=0)
        q = (E / bsum).T * inv_w[t_loc]  # (n, 3) screen barycentrics / w
        lam = q / q.sum(axis=1, keepdims=True)
        d = (lam * tz[t_loc]).sum(axis=1)
        keep = (d >= near) & (d <= far)
        if not keep.all():
            lam, d, t_loc, pix = lam[keep], d[keep], t_loc[keep], pix[keep]
        if len(d) == 0:
            continue
        order = np.lexsort((t_loc, d, pix))
        ps = pix[order]
        first = np.ones(len(ps), dtype=bool)
        first[1:] = ps[1:] != ps[:-1]
        win = order[first]
        p = pix[win]
        better = d[win] < zbuf[p]
        win, p = win[better], p[better]
        zbuf[p] = d[win]
        tbuf[p] = ids[t_loc[win]]
        lbuf[p] = lam[win]
    return zbuf, tbuf, lbuf


def _raster_scene(scene, camera, cull_backfaces, batch_fragments, count_buf=None):
    """Clip, rasterize; return (zbuf, face id, λ w.r.t. the face's vertices, number of clipped faces)."""
    tx, ty, tz, tw, src, bary, n_clip = _clip_near(scene, camera)
    zbuf, tbuf, lbuf = _rasterize_core(
        tx, ty, tz, tw, camera.width, camera.height, camera.near, camera.far, cull_backfaces, int(batch_fragments),
        count_buf=count_buf,
    )
    cov = tbuf >= 0
    face = np.full_like(tbuf, -1)
    face[cov] = src[tbuf[cov]]
    if bary is not None:
        lbuf[cov] = np.einsum("nk,nkj->nj", lbuf[cov], bary[tbuf[cov]])
    return zbuf, face, lbuf, n_clip


def rasterize(
    meshes,
    camera,
    *,
    cull_backfaces: bool = False,
    smooth_normals: bool = True,
    batch_fragments: int = 1 << 19,
    warn: bool = True,
) -> GBuffer:
    """Rasterize meshes into a :class:`GBuffer`.

    Parameters
    ----------
    meshes : see :func:`prepare_scene` (or a prepared :class:`Scene`; triangle ids index ``scene.faces``)
    camera : PerspectiveCamera | OrthographicCamera
    cull_backfaces : bool
        Skip triangles whose outward (counter-clockwise) normal faces away from the camera.  Default False.
    smooth_normals : bool
        Interpolate trimesh vertex normals (True) or use face normals (False).
    batch_fragments : int
        Upper bound on candidate pixels per vectorised batch (memory ≈ 200 bytes × this).
    warn : bool
        Warn about degenerate triangles dropped.

    Returns
    -------
    GBuffer
    """
    scene = prepare_scene(meshes, warn=warn)
    H, W = camera.height, camera.width
    zbuf, tbuf, lbuf, n_clip = _raster_scene(scene, camera, cull_backfaces, batch_fragments)
    mask = tbuf >= 0
    t = tbuf[mask]
    lam = lbuf[mask]
    fv = scene.faces[t]  # (n, 3)
    P = np.einsum("nk,nkc->nc", lam, scene.vertices[fv])
    fn = scene.face_normals[t]
    if smooth_normals:
        Nn = np.einsum("nk,nkc->nc", lam, scene.vertex_normals[fv])
        ln = np.linalg.norm(Nn, axis=1, keepdims=True)
        Nn = np.where(ln > 1e-12, Nn / np.where(ln > 0, ln, 1.0), fn)
    else:
        Nn = fn
    v = camera.view_vectors(P)
    ndv = np.sum(Nn * v, axis=1, keepdims=True)
    r = 2.0 * ndv * Nn - v  # reflection vector r = 2(n·v)n − v

    def img(vals, fill, dtype=np.float64):
        shape = (H * W,) + vals.shape[1:]
        out = np.full(shape, fill, dtype=dtype)
        out[mask] = vals
        return out.reshape((H, W) + vals.shape[1:])

    depth = np.where(mask, zbuf, camera.far).reshape(H, W)
    return GBuffer(
        depth=depth,
        position=img(P, 0.0),
        normal=img(Nn, 0.0),
        face_normal=img(fn, 0.0),
        view=img(v, 0.0),
        reflect=img(r, 0.0),
        triangle_id=tbuf.reshape(H, W),
        material_id=img(scene.material_id[t], -1, np.int64),
        barycentric=img(lam, 0.0),
        mask=mask.reshape(H, W),
        n_clipped_near=n_clip,
    )


def render_depth(meshes, camera, *, cull_backfaces: bool = False, batch_fragments: int = 1 << 19, warn: bool = True):
    """Depth map only (e.g. from an orthographic light camera): ``(depth (H, W), mask (H, W))``.

    Uncovered texels hold ``camera.far``.
    """
    scene = prepare_scene(meshes, warn=warn)
    zbuf, tbuf, _, _ = _raster_scene(scene, camera, cull_backfaces, batch_fragments)
    mask = tbuf >= 0
    depth = np.where(mask, zbuf, camera.far)
    return depth.reshape(camera.height, camera.width), mask.reshape(camera.height, camera.width)


def count_fragments(meshes, camera, *, cull_backfaces: bool = False, warn: bool = True) -> np.ndarray:
    """Number of triangles covering each pixel centre (before the depth test), shape (H, W) int64.

    A diagnostic of the fill rule: a closed, non-overlapping tessellation of a screen region gives exactly 1
    inside it (no gaps, no double coverage on shared edges).
    """
    scene = prepare_scene(meshes, warn=warn)
    counts = np.zeros(camera.width * camera.height, dtype=np.int64)
    _raster_scene(scene, camera, cull_backfaces, 1 << 19, count_buf=counts)
    return counts.reshape(camera.height, camera.width)


def interpolate_vertex_attribute(gbuf: GBuffer, scene: Scene, attr) -> np.ndarray:
    """Perspective-correct interpolation of a per-vertex attribute (V, …) over the G-buffer (0 where uncovered)."""
    a = np.asarray(attr, dtype=np.float64)
    if a.shape[0] != len(scene.vertices):
        raise MeshError(f"attribute has {a.shape[0]} rows, scene has {len(scene.vertices)} vertices")
    H, W = gbuf.mask.shape
    out = np.zeros((H, W) + a.shape[1:])
    m = gbuf.mask
    fv = scene.faces[gbuf.triangle_id[m]]
    lam = gbuf.barycentric[m]
    out[m] = np.einsum("nk,nk...->n...", lam, a[fv])
    return out
