"""Judge a prefiltered cube-map chain as users have it: what each level holds, against the exact prefilter.

A user's chain — one KTX 1 / DDS cube map with its MIP levels, or Filament cmgen's folder of per-face files — claims,
through its engine's MIP → roughness mapping, that level ℓ of L holds the split sum's n = v = r GGX prefilter (Karis
2013, Eq. 8; or, ``lobe="phong"``, a Phong lobe average) of its environment at the roughness
r_ℓ = :func:`~ibl_ref.prefilter.karis2013.roughness_of_level` (ℓ, L, mapping).  :func:`judge` measures every level
against the exact prefilter at that roughness, at that level's own texel directions, and says what roughness the
level really holds; :func:`write_report` writes the numbers and a one-page report in plain sentences.

What is compared
----------------
Per level ℓ (face size n_ℓ, texels j with their exact solid angles Ω_j, channels c), L the chain's level and E the
exact prefilter of the environment (resampled to the chain's base face size, integral-preserving) at r_ℓ:

* **E** — GGX: :func:`~ibl_ref.groundtruth.ggx_convolution.convolve_ggx_levels` at (r_ℓ, n_ℓ), every texel and
  channel within ``rtol`` of the exact lobe average (a rigorous per-texel bound: ``exact_rel_bound_max_frac``);
  Phong: :func:`~ibl_ref.groundtruth.convolve.convolve` at the exponent s(r_ℓ)
  (:func:`~ibl_ref.prefilter.ggx_phong_mapping.phong_exponent`, ``phong_mapping``; its bound kind in
  ``exact_bound_kind``).  A level of roughness 0 (level 0 under every mapping but ``unreal``) is the mirror: E is
  the environment itself at the level's size (bound 0).
* **Relative error** of a texel and channel: e = |L − E| / max(E, 0.1·Ē_c), Ē_c the Ω-weighted mean of E_c over
  the level (:data:`REL_FLOOR`): texels much darker than the level's mean count against a tenth of the mean, so a
  speck of noise on black does not read as an infinite error.  ``rel_err_p99_frac`` / ``rel_err_p999_frac`` /
  ``rel_err_max_frac``: its 99th / 99.9th percentile and maximum over every texel and channel.
* ``rel_l1_frac`` = Σ Ω |L − E| / Σ Ω E (all channels); ``bias_frac`` = Σ Ω (L − E) / Σ Ω E (signed: > 0, the
  level is too bright on the whole).
* ``energy_kept_ratio`` = mean over channels of Σ Ω L_c / Σ Ω E_c: 1 for a chain that neither loses nor gains
  energy (a normalised prefilter keeps ∫L dω; a chain that forgets to normalise, or clamps, does not).
* **Fitted roughness** (:func:`fit_roughness`): the r ∈ {0} ∪ [0.02, 1] that minimises the rel. L1 between the level
  and the exact prefilter of r.  To keep it cheap the comparison runs on a coarser grid: the exact prefilter at the
  texel centres of m² faces (m = the largest divisor of n_ℓ ≤ ``fit_size``, 32 by default) from the environment
  at min(N, 2 n_ℓ)² (twice the level's resolution: the lobe the level can hold is resolved), against the level
  read at the same centres (its texel there, or the mean of its 2 × 2 texels around it when n_ℓ/m is even: bilinear
  reading, which blurs by half a level texel — a level whose lobe spans two texels reads ≈ 2 % rougher).  First a
  grid (:data:`FIT_GRID`: 0 and nine roughnesses geometric in [0.02, 1], one source tree), then a bounded
  Brent search (golden section with parabolic steps, :func:`scipy.optimize.minimize_scalar`) in ln r between the
  grid neighbours of the best point, to ``FIT_XTOL`` (0.5 %) in r.  ``fit_rel_l1_frac`` is the error at the fit,
  ``fit_rel_l1_declared_frac`` at the declared roughness on the same grid.  A level whose comparison barely depends
  on r (a flat environment: the rel. L1 varies by less than 2·``rtol`` over the grid) gets ``fit_status``
  ``"undetermined"``; one best explained by the unfiltered source, ``"mirror"`` (fitted 0).  **The declared
  roughness holds** (``roughness_holds``) unless the fit differs from it by more than max(0.02, 10 %) *and* the
  declared roughness explains the level worse than the fit by more than max(2·rtol, 25 % of the fit's error): the
  first alone would flag rough levels of smooth maps, which barely change with r; the second alone, noise.
  :func:`best_mapping` names the mapping of :data:`~ibl_ref.prefilter.karis2013.ROUGHNESS_MAPPINGS` whose
  roughness per level is closest to the fitted ones.
* **Seams**: the relative error averaged over the texels on a face edge (the outer ring of texels of each face)
  divided by that of the face interiors (``seam_ratio``; ≈ 1 without seams, ≫ 1 where the faces do not meet
  smoothly).  That average hides a seam along one edge, and an error spot that happens to straddle an edge (a sun
  next to it) raises it without any seam; so each of the 24 face edges is also looked at alone, twice, and named
  by the two faces that meet there (``+X/+Y``): its **row** — the mean relative error of the texels along the edge
  over that of the rows 1 and 2 inside the face (``seam_worst_edge_ratio``) — and its **step** — a seam is a wrong
  step between the two texels facing each other across the edge, so the step's error (L_a − L_b) − (E_a − E_b)
  over max(E_a, 0.1·Ē) (channel means; a on the face, b across the edge) averaged along the edge, over the same for
  the steps between the rows 1 → 2 and 2 → 3 inside the face, which do not touch the edge row
  (``seam_worst_edge_step_ratio``).  An error spot centred on an edge raises the row ratio but not the step ratio
  (it is smooth across the edge); a level displaced differently on each face (cmgen's half-texel source offset)
  raises the step ratio but not the row ratio; an edge row of its own (faces filtered apart, clamped or averaged
  at their borders) raises both.  Flagged (``seam_flagged``) at the edge where the smaller of the two is largest,
  if it is ≥ :data:`SEAM_FLAG_RATIO` and the step error there ≥ :data:`SEAM_FLAG_ERROR`.  Every ratio adds
  ε = :data:`SEAM_EPS` to numerator and denominator, so a level that is exact everywhere has ratio 1.  Faces below
  3² have no interior (no seam ratio), faces below :data:`SEAM_MIN_FACE` texels across no edge ratios.
  Across every edge, the largest jump of the channel mean between the two texels facing each other
  (:func:`ibl_ref.knuth2014.filters.pad_cube` with the neighbouring faces), in units of the level's mean, for the
  chain and for E (``edge_jump_max_of_mean``, ``exact_edge_jump_max_of_mean``), and their ratio
  (``edge_jump_ratio``, ε added as above; ≈ 1: the chain's faces meet as the exact prefilter's do).
* **Fireflies**: texels where some channel exceeds :data:`FIREFLY_FACTOR` (10) × max(E, 0.1·Ē_c)
  (``firefly_texels``), the largest such ratio and where it is (face, row, column in the lab's orientation), and
  the p99.9 of e above.

The sphere (``shading=``)
-------------------------
What the chain does to a picture: the orthographic unit sphere (``sphere_size`` pixels across, view +Z), a GGX
material of roughness ρ ∈ ``shading_roughness`` (0.1, 0.3, 0.6) and F0 = ``f0`` (1 by default), shaded by the split
sum P(r, ρ)·(F0·A + B) with the exact DFG terms (:func:`~ibl_ref.prefilter.karis2013.split_sum` without a table)
and P read trilinearly at the mapping's level ℓ(ρ) (:class:`~ibl_ref.prefilter.karis2013.PrefilteredChain`), once
with the user's levels and once with the exact levels E — against the exact unoccluded integral of the GGX lobe.
``rel_l1_chain_vs_reference_frac`` is what the user's chain gives, ``rel_l1_exact_chain_vs_reference_frac`` what
the split sum gives with a perfect chain (its n = v = r and trilinear errors), ``rel_l1_chain_vs_exact_chain_frac``
the chain's own share.  Phong (``lobe="phong"``): the Phong material of exponent s(ρ), P itself, against the
exact Phong lobe integral.  The sphere and the exact reference belong to the rendering layer, which sits above this
package: ``shading`` is an object with ``pixels(size) -> (normals, views)`` and ``reference(env, lobe, param,
normals, views, f0=, rtol=) -> (values, estimated rel. L1 error)`` (``ibl-ref judge`` passes the lab's
orthographic sphere and :func:`ibl_ref.rendering.unoccluded_reference.integrate`); ``shading=None`` skips the step.
The teapot (occluded shading) is not judged: a chain has no visibility, the sphere shows all it can change.

Files (:func:`write_report`, one output set: all or nothing, atomic)
--------------------------------------------------------------------
``judge_levels.csv`` (one row per level, units in the column names), ``judge_shading.csv`` (one row per ρ),
``judge.json`` (inputs, settings, versions, timings, load averages, the summary, and the small previews the figure
is drawn from), ``judge_report.md`` (the page, generated from the CSV and JSON data alone: :func:`report_markdown`)
and ``judge_levels.png`` (per level: chain | exact | relative error, one exposure per row; drawn from the JSON's
previews alone: :func:`plot_levels`).  The folder must be new, empty, or hold only a previous judge's files.

Examples
--------
A chain whose every level is the constant of a constant environment is exact:

>>> import numpy as np
>>> from ibl_ref.prefilter.judge import judge
>>> env = np.full((6, 4, 4, 3), 2.0)
>>> res = judge([env, np.full((6, 2, 2, 3), 2.0)], env, "linear", fit=False, kernel="numpy")
>>> [(row["level"], row["rel_l1_frac"], row["energy_kept_ratio"]) for row in res["levels"]]
[(0, 0.0, 1.0), (1, 0.0, 1.0)]
"""

