"""The exact unoccluded shading of a cube-map environment: ∫ L(ω) w(ω) dω per pixel, converged by adaptive
subdivision of the map's texels.

A cube map is a piecewise-constant radiance function: L(ω) = L_j on texel j.  For a pixel with shading normal n and
view v (unit, toward the viewer) and a lobe weight w(ω) — the GGX term ``f_s(ω, v)·(n·ω)⁺`` of
:func:`ibl_ref.lobes.brdfs.ggx`, a Phong lobe, or one of the lobes of the split-sum chain below — the exact value
is

    I = Σ_j L_j ∫_{texel j} w(ω) dω          (unnormalised lobes: the GGX specular term)
    I = Σ_j L_j ∫_j w_num dω / Σ_j ∫_j w_den dω   (normalised lobes: a lobe average, the lab's Phong convention)

with no visibility (an unoccluded convex object: the orthographic sphere of
:func:`ibl_ref.rendering.sphere_render.orthographic_sphere`).  :func:`integrate` evaluates both integrals with a
midpoint rule on *cells*: sub-rectangles of a texel in its face plane (level k: the texel split into 2^k × 2^k),
each with its exact solid angle (:func:`ibl_ref.environment.envmap.rect_solid_angle`) and the weight at its centre
direction; a cell inherits its texel's radiance, so the sum over cells converges to I as the cells shrink (the same
as supersampling the cube with nearest-texel copies, but only where it matters).

Refinement, per pixel:

* **grading** (so that narrow lobes cannot fall between cell centres): a cell whose nearest point is γ from the lobe
  axis (its centre angle minus its size) is split until its size 2/(N·2^k) (face-plane side, ≥ its angular size)
  is ≤ ``grade_q``·max(w, ``grade_c``·γ), with w the lobe's narrowest half width at that pixel (GGX: 2θh½·(n·v),
  θh½ the half width at half maximum of D, n·v floored at 1/64; Phong: θ½ = arccos 2^(−1/s)); cells grow
  linearly away from the peak, so the count grows only with log(1/w);
* **error-driven**: each cell carries its own midpoint value and the sum over its four children; |children − own|
  (times the texel's radiance; for a lobe average also the normaliser's share) is the cell's error estimate; while
  a pixel's summed estimate exceeds ``rtol``·max(|I|, ``floor``·mean |I| over the image), its largest-error cells
  are split (the smallest set that carries all but half the tolerance), down to ``max_depth`` levels.

A lobe whose numerator is clipped to n's hemisphere (the reference's Phong convention) has a jump there; a cell cut
by that plane takes its numerator from the part above the plane only (the plane cuts the face plane in a straight
line: the part is the rectangle clipped by a half-plane, its solid angle a fan of spherical triangles, its weight at
its area centroid), so the jump costs no more than a smooth integrand.  The result is the children sums of the leaf
cells; the error estimate (``err``) is the sum of the leaves'
|children − own| (conservative: the children sum is the more accurate one).  Cells whose support is entirely below
the lobe's horizon (``support_axis``·ω < 0 everywhere in the cell, where both weights vanish) are skipped.
``tests/test_unoccluded_reference.py`` checks it against uniform supersampling, closed forms (white furnace: the
GGX albedo of :func:`ibl_ref.lobes.brdfs.albedo`; a linear environment under a Phong lobe) and refinement.

Lobes (``w_num``, ``w_den`` per unit solid angle; r = 2(n·v)n − v):

* :class:`GGXSpecularLobe` — ``f_s(ω, v)(n·ω)⁺`` (Fresnel F0, α = roughness², Smith form), unnormalised;
* :class:`PhongLobe` — ``max(d·ω, 0)^s``, d = r (``axis="mirror"``) or n (``"normal"``), normalised over the whole
  sphere; ``clip=True`` keeps the numerator on n's hemisphere only ([n·ω > 0], the reference renderer's Phong
  convention), ``clip=False`` is the lobe a prefilter sees;
* :class:`SplitSumLobe` — the first factor of Karis's split sum with the true view: GGX sampling pdf
  ``p(ω|v) = D(n·h)(n·h)/(4 v·h)`` weighted by (n·ω)⁺ (h = (v + ω)/|v + ω|), normalised;
* :class:`NVRKernelLobe` — the same with n = v = r: ``K(r·ω) = D(√((1 + r·ω)/2))·max(r·ω, 0)``
  (:func:`ibl_ref.prefilter.karis2013.prefilter_kernel`), normalised.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..conventions import ggx_alpha, lobe_half_angle
from ..environment import envmap
from ..errors import IBLError
from ..environment.validated import as_environment
from ..lobes.brdfs import SMITH_FORMS
from ..lobes.brdfs import ggx
from ..lobes.brdfs import ndf
from ..prefilter.karis2013 import check_f0
from ..prefilter.karis2013 import check_scalar_roughness
from ..progress import track

__all__ = ["GGXSpecularLobe", "PhongLobe", "SplitSumLobe", "NVRKernelLobe", "LobeIntegral", "integrate",
           "ggx_half_width_h", "GGX_MIN_COS_VIEW"]

#: the GGX lobe's width stops shrinking with n·v below this (the error-driven refinement resolves the rest)
GGX_MIN_COS_VIEW = 1.0 / 64.0


def _dot(a, b):
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _reflect(n, v):
    return 2.0 * _dot(n, v)[..., None] * n - v


def ggx_half_width_h(alpha: float) -> float:
    """Half width at half maximum of the GGX NDF in θh: cos²θh = (1 − √2 α²)/(1 − α²) (π/4 for α ≥ 2^(−1/4))."""
    a2 = float(alpha) ** 2
    if a2 >= 1.0 / np.sqrt(2.0):
        return np.pi / 4
    return float(np.arccos(np.sqrt((1.0 - np.sqrt(2.0) * a2) / (1.0 - a2))))


def _check_roughness(roughness) -> tuple:

    return check_scalar_roughness(roughness)


@dataclass(frozen=True)
class GGXSpecularLobe:
    """``f_s(ω, v)·(n·ω)⁺`` of :func:`ibl_ref.lobes.brdfs.ggx` (kd = 0): unnormalised, its integral is the directional
    albedo for L ≡ 1."""

    roughness: float
    f0: float = 1.0
    smith: str = "height_correlated"
    normalised = False

    def __post_init__(self):

        r, _ = _check_roughness(self.roughness)
        object.__setattr__(self, "roughness", r)
        object.__setattr__(self, "f0", check_f0(self.f0))
        if self.smith not in SMITH_FORMS:
            raise IBLError(f"smith must be one of {', '.join(SMITH_FORMS)}, got {self.smith!r}")

    def axis(self, n, v):
        return _reflect(n, v)

    def support_axis(self, n, v):
        return n

    def edges(self, n, v):
        return [n]

    def width(self, n, v):
        ndv = np.clip(_dot(n, v), GGX_MIN_COS_VIEW, 1.0)
        return 2.0 * ggx_half_width_h(ggx_alpha(self.roughness)) * ndv

    def weights(self, n, v, w):

        with np.errstate(divide="ignore", invalid="ignore", under="ignore", over="ignore"):
            f = ggx(w, v, n, roughness=self.roughness, f0=self.f0, kd=0.0, smith=self.smith)
        return f * np.maximum(_dot(n, w), 0.0), None


@dataclass(frozen=True)
class PhongLobe:
    """``max(d·ω, 0)^s`` about d = r (``"mirror"``) or n (``"normal"``), normalised over the whole sphere;
    ``clip``: numerator only on n's hemisphere."""

    s: float
    axis_kind: str = "mirror"
    clip: bool = True
    normalised = True

    def __post_init__(self):
        s = float(self.s)
        if not (np.isfinite(s) and s >= 1.0):
            raise IBLError(f"Phong exponent s must be finite and >= 1, got {self.s!r}")
        if self.axis_kind not in ("mirror", "normal"):
            raise IBLError(f"axis_kind must be 'mirror' or 'normal', got {self.axis_kind!r}")
        object.__setattr__(self, "s", s)

    def axis(self, n, v):
        return n if self.axis_kind == "normal" else _reflect(n, v)

    def support_axis(self, n, v):
        return self.axis(n, v)

    def edges(self, n, v):
        return [self.axis(n, v)]

    def clip_axis(self, n, v):
        """The numerator's clip plane [n·ω > 0] (cells cut by it are integrated over their part above it)."""
        return n if (self.clip and self.axis_kind == "mirror") else None

    def width(self, n, v):
        return np.full(len(n), float(lobe_half_angle(self.s)))

    def weights(self, n, v, w):
        c = np.maximum(_dot(self.axis(n, v), w), 0.0)
        with np.errstate(under="ignore"):
            den = c if self.s == 1.0 else np.power(c, self.s)
        return (den * (_dot(n, w) > 0) if self.clip else den), den


