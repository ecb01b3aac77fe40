"""Exact-lobe chain (ibl_ref.knuth2014.lobe_chain): levels against the independent dense gather, PEM identity, lookups."""

import numpy as np
import pytest

from ibl_ref.environment.envmap import texel_directions
from ibl_ref.errors import IBLError, LayoutError, RadianceError
from ibl_ref.knuth2014.gloss_lookup import lookup
from ibl_ref.knuth2014.lobe_chain import (
    build_lobe_chain,
    build_lobe_chain_pems,
    chain_spec,
    lobe_average_regions,
    lobe_half_angle,
)
from ibl_ref.groundtruth.phong_convolution import convolve_exact_many
from ibl_ref.rendering.reference_render import lobe_average
from ibl_ref.synthetic.synthetic_envs import make_env


@pytest.fixture(scope="module")
def sky16():
    return make_env("sky_sun", n=16)


@pytest.fixture(scope="module")
def chain16(sky16):
    return build_lobe_chain(sky16, weight_eps=1e-12)


def test_spec_exponents_and_sizes():
    for N in (8, 16, 64, 128):
        sp = chain_spec(N, factor=2.0)
        s = np.array(sp.s_phong)
        assert s[-1] == 1.0 and np.allclose(s[:-1] / s[1:], 2.0)
        # s_1 is the narrowest lobe still one input texel (2/N rad) wide; the next one would not be
        assert lobe_half_angle(s[0]) >= 2.0 / N > lobe_half_angle(2.0 * s[0])
        sizes = np.array(sp.face_sizes)
        assert sizes[0] == N and np.all(sizes[1:] <= N) and np.all(sizes[1:] >= min(8, N))
        assert np.all((sizes & (sizes - 1)) == 0) and np.all(np.diff(sizes[1:]) <= 0)


def test_levels_equal_dense_exact_gather(sky16, chain16):
    # independent route: phong_convolution's dense gather over every texel (no truncation, no regions)
    pyr, cal = chain16
    for k, s in enumerate(pyr.spec.s_phong, start=1):
        ref = convolve_exact_many(sky16, [s], out_size=pyr.levels[k].shape[1])[0]
        # truncation changes the average by <= delta * max L (module docstring); delta <= 1e-8 here
        assert pyr.truncation_bounds[k - 1] < 1e-8
        tol = pyr.truncation_bounds[k - 1] * sky16.max() + 1e-12 * np.abs(ref).max()
        assert np.abs(pyr.levels[k] - ref).max() <= tol


def test_truncation_bound_holds_when_loose(sky16):
    # a coarse cutoff (weight_eps = 1e-3) must stay within its own reported bound
    lab = np.zeros((6, 16, 16), dtype=int)
    for s in (4.0, 64.0):
        avg, bound = lobe_average_regions(sky16, lab, 1, s, 8, weight_eps=1e-3)
        ref = convolve_exact_many(sky16, [s], out_size=8)[0]
        err = np.abs(avg[:, :, :, 0, :] - ref).max(axis=-1)
        assert np.all(err <= bound * sky16.max() * (1 + 1e-9) + 1e-12)
        assert bound.max() > 0  # something was truncated


def test_constant_map_stays_constant():
    c = np.full((6, 16, 16, 3), 2.5)
    pyr, cal = build_lobe_chain(c)
    for lev in pyr.levels:
        assert np.allclose(lev, 2.5, rtol=0, atol=1e-13)
    rng = np.random.default_rng(1)
    d = rng.normal(size=(200, 3))
    for g in (0.0, 0.3, 0.9, 0.999, 1.0):
        assert np.allclose(lookup(pyr, d, g, calibration=cal), 2.5, atol=1e-13)


def test_lookup_hits_levels_exactly(sky16, chain16):
    pyr, cal = chain16
    for k, s in enumerate(pyr.spec.s_phong, start=1):
        d = texel_directions(pyr.levels[k].shape[1]).reshape(-1, 3)
        got = lookup(pyr, d, 1.0 - 1.0 / s, calibration=cal)
        # texel centres of level k: bilinear returns the stored value, no blend with neighbours' levels
        assert np.allclose(got, pyr.levels[k].reshape(-1, 3), rtol=1e-10, atol=0)


