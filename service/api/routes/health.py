"""Health: ``/health`` for people; ``/v2/health/live`` and ``/v2/health/ready`` for probes."""

from __future__ import annotations

from fastapi import APIRouter, Response, status
from pydantic import BaseModel

from service.api import auth
from service.api.dependencies import LoadingCatalogDep, LoadingDep, SettingsDep
from service.api.schemas import Health, ModelIdentity
from service.engine import kernels

router = APIRouter(tags=["health"])


class Live(BaseModel):
    live: bool


class Ready(BaseModel):
    ready: bool
    detail: str | None = None


@router.get(
    "/health",
    response_model=Health,
    summary="Model identity, execution providers, references; 503 until loaded",
    responses={503: {"model": Health, "description": "loading, or the gallery failed to load"}},
)
async def health(
    response: Response, catalog: LoadingCatalogDep, loading: LoadingDep, settings: SettingsDep
) -> Health:
    if not loading.ready:
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
    mapper = catalog.engine.mapper
    return Health(
        status=loading.status,
        auth=auth.mode(settings.auth),
        model=ModelIdentity(path=str(mapper.path), sha256=mapper.model_hash),
        providers=mapper.providers,
        loops="compiled" if kernels.switch.enabled else "numpy",
        references=len(catalog.engine),
        detail=loading.detail or loading.unreachable,
    )


@router.get("/v2/health/live", response_model=Live, summary="The process answers")
async def live() -> Live:
    return Live(live=True)


@router.get(
    "/v2/health/ready",
    response_model=Ready,
    summary="The model and the gallery are loaded and the gallery store is reachable (else 503)",
    responses={503: {"model": Ready, "description": "not ready, and why"}},
)
async def ready(response: Response, loading: LoadingDep) -> Ready:
    ready = loading.ready and loading.unreachable is None
    if not ready:
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
    return Ready(ready=ready, detail=loading.detail or loading.unreachable)
