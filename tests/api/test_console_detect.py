"""The console's view of POST /detect: a real server with a box registered, a frame of the box
on a table (tests/frames.py, an organized PCD with missing pixels) dropped on "Detect in a
frame" in Debian's Chromium, the detection listed and drawn; and what the console relies on,
POST /points?pixels=true giving each point's pixel, the indices /detect answers."""

from __future__ import annotations

import io
import re

import numpy as np
import pytest
import trimesh
from PIL import Image

from tests.api.test_console import Page, browser  # noqa: F401 - the browser fixture
from tests.conftest import server_holding
from tests.frames import resting, shoot, spin, table, without

BOX = (0.08, 0.06, 0.04)
SMALL = (320, 240, 262.5)  # a quarter of VGA: the same field of view, a quick /detect


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """A real server whose gallery holds one box, registered as an STL mesh."""
    server = server_holding(
        tmp_path_factory.mktemp("console-detect"), {"box-a": trimesh.creation.box(BOX)}
    )
    yield server
    server.stop()


@pytest.fixture(scope="module")
def shot():
    """The box on a table seen from 1.2 m: the far side of the frame has no depth."""
    mesh = trimesh.creation.box(BOX)
    shot = shoot([(mesh, *resting(mesh, spin(20), 0.0, 0.0))], table(), SMALL, 45.0, 30.0, 1.2)
    assert not np.isfinite(shot.points).all(), "the frame has missing pixels"
    return shot


@pytest.fixture(scope="module")
def detected(server, shot) -> dict:
    """The frame's /detect answer over HTTP, as a script would get it."""
    answer = server.client.post("/detect", files={"file": ("frame.pcd", shot.pcd())})
    assert answer.status_code == 200, answer.text
    return answer.json()


def frame_points(server, files, data=None, pixels=True):
    answer = server.client.post(
        "/points", files=files, data=data or {}, params={"pixels": str(pixels).lower()}
    )
    assert answer.status_code == 200, answer.text
    return answer


def test_points_give_an_organized_frame_s_pixels_as_detect_counts_them(server, shot, detected):
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

    claimed = np.concatenate([d["indices"] for d in detected["detections"]])
    assert len(claimed) and np.isin(claimed, pixels).all()  # every claim is a point drawn


def test_an_unorganized_cloud_has_no_pixels(server, shot):
    cloud = shot.points.reshape(-1, 3)
    cloud = cloud[np.isfinite(cloud).all(axis=1)][::7]
    buffer = io.BytesIO()
    np.save(buffer, cloud)
    answer = frame_points(server, {"file": ("cloud.npy", buffer.getvalue())})
    assert "X-Shape" not in answer.headers and len(answer.content) == 12 * len(cloud)


# the console's verdict colours (console.css, frame.js), as a screenshot shows them
VERDICT_RGB = {"match": (0x2F, 0xB3, 0x66), "uncertain": (0xE0, 0xA5, 0x26)}


def coloured(png: bytes, verdict: str) -> int:
    """Pixels of a verdict's reference colour in a screenshot; a claimed point's tint, nearer
    the frame's grey, is not counted."""
    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).reshape(-1, 3).astype(int)
    return int((np.abs(pixels - VERDICT_RGB[verdict]).max(axis=1) <= 12).sum())


def chip_rgb(item) -> tuple[int, ...]:
    """A listed detection's verdict chip's background, as the browser paints it."""
    style = item.locator(".chip").evaluate("(chip) => getComputedStyle(chip).backgroundColor")
    return tuple(int(v) for v in re.findall(r"\d+", style)[:3])


