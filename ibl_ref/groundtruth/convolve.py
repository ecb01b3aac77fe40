"""One entry point for Phong-lobe convolution (Knuth et al. 2014, Sec. 3.2, Eq. 4) with error bounds.

:func:`convolve` computes, for several Phong exponents ``s = s_Phong`` (Eq. 3: ``s = 1/(1−g)``), the
lobe average ``Σ_j L_j max(r·ω_j,0)^s Ω_j / Σ_j max(r·ω_j,0)^s Ω_j`` (``normalized=True``) or the
literal Eq. 4 sum (``normalized=False``) at every output texel ``r``, by one of

``"exact"``
    :func:`ibl_ref.groundtruth.phong_convolution.convolve_exact_many` — every source texel for every output texel
    (the reference; bound = 0 up to rounding).
``"sh"``
    :func:`ibl_ref.groundtruth.sh_convolution.convolve_sh_many` — spherical harmonics (Funk–Hecke) for the clipped
    remainder plus an exact gather from the few texels above a sun threshold, with a rigorous per-texel
    bound (see that module).
``"sparse"``
    :func:`ibl_ref.groundtruth.phong_convolution.convolve_sparse_many` — truncated-support gather with a rigorous
    per-texel bound (absolute per channel, converted here to relative).
``"moment"``
    :func:`ibl_ref.groundtruth.moment_convolution.convolve_moment_many` — ``s ∈ {1, 2}`` only: quadtree block
    moments (exact polynomial kernel on blocks in the positive hemisphere) plus an exact gather of
    the horizon band; equals the exact gather up to rounding, ≈ 10× faster at 128² faces.
``"auto"``
    per exponent the cheapest route by the cost models of the kernel in use (:func:`_route_auto`,
    :func:`plan_routes`): ``s ∈ {1, 2}`` by the moment route or the shared SH pass (broad lobes are where the
    SH bound is loose and the sparse gather degenerates to the dense one; from 256² faces,
    :func:`~ibl_ref.groundtruth.moment_convolution.moment_leaf`, the moment route uses linear brackets on
    leaf blocks of the horizon band instead of its exact gather: rigorous bound, the leaf halved while it
    misses rtol, cost growing as N² instead of N³); the other exponents by the SH/hybrid route when its
    planned band limit is affordable (broad lobes; the plan estimates the darkest output texel from a 16²
    copy of the map), the sparse gather otherwise (narrow lobes; its cost from its own first caps on a
    sample of tiles where that decides), and the exact gather when neither bound meets ``rtol`` (checked a
    posteriori, per exponent) or for the mirror ``s = inf``.  Exponents routed to SH share one SH pass;
    an exponent within reach of L_max may join it when that stays cheaper should it fail.

Kernels (``kernel``)
    ``"numpy"`` or ``"compiled"`` (numba; :mod:`ibl_ref.groundtruth.kernels`): the same routes and bounds;
    ``"auto"`` takes the compiled kernels when numba is installed and the call pays for loading them
    (:func:`_auto_kernel`).

Concurrency (``workers``)
    The work is cut into independent jobs — the moment and sparse routes per fixed group of output
    faces (:data:`FACE_PARTS`), the shared SH pass (a big one, :data:`SH_SPLIT_MIN_SECONDS`, as
    :data:`SH_PARTS` projection jobs over fixed ranges of source directions, whose partial coefficient sums
    are added in order, and then as many evaluation jobs over ranges of output directions:
    :func:`ibl_ref.groundtruth.sh_convolution.sh_project_part` / ``sh_evaluate_part``), the exact gather — that run on a pool of
    ``workers`` forked processes (``backend="process"``, the default on Linux when the caller is
    single-threaded and not a daemonic process) or threads (``backend="thread"``; NumPy releases the GIL in its array
    kernels, but the many small array calls of the gathers still contend for it).  Default
    ``workers``: ``$IBL_REF_WORKERS`` or min(2, usable CPUs).  BLAS is held at 1 thread (threadpoolctl) for the
    whole call, serial included: a multi-threaded BLAS splits the SH matrix products differently and
    changes their rounding (≈ 5e-16 relative, measured at 128²).  The jobs do not depend on the worker
    count or back-end, so results are bit-for-bit identical for every ``workers``/``backend``.  With the
    compiled kernels a round of sparse gathers only (no other route in it, no ``executor``) is one job over all
    six faces whose tiles ``workers`` threads share (the compiled gather releases the GIL; each tile is computed
    by one thread as in a serial call): no pool to start, the load balanced tile by tile.
    Measured (``python benchmarks/bench_convolution.py --repeat 3``, 128² faces, the 8 exponents
    {1, 2, 5, 10, 20, 50, 100, 1000}, 2-core VM, load ≈ 1.2, three runs each): 3.0–3.6 s serial;
    2.0–2.3 s wall with 2 processes, 2.4–3.0 s with 2 threads.

Scale-out (``executor``)
    The same jobs run on any :class:`concurrent.futures.Executor` (a process pool of your own, a
    ``dask.distributed.Client`` or its scheduler address, ``ibl-ref convolve --scheduler ADDRESS``):
    jobs and inputs are pickled, each job holds BLAS at one thread on its worker, and the results are
    bit-for-bit those of a serial run (``tests/test_convolve_executor.py``, a 2-worker Dask
    ``LocalCluster``).

Resources
    Jobs whose model cost sums to < :data:`PARALLEL_MIN_SECONDS` run serially (starting a pool would
    not pay).  Each job's peak memory is estimated (:func:`_job_bytes`; the moment route's by
    :func:`ibl_ref.groundtruth.moment_convolution.moment_peak_bytes`, which its output-tile chunking bounds) and
    the worker count is lowered until the largest concurrent jobs fit in :data:`MEMORY_FRACTION` of
    the available memory (:func:`available_memory_bytes`, or ``memory_limit``).  A worker process
    that dies anyway (out-of-memory killer) raises :class:`~ibl_ref.errors.IBLError`.

Float64 range
    Inputs whose largest radiance is outside [2^-64, 2^64] are scaled by a power of two (exact) and the
    maps scaled back, so ``ones·1e308`` gives finite maps for every method (a literal Eq. 4 sum beyond
    the float64 range is an IBLError); every bound carries an underflow allowance
    (:data:`UNDERFLOW_ABS`), so it also holds where exact values are subnormal.

The returned ``error_bound[s]`` is a per-texel bound on ``|approx − exact| / exact`` (max over channels,
``inf`` where the bound is useless, e.g. a black output texel); ``bound_kind[s]`` says whether it is
``"rigorous"`` (SH, sparse, moment with brackets), ``"estimate"`` (SH for very broad lobes, s ≈ 1, whose rigorous bound
cannot reach rtol at an affordable band limit: ``|y_L − y_{L/2}|/y_L``, see
:func:`ibl_ref.groundtruth.sh_convolution.convolve_sh_many`) or ``"rounding"`` (exact).  ``auto`` accepts an
estimate only when it meets rtol, and only for exponents where the exact gather would cost more.
"""

from __future__ import annotations

import functools
import math
import os
import sys
import threading
import time
from dataclasses import dataclass, field

import numpy as np

try:
    import resource
except ImportError:  # pragma: no cover - not POSIX (no fork either)
    resource = None

from ..errors import IBLError
from ..environment.validated import adopt
from ..executors import one_blas_thread, resolve_executor, worker_died
from ..limits import check_rtol
from .convolution_args import channel_max, check_cube, check_exponents, check_out_size
from . import moment_convolution as mc
from . import phong_convolution as pc
from . import sh_convolution as shc
from .kernels import KERNEL_ENV, KERNEL_METHODS, get_kernels, kernels_loaded, resolve_kernel
from .kernels.rounding import sum_error, weight_error
from .moment_convolution import moment_leaf, moment_peak_bytes
from .phong_convolution import estimate_candidates
from .sh_bounds import SH_L_MAX, band_limit_lower_bound, choose_band_limit, texel_max_radius
from .sh_convolution import SECONDS_PER_UNIT, sh_assemble, sh_coefficients

__all__ = ["ConvolutionResult", "convolve", "default_workers", "METHODS", "WORKERS_ENV"]

