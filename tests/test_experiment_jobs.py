"""Experiment sweeps on any Executor: the independent cases of fig5 and cross-validate, and the
experiments of ``reproduce``, run through ibl_ref.executors.map_jobs; the data files of a run on local processes or
on a local 2-worker Dask cluster are bit-for-bit those of a serial run (timing columns aside)."""

import csv
import io
from pathlib import Path

import numpy as np
import pytest

from ibl_ref import experiments
from ibl_ref.cli import main

FIG5_TINY = dict(face_sizes=(16,), centre_only_sizes=(32,), exponents=5)
CROSS_TINY = dict(size=8, env_size=8, spp=16, envmap_height=64, rtol=5e-2)
REPRODUCE_NAMES = ["fig3", "fig4"]  # fast, and no timing column in their data files


@pytest.fixture(scope="module")
def dask_client():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl:
        with distributed.Client(cl) as client:
            yield client


def _fig5(out, **jobs):
    experiments.get("fig5").run(Path(out), quick=True, **FIG5_TINY, **jobs)
    return (Path(out) / "fig5_errors.csv").read_bytes()


@pytest.mark.same_without_tools
def test_fig5_cases_on_processes_and_dask_match_serial(tmp_path, dask_client):
    serial = _fig5(tmp_path / "serial")
    assert serial.count(b"\n") > 100  # 4 configurations x 5 filters x s values x 2 volumes x 2 centrings
    assert _fig5(tmp_path / "w2", workers=2) == serial
    assert _fig5(tmp_path / "dask", executor=dask_client) == serial


def _rows_without_times(path):
    text = "".join(ln for ln in path.read_text().splitlines(keepends=True) if not ln.startswith("#"))
    return [{k: v for k, v in r.items() if not k.endswith("time_s")} for r in csv.DictReader(io.StringIO(text))]


def test_cross_validate_cases_on_dask_match_serial(tmp_path, dask_client, mitsuba_llvm):
    mod = experiments.get("cross-validate")
    mod.run(tmp_path / "serial", quick=True, **CROSS_TINY)
    mod.run(tmp_path / "dask", quick=True, executor=dask_client, **CROSS_TINY)
    a, b = (_rows_without_times(tmp_path / d / "cross_validate.csv") for d in ("serial", "dask"))
    assert len(a) == 12 and a == b  # 3 Phong cases + 3 GGX cases × 3 Mitsuba BSDF / Smith forms
    with np.load(tmp_path / "serial" / "cross_validate_images.npz") as za, \
            np.load(tmp_path / "dask" / "cross_validate_images.npz") as zb:
        assert sorted(za.files) == sorted(zb.files) and len(za.files) == 36
        for k in za.files:
            assert np.array_equal(za[k], zb[k]), k


def _data_files(root):
    return {p.relative_to(root): p.read_bytes() for p in sorted(Path(root).rglob("*"))
            if p.suffix in (".csv", ".json") and p.name != "reproduce_summary.json"
            and not p.name.endswith("_outputs.json")}  # the experiments' manifests (tests/test_adversarial_round3.py)


@pytest.mark.same_without_tools
def test_reproduce_on_processes_and_dask_matches_serial(tmp_path, dask_client):
    serial = experiments.reproduce(tmp_path / "serial", quick=True, names=REPRODUCE_NAMES)
    assert [r["experiment"] for r in serial["runs"]] == REPRODUCE_NAMES and serial["ran_on"] == "serial"
    ref = _data_files(tmp_path / "serial")
    assert len(ref) == 3
    for name, jobs in (("w2", dict(workers=2)), ("dask", dict(executor=dask_client))):
        s = experiments.reproduce(tmp_path / name, quick=True, names=REPRODUCE_NAMES, **jobs)
        assert [r["experiment"] for r in s["runs"]] == REPRODUCE_NAMES
        assert all(Path(f).exists() for r in s["runs"] for f in r["figures"])
        assert _data_files(tmp_path / name) == ref, name