def test_a_dropped_frame_is_detected_listed_and_drawn(server, shot, detected, browser):  # noqa: F811
    tab = Page(browser, server.url)
    page = tab.page
    page.wait_for_selector("body[data-state=ready]", timeout=30_000)
    tab.drop("detect-drop", "frame.pcd", shot.pcd(compressed=True))
    page.wait_for_selector("#view[data-drawn=detection]", timeout=60_000)

    (expected,) = detected["detections"]
    assert expected["label"] == "box-a" and expected["verdict"] == "match", expected
    (item,) = page.locator("#detections li.detection").all()
    assert item.get_attribute("data-label") == "box-a"
    assert item.get_attribute("data-verdict") == "match"
    assert chip_rgb(item) == VERDICT_RGB["match"]
    text = item.inner_text()
    assert text.startswith("MATCH") and "confidence" in text
    claimed = int(re.search(r"(\d+) points", text).group(1))
    assert claimed == expected["num_points"]
    # the claimed pixels placed on the frame's points: the centre of those very pixels
    centre = np.array(item.get_attribute("data-centre").split(","), float)
    pixels = shot.points.reshape(-1, 3)[expected["indices"]]
    assert np.abs(centre - pixels.mean(axis=0)).max() < 1e-5, centre
    assert (shot.shows.reshape(-1)[expected["indices"]] == 0).mean() > 0.9  # the box's pixels

    view = page.locator("#view")
    valid = int(np.isfinite(shot.points[..., 0]).sum())
    assert view.get_attribute("data-frame") == view.get_attribute("data-drawn-points") == str(valid)
    assert int(view.get_attribute("data-tinted")) == claimed > 50
    reference = server.client.get("/references/box-a").json()["num_points"]
    assert view.get_attribute("data-references") == str(reference)
    drawn = coloured(view.screenshot(), "match")
    assert drawn > 100, drawn  # the reference at its pose, in the match's green

    item.click()  # picks it out: listed as selected, its pose's details shown, drawn larger
    assert view.get_attribute("data-selected") == "0"
    assert "selected" in item.get_attribute("class") and "translation" in item.inner_text()
    assert coloured(view.screenshot(), "match") > drawn

    # a confidence no detection reaches: the same box answered uncertain, drawn in amber
    doubted = server.client.post(
        "/detect", files={"file": ("frame.pcd", shot.pcd())}, data={"min_confidence": "1"}
    )
    (expected,) = doubted.json()["detections"]
    assert expected["verdict"] == "uncertain" and expected["reasons"], doubted.text
    page.fill("#min-confidence", "1")
    tab.drop("detect-drop", "frame.pcd", shot.pcd(compressed=True))
    page.wait_for_selector("#detections li.detection[data-verdict=uncertain]", timeout=60_000)
    (item,) = page.locator("#detections li.detection").all()
    text = item.inner_text()
    assert text.startswith("UNCERTAIN") and all(r in text for r in expected["reasons"]), text
    assert chip_rgb(item) == VERDICT_RGB["uncertain"]
    picture = view.screenshot()
    assert coloured(picture, "uncertain") > 100 and coloured(picture, "match") == 0
    assert tab.errors == []


def test_a_frame_missing_every_other_row_is_drawn_whole(server, browser):  # noqa: F811
    """An interlaced frame of more points than the console draws: thinned to a point a block
    of pixels, not to every other row, which it has none on."""
    mesh = trimesh.creation.box(BOX)
    placed = [(mesh, *resting(mesh, spin(20), 0.0, 0.0))]
    whole = shoot(placed, table(), (1280, 960, 1050.0), 60.0, 30.0, 0.8)
    rows = np.arange(960)[:, None].repeat(1280, axis=1)
    shot = without(whole, rows % 2 == 0)
    valid = int(np.isfinite(shot.points[..., 0]).sum())
    assert valid > 320_000, valid  # more than the console draws (frame.js, MAX_DRAWN)
    tab = Page(browser, server.url)
    page = tab.page
    page.wait_for_selector("body[data-state=ready]", timeout=30_000)
    tab.drop("detect-drop", "frame.pcd", shot.pcd(compressed=True))
    page.wait_for_selector("#view[data-drawn=detection]", timeout=120_000)
    view = page.locator("#view")
    assert view.get_attribute("data-frame") == str(valid)
    drawn = int(view.get_attribute("data-drawn-points"))
    assert 0.4 * valid < drawn <= 320_000, drawn  # a point a 2 x 2 block: half of them
    assert tab.errors == []
