"""``/references``: register, list, describe and remove the objects the service recognises."""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import PurePath
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Query, Request, Response, status

from service.api.auth import AdminAccess, ReadAccess
from service.api.dependencies import CatalogDep, EngineDep, LimiterDep, SettingsDep
from service.api.limiter import Job
from service.api.parsers import Upload, in_metres, read_upload
from service.api.routes.common import (
    JSON,
    MULTIPART,
    body_kind,
    errors,
    invalid,
    json_object,
    known_fields,
    parse,
    points_answer,
    points_response,
    require,
)
from service.api.schemas import (
    ReferenceBatchResponse,
    ReferenceIdentity,
    ReferenceInfo,
    ReferenceList,
    ReferenceRequest,
    ReferenceResponse,
    SelfCheck,
    SymmetryChoice,
    Units,
    UnitsChoice,
)
from service.api.uploads import read_form, read_parts
from service.api.validation import validate_points
from service.engine.engine import Engine
from service.engine.look_alikes import confused, same_points, told_from
from service.engine.reference import Reference
from service.engine.symmetry import Symmetry
from service.engine.units import size_warnings
from service.errors import InvalidPoints, UnknownReference
from service.gallery.catalog import CREATED, IDENTICAL, Catalog, Part
from service.settings import Settings

router = APIRouter(prefix="/references", tags=["references"])

MAX_SELF_CHECK_POSES = 10

BODY = {
    "required": True,
    "content": {
        JSON: {"schema": {"$ref": "#/components/schemas/ReferenceRequest"}},
        MULTIPART: {"schema": {"$ref": "#/components/schemas/ReferenceUpload"}},
    },
}


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=ReferenceResponse,
    summary="Register an object (201), or replace one with ?replace=true (200)",
    responses={
        200: {
            "model": ReferenceResponse,
            "description": "replaced, or already registered with the same points (identical: "
            "nothing changed, so a registration is safe to send again)",
        }
    }
    | errors(401, 403, 409, 413, 415, 422, 503, 504, 507),
    openapi_extra={"requestBody": BODY},
    dependencies=[AdminAccess],
)
async def register(
    request: Request,
    response: Response,
    catalog: CatalogDep,
    settings: SettingsDep,
    limiter: LimiterDep,
    replace: Annotated[bool, Query(description="replace a reference of that name")] = False,
    self_check: Annotated[bool, Query(description="align the new reference with itself")] = True,
    units: Annotated[Units | None, Query(description=UNITS_DESCRIPTION)] = None,
) -> ReferenceResponse:
    """JSON ``{"name", "points"}``, or multipart ``name`` + ``file`` (STL, OBJ, PLY, PCD, NPY);
    ``units`` as a query parameter, a JSON field or a form field (the body's wins); a declared
    ``symmetry`` as a JSON field or a form field of JSON text."""
    if body_kind(request, JSON, MULTIPART) == MULTIPART:
        named = ("name", "units", "symmetry")
        form = await read_form(request, ("file",), named, "the mesh or cloud")
        fields = {k: v for k in named if (v := form.value(k)) is not None}
        source = form.files["file"]
    else:
        fields, source = json_object(await request.body()), None
    units = parse(UnitsChoice, {"units": fields.pop("units", units)}).units
    declared = symmetry_of(fields.pop("symmetry", None))
    poses = settings.gallery.self_check_poses if self_check else 0
    reference, outcome, checks = await limiter.write(
        _register, catalog, settings, fields, source, replace, poses, units, declared
    )
    response.status_code = status.HTTP_201_CREATED if outcome == CREATED else status.HTTP_200_OK
    return answer_of(catalog.engine, reference, outcome, checks, units)


IDENTICAL_MESSAGE = (
    "already registered, identical: the same points were stored before; nothing changed"
)
MAX_BATCH = 200  # parts in one POST /references/batch


def answer_of(
    engine: Engine,
    reference: Reference,
    outcome: str,
    checks: list[dict] | None,
    units: str | None = None,
) -> ReferenceResponse:
    """A registration's answer: the reference, its outcome and self-check, the warnings."""
    alike, named = look_alike_warnings(engine, reference, checks)
    return ReferenceResponse(
        **_info(reference, engine.look_alikes(reference.name)).model_dump(),
        self_check=None if checks is None else [SelfCheck.model_validate(c) for c in checks],
        warnings=alike
        + warnings(reference, checks, told=named)
        + _size_warnings(engine, reference, units),
        units=units,
        outcome=outcome,
        message=IDENTICAL_MESSAGE if outcome == IDENTICAL else None,
    )


