"""Error budget of an IBL method: from the exact image to the method's image, one approximation at a time.

For each method of :mod:`ibl_ref.rendering.method_shading` this module defines a chain of images I_0 … I_K, I_0 the
reference and I_K exactly the method's image (:func:`~ibl_ref.rendering.method_shading.shade_method`), each step
switching on one approximation, so that every approximation is measured alone — the increment δ_k = I_k − I_{k−1}
— as :mod:`ibl_ref.rendering.error_budget` does for the paper's method.  Notation: pixel with normal n, view v,
r = 2(n·v)n − v; "exact" integrals are the adaptive texel integrals of
:mod:`ibl_ref.rendering.unoccluded_reference` (the piecewise-constant map, converged to ``rtol``); DFG = F0·A + B of
Karis's Eq. 9 at (n·v, roughness): "exact" by :func:`ibl_ref.prefilter.karis2013.dfg_terms`, "table" the method's
64² table (:class:`~ibl_ref.prefilter.karis2013.DFGTable`).

Steps (in walk order; a step a method does not have is left out):

* ``visibility`` — the certified reference with V ≡ 1 (its ``unoccluded`` image; occluded scenes only): the
  increment is the light the method's missing visibility adds (what self-shadowing removes).  Every later image is
  unoccluded, except the last step of the methods with Eq. 5's visibility.
* ``integrator`` — the same unoccluded shading by the lab's adaptive texel integral instead of the reference
  renderer's converged quadrature (occluded scenes only; on the unoccluded sphere the adaptive integral *is* the
  reference).  Not an approximation: its increment must be within the two estimates (the check that the walk starts
  at the reference).
* GGX materials, split-sum methods (``split-sum``, ``split-sum-is``, ``split-sum-fis``, ``ggx-phong-pem``):

  - ``split_sum`` — Karis's Eq. 7 with the true view: ``P_v(n, v)·DFG_exact``, P_v the average of L under the GGX
    sampling pdf of view v weighted by (n·l)⁺ (:class:`~ibl_ref.rendering.unoccluded_reference.SplitSumLobe`):
    the separation of the integral into two factors alone;
  - ``n_v_r`` — the prefilter lobe with n = v = r: ``P(r)·DFG_exact``, P the average under
    K(r·l) = D(√((1 + r·l)/2))·max(r·l, 0) (:class:`~ibl_ref.rendering.unoccluded_reference.NVRKernelLobe`): no
    stretched reflections at grazing view (Karis: "the larger source of error");
  - ``phong_lobe`` (``ggx-phong-pem`` only) — K replaced by the Phong lobe max(r·l, 0)^s of the mapped exponent
    s(roughness) (:func:`ibl_ref.prefilter.ggx_phong_mapping.phong_exponent`), exact;
  - ``prefilter`` — the method's quadrature at each pixel's own r at full resolution, which each method provides
    as ``direct(cube, roughness, dirs)``: the texel-centre sum of the source (``split-sum``,
    :func:`~ibl_ref.prefilter.karis2013.prefilter_exact`), N GGX importance samples (``split-sum-is``), filtered
    importance sampling (``split-sum-fis``); for a method reading a Phong prefilter (``ggx-phong-pem``: it has a
    ``phong`` prefilter and an ``exponent`` mapping) the Phong prefilter's own look-up (for the paper's pyramid: its
    filter shape and its g → level mapping); for a prefilter run as a whole program (``cmgen``: no ``direct``) its
    chain as it comes, the ``mip`` step included;
  - ``mip`` — the method's roughness MIP chain read trilinearly (levels at coarser face sizes, roughness blended
    between the levels' ℓ/(n_levels − 1); methods with ``direct`` only);
  - ``dfg_table`` — DFG_exact → the method's table (bilinear between its texel centres).
* Phong materials, Phong methods: ``lobe_hemisphere`` — the lobe average no longer clipped to n's hemisphere (a
  prefilter does not know n; glossy lobes only); ``prefilter`` — the method's look-up.
* Diffuse materials (``sh9`` and the Phong methods at s = 1): ``prefilter`` — the method's irradiance.
* ``pem_visibility`` (methods with Eq. 5's visibility, occluded scenes only) — Σ_i VIS_i·PEM_i with variance
  shadow maps instead of Σ_i PEM_i: what the paper's self-shadowing gives back.

The increments telescope, so their signed biases add up to the method's bias exactly; their rel. L1s do not
(|Σδ| ≤ Σ|δ|): shares are rel. L1 / Σ rel. L1 (:func:`ibl_ref.rendering.error_budget.budget_rows`).
"""

from __future__ import annotations

import numpy as np

from ..errors import IBLError
from . import method_shading as ms
from . import unoccluded_reference as ur
from ..environment.envmap import unit_directions
from .error_budget import budget_rows
from .unoccluded_reference import integrate

__all__ = ["STEPS", "budget_walk", "budget_table_rows"]

#: every step name, in walk order
STEPS = ("visibility", "integrator", "split_sum", "n_v_r", "phong_lobe", "lobe_hemisphere", "prefilter", "mip",
         "dfg_table", "pem_visibility")


def _exact(cube, lobe, n, v, rtol, floor_value=None, cache=None):
    """The adaptive integral of ``lobe`` at the pixels (cached in ``cache`` by the lobe, which is hashable)."""

    if cache is not None and lobe in cache:
        return cache[lobe]
    val = integrate(cube, lobe, n, v, rtol=rtol, floor_value=floor_value).value
    if cache is not None:
        cache[lobe] = val
    return val


