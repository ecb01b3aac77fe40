"""Filament's ``cmgen`` as an outside peer: its GGX roughness prefilter (the chain an engine built on Filament
ships), run as a program, read back level by level and looked up the way Filament's run time looks it up.

``cmgen`` is the environment-map tool of Google's Filament renderer (github.com/google/filament, ``tools/cmgen``;
Apache-2.0).  It is not part of this package: give its path as ``binary=``, in the environment variable
``IBL_REF_CMGEN``, or have it on ``PATH`` (:func:`cmgen_binary`; on Debian ``apt-get install libfilament-tools``
installs ``/usr/bin/cmgen``).  Everything below was measured with Filament 1.9.25 (Debian ``1.9.25+dfsg2-10``) and
is pinned by ``tests/test_cmgen_peer.py``.

What the lab feeds it
---------------------
The lab's cube ``(6, N, N, C)`` (OpenEXR convention, :mod:`ibl_ref.environment.envmap`) is written as a
**horizontal cross** (:func:`ibl_ref.environment.resample.cube_to_cross`: 4N × 3N, faces in the OpenGL
orientation) in an **uncompressed float32 OpenEXR** file (:func:`write_input`), because

* cmgen chooses the layout from the aspect ratio alone: 2:1 is a lat-long map, 4:3 a horizontal and 3:4 a vertical
  cross whose width (height) must be a power of two; anything else is refused ("Aspect ratio not supported: 48x36"
  for a cross of 12² faces; a 1:6 strip or a square image likewise).  A lat-long input would be resampled onto
  cmgen's cube by its own interpolation; a cross of N² faces run with ``--size=N`` is not resampled, so level 0 is
  the lab's texels (below).  N must be a power of two (one-line error otherwise);
* its OpenEXR library is old: a DWAB file is refused ("Could not decode OpenEXR: Unknown compression type.");
  uncompressed and PIZ files are read (both checked); uncompressed needs no codec at all;
* it **mirrors** the environment by default (it negates x: checked on a cross, level 0 is the input at (−x, y, z));
  the lab's cube is already in the lab's orientation, so the command passes ``--no-mirror``.

The command (:func:`cmgen_command`) is ``cmgen --format=exr --size=N --ibl-min-lod-size=M --ibl-samples=K
--no-mirror [--ibl-no-prefilter] --ibl-ld=DIR IN.exr``; **the input comes last**: options after the file name are
ignored without a word (an ``--ibl-ld`` there writes nothing).  cmgen has no thread option: Filament's job system
runs the main thread and one worker per further core (on the lab's 2-core machine: the main thread and one
``JobSystem::loop`` thread, seen with ``ps -L``).

The radiance is scaled by a power of two first (:func:`half_scale`: the maximum into [2^14, 2^15)) and the levels
divided by it again, because cmgen writes **half floats** (largest 65504: a 1e5 sun comes back as Inf).  That is
exact: cmgen's filter is linear, a map × 2^3 gives bit-identical levels × 2^3 (no non-linear step such as a firefly
clamp), and power-of-two scaling rounds nothing.  After scaling, radiance below half's smallest normal 2^-14 (2^-28
of the maximum) is measured as its share of ∫L dω and refused above 1e-4, a warning above 1e-7 (the lab's rule for
what a format cannot hold, :func:`ibl_ref.environment.radiance_policy.check_format_range`).

What it writes, and what the lab reads back
-------------------------------------------
``DIR/in/m<l>_<face>.exr`` for levels l = 0 … L − 1 and faces ``px nx py ny pz nz`` (+X −X +Y −Y +Z −Z), level l
of face size N >> l, half-float RGB, PIZ.  :func:`read_levels` reads every level with the lab's reader
(:func:`ibl_ref.environment.exr_io.read_exr`) and re-orients the faces from the OpenGL convention to the lab's
(:func:`ibl_ref.environment.envmap.convert_convention`).  Checked against its output:

* **Face names and orientation** (:func:`check_face_mapping`): a labelled pattern whose texels hold their own
  direction, (R, G, B) = 1.5 + (x, y, z), comes back at level 0 as the lab's texel directions (to half rounding),
  each face centre on its named axis; at every level it is the lab's exact prefilter of the pattern within 0.0645
  (16² faces, 1024 samples; :data:`FACE_CHECK_ATOL` = 0.2), while the same files read without the re-orientation
  are 1.37 off and x-mirrored faces 1.99.
* **Level 0 is a copy of the input**: bit for bit the input (as written, float32) rounded to half (round to
  nearest), unfiltered — what the lab's field notes read in its source, confirmed on output.
* **Number of levels** (:func:`cmgen_levels`): log2(N/M) + 1 for a minimum level size M < N (256², M = 16: 5 levels,
  256² … 16²); for M ≥ N cmgen goes down to 1² (16² with the default M = 16: 16², 8², 4², 2², 1²).  A size or M that
  is not a power of two writes nothing.
* **Roughness per level**: cmgen prints "Level l, roughness = α, roughness (perceptual) = r" (three significant
  digits) with r = 1 − √(1 − l/(L − 1)), α = r² (:func:`filament_roughness_of_level`), the inverse of Filament's
  run-time look-up lod = r(2 − r)·(L − 1) (:func:`filament_level_of_roughness`).  :func:`run_cmgen` refuses a run
  whose printed values differ from these by more than the printing's rounding (:data:`PRINT_RTOL`).
* **Exit status**: cmgen exits 0 after refusing its input (an aspect ratio, a size that is not a power of two), so
  success is decided by the files: every level file must exist with the predicted face size and hold finite,
  non-negative radiance, not black for a non-black input (:class:`CmgenUnavailable` otherwise, one line naming the
  binary and cmgen's last line on stderr).  The run happens in a temporary folder that is removed whatever
  happens; nothing is written next to the user's files.
* ``--format=dds --compression=32`` (float32 DDS) writes every texel as 3.0 in this version; half-float DDS agrees
  with EXR.  The lab reads EXR.

**cmgen reads its source half a texel off.**  Its levels of a smooth map are the exact prefilter of the map with
every source texel moved from its centre to its corner toward +u, +v of the OpenGL face (half a texel; the same on
every face; :func:`cmgen_source_directions`): against that displaced source the error on the face-check pattern
falls from 0.039–0.065 to 0.001–0.0065 at every level of 16² faces, and on the smooth map of the test 5–60×.  The
displacement shrinks with the face size (at r = 1 the tangential bias is 4.4 %, 2.8 %, 1.9 % of the lobe's mean
cosine at 16², 32², 64², averaged over the faces); at engine sizes (256²) it is ≈ 0.2°, half of a 0.45° texel.
cmgen's default *prefiltered* sampling (samples read from coarser source levels) adds an error of its own that
grows with the face size: with ``--ibl-no-prefilter`` the displaced source explains cmgen's levels of a smooth map
to 0.05–0.17 % at 64², with the default 2.9–10 % remain (``docs/prefilters.md``).

The look-up (:class:`CmgenPrefilter`) is Filament's: perceptual roughness r → lod = r(2 − r)·(L − 1), seam-aware
bilinear in levels ⌊lod⌋ and ⌊lod⌋ + 1, linear between (the trilinear look-up of
:class:`~ibl_ref.prefilter.level_chain.LevelChainPrefilter`, :func:`ibl_ref.knuth2014.gloss_lookup.lookup_at_level`).
No error bound.  The errors of every level against the lab's exact n = v = r prefilter
(:func:`ibl_ref.prefilter.karis2013.prefilter_exact`) on a smooth map and a real probe, with the command, commit
and load that measured them, are in ``docs/prefilters.md`` ("Filament's cmgen as a peer"; :func:`level_errors`,
``benchmarks/bench_cmgen.py``).
"""

