"""A frame's supports: the largest planes (the table, a bin's floor and walls), set aside with
what lies behind the first of them, before the parts are looked for.

A plane found by RANSAC is a support when it holds ``SUPPORT_SHARE`` of the frame's points
and what lies over it is on the camera's side: parts rest on a table, in a bin; but behind a
part's own face lies the rest of the part (``BEHIND_SHARE``). The first support is the one
the parts rest on (a table, a bin's floor); what lies beyond it, away from the camera (the
floor under a table, the table under a bin), is set aside with it. What lies behind a plane
but apart from it (the floor the camera sees past a table's edge) does not count against it; a
bin's floor lies level on the table and just above it, and a later plane is a support only
level with an earlier one, over it (a table over the floor) or upright on it (a wall): two
parts' faces may lie in one plane; the largest part is the largest that fits in what is left
once the first support is set aside (docs/decisions.md#detect).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from service.engine import kernels
from service.engine.bins import Band, bin_band
from service.engine.frame import Frame
from service.engine.normalize import distances, lengths, subsample
from service.engine.segments import components, grid_links
from service.engine.tuning import (
    BEHIND_SHARE,
    BOUND_CELLS,
    BOUND_STRAYS,
    CARRIED_POINTS,
    FLOOR_DEG,
    LATER_SHARE,
    LEVEL_CONNECTED,
    MAX_PLANES,
    MAX_SUPPORTS,
    PART_EXTENTS,
    RAISED_SHARE,
    RIM_NOISES,
    RIM_STEPS,
    SENSOR_NOISE,
    SLAB_SHARE,
    SUPPORT_CELLS,
    SUPPORT_CONNECTED,
    SUPPORT_ITERATIONS,
    SUPPORT_NOISE,
    SUPPORT_POINTS,
    SUPPORT_REACH,
    SUPPORT_SAMPLE,
    SUPPORT_SHARE,
    SUPPORT_SPACINGS,
    WALL_DEG,
    WALL_REACH,
)


@dataclass(frozen=True)
class Support:
    plane: np.ndarray  # (4,) n . x = d, the normal towards the camera
    points: int  # the frame's points on it
    noise: float  # the robust spread of their distances to it (the sensor's depth noise) ...
    at_range: float  # ... at this median range from the camera
    band: Band | None = None  # a bin's floor: where its walls and rims stand (``bins``)

    def noise_at(self, distance: float | np.ndarray) -> float | np.ndarray:
        """The sensor's noise at ``distance`` (or each of them) from the camera, growing with
        the range."""
        return self.noise * distance / max(self.at_range, 1e-12)


def tolerances(frame: Frame, angle: float, step: int | None = None) -> np.ndarray:
    """(N,) how far from a support plane each point of the frame may lie and be on it: some
    pixel footprints (of a grid of stride ``step``, the frame's own by default) at its range,
    and the sensor's depth noise."""
    step = frame.step if step is None else step
    return frame.ranges() * (SUPPORT_SPACINGS * angle * step + SUPPORT_NOISE)


def largest_fitting(scales: np.ndarray, size: float) -> float:
    """The largest of the parts' ``scales`` no larger than ``size`` (of them all, if none is):
    the largest part a cloud of that radius may hold."""
    fits = scales[scales <= size]
    return float((fits if len(fits) else scales).max())


def extent(points: np.ndarray) -> float:
    """How far a cloud reaches from its centroid, stray points aside (the 95th percentile)."""
    if not len(points):
        return 0.0
    return float(np.percentile(distances(points, points.mean(axis=0)), 95))


def set_aside_supports(
    frame: Frame, angle: float, scales: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, list[Support]]:
    """Which of the frame's points are left once the supports are set aside (a mask), and the
    supports. ``angle``: the angle between neighbouring pixels' rays (``Frame.pixel_angle``);
    ``scales``: those of the parts the frame may hold (the largest that fits in the frame, then
    in what is left once the first support is set aside, is the largest a part may have).
    The supports are found on a coarser copy of ``SUPPORT_POINTS`` points at most, judged at
    the frame's own tolerances, and set aside at the frame's resolution: a support holds a
    share of the frame, and a quarter of its points tell it as well
    (docs/decisions.md#supports-on-a-coarser-copy)."""
    coarse = frame.at_most(SUPPORT_POINTS, rng)
    density = len(frame) / max(len(coarse), 1)
    supports = find_supports(coarse, angle, scales, rng, frame.step, density)
    return apply_supports(frame, supports, angle), supports


def find_supports(
    frame: Frame,
    angle: float,
    scales: np.ndarray,
    rng: np.random.Generator,
    step: int,
    density: float,
) -> list[Support]:
    """The supports of a frame (``set_aside_supports``), found on its coarser copy ``frame``:
    ``step``: the stride of the frame's own grid, whose tolerances and cells they are judged
    at; ``density``: how many of its points each of the copy's stands for."""
    if not len(frame):
        return []
    largest = largest_fitting(scales, extent(frame.points))
    links: tuple[np.ndarray, np.ndarray] | None = None  # the frame's pixel links, if needed
    floors: list[np.ndarray] = []  # the points of the bins' floors found
    bases: list[Support] = []  # the supports a bin's floor may stand on: all but floors
    keep = np.ones(len(frame), dtype=bool)
    faces = np.zeros(len(frame), dtype=bool)  # on planes found to be parts' faces
    supports: list[Support] = []
    tolerance = tolerances(frame, angle, step)
    ranges = frame.ranges()
    cell = SUPPORT_CELLS * angle * step * float(np.median(ranges))
    for _ in range(MAX_PLANES):
        rest = np.flatnonzero(keep & ~faces)
        # the first holds a share of the frame; the next (walls) a share of what is left
        least = LATER_SHARE * keep.sum() if supports else SUPPORT_SHARE * len(frame)
        if len(rest) < max(least, 3) or len(supports) == MAX_SUPPORTS:
            break
        found = largest_plane(frame.points[rest], tolerance[rest], rng)
        if found is None or len(found[1]) < least:
            break
        plane, on = found
        plane = plane * (1.0 if plane[:3] @ frame.viewpoint >= plane[3] else -1.0)
        others = keep.copy()
        others[rest[on]] = False
        off = np.flatnonzero(others)
        on_plane = frame.points[rest[on]]
        across = reach(on_plane, plane)
        # a bin's floor: level with the table, just above it; a later plane that is neither
        # level, raised nor a wall may be parts' faces in one plane, however far it reaches
        # (docs/decisions.md#parts-faces-in-one-tilted-plane); one level with a bin's floor
        # is flat parts' tops on it (docs/decisions.md#flat-parts-tops-over-a-bins-floor)
        level = any(is_level(on_plane, plane, below, across) for below in bases)
        # a table over the floor, where the floor was found first (docs/decisions.md#detect)
        raised = bool(supports) and is_raised(on_plane, plane, supports[0], across)
        raised = raised and len(on) * density >= RAISED_SHARE * supports[0].points
        # no part's face reaches this far: the table under a bin, whatever lies behind its
        # cells (a later plane may be parts' faces side by side: it must carry, or be a wall)
        vast = not supports and across >= SUPPORT_REACH * largest
        wall = bool(supports) and is_wall(
            on_plane, plane, supports, floors, across, largest, tolerance[rest[on]], cell
        )
        # the first may carry nothing (an empty table); a later one is a wall, or carries
        # something and lies level with an earlier one or over it
        least_over = CARRIED_POINTS if supports else 0
        may_carry = not supports or level or raised
        carrying = may_carry and carries(
            on_plane, frame.points[off], plane, cell, least_over, density=density
        )
        if may_carry and not carrying and frame.shape is not None:
            # the background seen past a table's edge lies behind it too, but apart from it
            if links is None:
                links = grid_links(frame, angle, ranges)
            apart = detached_behind(frame, links, rest[on], off, plane, tolerance, across)
            carrying = carries(on_plane, frame.points[off], plane, cell, least_over, apart, density)
        support = wall or carrying or vast
        if support and supports:  # one surface, not a slice through a pile's tops
            # parts lying on a bin's floor cut it up (decisions.md#a-bins-walls-and-rims)
            least_patch = LEVEL_CONNECTED if level else SUPPORT_CONNECTED
            support = connected(on_plane, plane, cell) >= least_patch
        if not support:
            faces[rest[on]] = True  # a part's face: the next plane may still be a support
            continue
        keep[rest[on]] = False
        band = None
        if level:
            floors.append(on_plane)
            slack = float(np.median(tolerance[rest[on]]))
            axes = in_plane(plane[:3])
            found = bin_band(on_plane, plane, axes, frame.points, keep, cell, across, slack, rng)
            if found is not None:
                band, held = found
                keep &= ~held
        if not supports:  # what lies beyond the surface the parts rest on
            keep &= frame.points @ plane[:3] - plane[3] > -tolerance
            if keep.any():  # the parts lie in what is left
                largest = largest_fitting(scales, PART_EXTENTS * extent(frame.points[keep]))
        residual = on_plane @ plane[:3] - plane[3]
        spread = 1.4826 * float(np.median(np.abs(residual - np.median(residual))))
        distance = distances(on_plane, frame.viewpoint)
        counted = int(round(len(on) * density))
        supports.append(Support(plane, counted, spread, float(np.median(distance)), band))
        if not level:  # a bin's floor stands on no other floor
            bases.append(supports[-1])
    return supports


def carries(
    on_plane: np.ndarray,
    others: np.ndarray,
    plane: np.ndarray,
    cell: float,
    least: int = 0,
    apart: np.ndarray | None = None,
    density: float = 1.0,
) -> bool:
    """Whether a plane carries what lies over it, as a table does: of the other points over
    the cells its own points occupy (more than ``least`` of them, and than ``CARRIED_POINTS``:
    else it is a bare surface, which carries only where ``least`` is 0), less than
    ``BEHIND_SHARE`` lie behind it (away from the camera), as a part's rest lies behind its
    face. ``apart``: a mask of ``others`` that do not count (``detached_behind``);
    ``density``: how many points each of them stands for (a coarser copy's)."""
    if apart is not None:
        others = others[~apart]
    if not len(others):
        return least == 0
    over = lies_over(on_plane, others, plane, cell)
    if over.sum() * density <= max(least, CARRIED_POINTS):  # too few to judge: a bare surface
        return least == 0
    height = others[over] @ plane[:3] - plane[3]
    return bool(np.mean(height < 0) < BEHIND_SHARE)


def lies_over(
    on_plane: np.ndarray, others: np.ndarray, plane: np.ndarray, cell: float
) -> np.ndarray:
    """(M,) which of the ``others`` lie over (in front of or behind) the cells, ``cell`` wide,
    that the plane's points occupy."""
    occupied, axes, low = cell_grid(on_plane, plane, cell)
    cells = np.floor(others @ axes / cell).astype(np.int64) - low
    inside = np.all((cells >= 0) & (cells < occupied.shape), axis=1)
    over = np.zeros(len(others), dtype=bool)
    over[inside] = occupied[cells[inside, 0], cells[inside, 1]]
    return over


def detached_behind(
    frame: Frame,
    links: tuple[np.ndarray, np.ndarray],
    on: np.ndarray,
    off: np.ndarray,
    plane: np.ndarray,
    tolerance: np.ndarray,
    across: float,
) -> np.ndarray:
    """A mask of the points ``off`` the plane (indices into ``frame``) that lie behind it but
    are not linked to its points ``on`` through points behind it (``links``: the frame's
    neighbouring pixel pairs, ``segments.grid_links``): the background the camera sees past a
    table's edge, under it; and of those linked that lie less than ``SLAB_SHARE`` of its
    reach (``across``) behind it: a table top's edge. The rest of a part lies behind its face,
    joins it, and reaches about as deep as the face is wide."""
    height = frame.points[off] @ plane[:3] - plane[3]
    behind = np.zeros(len(frame), dtype=bool)
    behind[off] = height < -tolerance[off]
    member = behind.copy()
    member[on] = True
    first, second = links
    both = member[first] & member[second]
    labels = components(len(frame), first[both], second[both])
    joined = np.zeros(int(labels.max(initial=-1)) + 1, dtype=bool)
    joined[labels[on]] = True
    edge = height > -SLAB_SHARE * across
    return behind[off] & (~joined[labels[off]] | edge)


def level_and_height(
    on_plane: np.ndarray, plane: np.ndarray, floor: Support, degrees: float = WALL_DEG
) -> tuple[bool, float]:
    """Whether a plane lies level with a support found before it (within ``degrees``), and
    how high above it its points lie (median)."""
    level = abs(float(plane[:3] @ floor.plane[:3])) > np.cos(np.radians(degrees))
    return level, float(np.median(on_plane @ floor.plane[:3] - floor.plane[3]))


def is_level(on_plane: np.ndarray, plane: np.ndarray, floor: Support, across: float) -> bool:
    """Whether a plane lies level with a support found before it, above it by less than
    ``SLAB_SHARE`` of its reach (``across``) and within ``FLOOR_DEG`` of it: a bin's floor on a
    table, not the face of a part (which would be a thin plate), nor parts' tops in one plane
    (docs/decisions.md#a-bins-floor-level-with-the-table)."""
    level, height = level_and_height(on_plane, plane, floor, FLOOR_DEG)
    return level and 0 < height < SLAB_SHARE * across


def is_raised(on_plane: np.ndarray, plane: np.ndarray, floor: Support, across: float) -> bool:
    """Whether a plane lies level with the first support and above it by more than a bin's
    floor would (``is_level``): a table over the floor the camera saw more of. It must still
    carry what lies over it, and be one patch, to be a support."""
    level, height = level_and_height(on_plane, plane, floor)
    return level and height >= SLAB_SHARE * across


def is_wall(
    on_plane: np.ndarray,
    plane: np.ndarray,
    supports: list[Support],
    floors: list[np.ndarray],
    across: float,
    largest: float,
    slack: np.ndarray,
    cell: float,
) -> bool:
    """Whether a plane is a bin's wall: upright on a support found before it (``WALL_DEG``),
    standing on it, and reaching along it (``across``: its ``reach``) farther than any part
    could (``WALL_REACH`` times the largest part's scale), or bounding a bin's floor found
    before it (``floors``: their points; ``bounds``). Behind a bin's near wall lies what the
    bin holds, so ``carries`` does not tell it from a part's face."""
    standing = False
    for floor in supports:
        upright = abs(float(plane[:3] @ floor.plane[:3])) < np.sin(np.radians(WALL_DEG))
        height = on_plane @ floor.plane[:3] - floor.plane[3]
        standing = standing or (upright and bool(np.min(height - slack) <= 0))
    if not standing:
        return False
    if across >= WALL_REACH * largest:
        return True
    return any(bounds(plane, points, cell) for points in floors)


def bounds(plane: np.ndarray, floor: np.ndarray, cell: float) -> bool:
    """Whether a plane bounds a bin's ``floor`` (its points): the floor lies on one side of
    it (all but ``BOUND_STRAYS`` of its points) and comes within ``BOUND_CELLS`` cells of it."""
    side = floor @ plane[:3] - plane[3]
    one_side = min(np.mean(side > 0), np.mean(side < 0)) < BOUND_STRAYS
    return bool(one_side and np.percentile(np.abs(side), 1) < BOUND_CELLS * cell)


def cell_grid(
    on_plane: np.ndarray, plane: np.ndarray, cell: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which cells (``cell`` wide, in the plane) a plane's points occupy: the grid, the
    plane's two in-plane axes, and the grid's lowest cell."""
    axes = in_plane(plane[:3])
    mine = np.floor(on_plane @ axes / cell).astype(np.int64)
    low = mine.min(axis=0)
    mine -= low
    occupied = np.zeros(mine.max(axis=0) + 1, dtype=bool)
    occupied[mine[:, 0], mine[:, 1]] = True
    return occupied, axes, low


def connected(on_plane: np.ndarray, plane: np.ndarray, cell: float) -> float:
    """The share of the cells a plane's points occupy (``cell`` wide) that lie in its largest
    patch of neighbouring cells: near 1 for a table or a bin's floor (the parts on it are
    islands), low for a plane through the tops of parts lying side by side (strips)."""
    grid, _, _ = cell_grid(on_plane, plane, cell)
    labels, count = ndimage.label(grid, structure=np.ones((3, 3)))
    if count == 0:
        return 0.0
    sizes = np.bincount(labels.ravel())[1:]
    return float(sizes.max() / sizes.sum())


def reach(on_plane: np.ndarray, plane: np.ndarray) -> float:
    """How far a plane's points reach across it from their centre (the 95th percentile)."""
    offset = on_plane - on_plane.mean(axis=0)
    across = offset - np.outer(offset @ plane[:3], plane[:3])
    return float(np.percentile(lengths(across), 95))


def in_plane(normal: np.ndarray) -> np.ndarray:
    """(3, 2) two unit vectors spanning the plane of ``normal``."""
    helper = np.array([1.0, 0, 0]) if abs(normal[0]) < 0.9 else np.array([0, 1.0, 0])
    first = np.cross(normal, helper)
    first /= np.linalg.norm(first)
    return np.stack([first, np.cross(normal, first)], axis=1)


def largest_plane(
    points: np.ndarray, tolerance: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray] | None:
    """The plane holding most of ``points`` (each within its own ``tolerance``), by RANSAC on
    a sample, refitted by least squares to its inliers; and the indices of its inliers."""
    chosen = subsample(points, SUPPORT_SAMPLE, rng)
    sample, slack = points[chosen], tolerance[chosen]
    triples = sample[rng.integers(0, len(sample), size=(SUPPORT_ITERATIONS, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    length = lengths(normals)
    good = length > 1e-12
    if not good.any():
        return None
    normals = normals[good] / length[good, None]
    offsets = np.einsum("ij,ij->i", normals, triples[good, 0])
    best = int(msac_votes(sample, normals, offsets, slack).argmax())
    on = np.flatnonzero(np.abs(points @ normals[best] - offsets[best]) < tolerance)
    if len(on) < 3:
        return None
    inliers = points[on]
    centre = inliers.mean(axis=0)
    normal = np.linalg.svd(inliers - centre, full_matrices=False)[2][2]
    plane = np.append(normal, normal @ centre)
    on = np.flatnonzero(np.abs(points @ plane[:3] - plane[3]) < tolerance)
    return plane, on


def msac_votes(
    sample: np.ndarray, normals: np.ndarray, offsets: np.ndarray, slack: np.ndarray
) -> np.ndarray:
    """(P,) each plane's vote: each point's falls off with its distance (MSAC), 1 - (|n . p -
    d| / slack)^2, at least 0; a plane tilted through two levels (a bin's floor 1 cm over the
    table) holds both within the tolerance, but loosely. Compiled, one loop in float64;
    else in place on one (sample, planes) array in float32, half the memory streamed (the
    same plane chosen every time measured: docs/decisions.md#supports-on-a-coarser-copy)."""
    if kernels.switch.enabled:
        return kernels.msac_votes(sample, normals, offsets, slack)
    near = sample.astype(np.float32) @ normals.T.astype(np.float32)
    near -= offsets.astype(np.float32)
    np.abs(near, out=near)
    near /= slack.astype(np.float32)[:, None]
    np.square(near, out=near)
    np.subtract(1, near, out=near)
    return np.maximum(near, 0, out=near).sum(axis=0)


def apply_supports(frame: Frame, supports: list[Support], angle: float) -> np.ndarray:
    """Which of the frame's points are left once the ``supports`` found on a thinned copy of
    it are set aside (a mask), as ``set_aside_supports`` sets them aside."""
    tolerance = tolerances(frame, angle)
    keep = np.ones(len(frame), dtype=bool)
    heights = []  # each point's height over each support
    for k, support in enumerate(supports):
        height = frame.points @ support.plane[:3] - support.plane[3]
        heights.append(height)
        keep &= np.abs(height) >= tolerance
        if k == 0:
            keep &= height > -tolerance
        if support.band is not None:
            keep &= ~support.band.holds(frame.points)
    if supports:
        keep |= rim(frame, keep, supports, heights, tolerance)
    return keep


def rim(
    frame: Frame,
    keep: np.ndarray,
    supports: list[Support],
    heights: list[np.ndarray],
    tolerance: np.ndarray,
) -> np.ndarray:
    """A mask of the points set aside only by the band of the support the parts rest on (a
    bin's floor, else the first) that are a part's lower rim: more than ``RIM_NOISES`` times
    its noise over it (and half the band), reached from a point ``keep`` holds through such
    points, ``RIM_STEPS`` pixels at most. The support's own noise, away from a part, stays set
    aside, and so does the table's band round a bin, where only the bin's walls stand
    (docs/decisions.md#a-supports-rim-given-back). ``heights``: each point's over each of the
    ``supports``, as ``apply_supports`` measured them."""
    given = np.zeros(len(frame), dtype=bool)
    if frame.shape is None or not keep.any():
        return given
    resting = resting_support(supports)
    height = heights[next(k for k, s in enumerate(supports) if s is resting)]
    lower = np.flatnonzero(~keep & (height > tolerance / 2) & (height < tolerance))
    lower = lower[height[lower] > RIM_NOISES * resting.noise_at(frame.ranges()[lower])]
    for support, over in zip(supports, heights, strict=True):
        if support is not resting:
            lower = lower[np.abs(over[lower]) >= tolerance[lower]]
        if support.band is not None:
            lower = lower[~support.band.holds(frame.points[lower])]
    if not len(lower):
        return given
    # grown from the kept points through the lower ones, on the grid round the lower ones only
    rows, columns = frame.cells(lower)
    low = np.array([rows.min(), columns.min()]) - RIM_STEPS
    high = np.array([rows.max(), columns.max()]) + RIM_STEPS + 1
    kept_rows, kept_columns = frame.cells(np.flatnonzero(keep))
    near = (kept_rows >= low[0]) & (kept_rows < high[0])
    near &= (kept_columns >= low[1]) & (kept_columns < high[1])
    kept, may = (np.zeros(high - low, dtype=bool) for _ in range(2))
    kept[kept_rows[near] - low[0], kept_columns[near] - low[1]] = True
    may[rows - low[0], columns - low[1]] = True
    grown = ndimage.binary_dilation(kept, np.ones((3, 3)), RIM_STEPS, mask=may | kept)
    given[lower] = grown[rows - low[0], columns - low[1]]
    return given


def resting_support(supports: list[Support]) -> Support:
    """The support the parts rest on: a bin's floor, else the first (a table)."""
    return next((s for s in supports if s.band is not None), supports[0])


def in_rims(frame: Frame, supports: list[Support], angle: float) -> np.ndarray:
    """(N,) which of the points left once the ``supports`` are set aside lie in the band of
    the one the parts rest on: the lower rims ``rim`` gave back."""
    if not supports:
        return np.zeros(len(frame), dtype=bool)
    plane = resting_support(supports).plane
    return np.abs(frame.points @ plane[:3] - plane[3]) < tolerances(frame, angle)


@dataclass(frozen=True)
class Noise:
    """The sensor's depth noise where points lie: measured on the support the parts rest on,
    grown with the range; without one, ``SENSOR_NOISE`` of the range."""

    support: Support | None

    def at(self, points: np.ndarray, viewpoint: np.ndarray) -> float:
        distance = float(np.median(distances(points, viewpoint)))
        if self.support is None:
            return SENSOR_NOISE * distance
        return self.support.noise_at(distance)
