"""Benchmark of one image at equal error (issue 40): the converged reference renderer against Mitsuba 3
(``llvm_ad_rgb``, the lab's BSDFs, the same scene, rays and radiance) at the sample count that gives the same rel.
L1 error, side by side in one run.

Usage: python benchmarks/bench_equal_error.py [--size 128] [--env-size 32] [--env sky_sun]
                                              [--materials ggx0.1 ggx0.3 ggx0.6 g0.9] [--rtol 2e-3]
                                              [--workers 2] [--pilot-spp 256] [--match actual|estimate]
                                              [--truth-dir DIR] [--out FILE.csv]

The scene is ``cross-validate``'s teapot on its ground quad (``ibl_ref.experiments.cross_validate``), the view its
default camera at ``--size``² pixels, the environment ``--env`` at ``--env-size``² faces; the materials are those of
``cross-validate`` (GGX with F0 = 1 and height-correlated Smith; ``g0.9`` the Phong lobe s = 10).  Per material:

1. the reference (``render_reference``, compiled quadrature, ``--workers`` processes, tolerance ``--rtol``): wall
   time and its estimated rel. L1 error (``info["err_rel_l1"]``, an estimate the tests show to be conservative:
   docs/results/reference-renderer.md), and its **actual** rel. L1 error ``e``: Σ|image − fine| / Σ|fine| over the
   pixels and channels both cover, ``fine`` the same image 10× finer (``rtol/10``, ``pixel_rtol`` / 5, another seed,
   untimed; kept in ``--truth-dir`` if given, reused when its key matches), so ``e`` is known to ± the finer run's
   own estimate, printed beside it.  ``--match estimate`` matches Mitsuba to the estimate instead (no finer run:
   the conservative comparison, which charges the reference its estimate's overstatement, about 2×);
2. a Mitsuba pilot at ``--pilot-spp`` samples per pixel: its noise ``n₀`` (``info["noise_rel_l1"]``: Σ|a − b|/2 /
   Σ|mean| of two independent halves); Monte Carlo noise falls as 1/√spp, so the sample count of equal error is
   about ``N = pilot·(n₀/e)²`` (rounded up to an even number);
3. Mitsuba at N samples, N corrected on the noise it measures (by the slope of log noise against log spp between
   the last two renders: Mitsuba's sampler can beat 1/√spp) until that noise is within ``NOISE_MATCH`` (15 %) of
   ``e`` (at most ``MAX_TRIES`` renders), then one more render at that N with a new seed, timed: the whole call
   (scene set-up, the kernels then in Dr.Jit's cache, the render); its measured noise and its rel. L1 to the
   reference (which holds both errors).

The last lines give, per material and in total, the ratio reference time / Mitsuba time at equal error (> 1: the
reference is slower), and ``uptime`` before and after.  Mitsuba runs on the machine's cores (Dr.Jit's default,
the 2 cores of the reference machine), the reference on ``--workers`` processes.  Timings depend on the machine
and its load; the ratios are the numbers to quote.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
import zipfile
from pathlib import Path

MATERIALS = ("ggx0.1", "ggx0.3", "ggx0.6", "g0.9", "g0.99", "diffuse")
#: Mitsuba's measured noise counts as equal to the reference's error within this share
NOISE_MATCH = 0.15
#: Mitsuba renders at most, the pilot not counted
MAX_TRIES = 4


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def equal_error_spp(pilot_spp: int, pilot_noise: float, target: float) -> int:
    """Samples per pixel at which Monte Carlo noise ∝ 1/√spp falls from ``pilot_noise`` to ``target`` (even, ≥ 2)."""
    n = pilot_spp * (pilot_noise / target) ** 2
    return max(2, 2 * math.ceil(n / 2))


def _finer_run(a, name, meshes, cam, env, material):
    """The case 10× finer (rtol/10, pixel_rtol/5, seed 1), from ``--truth-dir`` when a kept run's key matches, else
    rendered (and kept there, atomically).  Returns ({"image", "mask"}, the finer run's estimated rel. L1)."""
    import json

    import numpy as np

    from ibl_ref.atomic import atomic_write
    from ibl_ref.rendering.reference_converged import PIXEL_RTOL_FACTOR
    from ibl_ref.rendering.reference_render import render_reference

    rtol, pixel_rtol = a.rtol / 10, PIXEL_RTOL_FACTOR * a.rtol / 5
    key = dict(scene="teapot", material=name, size_px=a.size, env=a.env, env_face=a.env_size, rtol=rtol,
               pixel_rtol=pixel_rtol, seed=1)
    path = Path(a.truth_dir) / f"finer_{name}_{a.size}px_{a.env}{a.env_size}.npz" if a.truth_dir else None
    if path is not None and path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                if json.loads(str(z["key"])) == key and z["image"].shape == (a.size, a.size, 3):
                    return {"image": z["image"], "mask": z["mask"]}, float(z["est_rel_l1"])
            why = "another case's finer run"
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:  # damaged or not a kept run
            why = f"not a readable finer run ({type(exc).__name__})"
        print(f"{path}: {why}; rendering it again", flush=True)
    t0 = time.perf_counter()
    f = render_reference(meshes, cam, env, material=material, rtol=rtol, pixel_rtol=pixel_rtol, seed=1,
                         workers=a.workers, max_cells=8_000_000)
    print(f"{name}: 10x finer run {time.perf_counter() - t0:.1f} s (untimed), est. rel. L1 "
          f"{f.info['err_rel_l1']:.1e}, converged {f.info['converged']}", flush=True)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path, "wb") as fh:
            np.savez(fh, image=f.image, mask=f.mask, est_rel_l1=float(f.info["err_rel_l1"]), key=json.dumps(key))
    return {"image": f.image, "mask": f.mask}, float(f.info["err_rel_l1"])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=128, help="image width = height in pixels (default 128)")
    ap.add_argument("--env-size", type=int, default=32, help="environment face size (default 32)")
    ap.add_argument("--env", default="sky_sun", help="synthetic environment (default sky_sun)")
    ap.add_argument("--materials", nargs="*", default=["ggx0.1", "ggx0.3", "ggx0.6", "g0.9"], choices=MATERIALS)
    ap.add_argument("--rtol", type=float, default=2e-3, help="the reference's tolerance (default 2e-3)")
    ap.add_argument("--workers", type=int, default=2, help="reference worker processes (default 2)")
    ap.add_argument("--pilot-spp", type=int, default=256, help="Mitsuba's pilot samples per pixel (default 256)")
    ap.add_argument("--match", choices=("actual", "estimate"), default="actual",
                    help="match Mitsuba's noise to the reference's actual error, measured against a 10x finer run "
                         "(default), or to its estimate (conservative, no finer run)")
    ap.add_argument("--truth-dir", default="", help="keep the 10x finer runs here and reuse them (npz per case)")
    ap.add_argument("--out", default="", help="also write the rows to this CSV")
    a = ap.parse_args()

    import warnings

    import numpy as np

    from ibl_ref.experiments.cross_validate import ENVMAP_PX_PER_TEXEL, MATERIALS as CV_MATERIALS, scene_meshes
    from ibl_ref.rendering.mitsuba_render import render_mitsuba
    from ibl_ref.rendering.reference_render import render_reference
    from ibl_ref.rendering.scenes import default_camera
    from ibl_ref.synthetic.synthetic_envs import scene_environment

    warnings.simplefilter("ignore")
    print("uptime before:", _uptime(), flush=True)
    mesh, meshes = scene_meshes("teapot")
    cam = default_camera([(mesh, 0)], size=a.size)
    env = scene_environment(a.env, a.env_size)
    os.environ["IBL_REF_KERNEL"] = "compiled"
    # compile (or load) the reference's loops and Mitsuba's kernels outside the timings
    small = default_camera([(mesh, 0)], size=8)
    for m in ("ggx:0.3", (0.0, 1.0, 0.9)):
        render_reference(meshes, small, env, material=m, rtol=2e-2)
        render_mitsuba(meshes, small, env, material=m, spp=4)

    rows = []
    for name in a.materials:
        spec = CV_MATERIALS[name]
        material = f"{spec},smith=height_correlated" if isinstance(spec, str) else spec
        H = max(1024, ENVMAP_PX_PER_TEXEL.get(name, 0) * a.env_size)
        t0 = time.perf_counter()
        ref = render_reference(meshes, cam, env, material=material, rtol=a.rtol, workers=a.workers)
        t_ref = time.perf_counter() - t0
        e_est = float(ref.info["err_rel_l1"])
        e, e_fine = e_est, float("nan")
        if a.match == "actual":
            fine, e_fine = _finer_run(a, name, meshes, cam, env, material)
            both = ref.mask & fine["mask"]
            e = float(np.abs(ref.image[both] - fine["image"][both]).sum() / np.abs(fine["image"][both]).sum())
        pilot = render_mitsuba(meshes, cam, env, material=material, spp=a.pilot_spp, seed=1, envmap_height=H)
        n0 = float(pilot.info["noise_rel_l1"])
        # N from the 1/√spp law, then by the slope of log noise against log spp measured between the last two renders
        # (clamped to [1/2, 3/2]: Mitsuba's sampler can beat 1/√spp on smooth pixels) until the noise is within
        # NOISE_MATCH of e; the timed render is one more at that N with a new seed, its kernels then in Dr.Jit's cache
        N, tries, hist = equal_error_spp(a.pilot_spp, n0, e), [], [(a.pilot_spp, n0)]
        for k in range(MAX_TRIES):
            t0 = time.perf_counter()
            mi = render_mitsuba(meshes, cam, env, material=material, spp=N, seed=3 + 2 * k, envmap_height=H)
            t_cold = time.perf_counter() - t0
            n = float(mi.info["noise_rel_l1"])
            tries.append(f"{N} spp: {n:.2e} in {t_cold:.1f} s")
            if abs(n / e - 1.0) <= NOISE_MATCH:
                break
            (N0, m0), (N1, m1) = hist[-1], (N, n)
            hist.append((N, n))
            b = math.log(m0 / m1) / math.log(N1 / N0) if N1 != N0 and m0 > 0 and m1 > 0 else 0.5
            b = min(max(b, 0.5), 1.5)
            N = max(2, 2 * math.ceil(N1 * (n / e) ** (1.0 / b) / 2))
        if not tries[-1].startswith(f"{N} spp"):  # a new N: its kernels into Dr.Jit's cache first
            render_mitsuba(meshes, cam, env, material=material, spp=N, seed=99, envmap_height=H)
        t0 = time.perf_counter()
        mi = render_mitsuba(meshes, cam, env, material=material, spp=N, seed=101, envmap_height=H)
        t_mi = time.perf_counter() - t0
        n = float(mi.info["noise_rel_l1"])
        m = ref.mask & mi.mask
        diff = float(np.abs(ref.image[m] - mi.image[m]).sum() / np.abs(mi.image[m]).sum())
        row = dict(material=name, size_px=a.size, env=a.env, env_face=a.env_size, ref_workers=a.workers,
                   ref_wall_s=round(t_ref, 2), ref_est_rel_l1=round(e_est, 6), matched_to=a.match,
                   ref_actual_rel_l1=round(e, 6) if a.match == "actual" else "",
                   finer_run_est_rel_l1=round(e_fine, 6) if a.match == "actual" else "",
                   ref_converged=bool(ref.info["converged"]),
                   pilot_spp=a.pilot_spp, pilot_noise_rel_l1=round(n0, 6), mitsuba_spp=N,
                   mitsuba_wall_s=round(t_mi, 2), mitsuba_noise_rel_l1=round(n, 6), mitsuba_tries=len(tries),
                   ref_vs_mitsuba_rel_l1=round(diff, 6), ratio_ref_to_mitsuba=round(t_ref / t_mi, 3))
        rows.append(row)
        actual = f" (actual {e:.2e} ± {e_fine:.1e} against the 10x finer run)" if a.match == "actual" else ""
        print(f"{name}: reference {t_ref:.1f} s at est. rel. L1 {e_est:.2e}{actual}; Mitsuba {N} spp (pilot {a.pilot_spp} spp: "
              f"noise {n0:.2e}; tries {'; '.join(tries)}) {t_mi:.1f} s at noise {n:.2e}; the two differ by "
              f"{diff:.2e}; reference / Mitsuba time {t_ref / t_mi:.2f}x", flush=True)
    t_ref = sum(r["ref_wall_s"] for r in rows)
    t_mi = sum(r["mitsuba_wall_s"] for r in rows)
    print(f"equal error, {len(rows)} images ({a.size}² px, teapot, {a.env} at {a.env_size}² faces): reference "
          f"{t_ref:.1f} s, Mitsuba {t_mi:.1f} s: reference / Mitsuba {t_ref / t_mi:.2f}x")
    print("uptime after:", _uptime())
    if a.out and rows:
        from ibl_ref.atomic import write_csv

        write_csv(a.out, rows, comment=f"bench_equal_error.py {' '.join(sys.argv[1:])}; load: {_uptime()}")


if __name__ == "__main__":
    main()
