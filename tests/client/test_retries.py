"""The client sends idempotent calls again on a connection error, a 502 or a 503, within a
bounded time: against a real server on a real PostgreSQL gallery whose server is stopped and
started again, and against a port where nothing listens.

While PostgreSQL is down, a registration is answered 503 with the reason and stores nothing,
alignments are served from the replica's snapshot, and a client that retries (the database
started again once the client is told 503) has its registration stored once the database is
back: exactly once, its points as sent.
"""

from __future__ import annotations

import numpy as np
import pytest

from evaluation.postgres import ThrowawayPostgres, Unavailable
from service.client import Client, Unreachable
from service.settings import GallerySettings, Settings
from tests.ledger import sha
from tests.ledger import varied_cloud as cloud
from tests.servers import MODEL, Server, free_port

pytestmark = pytest.mark.skipif(not MODEL.path.exists(), reason=f"no ONNX model at {MODEL.path}")


@pytest.fixture
def database():
    try:
        server = ThrowawayPostgres(fsync=True)
    except Unavailable as error:
        pytest.skip(f"needs a PostgreSQL server: {error}")
    yield server
    server.close()


def test_a_registration_retried_through_a_database_restart_is_stored_once(database, tmp_path):
    model = MODEL.model_copy(update={"gallery": tmp_path / "no-seed.npz"})
    url = database.create_database()
    gallery = GallerySettings(data_dir=tmp_path, url=url, self_check_poses=0, connect_timeout_s=1)
    server = Server(Settings(model=model, gallery=gallery))
    try:
        with Client(server.url, retry_for=0) as once:
            once.register("first", cloud(1))
        database.stop()
        refused = server.client.post("/references", json={"name": "x", "points": cloud(2).tolist()})
        assert refused.status_code == 503, refused.text
        assert "cannot reach postgresql://" in refused.json()["detail"]
        scene = cloud(1) @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]]).T
        aligned = server.client.post("/align", json={"points": scene.tolist()})
        assert aligned.status_code == 200 and aligned.json()["label"] == "first"

        retried: list[str] = []

        def told(error, wait_s: float) -> None:  # the database comes back once it was said
            retried.append(str(error))
            if len(retried) == 1:
                database.start(fsync=True)

        with Client(server.url, on_retry=told) as client:
            stored = client.register("second", cloud(3))
        assert retried and all(r.startswith("503: ") for r in retried), retried
        assert stored.raw["outcome"] == "created" and stored.points_sha256 == sha(cloud(3))
        with Client(server.url, retry_for=0) as once:
            again = once.register("second", cloud(3))  # its answer lost: sent again
            assert again.raw["outcome"] == "identical"
            assert sorted(r.name for r in once.references()) == ["first", "second"]
        assert sorted(server.app.state.catalog.store.checksums()) == ["first", "second"]
    finally:
        server.stop()


def test_retries_stop_within_their_bound():
    calls: list[float] = []
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    with Client(url, retry_for=1.0, on_retry=lambda _, wait: calls.append(wait)) as client:
        with pytest.raises(Unreachable, match=r"cannot reach .*\(after \d+ attempts\)") as raised:
            client.references()
    assert raised.value.attempts == len(calls) + 1 >= 2
    assert sum(calls) <= 1.0  # the waits stay within the bound
    with Client(url, retry_for=0) as client, pytest.raises(Unreachable) as once:
        client.references()
    assert once.value.attempts == 1
