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

import pytest

from service.engine.engine import Engine
from service.engine.mapping import Mapper
from service.gallery.catalog import Catalog
from service.gallery.sqlite_store import SQLiteStore
from service.settings import EngineSettings
from tests.ledger import Ledger, sha
from tests.servers import MODEL, ProcessServer, cloud, needs_model

pytestmark = needs_model

KILL_AFTER_S = (0.3, 1.0, 2.0)


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
        report.append((kill_after, ledger.write_until_killed(server, run, kill_after)))
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
    catalog.register("kept", cloud(seed=1))
    original = catalog.engine.add_many

    def refuse(*args):
        raise RuntimeError("the engine failed")

    monkeypatch.setattr(catalog.engine, "add_many", refuse)
    with pytest.raises(RuntimeError, match="engine failed"):
        catalog.register("new", cloud(seed=2))
    with pytest.raises(RuntimeError, match="engine failed"):
        catalog.register("kept", cloud(seed=3), replace=True)
    (record,) = store.load_records()
    assert record.reference.name == "kept"
    assert sha(record.reference.points) == sha(cloud(seed=1))
    monkeypatch.setattr(catalog.engine, "add_many", original)
    monkeypatch.setattr(catalog.engine, "remove", refuse)
    with pytest.raises(RuntimeError, match="engine failed"):
        catalog.remove("kept")
    assert [r.name for r in store.load_all()] == ["kept"]
