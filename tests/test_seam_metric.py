"""Tests of ibl_ref.knuth2014.seam_metric: neighbour seams must beat clamp seams (Knuth et al. 2014 Sec. 4)."""

import numpy as np

from ibl_ref.environment.envmap import texel_directions
from ibl_ref.knuth2014.pyramid import build_pyramid
from ibl_ref.knuth2014.seam_metric import seam_metric, seam_summary


def _smooth_map(n):
    d = texel_directions(n)
    return (1.5 + d @ np.array([0.3, 0.5, 0.7]))[..., None] + 0.3 * np.sin(3 * d[..., :1])


def test_counts_12_edges_8_corners():
    rows = seam_metric(build_pyramid(_smooth_map(8), "box"))
    for L in range(4):
        assert sum(r["level"] == L and r["kind"] == "edge" for r in rows) == 12
        assert sum(r["level"] == L and r["kind"] == "corner" for r in rows) == 8


def test_neighbour_beats_clamp():
    c = _smooth_map(32)
    nb = seam_summary(seam_metric(build_pyramid(c, "sqrtcos", seam="neighbour")))
    cl = seam_summary(seam_metric(build_pyramid(c, "sqrtcos", seam="clamp")))
    for a, b in zip(nb, cl):
        if a["level"] in (1, 2, 3, 4):  # filtered levels with an inner gradient (faces >= 2)
            assert a["ratio_max"] < b["ratio_max"], (a, b)
    # a seamless smooth map: seam step comparable to an inner step (ratio ~1, <2 allows the
    # face-distortion difference between across-seam and in-face texel spacing)
    assert max(a["ratio_max"] for a in nb if a["level"] <= 4) < 2.0


def test_constant_map_has_no_seams():
    rows = seam_metric(build_pyramid(np.ones((6, 8, 8, 1)), "cos", seam="clamp"))
    assert all(r["step"] < 1e-14 for r in rows)
