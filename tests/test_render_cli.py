"""Tests of ``ibl-ref render`` (ibl_ref/cli/cmd_render.py) and ibl_ref.rendering.image_io."""

import json

import numpy as np
import pytest

from ibl_ref.cli import main
from ibl_ref.errors import IBLError


def _read_exr(path):
    """Read back with the OpenEXR 3.x API directly (independent of ibl_ref's readers)."""
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        ch = f.channels()
        assert "RGB" in ch or {"R", "G", "B"} <= set(ch)
        return np.asarray(ch["RGB"].pixels) if "RGB" in ch else np.stack([ch[c].pixels for c in "RGB"], -1)


def test_default_scene_writes_exr_and_png(tmp_path):
    out, png = tmp_path / "x.exr", tmp_path / "x.png"
    rc = main(["render", "--out", str(out), "--size", "32", "32", "--lights", "6", "--vsm-res", "64",
               "--png", str(png), "--no-progress"])
    assert rc == 0
    img = _read_exr(out)
    assert img.shape == (32, 32, 3)
    assert np.all(np.isfinite(img)) and np.all(img >= 0)
    assert (img.max(axis=2) > 0).sum() > 100  # teapot + ground cover a good part of the frame
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    import matplotlib.image as mpimg

    assert mpimg.imread(str(png)).shape[:2] == (32, 32)
    info = json.loads((tmp_path / "x.json").read_text())
    assert info["mode"] == "ours" and info["lights"] == 6 and info["size"] == [32, 32]


@pytest.mark.parametrize("prefilter", ["pyramid", "exact-lobe"])
def test_no_occlusion_constant_env_is_kd_plus_ks(tmp_path, prefilter):
    # constant map of value 1, VIS ≡ 1: every covered pixel is kd + ks (normalised lobes; float32 PEMs → 1e-6)
    # and W × H is honoured (non-square); both PEM prefilters keep a constant map constant
    out = tmp_path / "c.npz"
    rc = main(["render", "--synthetic", "constant", "--env-size", "16", "--mesh", "torus", "--lights", "6",
               "--size", "20", "12", "--mode", "no-occlusion", "--material", "0.25,0.5,0.9",
               "--ground-material", "0.1,0.3,0.2", "--prefilter", prefilter, "--out", str(out)])
    assert rc == 0
    d = np.load(out)
    assert d["image"].shape == (12, 20, 3)
    m = d["mask"]
    on_mesh = m & (d["glossiness"] == 0.9)
    assert on_mesh.sum() > 10
    np.testing.assert_allclose(d["image"][on_mesh], 0.75, rtol=1e-6)
    np.testing.assert_allclose(d["image"][m & ~on_mesh], 0.4, rtol=1e-6)
    np.testing.assert_allclose(d["diffuse"][on_mesh], 0.25, rtol=1e-6)


@pytest.mark.parametrize("material, match", [
    ("1,2", "kd,ks,g"), ("a,b,c", "kd,ks,g"), ("0.1,0.2,1.5", r"\[0, 1\]"), ("-0.1,0.5,0.5", ">= 0"),
    ("0.1,0.2,nan", r"\[0, 1\]"),
])
def test_bad_material_exits_1(tmp_path, capsys, material, match):
    import re

    rc = main(["render", "--out", str(tmp_path / "x.exr"), f"--material={material}"])  # '=' form: "-0.1,…"
    assert rc == 1
    err = capsys.readouterr().err
    assert "--material" in err and re.search(match, err)
    assert not (tmp_path / "x.exr").exists()


def test_unwritable_output_folder(tmp_path, capsys):
    blocker = tmp_path / "file.txt"
    blocker.write_text("not a folder")
    rc = main(["render", "--out", str(blocker / "x.exr"), "--size", "8"])
    assert rc == 1
    assert "not a folder" in capsys.readouterr().err
    assert main(["render", "--out", str(tmp_path / "x.tiff")]) == 1
    assert "extension" in capsys.readouterr().err
    import os

    if os.geteuid() != 0:  # root may write anywhere
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        try:
            assert main(["render", "--out", str(ro / "x.exr"), "--size", "8"]) == 1
            assert "not writable" in capsys.readouterr().err
        finally:
            ro.chmod(0o700)


def test_gmap_and_size_errors(tmp_path, capsys):
    bad = tmp_path / "g.npy"
    np.save(bad, np.full((4, 4), 1.5))
    assert main(["render", "--out", str(tmp_path / "x.exr"), "--gmap", str(bad)]) == 1
    assert "[0, 1]" in capsys.readouterr().err
    assert main(["render", "--out", str(tmp_path / "x.exr"), "--gmap", str(tmp_path / "none.png")]) == 1
    assert "not found" in capsys.readouterr().err
    assert main(["render", "--out", str(tmp_path / "x.exr"), "--size", "8", "8", "8"]) == 1
    assert "--size" in capsys.readouterr().err


