"""The README's sample cloud, posted as its curl example posts it, gets the right label.

``models/sample_cloud.json`` and its true pose come from ``scripts/make_sample.py``. The server
is the real app on a loopback port (``tests.servers.Server``) with the shipped model and seed
gallery; skipped when the model or the sample is missing.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.api.parsers import read_points
from service.settings import MODELS_DIR, GallerySettings, Settings
from tests.servers import MODEL, Server, needs_model

SAMPLE = MODELS_DIR / "sample_cloud.json"
SAMPLE_PCD = MODELS_DIR / "sample_cloud.pcd"  # the same points, for the console and dpc-mn
POSE = MODELS_DIR / "sample_cloud_pose.json"

pytestmark = pytest.mark.skipif(
    not (SAMPLE.exists() and POSE.exists()),
    reason="no sample cloud: run python scripts/make_sample.py",
)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    gallery = GallerySettings(data_dir=tmp_path_factory.mktemp("data"))
    running = Server(Settings(model=MODEL, gallery=gallery))
    yield running
    running.stop()


def test_the_sample_file_is_a_valid_align_body():
    body = json.loads(SAMPLE.read_text())
    points = np.asarray(body["points"], dtype=np.float64)
    assert set(body) == {"points"} and points.shape == (2048, 3) and np.isfinite(points).all()
    pose = json.loads(POSE.read_text())
    rotation = np.asarray(pose["rotation"])
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(rotation) == pytest.approx(1.0)


def test_the_sample_pcd_holds_the_same_points():
    points = read_points(SAMPLE_PCD.read_bytes(), SAMPLE_PCD.name, 2048, 10_000)
    expected = np.asarray(json.loads(SAMPLE.read_text())["points"], dtype=np.float32)
    np.testing.assert_array_equal(points, expected)


@needs_model
def test_the_sample_is_recognised(server):
    pose = json.loads(POSE.read_text())
    names = [r["name"] for r in server.client.get("/references").json()["references"]]
    if pose["label"] not in names:
        pytest.skip(f"the seed gallery has no reference {pose['label']!r}")
    response = server.client.post(
        "/align",
        content=SAMPLE.read_bytes(),  # as curl --data @models/sample_cloud.json sends it
        headers={"content-type": "application/json"},
    )
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["label"] == pose["label"], body["candidates"]
    # the right object placed well enough to explain the cloud (the resampling floor is ~0.03)
    assert body["alignment_error_normalized"] < 0.1, body
