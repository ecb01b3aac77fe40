"""Cube-map and lat-long conventions, tested against their definitions.

The OpenEXR oracle below is an independent Python transcription of ``CubeMap::pixelPosition``,
``CubeMap::direction``, ``CubeMap::faceAndPixelPosition`` and ``LatLongMap::direction`` from OpenEXR's
``ImfEnvmap.cpp`` (the definition of the CUBE / LATLONG envmap layouts), not a call into ibl_ref.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate

from ibl_ref.environment import envmap as E
from ibl_ref.errors import LayoutError


# ---- OpenEXR ImfEnvmap.cpp transcription (corner-to-corner pixel addressing) -------------------
def exr_pixel_position(face, sof, pif):
    """CubeMap::pixelPosition: (x, y) pixel of the N x 6N strip for positionInFace pif."""
    minx, miny, maxx, maxy = 0, face * sof, sof - 1, face * sof + sof - 1
    px, py = pif
    return {
        0: (minx + py, maxy - px),
        1: (maxx - py, maxy - px),
        2: (minx + px, maxy - py),
        3: (minx + px, miny + py),
        4: (maxx - px, maxy - py),
        5: (minx + px, maxy - py),
    }[face]


def exr_direction(face, sof, pif):
    """CubeMap::direction."""
    p = (pif[0] / (sof - 1) * 2 - 1, pif[1] / (sof - 1) * 2 - 1) if sof > 1 else (0.0, 0.0)
    return {
        0: (1, p[0], p[1]),
        1: (-1, p[0], p[1]),
        2: (p[0], 1, p[1]),
        3: (p[0], -1, p[1]),
        4: (p[0], p[1], 1),
        5: (p[0], p[1], -1),
    }[face]


def exr_face_and_pif(d, sof):
    """CubeMap::faceAndPixelPosition."""
    ax, ay, az = abs(d[0]), abs(d[1]), abs(d[2])
    if ax >= ay and ax >= az:
        return (0 if d[0] > 0 else 1), ((d[1] / ax + 1) / 2 * (sof - 1), (d[2] / ax + 1) / 2 * (sof - 1))
    if ay >= az:
        return (2 if d[1] > 0 else 3), ((d[0] / ay + 1) / 2 * (sof - 1), (d[2] / ay + 1) / 2 * (sof - 1))
    return (4 if d[2] > 0 else 5), ((d[0] / az + 1) / 2 * (sof - 1), (d[1] / az + 1) / 2 * (sof - 1))


@pytest.mark.parametrize("n", [2, 3, 4, 7])
def test_cube_orientation_matches_openexr_definition(n):
    """Every strip pixel: OpenEXR's direction and ours lie on the same face, and their in-plane
    components are related exactly by the addressing change (corner-to-corner → texel centres):
    ours = exr · (N−1)/N (both map pixel i to a coordinate linear in i, symmetric about the centre)."""
    ours = E.texel_directions(n, normalize=False)
    seen = np.zeros((6, n, n), bool)
    for face in range(6):
        for a in range(n):
            for b in range(n):
                x, y = exr_pixel_position(face, n, (a, b))
                row, col = y - face * n, x
                assert 0 <= row < n and 0 <= col < n
                seen[face, row, col] = True
                d_exr = np.array(exr_direction(face, n, (a, b)), float)
                major = face // 2
                expect = d_exr * (n - 1) / n
                expect[major] = d_exr[major]
                np.testing.assert_allclose(ours[face, row, col], expect, atol=1e-14)
    assert seen.all()  # pixelPosition is a bijection onto the strip


def test_face_lookup_matches_openexr_face_and_pixel_position():
    rng = np.random.default_rng(3)
    d = rng.normal(size=(2000, 3))
    n = 9
    face, x, y = E.direction_to_texel_coords(d, n)
    for k in range(len(d)):
        f_exr, pif = exr_face_and_pif(d[k], n)
        assert face[k] == f_exr
        # pif is corner-to-corner in face-local (x, y); map it to the strip pixel and then compare the
        # continuous coordinates after the addressing change c_ours = (c_exr + ½)·N/(N−1)·… (affine)
        px, py = exr_pixel_position(f_exr, n, pif)
        # strip pixel position (corner-to-corner) → face-plane coordinate → our texel coordinate
        col_plane = px / (n - 1) * 2 - 1
        row_plane = (py - f_exr * n) / (n - 1) * 2 - 1
        ex, ey = E.uv_to_texel_coords(col_plane, row_plane, n)
        assert abs(ex - x[k]) < 1e-9 and abs(ey - y[k]) < 1e-9


def test_opengl_convention_matches_the_opengl_d3d_face_table():
    # the OpenGL cube-map face selection (OpenGL 4.6 core spec, Sec. 8.13, Table 8.19; the same layout in D3D, cmft,
    # CubeMapGen, py360convert), written as each face's (u→, v↓) axes: = +X:(−z,−y), −X:(+z,−y), +Y:(+x,+z), −Y:(+x,−z), +Z:(+x,−y), −Z:(−x,−y)
    table = {0: ((0, 0, -1), (0, -1, 0)), 1: ((0, 0, 1), (0, -1, 0)), 2: ((1, 0, 0), (0, 0, 1)),
             3: ((1, 0, 0), (0, 0, -1)), 4: ((1, 0, 0), (0, -1, 0)), 5: ((-1, 0, 0), (0, -1, 0))}
    axes = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]
    for f, (du, dv) in table.items():
        d0 = E.face_uv_to_direction(f, 0.0, 0.0, "opengl", normalize=False)
        np.testing.assert_array_equal(d0, axes[f])
        np.testing.assert_array_equal(E.face_uv_to_direction(f, 1.0, 0.0, "opengl", normalize=False) - d0, du)
        np.testing.assert_array_equal(E.face_uv_to_direction(f, 0.0, 1.0, "opengl", normalize=False) - d0, dv)


def test_convert_convention_preserves_directions():
    n = 5
    fun = lambda d: np.stack([d[..., 0] + 2 * d[..., 1] + 3 * d[..., 2], d[..., 0] * d[..., 2]], -1)
    exr = fun(E.texel_directions(n, "openexr"))
    gl = fun(E.texel_directions(n, "opengl"))
    np.testing.assert_allclose(E.convert_convention(exr, "openexr", "opengl"), gl, atol=1e-15)
    np.testing.assert_allclose(E.convert_convention(gl, "opengl", "openexr"), exr, atol=1e-15)
    with pytest.raises(ValueError, match="convention"):
        E.convert_convention(exr, "openexr", "d3d9")


# ---- solid angles -------------------------------------------------------------------------------
@pytest.mark.parametrize("n", list(range(1, 65)) + [100, 127, 128, 255, 256, 511, 512, 1000, 1024, 2047, 2048])
def test_solid_angles_sum_to_4pi(n):
    # telescoping sum of exact rectangle solid angles; 1e-12 is the stated bound (rounding ~1e-14)
    assert abs(E.cube_solid_angles(n).sum() - 4 * np.pi) <= 1e-12


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7])
def test_solid_angles_match_quadrature(n):
    """Independent route: dω = (1 + x² + y²)^(−3/2) dx dy integrated by adaptive quadrature."""
    om = E.texel_solid_angles(n)
    e = np.linspace(-1, 1, n + 1)
    for r in range(n):
        for c in range(n):
            val, err = integrate.dblquad(lambda y, x: (1 + x * x + y * y) ** -1.5, e[c], e[c + 1], e[r], e[r + 1],
                                         epsabs=1e-14, epsrel=1e-12)
            assert abs(om[r, c] - val) <= 1e-11 * max(val, 1e-3)


def test_solid_angles_symmetry_and_common_approximation_is_worse():
    om = E.texel_solid_angles(4)
    np.testing.assert_allclose(om, om[::-1], rtol=1e-14)
    np.testing.assert_allclose(om, om.T, rtol=1e-14)
    u, v = E.face_plane_grid(4)
    approx = (1 + u * u + v * v) ** -1.5 * (2 / 4) ** 2
    # the common centre-point approximation is off by percents at 4² faces (docs/background.md §2)
    assert np.max(np.abs(approx / om - 1)) > 0.01


# ---- round trips (property tests) --------------------------------------------------------------
@settings(max_examples=200, deadline=None)
@given(st.integers(1, 300), st.integers(0, 5), st.data(), st.sampled_from(E.CONVENTIONS))
def test_texel_direction_texel_round_trip(n, face, data, conv):
    row = data.draw(st.integers(0, n - 1))
    col = data.draw(st.integers(0, n - 1))
    d = E.texel_directions(n, conv)[face, row, col]
    f2, r2, c2 = E.direction_to_texel(d, n, conv)
    assert (int(f2), int(r2), int(c2)) == (face, row, col)


finite = st.floats(-1e3, 1e3, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(st.tuples(finite, finite, finite).filter(lambda t: max(map(abs, t)) > 1e-6), st.sampled_from(E.CONVENTIONS))
def test_direction_face_uv_round_trip(t, conv):
    d = np.array(t)
    f, u, v = E.direction_to_face_uv(d, conv)
    assert -1 <= u <= 1 and -1 <= v <= 1
    back = E.face_uv_to_direction(f, u, v, conv)
    np.testing.assert_allclose(back, d / np.linalg.norm(d), atol=1e-12)


def test_any_leading_shape():
    d = np.random.default_rng(0).normal(size=(2, 3, 4, 3))
    f, r, c = E.direction_to_texel(d, 8)
    assert f.shape == r.shape == c.shape == (2, 3, 4)
    # same values as one direction at a time (the shape handling changes nothing)
    for idx in np.ndindex(2, 3, 4):
        one = E.direction_to_texel(d[idx], 8)
        assert (f[idx], r[idx], c[idx]) == tuple(int(np.asarray(v)) for v in one)
    back = E.face_uv_to_direction(f, 0.1, 0.2)
    assert back.shape == (2, 3, 4, 3)
    for idx in np.ndindex(2, 3, 4):
        np.testing.assert_array_equal(back[idx], E.face_uv_to_direction(int(f[idx]), 0.1, 0.2))
    # and every texel found contains its direction: the direction's face is the one returned
    face, _, _ = E.direction_to_face_uv(d)
    np.testing.assert_array_equal(face, f)


# ---- lat-long -------------------------------------------------------------------------------------
def test_latlong_matches_openexr_definition():
    h, w = 8, 16
    d = E.latlong_directions(h, w)
    lat, lon = E.latlong_angles(h, w)
    # LatLongMap::direction: (sin λ cos φ, sin φ, cos λ cos φ); top row φ → +π/2, left column λ → +π
    ref = np.stack(np.broadcast_arrays(np.sin(lon)[None] * np.cos(lat)[:, None], np.sin(lat)[:, None],
                                       np.cos(lon)[None] * np.cos(lat)[:, None]), -1)
    np.testing.assert_allclose(d, ref, atol=1e-15)
    assert lat[0] > lat[-1] and lon[0] > lon[-1]
    assert abs(lat[0] - (np.pi / 2 - np.pi / (2 * h))) < 1e-15 and abs(lon[0] - (np.pi - np.pi / w)) < 1e-15
    # φ = 0, λ = 0 is +Z, λ = +π/2 is +X (ImfEnvmap.h)
    x, y = E.direction_to_latlong(np.array([[0, 0, 1.0], [1, 0, 0], [0, 1, 0]]), h, w)
    np.testing.assert_allclose(x[:2], [w / 2 - 0.5, w / 4 - 0.5])
    np.testing.assert_allclose(y[:2], [h / 2 - 0.5] * 2)
    assert y[2] == -0.5
    xx, yy = E.direction_to_latlong(d, h, w)
    np.testing.assert_allclose(xx, np.broadcast_to(np.arange(w), (h, w)), atol=1e-12)
    np.testing.assert_allclose(yy, np.broadcast_to(np.arange(h)[:, None], (h, w)), atol=1e-12)


def test_latlong_solid_angles_sum():
    for h in (1, 2, 5, 64, 1000):
        assert abs(np.broadcast_to(E.latlong_solid_angles(h, 2 * h), (h, 2 * h)).sum() - 4 * np.pi) < 1e-12


# ---- MIP description and bad input ---------------------------------------------------------------
def test_mip_levels():
    lv = E.mip_levels(16)
    assert [m.face_size for m in lv] == [16, 8, 4, 2, 1]
    assert lv[-1].texel_angle == pytest.approx(np.pi / 2)
    assert abs(sum(lv[2].solid_angles().ravel()) * 6 - 4 * np.pi) < 1e-12
    with pytest.raises(ValueError, match="power-of-two"):
        E.mip_levels(12)


def test_bad_inputs():
    with pytest.raises(ValueError, match="face size"):
        E.texel_solid_angles(0)
    with pytest.raises(ValueError, match="NaN"):
        E.direction_to_face_uv(np.array([np.nan, 0, 1]))
    with pytest.raises(ValueError, match="zero-length"):
        E.direction_to_face_uv(np.zeros(3))
    with pytest.raises(ValueError, match="trailing axis"):
        E.direction_to_face_uv(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="convention"):
        E.texel_directions(4, "directx")
    with pytest.raises(LayoutError, match=r"\(6, N, N"):
        E.check_cube_shape(np.zeros((5, 4, 4, 3)))
    with pytest.raises(LayoutError, match="2H x H"):
        E.latlong_directions(4, 4)


def test_rect_solid_angle_matches_the_solid_angle_integral():
    # dΩ = du dv / (1 + u² + v²)^{3/2} on the face plane at distance 1: a midpoint sum over a 2000² grid
    # (error O(h²) ≈ 1e-8 relative here) against the closed form of four area primitives
    from ibl_ref.environment.envmap import rect_solid_angle

    for u0, u1, v0, v1 in [(-0.3, 0.7, 0.1, 0.9), (-1.0, 1.0, -1.0, 1.0), (0.5, 1.0, -1.0, -0.8)]:
        n = 2000
        uc = u0 + (np.arange(n) + 0.5) * (u1 - u0) / n
        vc = v0 + (np.arange(n) + 0.5) * (v1 - v0) / n
        U, V = np.meshgrid(uc, vc)
        q = ((u1 - u0) / n * (v1 - v0) / n / (1 + U ** 2 + V ** 2) ** 1.5).sum()
        np.testing.assert_allclose(rect_solid_angle(u0, u1, v0, v1), q, rtol=1e-6)
    # a whole face is 4π/6
    np.testing.assert_allclose(rect_solid_angle(-1.0, 1.0, -1.0, 1.0), 4 * np.pi / 6, rtol=1e-14)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 8, 9, 16, 33, 64])
def test_texel_max_radius_is_the_brute_force_maximum_over_every_texel_of_every_face(n):
    """texel_max_radius evaluates one quadrant in face-plane coordinates; the reference takes every texel of
    every face, its unit centre and unit corner directions through face_uv_to_direction, and the angle
    atan2(|a × b|, a·b).  Both are accurate to a few ulp of the angle (atan2 of well-conditioned arguments), so
    they agree to 1e-13 relative; n = 1: the face centre to a face corner, atan √2 (closed form)."""
    e = np.linspace(-1.0, 1.0, n + 1)
    c = E.texel_center_uv(n)
    worst = 0.0
    for f in range(6):
        cen = E.face_uv_to_direction(f, c[None, :], c[:, None])
        for dr in (0, 1):
            for dc in (0, 1):
                k = E.face_uv_to_direction(f, e[None, dc : dc + n], e[dr : dr + n, None])
                ang = np.arctan2(np.linalg.norm(np.cross(cen, k), axis=-1), np.sum(cen * k, axis=-1))
                worst = max(worst, float(ang.max()))
    assert E.texel_max_radius(n) == pytest.approx(worst, rel=1e-13)
    if n == 1:
        assert E.texel_max_radius(1) == pytest.approx(np.arctan(np.sqrt(2.0)), rel=1e-14)


def test_face_blocks_are_the_blocks_by_explicit_indices():
    """face_blocks against an explicit gather: block (f, I, J), texel (i, j) is a[f, I·b + i, J·b + j]; a trailing
    channel axis rides along; blocks that do not tile the face raise LayoutError."""
    rng = np.random.default_rng(0)
    for F, m, b, rest in ((6, 8, 4, ()), (2, 6, 3, (3,)), (1, 5, 5, (2, 2)), (6, 4, 1, ())):
        a = rng.random((F, m, m) + rest)
        nb = m // b
        ref = np.array([[a[f, I * b + i, J * b + j] for i in range(b) for j in range(b)]
                        for f in range(F) for I in range(nb) for J in range(nb)])
        np.testing.assert_array_equal(E.face_blocks(a, b), ref)
    with pytest.raises(LayoutError):
        E.face_blocks(np.zeros((6, 6, 6)), 4)
