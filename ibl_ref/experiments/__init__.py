"""Experiments that reproduce the papers' figures and measure the lab's speed/accuracy trades.

The experiment framework.  Each experiment is a module of this package declaring

``NAME`` (str)
    the name used by ``ibl-ref experiment NAME``;
``DESCRIPTION`` (str)
    one line for ``--list``;
``PAPER`` (str)
    which paper item it reproduces (figure, table, section or equation);
``PARAMS`` (tuple of :class:`Param`)
    its parameters: name, full-size default, quick value, help.  ``ibl-ref experiment NAME --PARAM VALUE``
    overrides one; :func:`resolve_params` merges defaults, quick values and overrides;
``RUNTIME`` (dict)
    typical wall-clock time of the quick and the full run on the reference machine (2 cores shared with other
    work; the load average during the measurement in brackets), ``{"quick": "8 s (load 1)", "full": "1 min
    (load 3)"}``;
``OUTPUTS`` (tuple of str)
    the files ``run`` writes (CSV/JSON/EXR, units in column names or metadata) and ``plot`` writes (PNG);
``run(out_dir: Path, quick: bool, **params) -> dict``
    the compute step: writes the data files into ``out_dir`` and returns a small summary;
``plot(out_dir: Path) -> list[Path]``
    the plot step: reads only those files and writes the figures (via :func:`ibl_ref.figures.save_figure`);
``IN_QUICK_REPRODUCE`` (bool, default True)
    whether ``ibl-ref reproduce --quick`` (the README's first command) runs it.

An experiment whose cases are independent jobs (``fig5``, ``cross-validate``) also takes ``executor=None,
workers=1`` in ``run`` and runs its cases through :func:`ibl_ref.executors.map_jobs`: on ``workers`` local
processes, any :class:`concurrent.futures.Executor`, a ``dask.distributed.Client`` or a Dask scheduler address
(``ibl-ref experiment NAME --workers N | --scheduler ADDRESS``); its data files are bit-for-bit those of a serial
run.  :func:`reproduce` runs whole experiments as such jobs (``ibl-ref reproduce --workers N | --scheduler
ADDRESS``).

Data flows one way: ``run`` never plots and ``plot`` never computes.  Shared scenes and environments come
from the library (:func:`ibl_ref.synthetic.synthetic_envs.make_env`, :mod:`ibl_ref.synthetic.synthetic_meshes`,
:mod:`ibl_ref.rendering.sphere_render`), never from another experiment.  :func:`run_experiment` runs both steps with
progress lines (:mod:`ibl_ref.progress`) and timings, into a staging folder whose files then replace the previous
run's as a set (its manifest ``NAME_outputs.json`` lists them), keeping every finished job of
:func:`~ibl_ref.executors.map_jobs` until then (:func:`job_store_folder`: a rerun after an interruption runs only
the jobs that had not finished); :func:`describe` is the ``--help`` text.

Examples
--------
>>> from ibl_ref import experiments
>>> "method-zoo" in experiments.available()
True
>>> experiments.resolve_params(experiments.get("fig3"), quick=True)["face_size"]
64
"""

from __future__ import annotations

import importlib
import math
import pkgutil
import time
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

__all__ = ["available", "get", "Param", "resolve_params", "run_experiment", "describe", "show", "images_to_json",
           "images_from_json", "takes_jobs", "reproduce", "job_store_folder"]


