"""Meunier et al. (2009) cosine-lobe algebra: integral, tables, product fit statistics, cap fit.

Outputs (all in ``out_dir``):

* ``integral_check.csv`` — closed form 2π/(e+1) vs adaptive quadrature (Eq. 20–21);
* ``integral_table_error.csv`` — the paper's 128-per-decade table with linear interpolation (Sec. 4.2) vs the
  closed form, on a dense exponent sweep;
* ``cap_fit.csv`` — e_cap(α) (Eq. 32–34), the residual of the fit, the paper-style 1000-entry α table error and
  the α²·e table error;
* ``product_fit.csv`` — one row per (e1, e2, θ) sample of the paper's product table (Sec. 4.1 sampling:
  ``per_interval`` linear samples in [0,1], [1,10], …, [1e4,1e5]; θ linear in [0, π]); the error measured as in the
  paper (|∫c1c2 − ∫c_r|, unit scales, Fig. 3), plus relative and L2 errors;
* ``product_table_interp.csv`` — a coarse product table read back by trilinear interpolation at random
  off-node (e1, e2, θ) vs adaptive quadrature (what a renderer using the table sees);
* ``summary.json`` — statistics (mean/variance/median/max of the paper's error measure, over the full e1×e2×θ
  grid: pairs with e1 < e2 are computed once and weighted twice, since the product is symmetric).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..progress import track
from ..atomic import read_csv, write_csv, write_json
from . import Param, resolve_params
from ..figures import pyplot
from ..figures import save_figure
from ..lobes import meunier2009 as m

NAME = "cosine-lobes"
DESCRIPTION = "Meunier 2009 cosine lobes: integral table, product-of-lobes fit errors (vs paper 7.1e-4), cap fit"
PAPER = "Meunier et al. 2009, Eq. 20-21 (lobe integral), Sec. 4.1-4.2 (tables, product fit: mean error 7.1e-4), Eq. 32-34 (cap fit)"
IN_QUICK_REPRODUCE = True
PARAMS = (
    Param("cap_angles", 6000, 2000, "cap half-angles alpha sampled in (0, pi/2]"),
    Param("per_interval", 6, 2, "product-table exponent samples per decade interval (the paper's sampling)"),
    Param("n_theta", 12, 5, "product-table angles theta in [0, pi]"),
    Param("random_checks", 600, 60, "random off-node product-table look-ups checked against quadrature"),
)
RUNTIME = {"quick": "7.8 s (load 0.3)", "full": "39 min (load 9; 15 min CPU)"}
OUTPUTS = ("integral_check.csv", "integral_table_error.csv", "cap_fit.csv", "product_fit.csv",
           "product_table_interp.csv", "summary.json", "cosine_lobes_tables.png", "cosine_lobes_product.png")

PAPER_MEAN_ABS_ERR = 7.1379e-4  # Meunier 2009 Sec. 4.1 (adaptive Simpson, tol 1e-7); variance 1.2091e-8, median 0
PAPER_VAR_ABS_ERR = 1.2091e-8


def _weighted_stats(x, w):
    x = np.asarray(x, float)
    w = np.asarray(w, float)
    mean = float(np.sum(w * x) / np.sum(w))
    var = float(np.sum(w * (x - mean) ** 2) / np.sum(w))
    order = np.argsort(x)
    cw = np.cumsum(w[order]) / np.sum(w)
    median = float(x[order][np.searchsorted(cw, 0.5)])
    return dict(mean=mean, variance=var, median=median, max=float(x.max()))


def run(out_dir: Path, quick: bool = False, **params) -> dict:
    p = resolve_params(__name__, quick, params)

    out_dir = Path(out_dir)
    t_start = time.perf_counter()
    summary: dict = {"quick": quick}

    # 1. integral closed form vs adaptive quadrature
    rows = []
    for e in [0.0, 0.25, 1.0, 3.7, 10.0, 100.0, 1e3, 1e4, 1e5]:
        cf = float(m.lobe_integral(e))
        q = m.lobe_integral_quadrature(e)
        rows.append(dict(exponent=e, closed_form_sr=cf, quadrature_sr=q, rel_err=abs(cf / q - 1)))
    write_csv(out_dir / "integral_check.csv", rows, comment="Meunier 2009 Eq. 20-21: 2*pi/(e+1) vs scipy quad")
    summary["integral_closed_form_max_rel_err"] = max(r["rel_err"] for r in rows)

    # 2. integral table (paper Sec. 4.2: 128 per decade interval, linear interpolation)
    tab = m.IntegralTable(128)
    e = np.unique(np.concatenate([np.linspace(0, 1, 20001), np.geomspace(1e-3, 1e5, 200001)]))
    e = e[e <= 1e5]
    exact = m.lobe_integral(e)
    approx = tab(e)
    rel = np.abs(approx / exact - 1)
    keep = np.unique(np.concatenate([np.linspace(0, len(e) - 1, 4000).astype(int), [int(np.argmax(rel))]]))
    write_csv(out_dir / "integral_table_error.csv",
              [dict(exponent=float(e[i]), table_sr=float(approx[i]), exact_sr=float(exact[i]), rel_err=float(rel[i]))
               for i in keep], comment="IntegralTable(128 per interval, linear interpolation) vs 2*pi/(e+1)")
    summary["integral_table"] = dict(nodes=int(len(tab.nodes)), max_rel_err=float(rel.max()),
                                     exponent_at_max=float(e[np.argmax(rel)]), mean_rel_err=float(rel.mean()),
                                     max_abs_err_sr=float(np.max(np.abs(approx - exact))))

    # 3. cap fit (Eq. 32-34) and its tables
    alpha = np.linspace(np.pi / 2 / 1000, np.pi / 2, p["cap_angles"])[:-1]
    alpha_mid = alpha + 0.5 * (alpha[1] - alpha[0])  # off-node angles
    e_cap = m.cap_exponent(alpha_mid)
    f2 = 2 * np.pi * 2 * np.sin(alpha_mid / 2) ** 2  # ∫ f_cap² = cap solid angle
    resid = m.cap_fit_error(e_cap, alpha_mid)
    t_a = m.CapTable(1000, "alpha")(alpha_mid)
    t_b = m.CapTable(1000, "alpha2e")(alpha_mid)
    with np.errstate(divide="ignore", invalid="ignore"):
        ra = np.abs(t_a / e_cap - 1)
        rb = np.abs(t_b / e_cap - 1)
    write_csv(out_dir / "cap_fit.csv",
              [dict(alpha_deg=float(np.degrees(a)), e_cap=float(x), alpha2_e=float(a * a * x),
                    fit_rel_l2=float(np.sqrt(r / f)), table_alpha_rel_err=float(p), table_alpha2e_rel_err=float(q))
               for a, x, r, f, p, q in zip(alpha_mid, e_cap, resid, f2, ra, rb)],
              comment="Eq. 32-34 cap fit; fit_rel_l2 = ||f_cap - c_cap|| / ||f_cap||; tables: 1000 entries, "
                      "alpha linear in [pi/2000, pi/2], linear interpolation")
    ok = alpha_mid < 1.5
    summary["cap_fit"] = dict(
        gaussian_limit_alpha2_e=float(alpha_mid[0] ** 2 * e_cap[0]),
        table_alpha_max_rel_err=float(np.nanmax(ra[ok])), table_alpha_median_rel_err=float(np.nanmedian(ra[ok])),
        table_alpha2e_max_rel_err=float(np.nanmax(rb[ok])),
        fit_rel_l2_range=[float(np.sqrt(resid / f2).min()), float(np.sqrt(resid / f2).max())])

    # 4. product fit over the paper's sampling
    per_interval, n_theta = p["per_interval"], p["n_theta"]
    es = m.paper_exponent_samples(per_interval)
    thetas = np.linspace(0.0, np.pi, n_theta)
    rows = []
    t0 = time.perf_counter()
    for i, e1 in track(list(enumerate(es)), "cosine-lobes: product fits", unit="e1"):
        for e2 in es[i:]:
            wgt = 1.0 if e1 == e2 else 2.0
            for th in thetas:
                f = m.fit_product(e1, e2, th)
                rel_e = f.abs_err / f.integral_exact if f.integral_exact > 1e-300 else 0.0
                rows.append(dict(e1=float(e1), e2=float(e2), theta_rad=float(th), t_rad=f.t, e_r=f.e_r,
                                 log_p=f.log_p if np.isfinite(f.log_p) else -1e308, p=f.p,
                                 integral_exact_sr=f.integral_exact, integral_fit_sr=f.integral_fit,
                                 abs_err_sr=f.abs_err, rel_err=rel_e, l2_rel=f.l2_rel, solver=f.solver,
                                 weight=wgt))
    t_fit = time.perf_counter() - t0
    write_csv(out_dir / "product_fit.csv", rows,
              comment=f"Meunier 2009 Eq. 15-19 product fit; exponents: {per_interval} per interval in [0,1],[1,10],"
                      f"...,[1e4,1e5]; theta: {n_theta} linear in [0,pi]; unit scales; weight=2 for e1<e2 (symmetry)")
    abs_err = np.array([r["abs_err_sr"] for r in rows])
    rel_err = np.array([r["rel_err"] for r in rows])
    l2 = np.array([r["l2_rel"] for r in rows])
    w = np.array([r["weight"] for r in rows])
    nonzero = np.array([r["integral_exact_sr"] > 1e-12 for r in rows])
    imax = int(np.argmax(abs_err))
    summary["product_fit"] = dict(
        per_interval=per_interval, n_exponents=int(len(es)), n_theta=n_theta, n_fits=len(rows),
        n_grid_points=float(w.sum()), fit_time_s=round(t_fit, 2),
        abs_err_sr=_weighted_stats(abs_err, w),
        abs_err_at_max=dict(e1=rows[imax]["e1"], e2=rows[imax]["e2"], theta_rad=rows[imax]["theta_rad"],
                            integral_exact_sr=rows[imax]["integral_exact_sr"]),
        fraction_abs_err_below_1e12=float(np.sum(w * (abs_err < 1e-12)) / w.sum()),
        rel_err_nonzero=_weighted_stats(rel_err[nonzero], w[nonzero]),
        l2_rel_nonzero=_weighted_stats(l2[nonzero], w[nonzero]),
        solver_counts={k: int(sum(r["solver"] == k for r in rows)) for k in sorted({r["solver"] for r in rows})},
        paper_mean_abs_err=PAPER_MEAN_ABS_ERR, paper_variance_abs_err=PAPER_VAR_ABS_ERR,
        abs_err_sr_e_ge_1=_weighted_stats(abs_err[np.array([r["e1"] >= 1 and r["e2"] >= 1 for r in rows])],
                                          w[np.array([r["e1"] >= 1 and r["e2"] >= 1 for r in rows])]),
    )
    # 5. product table read back by trilinear interpolation at off-node triplets (paper: "table fetching and
    #    linear interpolations"); exponents drawn like the paper's sampling: a random interval [d, 10d] (or [0,1]),
    #    uniform inside it
    t0 = time.perf_counter()
    tab_per, tab_emax, tab_nt = (2, 100.0, 5) if quick else (4, 1000.0, 13)
    n_rand = p["random_checks"]
    tab_es = m.paper_exponent_samples(tab_per, tab_emax)
    tab_th = np.linspace(0.0, np.pi, tab_nt)
    ptab_log = m.ProductTable(tab_es, tab_th, interp_p="log")
    rng = np.random.default_rng(2009)
    edges = np.concatenate([[0.0], 10.0 ** np.arange(0, int(round(np.log10(tab_emax))) + 1)])

    def draw():
        k = rng.integers(0, len(edges) - 1)
        return rng.uniform(edges[k], edges[k + 1])

    trip = np.array([[draw(), draw(), rng.uniform(0, np.pi)] for _ in range(n_rand)])
    tt, er, p = ptab_log(trip[:, 0], trip[:, 1], trip[:, 2])
    ex = np.array([m.product_integral_exact(*row) for row in trip])
    fit_int = 2 * np.pi * p / (er + 1.0)
    err = np.abs(fit_int - ex)
    write_csv(out_dir / "product_table_interp.csv",
              [dict(e1=a_[0], e2=a_[1], theta_rad=a_[2], integral_exact_sr=x, integral_table_sr=y, abs_err_sr=z)
               for a_, x, y, z in zip(trip.tolist(), ex, fit_int, err)],
              comment=f"ProductTable(exponents={tab_per}/interval up to {tab_emax:g}, {tab_nt} angles, log-p "
                      f"trilinear) at random off-node triplets vs adaptive quadrature")
    summary["product_table_interp"] = dict(
        exponent_nodes=tab_es.tolist(), n_theta=tab_nt, n_random=n_rand, abs_err_sr=_weighted_stats(err, np.ones_like(err)),
        rel_err_nonzero=_weighted_stats((err / ex)[ex > 1e-12], np.ones(int(np.sum(ex > 1e-12)))),
        time_s=round(time.perf_counter() - t0, 2))
    summary["total_time_s"] = round(time.perf_counter() - t_start, 2)
    write_json(out_dir / "summary.json", summary)
    return summary


#: exact zeros are drawn at this value on the log axes (and said so under the figure)
FLOOR = 1e-17


def plot(out_dir: Path) -> list[Path]:

    plt = pyplot()

    out_dir = Path(out_dir)
    figs = []

    t = read_csv(out_dir / "integral_table_error.csv")
    e = np.array([float(r["exponent"]) for r in t])
    rel = np.array([float(r["rel_err"]) for r in t])
    c = read_csv(out_dir / "cap_fit.csv")
    al = np.array([float(r["alpha_deg"]) for r in c])
    ec = np.array([float(r["e_cap"]) for r in c])
    ta = np.array([float(r["table_alpha_rel_err"]) for r in c])
    tb = np.array([float(r["table_alpha2e_rel_err"]) for r in c])
    fig, ax = plt.subplots(1, 3, figsize=(14, 4))
    ax[0].loglog(np.maximum(e, 1e-3), np.maximum(rel, FLOOR), lw=0.6)
    ax[0].set(xlabel="exponent e", ylabel="relative error", title="Integral table (128/decade, linear) vs 2π/(e+1)")
    ax[1].semilogy(al, ec, label="e_cap(α) (Eq. 32–34)")
    ax[1].semilogy(al, 1.92256 / np.radians(al) ** 2, "--", lw=0.8, label="Gaussian limit 1.9226/α²")
    ax[1].set(xlabel="cap half-angle α (deg)", ylabel="lobe exponent", title="Spherical cap → lobe exponent")
    ax[1].legend()
    ax[2].semilogy(al, np.maximum(ta, FLOOR), lw=0.6, label="table in α (paper-like)")
    ax[2].semilogy(al, np.maximum(tb, FLOOR), lw=0.6, label="table in α²e")
    ax[2].set(xlabel="α (deg)", ylabel="relative error of e_cap", title="Cap table, 1000 entries, linear interp.")
    ax[2].legend()
    fig.text(0.5, 0.005, f"errors of exactly 0 (at table nodes) are drawn at {FLOOR:g}", ha="center", fontsize=8)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    p = out_dir / "cosine_lobes_tables.png"
    save_figure(fig, p, dpi=110)
    figs.append(p)

    rows = read_csv(out_dir / "product_fit.csv")
    e1 = np.array([float(r["e1"]) for r in rows])
    e2 = np.array([float(r["e2"]) for r in rows])
    th = np.array([float(r["theta_rad"]) for r in rows])
    ab = np.array([float(r["abs_err_sr"]) for r in rows])
    es = np.unique(e1)
    ths = np.unique(th)
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.4))
    # worst over θ, symmetric grid (Fig. 3 analogue)
    M = np.zeros((len(es), len(es)))
    for a, b, v in zip(e1, e2, ab):
        i, j = np.searchsorted(es, a), np.searchsorted(es, b)
        M[i, j] = max(M[i, j], v)
        M[j, i] = M[i, j]
    im = ax[0].imshow(np.log10(np.maximum(M, 1e-16)), origin="lower", cmap="magma_r")
    lab = [f"{x:g}" for x in es]
    step = max(1, len(es) // 8)
    ax[0].set_xticks(range(0, len(es), step), lab[::step], rotation=60, fontsize=7)
    ax[0].set_yticks(range(0, len(es), step), lab[::step], fontsize=7)
    ax[0].set(xlabel="lobe exponent e2", ylabel="lobe exponent e1", title="worst product-fit error over θ")
    fig.colorbar(im, ax=ax[0], label="log10 max_θ |∫c1c2 − ∫c_r| (sr); ≤ −16: exact")
    for lo, hi, col in [(0, 1, "C0"), (1, 10, "C1"), (10, 1e3, "C2"), (1e3, 1e6, "C3")]:
        sel = (np.maximum(e1, e2) >= lo) & (np.maximum(e1, e2) < hi) if hi < 1e6 else np.maximum(e1, e2) >= lo
        if not np.any(sel):
            continue
        mean_by_th = [np.mean(ab[sel & (th == t)]) for t in ths]
        top = f"{hi:g})" if hi < 1e6 else "∞)"
        ax[1].semilogy(np.degrees(ths), np.maximum(mean_by_th, FLOOR), "o-", color=col,
                       label=f"max(e1, e2) ∈ [{lo:g}, {top}")
    ax[1].axhline(PAPER_MEAN_ABS_ERR, color="k", ls="--", lw=0.8, label="paper mean 7.1e-4")
    ax[1].set(xlabel="angle between axes θ (deg)", ylabel="mean |∫c1c2 − ∫c_r| (sr)", title="Product fit error vs θ")
    ax[1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the curves, never on them
    fig.text(0.5, 0.005, f"errors of exactly 0 (e.g. θ = 0° and 180°) are drawn at {FLOOR:g}", ha="center", fontsize=8)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    p = out_dir / "cosine_lobes_product.png"
    save_figure(fig, p, dpi=110)
    figs.append(p)
    return figs
