"""The image of one occlusion method: a scene, a camera, an environment cube and a material shaded by one method of
:data:`~ibl_ref.occlusion.registry.OCCLUSION_METHODS`, with exact unoccluded terms and the inputs it declares.

The route (one implementation: the occlusion zoo, :mod:`ibl_ref.experiments.occlusion_zoo`, calls these same
functions, and ``ibl-ref render --occlusion METHOD`` calls :func:`occlusion_image`):

1. :func:`scene_pixels` — rasterize the scene (:func:`ibl_ref.rendering.raster.rasterize`): per covered pixel the
   shading normal n, the direction toward the viewer v, the position and the geometric normal n_g; a mesh carrying a
   normal map (``mesh.metadata["normal_map"]``, :mod:`ibl_ref.rendering.normal_map`) has its n perturbed there, in
   the G-buffer itself, so that every later step — the exact reference, the oracle inputs and GTAO's cosine weighting
   (the normal a deferred engine's G-buffer stores) — sees the mapped n, while positions, depth and n_g stay those of
   the geometry (GTAO's horizons come from that depth);
2. :func:`unoccluded_terms` — the exact unoccluded (V ≡ 1) terms of the material
   (:class:`~ibl_ref.occlusion.interface.UnoccludedTerms`): the diffuse lobe average A_1(n) = ∫ L max(n·ω, 0)/π dω
   and the specular term S — GGX ``f_s(ω, v)(n·ω)⁺`` (Karis 2013's α = r², Fresnel F0, the Smith form of the
   material) or ks times the Phong lobe average about r = 2(n·v)n − v (Knuth et al. 2014, Eq. 3–4, the reference
   renderer's conventions, :mod:`ibl_ref.rendering.materials`) — converged to ``rtol`` by
   :func:`ibl_ref.rendering.unoccluded_reference.integrate`; for a per-region method the same terms of every
   region's partial environment (Knuth et al. 2014, Sec. 3.1: median-cut regions, :func:`stack_regions`), zero on
   back-facing pixels (n·v ≤ 0);
3. the inputs the method declares (:attr:`~ibl_ref.occlusion.interface.OcclusionMethod.needs`), of one kind:
   ``"oracle"`` — exact, from one stratified ray-cast visibility set (:func:`trace_oracle_inputs`,
   :mod:`ibl_ref.occlusion.oracle_inputs`: cosine-weighted AO, the bent normal, the SH visibility transfer (vector and
   glossy transfer matrix), the per-region visible fractions, each with its standard error), or ``"screen-space"`` —
   AO and bent normals estimated from the depth buffer by GTAO's horizon search (:func:`screen_space_inputs`,
   Jimenez et al. 2016), as engines get them; methods that read more than AO and the bent normal have no screen-space form
   (:func:`input_kinds`);
4. :func:`method_inputs` and :func:`apply_method` — the method's :class:`~ibl_ref.occlusion.interface.OcclusionResult`
   applied to the terms by :func:`~ibl_ref.occlusion.interface.shade`.

**Materials** (:func:`check_request`): anything :func:`ibl_ref.rendering.materials.as_material` accepts with
scalar weights — GGX with an optional Lambertian kd, Phong ``kd, ks, g`` with g < 1 — one for every mesh or one per
material id of the scene.  A Phong glossy lobe (ks > 0) has no GGX roughness, so only the methods that read none
(:attr:`~ibl_ref.occlusion.interface.OcclusionMethod.reads_roughness` False: no occlusion, AO, multi-bounce AO,
the horizon fades, PRT, per-region visibility) can serve it; the others refuse it in one line, as they refuse RGB
weights and glossiness maps.  The roughness fed to a method is the material's r (1 for a Phong material: its
specular formulas are then not read, or the specular term is 0), the albedo of multi-bounce AO is min(kd, 1).

Examples
--------
A floor under a constant sky: nothing occludes it, so every method gives the unoccluded image, kd·L:

>>> import numpy as np, trimesh
>>> from ibl_ref.occlusion.image import occlusion_image
>>> from ibl_ref.rendering.camera import PerspectiveCamera
>>> floor = trimesh.Trimesh([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], [[0, 2, 1], [0, 3, 2]], process=False)
>>> cam = PerspectiveCamera(eye=(0, 2, 0.5), target=(0, 0, 0), up=(0, 1, 0), fov_y_deg=30, width=4, height=4)
>>> res = occlusion_image(floor, cam, np.full((6, 4, 4, 3), 2.0), (0.5, 0.0, 0.0), "ao-diffuse", n_face=4)
>>> bool(np.allclose(res.image[res.mask], 1.0, rtol=1e-3)), bool(np.all(res.inputs["ao"] == 1.0))
(True, True)
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..errors import IBLError
from ..limits import positive_int
from .interface import OcclusionInputs, OcclusionMethod, UnoccludedTerms, shade
from .registry import OCCLUSION_METHODS, get

__all__ = [
    "CHUNK_CELLS",
    "COMMON_FIELDS",
    "DEFAULT_GTAO_RADIUS",
    "INPUT_KINDS",
    "SCREEN_SPACE_FIELDS",
    "SH_ORDER",
    "OcclusionImage",
    "OcclusionRequestError",
    "ScenePixels",
    "apply_method",
    "check_request",
    "input_kinds",
    "method_inputs",
    "occlusion_image",
    "scene_pixels",
    "screen_space_inputs",
    "shading_inputs",
    "specular_weight",
    "stack_regions",
    "trace_oracle_inputs",
    "unoccluded_terms",
]

#: the input kinds: exact (ray-cast visibility) and estimated from the depth buffer by GTAO
INPUT_KINDS = ("oracle", "screen-space")
#: what GTAO estimates (the other inputs exist only as oracle inputs)
SCREEN_SPACE_FIELDS = frozenset({"ao", "bent_normal"})
#: fields every method gets in both kinds (geometry and material)
COMMON_FIELDS = frozenset({"normal", "view", "roughness", "geo_normal", "albedo"})
#: the SH order of the oracle's visibility transfer (order 5: 25 coefficients; PRT order 3 reads the first 9)
SH_ORDER = 5
#: cells per chunk of the unoccluded integral for a 3-channel map (its default; fewer for stacked region channels)
CHUNK_CELLS = 300_000
#: GTAO's search radius by default (world units; engines use about half a metre, :func:`ibl_ref.occlusion.gtao.gtao`)
DEFAULT_GTAO_RADIUS = 0.5


class OcclusionRequestError(IBLError):
    """A request an occlusion method cannot serve: an unknown method, an input kind it cannot be fed, a material
    it cannot shade, or (on the command line) a render mode it does not combine with."""


@dataclass(frozen=True, eq=False)
class ScenePixels:
    """The covered pixels of one view (P of them, in row-major order of ``mask``).

    Attributes
    ----------
    meshes : object
        The scene as given.
    scene : Scene
        The prepared scene (:func:`ibl_ref.rendering.raster.prepare_scene`), also the occluder.
    camera : PerspectiveCamera or OrthographicCamera
    gbuffer : GBuffer
        :func:`ibl_ref.rendering.raster.rasterize` of the scene.
    mask : ndarray (H, W) of bool
        The covered pixels.
    normal, view, position, face_normal : ndarray (P, 3)
        Shading normal n (normal-mapped where the mesh carries a map), unit direction toward the viewer v, world
        position, geometric normal n_g.
    material_id : ndarray (P,) of int
    """

    meshes: object
    scene: object
    camera: object
    gbuffer: object
    mask: np.ndarray
    normal: np.ndarray
    view: np.ndarray
    position: np.ndarray
    face_normal: np.ndarray
    material_id: np.ndarray

    @property
    def n_pixels(self) -> int:
        return int(self.normal.shape[0])

    @property
    def front(self) -> np.ndarray:
        """(P, 1) bool: n·v > 0 (a back-facing pixel gets no light: its terms are 0)."""
        return (np.sum(self.normal * self.view, axis=1) > 0)[:, None]

    def subset(self, rows):
        """The same view restricted to the covered pixels ``rows`` (indices into P); ``None``: ``self``."""
        if rows is None:
            return self
        return ScenePixels(self.meshes, self.scene, self.camera, self.gbuffer, self.mask, self.normal[rows],
                           self.view[rows], self.position[rows], self.face_normal[rows], self.material_id[rows])


@dataclass(frozen=True, eq=False)
class OcclusionImage:
    """What :func:`occlusion_image` returns.

    Attributes
    ----------
    image : (H, W, C) float64
        The method's shading (0 outside ``mask``).
    unoccluded : (H, W, C) float64
        The same terms with V ≡ 1 (the method ``none``; 0 outside ``mask``).
    mask : (H, W) bool
        Covered pixels.
    inputs : dict
        The inputs the method was fed: ``normal``, ``view`` and every field it reads, per covered pixel (P, …) in
        row-major order of ``mask`` (``env_sh``: (K, C), not per pixel); :meth:`input_image` lays one out as an image.
    timings : dict
        Seconds: ``inputs_s`` (ray casts or GTAO), ``terms_s`` (the unoccluded integrals, median cut included),
        ``method_s`` (the method and :func:`~ibl_ref.occlusion.interface.shade`), ``total_s``.
    info : dict
        JSON-ready: the method (name, parameters, what it reads, citation), the input kind and its settings and
        error estimates, the materials, the regions, the integrals' estimated error.
    """

    image: np.ndarray
    unoccluded: np.ndarray
    mask: np.ndarray
    inputs: dict
    timings: dict
    info: dict

    def input_image(self, name: str) -> np.ndarray:
        """Input ``name`` laid out as an image (H, W, …), 0 on uncovered pixels."""
        v = np.asarray(self.inputs[name])
        out = np.zeros(self.mask.shape + v.shape[1:], dtype=v.dtype)
        out[self.mask] = v
        return out


# ------------------------------------------------------------------------------------------------------------------
# checks
# ------------------------------------------------------------------------------------------------------------------
def input_kinds(method: OcclusionMethod, **params) -> tuple:
    """The input kinds ``method`` (with these parameter overrides) can be fed: ``"oracle"`` always,
    ``"screen-space"`` when it reads nothing GTAO does not estimate (:data:`SCREEN_SPACE_FIELDS`)."""
    extra = set(method.inputs_needed(**params)) - COMMON_FIELDS
    return INPUT_KINDS if extra <= SCREEN_SPACE_FIELDS else ("oracle",)


def _method(method) -> OcclusionMethod:
    if isinstance(method, OcclusionMethod):
        return method
    try:
        return get(method)
    except IBLError as exc:
        raise OcclusionRequestError(str(exc)) from None


def _served(meth: OcclusionMethod, material, where: str):
    """The material (:func:`ibl_ref.rendering.method_shading.shading_material`: a ``PhongMaterial`` or
    ``GGXMaterial``, checked) if ``meth`` can shade it, or a one-line :class:`OcclusionRequestError`."""
    from ..rendering.method_shading import shading_material

    who = f"occlusion method {meth.name!r}"
    try:
        m = shading_material(material)
    except IBLError as exc:  # (as_material names its argument "material": the caller's name is ``where``)
        raise OcclusionRequestError(f"{who} cannot shade {where}: {str(exc).removeprefix('material: ')}") from None
    if m.has_specular and m.ggx_roughness is None and meth.reads_roughness:  # a Phong glossy lobe
        free = ", ".join(n for n, x in OCCLUSION_METHODS.items() if not x.reads_roughness)
        raise OcclusionRequestError(
            f"{who} cannot shade {where}, a Phong glossy lobe (ks = {m.ks:g}, g = {m.g:g}): its specular "
            f"formula reads the GGX roughness, which a Phong lobe does not have; use a GGX material (ggx:ROUGHNESS) "
            f"or a method that reads no roughness ({free})")
    return m


def check_request(method, material, inputs: str = "oracle", *, params=None, where: str = "material"):
    """Check, before any work, that ``method`` can be fed ``inputs`` and can shade ``material``.

    Parameters
    ----------
    method : str or OcclusionMethod
        A label of :data:`~ibl_ref.occlusion.registry.OCCLUSION_METHODS` or a method.
    material : material, dict or None
        One material (anything :func:`ibl_ref.rendering.materials.as_material` accepts: ``PhongMaterial``,
        ``GGXMaterial``, ``"ggx:0.3"``, ``(kd, ks, g)``, a dict with ``kind``) or ``{material_id: material}``;
        None: the method and the inputs only.
    inputs : {"oracle", "screen-space"}
    params : dict, optional
        Parameter overrides of the method.
    where : str
        How messages name the material (the CLI passes its flag).

    Returns
    -------
    method : OcclusionMethod
    materials : dict
        ``{None: material}`` for one material, ``{material_id: material}`` for a mapping (each a checked
        :class:`~ibl_ref.rendering.materials.PhongMaterial` or :class:`~ibl_ref.rendering.materials.GGXMaterial`),
        ``{}`` for None.

    Raises
    ------
    OcclusionRequestError
        An unknown method or parameter, an unknown input kind or one the method cannot be fed, a material it
        cannot shade (module docstring).
    """
    meth = _method(method)
    params = dict(params or {})
    try:
        meth.inputs_needed(**params)
    except IBLError as exc:
        raise OcclusionRequestError(str(exc)) from None
    if inputs not in INPUT_KINDS:
        raise OcclusionRequestError(f"inputs must be one of {', '.join(INPUT_KINDS)}, got {inputs!r}")
    kinds = input_kinds(meth, **params)
    if inputs not in kinds:
        extra = sorted(set(meth.inputs_needed(**params)) - COMMON_FIELDS - SCREEN_SPACE_FIELDS)
        raise OcclusionRequestError(
            f"occlusion method {meth.name!r} reads {', '.join(extra)}, which screen-space inputs (GTAO: AO and bent "
            "normals) do not estimate; feed it oracle inputs")
    if material is None:
        return meth, {}
    if _is_mapping(material):
        return meth, {int(k): _served(meth, m, f"{where} {int(k)}") for k, m in material.items()}
    return meth, {None: _served(meth, material, where)}


def _is_mapping(material) -> bool:
    """``{material_id: material}`` (every key an integer) rather than one material's parameters."""
    return isinstance(material, dict) and bool(material) and all(
        isinstance(k, (int, np.integer)) and not isinstance(k, bool) for k in material)


