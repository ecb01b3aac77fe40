"""Filament's cmgen against the lab's exact n = v = r GGX prefilter, per level (ibl_ref.prefilter.cmgen_peer).

Run:  python benchmarks/bench_cmgen.py [--probe ../shared/probes/courtyard.exr] [--faces 16 32] [--min-level 16 1]
      [--no-prefilter]

For each environment (a smooth synthetic map, exp(1.2x + 0.6y − 0.9z + 0.5xz) per channel, and optionally a probe
read with the lab's reader and resampled to the face size) and each (face size, min level size) it runs cmgen once
(1024 samples; ``--no-prefilter``: also with cmgen's ``--ibl-no-prefilter``), then compares every level with
:func:`ibl_ref.prefilter.karis2013.prefilter_exact` at the level's roughness r = 1 − √(1 − l/(L − 1)) and face
size (a dense sum: keep faces ≤ 32²).  Columns: the largest and the mean relative error per texel and channel, the
largest absolute error over the level's largest exact value; for the synthetic map also the largest relative
error against the exact prefilter of the map read at cmgen's half-texel-displaced source directions
(``cmgen_source_directions``), which separates cmgen's sampling error from its source displacement.  Prints a
Markdown table with the command, commit, date and load; writes nothing.
"""

from __future__ import annotations

import argparse
import datetime
import os
import subprocess
import sys
import time

import numpy as np

from ibl_ref.environment import envmap
from ibl_ref.environment.exr_io import load_cube
from ibl_ref.prefilter import cmgen_peer as cg
from ibl_ref.prefilter.karis2013 import prefilter_exact


def smooth(d):
    base = np.exp(1.2 * d[..., 0] + 0.6 * d[..., 1] - 0.9 * d[..., 2] + 0.5 * d[..., 0] * d[..., 2])
    return base[..., None] * np.array([1.0, 0.5, 0.25])


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--probe", default="", help="an environment file (read with the lab's reader, resampled)")
    ap.add_argument("--faces", type=int, nargs="+", default=[16, 32])
    ap.add_argument("--min-level", type=int, nargs="+", default=[16, 1])
    ap.add_argument("--samples", type=int, default=cg.DEFAULT_SAMPLES)
    ap.add_argument("--no-prefilter", action="store_true", help="also run cmgen with --ibl-no-prefilter")
    args = ap.parse_args(argv)
    start = datetime.datetime.now(datetime.timezone.utc)
    load = os.getloadavg()[0]
    rows = []
    for n in args.faces:
        envs = [("smooth", smooth(envmap.texel_directions(n)), smooth(cg.cmgen_source_directions(n)))]
        if args.probe:
            envs.append((os.path.basename(args.probe), load_cube(args.probe, size=n), None))
        for m, pre, (name, cube, displaced) in ((m, pre, e) for m in args.min_level
                                                for pre in ((True, False) if args.no_prefilter else (True,))
                                                for e in envs):
                t0 = time.perf_counter()
                run = cg.run_cmgen(cube, samples=args.samples, min_level_size=m, prefiltered=pre)
                wall = time.perf_counter() - t0
                errs = cg.level_errors(cube, run)
                for e in errs:
                    extra = ""
                    if displaced is not None:
                        k = e["level"]
                        ref = displaced if k == 0 else prefilter_exact(
                            displaced, float(cg.filament_roughness_of_level(k, run.n_levels)),
                            out_size=run.levels[k].shape[1])
                        extra = f"{float(np.max(np.abs(run.levels[k] - ref) / ref)):.2e}"
                    rows.append((name + ("" if pre else " (no prefilter)"), n, m, run.n_levels, e["level"], e["face"],
                                 e["roughness"], e["max_rel"], e["mean_rel"], e["max_abs_of_max"], extra,
                                 run.seconds, wall))
    print(f"Command: `python benchmarks/bench_cmgen.py {' '.join(sys.argv[1:] if argv is None else argv)}`; commit "
          f"`{_commit()}`; {start:%Y-%m-%d %H:%M} UTC, load avg {load:.2f} (1 min) on {os.cpu_count()} CPUs.\n")
    print("| environment | face | min level | L | level | level face | r | max rel | mean rel | max abs / max | "
          "max rel vs displaced source | cmgen s (wall) | run_cmgen s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} | {r[4]} | {r[5]} | {r[6]:.3g} | {r[7]:.2e} | {r[8]:.2e} | "
              f"{r[9]:.2e} | {r[10] or '–'} | {r[11]:.2f} | {r[12]:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
