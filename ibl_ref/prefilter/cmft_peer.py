"""cmft, the open-source cube-map filtering tool, as an outside peer: its released radiance prefilter with the
Phong lighting model, run as a program and read back from its own output file.

cmft (Dario Manesku, github.com/dariomanesku/cmft, BSD-2-Clause) is not part of this package; give the path of its
binary as ``binary=`` or in the environment variable ``IBL_REF_CMFT`` (:func:`cmft_binary`).  Its radiance filter
with ``--lightingModel phong`` computes, per output texel with direction r, the lobe average

    E_s(r) = Σ_j L_j Ω_j max(r·ω_j, 0)^s / Σ_j Ω_j max(r·ω_j, 0)^s

over the source texels j (exact texel solid angles; the lobe is cut where the weight falls below a threshold,
and the support it gathers is bounded by a box in face coordinates, which in the released code is too small for
wide lobes and misses bright texels near the edge of the box).  With ``--mipCount 1`` it writes one level
filtered from the full-resolution source with exponent ``s = 2^(glossScale + glossBias)``: only powers of two
(this module passes ``glossScale = log2 s``, ``glossBias = 0``).

Per exponent s_k (default: s = 1, 4, 16, … while the lobe still spans a texel,
:func:`~ibl_ref.prefilter.level_chain.default_exponents`, all powers of two) :class:`CmftRadiance`

1. writes the cube as a DDS cube map of RGBA float32 texels (:func:`write_dds_cube`; legacy header, FourCC 116 =
   ``D3DFMT_A32B32G32R32F``), its faces re-oriented to the OpenGL / Direct3D cube convention cmft reads
   (:func:`ibl_ref.environment.envmap.convert_convention`);
2. runs the binary (:func:`cmft_command`: ``--filter radiance --lightingModel phong --edgeFixup none
   --excludeBase false --mipCount 1 --srcFaceSize 0 --dstFaceSize 0``, CPU only; ``threads`` worker threads, i.e.
   ``--numCpuProcessingThreads threads + 1``: cmft's main thread only waits);
3. reads its DDS output back (:func:`read_dds_cube`: legacy or DX10 header, RGBA float32, faces
   +X −X +Y −Y +Z −Z) and re-orients the faces to the lab's convention (OpenEXR).

The maps are stacked over the input (the mirror) as the ``km00-lobes`` and ``kan2015`` prefilters are
(:func:`~ibl_ref.prefilter.level_chain.exponent_stack`): the look-up is seam-aware bilinear in direction and linear
in log s between stored exponents.  The face mapping is checked once per binary (``verify=True``,
:func:`check_face_mapping`): cmft's map of a smooth, strongly asymmetric pattern at s = 16 on 16² faces must be
within 5 % of the lab's exact lobe average (a face in the wrong orientation gives errors of order 1 there; the
released cmft is 0.97 % off; the unfiltered pattern itself is 14 % off, so a program that returns its input
unfiltered fails too).  Radiance is stored as float32 in the files, so the look-up carries a relative rounding of
≈ 6e-8.  No error bound.

**What comes back is checked** (:func:`run_cmft`): every map must be finite and non-negative, and not black where
the input is not (one line naming the binary and the exponent); a run longer than the timeout (``timeout=``,
``$IBL_REF_CMFT_TIMEOUT`` or :data:`DEFAULT_TIMEOUT_S`) is stopped and reported, naming the binary.
"""

from __future__ import annotations

import functools
import math
import os
import struct
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from ..environment import envmap
from ..errors import IBLError
from .level_chain import LevelChainPrefilter, check_exponents, exponent_stack
from .peer_programs import check_returned, run_timeout
from ..groundtruth.convolution_args import check_cube
from ..groundtruth.phong_convolution import lobe_average

