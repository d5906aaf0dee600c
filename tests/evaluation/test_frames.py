"""The whole-frame generator (evaluation.frames): real pybullet_data meshes dropped by pybullet's
physics, ray cast by Open3D; the session's scene and bin frame (conftest.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from service.api.depth import depth_points
from service.api.schemas import DepthCamera
from service.engine.sampling import sample_surface

pytest.importorskip("pybullet")
pytest.importorskip("open3d")
frames = pytest.importorskip("evaluation.frames")

TOUCH_M = 0.003  # resting: within the physics' contact margin of what holds it up


def test_parts_are_rescaled_to_a_table_by_their_units(parts):
    registered, _ = parts
    by_name = {p.name: p for p in registered}
    assert by_name["mug"].scale == 1.0  # already in metres, 9 cm across
    assert by_name["diff-ring"].scale == pytest.approx(0.001)  # millimetres
    assert by_name["random-000"].scale == pytest.approx(0.01)
    for part in registered:
        assert frames.RADIUS_RANGE_M[0] - 1e-9 <= part.radius <= frames.RADIUS_RANGE_M[1] + 1e-9


def _box_distance(points: np.ndarray, box) -> np.ndarray:
    """Distance from each point to the box (negative: the depth inside it)."""
    offset = np.abs(points - np.asarray(box.centre)) - np.asarray(box.half)
    outside = np.linalg.norm(np.maximum(offset, 0.0), axis=1)
    return np.where((offset < 0).all(axis=1), offset.max(axis=1), outside)


def _hull_distance(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The largest signed distance to a face plane (n, d) of a convex hull: negative inside
    (the depth), a lower bound of the distance outside."""
    return (points @ faces[:, :3].T + faces[:, 3]).max(axis=1)


@pytest.mark.parametrize("which", ["scene", "bin_frame"])
def test_parts_rest_on_the_support_or_on_each_other(which, request, parts):
    """Each part's mesh surface lies within the contact margin of a support or of another
    part's hull (the shape the physics simulated), and never deeper inside either."""
    frame = request.getfixturevalue(which)
    meshes = {p.name: p.mesh for p in parts[0] + parts[1]}
    surfaces = {n: sample_surface(m, 1000, 0).astype(np.float64) for n, m in meshes.items()}
    hulls = {n: ConvexHull(frames.hull_vertices(m)).equations for n, m in meshes.items()}
    assert len(frame.instances) >= 3
    placed = []
    for instance in frame.instances:
        rotation, translation = frame.world_pose(instance)
        surface = surfaces[instance.name] @ rotation.T + translation
        normals = hulls[instance.name][:, :3] @ rotation.T
        offsets = hulls[instance.name][:, 3] - normals @ translation
        placed.append((instance.name, surface, np.column_stack([normals, offsets])))
    for number, (name, surface, _) in enumerate(placed):
        to_supports = np.min([_box_distance(surface, box) for box in frame.supports], axis=0)
        assert to_supports.min() > -TOUCH_M, f"{name} is inside the table or the bin"
        centre, reach = surface.mean(axis=0), np.ptp(surface, axis=0).max()
        others = [  # the parts near enough to touch it
            hull
            for k, (_, other, hull) in enumerate(placed)
            if k != number
            and np.linalg.norm(other.mean(axis=0) - centre) < reach + np.ptp(other, axis=0).max()
        ]
        to_others = [_hull_distance(surface, hull) for hull in others]
        for gap in to_others:
            assert gap.min() > -TOUCH_M, f"{name} is inside another part"
        nearest = min([to_supports.min(), *(gap.min() for gap in to_others)])
        assert nearest < TOUCH_M, f"{name} floats {1000 * nearest:.0f} mm above everything"


def test_bins_hold_instances_of_one_part_some_on_others(bin_frame):
    names = [i.name for i in bin_frame.instances]
    assert bin_frame.support == "bin"
    assert max(names.count(n) for n in set(names)) >= frames.BIN_INSTANCES[0]
    bin_floor = frames.BIN_WALL_M
    lowest = []
    for instance in bin_frame.instances:
        rotation, translation = bin_frame.world_pose(instance)
        lowest.append(float(translation[2]))
    assert max(lowest) > bin_floor + 0.01  # at least one lies above the floor, on others


@pytest.mark.parametrize("which", ["scene", "bin_frame"])
def test_visible_shares_and_pixels_agree_with_the_labels(which, request):
    frame = request.getfixturevalue(which)
    camera = frame.camera
    assert frame.depth.shape == frame.labels.shape == (camera.height, camera.width)
    for number, instance in enumerate(frame.instances):
        assert 0.0 <= instance.visible_share <= 1.0
        assert len(frame.instance_pixels(number)) == instance.pixels <= instance.pixels_alone
        assert instance.valid_pixels <= instance.pixels
    assert frame.labels.max() <= len(frame.instances)
    shares = [i.visible_share for i in frame.instances]
    assert min(shares) < 0.95  # something hides something


