"""Logs: one JSON object a line with the request's fields, a request id in and out, and never
a key or a point in them, even at DEBUG level."""

from __future__ import annotations

import json
import logging
import re

import numpy as np

from service.api.logs import JsonFormatter, RequestIdFilter, request_id
from tests.servers import ProcessServer, cloud, needs_model

pytestmark = needs_model

ADMIN, READ = "Adm1n-Key-QWERTY-55", "Re4d-Key-ZXCVB-77"
WRONG = "Wr0ng-Key-POIUY-99"
MARK = 4321.8765  # a coordinate that must never reach the logs


MARKED = cloud(200, seed=3).astype(np.float64)  # float64: the mark's digits as written
MARKED[5] = MARK


def test_the_access_log_is_json_with_request_ids_and_no_secrets(tmp_path):
    keys = json.dumps({ADMIN: "admin", READ: "read"})
    log_path = tmp_path / "service.log"
    server = ProcessServer(tmp_path / "data", log_path, auth__keys=keys, server__log_level="debug")
    try:
        client = server.client
        traced = client.get(
            "/references", headers={"Authorization": f"Bearer {ADMIN}", "X-Request-ID": "cell-7.42"}
        )
        assert traced.status_code == 200 and traced.headers["x-request-id"] == "cell-7.42"
        fresh = client.get("/health")
        assert re.fullmatch(r"[0-9a-f]{32}", fresh.headers["x-request-id"])
        odd = client.get("/health", headers={"X-Request-ID": "has spaces and {braces}"})
        assert re.fullmatch(r"[0-9a-f]{32}", odd.headers["x-request-id"])
        assert client.get("/references", headers={"X-API-Key": WRONG}).status_code == 401
        aligned = client.post(
            "/align", json={"points": MARKED.tolist()}, headers={"X-API-Key": READ}
        )
        assert aligned.status_code == 200, aligned.text
        body = json.dumps(
            {"name": "marked", "points": [*MARKED.tolist(), [MARK, float("nan"), MARK]]}
        )
        refused = client.post(
            "/references",
            content=body,
            headers={"Authorization": f"Bearer {ADMIN}", "content-type": "application/json"},
        )
        assert refused.status_code == 422 and str(MARK) in refused.text  # told to the caller
        for response in (traced, fresh, aligned, refused):
            assert response.headers["x-request-id"]
    finally:
        server.stop()

    text = log_path.read_text()
    for secret in (ADMIN, READ, WRONG, str(MARK), "4321.87"):
        assert secret not in text, f"{secret} leaked into the logs"
    entries = [json.loads(line) for line in text.splitlines() if line.strip()]
    assert all({"time", "level", "message"} <= set(entry) for entry in entries)
    access = [entry for entry in entries if entry.get("logger") == "service.access"]
    for entry in access:
        assert {"request_id", "method", "path", "status", "duration_ms"} <= set(entry), entry
    (line,) = [entry for entry in access if entry["request_id"] == "cell-7.42"]
    assert line["method"] == "GET" and line["path"] == "/references" and line["status"] == 200
    statuses = {(entry["path"], entry["status"]) for entry in access}
    assert {("/references", 401), ("/align", 200), ("/references", 422)} <= statuses
    assert any("auth: 2 API key(s)" in entry["message"] for entry in entries)
    assert not any("OPEN MODE" in entry["message"] for entry in entries)


def test_log_lines_inside_a_request_carry_its_id():
    record = logging.LogRecord("service", logging.ERROR, __file__, 1, "failed %s", ("x",), None)
    token = request_id.set("abc-123")
    try:
        RequestIdFilter().filter(record)
    finally:
        request_id.reset(token)
    entry = json.loads(JsonFormatter().format(record))
    assert entry["request_id"] == "abc-123" and entry["message"] == "failed x"
    assert entry["level"] == "error" and entry["time"].endswith("+00:00")