from __future__ import annotations

import functools
import math
import os
import re
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..environment import envmap
from ..environment.exr_io import HALF_MIN_NORMAL, ExrPart, read_exr, write_exr
from ..environment.radiance_policy import check_format_range
from ..environment.resample import cube_to_cross
from ..errors import IBLError
from ..groundtruth.convolution_args import check_cube
from ..knuth2014.pyramid import Pyramid
from .interface import check_lobe_param
from ..lobes import brdfs
from .karis2013 import build_dfg_table, check_option, check_samples, prefilter_exact, roughness_of_level, shade
from .level_chain import LevelChainPrefilter
from .mip_mappings import ROUGHNESS_MAPPINGS
from .peer_programs import check_returned, run_timeout

__all__ = ["CmgenUnavailable", "CmgenRun", "CmgenPrefilter", "cmgen_binary", "cmgen_timeout", "cmgen_command",
           "cmgen_levels", "filament_roughness_of_level", "filament_level_of_roughness", "half_scale",
           "write_input", "read_levels", "level_file", "write_level", "parse_roughness", "run_cmgen",
           "face_check_pattern",
           "cmgen_source_directions", "check_face_mapping", "level_errors", "ENV_VAR", "TIMEOUT_ENV_VAR",
           "DEFAULT_TIMEOUT_S", "FACES", "DEFAULT_SAMPLES", "DEFAULT_MIN_LEVEL_SIZE", "FACE_CHECK_ATOL", "PRINT_RTOL",
           "HALF_ROUNDOFF"]

