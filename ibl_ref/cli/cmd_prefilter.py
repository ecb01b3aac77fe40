"""``ibl-ref prefilter``: the exact ``n = v = r`` GGX level chain of an environment, with its per-level bound.

Level ℓ of L (face size ``max(N >> ℓ, --min-level-size)``) holds the split sum's prefiltered radiance (Karis 2013,
Eq. 8) at the roughness of the level under ``--mapping`` (:func:`ibl_ref.prefilter.karis2013.roughness_of_level`:
``filament`` — Filament's cmgen and run time, lod = r(2 − r) — or ``linear``); level 0 is the source (roughness 0,
the mirror).  Every other level is the exact prefilter within ``--rtol`` at every texel
(:func:`ibl_ref.groundtruth.ggx_convolution.convolve_ggx_levels`, one source tree for the chain).

Output naming (``--layout``): ``cube`` (default), one OpenEXR cube per level, OUT with ``_l{ℓ}`` inserted before
the extension (``chain.exr`` → ``chain_l0.exr`` … ``chain_l4.exr``) and the JSON sidecar OUT.json; ``cmgen``, OUT
is a folder that gets Filament's cmgen layout, ``m<ℓ>_<face>.exr`` per level and face (faces px nx py ny pz nz in
the OpenGL orientation, float32 RGB: :func:`ibl_ref.prefilter.cmgen_peer.write_level`), and ``OUT/prefilter.json``;
``ktx`` / ``dds``, OUT is one KTX 1 / DDS cube map (its name must end in ``.ktx`` / ``.dds``) holding every level
as its MIP chain (:func:`ibl_ref.environment.cube_containers.write_ktx1` /
:func:`~ibl_ref.environment.cube_containers.write_dds`: RGBA16F by default, ``--dtype float32`` for RGBA32F; a
float16 overflow is refused naming the level), and the sidecar OUT.json with OUT's whole name (``chain.ktx.json``:
a KTX and a DDS of one chain keep their own).  The cube and cmgen layouts store float32.  The JSON holds the
mapping, the storage type and the roughness, face size, largest bound and seconds of every level.  Like
``convolve``, the set replaces only files the previous run for the same OUT wrote (and OUT itself in the container
layouts, which the user named), and is written whole or not at all (:class:`ibl_ref.atomic.OutputSet`).
"""

from __future__ import annotations

import time
from pathlib import Path

from ..errors import IBLError
from .radiance_args import add_radiance_args


def level_path(out, level: int) -> Path:
    """``OUT`` with ``_l{level}`` inserted before the extension."""
    out = Path(out)
    return out.with_name(f"{out.stem}_l{int(level)}{out.suffix or '.exr'}")


def _cube_layout(out, n_levels):
    """(side file, [[file of level ℓ]], files the user named): OUT_l{ℓ}.exr cubes and OUT.json."""
    return Path(out).with_suffix(".json"), [[level_path(out, lv)] for lv in range(n_levels)], []


def _cmgen_layout(out, n_levels):
    """(side file, [[6 files of level ℓ]], files the user named): cmgen's OUT/m{ℓ}_{face}.exr and
    OUT/prefilter.json."""
    from ..prefilter.cmgen_peer import FACES, level_file

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise IBLError(f"OUT {out} is a file; --layout cmgen writes a folder")
    return out / "prefilter.json", [[level_file(out, lv, f) for f in FACES] for lv in range(n_levels)], []


def _container_out(out, layout: str) -> Path:
    """OUT of a container layout, checked: its name must end in .ktx / .dds."""
    from ..environment.cube_containers import CONTAINERS

    out = Path(out)
    if out.suffix.lower() != CONTAINERS[layout]:
        raise IBLError(f"OUT {out}: --layout {layout} writes one {CONTAINERS[layout]} file; name it so")
    return out


def _container_layout(kind):
    """The layout of one KTX 1 / DDS file OUT holding every level, and OUT.{ktx,dds}.json."""

    def layout(out, n_levels):
        out = _container_out(out, kind)
        return out.with_name(out.name + ".json"), [[out]] + [[] for _ in range(n_levels - 1)], [out]

    return layout


def _write_cube(files, maps, dtype):
    from ..environment.exr_io import write_envmap

    # uncompressed: ZIP makes float32 radiance 2 % smaller at twice the write time (a 256² chain: 6.19 MB in 0.18 s
    # against 6.33 MB in 0.08 s)
    for level_files, m in zip(files, maps):
        write_envmap(level_files[0], m, layout="cube", compression="none")


def _write_cmgen(files, maps, dtype):
    from ..prefilter.cmgen_peer import write_level

    for level_files, m in zip(files, maps):
        write_level(level_files, m)


