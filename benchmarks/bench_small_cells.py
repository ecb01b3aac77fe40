"""Where the time of a small, narrow-lobe cell goes: the lab against cmft where cmft's whole run takes milliseconds.

Usage::

    python benchmarks/bench_small_cells.py --cmft PATH/cmft [--probe PATH/courtyard.exr] [--faces 64 128]
        [--exponents 256 1024 4096] [--repeat 5] [--markdown OUT.md] [--csv OUT.csv]

:mod:`bench_peer` (same folder) compares the tools cell by cell; this script takes its scenes (the sky + 1e5 sun of
:func:`ibl_ref.experiments.speed_accuracy.environment`, and with ``--probe`` a real probe resampled to each face
size), its commands (cmft's radiance filter with 2 worker threads, ``ibl-ref convolve --rtol 1e-3 --kernel
compiled``) and its interpreter floor, and splits the lab's cost in the cells where bench_peer's small-cell targets
are not met (face sizes 64² and 128², s ≥ 256), all measured side by side in one run (median of ``--repeat``):

* **cmft** — its whole run (a process: start, read the DDS, filter, write);
* **IO floor** — bench_peer's :data:`~bench_peer.IO_FLOOR`: start Python, import NumPy and OpenEXR, read the input EXR
  and write one of the same size (none of the lab's code); **process target** = cmft + IO floor (bench_peer's
  verdict below 0.5 s of cmft);
* **lab floor** — the IO floor plus importing every ``ibl_ref`` module that ``ibl-ref convolve`` loads for the cell
  (listed by running the command once) and loading the compiled kernels: the least any lab process costs before it
  computes anything;
* **lab process** — ``ibl-ref convolve`` as a whole process;
* **first call** — ``convolve(cube, [s], rtol=1e-3, kernel="compiled", workers=2)`` in this warm process (imports
  done, kernels loaded by a call on another map; it pays the cell's set-up: cutoff angles, tile layout, bound
  tables), as bench_peer's in-process column; **repeated call** — the median of the calls after it;
* **kernels** — of the repeated call, the wall time spent in the compiled kernels on the calling thread (the
  two-thread tile gather from start to join, the bound and local-extreme passes); **Python** — the rest.

A process target is out of reach for any lab process when the lab floor alone exceeds it (column "floor > target");
an in-process one when even the kernels of the repeated call exceed cmft's whole run.  No verdict is tuned here: the
numbers are printed as measured, with the command, commit and load average.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

import bench_peer as bp  # noqa: E402  (also puts this checkout first on sys.path)
from ibl_ref.atomic import atomic_write, write_csv  # noqa: E402
from ibl_ref.environment import envmap  # noqa: E402

#: run ``ibl-ref convolve`` in this interpreter and print the ``ibl_ref`` modules it loaded (JSON, last line)
_MODULES_OF_RUN = ("import sys, json, runpy; sys.argv = ['ibl_ref'] + sys.argv[1:]\n"
                   "try:\n    runpy.run_module('ibl_ref', run_name='__main__')\nexcept SystemExit:\n    pass\n"
                   "print(json.dumps(sorted(m for m in sys.modules if m.startswith('ibl_ref'))))")


def lab_floor_code(modules) -> str:
    """:data:`bench_peer.IO_FLOOR` with ``modules`` imported and the compiled kernels loaded first."""
    imports = "".join(f"import {m}; " for m in modules)
    return (imports + "from ibl_ref.groundtruth.kernels import get_kernels; get_kernels('compiled').warm_up(); "
            + bp.IO_FLOOR)


class KernelClock:
    """Wall seconds the calling thread spends in the compiled kernels during ``with clock:`` (the threaded tile
    gather from start to join counts once; kernels the tile threads call inside it are not counted again)."""

    def __init__(self):
        from ibl_ref.groundtruth.kernels import get_kernels, numba_backend, numba_loops

        get_kernels("compiled").warm_up()
        self.seconds = 0.0
        self._main = threading.get_ident()
        self._depth = 0
        self._patches = [(numba_loops.__dict__, k) for k in numba_loops.__all__]
        self._patches.append((numba_backend.__dict__, "_tile_gather_threads"))

    def _timed(self, fn):
        def call(*args):
            if threading.get_ident() != self._main or self._depth:
                return fn(*args)
            self._depth += 1
            t0 = time.perf_counter()
            try:
                return fn(*args)
            finally:
                self.seconds += time.perf_counter() - t0
                self._depth -= 1
        return call

    def __enter__(self):
        self._saved = [(d, k, d[k]) for d, k in self._patches]
        for d, k, fn in self._saved:
            d[k] = self._timed(fn)
        self.seconds = 0.0
        return self

    def __exit__(self, *exc):
        for d, k, fn in self._saved:
            d[k] = fn
        return False


def _ms(x):
    return "—" if x is None else f"{1e3 * x:.1f}"


def main(argv=None):
    from ibl_ref.environment.exr_io import load_cube, write_envmap
    from ibl_ref.experiments.speed_accuracy import environment
    from ibl_ref.groundtruth.convolve import convolve

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cmft", required=True, metavar="PATH", help="the cmft binary")
    ap.add_argument("--probe", default=None, help="also a real lat-long probe (resampled to each face size)")
    ap.add_argument("--faces", type=int, nargs="+", default=[64, 128])
    ap.add_argument("--exponents", type=float, nargs="+", default=[256.0, 1024.0, 4096.0])
    ap.add_argument("--repeat", type=int, default=5, help="runs per measurement (median)")
    ap.add_argument("--csv", type=Path, default=None, help="write the cells as CSV")
    ap.add_argument("--markdown", type=Path, default=None, help="write the tables to this file too")
    args = ap.parse_args(argv)
    if args.repeat < 2:
        ap.error("--repeat must be at least 2 (the repeated call is the median of the calls after the first)")
    cmft = str(Path(args.cmft).resolve())
    commit = subprocess.run(["git", "-C", str(bp.ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", str(bp.ROOT), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    head = (f"Command: `python benchmarks/bench_small_cells.py {' '.join(sys.argv[1:] if argv is None else argv)}`; "
            f"commit `{commit}`{' (with uncommitted changes)' if dirty else ''}; started "
            f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {bp._load()}.")
    print(head, flush=True)
    bp.compile_lab()
    env = bp.lab_env()
    convolve(environment(16), [3.0], rtol=1e-3, kernel="compiled", workers=2)  # imports and kernels: a warm process
    rows, md = [], [head, ""]
    scenes = [("sky + sun", None)] + ([(Path(args.probe).stem, args.probe)] if args.probe else [])
    with tempfile.TemporaryDirectory(prefix="ibl_small_") as td:
        tmp = Path(td)
        for scene, path in scenes:
            md += [f"**{scene}** — milliseconds, median of {args.repeat}; target = cmft + IO floor; floor > target: "
                   "the lab floor alone exceeds the process target", "",
                   "| face | s | cmft | IO floor | process target | lab floor | floor > target | lab process | "
                   "first call | repeated call | kernels | Python |",
                   "|---|---|---|---|---|---|---|---|---|---|---|---|"]
            for n in args.faces:
                cube = (environment(n) if path is None else load_cube(path, size=n)).astype(np.float32).astype(
                    np.float64)
                inp_exr, inp_dds = tmp / f"in{n}.exr", tmp / f"in{n}.dds"
                write_envmap(inp_exr, cube, layout="cube")
                bp.write_dds_cube(inp_dds, envmap.convert_convention(cube, "openexr", "opengl"))
                io_floor = bp.median_wall([sys.executable, "-c", bp.IO_FLOOR, str(inp_exr), str(tmp / "f.exr")],
                                          args.repeat, None, env)[0]
                for s in args.exponents:
                    out = tmp / f"lab{n}.exr"
                    lab = bp.lab_cmd(inp_exr, out, [s], "compiled")
                    p = subprocess.run([sys.executable, "-c", _MODULES_OF_RUN] + lab[3:], capture_output=True,
                                       text=True, env=env, check=True)
                    modules = json.loads(p.stdout.strip().splitlines()[-1])
                    lab_floor = bp.median_wall([sys.executable, "-c", lab_floor_code(modules), str(inp_exr),
                                                str(tmp / "f.exr")], args.repeat, None, env)[0]
                    c_wall = bp.median_wall(bp.cmft_cmd(cmft, inp_dds, tmp / "cm", s), args.repeat, 120)[0]
                    lab_wall = bp.median_wall(lab, args.repeat, None, env)[0]
                    t0 = time.perf_counter()
                    convolve(cube, [s], rtol=1e-3, kernel="compiled", workers=2)
                    first = time.perf_counter() - t0
                    reps, kern = [], []
                    for _ in range(args.repeat - 1):
                        with KernelClock() as clock:
                            t0 = time.perf_counter()
                            convolve(cube, [s], rtol=1e-3, kernel="compiled", workers=2)
                            reps.append(time.perf_counter() - t0)
                        kern.append(clock.seconds)
                    i = int(np.argsort(reps)[len(reps) // 2])  # the median call and its own kernel time
                    target = None if c_wall is None else c_wall + io_floor
                    row = {"scene": scene, "face": n, "s": s, "cmft_wall_s": c_wall, "io_floor_wall_s": io_floor,
                           "process_target_wall_s": target, "lab_floor_wall_s": lab_floor,
                           "lab_process_wall_s": lab_wall, "first_call_wall_s": first,
                           "repeated_call_wall_s": reps[i], "repeated_kernels_wall_s": kern[i],
                           "repeated_python_wall_s": reps[i] - kern[i], "lab_modules": len(modules)}
                    rows.append(row)
                    over = "—" if target is None else ("yes" if lab_floor > target else "no")
                    md.append(f"| {n}² | {s:g} | {_ms(c_wall)} | {_ms(io_floor)} | {_ms(target)} | {_ms(lab_floor)} | "
                              f"{over} | {_ms(lab_wall)} | {_ms(first)} | {_ms(reps[i])} | {_ms(kern[i])} | "
                              f"{_ms(reps[i] - kern[i])} |")
                    print(md[-1], flush=True)
            md.append("")
    md.append(f"Ended {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {bp._load()}.")
    text = "\n".join(md)
    print(text)
    if args.markdown:
        with atomic_write(args.markdown) as f:
            f.write(text + "\n")
    if args.csv:
        write_csv(args.csv, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
