"""Issue 42: the image of one occlusion method (:func:`ibl_ref.occlusion.image.occlusion_image`) and ``ibl-ref
render --occlusion METHOD``.

Independent expectations:

* the method ``none`` is the unoccluded image, which the converged reference renderer computes by its own
  quadrature (:func:`ibl_ref.rendering.reference_render.reference_shading`, its unoccluded output): the two agree
  within their tolerances;
* the paper's per-region method with **one region per environment texel** and the oracle's visibility cells equal
  to the texels is Σ_t VIS_t kd A_1,t, where the per-texel diffuse terms have a closed form (Lambert's polygon
  formula, ``_texel_first_moments`` of ``tests/test_occlusion_exact_regions.py``; every texel lies wholly above or
  below the crevice's axis-aligned normals at an even face size): the library's integrals must agree within their
  stated error, on a view where the visibility takes away a real share of the light;
* a constant environment L ≡ 1 makes the unoccluded diffuse term kd exactly (normalised lobes), so AO on the
  diffuse term gives kd·ao per pixel, one kd per material of the scene;
* ``reads_roughness`` is what the formulas do: a method declared not to read the roughness gives the same result
  at two roughnesses, every other one does not.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_occlusion_exact_regions import _texel_first_moments

from ibl_ref.cli import main
from ibl_ref.occlusion import (
    OCCLUSION_METHODS,
    OcclusionInputs,
    OcclusionRequestError,
    occlusion_image,
)
from ibl_ref.occlusion.image import check_request
from ibl_ref.rendering.materials import PhongMaterial
from ibl_ref.rendering.scenes import occlusion_scene
from ibl_ref.synthetic.synthetic_envs import make_env

N = 4  # environment face size = the oracle's cell face size: one texel per cell


@pytest.fixture(scope="module")
def crevice():
    meshes, camera = occlusion_scene("crevice")
    return meshes, camera(8), make_env("sky_sun", n=N)


def test_no_occlusion_is_the_reference_renderers_unoccluded_image(crevice):
    from ibl_ref.rendering.materials import as_material
    from ibl_ref.rendering.raster import prepare_scene, rasterize
    from ibl_ref.rendering.reference_render import reference_shading

    meshes, cam, cube = crevice
    mat = "ggx:roughness=0.3,f0=0.04,kd=0.5"  # both terms: the diffuse lobe and GGX
    res = occlusion_image(meshes, cam, cube, mat, "none", rtol=1e-2, n_face=N)
    assert np.array_equal(res.image, res.unoccluded)
    assert res.info["method"]["name"] == "none" and set(res.timings) == {"inputs_s", "terms_s", "method_s", "total_s"}
    sc = prepare_scene(meshes, warn=False)
    gb = rasterize(sc, cam)
    m = gb.mask
    assert np.array_equal(m, res.mask) and m.sum() > 30
    _occ, un, _em, _eb, _info = reference_shading(sc, gb.position[m], gb.normal[m], gb.face_normal[m], gb.view[m],
                                                  cube, as_material(mat), rtol=1e-2)
    rel = np.abs(res.image[m] - un).sum() / un.sum()
    assert rel < 1e-2 + 1e-2  # the two estimated errors (measured 1.1e-4)


def test_one_region_per_texel_is_the_closed_form_sum_over_texels(crevice):
    meshes, cam, cube = crevice
    kd, rtol = 0.8, 3e-2
    res = occlusion_image(meshes, cam, cube, (kd, 0.0, 0.0), "regions-exact", regions=np.arange(6 * N * N).reshape(
        6, N, N), n_face=N, rtol=rtol)
    vis, n = res.inputs["region_visibility"], res.inputs["normal"]
    assert vis.shape == (res.mask.sum(), 6 * N * N) and res.info["regions"]["n_regions"] == 6 * N * N
    G = np.clip(n @ _texel_first_moments(N).T / np.pi, 0.0, None)  # closed-form A_1 per unit radiance of each texel
    expected = kd * np.einsum("pt,pt,tc->pc", vis, G, cube.reshape(-1, 3))
    img = res.image[res.mask]
    # within the integrals' stated error (measured 9e-4 rel. L1 at this rtol; 6e-5 at rtol 1e-3)
    assert np.abs(img - expected).sum() / expected.sum() <= res.info["terms_err_rel_l1_max"]
    assert np.all(np.abs(img - expected) <= rtol * expected + 1e-12)
    # not a trivial agreement: the visibility takes away a real share of the light (12 % here)
    assert expected.sum() < 0.95 * res.unoccluded[res.mask].sum()


def test_reads_roughness_declares_what_the_formula_reads():
    rng = np.random.default_rng(1)
    P = 64

    def unit(a):
        return a / np.linalg.norm(a, axis=1, keepdims=True)

    n = unit(rng.normal(size=(P, 3)) + [0.0, 0.0, 2.0])
    v = unit(rng.normal(size=(P, 3)) + [0.0, 0.0, 1.0])
    fields = {"geo_normal": unit(n + 0.2 * rng.normal(size=(P, 3))), "ao": rng.uniform(0.05, 1.0, P),
              "bent_normal": unit(n + 0.5 * rng.normal(size=(P, 3))), "albedo": np.array([0.2, 0.5, 0.8]),
              "region_visibility": rng.uniform(size=(P, 6)), "sh_transfer": rng.normal(size=(P, 25)),
              "env_sh": rng.normal(size=(25, 3)), "sh_transfer_matrix": rng.normal(size=(P, 25, 25))}
    for name, meth in OCCLUSION_METHODS.items():
        out = []
        for r in (0.15, 0.7):
            res = meth(OcclusionInputs(normal=n, view=v, roughness=r, **fields))
            out.append([getattr(res, f) for f in ("diffuse_factor", "specular_factor", "region_weights",
                                                   "diffuse_radiance", "specular_radiance")])
        same = all((a is None and b is None) or np.array_equal(a, b) for a, b in zip(*out))
        assert same == (not meth.reads_roughness), name


def test_requests_a_method_cannot_serve_are_refused():
    with pytest.raises(OcclusionRequestError, match="unknown occlusion method 'gtao'"):
        check_request("gtao", "ggx:0.3")
    with pytest.raises(OcclusionRequestError, match="screen-space inputs .* do not estimate"):
        check_request("prt-5", "ggx:0.3", "screen-space")
    with pytest.raises(OcclusionRequestError, match="Phong glossy lobe"):
        check_request("gtso-exact-alpha", (0.0, 1.0, 0.8))
    # reads no roughness: served, as the one material type
    assert check_request("horizon-k1.3", (0.0, 1.0, 0.8))[1][None] == PhongMaterial(0.0, 1.0, 0.8)
    with pytest.raises(OcclusionRequestError, match="material 1"):
        check_request("ao-both", {0: "ggx:0.3", 1: (0.5, 0.5, 1.0)})  # the mirror has no finite Phong lobe


# ---- the command line -------------------------------------------------------------------------------------------------
TINY = ["--size", "12", "--env-size", "8", "--ref-rtol", "1e-2", "--no-progress"]


def test_cli_oracle_inputs_write_the_image_and_its_inputs(tmp_path, capsys):
    out, png = tmp_path / "o.npz", tmp_path / "o.png"
    rc = main(["render", "--occlusion", "ao-diffuse", "--synthetic", "constant", "--material", "0.8,0,0",
               "--ground-material", "0.5,0,0", *TINY, "--out", str(out), "--png", str(png)])
    assert rc == 0, capsys.readouterr().err
    d = np.load(out)
    m, ao, un, img = d["mask"], d["input_ao"], d["unoccluded"], d["image"]
    assert img.shape == (12, 12, 3) and m.sum() > 50 and ao[m].min() < 0.9  # the teapot shades the ground
    # L = 1: the unoccluded diffuse term is kd (0.8 on the teapot, 0.5 on the ground), the image kd * ao
    kd = un[m].mean(axis=1)
    assert np.all(np.isclose(kd, 0.8, rtol=1e-2) | np.isclose(kd, 0.5, rtol=1e-2))
    assert np.any(np.isclose(kd, 0.8, rtol=1e-2)) and np.any(np.isclose(kd, 0.5, rtol=1e-2))
    np.testing.assert_allclose(img[m], un[m] * ao[m][:, None], rtol=1e-12)
    info = json.loads((tmp_path / "o.json").read_text())
    assert info["mode"] == "occlusion" and info["occlusion"]["method"]["name"] == "ao-diffuse"
    assert info["occlusion"]["inputs"] == "oracle" and info["occlusion"]["input_info"]["n_face"] == 8
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_reports_each_step_of_a_long_render(tmp_path, capsys, monkeypatch):
    # progress lines (not a bar: stderr is captured): the inputs, then the unoccluded integrals of each material
    monkeypatch.setenv("IBL_REF_PROGRESS", "lines")
    rc = main(["render", "--occlusion", "ao-diffuse", "--synthetic", "constant", "--material", "0.8,0,0",
               "--ground-material", "0.5,0,0", *[a for a in TINY if a != "--no-progress"],
               "--out", str(tmp_path / "o.npz")])
    err = capsys.readouterr().err
    assert rc == 0, err
    lines = [ln for ln in err.splitlines() if ln.startswith(("oracle inputs", "unoccluded integrals"))]
    assert lines[0].startswith("oracle inputs (") and lines[0].endswith("…")
    assert any(ln.startswith("oracle inputs") and ": done in" in ln for ln in lines)
    for k in (1, 2):
        assert any(ln.startswith(f"unoccluded integrals, material {k} of 2 (phong") for ln in lines), lines


def test_cli_screen_space_inputs_write_an_exr(tmp_path, capsys):
    out = tmp_path / "s.exr"
    rc = main(["render", "--occlusion", "lagarde2014-alpha", "--occlusion-inputs", "screen-space", "--material",
               "ggx:0.3", "--ground-material", "ggx:roughness=0.6,kd=0.5", *TINY, "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    from ibl_ref.rendering.image_io import read_image_exr

    img = np.asarray(read_image_exr(out))
    assert img.shape[:2] == (12, 12) and np.all(np.isfinite(img)) and np.all(img >= 0) and img.max() > 0
    info = json.loads((tmp_path / "s.json").read_text())
    assert info["occlusion"]["inputs"] == "screen-space" and info["occlusion"]["input_info"]["radius"] == 0.5
    assert info["occlusion"]["materials"]["0"]["kind"] == "ggx"


@pytest.mark.parametrize("flags, match", [
    (["--occlusion", "gtao"], "unknown occlusion method 'gtao'"),
    (["--occlusion", "gtso-exact-alpha"], "cannot shade --material .* Phong glossy lobe"),
    (["--occlusion", "ao-both", "--material", "ggx:0.3", "--ground-material", "0.2,0.3,0.2,0.5,0.5,0.5,0.4"],
     "cannot shade --ground-material: .*RGB"),
    (["--occlusion", "ao-both", "--mode", "ao"], "does not combine with --mode ao"),
    (["--occlusion", "prt-5", "--occlusion-inputs", "screen-space"], "screen-space inputs"),
    (["--occlusion-inputs", "oracle"], "only apply to --occlusion"),
])
def test_cli_refuses_in_one_line_and_writes_nothing(tmp_path, capsys, flags, match):
    import re

    out = tmp_path / "x.exr"
    rc = main(["render", *flags, *TINY, "--out", str(out), "--png", str(tmp_path / "x.png")])
    err = capsys.readouterr().err
    assert rc == 1 and len(err.strip().splitlines()) == 1 and re.search(match, err), err
    assert list(tmp_path.iterdir()) == []
