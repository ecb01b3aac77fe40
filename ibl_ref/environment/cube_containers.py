"""Cube-map MIP chains in the two containers engines load: KTX 1 and DDS.

A prefiltered chain is a list of cube maps ``levels[ℓ]`` of shape ``(6, N_ℓ, N_ℓ, 3)`` with ``N_ℓ = max(N >> ℓ, 1)``
(level 0 the largest), in the lab's cube convention (:mod:`ibl_ref.environment.envmap`: faces +X −X +Y −Y +Z −Z in
OpenEXR's orientation).  :func:`read_ktx1` / :func:`read_dds` read such a chain from a file, :func:`write_ktx1` /
:func:`write_dds` write one, :func:`read_cube_chain` reads either, chosen by the file's first bytes.

Faces
-----
Both containers hold the six faces in the order +X, −X, +Y, −Y, +Z, −Z, each in the OpenGL / Direct3D cube-map
orientation (first stored row at t = 0, first texel of a row at s = 0; the ``"opengl"`` convention of
:mod:`ibl_ref.environment.envmap`).  The readers re-orient them with
:func:`ibl_ref.environment.envmap.convert_convention` ``(…, "opengl", "openexr")``, the writers the other way: the
function :mod:`ibl_ref.prefilter.cmgen_peer` and :mod:`ibl_ref.prefilter.cmft_peer` read those tools' files with.
Checked against files the tools wrote themselves (``tests/test_cube_containers.py``): a pattern whose texels hold
their own direction, run through Filament's ``cmgen --format=ktx --no-mirror`` and through cmft
``--filter none`` (DDS and KTX, half and float texels, from a cross and from a DDS input), reads back as the lab's
cube of the pattern at level 0.

KTX 1 (Khronos, *KTX File Format Specification*, version 1.1, 2018; all fields UInt32)
----------------------------------------------------------------------------------------
* ``identifier`` (12 bytes ``«KTX 11»\\r\\n\\x1a\\n``): checked; a KTX 2 identifier gets its own error.
* ``endianness``: 0x04030201 read in the file's byte order; read as 0x01020304 the file is big-endian, and every
  header field and every texel component is swapped (2-byte halves, 4-byte floats and packed words).  Written
  little-endian.
* ``glType``, ``glTypeSize``, ``glFormat``, ``glInternalFormat``: the texel format, decided by ``glInternalFormat``
  and checked against the other two: RGBA16F (0x881A) / RGB16F (0x881B) with HALF_FLOAT (0x140B, or
  HALF_FLOAT_OES 0x8D61); RGBA32F (0x8814) / RGB32F (0x8815) with FLOAT (0x1406); R11F_G11F_B10F (0x8C3A) with
  UNSIGNED_INT_10F_11F_11F_REV (0x8C3B) — Filament's cmgen writes 0x8C3A into ``glType`` as well, accepted for this
  format; RGB9_E5 (0x8C3D) with UNSIGNED_INT_5_9_9_9_REV (0x8C3E); ``glFormat`` RGBA (0x1908) or RGB (0x1907) as
  the internal format has.  ``glType`` 0 (compressed: BCn / S3TC, RGTC, BPTC, ETC, ASTC) or any other format is
  refused naming it.  ``glTypeSize`` is read but not trusted (cmgen writes 1 for its packed 32-bit words): the
  byte swap of a big-endian file follows the format.  Written: HALF_FLOAT / FLOAT, size 2 / 4, RGBA or RGB.
* ``glBaseInternalFormat``: read and ignored (cmgen writes its sized format there); written RGBA or RGB.
* ``pixelWidth`` = ``pixelHeight`` = N > 0, ``pixelDepth`` = 0, ``numberOfArrayElements`` = 0,
  ``numberOfFaces`` = 6: anything else (a 1-D, 3-D, array, non-square or non-cube texture) is refused naming the
  field.
* ``numberOfMipmapLevels``: 0 (the file holds one level) … log2 N + 1.
* ``bytesOfKeyValueData``: the key/value pairs are skipped (cmgen stores its spherical harmonics there); none
  written.
* Per level ℓ: ``imageSize`` (a non-array cube map: the bytes of *one* face), the six faces, each followed by
  ``cubePadding`` to a multiple of 4 bytes, then ``mipPadding`` to a multiple of 4.  Rows are padded to a multiple
  of 4 bytes (the specification's GL_UNPACK_ALIGNMENT of 4), and ``imageSize`` counts that padding; only RGB16F
  faces of odd width (the 1 × 1 level) have any.  Two writers' deviations there are read too: cmft pads the rows
  but gives ``imageSize`` without the padding (and its ``cubePadding`` from that ``imageSize``), others pad neither;
  the reader takes the first of the three layouts whose sizes account for every byte of the file.
* The file must end with the last level: a shorter or a longer file is refused, naming the level.

DDS
---
Microsoft Learn, *DDS_HEADER*, *DDS_PIXELFORMAT*, *DDS_HEADER_DXT10* structures and *Programming Guide for DDS*;
all fields DWORD / UINT, little-endian.

* ``dwMagic`` ``"DDS "``: checked.
* ``DDS_HEADER``: ``dwSize`` = 124 (checked); ``dwFlags`` (written CAPS | HEIGHT | WIDTH | PITCH | PIXELFORMAT |
  MIPMAPCOUNT; read: DDSD_DEPTH refused); ``dwHeight`` = ``dwWidth`` = N; ``dwPitchOrLinearSize`` (written: the
  bytes of one row of level 0; read and ignored); ``dwDepth`` (must be 0 or 1); ``dwMipMapCount`` (0 read as 1, as
  common readers do whatever DDSD_MIPMAPCOUNT says; at most log2 N + 1); ``dwReserved1`` (zero, ignored);
  ``dwCaps`` (written TEXTURE | COMPLEX, and MIPMAP with more than one level; ignored on reading); ``dwCaps2``
  (DDSCAPS2_CUBEMAP with all six face flags POSITIVEX … NEGATIVEZ required for a legacy header; DDSCAPS2_VOLUME
  refused; written: all of them); ``dwCaps3``, ``dwCaps4``, ``dwReserved2`` (zero).
* ``DDS_PIXELFORMAT`` (``ddspf``): ``dwSize`` = 32; ``dwFlags`` DDPF_FOURCC with ``dwFourCC`` 113
  (D3DFMT_A16B16G16R16F: half RGBA) or 116 (D3DFMT_A32B32G32R32F: float RGBA), or ``"DX10"`` (the extension header
  follows; written so).  Compressed FourCCs (``DXT1`` … ``DXT5``, ``ATI1``, ``ATI2``, ``BC4U`` …) and other D3D
  formats are refused naming them; DDPF_RGB / LUMINANCE formats (8-bit LDR, ``dwRGBBitCount`` and the masks) are
  refused too, by the lab's radiance policy: integer display images are not radiance
  (:mod:`ibl_ref.environment.radiance_policy`).
* ``DDS_HEADER_DXT10``: ``dxgiFormat`` R32G32B32A32_FLOAT (2), R32G32B32_FLOAT (6), R16G16B16A16_FLOAT (10),
  R11G11B10_FLOAT (26), R9G9B9E5_SHAREDEXP (67) — BC1–BC7 (70–84, 94–99) and others refused naming them;
  ``resourceDimension`` TEXTURE2D (3); ``miscFlag`` DDS_RESOURCE_MISC_TEXTURECUBE (0x4) required; ``arraySize`` 1
  (one cube; a cube-map array is refused); ``miscFlags2`` (the alpha mode: written DDS_ALPHA_MODE_OPAQUE, 3, the
  alpha channel is 1; ignored on reading).  Written: 10 (float16) or 2 (float32).
* Data, face-major: all levels of +X, then all levels of −X, …; rows unpadded.  The file must end with the last
  level of −Z (shorter or longer: refused).

Texel formats
-------------
Half and float texels are IEEE binary16 / binary32.  The packed formats (OpenGL 4.6 core specification §8.25
"Shared exponent texture color conversion" and §2.3.4 "Unsigned 11-bit / 10-bit floating-point numbers"; DXGI's
R11G11B10_FLOAT and R9G9B9E5_SHAREDEXP are the same bits): :func:`decode_r11g11b10`, :func:`decode_rgb9e5`.  Alpha
is not radiance: it is dropped on reading and written as 1.

Radiance
--------
Readers apply the lab's radiance policy to every level (:func:`ibl_ref.environment.radiance_policy.apply_policy`,
``negative`` / ``nonfinite`` as every reader; exact texel solid angles as weights): half floats can hold negative
values, NaN and Inf.  Writers refuse NaN, Inf and negative radiance (:class:`~ibl_ref.errors.RadianceError`), refuse
a value that overflows the texel type (float16: 65504) with one line naming the level and the value, and measure
what falls below the type's normal range as the EXR writer does
(:func:`ibl_ref.environment.exr_io.to_pixel_type`).  Every write is atomic (:func:`ibl_ref.atomic.atomic_path`).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from . import envmap
from ..atomic import atomic_path
from ..errors import EnvMapFileError, IBLError, check_input_file
from ..limits import check_allocation
from .exr_io import to_pixel_type
from .radiance_policy import apply_policy, check_radiance, warn_repaired

__all__ = ["read_ktx1", "write_ktx1", "read_dds", "write_dds", "read_cube_chain", "check_storable",
           "decode_r11g11b10", "decode_rgb9e5", "WRITE_DTYPES", "CONTAINERS"]

#: texel types the writers take: IEEE half or single floats
WRITE_DTYPES = ("float16", "float32")
#: container name → file suffix (``ibl-ref prefilter --layout``)
CONTAINERS = {"ktx": ".ktx", "dds": ".dds"}

_HALF_MAX = float(np.finfo(np.float16).max)  # 65504
_FLOAT_MAX = float(np.finfo(np.float32).max)

# ----------------------------------------------------------------------------------------------
# texel formats
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Texel:
    """A texel format: ``kind`` "f2" / "f4" (IEEE components), "r11g11b10" / "rgb9e5" (one packed 32-bit word),
    ``channels`` stored, bytes per texel."""

    name: str
    kind: str
    channels: int

    @property
    def nbytes(self) -> int:
        return {"f2": 2 * self.channels, "f4": 4 * self.channels}.get(self.kind, 4)


def _mini_float(bits: np.ndarray, mantissa_bits: int) -> np.ndarray:
    """Unsigned float of 5 exponent bits (bias 15) and ``mantissa_bits`` mantissa bits: 0 / denormal
    2^-14·m/2^M / normal 2^(e-15)·(1 + m/2^M) / Inf (e = 31, m = 0) / NaN (e = 31, m ≠ 0)."""
    m = (bits & ((1 << mantissa_bits) - 1)).astype(np.float64)
    e = (bits >> mantissa_bits).astype(np.int64)
    frac = m / float(1 << mantissa_bits)
    out = np.where(e == 0, np.ldexp(frac, -14), np.ldexp(1.0 + frac, e - 15))
    out = np.where(e == 31, np.where(m == 0, np.inf, np.nan), out)
    return out


def decode_r11g11b10(words) -> np.ndarray:
    """Decode packed R11F_G11F_B10F texels (GL_UNSIGNED_INT_10F_11F_11F_REV, DXGI_FORMAT_R11G11B10_FLOAT).

    Bits 0–10 hold R and 11–21 G as unsigned 11-bit floats (5-bit exponent, bias 15, 6-bit mantissa), bits 22–31 B as
    an unsigned 10-bit float (5-bit mantissa); exponent 0 is a denormal (2^-14·m/64), 31 is Inf (m = 0) or NaN (OpenGL
    4.6 core specification §2.3.4.3–4).

    Parameters
    ----------
    words : array_like of uint32

    Returns
    -------
    ndarray, float64, shape ``words.shape + (3,)``

    Examples
    --------
    1.0 in every channel (exponent 15, mantissa 0), and the largest finite values 65024 (R, G) and 64512 (B):

    >>> from ibl_ref.environment.cube_containers import decode_r11g11b10
    >>> one = (15 << 6) | (15 << 6) << 11 | (15 << 5) << 22
    >>> decode_r11g11b10([one]).tolist()
    [[1.0, 1.0, 1.0]]
    >>> top = (30 << 6 | 63) | (30 << 6 | 63) << 11 | (30 << 5 | 31) << 22
    >>> decode_r11g11b10(top).tolist()
    [65024.0, 65024.0, 64512.0]
    """
    w = np.asarray(words, dtype=np.uint32)
    return np.stack([_mini_float(w & 0x7FF, 6), _mini_float((w >> 11) & 0x7FF, 6), _mini_float(w >> 22, 5)],
                    axis=-1)


def decode_rgb9e5(words) -> np.ndarray:
    """Decode packed RGB9_E5 texels (GL_UNSIGNED_INT_5_9_9_9_REV, DXGI_FORMAT_R9G9B9E5_SHAREDEXP).

    Bits 0–8, 9–17, 18–26 are the R, G, B mantissas m, bits 27–31 the shared exponent e: value m·2^(e − 15 − 9)
    (OpenGL 4.6 core specification §8.25, B = 15, N = 9; no denormal, Inf or NaN).  Parameters and result as
    :func:`decode_r11g11b10`.

    Examples
    --------
    Mantissas (256, 128, 0) with exponent 16 (scale 2^-8) are (1, 0.5, 0); the largest value is 511·2^7 = 65408:

    >>> from ibl_ref.environment.cube_containers import decode_rgb9e5
    >>> decode_rgb9e5([16 << 27 | 0 << 18 | 128 << 9 | 256]).tolist()
    [[1.0, 0.5, 0.0]]
    >>> float(decode_rgb9e5(31 << 27 | 511)[0])
    65408.0
    """
    w = np.asarray(words, dtype=np.uint32)
    scale = np.ldexp(1.0, (w >> 27).astype(np.int64) - 24)
    return np.stack([(w >> s & 0x1FF) * scale for s in (0, 9, 18)], axis=-1).astype(np.float64)


def _decode(raw: np.ndarray, fmt: _Texel, order: str) -> np.ndarray:
    """Texels of ``raw`` (bytes, a whole number of texels) as float64 (count, 3)."""
    if fmt.kind in ("f2", "f4"):
        a = np.frombuffer(raw, dtype=order + fmt.kind).reshape(-1, fmt.channels)
        return a[:, :3].astype(np.float64)
    words = np.frombuffer(raw, dtype=order + "u4")
    return decode_r11g11b10(words) if fmt.kind == "r11g11b10" else decode_rgb9e5(words)


# ----------------------------------------------------------------------------------------------
# shared: reading and writing chains
# ----------------------------------------------------------------------------------------------
def _level_sizes(n: int, count: int, where: str, field: str) -> list:
    """Face sizes of ``count`` levels below an n² base; a one-line error if the count exceeds log2 n + 1."""
    if count > n.bit_length():
        raise EnvMapFileError(f"{where}: {field} = {count}, more than the {n.bit_length()} levels a {n}x{n} face has")
    return [max(n >> k, 1) for k in range(count)]


def _finish(faces_gl: list, path, negative: str, nonfinite: str) -> list:
    """Levels of GL-oriented faces (6, n, n, 3) → the lab's convention, under the radiance policy."""
    out = []
    for k, gl in enumerate(faces_gl):
        cube = envmap.convert_convention(gl, "opengl", "openexr")
        cube, rep = apply_policy(cube, f"{path}: level {k}", negative=negative, nonfinite=nonfinite,
                                 weights=envmap.cube_solid_angles(cube.shape[1]), inplace=True)
        warn_repaired(rep, stacklevel=4)
        out.append(cube)
    return out


