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
    deterministic gives bit-for-bit the serial result.  A worker that dies (e.g. killed for lack of memory) is
    an :class:`ibl_ref.errors.IBLError` naming the likely cause, never a ``BrokenProcessPool`` traceback.

Dask workers should run one thread each (``dask worker ADDRESS --nthreads 1``): the jobs are NumPy-bound.
"""

from __future__ import annotations

from .errors import IBLError

__all__ = ["resolve_executor", "map_jobs", "worker_died"]


def resolve_executor(executor):
    """``(executor, owned_client)`` from an Executor, a ``dask.distributed.Client``, a scheduler address or None."""
    if executor is None:
        return None, None
    if isinstance(executor, str):
        try:
            from distributed import Client
        except ImportError:
            raise IBLError("a scheduler address needs dask.distributed: pip install \".[dask]\"") from None
        try:
            client = Client(executor, timeout=30)
        except (OSError, TimeoutError) as exc:
            raise IBLError(f"cannot connect to the Dask scheduler at {executor!r}: {exc}") from None
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


def map_jobs(fn, items, executor=None, workers: int = 1, desc: str | None = None, what: str = "worker") -> list:
    """``[fn(x) for x in items]`` in order, serially, on ``workers`` local processes, or on ``executor``.

    ``executor``: anything :func:`resolve_executor` accepts (it wins over ``workers``).  ``desc``: a progress
    label (:mod:`ibl_ref.progress`, one tick per finished job).
    """
    from concurrent.futures import BrokenExecutor, ProcessPoolExecutor

    items = list(items)
    ex, owned = resolve_executor(executor)
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise IBLError(f"workers must be a positive integer (1 = serial), got {workers!r}")
    prog = None
    if desc:
        from .progress import callback

        prog = callback(desc, total=len(items), unit="job")
    try:
        if ex is None and (workers <= 1 or len(items) <= 1):
            out = []
            for x in items:
                out.append(fn(x))
                if prog:
                    prog()
            return out
        pool = None
        if ex is None:
            import multiprocessing

            ctx = multiprocessing.get_context("spawn" if "fork" not in multiprocessing.get_all_start_methods()
                                              else "forkserver")
            pool = ex = ProcessPoolExecutor(max_workers=min(workers, len(items)), mp_context=ctx)
        try:
            futs = [ex.submit(fn, x) for x in items]
            out = []
            for f in futs:
                out.append(f.result())
                if prog:
                    prog()
            return out
        except BrokenExecutor as exc:
            raise worker_died(exc, what) from None
        finally:
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
    finally:
        if prog:
            prog.close()
        if owned is not None:
            owned.close()
