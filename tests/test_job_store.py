"""Interrupted experiments lose no finished job (ibl_ref.executors.keeping_jobs, run by run_experiment): a rerun of
the same experiment runs only the jobs that had not finished and writes the same bytes as a run without
interruption; damaged or foreign store files are run again with a warning, a store of other code is never used,
a store that cannot be written is given up with one warning, the store is gone after a run that succeeds, and
``--fresh`` runs everything again.  A tiny fake experiment (five jobs of a few microseconds) and one tiny fig5 run:
a few seconds in all."""

import os
import shutil
import signal
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from ibl_ref import executors, experiments
from ibl_ref.cli import main
from ibl_ref.errors import IBLWarning
from ibl_ref.executors import JobStore, code_fingerprint, keeping_jobs, map_jobs

N_JOBS = 5
NAME = "fake-jobs"


# ------------------------------------------------------------------------------------------------------------------
# the fake experiment: N_JOBS jobs, each counted in a folder (any process) and able to stop the run once
# ------------------------------------------------------------------------------------------------------------------
def _fake_job(item):
    """Job ``i`` of the fake experiment: a deterministic array; every call leaves a file in ``calls``; a file
    ``stop-i`` in ``triggers`` makes it stop the run once (``raise``: an error, ``ctrl-c``: KeyboardInterrupt,
    ``kill``: SIGKILL of its own process, the caller when it runs serially)."""
    i, calls, triggers = item
    Path(calls, f"{i}-{os.getpid()}-{os.urandom(4).hex()}").touch()
    trigger = Path(triggers, f"stop-{i}")
    if trigger.exists():
        how = trigger.read_text()
        trigger.unlink()
        if how == "kill":
            os.kill(os.getpid(), signal.SIGKILL)
        raise KeyboardInterrupt if how == "ctrl-c" else RuntimeError(f"job {i} stopped the run")
    return np.random.default_rng(i).standard_normal(1000).cumsum()


def _inner_job(x):
    return x + 1


def _job_mapping_jobs_of_its_own(item):
    """A job that maps jobs itself (as a case that renders a converged reference does)."""
    return sum(map_jobs(_inner_job, range(3))) + _fake_job(item)


def fake_experiment(tmp_path, job=_fake_job):
    """A module that run_experiment runs: ``run`` maps ``job`` over N_JOBS items and writes their results."""
    calls, triggers = tmp_path / "calls", tmp_path / "triggers"
    calls.mkdir(exist_ok=True)
    triggers.mkdir(exist_ok=True)
    mod = types.ModuleType("fake_jobs_experiment")

    def run(out_dir, quick=False, executor=None, workers=1, **params):
        items = [(i, str(calls), str(triggers)) for i in range(N_JOBS)]
        res = map_jobs(job, items, executor=executor, workers=workers)
        np.save(Path(out_dir) / "fake_results.npy", np.stack(res))
        return {}

    mod.__dict__.update(NAME=NAME, DESCRIPTION="five jobs", PAPER="-", PARAMS=(), OUTPUTS=("fake_results.npy",),
                        RUNTIME={"quick": "0 s", "full": "0 s"}, run=run, plot=lambda out_dir: [])
    return mod


def _calls(tmp_path) -> list:
    """The jobs run since the last call (sorted item numbers); forgets them."""
    done = sorted(int(p.name.split("-")[0]) for p in (tmp_path / "calls").iterdir())
    for p in (tmp_path / "calls").iterdir():
        p.unlink()
    return done


def _stop_at(tmp_path, i, how="raise"):
    (tmp_path / "triggers" / f"stop-{i}").write_text(how)


def _store(out) -> Path:
    return Path(out) / f".jobs-{NAME}"


@pytest.fixture
def reference(tmp_path_factory):
    """The bytes of the fake experiment's output, run without interruption."""
    tmp = tmp_path_factory.mktemp("reference")
    experiments.run_experiment(fake_experiment(tmp), tmp / "out", quick=True)
    assert _calls(tmp) == list(range(N_JOBS)) and not _store(tmp / "out").exists()
    return (tmp / "out" / "fake_results.npy").read_bytes()


def _interrupted(tmp_path, mod, k, **jobs):
    """A run that job ``k`` stops (an error); returns its output folder."""
    out = tmp_path / "out"
    _stop_at(tmp_path, k)
    with pytest.raises(RuntimeError, match=f"job {k} stopped"):
        experiments.run_experiment(mod, out, quick=True, **jobs)
    assert not (out / "fake_results.npy").exists()
    return out


