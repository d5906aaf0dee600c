"""Step 8, decide: how far to trust an answer: a calibrated confidence, a verdict and its reasons.

A robot acts on every answer, so the engine says, besides the label and the pose, the
probability that both are right (the right part, ADD-S < 0.1 of its diameter). It is a
logistic regression over a few measures of the answer, each in units of the part's own scale:

- ``fit``: the share of observed points on the part's surface at the answered pose;
- ``coverage``: the share of what the camera should see of the part that was observed;
- ``margin``: how much better the part fits than the best other part (fit x coverage);
- ``alike``: how close the best other pose of the same part comes (0 when none does; a pose
  that places the part within ``search.RIGHT_EITHER_WAY`` of the answer's, by which the
  answer would still be precise, does not count);
- ``points``: log10 of the number of observed points;
- ``size``: log of the observed radius over the part's scale;
- ``misfit`` and ``missed``: log10 of the share of points off the surface and of the view
  missed (each plus 0.01), so that 99 % against 95 % weighs as much as 80 % against 0 %;
- ``told``: 1 when the request gave the viewpoint.

Its weights are fitted on parts nobody trained or tuned on, in groups (pybullet_data's other
meshes under several sensor profiles, on tables and in bins), beside the model's own parts, and
checked on each group held out in turn and on the evaluation's unseen parts (``python -m
evaluation.calibrate``; docs/decisions.md#calibration-that-transfers); shipped beside the model
as ``confidence.json``. The verdict follows: ``match`` at or above the acceptance threshold
(the request's ``min_confidence``, else the setting ``engine.accept``, else the calibration's
own: the lowest at which 99.5 % of the accepted answers it was fitted on were right),
``no_match`` below ``reject_below``, ``uncertain`` between; every verdict but ``match`` says
why. A detection's calibration (``SCENE_FEATURES``) may carry a second one, ``told``, fitted on
frames whose requests named the parts they hold (``candidates``); and each may carry one for the
instances that may be a match at all (``eligible``, where every measure of ``eligible_at`` is at
least its value), fitted on those alone: most instances are plainly wrong, and a fit on them all
sets its weights where nothing is decided (docs/decisions.md#detect). One told nothing may carry
a third, ``settled``, that judges each instance again once the frame's search is done, on what
no instance explains around it as well (``SETTLED_FEATURES``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

FEATURES = ("fit", "coverage", "margin", "alike", "points", "size", "misfit", "missed", "told")
# a detection in a whole frame (``Engine.detect``): the chain's confidence for its points, and
# what the frame says of its pose (``scene.evidence``)
SCENE_FEATURES = ("chain", "fit", "coverage", "margin", "seen", "through", "explained", "points")
# ... and of one that may be a match (``Calibration.eligible``): the share of its segment it
# leaves, on a log scale, so that half a segment shared with a touching part is no outlier
# among shares near 1 (docs/decisions.md#detect)
ELIGIBLE_FEATURES = (
    "chain", "fit", "coverage", "margin", "seen", "through", "unexplained", "points"
)  # fmt: skip
# ... and once the frame is settled (``Calibration.settled``): what no instance explains around
# it (docs/decisions.md#what-is-left-around)
SETTLED_FEATURES = ("around",)


@dataclass(frozen=True)
class Calibration:
    features: tuple[str, ...]
    weights: np.ndarray  # (F,)
    bias: float
    mean: np.ndarray  # (F,) the features are standardised with these before the weights
    spread: np.ndarray  # (F,)
    about: dict  # what it was fitted on and how well it did, for the record
    accept: float = 0.9  # the default acceptance threshold the fit chose (see evaluation)
    # a detection's, where the request names its candidates: the margin to the other parts
    # then counts only those named (docs/decisions.md#detect)
    told: Calibration | None = None
    # a detection's, for the instances that may be a match: those whose measures are at least
    # ``eligible_at``'s values (the chain's own word and the points a match needs)
    eligible: Calibration | None = None
    eligible_at: dict[str, float] = field(default_factory=dict)
    # a detection's once every instance of the frame is found: the same fit, with
    # ``SETTLED_FEATURES`` added (docs/decisions.md#what-is-left-around)
    settled: Calibration | None = None

    @classmethod
    def load(cls, path: Path) -> Calibration:
        return cls.of(json.loads(Path(path).read_text()), str(path))

    @classmethod
    def of(cls, document: dict, source: str = "the calibration") -> Calibration:
        known = {*FEATURES, *SCENE_FEATURES, *ELIGIBLE_FEATURES, *SETTLED_FEATURES}
        unknown = set(document["features"]) - known
        if unknown:
            raise ValueError(f"{source}: features this engine does not measure: {sorted(unknown)}")
        told, eligible, settled = (document.get(k) for k in ("told", "eligible", "settled"))
        return cls(
            tuple(document["features"]),
            np.asarray(document["weights"], dtype=np.float64),
            float(document["bias"]),
            np.asarray(document["mean"], dtype=np.float64),
            np.asarray(document["spread"], dtype=np.float64),
            document.get("about", {}),
            float(document.get("accept", 0.9)),
            None if told is None else cls.of(told, f"{source} (told)"),
            None if eligible is None else cls.of(eligible, f"{source} (eligible)"),
            {k: float(v) for k, v in document.get("eligible_at", {}).items()},
            None if settled is None else cls.of(settled, f"{source} (settled)"),
        )

    def document(self) -> dict:
        document = {
            "features": list(self.features),
            "weights": self.weights.tolist(),
            "bias": self.bias,
            "mean": self.mean.tolist(),
            "spread": self.spread.tolist(),
            "accept": self.accept,
            "about": self.about,
        }
        if self.told is not None:
            document["told"] = self.told.document()
        if self.eligible is not None:
            document["eligible"] = self.eligible.document()
            document["eligible_at"] = self.eligible_at
        if self.settled is not None:
            document["settled"] = self.settled.document()
        return document

    def save(self, path: Path) -> None:
        Path(path).write_text(json.dumps(self.document(), indent=2) + "\n")

    def confidence(self, measures: dict[str, float]) -> float:
        return from_log_odds(self.logit(measures))

    def logit(self, measures: dict[str, float]) -> float:
        """The log-odds of ``confidence``."""
        if self.eligible is not None and self.is_eligible(measures):
            return self.eligible.logit(measures)
        values = np.array([measures[name] for name in self.features])
        return float(((values - self.mean) / self.spread) @ self.weights + self.bias)

    def is_eligible(self, measures: dict[str, float]) -> bool:
        """Whether ``eligible`` judges these measures: each at least its ``eligible_at``."""
        return meets(measures, self.eligible_at)


def log_odds(probability: float, least: float = 0.0) -> float:
    """The log-odds of ``probability``, held ``least`` away from 0 and 1."""
    held = min(max(probability, least), 1 - least)
    return float(np.log(held / (1 - held)))


def from_log_odds(z: float) -> float:
    """The probability of log-odds ``z`` (``log_odds``' inverse)."""
    return float(1.0 / (1.0 + np.exp(-np.clip(z, -50, 50))))


def meets(measures: dict[str, float], floors: dict[str, float]) -> bool:
    """Whether each of ``floors``' measures is at least its value."""
    return all(measures[name] >= least for name, least in floors.items())


def measures(
    fit: float,
    coverage: float,
    runner_up: float,
    alike: float,
    points: int,
    size_ratio: float,
    told: bool = False,
) -> dict[str, float]:
    """The features of one answer (see the module's docstring); ``told``: the request gave
    the viewpoint."""
    score = fit * coverage
    return {
        "fit": fit,
        "coverage": coverage,
        "margin": score - runner_up,
        "alike": alike / score if score > 0 else 0.0,
        "points": float(np.log10(max(points, 1))),
        "size": float(np.log(max(size_ratio, 1e-9))),
        "misfit": float(np.log10(1.0 - fit + 0.01)),
        "missed": float(np.log10(1.0 - coverage + 0.01)),
        "told": 1.0 if told else 0.0,
    }


def reasons(
    label: str, values: dict[str, float], runner_up_label: str | None, ambiguous: bool
) -> list[str]:
    """Short sentences on what makes an answer doubtful, and what the caller can change."""
    said = []
    if values["fit"] < 0.8:
        said.append(
            f"only {values['fit']:.0%} of the observed points lie on {label}'s surface at the "
            "answered pose: the cloud may show another part, or more than the part"
        )
    if values["coverage"] < 0.7:
        said.append(
            f"only {values['coverage']:.0%} of what the camera should see of {label} was "
            "observed: the part may be occluded, or it is not this part"
        )
    if runner_up_label is not None and values["margin"] < 0.1:
        said.append(
            f"{runner_up_label} fits almost as well: restrict the search with candidates if "
            "the cell knows which part to expect"
        )
    if ambiguous:
        said.append(
            "other poses, not related by the part's symmetry, fit alike (see alternatives): "
            "another viewpoint would tell them apart"
        )
    return said
