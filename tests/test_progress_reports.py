"""Progress of long work goes through ibl_ref.progress everywhere: in a log (a captured, non-terminal stream) it is
separate status lines — no carriage-return bars, nothing glued together, nested loops within one rate limit — and
jobs run on workers are silent."""

import io
import re
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from ibl_ref import progress
from ibl_ref.cli import main
from ibl_ref.executors import map_jobs

#: a well-formed line of ibl_ref.progress: a start line, a counter line, a step's end line, or a plain message
LINE = re.compile(r"[^\r\n]+ …"                                              # start of a loop or step
                  r"|[^\r\n]+: \d+(/\d+)? [^\r\n]+?(\(\d+ %\))?, [\d.]+ s( › .+)?"  # counter (nested: ›)
                  r"|[^\r\n]+: done in ([\d.]+ s|\d+ min \d+ s)"              # end of a step
                  r"|[^\r\n…]+")                                              # a message (say) or a command's note


class _Stream(io.StringIO):
    def __init__(self, tty=False):
        super().__init__()
        self._tty = tty

    def isatty(self):
        return self._tty


@pytest.fixture
def log_mode(monkeypatch):
    """Progress on (the test session silences it), every update reported."""
    monkeypatch.delenv("IBL_REF_PROGRESS", raising=False)
    monkeypatch.setenv("IBL_REF_PROGRESS_INTERVAL", "0")


def _lines(text):
    assert "\r" not in text  # no bar in a log
    lines = text.splitlines()
    for ln in lines:
        assert LINE.fullmatch(ln), repr(ln)
        assert ln.count("…") <= 1 and ln.count("done in") <= 1, repr(ln)  # nothing glued
    return lines


def test_nested_loops_in_a_log_share_one_line_and_one_start(log_mode):
    s = _Stream()
    for _ in progress.track(range(2), "cases", unit="case", stream=s):
        for _ in progress.track(range(3), "directions", unit="dir", stream=s):
            pass
    lines = _lines(s.getvalue())
    assert lines[0] == "cases (2 cases) …"  # the inner loop prints no start line of its own
    assert not any(ln.startswith("directions") for ln in lines)
    nested = [ln for ln in lines if " › " in ln]
    assert nested and all(re.match(r"cases: \d/2 cases \(\d+ %\), [\d.]+ s › directions: \d/3 dir", ln) for ln in nested)
    assert lines[-1].startswith("cases: 2/2 cases (100 %)")


def test_rate_limit_holds_for_all_loops_together(monkeypatch):
    monkeypatch.delenv("IBL_REF_PROGRESS", raising=False)
    monkeypatch.setenv("IBL_REF_PROGRESS_INTERVAL", "3600")
    s = _Stream()
    for _ in progress.track(range(5), "outer", stream=s):
        for _ in progress.track(range(50), "inner", stream=s):
            pass
    assert _lines(s.getvalue()) == ["outer (5 it) …"]  # nothing more within the interval


def test_disabled_track_is_the_iterable_itself(log_mode):
    r = range(3)
    assert progress.track(r, "x", enabled=False) is r
    s = _Stream()
    with progress.step("quiet step", stream=s, enabled=False) as st:
        pass
    assert s.getvalue() == "" and st.elapsed >= 0


def test_step_left_by_an_error_prints_no_done_line(log_mode):
    s = _Stream()
    with pytest.raises(ValueError, match="^bad$"):
        with progress.step("reading x", stream=s):
            raise ValueError("bad")
    assert s.getvalue() == "reading x …\n"


def test_quiet_silences_only_its_own_thread(log_mode):
    s_main, s_thread = _Stream(), _Stream()

    def job():
        with progress.quiet():
            list(progress.track(range(2), "in a job", stream=s_thread))

    t = threading.Thread(target=job)
    with progress.quiet():
        t.start()
        t.join()
    list(progress.track(range(2), "main", stream=s_main))
    assert s_thread.getvalue() == ""
    assert s_main.getvalue().startswith("main (2 it) …")


