"""Tests of ibl_ref.synthetic.synthetic_meshes: counts, orientation, geometry against closed forms."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from ibl_ref.synthetic import synthetic_meshes as sm
from ibl_ref.errors import IBLError, MeshError


@pytest.fixture(scope="module")
def teapot():
    return sm.make_mesh("teapot")


def part(mesh, name):
    a, b = mesh.metadata["part_faces"][name]
    return trimesh.Trimesh(mesh.vertices, mesh.faces[a:b], process=False)


def signed_volume(tri, origin):
    t = tri - origin
    return np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0


def face_areas(mesh):
    return mesh.area_faces


# ------------------------------------------------------------------------------ teapot
def test_teapot_data_file_and_symmetry():
    cp, names = sm.teapot_patches()
    assert cp.shape == (32, 4, 4, 3)
    assert [names.count(p) for p in ("rim", "body", "handle", "spout", "lid", "bottom")] == [4, 8, 4, 4, 8, 4]
    # typo guard: Newell's data is mirror-symmetric in y (handle and spout lie in the xz plane) and the
    # rim/body/lid/bottom are also symmetric in x
    pts = cp.reshape(-1, 3)
    tree = cKDTree(pts)
    assert np.all(tree.query(pts * [1, -1, 1])[0] < 1e-12)
    rot = np.array([n in ("rim", "body", "lid", "bottom") for n in names])
    rp = cp[rot].reshape(-1, 3)
    assert np.all(cKDTree(rp).query(rp * [-1, 1, 1])[0] < 1e-12)


def test_bezier_patch_interpolates_corners():
    cp, _ = sm.teapot_patches()
    g = sm.bezier_patch_grid(np.asarray(cp), 5)
    for (i, j), (gi, gj) in {(0, 0): (0, 0), (0, 3): (0, 5), (3, 0): (5, 0), (3, 3): (5, 5)}.items():
        np.testing.assert_array_equal(g[:, gi, gj], cp[:, i, j])
    # partition of unity of the Bernstein basis: a patch of identical control points is that point
    same = np.broadcast_to(np.array([1.0, 2.0, 3.0]), (4, 4, 3))
    g = sm.bezier_patch_grid(same, 3)
    assert g.shape == (4, 4, 3)
    np.testing.assert_allclose(g, np.broadcast_to([1.0, 2.0, 3.0], g.shape), rtol=1e-14)


@pytest.mark.parametrize("m", [4, 16])
def test_teapot_triangle_count(m, teapot):
    mesh = teapot if m == 16 else sm.make_mesh("teapot", subdiv=m)
    # 32 patches × 2m² triangles, minus one triangle per pole quad: 8 patches (4 lid, 4 bottom) have a
    # degenerate first control row → m collapsed triangles each
    # … plus the lid ledge (close_lid_gap): a ring of 4m quads between the lid's and the rim's edge loops
    assert len(mesh.faces) == 32 * 2 * m * m - 8 * m + 8 * m
    assert np.all(face_areas(mesh) > 0)  # no degenerate faces left
    assert len(sm.make_mesh("teapot", subdiv=m, close_lid_gap=False).faces) == 32 * 2 * m * m - 8 * m


def test_teapot_bounds_and_topology(teapot):
    lo, hi = teapot.bounds
    # extreme points are interpolated patch corners: handle back x = −3.0 (vertex 136), body radius 2.0
    # (vertex 57 at height 0.9), lid-knob top 3.15, bottom 0; the spout tip is inside its control hull (3.525)
    assert lo[0] == pytest.approx(-3.0, abs=1e-12)
    assert lo[1] == pytest.approx(0.0, abs=1e-12) and hi[1] == pytest.approx(3.15, abs=1e-12)
    assert lo[2] == pytest.approx(-2.0, abs=1e-12) and hi[2] == pytest.approx(2.0, abs=1e-12)
    assert 3.3 < hi[0] < 3.525
    assert not teapot.is_watertight  # documented: the original data has open handle/spout ends
    assert teapot.is_winding_consistent
    # body(+rim+bottom), lid, handle, spout, and the lid ledge (own vertices: a crease with the plane's normal)
    assert len(teapot.split(only_watertight=False)) == 5
    # mirror symmetry z → −z of the tessellated surface
    assert np.all(cKDTree(teapot.vertices).query(teapot.vertices * [1, 1, -1])[0] < 1e-9)


def test_teapot_normals_point_outward(teapot):
    # 1) parity: a ray from just outside a face along its normal crosses the surface an even number of
    #    times iff the normal points out.  Open ends (lid gap, handle/spout inside the body) spoil a few
    #    rays; ≥ 90 % must escape (measured 97 %).
    rng = np.random.default_rng(1)
    sel = rng.choice(len(teapot.faces), 600, replace=False)
    n = teapot.face_normals[sel]
    o = teapot.triangles_center[sel] + 1e-4 * n
    _, ray_idx, _ = teapot.ray.intersects_location(o, n, multiple_hits=True)
    hits = np.bincount(ray_idx, minlength=len(sel))
    assert np.mean(hits % 2 == 0) > 0.9
    # 2) signed volume about each part's centroid is positive for the (almost closed) parts
    for name in ("body", "handle", "spout"):
        tri = part(teapot, name).triangles
        assert signed_volume(tri, tri.reshape(-1, 3).mean(axis=0)) > 0
    # 3) the body's lower half: normals point away from the vertical axis
    body = part(teapot, "body")
    c, fn = body.triangles_center, body.face_normals
    assert np.mean(np.einsum("ij,ij->i", fn[:, [0, 2]], c[:, [0, 2]]) > 0) > 0.99


def test_teapot_lid_ledge_closes_the_gap_seen_as_dark_rim_pixels(teapot):
    # 1) geometry, by an independent intersector (trimesh rays): vertical rays through the annulus between the
    #    lid (r = 1.3) and the rim (r = 1.4) hit a surface at height 2.4 with the ledge, and fall into the pot
    #    (first hit far below, on the bottom) without it
    ang = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    o = np.c_[1.35 * np.cos(ang), np.full(50, 5.0), 1.35 * np.sin(ang)]
    d = np.tile([0.0, -1.0, 0.0], (50, 1))
    for closed, want in ((True, 2.4), (False, None)):
        mesh = sm.make_mesh("teapot", close_lid_gap=closed)
        loc, ray, _ = mesh.ray.intersects_location(o, d, multiple_hits=True)
        top = np.full(50, -np.inf)
        np.maximum.at(top, ray, loc[:, 1])
        if want is None:
            assert np.all(top < 1.0)
        else:
            np.testing.assert_allclose(top, want, atol=1e-9)
    led = part(teapot, "lid_ledge")
    np.testing.assert_allclose(led.face_normals, np.tile([0.0, 1.0, 0.0], (len(led.faces), 1)), atol=1e-12)
    np.testing.assert_allclose(teapot.vertex_normals[np.unique(led.faces)], np.tile([0, 1.0, 0], (128, 1)))
    # 2) what a render sees: the rasteriser's G-buffer from two views above the lid; back faces (the pot's
    #    inside, whose reflection vectors point into the pot: the dark lid-rim pixels) are visible around
    #    the lid only through the open gap
    from ibl_ref.rendering.raster import rasterize
    from ibl_ref.rendering.scenes import default_camera

    for view, dist in (((0.6, 0.5, 1.0), "fit"), ((0.3, 0.5, 1.0), 2.6)):
        counts = []
        for closed in (True, False):
            mesh = teapot if closed else sm.make_mesh("teapot", close_lid_gap=False)
            cam = default_camera([mesh], view_dir=view, distance=dist, width=192, height=192)
            gb = rasterize([mesh], cam)
            # around the lid: height 2.15–2.55, radius < 1.6 (the spout's open tip, at r > 2.5, is not in it)
            lid_zone = (gb.mask & (np.abs(gb.position[..., 1] - 2.35) < 0.2)
                        & (np.hypot(gb.position[..., 0], gb.position[..., 2]) < 1.6))
            counts.append(int((lid_zone & ((gb.face_normal * gb.view).sum(-1) < 0)).sum()))
        assert counts[0] == 0 and counts[1] > 5, counts


def test_teapot_y_up_flag():
    zup = sm.make_mesh("teapot", subdiv=3, y_up=False)
    assert zup.bounds[1, 2] == pytest.approx(3.15)


# ------------------------------------------------------------------------------ sphere, torus
def test_sphere_on_plane():
    mesh = sm.make_mesh("sphere_on_plane", radius=0.5, subdivisions=3, plane_res=4)
    sphere, plane = part(mesh, "sphere"), part(mesh, "plane")
    sphere.merge_vertices()
    assert sphere.is_watertight
    # inscribed polyhedron: volume a little below 4/3 π r³ (1.3 % at 3 subdivisions)
    assert 0.97 * 4 / 3 * np.pi * 0.125 < sphere.volume < 4 / 3 * np.pi * 0.125
    assert -1e-12 <= sphere.vertices[np.unique(sphere.faces)][:, 1].min() < 0.02
    np.testing.assert_allclose(plane.face_normals, np.tile([0.0, 1.0, 0.0], (len(plane.faces), 1)), atol=1e-12)
    assert len(plane.faces) == 2 * 4 * 4
    assert mesh.vertex_normals.shape == mesh.vertices.shape


def test_torus_watertight_volume():
    R, r = 1.0, 0.3
    mesh = sm.make_mesh("torus", major_radius=R, minor_radius=r, major_sections=64, minor_sections=32)
    assert mesh.is_watertight and len(mesh.faces) == 2 * 64 * 32
    # closed form 2π²Rr²; inscribed polygons lose ≈ (1 − sinc) terms < 1 %
    assert mesh.volume == pytest.approx(2 * np.pi**2 * R * r * r, rel=1e-2)
    np.testing.assert_allclose(mesh.bounds[:, 1], [0.0, 2 * r], atol=1e-12)
    with pytest.raises(IBLError, match=r"torus: minor_radius \(0\.5\) must be smaller"):
        sm.make_mesh("torus", major_radius=0.3, minor_radius=0.5)


# ------------------------------------------------------------------------------ cloth
def test_cloth_geometry():
    ax, ay, az, cy = 0.5, 0.8, 0.3, 1.0
    mesh = sm.make_mesh("cloth")
    cloth, body = part(mesh, "cloth"), part(mesh, "body")
    assert len(cloth.faces) == 2 * 128 * 64
    assert 10_000 <= len(mesh.faces) <= 20_000
    v = cloth.vertices[np.unique(cloth.faces)]
    # never inside the torso ellipsoid
    q = (v[:, 0] / ax) ** 2 + ((v[:, 1] - cy) / ay) ** 2 + (v[:, 2] / az) ** 2
    assert q.min() > 1.0
    # outward: face normals point away from the vertical axis
    c, fn = cloth.triangles_center, cloth.face_normals
    assert np.mean(np.einsum("ij,ij->i", fn[:, [0, 2]], c[:, [0, 2]]) > 0) > 0.95
    assert np.all(face_areas(cloth) > 0)
    assert mesh.bounds[0, 1] >= 0.0
    body.merge_vertices()
    assert body.is_watertight
    assert body.volume == pytest.approx(4 / 3 * np.pi * ax * ay * az, rel=3e-2)  # icosphere(3), −2 %


def test_cloth_deterministic_and_seeded():
    a = sm.make_mesh("cloth", n_around=32, n_down=8)
    b = sm.make_mesh("cloth", n_around=32, n_down=8)
    c = sm.make_mesh("cloth", n_around=32, n_down=8, seed=5)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    assert not np.allclose(a.vertices, c.vertices)
    nobody = sm.make_mesh("cloth", n_around=32, n_down=8, include_body=False)
    assert list(nobody.metadata["part_faces"]) == ["cloth"]
    with pytest.raises(IBLError, match="fold_amplitude"):
        sm.make_mesh("cloth", fold_amplitude=0.5, flare=0.1)


# ------------------------------------------------------------------------------ loading, validation
def test_make_mesh_errors():
    with pytest.raises(IBLError, match="unknown synthetic mesh"):
        sm.make_mesh("bunny")
    with pytest.raises(IBLError, match="unknown parameter"):
        sm.make_mesh("teapot", subdivisions=3)
    with pytest.raises(IBLError, match=r"subdiv: expected an integer in \[1"):
        sm.make_mesh("teapot", subdiv=0)


def test_load_mesh_name_and_file(tmp_path):
    m = sm.load_mesh("torus", major_sections=12, minor_sections=6)
    assert len(m.faces) == 144
    p = tmp_path / "t.ply"
    m.export(str(p))
    back = sm.load_mesh(p)
    assert len(back.faces) == 144
    np.testing.assert_allclose(back.volume, m.volume, rtol=1e-6)


def test_load_mesh_errors(tmp_path):
    with pytest.raises(MeshError, match="no such mesh file"):
        sm.load_mesh(tmp_path / "missing.obj")
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    with pytest.raises(MeshError, match="empty"):
        sm.load_mesh(empty)
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n")
    with pytest.raises(MeshError, match="NaN"):
        sm.load_mesh(nan)
    with pytest.raises(MeshError, match="NaN"):
        sm.validate_mesh(trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [np.inf, 1, 0]], [[0, 1, 2]], process=False))
    with pytest.raises(MeshError, match="degenerate"):
        sm.validate_mesh(trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], process=False))
    with pytest.raises(MeshError, match="empty"):
        sm.validate_mesh(trimesh.Trimesh())
    with pytest.raises(IBLError, match=r"load_mesh: parameters \['subdiv'\] only apply to"):
        sm.load_mesh(empty, subdiv=3)


def test_analytic_vertex_normals(teapot):
    # teapot: Bézier normals averaged across seams vs trimesh's face-based vertex normals of the same
    # triangles — an independent route; they agree to O(h) (median < 1°) and never point opposite
    for mesh in (teapot, sm.make_mesh("sphere_on_plane", subdivisions=3)):
        vn = mesh.vertex_normals
        np.testing.assert_allclose(np.linalg.norm(vn, axis=1), 1.0, atol=1e-12)
        ref = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).vertex_normals
        dots = np.einsum("ij,ij->i", vn, ref)
        assert dots.min() > 0.5 and np.median(dots) > np.cos(np.radians(1.0))
    # sphere: exactly radial about its centre
    mesh = sm.make_mesh("sphere_on_plane", radius=2.0, subdivisions=2, gap=0.5)
    a, b = mesh.metadata["part_faces"]["sphere"]
    idx = np.unique(mesh.faces[a:b])
    radial = (mesh.vertices[idx] - [0.0, 2.5, 0.0]) / 2.0
    np.testing.assert_allclose(mesh.vertex_normals[idx], radial, atol=1e-12)
