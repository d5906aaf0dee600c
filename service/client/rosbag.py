"""Frames a ROS robot recorded: one ``sensor_msgs/PointCloud2`` message read from a bag.

A ROS 1 bag (``.bag``) or a ROS 2 bag (its folder, or its ``.db3`` or ``.mcap`` file) is read
with the pure-Python ``rosbags`` package (``pip install 'dpc-mn-service[ros]'``; no ROS
install). The message becomes the cloud the service takes: an organized ``(height, width,
3)`` float32 array, NaN where the camera saw nothing (an unorganized one, height 1, is
``(width, 3)``), from its ``x``, ``y`` and ``z`` fields whatever else each point carries
(rgb, intensity, normals) and however its rows are padded. The client uploads it as an NPY
file, so the service keeps the frame's pixel grid (``docs/api.md``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.client.errors import ServiceError

BAG_SUFFIXES = (".bag", ".db3", ".mcap")
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
FIELD_TYPES = {7: "f4", 8: "f8"}  # PointField.FLOAT32, FLOAT64: the types x, y, z come in
INSTALL = "pip install 'dpc-mn-service[ros]'"


class BagError(ServiceError):
    """A bag that holds no frame to send (read before anything reaches the service)."""


@dataclass(frozen=True)
class BagFrame:
    points: np.ndarray  # (height, width, 3) float32, NaN where no depth; (width, 3) if height 1
    topic: str
    timestamp_ns: int  # when the bag recorded it
    frame_id: str  # the sensor frame its points are in

    @property
    def valid(self) -> int:
        """How many of its points have a depth (what the service counts against its limits)."""
        return int(np.isfinite(self.points.reshape(-1, 3)).all(axis=1).sum())


def is_bag(path: str | Path) -> bool:
    """Whether ``path`` names a ROS bag: a ``.bag``, ``.db3`` or ``.mcap`` file, or a ROS 2
    bag's folder (its ``metadata.yaml``)."""
    path = Path(path)
    return path.suffix.lower() in BAG_SUFFIXES or (path / "metadata.yaml").is_file()


def read_bag_frame(path: str | Path, topic: str | None = None, message: int = 0) -> BagFrame:
    """Message ``message`` (0 the first, -1 the last) of the PointCloud2 ``topic`` (by default
    the bag's only PointCloud2 topic) in the bag at ``path``."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise BagError(f"reading a ROS bag needs the rosbags package: {INSTALL}") from None
    path = Path(path)
    if not path.exists():
        raise BagError(f"no such bag: {path}")
    # a ROS 2 bag is read as its folder, which holds the metadata beside the .db3 / .mcap
    bag = path.parent if path.is_file() and (path.parent / "metadata.yaml").is_file() else path
    try:
        with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            connections = _chosen(reader.connections, topic, path.name)
            count = sum(c.msgcount for c in connections)
            index = message + count if message < 0 else message
            if not 0 <= index < count:
                raise BagError(
                    f"{connections[0].topic} holds {count} message{'s' * (count != 1)} in "
                    f"{path.name}: "
                    f"message {message} is not among them (0 to {count - 1}, or -1 for the last)"
                )
            for k, (connection, timestamp, raw) in enumerate(reader.messages(connections)):
                if k == index:
                    cloud = reader.deserialize(raw, connection.msgtype)
                    return BagFrame(
                        cloud_points(cloud), connection.topic, timestamp, cloud.header.frame_id
                    )
    except BagError:
        raise
    except Exception as error:  # rosbags' own: not a bag, a truncated file, an unknown type
        raise BagError(f"{path.name} is not a ROS bag that can be read: {error}") from None
    raise BagError(f"{path.name}: the bag ended before message {message}")  # a short index


def _chosen(connections, topic: str | None, name: str) -> list:
    """The connections of the chosen PointCloud2 topic; a clear error when there is none, or
    several and none chosen."""
    clouds = [c for c in connections if c.msgtype == POINTCLOUD2]
    topics = sorted({c.topic for c in clouds})
    if not topics:
        held = ", ".join(sorted({f"{c.topic} ({c.msgtype})" for c in connections})) or "none"
        raise BagError(f"{name} holds no sensor_msgs/PointCloud2 topic; its topics: {held}")
    if topic is None:
        if len(topics) > 1:
            raise BagError(
                f"{name} holds several PointCloud2 topics: {', '.join(topics)}; choose one "
                "(--topic)"
            )
        topic = topics[0]
    if topic not in topics:
        raise BagError(
            f"{name} has no PointCloud2 topic {topic!r}; its PointCloud2 topics: "
            f"{', '.join(topics)}"
        )
    return [c for c in clouds if c.topic == topic]


def cloud_points(cloud) -> np.ndarray:
    """A ``sensor_msgs/PointCloud2`` message's ``x y z`` as float32: ``(height, width, 3)``
    for an organized cloud, ``(width, 3)`` for height 1; NaN stays NaN."""
    fields = {field.name: field for field in cloud.fields}
    missing = [axis for axis in "xyz" if axis not in fields]
    if missing:
        named = ", ".join(fields) or "none"
        raise BagError(f"the PointCloud2 has no {', '.join(missing)} field (its fields: {named})")
    height, width = int(cloud.height), int(cloud.width)
    step, row = int(cloud.point_step), int(cloud.row_step)
    data = np.asarray(cloud.data, dtype=np.uint8)
    if row < width * step or len(data) < height * row:
        raise BagError(
            f"the PointCloud2 is cut short: {len(data)} bytes for {height} rows of {row} "
            f"({width} points of {step} bytes a row)"
        )
    points = data[: height * row].reshape(height, row)[:, : width * step]
    points = points.reshape(height * width, step)
    order = ">" if cloud.is_bigendian else "<"
    axes = []
    for axis in "xyz":
        field = fields[axis]
        kind = FIELD_TYPES.get(int(field.datatype))
        if kind is None:
            raise BagError(
                f"the PointCloud2's {axis} field is of datatype {field.datatype}, not a float "
                "(7: FLOAT32, 8: FLOAT64)"
            )
        size = int(kind[1])
        if field.offset + size > step:
            raise BagError(f"the PointCloud2's {axis} field lies past its point_step {step}")
        raw = np.ascontiguousarray(points[:, field.offset : field.offset + size])
        axes.append(raw.view(order + kind)[:, 0].astype(np.float32))
    xyz = np.stack(axes, axis=1)
    return xyz.reshape(height, width, 3) if height > 1 else xyz