# ------------------------------------------------------------------------------------------------------------------
# the steps
# ------------------------------------------------------------------------------------------------------------------
def scene_pixels(meshes, camera) -> ScenePixels:
    """Rasterize ``meshes`` (anything :func:`ibl_ref.rendering.raster.prepare_scene` accepts) with ``camera``, the
    shading normals of meshes that carry a normal map perturbed by it
    (:func:`ibl_ref.rendering.normal_map.apply_normal_maps`; ``gbuffer`` holds the perturbed normals)."""
    from ..rendering.normal_map import apply_normal_maps
    from ..rendering.raster import prepare_scene, rasterize

    sc = prepare_scene(meshes, warn=False)
    gb = apply_normal_maps(meshes, sc, rasterize(sc, camera))
    m = gb.mask
    return ScenePixels(meshes=meshes, scene=sc, camera=camera, gbuffer=gb, mask=m, normal=gb.normal[m],
                       view=gb.view[m], position=gb.position[m], face_normal=gb.face_normal[m],
                       material_id=gb.material_id[m])


def trace_oracle_inputs(pixels: ScenePixels, *, n_face: int = 16, n_sets: int = 2, seed: int = 0,
                        sh_order: int | None = SH_ORDER, matrix_order: int | None = None, cache_dir=None,
                        progress: bool = False):
    """Exact inputs from one stratified ray-cast visibility set (:mod:`ibl_ref.occlusion.oracle_inputs`); with
    ``progress`` the trace reports its chunks (:func:`ibl_ref.progress.track`).

    Returns
    -------
    samples : :class:`~ibl_ref.occlusion.oracle_inputs.VisibilitySamples`
        The traced bits (for :func:`~ibl_ref.occlusion.oracle_inputs.region_visibility`).
    fields : dict
        ``ao`` (P,), ``bent_normal`` (P, 3), unless ``sh_order`` is None ``sh_transfer`` (P, sh_order²) and,
        unless ``matrix_order`` is None, ``sh_transfer_matrix`` (P, matrix_order², matrix_order²)
        (:func:`~ibl_ref.occlusion.oracle_inputs.sh_transfer_matrix`; its leading k² × k² block is that of order k).
    info : dict
        ``trace_time_s`` (the trace and the fields), the AO's mean and largest standard error, the bent normal's
        mean angular error (rad), ``n_rays``.
    """
    from . import oracle_inputs as oi

    t0 = time.perf_counter()
    kw = {} if cache_dir is None else {"cache_dir": cache_dir}
    vs = oi.trace_visibility(pixels.scene, pixels.position, pixels.normal, pixels.face_normal, n_face=n_face,
                             n_sets=n_sets, seed=seed, progress=progress, **kw)
    ao, ao_err = oi.ambient_occlusion(vs)
    bent, bent_err = oi.bent_normal(vs)
    fields = {"ao": ao, "bent_normal": bent}
    if sh_order is not None:
        fields["sh_transfer"] = oi.sh_transfer(vs, sh_order)[0]
    info = {}
    if matrix_order is not None:
        fields["sh_transfer_matrix"], m_err = oi.sh_transfer_matrix(vs, matrix_order)
        info = {"sh_transfer_matrix_err_mean": float(np.nanmean(m_err)),
                "sh_transfer_matrix_err_max": float(np.nanmax(m_err)) if np.isfinite(m_err).any() else float("nan")}
    return vs, fields, {"trace_time_s": time.perf_counter() - t0, "ao_err_mean": float(np.mean(ao_err)),
                        "ao_err_max": float(np.max(ao_err)), "bent_err_mean_rad": float(np.mean(bent_err)),
                        "n_rays": pixels.n_pixels * 6 * n_face ** 2 * n_sets, **info}


