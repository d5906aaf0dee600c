"""Frames from ROS bags (issue 35): the client and ``dpc-mn`` read a ``sensor_msgs/PointCloud2``
message from a ROS 1 or ROS 2 bag (rosbags, no ROS install) and send it as the organized frame
it is. The bags are written here by rosbags' own writers, as a robot's recorder writes them:
padded rows, rgb and intensity beside x y z, NaN where the camera saw nothing."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from service.client import Client
from service.client.cli import main
from service.client.rosbag import BagError, is_bag, read_bag_frame
from tests.conftest import server_holding
from tests.frames import resting, shoot, spin, table

rosbags = pytest.importorskip("rosbags")
from rosbags.rosbag1 import Writer as Ros1Writer  # noqa: E402
from rosbags.rosbag2 import Writer as Ros2Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

BOX = (0.08, 0.06, 0.04)
TOPIC = "/camera/depth/points"
PAD = 8  # bytes at the end of each row, as some drivers align them


def pointcloud2(store, points: np.ndarray, big_endian: bool = False):
    """An organized PointCloud2 of ``points`` (H, W, 3): x y z float32, rgb float32 and
    intensity float64 beside them, ``PAD`` bytes after each row."""
    types = store.types
    field = types["sensor_msgs/msg/PointField"]
    height, width, _ = points.shape
    order = ">" if big_endian else "<"
    layout = np.dtype(
        {
            "names": ["x", "y", "z", "rgb", "intensity"],
            "formats": [order + "f4"] * 4 + [order + "f8"],
            "offsets": [0, 4, 8, 16, 24],
            "itemsize": 32,
        }
    )
    rows = np.zeros((height, width), layout)
    for k, axis in enumerate("xyz"):
        rows[axis] = points[..., k]
    rows["rgb"], rows["intensity"] = 1.5, 7.0
    data = np.concatenate(
        [rows.view(np.uint8).reshape(height, -1), np.zeros((height, PAD), np.uint8)], axis=1
    )
    fields = [
        field(name=name, offset=offset, datatype=datatype, count=1)
        for name, offset, datatype in (
            ("x", 0, 7),
            ("y", 4, 7),
            ("z", 8, 7),
            ("rgb", 16, 7),
            ("intensity", 24, 8),
        )
    ]
    stamp = types["builtin_interfaces/msg/Time"](sec=1, nanosec=0)
    header_type = types["std_msgs/msg/Header"]
    header = (
        header_type(seq=0, stamp=stamp, frame_id="camera_depth_optical_frame")
        if "seq" in header_type.__dataclass_fields__
        else header_type(stamp=stamp, frame_id="camera_depth_optical_frame")
    )
    return types["sensor_msgs/msg/PointCloud2"](
        header=header,
        height=height,
        width=width,
        fields=fields,
        is_bigendian=big_endian,
        point_step=32,
        row_step=32 * width + PAD,
        data=data.reshape(-1),
        is_dense=False,
    )


def ros1_bag(path, messages: dict[str, list[np.ndarray]], big_endian: bool = False):
    store = get_typestore(Stores.ROS1_NOETIC)
    msgtype = "sensor_msgs/msg/PointCloud2"
    with Ros1Writer(path) as writer:
        for topic, frames in messages.items():
            connection = writer.add_connection(topic, msgtype, typestore=store)
            for k, points in enumerate(frames):
                message = pointcloud2(store, points, big_endian)
                writer.write(connection, 10 + k, store.serialize_ros1(message, msgtype))
    return path


def ros2_bag(path, messages: dict[str, list[np.ndarray]]):
    store = get_typestore(Stores.ROS2_HUMBLE)
    msgtype = "sensor_msgs/msg/PointCloud2"
    with Ros2Writer(path, version=8) as writer:
        for topic, frames in messages.items():
            connection = writer.add_connection(topic, msgtype, typestore=store)
            for k, points in enumerate(frames):
                message = pointcloud2(store, points)
                writer.write(connection, 10 + k, store.serialize_cdr(message, msgtype))
    return path


def grid(height: int = 4, width: int = 5, seed: int = 0) -> np.ndarray:
    """A small organized frame, a third of its pixels without depth."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(height, width, 3)).astype(np.float32)
    points[rng.random((height, width)) < 0.33] = np.nan
    return points


def same(a: np.ndarray, b: np.ndarray) -> None:
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_array_equal(a[np.isfinite(a)], b[np.isfinite(b)])


