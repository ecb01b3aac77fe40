"""Manson & Sloan 2016's error of "32 importance samples with LOD selection", reproduced or refuted on the lab's
environments.

Manson & Sloan 2016, "Fast Filtering of Reflection Probes" (EGSR 2016, Computer Graphics Forum 35(4)), Fig. 1:
against analytically evaluated GGX reference levels of a cube map's MIP chain, "the L1 errors are 0.0848 for our
method and 0.4201 for importance sampling" (32 importance samples with LOD selection, i.e. filtered importance
sampling, Křivánek & Colbert 2008; one HDR probe, 128² base faces).  The paper's normalisation of that L1 error is
not certain, so this experiment measures the same comparison under several.

The chain: base faces of ``base_size``² texels, ``n_levels`` levels of faces ``base_size >> ℓ``, level ℓ at the
roughness of ``mapping`` (default ``filament``, r(2 − r); :data:`ibl_ref.prefilter.mip_mappings.ROUGHNESS_MAPPINGS`).
A level of roughness 0 (level 0 under Filament's mapping) is the source itself, the same for every method, and is
left out.  For every other level ℓ (roughness r_ℓ, faces s_ℓ²):

* ``exact`` — the exact ``n = v = r`` GGX prefilter (Karis 2013, Eq. 8) at the texel centres of the level
  (:func:`ibl_ref.groundtruth.ggx_convolution.convolve_ggx_levels`, every texel within ``rtol``): the reference;
* ``fis`` — filtered importance sampling (:func:`ibl_ref.prefilter.krivanek_colbert2008.prefilter_fis`: each
  sample read from the box-filtered source pyramid at the level ``max(½ log2(Ω_s/Ω_p) + 1, 0)`` of its pdf and
  the texel solid angle) with each of ``fis_samples`` samples per texel;
* ``is`` — plain importance sampling (:func:`ibl_ref.prefilter.karis2013.prefilter_importance`, Karis's
  ``PrefilterEnvMap``, every sample read from the full-resolution source) with ``is_samples``;

each with each of ``sequences`` (``hammersley``: Karis's 2-D Hammersley set, the same for every texel;
``random``: independent uniform numbers per texel, seeded with ``(seed, ℓ)``).  Errors are measured ``at``:

* ``level-texels`` — the level's own texel centres (the stored texels against the reference; the paper's
  comparison).  The exact level's error there is zero by construction (it *is* the reference, within ``rtol``);
* ``finer-texels`` — the texel centres of a face twice as fine (2 s_ℓ, at most the base), each level read with the
  seam-aware bilinear look-up (:class:`ibl_ref.environment.sampling.CubeSampler`) against the exact prefilter
  there: what the stored level loses between its texel centres.  The ``exact`` rows there are the **exact chain's
  discretisation** — the error no filter storing s_ℓ² texels per face avoids — the floor to which FIS-32's error is
  compared (Manson & Sloan's 0.4201 / 0.0848 = 4.95).

Normalisations (solid-angle weighted, Ω_j the exact texel solid angle, mean over the colour channels):

* ``mae_radiance`` — mean absolute error in the environment's radiance units, Σ|a − e|Ω / Σ Ω (/ channels);
* ``rel_l1_frac`` — relative L1, Σ|a − e|Ω / Σ|e|Ω;
* ``mae_env_mean_frac`` — ``mae_radiance`` of the environment scaled to mean radiance 1 (``mae_radiance`` /
  ``env_mean_radiance``, the environment's Σ L Ω / 4π averaged over channels);
* ``mean_rel_err_frac`` — the mean per-texel relative error Σ(|a − e|/e)Ω / Σ Ω (/ channels);

and ``bias_frac`` Σ(a − e)Ω / Σ eΩ, ``rel_err_max_frac`` the largest |a − e|/e.  A chain's error is the mean over
its filtered levels (every level covers the sphere, so this is the solid-angle-weighted mean over the chain).
Environments: the synthetic sky with a small 1e5 sun (``sky_sun``) and the real probes ``city``, ``courtyard``,
``forest``, ``studio`` (:func:`ibl_ref.experiments.method_zoo.environment`; a missing probe is skipped with the
reason).

Files: ``manson_sloan.csv`` (one row per environment × level × method × samples × sequence × at),
``manson_sloan_meta.json`` (settings, the chain, each environment's mean radiance, the summary with the verdict,
skipped items, timings, load), ``manson_sloan.md`` (the tables).  Plot (reads only the CSV): ``manson_sloan.png``
(error per level for each method; FIS-32's chain error under each normalisation against the paper's 0.4201 and
0.0848).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from ..atomic import atomic_write, read_csv, write_csv, write_json
from ..environment import envmap
from ..environment.sampling import CubeSampler
from ..errors import IBLError
from ..figures import pyplot, save_figure
from ..groundtruth.ggx_convolution import convolve_ggx_levels
from ..prefilter import karis2013
from ..prefilter.krivanek_colbert2008 import prefilter_fis, source_pyramid
from ..prefilter.mip_mappings import ROUGHNESS_MAPPINGS
from ..progress import track
from . import params_from_settings, power_of_two, settings_with
from .method_zoo import ENVS, environment

NAME = "manson-sloan"
DESCRIPTION = ("Manson & Sloan 2016's L1 error of FIS with 32 samples (0.42) against the exact GGX MIP levels, "
               "under several normalisations, per environment and level")
PAPER = ("Manson & Sloan 2016, Fast Filtering of Reflection Probes, Fig. 1 (L1 0.4201 for 32 importance samples with "
         "LOD selection, 0.0848 for their filter); Krivanek & Colbert 2008 (FIS); Karis 2013, Eq. 8 (the n = v = r "
         "prefilter)")
IN_QUICK_REPRODUCE = False
RUNTIME = {"quick": "4 s (load 3)", "full": "4 min 30 s (load 3.9)"}
OUTPUTS = ("manson_sloan.csv", "manson_sloan_meta.json", "manson_sloan.md", "manson_sloan.png")

#: the paper's Fig. 1 numbers: 32 importance samples with LOD selection, and its own filter
PAPER_FIS32_L1 = 0.4201
PAPER_OWN_L1 = 0.0848
#: a measured error "matches" the paper's 0.4201 within this relative distance (the verdict of :func:`summarize`)
MATCH_TOL = 0.10
#: the normalisations (module docstring): CSV column → label
NORMALISATIONS = {"mae_radiance": "mean abs. error, radiance units",
                  "rel_l1_frac": "relative L1",
                  "mae_env_mean_frac": "mean abs. error, environment at mean radiance 1",
                  "mean_rel_err_frac": "mean per-texel relative error"}
#: where the errors are measured (module docstring)
AT = ("level-texels", "finer-texels")
#: the CSV's columns
COLUMNS = ["env", "base_face_size_texels", "n_levels", "mapping", "level", "roughness", "level_face_size_texels",
           "method", "samples", "sequence", "at", "eval_face_size_texels", "n_directions", "env_mean_radiance",
           "mae_radiance", "rel_l1_frac", "mae_env_mean_frac", "mean_rel_err_frac", "bias_frac", "rel_err_max_frac",
           "ref_rel_bound_max", "fis_lod_mean", "method_s"]


def _mapping_value(v):
    if v not in ROUGHNESS_MAPPINGS:
        raise IBLError(f"mapping must be one of {', '.join(ROUGHNESS_MAPPINGS)}, got {v!r}")
    return v


def _sequence_value(v):
    return karis2013.check_sequence(v)


def _levels_value(v):
    if not 2 <= v <= 16:
        raise IBLError(f"n_levels must be in [2, 16], got {v!r}")
    return v


def settings(quick: bool) -> dict:
    if quick:
        return dict(envs=["sky_sun"], base_size=16, n_levels=5, mapping="filament", fis_samples=[16, 32, 64, 256],
                    is_samples=[32], sequences=["hammersley", "random"], seed=1, rtol=1e-4, probe_dir="")
    return dict(envs=list(ENVS), base_size=128, n_levels=6, mapping="filament", fis_samples=[16, 32, 64, 256],
                is_samples=[32], sequences=["hammersley", "random"], seed=1, rtol=1e-4, probe_dir="")


PARAMS = params_from_settings(
    settings,
    {"envs": "environments: sky_sun and the probes city, courtyard, forest, studio",
     "base_size": "base face size of the chain (a power of two)",
     "n_levels": "levels of the chain, faces base_size >> level (level 0 of roughness 0 is the source: left out)",
     "mapping": "roughness of each level (filament: lod = r(2 - r)(N - 1))",
     "fis_samples": "samples per texel of filtered importance sampling (Krivanek & Colbert 2008)",
     "is_samples": "samples per texel of plain importance sampling (Karis 2013's PrefilterEnvMap)",
     "sequences": "sample sequences: hammersley (Karis's, the same for every texel), random (seeded per texel)",
     "seed": "seed of the random sequence (level l uses (seed, l))",
     "rtol": "largest relative error of the exact reference levels",
     "probe_dir": "folder of the probe EXRs (default: the method zoo's, ibl_ref.experiments.method_zoo.probe_dir)"},
    {"base_size": power_of_two, "mapping": _mapping_value, "sequences": _sequence_value,
     "n_levels": _levels_value})


# ------------------------------------------------------------------------------------------------------------------
# metrics
# ------------------------------------------------------------------------------------------------------------------
def env_mean_radiance(cube) -> float:
    """The environment's mean radiance Σ L Ω / 4π, averaged over the channels."""
    a = np.asarray(cube, dtype=np.float64)
    om = envmap.cube_solid_angles(a.shape[1])
    return float(np.einsum("fij,fijc->", om, a) / (om.sum() * a.shape[-1]))


