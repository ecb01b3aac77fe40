"""Probe-like files made the way published light probes are (DWAB/PIZ/ZIP lat-long EXRs, float and half,
no ``envmap`` attribute, a small sun; RLE Radiance .hdr) and the radiance policy (ibl_ref.environment.radiance_policy).

The reference integral of every probe is the closed form of ibl_ref.environment.probe_files (sky a·2π + b·π, texel
solid angles Δλ·(sin φ1 − sin φ0)), not a sum computed by ibl_ref.environment.resample.
"""

from __future__ import annotations

import json

import numpy as np
import OpenEXR
import pytest

from ibl_ref.environment import exr_io, hdr_io, resample
from ibl_ref.cli import main
from ibl_ref.errors import RadianceError
from ibl_ref.environment.probe_files import sky_sun_latlong, write_probe_exr
from ibl_ref.environment.radiance_policy import AUTO_MAX_REMOVED_FRACTION, apply_policy, assess, check_radiance

H = 64
# Codec error of ∫L dω (decoded file vs the closed form), the tolerance of each file kind:
#  float lossless: float32 rounding, 2^-24 relative per value → 1e-6 is generous;
#  half lossless: rounding to 11 significant bits, ≤ 2^-11 = 4.9e-4 relative per value;
#  DWAB (lossy DCT on half values): measured 4.3e-3 … 2.1e-2 for H = 32 … 128 and suns 1e4 … 6e4 (the
#  quantisation of the sun's edge dominates); bound 3e-2.
CODEC_TOL = {("zip", "float"): 1e-6, ("piz", "float"): 1e-6, ("zip", "half"): 4.9e-4, ("piz", "half"): 4.9e-4,
             ("dwab", "float"): 3e-2, ("dwab", "half"): 3e-2}
# lat-long → cube conservation of the balanced kernel: per-texel imbalance ≤ 2e-3 (tests/test_resample.py)
RESAMPLE_TOL = 2e-3


def _closed_form_integral(img):
    """∫L dω of an H × 2H lat-long image with the closed-form texel solid angles (independent of ibl_ref)."""
    h, w = img.shape[:2]
    edges = np.pi / 2 - np.pi * np.arange(h + 1) / h
    om = 2 * np.pi / w * (np.sin(edges[:-1]) - np.sin(edges[1:]))
    return np.einsum("ijc,i->c", img, om)


@pytest.fixture(scope="module")
def probe():
    return sky_sun_latlong(H, sun=3e4)


# ---------------------------------------------------------------------------------------------------------------
# the policy on arrays
# ---------------------------------------------------------------------------------------------------------------
def test_removed_fraction_and_auto_threshold():
    # 1000 values of 1 and k values of -x, uniform weights: f = k·x / (1000 + k·x) by hand
    a = np.ones(1003)
    a[:3] = -1e-5
    rep = assess(a, "t")
    assert rep.n_negative == 3 and rep.negative_min == -1e-5
    np.testing.assert_allclose(rep.removed_fraction, 3e-5 / (1000 + 3e-5), rtol=1e-12)
    out, rep = apply_policy(a, "t")  # auto: tiny → clamped, reported, input untouched
    assert out.min() == 0 and a.min() < 0 and "clamped 3 negative" in rep.action[0]
    big = np.ones(1000)
    big[:2] = -0.1  # f = 0.2/1000.2 = 2e-4 > 1e-4
    with pytest.raises(RadianceError, match="--negative clamp"):
        apply_policy(big, "t")
    assert apply_policy(big, "t", negative="clamp")[0].min() == 0
    with pytest.raises(RadianceError, match="negative"):
        apply_policy(a, "t", negative="error")
    # solid-angle weights change f: the negative texel weighs 10x more
    w = np.ones(1003)
    w[:3] = 10.0
    np.testing.assert_allclose(assess(a, "t", weights=w).removed_fraction, 3e-4 / (1000 + 3e-4), rtol=1e-12)
    assert AUTO_MAX_REMOVED_FRACTION == 1e-4


