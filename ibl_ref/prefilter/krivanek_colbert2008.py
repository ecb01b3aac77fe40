"""Křivánek & Colbert (2008), "Real-time Shading with Filtered Importance Sampling" — the GGX prefilter by
filtered importance sampling (FIS).

Computer Graphics Forum 27(4) (EGSR 2008), Sec. 3 ("Filtered importance sampling"; the same rule is in Colbert &
Křivánek, GPU Gems 3, Ch. 20).  Plain importance sampling (:func:`ibl_ref.prefilter.karis2013.prefilter_importance`)
reads the environment at full resolution, so a few samples alias; FIS reads every sample from a box-filtered MIP
level of the source whose texels cover about the solid angle the sample stands for::

    Ω_s = 1 / (N · p(l_k))                        solid angle of one of N samples with pdf p
    Ω_p = solid angle of a level-0 texel at l_k   (``texel_solid_angle="exact"``: the exact solid angle of the texel
                                                   containing l_k — the paper's Ω_p = d(u)/(w·h) with the
                                                   parameterisation's distortion d; ``"mean"``: 4π/(6N²), what most
                                                   shipped shaders use)
    lod   = max(½ · log2(Ω_s / Ω_p) + bias, 0)    the paper's level rule, ``bias = 1`` by default (the paper's
                                                   choice: filtering a bit wider than the sample spacing)

(½ log2: one MIP level halves the texel size along each axis, i.e. quarters its solid angle.)  The value of a sample
is the trilinear lookup at ``lod`` in the **source pyramid** (:func:`source_pyramid`: level k is the exact
area-weighted average of 2ᵏ × 2ᵏ blocks of source texels, so ∫L dω is the same on every level; lookups are the
seam-aware bilinear :class:`ibl_ref.environment.sampling.CubeSampler` within a level, linear between levels; the
lod is clipped to the top level).  The estimator is Karis's n·l-weighted ratio with ``n = v = r``
(:mod:`ibl_ref.prefilter.karis2013`, Eq. 8 there): ``P ≈ Σ_k L_lod(l_k)(r·l_k) / Σ_k (r·l_k)``, with the pdf of
the reflected direction ``p(l) = D(θh)/4`` (:func:`ibl_ref.prefilter.karis2013.sample_pdf`).

FIS trades noise for blur (bias): its result converges to a *filtered* prefilter, not to the exact one, but at
small N its error against :func:`~ibl_ref.prefilter.karis2013.prefilter_exact` is far smaller than that of plain
importance sampling (measured in ``tests/test_krivanek_colbert2008.py``).
"""

from __future__ import annotations

import numpy as np

from ..environment import envmap
from ..environment.resample import cube_to_cube
from ..environment.sampling import CubeSampler
from ..errors import IBLError
from ..groundtruth.convolution_args import check_cube
from . import karis2013

__all__ = ["TEXEL_SOLID_ANGLES", "source_pyramid", "fis_lod", "prefilter_fis", "build_fis_chain",
           "FilteredImportanceSampling"]

#: the Ω_p options of :func:`fis_lod` (module doc)
TEXEL_SOLID_ANGLES = ("exact", "mean")


def source_pyramid(cube) -> list:
    """Box-filtered MIP levels of the source: face sizes N, N/2, … while even (down to 1 for a power of two),
    level k the exact area-weighted average Σ Ω L / Σ Ω over 2ᵏ × 2ᵏ source blocks
    (:func:`ibl_ref.environment.resample.cube_to_cube`).  Returns a list of (6, N_k, N_k, C) float64."""
    a, _ = check_cube(cube)
    levels = [a]
    m = a.shape[1]
    while m % 2 == 0:
        m //= 2
        levels.append(cube_to_cube(a, m))
    return levels


