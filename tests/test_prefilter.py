"""The prefilter stage (ibl_ref.prefilter): the interface every registered method satisfies, the registry and
dispatcher, region sets (PEMs) of any Phong method, and the adapters against independent routes.

Per registered method (parametrised over ``PREFILTER_METHODS``, so a newly registered one is checked too): the
declared members, shapes and broadcasting, one-line errors for bad parameters and bad radiance, a constant
environment, and Σ_i PEM_i = the prefilter of the whole map (Knuth et al. 2014, Sec. 3.1: the method is linear in
the radiance).  Against other routes: the ``pyramid`` and ``exact-lobe`` prefilters are the look-ups the paper's
code computes (bit for bit), the generic per-partial-map region set of the pyramid equals the paper's stacked PEMs,
Kán's normalised maps equal the lab's exact lobe average at texel centres, and the Kautz & McCool profile
convolution agrees with Kán's dense sum (same quadrature, different code and lobe representation).
"""

import inspect

import numpy as np
import pytest

from ibl_ref.conventions import phong_exponent
from ibl_ref.environment.envmap import texel_directions
from ibl_ref.errors import IBLError, RadianceError
from ibl_ref.knuth2014.median_cut import median_cut
from ibl_ref.prefilter import (LOBES, PREFILTER_METHODS, Prefilter, RegionPrefilters, build_prefilter,
                               build_region_prefilters, prefilter_methods)
from ibl_ref.prefilter.cmft_peer import CmftUnavailable
from ibl_ref.prefilter.cmgen_peer import HALF_ROUNDOFF, CmgenUnavailable
from ibl_ref.prefilter.registry import get_method, region_params
from ibl_ref.synthetic.synthetic_envs import make_env

N = 8
METHODS = sorted(PREFILTER_METHODS)
#: accepted look-up parameters per lobe family, and rejected ones
GOOD = {"phong": [1.0, 2.5, 40.0, np.inf], "ggx": [0.1, 0.5, 1.0], "cosine": [1.0, 1.0]}
BAD = {"phong": [np.nan, 0.5, -1.0], "ggx": [np.nan, 0.0, 1.5], "cosine": [np.nan, 2.0, 0.5]}
#: |lookup − c| / c for a constant map c: 0 up to rounding where the method normalises by its discrete lobe
#: weight (pyramid filters normalised per texel, the chain's lobe averages); Kán's literal sum and Kautz & McCool's
#: unnormalised convolution divide by the continuous lobe integral 2π/(s+1), so a constant keeps the texel-centre
#: quadrature error of the lobe weight (Kán's docstring: 2.6e-3 at n = 16 on 16² faces; on 8² faces 1.03e-2 at
#: s = 16, measured; the look-up blends two such levels, so the bound is the largest level error)
CONSTANT_RTOL = {"pyramid": 1e-12, "exact-lobe": 1e-12, "kan2015": 1.2e-2, "km00-lobes": 1.2e-2,
                 # cmft normalises by its own discrete lobe weight; its files hold float32 (rounding 2^-24 per value,
                 # the log-s blend of two levels keeps it below a few of those)
                 "cmft": 1e-6,
                 # cmgen's levels are normalised averages stored as half floats (rounding 2^-11) after float32 sums
                 # (< 1e-6); a blend of two levels stays within that (tests/test_cmgen_peer.py)
                 "cmgen": HALF_ROUNDOFF + 1e-6}
#: the methods that run an outside program: skipped with the reason where it is not available
PEER_UNAVAILABLE = (CmftUnavailable, CmgenUnavailable)


def _build(cube, method, **params):
    """build_prefilter, skipping (with the reason) a method whose outside program is not available."""
    try:
        return build_prefilter(cube, method, **params)
    except PEER_UNAVAILABLE as exc:
        pytest.skip(str(exc))


@pytest.fixture(scope="module")
def env():
    return make_env("sky_sun", n=N)


@pytest.fixture(scope="module")
def built(env):
    out = {}
    for m in METHODS:
        try:
            out[m] = build_prefilter(env, m)
        except PEER_UNAVAILABLE as exc:
            out[m] = exc
    return out


def _get(built, method):
    if isinstance(built[method], PEER_UNAVAILABLE):
        pytest.skip(str(built[method]))
    return built[method]


def _dirs(shape, seed=0):
    return np.random.default_rng(seed).normal(size=shape + (3,))


