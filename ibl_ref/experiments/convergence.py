"""Convergence of the exact Phong-lobe convolution (Knuth et al. 2014, Eq. 4) — the lab's ground truth.

Two studies, both with closed-form or exact targets:

1. **Source resolution.**  The linear-gradient environment ``L(ω) = a + b·ω`` (evaluated here at texel
   centres from :func:`ibl_ref.environment.envmap.texel_directions`, independent of ``synthetic_envs``) has the
   closed-form lobe average ``a + b·r (s+1)/(s+2)``.  Max/RMS error of :func:`convolve_exact` at face
   sizes 8…64 for s ∈ {1, 16, 256, 4096}, observed order log2(e_N/e_2N).  Also the unnormalised total
   weight Σ cos^s Ω versus 2π/(s+1).
2. **Supersampling.**  Fixed face size, k×k sub-texels (k = 1, 2, 4, 8): the unnormalised total weight of
   L ≡ 1 versus 2π/(s+1) (exact target: a constant is exactly piecewise constant), and the gradient
   environment's lobe average versus the k = 16 result (self-convergence; the piecewise-constant
   environment has no closed form).

Outputs: ``convergence_resolution.csv``, ``convergence_supersample.csv``, ``convergence_summary.json``;
plots ``convergence_resolution.png`` / ``convergence_supersample.png``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..progress import track
from ..atomic import read_csv, write_csv, write_json
from ..environment import envmap
from ..groundtruth.phong_convolution import convolve_exact_many, phong_lobe_integral
from . import Param, resolve_params
from ..figures import pyplot
from ..figures import save_figure

NAME = "convergence"
DESCRIPTION = "exact Phong convolution vs source resolution and supersampling (closed-form targets)"
PAPER = "Knuth et al. 2014, Eq. 4 (the exact Phong lobe average the lab uses as ground truth): convergence"
IN_QUICK_REPRODUCE = True
RUNTIME = {"quick": "2.1 s (load 0.3)", "full": "5 min 13 s (load 7-10)"}
OUTPUTS = ("convergence_resolution.csv", "convergence_supersample.csv", "convergence_summary.json",
           "convergence_resolution.png", "convergence_supersample.png")

EXPONENTS = (1.0, 16.0, 256.0, 4096.0)
#: face sizes / supersampling factors of the quick and full runs (tests shrink them)
QUICK_SIZES, FULL_SIZES = (8, 16, 32), (8, 16, 32, 64)
QUICK_SS, FULL_SS = (8, (1, 2, 4, 8), 16), (16, (1, 2, 4, 8), 16)  # (face size, factors, reference factor)
PARAMS = (
    Param("face_sizes", FULL_SIZES, QUICK_SIZES, "face sizes N of the resolution study"),
    Param("ss_face_size", FULL_SS[0], QUICK_SS[0], "face size of the supersampling study"),
    Param("ss_factors", FULL_SS[1], None, "supersampling factors k (k x k sub-texels)"),
    Param("ss_reference", FULL_SS[2], None, "supersampling factor of the self-convergence reference"),
)
GRAD_A = 1.0
GRAD_B = np.array([0.3, -0.2, 0.4])


def _gradient(n: int):
    d = envmap.texel_directions(n)
    return (GRAD_A + d @ GRAD_B)[..., None], d


def run(out_dir: Path, quick: bool = False, **params) -> dict:
    out_dir = Path(out_dir)
    p = resolve_params(__name__, quick, params)
    sizes = p["face_sizes"]
    rows = []
    for n in track(sizes, "convergence: face sizes", unit="size"):
        cube, d = _gradient(n)
        t0 = time.perf_counter()
        avg, wsum = convolve_exact_many(cube, EXPONENTS, return_weights=True)  # wsum = Σ cos^s Ω
        avg = avg[..., 0]
        t_avg = time.perf_counter() - t0
        for k, s in enumerate(EXPONENTS):
            ref = GRAD_A + (d @ GRAD_B) * (s + 1) / (s + 2)
            e = np.abs(avg[k] - ref)
            rows.append(
                {
                    "s_phong": s,
                    "face_size_texels": n,
                    "max_abs_err": float(e.max()),
                    "rms_abs_err": float(np.sqrt(np.mean(e**2))),
                    "weight_rel_err_max": float(np.abs(wsum[k] / phong_lobe_integral(s) - 1).max()),
                    "time_all_exponents_s": round(t_avg, 4),
                }
            )
    orders = {}
    for s in EXPONENTS:
        r = [x for x in rows if x["s_phong"] == s]
        o = [float(np.log2(a["max_abs_err"] / b["max_abs_err"])) for a, b in zip(r, r[1:])]
        for x, oo in zip(r[1:], o):
            x["observed_order"] = round(oo, 3)
        r[0]["observed_order"] = ""
        orders[str(s)] = o
    write_csv(
        out_dir / "convergence_resolution.csv",
        rows,
        ["s_phong", "face_size_texels", "max_abs_err", "rms_abs_err", "observed_order", "weight_rel_err_max", "time_all_exponents_s"],
        comment=(
            "exact Phong lobe average (convolve_exact) of L = a + b.w vs closed form a + b.r (s+1)/(s+2); "
            f"a={GRAD_A}, b={GRAD_B.tolist()}; radiance units; observed_order = log2(err_N / err_2N); "
            "weight_rel_err_max = max |sum cos^s Omega / (2pi/(s+1)) - 1|; timings under load (shared 2 cores)"
        ),
    )

    n_ss, ks, k_ref = p["ss_face_size"], p["ss_factors"], p["ss_reference"]
    cube, _ = _gradient(n_ss)
    ref_avg = convolve_exact_many(cube, EXPONENTS, supersample=k_ref)[..., 0]
    ss_rows = []
    for k in track(ks, "convergence: supersampling factors", unit="factor"):
        t0 = time.perf_counter()
        avg, wsum = convolve_exact_many(cube, EXPONENTS, supersample=k, return_weights=True)
        avg = avg[..., 0]
        t_k = time.perf_counter() - t0
        for j, s in enumerate(EXPONENTS):
            ss_rows.append(
                {
                    "s_phong": s,
                    "face_size_texels": n_ss,
                    "supersample": k,
                    "weight_rel_err_max": float(np.abs(wsum[j] / phong_lobe_integral(s) - 1).max()),
                    "self_conv_max_abs_err": float(np.abs(avg[j] - ref_avg[j]).max()) if k != k_ref else 0.0,
                    "reference_supersample": k_ref,
                    "time_all_exponents_s": round(t_k, 4),
                }
            )
    write_csv(
        out_dir / "convergence_supersample.csv",
        ss_rows,
        comment=(
            "supersampled exact convolution (k x k sub-texels, piecewise-constant radiance); "
            "weight_rel_err_max: L=1 unnormalised vs 2pi/(s+1) (exact target); "
            "self_conv_max_abs_err: gradient env lobe average vs supersample=reference_supersample"
        ),
    )
    summary = {
        "face_sizes": list(sizes),
        "exponents": list(EXPONENTS),
        "observed_orders_max_err": orders,
        "supersample_face_size": n_ss,
        "quick": quick,
    }
    write_json(out_dir / "convergence_summary.json", summary)
    return summary


def plot(out_dir: Path) -> list[Path]:

    plt = pyplot()

    out_dir = Path(out_dir)
    paths = []
    rows = read_csv(out_dir / "convergence_resolution.csv")
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.6), layout="constrained")
    sizes = sorted({int(r["face_size_texels"]) for r in rows})
    unresolved = []
    for s in sorted({float(r["s_phong"]) for r in rows}):
        r = [x for x in rows if float(x["s_phong"]) == s]
        n = [int(x["face_size_texels"]) for x in r]
        axes[0].loglog(n, [float(x["max_abs_err"]) for x in r], "o-", label=f"s = {s:g}")
        axes[1].loglog(n, [float(x["weight_rel_err_max"]) for x in r], "o-", label=f"s = {s:g}")
        # half width of cos^s (cos^s θ = 1/2) vs the texel's angular size 90°/N: below one texel the lobe is not
        # resolved and the error is pre-asymptotic (it may grow with N until the texels resolve the lobe)
        hw = np.degrees(np.arccos(0.5 ** (1.0 / s)))
        if hw < 90.0 / max(n):
            unresolved.append(f"s = {s:g}: lobe half width {hw:.2f}° < one texel (90°/N = {90.0 / max(n):.1f}° at "
                              f"N = {max(n)}): not resolved, the error is pre-asymptotic")
    nn = np.array([sizes[0], sizes[-1]], dtype=float)
    axes[0].loglog(nn, 1e-2 * (nn / nn[0]) ** -2, "k--", lw=0.8, label="∝ N$^{-2}$")
    axes[0].set(xlabel="face size N (texels)", ylabel="max |exact − closed form| (radiance)",
                title="gradient environment: lobe average")
    axes[1].set(xlabel="face size N (texels)", ylabel="max |Σcos$^s$Ω / (2π/(s+1)) − 1|", title="lobe weight (L ≡ 1)")
    for ax in axes:
        ax.set_xscale("log", base=2)
        ax.set_xticks(sizes, [str(v) for v in sizes])
        ax.minorticks_off()
        ax.grid(True, which="major", alpha=0.3)
    axes[0].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    if unresolved:
        fig.text(0.01, 0.0, "\n".join(unresolved), fontsize=8, ha="left", va="bottom")
        fig.get_layout_engine().set(rect=(0, 0.06 * len(unresolved), 1, 1 - 0.06 * len(unresolved)))
    p = out_dir / "convergence_resolution.png"
    save_figure(fig, p, dpi=120)
    paths.append(p)

    rows = read_csv(out_dir / "convergence_supersample.csv")
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), layout="constrained")
    for s in sorted({float(r["s_phong"]) for r in rows}):
        r = [x for x in rows if float(x["s_phong"]) == s]
        k = [int(x["supersample"]) for x in r]
        axes[0].loglog(k, [max(float(x["weight_rel_err_max"]), 1e-17) for x in r], "o-", label=f"s={s:g}")
        axes[1].loglog(k, [max(float(x["self_conv_max_abs_err"]), 1e-17) for x in r], "o-", label=f"s={s:g}")
    ks = sorted({int(r["supersample"]) for r in rows})
    axes[0].set(xlabel="supersample k (k × k sub-texels)", ylabel="max |Σcos$^s$Ω / (2π/(s+1)) − 1|",
                title="lobe weight (L ≡ 1)")
    axes[1].set(xlabel="supersample k (k × k sub-texels)", ylabel="max |avg_k − avg_ref| (radiance)",
                title=f"gradient environment: self-convergence (ref. k = {rows[0]['reference_supersample']})")
    for ax in axes:
        ax.set_xscale("log", base=2)
        ax.set_xticks(ks, [str(v) for v in ks])
        ax.minorticks_off()
        ax.grid(True, which="major", alpha=0.3)
    axes[1].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    p = out_dir / "convergence_supersample.png"
    save_figure(fig, p, dpi=120)
    paths.append(p)
    return paths