def screen_space_inputs(pixels: ScenePixels, *, radius: float = DEFAULT_GTAO_RADIUS):
    """AO (clipped to [0, 1]) and bent normals of the covered pixels by GTAO (:func:`ibl_ref.occlusion.gtao.gtao`,
    Jimenez et al. 2016) with search ``radius`` (world units) → ``(fields, {"gtao_time_s": …})``."""
    from .gtao import gtao

    t0 = time.perf_counter()
    g = gtao(pixels.gbuffer, pixels.camera, radius=radius)
    m = pixels.mask
    fields = {"ao": np.clip(np.asarray(g.ao)[m], 0.0, 1.0), "bent_normal": np.asarray(g.bent_normal)[m]}
    return fields, {"gtao_time_s": time.perf_counter() - t0}


def stack_regions(cube, labels, R: int) -> np.ndarray:
    """(6, N, N, R·C): channel r·C + c holds channel c of region r's partial map (zero outside the region)."""
    C = cube.shape[-1]
    out = np.zeros(cube.shape[:3] + (R, C))
    for r in range(R):
        out[..., r, :] = np.where((labels == r)[..., None], cube, 0.0)
    return out.reshape(cube.shape[:3] + (R * C,))


def _integral(cube, lobe, pixels: ScenePixels, front, rtol):
    from ..rendering.unoccluded_reference import integrate

    # the integral's cell arrays grow with the channels (R regions × C stacked): fewer cells per chunk keep its memory
    # that of a 3-channel map (96 regions at the default chunk needed 22 GB)
    chunk = max(2_000, int(CHUNK_CELLS * 3 / cube.shape[-1]))
    ex = integrate(cube, lobe, pixels.normal, pixels.view, rtol=rtol, chunk_cells=chunk)
    return np.where(front, ex.value, 0.0), float(ex.info["err_rel_l1"])