@pytest.mark.parametrize("name", REPRODUCE_NAMES)
def test_data_files_do_not_depend_on_the_blas_thread_count(tmp_path, name):
    # a worker holds BLAS at one thread; the serial run uses all of them.  A BLAS dot splits its sum by thread, so an
    # experiment whose reductions went through BLAS wrote different last digits on a worker (fig4 did)
    from threadpoolctl import threadpool_info, threadpool_limits

    if max((i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"), default=1) < 2:
        pytest.skip("BLAS runs on one thread here: nothing to compare")
    mod = experiments.get(name)
    mod.run(tmp_path / "many", quick=True)
    with threadpool_limits(limits=1, user_api="blas"):
        mod.run(tmp_path / "one", quick=True)
    many, one = _data_files(tmp_path / "many"), _data_files(tmp_path / "one")
    assert many and many == one


@pytest.mark.same_without_tools
def test_job_options_on_the_command_line(tmp_path, capsys):
    out = str(tmp_path)
    assert main(["experiment", "fig3", "--quick", "--out", out, "--workers", "2"]) == 1
    err = capsys.readouterr().err
    assert "fig3 does not split into independent jobs" in err and "fig5" in err and len(err.splitlines()) == 1
    assert main(["experiment", "fig5", "--quick", "--out", out, "--workers", "0"]) == 1
    assert "--workers: must be a positive integer" in capsys.readouterr().err
    assert main(["reproduce", "--quick", "--out", out, "--workers", "2", "--scheduler", "tcp://x:1"]) == 1
    assert "exclude each other" in capsys.readouterr().err
    assert main(["experiment", "fig5", "--out", out, "--quick", "--face-sizes", "16", "--centre-only-sizes", "32",
                 "--exponents", "4", "--workers", "2"]) == 0
    assert (tmp_path / "fig5" / "fig5_errors.csv").exists()
    with pytest.raises(SystemExit, match=r"^0$"):
        main(["experiment", "fig5", "--help"])
    assert "independent jobs" in capsys.readouterr().out


_RNG = np.random.default_rng(5)
_X, _Y = _RNG.standard_normal(2_000_000), _RNG.standard_normal(2_000_000)


def _dot_and_blas_threads(_=None):
    import time

    from threadpoolctl import threadpool_info

    time.sleep(0.1)  # overlap with the other thread's job
    return float(_X @ _Y), [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_jobs_run_with_one_blas_thread_also_in_threads():
    # multi-threaded BLAS sums in an order that depends on its thread count (a long dot product differs in its
    # last bits between 1 and 2 threads): every job holds BLAS at one thread, also when jobs overlap in threads
    # of one process, and the caller's thread count comes back afterwards
    from concurrent.futures import ThreadPoolExecutor

    from threadpoolctl import threadpool_limits

    from ibl_ref.executors import map_jobs

    with threadpool_limits(limits=1, user_api="blas"):
        one = float(_X @ _Y)
    before = _dot_and_blas_threads()[1]
    for kw in (dict(), dict(executor=ThreadPoolExecutor(2)), dict(workers=2)):
        for dot, threads in map_jobs(_dot_and_blas_threads, range(4), **kw):
            assert dot == one and set(threads) <= {1}, kw
        assert _dot_and_blas_threads()[1] == before


def _slow_square(x):
    import time

    time.sleep(0.05 * x)
    return x * x


def test_costly_jobs_start_first_and_results_keep_their_order():
    from concurrent.futures import ThreadPoolExecutor

    from ibl_ref.errors import IBLError
    from ibl_ref.executors import map_jobs

    started = []

    class Recording(ThreadPoolExecutor):
        def submit(self, fn, *args, **kw):
            started.append(args[1])  # map_jobs submits _job(fn, item)
            return super().submit(fn, *args, **kw)

    items = [1, 4, 2, 3]
    with Recording(2) as ex:
        assert map_jobs(_slow_square, items, executor=ex, cost=items) == [1, 16, 4, 9]
    assert started == [4, 3, 2, 1]
    with pytest.raises(IBLError, match="cost has 2 entries for 4 jobs"):
        map_jobs(_slow_square, items, cost=[1, 2])
