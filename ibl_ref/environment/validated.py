"""The validated environment: a radiance cube map checked once, at the edge, and trusted by every later stage.

Not a paper concept: the front door of every stage of Knuth et al. 2014's pipeline (median cut, PEMs, filter
pyramids, convolution, rendering), each of which needs a ``(6, N, N, C)`` cube of finite, non-negative radiance
(:mod:`ibl_ref.environment.envmap` for the layout, :mod:`ibl_ref.environment.radiance_policy` for the values).

An :class:`Environment` holds such a cube as a **read-only float64** ``(6, N, N, C)`` array (C ≥ 1; a ``(6, N, N)``
input gets one channel), with its face size, channel count and the :class:`~ibl_ref.environment.radiance_policy.RadianceReport`
of its one check.  It is made in one of three ways:

* :func:`as_environment` (or ``Environment(x)``) validates anything else once — layout
  (:func:`~ibl_ref.environment.envmap.check_cube_shape`), then radiance
  (:func:`~ibl_ref.environment.radiance_policy.apply_policy`, by default refusing NaN, ±Inf, negative, complex,
  integer and boolean data) — and copies it, so the caller's array can change afterwards without changing the
  environment; an :class:`Environment` is returned unchanged, unchecked;
* the readers and generators return one that holds their own array, with the report of their read
  (:func:`ibl_ref.environment.exr_io.load_environment`, :func:`ibl_ref.synthetic.synthetic_envs.make_environment`);
* :func:`adopt` wraps an array a stage of the package made itself from a validated environment (a masked copy, a
  block average): valid by construction, so it is not checked again.

Every function of the package that takes an environment accepts a plain array or an :class:`Environment`: it
calls :func:`as_environment` with its own name for the argument, so a plain array is checked exactly once per call
and gives the same one-line :class:`~ibl_ref.errors.LayoutError` / :class:`~ibl_ref.errors.RadianceError` as
before, while an :class:`Environment` passes through every later stage with no further pass over its texels.
Functions that do not know the type read it as an array (``np.asarray(env)``, :meth:`Environment.__array__`: the
read-only array itself, no copy).  A ``(6, N, N)`` input becomes ``(6, N, N, 1)``; functions that return the shape
of their input return 4-D results for an :class:`Environment`.

Read-only means: the array the type exposes (:attr:`Environment.data`) is a read-only view of a read-only array
that no one else holds; neither writing to it nor setting its ``writeable`` flag back works, and a pickled copy is
read-only again.
"""

from __future__ import annotations

import numpy as np

from . import envmap
from ..errors import IBLError, LayoutError
from .radiance_policy import RadianceReport, apply_policy

__all__ = ["Environment", "as_environment", "environment_array", "adopt"]


class Environment:
    """A radiance cube map that passed the layout and radiance checks once.

    Parameters
    ----------
    data : array_like, shape (6, N, N) or (6, N, N, C)
        Radiance in the OpenEXR cube layout (:mod:`ibl_ref.environment.envmap`), any float dtype.
    name : str, optional
        What the array is called in error messages (default ``"environment"``).
    negative, nonfinite : str, optional
        Radiance policy (:mod:`ibl_ref.environment.radiance_policy`): ``"error"`` (default) refuses negative and
        NaN/Inf values; ``negative="clamp"`` / ``nonfinite="zero"`` repair them in the copy (recorded in
        :attr:`radiance`).

    Attributes
    ----------
    data : ndarray, float64, shape (6, N, N, C), read-only
        The radiance.
    face_size : int
        N.
    channels : int
        C (at least 1).
    radiance : RadianceReport
        What the one check found and did (``radiance.clean``: nothing to repair).
    name : str
        The name the environment was checked under.

    Raises
    ------
    LayoutError
        A shape other than (6, N, N) or (6, N, N, C), or zero channels.
    RadianceError
        NaN, ±Inf or negative values (under the default policy); complex, integer or boolean data.

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.environment.validated import Environment
    >>> env = Environment(np.full((6, 4, 4, 3), 2.0))
    >>> env
    Environment(face_size=4, channels=3, name='environment')
    >>> env.data.dtype, env.data.flags.writeable, env.radiance.clean
    (dtype('float64'), False, True)
    >>> Environment(np.zeros((6, 4, 5)))
    Traceback (most recent call last):
    ...
    ibl_ref.errors.LayoutError: environment: expected an array of shape (6, N, N) or (6, N, N, C), got (6, 4, 5)
    """

    __slots__ = ("_data", "_radiance")

    def __init__(self, data, name: str = "environment", *, negative: str = "error", nonfinite: str = "error"):
        envmap.check_cube_shape(data, name)  # LayoutError before any value is read
        a = np.asarray(data)
        if a.ndim == 4 and a.shape[3] < 1:
            raise LayoutError(f"{name}: zero channels in shape {a.shape}")
        fixed, rep = apply_policy(a, name, negative=negative, nonfinite=nonfinite)
        # a copy of the caller's array (a repaired one is a copy already): no one else can write to it
        self._set(np.array(a, dtype=np.float64, order="C") if fixed is a else fixed, rep)

    def _set(self, a: np.ndarray, radiance: RadianceReport) -> None:
        """Hold ``a`` (given up by the caller) read-only, as a read-only (6, N, N, C) view: the view's flag cannot be
        set back while the array under it is read-only."""
        a = np.ascontiguousarray(a, dtype=np.float64)
        b = a
        while isinstance(b, np.ndarray):  # the arrays under a view too (a view's flag follows its base's)
            b.flags.writeable = False
            b = b.base
        self._data = (a if a.ndim == 4 else a[..., None]).view()
        self._radiance = radiance

    @property
    def data(self) -> np.ndarray:
        return self._data

    @property
    def radiance(self) -> RadianceReport:
        return self._radiance

    @property
    def name(self) -> str:
        return self._radiance.name

    @property
    def face_size(self) -> int:
        return int(self._data.shape[1])

    @property
    def channels(self) -> int:
        return int(self._data.shape[3])

    @property
    def shape(self) -> tuple:
        """``(6, N, N, C)`` (so ``np.shape`` and ``np.ndim`` read it without converting)."""
        return self._data.shape

    @property
    def ndim(self) -> int:
        return 4

    @property
    def dtype(self) -> np.dtype:
        return self._data.dtype

    def __array__(self, dtype=None, copy=None):
        """The read-only array itself (``np.asarray(env)``); a writable copy with ``copy=True`` or another dtype."""
        if dtype is None or np.dtype(dtype) == self._data.dtype:
            return self._data.copy() if copy else self._data
        if copy is False:
            raise IBLError(f"an Environment holds float64; converting to {np.dtype(dtype)} needs a copy")
        return self._data.astype(dtype)

    def __repr__(self) -> str:
        return f"Environment(face_size={self.face_size}, channels={self.channels}, name={self.name!r})"

    def __reduce__(self):
        return adopt, (self._data, self._radiance)


