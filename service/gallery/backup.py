"""A copy of the gallery, or of chosen references, as one SQLite file: backup, restore, export
and import (``GET /gallery/backup``, ``POST /gallery/restore``, ``GET /gallery/export``,
``POST /gallery/import``; ``dpc-mn backup FILE`` and the others).

The file is a gallery database of this schema version (``store.SCHEMA_VERSION``: the tables
``reference``, ``meta``, ``gallery_version``) in one file (no WAL beside it), plus a table
``backup`` that lists each reference's name, ``points_sha256`` and row checksum as the copy
was taken. From SQLite, a whole gallery is copied with SQLite's online backup API (one
consistent snapshot while the service goes on writing); from PostgreSQL, and for chosen
references, the rows are read in one snapshot transaction and written into a new file, so
both stores give the same file and a copy of one may be restored into the other.

Reading a copy checks it all before anything is stored: the schema version, every row against
its checksum (which covers the points), every row's ``points_sha256`` against the list, and
that the list and the rows name the same references.
"""

from __future__ import annotations

import os
import sqlite3
from contextlib import closing
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from service.engine.reference import points_sha256
from service.gallery import encoding
from service.gallery.encoding import Row, StoreCorrupted
from service.gallery.store import (
    COLUMNS,
    INSERT,
    META_TABLE,
    REFERENCE_TABLE,
    SCHEMA_VERSION,
    SET_META,
    VERSION_TABLE,
    GalleryStore,
    StoredReference,
)

MANIFEST_TABLE = """
CREATE TABLE backup (
    name           TEXT PRIMARY KEY,
    points_sha256  TEXT NOT NULL,  -- of the points as little-endian float32 x y z triples
    sha256         TEXT NOT NULL   -- the row's checksum, as stored
)"""
KIND_KEY, SOURCE_KEY, TAKEN_KEY = "backup_kind", "backup_of", "backup_taken_at"
MEDIA_TYPE = "application/vnd.sqlite3"


class BackupInvalid(ValueError):
    """A file that is not a usable copy of a gallery (422); the message names the problem."""


@dataclass(frozen=True)
class Entry:
    """One reference as a copy lists it."""

    name: str
    points_sha256: str
    sha256: str


@dataclass(frozen=True)
class Copy:
    """A copy read back and checked: its rows (the store's columns), its list, its meta."""

    rows: list[tuple]  # (name, arrays, layout, extras, sha256, model_hash, created_at)
    entries: list[Entry]
    meta: dict[str, str]

    @property
    def checksums(self) -> dict[str, str]:
        return {entry.name: entry.sha256 for entry in self.entries}

    def records(self) -> list[StoredReference]:
        """The rows as the store would load them (decoded; checked when read)."""
        return [_record(row) for row in self.rows]


def write(store: GalleryStore, path: Path, names: list[str] | None = None) -> list[Entry]:
    """A copy of the whole gallery (``names`` None) or of those references into ``path`` (a
    new file; written beside it first, then renamed); what it lists."""
    path = Path(path)
    partial = path.with_name(path.name + ".partial")
    partial.unlink(missing_ok=True)
    try:
        copy_to = getattr(store, "copy_to", None)
        if names is None and copy_to is not None:  # SQLite: its online backup API
            copy_to(partial)
            kind = "backup"
        else:
            _write_rows(partial, *store.snapshot(names))
            kind = "backup" if names is None else "export"
        entries = _finish(partial, kind, store.where)
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    return entries


def read(path: Path) -> Copy:
    """The copy in ``path``, checked (``BackupInvalid`` naming the first problem)."""
    try:
        with closing(sqlite3.connect(f"file:{path}?mode=ro&immutable=1", uri=True)) as conn:
            tables = {row[0] for row in conn.execute("SELECT name FROM sqlite_master")}
            missing = {"reference", "meta", "backup"} - tables
            if missing:
                raise BackupInvalid(
                    f"the file is not a gallery copy made by dpc-mn backup or export (it has no "
                    f"{', '.join(sorted(missing))} table)"
                )
            meta = dict(conn.execute("SELECT key, value FROM meta").fetchall())
            rows = conn.execute(f"SELECT {COLUMNS} FROM reference ORDER BY name").fetchall()
            listed = conn.execute("SELECT name, points_sha256, sha256 FROM backup ORDER BY name")
            entries = [Entry(*row) for row in listed.fetchall()]
    except sqlite3.DatabaseError as error:
        raise BackupInvalid(f"the file is not a readable SQLite gallery copy: {error}") from None
    version = meta.get("schema_version")
    if version != SCHEMA_VERSION:
        raise BackupInvalid(
            f"the copy has gallery schema version {version}; this service reads version "
            f"{SCHEMA_VERSION}: restore it with the service version that made it"
        )
    check(rows, entries)
    return Copy([tuple(row) for row in rows], entries, meta)


