"""Measure the routes of :func:`ibl_ref.groundtruth.convolve.convolve` and fit the planner's cost models, per kernel.

Usage::

    python benchmarks/bench_cost_models.py [--kernel numpy|compiled] [--sizes 64 128 256] [--quick]

For the kernel given (both by default) it times, serially (1 BLAS thread, process CPU time), on the sky + 1e5 sun
of ``benchmarks/bench_peer.py`` at rtol 1e-3:

* the sparse gather (``convolve_sparse_many``) at every size × s ∈ {64, 256, 1024, 4096} (and with ``--probe`` on
  a real probe), and fits ``cost = a·(output texels × candidates per output) + b·(output texels)`` (non-negative
  least squares on relative residuals; candidates by ``estimate_candidates``, the gather's own first caps on a
  sample of tiles), the form of ``ibl_ref.groundtruth.convolve._sparse_cost``;
* the SH route (``convolve_sh_many``, 5 exponents 5…100, and s = 16, 256 alone) and fits one factor on
  ``sh_cost`` (its SH passes, ``time_sh_s``) and one on ``bright_cost`` (``time_bright_s``);
* the moment route (s = 1 and 2, the leaf ``auto`` uses) and fits ``c·(output texels)·(1 + N/leaf... )``, see
  ``ibl_ref.groundtruth.convolve._moment_cost``;

and prints the constants with every cell's measured / modelled ratio, in units of
``ibl_ref.groundtruth.sh_convolution.SECONDS_PER_UNIT``.  The constants in ``convolve.py`` come from one run of
this script (quoted there with the load); timings are CPU seconds, so the fit depends little on other work on a
shared machine, but quote the load average printed at the start and end.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from ibl_ref.experiments.speed_accuracy import environment  # noqa: E402
from ibl_ref.groundtruth import convolve as cv  # noqa: E402
from ibl_ref.groundtruth import moment_convolution as mc  # noqa: E402
from ibl_ref.groundtruth import phong_convolution as pc  # noqa: E402
from ibl_ref.groundtruth import sh_convolution as shc  # noqa: E402

RTOL = 1e-3
S_SPARSE = (64.0, 256.0, 1024.0, 4096.0)
S_SH = ((5.0, 10.0, 20.0, 50.0, 100.0), (16.0,), (256.0,))


def _load():
    try:
        return f"load avg {os.getloadavg()[0]:.2f} (1 min)"
    except OSError:
        return "load avg n/a"


def _cpu(fn):
    c0 = time.process_time()
    r = fn()
    return r, time.process_time() - c0


def _nnls2(A, y):
    """Non-negative least squares of relative residuals for 2 columns (closed form over the 3 supports)."""
    W = A / y[:, None]
    best = None
    for cols in ((0, 1), (0,), (1,)):
        x, *_ = np.linalg.lstsq(W[:, cols], np.ones(len(y)), rcond=None)
        if np.any(x < 0):
            continue
        full = np.zeros(2)
        full[list(cols)] = x
        r = float(np.sum((W @ full - 1.0) ** 2))
        if best is None or r < best[0]:
            best = (r, full)
    return best[1]


def _sparse_cells(sizes, probe):
    for n, cube in _sky(sizes):
        yield f"sky {n}²", cube, S_SPARSE
    if probe:
        from ibl_ref.environment.exr_io import load_cube

        yield Path(probe).stem, load_cube(probe), (256.0, 1024.0, 4096.0)


def fit_sparse(kernel, sizes, probe=None):
    """Fit ``a·(output texels × the candidates per output of estimate_candidates) + b·(output texels)``."""
    unit = shc.SECONDS_PER_UNIT
    rows = []
    for label, cube, ss in _sparse_cells(sizes, probe):
        n = cube.shape[1]
        for s in ss:
            cand = pc.estimate_candidates(cube, [s], rtol=RTOL, impl=kernel)[0]
            _, t = _cpu(lambda: pc.convolve_sparse_many(cube, [s], rtol=RTOL, impl=kernel))
            n_out = 6 * n * n
            rows.append((label, s, n_out * cand, n_out, t))
            print(f"  sparse {kernel} {label} s={s:g}: {t:.3f} s CPU, {cand:.0f} candidates per output", flush=True)
    A = np.array([[r[2], r[3]] for r in rows])
    y = np.array([r[4] for r in rows]) / unit
    a, b = _nnls2(A, y)
    print(f"sparse {kernel}: SPARSE_UNITS_PER_CAND = {a:.3g}, SPARSE_UNITS_PER_OUTPUT = {b:.3g}")
    for r, m in zip(rows, A @ np.array([a, b])):
        print(f"    {r[0]} s={r[1]:g}: measured / model = {r[4] / (m * unit):.2f}")
    return a, b


def _sky(sizes):
    """(face size, the sky + sun rounded to float32) per size."""
    for n in sizes:
        yield n, environment(n).astype(np.float32).astype(np.float64)


def fit_sh(kernel, sizes):
    unit = shc.SECONDS_PER_UNIT
    rows = []
    for n, cube in _sky(sizes):
        for ss in S_SH:
            _, _, info = shc.convolve_sh_many(cube, list(ss), rtol=RTOL, impl=kernel)
            n_src = n_out = 6 * n * n
            m_sh = shc.sh_cost(info["L"], n_src, n_out, len(ss), 4)
            m_b = shc.bright_cost(info["n_bright"], n_out, len(ss))
            rows.append((n, ss, info["L"], m_sh, m_b, info["time_sh_s"], info["time_bright_s"],
                         info["time_total_s"]))
            print(f"  sh {kernel} {n}² s={','.join(f'{s:g}' for s in ss)} L={info['L']}: passes "
                  f"{info['time_sh_s']:.3f} s, bright {info['time_bright_s']:.3f} s, total {info['time_total_s']:.3f} s",
                  flush=True)
    f_sh = float(np.median([r[5] / (r[3] * unit) for r in rows]))
    f_b = float(np.median([r[6] / (r[4] * unit) for r in rows if r[4] > 0] or [1.0]))
    print(f"sh {kernel}: factor on sh_cost = {f_sh:.3g}, on bright_cost = {f_b:.3g} (medians of measured / model)")
    return f_sh, f_b


def fit_moment(kernel, sizes):
    unit = shc.SECONDS_PER_UNIT
    rows = []
    for n, cube in _sky(sizes):
        leaf = mc.moment_leaf(n, RTOL)
        faces = (0,) if n >= 512 else None  # one face at 512² and more (× 6)
        _, t = _cpu(lambda: mc.convolve_moment_many(cube, [1.0, 2.0], leaf=leaf, rtol=RTOL if leaf > 1 else None,
                                                    faces=faces, impl=kernel))
        t *= 6 if faces else 1
        model = cv._moment_cost(n, n, leaf, kernel) / cv._unit("MOMENT_UNITS", kernel)
        rows.append((n, leaf, model, t))
        print(f"  moment {kernel} {n}² leaf {leaf}: {t:.3f} s CPU", flush=True)
    c = float(np.median([r[3] / (r[2] * unit) for r in rows]))
    print(f"moment {kernel}: MOMENT_UNITS = {c:.3g}")
    for r in rows:
        print(f"    {r[0]}² leaf {r[1]}: measured / model = {r[3] / (r[2] * c * unit):.2f}")
    return c


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kernel", choices=("numpy", "compiled"), action="append")
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    ap.add_argument("--moment-sizes", type=int, nargs="+", default=[64, 128, 256, 512])
    ap.add_argument("--only", choices=("sparse", "sh", "moment"), action="append")
    ap.add_argument("--probe", default=None, help="also fit the sparse gather on this probe (lat-long EXR)")
    args = ap.parse_args(argv)
    kernels = args.kernel or ["numpy", "compiled"]
    only = args.only or ["sparse", "sh", "moment"]
    print(f"ibl_ref from {ROOT}; {_load()}; CPU seconds, 1 BLAS thread, rtol {RTOL}")
    for k in kernels:
        if k == "compiled":
            from ibl_ref.groundtruth.kernels import get_kernels

            print(f"compiled kernels loaded in {get_kernels('compiled').warm_up():.2f} s")
        with threadpool_limits(limits=1, user_api="blas"):
            environment(8)
            if "sparse" in only:
                fit_sparse(k, args.sizes, args.probe)
            if "sh" in only:
                fit_sh(k, args.sizes)
            if "moment" in only:
                fit_moment(k, args.moment_sizes)
    print(_load())


if __name__ == "__main__":
    main()
