"""Tests of the optional compiled kernels (ibl_ref.groundtruth.kernels: numba loops behind the kernel interface), the
kernel switch and numba's cache of the loops.

The NumPy path is the reference: every compiled route is checked against the exact float64 gather (its bound must
hold), against the NumPy route (the two agree within the sum of their bounds) and for bit-identical results across
worker counts.  Tests that need numba skip without it; the kernel switch and the behaviour without numba are
tested in subprocesses where numba cannot be imported.
"""

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from ibl_ref.errors import IBLError
from ibl_ref.groundtruth import kernels as kc

ROOT = Path(__file__).resolve().parents[1]

#: makes ``import numba`` fail in a subprocess (as on an installation without the ``fast`` extra)
BLOCK_NUMBA = textwrap.dedent(
    """
    import importlib.abc, sys
    class _NoNumba(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name == "numba" or name.startswith("numba."):
                raise ImportError("numba blocked for this test")
    sys.meta_path.insert(0, _NoNumba())
    """
)


def _sun_env(n, sun=1e5):
    from ibl_ref.synthetic.synthetic_envs import SUN_NEAR_CORNER, make_env

    return make_env("sky_sun", n, sun_direction=SUN_NEAR_CORNER, sun_radiance=sun)


def _env(extra=None):
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.pop("IBL_REF_KERNEL", None)
    env.update(extra or {})
    return env


# ---------------------------------------------------------------------------------------------------------------
# the switch
# ---------------------------------------------------------------------------------------------------------------
def test_resolve_kernel_values_and_environment(monkeypatch):
    monkeypatch.setattr(kc, "numba_available", lambda: True)
    assert kc.resolve_kernel("numpy") == "numpy"
    assert kc.resolve_kernel("compiled") == "compiled"
    assert kc.resolve_kernel("auto") == "compiled"
    monkeypatch.setenv(kc.KERNEL_ENV, "numpy")
    assert kc.resolve_kernel(None) == "numpy"
    monkeypatch.setenv(kc.KERNEL_ENV, "fast")
    with pytest.raises(IBLError, match=r"\$IBL_REF_KERNEL must be one of auto, numpy, compiled"):
        kc.resolve_kernel(None)
    with pytest.raises(IBLError, match="kernel must be one of"):
        kc.resolve_kernel("gpu")
    monkeypatch.setattr(kc, "numba_available", lambda: False)
    assert kc.resolve_kernel("auto") == "numpy"
    with pytest.raises(IBLError, match=r"needs numba"):
        kc.resolve_kernel("compiled")
    for bad in ("gpu", None, 3):
        with pytest.raises(IBLError, match="impl must be one of 'numpy', 'compiled'"):
            kc.check_impl(bad)


def test_numba_disable_jit_means_numpy_with_a_clear_error_for_compiled():
    # NUMBA_DISABLE_JIT=1 (a common debugging switch) would run the loops as pure Python: the lab treats numba's JIT
    # as absent (auto: NumPy), and asking for the compiled kernels is one clear line
    code = textwrap.dedent(
        """
        import numpy as np
        from ibl_ref.errors import IBLError
        from ibl_ref.groundtruth.convolve import convolve
        r = convolve(np.ones((6, 8, 8, 3)), [4.0])
        print("KERNEL", r.info["kernel"])
        try:
            convolve(np.ones((6, 8, 8, 3)), [4.0], kernel="compiled")
        except IBLError as exc:
            print("ERROR", exc)
        """
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                       env=_env({"NUMBA_DISABLE_JIT": "1"}))
    assert p.returncode == 0, p.stderr
    assert "KERNEL numpy" in p.stdout
    if importlib.util.find_spec("numba") is not None:
        assert "ERROR kernel = 'compiled' needs numba's JIT (NUMBA_DISABLE_JIT is set)" in p.stdout


