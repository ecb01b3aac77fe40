"""The converged reference of Knuth et al. (2014) Eq. 4–5: visibility-weighted lobe integrals to a tolerance.

The one integrator of the lab's exact reference (:mod:`ibl_ref.rendering.reference_render` renders images with it;
:func:`converged_shading` is its entry for any surface points).  Per surface point x (shading normal n, face normal
n_f, view direction v) and lobe (:mod:`ibl_ref.rendering.materials`: the one definition of the lobe weights), it
computes::

    Phong lobe (axis d = n or r, s = 1/(1−g), Eq. 3):
        A = ∫ L(ω) V(x, ω) max(d·ω, 0)^s [n·ω > 0] dω  /  ∫ max(d·ω, 0)^s dω                                  (*)
    GGX lobe (α = roughness², f_s = D·G·F / (4 (n·ω)(n·v)), :func:`ibl_ref.lobes.brdfs.ggx`):
        A = ∫ L(ω) V(x, ω) f_s(ω, v) (n·ω) [n·ω > 0] dω                                                       (**)

(*) is the lobe average of Eq. 4 with exact visibility V (docs/background.md §8: the hemisphere Ω⁺ of n clips the
numerator only, as the normalised Phong BRDF of Kán et al. 2015, Eq. 2); (**) is the one-bounce rendering equation
of the GGX specular term.  L is the map's piecewise-constant radiance (each texel constant over its exact solid
angle).  Both are computed to a requested estimated relative L1 error ``rtol`` of the image (and, per pixel, to
``pixel_rtol`` where the visibility limits it), with two discretisations:

**Quadrature** (radiance × lobe).  The integrand without V is summed at the texel centres of face sizes M (power-
of-two multiples of the visibility base level, from the level the lobe needs whatever the map's size N; where M is
coarser than N a texel's radiance L_q is the map's exact area average over it, :func:`coarse_env`, so that the
lobe and not the map sets the cost — ``n_quad_min=N`` starts at the map's texels instead):
``w_q = L_q · weight(ω_q) · Ω_q`` with the lobe's weight (the midpoint rule; a Phong lobe's normalisation Σ_q max(d·ω_q,0)^s Ω_q is the same sum over the whole sphere, so L ≡ 1 without
occluders gives exactly the share of the lobe above the horizon; a GGX lobe is normalised analytically).  Each
(pixel, base cell) pair has its own level M_pc = min(M·2^g_pc, cap): Phong lobes are radially symmetric and take
g = 0 everywhere (one M per block, ≥ 4 texels across the half width θ½); a GGX lobe is not — it depends on (n, v,
ω), has heavy tails over the whole hemisphere and a core that narrows out of the plane of incidence by the factor
n·v at grazing view — so M starts where the tails need it (as for a diffuse lobe) and each pair gets the grade g
that puts ≥ 4 texels across its local scale ℓ = w + δ/2 (w the lobe's narrowest half width at that pixel,
:meth:`ibl_ref.rendering.materials.GGXLobe.width`; δ the angle from the peak r to the nearest point of the cell:
D falls as δ⁻⁴ in the tails).  Estimate per pixel: |Σ_c V̄_c (W_c(M_pc) − W_c(M_pc/2))| over the base cells c
with their visible fractions V̄_c — the change from M_pc/2 to M_pc of the visibility-weighted value (for a smooth
integrand the error of M is ≈ ⅓ of it; where the horizon or a cell edge cuts the lobe, about it), measured per
pair, so it sees the lobe's real shape whatever its symmetry.  M doubles for the block (the cells and their rays
stay) while this change, with the base cells' rays, exceeds :data:`QUAD_SHARE` of rtol for the block or of
``pixel_rtol`` for more than :data:`QUAD_PIXEL_SHARE` of its pixels (up to ``n_quad_max``).

**Visibility** (stratified, adaptive).  The sphere is cut into cells: the six faces at a base size n_b
(≥ ``n_vis_start`` and ≥ 2 cells across the lobe's half width; for GGX the tails' width), each cell splittable 2×2
down to face size ``n_vis_max``.  A cell c carries the exact quadrature weight W_c = Σ_{q∈c} w_q (cells finer than
M split their parent's weight in proportion to the lobe's weight × Ω at their centres, × their mean radiance per
channel where they are no finer than the map) and ONE shadow ray toward a
random point of the cell (drawn uniformly in the cell, or in proportion to the map's energy L·Ω where the cell
spans several map texels, so that a sun inside a coarse cell is aimed at) — and above the pixel's shading horizon
n·ω > 0, where the weight is: a point drawn below it in a cell that the horizon cuts is drawn again (up to
:data:`HORIZON_TRIES` times, from the same density restricted to n·ω > 0), since a ray below the receiving plane is
occluded by definition and would count the cell's lit weight as shadowed; such a cell is an edge cell whatever its
ray says (the surface and what stands on it — a contact, a concave part — often occlude its lowest directions,
which a ray drawn above the horizon cannot tell).  For a GGX lobe, cells that hold more
than :data:`PRESPLIT_SHARE` of the pixel's value and are wider than half the lobe's core are split before the
search for shadow edges (the base level is set by the tails; this gives the core the ≥ 2 cells per half width that
the base level gives a Phong lobe).  The pixel's value is Σ_c W_c V_c (/ Σ w for a Phong lobe).  A cell whose ray
differs from the ray of a neighbouring cell (the 8 cells around it at its own level, across face borders; a shadow
edge passes near it) is an *edge* cell: its visible fraction q_c is unknown, its ray is an unbiased one-sample
estimate of it, with error e_c = W_c (V_c − q_c), |e_c| ≤ W_c and variance W_c² q_c (1 − q_c) ≤ W_c²/4 (q_c
measured with the density the point is drawn from, not with the lobe's weight inside the cell: a second-order
difference that shrinks as edge cells are split).  The errors of different cells are independent (independent
points), so per pixel, taking the final cells as given (weights relative to the normalisation, channel means)

    E|e| ≤ √(Σ_edge W_c² q_c(1 − q_c)) ≤ σ = ½ √(Σ_edge W_c²)      (Jensen)
    P(|e| > t σ) ≤ 2 exp(−t²/2)                                      (Hoeffding: e_c lies in an interval of length W_c)

Cells that agree with all neighbours are taken as fully lit / fully shadowed: a feature thinner than the cells
between two agreeing rays is missed, which the model does not count (hence the base level's ≥ 2 cells per lobe
half width and ``n_vis_start``; the tests measure it against finer runs).

**Refinement** (where weight × possible change is largest).  Each round splits edge cells with the largest
weights — only among each pixel's cells that hold the top :data:`SPLIT_SHARE` of its Σ W² (a cell in the last
share cannot change the pixel's σ much; splitting it now would only multiply the finest cells): for the image, the
fewest whose split is predicted (a split cell's W² shrinks ≈ 8×: four children of W/4, about half of them edges)
to bring the block's Σ E|e| below rtol·ΣA minus the quadrature estimate; for every pixel whose bound (below)
exceeds ``pixel_rtol`` × max(A, :data:`ERR_FLOOR` × mean A), its largest edge cells until its predicted bound fits
(not where the quadrature estimate alone exceeds it: that is M's job).  The child that holds its parent's point
keeps the parent's ray (it is a uniform point of the child too); the others get their own.  New children are
compared with their siblings and with the 12 cells around their 2×2 block (a neighbour that differs from a child
becomes an edge too; edge flags of older cells only grow).  The estimate falls from round to round (up to the
re-measured κ̂ below), and the loop stops when both targets are met, no wanted edge cell can be split any more (the
finest level ``n_vis_max``), or the block holds ``max_cells`` cells (the memory bound, below).  ``converged`` says
whether the image target was met; the per-pixel target is best effort (its outcome is ``err_rel_p99``).

**Reported error.**  Per pixel: ``err_mean`` = √(κ̂ Σ_edge W_c²/4) + quadrature estimate, the estimate of E|e| used
for the image's rel. L1 ``err_rel_l1`` = Σ err_mean / Σ A.  κ̂ ≤ 1 is the share of the worst-case variance the edge
cells actually carry, measured in the block on the cells split so far (each split gives an estimate of its
q(1−q) from its four children, biased high: q̂(1−q̂)·n/(n−1) of stratified points); 1 until
:data:`KAPPA_MIN_SPLITS` cells were split.  ``err_bound`` = min(Σ_edge W_c, t σ) + quadrature estimate with the
worst case σ and t = √(2 ln(2/δ)), δ = :data:`BOUND_DELTA`: a per-pixel bound that holds with probability ≥ 1 − δ,
so its 99th percentile bounds the actual error's up to a δ share of the pixels.  ``tests/test_reference_render.py``
checks both against closed forms, brute force and much finer runs.

**Several environments** (``groups`` = E > 1: a sweep, the map's channels are E environments stacked).  The cells,
their rays, the quadrature levels and the lobe's weights depend on the scene, the view and the lobe, not on the
radiance: one structure serves every environment, the texels' radiance entering the weights W_c as further
channels.  Each environment e is held to the targets on its own — the estimates above computed with its own weights
Y_e (channel mean of its group), the image target and the per-pixel targets checked for every e (the quadrature
level M doubles until every e meets its share; a round splits, for each e over its targets, the cells its own
weights pick, the image budget going to the worst e) — and its ``err_mean``, ``err_bound`` are its own.  Where
one order of the cells is needed (the pre-split of a GGX core, the order of a round's splits, the visible fraction
V̄ of a split base cell) the driving weight is Y = max_e Y_e / T_e, T_e the block's mean unoccluded value of e.
With E = 1 (T = 1) every computation is the single-environment one, bit for bit.

**Blocks, memory and determinism.**  Pixels are dealt to blocks round-robin (block b holds pixels b, b + B,
b + 2B, …, so every block is a sample of the whole image and meets the image's tolerance on its own); blocks run
independently (:func:`ibl_ref.executors.map_jobs`: serially, on local processes or any executor) and each block's
random points come from a counter-based hash of (seed, block, cell[, pixel, try]), so the image is bit-identical
wherever the blocks ran.  A block's memory is bounded whatever the environment: the refined cells are kept as
leaves of a quadtree per pixel (Morton-sorted, ~100 bytes each) and never exceed ``max_cells``
(:data:`MAX_BLOCK_CELLS`); cells are split in chunks of :data:`SPLIT_CHUNK` parents; the quadrature texels are
summed per chunk of (pair, texel) elements or texel by texel, never as whole levels
(:mod:`ibl_ref.rendering.reference_quadrature`: a NumPy and a compiled implementation, ``kernel=``); the same
switch runs the block's per-pixel sums of cell weights, its channel means and its mask of weighted pairs either as
NumPy expressions or as compiled loops that round exactly as those do (bit-identical: only the block sums depend on
the implementation).  With
``progress``, the first block runs alone and the predicted cost of the rest (rays, CPU and wall time, memory per
worker) is printed before they start.

Shadow rays: :class:`ibl_ref.rendering.raycast.ShadowRays` (Embree with a float64 check of every hit when
``embreex`` is installed, the package's float64 casters otherwise).
"""

from __future__ import annotations

import time

import numpy as np

from ..errors import IBLError, LayoutError
from ..environment.envmap import cube_solid_angles
from ..environment.envmap import direction_to_face_uv
from ..environment.envmap import face_frames
from ..environment.envmap import rect_solid_angle
from ..environment.envmap import texel_directions
from ..environment.validated import as_environment
from ..executors import map_jobs
from ..limits import check_rtol
from .materials import GGXLobe
from .materials import PhongLobe
from .raster import prepare_scene
from .raycast import ShadowRays
from .reference_quadrature import get_quadrature
from .reference_quadrature import group_means as _group_means
from .raycast import resolve_shadow_backend

__all__ = ["converged_shading", "check_environment", "radiance_at_face_size", "coarse_env", "DEFAULT_RTOL",
           "BOUND_DELTA", "ERR_FLOOR", "PIXEL_RTOL_FACTOR", "MAX_BLOCK_CELLS", "memory_bound_mb", "base_level",
           "quadrature_start"]