def errors(approx, exact, omega, mean_radiance: float) -> dict:
    """The normalisations of the module docstring for (M, C) values at directions of solid angles ``omega`` (M,)."""
    a, e = np.asarray(approx, dtype=np.float64), np.asarray(exact, dtype=np.float64)
    w = np.asarray(omega, dtype=np.float64).reshape(-1, 1)
    if a.shape != e.shape or a.ndim != 2 or w.shape[0] != a.shape[0]:
        raise IBLError(f"errors: shapes {a.shape}, {e.shape} and {w.shape} do not match")
    d = a - e
    wsum, c = float(w.sum()), a.shape[1]
    rel = np.divide(np.abs(d), e, out=np.where(d == 0, 0.0, np.inf), where=e > 0)
    mae = float((np.abs(d) * w).sum() / (wsum * c))
    ew = float((np.abs(e) * w).sum())
    return {"mae_radiance": mae,
            "rel_l1_frac": float((np.abs(d) * w).sum() / ew) if ew > 0 else 0.0,
            "mae_env_mean_frac": mae / mean_radiance if mean_radiance > 0 else 0.0,
            "mean_rel_err_frac": float((rel * w).sum() / (wsum * c)),
            "bias_frac": float((d * w).sum() / ew) if ew > 0 else 0.0,
            "rel_err_max_frac": float(rel.max())}


