"""Step 7, refine: a pose refined with robust point-to-plane ICP on the reference's distance field.

Each iteration carries the observed points into the model frame, looks up the nearest reference
point and its normal in the distance field (O(1), no tree), and solves the linearised
point-to-plane problem: the small rotation ``w`` and translation ``d`` that minimise
``sum_i rho(n_i . (m_i + w x m_i + d - q_i))``. The robust kernel rho is Tukey's biweight with a
scale taken from the residuals' median absolute deviation (floored by ``noise``), so points that
the reference does not explain (clutter, another part, the wrong side) weigh nothing; pairs
farther than ``gate`` from their nearest point are left out at once. Iteratively reweighted
least squares; a little damping keeps the 6x6 system solvable on planes and cylinders, whose
sliding directions the data do not fix. Stops when the update turns by less than
``tolerance_rad`` and moves by less than ``tolerance`` times ``noise``.

Told where the camera was (``viewpoint``), the pairs of the last, precise iterations leave out
reference samples that face away from it: a depth camera sees no surface that turns its back
to it, but across a thin wall the nearest sample is as often the far side's
(docs/decisions.md#refine).

Where numba is installed, each start runs as one compiled loop of the same arithmetic
(``kernels.refine``; docs/decisions.md#compiled-loops); the numpy loops below run otherwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from service.engine import kernels
from service.engine.alignment import to_model_frame
from service.engine.distance_field import DistanceField
from service.engine.tuning import BACK_FACING, BEHIND, CLOSE, CLOSE_RAD, SURFACE_NEIGHBOURS

TUKEY = 4.685  # Tukey's constant: 95 % efficiency on Gaussian residuals
DAMPING = 1e-6  # relative to the system's trace
# what the compiled loop is told of these (numba's cache would not see them change elsewhere)
TUNED = (BACK_FACING, CLOSE, CLOSE_RAD, TUKEY, DAMPING)
DIAGONAL = np.arange(6)
# the cross-product matrix's entries: K[r, c] = sign * k[axis]
CROSS_ROWS, CROSS_COLS = np.array([0, 0, 1, 1, 2, 2]), np.array([1, 2, 0, 2, 0, 1])
CROSS_AXES, CROSS_SIGNS = np.array([2, 1, 2, 0, 1, 0]), np.array([-1.0, 1, 1, -1, -1, 1])


@dataclass(frozen=True)
class Surface:
    """A reference's surface as refinement and verification see it."""

    points: np.ndarray  # (N, 3) float64, model frame
    normals: np.ndarray  # (N, 3) unit, outward
    field: DistanceField
    neighbours: np.ndarray  # (N, k) each point's nearest others (itself first)
    spacing: float  # the median distance from a sample to its nearest other

    @classmethod
    def of(
        cls, points: np.ndarray, normals: np.ndarray, field: DistanceField, tree: cKDTree
    ) -> Surface:
        # a cloud of fewer points than SURFACE_NEIGHBOURS has that many neighbours a point (the tree
        # would name a missing one by an index past the end)
        count = min(SURFACE_NEIGHBOURS, len(points))
        distances, neighbours = tree.query(points, k=list(range(1, count + 1)))
        spacing = float(np.median(distances[:, 1]))
        return cls(points, normals, field, neighbours.astype(np.intp), spacing)

    def nearest(
        self, points: np.ndarray, facing: bool = False, camera: np.ndarray | None = None
    ) -> np.ndarray:
        """Index of the surface sample nearest each of ``points`` (..., 3): the distance
        field's answer, corrected among that sample's neighbours. The field names the sample
        nearest the voxel's centre, which may be a voxel away from the point's own nearest;
        that one is almost always among its neighbours.

        With ``facing``, the nearest of those the point lies in front of (not more than
        ``BEHIND`` spacings behind its tangent plane; the nearest where it is behind them
        all). A point is seen on the outside of its surface; across a thin wall (a hollow
        brick's, a cup's) the nearest sample is often on the far side, a wall's thickness
        from the point's own plane, with the point behind it. Measured at the true pose, 7-8 %
        of a hollow brick's full-cloud points lay beyond the tolerance from their nearest
        sample's tangent patch, 4-5 % from the facing one's.

        With ``camera`` (a point in the model frame; or (S, 3), one each of the S leading rows
        of ``points``), the nearest of those that do not face away from it (``BACK_FACING``;
        the nearest where they all do)."""
        # take: a third of indexing's time here (docs/decisions.md#refinements-together); the
        # array's own method, without np.take's wrapper (a microsecond a call)
        candidates = self.neighbours.take(self.field.lookup(points), axis=0)  # (..., k)
        if facing:
            offsets = points[..., None, :] - self.points.take(candidates, axis=0)
            square = np.einsum("...ki,...ki->...k", offsets, offsets)
            along = np.einsum("...ki,...ki->...k", offsets, self.normals.take(candidates, axis=0))
            behind = along < -BEHIND * self.spacing
            square[behind & ~behind.all(axis=-1, keepdims=True)] = np.inf
        else:  # |q|^2 - 2 p.q orders them as |p - q|^2 does: no (..., k, 3) arrays, 0.4x time
            square = self._squares.take(candidates)
            twice = -2.0 * points
            for axis in range(3):  # a column's view: take reads it as fast as a copy
                term = self.points[:, axis].take(candidates)
                term *= twice[..., axis, None]
                square += term
        if camera is not None:
            away = self.facing_away(np.asarray(camera, np.float64))
            if away.ndim == 1:
                away = away.take(candidates)
            else:  # a camera each of the leading rows of ``points``: row h's at h * N
                rows = np.arange(0, away.size, away.shape[1])
                away = away.take(candidates + rows.reshape(-1, *([1] * (candidates.ndim - 1))))
            square[away & ~away.all(axis=-1, keepdims=True)] = np.inf
        best = np.argmin(square, axis=-1)
        count = candidates.shape[-1]  # each point's pick, by its flat index: no index grids
        picked = candidates.take(np.arange(0, candidates.size, count) + best.ravel())
        return picked.reshape(best.shape)

    @cached_property
    def compiled(self) -> tuple:
        """The surface as ``kernels`` take it: the field's origin, voxel, shape and flat cells,
        the samples, their normals, neighbours, squared lengths and planes' offsets."""
        field = self.field
        return (
            field.origin,
            field.voxel,
            np.array(field.nearest.shape, np.int64),
            np.ascontiguousarray(field.nearest).reshape(-1),
            np.ascontiguousarray(self.points, np.float64),
            np.ascontiguousarray(self.normals, np.float64),
            np.ascontiguousarray(self.neighbours, np.int64),
            self._squares,
            self._offsets,
        )

    @cached_property
    def _squares(self) -> np.ndarray:
        """(N,) each sample's squared distance from the origin (``nearest``)."""
        return np.einsum("ni,ni->n", self.points, self.points)

    @cached_property
    def _offsets(self) -> np.ndarray:
        """(N,) each sample's tangent plane's offset, p . n (``facing_away``)."""
        return np.einsum("ni,ni->n", self.points, self.normals)

    def facing_away(self, camera: np.ndarray) -> np.ndarray:
        """(..., N) whether each sample faces away from ``camera`` (..., 3), model frame
        (``BACK_FACING``): the same for every point paired with it, so asked once a sample."""
        # (c - p).n and |c - p|^2 from products with the samples: no (..., N, 3) arrays
        toward = camera @ self.normals.T - self._offsets
        square = (camera @ self.points.T) * -2.0
        square += self._squares
        square += np.einsum("...i,...i->...", camera, camera)[..., None]
        return toward < -BACK_FACING * np.sqrt(np.maximum(square, 0.0, out=square), out=square)


