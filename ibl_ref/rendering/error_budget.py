"""Error budget of Knuth et al. (2014)'s method: from the exact image to Eq. 5, one approximation at a time.

The paper's renderer (Sec. 3.4, Eq. 5, :mod:`ibl_ref.rendering.render`) replaces the exact visibility-weighted Phong
lobe average by a chain of approximations.  This module defines an image for every link of that chain, so that
each approximation can be measured alone (the experiment ``error-budget`` reports them).  Notation: pixel x with
shading normal n, face normal n_f, view v, reflection r = 2(n·v)n − v; a material (kd, ks, g) per mesh, s = 1/(1−g)
(Eq. 3); lobe weight w_s(d, ω) = max(d·ω, 0)^s; the diffuse term uses d = n, s = 1, the glossy term d = r;
texels j of the N² cube with exact solid angles Ω_j and centres ω_j; median-cut regions R_i (Sec. 3.1) with light
direction ω_i (the region's energy centroid) and solid angle Ω_i.  Every image is kd·(diffuse) + ks·(glossy).

**0 — reference** (:func:`ibl_ref.rendering.reference_render.render_reference`, converged): the exact
visibility-weighted lobe average (Eq. 4 normalised as a lobe average, with Eq. 5's visibility inside the integral)

    A(x) = ∫ L(ω) V(x, ω) [n·ω > 0] w_s(d, ω) dω / ∫ w_s(d, ω) dω,

V the binary visibility of direction ω from x (the receiver's own plane blocks: n_f·ω ≤ 0 → 0); one-sided
shading: pixels with n·v ≤ 0 are black (docs/background.md §8).

**1 — regions** (one exact visibility per region): V(x, ω) is replaced, inside each region, by the visibility of
the region's light direction:

    c₁ = Σ_i V(x, ω_i) · P̃_i(x),   P̃_i = Σ_{j∈R_i} L_j [n·ω_j > 0] w_s(d, ω_j) Ω_j / Σ_j w_s(d, ω_j) Ω_j

(:func:`region_lobes` with normals; V(x, ω_i) from :func:`ibl_ref.rendering.render.light_visibilities`,
``method="raycast"``, which includes the receiver's plane).  The lobe is summed at the map's texel centres (the
lab's exact Eq. 4 quadrature, :func:`ibl_ref.groundtruth.phong_convolution.lobe_average`) instead of the
reference's converged quadrature, so this step also holds that (small) quadrature difference.  With one region per
texel (:func:`ibl_ref.knuth2014.median_cut.texel_lights`) on finer and finer nearest-texel copies of the same map,
c₁ converges to A (:func:`texel_limit_image`).

**2 — lobe_hemisphere**: the per-texel clip [n·ω_j > 0] is dropped, P̃_i → P_i = the exact partial environment
map look-up (:func:`ibl_ref.rendering.reference_render.exact_pem_lookup`): a PEM is looked up by direction and
glossiness only and cannot know n, so the glossy lobe of a grazing r now reaches below the surface.  (Diffuse:
w_1(n, ω) is already 0 below n's horizon, so the step is exactly 0.)

**3 — vsm**: V(x, ω_i) → VSM_i(x) · [n_f·ω_i > 0], one variance shadow map per light blurred from the region's
solid angle (Sec. 3.3/4, :func:`ibl_ref.rendering.vsm.build_vsm`); the receiver's plane is kept through the horizon
term, so this step is the shadow map alone.

**4 — horizon**: the horizon term [n_f·ω_i > 0] (the renderer's ``horizon=True`` / ``--horizon``) is dropped: the
paper's Eq. 5 (``horizon=False``, the default), in which a shadow map does not see the receiver's own surface
(an open ground quad is its own first occluder, t ≈ μ) and lights below the tangent plane count as visible.

**5 — prefilter**: P_i → the paper's filter pyramid of PEM i (2×2 shrink + 5×5 sqrt-cos filter, Sec. 3.2, Fig. 2;
:func:`ibl_ref.knuth2014.pem.build_pems`; any other level-chain method of the prefilter registry with
``budget_terms(..., prefilter=NAME)``) read by one trilinear look-up at the **best constant level** ℓ*(s) of this
map: the level (grid 0.05, or the calibrated one if better) whose look-up of the whole map (Σ_i PEM_i) has the
smallest rel. L1 against the exact lobe average at 4000 seeded directions uniform on the sphere
(:func:`ibl_ref.knuth2014.gloss_lookup.best_constant_level`; the ``lobe-chain`` experiment's ``rel_l1_best_level``).
This step is the filter shape alone, at the level the best possible g → level mapping would pick for this map
(fitting ℓ* to the image's own look-up directions instead would favour images with few distinct directions: every
ground pixel of the diffuse ground has the same normal).

**6 — gloss_lookup**: ℓ*(s) → the paper's g → level mapping ℓ(s_Phong(g)) (lobe-volume calibration, Sec. 3.2/5,
:func:`ibl_ref.knuth2014.gloss_lookup.lookup`).  Image = Eq. 5 as :func:`ibl_ref.rendering.render.render_pem` computes
it (``visibility="vsm"``, ``horizon=False``) on the front-facing pixels.

**7 — back_faces**: the pixels with n·v ≤ 0 (inside the spout and handle), black in the one-sided reference, get
their Eq. 5 value: the image is now exactly :func:`render_pem`'s.  A convention difference, not an approximation;
it is reported so that the steps add up to the whole error.

Every image after step 0 is a point of a small configuration space (:data:`SWITCHES`: visibility, hemisphere,
horizon, prefilter, level, back faces) and every step flips one switch, so the steps can be taken in another order
(:func:`check_order`: ``prefilter`` after ``lobe_hemisphere`` — a filtered PEM has no normal — and
``gloss_lookup`` after ``prefilter``).  In orders where ``horizon`` comes before ``vsm``, the exact visibility
without the horizon term counts only *other* geometry (``light_visibilities(..., horizon=False)``).

**Shares** (:func:`budget_rows`).  Errors do not add: |Σδ| ≤ Σ|δ|.  For each step k with image I_k (I_0 the
reference) the rows give the cumulative error of I_k against the reference (rel. L1 Σ|I_k − I_0|/Σ|I_0| and RMSE)
and the **increment** δ_k = I_k − I_{k−1} (its rel. L1 Σ|δ_k|/Σ|I_0|, RMSE and signed bias Σδ_k/Σ I_0); the **share**
of step k is its increment's rel. L1 divided by the sum of all increments' rel. L1 (shares sum to 1; the sum of
increments is ≥ the final error, equal only when no two steps cancel).  The signed biases do add up: Σ_k bias_k =
the final image's bias.  A share depends on the order of the steps (the increment of a step is measured at the
configuration the previous steps left), which :func:`walk` can show by reordering.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import IBLError
from ..groundtruth.phong_convolution import lobe_average
from ..knuth2014.gloss_lookup import best_constant_level
from ..knuth2014.gloss_lookup import level_fit_directions
from ..knuth2014.median_cut import texel_lights
from ..prefilter.registry import build_region_prefilters
from .render import eq5_lookups
from .render import horizon_term
from .render import light_visibilities
from .render import shade_eq5

__all__ = ["STEPS", "DEFAULT_ORDER", "SWITCHES", "BudgetTerms", "budget_terms", "check_order", "swapped_order",
           "configuration", "budget_image", "walk", "budget_rows", "region_lobes", "texel_limit_image",
           "material_weights"]

STEPS = ("regions", "lobe_hemisphere", "vsm", "horizon", "prefilter", "gloss_lookup", "back_faces")
DEFAULT_ORDER = STEPS
#: step → (switch, value after step 1 "regions", value in the paper's method)
SWITCHES = {"lobe_hemisphere": ("hemisphere", True, False), "vsm": ("visibility", "exact", "vsm"),
            "horizon": ("horizon", True, False), "prefilter": ("prefilter", "exact", "prefiltered"),
            "gloss_lookup": ("level", "best", "paper"), "back_faces": ("back_faces", "black", "shaded")}


def check_order(order) -> tuple:
    """Validate a step order (a permutation of :data:`STEPS`, ``regions`` first, ``prefilter`` after
    ``lobe_hemisphere``, ``gloss_lookup`` after ``prefilter``) → tuple."""
    order = tuple(order)
    if sorted(order) != sorted(STEPS):
        raise IBLError(f"step order must be a permutation of {', '.join(STEPS)}; got {', '.join(order)}")
    if order[0] != "regions":
        raise IBLError("step order: 'regions' (reference → one visibility per region) must come first")
    if order.index("prefilter") < order.index("lobe_hemisphere"):
        raise IBLError("step order: 'prefilter' must come after 'lobe_hemisphere' (a filtered PEM has no normal)")
    if order.index("gloss_lookup") < order.index("prefilter"):
        raise IBLError("step order: 'gloss_lookup' must come after 'prefilter' (the level of a pyramid look-up)")
    return order


def swapped_order(a: str, b: str, order=DEFAULT_ORDER) -> tuple:
    """``order`` with steps ``a`` and ``b`` exchanged (validated by :func:`check_order`)."""
    order = list(order)
    for x in (a, b):
        if x not in order:
            raise IBLError(f"unknown step {x!r}; steps: {', '.join(STEPS)}")
    i, j = order.index(a), order.index(b)
    order[i], order[j] = order[j], order[i]
    return check_order(order)


def configuration(done) -> dict:
    """The switches after the steps ``done`` (any subset of :data:`STEPS` containing ``regions``)."""
    return {sw: (v1 if step in done else v0) for step, (sw, v0, v1) in SWITCHES.items()}


def material_weights(material_id, materials) -> tuple:
    """Per-pixel kd (P, 1), ks (P, 1) and g (P,) from material ids and ``{id: (kd, ks, g)}`` (scalars; g < 1)."""
    mid = np.asarray(material_id).reshape(-1)
    kd, ks, g = np.zeros((len(mid), 1)), np.zeros((len(mid), 1)), np.zeros(len(mid))
    for m in np.unique(mid):
        if int(m) not in materials:
            raise IBLError(f"no material for material id {int(m)} (have {sorted(materials)})")
        mk, ms, mg = (float(x) for x in materials[int(m)])
        if not (mk >= 0 and ms >= 0 and np.isfinite(mk) and np.isfinite(ms)):
            raise IBLError(f"kd, ks must be finite and >= 0, got {mk}, {ms}")
        if not (0.0 <= mg < 1.0):
            raise IBLError(f"the error budget needs g in [0, 1) (a finite Phong exponent), got {mg}")
        sel = mid == m
        kd[sel], ks[sel], g[sel] = mk, ms, mg
    return kd, ks, g


def region_lobes(cube, lights, dirs, s: float, normals=None, chunk: int = 512) -> np.ndarray:
    """Exact per-region lobe averages (L, P, C) at directions ``dirs`` (P, 3): P_i, or P̃_i with ``normals``.

    P_i(d) = Σ_{j∈R_i} L_j w_s(d, ω_j) Ω_j / Σ_j w_s(d, ω_j) Ω_j (= :func:`~ibl_ref.rendering.reference_render.exact_pem_lookup`);
    with ``normals`` (P, 3) the numerator is clipped to [n·ω_j > 0] (module docstring, step 1).
    """

    out = lobe_average(cube, dirs, s, labels=lights.labels, n_regions=len(lights), normals=normals, chunk=chunk)
    return np.moveaxis(np.asarray(out).reshape(len(np.asarray(dirs).reshape(-1, 3)), len(lights), -1), 1, 0)


def _group_lookups(fn, kd, ks, g, n, r):
    """(pem_n, pem_r) (L, P, C) or None, from ``fn(dirs, s, sel)`` → (L, |sel|, C) per lobe kind and exponent."""
    P = len(n)
    out = []
    for dirs, w, sv in ((n, kd[:, 0], np.ones(P)), (r, ks[:, 0], 1.0 / (1.0 - g))):
        on = w > 0
        if not on.any():
            out.append(None)
            continue
        arr = None
        for s in np.unique(sv[on]):
            sel = np.flatnonzero(on & (sv == s))
            part = fn(dirs[sel], float(s), sel)
            if arr is None:
                arr = np.zeros((part.shape[0], P, part.shape[2]))
            arr[:, sel] = part
        out.append(arr)
    return tuple(out)


@dataclass
class BudgetTerms:
    """The ingredients of every configuration of one (scene, environment, material set, lights): computed lazily.

    Attributes
    ----------
    mask : (H, W) covered pixels; front : (P,) n·v > 0
    kd, ks : (P, 1); g : (P,) per-pixel material
    level_dirs : (K, 3) the directions the best level is fitted on (default 4000 seeded uniform directions,
        :func:`ibl_ref.knuth2014.gloss_lookup.level_fit_directions`, those of the ``lobe-chain`` experiment)
    best_levels : {s: {"level": ℓ*, "rel_l1": the whole map's look-up error there, "paper_level": ℓ(g),
        "paper_rel_l1": its error}} at the fit directions (step 5; = ``lobe-chain``'s ``rel_l1_best_level`` and
        ``rel_l1`` for the sqrt-cos pyramid)
    lookup_rel_l1_image : {s: {"best": …, "paper": …}} the same two look-up errors at the image's own look-up
        directions (unoccluded)
    """

    scene: object
    gbuffer: object
    cube: np.ndarray
    lights: object
    pems: object
    kd: np.ndarray
    ks: np.ndarray
    g: np.ndarray
    vsm_resolution: int = 256
    vsm_kw: dict = field(default_factory=dict)
    level_step: float = 0.05
    level_dirs: np.ndarray | None = None
    best_levels: dict = field(default_factory=dict)
    lookup_rel_l1_image: dict = field(default_factory=dict)
    _vis: dict = field(default_factory=dict, repr=False)
    _look: dict = field(default_factory=dict, repr=False)

    @property
    def mask(self):
        return self.gbuffer.mask

    @property
    def front(self):
        m = self.gbuffer.mask
        return np.sum(self.gbuffer.normal[m] * self.gbuffer.view[m], axis=1) > 0

    def _px(self, name):
        return getattr(self.gbuffer, name)[self.gbuffer.mask]

    def visibility(self, kind: str, horizon: bool) -> np.ndarray:
        """VIS (L, P): ``"exact"`` (binned ray caster, with or without the receiver's plane) or ``"vsm"``
        (× the horizon term if ``horizon``)."""

        key = (kind, bool(horizon))
        if key not in self._vis:
            P, fn = self._px("position"), self._px("face_normal")
            if kind == "exact":
                self._vis[key] = light_visibilities(self.scene, P, fn, self.lights, method="raycast",
                                                    horizon=None if horizon else False)
            elif kind == "vsm":
                if ("vsm", False) not in self._vis:
                    self._vis[("vsm", False)] = light_visibilities(
                        self.scene, P, fn, self.lights, method="vsm", vsm_resolution=self.vsm_resolution,
                        horizon=False, **self.vsm_kw)
                if horizon:
                    self._vis[key] = self._vis[("vsm", False)] * horizon_term(fn, self.lights.directions)
            else:
                raise IBLError(f"visibility kind must be 'exact' or 'vsm', got {kind!r}")
        return self._vis[key]

    def lookups(self, prefilter: str, hemisphere: bool, level: str):
        """(pem_n, pem_r) of Eq. 5 for a prefilter configuration (module docstring, steps 1, 2, 5, 6):
        ``prefilter`` ``"exact"`` (per-region lobe averages) or ``"prefiltered"`` (the PEMs ``pems``)."""

        key = ("exact", bool(hemisphere)) if prefilter == "exact" else ("prefiltered", level)
        if key in self._look:
            return self._look[key]
        n, r = self._px("normal"), self._px("reflect")
        if prefilter == "exact":
            nrm = n if hemisphere else None
            val = _group_lookups(lambda d, s, sel: region_lobes(self.cube, self.lights, d, s,
                                                                None if nrm is None else nrm[sel]),
                                 self.kd, self.ks, self.g, n, r)
        elif prefilter == "prefiltered" and level == "paper":
            val = eq5_lookups(self.pems, n, r, self.g, self.kd, self.ks)
        elif prefilter == "prefiltered" and level == "best":
            val = _group_lookups(lambda d, s, sel: self.pems.lookup_all_at_level(d, self._best_level(d, s, sel)),
                                 self.kd, self.ks, self.g, n, r)
        else:
            raise IBLError(f"unknown prefilter configuration {prefilter!r}/{level!r}")
        self._look[key] = val
        return val

    def _best_level(self, dirs, s, sel) -> float:
        """ℓ*(s): the best constant level of the whole map's look-up at the fit directions (step 5)."""

        key = float(s)
        if key not in self.best_levels:
            g = 1.0 - 1.0 / s
            fit = self.level_dirs
            exact = lobe_average(self.cube, fit, s)
            per_level = [self.pems.lookup_all_at_level(fit, k).sum(axis=0) for k in range(self.pems.n_levels)]
            err, lev = best_constant_level(per_level, exact, self.level_step)
            paper = self.pems.full_lookup(fit, g)
            err_paper = float(np.abs(paper - exact).sum() / np.abs(exact).sum())
            paper_level = float(self.pems.calibration.level_of(s))  # ℓ(s_Phong(g)) of the paper's look-up
            if err_paper < err:  # the calibrated level is a candidate too (as in the lobe-chain experiment)
                err, lev = err_paper, paper_level
            self.best_levels[key] = dict(level=float(lev), rel_l1=float(err), paper_level=paper_level,
                                         paper_rel_l1=err_paper)
        lev = self.best_levels[key]["level"]
        # the same two look-ups at the image's own directions (for the record)
        ex = lobe_average(self.cube, dirs, s)
        den = np.abs(ex).sum()
        self.lookup_rel_l1_image.setdefault(key, dict(
            best=float(np.abs(self.pems.lookup_all_at_level(dirs, lev).sum(axis=0) - ex).sum() / den),
            paper=float(np.abs(self.pems.full_lookup(dirs, 1.0 - 1.0 / s) - ex).sum() / den)))
        return float(lev)


def budget_terms(scene, gbuffer, cube, lights, materials, *, pems=None, prefilter: str = "pyramid",
                 prefilter_params: dict | None = None, vsm_resolution: int = 256, level_step: float = 0.05,
                 level_dirs=4000, **vsm_kw) -> BudgetTerms:
    """The :class:`BudgetTerms` of a scene (prepared meshes), its G-buffer, a cube map (6, N, N, C), median-cut
    ``lights`` and ``materials`` ``{material_id: (kd, ks, g)}``.  ``pems``: the PEM set of those lights (default:
    :func:`ibl_ref.prefilter.registry.build_region_prefilters` with method ``prefilter`` and ``prefilter_params``,
    the paper's pyramid, :func:`ibl_ref.knuth2014.pem.build_pems`; step 5 needs a level chain: the look-ups at a
    given level); ``level_dirs``: the directions (K, 3) the best level ℓ* is fitted on, or their number (seeded
    uniform directions); ``vsm_kw`` go to the shadow maps."""

    fit = np.asarray(level_fit_directions(level_dirs) if np.ndim(level_dirs) == 0 else level_dirs, dtype=np.float64)
    if fit.ndim != 2 or fit.shape[1] != 3 or len(fit) < 1:
        raise IBLError(f"level_dirs must be a number of directions or a (K, 3) array, got shape {fit.shape}")

    a = np.asarray(cube, dtype=np.float64)
    if a.ndim == 3:
        a = a[..., None]
    if pems is None:
        pems = build_region_prefilters(a, lights, method=prefilter, **(prefilter_params or {}))
    if not hasattr(pems, "lookup_all_at_level"):
        raise IBLError(f"error budget: the PEMs of prefilter {prefilter!r} are not a level chain (step 5 reads "
                       "them at the best constant level); choose a level-chain method")
    kd, ks, g = material_weights(gbuffer.material_id[gbuffer.mask], materials)
    return BudgetTerms(scene=scene, gbuffer=gbuffer, cube=a, lights=lights, pems=pems, kd=kd, ks=ks, g=g,
                       vsm_resolution=int(vsm_resolution), vsm_kw=dict(vsm_kw), level_step=float(level_step),
                       level_dirs=fit)


def budget_image(terms: BudgetTerms, config: dict) -> np.ndarray:
    """The image (H, W, C) of one configuration (:func:`configuration`), 0 off the geometry."""

    vis = terms.visibility(config["visibility"], config["horizon"])
    pem_n, pem_r = terms.lookups(config["prefilter"], config["hemisphere"], config["level"])
    c = shade_eq5(vis, pem_n, pem_r, terms.kd, terms.ks)
    if config["back_faces"] == "black":
        c = c * terms.front[:, None]
    img = np.zeros(terms.mask.shape + (c.shape[-1],))
    img[terms.mask] = c
    return img


def walk(terms: BudgetTerms, order=DEFAULT_ORDER) -> list:
    """``[(step, configuration, image), …]`` for the steps of ``order`` (:func:`check_order`), in that order."""
    order = check_order(order)
    out = []
    for k, step in enumerate(order):
        cfg = configuration(order[:k + 1])
        out.append((step, cfg, budget_image(terms, cfg)))
    return out


def budget_rows(reference, images, mask) -> list:
    """Metrics of a walk (module docstring, "Shares"): one dict per step, reference first.

    ``reference`` (H, W, C); ``images`` [(step, image), …] in walk order; ``mask`` (H, W) covered pixels.  Keys:
    step, rel_l1_vs_ref_frac, rmse_vs_ref_radiance, bias_vs_ref_frac, rel_l1_increment_frac,
    rmse_increment_radiance, bias_increment_frac, share_of_increments_frac, rel_l1_change_frac.
    """
    ref = np.asarray(reference, dtype=np.float64)[mask]
    den = float(np.abs(ref).sum())
    if not den > 0:
        raise IBLError("the reference image is zero on the covered pixels: relative errors undefined")
    rows, prev = [], ref
    prev_l1 = 0.0
    rows.append(dict(step="reference", rel_l1_vs_ref_frac=0.0, rmse_vs_ref_radiance=0.0, bias_vs_ref_frac=0.0,
                     rel_l1_increment_frac=0.0, rmse_increment_radiance=0.0, bias_increment_frac=0.0,
                     share_of_increments_frac=0.0, rel_l1_change_frac=0.0))
    for step, img in images:
        cur = np.asarray(img, dtype=np.float64)[mask]
        e, d = cur - ref, cur - prev
        l1 = float(np.abs(e).sum() / den)
        rows.append(dict(step=step, rel_l1_vs_ref_frac=l1, rmse_vs_ref_radiance=float(np.sqrt(np.mean(e ** 2))),
                         bias_vs_ref_frac=float(e.sum() / ref.sum()), rel_l1_increment_frac=float(np.abs(d).sum() / den),
                         rmse_increment_radiance=float(np.sqrt(np.mean(d ** 2))),
                         bias_increment_frac=float(d.sum() / ref.sum()), rel_l1_change_frac=l1 - prev_l1))
        prev, prev_l1 = cur, l1
    tot = sum(q["rel_l1_increment_frac"] for q in rows)
    for q in rows[1:]:
        q["share_of_increments_frac"] = q["rel_l1_increment_frac"] / tot if tot > 0 else 0.0
    return rows


def texel_limit_image(scene, gbuffer, cube, materials, factor: int = 1, *, pixels=None, chunk: int = 128,
                      progress: bool = False):
    """Step 1 with one region per texel of the map's nearest-texel copy at face size ``factor``·N → (H, W, C).

    The piecewise-constant radiance is the reference's; only the visibility (one exact ray per texel, along its
    centre) and the lobe quadrature (texel centres) differ, and both → exact as ``factor`` grows, so this image
    converges to the reference (the check of step 1 on its own).  Back-facing pixels are black (one-sided).
    ``materials``: ``{id: (kd, ks, g)}``, or a list of such dicts (then a list of images, sharing the visibility
    rays); ``pixels``: optional (H, W) bool — shade only these covered pixels (the others are 0).
    """

    a = np.asarray(cube, dtype=np.float64)
    if a.ndim == 3:
        a = a[..., None]
    if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
        raise IBLError(f"factor must be a positive integer, got {factor!r}")
    k = int(factor)
    a = np.repeat(np.repeat(a, k, axis=1), k, axis=2)
    lights = texel_lights(a)
    m = gbuffer.mask if pixels is None else gbuffer.mask & np.asarray(pixels, dtype=bool)
    P, n, fn, r = gbuffer.position[m], gbuffer.normal[m], gbuffer.face_normal[m], gbuffer.reflect[m]
    front = np.sum(n * gbuffer.view[m], axis=1) > 0
    vis = light_visibilities(scene, P, fn, lights, method="raycast", progress=progress)
    sets = materials if isinstance(materials, (list, tuple)) else [materials]
    out = []
    for mats in sets:
        kd, ks, g = material_weights(gbuffer.material_id[m], mats)
        c = np.zeros((len(P), a.shape[-1]))
        for i in range(0, len(P), chunk):
            sl = slice(i, min(i + chunk, len(P)))
            nn, rr = n[sl], r[sl]
            pem_n, pem_r = _group_lookups(lambda d, s, sel: region_lobes(a, lights, d, s, nn[sel]),
                                          kd[sl], ks[sl], g[sl], nn, rr)
            c[sl] = shade_eq5(vis[:, sl], pem_n, pem_r, kd[sl], ks[sl])
        img = np.zeros(m.shape + (a.shape[-1],))
        img[m] = c * front[:, None]
        out.append(img)
    return out if isinstance(materials, (list, tuple)) else out[0]