def test_nonfinite_needs_explicit_zero_and_bad_dtypes():
    a = np.ones((4, 3))
    a[1, 2] = np.nan
    a[2, 0] = np.inf
    with pytest.raises(RadianceError, match=r"2 non-finite value\(s\) \(first: NaN at index \(1, 2\)\).*--nonfinite zero"):
        apply_policy(a, "t", negative="clamp")  # no negative policy lets NaN through
    out, rep = apply_policy(a, "t", nonfinite="zero")
    assert np.isfinite(out).all() and out[1, 2] == 0 and rep.n_nan == 1 and rep.n_posinf == 1
    for bad, word in ((np.ones(3, complex), "complex"), (np.ones(3, int), "integer"), (np.ones(3, bool), "integer")):
        with pytest.raises(RadianceError, match=word):
            check_radiance(bad, "t")


# ---------------------------------------------------------------------------------------------------------------
# probe-like EXR files
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("pixel_type", ["float", "half"])
@pytest.mark.parametrize("compression", ["dwab", "piz", "zip"])
def test_probe_exr_read_policy_and_integral(tmp_path, probe, compression, pixel_type):
    img, exact = probe
    np.testing.assert_allclose(_closed_form_integral(img), exact, rtol=1e-12)  # the fixture's own closed form
    p = write_probe_exr(tmp_path / f"probe_{compression}_{pixel_type}.exr", img, compression, pixel_type)
    hdr = OpenEXR.File(str(p)).header()
    assert "envmap" not in hdr  # made like a published probe
    env = exr_io.read_envmap(p)
    assert env.layout == "latlong"
    rep = env.radiance
    if compression == "dwab":
        # the lossy codec rings below zero next to the black strip: reported and clamped (auto)
        assert rep.n_negative > 0 and rep.negative_min < 0 and rep.removed_fraction < AUTO_MAX_REMOVED_FRACTION
        assert any("clamped" in a for a in rep.action) and env.data.min() >= 0
        with pytest.raises(RadianceError, match="--negative auto or clamp"):
            exr_io.read_envmap(p, negative="error")
    else:
        assert rep.clean and not rep.action
    decoded = env.data
    codec = np.abs(_closed_form_integral(decoded) / exact - 1).max()
    assert codec <= CODEC_TOL[(compression, pixel_type)]
    cube, rep2 = exr_io.load_cube(p, size=16, return_report=True)
    assert rep2.n_negative == rep.n_negative
    # ∫ of the cube vs the decoded (clamped) file: resampling conservation only
    assert np.abs(resample.integral_cube(cube) / _closed_form_integral(decoded) - 1).max() <= RESAMPLE_TOL


def test_half_sun_above_65504_is_inf_and_needs_nonfinite_zero(tmp_path):
    img, _ = sky_sun_latlong(32, sun=1e5)  # fp16 overflows: a tool that does not clamp writes Inf
    p = write_probe_exr(tmp_path / "inf.exr", img, "zip", "half")
    with pytest.raises(RadianceError, match="Inf.*--nonfinite zero"):
        exr_io.load_cube(p)
    assert main(["mediancut", str(p), "--lights", "6", "--out", str(tmp_path / "l.json")]) == 1
    cube, rep = exr_io.load_cube(p, nonfinite="zero", return_report=True)
    assert rep.n_posinf > 0 and np.isfinite(cube).all()


def test_energetic_negatives_are_refused_by_auto(tmp_path):
    img = np.ones((16, 32, 3), np.float32)
    img[10:12, 3:9] = -0.5  # a signed (difference) image, not codec noise
    p = write_probe_exr(tmp_path / "signed.exr", img, "zip")
    with pytest.raises(RadianceError, match="more than the 0.0001.*--negative clamp"):
        exr_io.load_cube(p)
    assert exr_io.load_cube(p, negative="clamp").min() >= 0


