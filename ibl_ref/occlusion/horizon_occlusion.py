"""Horizon occlusion of the reflected direction: Marmoset 2014 ("Horizon Occlusion for Normal Mapped Reflections",
Marmoset's technical article on its Toolbag renderer) and Godot's variant.

A normal map can bend the shading normal n so far from the geometric normal n_g that the mirror direction
R = reflect(−v, n) = 2(n·v) n − v points below the surface's true horizon, where the environment cannot be seen.
Marmoset fades the specular term out as R sinks below the geometric horizon:

    h = saturate(1 + k·(R·n_g)),  f_s = h²

with a fade constant k (``horizon-k1.1``, ``horizon-k1.3``: k = 1.1, 1.3; h = 0 once R·n_g ≤ −1/k), in
:func:`horizon_occlusion`.  Godot (``godot-horizon``, :func:`godot_horizon_occlusion`) uses the shading normal and
first bends R toward it by r²: R' = normalize(R + r²·(n − R)), h = min(1 + R'·n, 1), f_s = h² (k = 1).

Both labels set f_d = ao, like every occluding method of the registry: only the specular model differs between
them.

Examples
--------
>>> import numpy as np
>>> from ibl_ref.occlusion.interface import OcclusionInputs
>>> from ibl_ref.occlusion.horizon_occlusion import horizon_occlusion
>>> n = np.array([[0.6, 0.0, 0.8]])          # a normal-mapped normal
>>> v = np.array([[-1.0, 0.0, 0.0]])         # grazing view
>>> inp = OcclusionInputs(normal=n, view=v, roughness=0.5, geo_normal=np.array([[0.0, 0.0, 1.0]]),
...                       ao=np.array([1.0]))
>>> horizon_occlusion(inp, k=1.3).specular_factor  # R = (0.28, 0, -0.96): below the horizon
array([0.])
"""

from __future__ import annotations

import numpy as np

from ..errors import IBLError
from .interface import OcclusionInputs, OcclusionResult, alpha_of, reflect_view

__all__ = ["horizon_occlusion", "godot_horizon_occlusion"]


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("pi,pi->p", a, b)


def horizon_occlusion(inputs: OcclusionInputs, *, k: float = 1.3) -> OcclusionResult:
    """Marmoset's horizon occlusion: f_s = saturate(1 + k·(R·n_g))², f_d = ao.

    Parameters
    ----------
    inputs : OcclusionInputs
        Reads ``geo_normal`` (P, 3) and ``ao`` (P,).
    k : float
        Fade constant > 0 (the specular term vanishes once R·n_g ≤ −1/k).

    Returns
    -------
    OcclusionResult
        ``diffuse_factor`` = ao and ``specular_factor``, each (P,) in [0, 1].
    """
    if isinstance(k, bool) or not isinstance(k, (int, float, np.floating, np.integer)) or not np.isfinite(k) or k <= 0:
        raise IBLError(f"parameter k must be a finite number > 0, got {k!r}")
    h = np.clip(1.0 + float(k) * _dot(reflect_view(inputs.normal, inputs.view), inputs.geo_normal), 0.0, 1.0)
    return OcclusionResult(diffuse_factor=inputs.ao.copy(), specular_factor=h * h)


def godot_horizon_occlusion(inputs: OcclusionInputs) -> OcclusionResult:
    """Godot's horizon occlusion: R' = normalize(R + r²(n − R)), f_s = min(1 + R'·n, 1)², f_d = ao.

    Parameters
    ----------
    inputs : OcclusionInputs
        Reads ``ao`` (P,) besides n, v and the roughness.

    Returns
    -------
    OcclusionResult
        ``diffuse_factor`` = ao and ``specular_factor``, each (P,) in [0, 1].  Where R + r²(n − R) vanishes
        (v = −n at r² = 1/2) R'·n is taken as 0 (h = 1).

    Examples
    --------
    With a view in front of the shading normal, R·n = n·v ≥ 0 and nothing is occluded:

    >>> import numpy as np
    >>> from ibl_ref.occlusion.interface import OcclusionInputs
    >>> z = np.array([[0.0, 0.0, 1.0]])
    >>> godot_horizon_occlusion(OcclusionInputs(normal=z, view=z, roughness=0.5, ao=np.array([0.5]))).specular_factor
    array([1.])
    """
    n = inputs.normal
    R = reflect_view(n, inputs.view)
    t = np.asarray(alpha_of(np.asarray(inputs.roughness, dtype=np.float64)))
    bent = R + (t[:, None] if t.ndim else t) * (n - R)
    length = np.linalg.norm(bent, axis=1)
    cos_rn = np.where(length > 0, _dot(bent, n) / np.where(length > 0, length, 1.0), 0.0)
    h = np.clip(np.minimum(1.0 + cos_rn, 1.0), 0.0, 1.0)
    return OcclusionResult(diffuse_factor=inputs.ao.copy(), specular_factor=h * h)
