"""The occlusion zoo (experiment ``occlusion-zoo``): its quick run, checked on its own numbers and against
expectations that do not come from the occlusion formulas — exactness where a closed form says so, the zero of
the no-occlusion row, the budget walk adding up, the disagreement table read back from the rows.

Independent expectation used below: under a uniform environment (L ≡ 1) a diffuse surface reflects
kd · ∫ V max(n·ω, 0)/π dω = kd · AO, so AO on the diffuse term — and the PRT transfer, whose constant coefficient
is that same integral — is exact there; the only differences left are the reference's and the oracle AO's
estimated errors.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from ibl_ref.atomic import read_csv
from ibl_ref.errors import IBLError
from ibl_ref.experiments import occlusion_zoo as oz

#: slow and the same in every installation (NumPy path, no optional tool): phase 2+3 of .ci/run skips it
pytestmark = pytest.mark.same_without_tools


@pytest.fixture(scope="module")
def quick(tmp_path_factory, run_quick):
    out = tmp_path_factory.mktemp("occlusion_zoo")
    summary, figs, problems = run_quick(oz, out)
    return out, summary, figs, problems


def _rows(out, **match):
    return [r for r in read_csv(out / "occlusion_zoo.csv") if all(str(r[k]) == str(v) for k, v in match.items())]


def test_quick_run_figures_pass_the_layout_check(quick):
    out, _, figs, problems = quick
    assert figs and all(f.exists() and f.read_bytes()[:4] == b"\x89PNG" for f in figs)
    assert sorted(problems) == sorted(f.name for f in figs)
    assert {k: v for k, v in problems.items() if v} == {}


def test_every_method_has_a_row_and_no_occlusion_gives_nothing_back(quick):
    out, _, _, _ = quick
    meta = json.loads((out / "occlusion_zoo_meta.json").read_text())
    rows = read_csv(out / "occlusion_zoo.csv")
    labels = oz.method_labels(meta["settings"]["methods"], meta["settings"]["n_regions"])
    for mat in meta["settings"]["materials"]:
        assert {q["method"] for q in rows if q["material"] == mat} == set(labels)
    for q in _rows(out, method="none"):
        assert float(q["given_back_frac"]) == 0.0
        assert float(q["rel_l1_frac"]) == float(q["missing_visibility_rel_l1_frac"])
    # the scene occludes: missing visibility is a real error, well above the reference's own estimate
    for q in _rows(out, method="none", inputs="oracle"):
        assert float(q["missing_visibility_rel_l1_frac"]) > 5 * float(q["ref_err_rel_l1_frac"])
    # methods that read more than AO and the bent normal have no screen-space row; the per-region ones have one row
    # per shadow filter instead
    kinds = {(q["method"], q["inputs"]) for q in rows}
    for label in labels:
        has_ss = (label, "screen-space") in kinds
        assert has_ss == (not label.startswith(("prt", "regions")))
        if label.startswith("regions"):
            assert {k for m, k in kinds if m == label} == {"oracle"} | {
                "shadow-map:" + f for f in meta["settings"]["shadow_filters"]}


def test_missing_visibility_only_adds_light(quick):
    out, _, _, _ = quick
    # a physical property, not a formula: V <= 1, so the unoccluded image is brighter than the reference at every
    # pixel; its signed bias then equals its rel. L1 up to the reference's own error (the pixels where the
    # reference's noise crosses the unoccluded value), for every material
    for q in _rows(out, method="none", inputs="oracle"):
        assert float(q["bias_frac"]) >= float(q["rel_l1_frac"]) - 2 * float(q["ref_err_rel_l1_frac"])


def test_budget_walk_adds_up_to_the_methods_error(quick):
    out, _, _, _ = quick
    rows = read_csv(out / "occlusion_zoo.csv")
    for q in read_csv(out / "occlusion_zoo_budget.csv"):
        if q["step"].startswith("occlusion model"):
            r = [x for x in rows if (x["scene"], x["env"], x["material"], x["method"], x["inputs"]) ==
                 (q["scene"], q["env"], q["material"], q["method"], "oracle")][0]
            assert float(q["rel_l1_vs_ref_frac"]) == pytest.approx(float(r["rel_l1_frac"]), rel=1e-12)
    walks = {}
    for q in read_csv(out / "occlusion_zoo_budget.csv"):
        walks.setdefault((q["scene"], q["env"], q["material"], q["method"], q["inputs"]), []).append(q)
    for steps in walks.values():
        # signed biases of the steps add up to the last image's bias
        assert sum(float(s["bias_increment_frac"]) for s in steps) == pytest.approx(
            float(steps[-1]["bias_vs_ref_frac"]), abs=1e-12)


def test_disagreement_table_is_read_back_from_the_rows(quick):
    out, _, _, _ = quick
    rows = read_csv(out / "occlusion_zoo.csv")
    for d in read_csv(out / "occlusion_zoo_disagreements.csv"):
        ea = [float(q["rel_l1_frac"]) for q in rows if q["method"] == d["method_a"] and q["inputs"] == d["inputs"]
              and q["applicable"] == "True"]
        assert float(d["mean_rel_l1_a_frac"]) == pytest.approx(np.mean(ea), rel=1e-12)
        assert int(d["a_closer_cases"]) + int(d["b_closer_cases"]) <= int(d["n_cases"])


def test_uniform_light_makes_ao_and_prt_exact_on_a_diffuse_surface(tmp_path):
    summary = oz.run(tmp_path, quick=True, envs=["uniform"], materials=["diffuse"],
                     methods=["none", "ao-diffuse", "prt-3"], n_sets=4)
    assert summary["skipped"] == {}
    meta = json.loads((tmp_path / "occlusion_zoo_meta.json").read_text())
    oracle = meta["oracle_inputs"]["crevice/uniform"]
    for method in ("ao-diffuse", "prt-3"):
        q = _rows(tmp_path, method=method, inputs="oracle")[0]
        # what is left is the reference's estimated error and the oracle AO's (the mean of its per-pixel standard
        # errors, 4 of them: a 4-sigma allowance), relative to the mean image value kd * mean AO
        allowance = float(q["ref_err_rel_l1_frac"]) + 4 * oracle["ao_err_mean"] / 0.5
        assert float(q["rel_l1_frac"]) <= allowance
        assert float(q["given_back_frac"]) > 0.8


def test_bad_parameters_fail_before_any_file_is_written(tmp_path):
    out = tmp_path / "never"
    for kw, msg in ((dict(scenes=["moon"]), "unknown scene"), (dict(envs=["mars"]), "unknown environment"),
                    (dict(materials=["chrome"]), "unknown material"), (dict(methods=["magic"]), "magic"),
                    (dict(n_regions=[0]), "n-regions"), (dict(shadow_filters=["blur"]), "unknown shadow filter"), (dict(env_size=8, n_face=3), "multiple of --n-face"),
                    (dict(ref_rtol=0.0), "ref-rtol"), (dict(gtao_radius_scale=float("nan")), "gtao-radius-scale")):
        with pytest.raises(IBLError, match=msg):
            oz.run(out, quick=True, **kw)
        assert not out.exists()


def test_a_scene_without_occluders_is_refused_in_one_line(tmp_path, monkeypatch):
    import trimesh

    from ibl_ref.rendering import scenes

    plane = trimesh.Trimesh(vertices=[[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], faces=[[0, 2, 1], [0, 3, 2]])
    monkeypatch.setitem(scenes.OCCLUSION_SCENES, "flat", lambda: [plane])
    with pytest.raises(IBLError, match="no occluders") as exc:
        oz.run(tmp_path / "out", quick=True, scenes=["flat"], materials=["diffuse"], methods=["none"],
               shadow_filters=["vsm"])
    assert "\n" not in str(exc.value)

