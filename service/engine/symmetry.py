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
"Fits" means that the moved points lie on the reference's surface as well as a fresh sample
of it would: a reference is a sample, so even its own points, each left out in turn, lie off
the surface the others describe (at sharp edges, studs, sparse patches). Of the moved points,
the share within ``TOLERANCE`` of the surface (or half a sample spacing, for a sparse one) must
be at least ``SHARE`` of that leave-one-out share, and the share farther than ``FAR`` times the
tolerance at most ``FAR_RATIO`` times its own plus ``FAR_EXTRA``: a feature that a turn moves
off the surface (a cross hole in a shaft, a notch in a flange) shows as far points, however
few. Measured on the meshes of the evaluation's parts (2,048 samples): true symmetries keep
0.98-1.03 of the leave-one-out share and as few far points; turns that a hole or notch breaks
keep 0.84-0.94, or add 2-9 % far points. An absolute share (the former rule, 95 % within the
tolerance) missed every symmetry of a part whose own samples fit worse than that (a stud brick:
74 %) and of a faceted ring.

The rotations found are closed under composition (``_group``); a revolution's turns are held
to ``REVOLUTION_SLACK`` times the tolerance (a faceted mesh's sag between facets).

Among poses the symmetry makes equivalent (``R S`` with the translation that keeps the scene
in place), ``canonical`` answers the one whose rotation is nearest the identity (the largest
trace), so the same surface in the same place always gives the same matrix.

An operator who knows the part may declare its symmetry at registration (``declared_symmetry``):
a turn the self-fit cannot confirm on a cloud's estimated normals, or one only a detail that
does not matter to the cell breaks. A declared turn must still nearly fit (``NEAR``); it joins
what was found (docs/decisions.md#declared-at-registration).

``near`` keeps the turns that nearly fit (``NEAR`` of the leave-one-out share) but are no
symmetry, and turns every ``NEAR_TURN_DEG`` about a nearly round axis: poses a view may hardly
tell apart from the answer's, which the engine tries too (``Search.resolve_near``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from itertools import permutations, product

import numpy as np
from scipy.spatial.transform import Rotation

from service.engine.alignment import orthonormal
from service.engine.icp import Surface, icp, rotation_vector
from service.engine.principal_axes import Frame
from service.engine.tuning import (  # docs/decisions.md#symmetry
    DRIFT,
    FAR,
    FAR_EXTRA,
    FAR_RATIO,
    FINE_DEG,
    MAX_FOLD,
    MAX_GROUP,
    MAX_NEAR,
    NEAR,
    NEAR_TURN_DEG,
    QUICK_SLACK,
    RANDOM_STARTS,
    REVOLUTION_ANGLES_DEG,
    REVOLUTION_SLACK,
    ROUND_TURNS,
    SAME_DEG,
    SHARE,
    SPACINGS,
    SYMMETRY_QUICK,
    SYMMETRY_QUICK_POINTS,
    TOLERANCE,
)
from service.engine.verification import patch_distance, surface_distance

RULE = 3  # the rule's version a description records: a stored older one is found again


@dataclass(frozen=True)
class Symmetry:
    kind: str  # "none" | "revolution" | "discrete"
    centroid: np.ndarray  # (3,) the rotations' fixed point, model frame
    rotations: np.ndarray  # (G, 3, 3), identity first: every discrete symmetry (or a flip)
    axis: np.ndarray | None = None  # revolution: unit axis through the centroid
    # (K, 3, 3) turns about the centroid that nearly fit but are no symmetry (a flange's turn
    # that only a notch tells apart, a shaft's end-for-end flip, a gear's tooth): poses the
    # answer is tried at as well, since a view may hardly tell them apart
    near: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    declared: dict | None = None  # what the operator declared at registration, as sent

    @classmethod
    def none(cls, centroid: np.ndarray, near: np.ndarray | None = None) -> Symmetry:
        near = np.zeros((0, 3, 3)) if near is None else near
        return cls("none", np.asarray(centroid, np.float64), np.eye(3)[None], near=near)

    @cached_property
    def round_axis(self) -> np.ndarray | None:
        """(3,) the axis that at least ``ROUND_TURNS`` of the near turns turn about (a nearly
        round part: the flange with its notch, the shaft with its cross hole), or None."""
        if not len(self.near):
            return None
        axes = _axes(self.near)
        shared = (np.abs(axes @ axes.T) > np.cos(np.radians(SAME_DEG))).sum(axis=1)
        return axes[int(np.argmax(shared))] if shared.max() >= ROUND_TURNS else None

    @cached_property
    def near_tried(self) -> np.ndarray:
        """(K', 3, 3) the turns an answer is tried at: ``near``; about a ``round_axis``, also
        each other near turn followed by each near turn about it, and every one of these and
        the identity turned by ``FINE_DEG`` either way about that axis."""
        axis = self.round_axis
        if axis is None:
            return self.near
        about = _near_axis(self.near, axis)
        # a turn about another axis, then one about the round axis (a shaft flipped end for
        # end, then turned about its own axis)
        others = self.near[~about]
        turns = np.concatenate(
            [self.near, np.einsum("oij,rjk->orik", others, self.near[about]).reshape(-1, 3, 3)]
        )
        turns = turns[apart(turns, SAME_DEG, len(turns))]
        fine = Rotation.from_rotvec(np.stack([axis, -axis]) * np.radians(FINE_DEG)).as_matrix()
        starts = np.concatenate([np.eye(3)[None], turns])
        return np.concatenate([turns, np.einsum("sij,fjk->sfik", starts, fine).reshape(-1, 3, 3)])

    @cached_property
    def near_reversing(self) -> np.ndarray:
        """(K',) bool: which of ``near_tried`` turn the ``round_axis`` end for end (none
        without one). Those poses of a nearly round part fit alike only where both ends look
        alike; the other kind, turns about the axis, fit alike all round."""
        axis = self.round_axis
        if axis is None:
            return np.zeros(len(self.near_tried), dtype=bool)
        return (self.near_tried @ axis) @ axis < 0

    def suggested(self) -> list[dict]:
        """Declarations (``declared_symmetry``) that would make the near turns symmetries: a
        revolution about the ``round_axis``; else, about each other axis they turn about, the
        turns by 360/n degrees that the smallest of them is (within ``SAME_DEG``). What an
        operator who knows the part may send (docs/decisions.md#declared-at-registration)."""
        if not len(self.near):
            return []
        if self.round_axis is not None:
            return [{"kind": "revolution", "axis": _rounded(self.round_axis)}]
        suggestions: list[dict] = []
        axes, angles = _axes(self.near), np.degrees(Rotation.from_matrix(self.near).magnitude())
        taken = np.zeros(len(axes), dtype=bool)
        for k in np.argsort(angles):
            if taken[k]:
                continue
            same = np.abs(axes @ axes[k]) > np.cos(np.radians(SAME_DEG))
            taken |= same
            order = int(round(360 / angles[k]))  # the folds find_symmetry tries
            if 2 <= order <= MAX_FOLD and abs(360 / order - angles[k]) <= SAME_DEG:
                suggestions.append({"kind": "discrete", "axis": _rounded(axes[k]), "order": order})
        return suggestions

    def describe(self) -> dict:
        """The JSON description a reference shows (and the store keeps)."""
        described: dict = {"kind": self.kind, "rule": RULE}
        if self.kind == "revolution":
            described["axis"] = np.round(self.axis, 6).tolist()
            described["flip"] = len(self.rotations) > 1
        elif self.kind == "discrete":
            described["rotations"] = np.round(self.rotations, 6).tolist()
        described["centre"] = np.round(self.centroid, 9).tolist()
        if len(self.near):
            described["near"] = np.round(self.near, 6).tolist()
        if self.declared is not None:
            described["declared"] = self.declared
        return described

    @staticmethod
    def declared_in(described: dict | None) -> dict | None:
        """What the operator declared, as a stored description keeps it (None: nothing)."""
        return (described or {}).get("declared")

    @staticmethod
    def outdated(described: dict | None) -> bool:
        """Whether a stored description was found by an earlier rule (before the rule's
        version was recorded: the absolute 95 % share, which missed a stud brick's quarter
        turns and a faceted ring's revolution)."""
        return described is not None and described.get("rule", 1) < RULE

    @classmethod
    def from_description(cls, described: dict, centroid: np.ndarray) -> Symmetry:
        centre = np.asarray(described.get("centre", centroid), np.float64)
        near = np.asarray(described.get("near", np.zeros((0, 3, 3))), np.float64).reshape(-1, 3, 3)
        declared = cls.declared_in(described)
        if described.get("kind") == "revolution":
            axis = np.asarray(described["axis"], np.float64)
            rotations = [np.eye(3)]
            if described.get("flip"):
                rotations.append(rotation_vector(np.pi * _perpendicular(axis)))
            axis = axis / np.linalg.norm(axis)
            return cls("revolution", centre, np.stack(rotations), axis, near, declared)
        if described.get("kind") == "discrete":
            rotations = np.asarray(described["rotations"], np.float64)
            return cls("discrete", centre, rotations, near=near, declared=declared)
        return replace(cls.none(centre, near), declared=declared)

    def equivalent(self, rotation: np.ndarray) -> np.ndarray:
        """(G, 3, 3) rotations equivalent to ``rotation`` under the discrete part."""
        return np.einsum("ij,gjk->gik", rotation, self.rotations)

    def canonical(
        self, rotation: np.ndarray, translation: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The equivalent pose whose rotation is nearest the identity, made exactly orthonormal
        (the stored turns and the poses composed with them carry float32's rounding)."""
        if self.kind == "none":
            return orthonormal(rotation), translation
        choices = self.equivalent(rotation)
        if self.kind == "revolution":  # turn each about the axis to its best angle
            choices = np.stack([c @ _best_turn(c, self.axis) for c in choices])
        best = orthonormal(choices[int(np.argmax(np.trace(choices, axis1=1, axis2=2)))])
        # scene = R m + t = R' m' + t' with m' = S^T (m - c) + c, S = R^T R'
        return best, translation + (rotation - best) @ self.centroid

    def distance_deg(self, first: np.ndarray, second: np.ndarray) -> float:
        """The angle between two rotations once symmetry is accounted for, in degrees: the
        smallest between ``first`` and a rotation equivalent to ``second``. Not the angle
        between their canonical poses: near a pose where two equivalents are about as near
        the identity, two rotations a degree apart can have canonical poses a symmetry apart
        (a square brick's 90 degrees)."""
        relative = np.einsum("ji,jk,gkl->gil", first, second, self.rotations)  # first^T second g
        if self.kind == "revolution":  # and any turn about the axis
            relative = np.stack([r @ _best_turn(r, self.axis) for r in relative])
        cosine = (np.trace(relative, axis1=1, axis2=2).max() - 1) / 2
        return float(np.degrees(np.arccos(np.clip(cosine, -1, 1))))


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


@dataclass(frozen=True)
class _SelfFit:
    """What "as well as a fresh sample" means for one reference: its own points, each left
    out of the surface in turn, and how far they lie from it."""

    tolerance: float
    distance: np.ndarray  # (N,) each sample's distance to the surface of the others

    @classmethod
    def of(cls, surface: Surface, scale: float) -> _SelfFit:
        return cls(_tolerance(surface, scale), _left_out_distance(surface))

    @property
    def far(self) -> float:
        return _far(self.distance, self.tolerance)

    @property
    def kept(self) -> float:
        """The share of the reference's own points within the tolerance."""
        return self.within(self.distance)

    def within(self, distance: np.ndarray) -> float:
        """The share of points at these distances within the tolerance."""
        return float(np.mean(distance < self.tolerance))

    def moved(self, surface: Surface, points: np.ndarray, rotation, translation) -> np.ndarray:
        """Distance of each of ``points`` moved by (R, t) to the reference's surface."""
        return surface_distance(surface, points @ rotation.T + translation, "nearest")[0]

    def fits(self, distance: np.ndarray, slack: float = 1.0) -> bool:
        """Whether points at these distances (``moved``) lie on the surface like the
        reference's own, within ``slack`` times the tolerance."""
        tolerance = slack * self.tolerance
        within = float(np.mean(distance < tolerance))
        own = float(np.mean(self.distance < tolerance))
        far = _far(distance, self.tolerance)
        return within >= SHARE * own and far <= FAR_RATIO * self.far + FAR_EXTRA

    def nearly(self, distance: np.ndarray) -> bool:
        """Whether points at these distances keep ``NEAR`` of the share the reference's own
        keep within the tolerance."""
        return self.within(distance) >= NEAR * self.kept


def _far(distance: np.ndarray, tolerance: float) -> float:
    return float(np.mean(distance > FAR * tolerance))


def _left_out_distance(surface: Surface) -> np.ndarray:
    """Each sample's distance to the surface the other samples describe (the tangent patch of
    the nearest other one, as ``surface_distance`` measures to the nearest samples)."""
    points, others = surface.points, surface.neighbours[:, 1:]
    offsets = points[:, None, :] - points[others]
    closest = np.argmin(np.einsum("nki,nki->nk", offsets, offsets), axis=1)
    return patch_distance(surface, points, others[np.arange(len(points)), closest])


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


def _self_noise_gate(scale: float) -> tuple[float, float]:
    """ICP's noise and gate for a reference refined onto itself."""
    return 0.002 * scale, 0.3 * scale


def _onto_itself(
    points: np.ndarray,
    surface: Surface,
    scale: float,
    start: np.ndarray,
    centre: np.ndarray,
    iterations: int,
) -> tuple[np.ndarray, np.ndarray]:
    """``points`` turned by ``start`` about ``centre``, refined onto the reference's own
    surface: (rotation, translation)."""
    translation = _about(start, centre)
    rotation, translation, _ = icp(
        points, surface, start, translation, *_self_noise_gate(scale), iterations
    )
    return rotation, translation


def find_symmetry(surface: Surface, scale: float, rng: np.random.Generator) -> Symmetry:
    """The reference's rotational symmetry (see the module's docstring)."""
    points = surface.points
    principal = Frame.of(points)
    centroid, frame = principal.centroid, principal.axes
    chosen = points[rng.choice(len(points), size=min(512, len(points)), replace=False)]
    own = _SelfFit.of(surface, scale)
    # a quick refinement is not yet converged: it may leave a few more points out than FAR
    quick_share = SHARE * (1 - own.far) - QUICK_SLACK

    def fits(rotation: np.ndarray, translation: np.ndarray, slack: float = 1.0) -> bool:
        return own.fits(own.moved(surface, points, rotation, translation), slack)

    def refined(
        start: np.ndarray, centre: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, bool] | None:
        """A start about ``centre`` refined onto the reference itself, if it then nearly fits
        and still turns about a point near the centroid (a sample's centroid is off by a
        little), and whether it fits: a symmetry. A few iterations on a few points first:
        most starts of most parts lead nowhere."""
        rotation, translation = _onto_itself(
            chosen[:SYMMETRY_QUICK_POINTS], surface, scale, start, centre, SYMMETRY_QUICK
        )
        moved = chosen[:SYMMETRY_QUICK_POINTS] @ rotation.T + translation
        near, _ = surface_distance(surface, moved, "nearest")
        if np.mean(near < FAR * own.tolerance) < NEAR * quick_share:
            return None
        rotation, translation, _ = icp(
            chosen, surface, rotation, translation, *_self_noise_gate(scale), 30
        )
        drift = np.linalg.norm(rotation @ centroid + translation - centroid)
        if drift > DRIFT * scale or _angle_deg(rotation, np.eye(3)) < SAME_DEG:
            return None
        distance = own.moved(surface, points, rotation, translation)
        if own.fits(distance):
            return rotation, translation, True
        if own.nearly(distance):
            return rotation, translation, False
        return None

    nearly: list[np.ndarray] = []  # refined turns that nearly fit, no symmetry
    round_turns: list[np.ndarray] = []  # turns about a nearly round axis that nearly fit

    for k in range(3):
        if not principal.round_about(k):
            continue
        # a sample's principal axis is off by a degree or so: a quarter turn about it, refined
        # onto the reference itself, turns about the true axis if there is one
        quarter = refined(rotation_vector(frame[:, k] * np.pi / 2), centroid)
        if quarter is None:
            continue
        axis = Rotation.from_matrix(quarter[0]).as_rotvec()
        axis = axis / np.linalg.norm(axis) * np.sign(axis @ frame[:, k])
        centre = _fixed_point([quarter[:2]], centroid)
        turns = [rotation_vector(axis * np.radians(a)) for a in REVOLUTION_ANGLES_DEG]
        if quarter[2] and all(fits(t, _about(t, centre), REVOLUTION_SLACK) for t in turns):
            flip = refined(rotation_vector(np.pi * _perpendicular(axis)), centre)
            flip = flip if flip is not None and flip[2] else None
            if flip is not None:
                centre = _fixed_point([quarter[:2], flip[:2]], centroid)
            rotations = [np.eye(3)] + ([flip[0]] if flip is not None else [])
            return Symmetry("revolution", centre, np.stack(rotations), axis)
        # nearly round: where the part stands about this axis, only a detail may tell
        step = np.radians(NEAR_TURN_DEG)
        for j in range(1, int(round(2 * np.pi / step))):
            turn = rotation_vector(axis * step * j)
            if own.nearly(own.moved(surface, points, turn, _about(turn, centre))):
                round_turns.append(turn)

    starts = []
    for order in permutations(range(3)):
        for signs in product((1.0, -1.0), repeat=3):
            candidate = frame[:, order] * signs
            if np.linalg.det(candidate) > 0:
                starts.append(candidate @ frame.T)
    for k, fold in product(range(3), range(2, MAX_FOLD + 1)):
        starts.append(rotation_vector(frame[:, k] * 2 * np.pi / fold))
    starts += list(Rotation.random(RANDOM_STARTS, random_state=rng).as_matrix())
    found: list[Transform] = [(np.eye(3), np.zeros(3))]

    for start in starts:
        result = refined(start, centroid)
        if result is None:
            continue
        rotation, translation, symmetric = result
        if not symmetric:
            nearly.append(rotation)
        elif all(_angle_deg(rotation, other) > SAME_DEG for other, _ in found):
            found.append((rotation, translation))
    found = _group(found, fits)
    group = np.stack([r for r, _ in found])
    near = _distinct_near(nearly + round_turns, group)
    if len(found) == 1:
        return Symmetry.none(centroid, near)
    centre = _fixed_point(found[1:], centroid)
    return Symmetry("discrete", centre, group, near=near)


def declared_symmetry(surface: Surface, scale: float, declared: dict, found: Symmetry) -> Symmetry:
    """The symmetry an operator declared (``{"kind": "revolution", "axis", "flip"}``, or
    ``{"kind": "discrete"}`` with ``"axis"`` and ``"order"``, or with ``"rotations"``: 3 x 3
    matrices in the points' frame), joined with what registration ``found``. The turns turn
    about the point a refinement of the first onto the part leaves in place. Raises
    ``ValueError``, naming the turn, where one does not nearly fit (``NEAR``), or where the
    rotations generate more than ``MAX_GROUP``."""
    points = surface.points
    own = _SelfFit.of(surface, scale)
    turns, flips = _declared_turns(declared)
    # the axis a round part turns about: declared, or found (None: no revolution)
    axis = _unit(declared["axis"]) if declared["kind"] == "revolution" else found.axis
    if declared["kind"] == "discrete" and found.kind == "revolution":  # a declared flip
        flips = [t for t in turns if (t @ axis) @ axis < 0][:1]
    centre = _centre(surface, scale, (turns + flips)[:1], found.centroid)

    def check(rotations: list[np.ndarray]) -> None:
        for turn in rotations:
            distance = own.moved(surface, points, turn, _about(turn, centre))
            if not own.nearly(distance):
                raise ValueError(_misfit(turn, distance, own))

    if axis is not None:  # a round part: every turn about its axis fits
        check(turns + flips)
        kept = list(found.rotations[1:2]) if found.kind == "revolution" else []  # its flip
        rotations = [np.eye(3)] + (flips[:1] or kept)
        near = found.near[~_near_axis(found.near, axis)] if len(found.near) else found.near
        return Symmetry("revolution", centre, np.stack(rotations), axis, near, declared)
    check(turns)  # the declared first, so that a refusal names one of them
    group = _closed([np.asarray(r, np.float64) for r in found.rotations] + turns)
    check([g for g in group[1:] if not _near(g[None], found.rotations).any()])  # products
    near = _distinct_near(list(found.near), group)
    return Symmetry("discrete", centre, group, near=near, declared=declared)


def _declared_turns(declared: dict) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The turns a declaration names (a revolution's at ``REVOLUTION_ANGLES_DEG``), none
    within ``SAME_DEG`` of the identity, and its flip."""
    flips = []
    if declared["kind"] == "revolution":
        axis = _unit(declared["axis"])
        turns = [rotation_vector(axis * np.radians(a)) for a in REVOLUTION_ANGLES_DEG]
        if declared.get("flip"):
            flips = [rotation_vector(np.pi * _perpendicular(axis))]
    elif "rotations" in declared:
        turns = [np.asarray(r, np.float64) for r in declared["rotations"]]
    else:
        axis, order = _unit(declared["axis"]), int(declared["order"])
        turns = [rotation_vector(axis * 2 * np.pi * k / order) for k in range(1, order)]
    return [t for t in turns if _angle_deg(t, np.eye(3)) > SAME_DEG], flips


def _rounded(axis: np.ndarray) -> list[float]:
    """An axis as a declaration gives it: its largest component positive, to 3 decimals."""
    axis = axis * np.sign(axis[np.argmax(np.abs(axis))])
    return [round(float(v), 3) + 0.0 for v in axis]  # + 0.0: no -0.0


def _unit(vector) -> np.ndarray:
    vector = np.asarray(vector, np.float64)
    return vector / np.linalg.norm(vector)


def _centre(
    surface: Surface, scale: float, turns: list[np.ndarray], centroid: np.ndarray
) -> np.ndarray:
    """The point ``turns[0]`` turns about once refined onto the part itself (a cloud's centroid
    lies off the axis where one side was sampled more), else ``centroid``."""
    if not turns:
        return centroid
    transform = _onto_itself(surface.points, surface, scale, turns[0], centroid, 30)
    centre = _fixed_point([transform], centroid)
    return centre if np.linalg.norm(centre - centroid) <= DRIFT * scale else centroid


def _misfit(turn: np.ndarray, distance: np.ndarray, own: _SelfFit) -> str:
    """Why a declared turn was refused: its angle and axis, and the shares on the surface."""
    vector = Rotation.from_matrix(turn).as_rotvec()
    angle = np.degrees(np.linalg.norm(vector))
    axis = ", ".join(f"{v:.3f}" for v in vector / max(np.linalg.norm(vector), 1e-12))
    share = own.within(distance)
    return (
        f"the declared symmetry does not fit the part: turned by {angle:.0f} degrees about "
        f"[{axis}], {share:.0%} of its points lie on its surface, where {NEAR:.0%} of its own "
        f"points' share ({own.kept:.0%}) is needed. Give the axis in the frame of the points sent"
    )


def _closed(rotations: list[np.ndarray]) -> np.ndarray:
    """(G, 3, 3) the group ``rotations`` generate, identity first; ``ValueError`` beyond
    ``MAX_GROUP`` (a turn by an angle that divides no whole turn)."""
    group = [np.eye(3)] + [r for r in rotations if _angle_deg(r, np.eye(3)) > SAME_DEG]
    while True:
        stacked = np.stack(group)
        products = np.einsum("aij,bjk->abik", stacked, stacked).reshape(-1, 3, 3)
        fresh = products[~_near(products, stacked).any(axis=1)]
        if not len(fresh):
            return stacked
        group.extend(fresh[apart(fresh, SAME_DEG, len(fresh))])
        if len(group) > MAX_GROUP:
            raise ValueError(
                f"the declared rotations generate more than {MAX_GROUP}: declare turns by "
                "whole fractions of a turn (360/n degrees), or a revolution"
            )


def _distinct_near(nearly: list[np.ndarray], group: np.ndarray) -> np.ndarray:
    """(K, 3, 3) of the turns that nearly fit, at most ``MAX_NEAR``, none a symmetry and no
    two alike up to one (S N and N answer the same pose once made canonical)."""
    kept: list[np.ndarray] = []
    for rotation in nearly:
        if _near(rotation[None], group).any():
            continue
        if kept and _near(np.einsum("gij,jk->gik", group, rotation), np.stack(kept)).any():
            continue
        kept.append(rotation)
        if len(kept) == MAX_NEAR:
            break
    return np.stack(kept) if kept else np.zeros((0, 3, 3))


Transform = tuple[np.ndarray, np.ndarray]  # (R, t): x -> R x + t
Refined = tuple[np.ndarray, np.ndarray, bool]  # (R, t) and whether it fits: a symmetry


def _group(found: list[Transform], fits) -> list[Transform]:
    """The group the found symmetries generate (products that fit as well), then closed: a
    product of two symmetries is one, so where a product does not fit, one of its factors
    was a near miss (a notch the sample is too sparse to see for sure); the one in the most
    such products is dropped until every product is in the set. The identity stays first.
    More than ``MAX_GROUP`` rotations that fit (a handful of points, where any turn does) is no
    part's group: the identity alone is kept."""
    while True:  # grow
        rotations = np.stack([r for r, _ in found])
        products = np.einsum("aij,bjk->abik", rotations, rotations).reshape(-1, 3, 3)
        fresh = ~_near(products, rotations).any(axis=1)
        count = len(found)
        for index in np.flatnonzero(fresh):
            (r1, t1), (r2, t2) = found[index // count], found[index % count]
            candidate = (r1 @ r2, r1 @ t2 + t1)
            if any(_angle_deg(candidate[0], r) < SAME_DEG for r, _ in found[count:]):
                continue  # the same product reached twice this round
            if fits(*candidate):
                found.append(candidate)
                if len(found) > MAX_GROUP:
                    return found[:1]
        if len(found) == count:
            break
    while True:  # close
        rotations = np.stack([r for r, _ in found])
        products = np.einsum("aij,bjk->abik", rotations, rotations)
        missing = ~_near(products.reshape(-1, 3, 3), rotations).any(axis=1)
        missing = missing.reshape(len(found), len(found))
        blame = missing.sum(axis=0) + missing.sum(axis=1)
        if not blame.any():
            return found
        del found[1 + int(np.argmax(blame[1:]))]


def apart(rotations: np.ndarray, degrees: float, count: int) -> np.ndarray:
    """Indices of the first ``count`` of ``rotations`` (K, 3, 3), in order, that lie more than
    ``degrees`` from every earlier one kept."""
    kept: list[int] = []
    for k in range(len(rotations)):  # each against the kept alone: most stop after a few
        if len(kept) == count:
            break
        if not kept or not _near(rotations[k : k + 1], rotations[kept], degrees).any():
            kept.append(k)
    return np.asarray(kept, dtype=np.intp)


def _axes(turns: np.ndarray) -> np.ndarray:
    """(K, 3) the unit axis each of ``turns`` (K, 3, 3) turns about."""
    vectors = Rotation.from_matrix(turns).as_rotvec()
    return vectors / np.maximum(np.linalg.norm(vectors, axis=1, keepdims=True), 1e-12)


def _near_axis(turns: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(K,) bool: which of ``turns`` turn about ``axis`` (either way)."""
    return np.abs(_axes(turns) @ axis) > np.cos(np.radians(SAME_DEG))


def _near(first: np.ndarray, second: np.ndarray, degrees: float = SAME_DEG) -> np.ndarray:
    """(A, B): whether each of ``first`` (A, 3, 3) is within ``degrees`` of each of
    ``second``."""
    cosine = (np.einsum("aij,bij->ab", first, second) - 1) / 2
    return cosine > np.cos(np.radians(degrees))


def _angle_deg(first: np.ndarray, second: np.ndarray) -> float:
    cosine = (np.trace(first.T @ second) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cosine, -1, 1))))
