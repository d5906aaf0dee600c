"""POST /detect through real HTTP on a real server: frames built by hand (tests/frames.py) of
boxes and ducks on a table and in a bin, as a camera's driver writes them."""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from service.client import Client
from service.client.cli import main
from service.settings import LimitSettings
from tests.conftest import empty_server, server_holding
from tests.frames import VGA, bin_walls, registered, resting, shoot, spin, table
from tests.meshes import pybullet_mesh

BOX_A, BOX_B = (0.08, 0.06, 0.04), (0.10, 0.04, 0.03)


@pytest.fixture(scope="module")
def meshes() -> dict[str, trimesh.Trimesh]:
    duck = pybullet_mesh("duck.obj").copy()
    duck.apply_translation(-duck.vertices.mean(axis=0))
    duck.apply_scale(0.05 / np.linalg.norm(duck.vertices, axis=1).max())
    return {
        "box-a": trimesh.creation.box(BOX_A),
        "box-b": trimesh.creation.box(BOX_B),
        "duck": duck,
    }


@pytest.fixture(scope="module")
def server(tmp_path_factory, meshes):
    """A real server whose gallery holds the two boxes and the duck, registered as meshes."""
    server = server_holding(tmp_path_factory.mktemp("detect"), meshes)
    yield server
    server.stop()


def detect(server, shot, **fields):
    answer = server.client.post(
        "/detect", files={"file": ("frame.pcd", shot.pcd())}, data=fields, timeout=300.0
    )
    assert answer.status_code == 200, answer.text
    return answer.json()


def owners(shot, detection) -> np.ndarray:
    """Which placed part each of a detection's pixels shows (-1: none)."""
    return shot.shows.reshape(-1)[np.asarray(detection["indices"])]


def assert_disjoint(body):
    claimed = np.concatenate([d["indices"] for d in body["detections"]] or [[]])
    assert len(claimed) == len(np.unique(claimed)), "two detections claim one point"


def test_two_boxes_touching_on_a_table_are_two_detections(server, meshes):
    a = resting(meshes["box-a"], np.eye(3), 0.0, 0.0)
    b = resting(meshes["box-b"], spin(0), 0.0, (BOX_A[1] + BOX_B[1]) / 2)  # side against side
    shot = shoot([(meshes["box-a"], *a), (meshes["box-b"], *b)], table())
    body = detect(server, shot)
    assert sorted(d["label"] for d in body["detections"]) == ["box-a", "box-b"], body
    for k, label in enumerate(("box-a", "box-b")):
        (found,) = [d for d in body["detections"] if d["label"] == label]
        assert np.mean(owners(shot, found) == k) > 0.9  # its own box's pixels
        assert np.linalg.norm(np.subtract(found["translation"], shot.poses[k][1])) < 0.01
    assert_disjoint(body)


def test_three_ducks_in_a_bin_one_lying_on_another_are_three(server, meshes):
    duck = meshes["duck"]
    turn = Rotation.from_euler("xz", [90, 40], degrees=True).as_matrix()
    first = resting(duck, np.eye(3), -0.07, -0.05)
    second = resting(duck, spin(120), 0.07, 0.06)
    top = (duck.vertices @ first[0].T + first[1])[:, 2].max()
    third = resting(duck, turn, -0.06, -0.04, z=top)  # lying on the first
    shot = shoot([(duck, *first), (duck, *second), (duck, *third)], bin_walls(), elevation_deg=75)
    body = detect(server, shot)
    ducks = [d for d in body["detections"] if d["label"] == "duck"]
    assert len(ducks) == 3, body
    shown = sorted(int(np.bincount(owners(shot, d) + 1).argmax()) - 1 for d in ducks)
    assert shown == [0, 1, 2]  # each a different duck
    assert_disjoint(body)


def test_metrics_count_the_detections_by_verdict(server, meshes):
    def counted() -> float:
        text = server.client.get("/metrics").text
        lines = [line for line in text.splitlines() if line.startswith("dpc_detections_total")]
        matched = [line for line in lines if 'verdict="match"' in line]
        return float(matched[0].split()[-1]) if matched else 0.0

    before = counted()
    a = resting(meshes["box-a"], spin(10), -0.12, 0.0)
    body = detect(server, shoot([(meshes["box-a"], *a)], table()))
    matches = sum(d["verdict"] == "match" for d in body["detections"])
    assert matches == 1
    assert counted() == before + matches


def test_an_empty_table_gives_no_detection(server):
    shot = shoot([], table())
    body = detect(server, shot)
    assert body["detections"] == []
    assert body["num_points"] == int(np.isfinite(shot.points[..., 0]).sum())
    assert body["supports"], "the table is set aside as a support"


