"""The gallery store, against each backend (SQLite, PostgreSQL): round trips byte-identical,
survives a restart, writes all or none, stores fields it was never told about, and the version
every write raises."""

import dataclasses
import hashlib
import json
import sqlite3
import threading

import numpy as np
import pytest

from service.engine.reference import Reference
from service.errors import ReferenceExists, StoreUnavailable, UnknownReference
from service.gallery.postgres_store import PostgresStore
from service.gallery.sqlite_store import SQLiteStore
from service.gallery.store import SCHEMA_VERSION, StoreCorrupted, StoreIncompatible
from tests.backends import Location

MODEL = "a" * 64


def reference(name: str, seed: int = 0, count: int = 100) -> Reference:
    """A reference with every field filled, of the right dtypes and shapes (random values: the
    store keeps bytes, it does not look into them)."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(count, 3)).astype(np.float32)
    return Reference(
        name=name,
        points=points,
        mapped=rng.normal(size=(count, 2)).astype(np.float32),
        view_grids=rng.random(size=(2, 64, 64)).astype(np.float32),
        scale=float(np.linalg.norm(points - points.mean(axis=0), axis=1).max()),
        normals=rng.normal(size=(count, 3)).astype(np.float32),
        visibility=rng.integers(0, 256, size=(4, (count + 7) // 8), dtype=np.uint8),
        view_features=rng.random(size=(4, 256)).astype(np.float16),
        field=rng.integers(0, count, size=(5, 6, 7), dtype=np.uint16),
        field_frame=rng.normal(size=4),
        symmetry={"kind": "revolution", "axis": [0.0, 0.0, 1.0], "flip": True},
    )


def assert_identical(a: Reference, b: Reference, fields: tuple[str, ...] | None = None) -> None:
    """The same name, scale and bytes in every field (or in ``fields``)."""
    assert a.name == b.name and a.scale == b.scale
    names = fields or tuple(item.name for item in dataclasses.fields(Reference))
    for name in names:
        x, y = getattr(a, name), getattr(b, name)
        if not isinstance(x, np.ndarray):
            assert x == y, name
        else:
            assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()


@pytest.fixture
def location(backend):
    return backend.new()


@pytest.fixture
def store(location):
    opened = location.store()
    yield opened
    opened.close()


def test_a_new_store_is_empty(store):
    assert store.is_empty() and store.count() == 0 and store.load_all() == []
    assert store.get_meta("schema_version") == SCHEMA_VERSION


def test_put_and_load_are_byte_identical(store):
    stored = [reference("b", 1), reference("a", 2, count=37), reference("B", 3)]
    for item in stored:
        store.put(item, MODEL)
    loaded = store.load_all()
    assert [r.name for r in loaded] == ["B", "a", "b"]  # by name, the same on both backends
    for item in loaded:
        assert_identical(item, next(s for s in stored if s.name == item.name))
    assert store.count() == 3 and not store.is_empty()
    (record,) = [r for r in store.load_records() if r.name == "a"]
    assert record.model_hash == MODEL and record.created_at.endswith("+00:00")
    assert record.missing == () and store.checksums()["a"] == record.sha256
    assert [r.name for r in store.load_records(["b", "gone", "a"])] == ["a", "b"]


def test_a_duplicate_name_is_refused_unless_replaced(store):
    store.put(reference("part", 1), MODEL)
    with pytest.raises(ReferenceExists, match="'part' exists"):
        store.put(reference("part", 2), MODEL)
    assert_identical(store.load_all()[0], reference("part", 1))
    store.put(reference("part", 3), "b" * 64, replace=True)
    (record,) = store.load_records()
    assert_identical(record.reference, reference("part", 3))
    assert record.model_hash == "b" * 64


def test_delete(store):
    store.put(reference("a"), MODEL)
    store.put(reference("b"), MODEL)
    store.delete("a")
    assert [r.name for r in store.load_all()] == ["b"]
    with pytest.raises(UnknownReference, match="no reference named 'a'"):
        store.delete("a")


def test_a_restart_sees_everything(store, location):
    store.put(reference("a", 1), MODEL)
    store.put(reference("b", 2), MODEL)
    store.delete("b")
    store.set_meta("seeded_from", "gallery.npz")
    again = location.store()
    (loaded,) = again.load_all()
    assert_identical(loaded, reference("a", 1))
    assert again.get_meta("seeded_from") == "gallery.npz"
    again.close()


def test_a_failed_transaction_leaves_nothing(store, location):
    store.put(reference("b"), MODEL)
    version = store.version()
    batch = [reference("a"), reference("c"), reference("b")]  # "b" exists: the batch fails
    with pytest.raises(ReferenceExists):
        store.put_many(batch, MODEL, meta={"seeded_from": "x"})
    with pytest.raises(UnknownReference):
        store.delete("nothing")
    again = location.store()
    assert [r.name for r in again.load_all()] == ["b"]
    again.close()
    assert store.get_meta("seeded_from") is None and store.version() == version


def test_damaged_data_is_detected_on_load(store, location):
    store.put(reference("a"), MODEL)
    (record,) = store.load_records()
    blob = bytearray(reference("a").points.tobytes())
    blob[7] ^= 0xFF
    location.execute("UPDATE reference SET arrays = ?", (bytes(blob) + b"\0" * 99,))
    with pytest.raises(StoreCorrupted, match="'a': checksum mismatch"):
        store.load_all()
    location.execute("UPDATE reference SET extras = ?", ('{"scale": 2.0}',))
    with pytest.raises(StoreCorrupted, match="'a': checksum mismatch"):
        store.load_records(["a"])


def test_a_big_endian_array_is_stored_little_endian(store):
    item = reference("a")
    swapped = Reference(
        item.name, item.points.astype(">f4"), item.mapped, item.view_grids, item.scale
    )
    store.put(swapped, MODEL)
    loaded = store.load_all()[0]
    assert loaded.points.dtype == np.dtype("<f4")
    np.testing.assert_array_equal(loaded.points, item.points)


# --- fields the store was never told about --------------------------------------------


@dataclasses.dataclass(frozen=True)
class LaterReference(Reference):
    """What a later version's ``Reference`` may hold: more arrays, a JSON-able description."""

    edges: np.ndarray = None  # type: ignore[assignment]
    notes: dict = None  # type: ignore[assignment]


