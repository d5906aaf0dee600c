"""A part's rotational symmetries, found at registration by aligning it with itself.

A bottle turned about its own axis, or a box turned by 180 degrees, shows the same surface:
every such pose is right, and a robot must get one and the same answer for the same physical
situation. Registration finds the rotations S (about the centroid c, in the model frame) that
carry the reference onto itself:
- ``revolution``: a principal axis whose two other variances are alike, about which turns by
  several unrelated angles all fit; ``flip`` says whether a half turn about a perpendicular
  axis fits as well (a cylinder, not a cone);
- ``discrete``: the rotations that fit after refining, by point-to-plane ICP of the reference
  onto itself, every signed permutation of its principal axes, turns by 360/n degrees about
  them (n = 2 to 8) and a few random rotations (a box: 4, a cube: 24, a hexagonal nut: 12);
- ``none``: only the identity fits.
"Fits" means that at least ``SHARE`` of the moved points lie within ``TOLERANCE`` of the
reference's surface (or half a sample spacing, for a sparse one).

Among poses the symmetry makes equivalent (``R S`` with the translation that keeps the scene
in place), ``canonical`` answers the one whose rotation is nearest the identity (the largest
trace), so the same surface in the same place always gives the same matrix.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import permutations, product

import numpy as np
from scipy.spatial.transform import Rotation

from service.engine.icp import Surface, icp, rotation_vector
from service.engine.principal_axes import principal_axes
from service.engine.verification import surface_distance

TOLERANCE = 0.015  # share of the scale
SPACINGS = 0.5  # or this many sample spacings, if more
SHARE = 0.95  # of the moved points within the tolerance
REVOLUTION_ANGLES_DEG = (37.0, 101.0, 163.0, 229.0, 293.0)
ROUND_AXES = 0.1  # the other two spreads (standard deviations) differ by at most this share
MAX_FOLD = 8
RANDOM_STARTS = 12
SAME_DEG = 5.0  # two found rotations this close are one
QUICK, QUICK_POINTS = 8, 128  # the first refinement of a start: iterations, points
MAX_GROUP = 60  # the largest discrete group looked for (an icosahedron's)
DRIFT = 0.1  # share of the scale a refined symmetry may move the sample's centroid (its own error)


@dataclass(frozen=True)
class Symmetry:
    kind: str  # "none" | "revolution" | "discrete"
    centroid: np.ndarray  # (3,) the rotations' fixed point, model frame
    rotations: np.ndarray  # (G, 3, 3), identity first: every discrete symmetry (or a flip)
    axis: np.ndarray | None = None  # revolution: unit axis through the centroid

    @classmethod
    def none(cls, centroid: np.ndarray) -> Symmetry:
        return cls("none", np.asarray(centroid, np.float64), np.eye(3)[None])

    def describe(self) -> dict:
        """The JSON description a reference shows (and the store keeps)."""
        described: dict = {"kind": self.kind}
        if self.kind == "revolution":
            described["axis"] = np.round(self.axis, 6).tolist()
            described["flip"] = len(self.rotations) > 1
        elif self.kind == "discrete":
            described["rotations"] = np.round(self.rotations, 6).tolist()
        described["centre"] = np.round(self.centroid, 9).tolist()
        return described

    @classmethod
    def from_description(cls, described: dict, centroid: np.ndarray) -> Symmetry:
        centre = np.asarray(described.get("centre", centroid), np.float64)
        if described.get("kind") == "revolution":
            axis = np.asarray(described["axis"], np.float64)
            rotations = [np.eye(3)]
            if described.get("flip"):
                rotations.append(rotation_vector(np.pi * _perpendicular(axis)))
            return cls("revolution", centre, np.stack(rotations), axis / np.linalg.norm(axis))
        if described.get("kind") == "discrete":
            return cls("discrete", centre, np.asarray(described["rotations"], np.float64))
        return cls.none(centre)

    def equivalent(self, rotation: np.ndarray) -> np.ndarray:
        """(G, 3, 3) rotations equivalent to ``rotation`` under the discrete part."""
        return np.einsum("ij,gjk->gik", rotation, self.rotations)

    def canonical(
        self, rotation: np.ndarray, translation: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The equivalent pose whose rotation is nearest the identity."""
        if self.kind == "none":
            return rotation, translation
        choices = self.equivalent(rotation)
        if self.kind == "revolution":  # turn each about the axis to its best angle
            choices = np.stack([c @ _best_turn(c, self.axis) for c in choices])
        best = choices[int(np.argmax(np.trace(choices, axis1=1, axis2=2)))]
        # scene = R m + t = R' m' + t' with m' = S^T (m - c) + c, S = R^T R'
        return best, translation + (rotation - best) @ self.centroid

    def distance_deg(self, first: np.ndarray, second: np.ndarray) -> float:
        """The angle between two rotations once symmetry is accounted for, in degrees."""
        a, _ = self.canonical(first, np.zeros(3))
        b, _ = self.canonical(second, np.zeros(3))
        return float(np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1))))


def _perpendicular(axis: np.ndarray) -> np.ndarray:
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    other = np.cross(axis, helper)
    return other / np.linalg.norm(other)