def fis_lod(pdf, samples: int, omega_p, bias: float = 1.0) -> np.ndarray:
    """The level rule ``max(½ log2(Ω_s/Ω_p) + bias, 0)`` with ``Ω_s = 1/(N·pdf)`` (module doc); arrays broadcast."""
    samples = karis2013.check_samples(samples)
    pdf = np.asarray(pdf, dtype=np.float64)
    omega_p = np.asarray(omega_p, dtype=np.float64)
    if np.any(~(pdf > 0)) or np.any(~(omega_p > 0)):
        raise IBLError("fis_lod: the pdf and the texel solid angle must be positive")
    omega_s = 1.0 / (samples * pdf)
    return np.maximum(0.5 * np.log2(omega_s / omega_p) + float(bias), 0.0)


def _check_bias(bias) -> float:
    try:
        b = float(bias)
    except (TypeError, ValueError):
        raise IBLError(f"bias must be a finite number, got {bias!r}") from None
    if not np.isfinite(b):
        raise IBLError(f"bias must be a finite number, got {bias!r}")
    return b


class _PyramidLookup:
    """Trilinear lookups at a per-sample level of detail in a source pyramid."""

    def __init__(self, pyramid, samples, alpha, bias, texel_solid_angle):
        self.samplers = [CubeSampler(lv) for lv in pyramid]
        self.n = pyramid[0].shape[1]
        self.samples, self.alpha, self.bias = samples, alpha, bias
        self.omega = envmap.texel_solid_angles(self.n) if texel_solid_angle == "exact" else None
        self.channels = pyramid[0].shape[-1]
        self.lods = []

    def __call__(self, l_dir, cos_h):
        pdf = karis2013.sample_pdf(cos_h, self.alpha)
        if self.omega is None:
            omega_p = 4.0 * np.pi / (6.0 * self.n * self.n)
        else:
            _, row, col = envmap.direction_to_texel(l_dir, self.n)
            omega_p = self.omega[row, col]
        top = len(self.samplers) - 1
        lod = np.minimum(fis_lod(pdf, self.samples, omega_p, self.bias), top)
        self.lods.append((float(lod.min(initial=np.inf)), float(lod.max(initial=-np.inf)), float(lod.sum()), lod.size))
        if top == 0:
            return self.samplers[0].bilinear(l_dir)
        k0 = np.minimum(np.floor(lod).astype(np.intp), top - 1)
        t = (lod - k0)[:, None]
        out = np.empty((len(l_dir), self.channels))
        for k in np.unique(k0):
            sel = k0 == k
            lo = self.samplers[k].bilinear(l_dir[sel])
            hi = self.samplers[k + 1].bilinear(l_dir[sel])
            out[sel] = (1.0 - t[sel]) * lo + t[sel] * hi
        return out


def prefilter_fis(cube, roughness, *, samples: int = 64, sequence: str = "hammersley", seed=0, bias: float = 1.0,
                  texel_solid_angle: str = "exact", out_size=None, dirs=None, pyramid=None,
                  chunk_elems: int = 1 << 20, return_info: bool = False):
    """Filtered importance sampling of the ``n = v = r`` GGX prefilter (module doc).

    Parameters
    ----------
    cube : (6, N, N[, C]) radiance;  roughness : float in (0, 1];  samples : N ≥ 1
    sequence, seed : as in :func:`ibl_ref.prefilter.karis2013.prefilter_importance`
    bias : the level bias (paper: 1)
    texel_solid_angle : Ω_p, ``"exact"`` (default) or ``"mean"``
    out_size, dirs : output texel centres of a face of ``out_size`` (default N) or given directions
    pyramid : a precomputed :func:`source_pyramid` of ``cube`` (built when None)
    return_info : also return ``{"empty": count, "lod_min", "lod_max", "lod_mean"}``
    """
    a, squeeze = check_cube(cube)
    _, alpha = karis2013.check_scalar_roughness(roughness)
    samples = karis2013.check_samples(samples)
    karis2013.check_sequence(sequence)
    bias = _check_bias(bias)
    karis2013.check_option(texel_solid_angle, TEXEL_SOLID_ANGLES, "texel_solid_angle")
    pyr = source_pyramid(a) if pyramid is None else pyramid
    if pyr[0].shape != a.shape:
        raise IBLError(f"pyramid level 0 has shape {pyr[0].shape}, the cube {a.shape}")
    out_d, lead = karis2013.output_directions(a.shape[1], out_size, dirs)
    look = _PyramidLookup(pyr, samples, alpha, bias, texel_solid_angle)
    out, n_empty = karis2013.importance_sum(out_d, alpha, samples, sequence, seed, chunk_elems, look, a.shape[-1])
    out = karis2013.check_finite(out, "prefilter_fis").reshape(lead + (a.shape[-1],))
    out = out[..., 0] if squeeze else out
    if not return_info:
        return out
    cnt = sum(x[3] for x in look.lods)
    info = {"empty": n_empty, "lod_min": min((x[0] for x in look.lods), default=0.0),
            "lod_max": max((x[1] for x in look.lods), default=0.0),
            "lod_mean": sum(x[2] for x in look.lods) / cnt if cnt else 0.0}
    return out, info


