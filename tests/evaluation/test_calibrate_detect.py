"""The detection calibration's threshold (``evaluation.calibrate_detect``): chosen on what the
service would accept, not on the confidence alone."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from evaluation.calibrate_detect import acceptance, fit_scene, fitted, served, served_figures
from service.engine.confidence import SCENE_FEATURES as FEATURES
from service.engine.confidence import Calibration


def by_chain() -> Calibration:
    """A calibration whose confidence is the chain's own (its logit, weight 1)."""
    weights = np.array([1.0 if name == "chain" else 0.0 for name in FEATURES])
    ones = np.ones(len(FEATURES))
    return Calibration(FEATURES, weights, 0.0, 0 * ones, ones, {})


def row(chain: float, points: int, right: bool, family: str = "scene") -> dict:
    logit = float(np.log(chain / (1 - chain)))
    return {"chain": logit, "fit": 1.0, "coverage": 1.0, "margin": 0.5, "seen": 1.0,
            "through": 0.0, "explained": 1.0, "unexplained": -2.0,
            "points": float(np.log10(points)), "around": -2.0,
            "right": right, "family": family}  # fmt: skip


def test_what_is_served_needs_the_points_and_the_chains_word():
    calibration = by_chain()
    rows = [row(0.9, 1000, True), row(0.9, 100, True), row(0.4, 1000, False)]
    assert served(calibration, rows, 0.5).tolist() == [True, False, False]
    # a confidence above the threshold is not enough where the chain itself refuses
    trusting = Calibration(
        FEATURES, np.zeros(len(FEATURES)), 50.0, np.zeros(len(FEATURES)), np.ones(len(FEATURES)), {}
    )
    assert served(trusting, rows, 0.5).tolist() == [True, False, False]


def test_an_instance_its_look_alikes_fit_alike_is_never_served():
    # Scan.judge doubts it (look_alikes.doubt): ambiguous, never a match, however sure
    calibration = by_chain()
    rows = [row(0.99, 1000, True), {**row(0.99, 1000, False), "doubted": True}]
    assert served(calibration, rows, 0.5).tolist() == [True, False]
    assert acceptance(calibration, rows) == 0.5


def test_the_threshold_is_the_lowest_where_what_is_served_is_right():
    calibration = by_chain()
    # a wrong instance the chain is 0.745 sure of, one on too few points at 0.95 (never served)
    rows = [row(c, 1000, True) for c in (0.8, 0.9, 0.95)] + [
        row(0.745, 1000, False),
        row(0.95, 100, False),
    ]
    assert acceptance(calibration, rows) == 0.75
    figures = served_figures(calibration, rows, 0.75)
    assert figures == {"scene": {"right": 3, "right_accepted": 1.0, "wrong_accepted": 0}}


def test_the_instances_that_may_match_get_a_fit_of_their_own():
    # many plainly wrong instances the chain refuses, and among those it does not, the right
    # ones fit better than the wrong ones: the fit on those alone tells them apart
    rng = np.random.default_rng(0)
    refused = [row(c, 1000, False) for c in rng.uniform(0.02, 0.3, 300)]
    right = [{**row(c, 1000, True), "fit": f} for c, f in zip(rng.uniform(0.6, 0.99, 40),
             rng.uniform(0.9, 1.0, 40), strict=True)]  # fmt: skip
    wrong = [{**row(c, 1000, False), "fit": f} for c, f in zip(rng.uniform(0.6, 0.99, 20),
             rng.uniform(0.6, 0.85, 20), strict=True)]  # fmt: skip
    calibration = fit_scene(refused + right + wrong)
    assert calibration.eligible is not None
    assert calibration.eligible_at == {"chain": 0.0, "points": pytest.approx(np.log10(150))}
    assert calibration.eligible.weights[calibration.eligible.features.index("fit")] > 0
    assert all(calibration.is_eligible(r) for r in right + wrong)
    assert not any(calibration.is_eligible(r) for r in refused)
    # the eligible fit decides them: every right one above every wrong one
    assert min(map(calibration.confidence, right)) > max(map(calibration.confidence, wrong))
    # too few wrong ones among those that may match: one fit for all
    assert fit_scene(refused + right + wrong[:5]).eligible is None


def test_the_settled_fit_weighs_what_no_instance_explains_around_one():
    # right and wrong instances the chain is alike sure of; the wrong ones have the rest of a
    # larger part around them: the fit without it cannot tell them apart, the settled one can
    rng = np.random.default_rng(1)
    chains = rng.uniform(0.6, 0.99, 120)
    right = [{**row(c, 1000, True), "around": a} for c, a in zip(chains[:80],
             rng.uniform(-2.0, -1.2, 80), strict=True)]  # fmt: skip
    wrong = [{**row(c, 1000, False), "around": a} for c, a in zip(chains[80:],
             rng.uniform(-0.8, 0.3, 40), strict=True)]  # fmt: skip
    rows = right + wrong
    settled = fitted(rows, rows, ("around",))
    assert settled.features[-1] == "around" and settled.eligible.features[-1] == "around"
    assert settled.eligible.weights[-1] < 0
    assert min(map(settled.confidence, right)) > max(map(settled.confidence, wrong))
    assert settled.about["fit"]["precision_of_accepted"] == 1.0
    plain = fitted(rows, rows)
    assert "around" not in plain.features
    assert plain.accept > settled.accept or plain.about["fit"]["right_accepted"] < 1.0
    again = Calibration.of(replace(plain, settled=settled).document())
    assert again.settled is not None and again.settled.features == settled.features
    assert again.settled.accept == settled.accept
