"""Filter pyramid vs exact-lobe chain: lookup error, build time and memory (the prefilter's speed/accuracy trade).

Knuth et al. (2014, Sec. 3.2) approximate the Phong lobe average of Eq. 4 by one trilinear lookup in a 5×5-filtered
MIP pyramid.  :mod:`ibl_ref.knuth2014.lobe_chain` keeps that lookup but fills the levels with exact lobe averages.  This
experiment measures, per environment and Phong exponent s (g = 1 − 1/s, Eq. 3), the error of one lookup against the
exact lobe average (:func:`ibl_ref.rendering.reference_render.lobe_average`: dense sum over every texel with exact solid
angles) at random directions, for these configurations of the prefilter registry (:data:`PREFILTERS`: label →
method of :data:`ibl_ref.prefilter.registry.PREFILTER_METHODS` and its parameters; any level-chain method,
:class:`ibl_ref.prefilter.level_chain.LevelChainPrefilter`, can be added there):

* ``pyramid-sqrtcos`` / ``pyramid-box``: the paper's pyramid (``pyramid``: 2×2 mean + filter, default calibration);
* ``pyramid-sqrtcos-solid-angle``: the same with the energy-exact solid-angle 2×2 shrink;
* ``chain-f4`` / ``chain-f2`` / ``chain-f1.41``: the exact-lobe chain (``exact-lobe``) with exponent ratio 4, 2, √2
  per level.

Metrics: relative L1 Σ|a − b| / Σ|b| over directions and channels (``rel_l1``), the largest per-direction relative
error of the luminance-like channel mean (``rel_max``), the energy ratio Σa/Σb, the relative L1 at the best constant
level (``rel_l1_best_level``, :func:`best_constant_level`: the floor of the prefilter under any glossiness
calibration); build time (s, wall, this machine)
and memory (MiB, the levels stored as float32 RGB — the paper stores RGBA16F).

Files: ``lobe_chain.csv`` (one row per environment × prefilter × s), ``lobe_chain_meta.json``.
Plot: ``lobe_chain.png`` (error vs s per environment; legend with build time and memory).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..knuth2014.gloss_lookup import LEVEL_STEP, best_constant_level, level_fit_directions
from ..progress import track
from ..atomic import read_csv, write_csv, write_json
from . import params_from_settings, settings_with
from ..conventions import phong_exponent
from ..figures import pyplot
from ..figures import save_figure
from ..prefilter.registry import build_prefilter
from ..rendering.reference_render import lobe_average
from ..synthetic.synthetic_envs import make_env

NAME = "lobe-chain"
DESCRIPTION = "filter pyramid vs exact-lobe chain: lookup error vs s, build time and memory"
PAPER = ("Knuth et al. 2014, Sec. 3.2 / Eq. 3-4: the filter pyramid's lookup vs the exact Phong lobe average, "
         "and the exact-lobe chain (not in the paper)")
IN_QUICK_REPRODUCE = True
RUNTIME = {"quick": "9 s (load 0.3)", "full": "13 min (load 13; 4 min 21 s CPU)"}
OUTPUTS = ("lobe_chain.csv", "lobe_chain_meta.json", "lobe_chain.png")

#: label → (prefilter method, its parameters)
PREFILTERS = {
    "pyramid-sqrtcos": ("pyramid", dict(kernel="sqrtcos")),
    "pyramid-box": ("pyramid", dict(kernel="box")),
    "pyramid-sqrtcos-solid-angle": ("pyramid", dict(kernel="sqrtcos", shrink="solid_angle")),
    "chain-f4": ("exact-lobe", dict(factor=4.0)),
    "chain-f2": ("exact-lobe", dict(factor=2.0)),
    "chain-f1.41": ("exact-lobe", dict(factor=float(np.sqrt(2.0)))),
}


def settings(quick: bool) -> dict:
    if quick:
        return dict(env_size=32, envs=["sky_sun"], n_dirs=1500, s_values=[1, 2, 4, 10, 30, 100, 300])
    return dict(env_size=64, envs=["sky_sun", "studio"], n_dirs=4000,
                s_values=[1, 1.5, 2, 3, 5, 7, 10, 15, 20, 30, 50, 70, 100, 200, 300, 500, 1000])


PARAMS = params_from_settings(settings, {"envs": "synthetic environments", "n_dirs": "random test directions",
                                         "s_values": "Phong exponents s"})


def build(name: str, env):
    """The prefilter of one :data:`PREFILTERS` label (a level chain: ``.pyramid``, ``.level_of``, ``.lookup``)."""

    method, params = PREFILTERS[name]
    return build_prefilter(env, method, **params)


def run(out_dir: Path, quick: bool = False, **params) -> dict:

    out_dir = Path(out_dir)
    st = settings_with(__name__, quick, params)
    d = level_fit_directions(st["n_dirs"])
    rows, meta_builds = [], {}
    t_start = time.perf_counter()
    for env_name in track(st["envs"], "lobe-chain: environments", unit="env"):
        env = make_env(env_name, n=st["env_size"])
        exact = {s: lobe_average(env, d, float(s)) for s in st["s_values"]}
        for pf in PREFILTERS:
            t0 = time.perf_counter()
            prefilter = build(pf, env)  # the pyramid's calibration: the shipped table
            t_build = time.perf_counter() - t0
            pyr = prefilter.pyramid
            mib = sum(int(np.prod(lev.shape[:3])) * 3 * 4 for lev in pyr.levels) / 2**20
            meta_builds[f"{env_name}/{pf}"] = dict(build_time_s=t_build, memory_MiB=mib,
                                                   face_sizes=[int(lev.shape[1]) for lev in pyr.levels])
            per_level = [pyr.sampler(k).bilinear(d) for k in range(pyr.max_level + 1)]
            for s in st["s_values"]:
                s_g = phong_exponent(1.0 - 1.0 / float(s))  # the look-up at the table's g (Eq. 3)
                a = prefilter.lookup(d, s_g)
                b = exact[s]
                per = np.abs(a - b).mean(axis=1) / np.maximum(b.mean(axis=1), 1e-300)
                rel_l1 = float(np.abs(a - b).sum() / np.abs(b).sum())
                best, best_level = best_constant_level(per_level, b)
                if rel_l1 < best:  # the calibrated level itself is a candidate too
                    best, best_level = rel_l1, float(np.mean(prefilter.level_of(s_g)))
                rows.append(dict(env=env_name, prefilter=pf, s_phong=float(s), g=1.0 - 1.0 / float(s),
                                 rel_l1=rel_l1, rel_max=float(per.max()),
                                 energy_ratio=float(a.sum() / b.sum()), rel_l1_best_level=best,
                                 best_level=best_level, build_time_s=t_build, memory_MiB=mib))
    cols = ["env", "prefilter", "s_phong", "g", "rel_l1", "rel_max", "energy_ratio", "rel_l1_best_level",
            "best_level", "build_time_s", "memory_MiB"]
    write_csv(out_dir / "lobe_chain.csv", rows, cols,
              comment=f"lookup vs exact lobe average at {st['n_dirs']} random directions, env {st['env_size']}^2; "
                      "rel_l1 = sum|a-b|/sum|b|; rel_l1_best_level = the same for the best constant level "
                      f"(grid {LEVEL_STEP}, incl. the calibrated one; the floor under any calibration), best_level "
                      "its level (0 = finest); build time wall clock on this machine; memory float32 RGB")
    summary = {}
    for env_name in st["envs"]:
        for pf in PREFILTERS:
            r = [x for x in rows if x["env"] == env_name and x["prefilter"] == pf]
            summary[f"{env_name}/{pf}"] = dict(rel_l1_max_over_s=max(x["rel_l1"] for x in r),
                                               rel_l1_at_s1=r[0]["rel_l1"],
                                               rel_l1_best_level_at_s1=r[0]["rel_l1_best_level"])
    write_json(out_dir / "lobe_chain_meta.json", dict(settings=st, builds=meta_builds, summary=summary,
                                                      total_time_s=time.perf_counter() - t_start))
    return summary


def plot(out_dir: Path) -> list:

    plt = pyplot()

    out_dir = Path(out_dir)
    rows = read_csv(out_dir / "lobe_chain.csv")
    envs = list(dict.fromkeys(q["env"] for q in rows))
    fig, axes = plt.subplots(1, len(envs), figsize=(6.5 * len(envs) + 2.0, 4.5), squeeze=False, layout="constrained")
    for ax, env_name in zip(axes[0], envs):
        for pf in dict.fromkeys(q["prefilter"] for q in rows):
            r = [q for q in rows if q["env"] == env_name and q["prefilter"] == pf]
            x = [float(q["s_phong"]) for q in r]
            y = [float(q["rel_l1"]) for q in r]
            ls = "--" if pf.startswith("pyramid") else "-"
            ax.plot(x, y, ls, marker="o", ms=3,
                    label=f"{pf} ({float(r[0]['build_time_s']):.2f} s, {float(r[0]['memory_MiB']):.2f} MiB)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("Phong exponent s (g = 1 − 1/s)")
        ax.set_ylabel("relative L1 of one lookup vs exact lobe average")
        ax.set_title(f"{env_name}: filter pyramid vs exact-lobe chain")
        ax.axhline(0.05, color="gray", lw=0.8, ls=":", label="5 %")
    axes[0, -1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0),
                       title=f"prefilter ({envs[-1]}: build time, memory)", title_fontsize=7)
    p = out_dir / "lobe_chain.png"
    save_figure(fig, p, dpi=100)
    return [p]
