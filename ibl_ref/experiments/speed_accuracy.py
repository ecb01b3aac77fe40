"""Speed vs accuracy of the Phong-lobe convolution methods (Knuth et al. 2014, Sec. 3.2, Eq. 4).

For the sky + 1e5 sun placed 0.0015 rad from a cube corner (:mod:`ibl_ref.synthetic.synthetic_envs`
``make_env("sky_sun", n, sun_direction=SUN_NEAR_CORNER, sun_radiance=1e5)``), every method of
:func:`ibl_ref.groundtruth.convolve.convolve` (``exact``, ``sh``, ``sparse``, ``auto`` at rtol = 1e-3) is timed
on the whole exponent set at once (the methods share work between exponents) and its per-texel relative
error ``|approx − exact| / exact`` (max over RGB) is measured per exponent: max and mean over texels,
together with the method's own reported bound.

Reference.  Face sizes ≤ 64: the full exact convolution
(:func:`ibl_ref.groundtruth.phong_convolution.convolve_exact_many`).  Face size 128: the exact sum
``Σ_j L_j max(r·ω_j,0)^s Ω_j / Σ_j max(r·ω_j,0)^s Ω_j`` over **all** source texels, evaluated only at a
seeded random subset of 2000 output texels (an exact reference for those texels; errors at 128 are
statistics over that subset), and the time of the full exact method at 128 is extrapolated from the
subset time (``time_extrapolated = True``; the subset routine is a plain NumPy gather, slower per
texel than ``convolve_exact_many`` — read that time as an upper estimate; measured: the exact gather
for s = 1 alone takes ≈ 47 s CPU at 128²).  The subset routine is checked against the full exact
method at the smallest size (``subset_check_max_abs_rel``).

Method ``sh`` is run only for s ≤ 256 (beyond that the band limit it would need exceeds
``SH_L_MAX``; ``auto`` never chooses it there); in the full run ``sparse`` only for s ≥ 64 (for broader
lobes the sparse gather falls back to the dense exact gather internally, already timed as ``exact``).  Timings are wall clock on the machine that runs the
experiment; the CSV has wall-clock and process CPU time (the plot uses CPU time, which is robust on a
shared machine when BLAS runs single-threaded).

Outputs: ``speed_accuracy.csv`` (one row per size × method × exponent), ``speed_accuracy.json``;
plots ``speed_accuracy_n{N}.png`` (one Pareto plot per face size).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..environment import envmap
from ..progress import track
from ..atomic import read_csv, write_csv, write_json
from . import Param, resolve_params, VALUE_CHECKS
from ..figures import plain_log_ticks
from ..figures import pyplot
from ..figures import save_figure
from ..groundtruth.convolve import convolve
from ..groundtruth.phong_convolution import convolve_exact_many
from ..synthetic.synthetic_envs import SUN_NEAR_CORNER
from ..synthetic.synthetic_envs import make_env

NAME = "speed-accuracy"
DESCRIPTION = "time vs max/mean relative error of exact / SH-hybrid / sparse / auto Phong convolution"
PAPER = "Knuth et al. 2014, Eq. 4 (exact Phong convolution) and Kan et al. 2015 (fast prefiltering): speed vs accuracy"
IN_QUICK_REPRODUCE = True
RUNTIME = {"quick": "9 s (load 0.3)", "full": "50 s (load 0.2; 71 s CPU)"}
OUTPUTS = ("speed_accuracy.csv", "speed_accuracy.json", "speed_accuracy_n<N>.png")

EXPONENTS = (1.0, 4.0, 16.0, 64.0, 256.0, 1024.0, 4096.0)
QUICK_EXPONENTS = (1.0, 16.0, 256.0, 4096.0)
RTOL = 1e-3
SUBSET = 2000
SEED = 20140
PARAMS = (Param("face_sizes", (32, 64, 128), (16, 32), "cube face sizes N"),
          Param("exponents", EXPONENTS, QUICK_EXPONENTS, "Phong exponents s", VALUE_CHECKS["s_values"]))


def environment(n: int) -> np.ndarray:
    """The sky + sun-near-corner environment (generator of :mod:`ibl_ref.synthetic.synthetic_envs`)."""

    return make_env("sky_sun", n, sun_direction=SUN_NEAR_CORNER, sun_radiance=1e5)


def exact_subset(cube, exponents, idx):
    """Exact lobe average at the output texels ``idx`` (flat indices into (6, n, n)), all sources."""
    n = cube.shape[1]
    src = envmap.texel_directions(n).reshape(-1, 3)
    om = np.ascontiguousarray(envmap.cube_solid_angles(n)).reshape(-1)
    rad = cube.reshape(-1, cube.shape[-1])
    r = src[idx]
    out = np.empty((len(exponents), len(idx), rad.shape[1]))
    for i0 in range(0, len(idx), 64):
        c = r[i0 : i0 + 64] @ src.T
        logc = np.full(c.shape, -np.inf)
        np.log(c, out=logc, where=c > 0)
        logc -= logc.max(axis=1, keepdims=True)  # per-row scaling cancels in the ratio
        for k, s in enumerate(exponents):
            w = np.exp(s * logc) * om
            out[k, i0 : i0 + 64] = (w @ rad) / w.sum(axis=1, keepdims=True)
    return out


def run(out_dir: Path, quick: bool = False, **params) -> dict:

    out_dir = Path(out_dir)
    p = resolve_params(__name__, quick, params)
    sizes, S = p["face_sizes"], p["exponents"]
    convolve(environment(4), [2.0, 64.0], method="auto")  # warm-up: imports and scipy set-up not timed
    rng = np.random.default_rng(SEED)
    rows = []
    summary = {"sizes": list(sizes), "exponents": list(S), "rtol": RTOL, "per_size": {}}
    for n in track(sizes, "speed-accuracy: face sizes", unit="size"):
        cube = environment(n)
        P = 6 * n * n
        full_ref = n <= 64
        if full_ref:
            t0, c0 = time.perf_counter(), time.process_time()
            ref = convolve_exact_many(cube, S).reshape(len(S), P, -1)
            t_exact, c_exact = time.perf_counter() - t0, time.process_time() - c0
            idx = np.arange(P)
            extrapolated = False
        else:
            idx = np.sort(rng.choice(P, size=min(SUBSET, P), replace=False))
            t0, c0 = time.perf_counter(), time.process_time()
            ref = exact_subset(cube, S, idx)
            t_exact = (time.perf_counter() - t0) * P / len(idx)
            c_exact = (time.process_time() - c0) * P / len(idx)
            extrapolated = True
        if n == sizes[0]:
            chk = exact_subset(cube, S, np.arange(0, P, 7))
            summary["subset_check_max_abs_rel"] = float(np.max(np.abs(chk - ref[:, ::7]) / ref[:, ::7]))
        methods = {"exact": None, "sh": [s for s in S if s <= 256], "auto": list(S),
                   "sparse": [s for s in S if s >= 64 or quick]}
        per_method = {}
        for meth, s_sub in methods.items():
            if meth == "exact":
                if full_ref:
                    maps = {s: ref[k] for k, s in enumerate(S)}
                    bounds = {s: np.full(P, 1e-12) for s in S}
                else:
                    maps = {s: ref[k] for k, s in enumerate(S)}
                    bounds = {s: np.full(len(idx), 1e-12) for s in S}
                used = {s: "exact" for s in S}
                t, tc = t_exact, c_exact
                kernel = "numpy"  # the float64 reference sum
            else:
                t0 = time.perf_counter()
                res = convolve(cube, s_sub, method=meth, rtol=RTOL)
                # CPU of this process and of convolve's forked workers (process_time alone misses them)
                t, tc = time.perf_counter() - t0, res.timings_s["total_cpu"]
                maps = {s: res.maps[s].reshape(P, -1)[idx] for s in s_sub}
                bounds = {s: res.error_bound[s].reshape(P)[idx] for s in s_sub}
                used = res.method_used
                kernel = res.info.get("kernel", "numpy")
            errs = []
            for s in (S if meth == "exact" else s_sub):
                k = S.index(s)
                rel = (np.abs(maps[s] - ref[k]) / ref[k]).max(axis=-1)
                b = bounds[s]
                fin = b[np.isfinite(b)]
                row = {
                    "face_size_texels": n,
                    "method": meth,
                    "s_phong": s,
                    "method_used": used[s],
                    "kernel": kernel,
                    "time_all_exponents_s": round(t, 4),
                    "cpu_time_all_exponents_s": round(tc, 4),
                    "time_extrapolated": bool(extrapolated and meth == "exact"),
                    "n_exponents_in_run": len(S if meth == "exact" else s_sub),
                    "rel_err_max": float(rel.max()),
                    "rel_err_mean": float(rel.mean()),
                    "rel_bound_max": float(b.max()) if np.all(np.isfinite(b)) else float("inf"),
                    "rel_bound_mean": float(fin.mean()) if fin.size else float("inf"),
                    "n_reference_texels": int(len(idx)),
                    # texels where the measured error exceeds the reported bound, beyond the reference's own
                    # float64 rounding (≲ 1e-12 relative: sums over 6N² terms)
                    "bound_violations": int(np.sum(rel > b + 1e-12)),
                }
                rows.append(row)
                errs.append(rel.max())
            per_method[meth] = {"time_s": t, "cpu_time_s": tc, "rel_err_max": float(max(errs)),
                                "bound_violations": sum(r["bound_violations"] for r in rows
                                                        if r["face_size_texels"] == n and r["method"] == meth)}
        summary["per_size"][str(n)] = per_method
    cols = list(rows[0].keys())
    write_csv(
        out_dir / "speed_accuracy.csv",
        [{k: (str(v) if isinstance(v, float) and not np.isfinite(v) else v) for k, v in r.items()} for r in rows],
        cols,
        comment=(
            "speed vs accuracy of Phong-lobe convolution; env sky_sun; sun 1e5 near a cube corner; rtol 1e-3\n"
            "rel_err = |approx - exact|/exact per texel (max over RGB); time = all exponents of the run at once\n"
            "kernel = the convolution kernel that ran (numpy or compiled: --kernel / IBL_REF_KERNEL, default auto)\n"
            "bound_violations = texels with rel_err > reported bound + 1e-12 (reference rounding)\n"
            "face size 128: reference = exact at a random subset of output texels; exact time extrapolated"
        ),
    )
    write_json(out_dir / "speed_accuracy.json", summary)
    return summary


def plot(out_dir: Path) -> list:

    plt = pyplot()

    out_dir = Path(out_dir)
    rows = read_csv(out_dir / "speed_accuracy.csv")
    sizes = sorted({int(r["face_size_texels"]) for r in rows})
    colors = {"exact": "k", "sh": "tab:blue", "sparse": "tab:orange", "auto": "tab:green", "moment": "tab:purple"}
    paths = []
    for n in sizes:
        rs = [r for r in rows if int(r["face_size_texels"]) == n]
        fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 4))
        for meth in ("exact", "sh", "sparse", "auto"):
            mr = [r for r in rs if r["method"] == meth]
            if not mr:
                continue
            t = float(mr[0]["cpu_time_all_exponents_s"])
            emax = max(max(float(r["rel_err_max"]) for r in mr), 1e-17)
            emean = max(np.mean([float(r["rel_err_mean"]) for r in mr]), 1e-17)
            # a time extrapolated from a subset of texels (the exact gather at large faces) is drawn hollow
            extra = str(mr[0].get("time_extrapolated", "")).lower() == "true"
            tag = ", time extrapolated" if extra else ""
            ax0.scatter([t], [emax], color=colors[meth], marker="o", facecolors="none" if extra else colors[meth],
                        label=f"{meth} (max{tag})")
            ax0.scatter([t], [emean], color=colors[meth], marker="x", label=f"{meth} (mean{tag})")
            s = [float(r["s_phong"]) for r in mr]
            ax1.plot(s, [max(float(r["rel_err_max"]), 1e-17) for r in mr], "o-", color=colors[meth], label=meth)
        ax0.axhline(RTOL, color="gray", ls=":", lw=1)
        ax1.axhline(RTOL, color="gray", ls=":", lw=1, label="rtol")
        ax0.set(xscale="log", yscale="log", xlabel="CPU time for all exponents (s)", ylabel="relative error",
                title=f"{n}² faces: time vs error (max over s)")
        plain_log_ticks(ax0.xaxis)  # 0.2 and 0.5, not 2×10⁻¹ running into 3×10⁻¹
        ax1.set(xscale="log", yscale="log", xlabel="Phong exponent s", ylabel="max relative error",
                title="per exponent")
        ax0.legend(fontsize=7)
        ax1.legend(fontsize=7)
        subsets = "; ".join(
            f"{m}: s = {', '.join(sorted({r['s_phong'].rstrip('0').rstrip('.') for r in rs if r['method'] == m}, key=float))}"
            for m in ("sh", "sparse")
        )
        fig.text(0.01, 0.005, f"exact = reference (plotted at the 1e-17 floor); runs cover {subsets}", fontsize=7)
        fig.tight_layout(rect=(0, 0.03, 1, 1))
        p = out_dir / f"speed_accuracy_n{n}.png"
        save_figure(fig, p, dpi=110)
        paths.append(p)
    return paths
