"""Step 5, hypothesise: pose hypotheses for one candidate reference, from four sources.

- ``views``: the observation's principal frame matched with the frames of the reference's
  rendered views that look most like it (four proper sign flips each); with a viewpoint, only
  the hypotheses whose camera lies on the viewpoint's side of the part. A single camera's view
  has its own principal frame, not the whole part's, so this is what poses a depth image;
- ``principal-axes``: the observation's and the whole reference's principal frames, four
  proper sign flips (classical, no learning; what a full 360-degree cloud needs), each also
  turned about the third axis every 45 degrees where two spreads are alike;
- ``mapped``: pairs of points that land on the same 2-D coordinate, solved by Kabsch inside
  RANSAC (the learned mapping's contribution);
- ``paper``: the paper's least squares + SVD (eqs. 5-6) over all mapped pairs.

Each hypothesis remembers its source and which of the reference's views it expects the camera
to see (-1: the whole reference), for verification's coverage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from service.engine.correspondences import mapped_pairs
from service.engine.principal_axes import PROPER_SIGN_FLIPS, Frame
from service.engine.registration import paper_least_squares, ransac
from service.engine.tuning import VIEWPOINT_AGREEMENT_DEG
from service.engine.views import Views

SOURCES = ("views", "principal-axes", "mapped", "paper")


@dataclass(frozen=True)
class Hypotheses:
    rotations: np.ndarray  # (H, 3, 3): scene = R @ model + t
    translations: np.ndarray  # (H, 3)
    sources: tuple[str, ...]  # (H,)
    views: np.ndarray  # (H,) int: the view the camera is expected to see, -1 the whole part

    def __len__(self) -> int:
        return len(self.translations)

    def take(self, index: np.ndarray) -> Hypotheses:
        index = np.asarray(index, dtype=np.intp)
        return Hypotheses(
            self.rotations[index],
            self.translations[index],
            tuple(self.sources[i] for i in index),
            self.views[index],
        )

    @classmethod
    def join(cls, parts: list[Hypotheses]) -> Hypotheses:
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls(np.zeros((0, 3, 3)), np.zeros((0, 3)), (), np.zeros(0, np.intp))
        return cls(
            np.concatenate([p.rotations for p in parts]),
            np.concatenate([p.translations for p in parts]),
            tuple(s for p in parts for s in p.sources),
            np.concatenate([p.views for p in parts]),
        )


def _frame_matches(
    observed: Frame, frames: np.ndarray, centroids: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Poses carrying each (frame, centroid) onto the observation's ``observed`` frame, four
    sign flips each: (4K, 3, 3) rotations and (4K, 3) translations, flips varying fastest."""
    rotations = np.einsum("ij,sj,kmj->ksim", observed.axes, PROPER_SIGN_FLIPS, frames)
    rotations = rotations.reshape(-1, 3, 3)
    translations = observed.centroid - np.einsum(
        "hij,hj->hi", rotations, np.repeat(centroids, 4, axis=0)
    )
    return rotations, translations


def from_views(
    observed: Frame, views: Views, chosen: np.ndarray, viewpoint: np.ndarray | None
) -> Hypotheses:
    """View hypotheses for the ``chosen`` view indices (``observed``: the observation's
    frame)."""
    chosen = np.asarray(chosen, dtype=np.intp)
    rotations, translations = _frame_matches(
        observed, views.frames[chosen], views.centroids[chosen]
    )
    expected = np.repeat(chosen, 4)
    if viewpoint is not None:
        toward = viewpoint - observed.centroid
        norm = np.linalg.norm(toward)
        if norm > 0:
            implied = np.einsum("hij,i->hj", rotations, toward / norm)  # R^T v, model frame
            agree = np.einsum("hj,hj->h", implied, views.directions[expected])
            keep = agree > np.cos(np.radians(VIEWPOINT_AGREEMENT_DEG))
            if keep.any():
                rotations, translations, expected = (
                    rotations[keep],
                    translations[keep],
                    expected[keep],
                )
    return Hypotheses(rotations, translations, ("views",) * len(expected), expected)


def from_principal_axes(observed: Frame, reference: Frame) -> Hypotheses:
    """The whole reference's principal frame carried onto the observation's, also turned about
    the third axis where two of its spreads are alike (``Frame.matched``: a square brick's, a
    flange's turn is otherwise left to chance and refinement)."""
    frames = reference.matched
    rotations, translations = _frame_matches(
        observed, frames, np.repeat(reference.centroid[None], len(frames), axis=0)
    )
    count = len(translations)
    return Hypotheses(rotations, translations, ("principal-axes",) * count, np.full(count, -1))


def from_mapped_pairs(
    sources: tuple[str, ...],
    observed: np.ndarray,
    observed_mapped: np.ndarray,
    reference: np.ndarray,
    reference_mapped_tree: cKDTree,
    threshold: float,
    iterations: int,
    rng: np.random.Generator,
) -> Hypotheses:
    """RANSAC (``mapped``) and the paper's solver (``paper``) over the mapped pairs."""
    paired = reference[mapped_pairs(observed_mapped, reference_mapped_tree)]
    poses = []
    if "mapped" in sources:
        rotation, translation, _ = ransac(paired, observed, threshold, iterations, rng)
        poses.append((rotation, translation, "mapped"))
    if "paper" in sources:
        poses.append((*paper_least_squares(paired, observed), "paper"))
    if not poses:
        return Hypotheses.join([])
    return Hypotheses(
        np.stack([p[0] for p in poses]),
        np.stack([p[1] for p in poses]),
        tuple(p[2] for p in poses),
        np.full(len(poses), -1),
    )
