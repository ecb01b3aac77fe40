"""The engines' roughness → MIP-level mappings measured: each at equal memory, each in its own chain, and every
mismatch between the mapping that filled a chain and the one that reads it.

A split-sum engine stores the n = v = r GGX prefilter P(·, r) (Karis 2013, Eq. 8) at one roughness per MIP level
and reads a roughness r at the fractional level ℓ(r) of its mapping with trilinear filtering (bilinear in each
level, linear between levels).  The mappings (:data:`ibl_ref.prefilter.mip_mappings.ROUGHNESS_MAPPINGS`):
``linear`` (Khronos glTF-IBL-Sampler, Bevy), ``filament``, ``unity``, ``unreal``, ``threejs`` (sources in that
module).  Per environment and base face size b, for each mapping A the chain is built with the exact prefilter
(:func:`ibl_ref.prefilter.karis2013.build_chain`, ``"exact"``, every texel within ``rtol``, level ℓ at A's
roughness of ℓ, a level of roughness 0 the source itself), in two layouts:

* ``equal-memory`` — N = log2 b + 1 levels, faces b², (b/2)², …, 1² (the full MIP chain): the same N and the same
  texels for every mapping, so the rows compare the mappings alone;
* ``engine`` — the engine's own chain at base b (:meth:`~ibl_ref.prefilter.mip_mappings.MipMapping.chain_sizes`):
  ``linear`` ⌊log2 b⌋ levels to 2², ``filament`` to 16², ``unity`` 7 levels, ``unreal`` to 1² (the same as
  equal-memory), ``threejs`` to 16² and 6 more levels at 16².

Each chain A is then read (:class:`ibl_ref.prefilter.karis2013.PrefilteredChain` look-up) under every mapping B
at B's level for r: A = B is the engine as shipped, A ≠ B the mismatch users report (a chain prefiltered by one
tool read by another engine's shader).

* ``grid`` rows: r ∈ ``roughness`` at the texel centres of a ``dir_size``² cube, against the exact prefilter of r
  itself there (:func:`ibl_ref.groundtruth.ggx_convolution.convolve_ggx_levels` at ``ref_rtol``);
* ``on-level`` rows (equal-memory chains, levels of at most ``dir_size``² faces that some r ∈ (0, 1] reads
  exactly): r = A's roughness of level ℓ at the texel centres of level ℓ itself, where A's look-up returns the
  stored texels: A = B is then the chain's own error, within its bound (``rtol`` against the exact, ``ref_rtol``
  the reference), and B ≠ A what reading another level costs.

Metrics over directions and channels: ``rel_l1_frac`` Σ|a − b| / Σ b, ``rel_err_p99_frac`` and
``rel_err_max_frac`` (99th percentile and maximum of |a − b| / b per direction and channel), ``bias_frac``
Σ(a − b) / Σ b.  Environments: the synthetic sky with a small 1e5 sun (``sky_sun``) and the real probes ``city``,
``courtyard``, ``forest``, ``studio`` (read and resampled as the method zoo does,
:func:`ibl_ref.experiments.method_zoo.environment`; a missing probe is skipped with the reason).

Files: ``mip_mappings.csv`` (one row per environment × base × layout × A × B × r), ``mip_mappings_meta.json``
(settings, each chain's faces, roughness, bound and time, skipped items, timings, load), ``mip_mappings.md`` (the
equal-memory, engine-chain and mismatch tables).  Plots (read only the CSV): ``mip_mappings.png`` (error vs r per
mapping, A = B), ``mip_mappings_mismatch.png`` (mean error per stored × look-up mapping).
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path

import numpy as np

from ..atomic import atomic_write, read_csv, write_csv, write_json
from ..environment import envmap
from ..errors import IBLError
from ..figures import pyplot, save_figure
from ..groundtruth.ggx_convolution import convolve_ggx_levels
from ..prefilter.karis2013 import build_chain
from ..prefilter.mip_mappings import ROUGHNESS_MAPPINGS
from ..progress import track
from . import params_from_settings, power_of_two, settings_with
from .method_zoo import ENVS, environment

NAME = "mip-mappings"
DESCRIPTION = "roughness -> MIP level: the engines' mappings at equal memory, in their own chains, and mismatched"
PAPER = ("Karis 2013, Eq. 8 (the n = v = r prefilter stored per MIP level) and the engines' roughness -> level "
         "look-ups (glTF-IBL-Sampler, Filament, Unity, Unreal Engine 4, three.js)")
IN_QUICK_REPRODUCE = False
RUNTIME = {"quick": "7 s (load 4)", "full": "10 min (load 4; --base-sizes 128,256: 39 min)"}
OUTPUTS = ("mip_mappings.csv", "mip_mappings_meta.json", "mip_mappings.md", "mip_mappings.png",
           "mip_mappings_mismatch.png")

#: the two chain layouts (module docstring)
LAYOUTS = ("equal-memory", "engine")
#: the CSV's columns
COLUMNS = ["env", "base_face_size_texels", "layout", "n_levels", "chain_texels", "stored_mapping", "lookup_mapping",
           "kind", "roughness", "level_stored", "level_read", "n_directions", "rel_l1_frac", "rel_err_p99_frac",
           "rel_err_max_frac", "bias_frac", "chain_rel_bound_max", "level_rel_bound_max", "ref_rel_bound_max"]


def _roughness_value(v):
    if not 0.0 < v <= 1.0:
        raise IBLError(f"a roughness must be in (0, 1], got {v!r}")
    return v


def settings(quick: bool) -> dict:
    if quick:
        return dict(envs=["sky_sun"], base_sizes=[16], roughness=[0.05, 0.1, 0.2, 0.4, 0.7, 1.0], dir_size=8,
                    rtol=1e-3, ref_rtol=1e-4, probe_dir="")
    grid = [0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0]
    return dict(envs=list(ENVS), base_sizes=[128], roughness=grid, dir_size=32, rtol=1e-3, ref_rtol=1e-4,
                probe_dir="")


PARAMS = params_from_settings(
    settings,
    {"envs": "environments: sky_sun and the probes city, courtyard, forest, studio",
     "base_sizes": "base face sizes b (powers of two); the equal-memory chain has log2 b + 1 levels",
     "roughness": "perceptual roughnesses of the grid rows",
     "dir_size": "the grid rows' directions: texel centres of a dir_size² cube",
     "rtol": "largest relative error of every chain texel (exact prefilter)",
     "ref_rtol": "largest relative error of the references",
     "probe_dir": "folder of the probe EXRs (default: the method zoo's, ibl_ref.experiments.method_zoo.probe_dir)"},
    {"base_sizes": power_of_two, "dir_size": power_of_two, "roughness": _roughness_value})


# ------------------------------------------------------------------------------------------------------------------
# chains and metrics
# ------------------------------------------------------------------------------------------------------------------
def layout_sizes(layout: str, mapping: str, base: int) -> tuple:
    """Face sizes of the chain of ``mapping`` in ``layout`` at a base face of ``base`` texels (module docstring)."""
    if layout == "equal-memory":
        return tuple(base >> k for k in range(base.bit_length()))
    if layout == "engine":
        return ROUGHNESS_MAPPINGS[mapping].chain_sizes(base)
    raise IBLError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")


def build_mapping_chain(cube, mapping: str, sizes: tuple, rtol: float):
    """The exact chain of ``mapping`` with faces ``sizes`` (:func:`~ibl_ref.prefilter.karis2013.build_chain`)."""
    chain = build_chain(cube, n_levels=len(sizes), min_face_size=min(sizes), mapping=mapping, rtol=rtol)
    if chain.face_sizes != tuple(sizes):
        raise IBLError(f"{mapping}: chain faces {chain.face_sizes} differ from the layout's {sizes}")
    return chain


def errors(approx, exact) -> dict:
    """rel. L1, 99th percentile and maximum of the relative error per direction and channel, signed bias."""
    a, b = np.asarray(approx, dtype=np.float64), np.asarray(exact, dtype=np.float64)
    diff = a - b
    rel = np.divide(np.abs(diff), b, out=np.where(diff == 0, 0.0, np.inf), where=b > 0)
    total = float(b.sum())
    return {"rel_l1_frac": float(np.abs(diff).sum() / total), "rel_err_p99_frac": float(np.percentile(rel, 99)),
            "rel_err_max_frac": float(rel.max()), "bias_frac": float(diff.sum() / total)}


def _on_level_targets(chain, mapping: str, dir_size: int) -> list:
    """(level, roughness, face size) of the levels checked on-level: roughness in (0, 1], read exactly at its
    level by ``mapping``, faces of at most ``dir_size``²."""
    m, n = ROUGHNESS_MAPPINGS[mapping], chain.n_levels
    out = []
    for lv, (r, size) in enumerate(zip(chain.roughness, chain.face_sizes)):
        if 0.0 < r <= 1.0 and size <= dir_size and abs(float(m.level(r, n)) - lv) <= 1e-9:
            out.append((lv, float(r), int(size)))
    return out


def measure_environment(cube, *, base: int, r_values, dir_size: int, rtol: float, ref_rtol: float,
                        mappings=None, env: str = "") -> tuple[list, dict]:
    """Every row of one environment at one base size: ``(rows, meta)`` (module docstring).

    ``cube`` is the (6, base, base, C) map; ``mappings`` the names to study (default all of
    :data:`~ibl_ref.prefilter.mip_mappings.ROUGHNESS_MAPPINGS`).
    """
    names = list(ROUGHNESS_MAPPINGS if mappings is None else mappings)
    dirs = envmap.texel_directions(dir_size).reshape(-1, 3)
    t0 = time.perf_counter()
    chains, built, meta = {}, {}, {"chains": {}}
    for layout in LAYOUTS:
        for a in names:
            sizes = layout_sizes(layout, a, base)
            if (a, sizes) not in built:  # unreal's engine chain is its equal-memory chain
                t = time.perf_counter()
                built[(a, sizes)] = build_mapping_chain(cube, a, sizes, rtol)
                meta["chains"][f"{layout}/{a}"] = {"seconds": time.perf_counter() - t}
            ch = chains[(layout, a)] = built[(a, sizes)]
            meta["chains"].setdefault(f"{layout}/{a}", {"seconds": 0.0}).update(
                face_sizes=list(ch.face_sizes), roughness=list(ch.roughness), bound_max=ch.info["bound_max"])
    meta["chains_s"] = time.perf_counter() - t0
    t = time.perf_counter()
    grid = convolve_ggx_levels(cube, [(float(r), dir_size) for r in r_values], rtol=ref_rtol)
    ref = {float(r): (m.reshape(len(dirs), -1), float(bnd.max())) for r, (m, bnd) in zip(r_values, grid)}
    targets = {a: _on_level_targets(chains[("equal-memory", a)], a, dir_size) for a in names}
    pairs = sorted({(r, s) for a in names for _, r, s in targets[a]})
    level_ref = {}
    if pairs:
        for (r, s), (m, bnd) in zip(pairs, convolve_ggx_levels(cube, pairs, rtol=ref_rtol)):
            level_ref[(r, s)] = (m.reshape(6 * s * s, -1), float(bnd.max()))
    meta["references_s"] = time.perf_counter() - t
    t = time.perf_counter()
    rows = []
    for (layout, a), chain in chains.items():
        n = chain.n_levels
        common = {"env": env, "base_face_size_texels": base, "layout": layout, "n_levels": n,
                  "chain_texels": 6 * sum(s * s for s in chain.face_sizes), "stored_mapping": a,
                  "chain_rel_bound_max": max(chain.info["bound_max"])}
        checked = targets[a] if layout == "equal-memory" else []
        first = 1 if chain.roughness[0] == 0.0 else 0  # info["bound_max"]: the filtered levels
        vals = chain.level_values(dirs)  # the bilinear look-ups of every level, shared by every (B, r)
        on_level = {s: (d, chain.level_values(d)) for s in {s for _, _, s in checked}
                    for d in [envmap.texel_directions(s).reshape(-1, 3)]}
        for b in names:
            view = dataclasses.replace(chain, mapping=b)  # A's levels read under B's mapping
            mb = ROUGHNESS_MAPPINGS[b]
            for r, (exact, rb) in ref.items():
                rows.append({**common, "lookup_mapping": b, "kind": "grid", "roughness": r, "level_stored": "",
                             "level_read": float(mb.level(r, n)), "n_directions": len(dirs),
                             "level_rel_bound_max": "",
                             **errors(view.lookup(dirs, r, level_values=vals), exact), "ref_rel_bound_max": rb})
            for lv, r, s in checked:
                exact, rb = level_ref[(r, s)]
                d, v = on_level[s]
                rows.append({**common, "lookup_mapping": b, "kind": "on-level", "roughness": r, "level_stored": lv,
                             "level_read": float(mb.level(r, n)), "n_directions": len(d),
                             "level_rel_bound_max": chain.info["bound_max"][lv - first],
                             **errors(view.lookup(d, r, level_values=v), exact), "ref_rel_bound_max": rb})
    meta["lookups_s"] = time.perf_counter() - t
    return rows, meta


# ------------------------------------------------------------------------------------------------------------------
# tables
# ------------------------------------------------------------------------------------------------------------------
def _grid(rows, **match):
    return [q for q in rows if q["kind"] == "grid" and all(str(q[k]) == str(v) for k, v in match.items())]


def _mean(qs, col="rel_l1_frac") -> float:
    return float(np.mean([float(q[col]) for q in qs])) if qs else float("nan")


def summarize(rows) -> dict:
    """Per base size: each mapping's mean rel. L1 over r and environments (A = B) in both layouts, the mean of
    every stored × look-up pair at equal memory, and the worst mismatch pair."""
    out = {}
    for base in dict.fromkeys(str(q["base_face_size_texels"]) for q in rows):
        names = list(dict.fromkeys(q["stored_mapping"] for q in rows))
        eq = {a: _grid(rows, base_face_size_texels=base, layout="equal-memory", stored_mapping=a, lookup_mapping=a)
              for a in names}
        eng = {a: _grid(rows, base_face_size_texels=base, layout="engine", stored_mapping=a, lookup_mapping=a)
               for a in names}
        pairs = {f"{a}->{b}": _mean(_grid(rows, base_face_size_texels=base, layout="equal-memory",
                                          stored_mapping=a, lookup_mapping=b)) for a in names for b in names}
        worst = max((k for k in pairs if k.split("->")[0] != k.split("->")[1]), key=pairs.get, default=None)
        out[base] = {"equal_memory_mean_rel_l1": {a: _mean(q) for a, q in eq.items()},
                     "equal_memory_max_rel_l1": {a: max(float(x["rel_l1_frac"]) for x in q) for a, q in eq.items()},
                     "engine_mean_rel_l1": {a: _mean(q) for a, q in eng.items()},
                     "engine_n_levels": {a: int(q[0]["n_levels"]) for a, q in eng.items() if q},
                     "pair_mean_rel_l1": pairs,
                     "worst_mismatch": {"pair": worst, "mean_rel_l1": pairs[worst] if worst else None}}
    return out


def _pct(v: float) -> str:
    return f"{100 * v:.2f} %"


def markdown(rows, summary: dict, settings_: dict) -> str:
    """The Markdown tables of :func:`summarize` (rel. L1 in %, means over r and environments)."""
    envs = ", ".join(dict.fromkeys(q["env"] for q in rows))
    grid = ", ".join(f"{r:g}" for r in settings_["roughness"])
    intro = (f"Grid rows: r ∈ {{{grid}}} at the texel centres of a {settings_['dir_size']}² cube, against the exact "
             f"prefilter (references within {settings_['ref_rtol']:g}; chains within {settings_['rtol']:g}). Mean "
             "rel. L1 over r and environments.")
    lines = [f"# Roughness → MIP level: measured ({envs})", "", intro, ""]
    for base, s in summary.items():
        names = list(s["equal_memory_mean_rel_l1"])
        layouts = (f"Each mapping read as its engine reads it (A = B). Equal memory: N = {int(base).bit_length()} "
                   f"levels, {base}² … 1²; engine: the engine's own chain at {base}².")
        lines += [f"## Base {base}²", "", layouts, "",
                  "| mapping | equal memory: mean rel. L1 | equal memory: worst r | engine N | engine: mean rel. L1 |",
                  "|---|---|---|---|---|"]
        for a in names:
            lines.append(f"| {a} | {_pct(s['equal_memory_mean_rel_l1'][a])} | {_pct(s['equal_memory_max_rel_l1'][a])}"
                         f" | {s['engine_n_levels'].get(a, '')} | {_pct(s['engine_mean_rel_l1'][a])} |")
        mismatch = ("Mismatch at equal memory: chain prefiltered under the row's mapping, read under the column's "
                    "(diagonal: as shipped).")
        lines += ["", mismatch, "", "| stored \\ read | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
        for a in names:
            lines.append(f"| {a} | " + " | ".join(_pct(s["pair_mean_rel_l1"][f"{a}->{b}"]) for b in names) + " |")
        w = s["worst_mismatch"]
        if w["pair"]:
            lines += ["", f"Worst mismatch: {w['pair'].replace('->', ' read as ')}, {_pct(w['mean_rel_l1'])}."]
        lines.append("")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------------------------
# compute and plot steps
# ------------------------------------------------------------------------------------------------------------------
def run(out_dir: Path, quick: bool = False, **params) -> dict:
    out_dir = Path(out_dir)
    st = settings_with(__name__, quick, params)
    load0, t_start = os.getloadavg(), time.perf_counter()
    rows, skipped, timings, chains = [], {}, {}, {}
    cases = [(e, b) for e in st["envs"] for b in st["base_sizes"]]
    for env_name, base in track(cases, "mip-mappings: environment × base size", unit="case"):
        if env_name in skipped:
            continue
        t = time.perf_counter()
        cube, why = environment(env_name, base, st["probe_dir"])
        if cube is None:
            skipped[env_name] = why
            continue
        got, meta = measure_environment(cube, base=base, r_values=st["roughness"], dir_size=st["dir_size"],
                                        rtol=st["rtol"], ref_rtol=st["ref_rtol"], env=env_name)
        rows += got
        chains[f"{env_name}/{base}"] = meta.pop("chains")
        timings[f"{env_name}/{base}"] = dict(meta, total_s=time.perf_counter() - t)
    if not rows:
        raise IBLError("mip-mappings: every environment was skipped: "
                       + "; ".join(f"{k}: {v}" for k, v in skipped.items()))
    write_csv(out_dir / "mip_mappings.csv", rows, COLUMNS,
              comment="chain of stored_mapping (layout equal-memory: log2 b + 1 levels b..1; engine: the engine's "
                      "own) read under lookup_mapping at level_read; kind grid: dir_size^2 texel centres; kind "
                      "on-level: the texel centres of level level_stored at its roughness (level_rel_bound_max: that "
                      "level's bound); errors against the exact n = v = r prefilter of the roughness (rel = |a-b|/b "
                      "per direction and channel)")
    summary = summarize(rows)
    with atomic_write(out_dir / "mip_mappings.md") as fh:
        fh.write(markdown(rows, summary, st))
    write_json(out_dir / "mip_mappings_meta.json", dict(
        settings=st, layouts={"equal-memory": "N = log2 b + 1 levels, faces b, b/2, ..., 1 (every mapping)",
                              "engine": "MipMapping.chain_sizes(b): the engine's own chain at base b"},
        mappings={k: {"engine": m.engine, "formula": m.formula, "source": m.source, "default_base": m.default_base,
                      "default_levels": m.default_levels, "min_face_size": m.min_face_size}
                  for k, m in ROUGHNESS_MAPPINGS.items()},
        chains=chains, skipped=skipped, timings=timings, summary=summary, total_time_s=time.perf_counter() - t_start,
        load_average_start=list(load0), load_average_end=list(os.getloadavg())))
    return {"summary": summary, "skipped": skipped, "rows": len(rows)}


def plot(out_dir: Path) -> list:
    plt = pyplot()
    out_dir = Path(out_dir)
    rows = [q for q in read_csv(out_dir / "mip_mappings.csv") if q["kind"] == "grid"]
    bases = list(dict.fromkeys(q["base_face_size_texels"] for q in rows))
    names = list(dict.fromkeys(q["stored_mapping"] for q in rows))
    fig, axes = plt.subplots(len(LAYOUTS), len(bases), figsize=(5.2 * len(bases) + 1.6, 7.4), squeeze=False,
                             layout="constrained")
    for j, base in enumerate(bases):
        for i, layout in enumerate(LAYOUTS):
            ax = axes[i, j]
            for a in names:
                qs = [q for q in rows if q["base_face_size_texels"] == base and q["layout"] == layout
                      and q["stored_mapping"] == a and q["lookup_mapping"] == a]
                rs = sorted({float(q["roughness"]) for q in qs})
                y = [np.mean([float(q["rel_l1_frac"]) for q in qs if float(q["roughness"]) == r]) for r in rs]
                ax.plot(rs, np.maximum(y, 1e-6), marker="o", ms=3, label=f"{a} (N {qs[0]['n_levels']})" if qs else a)
            ax.set_yscale("log")
            ax.set_xlabel("perceptual roughness r")
            ax.set_ylabel("rel. L1 vs exact prefilter")
            ax.set_title(f"{layout}, base {base}²", fontsize=10)
            ax.legend(fontsize=7)
    p1 = out_dir / "mip_mappings.png"
    save_figure(fig, p1, dpi=100)
    fig, axes = plt.subplots(1, len(bases), figsize=(4.6 * len(bases) + 1.0, 4.2), squeeze=False,
                             layout="constrained")
    for ax, base in zip(axes[0], bases):
        m = np.array([[np.mean([float(q["rel_l1_frac"]) for q in rows if q["base_face_size_texels"] == base
                                and q["layout"] == "equal-memory" and q["stored_mapping"] == a
                                and q["lookup_mapping"] == b]) for b in names] for a in names])
        im = ax.imshow(100 * m, cmap="viridis")
        for (i, k), v in np.ndenumerate(m):
            ax.text(k, i, f"{100 * v:.1f}", ha="center", va="center", fontsize=7,
                    color="white" if v < m.max() / 2 else "black")
        ax.set_xticks(range(len(names)), names, rotation=30, fontsize=8)
        ax.set_yticks(range(len(names)), names, fontsize=8)
        ax.set_xlabel("read under")
        ax.set_ylabel("prefiltered under")
        ax.set_title(f"equal memory, base {base}²: mean rel. L1 (%)", fontsize=9)
        fig.colorbar(im, ax=ax, shrink=0.8)
    p2 = out_dir / "mip_mappings_mismatch.png"
    save_figure(fig, p2, dpi=100)
    return [p1, p2]
