"""Benchmark of a reference sweep (issue 40): the teapot scene over materials × environments, rendered three ways in
one run — the baseline (NumPy quadrature, one render per environment: the reference before the compiled quadrature
and the sweep), the compiled quadrature with one render per environment, and the compiled quadrature with one
render per material for all the environments at once (``render_reference`` with a list of maps).

Usage: python benchmarks/bench_reference_quadrature.py [--size 64] [--env-size 32] [--workers 1]
                                                       [--materials diffuse ggx0.1 …] [--envs sky_sun city …]
                                                       [--rtol 2e-3] [--out FILE.csv]

Materials: diffuse, GGX 0.1 / 0.3 / 0.6 with F0 = 1, Phong s = 1 / 16 / 256 on the mirror axis (issue 40's seven);
environments ``sky_sun`` and the four probes of ``$IBL_REF_PROBE_DIR`` at ``--env-size`` faces.  Per material: the
wall and CPU time of each way, and per environment the estimated rel. L1 of the sweep and of the baseline and their
images' rel. L1 difference (both are converged references of the same image: the difference stays within the sum
of the two estimates, up to noise).  The last lines give the totals, the ratios to the baseline, and ``uptime``
before and after.  The compiled loops are compiled (or loaded from numba's cache) before the first case, outside
the timings.  Timings depend on the machine and its load; the ratios are the numbers to quote.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

MATERIALS = {"diffuse": (1.0, 0.0, 0.0), "ggx0.1": "ggx:roughness=0.1,f0=1", "ggx0.3": "ggx:roughness=0.3,f0=1",
             "ggx0.6": "ggx:roughness=0.6,f0=1", "phong1": (0.0, 1.0, 0.0), "phong16": (0.0, 1.0, 0.9375),
             "phong256": (0.0, 1.0, 0.99609375)}
ENVS = ("sky_sun", "city", "courtyard", "forest", "studio")
WAYS = ("numpy_single", "compiled_single", "compiled_sweep")


def _env(name: str, n: int):
    from ibl_ref.experiments.method_zoo import environment

    cube, why = environment(name, n)
    if cube is None:
        raise SystemExit(why)
    return cube


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=64, help="image width = height in pixels (default 64)")
    ap.add_argument("--env-size", type=int, default=32, help="environment face size (default 32)")
    ap.add_argument("--workers", type=int, default=1, help="worker processes per render (default 1)")
    ap.add_argument("--materials", nargs="*", default=list(MATERIALS), choices=tuple(MATERIALS))
    ap.add_argument("--envs", nargs="*", default=list(ENVS), help=f"environments (default: {' '.join(ENVS)})")
    ap.add_argument("--rtol", type=float, default=2e-3, help="the reference's tolerance (default 2e-3)")
    ap.add_argument("--out", default="", help="also write the rows to this CSV")
    a = ap.parse_args()

    import warnings

    import numpy as np

    from ibl_ref.rendering.reference_render import render_reference
    from ibl_ref.rendering.scenes import default_camera, teapot_on_ground

    warnings.simplefilter("ignore")
    load_before = _uptime()
    print("uptime before:", load_before, flush=True)
    meshes = teapot_on_ground()
    cam = default_camera(meshes, a.size)
    envs = [_env(e, a.env_size) for e in a.envs]
    os.environ["IBL_REF_KERNEL"] = "compiled"  # compile (or load) the loops outside the timings
    for m in ("ggx:0.3", (0.0, 1.0, 0.9)):
        render_reference(meshes, default_camera(meshes, 8), [_env("sky_sun", 8)] * 2, material=m, rtol=2e-2)

    def timed(kernel, cube, mat):
        os.environ["IBL_REF_KERNEL"] = kernel
        t, c = time.perf_counter(), time.process_time()
        r = render_reference(meshes, cam, cube, material=mat, rtol=a.rtol, workers=a.workers)
        return r, time.perf_counter() - t, time.process_time() - c

    rows = []
    tot = dict.fromkeys(WAYS, 0.0)
    for mn in a.materials:
        mat = MATERIALS[mn]
        wall, cpu, res = dict.fromkeys(WAYS, 0.0), dict.fromkeys(WAYS, 0.0), {}
        for way, kernel in (("numpy_single", "numpy"), ("compiled_single", "compiled")):
            res[way] = []
            for cube in envs:
                r, w, c = timed(kernel, cube, mat)
                res[way].append(r)
                wall[way] += w
                cpu[way] += c
        res["compiled_sweep"], wall["compiled_sweep"], cpu["compiled_sweep"] = timed("compiled", envs, mat)
        for w in WAYS:
            tot[w] += wall[w]
        for en, base, sw in zip(a.envs, res["numpy_single"], res["compiled_sweep"]):
            yb, ys = base.image.mean(-1), sw.image.mean(-1)
            row = dict(material=mn, env=en, size_px=a.size, env_face=a.env_size, workers=a.workers,
                       **{f"{w}_wall_s": round(wall[w], 3) for w in WAYS},
                       **{f"{w}_cpu_s": round(cpu[w], 3) for w in WAYS},
                       est_rel_l1_baseline=round(base.info["err_rel_l1"], 6),
                       est_rel_l1_sweep=round(sw.info["err_rel_l1"], 6),
                       diff_rel_l1=round(float(np.abs(ys - yb).sum() / max(np.abs(yb).sum(), 1e-300)), 6),
                       sweep_converged=bool(sw.info["converged"]))
            rows.append(row)
        print(f"{mn}: " + ", ".join(f"{w} {wall[w]:.1f} s wall / {cpu[w]:.1f} s CPU" for w in WAYS)
              + f"; ratio to baseline: {wall['numpy_single'] / wall['compiled_single']:.2f}x (compiled), "
              f"{wall['numpy_single'] / wall['compiled_sweep']:.2f}x (compiled sweep); per env est sweep / baseline "
              f"/ diff: " + "; ".join(f"{q['env']} {q['est_rel_l1_sweep']:.1e}/{q['est_rel_l1_baseline']:.1e}/"
                                      f"{q['diff_rel_l1']:.1e}" for q in rows[-len(envs):]), flush=True)
    n = len(a.materials) * len(envs)
    print(f"sweep of {n} images ({len(a.materials)} materials x {len(envs)} environments, {a.size}² px, "
          f"{a.env_size}² faces, workers={a.workers}): baseline {tot['numpy_single']:.1f} s, compiled "
          f"{tot['compiled_single']:.1f} s ({tot['numpy_single'] / tot['compiled_single']:.2f}x), compiled sweep "
          f"{tot['compiled_sweep']:.1f} s ({tot['numpy_single'] / tot['compiled_sweep']:.2f}x)")
    print("uptime after:", _uptime())
    if a.out and rows:
        from ibl_ref.atomic import write_csv

        write_csv(a.out, rows, comment=f"bench_reference_quadrature.py {' '.join(sys.argv[1:])}; load before: "
                  f"{load_before}; after: {_uptime()}")


if __name__ == "__main__":
    main()