def test_registry_lists_every_method_with_lobe_paper_and_parameters():
    rows = prefilter_methods()
    assert [r.name for r in rows] == list(PREFILTER_METHODS)
    assert {"pyramid", "exact-lobe", "km00-lobes", "kan2015"} <= set(PREFILTER_METHODS)
    for r in rows:
        assert r.lobe in LOBES and r.paper and r.summary, r
        # the recipe: keyword parameters with defaults, so Method(cube) builds the method's default
        assert all(v is not inspect.Parameter.empty for v in r.params.values()), r
    assert {r.name for r in prefilter_methods("phong")} >= {"pyramid", "exact-lobe", "km00-lobes", "kan2015"}
    assert all(r.lobe == "ggx" for r in prefilter_methods("ggx"))
    with pytest.raises(IBLError, match="unknown prefilter method 'nope'; choose one of pyramid"):
        get_method("nope")
    with pytest.raises(IBLError, match="unknown prefilter"):
        build_prefilter(np.ones((6, 4, 4, 3)), "nope")
    assert "calibration" in region_params("pyramid") and "factor" in region_params("exact-lobe")


@pytest.mark.parametrize("method", METHODS)
def test_interface_members_shapes_and_broadcasting(built, method):
    pf = _get(built, method)
    assert isinstance(pf, Prefilter)
    assert pf.lobe in LOBES and pf.lobe == PREFILTER_METHODS[method].lobe
    assert isinstance(pf.nbytes, int) and pf.nbytes > 0
    assert pf.error_bound is None or (np.isfinite(pf.error_bound) and pf.error_bound >= 0)
    good = GOOD[pf.lobe]
    d = _dirs((2, 5))
    one = pf.lookup(d, good[1])
    assert one.shape == (2, 5, 3) and np.all(np.isfinite(one)) and np.all(one >= 0)
    # a parameter per direction, broadcast against the directions' leading axes
    per = np.resize(np.array(good), (2, 5))
    both = pf.lookup(d, per)
    assert both.shape == (2, 5, 3)
    for idx in np.ndindex(2, 5):  # the same as one look-up per direction
        np.testing.assert_allclose(both[idx], pf.lookup(d[idx][None], per[idx])[0], rtol=1e-12, atol=1e-300)
    # directions need not be normalised
    np.testing.assert_allclose(pf.lookup(3.0 * d, good[1]), one, rtol=1e-12)


@pytest.mark.parametrize("method", METHODS)
def test_bad_parameters_and_bad_input_are_one_line_errors(env, built, method):
    pf = _get(built, method)
    for bad in BAD[pf.lobe]:
        with pytest.raises(IBLError) as exc:
            pf.lookup(_dirs((3,)), bad)
        assert "\n" not in str(exc.value)
    with pytest.raises(IBLError):
        pf.lookup(np.ones((4, 2)), GOOD[pf.lobe][0])  # not (..., 3)
    for value in (np.nan, np.inf, -1.0):
        bad_env = env.copy()
        bad_env[2, 3, 4, 1] = value
        with pytest.raises(RadianceError):
            build_prefilter(bad_env, method)
    with pytest.raises(IBLError):
        build_prefilter(np.ones((6, 8, 4, 3)), method)  # not square faces


@pytest.mark.parametrize("method", METHODS)
def test_constant_environment(method):
    c = 2.5
    pf = _build(np.full((6, N, N, 3), c), method)
    d = np.concatenate([_dirs((60,), 3), np.asarray(texel_directions(N)).reshape(-1, 3)])
    for p in GOOD[pf.lobe]:
        np.testing.assert_allclose(pf.lookup(d, p), c, rtol=CONSTANT_RTOL.get(method, 1e-12))


@pytest.mark.parametrize("method", [m for m in METHODS if PREFILTER_METHODS[m].lobe == "phong"])
def test_region_set_sums_to_the_prefilter_of_the_whole_map(env, built, method):
    # Sec. 3.1: Σ_i PEM_i = the prefiltered full map (every method is linear in the radiance); the region sets
    # store float32 (pyramid, exact-lobe PEMs: the paper stores 16-bit floats) or float64
    pf = _get(built, method)
    lights = median_cut(env, 6)
    pems = build_region_prefilters(env, lights, method)
    assert isinstance(pems, RegionPrefilters) and pems.lobe == "phong" and pems.lights is lights
    assert pems.nbytes > 0 and (pems.error_bound is None or pems.error_bound >= 0)
    d = _dirs((40,), 5)
    for g in (0.0, 0.6, 0.95, 1.0):
        each = pems.lookup_all(d, g)
        assert each.shape == (6, 40, 3)
        np.testing.assert_allclose(each.sum(axis=0), pf.lookup(d, phong_exponent(g)), rtol=2e-6)
    # per-direction glossiness, as Eq. 5 looks up per pixel
    g = np.linspace(0.0, 1.0, 40)
    np.testing.assert_allclose(pems.lookup_all(d, g).sum(axis=0), pf.lookup(d, phong_exponent(g)), rtol=2e-6)
    # the same set with the regions cut here
    again = build_region_prefilters(env, method=method, n_lights=6)
    np.testing.assert_array_equal(again.lights.labels, lights.labels)


