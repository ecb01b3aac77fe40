"""Atomic output, CSV/JSON with units, error types and the CLI shell."""

import json
import os
import stat
import subprocess
import sys

import numpy as np
import pytest

from ibl_ref import atomic
from ibl_ref.cli import build_parser, main
from ibl_ref.environment.radiance_policy import check_radiance
from ibl_ref.errors import RadianceError


def test_atomic_write_replaces_only_on_success(tmp_path):
    p = tmp_path / "data.json"
    atomic.write_json(p, {"a": 1})
    with pytest.raises(RuntimeError, match="^boom$"):
        with atomic.atomic_write(p) as fh:
            fh.write("partial")
            raise RuntimeError("boom")
    assert json.loads(p.read_text()) == {"a": 1}  # old content intact
    assert sorted(os.listdir(tmp_path)) == ["data.json"]  # no temporary file left behind


def test_json_rejects_nan_and_keeps_old_file(tmp_path):
    p = tmp_path / "x.json"
    atomic.write_json(p, {"v": 2.0})
    with pytest.raises(ValueError, match=r"cannot write NaN or Inf"):
        atomic.write_json(p, {"v": float("nan")})
    assert json.loads(p.read_text()) == {"v": 2.0}
    assert sorted(os.listdir(tmp_path)) == ["x.json"]


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write into read-only folders")
def test_unwritable_folder_is_a_clear_error(tmp_path):
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(stat.S_IREAD | stat.S_IEXEC)
    with pytest.raises(atomic.OutputError, match="not writable"):
        atomic.write_json(d / "x.json", {})


def test_output_path_that_is_a_folder_is_a_clear_error(tmp_path):
    with pytest.raises(atomic.OutputError, match="is a folder"):
        atomic.write_json(tmp_path, {})


def test_output_under_a_file_is_a_clear_error(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(atomic.OutputError, match="cannot create output folder"):
        atomic.write_json(f / "sub" / "x.json", {})


def test_csv_round_trip_with_comment(tmp_path):
    rows = [{"s_phong": 1, "rel_err_max": 0.5}, {"s_phong": 10, "rel_err_max": np.float64(0.25)}]
    p = atomic.write_csv(tmp_path / "t.csv", rows, comment="units: relative error is dimensionless")
    assert p.read_text().startswith("# units")
    back = atomic.read_csv(p)
    assert [float(r["rel_err_max"]) for r in back] == [0.5, 0.25]


def test_check_radiance_messages():
    with pytest.raises(RadianceError, match=r"env: 1 non-finite value\(s\) \(first: NaN at index \(1,\)\)"):
        check_radiance(np.array([1.0, np.nan]), "env")
    with pytest.raises(RadianceError, match="Inf"):
        check_radiance(np.array([np.inf]), "env")
    with pytest.raises(RadianceError, match="negative"):
        check_radiance(np.array([[0.0, -1e-30]]), "env")
    assert check_radiance(np.array([0.0, 1e30])).shape == (2,)


def test_every_cli_command_has_help(capsys):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    assert {"experiment", "reproduce"} <= set(sub.choices)
    for name, p in sub.choices.items():
        # a description of its own (not just the usage line), and every option explained in the help
        assert p.description and len(p.description) > 40, name
        with pytest.raises(SystemExit, match=r"^0$") as ex:
            main([name, "--help"])
        assert ex.value.code == 0
        text = capsys.readouterr().out
        assert " ".join(p.description.split())[:60] in " ".join(text.split()), name
        for action in p._actions:
            if action.option_strings and action.help and action.help != "==SUPPRESS==":
                assert max(action.option_strings, key=len) in text, (name, action.option_strings)


def test_cli_unknown_experiment_is_a_clean_error(capsys):
    assert main(["experiment", "no-such-thing", "--out", "unused"]) == 1
    assert "unknown experiment" in capsys.readouterr().err


def test_python_dash_m_entry_point():
    out = subprocess.run([sys.executable, "-m", "ibl_ref", "--help"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "ibl-ref" in out.stdout


def test_atomic_files_get_normal_permissions(tmp_path):
    p = atomic.write_json(tmp_path / "m.json", {})
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~umask
