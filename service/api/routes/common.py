"""Helpers the routes share: body parsing, option validation, documented error answers."""

from __future__ import annotations

import difflib
import json
from collections.abc import Iterable
from typing import Any, TypeVar

import numpy as np
import orjson
from fastapi import Request, Response
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ValidationError

from service.api.schemas import Error

M = TypeVar("M", bound=BaseModel)


class UnsupportedMediaType(ValueError):
    """A body of a content type the route does not read (415)."""


JSON = "application/json"
RAW = "application/octet-stream"
MULTIPART = "multipart/form-data"


def body_kind(request: Request, *accepted: str) -> str:
    """The body's media type, one of ``accepted`` (no Content-Type reads as JSON), else 415."""
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if kind == "" or kind.endswith("+json"):
        kind = JSON
    if kind not in accepted:
        raise UnsupportedMediaType(
            f"cannot read a body of type '{kind}': send {' or '.join(accepted)}"
        )
    return kind


def json_object(body: bytes) -> dict[str, Any]:
    """A JSON object from the body (orjson), or a 422 naming what is wrong."""
    if not body:
        raise invalid("the body is empty: send a JSON object")
    try:
        data = orjson.loads(body)
    except orjson.JSONDecodeError as error:
        try:  # NaN, Infinity, 1e999: not JSON, but what Python's json sends; name them later
            data = json.loads(body)
        except ValueError:
            raise invalid(f"the body is not valid JSON: {error}") from None
    if not isinstance(data, dict):
        raise invalid("the body must be a JSON object")
    return data


def parse(model: type[M], data: dict[str, Any]) -> M:
    """Validate ``data`` with ``model``; a failure is the caller's (422), not a bug."""
    try:
        return model.model_validate(data)
    except ValidationError as error:
        raise RequestValidationError(error.errors(include_url=False)) from None


def known_fields(data: Iterable[str], accepted: Iterable[str]) -> None:
    """A 422 naming each field of ``data`` that is not ``accepted``, and the accepted ones."""
    accepted = list(accepted)
    unknown = [name for name in data if name not in accepted]
    if not unknown:
        return
    named = []
    for name in unknown[:5]:
        guess = difflib.get_close_matches(name, accepted, n=1)
        named.append(f"'{name[:64]}'" + (f" (did you mean '{guess[0]}'?)" if guess else ""))
    raise invalid(
        f"unknown field{'s' * (len(unknown) > 1)} {', '.join(named)}: the accepted fields are "
        f"{', '.join(accepted)}"
    )


def require(data: dict[str, Any], key: str) -> Any:
    if key not in data:
        raise invalid("Field required", key)
    return data[key]


def invalid(message: str, field: str = "body") -> RequestValidationError:
    """A 422 about one field (or the whole body), worded like FastAPI's own."""
    return RequestValidationError([{"loc": (field,), "msg": message, "type": "value_error"}])


def points_answer(description: str) -> dict[int | str, dict[str, Any]]:
    """The OpenAPI entry of a 200 that answers raw points."""
    content = {RAW: {"schema": {"type": "string", "format": "binary"}}}
    return {200: {"content": content, "description": f"little-endian float32 x y z {description}"}}


def points_response(points: np.ndarray, headers: dict[str, str] | None = None) -> Response:
    """(N, 3) points as little-endian float32 ``x y z`` triples, 12 bytes a point."""
    return Response(np.asarray(points, "<f4").tobytes(), media_type=RAW, headers=headers)


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI entries for error answers, all ``{"detail": "..."}``."""
    described = {
        401: "no API key, or one that is not valid",
        403: "the API key's role may not do this",
        404: "an unknown reference",
        409: "a conflict with the gallery's state",
        413: "the body is over the size limit",
        415: "a content type the route does not read",
        422: "bad points or fields; the detail names the problem",
        503: "the model or gallery is not loaded yet, or every slot stayed busy",
        504: "the work ran past the request's time budget (`limits.request_timeout_s`)",
        507: "the gallery's disk is full: nothing was stored; free space, then send it again",
    }
    headers = {
        401: {"WWW-Authenticate": "`Bearer`"},
        503: {"Retry-After": "seconds to wait before retrying, when every slot was busy"},
    }
    return {
        code: {
            "model": Error,
            "description": described[code],
            **(
                {"headers": {k: _header(v) for k, v in headers[code].items()}}
                if code in headers
                else {}
            ),
        }
        for code in codes
    }


def _header(description: str) -> dict[str, Any]:
    return {"description": description, "schema": {"type": "string"}}
