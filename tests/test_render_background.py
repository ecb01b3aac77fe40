"""Backdrops (``background="env"``) and the ground material in every mode; ``ibl-ref render --background/--exposure``."""

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from ibl_ref.rendering.camera import PerspectiveCamera
from ibl_ref.cli import main
from ibl_ref.errors import IBLError

CAM = PerspectiveCamera(eye=[0.0, 1.2, 3.0], target=[0, 0.3, 0], up=[0, 1, 0], fov_y_deg=50, width=20, height=16)


def _scene():
    s = trimesh.creation.icosphere(2, 0.4).apply_translation([0, 0.4, 0])
    q = trimesh.Trimesh([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], [[0, 2, 1], [0, 3, 2]], process=False)
    return [(s, 0), (q, 1)]


def _unit_rays(cam):
    _, d = cam.pixel_rays()
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def test_env_background_is_the_environment_along_camera_rays():
    # gradient map L(ω) = a + b·ω (texel averages): the bilinear look-up along the camera ray equals the closed form
    # a + b·d up to the cube's bilinear interpolation error, O(1/N²) (32² faces: < 3e-3 with |b| = 0.5)
    from ibl_ref.knuth2014.pem import build_pems
    from ibl_ref.rendering.render import render_pem
    from ibl_ref.synthetic.synthetic_envs import make_env

    env = make_env("gradient", n=32)
    pems = build_pems(env, n_lights=6)
    black = render_pem(_scene(), CAM, pems, 0.5, visibility="none")
    res = render_pem(_scene(), CAM, pems, 0.5, visibility="none", background="env")
    m = res.mask
    assert 0 < m.sum() < m.size
    np.testing.assert_array_equal(res.image[m], black.image[m])  # the object is untouched
    np.testing.assert_array_equal(black.image[~m], 0.0)
    d = _unit_rays(CAM)[~m]
    want = 1.0 + d @ np.array([0.0, 0.5, 0.0])
    np.testing.assert_allclose(res.image[~m], np.repeat(want[:, None], 3, 1), atol=3e-3)
    with pytest.raises(IBLError, match="background"):
        render_pem(_scene(), CAM, pems, 0.5, visibility="none", background="grey")


def test_background_pem_mirror_lookup_equals_cube_lookup_and_modes_share_it():
    # Σ_i PEM_i(d, g = 1) is the pyramid's level-0 bilinear look-up of the full map (linearity, Sec. 3.1): equal to
    # the cube's bilinear look-up up to the PEMs' float32 storage (rel. 1e-6)
    from ibl_ref.rendering.ao_modes import render_modes
    from ibl_ref.knuth2014.pem import build_pems
    from ibl_ref.rendering.render import background_image
    from ibl_ref.synthetic.synthetic_envs import make_env

    env = make_env("sky_sun", n=16)
    pems = build_pems(env, n_lights=6)
    a, b = background_image(CAM, pems), background_image(CAM, env)
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6 * b.max())
    res = render_modes(_scene(), CAM, env, ("ours", "no-occlusion", "ao", "ao-color", "reference"), pems=pems,
                       kd=0.2, ks=0.8, g=0.5, vsm_resolution=32, background="env")
    m = res.mask
    for k, img in res.images.items():
        np.testing.assert_array_equal(img[~m], b[~m], err_msg=k)


def test_every_mode_honours_per_material_weights():
    # constant environment L ≡ 1 with normalised lobes and no occluder between the lights and the ground's top:
    # unoccluded modes give kd + ks per material exactly (float32 PEMs: 1e-5); the reference too (exact lobes)
    from ibl_ref.rendering.ao_modes import render_modes
    from ibl_ref.rendering.render import Material

    env = np.ones((6, 8, 8, 3))
    mats = {0: Material(kd=0.1, ks=0.2, g=0.3), 1: Material(kd=0.5, ks=0.4, g=0.0)}
    res = render_modes(_scene(), CAM, env, ("no-occlusion", "reference"), n_lights=6, materials=mats)
    mid = res.gbuffer.material_id
    for k in ("no-occlusion",):
        np.testing.assert_allclose(res.images[k][mid == 0], 0.3, rtol=1e-5, err_msg=k)
        np.testing.assert_allclose(res.images[k][mid == 1], 0.9, rtol=1e-5, err_msg=k)
    # the reference clips both lobes to the hemisphere of the shading normal (one-sided, docs/background.md §8),
    # so with L ≡ 1 and no occluder a pixel gets kd·H(n, 1) + ks·H(r, s) with
    # H(d, s) = (s+1)/(2π) ∫_{n·ω>0} max(d·ω, 0)^s dω, the share of the normalised lobe above the surface.
    # Brute force, independent of the renderer: a Fibonacci sphere of 2e5 points (error ~1e-4 for these
    # clipped cosine powers; the reference itself is converged to rtol 2e-3 per image, ~1e-2 per pixel).
    un = res.extras["reference-unoccluded"]
    gb = res.gbuffer
    k = np.arange(200_000) + 0.5
    z = 1 - 2 * k / k.size
    phi = np.pi * (1 + 5**0.5) * k
    w = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], axis=1)
    for mat_id, m in mats.items():
        px = mid == mat_id
        n, r = gb.normal[px], gb.reflect[px]
        s = 1.0 / (1.0 - m.g)
        up = (n @ w.T) > 0

        def share(d, s):
            return (s + 1) / (2 * np.pi) * 4 * np.pi * np.mean(np.maximum(d @ w.T, 0.0) ** s * up, axis=1)

        want = m.kd * share(n, 1.0) + m.ks * share(r, s)
        np.testing.assert_allclose(un[px].mean(axis=-1), want, atol=1e-2)
        assert np.all(un[px] <= m.kd + m.ks + 1e-9)
    assert (res.images["reference"][mid == 1].mean(axis=-1) < un[mid == 1].mean(axis=-1) - 1e-3).any()  # shadow