def test_the_camera_sees_the_table_from_the_family_s_range(scene):
    normal, offset = scene.table_plane[:3], scene.table_plane[3]
    distance_to_table = abs(offset)  # the camera at the origin
    assert 0.2 < distance_to_table < frames.DISTANCE_M[1]
    elevation = np.degrees(np.arcsin(abs(normal[2])))  # the optical axis against the plane
    assert frames.ELEVATION_DEG[0] - 1 <= elevation <= frames.ELEVATION_DEG[1] + 1
    table = scene.points()[scene.labels == frames.SUPPORT]
    table = table[np.isfinite(table).all(axis=1)]
    on_plane = np.abs(table @ normal + offset) < 0.01
    assert on_plane.mean() > 0.3  # much of the frame is the table top


def test_the_sensor_s_effects_are_there(scene):
    depth = scene.depth
    valid = np.isfinite(depth)
    assert 0.5 < valid.mean() < 1.0
    millimetres = depth[valid] / frames.DEPTH_STEP_M
    np.testing.assert_allclose(millimetres, np.round(millimetres), atol=1e-3)  # 1 mm steps


def test_depth_noise_quantisation_and_dropped_jumps():
    """A wall at 1 m with a 10 cm step in the middle: noise σ = 0.15 % of the distance along
    each ray, 1 mm steps, about half the pixels at the step missing and none elsewhere."""
    camera = frames.Camera(200, 100, 200.0)
    directions = camera.rays()
    z = np.where(np.arange(camera.width) < 100, 1.0, 1.1)[None, :].repeat(camera.height, 0)
    distance = z.ravel() / directions[:, 2]
    depth = frames.sensor_depth(distance, directions, camera, np.random.default_rng(0))
    at_step = np.zeros(depth.shape, bool)
    at_step[:, 99:101] = True
    assert np.isfinite(depth[~at_step]).all()
    assert 0.35 < np.isnan(depth[at_step]).mean() < 0.65
    near = depth[:, :99]
    residual = near / 1.0 - 1.0  # σ of z/z is that of the distance along the ray
    assert np.std(residual) == pytest.approx(frames.DEPTH_NOISE_SHARE, rel=0.15)
    np.testing.assert_allclose(near * 1000, np.round(near * 1000), atol=1e-3)


@pytest.mark.parametrize("compressed", [False, True])
def test_the_organized_pcd_round_trips_with_its_nan_pixels_in_place(scene, compressed):
    data = frames.pcd_bytes(scene, compressed)
    header = data[: data.index(b"DATA")].decode()
    assert "WIDTH 640" in header and "HEIGHT 480" in header and "POINTS 307200" in header
    read = frames.read_pcd(data)
    expected = scene.points()
    assert read.shape == (480, 640, 3)
    np.testing.assert_array_equal(np.isnan(read), np.isnan(expected))
    assert np.isnan(read).any()
    np.testing.assert_array_equal(read[np.isfinite(read)], expected[np.isfinite(expected)])


def test_the_depth_png_and_its_intrinsics_give_the_pcd_s_points(scene):
    depth = frames.read_depth_png(frames.depth_png_bytes(scene))
    np.testing.assert_array_equal(np.isnan(depth), np.isnan(scene.depth))
    intrinsics = frames.intrinsics(scene.camera)
    camera = DepthCamera(**{k: intrinsics[k] for k in ("fx", "fy", "cx", "cy")})
    millimetres = np.nan_to_num(depth / frames.DEPTH_STEP_M).round().astype(np.uint16)
    served = depth_points(millimetres, camera, None, 10**7)  # as the service reads the PNG
    expected = scene.points().reshape(-1, 3)
    expected = expected[np.isfinite(expected).all(axis=1)]
    np.testing.assert_allclose(served, expected, atol=1e-5)


def test_written_frames_read_back_with_their_ground_truth(scene, tmp_path):
    files = frames.write_frame(scene, tmp_path)
    truth = json.loads(files["truth"].read_text())
    assert truth["camera"]["fx"] == 525.0 and truth["camera"]["cx"] == 319.5
    assert [i["name"] for i in truth["instances"]] == [i.name for i in scene.instances]
    again = frames.read_frame(files["truth"])
    np.testing.assert_array_equal(again.labels, scene.labels)
    np.testing.assert_array_equal(np.isnan(again.depth), np.isnan(scene.depth))
    for read, made in zip(again.instances, scene.instances, strict=True):
        np.testing.assert_allclose(read.rotation, made.rotation)
        assert read.visible_share == pytest.approx(made.visible_share)


def test_empty_and_foreign_frames_hold_no_registered_part(parts):
    empty = frames.make_frame("empty", 0, 0, *parts)
    assert empty.instances == [] and (empty.labels == 0).all()
    foreign = frames.make_frame("foreign", 0, 0, *parts)
    assert foreign.instances and not any(i.registered for i in foreign.instances)


def test_the_same_seed_gives_the_same_frame(parts, scene):
    again = frames.make_frame("scene", 3, 0, *parts)
    np.testing.assert_array_equal(again.labels, scene.labels)
    np.testing.assert_array_equal(np.isnan(again.depth), np.isnan(scene.depth))
