"""Tests of ibl_ref.knuth2014.filters (Knuth et al. 2014 Sec. 4 5-tap kernels, seam modes)."""

import numpy as np
import pytest

from ibl_ref.errors import IBLError
from ibl_ref.knuth2014.filters import KERNELS, SEAM_MODES, filter_cube, kernel_taps, pad_cube


@pytest.mark.parametrize("name", list(KERNELS) + ["cos^2", "cos^0"])
def test_kernels_sum_to_one_and_symmetric(name):
    w = kernel_taps(name)
    # normalisation is one division: sum exact to a few ulp
    assert abs(w.sum() - 1.0) < 1e-15 * 8
    assert np.allclose(w, w[::-1], rtol=0, atol=1e-17)


def test_cos_taps_from_published_angles():
    # independent: cos(60°) = 1/2, cos(30°) = √3/2 (Sec. 4: [cos(-60), cos(-30), cos 0, ...] / sum)
    raw = np.array([0.5, np.sqrt(3) / 2, 1.0, np.sqrt(3) / 2, 0.5])
    assert np.allclose(kernel_taps("cos"), raw / raw.sum(), rtol=1e-14)
    assert np.allclose(kernel_taps("sqrtcos"), np.sqrt(raw) / np.sqrt(raw).sum(), rtol=1e-14)
    assert np.allclose(kernel_taps("cos^0"), kernel_taps("box"), rtol=1e-14)


def test_unknown_kernel_lists_options():
    with pytest.raises(IBLError, match="sqrtcos"):
        kernel_taps("lanczos")
    with pytest.raises(IBLError, match=r"explicit kernel taps must be 5"):
        kernel_taps([1, 2, 3])


def test_unknown_seam_mode():
    with pytest.raises(IBLError, match="neighbour"):
        filter_cube(np.ones((6, 4, 4, 1)), "box", seam="wrap")


@pytest.mark.parametrize("seam", SEAM_MODES)
@pytest.mark.parametrize("n", [1, 2, 8])
def test_constant_map_stays_constant(seam, n):
    c = np.full((6, n, n, 2), 3.25)
    out = filter_cube(c, "sqrtcos", seam)
    # weights sum to 1 and every padded value is 3.25: rounding only (a few ulp of 3.25)
    assert np.allclose(out, 3.25, rtol=0, atol=1e-14)


def test_pad_cube_matches_shared_pad_faces():
    from ibl_ref.environment.sampling import pad_faces

    rng = np.random.default_rng(1)
    for n in (2, 4, 8):
        c = rng.random((6, n, n, 3))
        assert np.array_equal(pad_cube(c, 2), pad_faces(c, 2))


def test_interior_equals_direct_2d_convolution():
    # independent route: explicit 5x5 outer-product correlation (loops) on a texel far from any edge
    rng = np.random.default_rng(2)
    c = rng.random((6, 16, 16, 1))
    w = kernel_taps("gauss")
    out = filter_cube(c, "gauss", "neighbour")
    f, r, col = 3, 7, 9
    ref = sum(w[a] * w[b] * c[f, r + a - 2, col + b - 2, 0] for a in range(5) for b in range(5))
    assert abs(out[f, r, col, 0] - ref) < 1e-14


def test_neighbour_reads_adjacent_face_clamp_does_not():
    # a lit texel on the right edge of +Z must leak into the neighbour face only with seam="neighbour"
    n = 8
    c = np.zeros((6, n, n, 1))
    c[4, 4, n - 1, 0] = 1.0
    nb = filter_cube(c, "box", "neighbour")
    cl = filter_cube(c, "box", "clamp")
    other = [f for f in range(6) if f != 4]
    assert nb[other].sum() > 0.1
    assert cl[other].sum() == 0.0


def test_single_pad_spreads_along_the_y_x_edge_repad_does_not():
    # +Y's right column touches +X (OpenEXR orientation, envmap docstring); a 5x5 box around a texel on
    # that column must cover 5 (along the edge) x 2 (depth) texels of +X.  The re-pad variant filters
    # across the edge twice and along it never: only 1 x 2 texels (the reason the default is single-pad).
    n = 8
    c = np.zeros((6, n, n, 1))
    c[2, 4, n - 1, 0] = 1.0
    single = filter_cube(c, "box", "neighbour")
    repad = filter_cube(c, "box", "neighbour_repad")
    assert int((single[0, ..., 0] > 0).sum()) == 10
    assert int((repad[0, ..., 0] > 0).sum()) == 2
