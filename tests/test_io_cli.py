"""``ibl-ref convert`` / ``ibl-ref info`` (ibl_ref.cli.cmd_io)."""

from __future__ import annotations

import re

import numpy as np
import OpenEXR

from ibl_ref.environment import envmap, exr_io, hdr_io
from ibl_ref.cli import main


def test_info_prints_exact_integral(tmp_path, capsys):
    p = tmp_path / "const.exr"
    exr_io.write_envmap(p, np.full((6, 4, 4, 3), 0.5))
    assert main(["info", str(p)]) == 0
    out = capsys.readouterr().out
    assert "layout:     cube" in out and "R,G,B" in out and "pixel type: float" in out
    # ∫ 0.5 dω over the sphere = 2π (exact texel solid angles sum to 4π)
    vals = [float(x) for x in re.findall(r"^[RGB]\s+\S+\s+\S+\s+\S+\s+(\S+)", out, re.M)]
    assert len(vals) == 3 and np.allclose(vals, 2 * np.pi, rtol=1e-8)
    assert "no NaN" in out


def test_info_hdr_and_errors(tmp_path, capsys):
    p = tmp_path / "ll.hdr"
    hdr_io.write_hdr(p, np.full((8, 16, 3), 1.0))
    assert main(["info", str(p)]) == 0
    assert "latlong" in capsys.readouterr().out
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"not an exr at all")
    assert main(["info", str(bad)]) == 1
    err = capsys.readouterr().err
    assert str(bad) in err and "not an OpenEXR" in err


def test_convert_latlong_to_cube_half_and_opengl(tmp_path, capsys):
    src = tmp_path / "ll.exr"
    ll = 1.0 + envmap.latlong_directions(16, 32)[..., 1:2] ** 2 * np.ones(3)
    exr_io.write_envmap(src, ll, layout="latlong")
    dst = tmp_path / "cube.exr"
    assert main(["convert", str(src), str(dst), "--layout", "cube", "--size", "8", "--half"]) == 0
    e = exr_io.read_envmap(dst)
    assert e.layout == "cube" and e.size == 8 and e.pixel_type == "half"
    # the +Y face centre region is brighter (1 + y²) than the +Z face centre (≈ 1)
    assert e.data[2, 3:5, 3:5].min() > 1.8 and e.data[4, 3:5, 3:5].max() < 1.1
    gl = tmp_path / "gl.exr"
    assert main(["convert", str(dst), str(gl), "--layout", "cube", "--convention", "opengl"]) == 0
    f = OpenEXR.File(str(gl), separate_channels=True)
    assert "envmap" not in f.header() and f.header()["iblref_convention"] == "opengl"
    np.testing.assert_array_equal(exr_io.read_envmap(gl).data, e.data)


def test_convert_half_overflow_needs_clamp(tmp_path, capsys):
    src = tmp_path / "sun.exr"
    cube = np.ones((6, 4, 4, 3))
    cube[4, 1, 2] = 1e5
    exr_io.write_envmap(src, cube)
    dst = tmp_path / "h.exr"
    assert main(["convert", str(src), str(dst), "--layout", "cube", "--half"]) == 1
    assert "65504" in capsys.readouterr().err and not dst.exists()
    assert main(["convert", str(src), str(dst), "--layout", "cube", "--half", "--clamp-half"]) == 0
    assert "clamped 3 value(s)" in capsys.readouterr().out
    assert exr_io.read_envmap(dst).data.max() == 65504.0
