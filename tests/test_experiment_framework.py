"""The experiment framework (ibl_ref.experiments), its command line, the figure helper and progress reporting."""

import io
import json
import re
from pathlib import Path

import pytest

from ibl_ref import experiments, figures, progress
from ibl_ref.cli import main
from ibl_ref.errors import IBLError

ROOT = Path(__file__).resolve().parent.parent
EXPS = experiments.available()


def test_param_parsing_follows_the_default_type():
    p = experiments.Param("sizes", (8, 16), (4,), "face sizes")
    assert p.parse("1, 2,3") == (1, 2, 3)
    assert experiments.Param("g", 0.5).parse("0.25") == 0.25
    assert experiments.Param("n", 4).parse("7") == 7
    assert experiments.Param("env", "studio").parse("sky_sun") == "sky_sun"
    with pytest.raises(IBLError, match="--n: expected an integer"):
        experiments.Param("n", 4).parse("seven")
    assert p.value(True) == (4,) and p.value(False) == (8, 16)


def test_unknown_parameter_is_refused():
    with pytest.raises(IBLError, match="unknown parameter 'nope'"):
        experiments.resolve_params(EXPS["fig3"], True, {"nope": 1})


@pytest.mark.parametrize("name", sorted(EXPS))
def test_every_experiment_declares_what_help_shows(name):
    mod = EXPS[name]
    for attr in ("NAME", "DESCRIPTION", "PAPER", "PARAMS", "RUNTIME", "OUTPUTS"):
        assert getattr(mod, attr, None), f"{name}: {attr} missing"
    assert set(mod.RUNTIME) == {"quick", "full"}
    assert "issue" not in mod.DESCRIPTION.lower()
    for p in mod.PARAMS:
        if p.quick is not None:  # the quick value parses back as the default's type
            assert p.parse(experiments._fmt(p.quick)) == (tuple(p.quick) if isinstance(p.quick, list) else p.quick)
    # the compute step takes its parameters by name (what `--PARAM` passes)
    assert mod.run.__code__.co_flags & 0x08, f"{name}.run must accept **params"


@pytest.mark.parametrize("name", sorted(EXPS))
def test_experiment_help_lists_description_paper_params_outputs_and_time(name, capsys):
    mod = EXPS[name]
    with pytest.raises(SystemExit, match=r"^0$") as ex:
        main(["experiment", name, "--help"])
    assert ex.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert " ".join(mod.DESCRIPTION.split()) in text
    assert " ".join(mod.PAPER.split()) in text
    assert f"--quick {mod.RUNTIME['quick']}" in text
    for p in mod.PARAMS:
        assert f"--{p.flag}" in text
    for o in mod.OUTPUTS:
        assert o in text


def test_parameters_reach_the_compute_step(tmp_path, capsys):
    assert main(["experiment", "fig3", "--quick", "--out", str(tmp_path), "--face-size", "8", "--pixels", "6",
                 "--gloss", "1,0"]) == 0
    d = json.loads((tmp_path / "fig3" / "fig3_spheres.json").read_text())
    assert (d["face_size"], d["pixels"], d["gloss"]) == (8, 6, [1.0, 0.0])
    assert len(d["images_linear_rgb"]) == 2 and len(d["images_linear_rgb"][0]) == 6
    assert main(["experiment", "fig3", "--out", str(tmp_path), "--pixels", "six"]) == 1
    assert "--pixels: expected an integer" in capsys.readouterr().err


def test_list_names_every_experiment(capsys):
    assert main(["experiment", "--list"]) == 0
    out = capsys.readouterr().out
    assert [ln.split()[0] for ln in out.splitlines()] == sorted(EXPS)
    assert "issue" not in out


def test_no_library_module_switches_the_matplotlib_backend():
    # a notebook's inline backend must survive every plot call: no matplotlib.use() anywhere in the package
    hits = [str(p.relative_to(ROOT)) for p in (ROOT / "ibl_ref").rglob("*.py")
            if re.search(r"matplotlib\.use\(|pyplot\.switch_backend\(", p.read_text())]
    assert hits == []


def test_plotting_keeps_the_callers_backend(tmp_path):
    import matplotlib

    old = matplotlib.get_backend()
    matplotlib.use("pdf")  # any backend other than Agg: a plot() that forced Agg would change it
    try:
        mod = EXPS["fig3"]
        mod.run(tmp_path, quick=True, face_size=8, pixels=6, gloss=(1.0, 0.0))
        assert [p.name for p in mod.plot(tmp_path)] == ["fig3.png"]
        assert matplotlib.get_backend() == "pdf"
        assert (tmp_path / "fig3.png").read_bytes()[:4] == b"\x89PNG"
    finally:
        matplotlib.use(old)


