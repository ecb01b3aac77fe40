"""OpenEXR environment-map files: CUBE strips, LATLONG maps and multi-part MIP pyramids.

File layouts (OpenEXR ``ImfEnvmap.h``; see ``docs/background.md`` §2 and :mod:`ibl_ref.environment.envmap`)
------------------------------------------------------------------------------------------
* **CUBE** (header attribute ``envmap = ENVMAP_CUBE``): one image ``N`` wide and ``6N`` high, the six
  faces stacked top to bottom in the order ``+X, -X, +Y, -Y, +Z, -Z``.  Face ``f`` occupies scanlines
  ``f·N … f·N+N−1``; pixel ``(x, y)`` of the strip is texel ``cube[y // N, y % N, x]`` of the in-memory
  ``(6, N, N, C)`` array, whose face orientation *is* OpenEXR's (``envmap.py``).  So reading or writing a
  CUBE file is a reshape, never a flip.
* **LATLONG** (``envmap = ENVMAP_LATLONG``): an ``H × 2H`` image, top row latitude +π/2, left column
  longitude +π (``envmap.latlong_directions``).  In memory ``(H, W, C)``.
* **Channels**: ``R, G, B`` (C = 3), ``R, G, B, A`` (C = 4) or a single luminance channel ``Y`` (C = 1).
  Arrays in memory always carry the channel axis.  The pixel type is ``float`` (32 bit) or ``half``
  (16 bit, max finite value 65504).  Files are written with lossless ZIP compression unless the caller names
  another (``ibl-ref prefilter``'s float32 level cubes: none, ZIP saves 2 % there).  Channel arrays are handed
  to the binding C-contiguous: the OpenEXR 3.5 Python binding ignores strides and writes a non-contiguous view as
  its raw buffer (scrambled pixels, no error).
* **OpenGL-oriented cube files**: ``write_envmap(..., convention="opengl")`` writes the faces re-oriented
  to the OpenGL/D3D convention (:func:`ibl_ref.environment.envmap.convert_convention`).  Such a strip is *not* an
  OpenEXR CUBE map, so it is written **without** the ``envmap`` attribute and with the string attribute
  ``iblref_convention = "opengl"``; :func:`read_envmap` honours that attribute and always returns
  OpenEXR-oriented arrays.  Every cube file ibl_ref writes carries ``iblref_convention``.
* **MIP pyramids** (:func:`write_pyramid`): a multi-part EXR (the Python binding's tiled/mip-mapped
  writing is unreliable, docs/background.md §2), one scanline part per level, named ``level0``, ``level1``, …,
  each a CUBE strip of its own size (``envmap = ENVMAP_CUBE``, int attribute ``iblref_level``).  All
  parts share level 0's display window (OpenEXR requires shared attributes to agree); each part's
  data window is its own strip size.

One writer, one reader
----------------------
Every OpenEXR file ibl_ref writes goes through :func:`write_exr` and every one it reads through
:func:`read_exr` (environment maps here, rendered images in :mod:`ibl_ref.rendering.image_io`, probe-like
test files in :mod:`ibl_ref.environment.probe_files`, the ``convert`` / ``info`` commands).  Header
policy of :func:`write_exr`: scanline parts, ZIP compression unless the caller names another, the caller's
attributes (``envmap``, ``iblref_*``) and nothing else; each channel is handed to the binding as its own
C-contiguous array.  File names that are not valid UTF-8 are passed to the binding as bytes (it refuses
such ``str`` names with an unrelated message).

Validation
----------
Writers check the data first (:func:`ibl_ref.environment.radiance_policy.check_radiance`: NaN, ±Inf, negative radiance →
:class:`~ibl_ref.errors.RadianceError`) and never let a value overflow silently: in ``half`` a value
above 65504 raises :class:`~ibl_ref.errors.IBLError` naming the file, the count and the maximum, unless
``clamp_half=True``, which clamps to 65504, warns and reports the clamping in the returned
:class:`WriteReport`.  Values below the pixel type's normal range (half: 6.1e-5, float: 1.2e-38) are
measured as a share of ∫L dω and refused or reported
(:func:`ibl_ref.environment.radiance_policy.check_format_range`): a map of 1e-8 written as half is an error,
not a black file.  Every write is atomic (:func:`ibl_ref.atomic.atomic_path`, the temporary file keeps
the ``.exr`` suffix): on any error the previous file is untouched and no temporary file remains.

Readers raise :class:`~ibl_ref.errors.EnvMapFileError`, :class:`~ibl_ref.errors.LayoutError` or
:class:`~ibl_ref.errors.RadianceError` with a message that names the file and the problem (missing,
not an EXR / truncated, wrong aspect ratio, missing R/G/B channels).  Negative and non-finite
radiance follow :mod:`ibl_ref.environment.radiance_policy` (parameters ``negative`` and ``nonfinite`` of every
reader): by default the tiny negatives of lossy (DWAB) compression are clamped to 0 and reported,
negatives carrying more than 1e-4 of ∫|L| dω and any NaN/Inf are errors.
"""

from __future__ import annotations

import contextlib
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import envmap
from ..atomic import atomic_path
from ..errors import (EnvMapFileError, FormatRangeWarning, IBLError, LayoutError, RadianceError, as_path,
                      check_input_file)
from .radiance_policy import check_radiance
from .validated import Environment, adopt
from . import resample
from ..limits import SizeError
from ..limits import check_allocation
from .radiance_policy import apply_policy
from .radiance_policy import check_format_range
from .radiance_policy import pixel_solid_angles
from .radiance_policy import warn_repaired

__all__ = [
    "HALF_MAX",
    "FLOAT_MAX",
    "HALF_MIN_NORMAL",
    "FLOAT_MIN_NORMAL",
    "COMPRESSIONS",
    "EnvMap",
    "ExrImage",
    "ExrPart",
    "WriteReport",
    "write_exr",
    "read_exr",
    "to_pixel_type",
    "write_envmap",
    "read_envmap",
    "read_map",
    "read_image",
    "load_cube",
    "load_environment",
    "write_pyramid",
    "read_pyramid",
    "infer_layout",
    "declared_layout",
    "cube_convention",
    "header_dict",
]

HALF_MAX = 65504.0  #: largest finite IEEE binary16 value
FLOAT_MAX = float(np.finfo(np.float32).max)
HALF_MIN_NORMAL = float(np.finfo(np.float16).tiny)  #: 2^-14, smallest half of full relative precision
FLOAT_MIN_NORMAL = float(np.finfo(np.float32).tiny)  #: 2^-126
#: compression names accepted by :func:`write_exr` (OpenEXR's ``*_COMPRESSION`` constants)
COMPRESSIONS = ("dwab", "dwaa", "piz", "zip", "zips", "none", "rle", "pxr24", "b44")
_LAYOUTS = ("cube", "latlong")
_PIXEL_TYPES = ("float", "half")
_HDR_SUFFIXES = (".hdr", ".pic", ".rgbe")


def _openexr():
    try:
        import OpenEXR
    except ImportError as exc:  # pragma: no cover - dependency declared in pyproject
        raise EnvMapFileError("the OpenEXR Python package (>= 3.2) is required for .exr files") from exc
    return OpenEXR


