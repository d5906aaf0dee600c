"""The innermost loops compiled (numba, the ``fast`` extra): refinement's, verification's,
and a frame's first steps.

ICP and verification ask the same few numpy steps thousands of times a frame on a few hundred
points, where each step's call costs as much as its arithmetic; a frame's first steps read its
300,000 points in a dozen passes each. Here each is one loop over the points, compiled once
(cached on disk) and run without the interpreter: a frame's ICP 5.5x faster, to the same poses
within 1e-7 and the same iterations; ``Engine.detect`` half the time, with the same detections
(docs/decisions.md#compiled-loops). Each does its numpy twin's arithmetic, and
``tests/engine/test_kernels.py`` holds the two together:

- ``refine`` is one start of ``icp.icp``: the distance field's answer while far, the nearest
  of the sample's neighbours not facing away from the camera once close, Tukey-weighted
  point-to-plane steps;
- ``distances`` is ``verification.surface_distance``: the field's, the nearest or the facing
  sample, and the distance to its tangent patch;
- ``shares`` and ``covered`` are ``verification.fit`` and ``verification.coverage``, each
  pose's points carried one at a time;
- ``squared_distances`` and ``pair_cosines``: a frame's ranges and the cosines its pixel angle
  is the median of, the same to the bit;
- ``msac_votes``: the supports' RANSAC votes, in float64 where numpy's are float32 (the same
  plane chosen);
- ``grid_labels``: an organized frame's segments, its neighbouring pixels linked and joined.

The helpers are compiled into the loops that call them, and each loop unpacks a surface's
arrays once: an array taken from a tuple a point is reference-counted a point.

Without numba (``pip install .`` without ``[fast]``), or with ``DPC_ENGINE__COMPILED=false``,
the numpy code runs instead.
"""

from __future__ import annotations

import math

import numpy as np

try:  # the fast extra
    from numba import __version__ as NUMBA_VERSION
    from numba import njit
except ImportError:  # the numpy twins run instead
    NUMBA_VERSION, njit = None, None

AVAILABLE = njit is not None
FIELD, NEAREST, FACING = 0, 1, 2  # ``distances``'s lookups, as verification.Lookup
NO_CAMERA = np.zeros(3)  # the camera where none is told (``refine``'s)


class _Switch:
    """Whether the compiled loops run: where numba is installed, unless the settings say not."""

    enabled = AVAILABLE


switch = _Switch()


def use(enabled: bool) -> bool:
    """Run the compiled loops (where numba is installed) or the numpy ones; what runs now."""
    switch.enabled = bool(enabled) and AVAILABLE
    return switch.enabled


def takes(points: np.ndarray) -> bool:
    """Whether a compiled loop runs on ``points``: switched on, and C-ordered float64 (the
    loops over a frame's points, ``squared_distances`` and ``pair_cosines``)."""
    return switch.enabled and points.dtype == np.float64 and points.flags.c_contiguous


def describe() -> str:
    """Which loops run, for the start's log."""
    if switch.enabled:
        return f"compiled loops (numba {NUMBA_VERSION})"
    if AVAILABLE:
        return "numpy loops (DPC_ENGINE__COMPILED=false)"
    return (
        "numpy loops (numba is not installed: with pip install '.[fast]', /detect takes "
        "half the time)"
    )