def rotation_vector(w: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation by ``|w|`` about ``w``."""
    x, y, z = (float(v) for v in w)
    angle = math.sqrt(x * x + y * y + z * z)
    if angle < 1e-12:
        return np.eye(3)
    x, y, z = x / angle, y / angle, z / angle
    s, c = math.sin(angle), math.cos(angle)
    t = 1.0 - c  # I + sin K + (1 - cos) K^2, K^2 = k k^T - I, written out: a 3x3 from floats
    return np.array(
        [
            [c + t * x * x, t * x * y - s * z, t * x * z + s * y],
            [t * x * y + s * z, c + t * y * y, t * y * z - s * x],
            [t * x * z - s * y, t * y * z + s * x, c + t * z * z],
        ]
    )


@dataclass(frozen=True)
class Start:
    """One pose to refine (``icp_many``): where it starts, on which surface, how."""

    surface: Surface
    rotation: np.ndarray
    translation: np.ndarray
    noise: float  # the smallest residual scale the kernel assumes (the sensor's noise)
    gate: float  # the largest point-to-point distance of a pair used at all
    iterations: int = 20
    viewpoint: np.ndarray | None = None  # where the camera was (scene frame), if known

    @classmethod
    def at_tolerance(
        cls,
        surface: Surface,
        rotation: np.ndarray,
        translation: np.ndarray,
        tolerance: float,
        iterations: int,
        viewpoint: np.ndarray | None,
    ) -> Start:
        """The chain's refinement of a pose, at a part's fit ``tolerance``: the sensor's noise
        a quarter of it, pairs within five of it."""
        return cls(
            surface, rotation, translation, 0.25 * tolerance, 5 * tolerance, iterations, viewpoint
        )


def icp(
    scene: np.ndarray,
    surface: Surface,
    rotation: np.ndarray,
    translation: np.ndarray,
    noise: float,
    gate: float,
    iterations: int = 20,
    tolerance_rad: float = 5e-4,
    tolerance: float = 0.05,
    viewpoint: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The pose ``scene = R @ model + t`` refined from the given one, and the iterations run.

    ``noise`` is the smallest residual scale the kernel assumes (the sensor's noise), ``gate``
    the largest point-to-point distance of a pair that is used at all, ``viewpoint`` where the
    camera was (scene frame), if known.
    """
    rotation, translation = np.asarray(rotation, np.float64), np.asarray(translation, np.float64)
    if kernels.switch.enabled:
        start = Start(surface, rotation, translation, noise, gate, iterations, viewpoint)
        return _compiled(np.ascontiguousarray(scene, np.float64), start, tolerance_rad, tolerance)
    done, precise = 0, False
    for iteration in range(1, iterations + 1):
        done = iteration
        model = to_model_frame(scene, rotation, translation)
        # the distance field's own answer while far; corrected among neighbours once close
        if precise:
            camera = None if viewpoint is None else (viewpoint - translation) @ rotation
            nearest = surface.nearest(model, camera=camera)
        else:
            nearest = surface.field.lookup(model)
        offset = model - surface.points.take(nearest, axis=0)
        normals = surface.normals.take(nearest, axis=0)
        near = np.einsum("ij,ij->i", offset, offset) < gate**2
        kept = np.count_nonzero(near)
        if kept < 6:
            break
        if kept < len(near):  # most iterations keep every pair: no copies then
            model, offset, normals = model[near], offset[near], normals[near]
        residual = np.einsum("ij,ij->i", offset, normals)
        spread = max(1.4826 * _median(np.abs(residual)), noise)
        u = residual / (TUKEY * spread)
        weight = np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)
        jacobian = _jacobian(model, normals)  # (M, 6)
        weighted = jacobian * weight[:, None]
        system = weighted.T @ jacobian
        system[DIAGONAL, DIAGONAL] += DAMPING * system.trace() + 1e-12
        step = -np.linalg.solve(system, weighted.T @ residual)
        correction = rotation_vector(step[:3])  # model points m -> C m + d
        rotation = rotation @ correction.T
        translation = translation - rotation @ step[3:]
        turned, moved = math.sqrt(step[:3] @ step[:3]), math.sqrt(step[3:] @ step[3:])
        if turned < CLOSE_RAD and moved < CLOSE * noise:
            if precise and turned < tolerance_rad and moved < tolerance * noise:
                break
            precise = True
    return rotation, translation, done