@dataclass
class EnvMap:
    """An environment map read from a file.

    Attributes
    ----------
    data : ndarray, float64
        ``(6, N, N, C)`` for ``layout == "cube"`` (OpenEXR face order and orientation), ``(H, 2H, C)``
        for ``"latlong"``.
    layout : {"cube", "latlong"}
    path : Path
    channels : tuple of str
        ``("R", "G", "B")``, ``("R", "G", "B", "A")`` or ``("Y",)``, matching the last axis of ``data``.
    header : dict
        File header attributes converted to simple Python values (str, int, float, lists).
    pixel_type : str
        ``"half"``, ``"float"``, ``"uint"`` or ``"mixed"`` as stored in the file.
    radiance : RadianceReport
        What the radiance policy found and did (:mod:`ibl_ref.environment.radiance_policy`).
    file_format : str
        ``"OpenEXR"`` or ``"Radiance RGBE"``.
    source_layout : str
        Layout of the image in the file: ``layout`` itself, or ``"hcross"`` / ``"vcross"`` for a cross
        cut into a cube by :func:`read_map`.
    """

    data: np.ndarray
    layout: str
    path: Path
    channels: tuple
    header: dict = field(default_factory=dict)
    pixel_type: str = "float"
    radiance: object = None  #: :class:`ibl_ref.environment.radiance_policy.RadianceReport` of the read
    file_format: str = "OpenEXR"
    source_layout: str = ""

    @property
    def size(self) -> int:
        """Face size N (cube) or height H (lat-long)."""
        return int(self.data.shape[1] if self.layout == "cube" else self.data.shape[0])


@dataclass
class WriteReport:
    """What :func:`write_envmap` / :func:`write_pyramid` wrote.

    ``clamped_count`` values above :data:`HALF_MAX` were clamped to it (only with ``clamp_half=True``);
    ``clamped_max`` is the largest original value among them (0 if none).
    """

    path: Path
    layout: str
    pixel_type: str
    shape: tuple
    clamped_count: int = 0
    clamped_max: float = 0.0


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------
def _channel_names(c: int, where: str) -> tuple:
    if c == 1:
        return ("Y",)
    if c == 3:
        return ("R", "G", "B")
    if c == 4:
        return ("R", "G", "B", "A")
    raise LayoutError(f"{where}: expected 1 (Y), 3 (RGB) or 4 (RGBA) channels, got {c}")


def _simple(v):
    """Header value → plain Python value (for EnvMap.header)."""
    if isinstance(v, (str, int, float, bool)) or v is None:
        return v
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, (tuple, list)):
        return [_simple(x) for x in v]
    name = getattr(v, "name", None)
    if isinstance(name, str):
        return name
    return str(v)


def _prepare(data, layout: str, where: str):
    """Validate a cube/latlong array (an :class:`~ibl_ref.environment.validated.Environment`'s radiance was checked
    when it was made: not again); return the strip (H, W, C) float64."""
    if layout not in _LAYOUTS:
        raise LayoutError(f"{where}: unknown layout {layout!r}; choose one of {_LAYOUTS}")
    a = np.asarray(data)
    if layout == "cube":
        envmap.check_cube_shape(a, f"{where}: cube map")
        if a.ndim == 3:
            a = a[..., None]
        n = a.shape[1]
        strip = a.reshape(6 * n, n, a.shape[3])
    else:
        if a.ndim == 2:
            a = a[..., None]
        if a.ndim != 3 or a.shape[1] != 2 * a.shape[0] or a.shape[0] < 1:
            raise LayoutError(f"{where}: lat-long maps must have shape (H, 2H[, C]), got {np.shape(data)}")
        strip = a
    _channel_names(strip.shape[2], where)
    if not isinstance(data, Environment):
        check_radiance(strip, f"{where}: radiance")
    return strip.astype(np.float64, copy=False)


def to_pixel_type(strip: np.ndarray, pixel_type: str, clamp_half: bool, where: str, weights=None):
    """Cast radiance to float32/float16 for :func:`write_exr` without silent overflow or underflow.

    Parameters
    ----------
    strip : ndarray, float64, shape (H, W, C)
        Checked radiance.
    pixel_type : {"float", "half"}
    clamp_half : bool
        With ``"half"``: clamp values above :data:`HALF_MAX` (warned) instead of refusing them.
    where : str
        Names the file in messages.
    weights : array_like, optional
        Per-pixel solid angles broadcastable to (H, W) (None: pixel sums) for the share of ∫L dω that values below
        the pixel type's normal range would change (:func:`ibl_ref.environment.radiance_policy.check_format_range`).

    Returns
    -------
    pixels : ndarray, float16 or float32, shape (H, W, C)
    clamped_count : int
    clamped_max : float
        The largest clamped value (0 if none).

    Raises
    ------
    IBLError
        Values that overflow the pixel type (unless clamped), an unknown pixel type.
    RadianceError
        Values below the normal range that carry more than 1e-4 of ∫L dω.
    """

    if pixel_type not in _PIXEL_TYPES:
        raise IBLError(f"{where}: unknown pixel type {pixel_type!r}; choose one of {_PIXEL_TYPES}")
    limit = HALF_MAX if pixel_type == "half" else FLOAT_MAX
    over = strip > limit
    count, vmax = int(over.sum()), float(strip.max()) if strip.size else 0.0
    if count:
        if pixel_type == "float" or not clamp_half:
            hint = " (pass clamp_half=True / --clamp-half to clamp, or write pixel_type='float')" if pixel_type == "half" else ""
            raise IBLError(
                f"{where}: {count} value(s) exceed the largest finite {pixel_type} ({limit:g}); "
                f"max value {vmax:g}; writing them would produce Inf{hint}"
            )
        warnings.warn(
            f"{where}: clamped {count} value(s) above {HALF_MAX:g} to {HALF_MAX:g} for half output "
            f"(max original value {vmax:g})",
            FormatRangeWarning,
            stacklevel=3,
        )
        strip = np.minimum(strip, HALF_MAX)
    out = strip.astype(np.float16 if pixel_type == "half" else np.float32)
    if not np.all(np.isfinite(out)):  # defensive: must be impossible after the checks above
        raise IBLError(f"{where}: conversion to {pixel_type} produced non-finite values")
    nc = 3 if strip.shape[-1] >= 3 else 1  # colour channels (alpha is not radiance)
    remedy = ("scale the map up, or write float pixels: pixel_type='float', no --half" if pixel_type == "half"
              else "scale the map up")
    check_format_range(strip[..., :nc], out[..., :nc], where, f"the smallest normal {pixel_type}",
                       HALF_MIN_NORMAL if pixel_type == "half" else FLOAT_MIN_NORMAL, weights, remedy)
    return out, count, (vmax if count else 0.0)


# ----------------------------------------------------------------------------------------------
# writing
# ----------------------------------------------------------------------------------------------
@dataclass
class ExrPart:
    """One part for :func:`write_exr`: ``pixels`` (H, W, C) float16 or float32 (or a list of C (H, W) planes, which
    big probes need: no stacked copy), one name per channel, header ``attributes`` (e.g. ``envmap``,
    ``iblref_convention``; the binding's types) and an optional part name."""

    pixels: np.ndarray
    channels: tuple
    attributes: dict = field(default_factory=dict)
    name: str | None = None


def _ox_compression(ox, name: str, where: str):
    if name not in COMPRESSIONS:
        raise IBLError(f"{where}: unknown compression {name!r}; choose one of {COMPRESSIONS}")
    return getattr(ox, f"{'NO' if name == 'none' else name.upper()}_COMPRESSION")


