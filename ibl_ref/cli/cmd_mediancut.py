"""``ibl-ref mediancut`` and ``ibl-ref pem``: median-cut lights and partial environment maps of a file.

Thin layer over :func:`ibl_ref.knuth2014.median_cut.median_cut`, :func:`ibl_ref.knuth2014.pem.build_pems` and
:mod:`ibl_ref.knuth2014.sparse_pem` (Knuth et al. 2014, Sec. 3.1 and 4).
"""

from __future__ import annotations

from pathlib import Path

from ..errors import IBLError
from .radiance_args import add_radiance_args

VARIANT_HELP = (
    "per-face: the paper (N/6 regions per face, Debevec's recursion; N must be a multiple of 6); "
    "global: split the most energetic region anywhere; variance: Viriyothai & Debevec 2009 variance-minimising cut "
    "(global and variance: any N >= 6)"
)


def check_lights(n_lights: int, variant: str, option: str = "--lights") -> None:
    """The light count's rules of :func:`ibl_ref.knuth2014.median_cut.median_cut`, checked before any file is read:
    N >= 6 for every variant (regions never cross a cube edge), a multiple of 6 for ``per-face``."""
    from ..knuth2014.median_cut import per_face_counts

    if n_lights < 6:
        raise IBLError(f"{option}: n_lights must be >= 6 (regions never cross a cube edge, so each face holds >= 1); "
                       f"got {n_lights}")
    if variant == "per-face":
        try:
            per_face_counts(n_lights)
        except IBLError as exc:
            raise IBLError(f"{option}: {exc}") from None


def _load(path, size, args):
    from .radiance_args import load_env

    p = Path(path)
    if not p.exists():
        raise IBLError(f"{p}: no such file")
    return load_env(args, p, size)


def cmd_mediancut(args) -> int:
    from ..atomic import refuse_overwriting_inputs, resolve_output, write_json
    from ..knuth2014.median_cut import check_partition, energy_spread, median_cut
    from ..progress import step

    refuse_overwriting_inputs({"IN": args.input}, {"--out": args.out})
    resolve_output(args.out)  # a folder / device / FIFO as --out: refuse before the work
    check_lights(args.lights, args.variant)  # before the file is read and converted
    cube, radiance = _load(args.input, args.size, args)
    with step(f"median cut of {cube.shape[1]}² faces into {args.lights} regions"):
        ls = median_cut(cube, args.lights, args.variant)
    chk = check_partition(ls, cube)
    data = {
        "source": str(args.input),
        "face_size": ls.face_size,
        "variant": ls.variant,
        "n_lights": len(ls),
        "convention": "openexr (ibl_ref.environment.envmap); regions row0:row1, col0:col1 with exclusive ends",
        "luminance_weights": list(ls.luminance_weights),
        "energy_spread": energy_spread(ls),
        "partition_check": chk,
        "lights": ls.to_records(),
        "radiance": radiance,
    }
    write_json(args.out, data)
    sp = data["energy_spread"]
    print(f"{len(ls)} lights ({ls.variant}) from {args.input} (faces {ls.face_size}²) → {args.out}")
    print(f"region energy: max/min {sp['max_over_min']:.3g}, CV {sp['cv']:.3g}, {sp['n_zero_energy']} without energy; "
          f"Σ rgb vs ∫L dω: rel. err {chk['rgb_sum_rel_err']:.2e}")
    return 0


