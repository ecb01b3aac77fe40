"""``ibl-ref render --mode reference|mitsuba``: the converged reference (:func:`ibl_ref.rendering.reference_render.render_reference`)
and Mitsuba 3 (:func:`ibl_ref.rendering.mitsuba_render.render_mitsuba`) with per-mesh materials (mesh id 0, ground id 1):
Phong ``kd,ks,g`` or GGX ``ggx:...`` (:mod:`ibl_ref.rendering.materials`)."""

from __future__ import annotations

import numpy as np

from ..errors import IBLError


def _material(mat, option):
    """The exact renderers' material (:func:`ibl_ref.rendering.materials.as_material`): scalar kd, ks, one g."""
    from ..rendering.materials import as_material

    try:
        return as_material(mat, option)
    except IBLError as exc:
        raise IBLError(f"{exc} (--mode reference/mitsuba: no RGB weights, no --gmap)") from None


def check_args(args) -> None:
    """Cheap flag checks before any rendering."""
    if args.mode == "reference" and args.ref_rtol is not None:
        from ..limits import check_rtol

        check_rtol(args.ref_rtol, "--ref-rtol")
    if getattr(args, "workers", None) is not None and args.workers < 1:
        raise IBLError(f"--workers must be a positive integer (1 = serial), got {args.workers}")
    if args.mode == "mitsuba" and (args.spp < 2 or args.spp % 2):
        raise IBLError(f"--spp must be an even number >= 2, got {args.spp}")


def render_exact(mode, meshes, camera, cube, mat, ground_mat, args, progress=False):
    """(image (H, W, C), mask (H, W), info dict) of ``mode`` ∈ {reference, mitsuba}."""
    materials = {0: _material(mat, "--material")}
    if ground_mat is not None:
        materials[1] = _material(ground_mat, "--ground-material")
    if mode == "reference":
        from ..rendering.reference_converged import DEFAULT_RTOL
        from ..rendering.reference_render import render_reference

        from ..groundtruth.convolve import default_workers

        rtol = DEFAULT_RTOL if args.ref_rtol is None else float(args.ref_rtol)
        workers = default_workers() if args.workers is None else int(args.workers)
        res = render_reference(meshes, camera, cube, materials=materials, rtol=rtol, seed=args.seed,
                               workers=workers, progress=progress)
        keep = ("rtol", "err_rel_l1", "err_rel_p99", "converged", "n_rays", "time_s", "sided", "n_back_facing",
                "quadrature", "ray_backend", "lobes", "materials")
        res.info["workers"] = workers
        keep = keep + ("workers",)
        return res.image, res.mask, {"reference": {k: res.info[k] for k in keep if k in res.info}}
    from ..rendering.mitsuba_render import bsdf_dict, render_mitsuba

    if any(m.kind == "phong" and m.mirror for m in materials.values()):
        raise IBLError("--mode mitsuba: glossiness must be < 1 (the mirror g = 1 is not a Phong lobe)")
    route = getattr(args, "mitsuba_ggx", "lab")
    has_ggx = any(m.kind == "ggx" for m in materials.values())
    first = "builtin" if route == "builtin" else "lab"
    res = render_mitsuba(meshes, camera, cube, materials=materials, ggx_route=first, spp=args.spp, seed=args.seed)
    info = {"mitsuba": res.info}
    if has_ggx and route == "both":
        try:
            for m in materials.values():
                bsdf_dict(m, "builtin")  # applies? (separable Smith, F0 = 1)
        except IBLError as exc:
            info["mitsuba_builtin"] = {"skipped": str(exc)}
        else:
            b = render_mitsuba(meshes, camera, cube, materials=materials, ggx_route="builtin", spp=args.spp,
                               seed=args.seed + 2)
            m = res.mask & b.mask
            den = float(np.abs(b.image[m]).sum())
            info["mitsuba_builtin"] = dict(b.info, rel_l1_vs_lab=float(np.abs(res.image[m] - b.image[m]).sum() / den)
                                           if den > 0 else 0.0,
                                           noise_rel_l1_both=float(res.info["noise_rel_l1"] + b.info["noise_rel_l1"]))
    return res.image, res.mask, info
