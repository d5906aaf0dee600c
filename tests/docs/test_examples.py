"""The README's quick-start files (``examples/``, from ``scripts/make_examples.py``): the part
registers from its STL, and its depth image (with its mask, or alone on its table), its scan and
its raw float32 cloud are each answered as that part, near the pose ``examples/truth.json``
records; ``/detect`` finds it in the whole depth image, on the mask's pixels."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[2]
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


def test_the_depth_image_alone_sets_its_table_aside(registered):
    answer = registered.client.post("/align", data=INTRINSICS, files={"file": read("depth.png")})
    near_the_truth(answer, "depth.png")
    table = TRUTH["depth.png"]["pixels"] - TRUTH["depth.png"]["part_pixels"]
    assert answer.json()["points_set_aside"] > 0.9 * table, answer.json()["points_set_aside"]


def test_the_whole_frame_through_detect_finds_the_part_in_its_mask(registered):
    answer = registered.client.post("/detect", data=INTRINSICS, files={"file": read("depth.png")})
    assert answer.status_code == 200, answer.text
    (found,) = answer.json()["detections"]
    assert found["label"] == PART and found["verdict"] == "match", found["reasons"]
    turned = np.asarray(found["rotation"]).T @ np.asarray(TRUTH["depth.png"]["rotation"])
    assert np.degrees(Rotation.from_matrix(turned).magnitude()) < 2.0
    mask = np.asarray(Image.open(EXAMPLES / "part-mask.png")).ravel() > 0
    pixels = np.asarray(found["indices"])  # row * width + col
    assert mask[pixels].mean() > 0.95 and mask[pixels].sum() > 0.9 * mask.sum()


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
