"""What clients sent and what the service acknowledged, for the kill tests: a few writer threads
register references (and delete some) as fast as a server takes them; ``check`` then compares a
server's gallery with the acknowledged state."""

from __future__ import annotations

import hashlib
import threading
import time

import httpx
import numpy as np

from tests.servers import cloud, eventually


def varied_cloud(seed: int) -> np.ndarray:
    """A ``cloud`` of 64-999 points and a spread of 5-50 cm along each axis, drawn by ``seed``."""
    rng = np.random.default_rng(seed)
    return cloud(int(rng.integers(64, 1000)), seed, rng.uniform(0.05, 0.5, 3))


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

    def write_until_killed(self, server, run: int, kill_after: float, writers: int = 3) -> int:
        """Writer threads on ``server`` (a ``ProcessServer``) until it is killed with SIGKILL,
        ``kill_after`` s after the run's first acknowledgement; the changes acknowledged."""
        changes_before = self.changes
        stop = threading.Event()
        threads = [
            threading.Thread(target=self.write, args=(server.url, run, k, stop), daemon=True)
            for k in range(writers)
        ]
        for thread in threads:
            thread.start()
        try:
            eventually(lambda: self.flowing(changes_before), timeout=20, every_s=0.01)
            time.sleep(kill_after)  # when in the stream the power fails: what the test varies
        finally:
            server.kill()
            stop.set()
        for thread in threads:
            thread.join(timeout=30)
            assert not thread.is_alive()
        return self.changes - changes_before

    def flowing(self, changes_before: int) -> None:
        """Raises until a change after the first ``changes_before`` is acknowledged."""
        assert self.changes > changes_before or self.failures, "no change acknowledged yet"

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
        points = varied_cloud(hash(name) % 2**32)
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
