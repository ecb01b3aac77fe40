"""What each compiled operation of the kernel interface buys: a route timed with the compiled backend, with the NumPy
backend, and with the compiled backend but one operation handed back to NumPy, side by side in one run.

Usage::

    python benchmarks/bench_kernel_ops.py [--probe PATH/courtyard.exr] [--repeat 3] [--markdown OUT.md] [--csv OUT.csv]

The operations (:class:`ibl_ref.groundtruth.kernels.Kernels`) and the route each one serves:

* ``tile_gather`` — the sparse gather's sums (the whole gather object: NumPy's float32/float64 kernels instead);
* ``tile_bounds`` — the sparse route's averages and bounds from those sums (NumPy's array formula instead);
* ``local_extremes`` — the sparse route's local radiance extremes (NumPy's block cones instead);
* ``band`` — the moment route's exact band and brackets;
* ``sh_passes`` — the SH route's projection and evaluation (NumPy's SH matrix and BLAS instead);
* ``bright_gather`` — the SH route's exact gather from its bright texels.

Each cell calls the route itself (:func:`~ibl_ref.groundtruth.phong_convolution.convolve_sparse_many`,
:func:`~ibl_ref.groundtruth.moment_convolution.convolve_moment_many`,
:func:`~ibl_ref.groundtruth.sh_convolution.convolve_sh_many`) in this process, one worker, BLAS at one thread, after a
warm-up call; the time is the best of ``--repeat`` calls made round robin over the variants (wall seconds; the machine
is shared, so the ratios within a row are what counts: ``ratio`` = variant / all compiled).  Every variant's maps are checked against the all-compiled
ones within the two bounds.  Output: a markdown table headed by the command, commit and load, and a CSV.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from ibl_ref.atomic import atomic_write, write_csv  # noqa: E402
from ibl_ref.groundtruth import moment_convolution as mc  # noqa: E402
from ibl_ref.groundtruth import phong_convolution as pc  # noqa: E402
from ibl_ref.groundtruth import sh_convolution as shc  # noqa: E402
from ibl_ref.groundtruth.kernels import get_kernels  # noqa: E402
from ibl_ref.groundtruth.kernels.numba_backend import CompiledKernels, CompiledSparseGather  # noqa: E402
from ibl_ref.groundtruth.kernels.numpy_backend import NumpyKernels, Sources, SparseGather  # noqa: E402


class _NumpyBounds(CompiledSparseGather):
    bounds = SparseGather.bounds


class _NumpyExtremes(CompiledSparseGather):
    def local_extremes(self, cen, q):
        return Sources.local_extremes(self.sources, cen, q)


def _variant(name, **ops):
    """A :class:`CompiledKernels` with the operations ``ops`` (name → function) replaced."""
    return type(name, (CompiledKernels,), ops)()


def variants():
    """Backend name → kernels object, and the route each variant's operation serves."""
    gathers = {"tile_bounds": _NumpyBounds, "local_extremes": _NumpyExtremes}
    out = {"compiled": (get_kernels("compiled"), None), "numpy": (NumpyKernels(), None),
           "tile_gather": (_variant("V1", sparse_gather=NumpyKernels.sparse_gather), "sparse")}
    for op, cls in gathers.items():
        out[op] = (_variant(op, sparse_gather=lambda self, *a, _c=cls: _c(*a)), "sparse")
    out["band"] = (_variant("V4", band_sources=NumpyKernels.band_sources, band_exact=NumpyKernels.band_exact,
                            brackets_prep=NumpyKernels.brackets_prep, band_brackets=NumpyKernels.band_brackets),
                   "moment")
    out["sh_passes"] = (_variant("V5", sh_shared_chunks=NumpyKernels.sh_shared_chunks,
                                 sh_project_octant=NumpyKernels.sh_project_octant,
                                 sh_octant_values=NumpyKernels.sh_octant_values), "sh")
    out["bright_gather"] = (_variant("V6", bright_gather=NumpyKernels.bright_gather,
                                     bright_gather_error=NumpyKernels.bright_gather_error), "sh")
    return out


