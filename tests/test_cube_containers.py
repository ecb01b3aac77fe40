"""KTX 1 and DDS cube-map chains (ibl_ref/environment/cube_containers.py).

The face order and orientation are checked against files the tools wrote themselves: a pattern whose texels hold
their own direction, (R, G, B) = 1.5 + (x, y, z), run through Filament's ``cmgen --format=ktx`` (with and without its
mirroring) and through cmft ``--filter none`` (DDS and KTX outputs in half and float, from a DDS and from a cross
input), must read back as the lab's cube of the pattern at level 0, and every further level as cmgen's own OpenEXR
levels (cmgen) or the 2 × 2 average of the level above (cmft's MIP chain); the other way round, cmft reads the lab's
files back as the pattern.  The packed-float decoder is checked against NumPy's half floats (an 11-bit float is a
half without its 4 lowest mantissa bits); the writers by round trips; bad files and bad chains get one line.

The tests that run the programs use the ``cmgen`` and ``cmft`` fixtures (skipped with the reason where a program is
missing; CI has both).  Faces of 16²: every program run takes tens of milliseconds.
"""

from __future__ import annotations

import math
import struct
import subprocess

import numpy as np
import pytest

from ibl_ref.environment import cube_containers as cc
from ibl_ref.environment import envmap
from ibl_ref.environment.hdr_io import read_hdr, write_hdr
from ibl_ref.environment.resample import cross_to_cube, cube_to_cross
from ibl_ref.errors import EnvMapFileError, IBLError, RadianceError, RadianceWarning
from ibl_ref.prefilter.cmft_peer import write_dds_cube
from ibl_ref.prefilter.cmgen_peer import face_check_pattern, read_levels, write_input

N = 16
WRITERS = {"ktx": cc.write_ktx1, "dds": cc.write_dds}
READERS = {"ktx": cc.read_ktx1, "dds": cc.read_dds}


def _one_line(exc):
    msg = str(exc.value)
    assert msg and "\n" not in msg, msg
    return msg


def _box(cube):
    """The 2 × 2 average of a cube (the next MIP level of a box-filtered chain)."""
    m = cube.shape[1] // 2
    return cube.reshape(6, m, 2, m, 2, -1).mean(axis=(2, 4))


def _chain(base):
    """A full box-filtered MIP chain of ``base`` down to 1²."""
    out = [np.asarray(base, dtype=np.float64)]
    while out[-1].shape[1] > 1:
        out.append(_box(out[-1]))
    return out


@pytest.fixture(scope="module")
def pattern():
    return face_check_pattern(N)


def _run(cmd, cwd):
    res = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, errors="replace", timeout=120,
                         cwd=cwd, stdin=subprocess.DEVNULL)
    assert res.returncode == 0, (cmd, res.stdout[-500:], res.stderr[-500:])
    return res


# ---- the packed floats --------------------------------------------------------------------------------------------
def test_r11g11b10_is_a_half_float_without_its_low_mantissa_bits():
    # all 2048 11-bit codes in R and G, all 1024 10-bit codes in B: zero, denormals, normals, Inf and NaN
    eleven = np.arange(2048, dtype=np.uint32)
    ten = np.arange(1024, dtype=np.uint32)
    half = lambda bits, shift: (bits << shift).astype(np.uint16).view(np.float16).astype(np.float64)  # noqa: E731
    got = cc.decode_r11g11b10(eleven | (eleven << 11))
    np.testing.assert_array_equal(got[:, 0], half(eleven, 4))
    np.testing.assert_array_equal(got[:, 1], half(eleven, 4))
    np.testing.assert_array_equal(cc.decode_r11g11b10(ten << 22)[:, 2], half(ten, 5))
    assert cc.decode_r11g11b10(1)[0] == 2.0 ** -20  # the smallest denormal, 2^-14 / 64
    assert np.isinf(cc.decode_r11g11b10(31 << 6)[0]) and np.isnan(cc.decode_r11g11b10(31 << 6 | 1)[0])


def test_rgb9e5_is_mantissa_times_a_shared_power_of_two():
    rng = np.random.default_rng(5)
    words = rng.integers(0, 2 ** 32, 200, dtype=np.uint64).astype(np.uint32)
    got = cc.decode_rgb9e5(words)
    for w, g in zip(words.tolist(), got):
        e = w >> 27
        want = [math.ldexp(float((w >> s) & 511), e - 24) for s in (0, 9, 18)]
        assert g.tolist() == want


