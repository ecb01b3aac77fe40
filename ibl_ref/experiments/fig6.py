"""Knuth et al. (2014) Fig. 6: our method vs ambient occlusion on a pure glossy teapot, plus the ray-traced reference.

Modes (:mod:`ibl_ref.rendering.ao_modes`): (a) no occlusion, (b) AO shadow only, (c) AO with color, (d) our method (Eq. 5
with VSM visibilities), and the reference (:mod:`ibl_ref.rendering.reference_render`: exact ray-cast visibility toward every
texel of a coarse level, exact Phong lobe).  Material kd = 0, ks = 1, g = 0.9 (s = 10), environment ``sky_sun``.

Files: ``fig6_metrics.csv`` (one row per mode: RMSE, relative L1, max relative error, FLIP if available, all vs
the reference; ``rel_l1_occlusion_only``: the mode's shadow factor (image / unoccluded image) applied to the
reference's exact unoccluded image — the occlusion model's error without the filter-pyramid error), ``fig6_images.json`` (linear radiance images, rounded to 6 significant digits, + mask),
``fig6_meta.json`` (parameters, timings, reference info).  Plot: ``fig6.png`` (tone-mapped images, one exposure for
all, and relative error maps).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..atomic import read_csv, write_csv, write_json
from . import images_from_json, images_to_json, params_from_settings, settings_with, power_of_two
from ..figures import pyplot
from ..figures import save_figure
from ..rendering.ao_modes import render_modes
from ..rendering.image_metrics import all_metrics
from ..rendering.image_metrics import error_map
from ..rendering.image_metrics import rel_l1
from ..rendering.scenes import default_camera
from ..rendering.tonemap import auto_exposure
from ..rendering.tonemap import backdrop
from ..rendering.tonemap import exposure_srgb
from ..rendering.tonemap import with_backdrop
from ..synthetic.synthetic_envs import make_env
from ..synthetic.synthetic_meshes import make_mesh

NAME = "fig6"
DESCRIPTION = "Knuth 2014 Fig. 6: no occlusion / AO / AO+color / ours / ray-traced reference on a glossy teapot"
PAPER = "Knuth et al. 2014, Fig. 6 (no occlusion / AO / AO with colour / our method) plus a ray-traced reference"
IN_QUICK_REPRODUCE = True
RUNTIME = {"quick": "9 s with embreex (load 3), 47 s without (load 0.9)", "full": "28 s with embreex (load 3)"}
OUTPUTS = ("fig6_metrics.csv", "fig6_images.json", "fig6_meta.json", "fig6.png")

ORDER = ("no-occlusion", "ao", "ao-color", "ours", "reference")
LABELS = {"no-occlusion": "(a) no occlusion", "ao": "(b) AO (shadow only)", "ao-color": "(c) AO with color",
          "ours": "(d) our method", "reference": "reference (ray traced)"}


def settings(quick: bool) -> dict:
    if quick:
        return dict(size=72, n_lights=48, vsm_resolution=128, env_size=64, g=0.9)
    return dict(size=128, n_lights=96, vsm_resolution=256, env_size=64, g=0.9)


PARAMS = params_from_settings(settings, checks={"env_size": power_of_two})


def run(out_dir: Path, quick: bool = False, **params) -> dict:

    out_dir = Path(out_dir)
    st = settings_with(__name__, quick, params)
    t0 = time.perf_counter()
    meshes = [(make_mesh("teapot"), 0)]
    env = make_env("sky_sun", n=st["env_size"])
    cam = default_camera(meshes, size=st["size"])
    res = render_modes(meshes, cam, env, ORDER, n_lights=st["n_lights"], kd=0.0, ks=1.0, g=st["g"],
                       vsm_resolution=st["vsm_resolution"], progress=True)  # shown per ibl_ref.progress
    ref = res.images["reference"]
    m = res.mask
    # occlusion model alone: each mode's shadow factor (mode / its unoccluded image) applied to the reference's
    # exact unoccluded image, so the filter-pyramid lookup error (common to modes a-d) cancels
    ref_un = res.extras["reference-unoccluded"]
    un = res.images["no-occlusion"]
    ratio = np.where(un > 0, ref_un / np.where(un > 0, un, 1.0), 0.0)
    rows = []
    for k in ORDER:
        mt = all_metrics(res.images[k], ref, m)
        occ_only = res.images[k] * ratio if k != "reference" else ref
        rows.append(dict(mode=k, rmse=mt["rmse"], rel_l1=mt["rel_l1"], rel_max=mt["rel_max"],
                         rel_l1_occlusion_only=rel_l1(occ_only, ref, m),
                         flip=("" if mt["flip"] is None else mt["flip"])))
    note = all_metrics(res.images["ours"], ref, res.mask)["flip_note"]
    write_csv(out_dir / "fig6_metrics.csv", rows, ["mode", "rmse", "rel_l1", "rel_max", "rel_l1_occlusion_only", "flip"],
              comment=f"errors vs the ray-traced reference over covered pixels; kd=0 ks=1 g={st['g']}; {note}")

    # stored for the plot: the environment behind the teapot and the reference without visibility
    extra = {"_background": backdrop(env, cam), "_reference-unoccluded": ref_un}
    write_json(out_dir / "fig6_images.json", images_to_json({**res.images, **extra}, res.mask))
    meta = dict(settings=st, scene="teapot", env="sky_sun", timings_s=res.timings, info=res.info,
                total_time_s=time.perf_counter() - t0, flip_note=note)
    write_json(out_dir / "fig6_meta.json", meta)
    return dict(metrics={r["mode"]: r["rel_l1"] for r in rows}, time_s=meta["total_time_s"])


def _meta_g(out_dir) -> str:
    import json

    try:
        return f"{json.loads((Path(out_dir) / 'fig6_meta.json').read_text())['settings']['g']:g}"
    except (OSError, KeyError, ValueError):
        return "?"


def plot(out_dir: Path) -> list:

    plt = pyplot()


    out_dir = Path(out_dir)
    imgs, mask = images_from_json(out_dir / "fig6_images.json")
    rows = {r["mode"]: r for r in read_csv(out_dir / "fig6_metrics.csv")}
    stops = auto_exposure(imgs["reference"], mask)
    bg = imgs.get("_background")
    fig, ax = plt.subplots(2, len(ORDER), figsize=(3.0 * len(ORDER), 6.6), layout="constrained")
    for j, k in enumerate(ORDER):
        shown = imgs[k] if bg is None else with_backdrop(imgs[k], mask, bg)
        ax[0, j].imshow(exposure_srgb(shown, stops))
        ax[0, j].set_title(LABELS[k], fontsize=9)
        if k == "reference":
            # the reference's own error is 0 by definition: show its shadowing instead (exact visibility)
            un = imgs.get("_reference-unoccluded")
            if un is not None:
                y, yu = imgs[k].mean(-1), un.mean(-1)
                shade = np.where(mask & (yu > 0), y / np.where(yu > 0, yu, 1.0), np.nan)
                sh = ax[1, j].imshow(shade, cmap="gray", vmin=0, vmax=1.0)
                ax[1, j].set_title("reference: occluded / unoccluded", fontsize=8)
                fig.colorbar(sh, ax=ax[1, j], shrink=0.8, label="shadow factor")
        else:
            e = error_map(imgs[k], imgs["reference"], mask)
            im = ax[1, j].imshow(np.where(mask, e, np.nan), cmap="magma", vmin=0, vmax=1.0)
            ax[1, j].set_title(f"rel. L1 {float(rows[k]['rel_l1']):.3f} (occlusion only "
                               f"{float(rows[k]['rel_l1_occlusion_only']):.3f})", fontsize=8)
        for a in ax[:, j]:
            a.set_xticks([])
            a.set_yticks([])
    fig.colorbar(im, ax=ax[1, :-1].tolist(), shrink=0.8, extend="max",  # errors above 1 are drawn at 1
                 label="|ΔY| / Y_ref (luminance; ≥ 1 at the top)")
    fig.suptitle(f"Fig. 6 reproduction: kd = 0, ks = 1, g = {_meta_g(out_dir)}; one exposure for all images; "
                 "background = the environment", fontsize=10)
    p = out_dir / "fig6.png"
    save_figure(fig, p, dpi=100)
    return [p]
