"""``ibl-ref render``: render a mesh lit by partial environment maps with shadows (Knuth et al. 2014, Eq. 5).

Thin layer over :func:`ibl_ref.rendering.scenes.teapot_on_ground` / :func:`ibl_ref.rendering.scenes.default_camera` (scene and view),
:func:`ibl_ref.rendering.render.render_pem` (modes ``ours`` and ``no-occlusion``), :func:`ibl_ref.rendering.ao_modes.render_mode`
(modes ``ao``, ``ao-color``, imported lazily), :mod:`ibl_ref.cli.exact_modes` (modes ``reference``, ``mitsuba``:
per-mesh materials) and :func:`ibl_ref.occlusion.image.occlusion_image` (``--occlusion METHOD``: one method of the
occlusion registry on the exact unoccluded terms, a mode of its own).
"""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import IBLError

MODES = ("ours", "no-occlusion", "ao", "ao-color", "reference", "mitsuba")
_AO_MODES = ("ao", "ao-color")
_EXACT_MODES = ("reference", "mitsuba")  # ibl_ref.cli.exact_modes (per-mesh materials)
OUT_EXTS = (".exr", ".npz")
#: flags that only ``--occlusion`` reads (their default is None: given without it, they are refused)
_OCCLUSION_FLAGS = (("occlusion_inputs", "--occlusion-inputs"), ("n_face", "--n-face"), ("n_sets", "--n-sets"),
                    ("gtao_radius", "--gtao-radius"))


def parse_material(text: str, option: str = "--material"):
    """``"kd,ks,g"`` (3 numbers) or ``"kdR,kdG,kdB,ksR,ksG,ksB,g"`` (7 numbers) → :class:`ibl_ref.rendering.render.Material`;
    ``"ggx:…"`` / ``"phong:…"`` → :func:`ibl_ref.rendering.materials.parse_material` (a GGX material is rendered by
    ``--mode reference`` and ``--mode mitsuba``)."""
    from ..rendering.render import Material

    if ":" in str(text):
        from ..rendering.materials import parse_material as parse_kind

        m = parse_kind(text, option)
        return m if m.kind == "ggx" else Material(kd=m.kd, ks=m.ks, g=m.g)
    parts = [p.strip() for p in str(text).split(",")]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = None
    if vals is None or len(vals) not in (3, 7):
        raise IBLError(f"{option}: expected 'kd,ks,g' (3 numbers, e.g. 0.2,0.8,0.9), "
                       f"'kdR,kdG,kdB,ksR,ksG,ksB,g' (7 numbers) or 'ggx:ROUGHNESS' (e.g. ggx:0.3, "
                       f"ggx:roughness=0.3,f0=1,kd=0.5), got {text!r}")
    if len(vals) == 3:
        kd, ks, g = vals
    else:
        kd, ks, g = vals[0:3], vals[3:6], vals[6]
    try:
        return Material(kd=kd, ks=ks, g=g)
    except IBLError as exc:
        raise IBLError(f"{option} {text!r}: {exc}") from exc


def _is_ggx(m) -> bool:
    return getattr(m, "kind", None) == "ggx"


def _weight_max(m) -> float:
    """Largest weight of a material's terms (a GGX term is at most 1: Fresnel ≤ 1)."""
    import numpy as np

    return max(float(np.max(m.kd)), 1.0 if _is_ggx(m) else float(np.max(m.ks)))


def _material_info(m, gmap=None) -> dict:
    if _is_ggx(m):
        return m.describe()
    return {"kd": m.kd, "ks": m.ks, "g": m.g, **({"g_map": gmap} if gmap is not None else {})}


def _check_output(path: Path, exts=None, option: str = "--out") -> Path:
    """Fail early (before any rendering) on a bad extension or an unwritable output folder."""
    path = Path(path)
    if exts is not None and path.suffix.lower() not in exts:
        raise IBLError(f"{option} {path}: extension must be one of {', '.join(exts)}")
    if path.is_dir():
        raise IBLError(f"{option} {path}: is a folder, expected a file path")
    parent = path.resolve().parent
    anc = next(a for a in [parent, *parent.parents] if a.exists() or a.is_symlink())  # "/" always exists
    if not anc.is_dir():
        raise IBLError(f"{option} {path}: output folder {parent} cannot be created: {anc} is not a folder")
    if not os.access(anc, os.W_OK | os.X_OK):  # created only when the outputs are written (none if the run fails)
        raise IBLError(f"{option} {path}: output folder {anc} is not writable")
    from ..atomic import resolve_output

    try:  # a device, FIFO or socket (also behind a symlink) is refused here, before rendering
        resolve_output(path)
    except IBLError as exc:
        raise IBLError(f"{option} {exc}") from None
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


#: largest |EV| accepted by --exposure: 2^1024 leaves float64 (every radiance would be white or black)
MAX_EXPOSURE_STOPS = 1024.0


