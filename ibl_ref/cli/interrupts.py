"""Ctrl-C and ``kill`` for the ``ibl-ref`` command: at any moment, exit code 130 (SIGINT) or 143 (SIGTERM), one
line, no partial output, no worker process left running.

Not a command module (no ``cmd_`` prefix).  :func:`handling` is entered by :func:`ibl_ref.cli.main` around a
command; inside it, SIGINT and SIGTERM (``kill PID``, a batch system's time limit: without a handler Python dies at
once and the pool's worker processes go on computing, orphaned) are handled by :func:`_on_sigint`:

* **Deferred while a module is being imported.**  Some dependencies guard their optional imports with
  ``except BaseException`` (trimesh does), which swallows a ``KeyboardInterrupt`` raised inside the import and
  leaves the half-imported modules behind (a later ``NameError`` deep in scipy.ndimage).  So while the Python
  stack of the main thread contains an import (a frame of ``importlib._bootstrap``), the handler records the
  signal and re-delivers it every 20 ms until no import is running; only then is ``KeyboardInterrupt`` raised.
* **Deferred inside the commit of outputs** (:func:`ibl_ref.atomic.critical_section`): the files of one output
  set are all moved into place or none.
* **Delivered again if swallowed**: trimesh also guards some numerical fallbacks with ``except BaseException``
  (``weighted_vertex_normals``).  Once raised, the interrupt is re-sent every :data:`_RESEND_S` s until the command
  has ended, so no library can make the command carry on; ibl_ref's own clean-up (removing temporary files and
  staging folders) runs in :func:`ibl_ref.atomic.critical_section`, where a repeated interrupt waits.
* **Worker processes stop with the command**: forked workers (``convolve``) and pool workers
  (:func:`ibl_ref.executors.map_jobs`) ignore SIGINT themselves (no traceback of theirs on the terminal); when
  the interrupt is raised the handler terminates every live :mod:`multiprocessing` child, so that the command
  does not wait for their jobs.

* **An ignored SIGINT stays ignored**: a process started with SIGINT set to ``SIG_IGN`` (a ``cmd &`` job of a
  non-interactive shell, ``nohup``-like launchers) was told not to stop on Ctrl-C, as POSIX shells and Python's
  own start-up respect; :func:`handling` then installs nothing for it.  SIGTERM is handled only where it has its
  default disposition (an embedding program's own handler stays); such a job still stops on ``kill``.

Every output is written atomically or as an :class:`ibl_ref.atomic.OutputSet`, so an interrupt leaves the
previous files as they were and no temporary file behind; :func:`ibl_ref.cli.main` prints
``ibl-ref CMD: interrupted`` and returns 130 (128 + SIGINT, the shell's convention).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading

__all__ = ["handling", "interrupted", "in_import", "received_signal"]

_RETRY_S = 0.02  #: re-delivery interval of a deferred SIGINT
_RESEND_S = 0.25  #: interval at which a raised interrupt is sent again while the command still runs
_STATE = {"active": False, "received": False, "pending": False, "generation": 0, "signum": None}
_FORK_HOOK = {"registered": False}


def in_import(frame) -> bool:
    """True if ``frame`` or a caller of it belongs to the import machinery (a module is being imported)."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def interrupted() -> bool:
    """True once SIGINT arrived inside :func:`handling` (also when something swallowed the KeyboardInterrupt)."""
    return _STATE["received"]


def _redeliver(generation: int) -> None:
    # only into the block that received the signal: a timer left over from an earlier block (an in-process caller
    # that runs several commands, e.g. a test session) must not interrupt the next one
    if _STATE["generation"] != generation:
        return
    _STATE["pending"] = False
    if _STATE["active"]:
        with contextlib.suppress(OSError):
            os.kill(os.getpid(), _STATE["signum"] or signal.SIGINT)


def _later(delay: float) -> None:
    t = threading.Timer(delay, _redeliver, args=(_STATE["generation"],))
    t.daemon = True
    t.start()


def _stop_children() -> None:
    import multiprocessing

    with contextlib.suppress(Exception):
        for child in multiprocessing.active_children():
            with contextlib.suppress(Exception):
                child.terminate()


def _in_critical_section() -> bool:
    """:func:`ibl_ref.atomic.in_critical_section`, without importing anything: the handler may run in the middle of
    an import (e.g. of ``pathlib``, which :mod:`ibl_ref.atomic` imports), where a nested import of a half-initialised
    module fails; before :mod:`ibl_ref.atomic` is imported no critical section can be open."""
    atomic = sys.modules.get("ibl_ref.atomic")
    return atomic is not None and atomic.in_critical_section()


def _on_sigint(signum, frame) -> None:
    """The handler of SIGINT and SIGTERM (module docstring); which one arrived is :func:`received_signal`."""
    _STATE["received"] = True
    _STATE["signum"] = signum
    if in_import(frame) or _in_critical_section():
        if not _STATE["pending"]:
            _STATE["pending"] = True
            _later(_RETRY_S)
        return
    _stop_children()
    if not _STATE["pending"]:  # in case a library swallows the KeyboardInterrupt: send it again
        _STATE["pending"] = True
        _later(_RESEND_S)
    raise KeyboardInterrupt


def _child_after_fork() -> None:
    if _STATE["active"]:  # a worker forked by a command: the command handles Ctrl-C, the worker keeps quiet, and
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # the command's terminate() (SIGTERM) ends it at once
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def received_signal():
    """The signal (``signal.SIGINT`` or ``signal.SIGTERM``) that interrupted the last :func:`handling` block, or
    None."""
    return _STATE["signum"] if _STATE["received"] else None


@contextlib.contextmanager
def handling():
    """Install :func:`_on_sigint` for SIGINT (unless ignored) and SIGTERM (unless ignored or handled by the
    embedding program) for the block; main thread only, elsewhere a no-op."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _STATE.update(received=False, signum=None)
    old = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        h = signal.getsignal(sig)
        if h is signal.SIG_IGN or (sig == signal.SIGTERM and h is not signal.SIG_DFL):
            continue  # an inherited SIG_IGN stays; a SIGTERM handler of the embedding program stays its own
        try:
            old[sig] = signal.signal(sig, _on_sigint)
        except (ValueError, OSError):  # pragma: no cover - no signals here (embedded interpreter)
            pass
    if not old:
        yield
        return
    if not _FORK_HOOK["registered"] and hasattr(os, "register_at_fork"):
        os.register_at_fork(after_in_child=_child_after_fork)
        _FORK_HOOK["registered"] = True
    _STATE.update(active=True, received=False, pending=False, generation=_STATE["generation"] + 1)
    try:
        yield
    finally:
        _STATE.update(active=False, generation=_STATE["generation"] + 1)  # pending timers of this block expire
        for sig, h in old.items():
            signal.signal(sig, h)
