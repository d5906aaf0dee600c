"""Steps 4-6 of ``Engine.align`` for one query: hypothesise poses of each candidate, verify
them (fit x coverage), refine the best (point-to-plane ICP); then the best pose's flips,
near-symmetries and finishing refinement."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.engine import hypotheses as sources
from service.engine.answer import CandidateFit
from service.engine.entry import EXPECTED, Entry
from service.engine.hypotheses import Hypotheses
from service.engine.icp import icp
from service.engine.normalize import radius, subsample
from service.engine.principal_axes import Frame
from service.engine.symmetry import FINE_DEG, apart
from service.engine.verification import Lookup, Occupancy, coverage, fit, surface_distance
from service.engine.views import camera_at
from service.settings import EngineSettings


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


def excellent(fits: list[Fit], settings: EngineSettings) -> bool:
    """Whether the best fit so far ends the search."""
    return any(f.score >= settings.excellent for f in fits)


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
            viewpoint=self.camera_of(entry, candidate),
        )
        candidate.settled = done < iterations
        return rotation, translation

    def camera_of(self, entry: Entry, candidate: Fit) -> np.ndarray | None:
        """Where the camera was, in the scene: the viewpoint, if told; else, for a pose
        hypothesised from one of the part's rendered views, that view's camera placed by the
        pose (``view_camera``), held where the start put
        it. Never told the viewpoint, the symmetric groups' depth views were answered within
        2 degrees in 69 -> 76 of 90 groups with it, depth views of unseen parts recognised
        94.4 -> 97.2 %."""
        if self.viewpoint is not None or candidate.view < 0:
            return self.viewpoint
        return view_camera(entry, candidate.view, candidate.rotation, candidate.translation)

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
