"""The validated environment (:mod:`ibl_ref.environment.validated`) against its definition.

* Read-only: the array of an :class:`Environment` cannot be changed through the type, through ``np.asarray``, by
  setting its flag back, through the caller's original array, or after a pickle round trip.
* Checked once: a plain array costs exactly one radiance check per call of a pipeline entry point (the count of
  :func:`ibl_ref.environment.radiance_policy.assess` calls), an :class:`Environment` none — through the median cut,
  the PEMs (dense and sparse, every pyramid chunk), the filter pyramid, resampling and writing.
* The errors of plain arrays are the one-line errors of the checks the entry points called before
  (:func:`~ibl_ref.environment.envmap.check_cube_shape` then
  :func:`~ibl_ref.environment.radiance_policy.check_radiance`, each under the entry point's own name): computed here
  by calling those two functions, the independent route.
* Results do not depend on the route: an :class:`Environment` gives the same lights and PEMs as its plain array.
"""

import pickle

import numpy as np
import pytest

from ibl_ref.environment import radiance_policy
from ibl_ref.environment.envmap import check_cube_shape
from ibl_ref.environment.radiance_policy import check_radiance
from ibl_ref.environment.validated import Environment, adopt, as_environment, environment_array
from ibl_ref.errors import IBLError, LayoutError, RadianceError
from ibl_ref.synthetic.synthetic_envs import make_env, make_environment


@pytest.fixture
def checks(monkeypatch):
    """A list that gets one entry (the checked array's name) per radiance check."""
    seen = []
    real = radiance_policy.assess

    def counting(values, name="radiance", *a, **k):
        seen.append(name)
        return real(values, name, *a, **k)

    monkeypatch.setattr(radiance_policy, "assess", counting)
    return seen


def _sky(n=8):
    return make_env("sky_sun", n)