#: default tolerance of :func:`ibl_ref.rendering.reference_render.render_reference` (relative L1 of the image,
#: estimated)
DEFAULT_RTOL = 2e-3
#: per-pixel failure probability of ``err_bound`` (Hoeffding): t = √(2 ln(2/δ)) ≈ 3.9
BOUND_DELTA = 1e-3
#: a split cell's Σ W² is predicted to shrink by this factor (4 children of W/4, about half of them edges)
SPLIT_GAIN = 1.0 / 8.0
#: a round splits only cells among the top SPLIT_SHARE of their pixel's Σ W² (largest first)
SPLIT_SHARE = 0.95
#: a round aims at this fraction of the visibility budget (fewer rounds, a little more refinement)
ROUND_AIM = 0.7
MAX_ROUNDS = 120
#: share of rtol (and of pixel_rtol) the quadrature may take: M doubles until the M/2 → M change of the average
#: (with the base cells' visibility) is below it for the image and for all but QUAD_PIXEL_SHARE of the pixels
QUAD_SHARE = 0.5
QUAD_PIXEL_SHARE = 0.01
#: per-pixel bound: t = √(2 ln(2/δ)) standard deviations (Hoeffding)
T_BOUND = float(np.sqrt(2.0 * np.log(2.0 / BOUND_DELTA)))
#: default ``pixel_rtol`` = this × rtol (3 % at the default rtol 2e-3)
PIXEL_RTOL_FACTOR = 15.0
#: per-pixel relative errors are relative to max(pixel value, ERR_FLOOR × the image's mean value): a pixel in deep
#: shadow is held to an absolute accuracy, not to a share of its tiny value
ERR_FLOOR = 0.1
#: κ̂ is used once this many cells were split, and never below KAPPA_FLOOR
KAPPA_MIN_SPLITS = 200
KAPPA_FLOOR = 0.1
#: κ used to plan the first split, before κ̂ can be measured (the estimate itself uses 1 until then)
KAPPA_PLAN = 0.3
#: default ``max_cells``: cells (base pairs + refined leaves) of one block; with ~100 B per cell kept and ~240 B at
#: the peak of a round (split chunks), this bounds a worker's memory (docs/background.md §8: measured at the cap)
MAX_BLOCK_CELLS = 1_000_000
#: memory model of a process running blocks (measured, docs/background.md §8): Python, NumPy, trimesh, Embree and
#: the scene, the peak bytes per cell of a block, and the environment's copies (its radiance and energy per texel)
MEM_BASE_MB = 120.0
MEM_PER_CELL_B = 240.0
#: and per channel beyond three (a sweep's stacked environments: the cell's weight row, kept and in about three
#: temporaries of a split; from the array layout, not measured)
MEM_PER_CELL_CHANNEL_B = 32.0
MEM_ENV_COPIES = 6.0
#: parents split per step (bounds the temporary arrays of a round)
SPLIT_CHUNK = 1 << 16
#: draws of a cell's random point until one lies above the pixel's shading horizon
HORIZON_TRIES = 8
#: GGX core: cells holding more than this share of the pixel's value are split while wider than half the core
PRESPLIT_SHARE = 1.0 / 16.0
#: graded quadrature (GGX): texels across the local scale ℓ = w + δ/2
GRADE_TEXELS = 4.0
#: (pixel, base cell) entries of a block's look-up table of base pairs (4 bytes each; more: binary search)
FIND_TABLE_MAX = 1 << 22
_MORTON_BITS = 21  # coordinates at the finest level < 2^21 per face side
_HASH_MUL = np.uint64(0x9E3779B97F4A7C15)


# ------------------------------------------------------------------------------------------------
# environment: validation and piecewise-constant radiance on any face size
# ------------------------------------------------------------------------------------------------
def check_environment(cube) -> np.ndarray:
    """The environment of a render as validated, read-only float64 radiance (6, N, N, C): checked once
    (:func:`ibl_ref.environment.validated.as_environment`: layout, NaN/Inf/negative radiance refused with a clear
    :class:`ibl_ref.errors.RadianceError`; a (6, N, N) map gets one channel), an
    :class:`~ibl_ref.environment.validated.Environment` passed through."""

    return as_environment(cube, "environment").data


def coarse_env(cube, n_env: int) -> np.ndarray:
    """Exact area average of a cube map onto face size ``n_env`` (must divide N).

    L_coarse = Σ_f L_f Ω_f / Σ_f Ω_f over the k×k fine texels f of each coarse texel (k = N / n_env); since the
    coarse texel is exactly the union of its fine texels, L_coarse·Ω_coarse = Σ L_f Ω_f and ∫L dω is kept.
    """

    a = check_environment(cube)
    N = a.shape[1]
    n_env = int(n_env)
    if n_env < 1 or N % n_env:
        raise LayoutError(f"n_env={n_env} must divide the face size {N}")
    k = N // n_env
    om = cube_solid_angles(N)[..., None]
    num = (a * om).reshape(6, n_env, k, n_env, k, -1).sum(axis=(2, 4))
    den = om.reshape(6, n_env, k, n_env, k, 1).sum(axis=(2, 4))
    return num / den


