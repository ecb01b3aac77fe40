"""Atomic file output and tabular results with units.

Every file ibl_ref writes goes through :func:`atomic_path` / :func:`atomic_write` (one file) or
:class:`OutputSet` (several files that belong together).  The rules:

* **Temporary file beside the target.**  The content goes to ``.NAME.ibl-tmp-PID-RANDOM[.ext]`` in the
  destination folder, is flushed and ``fsync``-ed, then moved over the destination with
  :func:`os.replace`; the folder is ``fsync``-ed after the rename (POSIX: a rename is durable only once
  its directory entry is).  A crash or an error never leaves a half-written file under the final name
  and never destroys the previous version.
* **Leftovers are recognisable and cleaned.**  A killed run (SIGKILL, power loss) can leave its
  temporary file behind.  The ``.ibl-tmp-PID-`` tag names the writing process; the next write to the
  same target removes every such leftover whose process no longer exists (:func:`clean_stale_temps`).
* **Only regular files are replaced.**  A target that is a device (``/dev/full``), a FIFO, a socket or
  a folder is refused with :class:`OutputError` before anything is written.  A **symlink is written
  through**: its final target is replaced atomically and the link itself is kept (a dangling link gets
  its target created).
* **Multi-file outputs are committed as a unit** (:class:`OutputSet`): every file is first written into
  a staging folder ``.MANIFEST.ibl-tmp-PID-RANDOM/`` beside the manifest; only when all of them were
  written are they moved into place, the JSON manifest last, and files that the *previous* manifest
  listed but the new run did not produce (a ``pem`` rerun with fewer lights, ``convolve`` with other
  exponents) are deleted.  A failure while writing (full disk, overflow, interrupt) leaves the previous
  outputs and manifest exactly as they were.
* **Inputs are never outputs**: :func:`refuse_overwriting_inputs` rejects an output path that names
  the same file as an input (``render --env X --out X``), before any work.
* **Side files never destroy a file the lab did not write** (:func:`check_side_files`, enforced again by
  :class:`OutputSet`).  A command writes the paths the user named, and *side files*: the JSON manifest ``OUT.json``
  of ``render``, ``km00-render`` and ``convolve``, ``convolve``'s ``OUT_s{S}.exr``, ``km00-render --png``'s
  ``OUT.png``, the files inside an output folder the user named (``pem --out DIR``'s ``pems.json`` and
  ``pem_NNN.exr``, an experiment's files and its manifest ``NAME_outputs.json``).  A side file is written only where
  no file of its name exists, or over a file that the previous run for the same output wrote: the manifest of an
  ibl_ref output set — recognised by the marker :data:`MANIFEST_MARKER` that :meth:`OutputSet.commit` puts in every
  manifest, not by its shape (a user's JSON with an ``"outputs"`` list is the user's) — and the files it lists.
  Anything else is refused with one line naming the file, before any work where the command knows its files up
  front.
* **Concurrent commits of one output set do not mix**: :meth:`OutputSet.commit` holds an exclusive lock
  (``flock``) on the manifest's folder while it reads the previous manifest, moves the files and removes the stale
  ones, so of two runs into one folder the later commit replaces the earlier one's set whole.
* OS errors while writing (``ENOSPC``, ``EROFS``, ``EACCES`` …) become :class:`OutputError` naming the
  file and the reason.
* **Folders created for an output that failed are removed** (when still empty): a failed or interrupted run
  leaves no empty folder behind (:func:`output_folder`).
* **Ctrl-C never splits a commit**: the renames of :class:`OutputSet` (and of :func:`atomic_path`) run in a
  :func:`critical_section`, which holds SIGINT back until they are done.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import json
import os
import re
import shutil
import stat
from pathlib import Path

from .errors import IBLError

__all__ = [
    "atomic_write",
    "atomic_path",
    "write_csv",
    "write_json",
    "read_csv",
    "OutputError",
    "OutputSet",
    "TEMP_TAG",
    "clean_stale_temps",
    "ensure_output_dir",
    "refuse_overwriting_inputs",
    "resolve_output",
    "output_folder",
    "check_side_files",
    "MANIFEST_MARKER",
    "critical_section",
    "in_critical_section",
]

TEMP_TAG = ".ibl-tmp-"  #: marker in every temporary file / staging folder name (followed by the PID)
#: key that :meth:`OutputSet.commit` puts first in every manifest it writes (value: the manifest format, 1): the lab
#: replaces a manifest, and the files it lists, only where this marker says the lab wrote it
MANIFEST_MARKER = "ibl_ref_manifest"


class OutputError(IBLError):
    """An output file or folder cannot be written."""


_CRITICAL = {"depth": 0}


def in_critical_section() -> bool:
    """True inside :func:`critical_section` (the CLI's SIGINT handler defers the interrupt then)."""
    return _CRITICAL["depth"] > 0


@contextlib.contextmanager
def critical_section():
    """Hold SIGINT back inside the block; an interrupt received meanwhile is delivered when it ends.

    Used around renames that must happen all together (:meth:`OutputSet.commit`).  Only the main thread
    receives signals; elsewhere the block just runs.
    """
    import signal
    import threading

    _CRITICAL["depth"] += 1
    got, old = [], None
    if threading.current_thread() is threading.main_thread() and _CRITICAL["depth"] == 1:
        with contextlib.suppress(ValueError, OSError):
            old = signal.signal(signal.SIGINT, lambda signum, frame: got.append(signum))
    try:
        yield
    finally:
        _CRITICAL["depth"] -= 1
        if old is not None:
            signal.signal(signal.SIGINT, old)
            if got:
                signal.raise_signal(signal.SIGINT)  # to the handler that was installed before the block


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket"),
                       (stat.S_ISDIR, "a folder")):
        if test(mode):
            return name
    return "not a regular file"


