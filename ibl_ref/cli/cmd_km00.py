"""``ibl-ref km00-render``: the glossy teapot by Kautz & McCool (2000) fitted lobes, or by the exact reference.

Thin layer over :func:`ibl_ref.rendering.km00_render.render_single_method` (library:
:mod:`ibl_ref.lobes.prefiltered_lobes`).  No visibility (KM2000 has none).
"""

from __future__ import annotations

from pathlib import Path

from ..errors import IBLError

METHOD_HELP = ("reference: per-pixel exact filtering over the environment texels; lobes: greedy multi-lobe fit in "
               "3D maps (KM2000 Sec. 5.3); single: one lobe per elevation (Sec. 5.1); 2d: one shared 2D lobe x k(theta_o) "
               "(Sec. 5.2); pyramid: the lobes' Phong fits looked up in the sqrt-cos pyramid (Knuth 2014)")


def _env(text: str, size: int, args=None):
    from ..synthetic.synthetic_envs import ENV_NAMES, make_env

    if text in ENV_NAMES:
        return make_env(text, n=size)
    p = Path(text)
    if not p.exists():
        raise IBLError(f"--env {text!r}: neither a synthetic environment ({', '.join(ENV_NAMES)}) nor an existing file")
    from .radiance_args import load_env

    return load_env(args, p, size)[0]


def run(args) -> int:
    from ..atomic import OutputSet, check_side_files, refuse_overwriting_inputs
    from ..rendering.km00_render import render_single_method
    from ..rendering.image_io import write_image_exr

    from .cmd_render import _check_output, _preview_exposure, _size, parse_exposure

    # ---- every argument first, before the environment is read --------------------------------------------
    out = _check_output(Path(args.out), (".exr",))
    png = out.with_suffix(".png") if args.png else None
    side = out.with_suffix(".json")
    stops = parse_exposure(args.exposure)
    env_file = args.env if Path(args.env).exists() else None
    refuse_overwriting_inputs({"--env": env_file}, {"--out": out, "--png": png, "--out (.json sidecar)": side})
    check_side_files(side, [png] if png else [], "outputs", "--out")  # never replace a file the user did not name
    w, h = _size(args.size)
    if args.env_size < 2 or args.env_size & (args.env_size - 1):
        raise IBLError(f"--env-size must be a power of two >= 2, got {args.env_size}")
    params = dict(ks=args.ks, kd=args.kd)
    if args.brdf in ("ward", "cook_torrance"):
        params["alpha"] = args.alpha
    elif args.brdf in ("phong", "blinn_phong"):
        params["s"] = args.s
    if args.brdf == "cook_torrance":
        params.pop("ks")
    env = _env(args.env, args.env_size, args)
    png_stops, exposure_rule = _preview_exposure(stops, env)
    img, mask, info = render_single_method(args.method, env, width=w, height=h, brdf=args.brdf, brdf_params=params,
                                           n_lobes=args.lobes, n_theta=args.n_theta, rescale_lobes=args.rescale_lobes,
                                           progress=not args.quiet)
    # ---- outputs: image, --png and the JSON manifest committed together (a failed PNG leaves no image) -------
    manifest = {"out": str(out), "method": args.method, "brdf": args.brdf, "brdf_params": params,
                "size": [w, h], "env": str(args.env), "env_size": int(env.shape[1]), "lobes": args.lobes,
                "n_theta": args.n_theta, "rescale_lobes": bool(args.rescale_lobes), "exposure_stops": png_stops,
                "exposure_rule": exposure_rule,
                "time_s": info.get("time_s"), "outputs": [out.name] + ([png.name] if png else [])}
    with OutputSet(side, owned_key="outputs", remove_stale=False, named=[out]) as outs:
        write_image_exr(outs.path(out), img)
        if png is not None:
            from ..rendering.tonemap import save_png

            save_png(outs.path(png), img, stops=png_stops, mask=mask)
        outs.commit(manifest)
    if not args.quiet:
        print(f"wrote {out} ({w}x{h}, method {args.method}, {info['time_s']} s)"
              + (f" and {png}" if png else "") + f"; settings in {side}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("km00-render", help="render the teapot with Kautz & McCool 2000 fitted lobes (or the reference)",
                       description=__doc__)
    p.add_argument("--brdf", default="ward", choices=("ward", "cook_torrance", "phong", "blinn_phong"),
                   help="analytic BRDF (default ward)")
    p.add_argument("--alpha", type=float, default=0.04, help="roughness of ward / cook_torrance (default 0.04)")
    p.add_argument("--s", type=float, default=100.0, help="exponent of phong / blinn_phong (default 100)")
    p.add_argument("--ks", type=float, default=0.8, help="specular weight (default 0.8)")
    p.add_argument("--kd", type=float, default=0.0, help="diffuse weight (default 0)")
    p.add_argument("--lobes", type=int, default=3, help="number of greedy lobes for --method lobes/pyramid (default 3)")
    p.add_argument("--rescale-lobes", action="store_true",
                   help="--method lobes/pyramid: scale the greedy lobes so that their albedo equals the BRDF's, one "
                        "factor per elevation (not in the paper; its minimum-profile lobes lose the residual's energy)")
    p.add_argument("--n-theta", type=int, default=16, help="sampled view elevations in [0, 80] deg (default 16)")
    p.add_argument("--method", default="lobes", choices=("reference", "lobes", "single", "2d", "pyramid"),
                   help=METHOD_HELP)
    p.add_argument("--size", type=int, nargs="+", default=[256, 256], metavar="N",
                   help="image size W H (or N for N x N; default 256 256)")
    p.add_argument("--env", default="sky_sun", help="synthetic environment name or an environment-map file")
    p.add_argument("--env-size", type=int, default=64, help="cube face size of the environment (default 64)")
    p.add_argument("--out", required=True,
                   help="output OpenEXR image OUT.exr (linear radiance); OUT.json beside it records the settings")
    p.add_argument("--png", action="store_true", help="also write a tone-mapped PNG next to it (OUT.png)")
    p.add_argument("--exposure", default="auto", metavar="auto|EV|xK",
                   help="PNG exposure: 'auto' (default: one exposure per environment, its solid-angle mean "
                   "radiance maps to 0.5, the same for every method), 'image' (per image), EV stops (e.g. -2) or a "
                   "linear scale (e.g. x0.25)")
    p.add_argument("--quiet", action="store_true", help="no progress reports (bar or status lines) and no summary line")
    from .radiance_args import add_radiance_args

    add_radiance_args(p)
    p.set_defaults(func=run)
