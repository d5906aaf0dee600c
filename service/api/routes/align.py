"""``POST /align``: recognise the object in an observed cloud and estimate its pose."""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Query, Request

from service.api.auth import ReadAccess
from service.api.dependencies import LimiterDep, ProcessesDep, RecentDep, SettingsDep
from service.api.engine_processes import EngineProcesses
from service.api.recent import RecentAlignments
from service.api.routes.common import (
    JSON,
    MULTIPART,
    RAW,
    body_kind,
    errors,
    invalid,
    json_object,
    known_fields,
    parse,
    require,
)
from service.api.schemas import (
    AlignOptions,
    AlignRequest,
    AlignResponse,
    AlternativePose,
    CandidateFit,
    ReferenceName,
)
from service.api.uploads import CAMERA_FIELDS, Form, form_points, read_body
from service.api.validation import points_from_raw, validate_points
from service.engine.answer import Alignment
from service.settings import Settings

router = APIRouter(tags=["align"])

OPTIONS = tuple(AlignOptions.model_fields)  # candidates top_k refine viewpoint min_confidence
BODY = {
    "required": True,
    "content": {
        JSON: {"schema": {"$ref": "#/components/schemas/AlignRequest"}},
        RAW: {
            "schema": {"type": "string", "format": "binary"},
            "description": "little-endian float32 x y z triples; options as query parameters",
        },
        MULTIPART: {"schema": {"$ref": "#/components/schemas/AlignUpload"}},
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
    engine: ProcessesDep,
    settings: SettingsDep,
    limiter: LimiterDep,
    recent: RecentDep,
    # for a raw body; a JSON body carries them as fields, which take precedence
    candidates: Annotated[list[ReferenceName] | None, Query()] = None,
    top_k: Annotated[int | None, Query(ge=1)] = None,
    refine: Annotated[bool | None, Query()] = None,
    viewpoint: Annotated[
        str | None, Query(description="where the sensor was: x,y,z", examples=["0,0,0"])
    ] = None,
    min_confidence: Annotated[float | None, Query(ge=0, le=1)] = None,
) -> AlignResponse:
    """JSON ``{"points": [[x, y, z], ...], ...}``; a raw body of little-endian float32 ``x y z``
    triples with the options as query parameters (``viewpoint=x,y,z``); or a multipart upload:
    a cloud, mesh or depth-image ``file`` (a depth image with ``fx``, ``fy``, ``cx``, ``cy``;
    its viewpoint is the camera, ``[0, 0, 0]``), the options as fields or query parameters."""
    kind = body_kind(request, JSON, RAW, MULTIPART)
    body = await read_body(request, kind, CAMERA_FIELDS + OPTIONS, "the cloud")
    query = {
        "candidates": candidates,
        "top_k": top_k,
        "refine": refine,
        "viewpoint": None if viewpoint is None else vector(viewpoint, "viewpoint"),
        "min_confidence": min_confidence,
    }
    query = {key: value for key, value in query.items() if value is not None}
    return await limiter.align(_align, engine, settings, body, kind, query, recent)


def _align(
    engine: EngineProcesses,
    settings: Settings,
    body: bytes | Form,
    kind: str,
    query: dict[str, Any],
    recent: RecentAlignments,
) -> AlignResponse:
    """Parse and validate the body, align (in a worker thread): CPU-bound from end to end."""
    limits = settings.limits
    if isinstance(body, Form):
        source = f"file {body.files['file'][1] or ''}".strip()
        options = parse(AlignOptions, {**query, **form_options(body)})
        points, implied = form_points(body, settings, imply=options.viewpoint is None)
        if options.viewpoint is None and implied is not None:
            options.viewpoint = implied
    elif kind == RAW:
        source = "raw"
        options = parse(AlignOptions, query)
        points = points_from_raw(body, limits.min_points, limits.max_points)
    else:
        source = "json"
        data = json_object(body)
        known_fields(data, AlignRequest.model_fields)
        options = parse(AlignOptions, {**query, **{k: v for k, v in data.items() if k != "points"}})
        points = validate_points(require(data, "points"), limits.min_points, limits.max_points)
    viewpoint = None if options.viewpoint is None else np.asarray(options.viewpoint, np.float64)
    alignment = engine.align(
        points,
        options.candidates,
        options.top_k,
        options.refine,
        viewpoint=viewpoint,
        min_confidence=options.min_confidence,
    )
    answer = alignment_response(alignment)
    recent.add(points, options.viewpoint, source, answer)
    return answer


def form_options(form: Form) -> dict[str, Any]:
    """The options a multipart body gives as text fields (``candidates`` may repeat)."""
    options: dict[str, Any] = {}
    for name in OPTIONS:
        value = form.value(name)
        if value is None:
            continue
        if name == "candidates":
            options[name] = form.fields[name]
        elif name == "viewpoint":
            options[name] = vector(value, name)
        else:
            options[name] = value
    return options


def vector(text: str, name: str) -> list[float]:
    """Three comma-separated finite numbers from a query parameter, or a 422 naming it."""
    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not all(np.isfinite(values)):
        raise invalid(f"'{text[:40]}' is not three finite numbers x,y,z", name)
    return values


def transform(alignment: Alignment) -> list[list[float]]:
    """The answer's pose as a 4x4 matrix ``[[R, t], [0, 0, 0, 1]]``."""
    matrix = np.eye(4)
    matrix[:3, :3] = alignment.rotation
    matrix[:3, 3] = alignment.translation
    return matrix.tolist()


def alternatives(alignment: Alignment) -> list[AlternativePose]:
    return [
        AlternativePose(
            rotation=np.asarray(a.rotation, float).tolist(),
            translation=np.asarray(a.translation, float).tolist(),
            confidence=a.confidence,
            label=a.label,
        )
        for a in alignment.alternatives
    ]


def alignment_response(alignment: Alignment) -> AlignResponse:
    return AlignResponse(
        label=alignment.label,
        score=alignment.score,
        rotation=np.asarray(alignment.rotation, dtype=float).tolist(),
        translation=np.asarray(alignment.translation, dtype=float).tolist(),
        transform=transform(alignment),
        alignment_error=alignment.alignment_error,
        alignment_error_normalized=alignment.alignment_error_normalized,
        hypothesis=alignment.hypothesis,
        candidates=[
            CandidateFit.model_validate(fit, from_attributes=True) for fit in alignment.candidates
        ],
        timings_ms=alignment.timings_ms,
        verdict=alignment.verdict,
        confidence=alignment.confidence,
        reasons=alignment.reasons,
        ambiguous=alignment.ambiguous,
        alternatives=alternatives(alignment),
        points_set_aside=alignment.points_set_aside,
    )