# ------------------------------------------------------------------------------------------------------------------
# resuming
# ------------------------------------------------------------------------------------------------------------------
def test_rerun_runs_only_the_jobs_that_had_not_finished_and_writes_the_same_bytes(tmp_path, reference, capsys,
                                                                                   monkeypatch):
    mod = fake_experiment(tmp_path)
    out = _interrupted(tmp_path, mod, 3)  # the run created out: it stays, for the 3 finished jobs
    assert _calls(tmp_path) == [0, 1, 2, 3]
    assert len(list(_store(out).glob("*.job"))) == 3
    monkeypatch.setenv("IBL_REF_PROGRESS", "lines")
    capsys.readouterr()
    experiments.run_experiment(mod, out, quick=True)
    assert _calls(tmp_path) == [3, 4]
    err = capsys.readouterr().err
    assert f"{NAME}: 3 of 5 jobs kept from an interrupted run in {_store(out)}" in err.splitlines()
    assert (out / "fake_results.npy").read_bytes() == reference
    assert not _store(out).exists()  # removed once the outputs are in place
    assert sorted(p.name for p in out.iterdir()) == sorted(["fake_results.npy", f"{NAME}_outputs.json"])


def test_jobs_on_worker_processes_are_kept_as_they_arrive(tmp_path, reference):
    mod = fake_experiment(tmp_path)
    out = _interrupted(tmp_path, mod, 1, workers=2)
    ran = _calls(tmp_path)
    kept = len(list(_store(out).glob("*.job")))
    assert 1 in ran and kept == len(ran) - 1  # every job that finished before the run stopped was kept
    experiments.run_experiment(mod, out, quick=True, workers=2)
    again = _calls(tmp_path)
    assert 1 in again and len(again) == N_JOBS - kept and set(again) | set(ran) == set(range(N_JOBS))
    assert (out / "fake_results.npy").read_bytes() == reference and not _store(out).exists()