@dataclass(frozen=True)
class _SplitSumFactor:
    """The normalised GGX lobes of the split sum's first factor (one roughness, axis r)."""

    roughness: float
    normalised = True

    def __post_init__(self):
        object.__setattr__(self, "roughness", _check_roughness(self.roughness)[0])

    def axis(self, n, v):
        return _reflect(n, v)


@dataclass(frozen=True)
class SplitSumLobe(_SplitSumFactor):
    """Karis's split-sum first factor with the true view: ``p(ω|v)·(n·ω)⁺``, ``p = D(n·h)(n·h)/(4 v·h)``, normalised."""

    def support_axis(self, n, v):
        return n

    def edges(self, n, v):
        return [n]

    def width(self, n, v):
        return GGXSpecularLobe(self.roughness).width(n, v)

    def weights(self, n, v, w):

        h = v + w
        ln = np.sqrt(_dot(h, h))
        ok = (ln > 1e-12) & (_dot(n, w) > 0)
        h = h / np.where(ln > 1e-12, ln, 1.0)[..., None]
        nh = np.clip(_dot(n, h), 0.0, 1.0)
        vh = _dot(v, h)
        with np.errstate(divide="ignore", invalid="ignore", under="ignore"):
            p = ndf(nh, ggx_alpha(self.roughness)) * nh / (4.0 * vh)
        wt = np.where(ok & (vh > 0), p * np.maximum(_dot(n, w), 0.0), 0.0)
        return wt, wt


