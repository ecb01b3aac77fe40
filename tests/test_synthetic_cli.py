"""Tests of ``ibl-ref synth``."""

import numpy as np
import pytest
import trimesh

from ibl_ref.environment import envmap
from ibl_ref.synthetic import synthetic_envs as se
from ibl_ref.cli import main
from ibl_ref.cli.cmd_synth import parse_params
from ibl_ref.errors import IBLError


def test_parse_params():
    p = parse_params(["a=1e5", "b=[1,2,3]", "c=1,2,3", "d=true", "e=latlong"])
    assert p == {"a": 1e5, "b": [1, 2, 3], "c": [1.0, 2.0, 3.0], "d": True, "e": "latlong"}
    with pytest.raises(IBLError, match=r"\-\-param expects key=value, got 'novalue'"):
        parse_params(["novalue"])


def test_synth_env_npy(tmp_path, capsys):
    out = tmp_path / "d.npy"
    assert main(["synth", "env", "delta", str(out), "--size", "8", "--param", "normalize=true",
                 "--param", "texel=[1,2,3]"]) == 0
    cube = np.load(out)
    assert cube.shape == (6, 8, 8, 3)
    # normalised delta: ∫L dω = 1 (exact texel solid angle)
    np.testing.assert_allclose(np.einsum("fij,fijc->c", envmap.cube_solid_angles(8), cube), 1.0, rtol=1e-12)
    assert "integral" in capsys.readouterr().out


def test_synth_env_exr_roundtrip(tmp_path):
    from ibl_ref.environment import exr_io
    out = tmp_path / "sky.exr"
    assert main(["synth", "env", "sky_sun", str(out), "--size", "16", "--param", "sun_radiance=1e5"]) == 0
    back = exr_io.load_cube(out)
    ref = se.make_env("sky_sun", 16, sun_radiance=1e5)
    np.testing.assert_allclose(back, ref, rtol=1e-6)  # float32 storage: 2^-24 relative rounding


def test_synth_env_bad_param_returns_error(tmp_path, capsys):
    assert main(["synth", "env", "constant", str(tmp_path / "c.npy"), "--param", "colour=1"]) == 1
    assert "unknown parameter" in capsys.readouterr().err
    assert not (tmp_path / "c.npy").exists()


def test_synth_mesh(tmp_path):
    out = tmp_path / "torus.ply"
    assert main(["synth", "mesh", "torus", str(out), "--param", "major_sections=16",
                 "--param", "minor_sections=8"]) == 0
    m = trimesh.load(str(out), force="mesh")
    assert len(m.faces) == 2 * 16 * 8 and m.is_watertight
    assert main(["synth", "mesh", "torus", str(tmp_path / "torus.xyz")]) == 1


def test_synth_help_lists_generators(capsys):
    with pytest.raises(SystemExit, match=r"^0$"):
        main(["synth", "env", "--help"])
    text = capsys.readouterr().out
    for name in se.ENV_NAMES:
        assert f"{name}:" in text
    assert "sun_solid_angle" in text