def icp_many(
    scene: np.ndarray,
    starts: list[Start],
    tolerance_rad: float = 5e-4,
    tolerance: float = 0.05,
) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """Each start's pose refined on the same ``scene`` points (M, 3), or each on its own
    (H, M, 3), all in one loop: each runs its own iterations and stops by its own test, as
    ``icp`` alone would, and gets the same pose to rounding; the arithmetic of an iteration
    is done for all at once, which on a few hundred points costs little more than for one
    (docs/decisions.md#refinements-together).
    Each start's refined rotation, translation and the iterations it ran. One start is
    refined by ``icp``: its arrays of one pose cost less than the stacks' of one."""
    scene = np.asarray(scene, np.float64)
    if kernels.switch.enabled:  # each start in one compiled loop (decisions.md#compiled-loops)
        scene = np.ascontiguousarray(scene)
        return [
            _compiled(scene if scene.ndim == 2 else scene[h], s, tolerance_rad, tolerance)
            for h, s in enumerate(starts)
        ]
    if len(starts) == 1:
        (s,) = starts
        return [
            icp(
                scene if scene.ndim == 2 else scene[0],
                s.surface,
                s.rotation,
                s.translation,
                s.noise,
                s.gate,
                s.iterations,
                tolerance_rad,
                tolerance,
                s.viewpoint,
            )
        ]
    out: list = [None] * len(starts)
    # the running starts' state, compacted as they stop
    ids = np.arange(len(starts))
    rotation = np.array([s.rotation for s in starts], np.float64).reshape(-1, 3, 3)
    translation = np.array([s.translation for s in starts], np.float64).reshape(-1, 3)
    noise = np.array([s.noise for s in starts], np.float64)
    gate = np.array([s.gate for s in starts], np.float64) ** 2
    budget = np.array([s.iterations for s in starts], int)
    precise = np.zeros(len(starts), bool)
    iteration = 0
    while len(ids):
        stop = budget <= iteration  # its iterations ran out (none given: where it started)
        if not stop.any():
            iteration += 1
            model = np.matmul(scene - translation[:, None], rotation)
            paired, normals = _pairs(starts, ids, model, precise, rotation, translation)
            offset = model - paired
            near = np.einsum("hij,hij->hi", offset, offset) < gate[:, None]
            counts = near.sum(axis=1)
            # too few pairs: it stops where it is
            stop = counts < 6
            if not stop.all():
                # the running starts with pairs enough (a view of all while none has stopped)
                live = slice(None) if not stop.any() else ~stop
                offset, normals, model, near = offset[live], normals[live], model[live], near[live]
                residual = np.einsum("hij,hij->hi", offset, normals)
                spread = np.maximum(1.4826 * _medians(np.abs(residual), near), noise[live])
                u = residual / (TUKEY * spread[:, None])
                kept = np.abs(u) < 1
                weight = np.where(kept if near.all() else kept & near, (1 - u**2) ** 2, 0.0)
                jacobian = _jacobian(model, normals)  # (H, M, 6)
                weighted = (jacobian * weight[..., None]).transpose(0, 2, 1)
                system = weighted @ jacobian
                trace = np.trace(system, axis1=1, axis2=2)
                system[:, DIAGONAL, DIAGONAL] += (DAMPING * trace + 1e-12)[:, None]
                step = -np.linalg.solve(system, weighted @ residual[..., None])[..., 0]
                # model points m -> C m + d
                correction = _rodrigues(step[:, :3])
                turned_to = rotation[live] @ correction.transpose(0, 2, 1)
                rotation[live] = turned_to
                translation[live] -= (turned_to @ step[:, 3:, None])[..., 0]
                turned = np.sqrt(np.einsum("hi,hi->h", step[:, :3], step[:, :3]))
                moved = np.sqrt(np.einsum("hi,hi->h", step[:, 3:], step[:, 3:]))
                close = (turned < CLOSE_RAD) & (moved < CLOSE * noise[live])
                settled = close & precise[live] & (turned < tolerance_rad)
                stop[live] = settled & (moved < tolerance * noise[live])
                precise[live] |= close
        if stop.any():
            for h in np.flatnonzero(stop):
                out[ids[h]] = (rotation[h], translation[h], iteration)
            keep = ~stop
            ids, rotation, translation = ids[keep], rotation[keep], translation[keep]
            noise, gate, budget, precise = noise[keep], gate[keep], budget[keep], precise[keep]
            scene = scene if scene.ndim == 2 else scene[keep]
    return out


