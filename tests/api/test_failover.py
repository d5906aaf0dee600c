"""Failover with the real parts, small enough for CI: ``benchmarks.failover`` (a throwaway
PostgreSQL, two ``python -m service`` replicas, Debian's nginx with ``deploy/nginx.conf``) with
one client aligning and one registering through the proxy, a replica killed in the middle of a
registration and started again, and PostgreSQL restarted. Skipped, saying what to install,
without nginx or PostgreSQL's server.

No ``/align`` fails; the killed replica is back in rotation; during the outage a registration
is answered 503 with the reason; every acknowledged registration is on both replicas with the
points it was sent with.
"""

from __future__ import annotations

import pytest

from benchmarks import failover
from evaluation import postgres, proxy
from tests.servers import MODEL

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not MODEL.path.exists(), reason=f"no ONNX model at {MODEL.path}"),
]


def test_a_replica_killed_and_the_database_restarted_under_load():
    if postgres.server_binaries() is None:
        pytest.skip(f"needs PostgreSQL's server: {postgres.INSTALL_HINT}")
    args = failover.parse_args(
        [
            "--references=4",
            "--clients=1",
            "--registrars=1",
            "--kills=1",
            "--steady-s=1",
            "--down-s=0.5",
            "--db-down-s=3",
            "--connect-timeout-s=1",
            "--no-self-check",
            "--setting=engine__view_grids=2",
        ]
    )
    try:
        report = failover.run(args)
    except proxy.Unavailable as error:
        pytest.skip(f"needs nginx: {error}")
    align, registrations = report["align"], report["registrations"]
    assert align["requests"] > 0 and align["failed"] == 0, align
    assert set(align["by_phase"]) >= {"replica-down", "rejoining", "database-down"}
    (kill,) = report["replica_kills"]
    assert kill["restart_to_rejoined_s"] >= kill["restart_to_ready_s"] > 0
    probe = report["database_restart"]["registration_without_retry_during_outage"]
    assert probe["status"] == 503 and "cannot reach postgresql://" in probe["detail"], probe
    assert registrations["acknowledged"] > 0 and registrations["lost"] == []
    assert registrations["gave_up"] == []
    assert "409" not in str(registrations["answered_after_retries"])


def test_the_proxy_serves_the_project_s_own_configuration(tmp_path):
    """Only the replicas' addresses, the port and where nginx keeps its files change; every
    other line of deploy/nginx.conf (balancing, retries, locations) is served as it is."""
    shipped = proxy.CONFIG.read_text()
    rendered = proxy.render(shipped, ["127.0.0.1:7001", "127.0.0.1:7002"], 7000, tmp_path)
    moved = ("server replica-", "listen 8080;")
    kept = [line for line in shipped.splitlines() if not line.strip().startswith(moved)]
    lines = rendered.splitlines()
    assert all(line in lines for line in kept)
    assert "        server 127.0.0.1:7001 max_fails=3 fail_timeout=5s;" in lines
    assert "        listen 127.0.0.1:7000;" in lines
    assert "replica-a" not in rendered and "8080" not in rendered
