"""Precomputed radiance transfer of a glossy lobe: Sloan, Kautz & Snyder 2002, "Precomputed Radiance Transfer for
Real-Time Rendering in Dynamic, Low-Frequency Lighting Environments", SIGGRAPH 2002, Sec. 5 (glossy transfer: the
transfer matrix M applied to the lighting's SH vector, then convolved with a radially symmetric BRDF kernel and
evaluated at the reflection direction R; Kautz, Sloan & Snyder 2002 generalise the kernel to arbitrary BRDFs).

**Transferred radiance.**  With M_ij = ∫ V(ω) Y_i(ω) Y_j(ω) dω per pixel
(:func:`ibl_ref.occlusion.oracle_inputs.sh_transfer_matrix`: V = 0 at and below the shading horizon) and the
radiance's coefficients L_j, the visible incident radiance V·L has, projected onto the first ``order`` bands, the
coefficients (M L)_i — exact when L lies in those bands.

**Zonal kernel and its normalisation.**  The lab's Phong lobe about R is normalised over the whole sphere,
k̂(ω) = max(R·ω, 0)^s / c_0 with c_0 = 2π/(s + 1), and its specular term is the lobe average ∫ L k̂ dω (clipped
to n·ω > 0 in the numerator, which V already holds here).  Funk–Hecke: ∫ f(ω) max(R·ω, 0)^s dω =
Σ_lm c_l f_lm Y_lm(R) with c_l = 2π ∫_0^1 t^s P_l(t) dt (Ramamoorthi & Hanrahan 2001; closed form
:func:`ibl_ref.groundtruth.sh_bounds.zonal_coefficients`).  The lobe's zonal coefficients g_l = ∫ k̂ Y_l0 dω =
√((2l + 1)/(4π)) c_l / c_0, so the paper's g_l √(4π/(2l + 1)) is c_l / c_0 (1 at l = 0: a constant radiance is
its own lobe average) and the occluded lobe average is

    G = Σ_{l < order} (c_l / c_0) Σ_m (M L)_lm Y_lm(R)         (:func:`transferred_lobe_average`).

**GGX.**  A GGX lobe is not radially symmetric about R.  The method replaces it by the Phong lobe of the lab's
GGX → Phong exponent mapping, s = :func:`ibl_ref.prefilter.ggx_phong_mapping.phong_exponent` (roughness)
(TV-optimal, about the n = v = R kernel), and weights G by the unoccluded term's specular weight
(:class:`~ibl_ref.occlusion.interface.UnoccludedTerms` ``specular_weight``: the GGX directional albedo F0·A + B,
Phong's ks).  Both the lobe shape and the split of the weight are model errors the occlusion zoo measures; so
is the truncation at ``order`` bands, which fails for narrow lobes (c_l / c_0 ≈ exp(−l²/(2s)) is far from 0 at
l = order when s ≫ order²: a sharp reflection is blurred to the band limit and rings).  The method reads the
roughness (``reads_roughness``), so it serves GGX materials and diffuse-only ones, not a Phong glossy lobe.

**Clamp.**  Near a bright small source (the sun) the truncated series rings below zero; the method returns
max(G, 0), as a shader writing radiance would (the paper's formula itself is unclamped; :func:`transferred_lobe_average`
is).  The diffuse term is left as ``prt-N``'s.

**Diffuse term.**  That of :func:`ibl_ref.occlusion.sloan2002.prt_diffuse`, D = T·L, so ``prt-glossy-N`` is
``prt-N``'s diffuse transfer plus the glossy transfer.

Examples
--------
A constant environment L ≡ 2 seen through M = I: every lobe average is 2.

>>> import numpy as np
>>> from ibl_ref.occlusion.sloan2002_glossy import transferred_lobe_average
>>> M = np.eye(9)[None]; L = np.zeros((9, 1)); L[0, 0] = 2 * np.sqrt(4 * np.pi)
>>> transferred_lobe_average(M, L, np.array([[0.0, 0.0, 1.0]]), 10.0, order=3).round(12)
array([[2.]])
"""

from __future__ import annotations

import numpy as np

from ..errors import IBLError
from .interface import OcclusionInputs, OcclusionResult, reflect_view
from .sloan2002 import prt_diffuse

