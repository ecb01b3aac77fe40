"""How the GGX tree (ibl_ref.groundtruth.ggx_convolution) spends its refinement: the split threshold of the last
rounds, the sampled first target and the passes that compute missing tiles again, each checked against the dense
texel sum (karis2013.prefilter_dense) and, for the threshold, against a direct per-tile loop."""

import numpy as np
import pytest

from ibl_ref.groundtruth import ggx_convolution as G
from ibl_ref.groundtruth.kernels import numba_available
from ibl_ref.groundtruth.kernels.numpy_backend import _split_threshold
from ibl_ref.prefilter import karis2013
from ibl_ref.synthetic import synthetic_envs as se

KERNELS = ["numpy"] + (["compiled"] if numba_available() else [])


def _threshold_by_loop(metric, target, gain):
    """The rule of numba_loops.ggx_tree for one tile, as written there."""
    total = 0.0
    for m in metric:
        total += m
    thr = total / (2.0 * len(metric))
    need = (total - target) / gain
    if total > target and need < total:
        while True:
            held = 0.0
            for m in metric:
                if m >= 2.0 * thr:
                    held += m
            if held < need:
                break
            thr *= 2.0
    return thr


def test_the_split_threshold_is_the_per_tile_rule():
    rng = np.random.default_rng(3)
    sizes = [1, 5, 40, 300, 7]
    tiles = np.repeat(np.arange(len(sizes)), sizes)
    metric = rng.random(tiles.size) ** 6
    total = np.bincount(tiles, weights=metric)
    count = np.bincount(tiles)
    for gain in (1.0, 0.875, 0.5):
        for frac in (0.1, 0.5, 0.9, 0.99, 1.5):
            target = total * frac
            thr = _split_threshold(tiles, metric, total, total / (2.0 * count), target, gain)
            for t in range(len(sizes)):
                assert thr[t] == _threshold_by_loop(metric[tiles == t], target[t], gain)
    # near the target only the largest pairs are split; far from it, every pair above half the mean
    big = np.array([0.5, 0.3, 0.1, 0.05, 0.05])
    t0 = np.zeros(5, dtype=np.int64)
    thr = _split_threshold(t0, big, np.array([1.0]), np.array([0.1]), np.array([0.95]), 0.875)
    assert thr[0] == 0.4 and np.sum(big >= thr[0]) == 1
    thr = _split_threshold(t0, big, np.array([1.0]), np.array([0.1]), np.array([0.01]), 0.875)
    assert thr[0] == 0.1


@pytest.mark.parametrize("kernel", KERNELS)
def test_the_sampled_first_target_against_the_dense_sum(kernel):
    # 32² output faces in 4² tiles: 384 tiles, so a sample of them sets the target of the others
    cube = se.env_sky_sun(32)
    for r in (0.2, 0.6):
        maps, bound = G.convolve_ggx(cube, r, rtol=1e-3, out_size=32, kernel=kernel)
        passes = G.LAST_INFO["levels"][0]["passes"]
        assert passes[0][1] == 384 // G.SAMPLE_STRIDE and passes[1][1] == 384 - 384 // G.SAMPLE_STRIDE
        ref = karis2013.prefilter_dense(cube, r, out_size=32)
        err = (np.abs(maps - ref) / ref).max(axis=-1)
        assert bound.max() <= 1e-3 and np.all(err <= bound)


@pytest.mark.parametrize("kernel", KERNELS)
def test_tiles_computed_again_and_exactly_stay_within_their_bound(kernel, monkeypatch):
    # a first target far above rtol: most tiles miss it and are computed again (and the last ones exactly)
    cube = se.env_sky_sun(16) + se.env_delta(16, texel=(2, 5, 9), radiance=1e4)
    ref = karis2013.prefilter_dense(cube, 0.15, out_size=16)
    monkeypatch.setattr(G, "BUDGET_TARGET", 500.0)
    monkeypatch.setattr(G, "SAMPLE_MIN_TILES", 10 ** 9)
    for steps in (2, 0):
        monkeypatch.setattr(G, "REFINE_STEPS", steps)
        maps, bound = G.convolve_ggx(cube, 0.15, rtol=1e-3, tile=2, kernel=kernel)
        passes = G.LAST_INFO["levels"][0]["passes"]
        assert len(passes) >= 2 and passes[-1][1] <= passes[0][1]
        if steps == 0:
            assert passes[-1][0] == 0.0  # the exact sum
        err = (np.abs(maps - ref) / ref).max(axis=-1)
        assert bound.max() <= 1e-3 and np.all(err <= bound)
