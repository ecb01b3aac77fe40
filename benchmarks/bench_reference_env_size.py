"""Benchmark of the reference's cost against the environment's size (issue 40, item 3): the teapot scene rendered with
environment faces of 32² to 256² texels, with the quadrature starting at the lobe's level (the default: a level
coarser than the map reads its exact area averages) and at the map's own size (``n_quad_min=N``: every quadrature
texel inside one map texel, the reference before 2026-12-07), side by side in one run.

Usage: python benchmarks/bench_reference_env_size.py [--size 32] [--env courtyard] [--sizes 32 64 128 256]
                                                     [--materials diffuse phong16 ggx0.3] [--out FILE.csv]

Per (material, face size, start): wall and CPU time, the quadrature levels used, the estimated rel. L1, and the two
images' rel. L1 difference (both converged to the default tolerance: within the sum of the two estimates, up to
noise).  The last lines give per material and start the exponent b of time ∝ (6N²)^b fitted over the face sizes
(least squares in log–log), and ``uptime`` before and after.  The compiled loops are loaded before the first case.
"""

from __future__ import annotations

import argparse
import csv
import subprocess
import time

MATERIALS = {"diffuse": (1.0, 0.0, 0.0), "phong16": (0.0, 1.0, 0.9375), "phong256": (0.0, 1.0, 0.99609375),
             "ggx0.1": "ggx:roughness=0.1,f0=1", "ggx0.3": "ggx:roughness=0.3,f0=1", "ggx0.6": "ggx:roughness=0.6,f0=1"}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=32, help="image width = height in pixels (default 32)")
    ap.add_argument("--env", default="courtyard", help="environment (default courtyard; sky_sun needs no probe)")
    ap.add_argument("--sizes", nargs="*", type=int, default=[32, 64, 128, 256], help="face sizes (default 32…256)")
    ap.add_argument("--materials", nargs="*", default=["diffuse", "phong16", "ggx0.3"], choices=tuple(MATERIALS))
    ap.add_argument("--out", default="", help="also write the rows to this CSV")
    a = ap.parse_args()

    import warnings

    import numpy as np

    from ibl_ref.experiments.method_zoo import environment
    from ibl_ref.rendering.reference_render import render_reference
    from ibl_ref.rendering.scenes import default_camera, teapot_on_ground

    warnings.simplefilter("ignore")
    up = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    print("uptime before:", up, flush=True)
    meshes = teapot_on_ground()
    cam = default_camera(meshes, a.size)
    render_reference(meshes, default_camera(meshes, 6), environment("sky_sun", 8)[0], material="ggx:0.3", rtol=2e-2)
    rows = []
    for mn in a.materials:
        for N in a.sizes:
            env, why = environment(a.env, N)
            if env is None:
                raise SystemExit(why)
            res = {}
            for start, nmin in (("lobe", None), ("map", N)):
                t, c = time.perf_counter(), time.process_time()
                r = render_reference(meshes, cam, env, material=MATERIALS[mn], n_quad_min=nmin)
                res[start] = (r, time.perf_counter() - t, time.process_time() - c)
            ya, yb = (res[k][0].image.mean(-1) for k in ("lobe", "map"))
            for start in ("lobe", "map"):
                r, w, c = res[start]
                lb = r.info["lobes"][0]
                row = dict(material=mn, env=a.env, face=N, start=start, size_px=a.size, wall_s=round(w, 3),
                           cpu_s=round(c, 3), n_quad=" ".join(map(str, lb["n_quad"])),
                           n_quad_pair_max=lb["n_quad_pair_max"], est_rel_l1=round(r.info["err_rel_l1"], 6),
                           diff_rel_l1=round(float(np.abs(ya - yb).sum() / max(np.abs(yb).sum(), 1e-300)), 6))
                rows.append(row)
                print("  ".join(f"{k}={v}" for k, v in row.items()), flush=True)
    for mn in a.materials:
        for start in ("lobe", "map"):
            q = [r for r in rows if r["material"] == mn and r["start"] == start]
            if len(q) > 1:
                b = np.polyfit(np.log([6 * r["face"] ** 2 for r in q]), np.log([r["cpu_s"] for r in q]), 1)[0]
                print(f"{mn}, quadrature from the {start}'s level: CPU time ∝ (texels)^{b:.2f} over faces "
                      f"{q[0]['face']}²…{q[-1]['face']}²")
    print("uptime after:", subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    if a.out and rows:
        with open(a.out, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


if __name__ == "__main__":
    main()
