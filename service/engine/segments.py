"""A frame's points, supports set aside, split into segments: groups of points linked to their
neighbours at the sensor's density. On an organized frame a point's neighbours are its
neighbouring pixels (linear in the pixels); on another cloud, the points within the link
distance (a tree). A segment may hold several touching parts, or a part cut in two by a jump
in depth where it hides itself; ``scene`` handles both.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from service.engine import kernels
from service.engine.frame import Frame
from service.engine.normalize import lengths
from service.engine.surroundings import groups
from service.engine.tuning import (
    CREASE_DEG,
    CREASE_PIXELS,
    LINK_FOOTPRINTS,
    LINK_NOISE,
    NORMAL_PIXELS,
    RIM_STEPS,
)

# neighbouring pixels linked: right, down, the diagonals, and two along (across a missing one)
OFFSETS = ((0, 1), (1, 0), (1, 1), (1, -1), (0, 2), (2, 0))
GRID_OFFSETS, APART = np.array(OFFSETS, dtype=np.intp), np.hypot(*np.array(OFFSETS).T)
LINKS = (LINK_FOOTPRINTS, LINK_NOISE)  # how near neighbours lie to be joined: footprints, range


def segments(
    frame: Frame,
    angle: float,
    links: tuple[float, float] = LINKS,
    rims: np.ndarray | None = None,
) -> np.ndarray:
    """(N,) a segment label per point of ``frame``; ``angle``: the angle between neighbouring
    pixels' rays at full resolution (``Frame.pixel_angle``); ``links``: how near neighbours
    must lie to be joined, in footprints and as a share of the range. ``rims``: a mask of
    points (parts' lower rims, given back from a support's band) that join the segment of
    the pixel nearest them, never two segments: two parts touching only at the support
    stay apart (docs/decisions.md#a-supports-rim-given-back)."""
    if rims is not None and rims.any() and frame.shape is not None and not rims.all():
        labels = np.empty(len(frame), dtype=np.intp)
        labels[~rims] = segments(frame.take(~rims), angle, links)
        labels[rims] = labels[~rims][nearest_pixel(frame, ~rims, rims)]
        return labels
    if len(frame) == 0:
        return np.zeros(0, dtype=np.intp)
    ranges = frame.ranges()
    if frame.shape is None:
        footprints, noise = links
        link = (footprints * angle + noise) * float(np.median(ranges))
        return groups(frame.points, link)
    return grid_segments(frame, angle, ranges, links)


def nearest_pixel(
    frame: Frame, among: np.ndarray, of: np.ndarray, reach: int = RIM_STEPS
) -> np.ndarray:
    """For each point ``of`` names (a mask of the organized ``frame``), which of the points
    ``among`` names (an index into them) lies on the nearest pixel of the frame's grid: looked
    for ``reach`` pixels round it, offsets nearest first (a rim lies that near its part), then
    over the whole grid for any left."""
    rows, columns, _, where = pixel_lookup(frame)
    height, width = frame.grid_shape
    grid = np.full(height * width, -1, dtype=np.intp)  # each pixel's point among ``among``
    held = where >= 0
    grid[held] = np.where(among, np.cumsum(among) - 1, -1)[where[held]]
    grid = grid.reshape(height, width)
    rows, columns = rows[of], columns[of]
    found = np.full(len(rows), -1, dtype=np.intp)
    steps = np.arange(-reach, reach + 1)
    offsets = np.stack(np.meshgrid(steps, steps, indexing="ij"), axis=-1).reshape(-1, 2)
    for down, right in offsets[np.argsort(np.hypot(*offsets.T), kind="stable")]:
        left = np.flatnonzero(found < 0)
        if not len(left):
            return found
        r, c = rows[left] + down, columns[left] + right
        inside = (r >= 0) & (r < height) & (c >= 0) & (c < width)
        found[left[inside]] = grid[r[inside], c[inside]]
    left = np.flatnonzero(found < 0)
    if len(left):
        found[left] = nearest_held(grid, grid >= 0, rows[left], columns[left])
    return found


def nearest_held(
    grid: np.ndarray, held: np.ndarray, rows: np.ndarray, columns: np.ndarray
) -> np.ndarray:
    """The value of ``grid`` (2-D) at the ``held`` cell nearest each of the cells ``rows``,
    ``columns`` (a distance transform of the grid, linear in its cells)."""
    _, (near_rows, near_columns) = ndimage.distance_transform_edt(~held, return_indices=True)
    return grid[near_rows[rows, columns], near_columns[rows, columns]]


def grid_segments(
    frame: Frame,
    angle: float,
    ranges: np.ndarray,
    links: tuple[float, float] = LINKS,
) -> np.ndarray:
    """Connected components of the organized frame's pixels, a pixel linked to each of its
    ``OFFSETS`` neighbours closer than ``links[0]`` of its own footprint (per pixel of
    offset) plus ``links[1]`` of its range."""
    if kernels.switch.enabled:  # linked and joined in one loop (decisions.md#compiled-loops)
        footprints, noise = links
        rows, columns, _, where = pixel_lookup(frame)
        height, width = frame.grid_shape
        reach = footprints * (angle * frame.step * ranges)
        points = np.ascontiguousarray(frame.points)
        return kernels.grid_labels(
            rows, columns, where, width, height, points, reach, noise * ranges, GRID_OFFSETS, APART
        )
    first, second = grid_links(frame, angle, ranges, links)
    return components(len(frame), first, second)


def grid_links(
    frame: Frame,
    angle: float,
    ranges: np.ndarray,
    links: tuple[float, float] = LINKS,
) -> tuple[np.ndarray, np.ndarray]:
    """The linked pairs of neighbouring pixels (``grid_segments``), as two index arrays into
    the frame's points."""
    footprints, noise = links
    step = frame.step
    rows, columns, pixel, where = pixel_lookup(frame)
    grid_height, grid_width = frame.grid_shape
    footprint = angle * step * ranges
    points = frame.points
    firsts, seconds = [], []
    for down, right in OFFSETS:
        length = np.hypot(down, right)
        inside = rows < grid_height - down
        inside &= columns < grid_width - right
        if right < 0:
            inside &= columns >= -right
        mine = np.flatnonzero(inside)
        # np.take: a tenth of indexing's time here (docs/decisions.md#refinements-together)
        other = np.take(where, np.take(pixel, mine) + (down * grid_width + right))
        there = other >= 0
        mine, other = mine[there], other[there]
        gap = lengths(np.take(points, mine, axis=0) - np.take(points, other, axis=0))
        reach = footprints * np.take(footprint, mine) * length
        linked = gap < reach + noise * np.take(ranges, mine)
        firsts.append(mine[linked])
        seconds.append(other[linked])
    return np.concatenate(firsts), np.concatenate(seconds)


def pixel_lookup(frame: Frame) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each point's row, column and pixel on the organized frame's own grid, and the point on
    each pixel of it (flat; -1 where none is)."""
    rows, columns = frame.cells()
    grid_height, grid_width = frame.grid_shape
    pixel = rows * grid_width + columns
    where = np.full(grid_height * grid_width, -1, dtype=np.intp)
    where[pixel] = np.arange(len(frame))
    return rows, columns, pixel, where


def components(count: int, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """(count,) a component label per node of the graph of edges ``first``-``second``."""
    graph = coo_matrix((np.ones(len(first)), (first, second)), shape=(count, count))
    # weak components of the one-way edges: the same labels, without symmetrising the graph
    _, labels = connected_components(graph.tocsr(), directed=True, connection="weak")
    return labels


def cell_groups(points: np.ndarray, cell: float) -> np.ndarray:
    """(N,) a group label per point: the connected components of the occupied cubic cells,
    ``cell`` wide, each joined to its 26 neighbours. Points within ``cell`` of each other are
    always in one group; points more than 2 sqrt(3) cells apart are joined only through others.
    Linear in the points, where a neighbour tree at that reach would list hundreds of pairs
    a point."""
    if not len(points):
        return np.zeros(0, dtype=np.intp)
    keys = np.floor((points - points.min(axis=0)) / cell).astype(np.int64)
    # one number a cell, in the rows' own order: a quarter of the time of unique rows
    spans = keys.max(axis=0) + 1
    flat = (keys[:, 0] * spans[1] + keys[:, 1]) * spans[2] + keys[:, 2]
    numbers, of_point = np.unique(flat, return_inverse=True)
    rest, third = np.divmod(numbers, spans[2])
    cells = np.stack([*np.divmod(rest, spans[1]), third], axis=1).astype(np.float64)
    return groups(cells, 1.75)[of_point.ravel()]  # sqrt(3): the corners


def adjacent(frame: Frame, labels: np.ndarray, chosen: np.ndarray, reach: int) -> set[tuple]:
    """Pairs (a, b), a < b, of the ``chosen`` segments that come within ``reach`` pixels of
    each other in an organized frame's image, whatever the depth between them (a part's near
    side hides its far side); for a cloud without a grid, within ``reach`` times the median
    distance between neighbouring points."""
    chosen_mask = np.zeros(int(labels.max(initial=-1)) + 1, dtype=bool)
    chosen_mask[np.asarray(chosen, dtype=np.intp)] = True
    pick = chosen_mask[labels] if len(labels) else np.zeros(0, dtype=bool)
    if not pick.any():
        return set()
    if frame.shape is None:
        points, mine = frame.points[pick], labels[pick]
        from scipy.spatial import cKDTree

        tree = cKDTree(points)
        spacing = float(np.median(tree.query(points[:256], k=2)[0][:, 1]))
        pairs = tree.query_pairs(reach * spacing, output_type="ndarray")
        a, b = mine[pairs[:, 0]], mine[pairs[:, 1]]
    else:
        rows, columns = frame.cells(pick)
        # the image of the box the chosen pixels span, not the frame's: a tenth of it, often
        rows -= rows.min()
        columns -= columns.min()
        grid_height, grid_width = int(rows.max()) + 1, int(columns.max()) + 1
        image = np.full((grid_height + 2 * reach, grid_width + 2 * reach), -1, dtype=np.intp)
        image[rows + reach, columns + reach] = labels[pick]
        core = image[reach:-reach, reach:-reach]
        a_list, b_list = [], []
        for down in range(0, reach + 1):
            for right in range(-reach, reach + 1):
                if down == 0 and right <= 0:
                    continue
                moved = image[
                    reach + down : reach + down + grid_height,
                    reach + right : reach + right + grid_width,
                ]
                both = (core >= 0) & (moved >= 0) & (core != moved)
                a_list.append(core[both])
                b_list.append(moved[both])
        a, b = np.concatenate(a_list), np.concatenate(b_list)
    different = a != b
    low, high = np.minimum(a, b)[different], np.maximum(a, b)[different]
    return set(zip(low.tolist(), high.tolist(), strict=True))


def creases(frame: Frame, reach: int = CREASE_PIXELS, degrees: float = CREASE_DEG) -> np.ndarray:
    """(N,) a label per point of an organized ``frame`` (a region of one), split where its
    surface folds inward: two parts touching meet in a valley, seen from the camera. A pixel
    lies on a crease where its neighbours ``reach`` pixels to either side (along a row, a
    column or a diagonal) face each other, their normals more than ``degrees`` apart; the
    rest falls into connected pieces, and each crease pixel joins the piece of the nearest
    (docs/decisions.md#touching-parts-split-at-a-crease). One label everywhere without a grid."""
    if frame.shape is None or len(frame) < 3:
        return np.zeros(len(frame), dtype=np.intp)
    rows, columns = frame.cells()
    rows, columns = rows - rows.min() + reach, columns - columns.min() + reach
    shape = (int(rows.max()) + reach + 1, int(columns.max()) + reach + 1)
    held = np.zeros(shape, dtype=bool)
    held[rows, columns] = True
    points = np.zeros((*shape, 3))
    points[rows, columns] = frame.points
    normals = np.zeros((*shape, 3))
    normals[rows, columns] = grid_normals(points, held, rows, columns, frame.viewpoint)
    crease = np.zeros(shape, dtype=bool)
    inner = (slice(reach, shape[0] - reach), slice(reach, shape[1] - reach))
    for down, right in ((0, reach), (reach, 0), (reach, reach), (reach, -reach)):
        before = (slice(reach - down, shape[0] - reach - down),
                  slice(reach - right, shape[1] - reach - right))  # fmt: skip
        after = (slice(reach + down, shape[0] - reach + down),
                 slice(reach + right, shape[1] - reach + right))  # fmt: skip
        both = held[before] & held[after] & held[inner]
        step = points[after] - points[before]
        step /= np.maximum(np.linalg.norm(step, axis=-1, keepdims=True), 1e-12)
        apart = np.einsum("ijk,ijk->ij", normals[before], normals[after])
        facing = np.einsum("ijk,ijk->ij", normals[before] - normals[after], step) > 0
        crease[inner] |= both & facing & (apart < np.cos(np.radians(degrees)))
    pieces, count = ndimage.label(held & ~crease, np.ones((3, 3)))
    if count <= 1:
        return np.zeros(len(frame), dtype=np.intp)
    return nearest_held(pieces, pieces > 0, rows, columns) - 1


def grid_normals(
    points: np.ndarray,
    held: np.ndarray,
    rows: np.ndarray,
    columns: np.ndarray,
    viewpoint: np.ndarray,
    width: int = NORMAL_PIXELS,
) -> np.ndarray:
    """(N,) unit normals at the held pixels ``rows``, ``columns`` of a grid of ``points``:
    the plane of the held pixels in a ``width`` square round each (box sums, linear in the
    pixels), turned towards ``viewpoint``."""
    weight = held.astype(np.float64)
    count = np.maximum(ndimage.uniform_filter(weight, width, mode="constant"), 1e-12)
    mean = (
        np.stack(
            [
                ndimage.uniform_filter(points[..., k] * weight, width, mode="constant")
                for k in range(3)
            ],
            axis=-1,
        )
        / count[..., None]
    )
    covariance = np.empty((len(rows), 3, 3))
    for a in range(3):
        for b in range(a, 3):
            product = ndimage.uniform_filter(
                points[..., a] * points[..., b] * weight, width, mode="constant"
            )
            covariance[:, a, b] = covariance[:, b, a] = (
                product[rows, columns] / count[rows, columns]
                - mean[rows, columns, a] * mean[rows, columns, b]
            )
    _, vectors = np.linalg.eigh(covariance)
    normals = vectors[:, :, 0]
    towards = viewpoint - points[rows, columns]
    return normals * np.where(np.einsum("ij,ij->i", normals, towards) < 0, -1.0, 1.0)[:, None]
