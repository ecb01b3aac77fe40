"""``ibl-ref judge``: take a prefiltered GGX (or Phong) cube-map chain as users have it and say what is wrong with it.

``ibl-ref judge CHAIN --env ENV --mapping NAME [--lobe ggx|phong] [--mirrored] [--rtol 1e-3] [--out DIR]
[--sphere-size 32]``.  CHAIN is a folder of Filament cmgen's per-face level files (``m<ℓ>_<face>.exr`` / ``.hdr``)
or one KTX 1 / DDS cube map; ENV the environment it was made from (resampled to the chain's base face size,
integral-preserving); ``--mapping`` the chain's declared MIP → roughness mapping.  The work is
:func:`ibl_ref.prefilter.judge.judge` and its files :func:`ibl_ref.prefilter.judge.write_report` (DIR, default
``CHAIN_judge`` beside the chain: ``judge_levels.csv``, ``judge_shading.csv``, ``judge.json``, ``judge_report.md``,
``judge_levels.png``; a new or empty folder, or one holding only a previous judge's files).  Every bad input — a
missing file, inconsistent level sizes, a compressed container, an unknown mapping or lobe, an unwritable or
foreign DIR — is one line before anything is written.

The sphere's exact reference belongs to the rendering layer, which sits above the prefilter package the judge lives
in: :class:`ibl_ref.rendering.judge_shading.SphereShading` hands it to the judge (the orthographic sphere of
:func:`ibl_ref.rendering.sphere_render.orthographic_sphere` and the exact unoccluded integral of
:func:`ibl_ref.rendering.unoccluded_reference.integrate`).
"""

from __future__ import annotations

import time
from pathlib import Path

from .radiance_args import add_radiance_args


def cmd_judge(args) -> int:
    from ..atomic import refuse_overwriting_inputs
    from ..limits import check_rtol
    from ..prefilter import judge as J
    from ..rendering.judge_shading import SphereShading
    from ..progress import step
    from .radiance_args import load_env, policy

    t0 = time.perf_counter()
    J.check_mapping(args.mapping)
    J.check_lobe(args.lobe)
    rtol = check_rtol(args.rtol, "--rtol")
    out = Path(args.out) if args.out is not None else J.default_out_dir(args.chain)
    J.check_out_dir(out)  # before reading anything: a foreign or unwritable DIR is refused first
    with step(f"reading the chain {args.chain}"):
        chain = J.read_chain(args.chain, mirrored=args.mirrored, **policy(args))
    n = chain.levels[0].shape[1]
    env, radiance = load_env(args, args.env, n)
    refuse_overwriting_inputs({"CHAIN": args.chain, "--env": args.env}, [("--out", out / f) for f in J.OUTPUT_FILES])
    inputs = {"chain": str(args.chain), "layout": chain.layout, "files": [str(p) for p in chain.files],
              "mirrored": bool(args.mirrored), "env": str(args.env), "env_radiance": radiance,
              "command": "ibl-ref judge " + " ".join(_argv(args)), "read_s": time.perf_counter() - t0}
    res = J.judge(chain.levels, env, args.mapping, lobe=args.lobe, rtol=rtol, fit=not args.no_fit,
                  fit_size=args.fit_size, shading=None if args.no_sphere else SphereShading(),
                  sphere_size=args.sphere_size, kernel=args.kernel, inputs=inputs, progress=True)
    paths = J.write_report(res, out, keep=[args.chain, args.env])
    for q in res["levels"]:
        fit = ("" if q["fitted_roughness"] is None else f", holds roughness {q['fitted_roughness']:.3g}")
        print(f"level {q['level']}: {q['face_size_texels']}², declared roughness {q['declared_roughness']:.3g}{fit}"
              f" ({q['roughness_holds']}), rel. L1 {100 * (q['rel_l1_frac'] or 0):.3g} %, seams "
              f"{'flagged' if q['seam_flagged'] else 'no'}, fireflies {q['firefly_texels']}")
    for q in res["shading"]:
        print(f"sphere at roughness {q['roughness']:g}: this chain {100 * q['rel_l1_chain_vs_reference_frac']:.3g} %, "
              f"the exact chain {100 * q['rel_l1_exact_chain_vs_reference_frac']:.3g} % rel. L1")
    print(f"total {time.perf_counter() - t0:.1f} s; wrote {len(paths)} files into {out}")
    return 0