def test_generic_region_set_of_the_pyramid_is_the_papers_pems(env):
    # two routes to the paper's PEMs: the method on each partial map (RegionSet.build) and all regions stacked in
    # one pyramid (build_pems); the pyramid filters channels independently, so they agree to float64 rounding
    from ibl_ref.knuth2014.pem import build_pems
    from ibl_ref.prefilter.knuth2014_pyramid import Knuth2014Pyramid
    from ibl_ref.prefilter.regions import RegionSet

    lights = median_cut(env, 12)
    generic = RegionSet.build(Knuth2014Pyramid, env, lights, dtype=np.float64)
    paper = build_pems(env, lights, dtype=np.float64)
    d = _dirs((50,), 7)
    for g in (0.0, 0.5, 0.9, 1.0):
        np.testing.assert_allclose(generic.lookup_all(d, g), paper.lookup_all(d, g), rtol=1e-12, atol=1e-300)
    assert generic.nbytes == paper.nbytes
    for k in (0.0, 1.5, 3.0):
        np.testing.assert_allclose(generic.lookup_all_at_level(d, k), paper.lookup_all_at_level(d, k), rtol=1e-12)
    assert generic.n_levels == paper.n_levels


def test_pyramid_and_chain_prefilters_are_the_papers_lookups(env):
    # bit for bit: the registry's look-up by s(g) is the paper's g look-up (Eq. 3 inside, the same level ℓ(s))
    from ibl_ref.knuth2014.gloss_lookup import lookup
    from ibl_ref.knuth2014.lobe_chain import build_lobe_chain
    from ibl_ref.knuth2014.pyramid import build_pyramid

    d = _dirs((30,), 8)
    g = np.linspace(0.0, 1.0, 30)
    np.testing.assert_array_equal(build_prefilter(env, "pyramid", kernel="box").lookup(d, phong_exponent(g)),
                                  lookup(build_pyramid(env, kernel="box"), d, g))
    pyr, cal = build_lobe_chain(env, factor=2.0)
    np.testing.assert_array_equal(build_prefilter(env, "exact-lobe", factor=2.0).lookup(d, phong_exponent(g)),
                                  lookup(pyr, d, g, calibration=cal))


def test_kan2015_normalised_maps_are_the_exact_lobe_average_at_texel_centres(env):
    # at a stored exponent the look-up is level k exactly; at a texel centre the bilinear weight is 1 there: the
    # value is Kán's normalised map, i.e. the lab's exact lobe average (an independent gather) to rounding
    from ibl_ref.groundtruth.phong_convolution import lobe_average

    pf = build_prefilter(env, "kan2015", quadrature="normalized", exponents=[1.0, 3.0, 12.0])
    assert pf.exponents == (12.0, 3.0, 1.0)
    d = np.asarray(texel_directions(N)).reshape(-1, 3)
    for s in pf.exponents:
        np.testing.assert_allclose(pf.lookup(d, s), lobe_average(env, d, s), rtol=1e-10)
    np.testing.assert_allclose(pf.lookup(d, np.inf), env.reshape(-1, 3), rtol=1e-12)  # the mirror: the map


def test_km00_profile_maps_agree_with_kan2015_dense_sum():
    # Kautz & McCool's convolution of the tabulated profile max(cos γ, 0)^s (KD-tree gather, no supersampling, no
    # tail cut) and Kán's literal sum of the analytic lobe are the same texel-centre quadrature of ∫ L cos^s dω;
    # they differ by the profile's tabulation on 256 nodes (its integral is within 3.3e-4 of 2π/(s+1)) → 1e-3 on a
    # smooth map
    c = make_env("gradient", n=16)
    km = build_prefilter(c, "km00-lobes", supersample=1, tail_rtol=0.0, exponents=[1, 4, 16, 64])
    ka = build_prefilter(c, "kan2015", exponents=[1, 4, 16, 64])
    d = np.asarray(texel_directions(16)).reshape(-1, 3)
    for s in (1.0, 4.0, 16.0, 64.0):
        np.testing.assert_allclose(km.lookup(d, s), ka.lookup(d, s), rtol=1e-3)


