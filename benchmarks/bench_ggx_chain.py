"""The exact GGX level chain (``ibl-ref prefilter``) against Filament's ``cmgen`` and against the dense texel sum.

Run:  python benchmarks/bench_ggx_chain.py [--probe ../shared/probes/courtyard.exr] [--sizes 256 512] [--repeat 3]
      [--dense-sizes 64 128] [--rtol 1e-3] [--cmgen /usr/bin/cmgen] [--markdown F.md] [--csv F.csv]
      [--save-dir tests/data/readme_runs/ggx-chain]

For each environment (the synthetic sky with a 1e5 sun, and ``--probe`` read by the lab's reader and resampled) and
each base face size N of ``--sizes`` it writes the cube once as the lab's OpenEXR cube and as cmgen's input (its
horizontal cross, ``ibl_ref.prefilter.cmgen_peer.write_input``), then times, side by side and in turn (round
robin, median of ``--repeat``):

* ``cmgen --size=N`` (its default 1024 samples, levels down to 16², Filament's mapping) as a program;
* ``python -m ibl_ref prefilter IN OUT --size N --mapping filament --rtol R``: the same levels, each the exact
  n = v = r prefilter within R at every texel (the compiled kernels, 2 threads), reading and writing its files.

Beside the times: cmgen's largest, 99th-percentile and mean relative error per level against the lab's chain (the
lab's maps are within R of exact, so cmgen's error is known to ± R), and the lab's largest bound and seconds per
level.  Wall and CPU seconds (children's CPU from ``resource``); the load (1-minute average) per cell.

``--dense-sizes``: the baseline the tree replaces, in this process: for each size, the same Filament chain by
:func:`ibl_ref.prefilter.karis2013.prefilter_dense` (the dense texel sum, exact to float64 rounding) and by
:func:`ibl_ref.groundtruth.ggx_convolution.convolve_ggx_levels` (compiled, after one warm-up call), with the
tree's largest error against the dense sum next to its bound (an independent check at sizes the tests do not reach).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import resource
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ibl_ref.atomic import atomic_write, write_csv
from ibl_ref.environment.exr_io import load_cube, write_envmap
from ibl_ref.groundtruth.ggx_convolution import LAST_INFO, convolve_ggx_levels
from ibl_ref.prefilter import cmgen_peer as cg
from ibl_ref.prefilter.karis2013 import prefilter_dense, roughness_of_level
from ibl_ref.synthetic.synthetic_envs import env_sky_sun


def _timed(cmd, env=None):
    """(wall s, CPU s of the child, completed process)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"{cmd[0]} failed ({proc.returncode}): {proc.stderr.strip()[-400:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), proc


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).parent).stdout.strip() or "unknown"
    except OSError:
        return "unknown"


def _envs(n, probe):
    envs = {"sky+sun": env_sky_sun(n)}
    if probe:
        envs[Path(probe).stem] = load_cube(probe, size=n, negative="clamp")
    return envs


def filament_levels(n, min_size=16):
    """[(roughness, face size)] of cmgen's chain of an n² source below level 0 (Filament's mapping)."""
    n_levels = cg.cmgen_levels(n, min_size)
    rough = roughness_of_level(np.arange(n_levels), n_levels, "filament")
    return [(float(rough[lv]), max(n >> lv, 1)) for lv in range(1, n_levels)]


def run_cell(name, cube, n, args, work):
    inp_lab = work / f"{name}{n}.exr"
    inp_cmgen = work / f"{name}{n}_cross.exr"
    write_envmap(inp_lab, cube.astype(np.float32), layout="cube")
    cg.write_input(inp_cmgen, cube.astype(np.float32))
    out_lab = work / f"lab{n}" / "chain.exr"
    out_cmgen = work / f"cmgen{n}"
    lab_cmd = [sys.executable, "-m", "ibl_ref", "prefilter", str(inp_lab), str(out_lab), "--size", str(n),
               "--mapping", "filament", "--rtol", str(args.rtol), "--threads", "2", "--kernel", "compiled"]
    cmgen_cmd = cg.cmgen_command(args.cmgen, inp_cmgen, out_cmgen, n)
    times = {"lab": [], "cmgen": []}
    for _ in range(args.repeat):
        for who, cmd in (("cmgen", cmgen_cmd), ("lab", lab_cmd)):
            if who == "cmgen":
                shutil.rmtree(out_cmgen, ignore_errors=True)
                out_cmgen.mkdir()
            wall, cpu, _proc = _timed(cmd)
            times[who].append((wall, cpu))
    side = json.loads(out_lab.with_suffix(".json").read_text())
    n_levels = len(side["levels"])
    cm = cg.read_levels(out_cmgen / inp_cmgen.stem, n_levels, n)
    med = {who: (statistics.median(w for w, _ in t), statistics.median(c for _, c in t)) for who, t in times.items()}
    cell = {"env": name, "face_size_texels": n, "levels": n_levels, "cmgen_wall_s": med["cmgen"][0],
            "cmgen_cpu_s": med["cmgen"][1], "lab_wall_s": med["lab"][0], "lab_cpu_s": med["lab"][1],
            "lab_over_cmgen_wall": med["lab"][0] / med["cmgen"][0],
            "lab_tree_s": side["seconds"]["tree"], "lab_total_in_process_s": side["seconds"]["total"],
            "load_1min": os.getloadavg()[0]}
    rows = []
    for e in side["levels"][1:]:
        lv = e["level"]
        lab = load_cube(out_lab.with_name(f"chain_l{lv}.exr")).astype(np.float64)
        rel = np.abs(cm[lv].astype(np.float64) - lab) / np.maximum(lab, 1e-300)
        rows.append({"env": name, "face_size_texels": n, "level": lv, "roughness": e["roughness"],
                     "level_face_size_texels": e["face_size"], "lab_rel_bound_max": e["rel_bound_max"],
                     "lab_level_s": e["seconds"], "cmgen_rel_err_max": float(rel.max()),
                     "cmgen_rel_err_p99": float(np.percentile(rel, 99)), "cmgen_rel_err_mean": float(rel.mean())})
    return cell, rows


