"""What the client raises: one exception type per kind of refusal, each with the service's words.

Every error answer of the service is ``{"detail": "..."}`` (docs/api.md); the exception keeps
``status``, ``detail`` (what to change), ``request_id`` (to find the request in the service's
log) and, for a 503, ``retry_after`` in seconds.
"""

from __future__ import annotations


class ServiceError(Exception):
    """The service refused or failed a request (``status`` is None when it was not reached)."""

    def __init__(
        self,
        detail: str,
        status: int | None = None,
        request_id: str | None = None,
        retry_after: float | None = None,
    ):
        super().__init__(detail)
        self.detail = detail
        self.status = status
        self.request_id = request_id
        self.retry_after = retry_after
        self.attempts = 1  # how many times the call was sent (more when retried)

    def __str__(self) -> str:
        return self.detail if self.status is None else f"{self.status}: {self.detail}"


class Unreachable(ServiceError):
    """No answer: the service is not running at that address, or the network failed."""


class BadRequest(ServiceError):
    """400: a request the service could not read (a malformed header)."""


class Unauthorized(ServiceError):
    """401: no API key, or one the service does not know."""


class Forbidden(ServiceError):
    """403: the API key's role may not do this (a ``read`` key registering)."""


class NotFound(ServiceError):
    """404: an unknown reference (or candidate), or an alignment no longer kept."""


class Conflict(ServiceError):
    """409: a name already registered, a full gallery, or no reference to align against."""


class TooLarge(ServiceError):
    """413: the body is over the service's size limit; send fewer points."""


class UnsupportedMediaType(ServiceError):
    """415: a content type the route does not read."""


class InvalidInput(ServiceError):
    """422: bad points, a bad file or a bad option; ``detail`` names the problem."""


class Unavailable(ServiceError):
    """503: still loading, busy, or the gallery's database is out of reach (nothing was
    changed); retry after ``retry_after`` seconds. 502 from a proxy in front (a replica died
    mid-request: a write's outcome is unknown) is raised as this too."""


class TimedOut(ServiceError):
    """504: the work ran past the service's time budget."""


class StorageFull(ServiceError):
    """507: the gallery's disk is full; nothing was stored (alignments are still served)."""


class ServerError(ServiceError):
    """Another 5xx: a bug in the service; ``request_id`` finds it in the log."""


BY_STATUS: dict[int, type[ServiceError]] = {
    400: BadRequest,
    401: Unauthorized,
    403: Forbidden,
    404: NotFound,
    409: Conflict,
    413: TooLarge,
    415: UnsupportedMediaType,
    422: InvalidInput,
    502: Unavailable,
    503: Unavailable,
    504: TimedOut,
    507: StorageFull,
}


def error_for(status: int) -> type[ServiceError]:
    """The exception type of an error status."""
    return BY_STATUS.get(status, ServerError if status >= 500 else ServiceError)
