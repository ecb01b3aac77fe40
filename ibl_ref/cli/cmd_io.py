"""``ibl-ref convert`` and ``ibl-ref info``: environment-map file conversion and inspection."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

from ..errors import IBLError
from .radiance_args import add_radiance_args

OUT_SUFFIXES = (".exr", ".hdr", ".pic")  #: file types ``convert`` writes


def _load_any(path: Path, negative: str = "auto", nonfinite: str = "error"):
    """:func:`ibl_ref.environment.exr_io.read_map` of any supported file (no resampling), EXR pixels as float32
    (exact for half and float files); the radiance policy is applied to the colour channels."""
    import warnings

    from ..environment import exr_io
    from ..errors import RadianceWarning

    with warnings.catch_warnings():  # the report is printed by the command (radiance_args.tell)
        warnings.simplefilter("ignore", RadianceWarning)
        return exr_io.read_map(path, negative=negative, nonfinite=nonfinite, dtype=np.float32)


def _hdr_extra(path: Path) -> dict:
    from ..environment.hdr_io import read_hdr_header

    hdr = read_hdr_header(path)
    return {"exposure_product": hdr["exposure"], "orientation": f"{hdr['major']} {hdr['minor']}"}


def _exr_extra(header: dict) -> dict:
    return {"envmap_attribute": header.get("envmap", "-"), "convention": header.get("iblref_convention", "-")}


_LAYOUT_RULES = "N wide x 6N high = cube strip, 2H x H = lat-long, 4N x 3N = horizontal cross, 3N x 4N = vertical cross"


def _info_read(path: Path):
    """Everything ``info`` shows, without refusing anything a decoder can read.

    Returns (image (H, W, C) with every channel, channel names, colour channel count, pixel type, format,
    extra fields, header, n_parts).
    """
    from ..environment import exr_io
    from ..environment.hdr_io import read_hdr

    if path.suffix.lower() in (".hdr", ".pic", ".rgbe"):
        img = read_hdr(path, negative="clamp", nonfinite="zero")
        return img, ("R", "G", "B"), 3, "rgbe", "Radiance RGBE", _hdr_extra(path), {}, 1
    ex = exr_io.read_exr(path, dtype=np.float32, channels="all")  # float32 holds half/float exactly
    extra = _exr_extra(ex.header)
    extra["compression"] = ex.header.get("compression", "-")
    return ex.pixels, ex.channels, ex.n_colour, ex.pixel_type, "OpenEXR", extra, ex.header, ex.n_parts


def _channel_stats(img: np.ndarray, weights) -> dict:
    """Per channel: min / max / mean of the finite values, NaN / Inf / negative counts and ∫ dω (NaN/Inf as 0).

    ``mean`` is the solid-angle weighted mean ∫L dω / ∫dω over the finite values when ``weights`` (per-pixel
    solid angles broadcastable to (H, W)) are given, the per-pixel mean otherwise.  Works in row chunks.
    """
    c = img.shape[-1]
    st = {"min": np.full(c, np.inf), "max": np.full(c, -np.inf), "sum": np.zeros(c), "n": np.zeros(c, np.int64),
          "nan": [0] * c, "inf": [0] * c, "neg": [0] * c, "integral": np.zeros(c), "omega": np.zeros(c)}
    wts = None if weights is None else np.broadcast_to(weights, img.shape[:2])
    step = max(1, (1 << 22) // max(1, img.shape[1] * c))
    for r0 in range(0, img.shape[0], step):
        blk = img[r0 : r0 + step].astype(np.float64)
        fin = np.isfinite(blk)
        for i in range(c):
            b, f = blk[..., i], fin[..., i]
            st["nan"][i] += int(np.isnan(b).sum())
            st["inf"][i] += int(np.isinf(b).sum())
            v = b[f]
            if v.size:
                st["min"][i] = min(st["min"][i], v.min())
                st["max"][i] = max(st["max"][i], v.max())
                st["sum"][i] += v.sum()
                st["n"][i] += v.size
                st["neg"][i] += int((v < 0).sum())
            if wts is not None:
                st["integral"][i] += float(np.sum(np.where(f, b, 0.0) * wts[r0 : r0 + step]))
                st["omega"][i] += float(np.sum(np.where(f, wts[r0 : r0 + step], 0.0)))
    if wts is not None:
        st["mean"] = np.where(st["omega"] > 0, st["integral"] / np.where(st["omega"] > 0, st["omega"], 1.0), np.nan)
    else:
        st["mean"] = np.where(st["n"] > 0, st["sum"] / np.maximum(st["n"], 1), np.nan)
    st["min"] = np.where(st["n"] > 0, st["min"], np.nan)
    st["max"] = np.where(st["n"] > 0, st["max"], np.nan)
    return st


def _layout_reason(path: Path, h: int, w: int, header: dict):
    """(layout or None, sentence saying where it came from)."""
    from ..environment import exr_io

    try:
        declared = exr_io.declared_layout(header, str(path))
    except IBLError as exc:
        return None, str(exc)
    try:
        lay = exr_io.infer_layout(h, w, declared, str(path))
    except IBLError as exc:
        return None, f"{exc}"
    if declared is not None:
        return lay, f"from the envmap attribute ({header.get('envmap')})"
    if path.suffix.lower() in (".hdr", ".pic", ".rgbe"):
        return lay, f"Radiance files carry no layout: inferred from the aspect ratio {w} x {h} ({_LAYOUT_RULES})"
    return lay, f"no envmap attribute: inferred from the aspect ratio {w} x {h} ({_LAYOUT_RULES})"


def cmd_info(args) -> int:
    from ..environment.radiance_policy import assess, decide, pixel_solid_angles

    from ..progress import step

    path = Path(args.file)
    with step(f"reading {path}"):  # a 16K probe takes seconds
        img, chans, nc, ptype, fmt, extra, header, n_parts = _info_read(path)
    h, w = img.shape[:2]
    layout, why = _layout_reason(path, h, w, header)
    bad_convention = None
    if layout == "cube" and fmt == "OpenEXR":
        from ..environment import exr_io

        try:
            exr_io.cube_convention(header, None, str(path))
        except IBLError as exc:
            bad_convention = str(exc)
    print(f"file:       {path}")
    print(f"format:     {fmt}  pixel type: {ptype}" + (f"  parts: {n_parts} (showing part 0)" if n_parts > 1 else ""))
    print(f"layout:     {layout or 'unknown'}  image: {w} x {h} (W x H)")
    print(f"layout from: {why}")
    print(f"channels:   {','.join(chans)}" + ("" if nc else "  (no R,G,B or Y channel: not an environment map)"))
    for k, v in extra.items():
        print(f"{k + ':':18s}{v}")
    if layout in ("cube", "hcross", "vcross"):
        print(f"cube:       6 faces of {w if layout == 'cube' else h // {'hcross': 3, 'vcross': 4}[layout]}²")
    weights = pixel_solid_angles(h, w, layout)
    if nc:  # before anything is zeroed
        rep = assess(img[..., :nc], f"{path}: radiance", weights, args.negative, args.nonfinite)
    st = _channel_stats(img, weights)
    mean_kind = "mean_per_sr" if weights is not None else "pixel_mean"  # solid-angle weighted, or not inferable
    print(f"channel     min           max           {mean_kind:13s} integral_L_domega_(sr)  NaN      Inf      negative")
    for i, c in enumerate(chans):
        integ = st["integral"][i] if layout is not None else np.nan
        print(f"{c:11s} {st['min'][i]:<13.6g} {st['max'][i]:<13.6g} {st['mean'][i]:<13.6g} {integ:<23.9g} "
              f"{st['nan'][i]:<8d} {st['inf'][i]:<8d} {st['neg'][i]}")
    other_nonfinite = any(st["nan"][i] + st["inf"][i] for i in range(nc, len(chans)))
    other_negative = {chans[i]: st["neg"][i] for i in range(nc, len(chans)) if st["neg"][i]}
    print("(mean_per_sr: the solid-angle weighted mean, integral / 4 pi for a full sphere)" if weights is not None
          else "(pixel_mean: the layout is unknown, so the mean is over pixels, not weighted by solid angle)")
    if any(st["nan"]) or any(st["inf"]):
        print("(statistics and integrals over the finite values; NaN/Inf counted as 0)")
    if nc:
        if rep.clean and not other_nonfinite and not other_negative:
            print("check:      no NaN, no Inf, no negative radiance")
        else:
            found = [rep.findings() or "colour channels clean"]
            if other_negative:
                found.append("negative values in channel(s) " + ", ".join(f"{c} ({n})" for c, n in other_negative.items())
                             + ", which are not radiance: left as they are")
            if other_nonfinite:
                found.append("NaN/Inf in the other channels (see the table)")
            print(f"check:      {'; '.join(found)}")
        try:
            zero_nf, clamp = decide(rep)
            todo = []
            if zero_nf:
                todo.append(f"replace {rep.n_nonfinite} NaN/Inf value(s) by 0")
            if clamp:
                todo.append(f"clamp {rep.n_negative} negative value(s) to 0 "
                            f"(removing {rep.removed_fraction:.2e} of the integral of |L| domega)")
            verdict = "; ".join(todo) if todo else "use the radiance unchanged"
            if other_nonfinite:
                verdict += ("; NaN/Inf in the other channels: " + ("replaced by 0" if args.nonfinite == "zero"
                            else "refused (--nonfinite zero replaces them by 0)"))
        except IBLError as exc:
            import re

            verdict = f"refuse the file: {str(exc).split(': radiance: ', 1)[-1]}"
            verdict = re.sub(r"\s*\(Python: [^()]*\)", "", verdict)  # the flags are named already
        if layout is None:
            verdict = "refuse the file: its layout cannot be inferred"
        elif bad_convention:
            verdict = f"refuse the file: {bad_convention.split(': ', 1)[-1]}"
    else:
        verdict = "refuse the file: no R,G,B or Y channel"
    print(f"commands:   with --negative {args.negative} --nonfinite {args.nonfinite} the other commands would {verdict}")
    return 0


def cmd_convert(args) -> int:
    from ..environment import exr_io, resample
    from ..environment.hdr_io import write_hdr

    from ..atomic import refuse_overwriting_inputs, resolve_output

    src, dst = Path(args.input), Path(args.output)
    if dst.suffix.lower() not in OUT_SUFFIXES:
        raise IBLError(f"OUT {dst}: convert writes OpenEXR (.exr) or Radiance (.hdr, .pic) files; "
                       f"use one of these extensions (a {dst.suffix or 'missing'} extension would mislabel the file)")
    refuse_overwriting_inputs({"IN": src}, {"OUT": dst})
    resolve_output(dst)  # a folder / device / FIFO as OUT: refuse before the work
    if args.clamp_half and not args.half:
        raise IBLError("--clamp-half only applies with --half")
    if args.size is not None and args.size < 1:
        raise IBLError(f"--size must be a positive integer, got {args.size}")
    from ..progress import step
    from .radiance_args import tell

    with step(f"reading {src}"):  # a 16K probe takes seconds
        m = _load_any(src, args.negative, args.nonfinite)
    data = m.data
    tell(m.radiance)
    if data.ndim == 3 and args.layout == "cube" and args.method == "conservative":  # say what it costs first
        from ..limits import check_allocation

        n_out = args.size or max(1, data.shape[0] // 2)
        cost = resample.latlong_to_cube_cost(data.shape[0], n_out)
        if cost["seconds"] > 10 or cost["bytes"] > 2**30:
            print(f"converting a {data.shape[0]}-row lat-long map to {n_out}² cube faces: expect about "
                  f"{cost['seconds']:.0f} s and {cost['bytes'] / 2**30:.1f} GiB of memory (2-core machine; "
                  "--size sets a smaller cube)", file=sys.stderr, flush=True)
        check_allocation(cost["bytes"], f"converting to {n_out}² cube faces", "--size")
    with step(f"converting to {args.layout}" + (f" (size {args.size})" if args.size else "")):  # 16K → 2048²: ~20 s
        if data.ndim == 4:  # cube
            src_int = resample.integral_cube(data)
            if args.layout == "cube":
                out = data if args.size is None or args.size == data.shape[1] else resample.cube_to_cube(data, args.size)
            else:
                out = resample.cube_to_latlong(data, args.size or 2 * data.shape[1], method=args.method)
        else:
            src_int = resample.integral_latlong(data)
            if args.layout == "cube":
                out = resample.latlong_to_cube(data, args.size or max(1, data.shape[0] // 2), method=args.method)
            else:
                out = (data if args.size is None or args.size == data.shape[0]
                       else resample.latlong_to_latlong(data, args.size))
    dst_int = resample.integral_cube(out) if out.ndim == 4 else resample.integral_latlong(out)
    if (data.ndim == 4) != (out.ndim == 4) and args.method == "conservative":  # lat-long <-> cube: report the kernel's per-texel bound
        h, n = (out.shape[0], data.shape[1]) if out.ndim == 3 else (data.shape[0], out.shape[1])
        if out.ndim == 4:  # lat-long -> cube reduces big inputs block-wise first (exact)
            h //= resample.prereduce_factor(h, n)
        kern = resample.conservative_kernel(h, n)
        print(f"conservative kernel ({h}-row lat-long <-> {n}-face cube): energy of any single source texel "
              f"preserved to {max(kern.energy_error_ll, kern.energy_error_cube):.1e} (relative)")
    if dst.suffix.lower() in (".hdr", ".pic"):
        if args.layout != "latlong":
            raise IBLError(f"{dst}: Radiance .hdr output supports --layout latlong only")
        rgb = out[..., :3] if out.shape[-1] >= 3 else np.repeat(out, 3, axis=-1)
        write_hdr(dst, rgb)
        ptype = "rgbe"
    else:
        with warnings.catch_warnings():  # the clamping is reported below instead
            warnings.simplefilter("ignore", RuntimeWarning)
            rep = exr_io.write_envmap(dst, out, layout=args.layout, pixel_type="half" if args.half else "float",
                                      clamp_half=args.clamp_half, convention=args.convention)
        ptype = rep.pixel_type
        if rep.clamped_count:
            print(f"clamped {rep.clamped_count} value(s) to 65504 for half output (max original {rep.clamped_max:g})")
    shape = "x".join(str(s) for s in out.shape)
    rel = np.max(np.abs(dst_int / np.where(src_int > 0, src_int, 1.0) - np.where(src_int > 0, 1.0, 0.0)))
    print(f"wrote {dst}: {args.layout} {shape} ({ptype}); integral L domega relative change {rel:.2e} "
          f"(resampling residual, before file quantisation)")
    return 0


def register(sub) -> None:
    p = sub.add_parser(
        "convert",
        help="convert an environment map between cube, lat-long and file formats",
        description="Read IN (OpenEXR cube strip / lat-long / cross, or Radiance .hdr) and write OUT as an "
        "OpenEXR CUBE or LATLONG map (or a lat-long .hdr). Resampling is area-weighted and conserves "
        "the integral of L dω (the relative change is printed).",
    )
    p.add_argument("input", metavar="IN", help="input file (.exr cube strip / lat-long / cross, .hdr)")
    p.add_argument("output", metavar="OUT", help="output file (.exr, or .hdr for --layout latlong)")
    p.add_argument("--layout", choices=("cube", "latlong"), required=True, help="output layout")
    p.add_argument("--size", type=int, default=None,
                   help="output face size N (cube) or height H (lat-long); default keeps the texel density")
    p.add_argument("--convention", choices=("openexr", "opengl"), default="openexr",
                   help="face orientation written to a cube file (opengl files carry no envmap attribute)")
    p.add_argument("--method", choices=("conservative", "gather"), default="conservative",
                   help="lat-long <-> cube resampling: balanced kernel conserving every texel's energy "
                   "(default) or destination supersampling (ibl_ref.environment.resample)")
    p.add_argument("--half", action="store_true", help="write 16-bit half floats (default 32-bit float)")
    p.add_argument("--clamp-half", action="store_true",
                   help="with --half, clamp values above 65504 instead of failing (reported)")
    add_radiance_args(p)
    p.set_defaults(func=cmd_convert)

    i = sub.add_parser(
        "info",
        help="print layout, size, channels and radiance statistics of an environment map",
        description="Print layout, size, channels, pixel type, min/max radiance, its solid-angle weighted mean "
        "and the integral of L dω per channel (exact texel solid angles) of an OpenEXR or Radiance .hdr environment map, "
        "the counts of NaN, Inf and negative values in every channel, where the layout came from (envmap "
        "attribute or aspect ratio) and what the other commands would do with the file under --negative / "
        "--nonfinite. Never refuses a file it can decode.",
    )
    i.add_argument("file", metavar="FILE")
    add_radiance_args(i)
    i.set_defaults(func=cmd_info)
