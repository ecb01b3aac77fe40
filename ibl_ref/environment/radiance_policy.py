"""What to do with the values real HDR files contain: negative, NaN and infinite radiance.

Not a paper concept: the front door every tool needs before Knuth et al. 2014's pipeline (which, like
every radiance formula, assumes L ≥ 0 and finite).  This module is the **one place** where that
policy lives; every reader (:func:`ibl_ref.environment.exr_io.read_image`, :func:`~ibl_ref.environment.exr_io.read_envmap`,
:func:`~ibl_ref.environment.exr_io.load_cube`, :func:`ibl_ref.environment.hdr_io.read_hdr`), every CLI command that reads an
environment (flags ``--negative`` and ``--nonfinite``) and :func:`check_radiance` (the check of every library
function that takes radiance arrays) use it.

Why negatives appear: published probes are often stored with OpenEXR's lossy **DWAB** compression,
whose quantisation leaves a few to thousands of tiny negative values in dark areas (measured on
probe-like files in ``tests/test_real_probes.py``: see docs/background.md "Real light probes").
They carry a negligible share of the energy; renderers simply use the data.

The policy (parameters ``negative`` and ``nonfinite``)
------------------------------------------------------
Let ``L⁻ = max(−L, 0)`` be the negative part of the colour channels and ω the texel solid angles of
the layout (exact, :mod:`ibl_ref.environment.envmap`; uniform weights when the layout is unknown).  The *removed
fraction* is

    f = Σ ω·L⁻ / Σ ω·|L|        (the share of ∫|L| dω that clamping to 0 removes)

* ``negative="auto"`` (default of the readers and the CLI): clamp negatives to 0 and report count,
  minimum and f, **unless** f > :data:`AUTO_MAX_REMOVED_FRACTION` (1e-4): then the data are refused
  (:class:`~ibl_ref.errors.RadianceError`) with a message naming ``--negative clamp`` / ``negative="clamp"``
  — negatives that carry real energy are a sign of a wrong file (signed data, a difference image), not of
  compression.
* ``negative="clamp"``: clamp every negative value to 0 (reported).
* ``negative="error"``: any negative value is an error (the default of the library functions that take
  arrays, via :func:`check_radiance`).
* ``nonfinite="error"`` (default everywhere): NaN or ±Inf is an error naming the count, the first index
  and ``--nonfinite zero``.  ``nonfinite="zero"``: replace them by 0 (reported).  There is no automatic
  mode: a NaN or Inf carries no radiance value to keep.
* Complex, integer or boolean arrays are an error (radiance is real and linear; an integer image is
  an 8-bit display image or a mask, not radiance).

Non-finite values are handled first, so f is computed over finite values.  Only the colour channels
(R, G, B or Y) are radiance; an alpha channel is checked for NaN/Inf by the readers but never clamped.
The :class:`RadianceReport` of every read is printed on stderr by the CLI and stored under
``"radiance"`` in each command's JSON sidecar; the Python readers warn once with the same line
(:class:`~ibl_ref.errors.RadianceWarning`) whenever the policy changed a value.

Writing: what a format cannot hold (:func:`check_format_range`)
----------------------------------------------------------------
Overflow is refused by every writer.  At the other end a format holds small values only down to a limit:
half floats are exact relative to 2^-11 down to their smallest normal number 2^-14 ≈ 6.1e-5, below it
(subnormals) the step is a constant 2^-24 ≈ 6e-8 and values under 2^-25 become 0; float32 likewise below
2^-126 ≈ 1.2e-38 (0 under 2^-150); Radiance RGBE stores a pixel whose largest channel is below 1e-32 as 0.  The
writers measure what this costs in the map's own unit, the share of ∫L dω (exact texel solid angles; pixel
sums for rendered images)

    f_range = Σ ω·|q(L) − L| / Σ ω·L        over the values below the format's normal range,

and refuse the write (:class:`~ibl_ref.errors.RadianceError`, naming the format, the count, f_range and the
remedy) when f_range > :data:`AUTO_MAX_REMOVED_FRACTION`, the same share the reader's ``negative="auto"``
accepts; a smaller positive f_range above :data:`RANGE_WARN_FRACTION` is a
:class:`~ibl_ref.errors.FormatRangeWarning` with the same numbers.  So a map of 1e-8 written as half (every
value would become 0) is an error, never a silent black file.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from ..errors import FormatRangeWarning, RadianceError
from . import envmap

__all__ = [
    "NEGATIVE_MODES",
    "NONFINITE_MODES",
    "AUTO_MAX_REMOVED_FRACTION",
    "RadianceReport",
    "assess",
    "decide",
    "apply_policy",
    "pixel_solid_angles",
    "check_radiance",
    "RANGE_WARN_FRACTION",
    "range_loss",
    "check_format_range",
    "warn_repaired",
]

NEGATIVE_MODES = ("auto", "clamp", "error")
NONFINITE_MODES = ("error", "zero")
#: largest share of ∫|L| dω that ``negative="auto"`` removes by clamping (above it the data are refused)
AUTO_MAX_REMOVED_FRACTION = 1e-4
#: share of ∫L dω below which the loss of values under a format's normal range is not reported
RANGE_WARN_FRACTION = 1e-7
_CHUNK = 1 << 22  # elements per reduction chunk (bounds the temporaries to ~32 MB)


@dataclass
class RadianceReport:
    """What an array or file contained and what the policy did with it.

    Counts are over the radiance values (every channel element); ``negative_min`` is the most negative
    value (0 if none); ``removed_fraction`` is f of the module docstring (0 if no negatives);
    ``action`` lists what was done (``[]``: the data were used unchanged).
    """

    name: str
    negative_policy: str
    nonfinite_policy: str
    n_values: int
    n_nan: int = 0
    n_posinf: int = 0
    n_neginf: int = 0
    first_nonfinite: tuple | None = None
    first_nonfinite_kind: str = ""
    n_negative: int = 0
    negative_min: float = 0.0
    removed_fraction: float = 0.0
    abs_integral: float = 0.0
    weights: str = "uniform"
    action: list = field(default_factory=list)

    @property
    def n_nonfinite(self) -> int:
        return self.n_nan + self.n_posinf + self.n_neginf

    @property
    def clean(self) -> bool:
        return self.n_nonfinite == 0 and self.n_negative == 0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["first_nonfinite"] = list(self.first_nonfinite) if self.first_nonfinite is not None else None
        d["auto_max_removed_fraction"] = AUTO_MAX_REMOVED_FRACTION
        return d

    def findings(self) -> str:
        """What was found (counts, minimum, removed fraction), without the name; empty when clean."""
        parts = []
        if self.n_nonfinite:
            parts.append(f"{self.n_nonfinite} NaN/Inf value(s) ({self.n_nan} NaN, {self.n_posinf} +Inf, "
                         f"{self.n_neginf} -Inf)")
        if self.n_negative:
            parts.append(f"{self.n_negative} negative value(s) (min {self.negative_min:.3g}, "
                         f"{self.removed_fraction:.2e} of the integral of |L| domega)")
        return ", ".join(parts)

    def summary(self) -> str:
        """One line for stderr; empty when the data were clean."""
        if self.clean:
            return ""
        did = "; ".join(self.action) if self.action else "left unchanged"
        return f"{self.name}: {self.findings()}: {did}"


def _check_modes(negative: str, nonfinite: str) -> None:
    if negative not in NEGATIVE_MODES:
        raise RadianceError(f"unknown negative-radiance policy {negative!r}; choose one of {NEGATIVE_MODES}")
    if nonfinite not in NONFINITE_MODES:
        raise RadianceError(f"unknown non-finite policy {nonfinite!r}; choose one of {NONFINITE_MODES}")


def _check_dtype(a: np.ndarray, name: str) -> None:
    if np.issubdtype(a.dtype, np.complexfloating):
        raise RadianceError(f"{name}: complex values (dtype {a.dtype}); radiance must be real")
    if a.dtype == bool or np.issubdtype(a.dtype, np.integer):
        raise RadianceError(f"{name}: integer/boolean dtype {a.dtype}; radiance must be a float array "
                            "(convert display images to linear floats first)")
    if not np.issubdtype(a.dtype, np.floating):
        raise RadianceError(f"{name}: expected a numeric float array, got dtype {a.dtype}")


def pixel_solid_angles(h: int, w: int, layout: str | None):
    """Per-pixel solid angles of an ``h × w`` image in ``layout`` (for the removed fraction).

    Returns an array broadcastable to ``(h, w)``: ``(h, 1)`` for ``"latlong"``, ``(h, w)`` for
    ``"cube"`` strips (faces stacked) and crosses (empty cells 0), or ``None`` (uniform weights) for an
    unknown layout.
    """

    if layout == "latlong" and w == 2 * h:
        return envmap.latlong_solid_angles(h, w)
    if layout == "cube" and h == 6 * w:
        return np.tile(envmap.texel_solid_angles(w), (6, 1))
    if layout in ("hcross", "vcross"):
        rows, cols = envmap.CROSS_LAYOUTS[layout]["cells"]
        n = h // rows
        if n * rows != h or n * cols != w:
            return None
        out = np.zeros((h, w))
        om = envmap.texel_solid_angles(n)
        for r, c, _ in envmap.CROSS_LAYOUTS[layout]["faces"]:
            out[r * n : (r + 1) * n, c * n : (c + 1) * n] = om
        return out
    return None


def _chunks(a: np.ndarray):
    """Slices along axis 0 of about _CHUNK elements each."""
    per = max(1, _CHUNK // max(1, a[:1].size))
    for i in range(0, a.shape[0], per):
        yield slice(i, min(a.shape[0], i + per))


def _weights_for(a: np.ndarray, weights, sl: slice):
    """Weights of rows ``sl`` broadcast against ``a[sl]`` (leading axes), or 1."""
    if weights is None:
        return 1.0
    w = np.asarray(weights, dtype=np.float64)
    w = w[sl] if w.ndim and w.shape[0] == a.shape[0] else w
    return w.reshape(w.shape + (1,) * (a.ndim - w.ndim))


def assess(values, name: str = "radiance", weights=None, negative: str = "auto",
           nonfinite: str = "error") -> RadianceReport:
    """Count NaN/Inf/negative values and the removed fraction f, without changing or refusing anything.

    ``weights``: per-texel solid angles broadcastable to the leading axes of ``values`` (its first axis
    must match), e.g. :func:`pixel_solid_angles`; ``None`` = uniform.  ``negative`` / ``nonfinite``
    are only recorded in the report (see :func:`decide`).
    """
    _check_modes(negative, nonfinite)
    a = np.asarray(values)
    _check_dtype(a, name)
    rep = RadianceReport(name=name, negative_policy=negative, nonfinite_policy=nonfinite, n_values=int(a.size),
                         weights="uniform" if weights is None else "solid_angle")
    if a.ndim == 0:
        a = a.reshape(1)
    neg_int, abs_int, first = 0.0, 0.0, None
    nmin = 0.0
    for sl in _chunks(a):
        blk = a[sl]
        w = _weights_for(a, weights, sl)
        if blk.size and a.dtype.kind == "f":
            lo, hi = blk.min(), blk.max()
            if lo >= 0 and hi < np.inf:  # (False for NaN) finite and non-negative: nothing to count
                abs_int += float(np.sum(blk * w, dtype=np.float64))
                continue
        fin = np.isfinite(blk)
        if not fin.all():
            nan = np.isnan(blk)
            rep.n_nan += int(nan.sum())
            rep.n_posinf += int((blk == np.inf).sum())
            rep.n_neginf += int((blk == -np.inf).sum())
            if first is None:
                idx = np.argwhere(~fin)[0]
                v = blk[tuple(idx)]
                rep.first_nonfinite_kind = "NaN" if np.isnan(v) else ("Inf" if v > 0 else "-Inf")
                idx[0] += sl.start
                first = tuple(int(i) for i in idx)
            blk = np.where(fin, blk, 0)
        neg = blk < 0
        k = int(neg.sum())
        absb = np.abs(blk, dtype=np.float64)
        abs_int += float(np.sum(absb * w))
        if k:
            rep.n_negative += k
            nmin = min(nmin, float(blk.min()))
            neg_int += float(np.sum(np.where(neg, absb, 0.0) * w))
    rep.first_nonfinite = first
    rep.negative_min = nmin
    rep.abs_integral = abs_int
    rep.removed_fraction = neg_int / abs_int if abs_int > 0 else 0.0
    return rep


def decide(rep: RadianceReport) -> tuple:
    """Apply the report's policy: ``(zero_nonfinite, clamp_negative)`` or raise :class:`RadianceError`."""
    name = rep.name
    zero_nf = clamp = False
    if rep.n_nonfinite:
        if rep.nonfinite_policy == "error":
            raise RadianceError(
                f"{name}: {rep.n_nonfinite} non-finite value(s) (first: {rep.first_nonfinite_kind} at index "
                f"{rep.first_nonfinite}): {rep.n_nan} NaN, {rep.n_posinf} +Inf, {rep.n_neginf} -Inf; NaN/Inf "
                f"radiance is refused unless you pass --nonfinite zero (Python: nonfinite='zero') to replace "
                f"them by 0")
        zero_nf = True
    if rep.n_negative:
        if rep.negative_policy == "error":
            raise RadianceError(
                f"{name}: {rep.n_negative} negative radiance value(s) (min {rep.negative_min:g}, "
                f"{rep.removed_fraction:.2e} of the integral of |L| domega); pass --negative auto or clamp "
                f"(Python: negative='auto' or negative='clamp') to clamp them to 0")
        if rep.negative_policy == "auto" and rep.removed_fraction > AUTO_MAX_REMOVED_FRACTION:
            raise RadianceError(
                f"{name}: {rep.n_negative} negative radiance value(s) (min {rep.negative_min:g}) carry "
                f"{rep.removed_fraction:.2e} of the integral of |L| domega, more than the "
                f"{AUTO_MAX_REMOVED_FRACTION:g} that --negative auto clamps silently (lossy compression "
                f"leaves far less); if the file is right, pass --negative clamp (Python: negative='clamp') "
                f"to clamp them to 0, or --negative error to refuse any")
        clamp = True
    return zero_nf, clamp


