"""Knuth et al. (2014) Fig. 8: memory footprint of the PEMs and VSMs, reproduced by a byte model.

The published table (Fig. 8, "Memory footprint (in MB). The PEMs use 16Bit floats with 4 color
channels (GL_RGBA16F) while the VSMs have only 2 channels (GL_RG16F)") has six unlabeled rows and the
columns PEM 128², PEM 256², VSM 64² … 1024² (:data:`PAPER_FIG8`).

What the printed numbers imply (worked out by :func:`infer_fig8_rows`, checked in the tests)
-------------------------------------------------------------------------------------------
* **"MB" is MiB (2²⁰ bytes)**: VSM 64² RG16F = 64·64·2·2 B = 16 KiB = 0.015625 MiB exactly.
* **Rows are the light counts 1, 12, 32, 64, 128, 256**: the VSM columns carry no MIP chain
  (a single RG16F map per light) and give count = MB·2²⁰ / (res²·4 B) in every VSM column.
* **PEM = 6 faces · n² · 8 B (RGBA16F) · 2 per light**: the first row PEM 128² is 1.5 MiB, while one
  RGBA16F cube map of 128² faces is 0.75 MiB; a full MIP chain costs ×(4/3)(1 − 4⁻ᴸ) ≈ 1.333 (→ 1.0 MiB),
  so the table uses a **MIP factor of exactly 2** (as if every level halved the texel count,
  1 + ½ + ¼ + … = 2; or storage for two levels' worth of copies).  With factor 2 every PEM number of
  the table is reproduced exactly, and so are the two numbers in the text of Sec. 5: 64 regions of
  512² cube maps "roughly 1.5 GB" (= 1536 MiB exactly), and 64 parabolic maps of 256² "about 70 MB"
  (= 64 MiB = 67.1 MB).  The paper's future-work saving is 1536/70 ≈ 21.9×.
* **Inconsistency with Sec. 4**: per-face median cut gives a multiple of six lights, but the rows 1,
  32, 64, 128 and 256 are not multiples of six (only 12 is); the table is a memory model per light
  count, not a list of median-cut runs (1 light cannot come from a per-face cut at all).

This library's own arrays (:func:`library_pem_bytes`, :func:`library_vsm_bytes`) are stated next to
the model: PEMs as float32 (default of :class:`ibl_ref.knuth2014.pem.PEMSet`) RGB, full MIP chain down to 1×1,
Σ_l 6·(n/2ˡ)²·C·4 B; VSMs as two channels (μ, μ²) in float32 or float16.
"""

from __future__ import annotations

import numpy as np

from ..errors import IBLError

__all__ = [
    "MIB",
    "PAPER_FIG8",
    "FIG8_COLUMNS",
    "FIG8_LIGHT_COUNTS",
    "PAPER_MIP_FACTOR",
    "paper_pem_bytes",
    "paper_vsm_bytes",
    "fig8_model_table",
    "infer_fig8_rows",
    "mip_chain_texels",
    "library_pem_bytes",
    "library_vsm_bytes",
]

MIB = 2**20

#: Fig. 8 as published (MB), columns in the printed order.
PAPER_FIG8 = {
    "PEM_128": (1.5, 18, 48, 96, 192, 384),
    "PEM_256": (6, 72, 192, 384, 768, 1536),
    "VSM_64": (0.015625, 0.1875, 0.5, 1, 2, 4),
    "VSM_128": (0.0625, 0.75, 2, 4, 8, 16),
    "VSM_256": (0.25, 3, 8, 16, 32, 64),
    "VSM_512": (1, 12, 32, 64, 128, 256),
    "VSM_1024": (4, 48, 128, 256, 512, 1024),
}
#: (kind, resolution) of each column.
FIG8_COLUMNS = {k: (k.split("_")[0], int(k.split("_")[1])) for k in PAPER_FIG8}
#: Light counts of the rows, as inferred by :func:`infer_fig8_rows`.
FIG8_LIGHT_COUNTS = (1, 12, 32, 64, 128, 256)
#: MIP-chain factor that reproduces the PEM columns (a true MIP chain is ≈ 4/3).
PAPER_MIP_FACTOR = 2.0