def unoccluded_terms(cube, m, pixels: ScenePixels, rtol: float, region_sets=None, cache=None,
                     errors=None, with_specular_weight: bool = False) -> dict:
    """The exact unoccluded terms of material ``m`` at ``pixels``: the integrals of its lobes
    (:meth:`~ibl_ref.rendering.materials.BaseMaterial.unoccluded_lobes`), the specular one weighted.

    Parameters
    ----------
    cube : (6, N, N, C) radiance
    m : PhongMaterial or GGXMaterial
        A checked material (:func:`check_request`).
    pixels : ScenePixels
    rtol : float
        Target of each integral's estimated error (:func:`ibl_ref.rendering.unoccluded_reference.integrate`).
    region_sets : {key: (R, stacked cube (6, N, N, R·C))}, optional
        The partial environments of the per-region methods (:func:`stack_regions`).
    cache : dict, optional
        Integrals by (lobe, key), shared by the materials of one (view, environment) that have a lobe in common.
    errors : dict, optional
        Filled with each integral's estimated rel. L1 error, by (lobe, key).
    with_specular_weight : bool
        Also fill ``specular_weight`` (:func:`specular_weight`; a quadrature per pixel for GGX), which glossy PRT
        reads; None otherwise.

    Returns
    -------
    dict
        ``{None: UnoccludedTerms, key: UnoccludedTerms with the region terms (P, R, C)}``.
    """
    lobes = m.unoccluded_lobes()
    kd, dl = m.kd, lobes["diffuse"][1] if m.has_diffuse else None
    ks, sl = lobes.get("specular", (None, None))
    cache = {} if cache is None else cache
    region_sets = region_sets or {}
    front = pixels.front
    C = cube.shape[-1]
    P = pixels.n_pixels

    def get_(lobe, key, weight=None):
        if lobe is None:
            return None
        k = (repr(lobe), key)
        if k not in cache:
            if key is None:
                cache[k], err = _integral(cube, lobe, pixels, front, rtol)
            else:
                R, stacked = region_sets[key]
                value, err = _integral(stacked, lobe, pixels, front, rtol)
                cache[k] = value.reshape(P, R, C)
            if errors is not None:
                errors[k] = err
        return cache[k] if weight is None else weight * cache[k]

    zero = np.zeros((P, C))
    w_s = specular_weight(m, pixels) if with_specular_weight else None
    out = {None: UnoccludedTerms(kd=kd, diffuse=get_(dl, None), specular=(get_(sl, None, ks) if sl is not None
                                                                            else zero), specular_weight=w_s)}
    for key, (R, _) in region_sets.items():
        dr = get_(dl, key)
        sr = get_(sl, key, ks) if sl is not None else np.zeros((P, R, C))
        out[key] = UnoccludedTerms(kd=kd, diffuse=out[None].diffuse, specular=out[None].specular,
                                   diffuse_regions=dr if dr is not None else np.zeros((P, R, C)),
                                   specular_regions=sr, specular_weight=w_s)
    return out