__all__ = ["CmftUnavailable", "CmftRadiance", "cmft_binary", "cmft_command", "run_cmft", "write_dds_cube",
           "read_dds_cube", "check_face_mapping", "cmft_timeout", "ENV_VAR", "TIMEOUT_ENV_VAR", "DEFAULT_TIMEOUT_S",
           "FACE_CHECK_RTOL", "FACE_CHECK_S"]

#: environment variable naming the cmft binary
ENV_VAR = "IBL_REF_CMFT"
#: environment variable bounding one run of cmft (seconds; :func:`cmft_timeout`)
TIMEOUT_ENV_VAR = "IBL_REF_CMFT_TIMEOUT"
#: default bound of one run of cmft (s): far above a 1024² run of the released build (≈ 10 s, README's peer bench)
DEFAULT_TIMEOUT_S = 600.0
#: largest relative error of cmft against the exact lobe average on the face-mapping pattern (module docstring)
FACE_CHECK_RTOL = 0.05
#: exponent of the face-mapping check: wide enough that the unfiltered pattern is 14 % off (module docstring)
FACE_CHECK_S = 16.0

# DDS layout: "DDS " + a 124-byte DDS_HEADER (+ a 20-byte DDS_HEADER_DXT10 when the FourCC is "DX10")
_DDSD_FLAGS = 0x1 | 0x2 | 0x4 | 0x8 | 0x1000  # CAPS | HEIGHT | WIDTH | PITCH | PIXELFORMAT
_DDPF_FOURCC = 0x4
_FOURCC_A32B32G32R32F = 116  # D3DFMT_A32B32G32R32F: four float32 channels in R, G, B, A order
_DXGI_R32G32B32A32_FLOAT = 2
_CAPS_COMPLEX_TEXTURE = 0x8 | 0x1000
_CAPS2_CUBEMAP_ALL_FACES = 0x200 | 0x400 | 0x800 | 0x1000 | 0x2000 | 0x4000 | 0x8000


class CmftUnavailable(IBLError):
    """The cmft binary is not given or cannot be run, or what it returned is refused (a timeout, a failed run,
    NaN / negative / black maps, a failed face-mapping check): the peer is not available for a comparison."""


def cmft_binary(binary=None) -> Path:
    """The cmft binary: ``binary`` or ``$IBL_REF_CMFT``; :class:`CmftUnavailable` (one line) if neither names an
    executable file."""
    path = binary if binary not in (None, "") else os.environ.get(ENV_VAR, "")
    if not path:
        raise CmftUnavailable(f"no cmft binary: pass binary=PATH or set {ENV_VAR} to the cmft executable")
    p = Path(path).expanduser()
    if not p.is_file() or not os.access(p, os.X_OK):
        raise CmftUnavailable(f"cmft binary {str(p)!r} is not an executable file (binary= or {ENV_VAR})")
    return p.resolve()


# ----------------------------------------------------------------------------------------------
# DDS cube maps of RGBA float32 texels
# ----------------------------------------------------------------------------------------------
def write_dds_cube(path, cube_gl) -> None:
    """Write a cube ``(6, N, N, C)`` (C = 1 or 3; faces already in the OpenGL convention) as a DDS cube map of
    RGBA float32 texels (alpha 1; one channel is replicated to RGB); float32 must hold every value."""
    a = np.asarray(cube_gl, dtype=np.float64)
    if a.ndim == 3:
        a = a[..., None]
    if a.ndim != 4 or a.shape[0] != 6 or a.shape[1] != a.shape[2] or a.shape[3] not in (1, 3):
        raise IBLError(f"write_dds_cube: expected (6, N, N, 1 or 3), got shape {a.shape}")
    if np.max(np.abs(a), initial=0.0) > np.finfo(np.float32).max:
        raise IBLError("write_dds_cube: radiance overflows float32")
    n = a.shape[1]
    rgba = np.ones((6, n, n, 4), dtype="<f4")
    rgba[..., :3] = a if a.shape[3] == 3 else a[..., :1]
    head = struct.pack("<4s7I44x", b"DDS ", 124, _DDSD_FLAGS, n, n, n * 16, 0, 1)  # magic, size .. mip count
    head += struct.pack("<2I4s5I", 32, _DDPF_FOURCC, struct.pack("<I", _FOURCC_A32B32G32R32F), 0, 0, 0, 0, 0)
    head += struct.pack("<4I4x", _CAPS_COMPLEX_TEXTURE, _CAPS2_CUBEMAP_ALL_FACES, 0, 0)
    Path(path).write_bytes(head + np.ascontiguousarray(rgba).tobytes())


