"""Tests of ibl_ref.knuth2014.memory_model against the published Fig. 8 of Knuth et al. (2014)."""

import numpy as np
import pytest

from ibl_ref.knuth2014.memory_model import (
    MIB,
    PAPER_FIG8,
    fig8_model_table,
    infer_fig8_rows,
    library_pem_bytes,
    library_vsm_bytes,
    mip_chain_texels,
    paper_pem_bytes,
)

# Fig. 8 as printed in the paper (MB), typed in again here from the paper's table (independent of the
# module's copy): columns PEM 128², PEM 256², VSM 64², 128², 256², 512², 1024².
PUBLISHED = [
    (1.5, 6, 0.015625, 0.0625, 0.25, 1, 4),
    (18, 72, 0.1875, 0.75, 3, 12, 48),
    (48, 192, 0.5, 2, 8, 32, 128),
    (96, 384, 1, 4, 16, 64, 256),
    (192, 768, 2, 8, 32, 128, 512),
    (384, 1536, 4, 16, 64, 256, 1024),
]
KEYS = ["PEM_128", "PEM_256", "VSM_64", "VSM_128", "VSM_256", "VSM_512", "VSM_1024"]


def test_module_copy_matches_paper():
    for j, k in enumerate(KEYS):
        assert tuple(PAPER_FIG8[k]) == tuple(row[j] for row in PUBLISHED)


def test_model_reproduces_every_published_number_exactly():
    model = fig8_model_table()
    for j, k in enumerate(KEYS):
        for i, row in enumerate(PUBLISHED):
            # all entries are dyadic rationals: the byte model must hit them exactly (no tolerance)
            assert model[k][i] == row[j], (k, i)


def test_inferred_rows_and_mip_factor():
    inf = infer_fig8_rows()
    assert inf["light_counts"] == (1, 12, 32, 64, 128, 256)
    assert inf["consistent"]
    assert np.all(inf["mip_factors"] == 2.0)
    # the factor 2 is not the true MIP-chain factor (≈ 4/3)
    assert mip_chain_texels(128) / (6 * 128**2) == pytest.approx(4 / 3, rel=1e-4)


def test_text_numbers_of_section5():
    # "512x512 ... 64 regions ... with MIP maps and floating point color values ... roughly 1.5 GB"
    assert paper_pem_bytes(64, 512) / MIB == 1536
    # parabolic maps, 256², 64 regions: "about 70 MB": the same model with one 256² image per map instead of six
    # cube faces, 64 · 256² texels · 8 bytes (RGBA16F) · 2 (Fig. 8's MIP factor) = 67 108 864 bytes exactly,
    # which the text rounds to the nearest 10 MB
    b = paper_pem_bytes(64, 256) / 6
    assert b == 64 * 256**2 * 8 * 2
    assert round(b / 10e6) * 10 == 70
    # and the saving the text draws from the two ("1.5 GB" → "about 70 MB") is the model's 4 · 6 = 24 exactly
    assert paper_pem_bytes(64, 512) / b == 24.0


def test_library_bytes_match_real_arrays():
    # independent: allocate the arrays and ask numpy
    levels = [np.zeros((6, m, m, 3), np.float32) for m in (16, 8, 4, 2, 1)]
    assert library_pem_bytes(1, 16) == sum(a.nbytes for a in levels)
    assert library_vsm_bytes(3, 64, np.float16) == 3 * np.zeros((64, 64, 2), np.float16).nbytes
    with pytest.raises(ValueError, match=r"face size must be a power"):
        mip_chain_texels(12)
