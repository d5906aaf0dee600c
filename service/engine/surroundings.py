"""Step 0, set aside: set aside what surrounds the part: the table it rests on, and stray points.

A cell's camera sees the part on its support, with a few stray points (edges, reflections)
and sometimes other things in view. Before recognition:
- ``support plane``: the largest plane found by RANSAC is the table when it holds at least
  ``PLANE_SHARE`` of the points, has the rest on one side, and spreads around it, mostly
  beyond its footprint: what a table under a part looks like, and what a face of the part
  itself does not (a face lies within the part's footprint, with the part behind it). Its
  points, and those under it, are set aside;
- ``strays``: the points fall into groups of neighbours (within ``LINK_SPACINGS`` times the
  median spacing); groups of a few points, well apart from the rest, are strays. Larger
  groups are all kept: one camera's view of one part often falls apart at the jumps in depth
  where it hides itself,
  so another object in view is not set aside (restrict the search with ``candidates``, or
  crop the cloud, when a cell's view holds several parts).
The answer says how many points were set aside.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from service.engine.normalize import radius, subsample
from service.engine.principal_axes import flatness
from service.engine.tuning import (
    AROUND,
    BEYOND,
    BIN_BAND,
    BIN_FLAT,
    BIN_FLOORS,
    BIN_JOIN,
    BIN_PART_POINTS,
    BIN_PLANE_SHARE,
    BIN_REACH,
    BIN_WALLS,
    LINK_SPACINGS,
    ONE_SIDE,
    PLANE_ITERATIONS,
    PLANE_REACH,
    PLANE_SCORED,
    PLANE_SHARE,
    PLANE_SHARE_BLIND,
    PLANE_SPACINGS,
    STRAY_GAP,
    STRAY_SHARE,
    SURROUNDINGS_SAMPLE,
    THICKNESS,
)

BRUTE_FORCE = 65536  # point pairs measured one by one rather than through a tree, at most
MIN_POINTS = 64  # a reading of fewer points is no part's


@dataclass(frozen=True)
class Reading:
    points: np.ndarray  # (M, 3) what is taken to be the part
    set_aside: int  # points of the original cloud taken to be support, strays or clutter
    support: np.ndarray | None  # (4,) the table's plane n . x = d, if one was found
    spacing: float  # the median distance between neighbouring points of a 1,024-point sample


def plane_candidate(
    points: np.ndarray, step: float, rng: np.random.Generator, share: float = PLANE_SHARE
) -> tuple[np.ndarray, np.ndarray] | None:
    """The plane (n, d with n . x = d) holding most points, by RANSAC, and its inliers; None
    when it holds less than ``share`` of them."""
    samples = points[rng.integers(0, len(points), size=(PLANE_ITERATIONS, 3))]
    normals = np.cross(samples[:, 1] - samples[:, 0], samples[:, 2] - samples[:, 0])
    found = best_plane(points, normals, samples[:, 0], PLANE_SPACINGS * step, rng)
    if found is None or found[1].mean() < share:
        return None
    return found


def best_plane(
    points: np.ndarray,
    normals: np.ndarray,
    through: np.ndarray,
    tolerance: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Of the candidate planes of (unnormalised) ``normals`` through the points ``through``,
    the one most of a sample of ``points`` lie within ``tolerance`` of, and its inliers among
    all of them; None when every candidate is degenerate."""
    length = np.linalg.norm(normals, axis=1)
    good = length > 1e-12
    if not good.any():
        return None
    normals = normals[good] / length[good, None]
    offsets = np.einsum("ij,ij->i", normals, through[good])
    count = len(points)
    scored = points[rng.choice(count, size=min(count, PLANE_SCORED), replace=False)]
    best = int((np.abs(scored @ normals.T - offsets) < tolerance).sum(axis=0).argmax())
    inliers = np.abs(points @ normals[best] - offsets[best]) < tolerance
    return np.append(normals[best], offsets[best]), inliers


def is_support(
    plane: np.ndarray, on_plane: np.ndarray, part: np.ndarray, viewpoint: np.ndarray | None
) -> bool:
    """Whether a plane is a table under ``part`` rather than a face of it: the part lies on
    one side, the camera (if known) on the same side (a face of a part is seen from outside,
    with the part behind it), and the plane spreads around it, mostly beyond its footprint (a
    face lies within the part's). Without a viewpoint the plane must also hold
    ``PLANE_SHARE_BLIND`` of all points (``set_aside_surroundings`` checks that first)."""
    height = part @ plane[:3] - plane[3]
    side = np.sign(np.median(height))
    if np.mean(np.sign(height) == side) < ONE_SIDE:
        return False
    if viewpoint is not None and np.sign(viewpoint @ plane[:3] - plane[3]) != side:
        return False
    centre = part.mean(axis=0)
    offset = on_plane - centre
    across = offset - np.outer(offset @ plane[:3], plane[:3])  # within the plane
    distance = np.linalg.norm(across, axis=1)
    footprint = radius(part)
    beyond = distance > footprint
    if np.percentile(distance, 95) < PLANE_REACH * footprint or beyond.mean() < BEYOND:
        return False
    # a table surrounds the part; a face of a part reaches out to one side of the rest
    u = across[beyond][:, :] @ _in_plane(plane[:3])
    sectors = np.unique(np.floor((np.arctan2(u[:, 1], u[:, 0]) + np.pi) / (2 * np.pi) * 12))
    return bool(len(sectors) >= AROUND)


