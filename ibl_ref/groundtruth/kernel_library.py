"""The compiled kernels of the Phong-lobe convolution (Knuth et al. 2014, Sec. 3.2, Eq. 4), loaded and called.

The kernels are numba source (:mod:`ibl_ref.groundtruth.compiled_kernels`).  Importing numba and loading its cached
machine code costs a process ≈ 0.45 s (measured by ``benchmarks/bench_peer.py``: ``import numba`` and "load the
compiled kernels"), more than the whole convolution of a small map.  So the kernels are compiled **ahead of time**
once per installation and machine, and later processes load them without numba:

1. **Build** (the first process that needs them, with numba installed): every kernel of
   :data:`ibl_ref.groundtruth.kernel_spec.KERNELS` is compiled by numba as a C callable (``numba.cfunc``) that
   takes its arrays as pointers and shapes (optimised for this CPU's features, with 512-bit vectors where it has
   AVX-512: :func:`_features`; numba then compiles them in a child process, as only its start-up configuration
   sets that); the optimised LLVM module of each is turned into machine code for this CPU (llvmlite's target
   machine, the options of numba's JIT) and written, with the symbol names, into one file
   (atomically); where a C compiler driver is installed (``$CC``, ``cc``, ``gcc`` or ``clang``, Linux/BSD) the
   same modules are also linked, as position-independent code, into a shared library beside it.  That is the
   compile cost a user pays once (cold and warm costs: ``benchmarks/bench_peer.py``).
2. **Load** (every process, the builder included): the shared library is opened with ctypes (≈ 1–5 ms, no
   llvmlite); without one, llvmlite's MCJIT links the file's machine code into the process (≈ 0.02 s for
   ``import llvmlite.binding``, a few ms for the code).  Each kernel is called through ctypes, which releases the
   GIL during the call, so threads run kernels in parallel as with numba's ``nogil``.

The files are keyed by the kernel sources, the numba and llvmlite versions, the Python version and the CPU (as
``/proc/cpuinfo`` reports it, else llvmlite's host CPU name and features): an edit of a kernel, an upgrade or
another machine builds new files; a file that does not load (damaged, foreign) is built again, a shared library
that does not open is passed over for the file's machine code.  They live in ``$NUMBA_CACHE_DIR/ibl_ref_kernels``
when that variable is set, else in ``__pycache__`` next to this module, else in ``$XDG_CACHE_HOME/ibl_ref``
(``~/.cache/ibl_ref``).

Where the ahead-of-time path is not possible — no writable folder, llvmlite unable to load the code, numba's
bounds checking on (``NUMBA_BOUNDSCHECK``, a test mode), or ``$IBL_REF_KERNEL_BACKEND=jit`` — the kernels are
numba's JIT functions of :mod:`~ibl_ref.groundtruth.compiled_kernels` with numba's own cache (one line on stderr
says why, unless numba's cache note says it already).  Both backends run the same kernels and give the same
numbers up to the order of the float64 sums (the ahead-of-time code may use wider vectors; the tests, which run
every compiled check on both, hold them within that rounding); :data:`BACKEND` says which one runs.

Routes call the functions of this module (:func:`tile_gather`, …, with the arguments of the kernels of the same
name minus their work arrays, which are allocated here); :func:`ibl_ref.groundtruth.kernel_choice.compiled` loads
the backend first.
"""

from __future__ import annotations

import ctypes
import importlib.util
import json
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

from ..errors import IBLError
from .kernel_spec import BRIGHT_GROUP, KERNELS, POINT_BLOCK, SH_BLOCK, VEC

__all__ = ["BACKEND", "BACKEND_ENV", "NOTE", "FORMAT", "artifact_path", "build", "load", "use", "loaded", "warm_up",
           "tile_scratch_size", "bright_groups", "tile_gather", "tile_bounds", "cone_extremes", "cap_count", "band_exact",
           "band_brackets", "point_gather", "sh_values_bounds", "sh_project", "sh_matrix"]

#: environment variable: ``jit`` forces numba's JIT backend, ``aot`` (or unset) the ahead-of-time one where possible
BACKEND_ENV = "IBL_REF_KERNEL_BACKEND"
#: version of the file format and of the generated C callables (part of the key)
FORMAT = "ibl_ref-kernels-2"
#: ``"aot"`` or ``"jit"`` once :func:`load` has run, else None
BACKEND = None
#: why the JIT backend runs instead of the ahead-of-time one (None: no reason to note)
NOTE = None
#: the raw kernels of the backend: name → callable with the kernel's full argument list
_RAW: dict = {}
#: what keeps the loaded machine code alive (llvmlite's execution engine and ctypes function objects)
_KEEP: list = []
#: the kernel stages warmed up (JIT backend: compiled or loaded from numba's cache; AOT: all at once)
_WARM: set = set()
#: stages of :func:`warm_up` (the routes of :func:`ibl_ref.groundtruth.convolve.convolve`)
STAGES = ("sparse", "moment", "sh")