@dataclass(frozen=True)
class NVRKernelLobe(_SplitSumFactor):
    """The split sum's n = v = r kernel ``K(r·ω) = D(√((1 + r·ω)/2))·max(r·ω, 0)``, normalised."""

    def support_axis(self, n, v):
        return self.axis(n, v)

    def edges(self, n, v):
        return [self.axis(n, v)]

    def width(self, n, v):
        return np.full(len(n), 2.0 * ggx_half_width_h(ggx_alpha(self.roughness)))

    def weights(self, n, v, w):

        c = np.clip(_dot(self.axis(n, v), w), -1.0, 1.0)
        with np.errstate(under="ignore"):
            k = ndf(np.sqrt(0.5 * (1.0 + c)), ggx_alpha(self.roughness)) * np.maximum(c, 0.0)
        return k, k


@dataclass
class LobeIntegral:
    """Output of :func:`integrate`: ``value`` (P, C), ``err`` (P,) estimate of |value − exact| (channel mean),
    ``num`` (P, C) and ``den`` (P,) (den None for unnormalised lobes), ``info`` (cells, depth, converged)."""

    value: np.ndarray
    err: np.ndarray
    num: np.ndarray
    den: np.ndarray | None
    info: dict = field(default_factory=dict)


_FRAMES = envmap.face_frames("openexr")


def _cell_geometry(f, k, i, j, n_face):
    """Centre directions (M, 3), solid angles (M,) and face-plane sizes (M,) of cells (face f, level k, row i,
    column j; level k has N·2^k cells per face side, k < 0 are blocks of 2^−k × 2^−k texels)."""
    size = 2.0 / (n_face * np.exp2(k))
    u0 = -1.0 + j * size
    v0 = -1.0 + i * size
    om = envmap.rect_solid_angle(u0, u0 + size, v0, v0 + size)
    fr = _FRAMES[f]
    uc, vc = u0 + 0.5 * size, v0 + 0.5 * size
    d = fr[:, 0] + uc[:, None] * fr[:, 1] + vc[:, None] * fr[:, 2]
    d /= np.sqrt(_dot(d, d))[:, None]
    return d, om, size


