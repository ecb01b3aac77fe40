"""Where independent jobs run: serially, on local worker processes, or on any ``concurrent.futures.Executor``.

One small API for every part of the lab whose work splits into independent jobs (the convolution's routes and
face groups, the reference renderer's pixel blocks, the cases of an experiment sweep):

``resolve_executor(spec)``
    an Executor from ``spec``: ``None`` (stays ``None``), any :class:`concurrent.futures.Executor`, a
    ``dask.distributed.Client`` (its ``get_executor()``) or a Dask scheduler address ``"tcp://host:8786"``
    (extra ``dask``).  Returns ``(executor, owned_client)``; close ``owned_client`` when done.
``map_jobs(fn, items, executor=None, workers=1, desc=None)``
    ``[fn(item) for item in items]`` in input order: serially (``workers=1``, no executor), on ``workers``
    local processes, or on ``executor``.  ``fn`` and the items must be picklable for the last two (module-level
    functions).  Results do not depend on where or in which order the jobs ran, so a job that is itself
    deterministic gives bit-for-bit the serial result (every job, serial ones included, runs with BLAS held at
    one thread: multi-threaded BLAS sums in an order that depends on its thread count, which differs between
    the caller, local worker processes and Dask workers).  Jobs run elsewhere report no progress of their own
    (:func:`ibl_ref.progress.quiet`); ``desc`` counts finished jobs.  A worker that dies (e.g. killed for lack of memory) is
    an :class:`ibl_ref.errors.IBLError` naming the likely cause, never a ``BrokenProcessPool`` traceback.

Dask workers should run one thread each (``dask worker ADDRESS --nthreads 1``): the jobs are NumPy-bound.
"""

from __future__ import annotations

import contextlib
import sys
import threading

from .errors import IBLError
from .progress import quiet

__all__ = ["resolve_executor", "map_jobs", "worker_died", "one_blas_thread", "CONNECT_TIMEOUT_S"]

#: seconds to wait for a Dask scheduler address to answer (announced before waiting)
CONNECT_TIMEOUT_S = 30.0


def resolve_executor(executor):
    """``(executor, owned_client)`` from an Executor, a ``dask.distributed.Client``, a scheduler address or None."""
    if executor is None:
        return None, None
    if isinstance(executor, str):
        try:
            from distributed import Client
        except ImportError:
            raise IBLError("a scheduler address needs dask.distributed: pip install \".[dask]\"") from None
        from .progress import say

        # an address with nothing behind it only fails after the timeout: say so before waiting
        say(f"connecting to the Dask scheduler at {executor} (waiting up to {CONNECT_TIMEOUT_S:g} s) …")
        try:
            client = Client(executor, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError) as exc:
            raise IBLError(f"cannot connect to the Dask scheduler at {executor!r} within {CONNECT_TIMEOUT_S:g} s: "
                           f"{exc}") from None
        return client.get_executor(), client
    if hasattr(executor, "get_executor") and hasattr(executor, "scheduler_info"):  # dask.distributed.Client
        return executor.get_executor(), None
    if not hasattr(executor, "submit"):
        raise IBLError(f"executor must be a concurrent.futures.Executor, a dask Client or an address, got {executor!r}")
    return executor, None


def worker_died(exc, what: str = "worker") -> IBLError:
    """The one-line error for a worker process that died before finishing its job."""
    return IBLError(
        f"a {what} process died before finishing its job (most likely killed by the operating system for lack "
        f"of memory: {type(exc).__name__}); retry with fewer workers (--workers 1) or a smaller size")


_BLAS_LOCK = threading.Lock()
_BLAS_HOLD = {"users": 0, "limiter": None}
#: the threadpoolctl controller of the libraries loaded so far, and the ``len(sys.modules)`` it was built at
_BLAS_CTL = {"modules": -1, "ctl": None}


def _blas_controller():
    """A ``ThreadpoolController`` of the loaded thread pools, built again only after new modules were imported
    (building one scans the process's shared libraries, ≈ 1–6 ms; applying a limit with it costs ≈ 0.1 ms)."""
    from threadpoolctl import ThreadpoolController

    n_mod = len(sys.modules)
    if _BLAS_CTL["ctl"] is None or _BLAS_CTL["modules"] != n_mod:
        _BLAS_CTL["ctl"] = ThreadpoolController()
        _BLAS_CTL["modules"] = n_mod
    return _BLAS_CTL["ctl"]


