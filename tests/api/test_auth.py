"""API keys: every endpoint against every kind of caller, the three modes, the OpenAPI document."""

from __future__ import annotations

import io
import logging

import numpy as np
import pytest

from service.api import auth
from service.settings import AuthSettings, GallerySettings, Settings
from tests.servers import MODEL, Server, cloud, needs_model

pytestmark = needs_model

ADMIN, READ = "admin-key-0123456789", "read-key-9876543210"
KEYS = {ADMIN: "admin", READ: "read"}
CALLERS = {
    "none": {},
    "wrong key": {"Authorization": "Bearer not-a-key"},
    "read (bearer)": {"Authorization": f"Bearer {READ}"},
    "read (X-API-Key)": {"X-API-Key": READ},
    "admin (bearer)": {"Authorization": f"Bearer {ADMIN}"},
    "admin (X-API-Key)": {"X-API-Key": ADMIN},
}


def settings(tmp_path, **auth_settings) -> Settings:
    return Settings(
        model=MODEL.model_copy(update={"gallery": tmp_path / "no-seed.npz"}),  # quicker start
        gallery=GallerySettings(data_dir=tmp_path, reference_points=256, self_check_poses=0),
        auth=AuthSettings(**auth_settings),
    )


@pytest.fixture(scope="module")
def keyed(tmp_path_factory):
    """A server with the two keys and one reference, ``seed``, that no test removes."""
    server = Server(settings(tmp_path_factory.mktemp("keyed"), keys=KEYS))
    seeded = server.client.post(
        "/references",
        json={"name": "seed", "points": cloud(seed=0).tolist()},
        headers=CALLERS["admin (bearer)"],
    )
    assert seeded.status_code == 201, seeded.text
    yield server
    server.stop()


def name_of(case: str) -> str:
    return "part-" + "".join(c for c in case if c.isalnum())


def prepare(client, operation: str, case: str) -> None:
    if operation == "delete" and case.startswith("admin"):  # something of its own to delete
        client.post(
            "/references?replace=true",
            json={"name": name_of(case) + "-d", "points": cloud(seed=3).tolist()},
            headers=CALLERS["admin (bearer)"],
        )


def call(client, operation: str, headers: dict, case: str):
    """One request of each operation, on names unique to the caller so all can succeed."""
    name = name_of(case)
    if operation == "list":
        return client.get("/references", headers=headers)
    if operation == "describe":
        return client.get("/references/seed", headers=headers)
    if operation == "align":
        return client.post("/align", json={"points": cloud(seed=1).tolist()}, headers=headers)
    if operation == "register":
        body = {"name": name, "points": cloud(seed=2).tolist()}
        return client.post("/references", json=body, headers=headers)
    if operation == "delete":  # an admin its own reference; any other caller tries ``seed``
        target = f"{name}-d" if case.startswith("admin") else "seed"
        return client.delete(f"/references/{target}", headers=headers)
    if operation == "read a file":
        return client.post(
            "/points", files={"file": ("a.npy", npy(cloud(seed=4)))}, headers=headers
        )
    if operation == "reference points":
        return client.get("/references/seed/points", headers=headers)
    if operation == "self-check":
        return client.get("/references/seed/self_check?poses=1", headers=headers)
    if operation == "recent alignments":
        return client.get("/alignments", headers=headers)
    raise AssertionError(operation)


def npy(points: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.asarray(points, dtype=np.float32))
    return buffer.getvalue()


EXPECTED = {  # operation -> caller -> status
    "list": [401, 401, 200, 200, 200, 200],
    "describe": [401, 401, 200, 200, 200, 200],
    "align": [401, 401, 200, 200, 200, 200],
    "register": [401, 401, 403, 403, 201, 201],
    "delete": [401, 401, 403, 403, 204, 204],
    "read a file": [401, 401, 200, 200, 200, 200],
    "reference points": [401, 401, 200, 200, 200, 200],
    "self-check": [401, 401, 200, 200, 200, 200],
    "recent alignments": [401, 401, 200, 200, 200, 200],
}


@pytest.mark.parametrize("operation", list(EXPECTED))
def test_every_operation_needs_the_right_role(keyed, operation):
    client = keyed.client
    for (case, headers), expected in zip(CALLERS.items(), EXPECTED[operation], strict=True):
        prepare(client, operation, case)
        before = client.get("/references", headers=CALLERS["read (bearer)"]).json()
        response = call(client, operation, headers, case)
        assert response.status_code == expected, (operation, case, response.text)
        if expected in (401, 403):
            assert set(response.json()) == {"detail"}
            after = client.get("/references", headers=CALLERS["read (bearer)"]).json()
            assert after == before, "a refused request changed the gallery"
        if expected == 401:
            assert response.headers["www-authenticate"] == "Bearer"
            assert "Authorization: Bearer" in response.json()["detail"]
        if expected == 403:
            assert "'admin'" in response.json()["detail"]


