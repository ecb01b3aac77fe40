"""Mitsuba 3 as an independent renderer of the lab's scenes (direct illumination with shadow rays).

The lab's reference (:mod:`ibl_ref.rendering.reference_render`) evaluates the exact quantity Knuth et al. (2014) Eq. 5
approximates: per pixel the visibility-weighted, normalised Phong lobe average of the environment,

    c = kd·(1/π)∫_{Ω⁺(n)} L(ω) V(ω) (n·ω) dω + ks·((s+1)/2π)∫_{Ω⁺(n)} L(ω) V(ω) max(r·ω, 0)^s dω          (*)

with s = 1/(1−g) (Eq. 3) and r = 2(n·v)n − v.  This is the one-bounce rendering equation with the modified Phong
BRDF of Kán et al. (2015), Eq. 2, f = kd/π + ks(s+1)/(2π)·max(r·ω,0)^s/(n·ω), and is exactly what Mitsuba 3's
``direct`` integrator estimates (environment importance sampling + BSDF sampling, multiple importance sampling, a
shadow ray per sample).  This module hands Mitsuba the *same* scene, so a difference between the two images is an
error of one of them (or Monte Carlo noise, which is estimated):

* **geometry** — the lab's :class:`ibl_ref.rendering.raster.Scene` triangles and its vertex normals (Mitsuba interpolates
  them barycentrically and normalises, as :func:`ibl_ref.rendering.raster.rasterize` does), one Mitsuba mesh per material id;
* **camera** — the lab's own pixel-centre rays (:meth:`ibl_ref.rendering.camera.PerspectiveCamera.pixel_rays`), one ray
  per pixel and sample through the pixel *centre*, fed to ``integrator.sample`` directly (so there is no
  reconstruction filter and no sub-pixel jitter: the lab shades the pixel centre too).  Coverage is Mitsuba's own
  (its first hit);
* **environment** — the lab's radiance function is the cube map with each texel constant over its exact solid
  angle (nearest-texel lookup, :func:`ibl_ref.environment.sampling.sample_nearest`).  Mitsuba's ``envmap`` emitter takes an
  (H, 2H) lat-long bitmap, addresses pixel (row j, column i) at u = (i+½)/W, **v = j/(H−1)** (rows are not
  pixel-centred: row 0 is exactly +Y), φ = 2πu, θ = πv, direction (sin φ sin θ, cos θ, −cos φ sin θ), and
  interpolates bilinearly.  :func:`mitsuba_envmap` therefore samples the cube's nearest-texel lookup at exactly
  those directions on a fine grid (default H = 1024), which reproduces the cube's radiance everywhere except within
  one lat-long pixel of a texel border, and scales each texel's pixels so that Mitsuba's own integral of the bitmap
  (the trapezoid sum it normalises its importance sampling with) holds exactly the texel's energy L·Ω — without
  that, a 1.5° sun of 3e4 lost 2.2 % of its energy to the pixel staircase at the texel borders
  (``tests/test_mitsuba_render.py`` checks directions, a bright patch, a mirror sphere and the energy);
* **BSDF** — the lab's materials (:mod:`ibl_ref.rendering.materials`), **one-sided** like Mitsuba's own BSDFs:
  zero when n·v ≤ 0 or n·ω ≤ 0 with n the shading normal (the lab's convention, README "Conventions").
  :class:`LabPhongBSDF` (a Python ``mi.BSDF``) implements f above; sampling picks the cosine lobe with probability
  kd/(kd+ks) and the Phong lobe around r otherwise.  A GGX material
  (:class:`ibl_ref.rendering.materials.GGXMaterial`, f = kd/π + D·G·F/(4 (n·ω)(n·v)), α = roughness²) goes one of
  two routes (``ggx_route``): ``"lab"`` — :class:`LabGGXBSDF`, the lab's formula (:func:`ibl_ref.lobes.brdfs.ggx`:
  GGX D, Schlick F with F0, Smith G in the material's form) as a Python BSDF, sampling D(h)·cos θh (and the cosine
  lobe with probability kd/(kd+1)); ``"builtin"`` — Mitsuba's own ``roughconductor`` with ``distribution='ggx'``,
  ``alpha = roughness²``, ``material='none'`` (η = 0, k = 1: Fresnel exactly 1 = Schlick with F0 = 1) and visible-
  normal sampling (``sample_visible``, its default and lower-variance sampler).  Mitsuba's microfacet model uses the
  **separable** Smith form: ``MicrofacetDistribution::G(wi, wo, m) = smith_g1(wi, m) * smith_g1(wo, m)``
  ("Smith's separable shadowing-masking approximation", ``include/mitsuba/render/microfacet.h``, Mitsuba 3), with
  the GGX ``smith_g1 = 2 / (1 + √(1 + α² tan²θ))`` — equal to the lab's G1 — and ``roughconductor``'s ``eval``
  returns D·G·F/(4 cos θi) (its f times cos θo), so the built-in route needs a material with ``smith="separable"``
  and ``f0 = 1``.  A diffuse part kd > 0 is added exactly with a ``blendbsdf`` of weight ½ between ``diffuse``
  (a ``uniform`` reflectance 2·kd: Mitsuba refuses RGB reflectances above 1, not uniform ones) and the
  conductor with ``specular_reflectance`` 2: ½·2kd/π + ½·2·f_s = kd/π + f_s (``tests/test_mitsuba_render.py``
  checks both routes against :func:`ibl_ref.lobes.brdfs.ggx` at random directions through Mitsuba's ``eval``).

Noise: the render is the mean of two independent halves (seeds ``seed`` and ``seed + 1``, ``spp/2`` samples
each).  For each pixel E|mean − truth| ≈ E|a − b|/2 (a, b the halves; Gaussian noise), so
``noise_rel_l1 = Σ|a−b|/2 / Σ|mean|`` is the rel. L1 that noise alone puts between this image and the truth, and
``noise_rmse = √(mean((a−b)²)/4)`` its RMSE.

Variant: ``llvm_ad_rgb`` (vectorised, 3–70× faster) needs libLLVM ≥ 17; with libLLVM 15/16 Dr.Jit aborts the whole
process at the first kernel compile (uncatchable), and it finds no library named ``libLLVM-N.so`` by itself.
:func:`select_variant` therefore looks for a libLLVM ≥ 17 file, points ``DRJIT_LIBLLVM_PATH`` at it and only then
selects ``llvm_ad_rgb``.  Without one, :class:`MitsubaUnavailable` says so: the scalar variants cannot run this
module (its emitter queries, meshes and BSDF pass whole NumPy arrays to Mitsuba, which only the vectorised variants
accept; a scalar fallback failed with ``TypeError`` deep inside Mitsuba).  Install with ``pip install ".[mitsuba]"``
and, on Debian, ``apt-get install libllvm19``.
"""

