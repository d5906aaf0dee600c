"""The embedded gallery store: one SQLite file, ``gallery.sqlite3`` in ``gallery.data_dir``.

The journal is WAL with ``synchronous=FULL``, so an acknowledged write survives a power cut.
A connection is opened per operation, so the store is safe to use from any thread, and from
several processes on one machine: each follows the others' changes through the version check.
Schema version 1 (one column per array: ``points``, ``mapped``, ``view_grids``) is migrated
to version 2 on the first start, every row checked against its old checksum on the way.
"""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
from collections.abc import Callable, Iterator
from contextlib import closing, contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from service.errors import StoreFull, StoreUnavailable
from service.gallery import encoding
from service.gallery.encoding import StoreCorrupted
from service.gallery.store import (
    INSERT,
    REFERENCE_TABLE,
    VERSION_TABLE,
    GalleryStore,
    StoreIncompatible,
)

FILENAME = "gallery.sqlite3"
V1_ARRAYS = ("points", "mapped", "view_grids")  # schema version 1: a column each


class SQLiteStore(GalleryStore):
    duplicate_errors = (sqlite3.IntegrityError,)

    def __init__(self, path: str | Path):
        self.path = Path(path)
        super().__init__(where=str(self.path))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self.check()  # before writing anything else to it
            with self._connect() as conn:
                conn.execute("PRAGMA journal_mode=WAL")
            # Held open while the store is: the last connection to close removes the WAL and
            # its index (-shm), and the next must make them again, which a full disk refuses
            # (even to a read: "disk I/O error", so the replica turned not ready).
            self._keeper = sqlite3.connect(self.path, check_same_thread=False)
            self._keeper.execute("SELECT COUNT(*) FROM meta").fetchone()
        except sqlite3.DatabaseError as error:  # not a database, or a damaged one
            if self._disk_full():
                raise StoreFull(self._full_message(error)) from error
            raise StoreIncompatible(f"{self.path} is not a usable SQLite file: {error}") from error

    def close(self) -> None:
        self._keeper.close()

    def _disk_full(self) -> bool:
        """Whether the data directory's filesystem has no block left (root's reserve counts:
        root may write into it)."""
        try:
            space = os.statvfs(self.path.parent)
        except OSError:
            return False
        return (space.f_bfree if os.geteuid() == 0 else space.f_bavail) == 0

    def _full_message(self, error: Exception) -> str:
        return (
            f"the disk of the gallery file {self.path} is full ({error}): nothing was stored; "
            "free space there (or move DPC_GALLERY__DATA_DIR), then send it again"
        )

    @classmethod
    def in_dir(cls, data_dir: str | Path) -> SQLiteStore:
        return cls(Path(data_dir) / FILENAME)

    @contextmanager
    def _connect(self) -> Iterator[sqlite3.Connection]:
        conn = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)  # we BEGIN
        try:
            conn.execute("PRAGMA synchronous=FULL")
            yield conn
        finally:
            conn.close()

    @contextmanager
    def _transaction(self, write: bool) -> Iterator[sqlite3.Connection]:
        """A write takes the file's write lock at once (``BEGIN IMMEDIATE``); a read needs no
        transaction. A full disk is ``StoreFull`` (SQLite has rolled the write back itself); a
        locked or unreadable file is ``StoreUnavailable``."""
        try:
            with self._connect() as conn:
                if not write:
                    yield conn
                    return
                conn.execute("BEGIN IMMEDIATE")
                try:
                    yield conn
                    conn.execute("COMMIT")
                except BaseException:
                    if conn.in_transaction:  # SQLITE_FULL ends the transaction itself
                        conn.execute("ROLLBACK")
                    raise
        except sqlite3.OperationalError as error:
            # SQLITE_FULL, or an I/O error where the disk has no block left (the WAL's index
            # could not grow)
            if error.sqlite_errorcode == sqlite3.SQLITE_FULL or self._disk_full():
                raise StoreFull(self._full_message(error)) from error
            raise StoreUnavailable(
                f"the gallery file {self.path} cannot be used: {error}"
            ) from error

    def _begin_snapshot(self, conn: sqlite3.Connection) -> None:
        conn.execute("BEGIN")  # WAL: the first read fixes what every later one sees

    def copy_to(self, path: Path) -> None:
        """The whole database into the new file ``path`` with SQLite's online backup API: one
        consistent snapshot, taken while other connections go on writing."""
        try:
            with closing(sqlite3.connect(self.path)) as source:
                with closing(sqlite3.connect(path)) as target:
                    source.backup(target)
        except sqlite3.OperationalError as error:
            raise StoreUnavailable(f"cannot copy the gallery file {self.path}: {error}") from error

    def _has_table(self, conn: sqlite3.Connection, table: str) -> bool:
        query = "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = ?"
        return conn.execute(query, (table,)).fetchone() is not None

    def _migrations(self) -> dict[int, Callable[[Any], None]]:
        return {1: self._migrate_from_1}

    def _migrate_from_1(self, conn: sqlite3.Connection) -> None:
        """Version 1 -> 2: each row's arrays into one blob with their layout, the scale into
        the extras; model hash and registration time kept. A row whose old checksum fails stops
        the migration (``StoreCorrupted``) and the transaction leaves the file as it was."""
        conn.execute("ALTER TABLE reference RENAME TO reference_v1")
        self._create_tables(conn, (REFERENCE_TABLE, VERSION_TABLE))
        rows = conn.execute(
            "SELECT name, scale, points, mapped, view_grids, layout, sha256, model_hash,"
            " created_at FROM reference_v1"
        )
        for name, scale, *blobs, layout, stored_sum, model_hash, created_at in rows.fetchall():
            arrays = _v1_arrays(name, blobs, json.loads(layout))
            if _v1_checksum(arrays, scale) != stored_sum:
                raise StoreCorrupted(
                    f"reference '{name}': checksum mismatch, the stored data is damaged "
                    "(found while migrating the gallery from schema version 1)"
                )
            row = encoding.encode_values(name, {**arrays, "scale": scale})
            values = (row.name, row.arrays, row.layout, row.extras, row.sha256)
            conn.execute(INSERT, (*values, model_hash, created_at))
        conn.execute("DROP TABLE reference_v1")


def _v1_arrays(name: str, blobs: list[bytes], layout: dict) -> dict[str, np.ndarray]:
    try:
        return {
            key: np.frombuffer(blob, layout[key]["dtype"]).reshape(layout[key]["shape"])
            for key, blob in zip(V1_ARRAYS, blobs, strict=True)
        }
    except (KeyError, TypeError, ValueError) as error:
        raise StoreCorrupted(f"reference '{name}': its arrays do not match their layout") from error


def _v1_checksum(arrays: dict[str, np.ndarray], scale: float) -> str:
    """Schema version 1's sha256: each array's name, dtype, shape and bytes, then the scale."""
    digest = hashlib.sha256()
    for name in V1_ARRAYS:
        array = np.ascontiguousarray(arrays[name])
        digest.update(f"{name}|{array.dtype.str}|{array.shape}|".encode())
        digest.update(array.tobytes())
    digest.update(f"scale|{float(scale)!r}".encode())
    return digest.hexdigest()
