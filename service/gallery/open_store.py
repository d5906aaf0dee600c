"""Which gallery store the settings name, opened: the one module that knows both backends, so
the interface (``service.gallery.store``) never imports the backends that import it."""

from __future__ import annotations

from service.gallery.sqlite_store import SQLiteStore
from service.gallery.store import GalleryStore
from service.settings import GallerySettings


def open_store(settings: GallerySettings) -> GalleryStore:
    """The store the settings name: PostgreSQL at ``url``, else SQLite in ``data_dir``."""
    if settings.url:
        from service.gallery.postgres_store import PostgresStore  # psycopg only where it is used

        return PostgresStore(
            settings.url,
            pool_size=settings.pool_size,
            listen=settings.listen,
            timeout_s=settings.connect_timeout_s,
        )
    return SQLiteStore.in_dir(settings.data_dir)
