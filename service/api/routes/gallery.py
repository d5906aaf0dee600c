"""``/gallery``: a consistent copy of the whole gallery while it serves, its restore, and the
export and import of chosen references between services (``service.gallery.backup``).

A copy is one SQLite file (``application/vnd.sqlite3``), the same from either store. Each
needs an admin key: a copy holds every reference's points.
"""

from __future__ import annotations

import asyncio
import tempfile
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Request, Response, status
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field
from starlette.background import BackgroundTask

from service.api.auth import AdminAccess
from service.api.dependencies import CatalogDep, LimiterDep, SettingsDep
from service.api.limiter import Job
from service.api.routes.common import RAW, errors, invalid
from service.api.routes.references import answer_of
from service.api.schemas import ReferenceResponse
from service.gallery import backup
from service.gallery.catalog import CREATED, IDENTICAL, Catalog

router = APIRouter(prefix="/gallery", tags=["gallery"])

COPY_ANSWER = {
    200: {
        "content": {backup.MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}},
        "description": "the copy: an SQLite gallery file; X-References says how many it holds",
    }
}
COPY_BODY = {  # the file's bytes as they are, whatever the Content-Type says
    "required": True,
    "content": {RAW: {"schema": {"type": "string", "format": "binary"}}},
}


class RestoreResponse(BaseModel):
    restored: int = Field(description="references the gallery now holds from the copy")
    checked: int = Field(description="rows checked against their checksum and points_sha256")
    outcome: str = Field(description="'restored', or 'identical' (it held the copy already)")


class ImportResponse(BaseModel):
    references: list[ReferenceResponse] = Field(description="each imported reference's outcome")


@router.get(
    "/backup",
    response_class=FileResponse,
    summary="A consistent copy of the whole gallery, taken while the service serves",
    responses=COPY_ANSWER | errors(401, 403, 503),
    dependencies=[AdminAccess],
)
async def take_backup(catalog: CatalogDep) -> FileResponse:
    return await _copy(catalog, None, "backup")


@router.get(
    "/export",
    response_class=FileResponse,
    summary="A copy of chosen references, for another service (POST /gallery/import there)",
    responses=COPY_ANSWER | errors(401, 403, 404, 422, 503),
    dependencies=[AdminAccess],
)
async def export(
    catalog: CatalogDep,
    name: Annotated[list[str] | None, Query(description="a reference to copy (repeat it)")] = None,
) -> FileResponse:
    if not name:
        raise invalid("name the references to export: ?name=a&name=b", "name")
    return await _copy(catalog, list(dict.fromkeys(name)), "export")


@router.post(
    "/restore",
    response_model=RestoreResponse,
    summary="Restore a backup into an empty gallery (or, with ?replace=true, in place of all)",
    responses=errors(401, 403, 409, 413, 422, 503, 504, 507),
    openapi_extra={"requestBody": COPY_BODY},
    dependencies=[AdminAccess],
)
async def restore(
    request: Request,
    catalog: CatalogDep,
    settings: SettingsDep,
    limiter: LimiterDep,
    replace: Annotated[bool, Query(description="replace every reference held now")] = False,
) -> RestoreResponse:
    with tempfile.TemporaryDirectory(prefix="dpc-restore-") as folder:
        copy = await _received(request, Path(folder) / "copy.sqlite3")
        source = copy.meta.get(backup.SOURCE_KEY, "an uploaded copy")
        outcome = await limiter.write(
            _restore,
            catalog,
            copy,
            f"a copy of {source} taken {copy.meta.get(backup.TAKEN_KEY, '?')}",
            replace,
            budget_s=settings.limits.request_timeout_s * max(1, len(copy.rows)),
        )
    count = len(copy.rows)
    return RestoreResponse(
        restored=count, checked=count, outcome="identical" if outcome == IDENTICAL else "restored"
    )


@router.post(
    "/import",
    response_model=ImportResponse,
    summary="Add the references of another service's export, all or none",
    responses={200: {"model": ImportResponse, "description": "every one already here, identical"}}
    | errors(401, 403, 409, 413, 422, 503, 504, 507),
    status_code=status.HTTP_201_CREATED,
    openapi_extra={"requestBody": COPY_BODY},
    dependencies=[AdminAccess],
)
async def import_references(
    request: Request,
    response: Response,
    catalog: CatalogDep,
    settings: SettingsDep,
    limiter: LimiterDep,
    replace: Annotated[bool, Query(description="replace references of those names")] = False,
) -> ImportResponse:
    with tempfile.TemporaryDirectory(prefix="dpc-import-") as folder:
        copy = await _received(request, Path(folder) / "copy.sqlite3")
        results = await limiter.write(
            _import,
            catalog,
            copy,
            replace,
            budget_s=settings.limits.request_timeout_s * max(1, len(copy.rows)),
        )
    if not any(outcome == CREATED for _, outcome, _ in results):
        response.status_code = status.HTTP_200_OK
    return ImportResponse(references=[answer_of(catalog.engine, *result) for result in results])


def _restore(job: Job, catalog: Catalog, copy: backup.Copy, source: str, replace: bool) -> str:
    return catalog.restore(copy, source, replace, job.commit)


def _import(job: Job, catalog: Catalog, copy: backup.Copy, replace: bool) -> list:
    return catalog.import_references(copy, replace, job.commit)


async def _copy(catalog: Catalog, names: list[str] | None, kind: str) -> FileResponse:
    """The copy written into a temporary file, sent, then deleted."""
    folder = tempfile.mkdtemp(prefix=f"dpc-{kind}-")
    path = Path(folder) / f"gallery-{kind}.sqlite3"
    cleanup = BackgroundTask(_remove, Path(folder))
    try:
        entries = await asyncio.to_thread(backup.write, catalog.store, path, names)
    except BaseException:
        await cleanup()
        raise
    return FileResponse(
        path,
        media_type=backup.MEDIA_TYPE,
        filename=path.name,
        headers={"X-References": str(len(entries))},
        background=cleanup,
    )


async def _received(request: Request, path: Path):
    """The request's body, a copy, written to ``path`` as it arrives, then read and checked."""
    size = 0
    with open(path, "wb") as handle:
        async for chunk in request.stream():
            size += len(chunk)
            handle.write(chunk)
    if size == 0:
        raise invalid("the body is empty: send the file dpc-mn backup or export wrote")
    return await asyncio.to_thread(backup.read, path)


def _remove(folder: Path) -> None:
    for child in folder.iterdir():
        child.unlink(missing_ok=True)
    folder.rmdir()
