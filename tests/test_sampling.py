"""Seam-aware padding and lookups: continuity across the 12 edges and 8 corners, O(N⁻²) accuracy."""

import itertools

import numpy as np
import pytest

from ibl_ref.environment import envmap as E
from ibl_ref.environment import sampling as S
from ibl_ref.errors import LayoutError


def smooth(d):
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return np.stack([1 + 0.5 * d[..., 0] + 0.3 * d[..., 1] ** 2, np.exp(d[..., 2]), np.sin(3 * d[..., 0] * d[..., 1]) + 2], -1)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


CORNERS = np.array(list(itertools.product([-1.0, 1.0], repeat=3)))
EDGES = [c for c in itertools.product([-1.0, 0.0, 1.0], repeat=3) if sum(x == 0 for x in c) == 1]


def _near(points, n, count, rng):
    """Directions within ~2 texels of the given cube-surface points."""
    p = np.repeat(np.asarray(points, float), count, axis=0)
    return _unit(_unit(p) + (2.0 / n) * rng.normal(size=p.shape))


@pytest.mark.parametrize("conv", E.CONVENTIONS)
def test_bilinear_error_shrinks_as_n_minus_2_near_edges_and_corners(conv):
    rng = np.random.default_rng(7)
    errs = {"corner": [], "edge": [], "any": []}
    sizes = [16, 32, 64, 128]
    for n in sizes:
        cube = smooth(E.texel_directions(n, conv))
        # points on each edge: one coordinate free
        edge_pts = []
        for e in EDGES:
            t = rng.uniform(-1, 1, 50)
            pts = np.tile(np.array(e), (50, 1))
            pts[:, [i for i, x in enumerate(e) if x == 0][0]] = t
            edge_pts.append(pts)
        dirs = {"corner": _near(CORNERS, n, 200, rng), "edge": _near(np.concatenate(edge_pts), n, 4, rng),
                "any": _unit(rng.normal(size=(5000, 3)))}
        for k, d in dirs.items():
            errs[k].append(np.abs(S.sample_bilinear(cube, d, conv) - smooth(d)).max())
    for k, e in errs.items():
        ratios = np.array(e[:-1]) / np.array(e[1:])
        # second order: halving h divides the error by ~4; 3 leaves room for the random sample points
        assert np.all(ratios > 3.0), (k, e, ratios)


def test_bilinear_is_continuous_across_every_edge_and_corner():
    rng = np.random.default_rng(11)
    n = 8
    cube = rng.random((6, n, n, 3)) * 10  # rough data: any discontinuity would show
    samp = S.CubeSampler(cube)
    eps = 1e-11
    for e in EDGES:  # straddle the edge: nudge each of the two non-zero coordinates outward
        free = [i for i, x in enumerate(e) if x == 0][0]
        pts = np.tile(np.array(e), (200, 1))
        pts[:, free] = rng.uniform(-1, 1, 200)
        fixed = [i for i in range(3) if i != free]
        a, b = pts.copy(), pts.copy()
        a[:, fixed[0]] *= 1 + eps
        b[:, fixed[1]] *= 1 + eps
        # a lies on one face, b on the other; the values must agree to O(eps · gradient)
        fa, _, _ = E.direction_to_face_uv(a)
        fb, _, _ = E.direction_to_face_uv(b)
        assert np.all(fa != fb)
        assert np.abs(samp.bilinear(a) - samp.bilinear(b)).max() < 1e-7
    for c in CORNERS:
        vals = []
        for k in range(3):
            p = c.copy()
            p[k] *= 1 + eps
            vals.append(samp.bilinear(p))
        assert np.ptp(np.array(vals), axis=0).max() < 1e-7


def test_bilinear_exact_at_texel_centres_and_preserves_constants_and_range():
    rng = np.random.default_rng(2)
    n = 6
    cube = rng.random((6, n, n, 2))
    np.testing.assert_allclose(S.sample_bilinear(cube, E.texel_directions(n)), cube, atol=1e-14)
    d = _unit(rng.normal(size=(4000, 3)))
    np.testing.assert_allclose(S.sample_bilinear(np.full((6, n, n), 3.5), d), 3.5, rtol=1e-14)
    # a single lit texel never produces negative or above-max values (no extrapolation overshoot)
    delta = np.zeros((6, n, n))
    delta[4, 0, n - 1] = 1.0
    d = np.concatenate([d, _near(CORNERS, n, 300, rng)])
    out = S.sample_bilinear(delta, d)
    assert out.min() >= 0.0 and out.max() <= 1.0


def test_nearest_returns_containing_texel():
    n = 5
    cube = np.arange(6 * n * n, dtype=float).reshape(6, n, n)
    np.testing.assert_array_equal(S.sample_nearest(cube, E.texel_directions(n)), cube)


def test_unfold_padding_copies_the_adjacent_neighbour_texels():
    """Independent check of the unfolding: folding the source texel's centre Q (on the neighbour's
    plane) by 90° about the shared edge must give the padded texel's centre P (on the extended plane):
    same coordinate along the edge, and depth beyond the edge (|P_b| − 1) = depth inside (1 − |Q_a|)."""
    n, k = 8, 2
    cube = np.arange(6 * n * n, dtype=float).reshape(6, n, n)
    pad = S.pad_faces(cube, k)
    assert pad.shape == (6, n + 2 * k, n + 2 * k)
    np.testing.assert_array_equal(pad[:, k:-k, k:-k], cube)
    centres = E.texel_directions(n, normalize=False).reshape(-1, 3)
    idx = np.arange(-k, n + k)
    checked = 0
    for f in range(6):
        a = f // 2
        for i, r in enumerate(idx):
            for j, c in enumerate(idx):
                inside_r, inside_c = 0 <= r < n, 0 <= c < n
                if inside_r == inside_c:
                    continue  # face interior, or a corner block (tested below)
                u, v = E.texel_coords_to_uv(c, r, n)
                P = E.face_uv_to_direction(f, u, v, normalize=False)
                src = int(pad[f, i, j])
                Q = centres[src]
                b = src // (n * n) // 2
                assert b != a
                third = 3 - a - b
                assert Q[third] == pytest.approx(P[third], abs=1e-12)
                assert abs(Q[b]) == pytest.approx(1.0) and np.sign(Q[b]) == np.sign(P[b])
                assert 1 - abs(Q[a]) == pytest.approx(abs(P[b]) - 1, abs=1e-12)
                assert np.sign(Q[a]) == np.sign(P[a])
                checked += 1
    assert checked == 6 * 4 * n * k


