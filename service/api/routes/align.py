"""``POST /align``: recognise the object in an observed cloud and estimate its pose."""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Query, Request

from service.api.auth import ReadAccess
from service.api.dependencies import EngineDep, LimiterDep, SettingsDep
from service.api.routes.common import JSON, body_kind, errors, json_object, parse, require
from service.api.schemas import AlignOptions, AlignResponse, CandidateFit, ReferenceName
from service.api.validation import points_from_raw, validate_points
from service.engine.engine import Alignment, Engine
from service.settings import LimitSettings

router = APIRouter(tags=["align"])

RAW = "application/octet-stream"
BODY = {
    "required": True,
    "content": {
        JSON: {"schema": {"$ref": "#/components/schemas/AlignRequest"}},
        RAW: {
            "schema": {"type": "string", "format": "binary"},
            "description": "little-endian float32 x y z triples; options as query parameters",
        },
    },
}


@router.post(
    "/align",
    response_model=AlignResponse,
    summary="Recognise the object in a cloud and estimate its pose",
    responses=errors(401, 404, 409, 413, 415, 422, 503, 504),
    openapi_extra={"requestBody": BODY},
    dependencies=[ReadAccess],
)
async def align(
    request: Request,
    engine: EngineDep,
    settings: SettingsDep,
    limiter: LimiterDep,
    # for a raw body; a JSON body carries them as fields, which take precedence
    candidates: Annotated[list[ReferenceName] | None, Query()] = None,
    top_k: Annotated[int | None, Query(ge=1)] = None,
    refine: Annotated[bool | None, Query()] = None,
) -> AlignResponse:
    """JSON ``{"points": [[x, y, z], ...], ...}``, or a raw body of little-endian float32
    ``x y z`` triples with ``candidates``, ``top_k`` and ``refine`` as query parameters."""
    kind = body_kind(request, JSON, RAW)
    body = await request.body()
    query = {"candidates": candidates, "top_k": top_k, "refine": refine}
    query = {key: value for key, value in query.items() if value is not None}
    return await limiter.align(_align, engine, settings.limits, body, kind, query)


def _align(
    engine: Engine, limits: LimitSettings, body: bytes, kind: str, query: dict[str, Any]
) -> AlignResponse:
    """Parse and validate the body, align (in a worker thread): CPU-bound from end to end."""
    if kind == RAW:
        options = parse(AlignOptions, query)
        points = points_from_raw(body, limits.min_points, limits.max_points)
    else:
        data = json_object(body)
        options = parse(AlignOptions, {**query, **{k: v for k, v in data.items() if k != "points"}})
        points = validate_points(require(data, "points"), limits.min_points, limits.max_points)
    alignment = engine.align(points, options.candidates, options.top_k, options.refine)
    return alignment_response(alignment)


def alignment_response(alignment: Alignment) -> AlignResponse:
    transform = np.eye(4)
    transform[:3, :3] = alignment.rotation
    transform[:3, 3] = alignment.translation
    return AlignResponse(
        label=alignment.label,
        score=alignment.score,
        rotation=np.asarray(alignment.rotation, dtype=float).tolist(),
        translation=np.asarray(alignment.translation, dtype=float).tolist(),
        transform=transform.tolist(),
        alignment_error=alignment.alignment_error,
        alignment_error_normalized=alignment.alignment_error_normalized,
        hypothesis=alignment.hypothesis,
        candidates=[
            CandidateFit.model_validate(fit, from_attributes=True) for fit in alignment.candidates
        ],
        timings_ms=alignment.timings_ms,
    )
