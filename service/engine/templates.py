"""Where a part lies among others: its rendered views tried all over a segment.

A segment may hold several parts touching (a bin of them, two boxes side by side). The chain's
hypotheses come from the whole observation's frame and its network mapping, so a segment of
two parts gives neither part's pose. Here every rendered view of a part is placed at points
spread over the segment (``seeds``), facing the camera from there, and turned about the line
of sight; each pose is screened by how much of what its view shows lands on observed points
(model to scene: other parts' points do not dilute it), and the best are refined by ICP on
the points around them. The caller then asks the chain about the points the best one
explains: a clean view of one part.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.engine.entry import Entry
from service.engine.icp import Start, icp_many
from service.engine.normalize import subsample
from service.engine.projection import DepthImage
from service.engine.tuning import (
    MAX_SEEDS,
    RANK_ANGLES,
    RANK_EVERY,
    RANK_SEEDS,
    SEED_SAMPLE,
    SEED_SPACING,
    TEMPLATE_ANGLES,
    TEMPLATE_ICP_POINTS,
    TEMPLATE_POINTS,
    TEMPLATE_REFINED,
    TEMPLATE_TOLERANCE,
    THROUGH_WEIGHT,
)
from service.engine.verification import Occupancy
from service.engine.views import camera_basis


@dataclass(frozen=True)
class Placed:
    rotation: np.ndarray
    translation: np.ndarray
    covered: float  # share of the view's expected points with an observed point near them


def seeds(points: np.ndarray, spacing: float, rng: np.random.Generator) -> np.ndarray:
    """Points spread over ``points`` (farthest first, among a sample of them) until every
    point of the sample lies within ``spacing`` of one, at most ``MAX_SEEDS``."""
    sample = points[subsample(points, SEED_SAMPLE, rng)]
    chosen = [int(rng.integers(len(sample)))]
    distance = np.linalg.norm(sample - sample[chosen[0]], axis=1)
    while len(chosen) < MAX_SEEDS and distance.max() > spacing:
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(sample - sample[chosen[-1]], axis=1))
    return sample[chosen]


def in_plane_turns(count: int) -> np.ndarray:
    """(count, 3, 3) turns about the third axis, evenly spaced."""
    angles = np.arange(count) * 2 * np.pi / count
    cos, sin = np.cos(angles), np.sin(angles)
    turns = np.zeros((count, 3, 3))
    turns[:, 0, 0], turns[:, 0, 1], turns[:, 1, 0], turns[:, 1, 1] = cos, -sin, sin, cos
    turns[:, 2, 2] = 1.0
    return turns


def place_views(
    entry: Entry,
    points: np.ndarray,
    viewpoint: np.ndarray,
    spacing: float,
    tolerance: float,
    rng: np.random.Generator,
    camera: DepthImage | None = None,
) -> list[Placed]:
    """The part's best poses among its views placed at seeds over ``points`` (a segment),
    each refined on the points around it and scored again at ``tolerance`` (a share of the
    scale), best first. ``spacing``: the segment's distance between neighbouring points. With
    the frame's ``camera``, a pose where the camera saw through the part scores less by that
    share (``DepthImage.look``)."""
    scale = entry.reference.scale
    found = screened(entry, points, viewpoint, spacing, rng, camera)
    fine = Occupancy.around(points, tolerance * scale, spacing)
    poses = refined(
        entry, points, found[:TEMPLATE_REFINED], viewpoint, fine, camera, tolerance * scale
    )
    return sorted(poses, key=lambda p: -p.covered)


def screened(
    entry: Entry,
    points: np.ndarray,
    viewpoint: np.ndarray,
    spacing: float,
    rng: np.random.Generator,
    camera: DepthImage | None,
    every: int = 1,
    angles: int = TEMPLATE_ANGLES,
    most_seeds: int = MAX_SEEDS,
) -> list[Placed]:
    """Every ``every``-th view of the part placed at up to ``most_seeds`` seeds, turned
    ``angles`` times about the line of sight, scored on a few points at a coarse tolerance:
    the best few of each seed, best first."""
    scale = entry.reference.scale
    # the depth image's word where there is one; else whether an observed point is near
    occupancy = (
        Occupancy.around(points, TEMPLATE_TOLERANCE * scale, spacing) if camera is None else None
    )
    views = entry.views
    chosen = np.arange(0, len(views.radii), every)
    model_bases = views.bases[chosen]  # rows u v d: each view's camera
    turns = in_plane_turns(angles)
    expected = entry.surface.points[entry.expected[chosen, :TEMPLATE_POINTS]]
    found = []
    for seed in seeds(points, SEED_SPACING * scale, rng)[:most_seeds]:
        scene_basis = camera_basis(viewpoint - seed)
        # R = B_scene^T T B_model: the view's camera direction onto the line of sight
        rotations = np.matmul((scene_basis.T @ turns)[None], model_bases[:, None])  # (V, T)
        translations = seed - np.einsum("vtij,vj->vti", rotations, views.centroids[chosen])
        placed = np.matmul(expected[:, None], rotations.transpose(0, 1, 3, 2))  # (V, T, P)
        placed += translations[:, :, None]
        if camera is not None:  # the depth image's word, each pose snapped onto its depth
            covered, shift = camera.agreement(placed, TEMPLATE_TOLERANCE * scale)
            rays = translations + np.einsum("vtij,vj->vti", rotations, views.centroids[chosen])
            rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
            translations = translations + rays * (shift / rays[..., 2])[..., None]
        else:
            covered = occupancy.near(placed).mean(axis=2)  # (V, T)
        best = np.argsort(-covered, axis=None)[:TEMPLATE_REFINED]
        v, t = np.unravel_index(best, covered.shape)
        found += [
            Placed(rotations[a, b], translations[a, b], covered[a, b])
            for a, b in zip(v, t, strict=True)
        ]
    return sorted(found, key=lambda p: -p.covered)


def likeliest(
    entries: list[Entry],
    points: np.ndarray,
    viewpoint: np.ndarray,
    spacing: float,
    rng: np.random.Generator,
    camera: DepthImage | None,
    count: int,
) -> list[Entry]:
    """The ``count`` parts whose views, coarsely placed over ``points`` (``RANK_EVERY``-th
    view, ``RANK_ANGLES`` turns, ``RANK_SEEDS`` seeds), cover most of it: the share of a
    view's surface covered times that surface's area (a small part's face fits anywhere on a
    large one)."""
    if len(entries) <= count:
        return entries
    scores = []
    for entry in entries:
        found = screened(
            entry, points, viewpoint, spacing, rng, camera, RANK_EVERY, RANK_ANGLES, RANK_SEEDS
        )
        if not found:
            scores.append(-np.inf)
            continue
        toward = (viewpoint - found[0].translation) @ found[0].rotation
        view = int(entry.views.nearest(toward[None])[0])
        area = entry.views.visible[view].sum() * entry.surface.spacing**2
        scores.append(found[0].covered * area)
    order = np.argsort(-np.array(scores), kind="stable")[:count]
    return [entries[k] for k in order]


def refined(
    entry: Entry,
    points: np.ndarray,
    poses: list[Placed],
    viewpoint: np.ndarray,
    fine: Occupancy,
    camera: DepthImage | None,
    tolerance: float,
) -> list[Placed]:
    """Placed views each refined by ICP on the points within reach of it (those of as many
    points together, ``icp_many``), and how much of what the camera should see of it then has
    an observed point near it (``fine``), less the share the camera saw through."""
    scale = entry.reference.scale
    out = list(poses)
    groups: dict[int, list[tuple[int, np.ndarray]]] = {}  # by how many points: pose, points
    for k, pose in enumerate(poses):
        centre = pose.rotation @ entry.frame.centroid + pose.translation
        near = points[np.linalg.norm(points - centre, axis=1) <= 1.5 * scale]
        if len(near) >= 16:
            near = near[subsample(near, TEMPLATE_ICP_POINTS, np.random.default_rng(0))]
            groups.setdefault(len(near), []).append((k, near))
    for group in groups.values():
        starts = [
            Start(
                entry.surface,
                poses[k].rotation,
                poses[k].translation,
                noise=0.01 * scale,
                gate=0.2 * scale,
                iterations=20,
                viewpoint=viewpoint,
            )
            for k, _ in group
        ]
        scenes = np.stack([near for _, near in group])
        for (k, _), (rotation, translation, _) in zip(group, icp_many(scenes, starts), strict=True):
            toward = (viewpoint - translation) @ rotation  # the camera's direction, model frame
            view = int(entry.views.nearest(toward[None])[0])
            expected = entry.surface.points[entry.expected[view]] @ rotation.T + translation
            if camera is not None:
                score = camera.agreement(expected, tolerance, THROUGH_WEIGHT)[0]
            else:
                score = fine.near(expected).mean()
            out[k] = Placed(rotation, translation, float(score))
    return out
