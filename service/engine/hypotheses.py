"""Step 4: pose hypotheses for one candidate reference, from three sources.

- ``mapped``: pairs of points that land on the same 2-D coordinate, solved by
  Kabsch inside RANSAC (the learned mapping's contribution);
- ``principal-axes``: the observation's and the reference's principal frames,
  four proper sign flips (classical, no learning);
- ``paper``: the paper's least squares + SVD (eqs. 5-6) over all mapped pairs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from service.engine.correspondences import mapped_pairs
from service.engine.principal_axes import principal_axes_hypotheses
from service.engine.registration import paper_least_squares, ransac

SOURCES = ("mapped", "principal-axes", "paper")


@dataclass(frozen=True)
class Hypothesis:
    rotation: np.ndarray  # (3, 3): scene = R @ model + t
    translation: np.ndarray  # (3,)
    source: str


def hypothesise(
    sources: tuple[str, ...],
    observed: np.ndarray,
    observed_mapped: np.ndarray,
    reference_points: np.ndarray,
    reference_mapped_tree: cKDTree,
    threshold: float,
    iterations: int,
    rng: np.random.Generator,
) -> list[Hypothesis]:
    """Every hypothesis the chosen ``sources`` give for this observation and reference."""
    hypotheses: list[Hypothesis] = []
    if "mapped" in sources or "paper" in sources:
        paired = reference_points[mapped_pairs(observed_mapped, reference_mapped_tree)]
        if "mapped" in sources:
            rotation, translation, _ = ransac(paired, observed, threshold, iterations, rng)
            hypotheses.append(Hypothesis(rotation, translation, "mapped"))
        if "paper" in sources:
            hypotheses.append(Hypothesis(*paper_least_squares(paired, observed), "paper"))
    if "principal-axes" in sources:
        for rotation, translation in principal_axes_hypotheses(observed, reference_points):
            hypotheses.append(Hypothesis(rotation, translation, "principal-axes"))
    return hypotheses