def _read_bytes(path, what: str):
    path = check_input_file(path, what)
    try:
        return path, path.read_bytes()
    except OSError as exc:
        raise EnvMapFileError(f"{path}: cannot read: {exc.strerror or exc}") from None


def _check_output_size(sizes, path) -> None:
    """The float64 levels of a file must fit in memory (checked before decoding)."""
    check_allocation(sum(6 * s * s * 3 * 8 for s in sizes), "the decoded float64 levels", str(path))


def check_storable(level, dtype: str, where: str) -> None:
    """A one-line :class:`~ibl_ref.errors.IBLError` naming ``where`` and the largest value if ``level`` (radiance)
    overflows the writers' texel type ``dtype`` (float16: 65504; the lab refuses rather than clamps, as
    :data:`ibl_ref.prefilter.karis2013.STORAGE_DTYPES` does).

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.environment.cube_containers import check_storable
    >>> check_storable(np.full((6, 1, 1, 3), 7e4), "float32", "sun")
    >>> check_storable(np.full((6, 1, 1, 3), 7e4), "float16", "sun")
    Traceback (most recent call last):
    ...
    ibl_ref.errors.IBLError: sun: value 70000 overflows float16 (max 65504); write float32 (...)
    """
    if dtype not in WRITE_DTYPES:
        raise IBLError(f"{where}: dtype must be one of {', '.join(WRITE_DTYPES)}, got {dtype!r}")
    limit = _HALF_MAX if dtype == "float16" else _FLOAT_MAX
    vmax = float(np.max(level, initial=0.0))
    if vmax > limit:
        fix = "; write float32 (dtype='float32', --dtype float32)" if dtype == "float16" else ""
        raise IBLError(f"{where}: value {vmax:.6g} overflows {dtype} (max {limit:g}){fix}")