def _in_plane(normal: np.ndarray) -> np.ndarray:
    """(3, 2) two unit vectors spanning the plane of ``normal``."""
    helper = np.array([1.0, 0, 0]) if abs(normal[0]) < 0.9 else np.array([0, 1.0, 0])
    first = np.cross(normal, helper)
    first /= np.linalg.norm(first)
    return np.stack([first, np.cross(normal, first)], axis=1)


def groups(points: np.ndarray, link: float, tree: cKDTree | None = None) -> np.ndarray:
    """A group label per point: connected components of the within-``link`` neighbour graph
    (``tree``: a ``cKDTree`` of ``points``, if one is at hand)."""
    pairs = (tree or cKDTree(points)).query_pairs(link, output_type="ndarray")
    # the graph in compressed rows, built directly (a COO matrix's conversion costs more
    # than the components); weak components of i -> j are the undirected ones
    order = np.argsort(pairs[:, 0], kind="stable")
    starts = np.zeros(len(points) + 1, dtype=np.int64)
    np.cumsum(np.bincount(pairs[:, 0], minlength=len(points)), out=starts[1:])
    graph = csr_matrix(  # float64 weights: what connected_components would convert them to
        (np.ones(len(pairs)), pairs[order, 1], starts),
        shape=(len(points), len(points)),
    )
    _, labels = connected_components(graph, directed=True, connection="weak")
    return labels


def the_part(points: np.ndarray, labels: np.ndarray, step: float) -> np.ndarray:
    """Which points belong to the part, given their ``groups``: every group but stray ones,
    each under ``STRAY_SHARE`` of the points and more than ``STRAY_GAP`` spacings from any
    larger group. A single view of one part often falls apart at the jumps in depth where it
    hides itself, so larger groups are never set aside."""
    sizes = np.bincount(labels)
    keep = np.isin(labels, np.flatnonzero(sizes >= STRAY_SHARE * len(labels)))
    if keep.all() or not keep.any():
        return np.ones(len(points), dtype=bool) if not keep.any() else keep
    outside, inside = points[~keep], points[keep]
    if len(outside) * len(inside) <= BRUTE_FORCE:  # a few strays: cheaper than a tree
        gap = np.sqrt(cdist(outside, inside, "sqeuclidean").min(axis=1))
    else:
        gap, _ = cKDTree(inside).query(outside, k=1)
    keep[np.flatnonzero(~keep)[gap <= STRAY_GAP * step]] = True
    return keep


def set_aside_surroundings(
    points: np.ndarray, rng: np.random.Generator, viewpoint: np.ndarray | None = None
) -> list[Reading]:
    """What may be the part's points (of all of ``points``): strays set aside, and a support
    plane if there is one; where a plane was set aside, also the reading that
    keeps it (in case it is the part's own face). The engine keeps the one the part fits best.

    The plane is found on a sample of ``SURROUNDINGS_SAMPLE``; what lies off it is judged on a
    sample of its own, so that a part small in the camera's view (a twentieth of the points,
    the rest table) is judged on as many points as a part that fills it. Then every point inside the
    part's bounding sphere (and above the table) is the part's."""
    sample = points[subsample(points, SURROUNDINGS_SAMPLE, rng)]
    tree = cKDTree(sample)
    step = median_spacing(sample, tree)
    everything = the_part(sample, groups(sample, LINK_SPACINGS * step, tree), step)
    whole = _reading(points, sample, everything, None, step)
    found = plane_candidate(sample, step, rng)
    if found is None:
        return [whole]
    plane, on_plane = found
    if viewpoint is None and on_plane.mean() < PLANE_SHARE_BLIND:
        # the share of all points on the plane, from the sample; the part's points cannot be
        # counted against the plane's, as they once were: they are a sample of their own
        # (1,024 of the rest), so a table under a part seen by more than ~1,000 points never
        # held half of them, whatever its share of the cloud
        return [whole]
    plane, thickness = fitted(sample[on_plane], plane, PLANE_SPACINGS * step)
    rest = points[np.abs(points @ plane[:3] - plane[3]) >= thickness]
    if len(rest) < 20:
        return [whole]
    kept = subsample(rest, SURROUNDINGS_SAMPLE, rng)
    # the part is seen as densely as the table around it: its spacing in its own sample, from
    # the sample's (the median of the rest's would be the strays' where they outnumber it)
    rest_step = step * np.sqrt(SURROUNDINGS_SAMPLE * len(rest) / (len(kept) * len(points)))
    rest = rest[kept]
    main = rest[the_part(rest, groups(rest, LINK_SPACINGS * rest_step), rest_step)]
    if not is_support(plane, sample[on_plane], main, viewpoint):
        return [whole]
    support = plane * np.sign(np.median(main @ plane[:3] - plane[3]))  # normal towards the part
    above = np.flatnonzero(rest @ support[:3] - support[3] > thickness)
    chosen = np.zeros(len(rest), dtype=bool)
    link = LINK_SPACINGS * rest_step
    chosen[above[the_part(rest[above], groups(rest[above], link), rest_step)]] = True
    part = _reading(points, rest, chosen, support, step, thickness)
    return [part, whole]  # whole: in case the plane is the part's own face