def _binding_path(path) -> "str | bytes":
    """The file name as the binding takes it: ``str``, or bytes for names that are not valid UTF-8."""
    s = os.fspath(path)
    try:
        s.encode("utf-8")
    except UnicodeEncodeError:  # surrogate-escaped bytes of a non-UTF-8 name: the binding refuses such str
        return os.fsencode(s)
    return s


def write_exr(path, parts, compression: str = "zip") -> Path:
    """The one OpenEXR writer: ``parts`` → ``path``, atomically.

    Header policy (module docstring): scanline, ``compression`` (one of :data:`COMPRESSIONS`, default ZIP),
    each part's attributes; several parts (or a named one) make a multi-part file.  Pixels are written as
    given: the callers check radiance and range (:func:`write_envmap`, :func:`write_pyramid`,
    :func:`ibl_ref.rendering.image_io.write_image_exr`).

    Parameters
    ----------
    path : str, bytes or os.PathLike
    parts : ExrPart or list of ExrPart
    compression : str, optional
        One of :data:`COMPRESSIONS` (default ``"zip"``, lossless).

    Returns
    -------
    pathlib.Path
        The file written.

    Raises
    ------
    EnvMapFileError
        The binding cannot write the file (message names ``path``).
    OutputError
        The target cannot be replaced (:mod:`ibl_ref.atomic`: folder, device, full disk …).
    """
    ox = _openexr()
    path = as_path(path, "OpenEXR output")
    where = str(path)
    parts = [parts] if isinstance(parts, ExrPart) else list(parts)
    if not parts:
        raise LayoutError(f"{where}: an OpenEXR file needs at least one part")
    comp = _ox_compression(ox, compression, where)
    built = []
    for part in parts:
        if isinstance(part.pixels, (list, tuple)):
            planes = [np.asarray(x) for x in part.pixels]
        else:
            px = np.asarray(part.pixels)
            planes = [px[..., i] for i in range(px.shape[2])] if px.ndim == 3 else [px]
        if (len(planes) != len(part.channels) or len({x.shape for x in planes}) != 1 or planes[0].ndim != 2
                or any(x.dtype not in (np.float16, np.float32) for x in planes)):
            raise LayoutError(f"{where}: part pixels must be (H, W, {len(part.channels)}) float16/float32, got "
                              f"{[x.shape for x in planes]} {sorted({str(x.dtype) for x in planes})}")
        header = {"compression": comp, "type": ox.scanlineimage}
        header.update(part.attributes)
        # one C-contiguous array per channel: the binding ignores strides (a view would be written scrambled)
        chans = {nm: np.ascontiguousarray(x) for nm, x in zip(part.channels, planes)}
        built.append((header, chans, part.name))
    try:
        with atomic_path(path, suffix=".exr") as tmp:
            if len(built) == 1 and built[0][2] is None:
                f = ox.File(built[0][0], built[0][1])
            else:
                f = ox.File([ox.Part(h, c, name=nm or f"part{i}") for i, (h, c, nm) in enumerate(built)])
            f.write(_binding_path(tmp))
    except IBLError:
        raise
    except (OSError, RuntimeError, ValueError, TypeError) as exc:
        raise EnvMapFileError(f"{where}: cannot write OpenEXR file: {exc}") from exc
    return path


def _strip_weights(strip: np.ndarray, layout: str):

    return pixel_solid_angles(strip.shape[0], strip.shape[1], layout)


def write_envmap(
    path,
    data,
    layout: str = "cube",
    pixel_type: str = "float",
    clamp_half: bool = False,
    convention: str = "openexr",
    compression: str = "zip",
) -> WriteReport:
    """Write a cube map or lat-long map as an OpenEXR environment map (atomically, through :func:`write_exr`).

    Parameters
    ----------
    path : str, bytes or os.PathLike
        Destination file (any name; ``.exr`` recommended).
    data : array_like or Environment
        ``(6, N, N[, C])`` for ``layout="cube"`` in OpenEXR face orientation, ``(H, 2H[, C])`` for
        ``"latlong"``; C ∈ {1, 3, 4} → channels Y / RGB / RGBA.  The radiance of a validated
        :class:`~ibl_ref.environment.validated.Environment` is not checked again.
    layout : {"cube", "latlong"}
    pixel_type : {"float", "half"}
    clamp_half : bool
        With ``pixel_type="half"``: clamp values above 65504 (warns and reports them) instead of raising.
    convention : {"openexr", "opengl"}
        Face orientation *in the file* (cube only).  ``"opengl"`` files carry no ``envmap`` attribute
        (they are not OpenEXR CUBE maps) but ``iblref_convention = "opengl"``.
    compression : str, optional
        One of :data:`COMPRESSIONS` (default ``"zip"``; ``"none"`` where the pixels hardly compress and the time
        matters: float32 radiance, whose mantissas are noise to ZIP — 2 % smaller files at twice the write time).

    Returns
    -------
    WriteReport

    Raises
    ------
    RadianceError
        NaN, Inf or negative values (checked before any file is touched), or values below the pixel type's
        range that carry more than 1e-4 of ∫L dω (module docstring).
    LayoutError
        Wrong shape or channel count.
    IBLError
        Values that do not fit the pixel type.

    Examples
    --------
    A lat-long map of 1e5 does not fit half floats unless clamped (then the report counts the clamped values):

    >>> import os, tempfile, warnings
    >>> import numpy as np
    >>> from ibl_ref.environment.exr_io import read_envmap, write_envmap
    >>> folder = tempfile.TemporaryDirectory()
    >>> path = os.path.join(folder.name, "sun.exr")
    >>> img = np.ones((4, 8, 3))
    >>> img[1, 2] = 1e5
    >>> write_envmap(path, img, layout="latlong", pixel_type="half")
    Traceback (most recent call last):
    ...
    ibl_ref.errors.IBLError: ...: 3 value(s) exceed the largest finite half (65504); max value 100000; ...
    >>> with warnings.catch_warnings():
    ...     warnings.simplefilter("ignore")
    ...     report = write_envmap(path, img, layout="latlong", pixel_type="half", clamp_half=True)
    >>> report.clamped_count, float(read_envmap(path).data.max())
    (3, 65504.0)
    >>> folder.cleanup()
    """
    ox = _openexr()
    path = as_path(path, "OpenEXR output")
    where = str(path)
    if convention not in envmap.CONVENTIONS:
        raise IBLError(f"{where}: unknown convention {convention!r}; choose one of {envmap.CONVENTIONS}")
    strip = _prepare(data, layout, where)
    if layout == "cube" and convention != "openexr":
        n = strip.shape[1]
        strip = envmap.convert_convention(strip.reshape(6, n, n, -1), "openexr", convention).reshape(strip.shape)
    elif layout == "latlong" and convention != "openexr":
        raise IBLError(f"{where}: convention={convention!r} applies to cube maps only")
    pix, count, cmax = to_pixel_type(strip, pixel_type, clamp_half, where, _strip_weights(strip, layout))
    attrs = {}
    if layout == "latlong":
        attrs["envmap"] = ox.ENVMAP_LATLONG
    else:
        if convention == "openexr":
            attrs["envmap"] = ox.ENVMAP_CUBE
        attrs["iblref_convention"] = convention
    write_exr(path, ExrPart(pix, _channel_names(pix.shape[2], where), attrs), compression=compression)
    return WriteReport(path, layout, pixel_type, tuple(np.shape(data)), count, cmax)


