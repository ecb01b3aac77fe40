"""``ibl-ref render --mode reference|mitsuba``: the converged reference (:func:`ibl_ref.rendering.reference_render.render_reference`)
and Mitsuba 3 (:func:`ibl_ref.rendering.mitsuba_render.render_mitsuba`) with per-mesh materials (mesh id 0, ground id 1)."""

from __future__ import annotations

import numpy as np

from ..errors import IBLError


def _scalar(mat, option):
    if np.ndim(mat.kd) or np.ndim(mat.ks) or mat.g_map is not None:
        raise IBLError(f"{option}: --mode reference/mitsuba take scalar kd, ks and one g (no RGB weights, no --gmap)")
    return float(mat.kd), float(mat.ks), float(mat.g)


def check_args(args) -> None:
    """Cheap flag checks before any rendering."""
    if args.mode == "reference" and args.ref_rtol is not None:
        if not (np.isfinite(args.ref_rtol) and args.ref_rtol >= 0):
            raise IBLError(f"--ref-rtol must be a finite number >= 0, got {args.ref_rtol}")
    if getattr(args, "workers", None) is not None and args.workers < 1:
        raise IBLError(f"--workers must be a positive integer (1 = serial), got {args.workers}")
    if args.mode == "mitsuba" and (args.spp < 2 or args.spp % 2):
        raise IBLError(f"--spp must be an even number >= 2, got {args.spp}")


def render_exact(mode, meshes, camera, cube, mat, ground_mat, args, progress=False):
    """(image (H, W, C), mask (H, W), info dict) of ``mode`` ∈ {reference, mitsuba}."""
    materials = {0: _scalar(mat, "--material")}
    if ground_mat is not None:
        materials[1] = _scalar(ground_mat, "--ground-material")
    if mode == "reference":
        from ..rendering.reference_render import DEFAULT_RTOL, render_reference

        from ..groundtruth.convolve import default_workers

        rtol = DEFAULT_RTOL if args.ref_rtol is None else float(args.ref_rtol)
        workers = default_workers() if args.workers is None else int(args.workers)
        res = render_reference(meshes, camera, cube, materials=materials, rtol=rtol, seed=args.seed,
                               workers=workers, progress=progress)
        keep = ("rtol", "err_rel_l1", "err_rel_p99", "converged", "n_rays", "time_s", "sided", "n_back_facing",
                "quadrature", "ray_backend", "lobes")
        res.info["workers"] = workers
        keep = keep + ("workers",)
        return res.image, res.mask, {"reference": {k: res.info[k] for k in keep if k in res.info}}
    from ..rendering.mitsuba_render import render_mitsuba

    if any(m[2] >= 1.0 for m in materials.values()):
        raise IBLError("--mode mitsuba: glossiness must be < 1 (the mirror g = 1 is not a Phong lobe)")
    res = render_mitsuba(meshes, camera, cube, materials=materials, spp=args.spp, seed=args.seed)
    return res.image, res.mask, {"mitsuba": res.info}
