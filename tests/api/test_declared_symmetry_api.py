"""A symmetry declared at registration (issue 33), through the HTTP API (a JSON field and a
form field), the Python client and ``dpc-mn register --symmetry``: stored and described, part
of what makes a registration identical, and refused with a reason (nothing stored) where it is
malformed or does not fit. The part is the KUKA flange sampled as a cloud, whose half turn the
self-fit does not confirm at this draw; the server is the session's."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from service.client import Client
from service.client.cli import OK, main
from service.engine.sampling import sample_surface_faces
from tests.meshes import pybullet_mesh

HALF_TURN = {"kind": "discrete", "axis": [0.0, 0.0, 1.0], "order": 2}


@pytest.fixture(scope="module")
def flange() -> np.ndarray:
    points, _ = sample_surface_faces(pybullet_mesh("kuka_iiwa/meshes/link_7.obj"), 2048, 0)
    return points.astype(np.float32)


def npy(points: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, points)
    return buffer.getvalue()


def post_json(service, name, points, replace=False, **fields):
    body = {"name": name, "points": points.tolist(), **fields}
    params = {"self_check": "false"} | ({"replace": "true"} if replace else {})
    return service.client.post("/references", json=body, params=params)


def test_a_declared_symmetry_is_stored_and_makes_registrations_differ(service, flange):
    plain = post_json(service, "flange-plain", flange)
    assert plain.status_code == 201 and plain.json()["symmetry"]["kind"] == "none"
    try:
        answer = post_json(service, "flange-json", flange, symmetry=HALF_TURN)
        assert answer.status_code == 201, answer.text[:500]
        symmetry = answer.json()["symmetry"]
        assert symmetry["kind"] == "discrete" and symmetry["declared"] == HALF_TURN
        assert service.client.get("/references/flange-json").json()["symmetry"] == symmetry
        again = post_json(service, "flange-json", flange, symmetry=HALF_TURN)
        assert again.status_code == 200 and again.json()["outcome"] == "identical"
        undeclared = post_json(service, "flange-json", flange)  # the same points, no declaration
        assert undeclared.status_code == 409, undeclared.text[:300]
        replaced = post_json(service, "flange-json", flange, replace=True)
        assert replaced.status_code == 200 and replaced.json()["symmetry"]["kind"] == "none"
    finally:
        for name in ("flange-plain", "flange-json"):
            service.client.delete(f"/references/{name}")


@pytest.mark.parametrize(
    "symmetry, said",
    [
        ({"kind": "revolution"}, "a revolution takes an 'axis'"),
        ({"kind": "discrete", "axis": [0, 0, 1]}, "'axis' and 'order', or 'rotations'"),
        ({"kind": "discrete", "axis": [0, 0, 0], "order": 2}, "non-zero vector"),
        ({"kind": "discrete", "rotations": [[[1, 0, 0], [0, 1, 0], [0, 0, 2]]]}, "no rotation"),
        ({"kind": "discrete", "axis": [0, 0, 1], "order": 1}, "greater than or equal to 2"),
        ({"kind": "discrete", "rotations": []}, "at least 1 item"),
        ({"kind": "helical", "axis": [0, 0, 1]}, "'revolution' or 'discrete'"),
        ({"kind": "discrete", "axis": [1, 0, 0], "order": 2}, "does not fit the part"),
        ("[1, 2", "must be a JSON object"),
    ],
)
def test_a_bad_declaration_is_refused_naming_it_and_stores_nothing(service, flange, symmetry, said):
    before = service.client.get("/references").json()
    if isinstance(symmetry, dict):
        answer = post_json(service, "flange-bad", flange, symmetry=symmetry)
    else:  # a form field that is no JSON
        answer = service.client.post(
            "/references",
            data={"name": "flange-bad", "symmetry": symmetry},
            files={"file": ("flange.npy", npy(flange))},
            params={"self_check": "false"},
        )
    assert answer.status_code == 422, answer.text[:500]
    assert said in answer.text, answer.text[:500]
    assert service.client.get("/references").json() == before


def test_the_form_the_client_and_the_command_line_declare_it(service, flange, tmp_path, capsys):
    answer = service.client.post(
        "/references",
        data={"name": "flange-form", "symmetry": json.dumps(HALF_TURN)},
        files={"file": ("flange.npy", npy(flange))},
        params={"self_check": "false"},
    )
    assert answer.status_code == 201 and answer.json()["symmetry"]["declared"] == HALF_TURN
    cloud = tmp_path / "flange.npy"
    cloud.write_bytes(npy(flange))
    with Client(service.url) as client:
        reference = client.register("flange-client", cloud, self_check=False, symmetry=HALF_TURN)
        assert reference.raw["symmetry"]["declared"] == HALF_TURN
    command = ["register", str(cloud), "--url", service.url, "--no-self-check", "--json"]
    assert main([*command, "--name", "flange-cli", "--symmetry", json.dumps(HALF_TURN)]) == OK
    assert json.loads(capsys.readouterr().out)["symmetry"]["declared"] == HALF_TURN
    for name in ("flange-form", "flange-client", "flange-cli"):
        assert service.client.delete(f"/references/{name}").status_code == 204


def test_the_registration_s_warning_offers_a_declaration_that_is_taken(service, flange):
    """The flange's cloud: its near turns about its axis make it nearly round, and the warning
    names the declaration that makes it round; sent back, it is."""
    answer = post_json(service, "flange-offer", flange)
    try:
        assert answer.status_code == 201, answer.text[:500]
        (said,) = [w for w in answer.json()["warnings"] if "nearly fit" in w]
        offered = json.loads(said.split("'symmetry': ")[1].split(" (")[0])
        assert offered == {"kind": "revolution", "axis": [0.0, 0.0, 1.0]}
        again = post_json(service, "flange-offer", flange, replace=True, symmetry=offered)
        assert again.status_code == 200, again.text[:500]
        assert again.json()["symmetry"]["kind"] == "revolution"
        assert not [w for w in again.json()["warnings"] if "nearly fit" in w]
    finally:
        service.client.delete("/references/flange-offer")
