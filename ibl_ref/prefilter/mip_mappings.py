"""Roughness ↔ MIP level: how each engine stores GGX-prefiltered radiance over roughness in a chain of levels.

A split-sum engine (Karis 2013, :mod:`ibl_ref.prefilter.karis2013`) stores the n = v = r prefilter P(·, r) at a
few roughnesses, one per MIP level of a cube map, and reads a perceptual roughness r (α = r²) at a fractional
level ℓ(r) with trilinear filtering.  The engines differ in that one function.  Each mapping here is a
:class:`MipMapping` (a frozen dataclass) with

* :meth:`MipMapping.level` — the engine's run-time look-up ℓ(r, N) for a chain of N levels (level 0 the base, the
  sharpest; fractional, clamped to [0, N − 1]);
* :meth:`MipMapping.roughness` — the roughness the engine's prefilter stores in level ℓ (its inverse where the
  look-up is invertible; what it returns where it is not is said per mapping below);
* :meth:`MipMapping.chain_sizes` — the face sizes of the engine's own chain for a base face size;
* ``source`` (the engine files and versions the formula comes from), ``default_base`` (the engine's default base
  face size), :attr:`MipMapping.default_levels` (its N there) and ``min_face_size`` (its smallest level there).

The mappings (ℓ the fractional level read for r in a chain of N levels, lod = ℓ/(N − 1), b the base face size)::

    name      look-up ℓ(r)                               roughness of level ℓ             default chain
    linear    lod = r                                    r = lod                          b² … 2², ⌊log2 b⌋ levels
    filament  lod = r(2 − r)                             r = 1 − √(1 − lod)               256² … 16², N = 5
    unity     lod = r(1.7 − 0.7r)                        r = (1.7 − √(2.89 − 2.8lod))/1.4 128² … 2², N = 7
    unreal    ℓ = N − 3 + 1.2·log2 max(r, 0.001)         r = min(2^((ℓ − N + 3)/1.2), 1)  128² … 1², N = 8
    threejs   ℓ = (N − 3) − clamp(m(r), −2, N − 3)       the inverse of m; 0 at ℓ = 0     256² … 16², 16² ×6, N = 11

(every ℓ clamped to [0, N − 1]).

Sources (formulas are facts of the engines' code; nothing is copied):

* ``linear`` — Khronos glTF-IBL-Sampler, ``lib/source/lib.cpp`` (commit 0138f41): level ℓ of ``mipLevelCount`` is
  filtered at roughness ℓ/(mipLevelCount − 1), and ``mipLevelCount`` defaults to ⌊log2 b⌋ for a base of b² (the
  panorama's height by default), so the chain ends at 2²; glTF-Sample-Viewer's ``ibl.glsl``
  (``getIBLRadianceGGX``) reads ``lod = roughness·(u_MipCount − 1)``, as Bevy's ``environment_map.wgsl`` does with
  ``textureNumLevels − 1``.  ``default_base`` is None: the sampler sizes the chain from its input.
* ``filament`` — Filament's run time, ``shaders/src/light_indirect.fs`` ``perceptualRoughnessToLod``:
  lod = iblRoughnessOneLevel · r(2 − r) with iblRoughnessOneLevel = N − 1; its prefilter ``cmgen`` stores
  r = 1 − √(1 − ℓ/(N − 1)) and by default writes 256² … 16² (``--size=256``, minimum level 16²: 5 levels;
  checked against cmgen 1.9.25's output in :mod:`ibl_ref.prefilter.cmgen_peer`).
* ``unity`` — Unity's SRP Core ``ShaderLibrary/ImageBasedLighting.hlsl`` (Graphics v10.8.0)
  ``PerceptualRoughnessToMipmapLevel`` = r(1.7 − 0.7r)·``UNITY_SPECCUBE_LOD_STEPS`` and its inverse
  ``MipmapLevelToPerceptualRoughness``; the built-in pipeline's ``UnityImageBasedLighting.cginc``
  (``Unity_GlossyEnvironment``) the same; ``UNITY_SPECCUBE_LOD_STEPS`` = 6, "the last mip index, we generate 7
  mips of convolution"; reflection probes default to 128².  The engine's factor is the constant 6; here it is
  N − 1 (= 6 for its 7 levels), so the mapping applies to any N.
* ``unreal`` — Unreal Engine 4.27 ``Engine/Shaders/Private/ReflectionEnvironmentShared.ush``
  ``ComputeReflectionCaptureMipFromRoughness`` (``REFLECTION_CAPTURE_ROUGHEST_MIP`` 1,
  ``REFLECTION_CAPTURE_ROUGHNESS_MIP_SCALE`` 1.2, ``CubemapMaxMip`` = N − 1):
  mip = (N − 1) − 1 − (1 − 1.2·log2 r) with r floored at 0.001, the sampler clamping to the chain; the capture
  filter (``ReflectionEnvironmentShaders.usf`` ``FilterPS``) fills mip ℓ at
  ``ComputeReflectionCaptureRoughnessFromMip``, r = 2^((ℓ − N + 3)/1.2): a fixed roughness per level counted from
  the 1² level (r = 1 at level N − 3).  ``r.ReflectionCaptureResolution`` defaults to 128: 128² … 1², N = 8.
* ``threejs`` — three.js ``src/renderers/shaders/ShaderChunk/cube_uv_reflection_fragment.glsl.js``
  (``roughnessToMip``, ``textureCubeUV``; the same formula in mrdoob/three.js commit 6f966c1's fixed 256² layout
  and in the variable layout's ``CUBEUV_MAX_MIP``): m(r) is piecewise linear through (r, m) = (1, −2), (0.8, −1),
  (0.4, 2), (0.305, 3), (0.21, 4) and m = −2·log2(1.16 r) below r = 0.21; the look-up clamps m to
  [−2, CUBEUV_MAX_MIP] and blends ⌊m⌋ with ⌊m⌋ + 1.  ``src/extras/PMREMGenerator.js`` (commit 54fe7ad):
  lodMax = ⌊log2 b⌋, ``LOD_MIN`` = 4, so the "cubeUV" chain holds b², …, 16² and then ``EXTRA_LOD_SIGMA``'s 6
  further levels at 16² (N = lodMax + 3: 11 at the default 256²); level 0 is the unfiltered source (sigma 0).

Where a mapping is not invertible
---------------------------------
``roughness(ℓ)`` returns the roughness the engine's prefilter stores; ``level(roughness(ℓ)) == ℓ`` holds for
every ℓ of ``linear``, ``filament`` and ``unity``, and otherwise except:

* ``unreal`` — every r below r₀ = 2^((3 − N)/1.2) reads level 0 (the look-up is clamped there); level 0 stores r₀.
  Levels above N − 3 are read by no r ≤ 1: the engine fills them at r = 2^((ℓ − N + 3)/1.2) > 1 (α > 1);
  ``roughness`` returns 1 there (the lab's prefilter takes r ≤ 1).
* ``threejs`` — level 0 stores the source (``roughness`` returns 0), read by every r with m(r) ≥ lodMax
  (r ≤ 2^(−lodMax/2)/1.16).  The two branches of m do not meet at r = 0.21 (4 against −2·log2(1.16·0.21) =
  4.0748): fractional levels whose m lies in (4, 4.0748) are read by no roughness, and ``roughness`` returns 0.21
  there.  The modelling simplification: three.js fills its levels with Gaussian blurs of standard deviation
  2^−m (b² … 16²) and ``EXTRA_LOD_SIGMA`` (the extra levels), fitted to GGX; the lab's chains store the exact GGX
  prefilter at ``roughness(ℓ)`` instead, so what is measured is the mapping (and the layout), not the blur.

For a chain of N levels not the engine's own (the lab's equal-memory comparison), ``unreal`` keeps its levels
counted from the last one (r = 1 at N − 3) and ``threejs`` its lodMax = N − 3 (its m = −2 level last).

Examples
--------
>>> from ibl_ref.prefilter.mip_mappings import ROUGHNESS_MAPPINGS
>>> round(float(ROUGHNESS_MAPPINGS["unity"].level(0.5, 7)), 6)     # 0.5 · 1.35 · 6
4.05
>>> float(ROUGHNESS_MAPPINGS["unreal"].level(1.0, 8)), float(ROUGHNESS_MAPPINGS["filament"].level(0.5, 5))
(5.0, 3.0)
>>> ROUGHNESS_MAPPINGS["threejs"].chain_sizes(256)
(256, 128, 64, 32, 16, 16, 16, 16, 16, 16, 16)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import IBLError

__all__ = ["MipMapping", "LinearMapping", "FilamentMapping", "UnityMapping", "UnrealMapping", "ThreejsMapping",
           "ROUGHNESS_MAPPINGS", "get_mapping", "check_n_levels"]

#: Unreal's REFLECTION_CAPTURE_ROUGHNESS_MIP_SCALE and the floor of its roughness in the look-up
_UE_SCALE, _UE_MIN_ROUGHNESS = 1.2, 0.001
#: three.js roughnessToMip: the knots (roughness, mip) of its linear pieces, mips increasing
_THREE_KNOTS_MIP = np.array([-2.0, -1.0, 2.0, 3.0, 4.0])
_THREE_KNOTS_R = np.array([1.0, 0.8, 0.4, 0.305, 0.21])
#: three.js: m = −2·log2(1.16 r) below r = 0.21, and the mip where that branch starts (the gap's upper end)
_THREE_LOG_FACTOR = 1.16
_THREE_GAP_TOP = -2.0 * np.log2(_THREE_LOG_FACTOR * 0.21)
#: three.js PMREMGenerator: LOD_MIN and the number of EXTRA_LOD_SIGMA levels
_THREE_LOD_MIN, _THREE_EXTRA = 4, 6


def check_n_levels(n_levels) -> int:
    """``n_levels`` as an int ≥ 2 (level 0 the base and at least one more); a one-line IBLError otherwise."""
    if isinstance(n_levels, bool) or not isinstance(n_levels, (int, np.integer)) or n_levels < 2:
        raise IBLError(f"n_levels must be an integer >= 2 (level 0 is the base), got {n_levels!r}")
    return int(n_levels)


def _check_roughness(roughness) -> np.ndarray:
    try:
        r = np.asarray(roughness, dtype=np.float64)
    except (TypeError, ValueError):
        raise IBLError(f"roughness must be a number in [0, 1], got {roughness!r}") from None
    bad = ~np.isfinite(r) | (r < 0) | (r > 1)
    if np.any(bad):
        raise IBLError(f"roughness must be in [0, 1], got {r[bad].ravel()[0]!r}")
    return r


def _check_level(level, n: int) -> np.ndarray:
    try:
        x = np.asarray(level, dtype=np.float64)
    except (TypeError, ValueError):
        raise IBLError(f"level must be a number, got {level!r}") from None
    if not np.all(np.isfinite(x)):
        raise IBLError("level must be finite")
    return np.clip(x, 0.0, n - 1.0)


def _power_of_two(base) -> int:
    if isinstance(base, bool) or not isinstance(base, (int, np.integer)) or base < 1 or base & (base - 1):
        raise IBLError(f"base face size must be a power of two >= 1, got {base!r}")
    return int(base)


@dataclass(frozen=True)
class MipMapping:
    """One engine's roughness ↔ MIP-level mapping (module docstring).

    Attributes
    ----------
    name : key in :data:`ROUGHNESS_MAPPINGS`
    engine : the engines that use it
    formula : the look-up, ℓ(r, N)
    source : where the formula and the defaults come from (file, version)
    default_base : the engine's default base face size (None: sized from the input)
    min_face_size : face size of the engine's smallest level at its default base
    """

    name: str
    engine: str
    formula: str
    source: str
    default_base: int | None
    min_face_size: int

    # the formulas on checked float64 arrays (r in [0, 1], ℓ in [0, N − 1]); one subclass per engine
    def _level(self, r: np.ndarray, n: int) -> np.ndarray:
        raise NotImplementedError

    def _roughness(self, x: np.ndarray, n: int) -> np.ndarray:
        raise NotImplementedError

    def _sizes(self, base: int) -> tuple:
        raise NotImplementedError

    def level(self, roughness, n_levels: int):
        """Fractional level (float64, same shape as ``roughness``) the engine reads for roughness r ∈ [0, 1] in a
        chain of ``n_levels``, within [0, n_levels − 1]."""
        n = check_n_levels(n_levels)
        r = _check_roughness(roughness)
        return np.clip(self._level(r, n), 0.0, n - 1.0)[()]

    def roughness(self, level, n_levels: int):
        """Roughness in [0, 1] the engine stores in (fractional) ``level`` of ``n_levels`` (levels outside
        [0, n_levels − 1] are clamped); the inverse of :meth:`level` where that is invertible (module docstring)."""
        n = check_n_levels(n_levels)
        return np.clip(self._roughness(_check_level(level, n), n), 0.0, 1.0)[()]

    def chain_sizes(self, base: int) -> tuple:
        """Face sizes of the engine's own chain for a base face of ``base`` texels (a power of two), level 0 first."""
        return self._sizes(_power_of_two(base))

    @property
    def default_levels(self) -> int | None:
        """N of the engine's chain at its default base (None where the base comes from the input)."""
        return None if self.default_base is None else len(self.chain_sizes(self.default_base))


