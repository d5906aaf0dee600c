"""``POST /points``: the points the service reads from a file, as ``/align`` would use them.

The console draws what the service sees: it posts the dropped file here, draws the answer and
sends the same points on to ``/align`` as raw float32. Scripts can use it to check a camera's
files (a depth image's intrinsics, a mask) before aligning them.
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from service.api.auth import ReadAccess
from service.api.dependencies import LimiterDep, SettingsDep
from service.api.routes.common import (
    MULTIPART,
    body_kind,
    errors,
    points_answer,
    points_response,
)
from service.api.uploads import CAMERA_FIELDS, CLOUD_FILES, form_points, read_form

router = APIRouter(tags=["align"])

COUNT_HEADER = "X-Points"
VIEWPOINT_HEADER = "X-Viewpoint"
BODY = {
    "required": True,
    "content": {MULTIPART: {"schema": {"$ref": "#/components/schemas/CloudUpload"}}},
}


@router.post(
    "/points",
    response_class=Response,
    summary="Read a cloud, mesh or depth-image file into the points /align would use",
    responses=points_answer(
        "triples; `X-Points` is their count, `X-Viewpoint` (x,y,z) the viewpoint the file "
        "implies (a depth image: 0,0,0)"
    )
    | errors(401, 413, 415, 422, 503, 504),
    openapi_extra={"requestBody": BODY},
    dependencies=[ReadAccess],
)
async def points(request: Request, settings: SettingsDep, limiter: LimiterDep) -> Response:
    body_kind(request, MULTIPART)
    form = await read_form(request, CLOUD_FILES, CAMERA_FIELDS, "the cloud")
    cloud, viewpoint = await limiter.align(form_points, form, settings)
    headers = {COUNT_HEADER: str(len(cloud))}
    if viewpoint is not None:
        headers[VIEWPOINT_HEADER] = ",".join(f"{v:g}" for v in viewpoint)
    return points_response(cloud, headers)