def write_pyramid(path, levels, pixel_type: str = "float", clamp_half: bool = False) -> WriteReport:
    """Write a list of cube maps (a MIP pyramid, level 0 first) as a multi-part EXR (through :func:`write_exr`).

    One part per level, named ``level{i}``, each an OpenEXR CUBE strip (see module docstring).

    Parameters
    ----------
    path : str, bytes or os.PathLike
    levels : sequence of array_like, each (6, n, n[, C])
        The same channel count C on every level.
    pixel_type, clamp_half
        As :func:`write_envmap`.

    Returns
    -------
    WriteReport
        ``shape`` is the list of level shapes; clamping counts are summed over levels.

    Raises
    ------
    LayoutError, RadianceError, IBLError
        As :func:`write_envmap`, per level; no level, or levels with different channel counts.
    """
    ox = _openexr()
    path = as_path(path, "OpenEXR output")
    where = str(path)
    levels = list(levels)
    if not levels:
        raise LayoutError(f"{where}: a pyramid needs at least one level")
    strips, total, cmax = [], 0, 0.0
    for i, lv in enumerate(levels):
        s = _prepare(lv, "cube", f"{where} level {i}")
        if strips and s.shape[2] != strips[0].shape[2]:
            raise LayoutError(f"{where}: level {i} has {s.shape[2]} channels, level 0 has {strips[0].shape[2]}")
        p, c, m = to_pixel_type(s, pixel_type, clamp_half, f"{where} level {i}", _strip_weights(s, "cube"))
        strips.append(p)
        total += c
        cmax = max(cmax, m)
    n0 = strips[0].shape[1]
    display = (np.array([0, 0], dtype=np.int32), np.array([n0 - 1, 6 * n0 - 1], dtype=np.int32))
    names = _channel_names(strips[0].shape[2], where)
    parts = [ExrPart(p, names, {"envmap": ox.ENVMAP_CUBE, "displayWindow": display, "iblref_convention": "openexr",
                                "iblref_level": i}, name=f"level{i}") for i, p in enumerate(strips)]
    write_exr(path, parts)
    return WriteReport(path, "cube", pixel_type, tuple(np.shape(x) for x in levels), total, cmax)


# ----------------------------------------------------------------------------------------------
# reading
# ----------------------------------------------------------------------------------------------
_EXR_MAGIC = b"\x76\x2f\x31\x01"
_FLAG_TILED, _FLAG_LONG_NAMES, _FLAG_DEEP, _FLAG_MULTIPART = 0x200, 0x400, 0x800, 0x1000


def _chlist_count(val: bytes) -> int:
    """Number of channels in a ``chlist`` attribute value: per channel a NUL-terminated name followed by 16 bytes
    (pixel type int32, pLinear uint8, 3 reserved bytes, x/y sampling int32 — which may contain NUL bytes
    themselves), ended by one NUL byte (OpenEXR file layout)."""
    n, i = 0, 0
    while i < len(val) and val[i] != 0:
        end = val.find(b"\0", i)
        if end < 0:
            break
        n += 1
        i = end + 1 + 16
    return n


def _scan_headers(path: Path, buf: bytes) -> list:
    """Parse the OpenEXR header(s) ourselves, before the binding allocates anything.

    OpenEXR file layout (openexr.com, "OpenEXR File Layout"): magic ``76 2f 31 01``, a 4-byte version
    field (bits 0-7 version 2; flag bits 0x200 single-part tiled, 0x800 deep / "non-image", 0x1000
    multi-part), then per part a list of attributes ``name\\0 type\\0 int32 size value`` ended by an
    empty name (multi-part files: one such list per part, the sequence ended by an empty header).
    Returns one dict per part with ``type`` (storage string or None), ``dataWindow`` (xmin, ymin, xmax,
    ymax) and ``n_channels``.  Raises :class:`EnvMapFileError` for deep files, truncated headers and
    invalid data windows, :class:`~ibl_ref.limits.SizeError` for data windows that cannot fit in memory.
    """
    import struct


    if len(buf) < 8:
        raise EnvMapFileError(f"{path}: truncated OpenEXR file ({len(buf)} bytes)")
    flags = struct.unpack_from("<i", buf, 4)[0]
    if flags & 0xFF != 2:
        raise EnvMapFileError(f"{path}: unsupported OpenEXR version {flags & 0xFF} (expected 2)")
    if flags & _FLAG_DEEP:
        raise EnvMapFileError(f"{path}: deep OpenEXR file (a list of samples per pixel); ibl_ref reads flat "
                              "scanline or tiled images only (flatten it first)")
    pos, parts = 8, []

    def cstr():
        nonlocal pos
        end = buf.find(b"\0", pos)
        if end < 0 or end - pos > 255:
            raise EnvMapFileError(f"{path}: truncated or corrupt OpenEXR header")
        out = buf[pos:end].decode("latin-1")
        pos = end + 1
        return out

    while True:
        hdr = {"type": None, "dataWindow": None, "n_channels": 0}
        name = cstr()
        if name == "":
            if not parts:
                raise EnvMapFileError(f"{path}: corrupt OpenEXR header (no attributes)")
            break
        while name != "":
            typ = cstr()
            if pos + 4 > len(buf):
                raise EnvMapFileError(f"{path}: truncated OpenEXR header")
            size = struct.unpack_from("<i", buf, pos)[0]
            pos += 4
            if size < 0 or pos + size > len(buf):
                raise EnvMapFileError(f"{path}: truncated or corrupt OpenEXR header (attribute {name!r})")
            val = buf[pos : pos + size]
            pos += size
            if name == "type" and typ == "string":
                hdr["type"] = val.decode("latin-1")
            elif name == "dataWindow" and typ == "box2i" and size == 16:
                hdr["dataWindow"] = struct.unpack("<4i", val)
            elif name == "channels" and typ == "chlist":
                hdr["n_channels"] = max(1, _chlist_count(val))
            name = cstr()
        parts.append(hdr)
        if not flags & _FLAG_MULTIPART:
            break
    for i, hdr in enumerate(parts):
        where = f"{path}" + (f" (part {i})" if len(parts) > 1 else "")
        if hdr["type"] and hdr["type"].startswith("deep"):
            raise EnvMapFileError(f"{where}: deep OpenEXR image ({hdr['type']}: a list of samples per pixel); "
                                  "ibl_ref reads flat scanline or tiled images only (flatten it first)")
        if hdr["dataWindow"] is None:
            raise EnvMapFileError(f"{where}: corrupt OpenEXR header (no dataWindow attribute)")
        x0, y0, x1, y1 = hdr["dataWindow"]
        w, h = x1 - x0 + 1, y1 - y0 + 1
        if w < 1 or h < 1:
            raise EnvMapFileError(f"{where}: invalid OpenEXR data window {hdr['dataWindow']} ({w} x {h} pixels)")
        try:  # the binding's arrays (≤ 4 bytes per sample) plus our float64 copy
            check_allocation(w * h * max(hdr["n_channels"], 1) * 12, f"the {w} x {h} data window", str(where))
        except SizeError as exc:
            raise EnvMapFileError(str(exc)) from None
    return parts


