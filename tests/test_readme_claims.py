"""The numbers of the "Claims and measured numbers" table (``docs/results/claims.md``, from
``tests/data/readme_runs/claims/claims.csv``; the README of commit 537f533 held it) and the other experiment
numbers of the documentation that no other test pins.  Each is recomputed by an independent route where one exists
(brute force, a closed form, a second implementation, quadrature) and compared with the number as printed; where
the number can only come from the lab's own code (a fit's RMS, a count on a G-buffer) the test says so and pins it
as a regression check.

Where each number is pinned (benchmark timings are measured in ``benchmarks/``, never in tests):

========================================================  =====================================================
number (as printed)                                        test
========================================================  =====================================================
box filter s = 1: 15.3 % / 19.4 % at 64², never ≈ 4 %      :func:`test_box_filter_s1_error_under_every_reading` (also
                                                           ``check_fig4``/``check_fig5`` of test_experiments_quick)
sqrt-cos near box at s = 1, better at higher s             ``check_claims`` (test_experiments_quick)
cosine filter "always below 10 %": 26 % before level 1     :func:`test_cosine_filter_exceeds_10_percent_before_level_1`
energy: +185 % corner, −50 % centre, random < 0.5 %        ``check_claims`` (test_experiments_quick)
Fig. 8: 42 published numbers, rows, MIP factor 2           tests/test_memory_model.py
sparse PEMs 10.8× … 64.5× at 128²                          :func:`test_sparse_pem_storage_at_128`
sparse PEMs 11.4× … 80.5× at 256²                          saved full run (test_readme_saved_runs)
lights alone: 0.017 at s = 1, 0.80 at s = 1000             :func:`test_point_lights_fail_for_glossy_lobes` (quick size)
render-error: 153 MiB chain vs 36 MiB PEMs                 :func:`test_exact_lobe_chain_memory`
render-error percentages (full run, minutes)               saved full run (test_readme_saved_runs); meaning at
                                                           quick size: ``check_render_error``
error-budget tables, text and swap (full run, 16 min)      saved full run + one case re-run (test_readme_saved_runs)
lobe-chain: best level 28.9 % / 20.0 % at s = 1, ranges,   :func:`test_pyramid_floor_at_s1`,
4.3× (7.7×) memory                                         :func:`test_exact_lobe_chain_memory`
lobe-chain: chain rows, ranges, floors, memory ratios      saved full run + one case re-run (test_readme_saved_runs)
speed-accuracy: 8.9e-7 at 32², 0 bound violations          :func:`test_auto_convolution_error_at_32`
speed-accuracy at 64² / 128², routes and kernels           saved full run (test_readme_saved_runs)
kan-table1: times, bounds, exact gather                    saved full run (test_readme_saved_runs); bounds at 32²:
                                                           :func:`test_auto_convolution_error_at_32`
km00-render: BRDF RMS 0.32 vs 0.43                         :func:`test_greedy_lobes_have_lower_brdf_rms`
km00-render image errors (full run, 4 min)                 saved full run (test_readme_saved_runs)
median-cut equivalent lobes 2.9 … 323 (10.8), …            :func:`test_equivalent_lobes_of_median_cut_regions`
Meunier: paper's statistics inconsistent                   :func:`test_meunier_published_statistics_are_inconsistent`
Meunier: product-fit mean 9.9e-4 (full run)                saved full run (test_readme_saved_runs); quick analogue
                                                           within a factor 3: ``check_cosine_lobes``
method-zoo tables and Karis statements                     saved full run + one case re-run (test_readme_method_zoo)
cross-validate table (4 min 48 s, Mitsuba)                 quick analogue, target: ``check_cross_validate``
reference at 128²: back-facing pixels                      :func:`test_back_facing_pixels_of_the_default_view`
solid angles sum to 4π within 1.1e-14 (1 … 2048)          :func:`test_solid_angles_sum_to_4pi_within_the_readme_bound`
DWAB negatives 42 … 2382, f = 1.5e-10 … 3.7e-9             :func:`test_dwab_negatives_of_the_probe_like_files`
========================================================  =====================================================

``check_*`` are in tests/test_experiments_quick.py.  Tolerances: where a number is reproduced at the printed number's own
size, the printed rounding (half a unit of its last digit); where only a smaller size is affordable, the measured
difference between the two sizes is stated.
"""

