"""Tests of ibl_ref.rendering.tonemap (display only)."""

import numpy as np
import pytest

from ibl_ref.rendering import tonemap as tm
from ibl_ref.errors import IBLError


def test_srgb_known_values():
    # IEC 61966-2-1 transfer: endpoints and the linear segment, value at 0.5 computed from the formula by hand
    np.testing.assert_allclose(tm.srgb_encode([0.0, 1.0, 0.001]), [0.0, 1.0, 0.01292])
    assert tm.srgb_encode(0.5) == pytest.approx(1.055 * 0.5 ** (1 / 2.4) - 0.055)


def test_monotone_and_finite_up_to_1e6():
    x = np.concatenate([[0.0], np.logspace(-6, 6, 2000)])
    for op in ("reinhard", "clip"):
        y = tm.exposure_srgb(x, stops=0.0, operator=op)
        assert np.all(np.isfinite(y)) and y.min() >= 0 and y.max() <= 1
        assert np.all(np.diff(y) >= 0)
    y = tm.exposure_srgb(x[x <= 1e3], operator="reinhard")
    assert np.all(np.diff(y) > 0)  # strictly increasing while 1/(1+x) is resolvable in float64
    assert tm.exposure_srgb(np.array([1e6]))[0] < 1.0  # Reinhard never reaches 1


def test_auto_exposure_maps_percentile_to_key():
    img = np.full((4, 4, 3), 5.0)
    stops = tm.auto_exposure(img, percentile=90, key=0.8)
    assert 5.0 * 2 ** stops == pytest.approx(0.8, rel=1e-15)
    assert tm.auto_exposure(np.zeros((2, 2, 3))) == 0.0
    # channel-mean luminances 1 … 100 (channels y/2, y, 3y/2), plus black pixels (ignored) and masked-out bright
    # ones: the 90th percentile with linear interpolation between order statistics is 1 + 0.9·99 = 90.1
    y = np.arange(1.0, 101.0)
    img = np.zeros((11, 11, 3))
    flat = img.reshape(-1, 3)
    flat[:100] = y[:, None] * [0.5, 1.0, 1.5]
    flat[100:110] = 1e6
    mask = np.ones((11, 11), bool)
    mask.reshape(-1)[100:110] = False
    stops = tm.auto_exposure(img, mask=mask, percentile=90, key=0.8)
    assert 2.0 ** stops == pytest.approx(0.8 / 90.1, rel=1e-14)


def test_save_png_roundtrip(tmp_path):
    import matplotlib.image as mpimg

    # values chosen so the display value is known in closed form: Reinhard x/(1+x) gives 0, 1/2, 3/4, 1e5/(1+1e5),
    # then the sRGB curve (IEC 61966-2-1) written out here, independent of tonemap.srgb_encode
    x = np.array([0.0, 1.0, 3.0, 1e5])
    img = np.stack([np.tile(x, (2, 1))] * 3, axis=-1)  # (2, 4, 3)
    p = tm.save_png(tmp_path / "x.png", img, stops=0.0)
    back = mpimg.imread(p)[..., :3]
    v = x / (1 + x)
    want = np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)
    assert back.shape == (2, 4, 3)
    # 8-bit PNG: within half a code value
    np.testing.assert_allclose(back, np.broadcast_to(want[None, :, None], back.shape), atol=0.5 / 255 + 1e-6)
    assert sorted(q.name for q in tmp_path.iterdir()) == ["x.png"]  # atomic: no temporary file left


def test_bad_inputs():
    with pytest.raises(IBLError, match=r"tone mapping: image contains NaN or"):
        tm.exposure_srgb(np.array([np.nan]))
    with pytest.raises(IBLError, match=r"operator must be 'reinhard' or 'clip'"):
        tm.exposure_srgb(np.array([1.0]), operator="filmic")
