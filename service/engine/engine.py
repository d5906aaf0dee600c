"""The engine: recognise a registered object in a cloud and estimate its pose.

``Engine.align`` is the paper's chain, one call a step:

0. set aside the surroundings (the table under the part, stray points): one or two readings;
1. normalise: the network's sample of a reading (centred and scaled in ``map``);
2. map every point to 2-D with the network (ONNX);
3. grid: bin the mapped points into the 64x64 grid;
4. classify: eq. (4)'s scores, the candidate parts of a plausible size ranked by them (and,
   for single views, the parts whose rendered views' grids look most like the observation's);
5. hypothesise poses of each candidate, 6. verify them (fit x coverage), 7. refine the best
   (point-to-plane ICP), pass by pass (``search.Search``): the whole part, single views, the
   mapped pairs, until one fits excellently; then the best pose's flips and near-symmetries;
8. decide: the best fit over every candidate and hypothesis, its canonical pose, the poses
   that fit alike, the alignment error; then the calibrated confidence and the verdict.

The gallery is an immutable snapshot swapped whole on every change, so any number of threads
may align while one registers or removes a reference. The engine's terms are defined in
docs/decisions.md, "Glossary".
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from service.engine import confidence, kernels
from service.engine.alignment import alignment_error
from service.engine.answer import Alignment, AlternativePose, SceneAnswer
from service.engine.classifier import LinearClassifier, view_features, view_gram
from service.engine.confidence import Calibration
from service.engine.distance_field import DistanceField
from service.engine.entry import Entry, Snapshot, stored_surface
from service.engine.fits import Fit
from service.engine.frame import Frame, cropped_reason
from service.engine.grid import grid
from service.engine.icp import Surface
from service.engine.look_alikes import SUSPECTS, confused, doubt, relation, suspects
from service.engine.mapping import Mapper
from service.engine.normalize import has_extent, no_larger, normalize, radius, subsample
from service.engine.normals import estimate_normals, mesh_normals, orient_by_views
from service.engine.principal_axes import flatness, one_line, thinness
from service.engine.projection import DepthImage
from service.engine.query import Observed, Query, Ranking, Stopwatch
from service.engine.reference import Reference
from service.engine.scene import Found, Scan, settle_claims, several
from service.engine.search import Plan, Search, excellent, sure_first
from service.engine.segments import segments
from service.engine.supports import Noise, apply_supports, in_rims, set_aside_supports
from service.engine.surroundings import Reading, as_is, set_aside_bin, set_aside_surroundings
from service.engine.symmetry import Symmetry, declared_symmetry, find_symmetry
from service.engine.tuning import (
    ALIKE,
    BIN_ACCEPT,
    BIN_BELOW,
    DIFFERENT_DEG,
    FLAT,
    INSTANCE_FLOOR,
    KEEP_SHARE,
    LINE,
    LOOK_ALIKE,
    MAX_ALTERNATIVES,
    MIN_SEGMENT,
    MORE_VIEWS_BELOW,
    PER_PART,
    POOR_FIT,
    RIGHT_EITHER_WAY,
    THIN_PER_SCALE,
    VIEW_POINTS,
    WHOLE_FINISHED,
    WHOLE_REFINED,
    WHOLE_SCREENED,
)
from service.engine.units import (
    UNIT_FACTORS,
    frame_scale_reason,
    nearest_sized,
    size_reason,
    unit_ratio,
)
from service.engine.views import (
    camera_at,
    directions,
    facing,
    render,
    sample_spacing,
    splat_visible,
)
from service.engine.visibility import hidden_share, random_camera, visible_points
from service.errors import EmptyGallery, InvalidPoints, UnknownReference
from service.settings import EngineSettings

SELF_CHECK_THREADS = 2  # renders of the registration check aligned at once


class Engine:
    def __init__(
        self,
        mapper: Mapper,
        settings: EngineSettings | None = None,
        calibration: Calibration | None = None,
        scene_calibration: Calibration | None = None,
    ):
        self.mapper = mapper
        self.settings = settings or EngineSettings()
        kernels.use(self.settings.compiled)  # the process's loops: one engine's settings a process
        self.calibration = calibration
        self.scene_calibration = scene_calibration  # a detection's confidence, if fitted
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
        symmetry: dict | None = None,
    ) -> Reference:
        """Compute what the engine needs of a new object from its points (sampled on ``mesh``'s
        faces ``face_index``, when it came as a mesh): mapped points, view grids, scale, then
        normals, rendered views, distance field and symmetry (with the one an operator
        declared, ``symmetry``: ``symmetry.declared_symmetry``; ``InvalidPoints`` where it does
        not fit).

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
            derived = self._derive(points, scale, mesh, face_index, network, symmetry)
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
        declared = Symmetry.declared_in(reference.symmetry)
        with ThreadPoolExecutor(1, thread_name_prefix="network") as network:
            derived = self._derive(
                reference.points, reference.scale, mesh, face_index, network, declared
            )
        return reference.with_(**derived)

    def _derive(
        self,
        points: np.ndarray,
        scale: float,
        mesh: trimesh.Trimesh | None,
        face_index: np.ndarray | None,
        network: ThreadPoolExecutor,
        declared: dict | None = None,
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
        symmetry = self._symmetry(surface_model, scale, declared)
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
        surface (points, normals, distance field), with what was declared, every other field
        as it was."""
        declared = Symmetry.declared_in(reference.symmetry)
        symmetry = self._symmetry(stored_surface(reference), reference.scale, declared)
        return reference.with_(symmetry=symmetry.describe())

    @staticmethod
    def _symmetry(surface: Surface, scale: float, declared: dict | None) -> Symmetry:
        """The part's symmetry: found, and joined with the ``declared`` one."""
        found = find_symmetry(surface, scale, np.random.default_rng(0))
        if declared is None:
            return found
        try:
            return declared_symmetry(surface, scale, declared, found)
        except ValueError as error:
            raise InvalidPoints(str(error)) from None

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
        # by name, as the store lists them: the order breaks ties among the parts, so the same
        # gallery answers alike whatever order it was registered in, here or in a worker
        entries = dict(sorted(entries.items()))
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
        alike = relation(entry.reference for entry in listed)
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
            look_alikes=alike,
        )

    def names(self) -> list[str]:
        return list(self._snapshot.entries)

    def look_alikes(self, name: str) -> tuple[str, ...]:
        """The references ``name`` looks alike (``service.engine.look_alikes``)."""
        return self._snapshot.look_alikes.get(name, ())

    def annotate(self, reference: Reference) -> None:
        """Swap in a reference that differs from the one of its name only in what no query
        derives anything from (its ``look_alikes``): nothing is refitted."""
        with self._write_lock:
            snapshot = self._snapshot
            entry = snapshot.entries[reference.name]
            entries = {
                **snapshot.entries,
                reference.name: dataclasses.replace(entry, reference=reference),
            }
            alike = relation(e.reference for e in entries.values())
            self._snapshot = dataclasses.replace(snapshot, entries=entries, look_alikes=alike)

    def claiming(self, name: str, others: Iterable[str]) -> Reference | None:
        """The reference ``name`` claiming the held ``others`` as look-alikes besides what it
        claims already, each named with its points now (``service.engine.look_alikes``);
        None when ``name`` is not held. Stored nowhere: ``annotate`` holds it."""
        reference = self.get(name)
        if reference is None:
            return None
        claims = dict(reference.look_alikes or {})
        for other in others:
            if (held := self.get(other)) is not None and other != name:
                claims[other] = held.points_sha256
        return reference.with_(look_alikes=claims)

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
        """Steps 3-4 alone: the label eq. (4) gives a mapped cloud, and its score."""
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
        surroundings: bool = True,
        noise: float = 0.0,
        rescued: int | None = None,
    ) -> Alignment:
        """Recognise and pose the object in ``points``; ``viewpoint`` is where the sensor was,
        in the cloud's frame, if known; below ``min_confidence`` the verdict is never "match".
        Without ``surroundings``, nothing is set aside (a frame's segment); ``noise``: the
        sensor's depth noise where the part lies, if known (``Query.tolerance``); ``rescued``:
        how many more parts are tried where none fits well (default ``rescued_parts``)."""
        query = self.query(candidates, top_k, refine, hypotheses, viewpoint)
        query.noise, query.rescued = noise, rescued
        scene = np.asarray(points)
        whole = len(scene)
        if whole > (most := self.settings.align_points):  # a sample answers as the whole would
            scene = scene[subsample(scene, most, np.random.default_rng(self.settings.seed))]
        scene = np.asarray(scene, dtype=np.float64)  # the sample's points alone
        if surroundings:
            readings = self.set_aside(query, scene)  # 0
        else:
            readings = [as_is(scene, np.random.default_rng(self.settings.seed))]
        answer, chosen = None, None
        for reading in readings:
            if answer is not None and answer.fit * answer.coverage >= self.settings.excellent:
                break
            answer, chosen = self.better(query, reading, answer, chosen, whole / len(scene))  # 1-8
        in_bin = None
        if surroundings and answer.fit * answer.coverage < BIN_BELOW:
            in_bin = self.in_bin(query, scene)  # 0, a bin's floor and walls set aside
            if in_bin is not None:
                answer, chosen = self.better(query, in_bin, answer, chosen, whole / len(scene))
        if answer.verdict != "no_match":  # 8. How far to trust it.
            answer.in_bin = in_bin is not None and chosen is in_bin
            self.judge(answer, min_confidence, query, flatness(chosen.points), answer.in_bin)
            doubt(answer)  # among look-alikes that fit alike, the label is a guess
        answer.timings_ms = query.clock.total()
        return answer

    def query(self, candidates, top_k, refine, hypotheses, viewpoint) -> Query:
        """What an ``align`` call asks, on the gallery's snapshot of now."""
        snapshot, settings = self._snapshot, self.settings
        if not snapshot.entries:
            raise EmptyGallery("no reference is registered: register one with POST /references")
        return Query(
            snapshot,
            self._candidate_rows(snapshot, candidates),
            hypotheses or settings.hypotheses,
            top_k,
            refine,
            None if viewpoint is None else np.asarray(viewpoint, dtype=np.float64),
            np.random.default_rng(settings.seed),
            Stopwatch(),
        )

    def set_aside(self, query: Query, scene: np.ndarray) -> list[Reading]:
        """Step 0: the readings of the observation, the table, stray points and clutter set
        aside (``surroundings``); more than one may be tried, the first first."""
        rng = np.random.default_rng(self.settings.seed)
        readings = set_aside_surroundings(scene, rng, query.viewpoint)
        query.clock.lap("surroundings")
        return readings

    def better(self, query, reading, answer, chosen, per_point) -> tuple[Alignment, Reading]:
        """Steps 1-8 on ``reading``: its answer and itself where it fits better than ``answer``
        (of the reading ``chosen``); ``per_point``: the request's points a point of the
        reading stands for."""
        found = self.align_reading(query, reading)
        found.points_set_aside = round(reading.set_aside * per_point)
        if answer is None or found.fit * found.coverage > answer.fit * answer.coverage:
            return found, reading
        return answer, chosen

    def in_bin(self, query: Query, scene: np.ndarray) -> Reading | None:
        """Step 0 once more where no reading fit well: the part in a bin, its floor and walls
        set aside (``surroundings.set_aside_bin``; docs/decisions.md#a-part-in-a-bin), where a
        table's reading sets aside one plane and leaves the walls with the part."""
        if not self.settings.bin_walls:
            return None
        in_bin = set_aside_bin(scene, np.random.default_rng(self.settings.seed), query.viewpoint)
        query.clock.lap("surroundings")
        return in_bin

    def align_reading(self, query: Query, reading: Reading) -> Alignment:
        """Steps 1-8 on one reading of the observation."""
        if not has_extent(radius(reading.points), float(np.abs(reading.points).max())):
            return self._at_one_place(query, reading.points)
        if (thin := thinness(reading.points - reading.points.mean(axis=0))) < LINE:
            return self._on_one_line(query, reading.points, thin)
        observed = self.normalise(query, reading)  # 1
        observed.mapped = self.map(observed.points)  # 2
        query.clock.lap("map")
        observed.grid = grid(observed.mapped)  # 3
        ranking = self.classify(query, observed)  # 4
        search = Search(self.settings, query, observed)
        fits = self.search(query, observed, ranking, search)  # 5-7
        if not fits:  # nothing of a plausible size: no search over the wrong sizes
            return self._unanswered(query.snapshot, query.allowed, observed.points, ranking.scores)
        fits.sort(key=lambda f: -f.score)
        if query.refine and fits[0].score >= self._finished_from(observed):
            fits = search.finish(fits)  # 7, the best pose
        return self.decide(query, observed, ranking, search, fits)  # 8

    def normalise(self, query: Query, reading: Reading) -> Observed:
        """Step 1: the network's sample of the reading (centring and scaling: ``map``)."""
        scene = reading.points
        sample = scene[subsample(scene, self.settings.network_points, query.rng)]
        query.clock.lap("normalize")
        return Observed(scene, sample, radius(sample), reading.spacing)

    def classify(self, query: Query, observed: Observed) -> Ranking:
        """Step 4: eq. (4)'s scores of the grid, and the candidates of a plausible size ranked
        by them; the first ``top_k`` are verified in every pass."""
        snapshot, settings = query.snapshot, self.settings
        scores = snapshot.classifier.scores(observed.grid)
        allowed = query.allowed
        sized = self._plausible(snapshot.scales[allowed], observed.size, settings.size_ratio)
        plausible = allowed[sized]
        ranked = plausible[np.argsort(-scores[plausible], kind="stable")]
        shortlist = ranked[: query.top_k or settings.top_k]
        query.clock.lap("classify")
        return Ranking(scores, ranked, shortlist, sure_first(scores, ranked))

    def search(
        self, query: Query, observed: Observed, ranking: Ranking, search: Search
    ) -> list[Fit]:
        """Steps 5-7, pass by pass until a fit is excellent: the whole part (principal axes),
        single views (rendered views), more parts' views where none fits well, the pairs the
        learned mapping makes."""
        fits: list[Fit] = []
        passes = (self._whole_part, self._single_views, self._more_views, self._mapped_pairs)
        for plan_of in passes:
            if excellent(fits, self.settings) or self._hopeless(fits, plan_of):
                break
            plan = plan_of(query, observed, ranking, fits)
            if plan is None:
                continue
            made = search.hypothesise(plan)  # 5
            found = search.verify(made, plan)  # 6
            fits += search.refine(found, plan)  # 7
        return fits

    def _hopeless(self, fits: list[Fit], next_pass) -> bool:
        """Whether the search stops before the mapped pairs: after the single views, no
        refined fit reaches ``settings.hopeless``, or ``settings.mapped_from`` (fit x
        coverage). Another part, or none: what the mapped pairs would add does not make a
        "match" of it (docs/decisions.md#at-camera-scale)."""
        floor = max(self.settings.hopeless, self.settings.mapped_from)
        if next_pass != self._mapped_pairs or not floor:
            return False
        refined = [f.score for f in fits if f.refined]  # none: nothing to judge it by
        return bool(refined) and max(refined) < floor

    def _finished_from(self, observed: Observed) -> float:
        """The least fit x coverage whose pose is finished (flips, near-symmetries): the
        search's ``hopeless``; for a whole part's cloud, ``WHOLE_FINISHED`` too. Its principal
        axes were verified every way round; the flips lifted a right part from a wrong sign's
        0.70, while other parts' clouds reached the finish at 0.31-0.66
        (docs/decisions.md#a-whole-parts-cloud)."""
        if observed.whole:
            return max(self.settings.hopeless, WHOLE_FINISHED)
        return self.settings.hopeless

    def _whole_part(
        self, query: Query, observed: Observed, ranking: Ranking, fits: list[Fit]
    ) -> Plan | None:
        """The shortlist's whole-part hypotheses (principal axes): what a full cloud needs."""
        if "principal-axes" not in query.sources:
            return None
        planned = {int(row): ["principal-axes"] for row in ranking.shortlist}
        return Plan(planned, WHOLE_REFINED, ranking.first, screened=WHOLE_SCREENED)

    def _single_views(
        self, query: Query, observed: Observed, ranking: Ranking, fits: list[Fit]
    ) -> Plan | None:
        """The parts whose rendered views' grids look most like the observation's, and the
        shortlist, from every rendered view of each: what one camera's view needs. Parts
        only the views propose get their whole-part hypotheses too; more parts are rescued
        where none fits well."""
        if "views" not in query.sources or self._whole_cloud(query, observed):
            return None
        shortlist = ranking.shortlist
        count = query.top_k or self.settings.view_candidates
        more = 0 if query.top_k else self.settings.more_views  # ranked once for _more_views
        snapshot, allowed = query.snapshot, query.allowed
        ranked = self._nearest_views(snapshot, observed.grid, observed.size, allowed, count + more)
        observed.nearest_views = ranked
        rows = ranked[:count]
        rows += [row for row in shortlist if row not in rows]
        query.clock.lap("classify")
        whole = ["principal-axes"] if "principal-axes" in query.sources else []
        planned = {row: ["views", *(whole if row not in shortlist else [])] for row in rows}
        return Plan(planned, self.settings.refine_best, ranking.first, rescue=True)

    def _whole_cloud(self, query: Query, observed: Observed) -> bool:
        """Whether the observation, told of no camera, is a whole part's cloud rather than one
        camera's view: it hides ``settings.whole_hidden`` of its points or more from every
        side. Its single views would pose another part, or the same part no better than its
        principal axes did (docs/decisions.md#a-whole-parts-cloud)."""
        if query.viewpoint is not None or self.settings.whole_hidden >= 1:
            return False
        if "principal-axes" not in query.sources:  # the views are all it is searched by
            return False
        rng = np.random.default_rng(self.settings.seed)  # the search's own draws unchanged
        observed.whole = hidden_share(observed.points, rng) >= self.settings.whole_hidden
        return observed.whole

    def _more_views(
        self, query: Query, observed: Observed, ranking: Ranking, fits: list[Fit]
    ) -> Plan | None:
        """Where no refined fit fits well (``MORE_VIEWS_BELOW``), the next
        ``settings.more_views`` parts whose rendered views look most like the observation,
        from every view of each: a part never seen in training, or seen from an unlucky side,
        may rank just below the first (docs/decisions.md#single-views). Not where the request
        set the budget (``top_k``)."""
        more, first = self.settings.more_views, self.settings.view_candidates
        if "views" not in query.sources or not more or query.top_k:
            return None
        if max((f.score for f in fits if f.refined), default=0.0) >= MORE_VIEWS_BELOW:
            return None
        searched = {f.row for f in fits}
        ranked = observed.nearest_views  # by _single_views, which runs before
        rows = [row for row in ranked[first : first + more] if row not in searched]
        if not rows:
            return None
        query.clock.lap("classify")
        whole = ["principal-axes"] if "principal-axes" in query.sources else []
        return Plan({row: ["views", *whole] for row in rows}, self.settings.refine_best)

    def _mapped_pairs(
        self, query: Query, observed: Observed, ranking: Ranking, fits: list[Fit]
    ) -> Plan | None:
        """The shortlist posed from the pairs of points the learned mapping makes (RANSAC, or
        the paper's least squares alone)."""
        paired = [s for s in query.sources if s in ("mapped", "paper")]
        if not paired:
            return None
        return Plan({row: paired for row in ranking.shortlist}, WHOLE_REFINED)

    def decide(
        self, query: Query, observed: Observed, ranking: Ranking, search: Search, fits: list[Fit]
    ) -> Alignment:
        """Step 8: the best fit x coverage of all, at its canonical pose (its symmetry), the
        poses that fit alike, and the alignment error on every point of the reading."""
        snapshot = query.snapshot
        winner = fits[0]
        label = snapshot.classifier.labels[winner.row]
        entry = snapshot.entries[label]
        rotation, translation = entry.symmetry.canonical(winner.rotation, winner.translation)
        runner_up = max(
            (f for f in fits if f.row != winner.row), key=lambda f: f.score, default=None
        )
        runner_label = None if runner_up is None else snapshot.classifier.labels[runner_up.row]
        alike, alternatives, closest = self._alike(entry, fits)
        look_alikes = self._look_alike_fits(query, search, fits, winner)
        parts = self._look_alike_poses(query, look_alikes)
        query.clock.lap("decide")
        error = alignment_error(observed.scene, entry.point_tree, rotation, translation)
        query.clock.lap("measure")
        return Alignment(
            label=label,
            score=float(ranking.scores[winner.row]),
            rotation=rotation,
            translation=translation,
            alignment_error=error,
            alignment_error_normalized=error / entry.reference.scale,
            hypothesis=winner.source,
            candidates=search.candidate_fits(fits, ranking.scores),
            ambiguous=bool(alternatives),
            alternatives=alternatives + parts,
            fit=winner.fit,
            coverage=winner.coverage,
            runner_up=0.0 if runner_up is None else runner_up.score,
            runner_up_label=runner_label,
            alike=alike,
            size_ratio=observed.size / entry.reference.scale,
            points=len(observed.scene),
            look_alikes=[other for other, _ in look_alikes],
            closest=closest,
        )

    @staticmethod
    def _look_alike_poses(
        query: Query, look_alikes: list[tuple[str, Fit]]
    ) -> list[AlternativePose]:
        """The look-alike parts' poses, as alternatives carrying their labels."""
        return [
            AlternativePose(
                *query.snapshot.entries[other].symmetry.canonical(fit.rotation, fit.translation),
                confidence=0.0,
                label=other,
            )
            for other, fit in look_alikes
        ]

    def _look_alike_fits(
        self, query: Query, search: Search, fits: list[Fit], winner: Fit
    ) -> list[tuple[str, Fit]]:
        """The winner's look-alikes among the allowed parts (``service.engine.look_alikes``)
        that fit within ``LOOK_ALIKE`` of its fit x coverage, each at its best pose: one of the same
        points at the winner's own; another searched as the winner was (its best hypotheses
        refined, then finished), had the search not verified it."""
        snapshot = query.snapshot
        labels = snapshot.classifier.labels
        rows = [labels.index(o) for o in snapshot.look_alikes.get(labels[winner.row], ())]
        if not rows:  # most parts: nothing to search, no set of the allowed rows to build
            return []
        allowed = set(query.allowed.tolist())
        rows = [row for row in rows if row in allowed]
        same = search.entry(winner.row).reference.points_sha256
        alike = []
        for row in rows:
            if search.entry(row).reference.points_sha256 == same:  # one surface: one fit
                best = dataclasses.replace(winner, row=row)
            else:
                best = self._searched_as_winner(query, search, fits, row)
            if best is not None and best.score >= LOOK_ALIKE * winner.score:
                alike.append((labels[row], best))
        return alike

    def _searched_as_winner(
        self, query: Query, search: Search, fits: list[Fit], row: int
    ) -> Fit | None:
        """A look-alike's best pose, searched and refined as the winner's was (copies: the
        search's own fits stay as they were)."""
        mine = [dataclasses.replace(f) for f in fits if f.row == row]
        if not mine:
            chosen = [s for s in ("views", "principal-axes", "mapped") if s in query.sources]
            plan = Plan({row: chosen}, self.settings.refine_best)
            mine = search.refine(search.verify(search.hypothesise(plan), plan), plan)
        if not mine:
            return None
        mine.sort(key=lambda f: (not f.refined, -f.score))
        if query.refine:
            search.refine_all([c for c in mine[:PER_PART] if not c.refined])
            mine = search.finish(sorted(mine, key=lambda f: -f.score))
        return max(mine, key=lambda f: f.score)

    @staticmethod
    def _alike(
        entry: Entry, fits: list[Fit]
    ) -> tuple[float, list[AlternativePose], AlternativePose | None]:
        """How well the best other refined pose of the winner's part fits (0 when none lies
        ``RIGHT_EITHER_WAY`` or farther from it) and that pose; and those that fit alike as
        alternatives: poses more than ``DIFFERENT_DEG`` apart, symmetry accounted for."""
        winner, alike, alternatives, closest = fits[0], 0.0, [], None
        for other in fits[1:]:
            if other.row != winner.row or not other.refined:
                continue
            if entry.symmetry.distance_deg(other.rotation, winner.rotation) <= DIFFERENT_DEG:
                continue
            pose = entry.symmetry.canonical(other.rotation, other.translation)
            if other.score > alike and entry.gap(winner, other) >= RIGHT_EITHER_WAY:
                alike, closest = other.score, AlternativePose(*pose, confidence=0.0)
            if other.score >= ALIKE * winner.score and len(alternatives) < MAX_ALTERNATIVES:
                alternatives.append(AlternativePose(*pose, confidence=0.0))
        return alike, alternatives, closest

    def judge(
        self,
        answer: Alignment,
        min_confidence: float | None,
        query: Query,
        flat: float,
        in_bin: bool = False,
    ) -> None:
        """Step 8's confidence, verdict and reasons (``service.engine.confidence``). ``flat``
        is the observation's ``flatness``: one flat face of a part that is not flat itself
        fixes neither its turn about the face's normal nor where along the face it lies, so
        such an answer is never a "match". ``in_bin``: the answer is of a bin's reading, whose
        walls may hide what tells parts apart: a "match" needs ``BIN_ACCEPT`` at least."""
        entry = query.snapshot.entries[answer.label]
        one_face = flat < FLAT <= entry.flatness
        values = self._measures(answer, query.viewpoint is not None)
        if self.calibration is None:
            answer.verdict, answer.confidence = "uncertain", None
            reasons = ["no confidence calibration is loaded (confidence.json)"]
        else:
            answer.confidence = self.calibration.confidence(values)
            for alternative in answer.alternatives:
                alternative.confidence = answer.confidence
            threshold = self._threshold(min_confidence)
            if in_bin:  # docs/decisions.md#a-part-in-a-bin
                threshold = max(threshold, BIN_ACCEPT)
            if answer.confidence >= threshold and not one_face:
                answer.verdict, answer.reasons = "match", []
                return
            self._two_poses(answer, values, threshold)
            low = answer.confidence < self.settings.reject_below
            answer.verdict = "no_match" if low else "uncertain"
            reasons = []
            if answer.confidence < threshold:
                reasons.append(
                    f"the confidence {answer.confidence:.2f} is below the threshold {threshold:.2f}"
                    + (" of a part seen in a bin (its floor and walls set aside)" if in_bin else "")
                )
        answer.reasons = reasons + self._doubts(answer, values, one_face, flat, query)

    def seen_as(self, answer: Alignment, coverage: float) -> float | None:
        """The chain's confidence in ``answer`` had it measured ``coverage`` (its logit moved
        by as much as that moves the calibration's): in a frame, the share of the part the
        camera shows of what nothing nearer hides (docs/decisions.md#what-the-frame-shows).
        A frame's asks are told the viewpoint."""
        if self.calibration is None or answer.confidence is None:
            return answer.confidence
        moved = self.calibration.logit(self._measures(answer, True, coverage))
        moved -= self.calibration.logit(self._measures(answer, True))
        return confidence.from_log_odds(confidence.log_odds(answer.confidence, 1e-6) + moved)

    @staticmethod
    def _measures(answer: Alignment, told: bool, coverage: float | None = None) -> dict:
        """The calibration's measures of ``answer`` (``confidence.measures``); ``coverage``:
        in place of its own."""
        return confidence.measures(
            answer.fit,
            answer.coverage if coverage is None else coverage,
            answer.runner_up,
            answer.alike,
            answer.points,
            answer.size_ratio,
            told,
        )

    def _two_poses(self, answer: Alignment, values: dict, threshold: float) -> None:
        """A refused answer that only the other pose it was measured against (``alike``)
        keeps from a "match": the view cannot tell the two apart, so that pose is listed as an
        alternative and the answer is ``ambiguous`` (docs/decisions.md#two-poses)."""
        closest = answer.closest
        if closest is None or answer.ambiguous:
            return
        if self.calibration.confidence(values | {"alike": 0.0}) >= threshold:
            closest.confidence = answer.confidence
            answer.alternatives.insert(0, closest)
            answer.ambiguous = True

    def _threshold(self, min_confidence: float | None) -> float:
        """The confidence of a "match": the request's, else the setting's, else the
        calibration's own."""
        chosen = (min_confidence, self.settings.accept, self.calibration.accept)
        return next(t for t in chosen if t is not None)

    def _doubts(self, answer: Alignment, values, one_face: bool, flat: float, query) -> list[str]:
        """What makes an answer doubtful, each with what the caller can change."""
        entry = query.snapshot.entries[answer.label]
        reasons = []
        if one_face:
            reasons.append(
                f"the observed points lie on one plane (thickness {flat:.1%} of their extent): "
                f"one flat face does not fix {answer.label}'s pose; look at the part from where "
                "more than one of its faces is seen"
            )
        reasons += confidence.reasons(
            answer.label, values, answer.runner_up_label, answer.ambiguous
        )
        # other units? Only where nothing says the part may fit: the right part on its table,
        # some of the table left in, fits as poorly (docs/decisions.md#decide)
        if values["fit"] < POOR_FIT and (answer.verdict == "no_match" or answer.confidence is None):
            size = answer.size_ratio * entry.reference.scale
            hint = self._unit_hint(query.snapshot.scales[query.allowed], size, toward=True)
            reasons += [hint] if hint else []
        return reasons

    def _at_one_place(self, query: Query, scene: np.ndarray) -> Alignment:
        """A no-match answer for a reading whose points, strays set aside, lie at one place."""
        snapshot = query.snapshot
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

    def _on_one_line(self, query: Query, scene: np.ndarray, thin: float) -> Alignment:
        """A no-match answer for a reading whose points lie on one line (``tuning.LINE``)."""
        snapshot = query.snapshot
        scores = np.zeros(len(snapshot.classifier.labels))
        reasons = [one_line(len(scene), thin)]
        return self._unanswered(snapshot, query.allowed, scene, scores, reasons)

    # --- a whole frame ----------------------------------------------------------------

    def detect(
        self,
        frame: Frame,
        candidates: list[str] | None = None,
        max_instances: int = 20,
        roi: tuple[np.ndarray, np.ndarray] | None = None,
        min_confidence: float | None = None,
        floor: float | None = None,
        deadline: float | None = None,
        submit: Callable[..., Future] | None = None,
    ) -> SceneAnswer:
        """Every instance of a registered part in a camera's ``frame``: the supports set
        aside, the rest split into segments, each searched by the chain until nothing more
        fits, and searched again for more of a part found several times; then one global
        check among the instances, each judged again on what is left around it, and a part
        found several times only then searched again as well. ``floor``:
        the least confidence of an instance (default ``INSTANCE_FLOOR``; the calibration
        collects them all with 0); ``deadline`` (``time.monotonic()``): no region is searched
        after it; ``submit``: an engine method by name in another process, answering a
        future (``Scan.ask_ahead``, ``scene.Shared``)."""
        query = self.query(candidates, None, True, None, frame.viewpoint)
        clock = Stopwatch()
        if roi is not None:
            inside = frame.cropped(*roi)
            if len(inside) < MIN_SEGMENT:  # nothing to search: say where the frame is
                reason = cropped_reason(frame.points, roi, len(inside), MIN_SEGMENT)
                return SceneAnswer.unsearched(len(inside), clock.total(), reason)
            frame = inside
        scales = self._frame_scales(query, frame)
        thin = frame.thinned(scales.min() / THIN_PER_SCALE)  # thin
        angle = frame.pixel_angle()
        clock.lap("thin")
        unit = frame_scale_reason(thin.ranges(), angle, float(scales.max()), MIN_SEGMENT)
        if unit is not None:  # no part could be seen: a frame in millimetres, say
            return SceneAnswer.unsearched(len(frame), clock.total(), unit)
        keep, supports = set_aside_supports(thin, angle, scales, query.rng)
        clock.lap("supports")
        rest = thin.take(keep)
        labels = segments(rest, angle, rims=in_rims(rest, supports, angle))  # segments
        clock.lap("segments")
        camera, noise = DepthImage.of(thin), Noise(supports[0] if supports else None)
        sizes = (float(scales.min()), float(scales.max()))
        scan = self._scan(
            query, rest, camera, noise, sizes, floor, min_confidence, deadline, submit
        )
        try:
            instances = scan.instances(labels, max_instances)  # explain, take out, search again
            instances += self._found_again(scan, instances, labels, max_instances)  # more of one
        finally:
            scan.settle()
        clock.lap("instances")
        searched = several(instances)  # the parts looked for again
        instances = settle_claims(instances, len(rest), KEEP_SHARE)  # one global check
        instances = scan.judged_around(instances)  # ... and what it leaves around each
        instances = self._settled_several(scan, instances, labels, max_instances, searched)
        clock.lap("global check")
        seen = keep if thin is frame else apply_supports(frame, supports, angle)  # full res
        return scan.answer(frame, seen, supports, instances, clock)

    def _scan(
        self, query, rest, camera, noise, sizes, floor, min_confidence, deadline, submit
    ) -> Scan:
        """The search of a frame's points off its supports (``service.engine.scene``)."""
        return Scan(
            self.align,
            self.seen_as,
            self.settings.tolerance,
            self.scene_calibration,
            query,
            rest,
            camera,
            noise,
            INSTANCE_FLOOR if floor is None else floor,
            min_confidence,
            sizes,
            deadline,
            submit,
        )

    def search_segments(
        self,
        rest: Frame,
        camera: DepthImage | None,
        noise: Noise,
        sizes: tuple[float, float],
        labels: np.ndarray,
        order: list[int],
        free: np.ndarray,
        candidates: list[str] | None,
        floor: float,
        min_confidence: float | None,
        deadline: float | None,
        most: int,
    ) -> tuple[list[Found], list[int], bool]:
        """A share of a frame's segments searched here while the process that runs
        ``detect`` searches the rest (``scene.Shared``): what was found, the segments where
        nothing was, and whether every region was searched in time. ``free``: the points
        not yet taken there."""
        query = self.query(candidates, None, True, None, rest.viewpoint)
        scan = self._scan(query, rest, camera, noise, sizes, floor, min_confidence, deadline, None)
        scan.free = free
        found: list = []
        failed = scan.search(labels, order, most, found)  # no ``submit``: nothing asked ahead
        return [Found.of(instance) for instance in found], failed, scan.complete

    def _found_again(
        self,
        scan: Scan,
        found: list,
        labels: np.ndarray,
        most: int,
        parts: list[str] | None = None,
    ) -> list:
        """More instances of the parts held ``SEVERAL`` times or more in the frame (or of
        ``parts``), looked for where nothing more was found, told only those parts: a frame
        that holds several of one part (a bin) may hold more of it, touching them, that the
        search among every part missed (docs/decisions.md#detect). Those found already and
        doubted are judged again as a frame told those parts would be
        (docs/decisions.md#a-part-the-frame-holds-several-of); other parts' doubted instances
        may be poses of them, and their points are searched again too
        (docs/decisions.md#several-likely-instances)."""
        parts = several(found) if parts is None else parts
        if not parts:
            return []
        told = self.query(parts, None, True, None, scan.query.viewpoint)
        if len(told.allowed) == len(scan.query.allowed):  # told those alone already
            return []
        again = scan.narrowed(told)  # judged as a frame told its parts
        for instance in found:  # ... the instances of them found already, too
            if instance.answer.verdict == "match":
                continue
            if instance.answer.label in parts:
                again.judge(instance)
            else:  # another part's doubted pose on one of them: its points searched, told
                again.free[instance.claimed] = True
        if len(found) >= most or not scan.in_time():
            return []
        try:
            more = again.instances(labels, most - len(found))
        finally:
            again.settle()
        scan.complete = again.complete
        return more

    def _settled_several(
        self, scan: Scan, found: list, labels: np.ndarray, most: int, searched: list[str]
    ) -> list:
        """``found`` with the parts held ``SEVERAL`` times only once judged on what is left
        around them (not among those ``searched`` again already) looked for again, as
        ``_found_again`` does, and the instances checked and judged once more
        (docs/decisions.md#a-part-the-frame-holds-several-of)."""
        parts = [label for label in several(found) if label not in searched]
        more = self._found_again(scan, found, labels, most, parts) if parts else []
        if not more:
            return found
        found = settle_claims(found + more, len(scan.frame), KEEP_SHARE)
        return scan.judged_around(found)

    def _frame_scales(self, query: Query, frame: Frame) -> np.ndarray:
        """The scales of the references a part in this frame could be: those no larger than
        the frame (all of them, if none is)."""
        scales = query.snapshot.scales[query.allowed]
        fits = scales[no_larger(scales, frame.points)]
        return fits if len(fits) else scales

    def _nearest_views(
        self,
        snapshot: Snapshot,
        observed_grid: np.ndarray,
        size: float,
        allowed: np.ndarray,
        count: int,
    ) -> list[int]:
        """The rows of the ``count`` parts whose rendered views look most like the observation
        (cosine of the grids' features, among views of a plausible size), best first."""
        settings = self.settings
        similarity = snapshot.view_keys @ view_features(observed_grid, settings.grid_blur)[0]
        low, high = settings.view_size_ratio
        ratio = size / np.maximum(snapshot.view_radii, 1e-12)
        usable = (ratio >= low) & (ratio <= high) & np.isin(snapshot.view_owner, allowed)
        similarity = np.where(usable, similarity, -np.inf)
        best_per_row = np.maximum.reduceat(similarity, snapshot.view_starts)
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

    def _unit_hint(self, scales: np.ndarray, size: float, toward: bool = False) -> str | None:
        """The reason naming the first unit in which an observation of radius ``size`` would
        be the size of one of these ``scales``; None if in none. ``toward``: only a unit that
        brings it nearer the references' median scale, for an observation of a size some
        reference has: a gallery of parts in mixed units has a part of any cloud's size in
        some other unit (docs/decisions.md#units-of-a-poor-fit)."""
        typical = float(np.median(scales)) if toward and len(scales) else size
        off = abs(np.log(max(size, 1e-12) / typical))
        for factor in UNIT_FACTORS:
            if toward and abs(np.log(max(size / factor, 1e-12) / typical)) >= off:
                continue
            if self._plausible(scales, size / factor, self.settings.size_ratio).any():
                return size_reason(factor, also=True)
        return None

    @staticmethod
    def _plausible(scales: np.ndarray, size: float, ratio: tuple[float, float]) -> np.ndarray:
        """Which references' scales could give an observation of this radius.

        The grid is scale-free, but a sensor measures sizes: a size far outside a part's own
        is another part (docs/decisions.md#classify).
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
        ``views`` single-camera views of it (``_renders``), each in a random pose, against the
        whole gallery. Each check says what was answered and how far its rotation is from the
        truth, the part's symmetry accounted for."""
        entry = self._snapshot.entries.get(reference.name)
        if entry is None or entry.reference is not reference:  # not the one the gallery holds
            entry = Entry.of(reference, self.settings.grid_blur)

        def check(kind: str, scene, viewpoint, rotation, result: Alignment) -> dict:
            return {
                "render": kind,
                "label": result.label,
                "label_ok": result.label == reference.name,
                "rotation_error_deg": entry.symmetry.distance_deg(result.rotation, rotation),
                "alignment_error_normalized": result.alignment_error_normalized,
                "verdict": result.verdict,
                "confidence": result.confidence,
                **(self._runner_up(result, scene, viewpoint) if kind == "full" else {}),
            }

        renders = self._renders(entry, views, mesh, full=True)
        return self._aligned(renders, check)

    def registration_check(
        self, reference: Reference, poses: int, mesh: trimesh.Trimesh | None = None
    ) -> tuple[list[dict], list[str]]:
        """A registered reference's check (``self_check`` on ``poses`` renders) and the parts
        it could not tell it from, either way (``look_alikes.confused``, ``taken_for`` on
        twice as many views of each suspect)."""
        checks = self.self_check(reference, poses, mesh)
        taken = self.taken_for(reference, 2 * poses)
        return checks, sorted({*confused(reference.name, checks), *taken})

    def taken_for(self, reference: Reference, views: int) -> list[str]:
        """The registration check's other direction: the held parts that ``views`` camera
        views of, each in a random pose, are now answered as ``reference``, or fitted alike
        by it (``ALIKE``). Only the ``SUSPECTS`` parts whose rendered views look most like
        the new one's are rendered (``look_alikes.suspects``; docs/decisions.md#either-way)."""
        snapshot = self._snapshot
        name = reference.name

        def taken(kind, scene, viewpoint, rotation, result: Alignment) -> bool:
            alike = result.runner_up >= ALIKE * result.fit * result.coverage > 0
            return result.label == name or (result.runner_up_label == name and alike)

        return [
            other
            for other in suspects(snapshot, name, SUSPECTS)
            if any(self._aligned(self._renders(snapshot.entries[other], views), taken))
        ]

    def _renders(
        self, entry: Entry, views: int, mesh: trimesh.Trimesh | None = None, full: bool = False
    ) -> list[tuple[str, np.ndarray, np.ndarray | None, tuple[np.ndarray, np.ndarray]]]:
        """A registration check's renders of ``entry``'s part: a full cloud (if ``full``) and
        ``views`` camera views, each (kind, points, camera, pose it is placed at). They are
        independent of the registered points: a mesh is sampled anew; a cloud's points are
        jittered by a third of their spacing and a fifth of them dropped. A view is what a
        camera 6 scales away sees of that sample (the mesh's depth buffer, or hidden-point
        removal), and the camera's place is its viewpoint."""
        rng = np.random.default_rng(self.settings.seed + 1)
        reference = entry.reference
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
        renders: list[tuple[str, np.ndarray, np.ndarray | None]] = []
        renders += [("full", sample, None)] if full else []
        for direction in Rotation.random(views, random_state=rng).apply([0.0, 0.0, 1.0]):
            camera = camera_at(centroid, direction, reference.scale)
            if surface is None:
                seen = visible_points(sample, camera)
            else:
                seen = splat_visible(sample, surface, camera, sample_spacing(surface, mesh.area))
            renders.append(("view", sample[seen], camera))
        # every pose drawn first, in the order one thread drew them
        return [
            (*render, (Rotation.random(random_state=rng).as_matrix(),
                       rng.uniform(-1, 1, 3) * reference.scale))
            for render in renders
        ]  # fmt: skip

    def _aligned(self, renders, judged: Callable) -> list:
        """``judged(kind, scene, viewpoint, rotation, answer)`` of each render placed at its
        pose and aligned against the whole gallery, two at a time (their numpy, cKDTree and
        onnxruntime steps let go of the GIL)."""

        def one(render) -> object:
            kind, cloud, camera, (rotation, translation) = render
            scene = cloud @ rotation.T + translation
            viewpoint = None if camera is None else rotation @ camera + translation
            result = self.align(scene, viewpoint=viewpoint)
            return judged(kind, scene, viewpoint, rotation, result)

        with ThreadPoolExecutor(SELF_CHECK_THREADS, thread_name_prefix="self-check") as pool:
            return list(pool.map(one, renders))

    def _runner_up(self, result: Alignment, scene: np.ndarray, viewpoint) -> dict:
        """The other part that fitted a render of a new reference best, and how well once the
        whole search is spent on it alone: its fit x coverage over the answer's. The search's
        own figure for it may be an unrefined pose's (service.engine.look_alikes)."""
        other = result.runner_up_label
        if other is None or result.fit * result.coverage <= 0:
            return {"runner_up": other, "runner_up_fit": None}
        alone = self.align(scene, candidates=[other], viewpoint=viewpoint)
        share = alone.fit * alone.coverage / (result.fit * result.coverage)
        return {"runner_up": other, "runner_up_fit": share}
