"""Request and response bodies of the HTTP contract (docs/api.md), as pydantic models.

They are the OpenAPI document a client generator reads. The routes validate the small fields
with these models and the (possibly 200,000-long) point lists with ``service.api.validation``.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StringConstraints,
    field_validator,
    model_validator,
)

from service.engine.tuning import MAX_GROUP  # the largest group a symmetry may have

ReferenceName = Annotated[
    str,
    StringConstraints(pattern=r"^[A-Za-z0-9._-]{1,64}$"),
    Field(description="1 to 64 characters of A-Z a-z 0-9 . _ -", examples=["bracket-a"]),
]
Vector3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Row4 = Annotated[list[float], Field(min_length=4, max_length=4)]
Matrix3 = Annotated[list[Vector3], Field(min_length=3, max_length=3)]
Matrix4 = Annotated[list[Row4], Field(min_length=4, max_length=4)]
Units = Literal["m", "mm", "cm", "in"]
Points = Annotated[
    list[Vector3],
    Field(description="[x, y, z] triples in the sensor's units", examples=[[[0, 0, 0]]]),
]


# Requests
class AlignOptions(BaseModel):
    """What ``POST /align`` takes besides the points."""

    model_config = ConfigDict(extra="forbid")  # a misspelt field is a 422, not ignored

    candidates: list[ReferenceName] | None = Field(
        None, min_length=1, description="restrict the search to these references"
    )
    top_k: int | None = Field(
        None, ge=1, description="how many candidates to verify geometrically (default: server's)"
    )
    refine: bool = Field(True, description="refine the pose with ICP")
    viewpoint: Vector3 | None = Field(
        None,
        description="where the sensor was, [x, y, z] in the cloud's own coordinates "
        "([0, 0, 0] for a cloud in a depth camera's frame)",
    )
    min_confidence: float | None = Field(
        None, ge=0, le=1, description="below it the verdict is never 'match' (default: server's)"
    )

    @field_validator("viewpoint")
    @classmethod
    def _finite(cls, viewpoint: list[float] | None) -> list[float] | None:
        if viewpoint is not None and not all(math.isfinite(v) for v in viewpoint):
            raise ValueError("the viewpoint must be three finite numbers [x, y, z]")
        return viewpoint


class AlignRequest(AlignOptions):
    points: Points


class Box(BaseModel):
    """An axis-aligned box in the frame's coordinates."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    min: Vector3
    max: Vector3

    @field_validator("max")
    @classmethod
    def _not_empty(cls, high: list[float], info) -> list[float]:
        low = info.data.get("min")
        if low is not None and any(h < lo for lo, h in zip(low, high, strict=True)):
            raise ValueError("every coordinate of max must be at least that of min")
        return high


class DetectOptions(BaseModel):
    """What ``POST /detect`` takes besides the frame."""

    model_config = ConfigDict(extra="forbid")

    candidates: list[ReferenceName] | None = Field(
        None, min_length=1, description="look only for these references"
    )
    min_confidence: float | None = Field(
        None, ge=0, le=1, description="below it the verdict is never 'match' (default: server's)"
    )
    viewpoint: Vector3 | None = Field(
        None,
        description="where the camera was, [x, y, z] in the frame's coordinates (default "
        "[0, 0, 0]: a frame in its camera's coordinates)",
    )
    max_instances: int = Field(20, ge=1, le=200, description="detections answered, at most")
    roi: Box | None = Field(None, description="only the points inside this box are searched")

    _finite = field_validator("viewpoint")(AlignOptions._finite.__func__)


class DetectRequest(DetectOptions):
    points: Points


class DepthCamera(BaseModel):
    """The camera of a depth image sent as a file: pinhole intrinsics, in pixels, and the unit."""

    model_config = ConfigDict(allow_inf_nan=False)

    fx: float = Field(gt=0, description="horizontal focal length (x), in pixels")
    fy: float = Field(gt=0, description="vertical focal length (y), in pixels")
    cx: float = Field(description="principal point's column (x); the top-left pixel is 0")
    cy: float = Field(description="principal point's row (y); the top-left pixel is 0")
    depth_scale: float | None = Field(
        None,
        gt=0,
        description="scene units per depth value; default 0.001 for a 16-bit image "
        "(millimetres to metres) and 1 for a float one (metres)",
    )


