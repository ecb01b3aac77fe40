"""Benchmark of the converged reference renderer: time, rays and memory at 128² on 2 cores, on synthetic and real
probes, with Phong and GGX materials.

Usage: python benchmarks/bench_reference.py [--size 128] [--workers 2] [--cases diffuse g0.9 g0.99 probe ggx0.3 …]
                                            [--probe FILE.exr …] [--probe-size 32] [--ray-backend auto|embree|exact]
                                            [--rtol 2e-3] [--env-size 32] [--check-estimate]

Run it under ``/usr/bin/time -v`` for the whole process tree's peak memory ("Maximum resident set size" is the
largest single process: this one or a worker); the script prints this process's and the largest worker's peak.

Scene: the teapot on its ground quad (``ibl-ref render``'s scene and default camera) under ``sky_sun`` (32² faces: a
1e5-bright sun of the real sun's solid angle) — cases ``diffuse`` (kd = 1), ``g0.9`` and ``g0.99`` (ks = 1), object
and ground with the same material; ``probe``: diffuse under a probe-like lat-long sky with a small 3e4 sun
(:func:`ibl_ref.environment.probe_files.sky_sun_latlong`, 256 × 512, turned into 32² cube faces); ``ggx0.1``,
``ggx0.3``, ``ggx0.6``: GGX with that roughness, F0 = 1, under ``sky_sun``; and one case per ``--probe`` file (read
with :func:`ibl_ref.environment.exr_io.load_cube` at ``--probe-size`` faces) with the materials a user gets from
``ibl-ref render`` without options (teapot g = 0.8, ground g = 0.2, pure glossy).  Per case the reference first
prints its predicted cost (from its first block), then one line: wall time, CPU time (this process + the blocks'
processes), the peak resident memory of this process and of the largest worker, rays, cells, levels, the estimated
rel. L1 and 99th percentile, converged, load.  Timings depend on the machine and its load (quote ``uptime``); CPU
times are the fairer comparison.  ``--check-estimate`` also renders each case 10× finer (rtol/10, pixel_rtol/5,
another seed, a cell budget of 8 M per block) and prints the actual rel. L1 and 99th percentile of the default run
against it, next to its estimates.
"""

from __future__ import annotations

import argparse
import os
import resource
import time
from pathlib import Path

SYNTHETIC = {"diffuse": (1.0, 0.0, 0.0), "g0.9": (0.0, 1.0, 0.9), "g0.99": (0.0, 1.0, 0.99),
             "ggx0.1": "ggx:roughness=0.1,f0=1", "ggx0.3": "ggx:roughness=0.3,f0=1", "ggx0.6": "ggx:roughness=0.6,f0=1"}


