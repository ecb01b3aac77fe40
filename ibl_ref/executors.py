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

``keeping_jobs(folder, label, fresh=False)``
    a context in which every ``map_jobs`` call keeps each finished job's result in ``folder`` (a :class:`JobStore`)
    and takes the results it already holds instead of running their jobs again: an interrupted or crashed run
    loses no finished job.  :func:`ibl_ref.experiments.run_experiment` runs every experiment inside one, so a rerun
    of the same command runs only the jobs that had not finished; outside it, ``map_jobs`` keeps nothing.  A job
    is known by its function, its item and the code (:func:`code_fingerprint`): the result of a job is assumed
    to depend on nothing else.  Only the ``map_jobs`` calls made directly in the block keep jobs (jobs that run
    serially and map jobs of their own keep none of those), and the results are written by the calling process,
    as they arrive, wherever the jobs ran.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import hashlib
import os
import pickle
import re
import sys
import threading
import warnings
from pathlib import Path

from .errors import IBLError, IBLWarning
from .progress import quiet

__all__ = ["resolve_executor", "map_jobs", "worker_died", "one_blas_thread", "CONNECT_TIMEOUT_S", "JobStore",
           "keeping_jobs", "code_fingerprint"]

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
    does not start last), the results still come back in the order of ``items``.  Inside :func:`keeping_jobs`,
    the jobs whose results the store holds are not run again and every other result is stored as it arrives.
    """
    items = list(items)
    if cost is not None:
        cost = [float(c) for c in cost]
        if len(cost) != len(items):
            raise IBLError(f"cost has {len(cost)} entries for {len(items)} jobs")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise IBLError(f"workers must be a positive integer (1 = serial), got {workers!r}")
    store = _STORE.get()
    token = _STORE.set(None)  # a job run here (serially) that maps jobs of its own keeps none of them
    owned = prog = None
    try:
        ex, owned = resolve_executor(executor)  # after the checks: an address opens a client that must be closed
        keys, out, todo = (store.recall(fn, items) if store is not None else
                           (None, [None] * len(items), list(range(len(items)))))
        if desc:
            from .progress import callback

            prog = callback(desc, total=len(items), unit=unit)
            if len(todo) < len(items):
                prog(len(items) - len(todo))

        def arrived(j, result):
            out[todo[j]] = result
            if keys is not None:
                store.save(keys[todo[j]], result)
            if prog:
                prog()

        # BLAS held at one thread from this (calling) thread for the whole map: OpenBLAS does not always honour
        # a limit set from a worker thread once the main thread has set one; jobs in other processes set theirs
        with one_blas_thread():
            _run_all(fn, [items[i] for i in todo], ex, workers, arrived, what,
                     None if cost is None else [cost[i] for i in todo])
        return out
    finally:
        if prog:
            prog.close()
        if owned is not None:
            owned.close()
        _STORE.reset(token)


def _run_all(fn, items, ex, workers, arrived, what, cost=None) -> None:
    """Run ``fn`` on every item; ``arrived(j, result)`` for each result, as it arrives (``j``: its index in
    ``items``).  When the run stops early (a job's error, a dead worker, Ctrl-C), the jobs not yet started are
    cancelled and the results that arrived meanwhile are handed on before the error is raised (on our own worker
    processes, but for Ctrl-C, the jobs already running finish first)."""
    from concurrent.futures import BrokenExecutor, ProcessPoolExecutor

    if ex is None and (workers <= 1 or len(items) <= 1):
        for j, x in enumerate(items):
            arrived(j, _job(fn, x, silent=False))
        return
    pool = None
    if ex is None:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn" if "fork" not in multiprocessing.get_all_start_methods()
                                          else "forkserver")
        pool = ex = ProcessPoolExecutor(max_workers=min(workers, len(items)), mp_context=ctx,
                                        initializer=_worker_ignores_sigint)
    from concurrent.futures import as_completed

    order = list(range(len(items))) if cost is None else sorted(range(len(items)), key=lambda i: -cost[i])
    index = {}
    try:
        index = {ex.submit(_job, fn, items[j]): j for j in order}
        for f in as_completed(index):  # results are handed on as they arrive, whatever their order
            arrived(index.pop(f), f.result())
    except BaseException as exc:
        if pool is not None:
            if isinstance(exc, KeyboardInterrupt):
                # do not wait for the running jobs: stop our workers (they ignore SIGINT)
                for proc in list((getattr(pool, "_processes", None) or {}).values()):
                    with contextlib.suppress(Exception):
                        proc.terminate()
            pool.shutdown(wait=True, cancel_futures=True)  # otherwise the jobs already running finish
        _hand_on_finished(index, arrived)
        if isinstance(exc, BrokenExecutor):
            raise worker_died(exc, what) from None
        raise
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)


def _hand_on_finished(index: dict, arrived) -> None:
    """``arrived`` for every future of ``index`` that finished with a result (a run that stops early keeps them)."""
    for f, j in list(index.items()):
        with contextlib.suppress(Exception):
            if f.done() and not f.cancelled() and f.exception(timeout=0) is None:
                arrived(j, f.result(timeout=0))


# ------------------------------------------------------------------------------------------------------------------
# the job store: finished jobs kept on disk while an experiment runs
# ------------------------------------------------------------------------------------------------------------------
#: the store that :func:`map_jobs` keeps jobs in (set by :func:`keeping_jobs`; None: none)
_STORE: contextvars.ContextVar = contextvars.ContextVar("ibl_ref_job_store", default=None)

#: first line of every job file (its format); a file without it is not one of the lab's
JOB_FILE_MAGIC = b"ibl_ref job result 1\n"
#: installed distributions whose version can change a job's numbers (one that is absent counts as absent)
NUMERIC_DISTRIBUTIONS = ("numpy", "scipy", "trimesh", "numba", "embreex", "mitsuba")
_JOB_FILE = re.compile(r"[0-9a-f]{64}\.job\Z")


@functools.cache
def code_fingerprint(root=None) -> str:
    """A hash of the code that computes a job: every file of the ``ibl_ref`` package (``root``; its sources and
    its data, not ``__pycache__`` nor hidden files), Python's version, the versions of
    :data:`NUMERIC_DISTRIBUTIONS` and ``$IBL_REF_KERNEL`` (which kernels run).

    Parameters
    ----------
    root : path, optional
        The package folder (default: the installed ``ibl_ref``).

    Returns
    -------
    str
        A SHA-256 hex digest; any edit of the package gives another one.  Computed once per process and root.
    """
    from importlib import metadata

    root = Path(__file__).parent if root is None else Path(root)
    h = hashlib.sha256()
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root)
        if "__pycache__" in rel.parts or any(part.startswith(".") for part in rel.parts) or not path.is_file():
            continue
        h.update(f"{rel.as_posix()}\0{path.stat().st_size}\0".encode())
        h.update(path.read_bytes())
    versions = [sys.version]
    for dist in NUMERIC_DISTRIBUTIONS:
        try:
            versions.append(f"{dist}={metadata.version(dist)}")
        except metadata.PackageNotFoundError:
            versions.append(f"{dist}=absent")
    versions.append(f"IBL_REF_KERNEL={os.environ.get('IBL_REF_KERNEL', '')}")
    h.update("\0".join(versions).encode())
    return h.hexdigest()


def _job_name(fn) -> str:
    """``module.qualname`` of a job function (what the store's warnings call it)."""
    return f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', type(fn).__name__)}"


class JobStore:
    """Finished jobs' results in a folder, one file a job, for a run that resumes where an earlier one stopped.

    A job's file is ``KEY.job`` with ``KEY`` = SHA-256 of :func:`code_fingerprint`, the job function's
    ``module.qualname`` and the pickle of ``(function, item)`` (a module-level function pickles as its module and
    name; an item as its values): the same job of the same code finds its file, any other job or code another
    key.  The file holds :data:`JOB_FILE_MAGIC`, then the SHA-256 of the pickle that follows, then that pickle
    (``{"key", "result"}``), written atomically (:func:`ibl_ref.atomic.atomic_write`).  A file that is damaged,
    truncated or not the lab's is ignored with one warning (:class:`~ibl_ref.errors.IBLWarning`) and its job
    runs again; a store that cannot be written (read-only folder, full disk) is given up with one warning and the
    run goes on without it.

    Parameters
    ----------
    folder : path
        The store's folder (created when the first result is saved).
    label : str
        What the messages start with (an experiment's name).
    fingerprint : str, optional
        The code's fingerprint (default: :func:`code_fingerprint`).
    """

    def __init__(self, folder, label: str, fingerprint: str | None = None):
        self.folder = Path(folder)
        self.label = label
        self._fingerprint = fingerprint
        self.enabled = True
        self._saved: set = set()  # keys written by this run (found again: not from an interrupted run)
        self._unkeyable: set = set()  # job functions whose jobs cannot be keyed (warned once each)

    @property
    def fingerprint(self) -> str:
        """The code's fingerprint (:func:`code_fingerprint`, computed when the first job is keyed)."""
        if self._fingerprint is None:
            self._fingerprint = code_fingerprint()
        return self._fingerprint

    def path(self, key: str) -> Path:
        """The file of the job ``key``."""
        return self.folder / f"{key}.job"

    def key(self, fn, item) -> str | None:
        """The key of the job ``fn(item)``; None (one warning per function) if it cannot be pickled."""
        try:
            blob = pickle.dumps((fn, item), protocol=4)
        except Exception as exc:  # a lambda, a local function, an item with an open file ...
            name = _job_name(fn)
            if name not in self._unkeyable:
                self._unkeyable.add(name)
                self._warn(f"the jobs of {name} are not kept (they do not pickle: {type(exc).__name__})")
            return None
        h = hashlib.sha256()
        for part in (self.fingerprint.encode(), _job_name(fn).encode(), blob):
            h.update(len(part).to_bytes(8, "little"))
            h.update(part)
        return h.hexdigest()

    def load(self, key: str):
        """``(True, result)`` if the store holds the job ``key``, else ``(False, None)`` (one warning if its file
        is there but unusable)."""
        path = self.path(key)
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            return False, None
        except OSError as exc:
            return self._unusable(path, f"unreadable: {exc.strerror or exc}")
        head, _, rest = data.partition(b"\n")
        digest, _, payload = rest.partition(b"\n")
        if head + b"\n" != JOB_FILE_MAGIC:
            return self._unusable(path, "not a job file of ibl_ref")
        if digest.decode("ascii", "replace") != hashlib.sha256(payload).hexdigest():
            return self._unusable(path, "damaged or truncated: its checksum does not match")
        try:
            record = pickle.loads(payload)
        except Exception as exc:  # checksum right but not loadable here (a class that no longer exists)
            return self._unusable(path, f"cannot be loaded: {type(exc).__name__}: {exc}")
        if not isinstance(record, dict) or record.get("key") != key or "result" not in record:
            return self._unusable(path, "written for another job")
        return True, record["result"]

    def save(self, key: str, result) -> None:
        """Write the job ``key``'s result atomically; on failure give the store up (one warning)."""
        from .atomic import atomic_write

        if not self.enabled:
            return
        try:
            payload = pickle.dumps({"key": key, "result": result}, protocol=4)
        except Exception as exc:
            return self._give_up(f"a result does not pickle ({type(exc).__name__}: {exc})")
        try:
            with atomic_write(self.path(key), "wb") as fh:
                fh.write(JOB_FILE_MAGIC + hashlib.sha256(payload).hexdigest().encode("ascii") + b"\n" + payload)
        except (OSError, IBLError) as exc:  # OutputError: a folder that cannot be created or written, a full disk
            return self._give_up(str(exc))
        self._saved.add(key)

    def recall(self, fn, items):
        """``(keys, results, todo)`` for the jobs ``fn(x) for x in items``: their keys (None if they cannot be
        kept), the stored results (None where there is none) and the indices of the jobs still to run; says how
        many were kept from an earlier run."""
        results = [None] * len(items)
        if self.enabled and (self.folder.exists() or self.folder.is_symlink()) and not self.folder.is_dir():
            self._give_up("it is not a folder")
        if not self.enabled:
            return None, results, list(range(len(items)))
        keys = []
        for x in items:
            k = self.key(fn, x)
            if k is None:
                return None, results, list(range(len(items)))
            keys.append(k)
        todo, kept = [], 0
        for i, k in enumerate(keys):
            hit, value = self.load(k)
            if hit:
                results[i] = value
                kept += k not in self._saved
            else:
                todo.append(i)
        if kept:
            from .progress import say

            say(f"{self.label}: {kept} of {len(items)} jobs kept from an interrupted run in {self.folder}")
        return keys, results, todo

    def files(self) -> list:
        """The job files in the store (none if it does not exist)."""
        try:
            return sorted(p for p in self.folder.iterdir() if _JOB_FILE.match(p.name))
        except OSError:
            return []

    def discard(self) -> int:
        """Remove the store's job files (and temporary files of writers that are gone), then its folder if that
        leaves it empty; returns how many job files were removed.  Files that are not the store's stay."""
        from .atomic import clean_stale_temps

        removed = 0
        for p in self.files():
            with contextlib.suppress(OSError):
                p.unlink()
                removed += 1
            clean_stale_temps(self.folder, p.name)
        with contextlib.suppress(OSError):
            for p in self.folder.iterdir():  # a writer killed before its first rename left only its temporary file
                m = re.match(r"\.([0-9a-f]{64}\.job)\.ibl-tmp-", p.name)
                if m:
                    clean_stale_temps(self.folder, m.group(1))
        with contextlib.suppress(OSError):
            self.folder.rmdir()
        return removed

    def _unusable(self, path: Path, why: str):
        self._warn(f"ignoring {path} ({why}); running its job again")
        return False, None

    def _give_up(self, why: str) -> None:
        self.enabled = False
        self._warn(f"cannot keep finished jobs in {self.folder} ({why}); going on without keeping them")

    def _warn(self, text: str) -> None:
        warnings.warn(f"{self.label}: {text}", IBLWarning, stacklevel=4)


@contextlib.contextmanager
def keeping_jobs(folder, label: str, fresh: bool = False):
    """Keep the finished jobs of every :func:`map_jobs` call in the block in a :class:`JobStore` at ``folder``.

    Jobs whose results the store holds (from an earlier run that did not finish) are not run again.  When the
    block ends normally the store is removed (its work is done); when it fails (an error, Ctrl-C, a dead worker)
    the store stays for the next run, or its folder is removed if it holds no job.

    Parameters
    ----------
    folder : path
        The store's folder.
    label : str
        What the store's messages start with (an experiment's name).
    fresh : bool
        Discard the jobs the store holds first: everything runs again.

    Yields
    ------
    JobStore
    """
    store = JobStore(folder, label)
    if fresh:
        n = store.discard()
        if n:
            from .progress import say

            say(f"{label}: {n} job(s) kept from an interrupted run in {store.folder} discarded (--fresh)")
    token = _STORE.set(store)
    try:
        yield store
    except BaseException:
        with contextlib.suppress(OSError):
            store.folder.rmdir()  # only if empty: a store with jobs stays
        raise
    finally:
        _STORE.reset(token)
    store.discard()