@contextlib.contextmanager
def one_blas_thread():
    """Hold BLAS at one thread inside the block (threadpoolctl).  Reference-counted: jobs that overlap in threads
    of one process keep the limit until the last of them ends, which then restores the original thread count
    (a plain ``threadpool_limits`` per job would let the first job to end lift the limit under the others);
    nested blocks cost nothing."""
    with _BLAS_LOCK:
        if _BLAS_HOLD["users"] == 0:
            _BLAS_HOLD["limiter"] = _blas_controller().limit(limits=1, user_api="blas")
        _BLAS_HOLD["users"] += 1
    try:
        yield
    finally:
        with _BLAS_LOCK:
            _BLAS_HOLD["users"] -= 1
            if _BLAS_HOLD["users"] == 0:
                _BLAS_HOLD["limiter"].restore_original_limits()
                _BLAS_HOLD["limiter"] = None


def _worker_ignores_sigint() -> None:
    """Initializer of the local worker processes: Ctrl-C is the caller's to handle (it stops the workers), so a
    worker prints no traceback of its own."""
    import signal

    with contextlib.suppress(ValueError, OSError):
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _job(fn, x, silent: bool = True):
    """``fn(x)`` with BLAS held at one thread (``silent``: and its progress reports silenced, as on a worker).

    Multi-threaded BLAS splits sums between threads, so a job's last digits would depend on how many BLAS
    threads the process it lands on has (a Dask worker sets one, a local process the machine's count); held
    at one everywhere, the job gives the same bits serially, on local processes and on a cluster.
    """

    with one_blas_thread(), (quiet() if silent else contextlib.nullcontext()):
        return fn(x)


def map_jobs(fn, items, executor=None, workers: int = 1, desc: str | None = None, what: str = "worker",
             unit: str = "job", cost=None) -> list:
    """``[fn(x) for x in items]`` in order, serially, on ``workers`` local processes, or on ``executor``.

    ``executor``: anything :func:`resolve_executor` accepts (it wins over ``workers``).  ``desc``: a progress
    label (:mod:`ibl_ref.progress`, one tick of ``unit`` per finished job).  Jobs run serially report their own
    progress nested in this one; jobs run elsewhere run silenced (:func:`ibl_ref.progress.quiet`).  ``cost``:
    optional relative cost per item; jobs run elsewhere are then submitted most expensive first (the longest job
    does not start last), the results still come back in the order of ``items``.
    """
    items = list(items)
    if cost is not None:
        cost = [float(c) for c in cost]
        if len(cost) != len(items):
            raise IBLError(f"cost has {len(cost)} entries for {len(items)} jobs")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise IBLError(f"workers must be a positive integer (1 = serial), got {workers!r}")
    ex, owned = resolve_executor(executor)  # after the checks: an address opens a client that must be closed
    prog = None
    if desc:
        from .progress import callback

        prog = callback(desc, total=len(items), unit=unit)
    try:
        # BLAS held at one thread from this (calling) thread for the whole map: OpenBLAS does not always honour
        # a limit set from a worker thread once the main thread has set one; jobs in other processes set theirs
        with one_blas_thread():
            return _run_all(fn, items, ex, workers, prog, what, cost)
    finally:
        if prog:
            prog.close()
        if owned is not None:
            owned.close()


def _run_all(fn, items, ex, workers, prog, what, cost=None) -> list:
    from concurrent.futures import BrokenExecutor, ProcessPoolExecutor

    if ex is None and (workers <= 1 or len(items) <= 1):
        out = []
        for x in items:
            out.append(_job(fn, x, silent=False))
            if prog:
                prog()
        return out
    pool = None
    if ex is None:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn" if "fork" not in multiprocessing.get_all_start_methods()
                                          else "forkserver")
        pool = ex = ProcessPoolExecutor(max_workers=min(workers, len(items)), mp_context=ctx,
                                        initializer=_worker_ignores_sigint)
    from concurrent.futures import as_completed

    order = list(range(len(items))) if cost is None else sorted(range(len(items)), key=lambda i: -cost[i])
    try:
        index = {ex.submit(_job, fn, items[i]): i for i in order}
        out = [None] * len(items)
        for f in as_completed(index):  # progress counts jobs as they finish, whatever their order
            out[index[f]] = f.result()
            if prog:
                prog()
        return out
    except BrokenExecutor as exc:
        raise worker_died(exc, what) from None
    except KeyboardInterrupt:  # do not wait for the running jobs: stop our workers (they ignore SIGINT)
        if pool is not None:
            for proc in list((getattr(pool, "_processes", None) or {}).values()):
                with contextlib.suppress(Exception):
                    proc.terminate()
        raise
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
