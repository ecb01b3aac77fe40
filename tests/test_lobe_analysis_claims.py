"""Tests of the claim criteria of ibl_ref.experiments.claims on synthetic error curves (no pyramid)."""

import numpy as np

from ibl_ref.experiments.claims import FILTERS, _evaluate


def _curves(err_by_kernel, levels):
    s = np.geomspace(1, 1000, len(levels))
    return {k: (s, np.asarray(err_by_kernel[k], float), np.asarray(levels, float)) for k in FILTERS}


def test_paper_like_curves_reproduce_and_opposite_do_not():
    levels = [5, 4, 3, 2, 1.5, 1.0, 0.5, 0.2]
    paper = {  # hand-made curves that follow every statement of Sec. 5
        "none": [40, 20, 60, 15, 70, 20, 30, 40],
        "gauss": [20, 18, 18, 18, 18, 18, 25, 30],
        "cos": [15, 8, 6, 7, 8, 9, 9, 9],
        "box": [4, 6, 30, 5, 35, 6, 20, 30],
        "sqrtcos": [5, 6, 7, 6, 8, 7, 20, 30],
    }
    r = _evaluate(_curves(paper, levels))
    for key in ("box_best_s1", "box_about_4pct_s1", "none_bad_s1", "none_box_spike", "gauss_stable_high",
                "cos_below_10_all", "cos_below_10_mid", "cos_weak_s1", "sqrtcos_near_box_s1",
                "sqrtcos_better_high", "sqrtcos_degrades_resolution"):
        assert r[key][1], (key, r[key][0])
    flat = {k: [10.0] * len(levels) for k in FILTERS}
    flat["sqrtcos"] = [50.0] * len(levels)
    r = _evaluate(_curves(flat, levels))
    assert not r["sqrtcos_near_box_s1"][1] and not r["none_box_spike"][1] and not r["sqrtcos_better_high"][1]
