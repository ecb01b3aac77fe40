"""Every experiment at quick size: its figures pass the layout check, and its headline result holds.

One test per experiment runs the compute step and the plot step (with :func:`ibl_ref.figures.layout_problems`
hooked into every figure save) and then checks the result the README quotes against an expectation that does
not come from the code under test: a closed form, a published number, a physical property (linearity,
convergence order, monotonicity), or a second route through different code.  Each tolerance says where it
comes from.  ``render-error`` and ``km00-render`` run with parameters below their quick size (the test time
budget; same code path, layout checked the same way).
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from ibl_ref import experiments
from ibl_ref.atomic import read_csv

EXPS = experiments.available()

#: parameters that shrink the slowest experiments below their quick size (layout and code path unchanged)
SMALL = {
    "render-error": dict(size=20, lights=(24, 96), vsm=(64,), vsm_default=64),
    "km00-render": dict(size=24, env_size=16, n_theta=5, n_gamma=64, n_phi=16, map_out_size=16,
                        ref_k_multipliers=(1, 2), ref_max_supersample=8),
    "fig5": dict(centre_only_sizes=()),
    "lights-vs-error": dict(light_counts=(6, 24, 96)),
}


def _rows(path, **match):
    return [r for r in read_csv(path) if all(str(r[k]) == str(v) for k, v in match.items())]


def check_claims(out, summary):
    # Knuth Sec. 5 and Sec. 3.2, as the README reports them: sqrt-cos nearly as good as box at s = 1 under all
    # 8 readings; "cosine filter always below 10 %" not reproduced; energy gain for a lit corner texel
    o = summary["outcome"]
    assert o["sqrtcos_near_box_s1"] == "yes" and o["sqrtcos_better_high"] == "yes"
    assert o["cos_below_10_all"] == "no" and o["box_about_4pct_s1"] == "no"
    row = _rows(out / "claims.csv", claim="energy_not_increased")[0]
    drift = {k: float(v) for k, v in re.findall(r"(\S+/\S+/\S+) ([+-][\d.]+)%", row["measured_stf_integral_texel"])}
    # README: "a lit texel at a cube corner gains +185 % (sqrt-cos), one at a face centre loses 50 %; random
    # maps drift < 0.5 %" (quick, 64²); ±1 %-point is the rounding of the README's numbers
    assert drift["corner_texel/sqrtcos/neighbour"] == pytest.approx(185, abs=1)
    assert drift["centre_texel/sqrtcos/neighbour"] == pytest.approx(-50, abs=1)
    assert all(abs(v) < 0.5 for k, v in drift.items() if k.startswith("random/"))


def check_convergence(out, summary):
    # a resolved lobe converges at second order (midpoint quadrature of a smooth integrand: O(h²));
    # the closed form a + b·r (s+1)/(s+2) is the target (margin 0.3 for the pre-asymptotic first step)
    assert min(summary["observed_orders_max_err"]["16.0"]) > 1.7


def check_cosine_lobes(out, summary):
    # Meunier Eq. 20-21: 2π/(e+1) against adaptive quadrature (scipy), to quadrature accuracy
    assert summary["integral_closed_form_max_rel_err"] < 1e-10
    # the product fit's mean error against the paper's 7.1e-4 (Sec. 4.1): within a factor 3 at the quick
    # sampling (2 exponents per decade instead of 6; the full run's number is pinned by test_readme_saved_runs)
    pf = summary["product_fit"]
    assert pf["paper_mean_abs_err"] == pytest.approx(7.1379e-4)
    assert pf["paper_mean_abs_err"] / 3 < pf["abs_err_sr"]["mean"] < 3 * pf["paper_mean_abs_err"]


def check_fig1(out, summary):
    # a narrower lobe keeps a small bright source more concentrated: under the sun the brightest pixel of the
    # glossy sphere grows with g (normalised lobe average of a near-delta source peaks ∝ s + 1).  Not the
    # mirror (g = 1): its pixels sample single directions, and none need hit the sub-texel sun
    imgs, mask = experiments.images_from_json(out / "fig1_images.json")
    peaks = [imgs[f"sky_sun|{g}"][mask].mean(-1).max() for g in (0.5, 0.9, 0.99)]
    assert all(b > a for a, b in zip(peaks, peaks[1:])), peaks
    assert all(np.all(np.isfinite(v)) and v.min() >= 0 for v in imgs.values())


def check_fig3(out, summary):
    # the diffuse-end sphere (g = 0: s = 1 around r) against the exact lobe average of a different code path
    # (phong_convolution.convolve_exact on the same studio map, sampled at r): within the README's lobe-chain
    # range of the sqrt-cos pyramid for studio at s = 1 (8-22 %), here < 25 %
    from ibl_ref.groundtruth.phong_convolution import convolve_exact
    from ibl_ref.environment.sampling import sample_bilinear
    from ibl_ref.rendering.sphere_render import orthographic_sphere
    from ibl_ref.synthetic.synthetic_envs import make_env

    d = json.loads((out / "fig3_spheres.json").read_text())
    mask, _, r = orthographic_sphere(d["pixels"])
    exact = sample_bilinear(convolve_exact(make_env("studio", d["face_size"]), 1.0), r)
    got = np.asarray(d["images_linear_rgb"][d["gloss"].index(0.0)])[mask]
    err = np.abs(got - exact).sum() / np.abs(exact).sum()
    assert 0.0 < err < 0.25, err


def check_fig4(out, summary):
    rows = read_csv(out / "fig4_cross_sections.csv")
    th = np.radians([float(r["theta_deg"]) for r in rows])
    # the target is the closed form max(cos θ, 0)
    np.testing.assert_allclose([float(r["target"]) for r in rows], np.maximum(np.cos(th), 0.0), atol=1e-12)
    # README: box 15.3 % (∫f dω volume) / 19.4 % (⅓∫f³ dω) at 64², s = 1 (±0.05: the README's rounding)
    lev = {(r["kernel"], r["volume"]): float(r["err_symdiff_pct"]) for r in read_csv(out / "fig4_levels.csv")}
    assert lev[("box", "integral")] == pytest.approx(15.3, abs=0.05)
    assert lev[("box", "radial")] == pytest.approx(19.4, abs=0.05)


def check_fig5(out, summary):
    # the same s = 1 numbers through the Fig. 5 sweep (a second experiment on the same analysis) and the README
    e = summary["err_at_s1"]
    assert e["box/integral/N64/centre"] == pytest.approx(15.3, abs=0.05)
    assert e["box/radial/N64/centre"] == pytest.approx(19.4, abs=0.05)
    # without filtering (MIP only) the s = 1 lobe is far off under both volume definitions (Fig. 4/5)
    assert e["none/radial/N64/centre"] > 2 * e["box/radial/N64/centre"]


def check_fig6(out, summary):
    # the paper's Fig. 6 claim: occlusion by VSM visibilities is closer to the ray-traced reference than no
    # occlusion and than ambient occlusion (occlusion-model error alone, the pyramid error factored out)
    r = {q["mode"]: float(q["rel_l1_occlusion_only"]) for q in read_csv(out / "fig6_metrics.csv")}
    assert r["ours"] < min(r["ao"], r["ao-color"], r["no-occlusion"])
    assert r["reference"] == 0.0


def check_fig7(out, summary):
    # bookkeeping of the timing table (no timing assertions in tests): stages sum to the frame time, one
    # G-buffer per scene whatever the light count
    rows = read_csv(out / "fig7_timings.csv")
    for q in rows:
        parts = sum(float(q[f"{k}_s"]) for k in ("raster", "shadow_maps", "blur", "visibility", "lookup", "shading"))
        assert parts == pytest.approx(float(q["frame_s"]), rel=1e-9)
    for scene in ("teapot", "cloth"):
        assert len({q["n_pixels"] for q in rows if q["scene"] == scene}) == 1


def check_fig8(out, summary):
    # the 42 published numbers of Fig. 8 (ibl_ref.knuth2014.memory_model.PAPER_FIG8 holds them as printed) are reproduced
    # by the byte model, and sparse PEMs reach the 10x storage goal (README: 10.8x at 12 regions, 128²)
    assert summary["model_equals_paper_everywhere"] is True
    assert summary["light_counts"] == [1, 12, 32, 64, 128, 256]
    assert summary["min_ratio_lossless"] > 10.0


def check_kan_table1(out, summary):
    # Kán et al. 2015 Table 1 as published (seconds), and every reported bound within the requested rtol 1e-3
    kan = {int(r["face_size_texels"]): float(r["kan2015_time_s"]) for r in read_csv(out / "kan_table1.csv")
           if r["kan2015_time_s"] != ""}
    assert kan == {32: 0.04, 64: 1.45, 128: 6.36, 256: 28.09, 512: 158.37, 1024: 1381.65}
    assert all(float(r["auto_rel_bound_max"]) <= 1e-3 for r in summary["rows"])


def check_km00(out, summary):
    # greedy fitting never increases the residual (each lobe is fitted to what the previous ones left), and
    # 3 greedy lobes beat one mean lobe in BRDF RMS (README / KM2000 Fig. 7)
    for brdf in ("ward_ks0.8_a0.04", "ggx_a0.15_f0.9"):
        multi = sorted((int(r["n_lobes"]), float(r["rel_rms"]))
                       for r in _rows(out / "rms_vs_lobes.csv", brdf=brdf, method="multi"))
        assert all(b[1] <= a[1] + 1e-12 for a, b in zip(multi, multi[1:])), multi
        single = float(_rows(out / "rms_vs_lobes.csv", brdf=brdf, method="single")[0]["rel_rms"])
        assert dict(multi)[3] < single


def check_km00_render(out, summary):
    # under L ≡ 1 the reference is the Ward albedo: the energy-rescaled lobes carry it (|bias| < 1 %, the
    # interpolation in θo), the greedy minimum-profile lobes leave energy out (full size: test_readme_saved_runs)
    r = {q["method"]: q for q in read_csv(out / "km00_render_metrics.csv")}
    assert abs(float(r["lobes3_rescaled"]["rel_bias_constant_env"])) < 0.01
    assert float(r["lobes3"]["rel_bias_constant_env"]) < -0.05


def check_lights_vs_error(out, summary):
    rows = read_csv(out / "lights_vs_error.csv")
    meta = json.loads((out / "lights_vs_error_meta.json").read_text())
    # the brute-force exact lobe average agrees with phong_convolution.convolve_exact (another implementation)
    assert max(meta["exact_check_max_rel_vs_convolve_exact"].values()) < 1e-10
    err = {(q["env"], int(q["lights"]), float(q["s_phong"])): q for q in rows}
    for env in ("sky_sun", "studio"):
        l1 = [float(err[(env, L, 1.0)]["rel_l1_lights"]) for L in (6, 24, 96)]
        # s = 1: point lights are a quadrature of a smooth lobe, error ∝ h² ∝ 1/L, i.e. ÷4 per 4x lights (≥ ÷3)
        assert l1[1] < l1[0] / 3 and l1[2] < l1[1] / 3, l1
        # Sec. 1: lights alone fail for glossy lobes: 24 lights at s = 1000 are off by more than half
        assert float(err[(env, 24, 1000.0)]["rel_l1_lights"]) > 0.5
        # the PEM sum equals the full-map pyramid lookup (linearity of the filters), up to float32 storage
        assert all(float(q["rel_l1_pem_vs_pyramid"]) < 1e-6 for q in rows if q["env"] == env)


def check_lobe_chain(out, summary):
    rows = read_csv(out / "lobe_chain.csv")
    err = {(q["prefilter"], float(q["s_phong"])): float(q["rel_l1"]) for q in rows if q["env"] == "sky_sun"}
    # the README's full run (64² faces, pinned by test_readme_saved_runs): the exact-lobe chain (ratio 2) within a
    # few % at every s, the paper's pyramid far above (sky+sun).  At the quick size (32² faces) the chain holds this up to s = 100; at s = 300 the lobe (half width
    # acos(2^(-1/300)) = 3.9°) spans barely more than one 32² texel (2.8°), so that point is left out
    assert max(v for (p, s), v in err.items() if p == "chain-f2" and s <= 100) < 0.031
    assert min(v for (p, s), v in err.items() if p == "pyramid-sqrtcos") > 0.15


def check_mediancut(out, summary):
    from ibl_ref.environment.envmap import direction_to_texel
    from ibl_ref.synthetic.synthetic_envs import DEFAULT_SUN_DIRECTION

    assert summary["partition_ok"] and summary["max_rgb_sum_rel_err"] < 1e-12
    lights = read_csv(out / "mediancut_lights.csv")
    # Meunier Eq. 32: the cap of a region's solid angle, Ω = 2π(1 − cos α) (closed form)
    for q in lights[:200]:
        a = np.radians(float(q["cap_half_angle_deg"]))
        assert 2 * np.pi * (1 - np.cos(a)) == pytest.approx(float(q["solid_angle_sr"]), rel=1e-9)
    # README: with 96 per-face regions on sky+sun the narrowest equivalent lobe is the region holding the sun
    sel = [q for q in lights if q["env"] == "sky_sun" and q["variant"] == "per-face" and int(q["lights"]) == 96]
    top = max(sel, key=lambda q: float(q["equivalent_lobe_exponent"]))
    n = json.loads((out / "mediancut_maps.json").read_text())["sky_sun"]["face_size"]
    f, row, col = (int(np.asarray(v).ravel()[0]) for v in direction_to_texel(np.asarray(DEFAULT_SUN_DIRECTION)[None], n))
    assert int(top["face"]) == f and int(top["row0"]) <= row < int(top["row1"]) and int(top["col0"]) <= col < int(top["col1"])


def check_render_error(out, summary):
    # the exact-lobe chain removes the filter-shape error: its lookup alone is far closer to the reference's
    # lobes than the paper's pyramid (the full run's numbers are pinned by test_readme_saved_runs)
    rows = read_csv(out / "render_error.csv")
    for q in rows:
        if q["material"] == "diffuse":
            assert float(q["rel_l1_chain_lookup_unoccluded"]) < 0.05 < 0.2 < float(q["rel_l1_lookup_unoccluded"])
            assert float(q["rel_l1_chain"]) < float(q["rel_l1_ours"])


def check_speed_accuracy(out, summary):
    # every texel's measured error (against the exact sum) is within the bound the method reported, and the
    # auto method meets the requested rtol (1e-3) everywhere
    rows = read_csv(out / "speed_accuracy.csv")
    assert rows and all(int(float(q["bound_violations"])) == 0 for q in rows)
    auto = [q for q in rows if q["method"] == "auto"]
    assert auto and all(float(q["rel_err_max"]) <= 1e-3 for q in auto)


def check_cross_validate(out, summary):
    # runs for real in CI: the lab's reference against an independent renderer, Mitsuba 3, on one scene x six
    # materials (diffuse, g = 0.9, g = 0.99, GGX roughness 0.1 / 0.3 / 0.6) under a sky with a small 1e5-bright sun;
    # GGX against both Mitsuba routes (its built-in roughconductor and the lab's formula as a Python BSDF) with the
    # separable Smith form, and the lab's BSDF with the height-correlated one
    from ibl_ref.experiments import cross_validate as cv

    rows = read_csv(out / "cross_validate.csv")
    assert {r["material"] for r in rows} == {"diffuse", "g0.9", "g0.99", "ggx0.1", "ggx0.3", "ggx0.6"}
    ggx = [r for r in rows if r["material"].startswith("ggx")]
    assert len(ggx) == 9 and {(r["mitsuba_bsdf"], r["smith"]) for r in ggx} == {
        ("roughconductor", "separable"), ("lab_ggx", "separable"), ("lab_ggx", "height_correlated")}
    smith = {r["material"]: float(r["smith_term_rel_l1"]) for r in ggx if r["smith"] == "height_correlated"}
    assert smith["ggx0.1"] < smith["ggx0.3"] < smith["ggx0.6"]  # the two Smith forms part as the lobe widens
    for r in rows:
        assert float(r["mask_agreement"]) > 0.99  # same pixel-centre rays, same triangles
        # the target: the reference within 0.5 % rel. L1 of Mitsuba beyond Mitsuba's own noise
        assert float(r["excess_rel_l1"]) <= cv.TARGET_EXCESS_REL_L1, r
        assert r["within_target"] == "True"
        # and the signed bias (noise averages out of it) is within the reference's own estimate + 3 noise units
        assert abs(float(r["bias"])) <= float(r["ref_err_rel_l1"]) + 3 * float(r["noise_rel_l1"]), r
    meta = json.loads((out / "cross_validate_meta.json").read_text())
    assert meta["all_within_target"] and summary["all_within_target"]
    assert all(m["renderer"] == "mitsuba" for c in meta["cases"] for m in c["mitsuba"].values())


def check_method_zoo(out, summary):
    from ibl_ref.experiments import method_zoo as mz

    rows = read_csv(out / "method_zoo.csv")
    meta = json.loads((out / "method_zoo_meta.json").read_text())
    st = meta["settings"]
    # the table: every method x material x environment run, n/a exactly where the method serves another material
    ran = [m for m in st["methods"] if f"method {m}" not in meta["skipped"]]
    # a probe environment is skipped (with its reason) only where its file is absent, e.g. a clone without the
    # probes beside it; the synthetic sky always runs
    envs = [e for e in st["envs"] if f"env {e}" not in meta["skipped"]]
    assert "sky_sun" in envs
    for e in set(st["envs"]) - set(envs):
        assert "not found" in meta["skipped"][f"env {e}"] and not (mz.probe_dir(st["probe_dir"]) / f"{e}.exr").exists()
    assert len(rows) == len(ran) * len(st["materials"]) * len(envs)
    assert {q["env"] for q in rows} == set(envs)
    kinds = {"split-sum": "ggx", "ggx-phong-pem+vsm": "ggx", "pyramid+vsm": "phong", "exact-lobe": "phong",
             "cmft": "phong", "cmgen": "ggx", "sh9": "diffuse"}
    for q in rows:
        kind = kinds.get(q["method"], "ggx" if q["method"].startswith("split-sum") else None)
        want = {"ggx": q["material"].startswith("ggx"), "phong": not q["material"].startswith("ggx"),
                "diffuse": q["material"] == "diffuse"}[kind]
        assert (q["applicable"] == "True") == want, q
    # the sphere's references converged to their tolerance (the adaptive integral's own estimate)
    for case in meta["references"].values():
        for info in case.values():
            assert info["exact_converged"] and info["err_rel_l1"] <= st["rtol"]
    # the budget's two routes agree: the walk ends at the method's image (float32 PEMs: 1e-5 relative) and its
    # signed biases add up to the method's bias (telescoping: rounding only)
    assert meta["checks"] and all(c["final_minus_method_rel"] <= 1e-5 for c in meta["checks"])
    assert all(abs(c["bias_sum_minus_total"]) < 1e-12 for c in meta["checks"])
    # convergence: the importance-sampling term falls from N = 16 to N = 256 where the lobe is wider than a texel
    # (roughness 0.6: the sampling noise dominates; at roughness 0.1 on 8² faces every sample lands in the texel
    # of r and the term is the bilinear reading of the source, not noise)
    b = read_csv(out / "method_zoo_budget.csv")
    pre = {(q["env"], q["material"], q["method"]): float(q["rel_l1_increment_frac"]) for q in b
           if q["step"] == "prefilter"}
    for (env, mat, meth), v in pre.items():
        if meth == "split-sum-is-16" and mat == "ggx0.6":
            assert pre[(env, mat, "split-sum-is-256")] < v / 2, (env, mat)
    # Karis's claim ("n = v = r ... is actually the larger source of error"): the quick analogue of the README's
    # finding — n = v = r's increment above the split-sum separation's in every quick GGX case
    karis = read_csv(out / "method_zoo_karis.csv")
    assert karis and all(q["n_v_r_larger"] == "True" for q in karis)
    # SH9 against its rigorous bound: |E9/π − E/π| ≤ (3/32)·Σ L Ω / π per pixel (E the texel sum), plus the gap
    # between the texel sum and the converged reference, which the exact-lobe chain's s = 1 level shows (an upper
    # estimate: it adds its own interpolation)
    from ibl_ref.prefilter.ramamoorthi_hanrahan2001 import error_bound

    # the README's orderings at quick size: the exact-lobe chain below the paper's pyramid on every Phong material,
    # cmft's released build above the exact-lobe chain on the diffuse material (its truncated support), FIS below
    # plain importance sampling at equal N (roughness 0.6); and the DFG table's step below its own error bound
    # (1.8e-2 in the albedo anywhere, karis2013) in every walk
    l1 = {(q["env"], q["material"], q["method"]): float(q["rel_l1_frac"]) for q in rows if q["applicable"] == "True"}
    for (e, mat, meth), v in l1.items():
        if meth == "exact-lobe":
            assert v < l1[(e, mat, "pyramid+vsm")], (e, mat)
            if mat == "diffuse" and (e, mat, "cmft") in l1:
                assert l1[(e, mat, "cmft")] > 3 * v
        if meth == "split-sum-fis-16" and mat == "ggx0.6":
            assert v < l1[(e, mat, "split-sum-is-16")]
    assert all(float(q["rel_l1_increment_frac"]) < 1.8e-2 for q in b if q["step"] == "dfg_table")
    env = mz.environment("sky_sun", st["env_size"])[0]
    ref_mean = float(np.load(out / "method_zoo_images.npz")["sphere__diffuse__reference"].mean())
    sh = next(float(q["rel_l1_frac"]) for q in rows if (q["env"], q["material"], q["method"]) ==
              ("sky_sun", "diffuse", "sh9"))
    gap = next(float(q["rel_l1_frac"]) for q in rows if (q["env"], q["material"], q["method"]) ==
               ("sky_sun", "diffuse", "exact-lobe"))
    assert sh <= float(np.mean(error_bound(env))) / np.pi / ref_mean + gap


#: experiments whose quick run, figure layout and headline are tested in a file of their own
OWN_TEST_FILE = {"error-budget": "tests/test_error_budget.py", "occlusion-zoo": "tests/test_occlusion_zoo.py",
                 "mip-mappings": "tests/test_mip_mappings.py", "manson-sloan": "tests/test_manson_sloan.py"}
CHECKS = {name: globals()[f"check_{name.replace('-', '_')}"] for name in EXPS if name not in OWN_TEST_FILE}


def test_every_experiment_is_checked_here_or_in_its_own_file():
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    assert set(CHECKS) | set(OWN_TEST_FILE) == set(EXPS)
    assert all((root / f).is_file() for f in OWN_TEST_FILE.values())


#: cross-validate renders with Mitsuba, so it runs again without the optional tools (phase 2+3 of .ci/run), where
#: it must skip with the reason; every other quick run takes the NumPy path only and is the same there
@pytest.mark.parametrize("name", [n if n == "cross-validate" else pytest.param(n, marks=pytest.mark.same_without_tools)
                                  for n in sorted(CHECKS)])
def test_experiment_quick_figures_and_headline(name, tmp_path, request, run_quick):
    if name == "cross-validate":  # renders with Mitsuba (skipped without its llvm variant, outside CI)
        request.getfixturevalue("mitsuba_llvm")
    summary, figs, problems = run_quick(EXPS[name], tmp_path, **SMALL.get(name, {}))
    # every figure the plot step returns exists, was saved through save_figure, and is laid out in its canvas
    assert figs and all(f.exists() and f.read_bytes()[:4] == b"\x89PNG" for f in figs)
    assert sorted(problems) == sorted(f.name for f in figs)
    assert {k: v for k, v in problems.items() if v} == {}
    CHECKS[name](tmp_path, summary)