def _job_with_progress(x):
    return sum(progress.track(range(x), "inner job work"))


def test_map_jobs_reports_jobs_and_silences_jobs_run_elsewhere(log_mode, capsys):
    assert map_jobs(_job_with_progress, [2, 3], desc="sweep", unit="case") == [1, 3]  # serial: nested reports
    err = capsys.readouterr().err
    lines = _lines(err)
    assert lines[0] == "sweep (2 cases) …" and any("› inner job work" in ln for ln in lines)
    with ThreadPoolExecutor(2) as ex:  # on an executor: the caller reports, the jobs are quiet
        assert map_jobs(_job_with_progress, [2, 3], executor=ex, desc="sweep", unit="case") == [1, 3]
    lines = _lines(capsys.readouterr().err)
    assert lines[0] == "sweep (2 cases) …" and not any("inner job work" in ln for ln in lines)


# ---- the library's long steps report through ibl_ref.progress -------------------------------------------------

def _env(n=8):
    from ibl_ref.synthetic.synthetic_envs import make_env

    return make_env("sky_sun", n=n)


def test_pem_and_chain_builds_report_lines(log_mode, capsys):
    from ibl_ref.knuth2014.lobe_chain import build_lobe_chain_pems
    from ibl_ref.knuth2014.pem import build_pems

    pems = build_pems(_env(), n_lights=6, chunk=2, progress=True)
    build_lobe_chain_pems(_env(), pems.lights, progress=True)
    lines = _lines(capsys.readouterr().err)
    assert "PEM pyramids (3 chunks) …" in lines and "exact-lobe chain (3 levels) …" in lines
    assert any(ln.startswith("PEM pyramids: 1/3 chunks (33 %)") for ln in lines)


def test_renderer_visibility_and_km00_report_lines(log_mode, capsys):
    from ibl_ref.lobes.km00_reference import render_reference
    from ibl_ref.lobes.brdfs import get_brdf
    from ibl_ref.lobes.profile_convolution import convolve_profiles
    from ibl_ref.rendering.raycast import any_hit, parallel_visibility
    from ibl_ref.rendering.render import light_visibilities
    from ibl_ref.knuth2014.median_cut import median_cut
    from ibl_ref.synthetic.synthetic_meshes import make_mesh

    mesh = make_mesh("sphere_on_plane")
    pts = np.array([[0.0, 1.5, 0.0], [2.0, 0.01, 0.0]])
    dirs = np.array([[0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 1.0]])
    parallel_visibility(mesh, pts, dirs, progress=True)
    any_hit(mesh, pts, dirs[:2], progress=True)
    light_visibilities(mesh, pts, None, median_cut(_env(), 6), method="vsm", vsm_resolution=16, progress=True)
    g = np.linspace(0.0, np.pi, 32)
    convolve_profiles(_env(), g, np.cos(np.minimum(g, np.pi / 2)) ** 4, progress=True)
    n = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    render_reference(_env(), n, n, get_brdf("ward", alpha=0.2, ks=0.8), progress=True)
    lines = _lines(capsys.readouterr().err)
    for start in ("exact visibility (3 dirs) …", "shadow maps (6 lights) …", "exact Ward reference (2 pixels) …"):
        assert start in lines, start
    assert any(ln.startswith("rays (") for ln in lines)
    assert any(re.fullmatch(r"prefilter of 1 profile\(s\), supersampling [\d, ]+ \(\d+ tiles?\) …", ln) for ln in lines)


# ---- the command line: progress on by default, lines in a log --------------------------------------------------

