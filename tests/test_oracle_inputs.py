"""Oracle inputs of occlusion methods (:mod:`ibl_ref.occlusion.oracle_inputs`) against closed forms.

Independent expectations:

* the clamped-cosine SH projection Â_l Y_k(n)/π (Ramamoorthi & Hanrahan 2001), checked against a fine-grid
  quadrature done here;
* form factors of polygons from a point by the contour integral (Lambert's formula; Stokes' theorem on the
  projected solid angle): F = (1/2π) Σ_edges θ_e (Γ_e · n), θ_e the angle the edge subtends, Γ_e the unit normal
  of the plane through the point and the edge — exact for the triangulated occluders the caster sees; the coaxial
  disk F = R²/(R² + h²) and the perpendicular rectangle (Howell's catalogue of configuration factors, B-8 with
  Φ = π/2, Hamilton & Morgan 1952) check it;
* tolerances from the samples' own statistics: only cells that the occluder's silhouette may cut carry error, each
  term independent and bounded, so Hoeffding's inequality gives an allowance that fails with probability ≤ 1e-6
  (the seeds are fixed: the tests are deterministic).
"""

import math
import warnings

import numpy as np
import pytest
import trimesh

from ibl_ref.environment.envmap import cube_solid_angles, face_frames, texel_directions
from ibl_ref.errors import IBLError, IBLWarning
from ibl_ref.groundtruth.sh_basis import real_sh
from ibl_ref.occlusion import oracle_inputs as oi

UP = np.array([[0.0, 0.0, 1.0]])


