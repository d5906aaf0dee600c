"""The HTTP contract of docs/api.md, against the real app and model over real HTTP.

Each server is uvicorn in a background thread on a free loopback port, with a gallery of its
own; the module runs against each store backend (SQLite, then PostgreSQL: ``backend``). The
model and the seed gallery are the shipped ones (``DPC_MODEL__PATH`` and
``DPC_MODEL__GALLERY`` point elsewhere). Skipped when the model file is missing.
"""

from __future__ import annotations

import io
import json
import re
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import orjson
import pytest
import trimesh

from service.engine import kernels
from service.engine.mapping import file_sha256
from service.engine.reference import Reference
from service.gallery.gallery_file import load_gallery
from service.settings import EngineSettings, LimitSettings, Settings
from tests.backends import Location
from tests.meshes import BROKEN_STL, LATIN1_STL
from tests.servers import MODEL, Server, eventually, needs_model

pytestmark = needs_model

MAX_POINTS = 20_000
MAX_BODY = 2 * 1024 * 1024


def api_settings(location: Location, gallery: Path | None = None) -> Settings:
    """A server's settings: the shipped model, its seed gallery (or ``gallery``), the gallery at
    ``location``, small references and two self-check renders, the limits above."""
    return Settings(
        model=MODEL.model_copy(update={"gallery": gallery or MODEL.gallery}),
        engine=EngineSettings(),
        gallery=location.settings(reference_points=512, self_check_poses=2),
        limits=LimitSettings(max_points=MAX_POINTS, max_body_bytes=MAX_BODY),
    )


@pytest.fixture(scope="module")
def location(backend) -> Location:
    """The module's gallery: SQLite in a folder, then a PostgreSQL database (``backend``)."""
    return backend.new()


@pytest.fixture(scope="module")
def server(location):
    running = Server(api_settings(location))
    yield running
    running.stop()


@pytest.fixture(scope="module")
def api(server) -> httpx.Client:
    return server.client


@pytest.fixture(scope="module")
def seeded(api) -> list[str]:
    return [r["name"] for r in api.get("/references").json()["references"]]


def box_points(count: int = 600, seed: int = 0) -> np.ndarray:
    mesh = trimesh.creation.box(extents=(0.1, 0.2, 0.4))
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return points.astype(np.float32)


