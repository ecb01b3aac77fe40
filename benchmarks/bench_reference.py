"""Benchmark of the converged reference renderer (issue 14: 128² at the default tolerance in about a minute on 2 cores,
memory ≤ 1 GB).

Usage: python benchmarks/bench_reference.py [--size 128] [--workers 2] [--cases diffuse g0.9 g0.99 probe]
                                            [--ray-backend auto|embree|exact] [--rtol 2e-3] [--env-size 32]
                                            [--check-estimate]

Scene: the teapot on its ground quad (``ibl-ref render``'s scene and default camera), object and ground with the
same material, under ``sky_sun`` (32² faces: a 1e5-bright sun of the real sun's solid angle) — cases ``diffuse``
(kd = 1), ``g0.9`` and ``g0.99`` (ks = 1) —, and ``probe``: diffuse under a probe-like lat-long sky with a small
3e4 sun (:func:`ibl_ref.environment.probe_files.sky_sun_latlong`, 256 × 512, turned into 32² cube faces).  One
line per case: wall time, CPU time (this process + the blocks' processes), the peak resident memory of this process
and of the largest worker (the total is about this process + workers × that), rays, cells, levels, the estimated
rel. L1 and 99th percentile, converged.  Timings depend on the machine and its load (quote ``uptime``); CPU times
are the fairer comparison.  ``--check-estimate`` also renders each case 10× finer (rtol/10, pixel_rtol/5, another
seed) and prints the actual rel. L1 and 99th percentile of the default run against it, next to its estimates.
"""

from __future__ import annotations

import argparse
import os
import resource
import time


def _case(name: str, env_size: int):
    from ibl_ref.synthetic.synthetic_envs import make_env

    if name == "probe":
        from ibl_ref.environment.probe_files import sky_sun_latlong
        from ibl_ref.environment.resample import latlong_to_cube

        img, _ = sky_sun_latlong(256)
        return latlong_to_cube(img, env_size), (1.0, 0.0, 0.0)
    mats = {"diffuse": (1.0, 0.0, 0.0), "g0.9": (0.0, 1.0, 0.9), "g0.99": (0.0, 1.0, 0.99)}
    return make_env("sky_sun", n=env_size), mats[name]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=128, help="image width = height in pixels (default 128)")
    ap.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    ap.add_argument("--cases", nargs="+", default=["diffuse", "g0.9", "g0.99", "probe"],
                    choices=("diffuse", "g0.9", "g0.99", "probe"))
    ap.add_argument("--ray-backend", default="auto", choices=("auto", "embree", "exact"))
    ap.add_argument("--rtol", type=float, default=2e-3, help="tolerance (default 2e-3, the renderer's default)")
    ap.add_argument("--env-size", type=int, default=32, help="environment face size (default 32, the CLI's)")
    ap.add_argument("--check-estimate", action="store_true", help="compare with a 10x finer run (slow)")
    args = ap.parse_args()

    from ibl_ref.rendering.reference_render import render_reference
    from ibl_ref.rendering.scenes import default_camera, teapot_on_ground

    meshes = teapot_on_ground()
    cam = default_camera(meshes[:1], size=args.size)
    print(f"teapot + ground, {args.size}² px, env {args.env_size}², rtol {args.rtol:g}, workers {args.workers}, "
          f"rays {args.ray_backend}, load {os.getloadavg()[0]:.1f}")
    for name in args.cases:
        env, (kd, ks, g) = _case(name, args.env_size)
        t0, c0 = time.perf_counter(), time.process_time()
        r = render_reference(meshes, cam, env, materials={0: (kd, ks, g), 1: (kd, ks, g)}, rtol=args.rtol,
                             workers=args.workers, ray_backend=args.ray_backend)
        wall, cpu_main = time.perf_counter() - t0, time.process_time() - c0
        lobes = r.info["lobes"]
        cpu_blocks = sum(lb["block_cpu_s"] for lb in lobes)
        rss_main = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        rss_worker = max(lb["worker_peak_rss_mb"] for lb in lobes)
        print(f"{name:8s} wall {wall:6.1f} s  cpu {cpu_main + (cpu_blocks if args.workers > 1 else 0):6.1f} s  "
              f"rss main {rss_main:5.0f} MB worker {rss_worker:5.0f} MB  rays {r.info['n_rays'] / 1e6:5.1f} M  "
              f"cells {sum(lb['n_cells'] for lb in lobes) / 1e6:5.1f} M  base {lobes[0]['n_vis_base']} finest "
              f"{lobes[0]['n_vis_finest']} quad {lobes[0]['n_quad']}  est {r.info['err_rel_l1']:.2e}  "
              f"p99 {r.info['err_rel_p99']:.3f}  converged {r.info['converged']}  load {os.getloadavg()[0]:.1f}")
        if args.check_estimate:
            import numpy as np

            from ibl_ref.rendering.reference_converged import ERR_FLOOR, PIXEL_RTOL_FACTOR

            f = render_reference(meshes, cam, env, materials={0: (kd, ks, g), 1: (kd, ks, g)}, rtol=args.rtol / 10,
                                 pixel_rtol=PIXEL_RTOL_FACTOR * args.rtol / 5, seed=1, workers=args.workers,
                                 ray_backend=args.ray_backend)
            m = r.mask & (r.image.mean(axis=-1) > 0)
            ya, yb = r.image[m].mean(axis=-1), f.image[m].mean(axis=-1)
            den = np.maximum(ya, ERR_FLOOR * ya.mean())
            print(f"{'':8s} vs 10x finer run: rel. L1 estimated {r.info['err_rel_l1']:.2e} actual "
                  f"{np.abs(ya - yb).sum() / np.abs(yb).sum():.2e} (finer run's estimate {f.info['err_rel_l1']:.1e}); "
                  f"p99 estimated {r.info['err_rel_p99']:.4f} actual {np.percentile(np.abs(ya - yb) / den, 99):.4f}; "
                  f"pixels above their bound {(np.abs(ya - yb) > r.error[m] + 1e-9 * den).mean():.4f}")


if __name__ == "__main__":
    main()
