"""Which implementation runs the inner loops of the Phong-lobe convolution (Knuth et al. 2014, Sec. 3.2, Eq. 4).

Two implementations of the same quadratures:

``"numpy"``
    the reference: array expressions in NumPy/SciPy (every test, every bound and every number of the
    routes was first established on it);
``"compiled"``
    :mod:`ibl_ref.groundtruth.compiled_kernels` — the gathers, the moment route's horizon band, the SH
    passes and the bright-texel gathers as loops compiled by numba (optional extra ``fast``:
    ``pip install "ibl_ref[fast]"``), compiled ahead of time once per installation and loaded without numba
    (:mod:`ibl_ref.groundtruth.kernel_library`).  Same quadratures, same rigorous bounds (each kernel's rounding is
    part of its bound); results agree with the NumPy path within the sum of the two bounds, not bit for bit.

The switch: the ``kernel=`` argument of :func:`ibl_ref.groundtruth.convolve.convolve`, ``ibl-ref convolve
--kernel``, or the environment variable :data:`KERNEL_ENV` (``IBL_REF_KERNEL``) when the argument is not
given.  ``"auto"`` (the default) is ``"compiled"`` when numba can be imported, else ``"numpy"`` — except that
:func:`ibl_ref.groundtruth.convolve.convolve` keeps the NumPy kernels for a call whose model cost with them is
below the compiled one plus :data:`COMPILED_LOAD_SECONDS` in a process that has not loaded the compiled kernels yet
(a small map in a fresh process: loading them would cost more than they save; ``info["kernel_auto"]`` says so);
asking for ``"compiled"`` without numba is a one-line :class:`~ibl_ref.errors.IBLError`.  :func:`resolve_kernel` only
looks numba up (``importlib.util.find_spec``); loading the compiled code happens on first use (:func:`compiled`).
"""

from __future__ import annotations

import importlib.util
import os

from ..errors import IBLError

__all__ = ["KERNELS", "KERNEL_ENV", "COMPILED_LOAD_SECONDS", "resolve_kernel", "numba_available", "compiled",
           "compiled_loaded"]

#: accepted values of the ``kernel`` switch
KERNELS = ("auto", "numpy", "compiled")
#: environment variable read when ``kernel`` is not given
KERNEL_ENV = "IBL_REF_KERNEL"
#: seconds a process pays once to use the compiled kernels: loading them compiled ahead of time (``import
#: llvmlite.binding`` ≈ 0.02 s and the machine code; :mod:`ibl_ref.groundtruth.kernel_library`)
COMPILED_LOAD_SECONDS = 0.05


def numba_available() -> bool:
    """True when numba can be found on the path (not imported here)."""
    try:
        return importlib.util.find_spec("numba") is not None
    except (ImportError, ValueError):  # a broken or blocked installation counts as absent
        return False


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
        raise IBLError(f"{source} = 'compiled' needs numba, which is not installed: "
                       "pip install 'ibl_ref[fast]', or use kernel 'numpy'")
    return kernel


def compiled_loaded() -> bool:
    """True when this process has loaded the compiled kernels already (:func:`compiled` and their warm-up)."""
    import sys

    mod = sys.modules.get("ibl_ref.groundtruth.kernel_library")
    return bool(mod is not None and mod.loaded())


def compiled():
    """The compiled kernels as the routes call them (:mod:`ibl_ref.groundtruth.kernel_library`; loaded on first use,
    compiled ahead of time on the first use after an installation)."""
    from . import kernel_library

    return kernel_library
