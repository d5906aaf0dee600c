"""The console's view of POST /detect: a real server with a box registered, a frame of the box
on a table (tests/frames.py, an organized PCD with missing pixels) dropped on "Detect in a
frame" in Debian's Chromium, the detection listed and drawn; and what the console relies on,
POST /points?pixels=true giving each point's pixel, the indices /detect answers."""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh

from tests.conftest import empty_server
from tests.frames import resting, shoot, spin, table
from tests.test_console import Page, browser  # noqa: F401 - the browser fixture

BOX = (0.08, 0.06, 0.04)
SMALL = (320, 240, 262.5)  # a quarter of VGA: the same field of view, a quick /detect


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """A real server whose gallery holds one box, registered as an STL mesh."""
    server = empty_server(tmp_path_factory.mktemp("console-detect"))
    buffer = io.BytesIO()
    trimesh.creation.box(BOX).export(buffer, file_type="stl")
    answer = server.client.post(
        "/references",
        data={"name": "box-a"},
        files={"file": ("box-a.stl", buffer.getvalue())},
        params={"self_check": "false"},
    )
    assert answer.status_code == 201, answer.text
    yield server
    server.stop()


@pytest.fixture(scope="module")
def shot():
    """The box on a table seen from 1.2 m: the far side of the frame has no depth."""
    mesh = trimesh.creation.box(BOX)
    shot = shoot([(mesh, *resting(mesh, spin(20), 0.0, 0.0))], table(), SMALL, 45.0, 30.0, 1.2)
    assert not np.isfinite(shot.points).all(), "the frame has missing pixels"
    return shot


def frame_points(server, files, data=None, pixels=True):
    answer = server.client.post(
        "/points", files=files, data=data or {}, params={"pixels": str(pixels).lower()}
    )
    assert answer.status_code == 200, answer.text
    return answer


def test_points_give_an_organized_frame_s_pixels_as_detect_counts_them(server, shot):
    height, width = shot.shows.shape
    valid = np.flatnonzero(np.isfinite(shot.points.reshape(-1, 3)).all(axis=1))
    answer = frame_points(server, {"file": ("frame.pcd", shot.pcd())})
    count = int(answer.headers["X-Points"])
    assert count == len(valid) and answer.headers["X-Shape"] == f"{height},{width}"
    assert len(answer.content) == 16 * count
    points = np.frombuffer(answer.content[: 12 * count], "<f4").reshape(-1, 3)
    pixels = np.frombuffer(answer.content[12 * count :], "<u4")
    assert np.array_equal(pixels, valid)
    assert np.array_equal(points, shot.points.reshape(-1, 3)[valid])

    plain = frame_points(server, {"file": ("frame.pcd", shot.pcd())}, pixels=False)
    assert plain.content == answer.content[: 12 * count]  # unchanged without ?pixels

    depth = {"file": ("frame.png", shot.depth_png())}
    from_depth = frame_points(server, depth, shot.intrinsics)
    count = int(from_depth.headers["X-Points"])
    depth_pixels = np.frombuffer(from_depth.content[12 * count :], "<u4")
    assert np.array_equal(depth_pixels, valid) and from_depth.headers["X-Viewpoint"] == "0,0,0"

    detected = server.client.post("/detect", files={"file": ("frame.pcd", shot.pcd())})
    assert detected.status_code == 200, detected.text
    claimed = np.concatenate([d["indices"] for d in detected.json()["detections"]])
    assert len(claimed) and np.isin(claimed, pixels).all()  # every claim is a point drawn


def test_an_unorganized_cloud_has_no_pixels(server, shot):
    cloud = shot.points.reshape(-1, 3)
    cloud = cloud[np.isfinite(cloud).all(axis=1)][::7]
    buffer = io.BytesIO()
    np.save(buffer, cloud)
    answer = frame_points(server, {"file": ("cloud.npy", buffer.getvalue())})
    assert "X-Shape" not in answer.headers and len(answer.content) == 12 * len(cloud)