def test_layout_check_finds_text_outside_cut_cells_and_overlaps():
    plt = figures.pyplot()
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.set_title("fits")
    fig.tight_layout()
    assert figures.layout_problems(fig) == []
    ax.text(1.5, 0.5, "far outside on the right", transform=ax.transAxes)
    assert any("outside the figure" in p for p in figures.layout_problems(fig))
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.axis("off")
    t = ax.table(cellText=[["a label much wider than its cell", "x"]], colWidths=[0.1, 0.1], loc="center")
    t.auto_set_font_size(False)
    t.set_fontsize(8)
    assert any("wider/taller than its cell" in p for p in figures.layout_problems(fig))
    plt.close(fig)
    fig, axes = plt.subplots(2, 1, figsize=(3, 2.2))
    axes[1].set_title("a title that runs into the axis above it\nsecond line\nthird line", fontsize=12)
    axes[0].set_xlabel("x label of the upper axes")
    assert any("overlaps" in p for p in figures.layout_problems(fig))
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(3, 2), layout="constrained")
    ax.plot([0, 1, 2], [0, 1, 2], "o-", label="data")
    ax.legend(loc="center")  # the middle point (1, 1) sits under the legend
    assert any("covers 1 data point" in p for p in figures.layout_problems(fig))
    plt.close(fig)


def test_save_figure_is_atomic_tight_and_closes(tmp_path):
    plt = figures.pyplot()
    fig, ax = plt.subplots()
    ax.plot([0, 1])
    seen = []
    hook = lambda f, p: seen.append(p.name)  # noqa: E731
    figures.add_save_hook(hook)
    try:
        p = figures.save_figure(fig, tmp_path / "a.png", dpi=50)
    finally:
        figures.remove_save_hook(hook)
    assert seen == ["a.png"] and p.read_bytes()[:4] == b"\x89PNG"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.png"]  # no temporary file left
    assert not plt.fignum_exists(fig.number)


class _Stream(io.StringIO):
    def __init__(self, tty):
        super().__init__()
        self._tty = tty

    def isatty(self):
        return self._tty


def test_progress_in_a_log_is_lines_without_carriage_returns(monkeypatch):
    monkeypatch.delenv("IBL_REF_PROGRESS", raising=False)
    monkeypatch.setenv("IBL_REF_PROGRESS_INTERVAL", "0")
    s = _Stream(False)
    assert list(progress.track(range(3), "work", unit="item", stream=s)) == [0, 1, 2]
    with progress.step("block", stream=s):
        pass
    text = s.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert lines[0] == "work (3 items) …"
    assert lines[1].startswith("work: 1/3 items (33 %)") and lines[-3].startswith("work: 3/3 items (100 %)")
    assert lines[-2] == "block …" and re.fullmatch(r"block: done in \d+\.\d s", lines[-1])


def test_progress_on_a_terminal_is_a_bar_and_messages_get_their_own_line(monkeypatch):
    monkeypatch.delenv("IBL_REF_PROGRESS", raising=False)
    s = _Stream(True)
    for i in progress.track(range(2), "bar", stream=s):
        progress.say(f"message {i}", stream=s)
    text = s.getvalue()
    assert "\r" in text  # a redrawn bar
    for i in range(2):  # each message starts a line and ends it: nothing glued to the bar
        assert re.search(rf"(^|\n|\r)message {i}\n", text)


def test_progress_can_be_silenced_and_used_as_a_callback(monkeypatch):
    monkeypatch.setenv("IBL_REF_PROGRESS", "0")
    s = _Stream(True)
    cb = progress.callback("quiet", 5, stream=s)
    for _ in range(5):
        cb()
    cb.close()
    assert s.getvalue() == "" and cb.progress.n == 5


def test_each_experiment_has_a_thin_script_in_experiments_folder():
    # the top-level experiments/ folder is where a reader looks for a figure's script; each one only forwards
    # to `ibl-ref experiment NAME` (the benchmarks live in benchmarks/)
    scripts = {p.stem: p.read_text() for p in (ROOT / "experiments").glob("*.py")}
    for name, mod in EXPS.items():
        stem = mod.__name__.rsplit(".", 1)[1]
        assert stem in scripts, name
        assert f'main(["experiment", "{name}", *sys.argv[1:]])' in scripts[stem]
    assert not list((ROOT / "experiments").glob("bench_*.py"))
    assert sorted(p.name for p in (ROOT / "benchmarks").glob("bench_*.py"))