def _flush_c_stdio() -> None:
    try:
        import ctypes

        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):  # pragma: no cover - no C library handle on this platform
        pass


class _NativeOutput:
    """Capture what the OpenEXR binding prints (on file descriptors 1 and 2 and on sys.stdout/stderr)."""

    def __enter__(self):
        import sys
        import tempfile

        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        self._tmp = tempfile.TemporaryFile()
        self._saved = []
        for fd in (1, 2):
            try:
                self._saved.append((fd, os.dup(fd)))
                os.dup2(self._tmp.fileno(), fd)
            except OSError:  # no such descriptor (embedded interpreter): nothing to capture
                pass
        self.text = ""
        # the binding also prints through Python's sys.stdout (pybind11 py::print): capture that level too
        import io

        self._py = io.StringIO()
        self._redirects = contextlib.ExitStack()
        self._redirects.enter_context(contextlib.redirect_stdout(self._py))
        self._redirects.enter_context(contextlib.redirect_stderr(self._py))
        return self

    def __exit__(self, *exc):
        self._redirects.close()
        _flush_c_stdio()  # C++ iostreams write through C stdio buffers (sync_with_stdio): flush them here
        for fd, saved in self._saved:
            os.dup2(saved, fd)
            os.close(saved)
        self._tmp.seek(0)
        self.text = self._tmp.read().decode("utf-8", "replace") + self._py.getvalue()
        self._tmp.close()
        return False

    def first_line(self) -> str:
        lines = [ln.strip() for ln in self.text.splitlines() if ln.strip()]
        return lines[0] if lines else ""


def _open(path: Path):
    ox = _openexr()
    check_input_file(path, "an OpenEXR file")
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 20)
    except OSError as exc:
        raise EnvMapFileError(f"{path}: cannot read: {exc.strerror}") from exc
    magic = head[:4]
    if magic != _EXR_MAGIC:
        raise EnvMapFileError(f"{path}: not an OpenEXR file (bad magic number {magic!r})")
    _scan_headers(path, head)
    native = _NativeOutput()
    try:
        with native:
            f = ox.File(_binding_path(path), separate_channels=True)
            parts = list(f.parts)
            if parts:
                for p in parts:  # force pixel access now so that truncation errors surface here
                    for ch in p.channels.values():
                        _ = ch.pixels.shape
    except IBLError:
        raise
    except MemoryError:
        raise EnvMapFileError(f"{path}: not enough memory to read the OpenEXR file") from None
    except Exception as exc:  # the binding raises RuntimeError/ValueError/IndexError for corrupt files
        detail = native.first_line() or str(exc)
        raise EnvMapFileError(f"{path}: corrupt or truncated OpenEXR file ({detail})") from exc
    if not parts:
        detail = native.first_line() or "no readable parts"
        raise EnvMapFileError(f"{path}: corrupt or truncated OpenEXR file ({detail})")
    if "Exception raised" in native.text or "EXR_ERR" in native.text:
        raise EnvMapFileError(f"{path}: corrupt or truncated OpenEXR file ({native.first_line()})")
    return f, parts


def cube_convention(header: dict, override=None, where: str = "image") -> str:
    """The face convention of a cube strip: ``override`` or the file's ``iblref_convention`` attribute.

    Parameters
    ----------
    header : dict
        The file's header (:attr:`EnvMap.header`).
    override : {"openexr", "opengl"}, optional
    where : str, optional
        Names the file in messages.

    Returns
    -------
    str

    Raises
    ------
    LayoutError
        An unknown convention.
    """
    conv = override if override is not None else header.get("iblref_convention", "openexr")
    if not isinstance(conv, str) or conv not in envmap.CONVENTIONS:
        src = "convention" if override is not None else "iblref_convention attribute"
        raise LayoutError(f"{where}: unknown cube {src} {conv!r}; expected one of {envmap.CONVENTIONS}")
    return conv


@dataclass
class ExrImage:
    """One part of an OpenEXR file as :func:`read_exr` returns it (radiance not yet checked).

    ``pixels`` (H, W, C) with ``channels`` in that order: the colour channels first (``R, G, B`` or ``Y``;
    ``n_colour`` of them, 0 if the part has neither), then alpha or, with ``channels="all"``, every other
    channel.  ``pixel_type``: ``"half"``, ``"float"``, ``"uint"`` or ``"mixed"``; ``header``: plain Python
    values; ``n_parts``: parts in the file; ``where``: the name used in messages (file and part).
    """

    pixels: np.ndarray
    channels: tuple
    n_colour: int
    pixel_type: str
    header: dict
    n_parts: int
    where: str


def _channel_order(names: set, which: str, where: str) -> tuple:
    """(order, n_colour) of a part's channels for :func:`read_exr` (``which`` = ``"colour"`` or ``"all"``)."""
    if {"R", "G", "B"} <= names:
        colour = ["R", "G", "B"]
    elif "Y" in names and (which == "all" or names <= {"Y", "A"}):
        colour = ["Y"]
    else:
        colour = []
    if which == "all":
        return tuple(colour + sorted(names - set(colour))), len(colour)
    if not colour:
        raise LayoutError(f"{where}: missing R/G/B channels (file has channels {sorted(names)})")
    return tuple(colour + (["A"] if colour != ["Y"] and "A" in names else [])), len(colour)


def _part_image(path: Path, part, label: str = "", dtype=np.float64, which: str = "colour"):
    """Raw (H, W, C) image (``dtype``), channel names, colour-channel count, pixel type and header of one part.

    No radiance check here (see :func:`_radiance`); channels are copied one by one into the result and
    the binding's copy of each is released at once (no stacked temporary: a 16K float32 RGB file peaks
    at the binding's 1.6 GB plus the result).  The part's channels are empty afterwards.
    """
    where = f"{path}{label}"
    chans = part.channels
    order, n_colour = _channel_order(set(chans), which, where)
    arrs, types = [], set()
    for nm in order:
        px = chans[nm].pixels
        if px is None or px.ndim != 2:
            raise EnvMapFileError(f"{where}: channel {nm} has no readable 2D pixel data")
        arrs.append(px)
        types.add(_simple(chans[nm].type()))
    shapes = {a.shape for a in arrs}
    if len(shapes) != 1:
        raise LayoutError(f"{where}: channels have different sizes {sorted(shapes)} (subsampled channels unsupported)")
    img = np.empty(arrs[0].shape + (len(arrs),), dtype=dtype)
    del arrs
    for i, nm in enumerate(order):
        img[..., i] = chans[nm].pixels
        chans[nm].pixels = np.empty((0, 0), np.float32)  # release the binding's copy now (big probes)
    ptype = {"HALF": "half", "FLOAT": "float", "UINT": "uint"}
    pixel_type = ptype.get(types.pop(), "mixed") if len(types) == 1 else "mixed"
    return img, order, n_colour, pixel_type, header_dict(part, where)