class ReferenceIdentity(BaseModel):
    """What ``POST /references`` takes besides the points."""

    model_config = ConfigDict(extra="forbid")

    name: ReferenceName


class UnitsChoice(BaseModel):
    """A registration's ``units`` (a query parameter, or a JSON or form field)."""

    units: Units | None = None


class DeclaredSymmetry(BaseModel):
    """A symmetry the operator declares at registration, in the frame of the points sent:
    round about ``axis`` (``revolution``, ``flip``: a half turn about a perpendicular fits
    too), or ``discrete``: ``order`` turns about ``axis``, or ``rotations``. Each turn must
    nearly fit the part; it joins what registration finds (docs/api-additions.md)."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["revolution", "discrete"]
    axis: Vector3 | None = Field(None, description="the axis, in the points' own frame")
    order: int | None = Field(None, ge=2, le=MAX_GROUP, description="discrete: 360/order turns")
    flip: bool = Field(False, description="revolution: a half turn about a perpendicular fits")
    rotations: list[Matrix3] | None = Field(
        None,
        min_length=1,
        max_length=MAX_GROUP,
        description="discrete: 3 x 3 rotations, as a description lists",
    )

    @model_validator(mode="after")
    def _complete(self) -> DeclaredSymmetry:
        if self.axis is not None:
            norm = math.sqrt(sum(v * v for v in self.axis))
            if not math.isfinite(norm) or norm < 1e-9:
                raise ValueError("the axis must be a finite, non-zero vector")
        if self.kind == "revolution":
            if self.axis is None or self.order is not None or self.rotations is not None:
                raise ValueError("a revolution takes an 'axis' (and 'flip'), nothing else")
        elif self.flip:
            raise ValueError("'flip' is a revolution's: declare a discrete one's 'rotations'")
        else:
            given = (self.axis is not None, self.order is not None, self.rotations is not None)
            if given not in ((True, True, False), (False, False, True)):
                raise ValueError("a discrete symmetry takes 'axis' and 'order', or 'rotations'")
        for k, rotation in enumerate(self.rotations or []):
            if not _is_rotation(rotation):
                raise ValueError(f"rotations[{k}] is no rotation (orthonormal, determinant 1)")
        return self

    def declared(self) -> dict:
        """The declaration as the engine takes it (and the description keeps it)."""
        return self.model_dump(exclude_none=True, exclude_defaults=True)  # kind has no default


def _is_rotation(rows: list[list[float]]) -> bool:
    """Orthonormal with determinant 1, to 1e-3."""
    matrix = np.asarray(rows, np.float64)
    if not np.isfinite(matrix).all():
        return False
    orthonormal = np.allclose(matrix @ matrix.T, np.eye(3), rtol=0, atol=1e-3)
    return orthonormal and abs(np.linalg.det(matrix) - 1) < 1e-3


class SymmetryChoice(BaseModel):
    """A registration's ``symmetry`` (a JSON field, or a form field of JSON text)."""

    symmetry: DeclaredSymmetry | None = None


class ReferenceRequest(ReferenceIdentity):
    points: Points
    symmetry: DeclaredSymmetry | None = Field(
        None,
        description="a symmetry the operator declares, in the points' frame: e.g. "
        '{"kind": "discrete", "axis": [0, 0, 1], "order": 2}; each turn must nearly fit',
    )
    units: Units | None = Field(
        None,
        description="the unit the points are in: m, mm, cm or in; the reference is stored in "
        "metres (its points times the unit). Default: stored as sent",
    )


# Responses
class CandidateFit(BaseModel):
    label: str
    score: float = Field(description="the classifier's probability for this reference")
    alignment_error: float = Field(description="mean observed-to-reference distance, scene units")
    alignment_error_normalized: float = Field(description="alignment_error / the scale")
    hypothesis: str = Field(description="the hypothesis source whose pose fitted best")


