"""The SQLite gallery store: round trips byte-identical, survives a restart, writes all or none."""

import sqlite3

import numpy as np
import pytest

from service.engine.reference import Reference
from service.errors import ReferenceExists, UnknownReference
from service.gallery.store import GalleryStore, StoreCorrupted

MODEL = "a" * 64


def reference(name: str, seed: int = 0, count: int = 100) -> Reference:
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(count, 3)).astype(np.float32)
    return Reference(
        name=name,
        points=points,
        mapped=rng.normal(size=(count, 2)).astype(np.float32),
        view_grids=rng.random(size=(2, 64, 64)).astype(np.float32),
        scale=float(np.linalg.norm(points - points.mean(axis=0), axis=1).max()),
    )


def assert_identical(a: Reference, b: Reference) -> None:
    assert a.name == b.name and a.scale == b.scale
    for field in ("points", "mapped", "view_grids"):
        x, y = getattr(a, field), getattr(b, field)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()


@pytest.fixture
def store(tmp_path) -> GalleryStore:
    return GalleryStore.in_dir(tmp_path / "data")


def test_a_new_store_is_empty_and_in_wal_mode(store):
    assert store.is_empty() and store.count() == 0 and store.load_all() == []
    with sqlite3.connect(store.path) as conn:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_put_and_load_are_byte_identical(store):
    stored = [reference("b", 1), reference("a", 2, count=37)]
    for item in stored:
        store.put(item, MODEL)
    loaded = store.load_all()
    assert [r.name for r in loaded] == ["a", "b"]  # by name
    for item in loaded:
        assert_identical(item, next(s for s in stored if s.name == item.name))
    assert store.count() == 2 and not store.is_empty()
    (record,) = [r for r in store.load_records() if r.reference.name == "a"]
    assert record.model_hash == MODEL and record.created_at.endswith("+00:00")


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


def test_a_restart_sees_everything(store):
    store.put(reference("a", 1), MODEL)
    store.put(reference("b", 2), MODEL)
    store.delete("b")
    store.set_meta("seeded_from", "gallery.npz")
    again = GalleryStore(store.path)
    (loaded,) = again.load_all()
    assert_identical(loaded, reference("a", 1))
    assert again.get_meta("seeded_from") == "gallery.npz"


def test_a_failed_transaction_leaves_nothing(store):
    store.put(reference("b"), MODEL)
    batch = [reference("a"), reference("c"), reference("b")]  # "b" exists: the batch fails
    with pytest.raises(ReferenceExists):
        store.put_many(batch, MODEL, meta={"seeded_from": "x"})
    assert [r.name for r in GalleryStore(store.path).load_all()] == ["b"]
    assert store.get_meta("seeded_from") is None


def test_damaged_data_is_detected_on_load(store):
    store.put(reference("a"), MODEL)
    with sqlite3.connect(store.path) as conn:
        blob = bytearray(conn.execute("SELECT points FROM reference").fetchone()[0])
        blob[7] ^= 0xFF
        conn.execute("UPDATE reference SET points = ?", (bytes(blob),))
    with pytest.raises(StoreCorrupted, match="'a': checksum mismatch"):
        store.load_all()


def test_a_big_endian_array_is_stored_little_endian(store):
    item = reference("a")
    swapped = Reference(
        item.name, item.points.astype(">f4"), item.mapped, item.view_grids, item.scale
    )
    store.put(swapped, MODEL)
    loaded = store.load_all()[0]
    assert loaded.points.dtype == np.dtype("<f4")
    np.testing.assert_array_equal(loaded.points, item.points)
