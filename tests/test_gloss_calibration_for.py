"""gloss_calibration.calibration_for: the shipped table where one exists, a computed one otherwise (what
``ibl-ref render --env-size N`` uses for face sizes without a shipped table, e.g. 1024²)."""

import numpy as np
import pytest

from ibl_ref.errors import IBLError
from ibl_ref.knuth2014.gloss_calibration import calibrate, calibration_for
from ibl_ref.knuth2014.gloss_lookup import get_calibration, shipped_calibration
from ibl_ref.knuth2014.pyramid import build_pyramid


def test_shipped_table_is_returned_as_is():
    cal = calibration_for(8)
    assert cal.source.startswith("calibration_sqrtcos_") and cal.source.endswith("_8.json")
    assert cal is shipped_calibration(8)


def test_missing_table_is_computed_and_matches_the_analysis():
    # no table is shipped for the filter-then-shrink order; the lookup alone refuses it ...
    cube = np.ones((6, 8, 8, 1))
    pyr = build_pyramid(cube, kernel="box", order="filter_then_shrink")
    assert shipped_calibration(8, "box", "filter_then_shrink") is None
    with pytest.raises(IBLError, match="no shipped glossiness calibration"):
        get_calibration(pyr)
    # ... while calibration_for runs the lobe analysis: the same table as calling it directly
    cal = calibration_for(8, "box", "filter_then_shrink")
    ref = calibrate(8, "box", "filter_then_shrink")
    assert cal.source == "lobe_analysis"
    assert np.array_equal(cal.level, ref.level) and np.array_equal(cal.s_phong, ref.s_phong)
    # levels never rise with s and stay inside the pyramid
    assert np.all(np.diff(cal.level) <= 0) and cal.level.min() >= 0 and cal.level.max() <= pyr.max_level