UNITS_DESCRIPTION = (
    "the unit the points are in: m, mm, cm or in; the reference is stored in metres (its "
    "points times the unit). Default: stored as sent"
)


def symmetry_of(value: object) -> dict | None:
    """A registration's declared ``symmetry`` (``DeclaredSymmetry``; a form field's JSON text
    decoded), as the engine takes it; None when not given."""
    if isinstance(value, str):
        try:
            value = json.loads(value)
        except ValueError:
            message = "'symmetry' must be a JSON object, e.g. " + SYMMETRY_EXAMPLE
            raise invalid(message, "symmetry") from None
    declared = parse(SymmetryChoice, {"symmetry": value}).symmetry
    return None if declared is None else declared.declared()


SYMMETRY_EXAMPLE = '{"kind": "discrete", "axis": [0, 0, 1], "order": 2}'


def _size_warnings(engine: Engine, reference: Reference, units: str | None) -> list[str]:
    """A size outside a camera's range, or far from every other part's, naming the unit."""
    others = {n: engine.get(n) for n in engine.names() if n != reference.name}
    scales = {n: float(r.scale) for n, r in others.items() if r is not None}
    return size_warnings(reference.name, float(reference.scale), units, scales)


def _register(
    job: Job,
    catalog: Catalog,
    settings: Settings,
    fields: dict,
    source: tuple[bytes, str | None] | None,
    replace: bool,
    self_check_poses: int,
    units: str | None = None,
    declared: dict | None = None,
) -> tuple[Reference, str, list[dict] | None]:
    """Validate, read the points (stored in metres, from ``units``), compute and store the
    reference with its ``declared`` symmetry (in a worker thread)."""
    known_fields(fields, ReferenceRequest.model_fields)
    identity = parse(ReferenceIdentity, {k: v for k, v in fields.items() if k != "points"})
    upload = Upload(require(fields, "points")) if source is None else None
    part = _part(settings, identity.name, upload or source, units)
    return catalog.register(
        part.name,
        part.points,
        replace,
        self_check_poses,
        job.commit,
        mesh=part.mesh,
        face_index=part.face_index,
        symmetry=declared,
    )


def _part(
    settings: Settings, name: str, source: Upload | tuple[bytes, str | None], units: str | None
) -> Part:
    """A part's points read (a file, or an ``Upload`` of sent points), validated and in
    metres, with the mesh they were sampled on."""
    limits = settings.limits
    if not isinstance(source, Upload):
        source = read_upload(*source, settings.gallery.reference_points, limits.max_points)
    points = validate_points(source.points, limits.min_points, limits.max_points)
    points, mesh = in_metres(points, source.mesh, units)
    return Part(name, points, mesh, source.face_index)


@router.post(
    "/batch",
    response_model=ReferenceBatchResponse,
    summary="Register several parts at once, all or none, with one refit of the classifier",
    responses=errors(401, 403, 409, 413, 415, 422, 503, 504, 507),
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {MULTIPART: {"schema": {"$ref": "#/components/schemas/ReferenceBatch"}}},
        }
    },
    dependencies=[AdminAccess],
)
async def register_batch(
    request: Request,
    response: Response,
    catalog: CatalogDep,
    settings: SettingsDep,
    limiter: LimiterDep,
    replace: Annotated[bool, Query(description="replace references of those names")] = False,
    self_check: Annotated[bool, Query(description="align each new reference with itself")] = True,
    units: Annotated[Units | None, Query(description=UNITS_DESCRIPTION)] = None,
) -> ReferenceBatchResponse:
    """Multipart: one ``file`` field a part (STL, OBJ, PLY, PCD, NPY) and, optionally, a ``name``
    field for each, in the same order (else each part is named for its file, without the
    suffix). One transaction stores all of them, or none (a bad file, a name taken by other
    points); the same points under the same name again are ``identical``, as for one part."""
    body_kind(request, MULTIPART)
    files, given = await read_parts(request, MAX_BATCH)
    if given and len(given) != len(files):
        raise invalid(f"{len(given)} 'name' fields for {len(files)} files: send one a file", "name")
    names = given or [PurePath(filename or "").stem for _, filename in files]
    for name in names:
        parse(ReferenceIdentity, {"name": name})
    if len(set(names)) < len(names):
        twice = sorted({name for name in names if names.count(name) > 1})
        raise invalid(f"the batch names {', '.join(twice)} more than once", "name")
    poses = settings.gallery.self_check_poses if self_check else 0
    refits = catalog.engine.refits
    results = await limiter.write(
        _register_batch,
        catalog,
        settings,
        list(zip(names, files, strict=True)),
        replace,
        poses,
        units,
        budget_s=settings.limits.request_timeout_s * len(files),
    )
    created = any(outcome == CREATED for _, outcome, _ in results)
    response.status_code = status.HTTP_201_CREATED if created else status.HTTP_200_OK
    return ReferenceBatchResponse(
        references=[answer_of(catalog.engine, *result, units) for result in results],
        refits=catalog.engine.refits - refits,
    )