from __future__ import annotations

import json
import math
import os
import platform
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..atomic import MANIFEST_MARKER, TEMP_TAG, OutputError, OutputSet, atomic_write, read_csv, write_csv
from ..environment import envmap
from ..environment.cube_containers import read_cube_chain
from ..environment.exr_io import read_exr
from ..environment.hdr_io import read_hdr
from ..environment.radiance_policy import apply_policy, warn_repaired
from ..environment.resample import cube_to_cross, cube_to_cube
from ..errors import EnvMapFileError, IBLError, as_path
from ..groundtruth.convolve import convolve
from ..groundtruth.ggx_convolution import convolve_ggx_levels
from ..knuth2014.filters import pad_cube
from ..knuth2014.seam_metric import edge_and_corner_tables
from ..limits import check_rtol
from ..progress import step, track
from . import karis2013
from .cmgen_peer import FACES, level_file
from .ggx_phong_mapping import MAPPINGS as PHONG_MAPPINGS
from .ggx_phong_mapping import phong_exponent

__all__ = ["ChainError", "ChainFiles", "read_chain", "check_chain", "check_lobe", "check_mapping", "mirror_x",
           "exact_levels", "compare_level", "fit_roughness", "best_mapping", "shading_rows", "judge",
           "check_out_dir", "default_out_dir", "write_report", "report_markdown", "plot_levels", "LOBES",
           "OUTPUT_FILES", "LEVEL_COLUMNS", "SHADING_COLUMNS", "REL_FLOOR", "FIREFLY_FACTOR", "SEAM_EPS",
           "SEAM_FLAG_RATIO", "SEAM_FLAG_ERROR", "SEAM_MIN_FACE", "FIT_GRID", "FIT_XTOL", "FIT_SOURCE_FACTOR",
           "DEFAULT_SHADING_ROUGHNESS"]

#: lobes a chain may hold: the split sum's n = v = r GGX kernel, or a Phong lobe (exponent from the roughness)
LOBES = ("ggx", "phong")
#: the relative error's denominator is max(exact, REL_FLOOR × the level's mean of that channel)
REL_FLOOR = 0.1
#: a firefly: a texel with a channel above FIREFLY_FACTOR × max(exact, REL_FLOOR × mean)
FIREFLY_FACTOR = 10.0
#: added to the seam ratios' numerator and denominator (a relative error of 1e-6 is float32 rounding)
SEAM_EPS = 1e-6
#: a seam is flagged at a face edge whose row and whose steps are both ≥ this × as wrong as those inside ...
SEAM_FLAG_RATIO = 3.0
#: ... on faces of at least this size (the rows and steps inside are those of its rows 1, 2 and 3) ...
SEAM_MIN_FACE = 4
#: ... and ≥ this itself (0.1 %: the exact prefilter's default tolerance, far below what a picture shows)
SEAM_FLAG_ERROR = 1e-3
#: the fit's first grid: the mirror and nine roughnesses from 0.02 to 1, geometric (ratio 1.63)
FIT_GRID = (0.0,) + tuple(float(x) for x in np.geomspace(0.02, 1.0, 9))
#: the Brent search stops at this width in ln r (0.5 % in r)
FIT_XTOL = 0.005
#: the fit reads the environment at min(N, FIT_SOURCE_FACTOR × n_ℓ)² faces
FIT_SOURCE_FACTOR = 4
#: output tile of the fit's GGX prefilters (the comparison's faces are ≤ 32² from a 4× finer source: 4 × 4 tiles
#: cost 2–5× less than the default single texels there, measured on a 256² sky with a sun)
FIT_TILE = 4
#: the declared roughness holds if the fit is within max(_R_ABS, _R_REL · declared) of it (module docstring) ...
_R_ABS, _R_REL = 0.02, 0.1
#: ... or if the declared roughness explains the level within max(_E_RTOL · rtol, _E_REL · fit error) of the fit
_E_RTOL, _E_REL = 2.0, 0.25
#: roughnesses of the sphere's GGX material
DEFAULT_SHADING_ROUGHNESS = (0.1, 0.3, 0.6)
#: largest preview face the JSON keeps per level for the figure
PREVIEW_SIZE = 16
#: the files of :func:`write_report`, the manifest last
OUTPUT_FILES = ("judge_levels.csv", "judge_shading.csv", "judge_report.md", "judge_levels.png", "judge.json")
_TOOL = "ibl-ref judge"

LEVEL_COLUMNS = [
    "level", "face_size_texels", "declared_roughness", "declared_exponent", "exact_rel_bound_max_frac",
    "exact_bound_kind", "rel_l1_frac", "rel_err_p99_frac", "rel_err_p999_frac", "rel_err_max_frac", "bias_frac",
    "energy_kept_ratio", "fitted_roughness", "fitted_exponent", "fit_status", "roughness_holds", "fit_rel_l1_frac",
    "fit_rel_l1_declared_frac", "fit_face_size_texels", "fit_source_size_texels", "fit_evaluations",
    "seam_ratio", "seam_edge_rel_err_mean_frac", "seam_interior_rel_err_mean_frac", "seam_worst_edge",
    "seam_worst_edge_ratio", "seam_worst_edge_step_ratio", "seam_flagged", "edge_jump_max_of_mean", "exact_edge_jump_max_of_mean",
    "edge_jump_ratio", "firefly_texels", "firefly_worst_ratio", "firefly_worst_texel", "fit_s"]
SHADING_COLUMNS = [
    "roughness", "phong_exponent", "level_read", "sphere_size_px", "n_pixels", "rel_l1_chain_vs_reference_frac",
    "rel_l1_exact_chain_vs_reference_frac", "rel_l1_chain_vs_exact_chain_frac", "bias_chain_vs_reference_frac",
    "bias_exact_chain_vs_reference_frac", "reference_err_estimate_frac", "reference_s"]


class ChainError(IBLError):
    """A chain the judge cannot read as a prefiltered cube-map chain (missing files, inconsistent level sizes,
    fewer than two levels, an unknown lobe or mapping)."""


# ----------------------------------------------------------------------------------------------------------------
# reading a chain
# ----------------------------------------------------------------------------------------------------------------
@dataclass
class ChainFiles:
    """A chain as read: ``levels`` (float64 cubes ``(6, n_ℓ, n_ℓ, 3)``, lab convention), ``layout`` (``"ktx"``,
    ``"dds"``, ``"cmgen-exr"``, ``"cmgen-hdr"``), ``files`` (the paths read), ``mirrored`` (un-mirrored on reading)."""

    levels: list
    layout: str
    files: list = field(default_factory=list)
    mirrored: bool = False


_LEVEL_FILE = re.compile(r"m(\d+)_(px|nx|py|ny|pz|nz)\.(exr|hdr)")


def _face_image(path: Path, ext: str, negative: str, nonfinite: str) -> np.ndarray:
    """One face file as an (H, W, 3) float64 image, radiance unchecked for OpenEXR (checked per level)."""
    if ext == "hdr":
        return read_hdr(path, negative=negative, nonfinite=nonfinite)
    img = read_exr(path)
    if img.n_colour == 1:
        return np.repeat(img.pixels[..., :1], 3, axis=-1)
    return img.pixels[..., :3]