def run_cell(route, cube, s_list, kern, leaf):
    """``(maps, relative bounds)`` of one route call with the kernels ``kern``."""
    if route == "sparse":
        m, b = pc.convolve_sparse_many(cube, s_list, rtol=1e-3, impl=kern)
        with np.errstate(divide="ignore", invalid="ignore"):
            return m, np.where(m > b, b / (m - b), np.inf).max(axis=-1)
    if route == "moment":
        return mc.convolve_moment_many(cube, s_list, leaf=leaf, rtol=1e-3 if leaf > 1 else None, impl=kern)
    m, r, _info = shc.convolve_sh_many(cube, s_list, rtol=1e-3, impl=kern)
    return m, r


def cells(probe):
    from ibl_ref.environment.exr_io import load_cube
    from ibl_ref.experiments.speed_accuracy import environment

    scenes = [("sky", n, environment(n)) for n in (64, 128, 256)]
    if probe:
        scenes += [("courtyard", n, load_cube(probe, size=n)) for n in (128, 256)]
    for scene, n, cube in scenes:
        for s in (256.0, 1024.0, 4096.0):
            if n >= 128 or s >= 1024:
                yield scene, n, cube, "sparse", [s], 1
        if scene == "sky" and n >= 128:
            yield scene, n, cube, "moment", [1.0, 2.0], 1 if n == 128 else 8
        if n >= 128:
            yield scene, n, cube, "sh", [5.0, 20.0, 100.0], 1


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--probe", help="a real lat-long probe (EXR) added at 128² and 256²")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--markdown")
    ap.add_argument("--csv")
    args = ap.parse_args(argv)
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    load0 = os.getloadavg()[0]
    head = (f"Command: `python benchmarks/bench_kernel_ops.py {' '.join(argv or sys.argv[1:])}`; commit `{commit}`; "
            f"started {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load avg {load0:.2f} on "
            f"{os.cpu_count()} CPUs")
    print(head, flush=True)
    vs = variants()
    get_kernels("compiled").warm_up()
    rows = []
    with threadpool_limits(limits=1, user_api="blas"):
        for scene, n, cube, route, s_list, leaf in cells(args.probe):
            names = ["compiled", "numpy"] + [k for k, (_v, r) in vs.items() if r == route]
            t, res = {name: np.inf for name in names}, {}
            for name in names:  # warm-up: set-up tables, numba signatures
                run_cell(route, cube, s_list, vs[name][0], leaf)
            for _ in range(args.repeat):  # round robin: a change of the machine's load falls on every variant alike
                for name in names:
                    t0 = time.perf_counter()
                    res[name] = run_cell(route, cube, s_list, vs[name][0], leaf)
                    t[name] = min(t[name], time.perf_counter() - t0)
            (m0, r0) = res["compiled"]
            for name in names:
                m1, r1 = res[name]
                d = np.abs(m1 - m0) / np.maximum(np.abs(m0), 1e-300)
                ok = bool(np.all(d.max(axis=-1) <= r0 + r1 + 1e-12))
                rows.append({"scene": scene, "face": n, "route": route, "exponents": " ".join(f"{s:g}" for s in s_list),
                             "leaf": leaf, "variant": name, "wall_s": t[name], "ratio": t[name] / t["compiled"],
                             "within_bounds": ok})
            print(f"{scene} {n}² {route} s={s_list}: " + ", ".join(f"{k} {v:.3f}s ({v / t['compiled']:.2f}×)"
                                                               for k, v in t.items()), flush=True)
    tail = f"Ended {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load avg {os.getloadavg()[0]:.2f}"
    lines = [head, "", "| scene | face | route | s | variant | wall s | × all compiled | maps within the bounds |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['scene']} | {r['face']}² | {r['route']} | {r['exponents']} | {r['variant']} | {r['wall_s']:.3f} | "
              f"{r['ratio']:.2f} | {'yes' if r['within_bounds'] else 'NO'} |" for r in rows]
    lines += ["", tail]
    print("\n".join(lines))
    if args.markdown:
        with atomic_write(args.markdown) as fh:
            fh.write("\n".join(lines) + "\n")
    if args.csv:
        write_csv(args.csv, rows)


if __name__ == "__main__":
    main()
