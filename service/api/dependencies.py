"""What routes get injected with ``Depends``: read from ``app.state``, set up by the app's lifespan.

Routes that need the gallery answer 503 until it has loaded. Each is ``async`` (and so is
``auth.authorize``): FastAPI runs a plain function dependency in a worker thread, a hop each
(docs/decisions.md#speed).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request

from service.api.engine_processes import EngineProcesses
from service.api.limiter import Limiter
from service.api.recent import RecentAlignments
from service.engine.engine import Engine
from service.gallery.catalog import Catalog
from service.settings import Settings


class NotReady(RuntimeError):
    """The model or the gallery is not loaded (yet), 503."""


@dataclass
class Loading:
    """Whether the gallery has loaded; written by the loading thread, read by the routes."""

    status: str = "loading"  # -> "ok" | "failed"
    detail: str | None = "loading the gallery"
    unreachable: str | None = None  # why the gallery store cannot be used now, while it cannot

    @property
    def ready(self) -> bool:
        """The gallery is in memory: alignments are served (from it, even while the store is
        out of reach)."""
        return self.status == "ok"

    def report_store(self, problem: str | None) -> None:
        self.unreachable = problem


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_loading(request: Request) -> Loading:
    return request.app.state.loading


async def get_loading_catalog(request: Request) -> Catalog:
    """The catalog, loaded or not (for health)."""
    return request.app.state.catalog


async def get_catalog(request: Request) -> Catalog:
    """The catalog, once the gallery has loaded."""
    loading: Loading = request.app.state.loading
    if not loading.ready:
        raise NotReady(f"the service is not ready: {loading.detail}")
    return request.app.state.catalog


async def get_engine(catalog: Annotated[Catalog, Depends(get_catalog)]) -> Engine:
    return catalog.engine


async def get_processes(
    request: Request, catalog: Annotated[Catalog, Depends(get_catalog)]
) -> EngineProcesses:
    """The engine's ``align`` and ``detect``, in its worker processes once they are up
    (``service.api.engine_processes``); through ``catalog``, 503 while the gallery loads, as
    ``get_engine``."""
    return request.app.state.processes


async def get_limiter(request: Request) -> Limiter:
    """The slots, threads and time budget of the engine's work (``service.api.limiter``)."""
    return request.app.state.limiter


async def get_recent(request: Request) -> RecentAlignments:
    """The last alignments, kept for the console (``service.api.recent``)."""
    return request.app.state.recent


SettingsDep = Annotated[Settings, Depends(get_settings)]
LoadingDep = Annotated[Loading, Depends(get_loading)]
LoadingCatalogDep = Annotated[Catalog, Depends(get_loading_catalog)]
CatalogDep = Annotated[Catalog, Depends(get_catalog)]
EngineDep = Annotated[Engine, Depends(get_engine)]
ProcessesDep = Annotated[EngineProcesses, Depends(get_processes)]
LimiterDep = Annotated[Limiter, Depends(get_limiter)]
RecentDep = Annotated[RecentAlignments, Depends(get_recent)]
