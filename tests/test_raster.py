"""Tests of ibl_ref.rendering.raster against ray casting (ibl_ref.rendering.raycast / trimesh) and closed forms."""

import warnings

import numpy as np
import pytest
import trimesh

from ibl_ref.rendering.camera import OrthographicCamera, PerspectiveCamera
from ibl_ref.errors import IBLError, MeshError
from ibl_ref.rendering.raster import (
    count_fragments,
    interpolate_vertex_attribute,
    prepare_scene,
    rasterize,
    render_depth,
)
from ibl_ref.rendering.raycast import primary_rays

# A pixel whose centre lies within EDGE_TOL pixels of a projected triangle edge may legitimately be decided
# differently by the rasterizer's exact edge functions and trimesh's barycentric test (which accepts points up to
# 1e-12 outside a triangle in barycentric units, i.e. ~1e-10 px for these sizes).
EDGE_TOL_PX = 1e-9


def _edge_distance(scene, cam, pix_i, pix_j):
    """Min distance (px) from pixel centres to any projected triangle edge."""
    x, y, _, _ = cam.project(scene.vertices)
    F = scene.faces
    a = np.stack([x[F], y[F]], -1)  # (F, 3, 2)
    A = a.reshape(-1, 2)
    B = np.roll(a, -1, axis=1).reshape(-1, 2)
    p = np.stack([pix_j + 0.5, pix_i + 0.5], -1)[:, None, :]
    ab = B - A
    t = np.clip(((p - A) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300), 0, 1)
    q = A + t[..., None] * ab
    return np.sqrt(((p - q) ** 2).sum(-1)).min(axis=1)


def _icosphere():
    return trimesh.creation.icosphere(subdivisions=2)  # 320 faces


def _overlapping_quads():
    q1 = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    q2 = trimesh.Trimesh([[-0.3, -0.5, 0.4], [1.4, -0.2, -0.3], [1.2, 1.3, 0.2], [-0.4, 0.9, 0.5]], [[0, 1, 2], [0, 2, 3]])
    return [(q1, 3), (q2, 7)]


SCENES = {
    "cube": lambda: trimesh.creation.box(extents=[1.0, 1.2, 0.8]),
    "icosphere320": _icosphere,
    "quads": _overlapping_quads,
}


@pytest.mark.parametrize("name", list(SCENES))
def test_raster_matches_raycast(name):
    meshes = SCENES[name]()
    scene = prepare_scene(meshes)
    cam = PerspectiveCamera(eye=[1.3, 1.1, 3.0], target=[0.05, -0.02, 0.0], up=[0, 1, 0], fov_y_deg=45, width=64, height=48)
    g = rasterize(scene, cam)
    depth_rc, tid_rc = primary_rays(scene, cam)
    cov_rc = tid_rc >= 0
    diff = np.argwhere(g.mask != cov_rc)
    if len(diff):
        d = _edge_distance(scene, cam, diff[:, 0], diff[:, 1])
        assert d.max() < EDGE_TOL_PX, f"{len(diff)} coverage differences, farthest {d.max()} px from an edge"
    assert g.mask.sum() > 300  # the scene is actually visible
    both = g.mask & cov_rc
    # same visible triangle except on (shared) edges, where either neighbour is a valid answer
    tdiff = np.argwhere(both & (g.triangle_id != tid_rc))
    if len(tdiff):
        assert _edge_distance(scene, cam, tdiff[:, 0], tdiff[:, 1]).max() < EDGE_TOL_PX
    # depth: both routes intersect the same plane in float64 → relative 1e-9 leaves ample rounding room
    np.testing.assert_allclose(g.depth[both], depth_rc[both], rtol=1e-9)
    assert np.all(g.depth[~g.mask] == cam.far)


def test_material_ids_of_mesh_list():
    meshes = _overlapping_quads()
    cam = PerspectiveCamera(eye=[0.2, 0.1, 4.0], target=[0, 0, 0], up=[0, 1, 0], fov_y_deg=40, width=40, height=40)
    g = rasterize(meshes, cam)
    scene = prepare_scene(meshes)
    ids = set(np.unique(g.material_id[g.mask]).tolist())
    assert ids == {3, 7}
    np.testing.assert_array_equal(g.material_id[g.mask], scene.material_id[g.triangle_id[g.mask]])
    assert np.all(g.material_id[~g.mask] == -1)


