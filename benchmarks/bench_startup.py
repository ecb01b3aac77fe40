"""Start-up cost of the lab's processes: ``ibl-ref --help``, a command's ``--help`` and a small ``convolve`` run, for
this checkout and, side by side in the same run, for other checkouts of the lab (e.g. a ``git worktree`` of an earlier
commit).

Usage::

    python benchmarks/bench_startup.py [--baseline DIR ...] [--repeat 9] [--markdown OUT.md] [--csv OUT.csv]

Each command runs as ``python -m ibl_ref …`` (what the ``ibl-ref`` script runs) with ``PYTHONPATH`` set to the
checkout, byte-compiled first (as ``pip install`` leaves it); the checkouts' runs are interleaved, command by command
and repeat by repeat, so that a change of the machine's load falls on all of them alike.  Reported: the median wall
seconds of ``--repeat`` runs, the ratio to this checkout, and how many ``ibl_ref`` modules the process imported.
The small convolution: a 32² sky + sun map (float32 cube EXR), s = 64, ``--kernel numpy`` and ``--kernel compiled``
(numba's cache of the kernels warm: each checkout runs it once first).  Output: a markdown table headed by the
command, commit and load average, and a CSV.
"""

from __future__ import annotations

import argparse
import compileall
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: label → arguments of ``python -m ibl_ref`` (``IN``/``OUT`` replaced by the input and output files)
COMMANDS = {
    "ibl-ref --help": ["--help"],
    "ibl-ref convolve --help": ["convolve", "--help"],
    "ibl-ref convolve (32², s = 64, numpy)": ["convolve", "IN", "OUT", "-s", "64", "--kernel", "numpy"],
    "ibl-ref convolve (32², s = 64, compiled)": ["convolve", "IN", "OUT", "-s", "64", "--kernel", "compiled"],
}
#: prints how many ibl_ref modules a run of ``python -m ibl_ref ARGS`` imported (stdout's last line)
_COUNT = ("import sys, runpy; sys.argv = ['ibl_ref'] + sys.argv[1:]\n"
          "try:\n    runpy.run_module('ibl_ref', run_name='__main__')\nexcept SystemExit:\n    pass\n"
          "print(len([m for m in sys.modules if m.startswith('ibl_ref')]))")


def run(tree: Path, args, env_extra=None, count=False):
    env = dict(os.environ, PYTHONPATH=str(tree), IBL_REF_PROGRESS="0")
    env.update(env_extra or {})
    cmd = [sys.executable, "-c", _COUNT, *args] if count else [sys.executable, "-m", "ibl_ref", *args]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    dt = time.perf_counter() - t0
    if p.returncode != 0:
        raise RuntimeError(f"{tree}: {' '.join(args)} failed: {p.stderr.strip().splitlines()[-1:]}")
    return dt, (int(p.stdout.strip().splitlines()[-1]) if count else None)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", action="append", default=[], help="another checkout of the lab to measure beside")
    ap.add_argument("--repeat", type=int, default=9)
    ap.add_argument("--markdown")
    ap.add_argument("--csv")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from ibl_ref.atomic import atomic_write, write_csv
    from ibl_ref.environment.exr_io import write_envmap
    from ibl_ref.experiments.speed_accuracy import environment

    trees = [ROOT] + [Path(b).resolve() for b in args.baseline]
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    head = (f"Command: `python benchmarks/bench_startup.py {' '.join(argv if argv is not None else sys.argv[1:])}`; "
            f"commit `{commit}`; started {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load avg "
            f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    print(head, flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        inp = tmp / "sky32.exr"
        write_envmap(inp, environment(32), layout="cube")
        cache = tmp / "numba"
        for t in trees:
            compileall.compile_dir(str(t / "ibl_ref"), quiet=1)
        rows = []
        for label, a in COMMANDS.items():
            times = {t: [] for t in trees}
            mods = {}
            for i, t in enumerate(trees):
                out = tmp / f"out{i}.exr"
                full = [str(inp) if x == "IN" else str(out) if x == "OUT" else x for x in a]
                env = {"NUMBA_CACHE_DIR": str(cache / str(i))}
                _d, mods[t] = run(t, full, env, count=True)  # (also warms numba's cache and the page cache)
            for _ in range(args.repeat):
                for i, t in enumerate(trees):
                    out = tmp / f"out{i}.exr"
                    full = [str(inp) if x == "IN" else str(out) if x == "OUT" else x for x in a]
                    times[t].append(run(t, full, {"NUMBA_CACHE_DIR": str(cache / str(i))})[0])
            base = sorted(times[ROOT])[len(times[ROOT]) // 2]
            for t in trees:
                med = sorted(times[t])[len(times[t]) // 2]
                rows.append({"command": label, "checkout": str(t), "wall_s_median": med, "ratio_to_this": med / base,
                             "ibl_ref_modules": mods[t], "repeat": args.repeat})
                print(f"{label} | {t}: {med:.3f} s ({med / base:.2f}×), {mods[t]} ibl_ref modules", flush=True)
    tail = f"Ended {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load avg {os.getloadavg()[0]:.2f}"
    lines = [head, "", "| command | checkout | wall s (median) | × this checkout | ibl_ref modules imported |",
             "|---|---|---|---|---|"]
    lines += [f"| {r['command']} | {r['checkout']} | {r['wall_s_median']:.3f} | {r['ratio_to_this']:.2f} | "
              f"{r['ibl_ref_modules']} |" for r in rows]
    lines += ["", tail]
    print("\n".join(lines))
    if args.markdown:
        with atomic_write(args.markdown) as fh:
            fh.write("\n".join(lines) + "\n")
    if args.csv:
        write_csv(args.csv, rows)


if __name__ == "__main__":
    main()