def chain_levels(base: int, n_levels: int, mapping: str) -> list:
    """(level, roughness, face size) of the chain's levels of roughness > 0."""
    rough = ROUGHNESS_MAPPINGS[mapping].roughness(np.arange(n_levels), n_levels)
    out = [(lv, float(r), max(base >> lv, 1)) for lv, r in enumerate(np.atleast_1d(rough)) if r > 0]
    if not out:
        raise IBLError(f"{mapping} with {n_levels} levels has no level of roughness > 0")
    return out


def method_list(fis_samples, is_samples, sequences) -> list:
    """(method, samples, sequence) of the sampled prefilters, in table order."""
    return ([("is", int(s), q) for q in sequences for s in is_samples]
            + [("fis", int(s), q) for q in sequences for s in fis_samples])


def sampled_level(cube, method: str, roughness: float, samples: int, sequence: str, seed, size: int, pyramid):
    """One level of ``method`` (``"fis"`` or ``"is"``) at the texel centres of a face of ``size``: ``(level (6, s,
    s, C), mean FIS level of detail or None)``."""
    if method == "fis":
        out, info = prefilter_fis(cube, roughness, samples=samples, sequence=sequence, seed=seed, out_size=size,
                                  pyramid=pyramid, return_info=True)
        return out, info["lod_mean"]
    if method == "is":
        return karis2013.prefilter_importance(cube, roughness, samples=samples, sequence=sequence, seed=seed,
                                              out_size=size), None
    raise IBLError(f"method must be fis or is, got {method!r}")