def _grid(n, jitter, rng):
    """n×n-quad planar grid on z = 0 over [−1, 1]², interior vertices jittered within the plane."""
    u = np.linspace(-1, 1, n + 1)
    X, Y = np.meshgrid(u, u)
    V = np.c_[X.ravel(), Y.ravel(), np.zeros(X.size)]
    interior = (np.abs(V[:, 0]) < 1) & (np.abs(V[:, 1]) < 1)
    V[interior, :2] += rng.uniform(-jitter, jitter, size=(interior.sum(), 2)) * (2 / n)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    F = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    return trimesh.Trimesh(V, F, process=False)


def test_shared_edges_no_gaps_no_double_coverage_perspective():
    rng = np.random.default_rng(3)
    mesh = _grid(12, 0.3, rng)
    cam = PerspectiveCamera(eye=[0.4, -1.5, 2.2], target=[0, 0, 0], up=[0, 0, 1], fov_y_deg=60, width=96, height=80)
    cnt = count_fragments(mesh, cam)
    # the boundary of the grid is a convex quadrilateral on screen: its interior must be covered exactly once.
    x, y, _, _ = cam.project(np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float))
    outline = trimesh.Trimesh(np.c_[x, y, np.zeros(4)], [[0, 1, 2], [0, 2, 3]], process=False)
    jj, ii = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    pts = np.c_[jj.ravel(), ii.ravel(), np.zeros(jj.size)]
    # inside the outline by more than 1e-9 px (distance from the outline's edges, independent route)
    from trimesh.triangles import points_to_barycentric

    inside = np.zeros(len(pts), bool)
    for f in outline.faces:
        bc = points_to_barycentric(np.repeat(outline.vertices[f][None], len(pts), 0), pts)
        inside |= np.all(bc > 1e-6, axis=1)
    inside = inside.reshape(cnt.shape)
    assert inside.sum() > 1000
    assert np.all(cnt[inside] == 1), f"gaps {np.sum(cnt[inside] == 0)}, double {np.sum(cnt[inside] > 1)}"
    assert cnt.max() == 1


def test_fill_rule_exact_ties_on_pixel_centres():
    # orthographic view of an axis-aligned grid whose vertices sit exactly on pixel centres: every vertical,
    # horizontal and diagonal edge passes through pixel centres.  A half-open rule must cover each of the
    # a×a pixel-centre cells of an a-pixel-wide square exactly once (closed-form count a²).
    W = 32
    cam = OrthographicCamera(eye=[0, 0, 1], forward=[0, 0, -1], up=[0, 1, 0], half_width=W / 2, half_height=W / 2,
                             width=W, height=W, near=0, far=2)
    n, a = 8, 24  # 8×8 quads over a 24-pixel square starting at pixel centre 4.5
    lo = -W / 2 + 4.5
    u = lo + np.linspace(0, a, n + 1)
    X, Y = np.meshgrid(u, u)
    V = np.c_[X.ravel(), Y.ravel(), np.zeros(X.size)]
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    q = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    F = np.r_[np.c_[q[0], q[1], q[2]], np.c_[q[0], q[2], q[3]]]
    mesh = trimesh.Trimesh(V, F, process=False)
    cnt = count_fragments(mesh, cam)
    assert cnt.max() == 1
    assert cnt.sum() == a * a


def test_perspective_correct_interpolation_exact():
    # a strongly receding plane; the G-buffer position must equal the analytic ray–plane intersection and a
    # world-linear attribute f(P) = c·P + k must equal f of that point (1e-10: float64 rounding).
    V = np.array([[-1, 0, -0.5], [1, 0, -0.5], [1, 0, -20], [-1, 0, -20]], float)
    mesh = trimesh.Trimesh(V, [[0, 1, 2], [0, 2, 3]], process=False)
    cam = PerspectiveCamera(eye=[0.1, 0.7, 0.5], target=[0, 0, -6], up=[0, 1, 0], fov_y_deg=70, width=48, height=48)
    g = rasterize(mesh, cam)
    o, d = cam.pixel_rays()
    t = -o[..., 1] / d[..., 1]  # plane y = 0
    P_ref = o + t[..., None] * d
    m = g.mask
    assert m.sum() > 500
    np.testing.assert_allclose(g.position[m], P_ref[m], rtol=0, atol=1e-10)
    c, k = np.array([0.3, -2.0, 1.7]), 0.25
    scene = prepare_scene(mesh)
    f_int = interpolate_vertex_attribute(g, scene, scene.vertices @ c + k)
    np.testing.assert_allclose(f_int[m], P_ref[m] @ c + k, atol=1e-9)
    # sensitivity check: affine (screen-space) interpolation would be far off on this plane
    scr = g.barycentric[m]  # perspective-correct λ; screen-space b_k ∝ λ_k·w_k
    w = (scene.vertices[scene.faces[g.triangle_id[m]]] - cam.eye) @ cam.forward
    b = scr * w
    b /= b.sum(1, keepdims=True)
    f_affine = np.einsum("nk,nk->n", b, (scene.vertices @ c + k)[scene.faces[g.triangle_id[m]]])
    assert np.abs(f_affine - (P_ref[m] @ c + k)).max() > 1e-2


