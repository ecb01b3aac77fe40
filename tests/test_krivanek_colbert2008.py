"""Tests of ibl_ref.prefilter.krivanek_colbert2008 (filtered importance sampling of the GGX prefilter)."""

import numpy as np
import pytest

from ibl_ref.environment import envmap
from ibl_ref.environment.resample import integral_cube
from ibl_ref.errors import IBLError
from ibl_ref.prefilter import karis2013 as k, krivanek_colbert2008 as kc
from ibl_ref.synthetic import synthetic_envs as se


def test_source_pyramid_keeps_the_integral_and_constants():
    cube = se.env_studio(16)
    pyr = kc.source_pyramid(cube)
    assert [lv.shape[1] for lv in pyr] == [16, 8, 4, 2, 1]
    ref = integral_cube(cube)
    for lv in pyr:  # exact area-weighted block averages: ∫L dω identical to rounding
        np.testing.assert_allclose(integral_cube(lv), ref, rtol=1e-13)
    const = kc.source_pyramid(np.full((6, 8, 8, 2), 3.0))
    for lv in const:
        np.testing.assert_allclose(lv, 3.0, rtol=1e-14)
    assert len(kc.source_pyramid(np.ones((6, 12, 12, 1)))) == 3  # 12, 6, 3: stops at an odd size


def test_fis_level_rule():
    # lod = max(½ log2(Ω_s/Ω_p) + bias, 0), Ω_s = 1/(N p): Ω_s = Ω_p -> bias; 4x larger -> one level more
    omega_p = 1e-3
    for n in (1, 16):
        p_equal = 1.0 / (n * omega_p)
        assert kc.fis_lod(p_equal, n, omega_p) == pytest.approx(1.0)
        assert kc.fis_lod(p_equal / 4, n, omega_p) == pytest.approx(2.0)
        assert kc.fis_lod(p_equal, n, omega_p, bias=0.0) == pytest.approx(0.0, abs=1e-15)
        assert kc.fis_lod(p_equal * 64, n, omega_p) == 0.0  # clipped at the finest level
    np.testing.assert_allclose(kc.fis_lod(np.array([1.0, 4.0]), 1, np.array([0.25, 0.25])), [2.0, 1.0])


@pytest.mark.parametrize("roughness", [0.5, 0.8])
@pytest.mark.parametrize("sequence", ["random", "hammersley"])
def test_fis_beats_plain_importance_sampling_at_equal_n(roughness, sequence):
    # a studio map (small bright area lights) on a 32² source: at N = 8 and 32 samples the RMS error of FIS against
    # the exact prefilter is below that of plain importance sampling (measured ratio 0.26 … 0.66).  This is the
    # regime FIS is for (lobes several texels wide, few samples); for narrow lobes (roughness 0.2 here) its blur can
    # cost more than the noise it removes.
    cube = se.env_studio(32)
    exact = k.prefilter_exact(cube, roughness, out_size=8)
    for n in (8, 32):
        kw = dict(samples=n, sequence=sequence, seed=11, out_size=8)
        e_is = np.sqrt(np.mean((k.prefilter_importance(cube, roughness, **kw) - exact) ** 2))
        e_fis = np.sqrt(np.mean((kc.prefilter_fis(cube, roughness, **kw) - exact) ** 2))
        assert e_fis < e_is


def test_fis_converges_and_is_exact_for_constants():
    # as N grows every sample's lod falls to 0 (Ω_s → 0) and FIS becomes plain importance sampling: the error
    # against the exact prefilter falls at least at the Monte Carlo rate, √(4096/16) = 16x, from N = 16 to 4096
    # (Hammersley; measured 100x)
    cube = se.env_sky_sun(32, sun_solid_angle=0.02, sun_radiance=30.0)
    exact = k.prefilter_exact(cube, 0.6, out_size=8)
    e = []
    for n in (16, 4096):
        out, info = kc.prefilter_fis(cube, 0.6, samples=n, out_size=8, return_info=True)
        e.append(np.sqrt(np.mean((out - exact) ** 2)))
        assert 0.0 <= info["lod_min"] <= info["lod_mean"] <= info["lod_max"] <= 5.0
    assert e[1] < e[0] / 16
    const = np.full((6, 8, 8, 3), 0.25)
    for tsa in kc.TEXEL_SOLID_ANGLES:
        np.testing.assert_allclose(kc.prefilter_fis(const, 0.7, samples=5, texel_solid_angle=tsa), 0.25, rtol=1e-14)


def test_fis_texel_solid_angle_options_differ_only_in_the_level():
    # "exact" uses the solid angle of the texel holding the sample, "mean" 4π/(6N²); at the face centre the texel
    # is larger than the mean (1.41x at N = 32), so "exact" reads finer levels there: lower lod on average
    cube = se.env_studio(32)
    d = np.array([[0.0, 0.0, 1.0]])
    _, ie = kc.prefilter_fis(cube, 0.5, samples=64, dirs=d, return_info=True, texel_solid_angle="exact")
    _, im = kc.prefilter_fis(cube, 0.5, samples=64, dirs=d, return_info=True, texel_solid_angle="mean")
    assert ie["lod_mean"] < im["lod_mean"]
    om = envmap.texel_solid_angles(32)
    assert om[16, 16] / (4 * np.pi / (6 * 32 * 32)) == pytest.approx(6 / np.pi, rel=1e-2)


def test_fis_chain_and_class():
    cube = se.env_studio(16)
    chain = kc.build_fis_chain(cube, samples=16, n_levels=3)
    assert chain.prefilter == "fis" and chain.info["samples"] == 16 and chain.info["bias"] == 1.0
    assert chain.face_sizes == (16, 8, 4)
    # the chain's level 1 is prefilter_fis at roughness 0.5, face 8, seed (0, 1)
    ref = kc.prefilter_fis(cube, 0.5, samples=16, out_size=8, seed=(0, 1))
    np.testing.assert_array_equal(chain.levels[1], ref)
    m = kc.FilteredImportanceSampling.build(cube, samples=16, n_levels=3, dfg_size=16)
    assert m.lobe == "ggx" and m.error_bound is None and m.chain.prefilter == "fis"
    assert m.lookup(np.array([[1.0, 0.0, 0.0]]), 0.4).shape == (1, 3)


def test_fis_bad_input():
    cube = se.env_constant(8)
    for call, word in ((lambda: kc.prefilter_fis(cube, 0.5, samples=0), "N >= 1"),
                       (lambda: kc.prefilter_fis(cube, 0.0), "roughness"),
                       (lambda: kc.prefilter_fis(cube, 0.5, bias=np.nan), "bias"),
                       (lambda: kc.prefilter_fis(cube, 0.5, texel_solid_angle="uniform"), "texel_solid_angle"),
                       (lambda: kc.prefilter_fis(cube, 0.5, pyramid=kc.source_pyramid(se.env_constant(4))), "pyramid"),
                       (lambda: kc.fis_lod(0.0, 4, 1e-3), "positive"),
                       (lambda: kc.build_fis_chain(cube, samples=2.0), "N >= 1")):
        with pytest.raises(IBLError) as e:
            call()
        assert word in str(e.value) and "\n" not in str(e.value)
    bad = cube.copy()
    bad[0, 0, 0, 1] = np.nan
    with pytest.raises(IBLError):
        kc.prefilter_fis(bad, 0.5)
