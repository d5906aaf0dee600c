"""Backup and restore, export and import: real servers, real stores (SQLite and PostgreSQL),
through the ``dpc-mn`` command and the client.

A backup taken while registrations go on is one consistent gallery, every row checked; restored
into an empty gallery (of either store) it holds exactly the same rows, every ``points_sha256``
checked, and sent again it is answered identical; a gallery that holds references refuses it
unless told to replace them all; a damaged copy is refused naming the reference, and nothing
is stored. Chosen references exported from one service and imported into another are the same
references there, and align there.
"""

from __future__ import annotations

import sqlite3
import threading

import numpy as np
import pytest

from service.client import Client, Conflict, InvalidInput
from service.client.cli import main
from service.engine.sampling import sample_surface
from service.gallery import backup
from service.settings import GallerySettings, Settings
from tests.conftest import empty_server
from tests.ledger import sha
from tests.ledger import varied_cloud as cloud
from tests.meshes import pybullet_mesh
from tests.servers import MODEL, Server


def server_on(location, **gallery) -> Server:
    if not MODEL.path.exists():
        pytest.skip(f"no ONNX model at {MODEL.path}")
    model = MODEL.model_copy(update={"gallery": location.data_dir / "no-seed.npz"})
    settings = GallerySettings(
        data_dir=location.data_dir, url=location.url, self_check_poses=0, **gallery
    )
    return Server(Settings(model=model, gallery=settings))


def rows(server) -> dict[str, str]:
    return server.app.state.catalog.store.checksums()


def points_of(server) -> dict[str, str]:
    engine = server.app.state.catalog.engine
    return {name: engine.get(name).points_sha256 for name in engine.names()}


def test_a_backup_while_serving_restores_into_an_empty_gallery(backend, tmp_path, capsys):
    source = server_on(backend.new())
    target = empty_server(tmp_path / "target")  # SQLite, whichever the source
    try:
        with Client(source.url, retry_for=0) as client:
            for index in range(2):
                client.register(f"part-{index}", cloud(index), self_check=False)
            acknowledged = set(rows(source))
            stop, failures = threading.Event(), []

            def keep_registering() -> None:  # the service goes on taking changes meanwhile
                with Client(source.url, retry_for=0) as writer:
                    index = 10
                    while not stop.is_set():
                        try:
                            writer.register(f"during-{index}", cloud(index), self_check=False)
                        except Exception as error:  # noqa: BLE001 - reported below
                            failures.append(repr(error))
                            return
                        index += 1

            writer = threading.Thread(target=keep_registering)
            writer.start()
            try:
                copy = tmp_path / "gallery.sqlite3"
                assert main(["backup", str(copy), "--url", source.url]) == 0
            finally:
                stop.set()
                writer.join()
        assert failures == []
        assert "references copied to" in capsys.readouterr().out
        checked = backup.read(copy)  # consistent: every row checks, the list matches the rows
        assert acknowledged <= set(checked.checksums)
        assert {n: rows(source)[n] for n in checked.checksums} == checked.checksums
        assert not (tmp_path / "gallery.sqlite3-wal").exists()

        assert main(["restore", str(copy), "--url", target.url]) == 0
        assert "points_sha256 checked" in capsys.readouterr().out
        assert rows(target) == checked.checksums  # the same rows, byte for byte
        assert points_of(target) == {n: points_of(source)[n] for n in checked.checksums}
        assert main(["restore", str(copy), "--url", target.url]) == 0  # sent again
        assert "already" in capsys.readouterr().out

        with Client(target.url, retry_for=0) as client:
            client.register("extra", cloud(99), self_check=False)
            with pytest.raises(Conflict, match="restore only into an empty one"):
                client.restore(copy)
            answer = client.restore(copy, replace=True)
            assert answer["outcome"] == "restored" and answer["checked"] == len(checked.rows)
        assert rows(target) == checked.checksums  # "extra" went with the rest
    finally:
        source.stop()
        target.stop()