__all__ = ["lobe_band_weights", "prt_glossy", "transferred_lobe_average"]


def lobe_band_weights(s, order: int) -> np.ndarray:
    """c_l / c_0, l < ``order``, of the Phong lobe max(R·ω, 0)^s (module docstring; per exponent).

    Parameters
    ----------
    s : float or array (P,)
        Phong exponent(s) ≥ 1; ``inf`` is the mirror limit, c_l / c_0 = 1.
    order : int

    Returns
    -------
    ndarray, shape (P, order) (P = 1 for a scalar s)

    Examples
    --------
    >>> from ibl_ref.occlusion.sloan2002_glossy import lobe_band_weights
    >>> lobe_band_weights(1.0, 3).round(6).tolist()  # the clamped cosine: A_l / A_0 = 1, 2/3, 1/4
    [[1.0, 0.666667, 0.25]]
    """
    from ..groundtruth.sh_bounds import zonal_coefficients

    s = np.atleast_1d(np.asarray(s, dtype=np.float64))
    uniq, inv = np.unique(s, return_inverse=True)
    w = np.array([np.ones(order) if np.isinf(u) else zonal_coefficients(float(u), order - 1) for u in uniq])
    return (w / w[:, :1])[inv.reshape(-1)]


def transferred_lobe_average(M, env_sh, R, s, *, order: int) -> np.ndarray:
    """G = Σ_{l < order} (c_l/c_0) Σ_m (M L)_lm Y_lm(R) per pixel and channel (module docstring).

    Parameters
    ----------
    M : array (P, K, K), K ≥ order²
    env_sh : array (K', C), K' ≥ order²
    R : array (P, 3)
        Unit lobe axes (reflection directions).
    s : float or array (P,)
        Phong exponent(s).
    order : int

    Returns
    -------
    ndarray (P, C)
    """
    from ..groundtruth.sh_basis import real_sh

    K = order * order
    ML = np.einsum("pij,jc->pic", M[:, :K, :K], env_sh[:K])  # (P, K, C)
    band = np.repeat(np.arange(order), 2 * np.arange(order) + 1)
    w = lobe_band_weights(s, order)[:, band]  # (P or 1, K)
    return np.einsum("pk,pkc->pc", w * real_sh(R, order - 1), ML)


def prt_glossy(inputs: OcclusionInputs, *, order: int = 3) -> OcclusionResult:
    """Diffuse D = T·L and glossy G (:func:`transferred_lobe_average`, s from the GGX → Phong mapping of the
    roughness; r = 0 the mirror limit s = ∞) of order ``order`` (module docstring).

    Parameters
    ----------
    inputs : OcclusionInputs
        Reads ``sh_transfer`` (P, K), ``sh_transfer_matrix`` (P, K, K) and ``env_sh`` (K', C), each with
        K, K' ≥ order², and the roughness.
    order : int
        Number of SH bands (≥ 1).

    Returns
    -------
    OcclusionResult
        ``diffuse_radiance`` and ``specular_radiance`` (P, C); G clamped at 0 (module docstring).

    Raises
    ------
    IBLError
        ``order`` not a whole number ≥ 1, or fewer than order² coefficients in an input.
    """
    from ..prefilter.ggx_phong_mapping import phong_exponent

    D = prt_diffuse(inputs, order=order).diffuse_radiance
    M = np.asarray(inputs.sh_transfer_matrix, dtype=np.float64)
    K = int(order) ** 2
    if M.ndim != 3 or M.shape[1] < K or M.shape[2] < K:
        raise IBLError(f"order {order} needs {K} x {K} transfer matrices, but sh_transfer_matrix has shape "
                       f"{M.shape}")
    r = np.broadcast_to(np.asarray(inputs.roughness, dtype=np.float64), (len(inputs.normal),))
    s = np.full(r.shape, np.inf)  # r = 0: the mirror limit of the lobe (c_l / c_0 → 1)
    if np.any(r > 0):
        s[r > 0] = phong_exponent(r[r > 0])
    G = transferred_lobe_average(M, inputs.env_sh, reflect_view(inputs.normal, inputs.view), s, order=order)
    G = np.maximum(G, 0.0)  # the truncated series rings below 0 near bright sources; a shader's output is ≥ 0
    return OcclusionResult(diffuse_radiance=D, specular_radiance=G)