def read_dds_cube(path) -> np.ndarray:
    """A DDS cube map of RGBA float32 texels (legacy FourCC 116, or a DX10 header with R32G32B32A32_FLOAT) as
    ``(6, N, N, 3)`` float64, faces as stored (+X −X +Y −Y +Z −Z); the first MIP level of each face."""
    path = Path(path)
    buf = path.read_bytes()
    if len(buf) < 128 or buf[:4] != b"DDS ":
        raise IBLError(f"{path}: not a DDS file")
    height, width = struct.unpack_from("<2I", buf, 12)
    mips = max(struct.unpack_from("<I", buf, 28)[0], 1)
    fourcc = buf[84:88]
    offset = 128
    if fourcc == b"DX10":
        dxgi = struct.unpack_from("<I", buf, 128)[0]
        if dxgi != _DXGI_R32G32B32A32_FLOAT:
            raise IBLError(f"{path}: DXGI format {dxgi}, expected R32G32B32A32_FLOAT (2)")
        offset += 20
    elif struct.unpack("<I", fourcc)[0] != _FOURCC_A32B32G32R32F:
        raise IBLError(f"{path}: pixel format {fourcc!r}, expected RGBA float32 (FourCC 116 or DX10)")
    if width != height or width < 1:
        raise IBLError(f"{path}: cube faces must be square, got {width}x{height}")
    n = int(width)
    per_face = sum(max(n >> k, 1) ** 2 for k in range(mips)) * 4
    data = np.frombuffer(buf, dtype="<f4", offset=offset)
    if data.size < 6 * per_face:
        raise IBLError(f"{path}: truncated DDS data ({data.size} floats, need {6 * per_face})")
    faces = data[:6 * per_face].reshape(6, per_face)[:, :n * n * 4]
    return faces.reshape(6, n, n, 4)[..., :3].astype(np.float64)


# ----------------------------------------------------------------------------------------------
# running cmft
# ----------------------------------------------------------------------------------------------
def _gloss_scale(s) -> int:
    """log2 s for an exponent s = 2^K (K ≥ 0 integer), else a one-line IBLError."""
    try:
        v = float(s) if not isinstance(s, bool) else float("nan")
    except (TypeError, ValueError):
        v = float("nan")
    k = math.log2(v) if math.isfinite(v) and v >= 1 else -1.0
    if k < 0 or abs(k - round(k)) > 1e-12:
        raise IBLError(f"cmft filters only Phong exponents s = 2^K (K = 0, 1, 2, …), got {s!r}")
    return int(round(k))


def cmft_command(binary, inp, outbase, s, threads: int = 2) -> list:
    """The command line of one radiance filter at exponent ``s`` = 2^K, full resolution, one level."""
    return [str(binary), "--input", str(inp), "--filter", "radiance", "--srcFaceSize", "0", "--dstFaceSize", "0",
            "--excludeBase", "false", "--mipCount", "1", "--lightingModel", "phong", "--edgeFixup", "none",
            "--numCpuProcessingThreads", str(int(threads) + 1), "--useOpenCL", "false",
            "--glossScale", str(_gloss_scale(s)), "--glossBias", "0", "--generateMipChain", "false",
            "--outputNum", "1", "--output0", str(outbase), "--output0params", "dds,rgba32f,cubemap", "--silent"]


def _check_threads(threads) -> int:
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or int(threads) < 1:
        raise IBLError(f"threads must be an integer >= 1, got {threads!r}")
    return int(threads)


