"""``ibl-ref convolve`` (Phong-lobe convolution with error bounds) and ``ibl-ref irradiance`` (Kán Ed map).

Output naming of ``convolve``: one OpenEXR CUBE file per exponent, named like OUT with ``_s{S}``
inserted before the extension (``S`` printed with ``%g``; ``inf`` for the mirror), e.g.
``out.exr --exponent 16 --exponent 2.5`` → ``out_s16.exr``, ``out_s2.5.exr``; plus a JSON sidecar
``out.json`` (OUT with the extension replaced by ``.json``) holding, per exponent, the method used, the
kind of bound (rigorous / rounding) and its max / mean / 99th percentile, and the timings.  The sidecar and the
``_s{S}`` files replace only files that the previous run for the same OUT wrote (listed in its ``out.json``); any
other file of those names is refused before the work (:func:`ibl_ref.atomic.check_side_files`).
"""

from __future__ import annotations

import math
from pathlib import Path

from ..errors import IBLError
from .radiance_args import add_radiance_args


def exponent_path(out, s) -> Path:
    """``OUT`` with ``_s{S}`` inserted before the extension (``S`` via ``%g``, ``inf`` for the mirror)."""
    out = Path(out)
    tag = "inf" if math.isinf(s) else format(float(s), "g")
    return out.with_name(f"{out.stem}_s{tag}{out.suffix or '.exr'}")