def _register_batch(
    job: Job,
    catalog: Catalog,
    settings: Settings,
    uploads: list[tuple[str, tuple[bytes, str | None]]],
    replace: bool,
    self_check_poses: int,
    units: str | None = None,
) -> list[tuple[Reference, str, list[dict] | None]]:
    parts = []
    for name, source in uploads:
        try:
            parts.append(_part(settings, name, source, units))
        except InvalidPoints as error:
            raise InvalidPoints(f"part '{name}' ({source[1]}): {error}") from None
    return catalog.register_many(parts, replace, self_check_poses, job.commit)


@router.get(
    "",
    response_model=ReferenceList,
    summary="List the references",
    responses=errors(401, 503),
    dependencies=[ReadAccess],
)
async def list_references(engine: EngineDep) -> ReferenceList:
    references = (engine.get(name) for name in sorted(engine.names()))
    return ReferenceList(
        references=[_info(r, engine.look_alikes(r.name)) for r in references if r is not None]
    )


@router.get(
    "/{name}",
    response_model=ReferenceInfo,
    summary="Describe a reference",
    responses=errors(401, 404, 503),
    dependencies=[ReadAccess],
)
async def describe(name: str, engine: EngineDep) -> ReferenceInfo:
    return _info(_known(engine, name), engine.look_alikes(name))


@router.get(
    "/{name}/points",
    response_class=Response,
    summary="The points a reference was registered with, as raw float32",
    responses=points_answer("triples in the model frame (their sha256 is points_sha256)")
    | errors(401, 404, 503),
    dependencies=[ReadAccess],
)
async def reference_points(name: str, engine: EngineDep) -> Response:
    return points_response(_known(engine, name).points)


@router.get(
    "/{name}/self_check",
    response_model=list[SelfCheck],
    summary="Align a reference against random poses of itself (as at registration)",
    responses=errors(401, 404, 503, 504),
    dependencies=[ReadAccess],
)
async def self_check(
    name: str,
    engine: EngineDep,
    settings: SettingsDep,
    limiter: LimiterDep,
    poses: Annotated[int | None, Query(ge=1, le=MAX_SELF_CHECK_POSES)] = None,
) -> list[SelfCheck]:
    reference = _known(engine, name)
    count = poses or settings.gallery.self_check_poses or 1
    checks = await limiter.align(engine.self_check, reference, count)
    return [SelfCheck.model_validate(check) for check in checks]


@router.delete(
    "/{name}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    summary="Remove a reference",
    responses=errors(401, 403, 404, 503, 504),
    dependencies=[AdminAccess],
)
async def remove(name: str, catalog: CatalogDep, limiter: LimiterDep) -> Response:
    await limiter.write(_remove, catalog, name)  # refits the classifier
    return Response(status_code=status.HTTP_204_NO_CONTENT)


def _remove(job: Job, catalog: Catalog, name: str) -> None:
    catalog.remove(name, job.commit)


def _known(engine: Engine, name: str) -> Reference:
    reference = engine.get(name)
    if reference is None:
        raise UnknownReference(f"no reference named '{name}'")
    return reference


