"""The engine: recognise a registered object in a cloud and estimate its pose.

``Engine.align`` is the paper's chain, one step a block: normalise -> map to 2-D (ONNX) ->
grid -> classify (eq. 4, and the rendered views whose grids look most alike) -> hypothesise
poses -> verify (fit x coverage) -> refine (point-to-plane ICP) -> decide -> measure the fit.
It runs in two passes: first the whole part (eq. 4's candidates, whole-reference hypotheses),
which a full 360-degree cloud passes at once; then, unless that found an excellent fit, single
views (the candidates and view hypotheses the rendered views propose), which is what a depth
camera posts. The gallery is an immutable snapshot swapped whole on every change, so any
number of threads may align while one registers or removes a reference.

Steps 4-6 for one query (hypothesise, verify, refine; the best pose's flips, near-symmetries
and finishing) are ``search.Search``; a reference's derived state and the gallery's snapshot
``entry``; the answer's types ``answer``; the reasons an observation's size gives ``units``.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from service.engine import confidence
from service.engine.alignment import alignment_error
from service.engine.answer import Alignment, AlternativePose
from service.engine.classifier import LinearClassifier, view_features, view_gram
from service.engine.confidence import Calibration
from service.engine.distance_field import DistanceField
from service.engine.entry import Entry, Snapshot, stored_surface
from service.engine.grid import grid
from service.engine.icp import Surface
from service.engine.mapping import Mapper
from service.engine.normalize import has_extent, normalize, radius, subsample
from service.engine.normals import estimate_normals, mesh_normals, orient_by_views
from service.engine.principal_axes import flatness
from service.engine.reference import Reference
from service.engine.search import (
    ALIKE,
    DIFFERENT_DEG,
    MAX_ALTERNATIVES,
    RIGHT_EITHER_WAY,
    WHOLE_REFINED,
    WHOLE_SCREENED,
    Search,
    excellent,
    sure_first,
)
from service.engine.surroundings import set_aside_surroundings
from service.engine.symmetry import find_symmetry
from service.engine.units import POOR_FIT, UNIT_FACTORS, nearest_sized, size_reason, unit_ratio
from service.engine.views import (
    camera_at,
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


VIEW_POINTS = 512  # a rendered view's grid is made of at most this many of its points
SELF_CHECK_THREADS = 2  # renders of the registration check aligned at once
FLAT = 0.03  # an observation this flat (smallest over largest principal spread) is one face


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
        self.refits = 0  # how many times the classifier was refitted (one a change, or a batch)

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
        normals, rendered views, distance field and symmetry.

        The network's share (the points, the augmented views, then the rendered views) runs in
        a thread of its own beside the geometry (onnxruntime lets go of the GIL while it runs);
        each view's randomness is drawn first, in the order one thread drew it, so the
        reference is the same bit for bit (docs/operations.md, "Registration time")."""
        points = np.asarray(points, dtype=np.float32)
        rng = np.random.default_rng(self.settings.seed if seed is None else seed)
        augmented = [self.augmented_view(points, rng) for _ in range(self.settings.view_grids)]
        scale = radius(points)
        with ThreadPoolExecutor(1, thread_name_prefix="network") as network:
            mapped = network.submit(self.map, points, True)
            grids = network.submit(self._grids, augmented)
            derived = self._derive(points, scale, mesh, face_index, network)
            reference = Reference(name, points, mapped.result(), grids.result(), scale)
        return reference.with_(**derived)

    def complete(
        self,
        reference: Reference,
        mesh: trimesh.Trimesh | None = None,
        face_index: np.ndarray | None = None,
    ) -> Reference:
        """The reference with every derived field computed (those it lacks, or all of them
        when a mesh is given): normals, views, distance field, symmetry."""
        if mesh is None and not reference.missing:
            return reference
        with ThreadPoolExecutor(1, thread_name_prefix="network") as network:
            derived = self._derive(reference.points, reference.scale, mesh, face_index, network)
        return reference.with_(**derived)

    def _derive(
        self,
        points: np.ndarray,
        scale: float,
        mesh: trimesh.Trimesh | None,
        face_index: np.ndarray | None,
        network: ThreadPoolExecutor,
    ) -> dict:
        """The derived fields of a reference of these points and scale; the rendered views'
        grids are mapped on ``network`` while this thread finds the symmetry."""
        settings = self.settings
        points = np.asarray(points, dtype=np.float64)
        tree = cKDTree(points)
        if mesh is not None:  # the views see the mesh's own surface; normals are its faces'
            surface = np.asarray(
                trimesh.sample.sample_surface(
                    mesh, settings.mesh_surface_points, seed=settings.seed + 1
                )[0]
            )
            visible = render(points, scale, settings.views, surface, mesh.area)
            normals = mesh_normals(mesh, face_index, points, directions(settings.views), visible)
        else:
            visible = render(points, scale, settings.views, tree=tree)
            normals = estimate_normals(points, tree=tree)
            normals = orient_by_views(points, normals, directions(settings.views), visible)
        if mesh is None:  # a cloud's own buffer lets through what its camera hardly samples;
            # a view left facing nothing (a few points, normals at odds) keeps what it showed
            faced = visible & facing(points, normals, scale, settings.views)
            visible = np.where(faced.any(axis=1, keepdims=True), faced, visible)
        seen = [points[shown][:VIEW_POINTS] for shown in visible]
        grids = network.submit(self._grids, seen)
        distance_field = DistanceField.of(points, scale, tree=tree)
        surface_model = Surface.of(points, normals, distance_field, tree)
        symmetry = find_symmetry(surface_model, scale, np.random.default_rng(0))
        return {
            "normals": normals.astype(np.float32),
            "visibility": np.packbits(visible, axis=1),
            "view_features": view_features(grids.result(), settings.grid_blur).astype(np.float16),
            "field": distance_field.nearest,
            "field_frame": np.array([*distance_field.origin, distance_field.voxel]),
            "symmetry": symmetry.describe(),
        }

    def _grids(self, clouds: list[np.ndarray]) -> np.ndarray:
        """(V, 64, 64) the grids of these clouds' mapped points (on the quiet session)."""
        return np.stack([grid(self.map(cloud, quiet=True)) for cloud in clouds])

    def refind_symmetry(self, reference: Reference) -> Reference:
        """The reference with its symmetry found again by this version's rule, from its stored
        surface (points, normals, distance field), every other field as it was."""
        surface = stored_surface(reference)
        symmetry = find_symmetry(surface, reference.scale, np.random.default_rng(0))
        return reference.with_(symmetry=symmetry.describe())

    def view_grid(self, points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The grid of an augmented view (``augmented_view``)."""
        return grid(self.map(self.augmented_view(points, rng)))

    def augmented_view(self, points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """An augmented view of the points: a random pose, a single camera's view with
        probability ``partial_views``, and 10-100 % of the remaining points kept."""
        if rng.random() < self.settings.partial_views:
            points = points[visible_points(points, random_camera(points, 3.0, rng))]
        count = min(len(points), self.settings.network_points)
        keep = max(16, int(count * rng.uniform(0.1, 1.0)))
        return points[subsample(points, keep, rng)] @ Rotation.random(random_state=rng).as_matrix()

    # --- the gallery ------------------------------------------------------------------

    def load(self, references: list[Reference]) -> None:
        entries = {r.name: Entry.of(r, self.settings.grid_blur) for r in references}
        with self._write_lock:
            gram = view_gram([e.view_features for e in entries.values()]) if entries else None
            self._publish(entries, gram)

    def add(self, reference: Reference) -> None:
        """Add a reference, or replace the one of its name."""
        self.add_many([reference])

    def add_many(self, references: list[Reference]) -> None:
        """Add references (or replace those of their names) with one refit of the classifier."""
        if not references:
            return
        entries_added = {r.name: Entry.of(r, self.settings.grid_blur) for r in references}
        # their views' part of the Gram, off the lock
        share = view_gram([entry.view_features for entry in entries_added.values()])
        with self._write_lock:
            entries, gram = self._snapshot.entries, self._snapshot.gram
            gram = share if gram is None else gram + share
            replaced = [entries[name] for name in entries_added if name in entries]
            if replaced:
                gram -= view_gram([previous.view_features for previous in replaced])
            self._publish({**entries, **entries_added}, gram)

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
        self.refits += 1
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

    def map(self, points: np.ndarray, quiet: bool = False) -> np.ndarray:
        """Normalise a cloud as training did and map it to 2-D (``quiet``: ``Mapper.map``'s)."""
        return self.mapper.map(normalize(points, self.mapper.canonical).points, quiet)

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
            return self._unanswered(snapshot, allowed, observed, scores)

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

    def _unanswered(self, snapshot, allowed, observed, scores, reasons=None) -> Alignment:
        """A no-match answer for these ``reasons`` (by default: no reference could give an
        observation of this size, naming the likely unit), and for diagnosis the nearest-sized
        reference placed at the observation's centroid."""
        size, scales = radius(observed), snapshot.scales[allowed]
        ratio = size / scales
        index = nearest_sized(ratio)
        if reasons is None:
            reasons = self._size_reasons(scales, size, float(ratio[index]))
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
        entry = self._snapshot.entries.get(reference.name)
        if entry is None or entry.reference is not reference:  # not the one the gallery holds
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
            camera = camera_at(centroid, direction, reference.scale)
            if surface is None:
                seen = visible_points(sample, camera)
            else:
                seen = splat_visible(sample, surface, camera, sample_spacing(surface, mesh.area))
            renders.append(("view", sample[seen], camera))
        # every pose drawn first, in the order one thread drew them; the renders are then
        # aligned two at a time (their numpy, cKDTree and onnxruntime steps let go of the GIL)
        poses = [
            (Rotation.random(random_state=rng).as_matrix(), rng.uniform(-1, 1, 3) * reference.scale)
            for _ in renders
        ]

        def check(render: tuple[str, np.ndarray, np.ndarray | None], pose) -> dict:
            (kind, cloud, camera), (rotation, translation) = render, pose
            scene = cloud @ rotation.T + translation
            viewpoint = None if camera is None else rotation @ camera + translation
            result = self.align(scene, viewpoint=viewpoint)
            return {
                "render": kind,
                "label": result.label,
                "label_ok": result.label == reference.name,
                "rotation_error_deg": entry.symmetry.distance_deg(result.rotation, rotation),
                "alignment_error_normalized": result.alignment_error_normalized,
                "verdict": result.verdict,
                "confidence": result.confidence,
            }

        with ThreadPoolExecutor(SELF_CHECK_THREADS, thread_name_prefix="self-check") as pool:
            return list(pool.map(check, renders, poses))