def test_missing_pixels_are_skipped_and_not_counted(server, meshes):
    a = resting(meshes["box-a"], spin(20), 0.0, 0.0)
    shot = shoot([(meshes["box-a"], *a)], table(), elevation_deg=45, distance=1.2)
    valid = int(np.isfinite(shot.points[..., 0]).sum())
    assert valid < shot.points.shape[0] * shot.points.shape[1]  # the frame has missing pixels
    for compressed in (False, True):
        answer = server.client.post(
            "/detect", files={"file": ("frame.pcd", shot.pcd(compressed))}, timeout=300.0
        )
        assert answer.status_code == 200, answer.text
        assert answer.json()["num_points"] == valid
    depth = server.client.post(
        "/detect",
        files={"file": ("depth.png", shot.depth_png())},
        data={k: str(v) for k, v in shot.intrinsics.items()},
        timeout=300.0,
    )
    assert depth.status_code == 200, depth.text
    body = depth.json()
    assert body["num_points"] == valid  # 0 pixels skipped
    assert [d["label"] for d in body["detections"] if d["verdict"] == "match"] == ["box-a"]
    width = shot.camera[0]
    pixels = np.asarray(body["detections"][0]["indices"])
    assert np.mean(shot.shows[pixels // width, pixels % width] == 0) > 0.9


def test_a_depth_image_registered_to_a_larger_colour_image_is_searched(server, meshes):
    """Registered to a colour image 2.1 times its size and not filled, as ROS's
    depth_image_proc does by default: a point on about one pixel in four, in a pattern that
    drifts. Such a frame's supports were not found, and its table was answered as parts."""
    a = resting(meshes["box-a"], spin(20), 0.0, 0.0)
    shot = registered(shoot([(meshes["box-a"], *a)], table()), 2.1)
    body = detect(server, shot)
    assert [d["label"] for d in body["detections"] if d["verdict"] == "match"] == ["box-a"]
    (found,) = [d for d in body["detections"] if d["label"] == "box-a"]
    assert np.mean(owners(shot, found) == 0) > 0.9
    assert np.linalg.norm(np.subtract(found["translation"], shot.poses[0][1])) < 0.01
    assert body["supports"], "the table is set aside"
    assert body["num_points"] == int(np.isfinite(shot.points[..., 0]).sum())


def test_pixels_without_depth_written_as_zeros_are_skipped(server, meshes):
    """A frame's vertices as RealSense's SDK gives them, saved as NPY: (0, 0, 0) where there
    is no depth. Such a frame was a 500 (its pixel angle NaN)."""
    a = resting(meshes["box-a"], spin(20), 0.0, 0.0)
    shot = shoot([(meshes["box-a"], *a)], table(), elevation_deg=45, distance=1.2)
    buffer = io.BytesIO()
    np.save(buffer, np.nan_to_num(shot.points, nan=0.0))
    answer = server.client.post(
        "/detect", files={"file": ("frame.npy", buffer.getvalue())}, timeout=300.0
    )
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert body["num_points"] == int(np.isfinite(shot.points[..., 0]).sum())
    assert [d["label"] for d in body["detections"] if d["verdict"] == "match"] == ["box-a"]


def test_a_frame_in_millimetres_says_so(server, meshes):
    """A camera that writes its frames in millimetres (as many industrial ones do), with
    the references in metres: the same empty list as a frame holding no part, before."""
    a = resting(meshes["box-a"], spin(20), 0.0, 0.0)
    shot = shoot([(meshes["box-a"], *a)], table())
    buffer = io.BytesIO()
    np.save(buffer, shot.points * 1000)
    answer = server.client.post(
        "/detect", files={"file": ("frame.npy", buffer.getvalue())}, timeout=300.0
    )
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert body["detections"] == []
    assert len(body["reasons"]) == 1 and "probably in millimetres" in body["reasons"][0]


@pytest.fixture(scope="module")
def limited(tmp_path_factory, meshes):
    """A real server that takes at most 200,000 valid points, holding box-a."""
    server = server_holding(
        tmp_path_factory.mktemp("limited"),
        {"box-a": meshes["box-a"]},
        limits=LimitSettings(max_points=200_000),
    )
    yield server
    server.stop()


def test_a_region_of_interest_counts_only_its_points_against_the_limit(limited, meshes):
    """A camera of more pixels than the limit, searched in a region: only the points inside
    count (up to twice the limit in the frame). Before, the frame was refused, its roi
    ignored, though the refusal said to send one."""
    a = resting(meshes["box-a"], spin(20), 0.0, 0.0)
    shot = shoot([(meshes["box-a"], *a)], table())
    valid = int(np.isfinite(shot.points[..., 0]).sum())
    assert 200_000 < valid <= 400_000, valid
    post = limited.client.post
    whole = post("/detect", files={"file": ("frame.pcd", shot.pcd())}, timeout=300.0)
    assert whole.status_code == 422 and "region of interest (roi)" in whole.json()["detail"]
    centre = shot.poses[0][1]
    roi = ",".join(f"{v:.4f}" for v in (*(centre - 0.1), *(centre + 0.1)))
    body = detect(limited, shot, roi=roi)
    assert [d["label"] for d in body["detections"] if d["verdict"] == "match"] == ["box-a"]
    everything = ",".join(["-9", "-9", "-9", "9", "9", "9"])
    wide = post("/detect", files={"file": ("frame.pcd", shot.pcd())}, data={"roi": everything})
    assert wide.status_code == 422
    assert f"the region of interest holds {valid} of the frame's valid points" in wide.text


def test_a_frame_of_2048_by_1536_pixels_is_accepted(server, meshes):
    a = resting(meshes["box-a"], spin(10), -0.1, 0.0)
    b = resting(meshes["box-b"], spin(-30), 0.12, 0.05)
    camera = (2048, 1536, VGA[2] * 2048 / VGA[0])
    shot = shoot([(meshes["box-a"], *a), (meshes["box-b"], *b)], table(), camera=camera)
    body = detect(server, shot)
    assert body["num_points"] == int(np.isfinite(shot.points[..., 0]).sum()) > 2_000_000
    assert sorted(d["label"] for d in body["detections"]) == ["box-a", "box-b"]


def test_the_region_of_interest_is_all_that_is_searched(server, meshes):
    a = resting(meshes["box-a"], spin(10), -0.12, 0.0)
    b = resting(meshes["box-b"], spin(-30), 0.12, 0.05)
    shot = shoot([(meshes["box-a"], *a), (meshes["box-b"], *b)], table())
    centre = shot.poses[1][1]
    low, high = centre - 0.09, centre + 0.09
    body = detect(server, shot, roi=",".join(f"{v:.4f}" for v in (*low, *high)))
    assert [d["label"] for d in body["detections"]] == ["box-b"]
    points = shot.points.reshape(-1, 3)
    inside = np.all((points >= low) & (points <= high), axis=1)
    assert body["num_points"] == int(inside.sum())
    assert inside[np.asarray(body["detections"][0]["indices"])].all()
    # a box beside the frame (in millimetres, say): nothing to search, and where the points are
    body = detect(server, shot, roi=",".join(f"{v:.4f}" for v in (*low * 1000, *high * 1000)))
    assert body["detections"] == [] and body["num_points"] < 60
    (said,) = body["reasons"]
    assert "the region of interest" in said and "the frame's points lie within" in said


@pytest.mark.parametrize(
    "request_kwargs, status, says",
    [
        ({"json": {"points": []}}, 422, "empty"),
        ({"json": {"points": [[0, 0, 0]] * 40, "max_instances": 0}}, 422, "max_instances"),
        (
            {
                "json": {
                    "points": [[0.0, 0, 1], [1, 0, 1]] * 20,
                    "roi": {"min": [1] * 3, "max": [0] * 3},
                }
            },
            422,
            "max",
        ),
        (
            {
                "json": {
                    "points": [[0.0, 0, 1], [1, 0, 1], [0, 1, 1], [0, 0, 2]] * 10,
                    "candidates": ["nothing"],
                }
            },
            404,
            "nothing",
        ),
        ({"params": {"roi": "1,2,3"}, "content": b"\0" * 480}, 422, "six"),
        ({"json": {"points": [[0.0, 0, 1], [1, 0, 1]] * 20, "colour": 1}}, 422, "colour"),
    ],
)
def test_bad_input_is_refused_as_for_align(server, request_kwargs, status, says):
    if "content" in request_kwargs:
        request_kwargs["headers"] = {"Content-Type": "application/octet-stream"}
    answer = server.client.post("/detect", **request_kwargs)
    assert answer.status_code == status, answer.text
    assert says in answer.json()["detail"]


def test_an_empty_gallery_is_a_409(tmp_path):
    empty = empty_server(tmp_path)
    try:
        answer = empty.client.post(
            "/detect", json={"points": [[0.0, 0, 1], [1, 0, 1], [0, 1, 1], [0, 0, 2]] * 10}
        )
        assert answer.status_code == 409
        assert "register" in answer.json()["detail"]
    finally:
        empty.stop()


def test_the_client_and_the_cli_detect_in_a_frame(server, meshes, tmp_path, capsys):
    a = resting(meshes["box-a"], spin(30), 0.02, -0.01)
    shot = shoot([(meshes["box-a"], *a)], table())
    frame = tmp_path / "frame.pcd"
    frame.write_bytes(shot.pcd())
    with Client(server.url, retry_for=0) as client:
        from_file = client.detect(frame)
        valid = shot.points.reshape(-1, 3)
        from_points = client.detect(valid[np.isfinite(valid[:, 0])], max_instances=1)
    for scene in (from_file, from_points):
        assert [d.label for d in scene.matches] == ["box-a"], scene.raw
        (found,) = scene.matches
        assert np.linalg.norm(found.translation - shot.poses[0][1]) < 0.01
    assert np.mean(owners(shot, from_file.raw["detections"][0]) == 0) > 0.9  # pixels, as sent
    assert main(["detect", str(frame), "--url", server.url]) == 0
    assert "match: box-a" in capsys.readouterr().out
    empty = tmp_path / "empty.pcd"
    empty.write_bytes(shoot([], table()).pcd())
    assert main(["detect", str(empty), "--url", server.url, "--json"]) == 3  # nothing to act on
    assert '"detections": []' in capsys.readouterr().out