METHODS = ("auto", "exact", "sh", "sparse", "moment")

#: ``auto`` runs the exact gather for every exponent when (output texels × source texels × exponents)
#: is below this (≈ 0.6 s of exact work measured on the shared 2-core machine): the fast methods'
#: fixed costs (planning, bound tables, KD-tree) do not pay off on tiny maps.
AUTO_EXACT_PAIRS = 1.5e7
#: exponents ``auto`` sends to :mod:`ibl_ref.groundtruth.moment_convolution` (exact up to rounding, ≈ 4 s CPU for
#: s = 1 at 128² faces on the shared machine vs ≈ 47 s for the dense exact gather)
MOMENT_EXPONENTS = (1.0, 2.0)
#: ``auto`` uses the moment route from this many (output × source texel) pairs on (below, the other
#: routes' planning is kept; the moment route's fixed costs make it no faster than exact at ≤ 32²)
MOMENT_MIN_PAIRS = 1e8


#: environment variable read by :func:`convolve` when ``workers`` is not given (a positive integer)
WORKERS_ENV = "IBL_REF_WORKERS"
#: parallel back-ends of :func:`convolve` (``auto``: forked processes where possible, else threads)
BACKENDS = ("auto", "process", "thread")
#: correction of the sparse cost model for the ordering of the jobs only (1: the model as fitted)
SPARSE_JOB_ORDER_FACTOR = 1.0
#: :func:`convolve` rescales the input by a power of two (exact) when its largest radiance is above
#: 2^SCALE_EXP or below 2^-SCALE_EXP, so that no sum of ≤ 6N² weighted terms overflows (e.g.
#: ``ones·1e308``) and nothing underflows needlessly; the maps are scaled back at the end
SCALE_EXP = 64
#: absolute underflow allowance, relative to the largest (scaled) radiance: every weight that
#: underflows (a power of a cosine, a product of small factors) is off by < 2^-1022 in absolute terms;
#: summed over ≤ 6·1024² source texels with Ω_max/Ω_min ≤ 5.2 and divided by a lobe weight ≥ the
#: largest (=1 after the shift by the maximum) times Ω_min, the error of a lobe average is below
#: L_max·2^-1022·4π·5.2·6.3e6 < L_max·2^-990.  Added to every bound as ``u/value`` (inf where the value
#: is 0 and u > 0: an exact value that underflowed cannot be told from 0); it is invisible (≪ 1e-16
#: relative) wherever the value is above ≈ 1e-280·L_max.
UNDERFLOW_ABS = 2.0 ** -990
#: jobs whose model cost sums to less than this many seconds run serially even when ``workers > 1``:
#: starting a forked pool costs ≈ 0.05–0.1 s (measured: 64², s = 1024, sparse: 0.35 s serial vs
#: 0.44–0.54 s with 2 processes on the loaded 2-core machine); results are the same either way
PARALLEL_MIN_SECONDS = 1.0
#: output faces of each job of the moment and sparse routes.  Fixed (not derived from the worker count),
#: so that every worker count computes exactly the same pieces: bit-for-bit identical results.
FACE_PARTS = ((0, 1), (2, 3), (4, 5))
#: from this output face size on, the moment route runs one job per output face (six jobs balance
#: better on 2 workers than three: 3 rounds of one face instead of 2 rounds of two); also fixed by
#: the sizes alone
MOMENT_SPLIT_MIN_SIZE = 256
MOMENT_FACE_PARTS_LARGE = tuple((f,) for f in range(6))
#: an SH pass whose model cost (:func:`ibl_ref.groundtruth.sh_convolution.sh_cost`) is at least this many seconds
#: runs as :data:`SH_PARTS` projection jobs and then :data:`SH_PARTS` evaluation jobs (two rounds) instead of
#: one job, so that two workers share it (1024², the 8-exponent set: one 425 s SH job had left the second
#: worker idle).  Decided from the sizes and the band limit only, never from the worker count: every
#: worker count computes the same pieces.
SH_SPLIT_MIN_SECONDS = 20.0
SH_PARTS = 4


def default_workers() -> int:
    """Default thread count of :func:`convolve`: ``$IBL_REF_WORKERS`` if set, else min(2, usable CPUs)."""
    env = os.environ.get(WORKERS_ENV, "").strip()
    if env:
        try:
            v = int(env)
        except ValueError:
            raise IBLError(f"{WORKERS_ENV} must be a positive integer, got {env!r}") from None
        if v < 1:
            raise IBLError(f"{WORKERS_ENV} must be a positive integer, got {env!r}")
        return v
    try:
        ncpu = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        ncpu = os.cpu_count() or 1
    return max(1, min(2, ncpu))


def _resolve_workers(workers) -> int:
    if workers is None:
        return default_workers()
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise IBLError(f"workers must be a positive integer (1 = serial), got {workers!r}")
    return int(workers)


#: jobs of the running :func:`_run_jobs` call, inherited by forked worker processes (never pickled)
_FORK_JOBS: list | None = None
_FORK_LOCK = threading.Lock()


def _call_job(key, fn, limit_blas=True):
    """Run one job, with BLAS held at one thread when ``limit_blas`` (on an executor's worker; local
    runs are already inside :func:`convolve`'s limit);
    returns ``(key, result, seconds)``."""
    t0 = time.perf_counter()
    if limit_blas:
        with one_blas_thread():
            r = fn()
    else:
        r = fn()
    return key, r, time.perf_counter() - t0


def _run_job(job):
    return _call_job(job[1], job[3], limit_blas=False)


def _run_forked_job(i):
    return _run_job(_FORK_JOBS[i])


def available_memory_bytes() -> float | None:
    """Memory this process may still use: ``MemAvailable`` of ``/proc/meminfo``, lowered to the cgroup
    limit minus its usage when one is set (containers); ``None`` where neither can be read."""
    avail = None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    avail = float(line.split()[1]) * 1024.0
                    break
    except OSError:
        pass
    try:
        with open("/sys/fs/cgroup/memory.max") as fh:
            lim = fh.read().strip()
        with open("/sys/fs/cgroup/memory.current") as fh:
            cur = float(fh.read().strip())
        if lim != "max":
            room = float(lim) - cur
            avail = room if avail is None else min(avail, room)
    except (OSError, ValueError):
        pass
    return avail


#: fraction of the available memory the planner lets the concurrent jobs of :func:`convolve` use
MEMORY_FRACTION = 0.8


def plan_memory_workers(workers: int, job_bytes, available) -> int:
    """Largest worker count ≤ ``workers`` whose concurrent jobs fit in ``MEMORY_FRACTION · available``.

    ``job_bytes``: estimated peak memory of each job; with w workers the w largest may run at once.
    At least 1 (a single job that does not fit is run anyway, serially; :func:`convolve` records it
    in ``info["memory_warning"]``).  ``available = None`` (unknown) keeps ``workers``.
    """
    if available is None or workers <= 1:
        return workers
    big = sorted((float(b) for b in job_bytes), reverse=True)
    w = workers
    while w > 1 and sum(big[:w]) > MEMORY_FRACTION * available:
        w -= 1
    return w


def _job_bytes(stage, n, out_size, C, n_faces, K, need2=True, leaf=1):
    """Estimated peak memory (bytes) of one job of :func:`convolve` (used by the memory planner only)."""
    n_src, n_out = 6 * n * n, n_faces * out_size * out_size
    maps = K * n_out * C * 8.0 * 2  # maps + bounds
    if stage == "moment":

        return moment_peak_bytes(n, out_size, n_faces, C, need2, leaf)
    if stage == "sh":  # SH matrix cache / chunk (≤ 256 MB + 128 MB) and per-texel work arrays
        return 4.0e8 + 4 * maps + n_src * (C + 4) * 8.0 * 4
    if stage == "sparse":  # sources, KD-tree, tile geometry
        return n_src * (C + 5) * 8.0 * 6 + n_out * 8 * 8.0 * 2 + 2 * maps
    return n_src * (C + 5) * 8.0 * 2 + 2 * maps + 3.2e7  # exact: chunked weight matrices