def _halving(base: int, n: int, smallest: int = 1) -> tuple:
    return tuple(max(base >> k, smallest, 1) for k in range(n))


class LinearMapping(MipMapping):
    """lod = r: Khronos glTF-IBL-Sampler, glTF-Sample-Viewer, Bevy."""

    def _level(self, r, n):
        return r * (n - 1)

    def _roughness(self, x, n):
        return x / (n - 1)

    def _sizes(self, base):
        return _halving(base, max(2, base.bit_length() - 1))  # ⌊log2 b⌋ levels: b … 2²


class FilamentMapping(MipMapping):
    """lod = r(2 − r): Filament's run time and cmgen."""

    def _level(self, r, n):
        return r * (2.0 - r) * (n - 1)

    def _roughness(self, x, n):
        return 1.0 - np.sqrt(np.maximum(1.0 - x / (n - 1), 0.0))

    def _sizes(self, base):
        k, m = base.bit_length() - 1, 16  # cmgen's minimum level 16²; smaller bases go down to 1²
        return _halving(base, max(2, k - 3 if base > m else k + 1))


class UnityMapping(MipMapping):
    """lod = r(1.7 − 0.7r): Unity built-in and SRP (URP, HDRP's core library)."""

    def _level(self, r, n):
        return r * (1.7 - 0.7 * r) * (n - 1)

    def _roughness(self, x, n):
        return (1.7 - np.sqrt(np.maximum(2.89 - 2.8 * x / (n - 1), 0.0))) / 1.4

    def _sizes(self, base):
        return _halving(base, 7)  # UNITY_SPECCUBE_LOD_STEPS + 1 levels


