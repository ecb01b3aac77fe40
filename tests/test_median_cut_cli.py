"""CLI tests of ``ibl-ref mediancut`` and ``ibl-ref pem`` (ibl_ref/cli/cmd_mediancut.py)."""

import json

import numpy as np

from ibl_ref.cli import main
from ibl_ref.environment.envmap import texel_solid_angles

from ibl_ref.environment import exr_io


def _map(n=16):
    rng = np.random.default_rng(11)
    cube = 0.1 + rng.random((6, n, n, 3))
    cube[2, 3, 4] = (200.0, 150.0, 100.0)
    return cube


def test_mediancut_cli_json(tmp_path, capsys):
    cube = _map()
    src = tmp_path / "env.exr"
    exr_io.write_envmap(src, cube, layout="cube")  # float32 pixels
    out = tmp_path / "lights.json"
    assert main(["mediancut", str(src), "--lights", "12", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["n_lights"] == 12 and len(data["lights"]) == 12
    # Σ rgb = ∫L dω of the file's (float32-rounded) map: independent sum here; float32 storage → rtol 1e-6
    ref = np.einsum("fijc,ij->c", cube.astype(np.float32).astype(np.float64), texel_solid_angles(16))
    np.testing.assert_allclose(np.sum([l["rgb"] for l in data["lights"]], axis=0), ref, rtol=1e-6)
    assert all(abs(np.linalg.norm(l["direction"]) - 1) < 1e-12 for l in data["lights"])
    assert main(["mediancut", str(src), "--lights", "13", "--out", str(out)]) == 1
    assert "multiple of 6" in capsys.readouterr().err


def test_pem_cli_roundtrip(tmp_path):
    cube = _map()
    src = tmp_path / "env.exr"
    exr_io.write_envmap(src, cube, layout="cube")
    out = tmp_path / "pems"
    assert main(["pem", str(src), "--lights", "6", "--out", str(out)]) == 0
    info = json.loads((out / "pems.json").read_text())
    assert info["n_pems"] == 6 and len(info["files"]) == 6
    levels = [exr_io.read_pyramid(out / f) for f in info["files"]]
    assert len(levels[0]) == 5  # 16, 8, 4, 2, 1
    # the PEMs add up to the full map at level 0 (masked copies partition the map; float32 file)
    np.testing.assert_allclose(sum(l[0] for l in levels), cube, rtol=1e-6)
