"""The registered references, durable: one interface, two backends.

``open_store(settings.gallery)`` (``service.gallery.open_store``) gives the embedded default,
one SQLite file in ``data_dir`` (``service.gallery.sqlite_store``), or, when ``url`` is a
``postgresql://`` URL, a PostgreSQL database that several replicas share
(``service.gallery.postgres_store``). Both hold the same tables, at schema version
``SCHEMA_VERSION``; an older database is migrated on start-up, in one transaction, and a newer
one is refused:

- ``reference``: one row a reference (``service.gallery.encoding``: its arrays, its other
  fields as JSON and a sha256 of all of it, checked on every load), the hash of the ONNX model
  that computed it, and when it was registered;
- ``meta``: the schema version, what the store was seeded from;
- ``gallery_version``: one number that every write raises. A replica that sees it move reads
  the stored checksums and loads what differs from what it holds (``catalog.Catalog.sync``).

Every write is one transaction that raises the version first, which makes writers take turns
(in PostgreSQL across replicas too), so the seed and the checks in a write see every write
committed before it.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np

from service.engine.reference import Reference
from service.errors import ReferenceExists, UnknownReference
from service.gallery import encoding
from service.gallery.encoding import Row, StoreCorrupted

if TYPE_CHECKING:
    from collections.abc import Callable

__all__ = [
    "GalleryStore",
    "StoreCorrupted",
    "StoreIncompatible",
    "StoreNotEmpty",
    "StoredReference",
]

SCHEMA_VERSION = "2"
SEEDED_KEY = "seeded_from"  # meta: the gallery file the store was seeded from, once

META_TABLE = """
CREATE TABLE meta (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL
)"""
REFERENCE_TABLE = """
CREATE TABLE reference (
    name        TEXT PRIMARY KEY,
    arrays      {blob} NOT NULL,  -- the array fields' little-endian bytes, one after another
    layout      TEXT NOT NULL,  -- JSON: [{{"field": "points", "dtype": "<f4", "shape": [N, 3]}}]
    extras      TEXT NOT NULL,  -- JSON: the other fields, e.g. {{"scale": 0.12}}
    sha256      TEXT NOT NULL,  -- of the name, layout, extras and arrays
    model_hash  TEXT NOT NULL,  -- sha256 of the ONNX file that computed the mapped fields
    created_at  TEXT NOT NULL   -- ISO 8601, UTC
)"""
VERSION_TABLE = """
CREATE TABLE gallery_version (
    id      INTEGER PRIMARY KEY CHECK (id = 1),
    version BIGINT NOT NULL  -- raised by every write
)"""
COLUMNS = "name, arrays, layout, extras, sha256, model_hash, created_at"
INSERT = f"INSERT INTO reference ({COLUMNS}) VALUES (?, ?, ?, ?, ?, ?, ?)"
UPSERT = (
    f"{INSERT} ON CONFLICT (name) DO UPDATE SET arrays = excluded.arrays,"
    " layout = excluded.layout, extras = excluded.extras, sha256 = excluded.sha256,"
    " model_hash = excluded.model_hash, created_at = excluded.created_at"
)
SET_META = (
    "INSERT INTO meta (key, value) VALUES (?, ?)"
    " ON CONFLICT (key) DO UPDATE SET value = excluded.value"
)


class StoreIncompatible(RuntimeError):
    """A database this code cannot use: written by a newer version, or not a gallery at all."""


class StoreNotEmpty(RuntimeError):
    """A restore into a store that holds references (409)."""


@dataclass(frozen=True)
class StoredReference:
    values: dict[str, Any]  # every stored field, the name included
    sha256: str  # of the stored row: what a replica compares to know it holds the same
    model_hash: str
    created_at: str

    @property
    def name(self) -> str:
        return self.values["name"]

    @property
    def points(self) -> np.ndarray:
        return self.values["points"]

    @property
    def missing(self) -> tuple[str, ...]:
        """Fields the current ``Reference`` has and this row lacks (an older version wrote it)."""
        return encoding.missing(self.values)

    @cached_property
    def reference(self) -> Reference:
        """The stored reference; a derived field it lacks is None (the catalog recomputes it)."""
        required = [name for name in self.missing if name in encoding.REQUIRED]
        if required:
            raise ValueError(
                f"reference '{self.name}' was stored without {', '.join(required)}: "
                "recompute it from its points"
            )
        return encoding.to_reference(self.values)


class GalleryStore(ABC):
    """Reads and writes in SQL both backends speak (``?`` placeholders); the backends add the
    connection, the transaction, and how a replica hears of another's change."""

    blob_type = "BLOB"  # the column type of raw bytes
    duplicate_errors: tuple[type[Exception], ...] = ()  # what the driver raises for a taken name

    def __init__(self, where: str):
        self.where = where  # for messages; never a password
        self._schema_ready = False
        self._schema_lock = threading.Lock()

    # --- what a backend provides ---------------------------------------------------------

    @abstractmethod
    def _transaction(self, write: bool) -> AbstractContextManager[Any]:
        """A connection in one transaction, committed on exit and rolled back on an error;
        ``StoreUnavailable`` when the database cannot be reached."""

    @abstractmethod
    def _has_table(self, conn: Any, table: str) -> bool: ...

    def _execute(self, conn: Any, sql: str, params: tuple = ()) -> Any:
        return conn.execute(sql, params)

    def _begin_snapshot(self, conn: Any) -> None:  # noqa: B027 - a hook
        """Make the statements that follow on ``conn`` read one consistent state."""

    def _lock_schema(self, conn: Any) -> None:  # noqa: B027 - a hook, empty by default
        """Make replicas that start together set the schema up one after the other."""

    def _announce(self, conn: Any, version: int) -> None:  # noqa: B027 - a hook
        """Tell other replicas, on commit, that the store changed."""

    def _migrations(self) -> dict[int, Callable[[Any], None]]:
        """Schema version -> the function that takes a database from it to the next one."""
        return {}

    def wait_for_change(self, timeout: float) -> None:
        """Return when another replica may have changed the store, or after ``timeout`` s."""
        threading.Event().wait(timeout)

    def close(self) -> None:  # noqa: B027 - a hook
        """Let go of connections (a no-op where there are none to keep)."""

    # --- the schema ----------------------------------------------------------------------

    def check(self) -> None:
        """Reach the database and bring its schema to this version (once): ``StoreIncompatible``
        for one this code cannot use, ``StoreUnavailable`` while it cannot be reached."""
        if self._schema_ready:
            return
        with self._schema_lock:
            if self._schema_ready:
                return
            with self._transaction(write=True) as conn:
                self._lock_schema(conn)
                self._set_up_schema(conn)
            self._schema_ready = True

    def _set_up_schema(self, conn: Any) -> None:
        version = self._schema_version(conn)
        if version is None:
            self._create_tables(conn, (META_TABLE, REFERENCE_TABLE, VERSION_TABLE))
            self._execute(conn, SET_META, ("schema_version", SCHEMA_VERSION))
            return
        if version == SCHEMA_VERSION:
            return
        if not version.isdigit() or int(version) > int(SCHEMA_VERSION):
            raise StoreIncompatible(
                f"{self.where} has gallery schema version {version}, newer than this service's "
                f"{SCHEMA_VERSION}: run the service version that wrote it, or start on a new "
                "gallery (docs/operations.md)"
            )
        migrations = self._migrations()
        for step in range(int(version), int(SCHEMA_VERSION)):
            if step not in migrations:
                raise StoreIncompatible(
                    f"{self.where} has gallery schema version {version}, and no migration "
                    f"exists from version {step}: rebuild it (docs/operations.md)"
                )
            migrations[step](conn)
        self._execute(conn, SET_META, ("schema_version", SCHEMA_VERSION))

    def _schema_version(self, conn: Any) -> str | None:
        if not self._has_table(conn, "meta"):
            return None
        return self._meta(conn, "schema_version")

    def _create_tables(self, conn: Any, tables: Iterable[str]) -> None:
        for table in tables:
            self._execute(conn, table.format(blob=self.blob_type))
        if VERSION_TABLE in tables:
            self._execute(conn, "INSERT INTO gallery_version (id, version) VALUES (1, 0)")

    # --- reads ---------------------------------------------------------------------------

    @contextmanager
    def _reading(self) -> Iterator[Any]:
        self.check()
        with self._transaction(write=False) as conn:
            yield conn

    def version(self) -> int:
        """The number every write raises."""
        with self._reading() as conn:
            return self._execute(conn, "SELECT version FROM gallery_version").fetchone()[0]

    def checksums(self) -> dict[str, str]:
        """Each stored reference's row checksum, by name: what differs from a snapshot."""
        with self._reading() as conn:
            return dict(self._execute(conn, "SELECT name, sha256 FROM reference").fetchall())

    def load_records(self, names: Iterable[str] | None = None) -> list[StoredReference]:
        """Every reference (or those of ``names`` that exist), by name, each checked against
        its checksum, with the model hash it was computed with and when it was registered."""
        select = f"SELECT {COLUMNS} FROM reference"
        with self._reading() as conn:
            if names is None:
                rows = self._execute(conn, select).fetchall()
            else:
                rows = [
                    row
                    for name in names
                    for row in self._execute(conn, f"{select} WHERE name = ?", (name,)).fetchall()
                ]
        return sorted((_record(row) for row in rows), key=lambda record: record.name)

    def snapshot(self, names: Iterable[str] | None = None) -> tuple[list[tuple], dict[str, str]]:
        """Every row (or those of ``names``, ``UnknownReference`` for one not stored) with its
        columns as stored, and the meta entries, as one consistent state: what a copy holds."""
        select = f"SELECT {COLUMNS} FROM reference"
        self.check()
        with self._transaction(write=False) as conn:
            self._begin_snapshot(conn)
            if names is None:
                rows = self._execute(conn, f"{select} ORDER BY name").fetchall()
            else:
                rows = []
                for name in names:
                    found = self._execute(conn, f"{select} WHERE name = ?", (name,)).fetchall()
                    if not found:
                        raise UnknownReference(f"no reference named '{name}'")
                    rows += found
            meta = dict(self._execute(conn, "SELECT key, value FROM meta").fetchall())
        return [(*row[:1], bytes(row[1]), *row[2:]) for row in rows], meta

    def restore(
        self,
        rows: list[tuple],
        source: str,
        replace_all: bool,
        check: Callable[[list[tuple]], None],
    ) -> None:
        """Store a copy's ``rows`` as they are (checksum, model hash, registration time) in one
        transaction, into an empty store (``StoreNotEmpty`` otherwise) or, with
        ``replace_all``, in place of everything it holds; ``check`` is given the rows as read
        back inside the transaction, before it commits, and raises to undo it all. The store
        is marked seeded from the copy, so that no later start seeds over it."""
        with self._writing() as conn:
            held = self._execute(conn, "SELECT COUNT(*) FROM reference").fetchone()[0]
            if held and not replace_all:
                raise StoreNotEmpty(
                    f"the gallery holds {held} references: restore only into an empty one, or "
                    "pass replace=true to replace all of them with the copy"
                )
            self._execute(conn, "DELETE FROM reference")
            for row in rows:
                self._execute(conn, INSERT, row)
            check(
                [
                    (*row[:1], bytes(row[1]), *row[2:])
                    for row in self._execute(conn, f"SELECT {COLUMNS} FROM reference").fetchall()
                ]
            )
            self._execute(conn, SET_META, (SEEDED_KEY, f"restored from {source}"))

    def load_all(self) -> list[Reference]:
        """Every reference, by name, each checked against its checksum."""
        return [record.reference for record in self.load_records()]

    def count(self) -> int:
        with self._reading() as conn:
            return self._execute(conn, "SELECT COUNT(*) FROM reference").fetchone()[0]

    def is_empty(self) -> bool:
        return self.count() == 0

    def get_meta(self, key: str) -> str | None:
        with self._reading() as conn:
            return self._meta(conn, key)

    def _meta(self, conn: Any, key: str) -> str | None:
        row = self._execute(conn, "SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else row[0]

    # --- writes: each one transaction ----------------------------------------------------

    @contextmanager
    def _writing(self) -> Iterator[Any]:
        """One write transaction: the version raised first (writers take turns), then the
        caller's statements, then the announcement, all committed together."""
        self.check()
        with self._transaction(write=True) as conn:
            self._execute(conn, "UPDATE gallery_version SET version = version + 1")
            version = self._execute(conn, "SELECT version FROM gallery_version").fetchone()[0]
            yield conn
            self._announce(conn, version)

    def put(self, reference: Reference, model_hash: str, replace: bool = False) -> str:
        """Store one reference; returns its row's checksum. ``ReferenceExists`` if its name is
        taken and not ``replace``."""
        return self.put_many([reference], model_hash, replace=replace)[reference.name]

    def put_many(
        self,
        references: Iterable[Reference],
        model_hash: str,
        replace: bool = False,
        meta: dict[str, str] | None = None,
    ) -> dict[str, str]:
        """Store several references and meta entries, all or none; their checksums by name."""
        rows = [encoding.encode(reference) for reference in references]
        with self._writing() as conn:
            self._insert(conn, rows, model_hash, replace)
            for key, value in (meta or {}).items():
                self._execute(conn, SET_META, (key, value))
        return {row.name: row.sha256 for row in rows}

    def seed(self, references: list[Reference], model_hash: str, source: str) -> bool:
        """Store the first references of a new store, once: nothing (False) if it was seeded
        before or holds references already. Replicas that start together seed it once."""
        rows = [encoding.encode(reference) for reference in references]
        with self._writing() as conn:
            if self._meta(conn, SEEDED_KEY) is not None:
                return False
            empty = self._execute(conn, "SELECT COUNT(*) FROM reference").fetchone()[0] == 0
            if empty:  # registered before seeding existed: never seed over it
                self._insert(conn, rows, model_hash, replace=False)
            self._execute(conn, SET_META, (SEEDED_KEY, source if empty else ""))
        return empty

    def rewrite(self, reference: Reference, model_hash: str, was: str) -> str | None:
        """Replace a row recomputed from its points, only if it still has the checksum ``was``
        (no replica changed or deleted it meanwhile); the new checksum, or None."""
        row = encoding.encode(reference)
        with self._writing() as conn:
            changed = self._execute(
                conn,
                "UPDATE reference SET arrays = ?, layout = ?, extras = ?, sha256 = ?,"
                " model_hash = ? WHERE name = ? AND sha256 = ?",
                (row.arrays, row.layout, row.extras, row.sha256, model_hash, row.name, was),
            ).rowcount
        return row.sha256 if changed else None

    def delete(self, name: str) -> None:
        """Remove one reference; ``UnknownReference`` if there is none of that name."""
        with self._writing() as conn:
            deleted = self._execute(conn, "DELETE FROM reference WHERE name = ?", (name,)).rowcount
            if not deleted:
                raise UnknownReference(f"no reference named '{name}'")

    def set_meta(self, key: str, value: str) -> None:
        with self._writing() as conn:
            self._execute(conn, SET_META, (key, value))

    def _insert(self, conn: Any, rows: list[Row], model_hash: str, replace: bool) -> None:
        created_at = datetime.now(UTC).isoformat(timespec="milliseconds")
        for row in rows:
            values = (row.name, row.arrays, row.layout, row.extras, row.sha256)
            try:
                self._execute(
                    conn, UPSERT if replace else INSERT, (*values, model_hash, created_at)
                )
            except self.duplicate_errors as error:
                raise ReferenceExists(
                    f"a reference named '{row.name}' exists: pick another name or pass replace=true"
                    " (the same points again are answered 200, identical)"
                ) from error


def _record(row: tuple) -> StoredReference:
    name, arrays, layout, extras, sha256, model_hash, created_at = row
    values = encoding.decode(Row(name, bytes(arrays), layout, extras, sha256))
    return StoredReference(values, sha256, model_hash, created_at)
