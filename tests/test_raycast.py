"""Tests of ibl_ref.rendering.raycast: exact visibility against closed-form occlusion by a sphere and a box."""

import numpy as np
import pytest
import trimesh

from ibl_ref.rendering import raycast
from ibl_ref.errors import IBLError


def test_backend_reported():
    assert raycast.backend() in ("embree", "triangle")
    assert raycast.estimate_time_s(10_000) > 0


def test_visibility_sphere_occluder_closed_form():
    # point at distance D from a sphere of radius r: direction d is blocked iff the angle between d and the
    # direction to the centre is < asin(r/D).  The sphere is an icosphere (inscribed polyhedron), so directions
    # within the gap between the inscribed-polyhedron and the true sphere (|angle − asin(r/D)| < 0.02 rad for
    # subdivision 3) are excluded from the comparison.
    s = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    p = np.array([[0.0, 0.0, 3.0]])
    rng = np.random.default_rng(7)
    d = rng.normal(size=(400, 3))
    d[:200] = d[:200] * 0.3 + [0, 0, -1]  # concentrate half near the sphere
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    vis = raycast.visibility_to_directions(s, p, None, d)[0]
    ang = np.arccos(np.clip(d @ [0, 0, -1], -1, 1))
    half = np.arcsin(1.0 / 3.0)
    clear = np.abs(ang - half) > 0.02
    assert clear.sum() > 300
    np.testing.assert_array_equal(vis[clear], (ang[clear] > half).astype(float))
    assert 0 < vis.mean() < 1


def test_directional_visibility_under_box():
    box = trimesh.creation.box(extents=[1, 1, 1])
    box.apply_translation([0, 1, 0])
    pts = np.array([[0, 0, 0], [2, 0, 0], [0.45, 0, 0], [0.55, 0, 0]], float)
    n = np.tile([0, 1, 0], (4, 1))
    v = raycast.directional_visibility(box, pts, n, [0, 1, 0])
    np.testing.assert_array_equal(v, [0, 1, 0, 1])  # box spans |x| ≤ 0.5
    # tilted light at 45° toward +x: the ray from (x0, 0, 0) is at x = x0 + y; it meets the box (|x| ≤ 0.5,
    # y ∈ [0.5, 1.5]) iff x0 ∈ (−2, 0): x0 = −0.9 is shadowed, x0 = −2.5 is lit
    w = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    v2 = raycast.directional_visibility(box, np.array([[-0.9, 0, 0], [-2.5, 0, 0]]), None, w)
    np.testing.assert_array_equal(v2, [0, 1])


def test_large_ray_count_warns_without_embree(monkeypatch):
    if raycast.backend() == "embree":
        pytest.skip("embree installed: no warning expected")
    monkeypatch.setattr(raycast, "WARN_RAYS", 10)
    s = trimesh.creation.box()
    with pytest.warns(UserWarning, match="embreex"):
        raycast.visibility_to_directions(s, np.zeros((4, 3)) + [0, 0, 2], None, np.eye(3))


def test_bad_inputs():
    s = trimesh.creation.box()
    with pytest.raises(IBLError, match="NaN"):
        raycast.visibility_to_directions(s, [[np.nan, 0, 0]], None, [[0, 0, 1]])
    with pytest.raises(IBLError, match="zero-length"):
        raycast.visibility_to_directions(s, [[0, 0, 2]], None, [[0, 0, 0]])
    with pytest.raises(IBLError, match="differ"):
        raycast.visibility_to_directions(s, [[0, 0, 2]], [[0, 0, 1], [0, 0, 1]], [[0, 0, 1]])


def _slab_hits(p, w, lo, hi):
    """Closed-form ray/box test (slab method): does p + t·w, t > 0, meet the box [lo, hi]?"""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - p) / w
        t2 = (hi - p) / w
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    return (tmax >= np.maximum(tmin, 0)), tmin, tmax