def moved(points: np.ndarray, seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points at a random pose: scene = R @ model + t."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    rotation = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    translation = rng.uniform(-0.5, 0.5, 3)
    return (points @ rotation.T + translation).astype(np.float32), rotation, translation


def detail(response: httpx.Response) -> str:
    body = response.json()
    assert set(body) == {"detail"} and isinstance(body["detail"], str), body
    return body["detail"]


# --- health ---------------------------------------------------------------------------


def test_health_names_the_model_providers_and_references(api, server, seeded):
    response = api.get("/health")
    assert response.status_code == 200
    body = response.json()
    assert body["status"] == "ok"
    assert body["model"]["sha256"] == file_sha256(server.settings.model.path)
    assert body["model"]["path"] == str(server.settings.model.path)
    assert "CPUExecutionProvider" in body["providers"]
    assert body["loops"] == ("compiled" if kernels.AVAILABLE else "numpy")  # the same venv
    assert body["references"] == len(seeded) > 0
    assert api.get("/v2/health/live").json() == {"live": True}
    ready = api.get("/v2/health/ready")
    assert ready.status_code == 200 and ready.json()["ready"] is True


# --- references -----------------------------------------------------------------------


def test_the_store_is_seeded_from_the_shipped_gallery(api, seeded):
    for item in api.get("/references").json()["references"]:
        assert item["num_points"] > 0 and item["scale"] > 0
    described = api.get(f"/references/{seeded[0]}")
    assert described.status_code == 200 and described.json()["name"] == seeded[0]


def test_a_part_whose_turns_nearly_fit_is_registered_with_a_warning(api):
    """The KUKA flange's points, registered as a cloud: turns about its axis nearly fit (a
    notch tells them apart); the description lists them and the operator is told."""
    (flange,) = [r for r in load_gallery(MODEL.gallery)[0] if r.name == "kuka-link-7"]
    body = {"name": "flange-copy", "points": np.asarray(flange.points).tolist()}
    created = api.post("/references?self_check=false", json=body)
    assert created.status_code == 201, created.text
    answer = created.json()
    assert len(answer["symmetry"]["near"]) > 0
    (said,) = [w for w in answer["warnings"] if "nearly fit" in w]
    assert "flange-copy" in said and "alternatives" in said
    # a cloud may hide its half turn: the declaration that would make it round is offered
    assert """'symmetry': {"kind": "revolution", "axis": [0.0, 0.0, 1.0]}""" in said
    assert api.delete("/references/flange-copy").status_code == 204


def test_register_replace_and_delete(api):
    points = box_points(2048)
    created = api.post("/references", json={"name": "box-a", "points": points.tolist()})
    assert created.status_code == 201, created.text
    body = created.json()
    assert body["name"] == "box-a" and body["num_points"] == len(points)
    radius = np.linalg.norm(points - points.mean(axis=0), axis=1).max()
    assert body["scale"] == pytest.approx(radius, rel=1e-5)
    assert [check["render"] for check in body["self_check"]] == ["full", "view", "view"]
    assert {"rotation_error_deg", "alignment_error_normalized", "label_ok", "verdict"} <= set(
        body["self_check"][0]
    )
    # a box's symmetry: the check reports it, the description shows it
    assert body["symmetry"]["kind"] == "discrete" and len(body["symmetry"]["rotations"]) == 4
    assert any("symmetry" in warning for warning in body["warnings"])

    again = api.post("/references", json={"name": "box-a", "points": points.tolist()})
    assert again.status_code == 200 and again.json()["outcome"] == "identical"  # safe to resend
    other = api.post("/references", json={"name": "box-a", "points": (points * 1.5).tolist()})
    assert other.status_code == 409 and "box-a" in detail(other)
    bigger = (points * 2).tolist()
    replaced = api.post("/references?replace=true", json={"name": "box-a", "points": bigger})
    assert replaced.status_code == 200 and replaced.json()["scale"] == pytest.approx(2 * radius)
    assert api.get("/references/box-a").json()["scale"] == pytest.approx(2 * radius)
    quick = {"replace": "true", "self_check": "false"}
    fresh = api.post("/references", params=quick, json={"name": "box-b", "points": points.tolist()})
    assert fresh.status_code == 201 and fresh.json()["self_check"] is None

    assert api.delete("/references/box-b").status_code == 204
    assert api.delete("/references/box-b").status_code == 404
    missing = api.get("/references/box-b")
    assert missing.status_code == 404 and "box-b" in detail(missing)
    names = [r["name"] for r in api.get("/references").json()["references"]]
    assert "box-a" in names and "box-b" not in names


def npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def test_register_uploaded_files(api, server):
    mesh = trimesh.creation.box(extents=(0.1, 0.2, 0.3))
    stl = mesh.export(file_type="stl")
    created = api.post("/references", data={"name": "box-stl"}, files={"file": ("part.stl", stl)})
    assert created.status_code == 201, created.text
    assert created.json()["num_points"] == server.settings.gallery.reference_points  # sampled

    cloud = box_points(300, seed=5)
    header = (
        b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 300\nHEIGHT 1\n"
        b"POINTS 300\nDATA binary\n"
    )
    uploads = {"scan.pcd": header + cloud.tobytes(), "scan.npy": npy(cloud)}
    for index, (filename, data) in enumerate(uploads.items()):
        created = api.post(
            "/references", data={"name": f"scan-{index}"}, files={"file": (filename, data)}
        )
        assert created.status_code == 201, created.text
        assert created.json()["num_points"] == 300  # used as is

    # a text STL whose solid name is not UTF-8 (trimesh decodes it with charset_normalizer)
    upload = {"file": ("part.stl", LATIN1_STL)}
    latin1 = api.post("/references", data={"name": "stl-latin-1"}, files=upload)
    assert latin1.status_code == 201, latin1.text
    assert api.delete("/references/stl-latin-1").status_code == 204
    broken = api.post("/references", data={"name": "x"}, files={"file": ("a.stl", BROKEN_STL)})
    assert broken.status_code == 422 and "STL mesh is unusable" in detail(broken)
    assert "module" not in detail(broken)

    bad = api.post("/references", data={"name": "x"}, files={"file": ("a.npy", b"nonsense")})
    assert bad.status_code == 422 and "NPY" in detail(bad)
    no_file = api.post("/references", data={"name": "x"}, files={"other": ("a.npy", b"")})
    assert no_file.status_code == 422 and "file" in detail(no_file)
    no_name = api.post("/references", files={"file": ("part.stl", stl)})
    assert no_name.status_code == 422 and "name" in detail(no_name)
    for name in ("scan-0", "scan-1", "box-stl"):
        assert api.delete(f"/references/{name}").status_code == 204


GOOD = box_points(100).tolist()
BAD_POINTS = {
    "empty": [],
    "fewer than the minimum": GOOD[:5],
    "more than the maximum": [[float(i), 0.0, 1.0] for i in range(MAX_POINTS + 1)],
    "points[3] has 2 values": [*GOOD[:3], [1.0, 2.0], *GOOD[3:]],
    "points[0][1] is a string": [[1.0, "2", 3.0], *GOOD],
    "points[0][0] is a boolean": [[True, 2.0, 3.0], *GOOD],
    "points[1] is a number": [GOOD[0], 5, *GOOD],
    "NaN": [*GOOD, [float("nan"), 0.0, 0.0]],
    "(nearly) the same": [[0.5, 0.5, 0.5]] * 100,
}


@pytest.mark.parametrize("problem", list(BAD_POINTS))
def test_bad_points_are_refused_and_change_nothing(api, problem):
    before = api.get("/references").json()
    points = BAD_POINTS[problem]
    if problem == "NaN":  # Python's json writes NaN, which is not JSON
        body = json.dumps({"name": "bad", "points": points}).encode()
        response = api.post(
            "/references", content=body, headers={"content-type": "application/json"}
        )
        body = json.dumps({"points": points}).encode()
        align = api.post("/align", content=body, headers={"content-type": "application/json"})
    else:
        response = api.post("/references", json={"name": "bad", "points": points})
        align = api.post("/align", json={"points": points})
    for answer in (response, align):
        assert answer.status_code == 422, answer.text
        assert problem in detail(answer)
    assert api.get("/references").json() == before


def test_a_cloud_at_one_place_but_for_strays_is_no_match(api):
    """Valid points (the strays give the cloud its extent), nothing to recognise once they are
    set aside: an answer saying so, not a 500."""
    points = [[0.5, 0.5, 0.5]] * 200 + [[1.5, 1.5, 1.5], [2.5, 2.5, 2.5], [-0.5, 3.5, 0.5]]
    answer = api.post("/align", json={"points": points})
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert body["verdict"] == "no_match" and body["points_set_aside"] == 3
    assert any("lie at one place" in reason for reason in body["reasons"])


def test_unknown_reference_fields_are_refused_and_change_nothing(api):
    before = api.get("/references").json()
    misspelt = api.post("/references", json={"nmae": "typo", "name": "typo", "points": GOOD})
    assert misspelt.status_code == 422
    assert "'nmae' (did you mean 'name'?)" in detail(misspelt)
    assert "the accepted fields are name, points" in detail(misspelt)
    upload = {"file": ("part.npy", npy(np.asarray(GOOD, np.float32)))}
    extra = api.post("/references", data={"name": "typo", "replace": "true"}, files=upload)
    assert extra.status_code == 422 and "'replace'" in detail(extra)
    assert "name, units, symmetry, file" in detail(extra)
    assert api.get("/references").json() == before


@pytest.mark.parametrize("name", ["", "a" * 65, "a/b", "has space", "ünï", 7])
def test_bad_names_are_refused(api, name):
    response = api.post("/references", json={"name": name, "points": GOOD})
    assert response.status_code == 422 and "name" in detail(response)


def test_bad_reference_bodies(api):
    missing = api.post("/references", json={"name": "x"})
    assert missing.status_code == 422 and "points" in detail(missing)
    broken = api.post(
        "/references", content=b"{not json", headers={"content-type": "application/json"}
    )
    assert broken.status_code == 422 and "not valid JSON" in detail(broken)
    text = api.post("/references", content=b"x", headers={"content-type": "text/plain"})
    assert text.status_code == 415 and "text/plain" in detail(text)
    flag = api.post("/references?replace=maybe", json={"name": "x", "points": GOOD})
    assert flag.status_code == 422 and "replace" in detail(flag)


# --- align ----------------------------------------------------------------------------


def check_alignment(body: dict, names: list[str]) -> None:
    assert body["label"] in names
    rotation, translation = np.array(body["rotation"]), np.array(body["translation"])
    transform = np.array(body["transform"])
    assert rotation.shape == (3, 3) and translation.shape == (3,) and transform.shape == (4, 4)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-6)
    np.testing.assert_allclose(transform[:3, :3], rotation)
    np.testing.assert_allclose(transform[:3, 3], translation)
    np.testing.assert_allclose(transform[3], [0, 0, 0, 1])
    assert body["alignment_error"] >= 0 and np.isfinite(body["alignment_error_normalized"])
    assert body["hypothesis"] in ("mapped", "principal-axes", "paper")
    assert body["timings_ms"]["total"] > 0 and 0 <= body["score"] <= 1.0 + 1e-6
    fit = body["candidates"][0]
    assert {"label", "score", "alignment_error", "alignment_error_normalized", "hypothesis"} <= set(
        fit
    )


