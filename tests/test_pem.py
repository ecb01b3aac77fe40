"""Tests of ibl_ref.knuth2014.pem (partial environment maps, Knuth et al. 2014 Sec. 3.1/4) and ibl_ref.knuth2014.sparse_pem."""

import numpy as np
import pytest

from ibl_ref.errors import IBLError
from ibl_ref.knuth2014.memory_model import library_pem_bytes
from ibl_ref.knuth2014.pem import build_pems
from ibl_ref.knuth2014.pyramid import build_pyramid
from ibl_ref.knuth2014.gloss_lookup import lookup
from ibl_ref.knuth2014.sparse_pem import build_sparse_pems, levels_touched, sparsify

N = 32
G_VALUES = (0.0, 0.3, 0.6, 0.9, 0.99, 1.0)


def _env(seed=0, n=N):
    """Smooth sky + a bright 2x2 sun + noise: positive everywhere, with a 1e4 dynamic range."""
    rng = np.random.default_rng(seed)
    cube = 0.05 + 0.5 * rng.random((6, n, n, 3)) ** 3
    cube[4, 10:12, 20:22] = (1e4, 9e3, 8e3)
    return cube


@pytest.fixture(scope="module")
def setup():
    cube = _env()
    pems = build_pems(cube, n_lights=24, dtype=np.float64)
    full = build_pyramid(cube)
    return cube, pems, full


def test_masked_pyramids_sum_to_full_pyramid(setup):
    cube, pems, full = setup
    assert len(pems.levels) == len(full.levels)
    for lev, ref in zip(pems.levels, full.levels):
        # linear filter: Σ_i F(M_i) = F(Σ_i M_i) up to float64 rounding of a 5-tap/2x2 chain (≲ 10 ulp of max)
        np.testing.assert_allclose(lev.sum(axis=3), ref, rtol=1e-12, atol=1e-12 * ref.max())
    # level 0 is the masked copy: exactly the input on the region, zero elsewhere (Sec. 4)
    lab = pems.lights.labels
    for i in (0, 7, 23):
        np.testing.assert_array_equal(pems.levels[0][:, :, :, i, :], cube * (lab == i)[..., None])


def test_lookup_linearity_whole_sphere(setup):
    """Σ_i lookup(PEM_i) = lookup(full pyramid) for every direction and g (Sec. 3.1): pyramid, seam-aware
    bilinear sampling (incl. edge and corner cells) and the level blend are all linear."""
    cube, pems, full = setup
    rng = np.random.default_rng(1)
    d = rng.normal(size=(20000, 3))
    # plus directions right at the 8 cube corners and on the 12 edges
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    d = np.concatenate([d, corners, corners * [1, 1, 0.999], corners * [1, 0.98, 1]])
    for g in G_VALUES:
        ref = lookup(full, d, g, calibration=pems.calibration)
        # float64 rounding of a sum of 24 lookups of non-negative values (≲ 24·8 ulp relative)
        np.testing.assert_allclose(pems.full_lookup(d, g), ref, rtol=1e-12)


def test_lookup_all_matches_single_lookups(setup):
    _, pems, _ = setup
    d = np.random.default_rng(3).normal(size=(7, 5, 3))
    for g in (0.2, 0.95):
        allv = pems.lookup_all(d, g)
        assert allv.shape == (24, 7, 5, 3)
        for i in (0, 5, 23):
            # the stacked pyramid filters/samples channels independently: identical to rounding
            np.testing.assert_allclose(allv[i], pems.lookup(i, d, g), rtol=1e-14, atol=0)


def test_pemset_interface_and_nbytes():
    cube = _env(4, n=16)
    pems = build_pems(cube, n_lights=12)
    assert pems.dtype == np.float32
    assert pems.directions.shape == (12, 3) and pems.rgb.shape == (12, 3) and pems.solid_angle.shape == (12,)
    # independent route: closed-form byte count L · Σ_l 6 (n/2^l)^2 · C · 4
    assert pems.nbytes == 12 * 6 * (16**2 + 8**2 + 4**2 + 2**2 + 1) * 3 * 4 == library_pem_bytes(12, 16)
    with pytest.raises(IBLError, match=r"PEM index must be an integer"):
        pems.lookup(12, np.array([0.0, 0.0, 1.0]), 0.5)
    with pytest.raises(IBLError, match=r"build_pems: give either lights \(a LightSet"):
        build_pems(cube)
    with pytest.raises(IBLError, match=r"PEM dtype must be a float"):
        build_pems(cube, n_lights=12, dtype=np.int32)


def test_sparse_lossless_is_bit_identical(setup):
    cube, pems, _ = setup
    sp = sparsify(pems, rtol=0.0)
    for i in (0, 11, 23):
        for lev_s, lev_d in zip(sp.dense_region(i), pems.levels):
            np.testing.assert_array_equal(lev_s, lev_d[:, :, :, i, :])
    d = np.random.default_rng(5).normal(size=(2000, 3))
    for g in (0.0, 0.7, 1.0):
        np.testing.assert_array_equal(sp.lookup_all(d, g), pems.lookup_all(d, g))
    assert sp.dense_nbytes == pems.nbytes
    assert sp.nbytes < pems.nbytes / 5  # 24 regions: most of every PEM is zero


def test_sparse_rtol_bound_and_streaming_build(setup):
    cube, pems, _ = setup
    sp = sparsify(pems, rtol=1e-6)
    d = np.random.default_rng(6).normal(size=(4000, 3))
    for g in G_VALUES:
        dense = pems.lookup_all(d, g)
        full = dense.sum(axis=0)
        err = np.abs(sp.lookup_all(d, g) - dense)
        # stated criterion: every PEM and the sum within 1e-6 of the full lookup value (+ float64 rounding)
        assert np.all(err <= 1e-6 * full[None] * (1 + 1e-9) + 1e-15)
        assert np.all(np.abs(err.sum(0)) <= 1e-6 * full * (1 + 1e-9) + 1e-15)
    # the streaming builder (FULL = pyramid of the full map) keeps the same tiles as sparsify(dense)
    st = build_sparse_pems(cube, pems.lights, rtol=0.0, dtype=np.float64)
    assert st.nbytes == sparsify(pems, rtol=0.0).nbytes


def test_sparse_levels_for_scene_g(setup):
    cube, pems, _ = setup
    g_scene = [0.0, 0.5]
    touched = levels_touched(g_scene, N, calibration=pems.calibration)
    assert 0 not in touched  # rough materials never read the mirror level
    sp = sparsify(pems, rtol=0.0, g_values=g_scene)
    assert sp.stored_levels == touched
    d = np.random.default_rng(7).normal(size=(500, 3))
    for g in g_scene:
        np.testing.assert_array_equal(sp.lookup_all(d, g), pems.lookup_all(d, g))
    with pytest.raises(IBLError, match="level"):
        sp.lookup_all(d, 1.0)
    assert sp.nbytes < sparsify(pems, rtol=0.0).nbytes