def _reason(exc: OSError) -> str:
    return exc.strerror or str(exc)


def resolve_output(path) -> Path:
    """The file that a write to ``path`` really replaces: ``path`` itself or, for a symlink, its final target.

    Raises :class:`OutputError` if that file exists and is not a regular file (device, FIFO, socket,
    folder) or the symlink chain cannot be resolved (a loop).
    """
    path = Path(path)
    real = path
    if path.is_symlink():
        try:
            real = Path(os.path.realpath(path, strict=False))
        except OSError as exc:  # pragma: no cover - realpath(strict=False) only fails on odd platforms
            raise OutputError(f"{path}: cannot resolve the symlink: {_reason(exc)}") from exc
        if real.is_symlink():  # realpath stops at a loop
            raise OutputError(f"{path}: symlink loop, cannot write through it")
    try:
        st = os.stat(real)
    except FileNotFoundError:
        return real
    except NotADirectoryError:
        return real  # a parent is a file: reported by _check_dir
    except OSError as exc:
        raise OutputError(f"{path}: cannot inspect the output path: {_reason(exc)}") from exc
    if stat.S_ISDIR(st.st_mode):
        raise OutputError(f"{path}: is a folder, expected a file path")
    if not stat.S_ISREG(st.st_mode):
        raise OutputError(f"{path}: is {_kind(st.st_mode)}; ibl_ref only replaces regular files "
                          "(choose a file path)")
    return real


def _missing_dirs(folder: Path) -> list:
    """The folders ``folder.mkdir(parents=True)`` would create, deepest first."""
    out = []
    for anc in [folder, *folder.parents]:
        if anc.exists() or anc.is_symlink():
            break
        out.append(anc)
    return out


def _remove_empty(created) -> None:
    """Remove the folders of ``created`` (deepest first) that are still empty; never anything else."""
    for d in created:
        with contextlib.suppress(OSError):
            d.rmdir()  # fails (and is skipped) if anything is inside


def ensure_output_dir(folder, what: str = "output folder", created: list | None = None) -> Path:
    """Create ``folder`` (and parents) if needed; clear :class:`OutputError` if it cannot be a writable folder.

    ``created``: a list that receives the folders this call made (deepest first), for removal on failure.
    """
    folder = Path(folder)
    for anc in [folder, *folder.parents]:
        if anc.exists() or anc.is_symlink():
            if not anc.is_dir():
                raise OutputError(f"{folder}: cannot create {what}: {anc} is a file, not a folder")
            break
    missing = _missing_dirs(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        _remove_empty([d for d in missing if d.is_dir()])
        raise OutputError(f"{folder}: cannot create {what}: {_reason(exc)}") from exc
    if created is not None:
        created.extend(missing)
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"{folder}: {what} is not writable")
    return folder