def test_parallel_visibility_box_closed_form():
    # points on the ground under a box, random lights in the upper hemisphere; reference: slab test.  Rays that
    # graze the box (entry/exit within 1e-9 of each other, or passing within 1e-9 of its boundary) are excluded.
    box = trimesh.creation.box(extents=[1, 1, 1])
    box.apply_translation([0, 1, 0])
    lo, hi = np.array([-0.5, 0.5, -0.5]), np.array([0.5, 1.5, 0.5])
    ground = trimesh.Trimesh([[-3, 0, -3], [3, 0, -3], [3, 0, 3], [-3, 0, 3]], [[0, 2, 1], [0, 3, 2]], process=False)
    rng = np.random.default_rng(8)
    pts = np.c_[rng.uniform(-2.5, 2.5, 4000), np.zeros(4000), rng.uniform(-2.5, 2.5, 4000)]
    n = np.tile([0.0, 1.0, 0.0], (len(pts), 1))
    for _ in range(4):
        w = rng.normal(size=3)
        w[1] = abs(w[1]) + 0.3
        w /= np.linalg.norm(w)
        vis = raycast.parallel_visibility([(box, 0), (ground, 1)], pts, w, normals=n)
        hit, tmin, tmax = _slab_hits(pts, w, lo, hi)
        clear = np.abs(tmax - np.maximum(tmin, 0)) > 1e-9
        assert 0 < hit[clear].sum() < clear.sum()
        np.testing.assert_array_equal(vis[clear], (~hit[clear]).astype(float))
        # brute force (one bin) gives the same answer
        np.testing.assert_array_equal(raycast.parallel_visibility([(box, 0), (ground, 1)], pts, w, normals=n, bins=1), vis)


def test_parallel_visibility_matches_trimesh_rays():
    # surface points of an icosphere over a ground quad; the trimesh route offsets ray origins by eps (1e-4 R), so
    # the two may differ only at grazing light (|n·ω| < 0.15, where the offset decides)
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.6)
    s.apply_translation([0, 0.7, 0])
    q = trimesh.Trimesh([[-2, 0, -2], [2, 0, -2], [2, 0, 2], [-2, 0, 2]], [[0, 2, 1], [0, 3, 2]], process=False)
    meshes = [(s, 0), (q, 1)]
    both = trimesh.util.concatenate([s, q])
    pts, fid = trimesh.sample.sample_surface(both, 1500, seed=3)
    n = both.face_normals[fid]
    w = np.array([0.4, 1.0, -0.3])
    w /= np.linalg.norm(w)
    a = raycast.parallel_visibility(meshes, pts, w, normals=n)
    b = raycast.visibility_to_directions(meshes, pts, n, w[None])[:, 0]
    diff = a != b
    assert np.all(np.abs(n[diff] @ w) < 0.15), np.abs(n[diff] @ w).max()
    assert 0.2 < a.mean() < 0.9


def _floor(s=1.0, y=0.0):
    return trimesh.Trimesh([[-s, y, -s], [s, y, -s], [s, y, s], [-s, y, s]], [[0, 2, 1], [0, 3, 2]], process=False)


def test_thin_sheet_contact_shadow_no_leak():
    # a sheet 5e-5 R above a floor (paper on a table): floor points under it are shadowed for every light above
    # the horizon whose ray stays under the sheet until it reaches the sheet's height (closed form: the ray rises
    # 5e-5 R over a horizontal run of 5e-5 R / tan(elevation) << the 0.1 margin to the sheet's edge)
    floor, sheet = _floor(1.0), _floor(0.5, 0.0)
    meshes = [(floor, 0), (sheet, 1)]
    R = raycast.prepare_scene(meshes, warn=False).bounds()[1]
    sheet.apply_translation([0, 5e-5 * R, 0])
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-0.4, 0.4, 300), np.zeros(300), rng.uniform(-0.4, 0.4, 300)]
    n = np.tile([0.0, 1.0, 0.0], (300, 1))
    w = rng.normal(size=(16, 3))
    w[:, 1] = np.abs(w[:, 1]) + 0.2
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    V = raycast.parallel_visibility(meshes, pts, w, normals=n)
    assert V.shape == (300, 16)
    np.testing.assert_array_equal(V, 0.0)
    # the usual origin offset of 1e-4 R (trimesh route) starts the rays above the sheet: light leaks under it
    leak = raycast.visibility_to_directions(meshes, pts[:40], n[:40], w[:4])
    assert leak.mean() == 1.0
    # floor points outside the sheet's shadow stay lit (shadow = sheet shifted by 5e-5 R / tan: < 0.01 here)
    out = np.c_[rng.uniform(0.52, 0.9, 100), np.zeros(100), rng.uniform(-0.9, 0.9, 100)]
    np.testing.assert_array_equal(raycast.parallel_visibility(meshes, out, w, normals=n[:100]), 1.0)