_HERE = Path(__file__).resolve().parent
#: the sources whose text is part of the key
_SOURCES = ("compiled_kernels.py", "kernel_spec.py", "kernel_library.py")
#: numba's runtime functions the C callables refer to on their error path (an exception in the kernel, which the
#: kernels never raise: no allocation, no bounds checks, division by the numpy error model): without numba in the
#: process they are defined here — the GIL pair as numba defines it, the others stop the process (never reached)
_HELPERS = ("numba_gil_ensure", "numba_gil_release", "NRT_MemInfo_call_dtor", "NRT_Free", "numba_do_raise",
            "numba_unpickle", "numba_runtime_build_excinfo_struct")
_HELPERS_IR = """
declare i32 @PyGILState_Ensure()
declare void @PyGILState_Release(i32)
declare void @abort()
define void @numba_gil_ensure(ptr %s) {
  %r = call i32 @PyGILState_Ensure()
  store i32 %r, ptr %s
  ret void
}
define void @numba_gil_release(ptr %s) {
  %v = load i32, ptr %s
  call void @PyGILState_Release(i32 %v)
  ret void
}
""" + "".join(f"define void @{h}() {{\n  call void @abort()\n  unreachable\n}}\n" for h in _HELPERS[2:])


# ----------------------------------------------------------------------------------------------------------------
# the generated C callables: every kernel as f(float64** F, int64** I, bool** Bp, int64* dims, double* fs, int64* is)
# ----------------------------------------------------------------------------------------------------------------
def _layout(kinds: str, result):
    """Slots of a kernel's arguments: per argument ``(kind, slot, first dim)`` and the counts of every slot list."""
    out, nf, ni, nb, nd, nfs, nis = [], 0, 0, 0, 0, 0, 0
    for k in kinds.split():
        if k in ("f", "i", "b"):
            if k == "f":
                out.append((k, nfs, 0))
                nfs += 1
            else:
                out.append((k, nis, 0))
                nis += 1
            continue
        base, ndim = k[0], int(k[1:])
        slot = {"f": nf, "i": ni, "b": nb}[base]
        out.append((k, slot, nd))
        nd += ndim
        if base == "f":
            nf += 1
        elif base == "i":
            ni += 1
        else:
            nb += 1
    return out, (nf, ni, nb, nd, nfs, nis + (1 if result else 0))


def _cfunc_source(name: str) -> str:
    """Python source of the C callable of kernel ``name`` (compiled by numba at build time)."""
    kinds, result = KERNELS[name]
    slots, _ = _layout(kinds, result)
    args = []
    for k, slot, d in slots:
        if k == "f":
            args.append(f"fs[{slot}]")
        elif k == "i":
            args.append(f"is_[{slot}]")
        elif k == "b":
            args.append(f"is_[{slot}] != 0")
        else:
            ptr = {"f": "F", "i": "I", "b": "Bp"}[k[0]]
            shape = ", ".join(f"dims[{d + j}]" for j in range(int(k[1:])))
            args.append(f"carray({ptr}[{slot}], ({shape},))")
    call = f"ck.{name}({', '.join(args)})"
    n_is = sum(1 for k, _, _ in slots if k in ("i", "b"))
    body = f"    is_[{n_is}] = {call}\n" if result else f"    {call}\n"
    return f"def _c_{name}(F, I, Bp, dims, fs, is_):\n{body}"


def _cpu_identity() -> str | None:
    """This CPU as the operating system reports it without llvmlite (Linux: vendor, family, model and the feature
    flags of the first processor in ``/proc/cpuinfo``); None where there is no such report."""
    try:
        text = Path("/proc/cpuinfo").read_text(errors="replace")
    except OSError:
        return None
    first = text.split("\n\n", 1)[0]
    keep = ("vendor_id", "cpu family", "model", "model name", "flags", "features", "cpu", "isa", "cpu part")
    fields = [ln.split(":", 1) for ln in first.splitlines() if ":" in ln]
    ident = [f"{k.strip()}={v.strip()}" for k, v in fields if k.strip().lower() in keep]
    return "\n".join(ident) if any(x.startswith(("flags=", "Features=", "isa=")) for x in ident) else None


def _package_version_file(name: str) -> bytes:
    spec = importlib.util.find_spec(name)  # (finds the package; does not import it)
    if spec is None or not spec.origin:
        raise ImportError(f"{name} is not installed")
    return (Path(spec.origin).parent / "_version.py").read_bytes()