class UnrealMapping(MipMapping):
    """ℓ = N − 3 + 1.2·log2 r: Unreal Engine 4's reflection captures (a fixed roughness per level from 1²)."""

    def _level(self, r, n):
        return n - 3.0 + _UE_SCALE * np.log2(np.maximum(r, _UE_MIN_ROUGHNESS))

    def _roughness(self, x, n):
        return np.minimum(np.exp2((x - n + 3.0) / _UE_SCALE), 1.0)

    def _sizes(self, base):
        return _halving(base, max(2, base.bit_length()))  # b … 1²


class ThreejsMapping(MipMapping):
    """three.js PMREM "cubeUV": piecewise roughness → mip, extra blurred levels at 16²."""

    @staticmethod
    def mip(roughness):
        """three.js's ``roughnessToMip`` m(r) (before the look-up's clamp): −2 at r = 1, 4 at r = 0.21,
        −2·log2(1.16 r) below; +inf at r = 0."""
        r = _check_roughness(roughness)
        with np.errstate(divide="ignore"):
            low = -2.0 * np.log2(_THREE_LOG_FACTOR * r)
        lin = np.interp(r, _THREE_KNOTS_R[::-1], _THREE_KNOTS_MIP[::-1])
        return np.where(r >= _THREE_KNOTS_R[-1], lin, low)[()]

    def _level(self, r, n):
        lod_max = n - 3.0
        return lod_max - np.clip(self.mip(r), _THREE_KNOTS_MIP[0], lod_max)

    def _roughness(self, x, n):
        m = (n - 3.0) - x
        lin = np.interp(m, _THREE_KNOTS_MIP, _THREE_KNOTS_R)
        log = np.exp2(-0.5 * m) / _THREE_LOG_FACTOR
        r = np.where(m <= _THREE_KNOTS_MIP[-1], lin, np.where(m < _THREE_GAP_TOP, _THREE_KNOTS_R[-1], log))
        return np.where(x == 0.0, 0.0, r)  # level 0: the unfiltered source

    def _sizes(self, base):
        lod_max = base.bit_length() - 1
        smallest = 2 ** min(_THREE_LOD_MIN, lod_max)
        return _halving(base, lod_max - _THREE_LOD_MIN + 1 + _THREE_EXTRA, smallest)


