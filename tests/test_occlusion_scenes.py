"""The occlusion scenes of ibl_ref/rendering/scenes.py: valid, closed where solid, outward, deterministic, and the
crevice really occludes (ray-cast visibility at the bottom of its pit against the closed-form form factor)."""

import numpy as np
import pytest
from test_gtao import cosine_visibility

from ibl_ref.errors import IBLError
from ibl_ref.rendering.raster import mesh_list, prepare_scene, rasterize
from ibl_ref.rendering.scenes import (OCCLUSION_SCENES, bumpy_scene, crevice_scene, occlusion_scene,
                                      scene_camera)
from ibl_ref.synthetic.synthetic_meshes import validate_mesh


@pytest.mark.parametrize("name", sorted(OCCLUSION_SCENES))
def test_scenes_are_valid_and_face_their_camera(name):
    meshes, camera = occlusion_scene(name)
    for k, (mesh, _) in enumerate(mesh_list(meshes)):
        validate_mesh(mesh, f"{name}[{k}]")
    scene = prepare_scene(meshes)
    assert scene.n_degenerate == 0 and len(scene.faces) < 20_000
    g = rasterize(meshes, camera(32))
    facing = np.einsum("hwc,hwc->hw", g.face_normal, g.view)[g.mask]
    # outward faces: what the camera sees faces it (the teapot's open lid gap shows a few inner faces: 0.1 %)
    assert g.mask.mean() > 0.7 and np.mean(facing > 0) > (0.99 if name == "teapot" else 1 - 1e-12)
    smooth = np.einsum("hwc,hwc->hw", g.normal, g.face_normal)[g.mask]
    assert np.mean(smooth > 0.5) > 0.99  # vertex normals agree with the faces (no smoothing across hard edges)


def test_crevice_is_a_closed_outward_solid():
    (mesh,) = crevice_scene(depth=0.4, width=0.6, length=0.9, slab=2.0)
    merged = mesh.copy()
    merged.merge_vertices()
    assert merged.is_watertight and merged.is_winding_consistent
    assert merged.volume == pytest.approx(2.0 * 2.0 * 0.8 - 0.6 * 0.9 * 0.4, rel=1e-12)  # > 0: outward
    np.testing.assert_allclose(mesh.vertex_normals, np.repeat(mesh.face_normals[::2], 4, axis=0), atol=1e-12)


def test_bumps_are_closed_disjoint_and_seeded():
    ground, bumps = bumpy_scene()
    assert bumps.is_watertight and bumps.volume > 0 and len(bumps.faces) == 40 * 320
    np.testing.assert_array_equal(ground.face_normals, [[0, 1, 0], [0, 1, 0]])
    c = bumps.metadata["bumps"]
    dist = np.hypot(c[:, None, 0] - c[None, :, 0], c[:, None, 2] - c[None, :, 2])
    reach = c[:, None, 3] + c[None, :, 3] + 0.01
    assert np.all((dist >= reach) | np.eye(len(c), dtype=bool))
    assert np.all(c[:, 1] - c[:, 3] < 0)  # every bump reaches into the ground: no floating spheres
    again = bumpy_scene()[1]
    assert np.array_equal(again.vertices, bumps.vertices)
    assert not np.array_equal(bumpy_scene(seed=1)[1].vertices, bumps.vertices)
    assert np.array_equal(crevice_scene()[0].vertices, crevice_scene()[0].vertices)


def parallel_rect_form_factor(a, b, c):
    """Form factor from a floor element to a parallel rectangle a × b at height c above one of its corners."""
    x, y = a / c, b / c
    sx, sy = np.sqrt(1 + x * x), np.sqrt(1 + y * y)
    return (x / sx * np.arctan(y / sx) + y / sy * np.arctan(x / sy)) / (2 * np.pi)


def test_crevice_pit_bottom_is_occluded():
    # the pit's floor centre sees the sky through the opening only: visibility = the opening's form factor, 0.361
    meshes = crevice_scene()
    vis, _ = cosine_visibility(meshes, [[0.0, -0.5, 0.0]], [[0.0, 1.0, 0.0]], [[0.0, 1.0, 0.0]], n_side=64)
    exact = 4 * parallel_rect_form_factor(0.25, 0.5, 0.5)
    assert exact == pytest.approx(0.361, abs=1e-3)
    assert vis[0] < 0.6 and abs(vis[0] - exact) < 0.01


def test_registry_and_cameras():
    assert set(OCCLUSION_SCENES) == {"teapot", "crevice", "bumpy", "normal-mapped"}
    _, camera = occlusion_scene("crevice", depth=0.8)
    cam = camera(20)
    assert (cam.width, cam.height) == (20, 20) and cam.target.tolist() == [0.0, -0.4, 0.0]
    assert scene_camera("crevice", 20).target.tolist() == [0.0, -0.25, 0.0]
    with pytest.raises(IBLError, match="unknown occlusion scene"):
        occlusion_scene("cornell")


@pytest.mark.parametrize("make, kw, match", [
    (crevice_scene, dict(depth=0.0), "depth"), (crevice_scene, dict(width=3.0), "smaller than the slab"),
    (bumpy_scene, dict(n_bumps=0), "n_bumps"), (bumpy_scene, dict(radii=(0.2, 0.1)), "radii"),
    (bumpy_scene, dict(radii=0.1), "radii"), (bumpy_scene, dict(radii=(0.1,)), "radii"),
    (bumpy_scene, dict(seed=-2), "seed"),
    (bumpy_scene, dict(n_bumps=200, radii=(0.2, 0.3)), "no room"),
])
def test_bad_scene_parameters_raise(make, kw, match):
    with pytest.raises(IBLError, match=match):
        make(**kw)
