"""The registered references, durable: one SQLite file under ``settings.gallery.data_dir``.

One row a reference: its arrays as little-endian blobs (dtype and shape beside them), its
scale, a sha256 of all of that (checked on every load), the hash of the ONNX model its mapped
coordinates were computed with, and when it was registered. Every write is one transaction;
the journal is WAL with ``synchronous=FULL``, so an acknowledged write survives a power cut.
A connection is opened per operation, so the store is safe to use from any thread.
"""

from __future__ import annotations

import hashlib
import json
import sqlite3
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from service.engine.reference import Reference
from service.errors import ReferenceExists, UnknownReference

FILENAME = "gallery.sqlite3"
SCHEMA_VERSION = "1"
ARRAYS = ("points", "mapped", "view_grids")  # the Reference fields stored as blobs

SCHEMA = """
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


class StoreCorrupted(RuntimeError):
    """A stored reference whose checksum does not match its data."""


class StoreIncompatible(RuntimeError):
    """A database this code cannot use: written by a newer version, or not a gallery at all."""


@dataclass(frozen=True)
class StoredReference:
    reference: Reference
    model_hash: str
    created_at: str


class GalleryStore:
    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            with self._connect() as conn:
                self._check_version(conn)  # before writing anything to it
                conn.execute("PRAGMA journal_mode=WAL")
                with conn:
                    conn.executescript(SCHEMA)
                    conn.execute(
                        "INSERT OR IGNORE INTO meta (key, value) VALUES ('schema_version', ?)",
                        (SCHEMA_VERSION,),
                    )
        except sqlite3.DatabaseError as error:  # not a database, or a damaged one
            raise StoreIncompatible(f"{self.path} is not a usable SQLite file: {error}") from error

    def _check_version(self, conn: sqlite3.Connection) -> None:
        """A newer schema stops here: this code would misread it or write over it."""
        has_meta = conn.execute(
            "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'meta'"
        ).fetchone()
        version = self._meta(conn, "schema_version") if has_meta else None
        if version is None or version == SCHEMA_VERSION:
            return
        if not version.isdigit() or int(version) > int(SCHEMA_VERSION):
            raise StoreIncompatible(
                f"{self.path} has gallery schema version {version}, newer than this service's "
                f"{SCHEMA_VERSION}: run the service version that wrote it, or move the file "
                "away to start a new gallery (docs/operations.md)"
            )
        raise StoreIncompatible(  # older: no migration exists yet (version 1 is the first)
            f"{self.path} has gallery schema version {version}, older than this service's "
            f"{SCHEMA_VERSION}, and no migration exists: rebuild it (docs/operations.md)"
        )

    @classmethod
    def in_dir(cls, data_dir: str | Path) -> GalleryStore:
        return cls(Path(data_dir) / FILENAME)

    # Reads
    def load_all(self) -> list[Reference]:
        """Every reference, by name, each checked against its checksum."""
        return [record.reference for record in self.load_records()]

    def load_records(self) -> list[StoredReference]:
        """Every reference with the model hash it was computed with and when it was registered."""
        with self._connect() as conn:
            rows = conn.execute(
                "SELECT name, scale, points, mapped, view_grids, layout, sha256, model_hash,"
                " created_at FROM reference ORDER BY name"
            ).fetchall()
        return [_record(row) for row in rows]

    def count(self) -> int:
        with self._connect() as conn:
            return conn.execute("SELECT COUNT(*) FROM reference").fetchone()[0]

    def is_empty(self) -> bool:
        return self.count() == 0

    def get_meta(self, key: str) -> str | None:
        with self._connect() as conn:
            return self._meta(conn, key)

    # Writes: each one transaction
    def put(self, reference: Reference, model_hash: str, replace: bool = False) -> None:
        """Store one reference; ``ReferenceExists`` if its name is taken and not ``replace``."""
        self.put_many([reference], model_hash, replace=replace)

    def put_many(
        self,
        references: Iterable[Reference],
        model_hash: str,
        replace: bool = False,
        meta: dict[str, str] | None = None,
    ) -> None:
        """Store several references and meta entries, all or none."""
        verb = "INSERT OR REPLACE" if replace else "INSERT"
        created_at = datetime.now(UTC).isoformat(timespec="milliseconds")
        with self._connect() as conn, conn:
            for reference in references:
                try:
                    conn.execute(
                        f"{verb} INTO reference (name, num_points, scale, points, mapped,"
                        " view_grids, layout, sha256, model_hash, created_at)"
                        " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                        _row(reference, model_hash, created_at),
                    )
                except sqlite3.IntegrityError as error:
                    raise ReferenceExists(
                        f"a reference named '{reference.name}' exists: pick another name or "
                        "pass replace=true"
                    ) from error
            for key, value in (meta or {}).items():
                conn.execute("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", (key, value))

    def delete(self, name: str) -> None:
        """Remove one reference; ``UnknownReference`` if there is none of that name."""
        with self._connect() as conn, conn:
            deleted = conn.execute("DELETE FROM reference WHERE name = ?", (name,)).rowcount
        if not deleted:
            raise UnknownReference(f"no reference named '{name}'")

    def set_meta(self, key: str, value: str) -> None:
        with self._connect() as conn, conn:
            conn.execute("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", (key, value))

    @contextmanager
    def _connect(self) -> Iterator[sqlite3.Connection]:
        conn = sqlite3.connect(self.path, timeout=30.0)
        try:
            conn.execute("PRAGMA synchronous=FULL")
            yield conn
        finally:
            conn.close()

    @staticmethod
    def _meta(conn: sqlite3.Connection, key: str) -> str | None:
        row = conn.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else row[0]


def checksum(arrays: dict[str, np.ndarray], scale: float) -> str:
    """sha256 of each array's name, dtype, shape and bytes, in ``ARRAYS`` order, and the scale."""
    digest = hashlib.sha256()
    for name in ARRAYS:
        array = np.ascontiguousarray(arrays[name])
        digest.update(f"{name}|{array.dtype.str}|{array.shape}|".encode())
        digest.update(array.tobytes())
    digest.update(f"scale|{float(scale)!r}".encode())
    return digest.hexdigest()


def _row(reference: Reference, model_hash: str, created_at: str) -> tuple:
    arrays = {name: _little_endian(getattr(reference, name)) for name in ARRAYS}
    layout = {name: {"dtype": a.dtype.str, "shape": list(a.shape)} for name, a in arrays.items()}
    return (
        reference.name,
        len(reference.points),
        float(reference.scale),
        *(arrays[name].tobytes() for name in ARRAYS),
        json.dumps(layout),
        checksum(arrays, reference.scale),
        model_hash,
        created_at,
    )


def _record(row: tuple) -> StoredReference:
    name, scale, *blobs, layout_json, stored_sum, model_hash, created_at = row
    layout = json.loads(layout_json)
    try:
        arrays = {
            key: np.frombuffer(blob, layout[key]["dtype"]).reshape(layout[key]["shape"]).copy()
            for key, blob in zip(ARRAYS, blobs, strict=True)
        }
    except (KeyError, TypeError, ValueError) as error:
        raise StoreCorrupted(f"reference '{name}': its arrays do not match their layout") from error
    if checksum(arrays, scale) != stored_sum:
        raise StoreCorrupted(f"reference '{name}': checksum mismatch, the stored data is damaged")
    return StoredReference(Reference(name=name, scale=scale, **arrays), model_hash, created_at)


def _little_endian(array: np.ndarray) -> np.ndarray:
    array = np.ascontiguousarray(array)
    return array.astype(array.dtype.newbyteorder("<")) if array.dtype.byteorder == ">" else array
