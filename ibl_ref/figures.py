"""Saving and checking experiment figures (display only; no numbers are computed here).

Plot code never chooses a matplotlib backend: a notebook keeps its inline backend (so the figures an
experiment makes can be shown), the command line picks a non-interactive one before matplotlib is imported
(:func:`ibl_ref.cli.main` sets ``MPLBACKEND=Agg`` unless the user set one), and the tests set it through the
environment (``tests/conftest.py``).

* :func:`pyplot` — ``matplotlib.pyplot``, imported lazily (``import ibl_ref`` stays cheap).
* :func:`save_figure` — the one way experiments write a figure: atomic (:func:`ibl_ref.atomic.atomic_path`),
  ``bbox_inches="tight"`` with a small pad, figure closed afterwards.  Hooks registered with
  :func:`add_save_hook` see every figure just before it is written (the tests use one to run
  :func:`layout_problems` over every figure of every experiment).
* :func:`layout_problems` — text drawn outside the figure canvas, table-cell text wider than its cell,
  titles overlapping text of another axes, legends over data and colliding tick labels; measured with the
  renderer's text extents (``Artist.get_window_extent``), in display pixels.
* :func:`integer_ticks` — integer-only tick locator for count axes (lights, lobes); :func:`count_ticks` — ticks
  at given counts, labels thinned where they would collide; :func:`plain_log_ticks` — plain numbers on log axes.
"""

from __future__ import annotations

from pathlib import Path
from .atomic import atomic_path

__all__ = ["pyplot", "save_figure", "add_save_hook", "remove_save_hook", "layout_problems", "integer_ticks",
           "count_ticks", "plain_log_ticks"]

_SAVE_HOOKS: list = []


def pyplot():
    """``matplotlib.pyplot`` (the backend is whatever the environment chose; never switched here)."""
    import matplotlib.pyplot as plt

    return plt


def add_save_hook(fn) -> None:
    """Call ``fn(fig, path)`` before every :func:`save_figure` (e.g. a layout check in the tests)."""
    _SAVE_HOOKS.append(fn)


def remove_save_hook(fn) -> None:
    if fn in _SAVE_HOOKS:
        _SAVE_HOOKS.remove(fn)


def save_figure(fig, path, dpi: int = 110, fmt: str | None = None) -> Path:
    """Write ``fig`` to ``path`` atomically (tight bounding box, 0.05 inch pad) and close it; returns the path."""

    path = Path(path)
    for hook in list(_SAVE_HOOKS):
        hook(fig, path)
    fmt = fmt or (path.suffix.lstrip(".").lower() or "png")
    with atomic_path(path, suffix=path.suffix or ".png") as tmp:
        fig.savefig(tmp, format=fmt, dpi=dpi, bbox_inches="tight", pad_inches=0.05)
    pyplot().close(fig)
    return path


def integer_ticks(axis) -> None:
    """Only integer tick positions on ``axis`` (``ax.xaxis`` / ``ax.yaxis``): counts have no 7.5."""
    from matplotlib.ticker import MaxNLocator

    axis.set_major_locator(MaxNLocator(integer=True))


def plain_log_ticks(axis, minor=(2, 5)) -> None:
    """Plain-number labels on a log ``axis`` (``0.3`` and ``2``, not ``3×10⁻¹`` and ``2×10⁰``); between decades
    only the minor ticks whose leading digit is in ``minor`` are labelled (room for the labels)."""
    import math

    from matplotlib.ticker import FuncFormatter

    def lead(v):
        return round(v / 10 ** math.floor(math.log10(v))) if v > 0 else 0

    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    axis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if lead(v) in minor else ""))


def count_ticks(ax, counts, axis: str = "x", pad_px: float = 3.0) -> None:
    """Ticks at the integer ``counts`` (lights, lobes: no 7.5), each labelled, except a label that would run
    into the one before it on a linear axis (6 and 12 beside 192): that tick stays, unlabelled.  The labels
    are measured as drawn at the figure's current size (lay the figure out first: ``layout="constrained"``)."""
    counts = sorted({int(c) for c in counts})
    setter = ax.set_xticks if axis == "x" else ax.set_yticks
    labels = [str(c) for c in counts]
    setter(counts, labels)
    fig = ax.figure
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    drawn = {t.label1.get_text(): t.label1.get_window_extent(renderer)
             for t in (ax.xaxis if axis == "x" else ax.yaxis)._update_ticks()}
    last = None
    for i, lab in enumerate(labels):
        bb = drawn.get(lab)
        if bb is None:
            continue
        if last is not None and (bb.x0 < last.x1 + pad_px if axis == "x" else bb.y0 < last.y1 + pad_px):
            labels[i] = ""
        else:
            last = bb
    setter(counts, labels)


def _texts(fig):
    """Visible, non-empty texts that are actually drawn (tick labels only of ticks inside the view)."""
    from matplotlib.text import Text

    tick_labels, drawn = set(), set()
    for ax in fig.axes:
        for axis in ax._axis_map.values() if hasattr(ax, "_axis_map") else (ax.xaxis, ax.yaxis):
            ticks = axis.get_major_ticks() + axis.get_minor_ticks()
            for tick in ticks:
                tick_labels.update({id(tick.label1), id(tick.label2)})
            if not (ax.axison and axis.get_visible()):
                continue
            for tick in axis._update_ticks():  # the ticks inside the view interval: the ones drawn
                for lab in (tick.label1, tick.label2):
                    if lab.get_visible():
                        drawn.add(id(lab))
    out = []
    for t in fig.findobj(Text):
        if not (t.get_visible() and t.get_text().strip() and t.figure is fig):
            continue
        if id(t) in tick_labels and id(t) not in drawn:
            continue
        if t.axes is not None and not t.axes.get_visible():
            continue
        out.append(t)
    return out


