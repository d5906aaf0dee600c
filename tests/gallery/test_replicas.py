"""Replicas on one PostgreSQL gallery: real ``python -m service`` processes on a throwaway
PostgreSQL server (``evaluation.postgres``; skipped, saying what to install, without one).

What one replica changes, the other serves (each keeps its snapshot in memory and follows the
store: LISTEN/NOTIFY, and the version check as the fallback). A replica killed with SIGKILL in
the middle of registrations and deletions loses nothing it acknowledged, and leaves nothing
half-written, as the other replica sees it. A replica that cannot reach the database is not
ready, says why, still aligns from its snapshot, and is ready again once the database is back;
one started before its database waits for it.
"""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from tests.backends import Location
from tests.ledger import Ledger, sha
from tests.servers import ProcessServer, ServiceProcess, cloud, eventually, needs_model

pytestmark = needs_model

KILL_AFTER_S = (0.3, 1.0, 2.0)
FOLLOW_TIMEOUT_S = 15.0  # a generous bound on the wait for a replica to follow (target: 1 s)


@pytest.fixture
def shared(postgres_server, tmp_path) -> Location:
    return Location(tmp_path / "data", postgres_server.create_database())


def replica(location: Location, log, **settings: str) -> ProcessServer:
    return ProcessServer(
        location.data_dir,
        log,
        gallery__url=location.url,
        model__gallery=str(location.data_dir / "no-seed.npz"),
        engine__view_grids="2",  # quicker registrations
        server__log_level="warning",
        **settings,
    )


def status(client: httpx.Client, method: str, path: str, expected: int, **kwargs) -> httpx.Response:
    response = client.request(method, path, **kwargs)
    assert response.status_code == expected, response.text
    return response


def test_a_change_on_one_replica_is_served_by_the_other(shared, tmp_path):
    a = replica(shared, tmp_path / "a.log")
    b = replica(shared, tmp_path / "b.log")
    try:
        points = cloud(seed=1)
        status(
            a.client, "POST", "/references", 201, json={"name": "part", "points": points.tolist()}
        )
        described = eventually(
            lambda: status(b.client, "GET", "/references/part", 200), FOLLOW_TIMEOUT_S
        )
        assert described.json()["points_sha256"] == sha(points)
        scene = (points @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]]).T + 0.1).astype("<f4")
        aligned = status(b.client, "POST", "/align", 200, json={"points": scene.tolist()})
        assert aligned.json()["label"] == "part"

        other = cloud(seed=2)
        body = {"name": "part", "points": other.tolist()}
        status(b.client, "POST", "/references?replace=true&self_check=false", 200, json=body)
        eventually(
            lambda: assert_sha(status(a.client, "GET", "/references/part", 200), sha(other)),
            FOLLOW_TIMEOUT_S,
        )
        status(b.client, "DELETE", "/references/part", 204)
        eventually(lambda: status(a.client, "GET", "/references/part", 404), FOLLOW_TIMEOUT_S)
        status(a.client, "POST", "/align", 409, json={"points": scene.tolist()})  # none left
        status(a.client, "DELETE", "/references/part", 404)
    finally:
        a.stop()
        b.stop()


def assert_sha(response: httpx.Response, expected: str) -> None:
    assert response.json()["points_sha256"] == expected


def test_acknowledged_changes_survive_sigkill_of_a_replica(shared, tmp_path):
    """Writers on replica A, killed 0.3, 1 and 2 s into a stream; replica B, never killed,
    serves exactly the acknowledged state after each kill, and so does A restarted."""
    ledger = Ledger()
    report = []
    b = replica(shared, tmp_path / "b.log")
    try:
        for run, kill_after in enumerate(KILL_AFTER_S):
            a = replica(shared, tmp_path / "a.log")
            changes = ledger.write_until_killed(a, run, kill_after)
            present = eventually(lambda: caught_up(ledger, b.client), FOLLOW_TIMEOUT_S)
            report.append((kill_after, changes, present, len(ledger.kept())))
        a = replica(shared, tmp_path / "a.log")
        try:
            assert ledger.check(a.client) == len(ledger.kept())
        finally:
            a.stop()
    finally:
        b.stop()
    assert ledger.failures == []
    assert ledger.acknowledged > 0 and len(ledger.deleted) > 0
    assert all(present == kept for *_, present, kept in report)
    runs = "; ".join(
        f"A killed {after} s in: {changes} changes acknowledged, then {found}/{kept} on B"
        for after, changes, found, kept in report
    )
    print(
        f"\nreplica kill test: {ledger.acknowledged} registrations acknowledged "
        f"({len(ledger.sent)} sent), {len(ledger.deleted)} deletions acknowledged; {runs}"
    )