def measure_environment(cube, *, base: int, n_levels: int, mapping: str, methods, seed: int, rtol: float,
                        env: str = "") -> tuple[list, dict]:
    """Every row of one environment (module docstring): ``(rows, meta)``."""
    cube = np.asarray(cube, dtype=np.float64)
    if cube.shape[1] != base:
        raise IBLError(f"the cube has {cube.shape[1]}² faces, the chain's base is {base}²")
    levels = chain_levels(base, n_levels, mapping)
    mean_l = env_mean_radiance(cube)
    t = time.perf_counter()
    pairs = [(r, s) for _, r, s in levels] + [(r, min(2 * s, base)) for _, r, s in levels]
    refs = convolve_ggx_levels(cube, pairs, rtol=rtol)
    ref_s = time.perf_counter() - t
    pyr = source_pyramid(cube)
    common = {"env": env, "base_face_size_texels": base, "n_levels": n_levels, "mapping": mapping,
              "env_mean_radiance": mean_l}
    rows, timings = [], {"references_s": ref_s, "methods_s": {}}
    for i, (lv, r, s) in enumerate(levels):
        fine = min(2 * s, base)
        (e_own, b_own), (e_fine, b_fine) = refs[i], refs[len(levels) + i]
        own = {"dirs": envmap.texel_directions(s).reshape(-1, 3), "om": envmap.cube_solid_angles(s).reshape(-1),
               "exact": e_own.reshape(6 * s * s, -1), "bound": float(b_own.max()), "size": s}
        fin = {"dirs": envmap.texel_directions(fine).reshape(-1, 3), "om": envmap.cube_solid_angles(fine).reshape(-1),
               "exact": e_fine.reshape(6 * fine * fine, -1), "bound": float(b_fine.max()), "size": fine}
        lev = {**common, "level": lv, "roughness": r, "level_face_size_texels": s}

        def add(method, samples, sequence, values, lod, seconds):
            for at, ev in zip(AT, (own, fin)):
                got = values.reshape(len(own["dirs"]), -1) if at == "level-texels" else \
                    CubeSampler(values).bilinear(ev["dirs"])
                rows.append({**lev, "method": method, "samples": samples, "sequence": sequence, "at": at,
                             "eval_face_size_texels": ev["size"], "n_directions": len(ev["dirs"]),
                             **errors(got, ev["exact"], ev["om"], mean_l), "ref_rel_bound_max": ev["bound"],
                             "fis_lod_mean": "" if lod is None else lod, "method_s": seconds})

        add("exact", "", "", e_own, None, "")
        for method, samples, sequence in methods:
            t = time.perf_counter()
            vals, lod = sampled_level(cube, method, r, samples, sequence, (seed, lv), s, pyr)
            dt = time.perf_counter() - t
            timings["methods_s"][f"{lv}/{method}-{samples}/{sequence}"] = dt
            add(method, samples, sequence, vals, lod, dt)
    return rows, {"env_mean_radiance": mean_l, "levels": [list(x) for x in levels], "timings": timings}


# ------------------------------------------------------------------------------------------------------------------
# summary and tables
# ------------------------------------------------------------------------------------------------------------------
def _sel(rows, **match):
    return [q for q in rows if all(str(q[k]) == str(v) for k, v in match.items())]


def chain_error(rows, col: str, **match) -> float:
    """Mean of ``col`` over the levels of the matching rows (one environment: the chain's error)."""
    qs = _sel(rows, **match)
    return float(np.mean([float(q[col]) for q in qs])) if qs else float("nan")