def parse_exposure(text, option: str = "--exposure"):
    """``auto`` → None (one exposure per environment, :func:`ibl_ref.rendering.tonemap.environment_exposure`),
    ``image`` → ``"image"`` (per-image auto exposure), a number → EV stops, ``xK`` or ``Kx`` → a linear scale K (stops = log2 K).

    |stops| ≤ :data:`MAX_EXPOSURE_STOPS`; beyond, the scale leaves float64 and the preview would be one colour.
    """
    import math

    t = str(text).strip().lower()
    if t == "auto":
        return None
    if t == "image":
        return "image"
    try:
        if t.startswith("x") or t.endswith("x"):
            k = float(t.strip("x"))
            if not (math.isfinite(k) and k > 0):
                raise ValueError
            v = math.log2(k)
        else:
            v = float(t)
            if not math.isfinite(v):
                raise ValueError
    except ValueError:
        raise IBLError(f"{option}: expected 'auto', 'image', EV stops (e.g. -2 or 1.5) or a linear scale (e.g. x0.25), "
                       f"got {text!r}") from None
    if abs(v) > MAX_EXPOSURE_STOPS:
        raise IBLError(f"{option} {text}: {v:g} stops scales radiance by 2^{v:g}, beyond float64 (at most "
                       f"{MAX_EXPOSURE_STOPS:g} stops either way; a preview needs a few)")
    return v


def _preview_exposure(stops, cube):
    """(stops for the PNG or None for per-image auto exposure, the rule in words) from ``--exposure``."""
    if stops == "image":
        return None, "per image: the object's 90th-percentile luminance maps to 0.8 (not comparable across images)"
    if stops is not None:
        return stops, "fixed by --exposure"
    import numpy as np

    from ..environment.envmap import cube_solid_angles
    from ..rendering.tonemap import environment_exposure

    omega = cube_solid_angles(cube.shape[1])
    y = cube.mean(axis=-1) if cube.ndim == 4 else cube
    mean = float(np.sum(y * omega) / np.sum(omega))
    return environment_exposure(mean), ("per environment: its solid-angle mean radiance maps to 0.5, the same for "
                                        "every mode and method, so previews of one scene compare")


def _camera(args, meshes):
    """:func:`ibl_ref.rendering.scenes.default_camera` from the camera flags (framing: the object's bounding sphere)."""
    import numpy as np

    from ..rendering.scenes import default_camera

    w, h = _size(args.size)
    if not (0 < args.fov < 180):
        raise IBLError(f"--fov must be in (0, 180) degrees, got {args.fov}")
    dist = args.distance
    if dist != "fit":
        try:
            dist = float(dist)
        except ValueError:
            raise IBLError(f"--distance: expected a number of bounding radii or 'fit', got {dist!r}") from None
        if not (np.isfinite(dist) and dist > 0):
            raise IBLError(f"--distance must be > 0, got {args.distance}")
    v = np.asarray(args.view_dir, float)
    if not np.all(np.isfinite(v)) or np.linalg.norm(v) == 0:
        raise IBLError("--view-dir must be a finite non-zero vector")
    from ..rendering.camera import CameraError

    try:
        return default_camera(meshes, view_dir=v, fov_y_deg=args.fov, distance=dist, width=w, height=h,
                              eye=args.camera_eye, target=args.camera_target, up=args.camera_up)
    except CameraError as exc:  # name the flag that set the vector
        flag = next((f for k, f in (("eye", "--camera-eye"), ("target", "--camera-target"), ("up", "--camera-up"))
                     if str(exc).startswith(k)), None)
        msg = str(exc)
        if flag:
            msg = f"{flag}:" + (msg.split(":", 1)[1] if msg.split(" ", 1)[0].endswith(":") else f" {msg}")
        raise CameraError(msg) from None


def _ao_render_mode():
    """:func:`ibl_ref.rendering.ao_modes.render_mode` (imported only for the modes that need it)."""
    from ..rendering.ao_modes import render_mode

    return render_mode


def _gloss_material(g, option):
    """``Material(0, 1, g)`` of a glossiness flag; its error names the flag."""
    from ..rendering.render import Material

    try:
        return Material(kd=0.0, ks=1.0, g=g)
    except IBLError as exc:
        raise IBLError(f"{option}: {exc}") from None