def read_exr(path, part: int = 0, dtype=np.float64, channels: str = "colour") -> ExrImage:
    """The one OpenEXR reader: one part of ``path`` as an :class:`ExrImage`, radiance unchecked.

    The header is parsed by ibl_ref first (deep files, impossible data windows and sizes beyond memory are
    refused before the binding allocates anything); the binding's own error text for corrupt or truncated
    files becomes the one-line :class:`~ibl_ref.errors.EnvMapFileError`.

    Parameters
    ----------
    path : str, bytes or os.PathLike
    part : int, optional
        Part index (0 = first).
    dtype : numpy dtype, optional
        float64 (default) or float32 (exact for half and float files, half the memory).
    channels : {"colour", "all"}, optional
        ``"colour"`` reads ``R, G, B`` (+ ``A``) or ``Y`` and refuses parts with neither (:class:`LayoutError`);
        ``"all"`` reads every channel, colour first, and refuses nothing a decoder can read (``ibl-ref info``).

    Returns
    -------
    ExrImage

    Raises
    ------
    EnvMapFileError
        A missing, corrupt, truncated or deep file; a part that does not exist.
    LayoutError
        No colour channels (``channels="colour"``), subsampled channels.
    """
    path = as_path(path, "OpenEXR file")
    if channels not in ("colour", "all"):
        raise IBLError(f"{path}: channels must be 'colour' or 'all', got {channels!r}")
    _, parts = _open(path)
    if isinstance(part, bool) or not isinstance(part, (int, np.integer)) or not 0 <= part < len(parts):
        raise EnvMapFileError(f"{path}: has {len(parts)} part(s), part {part!r} requested")
    label = f" (part {part})" if len(parts) > 1 else ""
    img, order, nc, ptype, header = _part_image(path, parts[int(part)], label, dtype=dtype, which=channels)
    return ExrImage(img, order, nc, ptype, header, len(parts), f"{path}{label}")


def header_dict(part, where: str) -> dict:
    """A part's header as plain Python values.

    Parameters
    ----------
    part : OpenEXR.Part
        A part of a file opened by the binding.
    where : str
        Names the file in messages.

    Returns
    -------
    dict

    Raises
    ------
    EnvMapFileError
        A corrupt attribute (naming it).
    """
    header = {}
    for k, v in part.header.items():
        try:
            header[k] = _simple(v)
        except (UnicodeDecodeError, ValueError) as exc:  # a corrupt string attribute surfaces only here
            raise EnvMapFileError(f"{where}: corrupt OpenEXR header attribute {k!r} ({exc})") from None
    return header


def _weights_layout(h: int, w: int, header: dict, layout=None):
    """Layout used for the solid-angle weights of the radiance policy (None when not inferable)."""
    try:
        return infer_layout(h, w, layout or declared_layout(header, ""), "")
    except IBLError:
        return None


def _radiance(img: np.ndarray, chans, where: str, layout, negative: str, nonfinite: str):
    """Apply :mod:`ibl_ref.environment.radiance_policy` to the colour channels of ``img`` in place → report.

    An alpha channel is checked for NaN/Inf under the same ``nonfinite`` policy, never clamped.
    """

    h, w = img.shape[:2]
    nc = 3 if len(chans) >= 3 else 1
    colour = img[..., :nc]
    weights = pixel_solid_angles(h, w, layout)
    fixed, rep = apply_policy(colour, f"{where}: radiance", negative=negative, nonfinite=nonfinite,
                              weights=weights, inplace=True)
    if fixed is not colour:
        img[..., :nc] = fixed
    if len(chans) > nc:
        alpha = img[..., nc:]
        if not np.all(np.isfinite(alpha)):
            bad = int((~np.isfinite(alpha)).sum())
            if nonfinite == "error":
                raise RadianceError(f"{where}: {bad} NaN/Inf value(s) in the alpha channel; pass --nonfinite zero "
                                    "(Python: nonfinite='zero') to replace them by 0")
            alpha[~np.isfinite(alpha)] = 0
            rep.action.append(f"replaced {bad} NaN/Inf alpha value(s) by 0")
    return rep


def infer_layout(h: int, w: int, declared=None, where: str = "image") -> str:
    """Layout of an ``h × w`` image: the declared one (checked) or inferred from the aspect ratio.

    ``6N × N`` (height × width) → ``"cube"`` strip, ``H × 2H`` → ``"latlong"``, ``3N × 4N`` → ``"hcross"``,
    ``4N × 3N`` → ``"vcross"``.

    Parameters
    ----------
    h, w : int
        Height and width of the image.
    declared : {"cube", "latlong", "hcross", "vcross"}, optional
        A layout to check instead of inferring one.
    where : str, optional
        Names the image in messages.

    Returns
    -------
    str

    Raises
    ------
    LayoutError
        No layout has this aspect ratio, or the declared one does not.

    Examples
    --------
    >>> from ibl_ref.environment.exr_io import infer_layout
    >>> infer_layout(48, 8), infer_layout(256, 512), infer_layout(96, 128)
    ('cube', 'latlong', 'hcross')
    """
    need = {"cube": h == 6 * w, "latlong": w == 2 * h, "hcross": 4 * h == 3 * w and w % 4 == 0,
            "vcross": 3 * h == 4 * w and w % 3 == 0}
    if declared is not None:
        if declared not in need:
            raise LayoutError(f"{where}: unknown layout {declared!r}; choose one of {tuple(need)}")
        if not need[declared]:
            expect = {"cube": "N wide x 6N high", "latlong": "2H wide x H high", "hcross": "4N wide x 3N high",
                      "vcross": "3N wide x 4N high"}[declared]
            raise LayoutError(f"{where}: layout {declared} needs an image {expect}, got {w} wide x {h} high")
        return declared
    for name, ok in need.items():
        if ok:
            return name
    raise LayoutError(
        f"{where}: cannot infer the environment-map layout of a {w} wide x {h} high image without an "
        f"'envmap' attribute (expected N x 6N cube strip, 2H x H lat-long, 4N x 3N or 3N x 4N cross)"
    )


def declared_layout(header: dict, where: str = "image"):
    """Layout named by a header's ``envmap`` attribute.

    Parameters
    ----------
    header : dict
        A file's header (:func:`header_dict`).
    where : str, optional
        Names the file in messages.

    Returns
    -------
    {"cube", "latlong"} or None
        None when the header has no ``envmap`` attribute.

    Raises
    ------
    LayoutError
        An ``envmap`` value other than CUBE or LATLONG.
    """
    env = header.get("envmap")
    if env is None:
        return None
    if env in ("ENVMAP_CUBE", "CUBE"):
        return "cube"
    if env in ("ENVMAP_LATLONG", "LATLONG"):
        return "latlong"
    raise LayoutError(f"{where}: unsupported envmap attribute {env!r}")