def _case(name: str, env_size: int, probe_size: int):
    """(environment, {material id: material})"""
    from ibl_ref.synthetic.synthetic_envs import make_env

    if name == "probe":
        from ibl_ref.environment.probe_files import sky_sun_latlong
        from ibl_ref.environment.resample import latlong_to_cube

        img, _ = sky_sun_latlong(256)
        return latlong_to_cube(img, env_size), {0: (1.0, 0.0, 0.0), 1: (1.0, 0.0, 0.0)}
    if name in SYNTHETIC:
        return make_env("sky_sun", n=env_size), {0: SYNTHETIC[name], 1: SYNTHETIC[name]}
    from ibl_ref.environment.exr_io import load_cube

    return load_cube(name, size=probe_size), {0: (0.0, 1.0, 0.8), 1: (0.0, 1.0, 0.2)}  # `ibl-ref render` defaults


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=128, help="image width = height in pixels (default 128)")
    ap.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    ap.add_argument("--cases", nargs="*", default=["diffuse", "g0.9", "g0.99", "probe"],
                    choices=("probe",) + tuple(SYNTHETIC))
    ap.add_argument("--probe", nargs="*", default=[], metavar="FILE",
                    help="real probes (EXR/HDR files) rendered with `ibl-ref render`'s default materials")
    ap.add_argument("--probe-size", type=int, default=32, help="cube face size of --probe files (default 32, the CLI's)")
    ap.add_argument("--ray-backend", default="auto", choices=("auto", "embree", "exact"))
    ap.add_argument("--rtol", type=float, default=2e-3, help="tolerance (default 2e-3, the renderer's default)")
    ap.add_argument("--env-size", type=int, default=32, help="environment face size (default 32, the CLI's)")
    ap.add_argument("--check-estimate", action="store_true", help="compare with a 10x finer run (slow)")
    args = ap.parse_args()

    from ibl_ref.rendering.reference_render import render_reference
    from ibl_ref.rendering.scenes import default_camera, teapot_on_ground

    meshes = teapot_on_ground()
    cam = default_camera(meshes[:1], size=args.size)
    print(f"teapot + ground, {args.size}² px, env {args.env_size}² (probes {args.probe_size}²), rtol {args.rtol:g}, "
          f"workers {args.workers}, rays {args.ray_backend}, load {os.getloadavg()[0]:.1f}", flush=True)
    for name in list(args.cases) + list(args.probe):
        env, mats = _case(name, args.env_size, args.probe_size)
        label = Path(name).stem if name not in SYNTHETIC and name != "probe" else name
        t0, c0 = time.perf_counter(), time.process_time()
        r = render_reference(meshes, cam, env, materials=mats, rtol=args.rtol, workers=args.workers,
                             ray_backend=args.ray_backend, progress=True)
        wall, cpu_main = time.perf_counter() - t0, time.process_time() - c0
        lobes = r.info["lobes"]
        # the blocks' CPU in the workers (the first block of each lobe runs in this process: predicted cost)
        cpu_blocks = sum(lb["block_cpu_s"] - lb.get("pilot_cpu_s", 0.0) for lb in lobes)
        rss_main = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        rss_worker = max(lb["worker_peak_rss_mb"] for lb in lobes)
        print(f"{label:10s} wall {wall:6.1f} s  cpu {cpu_main + (cpu_blocks if args.workers > 1 else 0):6.1f} s  "
              f"rss main {rss_main:5.0f} MB worker {rss_worker:5.0f} MB  rays {r.info['n_rays'] / 1e6:5.1f} M  "
              f"cells {sum(lb['n_cells'] for lb in lobes) / 1e6:5.1f} M (block max "
              f"{max(lb['block_cells_max'] for lb in lobes) / 1e6:.2f} M, at cap "
              f"{sum(lb['blocks_at_cell_cap'] for lb in lobes)})  base {[lb['n_vis_base'] for lb in lobes]} finest "
              f"{[lb['n_vis_finest'] for lb in lobes]} quad {[lb['n_quad'] for lb in lobes]}  "
              f"est {r.info['err_rel_l1']:.2e}  p99 {r.info['err_rel_p99']:.3f}  converged {r.info['converged']}  "
              f"load {os.getloadavg()[0]:.1f}", flush=True)
        for lb in lobes:
            pr = lb.get("predicted")
            if pr:
                print(f"{'':10s} lobe {lb['lobe']} {lb.get('s', lb.get('roughness'))}: predicted {pr['rays'] / 1e6:.1f} M "
                      f"rays, {pr['cpu_s']:.0f} s CPU, {pr['wall_s']:.0f} s wall; actual {lb['n_rays'] / 1e6:.1f} M rays, "
                      f"{lb['block_cpu_s']:.0f} s CPU, {lb['time_s']:.0f} s wall", flush=True)
        if args.check_estimate:
            import numpy as np

            from ibl_ref.rendering.reference_converged import ERR_FLOOR, PIXEL_RTOL_FACTOR

            f = render_reference(meshes, cam, env, materials=mats, rtol=args.rtol / 10,
                                 pixel_rtol=PIXEL_RTOL_FACTOR * args.rtol / 5, seed=1, workers=args.workers,
                                 ray_backend=args.ray_backend, max_cells=8_000_000)
            m = r.mask & (r.image.mean(axis=-1) > 0)
            ya, yb = r.image[m].mean(axis=-1), f.image[m].mean(axis=-1)
            den = np.maximum(ya, ERR_FLOOR * ya.mean())
            print(f"{'':10s} vs 10x finer run: rel. L1 estimated {r.info['err_rel_l1']:.2e} actual "
                  f"{np.abs(ya - yb).sum() / np.abs(yb).sum():.2e} (finer run's estimate {f.info['err_rel_l1']:.1e}, "
                  f"converged {f.info['converged']}); p99 estimated {r.info['err_rel_p99']:.4f} actual "
                  f"{np.percentile(np.abs(ya - yb) / den, 99):.4f}; pixels above their bound "
                  f"{(np.abs(ya - yb) > r.error[m] + 1e-9 * den).mean():.4f}", flush=True)


if __name__ == "__main__":
    main()