@contextlib.contextmanager
def output_folder(folder, what: str = "output folder", remove_tree: bool = False, keep=None):
    """Create ``folder`` for the block (:func:`ensure_output_dir`); if the block fails (an error, Ctrl-C), the
    folders created here are removed again when they are empty: a failed run leaves no empty folder.

    ``remove_tree=True`` (an experiment's own folder): a folder this block created is removed with everything in
    it — it did not exist before the run, so all it holds is the failed run's partial output — unless ``keep()``
    (a function, asked after the failure) is true: the failed run left something the next run wants (the finished
    jobs of an experiment, :func:`ibl_ref.executors.keeping_jobs`)."""
    created: list = []
    folder = ensure_output_dir(folder, what, created)
    try:
        yield folder
    except BaseException:
        with critical_section():  # a repeated Ctrl-C waits for the clean-up
            if remove_tree and created and not (keep is not None and keep()):
                shutil.rmtree(created[-1], ignore_errors=True)  # the outermost folder this block made
            _remove_empty(created)
        raise


def _check_dir(path: Path, created: list | None = None) -> Path:
    return ensure_output_dir(path.parent if str(path.parent) else Path("."), f"output folder for {path.name}",
                             created)


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:  # pragma: no cover
        return True
    return True


def clean_stale_temps(folder, name: str) -> list:
    """Remove leftovers ``.NAME.ibl-tmp-PID-*`` in ``folder`` whose process ``PID`` is gone; returns their paths.

    Files and staging folders of a live process (a concurrent writer) are left alone.
    """
    folder = Path(folder)
    pat = re.compile(re.escape(f".{name}{TEMP_TAG}") + r"(\d+)-[0-9a-f]+")
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for e in entries:
        m = pat.match(e.name)
        if not m or _pid_alive(int(m.group(1))):
            continue
        with contextlib.suppress(OSError):
            if e.is_dir(follow_symlinks=False):
                shutil.rmtree(e.path)
            else:
                os.unlink(e.path)
            removed.append(Path(e.path))
    return removed


def _temp_name(name: str, suffix: str) -> str:
    return f".{name}{TEMP_TAG}{os.getpid()}-{os.urandom(4).hex()}{suffix}"


def _fsync_path(p, directory: bool = False) -> None:
    flags = os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0)
    try:
        fd = os.open(p, flags)
    except OSError:
        if directory:  # some file systems do not allow opening folders; durability is best-effort there
            return
        raise
    try:
        os.fsync(fd)
    except OSError as exc:
        if not directory or exc.errno not in (errno.EINVAL, errno.EBADF, errno.ENOTSUP):
            raise
    finally:
        os.close(fd)


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


@contextlib.contextmanager
def atomic_path(path, suffix: str | None = None):
    """Yield a temporary path next to ``path``; on success it replaces ``path`` atomically.

    Use for writers that need a file name (e.g. OpenEXR, matplotlib).  The temporary file is fsync-ed
    before the rename and the folder after it.  On error the temporary file is removed and ``path`` is
    left as it was; an ``OSError`` of the writer (full disk, read-only file system) becomes
    :class:`OutputError` naming ``path``.  See the module docstring for symlinks and special files.
    """
    path = Path(path)
    real = resolve_output(path)
    created: list = []
    parent = _check_dir(real, created)
    clean_stale_temps(parent, real.name)
    tmp = parent / _temp_name(real.name, suffix if suffix is not None else real.suffix)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666 & ~_umask())
        os.close(fd)
    except OSError as exc:
        _remove_empty(created)
        raise OutputError(f"{path}: cannot create a file in {parent}: {_reason(exc)}") from exc
    try:
        yield tmp
        _fsync_path(tmp)
        with critical_section():
            os.replace(tmp, real)
        _fsync_path(parent, directory=True)
    except BaseException as exc:
        with critical_section(), contextlib.suppress(OSError):  # a repeated Ctrl-C waits for the clean-up
            os.unlink(tmp)
            if not real.exists():
                _remove_empty(created)
        if isinstance(exc, OSError) and not isinstance(exc, IBLError):
            raise OutputError(f"{path}: cannot write: {_reason(exc)}") from exc
        raise


@contextlib.contextmanager
def atomic_write(path, mode: str = "w", **kwargs):
    """Open a temporary file for writing; it replaces ``path`` only if the block succeeds."""
    with atomic_path(path) as tmp:
        with open(tmp, mode, **kwargs) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def refuse_overwriting_inputs(inputs: dict, outputs: dict) -> None:
    """Raise :class:`OutputError` if an output path names the same file as an input path.

    ``inputs`` and ``outputs`` map a label (the CLI flag or argument name, e.g. ``"--env"``) to a path
    (dicts or lists of ``(label, path)`` pairs; ``None`` paths are skipped).  Symlinks and hard links are
    seen through.
    """
    inputs = list(inputs.items()) if isinstance(inputs, dict) else list(inputs)
    outputs = list(outputs.items()) if isinstance(outputs, dict) else list(outputs)
    for ol, op in outputs:
        if op is None:
            continue
        for il, ip in inputs:
            if ip is None:
                continue
            if Path(op).exists() and Path(ip).exists() and _same_file(Path(op), Path(ip)):
                raise OutputError(f"{ol} {op}: is the same file as the input {il} {ip}; refusing to overwrite "
                                  "the input (choose another output path)")


