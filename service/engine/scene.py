"""Every registered part in a whole frame: the instances the one-part chain finds in its
segments, each with the points it explains, and one global check among them.

A segment is searched as ``Engine.align`` searches a cloud; an answer that explains enough
of it is an instance, its points (every point of the frame near its surface, the neighbouring
segments' too: a part cut in two by a jump in depth is one instance) are taken out, and what
is left of the segment is searched again, piece by piece where it falls apart, until nothing
fits. Where the chain finds nothing in a segment, it may hold several parts touching: the
likeliest parts' views are placed over it (``templates``) and the chain asked about the points
the best placed view explains. Segments where nothing was found are then tried joined with a
neighbour (a part cut in two). Where a part was found several times (a bin's), what is left is
searched again for it alone (``Engine.detect``). Last the global check: each claimed point goes
to the instance whose surface is nearest it, and an instance left with too little of what it
claimed is dropped; then each is judged again on what the frame leaves unexplained around it
(``Scan.judged_around``).

An instance's confidence is the scene calibration's (``evidence``: the chain's confidence and
what the frame's depth says of the pose), where one is fitted; else the chain's.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from service.engine.alignment import alignment_error, turned_about
from service.engine.answer import Alignment, Detection, SceneAnswer
from service.engine.confidence import Calibration, from_log_odds, log_odds
from service.engine.entry import Entry
from service.engine.frame import Frame
from service.engine.icp import Start, icp_many
from service.engine.look_alikes import doubt, undoubted
from service.engine.normalize import radius, squared_distances, subsample
from service.engine.projection import DepthImage
from service.engine.query import Query, Stopwatch
from service.engine.segments import adjacent, cell_groups, creases, segments
from service.engine.supports import Noise, Support
from service.engine.templates import likeliest, place_views
from service.engine.tuning import (
    ALIKE_EXPLAINED,
    ALIKE_FACE_POINTS,
    ALIKE_FACE_RATIO,
    ALIKE_FACE_SHARE,
    ALIKE_FACE_THROUGH,
    ALIKE_THROUGH,
    AROUND_DOUBT,
    AROUND_SAMPLE,
    AROUND_SCALES,
    CHAIN_AGREES,
    CLAIM_TOLERANCE,
    DUPLICATE_GAP,
    FINER_LINKS,
    FINISH_ITERATIONS,
    FINISH_POINTS,
    FRAGMENT,
    FRAGMENTS_ADD,
    HELD_FROM,
    INSTANCE_FLOOR,
    JOIN_PIXELS,
    JOIN_SCALES,
    MATCH_POINTS,
    MAX_JOINS,
    MAX_TRIES,
    MIN_EXPLAINED,
    MIN_SEGMENT,
    NOISE_TOLERANCES,
    PIECE_CELLS,
    SEGMENT_POINTS,
    SEGMENT_RESCUED,
    SEVERAL,
    STRAYS,
    TEMPLATE_FIT,
    TEMPLATE_PARTS,
    TEMPLATE_POOL,
    TEMPLATE_SIZES,
    TEMPLATES_ASKED,
    THROUGH_DOUBT,
    TURNED_EXPLAINED,
    TURNED_FLOOR,
    TURNED_POINTS,
    TURNED_THROUGH,
    WIDER,
)
from service.engine.verification import surface_distance

log = logging.getLogger(__name__)

NOTHING_AROUND = float(np.log10(0.01))  # ``evidence``'s ``around`` where nothing is left around
AROUND_SAID = "that no part explains"  # ``Scan.say_around``'s reason, known again by this


@dataclass
class Instance:
    """One found part: the answer of the chain for it, and the frame points it explains."""

    answer: Alignment
    entry: Entry
    claimed: np.ndarray  # (M,) indices into the searched frame's points
    distance: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))  # (M,)
    evidence: dict[str, float] = field(default_factory=dict)  # ``evidence``
    told: bool = False  # judged by the calibration of frames told their parts

    @property
    def centre(self) -> np.ndarray:
        return self.answer.rotation @ self.entry.frame.centroid + self.answer.translation


@dataclass(frozen=True)
class Found:
    """An instance as another process sends it back: its part by name (each process holds
    its own gallery), the rest as found (``Shared.gathered``)."""

    label: str
    answer: Alignment
    claimed: np.ndarray
    distance: np.ndarray
    evidence: dict[str, float]
    told: bool

    @classmethod
    def of(cls, found: Instance) -> Found:
        return cls(
            found.answer.label, found.answer, found.claimed, found.distance, found.evidence,
            found.told,
        )  # fmt: skip

    def instance(self, entry: Entry) -> Instance:
        return Instance(self.answer, entry, self.claimed, self.distance, self.evidence, self.told)


@dataclass(frozen=True)
class Claim:
    """What an answer's claim on a region holds: the region (a mask of the frame's points),
    the free points then (their indices, and the points) and the points it claimed at the
    chain's pose, which its poses are finished on, at the claim's ``tolerance``."""

    region: np.ndarray
    available: np.ndarray
    free: np.ndarray
    points: np.ndarray
    tolerance: float


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
    inside = np.flatnonzero(squared_distances(points, centre) <= reach**2)
    if not len(inside):
        return inside, np.zeros(0)
    model = (points[inside] - translation) @ rotation
    distance, _ = surface_distance(entry.surface, model, "nearest")
    close = distance < tolerance
    return inside[close], distance[close]


def claimable(
    available: np.ndarray, points: np.ndarray, entry: Entry, answer: Alignment, tolerance: float
) -> tuple[np.ndarray, np.ndarray]:
    """Of the free ``points`` (their indices ``available``), those within ``tolerance`` of the
    part's surface at the answer's pose: (indices, distances)."""
    close, distance = near_surface(points, entry, answer.rotation, answer.translation, tolerance)
    return available[close], distance


def several(instances: list[Instance]) -> list[str]:
    """The parts ``held`` ``SEVERAL`` times or more among ``instances``: a frame that holds
    several of one part (docs/decisions.md#a-part-the-frame-holds-several-of)."""
    counted = Counter(i.answer.label for i in instances if held(i))
    return sorted(label for label, count in counted.items() if count >= SEVERAL)


def held(instance: Instance) -> bool:
    """Whether ``instance`` counts towards the times its frame holds its part: a match, or one
    that would be at ``HELD_FROM``: a bin of one small part may hold no single instance sure
    enough (docs/decisions.md#several-likely-instances)."""
    return instance.answer.verdict == "match" or matchable(instance, HELD_FROM)


def matchable(instance: Instance, threshold: float) -> bool:
    """Whether ``instance`` may be a "match" at ``threshold``: ``may_match``, and
    ``MATCH_POINTS`` points claimed (docs/decisions.md#detect)."""
    enough = len(instance.claimed) >= MATCH_POINTS
    return enough and may_match(instance.evidence, instance.answer.confidence or 0.0, threshold)


def settle_claims(instances: list[Instance], count: int, keep_share: float) -> list[Instance]:
    """The global check: of two instances of one part at about one pose (``DUPLICATE_GAP``),
    the less confident goes; a point claimed by several instances goes to the one whose
    surface is nearest it; an instance left with less than ``keep_share`` of its claim is
    dropped, and its points go back to the others that claimed them."""
    instances = distinct(instances)
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


def distinct(instances: list[Instance]) -> list[Instance]:
    """The instances without those that place a part where a more confident instance of it
    already lies (the mean distance between the two placed surfaces under ``DUPLICATE_GAP``
    of its scale): one part found twice, from two of its segments."""
    kept: list[Instance] = []
    for instance in sorted(instances, key=lambda i: -(i.answer.confidence or 0.0)):
        twin = any(
            other.answer.label == instance.answer.label
            and other.entry.gap(other.answer, instance.answer) < DUPLICATE_GAP
            for other in kept
        )
        if not twin:
            kept.append(instance)
    return [i for i in instances if any(i is k for k in kept)]


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


def evidence(
    answer: Alignment,
    entry: Entry,
    claimed: int,
    region: int,
    viewpoint: np.ndarray,
    camera: DepthImage | None,
    tolerance: float,
    seen_as: Callable[[Alignment, float], float | None] | None = None,
) -> dict[str, float]:
    """What a frame says of an instance (``confidence.SCENE_FEATURES``): the chain's
    confidence for its points (as a logit; ``seen_as``: had it measured the share the camera
    shows where that is more than its coverage and the camera saw through no more than
    ``THROUGH_DOUBT`` of it), fit, coverage and margin; of what the camera
    should see of the part at its pose, the share the frame's depth shows (of what nothing
    nearer hides) and the share the camera saw through; the share of its segment's points it
    explains (and, ``ELIGIBLE_FEATURES``, log10 of the share it leaves plus 0.01), and how
    many (log10)."""
    seen, through = (answer.coverage, 0.0)
    if camera is not None:
        rotations, translations = answer.rotation[None], answer.translation[None]
        shares = seen_through(entry, rotations, translations, viewpoint, camera, tolerance)
        seen, through = float(shares[0][0]), float(shares[1][0])
    # the chain counts what neighbours hide as missed; where the camera saw through little of
    # the part, the frame tells that from what is not there (docs/decisions.md#what-the-frame-shows)
    chain = answer.confidence
    if seen_as is not None and camera is not None and through <= THROUGH_DOUBT:
        chain = seen_as(answer, max(seen, answer.coverage))
    score = answer.fit * answer.coverage
    explained = claimed / max(region, 1)
    return {
        "chain": log_odds(chain or 0.0, 1e-4),
        "fit": answer.fit,
        "coverage": answer.coverage,
        "margin": score - answer.runner_up,
        "seen": seen,
        "through": through,
        "explained": explained,
        "unexplained": float(np.log10(1 - explained + 0.01)),
        "points": float(np.log10(max(claimed, 1))),
        "around": NOTHING_AROUND,
    }


def unshared(one: Instance, other: Instance, points: np.ndarray, tolerance: float) -> int:
    """How many of the frame's ``points`` that ``one`` claims lie farther than ``tolerance``
    from ``other``'s surface at its pose (``near_surface``)."""
    answer = other.answer
    near, _ = near_surface(
        points[one.claimed], other.entry, answer.rotation, answer.translation, tolerance
    )
    return len(one.claimed) - len(near)


def around(others: np.ndarray, claimed: np.ndarray, reach: float) -> tuple[int, float]:
    """Of the frame's points ``others`` (M, 3) no instance explains, those within ``reach`` of
    an instance's ``claimed`` points (N, 3; of ``AROUND_SAMPLE`` of them, evenly): how many,
    and log10 of that per claimed point plus 0.01 (``evidence``'s ``around``)."""
    if not len(claimed):
        return 0, NOTHING_AROUND
    taken = min(len(claimed), AROUND_SAMPLE)
    mine = claimed[np.linspace(0, len(claimed) - 1, taken).astype(int)]
    low, high = mine.min(axis=0) - reach, mine.max(axis=0) + reach
    boxed = others[np.all((others >= low) & (others <= high), axis=1)]
    if not len(boxed):
        return 0, NOTHING_AROUND
    distance, _ = cKDTree(mine).query(boxed, distance_upper_bound=reach)
    count = int(np.isfinite(distance).sum())
    return count, float(np.log10(count / len(claimed) + 0.01))


def seen_through(
    entry: Entry,
    rotations: np.ndarray,
    translations: np.ndarray,
    viewpoint: np.ndarray,
    camera: DepthImage,
    tolerance: float,
) -> tuple[np.ndarray, np.ndarray]:
    """At each pose (K, 3, 3), (K, 3), of what the camera should see of the part (its nearest
    view's expected points), the share the frame's depth shows, and the share the camera saw
    through, of what nothing nearer hides: (K,) each."""
    toward = np.einsum("ki,kij->kj", viewpoint - translations, rotations)  # the camera, model
    views = entry.views.nearest(toward)
    expected = entry.surface.points[entry.expected[views]]  # (K, P, 3)
    expected = np.einsum("kpj,kij->kpi", expected, rotations) + translations[:, None]
    shown, behind = camera.look(expected, tolerance)
    counted = np.maximum((shown | behind).sum(axis=1), 1)
    return shown.sum(axis=1) / counted, behind.sum(axis=1) / counted


def chain_confidence(said: dict[str, float]) -> float:
    """The chain's own confidence for an instance's points, from its ``evidence``."""
    return from_log_odds(said["chain"])


def match_floors() -> dict[str, float]:
    """The least ``evidence`` of an instance that may be a match (``Scan.judge``): the chain's
    own confidence ``CHAIN_AGREES`` (its logit) and ``MATCH_POINTS`` points (log10); a
    detection calibration's fit on such instances is fitted on these (``eligible_at``)."""
    return {
        "chain": log_odds(CHAIN_AGREES),
        "points": float(np.log10(MATCH_POINTS)),
    }


def may_match(said: dict[str, float], confidence: float, threshold: float) -> bool:
    """Whether an instance with this ``evidence`` may be a "match" at ``confidence``: above
    the threshold, and not refused by the chain alone (``CHAIN_AGREES``): the frame's
    calibration weighs the margin to the other parts, which a small gallery inflates
    (docs/decisions.md#detect)."""
    return confidence >= threshold and chain_confidence(said) >= CHAIN_AGREES


class Shared:
    """A frame's segments searched in two processes at once: this one takes the largest left
    from the front of ``queue``, another the smallest from its back, one at a time, until
    none is left (docs/decisions.md#segments-on-two-cores). The other process searches each
    on its own, blind to what this one took: the global check settles a point both claimed."""

    def __init__(self, scan: Scan, labels: np.ndarray, queue: deque, most: int):
        self.scan, self.labels, self.queue, self.most = scan, labels, queue, most
        self.rank = {segment: k for k, segment in enumerate(queue)}  # largest first
        self.broken = False  # a search there failed: none is sent any more
        self.done: list[tuple[int, Future]] = []  # each segment sent, and its answer
        self.idle = threading.Event()  # no segment is being searched there
        self.idle.set()
        self.lock = threading.Lock()

    def front(self) -> int | None:
        """The largest segment left, taken for this process; None once none is left."""
        with self.lock:
            return self.queue.popleft() if self.queue else None

    def next(self, _: Future | None = None) -> bool:
        """The next segment (the smallest left) sent, once the one before is answered;
        whether one was."""
        with self.lock:
            if self.broken or not self.queue:
                self.idle.set()
                return False
            segment = self.queue.pop()
            self.idle.clear()
            scan = self.scan
            candidates = scan.asking(0.0)[0] if scan.told else None
            try:
                future = scan.submit(
                    "search_segments",
                    scan.frame,
                    scan.camera,
                    scan.noise,
                    scan.sizes,
                    self.labels,
                    [segment],
                    scan.free.copy(),  # what this one took so far is out there too
                    candidates,
                    scan.floor,
                    scan.min_confidence,
                    scan.deadline,
                    self.most,
                )
            except Exception:  # the other process is gone (a broken pool): searched here
                log.warning("a segment cannot be searched elsewhere", exc_info=True)
                self.queue.append(segment)
                self.broken = True
                self.idle.set()
                return False
            self.done.append((segment, future))
        future.add_done_callback(self.next)
        return True

    def gathered(self, found: list[Instance], wait: bool = True) -> list[int]:
        """What the other process found added to ``found`` (up to ``most``), its points taken
        out; the segments where nothing was found there. ``wait``: until every segment is
        answered, and those left searched here; else those answered so far. A segment whose
        search there failed (a worker died), or found a part this gallery does not hold (a
        registration landed meanwhile), goes back in turn to be searched here, and no more
        are sent."""
        scan, entries, failed = self.scan, self.scan.query.snapshot.entries, []
        answered = self.answered(wait)
        if any(records is None for _, records in answered):
            with self.lock:
                self.broken = True  # none more sent ...
            answered += self.answered(True)  # ... once the one there now is answered
        for segment, records in answered:
            if records is None:
                self.put_back(segment)
                continue
            records, missed, complete = records
            scan.complete = scan.complete and complete
            failed += missed
            for record in records[: max(0, self.most - len(found))]:
                scan.take(record.instance(entries[record.label]), found)
        while wait and (segment := self.front()) is not None:
            failed += scan.search(self.labels, [segment], self.most, found, ask_ahead=False)
        return failed

    def answered(self, wait: bool) -> list[tuple[int, tuple | None]]:
        """The segments answered there since last asked (all of them, with ``wait``), each
        with what was found, or None where the search failed or found a part this gallery
        does not hold."""
        if wait:
            self.idle.wait()
        with self.lock:
            done = [(s, f) for s, f in self.done if f.done()]
            self.done = [(s, f) for s, f in self.done if not f.done()]
        entries, answers = self.scan.query.snapshot.entries, []
        for segment, future in done:
            try:
                records = future.result()
            except Exception:  # a worker died
                log.warning("a segment's search elsewhere failed; searching here", exc_info=True)
                records = None
            if records is not None and any(r.label not in entries for r in records[0]):
                records = None
            answers.append((segment, records))
        return answers

    def put_back(self, segment: int) -> None:
        """``segment`` back in the queue, in its turn (largest first)."""
        with self.lock:
            later = [k for k, s in enumerate(self.queue) if self.rank[s] > self.rank[segment]]
            self.queue.insert(later[0] if later else len(self.queue), segment)


@dataclass
class Scan:
    """One ``Engine.detect``: the frame's points left once its supports are set aside, what
    its camera saw, and the search of its segments for instances."""

    align: Callable[..., Alignment]  # Engine.align
    seen_as: Callable[[Alignment, float], float | None]  # Engine.seen_as
    tolerance: float  # the engine's fit and coverage tolerance, share of a part's scale
    calibration: Calibration | None  # the scene calibration, if fitted
    query: Query
    frame: Frame  # thinned, supports set aside
    camera: DepthImage | None
    noise: Noise
    floor: float  # an instance is at least this confident
    min_confidence: float | None
    sizes: tuple[float, float]  # the smallest and largest scale a part here may have
    deadline: float | None = None  # time.monotonic() by which the search stops
    # an ``Engine`` method by name run elsewhere (another process), answering a future: the
    # first asks sent there at once (docs/decisions.md#detect-on-two-cores), and a share of
    # the segments searched there (``Shared``)
    submit: Callable[..., Future] | None = None
    free: np.ndarray = field(init=False)  # which points no instance has claimed yet
    cut: np.ndarray = field(init=False)  # which points lie in a region a crease split
    complete: bool = field(init=False, default=True)  # every region was searched in time
    asked: dict[tuple, tuple[np.ndarray, Future]] = field(init=False)  # sent ahead

    def __post_init__(self):
        self.free = np.ones(len(self.frame), dtype=bool)
        self.cut = np.zeros(len(self.frame), dtype=bool)
        self.asked = {}

    @property
    def told(self) -> bool:
        """Whether the request named the candidates, fewer than every registered part."""
        return len(self.query.allowed) < len(self.query.snapshot.classifier.labels)

    def narrowed(self, query: Query) -> Scan:
        """This search asking ``query`` (fewer parts) instead: what it took stays out."""
        again = replace(self, query=query)
        again.free, again.cut = self.free, self.cut
        return again

    def in_time(self) -> bool:
        """Whether there is time to search one more region (else the search is incomplete)."""
        if self.deadline is not None and time.monotonic() > self.deadline:
            self.complete = False
        return self.complete

    def instances(self, labels: np.ndarray, most: int) -> list[Instance]:
        """Each segment, largest first, searched until nothing more fits in it (``search``),
        the smallest ones meanwhile in another process (``Shared``); then the segments where
        nothing was found, with the fragments by them (``with_fragments``), then joined with a
        neighbour in the image."""
        found: list[Instance] = []
        sizes = np.bincount(labels) if len(labels) else np.zeros(0, int)
        order = [s for s in np.argsort(-sizes, kind="stable") if sizes[s] >= MIN_SEGMENT]
        queue = deque(int(s) for s in order)
        shared = Shared(self, labels, queue, most) if self.submit and len(order) >= 2 else None
        if shared is None or not shared.next():  # none sent: each searched here, in turn
            failed = self.search(labels, order, most, found)
        else:
            failed = []
            while True:
                failed += shared.gathered(found, wait=False)  # what it took is out
                if (segment := shared.front()) is None:
                    break
                failed += self.search(labels, [segment], most, found, ask_ahead=False)
            failed += shared.gathered(found)
        # the failed segments' neighbours in the image: fragments, and other failed segments
        small = np.flatnonzero((sizes > 0) & (sizes < MIN_SEGMENT))
        chosen = np.concatenate([np.asarray(failed, dtype=np.intp), small])
        near = adjacent(self.frame, labels, chosen, JOIN_PIXELS) if failed else set()
        found += self.with_fragments(
            labels, sizes, failed, set(small.tolist()), near, most - len(found)
        )
        return found + self.joined(labels, failed, near, most - len(found))

    def search(
        self,
        labels: np.ndarray,
        order: list[int],
        most: int,
        found: list[Instance],
        ask_ahead: bool = True,
    ) -> list[int]:
        """The segments ``order`` searched in turn, each until nothing more fits in it
        (``MAX_TRIES`` searches at most), the instances added to ``found``: once an instance
        is taken out, each piece of what is left (``pieces``), and once more what is left of a
        region where nothing was found that it took points from (``freed``). The segments
        where nothing was found at the first search."""
        failed: list[int] = []
        if ask_ahead:
            self.ask_ahead([np.flatnonzero(labels == segment) for segment in order])
        for segment in order:
            pending, tries = [np.flatnonzero(labels == segment)], 0
            missed: list[np.ndarray] = []  # the regions of it where nothing was found
            again: list[np.ndarray] = []  # ... that an instance took points from since
            while len(found) < most:
                retry = not pending or tries >= MAX_TRIES  # the segment's own searches done
                if retry and not again:
                    break
                region = again.pop(0) if retry else pending.pop(0)
                region = region[self.free[region]]
                if not self.worth_searching(region):
                    continue
                if not self.in_time():
                    return failed
                tries += 0 if retry else 1
                instance = self.instance(region)
                if instance is None:  # touching parts, a depth jump between them
                    failed += [segment] if tries == 1 and not retry else []
                    missed.append(region)
                    if not retry:  # finer pieces first; a crease's after the rest
                        finer = self.finer(region)
                        pending = finer + pending if finer else pending + self.creased(region)
                    continue
                self.take(instance, found)
                pieces = self.pieces(region[self.free[region]])
                self.ask_ahead(pieces[: MAX_TRIES - tries])
                pending = pieces + pending
                freed, missed = self.freed(missed, pending + again)
                again += freed
        return failed

    def joined(self, labels: np.ndarray, failed: list[int], near: set, most: int) -> list:
        """The failed segments that ``near`` pairs, each pair searched as one region (no wider
        than ``JOIN_SCALES`` of the largest part), ``MAX_JOINS`` at most: a part a jump in
        depth cut in two; then each failed segment with all its failed neighbours, where it
        has two or more, as many at most: a part cut in three
        (docs/decisions.md#a-part-cut-in-three). A region whose points were claimed since is
        skipped."""
        pairs = sorted((a, b) for a, b in near if a in failed and b in failed)
        neighbours: dict[int, set[int]] = {}
        for a, b in pairs:
            neighbours.setdefault(a, set()).add(b)
            neighbours.setdefault(b, set()).add(a)
        stars: dict[frozenset, tuple] = {}  # three segments all near each other: one star
        for a, n in sorted(neighbours.items()):
            if len(n) >= 2:
                stars.setdefault(frozenset({a, *n}), (a, *sorted(n)))
        found: list[Instance] = []
        for ways in (pairs, list(stars.values())):
            joins = 0
            for group in ways:
                if len(found) >= most or joins == MAX_JOINS:
                    break
                region = np.flatnonzero(np.isin(labels, group) & self.free)
                if not self.worth_searching(region):  # few points, or none left free
                    continue
                if radius(self.frame.points[region]) > JOIN_SCALES * self.sizes[1]:
                    continue
                if not self.in_time():
                    return found
                joins += 1
                instance = self.instance(region)
                if instance is not None:
                    self.take(instance, found)
        return found

    def with_fragments(
        self,
        labels: np.ndarray,
        sizes: np.ndarray,
        failed: list[int],
        small: set[int],
        near: set,
        most: int,
    ) -> list[Instance]:
        """The segments where nothing was found, each searched once more with the fragments
        next to it in the image (the ``small`` segments, too small to be searched alone, that
        ``near`` pairs with it) where they add ``FRAGMENTS_ADD`` of its points: a part's points
        that a jump in depth cut off (docs/decisions.md#detect). A segment an instance is
        found in is no longer failed."""
        pieces: dict[int, list[int]] = {}
        for a, b in near:
            if a in failed and b in small:
                pieces.setdefault(a, []).append(b)
            elif b in failed and a in small:
                pieces.setdefault(b, []).append(a)
        found: list[Instance] = []
        for segment, fragments in sorted(pieces.items()):
            if len(found) >= most or not self.in_time():
                break
            if sizes[fragments].sum() < FRAGMENTS_ADD * sizes[segment]:
                continue  # a few points more: the same answer
            region = np.flatnonzero(np.isin(labels, [segment, *fragments]) & self.free)
            if not self.worth_searching(region):
                continue
            instance = self.instance(region, place=False)  # its views were placed before
            if instance is not None:
                self.take(instance, found)
                failed.remove(segment)
        return found

    def freed(
        self, missed: list[np.ndarray], pending: list[np.ndarray]
    ) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Of the regions where nothing was found, those an instance since took points from,
        to be searched again without them and without what is to be searched anyway
        (``pending``), where ``MIN_SEGMENT`` points are left; and the rest: a part beside
        another one is posed once its neighbour's points are out
        (docs/decisions.md#a-region-searched-again)."""
        planned = np.zeros(len(self.frame), dtype=bool)
        for region in pending:
            planned[region] = True
        again: list[np.ndarray] = []
        kept: list[np.ndarray] = []
        for region in sorted(missed, key=len, reverse=True):
            left = region[self.free[region]]
            if len(left) == len(region):
                kept.append(region)
                continue
            left = left[~planned[left]]
            if len(left) >= MIN_SEGMENT:
                again.append(left)
                planned[left] = True
        return again, kept

    def pieces(self, region: np.ndarray) -> list[np.ndarray]:
        """What is left of a segment once an instance is taken out of it, in the pieces it
        falls into (``PIECE_CELLS``), largest first; those too small to search left out. A
        small part touching a large one is then searched without the large one's strays
        beyond it (docs/decisions.md#detect)."""
        if len(region) < MIN_SEGMENT:
            return []
        group = self.groups_of(self.frame.points[region])
        sizes = np.bincount(group)
        order = np.argsort(-sizes, kind="stable")
        return [region[group == g] for g in order if sizes[g] >= MIN_SEGMENT]

    def groups_of(self, points: np.ndarray) -> np.ndarray:
        """(N,) a group label per point: ``cell_groups`` of cells ``PIECE_CELLS`` spacings
        wide, what ``pieces`` and ``bulk`` part a region by."""
        return cell_groups(points, PIECE_CELLS * self.spacing)

    def finer(self, region: np.ndarray) -> list[np.ndarray]:
        """A region the search found nothing in (a segment, or what is left of one), split at
        finer jumps in depth (``FINER_LINKS``, the first that parts it), largest first: two parts
        touching, one in front of the other, join at the usual links but part at finer ones
        (docs/decisions.md#a-segment-split-finer). Empty where no level parts it."""
        frame = self.frame.take(region)
        for links in FINER_LINKS:
            parts = self.split(region, segments(frame, self.frame.pixel_angle(), links))
            if parts:
                return parts
        return []

    def creased(self, region: np.ndarray) -> list[np.ndarray]:
        """A region the search found nothing in and no finer jump in depth parts, split at the
        creases where parts touch (``segments.creases``), largest first; empty where none
        parts it (docs/decisions.md#touching-parts-split-at-a-crease)."""
        pieces = self.split(region, creases(self.frame.take(region)))
        if pieces:
            self.cut[region] = True
        return pieces

    @staticmethod
    def split(region: np.ndarray, labels: np.ndarray) -> list[np.ndarray]:
        """The pieces of ``region`` that ``labels`` (one per point) make, largest first,
        those too small to search left out; empty unless two or more are left."""
        sizes = np.bincount(labels)
        order = [g for g in np.argsort(-sizes, kind="stable") if sizes[g] >= MIN_SEGMENT]
        return [region[labels == g] for g in order] if len(order) >= 2 else []

    def take(self, instance: Instance, found: list[Instance]) -> None:
        """``instance`` added to ``found``, its points out of the search."""
        found.append(instance)
        self.free[instance.claimed] = False

    def worth_searching(self, region: np.ndarray) -> bool:
        """Whether a region holds enough points, spread wide enough, to be a part: at least
        ``MIN_SEGMENT``, and a radius of ``FRAGMENT`` of the smallest part's scale."""
        if len(region) < MIN_SEGMENT:
            return False
        return radius(self.frame.points[region]) >= FRAGMENT * self.sizes[0]

    def instance(self, region: np.ndarray, place: bool = True) -> Instance | None:
        """The chain's answer for the points ``region`` as an instance claiming the free
        points near its surface; else, among few plausible parts, the likeliest parts' views
        placed over the region, and the chain asked about the points the best explains, then
        the next best (``TEMPLATES_ASKED``; docs/decisions.md#a-supports-rim-given-back). None
        if neither explains enough."""
        region = self.bulk(region)
        points = self.frame.points[region]
        sigma = self.noise.at(points, self.frame.viewpoint)
        answer = self.answer_for(points, sigma)
        found = self.claim(region, answer, sigma)
        if found is None and len(points) > SEGMENT_POINTS:  # one sample may mislead the chain
            found = self.claim(region, self.ask(self.another_sample(points), sigma), sigma)
        if found is not None:
            return found
        if not place or not self.may_hold_several(points, answer):
            return None
        spacing = self.spacing
        for entry in self.template_parts(points, spacing):
            tolerance = self.part_tolerance(entry, sigma)
            poses = place_views(
                entry,
                points,
                self.frame.viewpoint,
                spacing,
                tolerance / entry.reference.scale,
                self.query.rng,
                self.camera,
            )
            for pose in poses[:TEMPLATES_ASKED]:
                close, _ = near_surface(
                    points, entry, pose.rotation, pose.translation, CLAIM_TOLERANCE * tolerance
                )
                if len(close) < MIN_EXPLAINED:
                    continue
                found = self.claim(region, self.answer_for(points[close], sigma), sigma)
                if found is not None:
                    return found
        return None

    def bulk(self, region: np.ndarray) -> np.ndarray:
        """``region`` without its strays: the groups (``groups_of``) too small to be a segment
        that lie beyond the rest's radius (a flying pixel, what a neighbour's claim left),
        where they are ``STRAYS`` of it at most. The chain scales a cloud by its radius, and
        one such point may double it (docs/decisions.md#a-regions-strays)."""
        points = self.frame.points[region]
        group = self.groups_of(points)
        big = np.bincount(group)[group] >= MIN_SEGMENT
        if big.all() or big.sum() < (1 - STRAYS) * len(region):
            return region
        centre = points[big].mean(axis=0)
        within = squared_distances(points, centre) <= radius(points[big], centre) ** 2
        keep = big | within
        return region if keep.all() else region[keep]

    def may_hold_several(self, points: np.ndarray, answer: Alignment) -> bool:
        """Whether a region the chain found nothing in may hold several parts: the chain's
        best part explains little of it (``TEMPLATE_FIT``), or it is wider than that part."""
        if answer.hypothesis == "none":  # no part of its size
            return radius(points) > self.sizes[1]
        scale = self.query.snapshot.entries[answer.label].reference.scale
        return answer.fit < TEMPLATE_FIT or radius(points) > WIDER * scale

    def answer_for(self, points: np.ndarray, sigma: float) -> Alignment:
        """The chain's answer for a segment's points (``SEGMENT_POINTS`` of them at most, drawn
        by the search's generator), nothing set aside."""
        return self.ask(points[subsample(points, SEGMENT_POINTS, self.query.rng)], sigma)

    def ask_ahead(self, regions: list[np.ndarray]) -> None:
        """The chain's first ask about each region of at most ``SEGMENT_POINTS`` points (asked
        about them all, as ``instance`` will ask: no draw) sent to ``submit`` at once, so that
        another process answers them while this one claims and judges. A larger region's ask
        is about a sample the search draws when it gets there, and stays here, so that the
        answers are those of a search alone (docs/decisions.md#detect-on-two-cores). An ask
        no longer made (its region shrank) is cancelled by ``settle``."""
        if self.submit is None:
            return
        for region in regions:
            region = self.bulk(region[self.free[region]])
            if len(region) <= SEGMENT_POINTS and self.worth_searching(region):
                points = self.frame.points[region]
                self.send(points, self.noise.at(points, self.frame.viewpoint))

    def send(self, sample: np.ndarray, sigma: float) -> None:
        """The chain's ask about ``sample`` sent to ``submit``, kept in ``asked``."""
        if self.submit is None:
            return
        try:
            candidates, kwargs = self.asking(sigma)
            future = self.submit("align", sample, candidates, **kwargs)
        except Exception:  # the other process is gone (a broken pool): all asked here
            log.warning("asks cannot be sent ahead; asking here", exc_info=True)
            self.submit = None
            return
        self.asked[self.ask_key(sample, sigma)] = (sample, future)

    def settle(self) -> None:
        """The asks sent ahead that no region needed, cancelled (or left to finish)."""
        for _, future in self.asked.values():
            future.cancel()
        self.asked.clear()

    def ask_key(self, points: np.ndarray, sigma: float) -> tuple:
        """What an ask asks, as a key of ``asked`` (its points compared on a hit)."""
        return (len(points), hash(points.tobytes()), sigma, tuple(self.query.allowed))

    def asking(self, sigma: float) -> tuple[list[str], dict]:
        """``Engine.align``'s arguments for a region's points, but the points: the
        candidates, and the rest by name."""
        labels = self.query.snapshot.classifier.labels
        return [labels[row] for row in self.query.allowed], {
            "viewpoint": self.frame.viewpoint,
            "min_confidence": self.min_confidence,
            "surroundings": False,
            "noise": sigma,
            # a segment may be a view of a part the network ranks low (a duck seen from one
            # side): docs/decisions.md#more-parts-tried-for-a-segment
            "rescued": SEGMENT_RESCUED,
        }

    @staticmethod
    def another_sample(points: np.ndarray, count: int = SEGMENT_POINTS) -> np.ndarray:
        """``count`` of ``points`` drawn apart from the search's own draws (which stay as they
        were), the same for the same points."""
        return points[subsample(points, count, Scan.apart(points))]

    @staticmethod
    def apart(points: np.ndarray) -> np.random.Generator:
        """A generator for draws from ``points`` apart from the search's own, the same for the
        same points (``another_sample``, ``turned_over``)."""
        return np.random.default_rng(len(points))

    def ask(self, points: np.ndarray, sigma: float = 0.0) -> Alignment:
        """The chain's answer for ``points``, nothing set aside: asked ahead, or here."""
        sent, ahead = self.asked.pop(self.ask_key(points, sigma), (None, None))
        if ahead is not None and np.array_equal(sent, points):
            try:
                answer = ahead.result()
            except Exception:  # the other process failed it (a worker died): asked here
                log.warning("an ask sent ahead failed; asking here", exc_info=True)
            else:  # a part registered or removed meanwhile is not this snapshot's: asked here
                if answer.label in self.query.snapshot.entries:
                    return answer
        candidates, kwargs = self.asking(sigma)
        return self.align(points, candidates, **kwargs)

    def template_parts(self, points: np.ndarray, spacing: float) -> list[Entry]:
        """The parts to place over a segment: of those that fit inside it and are not far
        smaller (``TEMPLATE_SIZES``), the ``TEMPLATE_PARTS`` whose views fit it best; none
        where more than ``TEMPLATE_POOL`` do. Among many parts the coarse ranking seldom picks
        the right one, and a placement and the ask after it cost two asks: a frame told its
        parts, or served by a small gallery, places them
        (docs/decisions.md#placed-views-among-few-parts)."""
        size = radius(points)
        low, high = TEMPLATE_SIZES
        snapshot = self.query.snapshot
        labels = snapshot.classifier.labels
        rows = [r for r in self.query.allowed if low * size <= snapshot.scales[r] <= high * size]
        if len(rows) > TEMPLATE_POOL:
            return []
        entries = [snapshot.entries[labels[r]] for r in rows]
        return likeliest(
            entries,
            points,
            self.frame.viewpoint,
            spacing,
            self.query.rng,
            self.camera,
            TEMPLATE_PARTS,
        )

    @cached_property
    def spacing(self) -> float:
        """The distance between neighbouring points of the frame at its median range."""
        if not len(self.frame):
            return 0.0
        angle = self.frame.pixel_angle()
        return angle * self.frame.step * float(np.median(self.frame.ranges()))

    def part_tolerance(self, entry: Entry, sigma: float) -> float:
        """The fit tolerance for a part here: its share of the scale, never under the
        sensor's noise (``Query.tolerance``)."""
        return max(self.tolerance * entry.reference.scale, NOISE_TOLERANCES * sigma)

    def claim_tolerance(self, entry: Entry, sigma: float) -> float:
        """How near a part's surface here a point must lie to be claimed."""
        return CLAIM_TOLERANCE * self.part_tolerance(entry, sigma)

    def claim(
        self, region: np.ndarray, answer: Alignment, sigma: float, again: bool = True
    ) -> Instance | None:
        """``answer`` as an instance claiming the free points near its surface, judged; None
        if it is no registered part, explains fewer than ``MIN_EXPLAINED`` of ``region``, or
        is less confident than the floor."""
        if answer.verdict == "no_match" and answer.hypothesis == "none":
            return None
        entry = self.query.snapshot.entries[answer.label]
        tolerance = self.claim_tolerance(entry, sigma)
        available = np.flatnonzero(self.free)
        free = self.frame.points[available]
        claimed, _ = claimable(available, free, entry, answer, tolerance)
        in_region = np.zeros(len(self.frame), dtype=bool)
        in_region[region] = True
        if in_region[claimed].sum() < MIN_EXPLAINED:
            return None
        chain = replace(answer, reasons=list(answer.reasons or []))  # as the chain gave it
        claim = Claim(in_region, available, free, self.frame.points[claimed], tolerance)
        instance = self.posed(answer, entry, claim)
        if instance is None:
            return None
        instance = self.turned(instance, chain, claim)
        instance = self.told_apart(instance, chain, claim, sigma)
        doubted = instance.answer.verdict != "match"
        if again and doubted and instance.answer.confidence >= INSTANCE_FLOOR:
            instance = self.asked_again(region, instance, sigma)
        if (instance.answer.confidence or 0.0) < self.floor:
            return None
        return instance

    def posed(
        self,
        answer: Alignment,
        entry: Entry,
        claim: Claim,
        rng: np.random.Generator | None = None,
    ) -> Instance | None:
        """``answer``'s pose finished on the points its claim holds (the chain saw a sample of
        a region; drawn by ``rng``, else the search's generator), as an instance claiming the
        free points near it, judged; None if it explains fewer than ``MIN_EXPLAINED`` of the
        region."""
        tolerance = claim.tolerance
        self.finish(answer, entry, claim.points, tolerance / CLAIM_TOLERANCE, rng)
        claimed, distance = claimable(claim.available, claim.free, entry, answer, tolerance)
        inside = int(claim.region[claimed].sum())
        if inside < MIN_EXPLAINED:
            return None
        instance = Instance(answer, entry, claimed, distance)
        instance.evidence = evidence(
            answer,
            entry,
            inside,
            int(claim.region.sum()),
            self.frame.viewpoint,
            self.camera,
            tolerance,
            self.seen_as,
        )
        self.judge(instance)
        return instance

    def turned(self, instance: Instance, chain: Alignment, claim: Claim) -> Instance:
        """A doubted instance the camera saw through (``THROUGH_DOUBT``) posed again where
        the camera sees through it least, if under half as much (``TURNED_THROUGH``): at
        its part's near turns, or at the other poses the chain found fitting alike (its
        ``closest`` and ``alternatives``); the more confident of the two. The chain tells
        such poses apart by how near its points lie to the surface, which hardly differs;
        what the camera saw through where the part would be does
        (docs/decisions.md#a-near-turn-the-camera-sees-through). Where none is seen through
        less, the instance is ``turned_over``."""
        through = instance.evidence["through"]
        if instance.answer.verdict == "match" or self.camera is None or through <= THROUGH_DOUBT:
            return instance
        rotations, translations = self.other_poses(instance, chain)
        if len(rotations):
            best = self.least_seen_through(instance, rotations, translations, claim)
            if best is not None:
                again = replace(chain, rotation=rotations[best], translation=translations[best])
                other = self.posed(again, instance.entry, claim)
                better = other is not None and other.answer.confidence > instance.answer.confidence
                return other if better else instance
        return self.turned_over(instance, chain, claim)

    def turned_over(self, instance: Instance, chain: Alignment, claim: Claim) -> Instance:
        """A doubted instance that no other pose of ``turned`` explains better, turned by a
        quarter, a half and three quarters about each of its part's principal axes, each
        refined on the claim's points: where the camera sees through the best of them under
        ``TURNED_THROUGH`` as much, and it is a match explaining as much of the region (to
        within ``TURNED_EXPLAINED``), that instance. Not tried where the frame gives the
        instance little chance (``TURNED_FLOOR``: mostly another part's points). A part whose
        ends look alike (a robot's link) is often posed a quarter turn off about its length,
        and no near turn names that (docs/decisions.md#turned-over)."""
        entry, answer = instance.entry, instance.answer
        if answer.confidence < TURNED_FLOOR:
            return instance
        frame = entry.frame
        rotations, translations = turned_about(
            answer.rotation, answer.translation, frame.quarter_turns, frame.centroid
        )
        # drawn apart from the search's own draws, which stay as they were: a turn not kept
        # changes nothing after it
        sample = self.another_sample(claim.points, TURNED_POINTS)
        tolerance = claim.tolerance / CLAIM_TOLERANCE
        rotations, translations = self.refined(entry, sample, rotations, translations, tolerance)
        best = self.least_seen_through(instance, rotations, translations, claim)
        if best is None:
            return instance
        again = replace(chain, rotation=rotations[best], translation=translations[best])
        other = self.posed(again, entry, claim, self.apart(claim.points))
        if other is None or other.answer.verdict != "match":
            return instance
        # a pose the camera sees through less may lie behind what it sees: it explains less
        short = instance.evidence["explained"] - other.evidence["explained"]
        return other if short <= TURNED_EXPLAINED else instance

    def least_seen_through(
        self, instance: Instance, rotations: np.ndarray, translations: np.ndarray, claim: Claim
    ) -> int | None:
        """Of the poses (K, 3, 3), (K, 3), the one the camera sees through least, where under
        ``TURNED_THROUGH`` as much as the instance (at the tolerance of its own evidence)."""
        _, shares = seen_through(
            instance.entry, rotations, translations, self.frame.viewpoint, self.camera,
            claim.tolerance,
        )  # fmt: skip
        best = int(np.argmin(shares))
        return best if shares[best] < TURNED_THROUGH * instance.evidence["through"] else None

    def told_apart(
        self, instance: Instance, chain: Alignment, claim: Claim, sigma: float
    ) -> Instance:
        """An instance whose look-alikes fit alike (``doubt``), posed as each of them too, at
        the chain's pose for it: where one part explains ``ALIKE_EXPLAINED`` more of its
        region's points than each other, and the camera sees through it no more than
        ``ALIKE_THROUGH`` more, or its claim alone shows a face the others lack
        (``shows_face``), the frame tells them apart. That part's instance, judged on the
        chain's confidence undivided among them; else the instance as it was. In a region a
        crease split, an instance of a part with look-alikes is doubted whatever the chain
        said, and told apart only by a face: the crease may have cut it off into a piece
        beside the region, where a claim still reaches it and the region's shares do not
        (docs/decisions.md#touching-parts-split-at-a-crease,
        docs/decisions.md#a-face-one-look-alike-lacks)."""
        answer = instance.answer
        cut = bool(self.cut[claim.region].any())
        unnamed: tuple[str, ...] = ()  # look-alikes the chain did not pose
        if cut and not answer.look_alikes:
            unnamed = self.query.snapshot.look_alikes.get(answer.label, ())
            if unnamed:
                answer.look_alikes = list(unnamed)
                doubt(answer, share=False)
        if not answer.look_alikes or self.camera is None:
            return instance
        alone = undoubted(chain)
        answers = [alone]
        for other in chain.alternatives:
            if other.label in answer.look_alikes:
                answers.append(self.posed_as(alone, other.label, other.rotation, other.translation))
        points = self.another_sample(self.frame.points[claim.region]) if unnamed else None
        for label in unnamed:  # asked told that part alone, on the region's points
            told = self.align(points, [label], **self.asking(sigma)[1])
            if told.label == label and told.hypothesis != "none":
                answers.append(self.posed_as(alone, label, told.rotation, told.translation))
        posed = []
        for each in answers:
            entry = self.query.snapshot.entries[each.label]
            tolerance = self.claim_tolerance(entry, sigma)
            again = self.posed(each, entry, replace(claim, tolerance=tolerance))
            if again is None:  # one explains too little to be told from: the doubt stands
                return instance
            posed.append(again)
        best = max(posed, key=lambda p: p.evidence["explained"])
        if not cut and all(self.explains_more(best, o) for o in posed if o is not best):
            return best
        faced = [p for p in posed if all(self.shows_face(p, o, sigma) for o in posed if o is not p)]
        return faced[0] if len(faced) == 1 and len(posed) > 1 else instance

    @staticmethod
    def posed_as(
        answer: Alignment, label: str, rotation: np.ndarray, translation: np.ndarray
    ) -> Alignment:
        """``answer`` as another part's, at that part's pose."""
        return replace(
            answer,
            label=label,
            rotation=rotation,
            translation=translation,
            alternatives=[],  # its own other poses were not searched
            ambiguous=False,
        )

    @staticmethod
    def explains_more(best: Instance, other: Instance) -> bool:
        """Whether ``best`` explains ``ALIKE_EXPLAINED`` more of its region's points than
        ``other``, seen through no more than ``ALIKE_THROUGH`` more."""
        more = best.evidence["explained"] - other.evidence["explained"]
        through = best.evidence["through"] - other.evidence["through"]
        return more >= ALIKE_EXPLAINED and through <= ALIKE_THROUGH

    def shows_face(self, one: Instance, other: Instance, sigma: float) -> bool:
        """Whether ``one``'s claim holds a face ``other`` lacks: ``ALIKE_FACE_SHARE`` of its
        points (``ALIKE_FACE_POINTS`` at least) lie beyond ``other``'s claim tolerance of its
        surface at its pose, ``ALIKE_FACE_RATIO`` times as many as ``other``'s claim holds so
        from ``one``'s. Counted on the frame's own points, which may lie beyond the region,
        not on a rendered view's sample; and only where the camera sees through ``other``'s
        pose no more than ``ALIKE_FACE_THROUGH`` more than ``one``'s: a look-alike asked about
        alone may be posed poorly, and any pose shows a face a poor one lacks
        (docs/decisions.md#a-face-one-look-alike-lacks)."""
        if other.evidence["through"] > one.evidence["through"] + ALIKE_FACE_THROUGH:
            return False  # a pose the camera sees through is no pose to compare faces with
        mine = unshared(one, other, self.frame.points, self.claim_tolerance(other.entry, sigma))
        theirs = unshared(other, one, self.frame.points, self.claim_tolerance(one.entry, sigma))
        least = max(ALIKE_FACE_POINTS, ALIKE_FACE_SHARE * len(one.claimed))
        return mine >= least and mine >= ALIKE_FACE_RATIO * theirs

    @staticmethod
    def other_poses(instance: Instance, chain: Alignment) -> tuple[np.ndarray, np.ndarray]:
        """The poses ``turned`` tries: the instance's turned by each of its part's near
        turns, and the chain's other poses of the part. (K, 3, 3), (K, 3)."""
        symmetry, answer = instance.entry.symmetry, instance.answer
        rotations, translations = turned_about(
            answer.rotation, answer.translation, symmetry.near_tried, symmetry.centroid
        )
        others = [p for p in [chain.closest, *chain.alternatives] if p and p.label is None]
        if others:
            rotations = np.concatenate([rotations, np.stack([p.rotation for p in others])])
            translations = np.concatenate([translations, np.stack([p.translation for p in others])])
        return rotations, translations

    def asked_again(self, region: np.ndarray, instance: Instance, sigma: float) -> Instance:
        """A posed instance the frame does not confirm, with the chain asked once more about
        just the points it claims: a segment's sample may have posed it poorly, or its
        neighbours' points misled the search (docs/decisions.md#detect). The more confident
        of the two; the search's own draws are left as they were."""
        points = self.frame.points[instance.claimed]
        second = self.claim(region, self.ask(self.another_sample(points), sigma), sigma, False)
        better = second is not None and second.answer.confidence > instance.answer.confidence
        return second if better else instance

    def finish(
        self,
        answer: Alignment,
        entry: Entry,
        points: np.ndarray,
        tolerance: float,
        rng: np.random.Generator | None = None,
    ):
        """``answer``'s pose refined by ICP on (a sample of) the points it claims (drawn by
        ``rng``, else the search's generator), told where the camera was, and its canonical
        pose among those its symmetry makes equivalent; its alignment error measured on them."""
        sample = points[subsample(points, FINISH_POINTS, rng or self.query.rng)]
        (rotation,), (translation,) = self.refined(
            entry, sample, answer.rotation[None], answer.translation[None], tolerance
        )
        answer.rotation, answer.translation = entry.symmetry.canonical(rotation, translation)
        error = alignment_error(sample, entry.point_tree, answer.rotation, answer.translation)
        answer.alignment_error = error
        answer.alignment_error_normalized = error / entry.reference.scale

    def refined(
        self,
        entry: Entry,
        sample: np.ndarray,
        rotations: np.ndarray,
        translations: np.ndarray,
        tolerance: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The poses (K, 3, 3), (K, 3) refined together by ICP on ``sample``
        (``FINISH_ITERATIONS``), told where the camera was."""
        starts = [
            Start.at_tolerance(
                entry.surface, rotation, translation, tolerance, FINISH_ITERATIONS,
                self.frame.viewpoint,
            )
            for rotation, translation in zip(rotations, translations, strict=True)
        ]  # fmt: skip
        refined = icp_many(sample, starts)
        return np.stack([r for r, _, _ in refined]), np.stack([t for _, t, _ in refined])

    def judged_around(self, instances: list[Instance]) -> list[Instance]:
        """Each instance judged again once the frame is searched, by the calibration's
        ``settled`` fit: on the frame's points that no listed instance explains within
        ``AROUND_SCALES`` of its part's scale of its points (``around``) as well. A part
        fitted on a piece of a larger one that nothing explains has the rest of it around;
        one lying alone has the support (docs/decisions.md#what-is-left-around). Not those
        judged as told (no such fit); those then less confident than the floor go."""
        unexplained = np.ones(len(self.frame), dtype=bool)
        for instance in instances:  # what the listed instances explain (a calibration's: all)
            if (instance.answer.confidence or 0.0) >= INSTANCE_FLOOR:
                unexplained[instance.claimed] = False
        others = self.frame.points[unexplained]
        settled = self.calibration.settled if self.calibration is not None else None
        judged = []
        for instance in instances:
            reach = AROUND_SCALES * instance.entry.reference.scale
            _, share = around(others, self.frame.points[instance.claimed], reach)
            instance.evidence["around"] = share
            if settled is not None and not instance.told:
                self.judge(instance, settled)
                if (instance.answer.confidence or 0.0) < self.floor:
                    continue
            judged.append(instance)
        return judged

    def judge(self, instance: Instance, calibration: Calibration | None = None) -> None:
        """The instance's confidence from the scene calibration (or ``calibration``), where
        one is fitted, its verdict and reasons; else the chain's own."""
        answer, said = instance.answer, instance.evidence
        if self.calibration is None:
            return
        instance.told = calibration is None and self.told and self.calibration.told is not None
        calibration = calibration or self.calibration
        if instance.told:
            calibration = calibration.told
        answer.confidence = calibration.confidence(said)
        threshold = next(t for t in (self.min_confidence, calibration.accept) if t is not None)
        if matchable(instance, threshold):
            answer.verdict, answer.reasons = "match", []
            doubt(answer, share=False)  # the chain's confidence, shared among them, is a feature
            self.say_around(instance)  # a look-alike doubted
            return
        answer.verdict = "uncertain" if answer.confidence >= 0.2 else "no_match"
        reasons = []
        if answer.confidence < threshold:
            reasons.append(
                f"the confidence {answer.confidence:.2f} is below the threshold {threshold:.2f}"
            )
        if len(instance.claimed) < MATCH_POINTS:
            reasons.append(
                f"only {len(instance.claimed)} of the frame's points (thinned) are explained by "
                f"{answer.label}, fewer than the {MATCH_POINTS} a match needs: too few to tell "
                "it from parts that look alike; image it closer, or with less hidden"
            )
        if (chain := chain_confidence(said)) < CHAIN_AGREES:
            reasons.append(
                f"the one-part search alone is {chain:.2f} confident of {answer.label} here, "
                f"under the {CHAIN_AGREES:.2f} a match needs whatever the frame says"
            )
        if said["through"] > THROUGH_DOUBT:
            reasons.append(
                f"the camera saw through {said['through']:.0%} of where {answer.label} would "
                "be at this pose: another part, or another pose"
            )
        if said["seen"] < 0.7:
            reasons.append(
                f"only {said['seen']:.0%} of what the camera should see of {answer.label} is "
                "in view: it may be hidden by others, or not this part"
            )
        earlier = [r for r in answer.reasons if "threshold" not in r]  # judged before, too
        answer.reasons = list(dict.fromkeys(reasons + earlier))
        doubt(answer, share=False)
        self.say_around(instance)

    @staticmethod
    def say_around(instance: Instance) -> None:
        """A reason for an instance not a match with ``AROUND_DOUBT`` of its points' count
        around it, once the frame is searched (``judged_around``); the one said when it was
        judged before goes (a part found several times judges it again)."""
        answer, said = instance.answer, instance.evidence
        answer.reasons = [r for r in answer.reasons if AROUND_SAID not in r]
        if answer.verdict == "match" or said["around"] < np.log10(AROUND_DOUBT + 0.01):
            return
        share = 10 ** said["around"] - 0.01
        answer.reasons.append(
            f"{round(share * len(instance.claimed))} of the frame's points {AROUND_SAID} "
            f"lie around it ({share:.0%} of those it explains): it may be a piece of a part not "
            "registered or not found"
        )

    def answer(
        self,
        frame: Frame,
        seen: np.ndarray,
        supports: list[Support],
        instances: list[Instance],
        clock: Stopwatch,
    ) -> SceneAnswer:
        """The detections at the frame's full resolution (``seen``: its points off the
        supports), best first."""
        kept = frame.take(seen)

        def tolerance(instance: Instance) -> float:
            sigma = self.noise.at(instance.centre[None], frame.viewpoint)
            return self.claim_tolerance(instance.entry, sigma)

        owned = frame_indices(kept, instances, tolerance)
        detections = [
            Detection(i.answer, kept.index[mine], i.entry.symmetry.describe(), i.evidence)
            for i, mine in zip(instances, owned, strict=True)
            if len(mine)
        ]
        detections.sort(key=lambda d: -(d.answer.confidence or 0.0))
        explained = sum(len(d.indices) for d in detections)
        clock.lap("explained points")
        reasons = (
            []
            if self.complete
            else [
                "the search ran out of its time budget before every region of the frame was "
                "searched: send a region of interest (roi), fewer candidates, or a coarser frame"
            ]
        )
        return SceneAnswer(
            detections,
            len(frame),
            int(seen.sum()) - explained,
            [s.plane for s in supports],
            clock.total(),
            self.complete,
            reasons,
        )
