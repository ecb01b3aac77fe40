"""Progress reporting for long work: a bar on a terminal, periodic one-line status in logs.

One small API that every long step uses (experiments, ``reproduce``, the renderer, the PEM and exact-lobe-chain
builds, the Kautz–McCool prefilter, the command-line tools; library functions take ``progress=True`` and call
:func:`track` with ``enabled=progress``):

``track(iterable, desc, total=None, unit="it", enabled=True)``
    iterate with progress.  On a terminal (the stream's ``isatty()``) a tqdm bar that disappears when done;
    otherwise a line ``desc (10 it) …`` when it starts, one line ``desc: 3/10 it (30 %), 12.3 s`` at most every
    ``interval`` seconds (``$IBL_REF_PROGRESS_INTERVAL``, default 10 s) and a final ``desc: 10/10 it (100 %),
    31.0 s`` if it took that long — no carriage-return bars in non-terminal logs.  ``enabled=False`` returns the
    iterable untouched.
``step(desc)``
    context manager for one block of work: prints ``desc …`` when it starts and ``desc: done in 3.2 s`` on
    its own line when it ends (``.update(done, total)`` inside reports intermediate progress; a block that
    reports nothing for an interval gets a line ``desc: running, 1 min 10 s`` per interval).
``callback(desc, total, unit)``
    a plain function ``cb(n=1)`` advancing a counter, plus ``cb.close()`` — the form a library function can
    accept as ``progress=`` without importing this module's classes.
``quiet()``
    context manager silencing all progress of the current thread (jobs that run on worker processes or a
    cluster: :func:`ibl_ref.executors.map_jobs` runs each job inside it, so only the caller reports).

Nested progress in a log (a loop over cases whose every case runs a loop over directions) stays within the
limit: only the outermost loop prints its start and end lines, and the periodic line, at most one every
``interval`` seconds for all loops together, shows every active level: ``cases: 1/9 case (11 %), 1 min 3 s ›
exact visibility: 120/400 dir (30 %), 12.0 s``.

Everything goes to ``sys.stderr`` (``stream=`` to change); ``$IBL_REF_PROGRESS=0`` silences it all
(tests and scripted runs), ``=bar`` / ``=lines`` forces one style.  Every message starts on a fresh line:
a line printed while a bar is active first ends the bar's line (nothing is glued to a bar).
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time

__all__ = ["track", "step", "callback", "Progress", "mode", "say", "quiet"]

_ACTIVE_BARS: list = []
_LINES: list = []  # active line-mode counters, outermost first
_LAST_LINE = [0.0]  # time of the last periodic line (all line-mode counters share one rate limit)
_LOCK = threading.RLock()
_LOCAL = threading.local()


def mode(stream=None) -> str:
    """``"bar"`` on a terminal, ``"lines"`` otherwise, ``"off"`` if ``$IBL_REF_PROGRESS=0`` or inside :func:`quiet`."""
    if getattr(_LOCAL, "quiet", 0):
        return "off"
    env = os.environ.get("IBL_REF_PROGRESS", "").strip().lower()
    if env in ("0", "off", "no", "false"):
        return "off"
    if env in ("bar", "lines"):
        return env
    stream = sys.stderr if stream is None else stream
    try:
        return "bar" if stream.isatty() else "lines"
    except (AttributeError, ValueError):
        return "lines"


@contextlib.contextmanager
def quiet():
    """Silence every progress report of the current thread inside the block (other threads keep theirs)."""
    _LOCAL.quiet = getattr(_LOCAL, "quiet", 0) + 1
    try:
        yield
    finally:
        _LOCAL.quiet -= 1


def _interval() -> float:
    try:
        return max(0.0, float(os.environ.get("IBL_REF_PROGRESS_INTERVAL", "10")))
    except ValueError:
        return 10.0


def say(msg: str, stream=None) -> None:
    """Print one status line, never glued to a bar (tqdm.write clears and redraws active bars)."""
    stream = sys.stderr if stream is None else stream
    if mode(stream) == "off":
        return
    if _ACTIVE_BARS:
        from tqdm import tqdm

        tqdm.write(msg, file=stream)
    else:
        print(msg, file=stream, flush=True)


def _plural(unit: str, n) -> str:
    """``light`` → ``lights`` for counts other than 1 (tqdm's short units such as ``it`` stay as they are)."""
    return unit if n == 1 or len(unit) <= 2 or unit.endswith("s") else unit + "s"


def _fmt_time(t: float) -> str:
    return f"{t:.1f} s" if t < 120 else f"{int(t // 60)} min {t % 60:.0f} s"


class Progress:
    """Counter with a bar (terminal) or periodic status lines (logs); see the module docstring."""

    def __init__(self, desc: str, total: int | None = None, unit: str = "it", stream=None):
        self.desc, self.total, self.unit = desc, total, unit
        self.stream = sys.stderr if stream is None else stream
        self.mode = mode(self.stream)
        self.n = 0
        self.t0 = time.perf_counter()
        self._bar = None
        self._closed = False
        self._outer = False
        if self.mode == "bar":
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=desc, unit=unit, file=self.stream, leave=False, dynamic_ncols=True)
            _ACTIVE_BARS.append(self._bar)
        elif self.mode == "lines":
            with _LOCK:
                self._outer = not _LINES
                _LINES.append(self)
                if self._outer:  # nested counters stay silent until the shared periodic line
                    _LAST_LINE[0] = self.t0
                    size = f" ({total} {_plural(unit, total)})" if total else ""
                    print(f"{desc}{size} …", file=self.stream, flush=True)

    def _state(self, now: float) -> str:
        el = _fmt_time(now - self.t0)
        if self.total:
            return f"{self.desc}: {self.n}/{self.total} {_plural(self.unit, self.total)} ({100.0 * self.n / self.total:.0f} %), {el}"
        return f"{self.desc}: {self.n} {_plural(self.unit, self.n)}, {el}"

    def update(self, n: int = 1) -> None:
        self.n += n
        if self._bar is not None:
            self._bar.update(n)
        elif self.mode == "lines":
            now = time.perf_counter()
            if now - _LAST_LINE[0] >= _interval() and not (self.total and self.n >= self.total):
                with _LOCK:
                    _LAST_LINE[0] = now
                    line = " › ".join(p._state(now) for p in _LINES) if self in _LINES else self._state(now)
                print(line, file=self.stream, flush=True)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._bar is not None:
            self._bar.close()
            _ACTIVE_BARS.remove(self._bar)
        elif self.mode == "lines":
            with _LOCK:
                if self in _LINES:
                    _LINES.remove(self)
            now = time.perf_counter()
            if self._outer and now - self.t0 >= _interval():
                print(self._state(now), file=self.stream, flush=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def _track(iterable, desc, total, unit, stream):
    with Progress(desc, total, unit, stream) as p:
        for item in iterable:
            yield item
            p.update(1)


def track(iterable, desc: str, total: int | None = None, unit: str = "it", stream=None, enabled: bool = True):
    """Yield the items of ``iterable`` while reporting progress (bar or status lines).

    ``enabled=False`` (a library function's ``progress=False``) returns ``iterable`` itself: no counter at all.
    """
    if not enabled:
        return iterable
    if total is None:
        try:
            total = len(iterable)
        except TypeError:
            total = None
    return _track(iterable, desc, total, unit, stream)


class _Step:
    def __init__(self, desc, stream):
        self.desc, self.stream = desc, stream
        self.t0 = time.perf_counter()
        self.elapsed = 0.0

    def update(self, done, total=None) -> None:
        """Report intermediate progress of the step (rate-limited like :class:`Progress`)."""
        now = time.perf_counter()
        if now - _LAST_LINE[0] >= _interval():
            _LAST_LINE[0] = now
            frac = f" ({100.0 * done / total:.0f} %)" if total else ""
            say(f"{self.desc}: {done}{'/' + str(total) if total else ''}{frac}, {_fmt_time(now - self.t0)}",
                self.stream)


@contextlib.contextmanager
def step(desc: str, stream=None, announce: bool = True, enabled: bool = True):
    """Time a block: ``desc …`` at the start, ``desc: done in X s`` on its own line at the end.

    A block left by an exception prints no ``done`` line (the caller reports the error).  ``enabled=False``
    (a library function's ``progress=False``) prints nothing.
    """
    s = _Step(desc, sys.stderr if stream is None else stream)
    if not enabled:
        yield s
        s.elapsed = time.perf_counter() - s.t0
        return
    if announce:
        say(f"{desc} …", s.stream)
    _LAST_LINE[0] = s.t0
    beat = _Heartbeat(s) if mode(s.stream) != "off" and _interval() >= HEARTBEAT_MIN_INTERVAL else None
    try:
        yield s
    finally:
        s.elapsed = time.perf_counter() - s.t0
        if beat is not None:
            beat.stop()
    say(f"{desc}: done in {_fmt_time(s.elapsed)}", s.stream)


#: a :func:`step` longer than the interval reports ``desc: running, 1 min 10 s`` once per interval when nothing
#: else printed in that interval (work without a counter, e.g. one long convolution job), if the interval is at
#: least this many seconds (``IBL_REF_PROGRESS_INTERVAL=0``, every update printed, has no heartbeat)
HEARTBEAT_MIN_INTERVAL = 1.0


class _Heartbeat:
    """Daemon thread printing the elapsed time of a :class:`_Step` while no other line was printed."""

    def __init__(self, s: _Step):
        self.s = s
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, name="ibl_ref-progress-heartbeat", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        period = _interval()
        while not self.done.wait(period):
            with _LOCK:
                now = time.perf_counter()
                if self.done.is_set() or now - _LAST_LINE[0] < period:
                    continue
                _LAST_LINE[0] = now
                say(f"{self.s.desc}: running, {_fmt_time(now - self.s.t0)}", self.s.stream)

    def stop(self) -> None:
        with _LOCK:
            self.done.set()
        self.thread.join()


def callback(desc: str, total: int | None = None, unit: str = "it", stream=None):
    """A function ``cb(n=1)`` that advances a :class:`Progress`; ``cb.close()`` ends it.

    For library functions that take ``progress=`` as a plain callable: they call ``progress(1)`` per unit of
    work and need not know how (or whether) it is shown.
    """
    p = Progress(desc, total, unit, stream)

    def cb(n: int = 1):
        p.update(n)

    cb.close = p.close
    cb.progress = p
    return cb
