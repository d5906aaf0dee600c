"""The gallery store's two backends, for tests that run against each: SQLite in a folder of its
own, or a database of its own on the session's throwaway PostgreSQL server
(``evaluation.postgres``; the ``backend`` fixture in conftest.py skips the PostgreSQL cases, saying
what to install, where no server can be started)."""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from pathlib import Path

import pytest

from evaluation.postgres import ThrowawayPostgres
from service.gallery.open_store import open_store
from service.gallery.sqlite_store import FILENAME
from service.gallery.store import GalleryStore
from service.settings import GallerySettings

BACKENDS = ("sqlite", "postgresql")


@dataclass(frozen=True)
class Location:
    """Where one gallery lives: a data directory, and for PostgreSQL a database URL."""

    data_dir: Path
    url: str | None = None

    def settings(self, **fields) -> GallerySettings:
        return GallerySettings(data_dir=self.data_dir, url=self.url, **fields)

    def env(self) -> dict[str, str]:
        """As ``python -m service`` settings (``ServiceProcess`` keyword arguments)."""
        return {"gallery__data_dir": str(self.data_dir)} | (
            {"gallery__url": self.url} if self.url else {}
        )

    def store(self) -> GalleryStore:
        """A store opened on it, as a (re)started service opens it."""
        store = open_store(self.settings())
        try:
            store.check()
        except BaseException:
            store.close()
            raise
        return store

    def execute(self, sql: str, params: tuple = ()) -> None:
        """Raw SQL on the database, around the store (``?`` placeholders): to damage it."""
        if self.url is None:
            with sqlite3.connect(self.data_dir / FILENAME) as conn:
                conn.execute(sql, params)
            conn.close()
            return
        import psycopg

        with psycopg.connect(self.url) as conn:
            conn.execute(sql.replace("?", "%s"), params)


class Backend:
    """Makes fresh locations of one kind."""

    def __init__(self, name: str, folders: pytest.TempPathFactory, server=None):
        self.name = name
        self.folders = folders
        self.server: ThrowawayPostgres | None = server

    def new(self) -> Location:
        data_dir = self.folders.mktemp(f"{self.name}-data")
        url = self.server.create_database() if self.server else None
        return Location(data_dir, url)