def test_normals_view_reflection():
    s = trimesh.creation.icosphere(subdivisions=3)
    cam = PerspectiveCamera(eye=[0, 0.5, 3], target=[0, 0, 0], up=[0, 1, 0], fov_y_deg=45, width=48, height=48)
    g = rasterize(s, cam)
    m = g.mask
    P = g.position[m]
    # smooth normals of a sphere ≈ radial direction (icosphere-3 facets subtend ~ 4°: cos > 0.995)
    radial = P / np.linalg.norm(P, axis=1, keepdims=True)
    assert np.min(np.sum(g.normal[m] * radial, axis=1)) > 0.995
    np.testing.assert_allclose(np.linalg.norm(g.normal[m], axis=1), 1, atol=1e-12)
    # view vector points to the eye; reflection: unit length, same angle with n as v, coplanar with n, v
    v_ref = cam.eye - P
    v_ref /= np.linalg.norm(v_ref, axis=1, keepdims=True)
    np.testing.assert_allclose(g.view[m], v_ref, atol=1e-12)
    r, n, v = g.reflect[m], g.normal[m], g.view[m]
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1, atol=1e-12)
    np.testing.assert_allclose(np.sum(r * n, 1), np.sum(v * n, 1), atol=1e-12)
    np.testing.assert_allclose(np.sum(np.cross(n, v) * r, 1), 0, atol=1e-12)
    # flat normals are the face normals
    gf = rasterize(s, cam, smooth_normals=False)
    fn = s.face_normals[gf.triangle_id[gf.mask]]
    np.testing.assert_allclose(gf.normal[gf.mask], fn, atol=1e-12)


def test_backface_culling_keeps_closed_convex_image():
    # for a closed convex mesh seen from outside, the front faces alone give the same image
    s = trimesh.creation.icosphere(subdivisions=2)
    cam = PerspectiveCamera(eye=[0.5, 1, 3], target=[0, 0, 0], up=[0, 1, 0], fov_y_deg=45, width=40, height=40)
    g = rasterize(s, cam)
    gc = rasterize(s, cam, cull_backfaces=True)
    np.testing.assert_array_equal(g.triangle_id, gc.triangle_id)
    # culling really removes the far hemisphere.  A line through the interior of a closed convex polytope crosses
    # its surface exactly twice, and the fill rule counts a crossing on a shared edge or vertex exactly once (one
    # owner), so every covered pixel centre has exactly 2 fragments without culling and 1 with it, and an
    # uncovered one none — at every pixel, silhouette included (no tolerance: counts are integers)
    c_all = count_fragments(s, cam)
    c_cull = count_fragments(s, cam, cull_backfaces=True)
    assert np.all(c_all[g.mask] == 2) and np.all(c_cull[g.mask] == 1)
    assert np.all(c_all[~g.mask] == 0) and np.all(c_cull[~g.mask] == 0)
    # with inverted winding the culled image shows the inside of the far hemisphere: the same silhouette (the
    # outline of the polytope is the outline of either hemisphere), deeper everywhere
    inv = trimesh.Trimesh(s.vertices, s.faces[:, ::-1], process=False)
    gi = rasterize(inv, cam, cull_backfaces=True)
    np.testing.assert_array_equal(gi.mask, g.mask)
    assert np.all(gi.depth[g.mask] > g.depth[g.mask])


def test_orthographic_depth_matches_raycast():
    rng = np.random.default_rng(5)
    s = trimesh.creation.icosphere(subdivisions=2)
    s.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    cam = OrthographicCamera(eye=[0, 3, 0], forward=[0.1, -1, 0.2], up=[0, 0, 1], half_width=1.3, half_height=1.3,
                             width=40, height=40, near=0, far=6)
    depth, mask = render_depth(s, cam)
    d_rc, t_rc = primary_rays(s, cam)
    both = mask & (t_rc >= 0)
    assert both.sum() > 500
    np.testing.assert_allclose(depth[both], d_rc[both], rtol=1e-9)
    assert np.all(depth[~mask] == cam.far)


