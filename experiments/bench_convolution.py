"""Benchmark of ibl_ref.convolve: ``auto`` vs ``exact`` at 64² (same run) and the 128² targets.

Usage: OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python experiments/bench_convolution.py [--skip-128]
       [--without-s1]

Environment: helper B's sky + 1e5 sun 0.0015 rad from a cube corner (``make_env("sky_sun", ...)``).
Prints, at 64² faces and exponents {1, 4, 16, 64, 256, 1024, 4096}: the time of ``auto`` (rtol 1e-3) and
of ``exact`` measured in the same run, their ratio, and auto's max / mean relative error per exponent
against exact.  Then the 128² targets: one exponent s = 16 (target ≤ 3 s) and the 8 exponents
{1, 2, 5, 10, 20, 50, 100, 1000} (target ≤ 6.4 s; s = 1 and 2 go to the hierarchical moment route
of :mod:`ibl_ref.moment_convolution`, which is also timed alone for s = 1; ``--without-s1`` drops s = 1).  Timings are wall clock on
whatever machine runs this, printed as wall clock and as process CPU time (robust on a shared machine
when BLAS runs single-threaded; state the load when you quote them).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ibl_ref.convolve import convolve
from ibl_ref.experiments.speed_accuracy import environment
from ibl_ref.phong_convolution import convolve_exact_many

S7 = [1.0, 4.0, 16.0, 64.0, 256.0, 1024.0, 4096.0]
S8 = [1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 1000.0]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--skip-128", action="store_true")
    ap.add_argument("--with-s1", action="store_true", help="(default now; kept for compatibility)")
    ap.add_argument("--without-s1", action="store_true", help="drop s = 1 from the 128² eight-exponent target")
    args = ap.parse_args()
    convolve(environment(4), [2.0, 64.0])  # warm-up (imports)

    cube = environment(64)
    t0, c0 = time.perf_counter(), time.process_time()
    res = convolve(cube, S7, method="auto", rtol=1e-3)
    t_auto, c_auto = time.perf_counter() - t0, time.process_time() - c0
    t0, c0 = time.perf_counter(), time.process_time()
    ref = convolve_exact_many(cube, S7)
    t_exact, c_exact = time.perf_counter() - t0, time.process_time() - c0
    print(f"64² faces, {len(S7)} exponents: auto {t_auto:.2f} s wall / {c_auto:.2f} s CPU, exact {t_exact:.2f} s "
          f"wall / {c_exact:.2f} s CPU; exact/auto = {t_exact / t_auto:.2f}x wall, {c_exact / c_auto:.2f}x CPU")
    for k, s in enumerate(S7):
        rel = (np.abs(res.maps[s] - ref[k]) / ref[k]).max(axis=-1)
        print(f"  s={s:g}: {res.method_used[s]:6s} rel err max {rel.max():.2e} mean {rel.mean():.2e} "
              f"(bound max {res.error_bound[s].max():.2e})")
    print(f"  auto stage times: {', '.join(f'{k} {v:.2f} s' for k, v in res.timings_s.items())}")

    if args.skip_128:
        return
    cube = environment(128)
    t0, c0 = time.perf_counter(), time.process_time()
    res = convolve(cube, [16.0], rtol=1e-3)
    t16, c16 = time.perf_counter() - t0, time.process_time() - c0
    print(f"128² faces, s=16: auto {t16:.2f} s wall / {c16:.2f} s CPU (target ≤ 3 s) via {res.method_used[16.0]}, "
          f"bound max {res.error_bound[16.0].max():.1e}")
    t0, c0 = time.perf_counter(), time.process_time()
    res = convolve(cube, [1.0], rtol=1e-3)
    t1, c1 = time.perf_counter() - t0, time.process_time() - c0
    print(f"128² faces, s=1: auto {t1:.2f} s wall / {c1:.2f} s CPU via {res.method_used[1.0]}, "
          f"bound max {res.error_bound[1.0].max():.1e}")
    s8 = S8[1:] if args.without_s1 else S8
    t0, c0 = time.perf_counter(), time.process_time()
    res = convolve(cube, s8, rtol=1e-3)
    t8, c8 = time.perf_counter() - t0, time.process_time() - c0
    print(f"128² faces, exponents {[f'{s:g}' for s in s8]}: auto {t8:.2f} s wall / {c8:.2f} s CPU "
          "(target ≤ 6.4 s for all 8)")
    print("  methods: " + ", ".join(f"{s:g}:{res.method_used[s]}" for s in s8))
    print(f"  stage times: {', '.join(f'{k} {v:.2f} s' for k, v in res.timings_s.items())}")
    print(f"  max bound over exponents: {max(float(b.max()) for b in res.error_bound.values()):.1e}")


if __name__ == "__main__":
    main()