def caught_up(ledger: Ledger, client: httpx.Client) -> int:
    """The acknowledged state on a replica, once it lists every kept reference (it may list
    the gallery before it has followed the last changes, and describe them just after)."""
    present = ledger.check(client)
    assert present == len(ledger.kept()), "not followed yet"
    return present


def test_a_replica_out_of_reach_of_the_database_is_not_ready_and_says_why(
    shared, postgres_server, tmp_path
):
    server = replica(shared, tmp_path / "a.log", gallery__poll_s="0.2")
    database = shared.url.rsplit("/", 1)[1]
    admin = psycopg_admin(postgres_server.url)
    try:
        points = cloud(seed=3)
        status(
            server.client, "POST", "/references", 201, json={"name": "p", "points": points.tolist()}
        )
        assert server.client.get("/v2/health/ready").json() == {"ready": True, "detail": None}
        admin.execute(f'ALTER DATABASE "{database}" ALLOW_CONNECTIONS false')
        admin.execute(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s", (database,)
        )
        ready = eventually(
            lambda: status(server.client, "GET", "/v2/health/ready", 503), FOLLOW_TIMEOUT_S
        )
        assert ready.json()["ready"] is False
        assert "gallery store cannot be used" in ready.json()["detail"]
        assert database in ready.json()["detail"]  # where it looked
        assert server.client.get("/v2/health/live").status_code == 200
        status(server.client, "POST", "/align", 200, json={"points": points.tolist()})  # memory
        refused = status(
            server.client, "POST", "/references", 503, json={"name": "q", "points": points.tolist()}
        )
        assert database in refused.json()["detail"]

        admin.execute(f'ALTER DATABASE "{database}" ALLOW_CONNECTIONS true')
        eventually(lambda: status(server.client, "GET", "/v2/health/ready", 200), timeout=60)
        status(
            server.client, "POST", "/references", 201, json={"name": "q", "points": points.tolist()}
        )
    finally:
        admin.execute(f'ALTER DATABASE "{database}" ALLOW_CONNECTIONS true')
        admin.close()
        server.stop()


def psycopg_admin(url: str):
    import psycopg

    return psycopg.connect(url, autocommit=True)


def test_a_replica_started_before_its_database_waits_for_it(postgres_server, tmp_path):
    name = f"later_{tmp_path.name[-12:].replace('-', '_').lower()}"
    url = postgres_server.database_url(name)
    location = Location(tmp_path / "data", url)
    process = ServiceProcess(
        tmp_path / "later.log",
        wait=False,
        gallery__url=url,
        gallery__data_dir=str(location.data_dir),
        model__gallery=str(tmp_path / "no-seed.npz"),
        server__log_level="warning",
    )
    try:
        with httpx.Client(base_url=process.url, timeout=10) as client:

            def waiting() -> None:
                detail = status(client, "GET", "/v2/health/ready", 503).json()["detail"]
                assert "waiting for the gallery store" in detail and name in detail, detail

            eventually(waiting, timeout=60)
            assert process.alive()
            admin = psycopg_admin(postgres_server.url)
            admin.execute(f'CREATE DATABASE "{name}"')
            admin.close()
            eventually(lambda: status(client, "GET", "/v2/health/ready", 200), timeout=60)
            store = location.store()
            assert store.get_meta("schema_version") == "2"
            store.close()
    finally:
        process.stop()
