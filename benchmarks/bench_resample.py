"""Accuracy (and time) of ibl_ref.environment.resample: round trips and ∫L dω conservation at 3 resolutions.

Run:  OMP_NUM_THREADS=1 python benchmarks/bench_resample.py

Inputs are *texel area averages* of a smooth positive function f (computed by brute-force midpoint
quadrature on an 8x finer grid), so that a perfect resampler would reproduce them; lat-long maps are
H x 2H, cube maps have faces N = H/2 (same texel count around the equator).
"""

from __future__ import annotations

import time

import numpy as np

from ibl_ref.environment import envmap
from ibl_ref.environment import resample as R

S = 8


def f_smooth(d):
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.stack([1 + 0.5 * x + 0.3 * y * z, np.exp(2 * (0.6 * x + 0.8 * y)), 2 + np.sin(3 * x) * np.cos(2 * z)], -1)


def latlong_average(h):
    d = envmap.latlong_directions(h * S, 2 * h * S)
    w = envmap.latlong_solid_angles(h * S, 2 * h * S)[:, 0]
    v = (f_smooth(d) * w[:, None, None]).reshape(h, S, 2 * h, S, 3).sum(axis=(1, 3))
    return v / (w.reshape(h, S).sum(1) * S)[:, None, None]


def cube_average(n):
    d = envmap.texel_directions(n * S)
    w = envmap.texel_solid_angles(n * S)
    v = (f_smooth(d) * w[None, :, :, None]).reshape(6, n, S, n, S, 3).sum(axis=(2, 4))
    return v / w.reshape(n, S, n, S).sum(axis=(1, 3))[None, :, :, None]


def stats(out, ref):
    e = np.abs(out - ref)
    r = e / ref
    return e.max(), e.mean(), r.max(), r.mean()


def main():
    for method in ("conservative", "gather"):
        kw = dict(method=method)
        rng = np.random.default_rng(0)
        print(f"\n=== method={method} ===")
        print("round trips on texel averages of a smooth f (values 0.1 .. 7.4); time includes kernel build")
        print(f"{'H':>4} {'N':>4} {'route':24s} {'abs_max':>10} {'abs_mean':>10} {'rel_max':>10} {'rel_mean':>10} {'time_s':>7}")
        for h in (16, 32, 64):
            n = h // 2
            ll, cube = latlong_average(h), cube_average(n)
            R._KERNELS.clear()
            t0 = time.perf_counter()
            a = R.cube_to_latlong(R.latlong_to_cube(ll, n, **kw), h, **kw)
            t1 = time.perf_counter()
            b = R.latlong_to_cube(R.cube_to_latlong(cube, h, **kw), n, **kw)
            t2 = time.perf_counter()
            for name, out, ref, t in (("latlong->cube->latlong", a, ll, t1 - t0), ("cube->latlong->cube", b, cube, t2 - t1)):
                print(f"{h:4d} {n:4d} {name:24s} " + " ".join(f"{v:10.3e}" for v in stats(out, ref)) + f" {t:7.3f}")
        print("∫L dω conservation: max over channels of |∫out/∫in - 1|; single texel: max over 40 random texels")
        print(f"{'H':>4} {'N':>4} {'smooth ll->cube':>16} {'smooth cube->ll':>16} {'noise ll->cube':>16} "
              f"{'noise cube->ll':>16} {'1texel ll->cube':>16} {'1texel cube->ll':>16}")
        for h in (16, 32, 64):
            n = h // 2
            ll, cube = latlong_average(h), cube_average(n)
            nl, nc = rng.uniform(0, 1, (h, 2 * h, 3)), rng.uniform(0, 1, (6, n, n, 3))
            res = [
                R.integral_cube(R.latlong_to_cube(ll, n, **kw)) / R.integral_latlong(ll) - 1,
                R.integral_latlong(R.cube_to_latlong(cube, h, **kw)) / R.integral_cube(cube) - 1,
                R.integral_cube(R.latlong_to_cube(nl, n, **kw)) / R.integral_latlong(nl) - 1,
                R.integral_latlong(R.cube_to_latlong(nc, h, **kw)) / R.integral_cube(nc) - 1,
            ]
            one_ll, one_c = [], []
            for _ in range(40):
                x = np.zeros((h, 2 * h))
                x[rng.integers(0, h), rng.integers(0, 2 * h)] = 1.0
                one_ll.append(R.integral_cube(R.latlong_to_cube(x, n, **kw)) / R.integral_latlong(x) - 1)
                y = np.zeros((6, n, n))
                y[rng.integers(0, 6), rng.integers(0, n), rng.integers(0, n)] = 1.0
                one_c.append(R.integral_latlong(R.cube_to_latlong(y, h, **kw)) / R.integral_cube(y) - 1)
            res += [np.array(one_ll), np.array(one_c)]
            print(f"{h:4d} {n:4d} " + " ".join(f"{np.abs(r).max():16.3e}" for r in res))


if __name__ == "__main__":
    main()