def set_aside_bin(
    points: np.ndarray, rng: np.random.Generator, viewpoint: np.ndarray | None
) -> Reading | None:
    """The part in a bin, seen by a camera at ``viewpoint``: the bin's floor (or the table it
    stands on) and its walls set aside, where ``set_aside_surroundings`` sets aside one plane
    and the walls stay with the part. The floor is the largest plane (else the next largest:
    a wall facing the camera may hold more); the walls are the largest planes upright on it
    (``upright_plane``), each with the part on its inner side and reaching farther from the
    part's centre than the part does (``BIN_REACH``): a face of the part reaches no farther
    than the rest of it. None unless at least one wall and a part (``largest_solid``) are
    found (docs/decisions.md#a-part-in-a-bin)."""
    if viewpoint is None or len(points) < MIN_POINTS:
        return None
    sample = points[subsample(points, SURROUNDINGS_SAMPLE, rng)]
    step = median_spacing(sample, cKDTree(sample))
    left = np.ones(len(sample), dtype=bool)
    for _ in range(BIN_FLOORS):
        rest = np.flatnonzero(left)
        if len(rest) < MIN_POINTS:  # the first plane held (nearly) everything
            return None
        found = plane_candidate(sample[rest], step, rng, BIN_PLANE_SHARE * len(sample) / len(rest))
        if found is None:
            return None
        on_floor = sample[rest[found[1]]]
        floor, thickness = fitted(on_floor, found[0], PLANE_SPACINGS * step)
        floor = floor * np.sign(viewpoint @ floor[:3] - floor[3])  # the camera looks into it
        reading = _in_bin(points, sample, step, floor, thickness, on_floor, rng)
        if reading is not None:
            return reading
        left[rest[found[1]]] = False
    return None


def _in_bin(points, sample, step, floor, floor_thickness, on_floor, rng) -> Reading | None:
    """``set_aside_bin`` on the floor ``floor`` (its ``on_floor`` sample points)."""
    # a noisy sensor's floor is thicker than its fitted band: a wider one is not a wall's
    left = sample @ floor[:3] - floor[3] > BIN_BAND * floor_thickness
    walls = []
    for _ in range(BIN_WALLS):
        wall = upright_plane(sample, left, floor[:3], step, rng)
        if wall is None:
            break
        walls.append(wall)
        left &= np.abs(sample @ wall[0][:3] - wall[0][3]) >= BIN_BAND * wall[1]
    # the bin's inside: each wall's side where most of the floor lies
    inside = on_floor.mean(axis=0)
    walls = [(wall * np.sign(inside @ wall[:3] - wall[3]), t) for wall, t in walls]
    pool = sample @ floor[:3] - floor[3] > floor_thickness
    for wall, thickness in walls:
        pool &= sample @ wall[:3] - wall[3] >= thickness
    if not walls or pool.sum() < BIN_PART_POINTS:
        return None
    kept = largest_solid(sample[pool], LINK_SPACINGS * step)
    if len(kept) < BIN_PART_POINTS:
        return None
    centre, reach = kept.mean(axis=0), radius(kept)
    bounds = [(floor, floor_thickness)]
    for wall, thickness in walls:
        on_wall = np.abs(sample @ wall[:3] - wall[3]) < thickness
        if not on_wall.any():
            continue
        spread = np.linalg.norm(sample[on_wall] - centre, axis=1)
        inner = np.mean(kept @ wall[:3] - wall[3] > thickness)
        if inner >= ONE_SIDE and np.percentile(spread, 95) >= BIN_REACH * reach:
            bounds.append((wall, thickness))
    if len(bounds) < 2:
        return None  # no wall round the part: a table's (or a part's own faces)
    chosen = np.linalg.norm(points - centre, axis=1) <= reach + LINK_SPACINGS * step
    for plane, thickness in bounds:
        chosen &= points @ plane[:3] - plane[3] > thickness
    if chosen.sum() < MIN_POINTS:
        return None
    return Reading(points[chosen], len(points) - int(chosen.sum()), floor, step)