# ------------------------------------------------------------------------------------------------------------------
# read-only
# ------------------------------------------------------------------------------------------------------------------
def _assert_frozen(env):
    before = env.data.copy()
    with pytest.raises(ValueError, match="read-only"):
        env.data[0, 0, 0, 0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        np.asarray(env)[...] = 0.0
    with pytest.raises(ValueError, match="read-only"):
        np.multiply(env.data, 2.0, out=env.data)
    with pytest.raises(ValueError, match="WRITEABLE"):
        env.data.flags.writeable = True
    with pytest.raises(ValueError, match="WRITEABLE"):
        np.asarray(env).flags.writeable = True
    with pytest.raises(AttributeError):
        env.data = np.zeros_like(before)
    with pytest.raises(AttributeError):
        env.extra = 1  # no other attributes (slots)
    writable = np.array(env)  # a copy, the user's to change
    writable[...] = -1.0
    assert np.array_equal(env.data, before)


def test_plain_array_is_copied_and_frozen():
    a = _sky()
    env = as_environment(a)
    _assert_frozen(env)
    a[...] = 7.0  # the caller's array changes afterwards: the environment does not
    assert np.array_equal(env.data, _sky()) and a.flags.writeable


@pytest.mark.parametrize("make", ["pickle", "adopt", "make_environment", "load_environment", "clamped", "3-d"])
def test_every_route_gives_a_frozen_environment(make, tmp_path):
    if make == "pickle":
        env = pickle.loads(pickle.dumps(as_environment(_sky())))
    elif make == "adopt":
        env = adopt(_sky()[:, :, :, :2])  # a view of an array the caller gives up
    elif make == "make_environment":
        env = make_environment("sky_sun", 8)
    elif make == "load_environment":
        from ibl_ref.environment.exr_io import load_environment, write_envmap

        write_envmap(tmp_path / "sky.exr", _sky())
        env = load_environment(tmp_path / "sky.exr")
    elif make == "clamped":
        env = as_environment(_sky() - 0.01, negative="clamp")
    else:
        env = as_environment(_sky()[..., 0])
    _assert_frozen(env)


def test_type_properties():
    env = as_environment(_sky()[..., 1], "sky")
    assert (env.face_size, env.channels, env.shape, env.ndim, env.dtype) == (8, 1, (6, 8, 8, 1), 4, np.float64)
    assert np.shape(env) == (6, 8, 8, 1) and np.ndim(env) == 4
    assert repr(env) == "Environment(face_size=8, channels=1, name='sky')"
    assert env.name == "sky" and env.radiance.clean and env.radiance.n_values == 6 * 8 * 8
    assert as_environment(env) is env and as_environment(env, "another name") is env
    assert np.asarray(env) is env.data
    f32 = np.asarray(env, dtype=np.float32)
    assert f32.dtype == np.float32 and np.array_equal(f32, env.data.astype(np.float32))
    with pytest.raises(IBLError, match="needs a copy"):
        env.__array__(np.float32, copy=False)
    a, squeezed = environment_array(_sky()[..., 0])
    assert a.shape == (6, 8, 8, 1) and squeezed
    assert environment_array(env) == (env.data, False)


def test_policy_repairs_are_reported():
    a = _sky()
    a[1, 2, 3, 0] = -1e-3
    env = as_environment(a, "sky", negative="clamp")
    assert env.data[1, 2, 3, 0] == 0.0 and env.radiance.n_negative == 1 and env.radiance.action
    assert a[1, 2, 3, 0] == -1e-3  # the caller's array is not repaired in place


# ------------------------------------------------------------------------------------------------------------------
# checked once
# ------------------------------------------------------------------------------------------------------------------
def test_plain_array_checked_once_environment_never(checks):
    a = _sky()
    checks.clear()
    env = as_environment(a)
    assert checks == ["environment"]
    assert as_environment(env) is env and checks == ["environment"]


def _pipeline(cube, tmp_path):
    from ibl_ref.environment.exr_io import write_envmap
    from ibl_ref.environment.resample import cube_to_cube, cube_to_latlong
    from ibl_ref.knuth2014.median_cut import median_cut, texel_lights
    from ibl_ref.knuth2014.pem import build_pems
    from ibl_ref.knuth2014.pyramid import build_pyramid
    from ibl_ref.knuth2014.sparse_pem import build_sparse_pems

    return {
        "median_cut": lambda: median_cut(cube, 6),
        "texel_lights": lambda: texel_lights(cube),
        "build_pems": lambda: build_pems(cube, n_lights=12, chunk=2),  # six pyramid chunks
        "build_sparse_pems": lambda: build_sparse_pems(cube, n_lights=6, chunk=2),
        "build_pyramid": lambda: build_pyramid(cube),
        "cube_to_cube": lambda: cube_to_cube(cube, 4),
        "cube_to_latlong": lambda: cube_to_latlong(cube, 8),
        "write_envmap": lambda: write_envmap(tmp_path / "out.exr", cube),
    }


@pytest.mark.parametrize("entry", ["median_cut", "texel_lights", "build_pems", "build_sparse_pems", "build_pyramid",
                                   "cube_to_cube", "cube_to_latlong", "write_envmap"])
def test_entry_points_check_a_plain_array_once_and_trust_an_environment(entry, checks, tmp_path):
    env, plain = make_environment("sky_sun", 8), _sky()
    checks.clear()
    _pipeline(env, tmp_path)[entry]()
    assert checks == [], f"{entry} re-checked a validated environment: {checks}"
    _pipeline(plain, tmp_path)[entry]()
    assert len(checks) == 1, f"{entry} checked a plain array {len(checks)} times: {checks}"


def test_readers_and_generators_check_once(checks, tmp_path):
    from ibl_ref.environment.exr_io import load_environment, write_envmap

    make_environment("constant", 4)
    assert len(checks) == 1
    write_envmap(tmp_path / "c.exr", np.ones((6, 4, 4, 3)))
    checks.clear()
    env = load_environment(tmp_path / "c.exr", size=2)  # a resampled read: the read's check only
    assert len(checks) == 1 and env.face_size == 2 and env.radiance.name.endswith("c.exr: radiance")


# ------------------------------------------------------------------------------------------------------------------
# the same one-line errors as before
# ------------------------------------------------------------------------------------------------------------------
def _bad_inputs(n):
    nan = np.ones((6, n, n, 3))
    nan[3, 1, 2, 0] = np.nan
    inf = np.ones((6, n, n))
    inf[0, 0, n - 1] = np.inf
    neg = np.ones((6, n, n, 3))
    neg[5, n - 1, n - 1, 2] = -2.0
    return {"not square": np.ones((6, n, n - 1, 3)), "five faces": np.ones((5, n, n, 3)),
            "5-d": np.ones((6, n, n, 3, 1)), "NaN": nan, "Inf": inf, "negative": neg,
            "complex": np.ones((6, n, n, 3), complex), "integer": np.ones((6, n, n, 3), int),
            "bool": np.ones((6, n, n), bool)}


def _old_error(x, shape_name, radiance_name):
    """The error of the checks the entry points made before the type: the layout, then the radiance."""
    try:
        check_cube_shape(x, shape_name)
        check_radiance(x, radiance_name)
    except IBLError as exc:
        return type(exc), str(exc)
    raise AssertionError("not a bad input")


@pytest.mark.parametrize("bad", sorted(_bad_inputs(4)))
@pytest.mark.parametrize("entry, shape_name, radiance_name", [
    ("as_environment", "environment", "environment"),
    ("median_cut", "median cut input", "median cut input"),
    ("texel_lights", "texel lights input", "texel lights input"),
    ("build_pems", "PEM input", "PEM input"),
    ("build_pyramid", "cube map", "environment map"),
    ("cube_to_cube", "cube map", "cube map"),
])
def test_plain_arrays_keep_their_one_line_errors(bad, entry, shape_name, radiance_name):
    from ibl_ref.environment.resample import cube_to_cube
    from ibl_ref.knuth2014.median_cut import median_cut, texel_lights
    from ibl_ref.knuth2014.pem import build_pems
    from ibl_ref.knuth2014.pyramid import build_pyramid

    x = _bad_inputs(4 if entry == "build_pyramid" else 6)[bad]  # the pyramid refuses 6 before the values
    call = {"as_environment": as_environment, "median_cut": lambda c: median_cut(c, 6), "texel_lights": texel_lights,
            "build_pems": lambda c: build_pems(c, n_lights=6), "build_pyramid": build_pyramid,
            "cube_to_cube": lambda c: cube_to_cube(c, 3)}[entry]
    with pytest.raises(IBLError) as ei:
        call(x)
    kind, msg = _old_error(x, shape_name, radiance_name)
    assert (type(ei.value), str(ei.value)) == (kind, msg)
    assert "\n" not in msg


def test_zero_channels_is_a_layout_error():
    with pytest.raises(LayoutError, match=r"^sky: zero channels in shape \(6, 4, 4, 0\)$"):
        as_environment(np.ones((6, 4, 4, 0)), "sky")


def test_environment_is_validated_when_made_directly():
    a = np.ones((6, 4, 4))
    a[2, 1, 1] = -1.0
    with pytest.raises(RadianceError, match="^environment: 1 negative radiance value"):
        Environment(a)


# ------------------------------------------------------------------------------------------------------------------
# same results by either route
# ------------------------------------------------------------------------------------------------------------------
def test_environment_and_array_give_the_same_pipeline_results():
    from ibl_ref.knuth2014.median_cut import median_cut
    from ibl_ref.knuth2014.pem import build_pems
    from ibl_ref.knuth2014.pyramid import build_pyramid

    a = make_env("sky_sun", 16)
    env = as_environment(a)
    la, le = median_cut(a, 12), median_cut(env, 12)
    assert np.array_equal(la.labels, le.labels) and np.array_equal(la.rgb, le.rgb)
    pa, pe = build_pems(a, la, chunk=5), build_pems(env, le, chunk=5)
    assert all(np.array_equal(x, y) for x, y in zip(pa.levels, pe.levels))
    f32 = make_env("sky_sun", 16).astype(np.float32)  # the pyramid keeps a float32 input's dtype
    assert build_pyramid(f32).levels[-1].dtype == np.float32