def budget_walk(built, material, cube, normals, views, *, reference=None, reference_unoccluded=None,
                exact_unoccluded=None, scene=None, points=None, face_normals=None, rtol: float = 2e-3,
                vsm_resolution: int = 256, vsm_kw: dict | None = None, cache: dict | None = None) -> list:
    """The walk ``[(step, image (P, C)), …]`` from the reference to the method's image (module docstring).

    ``built``: :func:`ibl_ref.rendering.method_shading.build_method` of ``cube``; ``material`` with kd = 0 for GGX,
    ks = 0 (diffuse) or kd = 0 (glossy) for Phong (one lobe at a time); ``reference`` / ``reference_unoccluded``:
    the certified occluded image and its V ≡ 1 image (occluded scenes; then ``scene``, ``points``,
    ``face_normals`` for the method's shadow maps); ``exact_unoccluded``: the adaptive integral of the material
    (computed here if None); ``cache``: a dict that keeps the exact integrals of the steps for other methods of the
    same pixels and map (the ``split_sum`` and ``n_v_r`` images are the same for every split-sum method).  The
    first image of the walk is the reference (not listed).
    """

    spec = built.spec
    m = ms.shading_material(material)
    if not ms.serves(spec.lobe, m):
        raise ms.MethodNotApplicable(f"method {spec.label!r} does not shade a {m.kind} material")
    if m.has_diffuse and m.has_specular:
        raise IBLError("the method budget takes one lobe at a time: a GGX material with kd = 0, or a Phong material "
                       "with either kd = 0 or ks = 0")
    a = np.asarray(cube, dtype=np.float64)
    n = unit_directions(np.asarray(normals, dtype=np.float64).reshape(-1, 3), "normals")
    v = unit_directions(np.asarray(views, dtype=np.float64).reshape(-1, 3), "views")
    nv = np.sum(n * v, axis=1)
    front = (nv > 0)[:, None]
    r = 2.0 * nv[:, None] * n - v
    occluded = reference is not None
    walk = []

    def add(step, img):
        walk.append((step, np.where(front, np.asarray(img, dtype=np.float64), 0.0)))

    ref_lobe = m.unoccluded_lobe()
    if exact_unoccluded is None:
        exact_unoccluded = _exact(a, ref_lobe, n, v, rtol, cache=cache)
    exact_unoccluded = np.where(front, exact_unoccluded, 0.0)
    scale = float(np.mean(np.abs(exact_unoccluded))) * 0.1  # the floor of the relative targets, shared by all steps
    if occluded:
        if reference_unoccluded is None:
            raise IBLError("an occluded reference needs its unoccluded image (reference_unoccluded)")
        add("visibility", reference_unoccluded)
        add("integrator", exact_unoccluded)
    vis = spec.visibility == "vsm" and scene is not None
    if spec.lobe == "ggx":  # the split-sum methods' steps (they shade the GGX materials)
        rough, f0 = m.roughness, m.f0
        dfg_exact = ms.dfg_weight(None, nv, rough, f0, m.smith)
        dfg_tab = ms.dfg_weight(built.prefilter.dfg, nv, rough, f0, m.smith)
        add("split_sum", _exact(a, ur.SplitSumLobe(rough), n, v, rtol, scale, cache) * dfg_exact)
        add("n_v_r", _exact(a, ur.NVRKernelLobe(rough), n, v, rtol, scale, cache) * dfg_exact)
        pf = built.prefilter
        if hasattr(pf, "phong"):  # a GGX method reading a Phong prefilter through a roughness → exponent mapping
            s = float(pf.exponent(rough))
            add("phong_lobe", _exact(a, ur.PhongLobe(s, "mirror", clip=False), n, v, rtol, scale, cache) * dfg_exact)
            add("prefilter", pf.phong.lookup(r, s) * dfg_exact)
        elif hasattr(pf, "direct"):  # the method's own quadrature at full resolution, then its MIP chain
            add("prefilter", pf.direct(a, rough, r) * dfg_exact)
            add("mip", pf.lookup(r, rough) * dfg_exact)
        else:  # a prefilter run as a whole (an outside program): its chain as it comes
            add("prefilter", pf.lookup(r, rough) * dfg_exact)
        add("dfg_table", ms.shade_method(built, m, n, v) if not vis else pf.lookup(r, rough) * dfg_tab)
    else:
        if m.has_specular:
            add("lobe_hemisphere", _exact(a, ur.PhongLobe(ref_lobe.s, "mirror", clip=False), n, v, rtol, scale, cache))
        add("prefilter", ms.shade_method(ms.BuiltMethod(ms.MethodSpec(spec.prefilter, spec.params, "none",
                                                                      label=spec.label), built.prefilter,
                                                        built.diffuse, None, 0.0, built.cube_shape), m, n, v))
    if vis:
        add("pem_visibility", ms.shade_method(built, m, n, v, scene=scene, points=points, face_normals=face_normals,
                                              vsm_resolution=vsm_resolution, vsm_kw=vsm_kw))
    return walk


def budget_table_rows(reference, walk, *, front=None) -> list:
    """:func:`ibl_ref.rendering.error_budget.budget_rows` of a walk over pixels (P, C): one dict per step, the
    reference first."""

    ref = np.asarray(reference, dtype=np.float64)
    mask = np.ones(len(ref), dtype=bool) if front is None else np.asarray(front, dtype=bool)
    return budget_rows(ref, walk, mask)
