"""``ibl-ref experiment NAME`` and ``ibl-ref reproduce``: run the figure experiments.

Every experiment gets its own sub-parser, built from its declarations (:mod:`ibl_ref.experiments`): its
``--help`` shows the description, the paper item, the typical run time, the outputs and one ``--PARAM``
option per parameter (default and quick value).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .. import experiments


def _run_one(mod, out: Path, quick: bool, overrides: dict | None = None) -> dict:
    from ..atomic import ensure_output_dir

    ensure_output_dir(out, "--out folder")  # under a file / read-only: one-line error, no traceback
    return experiments.run_experiment(mod, out, quick, overrides)


def experiment_parser(mod, defaults=None) -> argparse.ArgumentParser:
    """The parser of ``ibl-ref experiment NAME``: common options plus one ``--PARAM`` per parameter."""
    d = defaults or {}
    e = argparse.ArgumentParser(prog=f"ibl-ref experiment {mod.NAME}", description=experiments.describe(mod),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    e.add_argument("--out", default=d.get("out", "results"), help="output folder (default: results)")
    e.add_argument("--quick", action="store_true", default=d.get("quick", False),
                   help="quick sizes (the parameters' quick values) for a fast run")
    e.add_argument("--no-subdir", dest="subdir", action="store_false", default=d.get("subdir", True),
                   help="write directly into --out instead of --out/NAME")
    g = e.add_argument_group("parameters of this experiment (default = full run; quick = with --quick)")
    for prm in getattr(mod, "PARAMS", ()):
        q = "" if prm.quick is None else f"; quick: {experiments._fmt(prm.quick)}"
        g.add_argument(f"--{prm.flag}", dest=f"param_{prm.name}", metavar="V",
                       help=f"{prm.help} (default: {experiments._fmt(prm.default)}{q})".replace("%", "%%"))
    return e


def _overrides(mod, args) -> dict:
    out = {}
    for p in getattr(mod, "PARAMS", ()):
        text = getattr(args, f"param_{p.name}", None)
        if text is not None:
            out[p.name] = p.parse(text)
    return out


def cmd_experiment(args) -> int:
    if args.list or not getattr(args, "name", None):
        for name, mod in experiments.available().items():
            print(f"{name:16s} {getattr(mod, 'DESCRIPTION', '')}")
        return 0
    mod = experiments.get(args.name)
    args = experiment_parser(mod, vars(args)).parse_args(args.rest)
    out = Path(args.out) / mod.NAME if args.subdir else Path(args.out)
    res = _run_one(mod, out, args.quick, _overrides(mod, args))
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
        print(f"    {mod.NAME} done in {res['compute_time_s'] + res['plot_time_s']:.1f} s; "
              f"figures: {', '.join(res['figures']) or '-'}", flush=True)
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
        description="Run one experiment: compute its data into CSV/JSON under --out, then plot PNG "
        "figures from those files. 'ibl-ref experiment --list' shows the experiments, "
        "'ibl-ref experiment NAME --help' what one reproduces, its parameters, outputs and run time.",
    )
    p.add_argument("name", nargs="?", help="experiment name (see --list); 'NAME --help' for its parameters")
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    p.add_argument("--out", default="results", help="output folder (default: results)")
    p.add_argument("--quick", action="store_true", help="quick sizes for a fast run (seconds to a minute)")
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
