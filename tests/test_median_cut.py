"""Tests of ibl_ref.knuth2014.median_cut (Debevec 2008 median cut on the cube faces; Knuth et al. 2014 Sec. 3.1, 4)."""

import numpy as np
import pytest

from ibl_ref.environment.envmap import texel_directions, texel_solid_angles, direction_to_texel
from ibl_ref.errors import IBLError, LayoutError, RadianceError
from ibl_ref.knuth2014.median_cut import VARIANTS, check_partition, energy_spread, median_cut, region_angular_extent

N = 32


def _random_map(seed=0, n=N):
    rng = np.random.default_rng(seed)
    cube = rng.random((6, n, n, 3)) ** 4
    cube[4, 5, 7] = (5e4, 4e4, 3e4)  # a small bright "sun" texel
    return cube


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("n_lights", [6, 12, 36, 48, 96])
def test_partition_and_energy_identities(variant, n_lights):
    cube = _random_map(1)
    ls = median_cut(cube, n_lights, variant)
    assert len(ls) == n_lights
    chk = check_partition(ls, cube)
    # Eq. 1: every texel in exactly one region (checked from the rectangles, not the label map)
    assert chk["uncovered"] == 0 and chk["overlapping"] == 0 and chk["labels_match"]
    # Σ light colours = ∫L dω (independent reference: Σ L·Ω over the map, computed here);
    # float64 summation of 6·32² terms: relative rounding ≲ 6144·1.1e-16 ≈ 7e-13, so 1e-11 is generous.
    ref = np.einsum("fijc,ij->c", cube, texel_solid_angles(N))
    np.testing.assert_allclose(ls.rgb.sum(0), ref, rtol=1e-11)
    # solid angles tile the sphere: Σ Ω_i = 4π (same rounding argument)
    assert abs(ls.solid_angle.sum() - 4 * np.pi) < 1e-11
    # lights are unit vectors and lie inside their own region's face
    np.testing.assert_allclose(np.linalg.norm(ls.directions, axis=1), 1.0, atol=1e-14)
    f, r, c = direction_to_texel(ls.directions, N)
    assert np.array_equal(f, ls.regions[:, 0])
    inside = (r >= ls.regions[:, 1]) & (r < ls.regions[:, 2]) & (c >= ls.regions[:, 3]) & (c < ls.regions[:, 4])
    # a centroid of a rectangle on a face lies in the rectangle's spherical hull; its nearest texel can sit
    # on the boundary only by rounding, so demand every light inside its region
    assert inside.all()
    sp = energy_spread(ls)
    assert sp["max_over_min"] >= 1.0 and sp["cv"] >= 0.0


def test_per_face_counts_are_equal_per_face():
    ls = median_cut(_random_map(2), 36, "per-face")
    assert np.array_equal(np.bincount(ls.regions[:, 0], minlength=6), [6] * 6)


def test_single_lit_texel_one_region_holds_all_energy():
    cube = np.zeros((6, N, N, 3))
    cube[2, 9, 20] = (1.0, 2.0, 3.0)
    for n_lights in (6, 12, 48):
        ls = median_cut(cube, n_lights, "per-face")
        lit = np.nonzero(ls.energy > 0)[0]
        assert lit.size == 1
        i = lit[0]
        # colour = L·Ω of that texel (independent: closed-form exact solid angle of the texel)
        np.testing.assert_allclose(ls.rgb[i], np.array([1.0, 2.0, 3.0]) * texel_solid_angles(N)[9, 20], rtol=1e-12)
        # the light sits exactly at the texel centre direction
        np.testing.assert_allclose(ls.directions[i], texel_directions(N)[2, 9, 20], atol=1e-14)
        assert energy_spread(ls)["n_zero_energy"] == n_lights - 1


def test_constant_map_equal_solid_angles():
    cube = np.ones((6, 64, 64, 3))
    for n_lights in (6, 12, 24):
        # splits at the face's symmetry lines are exact: equal solid angles to rounding
        sa = median_cut(cube, n_lights, "per-face").solid_angle
        np.testing.assert_allclose(sa, 4 * np.pi / n_lights, rtol=1e-13)
    # 48 lights: the last split cuts a 32x32 quadrant at an integer column, so each half is off by at most
    # half a column: ½ · (largest column's share of the quadrant).  Bound computed from exact solid angles.
    om = texel_solid_angles(64)[:32, :32]
    half_col_share = 0.5 * om.sum(0).max() / om.sum()
    sa = median_cut(cube, 48, "per-face").solid_angle
    assert np.max(np.abs(sa / (4 * np.pi / 48) - 1)) <= 2 * half_col_share  # ×2: both halves' rounding
    assert half_col_share < 0.03