def _checked(args):
    """Every check that needs no file read, before the expensive parts: outputs, size, exposure, lights, materials,
    mode-specific flags → the settings of the run (a namespace)."""
    import numpy as np

    from ..atomic import check_side_files, refuse_overwriting_inputs
    from ..rendering.render import Material

    out = _check_output(Path(args.out), OUT_EXTS, "--out")
    png = _check_output(Path(args.png), (".png",), "--png") if args.png else None
    refuse_overwriting_inputs({"--env": args.env, "--mesh": args.mesh, "--gmap": args.gmap},
                              {"--out": out, "--png": png, "--out (.json sidecar)": out.with_suffix(".json")})
    check_side_files(out.with_suffix(".json"), (), "outputs", "--out")  # never replace a file the lab did not write
    w, h = _size(args.size)
    stops = parse_exposure(args.exposure)
    occlusion = _checked_occlusion(args)
    mode = args.mode
    if occlusion is None and mode is None:
        mode = args.mode = "ours"
    if occlusion is None and mode not in _EXACT_MODES:  # the median cut's light count, before the environment is read
        from .cmd_mediancut import check_lights

        check_lights(args.lights, args.median_cut)
    mat = parse_material(args.material) if args.material else _gloss_material(args.gloss, "--gloss")
    gmat = (parse_material(args.ground_material, "--ground-material") if args.ground_material
            else _gloss_material(args.ground_gloss, "--ground-gloss"))
    if occlusion is not None:
        occlusion.update(_occlusion_materials(args, occlusion, mat, gmat))
    elif (_is_ggx(mat) or _is_ggx(gmat)) and args.mode not in _EXACT_MODES:
        raise IBLError("GGX materials (ggx:...) are rendered by --mode reference and --mode mitsuba; the other modes "
                       "take kd,ks,g")
    if args.gmap and _is_ggx(mat):
        raise IBLError("--gmap replaces the glossiness g of a kd,ks,g material; a GGX material has none")
    if args.gmap:
        from ..rendering.image_io import read_g_map

        mat = Material(kd=mat.kd, ks=mat.ks, g=mat.g, g_map=read_g_map(args.gmap), uv_fallback=args.gmap_fallback)
    if mode in _EXACT_MODES:
        from .exact_modes import check_args

        check_args(args)
    visibility = {"ours": args.visibility or "vsm", "no-occlusion": "none"}.get(mode)
    if mode == "no-occlusion" and args.visibility not in (None, "none"):
        raise IBLError("--visibility only applies to --mode ours (no-occlusion means VIS_i = 1)")
    render_mode = None
    if mode in _AO_MODES:
        render_mode = _ao_render_mode()
        if mode == "reference" and (np.ndim(mat.kd) or np.ndim(mat.ks) or mat.g_map is not None
                                    or np.ndim(gmat.kd) or np.ndim(gmat.ks)):
            raise IBLError("--mode reference: the ray-traced reference takes scalar kd, ks and one g per "
                           "material; RGB weights and --gmap work with the other modes")
    from types import SimpleNamespace

    return SimpleNamespace(out=out, png=png, w=w, h=h, stops=stops, mode=mode, mat=mat, gmat=gmat,
                           visibility=visibility, render_mode=render_mode, occlusion=occlusion)


def _checked_occlusion(args):
    """``--occlusion`` and its flags, checked before anything is read → the settings of the method (a dict) or
    None.  ``--occlusion`` is a mode of its own: it refuses ``--mode``, ``--visibility`` and ``--gmap``."""
    from ..occlusion.image import OcclusionRequestError

    if args.occlusion is None:
        given = [flag for dest, flag in _OCCLUSION_FLAGS if getattr(args, dest) is not None]
        if given:
            raise OcclusionRequestError(f"{', '.join(given)} only apply to --occlusion METHOD")
        return None
    for value, flag in ((args.mode, "--mode"), (args.visibility, "--visibility"), (args.gmap, "--gmap")):
        if value is not None:
            raise OcclusionRequestError(
                f"--occlusion {args.occlusion} does not combine with {flag} {value}: it renders the exact unoccluded "
                "lighting darkened by the occlusion method, a mode of its own (drop one of the two)")
    from ..occlusion.image import DEFAULT_GTAO_RADIUS, check_request

    inputs = args.occlusion_inputs or "oracle"
    method, _ = check_request(args.occlusion, None, inputs)
    n_face = min(16, args.env_size) if args.n_face is None else args.n_face
    regions = "region_visibility" in method.inputs_needed()
    if regions and inputs == "oracle" and args.env_size % n_face:
        raise OcclusionRequestError(f"--env-size {args.env_size} must be a multiple of --n-face {n_face} (each "
                                    "visibility cell of the per-region visibility is a block of environment texels)")
    if regions:
        from .cmd_mediancut import check_lights

        check_lights(args.lights, args.median_cut)
    radius = DEFAULT_GTAO_RADIUS if args.gtao_radius is None else args.gtao_radius
    if not radius > 0:
        raise OcclusionRequestError(f"--gtao-radius must be > 0 (world units), got {radius:g}")
    rtol = None
    if args.ref_rtol is not None:
        from ..limits import check_rtol

        rtol = check_rtol(args.ref_rtol, "--ref-rtol")
    return {"method": method, "inputs": inputs, "n_face": n_face, "n_sets": 2 if args.n_sets is None else args.n_sets,
            "gtao_radius": float(radius), "rtol": rtol, "regions": regions}