RGBA16F_BYTES = 4 * 2
RG16F_BYTES = 2 * 2


def paper_pem_bytes(n_lights, face_size, bytes_per_texel: int = RGBA16F_BYTES, mip_factor: float = PAPER_MIP_FACTOR):
    """Bytes of ``n_lights`` PEM cube maps as Fig. 8 counts them: L · 6 · n² · bytes · mip_factor."""
    return np.asarray(n_lights) * 6 * face_size**2 * bytes_per_texel * mip_factor


def paper_vsm_bytes(n_lights, res, bytes_per_texel: int = RG16F_BYTES):
    """Bytes of ``n_lights`` variance shadow maps (RG16F, no MIP chain): L · res² · 4."""
    return np.asarray(n_lights) * res**2 * bytes_per_texel


def fig8_model_table(light_counts=FIG8_LIGHT_COUNTS) -> dict:
    """The model's Fig. 8 (MiB) for the given row light counts, same keys as :data:`PAPER_FIG8`."""
    out = {}
    for key, (kind, res) in FIG8_COLUMNS.items():
        b = paper_pem_bytes(np.asarray(light_counts), res) if kind == "PEM" else paper_vsm_bytes(np.asarray(light_counts), res)
        out[key] = tuple(float(x) for x in b / MIB)
    return out


def infer_fig8_rows(table=PAPER_FIG8) -> dict:
    """Work out from the printed numbers which light counts the rows are and the PEM MIP factor.

    Light counts come from the VSM columns alone (one RG16F map of res² per light, no MIP chain),
    count = MB·2²⁰ / (res²·4); they must agree across the five VSM columns and be integers.
    The MIP factor then follows from each PEM entry: MB·2²⁰ / (count · 6 · n² · 8).

    Returns
    -------
    dict with ``light_counts`` (tuple of int), ``mip_factors`` (per PEM entry), ``consistent`` (bool).
    """
    counts = []
    for key, (kind, res) in FIG8_COLUMNS.items():
        if kind != "VSM":
            continue
        counts.append(np.asarray(table[key], dtype=np.float64) * MIB / (res**2 * RG16F_BYTES))
    counts = np.array(counts)
    if not np.allclose(counts, counts[0], rtol=0, atol=1e-9) or not np.allclose(counts[0], np.round(counts[0]), atol=1e-9):
        raise IBLError(f"Fig. 8 VSM columns do not give one integer light count per row: {counts}")
    lc = np.round(counts[0]).astype(int)
    factors = []
    for key, (kind, res) in FIG8_COLUMNS.items():
        if kind == "PEM":
            factors.append(np.asarray(table[key], dtype=np.float64) * MIB / (lc * 6 * res**2 * RGBA16F_BYTES))
    factors = np.array(factors)
    return {
        "light_counts": tuple(int(x) for x in lc),
        "mip_factors": factors,
        "consistent": bool(np.allclose(factors, factors.flat[0], rtol=0, atol=1e-12)),
    }


def mip_chain_texels(face_size: int, levels: int | None = None) -> int:
    """Texels of a cube-map MIP chain: Σ_l 6·(n/2ˡ)² down to 1×1 (or ``levels`` levels)."""
    n = int(face_size)
    if n < 1 or n & (n - 1):
        raise IBLError(f"face size must be a power of two, got {face_size}")
    total, l, m = 0, 0, n
    while m >= 1 and (levels is None or l < levels):
        total += 6 * m * m
        m //= 2
        l += 1
    return total


def library_pem_bytes(n_lights, face_size, channels: int = 3, dtype=np.float32, levels: int | None = None):
    """Bytes of this library's dense PEM storage: L · Σ_l 6·(n/2ˡ)² · C · itemsize (the arrays' nbytes)."""
    return int(n_lights) * mip_chain_texels(face_size, levels) * channels * np.dtype(dtype).itemsize


def library_vsm_bytes(n_lights, res, dtype=np.float32, channels: int = 2):
    """Bytes of ``n_lights`` VSM arrays (μ, μ²) of res² texels: L · res² · 2 · itemsize."""
    return int(n_lights) * int(res) ** 2 * channels * np.dtype(dtype).itemsize