@dataclasses.dataclass(frozen=True)
class EarlierReference:
    """What an earlier version's ``Reference`` held: no view grids yet."""

    name: str
    points: np.ndarray
    mapped: np.ndarray
    scale: float


def test_a_new_field_is_stored_without_store_code(store):
    base = reference("a")
    edges = np.random.default_rng(1).normal(size=(100, 3)).astype(np.float64)
    notes = {"kind": "bracket", "holes": [0.0, 0.0, 1.0]}
    fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(Reference)}
    later = LaterReference(**fields, edges=edges, notes=notes)
    store.put(later, MODEL)
    (record,) = store.load_records()
    assert record.values["edges"].dtype == np.float64
    assert record.values["edges"].tobytes() == edges.tobytes()
    assert record.values["notes"] == notes
    assert_identical(record.reference, base)  # this version's Reference leaves them out


def test_a_row_without_a_field_this_version_needs_is_marked_missing(store):
    base = reference("old")
    store.put(EarlierReference(base.name, base.points, base.mapped, base.scale), MODEL)
    (record,) = store.load_records()
    assert "view_grids" in record.missing  # and every field derived at registration
    assert record.points.tobytes() == base.points.tobytes()
    with pytest.raises(ValueError, match="without view_grids: recompute"):
        assert record.reference


# --- what replicas rely on ------------------------------------------------------------


def test_every_write_raises_the_version(store):
    first = store.version()
    store.put(reference("a"), MODEL)
    store.put_many([reference("b"), reference("c")], MODEL)
    store.delete("b")
    assert store.version() == first + 3
    assert set(store.checksums()) == {"a", "c"}


def test_seeding_happens_once(store):
    assert store.seed([reference("a"), reference("b")], MODEL, "gallery.npz")
    assert not store.seed([reference("c")], MODEL, "gallery.npz")
    assert [r.name for r in store.load_all()] == ["a", "b"]
    assert store.get_meta("seeded_from") == "gallery.npz"


def test_a_store_with_references_is_never_seeded_over(store):
    store.put(reference("mine"), MODEL)
    assert not store.seed([reference("a")], MODEL, "gallery.npz")
    assert [r.name for r in store.load_all()] == ["mine"] and store.get_meta("seeded_from") == ""


def test_a_rewrite_only_replaces_the_row_it_read(store):
    was = store.put(reference("a", 1), MODEL)
    recomputed = store.rewrite(reference("a", 2), "b" * 64, was=was)
    assert recomputed == store.checksums()["a"] != was
    assert store.rewrite(reference("a", 3), "c" * 64, was=was) is None  # changed meanwhile
    store.delete("a")
    assert store.rewrite(reference("a", 4), "c" * 64, was=recomputed) is None  # deleted
    assert store.is_empty()


