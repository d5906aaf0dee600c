"""``POST /points``: the points the service reads from a file, as ``/align`` would use them.

The console draws what the service sees: it posts the dropped file here, draws the answer and
sends the same points on to ``/align`` as raw float32. Scripts can use it to check a camera's
files (a depth image's intrinsics, a mask) before aligning them.

An organized frame (a depth image, a PCD or NPY of height > 1) answers its grid in ``X-Shape``;
with ``?pixels=true`` each point's pixel (``row * width + col``, the indices ``/detect``
answers) follows the points, so that a client can place ``/detect``'s claims on them.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from fastapi import APIRouter, Query, Request, Response

from service.api.auth import ReadAccess
from service.api.dependencies import LimiterDep, SettingsDep
from service.api.routes.common import (
    MULTIPART,
    RAW,
    body_kind,
    errors,
    points_answer,
)
from service.api.uploads import CAMERA_FIELDS, CLOUD_FILES, form_cloud, read_form

router = APIRouter(tags=["align"])

COUNT_HEADER = "X-Points"
VIEWPOINT_HEADER = "X-Viewpoint"
SHAPE_HEADER = "X-Shape"
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
        "implies (a depth image: 0,0,0; an organized cloud: where its pixels' rays meet), "
        "`X-Shape` (height,width) an organized frame's grid; "
        "with `pixels=true` and an `X-Shape`, the triples are followed by each point's pixel "
        "(row * width + col) as little-endian uint32"
    )
    | errors(401, 413, 415, 422, 503, 504),
    openapi_extra={"requestBody": BODY},
    dependencies=[ReadAccess],
)
async def points(
    request: Request,
    settings: SettingsDep,
    limiter: LimiterDep,
    pixels: Annotated[
        bool, Query(description="an organized frame's pixels follow the points")
    ] = False,
) -> Response:
    body_kind(request, MULTIPART)
    form = await read_form(request, CLOUD_FILES, CAMERA_FIELDS, "the cloud")
    cloud, viewpoint = await limiter.align(form_cloud, form, settings)
    headers = {COUNT_HEADER: str(len(cloud.points))}
    if viewpoint is not None:
        headers[VIEWPOINT_HEADER] = ",".join(f"{v:g}" for v in viewpoint)
    body = np.asarray(cloud.points, "<f4").tobytes()
    if cloud.shape is not None:
        headers[SHAPE_HEADER] = ",".join(str(n) for n in cloud.shape)
        if pixels:
            body += np.asarray(cloud.index, "<u4").tobytes()
    return Response(body, media_type=RAW, headers=headers)
