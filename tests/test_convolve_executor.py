"""Scale-out and resource planning of ibl_ref.groundtruth.convolve: executors, Dask, the memory planner, dying workers.

The reference is always the serial run of the same call (``workers=1``), an independent execution path
(no pool, no pickling); results must agree bit for bit because the jobs are fixed by the sizes alone.
"""

import os
import signal
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

import numpy as np
import pytest

import ibl_ref.groundtruth.convolve as cv
from ibl_ref.groundtruth import moment_convolution as mc
from ibl_ref.groundtruth.convolve import convolve, plan_memory_workers
from ibl_ref.errors import IBLError

# the sky + sun scene and the routing of a small map like a 128² one are shared with the worker tests
from test_convolve_workers import _sun_env, routed_like_large  # noqa: F401 (fixture)

S = [1.0, 2.0, 10.0, 1000.0]


def _same(a, b):
    assert a.method_used == b.method_used
    for s in a.maps:
        assert np.array_equal(a.maps[s], b.maps[s]), s
        assert np.array_equal(a.error_bound[s], b.error_bound[s]), s


def test_any_executor_gives_the_serial_result(routed_like_large):
    cube = _sun_env(16)
    ref = convolve(cube, S, workers=1)
    assert set(ref.method_used.values()) == {"moment", "sh", "sparse"}
    with ThreadPoolExecutor(2) as ex:
        r = convolve(cube, S, executor=ex)
    _same(r, ref)
    assert r.info["backend"] == "executor"
    # a spawned process pool: jobs and inputs are pickled, BLAS is limited inside each job
    import multiprocessing

    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as ex:
        r = convolve(cube, S, executor=ex)
    _same(r, ref)


def test_dask_local_cluster_bit_identical(routed_like_large, tmp_path):
    distributed = pytest.importorskip("distributed")
    from ibl_ref.cli import main
    from ibl_ref.environment.exr_io import load_cube, write_envmap

    cube = _sun_env(16)
    ref = convolve(cube, S, workers=1)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        with distributed.Client(cluster) as client:
            r = convolve(cube, S, executor=client)
            _same(r, ref)
            r2 = convolve(cube, S, executor=cluster.scheduler_address)  # by address (own client)
            _same(r2, ref)
        # the command line: --scheduler ADDRESS writes the serial run's maps (stored as float32)
        src = tmp_path / "in.exr"
        write_envmap(src, cube.astype(np.float32), layout="cube")
        cube32 = load_cube(src)
        ref32 = convolve(cube32, [10.0], workers=1).maps[10.0]
        assert main(["convolve", str(src), str(tmp_path / "out.exr"), "-s", "10",
                     "--scheduler", cluster.scheduler_address]) == 0
        got = load_cube(tmp_path / "out_s10.exr")
        assert np.array_equal(got, ref32.astype(np.float32).astype(np.float64))


def test_bad_executor_and_address_are_clear_errors():
    cube = np.ones((6, 4, 4))
    with pytest.raises(IBLError, match="executor must be"):
        convolve(cube, [4.0], executor=42)
    pytest.importorskip("distributed")
    with pytest.raises(IBLError, match="cannot connect"):
        convolve(cube, [4.0], executor="tcp://127.0.0.1:9")  # discard port: nothing listens


def test_memory_planner_arithmetic():
    gb = 1e9
    # 3 jobs of 1, 2, 3 GB; 2 workers run the two largest together (5 GB)
    assert plan_memory_workers(2, [1 * gb, 2 * gb, 3 * gb], 10 * gb) == 2
    assert plan_memory_workers(2, [1 * gb, 2 * gb, 3 * gb], 5 * gb) == 1  # 0.8·5 = 4 < 5
    assert plan_memory_workers(4, [1 * gb] * 4, 3.9 * gb) == 3  # 0.8·3.9 = 3.12
    assert plan_memory_workers(2, [9 * gb], 1 * gb) == 1  # never below one
    assert plan_memory_workers(2, [9 * gb], None) == 2  # unknown memory: as asked


def test_memory_limit_lowers_workers_not_results(routed_like_large):
    cube = _sun_env(16)
    ref = convolve(cube, S, workers=1)
    r = convolve(cube, S, workers=2, backend="thread", memory_limit=1e6)  # 1 MB: nothing fits twice
    assert r.info["workers_planned"] == 1
    assert "memory_warning" in r.info
    _same(r, ref)
    r = convolve(cube, S, workers=2, backend="thread", memory_limit=1e12)
    assert r.info["workers_planned"] == 2
    with pytest.raises(IBLError, match="memory_limit"):
        convolve(cube, S, memory_limit=-1)


def test_tiny_jobs_do_not_start_a_pool(monkeypatch):
    # 16² faces: the model cost of all jobs is far below PARALLEL_MIN_SECONDS (1 s)
    monkeypatch.setattr(cv, "MOMENT_MIN_PAIRS", 0)
    monkeypatch.setattr(cv, "AUTO_EXACT_PAIRS", 0)
    r = convolve(_sun_env(16), [1.0, 2.0], workers=2, backend="process")
    assert r.method_used == {1.0: "moment", 2.0: "moment"}
    assert r.info["workers_planned"] == 1


def test_moment_memory_estimate_bounds_the_chunked_working_set():
    # the chunking keeps one chunk's band pairs below MOMENT_CHUNK_PAIRS; the estimate must exceed
    # the per-texel moment arrays it allocates (an independent count: 6·P²·(3+6)·Q float64)
    n, Q = 512, 4
    assert mc.moment_peak_bytes(n, n, 2) > 6 * n * n * 9 * Q * 8
    assert mc.moment_tiles_per_chunk(n, n, 8, 4) * mc.moment_band_pairs_per_tile(n, n, 8, 4) <= mc.MOMENT_CHUNK_PAIRS


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_dying_worker_is_a_clear_error(routed_like_large, monkeypatch):
    def killed(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGKILL)  # what the out-of-memory killer does

    monkeypatch.setattr(mc, "convolve_moment_many", killed)
    with pytest.raises(IBLError, match="worker process died"):
        convolve(_sun_env(16), S, workers=2, backend="process")
