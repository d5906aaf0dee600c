"""The engine: recognise a registered object in a cloud and estimate its pose.

``Engine.align`` is the paper's chain, one step a block: normalise -> map to 2-D (ONNX) ->
grid -> classify (eq. 4, and the rendered views whose grids look most alike) -> hypothesise
poses -> verify (fit x coverage) -> refine (point-to-plane ICP) -> decide -> measure the fit.
It runs in two passes: first the whole part (eq. 4's candidates, whole-reference hypotheses),
which a full 360-degree cloud passes at once; then, unless that found an excellent fit, single
views (the candidates and view hypotheses the rendered views propose), which is what a depth
camera posts. The gallery is an immutable snapshot swapped whole on every change, so any
number of threads may align while one registers or removes a reference.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from service.engine import confidence
from service.engine import hypotheses as sources
from service.engine.alignment import alignment_error
from service.engine.classifier import LinearClassifier, classifier_input, view_features, view_gram
from service.engine.confidence import Calibration
from service.engine.distance_field import DistanceField
from service.engine.grid import grid
from service.engine.hypotheses import Hypotheses
from service.engine.icp import Surface, icp
from service.engine.mapping import Mapper
from service.engine.normalize import has_extent, normalize, radius, subsample
from service.engine.normals import estimate_normals, mesh_normals, orient_by_views
from service.engine.principal_axes import Frame, flatness
from service.engine.reference import Reference
from service.engine.surroundings import set_aside_surroundings
from service.engine.symmetry import FINE_DEG, Symmetry, apart, find_symmetry
from service.engine.verification import Lookup, Occupancy, coverage, fit, surface_distance
from service.engine.views import (
    CAMERA_DISTANCE,
    Views,
    directions,
    facing,
    render,
    sample_spacing,
    splat_visible,
)
from service.engine.visibility import random_camera, visible_points
from service.errors import EmptyGallery, UnknownReference
from service.settings import EngineSettings


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
    fit: float = 0.0  # share of observed points near the reference's surface at the pose
    coverage: float = 0.0  # share of what the camera should see of it that was observed
    runner_up: float = 0.0  # the best fit x coverage of any other part
    runner_up_label: str | None = None
    alike: float = 0.0  # the best fit x coverage of another, non-equivalent pose of the part
    size_ratio: float = 1.0  # the observed radius over the part's scale
    points: int = 0  # observed points the answer rests on


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


@dataclass
class Query:
    """What one ``align`` call asked, and its clock."""

    snapshot: Snapshot
    allowed: np.ndarray  # the classifier rows the caller allows
    sources: tuple[str, ...]
    top_k: int | None
    refine: bool
    viewpoint: np.ndarray | None
    rng: np.random.Generator
    clock: Stopwatch


@dataclass
class Fit:
    """One verified (and perhaps refined) hypothesis of one candidate."""

    row: int
    rotation: np.ndarray
    translation: np.ndarray
    source: str
    view: int  # the view the camera was expected to see (-1: the whole part)
    fit: float
    coverage: float
    refined: bool = False
    settled: bool = False  # its last refinement stopped before its iterations ran out

    @property
    def score(self) -> float:
        return self.fit * self.coverage


VIEW_POINTS = 512  # a rendered view's grid is made of at most this many of its points
FLAT = 0.03  # an observation this flat (smallest over largest principal spread) is one face
DIFFERENT_DEG = 10.0  # poses this far apart (symmetry accounted for) are different answers
ALIKE = 0.9  # ... and fit alike when within this share of the best's fit x coverage
MAX_ALTERNATIVES = 3
NEAR_SOURCE = "near-symmetry"  # the hypothesis of a pose found by turning the best one
FLIP_SOURCE = "flip"  # ... by turning it half a turn about a principal axis of its part
NEAR_PRESCREENED = 32  # turned poses of a kind measured on the corrected distance ...
NEAR_SCREENED = 8  # ... of which these are measured again on the network's sample
SCREEN_ALIKE = 1.5  # a turned pose this much farther before refining is not refined
RESIDUAL_ALIKE = 1.15  # a turned pose this much farther from the surface is no alternative
# another pose that places the part closer than this share of its scale to the answer's (a
# gear turned by a tooth, a near-symmetric part flipped) does not lower the confidence: were it
# the truth, the answer would still be precise (ADD-S under 0.02 of the diameter, which is at
# least the scale); a mug turned to hide its handle (0.04-0.06 of its scale) still does
RIGHT_EITHER_WAY = 0.02


class Stopwatch:
    """Milliseconds per step, in the order the steps ran."""

    def __init__(self):
        self.timings: dict[str, float] = {}
        self.began = self.last = time.perf_counter()

    def lap(self, step: str) -> None:
        now = time.perf_counter()
        self.timings[step] = self.timings.get(step, 0.0) + (now - self.last) * 1e3
        self.last = now

    def total(self) -> dict[str, float]:
        self.timings["total"] = (time.perf_counter() - self.began) * 1e3
        return {k: round(v, 3) for k, v in self.timings.items()}


class Engine:
    def __init__(
        self,
        mapper: Mapper,
        settings: EngineSettings | None = None,
        calibration: Calibration | None = None,
    ):
        self.mapper = mapper
        self.settings = settings or EngineSettings()
        self.calibration = calibration
        self._snapshot = Snapshot({}, None)
        self._write_lock = threading.Lock()

    # --- a reference ------------------------------------------------------------------

    def make_reference(
        self,
        name: str,
        points: np.ndarray,
        seed: int | None = None,
        mesh: trimesh.Trimesh | None = None,
        face_index: np.ndarray | None = None,
    ) -> Reference:
        """Compute what the engine needs of a new object from its points (sampled on ``mesh``'s
        faces ``face_index``, when it came as a mesh): mapped points, view grids, scale, then
        normals, rendered views, distance field and symmetry."""
        points = np.asarray(points, dtype=np.float32)
        mapped = self.map(points)
        rng = np.random.default_rng(self.settings.seed if seed is None else seed)
        views = [self.view_grid(points, rng) for _ in range(self.settings.view_grids)]
        reference = Reference(name, points, mapped, np.stack(views), radius(points))
        return self.complete(reference, mesh, face_index)

    def complete(
        self,
        reference: Reference,
        mesh: trimesh.Trimesh | None = None,
        face_index: np.ndarray | None = None,
    ) -> Reference:
        """The reference with every derived field computed (those it lacks, or all of them
        when a mesh is given): normals, views, distance field, symmetry."""
        settings = self.settings
        if mesh is None and not reference.missing:
            return reference
        points = np.asarray(reference.points, dtype=np.float64)
        tree = cKDTree(points)
        if mesh is not None:  # the views see the mesh's own surface; normals are its faces'
            surface = np.asarray(
                trimesh.sample.sample_surface(
                    mesh, settings.mesh_surface_points, seed=settings.seed + 1
                )[0]
            )
            visible = render(points, reference.scale, settings.views, surface, mesh.area)
            normals = mesh_normals(mesh, face_index, points, directions(settings.views), visible)
        else:
            visible = render(points, reference.scale, settings.views, tree=tree)
            normals = estimate_normals(points, tree=tree)
            normals = orient_by_views(points, normals, directions(settings.views), visible)
        if mesh is None:  # a cloud's own buffer lets through what its camera hardly samples;
            # a view left facing nothing (a few points, normals at odds) keeps what it showed
            faced = visible & facing(points, normals, reference.scale, settings.views)
            visible = np.where(faced.any(axis=1, keepdims=True), faced, visible)
        distance_field = DistanceField.of(points, reference.scale, tree=tree)
        surface_model = Surface.of(points, normals, distance_field, tree)
        grids = np.stack([grid(self.map(points[seen][:VIEW_POINTS])) for seen in visible])
        symmetry = find_symmetry(surface_model, reference.scale, np.random.default_rng(0))
        return reference.with_(
            normals=normals.astype(np.float32),
            visibility=np.packbits(visible, axis=1),
            view_features=view_features(grids, settings.grid_blur).astype(np.float16),
            field=distance_field.nearest,
            field_frame=np.array([*distance_field.origin, distance_field.voxel]),
            symmetry=symmetry.describe(),
        )

    def refind_symmetry(self, reference: Reference) -> Reference:
        """The reference with its symmetry found again by this version's rule, from its stored
        surface (points, normals, distance field), every other field as it was."""
        surface = stored_surface(reference)
        symmetry = find_symmetry(surface, reference.scale, np.random.default_rng(0))
        return reference.with_(symmetry=symmetry.describe())

    def view_grid(self, points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The grid of an augmented view: a random pose, a single camera's view with
        probability ``partial_views``, and 10-100 % of the remaining points kept."""
        if rng.random() < self.settings.partial_views:
            points = points[visible_points(points, random_camera(points, 3.0, rng))]
        count = min(len(points), self.settings.network_points)
        keep = max(16, int(count * rng.uniform(0.1, 1.0)))
        view = points[subsample(points, keep, rng)] @ Rotation.random(random_state=rng).as_matrix()
        return grid(self.map(view))

    # --- the gallery ------------------------------------------------------------------

    def load(self, references: list[Reference]) -> None:
        entries = {r.name: Entry.of(r, self.settings.grid_blur) for r in references}
        with self._write_lock:
            gram = view_gram([e.view_features for e in entries.values()]) if entries else None
            self._publish(entries, gram)

    def add(self, reference: Reference) -> None:
        """Add a reference, or replace the one of its name."""
        entry = Entry.of(reference, self.settings.grid_blur)
        share = view_gram([entry.view_features])  # its views' part of the Gram, off the lock
        with self._write_lock:
            entries, gram = self._snapshot.entries, self._snapshot.gram
            gram = share if gram is None else gram + share
            if (previous := entries.get(reference.name)) is not None:
                gram -= view_gram([previous.view_features])
            self._publish({**entries, reference.name: entry}, gram)

    def remove(self, name: str) -> None:
        with self._write_lock:
            entries = self._snapshot.entries
            if name not in entries:
                raise UnknownReference(f"no reference named {name!r}")
            rest = {k: v for k, v in entries.items() if k != name}
            gram = self._snapshot.gram - view_gram([entries[name].view_features]) if rest else None
            self._publish(rest, gram)

    def _publish(self, entries: dict[str, Entry], gram: np.ndarray | None) -> None:
        """Refit the classifier on every reference's view features and swap the snapshot.

        ``gram`` is kept by sums across changes (one reference's share added or taken away),
        so a refit costs the same whatever the gallery's size."""
        classifier = None
        if entries:
            classifier = LinearClassifier.fit(
                list(entries),
                [e.view_features for e in entries.values()],
                self.settings.classifier_ridge,
                self.settings.grid_blur,
                gram,
            )
        listed = list(entries.values())
        scales = np.array([entry.reference.scale for entry in listed])
        counts = [len(e.views.radii) for e in listed]
        self._snapshot = Snapshot(
            entries,
            classifier,
            scales,
            gram,
            view_keys=np.concatenate([e.reference.view_features.astype(np.float32) for e in listed])
            if listed
            else np.zeros((0, 256), np.float32),
            view_owner=np.repeat(np.arange(len(listed)), counts),
            view_index=np.concatenate([np.arange(c) for c in counts])
            if listed
            else np.zeros(0, np.intp),
            view_radii=np.concatenate([e.views.radii for e in listed]) if listed else np.zeros(0),
        )

    def names(self) -> list[str]:
        return list(self._snapshot.entries)

    def get(self, name: str) -> Reference | None:
        entry = self._snapshot.entries.get(name)
        return entry.reference if entry else None

    def __len__(self) -> int:
        return len(self._snapshot.entries)

    def entry(self, name: str) -> Entry:
        """A reference with its search trees (for evaluation and diagnostics)."""
        try:
            return self._snapshot.entries[name]
        except KeyError:
            raise UnknownReference(f"no reference named {name!r}") from None

    def recognise(self, mapped: np.ndarray) -> tuple[str, float]:
        """Step 3 alone: the label eq. (4) gives a mapped cloud, and its score."""
        classifier = self._snapshot.classifier
        if classifier is None:
            raise EmptyGallery("no reference is registered: register one with POST /references")
        scores = classifier.scores(grid(mapped))
        best = int(np.argmax(scores))
        return classifier.labels[best], float(scores[best])

    # --- the chain --------------------------------------------------------------------

    def map(self, points: np.ndarray) -> np.ndarray:
        """Normalise a cloud as training did and map it to 2-D."""
        return self.mapper.map(normalize(points, self.mapper.canonical).points)

    def align(
        self,
        points: np.ndarray,
        candidates: list[str] | None = None,
        top_k: int | None = None,
        refine: bool = True,
        hypotheses: tuple[str, ...] | None = None,
        viewpoint: np.ndarray | None = None,
        min_confidence: float | None = None,
    ) -> Alignment:
        """Recognise and pose the object in ``points``; ``viewpoint`` is where the sensor was,
        in the cloud's frame, if known; below ``min_confidence`` the verdict is never "match"."""
        snapshot, settings = self._snapshot, self.settings
        if not snapshot.entries:
            raise EmptyGallery("no reference is registered: register one with POST /references")
        query = Query(
            snapshot,
            self._candidate_rows(snapshot, candidates),
            hypotheses or settings.hypotheses,
            top_k,
            refine,
            None if viewpoint is None else np.asarray(viewpoint, dtype=np.float64),
            np.random.default_rng(settings.seed),
            Stopwatch(),
        )
        scene = np.asarray(points, dtype=np.float64)
        # 0. Set aside the table, stray points and clutter; more than one reading may be tried.
        readings = set_aside_surroundings(
            scene, np.random.default_rng(settings.seed), query.viewpoint
        )
        query.clock.lap("surroundings")
        answer, seen = None, scene
        for reading in readings:
            if answer is not None and answer.fit * answer.coverage >= settings.excellent:
                break
            found = self._align_reading(query, reading.points, reading.spacing)
            found.points_set_aside = reading.set_aside
            if answer is None or found.fit * found.coverage > answer.fit * answer.coverage:
                answer, seen = found, reading.points
        if answer.verdict != "no_match":  # 9. How far to trust it.
            self._judge(answer, min_confidence, query, flatness(seen))
        answer.timings_ms = query.clock.total()
        return answer

    def _judge(
        self, answer: Alignment, min_confidence: float | None, query: Query, flat: float
    ) -> None:
        """Confidence, verdict and reasons of an answer (``service.engine.confidence``).
        ``flat`` is the observation's ``flatness``: one flat face of a part that is not flat
        itself fixes neither its turn about the face's normal nor where along the face it
        lies (a crop or an occlusion draws the outline), so such an answer is never a
        "match"."""
        settings = self.settings
        entry = query.snapshot.entries[answer.label]
        one_face = flat < FLAT <= entry.flatness
        values = confidence.measures(
            answer.fit,
            answer.coverage,
            answer.runner_up,
            answer.alike,
            answer.points,
            answer.size_ratio,
        )
        if self.calibration is None:
            answer.verdict, answer.confidence = "uncertain", None
            reasons = ["no confidence calibration is loaded (confidence.json)"]
        else:
            answer.confidence = self.calibration.confidence(values)
            for alternative in answer.alternatives:
                alternative.confidence = answer.confidence
            threshold = next(
                t
                for t in (min_confidence, settings.accept, self.calibration.accept)
                if t is not None
            )
            if answer.confidence >= threshold and not one_face:
                answer.verdict, answer.reasons = "match", []
                return
            low = answer.confidence < settings.reject_below
            answer.verdict = "no_match" if low else "uncertain"
            reasons = []
            if answer.confidence < threshold:
                reasons.append(
                    f"the confidence {answer.confidence:.2f} is below the threshold {threshold:.2f}"
                )
        if one_face:
            reasons.append(
                f"the observed points lie on one plane (thickness {flat:.1%} of their extent): "
                f"one flat face does not fix {answer.label}'s pose; look at the part from where "
                "more than one of its faces is seen"
            )
        reasons += confidence.reasons(
            answer.label, values, answer.runner_up_label, answer.ambiguous
        )
        # the part does not explain the cloud, nor does the confidence (if any) say it may:
        # other units? Only then: the right part seen on its table, some of the table left in
        # the cloud, fits as poorly (67-77 %), and was told that another unit would fit
        if values["fit"] < POOR_FIT and (answer.verdict == "no_match" or answer.confidence is None):
            size = answer.size_ratio * entry.reference.scale
            hint = self._unit_hint(query.snapshot.scales[query.allowed], size)
            reasons += [hint] if hint else []
        answer.reasons = reasons

    def _align_reading(self, query: Query, scene: np.ndarray, spacing: float) -> Alignment:
        """Steps 1-8 on one reading of the observation."""
        snapshot, settings, clock, rng = query.snapshot, self.settings, query.clock, query.rng
        # the strays set aside, what is left lies at one place
        if not has_extent(radius(scene), float(np.abs(scene).max())):
            return self._unanswered(
                snapshot,
                query.allowed,
                scene,
                np.zeros(len(snapshot.classifier.labels)),
                [
                    f"the {len(scene)} points left once stray points are set aside lie at one "
                    "place: there is no shape to recognise; send the part's points"
                ],
            )
        # 1. Normalise: subsample to the network's size (centring, scaling in map()).
        observed = scene[subsample(scene, settings.network_points, rng)]
        size = radius(observed)
        clock.lap("normalize")
        # 2. Map every point to 2-D with the network.
        observed_mapped = self.map(observed)
        clock.lap("map")
        # 3. Grid and classify (eq. 4) among the references of a plausible size.
        observed_grid = grid(observed_mapped)
        scores = snapshot.classifier.scores(observed_grid)
        allowed = query.allowed
        plausible = allowed[self._plausible(snapshot.scales[allowed], size, settings.size_ratio)]
        ranked = plausible[np.argsort(-scores[plausible], kind="stable")]
        shortlist = ranked[: query.top_k or settings.top_k]
        clock.lap("classify")

        # 4-6. The whole part: hypotheses from its principal axes, verified, the best refined
        # (and in each pass the best of eq. (4)'s first choice).
        search = Search(self, snapshot, observed, observed_mapped, spacing, query, clock)
        chosen = query.sources
        whole = [s for s in chosen if s == "principal-axes"]
        first = sure_first(scores, ranked)
        fits = search.run(
            {row: whole for row in shortlist},
            query.refine,
            WHOLE_REFINED,
            first,
            screened=WHOLE_SCREENED,
        )
        if "views" in chosen and not excellent(fits, settings):
            # 3b-6. Single views: the parts whose rendered views' grids look most like the
            # observation's, and eq. (4)'s; hypotheses from every rendered view of each.
            rows = [*self._nearest_views(snapshot, observed_grid, size, allowed, query.top_k)]
            rows += [row for row in shortlist if row not in rows]
            clock.lap("classify")
            planned = {row: ["views", *(whole if row not in shortlist else [])] for row in rows}
            fits += search.run(planned, query.refine, settings.refine_best, first, rescue=True)
        paired = [s for s in chosen if s in ("mapped", "paper")]
        if paired and not excellent(fits, settings):
            # 4-6 again with the mapped pairs: what the learned mapping pairs, solved.
            fits += search.run({row: paired for row in shortlist}, query.refine, WHOLE_REFINED)
        if not fits:  # nothing of a plausible size: no search over the wrong sizes
            return self._no_match_by_size(snapshot, allowed, observed, scores)

        # 6b. The best pose, where it fits short of excellent, turned half a turn about each of
        # the part's principal axes and refined: a view's frame is matched up to the signs of
        # its axes, and the wrong sign refines into a minimum of its own. Then the best part
        # turned by each of its near-symmetries, refined: a notch or a cross hole may be all
        # that tells those poses apart.
        fits.sort(key=lambda f: -f.score)
        if query.refine:
            fits = search.flip(fits)
            clock.lap("flips")
            fits = search.resolve_near(fits)
            clock.lap("near-symmetries")
            # 6c. The winner's pose finished, where the search's budget stopped short of it.
            if search.polish(fits[0]):
                clock.lap("refine")

        # 7. Decide: the best fit x coverage over every candidate and hypothesis; its
        # canonical pose among those its symmetry makes equivalent; other poses that fit alike.
        winner = fits[0]
        label = snapshot.classifier.labels[winner.row]
        entry = snapshot.entries[label]
        rotation, translation = entry.symmetry.canonical(winner.rotation, winner.translation)
        others = [f for f in fits if f.row != winner.row]
        runner_up = max(others, key=lambda f: f.score, default=None)
        runner_up_label = None if runner_up is None else snapshot.classifier.labels[runner_up.row]
        alike = 0.0
        alternatives = []
        for other in fits[1:]:
            if other.row != winner.row or not other.refined:
                continue
            if entry.symmetry.distance_deg(other.rotation, winner.rotation) <= DIFFERENT_DEG:
                continue
            if other.score > alike and entry.gap(winner, other) >= RIGHT_EITHER_WAY:
                alike = other.score
            if other.score >= ALIKE * winner.score and len(alternatives) < MAX_ALTERNATIVES:
                alternatives.append(
                    AlternativePose(
                        *entry.symmetry.canonical(other.rotation, other.translation), confidence=0.0
                    )
                )
        clock.lap("decide")

        # 8. Measure the fit of the winner on every observed point.
        error = alignment_error(scene, entry.point_tree, rotation, translation)
        clock.lap("measure")
        return Alignment(
            label=label,
            score=float(scores[winner.row]),
            rotation=rotation,
            translation=translation,
            alignment_error=error,
            alignment_error_normalized=error / entry.reference.scale,
            hypothesis=winner.source,
            candidates=search.candidate_fits(fits, scores),
            ambiguous=bool(alternatives),
            alternatives=alternatives,
            fit=winner.fit,
            coverage=winner.coverage,
            runner_up=0.0 if runner_up is None else runner_up.score,
            runner_up_label=runner_up_label,
            alike=alike,
            size_ratio=size / entry.reference.scale,
            points=len(scene),
        )

    def _nearest_views(
        self,
        snapshot: Snapshot,
        observed_grid: np.ndarray,
        size: float,
        allowed: np.ndarray,
        top_k: int | None,
    ) -> list[int]:
        """The rows of the parts whose rendered views look most like the observation (cosine
        of the grids' features, among views of a plausible size), best first."""
        settings = self.settings
        similarity = snapshot.view_keys @ view_features(observed_grid, settings.grid_blur)[0]
        low, high = settings.view_size_ratio
        ratio = size / np.maximum(snapshot.view_radii, 1e-12)
        usable = (ratio >= low) & (ratio <= high) & np.isin(snapshot.view_owner, allowed)
        similarity = np.where(usable, similarity, -np.inf)
        starts = np.flatnonzero(np.diff(snapshot.view_owner, prepend=-1))  # rows are in blocks
        best_per_row = np.maximum.reduceat(similarity, starts)
        count = top_k or settings.view_candidates
        return [int(r) for r in np.argsort(-best_per_row)[:count] if np.isfinite(best_per_row[r])]

    def _no_match_by_size(self, snapshot, allowed, observed, scores) -> Alignment:
        """The answer when no reference could give an observation of this size: no match, the
        reason naming the likely unit."""
        size, scales = radius(observed), snapshot.scales[allowed]
        ratio = size / scales
        reasons = self._size_reasons(scales, size, float(ratio[nearest_sized(ratio)]))
        return self._unanswered(snapshot, allowed, observed, scores, reasons)

    def _unanswered(self, snapshot, allowed, observed, scores, reasons) -> Alignment:
        """A no-match answer for these ``reasons``, and for diagnosis the nearest-sized
        reference placed at the observation's centroid."""
        ratio = radius(observed) / snapshot.scales[allowed]
        index = nearest_sized(ratio)
        row = int(allowed[index])
        label = snapshot.classifier.labels[row]
        entry = snapshot.entries[label]
        translation = observed.mean(axis=0) - entry.surface.points.mean(axis=0)
        error = alignment_error(observed, entry.point_tree, np.eye(3), translation)
        return Alignment(
            label=label,
            score=float(scores[row]),
            rotation=np.eye(3),
            translation=translation,
            alignment_error=error,
            alignment_error_normalized=error / entry.reference.scale,
            hypothesis="none",
            candidates=[],
            verdict="no_match",
            confidence=0.0,
            reasons=reasons,
            size_ratio=float(ratio[index]),
            points=len(observed),
        )

    def _size_reasons(self, scales: np.ndarray, size: float, nearest: float) -> list[str]:
        """Why no reference fits an observation of radius ``size`` (``nearest`` times the
        nearest reference's scale), and the unit it would fit a reference in, if one: a part
        in millimetres may be about as big as another registered in metres."""
        said = [size_reason(nearest)]
        hint = None if unit_ratio(nearest) else self._unit_hint(scales, size)
        return said + ([hint] if hint else [])

    def _unit_hint(self, scales: np.ndarray, size: float) -> str | None:
        """The reason naming the first unit in which an observation of radius ``size`` would
        be the size of one of these ``scales``; None if in none."""
        for factor in UNIT_FACTORS:
            if self._plausible(scales, size / factor, self.settings.size_ratio).any():
                return size_reason(factor, also=True)
        return None

    @staticmethod
    def _plausible(scales: np.ndarray, size: float, ratio: tuple[float, float]) -> np.ndarray:
        """Which references' scales could give an observation of this radius.

        The grid is scale-free, but a sensor measures sizes: a full view's radius is the
        reference's scale within a few per cent, a single camera's view 0.85-1.45 of it
        (measured on the evaluation's cases), so a size far outside that is another part.
        """
        low, high = ratio
        return (size >= low * scales) & (size <= high * scales)

    @staticmethod
    def _candidate_rows(snapshot: Snapshot, candidates: list[str] | None) -> np.ndarray:
        labels = snapshot.classifier.labels
        if not candidates:
            return np.arange(len(labels))
        unknown = [name for name in candidates if name not in snapshot.entries]
        if unknown:
            raise UnknownReference(f"unknown candidate reference(s): {', '.join(unknown)}")
        return np.array(sorted({labels.index(name) for name in candidates}))

    def self_check(
        self, reference: Reference, views: int = 3, mesh: trimesh.Trimesh | None = None
    ) -> list[dict]:
        """The new reference found again, as a cell would meet it: a resampled full cloud and
        ``views`` single-camera views of it, each in a random pose, against the whole gallery.
        They are independent of the registered points: a mesh is sampled anew; a cloud's points
        are jittered by a third of their spacing and a fifth of them dropped. A view is what a
        camera 6 scales away sees of that sample (the mesh's depth buffer, or hidden-point
        removal), and the camera's place is its viewpoint. Each check says what was answered
        and how far its rotation is from the truth, the part's symmetry accounted for."""
        rng = np.random.default_rng(self.settings.seed + 1)
        entry = Entry.of(reference, self.settings.grid_blur)
        points = np.asarray(reference.points, dtype=np.float64)
        if mesh is not None:
            sample = np.asarray(trimesh.sample.sample_surface(mesh, len(points), seed=7)[0])
            surface = np.asarray(
                trimesh.sample.sample_surface(mesh, self.settings.mesh_surface_points, seed=8)[0]
            )
        else:
            kept = rng.random(len(points)) >= 0.2
            sample = points[kept] + rng.normal(
                scale=entry.surface.spacing / 3, size=(kept.sum(), 3)
            )
            surface = None
        centroid = sample.mean(axis=0)
        renders: list[tuple[str, np.ndarray, np.ndarray | None]] = [("full", sample, None)]
        for direction in Rotation.random(views, random_state=rng).apply([0.0, 0.0, 1.0]):
            camera = centroid + direction * CAMERA_DISTANCE * reference.scale
            if surface is None:
                seen = visible_points(sample, camera)
            else:
                seen = splat_visible(sample, surface, camera, sample_spacing(surface, mesh.area))
            renders.append(("view", sample[seen], camera))
        checks = []
        for kind, cloud, camera in renders:
            rotation = Rotation.random(random_state=rng).as_matrix()
            translation = rng.uniform(-1, 1, 3) * reference.scale
            scene = cloud @ rotation.T + translation
            viewpoint = None if camera is None else rotation @ camera + translation
            result = self.align(scene, viewpoint=viewpoint)
            checks.append(
                {
                    "render": kind,
                    "label": result.label,
                    "label_ok": result.label == reference.name,
                    "rotation_error_deg": entry.symmetry.distance_deg(result.rotation, rotation),
                    "alignment_error_normalized": result.alignment_error_normalized,
                    "verdict": result.verdict,
                    "confidence": result.confidence,
                }
            )
        return checks


