"""Tests of ibl_ref.groundtruth.convolve (method dispatcher) and the ``convolve`` / ``irradiance`` CLI."""

import json

import numpy as np
import pytest

from ibl_ref.groundtruth.convolve import ConvolutionResult, convolve
from ibl_ref.errors import IBLError, LayoutError, RadianceError

from ibl_ref.groundtruth import phong_convolution as pc


def _sun_env(n):
    from ibl_ref.synthetic.synthetic_envs import SUN_NEAR_CORNER, make_env

    return make_env("sky_sun", n, sun_direction=SUN_NEAR_CORNER, sun_radiance=1e5)


@pytest.fixture
def no_tiny_shortcut(monkeypatch):
    """Route small test maps like large ones (auto would otherwise use exact on tiny maps)."""
    import ibl_ref.groundtruth.convolve as cv

    monkeypatch.setattr(cv, "AUTO_EXACT_PAIRS", 0)
    orig = cv._unit  # exact only as the bound-driven fallback (1e6 units per pair)
    monkeypatch.setattr(cv, "_unit", lambda name, impl: 1e6 if name.startswith("EXACT_UNITS") else orig(name, impl))


def test_auto_tiny_map_uses_exact():
    res = convolve(_sun_env(8), [4.0, 64.0])
    assert set(res.method_used.values()) == {"exact"}


@pytest.mark.parametrize("n", [8, 16])
def test_auto_meets_rtol_with_sun(n, no_tiny_shortcut):
    cube = _sun_env(n)
    S = [1.0, 4.0, 16.0, 64.0, 256.0, 1024.0, 4096.0]
    res = convolve(cube, S, rtol=1e-3)
    ref = pc.convolve_exact_many(cube, S)
    assert isinstance(res, ConvolutionResult)
    for k, s in enumerate(S):
        err = (np.abs(res.maps[s] - ref[k]) / ref[k]).max(axis=-1)
        assert err.max() <= 1e-3, (s, res.method_used[s], err.max())
        assert np.all(err <= res.error_bound[s] + 1e-12), (s, res.method_used[s])  # reported bound holds
        assert res.error_bound[s].max() <= 1e-3
        assert res.method_used[s] in ("exact", "sh", "sparse")
    assert res.method_used[16.0] == "sh"  # the fast route is really exercised


def test_auto_uses_fast_methods_and_mirror():
    cube = _sun_env(32)  # realistic cost model (no monkeypatching): SH wins for s = 16 at 32²
    res = convolve(cube, [16.0, np.inf], rtol=1e-3)
    assert res.method_used[16.0] == "sh"
    assert res.method_used[np.inf] == "exact"
    np.testing.assert_array_equal(res.maps[np.inf], cube)  # mirror at the input size = the input


@pytest.mark.parametrize("method", ["exact", "sh", "sparse"])
def test_forced_methods_bound_holds(method):
    cube = _sun_env(8)
    S = [2.0, 32.0]
    res = convolve(cube, S, method=method, rtol=1e-3)
    ref = pc.convolve_exact_many(cube, S)
    for k, s in enumerate(S):
        assert res.method_used[s] == method
        err = (np.abs(res.maps[s] - ref[k]) / ref[k]).max(axis=-1)
        assert np.all(err <= res.error_bound[s] + 1e-12)


def test_single_channel_and_out_size(no_tiny_shortcut):
    cube = _sun_env(8)[..., 0]
    res = convolve(cube, 8.0, out_size=4)
    assert res.maps[8.0].shape == (6, 4, 4)
    ref = pc.convolve_exact(cube, 8.0, out_size=4)
    err = np.abs(res.maps[8.0] - ref) / ref
    assert np.all(err <= res.error_bound[8.0] + 1e-12)