#: environment variable naming the cmgen binary (else ``cmgen`` on PATH)
ENV_VAR = "IBL_REF_CMGEN"
#: environment variable bounding one run of cmgen (seconds; :func:`cmgen_timeout`)
TIMEOUT_ENV_VAR = "IBL_REF_CMGEN_TIMEOUT"
#: default bound of one run (s): far above a 512² run (14.5 s wall on 2 cores, the lab's field notes)
DEFAULT_TIMEOUT_S = 600.0
#: cmgen's face names, in the lab's face order +X −X +Y −Y +Z −Z
FACES = ("px", "nx", "py", "ny", "pz", "nz")
#: cmgen's defaults: GGX samples per texel (``--ibl-samples``) and smallest level (``--ibl-min-lod-size``)
DEFAULT_SAMPLES = 1024
DEFAULT_MIN_LEVEL_SIZE = 16
#: largest relative rounding of a value stored as half (round to nearest: half an ulp, 2^-11)
HALF_ROUNDOFF = 2.0 ** -11
#: cmgen prints roughness with 3 significant digits: a printed value is within 5e-3 (relative) of the true one
PRINT_RTOL = 5e-3
#: face check: largest absolute error of cmgen's levels of :func:`face_check_pattern` (values 0.5 … 2.5) against
#: the exact prefilter: measured 0.0645 (3.1× below; most of it cmgen's half-texel source displacement), while faces
#: read without the re-orientation are 1.37 off and x-mirrored ones 1.99 (6.8× and 10× above; module docstring)
FACE_CHECK_ATOL = 0.2
#: the scaled maximum lies in [2^(_HALF_TOP − 1), 2^_HALF_TOP): below half's largest value 65504 with headroom
_HALF_TOP = 15
_LEVEL_LINE = re.compile(r"Level\s+(\d+),\s*roughness\s*=\s*([-+0-9.eE]+|nan|inf),\s*roughness \(perceptual\)\s*=\s*"
                         r"([-+0-9.eE]+|nan|inf)")


class CmgenUnavailable(IBLError):
    """The cmgen binary is not given or cannot be run, or what it returned is refused (a timeout, missing or
    unreadable level files, NaN / negative / black levels, a roughness that is not Filament's mapping, a failed
    face check): the peer is not available for a comparison."""


def cmgen_binary(binary=None) -> Path:
    """The cmgen binary: ``binary``, else ``$IBL_REF_CMGEN``, else ``cmgen`` on ``PATH``; a one-line
    :class:`CmgenUnavailable` if none names an executable file."""
    path = binary if binary not in (None, "") else os.environ.get(ENV_VAR, "")
    if not path:
        found = shutil.which("cmgen")
        if found is None:
            raise CmgenUnavailable(f"no cmgen binary: pass binary=PATH, set {ENV_VAR}, or install it "
                                   "(apt-get install libfilament-tools)")
        path = found
    p = Path(path).expanduser()
    if not p.is_file() or not os.access(p, os.X_OK):
        raise CmgenUnavailable(f"cmgen binary {str(p)!r} is not an executable file (binary= or {ENV_VAR})")
    return p.resolve()


def cmgen_timeout(timeout=None) -> float:
    """Seconds one run of cmgen may take: ``timeout``, else ``$IBL_REF_CMGEN_TIMEOUT``, else
    :data:`DEFAULT_TIMEOUT_S`; a finite number > 0, or a one-line :class:`IBLError` naming where it came from."""
    return run_timeout(timeout, TIMEOUT_ENV_VAR, DEFAULT_TIMEOUT_S, "cmgen")


def _power_of_two(n, name: str) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or int(n) < 1 or int(n) & (int(n) - 1):
        raise IBLError(f"{name} must be a power of two >= 1 (cmgen writes nothing otherwise), got {n!r}")
    return int(n)


def cmgen_levels(size: int, min_level_size: int = DEFAULT_MIN_LEVEL_SIZE) -> int:
    """Number of levels cmgen writes for base size ``size`` and ``--ibl-min-lod-size`` ``min_level_size`` (both
    powers of two; measured, module docstring): ``log2(size/min) + 1`` if ``min < size``, else ``log2(size) + 1``.

    Examples
    --------
    >>> from ibl_ref.prefilter.cmgen_peer import cmgen_levels
    >>> cmgen_levels(256), cmgen_levels(64, 4), cmgen_levels(16), cmgen_levels(8)
    (5, 5, 5, 4)
    """
    size = _power_of_two(size, "size")
    m = _power_of_two(min_level_size, "min_level_size")
    k = size.bit_length() - 1
    return k - (m.bit_length() - 1) + 1 if m < size else k + 1


def filament_roughness_of_level(level, n_levels: int) -> np.ndarray:
    """Perceptual roughness cmgen prefilters into level ``level`` of ``n_levels``: r = 1 − √(1 − l/(L − 1))
    (α = r²); the inverse of :func:`filament_level_of_roughness` (:func:`ibl_ref.prefilter.karis2013.roughness_of_level`
    with ``mapping="filament"``).

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.prefilter.cmgen_peer import filament_roughness_of_level
    >>> np.round(filament_roughness_of_level(np.arange(5), 5), 3)
    array([0.   , 0.134, 0.293, 0.5  , 1.   ])
    """
    return roughness_of_level(level, n_levels, "filament")