def radiance_at_face_size(a: np.ndarray, n: int) -> np.ndarray:
    """The map's piecewise-constant radiance as exact area averages on face size n (any n ≥ 1)."""
    import math

    N = a.shape[1]
    if n % N == 0:
        k = n // N
        return np.repeat(np.repeat(a, k, axis=1), k, axis=2)
    if N % n == 0:
        return coarse_env(a, n)
    return coarse_env(radiance_at_face_size(a, N * n // math.gcd(N, n)), n)


# ------------------------------------------------------------------------------------------------
# levels
# ------------------------------------------------------------------------------------------------
def _pow2_multiples(N: int):
    """Face sizes N·2^k (k ∈ ℤ, N/2^k only while integral), ascending."""
    lo = [N]
    while lo[-1] % 2 == 0:
        lo.append(lo[-1] // 2)
    return sorted(lo)[:-1] + [N * 2 ** k for k in range(0, 16)]


def base_level(theta_half: float, N: int, n_vis_start: int = 16) -> int:
    """Visibility base face size n_b = N·2^k (k ∈ ℤ): the smallest ≥ ``n_vis_start`` with ≥ 2 cells across the lobe's
    half width ``theta_half`` (cell angle (π/2)/n_b ≤ θ½/2)."""
    need = max(float(n_vis_start), np.pi / float(theta_half))
    for n in _pow2_multiples(int(N)):
        if n >= need:
            return int(n)
    return int(N) * 2 ** 15


def quadrature_start(theta_half: float, N: int, nb: int, n_quad_min: int | None = None) -> int:
    """First quadrature face size M: a power-of-two multiple of max(n_quad_min, n_b), ≥ 2 n_b (so M/2 nests in the
    cells) and with ≥ 4 texels across the half width ``theta_half`` ((π/2)/M ≤ θ½/4).  ``n_quad_min`` None: n_b
    (a level coarser than the map reads its exact area averages; the lobe, not the map, sets the cost); N: every
    quadrature texel inside one map texel."""
    need = max(2 * nb, 2 * np.pi / float(theta_half))
    M = max(int(nb) if n_quad_min is None else int(n_quad_min), int(nb))
    while M < need:
        M *= 2
    return M


# ------------------------------------------------------------------------------------------------
# cell addressing: Morton keys, neighbours across faces, counter-based random points
# ------------------------------------------------------------------------------------------------
def _spread_table():
    t = np.arange(1 << 16, dtype=np.uint64)
    x = t
    for sh, mask in ((8, 0x00FF00FF), (4, 0x0F0F0F0F), (2, 0x33333333), (1, 0x55555555)):
        x = (x | (x << np.uint64(sh))) & np.uint64(mask)
    return x


_SPREAD16 = _spread_table()


def _spread(x):
    """Bits of x (< 2^32) moved to the even bit positions (Morton interleave), by a 16-bit table."""
    x = x.astype(np.uint64)
    return _SPREAD16[x & np.uint64(0xFFFF)] | (_SPREAD16[(x >> np.uint64(16)) & np.uint64(0xFFFF)] << np.uint64(32))


def _keys(p, f, lvl, i, j, depth):
    """Morton range start (int64) of cell (level ``lvl``, face f, row i, col j) of pixel p at the finest level."""
    sh = (depth - lvl).astype(np.uint64)
    m = (_spread(i.astype(np.uint64) << sh) << np.uint64(1)) | _spread(j.astype(np.uint64) << sh)
    return ((((p.astype(np.uint64) * np.uint64(6)) + f.astype(np.uint64)) << np.uint64(2 * _MORTON_BITS)) | m).astype(
        np.int64)


def _hash(x):
    """SplitMix64 finaliser (uint64 → uint64), vectorised."""
    with np.errstate(over="ignore"):
        x = (x + _HASH_MUL)
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return x ^ (x >> np.uint64(31))


def _uniforms(seed: int, block: int, lvl, f, i, j, k: int = 3, salt=None):
    """(K, k) uniforms in [0, 1) from a hash of (seed, block, level, face, row, col[, salt]) — a pure function of the
    cell (and of ``salt``: a pixel and a try, for points drawn again above a pixel's horizon)."""
    with np.errstate(over="ignore"):
        h = _hash(np.uint64(seed & 0xFFFFFFFF) * np.uint64(0x100000001B3) + np.uint64(block & 0xFFFFFFFF))
        c = _hash(h ^ _hash(lvl.astype(np.uint64) * np.uint64(8) + f.astype(np.uint64)))
        c = _hash(c ^ (i.astype(np.uint64) << np.uint64(32)) ^ j.astype(np.uint64))
        if salt is not None:
            c = _hash(c ^ _hash(np.asarray(salt).astype(np.uint64) + np.uint64(0xD6E8FEB86659FD93)))
        out = np.empty((len(c), k))
        for m in range(k):
            c = _hash(c + np.uint64(m + 1))
            out[:, m] = (c >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)
    return out


#: the 8 cells around a cell (row, col offsets)
_OFFS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


def _neighbours(f, i, j, n: int):
    """The 8 cells around cells (f, i, j) of face size n (rows i ↔ v, cols j ↔ u), across face borders:
    (f, i, j) arrays of shape (K, 8)."""
    di = np.array([o[0] for o in _OFFS])
    dj = np.array([o[1] for o in _OFFS])
    I = i[:, None] + di[None, :]
    F, I, J = _neighbour_of(np.broadcast_to(f[:, None], I.shape).reshape(-1), I.reshape(-1),
                            (j[:, None] + dj[None, :]).reshape(-1), np.full(I.size, n, dtype=np.int64))
    return F.reshape(-1, 8), I.reshape(-1, 8), J.reshape(-1, 8)


def _direction_to_texel_n(d, n):
    """:func:`ibl_ref.environment.envmap.direction_to_texel` with a per-direction face size ``n`` (array)."""

    face, u, v = direction_to_face_uv(d)
    col = np.clip(np.floor((u + 1.0) * 0.5 * n), 0, n - 1).astype(np.int64)
    row = np.clip(np.floor((v + 1.0) * 0.5 * n), 0, n - 1).astype(np.int64)
    return face.astype(np.int64), row, col


def _rect(i, j, n):
    """Face-plane rectangle (u0, u1, v0, v1) of cells (row i, col j) of face size n."""
    h = 2.0 / n
    return j * h - 1.0, (j + 1) * h - 1.0, i * h - 1.0, (i + 1) * h - 1.0


def _dirs(f, u, v, normalize: bool = True):
    """Directions through face-plane points (u, v) of faces f (:func:`ibl_ref.environment.envmap.face_uv_to_direction`
    without its argument checks: f, u, v are the module's own arrays)."""

    # component by component (F₀ + u F₁) + v F₂ over 1-D arrays: the values of the row-wise expression, without its
    # gather of (n, 3, 3) frames and its loops over 3-element rows
    x, y, z = ([_FRAMES_T[0, c][f] + u * _FRAMES_T[1, c][f] + v * _FRAMES_T[2, c][f] for c in range(3)])
    d = np.empty((len(x), 3))
    if normalize:
        ln = np.sqrt(x * x + y * y + z * z)
        x, y, z = x / ln, y / ln, z / ln
    d[:, 0], d[:, 1], d[:, 2] = x, y, z
    return d


#: the face frames (:func:`ibl_ref.environment.envmap.face_frames`) as [row, component, face]
_FRAMES_T = np.ascontiguousarray(face_frames("openexr").transpose(1, 2, 0))


def _dot(a, b):
    """Σ a·b over the last axis without BLAS (the same rounding in every process)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


# ------------------------------------------------------------------------------------------------
# the per-block computation
# ------------------------------------------------------------------------------------------------
class _Geom:
    """Per-pixel geometry of a block: points, shading normals n, face normals, views v, lobe axis / peak d, the
    lobe's narrowest half width w."""

    def __init__(self, lobe, P, n, fn, v):
        self.P, self.n, self.fn, self.v = P, n, fn, v
        d = lobe.direction(n, v)
        self.d = d / np.sqrt(_dot(d, d))[:, None]
        self.w = np.asarray(lobe.width(n, v, self.d), dtype=np.float64)

    def weights(self, lobe, p, w, om):
        """The lobe's weights (:meth:`ibl_ref.rendering.materials.PhongLobe.weights`) for pixels ``p`` (rows of
        ``w``, ``om``: (len(p), …, 3) and (len(p), …))."""
        ex = (slice(None),) + (None,) * (w.ndim - 2) + (slice(None),)
        return lobe.weights(self.n[p][ex], self.v[p][ex], self.d[p][ex], w, om)


class _Env:
    """The map's radiance, and texel blocks of any face size generated on demand (never a whole fine level)."""

    def __init__(self, a, nb):

        self.a = a
        self.N = a.shape[1]
        self.C = a.shape[-1]
        self.nb = nb
        om = cube_solid_angles(self.N)
        self.energy = a.mean(axis=-1).clip(min=0.0) * om  # (6, N, N): where to aim rays inside coarse cells
        self._rad = {}
        self._edges = {}

    def _edge(self, M):
        if M not in self._edges:
            self._edges[M] = np.linspace(-1.0, 1.0, M + 1)  # the texel edges of texel_solid_angles
        return self._edges[M]

    def level(self, M: int):
        """The radiance read at face size M: (array, q) with texel (R, C) of face f reading ``array[f, R // q,
        C // q]`` (the map itself where N divides M, else its exact area averages on face size M)."""
        if M % self.N == 0:
            return self.a, M // self.N
        if M not in self._rad:
            self._rad[M] = radiance_at_face_size(self.a, M)
        return self._rad[M], 1

    def texels(self, f, r0, c0, k: int, M: int):
        """Blocks of k×k texels of face size M (block b: face f[b], rows r0[b]…, cols c0[b]…, row-major inside):
        centre directions (B, k², 3), exact solid angles (B, k²), radiance (B, k², C)."""

        ar = np.arange(k)
        R = np.repeat(r0[:, None] + ar[None, :], k, axis=1)
        Cc = np.tile(c0[:, None] + ar[None, :], (1, k))
        e = self._edge(M)
        om = rect_solid_angle(e[Cc], e[Cc + 1], e[R], e[R + 1])
        F = face_frames("openexr")[f]
        u = (Cc + 0.5) / M * 2.0 - 1.0
        v = (R + 0.5) / M * 2.0 - 1.0
        d = F[:, None, 0, :] + u[..., None] * F[:, None, 1, :] + v[..., None] * F[:, None, 2, :]
        d = d / np.sqrt(_dot(d, d))[..., None]
        fb = np.broadcast_to(f[:, None], R.shape)
        rad, q = self.level(M)
        return d, om, rad[fb, R // q, Cc // q]

    def samples(self, seed, block, lvl, f, i, j, n, salt=None):
        """Random points (u, v) in cells (f, i, j) of face sizes n (arrays): uniform in the cell's face-plane square,
        or — where the cell spans several map texels — a texel drawn in proportion to its energy L·Ω first."""
        r = _uniforms(seed, block, lvl, f, i, j, 3, salt=salt)
        u0, u1, v0, v1 = _rect(i, j, n)
        fine = n >= self.N
        u = u0 + r[:, 0] * (u1 - u0)
        v = v0 + r[:, 1] * (v1 - v0)
        coarse = np.flatnonzero(~fine)
        if len(coarse):
            N = self.N
            for kk in np.unique(N // n[coarse]):
                sel = coarse[(N // n[coarse]) == kk]
                rows = (i[sel] * kk)[:, None] + np.arange(kk)[None, :]
                cols = (j[sel] * kk)[:, None] + np.arange(kk)[None, :]
                E = self.energy[f[sel][:, None, None], rows[:, :, None], cols[:, None, :]].reshape(len(sel), -1)
                tot = E.sum(axis=1)
                E = np.where(tot[:, None] > 0, E, 1.0)
                cum = np.cumsum(E, axis=1)
                t = np.minimum((r[sel, 2:3] * cum[:, -1:] >= cum).sum(axis=1), kk * kk - 1)
                a_, b_ = t // kk, t % kk
                h = 2.0 / N
                u[sel] = (j[sel] * kk + b_ + r[sel, 0]) * h - 1.0
                v[sel] = (i[sel] * kk + a_ + r[sel, 1]) * h - 1.0
        return u, v

    def above(self, seed, block, lvl, f, i, j, n, su, sv, nrm, pix):
        """The points (su, sv) of cells (lvl, f, i, j of face sizes n), with each one below its pixel's shading
        horizon (n·ω ≤ 0; ``nrm`` per point, ``pix`` its pixel) drawn again from the cell's density, salted with
        (pixel, try), up to :data:`HORIZON_TRIES` times → (su, sv, directions, redrawn mask)."""
        su, sv = su.copy(), sv.copy()
        w = _dirs(f, su, sv)
        bad = np.flatnonzero(_dot(nrm, w) <= 0)
        moved = np.zeros(len(su), bool)
        for t in range(HORIZON_TRIES):
            if len(bad) == 0:
                break
            salt = pix[bad].astype(np.uint64) * np.uint64(HORIZON_TRIES) + np.uint64(t)
            u2, v2 = self.samples(seed, block, lvl[bad], f[bad], i[bad], j[bad], n[bad], salt=salt)
            w2 = _dirs(f[bad], u2, v2)
            ok = _dot(nrm[bad], w2) > 0
            g = bad[ok]
            su[g], sv[g], w[g] = u2[ok], v2[ok], w2[ok]
            moved[g] = True
            bad = bad[~ok]
        return su, sv, w, moved


def _cut_by_horizon(f, i, j, n, nrm):
    """Cells (f, i, j) of face sizes n that the shading horizon n·ω = 0 of their pixel (``nrm`` per cell) cuts: corners
    on both sides (a cell is convex on the sphere, so its corners decide).  Such a cell is an edge whatever its ray
    says: the surface and what stands on it (contact, concave parts) often occlude its low directions, and its ray,
    drawn above the horizon, cannot tell."""
    return _cut_by_corners(_corners(f, i, j, n), nrm)


def _corners(f, i, j, n):
    """The 4 corner directions (unnormalised, (K, 3) each; (u0, v0), (u0, v1), (u1, v0), (u1, v1)) of cells (f, i, j)
    of face sizes n."""
    u0, u1, v0, v1 = _rect(i, j, n)
    return [_dirs(f, u, v, normalize=False) for u, v in ((u0, v0), (u0, v1), (u1, v0), (u1, v1))]


def _cut_by_corners(corners, nrm, rows=None):
    """:func:`_cut_by_horizon` from the cells' corner directions (:func:`_corners`), one row per ``nrm`` row; with
    ``rows`` the corners are those of cells computed once each and row k reads cell ``rows[k]`` (gathered component
    by component: the values of :func:`_dot` on gathered rows)."""
    pos = np.zeros(len(nrm), bool)
    neg = np.zeros(len(nrm), bool)
    n_ = [nrm[:, c] for c in range(3)]
    for d in corners:
        if rows is None:
            c = _dot(d, nrm)
        else:
            c = d[:, 0][rows] * n_[0] + d[:, 1][rows] * n_[1] + d[:, 2][rows] * n_[2]
        pos |= c > 0
        neg |= c < 0
    return pos & neg


def _cell_geometry(nb):
    """Centre directions (K, 3) of the base cells of face size nb and their angular radius (K,): the largest angle
    from the centre to a corner (every direction of the cell lies within it)."""

    K = 6 * nb * nb
    cells = np.arange(K)
    f, i, j = cells // (nb * nb), (cells // nb) % nb, cells % nb
    cen = np.asarray(texel_directions(nb)).reshape(-1, 3)
    u0, u1, v0, v1 = _rect(i, j, nb)
    rad = np.zeros(K)
    for u, v in ((u0, v0), (u0, v1), (u1, v0), (u1, v1)):
        rad = np.maximum(rad, np.arccos(np.clip(_dot(_dirs(f, u, v), cen), -1.0, 1.0)))
    return cen, rad * (1.0 + 1e-9) + 1e-12


def _candidates(lobe, g, cen, rad):
    """(pixel, base cell) pairs whose cell meets the lobe's support cone (ascending pixel·K + cell)."""
    ax, cut = lobe.support(g.n, g.v, g.d)
    K = len(cen)
    step = max(1, (1 << 21) // K)
    ps, cs = [], []
    for a0 in range(0, len(ax), step):
        ang = np.arccos(np.clip(_dot(ax[a0:a0 + step, None, :], cen[None, :, :]), -1.0, 1.0))
        p, c = np.nonzero(ang <= cut[a0:a0 + step, None] + rad[None, :])
        ps.append(p + a0)
        cs.append(c)
    return np.concatenate(ps).astype(np.int64), np.concatenate(cs).astype(np.int64)


def _grades(lobe, g, cp, cc, cen, rad, M0):
    """Per pair the number of doublings g ≥ 0 of the block's quadrature level that puts GRADE_TEXELS texels across
    the local scale ℓ = w + δ/2 of a non-symmetric lobe (module docstring); 0 for a Phong lobe."""
    if not lobe.presplit:
        return np.zeros(len(cp), np.int64)
    delta = np.maximum(np.arccos(np.clip(_dot(g.d[cp], cen[cc]), -1.0, 1.0)) - rad[cc], 0.0)
    ell = g.w[cp] + 0.5 * delta
    need = GRADE_TEXELS * (np.pi / 2) / ell
    return np.maximum(np.ceil(np.log2(np.maximum(need / M0, 1.0)) - 1e-9), 0).astype(np.int64)


def _pair_weights(quad, env, lobe, g, cp, cc, Mp):
    """Weights W (n, C) = Σ L·weight·Ω over the level-M texels of base cell cc of pixel cp (M = Mp per pair), and the
    normalisation Σ norm·Ω (n,) (0 for a lobe without a discrete normalisation): :mod:`ibl_ref.rendering.
    reference_quadrature`'s block sums (``quad``)."""
    nb = env.nb
    hi = int(Mp.max()) if len(Mp) else 0
    # the levels, ascending (np.unique's; a count per face size where they are small: much faster)
    levels = np.flatnonzero(np.bincount(Mp, minlength=1)) if hi <= 1 << 16 else np.unique(Mp)
    if len(levels) == 1:  # one level (a Phong lobe): the pairs in one call, no scatter into W
        M, k = int(levels[0]), int(levels[0]) // nb
        W, ns = quad.block_sums(env, lobe, g.n, g.v, g.d, cc // (nb * nb), ((cc // nb) % nb) * k, (cc % nb) * k, k, M,
                                pix=cp)
        return W, (np.zeros(len(cp)) if ns is None else ns)
    W = np.zeros((len(cp), env.C))
    ns = np.zeros(len(cp))
    for M in levels:
        sel = np.flatnonzero(Mp == M)
        k = int(M) // nb
        c_ = cc[sel]
        quad.block_sums(env, lobe, g.n, g.v, g.d, c_ // (nb * nb), ((c_ // nb) % nb) * k, (c_ % nb) * k, k, int(M),
                        pix=cp[sel], out=(W, ns), rows=sel)  # into rows sel of W, ns (ns kept 0 without a norm)
    return W, ns


def _child_weights(quad, env, lobe, g, p, f, lvl, i, j, Wpar, Mpar):
    """Weights (4K, C) of the 4 children of K parent cells (level lvl → lvl + 1), children in order (a, b) =
    (0,0), (0,1), (1,0), (1,1) per parent: exact sums of the texels of the parent's quadrature level Mpar that they
    hold, or — finer than it — the parent's weight split in proportion to the lobe's weight × Ω at their centres
    (× the child's mean radiance per channel where the children are no finer than the map's texels)."""
    nb = env.nb
    K = len(p)
    a = np.array([0, 0, 1, 1])
    b = np.array([0, 1, 0, 1])
    ci = (2 * i[:, None] + a[None, :]).reshape(-1)
    cj = (2 * j[:, None] + b[None, :]).reshape(-1)
    cl = np.repeat(lvl + 1, 4)
    cf = np.repeat(f, 4)
    cp = np.repeat(p, 4)
    Mc = np.repeat(Mpar, 4)
    n_c = nb * (2 ** cl)
    W = np.zeros((4 * K, env.C))
    ns_c = np.zeros(4 * K)  # the children's normalisations (not used: the parent's normalisation holds)
    coarse = np.flatnonzero(n_c <= Mc)
    if len(coarse):
        kcs = Mc[coarse] // n_c[coarse]
        for M, kc in sorted(set(zip(Mc[coarse].tolist(), kcs.tolist()))):
            sel = coarse[(Mc[coarse] == M) & (kcs == kc)]
            quad.block_sums(env, lobe, g.n, g.v, g.d, cf[sel], ci[sel] * kc, cj[sel] * kc, int(kc), int(M),
                            pix=cp[sel], out=(W, ns_c), rows=sel)
    fine = np.flatnonzero(n_c > Mc)
    if len(fine):
        from ..environment.envmap import rect_solid_angle

        u0, u1, v0, v1 = _rect(ci[fine], cj[fine], n_c[fine])
        om = rect_solid_angle(u0, u1, v0, v1)
        w = _dirs(cf[fine], 0.5 * (u0 + u1), 0.5 * (v0 + v1))
        _, gw = g.weights(lobe, cp[fine], w[:, None, :], om[:, None])
        g4 = np.zeros(4 * K)
        g4[fine] = gw[:, 0]
        om4 = np.zeros(4 * K)
        om4[fine] = om
        gs = g4.reshape(K, 4).sum(axis=1)
        os_ = om4.reshape(K, 4).sum(axis=1)
        ratio = np.where(gs[:, None] > 0, g4.reshape(K, 4) / np.where(gs > 0, gs, 1.0)[:, None],
                         om4.reshape(K, 4) / np.where(os_ > 0, os_, 1.0)[:, None]).reshape(-1)
        Wrep = np.repeat(Wpar, 4, axis=0)
        W[fine] = Wrep[fine] * ratio[fine, None]
        # children no finer than the map (a quadrature level coarser than the map's texels: siblings hold different
        # radiance): the share of each channel in proportion to the lobe's weight × Ω × the child's mean radiance
        for n in np.unique(n_c[fine][n_c[fine] <= env.N]):
            sub = fine[n_c[fine] == n]  # the 4 children of each such parent, together
            rad, q = env.level(int(n))
            gl = g4[sub][:, None] * rad[cf[sub], ci[sub] // q, cj[sub] // q]
            tot = gl.reshape(-1, 4, env.C).sum(axis=1)
            share = gl.reshape(-1, 4, env.C) / np.where(tot > 0, tot, 1.0)[:, None, :]
            W[sub] = np.where(np.repeat(tot > 0, 4, axis=0), Wrep[sub] * share.reshape(-1, env.C), W[sub])
    return cp, cf, cl, ci, cj, W


def _kappa(num: float, den: float, n: int) -> float:
    """κ̂: the share of the worst-case variance W²/4 that edge cells carry, measured on the cells split so far (each
    split gives a stratified estimate of its q(1−q) from its children, biased high); 1 until KAPPA_MIN_SPLITS."""
    if n < KAPPA_MIN_SPLITS or den <= 0:
        return 1.0
    return float(min(1.0, max(KAPPA_FLOOR, num / den)))


def _by_pixel(pix, P: int):
    """``np.argsort(pix, kind="stable")`` of pixel indices < P: for P ≤ 2^16 the stable argsort of them as 16-bit
    integers (the same order; NumPy sorts those by radix, several times faster)."""
    return np.argsort(pix.astype(np.uint16) if P <= 1 << 16 else pix, kind="stable")


def _worth_splitting(pix, Y, S):
    """Mask of the cells (sorted by Y descending; ``pix`` their pixels) among the top :data:`SPLIT_SHARE` of their
    pixel's Σ Y² (``S`` per pixel): the largest cell of a pixel always is."""
    o = _by_pixel(pix, len(S))  # by pixel, Y still descending inside a pixel
    pp, y2 = pix[o], Y[o] ** 2
    first = np.r_[0, np.flatnonzero(pp[1:] != pp[:-1]) + 1] if len(pp) else np.zeros(0, np.int64)
    seg = np.repeat(first, np.diff(np.r_[first, len(pp)]))
    c2 = np.cumsum(y2)
    before = c2 - y2 - (c2[seg] - y2[seg])  # Σ Y² of the pixel's larger cells
    ok = np.zeros(len(pix), bool)
    ok[o] = before < SPLIT_SHARE * S[pp]
    return ok


def _select_pixels(pix, Y, idx, need, S, strict, q, target, P):
    """Cells (``idx``, sorted by Y descending; ``pix`` their pixels) to split so that each pixel of ``need`` gets its
    predicted bound min(Σ W, t·½√ΣW²) + q below ``target``: per pixel its largest cells, fewest first."""
    want = np.zeros(P, bool)
    want[need] = True
    sel = np.flatnonzero(want[pix])
    if len(sel) == 0:
        return np.zeros(0, np.int64)
    o = sel[_by_pixel(pix[sel], P)]  # by pixel, Y still descending inside a pixel
    pp, yy = pix[o], Y[o]
    first = np.r_[0, np.flatnonzero(pp[1:] != pp[:-1]) + 1]
    seg = np.repeat(first, np.diff(np.r_[first, len(pp)]))
    c1 = np.cumsum(yy)
    c2 = np.cumsum(yy ** 2)
    done1 = c1 - (c1[seg] - yy[seg])  # Σ Y over this pixel's cells up to and including this one
    done2 = c2 - (c2[seg] - yy[seg] ** 2)
    # predicted bound after splitting the cells before this one (split cells: Σ W halves, Σ W² shrinks 8×)
    prev1, prev2 = done1 - yy, done2 - yy ** 2
    pred = np.minimum(strict[pp] - 0.5 * prev1, T_BOUND * 0.5 * np.sqrt(np.maximum(S[pp] - (1 - SPLIT_GAIN) * prev2,
                                                                                    0.0))) + q[pp]
    return idx[o[pred > target[pp]]]


def _match(keys, values, query):
    """values[keys == query] for sorted ``keys`` (0 where a query key is absent)."""
    if len(keys) == 0:
        return np.zeros(len(query))
    at = np.minimum(np.searchsorted(keys, query), len(keys) - 1)
    return np.where(keys[at] == query, values[at], 0.0)


def _select(pix, Y, S, budget, min_split, kappa=1.0):
    """How many of the cells (sorted by Y, descending) to split: the fewest whose predicted Σ_p ½√(κ S_p) ≤ budget."""
    n = len(Y)
    if n == 0:
        return 0
    P = len(S)

    def predicted(k):
        red = np.bincount(pix[:k], weights=(1.0 - SPLIT_GAIN) * Y[:k] ** 2, minlength=P)
        return 0.5 * np.sqrt(kappa * np.maximum(S - red, 0.0)).sum()

    if predicted(n) > budget:
        return n
    lo, hi = 0, n  # predicted(hi) <= budget
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if predicted(mid) <= budget:
            hi = mid
        else:
            lo = mid
    return max(hi, min(n, min_split))


_FIELDS = (("p", np.int32), ("f", np.int8), ("l", np.int8), ("i", np.int32), ("j", np.int32), ("Y", np.float64),
           ("V", np.int8), ("edge", bool), ("su", np.float64), ("sv", np.float64), ("bi", np.int32),
           ("key", np.int64))


class _Cells:
    """The refined cells of a block (descendants of split base cells; only leaves count), with a Morton-sorted
    index for region look-ups.

    Stored in slots with room to grow (appending is amortised, not a copy of every cell per split): a split cell's
    slot stays in place, marked ``dead`` (no weight, no ray: V = −1, not an edge, Y = Ye = W = 0, so that every sum
    over the slots is the sum over the leaves, in the same order), until :meth:`compact` drops the dead slots.  The
    live cells keep their relative order, as if the split cells had been removed at once, so every result is the
    one of a plain array of leaves.  ``len`` is the number of slots (the length of every array), :attr:`live` the
    number of leaves."""

    #: spare slots: capacity × this when it grows; the dead slots are dropped when they exceed this share of the live
    GROW = 1.5
    DEAD_SHARE = 0.25

    def __init__(self, C, E=1, max_slots=None):
        self.max_slots = max_slots  # capacity grows by GROW up to here (the block's cell budget), further only as needed
        self._d = {k: np.zeros(0, t) for k, t in _FIELDS}
        self._d["dead"] = np.zeros(0, bool)
        self._W = np.zeros((0, C))
        self._Ye = np.zeros((0, E))  # per environment the channel mean of W relative to ws (kept, not recomputed)
        self.n = 0
        self.live = 0
        self.order = np.zeros(0, np.int64)
        self.skeys = np.zeros(0, np.int64)

    def __len__(self):
        return self.n

    def __getitem__(self, k):
        return self._d[k][:self.n]

    @property
    def W(self):
        return self._W[:self.n]

    @property
    def Ye(self):
        return self._Ye[:self.n]

    def _reserve(self, n_new):
        cap = len(self._W)
        if self.n + n_new <= cap:
            return
        grown = int(self.GROW * cap) if self.max_slots is None else min(int(self.GROW * cap), self.max_slots)
        cap = max(self.n + n_new, grown)
        for k in self._d:
            a = np.zeros(cap, self._d[k].dtype)
            a[:self.n] = self._d[k][:self.n]
            self._d[k] = a
        for name in ("_W", "_Ye"):
            old = getattr(self, name)
            a = np.zeros((cap, old.shape[1]))
            a[:self.n] = old[:self.n]
            setattr(self, name, a)

    def replace(self, gone, new, W_new, Ye_new):
        """Mark the cells ``gone`` (indices: split) dead, append ``new`` (dict of arrays) with weights ``W_new`` and
        per-environment weights ``Ye_new`` → index of the appended cells."""
        gone = np.asarray(gone, np.int64)
        d = self._d
        d["dead"][gone] = True
        d["V"][gone] = -1
        d["edge"][gone] = False
        d["Y"][gone] = 0.0
        self._W[gone] = 0.0
        self._Ye[gone] = 0.0
        self.live -= len(gone)
        m = len(W_new)
        self._reserve(m)
        n0 = self.n
        for k, t in _FIELDS:
            d[k][n0:n0 + m] = np.asarray(new[k]).astype(t)
        d["dead"][n0:n0 + m] = False
        self._W[n0:n0 + m] = W_new
        self._Ye[n0:n0 + m] = Ye_new
        self.n += m
        self.live += m
        # the Morton index: the old slots' sorted order merged with the new cells' — the stable argsort of all keys,
        # in time linear in the slots (a new key goes after equal old ones, as the stable sort puts it)
        kn = d["key"][n0:n0 + m]
        on = np.argsort(kn, kind="stable")
        at = np.searchsorted(self.skeys, kn[on], side="right") + np.arange(m)
        is_new = np.zeros(n0 + m, bool)
        is_new[at] = True
        order = np.empty(n0 + m, np.int64)
        order[at] = n0 + on
        order[~is_new] = self.order
        self.order = order
        self.skeys = d["key"][:self.n][order]
        return np.arange(n0, self.n)

    def compact(self, force=False):
        """Drop the dead slots (where they exceed :attr:`DEAD_SHARE` of the live cells, or ``force``): the live cells
        keep their order, so nothing computed from them changes; indices do (callers look cells up again)."""
        dead = self["dead"]
        n_dead = self.n - self.live
        if n_dead == 0 or not (force or n_dead > self.DEAD_SHARE * self.live):
            return
        keep = ~dead
        for k in self._d:
            self._d[k] = self._d[k][:self.n][keep]
        self._W = self._W[:self.n][keep]
        self._Ye = self._Ye[:self.n][keep]
        ok = keep[self.order]
        renum = np.cumsum(keep) - 1
        self.order = renum[self.order[ok]]
        self.skeys = self.skeys[ok]
        self.n = self.live


def _converge_block(job: dict) -> dict:
    """One block of pixels: quadrature levels, base rays, adaptive refinement → occluded, unoccluded, errors
    (:class:`_Block`, one method per stage)."""
    return _Block(job).run()


class _Block:
    """The state of one block while it converges: set-up (:meth:`__init__`), the block's quadrature level with the
    base cells' rays (:meth:`_quadrature`), the base cells' edge flags (:meth:`_base_edges`), the splitting of cells
    (:meth:`split`), the pre-split of a GGX core (:meth:`_presplit`), the refinement rounds (:meth:`_refine`) and the
    results (:meth:`_results`)."""

    def __init__(self, job: dict):

        self.t0, self.c0 = time.perf_counter(), time.process_time()
        self.job = job
        a, self.lobe, self.rtol = job["env"], job["lobe"], float(job["rtol"])
        self.nb, self.depth = int(job["nb"]), int(job["depth"])
        self.seed, self.blk = int(job["seed"]), int(job["block"])
        self.g = _Geom(self.lobe, job["points"], job["normals"], job["face_normals"], job["views"])
        self.P_, self.nrm, self.fn = self.g.P, self.g.n, self.g.fn
        self.Pn = len(self.P_)
        self.C = a.shape[-1]
        # environments stacked as channel groups (a sweep): E groups of Cg channels, each held to the tolerance; the
        # cells are refined by the driving weight Y = max_e Y_e / T_e (module docstring, "Several environments")
        self.E = int(job.get("groups", 1))
        self.Cg = self.C // self.E
        self.T = np.ones(self.E)
        self.env = _Env(a, self.nb)
        self.quad = get_quadrature(job["kernel"])
        self.caster = ShadowRays(job["scene"], job["backend"], job["eps"])
        self.max_cells = int(job["max_cells"])
        self.prtol = float(job["pixel_rtol"])

    def run(self) -> dict:
        self._quadrature()
        self._base_edges()
        # slots: the live cells (≤ max_cells) and the dead ones (≤ DEAD_SHARE of them) of one round's splits
        self.R = _Cells(self.C, self.E, int((1.0 + _Cells.DEAD_SHARE) * self.max_cells) + 4 * SPLIT_CHUNK)
        self.st = dict(n_rays=self.n_rays, kap_num=0.0, kap_den=0.0, n_kap=0, cap_reached=False, presplit=0)
        if self.lobe.presplit:
            self._presplit()
        rounds, converged = self._refine()
        return self._results(rounds, converged)

    # ---- base cells: one random point each (drawn again above a pixel's horizon where needed) -------------------
    def _quadrature(self) -> None:
        """The block's quadrature level M: doubled (the cells and their rays stay) until the M/2 → M change with the
        base visibility is within QUAD_SHARE of rtol (module docstring); the base pairs, their weights and rays."""
        lobe, g, env, nb, Pn = self.lobe, self.g, self.env, self.nb, self.Pn
        seed, blk, rtol, prtol = self.seed, self.blk, self.rtol, self.prtol
        K = 6 * nb * nb
        cells = np.arange(K)
        cf, ci, cj = cells // (nb * nb), (cells // nb) % nb, cells % nb
        su_c, sv_c = env.samples(seed, blk, np.zeros(K, np.int64), cf, ci, cj, np.full(K, nb))
        cen, rad = _cell_geometry(nb)
        cand_p, cand_c = _candidates(lobe, g, cen, rad)
        M = int(self.job["M0"])
        cap = max(int(self.job["n_quad_max"]), M)
        grade = _grades(lobe, g, cand_p, cand_c, cen, rad, M)

        def levels(M_):
            return np.minimum(M_ * 2 ** grade, max(cap, M_))

        Wh, nsh = _pair_weights(self.quad, env, lobe, g, cand_p, cand_c, levels(M // 2))
        Wq, nsq = _pair_weights(self.quad, env, lobe, g, cand_p, cand_c, levels(M))
        vis_key = np.zeros(0, np.int64)  # (pixel·K + cell) pairs cast so far, ascending, their visibility and points
        vis_val = np.zeros(0, np.int8)
        vis_su, vis_sv = np.zeros(0), np.zeros(0)
        n_rays = 0

        def norm_sums(ns):
            if not lobe.normalised:
                return np.ones(Pn)
            w = np.bincount(cand_p, weights=ns, minlength=Pn)
            return np.where(w > 0, w, 1.0)

        first = True
        # per environment the weights of every candidate pair at M/2 and M (relative to the normalisations): a pair's
        # value depends on its own row only, so the kept pairs' rows are those of _ye over the kept pairs; after a
        # doubling, the M/2 values are those computed at M before it
        Yhe_all = self._ye(Wh, norm_sums(nsh)[cand_p])
        while True:
            keep = self.quad.positive_rows(Wq)  # Wq.mean(axis=-1) > 0
            ki = np.flatnonzero(keep)  # the kept rows, gathered by index (the rows of boolean indexing, faster)
            ws = norm_sums(nsq)
            Ye_all = self._ye(Wq, ws[cand_p])
            bp, bc = cand_p[ki], cand_c[ki]
            bkey = bp * K + bc
            bYe = Ye_all[ki]
            bYhe = Yhe_all[ki]  # the same cells at M/2
            if first and self.E > 1:  # T_e: the block's mean unoccluded value of environment e
                T = np.array([np.bincount(bp, weights=bYe[:, e], minlength=Pn).mean() if Pn else 1.0
                              for e in range(self.E)])
                self.T = np.where(T > 0, T, 1.0)
            first = False
            bY = self._crit(bYe)
            # rays for the pairs not cast yet (a finer M can give weight to a few more cells)
            known = _match(vis_key, np.ones(len(vis_key)), bkey) > 0
            new = np.flatnonzero(~known)
            if len(new):
                p_, c_ = bp[new], bc[new]
                su, sv, w, moved = env.above(seed, blk, np.zeros(len(new), np.int64), cf[c_], ci[c_], cj[c_],
                                             np.full(len(new), nb), su_c[c_], sv_c[c_], self.nrm[p_], p_)
                grp = np.where(moved, K + np.arange(len(new)), c_)  # rays toward one cell's shared point: one direction
                v_new = self.caster.visibility(self.P_[p_], self.fn[p_], w, groups=grp).astype(np.int8)
                n_rays += len(new)
                o = np.argsort(np.concatenate([vis_key, bkey[new]]), kind="stable")
                vis_key = np.concatenate([vis_key, bkey[new]])[o]
                vis_val = np.concatenate([vis_val, v_new])[o]
                vis_su = np.concatenate([vis_su, su])[o]
                vis_sv = np.concatenate([vis_sv, sv])[o]
            at = np.searchsorted(vis_key, bkey)
            bV, bsu, bsv = vis_val[at], vis_su[at], vis_sv[at]
            # quadrature estimate with the base visibility: image share ≤ QUAD_SHARE·rtol, and ≤ 1 % of the pixels
            # above QUAD_SHARE·pixel_rtol of their value, for every environment; else M doubles (the cells and their
            # rays stay)
            met = True
            A0e = self.quad.sums_by(bp, bYe, Pn, bV > 0)
            q0e = np.abs(self.quad.sums_by(bp, bYe - bYhe, Pn, bV > 0))
            for e in range(self.E):
                A0, q0 = A0e[:, e], q0e[:, e]
                over = (q0 > QUAD_SHARE * prtol * np.maximum(A0, ERR_FLOOR * A0.mean())).mean() if Pn else 0.0
                met &= bool(q0.sum() <= QUAD_SHARE * rtol * max(A0.sum(), 1e-300) and over <= QUAD_PIXEL_SHARE)
            if met or 2 * M > cap:
                break
            M = 2 * M
            Yhe_all = Ye_all
            Wq, nsq = _pair_weights(self.quad, env, lobe, g, cand_p, cand_c, levels(M))
        # the final level's weights of the kept pairs, and the unoccluded value per pixel from them
        bW = Wq.take(ki, axis=0)
        U = self.quad.sums_by(bp, bW, Pn) / ws[:, None]
        self.bM = levels(M)[ki]
        self.M, self.K, self.n_rays = M, K, n_rays
        self.cf, self.ci, self.cj = cf, ci, cj
        self.ws, self.U = ws, U
        self.bp, self.bc, self.bW, self.bkey, self.bY, self.bYe, self.bYhe = bp, bc, bW, bkey, bY, bYe, bYhe
        self.bV, self.bsu, self.bsv = bV, bsu, bsv
        self.nB = len(bp)
        self._find_table = None
        self.bdY = bYe - bYhe  # per environment the pairs' change M/2 → M (read every round)

    def find(self, p, cb):
        """index of the base pair (pixel p, base cell cb), −1 where it has no weight (a table over all (pixel,
        cell) where it is small, else a binary search of the sorted keys)"""
        nB, bkey = self.nB, self.bkey
        q_ = p * self.K + cb
        if self._find_table is None and self.Pn * self.K <= FIND_TABLE_MAX:
            self._find_table = np.full(self.Pn * self.K, -1, np.int32)
            self._find_table[bkey] = np.arange(nB)
        if self._find_table is not None:
            return self._find_table[q_]
        at_ = np.minimum(np.searchsorted(bkey, q_), max(nB - 1, 0))
        return np.where((nB > 0) & (bkey[at_] == q_), at_, -1) if nB else np.full(len(q_), -1)

    def _base_edges(self) -> None:
        """A base cell is an edge where its ray differs from a neighbour's (8 cells around it, across face borders)
        or the pixel's horizon cuts it."""
        nb, bp, bc, bV, cf, ci, cj = self.nb, self.bp, self.bc, self.bV, self.cf, self.ci, self.cj
        nF, nI, nJ = _neighbours(cf, ci, cj, nb)
        nbr = (nF * nb + nI) * nb + nJ  # (K, 8)
        if self.Pn * self.K <= FIND_TABLE_MAX:  # the neighbours' rays from a table over all (pixel, cell): −1 where none
            Vt = np.full(self.Pn * self.K, -1, np.int8)
            Vt[self.bkey] = bV
            Vn = Vt[(bp * self.K)[:, None] + nbr[bc]]
        else:
            pin = self.find(np.repeat(bp, 8), nbr[bc].reshape(-1)).reshape(-1, 8)
            Vn = np.where(pin >= 0, bV[np.maximum(pin, 0)], -1)
        differs = ((Vn >= 0) & (Vn != bV[:, None])).any(axis=1)
        # the horizon test from each base cell's corners, computed once per cell (not per pair)
        self.bedge = differs | _cut_by_corners(_corners(cf, ci, cj, np.full(self.K, nb)), self.nrm[bp], rows=bc)
        self.bsplit = np.zeros(self.nB, dtype=bool)
        self.dirty = np.zeros(self.Pn, dtype=bool)  # pixels whose cells were split since the last pixel_sums
        self._sums = None

    # ---- estimates ---------------------------------------------------------------------------------------------
    def _ye(self, W, w):
        """Per environment the channel mean of weights W (n, C) relative to the normalisations w (n,) → (n, E)
        (:meth:`ibl_ref.rendering.reference_quadrature.Quadrature.relative_means`)."""
        return self.quad.relative_means(W, self.E, w)

    def _crit(self, Ye):
        """The driving weight of cells with per-environment weights Ye (n, E): max_e Ye/T_e (Ye itself for one;
        :meth:`ibl_ref.rendering.reference_quadrature.Quadrature.max_ratio`)."""
        return Ye[:, 0] if self.E == 1 else self.quad.max_ratio(Ye, self.T)

    def quad_est(self, vb):
        """per pixel and environment |Σ_c V̄_c (Y_c(M) − Y_c(M/2))| (channel mean, relative to ws) → (Pn, E)."""
        return np.abs(self.quad.sums_by(self.bp, self.bdY, self.Pn, vb))

    def per_env(self, ub, ur):
        """Per-environment weights (n, E) of the uncertain base pairs ``ub`` and refined cells ``ur``, and of the
        lit cells per pixel: (Ye of the uncertain cells, A (Pn, E))."""
        R, Pn = self.R, self.Pn
        Rye = R.Ye
        lit_b = (self.bV > 0) & ~self.bsplit
        lit_r = R["V"] > 0
        A = self.quad.sums_by(self.bp, self.bYe, Pn, lit_b) + self.quad.sums_by(R["p"], Rye, Pn, lit_r)
        return np.concatenate([self.bYe[ub], Rye[ur]]), A

    def pixel_sums(self):
        """Per pixel and environment the lit weight A and the quadrature estimate q (:meth:`per_env`,
        :meth:`quad_est`), recomputed only for the pixels whose cells were split since the last call (a split changes
        no other pixel's cells): each pixel's sums over its own cells in the same order as over all cells, so the
        values are those of the full computation, bit for bit."""
        Pn, R, bp = self.Pn, self.R, self.bp
        if self._sums is None:
            A = self.per_env(np.zeros(0, np.int64), np.zeros(0, np.int64))[1]
            self._sums = (A, self.quad_est(self.vbar()))
            self.dirty[:] = False
            return self._sums
        D = self.dirty.copy()
        if not D.any():
            return self._sums
        self.dirty[:] = False
        dirty_sums = getattr(self.quad, "dirty_sums", None)
        if dirty_sums is not None:  # the same sums in one compiled pass (CompiledQuadrature.dirty_sums)
            A, q = self._sums
            A, q = A.copy(), q.copy()
            dirty_sums(D, bp, self.bV, self.bsplit, self.bY, self.bYe, self.bdY, R["p"], R["bi"], R["V"], R["Y"],
                       R.Ye, A, q)
            self._sums = (A, q)
            return self._sums
        ib = np.flatnonzero(D[bp])
        ir = np.flatnonzero(D[R["p"]])
        rb, rp, rv = R["bi"][ir], R["p"][ir], R["V"][ir] > 0
        vb = self.bV[ib].astype(np.float64).clip(min=0.0)
        if len(R):
            num = np.bincount(rb, weights=R["Y"][ir] * rv, minlength=self.nB)[ib]
            bY = self.bY[ib]
            vb = np.where(self.bsplit[ib], num / np.where(bY > 0, bY, 1.0), vb)
        lit_b = (self.bV[ib] > 0) & ~self.bsplit[ib]
        bpi, Rye = bp[ib], R.Ye[ir]
        A, q = self._sums
        A, q = A.copy(), q.copy()
        A[D] = (self.quad.sums_by(bpi, self.bYe[ib], Pn, lit_b) + self.quad.sums_by(rp, Rye, Pn, rv))[D]
        q[D] = np.abs(self.quad.sums_by(bpi, self.bdY[ib], Pn, vb))[D]
        self._sums = (A, q)
        return self._sums

    def vbar(self):
        """visible fraction of each base pair from its leaves."""
        R, bY = self.R, self.bY
        vb = self.bV.astype(np.float64).clip(min=0.0)
        if len(R):
            num = np.bincount(R["bi"], weights=R["Y"] * (R["V"] > 0), minlength=self.nB)
            vb = np.where(self.bsplit, num / np.where(bY > 0, bY, 1.0), vb)
        return vb

    def uncertain(self):
        R = self.R
        ub = np.flatnonzero(self.bedge & ~self.bsplit & (self.bV >= 0))
        ur = np.flatnonzero(R["edge"])
        return ub, ur, np.concatenate([self.bp[ub], R["p"][ur]]), np.concatenate([self.bY[ub], R["Y"][ur]])

    # ---- splitting -------------------------------------------------------------------------------------------------
    def split(self, bsel, rsel):
        """Split base pairs ``bsel`` and refined cells ``rsel`` (both in priority order) into 2×2 children: weights,
        points, rays, edge flags; at most up to the block's cell budget → number of cells split."""
        room = max(0, (self.max_cells - self.nB - self.R.live) // 4)
        if len(bsel) + len(rsel) > room:
            self.st["cap_reached"] = True
            take_b = min(len(bsel), room)
            bsel, rsel = bsel[:take_b], rsel[:room - take_b]
        bsel = np.asarray(bsel, np.int64)
        rsel = np.sort(np.asarray(rsel, np.int64))[::-1]  # refined cells from the highest index: lower ones stay put
        for a0 in range(0, len(bsel), SPLIT_CHUNK):
            self._split_chunk(bsel[a0:a0 + SPLIT_CHUNK], np.zeros(0, np.int64))
        for a0 in range(0, len(rsel), SPLIT_CHUNK):
            self._split_chunk(np.zeros(0, np.int64), rsel[a0:a0 + SPLIT_CHUNK])
        self.R.compact()  # indices change: the callers look the cells up again
        return len(bsel) + len(rsel)

    def _split_chunk(self, bsel, rsel):
        R, nb, bc, st, env, seed, blk = self.R, self.nb, self.bc, self.st, self.env, self.seed, self.blk
        cb_ = bc[bsel]
        par = dict(p=np.concatenate([self.bp[bsel], R["p"][rsel]]).astype(np.int64),
                   f=np.concatenate([cb_ // (nb * nb), R["f"][rsel]]).astype(np.int64),
                   l=np.concatenate([np.zeros(len(bsel), np.int64), R["l"][rsel]]).astype(np.int64),
                   i=np.concatenate([(cb_ // nb) % nb, R["i"][rsel]]).astype(np.int64),
                   j=np.concatenate([cb_ % nb, R["j"][rsel]]).astype(np.int64),
                   V=np.concatenate([self.bV[bsel], R["V"][rsel]]),
                   su=np.concatenate([self.bsu[bsel], R["su"][rsel]]),
                   sv=np.concatenate([self.bsv[bsel], R["sv"][rsel]]),
                   bi=np.concatenate([bsel, R["bi"][rsel]]).astype(np.int64))
        Wpar = np.concatenate([self.bW[bsel], R.W[rsel]])
        pedge = np.concatenate([self.bedge[bsel], R["edge"][rsel]])  # κ̂ is measured on split edge cells only
        self.bsplit[bsel] = True
        self.dirty[par["p"]] = True
        cp, cf2, cl2, ci2, cj2, cW = _child_weights(self.quad, env, self.lobe, self.g, par["p"], par["f"], par["l"], par["i"],
                                                    par["j"], Wpar, self.bM[par["bi"]])
        nc = nb * (2 ** cl2)
        cYe = self._ye(cW, self.ws[cp])
        cY = self._crit(cYe)  # the driving weight, as the base pairs' bY (with one environment: the channel mean)
        # the child holding its parent's point keeps point and ray; the others get their own (above the horizon)
        u0, u1, v0, v1 = _rect(ci2, cj2, nc)
        psu, psv = np.repeat(par["su"], 4), np.repeat(par["sv"], 4)
        inherit = (psu >= u0) & (psu < u1) & (psv >= v0) & (psv < v1)
        su2, sv2 = env.samples(seed, blk, cl2, cf2, ci2, cj2, nc)
        su2 = np.where(inherit, psu, su2)
        sv2 = np.where(inherit, psv, sv2)
        cV = np.where(inherit, np.repeat(par["V"], 4), -1).astype(np.int8)
        relevant = cY > 0
        cast = np.flatnonzero(relevant & ~inherit)
        if len(cast):
            su_, sv_, w, moved = env.above(seed, blk, cl2[cast], cf2[cast], ci2[cast], cj2[cast], nc[cast],
                                           su2[cast], sv2[cast], self.nrm[cp[cast]], cp[cast])
            su2[cast], sv2[cast] = su_, sv_
            grp = None
            if self.caster.backend == "exact":  # rays toward one cell share their direction: one projection set-up
                ck = _keys(np.zeros(len(cast), np.int64), cf2[cast], cl2[cast], ci2[cast], cj2[cast], self.depth)
                grp = np.unique(ck, return_inverse=True)[1]
                grp = np.where(moved, grp.max() + 1 + np.arange(len(cast)), grp)
            cV[cast] = self.caster.visibility(self.P_[cp[cast]], self.fn[cp[cast]], w, groups=grp)
            st["n_rays"] += len(cast)
        cV[~relevant] = -1
        # siblings: a child differing from one of its three siblings is an edge
        v4 = cV.reshape(-1, 4)
        nrel = (v4 >= 0).sum(axis=1)
        ok = (nrel >= 2) & pedge  # a pre-split cell that agreed with its neighbours would dilute κ̂
        if ok.any():
            qh = (v4 > 0).sum(axis=1)[ok] / nrel[ok]
            wp = (Wpar.mean(axis=-1) / self.ws[par["p"]])[ok] ** 2
            st["kap_num"] += float((wp * qh * (1 - qh) * nrel[ok] / (nrel[ok] - 1)).sum())
            st["kap_den"] += float((wp / 4).sum())
            st["n_kap"] += int(ok.sum())
        has1 = ((v4 == 1).any(axis=1))[:, None]
        has0 = ((v4 == 0).any(axis=1))[:, None]
        sib = ((v4 == 1) & has0) | ((v4 == 0) & has1)
        sib |= (_cut_by_horizon(cf2, ci2, cj2, nc, self.nrm[cp]) & (cV >= 0)).reshape(-1, 4)
        new_ = dict(p=cp, f=cf2, l=cl2, i=ci2, j=cj2, Y=cY, V=cV, edge=sib.reshape(-1), su=su2, sv=sv2,
                    bi=np.repeat(par["bi"], 4), key=_keys(cp, cf2, cl2, ci2, cj2, self.depth))
        inew = R.replace(rsel, new_, cW, cYe)
        # the new children against the 12 cells around their 2×2 block (edge flags of older cells only grow)
        _classify_children(R, inew, dict(bV=self.bV, bedge=self.bedge, bsplit=self.bsplit, find=self.find, nb=nb,
                                         depth=self.depth))

    # ---- a non-symmetric lobe's core: split cells holding a large share of the pixel until they resolve it -------
    def _presplit(self) -> None:
        R, bp, bY, g, nb, depth = self.R, self.bp, self.bY, self.g, self.nb, self.depth
        for _ in range(depth):
            Up = np.bincount(bp, weights=bY, minlength=self.Pn)
            size_b = (np.pi / 2) / nb
            wb = np.flatnonzero(~self.bsplit & (bY > PRESPLIT_SHARE * Up[bp]) & (size_b > 0.5 * g.w[bp])
                                & (depth > 0))
            size_r = (np.pi / 2) / (nb * 2.0 ** R["l"].astype(np.float64))
            wr = np.flatnonzero((R["Y"] > PRESPLIT_SHARE * Up[R["p"]]) & (size_r > 0.5 * g.w[R["p"]])
                                & (R["l"] < depth))
            if len(wb) + len(wr) == 0:
                break
            self.st["presplit"] += self.split(wb[np.argsort(-bY[wb], kind="stable")],
                                              wr[np.argsort(-R["Y"][wr], kind="stable")])
            if self.st["cap_reached"]:
                break

    # ---- refinement rounds ------------------------------------------------------------------------------------------
    def _refine(self):
        """Rounds of splits where weight × possible change is largest (module docstring) → (rounds, converged)."""
        R, st, Pn, rtol, prtol = self.R, self.st, self.Pn, self.rtol, self.prtol
        rounds = []
        converged = False
        E = self.E
        for rnd in range(MAX_ROUNDS):
            ub, ur, pix, Yu = self.uncertain()
            Ye = np.concatenate([self.bYe[ub], R.Ye[ur]])
            Ae, qe = self.pixel_sums()
            kap = _kappa(st["kap_num"], st["kap_den"], st["n_kap"])
            # per environment: the image estimate and the pixels over pixel_rtol (lit pixels; best effort: pixels
            # whose quadrature estimate alone exceeds it, or whose edge cells are at the finest level, stay over)
            per, est, worst = [], -1.0, 0
            S_all, strict_all = self.quad.sums_by(pix, Ye ** 2, Pn), self.quad.sums_by(pix, Ye, Pn)
            for e in range(E):
                Se, strict = S_all[:, e], strict_all[:, e]
                A, q = Ae[:, e], qe[:, e]
                sig = 0.5 * np.sqrt(kap * Se)
                tot_A = max(A.sum(), 1e-300)
                est_e = (sig.sum() + q.sum()) / tot_A
                bound = np.minimum(strict, T_BOUND * 0.5 * np.sqrt(Se)) + q
                den = np.maximum(A, ERR_FLOOR * A.mean()) if Pn else A
                target = ROUND_AIM * prtol * den
                viol = np.flatnonzero((bound > prtol * den) & (q < target))
                per.append(dict(S=Se, strict=strict, q=q, target=target, viol=viol, tot_A=tot_A, est=est_e,
                                vis=float(sig.sum() / tot_A), quad=float(q.sum() / tot_A)))
                if est_e > est:
                    est, worst = est_e, e
            n_viol = int(len(np.unique(np.concatenate([d["viol"] for d in per]))))
            rounds.append(dict(round=rnd, rays=int(st["n_rays"]), est_rel_l1=float(est),
                               vis_rel_l1=per[worst]["vis"], quad_rel_l1=per[worst]["quad"],
                               kappa=float(kap), edge_cells=int(len(pix)), cells=int(self.nB + R.live),
                               pixels_over=n_viol))
            if est <= rtol and n_viol == 0:
                converged = True
                break
            if st["cap_reached"]:
                converged = est <= rtol
                break
            # candidates: edge cells that can still be split, largest weight first, among the top SPLIT_SHARE of
            # their pixel's Σ W² (the smallest cells of a pixel wait until the larger ones are split); each
            # environment over its targets picks by its own weights (the image budget: the worst one's)
            lv = np.concatenate([np.zeros(len(ub), np.int64), R["l"][ur].astype(np.int64)])
            can = np.flatnonzero(lv < self.depth)
            pick = np.zeros(len(pix), bool)
            for e, d in enumerate(per):
                if not ((e == worst and est > rtol) or len(d["viol"])):
                    continue
                y = Ye[:, e]
                c_ = can
                if not (e == worst and est > rtol):  # pixels only: their cells alone (the same order, the same picks)
                    over = np.zeros(Pn, bool)
                    over[d["viol"]] = True
                    c_ = can[over[pix[can]]]
                o = c_[np.argsort(-y[c_], kind="stable")]
                o = o[_worth_splitting(pix[o], y[o], d["S"])]
                if not len(o):
                    continue
                if e == worst and est > rtol:
                    budget = ROUND_AIM * max(rtol * d["tot_A"] - d["q"].sum(), 0.25 * rtol * d["tot_A"])
                    k_plan = kap if st["n_kap"] >= KAPPA_MIN_SPLITS else KAPPA_PLAN  # planning only (κ̂ = 1 in est)
                    pick[o[:_select(pix[o], y[o], d["S"], budget, min_split=64, kappa=k_plan)]] = True
                if len(d["viol"]):
                    pick[_select_pixels(pix[o], y[o], o, d["viol"], d["S"], d["strict"], d["q"], d["target"],
                                        Pn)] = True
            chosen = np.flatnonzero(pick)
            if len(chosen) == 0:
                converged = est <= rtol
                break
            chosen = chosen[np.argsort(-Yu[chosen], kind="stable")]
            isb = chosen < len(ub)
            if self.split(ub[chosen[isb]], ur[chosen[~isb] - len(ub)]) == 0:
                converged = est <= rtol
                break
        return rounds, converged

    # ---- results ---------------------------------------------------------------------------------------------------
    def _results(self, rounds, converged) -> dict:
        R, st, Pn, bp, bW, bV, nB = self.R, self.st, self.Pn, self.bp, self.bW, self.bV, self.nB
        lit_b = (bV > 0) & ~self.bsplit
        occ = self.quad.sums_by(bp, bW, Pn, lit_b) + self.quad.sums_by(R["p"], R.W, Pn, R["V"] > 0)
        occ = occ / self.ws[:, None]
        ub, ur, pix, _ = self.uncertain()
        Ye, _ = self.per_env(ub, ur)
        S, strict = self.quad.sums_by(pix, Ye ** 2, Pn), self.quad.sums_by(pix, Ye, Pn)
        q = self.quad_est(self.vbar())
        kap = _kappa(st["kap_num"], st["kap_den"], st["n_kap"])
        M = self.M
        return dict(occ=occ, un=self.U, err_mean=0.5 * np.sqrt(kap * S) + q,  # (Pn, E) per environment
                    err_bound=np.minimum(strict, T_BOUND * 0.5 * np.sqrt(S)) + q, kappa=float(kap),
                    n_rays=int(st["n_rays"]), n_quad=int(M), n_quad_pair_max=int(self.bM.max()) if nB else int(M),
                    converged=converged, rounds=rounds, cap_reached=bool(st["cap_reached"]),
                    presplit=int(st["presplit"]), max_level=int(self.nb * 2 ** (int(R["l"].max()) if len(R) else 0)),
                    n_cells=int(nB + R.live), time_s=time.perf_counter() - self.t0,
                    cpu_s=time.process_time() - self.c0, peak_rss_mb=_peak_rss_mb())


def _peak_rss_mb() -> float:
    """Peak resident set size of this process (MB; 0 where the platform does not report it)."""
    try:
        import resource
        import sys

        r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return r / 2 ** 20 if sys.platform == "darwin" else r / 1024
    except (ImportError, OSError):
        return 0.0


_XMASK = np.int64(0x0000015555555555)  # col bits of the 42-bit Morton code
_YMASK = np.int64(0x000002AAAAAAAAAA)  # row bits
#: region queries per vectorised step of :func:`_classify_children` (bounds its memory, ~150 B per query)
CLASSIFY_CHUNK = 1 << 17


#: the 12 cells around a 2×2 block of children (offsets from the block's first child), and which of the four
#: children (a, b) each one touches
_RING = np.array([(-1, -1), (-1, 0), (-1, 1), (-1, 2), (0, -1), (0, 2), (1, -1), (1, 2), (2, -1), (2, 0), (2, 1), (2, 2)])
_RING_ADJ = np.array([[abs(dr - a) <= 1 and abs(dc - b) <= 1 for dr, dc in _RING] for a in (0, 1) for b in (0, 1)])


def _classify_children(R, inew, ctx):
    """Edge flags of new children (``inew``: groups of 4 siblings, order (0,0), (0,1), (1,0), (1,1)): each child
    against the regions of the 12 same-level cells around its 2×2 block that it touches (its siblings were compared
    already); a region cell (base or refined) that differs from a child it touches becomes an edge too."""
    K = len(inew) // 4
    for a0 in range(0, K, CLASSIFY_CHUNK // 12):
        g = inew[4 * a0:4 * min(K, a0 + CLASSIFY_CHUNK // 12)]
        _classify_children_chunk(R, g, ctx)


def _classify_children_chunk(R, g, ctx):
    """:func:`_classify_children` for one chunk: the 12 ring cells of every 2×2 block at once, as (K, 12) arrays
    (every quantity is computed per (block, ring cell) and the results are OR-ed flags, so it is the same as one
    ring cell after the other, in far fewer array operations)."""
    nb, depth = ctx["nb"], ctx["depth"]
    first = g[0::4]
    K = len(first)
    V4 = R["V"][g].reshape(K, 4)
    if not (V4 >= 0).any():
        return
    lvl = R["l"][first].astype(np.int64)
    p = R["p"][first].astype(np.int64)
    f0 = R["f"][first].astype(np.int64)
    i0 = R["i"][first].astype(np.int64)
    j0 = R["j"][first].astype(np.int64)
    key = R["key"][first]
    n = nb << lvl
    sh = 2 * (depth - lvl)
    inc = (np.int64(1) << sh)[:, None]
    high = (key & ~(_XMASK | _YMASK))[:, None]
    x0, y0 = (key & _XMASK)[:, None], (key & _YMASK)[:, None]
    dr, dc = _RING[:, 0][None, :], _RING[:, 1][None, :]
    # per (block, ring cell), flattened block-major: the cell, its Morton key, whether it lies off the block's face
    I = (i0[:, None] + dr).reshape(-1)
    J = (j0[:, None] + dc).reshape(-1)
    F = np.repeat(f0, 12)
    x = np.where(dc > 0, ((x0 | _YMASK) + dc * inc) & _XMASK, np.where(dc < 0, (x0 - inc) & _XMASK, x0))
    y = np.where(dr > 0, ((y0 | _XMASK) + dr * (inc << 1)) & _YMASK, np.where(dr < 0, (y0 - (inc << 1)) & _YMASK, y0))
    k0 = (high | x | y).reshape(-1)
    pr, lr, nr = np.repeat(p, 12), np.repeat(lvl, 12), np.repeat(n, 12)
    out = (I < 0) | (I >= nr) | (J < 0) | (J >= nr)
    if out.any():
        o = np.flatnonzero(out)
        F[o], I[o], J[o] = _neighbour_of(F[o], I[o], J[o], nr[o])
        k0[o] = _keys(pr[o], F[o], lr[o], I[o], J[o], depth)
    cb = (F * nb + (I >> lr)) * nb + (J >> lr)
    pi_ = ctx["find"](pr, cb)
    valid = pi_ >= 0
    vd = np.where(valid, ctx["bV"][np.maximum(pi_, 0)], -1)
    split = valid & ctx["bsplit"][np.maximum(pi_, 0)]
    base = valid & ~split
    has0 = base & (vd == 0)
    has1 = base & (vd == 1)
    # whether a child that the ring cell touches is lit / shadowed
    adj = _RING_ADJ.astype(np.int64)
    t1 = (((V4 == 1).astype(np.int64) @ adj) > 0).reshape(-1)
    t0 = (((V4 == 0).astype(np.int64) @ adj) > 0).reshape(-1)
    # a base cell that differs from a child it touches becomes an edge
    rev_b = base & (((vd == 0) & t1) | ((vd == 1) & t0))
    ctx["bedge"][pi_[rev_b]] = True
    # regions inside split base cells: look them up among the refined cells (Morton ranges)
    sp = np.flatnonzero(split)
    if len(sp):
        sk, order = R.skeys, R.order
        Vs = R["V"][order]
        crel = np.r_[0, np.cumsum(Vs >= 0, dtype=np.int32)]
        cvis = np.r_[0, np.cumsum(Vs > 0, dtype=np.int32)]
        k0s = k0[sp]
        L_ = lr[sp]
        k1 = k0s + (np.int64(1) << (2 * (depth - L_)))
        lo = np.searchsorted(sk, k0s, side="right") - 1
        lo_c = np.maximum(lo, 0)
        cover = (lo >= 0) & (sk[lo_c] + (np.int64(1) << (2 * (depth - R["l"][order[lo_c]].astype(np.int64)))) > k0s)
        start = np.where(cover, lo, lo + 1)
        hi = np.searchsorted(sk, k1, side="left")
        nrel = crel[hi] - crel[start]
        nvis = cvis[hi] - cvis[start]
        h1 = nvis > 0
        h0 = nrel > nvis
        has0[sp] = h0
        has1[sp] = h1
        rv = np.flatnonzero((h0 & t1[sp]) | (h1 & t0[sp]))
        if len(rv):
            # the refined cell of the region nearest to the block (middle of the shared side, or the corner)
            s_ = sp[rv]
            w = np.int64(1) << (depth - L_[rv])
            r_ = s_ % 12  # the ring cell
            pos = [np.where(out[s_], X[s_] * w + w // 2,
                            X[s_] * w + np.where(d_ < 0, w - 1, np.where(d_ > 1, 0, w // 2)))
                   for X, d_ in ((I, _RING[r_, 0]), (J, _RING[r_, 1]))]
            kp = _keys(pr[s_], F[s_], np.full(len(rv), depth), pos[0], pos[1], depth)
            at = np.searchsorted(sk, kp, side="right") - 1
            Vr = Vs[at]
            diff = ((Vr == 0) & t1[s_]) | ((Vr == 1) & t0[s_])
            R["edge"][order[at[diff]]] = True
    # children: an edge if a region they touch holds the other value
    has0, has1 = has0.reshape(K, 12), has1.reshape(K, 12)
    e = np.zeros((K, 4), bool)
    for c in range(4):
        adj_c = _RING_ADJ[c]
        e[:, c] = np.where(V4[:, c] == 1, has0[:, adj_c].any(axis=1),
                           np.where(V4[:, c] == 0, has1[:, adj_c].any(axis=1), False))
    R["edge"][g] |= e.reshape(-1)


def _neighbour_of(f, I, J, n):
    """Cells (f, I, J) of face sizes n, with rows/cols one step outside a face mapped onto the adjacent face."""
    out = (I < 0) | (I >= n) | (J < 0) | (J >= n)
    if out.any():
        f, I, J = f.copy(), I.copy(), J.copy()
        nn = n[out].astype(np.float64)
        d = _dirs(f[out], (J[out] + 0.5) / nn * 2.0 - 1.0, (I[out] + 0.5) / nn * 2.0 - 1.0, normalize=False)
        f[out], I[out], J[out] = _direction_to_texel_n(d, n[out])
    return f, I, J


# ------------------------------------------------------------------------------------------------
# public entry
# ------------------------------------------------------------------------------------------------
def _int_arg(name, v):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
        raise IBLError(f"{name} must be a positive integer, got {v!r}")
    return int(v)


def converged_shading(scene, points, normals, face_normals, views, cube, lobe, *, rtol: float = DEFAULT_RTOL,
                      n_vis_start: int = 16, n_vis_max: int = 16384, n_quad_max: int | None = None,
                      n_quad_min: int | None = None, max_cells: int = MAX_BLOCK_CELLS, eps: float | None = None, backend: str = "auto",
                      seed: int = 0, block_pixels: int = 256, pixel_rtol: float | None = None, workers: int = 1,
                      executor=None, progress: bool = False, predict: bool | None = None, kernel: str | None = None,
                      groups: int = 1):
    """One lobe's visibility-weighted integral (*) or (**) at surface points, converged to ``rtol`` (module
    docstring).

    Parameters
    ----------
    scene : occluders (:func:`ibl_ref.rendering.raster.prepare_scene`)
    points, normals, face_normals, views : (P, 3) surface points, shading normals n, face normals, unit directions
        v toward the viewer
    cube : (6, N, N, C) radiance
    lobe : :class:`ibl_ref.rendering.materials.PhongLobe` or :class:`ibl_ref.rendering.materials.GGXLobe` (the
        weight of a material's term: :meth:`ibl_ref.rendering.materials.PhongMaterial.lobes`)
    rtol : target estimated relative L1 (Σ err_mean / Σ A)
    n_vis_start : smallest visibility base face size; n_vis_max : finest visibility face size
    n_quad_max : largest quadrature face size (default: the lobe's, 256 for Phong, 4096 for GGX)
    n_quad_min : smallest quadrature face size (default: the visibility base level's, whatever the map's size —
        coarser than the map a level reads the map's exact area averages; the map's N for every quadrature texel
        inside one map texel, the reference before 2026-12-07)
    max_cells : cells of one block at most (base pairs + refined leaves; the memory bound; the refinement stops
        there and ``converged`` says whether the targets were met)
    eps : shadow-ray offset (default 1e-6 × scene radius); backend : ray caster (``"auto"``, ``"embree"``,
        ``"exact"``; :class:`ibl_ref.rendering.raycast.ShadowRays`)
    seed : random points of the visibility cells; block_pixels : pixels per block (the blocks, hence the image,
        depend on it, never on ``workers``/``executor``)
    workers, executor : where the blocks run (:func:`ibl_ref.executors.map_jobs`); the result is bit-identical
    progress : progress reports; predict : run the first block alone and print the predicted cost of the others
        before they start (default: with ``progress``; it changes no result)
    kernel : the quadrature's implementation (:func:`ibl_ref.rendering.reference_quadrature.get_quadrature`:
        ``"auto"``, ``"numpy"``, ``"compiled"``; None: ``$IBL_REF_KERNEL`` or ``"auto"``), resolved here so that
        every block uses the same one
    groups : the map's C channels are ``groups`` environments of C/groups channels each, stacked (a sweep over
        environments: :func:`ibl_ref.rendering.reference_render.render_reference` with a list of maps); one set of
        cells, rays and quadrature weights serves them all and each is held to ``rtol`` and ``pixel_rtol`` (module
        docstring, "Several environments"); ``err_mean``, ``err_bound`` are then (P, groups) and
        ``info["est_rel_l1"]`` a list

    Returns
    -------
    occluded (P, C), unoccluded (P, C), err_mean (P,) or (P, groups), err_bound (P,) or (P, groups), info
    """

    if not isinstance(lobe, (PhongLobe, GGXLobe)):
        raise IBLError(f"lobe must be a PhongLobe or a GGXLobe (ibl_ref.rendering.materials), got {lobe!r}")
    a = check_environment(cube)
    N = a.shape[1]
    E = _int_arg("groups", groups)
    if a.shape[-1] % E:
        raise IBLError(f"groups={E} must divide the environment's {a.shape[-1]} channels")
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    arrs = []
    for name, x in (("normals", normals), ("face_normals", face_normals), ("views", views)):
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        if len(x) != len(P):
            raise IBLError(f"{name} has {len(x)} rows for {len(P)} points")
        ln = np.linalg.norm(x, axis=1, keepdims=True)
        if not (np.all(np.isfinite(x)) and np.all(ln > 0)):
            raise IBLError(f"{name} must be finite non-zero vectors")
        arrs.append(x / ln)
    nrm, fn, v = arrs

    rtol = check_rtol(rtol, "rtol")
    n_quad_max = lobe.n_quad_max if n_quad_max is None else n_quad_max
    for name, val in (("n_vis_start", n_vis_start), ("n_vis_max", n_vis_max), ("n_quad_max", n_quad_max),
                      ("block_pixels", block_pixels), ("max_cells", max_cells)):
        _int_arg(name, val)
    backend = resolve_shadow_backend(backend)
    kernel = get_quadrature(kernel).name
    t0 = time.perf_counter()
    scene = prepare_scene(scene, warn=False)
    theta = lobe.base_half_angle()
    nb = base_level(theta, N, n_vis_start)
    depth = 0
    while nb * 2 ** (depth + 1) <= n_vis_max and nb * 2 ** (depth + 1) < 2 ** _MORTON_BITS:
        depth += 1
    if n_quad_min is not None:
        _int_arg("n_quad_min", n_quad_min)
    M0 = quadrature_start(theta, N, nb, n_quad_min)
    n_quad_max = max(int(n_quad_max), M0)
    lobe.check_resolved(n_quad_max)  # a lobe narrower than the finest quadrature texel: refused before any work
    nP = len(P)
    nblk = max(1, -(-nP // int(block_pixels)))
    jobs = []
    for b in range(nblk):
        idx = np.arange(b, nP, nblk)
        jobs.append(dict(env=a, lobe=lobe, rtol=rtol, points=P[idx], normals=nrm[idx], face_normals=fn[idx],
                         views=v[idx], nb=nb, depth=depth, seed=int(seed), block=b, M0=M0, n_quad_max=n_quad_max,
                         scene=scene, max_cells=int(max_cells),
                         pixel_rtol=PIXEL_RTOL_FACTOR * rtol if pixel_rtol is None else float(pixel_rtol),
                         backend=backend, eps=eps, kernel=kernel, groups=E))
    label = _label(lobe)
    predict = progress if predict is None else bool(predict)
    res, prediction = [], None
    if predict and nblk > 1 and nP:
        from ..progress import say

        res = map_jobs(_converge_block, jobs[:1], workers=1)
        prediction = _predict(res[0], nblk, workers if executor is None else None, len(jobs[0]["points"]), nP,
                              time.perf_counter() - t0, int(max_cells), memory_bound_mb(int(max_cells), a))
        say(f"reference {label}: {prediction['text']}")
        jobs = jobs[1:]
    res = res + map_jobs(_converge_block, jobs, executor=executor, workers=workers,
                         desc=f"reference {label} ({nblk} blocks)" if progress else None, what="reference block")
    C = a.shape[-1]
    occ = np.zeros((nP, C))
    un = np.zeros((nP, C))
    em = np.zeros((nP, E))
    eb = np.zeros((nP, E))
    for b, r in enumerate(res):
        idx = np.arange(b, nP, nblk)
        occ[idx], un[idx], em[idx], eb[idx] = r["occ"], r["un"], r["err_mean"], r["err_bound"]
    y = occ.reshape(nP, E, C // E).mean(axis=-1)
    tot = np.maximum(np.abs(y).sum(axis=0), 1e-300)
    est = em.sum(axis=0) / tot
    info = dict(lobe_kind=lobe.kind, n_vis_base=int(nb), n_vis_finest=int(max(r["max_level"] for r in res)),
                n_quad=sorted({int(r["n_quad"]) for r in res}),
                n_quad_pair_max=int(max(r["n_quad_pair_max"] for r in res)),
                n_rays=int(sum(r["n_rays"] for r in res)),
                n_cells=int(sum(r["n_cells"] for r in res)), blocks=nblk, backend=backend, quadrature=kernel,
                rtol=rtol,
                est_rel_l1=float(est[0]) if E == 1 else [float(x) for x in est],
                block_converged=int(sum(r["converged"] for r in res)),
                converged=bool(all(r["converged"] for r in res)),
                max_cells=int(max_cells), blocks_at_cell_cap=int(sum(r["cap_reached"] for r in res)),
                block_cells_max=int(max(r["n_cells"] for r in res)),
                presplit_cells=int(sum(r["presplit"] for r in res)),
                rounds_max=int(max(len(r["rounds"]) for r in res)),
                block_rounds=[r["rounds"] for r in res[:1]], time_s=time.perf_counter() - t0,
                block_time_s=float(sum(r["time_s"] for r in res)), block_cpu_s=float(sum(r["cpu_s"] for r in res)),
                worker_peak_rss_mb=float(max(r["peak_rss_mb"] for r in res[1 if prediction is not None and
                                                                                 len(res) > 1 else 0:])))
    if prediction is not None:  # block 1 ran in this process (its CPU time is this process's, not a worker's)
        info["predicted"] = {k: vv for k, vv in prediction.items() if k != "text"}
        info["pilot_cpu_s"] = float(res[0]["cpu_s"])
    if E == 1:
        return occ, un, em[:, 0], eb[:, 0], info
    return occ, un, em, eb, info


def _label(lobe) -> str:
    if lobe.kind == "phong":
        return f"s={lobe.s:g}"
    return f"GGX roughness {lobe.roughness:g}"


def memory_bound_mb(max_cells: int, env) -> float:
    """Predicted peak memory (MB) of a process running blocks of at most ``max_cells`` cells on ``env`` (the
    measured model of :data:`MEM_BASE_MB`, :data:`MEM_PER_CELL_B`, :data:`MEM_ENV_COPIES`, with
    :data:`MEM_PER_CELL_CHANNEL_B` for the channels of stacked environments beyond three; the scene's own size
    aside)."""
    env = np.asarray(env)
    per_cell = MEM_PER_CELL_B + MEM_PER_CELL_CHANNEL_B * max(env.shape[-1] - 3, 0)
    return float(MEM_BASE_MB + per_cell * max_cells / 2 ** 20 + MEM_ENV_COPIES * env.nbytes / 2 ** 20)


def _predict(r0: dict, nblk: int, workers, n0: int, nP: int, elapsed: float, max_cells: int, mem_mb: float) -> dict:
    """Predicted cost of all blocks from the first one (a round-robin sample of the pixels)."""
    scale = nP / max(n0, 1)
    rays = r0["n_rays"] * scale
    cpu = r0["cpu_s"] * scale
    par = max(1, min(workers or 1, nblk - 1))
    wall = elapsed + r0["time_s"] * (nblk - 1) / par
    mem = r0["peak_rss_mb"]
    text = (f"predicted from block 1 of {nblk}: {rays / 1e6:.1f} M rays, {cpu:.0f} s CPU, ~{wall:.0f} s wall with "
            f"{par} worker{'s' if par > 1 else ''}; memory: block 1 held {r0['n_cells'] / 1e6:.2f} M cells and peaked at "
            f"{mem:.0f} MB; every block stops at {max_cells / 1e6:.2f} M cells: <= ~{mem_mb:.0f} MB per process)")
    return dict(rays=int(rays), cpu_s=float(cpu), wall_s=float(wall), block_peak_rss_mb=float(mem),
                memory_bound_mb=mem_mb, text=text)
