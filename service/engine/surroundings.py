"""Step 0: set aside what surrounds the part: the table it rests on, stray points, clutter.

A cell's camera sees the part on its support, with a few stray points (edges, reflections)
and sometimes other things in view. Before recognition:
- ``support plane``: the largest plane found by RANSAC is the table when it holds at least
  ``PLANE_SHARE`` of the points, has the rest on one side, and spreads around it, mostly
  beyond its footprint: what a table under a part looks like, and what a face of the part
  itself does not (a face lies within the part's footprint, with the part behind it). Its
  points, and those under it, are set aside;
- ``clusters``: the points fall into groups of neighbours (within ``LINK_SPACINGS`` times the
  median spacing); the largest group is the part, with any group near it of a fair size (a
  handle seen apart from its body); the rest is stray points and clutter.
The answer says how many points were set aside.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from service.engine.normalize import radius, subsample

MAX_POINTS = 2048  # decisions are made on a sample of this many points
PLANE_SHARE = 0.2  # a support plane holds at least this share of the points ...
PLANE_SHARE_BLIND = 0.5  # ... this share, when the viewpoint is not known
PLANE_REACH = 1.5  # ... reaches this many times the rest's radius from the rest's centroid
ONE_SIDE = 0.95  # ... has this share of the rest on one side of it
BEYOND = 0.5  # ... and has this share of its points beyond the part's footprint
PLANE_ITERATIONS = 96
PLANE_SPACINGS = 1.5  # plane inliers lie within this many spacings of it
LINK_SPACINGS = 3.0  # neighbours closer than this many spacings are one group
NEAR_RADII = 0.5  # a group this many of the largest's radii from it, or nearer, ...
FAIR_SHARE = 0.05  # ... that holds this share of its points belongs to the part
ANOTHER = 1.05  # a reading with strays alone set aside is tried too if it keeps more points


@dataclass(frozen=True)
class Observation:
    points: np.ndarray  # (M, 3) what is taken to be the part
    set_aside: int  # points of the original cloud taken to be support, strays or clutter
    support: np.ndarray | None  # (4,) the table's plane n . x = d, if one was found


def spacing(points: np.ndarray, tree: cKDTree, rng: np.random.Generator) -> float:
    """The median distance from a point to its nearest neighbour (on a sample)."""
    sample = points[rng.choice(len(points), size=min(256, len(points)), replace=False)]
    distance, _ = tree.query(sample, k=2)
    return float(np.median(distance[:, 1]))


def plane_candidate(
    points: np.ndarray, step: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray] | None:
    """The plane (n, d with n . x = d) holding most points, by RANSAC, and its inliers; None
    when it holds less than ``PLANE_SHARE`` of them."""
    count = len(points)
    samples = points[rng.integers(0, count, size=(PLANE_ITERATIONS, 3))]
    normals = np.cross(samples[:, 1] - samples[:, 0], samples[:, 2] - samples[:, 0])
    length = np.linalg.norm(normals, axis=1)
    good = length > 1e-12
    if not good.any():
        return None
    normals = normals[good] / length[good, None]
    offsets = np.einsum("ij,ij->i", normals, samples[good, 0])
    inliers = np.abs(points @ normals.T - offsets) < PLANE_SPACINGS * step  # (N, planes)
    best = int(inliers.sum(axis=0).argmax())
    if inliers[:, best].mean() < PLANE_SHARE:
        return None
    return np.append(normals[best], offsets[best]), inliers[:, best]


def is_support(
    plane: np.ndarray, on_plane: np.ndarray, part: np.ndarray, viewpoint: np.ndarray | None
) -> bool:
    """Whether a plane is a table under ``part`` rather than a face of it: the part lies on
    one side, the camera on the same side (a face of a part is seen from outside, with the
    part behind it), and the plane spreads around it, mostly beyond its footprint (a face lies
    within the part's). Without a viewpoint the plane must hold ``PLANE_SHARE_BLIND`` of all
    points."""
    height = part @ plane[:3] - plane[3]
    side = np.sign(np.median(height))
    if np.mean(np.sign(height) == side) < ONE_SIDE:
        return False
    if viewpoint is None:
        if len(on_plane) < PLANE_SHARE_BLIND * (len(on_plane) + len(part)):
            return False
    elif np.sign(viewpoint @ plane[:3] - plane[3]) != side:
        return False
    centre = part.mean(axis=0)
    offset = on_plane - centre
    across = offset - np.outer(offset @ plane[:3], plane[:3])  # within the plane
    distance = np.linalg.norm(across, axis=1)
    footprint = radius(part)
    return bool(
        np.percentile(distance, 95) >= PLANE_REACH * footprint
        and np.mean(distance > footprint) >= BEYOND
    )


def groups(points: np.ndarray, link: float) -> np.ndarray:
    """A group label per point: connected components of the within-``link`` neighbour graph."""
    pairs = cKDTree(points).query_pairs(link, output_type="ndarray")
    graph = coo_matrix(
        (np.ones(len(pairs), dtype=bool), (pairs[:, 0], pairs[:, 1])),
        shape=(len(points), len(points)),
    )
    _, labels = connected_components(graph, directed=False)
    return labels


def the_part(points: np.ndarray, labels: np.ndarray, strays_only: bool = False) -> np.ndarray:
    """Which points belong to the part, given their ``groups``: the largest group, and every
    group of a fair size that lies near it (a sparse or self-occluded part falls apart into
    nearby pieces); with ``strays_only``, every group of a fair size."""
    sizes = np.bincount(labels)
    largest = int(sizes.argmax())
    keep = labels == largest
    fair = [label for label in np.flatnonzero(sizes >= FAIR_SHARE * sizes[largest])]
    if strays_only:
        return np.isin(labels, fair)
    tree, reach = cKDTree(points[keep]), radius(points[keep])
    for label in fair:
        if label != largest:
            gap, _ = tree.query(points[labels == label], k=1)
            if gap.min() < NEAR_RADII * reach:
                keep |= labels == label
    return keep


def set_aside_surroundings(
    points: np.ndarray, rng: np.random.Generator, viewpoint: np.ndarray | None = None
) -> list[Observation]:
    """What may be the part's points (of all of ``points``): the reading with the support plane,
    strays and clutter set aside first, then, where that set aside more than strays, the
    reading with strays alone set aside. The engine keeps the one the part fits best.

    The decisions are made on a sample of ``MAX_POINTS``; then every point inside the part's
    bounding sphere (and above the table) is the part's."""
    sample = points[subsample(points, MAX_POINTS, rng)]
    distance, _ = cKDTree(sample).query(sample[: min(256, len(sample))], k=2)
    step = float(np.median(distance[:, 1]))
    link = LINK_SPACINGS * step
    support, part = None, np.ones(len(sample), dtype=bool)
    found = plane_candidate(sample, step, rng)
    if found is not None:
        plane, on_plane = found
        rest = sample[~on_plane]
        if len(rest) >= 20:
            main = rest[the_part(rest, groups(rest, link))]
            if is_support(plane, sample[on_plane], main, viewpoint):
                height = np.median(main @ plane[:3] - plane[3])
                support = plane * np.sign(height)  # its normal towards the part
                part = ~on_plane & (sample @ support[:3] - support[3] > PLANE_SPACINGS * step)
    labels = groups(sample, link)
    if support is None:
        first = _reading(points, sample, the_part(sample, labels), None, step)
    else:
        chosen = np.zeros(len(sample), dtype=bool)
        chosen[np.flatnonzero(part)[the_part(sample[part], groups(sample[part], link))]] = True
        first = _reading(points, sample, chosen, support, step)
    strays = _reading(points, sample, the_part(sample, labels, strays_only=True), None, step)
    return [first, strays] if len(strays.points) > ANOTHER * len(first.points) else [first]


def _reading(points, sample, chosen, support, step) -> Observation:
    """Every point of ``points`` within the bounding sphere of the ``chosen`` sample points,
    and above the support plane if there is one."""
    kept = sample[chosen]
    centre, reach = kept.mean(axis=0), radius(kept) + LINK_SPACINGS * step
    inside = np.linalg.norm(points - centre, axis=1) <= reach
    if support is not None:
        inside &= points @ support[:3] - support[3] > PLANE_SPACINGS * step
    observed = points[inside]
    return Observation(observed, len(points) - len(observed), support)
