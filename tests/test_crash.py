"""A power cut mid-stream: every acknowledged change survives, nothing half-written shows.

``python -m service`` runs as a real process on one data directory. A few client threads
register references (and delete some) as fast as the service takes them; the process is killed
with SIGKILL 0.3 s, 1 s and 2 s into that (after the run's first acknowledgement), and
restarted each time. After every restart
each acknowledged registration is present with the sha256 of exactly the float32 points the
client sent, each acknowledged deletion is absent, the gallery loads (every stored checksum
holds), and every visible reference is one the client sent, byte for byte.
"""

from __future__ import annotations

import hashlib
import threading
import time

import httpx
import numpy as np
import pytest

from service.engine.engine import Engine
from service.engine.mapping import Mapper
from service.gallery.catalog import Catalog
from service.gallery.sqlite_store import SQLiteStore
from service.settings import EngineSettings
from tests.servers import MODEL, ProcessServer

pytestmark = pytest.mark.skipif(not MODEL.path.exists(), reason=f"no ONNX model at {MODEL.path}")

KILL_AFTER_S = (0.3, 1.0, 2.0)
WRITERS = 3


def cloud(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    count = int(rng.integers(64, 1000))
    return (rng.normal(size=(count, 3)) * rng.uniform(0.05, 0.5, 3)).astype(np.float32)


def sha(points: np.ndarray) -> str:
    return hashlib.sha256(points.astype("<f4").tobytes()).hexdigest()


class Ledger:
    """What the clients sent and what the service acknowledged."""

    def __init__(self):
        self.lock = threading.Lock()
        self.sent: dict[str, str] = {}  # every registration sent: name -> sha256 of its points
        self.registered: dict[str, str] = {}  # acknowledged (201), not deleted since
        self.deleted: set[str] = set()  # acknowledged deletions (204)
        self.unsure: set[str] = set()  # a deletion sent but not answered: either outcome is fine
        self.acknowledged = 0  # registrations
        self.changes = 0  # registrations and deletions
        self.failures: list[str] = []  # what went wrong in a client thread

    def write(self, url: str, run: int, writer: int, stop: threading.Event) -> None:
        try:
            self._write(url, run, writer, stop)
        except Exception as error:  # noqa: BLE001 - reported by the test's thread
            self.failures.append(repr(error))

    def _write(self, url: str, run: int, writer: int, stop: threading.Event) -> None:
        """Register new references; every third time delete an acknowledged one instead."""
        with httpx.Client(base_url=url, timeout=30) as client:
            for index in range(10_000):
                if stop.is_set():
                    return
                try:
                    if index % 3 == 0 and self._delete_one(client):
                        continue
                    self._register_one(client, f"r{run}-w{writer}-{index}")
                except httpx.TransportError:
                    return  # killed

    def _register_one(self, client: httpx.Client, name: str) -> None:
        points = cloud(hash(name) % 2**32)
        with self.lock:
            self.sent[name] = sha(points)
        response = client.post(
            "/references?self_check=false", json={"name": name, "points": points.tolist()}
        )
        assert response.status_code == 201, response.text
        with self.lock:
            self.registered[name] = self.sent[name]
            self.acknowledged += 1
            self.changes += 1

    def _delete_one(self, client: httpx.Client) -> bool:
        with self.lock:
            victims = [name for name in self.registered if name not in self.unsure]
            if not victims:
                return False
            victim = victims[0]
            self.unsure.add(victim)  # until the answer comes: either outcome is fine
        response = client.delete(f"/references/{victim}")
        assert response.status_code == 204, response.text
        with self.lock:
            self.unsure.discard(victim)
            self.registered.pop(victim)
            self.deleted.add(victim)
            self.changes += 1
        return True

    def check(self, client: httpx.Client) -> int:
        """After a restart: the acknowledged state, exactly; returns how many are present."""
        listed = {r["name"]: r for r in client.get("/references").json()["references"]}
        for name, digest in self.registered.items():
            if name in self.unsure:
                continue
            described = client.get(f"/references/{name}")
            assert described.status_code == 200, f"acknowledged {name} was lost"
            assert described.json()["points_sha256"] == digest, f"{name} differs"
        for name in self.deleted:
            assert name not in listed, f"acknowledged deletion of {name} was undone"
        for name, info in listed.items():
            assert name in self.sent, f"{name} was never sent"
            assert info["points_sha256"] == self.sent[name], f"{name} is not what was sent"
        return sum(name in listed for name in self.kept())

    def kept(self) -> list[str]:
        """Acknowledged registrations with no deletion sent since."""
        return [name for name in self.registered if name not in self.unsure]


def test_acknowledged_changes_survive_sigkill(tmp_path):
    data, log = tmp_path / "data", tmp_path / "service.log"
    settings = {
        "model__gallery": str(tmp_path / "no-seed.npz"),
        "engine__view_grids": "2",  # quicker registrations: more of them between the kills
        "server__log_level": "warning",
    }
    ledger = Ledger()
    report = []
    for run, kill_after in enumerate(KILL_AFTER_S):
        server = ProcessServer(data, log, **settings)
        if run:
            report[-1] += (ledger.check(server.client), len(ledger.kept()))
        changes_before = ledger.changes
        stop = threading.Event()
        writers = [
            threading.Thread(target=ledger.write, args=(server.url, run, k, stop), daemon=True)
            for k in range(WRITERS)
        ]
        for writer in writers:
            writer.start()
        deadline = time.monotonic() + 20
        while ledger.changes == changes_before and time.monotonic() < deadline:
            time.sleep(0.01)  # the stream flows: the first change of this run is acknowledged
        time.sleep(kill_after)
        server.kill()
        stop.set()
        for writer in writers:
            writer.join(timeout=30)
            assert not writer.is_alive()
        report.append((kill_after, ledger.changes - changes_before))
    server = ProcessServer(data, log, **settings)
    try:
        present = ledger.check(server.client)
        report[-1] += (present, len(ledger.kept()))
    finally:
        server.stop()
    assert ledger.failures == []
    assert ledger.acknowledged > 0 and len(ledger.deleted) > 0
    assert present == len(ledger.kept())
    runs = "; ".join(
        f"killed {after} s in: {changes} changes acknowledged, then {found}/{kept} present"
        for after, changes, found, kept in report
    )
    print(
        f"\nkill test: {ledger.acknowledged} registrations acknowledged ({len(ledger.sent)} sent),"
        f" {len(ledger.deleted)} deletions acknowledged; {runs}"
    )


def test_a_change_the_engine_cannot_follow_is_undone_in_the_store(tmp_path, monkeypatch):
    """Store first, engine second: when the second step fails, the first is rolled back, so a
    restart cannot resurrect what the caller was told failed."""
    store = SQLiteStore.in_dir(tmp_path)
    catalog = Catalog(Engine(Mapper(MODEL.path), EngineSettings(view_grids=2)), store, 10)
    catalog.register("kept", cloud(1))
    original = catalog.engine.add

    def refuse(*args):
        raise RuntimeError("the engine failed")

    monkeypatch.setattr(catalog.engine, "add", refuse)
    with pytest.raises(RuntimeError, match="engine failed"):
        catalog.register("new", cloud(2))
    with pytest.raises(RuntimeError, match="engine failed"):
        catalog.register("kept", cloud(3), replace=True)
    (record,) = store.load_records()
    assert record.reference.name == "kept"
    assert sha(record.reference.points) == sha(cloud(1))
    monkeypatch.setattr(catalog.engine, "add", original)
    monkeypatch.setattr(catalog.engine, "remove", refuse)
    with pytest.raises(RuntimeError, match="engine failed"):
        catalog.remove("kept")
    assert [r.name for r in store.load_all()] == ["kept"]
