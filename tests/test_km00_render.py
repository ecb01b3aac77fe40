"""Tests of the km00-render experiment (tiny settings; the files it writes and the plot that reads only them)."""

from __future__ import annotations

import numpy as np

from ibl_ref.atomic import read_csv
from ibl_ref.experiments import km00_render as E
from ibl_ref.rendering.image_io import read_image_exr
from ibl_ref.rendering.km00_render import render_single_method


def _tiny(env="sky_sun"):
    return dict(size=20, env=env, env_size=8, n_theta=5, n_lobes=3, n_gamma=64, n_phi=8, map_supersample="auto",
                map_out_size=8, tail_rtol=1e-6, ref_samples_per_hwhm=1.0, ref_k_multipliers=[1, 2], ref_max_supersample=8,
                ref_eps=1e-12)


def test_experiment_writes_files_and_plot(tmp_path):
    out = E.run_with(tmp_path, _tiny())
    rows = {r["method"]: r for r in read_csv(tmp_path / "km00_render_metrics.csv")}
    assert set(rows) == set(E.METHODS)
    assert float(rows["reference"]["rel_l1"]) == 0.0
    for k in E.METHODS:
        assert np.isfinite(float(rows[k]["rmse"])) and float(rows[k]["rel_l1"]) >= 0
        img = read_image_exr(tmp_path / f"km00_render_{k}.exr")
        assert img.shape == (20, 20, 3) and np.all(np.isfinite(img))
    conv = read_csv(tmp_path / "km00_render_reference_convergence.csv")
    assert len(conv) == 1
    assert out["metrics"]["reference"] == 0.0
    pngs = E.plot(tmp_path)
    assert pngs[0].exists() and pngs[0].stat().st_size > 1000


def test_constant_environment_single_lobe_matches_albedo(tmp_path):
    # L ≡ 1: the reference is the Ward albedo a(θo) per pixel; the single-lobe render is cos θo ∫_{S²} p dω with p
    # rescaled to the albedo over the hemisphere — they differ by n·l ≈ n·r (relative effect ≈ lobe variance
    # × (1 + tan² θo)/2 ≲ 0.2 % × 33 = 7 % at 80°, < 1 % below 60°), the lobe part below the horizon (θo > 85°),
    # and the linear-in-θo interpolation of k(θo) between 5 elevations (albedo ∝ ≈ cos θo: ≤ 2 %); most pixels are
    # below 60°, so pooled over the teapot the relative L1 is below 3 %.  (Before per-pixel supersampling of the
    # reference its under-resolved grazing lobes gave 8 %: this test catches that.)
    E.run_with(tmp_path, _tiny("constant"))
    rows = {r["method"]: r for r in read_csv(tmp_path / "km00_render_metrics.csv")}
    assert float(rows["single"]["rel_l1"]) < 0.03
    # the 3-lobe greedy fit (minimum profiles, no energy rescale) loses energy: darker than the reference
    ref = read_image_exr(tmp_path / "km00_render_reference.exr")
    l3 = read_image_exr(tmp_path / "km00_render_lobes3.exr")
    assert l3.sum() < ref.sum()


def test_reference_with_a_diffuse_term_gathers_the_whole_hemisphere():
    # L ≡ 1, Ward with kd = 0.5, ks = 0: Lo = ∫ kd/π cos θi dω = kd at every front-facing pixel (closed form).
    # The Ward cone cut covers the specular term only; applied here it kept ≈ 6 % of the diffuse light.
    # Tolerance: texel quadrature of cos θi with its horizon cut on 8² faces, supersampled (≤ 1 %)
    img, mask, _ = render_single_method("reference", np.ones((6, 8, 8, 3)), width=12, brdf="ward",
                                          brdf_params=dict(kd=0.5, ks=0.0, alpha=0.04), n_theta=3)
    v = img[mask].mean(axis=-1)
    v = v[v > 0]  # back-facing pixels are black
    assert v.size > 10
    np.testing.assert_allclose(v, 0.5, rtol=1e-2)


def test_cli_writes_image_and_rejects_bad_input(tmp_path, capsys):
    from ibl_ref.cli import main

    out = tmp_path / "t.exr"
    rc = main(["km00-render", "--method", "single", "--size", "16", "12", "--env-size", "8", "--n-theta", "3",
               "--out", str(out), "--quiet"])
    assert rc == 0
    img = read_image_exr(out)
    assert img.shape == (12, 16, 3) and np.all(np.isfinite(img)) and img.max() > 0
    # --rescale-lobes: the greedy lobes carry the BRDF's albedo, so the image gets brighter, not darker
    plain, resc = tmp_path / "l.exr", tmp_path / "lr.exr"
    for path, extra in ((plain, []), (resc, ["--rescale-lobes"])):
        assert main(["km00-render", "--method", "lobes", "--size", "12", "--env-size", "8", "--n-theta", "3",
                     "--out", str(path), "--quiet"] + extra) == 0
    assert read_image_exr(resc).sum() > read_image_exr(plain).sum()
    assert main(["km00-render", "--out", str(tmp_path / "x.png"), "--quiet"]) == 1
    assert main(["km00-render", "--env", "no_such_env", "--out", str(out), "--quiet"]) == 1
    assert "neither a synthetic environment" in capsys.readouterr().err
    assert main(["km00-render", "--n-theta", "1", "--size", "8", "--out", str(out), "--quiet"]) == 1
    assert "n_theta must be an integer >= 2" in capsys.readouterr().err
    assert main(["km00-render", "--alpha", "0.3", "--size", "8", "--env-size", "8", "--out", str(out), "--quiet"]) == 1
    assert "peaks at the horizon" in capsys.readouterr().err
