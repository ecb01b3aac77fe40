"""Knuth et al. (2014) Fig. 1: gallery of materials from diffuse to mirror under two environments, our method.

Scene ``sphere_on_plane`` (sphere and ground share the material), environments ``sky_sun`` and ``studio``,
materials g ∈ {0, 0.5, 0.9, 0.99, 1}: g = 0 is the diffuse material (kd = 1, ks = 0: lobe s = 1 around the
normal), the others are pure glossy (kd = 0, ks = 1, lobe s = 1/(1−g) around r; g = 1 mirror).  Eq. 5 with VSM
visibilities; the visibilities are computed once per environment (they do not depend on the material).

Files: ``fig1_images.json`` (linear radiance per env × g, the environment seen behind the scene per env
(``ENV|background``, display only), + mask), ``fig1_meta.json``.  Plot: ``fig1.png``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..atomic import write_json
from . import images_from_json, images_to_json, params_from_settings, settings_with, power_of_two
from ..figures import pyplot
from ..figures import save_figure
from ..knuth2014.pem import build_pems
from ..rendering.raster import prepare_scene
from ..rendering.raster import rasterize
from ..rendering.render import light_visibilities
from ..rendering.render import shade_eq5
from ..rendering.scenes import default_camera
from ..rendering.tonemap import auto_exposure
from ..rendering.tonemap import backdrop
from ..rendering.tonemap import exposure_srgb
from ..rendering.tonemap import with_backdrop
from ..synthetic.synthetic_envs import make_env
from ..synthetic.synthetic_meshes import make_mesh

NAME = "fig1"
DESCRIPTION = "Knuth 2014 Fig. 1: diffuse-to-mirror gallery (g = 0 … 1) under sky_sun and studio, our method"
PAPER = "Knuth et al. 2014, Fig. 1 (materials from diffuse to mirror, our method, Eq. 5)"
IN_QUICK_REPRODUCE = True
RUNTIME = {"quick": "1.4 s (load 0.3)", "full": "68 s (load 10)"}
OUTPUTS = ("fig1_images.json", "fig1_meta.json", "fig1.png")

GLOSS = (0.0, 0.5, 0.9, 0.99, 1.0)
ENVS = ("sky_sun", "studio")


def settings(quick: bool) -> dict:
    if quick:
        return dict(size=64, n_lights=24, vsm_resolution=128, env_size=64)
    return dict(size=128, n_lights=96, vsm_resolution=512, env_size=128)


PARAMS = params_from_settings(settings, checks={"env_size": power_of_two})


def run(out_dir: Path, quick: bool = False, **params) -> dict:

    out_dir = Path(out_dir)
    st = settings_with(__name__, quick, params)
    t0 = time.perf_counter()
    meshes = [(make_mesh("sphere_on_plane"), 0)]
    sc = prepare_scene(meshes, warn=False)
    cam = default_camera(meshes, size=st["size"], view_dir=(0.0, 0.45, 1.0), distance=1.6)
    gb = rasterize(sc, cam)
    m = gb.mask
    images = {}
    for env_name in ENVS:
        env = make_env(env_name, n=st["env_size"])
        images[f"{env_name}|background"] = backdrop(env, cam)  # display only: the environment behind the scene
        pems = build_pems(env, n_lights=st["n_lights"])
        V = light_visibilities(sc, gb.position[m], gb.face_normal[m], pems.lights,
                               vsm_resolution=st["vsm_resolution"])
        for g in GLOSS:
            if g == 0.0:
                c = shade_eq5(V, np.asarray(pems.lookup_all(gb.normal[m], 0.0), float), None, 1.0, 0.0)
            else:
                c = shade_eq5(V, None, np.asarray(pems.lookup_all(gb.reflect[m], g), float), 0.0, 1.0)
            img = np.zeros(m.shape + (c.shape[-1],))
            img[m] = c
            images[f"{env_name}|{g}"] = img
    write_json(out_dir / "fig1_images.json", images_to_json(images, m))
    meta = dict(settings=st, scene="sphere_on_plane", gloss=list(GLOSS), envs=list(ENVS),
                total_time_s=time.perf_counter() - t0)
    write_json(out_dir / "fig1_meta.json", meta)
    return dict(time_s=meta["total_time_s"], n_images=len(images))


def plot(out_dir: Path) -> list:

    plt = pyplot()


    import json

    out_dir = Path(out_dir)
    imgs, mask = images_from_json(out_dir / "fig1_images.json")
    st = json.loads((out_dir / "fig1_meta.json").read_text())["settings"]
    fig, ax = plt.subplots(len(ENVS), len(GLOSS), figsize=(2.6 * len(GLOSS), 2.8 * len(ENVS) + 0.4))
    for i, e in enumerate(ENVS):
        stops = auto_exposure(imgs[f"{e}|0.0"], mask)
        for j, g in enumerate(GLOSS):
            img = imgs[f"{e}|{g}"]
            if f"{e}|background" in imgs:
                img = with_backdrop(img, mask, imgs[f"{e}|background"])
            ax[i, j].imshow(exposure_srgb(img, stops))
            kind = " (diffuse)" if g == 0 else " (mirror)" if g == 1 else f" (s = {1 / (1 - g):g})"
            ax[i, j].set_title(f"{e}, g = {g}{kind}", fontsize=8)
            ax[i, j].set_xticks([])
            ax[i, j].set_yticks([])
    fig.suptitle(f"Fig. 1 reproduction: sphere on a plane (same material), Eq. 5 with {st['n_lights']} median-cut "
                 f"lights and {st['vsm_resolution']}² VSMs, {st['env_size']}² faces; one exposure per row "
                 "(its diffuse image's)", fontsize=9)
    fig.tight_layout()
    p = out_dir / "fig1.png"
    save_figure(fig, p, dpi=100)
    return [p]