def test_jobs_finished_before_the_process_was_killed_are_kept(tmp_path, reference):
    # the calling process itself dies (SIGKILL: no clean-up at all) while running job 2 serially
    mod = fake_experiment(tmp_path)
    _stop_at(tmp_path, 2, "kill")
    out = tmp_path / "out"
    script = ("import sys; from pathlib import Path; sys.path.insert(0, sys.argv[1]); import test_job_store as t; "
              "from ibl_ref import experiments; "
              "experiments.run_experiment(t.fake_experiment(Path(sys.argv[2])), Path(sys.argv[3]), quick=True)")
    proc = subprocess.run([sys.executable, "-c", script, str(Path(__file__).parent), str(tmp_path), str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert _calls(tmp_path) == [0, 1, 2] and len(list(_store(out).glob("*.job"))) == 2
    experiments.run_experiment(mod, out, quick=True)
    assert _calls(tmp_path) == [2, 3, 4]
    assert (out / "fake_results.npy").read_bytes() == reference


def test_a_real_experiment_resumes_bit_for_bit(tmp_path, monkeypatch):
    # fig5 at a tiny size: 2 configurations; the second one is interrupted once
    mod = experiments.get("fig5")
    tiny = dict(face_sizes=(8,), centre_only_sizes=(16,), exponents=3)
    mod.run(tmp_path / "plain", quick=True, **tiny)
    real, seen = mod.compute_rows, []

    def compute_rows(*args, **kw):
        seen.append(args[0])
        if len(seen) == 4:  # the face size 8 has 3 positions: the 4th configuration is face size 16
            raise KeyboardInterrupt
        return real(*args, **kw)

    monkeypatch.setattr(mod, "compute_rows", compute_rows)
    out = tmp_path / "resumed"
    with pytest.raises(KeyboardInterrupt):
        experiments.run_experiment(mod, out, quick=True, overrides=tiny)
    assert len(list(experiments.job_store_folder(mod, out).glob("*.job"))) == 3
    seen.clear()
    experiments.run_experiment(mod, out, quick=True, overrides=tiny)
    assert seen == [16]
    assert (out / "fig5_errors.csv").read_bytes() == (tmp_path / "plain" / "fig5_errors.csv").read_bytes()
    assert not experiments.job_store_folder(mod, out).exists()


# ------------------------------------------------------------------------------------------------------------------
# reliability
# ------------------------------------------------------------------------------------------------------------------
def test_damaged_truncated_and_foreign_files_are_run_again_with_a_warning(tmp_path, reference):
    mod = fake_experiment(tmp_path)
    out = _interrupted(tmp_path, mod, 4)
    _calls(tmp_path)
    store = JobStore(_store(out), NAME)
    keys = [store.key(_fake_job, (i, str(tmp_path / "calls"), str(tmp_path / "triggers"))) for i in range(4)]
    assert all(store.path(k).exists() for k in keys)
    data = store.path(keys[0]).read_bytes()
    store.path(keys[0]).write_bytes(data[:-100])  # truncated
    flipped = bytearray(store.path(keys[1]).read_bytes())
    flipped[-50] ^= 1  # one bit of the result
    store.path(keys[1]).write_bytes(bytes(flipped))
    store.path(keys[2]).write_bytes(b"not a job file\n")  # foreign
    with pytest.warns(IBLWarning) as got:
        experiments.run_experiment(mod, out, quick=True)
    texts = [str(w.message) for w in got]
    assert len(texts) == 3 and all(t.startswith(f"{NAME}: ignoring ") and "running its job again" in t for t in texts)
    assert "truncated" in texts[0] and "checksum" in texts[1] and "not a job file" in texts[2]
    assert _calls(tmp_path) == [0, 1, 2, 4]
    assert (out / "fake_results.npy").read_bytes() == reference


def test_a_file_of_another_job_is_not_taken(tmp_path, reference):
    mod = fake_experiment(tmp_path)
    out = _interrupted(tmp_path, mod, 2)
    _calls(tmp_path)
    files = sorted(_store(out).glob("*.job"))
    other = _store(out) / ("0" * 64 + ".job")
    shutil.copy(files[0], other)
    store = JobStore(_store(out), NAME)
    with pytest.warns(IBLWarning, match="written for another job"):
        assert store.load("0" * 64) == (False, None)
    other.unlink()
    experiments.run_experiment(mod, out, quick=True)
    assert _calls(tmp_path) == [2, 3, 4] and (out / "fake_results.npy").read_bytes() == reference


def test_a_store_of_other_code_is_never_used(tmp_path, reference, monkeypatch):
    mod = fake_experiment(tmp_path)
    out = _interrupted(tmp_path, mod, 3)
    _calls(tmp_path)
    monkeypatch.setattr(executors, "code_fingerprint", lambda: "another version of the code")
    experiments.run_experiment(mod, out, quick=True)
    assert _calls(tmp_path) == list(range(N_JOBS))
    assert (out / "fake_results.npy").read_bytes() == reference and not _store(out).exists()


def test_the_fingerprint_follows_the_package_files(tmp_path):
    pkg = Path(executors.__file__).parent
    copy = tmp_path / "ibl_ref"
    shutil.copytree(pkg, copy, ignore=shutil.ignore_patterns("__pycache__"))
    before = code_fingerprint(copy)
    assert before == code_fingerprint(pkg) and len(before) == 64
    (copy / "__pycache__").mkdir()
    (copy / "__pycache__" / "x.pyc").write_bytes(b"compiled")
    (copy / ".executors.py.ibl-tmp-1-00").write_text("a temporary file")
    assert code_fingerprint.__wrapped__(copy) == before  # caches and hidden files do not count
    with open(copy / "executors.py", "a") as fh:
        fh.write("\n")
    assert code_fingerprint.__wrapped__(copy) != before
    data = sorted((copy / "data").glob("*.json"))[0]
    (copy / "executors.py").write_bytes((pkg / "executors.py").read_bytes())
    data.write_text(data.read_text() + " ")
    assert code_fingerprint.__wrapped__(copy) != before  # package data count too


def test_a_store_that_cannot_be_written_is_given_up_with_one_warning(tmp_path, reference, monkeypatch):
    from ibl_ref import atomic

    mod = fake_experiment(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    _store(out).write_text("a file in the way")  # the store's folder cannot be made
    with pytest.warns(IBLWarning) as got:
        experiments.run_experiment(mod, out, quick=True)
    assert len(got) == 1 and "cannot keep finished jobs" in str(got[0].message)
    assert "going on without keeping them" in str(got[0].message)
    assert (out / "fake_results.npy").read_bytes() == reference and _store(out).read_text() == "a file in the way"
    _store(out).unlink()

    write = atomic.atomic_write

    def full_disk(path, mode="w", **kw):  # the store's files only: the outputs still go to disk
        if f".jobs-{NAME}" in str(path):
            raise atomic.OutputError(f"{path}: cannot write: No space left on device")
        return write(path, mode, **kw)

    monkeypatch.setattr(atomic, "atomic_write", full_disk)
    _calls(tmp_path)
    with pytest.warns(IBLWarning) as got:
        experiments.run_experiment(fake_experiment(tmp_path), tmp_path / "out2", quick=True)
    assert len(got) == 1 and "No space left on device" in str(got[0].message)
    assert _calls(tmp_path) == list(range(N_JOBS))
    assert (tmp_path / "out2" / "fake_results.npy").read_bytes() == reference


def test_a_run_that_fails_before_any_job_finished_leaves_no_folder(tmp_path):
    mod = fake_experiment(tmp_path)
    _stop_at(tmp_path, 0)
    with pytest.raises(RuntimeError):
        experiments.run_experiment(mod, tmp_path / "out", quick=True)
    assert not (tmp_path / "out").exists()
    out = tmp_path / "existing"
    out.mkdir()
    _stop_at(tmp_path, 0)
    with pytest.raises(RuntimeError):
        experiments.run_experiment(mod, out, quick=True)
    assert list(out.iterdir()) == []


# ------------------------------------------------------------------------------------------------------------------
# scope: only the map_jobs calls of the experiment itself, only inside run_experiment
# ------------------------------------------------------------------------------------------------------------------
def test_map_jobs_outside_an_experiment_keeps_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "calls").mkdir()
    (tmp_path / "triggers").mkdir()
    items = [(i, str(tmp_path / "calls"), str(tmp_path / "triggers")) for i in range(3)]
    assert executors._STORE.get() is None
    res = map_jobs(_fake_job, items)
    assert len(res) == 3 and sorted(p.name for p in tmp_path.iterdir()) == ["calls", "triggers"]


def test_jobs_mapped_inside_a_job_are_not_kept(tmp_path, reference):
    mod = fake_experiment(tmp_path, _job_mapping_jobs_of_its_own)
    out = _interrupted(tmp_path, mod, 2)
    assert len(list(_store(out).glob("*.job"))) == 2  # the two outer jobs, none of their inner ones


def test_jobs_that_do_not_pickle_run_with_one_warning(tmp_path):
    with keeping_jobs(tmp_path / "store", "lambdas") as store:
        with pytest.warns(IBLWarning, match="lambdas: the jobs of .*<lambda> are not kept"):
            assert map_jobs(lambda x: 2 * x, [1, 2, 3]) == [2, 4, 6]
        assert store.files() == []
    assert not (tmp_path / "store").exists()


# ------------------------------------------------------------------------------------------------------------------
# the command line
# ------------------------------------------------------------------------------------------------------------------
def test_command_line_resumes_after_ctrl_c_and_fresh_runs_everything(tmp_path, reference, capsys, monkeypatch):
    mod = fake_experiment(tmp_path)
    every = experiments.available()
    monkeypatch.setattr(experiments, "available", lambda: {**every, NAME: mod})
    monkeypatch.setenv("IBL_REF_PROGRESS", "lines")
    argv = ["experiment", NAME, "--out", str(tmp_path / "results")]
    out = tmp_path / "results" / NAME
    _stop_at(tmp_path, 3, "ctrl-c")
    assert main(argv) == 130
    assert _calls(tmp_path) == [0, 1, 2, 3] and len(list(_store(out).glob("*.job"))) == 3
    _stop_at(tmp_path, 4, "ctrl-c")
    assert main(argv) == 130  # stopped again: the kept jobs stay kept, the new one joins them
    assert _calls(tmp_path) == [3, 4] and len(list(_store(out).glob("*.job"))) == 4
    capsys.readouterr()
    assert main(argv + ["--fresh"]) == 0
    assert _calls(tmp_path) == list(range(N_JOBS))
    err = capsys.readouterr().err
    assert f"{NAME}: 4 job(s) kept from an interrupted run in {_store(out)} discarded (--fresh)" in err
    assert "jobs kept from an interrupted run in" not in err
    assert (out / "fake_results.npy").read_bytes() == reference and not _store(out).exists()
    with pytest.raises(SystemExit, match=r"^0$"):
        main(["experiment", NAME, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--fresh discard the jobs an interrupted run kept" in text
    assert "Interrupted runs lose no finished job" in text and f".jobs-{NAME}" in text
