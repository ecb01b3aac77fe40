"""Per-pixel exact filtering: the reference of the Kautz & McCool (2000) renders (their Eq. 1 without approximation).

:func:`render_reference`: per-pixel exact filtering ``Lo = Σ_j L_j f(ω_j, wo) max(n·ω_j, 0) Ω_j`` over the
environment texels (source texels optionally supersampled); **no visibility/shadows** (KM2000 has none).  For a
narrow BRDF the gather can be restricted to a cone ``angle(ω, r) ≤ γc`` around the mirror direction; for Ward,
:func:`ward_cut_angle` chooses γc and :func:`ward_neglected_bound` bounds what is neglected (below).
``supersample`` may be per sample (array): the experiment picks k from the BRDF slice's narrowest half width
at the pixel's θo (:func:`brdf_min_hwhm`; a grazing Ward lobe is narrow out of the incidence plane).

Ward truncation bound.  ``h = normalize(wo + ω)``; the map ω ↦ h has singular values ``½`` and ``1/(2 h·ω)``, both ≥ ½
(dω_h/dω = 1/(4 h·ω)), so geodesic distances shrink at most by ½: ``θh = angle(h, n) ≥ angle(ω, r)/2`` (h(r) = n).
Outside the cone, therefore, ``f cos θi ≤ ks e^{−tan²(γc/2)/α²} √cos θi / (4π α² √cos θo)`` and the neglected
radiance is at most ``L_max · ks · e^{−tan²(γc/2)/α²} / (α² √cos θo)`` (texel solid angles summed over ≤ 4π).
"""

from __future__ import annotations

import math

import numpy as np

from ..environment import envmap
from ..errors import IBLError
from ..environment.validated import environment_array
from ..limits import positive_int
from .profile_convolution import BLOCK_ELEMS
from ..progress import Progress
from .brdfs import view_direction

__all__ = ["render_reference", "brdf_min_hwhm", "ward_cut_angle", "ward_neglected_bound"]


def ward_cut_angle(alpha: float, eps: float = 1e-12) -> float:
    """Cone half-angle γc around r outside which Ward's exponential factor is ≤ eps (θh ≥ γ/2, module doc)."""
    alpha, eps = float(alpha), float(eps)
    if not (alpha > 0 and np.isfinite(alpha)) or not (0 < eps < 1):
        raise IBLError(f"need alpha > 0 and 0 < eps < 1, got alpha={alpha!r}, eps={eps!r}")
    return float(min(2.0 * math.atan(alpha * math.sqrt(math.log(1.0 / eps))), np.pi))


def ward_neglected_bound(alpha: float, ks: float, gamma_c: float, cos_theta_o, L_max: float):
    """Bound on the radiance neglected by the cone cut γc for Ward's specular term (module docstring): per sample.

    The diffuse term ``kd/π`` is not covered (it is not concentrated around r): with ``kd > 0`` gather without a
    cut (the km00-render experiment does)."""
    e = math.exp(-math.tan(min(gamma_c, np.pi - 1e-9) / 2.0) ** 2 / alpha**2) if gamma_c < np.pi else 0.0
    co = np.maximum(np.asarray(cos_theta_o, dtype=np.float64), 1e-300)
    return L_max * ks * e / (alpha**2 * np.sqrt(co))


def brdf_min_hwhm(brdf, theta_o, n_phi: int = 24, n_gamma: int = 400) -> np.ndarray:
    """Smallest half width at half maximum (rad) of the slice ``f(·, wo(θo))`` over great circles through the
    mirror direction r (``n = +z``; :func:`ibl_ref.lobes.brdfs.view_direction`).

    Along each of ``n_phi`` azimuths the first γ where ``f < max f / 2`` (max over all samples) is the half width;
    the minimum over azimuths is returned (an off-specular peak makes one side narrower: conservative).  Used to
    choose the reference's supersampling (an anisotropic grazing Ward lobe is narrow out of the incidence plane).
    """

    th = np.atleast_1d(np.asarray(theta_o, dtype=np.float64))
    gam = 0.5 * np.pi * (np.arange(n_gamma) / (n_gamma - 1)) ** 2
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    out = np.empty(th.shape)
    for i, t in enumerate(th):
        wo = view_direction(t)
        r = np.array([np.sin(t), 0.0, np.cos(t)])
        u = np.array([np.cos(t), 0.0, -np.sin(t)])  # ⟂ r in the incidence plane
        v = np.array([0.0, 1.0, 0.0])
        d = (np.cos(gam)[:, None, None] * r + np.sin(gam)[:, None, None]
             * (np.cos(phi)[None, :, None] * u + np.sin(phi)[None, :, None] * v))
        f = np.where(d[..., 2] > 0, brdf(d, wo), 0.0)
        fmax = f.max()
        if not fmax > 0:
            out[i] = np.pi
            continue
        below = f < 0.5 * fmax
        first = np.where(below.any(axis=0), below.argmax(axis=0), n_gamma - 1)
        out[i] = float(gam[np.maximum(first, 1)].min())
    return out if np.ndim(theta_o) else float(out[0])