def cmd_pem(args) -> int:
    import numpy as np

    from ..atomic import OutputSet, output_folder
    from ..environment.exr_io import HALF_MAX, write_pyramid
    from ..knuth2014.filters import kernel_taps
    from ..knuth2014.median_cut import median_cut
    from ..knuth2014.pem import build_pems
    from ..progress import step, track

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise IBLError(f"--out {out}: exists and is not a folder")
    try:  # an unknown --kernel fails here, before any folder is created
        kernel_taps(args.kernel)
    except IBLError as exc:
        raise IBLError(f"--kernel: {exc}") from None
    check_lights(args.lights, args.variant)  # before the file is read and converted
    from ..atomic import check_side_files

    # pems.json and pem_NNN.exr inside --out: replaced only where the previous pem run wrote them
    check_side_files(out / "pems.json", [out / f"pem_{i:03d}.exr" for i in range(args.lights)], "files", "--out")
    cube, radiance = _load(args.input, args.size, args)
    with step(f"median cut of {cube.shape[1]}² faces into {args.lights} regions"):
        ls = median_cut(cube, args.lights, args.variant)
    # progress on stderr (ibl_ref.progress): a bar on a terminal, a status line at most every 10 s in a log
    pems = build_pems(cube, ls, kernel=args.kernel, order=args.order, seam=args.seam, dtype=np.float32,
                      progress=True)
    if args.pixel_type == "half":  # refuse before writing anything (pem has no clamping option)
        vmax = max(float(lev.max()) for lev in pems.levels)
        if vmax > HALF_MAX:
            raise IBLError(f"--pixel-type half: PEM values up to {vmax:g} exceed the largest half float "
                           f"({HALF_MAX:g}); use --pixel-type float")
    files = []
    rng = track(range(len(pems)), "writing PEMs", unit="file")
    # all or nothing; stale PEMs removed; a folder created for a failed run is removed again
    with output_folder(out, "--out folder"), OutputSet(out / "pems.json", owned_key="files", keep=[args.input]) as outs:
        for i in rng:
            p = out / f"pem_{i:03d}.exr"
            write_pyramid(outs.path(p), [lev[:, :, :, i, :] for lev in pems.levels], pixel_type=args.pixel_type)
            files.append(p.name)
        info = {"source": str(args.input), "face_size": pems.base_size, "n_pems": len(pems), "kernel": pems.kernel,
            "order": pems.order, "seam": pems.seam, "dense_nbytes_float32": pems.nbytes,
                "pixel_type": args.pixel_type, "files": files, "lights": ls.to_records(), "radiance": radiance}
        if args.sparse_report:
            from ..knuth2014.sparse_pem import sparsify

            sp = sparsify(pems, rtol=0.0)
            info["sparse_lossless_nbytes"] = sp.nbytes
            info["sparse_ratio"] = pems.nbytes / sp.nbytes
        outs.commit(info)
    print(f"{len(pems)} PEM pyramids ({pems.n_levels} levels, {pems.kernel}) → {out}/pem_*.exr "
          f"(in memory: {pems.nbytes / 2**20:.2f} MiB float32)")
    if args.sparse_report:
        print(f"sparse (lossless) storage: {info['sparse_lossless_nbytes'] / 2**20:.2f} MiB, "
              f"{info['sparse_ratio']:.1f}x smaller")
    return 0


def _common(p):
    p.add_argument("input", help="environment map (OpenEXR cube/lat-long, .hdr, cross; see 'ibl-ref' io commands)")
    p.add_argument("--lights", type=int, required=True, help="number of lights / regions N")
    p.add_argument("--variant", choices=("per-face", "global", "variance"), default="per-face", help=VARIANT_HELP)
    p.add_argument("--size", type=int, default=None, help="resample to this face size first (default: the file's)")
    add_radiance_args(p)


def register(sub) -> None:
    p = sub.add_parser(
        "mediancut",
        help="median-cut an environment map into N lights (JSON)",
        description="Partition the cube map into N regions of equal energy (luminance x exact solid angle; Debevec "
        "2008, per cube face as in Knuth et al. 2014) and write one light per region: direction (energy centroid), "
        "rgb (integral of L over the region), solid angle, face and region bounds.",
    )
    _common(p)
    p.add_argument("--out", required=True, help="output JSON file")
    p.set_defaults(func=cmd_mediancut)

    q = sub.add_parser(
        "pem",
        help="build the partial environment maps (one filter pyramid per median-cut region)",
        description="Median-cut the map, blacken everything outside each region and filter the copy into the "
        "Fig. 2 pyramid (Knuth et al. 2014 Sec. 4). Writes OUT/pem_NNN.exr (multi-part EXR, one part per level) "
        "and OUT/pems.json (lights, configuration, memory).",
    )
    _common(q)
    q.add_argument("--out", required=True, help="output folder")
    q.add_argument("--kernel", default="sqrtcos", help="5-tap filter: none, box, gauss, cos, sqrtcos (default), cos^k")
    q.add_argument("--order", default="shrink_then_filter", choices=("shrink_then_filter", "filter_then_shrink"))
    q.add_argument("--seam", default="neighbour", choices=("neighbour", "clamp", "neighbour_repad"))
    q.add_argument("--pixel-type", dest="pixel_type", default="float", choices=("float", "half"),
                   help="EXR pixel type (half overflows above 65504: an error unless the map is dim)")
    q.add_argument("--sparse-report", action="store_true", help="also report the lossless sparse storage size")
    q.set_defaults(func=cmd_pem)