# ------------------------------------------------------------------------------------------------
# scenes
# ------------------------------------------------------------------------------------------------
def plane(normal=(0.0, 0.0, 1.0), centre=(0.0, 0.0, 0.0), half=5.0, flip=False):
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    c = np.asarray(centre, float)
    v = [c + half * (sa * a + sb * b) for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    f = [[0, 1, 2], [0, 2, 3]]
    return trimesh.Trimesh(np.array(v), np.array(f)[:, ::-1] if flip else f, process=False)


def disk_polygon(R, h, M=256):
    ang = np.linspace(0.0, 2.0 * np.pi, M, endpoint=False)
    return np.c_[R * np.cos(ang), R * np.sin(ang), np.full(M, h)]


def fan(poly, flip=False):
    """The polygon as a triangle fan around its centroid (one-sided winding either way)."""
    M = len(poly)
    v = np.vstack([poly.mean(axis=0), poly])
    f = np.array([[0, 1 + i, 1 + (i + 1) % M] for i in range(M)])
    return trimesh.Trimesh(v, f[:, ::-1] if flip else f, process=False)


def wall_polygon(d, W, H):
    return np.array([[d, -W, 0.0], [d, W, 0.0], [d, W, H], [d, -W, H]])


# ------------------------------------------------------------------------------------------------
# closed forms
# ------------------------------------------------------------------------------------------------
def polygon_form_factor(poly, x, n):
    """Cosine-weighted solid angle / π of a planar polygon above the tangent plane of x (Lambert's contour
    formula)."""
    v = poly - x
    w = np.roll(v, -1, axis=0)
    g = np.cross(v, w)
    gn = np.linalg.norm(g, axis=1)
    theta = np.arctan2(gn, np.einsum("ec,ec->e", v, w))
    return abs(float((theta * (g @ n) / gn).sum())) / (2.0 * np.pi)


def wall_form_factor(d, W, H):
    """Point on the floor at distance d from the foot of a vertical rectangle of half-width W and height H, centred
    in front of it (two of Howell's B-8 corner cases at Φ = π/2)."""
    r = math.hypot(d, H)
    return (math.atan(W / d) - d / r * math.atan(W / r)) / np.pi


# ------------------------------------------------------------------------------------------------
# the error allowance: cells a convex polygon's silhouette may cut
# ------------------------------------------------------------------------------------------------
def cell_geometry(n):
    """Corners (K, 4, 3), centres (K, 3), angular radii (K,) and exact solid angles (K,) of the cells."""
    F = face_frames("openexr")
    e = np.linspace(-1.0, 1.0, n + 1)
    k = np.arange(6 * n * n)
    f, i, j = k // (n * n), (k // n) % n, k % n
    corners = []
    for du, dv in ((0, 0), (1, 0), (1, 1), (0, 1)):
        d = F[f, 0] + e[j + du][:, None] * F[f, 1] + e[i + dv][:, None] * F[f, 2]
        corners.append(d / np.linalg.norm(d, axis=1, keepdims=True))
    corners = np.stack(corners, axis=1)
    cen = texel_directions(n).reshape(-1, 3)
    rad = np.arccos(np.clip(np.einsum("kjc,kc->kj", corners, cen), -1, 1)).max(axis=1) * (1 + 1e-9) + 1e-12
    return corners, cen, rad, np.asarray(cube_solid_angles(n)).reshape(-1)


def silhouette_cells(poly, x, n_face):
    """Cells the silhouette of a convex polygon (seen from x) may cut: neither wholly inside its cone of directions
    (all corners inside: both are convex) nor wholly outside (the cell's bounding cap beyond one edge plane)."""
    corners, cen, rad, _ = cell_geometry(n_face)
    v = poly - x
    g = np.cross(v, np.roll(v, -1, axis=0))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    g *= np.sign(g @ v.mean(axis=0))[:, None]  # inward normals of the edge planes
    inside = (np.einsum("kjc,ec->kje", corners, g) >= 0).all(axis=(1, 2))
    outside = ((cen @ g.T) < -np.sin(rad)[:, None]).any(axis=1)
    return ~inside & ~outside


def hoeffding(ranges, n_sets, delta=1e-6):
    """t with P(|Σ terms| ≥ t) ≤ delta for independent zero-mean terms, one per (cell, set), the cell's term of the
    mean over the sets lying in an interval of length ranges[c] / S (Hoeffding's inequality)."""
    return math.sqrt(0.5 * math.log(2.0 / delta) * (np.asarray(ranges) ** 2).sum() / n_sets)


def hoeffding_allowance(poly, x, n_normal, n_face, n_sets):
    """Allowance on |estimate − exact| of a cosine-weighted blocked fraction (/π) of a convex polygon above x's
    horizon: the estimate is unbiased and only silhouette cells are random; cell c's term lies in an interval of
    length a_c = Ω_c max_cell cos / π."""
    _, cen, rad, om = cell_geometry(n_face)
    theta = np.arccos(np.clip(cen @ n_normal, -1, 1))
    a = om * np.cos(np.clip(theta - rad, 0.0, np.pi / 2)) / np.pi
    return hoeffding(a[silhouette_cells(poly, x, n_face)], n_sets)


def ratio_allowance(poly, x, n_normal, n_face, n_sets, denominators):
    """Allowance on |N/D − r0| for the horizon-restricted visible fraction r0 = N0/D0 (no cosine): N and D are
    unbiased, so N − r0·D has mean 0 and only cells cut by the silhouette or by the horizon are random, each term
    Ω_c up_c (V_c − r0) in an interval of length Ω_c; divided by the smallest D of the sets."""
    corners, _, _, om = cell_geometry(n_face)
    c = corners @ n_normal
    horizon = (c > 0).any(axis=1) & (c < 0).any(axis=1)
    return hoeffding(om[silhouette_cells(poly, x, n_face) | horizon], n_sets) / min(denominators)


# ------------------------------------------------------------------------------------------------
# unoccluded
# ------------------------------------------------------------------------------------------------
def test_unoccluded_point_is_exact():
    n = np.array([0.3, -0.5, 0.8])
    n /= np.linalg.norm(n)
    x = np.array([[0.2, 0.1, -0.3]])
    vs = oi.trace_visibility(plane(n, x[0]), x, n[None], n[None], n_face=8, seed=3)
    ao, err = oi.ambient_occlusion(vs)
    assert abs(ao[0] - 1.0) <= 1e-12 and err[0] == 0.0
    b, be = oi.bent_normal(vs)
    assert np.allclose(b[0], n, atol=1e-12, rtol=0) and be[0] == 0.0
    axis, cos_ap = oi.visibility_cone(vs)
    assert np.allclose(axis, b) and cos_ap[0] <= 1e-6
    for order in (3, 5):
        T, Te = oi.sh_transfer(vs, order)
        A = np.array([np.pi, 2 * np.pi / 3, np.pi / 4, 0.0, -np.pi / 24])[:order]
        band = np.repeat(np.arange(order), 2 * np.arange(order) + 1)
        closed = A[band] / np.pi * real_sh(n, order - 1)
        assert np.allclose(T[0], closed, atol=1e-12, rtol=0) and np.all(Te == 0)


def test_clamped_cosine_projection_matches_fine_grid_quadrature():
    """The closed form Â_l Y_k(n)/π against Σ_t max(n·ω_t, 0)/π Y_k(ω_t) Ω_t on a 128² cube (midpoint rule; the
    kink at the horizon limits it to ~1e-5)."""
    d = texel_directions(128).reshape(-1, 3)
    om = np.asarray(cube_solid_angles(128)).reshape(-1)
    Y = real_sh(d, 4)
    A = oi.clamped_cosine_coefficients(5)
    assert np.allclose(A / np.pi, [1, 2 / 3, 1 / 4, 0, -1 / 24], rtol=0, atol=1e-15)
    band = np.repeat(np.arange(5), 2 * np.arange(5) + 1)
    rng = np.random.default_rng(1)
    for n in [np.array([0.0, 0.0, 1.0]), *rng.normal(size=(2, 3))]:
        n = n / np.linalg.norm(n)
        brute = (np.maximum(d @ n, 0.0) / np.pi * om) @ Y
        assert np.allclose(brute, A[band] / np.pi * real_sh(n, 4), atol=2e-5, rtol=0)


def test_jittered_directions_are_uniform_in_solid_angle():
    """Within one cell (a corner cell of face 0, the most distorted), the share of many draws falling in each of
    4×4 sub-rectangles matches the sub-rectangle's exact solid angle share."""
    m = 20000  # draws in cell 0 of face size 2 (face +X, row 0, col 0: u, v ∈ [-1, 0])
    d = oi._uniform_in_cells(2, np.random.default_rng(5).random((m, 2)), np.zeros(m, dtype=np.int64))
    u, v = d[:, 2] / d[:, 0], -d[:, 1] / d[:, 0]  # +X: (1, -v, u)
    assert u.min() >= -1 and u.max() <= 0 and v.min() >= -1 and v.max() <= 0
    from ibl_ref.environment.envmap import rect_solid_angle

    e = np.linspace(-1.0, 0.0, 5)
    tot = rect_solid_angle(-1.0, 0.0, -1.0, 0.0)
    for a in range(4):
        for b in range(4):
            share = rect_solid_angle(e[a], e[a + 1], e[b], e[b + 1]) / tot
            got = np.mean((u >= e[a]) & (u < e[a + 1]) & (v >= e[b]) & (v < e[b + 1]))
            assert abs(got - share) <= 4.5 * math.sqrt(share * (1 - share) / len(d))


# ------------------------------------------------------------------------------------------------
# occluded: a coaxial disk, a wall
# ------------------------------------------------------------------------------------------------
def test_polygon_form_factor_helper_matches_disk_closed_form():
    for R, h in ((1.0, 1.0), (0.5, 2.0), (3.0, 0.4)):
        F = polygon_form_factor(disk_polygon(R, h, M=4096), np.zeros(3), UP[0])
        assert abs(F - R * R / (R * R + h * h)) < 1e-6


@pytest.mark.parametrize("flip", [False, True])
def test_disk_is_two_sided(flip):
    """Either winding of the occluder blocks alike (Embree and the float64 checks are two-sided)."""
    poly = disk_polygon(1.0, 1.0)
    a = oi.trace_visibility([plane(), fan(poly, flip=False)], np.zeros((1, 3)), UP, UP, n_face=8)
    b = oi.trace_visibility([plane(), fan(poly, flip=flip)], np.zeros((1, 3)), UP, UP, n_face=8)
    assert np.array_equal(a.bits, b.bits)
    assert 0.4 < oi.ambient_occlusion(a)[0][0] < 0.6


def test_disk_ambient_occlusion_and_bent_normal_within_error():
    """Several disks and seeds: |ao − exact| within max(4·err, the Hoeffding allowance); the bent normal is n within
    its error; and the error estimate is of the size of the actual errors (neither absurdly larger nor smaller)."""
    n_face, S = 16, 2
    actual, est = [], []
    for R, h in ((1.0, 1.0), (1.0, 0.5), (0.7, 1.3), (1.5, 0.6)):
        poly = disk_polygon(R, h)
        # the bent vector's z component, π − ∫_cap cos² dω (cap of half-angle α), sets the tilt a given error makes
        bz = np.pi - 2 * np.pi / 3 * (1 - (h / math.hypot(R, h)) ** 3)
        exact = 1.0 - polygon_form_factor(poly, np.zeros(3), UP[0])
        assert abs(exact - h * h / (R * R + h * h)) < 1e-3  # the polygon is the disk up to O(1/M²)
        allow = hoeffding_allowance(poly, np.zeros(3), UP[0], n_face, S)
        scene = [plane(), fan(poly)]
        for seed in range(4):
            vs = oi.trace_visibility(scene, np.zeros((1, 3)), UP, UP, n_face=n_face, n_sets=S, seed=seed)
            ao, err = oi.ambient_occlusion(vs)
            assert abs(ao[0] - exact) <= max(4 * err[0], allow), (R, h, seed, ao[0], exact, err[0], allow)
            b, be = oi.bent_normal(vs)
            tilt = math.acos(min(1.0, b[0] @ UP[0]))
            # each perpendicular component of the blocked part errs by at most π·allow (same cells, |ω_⊥| ≤ 1)
            assert tilt <= max(4 * be[0], math.sqrt(2) * np.pi * allow / bz), (tilt, be[0])
            actual.append(ao[0] - exact)
            est.append(err[0])
    rms_actual, rms_est = np.sqrt(np.mean(np.square(actual))), np.sqrt(np.mean(np.square(est)))
    assert rms_actual > 0 and 1 / 3 < rms_est / rms_actual < 3, (rms_actual, rms_est)


def test_wall_form_factor_and_bent_normal_tilt():
    d, W, H = 1.0, 6.0, 1.5
    poly = wall_polygon(d, W, H)
    F = wall_form_factor(d, W, H)
    assert abs(F - polygon_form_factor(poly, np.zeros(3), UP[0])) < 1e-12
    wall = trimesh.Trimesh(poly, [[0, 1, 2], [0, 2, 3]], process=False)
    floor = plane(half=20.0)
    allow = hoeffding_allowance(poly, np.zeros(3), UP[0], 16, 2)
    for seed in (0, 1):
        vs = oi.trace_visibility([floor, wall], np.zeros((1, 3)), UP, UP, n_face=16, seed=seed)
        ao, err = oi.ambient_occlusion(vs)
        assert abs(ao[0] - (1.0 - F)) <= max(4 * err[0], allow), (ao[0], 1 - F, err[0], allow)
        b, be = oi.bent_normal(vs)
        assert b[0, 0] < 0 and math.asin(-b[0, 0]) > 4 * be[0]  # away from the wall (at +x)
        axis, cos_ap = oi.visibility_cone(vs)
        assert np.allclose(axis, b) and abs(cos_ap[0] - math.sqrt(1 - ao[0])) < 1e-15


def test_sh_transfer_consistent_with_ambient_occlusion():
    """T_00 = ao·Y_00 (the same estimate); order 3 is the head of order 5."""
    poly = disk_polygon(1.0, 1.0)
    x = np.array([[0.3, 0.0, 0.0], [-0.5, 0.4, 0.0]])
    vs = oi.trace_visibility([plane(), fan(poly)], x, np.repeat(UP, 2, 0), np.repeat(UP, 2, 0), n_face=8, n_sets=3)
    ao, _ = oi.ambient_occlusion(vs)
    T3, e3 = oi.sh_transfer(vs, 3)
    T5, e5 = oi.sh_transfer(vs, 5)
    assert np.allclose(T3[:, 0], ao / (2 * math.sqrt(np.pi)), rtol=0, atol=1e-14)
    assert np.allclose(T5[:, :9], T3, rtol=0, atol=1e-14) and np.allclose(e5[:, :9], e3, rtol=0, atol=1e-14)
    assert T5.shape == (2, 25) and np.all(e5 > 0)


# ------------------------------------------------------------------------------------------------
# determinism and the cache
# ------------------------------------------------------------------------------------------------
def disk_case():
    poly = disk_polygon(1.0, 1.0)
    x = np.array([[0.0, 0.0, 0.0], [0.4, -0.2, 0.0], [1.5, 0.5, 0.0]])
    n = np.repeat(UP, 3, 0)
    return [plane(), fan(poly)], x, n


def test_same_seed_identical_other_seed_within_error():
    scene, x, n = disk_case()
    a = oi.trace_visibility(scene, x, n, n, n_face=12, seed=4)
    b = oi.trace_visibility(scene, x, n, n, n_face=12, seed=4, progress=True)
    c = oi.trace_visibility(scene, x, n, n, n_face=12, seed=5)
    assert np.array_equal(a.bits, b.bits) and np.array_equal(a.directions, b.directions)
    assert not np.array_equal(a.bits, c.bits)
    allow = hoeffding_allowance(disk_polygon(1.0, 1.0), x[0], UP[0], 12, 2)
    assert abs(oi.ambient_occlusion(a)[0][0] - oi.ambient_occlusion(c)[0][0]) <= 2 * allow
    # the first sets of a larger n_sets are the same sets
    d = oi.trace_visibility(scene, x, n, n, n_face=12, n_sets=3, seed=4)
    assert np.array_equal(d.bits[:2], a.bits)


def test_cache_round_trip_traces_no_rays(tmp_path, monkeypatch):
    scene, x, n = disk_case()
    a = oi.trace_visibility(scene, x, n, n, n_face=8, cache_dir=tmp_path)
    assert a.n_rays > 0 and not a.from_cache
    files = sorted(tmp_path.iterdir())
    assert [f.name for f in files] == [f"oracle_visibility_{a.key}.npz"]

    class NoRays:
        def __init__(self, *args, **kwargs):
            raise AssertionError("a cached call cast rays")

    monkeypatch.setattr(oi, "ShadowRays", NoRays)
    b = oi.trace_visibility(scene, x, n, n, n_face=8, cache_dir=tmp_path)
    assert b.from_cache and b.n_rays == 0 and b.key == a.key
    for f in ("bits", "normals", "face_normals", "directions", "solid_angles"):
        assert np.array_equal(getattr(a, f), getattr(b, f))
    assert np.array_equal(oi.ambient_occlusion(a)[0], oi.ambient_occlusion(b)[0])
    with pytest.raises(AssertionError, match="cast rays"):  # another seed is another key
        oi.trace_visibility(scene, x, n, n, n_face=8, seed=1, cache_dir=tmp_path)
    assert [f.name for f in sorted(tmp_path.iterdir())] == [files[0].name]


def test_corrupt_cache_is_traced_again_with_a_warning(tmp_path):
    scene, x, n = disk_case()
    a = oi.trace_visibility(scene, x, n, n, n_face=8, cache_dir=tmp_path)
    path = tmp_path / f"oracle_visibility_{a.key}.npz"
    other = tmp_path / "unrelated.npz"
    other.write_bytes(b"not ours")
    path.write_bytes(b"garbage")
    with pytest.warns(IBLWarning, match="unreadable"):
        b = oi.trace_visibility(scene, x, n, n, n_face=8, cache_dir=tmp_path)
    assert not b.from_cache and np.array_equal(a.bits, b.bits)
    assert other.read_bytes() == b"not ours"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert oi.trace_visibility(scene, x, n, n, n_face=8, cache_dir=tmp_path).from_cache  # rewritten whole
    assert sorted(f.name for f in tmp_path.iterdir()) == sorted([path.name, other.name])


def test_foreign_cache_under_our_name_is_traced_again(tmp_path):
    # a cache file of another scene (here: another seed) copied under this key's name: its stored key differs, so it
    # is traced again with a warning, never read as this scene's visibility
    scene, x, n = disk_case()
    a = oi.trace_visibility(scene, x, n, n, n_face=8, seed=1, cache_dir=tmp_path)
    b_key = oi.trace_visibility(scene, x, n, n, n_face=8, seed=2).key
    (tmp_path / f"oracle_visibility_{b_key}.npz").write_bytes((tmp_path / f"oracle_visibility_{a.key}.npz").read_bytes())
    with pytest.warns(IBLWarning, match="key differs"):
        b = oi.trace_visibility(scene, x, n, n, n_face=8, seed=2, cache_dir=tmp_path)
    assert not b.from_cache and np.array_equal(b.bits, oi.trace_visibility(scene, x, n, n, n_face=8, seed=2).bits)


def test_unwritable_cache_folder_keeps_the_traced_bits_with_a_warning(tmp_path):
    # a file where the cache folder should be (root ignores permission bits, this fails for everyone): one warning,
    # the traced visibility is returned, nothing is written
    scene, x, n = disk_case()
    blocker = tmp_path / "not_a_folder"
    blocker.write_bytes(b"mine")
    with pytest.warns(IBLWarning, match="not written"):
        a = oi.trace_visibility(scene, x, n, n, n_face=8, cache_dir=blocker / "cache")
    assert not a.from_cache and np.array_equal(a.bits, oi.trace_visibility(scene, x, n, n, n_face=8).bits)
    assert blocker.read_bytes() == b"mine" and sorted(p.name for p in tmp_path.iterdir()) == ["not_a_folder"]


# ------------------------------------------------------------------------------------------------
# region visibility
# ------------------------------------------------------------------------------------------------
def test_region_visibility_one_region_is_horizon_restricted_visible_fraction():
    scene, x, n = disk_case()
    vs = oi.trace_visibility(scene, x, n, n, n_face=16, n_sets=2)
    vis, err = oi.region_visibility(vs, np.full((6, 16, 16, 3), 0.7), np.zeros((6, 16, 16), int))
    per, den = [], []
    for s in range(vs.n_sets):
        V = np.unpackbits(vs.bits[s], axis=1, count=vs.n_cells).astype(float)
        up = n @ vs.directions[s].T > 0
        den.append((up * vs.solid_angles).sum(1))
        per.append((V * up * vs.solid_angles).sum(1) / den[-1])
    assert vis.shape == (3, 1)
    assert np.allclose(vis[:, 0], np.mean(per, axis=0), rtol=0, atol=1e-13)
    assert np.allclose(err[:, 0], np.std(per, axis=0, ddof=1) / math.sqrt(2), rtol=0, atol=1e-13)
    # on the axis: the unweighted visible fraction of the upper hemisphere, 1 − Ω_cap / 2π = cos α (polygon: ±1e-4)
    exact = 1.0 / math.sqrt(2.0)
    allow = ratio_allowance(disk_polygon(1.0, 1.0), x[0], UP[0], 16, 2, [d[0] for d in den]) + 1e-3
    assert abs(vis[0, 0] - exact) <= allow, (vis[0, 0], exact, allow)
    assert vis[2, 0] > vis[1, 0] > vis[0, 0]  # farther from the disk's axis, more is visible


def test_region_visibility_horizon_split_unoccluded_all_one():
    n = np.array([0.0, 0.6, 0.8])
    vs = oi.trace_visibility(plane(n), np.zeros((1, 3)), n[None], n[None], n_face=4)
    d = texel_directions(8)
    labels = (d @ n > 0).astype(int) + 2 * (d[..., 0] > 0)  # 4 regions cut by the horizon and by x = 0
    cube = np.random.default_rng(0).random((6, 8, 8, 3))
    vis, err = oi.region_visibility(vs, cube, labels)
    assert vis.shape == (1, 4) and np.all(vis == 1.0) and np.all(err == 0.0)


def test_region_visibility_disk_inside_zero_outside_one():
    """Regions: cells wholly inside the disk's cone of directions (inscribed circle), cells wholly outside it
    (circumscribed circle), and the cells between; random radiance."""
    M, R, h, n_face, N = 64, 1.0, 1.0, 8, 16
    poly = disk_polygon(R, h, M)
    vs = oi.trace_visibility([plane(), fan(poly)], np.zeros((1, 3)), UP, UP, n_face=n_face, n_sets=2, seed=2)
    corners, cen, rad, _ = cell_geometry(n_face)
    ang_in, ang_out = math.atan(R * math.cos(math.pi / M) / h), math.atan(R / h)
    inside = (np.arccos(np.clip(corners[..., 2], -1, 1)) < ang_in).all(axis=1)
    outside = np.arccos(np.clip(cen[:, 2], -1, 1)) - rad > ang_out
    lab_cell = np.where(inside, 0, np.where(outside, 1, 2)).reshape(6, n_face, n_face)
    labels = np.repeat(np.repeat(lab_cell, N // n_face, axis=1), N // n_face, axis=2)
    cube = np.random.default_rng(3).random((6, N, N, 3)) + 0.1
    vis, err = oi.region_visibility(vs, cube, labels)
    assert inside.any() and vis[0, 0] == 0.0 and err[0, 0] == 0.0
    assert vis[0, 1] == 1.0 and err[0, 1] == 0.0
    assert 0.0 < vis[0, 2] < 1.0


# ------------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------------
def test_bad_input_is_one_line_ibl_error():
    scene, x, n = plane(), np.zeros((2, 3)), np.repeat(UP, 2, 0)
    bad_x = x.copy()
    bad_x[1, 0] = np.nan
    bad_n = n.copy()
    bad_n[0, 2] = np.inf
    cases = [
        (dict(points=bad_x), "points: contains NaN"),
        (dict(normals=bad_n), "normals: contains NaN or Inf"),
        (dict(face_normals=2 * n), "face_normals: not unit"),
        (dict(normals=n[:1]), "normals: 1 rows for 2 points"),
        (dict(points=x[:, :2]), r"points: expected shape \(P, 3\)"),
        (dict(n_face=0), "n_face must be a positive integer"),
        (dict(n_sets=0), "n_sets must be a positive integer"),
        (dict(n_face=2.0), "n_face must be a positive integer"),
        (dict(seed=-1), "seed must be a non-negative integer"),
        (dict(ray_backend="optix"), "ray backend must be one of"),
    ]
    for kw, msg in cases:
        args = dict(points=x, normals=n, face_normals=n)
        args.update(kw)
        p, nn, fn = args.pop("points"), args.pop("normals"), args.pop("face_normals")
        with pytest.raises(IBLError, match=msg) as exc:
            oi.trace_visibility(scene, p, nn, fn, **args)
        assert "\n" not in str(exc.value)
    vs = oi.trace_visibility(scene, x, n, n, n_face=4)
    for cube, labels, msg in [
        (np.ones((6, 6, 6, 3)), np.zeros((6, 6, 6), int), "not a multiple of n_face=4"),
        (np.ones((6, 8, 8, 3)), np.zeros((6, 4, 4), int), "labels: expected shape"),
        (np.ones((6, 8, 8, 3)), -np.ones((6, 8, 8), int), "region indices must be >= 0"),
        (np.ones((6, 8, 8, 3)), np.zeros((6, 8, 8)), "integer region indices"),
        (-np.ones((6, 8, 8, 3)), np.zeros((6, 8, 8), int), "negative"),
    ]:
        with pytest.raises(IBLError, match=msg):
            oi.region_visibility(vs, cube, labels)
    with pytest.raises(IBLError, match="order must be a positive integer"):
        oi.sh_transfer(vs, 0)
    with pytest.raises(IBLError, match="expected VisibilitySamples"):
        oi.ambient_occlusion(np.zeros(3))


def test_one_set_has_unknown_error():
    scene, x, n = disk_case()
    vs = oi.trace_visibility(scene, x, n, n, n_face=8, n_sets=1)
    ao, err = oi.ambient_occlusion(vs)
    assert np.all(np.isnan(err)) and np.all((ao > 0) & (ao <= 1))
    assert np.all(np.isnan(oi.bent_normal(vs)[1]))


def test_no_points_and_unpacked_layout():
    vs = oi.trace_visibility(plane(), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), n_face=4)
    assert vs.bits.shape == (2, 0, 12) and oi.ambient_occlusion(vs)[0].shape == (0,)
    assert oi.sh_transfer(vs, 3)[0].shape == (0, 9) and oi.bent_normal(vs)[0].shape == (0, 3)
    # a cell's bit is 1 exactly where its direction is above the (shading = geometric) horizon of an open floor
    x = np.zeros((1, 3))
    vs = oi.trace_visibility(plane(), x, UP, UP, n_face=4, n_sets=1)
    assert vs.n_pixels == 1 and vs.n_cells == 96 and vs.n_rays == int((vs.directions[0] @ UP[0] > 0).sum())
    assert np.array_equal(vs.visibility(0)[0], (vs.directions[0] @ UP[0] > 0).astype(np.uint8))
    assert abs(vs.solid_angles.sum() - 4 * np.pi) < 1e-12


def test_region_visibility_has_no_horizon_bias():
    """A point enclosed by a sphere sees nothing: every region's part above the horizon has VIS = 0.  With the
    normal tilted, the horizon cuts many one-texel regions; a set whose point in such a cell fell below the horizon
    says nothing about it.  The mean of per-set ratios counted those sets as 1 (≈ the share of the cell below the
    horizon: 0.114 on average over these 35 texels, measured); the ratio of the sums is 0 unless every set fell below
    (probability ≈ 2^-16 for a cell cut in half, 16 sets)."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    sphere.invert()
    n = np.array([[1.0, 0.3, 1.0]]) / np.linalg.norm([1.0, 0.3, 1.0])
    vs = oi.trace_visibility(sphere, [[0.0, 0.0, 0.0]], n, n, n_face=8, n_sets=16)
    labels = np.arange(6 * 64).reshape(6, 8, 8)
    vis, err = oi.region_visibility(vs, np.ones((6, 8, 8, 3)), labels)
    d = texel_directions(8).reshape(-1, 3)
    corners_up = d @ n[0]  # the texel centres against the horizon
    cut = (corners_up > 0) & (corners_up < 0.15)  # centre above, near the horizon (most of them cut by it)
    assert cut.sum() > 20
    assert float(np.mean(vis[0, cut])) < 0.05
    assert np.all(vis[0, corners_up > 0.3] == 0.0)
