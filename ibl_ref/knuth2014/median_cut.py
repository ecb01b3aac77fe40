"""Debevec (2005/2008) median cut and Viriyothai & Debevec (2009) variance cut on the six cube faces.

Knuth et al. 2014, Sec. 3.1 (Eq. 1: the regions partition the map; every region "equally important")
and Sec. 4 ("we simply apply the process to the six sides of the cube.  Therefore, the number of
generated lights is a multitude of six").

Quantities
----------
* Energy weight of a texel: ``w = Y(L) · Ω`` with the exact texel solid angle Ω
  (:func:`ibl_ref.environment.envmap.texel_solid_angles`) and the Rec. 709 luminance
  ``Y = 0.2126 R + 0.7152 G + 0.0722 B`` (:data:`REC709`).  For a one-channel map ``Y = L``; other
  channel counts need explicit ``luminance_weights``.
* Split decisions use per-face summed-area tables (SAT) of ``w``, of ``w·d`` (variance cut), of Ω
  (dark regions) and an exact integer SAT of the "lit" indicator ``w > 0`` (so "this half has no
  energy" is decided exactly, not through float cancellation of a 1e5 sun).
* Reported per-region quantities (colour, energy, solid angle, centroid) are exact sums over the
  region's texels (``np.bincount`` over the label map), not SAT differences, so
  Σ_i rgb_i = ∫L dω of the map to float rounding.

Rules (choices that change results; all documented here)
-------------------------------------------------------
* **Regions** are axis-aligned texel rectangles ``(face, row0, row1, col0, col1)`` (row1/col1
  exclusive) on one face; a region never crosses a cube edge.  Hence N ≥ 6.
* **Split axis**: the longest side *measured as an angle*: the angle between the directions through
  the midpoints of the two opposite edges of the rectangle (:func:`region_angular_extent`).  Only
  axes along which the region's lit texels occupy ≥ 2 slices are candidates (otherwise one half would
  get no energy); a dark region (no lit texel) uses any axis with ≥ 2 texels.  Equal angles (within
  1e-12 rad, e.g. symmetric squares) split the columns.
* **Median cut position** (``per-face``, ``global``): the integer texel boundary minimising the energy
  imbalance |E_a − E_b|, among boundaries leaving lit texels on both sides; ties go to the boundary
  closest to the solid-angle midpoint.  A dark region is cut at the solid-angle median.
* **Variance cut position** (``variance``): the boundary minimising Σ_h E_h·Var_h over both halves,
  with Var_h the energy-weighted variance of the unit direction, E_h·Var_h = E_h − |Σ_h w·d|²/E_h
  (Viriyothai & Debevec 2009 use the variance of position; on the sphere the direction is the
  position).
* **Which region is split next**:

  - ``per-face`` (the paper): each face gets m = N/6 regions (N must be a multiple of 6).  Debevec's
    recursion is done level by level: at each level every region of the face is split; at the last,
    partial level (m not a power of two, e.g. N = 36 → m = 6 = 4 + 2) only the most energetic
    regions are split.  For m = 2ᵏ this is exactly Debevec's recursion (N = 6, 12, 24, 48, 96, 192,
    384 …).  A face without energy is still cut into m equal-solid-angle regions (zero-power lights):
    the paper's fixed split per face spends lights on dark faces.
  - ``global``: start from the six faces and repeatedly split the most energetic region that has ≥ 2
    lit texels, until N regions.  Every region then carries energy except dark faces (one region
    each).  Needs N ≤ (lit texels) + (dark faces).
  - ``variance``: like ``global`` but the region with the largest E·Var is split, at the variance-
    minimising position.
* **Light** of a region (Debevec 2008): direction = normalised energy centroid Σ w·d / |Σ w·d| (for a
  dark region the solid-angle centroid), colour = ∫_region L dω = Σ L·Ω per channel, and the region's
  solid angle Σ Ω.
* **Overflow-safe accumulation**: a map whose maximum is outside [2^-500, 2^500] (≈ 3e-151 … 3e150)
  is scaled by an exact power of two 2^-k before any sum, so that sums of energies and their squares
  (variance cut) neither overflow nor underflow; the region energies and colours are scaled back by 2^k
  at the end.  Split decisions are unchanged by the scaling except that, for very bright maps, texels
  more than 2^-1574 times dimmer than the maximum underflow to 0 (count as dark).  If a light's colour or energy is not
  representable in float64 after scaling back (e.g. ``ones * 1e308``: ∫L dω over 1/6 of the sphere
  ≈ 2.1e308), :class:`~ibl_ref.errors.IBLError` says so instead of returning Inf.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np

from ..environment.envmap import check_cube_shape, texel_directions, texel_solid_angles, FACE_NAMES
from ..environment.validated import as_environment
from ..errors import IBLError, LayoutError
from ..limits import SizeError
from ..limits import check_allocation
from ..lobes.meunier2009 import region_equivalent_lobe

__all__ = [
    "REC709",
    "VARIANTS",
    "LightSet",
    "median_cut",
    "texel_lights",
    "luminance",
    "region_angular_extent",
    "check_partition",
    "energy_spread",
    "per_face_counts",
]

#: Rec. 709 / sRGB luminance weights (ITU-R BT.709), used for RGB maps.
REC709 = (0.2126, 0.7152, 0.0722)
VARIANTS = ("per-face", "global", "variance")


@dataclass
class LightSet:
    """Result of :func:`median_cut`.

    Attributes
    ----------
    directions : (L, 3) float64
        Unit direction of each light (energy centroid of its region).
    rgb : (L, C) float64
        ∫_region L dω per channel (radiance × sr).
    solid_angle : (L,) float64
        Solid angle (sr) of each region.
    energy : (L,) float64
        ∫_region Y dω (luminance × sr), the quantity the median cut balances.
    regions : (L, 5) int64
        ``(face, row0, row1, col0, col1)``, row1/col1 exclusive.
    labels : (6, N, N) int32
        Region index of every texel.
    variant : str
    face_size : int
    luminance_weights : tuple
    """

    directions: np.ndarray
    rgb: np.ndarray
    solid_angle: np.ndarray
    energy: np.ndarray
    regions: np.ndarray
    labels: np.ndarray
    variant: str
    face_size: int
    luminance_weights: tuple = field(default=REC709)

    def __len__(self) -> int:
        return int(self.directions.shape[0])

    @property
    def n_lights(self) -> int:
        return len(self)

    def equivalent_lobes(self):
        """Meunier et al. (2009) equivalent cosine lobe of each region (Eq. 32–34).

        The region is taken as the spherical cap of the same solid angle, ``Ω = 2π(1 − cos α)``, and the
        cap is replaced by its L2-closest unit-peak lobe ``max(a·v, 0)^e``
        (:func:`ibl_ref.lobes.meunier2009.region_equivalent_lobe`); ``scale_energy`` makes the lobe carry Ω.
        For small regions α ≈ √(Ω/π), the disc half-angle that sizes the VSM blur (docs/background.md §4).
        """

        return region_equivalent_lobe(self.solid_angle)

    def to_records(self) -> list[dict]:
        """One JSON-friendly dict per light (direction, rgb, solid_angle_sr, face, region bounds, and the
        region's equivalent cosine lobe: cap half-angle, exponent, energy scale; :meth:`equivalent_lobes`)."""
        lobes = self.equivalent_lobes()
        out = []
        for i in range(len(self)):
            f, r0, r1, c0, c1 = (int(x) for x in self.regions[i])
            out.append(
                {
                    "index": i,
                    "direction": [float(x) for x in self.directions[i]],
                    "rgb": [float(x) for x in self.rgb[i]],
                    "energy_lum_sr": float(self.energy[i]),
                    "solid_angle_sr": float(self.solid_angle[i]),
                    "face": f,
                    "face_name": FACE_NAMES[f],
                    "row0": r0,
                    "row1": r1,
                    "col0": c0,
                    "col1": c1,
                    "cap_half_angle_rad": float(lobes.alpha[i]),
                    "equivalent_lobe_exponent": float(lobes.exponent[i]),
                    "equivalent_lobe_scale": float(lobes.scale_energy[i]),
                }
            )
        return out


# ----------------------------------------------------------------------------------------------
# inputs
# ----------------------------------------------------------------------------------------------
def luminance(cube: np.ndarray, luminance_weights=None) -> np.ndarray:
    """Luminance Y of every texel.

    Parameters
    ----------
    cube : array_like, shape (6, N, N, C) or (6, N, N)
    luminance_weights : sequence of C floats, optional
        Finite, non-negative, positive sum; default :data:`REC709` for RGB, 1 for one channel (a one-channel map
        is its own luminance).

    Returns
    -------
    ndarray, float64, shape (6, N, N)

    Raises
    ------
    LayoutError
        Neither 1 nor 3 channels and no weights.
    IBLError
        Invalid weights.
    """
    cube = np.asarray(cube, dtype=np.float64)
    if cube.ndim == 3:
        return cube
    c = cube.shape[-1]
    if luminance_weights is None:
        if c == 3:
            luminance_weights = REC709
        elif c == 1:
            luminance_weights = (1.0,)
        else:
            raise LayoutError(
                f"median cut: cannot infer luminance weights for {c} channels; pass luminance_weights of length {c}"
            )
    wts = np.asarray(luminance_weights, dtype=np.float64)
    if wts.shape != (c,) or np.any(wts < 0) or not np.all(np.isfinite(wts)) or wts.sum() <= 0:
        raise IBLError(f"luminance_weights must be {c} finite non-negative numbers with a positive sum, got {luminance_weights!r}")
    return cube @ wts


def _sat(a: np.ndarray) -> np.ndarray:
    """Per-face summed-area table with a zero border: S[f, r, c] = Σ a[f, :r, :c] (extra axes kept)."""
    s = np.zeros((a.shape[0], a.shape[1] + 1, a.shape[2] + 1) + a.shape[3:], dtype=a.dtype)
    s[:, 1:, 1:] = np.cumsum(np.cumsum(a, axis=1), axis=2)
    return s


def _edge_coord(i, n):
    return -1.0 + 2.0 * np.asarray(i, dtype=np.float64) / n


def _angle_between(p, q):
    """Angle between the (unnormalised) vectors p, q (…, 3), robust for small angles."""
    cross = np.linalg.norm(np.cross(p, q), axis=-1)
    dot = np.sum(p * q, axis=-1)
    return np.arctan2(cross, dot)


def region_angular_extent(row0, row1, col0, col1, n: int):
    """Angular width (along columns) and height (along rows) of a face rectangle, radians.

    Measured as the angle between the directions through the midpoints of opposite edges: e.g. the
    width is the angle between (u0, v_mid, 1) and (u1, v_mid, 1) in face coordinates (the face
    orientation does not matter for an angle).

    Parameters
    ----------
    row0, row1, col0, col1 : int or array_like
        Texel bounds (row1, col1 exclusive).
    n : int
        Face size.

    Returns
    -------
    width, height : float64 or ndarray

    Examples
    --------
    A whole face spans 90° both ways:

    >>> import numpy as np
    >>> from ibl_ref.knuth2014.median_cut import region_angular_extent
    >>> [round(float(np.degrees(a)), 6) for a in region_angular_extent(0, 8, 0, 8, 8)]
    [90.0, 90.0]
    """
    u0, u1 = _edge_coord(col0, n), _edge_coord(col1, n)
    v0, v1 = _edge_coord(row0, n), _edge_coord(row1, n)
    um, vm = 0.5 * (u0 + u1), 0.5 * (v0 + v1)
    one = np.ones_like(um)
    width = _angle_between(np.stack([u0, vm * one, one], -1), np.stack([u1, vm * one, one], -1))
    height = _angle_between(np.stack([um * one, v0, one], -1), np.stack([um * one, v1, one], -1))
    return width, height


# ----------------------------------------------------------------------------------------------
# the cut
# ----------------------------------------------------------------------------------------------
class _Tables:
    """SATs needed for split decisions."""

    def __init__(self, w: np.ndarray, need_dirs: bool):
        n = w.shape[1]
        self.n = n
        omega = np.broadcast_to(texel_solid_angles(n), w.shape)
        self.S_w = _sat(w)
        self.S_lit = _sat((w > 0).astype(np.int64))
        self.S_om = _sat(np.ascontiguousarray(omega))
        self.S_wd = _sat(w[..., None] * texel_directions(n)) if need_dirs else None

    @staticmethod
    def _rect(S, f, r0, r1, c0, c1):
        return S[f, r1, c1] - S[f, r0, c1] - S[f, r1, c0] + S[f, r0, c0]

    def energy(self, reg):
        return float(self._rect(self.S_w, *reg))

    def lit(self, reg):
        return int(self._rect(self.S_lit, *reg))

    def omega(self, reg):
        return float(self._rect(self.S_om, *reg))

    def var_energy(self, reg):
        """E·Var of the unit direction = E − |Σ w d|²/E (0 for a dark region)."""
        e = self.energy(reg)
        if self.lit(reg) == 0 or e <= 0:
            return 0.0
        d = self._rect(self.S_wd, *reg)
        return max(e - float(d @ d) / e, 0.0)

    def prefix(self, S, reg, axis):
        """Cumulative sums over the first k slices along ``axis`` (0 = rows, 1 = cols), k = 1..len-1."""
        f, r0, r1, c0, c1 = reg
        if axis == 1:
            k = np.arange(c0 + 1, c1)
            p = S[f, r1, k] - S[f, r0, k] - S[f, r1, c0] + S[f, r0, c0]
        else:
            k = np.arange(r0 + 1, r1)
            p = S[f, k, c1] - S[f, k, c0] - S[f, r0, c1] + S[f, r0, c0]
        return k, p


def _candidate_axes(tab: _Tables, reg):
    """Axes (0 rows, 1 cols) ordered longest angle first; restricted to axes that can separate lit texels."""
    f, r0, r1, c0, c1 = reg
    width, height = region_angular_extent(r0, r1, c0, c1, tab.n)
    # ties (symmetric squares, equal to rounding) go to the column axis, independent of the last ulp
    order = [1, 0] if float(width) >= float(height) - 1e-12 else [0, 1]
    sizes = {0: r1 - r0, 1: c1 - c0}
    order = [a for a in order if sizes[a] >= 2]
    lit = tab.lit(reg)
    if lit >= 2:
        good = []
        for a in order:
            _, p = tab.prefix(tab.S_lit, reg, a)
            if np.any((p > 0) & (p < lit)):
                good.append(a)
        return good
    return order


def _split(tab: _Tables, reg, cut: str):
    """Split one region; returns two child rectangles."""
    f, r0, r1, c0, c1 = reg
    axes = _candidate_axes(tab, reg)
    if not axes:
        raise IBLError(f"internal: region {reg} cannot be split")
    axis = axes[0]
    k, lit_p = tab.prefix(tab.S_lit, reg, axis)
    _, om_p = tab.prefix(tab.S_om, reg, axis)
    om_tot = tab.omega(reg)
    lit_tot = tab.lit(reg)
    tie = np.abs(om_p - 0.5 * om_tot)  # distance to the solid-angle midpoint
    if lit_tot == 0:
        score = tie  # dark region: equal solid angle
        j = int(np.argmin(score))
    else:
        ok = (lit_p > 0) & (lit_p < lit_tot) if lit_tot >= 2 else np.ones(k.shape, bool)
        _, e_p = tab.prefix(tab.S_w, reg, axis)
        e_tot = tab.energy(reg)
        # exact zero where no lit texel is on that side (removes SAT cancellation noise)
        e_a = np.where(lit_p == 0, 0.0, np.where(lit_p == lit_tot, e_tot, e_p))
        e_b = np.where(lit_p == lit_tot, 0.0, e_tot - e_a)
        if cut == "median":
            score = np.abs(e_a - e_b)
        else:  # variance: Σ_h (E_h − |D_h|²/E_h)
            _, d_p = tab.prefix(tab.S_wd, reg, axis)
            d_tot = tab._rect(tab.S_wd, *reg)
            d_b = d_tot[None, :] - d_p
            with np.errstate(divide="ignore", invalid="ignore"):
                va = np.where(e_a > 0, e_a - np.sum(d_p * d_p, -1) / np.where(e_a > 0, e_a, 1.0), 0.0)
                vb = np.where(e_b > 0, e_b - np.sum(d_b * d_b, -1) / np.where(e_b > 0, e_b, 1.0), 0.0)
            score = va + vb
        score = np.where(ok, score, np.inf)
        j = int(np.lexsort((tie, score))[0])
    b = int(k[j])
    if axis == 1:
        return (f, r0, r1, c0, b), (f, r0, r1, b, c1)
    return (f, r0, b, c0, c1), (f, b, r1, c0, c1)


def per_face_counts(n_lights: int) -> int:
    """Regions per face m = N/6 of the ``per-face`` variant.

    Parameters
    ----------
    n_lights : int

    Returns
    -------
    int

    Raises
    ------
    IBLError
        ``n_lights`` is not a multiple of 6 (naming the two nearest that are).
    """
    if n_lights % 6:
        raise IBLError(
            f"per-face median cut gives a multiple of 6 lights (the paper's rule, Sec. 4); got {n_lights}. "
            f"Use {6 * max(1, n_lights // 6)} or {6 * (n_lights // 6 + 1)}, or variant='global'"
        )
    return n_lights // 6


def _n_texels(reg):
    return (reg[2] - reg[1]) * (reg[4] - reg[3])


def _per_face(tab: _Tables, m: int):
    regions = []
    for f in range(6):
        face = [(f, 0, tab.n, 0, tab.n)]
        while len(face) < m:
            # one level of Debevec's recursion: split every splittable region, most energetic first;
            # on the last (partial) level only as many as needed.
            cand = [i for i, r in enumerate(face) if _n_texels(r) >= 2]
            if not cand:
                raise IBLError(f"face {FACE_NAMES[f]}: cannot make {m} regions from {tab.n}x{tab.n} texels")
            cand.sort(key=lambda i: (-tab.energy(face[i]), -tab.omega(face[i]), i))
            chosen = set(cand[: m - len(face)])
            nxt = []
            for i, r in enumerate(face):
                nxt.extend(_split(tab, r, "median") if i in chosen else [r])
            face = nxt
        regions.extend(face)
    return regions


def _greedy(tab: _Tables, n_lights: int, variant: str):
    regions = [(f, 0, tab.n, 0, tab.n) for f in range(6)]
    counter = 0
    heap = []

    def push(r):
        nonlocal counter
        if tab.lit(r) >= 2:
            e = tab.energy(r)
            key = tab.var_energy(r) if variant == "variance" else e
            heapq.heappush(heap, (-key, -e, counter, r))
            counter += 1

    final = []
    for r in regions:
        if tab.lit(r) >= 2:
            push(r)
        else:
            final.append(r)
    while len(heap) + len(final) < n_lights:
        if not heap:  # pragma: no cover - excluded by the up-front count check
            raise IBLError("internal: no region left to split")
        _, _, _, r = heapq.heappop(heap)
        for child in _split(tab, r, "variance" if variant == "variance" else "median"):
            if tab.lit(child) >= 2:
                push(child)
            else:
                final.append(child)
    final.extend(item[3] for item in heap)
    return final


#: peak working memory of :func:`median_cut` per cube texel, measured with ``benchmarks/bench_probe_sizes.py``
#: (about 1.6-1.9 GB at 1024² faces, ~280 bytes per texel); checked against the machine before the cut starts
WORKING_BYTES_PER_TEXEL = 300


def median_cut(cube, n_lights: int, variant: str = "per-face", *, luminance_weights=None) -> LightSet:
    """Partition a cube map into ``n_lights`` regions and make one light per region.

    Parameters
    ----------
    cube : Environment or array_like, shape (6, N, N, C) or (6, N, N)
        Radiance, finite and non-negative, OpenEXR cube layout (:mod:`ibl_ref.environment.envmap`); checked once
        unless it is a validated :class:`~ibl_ref.environment.validated.Environment`.
    n_lights : int
        Exact number of lights returned.  ≥ 6; a multiple of 6 for ``per-face``.
    variant : {"per-face", "global", "variance"}
        See the module docstring.
    luminance_weights : sequence of C floats, optional
        Defaults to Rec. 709 for RGB.

    Returns
    -------
    LightSet
        Lights ordered by face, then by creation (``per-face``) or as produced by the greedy split.

    Raises
    ------
    LayoutError, RadianceError, IBLError
        Wrong shape; NaN/Inf/negative radiance; zero-energy map; N < 6; N not a multiple of 6
        (``per-face``); more lights than texels (``per-face``) or than lit texels + dark faces
        (``global``/``variance``).

    Examples
    --------
    Four regions per face of a sky with a sun; the regions partition the sphere (Eq. 1), so their solid angles
    sum to 4π and their colours to ∫L dω of the map:

    >>> import numpy as np
    >>> from ibl_ref.environment.resample import integral_cube
    >>> from ibl_ref.knuth2014.median_cut import median_cut
    >>> from ibl_ref.synthetic.synthetic_envs import make_environment
    >>> sky = make_environment("sky_sun", 16)
    >>> lights = median_cut(sky, 24)
    >>> len(lights), lights.directions.shape, lights.rgb.shape
    (24, (24, 3), (24, 3))
    >>> float(lights.solid_angle.sum() / np.pi)
    4.0
    >>> bool(np.allclose(lights.rgb.sum(axis=0), integral_cube(sky), rtol=1e-12))
    True
    """
    if variant not in VARIANTS:
        raise IBLError(f"unknown median-cut variant {variant!r}; choose one of {VARIANTS}")
    n = check_cube_shape(cube, "median cut input")

    try:  # the working set (summed-area tables, labels, per-variant copies), before any of it is allocated
        check_allocation(WORKING_BYTES_PER_TEXEL * 6 * n * n, f"the median cut of a {n}x{n}-face cube map",
                         "median cut input")
    except SizeError as exc:
        raise IBLError(f"{exc}; cut a smaller cube. Resample the map first (e.g. ibl_ref.environment.resample)") from None
    cube = as_environment(cube, "median cut input").data
    if isinstance(n_lights, bool) or not isinstance(n_lights, (int, np.integer)):
        raise IBLError(f"n_lights must be an integer, got {n_lights!r}")
    n_lights = int(n_lights)
    if n_lights < 6:
        raise IBLError(f"n_lights must be >= 6 (regions never cross a cube edge, so each face holds >= 1); got {n_lights}")
    k = _overflow_exponent(cube)
    if k:
        cube = np.ldexp(cube, -k)  # exact power-of-two scaling (module docstring)
    y = luminance(cube, luminance_weights)
    if np.any(y < 0):
        raise IBLError("luminance is negative somewhere (check luminance_weights)")
    omega = texel_solid_angles(n)
    w = y * omega[None]  # energy weight Y·Ω per texel
    total = float(w.sum())
    if not total > 0:
        raise IBLError("median cut: the environment map has zero energy (all luminance is 0); nothing to sample")
    n_lit = int(np.count_nonzero(w > 0))
    if variant == "per-face":
        m = per_face_counts(n_lights)
        if m > n * n:
            raise IBLError(f"per-face median cut: {m} regions per face but a face has only {n * n} texels")
    else:
        dark_faces = int(np.sum(~np.any(w > 0, axis=(1, 2))))
        if n_lights > n_lit + dark_faces:
            raise IBLError(
                f"{variant} median cut: asked for {n_lights} lights but only {n_lit} texels carry energy "
                f"(+{dark_faces} dark face(s)); every light needs at least one lit texel"
            )
    tab = _Tables(w, need_dirs=(variant == "variance"))
    regions = _per_face(tab, per_face_counts(n_lights)) if variant == "per-face" else _greedy(tab, n_lights, variant)
    if len(regions) != n_lights:  # pragma: no cover - internal invariant
        raise IBLError(f"internal: produced {len(regions)} regions instead of {n_lights}")
    ls = _lights_from_regions(cube, w, regions, variant, luminance_weights)
    if k:
        big = float(np.max(ls.rgb))
        with np.errstate(over="ignore"):
            ls.rgb, ls.energy = np.ldexp(ls.rgb, k), np.ldexp(ls.energy, k)
        if not (np.all(np.isfinite(ls.rgb)) and np.all(np.isfinite(ls.energy))):
            raise IBLError(f"median cut: a light's colour (integral of L over its region, {big:.4g} x 2^{k}) exceeds "
                           f"the largest float64 ({np.finfo(np.float64).max:.4g}); scale the map down or use more lights")
    return ls


def texel_lights(cube, *, luminance_weights=None) -> LightSet:
    """The limit of the median cut: one region (and one light) per texel, 6N² lights.

    Region j is texel j alone, so its light direction is the texel centre, its colour L_j·Ω_j and its solid
    angle Ω_j (the same :class:`LightSet` quantities as :func:`median_cut`, exact sums over the region).  With it,
    Eq. 5 with exact per-region visibility approaches the exact visibility-weighted lobe average as the texels
    shrink (``ibl_ref.rendering.error_budget``).

    Parameters
    ----------
    cube : Environment or array_like, shape (6, N, N, C) or (6, N, N)
        Radiance (checked once unless it is an :class:`~ibl_ref.environment.validated.Environment`).
    luminance_weights : sequence of C floats, optional
        As :func:`median_cut`.

    Returns
    -------
    LightSet
        6N² lights, ``variant == "texel"``.

    Raises
    ------
    LayoutError, RadianceError
        Wrong shape; NaN/Inf/negative radiance.
    """
    cube = as_environment(cube, "texel lights input").data
    n = cube.shape[1]
    k = _overflow_exponent(cube)
    scaled = np.ldexp(cube, -k) if k else cube
    w = luminance(scaled, luminance_weights) * texel_solid_angles(n)[None]
    f, r, c = np.meshgrid(np.arange(6), np.arange(n), np.arange(n), indexing="ij")
    regions = np.stack([f, r, r + 1, c, c + 1], axis=-1).reshape(-1, 5)
    ls = _lights_from_regions(scaled, w, regions, "texel", luminance_weights)
    if k:
        ls.rgb, ls.energy = np.ldexp(ls.rgb, k), np.ldexp(ls.energy, k)
    return ls


SAFE_EXPONENT = 500  #: maps brighter than 2^SAFE_EXPONENT are scaled down before summing (module docstring)


def _overflow_exponent(cube: np.ndarray) -> int:
    """k with ``cube · 2^-k`` having its maximum in [2^-SAFE_EXPONENT, 2^SAFE_EXPONENT] (0 for ordinary maps).

    k > 0 scales very bright maps down (sums overflow otherwise), k < 0 very dim ones up (squares
    underflow otherwise, e.g. in the centroid's norm).
    """
    vmax = float(np.max(cube)) if np.size(cube) else 0.0
    if vmax == 0.0 or 2.0**-SAFE_EXPONENT <= vmax <= 2.0**SAFE_EXPONENT:
        return 0
    e = int(np.frexp(vmax)[1])
    return e - SAFE_EXPONENT if e > 0 else e + SAFE_EXPONENT


def _lights_from_regions(cube, w, regions, variant, luminance_weights) -> LightSet:
    n = cube.shape[1]
    L = len(regions)
    labels = np.full((6, n, n), -1, dtype=np.int32)
    for i, (f, r0, r1, c0, c1) in enumerate(regions):
        labels[f, r0:r1, c0:c1] = i
    if np.any(labels < 0):  # pragma: no cover - internal invariant
        raise IBLError("internal: regions do not cover the map")
    lab = labels.ravel()
    omega = np.broadcast_to(texel_solid_angles(n), (6, n, n)).ravel()
    dirs = texel_directions(n).reshape(-1, 3)
    cflat = cube.reshape(6 * n * n, -1)
    wf = w.ravel()
    energy = np.bincount(lab, weights=wf, minlength=L)
    sa = np.bincount(lab, weights=omega, minlength=L)
    rgb = np.stack([np.bincount(lab, weights=cflat[:, c] * omega, minlength=L) for c in range(cflat.shape[1])], -1)
    cw = np.stack([np.bincount(lab, weights=wf * dirs[:, k], minlength=L) for k in range(3)], -1)
    cg = np.stack([np.bincount(lab, weights=omega * dirs[:, k], minlength=L) for k in range(3)], -1)
    centroid = np.where((energy > 0)[:, None], cw, cg)
    centroid = centroid / np.max(np.abs(centroid), axis=-1, keepdims=True)  # scale first: no under/overflow
    directions = centroid / np.linalg.norm(centroid, axis=-1, keepdims=True)
    lw = tuple(luminance_weights) if luminance_weights is not None else (REC709 if cflat.shape[1] == 3 else (1.0,))
    return LightSet(
        directions=directions,
        rgb=rgb,
        solid_angle=sa,
        energy=energy,
        regions=np.asarray(regions, dtype=np.int64).reshape(L, 5),
        labels=labels,
        variant=variant,
        face_size=n,
        luminance_weights=lw,
    )


# ----------------------------------------------------------------------------------------------
# checks (Eq. 1) and statistics
# ----------------------------------------------------------------------------------------------
def check_partition(lights: LightSet, cube) -> dict:
    """Residuals of the partition identities of Eq. 1.

    Parameters
    ----------
    lights : LightSet
    cube : array_like or Environment, shape (6, N, N[, C])
        The map the lights were cut from.

    Returns
    -------
    dict
        ``uncovered`` / ``overlapping`` texel counts (from the rectangles, independent of the label map),
        ``labels_match`` (label map = rectangles), and the relative errors ``rgb_sum_rel_err`` (Σ_i rgb_i vs
        ∫L dω of the map, per channel max) and ``solid_angle_sum_err`` (Σ_i Ω_i − 4π).
    """
    cube = np.asarray(cube, dtype=np.float64)
    n = lights.face_size
    count = np.zeros((6, n, n), dtype=np.int64)
    ref_labels = np.full((6, n, n), -1, dtype=np.int64)
    for i, (f, r0, r1, c0, c1) in enumerate(lights.regions):
        count[f, r0:r1, c0:c1] += 1
        ref_labels[f, r0:r1, c0:c1] = i
    omega = texel_solid_angles(n)
    c = cube if cube.ndim == 4 else cube[..., None]
    k = max(_overflow_exponent(c), _overflow_exponent(lights.rgb))  # relative errors are scale-invariant
    integral = np.einsum("fijc,ij->c", np.ldexp(c, -k), omega)
    rgb_sum = np.ldexp(lights.rgb, -k).sum(axis=0)
    denom = np.where(integral > 0, integral, 1.0)
    return {
        "uncovered": int(np.sum(count == 0)),
        "overlapping": int(np.sum(count > 1)),
        "labels_match": bool(np.array_equal(ref_labels, lights.labels)),
        "rgb_sum_rel_err": float(np.max(np.abs(rgb_sum - integral) / denom)),
        "solid_angle_sum_err": float(lights.solid_angle.sum() - 4 * np.pi),
    }


def energy_spread(lights: LightSet) -> dict:
    """How equal the region energies are (the paper's "equally important" requirement).

    Parameters
    ----------
    lights : LightSet

    Returns
    -------
    dict
        ``max_over_min`` (over regions with energy > 0), ``cv`` (standard deviation / mean of all region
        energies), ``n_zero_energy`` (regions without energy, e.g. dark faces in ``per-face``).
    """
    e = np.asarray(lights.energy, dtype=np.float64)
    e = np.ldexp(e, -_overflow_exponent(e))  # the statistics are scale-invariant; avoid overflow in std()
    pos = e[e > 0]
    return {
        "max_over_min": float(pos.max() / pos.min()) if pos.size else float("nan"),
        "cv": float(e.std() / e.mean()) if e.mean() > 0 else float("nan"),
        "n_zero_energy": int(np.sum(e <= 0)),
    }