def _read_folder(folder: Path, negative: str, nonfinite: str) -> ChainFiles:
    found = {}
    for p in folder.iterdir():
        m = _LEVEL_FILE.fullmatch(p.name)
        if m:
            found[(int(m[1]), m[2])] = p
    exts = sorted({p.suffix for p in found.values()})
    if not found:
        raise ChainError(f"{folder}: no cmgen level files (m<level>_<face>.exr or .hdr, faces "
                         f"{' '.join(FACES)}) in the folder")
    if len(exts) > 1:
        raise ChainError(f"{folder}: holds both .exr and .hdr level files; put one chain in a folder")
    ext = exts[0][1:]
    n_levels = max(lv for lv, _ in found) + 1
    files = []
    for lv in range(n_levels):
        for f in FACES:
            want = level_file(folder, lv, f).with_suffix("." + ext)
            if (lv, f) not in found:
                raise ChainError(f"{folder}: {want.name} is missing (the folder holds levels up to m{n_levels - 1})")
            files.append(want)
    levels = []
    for lv in range(n_levels):
        faces = []
        for p in files[6 * lv:6 * lv + 6]:
            img = _face_image(p, ext, negative, nonfinite)
            if img.shape[0] != img.shape[1]:
                raise ChainError(f"{p}: a {img.shape[1]}x{img.shape[0]} face; cube faces are square")
            if faces and img.shape != faces[0].shape:
                raise ChainError(f"{p}: {img.shape[1]}x{img.shape[0]}, but {files[6 * lv].name} is "
                                 f"{faces[0].shape[1]}x{faces[0].shape[0]}; the six faces of a level have one size")
            faces.append(np.asarray(img, dtype=np.float64))
        cube = envmap.convert_convention(np.stack(faces), "opengl", "openexr")
        cube, rep = apply_policy(cube, f"{folder}: level {lv}", negative=negative, nonfinite=nonfinite,
                                 weights=envmap.cube_solid_angles(cube.shape[1]), inplace=True)
        warn_repaired(rep)
        levels.append(cube)
    return ChainFiles(levels, f"cmgen-{ext}", files)


def read_chain(path, mirrored: bool = False, negative: str = "auto", nonfinite: str = "error") -> ChainFiles:
    """Read a user's chain: a folder of cmgen's per-face level files, or a KTX 1 / DDS cube map.

    Parameters
    ----------
    path : str or os.PathLike
        A folder holding ``m<ℓ>_<face>.exr`` (or ``.hdr``) for ℓ = 0 … L − 1 and faces px nx py ny pz nz, in the
        OpenGL cube-map orientation (Filament cmgen's ``--ibl-ld`` layout; :func:`ibl_ref.prefilter.cmgen_peer.level_file`),
        or a KTX 1 / DDS file (:func:`ibl_ref.environment.cube_containers.read_cube_chain`, chosen by its first
        bytes; block-compressed and 8-bit texels are refused there, one line naming the format).
    mirrored : bool
        The chain was written x-mirrored — cmgen's default (without ``--no-mirror``) negates x, so its level 0
        holds the environment at (−x, y, z) — and is mirrored back (:func:`mirror_x`) on reading.
    negative, nonfinite : str
        The radiance policy (:mod:`ibl_ref.environment.radiance_policy`).

    Returns
    -------
    ChainFiles
        ``levels`` checked by :func:`check_chain` (square faces, each level half the one before, ≥ 2 levels).

    Raises
    ------
    ChainError, EnvMapFileError
        One line naming the file: missing (level files included), unreadable, inconsistent sizes.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from ibl_ref.environment.cube_containers import write_ktx1
    >>> from ibl_ref.prefilter.judge import read_chain
    >>> folder = tempfile.TemporaryDirectory()
    >>> path = write_ktx1(os.path.join(folder.name, "chain.ktx"), [np.ones((6, 4, 4, 3)), np.ones((6, 2, 2, 3))])
    >>> chain = read_chain(path)
    >>> chain.layout, [lv.shape[1] for lv in chain.levels]
    ('ktx', [4, 2])
    >>> folder.cleanup()
    """
    p = as_path(path, "CHAIN")
    if p.is_dir():
        out = _read_folder(p, negative, nonfinite)
    elif not p.exists():
        raise EnvMapFileError(f"{p}: not found (CHAIN is a folder of cmgen level files or a .ktx / .dds file)")
    else:
        levels = read_cube_chain(p, negative, nonfinite)
        with open(p, "rb") as fh:
            layout = "dds" if fh.read(4) == b"DDS " else "ktx"
        out = ChainFiles(levels, layout, [p])
    out.levels = check_chain(out.levels, where=str(p))
    if mirrored:
        out.levels = [mirror_x(lv) for lv in out.levels]
        out.mirrored = True
    return out


def check_chain(levels, where: str = "chain") -> list:
    """The levels as float64 cubes ``(6, n_ℓ, n_ℓ, 3)``, checked: at least 2, square faces, level ℓ of face size
    max(n_0 >> ℓ, 1) (each level half the one before, as KTX, DDS and cmgen store them), finite and ≥ 0; a
    one-line :class:`ChainError` (or :class:`~ibl_ref.errors.RadianceError`) naming the level otherwise."""
    levels = [levels] if isinstance(levels, np.ndarray) and levels.ndim == 4 else list(levels)
    if len(levels) < 2:
        raise ChainError(f"{where}: holds {len(levels)} level(s); a prefiltered chain has level 0 and at least one "
                         "filtered level")
    out = []
    for k, lv in enumerate(levels):
        a = np.asarray(lv, dtype=np.float64)
        if a.ndim != 4 or a.shape[0] != 6 or a.shape[1] != a.shape[2] or a.shape[3] != 3:
            raise ChainError(f"{where}: level {k} has shape {a.shape}; expected a cube (6, n, n, 3) of square faces")
        want = max(out[0].shape[1] >> k, 1) if out else a.shape[1]
        if a.shape[1] != want:
            raise ChainError(f"{where}: level {k} has {a.shape[1]}² faces; after {out[0].shape[1]}² at level 0 it "
                             f"must have {want}² (each level half the one before)")
        a, _ = apply_policy(a, f"{where}: level {k}", negative="error", nonfinite="error")
        out.append(a)
    return out


def mirror_x(cube) -> np.ndarray:
    """The cube mirrored in x: texel d of the result holds the input's texel at (−d_x, d_y, d_z) — the mirror maps
    texel centres onto texel centres, so this is a permutation of texels (its own inverse).

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.environment.envmap import texel_directions
    >>> from ibl_ref.prefilter.judge import mirror_x
    >>> d = texel_directions(4)
    >>> bool(np.allclose(mirror_x(d), d * [-1.0, 1.0, 1.0]))
    True
    """
    a = np.asarray(cube)
    n = a.shape[1]
    face, row, col = envmap.direction_to_texel(envmap.texel_directions(n) * np.array([-1.0, 1.0, 1.0]), n)
    return a[face, row, col]


# ----------------------------------------------------------------------------------------------------------------
# the exact levels
# ----------------------------------------------------------------------------------------------------------------
def check_lobe(lobe: str) -> str:
    """``lobe`` if it is one of :data:`LOBES`; a one-line :class:`ChainError` otherwise."""
    if lobe not in LOBES:
        raise ChainError(f"lobe must be one of {', '.join(LOBES)}, got {lobe!r}")
    return lobe


def check_mapping(mapping) -> str:
    """``mapping`` if it names a mapping of :data:`~ibl_ref.prefilter.karis2013.ROUGHNESS_MAPPINGS`; a one-line
    :class:`ChainError` listing them otherwise."""
    names = tuple(karis2013.ROUGHNESS_MAPPINGS)
    if mapping not in names:
        raise ChainError(f"unknown mapping {mapping!r}; the mappings are {', '.join(names)}")
    return mapping


def _at_size(cube: np.ndarray, m: int) -> np.ndarray:
    """The cube at face size m (integral-preserving area average; the cube itself at its own size)."""
    return cube if cube.shape[1] == m else cube_to_cube(cube, m, conserve=True)


