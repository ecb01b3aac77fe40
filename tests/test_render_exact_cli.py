"""``ibl-ref render --mode reference|mitsuba`` (ibl_ref/cli/exact_modes.py): per-mesh materials, --ref-rtol, --spp."""

import json

import numpy as np
import pytest

from ibl_ref.cli import main


@pytest.mark.usefixtures("mitsuba_llvm")
def test_reference_and_mitsuba_modes_agree_on_constant_env(tmp_path):
    # sphere on a plane (one mesh, one diffuse material) under L ≡ 1: the sphere shadows the plane, so there is no
    # closed form; the two independent renderers must agree (Mitsuba within its noise, the reference within rtol)
    common = ["render", "--mesh", "sphere_on_plane", "--no-ground", "--synthetic", "constant", "--env-size", "8",
              "--size", "16", "--material", "0.8,0,0", "--no-progress"]
    r, m = tmp_path / "r.npz", tmp_path / "m.npz"
    assert main(common + ["--mode", "reference", "--ref-rtol", "5e-3", "--out", str(r)]) == 0
    assert main(common + ["--mode", "mitsuba", "--spp", "256", "--out", str(m)]) == 0
    a, b = np.load(r), np.load(m)
    mask = a["mask"] & b["mask"]
    assert mask.sum() > 30
    ja, jb = json.loads((tmp_path / "r.json").read_text()), json.loads((tmp_path / "m.json").read_text())
    assert ja["reference"]["err_rel_l1"] <= 5e-3 and jb["mitsuba"]["spp"] >= 256
    rel = np.abs(a["image"][mask] - b["image"][mask]).sum() / np.abs(b["image"][mask]).sum()
    # tolerance: Mitsuba's noise (its own estimate) + the reference's rtol, ×2 for the noise of the noise estimate
    assert rel <= 2 * (jb["mitsuba"]["noise_rel_l1"] + 5e-3)


def test_ground_material_is_honoured(tmp_path):
    out = tmp_path / "g.npz"
    assert main(["render", "--size", "10", "--synthetic", "constant", "--env-size", "8", "--material", "0.5,0,0",
                 "--ground-material", "0,0.3,0.5", "--mode", "reference", "--ref-rtol", "1e-2", "--out", str(out),
                 "--no-progress"]) == 0
    info = json.loads((tmp_path / "g.json").read_text())
    assert info["reference"]["quadrature"] == "converged"
    img = np.load(out)["image"]
    # L ≡ 1: a teapot pixel (kd 0.5) is ≤ 0.5 and near it where little is occluded; a ground pixel (ks 0.3) ≤ 0.3
    v = img[np.load(out)["mask"]].mean(axis=-1)
    assert v.max() <= 0.5 + 1e-9 and (v > 0.4).any() and ((v > 0) & (v <= 0.3 + 1e-9)).any()


def test_bad_flags(tmp_path, capsys):  # runs without Mitsuba: the flags are checked before any rendering
    # one-line errors naming the flag, before any rendering
    out = str(tmp_path / "never.exr")
    assert main(["render", "--mode", "mitsuba", "--spp", "3", "--size", "4", "--out", out]) != 0
    assert "--spp" in capsys.readouterr().err
    assert main(["render", "--mode", "reference", "--ref-rtol", "-1", "--size", "4", "--out", out]) != 0
    assert "--ref-rtol" in capsys.readouterr().err
    assert main(["render", "--mode", "reference", "--workers", "0", "--size", "4", "--out", out]) != 0
    assert "--workers" in capsys.readouterr().err