class AlternativePose(BaseModel):
    rotation: Matrix3
    translation: Vector3
    confidence: float
    label: str | None = Field(
        None,
        description="another registered part that fits alike (a look-alike of the answer's): "
        "its pose; absent for another pose of the answer's own part",
    )


class AlignResponse(BaseModel):
    label: str = Field(description="the recognised reference")
    score: float
    rotation: Matrix3 = Field(description="R of scene_point = R @ model_point + t")
    translation: Vector3 = Field(description="t of scene_point = R @ model_point + t")
    transform: Matrix4 = Field(description="[[R, t], [0, 0, 0, 1]]")
    alignment_error: float = Field(description="mean observed-to-reference distance, scene units")
    alignment_error_normalized: float = Field(description="alignment_error / the scale")
    hypothesis: str = Field(description="which hypothesis source won")
    candidates: list[CandidateFit]
    timings_ms: dict[str, float] = Field(description="per stage, and 'total'")
    verdict: Literal["match", "uncertain", "no_match"] = Field(
        description="only 'match' is safe to act on; otherwise label and pose are a best guess"
    )
    confidence: float | None = Field(
        None, description="estimated probability that label and pose (ADD-S < 0.1) are right"
    )
    reasons: list[str] = Field(description="why the verdict is not 'match', and what to change")
    ambiguous: bool = Field(description="other poses, not related by symmetry, fit alike")
    alternatives: list[AlternativePose]
    points_set_aside: int = Field(
        0, description="observed points left out as a support plane, stray points or clutter"
    )


class DetectionOut(BaseModel):
    """One instance of a registered part in the frame."""

    label: str
    verdict: Literal["match", "uncertain", "no_match"] = Field(
        description="only 'match' is safe to act on"
    )
    confidence: float | None = Field(
        None, description="estimated probability that label and pose (ADD-S < 0.1) are right"
    )
    rotation: Matrix3 = Field(description="R of scene_point = R @ model_point + t")
    translation: Vector3 = Field(description="t of scene_point = R @ model_point + t")
    transform: Matrix4 = Field(description="[[R, t], [0, 0, 0, 1]]")
    alignment_error: float = Field(description="mean distance of its points to the reference")
    alignment_error_normalized: float = Field(description="alignment_error / the scale")
    reasons: list[str] = Field(description="why the verdict is not 'match', and what to change")
    ambiguous: bool = Field(description="other poses, not related by symmetry, fit alike")
    alternatives: list[AlternativePose]
    symmetry: dict = Field(description="the part's symmetry, as GET /references/{name} gives it")
    num_points: int = Field(description="how many of the frame's points it explains")
    indices: list[int] = Field(
        description="the points it explains: indices into the request's points (for an "
        "organized frame, the pixel index row * width + col)"
    )


class DetectResponse(BaseModel):
    detections: list[DetectionOut] = Field(description="best first, by confidence")
    num_points: int = Field(description="the frame's valid points (inside the roi, if given)")
    unexplained: int = Field(
        description="of those, neither on a support (table, bin) nor explained by a detection"
    )
    supports: list[Row4] = Field(
        description="planes [nx, ny, nz, d] (n . x = d) set aside as supports, the first the "
        "one the parts rest on"
    )
    timings_ms: dict[str, float] = Field(description="per stage, and 'total'")
    complete: bool = Field(
        True, description="every region of the frame was searched within the time budget"
    )
    reasons: list[str] = Field(
        default_factory=list,
        description="why the search is incomplete, or why no registered part could be found "
        "in the frame (its unit), and what to change",
    )


