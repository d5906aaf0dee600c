"""``POST /detect``: every registered part in a camera's whole frame."""

from __future__ import annotations

import time
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Query, Request

from service import memory
from service.api.auth import ReadAccess
from service.api.dependencies import LimiterDep, ProcessesDep, SettingsDep
from service.api.engine_processes import EngineProcesses
from service.api.routes.align import alternatives, transform, vector
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
    DetectionOut,
    DetectOptions,
    DetectRequest,
    DetectResponse,
    ReferenceName,
)
from service.api.uploads import CAMERA_FIELDS, Form, form_cloud, read_body
from service.api.validation import points_from_raw, validate_points
from service.engine.answer import SceneAnswer
from service.engine.frame import Frame, inside_box
from service.errors import InvalidPoints
from service.settings import Settings

router = APIRouter(tags=["detect"])

OPTIONS = tuple(DetectOptions.model_fields)  # candidates min_confidence viewpoint ...
SEARCH_SHARE = 0.75  # of the request's time budget, for the search (the rest: the answer)
ROI_CEILING = 2  # a frame given a region of interest: valid points up to this many limits
BODY = {
    "required": True,
    "content": {
        JSON: {"schema": {"$ref": "#/components/schemas/DetectRequest"}},
        RAW: {
            "schema": {"type": "string", "format": "binary"},
            "description": "little-endian float32 x y z triples; options as query parameters",
        },
        MULTIPART: {"schema": {"$ref": "#/components/schemas/DetectUpload"}},
    },
}


@router.post(
    "/detect",
    response_model=DetectResponse,
    summary="Find every registered part in a camera's whole frame",
    responses=errors(401, 404, 409, 413, 415, 422, 503, 504),
    openapi_extra={"requestBody": BODY},
    dependencies=[ReadAccess],
)
async def detect(
    request: Request,
    engine: ProcessesDep,
    settings: SettingsDep,
    limiter: LimiterDep,
    candidates: Annotated[list[ReferenceName] | None, Query()] = None,
    min_confidence: Annotated[float | None, Query(ge=0, le=1)] = None,
    viewpoint: Annotated[
        str | None, Query(description="where the camera was: x,y,z", examples=["0,0,0"])
    ] = None,
    max_instances: Annotated[int | None, Query(ge=1, le=200)] = None,
    roi: Annotated[
        str | None,
        Query(description="the box searched: min_x,min_y,min_z,max_x,max_y,max_z"),
    ] = None,
) -> DetectResponse:
    """A frame as ``/align`` takes a cloud: JSON ``{"points": ...}``, raw float32 triples, or a
    multipart ``file`` (an organized PCD or NPY, a depth image with ``fx fy cx cy``), the options
    as fields or query parameters. An organized frame keeps its pixel grid: its missing pixels
    are skipped, and ``indices`` are pixels (``row * width + col``)."""
    kind = body_kind(request, JSON, RAW, MULTIPART)
    # the frame's body and arrays come from the heap as the search's do: read and parsed
    # under the fixed threshold, they took 10-15 ms more (docs/decisions.md#a-frames-body)
    with memory.frame_heap():
        body = await read_body(request, kind, CAMERA_FIELDS + OPTIONS, "the frame")
        query = {
            "candidates": candidates,
            "min_confidence": min_confidence,
            "viewpoint": None if viewpoint is None else vector(viewpoint, "viewpoint"),
            "max_instances": max_instances,
            "roi": None if roi is None else box(roi),
        }
        query = {key: value for key, value in query.items() if value is not None}
        answer = await limiter.align(_detect, engine, settings, body, kind, query)
    counter = request.app.state.metrics_detections
    for detection in answer.detections:
        counter.labels(verdict=detection.verdict).inc()
    return answer


