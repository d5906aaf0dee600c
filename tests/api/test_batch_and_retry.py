"""Registrations safe to send again, and a batch of parts: a real server, real meshes.

The same name with the same points is answered 200 ``identical`` (never 409) and changes
nothing; other points under that name stay 409 without ``replace``. A batch (``POST
/references/batch``, ``dpc-mn register FOLDER``) stores every part or none, with one refit of
the classifier, and sent again is answered identical part by part.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import trimesh

from service.client import Client, Conflict, InvalidInput
from service.client.cli import main
from tests.conftest import empty_server


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    server = empty_server(tmp_path_factory.mktemp("batch"))
    yield server
    server.stop()


@pytest.fixture
def client(server):
    with Client(server.url, retry_for=0) as client:
        yield client


def meshes(folder: Path) -> list[Path]:
    """Three real parts of pybullet_data, as the files an operator would upload."""
    data = Path(pytest.importorskip("pybullet_data").getDataPath())
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, relative in (("duck", "duck.obj"), ("mug", "objects/mug.obj"), ("cube", "cube.obj")):
        target = folder / f"{name}{Path(relative).suffix}"
        target.write_bytes((data / relative).read_bytes())
        paths.append(target)
    return paths


def stored(server) -> dict[str, str]:
    """The store's rows, by name: their checksums."""
    return server.app.state.catalog.store.checksums()


def test_the_same_points_again_are_identical_and_change_nothing(server, client):
    points = trimesh.creation.box(extents=(0.05, 0.08, 0.12)).sample(800, seed=3)
    first = client.register("retried-box", points, self_check=False)
    assert first.raw["outcome"] == "created"
    before, refits = stored(server), server.app.state.catalog.engine.refits
    again = server.client.post(
        "/references", json={"name": "retried-box", "points": points.astype("<f4").tolist()}
    )
    assert again.status_code == 200, again.text
    answer = again.json()
    assert answer["outcome"] == "identical" and "already registered, identical" in answer["message"]
    assert answer["points_sha256"] == first.points_sha256 and answer["self_check"] is None
    assert stored(server) == before and server.app.state.catalog.engine.refits == refits
    with pytest.raises(Conflict, match="other points"):
        client.register("retried-box", points * 1.01)
    assert stored(server) == before
    replaced = client.register("retried-box", points, replace=True, self_check=False)
    assert replaced.raw["outcome"] == "replaced"  # replace=true recomputes, as before
    client.delete("retried-box")


def test_a_batch_is_one_refit_all_or_none_and_safe_to_resend(server, client, tmp_path):
    paths = meshes(tmp_path / "parts")
    engine = server.app.state.catalog.engine
    before, refits = stored(server), engine.refits
    broken = tmp_path / "broken" / "bad.stl"
    broken.parent.mkdir()
    broken.write_bytes(b"solid nothing\nendsolid nothing\n")
    with pytest.raises(InvalidInput, match="part 'bad'"):
        client.register_many([*paths, broken], self_check=False)
    assert stored(server) == before and engine.refits == refits  # none of them stored

    registered = client.register_many(paths)
    assert [r.name for r in registered] == ["duck", "mug", "cube"]
    assert {r.raw["outcome"] for r in registered} == {"created"}
    assert engine.refits == refits + 1  # one refit for the three
    assert all([c["render"] for c in r.self_check] == ["full", "view"] for r in registered)
    for reference in registered:
        described = client.reference(reference.name)
        assert described.points_sha256 == reference.points_sha256

    status = main(["register", str(paths[0].parent), "--url", server.url, "--json"])
    assert status == 0
    assert engine.refits == refits + 1  # sent again: identical, nothing refitted
    with pytest.raises(Conflict):
        client.register_many({"duck": paths[1]}, self_check=False)  # other points, that name
    for reference in registered:
        client.delete(reference.name)


def test_a_batch_refuses_names_twice_and_counts_that_differ(server, client, tmp_path):
    paths = meshes(tmp_path / "parts")
    twice = server.client.post(
        "/references/batch",
        files=[("file", (p.name, p.read_bytes())) for p in (paths[0], paths[0])],
    )
    assert twice.status_code == 422 and "duck more than once" in twice.json()["detail"]
    counts = server.client.post(
        "/references/batch",
        data={"name": ["a"]},
        files=[("file", (p.name, p.read_bytes())) for p in paths[:2]],
    )
    assert counts.status_code == 422 and "1 'name' fields for 2 files" in counts.json()["detail"]


def test_the_command_line_registers_a_folder(server, tmp_path, capsys):
    paths = meshes(tmp_path / "folder")
    status = main(
        ["register", str(paths[0].parent), "--url", server.url, "--no-self-check", "--json"]
    )
    out = json.loads(capsys.readouterr().out)
    assert status == 0 and [r["name"] for r in out["references"]] == ["cube", "duck", "mug"]
    status = main(["register", str(paths[0]), "--url", server.url])  # named for its file
    assert status == 0 and "already registered, identical" in capsys.readouterr().out
    for name in ("cube", "duck", "mug"):
        assert main(["delete", name, "--url", server.url]) == 0
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["register", str(empty), "--url", server.url]) == 1
    assert "no mesh or cloud file" in capsys.readouterr().err