class _Radiance:
    """∫ L dω over cells: L_texel·Ω for cells inside a texel (k ≥ 0), the exact sums Σ L_j Ω_j of the texel blocks
    for the coarse levels (k < 0)."""

    def __init__(self, a, levels: int):
        self.n = a.shape[1]
        self.C = a.shape[-1]
        self.L = a.reshape(-1, self.C)
        lw = a * envmap.cube_solid_angles(self.n)[..., None]
        self.sums = {}
        for m in range(1, levels + 1):
            b = 2 ** m
            g = self.n // b
            self.sums[-m] = lw.reshape(6, g, b, g, b, self.C).sum(axis=(2, 4)).reshape(-1, self.C)

    def __call__(self, f, k, i, j, om):
        out = np.empty((len(f), self.C))
        fine = k >= 0
        if fine.any():
            kk = k[fine]
            tex = (f[fine] * self.n + (i[fine] >> kk)) * self.n + (j[fine] >> kk)
            out[fine] = self.L[tex] * om[fine, None]
        for lev in np.unique(k[~fine]):
            sel = k == lev
            g = self.n >> int(-lev)
            out[sel] = self.sums[int(lev)][(f[sel] * g + i[sel]) * g + j[sel]]
        return out


class _Cells:
    """Leaf cells of a chunk of pixels: geometry, own and children midpoint values, edge terms."""

    __slots__ = ("px", "f", "k", "i", "j", "own", "fine", "fine_rgb", "own_den", "fine_den", "edge_num", "edge_den",
                 "gamma", "size")

    def __init__(self, **kw):
        for k_, v_ in kw.items():
            setattr(self, k_, v_)

    def take(self, sel):
        return _Cells(**{s: getattr(self, s)[sel] for s in self.__slots__})

    @staticmethod
    def concat(parts):
        return _Cells(**{s: np.concatenate([getattr(p, s) for p in parts]) for s in _Cells.__slots__})

    def __len__(self):
        return len(self.px)


def _triangle_solid_angle(a, b, c):
    """Solid angle of the spherical triangle of unit vectors a, b, c (Van Oosterom & Strackee 1983):
    tan(Ω/2) = |a·(b×c)| / (1 + a·b + b·c + c·a)."""
    num = np.abs(_dot(a, np.cross(b, c)))
    den = 1.0 + _dot(a, b) + _dot(b, c) + _dot(c, a)
    return 2.0 * np.arctan2(num, den)


