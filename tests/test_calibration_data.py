"""The calibration tables shipped in ibl_ref/data are what the Sec. 5 table builder computes today.

The shipped JSON files were written by :func:`ibl_ref.knuth2014.gloss_calibration.build_shipped_tables`;
rebuilding the small ones into a temporary folder must reproduce them, so the data cannot drift from the code that
defines it (Knuth et al. 2014, Sec. 5: the level for an exponent is the one whose lobe volume matches).  Whether the
tables are *right* is checked independently in ``tests/test_gloss_lookup.py`` (the run-time lookup's lobes against
the closed-form volumes, for every shipped table).
"""

import json

import numpy as np
import pytest

from ibl_ref.knuth2014 import gloss_calibration, gloss_lookup


def _same(paths):
    for p in paths:
        shipped = json.loads((gloss_lookup.DATA_DIR / p.name).read_text())
        rebuilt = json.loads(p.read_text())
        assert {k: v for k, v in shipped.items() if not isinstance(v, list)} == \
            {k: v for k, v in rebuilt.items() if not isinstance(v, list)}
        # same s grid and levels up to the optimiser's float rounding (levels are O(1); 1e-9 is far below
        # one texel's worth of level, 1/log2(16) = 0.25, and far above float64 noise of a 1-D root search)
        np.testing.assert_allclose(rebuilt["s_phong"], shipped["s_phong"], rtol=1e-12)
        np.testing.assert_allclose(rebuilt["level"], shipped["level"], atol=1e-9)


@pytest.mark.parametrize("kernel", ["none", "box", "gauss", "cos", "sqrtcos"])
def test_shipped_small_tables_are_reproduced(kernel, tmp_path):
    paths = gloss_calibration.build_calibration_tables([1, 2, 4, 8, 16], kernels=(kernel,), data_dir=tmp_path)
    assert len(paths) == 10
    _same(paths)


def test_shipped_solid_angle_tables_are_reproduced(tmp_path):
    paths = gloss_calibration.build_calibration_tables([4, 16], kernels=("sqrtcos",), shrink="solid_angle",
                                                       data_dir=tmp_path)
    assert [json.loads(p.read_text())["shrink"] for p in paths] == ["solid_angle"] * 4
    _same(paths)


def test_shipped_files_are_exactly_the_declared_set():
    # every configuration gloss_calibration.SHIPPED declares has its file, and there is no other table
    want = set()
    for spec in gloss_calibration.SHIPPED:
        for n in spec["face_sizes"]:
            for k in spec["kernels"]:
                for vol in ("integral", "radial"):
                    want.add(gloss_lookup.calibration_path(n, k, "shrink_then_filter", "neighbour", vol,
                                                           spec.get("shrink", "mean")).name)
    assert {p.name for p in gloss_lookup.DATA_DIR.glob("calibration_*.json")} == want