def filament_level_of_roughness(roughness, n_levels: int) -> np.ndarray:
    """Filament's run-time level of a perceptual roughness r: lod = r(2 − r)·(L − 1) (continuous; a trilinear
    look-up blends levels ⌊lod⌋ and ⌊lod⌋ + 1).

    Examples
    --------
    >>> from ibl_ref.prefilter.cmgen_peer import filament_level_of_roughness
    >>> float(filament_level_of_roughness(0.5, 5)), float(filament_level_of_roughness(1.0, 5))
    (3.0, 4.0)
    """
    # the mapping (:mod:`ibl_ref.prefilter.mip_mappings`), roughness 0 (the mirror level) included: karis2013's
    # look-up refuses it
    return ROUGHNESS_MAPPINGS["filament"].level(roughness, n_levels)


def half_scale(vmax: float) -> float:
    """The power of two 2^k that puts ``vmax`` (> 0, finite) in [2^14, 2^15): half-float files then hold the
    largest value with headroom (65504) and every value down to 2^-28 of it with full relative precision; 1 for a
    black map.  Scaling by a power of two is exact in binary floating point (no overflow, no subnormals here)."""
    v = float(vmax)
    if not (math.isfinite(v) and v >= 0):
        raise IBLError(f"half_scale: the maximum must be finite and >= 0, got {vmax!r}")
    if v == 0:
        return 1.0
    _, e = math.frexp(v)  # v = m·2^e, m in [0.5, 1)
    return math.ldexp(1.0, _HALF_TOP - e)


def cmgen_command(binary, inp, outdir, size: int, *, samples: int = DEFAULT_SAMPLES,
                  min_level_size: int = DEFAULT_MIN_LEVEL_SIZE, prefiltered: bool = True) -> list:
    """The command line of one run: ``--format=exr --size --ibl-min-lod-size --ibl-samples --no-mirror
    --ibl-ld=OUTDIR`` (``prefiltered=False``: also ``--ibl-no-prefilter``, plain importance sampling of the
    full-resolution source) and the input **last** (cmgen ignores options after the file name).

    Examples
    --------
    >>> from ibl_ref.prefilter.cmgen_peer import cmgen_command
    >>> cmgen_command("cmgen", "in.exr", "out", 64, samples=256)[1:]
    ['--format=exr', '--size=64', '--ibl-min-lod-size=16', '--ibl-samples=256', '--no-mirror', '--ibl-ld=out', 'in.exr']
    """
    size = _power_of_two(size, "size")
    m = _power_of_two(min_level_size, "min_level_size")
    samples = check_samples(samples)
    if not isinstance(prefiltered, (bool, np.bool_)):
        raise IBLError(f"prefiltered must be True or False, got {prefiltered!r}")
    return [str(binary), "--format=exr", f"--size={size}", f"--ibl-min-lod-size={m}", f"--ibl-samples={samples}",
            "--no-mirror"] + ([] if prefiltered else ["--ibl-no-prefilter"]) + [f"--ibl-ld={outdir}", str(inp)]


def write_input(path, cube) -> Path:
    """Write a lab cube ``(6, N, N, 3)`` (OpenEXR convention, float32-representable) as the horizontal cross cmgen
    reads: 4N × 3N, faces in the OpenGL orientation, float32, uncompressed (module docstring); atomic."""
    a = np.asarray(cube)
    if a.ndim != 4 or a.shape[3] != 3:
        raise IBLError(f"write_input: expected a cube (6, N, N, 3), got shape {a.shape}")
    cross = np.ascontiguousarray(cube_to_cross(a.astype(np.float32), "hcross"), dtype=np.float32)
    return write_exr(path, ExrPart(cross, ("R", "G", "B")), compression="none")


def parse_roughness(stdout: str) -> dict:
    """``{level: (alpha, perceptual roughness)}`` from cmgen's standard output ("Level l, roughness = α, roughness
    (perceptual) = r"; its progress bars in between are ignored).

    Examples
    --------
    >>> from ibl_ref.prefilter.cmgen_peer import parse_roughness
    >>> parse_roughness("Level 0, roughness = 0, roughness (perceptual) = 0\\n"
    ...                 "  0%  ◀Level 1, roughness = 0.0179, roughness (perceptual) = 0.134")
    {0: (0.0, 0.0), 1: (0.0179, 0.134)}
    """
    out = {}
    for m in _LEVEL_LINE.finditer(stdout or ""):
        out[int(m.group(1))] = (float(m.group(2)), float(m.group(3)))
    return out