def apply_policy(values, name: str = "radiance", negative: str = "auto", nonfinite: str = "error",
                 weights=None, inplace: bool = False):
    """Check ``values`` under the policy; return ``(array, RadianceReport)``.

    The array is ``values`` itself when nothing needs changing (or ``inplace=True``), else a repaired
    copy (NaN/Inf → 0 with ``nonfinite="zero"``, negatives → 0 when clamped).  Raises
    :class:`RadianceError` as described in the module docstring.
    """
    rep = assess(values, name, weights, negative, nonfinite)
    zero_nf, clamp = decide(rep)
    a = np.asarray(values)
    if zero_nf or clamp:
        if not inplace or not a.flags.writeable:
            a = a.copy()
        for sl in _chunks(a):
            blk = a[sl]
            if zero_nf:
                blk[~np.isfinite(blk)] = 0
            if clamp:
                np.maximum(blk, 0, out=blk)
        if zero_nf:
            rep.action.append(f"replaced {rep.n_nonfinite} NaN/Inf value(s) by 0 (policy nonfinite=zero)")
        if clamp:
            why = (f"policy negative=auto: {rep.removed_fraction:.2e} <= {AUTO_MAX_REMOVED_FRACTION:g} of the integral"
                   if rep.negative_policy == "auto" else "policy negative=clamp")
            rep.action.append(f"clamped {rep.n_negative} negative value(s) to 0 ({why})")
    return a, rep


