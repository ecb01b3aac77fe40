"""ibl_ref.executors: map_jobs keeps input order and gives the serial result on processes, threads and Dask;
a dying worker is a one-line IBLError."""

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from ibl_ref.errors import IBLError
from ibl_ref.executors import map_jobs, resolve_executor


def _job(seed):
    # deterministic numeric work whose result depends on the item only
    return np.random.default_rng(seed).standard_normal(1000).cumsum()


def _die(x):
    if x == 1:
        os._exit(3)  # simulate a worker killed by the OS
    return x


def test_serial_processes_threads_identical():
    items = [3, 1, 4, 1, 5]
    ref = [_job(i) for i in items]  # plain loop: the independent route
    for kw in (dict(), dict(workers=2), dict(executor=ThreadPoolExecutor(2))):
        out = map_jobs(_job, items, **kw)
        assert len(out) == len(ref)
        for a, b in zip(out, ref):
            assert np.array_equal(a, b)


def test_dead_worker_is_one_line_error():
    with pytest.raises(IBLError, match="died before finishing"):
        map_jobs(_die, [0, 1, 2], workers=2)


@pytest.mark.parametrize("bad", [0, -1, 1.5, True])
def test_bad_workers(bad):
    with pytest.raises(IBLError, match="workers"):
        map_jobs(_job, [1, 2], workers=bad)


def test_bad_executor():
    with pytest.raises(IBLError, match="executor must be"):
        resolve_executor(42)


def test_dask_local_cluster_identical():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl:
        with distributed.Client(cl) as client:
            out = map_jobs(_job, [7, 8, 9], executor=client)
    for a, i in zip(out, [7, 8, 9]):
        assert np.array_equal(a, _job(i))
