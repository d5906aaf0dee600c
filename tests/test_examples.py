"""The README's quick-start files (``examples/``, from ``scripts/make_examples.py``): the part
registers from its STL, and its depth image with the mask, its scan and its raw float32 cloud
are each answered as that part, near the pose ``examples/truth.json`` records."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.conftest import REPO

EXAMPLES = REPO / "examples"
TRUTH = json.loads((EXAMPLES / "truth.json").read_text())
CAMERA = {k: str(v) for k, v in json.loads((EXAMPLES / "camera.json").read_text()).items()}
INTRINSICS = {k: CAMERA[k] for k in ("fx", "fy", "cx", "cy")}
PART = TRUTH["part"]


def read(name: str) -> tuple[str, bytes]:
    return name, (EXAMPLES / name).read_bytes()


@pytest.fixture(scope="module")
def registered(service):
    answer = service.client.post(
        "/references",
        data={"name": PART},
        files={"file": read("panda-link5.stl")},
        params={"self_check": "false"},
    )
    assert answer.status_code == 201, answer.text
    yield service
    service.client.delete(f"/references/{PART}")


def near_the_truth(answer, example: str) -> None:
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert body["label"] == PART, body["candidates"]
    truth = TRUTH[example]
    turned = np.asarray(body["rotation"]).T @ np.asarray(truth["rotation"])
    assert np.degrees(Rotation.from_matrix(turned).magnitude()) < 2.0, body
    shift = np.linalg.norm(np.subtract(body["translation"], truth["translation"]))
    assert shift < 0.02 * TRUTH["scale"], body


def test_the_depth_image_with_its_mask(registered):
    files = {"file": read("depth.png"), "mask": read("part-mask.png")}
    near_the_truth(registered.client.post("/align", data=INTRINSICS, files=files), "depth.png")


def test_the_depth_image_without_its_mask_is_refused_naming_the_mask(registered):
    answer = registered.client.post("/align", data=INTRINSICS, files={"file": read("depth.png")})
    assert answer.status_code == 422 and "mask" in answer.json()["detail"], answer.text


def test_the_scan_seen_from_its_camera(registered):
    answer = registered.client.post(
        "/align", data={"viewpoint": "0,0,0"}, files={"file": read("scan.ply")}
    )
    near_the_truth(answer, "scan.ply")


def test_the_raw_float32_cloud(registered):
    answer = registered.client.post(
        "/align",
        content=read("cloud.f32")[1],
        params={"candidates": PART},
        headers={"content-type": "application/octet-stream"},
    )
    near_the_truth(answer, "cloud.f32")