def _resolve_backend(backend, workers):
    if backend not in BACKENDS:
        raise IBLError(f"unknown parallel backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if workers <= 1:
        return "serial"
    if backend == "auto":
        # fork only a single-threaded process (a fork copies no other thread; locks they hold would
        # stay locked in the child), only on Linux (macOS system libraries are not fork-safe), and not
        # from a daemonic process (multiprocessing forbids it children); otherwise threads
        # (multiprocessing is imported only to fork: ≈ 6 ms of every process otherwise.  A daemonic process is
        # a multiprocessing child, so multiprocessing is already imported there; on Linux "fork" is always
        # among the start methods)
        mp = sys.modules.get("multiprocessing")
        fork_ok = (sys.platform.startswith("linux") and threading.active_count() == 1
                   and not (mp is not None and mp.current_process().daemon))
        return "process" if fork_ok else "thread"
    import multiprocessing

    if backend == "process" and "fork" not in multiprocessing.get_all_start_methods():
        raise IBLError("backend 'process' needs the 'fork' start method (POSIX); use 'thread'")
    if backend == "process" and multiprocessing.current_process().daemon:
        raise IBLError("backend 'process' cannot start workers from a daemonic process; use 'thread'")
    return backend


def _run_jobs(jobs, workers, backend="thread", executor=None):
    """Run ``(stage, key, cost, fn)`` jobs, longest model cost first, on ``workers`` threads or processes.

    Returns ``({key: fn()}, {key: seconds}, child CPU seconds)``.  ``"process"``: a pool of forked
    worker processes that inherit the jobs (inputs are not copied; results come back pickled) —
    no GIL (``convolve`` of s = 1, 2 at 128², the three moment jobs: 1.69 s serial, 1.49 s with 2
    processes, 1.51 s with 2 threads; the 8-exponent benchmark gains more, see the module docstring).  ``"thread"``:
    NumPy releases the GIL inside large array operations, so the jobs overlap partly.
    """
    global _FORK_JOBS
    # (concurrent.futures imported where used: its process pool imports multiprocessing, ≈ 12 ms of a process)
    order = sorted(jobs, key=lambda j: -min(float(j[2]), 1e300))
    out, busy = {}, {}
    child_cpu = 0.0
    if executor is not None:  # any concurrent.futures.Executor (jobs and inputs are pickled)
        from concurrent.futures import BrokenExecutor

        futs = [executor.submit(_call_job, j[1], j[3]) for j in order]
        try:
            done = [f.result() for f in futs]
        except BrokenExecutor as exc:
            raise worker_died(exc, "convolution worker") from None
    elif workers <= 1 or len(order) <= 1 or backend == "serial":
        done = [_run_job(j) for j in order]
    elif backend == "process":
        with _FORK_LOCK:  # one forked pool at a time (the job table is a module global)
            r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            _FORK_JOBS = order
            try:
                import multiprocessing
                from concurrent.futures import BrokenExecutor, ProcessPoolExecutor

                ctx = multiprocessing.get_context("fork")
                with ProcessPoolExecutor(max_workers=min(workers, len(order)), mp_context=ctx) as ex:
                    futs = [ex.submit(_run_forked_job, i) for i in range(len(order))]
                    try:
                        done = [f.result() for f in futs]
                    except BrokenExecutor as exc:
                        raise worker_died(exc, "convolution worker") from None
            finally:
                _FORK_JOBS = None
            r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        child_cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    else:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max_workers=min(workers, len(order)), thread_name_prefix="ibl_convolve") as ex:
            futs = [ex.submit(_run_job, j) for j in order]
            done = [f.result() for f in futs]
    for key, r, dt in done:
        out[key] = r
        busy[key] = dt
    return out, busy, child_cpu


@dataclass
class ConvolutionResult:
    """Result of :func:`convolve`.

    Attributes
    ----------
    maps : dict float → ndarray (6, n, n, C)
        Convolved cube map per exponent.
    error_bound : dict float → ndarray (6, n, n)
        Per-texel bound on the relative error ``|approx − exact|/exact`` (max over channels).
    bound_kind : dict float → str
        ``"rigorous"``, ``"estimate"`` (SH, broad lobes) or ``"rounding"`` (exact and moment methods).
    method_used : dict float → str
        ``"exact"``, ``"sh"``, ``"sparse"`` (after any fallback).
    timings_s : dict
        Seconds per stage (keys ``"moment"``, ``"sh"``, ``"sparse"``, ``"exact"``: summed wall time of
        that stage's jobs, which overlap when ``workers > 1``; a compiled sparse gather shared by threads,
        ``info["sparse_threads"]``, counts its wall time × threads), ``"jobs_wall"`` (wall time of all
        jobs), ``"total"`` (wall time of the call) and the process CPU time of the whole call
        (``"total_cpu"``, all threads; equals the unloaded serial wall time when BLAS runs
        single-threaded, the recommended setting).
    info : dict
        Diagnostics (SH band limit, sun threshold, fallbacks, ``workers`` and the parallel
        ``backend`` actually used: ``"serial"``, ``"thread"`` or ``"process"``).
    """

    maps: dict = field(default_factory=dict)
    error_bound: dict = field(default_factory=dict)
    bound_kind: dict = field(default_factory=dict)
    method_used: dict = field(default_factory=dict)
    timings_s: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """JSON-friendly per-exponent summary (method, bound max/mean, timings)."""
        out = {"timings_s": dict(self.timings_s), "info": _jsonable(self.info), "exponents": []}
        for s in self.maps:
            b = self.error_bound[s]
            fin = b[np.isfinite(b)]
            out["exponents"].append(
                {
                    "s": _s_json(s),
                    "method": self.method_used[s],
                    "bound_kind": self.bound_kind[s],
                    "rel_bound_max": float(b.max()) if np.all(np.isfinite(b)) else None,
                    "rel_bound_mean": float(fin.mean()) if fin.size else None,
                    "rel_bound_p99": _quantile_linear(fin, 0.99) if fin.size else None,
                    "n_texels_unbounded": int(np.count_nonzero(~np.isfinite(b))),
                }
            )
        return out


def _quantile_linear(x: np.ndarray, q: float) -> float:
    """``np.quantile(x, q)`` (linear interpolation between the order statistics at (n − 1)·q) by ``np.partition``:
    ``np.quantile``'s first call in a process imports ``numpy.ma`` (≈ 10–25 ms of a small CLI run)."""
    x = np.ravel(x)
    h = (x.size - 1) * q
    lo = int(math.floor(h))
    hi = min(lo + 1, x.size - 1)
    part = np.partition(x, [lo, hi]) if hi != lo else np.partition(x, lo)
    a, b, w = float(part[lo]), float(part[hi]), h - lo
    return a + (b - a) * w if w < 0.5 else b - (b - a) * (1.0 - w)


def _s_json(s):
    return "inf" if not np.isfinite(s) else float(s)


def _jsonable(d):
    if isinstance(d, dict):
        return {str(k): _jsonable(v) for k, v in d.items()}
    if isinstance(d, (list, tuple)):
        return [_jsonable(v) for v in d]
    if isinstance(d, (np.floating, float)):
        return float(d) if np.isfinite(d) else str(d)
    if isinstance(d, np.integer):
        return int(d)
    return d


def _power_of_two_scaled(a4):
    """``(a4·2^-k, k)`` with 2^k near the largest radiance when that is outside [2^-SCALE_EXP, 2^SCALE_EXP].

    Multiplying by a power of two is exact (except for texels that would become subnormal: those
    below 2^(k−1022) of the largest, i.e. 1e-290 of it and less, lose low bits).  k = 0 otherwise.
    """
    l_max = float(a4.max()) if a4.size else 0.0
    if l_max == 0.0 or 2.0 ** -SCALE_EXP <= l_max <= 2.0 ** SCALE_EXP:
        return a4, 0
    k = math.frexp(l_max)[1]
    return np.ldexp(a4, -k), k


def _with_underflow(maps, rel, u):
    """Relative bound ``rel`` (per texel) plus the underflow allowance ``u/value`` (max over channels)."""
    if u == 0.0:
        return rel
    with np.errstate(divide="ignore"):
        extra = np.where(maps > 0, u / np.where(maps > 0, maps, 1.0), np.inf)
    extra = channel_max(extra)
    return np.where(extra > 0, rel + extra, rel)