def nearest_sized(ratio: np.ndarray) -> int:
    """Which of these observed-size-over-scale ratios is nearest 1 (a ratio of 0, an
    observation at one place, is the smallest scale's)."""
    return int(np.argmin(np.abs(np.log(np.maximum(ratio, np.finfo(float).tiny)))))


def excellent(fits: list[Fit], settings: EngineSettings) -> bool:
    """Whether the best fit so far ends the search."""
    return any(f.score >= settings.excellent for f in fits)


UNIT_FACTORS = (1000.0, 0.001, 100.0, 0.01)  # millimetres, metres, centimetres, metres
POOR_FIT = 0.8  # an answer whose part holds less of the cloud may be a cloud in other units


def size_reason(factor: float, also: bool = False) -> str:
    """Why an observation of ``factor`` times the nearest reference's size matches nothing;
    with ``also``: it fitted no part of its own size, but ``factor`` times smaller (or larger)
    it would be a registered part's size."""
    named = unit_ratio(factor)
    if named is None:
        return (
            f"no registered part has this size: the cloud's radius is {factor:.2g} times the "
            "nearest reference's scale"
        )
    ratio, unit, other = named
    small, big = (unit, "metres") if ratio > 1 else ("metres", unit)
    if also:
        scaled = f"1/{factor:,.0f} of" if ratio > 1 else f"{1 / factor:,.0f} times"
        return (
            f"at {scaled} its size the cloud would be a registered part's size: it may "
            f"be in {small} while the references are in {big}; send {other}"
        )
    times = f"{factor:,.0f} times" if ratio > 1 else f"1/{1 / factor:,.0f} of"
    return (
        f"the cloud is {times} the size of the nearest reference: it is probably in "
        f"{small} while the references are in {big}; send {other}"
    )