def adopt(data, radiance: RadianceReport | None = None, name: str = "environment") -> Environment:
    """Wrap an array the package made itself as an :class:`Environment`, without checking its values.

    For the readers and generators (their own freshly read or generated array, with the report of their check) and
    for stages that derive an environment from a validated one (valid by construction: e.g. the masked copies of the
    partial environment maps, :mod:`ibl_ref.knuth2014.pem`).  The caller gives the array up: it is made read-only (and
    copied only if it is not C-contiguous float64).  Only the layout is checked (no pass over the values).  Not for
    arrays from outside the package: use :func:`as_environment`.

    Parameters
    ----------
    data : ndarray, shape (6, N, N) or (6, N, N, C)
        Finite, non-negative radiance.
    radiance : RadianceReport, optional
        The report of the check that made it valid (default: an empty, clean report named ``name``).
    name : str, optional
        Name of the default report.

    Returns
    -------
    Environment
    """
    envmap.check_cube_shape(data, name)
    if radiance is None:
        radiance = RadianceReport(name=name, negative_policy="error", nonfinite_policy="error",
                                  n_values=int(np.size(data)))
    env = Environment.__new__(Environment)
    env._set(np.asarray(data), radiance)
    return env


def as_environment(x, name: str = "environment", *, negative: str = "error", nonfinite: str = "error") -> Environment:
    """``x`` as an :class:`Environment`: returned unchanged if it is one, else validated once (and copied).

    The front door of every stage that takes an environment map.

    Parameters
    ----------
    x : Environment or array_like, shape (6, N, N) or (6, N, N, C)
        Radiance cube map (OpenEXR layout, :mod:`ibl_ref.environment.envmap`).
    name : str, optional
        What the array is called in error messages, e.g. ``"median cut input"`` (default ``"environment"``);
        unused for an :class:`Environment`.
    negative, nonfinite : str, optional
        Radiance policy for a plain array (:class:`Environment`); unused for an :class:`Environment`.

    Returns
    -------
    Environment

    Raises
    ------
    LayoutError, RadianceError
        As :class:`Environment`, naming ``name``.

    Examples
    --------
    A constant map; the solid angles of its texels sum to 4π, so ∫L dω = 4π·L:

    >>> import numpy as np
    >>> from ibl_ref.environment.envmap import texel_solid_angles
    >>> from ibl_ref.environment.validated import as_environment
    >>> env = as_environment(np.full((6, 8, 8), 0.5), "sky")
    >>> env.face_size, env.channels
    (8, 1)
    >>> float(np.einsum("fijc,ij->", env.data, texel_solid_angles(8)) / np.pi)
    2.0
    >>> as_environment(env) is env
    True
    >>> bad = np.ones((6, 8, 8, 3))
    >>> bad[2, 0, 0, 1] = np.nan
    >>> as_environment(bad, "sky")
    Traceback (most recent call last):
    ...
    ibl_ref.errors.RadianceError: sky: 1 non-finite value(s) (first: NaN at index (2, 0, 0, 1)): ...
    """
    if isinstance(x, Environment):
        return x
    return Environment(x, name, negative=negative, nonfinite=nonfinite)


def environment_array(x, name: str = "environment") -> tuple:
    """``(radiance, squeezed)`` of an environment argument: :func:`as_environment`'s read-only float64
    ``(6, N, N, C)`` array, and whether ``x`` was a ``(6, N, N)`` array (a function that returns the shape of its
    input drops the channel axis again).

    Parameters
    ----------
    x : Environment or array_like, shape (6, N, N) or (6, N, N, C)
    name : str, optional
        What the array is called in error messages.

    Returns
    -------
    radiance : ndarray, float64, shape (6, N, N, C), read-only
    squeezed : bool

    Raises
    ------
    LayoutError, RadianceError
        As :class:`Environment`, naming ``name``.

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.environment.validated import environment_array
    >>> a, squeezed = environment_array(np.ones((6, 2, 2)))
    >>> a.shape, squeezed
    ((6, 2, 2, 1), True)
    """
    return as_environment(x, name).data, np.ndim(x) == 3
