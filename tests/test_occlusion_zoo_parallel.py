"""Issue 42: the occlusion zoo's jobs give bit-identical data wherever they run.

The experiment splits into one job per (scene, environment) (:func:`ibl_ref.executors.map_jobs`); every job is
deterministic (seeded visibility sets, seeded GTAO, seeded reference, Embree hits re-checked in float64, BLAS held at
one thread in every job), so a run on two local worker processes must write exactly the serial run's numbers —
as ``tests/test_experiment_jobs.py`` checks for fig5 and cross-validate.  Compared: every data file, the CSVs
without their timing columns (floats are written with ``repr``, so equal text is equal bits), the image arrays bit
for bit, and the metadata without its times and load averages.

Two jobs (the crevice under the sky and under the uniform environment), two materials (diffuse and GGX), one method
of every kind of input, at a small size and loose tolerances: the check is of where the work runs, not of accuracy.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ibl_ref.atomic import read_csv
from ibl_ref.experiments import occlusion_zoo as oz

#: slow and the same in every installation (NumPy path, no optional tool): phase 2+3 of .ci/run skips it
pytestmark = pytest.mark.same_without_tools

SMALL = dict(envs=["sky_sun", "uniform"], materials=["diffuse", "metal0.3"],
             methods=["none", "ao-diffuse", "multibounce-ao", "gtso-exact-alpha", "lagarde2014-alpha", "prt-5",
                      "regions-exact"],
             shadow_filters=["vsm"], size=10, rtol=2e-2, ref_rtol=2e-2)
#: metadata keys that hold wall times or the machine's load, and the timing keys inside its per-case entries
TIMING_META = {"case_time_s", "load_average_start", "load_average_end", "total_time_s"}
TIMING_CASE = {"trace_time_s", "gtao_time_s"}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("occlusion_zoo_parallel")
    out = {}
    for name, jobs in (("serial", {}), ("w2", {"workers": 2})):
        oz.run(root / name, quick=True, **SMALL, **jobs)
        out[name] = root / name
    return out


def _untimed_rows(path: Path):
    return [{k: v for k, v in q.items() if "time" not in k} for q in read_csv(path)]


def test_csv_rows_are_identical(runs):
    a, b = runs["serial"], runs["w2"]
    rows = _untimed_rows(a / "occlusion_zoo.csv")
    # 2 environments x 2 materials x (5 methods x 2 input kinds + prt-5 + regions-exact-6 x 2) = 52 rows
    assert len(rows) == 52 and {q["env"] for q in rows} == {"sky_sun", "uniform"}
    assert rows == _untimed_rows(b / "occlusion_zoo.csv")
    # the rows hold real, differing numbers (not a column of zeros that would match trivially)
    assert len({q["rel_l1_frac"] for q in rows}) > 20
    for name in ("occlusion_zoo_budget.csv", "occlusion_zoo_disagreements.csv"):
        assert not any("time" in c for c in read_csv(a / name)[0])
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    assert (a / "occlusion_zoo_table.md").read_bytes() == (b / "occlusion_zoo_table.md").read_bytes()


def test_image_arrays_are_bit_identical(runs):
    with np.load(runs["serial"] / "occlusion_zoo_images.npz") as za, np.load(runs["w2"] / "occlusion_zoo_images.npz") \
            as zb:
        assert sorted(za.files) == sorted(zb.files) and len(za.files) > 10
        for k in za.files:
            x, y = za[k], zb[k]
            assert x.dtype == y.dtype and x.shape == y.shape, k
            assert x.tobytes() == y.tobytes(), k  # bitwise (also NaN payloads and signed zeros)


def test_metadata_matches_apart_from_times(runs):
    ma, mb = (json.loads((runs[k] / "occlusion_zoo_meta.json").read_text()) for k in ("serial", "w2"))
    assert set(ma) == set(mb)

    def untimed(meta):
        out = {k: v for k, v in meta.items() if k not in TIMING_META}
        for key in ("oracle_inputs", "screen_space_inputs"):
            out[key] = {case: {k: v for k, v in d.items() if k not in TIMING_CASE} for case, d in out[key].items()}
        return out

    ua, ub = untimed(ma), untimed(mb)
    assert ua == ub
    # the oracle's error estimates and the references' are among what matched
    assert set(ua["oracle_inputs"]) == {"crevice/sky_sun", "crevice/uniform"}
    assert all(d["ao_err_mean"] > 0 for d in ua["oracle_inputs"].values())
    assert ua["references"] and all(r["err_rel_l1"] > 0 for r in ua["references"].values())
