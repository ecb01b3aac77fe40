"""Atomic file output and tabular results with units.

Every file ibl_ref writes goes through :func:`atomic_write`: the content is written to a temporary
file in the destination folder and moved over the destination with :func:`os.replace`, so a crash or
an error never leaves a half-written file and never destroys the previous version.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import tempfile
from pathlib import Path

from .errors import IBLError

__all__ = ["atomic_write", "atomic_path", "write_csv", "write_json", "OutputError"]


class OutputError(IBLError):
    """An output file or folder cannot be written."""


def _check_dir(path: Path) -> Path:
    parent = path.resolve().parent
    if not parent.exists():
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"{path}: cannot create output folder {parent}: {exc.strerror}") from exc
    if not os.access(parent, os.W_OK):
        raise OutputError(f"{path}: output folder {parent} is not writable")
    if path.exists() and path.is_dir():
        raise OutputError(f"{path}: is a folder, expected a file path")
    return parent


@contextlib.contextmanager
def atomic_path(path, suffix: str | None = None):
    """Yield a temporary path next to ``path``; on success it replaces ``path`` atomically.

    Use for writers that need a file name (e.g. OpenEXR, matplotlib).  On error the temporary file is
    removed and ``path`` is left as it was.
    """
    path = Path(path)
    parent = _check_dir(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix, dir=parent)
    os.close(fd)
    # mkstemp creates 0600 files; give the result the mode a plain open() would (0666 & ~umask)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_write(path, mode: str = "w", **kwargs):
    """Open a temporary file for writing; it replaces ``path`` only if the block succeeds."""
    with atomic_path(path) as tmp:
        with open(tmp, mode, **kwargs) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())


def write_csv(path, rows, columns=None, comment: str | None = None):
    """Write a list of dicts as CSV atomically.

    Column names should carry their units, e.g. ``time_s``, ``rel_err_max``, ``memory_MB``.
    ``comment`` lines (``# ...``) go before the header.
    """
    rows = list(rows)
    if columns is None:
        columns = []
        for r in rows:
            for k in r:
                if k not in columns:
                    columns.append(k)
    buf = io.StringIO()
    if comment:
        for line in comment.splitlines():
            buf.write(f"# {line}\n")
    w = csv.DictWriter(buf, fieldnames=list(columns), lineterminator="\n", extrasaction="raise")
    w.writeheader()
    for r in rows:
        w.writerow(r)
    with atomic_write(path, newline="") as fh:
        fh.write(buf.getvalue())
    return Path(path)


def _json_default(o):
    import numpy as np

    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


def write_json(path, data):
    """Write ``data`` as indented JSON atomically (NaN/Inf are rejected: they are not JSON)."""
    text = json.dumps(data, indent=2, default=_json_default, allow_nan=False, sort_keys=False)
    with atomic_write(path) as fh:
        fh.write(text + "\n")
    return Path(path)


def read_csv(path):
    """Read a CSV written by :func:`write_csv` (skipping ``#`` comment lines) into a list of dicts."""
    with open(path, newline="") as fh:
        lines = [ln for ln in fh if not ln.startswith("#")]
    return list(csv.DictReader(lines))
