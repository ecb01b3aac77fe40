"""Start-up cost of the lab's processes: ``ibl-ref --help``, a command's ``--help`` and a small ``convolve`` run, for
this checkout and, side by side in the same run, for other checkouts of the lab (e.g. a ``git worktree`` of an earlier
commit).

Usage::

    python benchmarks/bench_startup.py [--baseline DIR ...] [--repeat 9] [--markdown OUT.md] [--csv OUT.csv]

Each command runs as ``python -m ibl_ref …`` (what the ``ibl-ref`` script runs) with ``PYTHONPATH`` set to the
checkout, from a neutral working folder, byte-compiled first (as ``pip install`` leaves it); the checkouts' runs are interleaved, command by command
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
import shlex
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
    # (from a neutral folder: ``python -m`` puts the working directory first on sys.path, before PYTHONPATH)
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600, cwd=tempfile.gettempdir())
    dt = time.perf_counter() - t0
    if p.returncode != 0:
        raise RuntimeError(f"{tree}: {' '.join(args)} failed: {p.stderr.strip().splitlines()[-1:]}")
    return dt, (int(p.stdout.strip().splitlines()[-1]) if count else None)


def import_counts(package: Path) -> dict:
    """How many import statements of ``package`` import the package itself, and how many of those sit inside a
    function (the rest run when their module is imported)."""
    import ast

    total = inside = 0
    for p in sorted(package.rglob("*.py")):
        tree = ast.parse(p.read_text(encoding="utf-8"))
        funcs = [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
        local = {id(m) for f in funcs for m in ast.walk(f)}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                internal = node.level > 0 or (node.module or "").startswith("ibl_ref")
            elif isinstance(node, ast.Import):
                internal = node.names[0].name.startswith("ibl_ref")
            else:
                continue
            if internal:
                total += 1
                inside += id(node) in local
    return {"internal_imports": total, "inside_functions": inside,
            "share_inside_functions": f"{100.0 * inside / max(total, 1):.0f} %"}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", action="append", default=[], help="another checkout of the lab to measure beside")
    ap.add_argument("--repeat", type=int, default=9)
    ap.add_argument("--label", action="append", default=[],
                    help="names of the checkouts in the tables: this one first, then each --baseline (default: paths)")
    ap.add_argument("--markdown")
    ap.add_argument("--csv")
    ap.add_argument("--save-dir", help="write startup.csv, imports.csv and run.json (the documentation's layout)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from ibl_ref.atomic import atomic_write, write_csv
    from ibl_ref.environment.exr_io import write_envmap
    from ibl_ref.experiments.speed_accuracy import environment

    trees = [ROOT] + [Path(b).resolve() for b in args.baseline]
    names = {t: (args.label[i] if i < len(args.label) else str(t)) for i, t in enumerate(trees)}
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    load0 = os.getloadavg()[0]
    head = (f"Command: `python benchmarks/bench_startup.py {shlex.join(argv if argv is not None else sys.argv[1:])}`; "
            f"commit `{commit}`; started {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load avg "
            f"{load0:.2f} on {os.cpu_count()} CPUs")
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
            def full(i):
                return [str(inp) if x == "IN" else str(tmp / f"out{i}.exr") if x == "OUT" else x for x in a]

            for i, t in enumerate(trees):  # warm-up: numba's cache of the compiled kernels, the page cache
                run(t, full(i), {"NUMBA_CACHE_DIR": str(cache / str(i))})
            for _ in range(args.repeat):
                for i, t in enumerate(trees):
                    times[t].append(run(t, full(i), {"NUMBA_CACHE_DIR": str(cache / str(i))})[0])
            for i, t in enumerate(trees):  # (after the timed runs: an earlier lab built its kernels differently here)
                mods[t] = run(t, full(i), {"NUMBA_CACHE_DIR": str(cache / str(i))}, count=True)[1]
            base = sorted(times[ROOT])[len(times[ROOT]) // 2]
            for t in trees:
                med = sorted(times[t])[len(times[t]) // 2]
                rows.append({"command": label, "checkout": names[t], "wall_s_median": med, "ratio_to_this": med / base,
                             "ibl_ref_modules": mods[t], "repeat": args.repeat})
                print(f"{label} | {names[t]}: {med:.3f} s ({med / base:.2f}×), {mods[t]} ibl_ref modules", flush=True)
    tail = f"Ended {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load avg {os.getloadavg()[0]:.2f}"
    lines = [head, "", "| command | checkout | wall s (median) | × this checkout | ibl_ref modules imported |",
             "|---|---|---|---|---|"]
    lines += [f"| {r['command']} | {r['checkout']} | {r['wall_s_median']:.3f} | {r['ratio_to_this']:.2f} | "
              f"{r['ibl_ref_modules']} |" for r in rows]
    lines += ["", tail]
    print("\n".join(lines))
    imports = [{"checkout": names[t], **import_counts(t / "ibl_ref")} for t in trees]
    lines += ["", "| checkout | internal imports | inside functions | share |", "|---|---|---|---|"]
    lines += [f"| {q['checkout']} | {q['internal_imports']} | {q['inside_functions']} | {q['share_inside_functions']} |"
              for q in imports]
    print("\n".join(lines[-len(imports) - 2:]))
    if args.markdown:
        with atomic_write(args.markdown) as fh:
            fh.write("\n".join(lines) + "\n")
    if args.csv:
        write_csv(args.csv, rows)
    if args.save_dir:
        import json

        d = Path(args.save_dir)
        d.mkdir(parents=True, exist_ok=True)
        write_csv(d / "startup.csv", [{**r, "wall_s_median": f"{r['wall_s_median']:.3f}",
                                       "ratio_to_this": f"{r['ratio_to_this']:.2f}"} for r in rows],
                  comment="bench_startup.py: median wall seconds of whole processes, ratio to this version, ibl_ref "
                          "modules the process imported")
        write_csv(d / "imports.csv", imports, comment="internal (ibl_ref) import statements of the package, and those "
                                                      "inside functions (an AST count of ibl_ref/)")
        meta = {"title": "Start-up", "runs": [{"files": ["startup.csv", "imports.csv"], "what": "one run of "
                "bench_startup.py", "command": head.split("`")[1], "commit": head.split("`")[3],
                "date": head.split("started ")[1].split(",")[0],
                "load": f"{load0:.2f} at the start, {os.getloadavg()[0]:.2f} at the end"}]}
        with atomic_write(d / "run.json") as fh:
            json.dump(meta, fh, indent=1, ensure_ascii=False)
            fh.write("\n")


if __name__ == "__main__":
    main()
