"""Issue 35's real-frame check: a Kinect-class frame from PCL's test data (tests/data/real/
pcl-milk, BSD), posted as its driver wrote it to POST /detect of a real server holding the milk
carton's model, is answered with the carton as a "match" at its known pose, claiming its pixels.

The frame is PCL's own: an organized 640 x 480 binary_compressed PCD with an rgba field and
65,793 pixels without a depth. The model is the carton's points cut from that frame, so the
reference pose is the identity and the carton's pixels are known exactly (frame.json).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from pypcd4 import PointCloud
from scipy.spatial import cKDTree

from evaluation.metrics import geodesic_deg
from tests.conftest import empty_server

FIXTURE = Path(__file__).resolve().parents[1] / "data" / "real" / "pcl-milk"


@pytest.fixture(scope="module")
def fixture() -> dict:
    return json.loads((FIXTURE / "frame.json").read_text())


@pytest.fixture(scope="module")
def milk_server(tmp_path_factory, fixture):
    """A real server with the carton's model registered as its PCD file."""
    server = empty_server(tmp_path_factory.mktemp("real-frame"))
    model = FIXTURE / fixture["model"]
    answer = server.client.post(
        "/references",
        data={"name": fixture["label"]},
        files={"file": (model.name, model.read_bytes())},
        params={"self_check": "false"},
    )
    assert answer.status_code == 201, answer.text
    yield server
    server.stop()


def carton_pixels(fixture: dict) -> np.ndarray:
    """The frame's pixels (row * 640 + column) that are the model's points."""
    scene = PointCloud.from_path(FIXTURE / fixture["scene"]).numpy(("x", "y", "z"))
    model = PointCloud.from_path(FIXTURE / fixture["model"]).numpy(("x", "y", "z"))
    valid = np.flatnonzero(np.isfinite(scene).all(axis=1))
    distance, nearest = cKDTree(scene[valid]).query(model)
    assert (distance == 0).all()  # the model is the frame's own points
    return valid[nearest]


@pytest.mark.slow
def test_the_real_kinect_frame_shows_the_milk_carton_at_its_pose(milk_server, fixture):
    scene = FIXTURE / fixture["scene"]
    answer = milk_server.client.post(
        "/detect", files={"file": (scene.name, scene.read_bytes())}, timeout=300.0
    )
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert body["num_points"] == 241407  # the valid pixels only
    matches = [d for d in body["detections"] if d["verdict"] == "match"]
    assert [d["label"] for d in matches] == [fixture["label"]], body["detections"]
    milk = matches[0]
    expected, truth = fixture["expected"], fixture["reference_pose"]
    assert geodesic_deg(milk["rotation"], truth["rotation"]) < expected["rotation_deg"]
    offset = np.subtract(milk["translation"], truth["translation"])
    assert np.linalg.norm(offset) < expected["translation_m"]
    claimed = np.asarray(milk["indices"])
    assert claimed.min() >= 0 and claimed.max() < 640 * 480  # pixel indices
    carton = carton_pixels(fixture)
    both = np.intersect1d(claimed, carton).size
    assert both / carton.size >= expected["pixels_found_share"]
    assert both / claimed.size >= expected["pixels_precision"]