def _above_part(f, k, i, j, n_face, a):
    """The part of each cell above the plane a·ω = 0: its centre direction (area centroid in the face plane) and
    exact solid angle.  A plane through the origin cuts a face plane in a straight line, so the part is the cell's
    rectangle clipped by a half-plane (≤ 5 vertices), its solid angle a fan of spherical triangles."""
    size = 2.0 / (n_face * np.exp2(k))
    u0 = -1.0 + j * size
    v0 = -1.0 + i * size
    fr = _FRAMES[f]
    c0, cu, cv = _dot(a, fr[:, 0]), _dot(a, fr[:, 1]), _dot(a, fr[:, 2])
    U = np.stack([u0, u0 + size, u0 + size, u0], axis=1)
    V = np.stack([v0, v0, v0 + size, v0 + size], axis=1)
    L = c0[:, None] + cu[:, None] * U + cv[:, None] * V  # (M, 4) signed height of the corners
    pu, pv, ok = [], [], []
    for e in range(4):
        e2 = (e + 1) % 4
        la, lb = L[:, e], L[:, e2]
        pu.append(U[:, e])
        pv.append(V[:, e])
        ok.append(la > 0)
        t = np.where(la != lb, la / np.where(la != lb, la - lb, 1.0), 0.0)
        pu.append(U[:, e] + t * (U[:, e2] - U[:, e]))
        pv.append(V[:, e] + t * (V[:, e2] - V[:, e]))
        ok.append((la > 0) != (lb > 0))
    pu, pv, ok = np.stack(pu, 1), np.stack(pv, 1), np.stack(ok, 1)  # (M, 8) polygon slots in order
    order = np.argsort(~ok, axis=1, kind="stable")  # valid slots first, in polygon order
    pu = np.take_along_axis(pu, order, 1)
    pv = np.take_along_axis(pv, order, 1)
    cnt = ok.sum(axis=1)
    P = fr[:, None, 0] + pu[..., None] * fr[:, None, 1] + pv[..., None] * fr[:, None, 2]  # (M, 8, 3) on the plane
    Pn = P / np.sqrt(_dot(P, P))[..., None]
    om = np.zeros(len(f))
    cx = np.zeros(len(f))
    cy = np.zeros(len(f))
    ar = np.zeros(len(f))
    for t in range(1, 7):  # fan (0, t, t + 1)
        on = cnt > t + 1
        if not on.any():
            break
        om[on] += _triangle_solid_angle(Pn[on, 0], Pn[on, t], Pn[on, t + 1])
        x0, y0, x1, y1, x2, y2 = pu[on, 0], pv[on, 0], pu[on, t], pv[on, t], pu[on, t + 1], pv[on, t + 1]
        at = 0.5 * np.abs((x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0))
        ar[on] += at
        cx[on] += at * (x0 + x1 + x2) / 3.0
        cy[on] += at * (y0 + y1 + y2) / 3.0
    uc = np.where(ar > 0, cx / np.where(ar > 0, ar, 1.0), u0 + 0.5 * size)
    vc = np.where(ar > 0, cy / np.where(ar > 0, ar, 1.0), v0 + 0.5 * size)
    d = fr[:, 0] + uc[:, None] * fr[:, 1] + vc[:, None] * fr[:, 2]
    d /= np.sqrt(_dot(d, d))[:, None]
    return d, om


def _contributions(lobe, npx, vpx, d, om, f, k, i, j, n_face, clip, radiance):
    """Per cell: the numerator w·∫L (M, C), the normaliser w_den·Ω (M,) or None, and ∫L (M, C); a cell cut by the
    clip plane takes its numerator from its part above the plane (its radiance spread evenly over the cell)."""
    R = radiance(f, k, i, j, om)
    num, den = lobe.weights(npx, vpx, d)
    num = num[:, None] * R
    if clip is not None:
        h = _dot(clip, d)
        cut = np.abs(h) < np.sin(np.minimum(0.75 * 2.0 / (n_face * np.exp2(k)), np.pi / 2))
        if cut.any():
            dd, oo = _above_part(f[cut], k[cut], i[cut], j[cut], n_face, clip[cut])
            wn, _ = lobe.weights(npx[cut], vpx[cut], dd)
            num[cut] = np.where(oo > 0, wn * oo / om[cut], 0.0)[:, None] * R[cut]
    return num, (None if den is None else den * om), R


