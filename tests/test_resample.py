"""Resampling (ibl_ref.environment.resample): constants, ∫L dω conservation, convergence, crosses, face lists."""

from __future__ import annotations

import numpy as np
import pytest

from ibl_ref.environment import envmap
from ibl_ref.environment import resample as R
from ibl_ref.errors import LayoutError, RadianceError

RNG = np.random.default_rng(42)


def f_smooth(d):
    """A smooth positive test function on the sphere (3 channels)."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.stack([1 + 0.5 * x + 0.3 * y * z, np.exp(2 * (0.6 * x + 0.8 * y)), 2 + np.sin(3 * x) * np.cos(2 * z)], -1)


S = 8  # sub-samples per texel edge of the independent brute-force texel averages


def latlong_average(h):
    """Area average of f_smooth over every lat-long texel (midpoint rule on an S-times finer grid)."""
    d = envmap.latlong_directions(h * S, 2 * h * S)
    w = envmap.latlong_solid_angles(h * S, 2 * h * S)[:, 0]
    v = (f_smooth(d) * w[:, None, None]).reshape(h, S, 2 * h, S, 3).sum(axis=(1, 3))
    return v / (w.reshape(h, S).sum(1) * S)[:, None, None]


def cube_average(n):
    """Area average of f_smooth over every cube texel (midpoint rule on an S-times finer face)."""
    d = envmap.texel_directions(n * S)
    w = envmap.texel_solid_angles(n * S)
    v = (f_smooth(d) * w[None, :, :, None]).reshape(6, n, S, n, S, 3).sum(axis=(2, 4))
    return v / w.reshape(n, S, n, S).sum(axis=(1, 3))[None, :, :, None]


def exact_integral():
    """∫ f_smooth dω by the lat-long midpoint rule at a high resolution (independent of resample)."""
    h = 512
    d = envmap.latlong_directions(h, 2 * h)
    w = envmap.latlong_solid_angles(h, 2 * h)
    return np.einsum("ijc,i->c", f_smooth(d), w[:, 0])


# ---------------------------------------------------------------------------------------------
# constants and exact block averages
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method,interp", [("conservative", "bilinear"), ("gather", "bilinear"), ("gather", "box")])
def test_constant_maps_stay_constant(method, interp):
    # every destination value is a normalised weighted mean of source values: a constant is exact
    ll = np.full((12, 24, 2), [3.0, 0.25])
    cube = np.full((6, 5, 5, 2), [3.0, 0.25])
    kw = dict(method=method, interpolation=interp)
    for out in (R.latlong_to_cube(ll, 7, **kw), R.cube_to_latlong(cube, 9, **kw),
                R.cube_to_cube(cube, 3, interpolation=interp), R.cube_to_cube(cube, 7, interpolation=interp)):
        np.testing.assert_allclose(out, np.broadcast_to([3.0, 0.25], out.shape), rtol=1e-12)


def test_box_interpolation_stays_in_source_range():
    ll = RNG.uniform(1.0, 2.0, size=(16, 32))
    c = R.latlong_to_cube(ll, 6, method="gather", interpolation="box")
    assert c.shape == (6, 6, 6) and c.min() >= 1.0 - 1e-12 and c.max() <= 2.0 + 1e-12


def test_cube_downsample_by_integer_factor_is_exact_block_average():
    cube = RNG.uniform(0, 1, size=(6, 12, 12, 3))
    small = R.cube_to_cube(cube, 4)
    w = envmap.texel_solid_angles(12)
    # texel (f, i, j) of the 4² cube covers texels (3i..3i+2, 3j..3j+2) of the 12² cube
    i, j = 2, 1
    blk = (slice(3 * i, 3 * i + 3), slice(3 * j, 3 * j + 3))
    ref = np.einsum("abc,ab->c", cube[5][blk], w[blk]) / w[blk].sum()
    np.testing.assert_allclose(small[5, i, j], ref, rtol=1e-13)
    # Σ Ω L is conserved to rounding (the exact solid angle is additive)
    np.testing.assert_allclose(R.integral_cube(small), R.integral_cube(cube), rtol=1e-13)


# ---------------------------------------------------------------------------------------------
# ∫L dω conservation
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["conservative", "gather"])
@pytest.mark.parametrize("h", [16, 32, 64])
def test_integral_conserved_smooth(h, method):
    n = h // 2
    ll, cube = latlong_average(h), cube_average(n)
    ref = exact_integral()
    # the inputs themselves integrate f exactly up to the brute-force quadrature (≪ tolerance)
    np.testing.assert_allclose(R.integral_latlong(ll), ref, rtol=1e-4)
    for src_int, out_int in (
        (R.integral_latlong(ll), R.integral_cube(R.latlong_to_cube(ll, n, method=method))),
        (R.integral_cube(cube), R.integral_latlong(R.cube_to_latlong(cube, h, method=method))),
        (R.integral_cube(cube), R.integral_cube(R.cube_to_cube(cube, n + 3))),
    ):
        # midpoint quadrature of a bilinear interpolant: relative error O(p²), p = π/h the
        # lat-long texel pitch; bound p²/4 (measured residuals are 5-20x smaller)
        assert np.all(np.abs(out_int / src_int - 1) <= (np.pi / h) ** 2 / 4)


@pytest.mark.parametrize("h", [16, 64])
def test_single_texel_energy_conserved(h):
    """A one-texel "sun" anywhere (incl. the lat-long pole rows and cube corners) keeps its energy.

    Tolerance 2e-3: the design target of the balanced kernel (100 Sinkhorn steps leave a per-texel
    imbalance ≤ 1e-3, see ConservativeKernel).  The gather method is shown to miss it badly.
    """
    n = h // 2
    rows = [0, h - 1, 1, h // 3, h // 2]
    errs, errs_gather = [], []
    for r in rows:
        ll = np.zeros((h, 2 * h))
        ll[r, int(RNG.integers(0, 2 * h))] = 1.0
        errs.append(R.integral_cube(R.latlong_to_cube(ll, n)) / R.integral_latlong(ll) - 1)
        errs_gather.append(R.integral_cube(R.latlong_to_cube(ll, n, method="gather")) / R.integral_latlong(ll) - 1)
    for f, i, j in [(0, 0, 0), (2, n - 1, 0), (4, n // 2, n // 3), (5, 0, n - 1)]:
        cube = np.zeros((6, n, n))
        cube[f, i, j] = 1.0
        errs.append(R.integral_latlong(R.cube_to_latlong(cube, h)) / R.integral_cube(cube) - 1)
    assert np.max(np.abs(errs)) <= 2e-3
    assert np.max(np.abs(errs_gather)) > 0.05  # why the conservative kernel is the default


@pytest.mark.parametrize("h", [16, 32])
def test_integral_conserved_noise(h):
    # white noise: ∫ error = Σ_s (W_s/Ω_s − 1) Ω_s L_s; with per-texel imbalance ≤ 2e-3 (previous test)
    # the total is bounded by 2e-3 too
    ll = RNG.uniform(0, 1, size=(h, 2 * h, 3))
    cube = RNG.uniform(0, 1, size=(6, h // 2, h // 2, 3))
    r1 = R.integral_cube(R.latlong_to_cube(ll, h // 2)) / R.integral_latlong(ll) - 1
    r2 = R.integral_latlong(R.cube_to_latlong(cube, h)) / R.integral_cube(cube) - 1
    assert np.all(np.abs(r1) <= 2e-3) and np.all(np.abs(r2) <= 2e-3)
    # conserve=True rescales to the exact ratio
    c = R.latlong_to_cube(ll, h // 2, method="gather", conserve=True)
    np.testing.assert_allclose(R.integral_cube(c), R.integral_latlong(ll), rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# accuracy and round-trip convergence at 3 resolutions
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["conservative", "gather"])
def test_roundtrip_error_converges(method):
    errs = []
    kw = dict(method=method)
    for h in (16, 32, 64):
        n = h // 2
        ll, cube = latlong_average(h), cube_average(n)
        e_ll = np.abs(R.cube_to_latlong(R.latlong_to_cube(ll, n, **kw), h, **kw) - ll)
        e_cu = np.abs(R.latlong_to_cube(R.cube_to_latlong(cube, h, **kw), n, **kw) - cube)
        e_1 = np.abs(R.latlong_to_cube(ll, n, **kw) - cube)  # one step vs the independent exact averages
        e_2 = np.abs(R.cube_to_latlong(cube, h, **kw) - ll)
        errs.append([e.mean() for e in (e_ll, e_cu, e_1, e_2)] + [e.max() for e in (e_ll, e_cu, e_1, e_2)])
    errs = np.array(errs)
    ratio = errs[:-1] / errs[1:]
    # gather: O(h²) interpolation error → mean error ratio ≈ 4 per doubling; require ≥ 2.5.
    # conservative: the lat-long side is box-reconstructed inside the kernel, which adds a first-order
    # term (ratio between 2 and 4, measured 2.5-3.7); require ≥ 2.2
    assert np.all(ratio[:, :4] >= (2.5 if method == "gather" else 2.2)), ratio
    # max error is first order (lat-long pole slivers, cube-corner hats; module docstring): over two
    # doublings expect ≈ 4; require ≥ 2.5
    assert np.all(errs[0, 4:] / errs[2, 4:] >= 2.5), errs
    assert errs[-1, 0] < 3e-3 and errs[-1, 1] < 3e-3  # mean abs error at h=64 (values are O(0.1)..O(7))


# ---------------------------------------------------------------------------------------------
# crosses and face lists, checked against the OpenGL face table of docs/background.md §2
# ---------------------------------------------------------------------------------------------
def gl_direction(face, u, v):
    """OpenGL/D3D face orientation, (u→, v↓): +X:(−z,−y) −X:(+z,−y) +Y:(+x,+z) −Y:(+x,−z) +Z:(+x,−y) −Z:(−x,−y)."""
    one = np.ones_like(u)
    d = {
        0: (one, -v, -u), 1: (-one, -v, u), 2: (u, one, v), 3: (u, -one, -v), 4: (u, -v, one), 5: (-u, -v, -one),
    }[face]
    d = np.stack(d, -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


HCROSS = {2: (0, 1), 1: (1, 0), 4: (1, 1), 0: (1, 2), 5: (1, 3), 3: (2, 1)}  # face -> (cell row, cell col)
VCROSS = {2: (0, 1), 1: (1, 0), 4: (1, 1), 0: (1, 2), 3: (2, 1), 5: (3, 1)}


def _build_cross(n, cells, shape, rotate_neg_z=False):
    c = (np.arange(n) + 0.5) / n * 2 - 1
    v, u = np.meshgrid(c, c, indexing="ij")
    img = np.zeros((shape[0] * n, shape[1] * n, 3))
    for face, (r, col) in cells.items():
        d = gl_direction(face, u, v) + 2.0
        if rotate_neg_z and face == 5:
            d = d[::-1, ::-1]
        img[r * n : (r + 1) * n, col * n : (col + 1) * n] = d
    return img


@pytest.mark.parametrize("layout", ["hcross", "vcross"])
def test_cross_faces_match_directions(layout):
    n = 6
    img = (_build_cross(n, HCROSS, (3, 4)) if layout == "hcross" else _build_cross(n, VCROSS, (4, 3), True))
    cube = R.cross_to_cube(img, layout)
    np.testing.assert_allclose(cube, envmap.texel_directions(n) + 2.0, atol=1e-12)
    np.testing.assert_allclose(R.cube_to_cross(cube, layout), img, atol=1e-12)


@pytest.mark.parametrize("layout", ["hcross", "vcross"])
def test_cross_is_a_continuous_unfolding(layout):
    # neighbouring pixels of the cross (both in face cells) must be neighbouring directions: the angle
    # between them is at most one texel pitch 2·atan(1/n) (a misplaced or flipped face gives ≥ 45°)
    n = 8
    img = R.cube_to_cross(envmap.texel_directions(n) + 2.0, layout) - 2.0
    filled = np.abs(np.linalg.norm(img, axis=-1) - 1) < 1e-9  # face cells hold unit vectors, empty cells -2
    lim = 2 * np.arctan(1.0 / n) * (1 + 1e-9)
    for a, b in ((img[:, :-1], img[:, 1:]), (img[:-1], img[1:])):
        both = (np.abs(np.linalg.norm(a, axis=-1) - 1) < 1e-9) & (np.abs(np.linalg.norm(b, axis=-1) - 1) < 1e-9)
        ang = np.arccos(np.clip(np.einsum("...i,...i", a, b), -1, 1))[both]
        assert ang.size > 0 and ang.max() <= lim
    assert filled.sum() == 6 * n * n


@pytest.mark.parametrize("convention", ["opengl", "openexr"])
def test_faces_to_cube(convention):
    n = 5
    c = (np.arange(n) + 0.5) / n * 2 - 1
    v, u = np.meshgrid(c, c, indexing="ij")
    if convention == "opengl":
        faces = [gl_direction(f, u, v) for f in range(6)]
    else:
        faces = list(envmap.texel_directions(n))
    cube = R.faces_to_cube(faces, convention)
    np.testing.assert_allclose(cube, envmap.texel_directions(n), atol=1e-12)
    back = R.cube_to_faces(cube, convention)
    np.testing.assert_allclose(np.stack(back), np.stack(faces), atol=1e-12)


def test_bad_inputs():
    with pytest.raises(LayoutError, match=r"lat\-long map must have shape \(H"):
        R.latlong_to_cube(np.ones((8, 12, 3)), 4)
    bad = np.ones((8, 16, 3))
    bad[2, 3, 1] = np.nan
    with pytest.raises(RadianceError, match=r"lat\-long map: 1 non\-finite value\(s\) \(first"):
        R.latlong_to_cube(bad, 4)
    with pytest.raises(RadianceError, match=r"cube map: 288 negative radiance value\(s"):
        R.cube_to_latlong(-np.ones((6, 4, 4, 3)), 8)
    with pytest.raises(LayoutError, match=r"hcross: expected an image 4N wide"):
        R.cross_to_cube(np.ones((12, 12, 3)), "hcross")
    with pytest.raises(LayoutError, match=r"unknown cross layout 'diagonal'; choose one"):
        R.cross_to_cube(np.ones((12, 16, 3)), "diagonal")
    with pytest.raises(LayoutError, match=r"need 6 face images \(\+X, \-X"):
        R.faces_to_cube([np.ones((4, 4))] * 5)
    with pytest.raises(LayoutError, match=r"face images must all have the"):
        R.faces_to_cube([np.ones((4, 4))] * 5 + [np.ones((3, 3))])


def test_private_latlong_rows_match_envmap():
    full = envmap.latlong_directions(6, 12)
    np.testing.assert_array_equal(R._latlong_rows(6, 12, 2, 5), full[2:5])
