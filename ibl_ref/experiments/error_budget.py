"""Error budget of the paper's method: from the ray-traced reference to Knuth et al. (2014) Eq. 5, one approximation
at a time, per material.

Scene: the teapot on a ground quad (:func:`ibl_ref.rendering.scenes.teapot_on_ground`, camera framing the teapot,
:func:`ibl_ref.rendering.scenes.default_camera`), under ``sky_sun`` (synthetic sky, 1e5 sun of the real sun's
solid angle) and ``probe`` (:func:`ibl_ref.environment.probe_files.probe_cube`: a probe-like lat-long map — sky
gradient, textured ground with a black strip, a 1.5° sun of 3e4 — resampled to the cube).  Materials: diffuse
(kd = 1, ks = 0), g = 0.9 and g = 0.99 (kd = 0, ks = 1); the ground gets ``ground`` ("same": the object's material,
as in ``cross-validate``; or one of the material names).

Per (environment, material) the converged reference (:func:`ibl_ref.rendering.reference_render.render_reference`)
is rendered once; per number of median-cut regions (``regions``) the chain of :mod:`ibl_ref.rendering.error_budget`
is walked — reference → regions → lobe_hemisphere → vsm → horizon → prefilter → gloss_lookup → back_faces (that
module's docstring defines every intermediate image: quantity, equation, what changes) — and again with the two
steps ``swap`` exchanged.  The last image is exactly :func:`ibl_ref.rendering.render.render_pem` (Eq. 5, VSMs,
the paper's pyramid and g → level mapping, ``horizon=False``), so the cumulative error of the last step is the
paper's error against the reference (what ``render-error`` reports as ``ours``).  ``prefilter`` (default
``pyramid``) walks the same chain with another level-chain method of the prefilter registry
(:mod:`ibl_ref.prefilter.registry`) in steps 5–7.

Shares: the increment δ_k = I_k − I_{k−1} of each step, its rel. L1 Σ|δ_k|/Σ|I_ref| over the covered pixels, and its
share = that rel. L1 / the sum over all steps (errors do not add; the signed biases do).  Step 1 is checked on its
own: with one region per texel of nearest-texel copies of the map at ``texel_factors`` × N (the same
piecewise-constant radiance), Eq. 5 with exact per-region visibility must converge to the reference
(``error_budget_texel_limit.csv``, on a seeded sample of ``texel_pixels`` covered pixels).

Files: ``error_budget.csv`` (one row per environment × material × regions × order × step: rel. L1 / RMSE / bias of
the step's image against the reference and of its increment, share), ``error_budget_texel_limit.csv``,
``error_budget_meta.json`` (settings, reference info, best levels, definitions, timings, load),
``error_budget_table.md`` (the README summary table), ``error_budget_images.npz`` (reference and step images of
``figure_regions``), ``error_budget_diff/ENV__MATERIAL__LREGIONS__kSTEP.exr`` (signed difference image δ_k per step,
RGB radiance).  Plots: ``error_budget_diff_ENV.png`` (δ_k per step and material, diverging colour map, scale
stated), ``error_budget_shares.png``.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from ..atomic import atomic_write, read_csv, write_csv, write_json, write_npz
from . import params_from_settings, settings_with, power_of_two
from ..errors import IBLError
from ..executors import map_jobs
from ..figures import pyplot
from ..figures import save_figure
from ..knuth2014.median_cut import median_cut
from ..prefilter.registry import get_method
from ..rendering import error_budget as eb
from ..rendering.error_budget import DEFAULT_ORDER
from ..rendering.image_io import write_image_exr
from ..rendering.raster import prepare_scene
from ..rendering.raster import rasterize
from ..rendering.reference_render import render_reference
from ..rendering.scenes import default_camera
from ..rendering.scenes import teapot_on_ground
from ..rendering.tonemap import auto_exposure
from ..rendering.tonemap import exposure_srgb
from ..synthetic.synthetic_envs import scene_environment

NAME = "error-budget"
DESCRIPTION = "error budget of the paper's method: reference -> Eq. 5 one approximation at a time, share per step"
PAPER = ("Knuth et al. 2014, Eq. 4-5 and Sec. 3.1-3.4 (regions, VSMs, filter pyramid, glossiness lookup): each "
         "approximation's share of the error against a converged ray-traced reference")
IN_QUICK_REPRODUCE = False  # 38 s at quick size, most of it in the one-region-per-texel check: run on its own
RUNTIME = {"quick": "38 s serial (load 3.6)",
           "full": "8 min 35 s with --workers 2 (load 1.5-4.2; 95 s cases, 7 min one-region-per-texel check)"}
OUTPUTS = ("error_budget.csv", "error_budget_texel_limit.csv", "error_budget_meta.json", "error_budget_table.md",
           "error_budget_images.npz", "error_budget_diff/ENV__MATERIAL__LREGIONS__kSTEP.exr",
           "error_budget_diff_ENV.png", "error_budget_shares.png")

MATERIALS = {"diffuse": (1.0, 0.0, 0.0), "g0.9": (0.0, 1.0, 0.9), "g0.99": (0.0, 1.0, 0.99)}
ENVS = ("sky_sun", "probe")
#: the difference images are shown as ΔY / mean(Y_ref) clipped to ± this (one scale for every panel)
DIFF_SCALE = 0.5
COLUMNS = ["env", "material", "ground_material", "regions", "order", "step_index", "step", "rel_l1_vs_ref_frac",
           "rmse_vs_ref_radiance", "bias_vs_ref_frac", "rel_l1_increment_frac", "rmse_increment_radiance",
           "bias_increment_frac", "share_of_increments_frac", "rel_l1_change_frac"]
TEXEL_COLUMNS = ["env", "material", "ground_material", "texel_factor", "face_size_texels", "regions", "n_pixels",
                 "rel_l1_vs_ref_frac", "rmse_vs_ref_radiance", "ref_err_estimate_frac", "time_s"]


def settings(quick: bool) -> dict:
    if quick:
        return dict(size=20, env_size=16, envs=list(ENVS), materials=list(MATERIALS), ground="same", regions=[6, 24],
                    vsm_resolution=128, rtol=5e-3, texel_factors=[1], texel_pixels=120, swap=["vsm", "prefilter"],
                    level_dirs=1500, figure_regions=24, prefilter="pyramid")
    return dict(size=48, env_size=32, envs=list(ENVS), materials=list(MATERIALS), ground="same", regions=[6, 24, 96],
                vsm_resolution=256, rtol=2e-3, texel_factors=[1, 2], texel_pixels=300, swap=["vsm", "prefilter"],
                level_dirs=4000, figure_regions=24, prefilter="pyramid")


PARAMS = params_from_settings(settings, {
    "envs": "environments (sky_sun, probe)", "ground": "ground material: same (as the object) or a material name",
    "regions": "median-cut regions (lights) per walk", "rtol": "reference tolerance (estimated rel. L1)",
    "texel_factors": "face-size multiples of the one-region-per-texel check of step 1",
    "texel_pixels": "covered pixels sampled for that check", "swap": "two steps exchanged in the second walk",
    "figure_regions": "region count shown in the difference figures",
    "level_dirs": "seeded uniform directions the best pyramid level is fitted on (as lobe-chain's n_dirs)",
    "prefilter": "how the PEMs are prefiltered: a level-chain method of the prefilter registry (pyramid = the "
                 "paper's; exact-lobe, km00-lobes, kan2015)"},
    checks={"env_size": power_of_two})


def _scene(size: int):

    meshes = teapot_on_ground()
    sc = prepare_scene(meshes, warn=False)
    cam = default_camera(meshes[:1], size=size)
    return meshes, sc, cam, rasterize(sc, cam)


def _materials(material: str, ground: str) -> dict:

    for m in (material, ground):
        if m not in MATERIALS and m != "same":
            raise IBLError(f"unknown material {m!r}; choose from {', '.join(MATERIALS)} (ground also: same)")
    return {0: MATERIALS[material], 1: MATERIALS[material if ground == "same" else ground]}


def _case(job: dict) -> dict:
    """One (environment, material): the reference and every walk (a picklable job for :func:`map_jobs`)."""

    t0 = time.perf_counter()
    meshes, sc, cam, gb = _scene(job["size"])
    env = scene_environment(job["env"], job["env_size"])
    mats = _materials(job["material"], job["ground"])
    ref = render_reference(sc, cam, env, rtol=job["rtol"], materials=mats, gbuffer=gb)
    t_ref = time.perf_counter() - t0
    orders = {"default": eb.DEFAULT_ORDER, "swap " + "<->".join(job["swap"]): eb.swapped_order(*job["swap"])}
    rows, images, levels = [], {}, {}
    for L in job["regions"]:
        lights = median_cut(env, int(L))
        terms = eb.budget_terms(sc, gb, env, lights, mats, prefilter=job["prefilter"],
                                vsm_resolution=job["vsm_resolution"], level_dirs=job["level_dirs"])
        for label, order in orders.items():
            walk = eb.walk(terms, order)
            for k, q in enumerate(eb.budget_rows(ref.image, [(s, im) for s, _, im in walk], gb.mask)):
                rows.append(dict(env=job["env"], material=job["material"], ground_material=job["ground"],
                                 regions=int(L), order=label, step_index=k, **q))
            if label == "default":
                images[int(L)] = {s: im.astype(np.float32) for s, _, im in walk}
        levels[str(L)] = dict(fit_directions=terms.best_levels, image_directions=terms.lookup_rel_l1_image)
    return dict(env=job["env"], material=job["material"], rows=rows, images=images, levels=levels,
                reference=ref.image.astype(np.float32), mask=gb.mask, ref_info=ref.info, ref_time_s=t_ref,
                time_s=time.perf_counter() - t0)


def _texel_case(job: dict) -> list:
    """One (environment, factor) of the step-1 check: texel regions, all materials sharing the visibility rays."""

    t0 = time.perf_counter()
    meshes, sc, cam, gb = _scene(job["size"])
    env = scene_environment(job["env"], job["env_size"])
    pix = np.zeros(gb.mask.shape, dtype=bool)
    idx = np.flatnonzero(gb.mask)
    rng = np.random.default_rng(20140)
    pix.ravel()[np.sort(rng.choice(idx, size=min(int(job["texel_pixels"]), len(idx)), replace=False))] = True
    mats = [_materials(m, job["ground"]) for m in job["materials"]]
    imgs = eb.texel_limit_image(sc, gb, env, mats, job["factor"], pixels=pix)
    dt = time.perf_counter() - t0
    out = []
    for m, img in zip(job["materials"], imgs):
        ref = np.asarray(job["references"][m], dtype=np.float64)
        e = (img - ref)[pix]
        out.append(dict(env=job["env"], material=m, ground_material=job["ground"], texel_factor=int(job["factor"]),
                        face_size_texels=int(job["env_size"]) * int(job["factor"]),
                        regions=6 * (int(job["env_size"]) * int(job["factor"])) ** 2, n_pixels=int(pix.sum()),
                        rel_l1_vs_ref_frac=float(np.abs(e).sum() / np.abs(ref[pix]).sum()),
                        rmse_vs_ref_radiance=float(np.sqrt(np.mean(e ** 2))),
                        ref_err_estimate_frac=float(job["ref_err"][m]), time_s=round(dt, 2)))
    return out


def run(out_dir: Path, quick: bool = False, executor=None, workers: int = 1, **params) -> dict:

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    st = settings_with(__name__, quick, params)
    eb.swapped_order(*st["swap"])  # a bad pair fails before any work
    get_method(st["prefilter"])  # so does an unknown prefilter
    for e in st["envs"]:
        if e not in ENVS:
            raise IBLError(f"unknown environment {e!r}; choose from {', '.join(ENVS)}")
    for m in st["materials"]:
        _materials(m, st["ground"])
    load0, t_start = os.getloadavg(), time.perf_counter()
    common = {k: st[k] for k in ("size", "env_size", "ground", "rtol", "vsm_resolution", "regions", "swap",
                                 "level_dirs", "prefilter")}
    jobs = [dict(common, env=e, material=m) for e in st["envs"] for m in st["materials"]]
    cases = map_jobs(_case, jobs, executor=executor, workers=workers, desc="error-budget: cases (reference + walks)")
    rows = [q for c in cases for q in c["rows"]]
    write_csv(out_dir / "error_budget.csv", rows, COLUMNS,
              comment=f"teapot + ground, {st['size']}^2 px, env faces {st['env_size']}^2, VSM {st['vsm_resolution']}^2; "
                      "*_frac are fractions of the reference's sum over covered pixels (rel. L1, signed bias), "
                      "*_radiance in radiance units (RMSE over covered pixels and channels); increment = this "
                      "step's image minus the previous step's; share = increment rel. L1 / sum over the walk")
    tjobs = [dict(common, env=e, factor=int(f), materials=list(st["materials"]), texel_pixels=st["texel_pixels"],
                  references={c["material"]: c["reference"] for c in cases if c["env"] == e},
                  ref_err={c["material"]: c["ref_info"].get("err_rel_l1", float("nan")) for c in cases if c["env"] == e})
             for e in st["envs"] for f in st["texel_factors"]]
    texel = [q for part in map_jobs(_texel_case, tjobs, executor=executor, workers=workers,
                                    desc="error-budget: step-1 check (one region per texel)") for q in part]
    write_csv(out_dir / "error_budget_texel_limit.csv", texel, TEXEL_COLUMNS,
              comment="step 1 (exact visibility per region) with one region per texel of the map copied at "
                      "texel_factor x its face size (nearest texel: the same radiance) vs the converged reference, on a "
                      "seeded sample of covered pixels; ref_err_estimate_frac = the reference's own estimate")
    # images: the figure's region count in an npz (plot input), every step's signed difference as EXR
    fr = int(st["figure_regions"]) if int(st["figure_regions"]) in st["regions"] else int(st["regions"][0])
    arrays = {}
    (out_dir / "error_budget_diff").mkdir(exist_ok=True)
    for c in cases:
        key = f"{c['env']}__{c['material']}"
        arrays[f"{key}__reference"] = c["reference"]
        arrays[f"{key}__mask"] = c["mask"]
        for L, imgs in c["images"].items():
            prev = c["reference"]
            for k, (step, im) in enumerate(imgs.items(), start=1):
                write_image_exr(out_dir / "error_budget_diff" / f"{key}__L{L}__{k}{step}.exr",
                                np.asarray(im, np.float64) - prev, signed=True)
                prev = im
                if L == fr:
                    arrays[f"{key}__{step}"] = im
    write_npz(out_dir / "error_budget_images.npz", arrays)
    final = {f"{q['env']}/{q['material']}/L{q['regions']}": q["rel_l1_vs_ref_frac"] for q in rows
             if q["order"] == "default" and q["step"] == eb.DEFAULT_ORDER[-1]}
    meta = dict(settings=st, figure_regions=fr, steps=list(eb.DEFAULT_ORDER),
                swapped_order=list(eb.swapped_order(*st["swap"])),
                definitions="ibl_ref.rendering.error_budget (module docstring)",
                share_definition="share_k = rel_l1(I_k - I_{k-1}) / sum_k rel_l1(I_k - I_{k-1}); rel_l1 over the "
                                 "covered pixels, relative to sum|I_ref|; signed biases add up, shares of |.| do not",
                cases={f"{c['env']}/{c['material']}": dict(reference=c["ref_info"], ref_time_s=c["ref_time_s"],
                                                          time_s=c["time_s"], levels=c["levels"]) for c in cases},
                final_rel_l1=final, load_average_start=list(load0), load_average_end=list(os.getloadavg()),
                total_time_s=time.perf_counter() - t_start)
    write_json(out_dir / "error_budget_meta.json", meta)
    with atomic_write(out_dir / "error_budget_table.md") as fh:
        fh.write(markdown_table(rows, texel, st))
    return dict(final_rel_l1=final, texel_limit={f"{q['env']}/{q['material']}/x{q['texel_factor']}":
                                                 q["rel_l1_vs_ref_frac"] for q in texel},
                time_s=meta["total_time_s"])


def markdown_table(rows, texel, st) -> str:
    """The README table: per case the paper's error and each step's increment rel. L1 (share), default order."""

    head = ("| env | material | regions | Eq. 5 vs ref. | " + " | ".join(DEFAULT_ORDER) + " | Σ increments |\n"
            "|---|---|---|---|" + "---|" * (len(DEFAULT_ORDER) + 1) + "\n")
    lines = []
    keys = sorted({(q["env"], q["material"], int(q["regions"])) for q in rows},
                  key=lambda k: (list(st["envs"]).index(k[0]), list(st["materials"]).index(k[1]), k[2]))
    for env, mat, L in keys:
        w = {q["step"]: q for q in rows if (q["env"], q["material"], int(q["regions"]), q["order"]) ==
             (env, mat, L, "default")}
        cells = [f"{100 * float(w[s]['rel_l1_increment_frac']):.1f} % ({100 * float(w[s]['share_of_increments_frac']):.0f} %)"
                 for s in DEFAULT_ORDER]
        tot = sum(float(w[s]["rel_l1_increment_frac"]) for s in DEFAULT_ORDER)
        lines.append(f"| {env} | {mat} | {L} | **{100 * float(w[DEFAULT_ORDER[-1]]['rel_l1_vs_ref_frac']):.1f} %** | "
                     + " | ".join(cells) + f" | {100 * tot:.1f} % |")
    out = head + "\n".join(lines) + "\n"
    if texel:
        out += ("\n| env | material | one region per texel at face size | regions | rel. L1 vs ref. | reference's "
                "own estimate |\n|---|---|---|---|---|---|\n")
        out += "\n".join(f"| {q['env']} | {q['material']} | {q['face_size_texels']}² | {q['regions']} | "
                         f"{100 * float(q['rel_l1_vs_ref_frac']):.2f} % | {100 * float(q['ref_err_estimate_frac']):.2f} % |"
                         for q in texel) + "\n"
    return out


def plot(out_dir: Path) -> list:

    plt = pyplot()
    out_dir = Path(out_dir)
    meta = json.loads((out_dir / "error_budget_meta.json").read_text())
    st, fr = meta["settings"], meta["figure_regions"]
    figs = []
    with np.load(out_dir / "error_budget_images.npz") as z:
        arrays = {k: z[k] for k in z.files}
    for env in st["envs"]:
        mats = [m for m in st["materials"] if f"{env}__{m}__reference" in arrays]
        fig, ax = plt.subplots(len(mats), len(DEFAULT_ORDER) + 1, figsize=(2.0 * (len(DEFAULT_ORDER) + 1) + 1.2,
                                                                       2.1 * len(mats) + 0.9),
                               squeeze=False, layout="constrained")
        im = None
        for i, m in enumerate(mats):
            key = f"{env}__{m}"
            ref, mask = arrays[f"{key}__reference"].astype(np.float64), arrays[f"{key}__mask"]
            ax[i, 0].imshow(exposure_srgb(ref, auto_exposure(ref, mask)))
            ax[i, 0].set_title(f"{m}: reference", fontsize=8)
            yref = float(ref[mask].mean())
            prev = ref
            for j, step in enumerate(DEFAULT_ORDER, start=1):
                cur = arrays[f"{key}__{step}"].astype(np.float64)
                d = (cur - prev).mean(axis=-1) / yref
                im = ax[i, j].imshow(np.where(mask, d, np.nan), cmap="RdBu_r", vmin=-DIFF_SCALE, vmax=DIFF_SCALE)
                ax[i, j].set_title(f"{j} {step}", fontsize=8)
                prev = cur
        for a in ax.ravel():
            a.set_xticks([])
            a.set_yticks([])
        fig.colorbar(im, ax=ax[:, 1:].ravel().tolist(), shrink=0.8,
                     label=f"ΔY / mean Y_ref, clipped at ±{DIFF_SCALE:g}")
        fig.suptitle(f"{env}, {fr} regions: difference each step adds (step image − previous image)", fontsize=10)
        figs.append(save_figure(fig, out_dir / f"error_budget_diff_{env}.png", dpi=100))
    figs.append(_plot_shares(plt, save_figure, out_dir, st))
    return figs


def _plot_shares(plt, save_figure, out_dir, st):

    rows = read_csv(out_dir / "error_budget.csv")
    envs = list(dict.fromkeys(q["env"] for q in rows))
    fig, axes = plt.subplots(1, len(envs) + 1, figsize=(5.2 * (len(envs) + 1) + 1.5, 0.32 * len(rows) / 16 + 3.6),
                             squeeze=False, layout="constrained")
    colours = plt.get_cmap("tab10")(np.arange(len(DEFAULT_ORDER)))

    def bars(ax, keys, getter, labels):
        for y, key in enumerate(keys):
            w = getter(key)
            left = 0.0
            for c, step in enumerate(w["order"]):
                v = 100 * float(w[step]["rel_l1_increment_frac"])
                ax.barh(y, v, left=left, color=colours[DEFAULT_ORDER.index(step)], height=0.7)
                left += v
            ax.plot(100 * float(w[w["order"][-1]]["rel_l1_vs_ref_frac"]), y, "k|", ms=12, mew=2)
        ax.set_yticks(range(len(keys)), labels, fontsize=7)
        ax.invert_yaxis()
        ax.set_xlabel("rel. L1 of each step's increment, stacked (%)")

    def walk_of(env, mat, L, order):
        sel = [q for q in rows if (q["env"], q["material"], q["regions"], q["order"]) == (env, mat, L, order)]
        d = {q["step"]: q for q in sel if q["step"] != "reference"}
        d["order"] = [q["step"] for q in sorted(sel, key=lambda q: int(q["step_index"])) if q["step"] != "reference"]
        return d

    for ax, env in zip(axes[0], envs):
        keys = list(dict.fromkeys((q["material"], q["regions"]) for q in rows if q["env"] == env))
        bars(ax, keys, lambda k: walk_of(env, k[0], k[1], "default"), [f"{m}, {L} reg." for m, L in keys])
        ax.set_title(f"{env}: increments per step (| = Eq. 5's error)", fontsize=9)
    orders = list(dict.fromkeys(q["order"] for q in rows))
    env0, mat0 = envs[0], rows[0]["material"]
    L0 = str(st["figure_regions"]) if any(q["regions"] == str(st["figure_regions"]) for q in rows) else rows[0]["regions"]
    bars(axes[0, -1], orders, lambda o: walk_of(env0, mat0, L0, o), orders)
    axes[0, -1].set_title(f"{env0}, {mat0}, {L0} regions: order of the steps", fontsize=9)
    handles = [plt.Rectangle((0, 0), 1, 1, color=colours[i]) for i in range(len(DEFAULT_ORDER))]
    fig.legend(handles, [f"{i + 1} {s}" for i, s in enumerate(DEFAULT_ORDER)], loc="outside lower center",
               ncol=len(DEFAULT_ORDER), fontsize=8)
    return save_figure(fig, out_dir / "error_budget_shares.png", dpi=100)
