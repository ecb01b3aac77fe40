"""The converged reference's per-round bookkeeping (issue 40): the refined cells kept in slots with a merged Morton
index, the per-pixel sums recomputed only for the pixels split since the last round, and the driving weight of
refined cells in a sweep.  Each is checked against the plain computation it replaces."""

import numpy as np
import pytest

from ibl_ref.rendering import reference_converged as rc
from ibl_ref.rendering import reference_render as rr


def _scene(size=10):
    from ibl_ref.rendering.scenes import default_camera, teapot_on_ground

    meshes = teapot_on_ground()
    return meshes, default_camera(meshes[:1], size=size)


def _env(**kw):
    from ibl_ref.synthetic.synthetic_envs import make_env

    return make_env("sky_sun", n=16, **kw)


@pytest.mark.parametrize("dead_share", [0.0, 0.25, 1e9])
def test_cell_slots_are_a_plain_list_of_leaves(dead_share, monkeypatch):
    """Random splits (cells marked dead, children appended, keys with duplicates) and compactions: the live cells are
    the ones a plain array with removal would hold, in its order, and the Morton index is the stable argsort of the
    slots' keys (what the region look-ups read)."""
    monkeypatch.setattr(rc._Cells, "DEAD_SHARE", dead_share)
    rng = np.random.default_rng(3)
    R = rc._Cells(3, 2)
    ref_key = np.zeros(0, np.int64)
    ref_w = np.zeros((0, 3))
    for it in range(40):
        live = np.flatnonzero(~R["dead"])
        gone = live[rng.random(len(live)) < 0.2]
        m = int(rng.integers(0, 60))
        new = {k: rng.integers(0, 5, m).astype(t) for k, t in rc._FIELDS}
        new["key"] = rng.integers(0, 500, m)
        new["V"] = rng.integers(0, 2, m)
        W = rng.random((m, 3))
        # the plain list: remove the split cells (by their rank among the live ones), append the new ones
        rank = np.searchsorted(live, gone)
        keep = np.ones(len(ref_key), bool)
        keep[rank] = False
        ref_key = np.concatenate([ref_key[keep], new["key"]])
        ref_w = np.concatenate([ref_w[keep], W])
        R.replace(gone, new, W, W[:, :2])
        R.compact()
        assert np.array_equal(R.order, np.argsort(R["key"], kind="stable")), it
        assert np.array_equal(R.skeys, R["key"][R.order])
        alive = ~R["dead"]
        assert R.live == alive.sum() == len(ref_key)
        assert np.array_equal(R["key"][alive], ref_key) and np.array_equal(R.W[alive], ref_w)
        # dead slots hold nothing: no weight, no ray, not an edge (every sum over the slots is the leaves' sum)
        assert not R.W[~alive].any() and not R.Ye[~alive].any() and (R["V"][~alive] == -1).all()
        assert not R["edge"][~alive].any() and not R["Y"][~alive].any()
    R.compact(force=True)
    assert len(R) == R.live and np.array_equal(R["key"], ref_key)


@pytest.mark.parametrize("material", ["ggx:roughness=0.3,f0=1", (0.0, 1.0, 0.9)])
@pytest.mark.parametrize("sweep", [False, True])
def test_pixel_sums_are_the_full_sums_bit_for_bit(material, sweep, monkeypatch):
    """A and q recomputed only for the pixels split since the last round equal, at every round, the sums over all
    cells (:meth:`_Block.per_env`, :meth:`_Block.quad_est`) exactly."""
    calls = []
    orig = rc._Block.pixel_sums

    def checked(self):
        A, q = orig(self)
        A0 = self.per_env(np.zeros(0, np.int64), np.zeros(0, np.int64))[1]
        q0 = self.quad_est(self.vbar())
        calls.append(bool(np.array_equal(A, A0) and np.array_equal(q, q0)))
        return A, q

    monkeypatch.setattr(rc._Block, "pixel_sums", checked)
    meshes, cam = _scene(10)
    env = _env()
    rr.render_reference(meshes, cam, [env, 0.5 * env + 0.1] if sweep else env, material=material, rtol=3e-3,
                        block_pixels=64)
    assert len(calls) > 4 and all(calls)


@pytest.mark.parametrize("material", ["ggx:roughness=0.3,f0=1", (1.0, 0.0, 0.0)])
def test_a_sweep_of_one_map_twice_is_the_single_render(material):
    """Two copies of one map: T_e are equal, so the driving weight Y/T orders every cell as the single render's Y
    does, and each copy's weights are the single render's — its image and per-pixel errors are the single render's
    (to rounding: Y/T and Y round differently).  The refined cells' driving weight must be the base pairs' max_e
    Y_e/T_e: with the channel mean instead, the visible fraction V̄ of a split base pair was off by the factor T
    and the quadrature estimate with it."""
    meshes, cam = _scene(10)
    env = _env()
    a = rr.render_reference(meshes, cam, env, material=material, rtol=3e-3)
    b, c = rr.render_reference(meshes, cam, [env, env], material=material, rtol=3e-3)
    for x in (b, c):
        np.testing.assert_allclose(x.image, a.image, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(x.error, a.error, rtol=1e-9, atol=1e-15)
        assert x.info["err_rel_l1"] == pytest.approx(a.info["err_rel_l1"], rel=1e-9)


def test_visible_fractions_of_a_sweep_are_fractions(monkeypatch):
    """V̄ of every split base pair lies in [0, 1] in a sweep of maps of very different brightness (its leaves'
    driving weights sum to the pair's)."""
    seen = []
    orig = rc._Block._results

    def rec(self, rounds, converged):
        vb = self.vbar()[self.bsplit]
        seen.append((vb.min() if len(vb) else 0.0, vb.max() if len(vb) else 0.0, len(vb)))
        return orig(self, rounds, converged)

    monkeypatch.setattr(rc._Block, "_results", rec)
    meshes, cam = _scene(10)
    env = _env()
    rr.render_reference(meshes, cam, [env, 20.0 * _env(sun_direction=(0.3, 0.8, 0.5)) + 0.01],
                        material=(1.0, 0.0, 0.0), rtol=3e-3)
    assert sum(s[2] for s in seen) > 0
    assert min(s[0] for s in seen) >= 0.0 and max(s[1] for s in seen) <= 1.0 + 1e-12