def test_sphere_on_plane_contact_shadow_and_no_acne():
    # icosphere (radius 0.5) touching the floor at its lowest vertex
    from ibl_ref.rendering.camera import PerspectiveCamera
    from ibl_ref.rendering.raster import rasterize

    s = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    s.apply_translation(-np.array([0, s.vertices[:, 1].min(), 0]))
    c = s.vertices[np.argmin(s.vertices[:, 1])]
    meshes = [(s, 0), (_floor(2.0), 1)]
    rng = np.random.default_rng(2)
    w = rng.normal(size=(24, 3))
    w[:, 1] = np.abs(w[:, 1]) + 0.6  # elevations above ~30°
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    # contact shadow: floor points within 0.01 of the contact point are below the sphere's faces (which rise
    # at least ~0.01² / (2·0.5) above the floor there), so every upward ray enters the sphere
    ang = rng.uniform(0, 2 * np.pi, 200)
    rad = 0.01 * np.sqrt(rng.uniform(0, 1, 200))
    pts = c + np.c_[rad * np.cos(ang), np.zeros(200), rad * np.sin(ang)]
    pts[:, 1] = 0.0
    V = raycast.parallel_visibility(meshes, pts, w, normals=np.tile([0.0, 1.0, 0.0], (200, 1)))
    np.testing.assert_array_equal(V, 0.0)
    # no acne: points on the (convex) sphere, from the G-buffer of a camera, are lit by every light above their
    # face's plane (nothing else is above them), also at grazing incidence down to n·ω = 1e-3
    cam = PerspectiveCamera(eye=[0.3, 1.2, 2.0], target=[0, 0.5, 0], up=[0, 1, 0], fov_y_deg=40, width=48, height=48)
    gb = rasterize(meshes, cam)
    on = gb.mask & (gb.material_id == 0)
    P, fn = gb.position[on], gb.face_normal[on]
    ww = np.vstack([w, [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [-0.7, 0.1, 0.7]]])
    ww /= np.linalg.norm(ww, axis=1, keepdims=True)
    V = raycast.parallel_visibility(meshes, P, ww, normals=fn)
    up = (fn @ ww.T) > 1e-3
    above_floor = P[:, 1][:, None] + 0 * ww[:, 0] > 0.05  # rays from these cannot reach the floor going up/level
    sel = up & (above_floor | (ww[:, 1] > 0))
    assert sel.sum() > 1000
    np.testing.assert_array_equal(V[sel], 1.0)