def exact_rounding(s, n) -> float:
    """Relative rounding bound of the dense exact gather's lobe average for exponent ``s`` on faces of size ``n``: a
    ratio of two float64 sums of 6n² weights exp(s·(log c − log c_max)) (:func:`ibl_ref.groundtruth.kernels.rounding.
    weight_error`, relative to the row maximum) is off by ≤ 2(η + γ_m); at least 1e-12 (reported, not zero)."""
    if not np.isfinite(s):
        return 1e-12
    eta, _eps = weight_error(s, False, True)
    return max(1e-12, 2.0 * (eta + float(sum_error(6 * n * n))))


def _rel_from_abs(maps, abs_bound):
    """Relative bound per texel (max over channels) from an absolute per-channel bound."""
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(maps > abs_bound, abs_bound / np.maximum(maps - abs_bound, 1e-300), np.inf)
    r = np.where(abs_bound == 0, 0.0, r)
    return channel_max(r)


def _unit(name, impl):
    """The cost-model constant ``name`` of the kernel ``impl`` (its :data:`~ibl_ref.groundtruth.kernels.KERNEL_METHODS`
    entry; read at call time)."""
    return KERNEL_METHODS[impl].costs[name]


def _seconds_per_unit():
    return SECONDS_PER_UNIT


def _exact_cost(s, n_src, n_out, impl="numpy"):
    """Cost model of the dense exact gather of one exponent (units of :func:`_seconds_per_unit`)."""
    return n_out * n_src * _unit("EXACT_UNITS_PER_PAIR_S1" if s == 1.0 else "EXACT_UNITS_PER_PAIR", impl)


def _moment_cost(n, out_size, leaf, impl="numpy"):
    """Cost model of :func:`ibl_ref.groundtruth.moment_convolution.convolve_moment_many` for s = 1 and 2 (units of
    :func:`_seconds_per_unit`)."""
    return _unit("MOMENT_UNITS", impl) * 6.0 * out_size * out_size * 6.0 * n / max(leaf, 1)


#: the planner estimates the sparse candidates (≈ 0.05–2 s) only for exponents whose sparse cost by the static
#: model is at least this many seconds (below, the choice matters little) and not SPARSE_STATIC_SLACK times their SH
#: pass (the static model was 1.3–3.6× below the measured cost on the CC0 probes at 256², s = 256)
SPARSE_ESTIMATE_MIN_SECONDS = 0.3
SPARSE_STATIC_SLACK = 4.0


def _sparse_cost_estimated(cand, n_out, impl="numpy"):
    """Sparse cost from the estimated candidates per output texel (units of :func:`_seconds_per_unit`)."""
    return n_out * (cand * _unit("SPARSE_UNITS_PER_CAND", impl) + _unit("SPARSE_UNITS_PER_CAND_OUTPUT", impl))


def _sparse_cost(s, rtol, n_src, n_out, impl="numpy"):
    """Cost model of the sparse gather (units of :func:`ibl_ref.groundtruth.sh_convolution.sh_cost`)."""
    eps = max(rtol * 1e-2, 1e-300)
    cos_c = math.exp(math.log(eps) / (s + 1.0))
    frac = (1.0 - cos_c) / 2.0
    if frac > 0.4:  # the sparse gather itself falls back to the dense gather there
        return math.inf
    return (n_out * n_src * frac * _unit("SPARSE_UNITS_PER_PAIR", impl)
            + n_out * _unit("SPARSE_UNITS_PER_OUTPUT", impl))


def convolve(
    cube,
    exponents,
    *,
    method: str = "auto",
    rtol: float = 1e-3,
    out_size: int | None = None,
    normalized: bool = True,
    workers: int | None = None,
    backend: str = "auto",
    executor=None,
    memory_limit: float | None = None,
    kernel: str | None = None,
) -> ConvolutionResult:
    """Convolve a cube map with Phong lobes ``max(r·ω,0)^s`` for several exponents, with error bounds.

    Parameters
    ----------
    cube : array (6, N, N[, C])
        Non-negative finite radiance (OpenEXR face order, see :mod:`ibl_ref.environment.envmap`).
    exponents : float or sequence of float
        Phong exponents ≥ 1 (``np.inf`` = mirror; exact method only).
    method : {"auto", "exact", "sh", "sparse", "moment"}
    rtol : float
        Target per-texel relative error for ``auto`` (and the planning of ``sh``/``sparse``).
    out_size : int, optional
        Output face size (default N).
    normalized : bool
        Lobe average (default) or literal Eq. 4 (``sparse`` supports only the average; ``auto`` then
        uses SH or exact).
    workers : int, optional
        Threads running the independent jobs (each route's exponents × fixed groups of output faces,
        :data:`FACE_PARTS`) concurrently; 1 = serial.  Default :func:`default_workers`
        (``$IBL_REF_WORKERS`` or min(2, usable CPUs)).  The jobs do not depend on this number, so the
        maps and bounds are bit-for-bit identical for every worker count and back-end.  The
        BLAS thread pools are limited to 1 thread for the duration of the call (threadpoolctl; restored after).
    backend : {"auto", "process", "thread"}
        How ``workers > 1`` jobs run: ``"process"`` — a pool of forked worker processes (POSIX; no
        GIL: 8 exponents at 128² in 2.0 s vs 2.4 s with threads and 3.0 s serial, best of 3 runs);
        ``"thread"`` — a thread pool; ``"auto"`` (default) — processes on Linux when the calling process
        has a single thread (forking a multi-threaded process is unsafe) and is not daemonic, else
        threads.
    executor : concurrent.futures.Executor, dask.distributed.Client or str, optional
        Run the independent jobs on this executor instead (``workers``/``backend`` are then unused):
        any :class:`concurrent.futures.Executor` (e.g. a ``ProcessPoolExecutor`` of your own), a
        ``dask.distributed.Client`` (its :meth:`get_executor`) or a Dask scheduler address
        (``"tcp://host:8786"``; the client is closed after the call).  Jobs and their inputs are
        pickled; each job holds BLAS at one thread on its worker, so the maps and bounds are
        bit-for-bit those of a serial run.
    memory_limit : float, optional
        Bytes the concurrent jobs may use (default: what the machine has available,
        :func:`available_memory_bytes`).  The planner estimates each job's peak memory and runs
        fewer workers when ``workers`` of them would not fit (``info["workers_planned"]``); results
        do not change.  A worker process that dies anyway (killed for lack of memory) raises
        :class:`~ibl_ref.errors.IBLError`.
    kernel : {"auto", "numpy", "compiled"}, optional
        Implementation of the inner loops (:mod:`ibl_ref.groundtruth.kernels`): the NumPy reference or
        the numba-compiled kernels (extra ``fast``).  Default ``$IBL_REF_KERNEL`` or ``"auto"``.  Both give
        rigorous bounds; their maps agree within the sum of the two bounds.  ``info["kernel"]`` records the one
        used.

    Returns
    -------
    ConvolutionResult
        ``maps[s]`` (the lobe averages, the input's channel layout: (6,n,n) for a 3-d input), ``error_bound[s]``
        (per texel, a bound on ``|approx − exact| / exact``, max over channels), ``method_used[s]``,
        ``bound_kind[s]`` (``"rigorous"``, ``"estimate"`` or ``"rounding"``), ``info`` and ``timings_s``.

    Raises
    ------
    IBLError
        Bad method, exponent (< 1, NaN), rtol, out_size, workers or kernel; ``LayoutError`` / ``RadianceError``
        for a wrong shape or NaN/Inf/negative radiance.

    Examples
    --------
    A constant environment is its own lobe average, for every exponent (the mirror too):

    >>> import numpy as np
    >>> from ibl_ref.groundtruth.convolve import convolve
    >>> res = convolve(np.full((6, 8, 8, 3), 2.0), [1.0, 16.0, np.inf], kernel="numpy")
    >>> [float(np.abs(res.maps[s] - 2.0).max()) < 1e-12 for s in (1.0, 16.0, np.inf)]
    [True, True, True]

    A sky with a sun: every texel within the requested relative error, by the route ``auto`` chose:

    >>> from ibl_ref.synthetic.synthetic_envs import make_env
    >>> res = convolve(make_env("sky_sun", 16), [64.0], rtol=1e-3, kernel="numpy")
    >>> res.maps[64.0].shape, bool(res.error_bound[64.0].max() <= 1e-3), res.bound_kind[64.0]
    ((6, 16, 16, 3), True, 'rounding')
    """
    t_start = time.perf_counter()
    c_start = time.process_time()
    if method not in METHODS:
        raise IBLError(f"unknown convolution method {method!r}; choose one of {', '.join(METHODS)}")
    rtol = check_rtol(rtol)
    a4, squeeze = check_cube(cube)
    n = a4.shape[1]
    a4, scale_k = _power_of_two_scaled(a4)
    a4 = adopt(a4, name="environment cube map")  # (checked once here; every route and job trusts it)
    out_size = check_out_size(out_size, n)
    s_list = check_exponents(exponents)
    if not normalized and any(not np.isfinite(s) for s in s_list):
        raise IBLError("the unnormalised Eq. 4 integral vanishes for s = inf; use normalized=True")
    if method == "sh" and any(not np.isfinite(s) for s in s_list):
        raise IBLError("method 'sh' cannot represent the mirror (s = inf); use 'exact' or 'auto'")
    if method == "moment" and any(s not in MOMENT_EXPONENTS for s in s_list):
        raise IBLError(f"method 'moment' supports Phong exponents {MOMENT_EXPONENTS} only; use 'auto'")
    if method == "sparse" and not normalized:
        raise IBLError("method 'sparse' computes the normalised lobe average only; use 'sh' or 'exact'")
    workers = _resolve_workers(workers)
    backend = _resolve_backend(backend, workers)
    impl = resolve_kernel(kernel)
    kernel_auto = (kernel if kernel is not None else os.environ.get(KERNEL_ENV, "").strip().lower() or "auto") == "auto"
    if memory_limit is not None:
        try:
            memory_limit = float(memory_limit)
        except (TypeError, ValueError):
            raise IBLError(f"memory_limit must be a number of bytes, got {memory_limit!r}") from None
        if not memory_limit > 0:
            raise IBLError(f"memory_limit must be positive, got {memory_limit!r}")
    kernel_note = None
    if kernel_auto and KERNEL_METHODS[impl].load_seconds > 0:  # (a backend that costs a load: is it worth it here?)
        with one_blas_thread():
            impl, kernel_note = _auto_kernel(a4, s_list, method, rtol, out_size, normalized)
    executor, owned_client = resolve_executor(executor)
    try:
        return _convolve(a4, squeeze, n, s_list, method, rtol, out_size, normalized, workers, backend,
                         executor, memory_limit, scale_k, t_start, c_start, impl, kernel_note)
    finally:
        if owned_client is not None:
            owned_client.close()