def test_hdr_probe_rle(tmp_path, probe):
    img, exact = probe
    p = tmp_path / "probe.hdr"
    hdr_io.write_hdr(p, img, rle=True)
    assert p.stat().st_size < img.shape[0] * img.shape[1] * 4  # RLE actually compressed the sky rows
    cube, rep = exr_io.load_cube(p, size=16, return_report=True)
    assert rep.clean
    # RGBE stores 8-bit mantissas: ≤ 2^-8 relative per value (hdr_io module docstring); plus resampling
    assert np.abs(resample.integral_cube(cube) / exact - 1).max() <= 2**-8 + RESAMPLE_TOL


# ---------------------------------------------------------------------------------------------------------------
# every command on the raw files, no manual step
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def dwab_file(tmp_path_factory, probe):
    return write_probe_exr(tmp_path_factory.mktemp("probe") / "sky.exr", probe[0], "dwab", "float")


def test_info_reports_layout_source_and_negatives(dwab_file, capsys):
    assert main(["info", str(dwab_file)]) == 0
    out = capsys.readouterr().out
    assert "no envmap attribute: inferred from the aspect ratio 128 x 64" in out
    assert "negative value(s)" in out and "would clamp" in out and "DWAB" in out
    assert main(["info", str(dwab_file), "--negative", "error"]) == 0  # info never refuses
    assert "would refuse the file" in capsys.readouterr().out
    half = write_probe_exr(dwab_file.with_name("half.exr"), sky_sun_latlong(16)[0], "piz", "half")
    assert main(["info", str(half)]) == 0
    out = capsys.readouterr().out
    assert "pixel type: half" in out and "PIZ" in out and "use the radiance unchanged" in out


def test_info_never_refuses_readable_files(tmp_path, capsys):
    r = np.ones((8, 8), np.float32)  # square: no layout
    r[0, 0] = np.nan
    a = np.ones_like(r)
    a[1, 1] = np.inf  # Inf in alpha
    p = tmp_path / "odd.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"R": r, "G": np.ones_like(r), "B": -np.ones_like(r), "A": a}).write(str(p))
    assert main(["info", str(p)]) == 0
    out = capsys.readouterr().out
    assert "layout:     unknown" in out and "cannot infer" in out
    rows = {ln.split()[0]: ln.split() for ln in out.splitlines() if ln[:2] in ("R ", "G ", "B ", "A ")}
    assert rows["R"][-3:] == ["1", "0", "0"] and rows["A"][-3:] == ["0", "1", "0"] and rows["B"][-1] == "64"
    assert "would refuse the file" in out
    q = tmp_path / "depth.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"Z": np.ones((8, 16), np.float32)}).write(str(q))
    assert main(["info", str(q)]) == 0
    assert "no R,G,B or Y channel" in capsys.readouterr().out


@pytest.mark.parametrize("cmd", [
    ["convert", "{f}", "{o}/c.exr", "--layout", "cube", "--size", "8"],
    ["convolve", "{f}", "{o}/v.exr", "-s", "4", "--input-size", "8"],
    ["irradiance", "{f}", "{o}/e.exr", "--input-size", "8"],
    ["mediancut", "{f}", "--lights", "6", "--size", "12", "--out", "{o}/m.json"],
    ["pem", "{f}", "--lights", "6", "--size", "16", "--out", "{o}/pem"],
    ["pyramid", "{f}", "{o}/p.exr", "--size", "8"],
])
def test_commands_run_on_dwab_probe(tmp_path, dwab_file, cmd, capsys):
    argv = [a.format(f=dwab_file, o=tmp_path) for a in cmd]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "negative value(s)" in err and "clamped" in err  # the report reaches stderr
    side = {"convolve": tmp_path / "v.json", "mediancut": tmp_path / "m.json", "pem": tmp_path / "pem/pems.json"}
    if cmd[0] in side:
        rad = json.loads(side[cmd[0]].read_text())["radiance"]
        assert rad["n_negative"] > 0 and rad["removed_fraction"] < 1e-4 and rad["action"]
    assert main(argv + ["--negative", "error"]) == 1
    assert "--negative auto or clamp" in capsys.readouterr().err


