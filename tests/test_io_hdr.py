"""Radiance RGBE files (ibl_ref.environment.hdr_io): round trips, hand-built byte streams, orientation, bad input."""

from __future__ import annotations

import os
import re

import numpy as np
import pytest

from ibl_ref.environment import exr_io, hdr_io
from ibl_ref.errors import EnvMapFileError

RNG = np.random.default_rng(7)
HEAD = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n"


def _image(h=6, w=300):
    """Mixed content: log-uniform noise, a constant band (long runs) and exact zeros."""
    img = np.exp(RNG.uniform(np.log(1e-3), np.log(1e4), size=(h, w, 3)))
    img[1, :] = [2.0, 0.5, 0.25]  # one value repeated 300 times: runs longer than 127
    img[2, 10:20] = 0.0
    img[3, :, 1] = 0.0  # zero green channel under non-zero red/blue
    return img


def _quant_bound(img):
    # RGBE: M = max(r,g,b) = f·2^e, f ∈ [1/2, 1); mantissa m = floor(c·256/2^e), decoded (m+½)·2^e/256
    # ⇒ |error| ≤ ½·2^e/256 ≤ M/256 per channel (M ≥ 2^(e-1)); tiny slack for float rounding.
    return img.max(axis=-1, keepdims=True) / 256.0 * (1 + 1e-12) + 1e-300


@pytest.mark.parametrize("rle", [True, False])
def test_roundtrip_flat_and_rle(tmp_path, rle):
    img = _image()
    p = tmp_path / "x.hdr"
    hdr_io.write_hdr(p, img, rle=rle)
    back = hdr_io.read_hdr(p)
    assert back.shape == img.shape and back.dtype == np.float64
    assert np.all(np.abs(back - img) <= _quant_bound(img))
    # the channel holding the maximum has relative error ≤ 2^-8
    m = img.max(-1)
    nz = m > 0
    assert np.all(np.abs(back.max(-1) - m)[nz] / m[nz] <= 2.0**-8)
    assert np.all(back[~nz] == 0)  # all-zero pixels encode as E = 0 and decode to exact zeros


def test_rle_is_smaller_and_decodes_identically(tmp_path):
    img = _image()
    hdr_io.write_hdr(tmp_path / "r.hdr", img, rle=True)
    hdr_io.write_hdr(tmp_path / "f.hdr", img, rle=False)
    np.testing.assert_array_equal(hdr_io.read_hdr(tmp_path / "r.hdr"), hdr_io.read_hdr(tmp_path / "f.hdr"))
    flat_size = (tmp_path / "f.hdr").stat().st_size
    assert (tmp_path / "r.hdr").stat().st_size < flat_size


def test_hand_built_rle_and_old_style_file(tmp_path):
    # width 8 (smallest width allowed for new-style RLE), 2 scanlines
    line0 = bytes([2, 2, 0, 8])
    line0 += bytes([128 + 8, 128])  # R: run of 8 × 128
    line0 += bytes([8, 0, 16, 32, 48, 64, 80, 96, 112])  # G: 8 literals
    line0 += bytes([128 + 4, 200, 4, 1, 2, 3, 4])  # B: run of 4 × 200, then 4 literals
    line0 += bytes([128 + 8, 129])  # E: 129 everywhere
    # scanline 1: old-style RLE, one pixel then a repeat pixel (1,1,1,7) = 7 more copies
    line1 = bytes([255, 0, 0, 130, 1, 1, 1, 7])
    p = tmp_path / "tiny.hdr"
    p.write_bytes(b"#?RADIANCE\n# hand made\nFORMAT=32-bit_rle_rgbe\n\n-Y 2 +X 8\n" + line0 + line1)
    img = hdr_io.read_hdr(p)
    assert img.shape == (2, 8, 3)
    s = 2.0 ** (129 - 136)  # Radiance colr_color: (m + 0.5) * 2^(E - 136)
    np.testing.assert_array_equal(img[0, :, 0], (128 + 0.5) * s)
    np.testing.assert_array_equal(img[0, :, 1], (np.arange(8) * 16 + 0.5) * s)
    np.testing.assert_array_equal(img[0, :, 2], (np.array([200, 200, 200, 200, 1, 2, 3, 4]) + 0.5) * s)
    s1 = 2.0 ** (130 - 136)
    np.testing.assert_array_equal(img[1], np.tile([255.5 * s1, 0.5 * s1, 0.5 * s1], (8, 1)))