#: an exponent the SH plan cannot promise (band limit > L_max at the estimated output floor) but that is within
#: reach (:data:`ibl_ref.groundtruth.sh_convolution.FLOOR_REACH`) joins the SH pass at L_max only if that is cheaper
#: than its other route even when the attempt is charged this share of the other route (the cost of a failed
#: attempt: the bound is checked after the pass and a miss goes to the sparse gather)
SH_RISK_SHARE = 0.25


def _sh_pass_cost(L, n_bright, n_src, n_out, K, Q, impl):
    """Model cost of one SH pass (its passes, the bright gather and the fixed part; units of
    :func:`_seconds_per_unit`)."""
    return (_unit("SH_FACTOR", impl) * shc.sh_cost(L, n_src, n_out, K, Q)
            + _unit("SH_BRIGHT_FACTOR", impl) * shc.bright_cost(n_bright, n_out, K) + shc.SH_OVERHEAD_UNITS)


def _route_auto(a4, s_list, rtol, out_size, normalized, info, impl="numpy", estimate=True, floor_impl=None):
    """Method per exponent for ``method="auto"`` (module docstring): ``(route, SH plan or None, SH set)``.

    Every finite exponent gets the cheapest of its routes by the cost models of the kernel ``impl``: the exact
    gather, the sparse gather (normalised only), the moment route (s = 1, 2 from :data:`MOMENT_MIN_PAIRS`; one call
    for both) and the shared SH pass, whose cost is set by the largest band limit of its exponents: every prefix
    of the exponents sorted by their planned band limit (:func:`ibl_ref.groundtruth.sh_convolution.plan_sh`) is
    tried, exponents within reach of L_max last (charged :data:`SH_RISK_SHARE`).  Returns the SH plan made for
    exactly the chosen SH set.  Writes the planning diagnostics and the model costs of the chosen plan and of every
    single forced method into ``info`` (``route_model_costs_s``).  ``floor_impl``: the kernel of the SH planner's
    estimate of the darkest output texel (default ``impl``; the kernel choice plans without loading the kernels)."""
    n = a4.shape[1]
    floor_impl = floor_impl or impl
    n_src, n_out = 6 * n * n, 6 * out_size * out_size
    Q = a4.shape[-1] + 1
    unit = _seconds_per_unit()
    route, plan = {}, None
    finite = [s for s in s_list if np.isfinite(s)]
    for s in s_list:
        if not np.isfinite(s):
            route[s] = "exact"
    if finite and n_out * n_src * len(finite) <= AUTO_EXACT_PAIRS:
        info["auto_tiny_map_exact"] = True
        for s in finite:
            route[s] = "exact"
        return route, None, []
    if not finite:
        return route, None, []
    c_sp = {s: (_sparse_cost(s, rtol, n_src, n_out, impl) if normalized else np.inf) for s in finite}
    mo_cand = [s for s in finite if s in MOMENT_EXPONENTS] if n_out * n_src >= MOMENT_MIN_PAIRS else []
    c_mo = _moment_cost(n, out_size, moment_leaf(n, rtol), impl) if mo_cand else np.inf
    L_of, risky = {}, set()
    rest = [s for s in finite if s not in mo_cand]
    # the SH plan unless no SH pass can beat even 4× the static model of the other routes (which can be ≈ 3× low on
    # real probes, whose contrast widens the sparse caps)
    static_other = sum(min(c_sp[s], _exact_cost(s, n_src, n_out, impl)) for s in rest)
    if not rest or _sh_cannot_pay(rest, SPARSE_STATIC_SLACK * static_other, n, n_src, n_out, Q, impl, rtol):
        info["sh_plan_skipped"] = True
    else:
        plan = shc.plan_sh(a4, finite, rtol=rtol, out_size=out_size, impl=floor_impl)
    # the sparse gather's real caps on this map (a sample of tiles), where its cost decides: its static model within
    # SPARSE_STATIC_SLACK of the exponent's own SH pass, or no SH pass planned for it
    big = []
    for i, s in enumerate(finite):
        if not (estimate and np.isfinite(c_sp[s]) and c_sp[s] * unit >= SPARSE_ESTIMATE_MIN_SECONDS):
            continue
        L_s = plan["L_per_s"][i] if plan else None
        alt = _sh_pass_cost(L_s, plan["n_bright"], n_src, n_out, 1, Q, impl) if L_s is not None else np.inf
        if s in mo_cand:
            alt = min(alt, c_mo)
        alt = min(alt, _exact_cost(s, n_src, n_out, impl))
        if alt / SPARSE_STATIC_SLACK <= c_sp[s] <= SPARSE_STATIC_SLACK * alt:
            big.append(s)
    if big:
        cand = estimate_candidates(a4, big, rtol=rtol, out_size=out_size, impl=impl)
        info["sparse_candidates_per_output"] = {_s_json(s): float(c) for s, c in zip(big, cand)}
        for s, c in zip(big, cand):
            c_sp[s] = _sparse_cost_estimated(c, n_out, impl)
    other = {}
    for s in finite:
        c_ex = _exact_cost(s, n_src, n_out, impl)
        other[s] = ("sparse", c_sp[s]) if c_sp[s] < c_ex else ("exact", c_ex)
    costs = {"exact": sum(_exact_cost(s, n_src, n_out, impl) for s in finite)}
    if normalized:
        costs["sparse"] = sum(min(c_sp[s], _exact_cost(s, n_src, n_out, impl)) for s in finite)
    if plan is not None:
        info["sh_plan_L_per_s"] = {_s_json(s): L for s, L in zip(finite, plan["L_per_s"])}
        info["sh_plan_floor"] = {_s_json(s): y for s, y in zip(finite, plan["floor"])}
        for s, L_s, r in zip(finite, plan["L_per_s"], plan["reach"]):
            if L_s is not None:
                L_of[s] = L_s
            elif r and s not in MOMENT_EXPONENTS:
                L_of[s] = SH_L_MAX
                risky.add(s)
        if L_of:
            costs["sh"] = _sh_pass_cost(max(L_of.values()), plan["n_bright"], n_src, n_out, len(finite), Q, impl)
    # SH group: a prefix of the candidates by band limit (risky ones last); the rest by moment / sparse / exact
    cand = sorted(L_of, key=lambda s: (s in risky, L_of[s]))
    nb = plan["n_bright"] if plan else 0
    best = None
    for j in range(len(cand) + 1):
        grp = cand[:j]
        rest = [s for s in finite if s not in grp]
        mo = [s for s in rest if s in mo_cand and c_mo < sum(other[x][1] for x in rest if x in mo_cand)]
        mo = [s for s in rest if s in mo_cand] if mo else []
        cost = (c_mo if mo else 0.0) + sum(other[s][1] for s in rest if s not in mo)
        if grp:
            cost += _sh_pass_cost(L_of[grp[-1]], nb, n_src, n_out, len(grp), Q, impl)
            cost += SH_RISK_SHARE * sum(other[s][1] for s in grp if s in risky)
        if best is None or cost < best[0]:
            best = (cost, grp, mo)
    cost, grp, mo = best
    grp = [s for s in finite if s in grp]  # in the order of the exponents
    for s in finite:
        route[s] = "sh" if s in grp else ("moment" if s in mo else other[s][0])
    if risky & set(grp):
        info["sh_within_reach"] = [_s_json(s) for s in grp if s in risky]
    info["auto_model_cost_s"] = float(cost * unit)
    costs["auto"] = cost
    info["route_model_costs_s"] = {k: float(v * unit) for k, v in costs.items()}
    if grp and plan is not None and len(grp) != len(finite):
        plan = shc.plan_sh(a4, grp, rtol=rtol, out_size=out_size, impl=floor_impl)  # the plan of exactly the SH set
    return route, (plan if grp else None), grp