def test_render_and_km00_with_env_probe(tmp_path, dwab_file, capsys):
    out = tmp_path / "r.exr"
    assert main(["render", "--env", str(dwab_file), "--env-size", "16", "--lights", "6", "--size", "24",
                 "--out", str(out), "--vsm-res", "32"]) == 0
    assert json.loads(out.with_suffix(".json").read_text())["radiance"]["n_negative"] > 0
    hdr = tmp_path / "probe.hdr"
    hdr_io.write_hdr(hdr, exr_io.read_image(dwab_file)[0])
    assert main(["km00-render", "--env", str(hdr), "--env-size", "8", "--size", "16", "--method", "single",
                 "--n-theta", "4", "--out", str(tmp_path / "k.exr"), "--quiet"]) == 0


# ---------------------------------------------------------------------------------------------------------------
# big-probe machinery of ibl_ref.environment.resample on small sizes
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("h", [16, 32])
def test_symmetric_kernel_equals_the_whole_grid_kernel(h):
    """The 8-fold fundamental-domain kernel is the kernel built over every texel (symmetric=False)."""
    rng = np.random.default_rng(h)
    n = h // 2
    ks = resample.supersample_factor(np.pi / h, np.pi / (2 * n))
    a = resample.ConservativeKernel(h, n, ks, iters=100)
    b = resample.ConservativeKernel(h, n, ks, iters=100, symmetric=False)
    ll, cube = rng.random((h, 2 * h, 3)), rng.random((6, n, n, 3))
    # same Sinkhorn steps on the same matrix up to the order of floating-point sums
    np.testing.assert_allclose(a.to_cube(ll), b.to_cube(ll), rtol=1e-9)
    np.testing.assert_allclose(a.to_latlong(cube), b.to_latlong(cube), rtol=1e-9)
    assert a.k0.nnz * 7 < b.k0.nnz  # 1/8 of the columns (plus seams)


def test_block_reduction_and_prereduced_resampling_conserve_the_closed_form():
    img, exact = sky_sun_latlong(128, sun=5e4, sun_radius_deg=0.8)
    red = resample.latlong_block_reduce(img, 4)
    # exact block averages: ∫ kept to rounding (closed form of the source)
    np.testing.assert_allclose(_closed_form_integral(red), exact, rtol=1e-12)
    np.testing.assert_array_equal(resample.latlong_block_reduce(np.ones((8, 16, 1)), 2), np.ones((4, 8, 1)))
    assert resample.prereduce_factor(128, 8) == 8 and resample.prereduce_factor(96, 20) == 2
    assert resample.prereduce_factor(128, 64) == 1
    cube = resample.latlong_to_cube(img.astype(np.float32), 8)  # 128 rows → 16 rows → 8² faces
    assert np.abs(resample.integral_cube(cube) / exact - 1).max() <= RESAMPLE_TOL
    # a one-texel sun keeps its energy through reduction + kernel (per-texel imbalance bound)
    one = np.zeros((128, 256))
    one[3, 77] = 1.0
    e = resample.integral_cube(resample.latlong_to_cube(one, 8)) / _closed_form_integral(one[..., None])[0]
    assert abs(e - 1) <= RESAMPLE_TOL


@pytest.mark.parametrize("n", [1, 2, 3, 8])
def test_ring_rules_reproduce_the_padding_tables(n):
    """resample._padded_taps (size-independent rules read at n = 5) equals sampling.padding_tables(n, 1)."""
    from ibl_ref.environment.sampling import padding_tables

    m = n + 2
    f, y, x = np.meshgrid(np.arange(6), np.arange(m), np.arange(m), indexing="ij")
    src, w = resample._padded_taps(f, y, x, n)
    src0, w0 = padding_tables(n, 1)
    size = 6 * n * n
    # compare the weight each padded cell gives every texel (tap order may differ)
    dense = np.zeros((6 * m * m, size))
    dense0 = np.zeros_like(dense)
    rows = np.repeat(np.arange(6 * m * m), 3)
    np.add.at(dense, (rows, src.reshape(-1)), w.reshape(-1))
    np.add.at(dense0, (rows, src0.reshape(-1)), w0.reshape(-1))
    np.testing.assert_allclose(dense, dense0, atol=1e-15)
