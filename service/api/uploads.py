"""Multipart bodies: the files and text fields of an upload, and the points its ``file`` gives.

``POST /references`` takes a ``name`` and a mesh or cloud ``file``. ``POST /align`` and
``POST /points`` take a cloud or mesh ``file``, or a depth image with its camera's ``fx``, ``fy``,
``cx``, ``cy`` (``depth_scale`` and a ``mask`` image optional: ``service.api.depth``). A field
the route does not know is refused (422), so a misspelt ``fx`` is never silently ignored.
"""

from __future__ import annotations

import sys
from collections import defaultdict
from contextlib import aclosing
from dataclasses import dataclass
from typing import Any

import numpy as np
from fastapi import Request
from starlette.datastructures import FormData, UploadFile
from starlette.exceptions import HTTPException
from starlette.formparsers import MultiPartException, MultiPartParser

from service.api import depth
from service.api.clouds import Cloud, camera_centre
from service.api.parsers import read_upload
from service.api.routes.common import MULTIPART, invalid, known_fields, parse
from service.api.schemas import DepthCamera
from service.api.validation import validate_points
from service.settings import Settings

CAMERA_FIELDS = tuple(DepthCamera.model_fields)  # fx fy cx cy depth_scale
CLOUD_FILES = ("file", "mask")
MAX_FIELDS = 64
FILE_DESCRIPTION = (
    "a cloud (.ply, .pcd, .npy of shape (N, 3)), a mesh (.stl, .obj, .ply), or a depth image "
    "(16-bit PNG in millimetres; 32-bit float TIFF or NPY (H, W) in metres) sent with fx, fy, "
    "cx and cy"
)
ORIGIN = [0.0, 0.0, 0.0]  # a depth image's cloud is in the camera's frame


class InMemoryParser(MultiPartParser):
    """Starlette's multipart parser with its files held in memory. Starlette spools a file
    over 1 MB to disk, writing each chunk through the thread pool, and the route then reads it
    whole: a 3.7 MB camera frame spent 8 ms there (docs/decisions.md#a-frames-body). The body
    limit (``limits.max_body_bytes``) bounds what is held."""

    spool_max_size = sys.maxsize


async def parse_form(request: Request, max_files: int, max_fields: int) -> FormData:
    """The multipart body's form (``InMemoryParser``); Starlette's own 400 for a malformed
    body, too many files or fields."""
    try:
        async with aclosing(request.stream()) as stream:
            parser = InMemoryParser(
                request.headers, stream, max_files=max_files, max_fields=max_fields
            )
            return await parser.parse()
    except MultiPartException as error:
        raise HTTPException(status_code=400, detail=error.message) from None


@dataclass(frozen=True)
class Form:
    files: dict[str, tuple[bytes, str | None]]  # field -> (content, file name)
    fields: dict[str, list[str]]  # field -> its values, in order

    def value(self, name: str) -> str | None:
        """A text field's last value."""
        values = self.fields.get(name)
        return values[-1] if values else None


async def read_form(
    request: Request, files: tuple[str, ...], fields: tuple[str, ...], what: str
) -> Form:
    """The multipart body's files and fields; 422 for a malformed body, an unknown field, a
    file where text belongs (or the reverse), or no ``file``. ``what`` names the file wanted."""
    found: dict[str, tuple[bytes, str | None]] = {}
    texts: dict[str, list[str]] = defaultdict(list)
    expected = ", ".join(f"'{name}'" for name in (*files, *fields))
    try:
        form = await parse_form(request, len(files), MAX_FIELDS)
    except HTTPException as error:  # Starlette's 400: a malformed body, too many files or fields
        raise invalid(f"the multipart body is unusable ({error.detail}): send {expected}") from None
    try:
        known_fields(form.keys(), (*fields, *files))
        for key, value in form.multi_items():
            if (key in files) != isinstance(value, UploadFile):
                kind = "a file" if key in files else "a text field"
                raise invalid(f"send '{key}' as {kind}", key)
            if isinstance(value, UploadFile):
                found[key] = (await value.read(), value.filename)
            else:
                texts[key].append(value)
    finally:
        await form.close()
    if "file" not in found:
        raise invalid(f"upload {what} as a file field", "file")
    return Form(found, dict(texts))


