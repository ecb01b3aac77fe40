"""Knuth et al. (2014) Fig. 7: frame render time vs number of lights (teapot and cloth), and where the time goes.

Per frame (one image, ``kd = 0, ks = 1, g = 0.5``): rasterisation of the G-buffer, per light a shadow (depth) map,
the moment blur, the VSM look-ups (``visibility``), the PEM look-ups (``lookup``) and the Eq. 5 sum
(``shading``) — timed stage by stage (:func:`ibl_ref.rendering.render.light_visibilities` with ``timings``).  Building the
PEMs (median cut + one filter pyramid per region) is a pre-process in the paper and reported separately
(``pem_build_s``).  A least-squares line ``frame_s = intercept + slope·lights`` is fitted per scene.
CPU NumPy timings (2 shared cores, under load) — only the trend is comparable to the paper's GPU numbers.

Files: ``fig7_timings.csv`` (one row per scene and light count), ``fig7_fit.json``.  Plot: ``fig7.png``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from . import params_from_settings, settings_with, power_of_two
from ..progress import track
from ..atomic import read_csv, write_csv, write_json
from ..figures import count_ticks
from ..figures import pyplot
from ..figures import save_figure
from ..knuth2014.pem import build_pems
from ..rendering.ao_modes import render_modes
from ..rendering.scenes import default_camera
from ..synthetic.synthetic_envs import make_env
from ..synthetic.synthetic_meshes import make_mesh

NAME = "fig7"
DESCRIPTION = "Knuth 2014 Fig. 7: render time vs number of lights (teapot, cloth) with a per-stage breakdown"
PAPER = "Knuth et al. 2014, Fig. 7 (frame time vs number of lights, teapot and cloth)"
IN_QUICK_REPRODUCE = True
RUNTIME = {"quick": "1.5 s (load 0.3)", "full": "1 min 47 s (load 10; 34 s CPU)"}
OUTPUTS = ("fig7_timings.csv", "fig7_fit.json", "fig7.png")

STAGES = ("raster", "shadow_maps", "blur", "visibility", "lookup", "shading")
SCENES = ("teapot", "cloth")


def settings(quick: bool) -> dict:
    if quick:
        return dict(lights=[6, 12, 24], size=64, vsm_resolution=128, env_size=32)
    return dict(lights=[6, 12, 24, 48, 96, 192], size=128, vsm_resolution=256, env_size=64)


PARAMS = params_from_settings(settings, checks={"env_size": power_of_two})


def fit_line(x, y) -> dict:
    """Least-squares y = intercept + slope·x; returns slope, intercept and R²."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    A = np.stack([np.ones_like(x), x], axis=1)
    (b, a), *_ = np.linalg.lstsq(A, y, rcond=None)
    ss = ((y - y.mean()) ** 2).sum()
    r2 = 1.0 - ((y - (b + a * x)) ** 2).sum() / ss if ss > 0 else 1.0
    return dict(slope_s_per_light=float(a), intercept_s=float(b), r2=float(r2))


def _load_average():
    """The machine's 1-minute load average (None where the OS does not report one): timings need it."""
    import os

    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        return None


def run(out_dir: Path, quick: bool = False, **params) -> dict:

    out_dir = Path(out_dir)
    st = settings_with(__name__, quick, params)
    env = make_env("sky_sun", n=st["env_size"])
    load = _load_average()
    rows = []
    for scene in track(SCENES, "fig7: scenes", unit="scene"):
        meshes = [(make_mesh(scene), 0)]
        cam = default_camera(meshes, size=st["size"])
        # warm-up (caches: calibration tables, samplers) so the first timed frame is not penalised
        render_modes(meshes, cam, env, ("no-occlusion",), pems=build_pems(env, n_lights=6), kd=0.0, ks=1.0, g=0.5)
        for L in st["lights"]:
            t0 = time.perf_counter()
            pems = build_pems(env, n_lights=L)
            t_pem = time.perf_counter() - t0
            res = render_modes(meshes, cam, env, ("ours",), pems=pems, kd=0.0, ks=1.0, g=0.5,
                               vsm_resolution=st["vsm_resolution"])
            T = {k: float(res.timings.get(k, 0.0)) for k in STAGES}
            rows.append(dict(scene=scene, lights=len(pems.lights), frame_s=sum(T.values()), pem_build_s=t_pem,
                             n_pixels=int(res.mask.sum()), **{f"{k}_s": v for k, v in T.items()}))
    cols = ["scene", "lights", "frame_s", "pem_build_s", "n_pixels"] + [f"{k}_s" for k in STAGES]
    write_csv(out_dir / "fig7_timings.csv", rows, cols,
              comment=f"wall-clock seconds per frame (time.perf_counter; the machine's load average at the start "
                      f"is in fig7_fit.json), {st['size']}^2 px, VSM {st['vsm_resolution']}^2, env {st['env_size']}^2")
    fits = {}
    for scene in SCENES:
        r = [x for x in rows if x["scene"] == scene]
        fits[scene] = fit_line([x["lights"] for x in r], [x["frame_s"] for x in r])
        fits[scene]["shadow_share"] = float(sum(x["shadow_maps_s"] + x["blur_s"] for x in r) / sum(x["frame_s"] for x in r))
    import os

    write_json(out_dir / "fig7_fit.json", dict(settings=st, fits=fits, load_average_1min=load, cpus=os.cpu_count()))
    return fits


def plot(out_dir: Path) -> list:
    import json


    plt = pyplot()

    out_dir = Path(out_dir)
    rows = read_csv(out_dir / "fig7_timings.csv")
    meta = json.loads((out_dir / "fig7_fit.json").read_text())
    load = meta.get("load_average_1min")
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2), layout="constrained")
    colors = {"teapot": "red", "cloth": "blue"}
    for scene in SCENES:
        r = [x for x in rows if x["scene"] == scene]
        x = np.array([float(q["lights"]) for q in r])
        y = np.array([float(q["frame_s"]) for q in r])
        ax[0].plot(x, y, "o-", color=colors[scene], label=scene)
    ax[0].set_xlabel("number of lights")
    ax[0].set_ylabel("frame time (s, wall clock)")
    ax[0].set_ylim(0, None)
    ax[0].legend(loc="upper left")
    ax[0].set_title("render time vs lights")
    labels = [f"{q['scene']} {q['lights']}" for q in rows]
    bottom = np.zeros(len(rows))
    for k in STAGES:
        v = np.array([float(q[f"{k}_s"]) for q in rows])
        ax[1].bar(range(len(rows)), v, bottom=bottom, label=k)
        bottom += v
    ax[1].set_xticks(range(len(rows)))
    ax[1].set_xticklabels(labels, rotation=60, fontsize=7)
    ax[1].set_ylabel("time per frame (s)")
    ax[1].set_xlabel("scene, number of lights")
    ax[1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), title="stage")
    ax[1].set_title("where the time goes")
    where = f"load average {load:.1f} at the start" if load is not None else "load not recorded"
    if meta.get("cpus"):
        where = f"{meta['cpus']} CPUs, {where}"
    fig.suptitle(f"Fig. 7 reproduction: Eq. 5 frame time, {meta['settings']['size']}² px, VSM "
                 f"{meta['settings']['vsm_resolution']}² ({where})", fontsize=9)
    count_ticks(ax[0], [int(q["lights"]) for q in rows])  # integer light counts, no colliding labels
    p = out_dir / "fig7.png"
    save_figure(fig, p, dpi=100)
    return [p]