@pytest.mark.parametrize("variant", ["global", "variance"])
def test_first_split_is_the_brute_force_optimum(variant):
    """Independent route: direct sums over the texels (no SAT) for every boundary of the split face."""
    cube = _random_map(3, n=16)
    n = 16
    ls = median_cut(cube, 7, variant)
    w = (cube @ np.array([0.2126, 0.7152, 0.0722])) * texel_solid_angles(n)
    face_counts = np.bincount(ls.regions[:, 0], minlength=6)
    f = int(np.argmax(face_counts))
    assert face_counts[f] == 2
    a, b = ls.regions[ls.regions[:, 0] == f]
    # whole face: width and height are both 90°, ties go to the column axis
    assert a[1] == 0 and a[2] == n and b[1] == 0 and b[2] == n
    cut = a[4] if a[3] == 0 else b[4]
    d = texel_directions(n)[f]
    costs = []
    for k in range(1, n):
        wa, wb = w[f][:, :k], w[f][:, k:]
        if variant == "global":
            costs.append(abs(wa.sum() - wb.sum()))
        else:
            va = wa.sum() - np.sum(np.einsum("ij,ijk->k", wa, d[:, :k]) ** 2) / wa.sum()
            vb = wb.sum() - np.sum(np.einsum("ij,ijk->k", wb, d[:, k:]) ** 2) / wb.sum()
            costs.append(va + vb)
    assert cut == 1 + int(np.argmin(costs))
    if variant == "global":  # the most energetic face was split
        assert np.argmax(w.sum(axis=(1, 2))) == f


def test_lit_patch_at_known_direction_openexr_orientation():
    # OpenEXR table (ImfEnvmap.cpp): +Z face point (u, v) ↦ (−u, −v, 1).  Written by hand, not from code:
    # u = 0.5, v = −0.5 on +Z is the direction (−0.5, 0.5, 1) (up and towards −x).
    d0 = np.array([-0.5, 0.5, 1.0]) / np.linalg.norm([-0.5, 0.5, 1.0])
    n = 32
    cube = np.full((6, n, n, 3), 1e-3)
    cos = texel_directions(n) @ d0
    cube[cos > np.cos(np.radians(4.0))] = 100.0  # ~4° patch around d0
    ls = median_cut(cube, 12, "global")
    i = int(np.argmax(ls.energy))
    ang = np.degrees(np.arccos(np.clip(ls.directions[i] @ d0, -1, 1)))
    # energy centroid of the patch (or of the part of it in the brightest region) lies within the 4° cap
    assert ang < 4.0
    assert ls.regions[i, 0] == 4  # face +Z


def test_angular_extent_closed_form():
    # full face: edge midpoints (±1, 0, 1) are 90° apart
    w, h = region_angular_extent(0, 8, 0, 8, 8)
    assert abs(w - np.pi / 2) < 1e-15 and abs(h - np.pi / 2) < 1e-15
    # first column at the centre row: atan(−1 + 2/8) − atan(−1)
    w, _ = region_angular_extent(3, 5, 0, 1, 8)  # rows 3..5 → v_mid = 0
    assert abs(w - (np.arctan(-0.75) + np.pi / 4)) < 1e-15


def test_errors():
    cube = _random_map(4)
    with pytest.raises(IBLError, match="multiple of 6"):
        median_cut(cube, 7, "per-face")
    with pytest.raises(IBLError, match=">= 6"):
        median_cut(cube, 5, "global")
    with pytest.raises(IBLError, match="zero energy"):
        median_cut(np.zeros((6, 8, 8, 3)), 6)
    neg = cube.copy()
    neg[1, 2, 3, 0] = -1.0
    with pytest.raises(RadianceError, match="negative"):
        median_cut(neg, 6)
    nan = cube.copy()
    nan[0, 0, 0, 1] = np.nan
    with pytest.raises(RadianceError, match=r"median cut input: 1 non\-finite value\(s"):
        median_cut(nan, 6)
    with pytest.raises(LayoutError, match=r"median cut input: expected an array"):
        median_cut(np.ones((5, 8, 8, 3)), 6)
    with pytest.raises(IBLError, match="variant"):
        median_cut(cube, 6, "octree")
    sparse = np.zeros((6, 8, 8, 3))
    sparse[0, 1, 1] = 1.0
    sparse[0, 5, 5] = 1.0
    with pytest.raises(IBLError, match="carry energy"):
        median_cut(sparse, 12, "global")  # 2 lit texels + 5 dark faces = 7 < 12
    assert len(median_cut(sparse, 7, "global")) == 7
    with pytest.raises(IBLError, match="texels"):
        median_cut(np.ones((6, 2, 2, 3)), 30, "per-face")  # 5 regions on a 2x2 face
    with pytest.raises(LayoutError, match="luminance"):
        median_cut(np.ones((6, 4, 4, 2)), 6)


def _ref_angle(p, q):
    p, q = np.asarray(p, float), np.asarray(q, float)
    return np.arccos(np.clip(p @ q / np.linalg.norm(p) / np.linalg.norm(q), -1, 1))


