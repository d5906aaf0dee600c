"""A collinear cloud (issue 33: answered "one plane ... send centimetres") is said to lie on
one line: refused whole, and answered no_match when a line is what is left once strays are set
aside. Against a real server."""

from __future__ import annotations

import numpy as np


def line(count: int = 800) -> np.ndarray:
    """A part-sized straight line: 20 cm along (2, 1, 0.4), half a metre from the camera."""
    t = np.linspace(-0.1, 0.1, count)[:, None]
    return t * np.array([1.0, 0.5, 0.2]) + np.array([0.1, 0.0, 0.5])


def test_a_collinear_cloud_is_said_to_lie_on_one_line(service):
    """It was answered "one plane ... send centimetres" (a tenth of its size: the unit hint)."""
    for points in (line(), line() / 10):
        answer = service.client.post("/align", json={"points": points.tolist()})
        assert answer.status_code == 422, answer.text[:300]
        detail = answer.json()["detail"]
        assert "lie on one line" in detail
        assert "plane" not in detail and "centimetres" not in detail
    before = service.client.get("/references").json()
    refused = service.client.post("/references", json={"name": "a-line", "points": line().tolist()})
    assert refused.status_code == 422 and "one line" in refused.json()["detail"]
    assert service.client.get("/references").json() == before


def test_a_line_left_once_strays_are_set_aside_is_no_match(service):
    """The strays give the cloud a width; set aside, a line is left: said so, not posed."""
    strays = np.array([[0.6, 0.3, 0.9], [0.62, 0.3, 0.9], [0.6, 0.32, 0.9]])
    points = np.concatenate([line(), strays])
    answer = service.client.post("/align", json={"points": points.tolist()})
    assert answer.status_code == 200, answer.text[:300]
    body = answer.json()
    assert body["verdict"] == "no_match" and body["points_set_aside"] == 3
    assert any("lie on one line" in reason for reason in body["reasons"])
    assert not any("plane" in reason or "centimetres" in reason for reason in body["reasons"])