def test_gmap_render_two_halves(tmp_path):
    # a .npy g map with halves 0.1 | 0.95 on sphere_on_plane (planar_xz fallback: u = (x − x_min)/extent):
    # pixels well inside each half carry exactly that g
    gm = np.zeros((8, 8))
    gm[:, :4], gm[:, 4:] = 0.1, 0.95
    np.save(tmp_path / "g.npy", gm)
    out = tmp_path / "g.npz"
    assert main(["render", "--mesh", "sphere_on_plane", "--no-ground", "--synthetic", "constant", "--env-size", "16",
                 "--lights", "6", "--size", "24", "--visibility", "none", "--gmap", str(tmp_path / "g.npy"),
                 "--out", str(out)]) == 0
    d = np.load(out)
    g = d["glossiness"][d["mask"]]
    assert np.sum(g == 0.1) > 20 and np.sum(g == 0.95) > 20


def test_parse_material_rgb():
    from ibl_ref.cli.cmd_render import parse_material

    m = parse_material("0.1,0.2,0.3,0.4,0.5,0.6,0.7")
    np.testing.assert_array_equal(m.kd, [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(m.ks, [0.4, 0.5, 0.6])
    assert m.g == 0.7
    with pytest.raises(IBLError, match="kd,ks,g"):
        parse_material("0.1,0.2,0.3,0.4")


def test_image_io_roundtrip_and_errors(tmp_path):
    from ibl_ref.rendering.image_io import read_g_map, write_image_exr

    a = np.random.default_rng(0).random((5, 7, 3)) * 1e4
    write_image_exr(tmp_path / "a.exr", a)
    np.testing.assert_array_equal(_read_exr(tmp_path / "a.exr"), a.astype(np.float32))  # float32 storage
    for bad, why in ((np.full((2, 2, 3), np.nan), "non-finite"), (-np.ones((2, 2, 3)), "negative radiance"),
                     (np.ones((2, 2, 2)), r"must be \(H, W\)")):
        with pytest.raises(IBLError, match=why):
            write_image_exr(tmp_path / "b.exr", bad)
    assert not (tmp_path / "b.exr").exists()
    write_image_exr(tmp_path / "g.exr", np.full((3, 4, 3), 0.25))
    np.testing.assert_allclose(read_g_map(tmp_path / "g.exr"), 0.25)
    (tmp_path / "a.json").write_text("{}")
    with pytest.raises(IBLError, match="npy, .exr or .png"):
        read_g_map(tmp_path / "a.json")


def test_gmap_uses_mesh_uvs_from_file(tmp_path):
    # an OBJ quad whose u runs *against* x (u = (1 − x)/2): the g map's left half (g = 0.1) must land on +x,
    # the opposite of what the planar_xz fallback would give; camera from above with +x to the right
    (tmp_path / "q.obj").write_text(
        "v -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\nvt 1 0\nvt 0 0\nvt 0 1\nvt 1 1\nvn 0 1 0\n"
        "f 1/1/1 3/3/1 2/2/1\nf 1/1/1 4/4/1 3/3/1\n")
    gm = np.zeros((8, 8))
    gm[:, :4], gm[:, 4:] = 0.1, 0.95
    np.save(tmp_path / "g.npy", gm)
    out = tmp_path / "q.npz"
    assert main(["render", "--mesh", str(tmp_path / "q.obj"), "--no-ground", "--synthetic", "constant",
                 "--env-size", "16", "--lights", "6", "--size", "24", "--visibility", "none",
                 "--camera-eye", "0", "3", "0.3", "--camera-target", "0", "0", "0", "--camera-up", "0", "0", "-1",
                 "--fov", "50", "--gmap", str(tmp_path / "g.npy"), "--out", str(out)]) == 0
    d = np.load(out)
    m, g = d["mask"], d["glossiness"]
    # columns ≥ 2 pixels (> 1 texel) away from the centre line and from the quad's border (where the bilinear,
    # repeat-wrapped lookup blends the two halves)
    cols = np.flatnonzero(m.any(axis=0))
    c0, c1 = cols[0], cols[-1]
    mid = (c0 + c1) // 2
    left, right = np.zeros_like(m), np.zeros_like(m)
    left[:, c0 + 2:mid - 1] = True
    right[:, mid + 3:c1 - 1] = True
    left &= m
    right &= m
    assert left.sum() > 20 and right.sum() > 20
    np.testing.assert_array_equal(g[left], 0.95)
    np.testing.assert_array_equal(g[right], 0.1)