def read_levels(folder, n_levels: int, size: int, exe="cmgen") -> list:
    """cmgen's levels ``folder/m<l>_<face>.exr`` (l < ``n_levels``, faces :data:`FACES`) as float64 cubes
    ``(6, size >> l, size >> l, 3)`` in the lab's convention; :class:`CmgenUnavailable` (one line) for a missing,
    unreadable or wrongly sized file."""
    folder = Path(folder)
    levels = []
    for lv in range(n_levels):
        m = max(size >> lv, 1)
        faces = []
        for f in FACES:
            p = level_file(folder, lv, f)
            if not p.is_file():
                raise CmgenUnavailable(f"cmgen {str(exe)!r} did not write {p.name} (level {lv} of {n_levels})")
            try:
                img = read_exr(p)
            except IBLError as exc:
                raise CmgenUnavailable(f"cmgen {str(exe)!r} wrote an unreadable level file: {exc}") from None
            if img.n_colour != 3 or img.pixels.shape[:2] != (m, m):
                raise CmgenUnavailable(f"cmgen {str(exe)!r} wrote {p.name} as {img.pixels.shape[1]}x"
                                       f"{img.pixels.shape[0]} with {img.n_colour} colour channel(s); expected "
                                       f"{m}x{m} RGB")
            faces.append(img.pixels[..., :3])
        levels.append(envmap.convert_convention(np.stack(faces).astype(np.float64), "opengl", "openexr"))
    return levels


def level_file(folder, level: int, face: str) -> Path:
    """``folder/m<level>_<face>.exr``: cmgen's name of one face of one level (faces :data:`FACES`)."""
    return Path(folder) / f"m{int(level)}_{face}.exr"


def write_level(paths, cube, compression: str = "zip") -> None:
    """Write one level ``(6, M, M, 3)`` (lab convention) as cmgen writes it: one RGB OpenEXR file per face, in
    :data:`FACES` order, in the OpenGL orientation; ``paths`` the six file names (:func:`level_file`).  Float32 (cmgen
    writes half floats, whose rounding, 2^-11 relative, exceeds the tolerances an exact chain is made to); each file
    atomic.  :func:`read_levels` reads it back."""
    a = np.asarray(cube)
    if a.ndim != 4 or a.shape[0] != 6 or a.shape[3] != 3 or a.shape[1] != a.shape[2]:
        raise IBLError(f"write_level: expected a cube (6, M, M, 3), got shape {a.shape}")
    gl = envmap.convert_convention(a.astype(np.float64), "openexr", "opengl").astype(np.float32)
    for path, face in zip(paths, gl):
        write_exr(path, ExrPart(np.ascontiguousarray(face), ("R", "G", "B")), compression=compression)


@dataclass
class CmgenRun:
    """What :func:`run_cmgen` read back: ``levels`` (float64 cubes, lab convention, radiance units of the input),
    ``roughness`` (Filament's perceptual roughness of each level, :func:`filament_roughness_of_level`, checked
    against ``printed``: (α, r) per level as cmgen printed them), ``size``, ``min_level_size``, ``samples``, the
    power-of-two ``scale`` applied to the input, ``seconds`` (wall time of the program), ``binary``, ``info``
    (``prefiltered``, the command without its paths)."""

    levels: list
    roughness: tuple
    printed: tuple
    size: int
    min_level_size: int
    samples: int
    scale: float
    seconds: float
    binary: str
    info: dict = field(default_factory=dict)

    @property
    def n_levels(self) -> int:
        return len(self.levels)


def _check_printed(printed: dict, n_levels: int, exe) -> tuple:
    """Filament's roughness per level, after checking what cmgen printed against it within the printing's
    rounding; and the printed (α, r) per level."""
    if sorted(printed) != list(range(n_levels)):
        raise CmgenUnavailable(f"cmgen {str(exe)!r} printed the roughness of levels {sorted(printed)}, expected "
                               f"0..{n_levels - 1} (an unknown version?); the lab cannot tell which roughness each "
                               "level holds")
    want = filament_roughness_of_level(np.arange(n_levels), n_levels)
    r = np.array([printed[k][1] for k in range(n_levels)])
    al = np.array([printed[k][0] for k in range(n_levels)])
    for name, got, ref in (("perceptual roughness", r, want), ("roughness alpha", al, want ** 2)):
        off = np.abs(got - ref) > PRINT_RTOL * ref + 1e-12
        if off.any():
            k = int(np.argmax(off))
            raise CmgenUnavailable(f"cmgen {str(exe)!r} printed {name} {got[k]:g} for level {k} of {n_levels}; "
                                   f"Filament's mapping lod = r(2 - r)(L - 1) gives {ref[k]:.4g}; the lab's look-up "
                                   "would not match its chain")
    return tuple(float(x) for x in want), tuple((float(x), float(y)) for x, y in zip(al, r))


def _check_run_args(a, size, samples, min_level_size, prefiltered) -> int:
    """The base size of a run of cube ``a`` (checked, default its face size), every parameter checked (one-line
    :class:`IBLError`) before the program is looked for."""
    if a.shape[3] not in (1, 3):
        raise IBLError(f"cmgen takes 1 or 3 channels, got {a.shape[3]}")
    n = a.shape[1]
    if n & (n - 1):
        raise IBLError(f"cmgen reads cube crosses of power-of-two faces only, got {n}^2 faces; resample first "
                       "(ibl_ref.environment.resample.cube_to_cube)")
    size = n if size is None else _power_of_two(size, "the base size (--size)")
    cmgen_command("cmgen", "in", "out", size, samples=samples, min_level_size=min_level_size,
                  prefiltered=prefiltered)
    return size


