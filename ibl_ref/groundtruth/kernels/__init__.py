"""The kernel interface of the Phong-lobe convolution routes (Knuth et al. 2014, Sec. 3.2, Eq. 4) and its backends.

The routes (:mod:`~ibl_ref.groundtruth.phong_convolution`'s sparse gather, :mod:`~ibl_ref.groundtruth.moment_convolution`,
:mod:`~ibl_ref.groundtruth.sh_convolution`) say *what* is summed and how the rigorous bound is assembled; the inner
loops that do the summing are the operations of one interface, :class:`Kernels`, with two implementations:

``"numpy"``
    :class:`~ibl_ref.groundtruth.kernels.numpy_backend.NumpyKernels` — array expressions, the reference (every test,
    bound and number of the routes was first established on it);
``"compiled"``
    :class:`~ibl_ref.groundtruth.kernels.numba_backend.CompiledKernels` — numba ``@njit(cache=True, nogil=True)``
    loops (:mod:`~ibl_ref.groundtruth.kernels.numba_loops`; optional extra ``fast``: ``pip install
    "ibl_ref[fast]"``).  The same quadratures and rigorous bounds (each loop's rounding is part of its bound); the maps
    agree with the NumPy ones within the sum of the two bounds, not bit for bit.

Choosing (:func:`resolve_kernel`): the ``kernel=`` argument of :func:`ibl_ref.groundtruth.convolve.convolve`, ``ibl-ref
convolve --kernel``, or the environment variable :data:`KERNEL_ENV` (``IBL_REF_KERNEL``); ``"auto"`` (the default) is
``"compiled"`` where numba can be imported and is not switched off (``NUMBA_DISABLE_JIT=1``), else ``"numpy"`` —
and :func:`ibl_ref.groundtruth.convolve.convolve` keeps the NumPy kernels for a small call in a process that has not
loaded the compiled ones yet (:attr:`KernelMethod.load_seconds`).  Each backend is one registry entry of
:data:`KERNEL_METHODS`: its loader and the constants of the planner's cost models.  Adding a backend is one module
that implements :class:`Kernels` (extending the NumPy one for the operations it does not speed up) plus one entry.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from dataclasses import dataclass, field
from types import MappingProxyType

from ...errors import IBLError

__all__ = ["Kernels", "KernelMethod", "KERNEL_METHODS", "KERNELS", "KERNEL_ENV", "resolve_kernel", "check_impl", "get_kernels",
           "kernels_loaded", "numba_available"]

#: accepted values of the ``kernel`` switch
KERNELS = ("auto", "numpy", "compiled")
#: environment variable read when ``kernel`` is not given
KERNEL_ENV = "IBL_REF_KERNEL"


class Kernels:
    """What a backend provides to the routes (the operations' contracts; implementations in the backend modules).

    name : str
        ``"numpy"`` or ``"compiled"`` (:data:`KERNEL_METHODS`).
    gather_threads : bool
        Whether the sparse gather shares one call's tiles between threads (its ``threads`` argument).
    warm_up(stages) -> float
        Make the loops of the routes ``stages`` (``"sparse"``, ``"moment"``, ``"sh"``) ready (compiled or loaded)
        before workers are forked; seconds spent.  ``loaded()``: whether that has happened in this process.
    sparse_gather(src_dirs, omega, rad, bright, m, kernel, threads) -> SparseGather
        The sparse route's sums of every tile's cap and their rigorous bound, per call
        (:class:`~ibl_ref.groundtruth.kernels.numpy_backend.SparseGather` documents the protocol).
    moment_chunk_pairs(Q) -> int
        (tile, texel) pairs per chunk of output tiles of the moment route's band.
    band_sources(bdT, bw_pad), band_exact(Rc, tiles, blk, src, s_list, num, chunk_elems)
        The moment route's exact gather of the horizon band: ``num[s] += Σ max(r·ω, 0)^s·w`` (s ∈ {1, 2}).
    brackets_prep(cb_leaf, ab_leaf, M0, M1, M2), band_brackets(Rc, tiles, blk, prep, s_list, num, err, chunk_elems)
        Its linear brackets on straddling leaf blocks: midpoints into ``num``, half-widths into ``err``.
    sh_shared_chunks(dirs, sym), sh_project_octant(dirs, W, L, orb, chunks), sh_octant_values(dirs, Be, Bo, L, orb, chunks)
        The SH route's projection and evaluation over octant-symmetric direction sets
        (:class:`ibl_ref.groundtruth.sh_basis.NumpySH`).
    bright_gather(out_dirs, b_dirs, b_w, s_list), bright_gather_error(nb, b_w, s_list)
        The SH route's exact sums from its bright texels, and their rounding allowance (None: nothing to add).
    """

    name = ""


@dataclass(frozen=True)
class KernelMethod:
    """One backend of :data:`KERNEL_METHODS`: where it lives and what the planner of
    :func:`ibl_ref.groundtruth.convolve.convolve` knows of it without loading it."""

    #: ``module:Class`` of the backend (imported on first use: the compiled one imports numba, ≈ 0.3 s)
    target: str
    #: cost-model constants of the planner in units of :data:`ibl_ref.groundtruth.sh_convolution.SECONDS_PER_UNIT`
    #: (the dense exact gather per (output × source texel) pair, for s = 1 apart; the sparse gather per pair of its
    #: static model and per output texel, and per estimated candidate and output texel; the SH pass and its bright
    #: gather as factors of :func:`~ibl_ref.groundtruth.sh_convolution.sh_cost` / ``bright_cost``; the moment route
    #: per (output texel × 6N/leaf)), fitted by ``benchmarks/bench_cost_models.py`` (medians of measured / model)
    costs: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    #: seconds a process pays once to use the backend (importing and loading it)
    load_seconds: float = 0.0
    #: what must be importable for it, and why it may not be available (None: always available)
    requires: str | None = None


KERNEL_METHODS = MappingProxyType({
    # NumPy: the sparse constants refitted (non-negative least squares, relative residuals) to 12 cells of
    # ``convolve(method="sparse", workers=1)``, sky + 1e5 sun, rtol 1e-3, 64²–256² × s = 64…4096 (within 0.69–1.39×
    # of every cell), the candidate constants on sky + sun 64²–256² × s = 64…4096 and the courtyard probe at 256²
    # (0.78–1.57×); the exact gather 46.7 s CPU at 128²; the moment route 64²–512² (0.63–1.23×)
    "numpy": KernelMethod("ibl_ref.groundtruth.kernels.numpy_backend:NumpyKernels", MappingProxyType({
        "EXACT_UNITS_PER_PAIR": 17.0, "EXACT_UNITS_PER_PAIR_S1": 6.0,
        "SPARSE_UNITS_PER_PAIR": 6.0, "SPARSE_UNITS_PER_OUTPUT": 6.8e3,
        "SPARSE_UNITS_PER_CAND": 5.04, "SPARSE_UNITS_PER_CAND_OUTPUT": 992.0,
        "SH_FACTOR": 0.37, "SH_BRIGHT_FACTOR": 0.43, "MOMENT_UNITS": 56.0})),
    # compiled (no compiled exact gather: the NumPy constants); the sparse, SH and moment constants from
    # ``bench_cost_models.py --kernel compiled`` (sparse: 15 cells, measured / model 0.59–1.87; moment 64²–1024²,
    # 0.44–1.23); the load time measured by ``benchmarks/bench_peer.py``'s start-up floor
    "compiled": KernelMethod("ibl_ref.groundtruth.kernels.numba_backend:CompiledKernels", MappingProxyType({
        "EXACT_UNITS_PER_PAIR": 17.0, "EXACT_UNITS_PER_PAIR_S1": 6.0,
        "SPARSE_UNITS_PER_PAIR": 1.33, "SPARSE_UNITS_PER_OUTPUT": 800.0,
        "SPARSE_UNITS_PER_CAND": 1.24, "SPARSE_UNITS_PER_CAND_OUTPUT": 482.0,
        "SH_FACTOR": 0.19, "SH_BRIGHT_FACTOR": 0.23, "MOMENT_UNITS": 42.2}), load_seconds=0.6, requires="numba"),
})

#: the backends loaded in this process
_LOADED: dict = {}


def _numba_found() -> bool:
    try:
        return importlib.util.find_spec("numba") is not None
    except (ImportError, ValueError):  # a broken or blocked installation counts as absent
        return False


def _jit_disabled() -> bool:
    return os.environ.get("NUMBA_DISABLE_JIT", "").strip() not in ("", "0")


def numba_available() -> bool:
    """True when numba can be found (not imported here) and its JIT is not switched off (``NUMBA_DISABLE_JIT``)."""
    return _numba_found() and not _jit_disabled()


def resolve_kernel(kernel=None) -> str:
    """``"numpy"`` or ``"compiled"`` for the switch value ``kernel`` (None: ``$IBL_REF_KERNEL`` or ``"auto"``)."""
    source = "kernel"
    if kernel is None:
        kernel = os.environ.get(KERNEL_ENV, "").strip().lower() or "auto"
        source = f"${KERNEL_ENV}"
    if kernel not in KERNELS:
        raise IBLError(f"{source} must be one of {', '.join(KERNELS)}, got {kernel!r}")
    if kernel == "auto":
        return "compiled" if numba_available() else "numpy"
    if kernel == "compiled" and not numba_available():
        why = "NUMBA_DISABLE_JIT is set" if _numba_found() else "numba is not installed: pip install 'ibl_ref[fast]'"
        raise IBLError(f"{source} = 'compiled' needs numba's JIT ({why}); or use kernel 'numpy'")
    return kernel


def check_impl(impl):
    """``impl`` if it names a backend of :data:`KERNEL_METHODS` or is a :class:`Kernels` instance (the routes'
    ``impl=`` argument), else :class:`~ibl_ref.errors.IBLError`."""
    if not isinstance(impl, Kernels) and (not isinstance(impl, str) or impl not in KERNEL_METHODS):
        raise IBLError(f"impl must be one of {', '.join(repr(k) for k in KERNEL_METHODS)}, got {impl!r}")
    return impl


def get_kernels(name) -> Kernels:
    """The backend ``name`` of :data:`KERNEL_METHODS` (one instance per process, imported on first use); a
    :class:`Kernels` instance is returned as it is (a backend of one's own, e.g. a benchmark's variant)."""
    if isinstance(name, Kernels):
        return name
    if name not in _LOADED:
        check_impl(name)
        if os.environ.get("IBL_REF_KERNEL_BACKEND"):
            print("ibl_ref: IBL_REF_KERNEL_BACKEND is no longer read (the compiled kernels have one backend, "
                  "numba's JIT); unset it", file=sys.stderr)
        module, cls = KERNEL_METHODS[name].target.split(":")
        _LOADED[name] = getattr(importlib.import_module(module), cls)()
    return _LOADED[name]


def kernels_loaded(name: str) -> bool:
    """True when this process has the backend ``name`` ready (imported and its loops loaded)."""
    k = _LOADED.get(name)
    return bool(k is not None and k.loaded())
