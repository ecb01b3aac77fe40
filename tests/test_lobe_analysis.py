"""Tests of ibl_ref.knuth2014.lobe_analysis (Knuth et al. 2014 Sec. 5 lobe-volume fit)."""

import numpy as np
import pytest

from ibl_ref.environment.envmap import cube_solid_angles, texel_directions
from ibl_ref.errors import IBLError
from ibl_ref.knuth2014.lobe_analysis import (
    LobeResponse,
    analyse,
    lobe_volume,
    s_texel_limit,
    target_lobe,
    target_volume,
)


@pytest.mark.parametrize("s", [1.0, 4.0, 20.0])
def test_target_volumes_closed_form_vs_quadrature(s):
    # closed forms 2π/(s+1) and 2π/(3(3s+1)) vs exact-solid-angle quadrature on a 128² grid
    d = texel_directions(128).reshape(-1, 3)
    w = np.asarray(cube_solid_angles(128)).reshape(-1)
    t = target_lobe(d @ np.array([0.3, 0.4, np.sqrt(0.75)]), s)
    # midpoint quadrature, h = 2/128: relative error well below 1e-3 for these smooth lobes
    assert np.isclose(lobe_volume(t, w, "integral"), target_volume(s, "integral"), rtol=1e-3)
    assert np.isclose(lobe_volume(t, w, "radial"), target_volume(s, "radial"), rtol=2e-3)


def test_fit_matches_volume_and_errors_finite():
    resp = LobeResponse(16, "box")
    for vol in ("integral", "radial"):
        ell, clipped = resp.fit_level(3.0, vol)
        assert clipped == ""
        # bisection of a 1/32-level bracket 40 times: volume matches to rounding; 1e-6 is the fit's own check
        assert np.isclose(resp.volume(ell, vol), target_volume(3.0, vol), rtol=1e-6)
    rows = analyse(16, "box", [1.0, 10.0], response=resp)
    assert len(rows) == 4 and all(np.isfinite(r["err_symdiff_pct"]) for r in rows)
    # symmetric-difference volume can never be smaller than the volume difference
    assert all(r["err_symdiff_pct"] >= r["err_voldiff_pct"] - 1e-9 for r in rows)


def test_mip_only_cannot_reach_s1_at_small_sizes():
    # the plain MIP chain's coarsest (1x1) lobe is narrower than the s=1 cosine lobe: fit is clipped
    resp = LobeResponse(16, "none")
    ell, clipped = resp.fit_level(1.0, "integral")
    assert clipped == "wide" and ell == resp.max_level


def test_s_texel_limit():
    # FWHM of cos^s equals the texel angle 2 atan(1/n) at s = s_texel_limit(n)
    n = 64
    s = s_texel_limit(n)
    assert np.isclose(np.arccos(0.5 ** (1 / s)), np.arctan(1 / n), rtol=1e-12)


def test_bad_options():
    with pytest.raises(IBLError, match=r"unknown volume definition 'area'; choose one"):
        target_volume(1.0, "area")
    with pytest.raises(IBLError, match=r"unknown lit\-texel position 'middle'; choose one"):
        LobeResponse(8, "box", position="middle")


@pytest.mark.parametrize("kernel", ["none", "sqrtcos"])
@pytest.mark.parametrize("position", ["centre", "corner"])
def test_fast_volume_equals_full_lobe_volume(kernel, position):
    # moments + peak candidates vs the full peak-normalised lobe (independent route, same samples)
    resp = LobeResponse(16, kernel, position=position)
    for ell in np.linspace(0, resp.max_level, 23):
        for vol in ("integral", "radial"):
            # both are sums over the same 1536 samples in different order: rounding ~1e-13
            assert np.isclose(resp.volume(ell, vol), resp.volume_exact(ell, vol), rtol=1e-10)
