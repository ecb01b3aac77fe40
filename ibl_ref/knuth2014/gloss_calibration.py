"""Knuth et al. (2014) Sec. 5: the calibration tables s_Phong → pyramid level of the glossiness lookup.

The paper: "the lobe volume is characteristical for a given glossiness", so the level for a Phong exponent s
is the continuous level whose response lobe to one white texel has the volume of the target lobe cosˢ
(:meth:`ibl_ref.knuth2014.lobe_analysis.LobeResponse.fit_level`; volume definitions ``"integral"`` ∫f dω and
``"radial"`` ⅓∫f³ dω).  This module runs that fit over a grid of exponents and turns it into a
:class:`ibl_ref.knuth2014.gloss_lookup.Calibration` table (monotone envelope: levels never rise with s).

Data flow: this analysis step *writes* the tables (``ibl_ref/data/calibration_*.json``,
:func:`build_calibration_tables`); the run-time lookup (:mod:`ibl_ref.knuth2014.gloss_lookup`) only *reads* them
and never runs the analysis.  For a configuration without a shipped table, compute one here (:func:`calibrate`)
and pass it to the lookup as ``calibration=``, or write it into the data folder with
:func:`build_calibration_tables`.

Shipped (:data:`SHIPPED`; regenerate all with :func:`build_shipped_tables`): the five paper filters (``none, box,
gauss, cos, sqrtcos``), order ``shrink_then_filter``, seam ``neighbour``, both volume definitions, face sizes
1 … 256 (sqrtcos also 512); and sqrtcos with the solid-angle 2×2 shrink at 1 … 256.  ``tests/test_gloss_lookup.py``
checks every shipped table against the closed-form lobe volumes through the run-time lookup.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .gloss_lookup import Calibration, calibration_path
from .lobe_analysis import LobeResponse, s_grid
from ..atomic import write_json
from ..progress import step
from .gloss_lookup import shipped_calibration

__all__ = ["calibrate", "calibration_for", "build_calibration_tables", "build_shipped_tables", "save_calibration", "table_from_response",
           "SHIPPED"]

#: face sizes, kernels and shrinks of the shipped tables (see the module docstring)
SHIPPED = (
    dict(face_sizes=(1, 2, 4, 8, 16, 32, 64, 128, 256), kernels=("none", "box", "gauss", "cos", "sqrtcos")),
    dict(face_sizes=(512,), kernels=("sqrtcos",)),
    dict(face_sizes=(1, 2, 4, 8, 16, 32, 64, 128, 256), kernels=("sqrtcos",), shrink="solid_angle"),
)

#: number of exponents per table (log-spaced from 1 to the texel limit, :func:`ibl_ref.knuth2014.lobe_analysis.s_grid`)
TABLE_EXPONENTS = 48

_MEMORY: dict = {}


def table_from_response(resp: LobeResponse, volume: str = "integral", s_values=None) -> Calibration:
    """Calibration table of one lobe response: the volume-matching level at every exponent, monotone envelope."""
    s_values = s_grid(resp.n, TABLE_EXPONENTS) if s_values is None else np.asarray(s_values, dtype=np.float64)
    lev = np.array([resp.fit_level(float(s), volume)[0] for s in s_values])
    kernel = resp.kernel if isinstance(resp.kernel, str) else "custom"
    return Calibration(np.asarray(s_values, float), np.minimum.accumulate(lev), kernel, resp.order, resp.seam,
                       resp.n, volume, "lobe_analysis", resp.max_level, resp.shrink)


def calibrate(face_size: int, kernel="sqrtcos", order="shrink_then_filter", seam="neighbour",
              volume="integral", s_values=None, position="centre", shrink="mean") -> Calibration:
    """Calibration table from the lobe-volume fit of :mod:`ibl_ref.knuth2014.lobe_analysis` (memory-cached).

    ``kernel`` may also be 5 explicit taps (``kernel="custom"`` in the table); ``position`` moves the white
    texel (``"centre"``, the shipped tables' choice, ``"edge"``, ``"corner"``).
    """
    key = (int(face_size), kernel if isinstance(kernel, str) else tuple(np.ravel(kernel)), order, seam, volume,
           position, None if s_values is None else tuple(s_values), shrink)
    if key not in _MEMORY:
        resp = LobeResponse(int(face_size), kernel, order, seam, position, shrink=shrink)
        _MEMORY[key] = table_from_response(resp, volume, s_values)
    return _MEMORY[key]


def calibration_for(face_size: int, kernel="sqrtcos", order="shrink_then_filter", seam="neighbour",
                    volume="integral", shrink="mean", progress: bool = False) -> Calibration:
    """The shipped table of a configuration, or (none shipped, e.g. faces of 1024² and more) one computed here.

    For the commands that build the paper's pyramids from a user's size (``ibl-ref render --env-size N``): the
    run-time lookup only reads tables, so the command resolves the table first and passes it on as
    ``calibration=``.  Computing one costs a lobe analysis at that face size (measured 33 s at 512² on the
    loaded 2-core machine) and is reported as a progress step.
    """

    cal = shipped_calibration(face_size, kernel, order, seam, volume, shrink)
    if cal is None:
        with step(f"glossiness calibration for {face_size}² faces (no shipped table; lobe analysis)",
                  enabled=progress):
            cal = calibrate(face_size, kernel, order, seam, volume, shrink=shrink)
    return cal


def save_calibration(cal: Calibration, data_dir: Path | None = None) -> Path:
    """Write a calibration table as JSON (atomic) into ``ibl_ref/data`` (or ``data_dir``)."""

    return write_json(calibration_path(cal.face_size, cal.kernel, cal.order, cal.seam, cal.volume, cal.shrink,
                                       data_dir), cal.to_dict())


def build_calibration_tables(face_sizes, kernels=("sqrtcos",), volumes=("integral", "radial"),
                             order="shrink_then_filter", seam="neighbour", shrink="mean",
                             data_dir: Path | None = None) -> list:
    """Compute and save calibration JSON tables (one lobe response per size and kernel); returns the paths."""
    paths = []
    for n in face_sizes:
        for k in kernels:
            resp = LobeResponse(int(n), k, order, seam, "centre", shrink=shrink)
            for vol in volumes:
                paths.append(save_calibration(table_from_response(resp, vol), data_dir))
            del resp
    return paths


def build_shipped_tables(data_dir: Path | None = None) -> list:
    """Rebuild every table of :data:`SHIPPED` (into ``ibl_ref/data`` or ``data_dir``); returns the paths."""
    return [p for spec in SHIPPED for p in build_calibration_tables(**spec, data_dir=data_dir)]