async def read_body(
    request: Request, kind: str, fields: tuple[str, ...], what: str
) -> bytes | Form:
    """A cloud's or frame's body: the multipart form (``read_form``: a ``file`` and ``mask``,
    and ``fields``), or the bytes of a JSON or raw body."""
    if kind == MULTIPART:
        return await read_form(request, CLOUD_FILES, fields, what)
    return await request.body()


async def read_parts(
    request: Request, max_files: int
) -> tuple[list[tuple[bytes, str | None]], list[str]]:
    """A batch's multipart body: its ``file`` fields (each a mesh or cloud), in order, and its
    ``name`` fields (none: each part is named for its file); 422 as ``read_form``."""
    files: list[tuple[bytes, str | None]] = []
    names: list[str] = []
    try:
        async with request.form(max_files=max_files, max_fields=max_files) as form:
            known_fields(form.keys(), ("file", "name"))
            for key, value in form.multi_items():
                if (key == "file") != isinstance(value, UploadFile):
                    raise invalid(f"send '{key}' as {'a file' if key == 'file' else 'text'}", key)
                if isinstance(value, UploadFile):
                    files.append((await value.read(), value.filename))
                else:
                    names.append(value)
    except HTTPException as error:
        raise invalid(
            f"the multipart body is unusable ({error.detail}): send up to {max_files} 'file' "
            "fields, and optionally as many 'name' fields"
        ) from None
    if not files:
        raise invalid("upload the parts' meshes or clouds as 'file' fields", "file")
    return files, names


def form_points(
    form: Form, settings: Settings, imply: bool = True
) -> tuple[np.ndarray, list[float] | None]:
    """The checked points of the form's ``file`` (float32), and the viewpoint the file
    implies (``form_cloud``)."""
    cloud, viewpoint = form_cloud(form, settings, imply)
    return cloud.points, viewpoint


def form_cloud(
    form: Form, settings: Settings, imply: bool = True, max_points: int | None = None
) -> tuple[Cloud, list[float] | None]:
    """The form's ``file`` as a checked cloud (float32 points, and an organized frame's
    pixels), and the viewpoint the file implies: the origin for a depth image, the camera's
    centre for an organized cloud whose pixels' rays pin it (``clouds.camera_centre``), else
    None. Without ``imply`` (the request gives the viewpoint) no camera centre is solved
    for: None. ``max_points``: the most valid points (the settings' limit unless given)."""
    data, filename = form.files["file"]
    camera = {name: form.value(name) for name in CAMERA_FIELDS if name in form.fields}
    mask = form.files.get("mask")
    limits = settings.limits
    most = limits.max_points if max_points is None else max_points
    if camera or mask or depth.is_image(data, filename):
        if not camera:
            raise invalid(
                "a depth image needs its camera's intrinsics: send fx, fy, cx and cy", "fx"
            )
        image = depth.read_depth(data, filename)
        keep = None if mask is None else depth.read_image(*mask, "mask")
        cloud = depth.depth_cloud(image, parse(DepthCamera, camera), keep, most)
        viewpoint = ORIGIN
    else:
        upload = read_upload(data, filename, settings.gallery.reference_points, most)
        cloud = Cloud(upload.points, upload.index, upload.shape)
        # an organized frame's camera, where its rays pin it (2-5 ms on a camera's frame)
        centre = camera_centre(cloud) if imply else None
        viewpoint = None if centre is None else [float(v) for v in centre]
    points = validate_points(cloud.points, limits.min_points, most)
    return Cloud(points, cloud.index, cloud.shape), viewpoint


def cloud_upload_schema(title: str, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The OpenAPI schema of a multipart body with a cloud, mesh or depth-image ``file``."""
    camera = DepthCamera.model_json_schema()["properties"]
    return {
        "title": title,
        "type": "object",
        "required": ["file"],
        "properties": {
            "file": {"type": "string", "format": "binary", "description": FILE_DESCRIPTION},
            "mask": {
                "type": "string",
                "format": "binary",
                "description": "depth images only: an image of the same size (PNG, TIFF, NPY); "
                "pixels where it is 0 are left out",
            },
            **{
                name: {**schema, "description": f"depth images: {schema.get('description')}"}
                for name, schema in camera.items()
            },
            **(extra or {}),
        },
    }