def read_image(path, part: int = 0, negative: str = "auto", nonfinite: str = "error", return_report: bool = False,
               dtype=np.float64):
    """Read one part of an OpenEXR file as an image, its radiance checked; the layout is not interpreted.

    Parameters
    ----------
    path : str, bytes or os.PathLike
    part : int, optional
        Part index (0 = first).
    negative, nonfinite : str, optional
        Radiance policy (:mod:`ibl_ref.environment.radiance_policy`; solid-angle weights of the layout from the
        ``envmap`` attribute or the aspect ratio, uniform if neither applies); a repair warns once
        (:class:`~ibl_ref.errors.RadianceWarning`).
    return_report : bool, optional
        Also return the :class:`~ibl_ref.environment.radiance_policy.RadianceReport`.
    dtype : numpy dtype, optional
        float64 (default) or float32 (half the memory for big probes).

    Returns
    -------
    image : ndarray, shape (H, W, C)
    channels : tuple of str
        ``("R", "G", "B")``, ``("R", "G", "B", "A")`` or ``("Y",)``.
    pixel_type : str
        ``"half"``, ``"float"``, ``"uint"`` or ``"mixed"``.
    header : dict
    report : RadianceReport
        Only with ``return_report=True``.

    Raises
    ------
    EnvMapFileError, LayoutError, RadianceError
        As :func:`read_exr`; radiance refused by the policy.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from ibl_ref.environment.exr_io import read_image, write_envmap
    >>> folder = tempfile.TemporaryDirectory()
    >>> path = os.path.join(folder.name, "strip.exr")
    >>> report = write_envmap(path, np.full((6, 4, 4, 1), 3.0))
    >>> image, channels, pixel_type, header = read_image(path)
    >>> image.shape, channels, pixel_type, header["envmap"]
    ((24, 4, 1), ('Y',), 'float', 'ENVMAP_CUBE')
    >>> folder.cleanup()
    """

    ex = read_exr(path, part, dtype)
    img = ex.pixels
    rep = _radiance(img, ex.channels, ex.where, _weights_layout(img.shape[0], img.shape[1], ex.header), negative,
                    nonfinite)
    warn_repaired(rep)
    return (img, ex.channels, ex.pixel_type, ex.header, rep) if return_report else (img, ex.channels, ex.pixel_type,
                                                                                     ex.header)


def _as_map(img, lay: str, header: dict, convention, where: str):
    """(data, layout): a cube strip reshaped (and re-oriented to OpenEXR), a cross cut into a cube, lat-long as is."""

    h, w = img.shape[:2]
    if lay == "cube":
        data = img.reshape(6, w, w, img.shape[2])
        conv = cube_convention(header, convention, where)
        return (envmap.convert_convention(data, conv, "openexr") if conv != "openexr" else data), "cube"
    if lay in ("hcross", "vcross"):
        return resample.cross_to_cube(img, lay), "cube"
    return img, "latlong"


def _read_map(path, layout, convention, negative, nonfinite, dtype, part=0, crosses=True) -> EnvMap:
    """:func:`read_map` without the warning; ``crosses=False``: OpenEXR cube strips and lat-long maps only."""
    path = as_path(path, "environment map")
    where = str(path)
    if layout is not None and layout not in ("cube", "latlong", "hcross", "vcross"):
        raise LayoutError(f"{where}: unknown layout {layout!r}; choose one of "
                          f"{('cube', 'latlong', 'hcross', 'vcross') if crosses else _LAYOUTS}")
    if crosses and path.suffix.lower() in _HDR_SUFFIXES:
        from .hdr_io import read_hdr

        img, rep = read_hdr(path, negative=negative, nonfinite=nonfinite, return_report=True, dtype=dtype)
        header, chans, ptype, fmt = {}, ("R", "G", "B"), "rgbe", "Radiance RGBE"
        lay = infer_layout(img.shape[0], img.shape[1], layout, where)
    else:
        ex = read_exr(path, part, dtype)
        img, chans, ptype, header, fmt, where = ex.pixels, ex.channels, ex.pixel_type, ex.header, "OpenEXR", ex.where
        lay = infer_layout(img.shape[0], img.shape[1], layout or declared_layout(header, where), where)
        rep = _radiance(img, chans, where, lay, negative, nonfinite)
    if not crosses and lay not in _LAYOUTS:
        raise LayoutError(f"{where}: {img.shape[1]} x {img.shape[0]} looks like a {lay} image; use load_cube() or "
                          "read_map() for cross layouts")
    data, out_layout = _as_map(img, lay, header, convention, where)
    return EnvMap(data=data, layout=out_layout, path=path, channels=chans, header=header, pixel_type=ptype,
                  radiance=rep, file_format=fmt, source_layout=lay)


def read_map(path, layout: str | None = None, convention: str | None = None, negative: str = "auto",
             nonfinite: str = "error", dtype=np.float64) -> EnvMap:
    """Read any supported environment-map file without resampling.

    OpenEXR (first part) or Radiance ``.hdr`` / ``.pic``; a cube strip or a cross becomes a ``(6, N, N, C)``
    cube in OpenEXR orientation (``EnvMap.source_layout`` says which it was), a lat-long map stays ``(H, 2H, C)``.

    Parameters
    ----------
    path : str, bytes or os.PathLike
    layout : {"cube", "latlong", "hcross", "vcross"}, optional
        Overrides the ``envmap`` attribute / aspect ratio.
    convention, negative, nonfinite
        As :func:`read_envmap`; a repair of the radiance warns once (:class:`~ibl_ref.errors.RadianceWarning`).
    dtype : numpy dtype, optional
        float64 (default) or float32.

    Returns
    -------
    EnvMap

    Raises
    ------
    EnvMapFileError, LayoutError, RadianceError
        As :func:`read_envmap` and :func:`ibl_ref.environment.hdr_io.read_hdr`.
    """

    m = _read_map(path, layout, convention, negative, nonfinite, dtype)
    warn_repaired(m.radiance)
    return m


def read_envmap(path, layout: str | None = None, convention: str | None = None, part: int = 0,
                negative: str = "auto", nonfinite: str = "error") -> EnvMap:
    """Read an OpenEXR environment map (cube strip or lat-long; crosses: :func:`read_map`).

    Parameters
    ----------
    path : str, bytes or os.PathLike
    layout : {"cube", "latlong"}, optional
        Override the file's ``envmap`` attribute.  Without attribute or override, a ``N × 6N`` strip is a
        cube and a ``2H × H`` image a lat-long map; anything else is a :class:`LayoutError`.
    convention : {"openexr", "opengl"}, optional
        Face orientation of a cube strip in the file (default: the ``iblref_convention`` attribute, else
        ``"openexr"``).  The returned array is always in OpenEXR orientation.
    part : int
        Part index of a multi-part file (0 = first; use :func:`read_pyramid` for pyramids).
    negative, nonfinite : str
        Radiance policy (:mod:`ibl_ref.environment.radiance_policy`): default clamp negligible negatives (reported in
        ``EnvMap.radiance`` and warned once, :class:`~ibl_ref.errors.RadianceWarning`), refuse NaN/Inf.

    Returns
    -------
    EnvMap

    Raises
    ------
    EnvMapFileError
        A missing, corrupt or truncated file; a part that does not exist.
    LayoutError
        An aspect ratio that is no layout (crosses: :func:`read_map`), missing colour channels.
    RadianceError
        Radiance refused by the policy.

    Examples
    --------
    A lat-long file keeps its layout; the map's integral over the sphere is Σ L·Ω:

    >>> import os, tempfile
    >>> import numpy as np
    >>> from ibl_ref.environment.envmap import latlong_solid_angles
    >>> from ibl_ref.environment.exr_io import read_envmap, write_envmap
    >>> folder = tempfile.TemporaryDirectory()
    >>> path = os.path.join(folder.name, "sky.exr")
    >>> report = write_envmap(path, np.full((8, 16, 3), 0.5), layout="latlong")
    >>> m = read_envmap(path)
    >>> m.layout, m.data.shape, m.channels
    ('latlong', (8, 16, 3), ('R', 'G', 'B'))
    >>> float((m.data[..., 0] * latlong_solid_angles(8, 16)).sum() / np.pi)  # 4π · 0.5
    2.0
    >>> folder.cleanup()
    """

    path = as_path(path, "OpenEXR file")
    if layout is not None and layout not in _LAYOUTS:
        raise LayoutError(f"{path}: unknown layout {layout!r}; choose one of {_LAYOUTS}")
    m = _read_map(path, layout, convention, negative, nonfinite, np.float64, part=part, crosses=False)
    warn_repaired(m.radiance)
    return m