def test_orientations_and_exposure(tmp_path):
    # a 2 x 3 flat image with distinct pixels, stored bottom-up (+Y) and right-to-left (-X)
    px = np.array([[[128, 0, 0, 129], [129, 0, 0, 129], [130, 0, 0, 129]],
                   [[131, 0, 0, 129], [132, 0, 0, 129], [133, 0, 0, 129]]], dtype=np.uint8)
    expect = (px[..., 0] + 0.5) * 2.0 ** (129 - 136)
    p = tmp_path / "std.hdr"
    p.write_bytes(HEAD + b"-Y 2 +X 3\n" + px.tobytes())
    np.testing.assert_array_equal(hdr_io.read_hdr(p)[..., 0], expect)
    q = tmp_path / "flipped.hdr"
    q.write_bytes(HEAD + b"+Y 2 -X 3\n" + px[::-1, ::-1].tobytes())
    np.testing.assert_array_equal(hdr_io.read_hdr(q)[..., 0], expect)
    r = tmp_path / "columns.hdr"  # scanlines are columns, left to right, each top to bottom
    r.write_bytes(HEAD + b"+X 3 -Y 2\n" + np.ascontiguousarray(px.transpose(1, 0, 2)).tobytes())
    np.testing.assert_array_equal(hdr_io.read_hdr(r)[..., 0], expect)
    e = tmp_path / "exp.hdr"
    e.write_bytes(b"#?RADIANCE\nEXPOSURE=2\nEXPOSURE=0.25\n\n-Y 2 +X 3\n" + px.tobytes())
    assert hdr_io.read_hdr_header(e)["exposure"] == 0.5
    np.testing.assert_array_equal(hdr_io.read_hdr(e)[..., 0], expect)  # default: not applied
    np.testing.assert_array_equal(hdr_io.read_hdr(e, apply_exposure=True)[..., 0], expect / 0.5)


def _expect(path, *words):
    with pytest.raises(EnvMapFileError, match=re.escape(str(path))) as ei:
        hdr_io.read_hdr(path)
    msg = str(ei.value)
    assert str(path) in msg, msg
    for w in words:
        assert w in msg, msg


def test_bad_files(tmp_path):
    _expect(tmp_path / "missing.hdr", "not found")
    g = tmp_path / "garbage.hdr"
    g.write_bytes(b"\x00\x01garbage" * 20)
    _expect(g, "not a Radiance")
    x = tmp_path / "xyz.hdr"
    x.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-Y 1 +X 1\n\x80\x80\x80\x80")
    _expect(x, "xyze")
    r = tmp_path / "res.hdr"
    r.write_bytes(HEAD + b"Y 2 X 3\n" + bytes(24))
    _expect(r, "resolution line")
    img = _image(h=4, w=64)
    for rle in (True, False):
        p = tmp_path / f"full{rle}.hdr"
        hdr_io.write_hdr(p, img, rle=rle)
        data = p.read_bytes()
        t = tmp_path / f"trunc{rle}.hdr"
        t.write_bytes(data[: len(data) - 37])
        _expect(t, "truncated")
    c = tmp_path / "badrun.hdr"  # RLE run that overruns the 8-pixel scanline
    c.write_bytes(HEAD + b"-Y 1 +X 8\n" + bytes([2, 2, 0, 8, 128 + 9, 5]) + bytes(40))
    _expect(c, "corrupt")


def test_write_rejects_bad_radiance_atomically(tmp_path):
    p = tmp_path / "a.hdr"
    hdr_io.write_hdr(p, np.ones((2, 4, 3)))
    before = p.read_bytes()
    bad = np.ones((2, 4, 3))
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match=r"radiance: 1 non\-finite value\(s\) \(first"):
        hdr_io.write_hdr(p, bad)
    assert p.read_bytes() == before and os.listdir(tmp_path) == ["a.hdr"]


def test_load_cube_from_hdr(tmp_path):
    p = tmp_path / "const.hdr"
    hdr_io.write_hdr(p, np.full((8, 16, 3), 1.0))
    c = exr_io.load_cube(p)
    # 1.0 encodes as mantissa 128, E = 129 → decodes to 128.5/128 exactly; resampling keeps constants
    np.testing.assert_allclose(c, 128.5 / 128, rtol=1e-12)
    assert c.shape == (6, 4, 4, 3)


def test_rle_run_splitting_matches_flat(tmp_path):
    # rows made of runs of random lengths (1..300, incl. the 127/128 boundaries) of random values:
    # the RLE stream must decode to the same bytes as the flat stream
    rows = []
    for _ in range(5):
        vals = []
        while len(vals) < 1000:
            ln = int(RNG.choice([1, 2, 3, 4, 5, 127, 128, 129, 130, 131, 254, 255, 300]))
            vals.extend([RNG.uniform(0.1, 10.0, 3)] * ln)
        rows.append(np.array(vals[:1000]))
    img = np.stack(rows)
    hdr_io.write_hdr(tmp_path / "r.hdr", img, rle=True)
    hdr_io.write_hdr(tmp_path / "f.hdr", img, rle=False)
    np.testing.assert_array_equal(hdr_io.read_hdr(tmp_path / "r.hdr"), hdr_io.read_hdr(tmp_path / "f.hdr"))
    assert np.all(np.abs(hdr_io.read_hdr(tmp_path / "r.hdr") - img) <= _quant_bound(img))
