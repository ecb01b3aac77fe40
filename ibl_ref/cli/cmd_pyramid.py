"""``ibl-ref pyramid IN OUT``: build the Knuth et al. (2014) filter pyramid and write it as a multi-part EXR."""

from __future__ import annotations

import json


def cmd_pyramid(args) -> int:
    from ..atomic import refuse_overwriting_inputs, resolve_output
    from ..errors import IBLError
    from ..environment.exr_io import write_pyramid
    from ..knuth2014.filters import kernel_taps
    from ..knuth2014.pyramid import build_pyramid, pyramid_energy
    from ..progress import step
    from .radiance_args import load_env

    refuse_overwriting_inputs({"IN": args.input}, {"OUT": args.output})
    resolve_output(args.output)  # a folder / device / FIFO as OUT: refuse before the work
    try:
        kernel_taps(args.kernel)
    except IBLError as exc:
        raise IBLError(f"--kernel: {exc}") from None
    cube, radiance = load_env(args, args.input, args.size)
    with step(f"{args.kernel} pyramid of {cube.shape[1]}² faces"):
        pyr = build_pyramid(cube, kernel=args.kernel, order=args.order, seam=args.seam)
    write_pyramid(args.output, pyr.levels, pixel_type=args.pixel_type, clamp_half=args.clamp_half)
    drift = [max(abs(x) for x in r["rel_drift"]) for r in pyramid_energy(pyr)]
    print(json.dumps({"output": str(args.output), "levels": pyr.n_levels, "base_size": pyr.base_size,
                      "kernel": pyr.kernel, "order": pyr.order, "seam": pyr.seam,
                      "max_rel_energy_drift": max(drift), "radiance": radiance}, indent=1))
    return 0


def register(sub) -> None:
    from ..knuth2014.filters import KERNELS, SEAM_MODES
    from ..knuth2014.pyramid import ORDERS

    p = sub.add_parser(
        "pyramid",
        help="build the 5x5 filter pyramid (Knuth 2014 Fig. 2) of an environment map, write a multi-part EXR",
        description=(
            "Alternating 2x2 shrink and separable 5x5 filter down to 1x1 faces; level 0 is the input (mirror), "
            "the last level the diffuse end. Output: one EXR part per level (OpenEXR CUBE strips). "
            "Face sizes must be powers of two (use --size to resample)."
        ),
    )
    p.add_argument("input", help="environment map (EXR cube/lat-long, .hdr, cross)")
    p.add_argument("output", help="output multi-part .exr")
    p.add_argument("--kernel", default="sqrtcos",
                   help=f"5-tap filter: {', '.join(KERNELS)} or cos^k (default sqrtcos, the paper's choice)")
    p.add_argument("--order", default="shrink_then_filter", choices=ORDERS, help="default shrink_then_filter")
    p.add_argument("--seam", default="neighbour", choices=SEAM_MODES,
                   help="edge handling: neighbour faces (paper) or per-face clamp (default neighbour)")
    p.add_argument("--size", type=int, default=None, help="resample to this power-of-two face size first")
    p.add_argument("--pixel-type", default="float", choices=("float", "half"), help="EXR pixel type")
    p.add_argument("--clamp-half", action="store_true", help="clamp values above the fp16 maximum when writing half")
    from .radiance_args import add_radiance_args

    add_radiance_args(p)
    p.set_defaults(func=cmd_pyramid)
