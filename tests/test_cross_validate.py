"""Tests of the cross-validation experiment's pieces (ibl_ref.experiments.cross_validate); its quick run is checked in
tests/test_experiments_quick.py (``check_cross_validate``)."""

import numpy as np
import pytest

from ibl_ref.experiments import cross_validate as cv


def test_compare_metrics_by_hand():
    # two 2×2 images, one pixel not covered by the second renderer
    ref = np.array([[[1.0] * 3, [2.0] * 3], [[3.0] * 3, [9.0] * 3]])
    mi = np.array([[[1.1] * 3, [1.8] * 3], [[3.0] * 3, [0.0] * 3]])
    m_ref = np.ones((2, 2), bool)
    m_mi = np.array([[True, True], [True, False]])
    c = cv.compare(ref, m_ref, mi, m_mi, noise_rel_l1=0.01, noise_rmse=0.0)
    assert c["n_pixels"] == 3 and c["mask_agreement"] == pytest.approx(0.75)
    assert c["rel_l1"] == pytest.approx(0.3 / 5.9)
    assert c["bias"] == pytest.approx(0.1 / 5.9)
    assert c["rmse"] == pytest.approx(np.sqrt((0.01 + 0.04) / 3))
    assert c["excess_rel_l1"] == pytest.approx(0.3 / 5.9 - 0.01)
    assert c["within_target"] is False


@pytest.mark.usefixtures("mitsuba_llvm")
def test_ggx_case_with_a_diffuse_part_on_both_mitsuba_routes():
    # GGX roughness 0.3 with kd = 0.5 (Mitsuba's built-in route: a blendbsdf that is exactly kd/π + GGX): three
    # rows — the built-in and the lab's Python BSDF against the separable reference, the lab's BSDF against the
    # height-correlated one — each within the target beyond Mitsuba's noise, the signed bias within the reference's
    # estimate + 3 noise units, and the Smith term measured between the reference's two forms
    st = dict(size=12, env_size=8, spp=512, envmap_height=256, rtol=4e-3)
    rows, meta, arrays = cv.case_job((0, ("sphere_on_plane", "sky_sun", "ggx0.3+kd0.5"), st))
    assert [(r["mitsuba_bsdf"], r["smith"]) for r in rows] == [
        ("roughconductor", "separable"), ("lab_ggx", "separable"), ("lab_ggx", "height_correlated")]
    assert meta["mitsuba"]["roughconductor/separable"]["materials"]["0"]["type"] == "blendbsdf"
    for r in rows:
        assert r["excess_rel_l1"] <= cv.TARGET_EXCESS_REL_L1 and r["within_target"], r
        assert abs(r["bias"]) <= r["ref_err_rel_l1"] + 3 * r["noise_rel_l1"], r
        assert r["envmap_height"] == 64 * 8  # ENVMAP_PX_PER_TEXEL: narrow lobes get a finer bitmap
    assert 0 < rows[2]["smith_term_rel_l1"] < 0.05 and rows[0]["smith_term_rel_l1"] == ""
    assert len(arrays) == 9
    # the two Mitsuba routes render the same function: their images agree within their noise
    a, b = (arrays[f"sphere_on_plane__sky_sun__ggx0.3+kd0.5__{k}__separable__mitsuba"] for k in ("roughconductor",
                                                                                                 "lab_ggx"))
    m = arrays["sphere_on_plane__sky_sun__ggx0.3+kd0.5__lab_ggx__separable__mask"]
    assert np.abs(a[m] - b[m]).sum() / np.abs(b[m]).sum() <= 3 * (rows[0]["noise_rel_l1"] + rows[1]["noise_rel_l1"])
