"""Tests of ibl_ref.knuth2014.gloss_lookup (Knuth et al. 2014 Eq. 3 and the trilinear glossiness lookup)."""

import functools
import warnings

import numpy as np
import pytest

from ibl_ref.environment.envmap import cube_solid_angles, face_uv_to_direction, texel_directions
from ibl_ref.errors import IBLError
from ibl_ref.knuth2014.gloss_calibration import calibrate
from ibl_ref.knuth2014.gloss_lookup import (
    DATA_DIR,
    Calibration,
    analytic_calibration,
    get_calibration,
    lookup,
    phong_exponent,
)
from ibl_ref.knuth2014.pyramid import build_pyramid

SHIPPED = sorted(DATA_DIR.glob("calibration_*.json"))


@functools.lru_cache(maxsize=2)
def _one_texel_pyramid(n, kernel, order, seam, shrink):
    """Pyramid of the calibration's map (one white texel, face +Z, texel (N/2, N/2)), the level-0 texel
    directions and exact solid angles, and their cosines to the white texel's direction."""
    cube = np.zeros((6, n, n, 1))
    cube[4, n // 2, n // 2, 0] = 1.0
    pyr = build_pyramid(cube, kernel=kernel, order=order, seam=seam, dtype=np.float64, shrink=shrink)
    d0 = texel_directions(n)[4, n // 2, n // 2]
    d = texel_directions(n).reshape(-1, 3)
    return pyr, d0, d, cube_solid_angles(n).reshape(-1), d @ d0


def lobe_volume_through_lookup(cal: Calibration, s: float, cap: bool = True) -> float:
    """Volume of the run-time lookup's lobe at glossiness g = 1 − 1/s under table ``cal``, by brute force.

    Knuth Sec. 5 defines the calibration: a black map with one white texel (face +Z, texel (N/2, N/2)) is
    filtered into the pyramid and read back through the glossiness lookup; the lobe's volume (peak-normalised,
    ∫f dω or ⅓∫f³ dω, on the level-0 texel centres with exact solid angles) must equal the target cosˢ lobe's,
    2π/(s+1) or 2π/(3(3s+1)) in closed form.  This sums the lookup's own output (:func:`lookup`, the trilinear
    run-time path) directly; the table was made by :mod:`ibl_ref.knuth2014.lobe_analysis`'s moment polynomial and
    bisection, a different route.  ``cap``: only directions that can see a non-zero texel of the two levels
    blended (angle from the white texel ≤ the farthest non-zero texel centre + two texel diagonals of the
    coarser level, ≤ 2·2√2/m rad on an m² face), outside which bilinear lookups are exactly 0.
    """
    pyr, d0, d, w, cos0 = _one_texel_pyramid(cal.face_size, cal.kernel, cal.order, cal.seam, cal.shrink)
    ell = float(cal.level_of(s))
    if cap:
        reach = 0.0
        for lev in pyr.levels[int(np.floor(ell)):int(np.floor(ell)) + 2]:
            m = lev.shape[1]
            nz = texel_directions(m)[lev[..., 0] != 0]
            reach = max(reach, float(np.arccos(np.clip(nz @ d0, -1, 1)).max()) + 2 * 2 * np.sqrt(2) / m)
        if reach < np.pi:
            sel = cos0 >= np.cos(reach)
            d, w = d[sel], w[sel]
    f = lookup(pyr, d, 1.0 - 1.0 / s, calibration=cal)[:, 0]
    f = f / f.max()
    return float(f @ w) if cal.volume == "integral" else float((f**3) @ w / 3.0)


def target_volume(s: float, volume: str) -> float:
    return 2 * np.pi / (s + 1) if volume == "integral" else 2 * np.pi / (3 * (3 * s + 1))


def test_phong_exponent_eq3():
    # Eq. 3 by hand: g=0 -> 1, g=0.5 -> 2, g=0.9 -> 10
    assert np.allclose(phong_exponent(np.array([0.0, 0.5, 0.9])), [1.0, 2.0, 10.0], rtol=1e-12)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert phong_exponent(1.0) == np.inf
        assert np.isinf(phong_exponent(np.array([1.0, 0.2]))[0])


@pytest.mark.parametrize("g", [-0.1, 1.5, np.nan])
def test_bad_gloss(g):
    with pytest.raises(IBLError, match="g"):
        phong_exponent(g)
    p = build_pyramid(np.ones((6, 4, 4, 1)))
    with pytest.raises(IBLError, match=r"g must be in \[0, 1\]"):
        lookup(p, np.array([[0.0, 0.0, 1.0]]), g)


def test_mirror_lookup_returns_input_texel_at_centres():
    rng = np.random.default_rng(4)
    c = rng.random((6, 8, 8, 3))
    p = build_pyramid(c)
    out = lookup(p, texel_directions(8), 1.0)
    # bilinear weights (1,0,0,0) at texel centres; the direction -> texel-coordinate round trip costs a
    # few ulp of the coordinate, i.e. ~1e-15 relative in the weights
    assert np.allclose(out, c, rtol=0, atol=1e-12)


def test_per_direction_g_equals_scalar_calls():
    rng = np.random.default_rng(5)
    c = rng.random((6, 8, 8, 2))
    p = build_pyramid(c, "box")
    d = rng.normal(size=(50, 3))
    g = rng.random(50)
    g[:5] = 1.0
    g[5:10] = 0.0
    vec = lookup(p, d, g)
    ref = np.stack([lookup(p, d[i:i + 1], float(g[i]))[0] for i in range(50)])
    assert np.allclose(vec, ref, rtol=0, atol=1e-14)


def test_calibration_monotone_raw_fit():
    # the raw lobe-volume fits (before the monotone envelope) must already decrease with s
    from ibl_ref.knuth2014.lobe_analysis import LobeResponse

    resp = LobeResponse(16, "sqrtcos")
    s = np.geomspace(1, 300, 15)
    lev = [resp.fit_level(x)[0] for x in s]
    assert np.all(np.diff(lev) <= 1e-9)
    cal = calibrate(16, "sqrtcos")
    assert np.all(np.diff(cal.level) <= 0)
    assert cal.level_of(np.inf) == 0.0
    # the level for s = 1 gives the lookup a lobe of volume 2π/2 (closed form), by brute force through the
    # run-time lookup; 1e-6 is the fit's own acceptance threshold (LobeResponse.fit_level)
    assert 0 < cal.level_of(1.0) < cal.max_level
    assert lobe_volume_through_lookup(cal, 1.0, cap=False) == pytest.approx(np.pi, rel=1e-6)


def test_analytic_fallback_shape():
    cal = analytic_calibration(64)
    # closed form log2 64 - 0.5 log2((s+1)/3) (6 - 2 at s = 47); the table is interpolated linearly in
    # log s with 256 nodes over [1, 4·64²]: away from the clip at s = 2 the error is < 1e-3 level
    assert np.isclose(cal.level_of(1.0), 6.0, atol=1e-12)  # clipped to log2 N
    assert np.isclose(cal.level_of(47.0), 6.0 - 0.5 * np.log2(16.0), atol=1e-3)
    assert np.all(np.diff(cal.level_of(np.geomspace(1, 1e4, 20))) <= 1e-12)


def test_lookup_continuous_across_a_cube_corner():
    # lit texel at a cube corner; the glossy response must be continuous where three faces meet
    n = 16
    c = np.zeros((6, n, n, 1))
    c[4, 0, 0, 0] = 1.0
    p = build_pyramid(c, "sqrtcos")
    corner = face_uv_to_direction(4, -1.0, -1.0)
    rng = np.random.default_rng(6)
    eps = 1e-7
    for _ in range(20):
        t = rng.normal(size=3)
        t -= t.dot(corner) * corner
        t /= np.linalg.norm(t)
        a = lookup(p, (corner + eps * t)[None], 0.8)
        b = lookup(p, (corner - eps * t)[None], 0.8)
        # a Lipschitz function changes by O(eps * gradient); the lobe's gradient is < 1e2 per radian here,
        # so 1e-4 is a generous bound, while a seam would give a jump of the order of the value (~1e-2)
        assert abs(a - b).max() < 1e-4


def test_every_size_and_kernel_of_the_paper_is_shipped():
    # the run-time lookup reads only shipped tables: the five paper filters at every face size 1 … 256 (both
    # volume definitions), sqrtcos also at 512 and with the solid-angle shrink
    names = {p.name for p in SHIPPED}
    for n in (1, 2, 4, 8, 16, 32, 64, 128, 256):
        for vol in ("integral", "radial"):
            for k in ("none", "box", "gauss", "cos", "sqrtcos"):
                assert f"calibration_{k}_shrink_then_filter_neighbour_{vol}_{n}.json" in names
            assert f"calibration_sqrtcos_shrink_then_filter_neighbour_{vol}_solid_angle_{n}.json" in names
    assert len(SHIPPED) == 9 * 2 * 6 + 2


@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem[len("calibration_"):] for p in SHIPPED])
def test_shipped_table_gives_lobes_of_the_target_volume(path):
    # every shipped table, at 4 of its exponents (the widest, the narrowest and two between; at N ≥ 256 the
    # three narrower ones, whose lobes cover a small cap: the widest lobe there needs ~1e6 look-ups per exponent),
    # against the closed-form volume of the target lobe by brute force through the run-time lookup.
    # Where the fit is clipped the table holds the end level and the inequality the clip means: level 0 is
    # still too wide (V ≥ V_t, narrow lobes beyond the resolution) or the coarsest level too narrow
    # (V ≤ V_t, e.g. the unfiltered MIP chain at s = 1).  Tolerance 1e-6: the fit's acceptance threshold
    # (LobeResponse.fit_level re-bisects on the full lobe beyond it); measured ≤ 7e-9.
    import json

    cal = Calibration.from_dict(json.loads(path.read_text()), source=path.name)
    assert cal.s_phong[0] == 1.0 and np.all(np.diff(cal.s_phong) > 0) and np.all(np.diff(cal.level) <= 0)
    k = len(cal.s_phong)
    picks = [0, k // 3, 2 * k // 3, k - 1] if cal.face_size <= 128 else [k // 3, 2 * k // 3, k - 1]
    for i in picks:
        s, ell = float(cal.s_phong[i]), float(cal.level[i])
        v, vt = lobe_volume_through_lookup(cal, s), target_volume(s, cal.volume)
        if 0.0 < ell < cal.max_level:
            assert v == pytest.approx(vt, rel=1e-6), (s, ell)
        else:
            narrow = ell == 0.0 and v >= vt * (1 - 1e-6)
            wide = ell == cal.max_level and v <= vt * (1 + 1e-6)
            assert narrow or wide, (s, ell, v / vt)


def test_capped_quadrature_equals_the_full_sphere():
    # the cap in lobe_volume_through_lookup only drops directions where the lookup is exactly 0
    import json

    for name in ("calibration_box_shrink_then_filter_neighbour_integral_32.json",
                 "calibration_sqrtcos_shrink_then_filter_neighbour_radial_solid_angle_16.json"):
        cal = Calibration.from_dict(json.loads((DATA_DIR / name).read_text()))
        for s in (1.0, 7.0, 60.0):
            assert lobe_volume_through_lookup(cal, s) == pytest.approx(
                lobe_volume_through_lookup(cal, s, cap=False), rel=1e-12)


def test_missing_table_is_a_clear_error_naming_the_builder():
    # the run-time lookup never runs the Sec. 5 analysis: a configuration without a shipped table is a one-line
    # error that says how to build one
    p = build_pyramid(np.ones((6, 16, 16, 1)), order="filter_then_shrink")
    with pytest.raises(IBLError, match=r"gloss_calibration\.calibrate\(16, 'sqrtcos', 'filter_then_shrink'"):
        lookup(p, np.array([[0.0, 0.0, 1.0]]), 0.5)
    with pytest.raises(IBLError, match="explicit filter taps"):
        get_calibration(build_pyramid(np.ones((6, 4, 4, 1)), kernel=[0.1, 0.2, 0.4, 0.2, 0.1]))
    with pytest.raises(IBLError, match="source"):
        get_calibration(p, source="compute")
    # the builder's table for that configuration works when passed explicitly, and equals the closed-form target
    cal = calibrate(16, "sqrtcos", "filter_then_shrink")
    out = lookup(p, np.array([[0.0, 0.0, 1.0]]), 0.5, calibration=cal)
    assert out == pytest.approx(1.0, rel=1e-12)  # a constant map stays constant (normalised filters)
    s = float(cal.s_phong[5])  # a table node (between nodes the level is interpolated in log s)
    assert lobe_volume_through_lookup(cal, s) == pytest.approx(2 * np.pi / (s + 1), rel=1e-6)


def test_builder_names_live_in_the_analysis_step_only():
    # the table builder is imported from its home; the run-time lookup module does not re-export it (a lazy
    # re-export was an import cycle gloss_lookup <-> gloss_calibration)
    from ibl_ref.knuth2014 import gloss_calibration, gloss_lookup

    for name in ("calibrate", "build_calibration_tables", "save_calibration"):
        assert callable(getattr(gloss_calibration, name))
        assert not hasattr(gloss_lookup, name)


def test_lookup_uses_level_between_integer_levels():
    # trilinear: at a level ℓ = L + t the lookup is (1-t)·bilinear_L + t·bilinear_{L+1} (independent
    # evaluation through the per-level samplers)
    from ibl_ref.knuth2014.gloss_lookup import Calibration

    rng = np.random.default_rng(9)
    c = rng.random((6, 8, 8, 3))
    p = build_pyramid(c, "cos")
    # a calibration that maps every finite s to level 1.25
    cal = Calibration(np.array([1.0, 1e6]), np.array([1.25, 1.25]), "cos", p.order, p.seam, 8, "integral",
                      "test", p.max_level)
    d = rng.normal(size=(20, 3))
    out = lookup(p, d, 0.3, calibration=cal)
    ref = 0.75 * p.sampler(1).bilinear(d) + 0.25 * p.sampler(2).bilinear(d)
    assert np.allclose(out, ref, rtol=0, atol=1e-14)