def specular_weight(m, pixels: ScenePixels) -> np.ndarray:
    """w_s (P,): the weight of material ``m``'s specular lobe average in its specular term — Phong: ks (0 without a
    specular part); GGX: the directional albedo F0·A + B by exact quadrature
    (:func:`ibl_ref.prefilter.karis2013.dfg_terms` with the material's Smith form, 0 where n·v ≤ 0).  Glossy PRT
    shades w_s·G with it."""
    if m.ggx_roughness is None:
        return np.full(pixels.n_pixels, m.ks if m.has_specular else 0.0)
    from ..rendering.method_shading import dfg_weight

    nv = np.einsum("pi,pi->p", pixels.normal, pixels.view)
    return dfg_weight(None, nv, m.ggx_roughness, m.f0, m.smith)[:, 0]


def shading_inputs(pixels: ScenePixels, m, channels: int) -> dict:
    """The fields of :class:`~ibl_ref.occlusion.interface.OcclusionInputs` every method gets for material ``m``
    (a checked ``PhongMaterial`` or ``GGXMaterial``): n, v, the roughness (its GGX roughness; 1 for Phong, which
    has none), n_g and the albedo min(kd, 1) per channel."""
    rough = 1.0 if m.ggx_roughness is None else m.ggx_roughness
    albedo = np.full(channels, min(m.kd, 1.0))
    return {"normal": pixels.normal, "view": pixels.view, "roughness": rough, "geo_normal": pixels.face_normal,
            "albedo": albedo}