def test_cli_commands_report_progress_lines(log_mode, tmp_path, capsys):
    from ibl_ref.environment.exr_io import write_envmap

    env = tmp_path / "env.exr"
    write_envmap(env, _env(16), layout="cube")
    assert main(["render", "--size", "16", "--lights", "6", "--vsm-res", "16", "--env", str(env), "--env-size", "16",
                 "--prefilter", "exact-lobe", "--out", str(tmp_path / "r.exr")]) == 0
    lines = _lines(capsys.readouterr().err)
    for start in (f"reading {env} (to 16² faces) …", "shadow maps (6 lights) …"):
        assert start in lines, (start, lines)
    assert any(re.fullmatch(r"exact-lobe chain \(\d+ levels?\) …", ln) for ln in lines)
    assert "PEM pyramids (1 chunk) …" not in lines  # the chain's PEMs only: no filter pyramid built on the side
    assert main(["render", "--size", "16", "--lights", "6", "--vsm-res", "16", "--env", str(env), "--env-size", "16",
                 "--out", str(tmp_path / "r2.exr")]) == 0
    assert "PEM pyramids (1 chunk) …" in _lines(capsys.readouterr().err)  # the paper's pyramid (default)
    assert main(["pem", str(env), "--lights", "6", "--out", str(tmp_path / "pems")]) == 0
    lines = _lines(capsys.readouterr().err)
    assert "median cut of 16² faces into 6 regions …" in lines and "writing PEMs (6 files) …" in lines
    assert main(["convolve", str(env), str(tmp_path / "c.exr"), "-s", "4", "--workers", "1"]) == 0
    lines = _lines(capsys.readouterr().err)
    assert any(re.fullmatch(r"convolving 16² faces with 1 exponent\(s\), method auto: done in [\d.]+ s", ln)
               for ln in lines)
    assert main(["pyramid", str(env), str(tmp_path / "p.exr")]) == 0
    lines = _lines(capsys.readouterr().err)
    assert any(ln.startswith("sqrtcos pyramid of 16² faces: done in") for ln in lines)
    assert main(["mediancut", str(env), "--lights", "6", "--out", str(tmp_path / "m.json")]) == 0
    _lines(capsys.readouterr().err)
    assert main(["convert", str(env), str(tmp_path / "ll.exr"), "--layout", "latlong"]) == 0
    lines = _lines(capsys.readouterr().err)
    assert f"reading {env} …" in lines and "converting to latlong …" in lines
    assert main(["info", str(env)]) == 0
    out = capsys.readouterr()
    assert f"reading {env} …" in _lines(out.err) and "reading" not in out.out  # the report stays on stdout


def test_render_no_progress_is_silent(log_mode, tmp_path, capsys):
    assert main(["render", "--size", "12", "--lights", "6", "--vsm-res", "16", "--no-progress",
                 "--out", str(tmp_path / "r.exr")]) == 0
    assert capsys.readouterr().err == ""


def test_a_long_step_without_a_counter_reports_a_heartbeat(monkeypatch):
    # one long job with nothing to count (e.g. a 1024² convolution job): at least one "running" line per interval
    # in between the start and the end line, each on its own line; none when the interval is below the minimum
    import time

    monkeypatch.delenv("IBL_REF_PROGRESS", raising=False)
    monkeypatch.setenv("IBL_REF_PROGRESS_INTERVAL", "1")
    s = _Stream()
    with progress.step("long job", stream=s):
        time.sleep(3.5)  # ≥ 2 full intervals: at least one beat even on a loaded machine
    lines = _lines(s.getvalue())
    assert lines[0] == "long job …" and lines[-1].startswith("long job: done in")
    beats = lines[1:-1]
    assert beats and all(re.fullmatch(r"long job: running, [\d.]+ s", b) for b in beats), lines
    # after the step ends, its heartbeat thread is gone (nothing printed later)
    n = len(s.getvalue())
    time.sleep(1.5)
    assert len(s.getvalue()) == n
    monkeypatch.setenv("IBL_REF_PROGRESS_INTERVAL", "0")
    s = _Stream()
    with progress.step("short interval", stream=s):
        time.sleep(0.3)
    assert not any("running" in ln for ln in _lines(s.getvalue()))
