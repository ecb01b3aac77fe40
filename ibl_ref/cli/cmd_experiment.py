"""``ibl-ref experiment NAME`` and ``ibl-ref reproduce``: run the figure experiments.

Every experiment gets its own sub-parser, built from its declarations (:mod:`ibl_ref.experiments`): its
``--help`` shows the description, the paper item, the typical run time, the outputs and one ``--PARAM``
option per parameter (default and quick value).  ``--workers N`` / ``--scheduler ADDRESS`` run the independent
jobs (an experiment's cases, or ``reproduce``'s experiments) on local processes or a Dask cluster
(:func:`ibl_ref.executors.map_jobs`); ``reproduce`` is :func:`ibl_ref.experiments.reproduce`.  An interrupted
``experiment`` keeps the jobs it finished for the next run of the same command
(:func:`ibl_ref.experiments.run_experiment`); ``--fresh`` discards them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .. import experiments


#: the common end of every ``ibl-ref experiment NAME --help`` (one line, like the lines of the description)
EXPERIMENT_EPILOG = (
    "Interrupted runs lose no finished job: while the experiment runs, each independent job it finishes (a case, a "
    "block of a reference image) is kept in .jobs-{name} inside its output folder; the same command run again takes "
    "those results (one line says how many) and runs only the others, with the same data files as a run without "
    "interruption. The folder is removed once the outputs are in place; results of other code (another version of "
    "ibl_ref or NumPy) are never used; --fresh discards them.")


def _run_one(mod, out: Path, quick: bool, overrides: dict | None = None, fresh: bool = False, **jobs) -> dict:
    from ..atomic import output_folder

    # under a file / read-only: one-line error, no traceback; a failed run leaves no folder it created, but for the
    # jobs it finished (experiments.job_store_folder)
    with output_folder(out, "--out folder", remove_tree=True, keep=experiments.job_store_folder(mod, out).is_dir):
        return experiments.run_experiment(mod, out, quick, overrides, fresh=fresh, **jobs)


def _jobs(args) -> dict:
    """``executor=`` / ``workers=`` of :func:`ibl_ref.executors.map_jobs` from ``--scheduler`` / ``--workers``."""
    from ..errors import IBLError

    workers = getattr(args, "workers", None)
    scheduler = getattr(args, "scheduler", None)
    if workers is not None and scheduler is not None:
        raise IBLError("--workers and --scheduler exclude each other (a scheduler's workers are set where it runs)")
    if workers is not None and workers < 1:
        raise IBLError(f"--workers: must be a positive integer, got {workers}")
    return dict(executor=scheduler, workers=workers or 1)


def _add_job_options(p, d=None, note=None) -> None:
    d = d or {}
    note = note or ""
    p.add_argument("--workers", type=int, default=d.get("workers"), metavar="N",
                   help=f"run the independent jobs on N local processes (default: serially){note}")
    p.add_argument("--scheduler", default=d.get("scheduler"), metavar="ADDRESS",
                   help=f"run the independent jobs on a Dask cluster (e.g. tcp://host:8786; pip install '.[dask]'){note}")


def _add_fresh_option(p, d=None, name: str = "NAME") -> None:
    p.add_argument("--fresh", action="store_true", default=(d or {}).get("fresh", False),
                   help=f"discard the jobs an interrupted run kept (.jobs-{name} in the output folder) and run every "
                   "job again")


def experiment_parser(mod, defaults=None) -> argparse.ArgumentParser:
    """The parser of ``ibl-ref experiment NAME``: common options plus one ``--PARAM`` per parameter."""
    d = defaults or {}
    from . import _Parser  # the one usage-error path of the command line: one line naming the flag

    e = _Parser(prog=f"ibl-ref experiment {mod.NAME}", description=experiments.describe(mod),
                epilog=EXPERIMENT_EPILOG.format(name=mod.NAME), formatter_class=argparse.RawDescriptionHelpFormatter)
    e.add_argument("--out", default=d.get("out", "results"), help="output folder (default: results)")
    e.add_argument("--quick", action="store_true", default=d.get("quick", False),
                   help="quick sizes (the parameters' quick values) for a fast run")
    e.add_argument("--no-subdir", dest="subdir", action="store_false", default=d.get("subdir", True),
                   help="write directly into --out instead of --out/NAME")
    _add_job_options(e, d, None if experiments.takes_jobs(mod) else
                     " (not for this experiment: it does not split into independent jobs)")
    _add_fresh_option(e, d, mod.NAME)
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
    res = _run_one(mod, out, args.quick, _overrides(mod, args), fresh=args.fresh, **_jobs(args))
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
    from ..atomic import output_folder

    out = Path(args.out)
    with output_folder(out, "--out folder"):  # a run that fails leaves no empty folder behind
        return _reproduce(args, out)


def _reproduce(args, out: Path) -> int:
    jobs = _jobs(args)
    exps = experiments.available()
    n = sum(1 for m in exps.values() if not args.quick or getattr(m, "IN_QUICK_REPRODUCE", True))
    where = ("" if jobs["executor"] is None and jobs["workers"] == 1 else
             f"; {jobs['workers']} at a time" if jobs["executor"] is None else f"; on {jobs['executor']}")
    print(f"ibl-ref reproduce: {n} experiment(s) into {out} ({'quick' if args.quick else 'full'} sizes{where})",
          flush=True)
    summary = experiments.reproduce(out, args.quick, **jobs)
    if args.gallery:
        gallery = _copy_gallery(summary["runs"], Path(args.gallery))
        print(f"gallery: {len(gallery)} figure(s) in {args.gallery}")
    if summary["skipped_in_quick"]:
        print(f"not run at quick size (run 'ibl-ref experiment NAME'): {', '.join(summary['skipped_in_quick'])}")
    print(f"summary: {out / 'reproduce_summary.json'}")
    return 0


def register(sub) -> None:
    p = sub.add_parser(
        "experiment",
        help="run one experiment (a paper figure or a speed/accuracy study) and plot it",
        description="Run one experiment: compute its data into CSV/JSON under --out, then plot PNG "
        "figures from those files. 'ibl-ref experiment --list' shows the experiments, "
        "'ibl-ref experiment NAME --help' what one reproduces, its parameters, outputs and run time. "
        "An interrupted run keeps the jobs it finished: the same command run again runs only the others "
        "(--fresh: all of them).",
    )
    p.add_argument("name", nargs="?", help="experiment name (see --list); 'NAME --help' for its parameters")
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    p.add_argument("--out", default="results", help="output folder (default: results)")
    p.add_argument("--quick", action="store_true", help="quick sizes for a fast run (seconds to a minute)")
    p.add_argument("--list", action="store_true", help="list the experiments and exit")
    p.add_argument("--no-subdir", dest="subdir", action="store_false",
                   help="write directly into --out instead of --out/NAME")
    _add_job_options(p, note=" (experiments whose cases are independent jobs: see 'NAME --help')")
    _add_fresh_option(p)
    p.set_defaults(func=cmd_experiment)

    r = sub.add_parser(
        "reproduce",
        help="run every experiment (the paper's figures) into one folder",
        description="Run every experiment (with --quick: every one that has a quick version), each into "
        "OUT/NAME, and write OUT/reproduce_summary.json with timings and figure paths. The experiments are "
        "independent jobs: one after another by default, N at a time with --workers N, or on a Dask cluster "
        "with --scheduler ADDRESS (OUT must then be on a file system the workers share). The data files are "
        "the same as in a serial run (timing columns aside).",
    )
    r.add_argument("--out", default="results", help="output folder (default: results)")
    r.add_argument("--quick", action="store_true", help="quick sizes (the README's first command)")
    r.add_argument("--gallery", metavar="DIR",
                   help="also copy every PNG figure to DIR as EXPERIMENT__FIGURE.png (the README gallery: docs/gallery)")
    _add_job_options(r)
    r.set_defaults(func=cmd_reproduce)