def check_radiance(values, name: str = "radiance", negative: str = "error", nonfinite: str = "error") -> np.ndarray:
    """Return ``values`` as an array after checking it is finite and non-negative.

    Raises :class:`~ibl_ref.errors.RadianceError` naming ``name``, the count of offending values and the first
    index; complex, integer and boolean arrays are refused too.  ``negative`` / ``nonfinite`` select another
    policy (module docstring; then a repaired copy may be returned).
    """
    return apply_policy(values, name, negative=negative, nonfinite=nonfinite)[0]
def warn_repaired(rep: RadianceReport, stacklevel: int = 3) -> None:
    """Warn once (:class:`~ibl_ref.errors.RadianceWarning`, the CLI's ``note:`` line) if the policy changed values."""
    if rep is not None and rep.action:
        import warnings

        from ..errors import RadianceWarning

        warnings.warn(rep.summary(), RadianceWarning, stacklevel=stacklevel)


def range_loss(values, stored, min_normal: float, weights=None) -> tuple:
    """``(f_range, n_below, n_zeroed)`` of the module docstring for ``values`` written as ``stored``.

    ``values``: the radiance to write (float64, non-negative, leading axes as ``weights``), ``stored``: the
    same array as the format holds it (any float dtype, same shape); ``min_normal``: the format's smallest
    value of full relative precision.  Works in row chunks.
    """
    a = np.asarray(values)
    q = np.asarray(stored)
    if a.ndim == 0:
        a, q = a.reshape(1), q.reshape(1)
    lost = total = 0.0
    n_below = n_zero = 0
    for sl in _chunks(a):
        blk = np.asarray(a[sl], dtype=np.float64)
        w = _weights_for(a, weights, sl)
        total += float(np.sum(blk * w))
        small = (blk > 0) & (blk < min_normal)
        k = int(small.sum())
        if not k:
            continue
        qb = np.asarray(q[sl], dtype=np.float64)
        n_below += k
        n_zero += int((small & (qb == 0)).sum())
        lost += float(np.sum(np.where(small, np.abs(qb - blk), 0.0) * w))
    return (lost / total if total > 0 else 0.0), n_below, n_zero


def check_format_range(values, stored, where: str, fmt: str, min_normal: float, weights=None,
                       remedy: str = "") -> float:
    """Refuse or warn about values below a format's range (module docstring); returns f_range.

    ``fmt`` names the limit in the message (e.g. ``"the smallest normal half"``), ``remedy`` says what to do instead.
    """
    f, n_below, n_zero = range_loss(values, stored, min_normal, weights)
    if f <= RANGE_WARN_FRACTION:
        return f
    share = "of the integral of L domega" if weights is not None else "of the image's sum"
    what = (f"{n_below} value(s) below {fmt} ({min_normal:.3g}), {n_zero} of them stored as 0, "
            f"change {f:.2e} {share}")
    if f > AUTO_MAX_REMOVED_FRACTION:
        raise RadianceError(f"{where}: {what}, more than {AUTO_MAX_REMOVED_FRACTION:g}; the file would not hold "
                            f"this map" + (f" ({remedy})" if remedy else ""))
    import warnings

    warnings.warn(f"{where}: {what}", FormatRangeWarning, stacklevel=3)
    return f