def _key() -> str:
    """The key of the ahead-of-time files (sources, numba and llvmlite versions, Python, CPU).  The CPU is
    identified by the operating system's report (:func:`_cpu_identity`: no llvmlite import, ≈ 20 ms of a process),
    else by llvmlite's host CPU name and features."""
    try:  # (CPython's own BLAKE2: `import hashlib` loads OpenSSL first, ≈ 5–8 ms of a process)
        from _blake2 import blake2b
    except ImportError:  # pragma: no cover - other interpreters
        from hashlib import blake2b

    h = blake2b(FORMAT.encode(), digest_size=16)
    for f in _SOURCES:
        h.update((_HERE / f).read_bytes())
    h.update(os.environ.get("NUMBA_CPU_FEATURES", "").strip().encode())  # (:func:`_features`)
    h.update(_package_version_file("numba"))
    h.update(_package_version_file("llvmlite"))
    h.update(sys.version.encode())
    h.update((os.uname().machine if hasattr(os, "uname") else __import__("platform").machine()).encode())
    ident = _cpu_identity()
    if ident is not None:
        h.update(ident.encode())
    else:
        import llvmlite.binding as llvm

        h.update(llvm.get_process_triple().encode())
        h.update(llvm.get_host_cpu_name().encode())
        h.update(llvm.get_host_cpu_features().flatten().encode())
    return h.hexdigest()[:24]


def _folders() -> list:
    """Candidate folders of the ahead-of-time file, in order (module docstring)."""
    env = os.environ.get("NUMBA_CACHE_DIR", "").strip()
    if env:
        return [Path(env) / "ibl_ref_kernels"]
    xdg = os.environ.get("XDG_CACHE_HOME", "").strip()
    user = Path(xdg) if xdg else Path.home() / ".cache"
    return [_HERE / "__pycache__", user / "ibl_ref"]


def _writable(d: Path) -> bool:
    try:
        d.mkdir(parents=True, exist_ok=True)
        probe = d / f".probe-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
        return True
    except OSError:
        return False


def artifact_path(key: str | None = None, for_writing: bool = False) -> Path | None:
    """The ahead-of-time file of this machine: the first candidate folder that holds it (``for_writing``: the first
    writable one); None if there is none."""
    key = key or _key()
    name = f"kernels-{key}.bin"
    folders = _folders()
    if not for_writing:
        for d in folders:
            if (d / name).is_file():
                return d / name
    for d in folders:
        if _writable(d):
            return d / name
    return None


def _features() -> str:
    """The CPU features the kernels are compiled for ahead of time: ``$NUMBA_CPU_FEATURES`` where set, else this
    CPU's, plus ``-prefer-256-bit`` where it has AVX-512 (LLVM's tuning for such CPUs keeps vectors at 256 bits;
    the kernels are arithmetic-bound loops over contiguous float64 arrays, and 512-bit vectors gather 1.3–1.45×
    faster on this project's machines: ``benchmarks/bench_peer.py``)."""
    import llvmlite.binding as llvm

    env = os.environ.get("NUMBA_CPU_FEATURES", "").strip()
    if env:
        return env
    features = llvm.get_host_cpu_features().flatten()
    if "+avx512f" in features.split(",") and "prefer-256-bit" not in features:
        features += ",-prefer-256-bit"
    return features


def _target_machine(shared: bool = False):
    """llvmlite's target machine for this CPU (:func:`_features`): numba's JIT options, or (``shared``)
    position-independent code for a shared library."""
    import llvmlite.binding as llvm

    llvm.initialize_native_target()
    llvm.initialize_native_asmprinter()
    target = llvm.Target.from_triple(llvm.get_process_triple())
    cpu, features = llvm.get_host_cpu_name(), _features()
    if shared:
        return target.create_target_machine(cpu=cpu, features=features, opt=3, reloc="pic", codemodel="default")
    reloc = "static" if target.name.startswith("x86") else "pic" if target.name.startswith("ppc") else "default"
    return target.create_target_machine(cpu=cpu, features=features, opt=3, reloc=reloc, codemodel="jitdefault",
                                        jit=True)


def _external_symbols(mod) -> tuple[list, list]:
    """Names of the functions and of the data the LLVM module ``mod`` declares but does not define (LLVM intrinsics
    and :data:`_HELPERS` excluded)."""
    funcs = [f.name for f in mod.functions if f.is_declaration and not f.name.startswith("llvm.")
             and f.name not in _HELPERS]
    data = [g.name for g in mod.global_variables if g.is_declaration]
    return funcs, data


def _resolve(funcs, data) -> list:
    """Tell llvmlite where the process's functions ``funcs`` and data ``data`` are (libm and the Python C API, found
    through ``dlopen(NULL)``); returns the names not found."""
    import llvmlite.binding as llvm

    proc = ctypes.CDLL(None)
    missing = []
    for name in funcs:
        try:
            llvm.add_symbol(name, ctypes.cast(getattr(proc, name), ctypes.c_void_p).value)
        except AttributeError:
            missing.append(name)
    for name in data:
        try:
            llvm.add_symbol(name, ctypes.addressof(ctypes.c_char.in_dll(proc, name)))
        except ValueError:
            missing.append(name)
    return missing