def test_align_json_and_raw(api, seeded):
    points = box_points(800, seed=2)
    created = api.post("/references", json={"name": "box-align", "points": points.tolist()})
    assert created.status_code in (200, 201)
    names = [r["name"] for r in api.get("/references").json()["references"]]
    scene, rotation, translation = moved(box_points(800, seed=3))

    response = api.post("/align", json={"points": scene.tolist()})
    assert response.status_code == 200, response.text
    check_alignment(response.json(), names)

    restricted = api.post(
        "/align",
        json={"points": scene.tolist(), "candidates": ["box-align"], "top_k": 1, "refine": True},
    )
    assert restricted.status_code == 200 and restricted.json()["label"] == "box-align"
    body = restricted.json()
    assert body["alignment_error_normalized"] < 0.2  # the right object, whatever the pose

    raw = api.post(
        "/align?candidates=box-align&refine=false",
        content=scene.astype("<f4").tobytes(),
        headers={"content-type": "application/octet-stream"},
    )
    assert raw.status_code == 200, raw.text
    check_alignment(raw.json(), names)
    assert raw.json()["label"] == "box-align"


def test_bad_align_requests(api, seeded):
    scene = box_points(200).tolist()
    unknown = api.post("/align", json={"points": scene, "candidates": ["no-such-part"]})
    assert unknown.status_code == 404 and "no-such-part" in detail(unknown)
    cases = {
        "top_k": {"points": scene, "top_k": 0},
        "candidates": {"points": scene, "candidates": "one"},
        "refine": {"points": scene, "refine": "perhaps"},
        "points": {"candidates": [seeded[0]]},
    }
    for words, body in cases.items():
        response = api.post("/align", json=body)
        assert response.status_code == 422 and words in detail(response), (words, response.text)
    for body, words in ((b"[1, 2]", "JSON object"), (b"{", "not valid JSON"), (b"", "empty")):
        response = api.post("/align", content=body, headers={"content-type": "application/json"})
        assert response.status_code == 422 and words in detail(response)
    raw = {"content-type": "application/octet-stream"}
    wrong = api.post("/align", content=b"\0" * 1202, headers=raw)
    assert wrong.status_code == 422 and "1202 bytes" in detail(wrong)
    query = api.post("/align?top_k=0", content=np.zeros(300, "<f4").tobytes(), headers=raw)
    assert query.status_code == 422 and "top_k" in detail(query)
    xml = api.post("/align", content=b"<points/>", headers={"content-type": "application/xml"})
    assert xml.status_code == 415 and "application/xml" in detail(xml)


