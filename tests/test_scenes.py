"""What the depth camera sees (evaluation.camera, evaluation.scenes): the right points, where
the part is, and nothing it could not see."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from evaluation.camera import DEFAULT_CAMERA, DEPTH_NOISE_SHARE
from evaluation.cases import object_scale
from evaluation.scenes import sensor_view, surface_centroid
from service.engine.sampling import sample_surface

from .conftest import pybullet_mesh

o3d = pytest.importorskip("open3d", exc_type=ImportError)  # its wheel needs libusb


def distance_to_mesh(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """Each point's distance to the nearest point of the mesh's surface."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)),
    )
    query = o3d.core.Tensor(np.asarray(points, np.float32))
    return scene.compute_distance(query).numpy().astype(np.float64)


def in_model_frame(view) -> np.ndarray:
    return (view.points.astype(np.float64) - view.translation) @ view.rotation


@pytest.fixture(scope="module")
def duck():
    mesh = pybullet_mesh("duck.obj")
    return mesh, object_scale(sample_surface(mesh, 2048, 0))


def test_the_camera_looks_along_z_through_pixel_centres():
    rays = DEFAULT_CAMERA.rays()
    assert rays.shape == (240 * 320, 3)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0)
    np.testing.assert_allclose(DEFAULT_CAMERA.ray(160, 120), [0, 0, 1])
    # one pixel to the right of the centre, half a pixel in: x / z = 0.5 / f
    first_right = rays[120 * 320 + 160]
    assert first_right[0] / first_right[2] == pytest.approx(0.5 / 300)
    assert first_right[1] / first_right[2] == pytest.approx(0.5 / 300)
    corner = rays[0]
    assert corner[0] / corner[2] == pytest.approx(-159.5 / 300)


def test_the_same_seed_gives_the_same_view(duck):
    mesh, scale = duck
    rotation = Rotation.random(random_state=1).as_matrix()
    a = sensor_view(mesh, rotation, 5 * scale, np.random.default_rng(7))
    b = sensor_view(mesh, rotation, 5 * scale, np.random.default_rng(7))
    c = sensor_view(mesh, rotation, 5 * scale, np.random.default_rng(8))
    np.testing.assert_array_equal(a.points, b.points)
    assert a.pixel == b.pixel and a.pixel != c.pixel
    assert a.points.dtype == np.float32 and a.points.shape[1] == 3


def test_points_lie_on_the_mesh_at_the_true_pose_within_the_noise(duck):
    mesh, scale = duck
    rotation = Rotation.random(random_state=2).as_matrix()
    view = sensor_view(mesh, rotation, 6 * scale, np.random.default_rng(3))
    sigma = DEPTH_NOISE_SHARE * np.linalg.norm(view.points, axis=1)  # per point, along the ray
    distances = distance_to_mesh(mesh, in_model_frame(view))
    assert np.all(distances <= 5 * sigma)
    assert np.median(distances / sigma) > 0.05  # the noise is there
    exact = sensor_view(mesh, rotation, 6 * scale, np.random.default_rng(3), noise_share=0.0)
    assert distance_to_mesh(mesh, in_model_frame(exact)).max() < 1e-5 * scale
    # the pose: the surface centroid lies 6 scales away, on the ray through the chosen pixel
    centre = view.rotation @ surface_centroid(mesh) + view.translation
    assert np.linalg.norm(centre) == pytest.approx(6 * scale)
    np.testing.assert_allclose(centre / np.linalg.norm(centre), DEFAULT_CAMERA.ray(*view.pixel))


def test_point_counts_follow_the_view_and_fall_with_distance(duck):
    mesh, scale = duck
    rotation = Rotation.random(random_state=4).as_matrix()
    near = sensor_view(mesh, rotation, 4 * scale, np.random.default_rng(5), pixel=(160, 120))
    far = sensor_view(mesh, rotation, 8 * scale, np.random.default_rng(5), pixel=(160, 120))
    assert 100 < len(far.points) < len(near.points) < 20_000
    assert 2.5 < len(near.points) / len(far.points) < 6  # pixels per area: 1 / distance²


def test_the_camera_sees_the_near_side_only():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    view = sensor_view(sphere, np.eye(3), 5.0, np.random.default_rng(0), noise_share=0.0)
    centre = view.translation
    outward = view.points - centre  # the unit sphere's normal
    toward = -view.points / np.linalg.norm(view.points, axis=1, keepdims=True)
    cosines = np.einsum("ij,ij->i", outward, toward)
    assert cosines.min() > -0.03  # facing the camera; a facet at the rim, seen edge-on
    assert np.mean(cosines > 0) > 0.999
    # a cube seen along its axis shows one face, at the near side's depth
    cube = trimesh.creation.box((1.0, 1.0, 1.0))
    view = sensor_view(cube, np.eye(3), 4.0, np.random.default_rng(0), (160, 120), noise_share=0)
    np.testing.assert_allclose(view.points[:, 2], 3.5, atol=1e-5)
    assert len(view.points) == pytest.approx((300 / 3.5) ** 2, rel=0.05)  # its square, in pixels


def test_the_viewpoint_is_the_camera_at_the_origin(duck):
    mesh, scale = duck
    for seed in range(5):
        view = sensor_view(mesh, np.eye(3), 5 * scale, np.random.default_rng(seed))
        np.testing.assert_array_equal(view.viewpoint, [0.0, 0.0, 0.0])
        u, v = view.pixel
        assert 80 <= u <= 240 and 60 <= v <= 180  # the middle half of the image
        assert np.all(view.points[:, 2] > 0)  # in front of the camera
