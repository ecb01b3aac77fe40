"""``ibl-ref synth env|mesh``: write a deterministic synthetic environment map or test mesh."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..errors import IBLError

MESH_EXTENSIONS = ("obj", "ply", "stl", "glb", "off")


def parse_params(items) -> dict:
    """``["key=value", ...]`` → dict; values are JSON (``1e5``, ``[1,1,1]``, ``true``), ``1,2,3`` → list of
    numbers, anything else a string."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise IBLError(f"--param expects key=value, got {item!r}")
        key, val = item.split("=", 1)
        key = key.strip()
        if not key.isidentifier():
            raise IBLError(f"--param: invalid parameter name {key!r}")
        try:
            parsed = json.loads(val)
        except json.JSONDecodeError:
            try:
                parsed = [float(x) for x in val.split(",")] if "," in val else val
            except ValueError:
                parsed = val
        out[key] = parsed
    return out


def cmd_synth_env(args) -> int:
    import numpy as np

    from ..synthetic import synthetic_envs as se
    from ..atomic import atomic_path
    from ..environment.envmap import cube_solid_angles

    out = Path(args.out)
    if out.suffix.lower() not in (".exr", ".npy"):
        raise IBLError(f"OUT {out}: synth env writes OpenEXR (.exr) or NumPy (.npy) files; use one of these extensions")
    from ..atomic import resolve_output

    resolve_output(out)  # a folder / device / FIFO as OUT: refuse before generating
    params = parse_params(args.param)
    cube = se.make_env(args.name, args.size, **params)
    if out.suffix.lower() == ".npy":
        with atomic_path(out) as tmp:
            with open(tmp, "wb") as fh:
                np.save(fh, cube, allow_pickle=False)
    else:
        from ..environment.exr_io import write_envmap

        write_envmap(out, cube, layout="cube", pixel_type=args.pixel_type, clamp_half=args.clamp_half)
    integral = (cube * cube_solid_angles(args.size)[..., None]).sum(axis=(0, 1, 2))
    print(f"{args.name}: 6x{args.size}x{args.size} cube, max {cube.max():.6g}, "
          f"integral L dw (sr) = {', '.join(f'{v:.6g}' for v in integral)} -> {out}")
    return 0


def cmd_synth_mesh(args) -> int:
    from ..synthetic import synthetic_meshes as sm
    from ..atomic import atomic_path

    out = Path(args.out)
    ext = out.suffix.lower().lstrip(".")
    if ext not in MESH_EXTENSIONS:
        raise IBLError(f"{out}: unsupported mesh format {ext!r}; use one of {', '.join(MESH_EXTENSIONS)}")
    mesh = sm.make_mesh(args.name, **parse_params(args.param))
    with atomic_path(out) as tmp:
        mesh.export(str(tmp), file_type=ext)
    print(f"{args.name}: {len(mesh.faces)} triangles, {len(mesh.vertices)} vertices, "
          f"watertight={mesh.is_watertight}, bounds {mesh.bounds.tolist()} -> {out}")
    return 0


def register(sub) -> None:
    from ..synthetic import synthetic_envs as se
    from ..synthetic import synthetic_meshes as sm

    p = sub.add_parser(
        "synth",
        help="write a synthetic environment map (EXR cube) or test mesh",
        description="Deterministic synthetic data: 'ibl-ref synth env NAME OUT.exr' or 'ibl-ref synth mesh NAME OUT.obj'.",
    )
    ss = p.add_subparsers(dest="synth_kind", metavar="{env,mesh}")
    e = ss.add_parser(
        "env",
        help="synthetic environment map",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Write a synthetic cube map (6xNxN RGB float, OpenEXR CUBE layout; '.npy' writes the raw "
        "(6,N,N,3) array).  Parameters are passed as --param key=value (JSON values: 1e5, [1,1,1], true; "
        "'1,1,1' also works).\n\nGenerators:\n" + se.generator_help(),
    )
    e.add_argument("name", choices=se.ENV_NAMES, help="generator name")
    e.add_argument("out", help="output file (.exr, or .npy)")
    e.add_argument("--size", type=int, default=64, help="face size N (default 64)")
    e.add_argument("--param", action="append", metavar="KEY=VALUE", help="generator parameter (repeatable)")
    e.add_argument("--pixel-type", choices=("float", "half"), default="float", help="EXR pixel type (default float)")
    e.add_argument("--clamp-half", action="store_true", help="with --pixel-type half: clamp values > 65504")
    e.set_defaults(func=cmd_synth_env)

    m = ss.add_parser(
        "mesh",
        help="synthetic test mesh",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Write a generated test mesh (+Y up, standing on y=0); the format follows the extension ("
        + ", ".join(MESH_EXTENSIONS) + ").\n\nMeshes:\n" + sm.mesh_help(),
    )
    m.add_argument("name", choices=sm.MESH_NAMES, help="mesh name")
    m.add_argument("out", help="output file")
    m.add_argument("--param", action="append", metavar="KEY=VALUE", help="generator parameter (repeatable)")
    m.set_defaults(func=cmd_synth_mesh)

    def _no_kind(args):
        p.print_help()
        return 2

    p.set_defaults(func=_no_kind)
