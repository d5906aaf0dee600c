"""Every registered part in a whole frame: the instances the one-part chain finds in its
segments, each with the points it explains, and one global check among them.

A segment is searched as ``Engine.align`` searches a cloud; an answer that explains enough
of it is an instance, its points (every point of the frame near its surface, the neighbouring
segments' too: a part cut in two by a jump in depth is one instance) are taken out, and what
is left of the segment is searched again, until nothing fits. Then the global check: each
claimed point goes to the instance whose surface is nearest it, and an instance left with
too little of what it claimed is dropped (it explained points another explains better).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.engine.answer import Alignment
from service.engine.entry import Entry
from service.engine.frame import Frame
from service.engine.verification import surface_distance


@dataclass
class Instance:
    """One found part: the answer of the chain for it, and the frame points it explains."""

    answer: Alignment
    entry: Entry
    claimed: np.ndarray  # (M,) indices into the searched frame's points
    distance: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))  # (M,)

    @property
    def centre(self) -> np.ndarray:
        return self.answer.rotation @ self.entry.frame.centroid + self.answer.translation


def near_surface(
    points: np.ndarray,
    entry: Entry,
    rotation: np.ndarray,
    translation: np.ndarray,
    tolerance: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Which of ``points`` lie within ``tolerance`` of the part's surface at the pose (within
    its bounding sphere), and their distances: (indices, distances)."""
    centre = rotation @ entry.frame.centroid + translation
    reach = entry.reference.scale * 1.05 + tolerance
    inside = np.flatnonzero(np.sum((points - centre) ** 2, axis=1) <= reach**2)
    if not len(inside):
        return inside, np.zeros(0)
    model = (points[inside] - translation) @ rotation
    distance, _ = surface_distance(entry.surface, model, "nearest")
    close = distance < tolerance
    return inside[close], distance[close]


def settle_claims(instances: list[Instance], count: int, keep_share: float) -> list[Instance]:
    """The global check: a point claimed by several instances goes to the one whose surface
    is nearest it; an instance left with less than ``keep_share`` of its claim is dropped,
    and its points go back to the others that claimed them."""
    while True:
        owner = np.full(count, -1)
        best = np.full(count, np.inf)
        for k, instance in enumerate(instances):
            nearer = instance.distance < best[instance.claimed]
            owner[instance.claimed[nearer]] = k
            best[instance.claimed[nearer]] = instance.distance[nearer]
        kept = [
            np.sum(owner[instance.claimed] == k) >= keep_share * len(instance.claimed)
            for k, instance in enumerate(instances)
        ]
        if all(kept):
            break
        worst = min(
            (k for k in range(len(instances)) if not kept[k]),
            key=lambda k: np.sum(owner[instances[k].claimed] == k) / len(instances[k].claimed),
        )
        instances = [i for k, i in enumerate(instances) if k != worst]
    for k, instance in enumerate(instances):
        mine = owner[instance.claimed] == k
        instance.claimed, instance.distance = instance.claimed[mine], instance.distance[mine]
    return instances


def frame_indices(frame: Frame, instances: list[Instance], tolerance_of) -> list[np.ndarray]:
    """Each instance's points at the frame's full resolution (indices into ``frame``), every
    point going to the instance whose surface is nearest it; ``tolerance_of(instance)``: how
    near its surface a point must lie."""
    owner = np.full(len(frame), -1)
    best = np.full(len(frame), np.inf)
    for k, instance in enumerate(instances):
        answer = instance.answer
        tolerance = tolerance_of(instance)
        close, distance = near_surface(
            frame.points, instance.entry, answer.rotation, answer.translation, tolerance
        )
        nearer = distance < best[close]
        owner[close[nearer]] = k
        best[close[nearer]] = distance[nearer]
    return [np.flatnonzero(owner == k) for k in range(len(instances))]