def test_errors():
    cube = np.ones((6, 4, 4, 3))
    with pytest.raises(IBLError, match="method"):
        convolve(cube, 2.0, method="fft")
    with pytest.raises(IBLError, match=r"Phong exponent s must be >="):
        convolve(cube, 0.5)
    with pytest.raises(IBLError, match=r"Phong exponent s must be >="):
        convolve(cube, float("nan"))
    with pytest.raises(IBLError, match=r"no Phong exponents given"):
        convolve(cube, [])
    with pytest.raises(IBLError, match=r"rtol: a relative tolerance must be a number in \(0, 1"):
        convolve(cube, 2.0, rtol=0)
    # below what float64 sums of the lab's sizes can verify (it had run for minutes): one line, before any work
    for tiny in (1e-300, 1e-9):
        with pytest.raises(IBLError, match=r"rtol: .* is below 1.5e-08 \(2\^-26\)"):
            convolve(cube, 2.0, rtol=tiny)
    with pytest.raises(IBLError, match=r"method 'sh' cannot represent the mirror"):
        convolve(cube, np.inf, method="sh")
    with pytest.raises(LayoutError, match=r"environment cube map: expected an array"):
        convolve(np.ones((6, 4, 5, 3)), 2.0)
    bad = cube.copy()
    bad[1, 1, 1, 1] = np.inf
    with pytest.raises(RadianceError, match=r"environment cube map: 1 non\-finite value\(s"):
        convolve(bad, 2.0)


def test_cli_convolve_and_irradiance(tmp_path):
    pytest.importorskip("OpenEXR")
    from ibl_ref.environment import exr_io
    from ibl_ref.cli import main
    from ibl_ref.cli.cmd_convolve import exponent_path

    cube = _sun_env(8)
    src = tmp_path / "env.exr"
    exr_io.write_envmap(src, cube, layout="cube")
    out = tmp_path / "conv.exr"
    assert main(["convolve", str(src), str(out), "--exponent", "4", "-s", "2.5", "--rtol", "1e-3"]) == 0
    assert exponent_path(out, 2.5).name == "conv_s2.5.exr"
    got = exr_io.load_cube(tmp_path / "conv_s4.exr")
    ref = pc.convolve_exact(exr_io.load_cube(src), 4.0)
    # float32 file storage (≈ 6e-8) + the 1e-3 bound
    np.testing.assert_allclose(got, ref, rtol=1.1e-3)
    side = json.loads((tmp_path / "conv.json").read_text())
    assert {e["s"] for e in side["exponents"]} == {4.0, 2.5}
    assert all(e["rel_bound_max"] <= 1e-3 for e in side["exponents"])
    # bad exponent → clean error exit code
    assert main(["convolve", str(src), str(out), "--exponent", "0.5"]) == 1
    irr = tmp_path / "irr.exr"
    assert main(["irradiance", str(src), str(irr)]) == 0
    assert exr_io.load_cube(irr).shape == (6, 8, 8, 3)


def test_channel_extremes_are_numpys_bit_for_bit():
    """channel_max/channel_min (the routes' fast reductions over the last axis) give NumPy's max/min exactly,
    NaN and ±inf included, in float64 and float32, for C = 1…4."""
    from ibl_ref.groundtruth.convolution_args import channel_max, channel_min

    rng = np.random.default_rng(2)
    for C in (1, 2, 3, 4):
        for dt in (np.float64, np.float32):
            a = rng.normal(size=(7, 5, C)).astype(dt)
            a[0, 0, -1] = np.nan
            a[1, 1, 0] = np.inf
            a[2, 2, -1] = -np.inf
            for fast, ref in ((channel_max, np.max), (channel_min, np.min)):
                got = fast(a)
                assert got.dtype == a.dtype
                np.testing.assert_array_equal(got, ref(a, axis=-1))


def test_sidecar_p99_is_numpys_linear_quantile():
    """The summary's 99th percentile (by np.partition, which does not import numpy.ma) is np.quantile's value."""
    from ibl_ref.groundtruth.convolve import _quantile_linear

    rng = np.random.default_rng(4)
    for n in (1, 2, 3, 100, 101, 5000):
        x = rng.lognormal(size=n) * 1e-4
        assert _quantile_linear(x, 0.99) == float(np.quantile(x, 0.99))