def _occlusion_materials(args, occlusion, mat, gmat) -> dict:
    """``{"materials": {material id: material}}`` of the scene, each checked against the method (one line naming
    the flag if the method cannot shade it)."""
    from ..occlusion.image import check_request

    mats = {0: (mat, "--material" if args.material else "--material (default 0,1,--gloss)")}
    if args.ground:
        mats[1] = (gmat, "--ground-material" if args.ground_material else
                   "--ground-material (default 0,1,--ground-gloss)")
    for m, flag in mats.values():
        check_request(occlusion["method"], m, occlusion["inputs"], where=flag)
    return {"materials": {k: m for k, (m, _) in mats.items()}}


def _scene(args, run):
    """The mesh (first: cheaper to check than a big map), the camera and the environment; refuses weights that
    overflow float64 in Eq. 5's sum (L+1 terms, each at most weight × max radiance) → (meshes, camera, cube,
    radiance information)."""
    import numpy as np

    from ..rendering.scenes import teapot_on_ground

    meshes = teapot_on_ground(args.mesh, ground=args.ground)
    if getattr(run.mat, "g_map", None) is not None:  # NaN/Inf UVs of a mesh file: refused before any rendering
        from ..rendering.render import mesh_uv

        mesh_uv(meshes[0][0], f"--mesh {args.mesh}")
    cam = _camera(args, meshes[:1])
    radiance = None
    if args.env is not None:
        from .radiance_args import load_env

        cube, radiance = load_env(args, args.env, args.env_size)
    else:
        from ..synthetic.synthetic_envs import make_env

        cube = make_env(args.synthetic, n=args.env_size)
    wmax = max(_weight_max(run.mat), _weight_max(run.gmat))
    if wmax * float(np.max(cube)) * (args.lights + 1) > np.finfo(np.float64).max:
        raise IBLError(f"--material / --ground-material: weights up to {wmax:g} times radiance up to "
                       f"{float(np.max(cube)):g} overflow float64 in the shading sum; use smaller weights")
    return meshes, cam, cube, radiance


def _region_prefilters(args, cube, info):
    """The PEMs of Eq. 5 with ``--prefilter`` (modes other than reference / mitsuba); records them in ``info``."""
    from ..prefilter.registry import build_region_prefilters, region_params

    accepted = region_params(args.prefilter)
    params = {"progress": args.progress} if "progress" in accepted else {}
    if "calibration" in accepted:
        from ..knuth2014.gloss_calibration import calibration_for

        # the g → level table of the paper's pyramid (shipped, or computed for sizes without one)
        params["calibration"] = calibration_for(cube.shape[1], progress=args.progress)
    pems = build_region_prefilters(cube, method=args.prefilter, n_lights=args.lights, variant=args.median_cut,
                                   **params)
    info["lights"] = len(pems.lights.directions)
    info["median_cut"] = args.median_cut
    info["prefilter"] = args.prefilter
    return pems


def _render_image(args, run, meshes, cam, cube, pems, info):
    """The image of ``--mode`` → (image (H, W, C) float64, mask (H, W), the .npz's extra buffers)."""
    import numpy as np

    mat, gmat, mode, progress = run.mat, run.gmat, run.mode, args.progress
    if run.occlusion is not None:
        return _render_occlusion(args, run, meshes, cam, cube, info)
    if mode in _EXACT_MODES:
        from ..rendering.render import apply_background
        from .exact_modes import render_exact

        image, mask, more = render_exact(mode, meshes, cam, cube, mat, gmat if args.ground else None, args, progress)
        info.update(more)
        return apply_background(np.array(image, dtype=np.float64), mask, cam, cube, args.background), mask, {}
    if run.render_mode is None:
        from ..rendering.render import render_pem

        res = render_pem(meshes, cam, pems, materials={0: mat, 1: gmat}, visibility=run.visibility,
                         vsm_resolution=args.vsm_res, vsm_dtype=args.vsm_dtype, exact_backend=args.exact_backend,
                         horizon=args.horizon, background=args.background, progress=progress)
        info["visibility"] = run.visibility
        return res.image, res.mask, dict(unshadowed=res.unshadowed, visibility=res.visibility,
                                         depth=res.gbuffer.depth, diffuse=res.diffuse, specular=res.specular,
                                         glossiness=res.glossiness)
    kw = dict(camera=cam, materials={0: mat, 1: gmat}, vsm_resolution=args.vsm_res, vsm_dtype=args.vsm_dtype,
              background=args.background, progress=progress)
    if pems is not None:
        kw["pems"] = pems
    try:
        image = np.asarray(run.render_mode(meshes, cube, mode, **kw), dtype=np.float64)
    except TypeError as exc:
        raise IBLError(f"ibl_ref.rendering.ao_modes.render_mode does not accept the arguments of this CLI "
                       f"({exc}); the two modules are out of step") from exc
    from ..rendering.raster import rasterize

    return image, rasterize(meshes, cam, warn=False).mask, {}  # coverage (the image holds the backdrop elsewhere)


