"""One answer to one case, scored: what the evaluation keeps of every query.

A system's answer (the engine's ``Alignment`` or a baseline's dict) becomes an ``Answer``;
``case_record`` measures it against the case's truth (docs/evaluation-protocol.md's metrics) and
says whether it was the right thing to do: accept a right pose, refuse a cloud of no registered
part, or, for a millimetre cloud, answer the pose in its units or refuse naming the units.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from evaluation.cases import NO_MATCH, Case
from evaluation.metrics import (
    SUCCESS_ADD_S,
    add_s,
    alignment_error_normalized,
    alignment_floor,
    geodesic_deg,
)
from service.engine.alignment import to_model_frame

UNIT_WORDS = ("unit", "millimet", "metre", "meter", "1000", "1,000")  # a reason naming units
PARAMS_KEPT = (  # case parameters copied into its record
    "pose_index",
    "keep_share",
    "visible_share",
    "noise_share",
    "view",
    "kind",
    "group",
    "turn_deg",
    "distance_scales",
    "part_points",
    "table_points",
    "stray_points",
    "unit_factor",
)


@dataclass
class Truth:
    """What the metrics need of one object (registered or kept out of the gallery)."""

    points: np.ndarray  # the reference cloud, model frame
    scale: float
    diameter: float
    split: str
    model_points: np.ndarray | None = None  # a dense sample of the mesh for ADD-S (else points)
    _tree: cKDTree | None = field(default=None, repr=False)

    def add_s(self, rotation, translation, rotation_true, translation_true) -> float:
        """ADD-S of a pose of this object (``evaluation.metrics.add_s``) on ``model_points``."""
        points = self.points if self.model_points is None else self.model_points
        if self._tree is None:
            self._tree = cKDTree(np.asarray(points, np.float64))
        pose, truth = (rotation, translation), (rotation_true, translation_true)
        return add_s(points, *pose, *truth, self.diameter, self._tree)


@dataclass
class Answer:
    """What a system answered; ``verdict`` None when it found no pose at all."""

    label: str | None
    rotation: np.ndarray | None
    translation: np.ndarray | None
    verdict: str | None = "match"
    confidence: float | None = None
    reasons: list[str] = field(default_factory=list)
    points_set_aside: int = 0
    timings_ms: dict[str, float] = field(default_factory=dict)

    @classmethod
    def of_alignment(cls, alignment) -> Answer:
        """The engine's ``Alignment``, whose verdict fields may still be defaults."""
        return cls(
            alignment.label,
            alignment.rotation,
            alignment.translation,
            getattr(alignment, "verdict", "match"),
            getattr(alignment, "confidence", None),
            list(getattr(alignment, "reasons", [])),
            int(getattr(alignment, "points_set_aside", 0)),
            dict(alignment.timings_ms),
        )


NO_ANSWER = Answer(None, None, None, verdict=None)


def names_units(reasons: list[str]) -> bool:
    """Whether one of the reasons speaks of the cloud's units (e.g. millimetres, ×1000)."""
    return any(word in reason.lower() for reason in reasons for word in UNIT_WORDS)


def outcome_ok(case: Case, answer: Answer, success: bool) -> bool:
    """Whether the answer was the right thing to do: refuse (``no_match``) a case of no
    registered part; accept a right pose; for a millimetre cloud, either that or a refusal
    whose reasons name the units."""
    if case.params.get("expected") == NO_MATCH:
        return answer.verdict == "no_match"
    accepted_right = answer.verdict == "match" and success
    if case.params.get("right_refusal") == "units":
        return accepted_right or (answer.verdict == "no_match" and names_units(answer.reasons))
    return accepted_right


def case_record(
    case: Case,
    truths: dict[str, Truth],
    answer: Answer,
    latency_ms: float,
    viewpoint_given: bool = False,
) -> dict:
    """The metrics of one answer. ADD-S and the rotation error are measured on the true object;
    the alignment error (the service's own figure) on the reference the answer named, beside
    its floor: the true object's reference at the true pose. A millimetre case is measured in
    the references' units (cloud and translations over ``unit_factor``); a case of no object
    the metrics know (junk) has no floor, ADD-S or rotation error."""
    factor = float(case.params.get("unit_factor", 1.0))
    points, true_translation = case.points / factor, case.translation / factor
    truth = truths.get(case.object_name)
    expected = case.params.get("expected", case.object_name)
    label_ok = answer.label == case.object_name and expected != NO_MATCH
    record = {
        "object": case.object_name,
        "set": truth.split if truth else case.family,
        "family": case.family,
        "points": len(case.points),
        **{k: v for k, v in case.params.items() if k in PARAMS_KEPT},
        "expected": expected,
        "label": answer.label,
        "label_ok": label_ok,
        "latency_ms": latency_ms,
        "viewpoint_given": viewpoint_given,
        "verdict": answer.verdict,
        "accepted": answer.verdict == "match",
        "confidence": answer.confidence,
        "reasons": answer.reasons,
        "points_set_aside": answer.points_set_aside,
        "timings_ms": answer.timings_ms,
        "align_err_floor": None,
        "rot_err_deg": None,
        "add_s": None,
        "align_err": None,
    }
    if truth is not None:
        model_frame = to_model_frame(points, case.rotation, true_translation)
        record["align_err_floor"] = alignment_floor(model_frame, truth.points, truth.scale)
    if answer.label is not None and answer.rotation is not None:
        translation = np.asarray(answer.translation, np.float64) / factor
        if truth is not None:
            record["rot_err_deg"] = geodesic_deg(answer.rotation, case.rotation)
            record["add_s"] = truth.add_s(
                answer.rotation, translation, case.rotation, true_translation
            )
        named = truths.get(answer.label)
        if named is not None:
            record["align_err"] = alignment_error_normalized(
                points, named.points, answer.rotation, translation, named.scale
            )
        if case.family == "symmetric":
            record["rotation"] = np.asarray(answer.rotation, np.float64).tolist()
    success = label_ok and record["add_s"] is not None and record["add_s"] < SUCCESS_ADD_S
    record["success"] = bool(success)
    record["outcome_ok"] = outcome_ok(case, answer, success)
    return record