def _chain_for_write(levels, dtype: str, where: str) -> tuple:
    """The levels as GL-oriented float16/float32 RGB arrays (6, n, n, 3), after every check of the module
    docstring ("Radiance"); and the numpy dtype."""
    check_storable(0.0, dtype, where)
    if isinstance(levels, np.ndarray):
        levels = [levels]
    try:
        levels = list(levels)
    except TypeError:
        raise IBLError(f"{where}: levels must be a list of cube maps (6, N, N, C), got {type(levels).__name__}") \
            from None
    if not levels:
        raise IBLError(f"{where}: no levels to write")
    n0 = envmap.check_cube_shape(levels[0], f"{where}: level 0")
    _level_sizes(n0, len(levels), where, "the number of levels")
    half = dtype == "float16"
    out = []
    for k, lv in enumerate(levels):
        name = f"{where}: level {k}"
        n = envmap.check_cube_shape(lv, name)
        if n != max(n0 >> k, 1):
            raise IBLError(f"{name}: {n}x{n} faces, expected {max(n0 >> k, 1)}x{max(n0 >> k, 1)} (half the level "
                           "above: a MIP chain)")
        a = np.asarray(lv)
        a = a[..., None] if a.ndim == 3 else a
        if a.shape[3] not in (1, 3):
            raise IBLError(f"{name}: {a.shape[3]} channels; write 1 (luminance) or 3 (RGB)")
        a = check_radiance(np.repeat(a, 3, axis=3) if a.shape[3] == 1 else a, f"{name}: radiance")
        a = np.asarray(a, dtype=np.float64)
        check_storable(a, dtype, name)
        gl = envmap.convert_convention(a, "openexr", "opengl")
        strip, _, _ = to_pixel_type(gl.reshape(6 * n, n, 3), "half" if half else "float", False, name,
                                    envmap.cube_solid_angles(n).reshape(6 * n, n))
        out.append(strip.reshape(6, n, n, 3))
    return out, np.dtype("<f2" if half else "<f4")


