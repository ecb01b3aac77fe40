"""The calibration tables shipped in ibl_ref/data are what build_calibration_tables computes today.

The shipped JSON files were written by an earlier run of :func:`ibl_ref.knuth2014.gloss_lookup.build_calibration_tables`;
rebuilding them into a temporary folder must reproduce them, so the data cannot drift from the code that
defines it (Knuth et al. 2014, Sec. 5: the level for an exponent is the one whose lobe volume matches).
"""

import json

import numpy as np
import pytest

from ibl_ref.knuth2014 import gloss_lookup


@pytest.mark.parametrize("kernel", ["none", "box", "gauss", "cos", "sqrtcos"])
def test_shipped_16_tables_are_reproduced(kernel, tmp_path):
    paths = gloss_lookup.build_calibration_tables([16], kernels=(kernel,), data_dir=tmp_path)
    assert len(paths) == 2
    for p in paths:
        shipped = json.loads((gloss_lookup.DATA_DIR / p.name).read_text())
        rebuilt = json.loads(p.read_text())
        assert {k: v for k, v in shipped.items() if not isinstance(v, list)} == \
            {k: v for k, v in rebuilt.items() if not isinstance(v, list)}
        # same s grid and levels up to the optimiser's float rounding (levels are O(1); 1e-9 is far below
        # one texel's worth of level, 1/log2(16) = 0.25, and far above float64 noise of a 1-D root search)
        np.testing.assert_allclose(rebuilt["s_phong"], shipped["s_phong"], rtol=1e-12)
        np.testing.assert_allclose(rebuilt["level"], shipped["level"], atol=1e-9)
