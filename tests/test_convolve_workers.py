"""Tests of the ``workers`` option of ibl_ref.groundtruth.convolve and of the pieces it runs concurrently.

Reference values come from independent routes: the full (unsplit) call of each route for face
subsets, the dense SH matrix (no symmetry folding) for the octant-symmetric SH projection, and
``convolve_exact_many`` (every texel) for the accuracy check.
"""

import numpy as np
import pytest

from ibl_ref.environment import envmap
from ibl_ref.groundtruth import moment_convolution as mc
from ibl_ref.groundtruth import phong_convolution as pc
from ibl_ref.groundtruth import sh_convolution as shc
from ibl_ref.groundtruth import sh_basis as shbasis
from ibl_ref.groundtruth import sh_bounds as shb
from ibl_ref.groundtruth.convolve import WORKERS_ENV, convolve, default_workers
from ibl_ref.errors import IBLError


def _sun_env(n):
    from ibl_ref.synthetic.synthetic_envs import SUN_NEAR_CORNER, make_env

    return make_env("sky_sun", n, sun_direction=SUN_NEAR_CORNER, sun_radiance=1e5)


def _scaled_costs(monkeypatch, **factors):
    """Scale the planner's cost constants ``name=factor`` of every kernel (the registry entries are read-only)."""
    import ibl_ref.groundtruth.convolve as cv

    orig = cv._unit
    monkeypatch.setattr(cv, "_unit", lambda name, impl: orig(name, impl) * factors.get(name, 1.0))


@pytest.fixture
def routed_like_large(monkeypatch):
    """Route a small map like a 128² one: moment for s = 1, 2, SH / sparse for the rest."""
    import ibl_ref.groundtruth.convolve as cv

    monkeypatch.setattr(cv, "AUTO_EXACT_PAIRS", 0)
    monkeypatch.setattr(cv, "MOMENT_MIN_PAIRS", 0)
    monkeypatch.setattr(cv, "PARALLEL_MIN_SECONDS", 0.0)  # tiny jobs still go to the pool
    # exact only as the bound-driven fallback (1e6 units per pair); at 16² the sparse gather is cheap even for
    # s = 10: cost it 4× higher so that s = 10 goes to SH as it does at 128² (three routes in one call)
    _scaled_costs(monkeypatch, EXACT_UNITS_PER_PAIR=1e6 / 17.0, EXACT_UNITS_PER_PAIR_S1=1e6 / 6.0,
                  SPARSE_UNITS_PER_PAIR=4.0, SPARSE_UNITS_PER_OUTPUT=4.0)


def test_results_bit_identical_for_any_worker_count(routed_like_large):
    cube = _sun_env(16)
    S = [1.0, 2.0, 10.0, 1000.0]
    cfg = [(1, "auto"), (2, "thread"), (3, "thread"), (2, "process"), (2, "auto")]
    runs = [convolve(cube, S, rtol=1e-3, workers=w, backend=b) for w, b in cfg]
    used = set(runs[0].method_used.values())
    assert used == {"moment", "sh", "sparse"}  # three routes, 3 + 1 + 3 jobs ran concurrently
    for r in runs[1:]:
        assert r.method_used == runs[0].method_used
        for s in S:
            assert np.array_equal(r.maps[s], runs[0].maps[s])
            assert np.array_equal(r.error_bound[s], runs[0].error_bound[s])
    assert [r.info["workers"] for r in runs] == [w for w, _ in cfg]
    assert [r.info["backend"] for r in runs[:4]] == ["serial", "thread", "thread", "process"]
    assert runs[4].info["backend"] in ("process", "thread")


def test_parallel_auto_within_bound_of_exact(routed_like_large):
    # independent reference: the dense exact gather; auto's reported per-texel bound must hold
    # (+1e-12 relative: float64 rounding of sums over 6N² terms)
    cube = _sun_env(12)
    S = [1.0, 2.0, 16.0, 1000.0]
    res = convolve(cube, S, rtol=1e-3, workers=2)
    ref = pc.convolve_exact_many(cube, S)
    for k, s in enumerate(S):
        rel = (np.abs(res.maps[s] - ref[k]) / ref[k]).max(axis=-1)
        assert np.all(rel <= res.error_bound[s] + 1e-12), s
        assert rel.max() <= 1e-3, s