#: work (output × source texels × exponents) from which ``kernel="auto"`` takes the compiled kernels without
#: comparing the models (their load time is then a small part)
AUTO_COMPILED_PAIRS = 2e11


def _auto_kernel(a4, s_list, method, rtol, out_size, normalized):
    """``kernel="auto"`` with numba installed: ``("compiled", None)`` when the compiled kernels are loaded in this
    process already or the work is large, else the kernel whose model cost plus load time
    (:attr:`~ibl_ref.groundtruth.kernels.KernelMethod.load_seconds`) is smaller, with a note why."""
    n = a4.shape[1]
    load_s = KERNEL_METHODS["compiled"].load_seconds
    if kernels_loaded("compiled") or 36 * n * n * out_size * out_size * len(s_list) >= AUTO_COMPILED_PAIRS:
        return "compiled", None
    cost = {}
    for impl in ("numpy", "compiled"):
        info = {}
        _route_auto(a4, s_list, rtol, out_size, normalized, info, impl, estimate=False, floor_impl="numpy")
        costs = info.get("route_model_costs_s", {})
        cost[impl] = costs.get("auto" if method == "auto" else method, costs.get("auto", 0.0))
    if cost["numpy"] <= cost["compiled"] + load_s:
        return "numpy", (f"numpy: model {cost['numpy']:.2f} s vs compiled {cost['compiled']:.2f} s + "
                         f"{load_s:.2f} s to load it")
    return "compiled", None


def plan_routes(cube, exponents, *, rtol: float = 1e-3, out_size: int | None = None, normalized: bool = True,
                kernel: str | None = None) -> dict:
    """The routes :func:`convolve` with ``method="auto"`` would take, without running them: ``{"route": {s: method},
    "model_costs_s": {"auto": …, "exact": …, "sparse": …, "sh": …}}`` (model seconds of the chosen plan and of
    each method forced for every finite exponent; "sh" only when some exponent can be planned), ``"kernel"`` and
    the planning diagnostics of ``info``."""
    a4, _ = check_cube(cube)
    a4, _k = _power_of_two_scaled(a4)
    a4 = adopt(a4, name="environment cube map")
    s_list = check_exponents(exponents)
    out_size = check_out_size(out_size, a4.shape[1])
    impl = resolve_kernel(kernel)
    info = {}
    route, _plan, _grp = _route_auto(a4, s_list, float(rtol), out_size, normalized, info, impl)
    return {"route": route, "model_costs_s": info.pop("route_model_costs_s", {}), "kernel": impl, "info": info}


def _sh_cannot_pay(finite, others, n, n_src, n_out, Q, impl="numpy", rtol=1e-3):
    """True when no SH pass can be cheaper than the other routes of ``finite`` together (model cost ``others``), by
    a lower bound of its cost: the band limit the planner could choose is never below the one the truncation
    bound needs at the most lenient target 0.8·rtol (:func:`~ibl_ref.groundtruth.sh_bounds.choose_band_limit`).
    Spares the planner (its coarse lobe averages and bound tables) where narrow lobes go to the sparse gather."""
    # first without the truncation tables (≈ 10 ms per exponent): the band limit the tables give is never below
    # band_limit_lower_bound, and the pass cost grows with L, so when the other routes are cheaper than the pass at
    # those band limits they are cheaper than the planned pass too (the same answer as below)
    lows = [band_limit_lower_bound(s, 0.8 * rtol, SH_L_MAX) for s in finite]
    lb_fast = min((_sh_pass_cost(L, 0, n_src, n_out, 1, Q, impl) for L in lows if L is not None), default=np.inf)
    if others < lb_fast:
        return True
    # then the tables, only up to L_cap, the largest band limit whose pass costs no more than the other routes (a
    # band limit above it cannot pay whatever its table says; the tables to L_cap give the same band limits as the
    # full ones: sh_bounds.choose_band_limit)
    cost = [_sh_pass_cost(L, 0, n_src, n_out, 1, Q, impl) for L in range(SH_L_MAX + 1)]
    payable = [L for L in range(SH_L_MAX + 1) if cost[L] <= others]
    if not payable:
        return True
    L_cap = payable[-1]
    rho = texel_max_radius(n)
    sh_lb = np.inf
    for s in finite:
        L = choose_band_limit(s, 0.8 * rtol, rho, L_cap)
        if L is not None:
            sh_lb = min(sh_lb, cost[L])
    return others < sh_lb


def _sh_split_state(a4, sh_set, sh_plan, rtol, out_size, normalized, impl="numpy"):
    """``("project", setup)`` when the SH pass of ``sh_set`` is big enough to split
    (:data:`SH_SPLIT_MIN_SECONDS`, decided from the sizes and the band limit), else None.  Without a plan the
    band limit is planned here (as the single job would)."""
    n = a4.shape[1]
    n_src, n_out = 6 * n * n, 6 * out_size * out_size
    Q = a4.shape[-1] + 1
    # cheap test first, with the planned band limit (without a plan, L = 32; then checked again with the band
    # limit planned here: a pass that ends up below the threshold runs as one job, which plans once more)
    L_min = (sh_plan or {}).get("L") or 32
    if shc.sh_cost(L_min, n_src, n_out, len(sh_set), Q) * shc.SECONDS_PER_UNIT < SH_SPLIT_MIN_SECONDS:
        return None
    t0 = time.perf_counter()
    setup = shc.sh_setup(a4, sh_set, rtol=rtol, out_size=out_size, normalized=normalized, plan=sh_plan, impl=impl)
    if shc.sh_cost(setup.L, n_src, n_out, len(sh_set), Q) * shc.SECONDS_PER_UNIT < SH_SPLIT_MIN_SECONDS:
        return None
    shc.sh_split(setup, SH_PARTS)
    setup.time_setup_s = time.perf_counter() - t0
    return ("project", setup)