def test_a_damaged_copy_is_refused_and_stores_nothing(tmp_path):
    server = empty_server(tmp_path / "server")
    try:
        with Client(server.url, retry_for=0) as client:
            client.register("whole", cloud(1), self_check=False)
            client.register("other", cloud(2), self_check=False)
            copy = tmp_path / "copy.sqlite3"
            client.backup(copy)
            for name in ("whole", "other"):
                client.delete(name)
            damaged = tmp_path / "damaged.sqlite3"
            damaged.write_bytes(copy.read_bytes())
            with sqlite3.connect(damaged) as conn:  # one coordinate changed, the rest intact
                (arrays,) = conn.execute(
                    "SELECT arrays FROM reference WHERE name = 'whole'"
                ).fetchone()
                flipped = bytes([arrays[0] ^ 1]) + bytes(arrays[1:])
                conn.execute("UPDATE reference SET arrays = ? WHERE name = 'whole'", (flipped,))
            with pytest.raises(InvalidInput, match="'whole': checksum mismatch"):
                client.restore(damaged)
            listed = tmp_path / "listed.sqlite3"
            listed.write_bytes(copy.read_bytes())
            with sqlite3.connect(listed) as conn:  # a sound row, listed with other points
                conn.execute(
                    "UPDATE backup SET points_sha256 = ? WHERE name = 'other'",
                    (sha(cloud(3)),),
                )
            with pytest.raises(InvalidInput, match="'other': its points' sha256"):
                client.restore(listed)
            not_a_copy = tmp_path / "notes.txt"
            not_a_copy.write_text("not a gallery")
            with pytest.raises(InvalidInput, match="not a readable SQLite"):
                client.restore(not_a_copy)
            assert rows(server) == {}
            assert client.restore(copy)["restored"] == 2  # the sound copy still restores
    finally:
        server.stop()


def test_chosen_references_move_to_another_service(tmp_path, capsys):
    cell = empty_server(tmp_path / "cell")
    line = empty_server(tmp_path / "new-line")
    try:
        duck = sample_surface(pybullet_mesh("duck.obj"), 2048, 0)
        with Client(cell.url, retry_for=0) as client:
            client.register("duck", duck, self_check=False)
            client.register("box", cloud(5), self_check=False)
            client.register("stays", cloud(6), self_check=False)
        moved = tmp_path / "cell-4.sqlite3"
        url = ("--url", cell.url)
        assert main(["export", str(moved), "--names", "duck,box", *url]) == 0
        assert main(["export", str(tmp_path / "x"), "--names", "nothing-of-that-name", *url]) == 1
        assert "nothing-of-that-name" in capsys.readouterr().err
        assert main(["import", str(moved), "--url", line.url]) == 0
        assert capsys.readouterr().out.split() == ["created:", "box", "created:", "duck"]
        assert points_of(line) == {n: points_of(cell)[n] for n in ("box", "duck")}
        assert rows(line) == {n: rows(cell)[n] for n in ("box", "duck")}  # taken as they are
        assert main(["import", str(moved), "--url", line.url]) == 0  # sent again
        assert capsys.readouterr().out.split() == ["identical:", "box", "identical:", "duck"]
        with Client(line.url, retry_for=0) as client:
            client.register("clash", cloud(7), self_check=False)
        clash = tmp_path / "clash.sqlite3"
        with Client(cell.url, retry_for=0) as client:
            client.register("clash", cloud(8), self_check=False)
            client.export(clash, ["clash", "stays"])
        with Client(line.url, retry_for=0) as client:
            with pytest.raises(Conflict, match="'clash' exists with other points"):
                client.import_references(clash)
            assert "stays" not in rows(line)  # all or none
            rotation = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], float)
            pose = client.align(duck @ rotation.T + 0.2, candidates=["duck", "box"])
            assert pose.label == "duck"
    finally:
        cell.stop()
        line.stop()
