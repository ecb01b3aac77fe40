"""Tests of ibl_ref.knuth2014.gloss_lookup (Knuth et al. 2014 Eq. 3 and the trilinear glossiness lookup)."""

import warnings

import numpy as np
import pytest

from ibl_ref.environment.envmap import face_uv_to_direction, texel_directions
from ibl_ref.errors import IBLError
from ibl_ref.knuth2014.gloss_lookup import analytic_calibration, calibrate, lookup, phong_exponent
from ibl_ref.knuth2014.pyramid import build_pyramid


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
    with pytest.raises(IBLError):
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
    assert 0 < cal.level_of(1.0) <= 4


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


def test_shipped_calibration_tables_match_recomputation():
    # the JSON tables in ibl_ref/data must be what the lobe analysis computes now (regression guard);
    # fits are bisected to ~1e-9 level, so 1e-5 level allows any rounding in the JSON round trip
    import json

    from ibl_ref.knuth2014.gloss_lookup import DATA_DIR, Calibration

    for kernel in ("sqrtcos", "box"):
        p = DATA_DIR / f"calibration_{kernel}_shrink_then_filter_neighbour_integral_16.json"
        if not p.exists():
            pytest.skip("calibration tables not shipped")
        cal = Calibration.from_dict(json.loads(p.read_text()))
        fresh = calibrate(16, kernel, s_values=tuple(cal.s_phong))
        assert np.allclose(cal.level, fresh.level, atol=1e-5)
        assert np.all(np.diff(cal.level) <= 0)


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