def _round_jobs(a4, out_size, rtol, normalized, mo_set, mo_parts, sh_set, sh_plan, sparse_batches, parts, ex_set,
                mo_leaf=1, sh_state=None, impl="numpy", sparse_threads=1):
    """The independent jobs ``(stage, key, model cost, callable)`` of one round of :func:`convolve`.

    Every job computes a fixed piece of work (its exponents, its output faces) that does not depend on
    the number of workers, so the maps and bounds are bit-for-bit the same for any worker count.
    """
    n = a4.shape[1]
    n_src, n_out = 6 * n * n, 6 * out_size * out_size
    pair_units = n_out * n_src
    jobs = []
    if mo_set:
        for pi, fc in enumerate(mo_parts):
            jobs.append(("moment", ("moment", pi), _moment_cost(n, out_size, mo_leaf, impl) * len(fc) / 6,
                         functools.partial(mc.convolve_moment_many, a4, mo_set, out_size=out_size,
                                           normalized=normalized, faces=fc, leaf=mo_leaf,
                                           rtol=rtol if mo_leaf > 1 else None, impl=impl)))
    if sh_set and sh_state is not None:  # a split SH pass (:data:`SH_SPLIT_MIN_SECONDS`): one phase per round
        setup = sh_state[1]
        n_parts = setup.sym_src.n_parts
        cost = shc.sh_cost(setup.L, n_src, n_out, len(sh_set), a4.shape[-1] + 1) / (2 * n_parts)
        for i in range(n_parts):
            if sh_state[0] == "project":
                fn = functools.partial(shc.sh_project_part, setup, i)
            else:
                fn = functools.partial(shc.sh_evaluate_part, setup, sh_state[2], sh_state[3], i)
            jobs.append(("sh", ("sh", sh_state[0], i), cost, fn))
    elif sh_set:
        L_guess = (sh_plan or {}).get("L") or 32
        jobs.append(("sh", ("sh",), shc.sh_cost(L_guess, n_src, n_out, len(sh_set), a4.shape[-1] + 1),
                     functools.partial(shc.convolve_sh_many, a4, sh_set, rtol=rtol, out_size=out_size,
                                       normalized=normalized, plan=sh_plan, impl=impl)))
    for bi, (sb, sc, _att) in enumerate(sparse_batches):
        for pi, fc in enumerate(parts):
            cost = sum(_sparse_cost(x, rtol * sc, n_src, n_out, impl) for x in sb)
            cost = cost * len(fc) / 6 * SPARSE_JOB_ORDER_FACTOR if np.isfinite(cost) else (
                pair_units * _unit("EXACT_UNITS_PER_PAIR", impl))
            jobs.append(("sparse", ("sparse", bi, pi), cost,
                         functools.partial(pc.convolve_sparse_many, a4, list(sb), rtol=min(rtol * sc, 0.5),
                                           out_size=out_size, faces=fc, impl=impl, return_info=True,
                                           **({"threads": sparse_threads} if sparse_threads > 1 else {}))))
    if ex_set:
        jobs.append(("exact", ("exact",), _unit("EXACT_UNITS_PER_PAIR", impl) * pair_units * len(ex_set),
                     functools.partial(pc.convolve_exact_many, a4, ex_set, normalized=normalized,
                                       out_size=out_size)))
    return jobs


def _job_faces_exponents(fn):
    """(output faces, exponents) of a job's callable: a partial of ``(cube, exponents, ..., faces=...)``, or of
    ``(setup, ...)`` for the parts of a split SH pass (the setup's exponents; each part holds 1/parts of the
    outputs, counted as that share of the six faces)."""
    if fn.args and hasattr(fn.args[0], "s_list"):
        return 6 / fn.args[0].sym_src.n_parts, len(fn.args[0].s_list)
    return len(fn.keywords.get("faces") or range(6)), len(fn.args[1])


def _round_workers(jobs, a4, out_size, workers, executor, memory_limit, need2):
    """Workers for one round: the memory planner, and serial when the jobs are too small to pay for a
    pool (:data:`PARALLEL_MIN_SECONDS`).  Returns ``(workers, memory warning or None)``."""
    n, C = a4.shape[1], a4.shape[-1]
    job_mem = [_job_bytes(j[0], n, out_size, C, *_job_faces_exponents(j[3]), need2, j[3].keywords.get("leaf", 1))
               for j in jobs]
    avail = memory_limit if memory_limit is not None else available_memory_bytes()
    w_plan = plan_memory_workers(workers, job_mem, avail) if executor is None else workers
    est_s = sum(min(float(j[2]), 1e300) for j in jobs) * SECONDS_PER_UNIT
    if executor is None and est_s < PARALLEL_MIN_SECONDS:
        w_plan = 1  # worker start-up would not pay
    warning = None
    if avail is not None and max(job_mem) > MEMORY_FRACTION * avail:
        warning = f"a job needs ≈ {max(job_mem) / 1e9:.1f} GB, {avail / 1e9:.1f} GB available"
    return w_plan, warning


def _convolve(a4, squeeze, n, s_list, method, rtol, out_size, normalized, workers, backend, executor,
              memory_limit, scale_k, t_start, c_start, impl="numpy", kernel_note=None):
    """Body of :func:`convolve` after the argument checks: route every exponent, run rounds of independent jobs
    (route × output-face part, :func:`_round_jobs`) until every exponent has a result within ``rtol`` (or its last
    fallback), then assemble the result."""
    res = ConvolutionResult()
    if kernel_note:
        res.info["kernel_auto"] = kernel_note
    plan, finite = None, []
    if method == "auto":
        with one_blas_thread():
            route, plan, finite = _route_auto(a4, s_list, rtol, out_size, normalized, res.info, impl)
    else:
        route = {s: method for s in s_list}
    # the loops of the routes taken, ready before any worker is forked (the sparse gather is every route's fallback)
    stages = {"sparse", "moment", "sh"} & (set(route.values()) | {"sparse"})
    res.info["kernel_load_s"] = get_kernels(impl).warm_up(sorted(stages))
    rd = _Rounds(a4, s_list, route, method, rtol, out_size, normalized, impl, res.info)
    t_par = child_cpu = 0.0
    planned = []
    # one BLAS thread per worker (no oversubscription) and, serial included, the same BLAS blocking
    # for every worker count: bit-for-bit identical results (threadpoolctl restores the limits after)
    with one_blas_thread():
        while rd.mo_set or rd.sh_set or rd.sparse_batches or rd.ex_set:
            sub_plan = None
            if rd.sh_set and method == "auto":  # re-plan only if the SH subset differs from the planned set
                sub_plan = plan if list(rd.sh_set) == list(finite) else None
            if rd.sh_set and rd.sh_state is None:
                rd.sh_state = _sh_split_state(a4, rd.sh_set, sub_plan, rtol, out_size, normalized, impl)
            # a round of sparse gathers only, with a gather that shares its tiles between threads (the compiled one
            # releases the GIL): one job over all faces on `workers` threads, no pool to start, balanced tile by tile
            solo = (get_kernels(impl).gather_threads and executor is None and workers > 1 and rd.sparse_batches
                    and not (rd.mo_set or rd.sh_set or rd.ex_set))
            rd.sp_parts = (tuple(range(6)),) if solo else rd.parts
            jobs = _round_jobs(a4, out_size, rtol, normalized, rd.mo_set, rd.mo_parts, rd.sh_set, sub_plan,
                               rd.sparse_batches, rd.sp_parts, rd.ex_set, rd.mo_leaf, rd.sh_state, impl,
                               workers if solo else 1)
            w_plan, warning = _round_workers(jobs, a4, out_size, workers, executor, memory_limit, 2.0 in rd.mo_set)
            planned.append(w_plan)
            if warning:
                res.info["memory_warning"] = warning
            t0 = time.perf_counter()
            out, busy, cpu_c = _run_jobs(jobs, w_plan, backend, executor)
            t_par += time.perf_counter() - t0
            child_cpu += cpu_c
            for stage, key, _c, _f in jobs:
                # a solo sparse job's threads count as workers: its wall time × threads
                rd.stage_busy[stage] += busy[key] * (workers if solo and stage == "sparse" else 1)
            if solo:
                res.info["sparse_threads"] = workers
            rd.collect(out, busy)
    for key, fb in (("fallback_from_sh", rd.fallback_sh), ("fallback_from_sparse", rd.fallback_sparse)):
        if fb:
            res.info[key] = [_s_json(s) for s in fb]
    res.info.update(workers=workers, kernel=impl, workers_planned=min(planned) if planned else workers,
                    backend="executor" if executor is not None else backend)
    u = float(a4.data.max()) * UNDERFLOW_ABS if a4.data.size else 0.0
    for s in s_list:
        m, b, meth, kind = rd.results[s]
        b = _with_underflow(m, b, u)
        if scale_k:
            with np.errstate(over="ignore"):
                m = np.ldexp(m, scale_k)
            if not np.all(np.isfinite(m)):
                raise IBLError(f"the convolved map for s = {_s_json(s)} exceeds the float64 range "
                               "(literal Eq. 4 sum of a radiance near 1e308); use normalized=True")
        res.maps[s] = m[..., 0] if squeeze else m
        res.error_bound[s] = b
        res.method_used[s] = meth
        res.bound_kind[s] = kind
    # process CPU time (+ forked workers): robust on a loaded machine
    res.timings_s = {**rd.stage_busy, "jobs_wall": t_par, "total": time.perf_counter() - t_start,
                     "total_cpu": time.process_time() - c_start + child_cpu}
    return res


