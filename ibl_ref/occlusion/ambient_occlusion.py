"""No occlusion, and the ambient-occlusion value used as a plain factor (the glTF 2.0 occlusion texture).

* ``none`` (:func:`no_occlusion`): f_d = f_s = 1, the unoccluded image-based lighting.
* ``ao-diffuse`` / ``ao-both`` (:func:`ao_factors`): f_d = ao, and f_s = 1 or f_s = ao.  The glTF 2.0
  specification (Khronos, Sec. 3.9.3 "Additional Textures", ``occlusionTexture``) defines the occlusion map as
  darkening the indirect lighting without saying how it enters a specular term; engines differ: the occlusion
  map into the diffuse image-based term only (``ao-diffuse``), or into both terms (``ao-both``).

ao is the cosine-weighted visibility ∫ V max(n·ω, 0)/π dω (:class:`~ibl_ref.occlusion.interface.OcclusionInputs`),
so ``ao-diffuse`` is exact for the diffuse term wherever the environment's radiance is constant over the
hemisphere.

Examples
--------
>>> import numpy as np
>>> from ibl_ref.occlusion.interface import OcclusionInputs
>>> from ibl_ref.occlusion.ambient_occlusion import ao_factors
>>> z = np.array([[0.0, 0.0, 1.0]])
>>> res = ao_factors(OcclusionInputs(normal=z, view=z, roughness=0.5, ao=np.array([0.25])), specular="ao")
>>> res.diffuse_factor, res.specular_factor
(array([0.25]), array([0.25]))
"""

from __future__ import annotations

import numpy as np

from .interface import OcclusionInputs, OcclusionResult, choice

__all__ = ["no_occlusion", "ao_factors", "SPECULAR_FACTORS"]


def no_occlusion(inputs: OcclusionInputs) -> OcclusionResult:
    """f_d = f_s = 1 for every pixel (the unoccluded lighting).

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.occlusion.interface import OcclusionInputs
    >>> z = np.array([[0.0, 0.0, 1.0]])
    >>> no_occlusion(OcclusionInputs(normal=z, view=z, roughness=0.5)).specular_factor
    array([1.])
    """
    P = len(inputs.normal)
    return OcclusionResult(diffuse_factor=np.ones(P), specular_factor=np.ones(P))


#: ``specular`` parameter → the specular factor (P,) from the inputs (also PRT's, :mod:`~ibl_ref.occlusion.sloan2002`)
SPECULAR_FACTORS = {"none": lambda inputs: np.ones(len(inputs.normal)), "ao": lambda inputs: inputs.ao.copy()}


def ao_factors(inputs: OcclusionInputs, *, specular: str = "none") -> OcclusionResult:
    """f_d = ao; f_s = 1 (``specular="none"``, glTF's diffuse-only use) or f_s = ao (``specular="ao"``).

    Parameters
    ----------
    inputs : OcclusionInputs
        Reads ``ao`` (P,).
    specular : {"none", "ao"}
        Whether the specular term is left unoccluded or multiplied by ao too.

    Returns
    -------
    OcclusionResult
        ``diffuse_factor`` and ``specular_factor``, each (P,).

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.occlusion.interface import OcclusionInputs
    >>> z = np.array([[0.0, 0.0, 1.0]])
    >>> ao_factors(OcclusionInputs(normal=z, view=z, roughness=0.5, ao=np.array([0.5]))).specular_factor
    array([1.])
    """
    f_s = SPECULAR_FACTORS[choice(specular, "specular", tuple(SPECULAR_FACTORS))](inputs)
    return OcclusionResult(diffuse_factor=inputs.ao.copy(), specular_factor=f_s)