def warm() -> None:
    """Compile every loop for the types the engine passes (seconds, once per install: numba
    caches them on disk; then a fraction of a second), so that no request waits for it."""
    if not switch.enabled:
        return
    turns = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)  # a ring of 16 samples
    points = np.stack([np.cos(turns), np.sin(turns), np.zeros_like(turns)], axis=1)
    rows = np.arange(16)
    neighbours = np.stack([rows, (rows + 1) % 16, (rows - 1) % 16], axis=1).astype(np.int64)
    squares, offsets = np.ones(16), np.zeros(16)
    field = (np.full(3, -1.5), 0.5, np.array([7, 7, 7], np.int64), np.zeros(343, np.uint16))
    surface = (*field, points, points.copy(), neighbours, squares, offsets)
    pose = (np.eye(3), np.zeros(3))
    tuned = (0.2, 0.5, 0.01, 4.685, 1e-6)  # as icp.TUNED
    for told in (False, True):
        refine(points, *pose, 0.01, 0.5, 2, 5e-4, 0.05, told, np.ones(3), surface, tuned)
    poses = (np.eye(3)[None], np.zeros((1, 3)))
    for lookup in (FIELD, NEAREST, FACING):
        distances(points, lookup, surface, 0.1, 0.1)
        shares(points, *poses, 0.1, lookup, surface, 0.1, 0.1)
    grid = np.ones(27, bool)
    covered(points[None], *poses, np.zeros(3), 1.0, np.array([2, 2, 2]), np.array([9, 3, 1]), grid)
    pixels, steps = np.arange(16), np.array([[0, 1], [1, 0]], np.intp)  # a 4 x 4 grid
    grid_labels(pixels // 4, pixels % 4, pixels, 4, 4, points, squares, offsets, steps, squares[:2])
    msac_votes(points, points, squares, squares)
    squared_distances(points, np.zeros(3))
    pair_cosines(points, rows[:4], np.zeros(3))


def _inline(function):
    """A helper compiled into each loop that calls it. Its arrays come unpacked from the
    surface's tuple once a loop: an array taken from a tuple a point costs its reference
    counting a point, six times the arithmetic (docs/decisions.md#compiled-loops)."""
    if not AVAILABLE:
        return function
    return njit(nogil=True, inline="always")(function)


def _compiled(function):
    """``function`` compiled on its first call and cached on disk (in ``__pycache__``, or
    ``NUMBA_CACHE_DIR``); where no cache can be written, compiled anew in each process."""
    if not AVAILABLE:
        return function
    try:
        return njit(cache=True, nogil=True)(function)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return njit(nogil=True)(function)


@_inline
def _field(x, y, z, origin, voxel, shape, cells):
    """The distance field's sample for one point (``DistanceField.lookup``): the voxel's
    rounded index, clipped onto the grid (NaN to voxel 0); the field's arrays are the first
    four of ``Surface.compiled``."""
    i = np.rint((x - origin[0]) / voxel)
    j = np.rint((y - origin[1]) / voxel)
    k = np.rint((z - origin[2]) / voxel)
    i = 0.0 if not i >= 0.0 else min(i, shape[0] - 1.0)
    j = 0.0 if not j >= 0.0 else min(j, shape[1] - 1.0)
    k = 0.0 if not k >= 0.0 else min(k, shape[2] - 1.0)
    return cells[int(i * (shape[1] * shape[2]) + j * shape[2] + k)]


@_compiled
def _median(values, count):
    """The median of ``values[:count]`` (reordered in place): Hoare's selection, for the
    middle one or the middle two (np.median's own costs seconds of compiling)."""
    half = count // 2
    low, high = 0, count - 1
    while low < high:  # values[half] becomes what sorting would put there
        pivot = values[(low + high) // 2]
        i, j = low, high
        while i <= j:
            while values[i] < pivot:
                i += 1
            while values[j] > pivot:
                j -= 1
            if i <= j:
                values[i], values[j] = values[j], values[i]
                i, j = i + 1, j - 1
        if half <= j:
            high = j
        elif half >= i:
            low = i
        else:
            break
    middle = values[half]
    if count % 2:
        return middle
    below = values[0]  # the largest of those before it: the one sorting would put before
    for i in range(1, half):
        below = max(below, values[i])
    return 0.5 * (below + middle)


@_compiled
def _solve(system, right):
    """``system`` x = ``right`` for a 6 x 6 system, by Gaussian elimination with partial
    pivoting, as LAPACK's ``gesv`` (``np.linalg.solve``'s own costs seconds of compiling);
    both arrays are overwritten."""
    size = len(right)
    for col in range(size):
        pivot = col
        for row in range(col + 1, size):
            if abs(system[row, col]) > abs(system[pivot, col]):
                pivot = row
        if pivot != col:
            for k in range(size):
                system[col, k], system[pivot, k] = system[pivot, k], system[col, k]
            right[col], right[pivot] = right[pivot], right[col]
        for row in range(col + 1, size):
            factor = system[row, col] / system[col, col]
            for k in range(col + 1, size):
                system[row, k] -= factor * system[col, k]
            right[row] -= factor * right[col]
    for row in range(size - 1, -1, -1):
        total = right[row]
        for k in range(row + 1, size):
            total -= system[row, k] * right[k]
        right[row] = total / system[row, row]
    return right


@_inline
def _order(x, y, z, c, points, squares):
    """What ``Surface.nearest`` orders sample ``c`` by for the point: |q|^2 - 2 p.q."""
    square = squares[c] + points[c, 0] * (-2.0 * x)
    square = square + points[c, 1] * (-2.0 * y)
    return square + points[c, 2] * (-2.0 * z)


@_inline
def _nearest(
    x, y, z, first, points, normals, neighbours, squares, offsets, has_camera, camera, sq, back
):
    """``Surface.nearest`` for one point: the nearest of ``first``'s neighbours, ordered by
    |q|^2 - 2 p.q as there; told the camera (``sq``: its |c|^2), the nearest of those not
    facing away from it by more than ``back`` (the nearest of all where every one does)."""
    best, best_square, any_best, any_square = -1, np.inf, -1, np.inf
    for n in range(neighbours.shape[1]):
        c = neighbours[first, n]
        square = _order(x, y, z, c, points, squares)
        if square < any_square:
            any_best, any_square = c, square
        if has_camera:
            toward = camera[0] * normals[c, 0] + camera[1] * normals[c, 1]
            toward = toward + camera[2] * normals[c, 2] - offsets[c]
            sight = camera[0] * points[c, 0] + camera[1] * points[c, 1]
            sight = (sight + camera[2] * points[c, 2]) * -2.0 + squares[c] + sq
            if toward < -back * math.sqrt(max(sight, 0.0)):
                continue
        if square < best_square:
            best, best_square = c, square
    return best if best >= 0 else any_best


@_compiled
def refine(
    scene,
    rotation,
    translation,
    noise,
    gate,
    iterations,
    tolerance_rad,
    tolerance,
    has_camera,
    viewpoint,
    surface,
    tuned,
):
    """One start of ``icp.icp``: the refined rotation, translation and the iterations run.
    ``surface``: ``Surface.compiled``; ``tuned``: ``icp.TUNED``, the loop's constants."""
    origin, voxel, shape, cells, points, normals, neighbours, squares, offsets = surface
    back_facing, close, close_rad, tukey, damping = tuned
    count = scene.shape[0]
    rotation, translation = rotation.copy(), translation.copy()
    model = np.empty((count, 3))
    residual, size, rows = np.empty(count), np.empty(count), np.empty((count, 6))
    camera = np.zeros(3)
    camera_square = 0.0
    done, precise, gate_square = 0, False, gate * gate
    for iteration in range(1, iterations + 1):
        done = iteration
        for i in range(count):  # (q - t) @ R
            d0, d1, d2 = (
                scene[i, 0] - translation[0],
                scene[i, 1] - translation[1],
                scene[i, 2] - translation[2],
            )
            for a in range(3):
                model[i, a] = d0 * rotation[0, a] + d1 * rotation[1, a] + d2 * rotation[2, a]
        told = precise and has_camera
        if told:
            v0, v1, v2 = (
                viewpoint[0] - translation[0],
                viewpoint[1] - translation[1],
                viewpoint[2] - translation[2],
            )
            for a in range(3):
                camera[a] = v0 * rotation[0, a] + v1 * rotation[1, a] + v2 * rotation[2, a]
            camera_square = camera[0] * camera[0] + camera[1] * camera[1] + camera[2] * camera[2]
        kept = 0
        for i in range(count):
            x, y, z = model[i, 0], model[i, 1], model[i, 2]
            c = _field(x, y, z, origin, voxel, shape, cells)
            if precise:
                c = _nearest(
                    x,
                    y,
                    z,
                    c,
                    points,
                    normals,
                    neighbours,
                    squares,
                    offsets,
                    told,
                    camera,
                    camera_square,
                    back_facing,
                )
            o0, o1, o2 = x - points[c, 0], y - points[c, 1], z - points[c, 2]
            if o0 * o0 + o1 * o1 + o2 * o2 < gate_square:
                n0, n1, n2 = normals[c, 0], normals[c, 1], normals[c, 2]
                residual[kept] = o0 * n0 + o1 * n1 + o2 * n2
                size[kept] = abs(residual[kept])
                rows[kept, 0], rows[kept, 1], rows[kept, 2] = (
                    y * n2 - z * n1,
                    z * n0 - x * n2,
                    x * n1 - y * n0,
                )
                rows[kept, 3], rows[kept, 4], rows[kept, 5] = n0, n1, n2
                kept += 1
        if kept < 6:
            break
        scale = tukey * max(1.4826 * _median(size, kept), noise)
        system, right = np.zeros((6, 6)), np.zeros(6)
        for j in range(kept):
            u = residual[j] / scale
            if abs(u) < 1.0:
                weight = (1.0 - u * u) ** 2
                for a in range(6):
                    weighted = weight * rows[j, a]
                    right[a] += weighted * residual[j]
                    for b in range(6):
                        system[a, b] += weighted * rows[j, b]
        damped = damping * (
            system[0, 0] + system[1, 1] + system[2, 2] + system[3, 3] + system[4, 4] + system[5, 5]
        )
        for a in range(6):
            system[a, a] += damped + 1e-12
        step = -_solve(system, right)
        turned = math.sqrt(step[0] * step[0] + step[1] * step[1] + step[2] * step[2])
        turn = np.eye(3)  # Rodrigues, as icp.rotation_vector
        if turned >= 1e-12:
            x, y, z = step[0] / turned, step[1] / turned, step[2] / turned
            s, c = math.sin(turned), math.cos(turned)
            t = 1.0 - c
            turn[0, 0], turn[0, 1], turn[0, 2] = c + t * x * x, t * x * y - s * z, t * x * z + s * y
            turn[1, 0], turn[1, 1], turn[1, 2] = t * x * y + s * z, c + t * y * y, t * y * z - s * x
            turn[2, 0], turn[2, 1], turn[2, 2] = t * x * z - s * y, t * y * z + s * x, c + t * z * z
        turned_to = np.empty((3, 3))  # R @ C^T
        for a in range(3):
            for b in range(3):
                turned_to[a, b] = (
                    rotation[a, 0] * turn[b, 0]
                    + rotation[a, 1] * turn[b, 1]
                    + rotation[a, 2] * turn[b, 2]
                )
        rotation = turned_to
        for a in range(3):
            translation[a] -= (
                rotation[a, 0] * step[3] + rotation[a, 1] * step[4] + rotation[a, 2] * step[5]
            )
        moved = math.sqrt(step[3] * step[3] + step[4] * step[4] + step[5] * step[5])
        if turned < close_rad and moved < close * noise:
            if precise and turned < tolerance_rad and moved < tolerance * noise:
                break
            precise = True
    return rotation, translation, done


@_inline
def _nearest_of(x, y, z, first, points, neighbours, squares):
    """``Surface.nearest`` for one point, not told the camera: the nearest of ``first``'s
    neighbours, ordered by |q|^2 - 2 p.q as there: ``_nearest`` untold, in three arguments."""
    best, best_square = -1, np.inf
    for n in range(neighbours.shape[1]):
        c = neighbours[first, n]
        square = _order(x, y, z, c, points, squares)
        if square < best_square:
            best, best_square = c, square
    return best


@_inline
def _facing(x, y, z, first, points, normals, neighbours, behind):
    """The nearest of ``first``'s neighbours the point is not ``behind`` (the nearest if
    behind them all)."""
    best, best_square, any_best, any_square = -1, np.inf, -1, np.inf
    for n in range(neighbours.shape[1]):
        k = neighbours[first, n]
        o0, o1, o2 = x - points[k, 0], y - points[k, 1], z - points[k, 2]
        square = o0 * o0 + o1 * o1 + o2 * o2
        if square < any_square:
            any_best, any_square = k, square
        if o0 * normals[k, 0] + o1 * normals[k, 1] + o2 * normals[k, 2] < -behind:
            continue
        if square < best_square:
            best, best_square = k, square
    return best if best >= 0 else any_best


@_inline
def _patch(x, y, z, c, points, normals, patch):
    """One point's distance to sample ``c``'s tangent patch (``patch_distance``)."""
    o0, o1, o2 = x - points[c, 0], y - points[c, 1], z - points[c, 2]
    along = o0 * normals[c, 0] + o1 * normals[c, 1] + o2 * normals[c, 2]
    across = math.sqrt(max(o0 * o0 + o1 * o1 + o2 * o2 - along * along, 0.0))
    return math.sqrt(along * along + max(across - patch, 0.0) ** 2)


@_compiled
def distances(model, lookup, surface, behind, patch):
    """``verification.surface_distance`` on ``model`` (P, 3): each point's distance to the
    tangent patch of its sample (``FIELD``, ``NEAREST`` or ``FACING``), and the sample."""
    origin, voxel, shape, cells, points, normals, neighbours, squares, offsets = surface
    count = model.shape[0]
    distance, sample = np.empty(count), np.empty(count, np.int64)
    for i in range(count):
        x, y, z = model[i, 0], model[i, 1], model[i, 2]
        c = _field(x, y, z, origin, voxel, shape, cells)
        if lookup == NEAREST:
            c = _nearest_of(x, y, z, c, points, neighbours, squares)
        elif lookup == FACING:
            c = _facing(x, y, z, c, points, normals, neighbours, behind)
        distance[i] = _patch(x, y, z, c, points, normals, patch)
        sample[i] = c
    return distance, sample


@_compiled
def shares(observed, rotations, translations, tolerance, lookup, surface, behind, patch):
    """``verification.fit``: (H,) the share of ``observed`` (S, 3) within ``tolerance`` of the
    surface at each pose, the points carried into the model frame one at a time."""
    origin, voxel, shape, cells, points, normals, neighbours, squares, offsets = surface
    out = np.empty(len(rotations))
    for h in range(len(rotations)):
        r, t = rotations[h], translations[h]
        within = 0
        for i in range(observed.shape[0]):
            d0, d1 = observed[i, 0] - t[0], observed[i, 1] - t[1]
            d2 = observed[i, 2] - t[2]
            x = d0 * r[0, 0] + d1 * r[1, 0] + d2 * r[2, 0]
            y = d0 * r[0, 1] + d1 * r[1, 1] + d2 * r[2, 1]
            z = d0 * r[0, 2] + d1 * r[1, 2] + d2 * r[2, 2]
            c = _field(x, y, z, origin, voxel, shape, cells)
            if lookup == NEAREST:
                c = _nearest_of(x, y, z, c, points, neighbours, squares)
            elif lookup == FACING:
                c = _facing(x, y, z, c, points, normals, neighbours, behind)
            if _patch(x, y, z, c, points, normals, patch) < tolerance:
                within += 1
        out[h] = within / observed.shape[0]
    return out


@_compiled
def covered(expected, rotations, translations, low, voxel, last, strides, grid):
    """``verification.coverage``: (H,) the share of each pose's ``expected`` points (H, M, 3),
    placed by it, whose voxel of the occupancy ``grid`` (flat) is near an observed point."""
    out = np.empty(len(rotations))
    for h in range(len(rotations)):
        r, t = rotations[h], translations[h]
        near = 0
        for i in range(expected.shape[1]):
            m0, m1, m2 = expected[h, i, 0], expected[h, i, 1], expected[h, i, 2]
            flat = 0
            for a in range(3):  # the point placed, R m + t, then its voxel, clipped
                placed = m0 * r[a, 0] + m1 * r[a, 1] + m2 * r[a, 2] + t[a]
                cell = min(max(math.floor((placed - low[a]) / voxel), 0), last[a])
                flat += cell * strides[a]
            near += grid[flat]
        out[h] = near / expected.shape[1]
    return out


@_inline
def _root(parent, node):
    """The root of ``node``'s tree, halving the path on the way."""
    while parent[node] != node:
        parent[node] = parent[parent[node]]
        node = parent[node]
    return node


@_compiled
def grid_labels(rows, columns, where, width, height, points, reach, slack, offsets, apart):
    """``segments.grid_segments``: (N,) a component label per point of an organized frame,
    each linked to its neighbour at each of ``offsets`` (K, 2: down, right; ``apart``: their
    lengths in pixels) closer than ``reach`` x ``apart`` plus ``slack`` (each point's); the
    labels numbered in the order of each component's first point, as scipy's. ``where``: the
    point on each pixel of the grid (``height`` x ``width``, flat), -1 where none is."""
    count = len(rows)
    parent = np.arange(count)
    for i in range(count):
        row, column = rows[i], columns[i]
        for k in range(offsets.shape[0]):
            down, right = offsets[k, 0], offsets[k, 1]
            if row + down >= height or column + right >= width or column + right < 0:
                continue
            other = where[(row + down) * width + column + right]
            if other < 0:
                continue
            d0 = points[i, 0] - points[other, 0]
            d1 = points[i, 1] - points[other, 1]
            d2 = points[i, 2] - points[other, 2]
            gap = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)  # as normalize.lengths
            if gap < reach[i] * apart[k] + slack[i]:
                a, b = _root(parent, i), _root(parent, other)
                if a != b:
                    parent[max(a, b)] = min(a, b)
    labels = np.full(count, -1, np.int32)
    found = 0
    for i in range(count):
        root = _root(parent, i)
        if labels[root] < 0:
            labels[root] = found
            found += 1
        labels[i] = labels[root]
    return labels


@_compiled
def msac_votes(sample, normals, offsets, slack):
    """``supports.msac_votes``: (P,) each plane's MSAC vote over the ``sample`` (S, 3), each
    point's 1 - (|n . p - d| / its ``slack``)^2, at least 0. The planes innermost, each its
    own sum: a loop the compiler runs several planes at a time, without a branch."""
    planes = normals.shape[0]
    n0, n1, n2 = normals[:, 0].copy(), normals[:, 1].copy(), normals[:, 2].copy()
    votes = np.zeros(planes)
    for i in range(sample.shape[0]):
        x, y, z, scale = sample[i, 0], sample[i, 1], sample[i, 2], 1.0 / slack[i]
        for j in range(planes):
            u = (x * n0[j] + y * n1[j] + z * n2[j] - offsets[j]) * scale
            votes[j] += max(1.0 - u * u, 0.0)
    return votes


@_compiled
def squared_distances(points, centre):
    """``normalize.squared_distances`` of C-ordered float64 ``points``: in one pass, the same
    sums in the same order."""
    out = np.empty(points.shape[0])
    c0, c1, c2 = centre[0], centre[1], centre[2]
    for i in range(points.shape[0]):
        x, y, z = points[i, 0] - c0, points[i, 1] - c1, points[i, 2] - c2
        out[i] = x * x + y * y + z * z
    return out


@_compiled
def pair_cosines(points, first, viewpoint):
    """``frame.pair_angles``' cosines: (K,) the cosine between the rays from ``viewpoint`` to the
    points ``first`` and ``first + 1``, each made a unit vector; NaN where a point lies at the
    viewpoint. The same to the bit: summed in einsum's order."""
    out = np.empty(first.shape[0])
    v0, v1, v2 = viewpoint[0], viewpoint[1], viewpoint[2]
    for k in range(first.shape[0]):
        a, b = first[k], first[k] + 1
        a0, a1, a2 = points[a, 0] - v0, points[a, 1] - v1, points[a, 2] - v2
        b0, b1, b2 = points[b, 0] - v0, points[b, 1] - v1, points[b, 2] - v2
        na = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        nb = np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
        a0, a1, a2, b0, b1, b2 = a0 / na, a1 / na, a2 / na, b0 / nb, b1 / nb, b2 / nb
        out[k] = (a0 * b0 + a2 * b2) + a1 * b1
    return out
