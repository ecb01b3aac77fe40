"""``kill PID`` (SIGTERM) of a command that runs jobs on worker processes (ibl_ref.cli.interrupts).

Before, Python died at once on SIGTERM and the pool's worker processes (forkserver children of
:func:`ibl_ref.executors.map_jobs`) went on computing, orphaned, for as long as their jobs lasted; now the command
stops them, prints one line, exits 143 and leaves no process of its session behind (checked on the process group,
which the workers share).  Linux only (/proc).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")


def _group(pgid: int) -> list[int]:
    out = []
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid:  # the fifth field of stat: the process group
            out.append(int(d))
    return out


def test_kill_stops_the_command_and_its_pool_workers(tmp_path):
    # two quick occlusion-zoo cases (two environments) on 2 workers: each job takes seconds, so the signal arrives
    # while the workers compute
    env = dict(os.environ, PYTHONPATH=str(ROOT), IBL_REF_PROGRESS="0", IBL_REF_KERNEL="numpy")
    code = "import sys, ibl_ref.cli as c; sys.exit(c.main())"
    argv = ["experiment", "occlusion-zoo", "--quick", "--envs", "sky_sun,uniform", "--workers", "2",
            "--out", str(tmp_path / "out")]
    p = subprocess.Popen([sys.executable, "-c", code, *argv], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        t0 = time.monotonic()
        while len(_group(p.pid)) < 4 and p.poll() is None and time.monotonic() - t0 < 300:
            time.sleep(0.1)  # main, forkserver, resource tracker and at least one worker
        assert len(_group(p.pid)) >= 4, "the pool's workers never started"
        time.sleep(0.5)
        p.send_signal(signal.SIGTERM)  # `kill PID`: the command alone, not its group
        p.wait(timeout=120)
        t0 = time.monotonic()
        while _group(p.pid) and time.monotonic() - t0 < 30:
            time.sleep(0.2)
        left = _group(p.pid)
    finally:  # whatever happened, nothing of the command's group outlives the test
        for pid in _group(p.pid):
            os.kill(pid, signal.SIGKILL)
    err = p.stderr.read()
    assert not left, "processes of the command's group still run after it ended"
    assert p.returncode == 143, (p.returncode, err)
    assert err.strip().splitlines()[-1] == "ibl-ref experiment: terminated" and "Traceback" not in err, err
    assert not (tmp_path / "out" / "occlusion-zoo" / "occlusion_zoo.csv").exists()  # no partial output set