def summarize(rows) -> dict:
    """Per environment and over all of them: each method's chain error under every normalisation (at the level
    texels; the exact chain and the sampled chains also at the finer texels), FIS-32's ratio to the exact chain's
    discretisation, and the verdict on the paper's 0.4201."""
    envs = list(dict.fromkeys(q["env"] for q in rows))
    keys = list(dict.fromkeys((q["method"], str(q["samples"]), q["sequence"]) for q in rows))
    label = lambda m, s, q: "exact" if m == "exact" else f"{m}-{s}/{q}"  # noqa: E731
    per_env = {}
    for env in envs:
        per_env[env] = {at: {label(*k): {c: chain_error(rows, c, env=env, method=k[0], samples=k[1], sequence=k[2],
                                                        at=at) for c in NORMALISATIONS}
                             for k in keys} for at in AT}
    mean = {at: {label(*k): {c: float(np.mean([per_env[e][at][label(*k)][c] for e in envs])) for c in NORMALISATIONS}
                 for k in keys} for at in AT}
    fis32 = [label(*k) for k in keys if k[0] == "fis" and k[1] == "32"]
    ratio = {}
    for name in fis32:
        disc = mean["finer-texels"]["exact"]["rel_l1_frac"]
        ratio[name] = {"level_texels_over_exact_discretisation": mean["level-texels"][name]["rel_l1_frac"] / disc
                       if disc > 0 else float("inf"),
                       "finer_texels_over_exact_discretisation": mean["finer-texels"][name]["rel_l1_frac"] / disc
                       if disc > 0 else float("inf")}
    with32 = [label(*k) for k in keys if k[0] != "exact" and k[1] == "32"]
    return {"envs": envs, "per_env": per_env, "mean": mean, "fis32_ratio": ratio,
            "verdict": verdict(per_env, mean, with32)}


def verdict(per_env, mean, names) -> dict:
    """For each sampled method of 32 samples and each normalisation: its chain error at the level texels (mean
    over environments), its ratio to the paper's 0.4201, and whether it, or single environments, come within
    :data:`MATCH_TOL` of it."""
    out = {}
    for name in names:
        out[name] = {}
        for c in NORMALISATIONS:
            m = mean["level-texels"][name][c]
            out[name][c] = {"mean": m, "over_paper": m / PAPER_FIS32_L1,
                            "mean_matches": abs(m / PAPER_FIS32_L1 - 1) <= MATCH_TOL,
                            "envs_matching": [e for e in per_env if abs(per_env[e]["level-texels"][name][c]
                                                                        / PAPER_FIS32_L1 - 1) <= MATCH_TOL]}
    return out


def _f(v: float) -> str:
    return f"{v:.4g}"


def markdown(rows, summary: dict, st: dict) -> str:
    """The Markdown tables of :func:`summarize`."""
    envs = summary["envs"]
    lines = [f"# Manson & Sloan 2016, FIS-32's L1 error ({', '.join(envs)})", "",
             f"Chain: {st['base_size']}² base, {st['n_levels']} levels, mapping {st['mapping']}; levels of roughness "
             f"> 0 only. Paper: FIS-32 {PAPER_FIS32_L1}, their filter {PAPER_OWN_L1}.", ""]
    for at in AT:
        names = list(summary["mean"][at])
        lines += [f"## Chain error at the {at} (mean over environments)", "",
                  "| method | " + " | ".join(NORMALISATIONS.values()) + " |", "|---|" + "---|" * len(NORMALISATIONS)]
        for n in names:
            lines.append(f"| {n} | " + " | ".join(_f(summary["mean"][at][n][c]) for c in NORMALISATIONS) + " |")
        lines.append("")
    for name, r in summary["fis32_ratio"].items():
        lines.append(f"{name} / exact chain's discretisation (rel. L1): "
                     f"{r['level_texels_over_exact_discretisation']:.2f} (level texels), "
                     f"{r['finer_texels_over_exact_discretisation']:.2f} (finer texels); paper "
                     f"{PAPER_FIS32_L1 / PAPER_OWN_L1:.2f}.")
    lines.append("")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------------------------