def _render_occlusion(args, run, meshes, cam, cube, info):
    """The image of ``--occlusion`` (:func:`ibl_ref.occlusion.image.occlusion_image`) with the backdrop; the .npz's
    extra buffers: the unoccluded image and every input the method was fed, as images (``input_ao``, …)."""
    from ..occlusion.image import occlusion_image
    from ..rendering.render import apply_background

    occ = run.occlusion
    res = occlusion_image(meshes, cam, cube, occ["materials"], occ["method"], inputs=occ["inputs"],
                          regions=args.lights, median_cut_variant=args.median_cut, rtol=occ["rtol"],
                          n_face=occ["n_face"], n_sets=occ["n_sets"], seed=args.seed, gtao_radius=occ["gtao_radius"],
                          progress=True)
    info["occlusion"] = dict(res.info, timings_s={k: round(v, 3) for k, v in res.timings.items()})
    extra = {"unoccluded": res.unoccluded}
    extra.update({f"input_{k}": (v if k == "env_sh" else res.input_image(k)) for k, v in res.inputs.items()})
    return apply_background(res.image, res.mask, cam, cube, args.background), res.mask, extra


def _write_outputs(run, image, mask, extra, info, png_stops, times) -> None:
    """The image, ``--png`` and the JSON sidecar (``info`` with ``times``) committed together, the JSON last."""
    import numpy as np

    from ..atomic import OutputSet, atomic_path

    out, png = run.out, run.png
    info["outputs"] = [out.name]  # OUT.json: this output's manifest (the marker is ibl_ref.atomic.OutputSet's)
    with OutputSet(out.with_suffix(".json"), owned_key="outputs", remove_stale=False, named=[out, png]) as outs:
        if out.suffix.lower() == ".exr":
            from ..rendering.image_io import write_image_exr

            write_image_exr(outs.path(out), image)
        else:
            arrays = {"image": image, "mask": mask}
            arrays.update({k: v for k, v in extra.items() if v is not None})
            with atomic_path(outs.path(out), suffix=".npz") as tmp:
                with open(tmp, "wb") as fh:
                    np.savez_compressed(fh, **arrays)
        info.update(times)
        if png is not None:
            from ..rendering.tonemap import save_png

            save_png(outs.path(png), image, stops=png_stops, mask=mask)
            info["png"] = str(png)
        outs.commit(info)


def cmd_render(args) -> int:
    """``ibl-ref render``: checks (:func:`_checked`), scene (:func:`_scene`), PEMs (:func:`_region_prefilters`),
    the image of the mode (:func:`_render_image`), outputs (:func:`_write_outputs`)."""
    import time

    import numpy as np

    run = _checked(args)
    meshes, cam, cube, radiance = _scene(args, run)
    png_stops, exposure_rule = _preview_exposure(run.stops, cube)
    t0 = time.perf_counter()
    info = {"out": str(run.out), "mode": run.mode or "occlusion", "size": [run.w, run.h], "fov_y_deg": args.fov,
            "camera_eye": cam.eye.tolist(), "camera_target": cam.target.tolist(),
            "background": args.background, "exposure_stops": png_stops, "exposure_rule": exposure_rule,
            "material": _material_info(run.mat, args.gmap),
            "ground_material": (_material_info(run.gmat) if args.ground else None),
            "radiance": radiance}
    pems = None if (run.mode in _EXACT_MODES or run.occlusion) else _region_prefilters(args, cube, info)
    t1 = time.perf_counter()
    image, mask, extra = _render_image(args, run, meshes, cam, cube, pems, info)
    t2 = time.perf_counter()
    if image.shape[:2] != (run.h, run.w):
        raise IBLError(f"renderer returned an image of shape {image.shape}, expected ({run.h}, {run.w}, C)")
    top = float(np.max(image)) if image.size else 0.0
    if run.out.suffix.lower() == ".exr" and top > float(np.finfo(np.float32).max):  # name the flags, not the format
        raise IBLError(f"--out {run.out}: the image reaches {top:.3g}, beyond float32 (3.4e+38) of an .exr; use "
                       "smaller --material / --ground-material weights or write .npz (float64)")
    _write_outputs(run, image, mask, extra, info, png_stops,
                   {"pem_time_s": round(t1 - t0, 3), "render_time_s": round(t2 - t1, 3)})
    what = (f"mode {run.mode}; {info['render_time_s']} s render, {info['pem_time_s']} s PEMs" if run.occlusion is None
            else f"occlusion {run.occlusion['method'].name}, {run.occlusion['inputs']} inputs; "
                 f"{info['render_time_s']} s render")
    print(f"wrote {run.out} ({run.w}x{run.h}, {what})" + (f" and {run.png}" if run.png is not None else ""))
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