def render_reference(cube, n, wo, brdf, *, supersample: int = 1, cut_angle: float | None = None,
                     bucket_size: int = 16, progress: bool = False) -> np.ndarray:
    """Per-pixel exact filtering ``Lo = Σ_j L_j f(ω_j, wo, n) max(n·ω_j, 0) Ω_j`` (no visibility); (P, C).

    Parameters
    ----------
    cube : (6, N, N[, C]) radiance; supersample : k×k sub-texels per texel (piecewise-constant L).
    n, wo : (P, 3) unit normals and view directions.
    brdf : callable ``f(wi, wo, n)`` (:func:`ibl_ref.lobes.brdfs.get_brdf`), 0 below either horizon.
    cut_angle : float, optional
        Gather only source texels within this angle of the mirror direction r (None: all texels; for Ward see
        :func:`ward_cut_angle` / :func:`ward_neglected_bound`).  Texels outside the cone may be included (whole
        buckets share a candidate list); that only adds exact terms.
    bucket_size : int
        Samples are bucketed by the cube texel (face size ``bucket_size``) of r to share candidate lists.
    progress : bool
        Report progress over the pixels (:mod:`ibl_ref.progress`).
    """
    from scipy.spatial import cKDTree

    a, squeeze = environment_array(cube, "environment cube map")
    nb = positive_int("bucket_size", bucket_size)
    nn = envmap.unit_directions(n, "n").reshape(-1, 3)
    vv = envmap.unit_directions(wo, "wo").reshape(-1, 3)
    if nn.shape != vv.shape:
        raise IBLError(f"n and wo must have the same shape, got {np.shape(n)} and {np.shape(wo)}")
    ks = np.asarray(supersample)
    if ks.ndim == 0:
        ks = np.full(nn.shape[0], positive_int("supersample", int(ks) if np.issubdtype(ks.dtype, np.integer) else ks))
    elif ks.shape != (nn.shape[0],) or not np.issubdtype(ks.dtype, np.integer) or np.any(ks < 1):
        raise IBLError("supersample must be a positive integer or a (P,) array of positive integers")
    C = a.shape[-1]
    cdot = np.sum(nn * vv, axis=1)
    r = 2.0 * cdot[:, None] * nn - vv
    out = np.zeros((nn.shape[0], C))
    f, row, col = envmap.direction_to_texel(r, nb)

    prog = Progress("exact Ward reference", int((cdot > 0).sum()), "pixel") if progress else None
    for k in np.unique(ks):
        m = a.shape[1] * int(k)
        src = a if k == 1 else np.repeat(np.repeat(a, int(k), axis=1), int(k), axis=2)
        sd = envmap.texel_directions(m).reshape(-1, 3)
        rw = src.reshape(-1, C) * np.asarray(envmap.cube_solid_angles(m)).reshape(-1, 1)
        del src
        tree = cKDTree(sd) if cut_angle is not None else None
        ok = (cdot > 0) & (ks == k)
        key = np.where(ok, (f * nb + row) * nb + col, -1)
        order = np.argsort(key, kind="stable")
        ks_sorted = key[order]
        starts = np.flatnonzero(np.r_[True, ks_sorted[1:] != ks_sorted[:-1]])
        ends = np.r_[starts[1:], ks_sorted.size]
        groups = [order[s0:e0] for s0, e0 in zip(starts, ends) if ks_sorted[s0] >= 0]
        for idx in groups:
            if prog is not None:
                prog.update(idx.size)
            if tree is None:
                cand = np.arange(sd.shape[0])
            else:
                rr = r[idx]
                cen = rr.mean(axis=0)
                cen /= np.linalg.norm(cen)
                rad = float(np.arccos(np.clip(rr @ cen, -1.0, 1.0)).max())
                cap = min(float(cut_angle) + rad + 1e-9, np.pi)
                cand = np.asarray(tree.query_ball_point(cen, 2.0 * math.sin(cap / 2.0) * (1 + 1e-12) + 1e-12),
                                  dtype=np.intp)
            if cand.size == 0:
                continue
            wi = sd[cand]
            rwc = rw[cand]
            rows = max(1, BLOCK_ELEMS // cand.size)
            for b0 in range(0, idx.size, rows):
                ib = idx[b0:b0 + rows]
                fv = brdf(wi[None, :, :], vv[ib][:, None, :], nn[ib][:, None, :])
                ci = np.maximum(nn[ib] @ wi.T, 0.0)
                out[ib] = (fv * ci) @ rwc
    if prog is not None:
        prog.close()
    if not np.all(np.isfinite(out)):
        raise IBLError("reference render produced NaN/Inf (check the BRDF parameters)")
    return out[:, 0] if squeeze else out
