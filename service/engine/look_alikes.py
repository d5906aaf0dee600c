"""Look-alike parts: registered references that an observation cannot tell apart.

Two references look alike when their points are the same (one ``points_sha256``: the same
part registered under two names), or when the registration check of one could not tell it
from the other: any of its renders answered as the other part, or with the other fitting
alike; or, the other way, any view of a held part (one of the ``suspects``) answered as the
new one, or fitted alike by it (``Engine.taken_for``). That claim is stored with the
reference that made it (``Reference.look_alikes``), naming the other part's
``points_sha256`` then, so it lapses once that part is replaced by other points; the relation
is symmetric, so both descriptions list it.

``/align`` (``Engine.decide``) compares the winner with its look-alikes: one that fits within
``tuning.LOOK_ALIKE`` of the winner's fit x coverage makes the label a guess among them, so the
answer is ``ambiguous``, the look-alikes' poses are its alternatives (with their labels), its
confidence is shared among them and the verdict is no "match" (``doubt``).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from service.engine.answer import Alignment
from service.engine.reference import Reference
from service.engine.tuning import ALIKE

if TYPE_CHECKING:
    from service.engine.entry import Snapshot

SUSPECTS = 3  # held parts whose views the registration check renders (``Engine.taken_for``)
SIZES = (0.5, 2.0)  # ... among those this many times the new part's scale


def relation(references: Iterable[Reference]) -> dict[str, tuple[str, ...]]:
    """Each reference's look-alikes among ``references`` (only those that have any)."""
    references = list(references)
    sha = {r.name: r.points_sha256 for r in references}
    pairs: set[tuple[str, str]] = set()
    same: dict[str, list[str]] = defaultdict(list)
    for reference in references:
        same[sha[reference.name]].append(reference.name)
    for names in same.values():
        pairs.update((a, b) for a in names for b in names if a != b)
    for reference in references:
        for other, then in (reference.look_alikes or {}).items():
            if sha.get(other) != then:  # replaced by other points (or gone): it lapsed
                continue
            for alike in same[then]:  # and every part of those points
                if alike != reference.name:
                    pairs.update({(reference.name, alike), (alike, reference.name)})
    alike: dict[str, list[str]] = defaultdict(list)
    for a, b in sorted(pairs):
        alike[a].append(b)
    return {name: tuple(others) for name, others in alike.items()}


def confused(name: str, checks: list[dict] | None) -> list[str]:
    """The parts a registration check could not tell ``name`` from: any of its renders
    answered as one, or one fitting alike (``tuning.ALIKE``). One view in four is enough: a
    robot meets that view as often as the check drew it, and where the two do not fit alike
    the answer stays a match (docs/decisions.md#look-alike-parts)."""
    if not checks:
        return []
    return sorted({other for check in checks if (other := told_from(name, check)) is not None})


def told_from(name: str, check: dict) -> str | None:
    """The part one render of ``name`` could not be told from, if any."""
    if check["label"] != name:
        return check["label"]
    alike = (check.get("runner_up_fit") or 0.0) >= ALIKE
    return check.get("runner_up") if alike else None


def suspects(snapshot: Snapshot, name: str, count: int = SUSPECTS) -> list[str]:
    """The ``count`` held parts of a size like ``name``'s whose rendered views look most like
    its own: the mean, over a part's views, of the cosine to the nearest of ``name``'s (the
    features the nearest-view proposals compare). Those the gallery may now answer as
    ``name`` (docs/decisions.md#either-way)."""
    labels = list(snapshot.entries)
    row = labels.index(name)
    owner = snapshot.view_owner
    mine = snapshot.view_keys[owner == row]
    if not len(mine):
        return []
    nearest = (snapshot.view_keys @ mine.T).max(axis=1)
    starts = snapshot.view_starts
    counts = np.diff(np.append(starts, len(owner)))
    likeness = np.add.reduceat(nearest, starts) / counts
    ratio = snapshot.scales[owner[starts]] / snapshot.scales[row]
    plausible = (ratio >= SIZES[0]) & (ratio <= SIZES[1]) & (owner[starts] != row)
    order = [i for i in np.argsort(-likeness) if plausible[i]]
    return [labels[owner[starts[i]]] for i in order[:count]]


def same_points(reference: Reference, others: Iterable[Reference]) -> list[str]:
    """The other references that hold exactly ``reference``'s points."""
    return sorted(
        o.name
        for o in others
        if o.name != reference.name and o.points_sha256 == reference.points_sha256
    )


def doubt(answer: Alignment, share: bool = True) -> None:
    """An answer whose part's look-alikes fit alike (``answer.look_alikes``): ambiguous, never
    a "match", a reason naming them, and (with ``share``) its confidence shared among them."""
    if not answer.look_alikes:
        return
    answer.ambiguous = True
    if share and answer.confidence is not None:
        answer.confidence /= 1 + len(answer.look_alikes)
        for alternative in answer.alternatives:
            alternative.confidence = answer.confidence
    if answer.verdict == "match":
        answer.verdict = "uncertain"
    reason = _doubt_reason(answer)
    said_again = tuple(f"{other} fits almost as well" for other in answer.look_alikes)
    kept = [r for r in answer.reasons if not r.startswith(said_again) and r != reason]
    answer.reasons = [*kept, reason]


def undoubted(answer: Alignment) -> Alignment:
    """A copy of ``answer`` as it was before ``doubt`` (shared): its confidence undivided among
    its look-alikes, no reason naming them, and of its alternatives only its own part's poses.
    Where something other than the answer tells the parts apart (a frame:
    ``scene.Scan.told_apart``)."""
    alone = [a for a in answer.alternatives if a.label is None]
    confidence = answer.confidence
    if confidence is not None:
        confidence = min(1.0, confidence * (1 + len(answer.look_alikes)))
    reason = _doubt_reason(answer)
    return replace(
        answer,
        confidence=confidence,
        reasons=[r for r in answer.reasons if r != reason],
        alternatives=alone,
        ambiguous=bool(alone),
        look_alikes=[],
    )


def _doubt_reason(answer: Alignment) -> str:
    """The reason ``doubt`` gives ``answer``, naming its look-alikes."""
    others = ", ".join(answer.look_alikes)
    return (
        f"{answer.label} and its look-alike{'s' * (len(answer.look_alikes) > 1)} {others} fit "
        "alike (see alternatives, with their labels): no view tells them apart; send "
        "candidates naming the part the cell expects, or delete a duplicate registration"
    )