def test_reference_workers_and_seed_flags(tmp_path):
    # --workers only changes where the pixel blocks run (the image is bit-identical); --seed picks other random ray
    # points (another image within the tolerance); both are recorded in the JSON sidecar
    common = ["render", "--mesh", "sphere_on_plane", "--no-ground", "--synthetic", "sky_sun", "--env-size", "8",
              "--size", "12", "--material", "1,0,0", "--no-progress", "--mode", "reference", "--ref-rtol", "1e-2"]
    outs = {}
    for tag, extra in (("w1", ["--workers", "1"]), ("w2", ["--workers", "2"]), ("s5", ["--workers", "1", "--seed", "5"])):
        outs[tag] = tmp_path / f"{tag}.npz"
        assert main(common + extra + ["--out", str(outs[tag])]) == 0
    a, b, c = (np.load(outs[k])["image"] for k in ("w1", "w2", "s5"))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    info = json.loads((tmp_path / "w2.json").read_text())["reference"]
    assert info["workers"] == 2 and info["converged"] and info["ray_backend"] in ("embree", "exact")


def test_ggx_materials_on_the_command_line(tmp_path, capsys):
    # `--material ggx:…` in the exact modes: the reference renders it (L ≡ 1: the teapot's GGX conductor reflects
    # at most its directional albedo ≤ 1, the ground's kd part adds kd·A_1 ≤ kd); bad GGX parameters and GGX in
    # the other modes are one-line errors that write nothing
    out = tmp_path / "g.npz"
    assert main(["render", "--size", "10", "--synthetic", "constant", "--env-size", "8", "--material",
                 "ggx:roughness=0.5,f0=1", "--ground-material", "ggx:roughness=0.6,f0=0.04,kd=0.3", "--mode",
                 "reference", "--ref-rtol", "1e-2", "--out", str(out), "--no-progress"]) == 0
    info = json.loads((tmp_path / "g.json").read_text())
    assert info["material"]["kind"] == "ggx" and info["material"]["alpha"] == pytest.approx(0.25)
    assert [lb["lobe"] for lb in info["reference"]["lobes"]] == ["ggx", "diffuse", "ggx"]
    v = np.load(out)["image"][np.load(out)["mask"]].mean(axis=-1)
    assert 0 < v.max() <= 1.0 + 1e-9
    never = tmp_path / "never.exr"
    for args, what in ((["--material", "ggx:0"], "roughness must be in (0, 1]"),
                       (["--material", "ggx:roughness=0.3,f0=1.5"], "f0 must be in [0, 1]"),
                       (["--ground-material", "ggx:0.3,kd=-1"], "--ground-material"),
                       (["--material", "ggx:0.3", "--mode", "ours"], "--mode reference and --mode mitsuba"),
                       (["--material", "ggx:0.3", "--gmap", str(tmp_path / "g.png"), "--mode", "reference"], "--gmap")):
        mode = [] if "--mode" in args else ["--mode", "reference"]
        assert main(["render", "--size", "4", "--out", str(never), "--no-progress"] + mode + args) != 0
        err = capsys.readouterr().err
        assert what in err and err.count("\n") == 1, err
        assert not never.exists()


@pytest.mark.usefixtures("mitsuba_llvm")
def test_mitsuba_mode_renders_ggx_with_both_routes(tmp_path):
    # --mitsuba-ggx both (default): the lab's BSDF makes the image, Mitsuba's roughconductor the second render, whose
    # difference is recorded; where the built-in does not apply (height-correlated Smith) it is skipped with the reason
    common = ["render", "--mesh", "sphere_on_plane", "--no-ground", "--synthetic", "sky_sun", "--env-size", "8",
              "--size", "12", "--mode", "mitsuba", "--spp", "256", "--no-progress"]
    assert main(common + ["--material", "ggx:roughness=0.6,f0=1,smith=separable", "--out", str(tmp_path / "a.exr")]) == 0
    info = json.loads((tmp_path / "a.json").read_text())
    b = info["mitsuba_builtin"]
    assert info["mitsuba"]["materials"]["0"]["type"] == "lab_ggx" and b["materials"]["0"]["type"] == "roughconductor"
    assert b["rel_l1_vs_lab"] <= 3 * b["noise_rel_l1_both"]  # the same function, within the two renders' noise
    assert main(common + ["--material", "ggx:0.6", "--out", str(tmp_path / "b.exr")]) == 0
    assert "separable" in json.loads((tmp_path / "b.json").read_text())["mitsuba_builtin"]["skipped"]