def test_cli_background_and_exposure(tmp_path, capsys):
    from ibl_ref.cli.cmd_render import parse_exposure

    assert parse_exposure("auto") is None and parse_exposure("-1.5") == -1.5 and parse_exposure("x0.25") == -2.0
    assert parse_exposure("4x") == 2.0
    for bad in ("x0", "bright", "nan"):
        with pytest.raises(IBLError, match="--exposure"):
            parse_exposure(bad)
    base = ["render", "--size", "24", "--lights", "6", "--vsm-res", "32", "--no-progress", "--mode", "no-occlusion"]
    for bg in ("black", "env"):
        assert main(base + ["--background", bg, "--out", str(tmp_path / f"{bg}.npz")]) == 0
    a, b = np.load(tmp_path / "black.npz"), np.load(tmp_path / "env.npz")
    m = a["mask"]
    np.testing.assert_array_equal(a["image"][m], b["image"][m])
    assert np.all(a["image"][~m] == 0) and np.all(b["image"][~m] > 0)
    assert json.loads((tmp_path / "env.json").read_text())["background"] == "env"
    # a fixed exposure is honoured (the PNG of x4 is brighter than that of x0.25)
    import matplotlib.image as mpimg

    for e in ("x4", "x0.25"):
        assert main(base + ["--exposure", e, "--out", str(tmp_path / f"{e}.exr"), "--png", str(tmp_path / f"{e}.png")]) == 0
    assert mpimg.imread(str(tmp_path / "x4.png")).mean() > mpimg.imread(str(tmp_path / "x0.25.png")).mean() + 0.05
    assert main(base + ["--exposure", "loud", "--out", str(tmp_path / "z.exr")]) == 1
    assert "--exposure" in capsys.readouterr().err


def test_default_preview_exposure_is_one_per_environment(tmp_path):
    # two methods of one scene (the paper's filter pyramid and the exact-lobe chain): different shading, the same
    # environment.  The default exposure depends on the environment only, so both PNGs get the same stops and the
    # backdrop (the same environment in both) the same pixels; per-image exposure ('image') exposes each PNG for its
    # own object (their 90th percentiles differ by 0.05 stops here) and the backdrops differ
    import matplotlib.image as mpimg

    base = ["render", "--size", "24", "--lights", "6", "--vsm-res", "32", "--no-progress"]
    png = {}
    for rule in ("auto", "image"):
        for mode in ("pyramid", "exact-lobe"):
            stem = tmp_path / f"{rule}-{mode}"
            assert main(base + ["--prefilter", mode, "--exposure", rule, "--out", f"{stem}.npz", "--png", f"{stem}.png"]) == 0
            png[rule, mode] = (mpimg.imread(f"{stem}.png"), json.loads(Path(f"{stem}.json").read_text()),
                               np.load(f"{stem}.npz")["mask"])
    (a, ja, m), (b, jb, _) = png["auto", "pyramid"], png["auto", "exact-lobe"]
    assert ja["exposure_stops"] == jb["exposure_stops"] and "per environment" in ja["exposure_rule"]
    np.testing.assert_array_equal(a[~m], b[~m])
    assert np.any(a[m] != b[m])  # the methods do differ on the object
    (c, jc, _), (d, _, _) = png["image", "pyramid"], png["image", "exact-lobe"]
    assert jc["exposure_stops"] is None and "per image" in jc["exposure_rule"]
    assert np.abs(c[~m] - d[~m]).max() > 1 / 255


def test_environment_exposure_maps_the_mean_radiance_to_the_key():
    # closed form: stops = log2(key / L̄); a uniform environment L̄ = 3 gives 2^stops · 3 = key
    from ibl_ref.rendering.tonemap import environment_exposure

    assert environment_exposure(3.0) == pytest.approx(np.log2(0.5 / 3.0), abs=1e-15)
    assert 2.0 ** environment_exposure(3.0, key=0.25) * 3.0 == pytest.approx(0.25, rel=1e-15)
    assert environment_exposure(0.0) == 0.0 and environment_exposure(float("nan")) == 0.0