from __future__ import annotations

import contextlib
import glob
import os
import re
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import IBLError
from ..environment.envmap import cube_solid_angles
from ..environment.envmap import direction_to_texel
from .materials import as_material
from .raster import prepare_scene
from .reference_converged import check_environment

__all__ = [
    "MitsubaUnavailable",
    "MitsubaResult",
    "find_libllvm",
    "select_variant",
    "mitsuba_available",
    "envmap_directions",
    "mitsuba_envmap",
    "envmap_grid_weights",
    "ENVMAP_ENERGY_MODES",
    "ENVMAP_MAX_LOST_FRAC",
    "envmap_radiance",
    "render_mitsuba",
    "bsdf_dict",
    "GGX_ROUTES",
]

#: how :func:`render_mitsuba` renders a GGX material: the lab's formula as a Python BSDF, or Mitsuba's roughconductor
GGX_ROUTES = ("lab", "builtin")

#: Dr.Jit's LLVM backend needs at least this libLLVM major version (older ones abort the process).
MIN_LLVM_MAJOR = 17
_LLVM_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib",
              "/usr/local/lib", "/usr/lib/llvm-*/lib")
_STATE: dict = {}
SAMPLER = os.environ.get("HM_SAMPLER", "multijitter")


class MitsubaUnavailable(IBLError):
    """Mitsuba 3 is not installed (``pip install ".[mitsuba]"``) or no variant could be selected."""


def _llvm_major(path: str) -> int | None:
    m = re.search(r"libLLVM[-.]?(\d+)", os.path.basename(path)) or re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else None


def find_libllvm(min_major: int = MIN_LLVM_MAJOR) -> str | None:
    """Path of the newest libLLVM shared library with major version ≥ ``min_major``, or None.

    An explicit ``DRJIT_LIBLLVM_PATH`` is honoured only if its version (read from the file name) is high enough.
    """
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env:
        major = _llvm_major(os.path.realpath(env)) or _llvm_major(env)
        return env if (major is not None and major >= min_major and os.path.exists(env)) else None
    best = None
    for d in _LLVM_DIRS:
        for p in glob.glob(os.path.join(d, "libLLVM*.so*")):
            major = _llvm_major(p) or _llvm_major(os.path.realpath(p))
            if major is not None and major >= min_major and (best is None or major > best[0]):
                best = (major, p)
    return None if best is None else best[1]


@contextlib.contextmanager
def _captured_stderr():
    """Hold what native code writes to file descriptor 2 in the block; yields a function returning its lines.  On
    success the text is written to stderr afterwards (nothing is lost); on an error the caller puts it in the message.
    """
    import sys
    import tempfile

    lines = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no fd 2 (an embedded interpreter): nothing to hold
        yield lambda: lines
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        ok = False
        try:
            def said():
                tmp.seek(0)
                lines[:] = [ln.strip() for ln in tmp.read().decode(errors="replace").splitlines() if ln.strip()]
                return lines
            yield said
            ok = True
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            if ok:
                tmp.seek(0)
                text = tmp.read().decode(errors="replace")
                if text:
                    sys.stderr.write(text)


