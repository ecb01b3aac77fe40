"""Exact GGX prefiltering with a rigorous bound: the ``n = v = r`` lobe of Karis (2013) by a block-Taylor tree.

The split sum's prefiltered radiance (Karis 2013, Eq. 8 with ``n = v = r``) at an output direction r is the
lobe average over the source texels j (centres ω_j, exact solid angles Ω_j)::

    P(r) = Σ_j L_j K(r·ω_j) Ω_j / Σ_j K(r·ω_j) Ω_j,
    K(x) = D(√((1 + x)/2)) · max(x, 0) ∝ x / (α² + b(1 − x))²,  b = (1 − α²)/2      (x > 0; 0 otherwise)

(:func:`ibl_ref.prefilter.karis2013.prefilter_kernel`; the constant α²/π cancels in the average).  The dense
sum costs every source texel for every output texel (:func:`ibl_ref.prefilter.karis2013.prefilter_dense`, the
test oracle): 43 s at 128² faces, minutes at 256².  GGX has heavy tails (K ∝ θ⁻⁴ away from the peak), so a
truncated gather like the Phong lobes' (:mod:`ibl_ref.groundtruth.phong_convolution`) would keep a cap of tens
of degrees; instead the far field is summed by blocks, with the error of every block bounded.

The tree
--------
The source texels form a quadtree per face (blocks of b×b texels, b = P, P/2, …, 1).  Each block B stores its
bounding cone (centre ĉ, half-angle ψ over its texel centres) and its moments about ĉ, per channel q (the
last channel has L ≡ 1: the denominator)::

    M0 = Σ_j w_j,   U = Σ_j w_j (ω_j − ĉ),   V = Σ_j w_j (ω_j − ĉ)(ω_j − ĉ)ᵀ,     w_j = L_j Ω_j

(built bottom-up by the parallel-axis shift, so nothing cancels).  With x_B = r·ĉ, the second-order Taylor
expansion of K about x_B gives the block's contribution::

    Σ_{j∈B} w_j K(r·ω_j) = K(x_B) M0 + K'(x_B) r·U + ½ K''(x_B) rᵀVr + R,
    |R| ≤ (1/6) sup|K'''| Σ_j w_j |x_j − x_B|³ ≤ (1/6) sup|K'''| δ · rᵀVr,
    δ = (1 − cos ψ)|x_B| + sin ψ √(1 − x_B²) ≥ |x_j − x_B|,   x_j = r·ω_j

(ω_j − ĉ splits into (cos φ − 1)ĉ and sin φ times a unit vector ⊥ ĉ, φ ≤ ψ; r's component ⊥ ĉ has length
√(1 − x_B²)).  K is smooth on [x_B − δ, x_B + δ] when x_B − δ > 0, and there K''' > 0 grows with x
(:meth:`GGXLobeKernel.d3`), so the sup is K'''(min(x_B + δ, 1)).  Near the horizon the zero-order bracket
``0 ≤ K ≤ K(x_B + δ)`` (K increases with x) gives the midpoint and half-width instead; per output texel and block
the smaller of the two bounds is used.  Single texels are summed exactly, and so are the 2×2 blocks left after
the refinement (their four texels cost less than one Taylor sum per output texel).

Output texels are grouped in t×t tiles (axis c_T, half-angle β_T; :func:`default_tile`).  Each tile starts from
the six face blocks.  A (tile, block) pair is dropped when no texel of the block can be above the horizon of any
texel of the tile (x_max + δ ≤ 0 over the tile's whole cone: rigorous).  Every live pair gets an estimate of its
bound at the tile's axis, relative to the tile's running estimate of the sums (Σ K(r·ĉ) M0 over its pairs)::

    m = max_q e_q / Ŝ_q + e_Ω / Ŝ_Ω,   e_q = min(K'''(x_top)/6 · δ · min(δ² M0_q, tr V_q), ½K(x_top) M0_q)

plus :data:`HORIZON_SHARE` of the bracket where the pair straddles the horizon of some texel of the tile (so that
a zero estimate always means a zero bound).  While the tile's total Σ m exceeds its target, every pair with
m ≥ θ is split into its four children (children that are texels are exact): the greedy rule that spends the
splits where the bound is.  θ is Σ m / (2n) (n live pairs), doubled while the pairs at or above 2θ hold at least
(Σ m − target)/:data:`SPLIT_GAIN`: near the target only the largest pairs are split, as many as the excess needs.
The estimates only steer the cost: per output texel and channel the sums and their absolute bounds
(:func:`ibl_ref.groundtruth.kernels.numpy_backend.ggx_evaluate`, the better of the two brackets per texel) give the
lobe average and a rigorous relative bound
(:func:`ibl_ref.groundtruth.moment_convolution._ratio_bound`, plus :data:`ROUNDING_REL`).  Every tile is refined
to the target :data:`BUDGET_TARGET` · τ (τ = rtol/(1 + rtol)); the tiles whose per-texel bound still misses rtol
are computed again with the target scaled by :data:`REDO_SHARE` · rtol over their largest bound (at least divided by
:data:`REFINE_FACTOR`; :data:`REFINE_STEPS` times) and at last with target 0, which splits every live pair down to
texels: the exact sum.  So the bound ≤ rtol holds for every
output texel whatever the estimates, and the cost is what the bound needs.

References: Karis (2013), "Real Shading in Unreal Engine 4", Eq. 8 (the split sum); Walter et al. (2007), Eq. 33
(the GGX D); Barnes & Hut (1986) for the tree, here with a Taylor remainder in place of their opening angle.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..conventions import ggx_alpha
from ..environment import envmap
from ..errors import IBLError
from ..limits import check_rtol
from .convolution_args import channel_max, check_cube, check_faces, check_out_size
from .kernels import get_kernels, resolve_kernel
from .kernels.numpy_backend import GGX_ANGLE_EPS, SYM_PAIRS
from .moment_convolution import _ratio_bound

__all__ = ["GGXLobeKernel", "GGXSourceTree", "convolve_ggx", "convolve_ggx_levels", "ROUNDING_REL", "REFINE_STEPS",
           "LAST_INFO"]

#: relative allowance added to every bound for the float64 rounding of the sums (≤ 6N² non-negative terms of a
#: few roundings each, and the Taylor terms, each ≤ its block's K·M0: ≈ 1e-13 at 1024², ten times that here)
ROUNDING_REL = 1e-12
#: refinement passes (each with a smaller target, see REFINE_FACTOR) before the exact sum of the tiles still missing rtol
REFINE_STEPS = 2
#: the tile-level relative bound each tile is refined to, as a share of τ = rtol/(1 + rtol) (the per-texel bounds are
#: smaller: the tile-level ones hold for its whole cone)
BUDGET_TARGET = 1.0
#: share of a tile's cone half-angle β over which the refinement estimates each block's bound (0: at the tile's
#: axis); the bounds returned are per output texel whatever this is
BETA_SHARE = 0.0
#: share of the bracket of a pair near some texel's horizon (over the tile's whole cone) in its bound estimate
HORIZON_SHARE = 0.0625
#: divisor of the target of each refinement pass, at least (a tile whose largest per-texel bound b misses rtol is
#: computed again with its target times REDO_SHARE · rtol / b, clipped to [REFINE_FACTOR⁻⁴, 1/REFINE_FACTOR])
REFINE_FACTOR = 2.0
#: the share of rtol a tile's largest per-texel bound is aimed at when the tile is computed again
REDO_SHARE = 0.5
#: levels of at least this many output tiles first compute every SAMPLE_STRIDE-th tile at BUDGET_TARGET·τ, and the
#: others at the target that brings the sample's 90th-percentile largest per-texel bound to SAMPLE_AIM·rtol (the
#: tile-level estimates are 1–5× the per-texel bounds, depending on the lobe's width against the tile's)
SAMPLE_MIN_TILES = 64
SAMPLE_STRIDE = 8
SAMPLE_AIM = 0.85
#: the share of a split pair's bound estimate the split is expected to remove (2×2 children of a block in the Taylor
#: regime have about 1/8 of its remainder): the last rounds of a tile's refinement split only the largest pairs,
#: enough for the excess over the target, instead of every pair above half the mean
SPLIT_GAIN = 0.875
#: diagnostics of the last call (pairs per level, passes, seconds)
LAST_INFO: dict = {}


class GGXLobeKernel:
    """The ``n = v = r`` GGX kernel ``K(x) = x / (α² + b(1 − x))²`` (x = r·ω > 0, b = (1 − α²)/2; 0 for x ≤ 0) and
    its derivatives, up to the factor α²/π of D (module docstring).

    Examples
    --------
    >>> k = GGXLobeKernel(0.25)
    >>> float(k.value(1.0)) == 1 / 0.25 ** 4
    True
    >>> float(k.value(-0.5))
    0.0
    """

    def __init__(self, alpha: float):
        self.alpha = float(alpha)
        self.a = self.alpha ** 2
        self.b = 0.5 * (1.0 - self.a)

    def _iu(self, x):
        return 1.0 / (self.a + self.b * (1.0 - x))

    def value(self, x):
        """K(x), 0 where x ≤ 0."""
        x = np.asarray(x, dtype=np.float64)
        iu = self._iu(x)
        return np.where(x > 0.0, x * iu * iu, 0.0)

    def taylor(self, x):
        """``(K, K', K'')`` at x > 0 (the formula, without the clamp)."""
        b = self.b
        iu = self._iu(x)
        iu2 = iu * iu
        return x * iu2, iu2 + 2.0 * b * x * iu2 * iu, 4.0 * b * iu2 * iu + 6.0 * b * b * x * iu2 * iu2

    def d3(self, x):
        """K'''(x) = 18 b² u⁻⁴ + 24 b³ x u⁻⁵ (u = α² + b(1 − x)): positive and increasing for x ≥ 0, so its sup on
        an interval of x ≥ 0 is its value at the upper end."""
        b = self.b
        iu = self._iu(x)
        iu4 = (iu * iu) ** 2
        return 18.0 * b * b * iu4 + 24.0 * b ** 3 * x * iu4 * iu

    def peak_factor(self) -> float:
        """The largest of K, K′, K″, K‴ on [0, 1] (each peaks at x = 1, where u = α²): what a radiance is multiplied by in
        the sums and their bounds."""
        b, iu = self.b, 1.0 / self.a
        d1 = iu ** 2 + 2.0 * b * iu ** 3
        d2 = 4.0 * b * iu ** 3 + 6.0 * b * b * iu ** 4
        d3 = 18.0 * b * b * iu ** 4 + 24.0 * b ** 3 * iu ** 5
        return max(iu ** 2, d1, d2, d3)

    def lobe_integral(self) -> float:
        """W̃ = 2π ∫₀¹ K(x) dx = 2π (y − ln(1 + y)) / b², y = b/α² (1/(2α⁴) times 2π as b → 0)."""
        a, b = self.a, self.b
        y = b / a
        if y < 1e-4:
            inner = (1.0 - 2.0 * y / 3.0 + y * y / 2.0) / (2.0 * a * a)
        else:
            inner = (y - math.log1p(y)) / (b * b)
        return 2.0 * math.pi * inner


class _Level:
    """One level of the source quadtree: blocks of ``b``×``b`` texels on a 6×m×m grid (module docstring)."""

    __slots__ = ("b", "m", "c", "cos_psi", "sin_psi", "valid", "M0", "U", "V", "trV")

    def __init__(self, b, m, c, cos_psi, sin_psi, valid, M0, U, V):
        self.b, self.m, self.c, self.cos_psi, self.sin_psi, self.valid = b, m, c, cos_psi, sin_psi, valid
        self.M0, self.U, self.V = M0, U, V
        # Σ w |ω − ĉ|² ≥ Σ w (r·(ω − ĉ))² for every unit r: the tile-level form of the remainder's second moment
        self.trV = None if V is None else V[:, 0] + V[:, 3] + V[:, 5]


def _block_cones(dP, S, ok, n, b):
    """Bounding cones of the b×b blocks of the padded (6,P,P,3) texel directions ``dP`` whose real texels' direction
    sums are ``S`` (6,m,m,3) (``ok``: blocks with a real texel): the centres (6,m,m,3) and half-angles ψ (6,m,m),
    +GGX_ANGLE_EPS.  ψ is the largest angle from the centre c to a texel centre of the block, found among the real
    block's four corner texels: on the face plane the points p with p·c ≥ t|p| (t > 0) form a convex set, so the
    smallest cos over the rectangle of the block's texel centres is taken at a corner."""
    nrm = np.linalg.norm(S, axis=-1)
    c = S / np.where(nrm > 0, nrm, 1.0)[..., None]
    m = S.shape[1]
    lo = np.arange(m) * b
    hi = np.minimum(lo + b, n) - 1
    lo = np.minimum(lo, n - 1)
    dots = np.ones(S.shape[:3])
    for r in (lo, hi):
        for q in (lo, hi):
            corner = dP[:, r[:, None], q[None, :]]  # (6,m,m,3)
            dots = np.minimum(dots, np.einsum("...k,...k->...", corner, c))
    dots = np.where(ok, dots, 1.0)
    return c, np.arccos(np.clip(dots, -1.0, 1.0)) + GGX_ANGLE_EPS


class GGXSourceTree:
    """The quadtree of a cube map's texels (module docstring): ``levels[0]`` the texels (P×P per face, P the face
    size rounded up to a power of two, at least 2; padding texels invalid and of zero weight), ``levels[-1]`` the six
    faces.
    One tree serves every roughness of a chain (it does not depend on the lobe)."""

    def __init__(self, a4: np.ndarray):
        n = a4.shape[1]
        P = self.P = 1 << max(int(math.ceil(math.log2(n))), 1)  # ≥ 2: one level of blocks above the texels
        omega = envmap.cube_solid_angles(n)
        w = np.concatenate([a4 * omega[..., None], omega[..., None]], axis=-1)  # (6,n,n,Q): L Ω and Ω
        Q = self.Q = w.shape[-1]
        pad = ((0, 0), (0, P - n), (0, P - n), (0, 0))
        M0 = np.pad(w, pad)
        dP = np.pad(envmap.texel_directions(n), pad)
        real = np.pad(np.ones((6, n, n), bool), pad[:3])
        self.levels = [_Level(1, P, dP.reshape(-1, 3), None, None, real.ravel(), M0.reshape(-1, Q), None, None)]
        self._flat = None
        # moments about each block's centre from its children's by the parallel-axis shift (texels: U = V = 0), child
        # by child, component-major — M0 (Q, 6, m, m), U (3, Q, 6, m, m), V (6, Q, 6, m, m) — and one (6, m, m) grid
        # per operation, into scratch grids that stay in cache (component-last, with the Q channels as the innermost
        # loops and (6, m, m, 6, Q) temporaries, this took 0.55 s at 256², now 0.15 s); the same products and sums in
        # the same order as that: the same bits.  Each level is stored component-last (_Level)
        U = V = None
        Mc = np.moveaxis(M0, -1, 0)
        cc = np.moveaxis(dP, -1, 0)  # (3, 6, P, P): the children's centres
        S = dP  # per block the sum of its texels' directions (padding: 0)
        ok = real
        b = 1
        while b < P:
            b *= 2
            m = P // b
            kids = [(slice(None), slice(di, None, 2), slice(dj, None, 2)) for di in (0, 1) for dj in (0, 1)]
            S = sum(S[k] for k in kids)
            ok = ok[kids[0]] | ok[kids[1]] | ok[kids[2]] | ok[kids[3]]
            c, psi = _block_cones(dP, S, ok, n, b)
            cm = np.ascontiguousarray(np.moveaxis(c, -1, 0))
            M0n = np.zeros((Q, 6, m, m))
            Un = np.zeros((3, Q, 6, m, m))
            Vn = np.zeros((6, Q, 6, m, m))
            t1, t2 = np.empty((6, m, m)), np.empty((6, m, m))
            for k in kids:
                k1, k2 = (slice(None),) + k, (slice(None), slice(None)) + k
                d = cc[k1] - cm  # child centre − parent centre, (3, 6, m, m)
                M0k = np.ascontiguousarray(Mc[k1])
                M0n += M0k
                for q in range(Q):
                    for a in range(3):
                        Un[a, q] += np.multiply(d[a], M0k[q], out=t1)
                for p, (a, e) in enumerate(zip(*SYM_PAIRS)):
                    dd = d[a] * d[e]
                    for q in range(Q):
                        Vn[p, q] += np.multiply(dd, M0k[q], out=t1)
                if U is not None:
                    Uc = np.ascontiguousarray(U[k2])
                    Un += Uc
                    for p, (a, e) in enumerate(zip(*SYM_PAIRS)):
                        for q in range(Q):
                            np.add(V[k2][p, q], np.multiply(d[a], Uc[e, q], out=t1), out=t1)
                            t1 += np.multiply(Uc[a, q], d[e], out=t2)
                            Vn[p, q] += t1
            Mc, U, V, cc = M0n, Un, Vn, cm
            self.levels.append(_Level(b, m, c.reshape(-1, 3), np.cos(psi).ravel(), np.sin(psi).ravel(), ok.ravel(),
                                      np.ascontiguousarray(np.moveaxis(Mc, 0, -1).reshape(-1, Q)),
                                      np.ascontiguousarray(np.moveaxis(U, (0, 1), (-2, -1)).reshape(-1, 3, Q)),
                                      np.ascontiguousarray(np.moveaxis(V, (0, 1), (-2, -1)).reshape(-1, 6, Q))))

    def flat(self, factory):
        """``factory(levels)``, made once and kept (the compiled backend's flat arrays)."""
        if self._flat is None:
            self._flat = factory(self.levels)
        return self._flat


class _Tiles:
    """Output tiles: texel directions R (T, t², 3), cone centres cT and half-angles betaT."""

    def __init__(self, R):
        self.R = np.ascontiguousarray(R)
        cT = R.sum(axis=1)
        cT /= np.linalg.norm(cT, axis=-1, keepdims=True)
        self.cT = cT
        self.betaT = np.arccos(np.clip(np.einsum("tik,tk->ti", R, cT).min(axis=1), -1.0, 1.0)) + GGX_ANGLE_EPS


def _cube_tiles(out_size, faces, t):
    """The t×t tiles of the output faces (edge texels repeated to fill the last row and column of tiles)."""
    nt = -(-out_size // t)
    od = envmap.texel_directions(out_size)[list(faces)]
    od = np.pad(od, ((0, 0), (0, nt * t - out_size), (0, nt * t - out_size), (0, 0)), mode="edge")
    return envmap.face_blocks(od, t)


def _untile(x, n_faces, out_size, t):
    """(T, t², …) tile rows → (F, M, M, …)."""
    nt = -(-out_size // t)
    x = x.reshape((n_faces, nt, nt, t, t) + x.shape[2:])
    x = np.moveaxis(x, 3, 2).reshape((n_faces, nt * t, nt * t) + x.shape[5:])
    return x[:, :out_size, :out_size]


class _Run:
    """One lobe over one set of output tiles: the passes of :func:`convolve_ggx` (module docstring)."""

    def __init__(self, impl, tree, alpha, R, rtol, threads, info):
        self.impl, self.tree, self.threads, self.info = impl, tree, threads, info
        self.kern = GGXLobeKernel(alpha)
        self.tiles = _Tiles(R)
        self.rtol, self.tau = rtol, rtol / (1.0 + rtol)
        self.C = tree.Q - 1

    def _pass(self, sel, target):
        num, err, pairs = self.impl.ggx_tree_pass(self.tree, self.kern, self.tiles.R, self.tiles.cT, self.tiles.betaT,
                                                  sel, target, BETA_SHARE, HORIZON_SHARE, SPLIT_GAIN,
                                                  threads=self.threads)
        counts = self.info.setdefault("pairs", {})
        for li, k in enumerate(pairs):
            b = self.tree.levels[li].b
            counts[b] = counts.get(b, 0) + int(k)
        return num, err

    def _worst(self, num, err):
        """Per tile the largest per-texel relative bound of the sums ``num``/``err`` (tiles, t², Q)."""
        return channel_max(_ratio_bound(num, err, self.C, True)[1]).max(axis=1) + ROUNDING_REL

    def run(self):
        """``(approx (T, t², C), rel_bound (T, t²))``: a sample of the tiles (every :data:`SAMPLE_STRIDE`-th) refined to
        BUDGET_TARGET·τ, the others to the target at which the sample's 90th-percentile largest bound would be
        :data:`SAMPLE_AIM`·rtol (within 4× of BUDGET_TARGET·τ); then the tiles whose per-texel bound misses rtol
        again with the target times REDO_SHARE·rtol/(their largest bound) (at least divided by REFINE_FACTOR), at
        last exactly (target 0).  The targets only steer the cost: every tile's bound is checked per texel."""
        T = self.tiles.R.shape[0]
        passes = self.info.setdefault("passes", [])
        tgt = np.full(T, BUDGET_TARGET * self.tau)
        first = [np.arange(T)]
        if T >= SAMPLE_MIN_TILES:
            sample = np.arange(0, T, SAMPLE_STRIDE)
            first = [sample, np.setdiff1d(np.arange(T), sample)]
        num = err = None
        worst = np.empty(T)
        for k, sel in enumerate(first):
            nn, ee = self._pass(sel, tgt[sel])
            if num is None:
                num, err = np.empty((T,) + nn.shape[1:]), np.empty((T,) + ee.shape[1:])
            num[sel], err[sel] = nn, ee
            worst[sel] = self._worst(nn, ee)
            passes.append((float(tgt[sel].max()), int(sel.size)))
            if k == 0 and len(first) > 1:
                with np.errstate(divide="ignore", invalid="ignore"):
                    q = float(np.quantile(worst[sel] / tgt[sel], 0.9))
                if math.isfinite(q) and q > 0.0:
                    rest = first[1]
                    tgt[rest] = np.clip(SAMPLE_AIM * self.rtol / q, tgt[rest] / 4.0, tgt[rest] * 4.0)
        todo = np.flatnonzero(~(worst <= self.rtol))
        for step in range(REFINE_STEPS + 1):
            if not todo.size:
                break
            with np.errstate(divide="ignore"):
                scale = np.clip(REDO_SHARE * self.rtol / worst[todo], REFINE_FACTOR ** -4, 1.0 / REFINE_FACTOR)
            tgt[todo] = 0.0 if step == REFINE_STEPS else tgt[todo] * scale
            nn, ee = self._pass(todo, tgt[todo])
            num[todo], err[todo] = nn, ee
            worst[todo] = self._worst(nn, ee)
            passes.append((float(tgt[todo].max()), int(todo.size)))
            todo = todo[~(worst[todo] <= self.rtol)]
        C = self.C
        approx, r = _ratio_bound(num, err, C, True)
        if not np.all(np.isfinite(approx)):
            raise IBLError("GGX prefilter: non-finite result (overflow of the input radiance?)")
        return approx, channel_max(r) + ROUNDING_REL


def _check_range(a4, alpha: float) -> None:
    """One line (before any work) where the float64 sums would overflow: radiance × the kernel's peak factor × the
    sphere's 4π, with a margin of 2^10 for the moments' extents (|ω − ĉ| ≤ 2) and the sums' lengths."""
    l_max = float(a4.max()) if a4.size else 0.0
    peak = GGXLobeKernel(alpha).peak_factor()
    if not math.isfinite(l_max * peak * 4.0 * math.pi * 1024.0):
        raise IBLError(f"GGX prefilter: radiance up to {l_max:.3g} overflows the float64 sums at α = {alpha:.3g} "
                       f"(the kernel and its derivatives reach {peak:.3g}); scale the map down")


def _threads(threads) -> int:
    """``threads``, or :func:`ibl_ref.groundtruth.convolve.default_workers` (imported here: that module brings the other
    routes, ≈ 0.07 s of ``ibl-ref prefilter``'s start-up)."""
    if threads is not None:
        return int(threads)
    from .convolve import default_workers

    return default_workers()


def default_tile(out_size: int) -> int:
    """Output tile side for an output face size: 8 from 64² up, 4 at 32², else 1 (measured, compiled kernels, 256²
    sky + sun, Filament's levels: a tile's refinement costs about as much as summing its texels at 8 on large faces,
    while on small faces a tile spans so wide a cone that its horizon band goes down to texels)."""
    return 8 if out_size >= 64 else (4 if out_size >= 32 else 1)


def _check_tile(tile, default):
    t = default if tile is None else tile
    if isinstance(t, bool) or not isinstance(t, (int, np.integer)) or t < 1 or t & (t - 1):
        raise IBLError(f"tile must be a positive power of two, got {tile!r}")
    return int(t)


def convolve_ggx_levels(cube, levels, *, rtol: float = 1e-3, tile: int | None = None, kernel=None,
                        threads: int | None = None):
    """The exact ``n = v = r`` GGX prefilter at several (roughness, output face size) pairs of one cube map — a level
    chain — with one source tree (module docstring).

    Parameters
    ----------
    cube : array (6, N, N[, C])
        Finite, non-negative radiance.
    levels : sequence of (roughness, out_size)
        Perceptual roughness r (α = r², :func:`ibl_ref.conventions.ggx_alpha`) and output face size of each level
        (None: the source's).
    rtol : float
        Largest relative error allowed at any output texel and channel (:func:`ibl_ref.limits.check_rtol`).
    tile : int, optional
        Output tile side (a power of two; default :func:`default_tile` of each level): texels that share one
        refinement.
    kernel : {"auto", "numpy", "compiled"}, optional
        The kernel backend (:func:`ibl_ref.groundtruth.kernels.resolve_kernel`; None: ``$IBL_REF_KERNEL`` or auto).
    threads : int, optional
        Threads of the compiled tree (default :func:`ibl_ref.groundtruth.convolve.default_workers`); the result does
        not depend on it.

    Returns
    -------
    list of (maps (6, M, M, C), rel_bound (6, M, M))
        Per level; no channel axis for a 3-d cube.  ``rel_bound`` bounds ``|maps − exact| / exact`` (max over
        channels) and is ≤ ``rtol`` everywhere.
    """
    t_start = time.perf_counter()
    a4, squeeze = check_cube(cube)
    rtol = check_rtol(rtol)
    n = a4.shape[1]
    spec = []
    for item in levels:
        try:
            r, m = item
        except (TypeError, ValueError):
            raise IBLError(f"levels: expected (roughness, out_size) pairs, got {item!r}") from None
        if np.ndim(r):
            raise IBLError(f"one roughness per level, got an array of shape {np.shape(r)}")
        spec.append((float(ggx_alpha(r)), check_out_size(m, n)))
    if not spec:
        raise IBLError("levels: no (roughness, out_size) pair given")
    _check_range(a4, min(alpha for alpha, _ in spec))
    if tile is not None:
        _check_tile(tile, 4)
    impl = get_kernels(resolve_kernel(kernel))
    threads = _threads(threads)
    LAST_INFO.clear()
    LAST_INFO["kernel_load_s"] = impl.warm_up(("ggx",))
    tree = GGXSourceTree(a4)
    LAST_INFO.update(tree_s=time.perf_counter() - t_start, kernel=impl.name, levels=[])
    out = []
    for alpha, m in spec:
        t = default_tile(m) if tile is None else int(tile)
        info = {"alpha": alpha, "out_size": m, "tile": t}
        t0 = time.perf_counter()
        approx, rel = _Run(impl, tree, alpha, _cube_tiles(m, range(6), t), rtol, threads, info).run()
        info["seconds"] = time.perf_counter() - t0
        LAST_INFO["levels"].append(info)
        maps, rel = _untile(approx, 6, m, t), _untile(rel, 6, m, t)
        out.append((maps[..., 0] if squeeze else maps, rel))
    LAST_INFO["total_s"] = time.perf_counter() - t_start
    return out


def convolve_ggx(cube, roughness, *, rtol: float = 1e-3, out_size: int | None = None, dirs=None,
                 tile: int | None = None, faces=None, kernel=None, threads: int | None = None):
    """Exact ``n = v = r`` GGX prefilter of a cube map with a rigorous per-texel relative bound (module docstring).

    Parameters
    ----------
    cube : array (6, N, N[, C])
        Finite, non-negative radiance (an :class:`~ibl_ref.environment.validated.Environment` passes through).
    roughness : float
        Perceptual roughness r (α = r², :func:`ibl_ref.conventions.ggx_alpha`).
    rtol : float
        Largest relative error allowed at any output texel and channel (:func:`ibl_ref.limits.check_rtol`).
    out_size : int, optional
        Output face size (default N); ignored when ``dirs`` is given.
    dirs : array (..., 3), optional
        Output directions instead of texel centres (each its own tile).
    tile : int, optional
        Output tile side (a power of two; default :func:`default_tile`).
    faces : sequence of int, optional
        Output faces (0…5, OpenEXR order; default all six).
    kernel, threads
        As in :func:`convolve_ggx_levels`.

    Returns
    -------
    maps : ndarray (F, M, M, C), or (..., C) for ``dirs`` (no channel axis for a 3-d cube)
    rel_bound : ndarray (F, M, M) or (...)
        Rigorous bound on ``|maps − exact| / exact``, max over channels, ≤ ``rtol`` everywhere.

    Examples
    --------
    >>> import numpy as np
    >>> maps, bound = convolve_ggx(np.ones((6, 8, 8)), 0.5, rtol=1e-3, kernel="numpy")
    >>> maps.shape, bool(np.allclose(maps, 1.0)), bool(bound.max() <= 1e-3)
    ((6, 8, 8), True, True)
    """
    if dirs is None and faces is None:  # (out_size None: the source's face size, as in convolve_ggx_levels)
        return convolve_ggx_levels(cube, [(roughness, out_size)], rtol=rtol, tile=tile, kernel=kernel,
                                   threads=threads)[0]
    t_start = time.perf_counter()
    a4, squeeze = check_cube(cube)
    if np.ndim(roughness):
        raise IBLError(f"one roughness at a time, got an array of shape {np.shape(roughness)}")
    alpha = float(ggx_alpha(roughness))
    rtol = check_rtol(rtol)
    _check_range(a4, alpha)
    impl = get_kernels(resolve_kernel(kernel))
    threads = _threads(threads)
    if dirs is not None:
        d = envmap.unit_directions(dirs, "dirs")
        lead = d.shape[:-1]
        R = d.reshape(-1, 1, 3)
    else:
        out_size = check_out_size(out_size, a4.shape[1])
        faces = check_faces(faces)
        t = _check_tile(tile, default_tile(out_size))
        R = _cube_tiles(out_size, faces, t)
    LAST_INFO.clear()
    LAST_INFO["kernel_load_s"] = impl.warm_up(("ggx",))
    tree = GGXSourceTree(a4)
    LAST_INFO.update(tree_s=time.perf_counter() - t_start, kernel=impl.name)
    approx, rel = _Run(impl, tree, alpha, R, rtol, threads, LAST_INFO).run()
    LAST_INFO["total_s"] = time.perf_counter() - t_start
    if dirs is not None:
        maps, rel = approx.reshape(lead + (approx.shape[-1],)), rel.reshape(lead)
    else:
        maps, rel = _untile(approx, len(faces), out_size, t), _untile(rel, len(faces), out_size, t)
    return (maps[..., 0] if squeeze else maps), rel