def _entry(e, relative: bool):
    """A manifest entry as the name it stands for: its base name, or (``relative``) its path relative to the
    manifest's folder (POSIX, no ``..``, not absolute, no temporary name); None if it is none."""
    if not isinstance(e, str) or not e:
        return None
    if not relative:
        name = Path(e).name
        return name if name not in ("", ".", "..") and TEMP_TAG not in name else None
    parts = Path(e).parts
    if Path(e).is_absolute() or not parts or any(q in ("", ".", "..") or TEMP_TAG in q for q in parts):
        return None
    return Path(*parts).as_posix()


def _manifest_names(path: Path, owned_key: str, relative: bool = False):
    """Names listed under ``owned_key`` by the lab's JSON manifest at ``path`` (base names, or paths relative to its
    folder); None if it is not a manifest the lab wrote (no :data:`MANIFEST_MARKER`, or no list under the key)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get(MANIFEST_MARKER) != 1:
        return None
    entries = data.get(owned_key)
    if not isinstance(entries, list):
        return None
    return {n for n in (_entry(e, relative) for e in entries) if n is not None}


def _foreign_manifest(manifest: Path, label: str) -> OutputError:
    return OutputError(f"{label}: {manifest} exists and was not written by ibl_ref for this output (no "
                       f"'{MANIFEST_MARKER}' marker); refusing to replace it (move it away or choose another output "
                       "name)")


def _foreign_file(f: Path, manifest: Path, label: str) -> OutputError:
    return OutputError(f"{label}: {f} exists and was not written by the previous run for this output (not listed in "
                       f"{manifest.name}); refusing to replace a file you did not name (move it away or choose another "
                       "output name)")


def check_side_files(manifest, side=(), owned_key: str = "outputs", label: str = "--out",
                     relative: bool = False) -> None:
    """Refuse (:class:`OutputError`) to replace a file the lab did not write (module docstring), before any work.

    ``manifest``: the side-file JSON manifest of the output set (e.g. ``OUT.json``); ``side``: the other side
    files the run will write.  Each may exist only if it is that manifest (a JSON object with the lab's
    :data:`MANIFEST_MARKER` and a list under ``owned_key``) or a file the manifest lists (by base name, or with
    ``relative`` by its path relative to the manifest's folder).  ``label`` names the option of the output.
    """
    manifest = Path(manifest)
    listed = None
    if manifest.exists() or manifest.is_symlink():
        listed = _manifest_names(manifest, owned_key, relative)
        if listed is None:
            raise _foreign_manifest(manifest, label)
    for f in side:
        f = Path(f)
        if (f.exists() or f.is_symlink()) and (listed is None or _listed_name(f, manifest, relative) not in listed):
            raise _foreign_file(f, manifest, label)


def _listed_name(f: Path, manifest: Path, relative: bool) -> str:
    """The name under which a manifest lists the file ``f``."""
    if not relative:
        return f.name
    try:
        return Path(os.path.relpath(os.path.abspath(f), os.path.abspath(manifest.parent))).as_posix()
    except ValueError:  # pragma: no cover - another drive (Windows)
        return f.name


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
    try:
        text = json.dumps(data, indent=2, default=_json_default, allow_nan=False, sort_keys=False)
    except ValueError as exc:  # NaN / Inf: refuse, naming the file (the previous file stays)
        raise OutputError(f"{path}: cannot write NaN or Inf to JSON ({exc})") from exc
    with atomic_write(path) as fh:
        fh.write(text + "\n")
    return Path(path)


def write_npz(path, arrays: dict):
    """Write ``arrays`` as a compressed ``.npz`` atomically (the previous file stays until it is complete)."""
    import numpy as np

    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    return Path(path)


def read_csv(path):
    """Read a CSV written by :func:`write_csv` (skipping ``#`` comment lines) into a list of dicts."""
    with open(path, newline="") as fh:
        lines = [ln for ln in fh if not ln.startswith("#")]
    return list(csv.DictReader(lines))


@contextlib.contextmanager
def _folder_lock(folder: Path):
    """An exclusive ``flock`` on ``folder`` for the block (best effort: where the file system has no locks, none)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        yield
        return
    try:
        with contextlib.suppress(OSError):
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


class OutputSet:
    """Several output files committed as a unit; the JSON manifest is written last.

    Usage::

        with OutputSet(folder / "pems.json", owned_key="files") as outs:
            for i, level in ...:
                write_pyramid(outs.path(folder / f"pem_{i:03d}.exr"), ...)   # staged, not yet visible
            outs.commit({"files": [...], ...})                              # move into place, manifest last

    :meth:`path` returns a staging path inside ``.MANIFEST.ibl-tmp-PID-RANDOM/`` in the final file's
    folder; :meth:`staging_folder` returns that folder of the manifest's own folder for a writer that writes many
    files (an experiment): everything in it is committed, subfolders included, under the same relative paths.
    :meth:`commit` writes the manifest (with :data:`MANIFEST_MARKER`) into the staging folder too (so every write
    that needs disk space happens before anything is replaced), fsyncs the staged files, and — holding a lock on the
    manifest's folder (concurrent commits of one set do not mix) — renames them over their final names and the
    manifest last, then deletes the files the previous manifest listed under ``owned_key`` that this run did not
    produce, except the paths in ``keep`` (e.g. the inputs).  Leaving the block without :meth:`commit` (an
    exception) removes the staging folders and leaves the previous outputs and manifest untouched.

    A file is replaced only if the user named it (``named``) or the previous manifest — one the lab wrote, with
    its marker — lists it; a manifest without the marker is never replaced (module docstring).  Manifest entries
    are base names looked up in the manifest's folder, or with ``relative=True`` paths relative to it.
    """

    def __init__(self, manifest, owned_key: str = "files", keep=(), remove_stale: bool = True, named=(),
                 relative: bool = False, label: str = "--out"):
        self.manifest = Path(manifest)
        self.owned_key = owned_key
        self.remove_stale = remove_stale  # False: never delete files of the previous run (render's OUT.json)
        self.relative = relative
        self.label = label
        self._real_manifest = resolve_output(self.manifest)
        if (self.manifest.exists() or self.manifest.is_symlink()) and self._previous_names() is None:
            raise _foreign_manifest(self.manifest, label)
        self._created: list = []  # folders made for this set: removed again (if empty) when it fails
        self.folder = _check_dir(self._real_manifest, self._created)
        self.keep = [Path(k) for k in keep if k is not None]
        self.named = {Path(os.path.realpath(n)) for n in named if n is not None}
        self._staged: dict = {}  # real final path -> (staged path, given path)
        self._stage_dirs: dict = {}  # folder -> staging folder
        self._adopt = None  # staging folder whose whole content is committed (staging_folder)
        self.committed = False
        self.removed_stale: list = []

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if isinstance(exc, IBLError) and exc.args and isinstance(exc.args[0], str):
            msg = exc.args[0]  # name the final file, not its staging path
            for staged, given in self._staged.values():
                msg = msg.replace(str(staged), str(given))
            if self._adopt is not None:
                msg = msg.replace(str(self._adopt), str(self.manifest.parent))
            exc.args = (msg,) + exc.args[1:]
        with critical_section():  # a repeated Ctrl-C waits for the clean-up
            self._cleanup()
            if not self.committed:
                _remove_empty(self._created)
        return False

    def _cleanup(self):
        for d in self._stage_dirs.values():
            shutil.rmtree(d, ignore_errors=True)
        self._stage_dirs.clear()

    def _stage_dir(self, folder: Path) -> Path:
        key = os.path.realpath(folder)
        if key not in self._stage_dirs:
            clean_stale_temps(folder, self._real_manifest.name)
            d = folder / _temp_name(self._real_manifest.name, "")
            try:
                d.mkdir()
            except OSError as exc:
                raise OutputError(f"{self.manifest}: cannot create a staging folder in {folder}: {_reason(exc)}") from exc
            self._stage_dirs[key] = d
        return self._stage_dirs[key]

    def _previous_names(self):
        return _manifest_names(self._real_manifest, self.owned_key, self.relative)

    def _check_replace(self, real: Path, given: Path, listed) -> None:
        """Refuse to replace an existing file that the user did not name and the previous manifest does not list."""
        if not (given.exists() or given.is_symlink()) or Path(os.path.realpath(real)) in self.named:
            return
        if listed is None or _listed_name(given, self.manifest, self.relative) not in listed:
            raise _foreign_file(given, self.manifest, self.label)

    def path(self, final) -> Path:
        """Staging path for the output file ``final`` (pass it to any writer)."""
        if self.committed:
            raise OutputError(f"{self.manifest}: output set already committed")
        final = Path(final)
        real = resolve_output(final)
        self._check_replace(real, final, self._previous_names())
        folder = _check_dir(real, self._created)
        clean_stale_temps(folder, real.name)
        key = Path(os.path.realpath(real))
        if key in self._staged:
            raise OutputError(f"{final}: named twice in one output set")
        staged = self._stage_dir(folder) / real.name
        self._staged[key] = (staged, final)
        return staged

    def staging_folder(self) -> Path:
        """A staging folder for the manifest's folder: every file written into it (subfolders too) is committed into
        the manifest's folder under the same relative path (entries of the manifest: relative paths)."""
        if self.committed:
            raise OutputError(f"{self.manifest}: output set already committed")
        self._adopt = self._stage_dir(self.folder)
        return self._adopt

    def _adopt_staged(self, staged_manifest: Path) -> list:
        """Register every file of :meth:`staging_folder` as staged; returns their paths relative to the folder."""
        rel = []
        if self._adopt is None:
            return rel
        owned = {s for s, g in self._staged.values()} | {staged_manifest}
        for root, dirs, files in os.walk(self._adopt):
            dirs.sort()
            for name in sorted(files):
                src = Path(root) / name
                if src in owned:
                    continue
                r = src.relative_to(self._adopt)
                given = self.manifest.parent / r
                self._staged[Path(os.path.realpath(self.folder / r))] = (src, given)
                rel.append(r.as_posix())
        return rel

    def commit(self, manifest_data) -> Path:
        """Move the staged files into place, write ``manifest_data`` as the manifest (with :data:`MANIFEST_MARKER`
        first; a dict), delete stale files."""
        missing = [str(g) for s, g in self._staged.values() if not s.exists()]
        if missing:
            raise OutputError(f"{self.manifest}: output file(s) were never written: {', '.join(missing)}")
        # everything that needs disk space happens in the staging folder: a full disk fails here
        staged_manifest = self._stage_dir(self.folder) / self._real_manifest.name
        adopted = self._adopt_staged(staged_manifest)
        data = {MANIFEST_MARKER: 1, **(manifest_data or {})}
        if adopted and self.owned_key not in data:
            data[self.owned_key] = adopted
        write_json(staged_manifest, data)
        with _folder_lock(self.folder):  # a concurrent commit of the same set waits for this one
            listed = self._previous_names()
            if (self.manifest.exists() or self.manifest.is_symlink()) and listed is None:
                raise _foreign_manifest(self.manifest, self.label)
            for real, (staged, given) in self._staged.items():
                self._check_replace(real, given, listed)
            old_owned = sorted(listed or ()) if self.remove_stale else []
            try:
                for real, (staged, given) in self._staged.items():
                    _fsync_path(staged)
                    real.parent.mkdir(parents=True, exist_ok=True)  # a subfolder of an adopted staging folder
                with critical_section():  # Ctrl-C: every file moved into place, or none
                    for real, (staged, given) in self._staged.items():
                        os.replace(staged, real)
                    os.replace(staged_manifest, self._real_manifest)  # the manifest last
                    self.committed = True
                for folder in {real.parent for real in self._staged} | {self.folder}:
                    _fsync_path(folder, directory=True)
            except OSError as exc:
                raise OutputError(f"{self.manifest}: cannot move the outputs into place: {_reason(exc)}") from exc
            self._remove_stale(old_owned)
        self._cleanup()
        return self.manifest

    def _remove_stale(self, old_owned) -> None:
        produced = set(self._staged) | {Path(os.path.realpath(self._real_manifest))}
        protected = {Path(os.path.realpath(k)) for k in self.keep}
        owner = self.manifest.parent  # names are relative to the manifest as given (not its symlink target)
        for name in old_owned:
            cand = owner / name
            key = Path(os.path.realpath(cand))
            if key in produced or key in protected or cand.is_symlink() or not cand.is_file():
                continue
            with contextlib.suppress(OSError):
                os.unlink(cand)
                self.removed_stale.append(cand)
                for d in cand.parents:  # a subfolder the stale files emptied (relative entries)
                    if d == owner or owner not in d.parents:
                        break
                    d.rmdir()
