"""The service's answers as Python values: numpy for matrices, dataclasses for the rest.

Each keeps the answer as the service sent it (``raw``), so fields added by a newer service
are never lost; ``from_answer`` reads only the contract's names (docs/api.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Candidate:
    label: str
    score: float
    alignment_error: float
    alignment_error_normalized: float | None = None
    hypothesis: str | None = None


@dataclass(frozen=True)
class Alternative:
    """A pose that fits the observation as well, not related to the answer by a symmetry."""

    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    confidence: float | None
    label: str | None = None  # a look-alike part's pose (None: another pose of the answer's part)


class Placed:
    """What a ``Pose`` and a ``Detection`` share: a verdict and a rigid pose."""

    verdict: str
    rotation: np.ndarray
    translation: np.ndarray

    @property
    def is_match(self) -> bool:
        return self.verdict == "match"

    def apply(self, model_points: np.ndarray) -> np.ndarray:
        """Model-frame points (N, 3) placed in the scene at this pose."""
        return np.asarray(model_points, dtype=np.float64) @ self.rotation.T + self.translation


def _placement(answer: dict[str, Any]) -> dict[str, Any]:
    """The fields of an answer's pose and its fit, as ``Pose`` and ``Detection`` hold them."""
    return {
        "label": answer["label"],
        "rotation": np.array(answer["rotation"], dtype=np.float64),
        "translation": np.array(answer["translation"], dtype=np.float64),
        "transform": np.array(answer["transform"], dtype=np.float64),
        "alignment_error": answer["alignment_error"],
        "alignment_error_normalized": answer["alignment_error_normalized"],
        "confidence": answer.get("confidence"),
        "reasons": list(answer.get("reasons", [])),
        "ambiguous": bool(answer.get("ambiguous", False)),
        "alternatives": _alternatives(answer),
    }


@dataclass(frozen=True)
class Pose(Placed):
    """Which part the service recognised and where it is: ``scene = rotation @ model + t``.

    Only ``verdict == "match"`` is safe to act on; otherwise ``reasons`` says why.
    """

    label: str
    score: float
    rotation: np.ndarray  # (3, 3) float64
    translation: np.ndarray  # (3,) float64
    transform: np.ndarray  # (4, 4): [[R, t], [0, 0, 0, 1]]
    alignment_error: float  # mean observed-to-reference distance, scene units
    alignment_error_normalized: float  # divided by the reference's scale
    verdict: str  # "match" | "uncertain" | "no_match"
    confidence: float | None
    reasons: list[str]
    ambiguous: bool
    alternatives: list[Alternative]
    points_set_aside: int
    hypothesis: str | None
    candidates: list[Candidate]
    timings_ms: dict[str, float]
    raw: dict[str, Any] = field(repr=False)

    @classmethod
    def from_answer(cls, answer: dict[str, Any]) -> Pose:
        return cls(
            **_placement(answer),
            score=answer["score"],
            verdict=answer.get("verdict", "match"),
            points_set_aside=answer.get("points_set_aside", 0),
            hypothesis=answer.get("hypothesis"),
            candidates=[
                Candidate(
                    c["label"],
                    c["score"],
                    c["alignment_error"],
                    c.get("alignment_error_normalized"),
                    c.get("hypothesis"),
                )
                for c in answer.get("candidates", [])
            ],
            timings_ms=dict(answer.get("timings_ms", {})),
            raw=answer,
        )


@dataclass(frozen=True)
class Detection(Placed):
    """One instance of a registered part in a frame (``POST /detect``), at its pose:
    ``scene = rotation @ model + translation``. Only ``verdict == "match"`` is safe to act on.
    ``indices``: the frame's points it explains (pixels, ``row * width + col``, for an
    organized frame)."""

    label: str
    verdict: str  # "match" | "uncertain" | "no_match"
    confidence: float | None
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    transform: np.ndarray  # (4, 4)
    alignment_error: float
    alignment_error_normalized: float
    reasons: list[str]
    ambiguous: bool
    alternatives: list[Alternative]
    symmetry: dict[str, Any] | None
    indices: np.ndarray  # (K,) int64
    raw: dict[str, Any] = field(repr=False)

    @classmethod
    def from_answer(cls, answer: dict[str, Any]) -> Detection:
        return cls(
            **_placement(answer),
            verdict=answer["verdict"],
            symmetry=answer.get("symmetry"),
            indices=np.asarray(answer.get("indices", []), dtype=np.int64),
            raw=answer,
        )


@dataclass(frozen=True)
class Scene:
    """``POST /detect``'s answer: every detection in the frame, and what was left."""

    detections: list[Detection]
    num_points: int  # the frame's valid points
    unexplained: int  # of them, claimed by no detection nor support
    complete: bool  # False: the search stopped at its deadline (``reasons`` says so)
    reasons: list[str]
    timings_ms: dict[str, float]
    raw: dict[str, Any] = field(repr=False)

    @property
    def matches(self) -> list[Detection]:
        """The detections safe to act on."""
        return [d for d in self.detections if d.is_match]

    @classmethod
    def from_answer(cls, answer: dict[str, Any]) -> Scene:
        return cls(
            detections=[Detection.from_answer(d) for d in answer.get("detections", [])],
            num_points=answer.get("num_points", 0),
            unexplained=answer.get("unexplained", 0),
            complete=bool(answer.get("complete", True)),
            reasons=list(answer.get("reasons", [])),
            timings_ms=dict(answer.get("timings_ms", {})),
            raw=answer,
        )


def _alternatives(answer: dict[str, Any]) -> list[Alternative]:
    return [
        Alternative(
            np.array(a["rotation"], dtype=np.float64),
            np.array(a["translation"], dtype=np.float64),
            a.get("confidence"),
            a.get("label"),
        )
        for a in answer.get("alternatives", [])
    ]


@dataclass(frozen=True)
class Reference:
    """A registered part: its name, size (``scale``, the radius) and points' checksum."""

    name: str
    num_points: int
    scale: float
    points_sha256: str | None
    symmetry: dict[str, Any] | None  # {"kind": "none" | "revolution" | "discrete", ...}
    self_check: list[dict[str, Any]] | None  # registration only: renders of it aligned
    warnings: list[str]  # registration only: what the check found that a person should know
    raw: dict[str, Any] = field(repr=False)

    @classmethod
    def from_answer(cls, answer: dict[str, Any]) -> Reference:
        return cls(
            name=answer["name"],
            num_points=answer["num_points"],
            scale=answer["scale"],
            points_sha256=answer.get("points_sha256"),
            symmetry=answer.get("symmetry"),
            self_check=answer.get("self_check"),
            warnings=list(answer.get("warnings", [])),
            raw=answer,
        )