def method_inputs(method: OcclusionMethod, common: dict, source: dict, *, env_sh=None, region_visibility=None,
                  params=None) -> OcclusionInputs:
    """The :class:`~ibl_ref.occlusion.interface.OcclusionInputs` of ``method``: the ``common`` fields
    (:func:`shading_inputs`), the fields it reads from ``source`` (oracle or screen-space), ``env_sh`` and
    ``region_visibility`` where it reads them."""
    needed = method.inputs_needed(**(params or {}))
    extra = {f: source[f] for f in needed if f in source}
    if "env_sh" in needed:
        extra["env_sh"] = env_sh
    if region_visibility is not None:
        extra["region_visibility"] = region_visibility
    return OcclusionInputs(**common, **extra)


def apply_method(method: OcclusionMethod, inputs: OcclusionInputs, terms: UnoccludedTerms, params=None):
    """``(shaded radiance (P, C), seconds)``: :func:`~ibl_ref.occlusion.interface.shade` of the method's result."""
    t0 = time.perf_counter()
    img = shade(method(inputs, **(params or {})), terms)
    return img, time.perf_counter() - t0


# ------------------------------------------------------------------------------------------------------------------
# the whole image
# ------------------------------------------------------------------------------------------------------------------
def _region_labels(cube, regions, variant):
    """``(labels (6, N, N), R, description)`` from a median-cut count or given labels."""
    if isinstance(regions, (int, np.integer)) and not isinstance(regions, bool):
        from ..knuth2014.median_cut import median_cut

        labels = median_cut(cube, int(regions), variant).labels
        return labels, int(regions), {"median_cut": variant, "n_regions": int(regions)}
    labels = np.asarray(regions)
    if labels.shape != cube.shape[:3] or not np.issubdtype(labels.dtype, np.integer) or labels.min() < 0:
        raise IBLError(f"regions must be a median-cut region count or integer labels >= 0 of shape {cube.shape[:3]}, "
                       f"got {labels.dtype} {labels.shape}")
    R = int(labels.max()) + 1
    return labels, R, {"n_regions": R, "labels": "given"}


def _groups(pixels: ScenePixels, mats: dict):
    """``[(rows or None, material id or None, material)]``: every covered pixel's material."""
    if None in mats:
        return [(None, None, mats[None])]
    present = [int(i) for i in np.unique(pixels.material_id)]
    missing = [i for i in present if i not in mats]
    if missing:
        raise OcclusionRequestError(f"materials: no material for material id(s) {missing} of the scene")
    return [(np.flatnonzero(pixels.material_id == i), i, mats[i]) for i in present]


