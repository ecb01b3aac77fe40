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
  (16 bit, max finite value 65504).  Files are written with lossless ZIP compression.  Channel arrays
  are handed to the binding C-contiguous: the OpenEXR 3.5 Python binding ignores strides and writes a
  non-contiguous view as its raw buffer (scrambled pixels, no error).
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

Validation
----------
Writers check the data first (:func:`ibl_ref.environment.radiance_policy.check_radiance`: NaN, ±Inf, negative radiance →
:class:`~ibl_ref.errors.RadianceError`) and never let a value overflow silently: in ``half`` a value
above 65504 raises :class:`~ibl_ref.errors.IBLError` naming the file, the count and the maximum, unless
``clamp_half=True``, which clamps to 65504, warns and reports the clamping in the returned
:class:`WriteReport`.  Every write is atomic (:func:`ibl_ref.atomic.atomic_path`, the temporary file keeps
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
from ..errors import EnvMapFileError, IBLError, LayoutError, RadianceError, check_input_file
from .radiance_policy import check_radiance

__all__ = [
    "HALF_MAX",
    "FLOAT_MAX",
    "EnvMap",
    "WriteReport",
    "write_envmap",
    "read_envmap",
    "read_image",
    "load_cube",
    "write_pyramid",
    "read_pyramid",
    "infer_layout",
]

HALF_MAX = 65504.0  #: largest finite IEEE binary16 value
FLOAT_MAX = float(np.finfo(np.float32).max)
_LAYOUTS = ("cube", "latlong")
_PIXEL_TYPES = ("float", "half")


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
    """

    data: np.ndarray
    layout: str
    path: Path
    channels: tuple
    header: dict = field(default_factory=dict)
    pixel_type: str = "float"
    radiance: object = None  #: :class:`ibl_ref.environment.radiance_policy.RadianceReport` of the read

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
    """Validate a cube/latlong array; return (strip (H, W, C) float64, C)."""
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
    check_radiance(strip, f"{where}: radiance")
    return strip.astype(np.float64, copy=False)


def _to_pixel_type(strip: np.ndarray, pixel_type: str, clamp_half: bool, where: str):
    """Cast to float32/float16 without silent overflow; returns (array, clamped_count, clamped_max)."""
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
            RuntimeWarning,
            stacklevel=3,
        )
        strip = np.minimum(strip, HALF_MAX)
    out = strip.astype(np.float16 if pixel_type == "half" else np.float32)
    if not np.all(np.isfinite(out)):  # defensive: must be impossible after the checks above
        raise IBLError(f"{where}: conversion to {pixel_type} produced non-finite values")
    return out, count, (vmax if count else 0.0)


def _channels_dict(arr: np.ndarray) -> dict:
    names = _channel_names(arr.shape[2], "")
    return {nm: np.ascontiguousarray(arr[..., i]) for i, nm in enumerate(names)}


# ----------------------------------------------------------------------------------------------
# writing
# ----------------------------------------------------------------------------------------------
def write_envmap(
    path,
    data,
    layout: str = "cube",
    pixel_type: str = "float",
    clamp_half: bool = False,
    convention: str = "openexr",
) -> WriteReport:
    """Write a cube map or lat-long map as an OpenEXR environment map (atomically).

    Parameters
    ----------
    path : str or Path
        Destination file (any name; ``.exr`` recommended).
    data : array
        ``(6, N, N[, C])`` for ``layout="cube"`` in OpenEXR face orientation, ``(H, 2H[, C])`` for
        ``"latlong"``; C ∈ {1, 3, 4} → channels Y / RGB / RGBA.
    layout : {"cube", "latlong"}
    pixel_type : {"float", "half"}
    clamp_half : bool
        With ``pixel_type="half"``: clamp values above 65504 (warns and reports them) instead of raising.
    convention : {"openexr", "opengl"}
        Face orientation *in the file* (cube only).  ``"opengl"`` files carry no ``envmap`` attribute
        (they are not OpenEXR CUBE maps) but ``iblref_convention = "opengl"``.

    Returns
    -------
    WriteReport

    Raises
    ------
    RadianceError
        NaN, Inf or negative values (checked before any file is touched).
    LayoutError
        Wrong shape or channel count.
    IBLError
        Values that do not fit the pixel type.
    """
    ox = _openexr()
    path = Path(path)
    where = str(path)
    if convention not in envmap.CONVENTIONS:
        raise IBLError(f"{where}: unknown convention {convention!r}; choose one of {envmap.CONVENTIONS}")
    strip = _prepare(data, layout, where)
    if layout == "cube" and convention != "openexr":
        n = strip.shape[1]
        strip = envmap.convert_convention(strip.reshape(6, n, n, -1), "openexr", convention).reshape(strip.shape)
    elif layout == "latlong" and convention != "openexr":
        raise IBLError(f"{where}: convention={convention!r} applies to cube maps only")
    pix, count, cmax = _to_pixel_type(strip, pixel_type, clamp_half, where)
    header = {"compression": ox.ZIP_COMPRESSION, "type": ox.scanlineimage}
    if layout == "latlong":
        header["envmap"] = ox.ENVMAP_LATLONG
    else:
        if convention == "openexr":
            header["envmap"] = ox.ENVMAP_CUBE
        header["iblref_convention"] = convention
    try:
        with atomic_path(path, suffix=".exr") as tmp:
            ox.File(header, _channels_dict(pix)).write(str(tmp))
    except IBLError:
        raise
    except (OSError, RuntimeError, ValueError, TypeError) as exc:
        raise EnvMapFileError(f"{where}: cannot write OpenEXR file: {exc}") from exc
    return WriteReport(path, layout, pixel_type, tuple(np.shape(data)), count, cmax)


def write_pyramid(path, levels, pixel_type: str = "float", clamp_half: bool = False) -> WriteReport:
    """Write a list of cube maps (a MIP pyramid, level 0 first) as a multi-part EXR.

    One part per level, named ``level{i}``, each an OpenEXR CUBE strip (see module docstring).
    All levels must have the same channel count.  Returns a :class:`WriteReport` (``shape`` is the
    list of level shapes; clamping counts are summed over levels).
    """
    ox = _openexr()
    path = Path(path)
    where = str(path)
    levels = list(levels)
    if not levels:
        raise LayoutError(f"{where}: a pyramid needs at least one level")
    strips, total, cmax = [], 0, 0.0
    for i, lv in enumerate(levels):
        s = _prepare(lv, "cube", f"{where} level {i}")
        if strips and s.shape[2] != strips[0].shape[2]:
            raise LayoutError(f"{where}: level {i} has {s.shape[2]} channels, level 0 has {strips[0].shape[2]}")
        p, c, m = _to_pixel_type(s, pixel_type, clamp_half, f"{where} level {i}")
        strips.append(p)
        total += c
        cmax = max(cmax, m)
    n0 = strips[0].shape[1]
    display = (np.array([0, 0], dtype=np.int32), np.array([n0 - 1, 6 * n0 - 1], dtype=np.int32))
    parts = []
    for i, p in enumerate(strips):
        hdr = {
            "compression": ox.ZIP_COMPRESSION,
            "type": ox.scanlineimage,
            "envmap": ox.ENVMAP_CUBE,
            "displayWindow": display,
            "iblref_convention": "openexr",
            "iblref_level": i,
        }
        parts.append(ox.Part(hdr, _channels_dict(p), name=f"level{i}"))
    try:
        with atomic_path(path, suffix=".exr") as tmp:
            ox.File(parts).write(str(tmp))
    except IBLError:
        raise
    except (OSError, RuntimeError, ValueError, TypeError) as exc:
        raise EnvMapFileError(f"{where}: cannot write OpenEXR file: {exc}") from exc
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

    from ..limits import SizeError, check_allocation

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
            f = ox.File(str(path), separate_channels=True)
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


def _convention(header: dict, override, where: str) -> str:
    """Cube face convention: ``override`` or the file's ``iblref_convention`` attribute, validated."""
    conv = override if override is not None else header.get("iblref_convention", "openexr")
    if not isinstance(conv, str) or conv not in envmap.CONVENTIONS:
        src = "convention" if override is not None else "iblref_convention attribute"
        raise LayoutError(f"{where}: unknown cube {src} {conv!r}; expected one of {envmap.CONVENTIONS}")
    return conv


def _part_image(path: Path, part, label: str = "", dtype=np.float64):
    """Raw (H, W, C) image (``dtype``), channel names, pixel type and simple header of one part.

    No radiance check here (see :func:`_radiance`); channels are copied one by one into the result and
    the binding's copy of each is released at once (no stacked temporary: a 16K float32 RGB file peaks
    at the binding's 1.6 GB plus the result).  The part's channels are empty afterwards.
    """
    where = f"{path}{label}"
    chans = part.channels
    names = set(chans)
    if {"R", "G", "B"} <= names:
        order = ["R", "G", "B"] + (["A"] if "A" in names else [])
    elif names == {"Y"} or names == {"Y", "A"}:
        order = ["Y"]
    else:
        raise LayoutError(f"{where}: missing R/G/B channels (file has channels {sorted(names)})")
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
    return img, tuple(order), pixel_type, header_dict(part, where)


def header_dict(part, where: str) -> dict:
    """A part's header as plain Python values; a corrupt attribute is an :class:`EnvMapFileError` naming it."""
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
        return infer_layout(h, w, layout or _declared(header, ""), "")
    except IBLError:
        return None


def _radiance(img: np.ndarray, chans, where: str, layout, negative: str, nonfinite: str):
    """Apply :mod:`ibl_ref.environment.radiance_policy` to the colour channels of ``img`` in place → report.

    An alpha channel is checked for NaN/Inf under the same ``nonfinite`` policy, never clamped.
    """
    from .radiance_policy import apply_policy, pixel_solid_angles

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
    ``4N × 3N`` → ``"vcross"``; anything else raises :class:`LayoutError`.
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


def _declared(header: dict, where: str):
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
    """Read one part of an EXR file as ``(image (H, W, C), channels, pixel_type, header)``.

    Radiance is checked and repaired under ``negative`` / ``nonfinite`` (:mod:`ibl_ref.environment.radiance_policy`;
    solid-angle weights of the layout from the ``envmap`` attribute or the aspect ratio, uniform if
    neither applies); the layout is not otherwise interpreted.  ``return_report=True`` appends the
    :class:`~ibl_ref.environment.radiance_policy.RadianceReport` to the tuple.  ``dtype``: float64 (default) or
    float32 (half the memory for big probes).
    """
    img, chans, ptype, header, where = _read_raw(Path(path), part, dtype)
    rep = _radiance(img, chans, where, _weights_layout(img.shape[0], img.shape[1], header), negative, nonfinite)
    return (img, chans, ptype, header, rep) if return_report else (img, chans, ptype, header)


def _read_raw(path: Path, part: int = 0, dtype=np.float64):
    """(image, channels, pixel_type, header, name for messages) of one part, radiance unchecked."""
    _, parts = _open(path)
    if not 0 <= part < len(parts):
        raise EnvMapFileError(f"{path}: has {len(parts)} part(s), part {part} requested")
    label = f" (part {part})" if len(parts) > 1 else ""
    img, chans, ptype, header = _part_image(path, parts[part], label, dtype=dtype)
    return img, chans, ptype, header, f"{path}{label}"


def read_envmap(path, layout: str | None = None, convention: str | None = None, part: int = 0,
                negative: str = "auto", nonfinite: str = "error") -> EnvMap:
    """Read an OpenEXR environment map.

    Parameters
    ----------
    path : str or Path
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
        ``EnvMap.radiance``), refuse NaN/Inf.

    Returns
    -------
    EnvMap
    """
    path = Path(path)
    img, chans, ptype, header, rep = read_image(path, part, negative, nonfinite, return_report=True)
    h, w = img.shape[:2]
    if layout is None:
        layout = _declared(header, str(path))
    if layout is not None and layout not in _LAYOUTS:
        raise LayoutError(f"{path}: unknown layout {layout!r}; choose one of {_LAYOUTS}")
    layout = infer_layout(h, w, layout, str(path))
    if layout not in _LAYOUTS:
        raise LayoutError(f"{path}: {w} x {h} looks like a {layout} image; use load_cube() for cross layouts")
    data = img
    if layout == "cube":
        data = img.reshape(6, w, w, img.shape[2])
        conv = _convention(header, convention, str(path))
        if conv != "openexr":
            data = envmap.convert_convention(data, conv, "openexr")
    return EnvMap(data=data, layout=layout, path=path, channels=chans, header=header, pixel_type=ptype, radiance=rep)


def read_pyramid(path) -> list:
    """Read a multi-part pyramid written by :func:`write_pyramid` → list of ``(6, n, n, C)`` float64."""
    path = Path(path)
    _, parts = _open(path)
    levels = []
    for i, p in enumerate(parts):
        img, chans, _, header = _part_image(path, p, f" (part {i})")
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


def load_cube(path, size: int | None = None, layout: str | None = None, convention: str | None = None,
              negative: str = "auto", nonfinite: str = "error", return_report: bool = False):
    """Load any supported environment-map file as a ``(6, N, N, 3)`` float64 cube map.

    Supported: OpenEXR CUBE strips and LATLONG maps (attribute or aspect ratio), Radiance ``.hdr`` /
    ``.pic`` (lat-long), horizontal (4N × 3N) and vertical (3N × 4N) crosses in either file format
    (layout in :mod:`ibl_ref.environment.resample`).  Y files are replicated to RGB, alpha is dropped.

    Parameters
    ----------
    size : int, optional
        Face size of the result.  Default: the file's face size (cube, cross) or ``H // 2`` for an
        ``H × 2H`` lat-long map (same texel count around the equator).  Resampling conserves ∫L dω
        (:mod:`ibl_ref.environment.resample`).
    layout : {"cube", "latlong", "hcross", "vcross"}, optional
        Override the layout (otherwise from the ``envmap`` attribute or the aspect ratio).
    convention : {"openexr", "opengl"}, optional
        Face orientation of a cube strip in the file (see :func:`read_envmap`).
    negative, nonfinite : str
        Radiance policy (:mod:`ibl_ref.environment.radiance_policy`; default: clamp the negligible negatives of lossy
        compression and report them, refuse NaN/Inf).
    return_report : bool
        Return ``(cube, RadianceReport)`` instead of the cube.

    EXR pixels are read as float32 (exact for half and float files; half the memory of a big probe) and
    the result is float64.
    """
    path = Path(path)
    where = str(path)
    if size is not None:
        from ..limits import check_cube_size

        size = check_cube_size(size, "size")
    if path.suffix.lower() in (".hdr", ".pic", ".rgbe"):
        from .hdr_io import read_hdr

        img, rep = read_hdr(path, negative=negative, nonfinite=nonfinite, return_report=True, dtype=np.float32)
        header = {}
        lay = infer_layout(img.shape[0], img.shape[1], layout, where)
    else:
        # float32 holds every half/float pixel exactly and halves the memory of big probes
        img, chans, _, header, _ = _read_raw(path, dtype=np.float32)
        lay = infer_layout(img.shape[0], img.shape[1], layout or _declared(header, where), where)
        rep = _radiance(img, chans, where, lay, negative, nonfinite)
    cube = _load_cube_image(img, lay, header, size, convention, where)
    return (cube, rep) if return_report else cube


def _load_cube_image(img, lay, header, size, convention, where: str = "image"):
    from . import resample

    h, w = img.shape[:2]
    if lay == "cube":
        cube = img.reshape(6, w, w, img.shape[2])
        conv = _convention(header, convention, where)
        cube = envmap.convert_convention(cube, conv, "openexr") if conv != "openexr" else cube
    elif lay in ("hcross", "vcross"):
        cube = resample.cross_to_cube(img, lay)
    else:
        cube = None
    if cube is not None:
        cube = _rgb(cube)
        if size is not None and int(size) != cube.shape[1]:
            cube = resample.cube_to_cube(cube, int(size))
        return np.ascontiguousarray(cube, dtype=np.float64)
    n = int(size) if size is not None else max(1, h // 2)
    return resample.latlong_to_cube(_rgb(img), n)