@dataclass(frozen=True)
class Param:
    """One parameter of an experiment: ``default`` for the full run, ``quick`` for ``--quick``.

    Values are numbers, strings or tuples of numbers/strings; on the command line a tuple is given
    comma-separated (``--lights 6,24,96``).
    """

    name: str
    default: Any
    quick: Any = None
    help: str = ""
    #: what the computation needs of a value beyond its type: a function ``check(value) -> value`` raising
    #: :class:`~ibl_ref.errors.IBLError` (default: :data:`VALUE_CHECKS` by name; see :meth:`check`)
    check_value: Any = None

    def value(self, quick: bool):
        return self.quick if quick and self.quick is not None else self.default

    def parse(self, text: str):
        """Convert a command-line string to this parameter's type (the type of ``default``) and :meth:`check` it."""
        from ..errors import IBLError

        proto = self.default
        try:
            if isinstance(proto, (tuple, list)):
                item = type(proto[0]) if len(proto) else str
                value = tuple(_scalar(item, t.strip()) for t in text.split(",") if t.strip())
            else:
                value = _scalar(type(proto), text)
        except (ValueError, OverflowError):
            raise IBLError(f"--{self.flag}: expected {_kind(proto)}, got {text!r}") from None
        return self.check(value)

    def check(self, value):
        """``value`` if the computation can use it, else a one-line :class:`IBLError` naming ``--FLAG``.

        Every number by its type — an integer (a size, a count, a factor) must be >= 1 and, where the name says
        it is a size, its float64 cube map must fit in memory (:func:`ibl_ref.limits.check_cube_size`); a float
        must be finite — then by what it is (:attr:`check_value`, else :data:`VALUE_CHECKS` by name: tolerances
        above the float64 floor, Phong exponents >= 1, glossiness and F0 in [0, 1], …).
        """
        from ..errors import IBLError
        from ..limits import as_size, check_cube_size

        items = value if isinstance(value, (tuple, list)) else (value,)
        try:
            for v in items:
                if isinstance(v, bool) or not isinstance(v, (int, float)):
                    continue
                if isinstance(v, int):
                    (check_cube_size if "size" in self.name else as_size)(v, f"--{self.flag}")
                elif not math.isfinite(v):
                    raise IBLError(f"--{self.flag}: must be a finite number, got {v!r}")
            check = self.check_value or VALUE_CHECKS.get(self.name)
            if check is not None:
                for v in items:
                    check(v)
        except IBLError as exc:
            msg = str(exc)
            raise IBLError(msg if msg.startswith(f"--{self.flag}") else f"--{self.flag}: {msg}") from None
        return value

    @property
    def flag(self) -> str:
        return self.name.replace("_", "-")


def _in_range(lo: float, hi: float, what: str):
    def check(v):
        from ..errors import IBLError

        if not (lo <= v <= hi):
            raise IBLError(f"{what} must be in [{lo:g}, {hi:g}], got {v!r}")
        return v
    return check


#: largest Phong exponent of an experiment: the convolution's (:data:`ibl_ref.groundtruth.convolution_args.S_MAX`,
#: 2^30: beyond, the weights' float64 rounding cannot be bounded and the lobe is narrower than any texel)
MAX_PHONG_EXPONENT = 2.0 ** 30


def _exponent(v):
    from ..errors import IBLError

    if not 1 <= v <= MAX_PHONG_EXPONENT:
        raise IBLError(f"a Phong exponent must be in [1, 2^30] (beyond, its weights' float64 rounding cannot be "
                       f"bounded and the lobe is narrower than any texel), got {v!r}")
    return v


def _rtol(v):
    from ..limits import check_rtol

    return check_rtol(v, "tolerance")


def _cut_eps(v):
    """A cone cut's weight threshold: the lobe is cut where its weight falls below ``v`` times its peak (not a
    tolerance of a sum, so no float64 floor; :func:`ibl_ref.lobes.km00_reference.ward_cut_angle` needs 0 < v < 1)."""
    from ..errors import IBLError

    if not 0.0 < v < 1.0:
        raise IBLError(f"a cut threshold must be in (0, 1), got {v!r}")
    return v


def _greater_than_one(v):
    from ..errors import IBLError

    if not v > 1:
        raise IBLError(f"must be > 1, got {v!r}")
    return v


def power_of_two(v):
    """A face size the filter pyramid takes (a power of two), else a one-line :class:`IBLError`."""
    from ..errors import IBLError

    if v < 1 or v & (v - 1):
        raise IBLError(f"must be a power of two (the filter pyramid's face sizes: 2, 4, 8, ...), got {v!r}")
    return v