@pytest.mark.parametrize("n", [8, 7])
def test_face_subsets_match_full_call(n):
    # the full six-face call is the reference; moment: equal up to rounding of the band batching
    # (relative 1e-13 ≫ 6N² · 1e-16); sparse: every tile is independent, so bit-for-bit
    cube = _sun_env(n)
    m_full, r_full = mc.convolve_moment_many(cube, [1.0, 2.0])
    parts = [mc.convolve_moment_many(cube, [1.0, 2.0], faces=f) for f in ((0, 1), (2, 3), (4, 5))]
    m_cat = np.concatenate([p[0] for p in parts], axis=1)
    assert m_cat.shape == m_full.shape
    np.testing.assert_allclose(m_cat, m_full, rtol=1e-13, atol=0)
    sp_full, b_full = pc.convolve_sparse_many(cube, [64.0, 1000.0])
    sp5, b5 = pc.convolve_sparse_many(cube, [64.0, 1000.0], faces=[5, 1])
    assert np.array_equal(sp5, sp_full[:, [5, 1]]) and np.array_equal(b5, b_full[:, [5, 1]])


def test_octant_symmetric_sh_projection_matches_dense():
    # reference: the dense real-SH matrix at every direction (no symmetry folding)
    n, L = 6, 11
    dirs = envmap.texel_directions(n).reshape(-1, 3)
    assert shbasis._octant_orbits(dirs) is not None
    assert shbasis._octant_orbits(envmap.texel_directions(5).reshape(-1, 3)) is None  # texels on the planes
    rng = np.random.default_rng(3)
    cube = rng.random((6, n, n, 2))
    Y = shbasis.real_sh(dirs, L)  # (M, (L+1)²)
    w = cube.reshape(-1, 2) * envmap.cube_solid_angles(n).reshape(-1, 1)
    a = shbasis.sh_project(cube, L)
    np.testing.assert_allclose(a, Y.T @ w, rtol=0, atol=1e-13)  # sums of 216 terms ≤ 1: rounding only
    coeffs = rng.standard_normal(((L + 1) ** 2, 3))
    np.testing.assert_allclose(shbasis.sh_evaluate(coeffs, dirs), Y @ coeffs, rtol=0, atol=1e-12)
    # same directions in and out (shared SH matrix) vs an odd-size grid's generic path
    kc = np.stack([shb.zonal_coefficients(s, L) for s in (2.0, 9.0)])
    got = shbasis.sh_lobe_convolve(dirs, w, dirs, kc)
    want = np.einsum("kl,ml,lq->kmq", kc[:, [int(np.sqrt(i)) for i in range((L + 1) ** 2)]], Y, Y.T @ w)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)


def test_workers_argument_and_environment(monkeypatch):
    cube = _sun_env(4)
    monkeypatch.setenv(WORKERS_ENV, "3")
    assert default_workers() == 3
    assert convolve(cube, 4.0).info["workers"] == 3
    monkeypatch.delenv(WORKERS_ENV)
    assert 1 <= default_workers() <= 2
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(IBLError, match=r"workers must be a positive integer"):
            convolve(cube, 4.0, workers=bad)
    with pytest.raises(IBLError, match=r"unknown parallel backend 'mpi'; choose one"):
        convolve(cube, 4.0, workers=2, backend="mpi")
    monkeypatch.setenv(WORKERS_ENV, "many")
    with pytest.raises(IBLError, match=r"IBL_REF_WORKERS must be a positive integer"):
        convolve(cube, 4.0)
    with pytest.raises(IBLError, match=r"faces must be distinct face indices"):
        mc.convolve_moment_many(cube, [1.0], faces=[6])
    with pytest.raises(IBLError, match=r"faces must be distinct face indices"):
        pc.convolve_sparse_many(cube, [64.0], faces=[0, 0])