def _argv(args) -> list:
    words = [str(args.chain), "--env", str(args.env), "--mapping", args.mapping, "--lobe", args.lobe,
             "--rtol", format(args.rtol, "g"), "--sphere-size", str(args.sphere_size), "--fit-size",
             str(args.fit_size)]
    return words + [f for f, on in (("--mirrored", args.mirrored), ("--no-fit", args.no_fit),
                                    ("--no-sphere", args.no_sphere)) if on] + \
        (["--out", str(args.out)] if args.out is not None else [])


def register(sub) -> None:
    from ..prefilter.karis2013 import ROUGHNESS_MAPPINGS

    names = ", ".join(tuple(ROUGHNESS_MAPPINGS))
    p = sub.add_parser(
        "judge",
        help="judge a prefiltered GGX / Phong cube-map chain (cmgen folder, KTX, DDS) against the exact prefilter",
        description=(
            "Compare every level of a prefiltered cube-map chain with the exact prefilter of its environment at the "
            "roughness its declared --mapping gives the level: the error (rel. L1, p99, max, bias), the roughness "
            "the level really holds (a fit), the energy it keeps, seams along the face edges and fireflies; and "
            "what the chain does to an orthographic sphere shaded with the split sum, against the exact chain and "
            "the exact unoccluded shading. Writes judge_levels.csv, judge_shading.csv, judge.json, "
            "judge_report.md (a one-page report) and judge_levels.png into --out."
        ),
    )
    p.add_argument("chain", metavar="CHAIN",
                   help="a folder of cmgen level files m<level>_<face>.exr / .hdr (faces px nx py ny pz nz), or a "
                        ".ktx / .dds cube map with its MIP levels")
    p.add_argument("--env", required=True, metavar="ENV",
                   help="the environment the chain was made from (OpenEXR cube / lat-long / cross, .hdr); "
                        "resampled to the chain's base face size")
    p.add_argument("--mapping", required=True, metavar="NAME",
                   help=f"the chain's declared MIP -> roughness mapping: {names} (cmgen: filament)")
    p.add_argument("--lobe", default="ggx", metavar="ggx|phong",
                   help="what the levels hold: the GGX n = v = r prefilter (default) or Phong lobe averages (the "
                        "exponent of each level's roughness, TV-optimal mapping)")
    p.add_argument("--mirrored", action="store_true",
                   help="the chain is x-mirrored, as cmgen writes it without --no-mirror: mirror it back")
    p.add_argument("--rtol", type=float, default=1e-3,
                   help="tolerance of the exact prefilter at every texel (default 1e-3)")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="output folder (default CHAIN_judge beside the chain); new, empty, or a previous judge's")
    p.add_argument("--sphere-size", type=int, default=32, metavar="PX",
                   help="pixels across the shaded sphere (default 32: 812 pixels; its exact reference costs about 40 ms "
                        "a pixel and roughness on 2 cores)")
    p.add_argument("--fit-size", type=int, default=32, metavar="M",
                   help="largest face size of the roughness fit's comparison (default 32)")
    p.add_argument("--no-fit", action="store_true", help="do not fit the roughness each level holds")
    p.add_argument("--no-sphere", action="store_true", help="do not shade the sphere")
    p.add_argument("--kernel", choices=("auto", "numpy", "compiled"), default=None,
                   help="inner loops of the exact prefilters (default $IBL_REF_KERNEL or auto)")
    add_radiance_args(p)
    p.set_defaults(func=cmd_judge)
