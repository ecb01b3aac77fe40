"""Benchmark of ibl_ref.groundtruth.convolve: ``auto`` vs ``exact`` at 64² (same run) and the 128² targets.

Usage: OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python benchmarks/bench_convolution.py [--skip-128]
       [--without-s1] [--workers W] [--repeat R] [--check-128] [--exact-128]

Environment: the synthetic sky + 1e5 sun 0.0015 rad from a cube corner (``make_env("sky_sun", ...)``).
Prints, at 64² faces and exponents {1, 4, 16, 64, 256, 1024, 4096}: the time of ``auto`` (rtol 1e-3) and
of ``exact`` measured in the same run, their ratio, and auto's max / mean relative error per exponent
against exact.  Then the 128² targets: one exponent s = 16 (target ≤ 3 s) and the 8 exponents
{1, 2, 5, 10, 20, 50, 100, 1000} (target ≤ 6.4 s wall on 2 cores), run with ``workers = W``
(default :func:`ibl_ref.groundtruth.convolve.default_workers`) on the ``--backend`` (default auto = forked
processes), with W threads and serially (``workers = 1``), R times each (min and all runs printed), and
whether all give bit-for-bit identical maps.  CPU times are process + forked-worker CPU.  ``--check-128`` compares
the 8-exponent result with the moment route (s = 1, 2; exact up to rounding) and reports the bounds of
the others; ``--exact-128`` compares all 8 with :func:`convolve_exact_many` (several minutes).
Timings are wall clock on whatever machine runs this, printed as wall clock and as process CPU time (all
threads); the 1-minute load average is printed before and after — quote it with the timings.

``--probes [DIR]`` instead times ``auto`` against forced methods on every real probe in DIR (default
``../shared/probes`` next to the repository) at native size (1024×512 lat-long → 256² faces), exponents
``--probe-exponents`` (default 1 16 256), rtol 1e-3, ``--workers`` (default 2), for ``--kernel`` (numpy and
compiled by default; ``--forced sh sparse`` chooses the forced methods; exact is reported by its model cost only):
wall and CPU seconds, whether every bound meets rtol, the route ``auto`` took and the ratio auto ÷ the fastest
forced method that meets rtol and ÷ the fastest forced method at all; printed as a markdown table.
The repository root is put first on ``sys.path`` so that the working tree is measured, not an
installed copy of ``ibl_ref``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from ibl_ref.groundtruth.convolve import convolve, default_workers  # noqa: E402
from ibl_ref.experiments.speed_accuracy import environment  # noqa: E402
from ibl_ref.groundtruth.phong_convolution import convolve_exact_many  # noqa: E402

S7 = [1.0, 4.0, 16.0, 64.0, 256.0, 1024.0, 4096.0]
S8 = [1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 1000.0]


def _load():
    try:
        return f"load avg {os.getloadavg()[0]:.2f} (1 min) on {os.cpu_count()} CPUs"
    except OSError:
        return "load avg n/a"


def _timed(fn):
    t0, c0 = time.perf_counter(), time.process_time()
    r = fn()
    return r, time.perf_counter() - t0, time.process_time() - c0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--skip-128", action="store_true")
    ap.add_argument("--without-s1", action="store_true", help="drop s = 1 from the 128² eight-exponent target")
    ap.add_argument("--workers", type=int, default=None, help="workers of the timed auto runs (default: ibl_ref.groundtruth.convolve.default_workers)")
    ap.add_argument("--repeat", type=int, default=2, help="repetitions of the 128² eight-exponent timing")
    ap.add_argument("--backend", default="auto", choices=("auto", "process", "thread"),
                    help="parallel back-end of the main timed runs (threads are always timed too)")
    ap.add_argument("--check-128", action="store_true", help="check the 128² result against the moment route")
    ap.add_argument("--exact-128", action="store_true", help="check the 128² result against exact (minutes)")
    ap.add_argument("--exact-cache", type=Path, default=None, metavar="NPY",
                    help="with --exact-128: load the 128² exact maps from NPY if it exists, else compute and save")
    ap.add_argument("--probes", nargs="?", const=str(Path(__file__).resolve().parents[2] / "shared" / "probes"),
                    default=None, metavar="DIR", help="time auto against forced methods on the probes in DIR")
    ap.add_argument("--probe-exponents", type=float, nargs="+", default=[1.0, 16.0, 256.0])
    ap.add_argument("--kernel", action="append", choices=("numpy", "compiled"))
    ap.add_argument("--forced", nargs="+", default=["sh", "split"], choices=("sh", "sparse", "exact", "moment", "split"),
                    help="forced methods to time against auto; split = moment for s = 1, 2 and sh for the rest, "
                         "two calls (what a user forcing methods exponent by exponent would run)")
    args = ap.parse_args()
    if args.probes:
        return probe_routing(args)
    W = args.workers if args.workers is not None else default_workers()
    print(f"ibl_ref from {Path(sys.modules['ibl_ref'].__file__).parent}; workers = {W}; {_load()}")
    convolve(environment(4), [2.0, 64.0])  # warm-up (imports)

    cube = environment(64)
    res, t_auto, _ = _timed(lambda: convolve(cube, S7, method="auto", rtol=1e-3, workers=W, backend=args.backend))
    c_auto = res.timings_s["total_cpu"]
    ref, t_exact, c_exact = _timed(lambda: convolve_exact_many(cube, S7))
    print(f"64² faces, {len(S7)} exponents: auto {t_auto:.2f} s wall / {c_auto:.2f} s CPU (workers {W}, "
          f"{res.info['backend']}), exact "
          f"{t_exact:.2f} s wall / {c_exact:.2f} s CPU (dense gather, BLAS threads as configured); exact/auto = {t_exact / t_auto:.2f}x wall, "
          f"{c_exact / c_auto:.2f}x CPU")
    for k, s in enumerate(S7):
        rel = (np.abs(res.maps[s] - ref[k]) / ref[k]).max(axis=-1)
        print(f"  s={s:g}: {res.method_used[s]:6s} rel err max {rel.max():.2e} mean {rel.mean():.2e} "
              f"(bound max {res.error_bound[s].max():.2e})")
    print(f"  auto stage times: {', '.join(f'{k} {v:.2f} s' for k, v in res.timings_s.items())}")

    if args.skip_128:
        return
    cube = environment(128)
    res, t16, _ = _timed(lambda: convolve(cube, [16.0], rtol=1e-3, workers=W, backend=args.backend))
    c16 = res.timings_s["total_cpu"]
    print(f"128² faces, s=16: auto {t16:.2f} s wall / {c16:.2f} s CPU, workers {W} (target ≤ 3 s) via "
          f"{res.method_used[16.0]}, bound max {res.error_bound[16.0].max():.1e}")
    res, t1, _ = _timed(lambda: convolve(cube, [1.0], rtol=1e-3, workers=W, backend=args.backend))
    c1 = res.timings_s["total_cpu"]
    print(f"128² faces, s=1: auto {t1:.2f} s wall / {c1:.2f} s CPU, workers {W}, via {res.method_used[1.0]}, "
          f"bound max {res.error_bound[1.0].max():.1e}")
    s8 = S8[1:] if args.without_s1 else S8
    runs = {}
    configs = list(dict.fromkeys([(W, args.backend), (W, "thread"), (1, "auto")]))
    for rep in range(max(1, args.repeat)):
        for cfg in configs:
            load = _load()
            r, t8, _c8 = _timed(lambda: convolve(cube, s8, rtol=1e-3, workers=cfg[0], backend=cfg[1]))
            runs.setdefault(cfg, []).append((t8, r.timings_s["total_cpu"], load, r.info["backend"]))
            runs.setdefault(("res", cfg), r)
    for cfg in configs:
        ts = runs[cfg]
        print(f"128² faces, exponents {[f'{s:g}' for s in s8]}, workers {cfg[0]} ({ts[0][3]}): auto min "
              f"{min(t for t, _, _, _ in ts):.2f} s wall (target ≤ 6.4 s for all 8 on 2 cores); runs: "
              + "; ".join(f"{t:.2f} s wall / {c:.2f} s CPU [{ld}]" for t, c, ld, _ in ts))
    res = runs[("res", configs[0])]
    same = all(np.array_equal(res.maps[s], runs[("res", cfg)].maps[s])
               and np.array_equal(res.error_bound[s], runs[("res", cfg)].error_bound[s])
               for s in s8 for cfg in configs)
    print(f"  all configurations {configs}: maps and bounds bit-for-bit identical: {same}")
    print("  methods: " + ", ".join(f"{s:g}:{res.method_used[s]}" for s in s8))
    print(f"  stage times (workers {W}, {res.info['backend']}; per-stage = summed job time): "
          f"{', '.join(f'{k} {v:.2f} s' for k, v in res.timings_s.items())}")
    print("  bound max per exponent: " + ", ".join(f"{s:g}:{float(res.error_bound[s].max()):.1e}" for s in s8))
    if args.check_128 or args.exact_128:
        from ibl_ref.groundtruth.moment_convolution import convolve_moment_many

        if args.exact_128 and args.exact_cache is not None and args.exact_cache.exists():
            ref = np.load(args.exact_cache)
            label = f"exact (cached in {args.exact_cache})"
        elif args.exact_128:
            ref, t_ex, _ = _timed(lambda: convolve_exact_many(cube, s8))
            label = f"exact ({t_ex:.0f} s wall)"
            if args.exact_cache is not None:
                from ibl_ref.atomic import atomic_path

                with atomic_path(args.exact_cache) as tmp:
                    np.save(tmp, ref)
        else:
            mo = [s for s in s8 if s in (1.0, 2.0)]
            ref = dict(zip(mo, convolve_moment_many(cube, mo, leaf=1)[0]))
            label = "moment route leaf=1 (exact up to rounding) for s = 1, 2"
        print(f"  128² check against {label}:")
        for k, s in enumerate(s8):
            rk = ref[k] if args.exact_128 else ref.get(s)
            if rk is None:
                continue
            rel = (np.abs(res.maps[s] - rk) / rk).max(axis=-1)
            print(f"    s={s:g}: {res.method_used[s]:6s} rel err max {rel.max():.2e} mean {rel.mean():.2e} "
                  f"(bound max {res.error_bound[s].max():.2e}; err ≤ bound at every texel: "
                  f"{bool(np.all(rel <= res.error_bound[s] + 1e-12))})")
    print(f"done; {_load()}")


def probe_routing(args):
    """``--probes``: auto against forced methods on real probes (markdown table)."""
    import subprocess

    from ibl_ref.environment.exr_io import load_cube
    from ibl_ref.groundtruth.convolve import plan_routes

    W = args.workers if args.workers is not None else 2
    kernels = args.kernel or ["numpy", "compiled"]
    files = sorted(Path(args.probes).glob("*.exr"))
    if not files:
        raise SystemExit(f"no .exr probes in {args.probes}")
    commit = subprocess.run(["git", "-C", str(Path(__file__).resolve().parents[1]), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip()
    ss = args.probe_exponents
    print(f"command: python benchmarks/bench_convolution.py --probes {args.probes} --probe-exponents "
          f"{' '.join(f'{s:g}' for s in ss)} --workers {W}; commit {commit}; {_load()}")
    print()
    print("| probe | kernel | method | routes | wall s | CPU s | largest bound | meets rtol | auto ÷ fastest forced "
          "meeting rtol | auto ÷ fastest forced |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for f in files:
        cube = load_cube(f)
        for k in kernels:
            convolve(environment(8), [2.0, 64.0], kernel=k)  # warm-up: imports, compiled code
            rows = {}
            for m in ["auto"] + list(args.forced):
                if m == "moment" and any(s not in (1.0, 2.0) for s in ss):
                    continue
                groups = ([("moment", [s for s in ss if s in (1.0, 2.0)]), ("sh", [s for s in ss if s not in (1.0, 2.0)])]
                          if m == "split" else [(m, ss)])
                t = c = 0.0
                bounds, used = {}, {}
                for mm, sub in groups:
                    if not sub:
                        continue
                    r, tt, _ = _timed(lambda: convolve(cube, sub, method=mm, rtol=1e-3, workers=W, kernel=k))
                    t, c = t + tt, c + r.timings_s["total_cpu"]
                    bounds.update({s: float(np.max(r.error_bound[s])) for s in sub})
                    used.update(r.method_used)
                b = max(bounds.values())
                rows[m] = (t, c, b, b <= 1e-3, ", ".join(f"{s:g}:{used[s]}" for s in ss))
                print(f"  {f.stem} {k} {m}: {t:.1f} s wall, {rows[m][1]:.1f} s CPU, bound {b:.1e} [{_load()}]",
                      file=sys.stderr, flush=True)
            model = plan_routes(cube, ss, rtol=1e-3, kernel=k)["model_costs_s"]
            ok = [v[0] for m, v in rows.items() if m != "auto" and v[3]]
            anyf = [v[0] for m, v in rows.items() if m != "auto"]
            for m, (t, c, b, good, routes) in rows.items():
                r1 = (f"{rows['auto'][0] / min(ok):.2f}" if ok else "—") if m == "auto" else ""
                r2 = f"{rows['auto'][0] / min(anyf):.2f}" if m == "auto" and anyf else ""
                print(f"| {f.stem} | {k} | {m} | {routes} | {t:.1f} | {c:.1f} | {b:.1e} | {'yes' if good else 'no'} | "
                      f"{r1} | {r2} |")
            print(f"| {f.stem} | {k} | exact (model only) | | {model.get('exact', float('nan')):.0f} | | | | | |")
    print()
    print(f"done; {_load()}")


if __name__ == "__main__":
    main()
