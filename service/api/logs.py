"""Structured logs: one JSON object a line, and a request id on every request.

``RequestLog`` (ASGI middleware) takes the caller's ``X-Request-ID`` (or makes one), echoes
it in the response, keeps it in a context variable for every log line written while the
request is served (worker threads included), and writes one access line per request:
``time, level, message, request_id, method, path, status, duration_ms``. Nothing else of a
request is logged: no headers (so no API key), no query string, no body (so no points).
"""

from __future__ import annotations

import json
import logging
import re
import time
import uuid
from contextvars import ContextVar
from datetime import UTC, datetime

from starlette.types import ASGIApp, Message, Receive, Scope, Send

log = logging.getLogger("service.access")

request_id: ContextVar[str | None] = ContextVar("request_id", default=None)

HEADER = "X-Request-ID"
ACCEPTED_ID = re.compile(r"^[A-Za-z0-9._:-]{1,128}$")  # else a fresh one is made
FIELDS = ("request_id", "method", "path", "status", "duration_ms")
QUIET_PATHS = ("/metrics", "/v2/health/")  # polled by machines: logged at DEBUG


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
        }
        for field in FIELDS:
            value = getattr(record, field, None)
            if value is not None:
                entry[field] = value
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


class RequestIdFilter(logging.Filter):
    """Stamps every record with the id of the request being served, if any."""

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, "request_id", None) is None:
            record.request_id = request_id.get()
        return True


def configure(level: str, fmt: str = "json") -> None:
    """Root logging to stderr, one JSON object a line (``fmt="json"``) or plain text."""
    handler = logging.StreamHandler()
    handler.addFilter(RequestIdFilter())
    if fmt == "json":
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(
            logging.Formatter("%(asctime)s %(levelname)s %(name)s [%(request_id)s]: %(message)s")
        )
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    # trimesh logs a traceback at WARNING for every unreadable upload: the 422 says it already
    logging.getLogger("trimesh").setLevel(max(root.level, logging.ERROR))


class RequestLog:
    """Request id in and out, and one access log line a request."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        began = time.perf_counter()
        given = dict(scope["headers"]).get(HEADER.lower().encode(), b"").decode("latin-1")
        rid = given if ACCEPTED_ID.match(given) else uuid.uuid4().hex
        request_id.set(rid)  # the request's own task: later handlers (the 500 one) see it too
        status = 500

        async def send_with_id(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                headers = [(k, v) for k, v in message.get("headers", []) if k != b"x-request-id"]
                message = {**message, "headers": [*headers, (b"x-request-id", rid.encode())]}
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            path = scope.get("path", "")
            quiet = path.startswith(QUIET_PATHS)
            log.log(
                logging.DEBUG if quiet and status < 400 else logging.INFO,
                "%s %s %d",
                scope.get("method", ""),
                path,
                status,
                extra={
                    "method": scope.get("method"),
                    "path": path,
                    "status": status,
                    "duration_ms": round((time.perf_counter() - began) * 1e3, 3),
                },
            )