def unit_ratio(factor: float) -> tuple[float, str, str] | None:
    """The unit ratio a size ``factor`` is near (within 2x): (ratio, the other unit, what to
    send); None when it is near none of millimetres, centimetres against metres."""
    for unit_factor, unit in ((1000.0, "millimetres"), (100.0, "centimetres")):
        for ratio, other in ((unit_factor, "metres"), (1 / unit_factor, unit)):
            if 0.5 * ratio <= factor <= 2 * ratio:
                return ratio, unit, other
    return None


EXPECTED = 128  # expected-visible points drawn per view for coverage
QUICK_POINTS = 24  # observed and expected points of the quick look that screens hypotheses
WHOLE_REFINED = 2  # hypotheses refined in each whole-part pass
# principal-axes hypotheses verified in the whole-part pass: as many as their four sign flips
# (the turns of a round section are alternatives to them, and each verified costs as one)
WHOLE_SCREENED = 4
ENOUGH_BEHIND = 0.8  # a hypothesis this far below an excellent refined one is not refined
FAR_BELOW = 0.5  # nor one below this share of the best hypothesis before refining
RESCUE_BELOW = 0.7  # "fits well" for settings.rescued_parts: fit x coverage
RESCUE_EACH = 2  # hypotheses refined of each rescued part
FIRST_REFINED = 1  # hypotheses of eq. (4)'s first choice refined in any case ...
FIRST_LEAD = 2.0  # ... when its score is this many times the next part's


