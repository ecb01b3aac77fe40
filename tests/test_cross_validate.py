"""The cross-validate experiment (quick) runs for real in CI: the lab's reference against Mitsuba 3 on one scene ×
three materials (diffuse, g = 0.9, g = 0.99) under a sky with a small 1e5-bright sun."""

import json

from ibl_ref.atomic import read_csv
from ibl_ref.experiments import cross_validate as cv


def test_quick_cross_validation(tmp_path):
    out = cv.run(tmp_path, quick=True)
    rows = read_csv(tmp_path / "cross_validate.csv")
    assert {r["material"] for r in rows} == {"diffuse", "g0.9", "g0.99"}
    for r in rows:
        assert float(r["mask_agreement"]) > 0.99  # same pixel-centre rays, same triangles
        # the target: the reference within 0.5 % rel. L1 of Mitsuba beyond Mitsuba's own noise
        assert float(r["excess_rel_l1"]) <= cv.TARGET_EXCESS_REL_L1, r
        assert r["within_target"] == "True"
        # and the signed bias (noise averages out of it) is within the reference's own estimate + 3 noise units
        assert abs(float(r["bias"])) <= float(r["ref_err_rel_l1"]) + 3 * float(r["noise_rel_l1"]), r
    meta = json.loads((tmp_path / "cross_validate_meta.json").read_text())
    assert meta["all_within_target"] and out["all_within_target"]
    assert all(c["mitsuba"]["renderer"] == "mitsuba" for c in meta["cases"])
    pngs = cv.plot(tmp_path)
    assert pngs and pngs[0].read_bytes()[:4] == b"\x89PNG"
