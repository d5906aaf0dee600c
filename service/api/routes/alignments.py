"""``/alignments``: the last alignments the service answered, for the console to replay.

Kept in memory only while ``console.recent_alignments`` (``Settings.recent_alignments``) is
above 0: by default while the service is open, never once API keys are set unless asked for.
"""

from __future__ import annotations

from datetime import UTC, datetime

from fastapi import APIRouter, Response

from service.api.auth import ReadAccess
from service.api.dependencies import RecentDep
from service.api.recent import Recorded
from service.api.routes.common import errors, points_answer, points_response
from service.api.schemas import RecentAlignment, RecentAlignmentDetail, RecentAlignments

router = APIRouter(prefix="/alignments", tags=["align"])


class UnknownAlignment(LookupError):
    """An alignment the ring does not hold (never, or no longer): 404."""


@router.get(
    "",
    response_model=RecentAlignments,
    summary="The last alignments answered, newest first (empty while kept off)",
    responses=errors(401),
    dependencies=[ReadAccess],
)
async def recent(ring: RecentDep) -> RecentAlignments:
    return RecentAlignments(
        capacity=ring.capacity, alignments=[summary(entry) for entry in ring.newest_first()]
    )


@router.get(
    "/{alignment_id}",
    response_model=RecentAlignmentDetail,
    summary="One of the last alignments: its answer",
    responses=errors(401, 404),
    dependencies=[ReadAccess],
)
async def recorded(alignment_id: int, ring: RecentDep) -> RecentAlignmentDetail:
    entry = _kept(ring.get(alignment_id), alignment_id, ring.capacity)
    return RecentAlignmentDetail(**summary(entry).model_dump(), answer=entry.answer)


@router.get(
    "/{alignment_id}/points",
    response_class=Response,
    summary="One of the last alignments: the points as aligned, raw float32",
    responses=points_answer("triples") | errors(401, 404),
    dependencies=[ReadAccess],
)
async def recorded_points(alignment_id: int, ring: RecentDep) -> Response:
    entry = _kept(ring.get(alignment_id), alignment_id, ring.capacity)
    return points_response(entry.points)


def summary(entry: Recorded) -> RecentAlignment:
    answer = entry.answer
    return RecentAlignment(
        id=entry.id,
        time=datetime.fromtimestamp(entry.time, UTC).isoformat(timespec="seconds"),
        source=entry.source,
        num_points=len(entry.points),
        viewpoint=entry.viewpoint,
        label=answer.label,
        verdict=answer.verdict,
        confidence=answer.confidence,
        alignment_error_normalized=answer.alignment_error_normalized,
    )


def _kept(entry: Recorded | None, alignment_id: int, capacity: int) -> Recorded:
    if entry is None:
        why = (
            "the service keeps no alignments (DPC_CONSOLE__RECENT_ALIGNMENTS is 0)"
            if capacity == 0
            else f"it keeps only the last {capacity}"
        )
        raise UnknownAlignment(f"no alignment {alignment_id}: {why}")
    return entry