def _take(x, rows):
    """``x`` (an array, or a dict of arrays) at the covered pixels ``rows`` (None: all)."""
    if rows is None:
        return x
    return {k: v[rows] for k, v in x.items()} if isinstance(x, dict) else x[rows]


def occlusion_image(meshes, camera, cube, material, method, *, inputs: str = "oracle", params=None, regions=6,
                    median_cut_variant: str = "per-face", rtol: float | None = None, n_face: int = 16,
                    n_sets: int = 2, seed: int = 0, gtao_radius: float = DEFAULT_GTAO_RADIUS,
                    cache_dir=None, progress: bool = False) -> OcclusionImage:
    """Render the image of one occlusion method (module docstring: the route).

    Parameters
    ----------
    meshes : trimesh.Trimesh, list of meshes or (mesh, material id) pairs, or Scene
        The scene (:func:`ibl_ref.rendering.raster.prepare_scene`); it is also the occluder.
    camera : PerspectiveCamera or OrthographicCamera
    cube : array_like (6, N, N, C)
        Environment radiance (OpenEXR cube layout), finite and ≥ 0.
    material : material or {material_id: material}
        :func:`check_request`.
    method : str or OcclusionMethod
        A label of :data:`~ibl_ref.occlusion.registry.OCCLUSION_METHODS`.
    inputs : {"oracle", "screen-space"}
        Exact inputs from ray casts, or GTAO's estimate from the depth buffer.
    params : dict, optional
        Parameter overrides of the method.
    regions : int or array (6, N, N) of int
        Per-region methods: the number of median-cut regions (Knuth et al. 2014, Sec. 3.1; ``median_cut_variant``
        as :func:`ibl_ref.knuth2014.median_cut.median_cut`), or every texel's region.
    rtol : float, optional
        Target of the unoccluded integrals' estimated error (default that of the reference renderer,
        :data:`ibl_ref.rendering.reference_converged.DEFAULT_RTOL`).
    n_face, n_sets, seed
        Oracle inputs: face size of the visibility cells (N must be a multiple of it for region methods), the
        independent stratified sets (≥ 2 for an error estimate) and their seed
        (:func:`~ibl_ref.occlusion.oracle_inputs.trace_visibility`).
    gtao_radius : float
        Screen-space inputs: GTAO's search radius in world units.
    cache_dir : path, optional
        Cache of the traced visibility (:func:`~ibl_ref.occlusion.oracle_inputs.trace_visibility`).
    progress : bool
        Report each step (:func:`ibl_ref.progress.step`: the inputs, the median cut, the unoccluded integrals of
        each material) and the trace's chunks; the command line's ``render --occlusion`` turns it on.

    Returns
    -------
    OcclusionImage

    Raises
    ------
    OcclusionRequestError
        :func:`check_request`; a material id of the scene without a material.
    IBLError
        Bad settings, radiance, meshes (:class:`~ibl_ref.errors.MeshError`) or camera; a view that covers no pixel.
    """
    from ..environment.validated import as_environment
    from ..progress import step
    from ..rendering.reference_converged import DEFAULT_RTOL

    t_start = time.perf_counter()
    params = dict(params or {})
    meth, mats = check_request(method, material, inputs, params=params)
    rtol = DEFAULT_RTOL if rtol is None else rtol
    if not (isinstance(rtol, (int, float)) and np.isfinite(rtol) and rtol > 0):
        raise IBLError(f"rtol must be a finite number > 0, got {rtol!r}")
    n_face, n_sets = positive_int("n_face", n_face), positive_int("n_sets", n_sets)
    if not (isinstance(gtao_radius, (int, float)) and np.isfinite(gtao_radius) and gtao_radius > 0):
        raise IBLError(f"gtao_radius must be a finite number > 0, got {gtao_radius!r}")
    cube = as_environment(cube, "environment cube map").data
    needed = meth.inputs_needed(**params)
    with_regions = "region_visibility" in needed
    if with_regions and inputs == "oracle" and cube.shape[1] % n_face:
        raise IBLError(f"the environment's face size {cube.shape[1]} must be a multiple of n_face={n_face} (each "
                       "visibility cell is a block of environment texels)")

    px = scene_pixels(meshes, camera)
    if px.n_pixels == 0:
        raise IBLError("the scene covers no pixel of the camera's view")
    groups = _groups(px, mats)

    t0 = time.perf_counter()
    order = max(SH_ORDER, int(dict(meth.params, **params).get("order") or 0))
    env_sh, region_vis, region_info, region_sets = None, None, None, {}
    if inputs == "oracle":
        with step(f"oracle inputs ({px.n_pixels} pixels x {6 * n_face ** 2 * n_sets} rays)", enabled=progress):
            vs, source, input_info = trace_oracle_inputs(px, n_face=n_face, n_sets=n_sets, seed=seed,
                                                         sh_order=order if "sh_transfer" in needed else None,
                                                         matrix_order=(order if "sh_transfer_matrix" in needed
                                                                       else None),
                                                         cache_dir=cache_dir, progress=progress)
        input_info.update(n_face=n_face, n_sets=n_sets, seed=seed)
    else:
        with step(f"screen-space inputs (GTAO, {px.n_pixels} pixels)", enabled=progress):
            source, input_info = screen_space_inputs(px, radius=gtao_radius)
        input_info.update(radius=float(gtao_radius))
    if "env_sh" in needed:
        from ..groundtruth.sh_basis import sh_project

        env_sh = sh_project(cube, order - 1)
    t_inputs = time.perf_counter() - t0
    if with_regions:  # the median cut counts with the terms, the visible fractions with the inputs
        from . import oracle_inputs as oi

        t0 = time.perf_counter()
        with step("median-cut regions and their stacked maps", enabled=progress):
            labels, R, region_info = _region_labels(cube, regions, median_cut_variant)
            region_sets = {R: (R, stack_regions(cube, labels, R))}
        t1 = time.perf_counter()
        region_vis = oi.region_visibility(vs, cube, labels)[0]
        t_inputs += time.perf_counter() - t1
        t_terms = t1 - t0
    else:
        t_terms = 0.0
    key = next(iter(region_sets), None)

    C = cube.shape[-1]
    image, unocc = np.zeros(px.mask.shape + (C,)), np.zeros(px.mask.shape + (C,))
    flat, flat_un = np.zeros((px.n_pixels, C)), np.zeros((px.n_pixels, C))
    fed, errors, t_method = {}, {}, 0.0
    for k, (rows, _mid, m) in enumerate(groups):
        sub = px.subset(rows)
        t0 = time.perf_counter()
        with step(f"unoccluded integrals, material {k + 1} of {len(groups)} ({m.kind}, {sub.n_pixels} pixels)",
                  enabled=progress):
            terms = unoccluded_terms(cube, m, sub, rtol, region_sets, {}, errors,
                                     with_specular_weight="sh_transfer_matrix" in needed)
        t_terms += time.perf_counter() - t0
        common = shading_inputs(sub, m, C)
        inp = method_inputs(meth, common, _take(source, rows), env_sh=env_sh, params=params,
                            region_visibility=None if region_vis is None else _take(region_vis, rows))
        img, dt = apply_method(meth, inp, terms[key], params)
        t_method += dt
        sel = slice(None) if rows is None else rows
        flat[sel] = img
        flat_un[sel] = shade(get("none")(OcclusionInputs(**common)), terms[None])
        for f in ("normal", "view") + tuple(needed):
            v = np.asarray(getattr(inp, f), dtype=np.float64)
            if f == "env_sh":
                fed[f] = v
                continue
            if v.ndim == 1 and f == "albedo":  # one albedo per channel: per pixel
                v = np.broadcast_to(v, (sub.n_pixels, v.size))
            fed.setdefault(f, np.zeros((px.n_pixels,) + v.shape[1:]))[sel] = v
    image[px.mask], unocc[px.mask] = flat, flat_un
    info = {"method": {"name": meth.name, "params": dict(meth.params, **params), "reads": list(needed),
                       "reads_roughness": meth.reads_roughness, "citation": meth.citation, "summary": meth.summary},
            "inputs": inputs, "input_info": input_info,
            "materials": {("all" if mid is None else str(mid)): m.params() for _rows, mid, m in groups},
            "regions": region_info, "rtol": float(rtol), "terms_err_rel_l1_max": max(errors.values(), default=0.0),
            "n_pixels": px.n_pixels}
    timings = {"inputs_s": t_inputs, "terms_s": t_terms, "method_s": t_method,
               "total_s": time.perf_counter() - t_start}
    return OcclusionImage(image=image, unoccluded=unocc, mask=px.mask, inputs=fed, timings=timings, info=info)