def test_without_numba_auto_is_numpy_and_compiled_is_a_clear_error(tmp_path):
    code = BLOCK_NUMBA + textwrap.dedent(
        """
        import numpy as np
        from ibl_ref.errors import IBLError
        from ibl_ref.groundtruth.convolve import convolve
        cube = np.ones((6, 8, 8, 3))
        r = convolve(cube, [4.0], kernel="auto")
        print("KERNEL", r.info["kernel"])
        try:
            convolve(cube, [4.0], kernel="compiled")
        except IBLError as exc:
            print("ERROR", exc)
        """
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(), timeout=300)
    assert p.returncode == 0, p.stderr
    assert "KERNEL numpy" in p.stdout
    assert "ERROR kernel = 'compiled' needs numba" in p.stdout
    # the CLI: one line, exit status 2 (a user error), no traceback
    from ibl_ref.environment.exr_io import write_envmap

    write_envmap(tmp_path / "in.exr", np.ones((6, 8, 8, 3)), layout="cube")
    cli = BLOCK_NUMBA + "import sys\nfrom ibl_ref.cli import main\nsys.exit(main(sys.argv[1:]))\n"
    p = subprocess.run([sys.executable, "-c", cli, "convolve", str(tmp_path / "in.exr"), str(tmp_path / "o.exr"),
                        "-s", "4", "--kernel", "compiled"], capture_output=True, text=True, env=_env(), timeout=300)
    assert p.returncode != 0
    assert "Traceback" not in p.stderr and "needs numba" in p.stderr
    assert len([ln for ln in p.stderr.splitlines() if ln.strip()]) <= 2, p.stderr


# ---------------------------------------------------------------------------------------------------------------
# elementary functions and the weight error bound
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ck():
    """The numba loops and their rounding model (the routes' tests run on the compiled backend)."""
    pytest.importorskip("numba", reason="the compiled kernels need numba (pip install 'ibl_ref[fast]')")
    from types import SimpleNamespace

    from ibl_ref.groundtruth.kernels import numba_backend as nb, numba_loops as nl, rounding as spec

    def tile_gather(cen, rows, caps, arad, frames, n, X, Y, Z, RW, bdirs, brw, s, s_int, rowmax, c_floor, acc, logmx,
                    count, groups=None):
        gcen, galpha = nb.bright_groups(bdirs) if groups is None else groups
        nl.tile_gather(cen, rows, caps, arad, frames, n, X, Y, Z, RW, bdirs, brw, gcen, galpha, s, s_int, rowmax,
                       c_floor, acc, logmx, count, np.empty(cen.shape[0], dtype=np.int64))

    yield SimpleNamespace(exp_=nl.exp_, log_=nl.log_, powi_=nl.powi_, _scratch_size=nl._scratch_size,
                          tile_gather=tile_gather, cap_count=nl.cap_count, bright_groups=nb.bright_groups,
                          weight_error=spec.weight_error, sum_error=spec.sum_error, U64=spec.U64,
                          EXP_REL=spec.EXP_REL, LOG_ABS=spec.LOG_ABS, LOG_REL=spec.LOG_REL, POWI_MAX=spec.POWI_MAX)


def test_exp_log_powi_within_their_stated_bounds(ck):
    """exp_, log_ and powi_ against extended precision (numpy.longdouble, 64-bit mantissa on x86: exact to
    ≈ 5e-20 for these arguments) on 10⁵ seeded arguments each: the stated bounds hold."""
    from numba import njit

    exp_, log_, powi_ = ck.exp_, ck.log_, ck.powi_

    @njit
    def apply(u, c, s):
        e, lg, p = np.empty_like(u), np.empty_like(c), np.empty_like(c)
        for i in range(u.size):
            e[i] = exp_(u[i])
            lg[i] = log_(c[i])
            p[i] = powi_(c[i], s)
        return e, lg, p

    rng = np.random.default_rng(7)
    u = np.concatenate([-rng.random(50_000) * 700, rng.random(50_000) * 700])
    c = np.concatenate([rng.random(50_000), 1 - rng.random(30_000) * 1e-3, np.exp(-rng.random(20_000) * 600)])
    for s in (1, 2, 37, 1000, ck.POWI_MAX):
        e, lg, p = apply(u, c, s)
        ref_p = c.astype(np.longdouble) ** s
        ok = ref_p > 2.0 ** -1000
        n = s - 1
        assert np.all(np.abs(p[ok] - ref_p[ok]) <= (n * ck.U64 / (1 - n * ck.U64) + 1e-19) * ref_p[ok]), s
    ref_e = np.exp(u.astype(np.longdouble))
    assert np.all(np.abs(e - ref_e) <= ck.EXP_REL * ref_e)
    ref_l = np.log(c.astype(np.longdouble))
    assert np.all(np.abs(lg - ref_l) <= ck.LOG_ABS + ck.LOG_REL * np.abs(ref_l))
    assert ck.exp_(-800.0) == 0.0 and ck.exp_(0.0) == 1.0


