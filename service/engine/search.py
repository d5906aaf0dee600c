"""Steps 5-7 of ``Engine.align`` for one reading: hypothesise poses of each candidate part,
verify them (fit x coverage), refine the best (point-to-plane ICP), pass by pass; then the
best pose's flips, near-symmetries and finishing refinement (``finish``).

A pass is a ``Plan``: which sources each candidate row is hypothesised from, how many of the
verified hypotheses are refined, and whether more parts are rescued when none fits well.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from service.engine import hypotheses as sources
from service.engine.alignment import turned_about
from service.engine.answer import CandidateFit
from service.engine.entry import Entry
from service.engine.fits import Fit
from service.engine.hypotheses import Hypotheses
from service.engine.icp import Start, icp_many
from service.engine.normalize import radius, subsample
from service.engine.principal_axes import Frame
from service.engine.query import Observed, Query
from service.engine.symmetry import FINE_DEG, apart
from service.engine.tuning import (
    ALIKE,
    ALONE_FROM,
    DIFFERENT_DEG,
    ENOUGH_BEHIND,
    EXPECTED,
    FAR_BELOW,
    FIRST_LEAD,
    FIRST_REFINED,
    NEAR_PRESCREENED,
    NEAR_SCREENED,
    PER_PART,
    QUICK_POINTS,
    RESCUE_BELOW,
    RESCUE_EACH,
    RESIDUAL_ALIKE,
    SCREEN_ALIKE,
)
from service.engine.verification import Lookup, Occupancy, coverage, fit, surface_distance
from service.engine.views import camera_at
from service.settings import EngineSettings

NEAR_SOURCE = "near-symmetry"  # the hypothesis of a pose found by turning the best one
FLIP_SOURCE = "flip"  # ... by turning it half a turn about a principal axis of its part


@dataclass(frozen=True)
class Plan:
    """One pass of the search: hypotheses of each row from its sources, the best ``budget``
    refined (and eq. (4)'s sure ``first`` choice's in any case), ``screened`` kept of each
    row's quick look (default ``settings.screened``), and with ``rescue`` more parts' refined
    where none fits well."""

    sources: dict[int, list[str]]  # classifier row -> hypothesis sources
    budget: int
    first: int | None = None
    rescue: bool = False
    screened: int | None = None


def excellent(fits: list[Fit], settings: EngineSettings) -> bool:
    """Whether the best fit so far ends the search."""
    return any(f.score >= settings.excellent for f in fits)


def view_camera(
    entry: Entry, view: int, rotation: np.ndarray, translation: np.ndarray
) -> np.ndarray:
    """(3,) where the camera of the part's rendered ``view`` sits (``views.cameras``), in the
    scene of the pose ``rotation``, ``translation``."""
    camera = camera_at(entry.frame.centroid, entry.views.directions[view], entry.reference.scale)
    return rotation @ camera + translation


def sure_first(scores: np.ndarray, ranked: np.ndarray) -> int | None:
    """Eq. (4)'s first choice among the ``ranked`` rows (best first) when it is sure of it (its
    score ``FIRST_LEAD`` times the next one's), else None. Full clouds mostly: eq. (4) learned
    the parts' full views, and on one camera's view its scores lie close together."""
    if not len(ranked):
        return None
    runner_up = float(scores[ranked[1]]) if len(ranked) > 1 else 0.0
    return int(ranked[0]) if scores[ranked[0]] >= FIRST_LEAD * runner_up else None


class Search:
    """Steps 5-7 for one reading: hypothesise, verify, refine, pass by pass."""

    def __init__(self, settings: EngineSettings, query: Query, observed: Observed):
        self.settings = settings
        self.snapshot = query.snapshot
        self.labels = query.snapshot.classifier.labels
        self.refining = query.refine
        self.observed = points = observed.points
        self.observed_mapped = observed.mapped
        self.viewpoint = query.viewpoint
        self.rng = rng = query.rng
        self.clock = query.clock
        self.query = query
        self.frame = Frame.of(points)  # what every principal-axes and view hypothesis uses
        self.quick = points[subsample(points, QUICK_POINTS, rng)]
        self.cheap = points[subsample(points, settings.verify_points, rng)]
        self.refine_on = points[subsample(points, settings.icp_points, rng)]
        # "is an observed point near here", at the tolerance or the observation's own spacing
        self.occupancy = Occupancy.around(
            points, query.tolerance(settings.tolerance, radius(points)), observed.spacing
        )

    def entry(self, row: int) -> Entry:
        return self.snapshot.entries[self.labels[row]]

    def tolerance(self, entry: Entry) -> float:
        """The fit and coverage distance for this part (``Query.tolerance``)."""
        return self.query.tolerance(self.settings.tolerance, entry.reference.scale)

    # --- one pass -------------------------------------------------------------------------

    def hypothesise(self, plan: Plan) -> list[tuple[int, Hypotheses]]:
        """Step 5: every planned row's pose hypotheses from its sources."""
        made = [
            (row, self.hypotheses_of(self.entry(row), chosen))
            for row, chosen in plan.sources.items()
        ]
        self.clock.lap("hypothesise")
        return made

    def verify(self, made: list[tuple[int, Hypotheses]], plan: Plan) -> list[Fit]:
        """Step 6: each row's hypotheses screened by a quick look on a few points (the
        ``screened`` best kept), then fit x coverage on the cheap sample; best first."""
        keep = plan.screened or self.settings.screened
        fits: list[Fit] = []
        for row, hypotheses in made:
            entry = self.entry(row)
            if len(hypotheses) > keep:
                hypotheses = hypotheses.take(self.screen(entry, hypotheses)[:keep])
            if len(hypotheses):
                fits += self.check(row, entry, hypotheses)
        self.clock.lap("verify")
        fits.sort(key=lambda f: -f.score)
        return fits

    def refine(self, fits: list[Fit], plan: Plan) -> list[Fit]:
        """Step 7: the pass's best fits refined (``refine_best_first``). Returns each row's
        best fit, and every refined one. A row's best is its best refined fit where it has
        one: an unrefined score is the cheap sample's, and one lucky there would win
        unrefined, past the near-symmetries and the polish."""
        if not fits:
            return []
        if self.refining:
            self.refine_best_first(fits, plan)
            self.clock.lap("refine")
        best: dict[int, Fit] = {}
        for candidate in sorted(fits, key=lambda f: (not f.refined, -f.score)):
            best.setdefault(candidate.row, candidate)
        return list(best.values()) + [f for f in fits if f.refined and best[f.row] is not f]

    def screen(self, entry: Entry, made: Hypotheses) -> np.ndarray:
        """Hypotheses ordered by a quick fit x coverage on a few points, best first."""
        tolerance = self.tolerance(entry)
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

    def refine_best_first(self, fits: list[Fit], plan: Plan) -> None:
        """Refine the best of ``fits`` (sorted, best first) within the plan's budget; eq. (4)'s
        sure first choice in any case; and with ``rescue``, more parts where none fits well."""
        planned = self.within_budget(fits, plan.budget)
        # its best pose too: of two parts of nearly one shape, the right one's refined pose
        # fits better (docs/decisions.md#refine)
        firsts = [f for f in fits if f.row == plan.first][:FIRST_REFINED]
        sure = firsts if all(f.row != plan.first for f in planned) else []
        refined = self.refine_budget(planned, sure)
        per_row = Counter(candidate.row for candidate in refined)
        if firsts and plan.first not in per_row:  # planned, but the turn did not reach it
            self.refine_all(firsts)
            per_row[plan.first] += len(firsts)
            refined += firsts
        if plan.rescue and self.rescued_parts:
            self.rescue(fits, per_row, refined)

    def within_budget(self, fits: list[Fit], budget: int) -> list[Fit]:
        """The best ``budget`` of ``fits`` (``PER_PART`` a part at most), leaving out those far
        below the best: what ``refine_budget`` refines in turn."""
        planned: list[Fit] = []
        floor = FAR_BELOW * fits[0].score
        for candidate in fits:
            if len(planned) == budget or candidate.score < floor:
                break
            if sum(f.row == candidate.row for f in planned) < PER_PART:
                planned.append(candidate)
        return planned

    def refine_budget(self, planned: list[Fit], sure: list[Fit]) -> list[Fit]:
        """``planned`` refined in turn, stopping once one is excellent and the next looks
        clearly worse; ``sure`` refined alongside the first. The refined fits. The first
        alone where it verified well (``ALONE_FROM``): an answer's then mostly refines to
        excellent, and ends the turn; else all together."""
        excellent = self.settings.excellent

        def stops(candidate: Fit, best: float) -> bool:
            return best >= excellent and candidate.score < ENOUGH_BEHIND * best

        head = 1 if planned and planned[0].score >= ALONE_FROM else len(planned)
        refined = self.refine_in_turn(planned[:head], stops, along=sure)
        turn = refined[len(sure) :]
        if len(turn) == head:
            best = max((f.score for f in turn), default=0.0)
            turn += self.refine_in_turn(planned[head:], stops, best)
        return turn + sure

    @property
    def rescued_parts(self) -> int:
        """How many more parts ``rescue`` tries (0: none): the query's ``rescued`` where it
        asks (a frame's segment), else ``settings.rescued_parts``."""
        return self.settings.rescued_parts if self.query.rescued is None else self.query.rescued

    def rescue(self, fits: list[Fit], per_row: Counter[int], refined: list[Fit]) -> None:
        """Where no refined fit fits well (``RESCUE_BELOW``), the best ``RESCUE_EACH``
        hypotheses of each next part (up to ``rescued_parts`` parts) refined on half the ICP
        budget, until one does; the best of them then on the rest, if it beats every fully
        refined one. A part's right pose may verify worse than another part's before
        refinement (docs/decisions.md#refine)."""
        settings = self.settings
        best = max((f.score for f in refined), default=0.0)
        if best >= RESCUE_BELOW:
            return
        rescued: dict[int, int] = {}
        planned: list[Fit] = []
        for candidate in fits:
            if candidate.row in per_row or rescued.get(candidate.row, 0) == RESCUE_EACH:
                continue
            if candidate.row not in rescued and len(rescued) == self.rescued_parts:
                continue
            rescued[candidate.row] = rescued.get(candidate.row, 0) + 1
            planned.append(candidate)
        tried = self.refine_in_turn(
            planned,
            lambda _, best: best >= RESCUE_BELOW,
            best,
            iterations=max(1, settings.icp_iterations // 2),
        )
        winner = max(tried, key=lambda f: f.score, default=None)
        if winner is not None and winner.score > max((f.score for f in refined), default=0.0):
            self.refine_all([winner])

    def refine_in_turn(
        self,
        planned: list[Fit],
        stops: Callable[[Fit, float], bool],
        best: float = 0.0,
        iterations: int | None = None,
        along: list[Fit] | None = None,
    ) -> list[Fit]:
        """``planned`` refined in turn until ``stops(next, best refined score so far)``, and
        ``along`` in any case; those refined (``along`` first). All are refined together
        (``refine_all``), ``planned`` on copies, and those the turn never reaches left as they
        were: a refinement does not depend on the others', so each is what refining them one
        by one would give, in less time (docs/decisions.md#refinements-together)."""
        along = along or []
        if planned and stops(planned[0], best):
            planned = []
        trials = [dataclasses.replace(candidate) for candidate in planned]
        self.refine_all(along + trials, iterations)
        done = list(along)
        for candidate, trial in zip(planned, trials, strict=True):
            if stops(candidate, best):
                break
            vars(candidate).update(vars(trial))
            done.append(candidate)
            best = max(best, candidate.score)
        return done

    def hypotheses_of(self, entry: Entry, chosen: list[str]) -> Hypotheses:
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

    def check(self, row: int, entry: Entry, made: Hypotheses, count: int | None = None):
        """Fit x coverage of each hypothesis: on the cheap sample to the nearest surface
        sample, or (``count``, a refined pose, whose fit the confidence weighs) on the
        refinement's sample to the facing sample (docs/decisions.md#verify)."""
        settings = self.settings
        tolerance = self.tolerance(entry)
        observed = self.cheap if count is None else self.refine_on
        fits_ = fit(
            entry.surface,
            observed,
            made.rotations,
            made.translations,
            tolerance,
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

    def refine_all(self, candidates: list[Fit], iterations: int | None = None) -> None:
        """Each fit's pose refined by point-to-plane ICP (``iterations``: the setting's unless
        given), all together, then verified again on more points, each part's together."""
        if not candidates:
            return
        refined = self.icp_all(candidates, iterations or self.settings.icp_iterations)
        for candidate, (rotation, translation) in zip(candidates, refined, strict=True):
            candidate.rotation, candidate.translation = rotation, translation
        for row in dict.fromkeys(c.row for c in candidates):
            mine = [c for c in candidates if c.row == row]
            made = Hypotheses(
                np.stack([c.rotation for c in mine]),
                np.stack([c.translation for c in mine]),
                tuple(c.source for c in mine),
                np.array([c.view for c in mine]),
            )
            for candidate, checked in zip(
                mine, self.check(row, self.entry(row), made, count=EXPECTED), strict=True
            ):
                candidate.fit, candidate.coverage = checked.fit, checked.coverage
                candidate.refined = True

    # --- the best pose, finished ----------------------------------------------------------

    def finish(self, fits: list[Fit]) -> list[Fit]:
        """Step 7 for the best pose (``fits`` best first): turned by its part's flips and
        near-symmetries, each refined, the best first; then its refinement finished."""
        fits = self.flip(fits)
        self.clock.lap("flips")
        fits = self.resolve_near(fits)
        self.clock.lap("near-symmetries")
        if self.polish(fits[0]):
            self.clock.lap("refine")
        return fits

    def icp_all(
        self, candidates: list[Fit], iterations: int, points: np.ndarray | None = None
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each fit's pose refined by point-to-plane ICP on ``points`` (the refinement's
        sample unless given), all together (``icp_many``); each ``candidate.settled`` says
        whether it stopped before ``iterations``."""
        starts = []
        for candidate in candidates:
            entry = self.entry(candidate.row)
            starts.append(
                Start.at_tolerance(
                    entry.surface,
                    candidate.rotation,
                    candidate.translation,
                    self.tolerance(entry),
                    iterations,
                    self.camera_of(entry, candidate),
                )
            )
        refined = icp_many(self.refine_on if points is None else points, starts)
        for candidate, (_, _, done) in zip(candidates, refined, strict=True):
            candidate.settled = done < iterations
        return [(rotation, translation) for rotation, translation, _ in refined]

    def camera_of(self, entry: Entry, candidate: Fit) -> np.ndarray | None:
        """Where the camera was, in the scene: the viewpoint, if told; else, for a pose
        hypothesised from one of the part's rendered views, that view's camera placed by the
        pose (``view_camera``; docs/decisions.md#refine)."""
        if self.viewpoint is not None or candidate.view < 0:
            return self.viewpoint
        return view_camera(entry, candidate.view, candidate.rotation, candidate.translation)

    def polish(self, winner: Fit) -> bool:
        """Finish the winner's pose where the search's budget cut its refinement short: up to
        ``polish_iterations`` more, on the network's sample of the observation. Only the pose
        changes: its fit and coverage stay the search's, which the confidence was calibrated
        on (docs/decisions.md#refine). Whether it ran."""
        extra = self.settings.polish_iterations
        if not extra or not winner.refined or winner.settled:
            return False
        ((winner.rotation, winner.translation),) = self.icp_all([winner], extra, self.observed)
        return True

    def flip(self, fits: list[Fit]) -> list[Fit]:
        """``fits`` (best first) with the best pose turned half a turn about each of its part's
        principal axes (through the part's centroid, in the model frame), each refined, first
        where one fits better; unless the best fits excellently, or is unrefined. A frame is
        matched up to its axes' signs, and the wrong sign refines into a minimum of its own
        (docs/decisions.md#refine)."""
        best = fits[0]
        if not best.refined or best.score >= self.settings.excellent:
            return fits
        entry = self.entry(best.row)
        turns = entry.frame.half_turns
        centre = entry.frame.centroid  # scene = R (T (m - c) + c) + t
        rotations, translations = turned_about(best.rotation, best.translation, turns, centre)
        views = entry.views.turned(best.view, turns)
        flipped = []
        for k in range(len(turns)):
            if entry.symmetry.distance_deg(rotations[k], best.rotation) <= DIFFERENT_DEG:
                continue  # the same pose: a symmetry of the part
            flipped.append(
                Fit(best.row, rotations[k], translations[k], FLIP_SOURCE, views[k], 0, 0)
            )
        self.refine_all(flipped)
        top = max(flipped, key=lambda f: f.score, default=None)
        return fits if top is None or top.score <= best.score else [top, *fits]

    def resolve_near(self, fits: list[Fit], repeat: bool = True) -> list[Fit]:
        """``fits`` (best first) with the best pose tried turned by each near-symmetry of its
        part (about the part's centre, in the model frame), each refined: a notch or a cross
        hole may be all that tells those poses apart. Of the poses that fit alike, the one
        whose points lie closest to the surface goes first; those as close as it (within
        ``RESIDUAL_ALIKE``) stay as alternatives. Where a pose turned end for end goes first,
        or any turned pose of a best pose that fit less than excellently, its own turns are
        tried once more (``repeat``)."""
        best = fits[0]
        entry = self.entry(best.row)
        symmetry = entry.symmetry
        if not best.refined or not len(symmetry.near) or not self.settings.near_refined:
            return fits
        centre = symmetry.centroid  # scene = R (N (m - c) + c) + t
        turns = symmetry.near_tried
        rotations, translations = turned_about(best.rotation, best.translation, turns, centre)
        # coverage against the view each turned pose expects, not the unturned pose's
        views = entry.views.turned(best.view, turns)
        order = self.near_order(entry, best, rotations, translations, turns)
        turned = [
            Fit(best.row, rotations[k], translations[k], NEAR_SOURCE, views[k], 0, 0) for k in order
        ]
        self.refine_all(turned)
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
        reversing = symmetry.near_reversing
        flipped = any(
            alike[chosen] is t for t, k in zip(turned, order, strict=True) if reversing[k]
        )
        # the turns were chosen on the pose they turn: one that fit poorly may have left out
        # the right one (docs/decisions.md#beyond-the-evaluations-draw)
        poor = alike[chosen] is not best and best.score < self.settings.excellent
        if repeat and (flipped or poor):
            return self.resolve_near(answer, repeat=False)
        return answer

    def near_order(
        self,
        entry: Entry,
        best: Fit,
        rotations: np.ndarray,
        translations: np.ndarray,
        turns: np.ndarray,
    ) -> np.ndarray:
        """Which of the turned poses to refine, in order: those not clearly farther from the
        surface than the best (``SCREEN_ALIKE``), screened each kind on its own (turns about
        a nearly round axis, and flips end for end: the many turns would crowd out a flip),
        then nearest on the network's sample, the nearest of each kind first."""
        screened = self.residuals(entry, rotations, translations, lookup="field")
        (own,) = self.residuals(entry, best.rotation[None], best.translation[None], lookup="field")
        order = np.argsort(screened)
        order = order[screened[order] <= SCREEN_ALIKE * own]
        reversing = entry.symmetry.near_reversing
        kinds = [order[~reversing[order]], order[reversing[order]]]
        kinds = [self.screen_near(entry, kind, rotations, translations, turns) for kind in kinds]
        order = np.concatenate(kinds)
        again = self.residuals(entry, rotations[order], translations[order], self.observed)
        order = order[np.argsort(again, kind="stable")]
        firsts = np.concatenate([order[reversing[order] == flip][:1] for flip in (False, True)])
        order = np.concatenate([firsts, order[~np.isin(order, firsts)]])
        return order[: self.settings.near_refined]

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
        return np.minimum(distance, 3 * self.tolerance(entry)).mean(axis=1) / scale

    def candidate_fits(self, fits: list[Fit], scores: np.ndarray) -> list[CandidateFit]:
        """One line a candidate, best first: its best pose's mean distance from the observed
        points to the reference's surface samples (on the cheap subsample)."""
        out: dict[int, CandidateFit] = {}
        for candidate in sorted(fits, key=lambda f: -f.score):
            if candidate.row in out:
                continue
            entry = self.entry(candidate.row)
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