def dense_cell(name, cube, n, rtol):
    """The Filament chain of one map by the tree (compiled, warm) and by the dense sum, in this process."""
    levels = filament_levels(n)
    convolve_ggx_levels(cube[:, ::max(n // 8, 1), ::max(n // 8, 1)], [(0.5, 4)], rtol=rtol, kernel="compiled")
    t0 = time.perf_counter()
    tree = convolve_ggx_levels(cube, levels, rtol=rtol, kernel="compiled", threads=2)
    tree_s = time.perf_counter() - t0
    info = dict(LAST_INFO)
    rows = []
    dense_total = 0.0
    for (r, m), (maps, bound), li in zip(levels, tree, info["levels"]):
        t0 = time.perf_counter()
        ref = prefilter_dense(cube, r, out_size=m)
        d = time.perf_counter() - t0
        dense_total += d
        rel = np.abs(maps - ref) / ref
        rows.append({"env": name, "face_size_texels": n, "roughness": r, "level_face_size_texels": m,
                     "dense_s": d, "tree_level_s": li["seconds"], "tree_rel_bound_max": float(bound.max()),
                     "tree_rel_err_vs_dense_max": float(rel.max()),
                     "within_bound": bool(np.all(rel.max(axis=-1) <= bound + 1e-12))})
    summary = {"env": name, "face_size_texels": n, "levels_below_0": len(levels), "dense_s": dense_total,
               "tree_s": tree_s, "dense_over_tree": dense_total / tree_s, "load_1min": os.getloadavg()[0]}
    return summary, rows


def _table(rows, cols):
    lines = ["| " + " | ".join(c for c, _ in cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r) for _, fmt in cols) + " |" for r in rows]
    return lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--probe", default=None, help="an HDR probe (read by the lab's reader, resampled per size)")
    ap.add_argument("--sizes", type=int, nargs="*", default=[256], help="base face sizes against cmgen")
    ap.add_argument("--dense-sizes", type=int, nargs="*", default=[], help="base face sizes against the dense sum")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--rtol", type=float, default=1e-3)
    ap.add_argument("--cmgen", default=shutil.which("cmgen") or "cmgen")
    ap.add_argument("--markdown", default=None)
    ap.add_argument("--csv", default=None, help="the cmgen cells as CSV")
    ap.add_argument("--save-dir", default=None,
                    help="write cells.csv, levels.csv, dense.csv, dense_levels.csv and run.json (the documentation's "
                         "layout, e.g. tests/data/readme_runs/ggx-chain; then python docs/make_results.py)")
    args = ap.parse_args(argv)
    argv = sys.argv[1:] if argv is None else argv
    started = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    load0 = os.getloadavg()[0]
    t_start = time.perf_counter()
    cells, levels, dense, dense_levels = [], [], [], []
    with tempfile.TemporaryDirectory(prefix="bench_ggx_chain_") as tmp:
        for n in args.sizes:
            for name, cube in _envs(n, args.probe).items():
                c, rows = run_cell(name, cube, n, args, Path(tmp))
                cells.append(c)
                levels += rows
                print(f"  {name} {n}²: cmgen {c['cmgen_wall_s']:.2f} s wall ({c['cmgen_cpu_s']:.2f} CPU), lab "
                      f"{c['lab_wall_s']:.2f} s wall ({c['lab_cpu_s']:.2f} CPU) = {c['lab_over_cmgen_wall']:.2f}× "
                      f"[load {c['load_1min']:.2f}]", flush=True)
    for n in args.dense_sizes:
        for name, cube in _envs(n, args.probe).items():
            s, rows = dense_cell(name, cube, n, args.rtol)
            dense.append(s)
            dense_levels += rows
            print(f"  {name} {n}² dense {s['dense_s']:.2f} s, tree {s['tree_s']:.2f} s = {s['dense_over_tree']:.1f}× "
                  f"[load {s['load_1min']:.2f}]", flush=True)
    head = (f"`python benchmarks/{Path(__file__).name} {shlex.join(argv)}` — commit {_commit()}, {started}, load "
            f"{load0:.2f} at the start, {os.getloadavg()[0]:.2f} at the end; median of {args.repeat}")
    lines = [head, ""]
    lines += _table(cells, [("env", lambda c: c["env"]), ("N", lambda c: str(c["face_size_texels"])),
                            ("levels", lambda c: str(c["levels"])),
                            ("cmgen wall s (CPU)", lambda c: f"{c['cmgen_wall_s']:.2f} ({c['cmgen_cpu_s']:.2f})"),
                            ("lab wall s (CPU)", lambda c: f"{c['lab_wall_s']:.2f} ({c['lab_cpu_s']:.2f})"),
                            ("lab / cmgen", lambda c: f"{c['lab_over_cmgen_wall']:.2f}×"),
                            ("load", lambda c: f"{c['load_1min']:.2f}")])
    lines += [""] + _table(levels, [("env", lambda r: r["env"]), ("N", lambda r: str(r["face_size_texels"])),
                                    ("level", lambda r: str(r["level"])), ("r", lambda r: f"{r['roughness']:.4f}"),
                                    ("face", lambda r: str(r["level_face_size_texels"])),
                                    ("lab bound", lambda r: f"{r['lab_rel_bound_max']:.2e}"),
                                    ("lab s", lambda r: f"{r['lab_level_s']:.2f}"),
                                    ("cmgen err max", lambda r: f"{r['cmgen_rel_err_max']:.3g}"),
                                    ("p99", lambda r: f"{r['cmgen_rel_err_p99']:.3g}"),
                                    ("mean", lambda r: f"{r['cmgen_rel_err_mean']:.3g}")])
    if dense:
        lines += [""] + _table(dense_levels, [
            ("env", lambda r: r["env"]), ("N", lambda r: str(r["face_size_texels"])),
            ("r", lambda r: f"{r['roughness']:.4f}"), ("face", lambda r: str(r["level_face_size_texels"])),
            ("dense s", lambda r: f"{r['dense_s']:.2f}"), ("tree s", lambda r: f"{r['tree_level_s']:.3f}"),
            ("bound", lambda r: f"{r['tree_rel_bound_max']:.2e}"),
            ("err vs dense", lambda r: f"{r['tree_rel_err_vs_dense_max']:.2e}"),
            ("within", lambda r: "yes" if r["within_bound"] else "NO")])
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        with atomic_write(args.markdown) as fh:
            fh.write(text + "\n")
    if args.csv:
        write_csv(args.csv, cells)
    if args.save_dir:
        d = Path(args.save_dir)
        d.mkdir(parents=True, exist_ok=True)
        files = []
        for fname, rows, comment in (
                ("cells.csv", cells, "bench_ggx_chain.py: whole processes, median wall / CPU seconds; lab = ibl-ref "
                                     "prefilter (exact within rtol), cmgen = Filament's cmgen --size=N"),
                ("levels.csv", levels, "per level: the lab's largest relative bound and seconds, cmgen's relative "
                                       "error against the lab's chain (max, 99th percentile, mean over texels and "
                                       "channels)"),
                ("dense.csv", dense, "in-process seconds of the whole chain: the dense texel sum and the tree"),
                ("dense_levels.csv", dense_levels, "per level: the tree's largest error against the dense sum, "
                                                   "and its bound")):
            if rows:
                write_csv(d / fname, rows, comment=comment)
                files.append(fname)
        meta = {"title": "Exact GGX prefiltering at engine sizes",
                "runs": [{"files": files, "what": "one run of bench_ggx_chain.py",
                          "command": f"python benchmarks/{Path(__file__).name} {shlex.join(argv)}",
                          "commit": _commit(), "date": started,
                          "wall": f"{time.perf_counter() - t_start:.0f} s",
                          "load": f"{load0:.2f} at the start, {os.getloadavg()[0]:.2f} at the end",
                          "machine": f"{os.cpu_count()} CPUs"}]}
        with atomic_write(d / "run.json") as fh:
            json.dump(meta, fh, indent=1, ensure_ascii=False)
            fh.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