def cmft_timeout(timeout=None) -> float:
    """Seconds one run of cmft may take: ``timeout``, else ``$IBL_REF_CMFT_TIMEOUT``, else :data:`DEFAULT_TIMEOUT_S`;
    a finite number > 0, or a one-line :class:`IBLError` naming where the value came from."""
    return run_timeout(timeout, TIMEOUT_ENV_VAR, DEFAULT_TIMEOUT_S, "cmft")


def _check_map(got, exe, s, a) -> None:
    """One map read back from cmft (:func:`~ibl_ref.prefilter.peer_programs.check_returned`)."""
    check_returned(got, a, program="cmft", exe=exe, where=f"at s = {s:g}", error=CmftUnavailable)


def run_cmft(cube, exponents, *, binary=None, threads: int = 2, timeout: float | None = None) -> list:
    """cmft's radiance maps of ``cube`` (6, N, N, C; lab convention) at ``exponents`` (each 2^K), read back from its
    DDS outputs: a list of (6, N, N, 3) float64 in the lab convention (module docstring, steps 1–3).

    ``timeout``: seconds per run of the program (:func:`cmft_timeout`: default ``$IBL_REF_CMFT_TIMEOUT`` or
    :data:`DEFAULT_TIMEOUT_S`).  Every map read back is checked (finite, ≥ 0, not black for a non-black input).
    """

    a, _ = check_cube(cube)
    if a.shape[3] not in (1, 3):
        raise IBLError(f"cmft takes 1 or 3 channels, got {a.shape[3]}")
    timeout = cmft_timeout(timeout)
    exe = cmft_binary(binary)
    threads = _check_threads(threads)
    for s in exponents:
        _gloss_scale(s)
    out = []
    with tempfile.TemporaryDirectory(prefix="ibl_ref_cmft_") as tmp:
        tmp = Path(tmp)
        write_dds_cube(tmp / "in.dds", envmap.convert_convention(a, "openexr", "opengl"))
        for k, s in enumerate(exponents):
            base = tmp / f"out{k}"
            cmd = cmft_command(exe, tmp / "in.dds", base, s, threads)
            try:
                res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=tmp)
            except subprocess.TimeoutExpired:
                raise CmftUnavailable(f"cmft {str(exe)!r} did not finish within {timeout:g} s (s = {s:g}, face "
                                      f"{a.shape[1]}); stopped (a longer bound: timeout= or "
                                      f"${TIMEOUT_ENV_VAR})") from None
            except OSError as exc:
                raise CmftUnavailable(f"cannot run cmft {str(exe)!r}: {exc.strerror or exc}") from None
            dds = base.with_suffix(".dds")
            if res.returncode != 0 or not dds.is_file():
                last = (res.stderr or res.stdout or "").strip().splitlines()
                raise CmftUnavailable(f"cmft {str(exe)!r} failed (exit {res.returncode}, s = {s:g}): "
                                      f"{last[-1] if last else 'no output'}")
            try:
                got = read_dds_cube(dds)
            except IBLError as exc:
                raise CmftUnavailable(f"cmft {str(exe)!r} wrote an unreadable map at s = {s:g}: {exc}") from None
            if got.shape[1] != a.shape[1]:
                raise CmftUnavailable(f"cmft {str(exe)!r} wrote faces of {got.shape[1]}², expected {a.shape[1]}²")
            _check_map(got, exe, s, a)
            got = envmap.convert_convention(got, "opengl", "openexr")
            out.append(got if a.shape[3] == 3 else got[..., :1])
    return out


def face_check_pattern(n: int = 16) -> np.ndarray:
    """The face-mapping test pattern: exp(1.2x + 0.6y − 0.9z + 0.5xz) at texel centres (smooth, no symmetry
    that a face flip or swap would keep), (6, n, n, 3) with the channels scaled 1, 0.5, 0.25."""
    d = envmap.texel_directions(int(n))
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    base = np.exp(1.2 * x + 0.6 * y - 0.9 * z + 0.5 * x * z)
    return base[..., None] * np.array([1.0, 0.5, 0.25])


