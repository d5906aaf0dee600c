"""The shared gallery store: a PostgreSQL database (``DPC_GALLERY__URL=postgresql://...``) that
every replica reads and writes, through psycopg 3 and its connection pool.

A write commits with a ``NOTIFY`` on ``CHANNEL``; each replica ``LISTEN``s on a connection of
its own (``wait_for_change``) and, as the fallback when a notification is missed (a dropped
connection, a pooler in transaction mode: ``listen=False``), checks the version every
``poll_s``. Replicas that start together set up or migrate the schema one at a time (an
advisory lock). A database that cannot be reached is ``StoreUnavailable``: the pool checks
each connection before lending it and reconnects once the server is back.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from urllib.parse import urlsplit

import psycopg
from psycopg_pool import ConnectionPool, PoolTimeout

from service.errors import StoreFull, StoreUnavailable
from service.gallery.store import GalleryStore

log = logging.getLogger(__name__)

CHANNEL = "dpc_gallery"
SCHEMA_LOCK = 0x6470635F6D6E  # pg_advisory_xact_lock key for setting up the schema ("dpc_mn")


class PostgresStore(GalleryStore):
    blob_type = "BYTEA"
    duplicate_errors = (psycopg.errors.UniqueViolation,)

    def __init__(self, url: str, pool_size: int = 4, listen: bool = True, timeout_s: float = 5.0):
        super().__init__(where=redacted(url))
        self.url = url
        self.listen = listen
        self.timeout_s = timeout_s
        self._pool = ConnectionPool(
            url,
            min_size=1,
            max_size=pool_size,
            open=False,
            timeout=timeout_s,  # to lend a connection; then StoreUnavailable
            check=ConnectionPool.check_connection,  # a server restart leaves dead ones
            kwargs={"connect_timeout": max(1, round(timeout_s))},
            name="gallery",
        )
        self._pool.open(wait=False)  # connects in the background: the server may come later
        self._listener: psycopg.Connection | None = None

    @contextmanager
    def _transaction(self, write: bool) -> Iterator[psycopg.Connection]:
        try:
            with self._pool.connection() as conn:
                yield conn
        except psycopg.errors.DiskFull as error:  # SQLSTATE 53100: the transaction rolled back
            raise StoreFull(
                f"the database {self.where} has no room left ({_first_line(error)}): nothing was "
                "stored; free space on the database server, then send it again"
            ) from error
        except (psycopg.OperationalError, PoolTimeout) as error:
            raise StoreUnavailable(f"cannot reach {self.where}: {_first_line(error)}") from error

    def _execute(self, conn: psycopg.Connection, sql: str, params: tuple = ()) -> psycopg.Cursor:
        return conn.execute(sql.replace("?", "%s"), params)  # type: ignore[arg-type]

    def _begin_snapshot(self, conn: psycopg.Connection) -> None:
        conn.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ, READ ONLY")

    def _has_table(self, conn: psycopg.Connection, table: str) -> bool:
        return self._execute(conn, "SELECT to_regclass(?) IS NOT NULL", (table,)).fetchone()[0]

    def _lock_schema(self, conn: psycopg.Connection) -> None:
        self._execute(conn, "SELECT pg_advisory_xact_lock(?)", (SCHEMA_LOCK,))

    def _announce(self, conn: psycopg.Connection, version: int) -> None:
        self._execute(conn, "SELECT pg_notify(?, ?)", (CHANNEL, str(version)))

    def wait_for_change(self, timeout: float) -> None:
        """Until a notification comes or ``timeout`` s pass. A listener (re)connected here
        returns at once, so that the caller checks the version it may have missed."""
        if not self.listen:
            super().wait_for_change(timeout)
            return
        try:
            if self._listener is None or self._listener.closed:
                self._listener = psycopg.connect(
                    self.url, autocommit=True, connect_timeout=max(1, round(self.timeout_s))
                )
                self._listener.execute(f"LISTEN {CHANNEL}")
                return
            for _ in self._listener.notifies(timeout=timeout, stop_after=1):
                pass
        except psycopg.OperationalError as error:
            self._close_listener()
            raise StoreUnavailable(f"cannot reach {self.where}: {_first_line(error)}") from error

    def close(self) -> None:
        self._close_listener()
        self._pool.close()

    def _close_listener(self) -> None:
        if self._listener is not None:
            self._listener.close()
            self._listener = None


def redacted(url: str) -> str:
    """The URL without its password or query (which may hold one too), for logs and messages."""
    parts = urlsplit(url)
    user = f"{parts.username}@" if parts.username else ""
    port = f":{parts.port}" if parts.port else ""
    return f"{parts.scheme}://{user}{parts.hostname or ''}{port}{parts.path}"


def _first_line(error: Exception) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__
