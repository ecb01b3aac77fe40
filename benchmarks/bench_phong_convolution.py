"""Benchmark of ibl_ref.groundtruth.phong_convolution: exact gather timings and sparse speed-up / accuracy.

Usage: OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python benchmarks/bench_phong_convolution.py [--sizes 32,64]
       [--sparse-size 64] [--big 0]
Environment: smooth sky + noise + a 1e5 sun texel near a cube corner (seeded).  Ratios are against the
exact (dense) gather measured in the same run.  Times are CPU seconds of this process
(time.process_time, robust when the machine is shared) with wall seconds in brackets.
"""

from __future__ import annotations

import argparse
import time


class _Clock:
    def __enter__(self):
        self.c0, self.w0 = time.process_time(), time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.cpu = time.process_time() - self.c0
        self.wall = time.perf_counter() - self.w0

    def __str__(self):
        return f"{self.cpu:.2f} s CPU [{self.wall:.1f} s wall]"

import numpy as np

from ibl_ref.environment import envmap
from ibl_ref.groundtruth.phong_convolution import convolve_exact, convolve_exact_many, convolve_sparse_many

EIGHT = [1.0, 4.0, 16.0, 64.0, 256.0, 1024.0, 4096.0, 16384.0]


def sky_sun(n, sun=1e5, seed=7):
    rng = np.random.default_rng(seed)
    d = envmap.texel_directions(n)
    cube = 0.5 + 0.4 * np.clip(d[..., 1:2], 0, None) * np.array([0.6, 0.8, 1.0]) + 0.1 * rng.random((6, n, n, 3))
    corner = np.array([1.0, 1.0, 1.0]) / np.sqrt(3) + np.array([0.02, 0.0, -0.01])
    f, r, c = envmap.direction_to_texel(corner, n)
    cube[f, r, c] = sun
    return cube


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="32,64")
    ap.add_argument("--sparse-size", type=int, default=64)
    ap.add_argument("--big", type=int, default=0, help="also time one exponent at this face size (e.g. 128)")
    args = ap.parse_args()
    for n in [int(x) for x in args.sizes.split(",") if x]:
        cube = sky_sun(n)
        with _Clock() as c1:
            convolve_exact(cube, 16.0)
        with _Clock() as c8:
            convolve_exact_many(cube, EIGHT)
        print(f"exact N={n}: s=16 {c1}; 8 exponents at once {c8} ({c8.cpu / c1.cpu:.2f}x one)", flush=True)
    if args.big:
        cube = sky_sun(args.big)
        with _Clock() as cb:
            convolve_exact(cube, 16.0)
        print(f"exact N={args.big}: s=16 {cb}", flush=True)
    n = args.sparse_size
    if n:
        cube = sky_sun(n)
        exps = [16.0, 256.0, 4096.0]
        with _Clock() as ce:
            ex = convolve_exact_many(cube, exps)
        print(f"exact N={n}, 3 exponents at once: {ce}", flush=True)
        for k, s in enumerate(exps):
            with _Clock() as c1:
                convolve_exact(cube, s)
            with _Clock() as cs:
                m, b, info = convolve_sparse_many(cube, [s], rtol=1e-3, return_info=True)
            err = np.abs(m[0] - ex[k])
            print(
                f"sparse N={n} s={s:g}: {cs} vs exact {c1} → speed-up {c1.cpu / cs.cpu:.1f}x (CPU); "
                f"max rel err {float((err / ex[k]).max()):.2e}; max rel bound {float((b[0] / m[0]).max()):.2e}; "
                f"bound holds {bool(np.all(err <= b[0]))}; max bound / max err {float(b[0].max() / max(err.max(), 1e-300)):.3g}; max err/bound {float((err / b[0]).max()):.3g}; "
                f"theta_c {info[0].theta_c:.3f} rad; gathered {info[0].gathered_fraction:.4f}; bright {info[0].n_bright}",
                flush=True,
            )


if __name__ == "__main__":
    main()
