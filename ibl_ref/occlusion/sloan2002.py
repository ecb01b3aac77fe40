"""Precomputed radiance transfer of the diffuse term: Sloan, Kautz & Snyder 2002, "Precomputed Radiance Transfer
for Real-Time Rendering in Dynamic, Low-Frequency Lighting Environments", SIGGRAPH 2002, Sec. 4 (radiance
self-transfer: the shadowed diffuse transfer vector and its dot product with the lighting's SH coefficients).

With a transfer vector per pixel, T_k = ∫ V(ω) max(n·ω, 0)/π Y_k(ω) dω (the visibility-weighted clamped cosine,
divided by π so that T·L is a lobe average like A_1), and the radiance's coefficients L_k = ∫ L(ω) Y_k(ω) dω in the
same orthonormal basis, orthonormality turns the occluded diffuse lobe average into a dot product:

    D = ∫ L V max(n·ω, 0)/π dω ≈ Σ_{k < order²} T_k L_k    (per colour channel),

exact when either L or the transfer lies in the first ``order`` SH bands.  ``prt-3`` and ``prt-5``
(:func:`prt_diffuse`, ``order`` 3 or 5: 9 or 25 coefficients) return D as ``diffuse_radiance``, which replaces the
unoccluded A_1 in :func:`~ibl_ref.occlusion.interface.shade`; the specular term is left unoccluded
(``specular="none"``) or multiplied by ao (``specular="ao"``, which then needs the input ``ao``).

SH convention: the lab's real SH basis, :func:`ibl_ref.groundtruth.sh_basis.real_sh` (orthonormal, polar axis +z,
index l² + l + m, no Condon–Shortley phase); the first order² coefficients of either vector are the bands l < order.
The dot product itself holds in any orthonormal basis as long as T and L use the same one.

Examples
--------
A constant environment L ≡ 2 (L_0 = 2√(4π)) seen through an unoccluded transfer (T_0 = 1/√(4π)):

>>> import numpy as np
>>> from ibl_ref.occlusion.interface import OcclusionInputs
>>> from ibl_ref.occlusion.sloan2002 import prt_diffuse
>>> z = np.array([[0.0, 0.0, 1.0]])
>>> T = np.zeros((1, 9)); T[0, 0] = 1 / np.sqrt(4 * np.pi)
>>> L = np.zeros((9, 1)); L[0, 0] = 2 * np.sqrt(4 * np.pi)
>>> prt_diffuse(OcclusionInputs(normal=z, view=z, roughness=0.5, sh_transfer=T, env_sh=L), order=3).diffuse_radiance
array([[2.]])
"""

from __future__ import annotations

import numpy as np

from ..errors import IBLError
from .ambient_occlusion import SPECULAR_FACTORS
from .interface import OcclusionInputs, OcclusionResult, choice

__all__ = ["prt_diffuse"]

def prt_diffuse(inputs: OcclusionInputs, *, order: int = 3, specular: str = "none") -> OcclusionResult:
    """Diffuse radiance D = Σ_{k < order²} T_k L_k per channel (module docstring); f_s = 1 or ao.

    Parameters
    ----------
    inputs : OcclusionInputs
        Reads ``sh_transfer`` (P, K) and ``env_sh`` (K', C), both with K, K' ≥ order²; ``ao`` with
        ``specular="ao"``.
    order : int
        Number of SH bands used (≥ 1): order² coefficients.
    specular : {"none", "ao"}
        Specular factor 1 or ao.

    Returns
    -------
    OcclusionResult
        ``diffuse_radiance`` (P, C) and ``specular_factor`` (P,).

    Raises
    ------
    IBLError
        ``order`` not a whole number ≥ 1, or fewer than order² coefficients in either input.
    """
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or order < 1:
        raise IBLError(f"parameter order must be a whole number >= 1, got {order!r}")
    K = int(order) ** 2
    f_s = SPECULAR_FACTORS[choice(specular, "specular", tuple(SPECULAR_FACTORS))](inputs)
    for name, have in (("sh_transfer", inputs.sh_transfer.shape[1]), ("env_sh", inputs.env_sh.shape[0])):
        if have < K:
            raise IBLError(f"order {order} needs {K} SH coefficients, but {name} holds {have}")
    return OcclusionResult(diffuse_radiance=inputs.sh_transfer[:, :K] @ inputs.env_sh[:K], specular_factor=f_s)