def test_a_refused_caller_gets_401_before_its_body_is_read(keyed):
    garbage = keyed.client.post(
        "/references", content=b"{not json", headers={"content-type": "application/json"}
    )
    assert garbage.status_code == 401
    raw = keyed.client.post(
        "/align", content=b"\0" * 7, headers={"content-type": "application/octet-stream"}
    )
    assert raw.status_code == 401


def test_probes_health_metrics_and_docs_stay_open(keyed):
    for path in ("/health", "/v2/health/live", "/v2/health/ready", "/metrics", "/openapi.json"):
        assert keyed.client.get(path).status_code == 200, path
    assert keyed.client.get("/health").json()["auth"] == "keys"


def test_the_openapi_document_declares_the_schemes_and_roles(keyed):
    document = keyed.client.get("/openapi.json").json()
    schemes = document["components"]["securitySchemes"]
    assert schemes["HTTPBearer"] == {
        "type": "http",
        "scheme": "bearer",
        "description": schemes["HTTPBearer"]["description"],
    }
    assert schemes["APIKeyHeader"]["in"] == "header"
    assert schemes["APIKeyHeader"]["name"] == "X-API-Key"
    paths = document["paths"]
    roles = {
        ("/align", "post"): "read",
        ("/references", "get"): "read",
        ("/references/{name}", "get"): "read",
        ("/references", "post"): "admin",
        ("/references/{name}", "delete"): "admin",
    }
    for (path, method), role in roles.items():
        operation = paths[path][method]
        assert operation["security"] == [{"HTTPBearer": [role]}, {"APIKeyHeader": [role]}]
        assert "401" in operation["responses"]
        assert ("403" in operation["responses"]) == (role == "admin")
    for path in ("/health", "/v2/health/live", "/v2/health/ready"):
        assert "security" not in paths[path]["get"]


def test_reads_may_be_open_while_writes_need_an_admin_key(tmp_path):
    server = Server(settings(tmp_path, keys=KEYS, require_key_for_reads=False))
    try:
        client = server.client
        assert client.get("/health").json()["auth"] == "keys-for-writes"
        body = {"name": "x", "points": cloud(seed=2).tolist()}
        assert client.post("/references", json=body).status_code == 401
        read = {"X-API-Key": READ}
        assert client.post("/references", json=body, headers=read).status_code == 403
        admin = {"X-API-Key": ADMIN}
        assert client.post("/references", json=body, headers=admin).status_code == 201
        assert client.get("/references").status_code == 200
        assert client.get("/references/x").status_code == 200
        assert client.post("/align", json={"points": cloud(seed=1).tolist()}).status_code == 200
        assert client.delete("/references/x", headers=read).status_code == 403
        paths = client.get("/openapi.json").json()["paths"]
        assert "security" not in paths["/align"]["post"]
        assert paths["/references"]["post"]["security"][0] == {"HTTPBearer": ["admin"]}
    finally:
        server.stop()


def test_with_no_key_the_service_is_open_and_says_so(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="service"):
        server = Server(settings(tmp_path))
    try:
        client = server.client
        assert client.get("/health").json()["auth"] == "open"
        body = {"name": "anyone", "points": cloud(seed=2).tolist()}
        assert client.post("/references", json=body).status_code == 201
        assert client.delete("/references/anyone").status_code == 204
        document = client.get("/openapi.json").json()
        assert "securitySchemes" not in document.get("components", {})
        assert "security" not in document["paths"]["/references"]["post"]
    finally:
        server.stop()
    assert any("OPEN MODE" in record.getMessage() for record in caplog.records)


def test_keys_are_matched_exactly_and_every_key_is_compared(monkeypatch):
    keys = {"alpha-key": "read", "beta-key": "admin", "gamma-key": "read"}
    assert auth.role_of("beta-key", keys) == "admin"
    assert auth.role_of("alpha-key", keys) == "read"
    for near in ("beta-ke", "beta-key ", "BETA-KEY", "", "beta-keyy"):
        assert auth.role_of(near, keys) is None
    compared = []

    def counting(a, b):
        compared.append(b)
        return a == b

    monkeypatch.setattr(auth.hmac, "compare_digest", counting)
    auth.role_of("alpha-key", keys)  # the first key matches: the others are compared still
    assert len(compared) == len(keys)


def test_keys_do_not_show_in_the_settings_repr():
    configured = Settings(auth=AuthSettings(keys={"top-secret-key": "admin"}))
    assert "top-secret-key" not in repr(configured) and "top-secret-key" not in str(configured)