def _detect(
    engine: EngineProcesses,
    settings: Settings,
    body: bytes | Form,
    kind: str,
    query: dict[str, Any],
) -> DetectResponse:
    """Parse and validate the frame, detect (in a worker thread)."""
    limits = settings.limits
    index, shape, implied = None, None, None
    if isinstance(body, Form):
        options = parse(DetectOptions, {**query, **form_options(body)})
        most = _most_points(options, settings)
        cloud, implied = form_cloud(body, settings, options.viewpoint is None, most)
        points, index, shape = cloud.points, cloud.index, cloud.shape
    elif kind == RAW:
        options = parse(DetectOptions, query)
        points = points_from_raw(body, limits.min_points, _most_points(options, settings))
    else:
        data = json_object(body)
        known_fields(data, DetectRequest.model_fields)
        options = parse(
            DetectOptions, {**query, **{k: v for k, v in data.items() if k != "points"}}
        )
        most = _most_points(options, settings)
        points = validate_points(require(data, "points"), limits.min_points, most)
    viewpoint = options.viewpoint or implied
    frame = Frame.of(points, index, shape, None if viewpoint is None else np.asarray(viewpoint))
    roi = None if options.roi is None else (np.array(options.roi.min), np.array(options.roi.max))
    if roi is not None:
        _check_inside(points, roi, limits.max_points)
    # the search stops in time to answer with what it found, before the request's budget
    deadline = time.monotonic() + SEARCH_SHARE * limits.request_timeout_s
    scene = engine.detect(
        frame,
        options.candidates,
        options.max_instances,
        roi,
        options.min_confidence,
        deadline=deadline,
    )
    return detect_response(scene)


def _most_points(options: DetectOptions, settings: Settings) -> int:
    """The most valid points a frame may hold: the limit, or with a region of interest
    ``ROI_CEILING`` times it, of which only those inside count against the limit: a camera of
    more pixels than the limit, searched in a bin's region
    (docs/decisions.md#a-region-of-interest-and-the-limit)."""
    limit = settings.limits.max_points
    return limit if options.roi is None else ROI_CEILING * limit


def _check_inside(points: np.ndarray, roi: tuple[np.ndarray, np.ndarray], limit: int) -> None:
    """A 422 where the region of interest holds more than ``limit`` of the frame's points."""
    inside = int(np.count_nonzero(inside_box(points, *roi)))
    if inside > limit:
        raise InvalidPoints(
            f"the region of interest holds {inside} of the frame's valid points, more than the "
            f"maximum of {limit}: narrow it, or decimate the frame (every other row and column)"
        )


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
        elif name == "roi":
            options[name] = box(value)
        else:
            options[name] = value
    return options


def box(text: str) -> dict[str, list[float]]:
    """Six comma-separated finite numbers, min then max corner, or a 422 naming ``roi``."""
    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 6 or not all(np.isfinite(values)):
        raise invalid(
            f"'{text[:60]}' is not six finite numbers min_x,min_y,min_z,max_x,max_y,max_z", "roi"
        )
    return {"min": values[:3], "max": values[3:]}


def detect_response(scene: SceneAnswer) -> DetectResponse:
    detections = []
    for detection in scene.detections:
        a = detection.answer
        detections.append(
            DetectionOut(
                label=a.label,
                verdict=a.verdict,
                confidence=a.confidence,
                rotation=np.asarray(a.rotation, float).tolist(),
                translation=np.asarray(a.translation, float).tolist(),
                transform=transform(a),
                alignment_error=a.alignment_error,
                alignment_error_normalized=a.alignment_error_normalized,
                reasons=a.reasons,
                ambiguous=a.ambiguous,
                alternatives=alternatives(a),
                symmetry=detection.symmetry,
                num_points=len(detection.indices),
                indices=detection.indices.tolist(),
            )
        )
    return DetectResponse(
        detections=detections,
        num_points=scene.num_points,
        unexplained=scene.unexplained,
        supports=[np.asarray(plane, float).tolist() for plane in scene.supports],
        timings_ms=scene.timings_ms,
        complete=scene.complete,
        reasons=scene.reasons,
    )
