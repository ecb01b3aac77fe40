"""Adversarial suite, library side: bad files, extreme numbers, special output paths, full disks.

Every bad input is generated here (tests/adversarial_files.py).  What each case asserts:

* readers: the error is an :class:`~ibl_ref.errors.IBLError` subclass, one line, naming the file and
  the problem (fragment from the file-format fact that was violated);
* extreme values: a finite result whose value is checked against an independent route (power-of-two
  scaling is exact in binary floating point, so ``f(2^k·x) = 2^k·f(x)`` bit for bit for sums and
  unchanged for split decisions), or a clear error — never silent Inf/NaN;
* outputs (:mod:`ibl_ref.atomic`): no file under the final name on failure, the old file intact, no
  temporary or staging files left, special targets untouched.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import adversarial_files as af
from ibl_ref import atomic
from ibl_ref.errors import IBLError, RadianceError
from ibl_ref.environment.exr_io import load_cube, read_envmap, write_envmap
from ibl_ref.limits import SizeError
from ibl_ref.knuth2014.median_cut import check_partition, median_cut


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    return tmp_path_factory.mktemp("adv_api")


def _one_line_error(exc: BaseException, path: Path, fragment: str):
    msg = str(exc)
    assert isinstance(exc, IBLError), f"{type(exc).__name__}: {msg}"
    assert "\n" not in msg
    assert path.name in msg, msg
    assert fragment.lower() in msg.lower(), msg


def _no_temp_left(folder: Path):
    left = [p.name for p in Path(folder).iterdir() if atomic.TEMP_TAG in p.name]
    assert left == [], left


# ------------------------------------------------------------------------------------------------
# readers
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(af.BAD_EXR))
@pytest.mark.parametrize("reader", ["load_cube", "read_envmap"])
def test_bad_exr_is_a_one_line_error(files, name, reader, capfd):
    maker, fragment = af.BAD_EXR[name]
    p = maker(files)
    fn = load_cube if reader == "load_cube" else read_envmap
    with pytest.raises(IBLError, match=f"(?i){re.escape(fragment)}") as ei:
        fn(p)
    _one_line_error(ei.value, p, fragment)
    out, err = capfd.readouterr()
    assert "Warning" not in out + err  # OpenEXR's own stdout/stderr text is captured, not printed


@pytest.mark.parametrize("name", sorted(af.BAD_HDR))
def test_bad_hdr_is_a_one_line_error(files, name):
    p = af.write_hdr_bytes(files, name)
    with pytest.raises(IBLError, match=f"(?i){re.escape(af.BAD_HDR[name][1])}") as ei:
        load_cube(p)
    _one_line_error(ei.value, p, af.BAD_HDR[name][1])


@pytest.mark.parametrize("name", sorted(af.VALID_EXR))
def test_unusual_but_valid_exr_reads_exactly(files, name):
    # tiled, multi-part (first part read) and OpenGL-oriented files hold float32 copies of known cubes
    p, expected = af.VALID_EXR[name](files)
    assert np.array_equal(load_cube(p), expected)


@pytest.mark.parametrize("size", [2.5, 0, -1, True, "8", float("nan"), float("inf"), 10**9])
def test_load_cube_size_must_be_a_sane_integer(files, size):
    p = af.write_good_exr(files / "good_size.exr")
    with pytest.raises(SizeError, match="size"):
        load_cube(p, size=size)


def test_load_cube_accepts_integral_float_size(files):
    p = af.write_good_exr(files / "good_size2.exr")
    assert load_cube(p, size=8.0).shape == (6, 8, 8, 3)
    assert load_cube(p, size=np.int64(2)).shape == (6, 2, 2, 3)


@pytest.mark.parametrize("name", ["truncated_stl", "tiny_stl", "exr_renamed_obj", "point_cloud_ply", "empty_obj",
                                  "nan_vertex", "degenerate_faces", "vertices_only_obj", "binary_obj"])
def test_bad_mesh_files(files, name):
    from ibl_ref.synthetic.synthetic_meshes import load_mesh

    d = files / "meshes"
    d.mkdir(exist_ok=True)
    p, fragment = af.bad_meshes(d)[name]
    with pytest.raises(IBLError, match=f"(?i){re.escape(fragment)}") as ei:
        load_mesh(p)
    _one_line_error(ei.value, p, fragment)


# ------------------------------------------------------------------------------------------------
# extreme numbers
# ------------------------------------------------------------------------------------------------
MC_SCALES = [2.0**-1060, 1e-300, 1e-30, 1.0, 1e30, 1e300, 1e308]


@pytest.mark.parametrize("scale", MC_SCALES, ids=lambda s: f"{s:.0e}")
@pytest.mark.parametrize("variant", ["per-face", "global", "variance"])
@pytest.mark.parametrize("n_lights", [6, 24])
def test_median_cut_extreme_scales(scale, variant, n_lights):
    cube = af.good_cube(1)
    x = cube * scale
    try:
        ls = median_cut(x, n_lights, variant)
    except IBLError as exc:  # allowed only if a light's colour really exceeds float64
        assert "largest float64" in str(exc)
        # independent check that it does: the largest region integral, computed at scale 1
        ref = median_cut(cube, n_lights, variant)
        assert ref.rgb.max() * scale > np.finfo(np.float64).max / 4
        return
    assert np.all(np.isfinite(ls.rgb)) and np.all(np.isfinite(ls.energy))
    assert np.allclose(np.linalg.norm(ls.directions, axis=1), 1.0, rtol=0, atol=1e-12)
    # reference: the same map at scale 1; the partition is unchanged and the colours scale.  Scaling
    # by a non-power of two rounds each texel (1 ulp), hence rtol 1e-12; subnormal scales keep only a
    # few bits of each texel, there only the partition identity is checked.
    ref = median_cut(cube, n_lights, variant)
    if scale > 1e-300:
        assert np.array_equal(ls.regions, ref.regions)
        assert np.allclose(ls.rgb / scale, ref.rgb, rtol=1e-12, atol=0)
    chk = check_partition(ls, x)
    assert chk["uncovered"] == 0 and chk["overlapping"] == 0
    assert chk["rgb_sum_rel_err"] < (1e-12 if scale > 1e-300 else 0.2)


@pytest.mark.parametrize("k", [-1000, -600, 600, 1000])
def test_median_cut_power_of_two_scaling_is_exact(k):
    # 2^k scaling is exact for normal numbers, so every result must scale bit for bit
    cube = af.good_cube(2, 8)
    ref = median_cut(cube, 24, "variance")
    ls = median_cut(np.ldexp(cube, k), 24, "variance")
    assert np.array_equal(ls.regions, ref.regions)
    assert np.array_equal(ls.rgb, np.ldexp(ref.rgb, k))
    assert np.array_equal(ls.directions, ref.directions)


def test_median_cut_ones_1e308_six_lights_is_a_clear_error():
    # each light's colour is ∫ L dω over one face = 1e308 · 4π/6 ≈ 2.09e308 > 1.797e308: not representable
    with pytest.raises(IBLError, match="largest float64"):
        median_cut(np.ones((6, 4, 4, 3)) * 1e308, 6)


def test_median_cut_integer_map_is_refused():
    # an integer array is a display image (0..255), not linear radiance: the radiance policy refuses it
    # (ibl_ref.environment.radiance_policy), naming the dtype, instead of guessing a scale
    cube = (af.good_cube(3) * 100).astype(np.int64)
    with pytest.raises(RadianceError, match="int64"):
        median_cut(cube, 12, "global")


def test_median_cut_single_subnormal_texel():
    # one lit texel of 5e-324 (the smallest subnormal): the per-face cut still partitions the map and
    # the light that holds it points at that texel (its own direction: a one-texel centroid)
    from ibl_ref.environment.envmap import texel_directions

    cube = np.zeros((6, 4, 4, 3))
    cube[2, 1, 3] = 5e-324
    ls = median_cut(cube, 6)
    d = texel_directions(4)[2, 1, 3]
    assert np.all(np.isfinite(ls.directions))
    assert np.allclose(ls.directions[2], d / np.linalg.norm(d), atol=1e-12)


@pytest.mark.parametrize("method", ["exact", "sh", "sparse", "auto"])
def test_convolve_1e308_is_finite_or_an_error(method):
    from ibl_ref.groundtruth.convolve import convolve

    try:
        res = convolve(np.ones((6, 4, 4, 3)) * 1e308, [1.0], method=method)
    except IBLError:
        return
    m = res.maps[1.0]
    assert np.all(np.isfinite(m)), "convolution of finite input near 1e308 overflowed"
    assert np.allclose(m, 1e308, rtol=1e-9)  # the normalised lobe average of a constant map is the constant


@pytest.mark.parametrize("entry", ["check_radiance", "median_cut", "convolve", "write_envmap"])
def test_complex_input_is_refused(entry, tmp_path):
    from ibl_ref.groundtruth.convolve import convolve
    from ibl_ref.environment.radiance_policy import check_radiance

    z = np.ones((6, 4, 4, 3), dtype=complex) * (1 + 1e-3j)
    call = {"check_radiance": lambda: check_radiance(z), "median_cut": lambda: median_cut(z, 6),
            "convolve": lambda: convolve(z, [1.0]), "write_envmap": lambda: write_envmap(tmp_path / "z.exr", z)}[entry]
    try:
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            call()
    except IBLError:
        assert not (tmp_path / "z.exr").exists()
        return
    pytest.fail(f"complex radiance accepted by {entry}")


# ------------------------------------------------------------------------------------------------
# output mechanism
# ------------------------------------------------------------------------------------------------
WRITERS = {
    "write_json": lambda p: atomic.write_json(p, {"a": 1}),
    "write_csv": lambda p: atomic.write_csv(p, [{"x_m": 1}]),
    "write_envmap": lambda p: write_envmap(p, af.good_cube(), layout="cube"),
    "write_hdr": lambda p: __import__("ibl_ref.environment.hdr_io", fromlist=["write_hdr"]).write_hdr(p, np.ones((4, 8, 3))),
}


@pytest.mark.parametrize("writer", sorted(WRITERS))
@pytest.mark.parametrize("target", ["fifo", "folder", "link_to_dev_null", "link_to_fifo", "symlink_loop"])
def test_special_targets_are_refused(writer, target, tmp_path):
    p = af.make_special(target, tmp_path / "target.out")
    before = sorted(x.name for x in tmp_path.iterdir())
    with pytest.raises(atomic.OutputError, match="target.out: (is a|symlink loop)") as ei:
        WRITERS[writer](p)
    assert "target.out" in str(ei.value) and "\n" not in str(ei.value)
    assert sorted(x.name for x in tmp_path.iterdir()) == before  # nothing created, nothing replaced
    if target == "fifo":
        assert os.path.exists(p) and not p.is_file() and not p.is_symlink()
    if target == "link_to_dev_null":
        assert p.is_symlink() and os.readlink(p) == "/dev/null"


@pytest.mark.parametrize("writer", sorted(WRITERS))
def test_dev_full_is_refused_and_untouched(writer):
    st = os.stat("/dev/full")
    with pytest.raises(atomic.OutputError, match="character device"):
        WRITERS[writer]("/dev/full")
    st2 = os.stat("/dev/full")
    assert (st.st_mode, st.st_rdev) == (st2.st_mode, st2.st_rdev)
    assert not [n for n in os.listdir("/dev") if atomic.TEMP_TAG in n]


@pytest.mark.parametrize("writer", sorted(WRITERS))
@pytest.mark.parametrize("dangling", [False, True])
def test_symlink_is_written_through(writer, dangling, tmp_path):
    real = tmp_path / "real" / "data.out"
    real.parent.mkdir()
    if not dangling:
        real.write_bytes(b"old")
    link = tmp_path / "link.out"
    link.symlink_to(real)
    WRITERS[writer](link)
    assert link.is_symlink() and Path(os.readlink(link)) == real  # the link is kept
    assert real.is_file() and real.read_bytes() != b"old"  # its target was replaced
    _no_temp_left(tmp_path)
    _no_temp_left(real.parent)


@pytest.mark.parametrize("writer", sorted(WRITERS))
def test_under_a_file_is_a_clear_error(writer, tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(atomic.OutputError, match="is a file, not a folder"):
        WRITERS[writer](tmp_path / "file" / "sub" / "out.dat")
    assert (tmp_path / "file").read_text() == "x"


@pytest.mark.parametrize("writer", sorted(WRITERS))
def test_full_disk_keeps_the_old_file(writer, tmp_path, monkeypatch):
    p = tmp_path / "out.dat"
    p.write_bytes(b"previous version")
    af.inject_enospc(monkeypatch, 1)
    with pytest.raises(atomic.OutputError, match="No space left"):
        WRITERS[writer](p)
    assert p.read_bytes() == b"previous version"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["out.dat"]


@pytest.mark.parametrize("writer", sorted(WRITERS))
def test_read_only_file_system_is_a_clear_error(writer, tmp_path, monkeypatch):
    af.inject_read_only(monkeypatch)
    with pytest.raises(atomic.OutputError, match="Read-only file system"):
        WRITERS[writer](tmp_path / "out.dat")
    assert list(tmp_path.iterdir()) == []


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_leftovers_of_a_killed_run_are_cleaned_live_ones_kept(tmp_path):
    dead, live = _dead_pid(), os.getppid()
    stale_file = tmp_path / f".x.json{atomic.TEMP_TAG}{dead}-0badf00d.json"
    stale_dir = tmp_path / f".x.json{atomic.TEMP_TAG}{dead}-0badf00e"
    live_file = tmp_path / f".x.json{atomic.TEMP_TAG}{live}-0badf00f.json"
    other = tmp_path / f".y.json{atomic.TEMP_TAG}{dead}-0badf010.json"  # another target's: not ours to clean
    stale_file.write_bytes(b"x" * 1000)
    stale_dir.mkdir()
    (stale_dir / "pem_000.exr").write_bytes(b"partial")
    live_file.write_bytes(b"in progress")
    other.write_bytes(b"y")
    atomic.write_json(tmp_path / "x.json", {"ok": True})
    assert not stale_file.exists() and not stale_dir.exists()
    assert live_file.exists() and other.exists()


def test_killed_writer_leaves_a_recognisable_temp_that_the_next_write_removes(tmp_path):
    # a child process is SIGKILLed inside the atomic block; the temp file it leaves carries its PID
    code = ("import os, sys; sys.path.insert(0, %r)\n"
            "from ibl_ref import atomic\n"
            "with atomic.atomic_write(%r) as fh:\n"
            "    fh.write('partial'); fh.flush(); os.kill(os.getpid(), 9)\n") % (
        str(Path(atomic.__file__).parent.parent), str(tmp_path / "r.json"))
    subprocess.run([sys.executable, "-c", code], check=False)
    left = [p for p in tmp_path.iterdir()]
    assert len(left) == 1 and left[0].name.startswith(f".r.json{atomic.TEMP_TAG}")
    assert not (tmp_path / "r.json").exists()
    atomic.write_json(tmp_path / "r.json", {"v": 1})
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]


def _outset_run(folder: Path, names, content: bytes, fail_at=None, monkeypatch=None):
    if fail_at is not None:
        af.inject_enospc(monkeypatch, fail_at)
    with atomic.OutputSet(folder / "manifest.json", owned_key="files") as outs:
        for n in names:
            with atomic.atomic_write(outs.path(folder / n), "wb") as fh:
                fh.write(content)
        outs.commit({"files": list(names)})
    return outs


@pytest.mark.parametrize("fail_at", [1, 2, 3, 4])
def test_output_set_full_disk_at_nth_file_keeps_the_old_set(tmp_path, monkeypatch, fail_at):
    names = ["a_s1.exr", "a_s4.exr", "a_s16.exr"]
    _outset_run(tmp_path, names, b"old")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    with pytest.raises(atomic.OutputError, match="No space left"):
        _outset_run(tmp_path, names, b"new", fail_at=fail_at, monkeypatch=monkeypatch)  # 4 = the manifest
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_output_set_removes_stale_files_it_owned_only(tmp_path):
    _outset_run(tmp_path, [f"pem_{i:03d}.exr" for i in range(12)], b"12 lights")
    (tmp_path / "notes.txt").write_text("user file")
    outs = _outset_run(tmp_path, [f"pem_{i:03d}.exr" for i in range(6)], b"6 lights")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [f"pem_{i:03d}.exr" for i in range(6)] + ["manifest.json", "notes.txt"])
    assert len(outs.removed_stale) == 6
    assert json.loads((tmp_path / "manifest.json").read_text())["files"][-1] == "pem_005.exr"


def test_output_set_ignores_a_tampered_manifest(tmp_path):
    outside = tmp_path / "keep.txt"
    outside.write_text("precious")
    sub = tmp_path / "out"
    sub.mkdir()
    (sub / "manifest.json").write_text(json.dumps({atomic.MANIFEST_MARKER: 1,
                                                   "files": [str(outside), "../keep.txt", "..", ""]}))
    _outset_run(sub, ["x.exr"], b"x")
    assert outside.read_text() == "precious"  # only base names inside the manifest's folder are owned


def test_output_set_exception_in_block_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError, match="^boom$"):
        with atomic.OutputSet(tmp_path / "m.json") as outs:
            with atomic.atomic_write(outs.path(tmp_path / "f.exr"), "wb") as fh:
                fh.write(b"x")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("how", ["same_path", "symlink", "hardlink", "relative"])
def test_refuse_overwriting_inputs(tmp_path, how, monkeypatch):
    src = tmp_path / "env.exr"
    src.write_bytes(b"input")
    out = {"same_path": src, "symlink": tmp_path / "l.exr", "hardlink": tmp_path / "h.exr",
           "relative": Path("env.exr")}[how]
    if how == "symlink":
        out.symlink_to(src)
    elif how == "hardlink":
        os.link(src, out)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(atomic.OutputError, match="same file as the input --env"):
        atomic.refuse_overwriting_inputs({"--env": src}, {"--out": out})
    atomic.refuse_overwriting_inputs({"--env": src}, {"--out": tmp_path / "other.exr"})  # no error


def test_json_with_nan_is_an_output_error_naming_the_file(tmp_path):
    with pytest.raises(atomic.OutputError, match=r"x\.json: cannot write NaN"):
        atomic.write_json(tmp_path / "x.json", {"v": float("inf")})
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------------
# byte-level fuzzing of the readers (seeded): an IBLError or a finite, non-negative cube, nothing else
# ------------------------------------------------------------------------------------------------
def _mutations(base: bytes, seed: int, count: int):
    rng = np.random.default_rng(seed)
    for _ in range(count):
        b = bytearray(base)
        for _ in range(int(rng.integers(1, 4))):  # 1-3 random bytes overwritten
            b[int(rng.integers(0, len(b)))] = int(rng.integers(0, 256))
        if rng.random() < 0.3:  # and sometimes truncated as well
            b = b[: int(rng.integers(0, len(b)))]
        yield bytes(b)


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("fmt", ["exr", "hdr"])
def test_fuzzed_files_give_an_iblerror_or_a_valid_cube(fmt, seed, tmp_path, capfd):
    from ibl_ref.environment.hdr_io import write_hdr

    if fmt == "exr":
        base = af.write_good_exr(tmp_path / "g.exr").read_bytes()
    else:
        write_hdr(tmp_path / "g.hdr", np.random.default_rng(0).random((8, 16, 3)) + 0.1)
        base = (tmp_path / "g.hdr").read_bytes()
    p = tmp_path / f"fuzz.{fmt}"
    for data in _mutations(base, seed, 25):
        p.write_bytes(data)
        try:
            cube = load_cube(p)
        except IBLError as exc:
            assert "\n" not in str(exc) and "fuzz" in str(exc)
            continue
        assert cube.ndim == 4 and cube.shape[0] == 6 and np.all(np.isfinite(cube)) and np.all(cube >= 0)
    out, err = capfd.readouterr()
    assert out + err == ""  # nothing printed by the OpenEXR library either


@pytest.mark.parametrize("chans", [("Y",), ("R", "G", "B"), ("R", "G", "B", "A"), ("A", "B", "G", "R", "Z", "u", "v")])
def test_header_scan_counts_channels_like_the_binding(chans, tmp_path):
    # the memory check before decoding sizes the data window by the channel count of the chlist attribute;
    # its binary fields contain NUL bytes, so counting NULs overestimated a 3-channel 16K probe as 63 GiB.
    # Reference: the channels the OpenEXR binding was asked to write
    import OpenEXR

    from ibl_ref.environment import exr_io

    p = tmp_path / "c.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {c: np.ones((4, 8), np.float32) for c in chans}).write(str(p))
    parts = exr_io._scan_headers(p, p.read_bytes())
    assert parts[0]["n_channels"] == len(chans)


def test_median_cut_refuses_a_working_set_beyond_memory(monkeypatch):
    # the cut needs ~300 bytes per texel (measured, median_cut.WORKING_BYTES_PER_TEXEL): with a 1 MB limit
    # a 32²-face cube (6144 texels, ~1.8 MB) is refused up front with the size named, a 8² one still runs
    from ibl_ref.knuth2014 import median_cut as mc

    monkeypatch.setenv("IBL_REF_MAX_BYTES", str(10**6))
    with pytest.raises(IBLError, match="32x32-face"):
        mc.median_cut(np.ones((6, 32, 32, 3)), 6)
    assert len(mc.median_cut(np.ones((6, 8, 8, 3)), 6)) == 6


# ------------------------------------------------------------------------------------------------
# every user error is an IBLError; values a format cannot hold; one writer and one reader
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("call,fragment", [
    (lambda: __import__("ibl_ref.environment.resample", fromlist=["x"]).latlong_to_cube(np.zeros((0, 0, 3)), 8),
     "non-empty"),
    (lambda: __import__("ibl_ref.environment.resample", fromlist=["x"]).latlong_to_latlong(np.ones((4, 8, 3)), 0),
     "positive integer"),
    (lambda: __import__("ibl_ref.environment.envmap", fromlist=["x"]).cube_solid_angles(True), "positive integer"),
    (lambda: __import__("ibl_ref.environment.envmap", fromlist=["x"]).cube_solid_angles(0), "positive integer"),
    (lambda: __import__("ibl_ref.environment.envmap", fromlist=["x"]).texel_directions(2.5), "positive integer"),
    (lambda: __import__("ibl_ref.environment.envmap", fromlist=["x"]).texel_solid_angles(10**9), "memory"),
    (lambda: __import__("ibl_ref.environment.envmap", fromlist=["x"]).mip_levels(6), "power-of-two"),
    (lambda: __import__("ibl_ref.environment.envmap", fromlist=["x"]).face_uv_to_direction(7, 0, 0), "0..5"),
    (lambda: __import__("ibl_ref.environment.envmap", fromlist=["x"]).direction_to_texel(np.zeros(3), 4),
     "zero-length"),
    (lambda: __import__("ibl_ref.environment.sampling", fromlist=["x"]).sample_nearest(
        np.ones((6, 4, 4, 3)), np.full((2, 3), np.nan)), "NaN"),
    (lambda: __import__("ibl_ref.environment.sampling", fromlist=["x"]).sample_bilinear(np.ones((6, 4, 4, 3)), "abc"),
     "numeric"),
    (lambda: __import__("ibl_ref.environment.sampling", fromlist=["x"]).pad_faces(np.ones((6, 4, 4, 3)), 9),
     "padding width"),
    (lambda: __import__("ibl_ref.environment.resample", fromlist=["x"]).latlong_to_cube(np.ones((4, 8, 3)), 2,
                                                                                      method="nope"), "nope"),
    (lambda: load_cube(3), "file name"),
    (lambda: load_cube(None), "file name"),
    (lambda: __import__("ibl_ref.environment.probe_files", fromlist=["x"]).sky_sun_latlong(3), "even"),
])
def test_api_misuse_is_an_iblerror(call, fragment):
    with pytest.raises(IBLError, match=fragment):
        call()


def test_no_bare_value_error_is_raised_by_the_package():
    # a source-level check of the rule "every user error derives from IBLError": no `raise ValueError(` /
    # `raise TypeError(` in the package outside the internal helpers that are caught where they are raised
    root = Path(__file__).resolve().parent.parent / "ibl_ref"
    allowed = {"experiments/__init__.py"}  # its parse helper raises ValueError where it is caught
    found = []
    for f in root.rglob("*.py"):
        rel = f.relative_to(root).as_posix()
        for i, line in enumerate(f.read_text().splitlines(), 1):
            if ("raise ValueError(" in line or "raise TypeError(" in line) and rel not in allowed:
                if "not JSON serialisable" not in line:  # json.dumps' default hook, turned into OutputError
                    found.append(f"{rel}:{i}")
    assert found == [], found


def test_load_cube_accepts_bytes_and_pathlike_names(tmp_path):
    p = af.non_utf8_name(tmp_path)
    want = load_cube(p)
    np.testing.assert_array_equal(load_cube(os.fsencode(p)), want)

    class P:
        def __fspath__(self):
            return os.fsencode(p)

    np.testing.assert_array_equal(load_cube(P()), want)


def test_load_cube_warns_once_when_it_repairs_radiance(tmp_path):
    from ibl_ref.errors import RadianceWarning

    img = np.ones((8, 16, 3), np.float32)
    img[0, 0, 0] = -1e-7  # a DWAB-like negative: clamped by negative='auto'
    p = af._exr_raw(tmp_path / "neg.exr", {"R": img[..., 0], "G": img[..., 1], "B": img[..., 2]})
    with pytest.warns(RadianceWarning, match="clamped 1 negative value") as rec:
        cube, rep = load_cube(p, return_report=True)
    assert len([w for w in rec if issubclass(w.category, RadianceWarning)]) == 1
    assert cube.min() >= 0 and rep.n_negative == 1


@pytest.mark.parametrize("writer,value,fragment", [
    ("half", 1e-8, "smallest normal half"),
    ("half", 3e-8, "smallest normal half"),
    ("float", 1e-46, "smallest normal float"),
    ("hdr", 1e-40, "Radiance RGBE"),
])
def test_values_below_a_format_range_are_refused(writer, value, fragment, tmp_path):
    from ibl_ref.environment.hdr_io import write_hdr

    img = np.full((4, 8, 3), value)
    p = tmp_path / ("x.hdr" if writer == "hdr" else "x.exr")
    with pytest.raises(RadianceError, match=fragment) as ei:
        if writer == "hdr":
            write_hdr(p, img)
        else:
            write_envmap(p, img, layout="latlong", pixel_type=writer)
    assert "more than 0.0001" in str(ei.value)  # 3e-8 doubles to 2^-24 in half, the others become 0
    assert list(tmp_path.iterdir()) == []


def test_a_small_loss_below_the_range_warns_with_its_share(tmp_path):
    # lower hemisphere 5.5e-5 (below half's smallest normal 6.1e-5: stored in steps of 2^-24), upper 6e-4: about
    # 8 % of the integral sits in values rounded to ~4e-4 relative, so f_range is between the warning level
    # (1e-7) and the refusal level (1e-4): the file is written, with a warning that gives the share
    from ibl_ref.environment.radiance_policy import range_loss, pixel_solid_angles
    from ibl_ref.errors import FormatRangeWarning

    img = np.full((8, 16, 3), 6e-4)
    img[4:] = 5.5e-5
    f, n_below, n_zero = range_loss(img, img.astype(np.float16), 2.0**-14, pixel_solid_angles(8, 16, "latlong"))
    assert n_below == 4 * 16 * 3 and n_zero == 0 and 1e-7 < f < 1e-4, f
    with pytest.warns(FormatRangeWarning, match=f"change {f:.2e} of the integral"):
        write_envmap(tmp_path / "x.exr", img, layout="latlong", pixel_type="half")
    np.testing.assert_array_equal(read_envmap(tmp_path / "x.exr").data, img.astype(np.float16))


def test_write_exr_writes_views_and_planes_exactly(tmp_path):
    # the binding ignores strides: a transposed view and a list of planes must land in the file as given
    import OpenEXR

    from ibl_ref.environment.exr_io import ExrPart, write_exr

    base = np.arange(2 * 6 * 4, dtype=np.float32).reshape(4, 6, 2).transpose(1, 0, 2)  # (6, 4, 2) view
    img = np.concatenate([base, base[..., :1]], axis=-1)[:, ::-1]  # negative strides too
    write_exr(tmp_path / "v.exr", ExrPart(img, ("R", "G", "B")))
    write_exr(tmp_path / "p.exr", ExrPart([img[..., i] for i in range(3)], ("R", "G", "B")), compression="piz")
    for name in ("v.exr", "p.exr"):
        with OpenEXR.File(str(tmp_path / name), separate_channels=True) as f:
            ch = f.parts[0].channels
            got = np.stack([ch[c].pixels for c in "RGB"], axis=-1)
        np.testing.assert_array_equal(got, img)


def test_read_exr_all_channels_keeps_every_channel(tmp_path):
    from ibl_ref.environment.exr_io import read_exr

    z = np.full((6, 1), 7.0, np.float32)
    p = af._exr_raw(tmp_path / "z.exr", {"R": z, "G": z, "B": z, "Z": z * 2})
    ex = read_exr(p, channels="all")
    assert ex.channels == ("R", "G", "B", "Z") and ex.n_colour == 3 and ex.pixels[0, 0, 3] == 14.0
    with pytest.raises(IBLError, match="missing R/G/B"):
        read_exr(af._exr_raw(tmp_path / "zonly.exr", {"Z": z}))


@pytest.mark.parametrize("stops", [1e9, -1e9, 1100, 1023.5, -1074])
def test_tone_mapping_never_overflows(stops):
    from ibl_ref.rendering import tonemap as tm

    x = np.array([0.0, 5e-324, 1e-300, 1.0, 1e300, 1.7e308])
    for op in ("reinhard", "clip"):
        y = tm.exposure_srgb(x, stops, op)
        assert np.all(np.isfinite(y)) and y.min() >= 0 and y.max() <= 1 and y[0] == 0
    assert np.all(np.diff(tm.exposure_srgb(x, stops)) >= 0)  # monotone


def test_auto_exposure_of_subnormal_radiance_is_finite():
    from ibl_ref.rendering import tonemap as tm

    s = tm.auto_exposure(np.full((2, 2, 3), 5e-324))
    assert np.isfinite(s) and s > 1000
    assert np.all(np.isfinite(tm.exposure_srgb(np.full((2, 2, 3), 5e-324), s)))


def test_side_file_rule(tmp_path):
    side = tmp_path / "r.json"
    atomic.check_side_files(side, [tmp_path / "r_s4.exr"])  # nothing there: fine
    side.write_text("[1, 2]")
    with pytest.raises(atomic.OutputError, match="not written by ibl_ref"):
        atomic.check_side_files(side)
    side.write_text(json.dumps({"outputs": ["r_s4.exr"]}))  # a user's JSON of the same shape, without the marker
    with pytest.raises(atomic.OutputError, match="not written by ibl_ref"):
        atomic.check_side_files(side)
    side.write_text(json.dumps({atomic.MANIFEST_MARKER: 1, "outputs": ["r_s4.exr"]}))
    (tmp_path / "r_s4.exr").write_bytes(b"x")
    (tmp_path / "r_s8.exr").write_bytes(b"y")
    atomic.check_side_files(side, [tmp_path / "r_s4.exr"])  # listed by the previous run: ours
    with pytest.raises(atomic.OutputError, match="r_s8.exr"):
        atomic.check_side_files(side, [tmp_path / "r_s8.exr"])


@pytest.fixture
def sigint_default():
    """SIGINT raises KeyboardInterrupt during the test, as in an interactive session, whatever the test process
    inherited (a test run started as a background job of a script has SIGINT ignored); restored afterwards."""
    import signal

    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


def test_an_inherited_ignored_sigint_stays_ignored():
    # POSIX: a job started with SIGINT ignored is not meant to stop on Ctrl-C; the CLI's handler leaves it so
    import signal

    from ibl_ref.cli import interrupts

    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with interrupts.handling():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGINT)  # ignored: nothing is raised
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN and not interrupts.interrupted()
    finally:
        signal.signal(signal.SIGINT, old)


def test_critical_section_holds_ctrl_c_until_it_ends(sigint_default):
    import signal

    done = []
    with pytest.raises(KeyboardInterrupt, match="^$"):  # a signal's interrupt carries no message
        with atomic.critical_section():
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(100):  # the signal is handled between bytecodes: give it many chances
                done.append(1)
        done.append("after")  # never reached: the interrupt is delivered as the block ends
    assert done == [1] * 100


def test_interrupt_during_an_import_is_deferred_not_swallowed(tmp_path, monkeypatch, sigint_default):
    # a module that, like trimesh, guards its imports with `except BaseException`: a Ctrl-C inside is held until
    # the import is done, then raised (the guard never sees it)
    import signal
    import time

    from ibl_ref.cli import interrupts

    (tmp_path / "guarded_mod.py").write_text(
        "import os, signal, time\nswallowed = False\ntry:\n    os.kill(os.getpid(), signal.SIGINT)\n"
        "    time.sleep(0.05)\n    x = sum(range(1000))\nexcept BaseException:\n    swallowed = True\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(KeyboardInterrupt, match="^$"):  # a signal's interrupt carries no message
        with interrupts.handling():
            import guarded_mod  # noqa: F401
            time.sleep(0.5)  # the deferred interrupt arrives here
    assert sys.modules["guarded_mod"].swallowed is False and interrupts.interrupted()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_resend_left_from_one_command_does_not_interrupt_the_next(sigint_default):
    # in one process (a notebook, a test session) a Ctrl-C of one command arms its re-send timer; a command started
    # right after must not receive that leftover interrupt
    import signal
    import time

    from ibl_ref.cli import interrupts

    with pytest.raises(KeyboardInterrupt, match="^$"):
        with interrupts.handling():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
    with interrupts.handling():
        time.sleep(2 * interrupts._RESEND_S)  # the first block's timer fires in here and must do nothing
    assert not interrupts.interrupted()