def build(path: Path) -> Path:
    """Compile every kernel of :data:`~ibl_ref.groundtruth.kernel_spec.KERNELS` ahead of time into ``path`` (numba
    needed; about as long as numba's first compilation of the kernels).  Raises ``RuntimeError`` if a kernel needs
    more than libm, the Python C API and numba's C-callable error path (:data:`_HELPERS_IR`)."""
    import llvmlite.binding as llvm

    from ..atomic import atomic_write

    tm = _target_machine()
    blobs, symbols, ext_f, ext_d, irs = [], {}, set(), set(), []
    for name, (ir, native_name) in _kernel_irs().items():
        mod = llvm.parse_assembly(ir)
        mod.verify()
        funcs, data = _external_symbols(mod)
        bad = _resolve(funcs, data)
        if bad:
            raise RuntimeError(f"kernel {name} refers to symbols the ahead-of-time code cannot resolve: {bad[:5]}")
        ext_f.update(funcs)
        ext_d.update(data)
        blobs.append(tm.emit_object(mod))
        irs.append(ir)
        symbols[name] = native_name
    head = json.dumps({"format": FORMAT, "symbols": symbols, "sizes": [len(b) for b in blobs],
                       "functions": sorted(ext_f), "data": sorted(ext_d)}).encode()
    with atomic_write(path, "wb") as fh:
        fh.write(len(head).to_bytes(8, "little") + head + b"".join(blobs))
    _link_shared(irs, _shared_path(path))
    return path


def _kernel_irs_here() -> dict:
    """``{kernel: (optimised LLVM IR, symbol)}``: every kernel compiled by numba, in this process, as a C callable
    that takes its arrays as pointers and shapes."""
    from numba import carray, cfunc, types

    from . import compiled_kernels as ck

    sig = types.void(types.CPointer(types.CPointer(types.float64)), types.CPointer(types.CPointer(types.int64)),
                     types.CPointer(types.CPointer(types.boolean)), types.CPointer(types.int64),
                     types.CPointer(types.float64), types.CPointer(types.int64))
    out = {}
    for name in KERNELS:
        ns = {"ck": ck, "carray": carray}
        exec(compile(_cfunc_source(name), f"<ibl_ref kernel {name}>", "exec"), ns)
        cf = cfunc(sig, nogil=True, error_model="numpy")(ns[f"_c_{name}"])
        out[name] = (cf.inspect_llvm(), cf.native_name)
    return out


def _kernel_irs() -> dict:
    """:func:`_kernel_irs_here` optimised for :func:`_features`: numba optimises (and vectorises) for the features
    its configuration had when it started, which only ``$NUMBA_CPU_FEATURES`` sets; so where they differ from
    numba's default a child process compiles the kernels with that variable set (this process's numba, and the
    user's own numba code, are left as they are).  If the child fails, this process compiles them as numba
    configures it."""
    import subprocess

    import llvmlite.binding as llvm

    features = _features()
    if features == llvm.get_host_cpu_features().flatten() or "numba" in sys.modules and \
            getattr(sys.modules["numba"].config, "CPU_FEATURES", None) == features:
        return _kernel_irs_here()
    root = str(Path(__file__).resolve().parents[2])
    code = ("import json, sys; sys.path.insert(0, sys.argv[1]); "
            "from ibl_ref.groundtruth import kernel_library as k; json.dump(k._kernel_irs_here(), sys.stdout)")
    try:
        p = subprocess.run([sys.executable, "-c", code, root], env={**os.environ, "NUMBA_CPU_FEATURES": features},
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, timeout=1800)
        if p.returncode == 0:
            got = json.loads(p.stdout)
            if set(got) == set(KERNELS):
                return {k: tuple(v) for k, v in got.items()}
    except (OSError, ValueError, subprocess.SubprocessError):
        pass
    return _kernel_irs_here()


def _shared_path(path: Path) -> Path:
    return path.with_suffix(".so")


def _linker() -> str | None:
    """The C compiler driver that links the shared library (``$CC``, else ``cc``, ``gcc`` or ``clang``); None if
    there is none or the platform is not an ELF one."""
    import shutil

    if not sys.platform.startswith(("linux", "freebsd")):
        return None
    for cand in (os.environ.get("CC", "").split()[:1] or []) + ["cc", "gcc", "clang"]:
        found = shutil.which(cand)
        if found:
            return found
    return None