def select_variant(prefer: str = "auto") -> str:
    """Import Mitsuba and select its ``llvm_ad_rgb`` variant once per process (``prefer``: ``"auto"`` or
    ``"llvm"``, the same thing).  Raises :class:`MitsubaUnavailable` when Mitsuba is not installed or no
    libLLVM ≥ 17 exists (module docstring: the scalar variants cannot run this module's array code)."""
    if prefer not in ("auto", "llvm"):
        raise IBLError(f"variant preference must be auto or llvm, got {prefer!r} (the scalar variants cannot "
                       "run the lab's array-based Mitsuba code)")
    if "variant" in _STATE:
        return _STATE["variant"]
    lib = find_libllvm()
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if lib is None and env:
        raise MitsubaUnavailable(f"DRJIT_LIBLLVM_PATH={env}: not an existing libLLVM >= {MIN_LLVM_MAJOR} file (the "
                                 "version is read from its name, e.g. libLLVM-19.so.1); unset it to let the lab look "
                                 "for one, or install one (Debian: apt-get install libllvm19)")
    if lib is None:
        raise MitsubaUnavailable(
            f"Mitsuba's llvm_ad_rgb variant needs libLLVM >= {MIN_LLVM_MAJOR} and none was found (Debian: "
            "apt-get install libllvm19; or set DRJIT_LIBLLVM_PATH to a libLLVM-17+ file); the scalar variants "
            "cannot run the lab's array-based Mitsuba code")
    os.environ["DRJIT_LIBLLVM_PATH"] = lib
    variant = "llvm_ad_rgb"
    with _captured_stderr() as said:  # Dr.Jit reports a library it cannot load on the C stderr: into the message
        try:
            import mitsuba as mi
        except ImportError as exc:
            raise MitsubaUnavailable('Mitsuba 3 is not installed: pip install ".[mitsuba]"') from exc
        try:
            mi.set_variant(variant)
        except (ImportError, AttributeError, RuntimeError) as exc:
            why = " ".join(said()[:1]) or str(exc)
            raise MitsubaUnavailable(f"Mitsuba 3 could not select {variant} with {lib}: {why}") from None
    mi.set_log_level(mi.LogLevel.Error)  # e.g. multijitter's "sample count rounded up" (recorded in info["spp"])
    _register_bsdf(mi)
    _STATE["variant"] = variant
    _STATE["libllvm"] = lib
    return variant


def mitsuba_available() -> bool:
    """True if Mitsuba 3 imports and its llvm_ad_rgb variant can be selected (:func:`select_variant`)."""
    try:
        select_variant()
    except MitsubaUnavailable:
        return False
    return True


# ------------------------------------------------------------------------------------------------
# environment: the cube's nearest-texel radiance function as a Mitsuba lat-long bitmap
# ------------------------------------------------------------------------------------------------
def envmap_directions(height: int) -> np.ndarray:
    """World directions (H, 2H, 3) at which Mitsuba's ``envmap`` places its bitmap pixels (default ``to_world``).

    u = (i+½)/W, v = j/(H−1), φ = 2πu, θ = πv, d = (sin φ sin θ, cos θ, −cos φ sin θ).
    """
    H = int(height)
    if H < 2:
        raise IBLError(f"envmap height must be >= 2, got {height}")
    return _envmap_rows(H, 0, H)