#: the engines' mappings by name (module docstring); ``ibl-ref prefilter --mapping`` offers these names
ROUGHNESS_MAPPINGS = {m.name: m for m in (
    LinearMapping(
        "linear", "Khronos glTF-IBL-Sampler / glTF-Sample-Viewer, Bevy", "lod = r·(N − 1)",
        "glTF-IBL-Sampler lib/source/lib.cpp (commit 0138f41): roughness ℓ/(mipLevelCount − 1), "
        "mipLevelCount ⌊log2 b⌋; glTF-Sample-Viewer ibl.glsl getIBLRadianceGGX; Bevy environment_map.wgsl",
        None, 2),
    FilamentMapping(
        "filament", "Filament (cmgen and run time)", "lod = r(2 − r)·(N − 1)",
        "Filament shaders/src/light_indirect.fs perceptualRoughnessToLod (iblRoughnessOneLevel = N − 1); "
        "cmgen 1.9.25: r = 1 − √(1 − ℓ/(N − 1)), 256² … 16²",
        256, 16),
    UnityMapping(
        "unity", "Unity built-in and URP", "lod = r(1.7 − 0.7r)·(N − 1)",
        "Unity Graphics v10.8.0 com.unity.render-pipelines.core/ShaderLibrary/ImageBasedLighting.hlsl "
        "PerceptualRoughnessToMipmapLevel / MipmapLevelToPerceptualRoughness, UNITY_SPECCUBE_LOD_STEPS 6; "
        "built-in UnityImageBasedLighting.cginc Unity_GlossyEnvironment",
        128, 2),
    UnrealMapping(
        "unreal", "Unreal Engine 4 reflection captures", "ℓ = N − 3 + 1.2·log2 r, clamped to [0, N − 1]",
        "UE 4.27 Engine/Shaders/Private/ReflectionEnvironmentShared.ush ComputeReflectionCaptureMipFromRoughness "
        "/ ComputeReflectionCaptureRoughnessFromMip (ROUGHEST_MIP 1, ROUGHNESS_MIP_SCALE 1.2, "
        "CubemapMaxMip = N − 1); r.ReflectionCaptureResolution 128",
        128, 1),
    ThreejsMapping(
        "threejs", "three.js PMREMGenerator (cubeUV)",
        "ℓ = (N − 3) − clamp(m(r), −2, N − 3), m piecewise linear through (1, −2), (0.8, −1), (0.4, 2), "
        "(0.305, 3), (0.21, 4), −2·log2(1.16 r) below 0.21",
        "three.js src/renderers/shaders/ShaderChunk/cube_uv_reflection_fragment.glsl.js roughnessToMip / "
        "textureCubeUV (mrdoob/three.js 6f966c1; CUBEUV_MAX_MIP = lodMax in later revisions); "
        "src/extras/PMREMGenerator.js (54fe7ad): LOD_MIN 4, 6 EXTRA_LOD_SIGMA levels, fromScene 256²",
        256, 16),
)}


def get_mapping(mapping) -> MipMapping:
    """The :class:`MipMapping` of a name in :data:`ROUGHNESS_MAPPINGS` (or the mapping itself); a one-line
    IBLError listing the names otherwise.

    Examples
    --------
    >>> get_mapping("filament").default_levels, get_mapping("unreal").default_levels
    (5, 8)
    """
    if isinstance(mapping, MipMapping):
        return mapping
    if isinstance(mapping, str) and mapping in ROUGHNESS_MAPPINGS:
        return ROUGHNESS_MAPPINGS[mapping]
    raise IBLError(f"mapping must be one of {', '.join(ROUGHNESS_MAPPINGS)}, got {mapping!r}")