def _evaluate(lobe, n_face, n, v, axis, edges, clip, radiance, px, f, k, i, j):
    """Cells with their own value, the sum over their four children and the edge term (module docstring)."""
    d, om, size = _cell_geometry(f, k, i, j, n_face)
    npx, vpx = n[px], v[px]
    cpx = None if clip is None else clip[px]
    own_rgb, own_den, R = _contributions(lobe, npx, vpx, d, om, f, k, i, j, n_face, cpx, radiance)
    # a cell cut by an edge of the weight (a great circle a·ω = 0 where it jumps or kinks) may hide what lies on
    # the other side of the edge from all five sample points: its error term is the weight at the point of the
    # cell farthest above the edge times the cell's radiance integral
    edge_num = np.zeros(len(px))
    edge_den = np.zeros(len(px))
    rc = np.sin(np.minimum(0.75 * size, np.pi / 2))  # ≥ sin(the cell's angular radius)
    rbar = R.mean(axis=1)
    for e in edges:
        ax = e[px]
        h = _dot(ax, d)
        cut = np.abs(h) < rc
        if cut.any():
            up = d[cut] + (rc[cut] - h[cut])[:, None] * ax[cut]
            up /= np.sqrt(_dot(up, up))[:, None]
            wn, wd = lobe.weights(npx[cut], vpx[cut], up)
            edge_num[cut] = np.maximum(edge_num[cut], wn * rbar[cut])
            if wd is not None:
                edge_den[cut] = np.maximum(edge_den[cut], wd * om[cut])
    fine_rgb = np.zeros_like(own_rgb)
    fine_den = None if own_den is None else np.zeros(len(px))
    for a in (0, 1):
        for b in (0, 1):
            ci, cj, ck = 2 * i + a, 2 * j + b, k + 1
            dc, omc, _ = _cell_geometry(f, ck, ci, cj, n_face)
            cn, cd, _ = _contributions(lobe, npx, vpx, dc, omc, f, ck, ci, cj, n_face, cpx, radiance)
            fine_rgb += cn
            if cd is not None:
                fine_den += cd
    gamma = np.arccos(np.clip(_dot(axis[px], d), -1.0, 1.0))
    z = np.zeros(len(px))
    return _Cells(px=px, f=f, k=k, i=i, j=j, own=own_rgb.mean(axis=1), fine=fine_rgb.mean(axis=1), fine_rgb=fine_rgb,
                  own_den=z if own_den is None else own_den, fine_den=z if fine_den is None else fine_den,
                  edge_num=edge_num, edge_den=edge_den, gamma=gamma, size=size)


def _top_cells(n_face, k0):
    """(f, i, j) of every cell of level ``k0`` ≤ 0 (blocks of 2^−k0 texels)."""
    g = n_face >> (-k0)
    f = np.repeat(np.arange(6), g * g)
    i = np.tile(np.repeat(np.arange(g), g), 6)
    j = np.tile(np.arange(g), 6 * g)
    return f, i, j


def _initial(lobe, n_face, k0, n, v, axis, edges, clip, sup, radiance, pix):
    """Every top cell of every pixel in ``pix``, minus those wholly below the lobe's support horizon."""
    f, i, j = _top_cells(n_face, k0)
    d, _, size = _cell_geometry(f, np.full(len(f), k0), i, j, n_face)
    rad = min(1.5 * float(size[0]), np.pi / 2)  # ≥ the angular radius of a cell
    keep = (sup[pix] @ d.T) > -np.sin(rad)  # (P_chunk, T)
    pp, tt = np.nonzero(keep)
    return _evaluate(lobe, n_face, n, v, axis, edges, clip, radiance, pix[pp], f[tt], np.full(len(tt), k0,
                                                                                             dtype=np.int64),
                     i[tt], j[tt])


def _cell_errors(c: _Cells, value):
    """Error estimate of each cell in numerator units: |children − own| + the edge term (channel means), plus the
    value times the normaliser's (for a lobe average, ``value`` per cell)."""
    e = np.abs(c.fine - c.own) + c.edge_num
    if value is not None:
        e = e + value * (np.abs(c.fine_den - c.own_den) + c.edge_den)
    return e


def _children(c: _Cells):
    f = np.repeat(c.f, 4)
    k = np.repeat(c.k + 1, 4)
    a = np.tile([0, 0, 1, 1], len(c))
    b = np.tile([0, 1, 0, 1], len(c))
    return np.repeat(c.px, 4), f, k, 2 * np.repeat(c.i, 4) + a, 2 * np.repeat(c.j, 4) + b


