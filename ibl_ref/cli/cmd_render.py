"""``ibl-ref render``: render a mesh lit by partial environment maps with shadows (Knuth et al. 2014, Eq. 5).

Thin layer over :func:`ibl_ref.render.render_pem` (modes ``ours`` and ``no-occlusion``) and
:func:`ibl_ref.ao_modes.render_mode` (modes ``ao``, ``ao-color``, imported lazily) and
:mod:`ibl_ref.cli.exact_modes` (modes ``reference``, ``mitsuba``: per-mesh materials).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from ..errors import IBLError

MODES = ("ours", "no-occlusion", "ao", "ao-color", "reference", "mitsuba")
_AO_MODES = ("ao", "ao-color")
_EXACT_MODES = ("reference", "mitsuba")  # ibl_ref.cli.exact_modes (per-mesh materials)
OUT_EXTS = (".exr", ".npz")


def parse_material(text: str, option: str = "--material"):
    """``"kd,ks,g"`` (3 numbers) or ``"kdR,kdG,kdB,ksR,ksG,ksB,g"`` (7 numbers) → :class:`ibl_ref.render.Material`."""
    from ..render import Material

    parts = [p.strip() for p in str(text).split(",")]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = None
    if vals is None or len(vals) not in (3, 7):
        raise IBLError(f"{option}: expected 'kd,ks,g' (3 numbers, e.g. 0.2,0.8,0.9) or "
                       f"'kdR,kdG,kdB,ksR,ksG,ksB,g' (7 numbers), got {text!r}")
    if len(vals) == 3:
        kd, ks, g = vals
    else:
        kd, ks, g = vals[0:3], vals[3:6], vals[6]
    try:
        return Material(kd=kd, ks=ks, g=g)
    except IBLError as exc:
        raise IBLError(f"{option} {text!r}: {exc}") from exc


def _check_output(path: Path, exts=None, option: str = "--out") -> Path:
    """Fail early (before any rendering) on a bad extension or an unwritable output folder."""
    path = Path(path)
    if exts is not None and path.suffix.lower() not in exts:
        raise IBLError(f"{option} {path}: extension must be one of {', '.join(exts)}")
    if path.is_dir():
        raise IBLError(f"{option} {path}: is a folder, expected a file path")
    parent = path.resolve().parent
    if parent.exists() and not parent.is_dir():
        raise IBLError(f"{option} {path}: output folder {parent} is not a folder")
    if not parent.exists():
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise IBLError(f"{option} {path}: cannot create output folder {parent}: {exc.strerror}") from exc
    if not os.access(parent, os.W_OK):
        raise IBLError(f"{option} {path}: output folder {parent} is not writable")
    return path


def _size(values):
    if len(values) == 1:
        w = h = values[0]
    elif len(values) == 2:
        w, h = values
    else:
        raise IBLError(f"--size: expected W H (or a single N for N x N), got {len(values)} numbers")
    if w < 1 or h < 1 or w > 8192 or h > 8192:
        raise IBLError(f"--size: width and height must be in [1, 8192], got {w} x {h}")
    return int(w), int(h)


def _ground_quad(mesh):
    import trimesh

    lo, hi = mesh.bounds
    s = 1.5 * float((hi - lo).max())
    y0 = float(lo[1])
    c = 0.5 * (lo + hi)
    return trimesh.Trimesh(
        [[c[0] - s, y0, c[2] - s], [c[0] + s, y0, c[2] - s], [c[0] + s, y0, c[2] + s], [c[0] - s, y0, c[2] + s]],
        [[0, 2, 1], [0, 3, 2]], process=False)


def _camera(args, mesh_scene):
    import numpy as np

    from ..camera import PerspectiveCamera

    centre, radius = mesh_scene.bounds()
    w, h = _size(args.size)
    target = np.asarray(args.camera_target, float) if args.camera_target is not None else centre
    if args.camera_eye is not None:
        eye = np.asarray(args.camera_eye, float)
    else:
        direction = np.asarray(args.view_dir, float)
        if not np.all(np.isfinite(direction)) or np.linalg.norm(direction) == 0:
            raise IBLError("--view-dir must be a finite non-zero vector")
        direction = direction / np.linalg.norm(direction)
        if not (0 < args.fov < 180):
            raise IBLError(f"--fov must be in (0, 180) degrees, got {args.fov}")
        dist = radius / np.sin(np.radians(args.fov) / 2) * 1.1  # bounding sphere fits the vertical fov
        eye = target + dist * direction
    dist = float(np.linalg.norm(eye - target))
    scale = max(dist + radius, 1e-9)
    return PerspectiveCamera(eye=eye, target=target, up=args.camera_up, fov_y_deg=args.fov, width=w, height=h,
                             near=1e-4 * scale, far=100 * scale)


def _ao_render_mode():
    """:func:`ibl_ref.ao_modes.render_mode` (imported only for the modes that need it)."""
    from ..ao_modes import render_mode

    return render_mode


def cmd_render(args) -> int:
    import time

    import numpy as np

    from ..atomic import atomic_path, write_json
    from ..raster import prepare_scene
    from ..render import Material, render_pem
    from ..synthetic_meshes import load_mesh

    # ---- validate everything cheap before the expensive parts ----------------------------------------------
    out = _check_output(Path(args.out), OUT_EXTS, "--out")
    png = _check_output(Path(args.png), (".png",), "--png") if args.png else None
    w, h = _size(args.size)
    if args.lights < 1:
        raise IBLError(f"--lights must be >= 1, got {args.lights}")
    mat = parse_material(args.material) if args.material else Material(kd=0.0, ks=1.0, g=args.gloss)
    gmat = (parse_material(args.ground_material, "--ground-material") if args.ground_material
            else Material(kd=0.0, ks=1.0, g=args.ground_gloss))
    if args.gmap:
        from ..image_io import read_g_map

        mat = Material(kd=mat.kd, ks=mat.ks, g=mat.g, g_map=read_g_map(args.gmap), uv_fallback=args.gmap_fallback)
    mode = args.mode
    if mode in _EXACT_MODES:
        from .exact_modes import check_args

        check_args(args)
    visibility = {"ours": args.visibility or "vsm", "no-occlusion": "none"}.get(mode)
    if mode == "no-occlusion" and args.visibility not in (None, "none"):
        raise IBLError("--visibility only applies to --mode ours (no-occlusion means VIS_i = 1)")
    render_mode = None
    if mode in _AO_MODES:
        render_mode = _ao_render_mode()
        if np.ndim(mat.kd) or np.ndim(mat.ks) or mat.g_map is not None:
            raise IBLError(f"--mode {mode}: ibl_ref.ao_modes takes scalar kd, ks and one g; RGB weights and "
                           "--gmap are only supported by --mode ours / no-occlusion")
    progress = sys.stderr.isatty() if args.progress is None else args.progress

    # ---- scene -------------------------------------------------------------------------------------------
    if args.env is not None:
        from ..exr_io import load_cube

        cube = load_cube(args.env, size=args.env_size)
    else:
        from ..synthetic_envs import make_env

        cube = make_env(args.synthetic, n=args.env_size)
    mesh = load_mesh(args.mesh)
    meshes = [(mesh, 0)]
    if args.ground:
        meshes.append((_ground_quad(mesh), 1))
    cam = _camera(args, prepare_scene([(mesh, 0)], warn=False))

    t0 = time.perf_counter()
    info = {"out": str(out), "mode": mode, "size": [w, h], "fov_y_deg": args.fov,
            "camera_eye": cam.eye.tolist(), "camera_target": cam.target.tolist(),
            "material": {"kd": mat.kd, "ks": mat.ks, "g": mat.g, "g_map": args.gmap},
            "ground_material": ({"kd": gmat.kd, "ks": gmat.ks, "g": gmat.g} if args.ground else None)}
    pems = None
    if mode not in _EXACT_MODES:
        from ..pem import build_pems

        pems = build_pems(cube, n_lights=args.lights, variant=args.median_cut, progress=progress)
        if args.prefilter == "exact-lobe":
            from ..lobe_chain import build_lobe_chain_pems

            pems = build_lobe_chain_pems(cube, pems.lights, progress=progress)
        info["lights"] = len(pems.lights.directions)
        info["median_cut"] = args.median_cut
        info["prefilter"] = args.prefilter
    t1 = time.perf_counter()
    extra = {}
    if mode in _EXACT_MODES:
        from .exact_modes import render_exact

        image, mask, more = render_exact(mode, meshes, cam, cube, mat, gmat if args.ground else None, args, progress)
        info.update(more)
    elif render_mode is None:
        res = render_pem(meshes, cam, pems, materials={0: mat, 1: gmat}, visibility=visibility,
                         vsm_resolution=args.vsm_res, vsm_dtype=args.vsm_dtype, exact_backend=args.exact_backend,
                         horizon=args.horizon, progress=progress)
        image, mask = res.image, res.mask
        extra = dict(unshadowed=res.unshadowed, visibility=res.visibility, depth=res.gbuffer.depth,
                     diffuse=res.diffuse, specular=res.specular, glossiness=res.glossiness)
        info["visibility"] = visibility
    else:
        if args.ground and (gmat.kd, gmat.ks, gmat.g) != (mat.kd, mat.ks, mat.g):
            print(f"note: --mode {mode} shades every mesh with the --material (ibl_ref.ao_modes has one "
                  "material); the ground material is ignored", file=sys.stderr)
        kw = dict(camera=cam, kd=float(mat.kd), ks=float(mat.ks), g=float(mat.g), vsm_resolution=args.vsm_res,
                  vsm_dtype=args.vsm_dtype, progress=progress)
        if pems is not None:
            kw["pems"] = pems
        try:
            image = np.asarray(render_mode(meshes, cube, mode, **kw), dtype=np.float64)
        except TypeError as exc:
            raise IBLError(f"ibl_ref.ao_modes.render_mode does not accept the arguments of this CLI "
                           f"({exc}); the two modules are out of step") from exc
        from ..raster import rasterize

        mask = rasterize(meshes, cam, warn=False).mask
    t2 = time.perf_counter()
    if image.shape[:2] != (h, w):
        raise IBLError(f"renderer returned an image of shape {image.shape}, expected ({h}, {w}, C)")

    # ---- outputs -------------------------------------------------------------------------------------------
    if out.suffix.lower() == ".exr":
        from ..image_io import write_image_exr

        write_image_exr(out, image)
    else:
        arrays = {"image": image, "mask": mask}
        arrays.update({k: v for k, v in extra.items() if v is not None})
        with atomic_path(out, suffix=".npz") as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **arrays)
    info.update({"pem_time_s": round(t1 - t0, 3), "render_time_s": round(t2 - t1, 3)})
    if png is not None:
        from ..tonemap import save_png

        save_png(png, image, mask=mask)
        info["png"] = str(png)
    write_json(out.with_suffix(".json"), info)
    print(f"wrote {out} ({w}x{h}, mode {mode}; {info['render_time_s']} s render, {info['pem_time_s']} s PEMs)"
          + (f" and {png}" if png is not None else ""))
    return 0


_DESCRIPTION = """\
Render a mesh lit by an environment map with the method of Knuth et al. 2014 (Eq. 5):

    c = sum_i VIS_i * (kd * PEM_i(n, g=0) + ks * PEM_i(r, g))