def _link_shared(irs, out: Path) -> bool:
    """Link the kernels' LLVM modules (their IR texts ``irs``, parsed again: code generation may change a module it
    emits) with :data:`_HELPERS_IR` into the shared library ``out``, which later
    processes open with ctypes alone (no llvmlite: ≈ 0.03 s less per process than linking the machine code with
    llvmlite's MCJIT).  Optional: returns False (nothing written) when there is no C compiler driver or the link
    fails; the ahead-of-time file then loads through llvmlite."""
    import llvmlite.binding as llvm
    import subprocess
    import tempfile

    cc = _linker()
    if cc is None:
        return False
    tm = _target_machine(shared=True)
    try:
        with tempfile.TemporaryDirectory(prefix=".link-", dir=out.parent) as td:
            objs = []
            for i, ir in enumerate(irs + [_HELPERS_IR]):
                o = Path(td) / f"k{i}.o"
                o.write_bytes(tm.emit_object(llvm.parse_assembly(ir)))
                objs.append(str(o))
            tmp_so = Path(td) / "kernels.so"
            p = subprocess.run([cc, "-shared", "-Wl,-Bsymbolic", "-o", str(tmp_so), *objs, "-lm"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, timeout=120)
            if p.returncode != 0 or not tmp_so.is_file():
                return False
            os.replace(tmp_so, out)  # (atomic: the same folder)
        return True
    except (OSError, subprocess.SubprocessError):
        return False


def _read_head(path: Path) -> tuple[dict, bytes, int]:
    data = path.read_bytes()
    n = int.from_bytes(data[:8], "little")
    try:
        head = json.loads(data[8 : 8 + n])
    except ValueError:
        raise IBLError(f"{path}: not an ahead-of-time kernel file") from None
    if not isinstance(head, dict) or head.get("format") != FORMAT or set(head.get("symbols", {})) != set(KERNELS):
        raise IBLError(f"{path}: not an ahead-of-time kernel file of this version")
    return head, data, 8 + n


def _load_shared(path: Path, head: dict) -> dict | None:
    """The kernels' entry addresses from the shared library beside ``path`` (:func:`_link_shared`), opened with
    ctypes; None when there is none or it does not open (the MCJIT route then)."""
    so = _shared_path(path)
    if not so.is_file():
        return None
    try:
        lib = ctypes.CDLL(str(so))
        addr = {k: ctypes.cast(lib[v], ctypes.c_void_p).value for k, v in head["symbols"].items()}
    except (OSError, AttributeError):
        return None
    if not all(addr.values()):
        return None
    _KEEP.append(lib)
    return addr


def _load_file(path: Path) -> dict:
    """The kernels' entry addresses from the ahead-of-time file ``path`` (:class:`IBLError` if it is not one): from
    its shared library where there is one (ctypes only), else its machine code linked by llvmlite's MCJIT."""
    head, data, off = _read_head(path)
    addr = _load_shared(path, head)
    if addr is not None:
        return addr
    import llvmlite.binding as llvm

    missing = _resolve(head["functions"], head["data"])
    if missing:
        raise IBLError(f"{path}: symbols not found in this process: {missing[:5]}")
    tm = _target_machine()
    helpers = llvm.parse_assembly(_HELPERS_IR)
    engine = llvm.create_mcjit_compiler(helpers, tm)
    for size in head["sizes"]:
        engine.add_object_file(llvm.ObjectFileRef.from_data(data[off : off + size]))
        off += size
    if off != len(data):
        raise IBLError(f"{path}: truncated or padded ({len(data)} bytes, expected {off})")
    engine.finalize_object()
    addr = {k: engine.get_function_address(v) for k, v in head["symbols"].items()}
    if not all(addr.values()):
        raise IBLError(f"{path}: missing entry points")
    _KEEP.append(engine)
    return addr


_PTRS = ctypes.c_void_p
_CFUNC = ctypes.CFUNCTYPE(None, _PTRS, _PTRS, _PTRS, _PTRS, _PTRS, _PTRS)
_DT = {"f": np.dtype(np.float64), "i": np.dtype(np.int64), "b": np.dtype(np.bool_)}


def _caller(name: str, address: int):
    """A Python callable for the C callable of kernel ``name`` at ``address``: checks the arrays (dtype, number of
    dimensions, C order — a copy would lose what the kernel writes; :class:`IBLError` otherwise), packs pointers,
    shapes and scalars."""
    kinds, result = KERNELS[name]
    slots, (nf, ni, nb, nd, nfs, nis) = _layout(kinds, result)
    fn = _CFUNC(address)
    _KEEP.append(fn)
    ptr_t = {"f": _PTRS * max(nf, 1), "i": _PTRS * max(ni, 1), "b": _PTRS * max(nb, 1)}
    n_arg = len(slots)

    def call(*args):
        if len(args) != n_arg:
            raise IBLError(f"{name}() takes {n_arg} arguments, got {len(args)}")
        P = {"f": ptr_t["f"](), "i": ptr_t["i"](), "b": ptr_t["b"]()}
        dims = np.empty(max(nd, 1), dtype=np.int64)
        fs = np.empty(max(nfs, 1), dtype=np.float64)
        is_ = np.zeros(max(nis, 1), dtype=np.int64)
        for i, (a, (k, slot, d)) in enumerate(zip(args, slots)):
            if k == "f":
                fs[slot] = a
            elif k in ("i", "b"):
                is_[slot] = int(a)
            else:
                nd_k = int(k[1:])
                if not (isinstance(a, np.ndarray) and a.dtype == _DT[k[0]] and a.ndim == nd_k
                        and a.flags.c_contiguous):
                    raise IBLError(f"{name}(): argument {i} must be a C-contiguous {_DT[k[0]]} array of "
                                    f"{nd_k} dimensions, got {getattr(a, 'dtype', type(a))} "
                                    f"{getattr(a, 'shape', '')}")
                P[k[0]][slot] = a.ctypes.data
                dims[d : d + nd_k] = a.shape
        fn(P["f"], P["i"], P["b"], dims.ctypes.data, fs.ctypes.data, is_.ctypes.data)
        return int(is_[nis - 1]) if result else None

    call.__name__ = name
    return call


# ----------------------------------------------------------------------------------------------------------------
# choosing and loading the backend
# ----------------------------------------------------------------------------------------------------------------
def _load_aot() -> dict | None:
    """The raw kernels from the ahead-of-time file, building it first where needed; None (with :data:`NOTE` set)
    where that is not possible."""
    global NOTE
    if os.environ.get(BACKEND_ENV, "").strip().lower() == "jit":
        return None
    if os.environ.get("NUMBA_BOUNDSCHECK", "").strip() not in ("", "0"):
        return None  # bounds checking raises IndexError, which the C callables cannot carry
    try:
        key = _key()
        path = artifact_path(key)
    except Exception as exc:  # noqa: BLE001 - llvmlite or numba missing or broken: numba's JIT says more
        NOTE = f"ibl_ref: the kernels cannot be compiled ahead of time here ({exc})"
        return None
    if path is None:
        NOTE = ("ibl_ref: no writable folder for the ahead-of-time kernels "
                f"({', '.join(str(d) for d in _folders())}); numba's JIT runs them")
        return None
    for attempt in range(2):
        if not path.is_file():
            try:
                build(path)
            except Exception as exc:  # noqa: BLE001 - any failure: the JIT backend
                NOTE = f"ibl_ref: building the ahead-of-time kernels failed ({exc}); numba's JIT runs them"
                return None
        try:
            return {k: _caller(k, a) for k, a in _load_file(path).items()}
        except Exception as exc:  # noqa: BLE001 - a damaged or foreign file: build it again, once
            NOTE = f"ibl_ref: the ahead-of-time kernels in {path} did not load ({exc})"
            if attempt == 0:
                try:
                    path.unlink()
                except OSError:
                    path = artifact_path(key, for_writing=True)
                    if path is None or path.is_file():
                        return None
    return None


def _load_jit() -> dict:
    from . import compiled_kernels as ck

    return {k: getattr(ck, k) for k in KERNELS}


#: the raw kernels of each backend loaded in this process
_LOADED: dict = {}
#: one thread loads (or builds) the kernels; others wait for it (threads of a sparse gather call kernels at once)
_LOCK = threading.Lock()


def load() -> float:
    """Load the backend (once per process): the ahead-of-time kernels where possible, else numba's JIT (with one
    line on stderr saying why, unless numba's own cache note says it); returns the seconds it took (0 when loaded
    already)."""
    global BACKEND, _RAW
    if BACKEND is not None:
        return 0.0
    with _LOCK:
        return 0.0 if BACKEND is not None else _load_locked()


def _load_locked() -> float:
    global BACKEND, _RAW
    t0 = time.perf_counter()
    raw = _load_aot()
    if raw is not None:
        BACKEND, _RAW = "aot", _LOADED.setdefault("aot", raw)
        _WARM.update(STAGES)
        return time.perf_counter() - t0
    BACKEND, _RAW = "jit", _LOADED.setdefault("jit", _load_jit())
    from . import compiled_kernels as ck

    if NOTE and ck.CACHE_NOTE is None and os.environ.get(BACKEND_ENV, "").strip().lower() != "jit":
        print(NOTE, file=sys.stderr)
    return time.perf_counter() - t0


def use(backend: str) -> None:
    """Make ``backend`` (``"aot"`` or ``"jit"``) the one this process calls from now on (tests and benchmarks compare
    the two); :class:`~ibl_ref.errors.IBLError` if the ahead-of-time kernels cannot be had here."""
    global BACKEND, _RAW
    if backend not in ("aot", "jit"):
        raise IBLError(f"backend must be 'aot' or 'jit', got {backend!r}")
    with _LOCK:
        _use_locked(backend)


def _use_locked(backend: str) -> None:
    global BACKEND, _RAW
    if backend == BACKEND:
        return
    if backend == "aot":
        raw = _LOADED.get("aot") or _load_aot()
        if raw is None:
            raise IBLError(NOTE or "the ahead-of-time kernels are not available here")
        BACKEND, _RAW = "aot", _LOADED.setdefault("aot", raw)
        _WARM.update(STAGES)
    else:
        BACKEND, _RAW = "jit", _LOADED.setdefault("jit", _load_jit())
        _WARM.clear()


def loaded() -> bool:
    """True when this process has loaded the kernels (the ahead-of-time ones, or warmed-up JIT ones)."""
    return BACKEND is not None and bool(_WARM)


def warm_up(stages=STAGES) -> float:
    """Load the backend and make the kernels of ``stages`` ready (JIT: compiled or loaded from numba's cache on tiny
    inputs, before workers are forked so that they inherit the machine code; AOT: loaded all at once); returns the
    seconds it took (0 when done already)."""
    t0 = time.perf_counter()
    dt = load()
    todo = [st for st in stages if st in STAGES and st not in _WARM]
    if not todo:
        return dt
    from ..environment import envmap

    n = 2
    d = envmap.texel_directions(n).reshape(-1, 3)
    if "sparse" in todo:
        X, Y, Z = (np.ascontiguousarray(d[:, i]) for i in range(3))
        RW = np.ones((4, d.shape[0]))
        fr = np.ascontiguousarray(envmap.face_frames("openexr"), dtype=np.float64)
        cen = d[:2].copy()
        rows = d[:2].reshape(2, 1, 3).copy()
        for s_int, rowmax in ((2, False), (0, True)):
            tile_gather(cen, rows, np.full(2, 0.5), np.zeros(2), fr, n, X, Y, Z, RW, np.zeros((0, 3)),
                        np.zeros((0, 4)), 2.0, s_int, rowmax, 1e-300, np.zeros((2, 1, 4)), np.zeros((2, 1)),
                        np.zeros(2, dtype=np.int64))
        cap_count(cen[0].copy(), 0.5, fr, n)
        mem = np.array([[0, 1, -1, -1]], dtype=np.int64)
        cone_extremes(cen, np.full(2, 0.5), d[:2].copy(), 0.1, np.ones((2, 3)), np.ones((2, 3)), d[:1].copy(), 0.3,
                      mem, np.zeros((2, 3)), np.zeros((2, 3)))
        tile_bounds(np.ones((2, 1, 4)), np.zeros((2, 1)), np.zeros(2), np.zeros(2), 1.0, np.zeros((2, 1)),
                    np.ones(2), np.ones(2), 5e-8, np.array([0.0, 1.0]), np.array([0.0, -1.0]), np.ones((2, 3)),
                    np.ones((2, 3)), np.ones(3), np.ones(3), np.ones((2, 1), dtype=np.bool_),
                    np.zeros((2, 1), dtype=np.int64), np.zeros((2, 3)), np.zeros((2, 3)), np.zeros(2))
    if "moment" in todo:
        R = d[:2].reshape(2, 1, 3).copy()
        st = np.array([0, 1, 2], dtype=np.int64)
        tx = np.array([0, 1], dtype=np.int64)
        band_exact(R, st, tx, d, np.ones((d.shape[0], 4)), True, True, np.zeros((2, 1, 4)), np.zeros((2, 1, 4)))
        z = [np.zeros((2, 1, 4)) for _ in range(4)]
        band_brackets(R, st, tx, d, np.ones(d.shape[0]), np.zeros(d.shape[0]), np.ones((d.shape[0], 4)),
                      np.ones((d.shape[0], 3, 4)), np.ones((d.shape[0], 6, 4)), True, True, *z)
    if "sh" in todo:
        from .sh_tables import _row_layout, compiled_tables

        tabs = compiled_tables(2)
        ne, no = (r.size for r in _row_layout(2))
        sh_project(d[:3].copy(), np.ones((8, 4, 3)), 2, *tabs, np.zeros((ne, 4)), np.zeros((no, 4)))
        dest = np.zeros((2, ne), dtype=np.int64)
        dest[0] = np.arange(ne)
        dest[1, :no] = ne + np.arange(no)
        sh_matrix(d[:3].copy(), 2, *tabs, dest, np.zeros((ne + no, 3)))
        point_gather(d[:3].copy(), d[:2].copy(), np.ones((2, 4)), np.array([2.0, 2.5]),
                     np.array([2, 0], dtype=np.int64), np.zeros((2, 4, 3)))
        sh_values_bounds(np.ones((1, 2, 4)), np.ones((1, 2, 3)), np.ones(1), np.zeros((1, 2, 3)), 1.0, 0.0, True,
                         np.zeros((1, 2, 3)), np.zeros((1, 2)))
    _WARM.update(todo)
    return time.perf_counter() - t0


def _raw(name: str):
    if BACKEND is None:
        load()
    return _RAW[name]


# ----------------------------------------------------------------------------------------------------------------
# the kernels as the routes call them (work arrays allocated here)
# ----------------------------------------------------------------------------------------------------------------
def tile_scratch_size(caps, frames, n, cen, n_bright) -> int:
    """:func:`ibl_ref.groundtruth.compiled_kernels.tile_scratch_size`."""
    return _raw("tile_scratch_size")(caps, frames, n, cen, n_bright)


def bright_groups(bdirs):
    """The groups of :data:`~ibl_ref.groundtruth.kernel_spec.BRIGHT_GROUP` consecutive bright texels (rows of
    ``bdirs`` (nb, 3), unit vectors) that :func:`tile_gather` skips whole when out of reach: unit centres (G, 3) and
    the largest angle from each centre to a member (+1e-9 rad for the arccos)."""
    nb = bdirs.shape[0]
    G = -(-nb // BRIGHT_GROUP)
    pad = np.zeros((G * BRIGHT_GROUP, 3))
    pad[:nb] = bdirs
    grp = pad.reshape(G, BRIGHT_GROUP, 3)
    cen = grp.sum(axis=1)
    norm = np.linalg.norm(cen, axis=1, keepdims=True)
    cen = np.where(norm > 0, cen / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 1.0]))
    real = (np.arange(G * BRIGHT_GROUP) < nb).reshape(G, BRIGHT_GROUP)
    dots = np.where(real, np.einsum("gkj,gj->gk", grp, cen), 1.0)
    alpha = np.arccos(np.clip(dots.min(axis=1), -1.0, 1.0)) + 1e-9 if G else np.zeros(0)
    return np.ascontiguousarray(cen), np.ascontiguousarray(alpha)