def read_pyramid(path) -> list:
    """Read a multi-part pyramid written by :func:`write_pyramid`.

    Parameters
    ----------
    path : str, bytes or os.PathLike

    Returns
    -------
    list of ndarray, float64, each (6, n, n, C)
        Level 0 first; radiance under the default policy (negligible negatives clamped, NaN/Inf refused).

    Raises
    ------
    EnvMapFileError, LayoutError, RadianceError
        As :func:`read_envmap`, per part; a part that is not a cube strip.
    """
    path = as_path(path, "OpenEXR file")
    _, parts = _open(path)
    levels = []
    for i, p in enumerate(parts):
        img, chans, _, _, header = _part_image(path, p, f" (part {i})")
        h, w = img.shape[:2]
        infer_layout(h, w, "cube", f"{path} (part {i})")
        _radiance(img, chans, f"{path} (part {i})", "cube", "auto", "error")
        levels.append(img.reshape(6, w, w, img.shape[2]))
    return levels


# ----------------------------------------------------------------------------------------------
# anything → cube
# ----------------------------------------------------------------------------------------------
def _rgb(data: np.ndarray) -> np.ndarray:
    c = data.shape[-1]
    if c == 1:
        return np.repeat(data, 3, axis=-1)
    return data[..., :3]


def _load_cube(path, size, layout, convention, negative, nonfinite):
    """``(cube (6, N, N, 3) float64, RadianceReport)``: the work of :func:`load_cube` (the cube is the caller's)."""

    path = as_path(path, "environment map")
    if size is not None:
        from ..limits import check_cube_size

        size = check_cube_size(size, "size")
    # float32 holds every half/float pixel exactly and halves the memory of big probes
    m = _read_map(path, layout, convention, negative, nonfinite, np.float32)
    warn_repaired(m.radiance, stacklevel=4)
    if m.layout == "cube":
        cube = _rgb(m.data)
        if size is not None and int(size) != cube.shape[1]:  # radiance checked by the read: not again
            cube = resample.cube_to_cube(adopt(cube, m.radiance), int(size))
        cube = np.ascontiguousarray(cube, dtype=np.float64)
    else:
        n = int(size) if size is not None else max(1, m.data.shape[0] // 2)
        cube = resample.latlong_to_cube(_rgb(m.data), n)
    return cube, m.radiance


def load_cube(path, size: int | None = None, layout: str | None = None, convention: str | None = None,
              negative: str = "auto", nonfinite: str = "error", return_report: bool = False):
    """Load any supported environment-map file as a ``(6, N, N, 3)`` float64 cube map.

    Supported: OpenEXR CUBE strips and LATLONG maps (attribute or aspect ratio), Radiance ``.hdr`` /
    ``.pic`` (lat-long), horizontal (4N × 3N) and vertical (3N × 4N) crosses in either file format
    (layout in :mod:`ibl_ref.environment.resample`).  Y files are replicated to RGB, alpha is dropped.
    EXR pixels are read as float32 (exact for half and float files; half the memory of a big probe) and
    the result is float64.  :func:`load_environment` reads the same cube as a validated
    :class:`~ibl_ref.environment.validated.Environment`.

    Parameters
    ----------
    path : str, bytes or os.PathLike
        The file (names need not be UTF-8).
    size : int, optional
        Face size of the result.  Default: the file's face size (cube, cross) or ``H // 2`` for an
        ``H × 2H`` lat-long map (same texel count around the equator).  Resampling conserves ∫L dω
        (:mod:`ibl_ref.environment.resample`).
    layout : {"cube", "latlong", "hcross", "vcross"}, optional
        Override the layout (otherwise from the ``envmap`` attribute or the aspect ratio).
    convention : {"openexr", "opengl"}, optional
        Face orientation of a cube strip in the file (see :func:`read_envmap`).
    negative, nonfinite : str, optional
        Radiance policy (:mod:`ibl_ref.environment.radiance_policy`; default: clamp the negligible negatives of lossy
        compression, refuse NaN/Inf).  A repair is reported in the returned report and warned once
        (:class:`~ibl_ref.errors.RadianceWarning`, the line the CLI prints).
    return_report : bool, optional
        Return ``(cube, RadianceReport)`` instead of the cube.

    Returns
    -------
    cube : ndarray, float64, shape (6, N, N, 3)
        OpenEXR face order and orientation (:mod:`ibl_ref.environment.envmap`).
    report : RadianceReport
        Only with ``return_report=True``.

    Raises
    ------
    EnvMapFileError
        The file is missing, not an image or truncated.
    LayoutError
        An aspect ratio that is no layout, a missing colour channel, an unknown layout or convention.
    RadianceError
        NaN/Inf values, or negatives carrying more than 1e-4 of ∫|L| dω (under the default policy).
    SizeError
        A ``size`` that is not a positive integer or does not fit in memory.

    Examples
    --------
    Write a constant cube map and read it back, also at a smaller face size (block averages keep the constant):

    >>> import os, tempfile
    >>> import numpy as np
    >>> from ibl_ref.environment.exr_io import load_cube, write_envmap
    >>> folder = tempfile.TemporaryDirectory()
    >>> path = os.path.join(folder.name, "grey.exr")
    >>> report = write_envmap(path, np.full((6, 8, 8, 3), 0.25))
    >>> cube = load_cube(path)
    >>> cube.shape, cube.dtype, float(cube.min()), float(cube.max())
    ((6, 8, 8, 3), dtype('float64'), 0.25, 0.25)
    >>> cube, report = load_cube(path, size=4, return_report=True)
    >>> cube.shape, float(cube.max()), report.clean
    ((6, 4, 4, 3), 0.25, True)
    >>> folder.cleanup()
    """
    cube, rep = _load_cube(path, size, layout, convention, negative, nonfinite)
    return (cube, rep) if return_report else cube


def load_environment(path, size: int | None = None, layout: str | None = None, convention: str | None = None,
                     negative: str = "auto", nonfinite: str = "error"):
    """Load an environment-map file as a validated :class:`~ibl_ref.environment.validated.Environment`.

    The cube of :func:`load_cube` (same files, same parameters), checked once by the read: the stages that take
    an environment (median cut, PEMs, filter pyramids, …) trust it and do not check it again.

    Parameters
    ----------
    path, size, layout, convention, negative, nonfinite
        As :func:`load_cube`.

    Returns
    -------
    Environment
        Read-only float64 ``(6, N, N, 3)`` radiance (``.data``) with the report of the read (``.radiance``).

    Raises
    ------
    EnvMapFileError, LayoutError, RadianceError, SizeError
        As :func:`load_cube`.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from ibl_ref.environment.exr_io import load_environment, write_envmap
    >>> folder = tempfile.TemporaryDirectory()
    >>> path = os.path.join(folder.name, "grey.exr")
    >>> report = write_envmap(path, np.full((6, 8, 8, 3), 0.25))
    >>> env = load_environment(path)
    >>> env.face_size, env.channels, env.data.flags.writeable
    (8, 3, False)
    >>> folder.cleanup()
    """
    return adopt(*_load_cube(path, size, layout, convention, negative, nonfinite))