def exact_levels(env, pairs, *, lobe: str = "ggx", rtol: float = 1e-3, kernel=None, phong_mapping="tv_optimal",
                 workers=None, tile=None) -> list:
    """The exact prefilter of ``env`` at each (roughness, face size) of ``pairs``: ``[(map, rel_bound, kind)]``.

    GGX: :func:`~ibl_ref.groundtruth.ggx_convolution.convolve_ggx_levels` (one source tree for all pairs; ``kind``
    ``"rigorous"``); Phong: :func:`~ibl_ref.groundtruth.convolve.convolve` at the exponent s(r) of ``phong_mapping``,
    one call per face size (``kind`` its bound kind).  Roughness 0 is the mirror: the environment at that size, bound
    0, ``kind`` ``"source"``.  ``workers`` (Phong) and ``tile`` (GGX) steer the cost only.

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.prefilter.judge import exact_levels
    >>> [(m.shape, float(m.max()), k) for m, b, k in exact_levels(np.ones((6, 4, 4, 3)), [(0.0, 4), (0.5, 2)],
    ...                                                          kernel="numpy")]
    [((6, 4, 4, 3), 1.0, 'source'), ((6, 2, 2, 3), 1.0, 'rigorous')]
    """
    check_lobe(lobe)
    pairs = [(float(r), int(m)) for r, m in pairs]
    out = [None] * len(pairs)
    todo = []
    for k, (r, m) in enumerate(pairs):
        if r == 0.0:
            out[k] = (_at_size(env, m), np.zeros((6, m, m)), "source")
        else:
            todo.append(k)
    if todo and lobe == "ggx":
        res = convolve_ggx_levels(env, [pairs[k] for k in todo], rtol=rtol, kernel=kernel, tile=tile)
        for k, (mp, b) in zip(todo, res):
            out[k] = (mp, b, "rigorous")
    if todo and lobe == "phong":
        for m in sorted({pairs[k][1] for k in todo}):
            ks = [k for k in todo if pairs[k][1] == m]
            s = {k: float(phong_exponent(pairs[k][0], phong_mapping)) for k in ks}
            res = convolve(env, list(dict.fromkeys(s.values())), rtol=rtol, out_size=m, kernel=kernel,
                           workers=workers)
            for k in ks:
                out[k] = (res.maps[s[k]], res.error_bound[s[k]], res.bound_kind[s[k]])
    return out


# ----------------------------------------------------------------------------------------------------------------
# metrics of one level
# ----------------------------------------------------------------------------------------------------------------
def _weights(n: int) -> np.ndarray:
    return envmap.texel_solid_angles(n)[None, :, :, None]


def _rel_l1(level, exact, w) -> float | None:
    den = float(np.sum(w * exact))
    return float(np.sum(w * np.abs(level - exact)) / den) if den > 0 else None


def _texel_name(f: int, i: int, j: int) -> str:
    return f"{envmap.FACE_NAMES[f]} row {i} col {j}"


def _seams(level, exact, rel) -> dict:
    """The seam numbers of one level (module docstring)."""
    n = level.shape[1]
    out = dict(seam_ratio=None, seam_edge_rel_err_mean_frac=None, seam_interior_rel_err_mean_frac=None,
               seam_worst_edge=None, seam_worst_edge_ratio=None, seam_worst_edge_step_ratio=None, seam_flagged=False,
               edge_jump_max_of_mean=None,
               exact_edge_jump_max_of_mean=None, edge_jump_ratio=None)
    if n >= 2:
        mean = float(np.sum(_weights(n) * exact.mean(axis=-1, keepdims=True)) / (4.0 * np.pi))
        scale = mean if mean > 0 else 1.0
        jumps = []
        for a in (level, exact):
            p = pad_cube(a.mean(axis=-1), 1, "neighbour")
            jumps.append(max(float(np.max(np.abs(p[:, 0, 1:-1] - p[:, 1, 1:-1]))),
                             float(np.max(np.abs(p[:, -1, 1:-1] - p[:, -2, 1:-1]))),
                             float(np.max(np.abs(p[:, 1:-1, 0] - p[:, 1:-1, 1]))),
                             float(np.max(np.abs(p[:, 1:-1, -1] - p[:, 1:-1, -2])))))
        out.update(edge_jump_max_of_mean=jumps[0] / scale, exact_edge_jump_max_of_mean=jumps[1] / scale,
                   edge_jump_ratio=(jumps[0] / scale + SEAM_EPS) / (jumps[1] / scale + SEAM_EPS))
    if n < 3:
        return out
    t = rel.mean(axis=-1)  # (6, n, n)
    ring = np.zeros((n, n), dtype=bool)
    ring[0, :] = ring[-1, :] = ring[:, 0] = ring[:, -1] = True
    e_mean, i_mean = float(t[:, ring].mean()), float(t[:, ~ring].mean())
    out.update(seam_ratio=(e_mean + SEAM_EPS) / (i_mean + SEAM_EPS), seam_edge_rel_err_mean_frac=e_mean,
               seam_interior_rel_err_mean_frac=i_mean)
    if n < SEAM_MIN_FACE:
        return out
    # per edge: (1) the error of its row of texels against the rows 1 and 2 inside the face; (2) the error of the
    # steps between neighbouring texels, chain minus exact, across the edge (padded row 0 → 1) against those
    # between the rows 1 → 2 and 2 → 3 inside the face (not touching the edge row)
    floor = REL_FLOOR * float(np.sum(_weights(n)[..., 0] * exact.mean(axis=-1)) / (4.0 * np.pi))
    lv, ex, tp = (pad_cube(a, 1, "neighbour") for a in (level.mean(axis=-1), exact.mean(axis=-1), t))
    den = np.maximum(ex, floor) if floor > 0 else np.ones_like(ex)
    mid = slice(1, n + 1)
    nb, _ = edge_and_corner_tables(n)
    edges = []
    for side in ("top", "bottom", "left", "right"):
        pick = {"top": lambda a, k: a[:, k, mid], "bottom": lambda a, k: a[:, n + 1 - k, mid],
                "left": lambda a, k: a[:, mid, k], "right": lambda a, k: a[:, mid, n + 1 - k]}[side]

        def step(i, j):  # (6, n): |step error| between padded rows (columns) i and j, relative at i
            return np.abs((pick(lv, i) - pick(lv, j)) - (pick(ex, i) - pick(ex, j))) / pick(den, i)

        row = (pick(tp, 1).mean(axis=1) + SEAM_EPS) / (0.5 * (pick(tp, 2) + pick(tp, 3)).mean(axis=1) + SEAM_EPS)
        across = step(1, 0).mean(axis=1)
        stp = (across + SEAM_EPS) / (0.5 * (step(2, 3) + step(3, 4)).mean(axis=1) + SEAM_EPS)
        edges += [(bool(across[f] >= SEAM_FLAG_ERROR), float(min(row[f], stp[f])), float(row[f]), float(stp[f]),
                   f, side) for f in range(6)]
    big, score, row_ratio, step_ratio, f, side = max(edges)  # the worst edge whose step error is not negligible
    out.update(seam_worst_edge=f"{envmap.FACE_NAMES[f]}/{envmap.FACE_NAMES[nb[(f, side)]]}",
               seam_worst_edge_ratio=row_ratio, seam_worst_edge_step_ratio=step_ratio,
               seam_flagged=bool(big and score >= SEAM_FLAG_RATIO))
    return out


def compare_level(level, exact) -> dict:
    """Errors of one level against its exact prefilter (both ``(6, n, n, C)``): ``rel_l1_frac``,
    ``rel_err_p99_frac``, ``rel_err_p999_frac``, ``rel_err_max_frac``, ``bias_frac``, ``energy_kept_ratio``, the
    seam and firefly numbers (module docstring), and ``rel_error`` (the per-texel relative error, max over channels,
    (6, n, n)).  Undefined numbers (a black level) are None.

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.prefilter.judge import compare_level
    >>> exact = np.ones((6, 8, 8, 3))
    >>> level = exact.copy(); level[2, 3, 4] = 30.0   # one firefly
    >>> row = compare_level(level, exact)
    >>> row["firefly_texels"], row["firefly_worst_texel"], row["rel_err_max_frac"]
    (1, '+Y row 3 col 4', 29.0)
    """
    level = np.asarray(level, dtype=np.float64)
    exact = np.asarray(exact, dtype=np.float64)
    n = level.shape[1]
    w = _weights(n)
    tot_c = np.sum(w * exact, axis=(0, 1, 2))
    floor = REL_FLOOR * tot_c / (4.0 * np.pi)
    den = np.maximum(exact, floor)
    diff = level - exact
    rel = np.divide(np.abs(diff), den, out=np.zeros_like(diff), where=den > 0)
    flat = rel.ravel()
    kept = [float(np.sum(w[..., 0] * level[..., c]) / tot_c[c]) for c in range(level.shape[-1]) if tot_c[c] > 0]
    ratio = np.divide(level, den, out=np.zeros_like(level), where=den > 0)
    fire = np.any(ratio > FIREFLY_FACTOR, axis=-1)
    worst = np.unravel_index(int(np.argmax(ratio.max(axis=-1))), fire.shape)
    tot = float(tot_c.sum())
    out = dict(rel_l1_frac=_rel_l1(level, exact, w), rel_err_p99_frac=float(np.percentile(flat, 99)),
               rel_err_p999_frac=float(np.percentile(flat, 99.9)), rel_err_max_frac=float(flat.max()),
               bias_frac=float(np.sum(w * diff) / tot) if tot > 0 else None,
               energy_kept_ratio=float(np.mean(kept)) if kept else None)
    out.update(_seams(level, exact, rel))
    out.update(firefly_texels=int(fire.sum()),
               firefly_worst_ratio=float(ratio.max()) if fire.any() else None,
               firefly_worst_texel=_texel_name(*(int(x) for x in worst)) if fire.any() else None,
               rel_error=rel.max(axis=-1))
    return out