def largest_solid(points: np.ndarray, link: float) -> np.ndarray:
    """The part among ``points`` (what a bin holds off its floor and walls): the largest group
    of them (neighbours within ``link``) that is not flat (a piece of wall no plane was found
    for is; else the largest), with the groups not flat within ``BIN_JOIN`` of its radius of
    it (one view of a part falls apart where it hides itself)."""
    labels = groups(points, link)
    sizes = np.bincount(labels)
    solid = {}
    for label in np.flatnonzero(sizes >= 3):
        group = points[labels == label]
        solid[label] = flatness(group - group.mean(axis=0)) > BIN_FLAT
    big = [label for label in np.argsort(-sizes) if sizes[label] >= BIN_PART_POINTS]
    if not big:
        return points[:0]
    main = next((label for label in big if solid[label]), big[0])
    kept = points[labels == main]
    reach, tree = radius(kept), cKDTree(kept)
    joined = [kept]
    for label, is_solid in solid.items():
        if label == main or not is_solid:
            continue
        group = points[labels == label]
        if tree.query(group, k=1)[0].min() <= BIN_JOIN * reach:
            joined.append(group)
    return np.vstack(joined)


def upright_plane(
    sample: np.ndarray, left: np.ndarray, up: np.ndarray, step: float, rng: np.random.Generator
) -> tuple[np.ndarray, float] | None:
    """The plane upright on a floor of normal ``up`` holding most of the ``left`` points, by
    RANSAC over the planes through two of them and ``up``, and its thickness; None when it
    holds less than ``BIN_PLANE_SHARE`` of the sample."""
    rest = sample[left]
    if len(rest) < 2:
        return None
    pairs = rest[rng.integers(0, len(rest), size=(PLANE_ITERATIONS, 2))]
    tolerance = PLANE_SPACINGS * step
    found = best_plane(rest, np.cross(pairs[:, 1] - pairs[:, 0], up), pairs[:, 0], tolerance, rng)
    if found is None or found[1].sum() < BIN_PLANE_SHARE * len(sample):
        return None
    return fitted(rest[found[1]], found[0], tolerance)


def fitted(on_plane: np.ndarray, plane: np.ndarray, most: float) -> tuple[np.ndarray, float]:
    """The plane fitted to its RANSAC inliers by least squares, and how thick the table is:
    ``THICKNESS`` robust standard deviations of their distances, at most ``most``. The
    RANSAC plane's tilt and tolerance would cut the foot of a thin part resting on it."""
    centre = on_plane.mean(axis=0)
    normal = np.linalg.svd(on_plane - centre, full_matrices=False)[2][2]
    normal = normal * np.sign(normal @ plane[:3])
    residual = np.abs((on_plane - centre) @ normal)
    thickness = min(most, THICKNESS * 1.4826 * float(np.median(residual)))
    return np.append(normal, normal @ centre), thickness


def median_spacing(points: np.ndarray, tree: cKDTree) -> float:
    """The median distance from a point to its nearest neighbour, over the first 256 points
    (``points`` is a random sample; ``tree`` a ``cKDTree`` of them)."""
    distance, _ = tree.query(points[: min(256, len(points))], k=2)
    return float(np.median(distance[:, 1]))


def _reading(points, sample, chosen, support, step, thickness=0.0) -> Reading:
    """Every point of ``points`` within the bounding sphere of the ``chosen`` sample points,
    and more than ``thickness`` above the support plane if there is one."""
    kept = sample[chosen]
    centre, reach = kept.mean(axis=0), radius(kept) + LINK_SPACINGS * step
    inside = np.linalg.norm(points - centre, axis=1) <= reach
    if support is not None:
        inside &= points @ support[:3] - support[3] > thickness
    observed = points[inside]
    return Reading(observed, len(points) - len(observed), support, step)


def as_is(points: np.ndarray, rng: np.random.Generator) -> Reading:
    """The whole of ``points`` as one reading, nothing set aside (a frame's segment, whose
    supports are already set aside)."""
    sample = points[subsample(points, SURROUNDINGS_SAMPLE, rng)]
    return Reading(points, 0, None, median_spacing(sample, cKDTree(sample)))