def run_cmgen(cube, *, size: int | None = None, samples: int = DEFAULT_SAMPLES,
              min_level_size: int = DEFAULT_MIN_LEVEL_SIZE, prefiltered: bool = True, binary=None,
              timeout: float | None = None) -> CmgenRun:
    """cmgen's roughness chain of ``cube`` (6, N, N, C), C = 1 or 3, lab convention, N a power of two: write the
    cross, run the program in a temporary folder (removed afterwards, whatever happens), read every level back
    (module docstring).

    Parameters
    ----------
    cube : array (6, N, N, C)
        Finite, non-negative radiance; N a power of two (cmgen reads crosses of power-of-two width only).
    size : int, optional
        Base face size ``--size`` (a power of two; default N: no resampling, level 0 = the input in half floats).
    samples : int
        ``--ibl-samples``, GGX samples per texel (cmgen's default 1024).
    min_level_size : int
        ``--ibl-min-lod-size`` (a power of two; cmgen's default 16).
    prefiltered : bool
        cmgen's default prefiltered importance sampling (samples read from coarser source levels by their pdf);
        ``False`` passes ``--ibl-no-prefilter`` (every sample reads the full-resolution source).
    binary, timeout
        :func:`cmgen_binary`, :func:`cmgen_timeout`.

    Returns
    -------
    CmgenRun
        Every level in the radiance units of ``cube`` (the power-of-two scale undone), C channels.

    Raises
    ------
    IBLError
        Bad cube or parameter (before the program is looked for); :class:`CmgenUnavailable` for anything the
        program does wrong (one line, naming the binary).
    """
    a, _ = check_cube(cube)
    size = _check_run_args(a, size, samples, min_level_size, prefiltered)
    c, n = a.shape[3], a.shape[1]
    timeout = cmgen_timeout(timeout)
    rgb = a if c == 3 else np.repeat(a, 3, axis=3)
    scale = half_scale(float(np.max(rgb, initial=0.0)))
    scaled = rgb * scale
    check_format_range(scaled, scaled.astype(np.float16), "cmgen's half-float files",
                       "the smallest normal half", HALF_MIN_NORMAL, envmap.cube_solid_angles(n),
                       "the map's dynamic range exceeds what cmgen's half-float output holds")
    exe = cmgen_binary(binary)
    n_levels = cmgen_levels(size, min_level_size)
    with tempfile.TemporaryDirectory(prefix="ibl_ref_cmgen_") as tmp:
        tmp = Path(tmp)
        write_input(tmp / "in.exr", scaled)
        cmd = cmgen_command(exe, tmp / "in.exr", tmp / "out", size, samples=samples, min_level_size=min_level_size,
                            prefiltered=prefiltered)
        t0 = time.perf_counter()
        try:
            res = subprocess.run(cmd, capture_output=True, text=True, errors="replace", timeout=timeout, cwd=tmp,
                                 stdin=subprocess.DEVNULL)
        except subprocess.TimeoutExpired:
            raise CmgenUnavailable(f"cmgen {str(exe)!r} did not finish within {timeout:g} s (face {size}, {samples} "
                                   f"samples); stopped (a longer bound: timeout= or ${TIMEOUT_ENV_VAR})") from None
        except OSError as exc:
            raise CmgenUnavailable(f"cannot run cmgen {str(exe)!r}: {exc.strerror or exc}") from None
        seconds = time.perf_counter() - t0
        folder = tmp / "out" / "in"
        if res.returncode != 0 or not (folder / "m0_px.exr").is_file():
            last = [ln.strip() for ln in (res.stderr or res.stdout or "").splitlines() if ln.strip()]
            raise CmgenUnavailable(f"cmgen {str(exe)!r} failed (exit {res.returncode}, no level files): "
                                   f"{last[-1] if last else 'no output'}")
        levels = read_levels(folder, n_levels, size, exe)
        extra = sorted(p.name for p in folder.glob(f"m{n_levels}_*.exr"))
        if extra:
            raise CmgenUnavailable(f"cmgen {str(exe)!r} wrote more levels than the {n_levels} expected ({extra[0]}); "
                                   "an unknown version?")
        roughness, printed = _check_printed(parse_roughness(res.stdout), n_levels, exe)
    out = []
    for lv, got in enumerate(levels):
        check_returned(got, rgb, program="cmgen", exe=exe, where=f"at level {lv}", error=CmgenUnavailable,
                       what="chain")
        got = got / scale
        out.append(got if c == 3 else got[..., :1])
    return CmgenRun(out, roughness, printed, size, min_level_size, samples, scale, seconds, str(exe),
                    {"prefiltered": bool(prefiltered), "command": cmd[1:-2] + ["--ibl-ld=DIR", "IN.exr"]})