def integrate(cube, lobe, normals, views, *, rtol: float = 1e-3, floor: float = 0.1, floor_value: float | None = None,
              max_depth: int = 12, coarse_levels: int = 3, grade_q: float = 0.5, grade_c: float = 0.5,
              chunk_cells: int = 300_000, max_cells_per_pixel: int = 400_000, progress: bool = False) -> LobeIntegral:
    """The exact unoccluded integral of ``lobe`` at every pixel (module docstring).

    Parameters
    ----------
    cube : (6, N, N, C) radiance (finite, ≥ 0)
    lobe : :class:`GGXSpecularLobe`, :class:`PhongLobe`, :class:`SplitSumLobe`, :class:`NVRKernelLobe` (or any
        object with ``normalised``, ``axis``, ``support_axis``, ``width``, ``weights``)
    normals, views : (P, 3) unit shading normals and view directions (toward the viewer)
    rtol : per-pixel target of the error estimate, relative to max(|I|, floor·mean |I|)
    floor_value : the absolute floor instead (e.g. shared by several integrals of one image)
    max_depth : finest cell level (texel split into 2^max_depth per axis)
    coarse_levels : the refinement starts from blocks of 2^coarse_levels × 2^coarse_levels texels (fewer where the
        face size has fewer factors 2), whose radiance is their exact sum Σ L_j Ω_j
    grade_q, grade_c : the grading rule (module docstring)
    chunk_cells : cells per chunk of pixels (memory ≈ 200 bytes × chunk_cells × 5)
    max_cells_per_pixel : refinement stops there (``info["converged"]`` False)
    """

    a = as_environment(cube, "environment cube map").data
    n_face = a.shape[1]
    C = a.shape[-1]
    k0 = 0  # the top level: blocks of 2^−k0 texels, as many halvings as the face size has (≤ coarse_levels)
    while -k0 < int(coarse_levels) and n_face % (2 ** (1 - k0)) == 0:
        k0 -= 1
    radiance = _Radiance(a, -k0)
    n = envmap.unit_directions(np.asarray(normals, dtype=np.float64).reshape(-1, 3), "normals")
    v = envmap.unit_directions(np.asarray(views, dtype=np.float64).reshape(-1, 3), "views")
    if n.shape != v.shape:
        raise IBLError(f"normals and views must have the same shape, got {n.shape} and {v.shape}")
    if not (rtol > 0 and np.isfinite(rtol)):
        raise IBLError(f"rtol must be a finite number > 0, got {rtol!r}")
    P = len(n)
    axis = lobe.axis(n, v)
    axis = axis / np.maximum(np.sqrt(_dot(axis, axis)), 1e-300)[:, None]
    sup = lobe.support_axis(n, v)
    edges = [np.asarray(e, dtype=np.float64) for e in lobe.edges(n, v)]
    clip = getattr(lobe, "clip_axis", lambda n_, v_: None)(n, v)
    clip = None if clip is None else np.asarray(clip, dtype=np.float64)
    width = np.maximum(np.asarray(lobe.width(n, v), dtype=np.float64), 1e-9)
    num = np.zeros((P, C))
    den = np.zeros(P) if lobe.normalised else None
    err = np.zeros(P)
    n_top = 6 * (n_face >> -k0) ** 2
    step = max(1, chunk_cells // n_top)
    # pass 1: midpoint sums over the top cells give the image's scale for the floor of the relative target
    if floor_value is None:
        coarse = np.zeros(P)
        f0_, i0_, j0_ = _top_cells(n_face, k0)
        kk = np.full(len(f0_), k0)
        d0, om0, _ = _cell_geometry(f0_, kk, i0_, j0_, n_face)
        r0 = radiance(f0_, kk, i0_, j0_, om0).mean(axis=1)
        for s0 in range(0, P, step):
            sl = np.arange(s0, min(P, s0 + step))
            px = np.repeat(sl, len(d0))
            wn, wd = lobe.weights(n[px], v[px], np.tile(d0, (len(sl), 1)))
            c0 = wn.reshape(len(sl), -1) @ r0
            if wd is not None:
                c0 = c0 / np.maximum((wd * np.tile(om0, len(sl))).reshape(len(sl), -1).sum(axis=1), 1e-300)
            coarse[sl] = c0
        floor_value = float(floor) * float(np.mean(np.abs(coarse))) if P else 0.0
    floor_value = float(floor_value)
    n_cells, depth_max, converged = 0, k0, True

    def retire(cells, pix_sel):
        """Add the cells' sums to their pixels (every cell of those pixels is final)."""
        nonlocal n_cells, depth_max, converged
        px = cells.px
        for c in range(C):
            num[:, c] += np.bincount(px, cells.fine_rgb[:, c], P)
        if lobe.normalised:
            d_p = np.bincount(px, cells.fine_den, P)
            den[:] += d_p
            val = num.mean(axis=1)[px] / np.maximum(den[px], 1e-300)
            err[:] += np.bincount(px, _cell_errors(cells, val), P) / np.maximum(den, 1e-300) * (
                np.bincount(px, minlength=P) > 0)
        else:
            err[:] += np.bincount(px, _cell_errors(cells, None), P)
        cnt = np.bincount(px, minlength=P)[pix_sel]
        converged &= bool(np.all(cnt < max_cells_per_pixel))
        n_cells += len(cells)
        depth_max = max(depth_max, int(cells.k.max(initial=k0)))

    for s0 in track(range(0, P, step), "unoccluded reference", unit="chunk", enabled=progress):
        pix = np.arange(s0, min(P, s0 + step))
        cells = _initial(lobe, n_face, k0, n, v, axis, edges, clip, sup, radiance, pix)
        while len(cells):
            loc = cells.px - s0
            tot_num = np.bincount(loc, cells.fine, len(pix))
            if lobe.normalised:
                tot_den = np.maximum(np.bincount(loc, cells.fine_den, len(pix)), 1e-300)
                val = tot_num / tot_den
                e = _cell_errors(cells, val[loc])
                target = rtol * np.maximum(np.abs(val), floor_value) * tot_den
            else:
                e = _cell_errors(cells, None)
                target = rtol * np.maximum(np.abs(tot_num), floor_value)
            # grading: split cells larger than grade_q·max(w, grade_c·γ') (γ' = distance of the cell's nearest point)
            g = np.maximum(cells.gamma - cells.size, 0.0)
            forced = (cells.size > grade_q * np.maximum(width[cells.px], grade_c * g)) & (cells.k < max_depth)
            e_tot = np.bincount(loc, e, len(pix))
            counts = np.bincount(loc, minlength=len(pix))
            need = (e_tot > target) & (counts < max_cells_per_pixel)
            chosen = forced.copy()
            sel = np.flatnonzero(need[loc])
            if len(sel):
                ls, es = loc[sel], e[sel]
                order = np.lexsort((-es, ls))  # by pixel, largest error first
                es, ls = es[order], ls[order]
                cs = np.cumsum(es)
                cnt = np.bincount(ls, minlength=len(pix))
                start = np.r_[0, np.cumsum(cnt)[:-1]]
                before = cs - es - np.repeat((cs - es)[start[cnt > 0]], cnt[cnt > 0])
                pick = (before < (e_tot[ls] - 0.5 * target[ls])) & (cells.k[sel[order]] < max_depth)
                chosen[sel[order[pick]]] = True
            # pixels without a cell to split are final: their cells leave the working set
            busy = np.bincount(loc, chosen, len(pix)) > 0
            done = ~busy[loc]
            if done.any():
                retire(cells.take(done), pix[~busy])
            if not chosen.any():
                break
            keep = cells.take(~chosen & ~done)
            new = _evaluate(lobe, n_face, n, v, axis, edges, clip, radiance, *_children(cells.take(chosen)))
            cells = _Cells.concat([keep, new])
    value = num / np.maximum(den, 1e-300)[:, None] if lobe.normalised else num.copy()
    if not np.all(np.isfinite(value)):
        raise IBLError("unoccluded reference: non-finite result")
    info = dict(n_cells=int(n_cells), cells_per_pixel=n_cells / max(P, 1), max_depth_used=depth_max,
                converged=converged, rtol=float(rtol), floor_value=floor_value,
                err_rel_l1=float(err.sum() / max(np.abs(value.mean(axis=1)).sum(), 1e-300)))
    return LobeIntegral(value=value, err=err, num=num, den=den, info=info)