def _exponent(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise IBLError(f"--exponent: not a number: {text!r}") from None
    if math.isinf(v) and text.strip().lower().lstrip("+") not in ("inf", "infinity"):
        raise IBLError(f"--exponent: {text} overflows float64; write 'inf' for the mirror")
    if not (v >= 1):  # also NaN
        raise IBLError(f"--exponent: the Phong exponent must be >= 1 or 'inf' (mirror), got {text}")
    from ..groundtruth.convolution_args import check_exponent

    try:
        return check_exponent(v)  # (at most 2^30)
    except IBLError as exc:
        raise IBLError(f"--exponent: {exc}") from None


def cmd_convolve(args) -> int:
    from ..atomic import OutputSet, check_side_files, refuse_overwriting_inputs
    from ..groundtruth.convolve import convolve
    from ..limits import check_rtol
    from ..environment.exr_io import write_envmap
    from .radiance_args import load_env

    exps = [_exponent(e) for e in args.exponent]
    check_rtol(args.rtol, "--rtol")  # (before the file is read)
    side = Path(args.output).with_suffix(".json")
    maps = [exponent_path(args.output, s) for s in exps]
    refuse_overwriting_inputs({"IN": args.input}, [("OUT", side)] + [("OUT", m) for m in maps])
    check_side_files(side, maps, "outputs", "OUT")  # never replace a file the user did not name
    from ..executors import resolve_executor

    executor, client = resolve_executor(args.scheduler)  # an unreachable scheduler fails before the file is read
    try:
        cube, radiance = load_env(args, args.input, args.input_size)
        from ..progress import step

        with step(f"convolving {cube.shape[1]}² faces with {len(exps)} exponent(s), method {args.method}"):
            res = convolve(
                cube, exps, method=args.method, rtol=args.rtol, out_size=args.size, normalized=not args.unnormalized,
                workers=args.workers, backend=args.parallel, executor=executor, kernel=args.kernel,
            )
    finally:
        if client is not None:
            client.close()
    written = []
    outs = OutputSet(side, owned_key="outputs", keep=[args.input])  # all files or none; stale _s* removed
    with outs:
        for s, m in res.maps.items():
            p = exponent_path(args.output, s)
            write_envmap(outs.path(p), m, layout="cube")
            written.append(str(p))
        summary = res.summary()
        summary.update(
            {
                "workers": res.info.get("workers"),
                "kernel": res.info.get("kernel"),
                "parallel_backend": res.info.get("backend"),
                "input": str(args.input),
                "outputs": written,
                "normalized": not args.unnormalized,
                "rtol": args.rtol,
                "method_requested": args.method,
                "face_size_in": int(cube.shape[1]),
                "face_size_out": int(next(iter(res.maps.values())).shape[1]),
                "radiance": radiance,
            }
        )
        outs.commit(summary)
    for e in summary["exponents"]:
        b = e["rel_bound_max"]
        print(f"s={e['s']}: {e['method']:6s} rel. bound max {b if b is not None else 'inf'} ({e['bound_kind']})")
    print(f"total {res.timings_s['total']:.2f} s ({res.info.get('kernel')} kernels); wrote {len(written)} file(s) "
          f"and {side}")
    return 0


def cmd_irradiance(args) -> int:
    from ..environment.exr_io import write_envmap
    from ..groundtruth.kan2015 import irradiance_map
    from .radiance_args import load_env

    from ..atomic import refuse_overwriting_inputs

    refuse_overwriting_inputs({"IN": args.input}, {"OUT": args.output})
    from ..progress import step

    cube, _ = load_env(args, args.input, args.input_size)
    with step(f"irradiance of {cube.shape[1]}² faces"):
        ed = irradiance_map(cube, quadrature=args.quadrature, out_size=args.size)
    write_envmap(args.output, ed, layout="cube")
    print(f"wrote {args.output} (Kán et al. 2015 Ed map, {ed.shape[1]}² faces)")
    return 0


def register(sub) -> None:
    p = sub.add_parser(
        "convolve",
        help="convolve an environment map with Phong lobes cos^s (Knuth 2014 Eq. 4), with error bounds",
        description=(
            "Compute the Phong-lobe average sum L cos^s dw / sum cos^s dw (or, with --unnormalized, the "
            "literal Eq. 4 sum) for every output texel and each --exponent S. Methods: exact (every "
            "texel), sh (spherical harmonics + exact gather of the sun, rigorous bound), sparse "
            "(truncated gather, rigorous bound), auto (per exponent the cheapest method whose bound "
            "meets --rtol). Writes OUT with _s{S} inserted before the extension (one OpenEXR cube per "
            "exponent, e.g. out_s16.exr) and a JSON sidecar OUT.json with methods, bounds and timings."
        ),
    )
    p.add_argument("input", metavar="IN", help="environment map (OpenEXR cube / lat-long / cross, .hdr)")
    p.add_argument("output", metavar="OUT", help="output name; _s{S} is inserted before the extension")
    p.add_argument("--exponent", "-s", action="append", required=True, metavar="S",
                   help="Phong exponent s >= 1 (repeatable; 'inf' = mirror)")
    p.add_argument("--method", choices=("auto", "exact", "sh", "sparse", "moment"), default="auto",
                   help="auto (default): cheapest method whose bound meets --rtol; moment: exact for s = 1, 2 only")
    p.add_argument("--rtol", type=float, default=1e-3, help="target per-texel relative error (default 1e-3)")
    p.add_argument("--unnormalized", action="store_true",
                   help="literal Eq. 4 sum (value 2π/(s+1) for L=1) instead of the lobe average")
    p.add_argument("--size", type=int, default=None, help="output face size (default: input face size)")
    p.add_argument("--input-size", type=int, default=None, help="resample the input to this face size first")
    p.add_argument("--workers", type=int, default=None, metavar="W",
                   help="parallel workers (1 = serial; default $IBL_REF_WORKERS or min(2, CPUs)); results "
                        "are bit-for-bit identical for every W")
    p.add_argument("--kernel", choices=("auto", "numpy", "compiled"), default=None,
                   help="inner loops: numpy (the reference), compiled (numba, pip install 'ibl_ref[fast]'; cached "
                        "after the first run) or auto (compiled when numba is installed and the run is big enough "
                        "to pay for loading it); default $IBL_REF_KERNEL or auto. Both give rigorous bounds")
    p.add_argument("--parallel", choices=("auto", "process", "thread"), default="auto",
                   help="how W > 1 workers run: forked processes or threads (auto: processes when possible)")
    add_radiance_args(p)
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the jobs on a Dask cluster (e.g. tcp://host:8786; needs pip install '.[dask]'); "
                        "the maps are bit-for-bit those of a local run")
    p.set_defaults(func=cmd_convolve)

    q = sub.add_parser(
        "irradiance",
        help="Kán et al. 2015 diffuse map Ed = (1/π) ∫ L max(n·ω,0) dω as an OpenEXR cube",
        description="Exact per-texel irradiance/π map (Kán et al. 2015, Eq. 3-4), exact texel solid angles.",
    )
    q.add_argument("input", metavar="IN")
    q.add_argument("output", metavar="OUT")
    q.add_argument("--quadrature", choices=("literal", "normalized"), default="literal",
                   help="literal (1/π) sum, or divided by the discrete lobe weight (see ibl_ref.groundtruth.kan2015)")
    q.add_argument("--size", type=int, default=None, help="output face size (default: input face size)")
    q.add_argument("--input-size", type=int, default=None, help="resample the input to this face size first")
    add_radiance_args(q)
    q.set_defaults(func=cmd_irradiance)