from __future__ import annotations

import numpy as np
import pytest

from ibl_ref.environment.envmap import cube_solid_angles, texel_directions


def dense_lobe_average(cube, dirs, s, chunk=256):
    """Exact normalised Phong lobe average Σ L·max(d·ω, 0)^s·Ω / Σ max(d·ω, 0)^s·Ω over every texel of ``cube`` (exact
    solid angles), written out here as a dense sum; returns (average (P, C), denominator (P,))."""
    n = cube.shape[1]
    tex, om = texel_directions(n).reshape(-1, 3), cube_solid_angles(n).reshape(-1)
    rad = cube.reshape(-1, cube.shape[-1])
    avg, den = np.empty((len(dirs), rad.shape[1])), np.empty(len(dirs))
    for a in range(0, len(dirs), chunk):
        w = np.maximum(dirs[a:a + chunk] @ tex.T, 0.0) ** s * om
        den[a:a + chunk] = w.sum(axis=1)
        avg[a:a + chunk] = (w @ rad) / den[a:a + chunk, None]
    return avg, den


# ---- Knuth Sec. 5: lobe errors of the filter pyramid, by brute force through the pyramid's own samplers ----------
class WhiteTexelLobe:
    """The response of a pyramid to one white texel (face +Z, texel (N/2, N/2)), as the Sec. 5 analysis defines it,
    computed here without :mod:`ibl_ref.knuth2014.lobe_analysis`: the trilinear lookup at continuous level ℓ is
    (1 − t)·B_L + t·B_{L+1} (bilinear look-ups of levels L = ⌊ℓ⌋ and L + 1 at the level-0 texel centres); the lobe
    is peak-normalised; volumes are sums with exact texel solid angles; the level for s is found by bisection on
    the volume (it decreases monotonically towards finer levels)."""

    def __init__(self, n, kernel, order="shrink_then_filter"):
        from ibl_ref.knuth2014.pyramid import build_pyramid

        cube = np.zeros((6, n, n, 1))
        cube[4, n // 2, n // 2, 0] = 1.0
        pyr = build_pyramid(cube, kernel=kernel, order=order, dtype=np.float64)
        self.dirs = texel_directions(n).reshape(-1, 3)
        self.w = cube_solid_angles(n).reshape(-1)
        self.cos0 = self.dirs @ texel_directions(n)[4, n // 2, n // 2]
        self.B = [pyr.sampler(k).bilinear(self.dirs)[:, 0] for k in range(pyr.n_levels)]
        self.max_level = pyr.max_level
        self._v_int = {}

    def lobe(self, ell):
        k = min(int(np.floor(ell)), self.max_level - 1)
        t = ell - k
        f = (1.0 - t) * self.B[k] + t * self.B[k + 1]
        return f / f.max()

    @staticmethod
    def target_volume(s, volume):
        return 2 * np.pi / (s + 1) if volume == "integral" else 2 * np.pi / (3 * (3 * s + 1))

    def volume(self, f, volume, w=None):
        w = self.w if w is None else w
        return float(f @ w) if volume == "integral" else float((f**3) @ w / 3.0)

    def _support(self, k):
        """Directions where level k or k + 1 responds (outside, the blended lobe is exactly 0)."""
        m = (self.B[k] != 0) | (self.B[k + 1] != 0)
        return self.B[k][m], self.B[k + 1][m], self.w[m]

    def fit(self, s, volume):
        """Level whose lobe has the target volume (None if clipped at either end), bisected to 1e-12 level."""
        vt = self.target_volume(s, volume)
        if volume not in self._v_int:
            self._v_int[volume] = [self.volume(self.lobe(float(k)), volume) for k in range(self.max_level + 1)]
        v = self._v_int[volume]
        if v[-1] < vt or v[0] > vt:
            return None
        k = next(i for i in range(1, len(v)) if v[i] >= vt)
        a, b, w = self._support(k - 1)
        lo, hi = 0.0, 1.0
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            f = (1.0 - mid) * a + mid * b
            lo, hi = (mid, hi) if self.volume(f / f.max(), volume, w) < vt else (lo, mid)
        return k - 1 + 0.5 * (lo + hi)

    def error_pct(self, s, volume, ell):
        """Volume of the symmetric difference to max(cos θ, 0)^s around the white texel, % of the target volume."""
        f, t = self.lobe(ell), np.maximum(self.cos0, 0.0) ** s
        d = np.abs(f - t) @ self.w if volume == "integral" else np.abs(f**3 - t**3) @ self.w / 3.0
        return 100.0 * float(d) / self.target_volume(s, volume)


def test_box_filter_s1_error_under_every_reading():
    # Quoted: "box ... its error is 15.3 % (∫f dω volume) / 19.4 % (⅓∫f³ dω volume) at 64², not 4 %; no reading
    # tried gives 4 %".  Both pyramid orders × both volume definitions (white texel at a face centre, target on the
    # texel's direction); ±0.05 %-points is the printed rounding.  "Roughly 4 %" would be within a factor 2
    # (2–8 %): every reading is above 8 % (measured 15.3 / 19.4 / 22.2 / 23.0 %)
    errs = {}
    for order in ("shrink_then_filter", "filter_then_shrink"):
        lobe = WhiteTexelLobe(64, "box", order)
        for volume in ("integral", "radial"):
            errs[order, volume] = lobe.error_pct(1.0, volume, lobe.fit(1.0, volume))
    assert errs["shrink_then_filter", "integral"] == pytest.approx(15.3, abs=0.05)
    assert errs["shrink_then_filter", "radial"] == pytest.approx(19.4, abs=0.05)
    assert min(errs.values()) > 8.0, errs


def test_cosine_filter_exceeds_10_percent_before_level_1():
    # Quoted: "cosine filter always below 10 %": not reproduced (26 % before the lookup reaches level 1), from
    # `ibl-ref experiment claims` at its full size: 128² faces, 40 exponents from 1 to the texel limit
    # (lobe_analysis.s_grid), the "mid range" 2 ≤ s with a fitted level ≥ 1, volume ∫f dω, shrink-then-filter.
    # Recomputed here by brute force on the same exponents; ±0.5 %-points is the printed rounding.  The maximum
    # sits on the spike where the level approaches 1, so it depends on the sampled exponents (25.3 % on the quick
    # run's 24 exponents at 64²)
    from ibl_ref.knuth2014.lobe_analysis import s_grid

    lobe = WhiteTexelLobe(128, "cos")
    errs = []
    for s in s_grid(128, 40):
        ell = lobe.fit(float(s), "integral")
        if s >= 2 and ell is not None and ell >= 1:
            errs.append(lobe.error_pct(float(s), "integral", ell))
    assert len(errs) > 20
    assert max(errs) == pytest.approx(26.0, abs=0.5)
    assert sum(e > 10.0 for e in errs) > 1  # the claim fails at more than one exponent


# ---- Knuth Fig. 8 and Sec. 3.1: sparse PEM storage ----------------------------------------------------------------
def test_sparse_pem_storage_at_128():
    # Quoted: "lossless 10.8× (12 regions) … 64.5× (96) at 128²" (sky+sun; 12 and 96 are the ends of the sweep).
    # Dense bytes in closed form (float32 RGB, full MIP chain: L · 3 · 4 B · 6 · Σ n_l²); sparse bytes recounted from
    # the stored tiles (data + 20 B of metadata each); ratios to the printed rounding (±0.05)
    from ibl_ref.knuth2014.sparse_pem import build_sparse_pems
    from ibl_ref.synthetic.synthetic_envs import make_env

    cube = make_env("sky_sun", 128)
    for regions, ratio in ((12, 10.8), (96, 64.5)):
        sp = build_sparse_pems(cube, n_lights=regions, rtol=0.0, chunk=8)
        dense = regions * 3 * 4 * 6 * sum((128 >> k) ** 2 for k in range(8))
        assert sp.dense_nbytes == dense
        stored = sum(t.data.nbytes + 20 for reg in sp.tiles for ts in reg.values() for t in ts)
        assert sp.nbytes == stored
        assert dense / stored == pytest.approx(ratio, abs=0.05)


# ---- Sec. 1: point lights alone fail for glossy surfaces ----------------------------------------------------------
def test_point_lights_fail_for_glossy_lobes():
    # Quoted: "24 median-cut point lights: rel. L1 0.017 at s = 1, 0.80 at s = 1000 (sky+sun)", from
    # `ibl-ref experiment lights-vs-error` at 64² faces and a 128² px sphere (measured again this session: 0.0173,
    # 0.802; 4 min).  Here at its quick size (32², 48² px), with the exact lobe average as a dense sum written out
    # here (not the experiment's brute force) on the 2× supersampled map: 0.0169 and 0.821.  Tolerances: the
    # printed rounding plus the measured size effect, ±0.001 at s = 1 (0.0004) and ±0.03 at s = 1000 (0.019)
    from ibl_ref.knuth2014.median_cut import median_cut
    from ibl_ref.rendering.sphere_render import orthographic_sphere
    from ibl_ref.synthetic.synthetic_envs import make_env

    cube = make_env("sky_sun", 32)
    fine = np.repeat(np.repeat(cube, 2, axis=1), 2, axis=2)  # the same piecewise-constant radiance, 2× quadrature
    _, _, r = orthographic_sphere(48)
    lights = median_cut(cube, 24, "per-face")
    got = {}
    for s in (1.0, 1000.0):
        exact, den = dense_lobe_average(fine, r, s)
        # the lights' estimate of the same normalised average: Σ_i rgb_i max(r·ω_i, 0)^s / Σ_texels max(r·ω, 0)^s Ω
        approx = (np.maximum(r @ lights.directions.T, 0.0) ** s) @ lights.rgb / den[:, None]
        got[s] = float(np.abs(approx - exact).sum() / np.abs(exact).sum())
    assert got[1.0] == pytest.approx(0.017, abs=0.001)
    assert got[1000.0] == pytest.approx(0.80, abs=0.03)


# ---- the exact-lobe chain: memory (render-error, lobe-chain) ------------------------------------------------------
@pytest.mark.parametrize("factor,ratio", [(2.0, 4.3), (np.sqrt(2.0), 7.7)])
def test_exact_lobe_chain_memory(factor, ratio):
    # Quoted: "chain: 153 MiB vs 36 MiB for 96 PEMs at 64²" (render-error, factor 2) and "4.3× (7.7×) the memory"
    # (lobe-chain, factor 2 (√2); the README once said 7.8× from MiB rounded to two decimals, 2.90 / 0.37).  Level sizes
    # by the chain's rule, written out here: level exponents s = 1·f^k up to the last whose half-width
    # arccos(2^(−1/s)) still spans a 64² texel (2/64 rad), each level the smallest power of two ≥ 8 texels with
    # 2 texels (2/n rad) per half-width, at most 64; plus level 0 (the input).  The pyramid: 64², 32², …, 1².
    # float32 RGB.  Ratios and MiB to the printed rounding
    from ibl_ref.knuth2014.lobe_chain import chain_spec

    s = [1.0]
    while np.arccos(2.0 ** (-1.0 / (s[-1] * factor))) >= 2.0 / 64:
        s.append(s[-1] * factor)
    sizes = [64]
    for x in s[::-1]:
        need, n = 2 * 2.0 / np.arccos(2.0 ** (-1.0 / x)), 8
        while n < need and n < 64:
            n *= 2
        sizes.append(min(n, 64))
    assert tuple(sizes) == chain_spec(64, factor=factor).face_sizes
    chain = sum(6 * n * n * 3 * 4 for n in sizes)
    pyramid = sum(6 * (64 >> k) ** 2 * 3 * 4 for k in range(7))
    assert chain / pyramid == pytest.approx(ratio, abs=0.05)
    if factor == 2.0:
        assert 96 * chain / 2**20 == pytest.approx(153, abs=0.5)
        assert 96 * pyramid / 2**20 == pytest.approx(36, abs=0.5)


def test_pyramid_floor_at_s1():
    # Quoted (lobe-chain, 64², 4000 random directions): "the best constant level (any glossiness calibration) does not
    # fix it: 28.9 % / 20.0 % at s = 1" (sky+sun / studio), and the paper's sqrt-cos pyramid lies in 20–52 % / 8–22 %.
    # The exact s = 1 lobe average by a dense sum written out here (dense_lobe_average); the
    # best level on the experiment's grid (step 0.05) of (1 − t)·B_k + t·B_{k+1}; the same directions
    # (default_rng(20141)).  ±0.05 %-points: the printed rounding
    from ibl_ref.knuth2014.gloss_lookup import lookup
    from ibl_ref.knuth2014.pyramid import build_pyramid
    from ibl_ref.synthetic.synthetic_envs import make_env

    rng = np.random.default_rng(20141)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for env_name, floor, (lo, hi) in (("sky_sun", 28.9, (20, 52)), ("studio", 20.0, (8, 22))):
        env = make_env(env_name, 64)
        exact, _ = dense_lobe_average(env, d, 1.0)
        pyr = build_pyramid(env)
        B = [pyr.sampler(k).bilinear(d) for k in range(pyr.n_levels)]
        rel = lambda a: 100 * float(np.abs(a - exact).sum() / np.abs(exact).sum())  # noqa: E731
        best = min(rel((1 - t) * B[k] + t * B[k + 1]) for k in range(pyr.max_level) for t in np.arange(0, 1, 0.05))
        best = min(best, rel(B[-1]))
        assert best == pytest.approx(floor, abs=0.05)
        paper = rel(lookup(pyr, d, 0.0))
        assert lo <= paper <= hi and paper >= best


# ---- the ground-truth convolution: speed-accuracy and Kán Table 1 --------------------------------------------------
@pytest.mark.same_without_tools
def test_auto_convolution_error_at_32():
    # Quoted: "auto convolution at rtol 1e-3 (1e5 sun near a corner): max rel. error ... 8.9e-7 at 32²; 0 texels
    # anywhere above a method's reported bound" (speed-accuracy, 7 exponents; at 32² its reference is every texel)
    # and Kán's 8 exponents (kan-table1; its numbers are pinned by test_readme_saved_runs).  At 32², against the dense
    # exact sum (phong_convolution.convolve_exact_many, float64): the largest relative error of the speed-accuracy sweep
    # to the printed rounding (±0.05e-6), every texel within its reported bound (plus 1e-12 of float64 rounding in
    # the 6N²-term reference sums, as the experiment allows); every bound of both sweeps within the requested rtol
    from ibl_ref.experiments.kan_table1 import EXPONENTS as KAN_EXPONENTS
    from ibl_ref.experiments.speed_accuracy import EXPONENTS, environment
    from ibl_ref.groundtruth.convolve import convolve
    from ibl_ref.groundtruth.phong_convolution import convolve_exact_many

    cube = environment(32)
    res = convolve(cube, list(EXPONENTS), method="auto", rtol=1e-3)
    worst = 0.0
    for s, exact in zip(EXPONENTS, convolve_exact_many(cube, list(EXPONENTS))):
        rel = (np.abs(res.maps[s] - exact) / exact).max(axis=-1)
        assert np.all(rel <= res.error_bound[s] + 1e-12), s
        worst = max(worst, float(rel.max()))
    assert worst == pytest.approx(8.9e-7, abs=0.05e-7)
    for exps in (EXPONENTS, KAN_EXPONENTS):
        res = convolve(cube, list(exps), method="auto", rtol=1e-3)
        assert max(float(b.max()) for b in res.error_bound.values()) <= 1e-3


# ---- Kautz & McCool 2000: greedy lobes vs one lobe -----------------------------------------------------------------
def test_greedy_lobes_have_lower_brdf_rms():
    # Quoted (km00-render): "the greedy minimum-profile lobes ... although their BRDF RMS is lower, 0.32 vs 0.43":
    # Ward kd 0, ks 0.8, α 0.04 at the full run's 16 view elevations 0 … 80°, default profile sampling; the relative
    # RMS of the fit over the hemisphere (kautz_mccool2000.rms_error), to the printed rounding (±0.005).  And what
    # the greedy construction guarantees: each lobe is fitted to what the previous ones left, so 3 lobes are never
    # worse than the first alone
    from ibl_ref.lobes import brdfs, kautz_mccool2000 as km

    f = brdfs.get_brdf("ward", kd=0.0, ks=0.8, alpha=0.04)
    thetas = np.radians(np.linspace(0.0, 80.0, 16))
    multi = [km.fit_multi_lobe(f, t, 3) for t in thetas]
    single = [km.fit_single_lobe(f, t) for t in thetas]
    assert km.rms_error(multi, 3) == pytest.approx(0.32, abs=0.005)
    assert km.rms_error(single) == pytest.approx(0.43, abs=0.005)
    assert km.rms_error(multi, 3) <= km.rms_error(multi, 1)


# ---- Meunier et al. 2009 -----------------------------------------------------------------------------------------
def test_equivalent_lobes_of_median_cut_regions():
    # Quoted: "sky+sun 128², per-face cut: 24 regions 2.9 … 323 (median 10.8), 96 regions 9.2 … 70 492 (median 61;
    # the smallest region holds the sun); studio, 96 regions: 3.4 … 1 140 (median 106)", at the README's size,
    # to its rounding.  The exponents of the two extreme regions of each cut are recomputed from Meunier Eq. 32
    # by brute force: the cap of the region's solid angle, then the e minimising ∫(cap − max(cos β, 0)^e)² dω by
    # adaptive quadrature and a bounded scalar search (not meunier2009's closed-form derivative and root), rel.
    # 1e-5 (the search's tolerance on log e)
    from scipy import integrate, optimize

    from ibl_ref.knuth2014.median_cut import median_cut
    from ibl_ref.synthetic.synthetic_envs import make_env

    def eq32_exponent(omega):
        # in x = 1 − cos β (dω = 2π dx): the cap is x ≤ x0 = Ω/2π; below the horizon (x > 1) both are 0
        x0 = omega / (2 * np.pi)

        def err(u):
            e = np.exp(u)
            inside, _ = integrate.quad(lambda x: (1.0 - (1.0 - x) ** e) ** 2, 0.0, x0, epsabs=0, epsrel=1e-12)
            outside, _ = integrate.quad(lambda x: (1.0 - x) ** (2 * e), x0, 1.0, epsabs=0, epsrel=1e-12,
                                        points=[min(x0 + 50 / e, 1.0)], limit=200)
            return inside + outside

        alpha = np.arccos(1.0 - x0)

        guess = np.log(2 * 0.9613 / alpha**2)  # the small-α (Gaussian) limit
        return float(np.exp(optimize.minimize_scalar(err, bounds=(guess - 3, guess + 3), method="bounded",
                                                     options=dict(xatol=1e-7)).x))

    want = {("sky_sun", 24): (2.9, 323, 10.8, (0.05, 0.5, 0.05)),
            ("sky_sun", 96): (9.2, 70492, 61, (0.05, 0.5, 0.5)),
            ("studio", 96): (3.4, 1140, 106, (0.05, 5, 0.5))}
    for (env, n_lights), (lo, hi, med, tol) in want.items():
        lights = median_cut(make_env(env, 128), n_lights, "per-face")
        e = np.asarray(lights.equivalent_lobes().exponent)
        assert e.min() == pytest.approx(lo, abs=tol[0])
        assert e.max() == pytest.approx(hi, abs=tol[1])
        assert float(np.median(e)) == pytest.approx(med, abs=tol[2])
        for i in (int(np.argmin(e)), int(np.argmax(e))):
            assert e[i] == pytest.approx(eq32_exponent(float(lights.solid_angle[i])), rel=1e-5)


def test_meunier_published_statistics_are_inconsistent():
    # Quoted: "the paper's own statistics are inconsistent: median 0 with variance 1.2e-8 < mean²".  For a
    # non-negative error X with median 0, P(X > 0) ≤ ½, so by Cauchy–Schwarz E[X]² = E[X·1{X>0}]² ≤ E[X²]·½, i.e.
    # Var X = E[X²] − E[X]² ≥ E[X]²: the published variance would have to be at least the squared mean
    from ibl_ref.experiments.cosine_lobes import PAPER_MEAN_ABS_ERR, PAPER_VAR_ABS_ERR

    assert (PAPER_MEAN_ABS_ERR, PAPER_VAR_ABS_ERR) == (7.1379e-4, 1.2091e-8)  # as published (Sec. 4.1)
    assert PAPER_VAR_ABS_ERR < PAPER_MEAN_ABS_ERR**2 / 40  # short of the bound by a factor > 40


# ---- the reference renderer's default view ------------------------------------------------------------------------
def test_back_facing_pixels_of_the_default_view():
    # Quoted (reference at 128²): the view of `ibl-ref render --mode reference --size 128` has pixels whose shading
    # normal faces away from the viewer (n·v ≤ 0), black under the one-sided convention: 3 with the teapot's lid
    # ledge (the run quoted there, on the teapot before the ledge, had 24).  The CLI's own camera from its parser
    # defaults; counted on the G-buffer
    from ibl_ref.cli import build_parser
    from ibl_ref.cli.cmd_render import _camera
    from ibl_ref.rendering.raster import rasterize
    from ibl_ref.rendering.scenes import teapot_on_ground

    args = build_parser().parse_args(["render", "--mode", "reference", "--size", "128", "--out", "unused.npz"])
    meshes = teapot_on_ground(args.mesh, ground=args.ground)
    g = rasterize(meshes, _camera(args, meshes[:1]))
    back = g.mask & (np.sum(g.normal * g.view, axis=-1) <= 0)
    assert int(back.sum()) == 3
    assert np.all(g.material_id[back] == 0)  # on the teapot (inside spout/handle), never the ground


# ---- conventions and real probes ---------------------------------------------------------------------------------
def test_solid_angles_sum_to_4pi_within_the_readme_bound():
    # Quoted (Conventions): exact texel solid angles "sum to 4π within 1.1e-14 at every face size tested from 1 to
    # 2048" (tests/test_envmap.py checks each size against 1e-12; this pins the README's number, measured 1.07e-14)
    from ibl_ref.environment.envmap import cube_solid_angles as omega

    sizes = list(range(1, 65)) + [100, 127, 128, 255, 256, 511, 512, 1000, 1024, 2047, 2048]
    assert max(abs(float(omega(n).sum()) - 4 * np.pi) for n in sizes) <= 1.1e-14


def test_dwab_negatives_of_the_probe_like_files(tmp_path):
    # Quoted (Real light probes) / docs/background.md §6: DWAB's ringing leaves "42 … 2382 negatives at H = 32 … 512
    # (minimum ≈ −5e-6, f = 1.5e-10 … 3.7e-9)" on probe_files.sky_sun_latlong written with the OpenEXR binding
    # (3.5 here: a different DWAB codec may ring differently), suns 1e4 … 6e4.  Counts exact; f, the removed share of
    # ∫|L| dω, to the printed rounding; every minimum of the order the README's "≈ −5e-6" states, in [−1e-5, −1e-6]
    # (measured −1.7e-6 at H = 32 … −7.7e-6 at H = 128)
    from ibl_ref.environment import exr_io
    from ibl_ref.environment.probe_files import sky_sun_latlong, write_probe_exr

    counts, f, mins = {}, [], []
    for h in (32, 64, 128, 256, 512):
        for sun in (1e4, 6e4):
            img, _ = sky_sun_latlong(h, sun=sun)
            rep = exr_io.read_envmap(write_probe_exr(tmp_path / f"p{h}.exr", img), negative="clamp").radiance
            counts.setdefault(h, set()).add(rep.n_negative)
            f.append(rep.removed_fraction)
            mins.append(rep.negative_min)
    assert counts == {32: {42}, 64: {165}, 128: {609}, 256: {1143}, 512: {2382}}
    assert min(f) == pytest.approx(1.5e-10, abs=0.05e-10) and max(f) == pytest.approx(3.7e-9, abs=0.05e-9)
    assert all(-1e-5 <= m <= -1e-6 for m in mins)
