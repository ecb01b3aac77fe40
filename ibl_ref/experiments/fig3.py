"""Knuth et al. (2014) Fig. 3: spheres from mirror (g = 1) to diffuse (g = 0) from one filter pyramid.

"Applying different filtering levels to the environment map creates more or less glossy surfaces from
mirror-like to completely diffuse."  A unit sphere is viewed orthographically along −z (view vector
v = (0, 0, 1) towards the camera); per pixel the normal n gives the reflection r = 2(n·v)n − v, and the
colour is the glossiness lookup :func:`ibl_ref.knuth2014.gloss_lookup.lookup` of the sqrtcos pyramid at (r, g)
(the PEM lookup of Eq. 5 without occlusion; no renderer needed).  Environment: the synthetic
``studio`` map of :func:`ibl_ref.synthetic.synthetic_envs.make_env`.

Files: ``fig3_spheres.json`` (linear RGB per sphere, float32-rounded), plot ``fig3.png`` (tone-mapped
x/(1+x) after scaling by the mirror sphere's 90th percentile).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..atomic import write_json
from . import Param, resolve_params
from ..figures import pyplot
from ..figures import save_figure
from ..knuth2014.pyramid import build_pyramid
from ..rendering.sphere_render import render_sphere_lookup
from ..synthetic.synthetic_envs import make_env

NAME = "fig3"
DESCRIPTION = "Knuth 2014 Fig. 3: a row of spheres from mirror to diffuse via the sqrtcos pyramid lookup"
PAPER = "Knuth et al. 2014, Fig. 3 (glossiness row from one filter pyramid; Eq. 3 lookup)"
IN_QUICK_REPRODUCE = True
PARAMS = (
    Param("face_size", 256, 64, "environment cube face size N (texels)"),
    Param("pixels", 128, 48, "sphere image size (pixels)"),
    Param("gloss", (1.0, 0.995, 0.98, 0.95, 0.9, 0.75, 0.5, 0.0), None, "glossiness values g, mirror (1) to diffuse (0)"),
    Param("environment", "studio", None, "synthetic environment (ibl_ref.synthetic.synthetic_envs.make_env name)"),
)
RUNTIME = {"quick": "0.4 s (load 0.3)", "full": "5 s (load 3.4)"}
OUTPUTS = ("fig3_spheres.json", "fig3.png")

GLOSS = PARAMS[2].default


def run(out_dir: Path, quick: bool = False, **params) -> dict:

    p = resolve_params(__name__, quick, params)
    n, px = p["face_size"], p["pixels"]
    env_name = f"synthetic_envs.{p['environment']}"
    pyr = build_pyramid(make_env(p["environment"], n=n), "sqrtcos")
    spheres = [render_sphere_lookup(pyr, g, px).astype(np.float32).round(6).tolist() for g in p["gloss"]]
    write_json(Path(out_dir) / "fig3_spheres.json", {"face_size": n, "pixels": px, "environment": env_name,
                                                     "kernel": "sqrtcos", "gloss": list(p["gloss"]),
                                                     "images_linear_rgb": spheres})
    return {"face_size": n, "pixels": px, "environment": env_name}


def plot(out_dir: Path) -> list[Path]:

    plt = pyplot()

    d = json.loads((Path(out_dir) / "fig3_spheres.json").read_text())
    imgs = [np.asarray(a, dtype=np.float64) for a in d["images_linear_rgb"]]
    ref = imgs[0][imgs[0].sum(-1) > 0]
    scale = np.percentile(ref, 90) if ref.size else 1.0
    fig, axes = plt.subplots(1, len(imgs), figsize=(1.6 * len(imgs), 2.0))
    for ax, img, g in zip(axes, imgs, d["gloss"]):
        x = img / max(scale, 1e-12)
        ax.imshow(np.clip(x / (1 + x), 0, 1) ** (1 / 2.2))
        ax.set_title(f"g = {g}" + (" (mirror)" if g == 1 else " (s = 1)" if g == 0 else f" (s = {1 / (1 - g):.3g})"),
                     fontsize=8)
        ax.axis("off")
    fig.suptitle(f"Fig. 3 reproduction: orthographic spheres, look-up in one sqrtcos pyramid "
                 f"({d['environment']}, {d['face_size']}² faces); one tone map for all", fontsize=9)
    fig.tight_layout()
    p = Path(out_dir) / "fig3.png"
    save_figure(fig, p, dpi=110)
    return [p]
