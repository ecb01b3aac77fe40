"""The normal-mapped scene (ibl_ref/rendering/scenes.py: normal_mapped_scene; ibl_ref/rendering/normal_map.py): the
map's normals are unit and tilt by at most the stated maximum; zero amplitude is the plain quad; the occlusion
pipeline's pixels carry the mapped normal and the exact reference occludes what dips below the geometric plane
(closed form for the diffuse lobe, brute-force quadrature for a Phong lobe); the horizon methods against their
formula; the occlusion zoo takes the scene; the docs' numbers are those of the saved run."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh

from ibl_ref.errors import IBLError
from ibl_ref.occlusion import OcclusionInputs, get
from ibl_ref.occlusion.image import scene_pixels
from ibl_ref.rendering.materials import PhongMaterial
from ibl_ref.rendering.normal_map import METADATA_KEY, apply_normal_maps, procedural_normal_map
from ibl_ref.rendering.raster import prepare_scene, rasterize
from ibl_ref.rendering.scenes import OCCLUSION_SCENES, normal_mapped_scene, occlusion_scene, scene_camera

ROOT = Path(__file__).resolve().parent.parent
SAVED = ROOT / "tests" / "data" / "readme_runs" / "occlusion-zoo-normal-mapped"
UP = np.array([0.0, 1.0, 0.0])


def _pixels(size=8, **params):
    meshes, camera = occlusion_scene("normal-mapped", **params)
    return scene_pixels(meshes, camera(size))


def _tilt_deg(n, n0=UP):
    return np.degrees(np.arccos(np.clip(n @ n0, -1.0, 1.0)))


@pytest.mark.parametrize("max_tilt, n_waves, seed", [(45.0, 3, 0), (10.0, 1, 3), (70.0, 5, 7), (89.0, 2, 1)])
def test_map_normals_are_unit_and_tilt_at_most_the_maximum(max_tilt, n_waves, seed):
    nm = procedural_normal_map(max_tilt, n_waves, (0.2, 0.6), seed)
    p = np.random.default_rng(seed).uniform(-3, 3, (20_000, 3)) * [1, 0, 1]
    n = nm.perturb(p, np.tile(UP, (len(p), 1)))
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-14)
    tilt = _tilt_deg(n)
    assert tilt.max() <= max_tilt + 1e-9
    if n_waves == 1:  # one wave reaches its largest slope on every crest line
        assert tilt.max() > max_tilt - 0.1
    # the normal is that of the height field's graph: its gradient against central differences
    e = 1e-6
    u, w = nm.tangent, nm.bitangent
    fd = np.stack([(nm.height(p + e * u) - nm.height(p - e * u)) / (2 * e),
                   (nm.height(p + e * w) - nm.height(p - e * w)) / (2 * e)], axis=1)
    np.testing.assert_allclose(nm.gradient(p), fd, atol=1e-7)
    np.testing.assert_allclose(np.tan(np.radians(tilt)), np.linalg.norm(fd, axis=1), atol=1e-6)
    # the frame is right-handed (t, b, n_0) and a seed gives one map
    np.testing.assert_allclose(np.cross(nm.tangent, nm.bitangent), nm.normal, atol=1e-15)
    again = procedural_normal_map(max_tilt, n_waves, (0.2, 0.6), seed)
    assert np.array_equal(again.perturb(p, np.tile(UP, (len(p), 1))), n)


def test_zero_amplitude_is_the_plain_quad():
    (flat,) = normal_mapped_scene(max_tilt_deg=0.0)
    plain = trimesh.Trimesh(flat.vertices.copy(), flat.faces.copy(), process=False)
    camera = scene_camera("normal-mapped", 12)
    a, b = scene_pixels([flat], camera), scene_pixels([plain], camera)
    for f in ("mask", "normal", "view", "position", "face_normal", "material_id"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    for f in ("normal", "reflect", "depth", "face_normal", "barycentric"):
        assert np.array_equal(getattr(a.gbuffer, f), getattr(b.gbuffer, f)), f
    sc = prepare_scene([plain])
    gb = rasterize(sc, camera)
    assert apply_normal_maps([plain], sc, gb) is gb  # no map: the G-buffer itself


def test_pixels_carry_the_mapped_normal_and_the_geometric_one():
    px = _pixels(16)
    nm = px.meshes[0].metadata[METADATA_KEY]
    np.testing.assert_array_equal(px.face_normal, np.tile(UP, (px.n_pixels, 1)))
    np.testing.assert_allclose(px.normal, nm.perturb(px.position, np.tile(UP, (px.n_pixels, 1))), atol=1e-15)
    np.testing.assert_array_equal(px.gbuffer.normal[px.mask], px.normal)  # the reference reads the G-buffer
    r = 2 * np.sum(px.normal * px.view, axis=1, keepdims=True) * px.normal - px.view
    np.testing.assert_allclose(px.gbuffer.reflect[px.mask], r, atol=1e-15)
    tilt = _tilt_deg(px.normal)
    assert tilt.max() <= 45.0 and np.median(tilt) > 10.0
    # the geometry is untouched: positions and depth are those of a plain rasterization
    plain = rasterize(px.scene, px.camera)
    assert np.array_equal(plain.position, px.gbuffer.position) and np.array_equal(plain.depth, px.gbuffer.depth)


@pytest.mark.parametrize("backend", ["exact", "embree"])
def test_the_quad_blocks_rays_from_both_sides(backend):
    from ibl_ref.rendering.raycast import ShadowRays, has_embreex

    if backend == "embree" and not has_embreex():
        pytest.skip("embreex not installed")
    (quad,) = normal_mapped_scene()
    rays = ShadowRays(prepare_scene([quad]), backend=backend)
    down = np.array([0.3, -0.5, 0.1]) / np.linalg.norm([0.3, -0.5, 0.1])
    up = -down
    p = np.array([[0.2, 0.0, -0.4]])
    # a point on the quad: a ray into the quad is blocked (the surface below its plane), a ray out of it is free
    assert rays.visibility(p, [UP], [down])[0] == 0 and rays.visibility(p, [UP], [up])[0] == 1
    # the caster itself is two-sided: from above toward the front face and from below toward the back face
    above, below = p + [0.0, 0.5, 0.0], p - [0.0, 0.5, 0.0]
    assert rays.visibility(above, [-UP], [down])[0] == 0  # (face normal -y: no below-the-plane shortcut)
    assert rays.visibility(below, [UP], [up])[0] == 0
    assert rays.visibility(below, [-UP], [down])[0] == 1 and rays.visibility(above, [UP], [up])[0] == 1


def _reference(px, material):
    from ibl_ref.rendering.reference_render import render_reference

    rr = render_reference(px.scene, px.camera, np.ones((6, 8, 8, 3)), material=material, rtol=1e-3,
                          gbuffer=px.gbuffer)
    assert rr.info["converged"]
    return rr.image[px.mask][:, 0], rr.unoccluded[px.mask][:, 0], rr.error[px.mask]


def test_gtao_reads_the_mapped_normal():
    # screen-space inputs use the G-buffer's (mapped) shading normal and the depth of the flat geometry, whose horizon
    # is the plane itself: AO ≈ (1 + cos θ)/2, where the face normal would give AO = 1
    from ibl_ref.occlusion.image import screen_space_inputs

    px = _pixels(24)
    front = np.sum(px.normal * px.view, axis=1) > 0
    exact = (1.0 + px.normal @ UP) / 2
    ao = screen_space_inputs(px, radius=0.5)[0]["ao"]
    err = np.abs(ao - exact)[front]
    assert err.mean() < 0.003 and err.mean() < 0.15 * np.mean(1.0 - exact[front])  # measured 0.0025 of 0.032


def test_reference_diffuse_is_the_tilted_sky_view_factor():
    # L = 1, kd = 1: ∫ [n·ω > 0][n_g·ω > 0] (n·ω)/π dω = (1 + cos θ)/2, θ the angle between n and n_g
    px = _pixels(8)
    img, unocc, _ = _reference(px, PhongMaterial(kd=1.0, ks=0.0, g=0.0))
    front = np.sum(px.normal * px.view, axis=1) > 0
    exact = (1.0 + px.normal @ UP) / 2
    assert np.abs(img - exact)[front].max() < 1e-3
    assert np.abs(unocc - 1.0)[front].max() < 1e-3  # without the plane the whole hemisphere of n is lit
    assert (exact[front] < 0.95).sum() >= 5  # strongly tilted pixels (θ > 26°) are in view


def _fibonacci_sphere(N):
    k = np.arange(N) + 0.5
    z = 1.0 - 2.0 * k / N
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    s = np.sqrt(1.0 - z * z)
    return np.stack([s * np.cos(phi), z, s * np.sin(phi)], axis=1)


def test_reference_glossy_lobe_loses_what_dips_below_the_geometric_plane():
    # Phong s = 10 about r = 2(n·v)n − v, L = 1: the lobe average over ω with [n·ω > 0][n_g·ω > 0], normalised over
    # the whole sphere (ibl_ref.rendering.materials.PhongLobe), by brute force on 10⁶ equal-area directions
    px = _pixels(8)
    m = PhongMaterial(kd=0.0, ks=1.0, g=0.9)
    img, unocc, bound = _reference(px, m)
    front = np.sum(px.normal * px.view, axis=1) > 0
    r = 2 * np.sum(px.normal * px.view, axis=1, keepdims=True) * px.normal - px.view
    w = _fibonacci_sphere(1_000_000)
    brute, brute_unocc = np.zeros(px.n_pixels), np.zeros(px.n_pixels)
    for i in np.flatnonzero(front):
        lobe = np.maximum(w @ r[i], 0.0) ** m.s
        above_n = (w @ px.normal[i]) > 0
        brute[i] = np.sum(lobe * above_n * (w[:, 1] > 0)) / lobe.sum()
        brute_unocc[i] = np.sum(lobe * above_n) / lobe.sum()
    err = np.abs(img - brute)[front]
    assert err.max() < 3e-3 and err.mean() < 1e-3
    assert np.abs(unocc - brute_unocc)[front].max() < 3e-3
    lost = (brute_unocc - brute)[front]
    assert lost.max() > 0.3 and (lost > 0.05).sum() >= 5  # the geometric plane takes a real share of the lobe


def test_horizon_factors_against_their_formula():
    px = _pixels(24)
    front = np.sum(px.normal * px.view, axis=1) > 0
    inp = OcclusionInputs(normal=px.normal[front], view=px.view[front], roughness=0.3,
                          geo_normal=px.face_normal[front], ao=np.ones(int(front.sum())))
    R = 2 * np.sum(inp.normal * inp.view, axis=1, keepdims=True) * inp.normal - inp.view
    below = R @ UP < 0
    assert 0.1 < below.mean() < 0.5  # the mirror direction dips below the geometric horizon on a fair share
    for name, k in (("horizon-k1.1", 1.1), ("horizon-k1.3", 1.3)):
        h2 = get(name)(inp).specular_factor
        assert np.all(h2[~below] == 1.0)
        np.testing.assert_allclose(h2[below], np.clip(1.0 + k * (R[below] @ UP), 0.0, 1.0) ** 2, rtol=1e-14)
        assert np.all(h2[below] < 1.0)
    # Godot's variant reads the shading normal: R·n = n·v > 0 on every front-facing pixel, so it never fades
    assert np.all(get("godot-horizon")(inp).specular_factor == 1.0)


def test_registered_and_framed():
    assert OCCLUSION_SCENES["normal-mapped"] is normal_mapped_scene
    px = _pixels(24)
    assert px.mask.mean() > 0.75 and np.all(px.face_normal @ UP == 1.0)
    elevation = np.degrees(np.arcsin(px.view @ UP))
    assert 10 < elevation.min() < 16 and 40 < elevation.max() < 50


def test_the_occlusion_zoo_takes_the_scene(tmp_path):
    from ibl_ref.atomic import read_csv
    from ibl_ref.experiments import occlusion_zoo as oz

    oz.run(tmp_path, quick=True, scenes=["normal-mapped"], envs=["uniform"], materials=["metal0.3"], size=10,
           methods=["none", "horizon-k1.1", "horizon-k1.3", "godot-horizon"], shadow_filters=["vsm"])
    rows = {(q["method"], q["inputs"]): q for q in read_csv(tmp_path / "occlusion_zoo.csv")}
    missing = float(rows["none", "oracle"]["rel_l1_frac"])
    assert missing > 0.05  # the plane below a tilted lobe is all the occlusion there is, and it costs
    k11, k13 = (float(rows[m, "oracle"]["given_back_frac"]) for m in ("horizon-k1.1", "horizon-k1.3"))
    assert 0 < k11 < k13 < 1  # under L = 1 the steeper fade gives back more (it still under-occludes)
    assert float(rows["godot-horizon", "oracle"]["rel_l1_frac"]) == missing


@pytest.mark.parametrize("kw, match", [
    (dict(max_tilt_deg=90.0), "max_tilt_deg"), (dict(max_tilt_deg=-1.0), "max_tilt_deg"),
    (dict(max_tilt_deg="steep"), "max_tilt_deg"), (dict(max_tilt_deg=True), "max_tilt_deg"),
    (dict(n_waves=0), "n_waves"), (dict(n_waves=2.5), "n_waves"), (dict(wavelengths=(0.5, 0.1)), "wavelengths"),
    (dict(wavelengths=0.3), "wavelengths"), (dict(wavelengths=(0.0, 1.0)), "wavelengths"),
    (dict(seed=-1), "seed"), (dict(seed=1.5), "seed"), (dict(size=0.0), "size"), (dict(size=float("inf")), "size"),
])
def test_bad_parameters_raise_in_one_line(kw, match):
    with pytest.raises(IBLError, match=match) as exc:
        normal_mapped_scene(**kw)
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize("kw, match", [(dict(tangent=(0, 1, 0)), "tangent"), (dict(normal=(0, 0, 0)), "normal"),
                                       (dict(origin=(0, float("nan"), 0)), "origin")])
def test_bad_frames_raise_in_one_line(kw, match):
    with pytest.raises(IBLError, match=match) as exc:
        procedural_normal_map(**kw)
    assert "\n" not in str(exc.value)


# ---- the saved run and the section of docs/occlusion.md that quotes it ----------------------------------------------
def _section() -> str:
    text = (ROOT / "docs" / "occlusion.md").read_text(encoding="utf-8")
    start = text.index("## Horizon occlusion on a normal-mapped surface")
    return text[start:text.index("\n## ", start + 1)]


def _flat(text: str) -> str:
    return " ".join(text.split())


def _pc(x: float, sign: bool = False) -> str:
    return (f"{100 * x:+.1f}" if sign else f"{100 * x:.1f}").replace("-", "−")


def test_the_docs_section_quotes_the_saved_run():
    from ibl_ref.atomic import read_csv

    run = json.loads((SAVED / "run.json").read_text(encoding="utf-8"))["runs"][0]
    meta = json.loads((SAVED / "occlusion_zoo_meta.json").read_text(encoding="utf-8"))
    rows = read_csv(SAVED / "occlusion_zoo.csv")
    section = _section()
    flat = _flat(section)

    # the command quoted is the run's, and the run's settings are that command's
    command = _flat(re.search(r"\n    (IBL_REF_PROBE_DIR=.*?--out \S+)", section, re.S).group(1).replace("\\\n", " "))
    assert command == run["command"]
    st = meta["settings"]
    for flag in ("scenes", "envs", "materials", "methods"):
        assert f"--{flag} {','.join(st[flag])}" in command
    assert meta["scenes_run"] == ["normal-mapped"] and not meta["skipped"]
    wall = re.match(r"([\d.]+) min, one process", run["wall"]).group(1)
    assert f"wall time of {wall} min on one process" in flat and float(wall) * 60 >= meta["total_time_s"]
    start, end = re.match(r"([\d.]+) at the start, ([\d.]+) at the end", run["load"]).groups()
    assert f"{float(start):.1f} at the start and {float(end):.1f} at the end" in flat
    assert f"{meta['n_pixels']['normal-mapped']} pixels at {st['size']}²" in flat
    assert f"environment faces of {st['env_size']}²" in flat

    def q(env, mat, method, col="rel_l1_frac", kind="oracle"):
        (row,) = [r for r in rows if (r["env"], r["material"], r["method"], r["inputs"]) == (env, mat, method, kind)]
        return float(row[col])

    # the table, row by row
    cases = [(e, m) for e in st["envs"] for m in st["materials"]]
    for env, mat in cases:
        cells = [f"{100 * q(env, mat, m):.1f} ({100 * q(env, mat, m, 'bias_frac'):+.1f})"
                 for m in ("none", "horizon-k1.1", "horizon-k1.3")]
        closer = "k = 1.1" if q(env, mat, "horizon-k1.1") < q(env, mat, "horizon-k1.3") else "k = 1.3"
        gb = f"{100 * q(env, mat, 'horizon-k1.3', 'given_back_frac'):.0f}"
        assert f"| {env} | {mat} | " + " | ".join(cells) + f" | {closer} | {gb} |" in section, (env, mat)

    # which k: the disagreement row of the run
    (dis,) = [r for r in read_csv(SAVED / "occlusion_zoo_disagreements.csv")
              if (r["method_a"], r["method_b"], r["inputs"]) == ("horizon-k1.1", "horizon-k1.3", "oracle")]
    assert dis["closer"] == "horizon-k1.3" and int(dis["n_cases"]) == len(cases)
    assert f"**{dis['b_closer_cases']} of the {dis['n_cases']}** cases" in flat
    assert (f"mean rel. L1 {_pc(float(dis['mean_rel_l1_b_frac']))} % against "
            f"{_pc(float(dis['mean_rel_l1_a_frac']))} % for k = 1.1") in flat
    env, mat = dis["worst_case"].split("/")[1:]
    assert (f"largest gap is {_pc(-float(dis['worst_case_gap_frac']))} points, at {env}/{mat} "
            f"({_pc(q(env, mat, 'horizon-k1.3'))} % against {_pc(q(env, mat, 'horizon-k1.1'))} %)") in flat
    assert (f"no occlusion errs by {_pc(q('courtyard', 'metal0.1', 'none'))} % on metal0.1 and k = 1.3 still by "
            f"{_pc(q('courtyard', 'metal0.1', 'horizon-k1.3'))} % "
            f"({100 * q('courtyard', 'metal0.1', 'horizon-k1.3', 'given_back_frac'):.0f} % given back)") in flat

    # where it breaks
    assert (f"{_pc(q('sky_sun', 'metal0.6', 'none'))} % without occlusion, "
            f"{_pc(q('sky_sun', 'metal0.6', 'horizon-k1.1'))} % with k = 1.1 and "
            f"{_pc(q('sky_sun', 'metal0.6', 'horizon-k1.3'))} % with k = 1.3, biased dark "
            f"({_pc(q('sky_sun', 'metal0.6', 'horizon-k1.1', 'bias_frac'))} %, "
            f"{_pc(q('sky_sun', 'metal0.6', 'horizon-k1.3', 'bias_frac'))} %)") in flat
    k11 = [(e, m) for e, m in cases if q(e, m, "horizon-k1.1") < q(e, m, "horizon-k1.3")]
    assert len(k11) == int(dis["a_closer_cases"]) == 4 and {e for e, _ in k11} == {"sky_sun"}
    assert f"all four cases it wins (sky_sun: {', '.join(m for _, m in k11)})" in flat
    assert f"gtso-exact-alpha: {_pc(q('courtyard', 'metal0.1', 'gtso-exact-alpha'))} % at courtyard/metal0.1" in flat
    assert f"({_pc(q('sky_sun', 'metal0.6', 'gtso-exact-alpha'))} % at sky_sun/metal0.6)" in flat

    # Godot's variant is ao-diffuse, case by case and input kind by input kind
    for env, mat in cases:
        for kind in ("oracle", "screen-space"):
            assert q(env, mat, "godot-horizon", kind=kind) == q(env, mat, "ao-diffuse", kind=kind)
    assert f"its image is ao-diffuse's in all {len(cases)} cases" in flat

    # dielectrics
    assert (f"ao-diffuse {_pc(q('sky_sun', 'dielectric0.1', 'ao-diffuse'))} % against "
            f"{_pc(q('sky_sun', 'dielectric0.1', 'none'))} % without occlusion at dielectric0.1") in flat
    assert (f"takes dielectric0.1 from {_pc(q('courtyard', 'dielectric0.1', 'none'))} % to "
            f"{_pc(q('courtyard', 'dielectric0.1', 'horizon-k1.3'))} % (k = 1.3)") in flat

    # with GTAO's inputs the metals' horizon rows are the oracle's
    for env, mat in cases:
        if mat.startswith("metal"):
            for m in ("horizon-k1.1", "horizon-k1.3"):
                assert q(env, mat, m, kind="screen-space") == q(env, mat, m)


def test_the_readme_row_quotes_the_saved_run():
    from ibl_ref.atomic import read_csv

    row = next(ln for ln in (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
               if "occlusion-zoo-normal-mapped.md" in ln)
    rows = read_csv(SAVED / "occlusion_zoo.csv")

    def q(env, mat, method):
        (r,) = [r for r in rows if (r["env"], r["material"], r["method"], r["inputs"]) == (env, mat, method, "oracle")]
        return float(r["rel_l1_frac"])

    (dis,) = [r for r in read_csv(SAVED / "occlusion_zoo_disagreements.csv")
              if (r["method_a"], r["method_b"], r["inputs"]) == ("horizon-k1.1", "horizon-k1.3", "oracle")]
    assert f"**{dis['b_closer_cases']} of the {dis['n_cases']}** cases" in row
    assert (f"no occlusion **{_pc(q('courtyard', 'metal0.1', 'none'))} %**, k = 1.3 "
            f"{_pc(q('courtyard', 'metal0.1', 'horizon-k1.3'))} % on metal 0.1") in row
    assert (f"({_pc(q('sky_sun', 'metal0.6', 'none'))} % → **{_pc(q('sky_sun', 'metal0.6', 'horizon-k1.3'))} %**)"
            in row)


def test_the_renderers_shade_a_mapped_mesh_with_its_map():
    # render_reference and render_pem rasterise the scene themselves: a mesh that carries a normal map is shaded with
    # the mapped normals (before, both silently shaded the geometric one).  Reference: diffuse, L = 1, the closed
    # form (1 + n·n_g)/2 of test_reference_diffuse_is_the_tilted_sky_view_factor, to its rtol.
    from ibl_ref.rendering.reference_render import render_reference
    from ibl_ref.rendering.render import render_pem
    from ibl_ref.prefilter import build_region_prefilters

    meshes, camera = occlusion_scene("normal-mapped")
    cam = camera(8)
    res = render_reference(meshes, cam, np.ones((6, 8, 8, 3)), material=(1.0, 0.0, 0.0), rtol=1e-3)
    mapped = apply_normal_maps(meshes, prepare_scene(meshes), rasterize(prepare_scene(meshes), cam))
    m = res.mask
    n = mapped.normal[m]
    front = np.sum(n * mapped.view[m], axis=1) > 0
    exact = (1.0 + n @ UP) / 2
    assert np.abs(res.image[m][:, 0] - exact)[front].max() < 2e-3
    assert (exact[front] < 0.95).sum() >= 5  # the map tilts: the geometric normal would give 1 everywhere
    np.testing.assert_array_equal(res.gbuffer.normal, mapped.normal)
    pems = build_region_prefilters(np.ones((6, 8, 8, 3)), method="pyramid", n_lights=6)
    out = render_pem(meshes, cam, pems, glossiness=0.5, visibility="none")
    np.testing.assert_array_equal(out.gbuffer.normal, mapped.normal)
    np.testing.assert_array_equal(out.gbuffer.reflect, mapped.reflect)


def test_mitsuba_refuses_a_mapped_mesh_in_one_line():
    # the maps are procedural and not handed to Mitsuba: its image would be another scene's, so it is refused before
    # Mitsuba is loaded (no Mitsuba needed for this test)  # runs without Mitsuba
    from ibl_ref.rendering.mitsuba_render import render_mitsuba

    meshes, camera = occlusion_scene("normal-mapped")
    with pytest.raises(IBLError, match=r"^mesh 0 carries a normal map .*not supported[^\n]*$"):
        render_mitsuba(meshes, camera(4), np.ones((6, 8, 8, 3)), spp=2)