def check_face_mapping(binary=None, *, n: int = 16, s: float = FACE_CHECK_S, threads: int = 2,
                       timeout: float | None = None) -> dict:
    """cmft's map of :func:`face_check_pattern` at ``s`` against the lab's exact lobe average, read back with and
    without the convention change, and the unfiltered pattern's own distance to it: ``{"max_rel_error",
    "max_rel_error_unconverted", "max_rel_error_unfiltered", "max_rel_change"}`` (the first must be below
    :data:`FACE_CHECK_RTOL`, the next two far above it; the last is the map's change from the pattern)."""

    pat = face_check_pattern(n)
    got = run_cmft(pat, [s], binary=binary, threads=threads, timeout=timeout)[0]
    ref = lobe_average(pat, envmap.texel_directions(n), s)
    raw = envmap.convert_convention(got, "openexr", "opengl")  # what a reader without the re-orientation gets
    return {"max_rel_error": float(np.max(np.abs(got - ref) / ref)),
            "max_rel_error_unconverted": float(np.max(np.abs(raw - ref) / ref)),
            "max_rel_error_unfiltered": float(np.max(np.abs(pat - ref) / ref)),
            "max_rel_change": float(np.max(np.abs(got - pat) / pat))}


@functools.lru_cache(maxsize=8)
def _verified(path: str, mtime: float, timeout: float) -> float:
    res = check_face_mapping(path, timeout=timeout)
    err = res["max_rel_error"]
    if not err < FACE_CHECK_RTOL:
        if res["max_rel_change"] < 1e-3:  # float32 files: an unfiltered input comes back to ≈ 6e-8
            why = "it returned its input unfiltered"
        elif res["max_rel_error_unconverted"] < err:
            why = "the cube convention does not match"
        else:
            why = "its filter is not the Phong lobe average the lab compares against"
        raise CmftUnavailable(f"cmft {path!r}: its map of the face-mapping pattern at s = {FACE_CHECK_S:g} is "
                              f"{100 * err:.1f} % off the exact lobe average (> {100 * FACE_CHECK_RTOL:g} %): {why}; "
                              "the lab refuses it")
    return err


class CmftRadiance(LevelChainPrefilter):
    """cmft's released radiance prefilter (Phong lobe, s = 2^K) run as a program, blended in log s between maps.

    Parameters: ``exponents`` (powers of two ≥ 1; default s = 1, 4, 16, …), ``binary`` (default
    ``$IBL_REF_CMFT``), ``threads`` (cmft worker threads), ``timeout`` (s per run; default
    ``$IBL_REF_CMFT_TIMEOUT`` or :data:`DEFAULT_TIMEOUT_S`), ``verify`` (check the face mapping once per binary,
    :func:`check_face_mapping`).
    """

    lobe = "phong"
    paper = ("cmft (Manesku, github.com/dariomanesku/cmft): radiance filter, Phong lighting model, "
             "sum of L·Ω·(r·ω)^s / sum of Ω·(r·ω)^s over source texels, s = 2^K (an outside peer)")

    def __init__(self, cube, *, exponents=None, binary=None, threads: int = 2, timeout: float | None = None,
                 verify: bool = True):

        a, _ = check_cube(cube)
        self.exponents = check_exponents(exponents, a.shape[1])
        for s in self.exponents:
            _gloss_scale(s)
        timeout = cmft_timeout(timeout)
        exe = cmft_binary(binary)
        self.binary = str(exe)
        self.face_check_error = _verified(self.binary, exe.stat().st_mtime, timeout) if verify else None
        maps = run_cmft(a, self.exponents, binary=exe, threads=threads, timeout=timeout)
        self.pyramid, self.calibration = exponent_stack(a, self.exponents, maps, "cmft")