def test_unknown_align_fields_are_refused(api, seeded):
    scene = box_points(200).tolist()
    for field, words in (("candidate", "did you mean 'candidates'?"), ("viewpont", "'viewpoint'")):
        response = api.post("/align", json={"points": scene, field: [seeded[0]]})
        assert response.status_code == 422, response.text
        assert f"unknown field '{field}'" in detail(response) and words in detail(response)
        accepted = "candidates, top_k, refine, viewpoint, min_confidence, points"
        assert accepted in detail(response)
    both = api.post("/align", json={"points": scene, "topk": 1, "refined": False})
    assert both.status_code == 422 and "unknown fields 'topk'" in detail(both)
    assert "'refined' (did you mean 'refine'?)" in detail(both)


def test_every_field_of_the_contract_is_accepted(api, seeded):
    scene = moved(box_points(400, seed=8))[0].tolist()
    contract = {
        "points": scene,
        "candidates": seeded[:2],
        "top_k": 2,
        "refine": False,
        "viewpoint": [0.0, 0.0, 0.0],
        "min_confidence": 0.5,
    }
    response = api.post("/align", json=contract)
    assert response.status_code == 200, response.text
    assert response.json()["label"] in seeded[:2]


def test_viewpoint_is_three_finite_numbers(api, seeded):
    scene = moved(box_points(400, seed=7))[0]
    fine = api.post("/align", json={"points": scene.tolist(), "viewpoint": [0, 0, 0]})
    assert fine.status_code == 200, fine.text
    raw = {"content-type": "application/octet-stream"}
    body = scene.astype("<f4").tobytes()
    assert api.post("/align?viewpoint=0,0.5,-1", content=body, headers=raw).status_code == 200
    for bad in ([0, 0], [0, 0, 0, 0], ["a", 0, 0], "0,0,0", {"x": 0}):
        response = api.post("/align", json={"points": scene.tolist(), "viewpoint": bad})
        assert response.status_code == 422 and "viewpoint" in detail(response), (bad, response.text)
    nan = json.dumps({"points": scene.tolist(), "viewpoint": [0, float("nan"), 0]})
    response = api.post("/align", content=nan, headers={"content-type": "application/json"})
    assert response.status_code == 422 and "finite" in detail(response)
    for bad in ("0,0", "a,b,c", "1,2,inf", "1,,2"):
        response = api.post(f"/align?viewpoint={bad}", content=body, headers=raw)
        assert response.status_code == 422 and "viewpoint" in detail(response), bad
    confidence = api.post("/align", json={"points": scene.tolist(), "min_confidence": 1.5})
    assert confidence.status_code == 422 and "min_confidence" in detail(confidence)