def _envmap_rows(H: int, j0: int, j1: int) -> np.ndarray:
    """Rows j0 … j1−1 of :func:`envmap_directions` (H)."""
    W = 2 * H
    u = (np.arange(W) + 0.5) / W
    v = np.arange(j0, j1) / (H - 1)
    phi = 2 * np.pi * u[None, :]
    theta = np.pi * v[:, None]
    st = np.sin(theta)
    d = np.stack(np.broadcast_arrays(np.sin(phi) * st, np.cos(theta), -np.cos(phi) * st), axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


#: what :func:`mitsuba_envmap` preserves: ``"texel"`` (each cube texel's exact energy L·Ω) or ``"none"``
ENVMAP_ENERGY_MODES = ("texel", "none")
#: ``energy="texel"`` refuses a bitmap that leaves more than this share of the energy in texels without a pixel
ENVMAP_MAX_LOST_FRAC = 1e-6


def envmap_grid_weights(height: int) -> np.ndarray:
    """(H,) solid-angle weight of one bitmap pixel of row j in Mitsuba's integral of its ``envmap``.

    Mitsuba builds the sampling density from the pixel values times sin θ_j at the grid rows θ_j = πj/(H−1),
    interpolated bilinearly over the cells between grid points and normalised by their sum, so its
    importance-sampling estimator (an emitter sample's weight is the radiance over that density) converges to the
    trapezoid sum Σ_ij B_ij sin θ_j Δθ Δφ with Δθ = π/(H−1), Δφ = 2π/W and half weights on the two pole rows
    (measured: its mean weight over 4M samples equals this sum within 3e-5 on the lab's maps); the
    integral of its bilinear radiance differs from the sum only by sin θ varying within a row (O(Δθ²)).
    """
    H = int(height)
    w = np.full(H, (np.pi / (H - 1)) * (2 * np.pi / (2 * H)))
    w[[0, -1]] *= 0.5
    return w * np.sin(np.pi * np.arange(H) / (H - 1))


def mitsuba_envmap(cube, height: int = 1024, energy: str = "texel", return_info: bool = False):
    """(H, 2H, 3) float32 bitmap whose Mitsuba ``envmap`` reproduces the cube's nearest-texel radiance.

    Each pixel is the cube's radiance at the pixel's direction (:func:`envmap_directions`).  The texel borders of
    the cube then fall between pixels, so with ``energy="none"`` a texel's energy in Mitsuba is its radiance times
    the weights of the pixels that happen to fall into it (:func:`envmap_grid_weights`) instead of its solid
    angle: for a small bright sun (a few texels of 3e4, 16 pixels across) that is off by 2 %.  ``energy="texel"``
    (default) scales every texel's pixels by Ω_t / Σ_(pixels in t) w so that Mitsuba integrates exactly each texel's
    L·Ω (the radiance inside a texel changes by that staircase ratio, the direction of its energy by at most a
    pixel).  With ``return_info`` also a dict: ``texels_without_pixel`` and ``energy_lost_frac``.  A bitmap too
    coarse for the cube (texels that no pixel falls into, holding more than :data:`ENVMAP_MAX_LOST_FRAC` of the
    energy) is refused with an :class:`IBLError` naming a height that works, in ``"texel"`` mode; ``"none"``
    reports it in the info only.
    """

    if energy not in ENVMAP_ENERGY_MODES:
        raise IBLError(f"energy must be one of {ENVMAP_ENERGY_MODES}, got {energy!r}")
    a = check_environment(cube)
    if a.shape[-1] == 1:
        a = np.repeat(a, 3, axis=-1)
    if a.shape[-1] != 3:
        raise IBLError(f"environment must have 1 or 3 channels for Mitsuba, got {a.shape[-1]}")
    N = a.shape[1]
    H = int(height)
    if H < 2:
        raise IBLError(f"envmap height must be >= 2, got {height}")
    t = np.empty((H, 2 * H), dtype=np.int32 if 6 * N * N < 2 ** 31 else np.int64)  # texel of every pixel
    rows = max(1, (1 << 21) // (2 * H))  # rows per step: bounded memory at any height
    for j0 in range(0, H, rows):
        d = _envmap_rows(H, j0, min(H, j0 + rows))
        f, r, c = direction_to_texel(d, N)
        t[j0:j0 + rows] = (np.asarray(f) * N + np.asarray(r)) * N + np.asarray(c)
    omega = np.asarray(cube_solid_angles(N), dtype=np.float64).reshape(-1)
    w_row = envmap_grid_weights(H)
    w_tex = np.zeros(6 * N * N)
    for j0 in range(0, H, rows):
        tt = t[j0:j0 + rows]
        w_tex += np.bincount(tt.reshape(-1), weights=np.broadcast_to(w_row[j0:j0 + rows, None], tt.shape).reshape(-1),
                             minlength=6 * N * N)
    empty = w_tex <= 0
    e_tex = (a.reshape(-1, 3) * omega[:, None]).sum(axis=-1)
    tot = float(e_tex.sum())
    lost = float(e_tex[empty].sum() / tot) if tot > 0 else 0.0
    if energy == "texel" and lost > ENVMAP_MAX_LOST_FRAC:
        raise IBLError(f"envmap height {int(height)} is too coarse for a {N}² cube: {int(empty.sum())} texels get no "
                       f"bitmap pixel ({lost:.2%} of the energy); use a height of at least {max(8 * N, 64)}")
    lut = a.reshape(-1, 3)
    if energy == "texel":
        lut = lut * np.where(empty, 0.0, omega / np.where(empty, 1.0, w_tex))[:, None]
    out = np.empty((H, 2 * H, 3), dtype=np.float32)
    for j0 in range(0, H, rows):
        out[j0:j0 + rows] = lut[t[j0:j0 + rows]]
    if not return_info:
        return out
    return out, dict(energy=energy, texels_without_pixel=int(empty.sum()), energy_lost_frac=lost)


def envmap_radiance(cube, dirs, height: int = 1024, variant: str = "auto", energy: str = "texel") -> np.ndarray:
    """Radiance (..., 3) that Mitsuba's ``envmap`` emitter, built by :func:`mitsuba_envmap` (``energy``), returns
    toward world directions ``dirs`` (..., 3) (``emitter.eval`` of a ray leaving the scene along ``dirs``)."""
    import drjit as dr

    select_variant(variant)
    import mitsuba as mi

    d = np.asarray(dirs, dtype=np.float64)
    shape = d.shape[:-1]
    d = (d / np.linalg.norm(d, axis=-1, keepdims=True)).reshape(-1, 3).astype(np.float32)
    em = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(mitsuba_envmap(cube, height, energy=energy))})
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.wi = -mi.Vector3f(*d.T)
    out = np.array(em.eval(si), dtype=np.float64).reshape(3, -1).T
    return out.reshape(shape + (3,))