#: what the experiments' parameters of these names must be, beyond a finite number or an integer >= 1
VALUE_CHECKS = {"rtol": _rtol, "ref_rtol": _rtol, "tail_rtol": _rtol, "ref_eps": _cut_eps,
                "s_values": _exponent, "gloss": _in_range(0.0, 1.0, "a glossiness g"),
                "g": _in_range(0.0, 1.0, "a glossiness g"), "ggx_f0": _in_range(0.0, 1.0, "F0"),
                "chain_factor": _greater_than_one,
                "ref_samples_per_hwhm": _in_range(1e-3, 1e3, "sub-texels per half width")}


def _scalar(kind, text: str):
    if kind is bool:
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        raise ValueError(text)
    return kind(text)


def _kind(proto) -> str:
    if isinstance(proto, (tuple, list)):
        return f"a comma-separated list of {_kind(proto[0]) if len(proto) else 'values'}s"
    return {int: "an integer", float: "a number", str: "a string", bool: "true/false"}.get(type(proto), "a value")


def _fmt(v) -> str:
    return ",".join(str(x) for x in v) if isinstance(v, (tuple, list)) else str(v)


#: help texts of the settings keys the rendering experiments share
SETTING_HELP = {'size': 'image width = height (pixels)', 'n_lights': 'median-cut lights (PEMs)', 'vsm_resolution': 'VSM resolution (texels)', 'env_size': 'environment cube face size (texels)', 'g': 'glossiness g of the material (s = 1/(1-g))', 'lights': 'light counts', 'materials': 'materials (diffuse, g0.9, g0.99)', 'vsm': 'VSM resolutions at 96 lights', 'vsm_default': 'VSM resolution of the light-count sweep', 'chain_factor': 'exact-lobe chain exponent ratio'}


def params_from_settings(settings, helps: dict | None = None, checks: dict | None = None) -> tuple:
    """:class:`Param` s from an experiment's ``settings(quick) -> dict`` (full values as defaults).

    Lists become tuples; ``helps`` maps a name to its help text, ``checks`` to its :attr:`Param.check_value`.
    """
    full, quick = settings(False), settings(True)
    tup = lambda v: tuple(v) if isinstance(v, list) else v  # noqa: E731
    helps = {**SETTING_HELP, **(helps or {})}
    checks = checks or {}
    return tuple(Param(k, tup(v), tup(quick.get(k)) if quick.get(k) != v else None, helps.get(k, ""), checks.get(k))
                 for k, v in full.items())


def settings_with(mod, quick: bool, params: dict) -> dict:
    """``mod.settings(quick)`` updated with the resolved parameters (the ``run`` of a settings-based experiment)."""
    import sys

    mod = sys.modules[mod] if isinstance(mod, str) else mod
    return {**mod.settings(quick), **resolve_params(mod, quick, params)}


def resolve_params(mod: ModuleType, quick: bool, overrides: dict | None = None) -> dict:
    """Parameter values of ``mod`` for a quick or full run, with ``overrides`` (name → value) applied.

    ``mod`` may be the module or its ``__name__`` (an experiment's ``run`` calls
    ``resolve_params(__name__, quick, params)``).  ``None`` values in ``overrides`` keep the default.
    """
    import sys

    from ..errors import IBLError

    if isinstance(mod, str):
        mod = sys.modules[mod]

    declared = {p.name: p for p in getattr(mod, "PARAMS", ())}
    params = {k: p.value(quick) for k, p in declared.items()}
    for k, v in (overrides or {}).items():
        if k not in params:
            raise IBLError(f"experiment {mod.NAME}: unknown parameter {k!r}; parameters: "
                           f"{', '.join(params) or '(none)'}")
        if v is not None:
            params[k] = declared[k].check(v)
    return params


