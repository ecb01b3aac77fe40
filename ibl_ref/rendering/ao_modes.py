"""Comparison modes of Knuth et al. (2014), Fig. 6: no occlusion, AO (shadow only), AO with color, our method.

Fig. 6 compares the paper's method with ambient occlusion on a **pure glossy** material ("no additional diffuse
term").  The paper gives no formulas for (a)–(c); the readings implemented here (all from the same median-cut
lights, the same G-buffer and the same PEM lookups, so only the occlusion model differs):

* ``"no-occlusion"`` (a): c = kd·Σ_i PEM_i(n, 0) + ks·Σ_i PEM_i(r, g) — the full filtered map (by linearity of
  the pyramid, Σ_i PEM_i = the full map's lookup, Sec. 3.1).
* ``"ao"`` (b) AO, shadow only: a scalar ambient-occlusion factor times the unoccluded lighting,
  AO = Σ_i VIS_i w_i / Σ_i w_i with w_i = max(n·ω_i, 0)·Ω_i — the cosine-weighted visible fraction of the
  hemisphere, estimated from the same lights' visibilities (VSM by default, ``ao_visibility="raycast"`` for exact
  binary visibility of the light directions; the lights tile the sphere, so Σ_i w_i ≈ π).
* ``"ao-color"`` (c) AO with color: each light's shadow carries the light's colour but not the glossy lobe.
  Per channel, E_i = rgb_i·max(n·ω_i, 0)/π (rgb_i = ∫_region L dω; irradiance-like, normalised as the s = 1 lobe
  average), and
  ``ao_color_variant="modulate"`` (default): c = unoccluded ⊙ Σ_i VIS_i E_i / Σ_i E_i (a coloured AO factor
  applied to the glossy lighting: the material stays glossy, the shadow colour comes from the lights);
  ``"irradiance"``: c = (kd + ks)·Σ_i VIS_i E_i (the literal Σ VIS_i·E_i: a diffuse, coloured, shadowed image).
  Which one the paper shows is not stated; "modulate" keeps the glossy appearance that all four images share.
* ``"ours"`` (d): Eq. 5 with a kd/ks material, c = Σ_i VIS_i (kd·PEM_i(n, 0) + ks·PEM_i(r, g)), VIS_i from
  variance shadow maps (:mod:`ibl_ref.rendering.vsm`).  With kd = 0 this is exactly :func:`ibl_ref.rendering.render.render_pem`.
  Look-ups, visibilities and the Eq. 5 sum are :mod:`ibl_ref.rendering.render`'s (``eq5_lookups``, ``light_visibilities``,
  ``shade_eq5``): one Eq. 5 path, the modes differ only in the occlusion model applied to it.
* ``"reference"``: :func:`ibl_ref.rendering.reference_render.render_reference` (exact visibility, exact lobes).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import IBLError
from .render import light_visibilities, shade_eq5  # the one Eq. 5 path
from .scenes import default_camera
from ..environment.validated import as_environment
from .raster import prepare_scene
from .raster import rasterize
from .reference_render import render_reference
from .render import BACKGROUNDS
from .render import apply_background
from .render import eq5_lookups
from .render import unshadowed_eq5

__all__ = ["MODES", "ModesResult", "render_modes", "render_mode"]

MODES = ("ours", "no-occlusion", "ao", "ao-color", "reference")
AO_COLOR_VARIANTS = ("modulate", "irradiance")


@dataclass
class ModesResult:
    """Images (H, W, C) per mode, coverage mask, G-buffer and timings (seconds per stage).

    ``extras`` holds auxiliary images: ``"reference-unoccluded"`` (the reference with V ≡ 1) when the reference
    was rendered.
    """

    images: dict
    mask: np.ndarray
    gbuffer: object
    timings: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)
    extras: dict = field(default_factory=dict)


def _check_material(kd, ks, g):
    kd, ks, g = float(kd), float(ks), float(g)
    if not (np.isfinite(kd) and np.isfinite(ks) and kd >= 0 and ks >= 0):
        raise IBLError(f"kd, ks must be finite and >= 0, got {kd}, {ks}")
    if not (0.0 <= g <= 1.0):
        raise IBLError(f"g must be in [0, 1], got {g}")
    return kd, ks, g


def render_modes(meshes, camera, env, modes=MODES, *, pems=None, n_lights: int = 96, kd: float = 0.0,
                 ks: float = 1.0, g: float = 0.9, vsm_resolution: int = 256, vsm_dtype: str = "float32",
                 ao_visibility: str = "vsm", ao_color_variant: str = "modulate", reference_kw: dict | None = None,
                 smooth_normals: bool = True, background: str = "black", materials=None, progress: bool = False,
                 **vsm_kw) -> ModesResult:
    """Render several Fig. 6 modes sharing the G-buffer, PEMs and visibilities.

    Parameters
    ----------
    meshes, camera : scene and view (see :func:`ibl_ref.rendering.raster.prepare_scene`)
    env : (6, N, N, C) radiance cube (N a power of two)
    modes : subset of :data:`MODES`
    pems : a prebuilt :class:`ibl_ref.knuth2014.pem.PEMSet` of ``env`` (else built with ``n_lights`` per-face median cut)
    kd, ks, g : material (diffuse weight, glossy weight, glossiness of the glossy lobe)
    materials : optional per-mesh materials instead of kd, ks, g: a :class:`ibl_ref.rendering.render.Material`, a
        (kd, ks, g) tuple, or ``{material_id: ...}`` (as :func:`ibl_ref.rendering.render.render_pem`); every mode honours
        them (the reference is rendered once per material on that material's pixels; it needs scalar kd, ks and
        no g map)
    vsm_resolution, vsm_dtype, **vsm_kw : shadow maps (:func:`ibl_ref.rendering.vsm.build_vsm`)
    ao_visibility : "vsm" or "raycast" visibility for the AO modes
    ao_color_variant : "modulate" or "irradiance" (module docstring)
    reference_kw : extra arguments of :func:`ibl_ref.rendering.reference_render.render_reference`
    background : ``"black"`` (default) or ``"env"``: every mode's image (the reference too) shows the environment
        along the camera rays outside the geometry (:func:`ibl_ref.rendering.render.background_image` of ``env``, the
        bilinear mirror look-up; the same backdrop in every mode)

    Returns
    -------
    ModesResult (``timings`` in seconds: pem_build, raster, shadow_maps, blur, visibility, lookup, shading, reference)
    """

    kd, ks, g = _check_material(kd, ks, g)
    mats = None
    if materials is not None:
        from .render import resolve_materials

        mats = resolve_materials(materials)
    if background not in BACKGROUNDS:
        raise IBLError(f"background must be one of {BACKGROUNDS}, got {background!r}")
    modes = tuple(modes)
    bad = [m for m in modes if m not in MODES]
    if bad or not modes:
        raise IBLError(f"modes must be a non-empty subset of {MODES}, got {modes!r}")
    if ao_color_variant not in AO_COLOR_VARIANTS:
        raise IBLError(f"ao_color_variant must be one of {AO_COLOR_VARIANTS}, got {ao_color_variant!r}")
    if ao_visibility not in ("vsm", "raycast"):
        raise IBLError(f"ao_visibility must be 'vsm' or 'raycast', got {ao_visibility!r}")

    env = as_environment(env, "environment")
    T: dict = {}
    sc = prepare_scene(meshes, warn=False)
    t0 = time.perf_counter()
    gb = rasterize(sc, camera, smooth_normals=smooth_normals)
    T["raster"] = time.perf_counter() - t0
    m = gb.mask
    H, W = m.shape
    C = env.shape[-1]
    images = {}
    info = dict(kd=kd, ks=ks, g=g, n_pixels=int(m.sum()), ao_color_variant=ao_color_variant,
                ao_visibility=ao_visibility, vsm_resolution=vsm_resolution)
    if mats is not None:  # per-pixel kd (P, K), ks (P, K), g (P,) from the material ids
        from .render import material_images

        kd_l, ks_l, g_l = material_images(meshes, sc, gb, mats)
        info.update(kd=None, ks=None, g=None, materials={str(k): dict(kd=np.asarray(v.kd).tolist(),
                                                                       ks=np.asarray(v.ks).tolist(), g=v.g)
                                                          for k, v in mats.items()})
    else:
        kd_l, ks_l, g_l = kd, ks, g
    need_pem = any(x in modes for x in ("ours", "no-occlusion", "ao", "ao-color"))
    if need_pem:
        if pems is None:
            from ..knuth2014.pem import build_pems

            t0 = time.perf_counter()
            pems = build_pems(env, n_lights=int(n_lights), progress=progress)
            T["pem_build"] = time.perf_counter() - t0
        info["n_lights"] = len(pems.lights)
        P, n, fn, r = gb.position[m], gb.normal[m], gb.face_normal[m], gb.reflect[m]
        t0 = time.perf_counter()
        pem_n, pem_r = eq5_lookups(pems, n, r, g_l, kd_l, ks_l)  # the Eq. 5 look-ups (ibl_ref.rendering.render)
        T["lookup"] = time.perf_counter() - t0
        unocc = unshadowed_eq5(pem_n, pem_r, kd_l, ks_l)
        vis_cache = {}

        def vis(method):
            if method not in vis_cache:
                vis_cache[method] = light_visibilities(sc, P, fn, pems.lights, method=method,
                                                       vsm_resolution=vsm_resolution, vsm_dtype=vsm_dtype,
                                                       timings=T, progress=progress, **dict(vsm_kw))
            return vis_cache[method]

        out = {}
        t_shade = 0.0
        if "no-occlusion" in modes:
            out["no-occlusion"] = unocc
        if "ours" in modes:
            V = vis("vsm")
            t0 = time.perf_counter()
            out["ours"] = shade_eq5(V, pem_n, pem_r, kd_l, ks_l)  # Eq. 5
            t_shade += time.perf_counter() - t0
        if "ao" in modes or "ao-color" in modes:
            V = vis(ao_visibility)
            t0 = time.perf_counter()
            dirs = np.asarray(pems.lights.directions, dtype=np.float64)
            cosw = np.clip(n @ dirs.T, 0.0, None).T  # (L, P): max(n·ω_i, 0)
            if "ao" in modes:
                w = cosw * np.asarray(pems.lights.solid_angle, dtype=np.float64)[:, None]
                ws = w.sum(axis=0)
                ao = np.where(ws > 0, (V * w).sum(axis=0) / np.where(ws > 0, ws, 1.0), 1.0)
                out["ao"] = unocc * ao[:, None]
                info["ao_mean"] = float(ao.mean()) if len(ao) else float("nan")
            if "ao-color" in modes:
                rgb = np.asarray(pems.lights.rgb, dtype=np.float64).reshape(len(dirs), -1)
                E = cosw[:, :, None] * rgb[:, None, :] / np.pi  # (L, P, C)
                visE = np.einsum("lp,lpc->pc", V, E)
                if ao_color_variant == "irradiance":
                    out["ao-color"] = (kd_l + ks_l) * visE
                else:
                    Es = E.sum(axis=0)
                    f = np.where(Es > 0, visE / np.where(Es > 0, Es, 1.0), 1.0)
                    out["ao-color"] = unocc * f
            t_shade += time.perf_counter() - t0
        T["shading"] = t_shade
        for k, v in out.items():
            img = np.zeros((H, W, C))
            img[m] = v
            images[k] = img
    if "reference" in modes:
        from ..progress import step
        from .reference_render import render_reference

        t0 = time.perf_counter()
        with step(f"converged reference of {int(m.sum())} pixels", enabled=progress):
            if mats is None:
                ref = render_reference(sc, camera, env, kd=kd, ks=ks, g=g, gbuffer=gb, progress=progress,
                                       **(reference_kw or {}))
                ref_img, ref_un, info["reference"] = ref.image, ref.unoccluded, ref.info
            else:
                ref_img, ref_un, info["reference"] = _reference_per_material(sc, camera, env, gb, mats, progress,
                                                                             reference_kw or {})
        T["reference"] = time.perf_counter() - t0
        images["reference"] = ref_img
    extras = {}
    if "reference" in modes:
        extras["reference-unoccluded"] = ref_un
    for k, v in images.items():
        if not np.all(np.isfinite(v)):
            raise IBLError(f"mode {k!r} produced non-finite values")
        apply_background(v, m, camera, env, background)
    return ModesResult(images={k: images[k] for k in modes}, mask=m, gbuffer=gb, timings=T, info=info, extras=extras)


def _reference_per_material(scene, camera, env, gb, mats, progress, reference_kw):
    """The reference on each material's pixels (a G-buffer masked to its material id), summed into one image."""
    import dataclasses


    H, W = gb.mask.shape
    img = np.zeros((H, W, env.shape[-1]))
    un = np.zeros_like(img)
    infos = {}
    for key, mat in mats.items():
        if np.ndim(mat.kd) or np.ndim(mat.ks) or mat.g_map is not None:
            raise IBLError("mode 'reference' needs scalar kd, ks and no g map per material")
        sub = gb.mask if key is None else gb.mask & (gb.material_id == key)
        if not sub.any():
            continue
        r = render_reference(scene, camera, env, kd=mat.kd, ks=mat.ks, g=mat.g, progress=progress,
                             gbuffer=dataclasses.replace(gb, mask=sub), **reference_kw)
        img[sub] = r.image[sub]
        un[sub] = r.unoccluded[sub]
        infos[str(key)] = r.info
    return img, un, infos


def render_mode(scene, env, mode: str, *, camera=None, **kw) -> np.ndarray:
    """One Fig. 6 image (H, W, C) for ``mode`` ∈ :data:`MODES` (keywords as :func:`render_modes`).

    ``scene`` are the meshes; ``camera`` defaults to :func:`ibl_ref.rendering.scenes.default_camera` (64² px).
    """
    if mode not in MODES:
        raise IBLError(f"mode must be one of {MODES}, got {mode!r}")
    cam = default_camera(scene) if camera is None else camera
    return render_modes(scene, cam, env, (mode,), **kw).images[mode]