# ----------------------------------------------------------------------------------------------------------------
# fitted roughness
# ----------------------------------------------------------------------------------------------------------------
def _fit_face(n: int, fit_size: int) -> int:
    """The largest divisor of n that is ≤ fit_size."""
    return max(m for m in range(1, min(n, int(fit_size)) + 1) if n % m == 0)


def _at_centres(cube: np.ndarray, m: int) -> np.ndarray:
    """The cube read at the texel centres of m² faces (m divides n): the texel there (n/m odd) or the mean of the
    2 × 2 texels around it (n/m even: bilinear reading at the shared corner; exact in the face plane)."""
    k = cube.shape[1] // m
    if k == 1:
        return cube
    h = k // 2
    if k % 2:
        return cube[:, h::k, h::k]
    return 0.25 * (cube[:, h - 1::k, h - 1::k] + cube[:, h - 1::k, h::k] + cube[:, h::k, h - 1::k]
                   + cube[:, h::k, h::k])


def _holds(fitted, declared, err_fit, err_declared, rtol) -> str:
    if fitted is None:
        return "undetermined"
    if abs(fitted - declared) <= max(_R_ABS, _R_REL * declared):
        return "yes"
    if err_declared is not None and err_fit is not None and \
            err_declared - err_fit <= max(_E_RTOL * rtol, _E_REL * err_fit):
        return "yes"
    return "no"


def fit_roughness(level, env, *, declared=None, lobe: str = "ggx", fit_size: int = 32, rtol: float = 1e-3,
                  kernel=None, phong_mapping: str = "tv_optimal", xtol: float = FIT_XTOL) -> dict:
    """The roughness a level holds: the r minimising the rel. L1 against the exact prefilter of r (module docstring).

    Parameters
    ----------
    level : (6, n, n, C) the chain's level
    env : (6, N, N, C) the environment at the chain's base face size
    declared : the level's declared roughness (its error on the same grid is ``fit_rel_l1_declared_frac``)
    fit_size : largest face size of the comparison
    rtol : tolerance of the exact prefilters (and the fit's noise floor: 2·rtol)

    Returns
    -------
    dict
        ``fitted_roughness`` (None if undetermined), ``fitted_exponent`` (Phong), ``fit_status`` (``"ok"``,
        ``"mirror"``, ``"undetermined"``), ``fit_rel_l1_frac``, ``fit_rel_l1_declared_frac``,
        ``fit_face_size_texels``, ``fit_source_size_texels``, ``fit_evaluations``, ``fit_s``.

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.prefilter.judge import fit_roughness
    >>> fit_roughness(np.ones((6, 2, 2, 3)), np.ones((6, 4, 4, 3)), kernel="numpy")["fit_status"]
    'undetermined'
    """
    from scipy.optimize import minimize_scalar

    t0 = time.perf_counter()
    level = np.asarray(level, dtype=np.float64)
    env = np.asarray(env, dtype=np.float64)
    n, big = level.shape[1], env.shape[1]
    m = _fit_face(n, fit_size)
    s = min(big, FIT_SOURCE_FACTOR * n)
    src = _at_size(env, s)
    target = _at_centres(level, m)
    w = _weights(m)
    memo = {}

    def errors(rs):
        new = [float(r) for r in dict.fromkeys(rs) if float(r) not in memo]
        if 0.0 in new:
            memo[0.0] = _rel_l1(target, _at_centres(_at_size(env, n), m), w)
        pos = [r for r in new if r > 0]
        if pos:
            for r, (mp, _, _) in zip(pos, exact_levels(src, [(r, m) for r in pos], lobe=lobe, rtol=rtol,
                                                       kernel=kernel, phong_mapping=phong_mapping, workers=1,
                                                       tile=FIT_TILE)):
                memo[r] = _rel_l1(target, mp, w)
        return [memo[float(r)] for r in rs]

    grid = list(FIT_GRID)
    vals = errors(grid)
    out = dict(fit_face_size_texels=m, fit_source_size_texels=s, fitted_exponent=None)
    finite = [v for v in vals if v is not None]
    if not finite or max(finite) - min(finite) <= _E_RTOL * rtol:
        fitted, status = None, "undetermined"
    else:
        i = int(np.argmin([np.inf if v is None else v for v in vals]))
        if grid[i] == 0.0:
            fitted, status = 0.0, "mirror"
        else:
            lo, hi = grid[max(i - 1, 1)], grid[min(i + 1, len(grid) - 1)]
            minimize_scalar(lambda x: errors([math.exp(x)])[0], bounds=(math.log(lo), math.log(hi)),
                            method="bounded", options={"xatol": float(xtol)})
            fitted = min((r for r in memo if memo[r] is not None), key=lambda r: (memo[r], r))
            status = "mirror" if fitted == 0.0 else "ok"
    err_declared = errors([float(declared)])[0] if declared is not None else None
    if fitted is not None and lobe == "phong" and fitted > 0:
        out["fitted_exponent"] = float(phong_exponent(fitted, phong_mapping))
    out.update(fitted_roughness=fitted, fit_status=status, fit_rel_l1_frac=memo.get(fitted) if fitted is not None
               else None, fit_rel_l1_declared_frac=err_declared, fit_evaluations=len(memo),
               fit_s=time.perf_counter() - t0)
    return out


def best_mapping(fitted, n_levels: int) -> tuple:
    """``(name, mean |Δr|)`` of the mapping of :data:`~ibl_ref.prefilter.karis2013.ROUGHNESS_MAPPINGS` whose
    roughness per level is closest to ``fitted`` (a list per level, None where undetermined); ``(None, None)``
    without any fitted level.

    Examples
    --------
    >>> from ibl_ref.prefilter.judge import best_mapping
    >>> best_mapping([0.0, 1 / 3, 2 / 3, 1.0], 4)
    ('linear', 0.0)
    """
    known = [(k, r) for k, r in enumerate(fitted) if r is not None]
    if not known:
        return None, None
    best = None
    for name in tuple(karis2013.ROUGHNESS_MAPPINGS):
        want = karis2013.roughness_of_level([k for k, _ in known], n_levels, name)
        d = float(np.mean(np.abs(np.asarray(want, dtype=np.float64) - [r for _, r in known])))
        if best is None or d < best[1] - 1e-12:
            best = (name, d)
    return best


# ----------------------------------------------------------------------------------------------------------------
# the sphere
# ----------------------------------------------------------------------------------------------------------------
def _image_metrics(img, ref) -> tuple:
    y, yr = np.asarray(img).mean(axis=1), np.asarray(ref).mean(axis=1)
    den = float(np.abs(yr).sum())
    if den == 0:
        return None, None
    return float(np.abs(y - yr).sum() / den), float((y - yr).sum() / den)


def shading_rows(chain, exact_chain, env, shading, *, lobe: str = "ggx", roughness=DEFAULT_SHADING_ROUGHNESS,
                 size: int = 32, f0: float = 1.0, reference_rtol: float = 2e-3, phong_mapping: str = "tv_optimal",
                 progress: bool = False) -> list:
    """One row per roughness ρ: the sphere shaded with ``chain`` and with ``exact_chain`` (two
    :class:`~ibl_ref.prefilter.karis2013.PrefilteredChain`), each against the exact reference (module docstring).
    ``shading`` provides the pixels and the reference (``pixels(size)``, ``reference(env, lobe, param, normals,
    views, f0=, rtol=)``)."""
    normals, views = shading.pixels(int(size))
    nv = np.sum(normals * views, axis=1)
    refl = 2.0 * nv[:, None] * normals - views
    rows = []
    for rho in track(list(roughness), "sphere", unit="roughness", enabled=progress):
        t0 = time.perf_counter()
        rho = float(rho)
        if lobe == "ggx":
            weight = karis2013.split_sum(np.ones((len(nv), 1)), nv, rho, f0, None)
            param, s = rho, None
        else:
            weight, s = 1.0, float(phong_exponent(rho, phong_mapping))
            param = s
        mine, ideal = weight * chain.lookup(refl, rho), weight * exact_chain.lookup(refl, rho)
        ref, err = shading.reference(env, lobe, param, normals, views, f0=f0, rtol=reference_rtol)
        l1, bias = _image_metrics(mine, ref)
        l1x, biasx = _image_metrics(ideal, ref)
        rows.append(dict(roughness=rho, phong_exponent=s,
                         level_read=float(karis2013.level_of_roughness(rho, chain.n_levels, chain.mapping)),
                         sphere_size_px=int(size), n_pixels=len(nv), rel_l1_chain_vs_reference_frac=l1,
                         rel_l1_exact_chain_vs_reference_frac=l1x,
                         rel_l1_chain_vs_exact_chain_frac=_image_metrics(mine, ideal)[0],
                         bias_chain_vs_reference_frac=bias, bias_exact_chain_vs_reference_frac=biasx,
                         reference_err_estimate_frac=float(err), reference_s=time.perf_counter() - t0))
    return rows


