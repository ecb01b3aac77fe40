"""Radiance RGBE (``.hdr`` / ``.pic``) image files: reading and writing.

Format (Greg Ward, Radiance file formats; "Real Pixels", Graphics Gems II)
-------------------------------------------------------------------------
* **Header**: first line ``#?RADIANCE`` (``#?RGBE`` is accepted too), then ``KEY=value`` / comment lines
  up to an empty line.  ``FORMAT=32-bit_rle_rgbe`` is required if present (``32-bit_rle_xyze`` is
  rejected with a clear error).  ``EXPOSURE=e`` lines are cumulative multipliers that *have been applied*
  to the pixels: the original radiance is the stored value divided by the product of all EXPOSURE
  values.  :func:`read_hdr` does **not** apply them by default (like most image loaders), pass
  ``apply_exposure=True`` to divide by the product; :func:`read_hdr_header` returns it.
* **Resolution line**: ``-Y H +X W`` is the standard orientation (scanlines top to bottom, pixels left to
  right).  All eight orientations (``±Y H ±X W`` and ``±X W ±Y H``) are decoded and returned as a
  standard top-to-bottom, left-to-right image.
* **Pixels**: 4 bytes (R, G, B mantissas, shared exponent E).  Value = ``(m + ½)·2^(E−136)`` for E > 0 and 0
  for E = 0 (Radiance's ``colr_color``).  Encoding (:func:`write_hdr`, Radiance's ``setcolr``): with
  ``M = max(R, G, B) = f·2^e`` (f ∈ [½, 1)), ``m = ⌊c·256/2^e⌋`` and E = e + 128; M < 1e-32 → (0, 0, 0, 0).
  Quantisation error of every channel ≤ ½·2^(e−8) = 2^(e−9) ≤ M/256 (since M ≥ 2^(e−1)).
* **Scanline encodings**: flat (4 bytes per pixel); *new-style RLE* (widths 8..32767: bytes 2, 2, W>>8,
  W&255, then the four components one after the other, each as runs — a count byte c > 128 means the
  next byte repeated c−128 times, otherwise c literal bytes follow); *old-style RLE* (a pixel (1, 1, 1, n)
  repeats the previous pixel n·256^s times, s counting consecutive repeat pixels).  All three are
  decoded; a file of flat scanlines is decoded in one vectorised step, RLE per scanline.

Errors name the file: missing, not a Radiance file, unsupported format/orientation, corrupt or
truncated pixel data (:class:`~ibl_ref.errors.EnvMapFileError`).  Writes are atomic.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..atomic import atomic_write
from ..errors import EnvMapFileError, LayoutError, as_path, check_input_file
from .radiance_policy import check_radiance
from ..limits import SizeError
from ..limits import check_allocation
from .radiance_policy import apply_policy
from .radiance_policy import check_format_range
from .radiance_policy import pixel_solid_angles

__all__ = ["read_hdr", "read_hdr_header", "write_hdr", "rgbe_to_float", "float_to_rgbe"]

#: smallest pixel maximum RGBE keeps (Radiance's ``setcolr`` writes (0, 0, 0, 0) below it)
RGBE_MIN = 1e-32

_RES_RE = re.compile(rb"^([-+])([XY]) (\d+) ([-+])([XY]) (\d+)$")


def rgbe_to_float(rgbe: np.ndarray) -> np.ndarray:
    """Decode RGBE pixels: ``(m + ½)·2^(E−136)``, 0 where E = 0 (Radiance's ``colr_color``).

    Parameters
    ----------
    rgbe : array_like, uint8, shape (..., 4)

    Returns
    -------
    ndarray, float64, shape (..., 3)

    Examples
    --------
    >>> from ibl_ref.environment.hdr_io import float_to_rgbe, rgbe_to_float
    >>> rgbe = float_to_rgbe([1.0, 0.5, 0.0])
    >>> rgbe.tolist()
    [128, 64, 0, 129]
    >>> rgbe_to_float(rgbe)  # within half a mantissa step (1/256) of the input
    array([1.0039, 0.5039, 0.0039])
    """
    rgbe = np.asarray(rgbe, dtype=np.uint8)
    e = rgbe[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    return (rgbe[..., :3].astype(np.float64) + 0.5) * scale[..., None]


def float_to_rgbe(rgb: np.ndarray) -> np.ndarray:
    """Encode non-negative floats as RGBE pixels (Radiance's ``setcolr``; module docstring).

    Parameters
    ----------
    rgb : array_like, shape (..., 3)
        Finite, non-negative; pixels whose largest channel is below :data:`RGBE_MIN` become (0, 0, 0, 0).

    Returns
    -------
    ndarray, uint8, shape (..., 4)

    Raises
    ------
    EnvMapFileError
        A value too large for RGBE (≈ 1.7e38).
    """
    rgb = np.asarray(rgb, dtype=np.float64)
    m = rgb.max(axis=-1)
    frac, ex = np.frexp(m)  # m = frac * 2**ex, frac in [0.5, 1)
    ok = m > RGBE_MIN
    if np.any(ex[ok] + 128 > 255):
        raise EnvMapFileError(f"radiance {m.max():g} is too large for RGBE (max ≈ 1.7e38)")
    scale = np.where(ok, np.ldexp(256.0, -ex), 0.0)  # 256 / 2**ex
    mant = np.floor(rgb * scale[..., None])
    mant = np.clip(mant, 0, 255).astype(np.uint8)
    out = np.zeros(rgb.shape[:-1] + (4,), dtype=np.uint8)
    out[..., :3] = np.where(ok[..., None], mant, 0)
    out[..., 3] = np.where(ok, ex + 128, 0).astype(np.uint8)
    return out


# ----------------------------------------------------------------------------------------------
# reading
# ----------------------------------------------------------------------------------------------
def _parse_header(buf: bytes, path, data_complete: bool = True) -> tuple[dict, int]:
    """Parse header + resolution line; returns (info, offset of pixel data)."""
    if not (buf.startswith(b"#?RADIANCE") or buf.startswith(b"#?RGBE")):
        raise EnvMapFileError(f"{path}: not a Radiance HDR file (missing '#?RADIANCE' signature)")
    pos = 0
    info = {"exposure": 1.0, "format": None, "lines": []}
    while True:
        end = buf.find(b"\n", pos)
        if end < 0:
            raise EnvMapFileError(f"{path}: truncated Radiance header (no end of header)")
        line = buf[pos:end].rstrip(b"\r")
        pos = end + 1
        if line == b"":
            break
        info["lines"].append(line.decode("latin-1"))
        if line.startswith(b"FORMAT="):
            info["format"] = line[7:].strip().decode("latin-1")
        elif line.startswith(b"EXPOSURE="):
            try:
                info["exposure"] *= float(line[9:].strip())
            except ValueError:
                raise EnvMapFileError(f"{path}: bad EXPOSURE line {line!r}") from None
    if info["format"] not in (None, "32-bit_rle_rgbe"):
        raise EnvMapFileError(f"{path}: unsupported pixel format {info['format']!r} (only 32-bit_rle_rgbe)")
    end = buf.find(b"\n", pos)
    if end < 0:
        raise EnvMapFileError(f"{path}: truncated Radiance file (no resolution line)")
    res = buf[pos:end].rstrip(b"\r").strip()
    m = _RES_RE.match(res)
    if not m or m.group(2) == m.group(5):
        raise EnvMapFileError(f"{path}: bad resolution line {res[:40]!r} (expected e.g. '-Y 512 +X 1024')")
    s1, a1, n1, s2, a2, n2 = m.groups()
    info.update(major=(s1.decode() + a1.decode()), minor=(s2.decode() + a2.decode()), n_major=int(n1), n_minor=int(n2))
    if info["n_major"] < 1 or info["n_minor"] < 1:
        raise EnvMapFileError(f"{path}: empty image ({res.decode('latin-1')})")
    _check_claimed_size(info["n_major"], info["n_minor"], len(buf) - (end + 1) if data_complete else -1, path, res)
    return info, end + 1


def _check_claimed_size(n_major: int, n_minor: int, n_data: int, path, res: bytes) -> None:
    """Refuse a resolution line the file cannot hold or memory cannot hold, before any allocation.

    Every scanline takes at least 4 bytes in any encoding (a flat pixel, an old-style RLE pixel or the new
    RLE marker), so fewer than ``4·n_major`` bytes of pixel data mean a truncated file or a false header.
    ``n_data < 0`` means only the header was read (:func:`read_hdr_header`), then only memory is checked.
    """

    claim = res.decode("latin-1")
    if 0 <= n_data < 4 * n_major:
        raise EnvMapFileError(f"{path}: header claims {claim} but the file holds only {n_data} byte(s) of "
                              f"pixel data (truncated or corrupt)")
    try:  # uint8 RGBE + float64 RGB per pixel
        check_allocation(n_major * n_minor * (4 + 24), f"the {claim} image", str(path))
    except SizeError as exc:
        raise EnvMapFileError(str(exc)) from None


def read_hdr_header(path) -> dict:
    """The header of a Radiance file.

    Parameters
    ----------
    path : str, bytes or os.PathLike

    Returns
    -------
    dict
        ``format``, ``exposure`` (the product of the EXPOSURE lines), ``lines`` (the header lines), the orientation
        and the size.

    Raises
    ------
    EnvMapFileError
        A missing file, not a Radiance file, an unsupported format or orientation.
    """
    path = as_path(path, "Radiance file")
    with _open(path) as fh:
        buf = fh.read(65536)
        complete = not fh.read(1)
    info, _ = _parse_header(buf, path, data_complete=complete)
    return info


def _open(path: Path):
    return open(check_input_file(path, "a Radiance .hdr file"), "rb")


def _decode_new_rle(buf: memoryview, pos: int, width: int, path, row: int):
    """Decode one new-style RLE scanline starting after its 4-byte marker; returns ((width, 4), pos)."""
    out = np.empty((4, width), dtype=np.uint8)
    nbuf = len(buf)
    for c in range(4):
        i = 0
        comp = out[c]
        while i < width:
            if pos >= nbuf:
                raise EnvMapFileError(f"{path}: truncated RLE data in scanline {row}")
            count = buf[pos]
            pos += 1
            if count > 128:
                count -= 128
                if i + count > width or pos >= nbuf:
                    raise EnvMapFileError(f"{path}: corrupt RLE run in scanline {row} (overruns the scanline)")
                comp[i : i + count] = buf[pos]
                pos += 1
            else:
                if count == 0 or i + count > width:
                    raise EnvMapFileError(f"{path}: corrupt RLE literal in scanline {row} (count {count})")
                if pos + count > nbuf:
                    raise EnvMapFileError(f"{path}: truncated RLE data in scanline {row}")
                comp[i : i + count] = np.frombuffer(buf[pos : pos + count], dtype=np.uint8)
                pos += count
            i += count
    return out.T, pos


def _decode_old(buf: memoryview, pos: int, width: int, path, row: int):
    """Flat or old-style RLE scanline; returns ((width, 4), pos)."""
    out = np.empty((width, 4), dtype=np.uint8)
    i, shift = 0, 0
    nbuf = len(buf)
    while i < width:
        if pos + 4 > nbuf:
            raise EnvMapFileError(f"{path}: truncated pixel data in scanline {row}")
        px = buf[pos : pos + 4]
        pos += 4
        if px[0] == 1 and px[1] == 1 and px[2] == 1:
            if i == 0:
                raise EnvMapFileError(f"{path}: corrupt old-style RLE (repeat at start of scanline {row})")
            count = px[3] << shift
            if i + count > width:
                raise EnvMapFileError(f"{path}: corrupt old-style RLE run in scanline {row}")
            out[i : i + count] = out[i - 1]
            i += count
            shift += 8
        else:
            out[i] = np.frombuffer(px, dtype=np.uint8)
            i += 1
            shift = 0
    return out, pos


def _decode_pixels(buf: bytes, pos: int, h: int, w: int, path) -> np.ndarray:
    """Decode h scanlines of w pixels to (h, w, 4) uint8."""
    mv = memoryview(buf)
    # fast path: all flat (no RLE marker possible or file size says flat)
    if len(buf) - pos == 4 * h * w and not (8 <= w <= 0x7FFF and buf[pos] == 2 and buf[pos + 1] == 2):
        flat = np.frombuffer(buf, dtype=np.uint8, count=4 * h * w, offset=pos).reshape(h, w, 4)
        if not np.any((flat[..., 0] == 1) & (flat[..., 1] == 1) & (flat[..., 2] == 1)):
            return flat.copy()
    out = np.empty((h, w, 4), dtype=np.uint8)
    for row in range(h):
        if 8 <= w <= 0x7FFF and pos + 4 <= len(buf) and buf[pos] == 2 and buf[pos + 1] == 2 and not (buf[pos + 2] & 0x80):
            sw = (buf[pos + 2] << 8) | buf[pos + 3]
            if sw != w:
                raise EnvMapFileError(f"{path}: RLE scanline {row} declares width {sw}, image width is {w}")
            out[row], pos = _decode_new_rle(mv, pos + 4, w, path, row)
        else:
            out[row], pos = _decode_old(mv, pos, w, path, row)
    return out


def read_hdr(path, apply_exposure: bool = False, negative: str = "auto", nonfinite: str = "error",
             return_report: bool = False, dtype=np.float64):
    """Read a Radiance RGBE file as an ``(H, W, 3)`` float64 image (top row first, left column first).

    Parameters
    ----------
    path : str, bytes or os.PathLike
    apply_exposure : bool
        Divide by the product of the header's EXPOSURE values (recovering Radiance's original
        radiance).  Off by default, like most HDR loaders (see module docstring).
    negative, nonfinite : str
        Radiance policy (:mod:`ibl_ref.environment.radiance_policy`).  RGBE cannot store negative, NaN or infinite
        values, so the check always passes; the parameters exist so that every reader takes the same ones.
    return_report : bool
        Return ``(image, RadianceReport)``.
    dtype : float64 (default) or float32
        Of the result; RGBE values (8-bit mantissas) are exact in float32.  Decoding runs in row blocks,
        so a big probe needs the file, its (H, W, 4) bytes and the result only.

    Returns
    -------
    image : ndarray, shape (H, W, 3)
    report : RadianceReport
        Only with ``return_report=True``.

    Raises
    ------
    EnvMapFileError
        A missing, corrupt or truncated file; an unsupported format (XYZE) or orientation.

    Examples
    --------
    A lat-long sky written and read back: RGBE keeps 8 mantissa bits, so every value comes back within 2⁻⁸ of its
    size (module docstring):

    >>> import os, tempfile
    >>> import numpy as np
    >>> from ibl_ref.environment.hdr_io import read_hdr, write_hdr
    >>> folder = tempfile.TemporaryDirectory()
    >>> path = os.path.join(folder.name, "sky.hdr")
    >>> sky = np.linspace(0.1, 2.0, 16 * 32 * 3).reshape(16, 32, 3)
    >>> path = write_hdr(path, sky)
    >>> img = read_hdr(path)
    >>> img.shape, img.dtype
    ((16, 32, 3), dtype('float64'))
    >>> bool(np.all(np.abs(img - sky) <= sky.max(axis=-1, keepdims=True) / 256))
    True
    >>> folder.cleanup()
    """
    path = as_path(path, "Radiance file")
    with _open(path) as fh:
        buf = fh.read()
    info, pos = _parse_header(buf, path)
    n_major, n_minor = info["n_major"], info["n_minor"]
    raw = _decode_pixels(buf, pos, n_major, n_minor, path)  # (scanline, pixel, 4)
    del buf
    img = np.empty(raw.shape[:2] + (3,), dtype=dtype)
    step = max(1, (1 << 20) // max(1, raw.shape[1]))
    for r0 in range(0, raw.shape[0], step):
        img[r0 : r0 + step] = rgbe_to_float(raw[r0 : r0 + step])
    del raw
    # orient to the standard -Y H +X W
    if info["major"][1] == "Y":
        if info["major"][0] == "+":
            img = img[::-1]
        if info["minor"][0] == "-":
            img = img[:, ::-1]
    else:  # scanlines are columns
        img = np.swapaxes(img, 0, 1)  # rows = minor (Y), cols = major (X)
        if info["minor"][0] == "+":
            img = img[::-1]
        if info["major"][0] == "-":
            img = img[:, ::-1]
    if apply_exposure:
        if not info["exposure"] > 0:
            raise EnvMapFileError(f"{path}: EXPOSURE product {info['exposure']} is not positive")
        img /= info["exposure"]
    img = np.ascontiguousarray(img)

    h, w = img.shape[:2]
    img, rep = apply_policy(img, f"{path}: radiance", negative, nonfinite,
                            weights=pixel_solid_angles(h, w, "latlong" if w == 2 * h else None), inplace=True)
    return (img, rep) if return_report else img


# ----------------------------------------------------------------------------------------------
# writing
# ----------------------------------------------------------------------------------------------
def _rle_component(comp: np.ndarray) -> bytes:
    """New-style RLE of one component of one scanline: runs ≥ 4 as runs (≤ 127), rest as literals (≤ 128)."""
    w = comp.size
    # run boundaries
    change = np.flatnonzero(np.diff(comp.astype(np.int16)) != 0) + 1
    starts = np.concatenate([[0], change])
    lengths = np.diff(np.concatenate([starts, [w]]))
    out = bytearray()
    lit_start = None

    def flush_literal(a, b):
        while a < b:
            c = min(128, b - a)
            out.append(c)
            out.extend(comp[a : a + c].tobytes())
            a += c

    for s, ln in zip(starts.tolist(), lengths.tolist()):
        if ln >= 4:
            if lit_start is not None:
                flush_literal(lit_start, s)
                lit_start = None
            val = int(comp[s])
            while ln > 0:
                c = min(127, ln)
                if c < 4 and lit_start is None:  # short remainder: emit as literal
                    flush_literal(s, s + c)
                else:
                    out.append(128 + c)
                    out.append(val)
                s += c
                ln -= c
        elif lit_start is None:
            lit_start = s
    if lit_start is not None:
        flush_literal(lit_start, w)
    return bytes(out)


def write_hdr(path, img, rle: bool = True, exposure: float | None = None) -> Path:
    """Write an ``(H, W, 3)`` (or (H, W) grey) non-negative image as a Radiance RGBE file (atomically).

    Parameters
    ----------
    path : str, bytes or os.PathLike
    img : array_like, shape (H, W, 3) or (H, W)
        Finite, non-negative radiance.
    rle : bool
        New-style run-length encoding (needs 8 ≤ W ≤ 32767; otherwise flat scanlines are written).
    exposure : float, optional
        Written as an ``EXPOSURE=`` header line (pixels are stored as given).

    Returns
    -------
    pathlib.Path
        The file written.

    Raises
    ------
    LayoutError
        Not an (H, W, 3) or (H, W) image.
    RadianceError
        NaN, Inf or negative values; values below :data:`RGBE_MIN` carrying more than 1e-4 of ∫L dω.
    EnvMapFileError
        Radiance above ≈ 1.7e38.

    Notes
    -----
    Values that RGBE cannot hold are never lost silently: radiance above ≈ 1.7e38 is refused, pixels below
    :data:`RGBE_MIN` (stored as 0) are measured as a share of ∫L dω and refused above 1e-4 or reported
    (:func:`ibl_ref.environment.radiance_policy.check_format_range`; lat-long solid angles for W = 2H images).
    """
    path = as_path(path, "Radiance file")
    a = np.asarray(img, dtype=np.float64)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 1 or a.shape[1] < 1:
        raise LayoutError(f"{path}: expected an (H, W, 3) image, got shape {np.shape(img)}")
    check_radiance(a, f"{path}: radiance")
    try:
        rgbe = float_to_rgbe(a)
    except EnvMapFileError as exc:
        raise EnvMapFileError(f"{path}: {exc}") from None
    # RGBE stores a pixel whose largest channel is below 1e-32 as 0: refuse or report what that loses

    h, w = a.shape[:2]
    check_format_range(a, rgbe_to_float(rgbe), str(path), "the smallest pixel value of Radiance RGBE", RGBE_MIN,
                       pixel_solid_angles(h, w, "latlong" if w == 2 * h else None), "scale the map up")
    h, w = a.shape[:2]
    head = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n"
    if exposure is not None:
        head += f"EXPOSURE={float(exposure):.9g}\n".encode()
    head += b"SOFTWARE=ibl_ref\n\n" + f"-Y {h} +X {w}\n".encode()
    body = bytearray()
    if rle and 8 <= w <= 0x7FFF:
        for row in range(h):
            body.extend(bytes([2, 2, w >> 8, w & 255]))
            for c in range(4):
                body.extend(_rle_component(rgbe[row, :, c]))
    else:
        body.extend(rgbe.tobytes())
    with atomic_write(path, "wb") as fh:
        fh.write(head + bytes(body))
    return path