def check(rows: list[tuple], entries: list[Entry]) -> None:
    """Every row decodes against its checksum and has the ``points_sha256`` and checksum its
    entry lists; the rows and the entries name the same references."""
    listed = {entry.name: entry for entry in entries}
    names = [row[0] for row in rows]
    if set(names) != set(listed):
        extra, lacking = set(names) - set(listed), set(listed) - set(names)
        said = [f"rows not listed: {', '.join(sorted(extra))}"] if extra else []
        said += [f"listed but absent: {', '.join(sorted(lacking))}"] if lacking else []
        raise BackupInvalid(f"the copy's list and its rows differ ({'; '.join(said)})")
    for row in rows:
        entry = listed[row[0]]
        try:
            record = _record(row)
        except StoreCorrupted as error:
            raise BackupInvalid(f"the copy is damaged: {error}") from None
        if record.sha256 != entry.sha256:
            raise BackupInvalid(f"reference '{entry.name}': its row is not the one listed")
        found = points_sha256(record.points)
        if found != entry.points_sha256:
            raise BackupInvalid(
                f"reference '{entry.name}': its points' sha256 is {found[:12]}..., the copy "
                f"lists {entry.points_sha256[:12]}...: the copy is damaged"
            )


def _record(row: tuple) -> StoredReference:
    name, arrays, layout, extras, sha256, model_hash, created_at = row
    values = encoding.decode(Row(name, bytes(arrays), layout, extras, sha256))
    return StoredReference(values, sha256, model_hash, created_at)


def _write_rows(path: Path, rows: list[tuple], meta: dict[str, str]) -> None:
    """A new gallery file holding ``rows`` (the store's columns) and ``meta``."""
    with closing(sqlite3.connect(path, isolation_level=None)) as conn:
        conn.execute("BEGIN")
        for table in (META_TABLE, REFERENCE_TABLE, VERSION_TABLE):
            conn.execute(table.format(blob="BLOB"))
        conn.execute("INSERT INTO gallery_version (id, version) VALUES (1, 0)")
        for key, value in {**meta, "schema_version": SCHEMA_VERSION}.items():
            conn.execute(SET_META, (key, value))
        conn.executemany(INSERT, rows)
        conn.execute("COMMIT")


def _finish(path: Path, kind: str, source: str) -> list[Entry]:
    """Add the list of what the copy holds (each row checked on the way) and say what it is;
    the file ends as one self-contained file, synced to disk."""
    with closing(sqlite3.connect(path, isolation_level=None)) as conn:
        conn.execute("PRAGMA journal_mode=DELETE")  # no -wal file beside a copy
        entries = []
        for row in conn.execute(f"SELECT {COLUMNS} FROM reference ORDER BY name"):  # one a time
            try:
                record = _record(row)
            except StoreCorrupted as error:  # a damaged row is not copied as if it were sound
                raise StoreCorrupted(f"cannot copy the gallery: {error}") from None
            entries.append(Entry(record.name, points_sha256(record.points), record.sha256))
        conn.execute("BEGIN")
        conn.execute(MANIFEST_TABLE)
        conn.executemany(
            "INSERT INTO backup (name, points_sha256, sha256) VALUES (?, ?, ?)",
            [(e.name, e.points_sha256, e.sha256) for e in entries],
        )
        taken = datetime.now(UTC).isoformat(timespec="milliseconds")
        for key, value in {KIND_KEY: kind, SOURCE_KEY: source, TAKEN_KEY: taken}.items():
            conn.execute(SET_META, (key, value))
        conn.execute("COMMIT")
    with open(path, "rb+") as handle:
        os.fsync(handle.fileno())
    return entries