# compute and plot steps
# ------------------------------------------------------------------------------------------------------------------
def run(out_dir: Path, quick: bool = False, **params) -> dict:
    out_dir = Path(out_dir)
    st = settings_with(__name__, quick, params)
    load0, t_start = os.getloadavg(), time.perf_counter()
    methods = method_list(st["fis_samples"], st["is_samples"], st["sequences"])
    rows, skipped, envs_meta = [], {}, {}
    for env_name in track(list(dict.fromkeys(st["envs"])), "manson-sloan: environment", unit="env"):
        t = time.perf_counter()
        cube, why = environment(env_name, st["base_size"], st["probe_dir"])
        if cube is None:
            skipped[env_name] = why
            continue
        got, meta = measure_environment(cube, base=st["base_size"], n_levels=st["n_levels"], mapping=st["mapping"],
                                        methods=methods, seed=st["seed"], rtol=st["rtol"], env=env_name)
        rows += got
        envs_meta[env_name] = dict(meta, total_s=time.perf_counter() - t)
    if not rows:
        raise IBLError("manson-sloan: every environment was skipped: "
                       + "; ".join(f"{k}: {v}" for k, v in skipped.items()))
    write_csv(out_dir / "manson_sloan.csv", rows, COLUMNS,
              comment="level of the chain (faces base >> level, roughness of the mapping) by method (exact: the "
                      "reference; fis: Krivanek & Colbert 2008; is: Karis 2013) against the exact n = v = r GGX "
                      "prefilter; at level-texels: the level's texel centres; finer-texels: texel centres of a face "
                      "of eval_face_size_texels, the level read bilinearly; errors solid-angle weighted, mean over "
                      "channels; mae_radiance in the environment's radiance units; mae_env_mean_frac = mae_radiance "
                      "/ env_mean_radiance")
    summary = summarize(rows)
    with atomic_write(out_dir / "manson_sloan.md") as fh:
        fh.write(markdown(rows, summary, st))
    write_json(out_dir / "manson_sloan_meta.json", dict(
        settings=st, paper={"fis32_l1": PAPER_FIS32_L1, "own_filter_l1": PAPER_OWN_L1,
                            "source": "Manson & Sloan 2016, Fig. 1 caption"},
        normalisations=NORMALISATIONS, levels=chain_levels(st["base_size"], st["n_levels"], st["mapping"]),
        environments=envs_meta, skipped=skipped, summary=summary, total_time_s=time.perf_counter() - t_start,
        load_average_start=list(load0), load_average_end=list(os.getloadavg())))
    return {"summary": summary, "skipped": skipped, "rows": len(rows)}


def plot(out_dir: Path) -> list:
    plt = pyplot()
    out_dir = Path(out_dir)
    rows = read_csv(out_dir / "manson_sloan.csv")
    envs = list(dict.fromkeys(q["env"] for q in rows))
    fig, axes = plt.subplots(1, 2, figsize=(11.5, 4.4), layout="constrained")
    ax = axes[0]
    keys = list(dict.fromkeys((q["method"], q["samples"], q["sequence"]) for q in rows
                              if q["sequence"] in ("", "hammersley")))
    for m, s, seq in keys:
        at = "finer-texels" if m == "exact" else "level-texels"
        qs = _sel(rows, method=m, samples=s, sequence=seq, at=at)
        rs = sorted({float(q["roughness"]) for q in qs})
        y = [np.mean([float(q["rel_l1_frac"]) for q in qs if float(q["roughness"]) == r]) for r in rs]
        lab = "exact chain, between texels" if m == "exact" else f"{m.upper()}-{s}"
        ax.plot(rs, np.maximum(y, 1e-6), marker="o", ms=3, ls="--" if m == "exact" else "-", label=lab)
    ax.set_yscale("log")
    ax.set_xlabel("roughness of the level")
    ax.set_ylabel("rel. L1 vs exact level (mean over envs)")
    ax.set_title("error per level (Hammersley)", fontsize=10)
    ax.legend(fontsize=7)
    ax = axes[1]
    width = 0.8 / len(NORMALISATIONS)
    for k, c in enumerate(NORMALISATIONS):
        y = [chain_error(rows, c, env=e, method="fis", samples="32", sequence="hammersley", at="level-texels")
             for e in envs]
        ax.bar(np.arange(len(envs)) + (k - (len(NORMALISATIONS) - 1) / 2) * width, np.maximum(y, 1e-6), width,
               label=NORMALISATIONS[c])
    ax.axhline(PAPER_FIS32_L1, color="k", lw=1, label=f"paper FIS-32 {PAPER_FIS32_L1}")
    ax.axhline(PAPER_OWN_L1, color="grey", lw=1, ls=":", label=f"paper's filter {PAPER_OWN_L1}")
    ax.set_yscale("log")
    ax.set_xticks(range(len(envs)), envs, fontsize=8)
    ax.set_ylabel("FIS-32 chain error")
    ax.set_title("FIS-32 (Hammersley) per normalisation", fontsize=10)
    ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    path = out_dir / "manson_sloan.png"
    save_figure(fig, path, dpi=100)
    return [path]