# ---- round trips --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind, dtype, channels", [
    ("ktx", "float32", 4), ("ktx", "float16", 4), ("ktx", "float32", 3), ("ktx", "float16", 3),
    ("dds", "float32", 4), ("dds", "float16", 4),
])
def test_a_chain_round_trips_through_its_texel_type(tmp_path, kind, dtype, channels):
    rng = np.random.default_rng(1)
    chain = _chain(rng.uniform(0.01, 50.0, (6, N, N, 3)))  # 16² … 1²: the 1² RGB16F level has padded rows
    kw = {"channels": channels} if kind == "ktx" else {}
    path = WRITERS[kind](tmp_path / f"c.{kind}", chain, dtype=dtype, **kw)
    got = READERS[kind](path)
    assert [g.shape for g in got] == [c.shape for c in chain]
    for g, c in zip(got, chain):
        assert g.dtype == np.float64
        np.testing.assert_array_equal(g, c.astype(dtype).astype(np.float64))  # exact, or the nearest half
    assert [p.name for p in tmp_path.iterdir()] == [f"c.{kind}"]  # no temporary file left


@pytest.mark.parametrize("kind", ["ktx", "dds"])
def test_a_constant_environment_stays_constant_and_one_channel_becomes_grey(tmp_path, kind):
    chain = [np.full((6, n, n), 2.5) for n in (8, 4, 2)]  # (6, N, N): one channel
    got = READERS[kind](WRITERS[kind](tmp_path / f"k.{kind}", chain))
    assert [g.shape for g in got] == [(6, n, n, 3) for n in (8, 4, 2)]
    assert all(np.all(g == 2.5) for g in got)