def build_fis_chain(cube, *, samples: int = 64, sequence: str = "hammersley", seed: int = 0, bias: float = 1.0,
                    texel_solid_angle: str = "exact", **chain_kw):
    """A prefiltered roughness chain (:func:`ibl_ref.prefilter.karis2013.build_chain`) whose levels are computed
    by :func:`prefilter_fis` (one source pyramid shared by all levels; per-level seeds ``(seed, ℓ)``)."""
    a, _ = check_cube(cube)
    samples = karis2013.check_samples(samples)
    karis2013.check_sequence(sequence)
    bias = _check_bias(bias)
    karis2013.check_option(texel_solid_angle, TEXEL_SOLID_ANGLES, "texel_solid_angle")
    pyr = source_pyramid(a)

    def fis(c, rough, out_size, level):
        return prefilter_fis(c, rough, samples=samples, sequence=sequence, seed=(seed, level), bias=bias,
                             texel_solid_angle=texel_solid_angle, out_size=out_size, pyramid=pyr)

    chain = karis2013.build_chain(a, prefilter=fis, name="fis", **chain_kw)
    chain.info.update(samples=samples, sequence=sequence, seed=int(seed), bias=bias,
                      texel_solid_angle=texel_solid_angle)
    return chain


class FilteredImportanceSampling(karis2013.SplitSum):
    """Karis 2013 split sum with the chain prefiltered by filtered importance sampling (Křivánek & Colbert 2008)."""

    paper = ("Křivánek & Colbert 2008, Real-time Shading with Filtered Importance Sampling, Sec. 3, as the "
             "prefilter of Karis 2013's split sum")

    def __init__(self, cube, *, samples: int = 64, sequence: str = "hammersley", seed: int = 0, bias: float = 1.0,
                 texel_solid_angle: str = "exact", n_levels=None, min_face_size: int = 1, dfg_size=64,
                 smith: str = "height_correlated", dtype="float64"):
        self._init(build_fis_chain(cube, samples=samples, sequence=sequence, seed=seed, bias=bias,
                                   texel_solid_angle=texel_solid_angle, n_levels=n_levels,
                                   min_face_size=min_face_size, dtype=dtype),
                   karis2013.build_dfg_table(dfg_size, smith=smith))

    @classmethod
    def build(cls, cube, *, samples: int = 64, sequence: str = "hammersley", seed: int = 0, bias: float = 1.0,
              texel_solid_angle: str = "exact", dfg_size=64, smith: str = "height_correlated", **chain_kw):
        chain = build_fis_chain(cube, samples=samples, sequence=sequence, seed=seed, bias=bias,
                                texel_solid_angle=texel_solid_angle, **chain_kw)
        return cls.from_parts(chain, karis2013.build_dfg_table(dfg_size, smith=smith))

    def direct(self, cube, roughness, dirs) -> np.ndarray:
        """The chain's filtered importance sampling (same samples, sequence, seed, bias and texel solid angle) at
        ``dirs`` from the full-resolution ``cube``."""
        info = self.chain.info
        return prefilter_fis(cube, roughness, samples=info["samples"], sequence=info["sequence"],
                             seed=(info["seed"], 0), bias=info["bias"], texel_solid_angle=info["texel_solid_angle"],
                             dirs=dirs)