def test_concurrent_writers_lose_nothing(location):
    """Two stores (two replicas' pools) writing at once: every write lands, versions count."""
    stores = [location.store(), location.store()]
    first = stores[0].version()

    def write(index: int) -> None:
        for k in range(10):
            stores[index].put(reference(f"w{index}-{k}", k, count=20), MODEL)

    threads = [threading.Thread(target=write, args=(i,)) for i in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert stores[1].count() == 20 and stores[0].version() == first + 20
    for item in stores:
        item.close()


def test_a_newer_schema_is_refused(store, location):
    location.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", ("99",))
    with pytest.raises(StoreIncompatible, match="schema version 99, newer"):
        location.store()


def test_another_replica_hears_of_a_change(postgres_server, tmp_path):
    """With PostgreSQL a write wakes a replica waiting for changes (LISTEN/NOTIFY); without
    the notification the wait would run its whole minute."""
    location = Location(tmp_path, postgres_server.create_database())
    writer, listener = location.store(), location.store()
    listener.wait_for_change(60)  # connects and listens: returns at once
    woken = threading.Event()
    waiting = threading.Thread(target=lambda: (listener.wait_for_change(60), woken.set()))
    waiting.start()
    writer.put(reference("a"), MODEL)
    waiting.join(timeout=20)
    assert woken.is_set()
    writer.close()
    listener.close()


# --- SQLite: the file, and the schema of version 1 ------------------------------------


def test_sqlite_is_in_wal_mode(tmp_path):
    store = SQLiteStore.in_dir(tmp_path)
    with sqlite3.connect(store.path) as conn:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    conn.close()


# Schema version 1, exactly as the service wrote it before version 2.
SCHEMA_V1 = """
CREATE TABLE IF NOT EXISTS meta (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS reference (
    name        TEXT PRIMARY KEY,
    num_points  INTEGER NOT NULL,
    scale       REAL NOT NULL,
    points      BLOB NOT NULL,
    mapped      BLOB NOT NULL,
    view_grids  BLOB NOT NULL,
    layout      TEXT NOT NULL,  -- JSON: {"points": {"dtype": "<f4", "shape": [N, 3]}, ...}
    sha256      TEXT NOT NULL,  -- of the arrays' layout and bytes and the scale
    model_hash  TEXT NOT NULL,  -- sha256 of the ONNX file that computed "mapped"
    created_at  TEXT NOT NULL   -- ISO 8601, UTC
);
"""


def write_v1(path, references: list[Reference], model_hashes: list[str]) -> None:
    """A gallery file of schema version 1, rows as version 1 wrote them."""
    conn = sqlite3.connect(path)
    with conn:
        conn.executescript(SCHEMA_V1)
        conn.execute("INSERT INTO meta VALUES ('schema_version', '1')")
        conn.execute("INSERT INTO meta VALUES ('seeded_from', 'models/gallery.npz')")
        for index, (item, model_hash) in enumerate(zip(references, model_hashes, strict=True)):
            arrays = {k: getattr(item, k) for k in ("points", "mapped", "view_grids")}
            digest = hashlib.sha256()
            for key, array in arrays.items():
                digest.update(f"{key}|{array.dtype.str}|{array.shape}|".encode() + array.tobytes())
            digest.update(f"scale|{item.scale!r}".encode())
            layout = {k: {"dtype": a.dtype.str, "shape": list(a.shape)} for k, a in arrays.items()}
            conn.execute(
                "INSERT INTO reference VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    item.name,
                    len(item.points),
                    item.scale,
                    *(a.tobytes() for a in arrays.values()),
                    json.dumps(layout),
                    digest.hexdigest(),
                    model_hash,
                    f"2026-11-0{index + 1}T00:00Z",
                ),
            )
    conn.close()


def test_a_version_1_gallery_is_migrated_with_nothing_lost(tmp_path):
    references = [reference(f"part-{k}", k, count=50 + k) for k in range(5)]
    hashes = [MODEL, MODEL, "b" * 64, MODEL, "c" * 64]
    write_v1(tmp_path / "gallery.sqlite3", references, hashes)
    store = SQLiteStore.in_dir(tmp_path)
    assert store.get_meta("schema_version") == SCHEMA_VERSION
    assert store.get_meta("seeded_from") == "models/gallery.npz"
    records = store.load_records()
    assert [r.name for r in records] == [r.name for r in references]
    for record, item, model_hash in zip(records, references, hashes, strict=True):
        assert record.reference.points_sha256 == item.points_sha256  # byte-identical points
        assert_identical(record.reference, item, ("points", "mapped", "view_grids"))
        assert "normals" in record.missing  # derived since version 1: the catalog computes it
        assert record.model_hash == model_hash and record.created_at.startswith("2026-11-0")
    store.put(reference("new"), MODEL)  # and it takes writes as a version 2 store
    assert SQLiteStore.in_dir(tmp_path).count() == 6


def test_a_damaged_version_1_row_stops_the_migration_and_changes_nothing(tmp_path):
    write_v1(tmp_path / "gallery.sqlite3", [reference("a"), reference("b")], [MODEL, MODEL])
    with sqlite3.connect(tmp_path / "gallery.sqlite3") as conn:
        conn.execute("UPDATE reference SET scale = scale * 2 WHERE name = 'b'")
    conn.close()
    before = (tmp_path / "gallery.sqlite3").read_bytes()
    with pytest.raises(StoreCorrupted, match="'b': checksum mismatch.*schema version 1"):
        SQLiteStore.in_dir(tmp_path)
    with sqlite3.connect(tmp_path / "gallery.sqlite3") as conn:
        assert conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone() == (
            "1",
        )
        assert conn.execute("SELECT COUNT(*) FROM reference").fetchone() == (2,)
    conn.close()
    assert len(before) > 0


def test_a_postgresql_store_out_of_reach_says_where_but_never_the_password():
    store = PostgresStore(
        "postgresql://dpc:hunter2@127.0.0.1:1/gallery?password=hunter3", 1, True, 1
    )
    try:
        with pytest.raises(StoreUnavailable) as raised:
            store.check()
        message = str(raised.value)
        assert "postgresql://dpc@127.0.0.1:1/gallery" in message and "hunter" not in message
    finally:
        store.close()