def test_bad_meshes():
    with pytest.raises(MeshError, match="empty"):
        rasterize(trimesh.Trimesh(), PerspectiveCamera([0, 0, 3], [0, 0, 0], [0, 1, 0], 45, 8, 8))
    with pytest.raises(MeshError, match="empty mesh list"):
        prepare_scene([])
    nan = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]], [[0, 1, 2]], process=False)
    with pytest.raises(MeshError, match="NaN"):
        prepare_scene(nan)
    degen = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], process=False)
    with pytest.raises(MeshError, match="degenerate"):
        prepare_scene(degen)
    mixed = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], [[0, 1, 2], [0, 1, 3]], process=False)
    with pytest.warns(UserWarning, match="dropped 1 degenerate"):
        sc = prepare_scene(mixed)
    assert len(sc.faces) == 1 and sc.n_degenerate == 1
    with pytest.raises(MeshError, match=r"mesh list item 0: not a"):
        prepare_scene([("not a mesh", 0)])
    assert issubclass(MeshError, IBLError)


def test_near_plane_clipping_camera_inside_box():
    # camera inside a closed box: every pixel sees a wall; clipped faces keep their ids and the depth equals the
    # ray-cast depth (1e-9 relative, float64 rounding), the position lies on the face's plane
    box = trimesh.creation.box(extents=[2, 2, 2])
    scene = prepare_scene(box)
    cam = PerspectiveCamera([0.1, 0.2, 0.3], [0.2, -0.3, -1], [0, 1, 0], 100, 40, 32, near=0.05)
    g = rasterize(scene, cam)
    assert g.n_clipped_near > 0
    assert g.mask.all()
    d_rc, t_rc = primary_rays(scene, cam)
    assert (t_rc >= 0).all()
    np.testing.assert_allclose(g.depth, d_rc, rtol=1e-9)
    fn = scene.face_normals[g.triangle_id]
    v0 = scene.vertices[scene.faces[g.triangle_id][..., 0]]
    np.testing.assert_allclose(np.sum((g.position - v0) * fn, -1), 0, atol=1e-12)
    # positions from the clipped pieces' barycentrics mapped back to the face = the ray-cast hit points
    o, d = cam.pixel_rays()
    np.testing.assert_allclose(g.position, o + d_rc[..., None] * d, atol=1e-9)
    # watertight after clipping: each pixel centre covered exactly once by the inward-facing walls
    assert count_fragments(scene, cam).max() == 1 and count_fragments(scene, cam).min() == 1


def test_no_spurious_warnings_for_clean_mesh():
    box = trimesh.creation.box(extents=[2, 2, 2])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rasterize(box, PerspectiveCamera([0, 0, 5], [0, 0, 0], [0, 1, 0], 45, 16, 16), warn=True)


def test_result_independent_of_batch_size():
    # tiny batches force row-band splitting of every bounding box; the image must be bit-identical
    s = trimesh.creation.icosphere(subdivisions=2)
    q = trimesh.Trimesh([[-3, -1, -3], [3, -1, -3], [3, -1, 3], [-3, -1, 3]], [[0, 2, 1], [0, 3, 2]])
    cam = PerspectiveCamera([0.5, 1, 3], [0, 0, 0], [0, 1, 0], 60, 50, 40)
    a = rasterize([s, q], cam)
    b = rasterize([s, q], cam, batch_fragments=7)
    np.testing.assert_array_equal(a.triangle_id, b.triangle_id)
    np.testing.assert_array_equal(a.depth, b.depth)


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_near_plane_cut_of_a_face_with_an_edge_parallel_to_the_plane():
    # one triangle, two vertices at depth 1 (their edge is parallel to the near plane: the cut of that edge divides by
    # zero and is unused) and one behind the camera: clipped without a RuntimeWarning, and every covered pixel lies
    # on the triangle's plane (y = 0.75 z − 0.25 through the three vertices: 1e-12, float64 rounding) at depth ≥ near
    tri = trimesh.Trimesh(vertices=[[-1, -1, -1], [1, -1, -1], [0, 0.5, 1]], faces=[[0, 1, 2]], process=False)
    cam = PerspectiveCamera([0, 0, 0], [0, 0, -1], [0, 1, 0], 100, 16, 16, near=0.05)
    g = rasterize(prepare_scene(tri), cam)
    assert g.n_clipped_near == 1 and g.mask.any()
    P = g.position[g.mask]
    np.testing.assert_allclose(P[:, 1], 0.75 * P[:, 2] - 0.25, rtol=0, atol=1e-12)
    assert np.all(g.depth[g.mask] >= 0.05)
