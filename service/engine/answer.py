"""What ``Engine.align`` answers: the label and pose, how far to trust them, and the
candidates and alternatives behind them."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class CandidateFit:
    label: str
    score: float
    alignment_error: float
    alignment_error_normalized: float
    hypothesis: str


@dataclass
class AlternativePose:
    """A pose that fits the observation about as well as the answer, not related to it by the
    reference's symmetry (e.g. a flat part seen edge-on)."""

    rotation: np.ndarray
    translation: np.ndarray
    confidence: float
    label: str | None = None  # another part's pose: a look-alike's (None: the answer's part)


@dataclass
class Alignment:
    label: str
    score: float
    rotation: np.ndarray  # (3, 3): scene = R @ model + t
    translation: np.ndarray  # (3,)
    alignment_error: float
    alignment_error_normalized: float
    hypothesis: str  # the source of the winning hypothesis
    candidates: list[CandidateFit]
    timings_ms: dict[str, float] = field(default_factory=dict)
    # whether to act on it: only "match" is safe; "uncertain" and "no_match" say why in reasons
    verdict: str = "match"
    confidence: float | None = None  # calibrated probability that label and pose are right
    reasons: list[str] = field(default_factory=list)
    ambiguous: bool = False
    alternatives: list[AlternativePose] = field(default_factory=list)
    points_set_aside: int = 0  # observed points left out as support plane, strays, clutter
    in_bin: bool = False  # the answer is of a bin's reading: its floor and walls set aside
    fit: float = 0.0  # share of observed points near the reference's surface at the pose
    coverage: float = 0.0  # share of what the camera should see of it that was observed
    runner_up: float = 0.0  # the best fit x coverage of any other part
    runner_up_label: str | None = None
    alike: float = 0.0  # the best fit x coverage of another, non-equivalent pose of the part
    size_ratio: float = 1.0  # the observed radius over the part's scale
    points: int = 0  # observed points the answer rests on
    look_alikes: list[str] = field(default_factory=list)  # parts that fit alike, no view tells
    closest: AlternativePose | None = None  # the other pose of the part that ``alike`` measures


@dataclass
class Detection:
    """One instance of a registered part in a frame: the chain's answer for it, the points it
    explains (indices into the request's points: an organized frame's pixels) and the part's
    symmetry, as ``GET /references/{name}`` describes it."""

    answer: Alignment
    indices: np.ndarray  # (M,) int
    symmetry: dict
    evidence: dict[str, float] = field(default_factory=dict)  # what the frame says of it


@dataclass
class SceneAnswer:
    """What ``Engine.detect`` answers for a frame."""

    detections: list[Detection]  # best first: by confidence
    num_points: int  # the frame's valid points (inside the roi)
    unexplained: int  # of those, not set aside as a support nor explained by a detection
    supports: list[np.ndarray]  # (4,) planes n . x = d set aside, the first the parts rest on
    timings_ms: dict[str, float] = field(default_factory=dict)
    complete: bool = True  # every region was searched before the deadline
    reasons: list[str] = field(default_factory=list)  # why not, if not

    @classmethod
    def unsearched(cls, num_points: int, timings_ms: dict[str, float], reason: str) -> SceneAnswer:
        """A frame not searched, and why: none of its ``num_points`` set aside or explained."""
        return cls([], num_points, num_points, [], timings_ms, True, [reason])