def test_unfold_padding_corner_is_mean_of_the_three_corner_texels():
    n = 4
    rng = np.random.default_rng(5)
    cube = rng.random((6, n, n))
    pad = S.pad_faces(cube, 1)
    # corner texel of +Z (openexr) at row 0, col 0 → the direction (+x, +y, +z) corner
    d = _unit(np.array([1.0, 1.0, 1.0]))
    # the three texels meeting at that cube corner
    owners = []
    for f in (0, 2, 4):
        fu, _, _ = E.direction_to_face_uv(d + 1e-9 * np.eye(3)[f // 2])
        assert fu == f
        _, r, c = E.direction_to_texel(d + 1e-9 * np.eye(3)[f // 2], n)
        owners.append(cube[f, r, c])
    assert pad[4, 0, 0] == pytest.approx(np.mean(owners), rel=1e-14)


def test_padding_dtypes_and_errors():
    cube = np.ones((6, 4, 4, 3), np.float16)
    assert S.pad_faces(cube, 1).dtype == np.float16
    assert S.pad_faces(cube, 2, mode="geometric").dtype == np.float16
    with pytest.raises(ValueError, match="padding width"):
        S.pad_faces(cube, 5)
    with pytest.raises(ValueError, match="mode"):
        S.pad_faces(cube, 1, mode="mirror")
    with pytest.raises(LayoutError, match=r"cube map: expected an array of"):
        S.sample_bilinear(np.ones((6, 4, 5)), np.array([0, 0, 1.0]))


def test_lookups_and_padding_are_linear_and_positive():
    """Σ_i lookup(PEM_i) = lookup(Σ_i PEM_i) (Knuth et al. Sec. 3.1 rely on it): the sampler must be a
    fixed linear operator; rounding-level tolerance."""
    rng = np.random.default_rng(9)
    n = 8
    x, y = rng.random((6, n, n, 3)), rng.random((6, n, n, 3)) * 1e3
    d = np.concatenate([_unit(rng.normal(size=(3000, 3))), _near(CORNERS, n, 200, rng)])
    lhs = S.sample_bilinear(2.0 * x + 0.5 * y, d)
    rhs = 2.0 * S.sample_bilinear(x, d) + 0.5 * S.sample_bilinear(y, d)
    np.testing.assert_allclose(lhs, rhs, rtol=1e-12, atol=1e-9)
    for mode in ("unfold", "geometric"):
        np.testing.assert_allclose(S.pad_faces(x + y, 2, mode=mode), S.pad_faces(x, 2, mode=mode) + S.pad_faces(y, 2, mode=mode),
                                   rtol=1e-12)
    # positivity: every padded value is a convex combination → within [min, max] of the data
    g = S.pad_faces(x, 2, mode="geometric")
    assert g.min() >= x.min() - 1e-15 and g.max() <= x.max() + 1e-15


def test_directions_exactly_on_edges_and_corners_give_finite_values_without_warnings():
    import warnings

    cube = np.random.default_rng(1).random((6, 4, 4, 3))
    pts = np.array([e for e in EDGES] + list(CORNERS), float)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = S.sample_bilinear(cube, pts)
        out1 = S.sample_bilinear(cube[..., 0], pts)
    assert np.all(np.isfinite(out)) and np.all(np.isfinite(out1))
    np.testing.assert_allclose(out[:, 0], out1, rtol=1e-14)


def test_leading_shapes_of_directions():
    rng = np.random.default_rng(4)
    cube = rng.random((6, 4, 4, 2))
    d = _unit(rng.normal(size=(5, 1, 7, 3)))
    out = S.sample_bilinear(cube, d)
    assert out.shape == (5, 1, 7, 2)
    np.testing.assert_allclose(out.reshape(-1, 2), S.sample_bilinear(cube, d.reshape(-1, 3)), rtol=1e-14)


@pytest.mark.parametrize("n", [1, 2])
def test_tiny_faces(n):
    """Face sizes 1 and 2 (the top of every MIP pyramid): constants exact, values within the data range,
    continuous across edges and corners, linear."""
    rng = np.random.default_rng(n)
    d = _unit(rng.normal(size=(3000, 3)))
    np.testing.assert_allclose(S.sample_bilinear(np.full((6, n, n, 2), 0.7), d), 0.7, rtol=1e-14)
    cube = rng.random((6, n, n))
    out = S.sample_bilinear(cube, d)
    assert out.min() >= cube.min() - 1e-15 and out.max() <= cube.max() + 1e-15
    np.testing.assert_allclose(S.sample_bilinear(cube, E.texel_directions(n)), cube, atol=1e-14)
    samp = S.CubeSampler(cube)
    for c in CORNERS:
        vals = [samp.bilinear(c * (1 + 1e-11 * np.eye(3)[k])) for k in range(3)]
        assert np.ptp(vals) < 1e-7