def _rgba(face: np.ndarray, channels: int, dt: np.dtype) -> np.ndarray:
    """(…, 3) texels → (…, channels) in ``dt`` (alpha 1)."""
    if channels == 3:
        return face.astype(dt)
    out = np.ones(face.shape[:-1] + (4,), dtype=dt)
    out[..., :3] = face
    return out


def _write_file(path, chunks) -> None:
    """Write the byte strings ``chunks`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            for c in chunks:
                fh.write(c)


# ----------------------------------------------------------------------------------------------
# KTX 1
# ----------------------------------------------------------------------------------------------
_KTX1_ID = b"\xabKTX 11\xbb\r\n\x1a\n"
_KTX2_ID = b"\xabKTX 20\xbb\r\n\x1a\n"
_KTX_HEADER = 64
_GL_HALF_FLOAT, _GL_HALF_FLOAT_OES, _GL_FLOAT = 0x140B, 0x8D61, 0x1406
_GL_RGB, _GL_RGBA = 0x1907, 0x1908
_GL_R11F_G11F_B10F = 0x8C3A
#: glInternalFormat → (texel format, accepted glType values, glFormat)
_KTX_FORMATS = {
    0x881A: (_Texel("RGBA16F", "f2", 4), (_GL_HALF_FLOAT, _GL_HALF_FLOAT_OES), _GL_RGBA),
    0x881B: (_Texel("RGB16F", "f2", 3), (_GL_HALF_FLOAT, _GL_HALF_FLOAT_OES), _GL_RGB),
    0x8814: (_Texel("RGBA32F", "f4", 4), (_GL_FLOAT,), _GL_RGBA),
    0x8815: (_Texel("RGB32F", "f4", 3), (_GL_FLOAT,), _GL_RGB),
    # glType UNSIGNED_INT_10F_11F_11F_REV; cmgen writes the internal format's value (0x8C3A) there
    _GL_R11F_G11F_B10F: (_Texel("R11F_G11F_B10F", "r11g11b10", 3), (0x8C3B, _GL_R11F_G11F_B10F), _GL_RGB),
    0x8C3D: (_Texel("RGB9_E5", "rgb9e5", 3), (0x8C3E,), _GL_RGB),
}
#: compressed glInternalFormat ranges (first, last, family) for the error message
_GL_COMPRESSED = ((0x83F0, 0x83F3, "S3TC / BC1-BC3"), (0x8C4C, 0x8C4F, "sRGB S3TC / BC1-BC3"),
                  (0x8DBB, 0x8DBE, "RGTC / BC4-BC5"), (0x8E8C, 0x8E8F, "BPTC / BC6H-BC7"),
                  (0x8D64, 0x8D64, "ETC1"), (0x9270, 0x9279, "ETC2 / EAC"), (0x93B0, 0x93BD, "ASTC"),
                  (0x93D0, 0x93DD, "sRGB ASTC"), (0x8C00, 0x8C03, "PVRTC"))
_KTX_FIELDS = ("endianness", "glType", "glTypeSize", "glFormat", "glInternalFormat", "glBaseInternalFormat",
               "pixelWidth", "pixelHeight", "pixelDepth", "numberOfArrayElements", "numberOfFaces",
               "numberOfMipmapLevels", "bytesOfKeyValueData")
#: rows padded? imageSize counts the row padding? — the specification's layout first, then two writers' (docstring)
_KTX_ROW_LAYOUTS = ((True, True), (True, False), (False, False))


def _pad4(nbytes: int) -> int:
    return -nbytes % 4


def _ktx_header(buf: bytes, path) -> tuple:
    """(header dict, byte order '<' / '>') of a KTX 1 file; one-line errors for anything but an uncompressed cube."""
    if len(buf) < 12 or buf[:12] != _KTX1_ID:
        if buf[:12] == _KTX2_ID:
            raise EnvMapFileError(f"{path}: a KTX 2 file; only KTX 1 (identifier «KTX 11») is read")
        raise EnvMapFileError(f"{path}: not a KTX 1 file (no KTX 11 identifier)")
    if len(buf) < _KTX_HEADER:
        raise EnvMapFileError(f"{path}: truncated KTX header ({len(buf)} bytes, the header has {_KTX_HEADER})")
    for order in ("<", ">"):
        h = dict(zip(_KTX_FIELDS, struct.unpack_from(order + "13I", buf, 12)))
        if h["endianness"] == 0x04030201:
            return h, order
    raise EnvMapFileError(f"{path}: KTX endianness field {buf[12:16].hex()} is neither 01020304 nor 04030201")


def _ktx_format(h: dict, path) -> _Texel:
    internal, gl_type = h["glInternalFormat"], h["glType"]
    if gl_type == 0 or h["glFormat"] == 0:
        fam = next((f for lo, hi, f in _GL_COMPRESSED if lo <= internal <= hi), "unknown family")
        raise EnvMapFileError(f"{path}: compressed KTX texture (glInternalFormat 0x{internal:04X}, {fam}); only "
                              "uncompressed half / float / packed-float formats are read")
    if internal not in _KTX_FORMATS:
        raise EnvMapFileError(f"{path}: KTX glInternalFormat 0x{internal:04X} is not read (RGBA16F, RGB16F, RGBA32F, "
                              "RGB32F, R11F_G11F_B10F, RGB9_E5 are)")
    fmt, types, gl_format = _KTX_FORMATS[internal]
    if gl_type not in types or h["glFormat"] != gl_format:
        raise EnvMapFileError(f"{path}: KTX {fmt.name} with glType 0x{gl_type:04X} and glFormat "
                              f"0x{h['glFormat']:04X}; expected glType {' or '.join(f'0x{t:04X}' for t in types)} "
                              f"and glFormat 0x{gl_format:04X}")
    return fmt


def _ktx_geometry(h: dict, path) -> int:
    """N of an n² cube map KTX; one-line errors for any other texture."""
    w, ht = h["pixelWidth"], h["pixelHeight"]
    if h["numberOfFaces"] != 6:
        raise EnvMapFileError(f"{path}: not a cube map (KTX numberOfFaces = {h['numberOfFaces']}, expected 6)")
    if h["numberOfArrayElements"] != 0:
        raise EnvMapFileError(f"{path}: a cube-map array (KTX numberOfArrayElements = "
                              f"{h['numberOfArrayElements']}); one cube map is read")
    if h["pixelDepth"] != 0:
        raise EnvMapFileError(f"{path}: a 3-D texture (KTX pixelDepth = {h['pixelDepth']}), not a cube map")
    if w < 1 or ht != w:
        raise EnvMapFileError(f"{path}: cube faces must be square and non-empty, got KTX pixelWidth {w}, "
                              f"pixelHeight {ht}")
    return w


def _ktx_offsets(buf: bytes, start: int, sizes: list, fmt: _Texel, order: str, rows_padded: bool,
                 counts_padding: bool):
    """Offsets of every face of every level under one row layout, or (None, message) if the file disagrees."""
    pos, offsets = start, []
    for k, n in enumerate(sizes):
        if pos + 4 > len(buf):
            return None, f"truncated before level {k} (its imageSize at byte {pos}, file {len(buf)} bytes)"
        image_size = struct.unpack_from(order + "I", buf, pos)[0]
        row = n * fmt.nbytes
        padded = row + _pad4(row)
        want = n * (padded if counts_padding else row)
        if image_size != want:
            return None, f"level {k} imageSize {image_size}, expected {want} ({n}x{n} {fmt.name} face)"
        pos += 4
        face_bytes = n * (padded if rows_padded else row)
        stride = face_bytes + _pad4(image_size)  # cubePadding (0 in the specification's layout)
        level = [pos + f * stride for f in range(6)]
        pos += 6 * stride
        pos += _pad4(pos)  # mipPadding (0 after cubePadding)
        if pos > len(buf):
            return None, f"truncated in level {k} (the levels up to it need {pos} bytes, file {len(buf)})"
        offsets.append((level, n, row, padded if rows_padded else row))
    if pos != len(buf):
        return None, f"{len(buf) - pos} byte(s) after the last level (the header describes {pos})"
    return offsets, ""


def read_ktx1(path, negative: str = "auto", nonfinite: str = "error") -> list:
    """Read a KTX 1 cube map with all its MIP levels (module docstring: formats, fields, layout).

    Parameters
    ----------
    path : str or path-like
    negative, nonfinite : str
        The radiance policy applied to every level (:mod:`ibl_ref.environment.radiance_policy`).

    Returns
    -------
    list of ndarray
        Level ℓ as float64 ``(6, N >> ℓ, N >> ℓ, 3)`` in the lab's cube convention (alpha dropped).

    Raises
    ------
    EnvMapFileError
        One line naming the file and the field or format: not KTX 1, a compressed or unsupported format, not a
        cube map (1-D, 3-D, array, non-square), a size that disagrees with the header.
    RadianceError
        NaN / Inf / negative texels the policy refuses.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from ibl_ref.environment.cube_containers import read_ktx1, write_ktx1
    >>> folder = tempfile.TemporaryDirectory()
    >>> path = write_ktx1(os.path.join(folder.name, "chain.ktx"), [np.full((6, 4, 4, 3), 2.5), np.ones((6, 2, 2, 3))])
    >>> [(lv.shape, float(lv.max())) for lv in read_ktx1(path)]
    [((6, 4, 4, 3), 2.5), ((6, 2, 2, 3), 1.0)]
    """
    path, buf = _read_bytes(path, "a KTX 1 file")
    h, order = _ktx_header(buf, path)
    fmt = _ktx_format(h, path)
    n = _ktx_geometry(h, path)
    sizes = _level_sizes(n, max(h["numberOfMipmapLevels"], 1), path, "KTX numberOfMipmapLevels")
    start = _KTX_HEADER + h["bytesOfKeyValueData"]
    if start > len(buf):
        raise EnvMapFileError(f"{path}: truncated KTX file (bytesOfKeyValueData {h['bytesOfKeyValueData']} runs "
                              f"past its {len(buf)} bytes)")
    first = ""
    for rows_padded, counts in _KTX_ROW_LAYOUTS:
        offsets, why = _ktx_offsets(buf, start, sizes, fmt, order, rows_padded, counts)
        if offsets is not None:
            break
        first = first or why
    else:
        raise EnvMapFileError(f"{path}: KTX data does not match its header: {first}")
    _check_output_size(sizes, path)
    levels = []
    for faces, m, row, stride in offsets:
        gl = np.empty((6, m, m, 3))
        for f, off in enumerate(faces):
            raw = np.frombuffer(buf, np.uint8, m * stride, off).reshape(m, stride)[:, :row]
            gl[f] = _decode(np.ascontiguousarray(raw), fmt, order).reshape(m, m, 3)
        levels.append(gl)
    return _finish(levels, path, negative, nonfinite)


def write_ktx1(path, levels, dtype: str = "float16", channels: int = 4):
    """Write a MIP chain of cube maps as a KTX 1 cube map (module docstring), atomically.

    Parameters
    ----------
    path : str or path-like
    levels : list of array_like
        Level ℓ of shape (6, N >> ℓ, N >> ℓ[, C]), C = 1 or 3, lab convention; finite, non-negative.
    dtype : {"float16", "float32"}
        RGBA16F / RGB16F (HALF_FLOAT) or RGBA32F / RGB32F (FLOAT) texels.
    channels : {4, 3}
        RGBA (alpha 1; every engine samples it) or RGB.

    Returns
    -------
    pathlib.Path

    Raises
    ------
    IBLError
        A bad chain, dtype or channel count; a value that overflows ``dtype`` (naming the level).
    RadianceError
        NaN / Inf / negative radiance; values below the type's normal range carrying more than 1e-4 of ∫L dω.
    OutputError
        The file cannot be written (nothing is left behind).

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from ibl_ref.environment.cube_containers import write_ktx1
    >>> folder = tempfile.TemporaryDirectory()
    >>> path = write_ktx1(os.path.join(folder.name, "c.ktx"), [np.ones((6, 2, 2, 3)), np.ones((6, 1, 1, 3))])
    >>> path.read_bytes()[:12]
    b'\\xabKTX 11\\xbb\\r\\n\\x1a\\n'
    """
    from pathlib import Path

    where = str(path)
    if channels not in (3, 4):
        raise IBLError(f"{where}: channels must be 3 (RGB) or 4 (RGBA), got {channels!r}")
    gl_levels, dt = _chain_for_write(levels, dtype, where)
    half = dt.itemsize == 2
    internal = {(True, 4): 0x881A, (True, 3): 0x881B, (False, 4): 0x8814, (False, 3): 0x8815}[(half, channels)]
    gl_format = _GL_RGBA if channels == 4 else _GL_RGB
    n = gl_levels[0].shape[1]
    chunks = [_KTX1_ID, struct.pack("<13I", 0x04030201, _GL_HALF_FLOAT if half else _GL_FLOAT, dt.itemsize,
                                    gl_format, internal, gl_format, n, n, 0, 0, 6, len(gl_levels), 0)]
    for gl in gl_levels:
        m = gl.shape[1]
        texels = _rgba(gl, channels, dt)  # (6, m, m, channels)
        row = m * channels * dt.itemsize
        pad = _pad4(row)
        if pad:  # rows to a multiple of 4 bytes (GL_UNPACK_ALIGNMENT 4): RGB16F at 1x1
            rows = np.zeros((6, m, row + pad), np.uint8)
            rows[..., :row] = texels.reshape(6, m, -1).view(np.uint8).reshape(6, m, row)
            faces = rows
        else:
            faces = np.ascontiguousarray(texels)
        chunks.append(struct.pack("<I", m * (row + pad)))  # imageSize: one face (non-array cube map)
        chunks.append(faces.tobytes())  # every face a multiple of 4 bytes: no cube or mip padding
    _write_file(path, chunks)
    return Path(path)


# ----------------------------------------------------------------------------------------------
# DDS
# ----------------------------------------------------------------------------------------------
_DDS_MAGIC = b"DDS "
_DDS_HEADER = 4 + 124
_DDS_DX10 = 20
_DDSD_CAPS, _DDSD_HEIGHT, _DDSD_WIDTH, _DDSD_PITCH = 0x1, 0x2, 0x4, 0x8
_DDSD_PIXELFORMAT, _DDSD_MIPMAPCOUNT, _DDSD_DEPTH = 0x1000, 0x20000, 0x800000
_DDPF_FOURCC, _DDPF_RGB, _DDPF_LUMINANCE = 0x4, 0x40, 0x20000
_DDSCAPS_COMPLEX, _DDSCAPS_TEXTURE, _DDSCAPS_MIPMAP = 0x8, 0x1000, 0x400000
_DDSCAPS2_CUBEMAP, _DDSCAPS2_ALL_FACES, _DDSCAPS2_VOLUME = 0x200, 0xFC00, 0x200000
_D3D10_TEXTURE2D, _MISC_TEXTURECUBE, _ALPHA_MODE_OPAQUE = 3, 0x4, 3
#: legacy FourCC (as a number) → texel format
_DDS_FOURCC = {113: _Texel("D3DFMT_A16B16G16R16F", "f2", 4), 116: _Texel("D3DFMT_A32B32G32R32F", "f4", 4)}
#: DXGI_FORMAT → texel format
_DXGI = {2: _Texel("DXGI_FORMAT_R32G32B32A32_FLOAT", "f4", 4), 6: _Texel("DXGI_FORMAT_R32G32B32_FLOAT", "f4", 3),
         10: _Texel("DXGI_FORMAT_R16G16B16A16_FLOAT", "f2", 4),
         26: _Texel("DXGI_FORMAT_R11G11B10_FLOAT", "r11g11b10", 3),
         67: _Texel("DXGI_FORMAT_R9G9B9E5_SHAREDEXP", "rgb9e5", 3)}
#: block-compressed DXGI formats (first, last, name) and legacy compressed FourCCs, for the error message
_DXGI_BC = ((70, 72, "BC1"), (73, 75, "BC2"), (76, 78, "BC3"), (79, 81, "BC4"), (82, 84, "BC5"), (94, 96, "BC6H"),
            (97, 99, "BC7"))
_BC_FOURCC = {b"DXT1": "BC1", b"DXT2": "BC2", b"DXT3": "BC2", b"DXT4": "BC3", b"DXT5": "BC3", b"ATI1": "BC4",
              b"BC4U": "BC4", b"BC4S": "BC4", b"ATI2": "BC5", b"BC5U": "BC5", b"BC5S": "BC5"}
_DDS_FIELDS = ("dwSize", "dwFlags", "dwHeight", "dwWidth", "dwPitchOrLinearSize", "dwDepth", "dwMipMapCount")
_PF_FIELDS = ("dwSize", "dwFlags", "dwRGBBitCount")  # dwFourCC (bytes 84-87) is read as bytes


def _fourcc_text(code: bytes) -> str:
    return repr(code.decode("latin-1")) if all(32 <= b < 127 for b in code) else str(struct.unpack("<I", code)[0])


def _dds_format(buf: bytes, h: dict, pf: dict, path) -> tuple:
    """(texel format, data offset) of a DDS header; one-line errors for anything else."""
    flags = pf["dwFlags"]
    code = buf[84:88]
    if not flags & _DDPF_FOURCC:
        if flags & (_DDPF_RGB | _DDPF_LUMINANCE):
            raise EnvMapFileError(f"{path}: an integer DDS texture ({pf['dwRGBBitCount']}-bit RGB / luminance "
                                  "masks): display images are not radiance; store half or float texels")
        raise EnvMapFileError(f"{path}: DDS pixel format flags 0x{flags:X} name no texel format the lab reads")
    if code == b"DX10":
        if len(buf) < _DDS_HEADER + _DDS_DX10:
            raise EnvMapFileError(f"{path}: truncated DDS_HEADER_DXT10 ({len(buf)} bytes)")
        dxgi, dim, misc, array = struct.unpack_from("<4I", buf, _DDS_HEADER)
        bc = next((name for lo, hi, name in _DXGI_BC if lo <= dxgi <= hi), None)
        if bc is not None:
            raise EnvMapFileError(f"{path}: block-compressed DDS texture (DXGI_FORMAT {dxgi}, {bc}); only "
                                  "uncompressed half / float / packed-float formats are read")
        if dxgi not in _DXGI:
            raise EnvMapFileError(f"{path}: DDS DXGI_FORMAT {dxgi} is not read (R16G16B16A16_FLOAT, "
                                  "R32G32B32A32_FLOAT, R32G32B32_FLOAT, R11G11B10_FLOAT, R9G9B9E5_SHAREDEXP are)")
        if dim != _D3D10_TEXTURE2D or not misc & _MISC_TEXTURECUBE:
            raise EnvMapFileError(f"{path}: not a cube map (DDS_HEADER_DXT10 resourceDimension {dim}, miscFlag "
                                  f"0x{misc:X}: TEXTURE2D (3) with TEXTURECUBE (0x4) expected)")
        if array != 1:
            raise EnvMapFileError(f"{path}: a cube-map array (DDS_HEADER_DXT10 arraySize {array}); one cube map "
                                  "is read")
        return _DXGI[dxgi], _DDS_HEADER + _DDS_DX10
    number = struct.unpack("<I", code)[0]
    if code in _BC_FOURCC:
        raise EnvMapFileError(f"{path}: block-compressed DDS texture (FourCC {_fourcc_text(code)}, "
                              f"{_BC_FOURCC[code]}); only uncompressed half / float formats are read")
    if number not in _DDS_FOURCC:
        raise EnvMapFileError(f"{path}: DDS FourCC {_fourcc_text(code)} is not read (113 A16B16G16R16F, "
                              "116 A32B32G32R32F or DX10 are)")
    if (h["dwCaps2"] & (_DDSCAPS2_CUBEMAP | _DDSCAPS2_ALL_FACES)) != _DDSCAPS2_CUBEMAP | _DDSCAPS2_ALL_FACES:
        raise EnvMapFileError(f"{path}: not a cube map with all six faces (DDS dwCaps2 0x{h['dwCaps2']:X}: "
                              "DDSCAPS2_CUBEMAP 0x200 and the face flags 0xFC00 expected)")
    return _DDS_FOURCC[number], _DDS_HEADER


def read_dds(path, negative: str = "auto", nonfinite: str = "error") -> list:
    """Read a DDS cube map with all its MIP levels (legacy or DX10 header; module docstring).

    Parameters, result and errors as :func:`read_ktx1`; the file errors here: not DDS, block-compressed or integer
    texels, not a cube map with six faces (a 2-D texture, a volume, a cube array, non-square), a size that disagrees
    with the header.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from ibl_ref.environment.cube_containers import read_dds, write_dds
    >>> folder = tempfile.TemporaryDirectory()
    >>> path = write_dds(os.path.join(folder.name, "chain.dds"), [np.full((6, 2, 2, 3), 0.25), np.ones((6, 1, 1, 3))],
    ...                  dtype="float32")
    >>> [(lv.shape, float(lv.min())) for lv in read_dds(path)]
    [((6, 2, 2, 3), 0.25), ((6, 1, 1, 3), 1.0)]
    """
    path, buf = _read_bytes(path, "a DDS file")
    if buf[:4] != _DDS_MAGIC:
        raise EnvMapFileError(f"{path}: not a DDS file (no 'DDS ' magic)")
    if len(buf) < _DDS_HEADER:
        raise EnvMapFileError(f"{path}: truncated DDS header ({len(buf)} bytes, the header has {_DDS_HEADER})")
    h = dict(zip(_DDS_FIELDS, struct.unpack_from("<7I", buf, 4)))
    h["dwCaps2"] = struct.unpack_from("<I", buf, 112)[0]
    pf = dict(zip(_PF_FIELDS, struct.unpack_from("<2I4xI", buf, 76)))
    if h["dwSize"] != 124 or pf["dwSize"] != 32:
        raise EnvMapFileError(f"{path}: DDS header dwSize {h['dwSize']} / pixel format dwSize {pf['dwSize']}, "
                              "expected 124 / 32")
    if h["dwFlags"] & _DDSD_DEPTH or h["dwCaps2"] & _DDSCAPS2_VOLUME or h["dwDepth"] > 1:
        raise EnvMapFileError(f"{path}: a volume (3-D) DDS texture (dwDepth {h['dwDepth']}), not a cube map")
    fmt, start = _dds_format(buf, h, pf, path)
    n = h["dwWidth"]
    if n < 1 or h["dwHeight"] != n:
        raise EnvMapFileError(f"{path}: cube faces must be square and non-empty, got DDS dwWidth {n}, dwHeight "
                              f"{h['dwHeight']}")
    sizes = _level_sizes(n, max(h["dwMipMapCount"], 1), path, "DDS dwMipMapCount")
    per_face = sum(s * s for s in sizes) * fmt.nbytes
    need = start + 6 * per_face
    if len(buf) != need:
        what = "truncated" if len(buf) < need else f"{len(buf) - need} byte(s) longer than its header says"
        raise EnvMapFileError(f"{path}: DDS file {what}: {len(sizes)} level(s) of {n}x{n} {fmt.name} cube faces "
                              f"need {need} bytes, the file has {len(buf)}")
    _check_output_size(sizes, path)
    levels = [np.empty((6, s, s, 3)) for s in sizes]
    pos = start
    for f in range(6):  # face-major: every level of +X, then of -X, ...
        for k, s in enumerate(sizes):
            nbytes = s * s * fmt.nbytes
            levels[k][f] = _decode(buf[pos:pos + nbytes], fmt, "<").reshape(s, s, 3)
            pos += nbytes
    return _finish(levels, path, negative, nonfinite)


def write_dds(path, levels, dtype: str = "float16"):
    """Write a MIP chain of cube maps as a DDS cube map with the DX10 header (module docstring), atomically.

    ``path``, ``levels``, the result and the errors as :func:`write_ktx1`; ``dtype`` "float16" or "float32" writes
    DXGI_FORMAT_R16G16B16A16_FLOAT or R32G32B32A32_FLOAT texels (alpha 1).

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from ibl_ref.environment.cube_containers import write_dds
    >>> folder = tempfile.TemporaryDirectory()
    >>> path = write_dds(os.path.join(folder.name, "c.dds"), [np.ones((6, 2, 2, 3)), np.ones((6, 1, 1, 3))])
    >>> data = path.read_bytes()
    >>> data[:4], data[84:88], len(data) - 148   # magic, FourCC, 6 faces x (4 + 1 texels) x 8 bytes
    (b'DDS ', b'DX10', 240)
    """
    from pathlib import Path

    gl_levels, dt = _chain_for_write(levels, dtype, str(path))
    n, count = gl_levels[0].shape[1], len(gl_levels)
    texel = 4 * dt.itemsize
    flags = _DDSD_CAPS | _DDSD_HEIGHT | _DDSD_WIDTH | _DDSD_PITCH | _DDSD_PIXELFORMAT | _DDSD_MIPMAPCOUNT
    caps = _DDSCAPS_TEXTURE | _DDSCAPS_COMPLEX | (_DDSCAPS_MIPMAP if count > 1 else 0)
    head = _DDS_MAGIC + struct.pack("<7I44x", 124, flags, n, n, n * texel, 0, count)
    head += struct.pack("<2I4s5I", 32, _DDPF_FOURCC, b"DX10", 0, 0, 0, 0, 0)
    head += struct.pack("<5I", caps, _DDSCAPS2_CUBEMAP | _DDSCAPS2_ALL_FACES, 0, 0, 0)
    head += struct.pack("<5I", 10 if dt.itemsize == 2 else 2, _D3D10_TEXTURE2D, _MISC_TEXTURECUBE, 1,
                        _ALPHA_MODE_OPAQUE)
    rgba = [_rgba(gl, 4, dt) for gl in gl_levels]
    _write_file(path, [head] + [rgba[k][f].tobytes() for f in range(6) for k in range(count)])
    return Path(path)


# ----------------------------------------------------------------------------------------------
# either container
# ----------------------------------------------------------------------------------------------
def read_cube_chain(path, negative: str = "auto", nonfinite: str = "error") -> list:
    """Read a KTX 1 or DDS cube-map chain, chosen by the file's first bytes (not its name): :func:`read_ktx1` or
    :func:`read_dds`.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from ibl_ref.environment.cube_containers import read_cube_chain, write_dds
    >>> folder = tempfile.TemporaryDirectory()
    >>> path = write_dds(os.path.join(folder.name, "named.ktx"), [np.ones((6, 1, 1, 3))])
    >>> read_cube_chain(path)[0].shape
    (6, 1, 1, 3)
    """
    p = check_input_file(path, "a KTX 1 or DDS file")
    try:
        with open(p, "rb") as fh:
            head = fh.read(12)
    except OSError as exc:
        raise EnvMapFileError(f"{p}: cannot read: {exc.strerror or exc}") from None
    if head[:4] == _DDS_MAGIC:
        return read_dds(p, negative, nonfinite)
    if head in (_KTX1_ID, _KTX2_ID):
        return read_ktx1(p, negative, nonfinite)
    raise EnvMapFileError(f"{p}: neither a KTX 1 nor a DDS file (first bytes {head[:4]!r})")