def _best_turn(rotation: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """The turn T about ``axis`` maximising trace(R T): R T is then nearest the identity.

    trace(R T(theta)) = A cos(theta) + B sin(theta) + C with A = trace(R) - a.R.a,
    B = trace(R [a]x) and C = a.R.a, so theta = atan2(B, A).
    """
    a = axis
    cross = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    along = a @ rotation @ a
    theta = np.arctan2(np.trace(rotation @ cross), np.trace(rotation) - along)
    return rotation_vector(a * theta)


def _fits(surface: Surface, points: np.ndarray, rotation, translation, scale) -> bool:
    """Whether the reference moved by (R, t) lies on itself: within the tolerance, or within
    half a sample spacing where the samples are sparser (their normals are rougher)."""
    distance, _ = surface_distance(surface, points @ rotation.T + translation)
    return bool((distance < _tolerance(surface, scale)).mean() >= SHARE)


def _tolerance(surface: Surface, scale: float) -> float:
    return max(TOLERANCE * scale, SPACINGS * surface.spacing)


def _about(rotation: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The translation of ``rotation`` about ``centre``: t = c - R c."""
    return centre - rotation @ centre


def _fixed_point(transforms: list[tuple[np.ndarray, np.ndarray]], near: np.ndarray) -> np.ndarray:
    """The point every (R, t) leaves in place, by least squares: (I - R) c = t, stacked; the
    solution nearest ``near`` where they leave a line (a single axis) in place."""
    if not transforms:
        return near
    system = np.concatenate([np.eye(3) - r for r, _ in transforms])
    target = np.concatenate([t - (np.eye(3) - r) @ near for r, t in transforms])
    offset, *_ = np.linalg.lstsq(system, target, rcond=1e-6)
    return near + offset


def find_symmetry(surface: Surface, scale: float, rng: np.random.Generator) -> Symmetry:
    """The reference's rotational symmetry (see the module's docstring)."""
    points = surface.points
    centroid = points.mean(axis=0)
    frame = principal_axes(points - centroid)
    spread = np.sqrt(np.maximum(np.var((points - centroid) @ frame, axis=0), 0))
    chosen = points[rng.choice(len(points), size=min(512, len(points)), replace=False)]
    noise, gate = 0.002 * scale, 0.3 * scale

    def refined(start: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """A start about ``centre`` refined onto the reference itself, if it then fits and
        still turns about a point near the centroid (a sample's centroid is off by a little).
        A few iterations on a few points first: most starts of most parts lead nowhere."""
        rotation, translation, _ = icp(
            chosen[:QUICK_POINTS], surface, start, _about(start, centre), noise, gate, QUICK
        )
        moved = chosen[:QUICK_POINTS] @ rotation.T + translation
        near, _ = surface_distance(surface, moved)
        if np.mean(near < 3 * _tolerance(surface, scale)) < SHARE:
            return None
        rotation, translation, _ = icp(chosen, surface, rotation, translation, noise, gate, 30)
        drift = np.linalg.norm(rotation @ centroid + translation - centroid)
        if drift > DRIFT * scale or not _fits(surface, chosen, rotation, translation, scale):
            return None
        return rotation, translation

    for k in range(3):
        others = [spread[j] for j in range(3) if j != k]
        if abs(others[0] - others[1]) > ROUND_AXES * max(others):
            continue
        # a sample's principal axis is off by a degree or so: a quarter turn about it, refined
        # onto the reference itself, turns about the true axis if there is one
        quarter = refined(rotation_vector(frame[:, k] * np.pi / 2), centroid)
        if quarter is None:
            continue
        axis = Rotation.from_matrix(quarter[0]).as_rotvec()
        axis = axis / np.linalg.norm(axis) * np.sign(axis @ frame[:, k])
        centre = _fixed_point([quarter], centroid)
        turns = [rotation_vector(axis * np.radians(a)) for a in REVOLUTION_ANGLES_DEG]
        if all(_fits(surface, chosen, turn, _about(turn, centre), scale) for turn in turns):
            flip = refined(rotation_vector(np.pi * _perpendicular(axis)), centre)
            if flip is not None:
                centre = _fixed_point([quarter, flip], centroid)
            rotations = [np.eye(3)] + ([flip[0]] if flip is not None else [])
            return Symmetry("revolution", centre, np.stack(rotations), axis)

    starts = []
    for order in permutations(range(3)):
        for signs in product((1.0, -1.0), repeat=3):
            candidate = frame[:, order] * signs
            if np.linalg.det(candidate) > 0:
                starts.append(candidate @ frame.T)
    for k, fold in product(range(3), range(2, MAX_FOLD + 1)):
        starts.append(rotation_vector(frame[:, k] * 2 * np.pi / fold))
    starts += list(Rotation.random(RANDOM_STARTS, random_state=rng).as_matrix())
    found: list[tuple[np.ndarray, np.ndarray]] = [(np.eye(3), np.zeros(3))]

    def keep(transform: tuple[np.ndarray, np.ndarray] | None) -> None:
        if transform is not None and all(
            _angle_deg(transform[0], other) > SAME_DEG for other, _ in found
        ):
            found.append(transform)

    for start in starts:
        keep(refined(start, centroid))
    grown = True
    while grown and len(found) <= MAX_GROUP:  # the group the found ones generate
        before = len(found)
        for (r1, t1), (r2, t2) in product(list(found), repeat=2):
            product_ = (r1 @ r2, r1 @ t2 + t1)
            if all(_angle_deg(product_[0], other) > SAME_DEG for other, _ in found):
                if _fits(surface, chosen, *product_, scale):
                    found.append(product_)
        grown = len(found) > before
    if len(found) == 1:
        return Symmetry.none(centroid)
    centre = _fixed_point(found[1:], centroid)
    return Symmetry("discrete", centre, np.stack([r for r, _ in found]))


def _angle_deg(first: np.ndarray, second: np.ndarray) -> float:
    cosine = (np.trace(first.T @ second) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cosine, -1, 1))))
