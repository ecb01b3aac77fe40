"""The method zoo: the IBL methods engines ship today, and the paper's, against the exact reference — error, build
time, memory, and an error budget per method.

Methods (:data:`METHODS`, each a :class:`ibl_ref.rendering.method_shading.MethodSpec` of the prefilter registry):
Karis (2013)'s split sum with the exact n = v = r prefilter (``split-sum``), with N GGX importance samples
(``split-sum-is-N``) and with filtered importance sampling (Křivánek & Colbert 2008, ``split-sum-fis-N``); the
paper's method for GGX — roughness → Phong exponent, the paper's filter pyramid, partial environment maps and
variance shadow maps (Knuth et al. 2014, Eq. 5; ``ggx-phong-pem+vsm``); the paper's method for Phong materials
(``pyramid+vsm``); the exact-lobe chain, Kautz & McCool's and Kán et al.'s Phong maps; cmft's released prefilter
run as a program (``cmft``: ``$IBL_REF_CMFT``, parameter ``cmft``, or ``../shared/peers/cmft/cmft`` beside the
project; skipped with the reason if absent); Filament's cmgen run as a program (``cmgen``: ``$IBL_REF_CMGEN`` or
``cmgen`` on PATH, skipped with the reason if absent; levels down to 4² so that a 32² map has 4 of them, looked up
with Filament's lod = r(2 − r)·(N − 1)); SH9 irradiance (Ramamoorthi & Hanrahan 2001, ``sh9``) for the diffuse
material.  Every method shades the materials it serves (:func:`ibl_ref.rendering.method_shading.serves`; the
others are n/a): :data:`MATERIALS` — diffuse (kd = 1), GGX roughness 0.1 / 0.3 / 0.6 (kd = 0, F0 = ``ggx_f0``,
height-correlated Smith), Phong s = 1 / 16 / 256 (ks = 1).

Environments: the synthetic sky with a small 1e5 sun of the real sun's solid angle (``sky_sun``) and the real
probes ``city``, ``courtyard``, ``forest``, ``studio`` (1024 × 512 lat-long OpenEXR files read with
:func:`ibl_ref.environment.exr_io.load_cube` and resampled to the cube, integral-preserving; from ``probe_dir``,
``$IBL_REF_PROBE_DIR`` or ``../shared/probes`` beside the project; a missing probe is skipped with the reason).

Scenes: ``sphere`` — the orthographic unit sphere (:func:`ibl_ref.rendering.sphere_render.orthographic_sphere`,
view +z), unoccluded: the reference is the exact texel integral of
:mod:`ibl_ref.rendering.unoccluded_reference` (adaptive subdivision of the map's texels converged to ``rtol``, with
its error estimate); ``teapot`` — the teapot on a ground quad (both with the material), the reference of
:func:`ibl_ref.rendering.reference_render.render_reference` (exact visibility, GGX materials of
:mod:`ibl_ref.rendering.materials`, converged to ``ref_rtol``).

Per (scene, environment, material, method): rel. L1 Σ|I − I_ref| / Σ|I_ref| and the signed bias Σ(I − I_ref) /
Σ I_ref over the covered pixels (channel means), the 99th percentile of the per-pixel relative error
|I − I_ref| / max(I_ref, 10 % of the mean I_ref) (``p99``), the build time (prefilter, PEMs and diffuse method
from the map; the DFG tables are computed once before timing, as an engine ships them), the shading time (look-ups,
shadow maps) and the memory a renderer keeps (prefilter or PEMs, DFG table, variance shadow maps).  The error
budget of each (method, material) is the walk of :mod:`ibl_ref.rendering.method_budget` (reference → … → the
method's image, one approximation per step); its signed biases add up to the method's bias (checked), and on the
teapot the walk's ``integrator`` step compares the two exact integrators (within their estimates).

Files: ``method_zoo.csv`` (the table), ``method_zoo_budget.csv`` (every step of every walk),
``method_zoo_karis.csv`` (per GGX case: the split-sum separation's and the n = v = r lobe's increments),
``method_zoo_meta.json`` (settings, skipped items with reasons, reference information, checks, timings, load),
``method_zoo_table.md`` (summary tables), ``method_zoo_images.npz`` (images of ``figure_env``).
Plots (read only those files): ``method_zoo_pareto_MATERIAL.png`` (error vs time and vs memory per material),
``method_zoo_budget_SCENE.png`` (the budget bars per method), ``method_zoo_images_SCENE.png`` (reference and
methods, one exposure per row).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from ..atomic import atomic_write, read_csv, write_csv, write_json, write_npz
from . import params_from_settings, settings_with, power_of_two
from ..environment.exr_io import load_cube
from ..errors import IBLError
from ..executors import map_jobs
from ..figures import plain_log_ticks
from ..figures import pyplot
from ..figures import save_figure
from ..prefilter.karis2013 import build_dfg_table
from ..progress import track
from ..rendering import method_budget as mb
from ..rendering import method_shading as ms
from ..rendering.materials import GGXMaterial
from ..rendering.materials import PhongMaterial
from ..rendering.method_budget import STEPS
from ..rendering.method_shading import MethodSpec
from ..rendering.method_shading import shading_material
from ..rendering.raster import prepare_scene
from ..rendering.raster import rasterize
from ..rendering.scenes import default_camera
from ..rendering.scenes import teapot_on_ground
from ..rendering.tonemap import auto_exposure
from ..rendering.tonemap import exposure_srgb
from ..rendering.unoccluded_reference import integrate

NAME = "method-zoo"
DESCRIPTION = ("GGX-era IBL methods (split sum with exact / importance / filtered importance sampling, SH9, the "
               "paper's PEMs + VSM for GGX, cmft) vs the exact reference: error, time, memory, error budget")
PAPER = ("Karis 2013 (split sum, Eq. 7-9), Krivanek & Colbert 2008 (FIS), Ramamoorthi & Hanrahan 2001 (SH9), "
         "Knuth et al. 2014 Eq. 5 for GGX, cmft; Karis's claim that the n = v = r assumption is the larger error")
IN_QUICK_REPRODUCE = True
RUNTIME = {"quick": "12 s (load 3)",
           "full": "17 min with --workers 2 (load 0.4-1.9; sphere 1-4 min, teapot 3-6 min per environment)"}
OUTPUTS = ("method_zoo.csv", "method_zoo_budget.csv", "method_zoo_karis.csv", "method_zoo_meta.json",
           "method_zoo_table.md", "method_zoo_images.npz", "method_zoo_pareto_MATERIAL.png",
           "method_zoo_budget_SCENE.png", "method_zoo_images_SCENE.png")

PROBES = ("city", "courtyard", "forest", "studio")
ENVS = ("sky_sun",) + PROBES
SCENES = ("sphere", "teapot")


def _phong(s):
    return PhongMaterial(kd=0.0, ks=1.0, g=1.0 - 1.0 / s)


#: material name → material (GGX F0 from the ``ggx_f0`` setting, :func:`material`)
MATERIALS = {"diffuse": PhongMaterial(kd=1.0, ks=0.0, g=0.0),
             **{f"ggx{r}": GGXMaterial(roughness=r, kd=0.0) for r in (0.1, 0.3, 0.6)},
             **{f"phong{s:g}": _phong(s) for s in (1.0, 16.0, 256.0)}}

#: method label → (registry name, parameters, visibility)
METHODS = {
    "split-sum": ("split-sum", {}, "none"),
    "split-sum-is-16": ("split-sum-is", {"samples": 16}, "none"),
    "split-sum-is-64": ("split-sum-is", {"samples": 64}, "none"),
    "split-sum-is-256": ("split-sum-is", {"samples": 256}, "none"),
    "split-sum-is-1024": ("split-sum-is", {"samples": 1024}, "none"),
    "split-sum-fis-16": ("split-sum-fis", {"samples": 16}, "none"),
    "split-sum-fis-64": ("split-sum-fis", {"samples": 64}, "none"),
    "ggx-phong-pem+vsm": ("ggx-phong-pem", {}, "vsm"),
    "pyramid+vsm": ("pyramid", {}, "vsm"),
    "exact-lobe": ("exact-lobe", {}, "none"),
    "km00-lobes": ("km00-lobes", {}, "none"),
    "kan2015": ("kan2015", {}, "none"),
    "cmft": ("cmft", {}, "none"),
    "cmgen": ("cmgen", {"min_level_size": 4}, "none"),
    "sh9": ("sh9", {}, "none"),
}

COLUMNS = ["scene", "env", "material", "method", "prefilter", "visibility", "applicable", "rel_l1_frac",
           "p99_rel_error_frac", "bias_frac", "build_time_s", "shade_time_s", "total_time_s", "memory_bytes",
           "ref_err_rel_l1_frac", "n_pixels"]
BUDGET_COLUMNS = ["scene", "env", "material", "method", "step_index", "step", "rel_l1_increment_frac",
                  "bias_increment_frac", "share_of_increments_frac", "rel_l1_vs_ref_frac", "bias_vs_ref_frac"]
KARIS_COLUMNS = ["scene", "env", "material", "split_sum_rel_l1_frac", "n_v_r_rel_l1_frac", "n_v_r_over_split_sum",
                 "n_v_r_larger", "split_sum_bias_frac", "n_v_r_bias_frac"]
#: the per-pixel relative error is relative to max(I_ref, this × mean I_ref) (deep shadows count absolutely)
P99_FLOOR = 0.1


def settings(quick: bool) -> dict:
    if quick:
        return dict(scenes=["sphere"], envs=["sky_sun", "city"], materials=["diffuse", "ggx0.1", "ggx0.6", "phong16"],
                    methods=["split-sum", "split-sum-is-16", "split-sum-is-256", "split-sum-fis-16",
                             "ggx-phong-pem+vsm", "pyramid+vsm", "exact-lobe", "cmft", "cmgen", "sh9"],
                    size=10, teapot_size=16, env_size=8, rtol=4e-3, ref_rtol=5e-3, vsm_resolution=64, n_lights=6,
                    ggx_f0=1.0, figure_env="sky_sun", cmft="", probe_dir="")
    return dict(scenes=list(SCENES), envs=list(ENVS), materials=list(MATERIALS), methods=list(METHODS), size=24,
                teapot_size=32, env_size=32, rtol=2e-3, ref_rtol=2e-3, vsm_resolution=256, n_lights=24, ggx_f0=1.0,
                figure_env="sky_sun", cmft="", probe_dir="")


PARAMS = params_from_settings(settings, {
    "scenes": "scenes: sphere (unoccluded), teapot (teapot on ground, exact visibility)",
    "envs": "environments: sky_sun and the probes city, courtyard, forest, studio",
    "materials": "materials: " + ", ".join(MATERIALS), "methods": "methods: " + ", ".join(METHODS),
    "size": "sphere image width = height (pixels)", "teapot_size": "teapot image width = height (pixels)",
    "rtol": "tolerance of the sphere reference and of the budget's exact integrals (estimated rel. L1)",
    "ref_rtol": "tolerance of the teapot's converged reference", "ggx_f0": "Fresnel F0 of the GGX materials",
    "figure_env": "environment of the image figure", "cmft": "cmft binary (default $IBL_REF_CMFT or the peers folder)",
    "probe_dir": "folder of the probe EXRs (default $IBL_REF_PROBE_DIR or ../shared/probes beside the project)"},
    checks={"env_size": power_of_two})


# ------------------------------------------------------------------------------------------------------------------
# inputs
# ------------------------------------------------------------------------------------------------------------------
def _project_root() -> Path:
    return Path(__file__).resolve().parents[2]


def probe_dir(folder: str = "") -> Path:
    """The probe folder: ``folder``, ``$IBL_REF_PROBE_DIR`` or ``../shared/probes`` beside the project."""
    return Path(folder or os.environ.get("IBL_REF_PROBE_DIR") or _project_root().parent / "shared" / "probes")


def cmft_path(binary: str = "") -> str:
    """The cmft binary: ``binary``, ``$IBL_REF_CMFT`` or ``../shared/peers/cmft/cmft`` beside the project ("" if
    none exists)."""
    if binary:
        return binary
    if os.environ.get("IBL_REF_CMFT"):
        return os.environ["IBL_REF_CMFT"]
    p = _project_root().parent / "shared" / "peers" / "cmft" / "cmft"
    return str(p) if p.is_file() else ""


def environment(name: str, n: int, folder: str = ""):
    """``(cube (6, n, n, 3), None)`` or ``(None, reason)`` for an environment of :data:`ENVS`."""

    if name == "sky_sun":
        from ..synthetic.synthetic_envs import make_env

        return make_env("sky_sun", n=n), None
    if name not in PROBES:
        raise IBLError(f"unknown environment {name!r}; choose from {', '.join(ENVS)}")
    path = probe_dir(folder) / f"{name}.exr"
    if not path.is_file():
        return None, f"probe file {path} not found (set IBL_REF_PROBE_DIR or --probe-dir)"

    return load_cube(path, size=n), None


def material(name: str, f0: float):
    """The material of :data:`MATERIALS` entry ``name`` with Fresnel F0 = ``f0`` where it has one (GGX), checked
    (:func:`ibl_ref.rendering.method_shading.shading_material`)."""

    if name not in MATERIALS:
        raise IBLError(f"unknown material {name!r}; choose from {', '.join(MATERIALS)}")
    return shading_material(MATERIALS[name].with_fresnel(f0))


def method_spec(label: str, n_lights: int, cmft: str):

    if label not in METHODS:
        raise IBLError(f"unknown method {label!r}; choose from {', '.join(METHODS)}")
    name, params, vis = METHODS[label]
    params = dict(params)
    if name == "cmft" and cmft:
        params["binary"] = cmft
    return MethodSpec(name, params, vis, int(n_lights), label=label)


# ------------------------------------------------------------------------------------------------------------------
# one (scene, environment): references, methods, budgets
# ------------------------------------------------------------------------------------------------------------------
def _metrics(img, ref):
    y, yr = np.asarray(img).mean(axis=1), np.asarray(ref).mean(axis=1)
    den = float(np.abs(yr).sum())
    e = np.abs(y - yr)
    rel = e / np.maximum(yr, P99_FLOOR * max(float(np.abs(yr).mean()), 1e-300))
    return dict(rel_l1_frac=float(e.sum() / den), bias_frac=float((y - yr).sum() / yr.sum()),
                p99_rel_error_frac=float(np.percentile(rel, 99)))


def _pixels(scene: str, size: int):
    """(normals, views, points, face normals, prepared scene, meshes, camera, gbuffer, mask) of a scene."""
    if scene == "sphere":
        from ..rendering.sphere_render import orthographic_sphere

        mask, n, _ = orthographic_sphere(size)
        v = np.broadcast_to(np.array([0.0, 0.0, 1.0]), n.shape).copy()
        return dict(n=n, v=v, P=None, fn=None, sc=None, meshes=None, cam=None, gb=None, mask=mask)

    meshes = teapot_on_ground()
    sc = prepare_scene(meshes, warn=False)
    cam = default_camera(meshes[:1], size=size)
    gb = rasterize(sc, cam)
    m = gb.mask
    return dict(n=gb.normal[m], v=gb.view[m], P=gb.position[m], fn=gb.face_normal[m], sc=sc, meshes=meshes, cam=cam,
                gb=gb, mask=m)


def _references(job, px, cube, mats):
    """Per material: (occluded or None, unoccluded exact (lab's integral), unoccluded of the reference renderer or
    None, info)."""


    out = {}
    front = (np.sum(px["n"] * px["v"], axis=1) > 0)[:, None]
    for name in track(list(mats), f"{job['scene']}/{job['env']}: references", unit="material"):
        m = mats[name]
        t0 = time.perf_counter()
        ex = integrate(cube, m.unoccluded_lobe(), px["n"], px["v"], rtol=job["rtol"])
        exact = np.where(front, ex.value, 0.0)
        info = dict(exact_err_rel_l1=ex.info["err_rel_l1"], exact_cells_per_pixel=ex.info["cells_per_pixel"],
                    exact_converged=ex.info["converged"], exact_time_s=time.perf_counter() - t0)
        if job["scene"] == "sphere":
            out[name] = (None, exact, None, dict(info, err_rel_l1=ex.info["err_rel_l1"]))
            continue
        from ..rendering.reference_render import render_reference

        t0 = time.perf_counter()
        rr = render_reference(px["sc"], px["cam"], cube, materials={0: m, 1: m}, rtol=job["ref_rtol"],
                              gbuffer=px["gb"])
        mk = px["mask"]
        info.update(err_rel_l1=rr.info["err_rel_l1"], err_rel_p99=rr.info.get("err_rel_p99"),
                    converged=rr.info.get("converged"), ref_time_s=time.perf_counter() - t0)
        out[name] = (rr.image[mk], exact, rr.unoccluded[mk], info)
    return out


def _case(job: dict) -> dict:
    """One (scene, environment): a picklable job for :func:`ibl_ref.executors.map_jobs`."""

    t_case = time.perf_counter()
    cube, why = environment(job["env"], job["env_size"], job["probe_dir"])
    if cube is None:
        return dict(scene=job["scene"], env=job["env"], skipped=why)
    px = _pixels(job["scene"], job["size"] if job["scene"] == "sphere" else job["teapot_size"])
    mats = {name: material(name, job["ggx_f0"]) for name in job["materials"]}
    refs = _references(job, px, cube, mats)
    if any(ms.serves("ggx", m) for m in mats.values()):
        build_dfg_table(64)  # once, before timing, for every GGX method that carries it (an engine ships its table)
    rows, brows, karis, skipped, images, checks = [], [], [], {}, {}, []
    occluded = job["scene"] == "teapot"
    vis_kw = dict(scene=px["sc"], points=px["P"], face_normals=px["fn"], vsm_resolution=job["vsm_resolution"])
    caches = {name: {} for name in mats}
    for name in mats:
        caches[name][mats[name].unoccluded_lobe()] = refs[name][1]

    for label in track(list(job["methods"]), f"{job['scene']}/{job['env']}: methods", unit="method"):
        spec = method_spec(label, job["n_lights"], job["cmft"])
        try:
            built = ms.build_method(cube, spec)
        except Exception as exc:  # an outside program missing: the method is skipped with its reason
            from ..prefilter.cmft_peer import CmftUnavailable
            from ..prefilter.cmgen_peer import CmgenUnavailable

            if isinstance(exc, (CmftUnavailable, CmgenUnavailable)):
                skipped[label] = str(exc)
                continue
            raise
        nbytes = ms.method_nbytes(built, job["vsm_resolution"])
        for name, m in mats.items():
            ref_occ, exact, ref_un, rinfo = refs[name]
            ref = ref_occ if occluded else exact
            base = dict(scene=job["scene"], env=job["env"], material=name, method=label, prefilter=spec.prefilter,
                        visibility=spec.visibility, ref_err_rel_l1_frac=rinfo["err_rel_l1"], n_pixels=len(ref))
            if not ms.serves(spec.lobe, m):
                rows.append(dict(base, applicable=False))
                continue
            tm = {}
            img = ms.shade_method(built, m, px["n"], px["v"], timings=tm, **(vis_kw if occluded else {}))
            rows.append(dict(base, applicable=True, **_metrics(img, ref), build_time_s=round(built.build_time_s, 4),
                             shade_time_s=round(tm["shade_s"], 4), total_time_s=round(built.build_time_s
                                                                                       + tm["shade_s"], 4),
                             memory_bytes=nbytes))
            if job["env"] == job["figure_env"]:
                images[f"{name}__{label}"] = img.astype(np.float32)
            walk = mb.budget_walk(built, m, cube, px["n"], px["v"], reference=ref_occ, reference_unoccluded=ref_un,
                                  exact_unoccluded=exact, rtol=job["rtol"], vsm_resolution=job["vsm_resolution"],
                                  cache=caches[name], **({k: vis_kw[k] for k in ("scene", "points", "face_normals")}
                                                         if occluded else {}))
            steps = mb.budget_table_rows(ref, walk)
            checks.append(dict(material=name, method=label,
                               final_minus_method_rel=float(np.max(np.abs(walk[-1][1] - img), initial=0.0)
                                                            / max(float(np.max(np.abs(img), initial=0.0)), 1e-300)),
                               bias_sum_minus_total=float(sum(q["bias_increment_frac"] for q in steps)
                                                          - steps[-1]["bias_vs_ref_frac"]),
                               **({"integrator_increment_frac": next(q["rel_l1_increment_frac"] for q in steps
                                                                     if q["step"] == "integrator"),
                                   "integrator_estimate_frac": rinfo["exact_err_rel_l1"] + rinfo["err_rel_l1"]}
                                  if occluded else {})))
            for k, q in enumerate(steps):
                brows.append(dict(scene=job["scene"], env=job["env"], material=name, method=label, step_index=k,
                                  step=q["step"], rel_l1_increment_frac=q["rel_l1_increment_frac"],
                                  bias_increment_frac=q["bias_increment_frac"],
                                  share_of_increments_frac=q["share_of_increments_frac"],
                                  rel_l1_vs_ref_frac=q["rel_l1_vs_ref_frac"], bias_vs_ref_frac=q["bias_vs_ref_frac"]))
    for name, m in mats.items():  # Karis's claim: the two split-sum increments of every GGX case
        # (exact integrals, the same in the walk of every GGX method: the first walk that has them)
        st = {}
        for q in brows:
            if q["material"] == name and q["step"] in ("split_sum", "n_v_r"):
                st.setdefault(q["step"], q)
        if "split_sum" in st:  # (only the walks of the split-sum methods, which shade the GGX materials, have it)
            a, b = st["split_sum"], st["n_v_r"]
            karis.append(dict(scene=job["scene"], env=job["env"], material=name,
                              split_sum_rel_l1_frac=a["rel_l1_increment_frac"],
                              n_v_r_rel_l1_frac=b["rel_l1_increment_frac"],
                              n_v_r_over_split_sum=b["rel_l1_increment_frac"] / max(a["rel_l1_increment_frac"], 1e-300),
                              n_v_r_larger=bool(b["rel_l1_increment_frac"] > a["rel_l1_increment_frac"]),
                              split_sum_bias_frac=a["bias_increment_frac"], n_v_r_bias_frac=b["bias_increment_frac"]))
    if job["env"] == job["figure_env"]:
        for name in mats:
            ref_occ, exact, _, _ = refs[name]
            images[f"{name}__reference"] = (ref_occ if occluded else exact).astype(np.float32)
    return dict(scene=job["scene"], env=job["env"], skipped=None, rows=rows, budget=brows, karis=karis,
                skipped_methods=skipped, checks=checks, images=images, mask=px["mask"],
                references={k: v[3] for k, v in refs.items()}, time_s=time.perf_counter() - t_case)


# ------------------------------------------------------------------------------------------------------------------
# run
# ------------------------------------------------------------------------------------------------------------------
def run(out_dir: Path, quick: bool = False, executor=None, workers: int = 1, **params) -> dict:

    out_dir = Path(out_dir)
    st = settings_with(__name__, quick, params)
    # every parameter is checked before any work (and before any file is written)
    for s in st["scenes"]:
        if s not in SCENES:
            raise IBLError(f"unknown scene {s!r}; choose from {', '.join(SCENES)}")
    for e in st["envs"]:
        if e not in ENVS:
            raise IBLError(f"unknown environment {e!r}; choose from {', '.join(ENVS)}")
    for mname in st["materials"]:
        material(mname, st["ggx_f0"])
    for k in ("size", "teapot_size", "env_size", "vsm_resolution", "n_lights"):
        if isinstance(st[k], bool) or not isinstance(st[k], int) or st[k] < 1:
            raise IBLError(f"--{k.replace('_', '-')} must be a positive integer, got {st[k]!r}")
    for label in st["methods"]:
        method_spec(label, st["n_lights"], "")
    for k in ("rtol", "ref_rtol"):
        if not (np.isfinite(st[k]) and st[k] > 0):
            raise IBLError(f"--{k.replace('_', '-')} must be a finite number > 0, got {st[k]!r}")
    out_dir.mkdir(parents=True, exist_ok=True)
    skipped = {}
    scenes = list(st["scenes"])
    cmft = cmft_path(st["cmft"])
    load0, t0 = os.getloadavg(), time.perf_counter()
    common = {k: st[k] for k in ("materials", "methods", "size", "teapot_size", "env_size", "rtol", "ref_rtol",
                                 "vsm_resolution", "n_lights", "ggx_f0", "figure_env", "probe_dir")}
    jobs = [dict(common, scene=s, env=e, cmft=cmft) for s in scenes for e in st["envs"]]
    cases = map_jobs(_case, jobs, executor=executor, workers=workers, desc="method-zoo: cases (scene x environment)",
                     cost=[4.0 if j["scene"] == "teapot" else 1.0 for j in jobs])
    done = [c for c in cases if not c["skipped"]]
    for c in cases:
        if c["skipped"]:
            skipped[f"env {c['env']}"] = c["skipped"]
        for k, v in c.get("skipped_methods", {}).items():
            skipped[f"method {k}"] = v
    if not done:
        raise IBLError("method-zoo: every case was skipped: " + "; ".join(f"{k}: {v}" for k, v in skipped.items()))
    rows = [q for c in done for q in c["rows"]]
    brows = [q for c in done for q in c["budget"]]
    karis = [q for c in done for q in c["karis"]]
    note = ("*_frac: fractions of the reference's sum over the covered pixels (rel. L1, signed bias; channel means); "
            f"p99: 99th percentile of |I - I_ref| / max(I_ref, {P99_FLOOR:g} x mean I_ref); times in seconds (wall, "
            "this machine); memory in bytes")
    write_csv(out_dir / "method_zoo.csv", rows, COLUMNS, comment=note)
    write_csv(out_dir / "method_zoo_budget.csv", brows, BUDGET_COLUMNS,
              comment="one row per step of each walk (ibl_ref.rendering.method_budget): increment = this step's image "
                      "minus the previous one; share = increment rel. L1 / sum over the walk; " + note)
    write_csv(out_dir / "method_zoo_karis.csv", karis, KARIS_COLUMNS,
              comment="per GGX case: rel. L1 of the split-sum separation step and of the n = v = r step (the same in "
                      "every split-sum method's walk)")
    arrays = {}
    for c in done:
        for k, v in c["images"].items():
            arrays[f"{c['scene']}__{k}"] = v
        if c["env"] == st["figure_env"]:
            arrays[f"{c['scene']}__mask"] = c["mask"]
    write_npz(out_dir / "method_zoo_images.npz", arrays)
    checks = [dict(scene=c["scene"], env=c["env"], **q) for c in done for q in c["checks"]]
    meta = dict(settings=st, scenes_run=scenes, skipped=skipped, cmft=cmft or None,
                probe_dir=str(probe_dir(st["probe_dir"])), materials={k: material(k, st["ggx_f0"]).params() for k in
                                                                       st["materials"]},
                methods={k: dict(prefilter=METHODS[k][0], params=METHODS[k][1], visibility=METHODS[k][2])
                         for k in st["methods"]},
                references={f"{c['scene']}/{c['env']}": c["references"] for c in done},
                checks=checks, case_time_s={f"{c['scene']}/{c['env']}": c["time_s"] for c in done},
                p99_floor=P99_FLOOR, load_average_start=list(load0), load_average_end=list(os.getloadavg()),
                total_time_s=time.perf_counter() - t0)
    write_json(out_dir / "method_zoo_meta.json", meta)
    with atomic_write(out_dir / "method_zoo_table.md") as fh:
        fh.write(markdown_tables(rows, brows, karis, st))
    return dict(mean_rel_l1=_mean_table(rows), karis_holds=_karis_summary(karis), skipped=skipped,
                dominant=dominant_terms(brows), time_s=meta["total_time_s"])


def _mean_table(rows) -> dict:
    """{(scene/material/method): mean rel. L1 over the environments}."""
    acc = {}
    for q in rows:
        if str(q["applicable"]) == "True":
            acc.setdefault(f"{q['scene']}/{q['material']}/{q['method']}", []).append(float(q["rel_l1_frac"]))
    return {k: float(np.mean(v)) for k, v in acc.items()}


def _karis_summary(karis) -> dict:
    out = {}
    for q in karis:
        out.setdefault(q["material"], []).append(str(q["n_v_r_larger"]) == "True")
    return {k: f"{sum(v)}/{len(v)}" for k, v in out.items()}


def dominant_terms(brows) -> dict:
    """{scene/env/material/method: (step with the largest increment, its share)} (the reference row excluded)."""
    out = {}
    for q in brows:
        if q["step"] == "reference":
            continue
        key = f"{q['scene']}/{q['env']}/{q['material']}/{q['method']}"
        if key not in out or float(q["rel_l1_increment_frac"]) > out[key][2]:
            out[key] = (q["step"], float(q["share_of_increments_frac"]), float(q["rel_l1_increment_frac"]))
    return {k: (v[0], round(v[1], 3)) for k, v in out.items()}


def markdown_tables(rows, brows, karis, st) -> str:
    """The README tables: per scene, rel. L1 (mean over environments) method × material; the budget's dominant
    term per method and material; Karis's claim per GGX case."""
    mats = list(st["materials"])
    lines = []
    for scene in dict.fromkeys(q["scene"] for q in rows):
        envs = list(dict.fromkeys(q["env"] for q in rows if q["scene"] == scene))
        lines.append(f"\n**{scene}** — rel. L1 vs the reference, mean over {', '.join(envs)} (p99 in brackets); "
                     "n/a: the method does not shade the material\n")
        lines.append("| method | " + " | ".join(mats) + " | build (s) | memory (MiB) |")
        lines.append("|---|" + "---|" * (len(mats) + 2))
        for meth in dict.fromkeys(q["method"] for q in rows if q["scene"] == scene):
            cells, bt, mem = [], [], []
            for mat in mats:
                sel = [q for q in rows if (q["scene"], q["method"], q["material"]) == (scene, meth, mat)
                       and str(q["applicable"]) == "True"]
                if not sel:
                    cells.append("n/a")
                    continue
                l1 = np.mean([float(q["rel_l1_frac"]) for q in sel])
                p99 = np.mean([float(q["p99_rel_error_frac"]) for q in sel])
                cells.append(f"{100 * l1:.1f} % ({100 * p99:.0f} %)")
                bt += [float(q["build_time_s"]) for q in sel]
                mem += [float(q["memory_bytes"]) for q in sel]
            lines.append(f"| {meth} | " + " | ".join(cells) + f" | {np.mean(bt):.3g} | {np.mean(mem) / 2 ** 20:.3g} |"
                         if bt else f"| {meth} | " + " | ".join(cells) + " | – | – |")
    dom = dominant_terms(brows)
    lines.append("\n**Dominant budget term** (largest increment; share of the summed increments) per scene, material "
                 "and method, over the environments\n")
    lines.append("| scene | material | method | " + " | ".join(dict.fromkeys(q["env"] for q in brows)) + " |")
    envs_b = list(dict.fromkeys(q["env"] for q in brows))
    lines.append("|---|---|---|" + "---|" * len(envs_b))
    keys = list(dict.fromkeys((q["scene"], q["material"], q["method"]) for q in brows))
    for scene, mat, meth in keys:
        cells = []
        for e in envs_b:
            d = dom.get(f"{scene}/{e}/{mat}/{meth}")
            cells.append(f"{d[0]} ({100 * d[1]:.0f} %)" if d else "–")
        lines.append(f"| {scene} | {mat} | {meth} | " + " | ".join(cells) + " |")
    if karis:
        lines.append("\n**Karis: is n = v = r the larger error?** rel. L1 of the two split-sum steps\n")
        lines.append("| scene | env | material | split-sum separation | n = v = r | ratio | n = v = r larger |")
        lines.append("|---|---|---|---|---|---|---|")
        for q in karis:
            lines.append(f"| {q['scene']} | {q['env']} | {q['material']} | {100 * float(q['split_sum_rel_l1_frac']):.2f} % | "
                         f"{100 * float(q['n_v_r_rel_l1_frac']):.2f} % | {float(q['n_v_r_over_split_sum']):.2f} | "
                         f"{'yes' if str(q['n_v_r_larger']) == 'True' else 'no'} |")
    return "\n".join(lines).lstrip("\n") + "\n"


# ------------------------------------------------------------------------------------------------------------------
# plots (read only the files written above)
# ------------------------------------------------------------------------------------------------------------------
def plot(out_dir: Path) -> list:

    plt = pyplot()
    out_dir = Path(out_dir)
    meta = json.loads((out_dir / "method_zoo_meta.json").read_text())
    rows = [q for q in read_csv(out_dir / "method_zoo.csv") if q["applicable"] == "True"]
    brows = read_csv(out_dir / "method_zoo_budget.csv")
    figs = []
    for mat in meta["settings"]["materials"]:
        sel = [q for q in rows if q["material"] == mat]
        if sel:
            figs.append(_plot_pareto(plt, out_dir, mat, sel))
    for scene in meta["scenes_run"]:
        sel = [q for q in brows if q["scene"] == scene]
        if sel:
            figs.append(_plot_budget(plt, out_dir, scene, sel, meta))
        if (out_dir / "method_zoo_images.npz").exists():
            f = _plot_images(plt, out_dir, scene, meta)
            if f is not None:
                figs.append(f)
    return figs


def _pareto_front(x, y):
    order = np.lexsort((y, x))
    best, keep = np.inf, []
    for i in order:
        if y[i] < best:
            keep.append(i)
            best = y[i]
    return keep


def _plot_pareto(plt, out_dir, mat, sel):

    scenes = list(dict.fromkeys(q["scene"] for q in sel))
    methods = list(dict.fromkeys(q["method"] for q in sel))
    colours = plt.get_cmap("tab20")(np.linspace(0, 1, max(len(METHODS), 2)))
    col = {m: colours[list(METHODS).index(m) % len(colours)] for m in methods}
    marks = {"sphere": "o", "teapot": "s"}
    fig, ax = plt.subplots(1, 2, figsize=(11.5, 4.6), layout="constrained")
    for j, (key, label) in enumerate((("total_time_s", "build + shading time (s, wall)"),
                                      ("memory_bytes", "memory (MiB)"))):
        a = ax[j]
        for scene in scenes:
            xs, ys = [], []
            for meth in methods:
                q = [r for r in sel if (r["scene"], r["method"]) == (scene, meth)]
                if not q:
                    continue
                x = np.mean([float(r[key]) for r in q]) / (2 ** 20 if key == "memory_bytes" else 1.0)
                y = 100 * np.mean([float(r["rel_l1_frac"]) for r in q])
                a.scatter(x, y, color=col[meth], marker=marks.get(scene, "o"), s=36, zorder=3,
                          label=meth if (j == 0 and scene == scenes[0]) else None)
                xs.append(x)
                ys.append(y)
            if len(xs) > 1:
                k = _pareto_front(np.array(xs), np.array(ys))
                a.plot(np.array(xs)[k], np.array(ys)[k], "-", color="0.5", lw=0.8, zorder=2)
        a.set_xscale("log")
        plain_log_ticks(a.xaxis, minor=())
        a.set_ylim(bottom=0)
        a.set_xlabel(label)
        a.set_ylabel("rel. L1 vs reference (%), mean over environments")
        a.grid(True, which="both", alpha=0.3)
    ax[0].set_title(f"{mat}: error vs time (grey: Pareto front per scene)", fontsize=9)
    ax[1].set_title(f"{mat}: error vs memory ({' / '.join(f'{marks[s]} {s}' for s in scenes)})", fontsize=9)
    fig.legend(loc="outside right upper", fontsize=7)
    return save_figure(fig, out_dir / f"method_zoo_pareto_{mat}.png", dpi=100)


def _plot_budget(plt, out_dir, scene, sel, meta):

    mats = [m for m in meta["settings"]["materials"] if any(q["material"] == m for q in sel)]
    colours = plt.get_cmap("tab10")(np.arange(len(STEPS)))
    n_m = max(len({q["method"] for q in sel if q["material"] == m}) for m in mats)
    fig, axes = plt.subplots(len(mats), 1, figsize=(9.5, 0.36 * n_m * len(mats) + 1.2 * len(mats) + 0.8),
                             squeeze=False, layout="constrained")
    for ax, mat in zip(axes[:, 0], mats):
        meths = list(dict.fromkeys(q["method"] for q in sel if q["material"] == mat))
        for y, meth in enumerate(meths):
            rs = [q for q in sel if (q["material"], q["method"]) == (mat, meth) and q["step"] != "reference"]
            left = 0.0
            for step in STEPS:
                v = [float(q["rel_l1_increment_frac"]) for q in rs if q["step"] == step]
                if not v:
                    continue
                w = 100 * float(np.mean(v))  # mean over the environments
                ax.barh(y, w, left=left, color=colours[STEPS.index(step)], height=0.7)
                left += w
            fin = [float(q["rel_l1_vs_ref_frac"]) for q in rs if int(q["step_index"]) == max(int(r["step_index"])
                                                                                            for r in rs)]
            ax.plot(100 * float(np.mean(fin)), y, "k|", ms=10, mew=2)
        ax.set_yticks(range(len(meths)), meths, fontsize=7)
        ax.invert_yaxis()
        ax.set_title(f"{scene}, {mat}: rel. L1 of each step's increment, stacked (| = the method's error)",
                     fontsize=8)
        ax.set_xlabel("% of the reference (mean over environments)", fontsize=8)
    handles = [plt.Rectangle((0, 0), 1, 1, color=colours[i]) for i in range(len(STEPS))]
    fig.legend(handles, list(STEPS), loc="outside lower center", ncol=5, fontsize=7)
    return save_figure(fig, out_dir / f"method_zoo_budget_{scene}.png", dpi=100)


def _plot_images(plt, out_dir, scene, meta):

    with np.load(out_dir / "method_zoo_images.npz") as z:
        arr = {k: z[k] for k in z.files if k.startswith(scene + "__")}
    if f"{scene}__mask" not in arr:
        return None
    mats = [m for m in meta["settings"]["materials"] if f"{scene}__{m}__reference" in arr]
    rows = [(mat, arr[f"{scene}__{mat}__reference"], [(x, arr[f"{scene}__{mat}__{x}"])
                                                        for x in meta["settings"]["methods"]
                                                        if f"{scene}__{mat}__{x}" in arr]) for mat in mats]
    return plot_image_rows(plt, out_dir / f"method_zoo_images_{scene}.png", arr[f"{scene}__mask"], rows,
                           f"{scene}, {meta['settings']['figure_env']}: reference and the methods that shade each "
                           "material (one exposure per row, the reference's)")


def plot_image_rows(plt, path, mask, rows, title, cell=(1.3, 1.45), fontsize=6):
    """One row per material: its reference, then each method's image, all at the reference's exposure.

    ``rows``: ``[(material, reference (P, C), [(label, image (P, C)), …]), …]`` over the pixels of ``mask``."""

    ncol = 1 + max(len(r[2]) for r in rows)
    fig, ax = plt.subplots(len(rows), ncol, figsize=(cell[0] * ncol + 0.4, cell[1] * len(rows) + 0.6), squeeze=False,
                           layout="constrained")

    def show(a, vals, stops, label):
        img = np.zeros(mask.shape + (vals.shape[-1],))
        img[mask] = vals
        a.imshow(exposure_srgb(img, stops))
        a.set_title(label, fontsize=fontsize)

    for i, (mat, ref, images) in enumerate(rows):
        ref = np.asarray(ref, dtype=np.float64)
        full = np.zeros(mask.shape + (ref.shape[-1],))
        full[mask] = ref
        stops = auto_exposure(full, mask)  # one exposure per row: the reference's
        show(ax[i, 0], ref, stops, f"{mat}: reference")
        for j, (label, img) in enumerate(images, start=1):
            show(ax[i, j], np.asarray(img, dtype=np.float64), stops, label)
        for j in range(1 + len(images), ncol):
            ax[i, j].set_axis_off()
    for a in ax.ravel():
        a.set_xticks([])
        a.set_yticks([])
    fig.suptitle(title, fontsize=8)
    return save_figure(fig, path, dpi=100)