def describe(mod: ModuleType) -> str:
    """The ``ibl-ref experiment NAME --help`` text: description, paper item, parameters, outputs, run time."""
    lines = [getattr(mod, "DESCRIPTION", ""), ""]
    if getattr(mod, "PAPER", ""):
        lines.append(f"Reproduces: {mod.PAPER}")
    rt = getattr(mod, "RUNTIME", {})
    if rt:
        lines.append(f"Typical run time on the reference machine (2 cores shared with other work; the load average "
                     f"during the measurement in brackets): --quick {rt.get('quick', '?')}, full {rt.get('full', '?')}")
    if not getattr(mod, "IN_QUICK_REPRODUCE", True):
        lines.append("Not part of 'ibl-ref reproduce --quick' (too slow); run it on its own.")
    outs = getattr(mod, "OUTPUTS", ())
    if outs:
        lines.append("Outputs (in OUT/NAME): " + ", ".join(outs) + f"; their list {manifest_name(mod)} (a rerun "
                     "replaces them as a set and removes those it did not write again)")
    if takes_jobs(mod):
        lines.append("Its cases are independent jobs: --workers N runs them on N local processes, --scheduler "
                     "ADDRESS on a Dask cluster (the data files are bit-for-bit those of a serial run).")
    return "\n".join(lines)


def takes_jobs(mod: ModuleType) -> bool:
    """Whether ``mod.run`` runs its cases through :func:`ibl_ref.executors.map_jobs` (takes ``executor=``)."""
    import inspect

    return "executor" in inspect.signature(mod.run).parameters


def available() -> dict[str, ModuleType]:
    """Map experiment name → module, discovered from this package."""
    out = {}
    for m in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if m.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{__name__}.{m.name}")
        name = getattr(mod, "NAME", None)
        if name:
            out[name] = mod
    return out


def get(name: str) -> ModuleType:
    """The experiment module registered as ``name`` (its ``NAME``).

    Parameters
    ----------
    name : str
        An experiment name, as ``ibl-ref experiment --list`` shows them.

    Returns
    -------
    module
        The experiment: ``NAME``, ``DESCRIPTION``, ``PAPER``, ``PARAMS``, ``OUTPUTS``, ``run``, ``plot`` (module
        docstring).

    Raises
    ------
    IBLError
        An unknown name (the message lists the experiments).

    Examples
    --------
    >>> from ibl_ref import experiments
    >>> mod = experiments.get("fig3")
    >>> mod.NAME, [p.name for p in mod.PARAMS]
    ('fig3', ['face_size', 'pixels', 'gloss', 'environment'])
    >>> experiments.get("fig2")
    Traceback (most recent call last):
    ...
    ibl_ref.errors.IBLError: unknown experiment 'fig2'; available: ...
    """
    exps = available()
    if name not in exps:
        from ..errors import IBLError

        raise IBLError(f"unknown experiment {name!r}; available: {', '.join(sorted(exps)) or '(none yet)'}")
    return exps[name]


def manifest_name(mod: ModuleType) -> str:
    """The file that lists an experiment's outputs in its folder: ``NAME_outputs.json``."""
    return f"{mod.NAME}_outputs.json"


def _output_patterns(mod: ModuleType) -> list:
    """Regular expressions of the declared ``OUTPUTS`` (placeholders ``<n>`` and capitalised words such as
    ``MATERIAL`` match any text): the names an earlier run of the experiment may have left in its folder."""
    import re

    pats = []
    for o in getattr(mod, "OUTPUTS", ()):
        parts = re.split(r"(<[^>]+>|[A-Z]{3,})", o)
        pats.append(re.compile("".join(".+" if i % 2 else re.escape(s) for i, s in enumerate(parts)) + r"\Z"))
    return pats