def _compiled(
    scene: np.ndarray, start: Start, tolerance_rad: float, tolerance: float
) -> tuple[np.ndarray, np.ndarray, int]:
    """One start refined by ``kernels.refine`` on ``scene`` (M, 3), C-ordered float64."""
    told = start.viewpoint is not None
    rotation, translation, done = kernels.refine(
        scene,
        np.ascontiguousarray(start.rotation, np.float64),
        np.ascontiguousarray(start.translation, np.float64),
        float(start.noise),
        float(start.gate),
        int(start.iterations),
        tolerance_rad,
        tolerance,
        told,
        np.ascontiguousarray(start.viewpoint, np.float64) if told else kernels.NO_CAMERA,
        start.surface.compiled,
        TUNED,
    )
    return rotation, translation, done


def _pairs(
    starts: list[Start],
    active: np.ndarray,
    model: np.ndarray,
    precise: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """(H, M, 3) the surface sample each model point pairs with, and its normal: the distance
    field's own answer while far; corrected among neighbours (facing the camera) once close.
    The starts on one surface alike are looked up together."""
    groups: dict[tuple, list[int]] = {}
    for slot, h in enumerate(active):
        key = (id(starts[h].surface), bool(precise[slot]), starts[h].viewpoint is None)
        groups.setdefault(key, []).append(slot)
    if len(groups) == 1:  # no copies: one pose, or the turns of one
        (slots,) = groups.values()
        return _nearest(starts, active, slots, model, precise, rotation, translation)
    paired, normals = np.empty_like(model), np.empty_like(model)
    for slots in groups.values():
        paired[slots], normals[slots] = _nearest(
            starts, active, slots, model[slots], precise, rotation, translation
        )
    return paired, normals


def _nearest(
    starts: list[Start],
    active: np.ndarray,
    slots: list[int],
    model: np.ndarray,
    precise: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The samples, and their normals, that ``model`` (S, M, 3), the points of the running
    ``slots`` of one surface, pair with (``_pairs``)."""
    start = starts[active[slots[0]]]
    surface = start.surface
    if not precise[slots[0]]:
        nearest = surface.field.lookup(model)
    elif start.viewpoint is None:
        nearest = surface.nearest(model)
    else:
        viewpoints = np.array([starts[active[slot]].viewpoint for slot in slots])
        toward = viewpoints - translation[slots]
        cameras = np.einsum("hi,hij->hj", toward, rotation[slots])  # (v - t) @ R, each
        nearest = surface.nearest(model, camera=cameras)
    return surface.points.take(nearest, axis=0), surface.normals.take(nearest, axis=0)


def _rodrigues(w: np.ndarray) -> np.ndarray:
    """(H, 3, 3) the rotations by ``|w|`` about each of ``w`` (H, 3): cos I + sin K + (1 - cos)
    k k^T, K the cross-product matrix of the unit axis k (``rotation_vector`` for many)."""
    angle = np.sqrt(np.einsum("hi,hi->h", w, w))
    k = w / np.where(angle < 1e-12, 1.0, angle)[:, None]  # no turn: k ~ 0, the identity
    c, s = np.cos(angle), np.sin(angle)
    t = 1.0 - c
    x, y, z = k.T
    turns = np.empty((len(w), 3, 3))  # written out entry by entry, as ``rotation_vector``
    turns[:, 0, 0], turns[:, 1, 1], turns[:, 2, 2] = c + t * x * x, c + t * y * y, c + t * z * z
    xy, xz, yz = t * x * y, t * x * z, t * y * z
    turns[:, 0, 1], turns[:, 1, 0] = xy - s * z, xy + s * z
    turns[:, 0, 2], turns[:, 2, 0] = xz + s * y, xz - s * y
    turns[:, 1, 2], turns[:, 2, 1] = yz - s * x, yz + s * x
    return turns


def cross_matrices(vectors: np.ndarray) -> np.ndarray:
    """(N, 3, 3) the cross-product matrix ``[v]x`` of each of ``vectors`` (N, 3):
    ``[v]x u = v x u``."""
    cross = np.zeros((len(vectors), 3, 3))
    cross[:, CROSS_ROWS, CROSS_COLS] = vectors[:, CROSS_AXES] * CROSS_SIGNS
    return cross


def _jacobian(model: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(..., M, 6): each pair's [m x n, n], the derivative of its point-to-plane residual by
    the small rotation and the translation (written out: np.cross costs more than the loop's
    arithmetic on a few hundred points)."""
    jacobian = np.empty((*model.shape[:-1], 6))
    mx, my, mz = model[..., 0], model[..., 1], model[..., 2]
    nx, ny, nz = normals[..., 0], normals[..., 1], normals[..., 2]
    jacobian[..., 0] = my * nz - mz * ny
    jacobian[..., 1] = mz * nx - mx * nz
    jacobian[..., 2] = mx * ny - my * nx
    jacobian[..., 3:] = normals
    return jacobian


def _medians(values: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """(H,) the median of each row of ``values`` (H, M) over its ``kept`` entries (at least
    six a row): those sorted first, the rest pushed past them."""
    half = values.shape[1] // 2
    if kept.all():  # the common case: one partition for all rows
        kth = [half - 1, half] if values.shape[1] % 2 == 0 else [half]
        part = np.partition(values, kth, axis=1)
        return part[:, half] if len(kth) == 1 else 0.5 * (part[:, half - 1] + part[:, half])
    ordered = np.sort(np.where(kept, values, np.inf), axis=1)
    counts = kept.sum(axis=1)
    rows = np.arange(len(values))
    upper = ordered[rows, counts // 2]
    lower = ordered[rows, (counts - 1) // 2]
    return np.where(counts % 2, upper, 0.5 * (lower + upper))


def _median(values: np.ndarray) -> float:
    """The median of a 1-D array (np.median's checks cost more than the partition)."""
    half = len(values) // 2
    part = np.partition(values, [half - 1, half] if len(values) % 2 == 0 else half)
    return float(part[half] if len(values) % 2 else 0.5 * (part[half - 1] + part[half]))
