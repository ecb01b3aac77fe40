"""Tests of ibl_ref.rendering.camera: pixel mapping, vertical fov, matrices, light camera fit, bad input."""

import numpy as np
import pytest

from ibl_ref.rendering.camera import CameraError, OrthographicCamera, PerspectiveCamera, light_camera, scene_bounds
from ibl_ref.errors import IBLError


def _cam(w=8, h=6, fov=50.0):
    return PerspectiveCamera(eye=[1.0, 2.0, 5.0], target=[0.2, -0.1, 0.3], up=[0, 1, 0], fov_y_deg=fov, width=w, height=h)


def test_pixel_rays_project_to_pixel_centres():
    # ray generation and projection are separate code paths; points on each pixel's ray must land on
    # (j + 1/2, i + 1/2).  Tolerance: float64 rounding of a few operations on O(10) numbers.
    cam = _cam()
    o, d = cam.pixel_rays()
    for t in (0.5, 3.0, 40.0):
        x, y, depth, w = cam.project(o + t * d)
        jj, ii = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
        np.testing.assert_allclose(x, jj, atol=1e-11)
        np.testing.assert_allclose(y, ii, atol=1e-11)
        # directions have unit forward component, so the ray parameter is the depth
        np.testing.assert_allclose(depth, t, rtol=1e-13)
        np.testing.assert_allclose(w, depth)


def test_vertical_fov_and_row_zero_at_top():
    # closed form: a point at angle fov/2 above the optical axis lies on the top image border (y = 0),
    # and the horizontal half-extent is aspect·tan(fov/2) (the fov is vertical).
    fov = 60.0
    cam = PerspectiveCamera(eye=[0, 0, 0], target=[0, 0, -1], up=[0, 1, 0], fov_y_deg=fov, width=20, height=10)
    a = np.radians(fov / 2)
    x, y, depth, _ = cam.project(np.array([0.0, np.sin(a), -np.cos(a)]))
    assert abs(y - 0.0) < 1e-12 and abs(x - 10.0) < 1e-12
    x, y, _, _ = cam.project(np.array([0.0, -np.sin(a), -np.cos(a)]))
    assert abs(y - 10.0) < 1e-12
    # horizontal: aspect 2 → the right border is at tan(h/2) = 2·tan(fov/2)
    x, y, _, _ = cam.project(np.array([2 * np.tan(a), 0.0, -1.0]))
    assert abs(x - 20.0) < 1e-12 and abs(y - 5.0) < 1e-12


def test_matrices_agree_with_project():
    # OpenGL route: clip = P·V·p, ndc = clip.xy / clip.w  → pixel; independent of project()'s formula
    cam = _cam(32, 24)
    rng = np.random.default_rng(1)
    pts = cam.target + rng.normal(scale=0.5, size=(50, 3))
    ph = np.c_[pts, np.ones(len(pts))]
    clip = ph @ (cam.projection_matrix() @ cam.view_matrix()).T
    ndc = clip[:, :3] / clip[:, 3:]
    x_ref = (ndc[:, 0] + 1) / 2 * cam.width
    y_ref = (1 - ndc[:, 1]) / 2 * cam.height
    x, y, depth, _ = cam.project(pts)
    np.testing.assert_allclose(x, x_ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(y, y_ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(depth, clip[:, 3], rtol=1e-12)  # w_clip = −z_view = depth


def test_light_camera_contains_scene():
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(200, 3)) * [2, 0.5, 1] + [3, 1, -2]
    c, r = scene_bounds(pts)
    for wdir in ([0, 1, 0], [0.3, -0.2, 0.9], [0, -1, 0]):
        cam = light_camera(wdir, c, r, resolution=64)
        x, y, depth, w = cam.project(pts)
        assert np.all((x > 0) & (x < 64) & (y > 0) & (y < 64))
        assert np.all((depth > cam.near) & (depth < cam.far))
        np.testing.assert_allclose(-cam.forward, np.asarray(wdir) / np.linalg.norm(wdir), atol=1e-15)
        assert cam.texel_size == pytest.approx(2 * r * 1.05 / 64)
        np.testing.assert_allclose(w, 1.0)


def test_orthographic_rays_match_projection():
    cam = OrthographicCamera(eye=[0, 0, 0], forward=[0, 0, -1], up=[0, 1, 0], half_width=2, half_height=1,
                             width=8, height=4, near=0, far=10)
    o, d = cam.pixel_rays()
    x, y, depth, _ = cam.project(o + 3.0 * d)
    np.testing.assert_allclose(x, np.arange(8)[None, :] + 0.5 + 0 * y, atol=1e-12)
    np.testing.assert_allclose(y, np.arange(4)[:, None] + 0.5 + 0 * x, atol=1e-12)
    np.testing.assert_allclose(depth, 3.0, atol=1e-12)


@pytest.mark.parametrize(
    "kwargs, msg",
    [
        (dict(eye=[1, 1, 1], target=[1, 1, 1]), "coincides"),
        (dict(eye=[0, 0, 0], target=[0, 2, 0]), "parallel"),
        (dict(fov_y_deg=180.0), "fov"),
        (dict(fov_y_deg=0.0), "fov"),
        (dict(width=0), "size"),
        (dict(width=2.5), "size"),
        (dict(near=0.0), "near"),
        (dict(eye=[np.nan, 0, 0]), "NaN"),
    ],
)
def test_bad_camera(kwargs, msg):
    base = dict(eye=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0], fov_y_deg=45.0, width=4, height=4)
    base.update(kwargs)
    with pytest.raises(CameraError, match=msg):
        PerspectiveCamera(**base)
    assert issubclass(CameraError, IBLError)


def test_bad_light_camera():
    with pytest.raises(CameraError, match="zero"):
        light_camera([0, 0, 0], [0, 0, 0], 1.0)
    with pytest.raises(CameraError, match="radius"):
        light_camera([0, 1, 0], [0, 0, 0], -1.0)
