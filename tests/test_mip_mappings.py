"""The engines' roughness ↔ MIP-level mappings (ibl_ref.prefilter.mip_mappings) and the mip-mappings experiment.

The mappings against values computed by hand from the engines' formulas (the sources in the module docstring), their
inverses, monotonicity and bad input; the experiment's quick run against its own numbers: at a level's own
roughness and texel centres a chain read under its own mapping returns that level, so its error is the chain's and
the reference's rigorous bounds and nothing else; a chain read under another mapping that picks another level is
further off (a real detection); a constant environment gives no error anywhere; the figures pass the layout check.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from ibl_ref.atomic import read_csv
from ibl_ref.errors import IBLError
from ibl_ref.experiments import mip_mappings as exp
from ibl_ref.prefilter import karis2013 as k
from ibl_ref.prefilter.mip_mappings import ROUGHNESS_MAPPINGS, ThreejsMapping, get_mapping
from ibl_ref.synthetic import synthetic_envs as se

M = ROUGHNESS_MAPPINGS
NAMES = ("linear", "filament", "unity", "unreal", "threejs")


# ---- the formulas, by hand --------------------------------------------------------------------------------------
def test_registry_names_and_defaults():
    assert tuple(M) == NAMES and all(m.name == n for n, m in M.items())
    assert {n: m.default_levels for n, m in M.items()} == {"linear": None, "filament": 5, "unity": 7, "unreal": 8,
                                                          "threejs": 11}
    assert {n: m.default_base for n, m in M.items()} == {"linear": None, "filament": 256, "unity": 128,
                                                        "unreal": 128, "threejs": 256}
    assert M["filament"].chain_sizes(256) == (256, 128, 64, 32, 16)
    assert M["unity"].chain_sizes(128) == (128, 64, 32, 16, 8, 4, 2)
    assert M["unreal"].chain_sizes(128) == (128, 64, 32, 16, 8, 4, 2, 1)
    assert M["linear"].chain_sizes(256) == (256, 128, 64, 32, 16, 8, 4, 2)  # ⌊log2 256⌋ = 8 levels
    assert M["threejs"].chain_sizes(256) == (256, 128, 64, 32) + (16,) * 7
    assert M["threejs"].chain_sizes(32) == (32,) + (16,) * 7
    for m in M.values():  # the smallest level at the default base
        assert m.min_face_size == min(m.chain_sizes(m.default_base or 256))
        assert m.source and m.formula and m.engine


@pytest.mark.parametrize("name, r, n, level", [
    ("linear", 0.25, 9, 2.0), ("linear", 1.0, 8, 7.0), ("linear", 0.0, 5, 0.0),
    ("filament", 0.5, 5, 3.0),  # 0.5·1.5·4
    ("filament", 0.25, 5, 1.75),  # 0.25·1.75·4
    ("unity", 0.5, 7, 4.05),  # 0.5·(1.7 − 0.35)·6
    ("unity", 1.0, 7, 6.0), ("unity", 0.2, 7, 1.872),  # 0.2·1.56·6
    ("unreal", 1.0, 8, 5.0),  # 8 − 3 + 0
    ("unreal", 0.5, 8, 3.8),  # 5 − 1.2
    ("unreal", 0.25, 9, 3.6),  # 6 − 2.4
    ("unreal", 0.01, 8, 0.0),  # 5 + 1.2·log2(0.01) = −2.97: clamped to the base
    ("threejs", 1.0, 11, 10.0), ("threejs", 0.8, 11, 9.0), ("threejs", 0.4, 11, 6.0),  # mips −2, −1, 2
    ("threejs", 0.6, 11, 7.5),  # mip (0.8 − 0.6)·3/0.4 − 1 = 0.5
    ("threejs", 0.21, 11, 4.0),  # mip 4: the 16² level
    ("threejs", 0.1, 11, 8.0 + 2.0 * np.log2(0.116)),  # mip −2·log2(0.116) = 6.214
    ("threejs", 0.05, 11, 0.0),  # mip 8.21 > lodMax 8: the base
])
def test_level_against_the_engines_formulas(name, r, n, level):
    assert float(M[name].level(r, n)) == pytest.approx(level, abs=1e-12)
    if r > 0:  # karis2013's look-up, by name
        assert float(k.level_of_roughness(r, n, name)) == pytest.approx(level, abs=1e-12)


@pytest.mark.parametrize("name, level, n, rough", [
    ("linear", 3, 5, 0.75), ("filament", 1, 5, 1 - np.sqrt(0.75)), ("filament", 3, 5, 0.5),
    ("unity", 6, 7, 1.0), ("unity", 0, 7, 0.0),
    ("unreal", 0, 8, 2 ** (-5 / 1.2)),  # the base stores r₀ = 0.0557
    ("unreal", 5, 8, 1.0), ("unreal", 4, 8, 2 ** (-1 / 1.2)),
    ("unreal", 6, 8, 1.0), ("unreal", 7, 8, 1.0),  # the engine's r > 1 levels: 1 here
    ("threejs", 0, 11, 0.0),  # the unfiltered source
    ("threejs", 4, 11, 0.21), ("threejs", 10, 11, 1.0), ("threejs", 6, 11, 0.4),
    ("threejs", 8, 11, 0.8 - 0.4 / 3),  # mip 0: a third of the way from (0.8, −1) to (0.4, 2)
    ("threejs", 1, 11, 2 ** -3.5 / 1.16),  # mip 7, the log branch
])
def test_roughness_against_the_engines_formulas(name, level, n, rough):
    assert float(M[name].roughness(level, n)) == pytest.approx(rough, abs=1e-12)
    assert float(k.roughness_of_level(level, n, name)) == pytest.approx(rough, abs=1e-12)


def _invertible(name, x, n):
    """Where level(roughness(ℓ)) = ℓ (module docstring of mip_mappings)."""
    if name == "unreal":
        return x <= n - 3
    if name == "threejs":
        mip = (n - 3) - x
        return not (4.0 < mip < -2.0 * np.log2(1.16 * 0.21))
    return True


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("n", [2, 5, 8, 11])
def test_round_trip_and_monotone(name, n):
    m = M[name]
    x = np.linspace(0.0, n - 1.0, 4 * (n - 1) * 25 + 1)
    rough = m.roughness(x, n)
    assert np.all((rough >= 0) & (rough <= 1)) and np.all(np.diff(rough) >= 0)
    ok = np.array([_invertible(name, v, n) for v in x])
    np.testing.assert_allclose(m.level(rough[ok], n), x[ok], atol=1e-9)
    r = np.linspace(0.0, 1.0, 2001)
    lv = m.level(r, n)
    assert np.all(np.diff(lv) >= -1e-12) and lv.min() >= 0 and lv.max() <= n - 1


def test_threejs_branches_and_gap():
    # the two branches do not meet at r = 0.21: the look-up jumps from mip 4 to 4.0748 just below it
    mip = ThreejsMapping.mip
    assert float(mip(0.21)) == pytest.approx(4.0)
    assert float(mip(0.21 - 1e-12)) == pytest.approx(-2 * np.log2(1.16 * 0.21), abs=1e-9)
    assert -2 * np.log2(1.16 * 0.21) == pytest.approx(4.0748, abs=1e-4)
    assert float(mip(0.0)) == np.inf
    gap_level = (11 - 3) - 4.03  # a fractional level no roughness reads
    assert float(M["threejs"].roughness(gap_level, 11)) == pytest.approx(0.21)


@pytest.mark.parametrize("bad", [-0.1, 1.5, np.nan, np.inf, "rough"])
def test_bad_roughness_is_one_line(bad):
    for m in M.values():
        with pytest.raises(IBLError, match="roughness") as e:
            m.level(bad, 5)
        assert "\n" not in str(e.value)


def test_unknown_mapping_and_bad_levels():
    with pytest.raises(IBLError) as e:
        get_mapping("ue5")
    assert str(e.value) == "mapping must be one of linear, filament, unity, unreal, threejs, got 'ue5'"
    for call in (lambda: k.roughness_of_level(1, 5, "ue5"), lambda: k.level_of_roughness(0.5, 5, "ue5"),
                 lambda: k.build_chain(se.env_constant(4), mapping="ue5")):
        with pytest.raises(IBLError, match="linear, filament, unity, unreal, threejs") as e:
            call()
        assert "\n" not in str(e.value)
    for n in (1, 0, 2.5, True):
        with pytest.raises(IBLError, match="n_levels"):
            M["unity"].level(0.5, n)
    with pytest.raises(IBLError, match="power of two"):
        M["unreal"].chain_sizes(48)
    with pytest.raises(IBLError, match="finite"):
        M["linear"].roughness(np.nan, 5)
    assert float(M["linear"].roughness(9, 5)) == 1.0  # levels beyond the chain are clamped (karis2013's rule)


def test_build_chain_follows_the_mapping():
    cube = se.env_studio(8)
    ue = k.build_chain(cube, n_levels=4, mapping="unreal", rtol=1e-3)  # 8² … 1²: r₀ = 2^(-1/1.2)
    assert ue.roughness[0] == pytest.approx(2 ** (-1 / 1.2)) and ue.roughness[1:] == (1.0, 1.0, 1.0)
    assert len(ue.info["bound_max"]) == 4 and max(ue.info["bound_max"]) <= 1e-3  # level 0 filtered too
    np.testing.assert_allclose(ue.levels[0], k.prefilter_dense(cube, ue.roughness[0]), rtol=1e-3)
    tj = k.build_chain(cube, n_levels=4, mapping="threejs", min_face_size=4)
    np.testing.assert_array_equal(tj.levels[0], cube)  # three.js: level 0 is the source
    assert tj.face_sizes == (8, 4, 4, 4) and len(tj.info["bound_max"]) == 3
    d = np.random.default_rng(1).normal(size=(30, 3))
    np.testing.assert_allclose(tj.lookup(d, 0.8), tj.lookup(d, 0.8, level_values=tj.level_values(d)), rtol=0)


# ---- the experiment ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def quick(tmp_path_factory, run_quick):
    out = tmp_path_factory.mktemp("mip_mappings")
    summary, figs, problems = run_quick(exp, out)
    return out, summary, figs, problems, read_csv(out / "mip_mappings.csv")


def test_quick_outputs_and_figures(quick):
    out, summary, figs, problems, rows = quick
    assert {p.name for p in out.iterdir()} >= {o for o in exp.OUTPUTS}
    assert figs and all(f.read_bytes()[:4] == b"\x89PNG" for f in figs)
    assert sorted(problems) == sorted(f.name for f in figs) and not any(problems.values())
    meta = json.loads((out / "mip_mappings_meta.json").read_text())
    assert len(meta["load_average_start"]) == 3 and meta["skipped"] == {}
    assert set(meta["summary"]["16"]["equal_memory_mean_rel_l1"]) == set(NAMES)
    # equal memory: every mapping's chain holds the same texels
    eq = {q["chain_texels"] for q in rows if q["layout"] == "equal-memory"}
    assert eq == {str(6 * sum(s * s for s in (16, 8, 4, 2, 1)))}
    assert "| stored \\ read |" in (out / "mip_mappings.md").read_text()
    assert summary["summary"]["16"]["worst_mismatch"]["pair"].split("->")[0] != \
        summary["summary"]["16"]["worst_mismatch"]["pair"].split("->")[1]


def test_on_a_level_the_own_mapping_is_within_the_bounds(quick):
    # at level ℓ's roughness and texel centres the look-up under the chain's own mapping is level ℓ itself (weight
    # 1, bilinear at texel centres): |a − e| ≤ bound_ℓ·e and |b − e| ≤ ref·e give |a − b|/b ≤ (bound_ℓ + ref)/(1 − ref)
    rows = [q for q in quick[4] if q["kind"] == "on-level" and q["stored_mapping"] == q["lookup_mapping"]]
    assert {q["stored_mapping"] for q in rows} == set(NAMES) and len(rows) >= 15
    for q in rows:
        assert float(q["level_read"]) == pytest.approx(float(q["level_stored"]), abs=1e-9)
        bound, ref = float(q["level_rel_bound_max"]), float(q["ref_rel_bound_max"])
        assert bound <= 1e-3 and ref <= 1e-4
        assert float(q["rel_err_max_frac"]) <= (bound + ref) / (1 - ref) + 1e-12, q


def test_a_mismatch_that_reads_another_level_is_detected(quick):
    rows = [q for q in quick[4] if q["kind"] == "on-level"]
    own = {(q["stored_mapping"], q["level_stored"]): float(q["rel_l1_frac"]) for q in rows
           if q["stored_mapping"] == q["lookup_mapping"]}
    other = [q for q in rows if q["stored_mapping"] != q["lookup_mapping"]
             and abs(float(q["level_read"]) - float(q["level_stored"])) >= 0.1]
    assert len(other) >= 40
    for q in other:  # above the chain's own error, and above what the bounds allow
        assert float(q["rel_l1_frac"]) > own[(q["stored_mapping"], q["level_stored"])], q
        assert float(q["rel_err_max_frac"]) > 2e-3, q


def test_a_constant_environment_has_no_error():
    rows, meta = exp.measure_environment(se.env_constant(8) * 2.5, base=8, r_values=[0.05, 0.5, 1.0], dir_size=4,
                                         rtol=1e-3, ref_rtol=1e-4)
    assert {(q["stored_mapping"], q["lookup_mapping"]) for q in rows} == {(a, b) for a in NAMES for b in NAMES}
    assert {q["kind"] for q in rows} == {"grid", "on-level"}
    for q in rows:
        assert abs(q["rel_l1_frac"]) <= 1e-12 and abs(q["rel_err_max_frac"]) <= 1e-12 and abs(q["bias_frac"]) <= 1e-12
    assert set(meta["chains"]) == {f"{lay}/{a}" for lay in exp.LAYOUTS for a in NAMES}


def test_bad_experiment_parameters():
    with pytest.raises(IBLError, match="--roughness"):
        exp.PARAMS[[p.name for p in exp.PARAMS].index("roughness")].parse("0.5,1.5")
    with pytest.raises(IBLError, match="power of two"):
        exp.PARAMS[[p.name for p in exp.PARAMS].index("base_sizes")].parse("24")
    with pytest.raises(IBLError, match="layout"):
        exp.layout_sizes("gpu", "linear", 16)