# ----------------------------------------------------------------------------------------------------------------
# the judge
# ----------------------------------------------------------------------------------------------------------------
def _preview(level, exact, rel, size: int = PREVIEW_SIZE) -> dict:
    """Channel means of the level and of E (area averages), and the relative error (max over each block), at
    ≤ size² faces: what the figure shows; each row of a face one string of numbers with 3 significant digits."""
    n = level.shape[1]
    p = _fit_face(n, size)
    k = n // p

    def rows(a):
        return [[" ".join(f"{v:.3g}" for v in row) for row in face] for face in np.asarray(a, dtype=np.float64)]

    return {"face_size": p, "chain": rows(_at_size(level, p).mean(axis=-1)),
            "exact": rows(_at_size(exact, p).mean(axis=-1)),
            "rel_error": rows(rel.reshape(6, p, k, p, k).max(axis=(2, 4)))}


def _preview_array(rows) -> np.ndarray:
    """A preview cube (6, p, p) from its rows of numbers (:func:`_preview`)."""
    return np.array([[[float(x) for x in row.split()] for row in face] for face in rows], dtype=np.float64)


def _positive(v, name: str) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
        raise ChainError(f"{name} must be an integer >= 1, got {v!r}")
    return int(v)


def _versions() -> dict:
    import scipy

    from .. import __version__

    return {"ibl_ref": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__}


def judge(chain_levels, env_cube, mapping: str, lobe: str = "ggx", rtol: float = 1e-3, *, fit: bool = True,
          fit_size: int = 32, shading=None, sphere_size: int = 32, shading_roughness=DEFAULT_SHADING_ROUGHNESS,
          f0: float = 1.0, reference_rtol: float = 2e-3, phong_mapping: str = "tv_optimal", kernel=None,
          inputs: dict | None = None, progress: bool = False) -> dict:
    """Judge a prefiltered chain against the exact prefilter of its environment (module docstring).

    Parameters
    ----------
    chain_levels : list of (6, n_ℓ, n_ℓ, 3) arrays
        Level 0 first, each level half the one before (:func:`check_chain`), lab convention (:func:`read_chain`).
    env_cube : (6, N, N, 3) array
        The environment the chain was made from; resampled to the chain's base face size (integral-preserving,
        :func:`ibl_ref.environment.resample.cube_to_cube`) if it has another.
    mapping : str
        The chain's declared MIP → roughness mapping (a name of
        :data:`~ibl_ref.prefilter.karis2013.ROUGHNESS_MAPPINGS`).
    lobe : {"ggx", "phong"}
        What the levels are declared to hold; Phong: the exponent s(r) of ``phong_mapping``
        (:func:`~ibl_ref.prefilter.ggx_phong_mapping.phong_exponent`).
    rtol : float
        Tolerance of every exact prefilter (a rigorous per-texel bound for GGX).
    fit : bool
        Fit the roughness each level holds (:func:`fit_roughness`, ``fit_size``); the costly step.
    shading : object or None
        The rendering layer's sphere and exact reference (module docstring); None skips the sphere.
    sphere_size, shading_roughness, f0, reference_rtol
        The sphere (pixels across), the material roughnesses, Fresnel F0 and the reference's tolerance.
    kernel : {"auto", "numpy", "compiled"} or None
        The convolution kernels (:mod:`ibl_ref.groundtruth.kernels`).
    inputs : dict, optional
        What to record as the inputs (paths, layout), copied into the result.
    progress : bool
        Progress lines (:mod:`ibl_ref.progress`).

    Returns
    -------
    dict
        ``levels`` (rows, :data:`LEVEL_COLUMNS`), ``shading`` (rows, :data:`SHADING_COLUMNS`), ``summary``,
        ``settings``, ``inputs``, ``versions``, ``timings_s``, ``load_average_start`` / ``_end``, ``previews`` (per
        level, for the figure), and ``exact_levels`` (the exact maps, not written).

    Examples
    --------
    >>> import numpy as np
    >>> from ibl_ref.prefilter.judge import judge
    >>> env = np.full((6, 4, 4, 3), 0.5)
    >>> res = judge([env, env[:, :2, :2]], env, "filament", fit=False, kernel="numpy")
    >>> res["levels"][1]["declared_roughness"], res["levels"][1]["seam_flagged"], res["summary"]["mapping"]
    (1.0, False, 'filament')
    """
    load0, t_start = os.getloadavg(), time.perf_counter()
    fit_size, sphere_size = _positive(fit_size, "fit_size"), _positive(sphere_size, "sphere_size")
    check_lobe(lobe)
    check_mapping(mapping)
    karis2013.check_option(phong_mapping, PHONG_MAPPINGS, "phong_mapping")
    rtol = check_rtol(rtol)
    levels = check_chain(chain_levels)
    n_levels, big = len(levels), levels[0].shape[1]
    env = np.asarray(env_cube, dtype=np.float64)
    if env.ndim != 4 or env.shape[0] != 6 or env.shape[1] != env.shape[2] or env.shape[3] != levels[0].shape[3]:
        raise ChainError(f"the environment must be a cube (6, N, N, {levels[0].shape[3]}), got shape {env.shape}")
    env_size = env.shape[1]
    env = _at_size(env, big)
    rough = [float(r) for r in karis2013.roughness_of_level(np.arange(n_levels), n_levels, mapping)]
    sizes = [lv.shape[1] for lv in levels]
    timings = {}
    t0 = time.perf_counter()
    with step(f"exact {lobe} prefilter of {n_levels} level(s), {big}² … {sizes[-1]}², rtol {rtol:g}",
              enabled=progress):
        exact = exact_levels(env, list(zip(rough, sizes)), lobe=lobe, rtol=rtol, kernel=kernel,
                             phong_mapping=phong_mapping)
    timings["exact"] = time.perf_counter() - t0
    rows, previews = [], []
    for k in track(range(n_levels), "judging levels", unit="level", enabled=progress):
        t1 = time.perf_counter()
        cmp = compare_level(levels[k], exact[k][0])
        rel = cmp.pop("rel_error")
        row = dict(level=k, face_size_texels=sizes[k], declared_roughness=rough[k],
                   declared_exponent=float(phong_exponent(rough[k], phong_mapping))
                   if lobe == "phong" and rough[k] > 0 else None,
                   exact_rel_bound_max_frac=float(np.max(exact[k][1])), exact_bound_kind=exact[k][2], **cmp)
        fitted = dict(fitted_roughness=None, fitted_exponent=None, fit_status="not run", fit_rel_l1_frac=None,
                      fit_rel_l1_declared_frac=None, fit_face_size_texels=None, fit_source_size_texels=None,
                      fit_evaluations=0, fit_s=0.0)
        if fit:
            fitted.update(fit_roughness(levels[k], env, declared=rough[k], lobe=lobe, fit_size=fit_size, rtol=rtol,
                                        kernel=kernel, phong_mapping=phong_mapping))
        row.update(fitted, roughness_holds=_holds(fitted["fitted_roughness"], rough[k], fitted["fit_rel_l1_frac"],
                                                  fitted["fit_rel_l1_declared_frac"], rtol) if fit else "not fitted",
                   fit_s=fitted["fit_s"])
        rows.append({c: row.get(c) for c in LEVEL_COLUMNS})
        previews.append(_preview(levels[k], exact[k][0], rel))
        timings["levels"] = timings.get("levels", 0.0) + time.perf_counter() - t1
    shading_out = []
    if shading is not None:
        t2 = time.perf_counter()
        mine = karis2013.PrefilteredChain(levels, tuple(rough), mapping, "user chain")
        ideal = karis2013.PrefilteredChain([e[0] for e in exact], tuple(rough), mapping, "exact")
        shading_out = shading_rows(mine, ideal, env, shading, lobe=lobe, roughness=shading_roughness,
                                   size=sphere_size, f0=f0, reference_rtol=reference_rtol,
                                   phong_mapping=phong_mapping, progress=progress)
        timings["shading"] = time.perf_counter() - t2
    timings["total"] = time.perf_counter() - t_start
    best = best_mapping([r["fitted_roughness"] for r in rows], n_levels) if fit else (None, None)
    summary = dict(mapping=mapping, lobe=lobe, n_levels=n_levels, face_sizes=sizes,
                   levels_roughness_differs=[r["level"] for r in rows if r["roughness_holds"] == "no"],
                   levels_seam_flagged=[r["level"] for r in rows if r["seam_flagged"]],
                   levels_with_fireflies=[r["level"] for r in rows if r["firefly_texels"]],
                   worst_rel_l1_level=max(rows, key=lambda r: r["rel_l1_frac"] or 0.0)["level"],
                   best_fitting_mapping=best[0], best_fitting_mapping_mean_abs_dr=best[1])
    settings = dict(mapping=mapping, lobe=lobe, rtol=rtol, fit=bool(fit), fit_size=int(fit_size),
                    fit_grid=list(FIT_GRID), fit_xtol=FIT_XTOL, rel_floor=REL_FLOOR, firefly_factor=FIREFLY_FACTOR,
                    seam_eps=SEAM_EPS, seam_flag_ratio=SEAM_FLAG_RATIO, seam_flag_error=SEAM_FLAG_ERROR,
                    shading=shading is not None, sphere_size_px=int(sphere_size),
                    shading_roughness=[float(r) for r in shading_roughness], f0=float(f0),
                    reference_rtol=float(reference_rtol), phong_mapping=phong_mapping if lobe == "phong" else None,
                    kernel=kernel, teapot="skipped: a chain has no visibility; the unoccluded sphere shows what it "
                                          "changes")
    return dict(tool=_TOOL, inputs=dict(inputs or {}, env_face_size=env_size, chain_base_size=big),
                settings=settings, summary=summary, versions=_versions(), timings_s=timings,
                load_average_start=list(load0), load_average_end=list(os.getloadavg()), levels=rows,
                shading=shading_out, previews=previews, exact_levels=[e[0] for e in exact])


