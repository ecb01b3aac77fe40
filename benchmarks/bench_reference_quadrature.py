"""Benchmark of the converged reference's quadrature implementations: a sweep of the teapot scene over materials ×
environments, each case rendered with the NumPy and the compiled quadrature back to back (same process, same load).

Usage: python benchmarks/bench_reference_quadrature.py [--size 64] [--env-size 32] [--workers 1]
                                                       [--materials diffuse ggx0.1 …] [--envs sky_sun courtyard …]
                                                       [--rtol 2e-3] [--out FILE.csv]

The sweep of issue 40 (teapot on its ground, ``ibl-ref render``'s camera; materials diffuse, GGX 0.1 / 0.3 / 0.6
with F0 = 1, Phong s = 1 / 16 / 256 on the mirror axis; environments ``sky_sun`` and the four probes of
``$IBL_REF_PROBE_DIR`` at ``--env-size`` faces).  Per case: wall and CPU time of each implementation, their ratio,
the share of the NumPy render spent in the quadrature's block sums, the two images' largest relative difference and
the estimated rel. L1 (both must agree: the refinement takes the same decisions).  The last lines give the sweep's
totals and the ratio, and ``uptime`` before and after.  The compiled loops are compiled (or loaded from numba's
cache) before the first case, outside the timings.  Timings depend on the machine and its load; the ratio is the
number to quote.
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import time

MATERIALS = {"diffuse": (1.0, 0.0, 0.0), "ggx0.1": "ggx:roughness=0.1,f0=1", "ggx0.3": "ggx:roughness=0.3,f0=1",
             "ggx0.6": "ggx:roughness=0.6,f0=1", "phong1": (0.0, 1.0, 0.0), "phong16": (0.0, 1.0, 0.9375),
             "phong256": (0.0, 1.0, 0.99609375)}
ENVS = ("sky_sun", "city", "courtyard", "forest", "studio")


def _env(name: str, n: int):
    from ibl_ref.experiments.method_zoo import environment

    return environment(name, n)[0]


def _timed(fn):
    t, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t, time.process_time() - c


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

    from ibl_ref.rendering import reference_quadrature as rq
    from ibl_ref.rendering.reference_render import render_reference
    from ibl_ref.rendering.scenes import default_camera, teapot_on_ground

    warnings.simplefilter("ignore")
    print("uptime before:", subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(), flush=True)
    meshes = teapot_on_ground()
    cam = default_camera(meshes, a.size)
    spent = {"t": 0.0}
    orig = rq.NumpyQuadrature.block_sums

    def counted(self, *args, **kw):  # the NumPy quadrature's share of a render
        t = time.perf_counter()
        try:
            return orig(self, *args, **kw)
        finally:
            spent["t"] += time.perf_counter() - t

    rq.NumpyQuadrature.block_sums = counted
    # compile (or load) the loops outside the timings
    render_reference(meshes, default_camera(meshes, 8), _env("sky_sun", 8), material="ggx:0.3", rtol=2e-2)
    render_reference(meshes, default_camera(meshes, 8), _env("sky_sun", 8), material=(0.0, 1.0, 0.9), rtol=2e-2)
    rows = []
    tot = {"numpy": 0.0, "compiled": 0.0}
    for en in a.envs:
        env = _env(en, a.env_size)
        for mn in a.materials:
            res = {}
            for kernel in ("numpy", "compiled"):
                os.environ["IBL_REF_KERNEL"] = kernel
                spent["t"] = 0.0
                r, wall, cpu = _timed(lambda: render_reference(meshes, cam, env, material=MATERIALS[mn],
                                                               rtol=a.rtol, workers=a.workers))
                res[kernel] = (r, wall, cpu, spent["t"])
                tot[kernel] += wall
            (rn, wn, cn, qn), (rc, wc, cc, _) = res["numpy"], res["compiled"]
            den = np.maximum(np.abs(rn.image), 1e-12 * max(float(np.abs(rn.image).max()), 1e-300))
            row = dict(env=en, material=mn, size_px=a.size, env_face=a.env_size, numpy_wall_s=round(wn, 3),
                       compiled_wall_s=round(wc, 3), numpy_cpu_s=round(cn, 3), compiled_cpu_s=round(cc, 3),
                       speedup=round(wn / wc, 2), numpy_quadrature_share=round(qn / wn, 3),
                       max_rel_image_diff=float(np.max(np.abs(rc.image - rn.image) / den)),
                       est_rel_l1_numpy=round(rn.info["err_rel_l1"], 6),
                       est_rel_l1_compiled=round(rc.info["err_rel_l1"], 6))
            rows.append(row)
            print("  ".join(f"{k}={v}" for k, v in row.items()), flush=True)
    print(f"sweep ({len(rows)} renders, {a.size}² px, {a.env_size}² faces, workers={a.workers}): NumPy "
          f"{tot['numpy']:.1f} s, compiled {tot['compiled']:.1f} s, ratio {tot['numpy'] / tot['compiled']:.2f}×")
    print("uptime after:", subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    if a.out and rows:
        with open(a.out, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


if __name__ == "__main__":
    main()
