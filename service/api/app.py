"""The FastAPI application: lifespan, error mapping, body limit, metrics, logs, the routers.

``create_app(settings)`` builds it; the lifespan runs the startup checks (``service.api.startup``:
the model, its manifest, the data directory, the store's schema), then loads the gallery in a
background thread, so ``/v2/health/live`` answers at once and ``/v2/health/ready`` turns 200
when the gallery is in; the same thread then follows other replicas' changes to the store
(``service.gallery.follower``), and readiness turns 503 while the store cannot be reached.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from prometheus_client import CollectorRegistry, Counter, Gauge
from prometheus_fastapi_instrumentator import Instrumentator
from starlette.exceptions import HTTPException
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api import auth, logs, startup
from service.api.dependencies import Loading, NotReady
from service.api.engine_processes import EngineProcesses
from service.api.limiter import Busy, Limiter, TimedOut
from service.api.recent import RecentAlignments
from service.api.routes import align, alignments, detect, gallery, health, points, references
from service.api.routes.common import UnsupportedMediaType
from service.api.schemas import (
    AlignOptions,
    AlignRequest,
    DetectOptions,
    DetectRequest,
    ReferenceRequest,
)
from service.api.uploads import cloud_upload_schema
from service.engine import kernels
from service.engine.mapping import Mapper
from service.errors import (
    EmptyGallery,
    InvalidPoints,
    ReferenceExists,
    StoreFull,
    StoreUnavailable,
    UnknownReference,
)
from service.gallery.backup import BackupInvalid
from service.gallery.catalog import Catalog, GalleryFull
from service.gallery.follower import follow
from service.gallery.store import GalleryStore, StoreCorrupted, StoreIncompatible, StoreNotEmpty
from service.settings import Settings

log = logging.getLogger("service")

CONSOLE = Path(__file__).resolve().parent.parent / "console"  # static files, no build step

VERSION = "0.1.0"
LOAD_RETRY_S = 2.0  # between tries to load the gallery while its store cannot be reached
STATUS = {  # the one status code of each error the engine, store and routes raise
    InvalidPoints: 422,
    UnknownReference: 404,
    alignments.UnknownAlignment: 404,
    EmptyGallery: 409,
    ReferenceExists: 409,
    GalleryFull: 409,
    StoreNotEmpty: 409,  # a restore into a gallery that holds references
    BackupInvalid: 422,  # not a usable copy of a gallery: the detail names the problem
    UnsupportedMediaType: 415,
    NotReady: 503,
    StoreUnavailable: 503,  # the gallery's database is out of reach: a write may be retried
    StoreFull: 507,  # no room on the gallery's disk: nothing stored, reads still served
    Busy: 503,  # with Retry-After
    TimedOut: 504,
}
ERROR_REF = "#/components/schemas/Error"


DESCRIPTION = (
    "Recognise a registered object in a point cloud and estimate its 6-DoF pose "
    "(scene = R @ model + t). Points go as JSON, raw little-endian float32, or a camera's file "
    "(PLY, PCD, NPY, or a depth image with its intrinsics) as a multipart upload. The web "
    "console is at [/ui/](/ui/); the package ships a Python client (`service.client.Client`) "
    "and the `dpc-mn` command."
)


class BodyTooLarge(Exception):
    """A request body over ``limits.max_body_bytes`` (413)."""


def create_app(
    settings: Settings | None = None, prepared: tuple[Mapper, GalleryStore] | None = None
) -> FastAPI:
    """The app; ``prepared`` is ``startup.prepare``'s result when the caller already ran it."""
    settings = settings or Settings()
    app = FastAPIOffline(  # /docs and /redoc load Swagger UI and ReDoc from this service
        title="DPC-MN pose service",
        version=VERSION,
        description=DESCRIPTION,
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.prepared = prepared
    app.state.recent = RecentAlignments(settings.recent_alignments)
    routers = (
        align.router,
        detect.router,
        points.router,
        alignments.router,
        references.router,
        gallery.router,
        health.router,
    )
    for router in routers:
        app.include_router(router)
    if settings.console.enabled:
        _add_console(app)
    _add_error_handlers(app)
    bulk = dict.fromkeys(BULK_ROUTES, settings.limits.max_bulk_bytes)
    app.add_middleware(BodyLimit, max_bytes=settings.limits.max_body_bytes, larger=bulk)
    _add_metrics(app)  # counts every answer, the 413s included
    app.add_middleware(logs.RequestLog)  # outermost: every answer has a request id
    app.openapi = lambda: _openapi(app)
    return app


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    settings: Settings = app.state.settings
    mapper, store = app.state.prepared or startup.prepare(settings)
    log.info(
        "model %s (sha256 %s), execution providers %s",
        mapper.path,
        mapper.model_hash,
        ", ".join(mapper.providers),
    )
    _log_auth(settings)
    engine = startup.make_engine(settings, mapper)
    log.info("the engine's loops: %s", kernels.describe())
    catalog = Catalog(engine, store, settings.gallery.max_references)
    app.state.catalog = catalog
    app.state.processes = processes = EngineProcesses(catalog, settings, settings.engine_processes)
    limits = settings.limits
    app.state.limiter = limiter = Limiter(
        settings.align_slots, limits.queue_timeout_s, limits.request_timeout_s
    )
    app.state.loading = loading = Loading()
    app.state.metrics_references.set_function(lambda: len(catalog.engine))
    stop = threading.Event()
    keeper = threading.Thread(
        target=_keep_gallery,
        args=(catalog, settings, loading, stop, processes),
        name="gallery",
        daemon=True,
    )
    keeper.start()
    yield
    limiter.close()
    processes.close()
    stop.set()
    keeper.join(timeout=settings.gallery.poll_s + 1.0)  # a load cannot be interrupted: the
    # daemon thread then dies with us
    if not keeper.is_alive():
        store.close()


def _log_auth(settings: Settings) -> None:
    """Say how callers are checked; the keys themselves are never logged."""
    keys = settings.auth.keys
    if not keys:
        log.warning(
            "auth: OPEN MODE, no API key is configured (DPC_AUTH__KEYS): anyone who reaches "
            "this port may register and delete references"
        )
        return
    roles = sorted(keys.values())
    log.info(
        "auth: %d API key(s) (%d admin, %d read); reads %s a key",
        len(keys),
        roles.count("admin"),
        roles.count("read"),
        "need" if settings.auth.require_key_for_reads else "do not need",
    )


def _keep_gallery(
    catalog: Catalog,
    settings: Settings,
    loading: Loading,
    stop: threading.Event,
    processes: EngineProcesses,
) -> None:
    """Load the gallery, waiting while its store cannot be reached; start the engine's worker
    processes; then follow the changes other replicas make (``service.gallery.follower``) until
    the app stops."""
    kernels.warm()  # compiled on the first start (seconds), loaded from numba's cache after
    while not _load(catalog, settings, loading):
        if loading.status == "failed" or stop.wait(LOAD_RETRY_S):
            return
    threading.Thread(target=processes.start, name="engine-processes", daemon=True).start()
    follow(catalog, settings.gallery.poll_s, stop, loading.report_store)


def _load(catalog: Catalog, settings: Settings, loading: Loading) -> bool:
    """Seed, refresh and load the gallery; record the outcome for the health routes. False
    while the store cannot be reached (try again) or when the load failed."""
    try:
        catalog.load(settings.model.gallery)
    except StoreUnavailable as error:
        log.warning("waiting for the gallery store: %s", error)
        loading.detail = f"waiting for the gallery store: {error}"
        return False
    except StoreCorrupted as error:
        log.error("the gallery store is damaged: %s", error)
        loading.detail, loading.status = f"the gallery store is damaged: {error}", "failed"
    except StoreIncompatible as error:  # a database reached only now, of another version
        log.error("the gallery store cannot be used: %s", error)
        loading.detail, loading.status = f"loading the gallery failed: {error}", "failed"
    except Exception as error:
        log.exception("loading the gallery failed")
        loading.detail, loading.status = f"loading the gallery failed: {error}", "failed"
    else:
        loading.detail, loading.status = None, "ok"
    return loading.ready


BULK_ROUTES = ("/references/batch", "/gallery/restore", "/gallery/import")


class BodyLimit:
    """413 for a body over ``max_bytes`` (on the paths of ``larger``, their limit): by its
    Content-Length, or by the bytes actually read."""

    def __init__(self, app: ASGIApp, max_bytes: int, larger: dict[str, int] | None = None):
        self.app = app
        self.max_bytes = max_bytes
        self.larger = larger or {}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if scope["path"] in self.larger:
            limited = BodyLimit(self.app, self.larger[scope["path"]])
            await limited(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None:
            if not declared.isdigit():
                await _answer(scope, receive, send, 400, "Content-Length is not a number")
                return
            if int(declared) > self.max_bytes:
                await _answer(scope, receive, send, 413, self.message(int(declared)))
                return
        received = 0

        async def limited() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise BodyTooLarge(self.message(received, at_least=True))
            return message

        await self.app(scope, limited, send)

    def message(self, size: int, at_least: bool = False) -> str:
        return (
            f"the body is {'over ' if at_least else ''}{size} bytes, more than the limit of "
            f"{self.max_bytes}: send fewer points"
        )


async def _answer(scope: Scope, receive: Receive, send: Send, code: int, detail: str) -> None:
    await JSONResponse({"detail": detail}, status_code=code)(scope, receive, send)


def _add_error_handlers(app: FastAPI) -> None:
    """Every error answer is ``{"detail": "..."}``; an unexpected exception is a 500 (a bug)."""

    def handler(code: int) -> Callable[[Request, Exception], Awaitable[JSONResponse]]:
        async def answer(request: Request, error: Exception) -> JSONResponse:
            headers = getattr(error, "headers", None)  # Busy's Retry-After
            return JSONResponse({"detail": str(error)}, status_code=code, headers=headers)

        return answer

    for error_type, code in STATUS.items():
        app.add_exception_handler(error_type, handler(code))
    app.add_exception_handler(BodyTooLarge, handler(413))

    async def invalid(request: Request, error: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": validation_message(error.errors())}, status_code=422)

    async def http_error(request: Request, error: HTTPException) -> JSONResponse:
        headers = error.headers
        if error.status_code == 405:  # every method of the path, not only its first route's
            headers = {**(headers or {}), "Allow": ", ".join(allowed_methods(app, request))}
        return JSONResponse(
            {"detail": str(error.detail)}, status_code=error.status_code, headers=headers
        )

    async def bug(request: Request, error: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        rid = logs.request_id.get()
        return JSONResponse(
            {"detail": f"internal error ({type(error).__name__}); this is a bug"},
            status_code=500,
            headers={logs.HEADER: rid} if rid else None,
        )

    app.add_exception_handler(RequestValidationError, invalid)
    app.add_exception_handler(HTTPException, http_error)
    app.add_exception_handler(Exception, bug)


def allowed_methods(app: FastAPI, request: Request) -> list[str]:
    """The methods the routes of a request's path answer (Starlette names only the first's)."""
    methods: set[str] = set()
    for route in app.router.routes:
        match, _ = route.matches(request.scope)
        if match != Match.NONE:
            methods |= getattr(route, "methods", None) or set()
    return sorted(methods)


def validation_message(errors: Any) -> str:
    """pydantic/FastAPI errors as one readable line: ``top_k: Input should be ...; ...``."""
    parts = []
    for error in errors:
        where = ".".join(str(p) for p in error.get("loc", ()) if p != "body")
        message = error.get("msg", "invalid")
        if error.get("type") == "string_pattern_mismatch":
            message = "a reference name is 1 to 64 characters of A-Z a-z 0-9 . _ -"
        parts.append(f"{where}: {message}" if where else message)
    return "; ".join(parts) or "invalid request"


def _add_console(app: FastAPI) -> None:
    """The web console's static files at ``/ui/`` (``service/console``), and ``/`` leading there."""
    app.mount("/ui", StaticFiles(directory=CONSOLE, html=True), name="console")

    @app.get("/", include_in_schema=False)
    async def home() -> RedirectResponse:
        return RedirectResponse("/ui/")


def _add_metrics(app: FastAPI) -> None:
    """Prometheus at ``/metrics``: requests, latencies and status codes per route, references,
    and the writes (registrations, deletions, restores) being worked on: what a replica held
    when it died."""
    registry = CollectorRegistry()  # one per app, so several apps can live in one process
    Instrumentator(
        should_group_status_codes=False,
        excluded_handlers=["/metrics"],
        registry=registry,
    ).instrument(app).expose(app, endpoint="/metrics", include_in_schema=False)
    app.state.metrics_references = Gauge(
        "dpc_references", "References in the gallery", registry=registry
    )
    app.state.metrics_detections = Counter(
        "dpc_detections",
        "Instances POST /detect answered, by verdict",
        ["verdict"],
        registry=registry,
    )
    for name, described, holder, field in (
        ("dpc_writes_in_progress",
         "Registrations, deletions, restores and imports being worked on", "limiter", "writing"),
        ("dpc_engine_processes",
         "Engine worker processes answering /align and /detect (0: the service's own process)",
         "processes", "ready"),
        ("dpc_engine_processes_wanted",
         "Engine worker processes meant to answer (server.engine_processes; 0 if they failed)",
         "processes", "wanted"),
        ("dpc_engine_process_jobs",
         "Alignments and detections the engine worker processes answered", "processes", "jobs"),
        ("dpc_engine_process_segments",
         "Segments of a lone /detect's frame that the engine worker processes searched",
         "processes", "segments"),
    ):  # fmt: skip
        _read_at_scrape(Gauge(name, described, registry=registry), app, holder, field)


def _read_at_scrape(gauge: Gauge, app: FastAPI, holder: str, field: str) -> None:
    """``gauge`` reads ``app.state.<holder>.<field>`` when scraped (0 before the lifespan has
    made the holder)."""
    gauge.set_function(lambda: getattr(getattr(app.state, holder, None), field, 0))


def _document_auth(document: dict[str, Any], settings: Settings) -> None:
    """Keep the security requirements (a role each, as the scope) that this service enforces:
    none when it is open, only the writes' when reads need no key."""
    mode = auth.mode(settings.auth)
    for operation in (op for path in document["paths"].values() for op in path.values()):
        roles = {role for need in operation.get("security", []) for role in sum(need.values(), [])}
        if mode == "open" or (mode == "keys-for-writes" and roles == {"read"}):
            operation.pop("security", None)
            for code in ("401", "403"):
                operation.get("responses", {}).pop(code, None)
    if mode == "open":
        document.get("components", {}).pop("securitySchemes", None)


def _openapi(app: FastAPI) -> dict[str, Any]:
    """The generated document, plus the request bodies the routes read themselves."""
    if app.openapi_schema:
        return app.openapi_schema
    document = get_openapi(
        title=app.title, version=app.version, description=app.description, routes=app.routes
    )
    schemas = document.setdefault("components", {}).setdefault("schemas", {})
    # our 422 is {"detail": "..."} (validation_message), not FastAPI's list of errors
    for operation in (op for path in document["paths"].values() for op in path.values()):
        invalid = operation.get("responses", {}).get("422")
        if invalid:
            invalid["content"] = {"application/json": {"schema": {"$ref": ERROR_REF}}}
    for name in ("HTTPValidationError", "ValidationError"):
        schemas.pop(name, None)
    _document_auth(document, app.state.settings)
    for model in (AlignRequest, DetectRequest, ReferenceRequest):
        schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
        schemas.update(schema.pop("$defs", {}))
        schemas[model.__name__] = schema
    name = ReferenceRequest.model_json_schema()["properties"]["name"]
    schemas["ReferenceUpload"] = {
        "title": "ReferenceUpload",
        "type": "object",
        "required": ["name", "file"],
        "additionalProperties": False,
        "properties": {
            "name": name,
            "file": {
                "type": "string",
                "format": "binary",
                "description": "a mesh (.stl, .obj, .ply) or a cloud (.ply, .pcd, .npy)",
            },
            "units": ReferenceRequest.model_json_schema()["properties"]["units"],
        },
    }
    schemas["ReferenceBatch"] = {
        "title": "ReferenceBatch",
        "type": "object",
        "required": ["file"],
        "additionalProperties": False,
        "properties": {
            "file": {
                "type": "array",
                "items": {"type": "string", "format": "binary"},
                "description": "one mesh or cloud a part (repeat the field)",
            },
            "name": {
                "type": "array",
                "items": name,
                "description": "one a file, in order (default: each file's name without suffix)",
            },
        },
    }
    options = AlignOptions.model_json_schema()["properties"]
    options["viewpoint"] = {"type": "string", "description": "x,y,z: where the sensor was"}
    options["candidates"]["description"] += " (repeat the field for each name)"
    schemas["CloudUpload"] = cloud_upload_schema("CloudUpload")
    schemas["AlignUpload"] = cloud_upload_schema("AlignUpload", options)
    options = DetectOptions.model_json_schema()["properties"]
    options["viewpoint"] = {"type": "string", "description": "x,y,z: where the camera was"}
    options["roi"] = {"type": "string", "description": "min_x,min_y,min_z,max_x,max_y,max_z"}
    options["candidates"]["description"] += " (repeat the field for each name)"
    schemas["DetectUpload"] = cloud_upload_schema("DetectUpload", options)
    app.openapi_schema = document
    return document
