"""A part that jumps in depth cut into three segments, none of which the search poses alone
and no pair of which it poses: found by searching a failed segment with all its failed
neighbours (``scene.Scan.joined``; docs/decisions.md#a-part-cut-in-three).

The frame is the report's scene-0-0015 (tests/data/frames), posted as its depth PNG with its
intrinsics to a real server holding the shipped gallery and pybullet's random object 750.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from evaluation.metrics import add_s, diameter
from service.engine.sampling import sample_surface
from service.settings import GallerySettings, Settings
from tests.meshes import pybullet_mesh
from tests.servers import Server

FRAME = Path(__file__).resolve().parents[1] / "data" / "frames" / "scene-0-0015"
PART = "random-750"


@pytest.fixture(scope="module")
def truth() -> dict:
    return json.loads((FRAME / "truth.json").read_text())


@pytest.fixture(scope="module")
def part_mesh(truth):
    instance = next(i for i in truth["instances"] if i["name"] == PART)
    mesh = pybullet_mesh("random_urdfs/750/750.obj")
    mesh.apply_scale(instance["scale"])
    return mesh


@pytest.fixture(scope="module")
def server(tmp_path_factory, part_mesh):
    """The shipped gallery, and random-750 registered from its rescaled mesh."""
    gallery = GallerySettings(data_dir=tmp_path_factory.mktemp("cut"), self_check_poses=1)
    server = Server(Settings(gallery=gallery))
    answer = server.client.post(
        "/references",
        data={"name": PART},
        files={"file": (f"{PART}.stl", part_mesh.export(file_type="stl"), "model/stl")},
    )
    assert answer.status_code == 201, answer.text
    yield server
    server.stop()


@pytest.mark.slow
def test_a_part_cut_in_three_by_jumps_in_depth_is_found(server, truth, part_mesh):
    camera = json.loads((FRAME / "camera.json").read_text())
    answer = server.client.post(
        "/detect",
        files={"file": ("depth.png", (FRAME / "depth.png").read_bytes(), "image/png")},
        data={k: str(camera[k]) for k in ("fx", "fy", "cx", "cy")},
    )
    assert answer.status_code == 200, answer.text
    found = [d for d in answer.json()["detections"] if d["label"] == PART]
    assert [d["verdict"] for d in found] == ["match"]
    k, instance = next((k, i) for k, i in enumerate(truth["instances"]) if i["name"] == PART)
    points = sample_surface(part_mesh, 4096, 1).astype(np.float64)
    error = add_s(
        points,
        np.array(found[0]["rotation"]),
        np.array(found[0]["translation"]),
        np.array(instance["rotation"]),
        np.array(instance["translation"]),
        diameter(points),
    )
    assert error < 0.1
    labels = np.asarray(Image.open(FRAME / "labels.png")).ravel()
    claimed = labels[np.array(found[0]["indices"])]
    assert np.mean(claimed == k + 1) > 0.9  # its own pixels
    assert np.isin(np.flatnonzero(labels == k + 1), found[0]["indices"]).mean() > 0.8