def _check_folder(mod: ModuleType, out: Path) -> None:
    """Before any work: the files of ``out`` that this experiment may write must be the lab's — listed by the
    experiment's manifest (:func:`manifest_name`, with the lab's marker); otherwise one line naming the first."""
    import os

    from ..atomic import OutputError, check_side_files

    manifest = out / manifest_name(mod)
    check_side_files(manifest, (), "files", "--out", relative=True)  # a manifest without the marker: refused
    if not out.is_dir():
        return
    pats = _output_patterns(mod)
    found = []
    for root, dirs, files in os.walk(out):
        dirs[:] = sorted(d for d in dirs if ".ibl-tmp-" not in d and not d.startswith(".jobs-"))  # job stores
        for f in sorted(files):
            rel = (Path(root) / f).relative_to(out).as_posix()
            if any(p.match(rel) for p in pats):
                found.append(Path(root) / f)
    try:
        check_side_files(manifest, found, "files", "--out", relative=True)
    except OutputError as exc:
        raise OutputError(f"{exc} [experiment {mod.NAME}: {len(found)} file(s) of its names in {out}; a folder of a "
                          "run before the lab listed its outputs must be moved away once]") from None


def _rebase(obj, old: str, new: str):
    """``obj`` (a JSON-like summary) with the staging folder's path ``old`` replaced by the final folder ``new``."""
    if isinstance(obj, str):
        return obj.replace(old, new)
    if isinstance(obj, Path):
        return Path(str(obj).replace(old, new))
    if isinstance(obj, dict):
        return {k: _rebase(v, old, new) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_rebase(v, old, new) for v in obj)
    return obj


def run_experiment(mod: ModuleType, out: Path, quick: bool, overrides: dict | None = None, *, executor=None,
                   workers: int = 1, fresh: bool = False) -> dict:
    """Compute step then plot step of an experiment into ``out``, with a status line per step and timings; the
    outputs replace those of an earlier run as a set.

    The two steps write into a staging folder inside ``out``; only when both succeeded are the files moved into
    ``out`` together (:class:`ibl_ref.atomic.OutputSet`, the experiment's manifest ``NAME_outputs.json`` last, with
    the lab's marker) and the files of the previous run of the same experiment that this run did not write are
    removed; files the lab did not write are left alone.  An error or Ctrl-C leaves the previous run's files as they
    were; of two runs into one folder at once, the later commit replaces the earlier one's set whole.

    Nothing finished is lost: while the experiment runs, the result of every job it runs through
    :func:`ibl_ref.executors.map_jobs` is kept as it finishes in ``out/.jobs-NAME`` (:func:`job_store_folder`,
    :func:`ibl_ref.executors.keeping_jobs`).  A run that fails or is interrupted leaves that folder (and ``out``,
    even one it created); the next run of the experiment into ``out`` takes the results of the jobs it holds
    (one line says how many) and runs only the others, with the same results as a run without interruption.
    The store is removed once the outputs are in place; a store of other code (another version of ``ibl_ref``
    or of NumPy) is never used.

    Parameters
    ----------
    mod : module
        The experiment (:func:`get`).
    out : path
        Its output folder (created if needed; a folder this call created is removed again if the run fails).
    quick : bool
        The parameters' quick values (seconds to a minute) instead of the full run's.
    overrides : dict, optional
        Parameter name → value (checked as on the command line, :meth:`Param.check`); ``None`` keeps the default.
    executor, workers
        Where the experiment's independent cases run (:func:`ibl_ref.executors.map_jobs`); only for experiments
        that split into jobs (:func:`takes_jobs`), an error otherwise.
    fresh : bool
        Discard the finished jobs an interrupted run left and run every job again.

    Returns
    -------
    dict
        ``experiment``, ``quick``, ``params``, ``compute_time_s``, ``plot_time_s``, ``figures`` (final paths),
        ``summary`` (what ``run`` returned).

    Raises
    ------
    IBLError
        A bad parameter, an output folder that cannot be written, a file in it of the experiment's names that the
        lab did not write (before any work), or an error of the experiment itself.

    Examples
    --------
    >>> import json, tempfile
    >>> from pathlib import Path
    >>> from ibl_ref import experiments
    >>> out = Path(tempfile.mkdtemp())
    >>> res = experiments.run_experiment(experiments.get("fig3"), out, quick=True,
    ...                                  overrides={"face_size": 8, "pixels": 4, "gloss": (1.0, 0.0)})
    >>> res["params"]["gloss"], [Path(f).name for f in res["figures"]]
    ([1.0, 0.0], ['fig3.png'])
    >>> json.loads((out / "fig3_outputs.json").read_text())["files"]
    ['fig3.png', 'fig3_spheres.json']
    """
    from .. import progress
    from ..atomic import OutputSet, output_folder
    from ..executors import keeping_jobs

    out = Path(out)
    params = resolve_params(mod, quick, overrides)
    jobs = {}
    if executor is not None or workers != 1:
        if not takes_jobs(mod):
            from ..errors import IBLError

            names = ", ".join(n for n, m in available().items() if takes_jobs(m))
            raise IBLError(f"experiment {mod.NAME} does not split into independent jobs (--workers / --scheduler "
                           f"apply to {names}; 'ibl-ref reproduce --workers N' runs whole experiments in parallel)")
        jobs = dict(executor=executor, workers=workers)
    store = job_store_folder(mod, out)
    # a failed run leaves no folder of its own, but for the jobs it finished
    with output_folder(out, "experiment output folder", remove_tree=True, keep=store.is_dir):
        _check_folder(mod, out)
        with keeping_jobs(store, mod.NAME, fresh=fresh):  # removed when the outputs are in place
            with OutputSet(out / manifest_name(mod), owned_key="files", relative=True) as outs:
                stage = outs.staging_folder()
                t0 = time.perf_counter()
                with progress.step(f"{mod.NAME}: compute", announce=False):
                    summary = mod.run(stage, quick=quick, **params, **jobs) or {}
                t1 = time.perf_counter()
                with progress.step(f"{mod.NAME}: plot", announce=False):
                    figs = mod.plot(stage) or []
                t2 = time.perf_counter()
                res = {"experiment": mod.NAME, "quick": quick, "params": {k: _jsonable(v) for k, v in params.items()},
                       "compute_time_s": round(t1 - t0, 3), "plot_time_s": round(t2 - t1, 3),
                       "figures": [str(f) for f in figs], "summary": summary}
                res = _rebase(res, str(stage), str(out))
                outs.commit({k: res[k] for k in ("experiment", "quick", "params")})  # no timings: the same every run
    return res