def test_tile_gather_collects_every_texel_of_the_cap_and_its_weights_are_within_the_bound(ck):
    """Brute force: the kernel's sums are at least the exact (extended-precision) sums over the texels within the
    cap and, for narrow caps, at most those over the cap widened by its stated slack (1e-6 rad + 1e-3 texel), within
    the weight error bound; for each of the kernel's weight loops (s = 2^k by squarings, other integers by binary
    powering, a fraction by exp/log)."""
    from ibl_ref.environment import envmap

    rng = np.random.default_rng(3)
    for n, s in ((16, 7.0), (17, 64.0), (18, 1.0), (32, 300.5), (33, 4096.0)):  # (2^k: the squaring loop)
        d = envmap.texel_directions(n).reshape(-1, 3)
        rw = np.zeros((4, d.shape[0]))
        rw[:3] = rng.random((3, d.shape[0]))
        rw[3] = envmap.cube_solid_angles(n).reshape(-1)
        X, Y, Z = (np.ascontiguousarray(d[:, i]) for i in range(3))
        nt = 60
        cen = d[rng.choice(d.shape[0], nt, replace=False)] + rng.normal(0, 0.02, (nt, 3))
        cen /= np.linalg.norm(cen, axis=1, keepdims=True)
        rows = cen[:, None, :] + rng.normal(0, 0.01, (nt, 4, 3))
        rows /= np.linalg.norm(rows, axis=2, keepdims=True)
        caps = rng.uniform(0.02, 1.2, nt)
        acc, lm, cnt = np.zeros((nt, 4, 4)), np.zeros((nt, 4)), np.zeros(nt, dtype=np.int64)
        s_int = int(s) if float(s).is_integer() else 0
        ck.tile_gather(cen, rows, caps, np.zeros(len(caps)), envmap.face_frames("openexr"), n, X, Y, Z, rw,
                       np.zeros((0, 3)), np.zeros((0, 4)), s, s_int, not s_int, np.exp(-700.0 / s), acc, lm, cnt)
        eta, eps = ck.weight_error(s, bool(s_int), not s_int)
        D = d.astype(np.longdouble)
        for i in range(nt):
            got = acc[i] * np.exp(lm[i])[:, None]
            # at least the cap; for caps below 0.3 rad (no face-horizon case, where whole rows are taken) at most
            # the cap widened by the slack
            for slack, sign in ((0.0, 1.0),) + (((1e-6 + 2e-3 / n * 1.8, -1.0),) if caps[i] < 0.3 else ()):
                sel = (d @ cen[i]) >= np.cos(caps[i] + slack)
                c = np.maximum(rows[i].astype(np.longdouble) @ D[sel].T, 0)
                ref = (c ** s) @ rw[:, sel].T.astype(np.longdouble)
                # relative η per weight and sum, absolute ε per weight in units of the reference weight e^{lm}
                tol = ((eta + ck.sum_error(cnt[i])) * ref
                       + eps * np.abs(rw).sum(axis=1)[None, :] * np.exp(lm[i])[:, None])
                assert np.all(sign * (got - ref) >= -tol), (n, s, i, slack)


def test_scratch_size_bound_holds_for_narrow_caps(ck):
    """The scratch size of tile_gather for caps below 0.3 rad comes from a cap-area bound, not a count: it is at
    least the number of texels collected (the count of cap_count) for random caps and centres, corner ones too."""
    from ibl_ref.environment import envmap

    fr = envmap.face_frames("openexr")
    rng = np.random.default_rng(11)
    for n in (8, 17, 64, 255):
        cen = rng.normal(size=(300, 3))
        cen[:20] = [1.0, 1.0, 1.0]  # cube corners, where texels are smallest
        cen[20:40] = [1.0, 0.0, 1e-7]  # a face edge
        cen /= np.linalg.norm(cen, axis=1, keepdims=True)
        caps = rng.uniform(0.0, 0.2999, len(cen))
        for i in range(len(cen)):
            cnt = ck.cap_count(cen[i], caps[i], fr, n)
            assert ck._scratch_size(caps[i : i + 1], fr, n, cen[i : i + 1]) >= cnt, (n, i, caps[i])