def _info(reference: Reference, look_alikes: Iterable[str] = ()) -> ReferenceInfo:
    return ReferenceInfo(
        name=reference.name,
        num_points=len(reference.points),
        scale=float(reference.scale),
        points_sha256=reference.points_sha256,
        symmetry=reference.symmetry or {"kind": "none"},
        look_alikes=list(look_alikes),
    )


def look_alike_warnings(
    engine: Engine, reference: Reference, checks: list[dict] | None
) -> tuple[list[str], set[str]]:
    """What an operator should know of the registered parts the new one looks alike
    (``service.engine.look_alikes``): the same points, or a check that could not tell them
    apart; and which parts that names."""
    name = reference.name
    others = [r for n in engine.names() if n != name and (r := engine.get(n)) is not None]
    said, named = [], set()
    if same := same_points(reference, others):
        named.update(same)
        said.append(
            f"{name}'s points are identical to those of {' and '.join(same)} (the same "
            "points_sha256): no view tells them apart, so /align answers ambiguous among them "
            "(their poses in alternatives, never a match); delete the duplicate, or send "
            "candidates naming the part the cell expects"
        )
    for other in confused(name, checks):
        if other in named:
            continue
        named.add(other)
        renders = [c for c in checks or [] if told_from(name, c) == other]
        full = " (the full cloud among them)" if any(c["render"] == "full" for c in renders) else ""
        said.append(
            f"the registration check could not tell {name} from {other}: {len(renders)} of "
            f"{len(checks or [])} renders{full} were answered as {other}, or {other} fitted them "
            f"alike. /align answers ambiguous where {other} fits as well (never a match); send "
            "candidates naming the part the cell expects where you can"
        )
    for other in engine.look_alikes(name):  # e.g. the check's other direction
        if other in named:
            continue
        named.add(other)
        said.append(
            f"the registration check could not tell {name} and {other} apart: views of "
            f"{other} were answered as {name}. /align answers ambiguous where both fit alike "
            "(never a match); send candidates naming the part the cell expects where you can"
        )
    return said, named


def warnings(
    reference: Reference, checks: list[dict] | None, told: set[str] | None = None
) -> list[str]:
    """What the registration check found that an operator should know (of the parts in
    ``told``, said already, nothing more)."""
    said = []
    if checks:
        confused: dict[str, int] = {}
        for check in checks:
            if not check["label_ok"] and check["label"] not in (told or set()):
                confused[check["label"]] = confused.get(check["label"], 0) + 1
        for other, count in confused.items():
            said.append(
                f"{count} of {len(checks)} renders of {reference.name} were answered as {other}: "
                "the two look alike; restrict alignments with candidates where you can"
            )
        off = [c for c in checks if c["label_ok"] and c["rotation_error_deg"] > 5]
        if off:
            worst = max(c["rotation_error_deg"] for c in off)
            said.append(
                f"{len(off)} of {len(checks)} renders were posed more than 5 degrees off (up to "
                f"{worst:.0f}): poses of this part may be ambiguous from some sides"
            )
    symmetry = reference.symmetry or {}
    kind = symmetry.get("kind", "none")
    if kind != "none":
        said.append(
            f"{reference.name} has a {kind} symmetry: /align answers one canonical pose "
            "among the poses it makes equivalent"
        )
    near = np.asarray(symmetry.get("near", []), np.float64).reshape(-1, 3, 3)
    if len(near):
        cosines = np.clip((np.trace(near, axis1=1, axis2=2) - 1) / 2, -1, 1)
        turns = ", ".join(f"{a:.0f}" for a in sorted(set(np.round(np.degrees(np.arccos(cosines))))))
        offered = Symmetry.from_description(symmetry, np.zeros(3)).suggested()
        example = " or ".join(json.dumps(d) for d in offered[:2]) or SYMMETRY_EXAMPLE
        said.append(
            f"turns of {reference.name} by {turns} degrees nearly fit its own surface (only a "
            "detail tells them apart): /align tries them and names those that fit alike as "
            "alternatives; a view that does not show the detail may be answered as ambiguous. "
            "If a turn is a true symmetry of the part, or the detail does not matter to your "
            f"cell, register it again with 'symmetry': {example} (a cloud's estimated normals "
            "can hide a symmetry, and then one surface may be answered at poses that turn "
            "apart; a mesh shows it best)"
        )
    return said