The environment is split into --lights regions by median cut; each region becomes a partial environment
map (PEM) filtered into a glossiness pyramid. Per pixel, the diffuse part is looked up through the
surface normal n (g = 0), the glossy part through the reflection vector r with the material's
glossiness g (0 = diffuse ... 1 = mirror), and VIS_i is the visibility of region i (variance shadow
maps in the paper's method). Everything runs on the CPU with NumPy, so keep sizes small.

Without options it renders the Utah teapot on a ground quad under the synthetic 'sky_sun' map
(96x96 pixels, 24 lights) -- try:  ibl-ref render --out teapot.exr --png teapot.png

Output: OUT.exr is linear radiance (float32 RGB, no tone mapping); OUT.npz instead stores the image plus
unshadowed image, per-light visibility, depth, mask, diffuse/specular terms and per-pixel g. A small
OUT.json next to it records the settings and timings. --png writes a tone-mapped preview
(auto exposure, Reinhard, sRGB).
"""

_EPILOG = """\
modes:
  ours          Eq. 5 with VIS_i from variance shadow maps (the paper); --visibility raycast gives exact
                shadows of the same lights, --visibility none no shadows
  no-occlusion  VIS_i = 1 (Fig. 6a)
  ao, ao-color  ambient-occlusion comparisons of Fig. 6b/6c (ibl_ref.ao_modes)
  reference     exact lobes and ray-cast visibility, converged to --ref-rtol (ibl_ref.reference_render; slow)
  mitsuba       the same scene rendered by Mitsuba 3 (pip install ".[mitsuba]"; --spp, --seed)
  ao / ao-color shade every mesh with --material; reference / mitsuba honour --ground-material
  (scalar kd, ks; no --gmap).

examples:
  ibl-ref render --out x.exr
  ibl-ref render --mesh sphere_on_plane --no-ground --material 0.3,0.7,0.9 --out s.exr --png s.png
  ibl-ref render --env studio.exr --mesh bunny.obj --size 320 240 --lights 48 --out b.exr
  ibl-ref render --mesh cloth --gmap yarns.png --gmap-fallback spherical --out c.exr
  ibl-ref render --camera-eye 3 2 4 --camera-target 0 0.5 0 --fov 30 --out v.exr
"""


def register(sub) -> None:
    import argparse

    p = sub.add_parser(
        "render",
        help="render a mesh lit by an environment map with PEMs and shadows (Eq. 5)",
        description=_DESCRIPTION,
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    g = p.add_argument_group("scene")
    g.add_argument("--mesh", default="teapot", metavar="PATH|NAME",
                   help="mesh file (OBJ/PLY/STL/GLB/...) or generated mesh: teapot (default), sphere_on_plane, "
                   "torus, cloth")
    g.add_argument("--no-ground", dest="ground", action="store_false",
                   help="do not add a ground quad below the mesh")
    src = g.add_mutually_exclusive_group()
    src.add_argument("--env", metavar="IN.exr", help="environment map file (EXR/HDR, any layout; converted to a cube)")
    src.add_argument("--synthetic", default="sky_sun", metavar="NAME",
                     help="synthetic environment: sky_sun (default), constant, gradient, studio, checker, delta")
    g.add_argument("--env-size", type=int, default=32, metavar="N",
                   help="cube face size the PEMs are built at (power of two; default 32)")
    g = p.add_argument_group("material (kd, ks >= 0; g in [0, 1], 0 = diffuse, 1 = mirror)")
    g.add_argument("--material", metavar="kd,ks,g",
                   help="mesh material, e.g. 0.2,0.8,0.9; RGB weights as kdR,kdG,kdB,ksR,ksG,ksB,g "
                   "(default: pure glossy 0,1,--gloss)")
    g.add_argument("--gloss", type=float, default=0.8, metavar="G",
                   help="shortcut for --material 0,1,G (default 0.8)")
    g.add_argument("--ground-material", metavar="kd,ks,g", help="ground material (default 0,1,--ground-gloss)")
    g.add_argument("--ground-gloss", type=float, default=0.2, metavar="G", help="ground glossiness (default 0.2)")
    g.add_argument("--gmap", metavar="FILE",
                   help="per-texel glossiness map for the mesh (.png, .exr or .npy, values in [0, 1]; row 0 = top, "
                   "indexed by the mesh's UVs); replaces g of --material")
    g.add_argument("--gmap-fallback", choices=("planar_xz", "spherical", "error"), default="planar_xz",
                   help="texture coordinates for meshes without UVs (all generated meshes): top-down planar "
                   "projection over the mesh's bounding box (default), spherical around its centre, or error")
    g = p.add_argument_group("method")
    g.add_argument("--mode", choices=MODES, default="ours", help="what to render (see below; default ours)")
    g.add_argument("--lights", type=int, default=24, metavar="N",
                   help="number of median-cut lights / PEMs: a multiple of 6, N/6 per cube face as in the paper "
                   "(default 24)")
    g.add_argument("--median-cut", choices=("per-face", "global", "variance"), default="per-face",
                   help="region split: per cube face (paper, default), global over the whole map, or "
                   "variance-minimising (Viriyothai & Debevec 2009); the last two allow any --lights")
    g.add_argument("--prefilter", choices=("pyramid", "exact-lobe"), default="pyramid",
                   help="how each PEM is prefiltered: 'pyramid' = the paper's 2x2-shrink + 5x5-filter MIP pyramid "
                        "(default); 'exact-lobe' = the same lookup on levels holding exact Phong lobe averages "
                        "(ibl_ref.lobe_chain; slower to build, no filter-shape error)")
    g.add_argument("--visibility", choices=("vsm", "raycast", "none"), default=None,
                   help="VIS_i for --mode ours: variance shadow maps (default), exact ray casting, none")
    g.add_argument("--exact-backend", choices=("binned", "trimesh"), default="binned",
                   help="exact visibility for --visibility raycast: binned parallel rays (default) or trimesh")
    g.add_argument("--horizon", action="store_true",
                   help="block lights below each triangle's tangent plane (not in the paper)")
    g.add_argument("--vsm-res", type=int, default=256, metavar="N", help="shadow map size (default 256)")
    g.add_argument("--vsm-dtype", choices=("float16", "float32", "float64"), default="float32",
                   help="shadow-map moment storage (float16 = the paper's RG16F; default float32)")
    g.add_argument("--ref-rtol", type=float, default=None, metavar="R",
                   help="--mode reference: estimated relative L1 error to converge to (default 2e-3; 0 = the "
                   "fixed coarse quadrature)")
    g.add_argument("--spp", type=int, default=1024, metavar="N",
                   help="--mode mitsuba: samples per pixel (two halves with seeds S, S+1 estimate the noise)")
    g.add_argument("--seed", type=int, default=0, metavar="S", help="--mode mitsuba: first seed (default 0)")
    g = p.add_argument_group("camera (perspective, y is up)")
    g.add_argument("--size", type=int, nargs="+", default=[96, 96], metavar="N",
                   help="image size W H in pixels, or one N for N x N (default 96 96)")
    g.add_argument("--fov", type=float, default=40.0, metavar="DEG",
                   help="VERTICAL field of view in degrees (default 40)")
    g.add_argument("--camera-eye", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="eye position (default: on --view-dir, far enough for the mesh to fit the view)")
    g.add_argument("--camera-target", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="point looked at (default: centre of the mesh's bounding sphere)")
    g.add_argument("--camera-up", type=float, nargs=3, default=[0.0, 1.0, 0.0], metavar=("X", "Y", "Z"),
                   help="up hint (default 0 1 0)")
    g.add_argument("--view-dir", type=float, nargs=3, default=[0.6, 0.5, 1.0], metavar=("X", "Y", "Z"),
                   help="direction from the target to the eye when --camera-eye is not given (default 0.6 0.5 1)")
    g = p.add_argument_group("output")
    g.add_argument("--out", required=True, metavar="OUT.exr",
                   help="output radiance image: .exr (float32 RGB) or .npz (image + intermediate buffers)")
    g.add_argument("--png", metavar="OUT.png", help="also write a tone-mapped PNG preview")
    g.add_argument("--progress", dest="progress", action="store_true", default=None,
                   help="show progress bars (default: only on a terminal)")
    g.add_argument("--no-progress", dest="progress", action="store_false", help="never show progress bars")
    p.set_defaults(func=cmd_render)