@pytest.mark.parametrize("big_endian", [False, True])
def test_a_ros1_bags_pointcloud2_reads_as_its_organized_frame(tmp_path, big_endian):
    first, last = grid(seed=1), grid(seed=2)
    bag = ros1_bag(tmp_path / "cell.bag", {TOPIC: [first, last]}, big_endian)
    assert is_bag(bag)
    frame = read_bag_frame(bag)
    assert frame.points.shape == (4, 5, 3) and frame.points.dtype == np.float32
    same(frame.points, first)
    assert frame.topic == TOPIC and frame.frame_id == "camera_depth_optical_frame"
    assert frame.valid == int(np.isfinite(first[..., 0]).sum())
    same(read_bag_frame(bag, TOPIC, -1).points, last)
    same(read_bag_frame(bag, message=1).points, last)


def test_a_ros2_bag_reads_from_its_folder_or_its_file(tmp_path):
    points = grid(seed=3)
    bag = ros2_bag(tmp_path / "cell", {TOPIC: [points]})
    (database,) = bag.glob("*.db3")
    assert is_bag(bag) and is_bag(database)
    same(read_bag_frame(bag).points, points)
    same(read_bag_frame(database).points, points)


def test_a_bag_without_the_frame_asked_for_says_what_it_holds(tmp_path):
    two = ros1_bag(tmp_path / "two.bag", {TOPIC: [grid()], "/camera/other": [grid()]})
    with pytest.raises(BagError, match="several PointCloud2 topics.*--topic"):
        read_bag_frame(two)
    with pytest.raises(BagError, match="no PointCloud2 topic '/nope'.*/camera/other"):
        read_bag_frame(two, "/nope")
    with pytest.raises(BagError, match="holds 1 message in two.bag: message 3"):
        read_bag_frame(two, TOPIC, 3)
    store = get_typestore(Stores.ROS1_NOETIC)
    with Ros1Writer(tmp_path / "talk.bag") as writer:
        connection = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        text = store.types["std_msgs/msg/String"](data="hello")
        writer.write(connection, 1, store.serialize_ros1(text, "std_msgs/msg/String"))
    with pytest.raises(BagError, match=r"no sensor_msgs/PointCloud2 topic.*/chatter"):
        read_bag_frame(tmp_path / "talk.bag")
    broken = tmp_path / "broken.bag"
    broken.write_bytes(b"not a bag at all")
    with pytest.raises(BagError, match="broken.bag is not a ROS bag"):
        read_bag_frame(broken)


def test_the_cli_refuses_a_bag_without_its_frame_before_sending_it(tmp_path, capsys):
    bag = ros1_bag(tmp_path / "cell.bag", {TOPIC: [grid()]})
    # no service at this address: the bag is read, and refused, first
    url = "http://127.0.0.1:9"
    assert main(["detect", str(bag), "--topic", "/nope", "--url", url, "--retry-for", "0"]) == 1
    said = capsys.readouterr()
    assert "no PointCloud2 topic '/nope'" in said.out + said.err


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    server = server_holding(tmp_path_factory.mktemp("rosbag"), {"box-a": trimesh.creation.box(BOX)})
    yield server
    server.stop()


def test_the_client_and_the_cli_detect_in_a_frame_a_bag_recorded(server, tmp_path, capsys):
    box = trimesh.creation.box(BOX)
    shot = shoot([(box, *resting(box, spin(20), 0.01, 0.0))], table())
    empty = shoot([], table())
    bag = ros2_bag(tmp_path / "cell", {TOPIC: [empty.points, shot.points]})
    with Client(server.url, retry_for=0) as client:
        scene = client.detect(bag, topic=TOPIC, message=-1)
        nothing = client.detect(bag, message=0)
    assert [d.label for d in scene.matches] == ["box-a"], scene.raw
    (found,) = scene.matches
    assert np.linalg.norm(found.translation - shot.poses[0][1]) < 0.01
    assert scene.raw["num_points"] == int(np.isfinite(shot.points[..., 0]).sum())  # valid only
    shows = shot.shows.reshape(-1)[np.asarray(scene.raw["detections"][0]["indices"])]
    assert np.mean(shows == 0) > 0.9  # the indices are the frame's pixels: its grid was kept
    assert nothing.raw["detections"] == []
    assert main(["detect", str(bag), "--message", "-1", "--url", server.url]) == 0
    assert "match: box-a" in capsys.readouterr().out
    assert main(["detect", str(bag), "--url", server.url]) == 3  # the empty table first