def test_parallel_visibility_many_directions_mask_and_one_direction_agree():
    box = trimesh.creation.box(extents=[1, 1, 1])
    box.apply_translation([0, 1, 0])
    meshes = [(box, 0), (_floor(3.0), 1)]
    rng = np.random.default_rng(3)
    pts = np.c_[rng.uniform(-2, 2, 500), np.zeros(500), rng.uniform(-2, 2, 500)]
    n = np.tile([0.0, 1.0, 0.0], (500, 1))
    w = rng.normal(size=(6, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    V = raycast.parallel_visibility(meshes, pts, w, normals=n)
    for j in range(6):
        np.testing.assert_array_equal(V[:, j], raycast.parallel_visibility(meshes, pts, w[j], normals=n))
    mask = rng.random(V.shape) < 0.5
    Vm = raycast.parallel_visibility(meshes, pts, w, normals=n, mask=mask)
    np.testing.assert_array_equal(Vm[mask], V[mask])
    below = (n @ w.T) <= 0
    np.testing.assert_array_equal(Vm[~mask], np.where(below[~mask], 0.0, 1.0))  # not cast: 1, or 0 below n


# ------------------------------------------------------------------------------------------------
# scattered shadow rays (ShadowRays): Embree with float64 hit checks against the float64 casters
# ------------------------------------------------------------------------------------------------
def _teapot_gbuffer(size=40):
    from ibl_ref.rendering.raster import prepare_scene, rasterize
    from ibl_ref.rendering.scenes import default_camera, teapot_on_ground

    meshes = teapot_on_ground()
    sc = prepare_scene(meshes, warn=False)
    gb = rasterize(sc, default_camera(meshes[:1], size=size))
    return sc, gb.position[gb.mask], gb.face_normal[gb.mask]


def test_shadow_rays_bvh_matches_projection_caster():
    # two float64 algorithms: per-ray Möller–Trumbore over bounding-sphere leaves (LeafBVH, rays offset by
    # 1e-6 R along n_f and ω) and per-direction 2D projection (parallel_visibility, blocking threshold 1e-6 R).
    # Rays toward shared directions from surface points of the teapot scene (16k triangles) agree exactly.
    sc, P, fn = _teapot_gbuffer(24)
    rng = np.random.default_rng(4)
    w = rng.normal(size=(12, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    want = raycast.parallel_visibility(sc, P, w, normals=fn)  # (P, 12); below the face plane → 0
    pix, j = np.nonzero(np.ones(want.shape, bool))
    got = raycast.ShadowRays(sc, "exact").visibility(P[pix], fn[pix], w[j])  # no groups: all by LeafBVH
    assert 0.2 < want.mean() < 0.8
    np.testing.assert_array_equal(got.reshape(want.shape), want)


def test_shadow_rays_embree_agrees_with_float64_casters():
    # Embree (float32, every hit re-tested in float64) against the float64 casters, on rays from the G-buffer
    # points of the teapot scene: scattered random directions (LeafBVH) and shared directions (projection caster).
    pytest.importorskip("embreex")
    sc, P, fn = _teapot_gbuffer(32)
    rng = np.random.default_rng(5)
    K = 8000
    pi = rng.integers(0, len(P), K)
    w = rng.normal(size=(K, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    w = np.where((np.einsum("kc,kc->k", w, fn[pi]) < 0)[:, None], -w, w)  # above the receiving face
    emb = raycast.ShadowRays(sc, "embree")
    ex = raycast.ShadowRays(sc, "exact")
    a, b = emb.visibility(P[pi], fn[pi], w), ex.visibility(P[pi], fn[pi], w)
    assert 0.1 < 1 - b.mean() < 0.9  # both outcomes are frequent
    np.testing.assert_array_equal(a, b)
    # shared directions (grazing ones included): the projection caster, no origin offset
    D = 24
    dirs = rng.normal(size=(D, 3))
    dirs[:4, 1] = 0.02  # nearly horizontal: grazing on the ground
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pp = np.repeat(np.arange(len(P)), D)
    gg = np.tile(np.arange(D), len(P))
    a = emb.visibility(P[pp], fn[pp], dirs[gg], groups=gg)
    b = ex.visibility(P[pp], fn[pp], dirs[gg], groups=gg)
    assert (a != b).sum() <= 2e-5 * len(a)  # the predicates differ only by the 1e-6 R offset (none seen here)
    assert emb.backend == "embree" and ex.backend == "exact"


def test_shadow_rays_below_face_plane_and_backend_errors(monkeypatch):
    sc = raycast.prepare_scene(_floor(1.0), warn=False)
    p = np.zeros((2, 3))
    n = np.tile([0.0, 1.0, 0.0], (2, 1))
    w = np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0]])
    for be in ("exact",) + (("embree",) if raycast.has_embreex() else ()):
        np.testing.assert_array_equal(raycast.ShadowRays(sc, be).visibility(p, n, w), [0, 1])
    with pytest.raises(IBLError, match="backend"):
        raycast.ShadowRays(sc, "optix")
    monkeypatch.setattr(raycast, "has_embreex", lambda: False)
    assert raycast.resolve_shadow_backend("auto") == "exact"
    with pytest.raises(IBLError, match="embreex"):
        raycast.ShadowRays(sc, "embree")
