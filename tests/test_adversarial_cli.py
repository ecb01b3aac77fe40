"""Adversarial suite, command-line side: every command over bad files, bad flags and special outputs.

Commands run in-process (``ibl_ref.cli.main(argv)``, fast) and a few as real subprocesses.  For each
failing case the suite asserts: the exit code (2 for argparse usage errors, 1 for every bad value or file), a single
line on stderr of the form ``ibl-ref CMD: error: …`` naming the file or flag, no traceback, nothing
written under the output name, no temporary/staging files, and the previous outputs intact.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import adversarial_files as af
from ibl_ref import atomic
from ibl_ref.cli import main

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(autouse=True)
def _alarm():
    """No case may hang (a FIFO opened for writing blocks forever): fail after 60 s instead."""

    def boom(*_):
        raise TimeoutError("adversarial CLI case hung")

    old = signal.signal(signal.SIGALRM, boom)
    signal.alarm(60)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


def run(argv, capfd, expect: int):
    """Run the CLI in-process; return stderr.  Checks the exit code and the one-line, no-traceback rule."""
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse usage errors (and the numeric-flag validation) exit with 2
        rc = exc.code
    out, err = capfd.readouterr()
    assert "Traceback" not in out + err
    assert rc == expect, f"rc={rc}\nstdout: {out}\nstderr: {err}"
    if expect != 0:
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert len(lines) == 1, err
        assert lines[0].startswith(f"ibl-ref {argv[0]}") and ": error: " in lines[0], lines[0]
        assert "Warning" not in out  # e.g. OpenEXR's own text for truncated files
    return err


def listing(folder: Path) -> dict:
    return {str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None)
            for p in sorted(folder.rglob("*")) if not p.is_symlink()}


def no_temps(folder: Path):
    left = [str(p) for p in folder.rglob("*") if atomic.TEMP_TAG in p.name]
    assert left == [], left


# ------------------------------------------------------------------------------------------------
# every command that reads an environment map, over every bad file
# ------------------------------------------------------------------------------------------------
ENV_COMMANDS = {
    "info": lambda f, o: ["info", f],
    "convert": lambda f, o: ["convert", f, o / "c.exr", "--layout", "cube"],
    "convolve": lambda f, o: ["convolve", f, o / "v.exr", "-s", "4"],
    "irradiance": lambda f, o: ["irradiance", f, o / "i.exr"],
    "mediancut": lambda f, o: ["mediancut", f, "--lights", "6", "--out", o / "m.json"],
    "pem": lambda f, o: ["pem", f, "--lights", "6", "--out", o / "pems"],
    "pyramid": lambda f, o: ["pyramid", f, o / "p.exr"],
    "render": lambda f, o: ["render", "--env", f, "--mesh", "torus", "--out", o / "r.exr", "--size", "8",
                            "--lights", "6"],
    "km00-render": lambda f, o: ["km00-render", "--env", f, "--out", o / "k.exr", "--size", "8", "--quiet"],
}

# a representative subset of the bad files for the costlier commands; all of them for info/convolve
CLI_BAD_EXR = ["trunc_half", "trunc_40B", "empty", "deep", "huge_window", "conv_directx", "conv_int", "nan_pixel",
               "z_channel_only", "zeroed_chunks"]
CLI_BAD_HDR = ["huge_claim_1e9x2e9", "huge_claim_with_data", "rle_truncated", "res_words", "xyze"]


@pytest.fixture(scope="module")
def bad_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("adv_cli_inputs")
    made = {}
    for name, (maker, frag) in af.BAD_EXR.items():
        made[name] = (maker(d), frag)
    for name in af.BAD_HDR:
        made[name] = (af.write_hdr_bytes(d, name), af.BAD_HDR[name][1])
    return made


def _cases():
    for cmd in ENV_COMMANDS:
        names = sorted(af.BAD_EXR) + sorted(af.BAD_HDR) if cmd in ("info", "convolve") else CLI_BAD_EXR + CLI_BAD_HDR
        for n in names:
            yield cmd, n


# files whose pixels decode: `info` (the diagnostic tool) reports them instead of refusing them, and its
# "check:"/"commands:" lines say what is wrong and that the other commands would refuse the file
INFO_REPORTS = {"nan_pixel": "NaN", "inf_pixel": "Inf", "negative_pixel": "negative",
                "conv_directx": "iblref_convention", "conv_int": "iblref_convention",
                "z_channel_only": "no R,G,B or Y channel", "aspect_5x7": "layout cannot be inferred"}


@pytest.mark.parametrize("cmd,bad", list(_cases()))
def test_every_command_over_bad_env_files(cmd, bad, bad_dir, tmp_path, capfd):
    path, fragment = bad_dir[bad]
    out = tmp_path / "out"
    out.mkdir()
    if cmd == "info" and bad in INFO_REPORTS:
        rc = main([str(a) for a in ENV_COMMANDS[cmd](path, out)])
        stdout, err = capfd.readouterr()
        assert rc == 0 and "Traceback" not in stdout + err and err == "", (rc, err)
        verdict = "\n".join(ln for ln in stdout.splitlines() if ln.startswith(("check:", "commands:")))
        assert INFO_REPORTS[bad] in verdict, stdout
        if bad != "negative_pixel":  # a large negative share is refused by --negative auto: also named
            assert "would refuse the file" in verdict, stdout
        assert listing(out) == {}
        return
    err = run(ENV_COMMANDS[cmd](path, out), capfd, 1)
    assert path.name in err and fragment.lower() in err.lower(), err
    assert listing(out) == {}  # nothing written, no folder created, no temp


@pytest.mark.parametrize("cmd", sorted(ENV_COMMANDS))
def test_missing_input_file(cmd, tmp_path, capfd):
    out = tmp_path / "out"
    out.mkdir()
    err = run(ENV_COMMANDS[cmd](tmp_path / "nope.exr", out), capfd, 1)
    assert "nope.exr" in err
    assert listing(out) == {}


@pytest.mark.parametrize("kind", ["fifo.exr", "fifo.hdr", "/dev/zero", "folder.exr"])
@pytest.mark.parametrize("cmd", sorted(ENV_COMMANDS))
def test_special_input_files_do_not_hang(cmd, kind, tmp_path, capfd):
    if kind.startswith("/"):
        src = Path(kind)
    else:
        src = tmp_path / kind
        os.mkfifo(src) if kind.startswith("fifo") else src.mkdir()
    out = tmp_path / "out"
    out.mkdir()
    err = run(ENV_COMMANDS[cmd](src, out), capfd, 1)
    assert src.name in err and ("not a regular file" in err or "folder" in err), err
    assert listing(out) == {}


@pytest.mark.parametrize("name", sorted(af.VALID_EXR))
@pytest.mark.parametrize("cmd", ["info", "convert", "mediancut"])
def test_unusual_valid_files_work(name, cmd, tmp_path, capfd):
    p, _ = af.VALID_EXR[name](tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    run(ENV_COMMANDS[cmd](p, out), capfd, 0)


# ------------------------------------------------------------------------------------------------
# numeric flags: one validation layer, usage errors name the flag
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def good(tmp_path_factory):
    d = tmp_path_factory.mktemp("adv_cli_good")
    return af.write_good_exr(d / "good.exr")


SIZE_FLAGS = [
    ("convolve", "--size"), ("convolve", "--input-size"), ("convolve", "--workers"),
    ("irradiance", "--size"), ("irradiance", "--input-size"),
    ("mediancut", "--size"), ("mediancut", "--lights"), ("pem", "--size"), ("pem", "--lights"),
    ("pyramid", "--size"), ("convert", "--size"),
    ("render", "--size"), ("render", "--vsm-res"), ("render", "--env-size"), ("render", "--lights"),
    ("km00-render", "--size"), ("km00-render", "--env-size"), ("km00-render", "--lobes"), ("km00-render", "--n-theta"),
    ("synth", "--size"),
]


def _argv_with(cmd, flag, value, good, out):
    base = {"synth": ["synth", "env", "sky_sun", out / "s.exr"]}.get(cmd) or ENV_COMMANDS[cmd](good, out)
    argv = [str(a) for a in base]
    if flag in argv:  # drop the existing value
        i = argv.index(flag)
        del argv[i : i + 2]
    return argv + [f"{flag}={value}"]  # the = form: "-inf" / "-5" are values, not options


COUNT_FLAGS = ("--workers", "--lights", "--lobes", "--n-theta")  # counts, not array sizes: no memory check


@pytest.mark.parametrize("cmd,flag,value", [(c, f, v) for c, f in SIZE_FLAGS for v in ("0", "-5", "1000000000")
                                            if not (v == "1000000000" and f in COUNT_FLAGS)])
def test_bad_sizes_are_usage_errors_naming_the_flag(cmd, flag, value, good, tmp_path, capfd):
    out = tmp_path / "out"
    out.mkdir()
    argv = _argv_with(cmd, flag, value, good, out)
    if cmd == "synth":
        argv = ["synth", "env", f"--size={value}", "sky_sun", str(out / "s.exr")]
    err = run(argv, capfd, 1)
    assert f"argument {flag}" in err, err
    if value == "1000000000":
        assert "memory" in err
    assert listing(out) == {}


FLOAT_FLAGS = [("convolve", "--rtol"), ("render", "--fov"), ("render", "--gloss"), ("km00-render", "--s"),
               ("km00-render", "--alpha")]


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
@pytest.mark.parametrize("cmd,flag", FLOAT_FLAGS)
def test_non_finite_floats_are_usage_errors(cmd, flag, value, good, tmp_path, capfd):
    out = tmp_path / "out"
    out.mkdir()
    err = run(_argv_with(cmd, flag, value, good, out), capfd, 1)
    assert f"argument {flag}" in err and "finite" in err


@pytest.mark.parametrize("argv,fragment", [
    (["convolve", "IN", "o.exr"], "--exponent"),
    (["convolve", "IN", "o.exr", "-s", "abc"], "--exponent"),
    (["convolve", "IN", "o.exr", "-s", "4", "--size", "2.5"], "--size"),  # argparse type error: exit 2
    (["mediancut", "IN", "--lights", "six", "--out", "m.json"], "--lights"),
    (["convert", "IN", "o.exr", "--layout", "sphere"], "--layout"),
    (["nosuchcommand"], "invalid choice"),
])
def test_usage_errors_are_one_line(argv, fragment, good, tmp_path, capfd, monkeypatch):
    monkeypatch.chdir(tmp_path)
    argv = [str(good) if a == "IN" else a for a in argv]
    expect = 1 if fragment == "--exponent" and "abc" in argv else 2
    if argv[0] == "nosuchcommand":
        with pytest.raises(SystemExit, match=r"^2$") as ei:
            main(argv)
        rc = ei.value.code
        _, err = capfd.readouterr()
        assert rc == 2 and len(err.strip().splitlines()) == 1 and fragment in err
        return
    err = run(argv, capfd, expect)
    assert fragment in err


# ------------------------------------------------------------------------------------------------
# special output paths
# ------------------------------------------------------------------------------------------------
OUT_COMMANDS = {  # command -> (argv builder, relative name of the output the argv writes)
    "convert": (lambda f, o: ["convert", f, o, "--layout", "cube"], "x.exr"),
    "irradiance": (lambda f, o: ["irradiance", f, o], "x.exr"),
    "pyramid": (lambda f, o: ["pyramid", f, o], "x.exr"),
    "mediancut": (lambda f, o: ["mediancut", f, "--lights", "6", "--out", o], "x.json"),
    "synth-env": (lambda f, o: ["synth", "env", "sky_sun", o, "--size", "4"], "x.exr"),
    "km00-render": (lambda f, o: ["km00-render", "--env", f, "--out", o, "--size", "8", "--env-size", "8",
                                  "--quiet", "--method", "single", "--n-theta", "2"], "x.exr"),
    "render": (lambda f, o: ["render", "--env", f, "--mesh", "torus", "--out", o, "--size", "8", "--lights", "6"],
               "x.exr"),
}


@pytest.mark.parametrize("kind", ["fifo", "folder", "link_to_dev_full", "link_to_fifo"])
@pytest.mark.parametrize("cmd", sorted(OUT_COMMANDS))
def test_special_output_targets_are_refused(cmd, kind, good, tmp_path, capfd):
    build, name = OUT_COMMANDS[cmd]
    target = tmp_path / name
    af.make_special(kind, target)
    before = sorted(p.name for p in tmp_path.iterdir())
    err = run(build(good, target), capfd, 1)
    assert name in err
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    if kind == "fifo":
        assert not target.is_file() and target.exists()


@pytest.mark.parametrize("cmd", sorted(OUT_COMMANDS))
def test_output_under_a_file(cmd, good, tmp_path, capfd):
    build, name = OUT_COMMANDS[cmd]
    (tmp_path / "afile").write_text("x")
    err = run(build(good, tmp_path / "afile" / "sub" / name), capfd, 1)
    assert "afile" in err
    assert (tmp_path / "afile").read_text() == "x"


@pytest.mark.parametrize("cmd", sorted(OUT_COMMANDS))
def test_output_through_a_symlink_keeps_the_link(cmd, good, tmp_path, capfd):
    build, name = OUT_COMMANDS[cmd]
    real = tmp_path / "real" / name
    real.parent.mkdir()
    real.write_bytes(b"old")
    link = tmp_path / name
    link.symlink_to(real)
    run(build(good, link), capfd, 0)
    assert link.is_symlink() and real.read_bytes() != b"old"
    no_temps(tmp_path)


@pytest.mark.parametrize("cmd", sorted(OUT_COMMANDS))
def test_read_only_file_system(cmd, good, tmp_path, capfd, monkeypatch):
    build, name = OUT_COMMANDS[cmd]
    af.inject_read_only(monkeypatch)
    (tmp_path / "out").mkdir()
    err = run(build(good, tmp_path / "out" / name), capfd, 1)
    assert "Read-only file system" in err
    assert listing(tmp_path / "out") == {}


@pytest.mark.parametrize("cmd", ["experiment", "reproduce"])
def test_experiment_out_under_a_file_or_read_only(cmd, tmp_path, capfd, monkeypatch):
    (tmp_path / "afile").write_text("x")
    argv = [cmd, "--quick", "--out", tmp_path / "afile" / "res"] + (["fig1"] if cmd == "experiment" else [])
    err = run(argv, capfd, 1)
    assert "afile" in err and "not a folder" in err

    af.inject_read_only_mkdir(monkeypatch)
    argv = [cmd, "--quick", "--out", tmp_path / "ro" / "res"] + (["fig1"] if cmd == "experiment" else [])
    err = run(argv, capfd, 1)
    assert "Read-only file system" in err


# ------------------------------------------------------------------------------------------------
# input == output
# ------------------------------------------------------------------------------------------------
SAME_FILE = {
    "convert": lambda f: ["convert", f, f, "--layout", "cube"],
    "irradiance": lambda f: ["irradiance", f, f],
    "pyramid": lambda f: ["pyramid", f, f],
    "mediancut": lambda f: ["mediancut", f, "--lights", "6", "--out", f],
    "render": lambda f: ["render", "--env", f, "--mesh", "torus", "--out", f],
    "render-png": lambda f: ["render", "--env", f, "--mesh", "torus", "--out", f.with_name("r.exr"), "--png", f],
    "km00-render": lambda f: ["km00-render", "--env", f, "--out", f],
    "convolve": lambda f: ["convolve", f, f.with_name("m.exr"), "-s", "4"],  # m_s4.exr == the input
}


@pytest.mark.parametrize("how", ["same", "symlink"])
@pytest.mark.parametrize("cmd", sorted(SAME_FILE))
def test_input_equal_to_output_is_refused(cmd, how, tmp_path, capfd):
    name = "m_s4.exr" if cmd == "convolve" else ("env.png" if cmd == "render-png" else "env.exr")
    src = af.write_good_exr(tmp_path / name)
    if cmd == "render-png":  # an EXR under a .png name: still an input, must not be overwritten
        pass
    data = src.read_bytes()
    arg = src
    if how == "symlink":
        link = tmp_path / ("link_" + name)
        link.symlink_to(src)
        argv = SAME_FILE[cmd](src)
        argv = [link if (a == src and i > 1 and cmd != "convolve") else a for i, a in enumerate(argv)]
        if cmd == "convolve":
            argv = ["convolve", link, tmp_path / "m.exr", "-s", "4"]
    else:
        argv = SAME_FILE[cmd](arg)
    err = run(argv[0:1] + argv[1:], capfd, 1)
    assert "same file as the input" in err
    assert src.read_bytes() == data
    no_temps(tmp_path)


# ------------------------------------------------------------------------------------------------
# multi-file outputs: full disk at the n-th file, stale files, leftovers
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("nth", [1, 2, 3, 4, 5, 6, 7])
def test_convolve_full_disk_keeps_the_previous_set(nth, tmp_path, capfd, monkeypatch):
    # 3 EXR writes + the staged JSON = 4 fsyncs while staging, then 4 before the renames
    a = af.write_good_exr(tmp_path / "a.exr", seed=1)
    b = af.write_good_exr(tmp_path / "b.exr", seed=2)
    out = tmp_path / "out"
    run(["convolve", a, out / "o.exr", "-s", "1", "-s", "4", "-s", "16", "--method", "exact"], capfd, 0)
    before = listing(out)
    af.inject_enospc(monkeypatch, nth)
    err = run(["convolve", b, out / "o.exr", "-s", "1", "-s", "4", "-s", "16", "--method", "exact"], capfd, 1)
    assert "No space left" in err
    assert listing(out) == before  # old _s1/_s4/_s16 and JSON, nothing new, no staging folder
    assert json.loads((out / "o.json").read_text())["input"] == str(a)


@pytest.mark.parametrize("nth", [1, 4, 7, 8])
def test_pem_full_disk_keeps_the_previous_set(nth, tmp_path, capfd, monkeypatch):
    a = af.write_good_exr(tmp_path / "a.exr", seed=1)
    b = af.write_good_exr(tmp_path / "b.exr", seed=2)
    out = tmp_path / "pems"
    run(["pem", a, "--lights", "6", "--out", out], capfd, 0)
    before = listing(out)
    af.inject_enospc(monkeypatch, nth)
    err = run(["pem", b, "--lights", "6", "--out", out], capfd, 1)
    assert "No space left" in err
    assert listing(out) == before


def test_pem_half_overflow_refused_before_writing(tmp_path, capfd):
    from ibl_ref.environment.exr_io import write_envmap

    cube = af.good_cube()
    cube[0, 0, 0] = 1e6  # > 65504 after filtering too (level 0 is the map itself)
    write_envmap(tmp_path / "bright.exr", cube)
    err = run(["pem", tmp_path / "bright.exr", "--lights", "6", "--out", tmp_path / "p", "--pixel-type", "half"],
              capfd, 1)
    assert "--pixel-type float" in err and "--clamp-half" not in err
    assert not (tmp_path / "p").exists()


def test_pem_rerun_with_fewer_lights_removes_stale_files(tmp_path, capfd):
    a = af.write_good_exr(tmp_path / "a.exr")
    out = tmp_path / "pems"
    run(["pem", a, "--lights", "12", "--out", out], capfd, 0)
    (out / "README.txt").write_text("mine")
    run(["pem", a, "--lights", "6", "--out", out], capfd, 0)
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"pem_{i:03d}.exr" for i in range(6)] + ["pems.json", "README.txt"])


def test_convolve_rerun_with_other_exponents_removes_stale_files(tmp_path, capfd):
    a = af.write_good_exr(tmp_path / "a.exr")
    out = tmp_path / "out"
    run(["convolve", a, out / "o.exr", "-s", "1", "-s", "4", "--method", "exact"], capfd, 0)
    (out / "o_s2.exr").write_bytes(b"user file, not in the manifest")
    run(["convolve", a, out / "o.exr", "-s", "16", "--method", "exact"], capfd, 0)
    assert sorted(p.name for p in out.iterdir()) == ["o.json", "o_s16.exr", "o_s2.exr"]


def test_killed_run_leftovers_are_cleaned_by_the_next_run(tmp_path, capfd):
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    a = af.write_good_exr(tmp_path / "a.exr")
    out = tmp_path / "pems"
    out.mkdir()
    (out / f".pems.json{atomic.TEMP_TAG}{p.pid}-00c0ffee").mkdir()
    (out / f".pems.json{atomic.TEMP_TAG}{p.pid}-00c0ffee" / "pem_000.exr").write_bytes(b"x" * 10000)
    (out / f".pem_000.exr{atomic.TEMP_TAG}{p.pid}-00c0ffef.exr").write_bytes(b"x" * 10000)
    run(["pem", a, "--lights", "6", "--out", out], capfd, 0)
    no_temps(out)


# ------------------------------------------------------------------------------------------------
# messages that used to mislead
# ------------------------------------------------------------------------------------------------
def test_pem_bogus_kernel_creates_nothing(good, tmp_path, capfd):
    err = run(["pem", good, "--lights", "6", "--out", tmp_path / "new", "--kernel", "bogus"], capfd, 1)
    assert "--kernel" in err and not (tmp_path / "new").exists()


@pytest.mark.parametrize("ext", [".png", ".jpg", ".tif", ""])
def test_convert_refuses_misleading_extensions(ext, good, tmp_path, capfd):
    err = run(["convert", good, tmp_path / f"x{ext}", "--layout", "cube"], capfd, 1)
    assert ".exr" in err and not (tmp_path / f"x{ext}").exists()


def test_synth_env_refuses_png(tmp_path, capfd):
    run(["synth", "env", "sky_sun", tmp_path / "x.png", "--size", "4"], capfd, 1)
    assert not (tmp_path / "x.png").exists()


def test_mediancut_hint_names_the_cli_flag(good, tmp_path, capfd):
    err = run(["mediancut", good, "--lights", "10", "--out", tmp_path / "m.json"], capfd, 1)
    assert "--variant global" in err and "variant='global'" not in err


def test_pyramid_hint_names_the_cli_flag(tmp_path, capfd):
    from ibl_ref.environment.exr_io import write_envmap

    write_envmap(tmp_path / "n3.exr", np.ones((6, 3, 3, 3)))
    err = run(["pyramid", tmp_path / "n3.exr", tmp_path / "p.exr"], capfd, 1)
    assert "--size" in err and "ibl_ref.environment.resample" not in err


def test_layout_hint_does_not_name_a_python_parameter(bad_dir, tmp_path, capfd):
    err = run(["convolve", bad_dir["aspect_5x7"][0], tmp_path / "o.exr", "-s", "4"], capfd, 1)
    assert "layout=" not in err
    assert main(["info", str(bad_dir["aspect_5x7"][0])]) == 0
    assert "layout=" not in capfd.readouterr().out


def test_material_overflow_names_the_flag(tmp_path, capfd):
    err = run(["render", "--mesh", "torus", "--material", "1e308,1e308,0.5", "--out", tmp_path / "r.exr",
               "--size", "8", "--lights", "6", "--env-size", "8"], capfd, 1)
    assert "--material" in err and "check the PEMs" not in err
    assert listing(tmp_path) == {}


@pytest.mark.parametrize("name", ["truncated_stl", "tiny_stl", "exr_renamed_obj", "point_cloud_ply", "empty_obj",
                                  "nan_vertex", "degenerate_faces", "vertices_only_obj", "binary_obj",
                                  "huge_coordinates"])
def test_render_bad_meshes(name, tmp_path, capfd):
    meshes = af.bad_meshes(tmp_path)
    p, fragment = meshes[name]
    out = tmp_path / "out"
    out.mkdir()
    err = run(["render", "--mesh", p, "--out", out / "r.exr", "--size", "8", "--lights", "6", "--env-size", "8"],
              capfd, 1)
    assert p.name in err and fragment.lower() in err.lower() and "charset" not in err
    assert listing(out) == {}


def test_mediancut_1e308_map_gives_finite_json_or_clear_error(tmp_path, capfd):
    from ibl_ref.environment.exr_io import write_envmap

    # float32 files top out at 3.4e38: a 1e38 map; the JSON must stay finite (no NaN/Inf written)
    write_envmap(tmp_path / "b.exr", np.ones((6, 4, 4, 3)) * 1e38)
    run(["mediancut", tmp_path / "b.exr", "--lights", "6", "--out", tmp_path / "m.json"], capfd, 0)
    data = json.loads((tmp_path / "m.json").read_text())
    rgb = np.array([li["rgb"] for li in data["lights"]])
    assert np.allclose(rgb, 1e38 * 4 * np.pi / 6, rtol=1e-6)  # ∫ L dω over one face of a constant map


# ------------------------------------------------------------------------------------------------
# real subprocesses
# ------------------------------------------------------------------------------------------------
def _sub(args, timeout=120):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "ibl_ref", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=env)


@pytest.mark.parametrize("bad", ["trunc_half", "deep", "huge_claim_1e9x2e9"])
def test_subprocess_bad_file_one_line_no_openexr_noise(bad, bad_dir):
    r = _sub(["info", bad_dir[bad][0]])
    assert r.returncode == 1 and r.stdout == ""
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr


def test_subprocess_fifo_output_does_not_hang(good, tmp_path):
    os.mkfifo(tmp_path / "x.exr")
    r = _sub(["convert", good, tmp_path / "x.exr", "--layout", "cube"], timeout=60)
    assert r.returncode == 1 and "FIFO" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_subprocess_usage_error(good):
    r = _sub(["convolve", good, "o.exr", "-s", "1", "--size", "1000000000"])
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1 and "--size" in r.stderr


@pytest.mark.parametrize("case", ["under_a_file", "is_a_file", "read_only"])
def test_pem_out_folder_problems(case, good, tmp_path, capfd, monkeypatch):
    (tmp_path / "afile").write_text("x")
    out = {"under_a_file": tmp_path / "afile" / "pems", "is_a_file": tmp_path / "afile",
           "read_only": tmp_path / "ro" / "pems"}[case]
    if case == "read_only":
        af.inject_read_only_mkdir(monkeypatch)
    err = run(["pem", good, "--lights", "6", "--out", out], capfd, 1)
    assert str(out.name) in err or "afile" in err
    assert (tmp_path / "afile").read_text() == "x"
    assert not (tmp_path / "ro").exists()


def test_info_negative_alpha_is_not_reported_as_clean(tmp_path, capfd):
    s = np.ones((24, 4, 4), np.float32)
    s[..., 3] = -1.0  # alpha < 0: not radiance, but "no negative values" would be false
    af._exr_raw(tmp_path / "nega.exr", {"R": s[..., 0], "G": s[..., 1], "B": s[..., 2], "A": s[..., 3]})
    rc = main(["info", str(tmp_path / "nega.exr")])
    out, err = capfd.readouterr()
    assert "Traceback" not in out + err
    check = next((ln for ln in out.splitlines() if ln.startswith("check:")), "")
    assert rc == 0
    assert "no negative radiance" not in check and "channel(s) A (96)" in check, check


@pytest.mark.parametrize("argv,fragment", [
    (["convolve", "IN", "OUT/o.exr", "-s=nan"], "--exponent"),
    (["convolve", "IN", "OUT/o.exr", "-s=0.5"], "--exponent"),
    (["convolve", "IN", "OUT/o.exr", "-s=-1"], "--exponent"),
    (["convolve", "IN", "OUT/o.exr", "-s=1e400"], "write 'inf'"),  # overflow must not silently mean the mirror
    (["convolve", "IN", "OUT/o.exr", "-s", "4", "--rtol", "0"], "--rtol"),
    (["convolve", "IN", "OUT/o.exr", "-s", "4", "--rtol", "2"], "--rtol"),
    (["km00-render", "--alpha", "0", "--out", "OUT/k.exr", "--size", "8", "--env-size", "4", "--quiet"], "--alpha"),
    (["km00-render", "--ks=-1", "--out", "OUT/k.exr", "--size", "8", "--env-size", "4", "--quiet"], "--ks"),
    (["km00-render", "--env-size", "3", "--out", "OUT/k.exr", "--size", "8", "--quiet"], "--env-size"),
    (["render", "--mesh", "torus", "--fov", "0", "--out", "OUT/r.exr"], "--fov"),
    (["render", "--mesh", "torus", "--size", "1", "2", "3", "--out", "OUT/r.exr"], "--size"),
    (["render", "--mesh", "torus", "--size", "9000", "--out", "OUT/r.exr"], "--size"),
    (["render", "--mesh", "torus", "--material", "1,2", "--out", "OUT/r.exr"], "--material"),
    (["render", "--mesh", "torus", "--material", "nan,0.5,0.5", "--out", "OUT/r.exr"], "--material"),
    (["render", "--mesh", "torus", "--out", "OUT/r.png"], "--out"),
    (["render", "--mesh", "nosuchmesh", "--out", "OUT/r.exr"], "nosuchmesh"),
    (["convert", "IN", "OUT/o.exr", "--layout", "cube", "--clamp-half"], "--clamp-half"),
    (["convert", "IN", "OUT/o.hdr", "--layout", "cube"], "latlong"),
    (["synth", "mesh", "torus", "OUT/m.xyz"], "unsupported mesh format"),
    (["synth", "env", "sky_sun", "OUT/e.exr", "--size", "4", "--param", "nosuch=1"], "nosuch"),
    (["mediancut", "IN", "--lights", "3", "--out", "OUT/m.json"], "--lights"),
    (["render", "--mesh", "torus", "--lights", "5", "--out", "OUT/r.exr", "--size", "8"], "--lights"),
    (["render", "--mesh", "torus", "--lights", "7", "--out", "OUT/r.exr", "--size", "8"], "--median-cut global"),
    (["pem", "IN", "--lights", "7", "--out", "OUT/p"], "--variant global"),
    (["render", "--mesh", "torus", "--distance", "1e308", "--out", "OUT/r.exr", "--size", "8"], "--distance 1e+308"),
    (["render", "--mesh", "torus", "--camera-eye", "1e308", "1", "1", "--out", "OUT/r.exr", "--size", "8"],
     "--camera-eye: coordinates up to 1e+308"),
    (["render", "--mesh", "torus", "--camera-target", "1e200", "0", "0", "--out", "OUT/r.exr", "--size", "8"],
     "--camera-target: coordinates up to 1e+200"),
    (["render", "--mesh", "torus", "--camera-up", "1e300", "0", "0", "--out", "OUT/r.exr", "--size", "8"],
     "--camera-up"),
    (["render", "--mesh", "torus", "--material", "1e300,0,0.5", "--out", "OUT/r.exr", "--size", "8", "--lights", "6",
      "--env-size", "8"], "--material / --ground-material"),
])
def test_bad_values_name_the_cli_flag(argv, fragment, good, tmp_path, capfd):
    out = tmp_path / "out"
    out.mkdir()
    argv = [str(good) if a == "IN" else a.replace("OUT", str(out)) for a in argv]
    err = run(argv, capfd, 1)
    assert fragment in err, err
    assert listing(out) == {}


def test_subprocess_overflowing_material_prints_one_line(tmp_path):
    # in a real process numpy's RuntimeWarnings would reach stderr: the check happens before any arithmetic
    r = _sub(["render", "--mesh", "torus", "--material", "1e308,1e308,0.5", "--out", tmp_path / "r.exr",
              "--size", "8", "--lights", "6", "--env-size", "8"])
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1 and "--material" in r.stderr
    assert list(tmp_path.iterdir()) == []



# ------------------------------------------------------------------------------------------------
# reliability classes: overflow, values below a format's range, side files, messages, Ctrl-C
# ------------------------------------------------------------------------------------------------
def _exr_pixels(path) -> np.ndarray:
    """(H, W, C) float64 of an EXR read with the OpenEXR binding directly (not through ibl_ref's reader)."""
    import OpenEXR

    with OpenEXR.File(os.fsencode(path), separate_channels=True) as f:
        ch = f.parts[0].channels
        names = [c for c in ("R", "G", "B", "Y") if c in ch]
        return np.stack([np.asarray(ch[c].pixels, np.float64) for c in names], axis=-1)


@pytest.mark.parametrize("argv", [
    ["render", "--mesh", "torus", "--out", "OUT/r.exr", "--png", "OUT/r.png", "--exposure", "1e9", "--size", "8"],
    ["render", "--mesh", "torus", "--out", "OUT/r.exr", "--png", "OUT/r.png", "--exposure", "1100", "--size", "8"],
    ["render", "--mesh", "torus", "--out", "OUT/r.exr", "--png", "OUT/r.png", "--exposure", "x1e-320", "--size", "8"],
    ["km00-render", "--png", "--exposure", "1e9", "--out", "OUT/k.exr", "--size", "8", "--quiet"],
    ["km00-render", "--png", "--exposure=-1e9", "--out", "OUT/k.exr", "--size", "8", "--quiet"],
])
def test_exposure_overflow_is_one_line_naming_the_flag(argv, tmp_path, capfd):
    out = tmp_path / "out"
    out.mkdir()
    err = run([a.replace("OUT", str(out)) for a in argv], capfd, 1)
    assert "--exposure" in err and "float64" in err
    assert listing(out) == {}  # nothing written, not even the EXR


def test_exposure_at_the_limit_writes_a_saturated_png(tmp_path, capfd):
    # 1000 stops: every covered pixel saturates (Reinhard of 2^1000 x), no overflow, no NaN in the PNG
    import matplotlib.image as mpimg

    run(["render", "--mesh", "torus", "--out", tmp_path / "r.exr", "--png", tmp_path / "r.png", "--exposure", "1000",
         "--size", "8", "--lights", "6", "--env-size", "8", "--background", "black"], capfd, 0)
    png = mpimg.imread(tmp_path / "r.png")[..., :3]
    img = _exr_pixels(tmp_path / "r.exr")
    lit = img.max(axis=-1) > 1e-200
    assert np.all(np.isfinite(png)) and lit.any() and np.all(png[lit] > 0.99)


def test_km00_failed_png_leaves_no_exr(tmp_path, capfd, monkeypatch):
    from ibl_ref.errors import IBLError
    from ibl_ref.rendering import tonemap

    def fail(*a, **k):
        raise IBLError("injected PNG failure")

    monkeypatch.setattr(tonemap, "save_png", fail)
    out = tmp_path / "out"
    out.mkdir()
    run(["km00-render", "--png", "--out", out / "k.exr", "--size", "8", "--env-size", "8", "--n-theta", "2",
         "--method", "single", "--quiet"], capfd, 1)
    assert listing(out) == {}


@pytest.mark.parametrize("value,argv,fragment", [
    (1e-8, ["convert", "IN", "OUT/o.exr", "--layout", "latlong", "--half"], "half"),
    (1e-8, ["convert", "IN", "OUT/o.exr", "--layout", "cube", "--half"], "half"),
    (1e-40, ["convert", "IN", "OUT/o.hdr", "--layout", "latlong"], "RGBE"),
    (1e-8, ["pyramid", "IN", "OUT/p.exr", "--pixel-type", "half"], "half"),
])
def test_values_below_a_format_range_are_refused_not_zeroed(value, argv, fragment, tmp_path, capfd):
    src = af.tiny_latlong(tmp_path / "tiny.exr", value)
    out = tmp_path / "out"
    out.mkdir()
    err = run([str(src) if a == "IN" else a.replace("OUT", str(out)) for a in argv], capfd, 1)
    assert fragment in err and "1.00e+00 of the integral" in err and "stored as 0" in err, err
    assert listing(out) == {}


def test_values_within_a_format_range_convert_exactly(tmp_path, capfd):
    # 1e-8 survives float32 and RGBE: both files, read back independently, hold the map (RGBE to 1/256)
    from ibl_ref.environment.hdr_io import read_hdr

    src = af.tiny_latlong(tmp_path / "tiny.exr", 1e-8)
    run(["convert", src, tmp_path / "o.exr", "--layout", "latlong"], capfd, 0)
    np.testing.assert_allclose(_exr_pixels(tmp_path / "o.exr"), np.float32(1e-8), rtol=0)
    run(["convert", src, tmp_path / "o.hdr", "--layout", "latlong"], capfd, 0)
    np.testing.assert_allclose(read_hdr(tmp_path / "o.hdr"), 1e-8, rtol=1 / 256)


@pytest.mark.parametrize("cmd", ["render", "convolve", "km00-render"])
def test_side_files_never_replace_a_users_file(cmd, good, tmp_path, capfd):
    out = tmp_path / "out"
    out.mkdir()
    argv = {"render": ["render", "--mesh", "torus", "--out", out / "r.exr", "--size", "8", "--lights", "6",
                       "--env-size", "8"],
            "convolve": ["convolve", good, out / "r.exr", "-s", "4"],
            "km00-render": ["km00-render", "--png", "--out", out / "r.exr", "--size", "8", "--env-size", "8",
                            "--n-theta", "2", "--method", "single", "--quiet"]}[cmd]
    (out / "r.json").write_text('{"mine": 1}\n')  # a file of the user's that happens to have the sidecar's name
    err = run(argv, capfd, 1)
    assert "r.json" in err and "refusing" in err
    assert listing(out) == {"r.json": b'{"mine": 1}\n'}
    (out / "r.json").unlink()
    side = {"render": None, "convolve": "r_s4.exr", "km00-render": "r.png"}[cmd]
    if side:  # the other side file: also never replaced when it is not the previous run's
        (out / side).write_bytes(b"user data")
        err = run(argv, capfd, 1)
        assert side in err and (out / side).read_bytes() == b"user data"
        (out / side).unlink()
    run(argv, capfd, 0)  # a fresh run, then a rerun over its own side files: both fine
    first = json.loads((out / "r.json").read_text())
    assert first.get("outputs")
    run(argv, capfd, 0)
    no_temps(out)


def test_km00_too_narrow_lobe_names_alpha_without_warnings(tmp_path, capfd):
    r = _sub(["km00-render", "--brdf", "cook_torrance", "--alpha", "1e-9", "--out", tmp_path / "k.exr", "--size", "8",
              "--quiet"])
    lines = r.stderr.strip().splitlines()
    # 1e-9 is below the lobe-width floor 2^-20 (the GGX roughness floor squared), refused before any work
    assert r.returncode == 1 and len(lines) == 1 and "--alpha" in lines[0] and "2^-20" in lines[0], lines
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("alpha", ["1e-4", "1e-3"])
def test_km00_lobes_the_maps_cannot_resolve_are_refused(alpha, tmp_path, capfd):
    # Ward alpha 1e-4 gave an all-black lobes image with exit 0; 1e-3 was 38 % too dark (measured vs. the reference)
    err = run(["km00-render", "--alpha", alpha, "--out", tmp_path / "k.exr", "--size", "8", "--quiet"], capfd, 1)
    assert f"--alpha {float(alpha):g}" in err and "larger environment" in err


def test_km00_horizon_singularity_is_named_as_such(tmp_path, capfd):
    err = run(["km00-render", "--alpha", "0.3", "--out", tmp_path / "k.exr", "--size", "8", "--env-size", "8",
               "--quiet"], capfd, 1)
    assert "peaks at the horizon" in err


def test_nan_uvs_with_a_gmap_name_the_mesh_and_the_flag(tmp_path, capfd):
    mesh = af.obj_file(tmp_path / "nanuv.obj", uv="nan nan")
    np.save(tmp_path / "g.npy", np.full((4, 4), 0.5))
    out = tmp_path / "out"
    out.mkdir()
    base = ["render", "--mesh", mesh, "--out", out / "r.exr", "--size", "8", "--lights", "6", "--env-size", "8"]
    for extra in ([], ["--gmap-fallback", "error"], ["--gmap-fallback", "spherical"]):
        err = run(base + ["--gmap", tmp_path / "g.npy"] + extra, capfd, 1)
        assert "nanuv.obj" in err and "NaN" in err and "--gmap-fallback" in err and "uv_fallback" not in err, err
    assert listing(out) == {}
    run(base, capfd, 0)  # without a g map the UVs are not used


def test_missing_uvs_error_names_the_flag(tmp_path, capfd):
    np.save(tmp_path / "g.npy", np.full((4, 4), 0.5))
    err = run(["render", "--mesh", "torus", "--gmap", tmp_path / "g.npy", "--gmap-fallback", "error", "--out",
               tmp_path / "r.exr", "--size", "8", "--lights", "6", "--env-size", "8"], capfd, 1)
    assert "--gmap-fallback planar_xz" in err and "uv_fallback" not in err


def test_non_utf8_file_names_read_and_write(tmp_path, capfd):
    src = af.non_utf8_name(tmp_path)
    run(["info", src], capfd, 0)
    dst = tmp_path / os.fsdecode(b"o\xff.exr")
    run(["convert", src, dst, "--layout", "cube"], capfd, 0)
    np.testing.assert_allclose(_exr_pixels(dst).reshape(6, af.N, af.N, 3), af.good_cube().astype(np.float32))
    hdr = tmp_path / os.fsdecode(b"o\xfe.hdr")
    run(["convert", src, hdr, "--layout", "latlong"], capfd, 0)
    assert os.fsencode(hdr.name) in os.listdir(os.fsencode(tmp_path))
    r = tmp_path / os.fsdecode(b"r\xff.exr")
    run(["render", "--mesh", "torus", "--env", src, "--out", r, "--size", "8", "--lights", "6", "--env-size", "8"],
        capfd, 0)
    assert _exr_pixels(r).shape == (8, 8, 3)


def test_render_help_matches_the_light_rules(good, tmp_path, capfd):
    with pytest.raises(SystemExit, match="^0$"):
        main(["render", "--help"])
    text = " ".join(capfd.readouterr().out.split())
    assert "allow any --lights >= 6" in text
    for variant in ("variance", "global"):
        err = run(["render", "--mesh", "torus", "--median-cut", variant, "--lights", "1", "--out", tmp_path / "r.exr",
                   "--size", "8"], capfd, 1)
        assert ">= 6" in err
        run(["render", "--mesh", "torus", "--median-cut", variant, "--lights", "7", "--out", tmp_path / "r.exr",
             "--size", "8", "--env-size", "8"], capfd, 0)


@pytest.mark.parametrize("cmd", ["mediancut", "pem", "render"])
def test_light_count_is_checked_before_the_file_is_read(cmd, bad_dir, tmp_path, capfd):
    bad, _ = bad_dir["trunc_half"]  # a file that would fail to read: the --lights error must come first
    argv = {"mediancut": ["mediancut", bad, "--lights", "16", "--out", tmp_path / "m.json"],
            "pem": ["pem", bad, "--lights", "16", "--out", tmp_path / "p"],
            "render": ["render", "--env", bad, "--lights", "16", "--out", tmp_path / "r.exr"]}[cmd]
    err = run(argv, capfd, 1)
    assert "--lights" in err and "multiple of 6" in err and bad.name not in err


def test_scheduler_at_nothing_says_it_is_waiting(good, tmp_path, capfd, monkeypatch):
    pytest.importorskip("distributed")
    from ibl_ref import executors

    monkeypatch.setattr(executors, "CONNECT_TIMEOUT_S", 0.5)
    monkeypatch.setenv("IBL_REF_PROGRESS", "lines")
    rc = main(["convolve", str(good), str(tmp_path / "o.exr"), "-s", "4", "--scheduler", "tcp://127.0.0.1:9"])
    _, err = capfd.readouterr()
    lines = err.strip().splitlines()
    assert rc == 1 and "waiting up to 0.5 s" in lines[0] and "cannot connect" in lines[-1], lines
    assert "reading" not in err  # refused before the input is read
    assert list(tmp_path.iterdir()) == []


def test_failed_experiment_leaves_no_folder(tmp_path, capfd, monkeypatch):
    af.inject_enospc(monkeypatch, 1)
    out = tmp_path / "res"
    run(["experiment", "fig1", "--quick", "--out", out], capfd, 1)
    assert not out.exists()


def test_failed_pem_leaves_no_folder(good, tmp_path, capfd, monkeypatch):
    af.inject_enospc(monkeypatch, 1)
    out = tmp_path / "new" / "pems"
    run(["pem", good, "--lights", "6", "--out", out], capfd, 1)
    assert not (tmp_path / "new").exists()


def test_convert_says_what_a_big_conversion_costs(tmp_path, capfd, monkeypatch):
    # the cost model of ibl_ref.environment.resample says the peak memory before the work: beyond the (here
    # lowered) memory limit the conversion is refused; the 16K -> 4096² case is predicted at > 10 GiB
    from ibl_ref.environment.resample import latlong_to_cube_cost

    assert latlong_to_cube_cost(8192, 4096)["bytes"] > 10 * 2**30
    src = af.tiny_latlong(tmp_path / "p.exr", 1.0, h=64)
    monkeypatch.setenv("IBL_REF_MAX_BYTES", str(50 * 2**20))
    rc = main(["convert", str(src), str(tmp_path / "o.exr"), "--layout", "cube"])
    _, err = capfd.readouterr()
    assert rc == 1 and "--size" in err and "memory" in err and not (tmp_path / "o.exr").exists()


def test_info_mean_is_weighted_by_solid_angle(tmp_path, capfd):
    # radiance 1 above latitude 45°, 0 below (lat-long rows): the solid-angle weighted mean is the cap's share of
    # the sphere, (1 - sin 45°)/2 = 0.146447 (closed form); the per-pixel mean would be 1/4
    h = 16
    px = np.zeros((h, 2 * h), np.float32)
    px[: h // 4] = 1.0
    af._exr_raw(tmp_path / "cap.exr", {"R": px, "G": px, "B": px})
    assert main(["info", str(tmp_path / "cap.exr")]) == 0
    out = capfd.readouterr().out
    head = next(ln for ln in out.splitlines() if ln.startswith("channel "))
    row = next(ln for ln in out.splitlines() if ln.startswith("R "))
    assert head.split()[3] == "mean_per_sr"
    assert float(row.split()[3]) == pytest.approx((1 - np.sin(np.pi / 4)) / 2, rel=1e-5)


def _interrupt(argv, delay, cwd, tries: int = 0):
    """Run the CLI in a subprocess; ``delay`` s after its code starts (the "go" line, printed once ``ibl_ref.cli`` is
    imported: the interpreter's own start-up before it is Python's, not the package's), send Ctrl-C."""
    import time

    env = dict(os.environ, PYTHONPATH=str(ROOT), IBL_REF_PROGRESS="0")
    code = "import sys, ibl_ref.cli as c; print('go', file=sys.stderr, flush=True); sys.exit(c.main())"
    # the child starts with SIGINT's default disposition, as from an interactive shell, even when this test
    # process inherited it ignored (an inherited SIG_IGN is kept by the CLI: ibl_ref.cli.interrupts)
    p = subprocess.Popen([sys.executable, "-c", code, *map(str, argv)], cwd=cwd, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert p.stderr.readline() == "go\n"
    time.sleep(delay)
    os.killpg(p.pid, signal.SIGINT)  # Ctrl-C on a terminal: the whole process group
    out, err = p.communicate(timeout=120)
    if err == _BEFORE_MAIN and tries < 5:
        # on a loaded machine the child can be descheduled right after its "go" line, so that the interrupt lands
        # in this harness's own line, before ``main`` is entered: not the package's code; run again
        return _interrupt(argv, delay, cwd, tries + 1)
    return p.returncode, err


#: the whole stderr of a child interrupted in the harness's ``-c`` line, before ``ibl_ref.cli.main`` was entered
_BEFORE_MAIN = 'Traceback (most recent call last):\n  File "<string>", line 1, in <module>\nKeyboardInterrupt\n'


@pytest.mark.parametrize("delay", [0.0, 0.05, 0.2, 0.4, 0.7, 1.0])
def test_ctrl_c_at_any_moment_is_130_one_line_no_partial_output(delay, tmp_path):
    # the first second of `render` imports trimesh and scipy (whose optional-import guards swallowed a
    # KeyboardInterrupt): the interrupt is deferred until the import is done, never lost
    rc, err = _interrupt(["render", "--mesh", "torus", "--out", "r.exr", "--png", "r.png", "--size", "16",
                          "--lights", "6", "--env-size", "8"], delay, tmp_path)
    names = sorted(p.name for p in tmp_path.iterdir())
    assert "Traceback" not in err and "NameError" not in err, err
    assert rc in (0, 130), (rc, err)
    if rc == 130:
        assert err.strip().splitlines() == ["ibl-ref render: interrupted"]
    assert names in ([], ["r.exr", "r.json", "r.png"]), names  # the output set entirely, or nothing
    assert rc == 130 or names, "exit 0 without outputs"


def test_ctrl_c_handler_imports_nothing_so_it_can_land_inside_any_import():
    """The SIGINT handler may run while a module is half-imported, e.g. ``pathlib`` during the first command's
    imports (a fresh, non-editable installation imports it late); an import made by the handler itself would then
    fail (``cannot import name 'Path' from partially initialized module 'pathlib'``, a traceback instead of exit
    130; seen once in the timing test above).  Here ``pathlib`` is replaced by a half-initialised stand-in before
    ``ibl_ref.atomic`` was imported: the handler must raise KeyboardInterrupt and import nothing."""
    code = textwrap.dedent("""
        import signal, sys, types
        from ibl_ref.cli import interrupts
        assert "ibl_ref.atomic" not in sys.modules
        real = sys.modules.pop("pathlib", None)
        sys.modules["pathlib"] = types.ModuleType("pathlib")  # half-initialised: no Path yet
        try:
            interrupts._on_sigint(signal.SIGINT, None)
        except KeyboardInterrupt:
            print("KeyboardInterrupt", "ibl_ref.atomic" in sys.modules)
        finally:
            sys.modules["pathlib"] = real
    """)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert p.returncode == 0 and p.stdout.split() == ["KeyboardInterrupt", "False"], (p.stdout, p.stderr)


def test_ctrl_c_stops_forked_workers(tmp_path, monkeypatch):
    # convolve on 2 forked workers: the workers print nothing, the command stops them and exits 130 at once.
    # The work must outlast the delay on any machine: the dense gather at 64² is 6e8 texel pairs per exponent
    # (seconds on the NumPy kernel, which the environment pins), so the interrupt arrives while the workers run
    src = af.tiny_latlong(tmp_path / "p.exr", 1.0, h=128)
    out = tmp_path / "out"
    out.mkdir()
    monkeypatch.setenv("IBL_REF_KERNEL", "numpy")
    rc, err = _interrupt(["convolve", src, out / "v.exr", "-s", "4", "-s", "16", "-s", "64", "--method", "exact",
                          "--workers", "2", "--parallel", "process", "--input-size", "64"], 1.0, tmp_path)
    assert rc == 130 and err.strip().splitlines() == ["ibl-ref convolve: interrupted"], err
    assert listing(out) == {}