def tile_gather(cen, rows, caps, arad, frames, n, X, Y, Z, RW, bdirs, brw, s, s_int, rowmax, c_floor, acc, logmx,
                count, groups=None, pairs=None):
    """:func:`ibl_ref.groundtruth.compiled_kernels.tile_gather` with its scratch lists; ``groups``: the bright
    texels' :func:`bright_groups` (computed here if not given); ``pairs``: where to write the entries per tile."""
    m = tile_scratch_size(caps, frames, n, cen, bdirs.shape[0])
    gcen, galpha = bright_groups(bdirs) if groups is None else groups
    if pairs is None:
        pairs = np.empty(cen.shape[0], dtype=np.int64)
    _raw("tile_gather")(cen, rows, caps, arad, frames, n, X, Y, Z, RW, bdirs, brw, gcen, galpha, s, s_int, rowmax,
                        c_floor, acc, logmx, count, pairs, np.zeros((7, m)))


def tile_bounds(*args):
    """:func:`ibl_ref.groundtruth.compiled_kernels.tile_bounds`."""
    _raw("tile_bounds")(*args)


def cone_extremes(*args):
    """:func:`ibl_ref.groundtruth.compiled_kernels.cone_extremes`."""
    _raw("cone_extremes")(*args)


def cap_count(t, q, frames, n) -> int:
    """:func:`ibl_ref.groundtruth.compiled_kernels.cap_count`."""
    return _raw("cap_count")(t, q, frames, n)


