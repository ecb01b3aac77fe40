"""``ibl-ref experiment NAME`` and ``ibl-ref reproduce``: run the figure experiments."""

from __future__ import annotations

import json
import time
from pathlib import Path

from .. import experiments


def _run_one(mod, out: Path, quick: bool) -> dict:
    from ..atomic import ensure_output_dir

    ensure_output_dir(out, "--out folder")  # under a file / read-only: one-line error, no traceback
    t0 = time.perf_counter()
    summary = mod.run(out, quick=quick) or {}
    t1 = time.perf_counter()
    figs = mod.plot(out) or []
    t2 = time.perf_counter()
    return {"experiment": mod.NAME, "quick": quick, "compute_time_s": round(t1 - t0, 3),
            "plot_time_s": round(t2 - t1, 3), "figures": [str(f) for f in figs], "summary": summary}


def cmd_experiment(args) -> int:
    if args.list or not args.name:
        for name, mod in experiments.available().items():
            print(f"{name:16s} {getattr(mod, 'DESCRIPTION', '')}")
        return 0
    mod = experiments.get(args.name)
    out = Path(args.out) / mod.NAME if args.subdir else Path(args.out)
    res = _run_one(mod, out, args.quick)
    print(json.dumps({k: v for k, v in res.items() if k != "summary"}, indent=1))
    print(f"results in {out}")
    return 0


def _copy_gallery(results, folder: Path) -> list:
    """Copy every experiment's PNG figures to ``folder/NAME__FIGURE.png`` (stable names, atomic)."""
    from ..atomic import atomic_write

    out = []
    for res in results:
        for fig in res["figures"]:
            src = Path(fig)
            if src.suffix.lower() != ".png":
                continue
            dst = folder / f"{res['experiment']}__{src.name}"
            with atomic_write(dst, "wb") as fh:
                fh.write(src.read_bytes())
            out.append(dst)
    return out


def cmd_reproduce(args) -> int:
    from ..atomic import write_json

    out = Path(args.out)
    exps = experiments.available()
    chosen = [m for m in exps.values() if not args.quick or getattr(m, "IN_QUICK_REPRODUCE", True)]
    print(f"ibl-ref reproduce: {len(chosen)} experiment(s) into {out} ({'quick' if args.quick else 'full'} sizes)")
    results = []
    for i, mod in enumerate(chosen, 1):
        print(f"[{i}/{len(chosen)}] {mod.NAME}: {getattr(mod, 'DESCRIPTION', '')}", flush=True)
        res = _run_one(mod, out / mod.NAME, args.quick)
        print(f"    done in {res['compute_time_s'] + res['plot_time_s']:.1f} s; figures: {', '.join(res['figures']) or '-'}")
        results.append(res)
    skipped = sorted(set(exps) - {m.NAME for m in chosen})
    write_json(out / "reproduce_summary.json", {"quick": args.quick, "runs": results, "skipped_in_quick": skipped})
    if args.gallery:
        gallery = _copy_gallery(results, Path(args.gallery))
        print(f"gallery: {len(gallery)} figure(s) in {args.gallery}")
    if skipped:
        print(f"not run at quick size (run 'ibl-ref experiment NAME'): {', '.join(skipped)}")
    print(f"summary: {out / 'reproduce_summary.json'}")
    return 0


def register(sub) -> None:
    p = sub.add_parser(
        "experiment",
        help="run one experiment (a paper figure or a speed/accuracy study) and plot it",
        description="Run one experiment: compute its data into CSV/JSON under --out, then plot PNG/PDF "
        "figures from those files. 'ibl-ref experiment --list' shows the experiments.",
    )
    p.add_argument("name", nargs="?", help="experiment name (see --list)")
    p.add_argument("--out", default="results", help="output folder (default: results)")
    p.add_argument("--quick", action="store_true", help="small sizes for a fast run (seconds to a minute)")
    p.add_argument("--list", action="store_true", help="list the experiments and exit")
    p.add_argument("--no-subdir", dest="subdir", action="store_false",
                   help="write directly into --out instead of --out/NAME")
    p.set_defaults(func=cmd_experiment)

    r = sub.add_parser(
        "reproduce",
        help="run every experiment (the paper's figures) into one folder",
        description="Run all experiments one after another, each into OUT/NAME, and write "
        "OUT/reproduce_summary.json with timings and figure paths.",
    )
    r.add_argument("--out", default="results", help="output folder (default: results)")
    r.add_argument("--quick", action="store_true", help="quick sizes (the README's first command)")
    r.add_argument("--gallery", metavar="DIR",
                   help="also copy every PNG figure to DIR as EXPERIMENT__FIGURE.png (the README gallery: docs/gallery)")
    r.set_defaults(func=cmd_reproduce)