class SelfCheck(BaseModel):
    """One render of the registration check: an independent resample of the new part (a full
    cloud, or one camera's view of it) in a random pose, aligned against the whole gallery."""

    model_config = ConfigDict(extra="allow")

    render: Literal["full", "view"]
    label: str = Field(description="what the gallery answered")
    label_ok: bool
    rotation_error_deg: float = Field(description="from the true rotation, symmetry accounted")
    alignment_error_normalized: float
    verdict: str
    confidence: float | None
    runner_up: str | None = Field(None, description="the other part that fitted best")
    runner_up_fit: float | None = Field(
        None, description="its fit x coverage over the answer's (1: as well; 0.9 and up: alike)"
    )


class ReferenceInfo(BaseModel):
    name: str
    num_points: int
    scale: float = Field(description="radius: the largest distance from the centroid to a point")
    points_sha256: str = Field(
        description="sha256 of the stored points as little-endian float32 x y z triples"
    )
    symmetry: dict = Field(
        description='the rotations that leave the part as it is: {"kind": "none"}, '
        '{"kind": "revolution", "axis": [x, y, z], "flip": bool, "centre": [x, y, z]} or '
        '{"kind": "discrete", "rotations": [3x3, ...], "centre": [x, y, z]}; /align answers '
        "the equivalent pose whose rotation is nearest the identity"
    )
    look_alikes: list[str] = Field(
        default_factory=list,
        description="registered parts no view tells this one from: the same points "
        "(points_sha256), or a registration check that answered its renders as them; /align "
        "answers ambiguous where one fits as well",
    )


class ReferenceResponse(ReferenceInfo):
    self_check: list[SelfCheck] | None = Field(
        None,
        description="registration only: independent renders of the new part (a full cloud "
        "and single views) aligned against the whole gallery",
    )
    warnings: list[str] = Field(
        default_factory=list,
        description="what the check found that an operator should know: renders answered as "
        "another part, poses off by more than 5 degrees, a symmetry, a size outside a camera's "
        "working range or far from every other part's (naming the likely unit)",
    )
    units: Units | None = Field(
        None, description="registration only: the unit the points were sent in, if given"
    )
    outcome: Literal["created", "replaced", "identical"] | None = Field(
        None,
        description="registration only: 'created' (201), 'replaced' (200, ?replace=true), or "
        "'identical' (200: that name already holds the same points, same points_sha256; "
        "nothing was computed or changed, so sending a registration again is safe)",
    )
    message: str | None = Field(None, description="'already registered, identical: ...'")


class ReferenceList(BaseModel):
    references: list[ReferenceInfo]


class ReferenceBatchResponse(BaseModel):
    references: list[ReferenceResponse] = Field(description="one a part, in the order sent")
    refits: int = Field(
        description="refits of the classifier the batch took: 1, or 0 if every "
        "part was already registered, identical"
    )


class RecentAlignment(BaseModel):
    """One of the last alignments the service answered (``GET /alignments``)."""

    id: int
    time: str = Field(description="when it was answered, ISO 8601 UTC")
    source: str = Field(description="'json', 'raw' or 'file <name>'")
    num_points: int
    viewpoint: Vector3 | None
    label: str
    verdict: str
    confidence: float | None
    alignment_error_normalized: float


class RecentAlignments(BaseModel):
    capacity: int = Field(
        description="how many the service keeps; 0: off (console.recent_alignments)"
    )
    alignments: list[RecentAlignment] = Field(description="newest first")


class RecentAlignmentDetail(RecentAlignment):
    answer: AlignResponse


class ModelIdentity(BaseModel):
    path: str
    sha256: str


class Health(BaseModel):
    status: Literal["ok", "loading", "failed"]
    auth: Literal["open", "keys", "keys-for-writes"] = Field(
        description="open: no API key is configured; keys: every operation but health needs "
        "one; keys-for-writes: only registering and deleting need one"
    )
    model: ModelIdentity
    providers: list[str] = Field(description="onnxruntime execution providers in use")
    loops: Literal["compiled", "numpy"] = Field(
        description="the engine's innermost loops: compiled by numba (the fast extra), or "
        "numpy's (POST /detect twice as slow; the same answers)"
    )
    references: int
    detail: str | None = Field(None, description="why the service is not ready")


class Error(BaseModel):
    detail: str