--occlusion METHOD renders instead with one of the occlusion methods engines ship (AO, specular
occlusion, horizon fades, GTSO cones, PRT, the paper's per-region visibility; the labels of
ibl_ref.occlusion, listed below): the exact unoccluded lighting of the material, darkened by METHOD
fed the inputs it reads, exact ones from ray casts (--occlusion-inputs oracle, default) or AO and bent
normals estimated from the depth buffer by GTAO (--occlusion-inputs screen-space) -- try:
    ibl-ref render --occlusion gtso-exact-alpha --material ggx:0.3 --ground-material ggx:0.6 --out o.exr

Output: OUT.exr is linear radiance (float32 RGB, no tone mapping); OUT.npz instead stores the image plus
unshadowed image, per-light visibility, depth, mask, diffuse/specular terms and per-pixel g (with
--occlusion: the unoccluded image and every input the method read, input_ao, input_bent_normal, ...). A small
OUT.json next to it records the settings and timings. --png writes a tone-mapped preview
(Reinhard, sRGB; auto exposure from the object's pixels unless --exposure is given). Pixels not covered
by geometry show the environment seen along the camera ray (--background env, default) or are 0
(--background black); the .npz 'mask' marks the covered pixels.
"""

_EPILOG = """\
modes:
  ours          Eq. 5 with VIS_i from variance shadow maps (the paper); --visibility raycast gives exact
                shadows of the same lights, --visibility none no shadows
  no-occlusion  VIS_i = 1 (Fig. 6a)
  ao, ao-color  ambient-occlusion comparisons of Fig. 6b/6c (ibl_ref.rendering.ao_modes)
  reference     exact lobes and ray-cast visibility, converged to --ref-rtol with an error estimate
                (ibl_ref.rendering.reference_render; --workers, --seed; ~20-60 s at 128² on 2 cores with
                embreex, pip install ".[fast]"; ~13× the CPU without)
  mitsuba       the same scene rendered by Mitsuba 3 (pip install ".[mitsuba]"; --spp, --seed)
  every mode shades the mesh with --material and the ground with --ground-material
  (reference, mitsuba: scalar kd, ks and no --gmap; they also take GGX materials, ggx:ROUGHNESS).

occlusion methods (--occlusion METHOD, instead of --mode; docs/occlusion.md):
  the mesh and the ground are shaded with their materials' exact unoccluded terms (the diffuse
  lobe average and the GGX or Phong specular term, integrated to --ref-rtol, V = 1), then METHOD
  darkens them from the inputs it reads. GGX materials (any method) and Phong kd,ks,g with scalar
  weights and g < 1; a Phong glossy lobe (ks > 0) has no GGX roughness, so only the methods that
  read none (marked *) shade it. An unknown METHOD, a material it cannot shade, inputs it cannot
  be fed or --mode / --visibility / --gmap with it: one line, nothing written.
{methods}

  --occlusion-inputs oracle        exact AO, bent normal, SH transfer and per-region visible fractions
                                   by ray casting (--n-face cells, --n-sets sets, --seed)
  --occlusion-inputs screen-space  AO and bent normals from the depth buffer by GTAO (--gtao-radius),
                                   as engines get them: methods reading only those two

examples:
  ibl-ref render --out x.exr
  ibl-ref render --occlusion lagarde2014-alpha --occlusion-inputs screen-space --material ggx:0.3 --out so.exr
  ibl-ref render --occlusion regions-exact --lights 24 --material 0.2,0.8,0.9 --out r.exr --png r.png
  ibl-ref render --mesh sphere_on_plane --no-ground --material 0.3,0.7,0.9 --out s.exr --png s.png
  ibl-ref render --mode reference --material ggx:roughness=0.3,f0=1 --ground-material ggx:0.6 --out g.exr
  ibl-ref render --env studio.exr --mesh bunny.obj --size 320 240 --lights 48 --out b.exr
  ibl-ref render --mesh cloth --gmap yarns.png --gmap-fallback spherical --out c.exr
  ibl-ref render --camera-eye 3 2 4 --camera-target 0 0.5 0 --fov 30 --out v.exr
  ibl-ref render --env probe.hdr --background env --exposure -1 --out p.exr --png p.png
