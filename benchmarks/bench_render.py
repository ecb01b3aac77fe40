"""Benchmark of the Eq. 5 renderer (goal: teapot 256², 24 lights, 256² VSMs ≤ 30 s wall on 2 cores).

Usage: python benchmarks/bench_render.py [--size 256] [--vsm 256] [--lights 6 12 24 48 96] [--repeat 2]

Scene: the tessellated teapot (16,256 triangles) under ``sky_sun`` (64² faces), pure glossy g = 0.5, the paper's
method (``ours``: median cut → PEM pyramids → one VSM per light → Eq. 5).  For every light count it prints the
wall-clock time of one frame (rasterisation + shadow maps + blur + lookups + shading; best of ``--repeat``),
the one-off precomputation (median cut + PEM pyramids) separately, and the stage split.  Then the least-squares
line frame_s = intercept + slope · lights with R², and the ratio of the frame time to the rasterisation of the
G-buffer alone measured in the same run (the baseline).  Timings depend on the machine and its load; quote both.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=256, help="image width = height in pixels (default 256)")
    ap.add_argument("--vsm", type=int, default=256, help="shadow-map resolution (default 256)")
    ap.add_argument("--lights", type=int, nargs="+", default=[6, 12, 24, 48, 96], help="light counts")
    ap.add_argument("--env-size", type=int, default=64, help="environment face size (default 64)")
    ap.add_argument("--repeat", type=int, default=2, help="frames per light count; the best is kept")
    args = ap.parse_args()

    from ibl_ref.rendering.ao_modes import render_modes
    from ibl_ref.rendering.scenes import default_camera
    from ibl_ref.experiments.fig7 import STAGES, fit_line
    from ibl_ref.knuth2014.pem import build_pems
    from ibl_ref.rendering.raster import prepare_scene, rasterize
    from ibl_ref.synthetic.synthetic_envs import make_env
    from ibl_ref.synthetic.synthetic_meshes import make_mesh

    env = make_env("sky_sun", n=args.env_size)
    meshes = [(make_mesh("teapot"), 0)]
    cam = default_camera(meshes, size=args.size)
    print(f"teapot ({len(meshes[0][0].faces)} triangles), {args.size}² px, VSM {args.vsm}², env {args.env_size}², "
          f"cpu_count {os.cpu_count()}, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}")
    # warm-up: imports, calibration tables, sampler caches
    render_modes(meshes, cam, env, ("ours",), pems=build_pems(env, n_lights=6), kd=0.0, ks=1.0, g=0.5,
                 vsm_resolution=64)
    t_raster = np.inf
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        gb = rasterize(prepare_scene(meshes, warn=False), cam)
        t_raster = min(t_raster, time.perf_counter() - t0)
    print(f"baseline: G-buffer rasterisation alone {t_raster:.3f} s ({int(gb.mask.sum())} covered pixels)")
    xs, ys = [], []
    for L in args.lights:
        t0 = time.perf_counter()
        pems = build_pems(env, n_lights=L)
        t_pre = time.perf_counter() - t0
        best, split = np.inf, None
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            res = render_modes(meshes, cam, env, ("ours",), pems=pems, kd=0.0, ks=1.0, g=0.5,
                               vsm_resolution=args.vsm)
            wall = time.perf_counter() - t0
            if wall < best:
                best, split = wall, {k: float(res.timings.get(k, 0.0)) for k in STAGES}
        xs.append(len(pems.lights))
        ys.append(best)
        stages = ", ".join(f"{k} {v:.2f}" for k, v in split.items())
        print(f"lights {len(pems.lights):4d}: frame {best:6.2f} s wall ({best / t_raster:6.1f}x raster) "
              f"[{stages}]; precompute (median cut + PEMs) {t_pre:.2f} s")
    fit = fit_line(xs, ys)
    print(f"fit: frame_s = {fit['intercept_s']:.3f} + {fit['slope_s_per_light']:.4f} * lights (R² {fit['r2']:.4f})")
    if 24 in xs:
        t24 = ys[xs.index(24)]
        print(f"target: 24 lights at {args.size}², VSM {args.vsm}²: {t24:.2f} s wall (target ≤ 30 s: "
              f"{'met' if t24 <= 30 else 'missed'})")


if __name__ == "__main__":
    main()
