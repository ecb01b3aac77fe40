"""Specular occlusion from ambient occlusion: Lagarde & de Rousiers 2014, "Moving Frostbite to Physically Based
Rendering" (SIGGRAPH 2014 course notes, the specular-occlusion part of the section on shadowing and occlusion, the
function ``computeSpecOcclusion``), and Unreal Engine 4's variant of it.

With ao the cosine-weighted visibility and n·v clamped to [0, 1] (the engines' saturated NoV; a negative n·v would
leave the power undefined):

    f_s = saturate((n·v + ao)^e − 1 + ao),

* ``exponent="frostbite"``: e = 2^(−16·x − 1) — x = α = r² (``roughness_input="alpha"``: labels
  ``lagarde2014-alpha``, the roughness Filament, Unity HDRP and Bevy pass) or x = r (``"perceptual"``:
  ``lagarde2014-r``, three.js);
* ``exponent="unreal"``: e = x (Unreal Engine 4's ``GetSpecularOcclusion`` with its squared roughness α: label
  ``unreal-so``).

The formula is an empirical fit: f_s = ao at grazing n·v = 0 when e → 0 (rough), and → 1 as ao → 1 (every e: the
power of a base ≥ 1 is ≥ 1); at ao = 0 it is (n·v)^e − 1 ≤ 0, saturated to 0.  The diffuse factor of these labels is
f_d = ao (:func:`specular_occlusion_from_ao`), as for every occluding method of the registry.

Examples
--------
>>> import numpy as np
>>> from ibl_ref.occlusion.interface import OcclusionInputs
>>> from ibl_ref.occlusion.lagarde2014 import specular_occlusion_from_ao
>>> z = np.array([[0.0, 0.0, 1.0]])
>>> inp = OcclusionInputs(normal=z, view=z, roughness=1.0, ao=np.array([0.5]))
>>> specular_occlusion_from_ao(inp).specular_factor  # (1.5)^(1/2^17) - 0.5
array([0.50000309])
>>> specular_occlusion_from_ao(inp, exponent="unreal").specular_factor
array([1.])
"""

from __future__ import annotations

import numpy as np

from .interface import OcclusionInputs, OcclusionResult, choice, roughness_value

__all__ = ["specular_occlusion_from_ao", "EXPONENTS"]

#: ``exponent`` → e(x), the power applied to (n·v + ao)
EXPONENTS = {
    "frostbite": lambda x: np.exp2(-16.0 * x - 1.0),
    "unreal": lambda x: x,
}


def specular_occlusion_from_ao(inputs: OcclusionInputs, *, exponent: str = "frostbite",
                               roughness_input: str = "alpha") -> OcclusionResult:
    """f_s = saturate((n·v + ao)^e − 1 + ao), f_d = ao (module docstring).

    Parameters
    ----------
    inputs : OcclusionInputs
        Reads ``ao`` (P,) besides n, v and the roughness.
    exponent : {"frostbite", "unreal"}
        e = 2^(−16·x − 1) (Lagarde & de Rousiers 2014) or e = x (Unreal Engine 4).
    roughness_input : {"alpha", "perceptual"}
        x = α = r² or x = r.

    Returns
    -------
    OcclusionResult
        ``diffuse_factor`` = ao and ``specular_factor``, each (P,) in [0, 1].

    Examples
    --------
    ao = 1 leaves the specular term unoccluded, ao = 0 removes it:

    >>> import numpy as np
    >>> from ibl_ref.occlusion.interface import OcclusionInputs
    >>> n = np.array([[0.0, 0.0, 1.0]] * 2)
    >>> v = np.array([[0.6, 0.0, 0.8]] * 2)
    >>> inp = OcclusionInputs(normal=n, view=v, roughness=0.3, ao=np.array([1.0, 0.0]))
    >>> specular_occlusion_from_ao(inp, roughness_input="perceptual").specular_factor
    array([1., 0.])
    """
    e = EXPONENTS[choice(exponent, "exponent", tuple(EXPONENTS))](roughness_value(inputs, roughness_input))
    ao = inputs.ao
    nv = np.clip(np.einsum("pi,pi->p", inputs.normal, inputs.view), 0.0, 1.0)
    f_s = np.clip((nv + ao) ** e - 1.0 + ao, 0.0, 1.0)
    return OcclusionResult(diffuse_factor=ao.copy(), specular_factor=f_s)
