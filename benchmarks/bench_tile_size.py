"""Tile width of the compiled sparse gather: measured cost of every width against the cost model's choice.

Usage::

    python benchmarks/bench_tile_size.py [--probe PATH/courtyard.exr] [--csv OUT.csv]

For the sky + 1e5 sun of :func:`ibl_ref.experiments.speed_accuracy.environment` at 64², 128², 256² faces (and the
probe at 128², 256²), s ∈ {64, 256, 1024, 4096} (256²: from 256), rtol 1e-3, it runs
:func:`ibl_ref.groundtruth.phong_convolution.convolve_sparse_many` (``impl="compiled"``) with every tile width T ∈
{2, 3, 4, 6, 8, 12, 16} forced (process CPU seconds, best of 2 after one warm call), then fits the two constants of
the tile-size model (``numba_backend.TILE_OVERHEAD``, ``CAND_OVERHEAD``: cost per tile and per candidate
in units of one weight) on a grid, by the mean ratio chosen / best over the cells, and prints the best fits and the
current constants' ratio.  CPU time: the cells are single-threaded and CPU time depends least on the machine's load.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

WIDTHS = (2, 3, 4, 6, 8, 12, 16)
TILE_GRID = (100, 300, 1000, 1500, 2000, 4000, 8000, 16000)
CAND_GRID = (0, 2, 4, 8, 16, 32, 64)


def model_choice(n, theta_c, m_src, n_bright, tile_overhead, cand_overhead):
    """The width :func:`ibl_ref.groundtruth.phong_convolution._tile_size` picks among :data:`WIDTHS`."""
    best, best_cost = None, math.inf
    delta = (math.pi / 2) / n
    for T in WIDTHS:
        q = min(theta_c + 0.75 * T * delta, math.pi)
        cand = m_src * (1.0 - math.cos(q)) / 2.0 + n_bright
        cost = 6 * math.ceil(n / T) ** 2 * (tile_overhead + cand * (T * T + cand_overhead))
        if cost < best_cost:
            best, best_cost = T, cost
    return best


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--probe", help="a real lat-long probe (EXR) to add at 128² and 256²")
    ap.add_argument("--csv", help="write the measured cells (CPU seconds per width) to this CSV")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    from ibl_ref.environment.exr_io import load_cube
    from ibl_ref.experiments.speed_accuracy import environment
    from ibl_ref.groundtruth import phong_convolution as pc

    orig = pc._tile_size
    state = {}

    def forced(*a, **k):
        state["args"] = a
        return state["T"]

    pc._tile_size = forced
    scenes = [("sky", n) for n in (64, 128, 256)] + ([("probe", n) for n in (128, 256)] if args.probe else [])
    rows = []
    try:
        for scene, n in scenes:
            cube = environment(n) if scene == "sky" else load_cube(args.probe, size=n)
            for s in (64.0, 256.0, 1024.0, 4096.0):
                if n >= 256 and s < 256:
                    continue
                t = {}
                for T in WIDTHS:
                    state["T"] = T
                    pc.convolve_sparse_many(cube, [s], rtol=1e-3, impl="compiled")
                    best = math.inf
                    for _ in range(2):
                        c0 = time.process_time()
                        pc.convolve_sparse_many(cube, [s], rtol=1e-3, impl="compiled")
                        best = min(best, time.process_time() - c0)
                    t[T] = best
                rows.append({"scene": scene, "face": n, "s": s, "args": state["args"][:4], "t": t})
                print(f"{scene} {n}² s={s:g}: " + " ".join(f"T={T} {v:.3f}s" for T, v in t.items()), flush=True)
    finally:
        pc._tile_size = orig

    def regret(to, co):
        r = [row["t"][model_choice(row["face"], *row["args"][1:4], to, co)] / min(row["t"].values()) for row in rows]
        return float(np.mean(r)), float(np.max(r))

    fits = sorted((regret(to, co), to, co) for to in TILE_GRID for co in CAND_GRID)
    print("best fits (mean, max chosen/best; tile overhead; candidate overhead):")
    for (mean, mx), to, co in fits[:5]:
        print(f"  {mean:.3f} {mx:.3f}  {to:g}  {co:g}")
    from ibl_ref.groundtruth.kernels.numba_backend import CAND_OVERHEAD, TILE_OVERHEAD

    cur = regret(TILE_OVERHEAD, CAND_OVERHEAD)
    print(f"current ({TILE_OVERHEAD:g}, {CAND_OVERHEAD:g}): {cur[0]:.3f} {cur[1]:.3f}")
    for T in (4, 6, 8):
        print(f"fixed T={T}: {np.mean([row['t'][T] / min(row['t'].values()) for row in rows]):.3f}")
    if args.csv:
        from ibl_ref.atomic import write_csv

        write_csv(args.csv, [{"scene": row["scene"], "face": row["face"], "s": row["s"],
                              **{f"cpu_s_T{T}": row["t"][T] for T in WIDTHS}} for row in rows])


if __name__ == "__main__":
    main()
