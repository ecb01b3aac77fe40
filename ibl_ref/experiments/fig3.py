"""Knuth et al. (2014) Fig. 3: spheres from mirror (g = 1) to diffuse (g = 0) from one filter pyramid.

"Applying different filtering levels to the environment map creates more or less glossy surfaces from
mirror-like to completely diffuse."  A unit sphere is viewed orthographically along −z (view vector
v = (0, 0, 1) towards the camera); per pixel the normal n gives the reflection r = 2(n·v)n − v, and the
colour is the glossiness lookup :func:`ibl_ref.gloss_lookup.lookup` of the sqrtcos pyramid at (r, g)
(the PEM lookup of Eq. 5 without occlusion; no renderer needed).  Environment: the synthetic
``studio`` map of :func:`ibl_ref.synthetic_envs.make_env`.

Files: ``fig3_spheres.json`` (linear RGB per sphere, float32-rounded), plot ``fig3.png`` (tone-mapped
x/(1+x) after scaling by the mirror sphere's 90th percentile).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..atomic import write_json

NAME = "fig3"
DESCRIPTION = "Knuth 2014 Fig. 3: a row of spheres from mirror to diffuse via the sqrtcos pyramid lookup"
IN_QUICK_REPRODUCE = True

GLOSS = (1.0, 0.995, 0.98, 0.95, 0.9, 0.75, 0.5, 0.0)


def _environment(n: int):
    from ..synthetic_envs import make_env

    return make_env("studio", n=n), "synthetic_envs.studio"


def render_sphere(pyr, g: float, px: int) -> np.ndarray:
    """(px, px, C) image of the unit sphere; background 0."""
    from ..gloss_lookup import lookup

    c = (np.arange(px) + 0.5) / px * 2 - 1
    x, y = np.meshgrid(c, -c)  # y up
    inside = x * x + y * y < 1.0
    nrm = np.stack([x, y, np.sqrt(np.clip(1 - x * x - y * y, 0, 1))], axis=-1)[inside]
    v = np.array([0.0, 0.0, 1.0])
    r = 2.0 * (nrm @ v)[:, None] * nrm - v  # reflection of the view vector
    img = np.zeros((px, px, pyr.levels[0].shape[3]))
    img[inside] = lookup(pyr, r, g)
    return img


def run(out_dir: Path, quick: bool) -> dict:
    from ..pyramid import build_pyramid

    n, px = (64, 48) if quick else (256, 128)
    env, env_name = _environment(n)
    pyr = build_pyramid(env, "sqrtcos")
    spheres = [render_sphere(pyr, g, px).astype(np.float32).round(6).tolist() for g in GLOSS]
    write_json(Path(out_dir) / "fig3_spheres.json", {"face_size": n, "pixels": px, "environment": env_name,
                                                     "kernel": "sqrtcos", "gloss": list(GLOSS),
                                                     "images_linear_rgb": spheres})
    return {"face_size": n, "pixels": px, "environment": env_name}


def plot(out_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..atomic import atomic_path

    d = json.loads((Path(out_dir) / "fig3_spheres.json").read_text())
    imgs = [np.asarray(a, dtype=np.float64) for a in d["images_linear_rgb"]]
    ref = imgs[0][imgs[0].sum(-1) > 0]
    scale = np.percentile(ref, 90) if ref.size else 1.0
    fig, axes = plt.subplots(1, len(imgs), figsize=(1.6 * len(imgs), 2.0))
    for ax, img, g in zip(axes, imgs, d["gloss"]):
        x = img / max(scale, 1e-12)
        ax.imshow(np.clip(x / (1 + x), 0, 1) ** (1 / 2.2))
        ax.set_title(f"g={g}", fontsize=8)
        ax.axis("off")
    fig.suptitle(f"Fig. 3 reproduction ({d['environment']}, sqrtcos pyramid, N={d['face_size']})", fontsize=9)
    fig.tight_layout()
    p = Path(out_dir) / "fig3.png"
    with atomic_path(p) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return [p]