class _Rounds:
    """What each route of :func:`_convolve` still has to compute, and the results collected from its rounds of jobs:
    ``results[s] = (map, relative bound, method, bound kind)``.  An SH or sparse result that misses ``rtol`` (``auto``
    only) goes to the next round's sparse gather (once with a tighter target) and finally to the exact gather; a
    moment result with a bracket band that misses it is computed again with half the leaf."""

    def __init__(self, a4, s_list, route, method, rtol, out_size, normalized, impl, info):
        n = a4.shape[1]
        self.method, self.rtol, self.out_size, self.normalized, self.info, self.n = (method, rtol, out_size,
                                                                                    normalized, info, n)
        self.results = {}
        self.parts = self.sp_parts = FACE_PARTS
        self.mo_parts = MOMENT_FACE_PARTS_LARGE if out_size >= MOMENT_SPLIT_MIN_SIZE else FACE_PARTS
        self.mo_set = [s for s in s_list if route[s] == "moment"]
        # auto: the bracket band (rigorous bound, leaf > 1) where it is cheaper; halved while it misses rtol
        self.mo_leaf = moment_leaf(n, rtol) if method == "auto" and self.mo_set else 1
        info["moment_leaf"] = []
        self.sh_set = [s for s in s_list if route[s] == "sh"]
        self.sh_state = None  # a split SH pass: ("project", setup) then ("evaluate", setup, Be, Bo)
        self.sh_busy_parts = 0.0
        # the sparse gather aims at rtol at every texel by itself (its local bound and per-tile caps); a batch whose
        # bound still misses rtol somewhere is retried once with a tighter target, then exact
        self.sparse_batches = [b for b in [(tuple(s for s in s_list if route[s] == "sparse"), 1.0, 0)] if b[0]]
        if self.sparse_batches and normalized:
            # a sparse gather too small to pay for a pool runs as one job over all faces (each face's result is the
            # same whatever the face subset, so this changes no number)
            n_src, n_out = 6 * n * n, 6 * out_size * out_size
            sp_cost = sum(_sparse_cost(s, rtol, n_src, n_out, impl) for s in self.sparse_batches[0][0])
            if sp_cost * _seconds_per_unit() < PARALLEL_MIN_SECONDS:
                self.parts = (tuple(range(6)),)
        self.ex_set = [s for s in s_list if route[s] == "exact"]
        self.fallback_sh, self.fallback_sparse = [], []
        self.stage_busy = {"sh": 0.0, "sparse": 0.0, "exact": 0.0, "moment": 0.0}

    def _miss(self, rel) -> bool:
        return self.method == "auto" and not float(rel.max()) <= self.rtol

    def collect(self, out, busy):
        """Take one round's outputs ``out`` (job key → result) and set up the next round."""
        self._nxt_batches, self._nxt_exact = [], []
        if self.mo_set:
            self._collect_moment(out)
        if self.sh_set:
            self._collect_sh(out, busy)
        for bi, batch in enumerate(self.sparse_batches):
            self._collect_sparse(out, bi, batch)
        for k, s in enumerate(self.ex_set):
            self.results[s] = (out[("exact",)][k], np.full((6, self.out_size, self.out_size), exact_rounding(s, self.n)),
                               "exact", "rounding")
        self.sparse_batches, self.ex_set = self._nxt_batches, self._nxt_exact

    def _collect_moment(self, out):
        maps = np.concatenate([out[("moment", pi)][0] for pi in range(len(self.mo_parts))], axis=1)
        rel = np.concatenate([out[("moment", pi)][1] for pi in range(len(self.mo_parts))], axis=1)
        self.info["moment_leaf"].append(self.mo_leaf)
        retry = []
        for k, s in enumerate(self.mo_set):
            if self.mo_leaf > 1 and not float(rel[k].max()) <= self.rtol:
                retry.append(s)
                continue
            self.results[s] = (maps[k], rel[k], "moment", "rigorous" if self.mo_leaf > 1 else "rounding")
        self.mo_set = retry
        self.mo_leaf = self.mo_leaf // 2 if self.mo_leaf // 2 >= 4 else 1

    def _collect_sh(self, out, busy):
        state = self.sh_state
        if state is not None and state[0] == "project":  # the projection round of a split pass
            setup = state[1]
            n_sp = setup.sym_src.n_parts
            self.sh_busy_parts += sum(busy[("sh", "project", i)] for i in range(n_sp))
            self.sh_state = ("evaluate", setup) + sh_coefficients(setup, [out[("sh", "project", i)]
                                                                          for i in range(n_sp)])
            return
        if state is not None:  # the evaluation round of a split pass
            setup = state[1]
            n_sp = setup.sym_src.n_parts
            self.sh_busy_parts += sum(busy[("sh", "evaluate", i)] for i in range(n_sp))
            maps, rel, info = sh_assemble(setup, [out[("sh", "evaluate", i)] for i in range(n_sp)],
                                          {"time_plan_s": setup.time_setup_s, "time_parts_s": self.sh_busy_parts,
                                           "parts": n_sp})
            self.sh_state = None
        else:
            maps, rel, info = out[("sh",)]
        self.info["sh"] = dict(info)
        fb = []
        for k, s in enumerate(self.sh_set):
            if self._miss(rel[k]):
                fb.append(s)
                continue
            self.results[s] = (maps[k], rel[k], "sh", info["bound_kind"][k])
        if fb:
            self.fallback_sh += fb
            if self.normalized:
                self._nxt_batches.append((tuple(fb), 1.0, 0))
            else:
                self._nxt_exact += fb
        self.sh_set = []

    def _collect_sparse(self, out, bi, batch):
        sb, sc, att = batch
        parts = self.sp_parts
        maps = np.concatenate([out[("sparse", bi, pi)][0] for pi in range(len(parts))], axis=1)
        abs_b = np.concatenate([out[("sparse", bi, pi)][1] for pi in range(len(parts))], axis=1)
        # (output, source texel) pairs the gathers computed (all attempts), for the benchmarks
        n_src = 6 * self.n * self.n
        self.info["sparse_pairs"] = self.info.get("sparse_pairs", 0.0) + sum(
            i.gathered_fraction * len(fc) * self.out_size * self.out_size * n_src
            for pi, fc in enumerate(parts) for i in out[("sparse", bi, pi)][2])
        worst, fb = 0.0, []
        for k, s in enumerate(sb):
            rel = _rel_from_abs(maps[k], abs_b[k])
            if self._miss(rel):
                fb.append(s)
                worst = max(worst, float(rel.max()))
                continue
            self.results[s] = (maps[k], rel, "sparse", "rigorous")
        if fb and att == 0 and np.isfinite(worst):
            self._nxt_batches.append((tuple(fb), sc * 0.8 * self.rtol / worst, 1))
        elif fb:
            self.fallback_sparse += fb
            self._nxt_exact += fb