def _ref_debevec_face(w, om, n, levels):
    """Independent reference: Debevec's recursion on one face, every region split at every level,
    direct sums (no SAT), angles via arccos of face-plane vectors."""
    regions = [(0, n, 0, n)]
    for _ in range(levels):
        nxt = []
        for r0, r1, c0, c1 in regions:
            e = lambda a: -1 + 2 * a / n
            vm, um = 0.5 * (e(r0) + e(r1)), 0.5 * (e(c0) + e(c1))
            width = _ref_angle([e(c0), vm, 1], [e(c1), vm, 1])
            height = _ref_angle([um, e(r0), 1], [um, e(r1), 1])
            cols = width >= height - 1e-12 if (c1 - c0) >= 2 else False
            block, oblk = w[r0:r1, c0:c1], om[r0:r1, c0:c1]
            slices = block.sum(0) if cols else block.sum(1)
            oslices = oblk.sum(0) if cols else oblk.sum(1)
            pre, opre = np.cumsum(slices)[:-1], np.cumsum(oslices)[:-1]
            imb = np.abs(2 * pre - slices.sum())
            j = np.lexsort((np.abs(opre - 0.5 * oslices.sum()), imb))[0]
            b = (c0 if cols else r0) + j + 1
            nxt += [(r0, r1, c0, b), (r0, r1, b, c1)] if cols else [(r0, b, c0, c1), (b, r1, c0, c1)]
        regions = nxt
    return sorted(regions)


def test_per_face_equals_debevec_recursion():
    n = 16
    cube = _random_map(5, n=n) + 0.01  # every texel lit
    om = texel_solid_angles(n)
    w = (cube @ np.array([0.2126, 0.7152, 0.0722])) * om
    ls = median_cut(cube, 6 * 8, "per-face")
    for f in range(6):
        mine = sorted(tuple(int(v) for v in r[1:]) for r in ls.regions if r[0] == f)
        assert mine == _ref_debevec_face(w[f], om, n, 3)


from hypothesis import given, settings, strategies as st  # noqa: E402


@settings(max_examples=40, deadline=None, derandomize=True)
@given(n=st.sampled_from([2, 4, 8]), seed=st.integers(0, 2**16), density=st.floats(0.05, 1.0),
       variant=st.sampled_from(VARIANTS), k=st.integers(1, 6))
def test_partition_property(n, seed, density, variant, k):
    rng = np.random.default_rng(seed)
    cube = rng.random((6, n, n, 3)) * (rng.random((6, n, n, 1)) < density)
    if not cube.any():
        cube[0, 0, 0] = 1.0
    n_lit = int(np.count_nonzero(cube.sum(-1)))
    dark = int(np.sum(~cube.reshape(6, -1).any(1)))
    n_lights = 6 * k
    feasible = n_lights <= 6 * n * n if variant == "per-face" else n_lights <= n_lit + dark
    if not feasible:
        with pytest.raises(IBLError, match=r"regions per face but a face has only" if variant == "per-face"
                           else r"dark face\(s\)\); every light needs at"):
            median_cut(cube, n_lights, variant)
        return
    ls = median_cut(cube, n_lights, variant)
    chk = check_partition(ls, cube)
    assert len(ls) == n_lights and chk["uncovered"] == 0 and chk["overlapping"] == 0
    assert chk["rgb_sum_rel_err"] < 1e-12
    if variant != "per-face":  # energy-driven variants never make a dark light on a lit face
        lit_faces = cube.reshape(6, -1).any(1)
        assert np.all(ls.energy[lit_faces[ls.regions[:, 0]]] > 0)


@pytest.mark.parametrize("n_lights", [6, 96])
def test_equivalent_lobes_of_regions(n_lights):
    # Independent routes: the cap's solid-angle closed form Ω = 2π(1 − cos α); the lobe integral closed form
    # 2π/(e+1) (Meunier Eq. 20), so scale · 2π/(e+1) = Ω and the lobes together carry 4π; the small-cap limit
    # e·α² → 2y*, (1+y*)e^{−y*} = 3/4 (Gaussian limit of Eq. 32–34, solved here by bisection).
    ls = median_cut(_random_map(5), n_lights, "per-face")
    lobes = ls.equivalent_lobes()
    om = ls.solid_angle
    np.testing.assert_allclose(2 * np.pi * (1 - np.cos(lobes.alpha)), om, rtol=1e-12)  # float64 round-off
    np.testing.assert_allclose(lobes.scale_energy * 2 * np.pi / (lobes.exponent + 1), om, rtol=1e-12)
    assert abs(np.sum(lobes.scale_energy * 2 * np.pi / (lobes.exponent + 1)) - 4 * np.pi) < 1e-11
    order = np.argsort(om)
    assert np.all(np.diff(lobes.exponent[order]) <= 1e-9 * lobes.exponent[order][1:])  # wider cap, broader lobe
    lo, hi = 0.5, 1.5
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if (1 + mid) * np.exp(-mid) > 0.75 else (lo, mid)
    small = lobes.alpha < 0.05  # O(α²) from the limit: < 0.3% at 0.05 rad
    if small.any():
        np.testing.assert_allclose(lobes.exponent[small] * lobes.alpha[small] ** 2, 2 * lo, rtol=3e-3)
    rec = ls.to_records()
    assert [r["equivalent_lobe_exponent"] for r in rec] == [float(e) for e in lobes.exponent]
    assert all(np.isfinite(r["cap_half_angle_rad"]) and r["equivalent_lobe_scale"] > 0 for r in rec)
