"""Spherical-harmonic (SH) Phong-lobe convolution with a rigorous per-texel error bound.

Implements Knuth et al. (2014), Sec. 3.2, Eq. 4 (the convolution of the environment with the clamped
cosine lobe ``max(r·ω, 0)^s``, ``s = s_Phong = 1/(1−g)``, Eq. 3) by the Funk–Hecke theorem, plus a
"hybrid" split that convolves the brightest texels (a sun) exactly.

The quadrature that is approximated
-----------------------------------
The reference (:func:`ibl_ref.groundtruth.phong_convolution.convolve_exact`) is the discrete sum over source texels
``N(r) = Σ_j L_j k(r·ω_j) Ω_j`` with ``k(t) = max(t, 0)^s`` and exact texel solid angles ``Ω_j``, and the
lobe average ``y(r) = N(r) / D(r)``, ``D(r) = Σ_j k(r·ω_j) Ω_j``.

Funk–Hecke / addition theorem
-----------------------------
Expand the kernel in Legendre polynomials, ``k(t) = Σ_l c_l (2l+1)/(4π) P_l(t)`` with::

    c_l = 2π ∫_{-1}^{1} k(t) P_l(t) dt = 2π ∫_0^1 x^s P_l(x) dx                     (Funk–Hecke eigenvalue)

and use ``(2l+1)/(4π) P_l(r·ω) = Σ_m Y_lm(r) Y_lm(ω)`` (addition theorem, real orthonormal SH).  With the
*discrete* projection ``a_lm = Σ_j L_j Y_lm(ω_j) Ω_j`` this gives **exactly** (no quadrature error)::

    N_L(r) = Σ_{l≤L} c_l Σ_m a_lm Y_lm(r) = Σ_j L_j k_L(r·ω_j) Ω_j,

where ``k_L`` is the degree-L truncation of the Legendre series.  The only error is the kernel
truncation ``e_L = k − k_L``.  The normalised average uses the same truncation for ``D`` (the SH of the
all-ones map), so a constant environment is reproduced to rounding.  For ``L(ω) = a + b·ω`` the
continuous average is ``a + (b·r)·c_1/c_0 = a + (b·r)(s+1)/(s+2)``.

Closed form of the zonal coefficients
-------------------------------------
For Re μ > −1 (Gradshteyn & Ryzhik 7.126.2; also Byerly, *Fourier's Series and Spherical Harmonics*)::

    ∫_0^1 x^μ P_ν(x) dx = √π · 2^{−μ−1} · Γ(1+μ) / [ Γ(1 + μ/2 − ν/2) · Γ(μ/2 + ν/2 + 3/2) ]

(checks: μ=ν=0 → 1; μ=ν=1 → 1/3; μ=0, ν=2 → 0).  It is evaluated in log space with
``math.lgamma`` (log |Γ|) and the sign of ``1/Γ(1 + μ/2 − ν/2)`` (zero at the poles; :func:`_lgamma_sign`), so
it does not overflow for s up to 1e6 and l in the hundreds.  :func:`zonal_coefficients` returns ``c_l``.

Rigorous error bound
--------------------
Write the remainder environment ``L_r`` (see *hybrid*, below) with values in ``[m, τ]``.  With ``N' = N +
ε_N`` and ``D' = D + ε_D`` the SH results, ``(y' − y) D' = ε_N − y ε_D = Σ_j (L_r,j − y) Ω_j e_L(r·ω_j)``,
hence ``|y' − y| ≤ (max(τ, y) − m) · E_L / D'`` with the **texel-envelope integral**::

    E_L = 2π ∫_0^π ê_L(θ) sin θ dθ ,   ê_L(θ) = max_{|θ' − θ| ≤ ρ} |e_L(cos θ')| ,

where ρ is the largest angle between a source texel centre and its corners.  Since every point ω of
texel j is within ρ of ω_j, ``|e_L(r·ω_j)| ≤ ê_L(angle(r, ω))`` on the whole texel and
``Σ_j Ω_j |e_L(r·ω_j)| ≤ ∫ ê_L dω = E_L`` for **every** r.  ``ê_L`` is evaluated on a fine θ grid (the
window is widened by one grid step; the only non-rigorous part is the sampling of ``|e_L|`` between
grid points, with a grid of ≥ 40 points per oscillation of ``P_L``).  Solving for y gives the absolute
bound ``A = max((τ − m) η, (y' − m) η/(1 − η))`` with ``η = E_L / D'`` and the relative bound
``A / (y' − A)`` (∞ where ``y' ≤ A``).  Unnormalised Eq. 4: ``|ε_N| ≤ τ · E_L`` (``L_r ∈ [0, τ]``).

Band limit
----------
The band limit is the smallest tabulated L (every L ≤ 24, then every 4th, up to :data:`SH_L_MAX`)
with ``E_L / (2π/(s+1)) ≤ 0.8 rtol · min(1, y_lo / (τ − m))``, where ``y_lo`` is an estimate of the darkest
output texel of that exponent (:func:`_output_floor`: half the minimum of the exact lobe averages of a 16² copy of
the map; a band-4 SH preview used before rang below zero on probes with a dark ground), or the environment minimum
if larger.  The a-posteriori bound
above is what is reported (plus a rounding allowance ``4π·ε_mach·(L+1)²`` added to ``E_L``); the
a-priori choice only aims at it.  Exponents that would need L > SH_L_MAX (s ≈ 1, whose lobe has a kink at the
horizon so ``E_L`` decays only like L^−1.5, and s ≳ 500, whose lobe is narrow) are left to the other
methods by :func:`ibl_ref.groundtruth.convolve.convolve`.

Hybrid for bright suns
----------------------
A small 1e5 sun makes the truncated series ring over the whole sphere and makes ``τ − m`` huge.  The
environment is split as ``L = min(L, τ) + max(L − τ, 0)``: the second term is non-zero on the few
texels above the threshold τ and is convolved **exactly** (a gather from those texels for every output
texel); only the clipped remainder ``min(L, τ) ∈ [m, τ]`` goes through SH, so the bound uses τ.  τ is
chosen among the brightest-texel quantiles by a simple cost model (SH band limit needed for the bound
vs. number of gathered texels).

Modules.  This module holds the hybrid split, the planner (band limit, sun threshold, cost model) and
:func:`convolve_sh_many`; the basis with the cube grid's reflection symmetries is :mod:`ibl_ref.groundtruth.sh_basis`, the
zonal coefficients and the truncation envelope :mod:`ibl_ref.groundtruth.sh_bounds`.

Real SH basis (no Condon–Shortley phase; projection and evaluation use the same basis, so the phase is
irrelevant): ``Y_l0 = P̄_l0(cos θ)``, ``Y_lm = √2 P̄_l|m|(cos θ) cos(mφ)`` (m > 0), ``√2 P̄_l|m| sin(|m|φ)``
(m < 0), index ``l² + l + m``; ``P̄_lm`` are the fully normalised associated Legendre functions from the
standard stable recurrences (sectoral ``P̄_mm = √((2m+1)/(2m)) sin θ P̄_{m−1,m−1}``, then
``P̄_lm = a_lm (x P̄_{l−1,m} − b_lm P̄_{l−2,m})``), which do not overflow for L in the hundreds (values
only underflow to 0 near the poles, where they are negligible).
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..environment import envmap
from .convolution_args import channel_max, check_cube, check_exponent, check_out_size
from ..errors import IBLError
from ..limits import check_rtol
from .phong_convolution import convolve_exact_many
from .sh_basis import SymmetryPlan
from .sh_basis import evaluate_part
from .sh_basis import funk_hecke
from .sh_basis import project_part

__all__ = [
    "convolve_sh",
    "convolve_sh_many",
    "plan_sh",
    "sh_cost",
    "bright_cost",
]

_FOUR_PI = 4.0 * np.pi

# the basis (with the grid symmetries) and the zonal coefficients / truncation bounds live in their own modules
from .kernels import get_kernels  # noqa: E402
from .sh_basis import sh_lobe_convolve  # noqa: E402
from .sh_bounds import (  # noqa: E402
    SH_L_MAX,
    choose_band_limit,
    legendre_series_truncation_envelope,
    texel_max_radius,
    zonal_coefficients,
)


# ----------------------------------------------------------------------------------------------
# hybrid SH convolution with bound
# ----------------------------------------------------------------------------------------------
def _threshold_candidates(lum):
    order = np.sort(lum.ravel())[::-1]
    cands = []
    for k in (0, 8, 32, 128, 512, 2048):
        if k < order.size:
            tau = float(order[k])  # texels strictly above tau are gathered: at most k of them
            cands.append((int(np.count_nonzero(lum > tau)), tau))
    return cands


#: face size of the coarse map whose exact lobe averages estimate the darkest output texel (:func:`_output_floor`)
FLOOR_FACE = 16
#: the planner takes this share of that estimate as the output floor (minima narrower than a coarse texel)
FLOOR_SAFETY = 0.5
#: an exponent whose band limit would fit L_max with a floor this many times higher is "within reach": the
#: planner of :func:`ibl_ref.groundtruth.convolve.convolve` may try it at L_max (the bound is checked after)
FLOOR_REACH = 10.0


def _output_floor(rad, s_list, impl="numpy"):
    """Per exponent, an estimate of the smallest lobe average of the output (over texels and channels):
    :data:`FLOOR_SAFETY` × the minimum of the exact lobe averages of a coarse copy of the map (face size
    :data:`FLOOR_FACE`, each coarse texel the solid-angle-weighted mean of the texels whose face position falls in
    it).  On the CC0 probes at 256² it is within 0.86–1.0 of the darkest output texel of the SH route at L = 160
    (s = 16, 256), where the band-4 SH preview used before rang below zero (probes with a dark ground).
    The exact sums by the bright-texel gather of the kernel ``impl`` (absolute weights c^s); where the nearest
    texel's weight could underflow, by the exact gather, which normalises every row by its largest weight."""

    M, C = rad.shape
    key = (impl, rad.shape, float(rad.sum()), float(rad[:: max(1, M // 997)].sum()), float(rad.max()))
    if all((key, float(s)) in _FLOOR_CACHE for s in s_list):  # the map planned again (kernel choice, SH subset)
        return np.array([_FLOOR_CACHE[(key, float(s))] for s in s_list])
    n = int(round(math.sqrt(M / 6)))
    nc = min(n, FLOOR_FACE)
    om = envmap.cube_solid_angles(n)
    idx = (np.arange(n) * nc) // n
    flat = (np.arange(6)[:, None, None] * nc * nc + (idx[:, None] * nc + idx[None, :])[None]).ravel()
    oc = np.bincount(flat, om.ravel(), 6 * nc * nc)
    a = rad.reshape(6, n, n, C)
    coarse = np.stack([np.bincount(flat, (a[..., c] * om).ravel(), 6 * nc * nc) for c in range(C)], axis=-1)
    coarse = (coarse / oc[:, None]).reshape(6, nc, nc, C)
    if max(s_list) * math.log(math.cos(texel_max_radius(nc))) > -600.0:
        d = envmap.texel_directions(nc).reshape(-1, 3)
        om_c = envmap.cube_solid_angles(nc).reshape(-1)
        sums = get_kernels(impl).bright_gather(d, d, np.concatenate([coarse.reshape(-1, C), np.ones((d.shape[0], 1))],
                                                                    axis=1) * om_c[:, None], list(s_list))
        ys = sums[..., :C] / sums[..., C:]
    else:
        ys = convolve_exact_many(coarse, list(s_list))
    out = FLOOR_SAFETY * ys.reshape(len(s_list), -1).min(axis=1)
    if len(_FLOOR_CACHE) > 64:
        _FLOOR_CACHE.clear()
    _FLOOR_CACHE.update({(key, float(s)): float(y) for s, y in zip(s_list, out)})
    return out


#: the last floors of :func:`_output_floor`, keyed by a fingerprint of the map and the exponents (planning only)
_FLOOR_CACHE: dict = {}


def _plan(rad, omega, src, n_out, s_list, rtol, rho, hybrid, tau, L_max, estimate=False, impl="numpy"):
    """Choose the sun threshold τ and band limit L from the a-priori bound and a cost model.

    Returns dict with ``L`` (joint band limit; None if no candidate meets rtol within L_max and
    ``estimate`` is False), ``tau``, ``L_per_s`` (band limit each exponent needs for the rigorous bound,
    None if > L_max), ``L_est`` (exponent → band limit used in estimate mode), ``reach`` (per exponent: would
    fit L_max with a :data:`FLOOR_REACH` times higher output floor), ``n_bright`` and ``cost``.  The output floor of
    each exponent is :func:`_output_floor` (computed by the kernel ``impl``).
    """
    C = rad.shape[1]
    lum = rad.max(axis=1)
    m_min = float(rad.min())
    if not hybrid:
        cands = [(0, float(rad.max()))]
    elif tau is not None:
        cands = [(int(np.count_nonzero(lum > tau)), float(tau))]
    else:
        cands = _threshold_candidates(lum)
    # a-priori estimate of the darkest output texel, per exponent
    y_lo = np.maximum(np.maximum(_output_floor(rad, s_list, impl), m_min), 1e-300)
    best = None
    K = len(s_list)
    reach = [False] * K
    for nb, tau_k in cands:
        eta_t = [0.8 * rtol * min(1.0, y / max(tau_k - m_min, 1e-300)) for y in y_lo]
        Ls = [choose_band_limit(s, e, rho, L_max) for s, e in zip(s_list, eta_t)]
        reach = [r or choose_band_limit(s, min(FLOOR_REACH * e, 0.8 * rtol), rho, L_max) is not None
                 for r, s, e in zip(reach, s_list, eta_t)]
        L_est = {s: _estimate_band_limit(s, rtol, rho) for s, x in zip(s_list, Ls) if x is None} if estimate else {}
        feas = [x for x in Ls if x is not None] + list(L_est.values())
        if not feas:
            continue
        Lk = max(feas + [1])
        cost = sh_cost(Lk, src.shape[0], n_out, len(feas) + len(L_est), C + 1) + bright_cost(nb, n_out, len(feas))
        key = (-len(feas), cost)  # serve as many exponents as possible, then cheapest
        if best is None or key < best[0]:
            best = (key, Lk, nb, tau_k, Ls, L_est)
    if best is None:
        return {"L": None, "tau": cands[-1][1], "L_per_s": [None] * K, "L_est": {}, "cost": np.inf, "reach": reach,
                "n_bright": cands[-1][0], "floor": [float(y) for y in y_lo]}
    return {"L": best[1], "tau": best[3], "L_per_s": best[4], "L_est": best[5], "cost": best[0][1], "reach": reach,
            "n_bright": best[2], "floor": [float(y) for y in y_lo]}


#: largest band limit used for exponents whose rigorous bound cannot meet rtol (estimate mode)
SH_L_EST_MAX = 64


def _estimate_band_limit(s, rtol, rho):
    """Band limit for the estimate mode: E_L/D ≤ rtol/2 (spread ≈ output), within [16, SH_L_EST_MAX]."""
    L = choose_band_limit(s, 0.5 * rtol, rho, SH_L_EST_MAX)
    return int(min(max(L if L is not None else SH_L_EST_MAX, 16), SH_L_EST_MAX))


#: seconds per cost unit of :func:`sh_cost` (fitted: 128² faces, K = 8, Q = 4, L = 40 / 80 on the shared
#: 2-core machine, 1 BLAS thread: 1.2 s / 6.2 s)
SECONDS_PER_UNIT = 8e-10

#: fixed cost of one SH call (planning preview, bound tables), in units (≈ 0.04 s)
SH_OVERHEAD_UNITS = 5e7


def sh_cost(L, n_src, n_out, K, Q):
    """Cost model of :func:`sh_lobe_convolve` (units of :data:`SECONDS_PER_UNIT`).

    Refitted after the octant-symmetric SH matrix (one eighth of the directions, built once for
    projection and evaluation).  Measured wall time of :func:`sh_lobe_convolve`, 128² faces, Q = 4, 1 BLAS
    thread, K = 1 … 8 kernels: 0.12–0.19 s at L = 40, 0.58–0.90 s at L = 80 (nearly independent of K, as the
    small K·Q term says; the model is conservative and used for routing and job order only).
    """
    return (L + 1) ** 2 * (n_src + n_out) * 0.5 * (4.0 + 0.03 * K * Q)


def bright_cost(n_bright, n_out, K):
    """Cost model of the exact gather from the bright texels (same units as :func:`sh_cost`)."""
    return n_bright * n_out * (3.0 + 15.0 * K)


def plan_sh(cube, exponents, *, rtol=1e-3, out_size=None, hybrid=True, L_max=SH_L_MAX, estimate=False,
            impl="numpy"):
    """A-priori plan of the hybrid SH route: band limit each exponent needs and the model cost.

    Returns dict ``L`` (joint band limit or None), ``tau``, ``L_per_s`` (list, None = would need more
    than L_max), ``cost`` (model units, comparable with :func:`sh_cost`).  ``impl``: the kernel of the estimate of
    the darkest output texel (the plan of the route that runs with that kernel).
    """
    a, _ = check_cube(cube)
    n = a.shape[1]
    out_size = check_out_size(out_size, n)
    s_list = [check_exponent(s) for s in np.atleast_1d(np.asarray(exponents, dtype=object))]
    src = envmap.texel_directions(n).reshape(-1, 3)
    omega = np.ascontiguousarray(envmap.cube_solid_angles(n)).reshape(-1)
    rad = a.reshape(-1, a.shape[-1])
    return _plan(rad, omega, src, 6 * out_size * out_size, s_list, rtol, texel_max_radius(n), hybrid, None, L_max,
                 estimate, impl)



def convolve_sh_many(
    cube,
    exponents,
    *,
    rtol: float = 1e-3,
    L: int | None = None,
    hybrid: bool = True,
    tau: float | None = None,
    out_size: int | None = None,
    normalized: bool = True,
    L_max: int = SH_L_MAX,
    estimate: bool = False,
    plan: dict | None = None,
    impl: str = "numpy",
):
    """SH (optionally hybrid) convolution for several exponents sharing one SH pass.

    Parameters
    ----------
    cube : array (6, N, N[, C])
    exponents : sequence of float ≥ 1 (finite)
    rtol : float
        Target relative error used to choose the band limit and the sun threshold (not guaranteed:
        check the returned bound).
    L : int, optional
        Force the band limit (otherwise chosen from the bound).
    hybrid : bool
        Convolve texels above the threshold τ exactly (default True).
    tau : float, optional
        Force the threshold (radiance, compared with the per-texel channel maximum).
    out_size : int, optional
    normalized : bool
        Lobe average (default) or literal Eq. 4.
    L_max : int
        Cap for the automatically chosen band limit (rigorous mode).
    estimate : bool
        For exponents whose rigorous bound cannot meet rtol within L_max (broad lobes with a kinked
        horizon, s ≈ 1), also evaluate the band-limit-L/2 result and report the **estimate**
        ``|y_L − y_{L/2}| / y_L`` (the error of the coarser result, which over-estimates the error of
        y_L when the truncation error decreases with L).  Not a proof; flagged in ``info["bound_kind"]``.
        Default False: measured on the sky+sun environment at 32² (s = 1, L = 32…96) the true error
        exceeded this estimate by up to ~2000× at single texels, so :func:`ibl_ref.groundtruth.convolve.convolve`
        never relies on it.
    plan : dict, optional
        Result of :func:`plan_sh` for the same cube/exponents/rtol (avoids planning twice).
    impl : {"numpy", "compiled"}
        The kernel backend (:mod:`ibl_ref.groundtruth.kernels`) of the SH passes and the bright gather (the compiled
        one without an SH matrix; its gather's rounding bound is added to the bound).

    Returns
    -------
    maps : ndarray (K, 6, n, n, C)
    rel_bound : ndarray (K, 6, n, n) — per-texel relative error bound (max over channels; inf where the
        bound is useless, e.g. zero output); rigorous unless ``info["bound_kind"][k] == "estimate"``
    info : dict (L, tau, n_bright, bound_kind list, timings)
    """
    setup = sh_setup(cube, exponents, rtol=rtol, L=L, hybrid=hybrid, tau=tau, out_size=out_size,
                     normalized=normalized, L_max=L_max, estimate=estimate, plan=plan, impl=impl)
    t_plan = time.perf_counter()
    kern = get_kernels(setup.impl)
    shq = sh_lobe_convolve(setup.src, setup.Wq, setup.out_dirs, setup.kcoef, kern)  # (K, P, C+1)
    t_sh = time.perf_counter()
    nb = kern.bright_gather(setup.out_dirs, setup.b_dirs, setup.b_w, setup.s_list)  # exact part
    t_gather = time.perf_counter()
    return sh_finish(setup, shq, nb, {"time_plan_s": t_plan - setup.t0, "time_sh_s": t_sh - t_plan,
                                      "time_bright_s": t_gather - t_sh})


class ShSetup:
    """Everything one SH convolution needs after planning (:func:`sh_setup`): the split of the radiance into
    the SH remainder and the exactly gathered bright excess, the band limit and the zonal kernels.  Plain
    arrays and numbers (picklable), so the parts of a split pass can run on any executor."""

    def __init__(self, **kw):
        self.__dict__.update(kw)


def sh_setup(cube, exponents, *, rtol: float = 1e-3, L: int | None = None, hybrid: bool = True,
             tau: float | None = None, out_size: int | None = None, normalized: bool = True,
             L_max: int = SH_L_MAX, estimate: bool = False, plan: dict | None = None,
             impl: str = "numpy") -> ShSetup:
    """Checks, plan (band limit, sun threshold) and the split of :func:`convolve_sh_many` (same parameters)."""
    t0 = time.perf_counter()
    a, squeeze = check_cube(cube)
    n = a.shape[1]
    out_size = check_out_size(out_size, n)
    s_list = [check_exponent(s) for s in np.atleast_1d(np.asarray(exponents, dtype=object))]
    if not s_list:
        raise IBLError("no Phong exponents given")
    if any(not np.isfinite(s) for s in s_list):
        raise IBLError("the SH route cannot represent the mirror (s = inf); use method='exact'")
    rtol = check_rtol(rtol)
    C = a.shape[-1]
    src = envmap.texel_directions(n).reshape(-1, 3)
    omega = np.ascontiguousarray(envmap.cube_solid_angles(n)).reshape(-1)
    rad = a.reshape(-1, C)
    out_dirs = src if out_size == n else envmap.texel_directions(out_size).reshape(-1, 3)
    rho = texel_max_radius(n)

    # --- threshold / band limit -----------------------------------------------------------
    if L is None:
        if plan is None:
            plan = _plan(rad, omega, src, out_dirs.shape[0], s_list, rtol, rho, hybrid, tau, L_max, estimate, impl)
        L_use, tau_use = plan["L"], plan["tau"]
        est_idx = [k for k, x in enumerate(plan["L_per_s"]) if x is None] if estimate else []
        if L_use is None:  # nothing meets rtol within L_max: use L_max with the largest bright set
            L_use = L_max
    else:
        L_use = int(L)
        if not hybrid:
            tau_use = float(rad.max())
        elif tau is not None:
            tau_use = float(tau)
        else:
            tau_use = _threshold_candidates(rad.max(axis=1))[-1][1]
        est_idx = list(range(len(s_list))) if estimate else []

    # --- split: SH remainder (clamped at τ) + exact excess of the bright texels ---------------
    bright = rad.max(axis=1) > tau_use
    rem = np.minimum(rad, tau_use)
    excess = rad[bright] - rem[bright]
    kcoef = np.stack([zonal_coefficients(s, L_use) for s in s_list])
    if est_idx:  # the same kernels truncated at L/2 (estimate mode)
        half = kcoef[est_idx].copy()
        half[:, L_use // 2 + 1 :] = 0.0
        kcoef = np.concatenate([kcoef, half])
    Wq = np.concatenate([rem, np.ones((rem.shape[0], 1))], axis=1) * omega[:, None]
    return ShSetup(t0=t0, squeeze=squeeze, out_size=out_size, C=C, s_list=s_list, src=src, out_dirs=out_dirs,
                   rho=rho, L=int(L_use), tau=float(tau_use), est_idx=est_idx, n_bright=int(np.count_nonzero(bright)),
                   b_dirs=src[bright], b_w=excess * omega[bright][:, None], kcoef=kcoef, Wq=Wq,
                   m_rem=float(rem.min()), tau_eff=float(rem.max()), normalized=normalized, rtol=rtol,
                   sym_src=None, sym_out=None, impl=impl)


def sh_split(setup: ShSetup, n_parts: int) -> ShSetup:
    """Prepare ``setup`` for a pass in ``n_parts`` independent pieces (:func:`sh_project_part`, then
    :func:`sh_evaluate_part`): the symmetry plans of the source and output directions (computed once here,
    not in every part).  Returns ``setup``."""

    setup.sym_src = SymmetryPlan(setup.src, setup.L, n_parts)
    setup.sym_out = setup.sym_src if setup.out_dirs is setup.src else SymmetryPlan(setup.out_dirs, setup.L, n_parts)
    return setup


def sh_project_part(setup: ShSetup, part: int):
    """Projection of the remainder (all kernels share it) over part ``part`` of the source directions:
    ``(a_even, a_odd)``; :func:`sh_coefficients` adds the parts in order."""

    return project_part(setup.src, setup.Wq, setup.sym_src, part, get_kernels(setup.impl))


def sh_coefficients(setup: ShSetup, parts):
    """Sum of the projection parts (in the given order) times the Funk–Hecke eigenvalues: ``(Be, Bo)``."""

    ae = parts[0][0].copy()
    ao = parts[0][1].copy()
    for pe, po in parts[1:]:
        ae += pe
        ao += po
    return funk_hecke(setup.kcoef, ae, ao)


def sh_evaluate_part(setup: ShSetup, Be, Bo, part: int):
    """Evaluation at part ``part`` of the output directions, the exact gather of the bright excess there and
    the per-texel values and bounds: ``(idx, maps (K, p, C), rel (K, p), rel_estimate (K, p) or None)``
    for the outputs ``idx`` (:func:`sh_assemble` puts the parts together)."""

    kern = get_kernels(setup.impl)
    idx, vals = evaluate_part(setup.out_dirs, Be, Bo, setup.sym_out, part, kern)
    K = setup.kcoef.shape[0]
    shq = vals.reshape(-1, K, setup.Wq.shape[1]).transpose(1, 0, 2)
    nb = kern.bright_gather(setup.out_dirs[idx], setup.b_dirs, setup.b_w, setup.s_list)
    return (idx,) + _values_and_bounds(setup, shq, nb)


def sh_assemble(setup: ShSetup, parts, times: dict):
    """The parts ``[(idx, maps, rel, rel_estimate), …]`` of :func:`sh_evaluate_part` as the return value of
    :func:`convolve_sh_many`."""
    K, P = len(setup.s_list), setup.out_dirs.shape[0]
    maps = np.empty((K, P, setup.C))
    rel = np.empty((K, P))
    est = np.empty((K, P)) if setup.est_idx else None
    for idx, m, r, e in parts:
        maps[:, idx] = m
        rel[:, idx] = r
        if est is not None:
            est[:, idx] = e
    return _finish(setup, maps, rel, est, times)


def sh_finish(setup: ShSetup, shq, nb, times: dict):
    """Maps and rigorous bounds (module docstring) from the SH sums ``shq`` (K', P, C+1) and the bright gather
    ``nb`` (K, P, C) at every output texel: the return value of :func:`convolve_sh_many`."""
    return _finish(setup, *_values_and_bounds(setup, shq, nb), times)


def _values_and_bounds(setup: ShSetup, shq, nb):
    """Lobe averages (or Eq. 4 sums) and their rigorous relative bounds at the outputs of ``shq``/``nb`` (any
    subset: every texel's bound uses only global constants): ``(maps (K, p, C), rel (K, p), rel_estimate)``,
    the last (the |y_L − y_{L/2}| estimate of the exponents in ``setup.est_idx``) None without estimates."""
    C, s_list, normalized, rho, L_use = setup.C, setup.s_list, setup.normalized, setup.rho, setup.L
    est_idx, m_rem, tau_eff = setup.est_idx, setup.m_rem, setup.tau_eff
    K = len(s_list)
    P = shq.shape[1]
    maps = np.empty((K, P, C))
    rel = np.empty((K, P))
    rel_est = np.full((K, P), np.inf) if est_idx else None
    d_nb = get_kernels(setup.impl).bright_gather_error(nb, setup.b_w, s_list)
    for k, s in enumerate(s_list):
        E_L = legendre_series_truncation_envelope(s, L_use, rho)
        E_L += _FOUR_PI * np.finfo(float).eps * (L_use + 1) ** 2  # rounding of the O(L²) SH sums
        num = shq[k, :, :C] + nb[k]
        den = shq[k, :, C:]
        if normalized:
            ok_den = den > E_L
            # den ≤ E_L: the truncated lobe weight is not even positive-definite there; the value is
            # kept (num/den, or 0 if den ≤ 0) but its bound is inf
            y = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
            eta = np.where(ok_den, E_L / np.where(ok_den, den, 1.0), np.inf)
            with np.errstate(invalid="ignore", divide="ignore"):
                A = np.maximum((tau_eff - m_rem) * eta, np.maximum(y - m_rem, 0.0) * eta / np.maximum(1.0 - eta, 1e-300))
                A = np.where(eta < 1.0, A, np.inf)
        else:
            y = num
            A = np.full_like(y, tau_eff * E_L)
        if d_nb is not None:  # the bright gather's rounding (the compiled kernels': relative and absolute parts)
            with np.errstate(invalid="ignore", divide="ignore"):
                A = A + (np.where(den > 0, d_nb[k] / np.where(den > 0, den, 1.0), np.inf) if normalized else d_nb[k])
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.where(y > A, A / np.maximum(y - A, 1e-300), np.inf)
        maps[k] = y
        rel[k] = channel_max(r)
        if k in est_idx:
            j = K + est_idx.index(k)
            y_half = (shq[j, :, :C] + nb[k]) / (shq[j, :, C:] if normalized else 1.0)
            with np.errstate(invalid="ignore", divide="ignore"):
                est = np.abs(y - y_half) + 1e-12 * np.abs(y)
                est = np.where(y > est, est / np.maximum(y - est, 1e-300), np.inf)
            rel_est[k] = channel_max(est)
    return maps, rel, rel_est


def _finish(setup: ShSetup, maps, rel, rel_est, times: dict):
    """Bound kinds (an estimate replaces the rigorous bound of an exponent in ``est_idx`` only where the
    rigorous one misses rtol somewhere), shapes and the info dict."""
    K = len(setup.s_list)
    kinds = []
    for k in range(K):
        kinds.append("rigorous")
        if k in setup.est_idx and not float(rel[k].max()) <= setup.rtol:
            rel[k] = rel_est[k]
            kinds[-1] = "estimate"
    n = setup.out_size
    maps = maps.reshape((K, 6, n, n, setup.C))
    if setup.squeeze:
        maps = maps[..., 0]
    info = {
        "L": int(setup.L),
        "tau": setup.tau,
        "n_bright": setup.n_bright,
        "texel_radius_rad": setup.rho,
        "bound_kind": kinds,
        **times,
        "time_total_s": time.perf_counter() - setup.t0,
    }
    return maps, rel.reshape((K, 6, n, n)), info


def convolve_sh(cube, s, **kwargs):
    """Single-exponent :func:`convolve_sh_many`; returns ``(maps (6,n,n,C), rel_bound (6,n,n), info)``."""
    maps, rel, info = convolve_sh_many(cube, [s], **kwargs)
    return maps[0], rel[0], info