# ----------------------------------------------------------------------------------------------
# the face check and the errors against the exact prefilter
# ----------------------------------------------------------------------------------------------
def face_check_pattern(n: int = 16) -> np.ndarray:
    """The labelled pattern of the face check: every texel holds its own direction, (R, G, B) = 1.5 + (x, y, z) at
    texel centres (lab convention), (6, n, n, 3).  A radially symmetric lobe maps it to 1.5 + c·d (c the lobe's
    mean cosine), so every level of a correct chain still names its texels' directions."""
    return 1.5 + envmap.texel_directions(int(n))


def cmgen_source_directions(n: int) -> np.ndarray:
    """Where cmgen's filter reads each source texel, as measured (module docstring): the direction of texel
    (row i, column j) of an OpenGL-oriented face displaced by half a texel to the face-plane point
    (u, v) = (2(j + 1)/n − 1, 2(i + 1)/n − 1), i.e. toward +u and +v, instead of its centre; unit vectors
    (6, n, n, 3) in the lab's convention.  The exact prefilter of a smooth map f sampled there,
    ``prefilter_exact(f(cmgen_source_directions(n)), r)``, is within 0.0065 of cmgen's levels of f on the face-check
    pattern (against 0.065 for f at the texel centres; module docstring)."""
    n = envmap.check_face_size(n)
    x = 2.0 * (np.arange(n) + 1.0) / n - 1.0
    u, v = np.meshgrid(x, x)
    fr = envmap.face_frames("opengl")
    d = fr[:, None, None, 0] + u[None, ..., None] * fr[:, None, None, 1] + v[None, ..., None] * fr[:, None, None, 2]
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return envmap.convert_convention(d, "opengl", "openexr")


def _exact_levels(cube, run: CmgenRun) -> list:
    """The exact n = v = r prefilter of ``cube`` at every level's roughness and face size (level 0: ``cube``)."""
    a = np.asarray(cube, dtype=np.float64)
    rough = filament_roughness_of_level(np.arange(run.n_levels), run.n_levels)
    return [a] + [prefilter_exact(a, float(rough[k]), out_size=run.levels[k].shape[1])
                  for k in range(1, run.n_levels)]


def check_face_mapping(binary=None, *, n: int = 16, samples: int = DEFAULT_SAMPLES,
                       timeout: float | None = None) -> dict:
    """cmgen's chain of :func:`face_check_pattern` against the lab's exact prefilter of the same pattern, read with
    the lab's re-orientation, without it, and x-mirrored (what cmgen's default mirroring gives).

    Returns ``{"max_abs_error"`` (per level; level 0 against the pattern), ``"max_abs_error_unconverted"``,
    ``"max_abs_error_mirrored"`` (largest over levels), ``"level0_is_half_copy"`` (level 0 equals the pattern
    rounded to half, bit for bit), ``"printed"`` (α, r per level as cmgen printed them)``}``; every
    ``max_abs_error`` must be below :data:`FACE_CHECK_ATOL`, the other two far above it.
    """
    pat = face_check_pattern(n)
    run = run_cmgen(pat, samples=samples, binary=binary, timeout=timeout)
    ref = _exact_levels(pat, run)
    mirror = np.array([-1.0, 1.0, 1.0])
    err, unconv, mirr = [], 0.0, 0.0
    for k, (got, want) in enumerate(zip(run.levels, ref)):
        err.append(float(np.max(np.abs(got - want))))
        raw = envmap.convert_convention(got, "openexr", "opengl")  # a reader without the re-orientation
        unconv = max(unconv, float(np.max(np.abs(raw - want))))
        flipped = 1.5 + (want - 1.5) * mirror  # the exact level of the x-mirrored pattern
        mirr = max(mirr, float(np.max(np.abs(got - flipped))))
    h = pat.astype(np.float32).astype(np.float16).astype(np.float64)  # as written (float32), as stored (half)
    return {"max_abs_error": err, "max_abs_error_unconverted": unconv, "max_abs_error_mirrored": mirr,
            "level0_is_half_copy": bool(np.array_equal(run.levels[0], h)), "printed": run.printed}


def level_errors(cube, run: CmgenRun) -> list:
    """Per level of ``run`` (made from ``cube``): ``{"level", "face", "roughness", "max_rel", "mean_rel",
    "max_abs_of_max"}`` of cmgen's texels against the exact n = v = r prefilter at that roughness (level 0: against
    ``cube``): relative to the exact value per texel and channel (``cube`` must be positive), and the largest
    absolute error over the level's largest exact value.  A dense sum: keep faces ≤ 32²."""
    ref = _exact_levels(cube, run)
    out = []
    for k, (got, want) in enumerate(zip(run.levels, ref)):
        err = np.abs(got - want)
        rel = err / want
        out.append({"level": k, "face": int(got.shape[1]), "roughness": run.roughness[k],
                    "max_rel": float(np.max(rel)), "mean_rel": float(np.mean(rel)),
                    "max_abs_of_max": float(np.max(err) / np.max(want))})
    return out


