"""Tick labels a reader can read: the layout check finds labels that run into each other ("6" and "12" drawn as
"612" beside 192 on a linear axis; "3×10⁻¹4×10⁻¹" on a short log axis), and the two helpers that the plots use
against it (figures.count_ticks, figures.plain_log_ticks) remove the collision."""

from ibl_ref import figures

COUNTS = [6, 12, 24, 48, 96, 192]


def _lights_axis():
    plt = figures.pyplot()
    fig, ax = plt.subplots(figsize=(4.0, 3.0), layout="constrained")
    ax.plot(COUNTS, [0.1 * c for c in COUNTS], "o-")
    return fig, ax


def test_colliding_count_labels_are_found_and_thinned():
    plt = figures.pyplot()
    fig, ax = _lights_axis()
    ax.set_xticks(COUNTS, [str(c) for c in COUNTS])
    problems = figures.layout_problems(fig)
    assert any("tick labels '6' and '12'" in p for p in problems), problems
    plt.close(fig)

    fig, ax = _lights_axis()
    figures.count_ticks(ax, COUNTS)
    assert figures.layout_problems(fig) == []
    labels = [t.get_text() for t in ax.get_xticklabels()]
    assert list(ax.get_xticks()) == COUNTS  # every count keeps its tick
    assert labels[0] == "6" and labels[-1] == "192" and "" in labels  # only colliding labels are left out
    plt.close(fig)


def test_short_log_axis_gets_plain_labels_that_do_not_collide():
    plt = figures.pyplot()

    def draw():
        fig, ax = plt.subplots(figsize=(3.2, 2.5), layout="constrained")
        ax.plot([0.09, 0.2, 0.8], [1e-3, 1e-5, 1e-7], "o")
        ax.set(xscale="log", yscale="log")
        return fig, ax

    fig, ax = draw()
    assert any("x tick labels" in p for p in figures.layout_problems(fig))  # matplotlib's 3×10⁻¹ 4×10⁻¹ …
    plt.close(fig)
    fig, ax = draw()
    figures.plain_log_ticks(ax.xaxis)
    assert figures.layout_problems(fig) == []
    fig.canvas.draw()
    shown = {t.get_text() for t in ax.xaxis.get_majorticklabels() + ax.xaxis.get_minorticklabels()} - {""}
    assert {"0.1", "0.2", "0.5"} <= shown and not any("times" in t or "×" in t for t in shown)
    plt.close(fig)
