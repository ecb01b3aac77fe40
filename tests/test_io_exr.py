"""OpenEXR environment-map I/O (ibl_ref.environment.exr_io): round trips, orientation, overflow, atomicity, bad input."""

from __future__ import annotations

import os
import re
import warnings

import numpy as np
import OpenEXR
import pytest

from ibl_ref.environment import envmap, exr_io
from ibl_ref.errors import EnvMapFileError, IBLError, LayoutError, RadianceError

RNG = np.random.default_rng(1234)


def _cube(n=8, c=3, lo=0.01, hi=100.0):
    # log-uniform positive radiance, deterministic
    return np.exp(RNG.uniform(np.log(lo), np.log(hi), size=(6, n, n, c)))


def _raw_write(path, channels: dict, header=None):
    """Write an EXR directly with the OpenEXR binding (bypassing the code under test)."""
    hdr = {"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage}
    hdr.update(header or {})
    # the binding ignores strides: non-contiguous views are written as their raw buffer (OpenEXR 3.5)
    OpenEXR.File(hdr, {k: np.ascontiguousarray(v) for k, v in channels.items()}).write(str(path))


def _raw_read(path):
    f = OpenEXR.File(str(path), separate_channels=True)
    return f.header(), {k: v.pixels for k, v in f.channels().items()}


# ---------------------------------------------------------------------------------------------
# round trips
# ---------------------------------------------------------------------------------------------
def test_float_roundtrip_cube_and_latlong(tmp_path):
    cube = _cube()
    exr_io.write_envmap(tmp_path / "c.exr", cube)
    e = exr_io.read_envmap(tmp_path / "c.exr")
    assert e.layout == "cube" and e.channels == ("R", "G", "B") and e.pixel_type == "float"
    assert e.data.dtype == np.float64 and e.data.shape == cube.shape
    # float32 storage: relative rounding ≤ 2^-24
    np.testing.assert_allclose(e.data, cube, rtol=2.0**-24, atol=0)
    ll = RNG.uniform(0, 5, size=(8, 16, 3))
    exr_io.write_envmap(tmp_path / "l.exr", ll, layout="latlong")
    e = exr_io.read_envmap(tmp_path / "l.exr")
    assert e.layout == "latlong" and e.size == 8
    np.testing.assert_allclose(e.data, ll, rtol=2.0**-24, atol=0)


def test_half_roundtrip_within_fp16_rounding(tmp_path):
    # values in the half *normal* range [6.1e-5, 65504]: round-to-nearest relative error ≤ 2^-11
    cube = _cube(lo=1e-3, hi=6e4)
    exr_io.write_envmap(tmp_path / "h.exr", cube, pixel_type="half")
    e = exr_io.read_envmap(tmp_path / "h.exr")
    assert e.pixel_type == "half"
    rel = np.abs(e.data - cube) / cube
    assert rel.max() <= 2.0**-11
    hdr, ch = _raw_read(tmp_path / "h.exr")
    assert ch["R"].dtype == np.float16


@pytest.mark.parametrize("c,names", [(1, {"Y"}), (3, {"R", "G", "B"}), (4, {"R", "G", "B", "A"})])
def test_channel_sets(tmp_path, c, names):
    cube = _cube(n=4, c=c)
    exr_io.write_envmap(tmp_path / "x.exr", cube)
    _, ch = _raw_read(tmp_path / "x.exr")
    assert set(ch) == names
    e = exr_io.read_envmap(tmp_path / "x.exr")
    assert e.data.shape == (6, 4, 4, c)
    np.testing.assert_allclose(e.data, cube, rtol=2.0**-24)
    # load_cube always gives RGB: Y replicated, alpha dropped
    lc = exr_io.load_cube(tmp_path / "x.exr")
    assert lc.shape == (6, 4, 4, 3)
    np.testing.assert_allclose(lc, np.repeat(cube, 3, -1) if c == 1 else cube[..., :3], rtol=2.0**-24)


# ---------------------------------------------------------------------------------------------
# envmap attribute and orientation against OpenEXR's definition (ImfEnvmap.cpp, re-typed here)
# ---------------------------------------------------------------------------------------------
def test_envmap_attribute_written(tmp_path):
    exr_io.write_envmap(tmp_path / "c.exr", _cube(n=2))
    exr_io.write_envmap(tmp_path / "l.exr", np.ones((4, 8, 3)), layout="latlong")
    exr_io.write_envmap(tmp_path / "g.exr", _cube(n=2), convention="opengl")
    assert _raw_read(tmp_path / "c.exr")[0]["envmap"] == OpenEXR.ENVMAP_CUBE
    assert _raw_read(tmp_path / "l.exr")[0]["envmap"] == OpenEXR.ENVMAP_LATLONG
    g = _raw_read(tmp_path / "g.exr")[0]
    assert "envmap" not in g and g["iblref_convention"] == "opengl"


def _exr_cube_direction(px, py, n):
    """Direction of strip pixel (px, py) by OpenEXR's CubeMap::pixelPosition (inverted) + direction.

    Corner-to-corner addressing pos/(n-1)*2-1 exactly as in ImfEnvmap.cpp.
    """
    face = py // n
    lx, ly = px, py - face * n
    m = n - 1
    # invert pixelPosition: (pif.x, pif.y) per face
    pif = {
        0: (m - ly, lx),  # +X: pos.x = min.x + pif.y, pos.y = max.y - pif.x
        1: (m - ly, m - lx),  # -X: pos.x = max.x - pif.y, pos.y = max.y - pif.x
        2: (lx, m - ly),  # +Y: pos.x = min.x + pif.x, pos.y = max.y - pif.y
        3: (lx, ly),  # -Y: pos.x = min.x + pif.x, pos.y = min.y + pif.y
        4: (m - lx, m - ly),  # +Z: pos.x = max.x - pif.x, pos.y = max.y - pif.y
        5: (lx, m - ly),  # -Z: pos.x = min.x + pif.x, pos.y = max.y - pif.y
    }[face]
    a, b = pif[0] / m * 2 - 1, pif[1] / m * 2 - 1
    d = {0: (1, a, b), 1: (-1, a, b), 2: (a, 1, b), 3: (a, -1, b), 4: (a, b, 1), 5: (a, b, -1)}[face]
    d = np.array(d, dtype=float)
    return face, d / np.linalg.norm(d)


def test_cube_strip_orientation_matches_openexr(tmp_path):
    n = 8
    dirs = envmap.texel_directions(n)
    exr_io.write_envmap(tmp_path / "d.exr", dirs + 2.0)  # store direction (+2 to stay non-negative)
    _, ch = _raw_read(tmp_path / "d.exr")
    strip = np.stack([ch["R"], ch["G"], ch["B"]], -1).astype(np.float64) - 2.0
    assert strip.shape == (6 * n, n, 3)
    texel_angle = 2 * np.arctan(1.0 / n)  # largest angular texel width (face centre)
    for py in range(6 * n):
        for px in range(n):
            face, d_exr = _exr_cube_direction(px, py, n)
            d_file = strip[py, px] / np.linalg.norm(strip[py, px])
            # centre vs corner addressing differ by < 1 texel; a wrong flip/rotation would be far off
            assert np.arccos(np.clip(d_file @ d_exr, -1, 1)) < texel_angle, (face, px, py)
            # same face: dominant axis and sign agree
            assert np.argmax(np.abs(d_file)) == face // 2 and np.sign(d_file[face // 2]) == (1 - 2 * (face % 2))


def test_latlong_orientation_matches_openexr(tmp_path):
    h = 8
    ll = envmap.latlong_directions(h, 2 * h) + 2.0
    exr_io.write_envmap(tmp_path / "l.exr", ll, layout="latlong")
    _, ch = _raw_read(tmp_path / "l.exr")
    img = np.stack([ch["R"], ch["G"], ch["B"]], -1).astype(np.float64) - 2.0
    ys, xs = np.mgrid[0:h, 0 : 2 * h].astype(float)
    # LatLongMap::latLong(dataWindow, pixelPosition) and direction(), corner-to-corner addressing
    lat = -np.pi * (ys / (h - 1) - 0.5)
    lon = -2 * np.pi * (xs / (2 * h - 1) - 0.5)
    d_exr = np.stack([np.sin(lon) * np.cos(lat), np.sin(lat), np.cos(lon) * np.cos(lat)], -1)
    ang = np.arccos(np.clip(np.einsum("...i,...i", img, d_exr), -1, 1))
    # addressing difference ≤ one latitude step π/(h-1) along y
    assert ang.max() < np.pi / (h - 1)


def test_opengl_convention_file_roundtrip(tmp_path):
    cube = _cube(n=4)
    exr_io.write_envmap(tmp_path / "g.exr", cube, convention="opengl")
    _, ch = _raw_read(tmp_path / "g.exr")
    strip = np.stack([ch["R"], ch["G"], ch["B"]], -1)
    # OpenGL +Z face (u→ +x) is the OpenEXR +Z face (u→ -x) mirrored horizontally
    np.testing.assert_allclose(strip[16:20], cube[4][:, ::-1], rtol=2.0**-24)
    e = exr_io.read_envmap(tmp_path / "g.exr")  # back to openexr orientation
    np.testing.assert_allclose(e.data, cube, rtol=2.0**-24)


# ---------------------------------------------------------------------------------------------
# half overflow
# ---------------------------------------------------------------------------------------------
def test_half_overflow_raises_naming_file_count_and_max(tmp_path):
    cube = _cube(n=4)
    cube[0, 0, 0, 0] = 1e5
    cube[2, 1, 1, 2] = 70000.0
    p = tmp_path / "sun.exr"
    with pytest.raises(IBLError, match=r"2 value\(s\) exceed the largest") as ei:
        exr_io.write_envmap(p, cube, pixel_type="half")
    msg = str(ei.value)
    assert str(p) in msg and "2 value(s)" in msg and "100000" in msg
    assert not p.exists() and os.listdir(tmp_path) == []


def test_half_clamp_is_reported(tmp_path):
    cube = _cube(n=4)
    cube[0, 0, 0, 0] = 1e5
    cube[2, 1, 1, 2] = 70000.0
    p = tmp_path / "sun.exr"
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        rep = exr_io.write_envmap(p, cube, pixel_type="half", clamp_half=True)
    assert rep.clamped_count == 2 and rep.clamped_max == 1e5
    assert any("clamped 2 value(s)" in str(x.message) for x in w)
    e = exr_io.read_envmap(p)
    assert np.all(np.isfinite(e.data))
    assert e.data[0, 0, 0, 0] == 65504.0 and e.data[2, 1, 1, 2] == 65504.0


# ---------------------------------------------------------------------------------------------
# atomic writes
# ---------------------------------------------------------------------------------------------
def test_failed_write_keeps_old_file(tmp_path):
    p = tmp_path / "env.exr"
    good = _cube(n=4)
    exr_io.write_envmap(p, good)
    before = p.read_bytes()
    bad = good.copy()
    bad[1, 2, 3, 0] = np.nan
    with pytest.raises(RadianceError, match=r"radiance: 1 non\-finite value\(s\) \(first"):
        exr_io.write_envmap(p, bad)
    neg = good.copy()
    neg[0, 0, 0, 1] = -1.0
    with pytest.raises(RadianceError, match=r"radiance: 1 negative radiance value\(s"):
        exr_io.write_envmap(p, neg)
    assert p.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["env.exr"]


def test_crash_during_write_keeps_old_file_and_no_temp(tmp_path, monkeypatch):
    p = tmp_path / "env.exr"
    exr_io.write_envmap(p, _cube(n=4))
    before = p.read_bytes()
    seen = []

    class Exploding:
        def __init__(self, *a, **k):
            pass

        def write(self, name):
            seen.append(name)
            with open(name, "wb") as fh:  # half-written garbage, then failure
                fh.write(b"v/1\x01partial")
            raise RuntimeError("disk full (simulated)")

    monkeypatch.setattr(OpenEXR, "File", Exploding)
    with pytest.raises(EnvMapFileError, match="disk full"):
        exr_io.write_envmap(p, _cube(n=4))
    assert seen and seen[0].endswith(".exr")  # the temp file keeps the .exr suffix
    assert p.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["env.exr"]


def test_unwritable_destination_is_a_clear_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(IBLError, match="file"):
        exr_io.write_envmap(blocker / "sub" / "x.exr", _cube(n=2))
    assert blocker.read_text() == "x"


# ---------------------------------------------------------------------------------------------
# bad input files: each error names the file
# ---------------------------------------------------------------------------------------------
def _expect(exc, path, *words):
    with pytest.raises(exc, match=re.escape(str(path))) as ei:
        exr_io.read_envmap(path)
    msg = str(ei.value)
    assert str(path) in msg, msg
    for w in words:
        assert w in msg, msg


def test_missing_file(tmp_path):
    _expect(EnvMapFileError, tmp_path / "nope.exr", "not found")


def test_garbage_bytes(tmp_path):
    p = tmp_path / "garbage.exr"
    p.write_bytes(bytes(RNG.integers(0, 256, 200, dtype=np.uint8)))
    _expect(EnvMapFileError, p, "not an OpenEXR")


def test_truncated_exr(tmp_path):
    p = tmp_path / "full.exr"
    exr_io.write_envmap(p, _cube(n=8))
    data = p.read_bytes()
    t = tmp_path / "trunc.exr"
    t.write_bytes(data[: len(data) // 2])
    _expect(EnvMapFileError, t, "corrupt or truncated")


@pytest.mark.parametrize("value,word", [(np.nan, "NaN"), (np.inf, "NaN/Inf"), (-0.5, "negative")])
def test_bad_radiance_in_file(tmp_path, value, word):
    r = np.ones((24, 4), np.float32)
    r[5, 2] = value
    p = tmp_path / "bad.exr"
    _raw_write(p, {"R": r, "G": np.ones_like(r), "B": np.ones_like(r)}, {"envmap": OpenEXR.ENVMAP_CUBE})
    _expect(RadianceError, p, word)


def test_wrong_aspect_for_declared_layout(tmp_path):
    p = tmp_path / "aspect.exr"
    one = np.ones((8, 16), np.float32)  # 2:1 image claiming to be a cube strip
    _raw_write(p, {"R": one, "G": one, "B": one}, {"envmap": OpenEXR.ENVMAP_CUBE})
    _expect(LayoutError, p, "cube", "16 wide x 8 high")


def test_uninferable_layout_without_attribute(tmp_path):
    p = tmp_path / "square.exr"
    one = np.ones((8, 8), np.float32)
    _raw_write(p, {"R": one, "G": one, "B": one})
    _expect(LayoutError, p, "cannot infer")
    # explicit override on an inferable shape without attribute
    q = tmp_path / "noattr.exr"
    two = np.ones((8, 16), np.float32)
    _raw_write(q, {"R": two, "G": two, "B": two})
    assert exr_io.read_envmap(q).layout == "latlong"


def test_missing_rgb_channels(tmp_path):
    p = tmp_path / "depth.exr"
    _raw_write(p, {"Z": np.ones((24, 4), np.float32)}, {"envmap": OpenEXR.ENVMAP_CUBE})
    _expect(LayoutError, p, "missing R/G/B", "Z")
    q = tmp_path / "rg.exr"
    _raw_write(q, {"R": np.ones((24, 4), np.float32), "G": np.ones((24, 4), np.float32)})
    _expect(LayoutError, q, "missing R/G/B")


# ---------------------------------------------------------------------------------------------
# pyramids and load_cube
# ---------------------------------------------------------------------------------------------
def test_pyramid_roundtrip_multipart(tmp_path):
    levels = [_cube(n=8), _cube(n=4), _cube(n=2), _cube(n=1)]
    p = tmp_path / "pyr.exr"
    exr_io.write_pyramid(p, levels)
    f = OpenEXR.File(str(p), separate_channels=True)
    assert [part.name() for part in f.parts] == ["level0", "level1", "level2", "level3"]
    assert all(part.header["envmap"] == OpenEXR.ENVMAP_CUBE for part in f.parts)
    assert [part.channels["R"].pixels.shape for part in f.parts] == [(48, 8), (24, 4), (12, 2), (6, 1)]
    back = exr_io.read_pyramid(p)
    assert len(back) == 4
    for a, b in zip(back, levels):
        np.testing.assert_allclose(a, b, rtol=2.0**-24)
    # half pyramid with a sun: error unless clamped
    levels[1][0, 0, 0, 0] = 2e5
    with pytest.raises(IBLError, match="level 1"):
        exr_io.write_pyramid(tmp_path / "h.exr", levels, pixel_type="half")
    with pytest.warns(RuntimeWarning):
        rep = exr_io.write_pyramid(tmp_path / "h.exr", levels, pixel_type="half", clamp_half=True)
    assert rep.clamped_count == 1 and rep.clamped_max == 2e5


def test_load_cube_from_latlong_and_resize(tmp_path):
    # a constant map must come back constant (area-weighted averages of a constant)
    exr_io.write_envmap(tmp_path / "l.exr", np.full((8, 16, 3), 3.0), layout="latlong")
    c = exr_io.load_cube(tmp_path / "l.exr")
    assert c.shape == (6, 4, 4, 3)
    np.testing.assert_allclose(c, 3.0, rtol=1e-12)
    cube = _cube(n=8)
    exr_io.write_envmap(tmp_path / "c.exr", cube)
    small = exr_io.load_cube(tmp_path / "c.exr", size=4)
    # 2x2 block averages weighted by exact solid angle (independent computation)
    w = envmap.texel_solid_angles(8)
    ref = np.einsum("fiajbc,iajb->fijc", cube.reshape(6, 4, 2, 4, 2, 3), w.reshape(4, 2, 4, 2))
    ref /= w.reshape(4, 2, 4, 2).sum(axis=(1, 3))[None, :, :, None]
    np.testing.assert_allclose(small, ref, rtol=1e-6)


def test_load_cube_from_cross_files(tmp_path):
    from ibl_ref.environment import resample

    cube = _cube(n=4)
    for layout in ("hcross", "vcross"):
        img = resample.cube_to_cross(cube, layout).astype(np.float32)
        p = tmp_path / f"{layout}.exr"
        _raw_write(p, {"R": img[..., 0], "G": img[..., 1], "B": img[..., 2]})  # no envmap attribute
        np.testing.assert_allclose(exr_io.load_cube(p), cube, rtol=2.0**-24)


def test_read_overrides(tmp_path):
    cube = _cube(n=4)
    gl = envmap.convert_convention(cube, "openexr", "opengl").reshape(24, 4, 3).astype(np.float32)
    p = tmp_path / "foreign_gl.exr"  # an OpenGL-oriented strip from another tool: no attributes at all
    _raw_write(p, {"R": gl[..., 0], "G": gl[..., 1], "B": gl[..., 2]})
    np.testing.assert_allclose(exr_io.read_envmap(p, convention="opengl").data, cube, rtol=2.0**-24)
    np.testing.assert_allclose(exr_io.load_cube(p, convention="opengl"), cube, rtol=2.0**-24)
    with pytest.raises(LayoutError, match=str(p)):
        exr_io.read_envmap(p, layout="latlong")


def test_non_contiguous_input_written_correctly(tmp_path):
    # guards against the binding's stride bug (see _raw_write): pass a strided view of a bigger array
    big = _cube(n=4, c=4)
    view = big[..., 1:4]  # non-contiguous
    assert not view.flags["C_CONTIGUOUS"]
    exr_io.write_envmap(tmp_path / "v.exr", view)
    np.testing.assert_allclose(exr_io.read_envmap(tmp_path / "v.exr").data, view, rtol=2.0**-24)