@functools.lru_cache(maxsize=8)
def _verified(path: str, mtime: float, timeout: float) -> float:
    res = check_face_mapping(path, timeout=timeout)
    err = max(res["max_abs_error"])
    if not err < FACE_CHECK_ATOL:
        why = ("its faces are x-mirrored" if res["max_abs_error_mirrored"] < err else
               "the cube convention does not match" if res["max_abs_error_unconverted"] < err else
               "its levels are not the GGX prefilter the lab compares against")
        raise CmgenUnavailable(f"cmgen {path!r}: its chain of the face-check pattern is {err:.3g} off the exact "
                               f"prefilter (> {FACE_CHECK_ATOL:g}): {why}; the lab refuses it")
    return err


class CmgenPrefilter(LevelChainPrefilter):
    """Filament's cmgen GGX roughness chain run as a program, looked up as Filament does (lod = r(2 − r)·(L − 1)).

    Parameters: ``samples`` (``--ibl-samples``, default 1024), ``base_size`` (``--size``, default the input's face
    size), ``min_level_size`` (``--ibl-min-lod-size``, default 16), ``binary`` (default ``$IBL_REF_CMGEN`` or
    ``cmgen`` on PATH), ``timeout`` (s; default ``$IBL_REF_CMGEN_TIMEOUT`` or :data:`DEFAULT_TIMEOUT_S`),
    ``verify`` (run :func:`check_face_mapping` once per binary), ``dfg_size`` and ``smith`` (the lab's DFG table
    for the split sum's second factor, as the other GGX methods carry it: cmgen supplies the prefiltered radiance).

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.prefilter import build_prefilter
    >>> pf = build_prefilter(np.full((6, 16, 16, 3), 2.5), "cmgen")  # doctest: +SKIP
    >>> pf.n_levels, [round(r, 3) for r in pf.roughness]  # doctest: +SKIP
    (5, [0.0, 0.134, 0.293, 0.5, 1.0])
    >>> pf.lookup(np.array([[0.0, 0.0, 1.0]]), 0.4)  # doctest: +SKIP
    array([[2.5, 2.5, 2.5]])
    """

    lobe = "ggx"
    paper = ("Filament's cmgen (github.com/google/filament, tools/cmgen; Apache-2.0): GGX n = v = r roughness "
             "prefilter by prefiltered importance sampling, level l at r = 1 - sqrt(1 - l/(L-1)), looked up at "
             "lod = r(2 - r)(L - 1) (an outside peer)")

    def __init__(self, cube, *, samples: int = DEFAULT_SAMPLES, base_size: int | None = None,
                 min_level_size: int = DEFAULT_MIN_LEVEL_SIZE, prefiltered: bool = True, binary=None,
                 timeout: float | None = None, verify: bool = True, dfg_size=64, smith: str = "height_correlated"):
        a, _ = check_cube(cube)
        _check_run_args(a, base_size, samples, min_level_size, prefiltered)
        timeout = cmgen_timeout(timeout)
        exe = cmgen_binary(binary)
        self.binary = str(exe)
        self.face_check_error = _verified(self.binary, exe.stat().st_mtime, timeout) if verify else None
        self.run = run_cmgen(a, size=base_size, samples=samples, min_level_size=min_level_size,
                             prefiltered=prefiltered, binary=exe, timeout=timeout)
        self.roughness = self.run.roughness  # Filament's r per level (checked against what cmgen printed)
        self.pyramid = Pyramid(levels=self.run.levels, kernel="cmgen", order="exact", seam="exact",
                               base_size=self.run.size)
        sizes = (dfg_size, dfg_size) if np.ndim(dfg_size) == 0 else tuple(dfg_size)
        if len(sizes) != 2 or any(check_samples(x, "DFG table size") < 2 for x in sizes):
            raise IBLError(f"DFG table size must be >= 2 per axis, got {dfg_size!r}")
        check_option(smith, brdfs.SMITH_FORMS, "smith")
        self._dfg_args = (dfg_size, smith)  # the table itself is built on first use (dfg)

    @functools.cached_property
    def dfg(self):
        """The lab's DFG table (:func:`ibl_ref.prefilter.karis2013.build_dfg_table`), built on first use (a few
        seconds the first time in a process; look-ups alone never need it)."""
        size, smith = self._dfg_args
        return build_dfg_table(size, smith=smith)

    def level_of(self, roughness) -> np.ndarray:
        """Filament's continuous level of perceptual ``roughness``: lod = r(2 − r)·(L − 1)."""
        r = check_lobe_param(self.lobe, roughness)
        return filament_level_of_roughness(r, self.n_levels)

    def shade(self, normals, views, roughness, f0) -> np.ndarray:
        """Split-sum specular radiance ``P(r, roughness)·(F0·A + B)`` with cmgen's P and the lab's DFG table
        (:func:`ibl_ref.prefilter.karis2013.shade`)."""
        return shade(self.lookup, self.dfg, normals, views, roughness, f0)