def sure_first(scores: np.ndarray, ranked: np.ndarray) -> int | None:
    """Eq. (4)'s first choice among the ``ranked`` rows (best first) when it is sure of it (its
    score ``FIRST_LEAD`` times the next one's), else None. Full clouds mostly: eq. (4) learned
    the parts' full views, and on one camera's view its scores lie close together."""
    if not len(ranked):
        return None
    runner_up = float(scores[ranked[1]]) if len(ranked) > 1 else 0.0
    return int(ranked[0]) if scores[ranked[0]] >= FIRST_LEAD * runner_up else None


class Search:
    """Steps 4-6 for one query: hypothesise, verify, refine, for a set of candidates."""

    def __init__(self, engine, snapshot, observed, observed_mapped, spacing, query, clock):
        settings = engine.settings
        self.settings = settings
        self.snapshot = snapshot
        self.labels = snapshot.classifier.labels
        self.observed = observed
        self.observed_mapped = observed_mapped
        self.viewpoint = query.viewpoint
        self.rng = rng = query.rng
        self.clock = clock
        self.frame = Frame.of(observed)  # what every principal-axes and view hypothesis uses
        self.quick = observed[subsample(observed, QUICK_POINTS, rng)]
        self.cheap = observed[subsample(observed, settings.verify_points, rng)]
        self.refine_on = observed[subsample(observed, settings.icp_points, rng)]
        # "is an observed point near here", at the tolerance or the observation's own spacing
        self.occupancy = Occupancy.around(observed, settings.tolerance * radius(observed), spacing)

    def run(
        self,
        planned: dict[int, list[str]],
        refine: bool,
        budget: int,
        first: int | None = None,
        rescue: bool = False,
        screened: int | None = None,
    ) -> list[Fit]:
        """Verified fits of every candidate row from its planned sources (the ``screened``
        best of a quick look where it made more: ``settings.screened`` unless given); the best
        ``budget`` refined, and the best of row ``first`` (eq. (4)'s first choice) in any case,
        and with ``rescue`` more parts' when none fits well. Returns each row's best fit, and
        every refined one."""
        settings = self.settings
        keep = screened or settings.screened
        fits: list[Fit] = []
        for row, chosen in planned.items():
            entry = self.snapshot.entries[self.labels[row]]
            made = self.hypothesise(entry, chosen)
            self.clock.lap("hypothesise")
            if len(made) > keep:  # a quick look first, on a few points
                made = made.take(self.screen(entry, made)[:keep])
            if len(made):
                fits += self.verify(row, entry, made)
            self.clock.lap("verify")
        if not fits:
            return []
        fits.sort(key=lambda f: -f.score)
        if refine:
            self.refine_best_first(fits, budget, first, rescue)
            self.clock.lap("refine")
        best: dict[int, Fit] = {}
        # a row's best is its best refined fit where it has one: an unrefined fit's score is
        # measured on the cheap sample, and one lucky there (a flange turned 55 degrees, 0.97
        # on 64 points) would otherwise win unrefined, past the near-symmetries and the polish
        for candidate in sorted(fits, key=lambda f: (not f.refined, -f.score)):
            best.setdefault(candidate.row, candidate)
        return list(best.values()) + [f for f in fits if f.refined and best[f.row] is not f]

    def screen(self, entry: Entry, made: Hypotheses) -> np.ndarray:
        """Hypotheses ordered by a quick fit x coverage on a few points, best first."""
        tolerance = self.settings.tolerance * entry.reference.scale
        fits_ = fit(
            entry.surface,
            self.quick,
            made.rotations,
            made.translations,
            tolerance,
            lookup="field",
        )
        expected = self.expected(entry, made, QUICK_POINTS)
        covered = coverage(expected, made.rotations, made.translations, self.occupancy)
        return np.argsort(-(fits_ * covered), kind="stable")

    def refine_best_first(
        self, fits: list[Fit], budget: int, first: int | None = None, rescue: bool = False
    ) -> None:
        """Refine the best ``budget`` hypotheses (at most two a candidate), best first, leaving
        out those far below the best before refining; stop once one is excellent and the next
        looks clearly worse than it. With ``rescue`` (the single-view pass), if none then fits
        well (``RESCUE_BELOW``), the best two hypotheses of each next part (up to
        ``settings.rescued_parts`` parts) are refined too, until one does: a part's right pose
        may verify worse than another part's before refinement (a single view seen from an
        unlucky side), and a part told alone then finds it. Not in the whole-part pass, whose
        candidates are eq. (4)'s own few: there a rescued part that fits as poorly as the
        first choice's refined pose only takes its place (a full cloud of random-125)."""
        settings = self.settings
        per_row: dict[int, int] = {}
        refined: list[Fit] = []
        floor = FAR_BELOW * fits[0].score  # sorted, best first
        for candidate in fits:
            if len(refined) == budget or candidate.score < floor:
                break
            if per_row.get(candidate.row, 0) == 2:
                continue
            best = max((f.score for f in refined), default=0.0)
            if best >= settings.excellent and candidate.score < ENOUGH_BEHIND * best:
                break
            per_row[candidate.row] = per_row.get(candidate.row, 0) + 1
            self.refine(candidate)
            refined.append(candidate)
        if first is not None and first not in per_row:
            # the part eq. (4) likes best, left out because another part's pose verified
            # better before refining: its best pose is refined too, in this pass's sources.
            # Two parts of nearly one shape (under noise) are told apart by the right one's
            # refined pose, which then fits better than the wrong one's (both noisy clouds of
            # random-250: one needed the principal axes' pose, the other a rendered view's)
            for mine in [f for f in fits if f.row == first][:FIRST_REFINED]:
                per_row[first] = per_row.get(first, 0) + 1
                self.refine(mine)
                refined.append(mine)
        if not rescue or not settings.rescued_parts:
            return
        best = max((f.score for f in refined), default=0.0)
        rescued: dict[int, int] = {}
        tried: list[Fit] = []
        for candidate in fits:  # nothing fits well: each next part's best get their chance
            if best >= RESCUE_BELOW:
                break
            if candidate.row in per_row or rescued.get(candidate.row, 0) == RESCUE_EACH:
                continue
            if candidate.row not in rescued and len(rescued) == settings.rescued_parts:
                continue
            rescued[candidate.row] = rescued.get(candidate.row, 0) + 1
            self.refine(candidate, iterations=max(1, settings.icp_iterations // 2))
            tried.append(candidate)
            best = max(best, candidate.score)
        # a rescued pose was refined on half the budget; the one that now fits best gets the
        # rest, if it beats every fully refined one
        winner = max(tried, key=lambda f: f.score, default=None)
        if winner is not None and winner.score > max((f.score for f in refined), default=0.0):
            self.refine(winner)

    def hypothesise(self, entry: Entry, chosen: list[str]) -> Hypotheses:
        settings = self.settings
        reference = entry.reference
        made = []
        if "views" in chosen:
            every = np.arange(len(entry.views.radii))
            made.append(sources.from_views(self.frame, entry.views, every, self.viewpoint))
        if "principal-axes" in chosen:
            made.append(sources.from_principal_axes(self.frame, entry.frame))
        if "mapped" in chosen or "paper" in chosen:
            made.append(
                sources.from_mapped_pairs(
                    tuple(chosen),
                    self.observed,
                    self.observed_mapped,
                    entry.surface.points,
                    entry.mapped_tree,
                    settings.ransac_threshold * reference.scale,
                    settings.ransac_iterations,
                    self.rng,
                )
            )
        return Hypotheses.join(made)

    def expected(self, entry: Entry, made: Hypotheses, count: int) -> np.ndarray:
        """(H, count, 3) reference points each hypothesis expects the camera to see: of the
        view the viewpoint implies at its pose, else of its own view (-1: all points)."""
        views = made.views
        if self.viewpoint is not None:
            toward = self.viewpoint[None] - made.translations
            implied = np.einsum("hij,hi->hj", made.rotations, toward)  # R^T v, model frame
            views = entry.views.nearest(implied)
        return entry.surface.points[entry.expected[views, :count]]

    def verify(self, row: int, entry: Entry, made: Hypotheses, count: int | None = None):
        settings = self.settings
        scale = entry.reference.scale
        tolerance = settings.tolerance * scale
        observed = self.cheap if count is None else self.refine_on
        fits_ = fit(
            entry.surface,
            observed,
            made.rotations,
            made.translations,
            tolerance,
            # the cheap check of many poses to the nearest sample; the refined one, whose fit
            # the confidence weighs, to the facing one (measured against the nearest sample:
            # 4 more right answers accepted of 216 depth views, 2 of 108 tables, 4 of 432 full
            # clouds; never told the viewpoint, 3 and 4 more)
            "nearest" if count is None else "facing",
        )
        expected = self.expected(entry, made, count or settings.coverage_points)
        covered = coverage(expected, made.rotations, made.translations, self.occupancy)
        return [
            Fit(
                row,
                made.rotations[h],
                made.translations[h],
                made.sources[h],
                int(made.views[h]),
                float(fits_[h]),
                float(covered[h]),
            )
            for h in range(len(made))
        ]

    def refine(self, candidate: Fit, iterations: int | None = None) -> None:
        """Point-to-plane ICP from the fit's pose (``iterations``: the setting's unless
        given), then verified again on more points."""
        entry = self.snapshot.entries[self.labels[candidate.row]]
        rotation, translation = self.icp(candidate, iterations or self.settings.icp_iterations)
        made = Hypotheses(
            rotation[None], translation[None], (candidate.source,), np.array([candidate.view])
        )
        (checked,) = self.verify(candidate.row, entry, made, count=EXPECTED)
        candidate.rotation, candidate.translation = rotation, translation
        candidate.fit, candidate.coverage, candidate.refined = checked.fit, checked.coverage, True

    def icp(
        self, candidate: Fit, iterations: int, points: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The fit's pose refined by point-to-plane ICP on ``points`` (the refinement's sample
        unless given); ``candidate.settled`` says whether it stopped before ``iterations``."""
        settings = self.settings
        entry = self.snapshot.entries[self.labels[candidate.row]]
        scale = entry.reference.scale
        rotation, translation, done = icp(
            self.refine_on if points is None else points,
            entry.surface,
            candidate.rotation,
            candidate.translation,
            noise=0.25 * settings.tolerance * scale,
            gate=5 * settings.tolerance * scale,
            iterations=iterations,
        )
        candidate.settled = done < iterations
        return rotation, translation

    def polish(self, winner: Fit) -> bool:
        """Finish the winner's pose where the search's budget cut its refinement short: up to
        ``polish_iterations`` more, on the network's sample of the observation (the search
        refines on a smaller one of ``icp_points``, whose own scatter limits the pose). Only
        the pose changes: its fit and coverage stay the search's, which the confidence was
        calibrated on (measured again at the finished pose, they let a foreign part's view
        past the threshold). Whether it ran."""
        extra = self.settings.polish_iterations
        if not extra or not winner.refined or winner.settled:
            return False
        winner.rotation, winner.translation = self.icp(winner, extra, self.observed)
        return True

    def flip(self, fits: list[Fit]) -> list[Fit]:
        """``fits`` (best first) with the best pose turned half a turn about each of its part's
        principal axes (through the part's centroid, in the model frame), each refined, first
        where one fits better; unless the best fits excellently, or is unrefined. A pose from
        principal frames is matched up to their axes' signs, and one in the wrong sign
        refines into its own minimum: of the evaluation's depth views and views on a table,
        28 answers fitted clearly worse than the truth (60-93 % of the points against
        96-100 %), most turned about half a turn from it (README, "Flips")."""
        best = fits[0]
        if not best.refined or best.score >= self.settings.excellent:
            return fits
        entry = self.snapshot.entries[self.labels[best.row]]
        turns = entry.frame.half_turns
        centre = entry.frame.centroid  # scene = R (T (m - c) + c) + t
        rotations = np.einsum("ij,njk->nik", best.rotation, turns)
        translations = best.translation + (centre - turns @ centre) @ best.rotation.T
        views = entry.views.turned(best.view, turns)
        flipped = []
        for k in range(len(turns)):
            if entry.symmetry.distance_deg(rotations[k], best.rotation) <= DIFFERENT_DEG:
                continue  # the same pose: a symmetry of the part
            candidate = Fit(best.row, rotations[k], translations[k], FLIP_SOURCE, views[k], 0, 0)
            self.refine(candidate)
            flipped.append(candidate)
        top = max(flipped, key=lambda f: f.score, default=None)
        return fits if top is None or top.score <= best.score else [top, *fits]

    def resolve_near(self, fits: list[Fit], repeat: bool = True) -> list[Fit]:
        """``fits`` (best first) with the best pose tried turned by each near-symmetry of its
        part (about the part's centre, in the model frame), each refined: a notch or a cross
        hole may be all that tells those poses apart, too little to move fit x coverage. Of
        the poses that fit alike, the one whose points lie closest to the surface (the mean
        distance, cut at three tolerances) goes first; those as close as it (within
        ``RESIDUAL_ALIKE``) stay as alternatives, the clearly farther ones go. Where a pose
        turned end for end goes first, its own turns are tried once more (``repeat``): the
        flip was found at some turn about the axis, its cross hole's perhaps elsewhere."""
        best = fits[0]
        entry = self.snapshot.entries[self.labels[best.row]]
        symmetry = entry.symmetry
        if not best.refined or not len(symmetry.near) or not self.settings.near_refined:
            return fits
        centre = symmetry.centroid  # scene = R (N (m - c) + c) + t
        turns = symmetry.near_tried
        rotations = np.einsum("ij,njk->nik", best.rotation, turns)
        translations = best.translation + (centre - turns @ centre) @ best.rotation.T
        # without a viewpoint, coverage is measured against the view each turned pose expects:
        # the unturned pose's would judge a flange turned by half a turn by its hidden side
        views = entry.views.turned(best.view, turns)
        # screened first: the few turned poses nearest the surface are refined, unless even
        # they lie clearly farther from it than the best; each kind on its own (a nearly
        # round part's turns about its axis, and its flips end for end), as the many turns
        # about the axis, alike all round, would crowd out a flip
        screened = self.residuals(entry, rotations, translations, lookup="field")
        (own,) = self.residuals(entry, best.rotation[None], best.translation[None], lookup="field")
        order = np.argsort(screened)
        order = order[screened[order] <= SCREEN_ALIKE * own]
        reversing = symmetry.near_reversing
        kinds = [order[~reversing[order]], order[reversing[order]]]
        kinds = [self.screen_near(entry, kind, rotations, translations, turns) for kind in kinds]
        # then nearest on the network's sample (a notch or a cross hole is a few of them): the
        # nearest of each kind refined first, then the nearest others
        order = np.concatenate(kinds)
        again = self.residuals(entry, rotations[order], translations[order], self.observed)
        order = order[np.argsort(again, kind="stable")]
        firsts = np.concatenate([order[reversing[order] == flip][:1] for flip in (False, True)])
        order = np.concatenate([firsts, order[~np.isin(order, firsts)]])
        order = order[: self.settings.near_refined]
        turned = []
        for k in order:
            candidate = Fit(best.row, rotations[k], translations[k], NEAR_SOURCE, views[k], 0, 0)
            self.refine(candidate)
            turned.append(candidate)
        alike = [best] + [t for t in turned if t.score >= ALIKE * best.score]
        if len(alike) == 1:
            return fits
        # told apart on the network's sample: a notch is a few of its points
        residuals = self.residuals(
            entry,
            np.stack([t.rotation for t in alike]),
            np.stack([t.translation for t in alike]),
            self.observed,
        ).tolist()
        chosen = int(np.argmin(residuals))
        close = [
            f
            for f, r in zip(alike, residuals, strict=True)
            if f is not alike[chosen] and r <= RESIDUAL_ALIKE * residuals[chosen]
        ]
        answer = [alike[chosen], *close, *fits[1:]]
        flipped = [t for t, k in zip(turned, order, strict=True) if reversing[k]]
        if repeat and any(alike[chosen] is t for t in flipped):
            return self.resolve_near(answer, repeat=False)
        return answer

    def screen_near(
        self,
        entry: Entry,
        order: np.ndarray,
        rotations: np.ndarray,
        translations: np.ndarray,
        turns: np.ndarray,
    ) -> np.ndarray:
        """Of the turned poses ``order`` (nearest the surface first, on the distance field's
        own answer), the ``NEAR_SCREENED`` nearest on the corrected distance, no two a fine
        turn of each other (several of one would crowd out the others). The field's own
        answer is an eighth of the time but blind to a cross hole: it keeps
        ``NEAR_PRESCREENED`` of them."""
        order = order[:NEAR_PRESCREENED]
        closer = self.residuals(entry, rotations[order], translations[order])
        order = order[np.argsort(closer, kind="stable")]
        return order[apart(turns[order], 2 * FINE_DEG, NEAR_SCREENED)]

    def residuals(
        self,
        entry: Entry,
        rotations: np.ndarray,
        translations: np.ndarray,
        points: np.ndarray | None = None,
        lookup: Lookup = "nearest",
    ):
        """(H,) mean distance of ``points`` (the refinement's unless given) to the surface at
        each of H poses, each cut at three tolerances, over the part's scale, to the nearest
        samples (``lookup``; the field's own answer, a fifth of the time, for screening)."""
        scale = entry.reference.scale
        points = self.refine_on if points is None else points
        model = np.matmul(points[None] - translations[:, None], rotations)
        distance, _ = surface_distance(entry.surface, model, lookup)
        return np.minimum(distance, 3 * self.settings.tolerance * scale).mean(axis=1) / scale

    def candidate_fits(self, fits: list[Fit], scores: np.ndarray) -> list[CandidateFit]:
        """One line a candidate, best first: its best pose's mean distance from the observed
        points to the reference's surface samples (on the cheap subsample)."""
        out: dict[int, CandidateFit] = {}
        for candidate in sorted(fits, key=lambda f: -f.score):
            if candidate.row in out:
                continue
            entry = self.snapshot.entries[self.labels[candidate.row]]
            model = (self.cheap - candidate.translation) @ candidate.rotation
            nearest = entry.surface.field.lookup(model)
            error = float(np.linalg.norm(model - entry.surface.points[nearest], axis=1).mean())
            out[candidate.row] = CandidateFit(
                self.labels[candidate.row],
                float(scores[candidate.row]),
                error,
                error / entry.reference.scale,
                candidate.source,
            )
        return list(out.values())