def _write_ktx(files, maps, dtype):
    from ..environment.cube_containers import write_ktx1

    write_ktx1(files[0][0], maps, dtype=dtype)


def _write_dds(files, maps, dtype):
    from ..environment.cube_containers import write_dds

    write_dds(files[0][0], maps, dtype=dtype)


#: --layout: (side file, the files of each level, the files the user named), and how the levels are written
LAYOUTS = {"cube": _cube_layout, "cmgen": _cmgen_layout, "ktx": _container_layout("ktx"),
           "dds": _container_layout("dds")}
WRITERS = {"cube": _write_cube, "cmgen": _write_cmgen, "ktx": _write_ktx, "dds": _write_dds}
#: the layouts that write one container file (``--dtype`` chooses their texels; the others store float32)
CONTAINER_LAYOUTS = ("ktx", "dds")
#: stored texel type → its relative rounding (round to nearest: half an ulp of a normal number)
STORAGE = {"float32": 2.0 ** -24, "float16": 2.0 ** -11}


def _power_of_two(v, name) -> int:
    if v < 1 or v & (v - 1):
        raise IBLError(f"{name} must be a power of two >= 1, got {v}")
    return v


def cmd_prefilter(args) -> int:
    import numpy as np

    from ..atomic import OutputSet, check_side_files, refuse_overwriting_inputs
    from ..groundtruth.ggx_convolution import LAST_INFO, convolve_ggx_levels
    from ..limits import check_rtol
    from ..prefilter.mip_mappings import get_mapping  # (not karis2013: it imports SciPy for its other routes)
    from ..progress import step
    from .radiance_args import load_env

    rtol = check_rtol(args.rtol, "--rtol")
    size = _power_of_two(args.size, "--size") if args.size is not None else None
    min_size = _power_of_two(args.min_level_size, "--min-level-size")
    if args.threads is not None and args.threads < 1:
        raise IBLError(f"--threads must be >= 1, got {args.threads}")
    container = args.layout in CONTAINER_LAYOUTS
    if args.dtype is not None and not container:
        raise IBLError(f"--dtype applies to --layout ktx and dds; --layout {args.layout} stores float32")
    dtype = args.dtype or ("float16" if container else "float32")
    if container:
        _container_out(args.output, args.layout)  # before reading IN
    t0 = time.perf_counter()
    cube, radiance = load_env(args, args.input, size)
    n = cube.shape[1]
    _power_of_two(n, "the face size of IN (give --size)")
    n_levels = max(2, n.bit_length() - max(min_size, 1).bit_length() + 1) if min_size < n else 1
    if n_levels < 2:
        raise IBLError(f"--min-level-size {min_size} leaves no level below the {n}² source")
    rough = [float(r) for r in get_mapping(args.mapping).roughness(np.arange(n_levels), n_levels)]
    sizes = [max(n >> lv, min_size) for lv in range(n_levels)]
    side, files, named = LAYOUTS[args.layout](args.output, n_levels)  # files[ℓ]: the file(s) of level ℓ
    paths = [p for level in files for p in level]
    refuse_overwriting_inputs({"IN": args.input}, [("OUT", side)] + [("OUT", p) for p in paths])
    # never replace a file the user did not name
    check_side_files(side, [p for p in paths if p not in named], "outputs", "OUT")
    # the levels of roughness 0 are the source itself (level 0 under every mapping but Unreal's, whose level 0 holds
    # its smallest roughness r0 > 0); every other level is filtered
    filtered = [lv for lv in range(n_levels) if rough[lv] > 0]
    if any(rough[lv] == 0 for lv in range(1, n_levels)):
        raise IBLError(f"mapping {args.mapping}: a level below the top has roughness 0")
    if container:  # no lobe average exceeds the source's maximum: refuse an overflow now
        from ..environment.cube_containers import check_storable

        check_storable(cube, dtype, f"{args.output}: level 0")
    t_read = time.perf_counter() - t0
    with step(f"prefiltering {n}² faces into {len(filtered)} GGX level(s), mapping {args.mapping}, rtol {rtol:g}"):
        out = convolve_ggx_levels(cube, [(rough[lv], sizes[lv]) for lv in filtered], rtol=rtol, kernel=args.kernel,
                                  threads=args.threads)
    info = dict(LAST_INFO)
    done = {lv: (m, float(b.max()), li["seconds"]) for lv, (m, b), li in zip(filtered, out, info["levels"])}
    maps = [done[lv][0] if lv in done else cube for lv in range(n_levels)]
    levels = [{"level": lv, "roughness": rough[lv], "face_size": sizes[lv],
               "rel_bound_max": done[lv][1] if lv in done else 0.0, "seconds": done[lv][2] if lv in done else 0.0}
              for lv in range(n_levels)]
    outs = OutputSet(side, owned_key="outputs", keep=[args.input], named=named, label="OUT")
    with outs:
        WRITERS[args.layout]([[outs.path(p) for p in level_files] for level_files in files],
                             maps, dtype)
        outs.commit({"input": str(args.input), "outputs": [str(p) for p in paths], "lobe": "ggx n = v = r",
                     "layout": args.layout, "mapping": args.mapping, "rtol": rtol,
                     "storage": {"dtype": dtype, "rel_rounding": STORAGE[dtype]}, "levels": levels,
                     "kernel": info.get("kernel"),
                     "radiance": radiance,
                     "seconds": {"read": t_read, "tree": info.get("tree_s"), "kernel_load": info.get("kernel_load_s"),
                                 "total": time.perf_counter() - t0}})
    for e in levels:
        if e["roughness"] == 0:
            continue
        print(f"level {e['level']}: roughness {e['roughness']:.4f}, {e['face_size']}² faces, rel. bound max "
              f"{e['rel_bound_max']:.2e} ({e['seconds']:.2f} s)")
    print(f"total {time.perf_counter() - t0:.2f} s ({info.get('kernel')} kernels); wrote {len(paths)} file(s) and "
          f"{side}")
    return 0