"""


def register(sub) -> None:
    import argparse
    import textwrap

    from ..occlusion.image import INPUT_KINDS
    from ..occlusion.registry import OCCLUSION_METHODS

    methods = "\n".join(textwrap.fill(m.summary + ("" if m.reads_roughness else " *"), 100,
                                       initial_indent=f"  {name:<23}", subsequent_indent=" " * 25,
                                       break_on_hyphens=False)
                         for name, m in OCCLUSION_METHODS.items())
    methods += "\n  (regions-exact: --lights median-cut regions, --median-cut; prt-3, prt-5, regions-exact: oracle " \
               "inputs only)"
    p = sub.add_parser(
        "render",
        help="render a mesh lit by an environment map with PEMs and shadows (Eq. 5), or with an occlusion method",
        description=_DESCRIPTION,
        epilog=_EPILOG.format(methods=methods),
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
    g = p.add_argument_group("material (kd,ks,g: kd, ks >= 0, g in [0, 1], 0 = diffuse, 1 = mirror; or ggx:...)")
    g.add_argument("--material", metavar="SPEC",
                   help="mesh material: kd,ks,g (Phong lobes of Eq. 5, e.g. 0.2,0.8,0.9; RGB weights as "
                   "kdR,kdG,kdB,ksR,ksG,ksB,g), or for --mode reference/mitsuba a GGX microfacet material "
                   "ggx:ROUGHNESS or ggx:roughness=R,f0=F,kd=K,smith=S (roughness in (0, 1], alpha = roughness^2; "
                   "f0 in [0, 1], default 0.04; kd >= 0 Lambertian, default 0; smith: height-correlated (default) "
                   "or separable), e.g. ggx:0.3 or ggx:roughness=0.3,f0=1 (default: pure glossy 0,1,--gloss)")
    g.add_argument("--gloss", type=float, default=0.8, metavar="G",
                   help="shortcut for --material 0,1,G (default 0.8)")
    g.add_argument("--ground-material", metavar="SPEC",
                   help="ground material, same forms as --material (default 0,1,--ground-gloss)")
    g.add_argument("--ground-gloss", type=float, default=0.2, metavar="G", help="ground glossiness (default 0.2)")
    g.add_argument("--gmap", metavar="FILE",
                   help="per-texel glossiness map for the mesh (.png, .exr or .npy, values in [0, 1]; row 0 = top, "
                   "indexed by the mesh's UVs); replaces g of --material")
    g.add_argument("--gmap-fallback", choices=("planar_xz", "spherical", "error"), default="planar_xz",
                   help="texture coordinates for meshes without UVs (all generated meshes): top-down planar "
                   "projection over the mesh's bounding box (default), spherical around its centre, or error")
    g = p.add_argument_group("method")
    g.add_argument("--mode", choices=MODES, default=None, help="what to render (see below; default ours)")
    g.add_argument("--lights", type=int, default=24, metavar="N",
                   help="number of median-cut lights / PEMs, >= 6: a multiple of 6 (N/6 per cube face as in the "
                   "paper) for --median-cut per-face (default 24)")
    g.add_argument("--median-cut", choices=("per-face", "global", "variance"), default="per-face",
                   help="region split: per cube face (paper, default), global over the whole map, or "
                   "variance-minimising (Viriyothai & Debevec 2009); the last two allow any --lights >= 6, not only "
                   "multiples of 6")
    from ..prefilter.registry import prefilter_methods

    phong = prefilter_methods("phong")
    g.add_argument("--prefilter", choices=[m.name for m in phong], default="pyramid",
                   help="how each PEM is prefiltered (ibl_ref.prefilter): "
                        + "; ".join(f"'{m.name}' = {m.summary} ({m.paper})" for m in phong)
                        + ". Default: pyramid (the paper's method)")
    g.add_argument("--visibility", choices=("vsm", "raycast", "none"), default=None,
                   help="VIS_i for --mode ours: variance shadow maps (default), exact ray casting, none")
    g.add_argument("--exact-backend", choices=("binned", "trimesh"), default="binned",
                   help="exact visibility for --visibility raycast: binned parallel rays (default) or trimesh")
    g.add_argument("--horizon", action="store_true",
                   help="block lights below each triangle's tangent plane (not in the paper; the paper's method lets a "
                   "surface receive light from below its horizon). Measured on the default view at 128x128 with the "
                   "default materials: without --horizon the ground's mean radiance is 24.8 %% higher under the "
                   "default sky and 65.5 %% higher under the courtyard probe (the teapot 2.7 %% / 6.3 %%)")
    g.add_argument("--vsm-res", type=int, default=256, metavar="N", help="shadow map size (default 256)")
    g.add_argument("--vsm-dtype", choices=("float16", "float32", "float64"), default="float32",
                   help="shadow-map moment storage (float16 = the paper's RG16F; default float32)")
    g.add_argument("--ref-rtol", type=float, default=None, metavar="R",
                   help="--mode reference, and the unoccluded terms of --occlusion: estimated relative L1 error to "
                   "converge to (default 2e-3; > 0, e.g. 1e-2 for a quick look)")
    g.add_argument("--workers", type=int, default=None, metavar="W",
                   help="--mode reference: worker processes for its pixel blocks (1 = serial; default "
                   "$IBL_REF_WORKERS or min(2, CPUs)); the image is bit-for-bit the same for every W")
    g.add_argument("--spp", type=int, default=1024, metavar="N",
                   help="--mode mitsuba: samples per pixel (two halves with seeds S, S+1 estimate the noise)")
    g.add_argument("--mitsuba-ggx", choices=("lab", "builtin", "both"), default="both",
                   help="--mode mitsuba with a GGX material: the lab's GGX formula as a Python BSDF (lab), Mitsuba's "
                   "own roughconductor (builtin: separable Smith and Fresnel 1, so it needs smith=separable and "
                   "f0=1), or both (default): the image is the lab's, the JSON records the built-in's difference "
                   "(the built-in is skipped, with a note, where it does not apply)")
    g.add_argument("--seed", type=int, default=0, metavar="S",
                   help="--mode mitsuba: first seed; --mode reference: seed of its random ray points; --occlusion "
                   "with oracle inputs: seed of the ray directions (default 0)")
    g = p.add_argument_group("occlusion methods (instead of --mode; see below)")
    g.add_argument("--occlusion", metavar="METHOD",
                   help="render with an occlusion method engines ship, a label of ibl_ref.occlusion (listed below, "
                   "e.g. ao-diffuse, lagarde2014-alpha, gtso-exact-alpha, prt-5, regions-exact): the exact "
                   "unoccluded lighting of --material / --ground-material darkened by METHOD; regions-exact splits "
                   "the map into --lights median-cut regions (--median-cut)")
    g.add_argument("--occlusion-inputs", choices=INPUT_KINDS, default=None,
                   help="what METHOD reads: oracle (default) = exact AO, bent normal, SH transfer, per-region "
                   "visibility by ray casting; screen-space = AO and bent normals estimated from the depth buffer by "
                   "GTAO, as engines do (only for the methods that read nothing else)")
    g.add_argument("--n-face", type=int, default=None, metavar="N",
                   help="oracle inputs: face size of the cube of ray-direction cells, 6*N^2 rays per point and set "
                   "(default min(16, --env-size); --occlusion regions-exact: --env-size must be a multiple of N)")
    g.add_argument("--n-sets", type=int, default=None, metavar="K",
                   help="oracle inputs: independent stratified ray sets, their spread is the inputs' error estimate "
                   "(default 2)")
    g.add_argument("--gtao-radius", type=float, default=None, metavar="R",
                   help="screen-space inputs: GTAO's search radius in world units (default 0.5; the teapot is "
                   "about 3 units tall)")
    g = p.add_argument_group("camera (perspective, y is up)")
    g.add_argument("--size", type=int, nargs="+", default=[96, 96], metavar="N",
                   help="image size W H in pixels, or one N for N x N (default 96 96)")
    g.add_argument("--fov", type=float, default=40.0, metavar="DEG",
                   help="VERTICAL field of view in degrees (default 40)")
    g.add_argument("--camera-eye", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="eye position (default: on --view-dir at --distance from the target)")
    g.add_argument("--camera-target", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="point looked at (default: centre of the mesh's bounding sphere)")
    g.add_argument("--camera-up", type=float, nargs=3, default=[0.0, 1.0, 0.0], metavar=("X", "Y", "Z"),
                   help="up hint (default 0 1 0)")
    g.add_argument("--view-dir", type=float, nargs=3, default=[0.3, 0.5, 1.0], metavar=("X", "Y", "Z"),
                   help="direction from the target to the eye when --camera-eye is not given (default 0.3 0.5 1, "
                   "the view of 'ibl-ref experiment fig6')")
    g.add_argument("--distance", default="2.6", metavar="R|fit",
                   help="eye distance from the target in bounding radii of the mesh (default 2.6), or 'fit': the "
                   "mesh's bounding sphere fits the vertical field of view with a 10%% margin")
    g = p.add_argument_group("output")
    g.add_argument("--out", required=True, metavar="OUT.exr",
                   help="output radiance image: .exr (float32 RGB) or .npz (image + intermediate buffers)")
    g.add_argument("--png", metavar="OUT.png", help="also write a tone-mapped PNG preview")
    g.add_argument("--background", choices=("env", "black"), default="env",
                   help="pixels without geometry: the environment seen along the camera ray (default; the same "
                   "look-up a mirror reflection gets) or black")
    g.add_argument("--exposure", default="auto", metavar="auto|EV|xK",
                   help="PNG exposure: 'auto' (default: one exposure per environment, its solid-angle mean "
                   "radiance maps to 0.5, so the previews of every mode and method of a scene compare by eye), "
                   "'image' (per image: the object's 90th-percentile luminance maps to 0.8), EV stops (e.g. -2), "
                   "or a linear scale (e.g. x0.25); the sidecar JSON records the stops and the rule")
    g.add_argument("--progress", dest="progress", action="store_true", default=True,
                   help="report progress on stderr (default): a bar on a terminal, a status line at most every "
                   "10 s in a log ($IBL_REF_PROGRESS_INTERVAL)")
    g.add_argument("--no-progress", dest="progress", action="store_false",
                   help="no progress reports (also: $IBL_REF_PROGRESS=0)")
    from .radiance_args import add_radiance_args

    add_radiance_args(p)
    p.set_defaults(func=cmd_render)
