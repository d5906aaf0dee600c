"""A registered reference with what queries need of it (its surface, views, symmetry, frame),
built once at registration or load, and the gallery's immutable snapshot of them."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from service.engine.classifier import LinearClassifier, classifier_input
from service.engine.distance_field import DistanceField
from service.engine.icp import Surface
from service.engine.principal_axes import Frame, flatness
from service.engine.reference import Reference
from service.engine.symmetry import Symmetry
from service.engine.tuning import EXPECTED
from service.engine.verification import surface_distance
from service.engine.views import Views

if TYPE_CHECKING:
    from service.engine.search import Fit


@dataclass(frozen=True)
class Entry:
    """A reference with what queries need of it, built once at registration or load."""

    reference: Reference
    point_tree: cKDTree
    mapped_tree: cKDTree
    view_features: np.ndarray  # eq. (4)'s input for each augmented full view
    surface: Surface
    views: Views
    symmetry: Symmetry
    # EXPECTED indices of the points each view sees (row K: of all points), drawn once, for
    # coverage; repeated where a view sees fewer
    expected: np.ndarray
    flatness: float  # principal_axes.flatness of its points (a flat part: under FLAT)
    frame: Frame  # its points' centroid and principal axes

    @classmethod
    def of(cls, reference: Reference, blur: float) -> Entry:
        points = np.asarray(reference.points, dtype=np.float64)
        tree = cKDTree(points)
        visible = reference.visible()
        rng = np.random.default_rng(0)
        expected = np.empty((len(visible) + 1, EXPECTED), dtype=np.uint16)
        for k, seen in enumerate([*visible, np.ones(len(points), bool)]):
            pool = np.flatnonzero(seen) if seen.any() else np.arange(len(points))
            drawn = rng.permutation(len(pool))[:EXPECTED]
            expected[k] = pool[np.resize(drawn, EXPECTED)]  # repeated where it sees fewer
        frame = Frame.of(points)
        return cls(
            reference,
            tree,
            cKDTree(reference.mapped),
            classifier_input(reference.view_grids, blur),
            stored_surface(reference, tree),
            Views.of(points, visible),
            Symmetry.from_description(reference.symmetry, frame.centroid),
            expected,
            flatness(points),
            frame,
        )

    def gap(self, pose: Fit, other: Fit) -> float:
        """How far apart the part lies at two poses, over its scale: the mean distance from
        its points placed at ``other`` to its surface placed at ``pose`` (ADD-S, measured on
        the surface rather than between samples), on the points coverage draws for the
        whole part."""
        turn = pose.rotation.T @ other.rotation  # ``other`` in ``pose``'s model frame
        shift = (other.translation - pose.translation) @ pose.rotation
        distance, _ = surface_distance(
            self.surface, self.surface.points[self.expected[-1]] @ turn.T + shift, "nearest"
        )
        return float(distance.mean()) / self.reference.scale


def stored_surface(reference: Reference, tree: cKDTree | None = None) -> Surface:
    """The surface a complete reference stores: its points, normals and distance field
    (``tree``: a ``cKDTree`` of its points, if one is at hand)."""
    points = np.asarray(reference.points, dtype=np.float64)
    frame = reference.field_frame
    distance_field = DistanceField(frame[:3], float(frame[3]), reference.field)
    normals = np.asarray(reference.normals, np.float64)
    return Surface.of(points, normals, distance_field, tree or cKDTree(points))


@dataclass(frozen=True)
class Snapshot:
    entries: dict[str, Entry]
    classifier: LinearClassifier | None
    scales: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per classifier row
    gram: np.ndarray | None = None  # view_gram of every entry's view features, kept by sums
    # every rendered view of every reference, for nearest-view proposals
    view_keys: np.ndarray = field(default_factory=lambda: np.zeros((0, 256), np.float32))
    view_owner: np.ndarray = field(default_factory=lambda: np.zeros(0, np.intp))  # its row
    view_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.intp))
    view_radii: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # each reference's look-alikes (``service.engine.look_alikes.relation``), where it has any
    look_alikes: dict[str, tuple[str, ...]] = field(default_factory=dict)

    @cached_property
    def view_starts(self) -> np.ndarray:
        """Where each row's block of views begins in ``view_keys`` (the rows are in blocks)."""
        return np.flatnonzero(np.diff(self.view_owner, prepend=-1))