def layout_problems(fig, tol_px: float = 1.0) -> list[str]:
    """Layout defects of ``fig`` as it would be drawn at its own size and dpi (empty list: none).

    1. a visible text whose extent leaves the figure's bounding box (it would be cut, or — with a tight
       bounding box — shift everything else);
    2. a table cell whose text is wider or taller than the cell (matplotlib does not clip or wrap it);
    3. an axes title (or the figure's suptitle) overlapping a text that belongs to a different axes;
    4. a legend drawn over data points of its own axes (line vertices and markers inside the legend box);
    5. tick labels of one axis running into each other (``6`` and ``12`` drawn as ``612``).

    The figure is checked at its own size: :func:`save_figure` saves with a tight bounding box, which would
    silently grow the canvas around text that does not fit, so plot code lays its figures out
    (``tight_layout`` / ``layout="constrained"``) and this check holds it to that.
    """
    from matplotlib.table import Table

    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    fb = fig.bbox
    problems = []
    texts = _texts(fig)
    for t in texts:
        bb = t.get_window_extent(renderer)
        if (bb.x0 < fb.x0 - tol_px or bb.y0 < fb.y0 - tol_px or bb.x1 > fb.x1 + tol_px
                or bb.y1 > fb.y1 + tol_px):
            problems.append(f"text {t.get_text()[:40]!r} outside the figure: {bb.bounds} vs {fb.bounds}")
    for tab in fig.findobj(Table):
        for (row, col), cell in tab.get_celld().items():
            if not cell.get_visible():
                continue
            cb = cell.get_window_extent(renderer)
            tb = cell.get_text().get_window_extent(renderer)
            if cell.get_text().get_text().strip() and (tb.width > cb.width + tol_px or tb.height > cb.height + tol_px):
                problems.append(f"table cell ({row}, {col}) text {cell.get_text().get_text()[:40]!r} "
                                f"({tb.width:.0f}x{tb.height:.0f} px) wider/taller than its cell "
                                f"({cb.width:.0f}x{cb.height:.0f} px)")

    titles = [(ax.title, ax) for ax in fig.axes if ax.title.get_text().strip()]
    if getattr(fig, "_suptitle", None) is not None and fig._suptitle.get_text().strip():
        titles.append((fig._suptitle, None))
    for title, ax in titles:
        tb = title.get_window_extent(renderer)
        for t in texts:
            if t is title or t.axes is ax:  # same axes (or, for the suptitle, other figure-level text)
                continue
            ob = t.get_window_extent(renderer)
            ix = min(tb.x1, ob.x1) - max(tb.x0, ob.x0)
            iy = min(tb.y1, ob.y1) - max(tb.y0, ob.y0)
            if ix > tol_px and iy > tol_px:
                problems.append(f"title {title.get_text()[:40]!r} overlaps {t.get_text()[:40]!r}")
    import numpy as np
    from matplotlib.lines import Line2D

    for ax in fig.axes:
        leg = ax.get_legend()
        if leg is None or not leg.get_visible() or leg.axes is not ax:
            continue
        lb = leg.get_window_extent(renderer)
        covered = 0
        for line in ax.get_lines():
            if not isinstance(line, Line2D) or not line.get_visible():
                continue
            xy = np.column_stack(line.get_data()).astype(float)
            xy = xy[np.all(np.isfinite(xy), axis=1)]
            if not len(xy):
                continue
            d = line.get_transform().transform(xy)
            covered += int(np.sum((d[:, 0] > lb.x0) & (d[:, 0] < lb.x1) & (d[:, 1] > lb.y0) & (d[:, 1] < lb.y1)))
        if covered:
            problems.append(f"legend of axes {ax.get_title()[:30]!r} covers {covered} data point(s)")
    for ax in fig.axes:
        problems += _tick_collisions(ax, renderer, tol_px)
    return problems


def _tick_collisions(ax, renderer, tol_px: float) -> list[str]:
    """Drawn tick labels of one axis of ``ax`` whose text extents overlap (see :func:`layout_problems`)."""
    out = []
    if not ax.axison or not ax.get_visible():
        return out
    for name, axis in getattr(ax, "_axis_map", {"x": ax.xaxis, "y": ax.yaxis}).items():
        if not axis.get_visible():
            continue
        for side in ("label1", "label2"):
            boxes = []
            for tick in axis._update_ticks():  # the ticks inside the view interval: the ones drawn
                lab = getattr(tick, side)
                if lab.get_visible() and lab.get_text().strip():
                    boxes.append((lab.get_window_extent(renderer), lab.get_text()))
            for i in range(len(boxes)):
                for j in range(i + 1, len(boxes)):
                    a, b = boxes[i][0], boxes[j][0]
                    ix = min(a.x1, b.x1) - max(a.x0, b.x0)
                    iy = min(a.y1, b.y1) - max(a.y0, b.y0)
                    if ix > tol_px and iy > tol_px:
                        out.append(f"{name} tick labels {boxes[i][1]!r} and {boxes[j][1]!r} of axes "
                                   f"{ax.get_title()[:30]!r} overlap")
    return out