def register(sub) -> None:
    from ..prefilter.mip_mappings import ROUGHNESS_MAPPINGS

    p = sub.add_parser(
        "prefilter",
        help="the exact GGX (n = v = r) level chain of an environment, with a rigorous per-level bound",
        description=(
            "Prefilter an environment into a GGX MIP chain as engines store it for the split sum (Karis 2013): "
            "level l holds the n = v = r prefilter at the roughness of its level under --mapping ("
            + "; ".join(f"{k}: {v.engine}, {v.formula}" for k, v in ROUGHNESS_MAPPINGS.items())
            + "), each exact within --rtol at every texel; a level of roughness 0 (level 0 under every mapping but "
            "unreal's) is the source. Writes OUT with _l{l} inserted before the extension (one OpenEXR "
            "cube per level; --layout cmgen: cmgen's per-face files; --layout ktx / dds: one KTX 1 / DDS cube map "
            "OUT with every level as its MIP chain) and a JSON sidecar with the roughness, size and bound of every "
            "level."
        ),
    )
    p.add_argument("input", metavar="IN", help="environment map (OpenEXR cube / lat-long / cross, .hdr)")
    p.add_argument("output", metavar="OUT",
                   help="output name: with --layout cube, _l{level} is inserted before the extension; with --layout "
                        "cmgen, a folder; with --layout ktx / dds, the file (ending in .ktx / .dds)")
    p.add_argument("--layout", choices=tuple(LAYOUTS), default="cube",
                   help="cube (default): one OpenEXR cube per level, OUT_l{level}.exr, and OUT.json; cmgen: Filament "
                        "cmgen's files OUT/m{level}_{face}.exr (OpenGL faces px nx py ny pz nz, float32) and "
                        "OUT/prefilter.json; ktx / dds: one KTX 1 / DDS cube map OUT (faces +X -X +Y -Y +Z -Z, "
                        "OpenGL / Direct3D orientation) with every level as its MIP chain, and OUT.json beside it "
                        "(chain.ktx.json)")
    p.add_argument("--dtype", choices=("float16", "float32"), default=None,
                   help="texels of --layout ktx / dds: float16 (default; RGBA16F, what engines load; a value above "
                        "65504 is refused) or float32 (RGBA32F)")
    p.add_argument("--size", type=int, default=None, metavar="N",
                   help="face size of level 0 (a power of two; the input is resampled to it; default: its own)")
    p.add_argument("--min-level-size", type=int, default=16, metavar="M",
                   help="face size of the last level (default 16, cmgen's; 256² gives 5 levels)")
    p.add_argument("--mapping", choices=tuple(ROUGHNESS_MAPPINGS), default="filament",
                   help="roughness of each level (default filament)")
    p.add_argument("--rtol", type=float, default=1e-3, help="largest relative error per texel (default 1e-3)")
    p.add_argument("--kernel", choices=("auto", "numpy", "compiled"), default=None,
                   help="inner loops: numpy or compiled (numba); default $IBL_REF_KERNEL or auto")
    p.add_argument("--threads", type=int, default=None, metavar="T",
                   help="threads of the compiled kernels (default $IBL_REF_WORKERS or min(2, CPUs)); the maps do "
                        "not depend on it")
    add_radiance_args(p)
    p.set_defaults(func=cmd_prefilter)