def _band_scratch(starts, rows: int) -> np.ndarray:
    """Work array of the band kernels: ``rows`` × (the longest list + :data:`~ibl_ref.groundtruth.kernel_spec.VEC`)."""
    longest = int(np.max(np.diff(starts))) if starts.size > 1 else 0
    return np.zeros((rows, longest + VEC))


def band_exact(R, starts, texels, D, Wt, do1, do2, num1, num2):
    """:func:`ibl_ref.groundtruth.compiled_kernels.band_exact` with its scratch lists."""
    _raw("band_exact")(R, starts, texels, D, Wt, do1, do2, num1, num2, _band_scratch(starts, 7))


def band_brackets(R, starts, blocks, cb, ca, sa, M0, M1, M2, do1, do2, num1, err1, num2, err2):
    """:func:`ibl_ref.groundtruth.compiled_kernels.band_brackets` with its scratch lists."""
    _raw("band_brackets")(R, starts, blocks, cb, ca, sa, M0, M1, M2, do1, do2, num1, err1, num2, err2,
                          _band_scratch(starts, 45))


def point_gather(out_dirs, b_dirs, b_w, s_arr, s_int, res):
    """:func:`ibl_ref.groundtruth.compiled_kernels.point_gather` with its block arrays."""
    _raw("point_gather")(out_dirs, b_dirs, b_w, s_arr, s_int, res, np.zeros((4, POINT_BLOCK)),
                         np.zeros((s_arr.shape[0], 4, POINT_BLOCK)))


def sh_values_bounds(*args):
    """:func:`ibl_ref.groundtruth.compiled_kernels.sh_values_bounds`."""
    _raw("sh_values_bounds")(*args)


def _sh_blocks(L: int):
    """Work arrays of one block of the SH passes (:func:`ibl_ref.groundtruth.compiled_kernels._sh_rows`)."""
    return np.zeros((2 * L + 4, SH_BLOCK)), np.zeros((3, L + 1, SH_BLOCK))


def sh_project(reps, Wk, L, row_of, cls_of, a_tab, b_tab, acc_e, acc_o):
    """:func:`ibl_ref.groundtruth.compiled_kernels.sh_project` with its block arrays."""
    _raw("sh_project")(reps, Wk, L, row_of, cls_of, a_tab, b_tab, acc_e, acc_o, *_sh_blocks(int(L)))


def sh_matrix(reps, L, row_of, cls_of, a_tab, b_tab, dest, out):
    """:func:`ibl_ref.groundtruth.compiled_kernels.sh_matrix` with its block arrays."""
    _raw("sh_matrix")(reps, L, row_of, cls_of, a_tab, b_tab, dest, out, *_sh_blocks(int(L)))
