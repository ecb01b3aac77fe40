"""The occlusion zoo: the self-shadowing that engines ship for image-based lighting, judged against exact visibility
term by term.

A prefiltered look-up cannot see the visibility V(ω) of a surface point; engines stand in for it with a factor, a
cone or a transfer.  Each method of :data:`ibl_ref.occlusion.OCCLUSION_METHODS` (AO on diffuse / on both terms,
multi-bounce AO, specular occlusion from AO after Lagarde & de Rousiers 2014 fed α or r and Unreal's variant,
horizon occlusion (Marmoset; Godot), cone–cone GTSO (Jimenez et al. 2016) with the Oat–Sander smoothstep or the
exact cap intersection, PRT diffuse transfer (Sloan et al. 2002, orders 3 and 5), and the paper's per-region
visibility made exact (Knuth et al. 2014, Eq. 5) at several region counts) is applied to the **exact** unoccluded
terms of the material — the lab's converged integrals A_1(n) and the GGX term (V ≡ 1,
:func:`ibl_ref.rendering.unoccluded_reference.integrate`; per region for the region methods) — so the only error
left is the occlusion model's, and, with screen-space inputs, the estimator's:

* **oracle inputs** (:mod:`ibl_ref.occlusion.oracle_inputs`): cosine-weighted AO, the bent normal, SH visibility
  transfer and per-region visible fractions from one stratified ray-cast visibility set per (scene, view) and job,
  shared by every material and method of the job (a job is one scene under one environment; tracing takes about a
  second at these sizes), each with its error estimate;
* **screen-space inputs** (:mod:`ibl_ref.occlusion.gtao`): AO and bent normals by GTAO's horizon search in the
  rasterizer's depth buffer (Jimenez et al. 2016), the way engines get them.  Methods that need more than AO and
  the bent normal have no screen-space row.

The reference is the converged renderer with exact visibility
(:func:`ibl_ref.rendering.reference_render.render_reference`, direct lighting only — it has no interreflections, so
multi-bounce AO, which models them, is judged against a reference without them and its brightening counts as
error).  Per (scene, environment, material, method, inputs): rel. L1 Σ|I − I_ref| / Σ I_ref, the signed bias,
the 99th percentile of the per-pixel relative error (relative to max(I_ref, 10 % of the mean)) and **the share of
the missing-visibility error the method gives back**, 1 − rel. L1(method) / rel. L1(no occlusion) (0 % = no
occlusion, 100 % = exact; negative = worse than none), with the cost: the input's time (the shared ray-cast set or
GTAO, per pixel), the method's own time per pixel and the bytes per pixel of the inputs it reads (float32 each).
The budget walk of each method: no occlusion → the method with oracle inputs (the occlusion model's step) → with
screen-space inputs (the estimator's step); the prefilter step is zero here by construction (exact terms).

Scenes (:data:`ibl_ref.rendering.scenes.OCCLUSION_SCENES`): the teapot on the ground, a crevice and a bumpy
cluster; on request (``--scenes normal-mapped``, not in the default list) a flat quad with a procedural normal map
(:func:`ibl_ref.rendering.scenes.normal_mapped_scene`), whose only occluder is the surface's own geometric horizon:
the case horizon occlusion was made for.  Materials (:data:`MATERIALS`): diffuse (kd = 0.8), metals (GGX, F0 = 1)
and dielectrics (GGX, F0 = 0.04, kd = 0.5) at roughness 0.1 / 0.3 / 0.6.  Environments: the synthetic sky with a small sun and the four probes
(:func:`ibl_ref.experiments.method_zoo.environment`).

The engines' disagreements (:data:`DISAGREEMENTS`: α vs r in Lagarde's formula and in the GTSO aperture, smoothstep
vs exact cap intersection, the horizon constant, Filament's fade, multi-bounce vs plain AO) are summarised from the
rows: which choice is closer to the reference, by how much, and the case where it breaks.

Files: ``occlusion_zoo.csv``, ``occlusion_zoo_budget.csv``, ``occlusion_zoo_disagreements.csv``,
``occlusion_zoo_meta.json``, ``occlusion_zoo_table.md``, ``occlusion_zoo_images.npz``; plots (reading only those):
``occlusion_zoo_pareto_MATERIAL.png`` and ``occlusion_zoo_images_SCENE.png``.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from ..atomic import atomic_write, read_csv, write_csv, write_json, write_npz
from ..errors import IBLError
from ..executors import map_jobs
from ..figures import plain_log_ticks, pyplot, save_figure
from ..occlusion.image import DEFAULT_GTAO_RADIUS, INPUT_KINDS, SH_ORDER
from ..progress import track
from ..rendering.materials import GGXMaterial, PhongMaterial
from . import params_from_settings, power_of_two, settings_with
from .method_zoo import ENVS as _ZOO_ENVS
from .method_zoo import P99_FLOOR, _metrics, plot_image_rows, probe_dir
from .method_zoo import environment as _zoo_environment

NAME = "occlusion-zoo"
DESCRIPTION = ("occlusion methods engines ship (AO, multi-bounce, specular occlusion, horizon, GTSO cones, PRT, "
               "per-region visibility) with oracle and screen-space (GTAO) inputs vs exact visibility")
PAPER = ("Knuth et al. 2014 (self-shadowing, Eq. 5) against Lagarde & de Rousiers 2014, Jimenez et al. 2016 (GTAO, "
         "GTSO, multi-bounce), Marmoset 2014 horizon occlusion, Sloan et al. 2002 (PRT)")
IN_QUICK_REPRODUCE = True
RUNTIME = {"quick": "15 s (load 2)", "full": "measured in the saved run's meta (total_time_s)"}
OUTPUTS = ("occlusion_zoo.csv", "occlusion_zoo_budget.csv", "occlusion_zoo_disagreements.csv",
           "occlusion_zoo_meta.json", "occlusion_zoo_table.md", "occlusion_zoo_images.npz",
           "occlusion_zoo_pareto_MATERIAL.png", "occlusion_zoo_images_SCENE.png")

#: environments: the method zoo's and ``uniform`` (L ≡ 1: AO on a diffuse material is then exact, a check)
ENVS = _ZOO_ENVS + ("uniform",)
#: the estimated input kind of the per-region methods: shadow maps of the region lights with a filter
SHADOW_KIND = "shadow-map:"
#: GTAO's search radius per scene (world units), set to each scene's occluders as an engine would tune it: half the
#: teapot's height, twice the crevice's depth, about twice the bumps' radius, and for the normal-mapped quad, whose
#: only occluder is its own plane (found at any radius), the default (0.5 for a scene added elsewhere too)
GTAO_RADIUS = {"teapot": 1.5, "crevice": 1.0, "bumpy": 0.3, "normal-mapped": DEFAULT_GTAO_RADIUS}
DIFFUSE_KD = 0.8
DIELECTRIC_KD = 0.5


#: material name → material
MATERIALS = {"diffuse": PhongMaterial(kd=DIFFUSE_KD, ks=0.0, g=0.0),
             **{f"metal{r}": GGXMaterial(roughness=r, f0=1.0, kd=0.0) for r in (0.1, 0.3, 0.6)},
             **{f"dielectric{r}": GGXMaterial(roughness=r, f0=0.04, kd=DIELECTRIC_KD) for r in (0.1, 0.3, 0.6)}}

#: (method a, method b, what the choice is): the engines' disagreements the table settles
DISAGREEMENTS = (
    ("lagarde2014-alpha", "lagarde2014-r", "Lagarde's specular occlusion fed alpha (Filament, HDRP, Bevy) or r "
                                           "(three.js)"),
    ("lagarde2014-alpha", "unreal-so", "Frostbite's exponent or Unreal's"),
    ("gtso-smoothstep-alpha", "gtso-smoothstep-r", "GTSO aperture from alpha (Filament) or r (Unity)"),
    ("gtso-exact-alpha", "gtso-smoothstep-alpha", "exact cap intersection or Oat-Sander's smoothstep"),
    ("horizon-k1.1", "horizon-k1.3", "horizon fade constant k = 1.1 (Babylon) or 1.3 (Substance)"),
    ("horizon-k1.3", "godot-horizon", "Marmoset's horizon on the geometric normal or Godot's variant"),
    ("gtso-smoothstep-alpha", "filament-gtso", "GTSO without or with Filament's fade below alpha 0.01-0.09"),
    ("ao-diffuse", "multibounce-ao", "plain AO or Jimenez's multi-bounce AO on the diffuse term"),
    ("ao-diffuse", "ao-both", "AO on the diffuse term only or on both terms"),
)

COLUMNS = ["scene", "env", "material", "method", "inputs", "applicable", "rel_l1_frac", "p99_rel_error_frac",
           "bias_frac", "given_back_frac", "missing_visibility_rel_l1_frac", "input_time_per_pixel_s",
           "method_time_per_pixel_s", "input_bytes_per_pixel", "ref_err_rel_l1_frac", "n_pixels"]
BUDGET_COLUMNS = ["scene", "env", "material", "method", "inputs", "step_index", "step", "rel_l1_increment_frac",
                  "bias_increment_frac", "rel_l1_vs_ref_frac", "bias_vs_ref_frac"]
DISAGREEMENT_COLUMNS = ["method_a", "method_b", "choice", "inputs", "n_cases", "mean_rel_l1_a_frac",
                        "mean_rel_l1_b_frac", "a_closer_cases", "b_closer_cases", "closer", "mean_gap_frac",
                        "worst_case", "worst_case_gap_frac"]


def settings(quick: bool) -> dict:
    from ..occlusion import OCCLUSION_METHODS
    from ..occlusion.shadow_filters import SHADOW_FILTERS

    if quick:
        return dict(scenes=["crevice"], envs=["sky_sun"], materials=["diffuse", "metal0.3", "dielectric0.1"],
                    methods=list(OCCLUSION_METHODS), n_regions=[6], size=12, env_size=8, rtol=4e-3, ref_rtol=1e-2,
                    n_face=8, n_sets=2, gtao_radius_scale=1.0, shadow_filters=["pcf", "vsm", "msm"], shadow_resolution=64,
                    figure_env="sky_sun", probe_dir="")
    return dict(scenes=["teapot", "crevice", "bumpy"], envs=list(_ZOO_ENVS), materials=list(MATERIALS),
                methods=list(OCCLUSION_METHODS), n_regions=[6], size=24, env_size=32, rtol=2e-3,
                ref_rtol=2e-3, n_face=16, n_sets=4, gtao_radius_scale=1.0, shadow_filters=list(SHADOW_FILTERS),
                shadow_resolution=256, figure_env="sky_sun", probe_dir="")


PARAMS = params_from_settings(settings, {
    "scenes": "scenes: teapot, crevice, bumpy, normal-mapped (a flat quad with a normal map; not in the default "
              "list)",
    "envs": "environments: sky_sun, the probes city, courtyard, forest, studio, and uniform (L = 1)",
    "materials": "materials: " + ", ".join(MATERIALS), "methods": "occlusion methods (ibl_ref.occlusion registry)",
    "n_regions": "region counts of the per-region methods (median cut; the env face size must be a multiple of "
                 "--n-face)",
    "size": "image width = height (pixels)",
    "rtol": "tolerance of the exact unoccluded integrals (estimated rel. L1)",
    "ref_rtol": "tolerance of the converged reference", "n_face": "face size of the oracle visibility cells",
    "n_sets": "independent stratified visibility sets (their spread is the oracle inputs' error estimate)",
    "gtao_radius_scale": "GTAO search radius as a multiple of each scene's radius (GTAO_RADIUS)",
    "shadow_filters": "shadow-map filters estimating the per-region visibility (pcf, vsm, esm, evsm, msm)",
    "shadow_resolution": "shadow-map size (texels) of the region lights",
    "figure_env": "environment of the image figure",
    "probe_dir": "folder of the probe EXRs (default $IBL_REF_PROBE_DIR or ../shared/probes beside the project)"},
    checks={"env_size": power_of_two})


# ------------------------------------------------------------------------------------------------------------------
# materials, methods and their inputs
# ------------------------------------------------------------------------------------------------------------------
def material(name: str):
    """The material of :data:`MATERIALS` entry ``name`` (a ``PhongMaterial`` or ``GGXMaterial``)."""

    if name not in MATERIALS:
        raise IBLError(f"unknown material {name!r}; choose from {', '.join(MATERIALS)}")
    return MATERIALS[name]


def method_labels(methods, n_regions) -> list:
    """Row labels: every method, the per-region ones once per region count (``regions-exact-24``)."""
    from ..occlusion import get

    out = []
    for name in methods:
        meth = get(name)
        if "region_visibility" in meth.needs:
            out += [f"{name}-{int(r)}" for r in n_regions]
        else:
            out.append(name)
    return out


def _split_label(label: str):
    """``(registry name, region count or None)`` of a row label."""
    from ..occlusion import OCCLUSION_METHODS

    if label in OCCLUSION_METHODS:
        return label, None
    base, _, r = label.rpartition("-")
    return base, int(r)


def input_kinds(method, shadow_filters=()) -> tuple:
    """The input kinds a method can be fed: those of :func:`ibl_ref.occlusion.image.input_kinds` (``oracle``
    always; ``screen-space`` when it reads nothing GTAO does not estimate), and ``shadow-map:FILTER``
    (:data:`ibl_ref.occlusion.shadow_filters.SHADOW_FILTERS`) when it reads the per-region visibility, which the
    paper estimates with shadow maps of the region lights."""
    from ..occlusion.image import input_kinds as kinds

    if "region_visibility" in method.needs:
        return kinds(method) + tuple(SHADOW_KIND + f for f in shadow_filters)
    return kinds(method)


def _nbytes_per_pixel(method, n_regions) -> int:
    """Bytes per pixel of the inputs a method reads beyond the G-buffer, stored as float32 (an engine's layout)."""
    size = {"ao": 1, "bent_normal": 3, "sh_transfer": 25, "sh_transfer_matrix": 625,
            "region_visibility": n_regions or 0}
    sh_order = method.params.get("order")
    if sh_order:
        size["sh_transfer"] = int(sh_order) ** 2
        size["sh_transfer_matrix"] = int(sh_order) ** 4  # order 5: 625 floats, 2500 bytes
    return 4 * sum(size.get(f, 0) for f in method.needs)


# ------------------------------------------------------------------------------------------------------------------
# one job (a scene under its environments): the visibility traced once, then every material and method
# ------------------------------------------------------------------------------------------------------------------
def environment(name: str, n: int, folder: str = ""):
    """``(cube (6, n, n, 3), None)`` or ``(None, reason)`` of an environment of :data:`ENVS`."""
    if name == "uniform":
        return np.ones((6, n, n, 3)), None
    return _zoo_environment(name, n, folder)


def _scene_pixels(scene: str, size: int):
    from ..occlusion.image import scene_pixels
    from ..rendering.scenes import occlusion_scene

    meshes, camera = occlusion_scene(scene)
    return scene_pixels(meshes, camera(size))


def _reference(px, cube, m, job):
    from ..rendering.reference_render import render_reference

    mats = {int(i): m for i in np.unique(px.scene.material_id)}
    rr = render_reference(px.scene, px.camera, cube, materials=mats, rtol=job["ref_rtol"], gbuffer=px.gbuffer)
    return rr.image[px.mask], dict(err_rel_l1=float(rr.info["err_rel_l1"]),
                                      err_rel_p99=rr.info.get("err_rel_p99"), converged=rr.info.get("converged"))


def _scene_job(job: dict) -> dict:
    """One scene under ``job["envs"]``: its visibility traced once, then every (environment, material, method,
    input kind), by the steps of :mod:`ibl_ref.occlusion.image`."""
    from ..groundtruth.sh_basis import sh_project
    from ..knuth2014.median_cut import median_cut
    from ..occlusion import OcclusionInputs, get, shade
    from ..occlusion import image as oimg
    from ..occlusion import oracle_inputs as oi
    from ..occlusion.shadow_filters import region_visibility_shadow_maps

    t_case = time.perf_counter()
    px = _scene_pixels(job["scene"], job["size"])
    P = px.n_pixels
    if P == 0:
        raise IBLError(f"occlusion-zoo: scene {job['scene']!r} covers no pixel at size {job['size']}")
    labels = method_labels(job["methods"], job["n_regions"])
    glossy = any("sh_transfer_matrix" in get(_split_label(label)[0]).needs for label in labels)
    vs, oracle, oinfo = oimg.trace_oracle_inputs(px, n_face=job["n_face"], n_sets=job["n_sets"], seed=0,
                                                 sh_order=SH_ORDER, matrix_order=SH_ORDER if glossy else None)
    if float(np.min(oracle["ao"])) >= 1.0 - 1e-12:
        raise IBLError(f"occlusion-zoo: scene {job['scene']!r} has no occluders in view (every pixel's AO is 1): "
                       "the share of the missing visibility a method gives back is undefined")
    screen, sinfo = oimg.screen_space_inputs(
        px, radius=GTAO_RADIUS.get(job["scene"], DEFAULT_GTAO_RADIUS) * job["gtao_radius_scale"])
    input_time = {"oracle": oinfo["trace_time_s"] / P, "screen-space": sinfo["gtao_time_s"] / P}
    rows, brows, images, refs, skipped = [], [], {}, {}, {}
    for env in job["envs"]:
        cube, why = environment(env, job["env_size"], job["probe_dir"])
        if cube is None:
            skipped[f"env {env}"] = why
            continue
        env_sh = sh_project(cube, SH_ORDER - 1)
        region_sets, region_vis = {}, {}
        for R in job["n_regions"]:
            lights = median_cut(cube, int(R))
            region_sets[int(R)] = (int(R), oimg.stack_regions(cube, lights.labels, int(R)))
            region_vis[(int(R), "oracle")] = oi.region_visibility(vs, cube, lights.labels)[0]
            for f in job["shadow_filters"]:
                t0 = time.perf_counter()
                region_vis[(int(R), SHADOW_KIND + f)] = region_visibility_shadow_maps(
                    px.scene, px.position, px.face_normal, lights, filter=f, resolution=job["shadow_resolution"])
                input_time[(int(R), SHADOW_KIND + f)] = (time.perf_counter() - t0) / P  # per pixel, all R lights
        cache = {}
        for mname in track(list(job["materials"]), f"{job['scene']}/{env}: materials", unit="material"):
            m = material(mname)
            ref, rinfo = _reference(px, cube, m, job)
            refs[f"{env}/{mname}"] = rinfo
            terms = oimg.unoccluded_terms(cube, m, px, job["rtol"], region_sets, cache, with_specular_weight=glossy)
            common = oimg.shading_inputs(px, m, cube.shape[-1])
            unocc = shade(get("none")(OcclusionInputs(**common)), terms[None])
            missing = _metrics(unocc, ref)["rel_l1_frac"]
            base = dict(scene=job["scene"], env=env, material=mname, ref_err_rel_l1_frac=rinfo["err_rel_l1"],
                        missing_visibility_rel_l1_frac=missing, n_pixels=P)
            if env == job["figure_env"]:
                images[f"{mname}__reference"] = ref.astype(np.float32)
            for label in labels:
                name, R = _split_label(label)
                meth = get(name)
                imgs = {}
                for kind in input_kinds(meth, job["shadow_filters"]):
                    inp = oimg.method_inputs(meth, common, oracle if kind == "oracle" else screen, env_sh=env_sh,
                                             region_visibility=None if R is None else region_vis[(R, kind)])
                    img, dt = oimg.apply_method(meth, inp, terms[R])
                    imgs[kind] = img
                    met = _metrics(img, ref)
                    rows.append(dict(base, method=label, inputs=kind, applicable=True, **met,
                                     given_back_frac=1.0 - met["rel_l1_frac"] / max(missing, 1e-300),
                                     input_time_per_pixel_s=input_time.get((R, kind), input_time.get(kind)),
                                     method_time_per_pixel_s=dt / P,
                                     input_bytes_per_pixel=_nbytes_per_pixel(meth, R)))
                    if env == job["figure_env"] and kind == "oracle":
                        images[f"{mname}__{label}"] = img.astype(np.float32)
                brows += _walks(base, label, unocc, imgs, ref)
    return dict(scene=job["scene"], case="/".join([job["scene"]] + list(job["envs"])), rows=rows, budget=brows,
                images=images, mask=px.mask, references=refs, skipped=skipped, oracle=oinfo, screen_space=sinfo,
                n_pixels=P, time_s=time.perf_counter() - t_case)


def _walks(base, label, unocc, imgs, ref):
    """One walk per input kind: no occlusion → the method with oracle inputs (→ with the estimated inputs)."""
    out = []
    for kind in imgs:
        steps = [("no occlusion", unocc), ("occlusion model (oracle inputs)", imgs["oracle"])]
        if kind != "oracle":
            steps.append((f"estimator ({kind} inputs)", imgs[kind]))
        out += _walk(dict(base, method=label, inputs=kind), steps, ref)
    return out


def _walk(base, steps, ref):
    den = float(np.abs(ref.mean(axis=1)).sum())
    out, prev = [], None
    for k, (step, img) in enumerate(steps):
        m = _metrics(img, ref)
        inc = 0.0 if prev is None else float(np.abs((img - prev).mean(axis=1)).sum() / den)
        binc = m["bias_frac"] if prev is None else float((img - prev).mean(axis=1).sum() / ref.mean(axis=1).sum())
        out.append(dict(scene=base["scene"], env=base["env"], material=base["material"], method=base["method"],
                        inputs=base["inputs"], step_index=k,
                        step=step, rel_l1_increment_frac=inc if prev is not None else m["rel_l1_frac"],
                        bias_increment_frac=binc, rel_l1_vs_ref_frac=m["rel_l1_frac"], bias_vs_ref_frac=m["bias_frac"]))
        prev = img
    return out


# ------------------------------------------------------------------------------------------------------------------
# run
# ------------------------------------------------------------------------------------------------------------------
def _check(st):
    from ..occlusion import get
    from ..rendering.scenes import OCCLUSION_SCENES

    for s in st["scenes"]:
        if s not in OCCLUSION_SCENES:
            raise IBLError(f"unknown scene {s!r}; choose from {', '.join(OCCLUSION_SCENES)}")
    for e in st["envs"]:
        if e not in ENVS:
            raise IBLError(f"unknown environment {e!r}; choose from {', '.join(ENVS)}")
    for mname in st["materials"]:
        material(mname)
    for name in st["methods"]:
        get(name)
    from ..occlusion.shadow_filters import SHADOW_FILTERS

    filters = st["shadow_filters"] if isinstance(st["shadow_filters"], (list, tuple)) else [st["shadow_filters"]]
    for f in filters:
        if f not in SHADOW_FILTERS:
            raise IBLError(f"unknown shadow filter {f!r}; choose from {', '.join(SHADOW_FILTERS)}")
    st["shadow_filters"] = list(filters)
    for k in ("size", "env_size", "n_face", "n_sets", "shadow_resolution"):
        if isinstance(st[k], bool) or not isinstance(st[k], int) or st[k] < 1:
            raise IBLError(f"--{k.replace('_', '-')} must be a positive integer, got {st[k]!r}")
    regions = st["n_regions"] if isinstance(st["n_regions"], (list, tuple)) else [st["n_regions"]]
    for R in regions:
        if isinstance(R, bool) or not isinstance(R, int) or R < 1:
            raise IBLError(f"--n-regions must be positive integers, got {R!r}")
    if st["env_size"] % st["n_face"]:
        raise IBLError(f"--env-size {st['env_size']} must be a multiple of --n-face {st['n_face']} (each visibility "
                       "cell is a block of environment texels)")
    for k in ("rtol", "ref_rtol", "gtao_radius_scale"):
        if not (np.isfinite(st[k]) and st[k] > 0):
            raise IBLError(f"--{k.replace('_', '-')} must be a finite number > 0, got {st[k]!r}")
    return [int(R) for R in regions]


def run(out_dir: Path, quick: bool = False, executor=None, workers: int = 1, **params) -> dict:
    out_dir = Path(out_dir)
    st = settings_with(__name__, quick, params)
    st["n_regions"] = _check(st)  # every parameter is checked before any work (and before any file is written)
    out_dir.mkdir(parents=True, exist_ok=True)
    load0, t0 = os.getloadavg(), time.perf_counter()
    common = {k: st[k] for k in ("envs", "materials", "methods", "n_regions", "size", "env_size", "rtol", "ref_rtol",
                                 "n_face", "n_sets", "gtao_radius_scale", "shadow_filters", "shadow_resolution", "figure_env",
                                 "probe_dir")}
    jobs = [dict(common, scene=s, envs=[e]) for s in st["scenes"] for e in st["envs"]]
    cases = map_jobs(_scene_job, jobs, executor=executor, workers=workers,
                     desc="occlusion-zoo: cases (scene x environment)", unit="case",
                     cost=[2.0 if j["scene"] == "teapot" else 1.0 for j in jobs])
    rows = [q for c in cases for q in c["rows"]]
    if not any(str(q.get("applicable")) == "True" for q in rows):
        raise IBLError("occlusion-zoo: every environment was skipped: "
                       + "; ".join(f"{k}: {v}" for c in cases for k, v in c["skipped"].items()))
    brows = [q for c in cases for q in c["budget"]]
    dis = disagreements(rows)
    note = ("*_frac: fractions of the reference's sum over the covered pixels (channel means); given_back = 1 - "
            "rel_l1 / missing_visibility_rel_l1 (0 = no occlusion, 1 = exact); "
            f"p99: 99th percentile of |I - I_ref| / max(I_ref, {P99_FLOOR:g} x mean I_ref); times in seconds per "
            "pixel (wall, this machine); bytes per pixel of the inputs read, stored as float32")
    write_csv(out_dir / "occlusion_zoo.csv", rows, COLUMNS, comment=note)
    write_csv(out_dir / "occlusion_zoo_budget.csv", brows, BUDGET_COLUMNS,
              comment="per method: no occlusion -> occlusion model with oracle inputs -> estimator (screen-space "
                      "inputs); increment = rel. L1 of this step's image minus the previous one; " + note)
    write_csv(out_dir / "occlusion_zoo_disagreements.csv", dis, DISAGREEMENT_COLUMNS,
              comment="per pair of engine choices, over the GGX and diffuse cases both apply to: mean rel. L1 of "
                      "each, cases where each is closer to the reference, mean |gap| and the case of the largest gap")
    arrays = {}
    for c in cases:
        for k, v in c["images"].items():
            arrays[f"{c['scene']}__{k}"] = v
        arrays[f"{c['scene']}__mask"] = c["mask"]
    write_npz(out_dir / "occlusion_zoo_images.npz", arrays)
    from ..occlusion import get

    meta = dict(settings=st, scenes_run=list(dict.fromkeys(c["scene"] for c in cases)),
                skipped={k: v for c in cases for k, v in c["skipped"].items()},
                probe_dir=str(probe_dir(st["probe_dir"])),
                materials={k: material(k).params() for k in st["materials"]},
                methods={name: dict(needs=list(get(name).needs), params=dict(get(name).params), citation=get(name).citation,
                                    inputs=list(input_kinds(get(name), st["shadow_filters"])))
                         for name in st["methods"]},
                references={f"{c['scene']}/{k}": v for c in cases for k, v in c["references"].items()},
                oracle_inputs={c["case"]: c["oracle"] for c in cases},
                screen_space_inputs={c["case"]: c["screen_space"] for c in cases},
                n_pixels={c["scene"]: c["n_pixels"] for c in cases},
                case_time_s={c["case"]: c["time_s"] for c in cases}, p99_floor=P99_FLOOR,
                load_average_start=list(load0), load_average_end=list(os.getloadavg()),
                total_time_s=time.perf_counter() - t0)
    write_json(out_dir / "occlusion_zoo_meta.json", meta)
    with atomic_write(out_dir / "occlusion_zoo_table.md") as fh:
        fh.write(markdown_tables(rows, brows, dis, st))
    return dict(given_back=given_back_table(rows), disagreements={f"{q['method_a']} vs {q['method_b']}": q["closer"]
                                                                  for q in dis},
                skipped=meta["skipped"], time_s=meta["total_time_s"])


# ------------------------------------------------------------------------------------------------------------------
# summaries (from the rows only)
# ------------------------------------------------------------------------------------------------------------------
def _applicable(rows, inputs=None):
    return [q for q in rows if str(q["applicable"]) == "True" and (inputs is None or q["inputs"] == inputs)]


def given_back_table(rows) -> dict:
    """{"method/inputs": mean share of the missing-visibility error given back, over every case}."""
    acc = {}
    for q in _applicable(rows):
        acc.setdefault(f"{q['method']}/{q['inputs']}", []).append(float(q["given_back_frac"]))
    return {k: float(np.mean(v)) for k, v in acc.items()}


def disagreements(rows) -> list:
    """One row per :data:`DISAGREEMENTS` pair and input kind, from the cases both methods were applied to."""
    out = []
    for a, b, what in DISAGREEMENTS:
        for kind in INPUT_KINDS:
            sel = {}
            for q in _applicable(rows, kind):
                if q["method"] in (a, b):
                    sel.setdefault((q["scene"], q["env"], q["material"]), {})[q["method"]] = float(q["rel_l1_frac"])
            pairs = {k: v for k, v in sel.items() if a in v and b in v}
            if not pairs:
                continue
            ea = np.array([v[a] for v in pairs.values()])
            eb = np.array([v[b] for v in pairs.values()])
            gap = eb - ea
            worst = int(np.argmax(np.abs(gap)))
            out.append(dict(method_a=a, method_b=b, choice=what, inputs=kind, n_cases=len(pairs),
                            mean_rel_l1_a_frac=float(ea.mean()), mean_rel_l1_b_frac=float(eb.mean()),
                            a_closer_cases=int(np.sum(ea < eb)), b_closer_cases=int(np.sum(eb < ea)),
                            closer=a if ea.mean() < eb.mean() else (b if eb.mean() < ea.mean() else "tie"),
                            mean_gap_frac=float(np.mean(np.abs(gap))), worst_case="/".join(list(pairs)[worst]),
                            worst_case_gap_frac=float(gap[worst])))
    return out


def _pct(x):
    return f"{100 * float(x):.1f}"


def markdown_tables(rows, brows, dis, st) -> str:
    app = _applicable(rows)
    mats = [m for m in st["materials"] if any(q["material"] == m for q in app)]
    methods = list(dict.fromkeys(q["method"] for q in app))
    lines = ["# Occlusion zoo", "",
             "Share of the missing-visibility error each method gives back (100 % = exact visibility, 0 % = none, "
             "negative = worse than none), mean over scenes and environments; oracle inputs / screen-space (GTAO) "
             "inputs.", "", "| method | " + " | ".join(mats) + " |", "|---|" + "---|" * len(mats)]
    for meth in methods:
        cells = []
        for mat in mats:
            parts = []
            for kind in INPUT_KINDS:
                v = [float(q["given_back_frac"]) for q in app if (q["method"], q["material"], q["inputs"]) ==
                     (meth, mat, kind)]
                parts.append(_pct(np.mean(v)) if v else "n/a")
            cells.append(" / ".join(parts))
        lines.append(f"| {meth} | " + " | ".join(cells) + " |")
    lines += ["", "Rel. L1 against the reference (%), oracle inputs, mean over scenes and environments (first row: no "
                  "occlusion, the missing-visibility error).", "",
              "| method | " + " | ".join(mats) + " |", "|---|" + "---|" * len(mats)]
    for meth in methods:
        cells = []
        for mat in mats:
            v = [float(q["rel_l1_frac"]) for q in app if (q["method"], q["material"], q["inputs"]) ==
                 (meth, mat, "oracle")]
            cells.append(_pct(np.mean(v)) if v else "n/a")
        lines.append(f"| {meth} | " + " | ".join(cells) + " |")
    region = sorted({(q["method"], q["inputs"]) for q in app if q["inputs"].startswith(SHADOW_KIND)
                     or (q["method"].startswith("regions") and q["inputs"] == "oracle")})
    if region:
        lines += ["", "The paper's per-region visibility (Eq. 5 on exact per-region terms) with its visible fractions "
                      "exact (oracle) or estimated by shadow maps of the region lights with each filter: share given "
                      "back (%), mean over scenes and environments.", "",
                  "| method | inputs | " + " | ".join(mats) + " |", "|---|---|" + "---|" * len(mats)]
        for meth, kind in region:
            cells = []
            for mat in mats:
                v = [float(q["given_back_frac"]) for q in app if (q["method"], q["material"], q["inputs"]) ==
                     (meth, mat, kind)]
                cells.append(_pct(np.mean(v)) if v else "n/a")
            lines.append(f"| {meth} | {kind} | " + " | ".join(cells) + " |")
    lines += ["", "The engines' disagreements (rel. L1 %, mean over the cases both apply to).", "",
              "| choice | inputs | a | b | a / b | a closer / b closer | closer | largest gap (b − a) at |",
              "|---|---|---|---|---|---|---|---|"]
    for q in dis:
        lines.append(f"| {q['choice']} | {q['inputs']} | {q['method_a']} | {q['method_b']} | "
                     f"{_pct(q['mean_rel_l1_a_frac'])} / {_pct(q['mean_rel_l1_b_frac'])} | {q['a_closer_cases']} / "
                     f"{q['b_closer_cases']} | {q['closer']} | {_pct(q['worst_case_gap_frac'])} at "
                     f"{q['worst_case']} |")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------------------------------
# plots (read only the files)
# ------------------------------------------------------------------------------------------------------------------
def plot(out_dir: Path) -> list:
    plt = pyplot()
    out_dir = Path(out_dir)
    meta = json.loads((out_dir / "occlusion_zoo_meta.json").read_text())
    rows = _applicable(read_csv(out_dir / "occlusion_zoo.csv"))
    figs = []
    for mat in meta["settings"]["materials"]:
        sel = [q for q in rows if q["material"] == mat]
        if sel:
            figs.append(_plot_pareto(plt, out_dir, mat, sel))
    for scene in meta["scenes_run"]:
        f = _plot_images(plt, out_dir, scene, meta)
        if f is not None:
            figs.append(f)
    return figs


def _plot_pareto(plt, out_dir, mat, sel):
    methods = list(dict.fromkeys(q["method"] for q in sel))
    colours = plt.get_cmap("tab20")(np.linspace(0, 1, max(len(methods), 2)))
    kinds = list(dict.fromkeys(q["inputs"] for q in sel))
    marks = {k: {"oracle": "o", "screen-space": "^"}.get(k, "s") for k in kinds}  # s: a shadow-map filter
    fig, ax = plt.subplots(1, 2, figsize=(11.5, 4.6), layout="constrained")
    cost = {"time": lambda r: float(r["input_time_per_pixel_s"]) + float(r["method_time_per_pixel_s"]),
            "bytes": lambda r: max(float(r["input_bytes_per_pixel"]), 0.5)}  # no inputs: drawn at 0.5 B
    for j, (key, label) in enumerate((("time", "time per pixel: its inputs (ray casts or GTAO) + the method (s)"),
                                      ("bytes", "bytes per pixel of its inputs (float32; none at 0.5)"))):
        a = ax[j]
        for i, meth in enumerate(methods):
            for kind, mk in marks.items():
                q = [r for r in sel if (r["method"], r["inputs"]) == (meth, kind)]
                if not q:
                    continue
                x = np.mean([cost[key](r) for r in q])
                y = 100 * np.mean([float(r["rel_l1_frac"]) for r in q])
                a.scatter(x, y, color=colours[i], marker=mk, s=36, zorder=3,
                          label=meth if (j == 0 and kind == "oracle") else None)
        a.set_xscale("log")
        plain_log_ticks(a.xaxis, minor=())
        a.set_ylim(bottom=0)
        a.set_xlabel(label)
        a.set_ylabel("rel. L1 vs reference (%), mean over scenes and environments")
        a.grid(True, which="both", alpha=0.3)
    ax[0].set_title(f"{mat}: error vs time (o oracle, ^ GTAO, s shadow maps)", fontsize=9)
    ax[1].set_title(f"{mat}: error vs input memory", fontsize=9)
    fig.legend(loc="outside right upper", fontsize=7)
    return save_figure(fig, out_dir / f"occlusion_zoo_pareto_{mat}.png", dpi=100)


def _plot_images(plt, out_dir, scene, meta):
    with np.load(out_dir / "occlusion_zoo_images.npz") as z:
        arr = {k: z[k] for k in z.files if k.startswith(scene + "__")}
    mats = [m for m in meta["settings"]["materials"] if f"{scene}__{m}__reference" in arr]
    if f"{scene}__mask" not in arr or not mats:
        return None
    labels = method_labels(meta["settings"]["methods"], meta["settings"]["n_regions"])
    rows = [(mat, arr[f"{scene}__{mat}__reference"], [(x, arr[f"{scene}__{mat}__{x}"]) for x in labels
                                                        if f"{scene}__{mat}__{x}" in arr]) for mat in mats]
    return plot_image_rows(plt, out_dir / f"occlusion_zoo_images_{scene}.png", arr[f"{scene}__mask"], rows,
                           f"{scene}, {meta['settings']['figure_env']}: reference and each occlusion method with "
                           "oracle inputs (one exposure per row, the reference's)", cell=(1.1, 1.25), fontsize=5)
