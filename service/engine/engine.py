"""The engine: recognise a registered object in a cloud and estimate its pose.

``Engine.align`` is the paper's chain, one step per line: normalise -> map to 2-D
(ONNX) -> grid -> classify -> hypothesise poses from mapped pairs and principal
axes -> verify by the alignment error -> refine with ICP -> measure the fit.
The gallery is an immutable snapshot swapped whole on every change, so any
number of threads may align while one registers or removes a reference.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from service.engine.alignment import alignment_error
from service.engine.classifier import LinearClassifier, classifier_input, view_gram
from service.engine.grid import grid
from service.engine.hypotheses import Hypothesis, hypothesise
from service.engine.icp import icp
from service.engine.mapping import Mapper
from service.engine.normalize import normalize, radius, subsample
from service.engine.reference import Reference
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


@dataclass(frozen=True)
class Entry:
    """A reference with the search trees built once at registration or load."""

    reference: Reference
    point_tree: cKDTree
    mapped_tree: cKDTree
    view_features: np.ndarray  # the classifier's input for each view grid

    @classmethod
    def of(cls, reference: Reference, blur: float) -> Entry:
        return cls(
            reference,
            cKDTree(reference.points),
            cKDTree(reference.mapped),
            classifier_input(reference.view_grids, blur),
        )


@dataclass(frozen=True)
class Snapshot:
    entries: dict[str, Entry]
    classifier: LinearClassifier | None
    scales: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per classifier row
    gram: np.ndarray | None = None  # view_gram of every entry's view features, kept by sums


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
    def __init__(self, mapper: Mapper, settings: EngineSettings | None = None):
        self.mapper = mapper
        self.settings = settings or EngineSettings()
        self._snapshot = Snapshot({}, None)
        self._write_lock = threading.Lock()

    # --- the gallery -------------------------------------------------------------

    def make_reference(self, name: str, points: np.ndarray, seed: int | None = None) -> Reference:
        """Compute what the engine needs of a new object: mapped points, view grids, scale."""
        points = np.asarray(points, dtype=np.float32)
        mapped = self.map(points)
        rng = np.random.default_rng(self.settings.seed if seed is None else seed)
        views = [self.view_grid(points, rng) for _ in range(self.settings.view_grids)]
        return Reference(name, points, mapped, np.stack(views), radius(points))

    def view_grid(self, points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The grid of an augmented view: a random pose, a single camera's view with
        probability ``partial_views``, and 10-100 % of the remaining points kept."""
        if rng.random() < self.settings.partial_views:
            points = points[visible_points(points, random_camera(points, 3.0, rng))]
        count = min(len(points), self.settings.network_points)
        keep = max(16, int(count * rng.uniform(0.1, 1.0)))
        view = points[subsample(points, keep, rng)] @ Rotation.random(random_state=rng).as_matrix()
        return grid(self.map(view))

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
        scales = np.array([entry.reference.scale for entry in entries.values()])
        self._snapshot = Snapshot(entries, classifier, scales, gram)

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

    # --- the chain ---------------------------------------------------------------

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
        allowed = self._candidate_rows(snapshot, candidates)
        rng = np.random.default_rng(settings.seed)
        clock = Stopwatch()
        scene = np.asarray(points, dtype=np.float64)

        # 1. Normalise: subsample to the network's size (centring, scaling in map()).
        observed = scene[subsample(scene, settings.network_points, rng)]
        clock.lap("normalize")
        # 2. Map every point to 2-D with the network.
        observed_mapped = self.map(observed)
        clock.lap("map")
        # 3. Grid and classify (eq. 4) among the references of a plausible size; keep top_k.
        scores = snapshot.classifier.scores(grid(observed_mapped))
        allowed = self._plausible_size(snapshot, allowed, radius(scene))
        ranked = allowed[np.argsort(-scores[allowed], kind="stable")]
        shortlist = ranked[: top_k or settings.top_k]
        clock.lap("classify")

        verify = observed[subsample(observed, settings.verify_points, rng)]
        refine_on = observed[subsample(observed, settings.icp_points, rng)]
        labels = snapshot.classifier.labels
        fits: list[tuple[float, str, Hypothesis]] = []
        for row in shortlist:
            entry = snapshot.entries[labels[row]]
            # 4. Hypothesise poses: mapped pairs (RANSAC), principal axes, the paper's solver.
            poses = hypothesise(
                hypotheses or settings.hypotheses,
                observed,
                observed_mapped,
                entry.reference.points,
                entry.mapped_tree,
                settings.ransac_threshold * entry.reference.scale,
                settings.ransac_iterations,
                rng,
            )
            clock.lap("hypothesise")
            # 5. Verify each cheaply: the alignment error on a small subsample.
            for pose in poses:
                error = alignment_error(verify, entry.point_tree, pose.rotation, pose.translation)
                fits.append((error, labels[row], pose))
            clock.lap("verify")

        # 6. Refine the best few hypotheses of all candidates with ICP; the best fit wins.
        fits.sort(key=lambda fit: fit[0])
        if refine:
            for index, (_, label, pose) in enumerate(fits[: settings.refine_best]):
                entry = snapshot.entries[label]
                rotation, translation = icp(
                    refine_on,
                    entry.reference.points,
                    entry.point_tree,
                    pose.rotation,
                    pose.translation,
                    settings.icp_iterations,
                )
                error = alignment_error(verify, entry.point_tree, rotation, translation)
                fits[index] = (error, label, Hypothesis(rotation, translation, pose.source))
            fits.sort(key=lambda fit: fit[0])
        clock.lap("refine")
        best = fits[0]

        # 7. Measure the fit of the winner on every observed point.
        _, label, winner = best
        winner_entry = snapshot.entries[label]
        error = alignment_error(scene, winner_entry.point_tree, winner.rotation, winner.translation)
        clock.lap("measure")
        scale = winner_entry.reference.scale
        per_label: dict[str, CandidateFit] = {}
        for fit_error, fit_label, hypothesis in fits:  # sorted: the first per label is its best
            if fit_label not in per_label:
                per_label[fit_label] = CandidateFit(
                    fit_label,
                    float(scores[labels.index(fit_label)]),
                    fit_error,
                    fit_error / snapshot.entries[fit_label].reference.scale,
                    hypothesis.source,
                )
        return Alignment(
            label=label,
            score=float(scores[labels.index(label)]),
            rotation=winner.rotation,
            translation=winner.translation,
            alignment_error=error,
            alignment_error_normalized=error / scale,
            hypothesis=winner.source,
            candidates=list(per_label.values()),
            timings_ms=clock.total(),
        )

    @staticmethod
    def _candidate_rows(snapshot: Snapshot, candidates: list[str] | None) -> np.ndarray:
        labels = snapshot.classifier.labels
        if not candidates:
            return np.arange(len(labels))
        unknown = [name for name in candidates if name not in snapshot.entries]
        if unknown:
            raise UnknownReference(f"unknown candidate reference(s): {', '.join(unknown)}")
        return np.array(sorted({labels.index(name) for name in candidates}))

    def _plausible_size(self, snapshot: Snapshot, rows: np.ndarray, observed: float) -> np.ndarray:
        """The rows whose scale could give an observation of this radius (all if none can).

        The grid is scale-free, but a sensor measures sizes: a full view's radius is the
        reference's scale within a few per cent, a single camera's view 0.85-1.45 of it
        (measured on the evaluation's cases), so a size far outside that is another part.
        """
        low, high = self.settings.size_ratio
        scales = snapshot.scales[rows]
        plausible = rows[(observed >= low * scales) & (observed <= high * scales)]
        return plausible if len(plausible) else rows

    def self_check(self, reference: Reference, poses: int = 3) -> list[dict]:
        """Align the reference against a few random poses of itself, as an operator would."""
        rng = np.random.default_rng(self.settings.seed + 1)
        checks = []
        for _ in range(poses):
            rotation = Rotation.random(random_state=rng).as_matrix()
            translation = rng.uniform(-1, 1, 3) * reference.scale
            chosen = subsample(reference.points, self.settings.network_points, rng)
            scene = reference.points[chosen] @ rotation.T + translation
            result = self.align(scene)
            error = np.clip((np.trace(result.rotation.T @ rotation) - 1) / 2, -1, 1)
            checks.append(
                {
                    "label_ok": result.label == reference.name,
                    "rotation_error_deg": float(np.degrees(np.arccos(error))),
                    "alignment_error_normalized": result.alignment_error_normalized,
                }
            )
        return checks