def _ktx_to_big_endian(data: bytes, unit: int) -> bytes:
    """A little-endian KTX 1 file of the specification's layout (no key/value data) in big-endian byte order."""
    head = struct.unpack_from("<13I", data, 12)
    assert head[12] == 0
    out = bytearray(data[:12]) + struct.pack(">13I", *head)
    pos = 64
    while pos < len(data):
        size = struct.unpack_from("<I", data, pos)[0]
        words = np.frombuffer(data, f"<u{unit}", 6 * size // unit, pos + 4)
        out += struct.pack(">I", size) + words.astype(f">u{unit}").tobytes()
        pos += 4 + 6 * size
    return bytes(out)


@pytest.mark.parametrize("dtype", ["float16", "float32"])
def test_a_big_endian_ktx_reads_as_the_little_endian_one(tmp_path, pattern, dtype):
    le = cc.write_ktx1(tmp_path / "le.ktx", _chain(pattern)[:3], dtype=dtype)
    be = tmp_path / "be.ktx"
    be.write_bytes(_ktx_to_big_endian(le.read_bytes(), 2 if dtype == "float16" else 4))
    assert be.read_bytes()[12:16] == b"\x04\x03\x02\x01"
    for a, b in zip(cc.read_ktx1(le), cc.read_ktx1(be)):
        np.testing.assert_array_equal(a, b)


def test_key_value_data_is_skipped(tmp_path, pattern):
    data = cc.write_ktx1(tmp_path / "a.ktx", [pattern]).read_bytes()
    pair = b"KTXorientation\0S=r,T=d\0"
    kv = struct.pack("<I", len(pair)) + pair + b"\0" * (-len(pair) % 4)
    head = bytearray(data[:64])
    struct.pack_into("<I", head, 60, len(kv))
    (tmp_path / "b.ktx").write_bytes(bytes(head) + kv + data[64:])
    np.testing.assert_array_equal(cc.read_ktx1(tmp_path / "b.ktx")[0], cc.read_ktx1(tmp_path / "a.ktx")[0])


def _ktx_bytes(internal, gl_type, gl_format, n, levels, type_size=1):
    """A hand-made little-endian KTX 1 cube map: ``levels`` are (imageSize, bytes of the six faces with padding)."""
    head = struct.pack("<13I", 0x04030201, gl_type, type_size, gl_format, internal, gl_format, n, n, 0, 0, 6,
                       len(levels), 0)
    body = b"".join(struct.pack("<I", size) + faces for size, faces in levels)
    return b"\xabKTX 11\xbb\r\n\x1a\n" + head + body


def _dds_bytes(n, n_levels, payload, *, dxgi=None, fourcc=113, caps2=0xFE00, misc=0x4, array=1, dim=3):
    """A hand-made DDS (legacy FourCC or, with ``dxgi``, the DX10 header) with ``payload`` after the header."""
    code = b"DX10" if dxgi is not None else struct.pack("<I", fourcc)
    head = b"DDS " + struct.pack("<7I44x", 124, 0x21007, n, n, 0, 0, n_levels)
    head += struct.pack("<2I4s5I", 32, 0x4, code, 0, 0, 0, 0, 0) + struct.pack("<5I", 0x401008, caps2, 0, 0, 0)
    if dxgi is not None:
        head += struct.pack("<5I", dxgi, dim, misc, array, 0)
    return head + payload


def test_packed_and_rgb_float_formats_in_both_containers(tmp_path):
    # one 1² cube per format, faces f = 0..5 holding distinct values: decoded, and re-oriented (a 1² face is its
    # own flip), in face order
    one = 15 << 6  # 1.0 as an 11-bit float
    r11 = [(one + f) | (one << 11) | ((15 << 5) << 22) for f in range(6)]  # R = 1 + f/64, G = B = 1
    e5 = [16 << 27 | 128 << 9 | (256 + f) for f in range(6)]  # R = (256 + f)/256, G = 0.5, B = 0
    want_r11 = [[1 + f / 64, 1.0, 1.0] for f in range(6)]
    want_e5 = [[1 + f / 256, 0.5, 0.0] for f in range(6)]
    words = lambda ws: struct.pack("<6I", *ws)  # noqa: E731
    cases = {
        "r11.ktx": (_ktx_bytes(0x8C3A, 0x8C3B, 0x1907, 1, [(4, words(r11))], 4), want_r11),
        "e5.ktx": (_ktx_bytes(0x8C3D, 0x8C3E, 0x1907, 1, [(4, words(e5))], 4), want_e5),
        "r11.dds": (_dds_bytes(1, 1, words(r11), dxgi=26), want_r11),
        "e5.dds": (_dds_bytes(1, 1, words(e5), dxgi=67), want_e5),
        "rgb32.dds": (_dds_bytes(1, 1, np.array(want_e5, "<f4").tobytes(), dxgi=6), want_e5),
    }
    for name, (data, want) in cases.items():
        (tmp_path / name).write_bytes(data)
        got = cc.read_cube_chain(tmp_path / name)
        assert len(got) == 1 and got[0].shape == (6, 1, 1, 3), name
        np.testing.assert_array_equal(got[0][:, 0, 0], want, err_msg=name)


def test_rgb16f_1x1_faces_in_all_three_row_layouts(tmp_path):
    # the specification pads a 6-byte row to 8 and counts it in imageSize; cmft pads the row but gives imageSize 6
    # (and pads the face again from it); other writers pad neither: each file holds faces of 1 + f
    vals = [np.array([1 + f, 2, 3], "<f2").tobytes() for f in range(6)]
    layouts = {"spec": (8, b"".join(v + b"\0\0" for v in vals)),
               "cmft": (6, b"".join(v + b"\0" * 4 for v in vals)),
               "unpadded": (6, b"".join(v + b"\0\0" for v in vals))}
    for name, (size, faces) in layouts.items():
        p = tmp_path / f"{name}.ktx"
        p.write_bytes(_ktx_bytes(0x881B, 0x140B, 0x1907, 1, [(size, faces)], 2))
        np.testing.assert_array_equal(cc.read_ktx1(p)[0][:, 0, 0, 0], np.arange(1, 7), err_msg=name)
    # the lab writes the specification's layout
    data = cc.write_ktx1(tmp_path / "lab.ktx", [np.ones((6, 1, 1, 3))], channels=3).read_bytes()
    assert struct.unpack_from("<I", data, 64)[0] == 8 and len(data) == 64 + 4 + 6 * 8


def test_read_cube_chain_goes_by_content(tmp_path, pattern):
    k = cc.write_ktx1(tmp_path / "really_a_ktx.dds", [pattern], dtype="float32")
    np.testing.assert_array_equal(cc.read_cube_chain(k)[0], pattern.astype(np.float32))
    (tmp_path / "x.ktx").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    with pytest.raises(EnvMapFileError) as exc:
        cc.read_cube_chain(tmp_path / "x.ktx")
    assert "neither a KTX 1 nor a DDS" in _one_line(exc)


# ---- against the tools' own files ---------------------------------------------------------------------------------
def _cmgen_ktx(cmgen, tmp_path, pattern, name, *flags):
    """cmgen's KTX of the pattern cross (--size 16, 64 samples, deploy folder: its key/value data included)."""
    inp = tmp_path / "pattern.exr"
    if not inp.exists():
        write_input(inp, pattern)
    _run([cmgen, "--format=ktx", f"--size={N}", "--ibl-samples=64", *flags, "-x", tmp_path / name, inp], tmp_path)
    (ktx,) = (tmp_path / name).glob("*_ibl.ktx")
    head = ktx.read_bytes()
    assert struct.unpack_from("<3I", head, 24) == (0x1907, 0x8C3A, 0x8C3A)  # glFormat RGB, R11F_G11F_B10F
    assert struct.unpack_from("<I", head, 60)[0] > 0  # key/value data (cmgen's spherical harmonics) to skip
    return cc.read_ktx1(ktx)


def test_cmgen_ktx_reads_as_the_pattern_and_as_cmgens_exr_levels(cmgen, tmp_path, pattern):
    # --no-mirror, as the lab runs cmgen for its OpenEXR levels (cmgen_peer): level 0 is the input, rounded to
    # cmgen's packed floats (6-bit mantissas in R and G, 5-bit in B: half an ulp is 2^-7 and 2^-6 of the value)
    got = _cmgen_ktx(cmgen, tmp_path, pattern, "plain", "--no-mirror")
    assert [g.shape[1] for g in got] == [16, 8, 4, 2, 1]
    rnd = np.array([2.0 ** -7, 2.0 ** -7, 2.0 ** -6])
    assert np.all(np.abs(got[0] - pattern) <= rnd * pattern)
    raw = envmap.convert_convention(got[0], "openexr", "opengl")  # read without the re-orientation
    assert np.max(np.abs(raw - pattern)) > 1.0
    # every level against cmgen's own OpenEXR levels of the same input (half floats, read by cmgen_peer's reader)
    _run([cmgen, "--format=exr", f"--size={N}", "--ibl-samples=64", "--no-mirror", f"--ibl-ld={tmp_path / 'exr'}",
          tmp_path / "pattern.exr"], tmp_path)
    exr = read_levels(tmp_path / "exr" / "pattern", 5, N)
    for k, (a, b) in enumerate(zip(got, exr)):
        assert np.all(np.abs(a - b) <= (rnd + 2.0 ** -11) * b), k
    # cmgen's default mirroring: level 0 is the pattern at (-x, y, z), so the KTX holds the same convention and
    # the mirror is cmgen's option, not the container's
    mirrored = _cmgen_ktx(cmgen, tmp_path, pattern, "mirrored")[0]
    flipped = 1.5 + (pattern - 1.5) * np.array([-1.0, 1.0, 1.0])
    assert np.all(np.abs(mirrored - flipped) <= rnd * flipped)


_CMFT_OUTPUTS = {"dds16": "dds,rgba16f", "dds32": "dds,rgba32f", "ktx16": "ktx,rgba16f", "ktx3h": "ktx,rgb16f",
                 "ktx32": "ktx,rgba32f", "ktx3f": "ktx,rgb32f", "dds8": "dds,bgra8"}


@pytest.mark.parametrize("source", ["dds", "hcross"])
def test_cmft_files_read_as_the_pattern_with_cmfts_mip_chain(cmft, tmp_path, pattern, source):
    # cmft --filter none re-encodes its input and builds the MIP chain by 2 x 2 averages: level 0 is the pattern
    # (exactly in float32 from the float32 DDS input; the cross goes through RGBE, 8-bit mantissas), level k the
    # average of level k - 1, in every container and texel type cmft writes
    if source == "dds":
        inp, ref, rgbe = tmp_path / "in.dds", pattern, 0.0
        write_dds_cube(inp, envmap.convert_convention(pattern, "openexr", "opengl"))
    else:  # RGBE: cmft decodes m·2^(E-136), the lab (m + ½)·2^(E-136): half a step, ≤ 1/128 of the texel's maximum
        inp, rgbe = tmp_path / "in.hdr", 2.0 ** -7
        write_hdr(inp, cube_to_cross(pattern, "hcross"))
        ref = cross_to_cube(read_hdr(inp), "hcross")  # the pattern as RGBE holds it
    cmd = [cmft, "--input", inp, "--filter", "none", "--generateMipChain", "true", "--silent",
           "--outputNum", len(_CMFT_OUTPUTS)]
    for k, (name, params) in enumerate(_CMFT_OUTPUTS.items()):
        cmd += [f"--output{k}", tmp_path / name, f"--output{k}params", params + ",cubemap"]
    _run(cmd, tmp_path)
    for name in _CMFT_OUTPUTS:
        path = tmp_path / f"{name}.{name[:3]}"
        if name == "dds8":  # 8-bit display texels are not radiance
            with pytest.raises(EnvMapFileError) as exc:
                cc.read_dds(path)
            assert "integer" in _one_line(exc)
            continue
        got = cc.read_cube_chain(path)
        assert [g.shape for g in got] == [(6, n, n, 3) for n in (16, 8, 4, 2, 1)], name
        half = "16" in name or "3h" in name
        tol = (2.0 ** -11 if half else 2.0 ** -24) * ref + rgbe * ref.max(axis=-1, keepdims=True)
        assert np.all(np.abs(got[0] - ref) <= tol), name
        raw = envmap.convert_convention(got[0], "openexr", "opengl")
        assert np.max(np.abs(raw - ref)) > 1.0, name
        for k in range(1, len(got)):
            np.testing.assert_allclose(got[k], _box(got[k - 1]), rtol=2.0 ** -10 if half else 1e-6,
                                       err_msg=f"{name} level {k}")


def test_cmft_reads_the_labs_files_as_the_pattern(cmft, tmp_path, pattern):
    # the writers against cmft's reader: cmft re-encodes each file as horizontal crosses in RGBE (one file per
    # level, NAME_<level>_<W>x<H>.hdr), read with the lab's cross reader
    chain = _chain(pattern)[:2]
    files = {"d16": cc.write_dds(tmp_path / "d16.dds", chain), "d32": cc.write_dds(tmp_path / "d32.dds", chain,
                                                                                    dtype="float32"),
             "k16": cc.write_ktx1(tmp_path / "k16.ktx", chain), "k3": cc.write_ktx1(tmp_path / "k3.ktx", chain,
                                                                                      dtype="float32", channels=3)}
    for name, path in files.items():
        _run([cmft, "--input", path, "--filter", "none", "--silent", "--outputNum", 1, "--output0",
              tmp_path / f"back_{name}", "--output0params", "hdr,rgbe,hcross"], tmp_path)
        for k, ref in enumerate(chain):
            n = ref.shape[1]
            got = cross_to_cube(read_hdr(tmp_path / f"back_{name}_{k}_{4 * n}x{3 * n}.hdr"), "hcross")
            # RGBE: cmft's encoding and the lab's decoding (+ ½) are within one step of an 8-bit mantissa of the
            # texel's largest channel M, ≤ M/128 (the faces x-flipped: > 1)
            assert np.all(np.abs(got - ref) <= ref.max(axis=-1, keepdims=True) / 128), (name, k)


# ---- bad files ----------------------------------------------------------------------------------------------------
@pytest.fixture
def files(tmp_path, pattern):
    chain = _chain(pattern)[:3]
    return {"ktx": cc.write_ktx1(tmp_path / "ok.ktx", chain).read_bytes(),
            "dds": cc.write_dds(tmp_path / "ok.dds", chain).read_bytes()}


def _patched(data: bytes, *edits) -> bytes:
    out = bytearray(data)
    for offset, value in edits:
        struct.pack_into("<I", out, offset, value)
    return bytes(out)


_KTX = {"glType": 16, "glFormat": 24, "glInternalFormat": 28, "pixelHeight": 40, "pixelDepth": 44,
        "numberOfArrayElements": 48, "numberOfFaces": 52, "numberOfMipmapLevels": 56}


@pytest.mark.parametrize("kind, edit, words", [
    ("ktx", lambda d: d[:-5], "truncated"),
    ("ktx", lambda d: d + b"\0" * 4, "after the last level"),
    ("ktx", lambda d: d[:40], "truncated KTX header"),
    ("ktx", lambda d: b"\xabKTX 20\xbb\r\n\x1a\n" + d[12:], "KTX 2"),
    ("ktx", lambda d: b"GIF89a" + d[6:], "not a KTX 1 file"),
    ("ktx", lambda d: _patched(d, (12, 0x05060708)), "endianness"),
    ("ktx", lambda d: _patched(d, (_KTX["numberOfFaces"], 1)), "not a cube map"),
    ("ktx", lambda d: _patched(d, (_KTX["numberOfArrayElements"], 2)), "numberOfArrayElements = 2"),
    ("ktx", lambda d: _patched(d, (_KTX["pixelDepth"], 4)), "3-D"),
    ("ktx", lambda d: _patched(d, (_KTX["pixelHeight"], 8)), "square"),
    ("ktx", lambda d: _patched(d, (_KTX["numberOfMipmapLevels"], 9)), "numberOfMipmapLevels = 9"),
    ("ktx", lambda d: _patched(d, (_KTX["glType"], 0), (_KTX["glFormat"], 0), (_KTX["glInternalFormat"], 0x8E8F)),
     "BPTC / BC6H-BC7"),
    ("ktx", lambda d: _patched(d, (_KTX["glType"], 0), (_KTX["glFormat"], 0), (_KTX["glInternalFormat"], 0x93B0)),
     "ASTC"),
    ("ktx", lambda d: _patched(d, (_KTX["glType"], 0x1401), (_KTX["glInternalFormat"], 0x8058)), "0x8058"),
    ("ktx", lambda d: _patched(d, (_KTX["glType"], 0x1406)), "glType 0x1406"),
    ("ktx", lambda d: _patched(d, (64, 7)), "imageSize 7"),
    ("dds", lambda d: d[:-1], "truncated"),
    ("dds", lambda d: d + b"\0", "longer than its header says"),
    ("dds", lambda d: d[:100], "truncated DDS header"),
    ("dds", lambda d: b"DDX " + d[4:], "not a DDS file"),
    ("dds", lambda d: _patched(d, (4, 100)), "dwSize 100"),
    ("dds", lambda d: _patched(d, (128 + 8, 0)), "not a cube map"),  # DX10 miscFlag without TEXTURECUBE
    ("dds", lambda d: _patched(d, (128 + 12, 3)), "arraySize 3"),
    ("dds", lambda d: _patched(d, (128, 95)), "BC6H"),
    ("dds", lambda d: _patched(d, (128, 28)), "DXGI_FORMAT 28"),
    ("dds", lambda d: _patched(d, (12, 8)), "square"),
    ("dds", lambda d: _patched(d, (28, 7)), "dwMipMapCount = 7"),
    ("dds", lambda d: _patched(d, (24, 4), (112, 0x200000)), "volume"),
])
def test_bad_files_are_one_line_errors(tmp_path, files, kind, edit, words):
    p = tmp_path / f"bad.{kind}"
    p.write_bytes(edit(files[kind]))
    with pytest.raises(EnvMapFileError) as exc:
        READERS[kind](p)
    msg = _one_line(exc)
    assert words in msg and str(p) in msg


@pytest.mark.parametrize("fourcc, caps2, words", [
    (b"DXT5", 0xFE00, "BC3"), (b"ATI2", 0xFE00, "BC5"), (struct.pack("<I", 36), 0xFE00, "FourCC 36"),
    (struct.pack("<I", 113), 0x0200 | 0x0400, "all six faces"), (struct.pack("<I", 116), 0, "not a cube map"),
])
def test_legacy_dds_headers(tmp_path, fourcc, caps2, words):
    n = 2
    data = _dds_bytes(n, 1, bytes(6 * n * n * 8), fourcc=struct.unpack("<I", fourcc)[0], caps2=caps2)
    p = tmp_path / "legacy.dds"
    p.write_bytes(data)
    with pytest.raises(EnvMapFileError) as exc:
        cc.read_dds(p)
    assert words in _one_line(exc)


def test_a_legacy_half_dds_reads(tmp_path):
    faces = np.arange(6 * 4 * 4, dtype="<f2").reshape(6, 2, 2, 4)  # 2² faces, one level, RGBA
    p = tmp_path / "legacy.dds"
    p.write_bytes(_dds_bytes(2, 1, faces.tobytes(), fourcc=113))
    want = envmap.convert_convention(faces[..., :3].astype(np.float64), "opengl", "openexr")
    np.testing.assert_array_equal(cc.read_dds(p)[0], want)


def test_missing_file_and_folder(tmp_path):
    for reader in READERS.values():
        with pytest.raises(EnvMapFileError) as exc:
            reader(tmp_path / "none.ktx")
        assert "not found" in _one_line(exc)
        with pytest.raises(EnvMapFileError) as exc:
            reader(tmp_path)
        assert "folder" in _one_line(exc)


def test_nonfinite_and_negative_texels_follow_the_radiance_policy(tmp_path):
    faces = np.ones((6, 2, 2, 4), "<f2")
    faces[2, 0, 1, 1] = np.nan
    p = tmp_path / "nan.dds"
    p.write_bytes(_dds_bytes(2, 1, faces.tobytes(), dxgi=10))
    with pytest.raises(RadianceError) as exc:
        cc.read_dds(p)
    assert "level 0" in _one_line(exc) and "NaN" in _one_line(exc)
    with pytest.warns(RadianceWarning):
        assert cc.read_dds(p, nonfinite="zero")[0].sum() == 6 * 4 * 3 - 1
    faces[2, 0, 1, 1] = -1e-6  # a tiny negative: clamped to 0 by the readers' default policy, with a warning
    p.write_bytes(_dds_bytes(2, 1, faces.tobytes(), dxgi=10))
    with pytest.warns(RadianceWarning):
        assert cc.read_dds(p)[0].min() == 0.0
    with pytest.raises(RadianceError):
        cc.read_dds(p, negative="error")


# ---- bad chains and outputs ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["ktx", "dds"])
@pytest.mark.parametrize("bad, exc_type, words", [
    ("nan", RadianceError, "level 1"), ("inf", RadianceError, "level 1"), ("negative", RadianceError, "level 1"),
    ("overflow", IBLError, "level 1: value 70000 overflows float16 (max 65504)"),
    ("sizes", IBLError, "expected 4x4"), ("channels", IBLError, "4 channels"), ("empty", IBLError, "no levels"),
    ("levels", IBLError, "more than the 2 levels"), ("dtype", IBLError, "dtype must be one of"),
    ("tiny", RadianceError, "smallest normal half"),
])
def test_bad_chains_write_nothing_and_keep_the_old_file(tmp_path, kind, bad, exc_type, words):
    good = [np.ones((6, 8, 8, 3)), np.ones((6, 4, 4, 3))]
    chain = [c.copy() for c in good]
    dtype = "float16"
    if bad in ("nan", "inf", "negative", "overflow"):
        chain[1][3, 1, 2, 0] = {"nan": np.nan, "inf": np.inf, "negative": -1.0, "overflow": 7e4}[bad]
    elif bad == "sizes":
        chain[1] = np.ones((6, 2, 2, 3))
    elif bad == "channels":
        chain[1] = np.ones((6, 4, 4, 4))
    elif bad == "empty":
        chain = []
    elif bad == "levels":
        chain = [np.ones((6, 2, 2, 3)), np.ones((6, 1, 1, 3)), np.ones((6, 1, 1, 3))]
    elif bad == "dtype":
        dtype = "float64"
    elif bad == "tiny":
        chain[1] = np.full((6, 4, 4, 3), 1e-9)  # every value would be 0 as half
    target = tmp_path / f"chain.{kind}"
    target.write_bytes(b"previous")
    with pytest.raises(exc_type) as exc:
        WRITERS[kind](target, chain, dtype=dtype)
    assert words in _one_line(exc)
    assert target.read_bytes() == b"previous" and [p.name for p in tmp_path.iterdir()] == [target.name]
    if bad == "overflow":  # float32 holds it
        assert READERS[kind](WRITERS[kind](target, chain, dtype="float32"))[1].max() == 7e4


@pytest.mark.parametrize("kind", ["ktx", "dds"])
def test_an_unwritable_output_is_one_line_and_leaves_nothing(tmp_path, kind):
    (tmp_path / "file").write_text("x")
    for target in (tmp_path / "file" / f"c.{kind}", tmp_path):  # below a file; a folder
        with pytest.raises(IBLError) as exc:
            WRITERS[kind](target, [np.ones((6, 1, 1, 3))])
        _one_line(exc)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_ktx_channel_count_is_checked(tmp_path):
    with pytest.raises(IBLError) as exc:
        cc.write_ktx1(tmp_path / "c.ktx", [np.ones((6, 1, 1, 3))], channels=2)
    assert "channels must be 3" in _one_line(exc)
    assert list(tmp_path.iterdir()) == []
