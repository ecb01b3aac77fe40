"""``ibl-ref prefilter``: the exact GGX level chain as files (ibl_ref/cli/cmd_prefilter.py).

Every level is checked against the dense texel sum (:func:`ibl_ref.prefilter.karis2013.prefilter_dense`, exact to
float64 rounding: an independent route) within the bound the command reports; the roughness of each level against
the mapping's closed form; bad input gets one line and writes nothing; a file the lab did not write is never
replaced.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from ibl_ref.cli import main
from ibl_ref.cli.cmd_prefilter import level_path
from ibl_ref.environment.exr_io import load_cube, write_envmap
from ibl_ref.prefilter.karis2013 import prefilter_dense
from ibl_ref.synthetic.synthetic_envs import make_env

N = 16


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    p = tmp_path_factory.mktemp("prefilter_cli") / "sky.exr"
    write_envmap(p, make_env("sky_sun", n=N), layout="cube")
    return p


def _one_line_error(capsys):
    err = capsys.readouterr().err.strip()
    assert err and len(err.splitlines()) == 1, err
    return err


@pytest.mark.parametrize("mapping, roughness", [
    ("filament", [0.0, 1.0 - np.sqrt(0.5), 1.0]),  # r = 1 − √(1 − lod), lod = 0, ½, 1
    ("linear", [0.0, 0.5, 1.0]),
])
def test_every_level_is_the_dense_sum_within_its_bound(env, tmp_path, capsys, mapping, roughness):
    out = tmp_path / "chain.exr"
    rtol = 1e-3
    argv = ["prefilter", env, out, "--min-level-size", "4", "--mapping", mapping, "--rtol", rtol, "--kernel",
            "numpy"]
    assert main([str(a) for a in argv]) == 0
    assert "level 2" in capsys.readouterr().out
    side = json.loads((tmp_path / "chain.json").read_text())
    levels = side["levels"]
    assert [e["face_size"] for e in levels] == [16, 8, 4]
    np.testing.assert_allclose([e["roughness"] for e in levels], roughness, rtol=1e-12, atol=1e-15)
    src = load_cube(env)
    np.testing.assert_array_equal(load_cube(tmp_path / "chain_l0.exr"), src)  # level 0: the source itself
    for e in levels[1:]:
        got = load_cube(tmp_path / f"chain_l{e['level']}.exr")
        ref = prefilter_dense(src, e["roughness"], out_size=e["face_size"])
        rel = np.abs(got - ref) / ref
        # the bound the command reports, plus the float32 rounding of the EXR file (2^-24 relative)
        assert 0.0 < e["rel_bound_max"] <= rtol
        assert rel.max() <= e["rel_bound_max"] + 2.0 ** -23, (e, rel.max())
    assert side["mapping"] == mapping and side["rtol"] == rtol
    assert sorted(side["outputs"]) == sorted(str(tmp_path / f"chain_l{k}.exr") for k in range(3))
    # its own files: a second run replaces them
    assert main([str(a) for a in argv]) == 0


def test_unreal_filters_its_top_level_at_its_smallest_roughness(env, tmp_path, capsys):
    # Unreal's level 0 is not the source: with N = 3 levels it holds r0 = 2^((0 - 3 + 3)/1.2) = 1 (and every level
    # r = 1 after clamping); with N = 4 (16², 8², 4², 2²), r0 = 2^(-1/1.2) = 0.5612 -- within its bound of the dense sum
    out = tmp_path / "chain.exr"
    argv = ["prefilter", env, out, "--min-level-size", "2", "--mapping", "unreal", "--rtol", 1e-3, "--kernel", "numpy"]
    assert main([str(a) for a in argv]) == 0
    levels = json.loads((tmp_path / "chain.json").read_text())["levels"]
    assert [e["face_size"] for e in levels] == [16, 8, 4, 2]
    np.testing.assert_allclose([e["roughness"] for e in levels], [2.0 ** (-1 / 1.2), 1.0, 1.0, 1.0], rtol=1e-12)
    got = load_cube(tmp_path / "chain_l0.exr")
    ref = prefilter_dense(load_cube(env), levels[0]["roughness"], out_size=16)
    assert 0.0 < levels[0]["rel_bound_max"] <= 1e-3
    assert np.max(np.abs(got - ref) / ref) <= levels[0]["rel_bound_max"] + 2.0 ** -23
    assert "level 0: roughness 0.5612" in capsys.readouterr().out


def test_the_chain_does_not_depend_on_the_kernel(env, tmp_path):
    pytest.importorskip("numba")
    for k in ("numpy", "compiled"):
        assert main(["prefilter", str(env), str(tmp_path / f"{k}.exr"), "--min-level-size", "8", "--kernel", k]) == 0
    a, b = load_cube(tmp_path / "numpy_l1.exr"), load_cube(tmp_path / "compiled_l1.exr")
    bound = json.loads((tmp_path / "numpy.json").read_text())["levels"][1]["rel_bound_max"]
    assert np.max(np.abs(a - b) / a) <= 2 * bound + 2.0 ** -23


@pytest.mark.parametrize("extra, words", [
    (["--size", "12"], "--size must be a power of two"),
    (["--min-level-size", "3"], "--min-level-size must be a power of two"),
    (["--min-level-size", "16"], "leaves no level"),
    (["--rtol", "0"], "rtol"),
    (["--rtol", "nan"], "rtol"),
    (["--threads", "0"], "--threads"),
])
def test_bad_options_give_one_line_and_write_nothing(env, tmp_path, capsys, extra, words):
    out = tmp_path / "x.exr"
    assert main(["prefilter", str(env), str(out)] + extra) != 0
    assert words in _one_line_error(capsys)
    assert list(tmp_path.iterdir()) == []


def test_a_source_that_is_not_a_power_of_two_asks_for_size(tmp_path, capsys):
    p = tmp_path / "odd.exr"
    write_envmap(p, make_env("sky_sun", n=12), layout="cube")
    assert main(["prefilter", str(p), str(tmp_path / "o.exr")]) != 0
    assert "give --size" in _one_line_error(capsys)
    assert main(["prefilter", str(p), str(tmp_path / "o.exr"), "--size", "8", "--min-level-size", "4",
                 "--kernel", "numpy"]) == 0
    assert load_cube(tmp_path / "o_l0.exr").shape[1] == 8


def test_nonfinite_radiance_is_refused(tmp_path, capsys):
    from ibl_ref.environment.exr_io import ExrPart, write_exr

    img = np.ones((16, 32, 3), np.float32)  # a lat-long map with one NaN texel
    img[5, 7, 1] = np.nan
    p = tmp_path / "nan.exr"
    write_exr(p, ExrPart(img, ("R", "G", "B")))
    assert main(["prefilter", str(p), str(tmp_path / "o.exr"), "--size", "8"]) != 0
    assert "nan" in _one_line_error(capsys).lower()
    assert not list(tmp_path.glob("o*"))


@pytest.mark.parametrize("victim", ["chain.json", "chain_l1.exr"])
def test_files_the_lab_did_not_write_are_not_replaced(env, tmp_path, capsys, victim):
    (tmp_path / victim).write_text("mine")
    assert main(["prefilter", str(env), str(tmp_path / "chain.exr"), "--min-level-size", "8"]) != 0
    err = _one_line_error(capsys)
    assert "refusing" in err and victim in err
    assert (tmp_path / victim).read_text() == "mine"
    assert not (tmp_path / "chain_l0.exr").exists()


def test_the_input_is_never_an_output(env, tmp_path, capsys):
    import shutil

    src = tmp_path / "in_l0.exr"
    shutil.copy(env, src)
    before = src.read_bytes()
    assert main(["prefilter", str(src), str(tmp_path / "in.exr"), "--min-level-size", "8"]) != 0
    _one_line_error(capsys)
    assert src.read_bytes() == before


def test_the_cmgen_layout_reads_back_as_cmgen_files(env, tmp_path):
    # read_levels is the reader checked against cmgen's own output (tests/test_cmgen_peer.py): the files written in
    # cmgen's layout must come back as the chain the cube layout holds, face names and orientation included
    from ibl_ref.prefilter.cmgen_peer import read_levels

    out = tmp_path / "cm"
    common = ["--min-level-size", "4", "--kernel", "numpy"]
    assert main(["prefilter", str(env), str(out), "--layout", "cmgen"] + common) == 0
    assert main(["prefilter", str(env), str(tmp_path / "c.exr")] + common) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["prefilter.json"] + [f"m{lv}_{f}.exr" for lv in range(3) for f in ("px", "nx", "py", "ny", "pz", "nz")])
    got = read_levels(out, 3, N)
    for lv in range(3):
        np.testing.assert_array_equal(got[lv], load_cube(tmp_path / f"c_l{lv}.exr"))
    assert json.loads((out / "prefilter.json").read_text())["layout"] == "cmgen"
    (out / "m1_px.exr").unlink()  # a second run restores its own set
    assert main(["prefilter", str(env), str(out), "--layout", "cmgen"] + common) == 0
    assert (out / "m1_px.exr").is_file()


def test_the_cmgen_layout_refuses_a_file_as_its_folder(env, tmp_path, capsys):
    f = tmp_path / "taken"
    f.write_text("mine")
    assert main(["prefilter", str(env), str(f), "--layout", "cmgen", "--min-level-size", "8"]) != 0
    assert "is a file" in _one_line_error(capsys)
    assert f.read_text() == "mine"


# ---- --layout ktx / dds: one container file with every level ------------------------------------------------------
@pytest.fixture(scope="module")
def cube_chain(env, tmp_path_factory):
    """The chain of ``env`` in the cube layout (float32 OpenEXR files), to hold the containers against."""
    out = tmp_path_factory.mktemp("cube_chain") / "c.exr"
    assert main(["prefilter", str(env), str(out), "--min-level-size", "4", "--kernel", "numpy"]) == 0
    return [load_cube(level_path(out, k)) for k in range(3)]


@pytest.mark.parametrize("layout, dtype", [("ktx", None), ("dds", None), ("ktx", "float32"), ("dds", "float32")])
def test_the_container_layouts_hold_the_chain_the_cube_layout_holds(env, cube_chain, tmp_path, layout, dtype):
    # the readers are the ones checked against cmgen's and cmft's own files (tests/test_cube_containers.py)
    from ibl_ref.environment.cube_containers import read_cube_chain

    out = tmp_path / f"chain.{layout}"
    argv = (["prefilter", str(env), str(out), "--layout", layout, "--min-level-size", "4", "--kernel", "numpy"]
            + (["--dtype", dtype] if dtype else []))
    assert main(argv) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name, out.name + ".json"]
    got = read_cube_chain(out)
    assert [g.shape for g in got] == [(6, n, n, 3) for n in (16, 8, 4)]
    side = json.loads((tmp_path / f"chain.{layout}.json").read_text())
    assert side["layout"] == layout and side["outputs"] == [str(out)] and len(side["levels"]) == 3
    assert side["storage"] == {"dtype": dtype or "float16", "rel_rounding": 2.0 ** -24 if dtype else 2.0 ** -11}
    for k, ref in enumerate(cube_chain):
        if dtype == "float32":
            np.testing.assert_array_equal(got[k], ref)
        else:  # float16 by default: half an ulp (values here are far above half's smallest normal)
            assert np.all(np.abs(got[k] - ref) <= 2.0 ** -11 * ref * (1 + 2.0 ** -10)), k
    if dtype is None and layout == "ktx":
        assert main(argv) == 0  # its own files: a second run replaces them
        assert sorted(p.name for p in tmp_path.iterdir()) == [out.name, out.name + ".json"]


@pytest.mark.parametrize("argv, words", [
    (["--layout", "ktx", "OUT=chain.exr"], "writes one .ktx file"),
    (["--layout", "dds", "OUT=chain.ktx"], "writes one .dds file"),
    (["--dtype", "float16", "OUT=c.exr"], "--dtype applies to --layout ktx and dds"),
    (["--layout", "cmgen", "--dtype", "float32", "OUT=cm"], "--dtype applies"),
])
def test_container_options_are_checked_before_any_work(env, tmp_path, capsys, argv, words):
    out = next(a[4:] for a in argv if a.startswith("OUT="))
    rest = [a for a in argv if not a.startswith("OUT=")]
    assert main(["prefilter", str(env), str(tmp_path / out), "--min-level-size", "4"] + rest) != 0
    assert words in _one_line_error(capsys)
    assert list(tmp_path.iterdir()) == []


def test_a_float16_overflow_names_the_level_and_value_and_float32_holds_it(tmp_path, capsys):
    from ibl_ref.environment.cube_containers import read_dds

    cube = make_env("sky_sun", n=8)
    cube[4, 3, 5] = 1e5  # a sun texel above half's 65504
    src = tmp_path / "sun.exr"
    write_envmap(src, cube, layout="cube")
    out = tmp_path / "o.dds"
    common = ["prefilter", str(src), str(out), "--layout", "dds", "--min-level-size", "4", "--kernel", "numpy"]
    assert main(common) != 0
    err = _one_line_error(capsys)
    assert "level 0: value 100000 overflows float16 (max 65504)" in err and "--dtype float32" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sun.exr"]
    assert main(common + ["--dtype", "float32"]) == 0
    assert read_dds(out)[0].max() == 1e5


def test_the_container_sidecar_is_its_own_and_a_foreign_one_is_kept(env, tmp_path, capsys):
    # OUT is the user's to replace (they named it); its sidecar OUT.ktx.json only if the lab wrote it
    out = tmp_path / "chain.ktx"
    out.write_text("an older file the user names again")
    (tmp_path / "chain.ktx.json").write_text("mine")
    argv = ["prefilter", str(env), str(out), "--layout", "ktx", "--min-level-size", "8", "--kernel", "numpy"]
    assert main(argv) != 0
    assert "refusing" in _one_line_error(capsys)
    assert (tmp_path / "chain.ktx.json").read_text() == "mine"
    (tmp_path / "chain.ktx.json").unlink()
    assert main(argv) == 0
    assert out.read_bytes()[:12] == b"\xabKTX 11\xbb\r\n\x1a\n"
