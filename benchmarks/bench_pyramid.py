"""Benchmark: sqrtcos filter pyramid vs a plain 2×2-mean MIP chain (Knuth et al. 2014, Fig. 2).

Builds both for a 6×N² RGB float32 map (default N = 512) in the same run, best of ``--repeat`` runs
each, and prints the ratio (target: ≤ 3).  Also times the other kernels, both orders and seam modes.

    OMP_NUM_THREADS=1 python benchmarks/bench_pyramid.py [--size 512] [--repeat 5]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ibl_ref.knuth2014.pyramid import build_mip_chain, build_pyramid


def best_time(fn, repeat):
    fn()  # warm-up: padding tables are cached per face size
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return min(ts)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--repeat", type=int, default=5)
    a = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    cube = rng.random((6, a.size, a.size, 3)).astype(np.float32)
    t_mip = best_time(lambda: build_mip_chain(cube), a.repeat)
    print(f"face size {a.size}, RGB float32, best of {a.repeat}")
    print(f"plain 2x2-mean MIP chain            : {t_mip * 1e3:8.1f} ms (baseline)")
    for kernel in ("sqrtcos", "box", "gauss", "cos"):
        for order in ("shrink_then_filter", "filter_then_shrink"):
            for seam in ("neighbour", "clamp"):
                if kernel != "sqrtcos" and (order != "shrink_then_filter" or seam != "neighbour"):
                    continue
                t = best_time(lambda: build_pyramid(cube, kernel, order, seam), a.repeat)
                print(f"{kernel:8s} {order:19s} {seam:9s}: {t * 1e3:8.1f} ms  ratio {t / t_mip:5.2f}")
    # final ratio from interleaved runs (the machine is shared: interleaving cancels load drifts)
    tm, tp = [], []
    for _ in range(a.repeat):
        tm.append(best_time(lambda: build_mip_chain(cube), 1))
        tp.append(best_time(lambda: build_pyramid(cube, "sqrtcos"), 1))
    print(f"interleaved: MIP {min(tm) * 1e3:.1f} ms, sqrtcos {min(tp) * 1e3:.1f} ms")
    print(f"RATIO sqrtcos (default) / plain MIP = {min(tp) / min(tm):.2f}  (target <= 3)")


if __name__ == "__main__":
    main()
