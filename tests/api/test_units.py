"""Units at registration (issue 33): a CAD model in millimetres registered beside parts in metres
is warned about, naming the unit, and with ``units`` it is stored in metres: through the HTTP
API (query, form and JSON fields), the Python client and ``dpc-mn register --units``.

The part is pybullet's duck made about 10 cm across: written in metres and in
millimetres by trimesh, as a CAD export would be; the server is the session's (the mug and the
bunny registered, in metres)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.api.parsers import read_upload
from service.client import Client
from service.client.cli import OK, main
from service.engine.normalize import radius
from service.settings import Settings
from tests.meshes import pybullet_mesh

SIZE = 0.05  # the duck's mesh times this: metres


def stl(scale: float) -> bytes:
    mesh = pybullet_mesh("duck.obj")
    mesh.apply_scale(scale)
    return mesh.export(file_type="stl")


@pytest.fixture(scope="module")
def in_metres() -> np.ndarray:
    """The points the service samples on the duck in metres."""
    count = Settings().gallery.reference_points
    return read_upload(stl(SIZE), "duck.stl", count, 10**6).points


def register(service, name: str, data: bytes, **params) -> dict:
    form = {k: v for k, v in params.items() if k == "units" and v is not None}
    query = {k: v for k, v in params.items() if k != "units"} | {"self_check": "false"}
    answer = service.client.post(
        "/references", data={"name": name, **form}, files={"file": ("duck.stl", data)}, params=query
    )
    assert answer.status_code == 201, answer.text[:500]
    return answer.json()


def stored(service, name: str) -> np.ndarray:
    raw = service.client.get(f"/references/{name}/points").content
    return np.frombuffer(raw, "<f4").reshape(-1, 3)


def test_a_part_in_millimetres_is_warned_about_naming_the_unit(service):
    body = register(service, "duck-cad", stl(SIZE * 1000))
    try:
        assert body["scale"] > 50 and body["units"] is None  # stored as sent
        said = [w for w in body["warnings"] if "radius" in w]
        assert len(said) == 1, body["warnings"]
        assert "working range" in said[0] and "nearest-sized registered part" in said[0]
        assert "probably in millimetres" in said[0] and "units=mm" in said[0]
    finally:
        assert service.client.delete("/references/duck-cad").status_code == 204


@pytest.mark.parametrize("where", ["form", "query"])
def test_units_store_the_part_in_metres(service, in_metres, where):
    units = {"units": "mm"} if where == "form" else {}
    query = {} if where == "form" else {"units": "mm"}
    form = {"name": f"duck-mm-{where}", **units}
    answer = service.client.post(
        "/references",
        data=form,
        files={"file": ("duck.stl", stl(SIZE * 1000))},
        params={"self_check": "false", **query},
    )
    assert answer.status_code == 201, answer.text[:500]
    body = answer.json()
    try:
        assert body["units"] == "mm"
        assert not [w for w in body["warnings"] if "radius" in w], body["warnings"]
        points = stored(service, form["name"])
        assert body["scale"] == pytest.approx(radius(in_metres), rel=1e-5)
        # the same surface as the part sampled in metres, to float32's rounding
        assert np.median(np.linalg.norm(points - in_metres, axis=1)) < 1e-6
    finally:
        assert service.client.delete(f"/references/{form['name']}").status_code == 204


def test_json_points_in_centimetres(service, in_metres):
    points = (in_metres.astype(np.float64) * 100).tolist()
    answer = service.client.post(
        "/references",
        json={"name": "duck-cm", "points": points, "units": "cm"},
        params={"self_check": "false"},
    )
    assert answer.status_code == 201, answer.text[:500]
    try:
        np.testing.assert_allclose(stored(service, "duck-cm"), in_metres, atol=1e-7)
    finally:
        assert service.client.delete("/references/duck-cm").status_code == 204


@pytest.mark.parametrize("where", ["json", "form", "query"])
def test_an_unknown_unit_is_refused_naming_the_accepted_ones(service, in_metres, where):
    before = service.client.get("/references").json()
    if where == "json":
        answer = service.client.post(
            "/references", json={"name": "duck-km", "points": in_metres.tolist(), "units": "km"}
        )
    else:
        answer = service.client.post(
            "/references",
            data={"name": "duck-km"} | ({"units": "km"} if where == "form" else {}),
            files={"file": ("duck.stl", stl(SIZE))},
            params={"units": "km"} if where == "query" else {},
        )
    assert answer.status_code == 422, answer.text[:500]
    assert all(f"'{unit}'" in answer.text for unit in ("m", "mm", "cm", "in"))
    assert service.client.get("/references").json() == before


def test_the_client_and_the_command_line_send_units(service, in_metres, tmp_path, capsys):
    cad = tmp_path / "duck-cad.stl"
    cad.write_bytes(stl(SIZE * 1000))
    with Client(service.url) as client:
        reference = client.register("duck-client", cad, self_check=False, units="mm")
        assert reference.scale == pytest.approx(radius(in_metres), rel=1e-5)
        assert reference.raw["units"] == "mm"
        client.delete("duck-client")
    command = ["register", str(cad), "--url", service.url, "--no-self-check"]
    assert main([*command, "--name", "duck-cli", "--units", "mm", "--json"]) == OK
    answer = json.loads(capsys.readouterr().out)
    assert answer["units"] == "mm" and answer["scale"] == pytest.approx(radius(in_metres), rel=1e-5)
    assert main([*command, "--name", "duck-cli-as-sent"]) == OK
    said = capsys.readouterr().out
    assert "probably in millimetres" in said and "--units mm" in said and "units=mm" not in said
    for name in ("duck-cli", "duck-cli-as-sent"):
        assert service.client.delete(f"/references/{name}").status_code == 204