# ----------------------------------------------------------------------------------------------------------------
# files
# ----------------------------------------------------------------------------------------------------------------
def default_out_dir(chain) -> Path:
    """``CHAIN_judge`` beside the chain (``chain.ktx`` → ``chain_judge``, folder ``ld`` → ``ld_judge``)."""
    p = Path(chain)
    return p.with_name((p.name if p.is_dir() else p.stem) + "_judge")


def check_out_dir(out_dir) -> Path:
    """``out_dir`` if the judge may write there: new (its nearest existing parent a writable folder), or an existing
    writable folder that holds nothing but a previous judge's files (those its ``judge.json`` lists) — the judge
    never replaces or mixes with files it did not write.  A one-line :class:`~ibl_ref.atomic.OutputError` otherwise,
    before any work."""
    out = as_path(out_dir, "--out")
    if not (out.exists() or out.is_symlink()):
        anc = out.parent
        while not (anc.exists() or anc.is_symlink()) and anc != anc.parent:
            anc = anc.parent
        if not anc.is_dir():
            raise OutputError(f"--out {out}: cannot create the folder: {anc} is not a folder")
        if not os.access(anc, os.W_OK | os.X_OK):
            raise OutputError(f"--out {out}: cannot create the folder: {anc} is not writable")
        return out
    if not out.is_dir():
        raise OutputError(f"--out {out}: is a file, not a folder")
    if not os.access(out, os.W_OK | os.X_OK):
        raise OutputError(f"--out {out}: the folder is not writable")
    ours = {"judge.json"}
    manifest = out / "judge.json"
    if manifest.exists():
        try:
            data = json.loads(manifest.read_text())
        except (OSError, ValueError):
            data = None
        if not isinstance(data, dict) or not data.get(MANIFEST_MARKER) or data.get("tool") != _TOOL:
            raise OutputError(f"--out {out}: judge.json there was not written by {_TOOL}; refusing to replace it "
                              "(choose a new or empty folder)")
        ours |= {str(x) for x in data.get("outputs", [])}
    foreign = sorted(p.name for p in out.iterdir() if p.name not in ours and TEMP_TAG not in p.name)
    if foreign:
        more = f" and {len(foreign) - 1} more" if len(foreign) > 1 else ""
        raise OutputError(f"--out {out}: holds {foreign[0]}{more}, which the judge did not write; choose a new or "
                          "empty folder")
    return out


def _jsonable(result: dict) -> dict:
    """What ``judge.json`` holds (everything but the rows, which are the CSV files, and the exact maps)."""
    keep = {k: v for k, v in result.items() if k not in ("levels", "shading", "exact_levels")}
    return json.loads(json.dumps(keep, allow_nan=False))


def write_report(result: dict, out_dir, keep=()) -> list:
    """Write the judge's files into ``out_dir`` (:data:`OUTPUT_FILES`; :func:`check_out_dir` first) as one output
    set: the CSV files, the report and the figure are generated from the data as written, then committed with
    ``judge.json`` last.  ``keep``: paths never deleted (the inputs).  Returns the paths written."""
    out = check_out_dir(out_dir)
    meta = _jsonable(result)
    with OutputSet(out / "judge.json", owned_key="outputs", keep=keep, label="--out") as outs:
        lv, sh = outs.path(out / OUTPUT_FILES[0]), outs.path(out / OUTPUT_FILES[1])
        write_csv(lv, result["levels"], LEVEL_COLUMNS,
                  comment="ibl-ref judge: one row per level of the chain; *_frac are fractions, *_s seconds")
        write_csv(sh, result["shading"], SHADING_COLUMNS,
                  comment="ibl-ref judge: the orthographic sphere, one row per material roughness")
        text = report_markdown(read_csv(lv), read_csv(sh), meta)
        with atomic_write(outs.path(out / OUTPUT_FILES[2])) as fh:
            fh.write(text)
        plot_levels(read_csv(lv), meta, outs.path(out / OUTPUT_FILES[3]))
        outs.commit(dict(outputs=list(OUTPUT_FILES[:-1]), **meta))
    return [out / name for name in OUTPUT_FILES]


# ----------------------------------------------------------------------------------------------------------------
# the page and the figure: from the data alone
# ----------------------------------------------------------------------------------------------------------------
def _num(v):
    """A CSV cell as a float (None for an empty cell)."""
    if v is None or v == "" or v == "None":
        return None
    return float(v)


def _true(v) -> bool:
    """A flag of a row as written to CSV ("True") or as computed (True)."""
    return v is True or v == "True"


def _pct(v) -> str:
    return "–" if v is None else f"{100 * v:.3g} %"


def _g(v, digits: int = 3) -> str:
    return "–" if v is None else f"{v:.{digits}g}"


def _worst_edge(q: dict) -> str:
    return f" ({_g(_num(q['seam_worst_edge_ratio']))} at {q['seam_worst_edge']})" if q["seam_worst_edge"] else ""


def _level_sentences(q: dict, lobe: str) -> str:
    k, r = int(q["level"]), _num(q["declared_roughness"])
    n = int(q["face_size_texels"])
    fr = _num(q["fitted_roughness"])
    held = q["roughness_holds"]
    if q["fit_status"] in ("not run", ""):
        hold = f"declared roughness {r:.3g} (not fitted)"
    elif held == "undetermined":
        hold = f"declared roughness {r:.3g}: the environment is too flat here to tell which roughness it holds"
    elif held == "yes":
        hold = f"holds roughness {fr:.3g}, declared {r:.3g}: the declared roughness holds"
    else:
        hold = (f"holds roughness {fr:.3g}, declared {r:.3g}: **the declared roughness does not hold** (the fit "
                f"explains it with {_pct(_num(q['fit_rel_l1_frac']))} rel. L1, the declared roughness with "
                f"{_pct(_num(q['fit_rel_l1_declared_frac']))})")
    parts = [f"**Level {k}** ({n}² faces) {hold}.",
             f"Against the exact {'GGX' if lobe == 'ggx' else 'Phong'} prefilter it is {_pct(_num(q['rel_l1_frac']))}"
             f" off on average (rel. L1; 99 % of texels within {_pct(_num(q['rel_err_p99_frac']))}, the worst "
             f"{_pct(_num(q['rel_err_max_frac']))}), bias {_pct(_num(q['bias_frac']))}, and it keeps "
             f"{_pct(_num(q['energy_kept_ratio']))} of the exact energy."]
    if _true(q["seam_flagged"]):
        parts.append(f"Seams: where faces {q['seam_worst_edge']} meet, the texels along the edge are "
                     f"{_g(_num(q['seam_worst_edge_ratio']))}× as far off as the rows inside the face, and the step "
                     f"from one face to the other {_g(_num(q['seam_worst_edge_step_ratio']))}× as wrong as the steps "
                     f"inside it (over all edges, the edge texels are {_g(_num(q['seam_ratio']))}× as far off as "
                     "the face interiors).")
    if int(q["firefly_texels"] or 0):
        parts.append(f"Fireflies: {q['firefly_texels']} texel(s) more than {FIREFLY_FACTOR:g}× the exact value, the "
                     f"worst {_g(_num(q['firefly_worst_ratio']))}× at {q['firefly_worst_texel']}.")
    return " ".join(parts)