def test_s1_lookup_converges_with_level_size(sky16):
    # bilinear lookup of a smooth (s = 1) function: error O(h^2) -> halving the texel size divides it by ~4
    rng = np.random.default_rng(2)
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ex = lobe_average(sky16, d, 1.0)
    errs = []
    for n_min in (4, 8, 16):
        pyr, cal = build_lobe_chain(sky16, n_min=n_min)
        assert pyr.levels[-1].shape[1] == n_min
        a = lookup(pyr, d, 0.0, calibration=cal)
        errs.append(np.abs(a - ex).sum() / ex.sum())
    assert errs[1] < errs[0] / 3 and errs[2] < errs[1] / 3, errs


def test_pems_sum_to_full_chain(sky16, chain16):
    pyr, cal = chain16
    pems = build_lobe_chain_pems(sky16, n_lights=12, dtype=np.float64)
    assert pems.kernel == "exact-lobe" and len(pems) == 12
    # level 0 of the PEMs partitions the input (Sec. 4: blacken all texels outside the region)
    assert np.array_equal(pems.levels[0].sum(axis=3), sky16)
    rng = np.random.default_rng(3)
    d = rng.normal(size=(300, 3))
    for g in (0.0, 0.5, 0.95, 1.0):
        full = lookup(pyr, d, g, calibration=cal)
        parts = pems.lookup_all(d, g)
        assert parts.shape == (12, 300, 3)
        assert np.allclose(parts.sum(axis=0), full, rtol=1e-10, atol=1e-12 * np.abs(full).max())


def test_float32_pems_close_to_float64(sky16):
    p32 = build_lobe_chain_pems(sky16, n_lights=6, dtype=np.float32)
    p64 = build_lobe_chain_pems(sky16, p32.lights, dtype=np.float64)
    d = np.array([[0.3, 0.8, 0.5], [-1.0, 0.1, 0.0]])
    a, b = p32.lookup_all(d, 0.7), p64.lookup_all(d, 0.7)
    assert np.all(np.isfinite(a))
    # float32 storage: relative rounding 2^-24 per stored value, a few values blended
    assert np.allclose(a, b, rtol=1e-6, atol=1e-6 * np.abs(b).max())


def test_bad_input(sky16):
    with pytest.raises(IBLError, match=r"s_min must be >= 1 and"):
        chain_spec(16, s_min=0.5)
    with pytest.raises(IBLError, match=r"factor must be > 1 and"):
        chain_spec(16, factor=1.0)
    with pytest.raises(IBLError, match=r"n_min must be a power of"):
        chain_spec(16, n_min=3)
    with pytest.raises(IBLError, match=r"texels_per_halfwidth must be > 0, got"):
        chain_spec(16, texels_per_halfwidth=0.0)
    bad = sky16.copy()
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(RadianceError, match=r"environment: 1 non\-finite value\(s\) \(first: NaN"):
        build_lobe_chain(bad)
    with pytest.raises(LayoutError, match=r"environment: expected an array of shape"):
        build_lobe_chain(np.ones((5, 4, 4, 3)))
    with pytest.raises(LayoutError, match=r"labels must have shape \(6, 16"):
        lobe_average_regions(sky16, np.zeros((6, 8, 8), dtype=int), 1, 2.0, 4)
    with pytest.raises(IBLError, match=r"Phong exponent must be finite and"):
        lobe_average_regions(sky16, np.zeros((6, 16, 16), dtype=int), 1, 0.5, 4)
    with pytest.raises(IBLError, match=r"PEM dtype must be a float"):
        build_lobe_chain_pems(sky16, n_lights=6, dtype=np.int32)
    with pytest.raises(IBLError, match=r"PEM values exceed the range of"):
        build_lobe_chain_pems(np.full((6, 16, 16, 3), 1e39), n_lights=6, dtype=np.float32)