def test_blas_held_at_one_thread_inside_and_restored_after(monkeypatch):
    # bit-for-bit identity across worker counts needs the same BLAS blocking in every job: the SH pass (the
    # only BLAS-heavy route) must see 1 BLAS thread, serial included, and the caller's limits come back
    from threadpoolctl import threadpool_info

    def blas_threads():
        return sorted(p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas")

    before = blas_threads()
    assert before  # NumPy's BLAS is loaded, so the check below is not vacuous
    seen = []
    real = shc.convolve_sh_many

    def spy(*a, **k):
        seen.append(blas_threads())
        return real(*a, **k)

    monkeypatch.setattr(shc, "convolve_sh_many", spy)
    res = convolve(_sun_env(8), [16.0], method="sh", workers=1)
    assert res.method_used[16.0] == "sh" and seen and all(t == 1 for t in seen[0])
    assert blas_threads() == before


def test_cli_workers_option(tmp_path):
    pytest.importorskip("OpenEXR")
    from ibl_ref.environment import exr_io
    import json

    from ibl_ref.cli import main

    cube = _sun_env(6)
    src = tmp_path / "env.exr"
    exr_io.write_envmap(src, cube, layout="cube")
    for w in (1, 2):
        out = tmp_path / f"w{w}.exr"
        assert main(["convolve", str(src), str(out), "-s", "16", "-s", "1000", "--workers", str(w)]) == 0
        assert json.loads(out.with_suffix(".json").read_text())["workers"] == w
    # same bits from one and two workers (the jobs do not depend on the worker count)
    for s in ("16", "1000"):
        a = exr_io.load_cube(tmp_path / f"w1_s{s}.exr")
        b = exr_io.load_cube(tmp_path / f"w2_s{s}.exr")
        assert np.array_equal(a, b)
    assert main(["convolve", str(src), str(tmp_path / "bad.exr"), "-s", "4", "--workers", "0"]) == 1


def test_auto_backend_avoids_fork_in_multithreaded_process(routed_like_large):
    # forking a process that runs other threads is unsafe: auto must fall back to threads then
    import threading

    cube = _sun_env(8)
    serial = convolve(cube, [1.0, 1000.0], workers=1)
    stop = threading.Event()
    t = threading.Thread(target=stop.wait, daemon=True)
    t.start()
    try:
        res = convolve(cube, [1.0, 1000.0], workers=2, backend="auto")
    finally:
        stop.set()
        t.join()
    assert res.info["backend"] == "thread"
    for s in (1.0, 1000.0):
        assert np.array_equal(res.maps[s], serial.maps[s])


def test_auto_backend_uses_threads_inside_a_daemonic_process():
    # a multiprocessing worker (daemonic) may not start children: auto must pick threads there, and
    # an explicit process backend must say why it cannot run
    import multiprocessing

    ctx = multiprocessing.get_context("fork")
    with ctx.Pool(1) as pool:
        backend, err = pool.apply(_daemon_probe)
    assert backend == "thread"
    assert "daemonic" in err


def _daemon_probe():
    res = convolve(_sun_env(4), [1.0, 1000.0], workers=2)
    try:
        convolve(_sun_env(4), [1.0, 1000.0], workers=2, backend="process")
        err = ""
    except IBLError as exc:
        err = str(exc)
    return res.info["backend"], err


def test_sparse_float32_kernel_identical_for_any_worker_count():
    # at 128², s = 256 the sparse route runs the float32 kernel (kernel="auto"): its jobs (fixed face groups) give
    # the same maps and bounds bit for bit with 1 and 2 workers
    cube = _sun_env(128)
    _, _, info = pc.convolve_sparse_many(cube, [256.0], faces=(0,), return_info=True)
    assert info[0].kernel == "float32"
    r1 = convolve(cube, [256.0], method="sparse", workers=1)
    r2 = convolve(cube, [256.0], method="sparse", workers=2)
    assert np.array_equal(r1.maps[256.0], r2.maps[256.0])
    assert np.array_equal(r1.error_bound[256.0], r2.error_bound[256.0])


@pytest.mark.parametrize("n", [16, 15])  # even: octant orbits; odd: z-mirror pairs
def test_split_sh_pass_agrees_with_the_single_job_and_is_bit_identical_across_workers(monkeypatch, n):
    # a big SH pass runs as SH_PARTS projection jobs, then SH_PARTS evaluation jobs (the 1024² case);
    # forced here on a small map, with SH chunks of 24 directions so that every part holds real work.
    # Independent references: the single-job pass (the same sums in one order, so equal to rounding)
    # and the dense exact gather (the reported rigorous bound must hold)
    import ibl_ref.groundtruth.convolve as cv
    from ibl_ref.groundtruth import sh_basis

    monkeypatch.setattr(sh_basis, "_chunk", lambda L: 24)
    cube = _sun_env(n)
    S = [8.0, 32.0]
    single = convolve(cube, S, method="sh", rtol=1e-3, workers=1)
    assert "parts" not in single.info["sh"]
    monkeypatch.setattr(cv, "SH_SPLIT_MIN_SECONDS", 0.0)
    monkeypatch.setattr(cv, "PARALLEL_MIN_SECONDS", 0.0)
    runs = [convolve(cube, S, method="sh", rtol=1e-3, workers=w, backend=b)
            for w, b in [(1, "auto"), (2, "process"), (2, "thread")]]
    assert runs[0].info["sh"]["parts"] == cv.SH_PARTS
    sym = shc.sh_split(shc.sh_setup(cube, S, rtol=1e-3), cv.SH_PARTS).sym_src
    assert sum(u1 > u0 for u0, u1 in sym.ranges) >= 3  # the work is really spread over the parts
    exact = pc.convolve_exact_many(cube, S)
    for k, s in enumerate(S):
        ref = single.maps[s]
        # same terms, other summation order: float64 rounding of sums of O(L²) terms (L ≈ 28) per value
        assert np.max(np.abs(runs[0].maps[s] - ref) / ref) < 1e-12
        err = np.max(np.abs(runs[0].maps[s] - exact[k]) / exact[k], axis=-1)
        assert np.all(err <= runs[0].error_bound[s] * (1 + 1e-9) + 1e-12)
        for r in runs[1:]:
            assert np.array_equal(r.maps[s], runs[0].maps[s])
            assert np.array_equal(r.error_bound[s], runs[0].error_bound[s])


def test_sh_parts_cover_every_direction_once_and_sum_to_the_whole_projection(monkeypatch):
    # the pieces of work of a split pass (octant orbits at even sizes, mirror pairs at odd ones), against
    # the dense SH matrix of real_sh (no symmetry folding); chunks of 8 directions give every part work
    from ibl_ref.groundtruth import sh_basis as sb

    monkeypatch.setattr(sb, "_chunk", lambda L: 8)
    rng = np.random.default_rng(3)
    for n in (6, 5):
        d = envmap.texel_directions(n).reshape(-1, 3)
        W = rng.random((d.shape[0], 2))
        L = 6
        Y = sb.real_sh(d, L)  # (M, (L+1)²), dense, no symmetry folding
        a_ref = Y.T @ W
        sym = sb.SymmetryPlan(d, L, 3)
        assert all(u1 > u0 for u0, u1 in sym.ranges)
        parts = [sb.project_part(d, W, sym, i) for i in range(3)]
        ae = sum(p[0] for p in parts)
        ao = sum(p[1] for p in parts)
        ev, od = sb._layout(L)
        std = np.empty_like(a_ref)
        std[sb._std_index(ev)] = ae
        std[sb._std_index(od)] = ao
        assert np.allclose(std, a_ref, rtol=0, atol=1e-12)
        Be, Bo = rng.random((len(ev), 3)), rng.random((len(od), 3))
        coef = np.empty((Y.shape[1], 3))
        coef[sb._std_index(ev)] = Be
        coef[sb._std_index(od)] = Bo
        hits = np.zeros(d.shape[0], dtype=int)
        for i in range(3):
            idx, vals = sb.evaluate_part(d, Be, Bo, sym, i)
            np.add.at(hits, idx, 1)
            assert np.allclose(vals, Y[idx] @ coef, rtol=0, atol=1e-12)
        assert np.all(hits == 1)
