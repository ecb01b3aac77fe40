"""``ibl-ref convert`` and ``ibl-ref info``: environment-map file conversion and inspection."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..errors import IBLError

OUT_SUFFIXES = (".exr", ".hdr", ".pic")  #: file types ``convert`` writes


def _load_any(path: Path):
    """(data, layout, channels, pixel_type, file_format, extra) of any supported file without resampling."""
    from .. import exr_io, resample
    from ..hdr_io import read_hdr, read_hdr_header

    if path.suffix.lower() in (".hdr", ".pic", ".rgbe"):
        img = read_hdr(path)
        hdr = read_hdr_header(path)
        layout = exr_io.infer_layout(img.shape[0], img.shape[1], None, str(path))
        extra = {"exposure_product": hdr["exposure"], "orientation": f"{hdr['major']} {hdr['minor']}"}
        ptype, fmt, chans = "rgbe", "Radiance RGBE", ("R", "G", "B")
    else:
        img, chans, ptype, header = exr_io.read_image(path)
        layout = exr_io._declared(header, str(path))
        layout = exr_io.infer_layout(img.shape[0], img.shape[1], layout, str(path))
        extra = {"envmap_attribute": header.get("envmap", "-"), "convention": header.get("iblref_convention", "-")}
        fmt = "OpenEXR"
        conv = exr_io._convention(header, None, str(path)) if layout == "cube" else "openexr"
        if conv != "openexr":
            from .. import envmap

            n = img.shape[1]
            img = envmap.convert_convention(img.reshape(6, n, n, -1), conv, "openexr")
    if layout == "cube":
        n = img.shape[-2]
        data = img.reshape(6, n, n, img.shape[-1])
    elif layout in ("hcross", "vcross"):
        data = resample.cross_to_cube(img, layout)
    else:
        data = img
    return data, layout, chans, ptype, fmt, extra


def cmd_info(args) -> int:
    from .. import resample

    path = Path(args.file)
    data, layout, chans, ptype, fmt, extra = _load_any(path)
    if data.ndim == 4:
        n = data.shape[1]
        integ = resample.integral_cube(data)
        size = f"6 faces of {n} x {n}" + (f" (read from a {layout})" if layout != "cube" else "")
    else:
        integ = resample.integral_latlong(data)
        size = f"{data.shape[1]} x {data.shape[0]} (W x H)"
    flat = data.reshape(-1, data.shape[-1])
    print(f"file:       {path}")
    print(f"format:     {fmt}  pixel type: {ptype}")
    print(f"layout:     {layout}  size: {size}")
    print(f"channels:   {','.join(chans)}")
    for k, v in extra.items():
        print(f"{k + ':':18s}{v}")
    print("channel     min           max           mean          integral_L_domega_(sr)")
    for i, c in enumerate(chans):
        col = flat[:, i]
        print(f"{c:11s} {col.min():<13.6g} {col.max():<13.6g} {col.mean():<13.6g} {float(np.atleast_1d(integ)[i]):<.9g}")
    # readers reject NaN/Inf/negative radiance, so reaching this line means the check passed
    print("check:      no NaN, no Inf, no negative radiance")
    return 0


def cmd_convert(args) -> int:
    from .. import exr_io, resample
    from ..hdr_io import write_hdr

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
    data, layout, chans, _, _, _ = _load_any(src)
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
            out = data if args.size is None or args.size == data.shape[0] else resample.latlong_to_latlong(data, args.size)
    dst_int = resample.integral_cube(out) if out.ndim == 4 else resample.integral_latlong(out)
    if (data.ndim == 4) != (out.ndim == 4) and args.method == "conservative":  # lat-long <-> cube: report the kernel's per-texel bound
        h, n = (out.shape[0], data.shape[1]) if out.ndim == 3 else (data.shape[0], out.shape[1])
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
                   "(default) or destination supersampling (ibl_ref.resample)")
    p.add_argument("--half", action="store_true", help="write 16-bit half floats (default 32-bit float)")
    p.add_argument("--clamp-half", action="store_true",
                   help="with --half, clamp values above 65504 instead of failing (reported)")
    p.set_defaults(func=cmd_convert)

    i = sub.add_parser(
        "info",
        help="print layout, size, channels and radiance statistics of an environment map",
        description="Print layout, size, channels, pixel type, min/max/mean radiance and the integral of "
        "L dω per channel (exact texel solid angles) of an OpenEXR or Radiance .hdr environment map. "
        "Files with NaN, Inf or negative radiance are reported as errors.",
    )
    i.add_argument("file", metavar="FILE")
    i.set_defaults(func=cmd_info)