def job_store_folder(mod: ModuleType, out) -> Path:
    """Where :func:`run_experiment` keeps the finished jobs of the experiment ``mod`` run into ``out`` until its
    outputs are in place: ``out/.jobs-NAME`` (one folder per experiment: ``--no-subdir`` runs of several
    experiments into one folder keep their jobs apart)."""
    return Path(out) / f".jobs-{mod.NAME}"


def _jsonable(v):
    return list(v) if isinstance(v, tuple) else v


def _reproduce_job(job) -> dict:
    """One experiment of :func:`reproduce` (a job of :func:`ibl_ref.executors.map_jobs`): both steps, with its
    status lines (printed where the job runs)."""
    name, out, quick, i, n = job
    mod = get(name)
    print(f"[{i}/{n}] {name}: {getattr(mod, 'DESCRIPTION', '')}", flush=True)
    res = run_experiment(mod, Path(out) / name, quick)
    print(f"    {name} done in {res['compute_time_s'] + res['plot_time_s']:.1f} s; "
          f"figures: {', '.join(res['figures']) or '-'}", flush=True)
    return res


def reproduce(out, quick: bool = False, names=None, *, executor=None, workers: int = 1) -> dict:
    """Run experiments into ``out/NAME`` (each with :func:`run_experiment`: its outputs replaced as a set) and write
    ``out/reproduce_summary.json``.

    The experiments are independent jobs of :func:`ibl_ref.executors.map_jobs`: serially (default), on
    ``workers`` local processes, or on ``executor`` (any :class:`concurrent.futures.Executor`, a
    ``dask.distributed.Client`` or a scheduler address).  Each writes its own files, so on a cluster ``out`` must
    be a folder that every worker and this process see (a shared file system); a run whose files are missing
    here is an error.  Every data file is the same as in a serial run (timing columns aside).

    Parameters
    ----------
    out : path
        The folder of the runs (created if needed).
    quick : bool
        Quick sizes; without ``names`` only the experiments with ``IN_QUICK_REPRODUCE`` run.
    names : list of str, optional
        The experiments to run (default: all, or with ``quick`` all that have a quick version).
    executor, workers
        Where the experiments run (:func:`ibl_ref.executors.map_jobs`).

    Returns
    -------
    dict
        The summary written to ``reproduce_summary.json``: ``quick``, ``ran_on``, ``runs`` (one
        :func:`run_experiment` result each), ``skipped_in_quick``.

    Raises
    ------
    IBLError
        An unknown experiment name, an output folder that cannot be written, an experiment's own error, or figures
        written by workers that this process cannot see.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> from ibl_ref import experiments
    >>> out = Path(tempfile.mkdtemp())
    >>> s = experiments.reproduce(out, quick=True, names=[])  # nothing to run: the summary alone
    >>> s["runs"], s["ran_on"], (out / "reproduce_summary.json").exists()
    ([], 'serial', True)
    >>> experiments.reproduce(out, names=["fig2"])
    Traceback (most recent call last):
    ...
    ibl_ref.errors.IBLError: unknown experiment 'fig2'; available: ...
    """
    from ..atomic import write_json
    from ..errors import IBLError
    from ..executors import map_jobs

    out = Path(out)
    exps = available()
    if names is None:
        chosen = [n for n, m in exps.items() if not quick or getattr(m, "IN_QUICK_REPRODUCE", True)]
    else:
        chosen = [get(n).NAME for n in names]
    from ..atomic import output_folder

    with output_folder(out, "reproduce output folder"):  # created for a run that fails: removed if still empty
        jobs = [(n, str(out.resolve()), bool(quick), i, len(chosen)) for i, n in enumerate(chosen, 1)]
        where = ("serial" if executor is None and workers <= 1 else
                 f"{workers} local processes" if executor is None else f"executor {executor!r}")
        results = map_jobs(_reproduce_job, jobs, executor=executor, workers=workers,
                           desc=None if executor is None and workers <= 1 else "reproduce", unit="experiment",
                           what="reproduce worker")
        missing = [f for r in results for f in r["figures"] if not Path(f).exists()]
        if missing:
            raise IBLError(f"{len(missing)} figure(s) written by the workers are not visible here (first: "
                           f"{missing[0]}); the output folder must be on a file system every worker shares")
        skipped = sorted(set(exps) - set(chosen))
        summary = {"quick": bool(quick), "ran_on": where, "runs": results, "skipped_in_quick": skipped}
        write_json(out / "reproduce_summary.json", summary)
    return summary


