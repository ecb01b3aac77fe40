"""Lights alone vs PEMs vs exact, for glossy lobes (Knuth et al. 2014 Sec. 3: "Existing methods substitute the
environment map with a set of light sources which is problematic when dealing with high gloss surfaces").

Scene: unoccluded sphere, orthographic camera on +Z looking down −Z (image row 0 = +y), view v = +Z;
per pixel the reflection direction r = 2(n·v)n − v (:func:`ibl_ref.rendering.sphere_render.orthographic_sphere`).

Shading model (stated): the *normalised* Phong lobe of exponent s around r (the lobe average that the
filter pyramid approximates, docs/background.md §2),

    I(r) = ∫ L(ω) max(r·ω, 0)^s dω / W_s(r),   W_s(r) = ∫ max(r·ω, 0)^s dω  (≈ 2π/(s+1)),

without the n·ω factor or the hemisphere clip (Eq. 4 integrates over Ω⁺; for a lobe around r the clip
only matters for s ≈ 1 at grazing angles and is the same for all three estimates).

* ``exact``: quadrature over the environment's texels, each split into k×k sub-texels with exact solid
  angles (:func:`ibl_ref.environment.envmap.texel_solid_angles` of the N·k grid), radiance piecewise constant; the
  weights are evaluated as exp(s·(log c − log c_max)) (no underflow at s = 1000).  Cross-checked against
  :func:`ibl_ref.groundtruth.phong_convolution.convolve_exact` at texel centres (``exact_check_max_rel``).
* ``lights``: the median-cut lights as point lights, I = Σ_i rgb_i max(r·ω_i, 0)^s / W_s(r), rgb_i = ∫_region L dω
  (same W_s quadrature as ``exact``, so only the light discretisation differs).
* ``pem``: Σ_i lookup(PEM_i, r, g) with g = 1 − 1/s (Eq. 3): the paper's method without shadows.
* ``pyramid``: lookup of the full map's pyramid (= ``pem`` by linearity; ``rel_l1_pem_vs_pyramid`` shows
  the float32 rounding of the stored PEMs).

Error: relative L1 over the sphere's pixels and the three channels, Σ|I − I_exact| / Σ|I_exact|.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..progress import track

from . import Param, resolve_params
from ..atomic import read_csv
from ..atomic import write_csv
from ..atomic import write_json
from ..environment.envmap import texel_directions
from ..environment.envmap import texel_solid_angles
from ..figures import pyplot
from ..figures import save_figure
from ..knuth2014.gloss_lookup import lookup
from ..knuth2014.median_cut import median_cut
from ..knuth2014.pem import build_pems
from ..knuth2014.pyramid import build_pyramid
from ..rendering.sphere_render import orthographic_sphere
from ..synthetic.synthetic_envs import make_env

NAME = "lights-vs-error"
DESCRIPTION = "sphere lit by median-cut point lights vs PEM lookups vs exact Phong convolution, s = 1..1000"
PAPER = "Knuth et al. 2014, Sec. 1 and 3 (point lights alone fail for glossy surfaces; PEMs do not)"
IN_QUICK_REPRODUCE = True
PARAMS = (
    Param("face_size", 64, 32, "environment cube face size N"),
    Param("sphere_pixels", 128, 48, "sphere image size (pixels)"),
    Param("supersample", 2, None, "sub-texels per texel side of the exact quadrature"),
    Param("light_counts", (6, 24, 96, 384), (6, 24, 96), "median-cut light counts"),
)
RUNTIME = {"quick": "14 s (load 0.3)", "full": "14 min (load 16; 5 min 6 s CPU)"}
OUTPUTS = ("lights_vs_error.csv", "lights_vs_error_images.json", "lights_vs_error_meta.json", "lights_vs_error.png",
           "lights_vs_error_spheres.png")

S_VALUES = (1.0, 10.0, 100.0, 1000.0)
ENVS = ("sky_sun", "studio")


def exact_lobe_average(cube, r, s, supersample: int = 1, chunk: int = 512):
    """Brute-force normalised Phong lobe average at directions r (P, 3); also returns W_s(r)."""

    n = cube.shape[1]
    m = n * supersample
    dirs = texel_directions(m).reshape(-1, 3)
    omega = np.broadcast_to(texel_solid_angles(m), (6, m, m)).reshape(-1)
    rad = np.repeat(np.repeat(cube, supersample, axis=1), supersample, axis=2).reshape(-1, cube.shape[3])
    log_om = np.log(omega)
    out = np.empty((r.shape[0], cube.shape[3]))
    wsum = np.empty(r.shape[0])
    for a in range(0, r.shape[0], chunk):
        c = r[a:a + chunk] @ dirs.T
        pos = c > 0
        logc = np.full(c.shape, -np.inf)
        np.log(c, out=logc, where=pos)
        cmax = logc.max(axis=1, keepdims=True)
        w = np.exp(s * (logc - cmax) + log_om)
        den = w.sum(axis=1)
        out[a:a + chunk] = (w @ rad) / den[:, None]
        wsum[a:a + chunk] = den * np.exp(s * cmax[:, 0])
    return out, wsum


def point_lights(lights, r, s, wsum):
    """Σ_i rgb_i max(r·ω_i,0)^s / W_s(r)."""
    c = np.clip(r @ lights.directions.T, 0.0, None)
    return (c**s) @ lights.rgb / wsum[:, None]


def rel_l1(a, ref):
    return float(np.abs(a - ref).sum() / np.abs(ref).sum())


def run(out_dir: Path, quick: bool = False, **params) -> dict:

    out_dir = Path(out_dir)
    p = resolve_params(__name__, quick, params)
    n, res, ss, counts = p["face_size"], p["sphere_pixels"], p["supersample"], p["light_counts"]
    img_lights = 24
    mask, _, r = orthographic_sphere(res)
    rows, images, checks = [], {}, {}
    t0 = time.perf_counter()
    for env in track(ENVS, "lights-vs-error: environments", unit="env"):
        cube = make_env(env, n)
        full = build_pyramid(cube)
        exact = {}
        for s in S_VALUES:
            exact[s] = exact_lobe_average(cube, r, s, ss)
        # cross-check the brute force against the exact convolution of ibl_ref.groundtruth.phong_convolution at texel
        # centres of an 8² output
        from ..groundtruth.phong_convolution import convolve_exact
        from ..environment.envmap import texel_directions

        worst = 0.0
        for s in (1.0, 100.0):
            ref = convolve_exact(cube, s, supersample=ss, out_size=8).reshape(-1, 3)
            mine, _ = exact_lobe_average(cube, texel_directions(8).reshape(-1, 3), s, ss)
            worst = max(worst, float(np.max(np.abs(mine - ref) / np.abs(ref))))
        checks[env] = worst
        for L in counts:
            ls = median_cut(cube, L, "per-face")
            pems = build_pems(cube, ls)
            for s in S_VALUES:
                g = 1.0 - 1.0 / s  # Eq. 3
                ex, wsum = exact[s]
                il = point_lights(ls, r, s, wsum)
                ip = pems.full_lookup(r, g).astype(np.float64)
                iy = lookup(full, r, g, calibration=pems.calibration).astype(np.float64)
                rows.append({"env": env, "face_size": n, "lights": L, "s_phong": s, "g": g,
                             "rel_l1_lights": rel_l1(il, ex), "rel_l1_pem": rel_l1(ip, ex),
                             "rel_l1_pyramid": rel_l1(iy, ex), "rel_l1_pem_vs_pyramid": rel_l1(ip, iy)})
                if L == img_lights and s in (10.0, 1000.0):
                    for name, val in (("exact", ex), ("lights", il), ("pem", ip)):
                        img = np.zeros((res, res, 3))
                        img[mask] = val
                        images[f"{env}|{int(s)}|{name}"] = np.round(img, 6).tolist()
    write_csv(out_dir / "lights_vs_error.csv", rows, comment=(
        "Relative L1 (sum over sphere pixels and RGB) vs the exact normalised Phong lobe average. lights = median-cut "
        "point lights (per-face); pem = sum of PEM lookups at g = 1 - 1/s; pyramid = full-map pyramid lookup."))
    write_json(out_dir / "lights_vs_error_images.json", {"res": res, "lights": img_lights, "images": images})
    write_json(out_dir / "lights_vs_error_meta.json", {
        "face_size": n, "sphere_res": res, "exact_supersample": ss, "light_counts": list(counts),
        "exact_check_max_rel_vs_convolve_exact": checks, "time_s": round(time.perf_counter() - t0, 2)})
    best = {}
    for s in S_VALUES:
        sel = [x for x in rows if x["s_phong"] == s]
        best[str(int(s))] = {"lights_min": min(x["rel_l1_lights"] for x in sel),
                             "pem_max": max(x["rel_l1_pem"] for x in sel)}
    return {"by_s": best, "exact_check": checks}


def plot(out_dir: Path) -> list:
    import json


    plt = pyplot()


    out_dir = Path(out_dir)
    rows = read_csv(out_dir / "lights_vs_error.csv")
    paths = []
    fig, axes = plt.subplots(1, len(ENVS), figsize=(11, 4.2), sharey=True, layout="constrained")
    same = True  # do the PEM curves of the fewest and the most lights coincide (they should: see below)?
    for ax, env in zip(axes, ENVS):
        sel = [x for x in rows if x["env"] == env]
        counts = sorted({int(x["lights"]) for x in sel})
        for L in counts:
            q = [x for x in sel if int(x["lights"]) == L]
            ax.plot([float(x["s_phong"]) for x in q], [float(x["rel_l1_lights"]) for x in q], "o-",
                    label=f"{L} point lights")
        pem = {}
        for L, mk in ((counts[0], "s"), (counts[-1], "^")):
            q = [x for x in sel if int(x["lights"]) == L]
            pem[L] = np.array([float(x["rel_l1_pem"]) for x in q])
            ax.plot([float(x["s_phong"]) for x in q], pem[L], "k--", marker=mk,
                    mfc="none", label=f"PEMs ({L})")
        a_, b_ = pem[counts[0]], pem[counts[-1]]
        same = same and a_.shape == b_.shape and bool(np.allclose(a_, b_, rtol=1e-6, atol=0))
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("Phong exponent s")
        ax.set_title(env)
        ax.grid(True, which="both", lw=0.3)
    axes[0].set_ylabel("relative L1 error vs exact (sphere)")
    axes[-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    note = (f"\nthe PEM curves of {counts[0]} and {counts[-1]} lights coincide (markers on top of each other): "
            "without occlusion the PEMs sum to the pyramid of the whole map" if same else "")
    fig.suptitle("Unoccluded glossy sphere: median-cut point lights vs PEM lookups (normalised Phong lobe)" + note,
                 fontsize=9)
    p = out_dir / "lights_vs_error.png"
    save_figure(fig, p, dpi=120)
    paths.append(p)

    data = json.loads((out_dir / "lights_vs_error_images.json").read_text())
    keys = list(data["images"])
    groups = sorted({k.rsplit("|", 1)[0] for k in keys})
    fig, axes = plt.subplots(len(groups), 3, figsize=(7, 2.4 * len(groups)))
    axes = np.atleast_2d(axes)
    for i, grp in enumerate(groups):
        ref = np.array(data["images"][f"{grp}|exact"])
        scale = np.percentile(ref[ref > 0], 99) if np.any(ref > 0) else 1.0
        for j, name in enumerate(("exact", "lights", "pem")):
            img = np.array(data["images"][f"{grp}|{name}"]) / scale
            axes[i, j].imshow(np.clip(img, 0, 1) ** (1 / 2.2), interpolation="nearest")
            env, s = grp.split("|")
            axes[i, j].set_title(f"{env} s={s}: {name}" + (f" ({data['lights']})" if name != "exact" else ""), fontsize=7)
            axes[i, j].axis("off")
    fig.suptitle(f"exact Phong lobe vs {data['lights']} median-cut point lights vs {data['lights']} PEM lookups;\n"
                 "each row scaled to its exact image's 99th percentile (γ 2.2)", fontsize=8)
    fig.tight_layout()
    p = out_dir / "lights_vs_error_spheres.png"
    save_figure(fig, p, dpi=120)
    paths.append(p)
    return paths
