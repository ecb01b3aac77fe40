"""The method-zoo experiment's inputs: bad parameters are one-line errors before any work, and nothing already in
the output folder is overwritten; missing probes and a missing cmft are skipped with the reason."""

import numpy as np
import pytest

from ibl_ref.errors import IBLError
from ibl_ref.experiments import method_zoo as mz


@pytest.mark.parametrize("params,word", [
    (dict(ggx_f0=1.5), "F0"), (dict(ggx_f0=-0.1), "F0"), (dict(materials=("ggx9",)), "unknown material"),
    (dict(methods=("split-sum-is-0",)), "unknown method"), (dict(envs=("moon",)), "unknown environment"),
    (dict(scenes=("cube",)), "unknown scene"), (dict(rtol=0.0), "rtol"), (dict(size=0), "size"),
    (dict(n_lights=0), "n-lights")])
def test_bad_parameters_write_nothing(tmp_path, params, word):
    keep = tmp_path / "method_zoo.csv"
    keep.write_text("an earlier result\n")
    with pytest.raises(IBLError) as e:
        mz.run(tmp_path, quick=True, **params)
    assert word.lower() in str(e.value).lower() and "\n" not in str(e.value)
    assert keep.read_text() == "an earlier result\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["method_zoo.csv"]


def test_cli_bad_f0_is_one_line_and_exit_code(tmp_path, capsys):
    from ibl_ref.cli import main

    out = tmp_path / "res"
    assert main(["experiment", "method-zoo", "--quick", "--ggx-f0", "2", "--out", str(out)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert any("f0" in line.lower() for line in err)
    assert not (out / "method-zoo" / "method_zoo.csv").exists()


def test_missing_inputs_are_skipped_with_the_reason(tmp_path, monkeypatch):
    monkeypatch.setenv("IBL_REF_PROBE_DIR", str(tmp_path / "no-probes"))
    cube, why = mz.environment("city", 8)
    assert cube is None and "no-probes" in why and "IBL_REF_PROBE_DIR" in why
    monkeypatch.setenv("IBL_REF_CMFT", str(tmp_path / "no-cmft"))
    res = mz.run(tmp_path / "out", quick=True, envs=("sky_sun", "city"), materials=("phong16",),
                 methods=("exact-lobe", "cmft"), size=6)
    assert "env city" in res["skipped"] and "method cmft" in res["skipped"]
    assert set(res["mean_rel_l1"]) == {"sphere/phong16/exact-lobe"}
    cube, why = mz.environment("sky_sun", 4)
    assert why is None and np.all(np.isfinite(cube))


def test_teapot_walk_starts_at_the_certified_reference(tmp_path):
    # occluded scene: the walk's first step is the reference renderer's own V ≡ 1 image, the second the lab's
    # adaptive texel integral of the same unoccluded shading — two independent exact integrators, which must agree
    # within the sum of their error estimates; the paper's Eq. 5 step then gives back part of the missing light
    import json

    res = mz.run(tmp_path, quick=True, scenes=("teapot",), envs=("sky_sun",), materials=("ggx0.6", "phong16"),
                 methods=("split-sum", "pyramid+vsm"), teapot_size=10)
    assert not res["skipped"]
    meta = json.loads((tmp_path / "method_zoo_meta.json").read_text())
    assert {(c["material"], c["method"]) for c in meta["checks"]} == {("ggx0.6", "split-sum"), ("phong16", "pyramid+vsm")}
    for c in meta["checks"]:
        assert c["integrator_increment_frac"] <= c["integrator_estimate_frac"], c
        assert c["final_minus_method_rel"] <= 1e-5 and abs(c["bias_sum_minus_total"]) < 1e-12
    from ibl_ref.atomic import read_csv

    b = {(q["method"], q["step"]): q for q in read_csv(tmp_path / "method_zoo_budget.csv")}
    assert float(b[("split-sum", "visibility")]["bias_increment_frac"]) > 0  # the missing shadows add light
    assert float(b[("pyramid+vsm", "pem_visibility")]["bias_increment_frac"]) < 0  # the VSMs take some back