def test_exponent_stack_blends_in_log_s_between_stored_exponents(env):
    # between two stored exponents the look-up is the linear blend in log s of the two maps (the chain's table)
    pf = build_prefilter(env, "kan2015", exponents=[2.0, 8.0])
    d = np.asarray(texel_directions(N)).reshape(-1, 3)
    a, b = pf.lookup(d, 8.0), pf.lookup(d, 2.0)
    t = (np.log(4.0) - np.log(2.0)) / (np.log(8.0) - np.log(2.0))  # s = 4: halfway in log s
    np.testing.assert_allclose(pf.lookup(d, 4.0), b + (a - b) * (1 - t), rtol=1e-12)
    np.testing.assert_array_equal(pf.lookup(d, 1.0), b)  # below the smallest stored exponent: clamped to it


def test_a_new_method_is_one_class_and_one_registry_entry(monkeypatch, env):
    # the package docstring's recipe: a class with lobe, paper, __init__(cube, **params), lookup, nbytes,
    # error_bound — registered by one entry — is built by the dispatcher, listed, offered by `render --prefilter`,
    # and gets PEMs (the method on each partial map) that Eq. 5 can use
    from ibl_ref.prefilter.interface import check_lobe_param
    from ibl_ref.rendering.render import eq5_lookups

    class MirrorOnly:
        """The environment itself for every exponent (a test method)."""

        lobe = "phong"
        paper = "none (test)"

        def __init__(self, cube, *, scale: float = 1.0):
            from ibl_ref.environment.sampling import CubeSampler

            self.cube = np.asarray(cube, dtype=np.float64) * scale
            self._sampler = CubeSampler(self.cube)

        def lookup(self, directions, param):
            check_lobe_param(self.lobe, param)
            return self._sampler.bilinear(np.asarray(directions, dtype=np.float64).reshape(-1, 3)).reshape(
                np.shape(directions)[:-1] + (self.cube.shape[-1],))

        @property
        def nbytes(self):
            return int(self.cube.nbytes)

        @property
        def error_bound(self):
            return None

    monkeypatch.setitem(PREFILTER_METHODS, "mirror-only", MirrorOnly)
    assert "mirror-only" in [m.name for m in prefilter_methods("phong")]
    assert isinstance(build_prefilter(env, "mirror-only", scale=2.0), Prefilter)
    lights = median_cut(env, 6)
    pems = build_region_prefilters(env, lights, "mirror-only")
    n = _dirs((20,), 9)
    pem_n, pem_r = eq5_lookups(pems, n, n, 0.5, 1.0, 1.0)
    np.testing.assert_allclose(pem_n.sum(axis=0), MirrorOnly(env).lookup(n, 1.0), rtol=1e-12)
    assert pems.nbytes == 6 * env.nbytes and pems.error_bound is None
    with pytest.raises(IBLError, match="not level chains"):
        pems.lookup_all_at_level(n, 1.0)
    from ibl_ref.cli import build_parser

    assert build_parser().parse_args(["render", "--out", "x.exr", "--prefilter", "mirror-only"]).prefilter == "mirror-only"


def test_region_sets_need_phong_methods(monkeypatch, env):
    class GGXThing:
        """A GGX test method."""

        lobe = "ggx"
        paper = "none (test)"

    monkeypatch.setitem(PREFILTER_METHODS, "ggx-thing", GGXThing)
    with pytest.raises(IBLError, match="need a Phong prefilter"):
        build_region_prefilters(env, method="ggx-thing", n_lights=6)
    assert "ggx-thing" not in [m.name for m in prefilter_methods("phong")]
    with pytest.raises(IBLError, match="lights"):
        build_region_prefilters(env, method="pyramid")  # neither lights nor n_lights


@pytest.mark.parametrize("method", ["km00-lobes", "kan2015"])
def test_render_cli_with_every_phong_prefilter(tmp_path, method):
    # `ibl-ref render --prefilter` takes every registered Phong method; a constant map 1 with VIS ≡ 1 gives
    # kd + ks on every covered pixel up to the method's constant-map error (CONSTANT_RTOL; 16² faces: ≤ 7.2e-3)
    from ibl_ref.cli import main

    out = tmp_path / "c.npz"
    assert main(["render", "--synthetic", "constant", "--env-size", "16", "--mesh", "torus", "--lights", "6",
                 "--size", "16", "12", "--mode", "no-occlusion", "--material", "0.25,0.5,0.9", "--no-ground",
                 "--prefilter", method, "--no-progress", "--out", str(out)]) == 0
    d = np.load(out)
    assert d["mask"].sum() > 10
    np.testing.assert_allclose(d["image"][d["mask"]], 0.75, rtol=CONSTANT_RTOL[method])


def test_render_cli_lists_the_methods_in_help(capsys):
    from ibl_ref.cli import main

    with pytest.raises(SystemExit):
        main(["render", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    for m in prefilter_methods("phong"):
        assert f"'{m.name}'" in out
    assert "Knuth et al. 2014" in out and "Kán" in out