# ------------------------------------------------------------------------------------------------
# BSDF: normalised Phong (Kán et al. 2015, Eq. 2) + Lambert, one-sided
# ------------------------------------------------------------------------------------------------
def _register_bsdf(mi):
    import drjit as dr

    class _LabBSDF(mi.BSDF):
        """A cosine lobe (probability ``p_diffuse``) and a glossy lobe (:meth:`_glossy_direction`), one-sided; the
        subclasses give the value f·(n·ω) and the mixture pdf (:meth:`_value_pdf`)."""

        def _flags(self, diffuse: bool, glossy: bool):
            flags = mi.BSDFFlags.FrontSide
            if diffuse:
                flags = flags | mi.BSDFFlags.DiffuseReflection
            if glossy:
                flags = flags | mi.BSDFFlags.GlossyReflection
            self.m_components = [flags]
            self.m_flags = flags

        def sample(self, ctx, si, sample1, sample2, active=True):
            cos_i = mi.Frame3f.cos_theta(si.wi)
            w_diff = mi.warp.square_to_cosine_hemisphere(sample2)
            pick_diffuse = sample1 < self.p_diffuse
            wo = dr.select(pick_diffuse, w_diff, self._glossy_direction(si, sample2))
            value, pdf = self._value_pdf(si, wo)
            bs = mi.BSDFSample3f()
            bs.wo = wo
            bs.pdf = pdf
            bs.eta = 1.0
            bs.sampled_component = mi.UInt32(0)
            bs.sampled_type = dr.select(pick_diffuse, mi.UInt32(+mi.BSDFFlags.DiffuseReflection),
                                        mi.UInt32(+mi.BSDFFlags.GlossyReflection))
            ok = active & (cos_i > 0) & (pdf > 0)
            weight = dr.select(ok, value / dr.select(pdf > 0, pdf, 1.0), 0.0)
            return bs, mi.Color3f(weight)

        def eval(self, ctx, si, wo, active=True):
            value, _ = self._value_pdf(si, wo)
            return mi.Color3f(dr.select(active, value, 0.0))

        def pdf(self, ctx, si, wo, active=True):
            _, pdf = self._value_pdf(si, wo)
            return dr.select(active, pdf, 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            value, pdf = self._value_pdf(si, wo)
            return mi.Color3f(dr.select(active, value, 0.0)), dr.select(active, pdf, 0.0)

    class LabPhongBSDF(_LabBSDF):
        """f·(n·ω) = kd/π·(n·ω) + ks·(s+1)/(2π)·max(r·ω,0)^s on n·v > 0, n·ω > 0 (shading frame); else 0."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.kd = float(props.get("kd", 0.0))
            self.ks = float(props.get("ks", 1.0))
            self.s = float(props.get("s", 1.0))
            tot = self.kd + self.ks
            self.p_diffuse = self.kd / tot if tot > 0 else 1.0
            self._flags(self.kd > 0, self.ks > 0)

        def _value_pdf(self, si, wo):
            cos_i = mi.Frame3f.cos_theta(si.wi)
            cos_o = mi.Frame3f.cos_theta(wo)
            r = mi.Vector3f(-si.wi.x, -si.wi.y, si.wi.z)  # mirror direction of wi about the shading normal
            lobe = dr.power(dr.maximum(dr.dot(r, wo), 0.0), self.s) * ((self.s + 1.0) / (2.0 * dr.pi))
            diff = dr.maximum(cos_o, 0.0) * dr.inv_pi
            ok = (cos_i > 0) & (cos_o > 0)
            value = dr.select(ok, self.kd * diff + self.ks * lobe, 0.0)
            pdf = dr.select(ok, self.p_diffuse * diff + (1.0 - self.p_diffuse) * lobe, 0.0)
            return value, pdf

        def _glossy_direction(self, si, sample2):
            r = mi.Vector3f(-si.wi.x, -si.wi.y, si.wi.z)
            # Phong lobe around r: cos α = ξ^(1/(s+1)), pdf (s+1)/(2π) cos^s α
            ca = dr.power(sample2.x, 1.0 / (self.s + 1.0))
            sa = dr.safe_sqrt(1.0 - ca * ca)
            phi = 2.0 * dr.pi * sample2.y
            return mi.Frame3f(r).to_world(mi.Vector3f(sa * dr.cos(phi), sa * dr.sin(phi), ca))

        def to_string(self):
            return f"LabPhongBSDF[kd={self.kd}, ks={self.ks}, s={self.s}]"

    mi.register_bsdf("lab_phong", lambda props: LabPhongBSDF(props))

    class LabGGXBSDF(_LabBSDF):
        """f·(n·ω) = kd/π·(n·ω) + D·G·F/(4 n·v) on n·v > 0, n·ω > 0 (shading frame; :func:`ibl_ref.lobes.brdfs.ggx`:
        D = α²/(π(cos²θh(α²−1)+1)²), G1(c) = 2c/(c + √(α² + (1−α²)c²)), G = G1·G1 or 1/(1/G1 + 1/G1 − 1),
        F = F0 + (1−F0)(1 − h·ω)⁵); else 0.  Sampling: the cosine lobe with probability kd/(kd+1), else h from
        D(h)·cos θh (tan²θh = α² ξ/(1 − ξ)) reflected about h."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.kd = float(props.get("kd", 0.0))
            self.alpha = float(props.get("alpha", 0.25))
            self.f0 = float(props.get("f0", 0.04))
            self.height_correlated = bool(props.get("height_correlated", True))
            self.p_diffuse = self.kd / (self.kd + 1.0)
            self._flags(self.kd > 0, True)

        def _g1(self, c):
            a2 = self.alpha * self.alpha
            return 2.0 * c / (c + dr.sqrt(a2 + (1.0 - a2) * c * c))

        def _value_pdf(self, si, wo):
            cos_i = mi.Frame3f.cos_theta(si.wi)  # toward the viewer
            cos_o = mi.Frame3f.cos_theta(wo)  # toward the light
            ok = (cos_i > 0) & (cos_o > 0)
            h = dr.normalize(si.wi + wo)
            ch = mi.Frame3f.cos_theta(h)
            a2 = self.alpha * self.alpha
            t = ch * ch * (a2 - 1.0) + 1.0
            D = dr.select(ch > 0, a2 / (dr.pi * t * t), 0.0)
            ci_ = dr.select(ok, cos_i, 1.0)
            co_ = dr.select(ok, cos_o, 1.0)
            g_i, g_o = self._g1(ci_), self._g1(co_)
            G = 1.0 / (1.0 / g_i + 1.0 / g_o - 1.0) if self.height_correlated else g_i * g_o
            F = self.f0 + (1.0 - self.f0) * dr.power(1.0 - dr.clip(dr.dot(h, wo), 0.0, 1.0), 5.0)
            diff = dr.maximum(cos_o, 0.0) * dr.inv_pi
            value = dr.select(ok, self.kd * diff + D * G * F / (4.0 * ci_), 0.0)
            hw = dr.dot(wo, h)
            pdf_spec = dr.select(hw > 0, D * ch / (4.0 * dr.select(hw > 0, hw, 1.0)), 0.0)
            pdf = dr.select(ok, self.p_diffuse * diff + (1.0 - self.p_diffuse) * pdf_spec, 0.0)
            return value, pdf

        def _glossy_direction(self, si, sample2):
            a2 = self.alpha * self.alpha
            xi = dr.minimum(sample2.x, 1.0 - 1e-7)
            tan2 = a2 * xi / (1.0 - xi)
            ct = dr.rsqrt(1.0 + tan2)
            st = dr.safe_sqrt(1.0 - ct * ct)
            phi = 2.0 * dr.pi * sample2.y
            h = mi.Vector3f(st * dr.cos(phi), st * dr.sin(phi), ct)
            return 2.0 * dr.dot(si.wi, h) * h - si.wi

        def to_string(self):
            return (f"LabGGXBSDF[kd={self.kd}, alpha={self.alpha}, f0={self.f0}, "
                    f"smith={'height_correlated' if self.height_correlated else 'separable'}]")

    mi.register_bsdf("lab_ggx", lambda props: LabGGXBSDF(props))


# ------------------------------------------------------------------------------------------------
# scene and render
# ------------------------------------------------------------------------------------------------
@dataclass
class MitsubaResult:
    """Output of :func:`render_mitsuba`.

    Attributes
    ----------
    image : (H, W, 3) — mean of the two halves (0 where Mitsuba's camera ray misses the scene).
    half_a, half_b : (H, W, 3) — the two independent halves (seeds ``seed``, ``seed + 1``).
    mask : (H, W) bool — Mitsuba's coverage.
    info : dict — variant, spp, seeds, noise_rel_l1, noise_rmse, time_s, envmap_height, …
    """

    image: np.ndarray
    half_a: np.ndarray
    half_b: np.ndarray
    mask: np.ndarray
    info: dict = field(default_factory=dict)


def bsdf_dict(material, ggx_route: str = "lab") -> dict:
    """The Mitsuba BSDF dictionary of a lab material (:func:`ibl_ref.rendering.materials.as_material`; a raw Mitsuba
    dict passes through): Phong → ``lab_phong``; GGX → ``lab_ggx`` (``ggx_route="lab"``) or Mitsuba's
    ``roughconductor`` (``"builtin"``; needs ``smith="separable"`` and ``f0 = 1``, module docstring), blended with a
    ``diffuse`` for kd > 0."""

    if isinstance(material, dict) and "type" in material:  # a raw Mitsuba BSDF dict (tests: a perfect mirror)
        return dict(material)
    if ggx_route not in GGX_ROUTES:
        raise IBLError(f"ggx_route must be one of {', '.join(GGX_ROUTES)}, got {ggx_route!r}")
    m = as_material(material)
    if m.kind == "phong":
        if not (m.kd + m.ks > 0):
            raise IBLError(f"kd, ks must not both be 0, got {m.kd}, {m.ks}")
        if m.mirror:
            raise IBLError("the Mitsuba renderer needs 0 <= g < 1 (the mirror g = 1 is not a Phong lobe)")
        return {"type": "lab_phong", "kd": m.kd, "ks": m.ks, "s": m.s}
    if ggx_route == "lab":
        return {"type": "lab_ggx", "kd": m.kd, "alpha": m.alpha, "f0": m.f0,
                "height_correlated": m.smith == "height_correlated"}
    if m.smith != "separable" or m.f0 != 1.0:
        raise IBLError(f"Mitsuba's built-in roughconductor is GGX with separable Smith G1·G1 and (material='none') "
                       f"Fresnel 1: render a GGX material with smith='separable' and f0=1 (got smith={m.smith!r}, "
                       f"f0={m.f0:g})")
    cond = {"type": "roughconductor", "distribution": "ggx", "alpha": m.alpha, "material": "none",
            "sample_visible": True}
    if m.kd == 0:
        return cond
    cond["specular_reflectance"] = {"type": "uniform", "value": 2.0}
    return {"type": "blendbsdf", "weight": 0.5, "a": {"type": "diffuse", "reflectance": {"type": "uniform",
                                                                                        "value": 2.0 * m.kd}},
            "b": cond}


def _material_table(materials, mat_ids, ggx_route="lab"):
    out = {}
    for mid in mat_ids:
        if mid not in materials:
            raise IBLError(f"no material for material id {mid} (have {sorted(materials)})")
        try:
            out[mid] = bsdf_dict(materials[mid], ggx_route)
        except IBLError as exc:
            raise IBLError(f"material {mid}: {exc}") from None
    return out


def _build_scene(mi, scene, materials, bitmap):
    import drjit as dr

    d = {"type": "scene", "integrator": {"type": "direct"},
         "env": {"type": "envmap", "bitmap": mi.Bitmap(bitmap)}}
    for mid, mat in materials.items():
        sel = scene.material_id == mid
        faces = scene.faces[sel]
        used, inv = np.unique(faces.reshape(-1), return_inverse=True)
        V = scene.vertices[used]
        N = scene.vertex_normals[used]
        F = inv.reshape(-1, 3)
        bsdf = mi.load_dict(mat)
        props = mi.Properties()
        props["bsdf"] = bsdf
        mesh = mi.Mesh(f"mat{mid}", len(V), len(F), props=props, has_vertex_normals=True)
        p = mi.traverse(mesh)
        p["vertex_positions"] = dr.ravel(mi.Point3f(*(V.T.astype(np.float32))))
        p["vertex_normals"] = dr.ravel(mi.Normal3f(*(N.T.astype(np.float32))))
        p["faces"] = dr.ravel(mi.Vector3u(*(F.T.astype(np.uint32))))
        p.update()
        d[f"mesh{mid}"] = mesh
    return mi.load_dict(d)


def _render_half(mi, mscene, o, dirs, spp, seed, lanes):
    """Mean radiance (P, 3) of ``spp`` samples per ray, in passes of at most ``lanes`` wavefront lanes."""
    P = len(o)
    per_pass = max(1, min(spp, lanes // max(P, 1)))
    integ = mscene.integrator()
    acc = np.zeros((P, 3))
    done, k = 0, 0
    while done < spp:
        sampler = mi.load_dict({"type": SAMPLER, "sample_count": min(per_pass, spp - done)})
        K = int(sampler.sample_count())  # multijitter rounds to its stratification grid
        if SAMPLER != "independent":
            sampler.set_samples_per_wavefront(K)
        sampler.seed(int(seed) * 1_000_003 + k, P * K)
        oo = np.repeat(o, K, axis=0).astype(np.float32)
        dd = np.repeat(dirs, K, axis=0).astype(np.float32)
        ray = mi.Ray3f(mi.Point3f(*oo.T), mi.Vector3f(*dd.T))
        spec, _, _ = integ.sample(mscene, sampler, ray, None, True)
        acc += np.array(spec, dtype=np.float64).reshape(3, P, K).sum(axis=2).T
        done += K
        k += 1
    return acc / done, done


def _refuse_normal_maps(meshes) -> None:
    """One-line error for a mesh that carries a normal map (``mesh.metadata["normal_map"]``): the lab's maps are
    procedural (:mod:`ibl_ref.rendering.normal_map`) and are not handed to Mitsuba, whose render would show the
    geometric normals instead — a different image, not a check of the lab's."""
    from .normal_map import METADATA_KEY, mesh_normal_maps

    maps = mesh_normal_maps(meshes)
    if maps:
        raise IBLError(f"mesh {min(maps)} carries a normal map (metadata[{METADATA_KEY!r}]): Mitsuba renders of "
                       f"normal-mapped meshes are not supported (Mitsuba would shade the geometric normals)")


def render_mitsuba(meshes, camera, cube, *, materials=None, kd: float = 0.0, ks: float = 1.0, g: float = 0.9,
                   material=None, ggx_route: str = "lab", spp: int = 256, seed: int = 0,
                   envmap_height: int | None = None, envmap_energy: str = "texel", lanes: int = 1 << 21,
                   variant: str = "auto") -> MitsubaResult:
    """Render (*) with Mitsuba 3's ``direct`` integrator through the lab's pixel centres.

    Parameters
    ----------
    meshes : see :func:`ibl_ref.rendering.raster.prepare_scene` (material ids select ``materials``)
    camera : :class:`ibl_ref.rendering.camera.PerspectiveCamera` (any camera with ``pixel_rays``)
    cube : (6, N, N, C) environment (the radiance function: nearest texel, see module docstring)
    materials : {material_id: material} (any form :func:`ibl_ref.rendering.materials.as_material` takes, or a raw
        Mitsuba BSDF dict); default: every id gets ``material``, else the Phong material (kd, ks, g)
    ggx_route : how a GGX material is rendered (:data:`GGX_ROUTES`; module docstring): ``"lab"`` (the lab's formula
        as a Python BSDF, any smith and F0) or ``"builtin"`` (Mitsuba's roughconductor: separable Smith, F0 = 1)
    spp : samples per pixel in total (two halves of spp/2 with seeds ``seed``, ``seed + 1``; even, ≥ 2)
    envmap_height : lat-long bitmap height handed to Mitsuba (width 2H); default max(1024, 8·N) for an N² cube
        (every texel then holds at least one pixel)
    envmap_energy : :func:`mitsuba_envmap`'s ``energy`` (default ``"texel"``: every texel's exact energy)
    lanes : wavefront lanes per pass (memory ≈ 1 kB per lane in ``llvm_ad_rgb``)
    variant : ``auto`` / ``llvm`` (see :func:`select_variant`)
    """

    spp = int(spp)
    if spp < 2 or spp % 2:
        raise IBLError(f"spp must be an even number >= 2, got {spp}")
    _refuse_normal_maps(meshes)
    t0 = time.perf_counter()
    scene = prepare_scene(meshes, warn=False)
    ids = sorted(int(x) for x in np.unique(scene.material_id))
    default = (kd, ks, g) if material is None else material
    mats = _material_table({i: default for i in ids} if materials is None else materials, ids, ggx_route)
    if envmap_height is None:
        shape = np.shape(cube)  # the layout itself is checked by mitsuba_envmap
        envmap_height = max(1024, 8 * int(shape[1])) if len(shape) >= 2 else 1024
    bitmap, env_info = mitsuba_envmap(cube, envmap_height, energy=envmap_energy, return_info=True)
    v = select_variant(variant)  # after the argument checks: a bad argument is reported even without Mitsuba
    import mitsuba as mi

    mscene = _build_scene(mi, scene, mats, bitmap)
    o, d = camera.pixel_rays(normalize=True)
    H, W = o.shape[:2]
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    # coverage by Mitsuba's own first hit
    si = mscene.ray_intersect(mi.Ray3f(mi.Point3f(*o.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32))))
    hit = np.array(si.is_valid(), dtype=bool).reshape(-1)
    t1 = time.perf_counter()
    halves, spp_done = [], []
    for k in range(2):
        img = np.zeros((H * W, 3))
        if hit.any():
            img[hit], n_done = _render_half(mi, mscene, o[hit], d[hit], spp // 2, seed + k, lanes)
            spp_done.append(2 * n_done)
        halves.append(img.reshape(H, W, 3))
    a, b = halves
    mean = 0.5 * (a + b)
    mask = hit.reshape(H, W)
    den = np.abs(mean[mask]).sum()
    diff = (a - b)[mask]
    info = dict(renderer="mitsuba", variant=v, libllvm=_STATE.get("libllvm"), mitsuba_version=mi.__version__,
                integrator="direct", sampler=SAMPLER, spp=int(min(spp_done)) if spp_done else spp, seeds=[int(seed), int(seed) + 1],
                envmap_height=int(envmap_height), envmap=env_info, n_pixels=int(mask.sum()),
                materials={str(k_): m for k_, m in mats.items()}, ggx_route=ggx_route,
                noise_rel_l1=float(np.abs(diff).sum() / 2 / den) if den > 0 else float("nan"),
                noise_rmse=float(np.sqrt(np.mean(diff ** 2) / 4)) if diff.size else float("nan"),
                setup_s=round(t1 - t0, 3), time_s=round(time.perf_counter() - t0, 3))
    if not np.all(np.isfinite(mean)):
        raise IBLError("Mitsuba produced non-finite values")
    return MitsubaResult(image=mean, half_a=a, half_b=b, mask=mask, info=info)