def test_tile_gather_leaves_out_only_zero_weight_bright_texels(ck):
    """Bright texels farther than acos(e^(-700/s)) + the tile radius from a tile's centre are left out of its list:
    the sums equal those with every bright texel within the weights' error bound, and the left-out ones are counted."""
    from ibl_ref.environment import envmap

    rng = np.random.default_rng(5)
    n = 24
    d = envmap.texel_directions(n).reshape(-1, 3)
    X, Y, Z = (np.ascontiguousarray(d[:, i]) for i in range(3))
    rw = np.zeros((4, d.shape[0]))
    rw[:3] = rng.random((3, d.shape[0]))
    rw[3] = envmap.cube_solid_angles(n).reshape(-1)
    nb = 300
    bdirs = rng.normal(size=(nb, 3))
    bdirs[:200] = d[np.sort(rng.choice(d.shape[0] // 6, 200, replace=False))]  # most in clusters (face 0, by index)
    bdirs /= np.linalg.norm(bdirs, axis=1, keepdims=True)
    brw = np.abs(rng.normal(size=(nb, 4))) * 1e4
    nt = 40
    cen = rng.normal(size=(nt, 3))
    cen /= np.linalg.norm(cen, axis=1, keepdims=True)
    rows = cen[:, None, :] + rng.normal(0, 0.02, (nt, 4, 3))
    rows /= np.linalg.norm(rows, axis=2, keepdims=True)
    arad = np.arccos(np.clip(np.einsum("tbk,tk->tb", rows, cen), -1, 1)).max(axis=1) * (1 + 1e-9)
    caps = np.full(nt, 0.1)
    fr = envmap.face_frames("openexr")
    for s in (64.0, 4096.0, 777.5):
        s_int = int(s) if float(s).is_integer() else 0
        out = {}
        for name, a in (("culled", arad), ("all", np.full(nt, 10.0))):  # a radius beyond π keeps every texel
            acc, lm, cnt = np.zeros((nt, 4, 4)), np.zeros((nt, 4)), np.zeros(nt, dtype=np.int64)
            ck.tile_gather(cen, rows, caps, a, fr, n, X, Y, Z, rw, bdirs, brw, s, s_int, False, np.exp(-700.0 / s),
                           acc, lm, cnt)
            out[name] = (acc, cnt)
        eta, eps = ck.weight_error(s, bool(s_int))
        (a1, c1), (a0, c0) = out["culled"], out["all"]
        # the groups skipped whole leave out exactly what the per-texel test leaves out
        gcen, galpha = ck.bright_groups(bdirs)
        acc, lm, cnt = np.zeros((nt, 4, 4)), np.zeros((nt, 4)), np.zeros(nt, dtype=np.int64)
        ck.tile_gather(cen, rows, caps, arad, fr, n, X, Y, Z, rw, bdirs, brw, s, s_int, False,
                       np.exp(-700.0 / s), acc, lm, cnt, (gcen, np.full(len(galpha), 4.0)))
        np.testing.assert_array_equal(acc, a1)
        np.testing.assert_array_equal(cnt, c1)
        # the left-out texels still count in the error allowance: every cap texel and every bright texel
        real = np.array([ck.cap_count(cen[i], caps[i], fr, n) for i in range(nt)]) + nb
        assert np.all(c1 >= real) and np.all(c0 >= real)
        tol = (eta + ck.sum_error(c0))[:, None, None] * a0 + eps * (nb + np.abs(rw).sum(axis=1))[None, None, :]
        assert np.all(np.abs(a1 - a0) <= 2 * tol), s
        if s >= 4096:  # the cut does leave texels out at narrow lobes
            kept = (bdirs @ cen.T >= np.cos(np.arccos(np.exp(-700.0 / s)) + arad + 1e-9)).sum()
            assert kept < 0.5 * nb * nt


# ---------------------------------------------------------------------------------------------------------------
# routes: bounds against the exact gather, agreement with the NumPy path
# ---------------------------------------------------------------------------------------------------------------
def test_sparse_compiled_bound_holds_and_agrees_with_numpy(ck):
    from ibl_ref.groundtruth import phong_convolution as pc

    cube = _sun_env(32)
    S = [64.0, 256.0, 1000.0, 4096.0, 777.5, 2e6]  # integer powers, exp(s log c), and a reference-row exponent
    ref = pc.convolve_exact_many(cube, S)
    m0, b0 = pc.convolve_sparse_many(cube, S, rtol=1e-3, impl="numpy")
    m1, b1, info = pc.convolve_sparse_many(cube, S, rtol=1e-3, impl="compiled", return_info=True)
    assert all(i.kernel == "compiled" for i in info[:5])
    for k, s in enumerate(S):
        assert np.all(np.abs(m1[k] - ref[k]) <= b1[k]), s  # rigorous on the compiled path
        assert np.all(np.abs(m0[k] - ref[k]) <= b0[k]), s  # and on the reference
        assert np.all(np.abs(m1[k] - m0[k]) <= b0[k] + b1[k]), s
    # a face subset gives the same numbers on its faces
    sub = pc.convolve_sparse_many(cube, S[:2], rtol=1e-3, impl="compiled", faces=(4, 1))[0]
    np.testing.assert_array_equal(sub, m1[:2][:, [4, 1]])


@pytest.mark.parametrize("leaf", [1, 4])
def test_moment_compiled_equals_numpy_to_rounding(ck, leaf):
    from ibl_ref.groundtruth import moment_convolution as mc
    from ibl_ref.groundtruth import phong_convolution as pc

    cube = _sun_env(32)
    m0, r0 = mc.convolve_moment_many(cube, [1.0, 2.0], leaf=leaf, impl="numpy")
    m1, r1 = mc.convolve_moment_many(cube, [1.0, 2.0], leaf=leaf, impl="compiled")
    np.testing.assert_allclose(m1, m0, rtol=1e-13, atol=0)
    np.testing.assert_allclose(r1, r0, rtol=1e-9, atol=1e-15)
    ref = pc.convolve_exact_many(cube, [1.0, 2.0])
    for k in range(2):
        err = (np.abs(m1[k] - ref[k]) / ref[k]).max(axis=-1)
        assert np.all(err <= r1[k] + 1e-12)


def test_sh_compiled_bound_holds_and_agrees_with_numpy(ck):
    from ibl_ref.groundtruth import phong_convolution as pc
    from ibl_ref.groundtruth import sh_convolution as shc

    cube = _sun_env(32)
    S = [5.0, 20.0, 100.0, 2.5]
    ref = pc.convolve_exact_many(cube, S)
    m0, r0, i0 = shc.convolve_sh_many(cube, S, rtol=1e-3, impl="numpy")
    m1, r1, i1 = shc.convolve_sh_many(cube, S, rtol=1e-3, impl="compiled")
    assert i1["n_bright"] > 0 and i0["L"] == i1["L"]
    for k, s in enumerate(S):
        err = (np.abs(m1[k] - ref[k]) / ref[k]).max(axis=-1)
        assert np.all(err <= r1[k]), s
        d = (np.abs(m1[k] - m0[k]) / ref[k]).max(axis=-1)
        assert np.all(d <= r0[k] + r1[k]), s
    # the split passes (parts) give the single pass to rounding
    setup = shc.sh_split(shc.sh_setup(cube, S, rtol=1e-3, impl="compiled"), 3)
    parts = [shc.sh_project_part(setup, i) for i in range(3)]
    Be, Bo = shc.sh_coefficients(setup, parts)
    mp, rp, _ = shc.sh_assemble(setup, [shc.sh_evaluate_part(setup, Be, Bo, i) for i in range(3)], {})
    np.testing.assert_allclose(mp, m1, rtol=1e-11, atol=0)


def test_sh_planner_floor_by_the_compiled_gather_equals_numpy(ck):
    # the SH planner's estimate of the darkest output texel (exact lobe averages of a 16² copy) by the compiled
    # bright-texel gather: NumPy's values to rounding; exponents whose nearest-texel weight could underflow keep
    # NumPy's row-normalised gather
    from ibl_ref.groundtruth import sh_convolution as shc
    from ibl_ref.synthetic.synthetic_envs import make_env

    rng = np.random.default_rng(2)
    for cube in (_sun_env(32), np.exp(rng.normal(0, 2, (6, 20, 20, 3))), make_env("sky_sun", 8)[..., :1]):
        rad = cube.reshape(-1, cube.shape[-1])
        S = [1.0, 5.0, 64.0, 777.5, 4096.0]
        a, b = shc._output_floor(rad, S, "numpy"), shc._output_floor(rad, S, "compiled")
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=0)
    big = shc._output_floor(rad, [2e6], "compiled")  # e^(s log cos ρ) far below e^-600: NumPy's gather
    np.testing.assert_array_equal(big, shc._output_floor(rad, [2e6], "numpy"))


def test_sparse_bright_cut_of_the_first_attempt_keeps_the_bound(ck):
    # the first compiled attempt leaves out bright texels whose weight is below δ0 ≫ e^-700 (charged in the
    # bound); on log-normal maps with a bright band (many bright texels) and a 1e-4 dark region (tiles that miss
    # and are gathered again) the bound must hold against the exact gather at every texel
    from ibl_ref.environment import envmap
    from ibl_ref.groundtruth import phong_convolution as pc

    rng = np.random.default_rng(7)
    retried = 0
    for n in (12, 16):
        d = envmap.texel_directions(n)
        cube = np.exp(rng.normal(0.0, 2.5, (6, n, n, 3)))
        cube[np.abs(d[..., 2]) < 0.3] *= 1e3
        cube[d[..., 0] > 0.5] *= 1e-4
        S = [64.0, 1000.0, 4096.0, 777.5]
        m, b, info = pc.convolve_sparse_many(cube, S, rtol=1e-3, impl="compiled", return_info=True)
        ref = pc.convolve_exact_many(cube, S)
        for k, s in enumerate(S):
            assert np.all(np.abs(m[k] - ref[k]) <= b[k]), (n, s)
        retried += sum(i.retried_tiles for i in info)
    assert retried > 0  # the dark tiles were gathered again


def test_sparse_threads_bit_identical_and_checked(ck):
    from ibl_ref.groundtruth import phong_convolution as pc
    from ibl_ref.groundtruth.convolve import convolve

    cube = _sun_env(32)
    S = [256.0, 4096.0, 777.5]
    one = pc.convolve_sparse_many(cube, S, rtol=1e-3, impl="compiled")
    for th in (2, 3, 64):  # more threads than half the tiles: capped
        many = pc.convolve_sparse_many(cube, S, rtol=1e-3, impl="compiled", threads=th)
        np.testing.assert_array_equal(many[0], one[0])
        np.testing.assert_array_equal(many[1], one[1])
    for bad in (0, 1.5, True, "2"):
        with pytest.raises(IBLError, match="threads"):
            pc.convolve_sparse_many(cube, S[:1], impl="compiled", threads=bad)
    # a round of sparse gathers only: one job whose tiles the workers' threads share; the same numbers as serial
    r1 = convolve(cube, S, rtol=1e-3, method="sparse", kernel="compiled", workers=1)
    r2 = convolve(cube, S, rtol=1e-3, method="sparse", kernel="compiled", workers=2)
    assert r2.info.get("sparse_threads") == 2 and "sparse_threads" not in r1.info
    for s in S:
        np.testing.assert_array_equal(r2.maps[s], r1.maps[s])
        np.testing.assert_array_equal(r2.error_bound[s], r1.error_bound[s])


@pytest.fixture
def no_tiny_shortcut(monkeypatch):
    import ibl_ref.groundtruth.convolve as cv

    monkeypatch.setattr(cv, "AUTO_EXACT_PAIRS", 0)
    monkeypatch.setattr(cv, "MOMENT_MIN_PAIRS", 0)


def test_convolve_compiled_bounds_rigorous_and_bit_identical_across_workers(ck, no_tiny_shortcut):
    from ibl_ref.groundtruth.convolve import convolve
    from ibl_ref.groundtruth import phong_convolution as pc

    cube = _sun_env(32)  # 32²: every route is the cheapest for some exponent
    S = [1.0, 2.0, 5.0, 64.0, 1000.0, 4096.0, np.inf]
    ref = pc.convolve_exact_many(cube, S)
    runs = [convolve(cube, S, rtol=1e-3, kernel="compiled", workers=w, backend=b)
            for w, b in ((1, "auto"), (2, "process"), (2, "thread"))]
    res = runs[0]
    assert res.info["kernel"] == "compiled"
    assert {"moment", "sh", "sparse", "exact"} <= set(res.method_used.values())
    for k, s in enumerate(S):
        err = (np.abs(res.maps[s] - ref[k]) / ref[k]).max(axis=-1)
        assert np.all(err <= res.error_bound[s] + 1e-12), (s, res.method_used[s])
        assert res.error_bound[s].max() <= 1e-3
        for r in runs[1:]:
            np.testing.assert_array_equal(r.maps[s], res.maps[s])
            np.testing.assert_array_equal(r.error_bound[s], res.error_bound[s])
    num = convolve(cube, S, rtol=1e-3, kernel="numpy", workers=1)
    assert num.info["kernel"] == "numpy"
    for s in S:  # the two kernels agree within the sum of their bounds
        d = (np.abs(num.maps[s] - res.maps[s]) / ref[S.index(s)]).max(axis=-1)
        assert np.all(d <= num.error_bound[s] + res.error_bound[s] + 1e-12), s


#: a fresh process: the compiled kernels on a tiny map (each route); it prints the routes and a checksum
_RUN_COMPILED = textwrap.dedent(
    """
    import numpy as np
    import ibl_ref.groundtruth.convolve as cv
    from ibl_ref.synthetic.synthetic_envs import SUN_NEAR_CORNER, make_env
    cube = make_env("sky_sun", 16, sun_direction=SUN_NEAR_CORNER, sun_radiance=1e5)
    rs = [cv.convolve(cube, [s], method=m, kernel="compiled", workers=1)
          for s, m in ((1.0, "moment"), (5.0, "sh"), (300.0, "sparse"))]
    print(sorted(m for r in rs for m in r.method_used.values()),
          repr(float(sum(float(np.sum(r.maps[s])) for r in rs for s in r.maps))))
    """
)


def _run_compiled(cache, extra=None, preexec=None):
    p = subprocess.run([sys.executable, "-c", _RUN_COMPILED], capture_output=True, text=True, timeout=900,
                       env=_env({"NUMBA_CACHE_DIR": str(cache), **(extra or {})}), preexec_fn=preexec)
    return p.returncode, p.stdout.strip(), [ln for ln in p.stderr.splitlines() if ln.strip()]


def _entries(cache, kind):
    return sorted(cache.rglob(f"numba_loops.*.{kind}"))


@pytest.fixture(scope="module")
def warm_cache(tmp_path_factory):
    """A numba cache of the loops written by one process, and that process's output."""
    pytest.importorskip("numba", reason="the compiled kernels need numba")
    cache = tmp_path_factory.mktemp("nbcache")
    rc, out, err = _run_compiled(cache)
    assert rc == 0 and not err, err
    assert "'moment'" in out and "'sh'" in out and "'sparse'" in out
    assert _entries(cache, "nbi") and _entries(cache, "nbc") and list(cache.rglob("ibl_ref_kernels.json"))
    return cache, out


@pytest.mark.parametrize("damage", ["truncated index", "truncated data", "zeroed data", "garbage record"])
def test_a_damaged_numba_cache_never_crashes_a_run(warm_cache, tmp_path, damage):
    """Every kind of damage to the cache of the loops (a truncated index or data file, data zeroed in the middle —
    machine code that may crash the process that runs it —, a garbage record): the next run gives the same numbers
    with at most one line on stderr, and the run after it none (the cache was rebuilt)."""
    import shutil

    src, good = warm_cache
    cache = tmp_path / "nbcache"
    shutil.copytree(src, cache)
    if damage == "truncated index":
        for f in _entries(cache, "nbi"):
            f.write_bytes(f.read_bytes()[:40])
    elif damage == "truncated data":
        for f in _entries(cache, "nbc"):
            f.write_bytes(f.read_bytes()[: len(f.read_bytes()) // 3])
    elif damage == "zeroed data":
        for f in _entries(cache, "nbc"):
            b = bytearray(f.read_bytes())
            b[len(b) // 4 : 3 * len(b) // 4] = bytes(len(b) // 2)
            f.write_bytes(bytes(b))
    else:
        next(cache.rglob("ibl_ref_kernels.json")).write_text("{not json")
    rc, out, err = _run_compiled(cache)
    assert rc == 0 and out == good, err
    assert len(err) <= 1, err
    if damage != "garbage record":
        assert len(err) == 1 and "numba's cache of the kernels" in err[0] and str(cache) in err[0], err
    rc, out, err = _run_compiled(cache)
    assert rc == 0 and out == good and not err, err


def test_a_cache_that_cannot_be_written_falls_back_without_a_traceback(tmp_path):
    """A cold cache whose files cannot be written (the file-size limit makes every write fail, as a full disk
    does): the run compiles without the cache and gives the numbers, naming the folder, without a traceback."""
    pytest.importorskip("numba", reason="the compiled kernels need numba")
    import resource
    import signal

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write beyond the limit fails (EFBIG) instead
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))

    rc, out, err = _run_compiled(tmp_path / "full", preexec=limit)
    assert rc == 0 and "'sparse'" in out, err
    assert not any("Traceback" in ln for ln in err) and 1 <= len(err) <= 2, err
    assert str(tmp_path / "full") in err[-1] and "without it" in err[-1], err


def test_removed_backend_switch_is_named_not_ignored(tmp_path):
    pytest.importorskip("numba", reason="the compiled kernels need numba")
    rc, out, err = _run_compiled(tmp_path / "c", {"IBL_REF_KERNEL_BACKEND": "garbage"})
    assert rc == 0 and "'sparse'" in out
    assert len(err) == 1 and "IBL_REF_KERNEL_BACKEND is no longer read" in err[0], err


def test_auto_kernel_keeps_numpy_for_small_work_in_a_fresh_process():
    pytest.importorskip("numba", reason="auto chooses between the kernels only when numba is installed")
    code = textwrap.dedent(
        """
        import numpy as np
        from ibl_ref.groundtruth.convolve import convolve
        from ibl_ref.synthetic.synthetic_envs import SUN_NEAR_CORNER, make_env
        cube = make_env("sky_sun", 32, sun_direction=SUN_NEAR_CORNER, sun_radiance=1e5)
        r = convolve(cube, [4096.0])
        print(r.info["kernel"], "|", r.info.get("kernel_auto"))
        r = convolve(cube, [4096.0], kernel="compiled")
        r = convolve(cube, [4096.0])
        print(r.info["kernel"])
        """
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(), timeout=600)
    assert p.returncode == 0, p.stderr
    first, second = p.stdout.strip().splitlines()
    assert first.startswith("numpy | numpy: model")  # loading the compiled kernels would cost more
    assert second == "compiled"  # once loaded, they are free to use


def test_cli_kernel_flag_and_sidecar(tmp_path, ck):
    from ibl_ref.environment.exr_io import load_cube, write_envmap

    write_envmap(tmp_path / "in.exr", _sun_env(16), layout="cube")
    outs = {}
    for k in ("numpy", "compiled"):
        p = subprocess.run([sys.executable, "-m", "ibl_ref", "convolve", str(tmp_path / "in.exr"),
                            str(tmp_path / f"{k}.exr"), "-s", "300", "--kernel", k], capture_output=True, text=True,
                           env=_env(), timeout=600)
        assert p.returncode == 0, p.stderr
        side = json.loads((tmp_path / f"{k}.json").read_text())
        assert side["kernel"] == k and side["info"]["kernel"] == k
        outs[k] = (load_cube(tmp_path / f"{k}_s300.exr"), side["exponents"][0]["rel_bound_max"])
    (a, ba), (b, bb) = outs["numpy"], outs["compiled"]
    assert np.max(np.abs(a - b) / a) <= ba + bb + 1e-6  # float32 files


# ---------------------------------------------------------------------------------------------------------------
# the cache, read-only; array bounds
# ---------------------------------------------------------------------------------------------------------------
def _read_only_dir(tmp_path):
    d = tmp_path / "ro_cache"
    d.mkdir()
    d.chmod(0o555)
    try:  # root may write anyway: then a folder no one can write to
        (d / "probe").write_text("x")
        (d / "probe").unlink()
        return Path("/sys/kernel") if Path("/sys/kernel").is_dir() else None
    except OSError:
        return d


def test_read_only_numba_cache_dir_falls_back_with_one_line(tmp_path):
    pytest.importorskip("numba", reason="the compiled kernels need numba")
    ro = _read_only_dir(tmp_path)
    if ro is None:
        pytest.skip("no read-only folder available on this machine (running as root without /sys)")
    code = textwrap.dedent(
        """
        import numpy as np
        from ibl_ref.groundtruth.convolve import convolve
        r = convolve(np.ones((6, 8, 8, 3)), [64.0], method="sparse", kernel="compiled")
        print("OK", r.info["kernel"], float(r.error_bound[64.0].max()))
        """
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900,
                       env=_env({"NUMBA_CACHE_DIR": str(ro)}))
    assert p.returncode == 0, p.stderr
    assert "OK compiled" in p.stdout
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    # numba passes over the folder (its cache goes elsewhere, or nowhere): one line says so
    assert len(lines) == 1 and ("no writable folder for numba's cache" in lines[0]
                                or f"NUMBA_CACHE_DIR={ro} cannot be written" in lines[0]), p.stderr


def test_kernels_stay_within_their_arrays(tmp_path):
    """Every kernel compiled with numba's bounds checking (its own cache) on small inputs: no index leaves its
    array (an out-of-bounds write had corrupted the heap once)."""
    pytest.importorskip("numba", reason="the compiled kernels need numba")
    code = textwrap.dedent(
        """
        import numpy as np
        from ibl_ref.groundtruth.kernels import get_kernels
        from ibl_ref.groundtruth import moment_convolution as mc, phong_convolution as pc, sh_convolution as shc
        from ibl_ref.synthetic.synthetic_envs import SUN_NEAR_CORNER, make_env
        get_kernels("compiled").warm_up()
        cube = make_env("sky_sun", 12, sun_direction=SUN_NEAR_CORNER, sun_radiance=1e5)
        pc.convolve_sparse_many(cube, [64.0, 2e6, 300.5], impl="compiled")
        # narrow caps: the scratch size from the cap-area bound, the bright texels left out far from a tile
        pc.convolve_sparse_many(make_env("sky_sun", 48, sun_direction=SUN_NEAR_CORNER, sun_radiance=1e5),
                                [1024.0, 4096.0], impl="compiled", n_bright=40)
        mc.convolve_moment_many(cube, [1.0, 2.0], impl="compiled")
        mc.convolve_moment_many(make_env("sky_sun", 16), [1.0, 2.0], leaf=4, impl="compiled")
        shc.convolve_sh_many(make_env("sky_sun", 16), [5.0, 20.0], impl="compiled")
        print("OK")
        """
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=1200,
                       env=_env({"NUMBA_BOUNDSCHECK": "1", "NUMBA_CACHE_DIR": str(tmp_path / "nbc")}))
    assert p.returncode == 0 and "OK" in p.stdout, p.stderr[-2000:]
