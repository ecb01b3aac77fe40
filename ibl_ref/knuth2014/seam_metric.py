"""Seam metric for cube-map pyramids (Knuth et al. 2014, Sec. 4: "At edges, the neighboring face needs to
be taken into account").

For every level, each of the 12 cube edges and 8 cube corners, the step across the seam is compared with
the gradient inside the faces next to it:

edge
    step = mean over the edge of |L_A(edge texel) − L_B(adjacent edge texel)| (the two texels facing each
    other across the seam, one texel apart like any two neighbours inside a face);
    inner gradient = mean of |L(edge texel) − L(next texel inward)| over both faces;
    ratio = step / inner gradient.
corner
    step = largest pairwise difference of the three texels that meet at the corner;
    inner gradient = mean |L(corner texel) − L(its row / column neighbour)| over the three faces.

A seamless map of a smooth function has ratios ≈ 1; a seam shows as ratio ≫ 1.  Values are averaged over
channels.  For 1×1 faces (no inner gradient) the step is divided by the level's mean |L| instead
(``reference = "mean_value"`` in the table).  A zero inner gradient is replaced by 1e-12·(mean |L| + 1e-300)
so that the ratio stays finite (flagged by a ratio ≥ 1e6).
"""

from __future__ import annotations

import functools

import numpy as np

from ..environment.envmap import FACE_NAMES, face_uv_to_direction
from ..environment.sampling import padding_tables
from .filters import SEAM_MODES
from .filters import pad_cube
from .pyramid import build_pyramid

__all__ = ["seam_metric", "seam_summary", "edge_and_corner_tables", "compare_seam_modes"]

_SIDES = ("left", "right", "top", "bottom")


@functools.lru_cache(maxsize=32)
def edge_and_corner_tables(n: int):
    """Neighbour face of each (face, side) and the 8 corners' (face, row, col) triples."""

    src, _ = padding_tables(n, 1)
    mid = 1 + n // 2 if n > 1 else 1
    nb = {}
    for f in range(6):
        pos = {"left": (mid, 0), "right": (mid, n + 1), "top": (0, mid), "bottom": (n + 1, mid)}
        for side, (r, c) in pos.items():
            nb[(f, side)] = int(src[f, r, c, 0] // (n * n))
    corners = {}
    for f in range(6):
        for rs in (0, 1):
            for cs in (0, 1):
                r, c = rs * (n - 1), cs * (n - 1)
                sgn = np.sign(face_uv_to_direction(f, 2.0 * cs - 1.0, 2.0 * rs - 1.0))
                name = "".join(("+" if s > 0 else "-") + ax for s, ax in zip(sgn, "XYZ"))
                corners.setdefault(name, []).append((f, r, c))
    return nb, corners


def _side_values(face_arr, side, depth):
    """Row/column of one face at ``depth`` (0 = edge texels) from ``side``."""
    n = face_arr.shape[0]
    if side == "left":
        return face_arr[:, depth]
    if side == "right":
        return face_arr[:, n - 1 - depth]
    if side == "top":
        return face_arr[depth, :]
    return face_arr[n - 1 - depth, :]


def seam_metric(pyramid) -> list[dict]:
    """Seam table of every level of a pyramid (or a list of cube levels).

    Returns
    -------
    list of dict
        Rows: ``level, face_size, kind ("edge"|"corner"), name, step, inner_gradient, reference, ratio``.
    """

    levels = pyramid.levels if hasattr(pyramid, "levels") else list(pyramid)
    rows = []
    for L, lev in enumerate(levels):
        a = np.asarray(lev, dtype=np.float64)
        if a.ndim == 4:
            a = a.mean(axis=3)
        n = a.shape[1]
        mean_abs = float(np.mean(np.abs(a)))
        floor = 1e-12 * (mean_abs + 1e-300)
        p = pad_cube(a, 1, "neighbour")
        nb, corners = edge_and_corner_tables(n)
        done = {}
        for f in range(6):
            for side in _SIDES:
                g = nb[(f, side)]
                inner_edge = _side_values(p[f, 1:-1, 1:-1], side, 0)
                across = _side_values(p[f][1:-1, :] if side in ("left", "right") else p[f][:, 1:-1],
                                      {"left": "left", "right": "right", "top": "top", "bottom": "bottom"}[side], 0)
                step = np.abs(inner_edge - across)
                if n >= 2:
                    grad = np.abs(inner_edge - _side_values(p[f, 1:-1, 1:-1], side, 1))
                else:
                    grad = None
                key = tuple(sorted((f, g)))
                acc = done.setdefault(key, {"step": [], "grad": []})
                acc["step"].append(step.mean())
                if grad is not None:
                    acc["grad"].append(grad.mean())
        for (f, g), acc in sorted(done.items()):
            step = float(np.mean(acc["step"]))
            if acc["grad"]:
                ref, refname = float(np.mean(acc["grad"])), "inner_gradient"
            else:
                ref, refname = mean_abs, "mean_value"
            rows.append({"level": L, "face_size": n, "kind": "edge", "name": f"{FACE_NAMES[f]}/{FACE_NAMES[g]}",
                         "step": step, "inner_gradient": ref, "reference": refname,
                         "ratio": step / max(ref, floor)})
        for name, trip in sorted(corners.items()):
            vals = np.array([a[f, r, c] for f, r, c in trip])
            step = float(vals.max() - vals.min())
            if n >= 2:
                gr = []
                for f, r, c in trip:
                    r2 = 1 if r == 0 else n - 2
                    c2 = 1 if c == 0 else n - 2
                    gr += [abs(a[f, r, c] - a[f, r2, c]), abs(a[f, r, c] - a[f, r, c2])]
                ref, refname = float(np.mean(gr)), "inner_gradient"
            else:
                ref, refname = mean_abs, "mean_value"
            rows.append({"level": L, "face_size": n, "kind": "corner", "name": name, "step": step,
                         "inner_gradient": ref, "reference": refname, "ratio": step / max(ref, floor)})
    return rows


def seam_summary(rows) -> list[dict]:
    """Per level and kind: mean and max ratio."""
    out = []
    for L in sorted({r["level"] for r in rows}):
        for kind in ("edge", "corner"):
            rr = [r["ratio"] for r in rows if r["level"] == L and r["kind"] == kind]
            if rr:
                out.append({"level": L, "kind": kind, "ratio_mean": float(np.mean(rr)), "ratio_max": float(np.max(rr))})
    return out


def compare_seam_modes(cube, kernel="sqrtcos", order="shrink_then_filter", seams=None) -> list[dict]:
    """Seam summary (per level and kind) of the pyramid of ``cube`` for every seam mode.

    Returns rows ``seam, level, kind, ratio_mean, ratio_max``.
    """

    out = []
    for seam in seams or SEAM_MODES:
        for r in seam_summary(seam_metric(build_pyramid(cube, kernel, order, seam))):
            out.append({"seam": seam, **r})
    return out