def report_markdown(level_rows, shading_rows_, meta: dict) -> str:
    """The one-page report, from the rows of ``judge_levels.csv`` / ``judge_shading.csv`` (as read back: strings;
    the rows of :func:`judge` give the same page) and the data of ``judge.json`` alone (or :func:`judge`'s result)."""
    s, st, inp = meta["summary"], meta["settings"], meta.get("inputs", {})
    lobe = st["lobe"]
    lines = [f"# Judge: {inp.get('chain', 'chain')}", ""]
    sizes = s["face_sizes"]
    lines.append(f"The chain ({inp.get('layout', 'levels')}{', un-mirrored' if inp.get('mirrored') else ''}: "
                 f"{s['n_levels']} levels, {sizes[0]}² … {sizes[-1]}²) declares mapping **{s['mapping']}** and "
                 f"the {'GGX n = v = r' if lobe == 'ggx' else 'Phong'} lobe; it is compared with the exact "
                 f"prefilter of {inp.get('env', 'its environment')} (resampled to {sizes[0]}² faces), every exact "
                 f"texel within {st['rtol']:g}.")
    lines += ["", "## In short", ""]
    differ = s["levels_roughness_differs"]
    if not st["fit"]:
        lines.append("- The roughness of the levels was not fitted.")
    elif differ:
        lines.append(f"- **The declared mapping {s['mapping']} does not hold** at level(s) "
                     f"{', '.join(map(str, differ))}.")
    else:
        lines.append(f"- The declared mapping {s['mapping']} holds at every level the fit could tell.")
    if s.get("best_fitting_mapping") is not None:
        lines.append(f"- The fitted roughnesses follow the mapping **{s['best_fitting_mapping']}** best (mean "
                     f"|Δr| {s['best_fitting_mapping_mean_abs_dr']:.3g}).")
    worst = next(q for q in level_rows if int(q["level"]) == s["worst_rel_l1_level"])
    lines.append(f"- Farthest from exact: level {worst['level']}, {_pct(_num(worst['rel_l1_frac']))} rel. L1.")
    lines.append("- Seams: " + (f"at level(s) {', '.join(map(str, s['levels_seam_flagged']))}."
                                if s["levels_seam_flagged"] else "none flagged."))
    lines.append("- Fireflies: " + (f"at level(s) {', '.join(map(str, s['levels_with_fireflies']))}."
                                    if s["levels_with_fireflies"] else "none."))
    kept = [_num(q["energy_kept_ratio"]) for q in level_rows if _num(q["energy_kept_ratio"]) is not None]
    if kept:
        lines.append(f"- Energy kept: {_pct(min(kept))} … {_pct(max(kept))} of the exact prefilter's.")
    for q in shading_rows_:
        mine, ideal = _num(q["rel_l1_chain_vs_reference_frac"]), _num(q["rel_l1_exact_chain_vs_reference_frac"])
        lines.append(f"- Sphere at roughness {_num(q['roughness']):.3g}: this chain {_pct(mine)} off the exact "
                     f"shading, the exact chain {_pct(ideal)} (the split sum's own error, its trilinear look-up "
                     f"included); the chain alone "
                     f"changes the picture by {_pct(_num(q['rel_l1_chain_vs_exact_chain_frac']))}.")
    lines += ["", "## Level by level", ""]
    lines += [_level_sentences(q, lobe) + "\n" for q in level_rows]
    lines += ["| level | face | declared r | fitted r | holds | rel. L1 | p99 | max | bias | energy | seam ratio "
              "(worst edge) | fireflies | exact bound |", "|" + "---|" * 13]
    for q in level_rows:
        lines.append(f"| {q['level']} | {q['face_size_texels']}² | {_g(_num(q['declared_roughness']))} | "
                     f"{_g(_num(q['fitted_roughness']))} | {q['roughness_holds']} | {_pct(_num(q['rel_l1_frac']))} | "
                     f"{_pct(_num(q['rel_err_p99_frac']))} | {_pct(_num(q['rel_err_max_frac']))} | "
                     f"{_pct(_num(q['bias_frac']))} | {_g(_num(q['energy_kept_ratio']), 4)} | "
                     f"{_g(_num(q['seam_ratio']))}{_worst_edge(q)} | {q['firefly_texels']} | "
                     f"{_g(_num(q['exact_rel_bound_max_frac']))} |")
    if shading_rows_:
        lines += ["", "## The sphere", "", f"Orthographic sphere, {shading_rows_[0]['sphere_size_px']} pixels across, "
                  f"F0 = {st['f0']:g}; rel. L1 of the image against the exact unoccluded shading "
                  f"(estimated within {_pct(max(_num(q['reference_err_estimate_frac']) for q in shading_rows_))}).",
                  "", "| roughness | level read | this chain | exact chain | this chain vs exact chain |",
                  "|---|---|---|---|---|"]
        for q in shading_rows_:
            lines.append(f"| {_g(_num(q['roughness']))} | {_g(_num(q['level_read']))} | "
                         f"{_pct(_num(q['rel_l1_chain_vs_reference_frac']))} | "
                         f"{_pct(_num(q['rel_l1_exact_chain_vs_reference_frac']))} | "
                         f"{_pct(_num(q['rel_l1_chain_vs_exact_chain_frac']))} |")
    else:
        lines += ["", "The sphere was not shaded."]
    lines += ["", f"The teapot: {st['teapot']}.", "",
              "Rel. L1: Σ Ω |chain − exact| / Σ Ω exact over the level's texels (Ω: solid angles). Per-texel errors "
              f"are relative to max(exact, {REL_FLOOR:g} × the level's mean). Fitted roughness: the roughness whose "
              "exact prefilter is closest to the level (rel. L1). Seam ratio: the error on the face edges over the "
              "error inside the faces (≈ 1 without seams). Definitions: `ibl_ref.prefilter.judge`; files: "
              "judge_levels.csv, judge_shading.csv, judge.json, judge_levels.png.",
              "", f"ibl_ref {meta['versions']['ibl_ref']}, {meta['timings_s']['total']:.1f} s, load average "
              f"{meta['load_average_start'][0]:.2f} → {meta['load_average_end'][0]:.2f}.", ""]
    return "\n".join(lines)


def plot_levels(level_rows, meta: dict, path) -> Path:
    """``judge_levels.png``: per level (rows) the chain, the exact prefilter (one exposure per row: the exact
    preview's 99th percentile maps to white) and the relative error (log scale, 1e-4 … 1), each as a horizontal
    cross; from the rows of ``judge_levels.csv`` and the previews of ``judge.json`` alone."""
    from ..figures import pyplot, save_figure

    plt = pyplot()
    pv = meta["previews"]
    fig, axes = plt.subplots(len(pv), 3, figsize=(9.0, 2.1 * len(pv) + 0.4), squeeze=False)
    err_im = None
    for k, (p, q) in enumerate(zip(pv, level_rows)):
        ch, ex, er = (_preview_array(p[key])[..., None] for key in ("chain", "exact", "rel_error"))
        mask = cube_to_cross(np.ones_like(ex), "hcross")[..., 0] > 0
        scale = float(np.percentile(ex, 99)) or 1.0
        for j, (a, title) in enumerate(((ch, "chain"), (ex, "exact"))):
            img = np.clip(cube_to_cross(a, "hcross")[..., 0] / scale, 0.0, 1.0) ** (1 / 2.2)
            axes[k, j].imshow(np.where(mask, img, np.nan), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
            axes[k, j].set_title(f"level {q['level']} ({q['face_size_texels']}², r {_g(_num(q['declared_roughness']))})"
                                 f": {title}", fontsize=8)
        e = np.log10(np.clip(cube_to_cross(er, "hcross")[..., 0], 1e-4, 1.0))
        err_im = axes[k, 2].imshow(np.where(mask, e, np.nan), cmap="magma", vmin=-4, vmax=0, interpolation="nearest")
        axes[k, 2].set_title(f"relative error (rel. L1 {_pct(_num(q['rel_l1_frac']))})", fontsize=8)
        for ax in axes[k]:
            ax.set_axis_off()
    cb = fig.colorbar(err_im, ax=axes[:, 2].tolist(), shrink=0.8, pad=0.02)
    cb.set_label("log10 relative error", fontsize=8)
    cb.ax.tick_params(labelsize=7)
    return save_figure(fig, path)
