"""Tests of ibl_ref.raycast: exact visibility against closed-form occlusion by a sphere and a box."""

import numpy as np
import pytest
import trimesh

from ibl_ref import raycast
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