def test_a_body_over_the_limit_is_413(api):
    big = b"\0" * (MAX_BODY + 12)
    raw = {"content-type": "application/octet-stream"}
    declared = api.post("/align", content=big, headers=raw)
    assert declared.status_code == 413 and "limit" in detail(declared)

    def chunks():  # no Content-Length: the server counts what it reads
        for _ in range(MAX_BODY // 65536 + 2):
            yield b"\0" * 65536

    chunked = api.post("/align", content=chunks(), headers=raw)
    assert chunked.status_code == 413 and "limit" in detail(chunked)
    upload = api.post("/references", data={"name": "x"}, files={"file": ("a.npy", big)})
    assert upload.status_code == 413


def test_health_answers_while_every_alignment_slot_is_taken(server, monkeypatch):
    """Alignments run off the event loop: with every slot held by a running alignment, the
    health routes still answer at once, and the alignments answer once they may finish."""
    engine = server.app.state.catalog.engine
    slots = server.settings.align_slots
    original, gate, entered = engine.align, threading.Event(), threading.Semaphore(0)

    def held_align(*args, **kwargs):  # the real alignment, started only when the gate opens
        entered.release()
        assert gate.wait(timeout=60), "the test never opened the gate"
        return original(*args, **kwargs)

    monkeypatch.setattr(engine, "align", held_align)
    body = orjson.dumps({"points": moved(box_points(600, seed=4))[0].tolist()})
    headers = {"content-type": "application/json"}
    try:
        with ThreadPoolExecutor(slots) as pool:
            aligns = [
                pool.submit(server.client.post, "/align", content=body, headers=headers)
                for _ in range(slots)
            ]
            for _ in range(slots):  # every slot is now held by an alignment in a worker thread
                assert entered.acquire(timeout=60), "an alignment never started"
            assert server.client.get("/health").status_code == 200
            assert server.client.get("/v2/health/ready").json() == {"ready": True, "detail": None}
            assert not any(future.done() for future in aligns)
            gate.set()
            assert all(future.result().status_code == 200 for future in aligns)
    finally:
        gate.set()


# --- the rest -------------------------------------------------------------------------


def test_metrics(api):
    api.post("/align", json={"points": []})
    text = api.get("/metrics").text
    assert 'http_requests_total{handler="/align",method="POST",status="422"}' in text
    assert "http_request_duration_seconds_bucket" in text
    assert "dpc_references " in text


def test_errors_and_unknown_routes_are_json(api):
    assert detail(api.get("/nowhere")) == "Not Found"
    assert api.put("/align").status_code == 405


def test_openapi_document(api):
    document = api.get("/openapi.json").json()
    assert document["openapi"].startswith("3.")
    paths = document["paths"]
    expected = {
        "/align": {"post"},
        "/references": {"get", "post"},
        "/references/{name}": {"get", "delete"},
        "/health": {"get"},
        "/v2/health/live": {"get"},
        "/v2/health/ready": {"get"},
    }
    for path, methods in expected.items():
        assert methods <= set(paths[path]), path
    schemas = document["components"]["schemas"]
    names = "AlignRequest AlignResponse CandidateFit ReferenceRequest ReferenceResponse"
    for name in (names + " ReferenceList Health Error ReferenceUpload").split():
        assert name in schemas, name
    assert "HTTPValidationError" not in schemas  # every error answer is {"detail": "..."}
    align = paths["/align"]["post"]
    kinds = {"application/json", "application/octet-stream", "multipart/form-data"}
    assert set(align["requestBody"]["content"]) == kinds
    assert {"200", "404", "409", "413", "422"} <= set(align["responses"])
    register = paths["/references"]["post"]
    assert set(register["requestBody"]["content"]) == {"application/json", "multipart/form-data"}
    assert {"200", "201", "409", "413", "422"} <= set(register["responses"])
    response = set(schemas["AlignResponse"]["properties"])
    fields = "label score rotation translation transform alignment_error hypothesis"
    assert {*fields.split(), "alignment_error_normalized", "candidates", "timings_ms"} <= response

    def refs(node):
        if isinstance(node, dict):
            for key, value in node.items():
                if key == "$ref":
                    yield value
                else:
                    yield from refs(value)
        elif isinstance(node, list):
            for value in node:
                yield from refs(value)

    for ref in refs(document):
        assert ref.startswith("#/components/schemas/") and ref.rsplit("/", 1)[1] in schemas, ref
    jsonschema = pytest.importorskip("jsonschema")
    for schema in schemas.values():
        jsonschema.Draft202012Validator.check_schema(schema)


def test_the_documentation_pages_load_nothing_from_another_host(api):
    """/docs and /redoc work on a cell's network: every file they load comes from the service."""
    for page in ("/docs", "/redoc"):
        response = api.get(page)
        assert response.status_code == 200 and "text/html" in response.headers["content-type"]
        html = response.text
        assert not re.search(r"(https?:)?//[a-z0-9.-]+\.[a-z]{2,}", html, re.IGNORECASE), html
        assets = re.findall(r'(?:src|href|url|spec-url)\s*[=:]\s*["\']([^"\']+)["\']', html)
        assert any(a.endswith(".js") for a in assets), assets
        assert "/openapi.json" in assets, assets
        for asset in assets:
            assert asset.startswith("/"), asset
            loaded = api.get(asset)
            assert loaded.status_code == 200 and len(loaded.content) > 0, asset


# --- other servers: empty, restarted, damaged -----------------------------------------


def test_an_empty_gallery_answers_409(backend, tmp_path):
    empty = Server(api_settings(backend.new(), gallery=tmp_path / "none.npz"))
    try:
        assert empty.client.get("/health").json()["references"] == 0
        response = empty.client.post("/align", json={"points": GOOD})
        assert response.status_code == 409 and "no reference" in detail(response)
    finally:
        empty.stop()


def test_a_restart_keeps_the_references(server, location, api, seeded):
    """Stops the module's server: the tests after this one start their own."""
    points = box_points(400, seed=9)
    api.post("/references?replace=true", json={"name": "kept", "points": points.tolist()})
    removed = seeded[-1]
    assert api.delete(f"/references/{removed}").status_code == 204
    before = api.get("/references").json()
    server.stop()

    again = Server(api_settings(location))
    try:
        assert again.client.get("/references").json() == before  # deleted seeds stay deleted
        assert again.client.get("/references/kept").json()["num_points"] == 400
        assert again.client.get("/references/" + removed).status_code == 404
        scene = moved(points)[0].tolist()
        aligned = again.client.post("/align", json={"points": scene, "candidates": ["kept"]})
        assert aligned.status_code == 200 and aligned.json()["label"] == "kept"
    finally:
        again.stop()


def stale_reference(name: str, points: np.ndarray) -> Reference:
    """A reference whose mapped points and grids no model computed."""
    return Reference(
        name=name,
        points=points,
        mapped=np.zeros((len(points), 2), np.float32),
        view_grids=np.zeros((1, 64, 64), np.float32),
        scale=float(np.linalg.norm(points - points.mean(axis=0), axis=1).max()),
    )


def test_a_damaged_store_is_not_ready(backend):
    damaged = backend.new()
    store = damaged.store()
    store.put(stale_reference("part", box_points(300)), model_hash="0" * 64)
    store.set_meta("seeded_from", "")
    store.close()
    damaged.execute("UPDATE reference SET extras = ?", ('{"scale": 2.0}',))

    broken = Server(api_settings(damaged), ready=False)

    def loaded() -> httpx.Response:
        health = broken.client.get("/health")
        assert health.json()["status"] != "loading"
        return health

    try:
        health = eventually(loaded, timeout=60)
        assert health.status_code == 503 and health.json()["status"] == "failed"
        assert "checksum" in health.json()["detail"]
        assert broken.client.get("/v2/health/ready").status_code == 503
        assert broken.client.get("/v2/health/live").status_code == 200
        refused = broken.client.post("/align", json={"points": GOOD})
        assert refused.status_code == 503 and "not ready" in detail(refused)
    finally:
        broken.stop()


def test_references_of_another_model_are_recomputed(backend):
    location = backend.new()
    points = box_points(300)
    store = location.store()
    store.put(stale_reference("stale", points), model_hash="0" * 64)
    store.set_meta("seeded_from", "")  # as if seeded before

    server = Server(api_settings(location))
    try:
        listed = server.client.get("/references").json()["references"]
        assert [r["name"] for r in listed] == ["stale"]
    finally:
        server.stop()
    (record,) = store.load_records()
    assert record.model_hash == file_sha256(server.settings.model.path)
    assert record.reference.view_grids.shape[0] == server.settings.engine.view_grids
    assert np.abs(record.reference.mapped).sum() > 0
    np.testing.assert_array_equal(record.reference.points, points)
    store.close()