def show(figures) -> list:
    """Display the PNG files ``figures`` in a notebook (IPython), in order; returns their names.

    Experiments close their figures after saving them, so a notebook shows what they wrote with this.
    """
    from IPython.display import Image, display

    names = []
    for f in figures:
        f = Path(f)
        if f.suffix.lower() == ".png":
            display(Image(filename=str(f)))
            names.append(f.name)
    return names


def images_to_json(images: dict, mask) -> dict:
    """Images (H, W, C) → nested lists rounded to 6 significant digits (JSON-friendly), plus the mask.

    The storage format of the rendering experiments' images (``*_images.json``), read by their plot step
    with :func:`images_from_json`.
    """
    import numpy as np

    out = {k: np.vectorize(lambda x: float(f"{x:.6g}"))(np.asarray(v)).tolist() for k, v in images.items()}
    out["_mask"] = np.asarray(mask, dtype=int).tolist()
    return out


def images_from_json(path: Path):
    """(images name → (H, W, C) float64, mask (H, W) bool) from a file written with :func:`images_to_json`."""
    import json

    import numpy as np

    d = json.loads(Path(path).read_text())
    mask = np.asarray(d.pop("_mask"), dtype=bool)
    return {k: np.asarray(v, dtype=np.float64) for k, v in d.items()}, mask
