"""What a file or body gives the engine: points, and, for an organized frame (a depth image,
a PCD or NPY of height > 1), where each came from in its pixel grid.

A missing pixel of an organized frame (NaN or infinity in a cloud file, 0 in a depth image)
is skipped, never an error: only the valid points are counted against the limits."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.engine.icp import cross_matrices
from service.errors import InvalidPoints


@dataclass(frozen=True)
class Cloud:
    points: np.ndarray  # (N, 3), not yet validated
    index: np.ndarray | None = None  # (N,) each point's pixel, row * width + column
    shape: tuple[int, int] | None = None  # (height, width) of the grid it came from


def organized(grid: np.ndarray, max_points: int, what: str) -> Cloud:
    """The valid pixels of an (H, W, 3) grid of points, counted against ``max_points``: a
    pixel whose point is NaN, infinite or exactly (0, 0, 0) has none. A camera measures no
    point at its own centre; RealSense's SDK, and drivers after it, write a pixel without a
    depth so (docs/decisions.md#a-pixel-at-the-cameras-centre)."""
    height, width = grid.shape[:2]
    flat = grid.reshape(-1, 3)
    # column by column: .all(axis=1) over rows of 3 is 8x slower
    x, y, z = flat[:, 0], flat[:, 1], flat[:, 2]
    kept = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
    kept &= (x != 0) | (y != 0) | (z != 0)
    valid = np.flatnonzero(kept)
    if not len(valid):
        raise InvalidPoints(
            f"the {what} ({width}x{height} pixels) has no valid point: every pixel is NaN, "
            "infinite or (0, 0, 0), where its camera saw nothing; check that the camera sees "
            "the scene"
        )
    if len(valid) > max_points:
        raise InvalidPoints(
            f"the {what} has {len(valid)} valid points, more than the maximum of {max_points}: "
            "crop or decimate it (every other row and column), or send POST /detect a region "
            "of interest (roi): only the points inside it count then"
        )
    return Cloud(np.take(flat, valid, axis=0), valid.astype(np.int64), (height, width))


CENTRE_SAMPLE = 1024  # pixels the camera's centre is solved on
RAY_TOLERANCE_RAD = 1e-3  # every sampled point within this of its pixel's ray (99th percentile)
DEGENERATE = 1e-6  # the next solution this close to the best: the pixels do not pin the centre
AT_ORIGIN = 1e-4  # a centre this near the origin, in the points' ranges, is the origin


def camera_centre(cloud: Cloud) -> np.ndarray | None:
    """Where the camera of an organized frame was, in the frame's own coordinates: the point
    every pixel's ray passes through, or None where the points do not lie on a pinhole's rays
    (not a camera's frame) or do not pin it down (a single plane). A camera driver's frame
    gives the origin; the same frame carried into a robot's base frame gives the camera there.

    Each point ``p`` lies on its pixel's ray: ``(p - c) x (M q) = 0`` with ``q = (u, v, 1)``
    and ``M`` the camera's inverse intrinsics turned into the frame. Writing ``N = [c]x M``
    makes it linear in ``M`` and ``N`` (``p x M q - N q = 0``), solved by SVD; ``c`` is then
    the skew part of ``N M^-1`` (docs/decisions.md#the-camera-of-an-organized-frame)."""
    if cloud.shape is None or cloud.index is None or len(cloud.points) < 32:
        return None
    count = len(cloud.points)
    pick = np.random.default_rng(0).choice(count, min(CENTRE_SAMPLE, count), replace=False)
    points = np.asarray(cloud.points[pick], np.float64)
    rows, columns = np.divmod(cloud.index[pick], cloud.shape[1])
    if np.ptp(rows) < 2 or np.ptp(columns) < 2:
        return None
    # conditioned: pixels and points centred and scaled to about one
    pixels = np.stack([columns, rows], axis=1).astype(np.float64)
    pixel_mean, pixel_scale = pixels.mean(axis=0), max(float(pixels.std()), 1e-12)
    q = np.column_stack([(pixels - pixel_mean) / pixel_scale, np.ones(len(points))])
    point_mean, point_scale = points.mean(axis=0), max(float(points.std()), 1e-12)
    p = (points - point_mean) / point_scale
    # p x (M q) - N q = 0: three rows a point, unknowns vec(M) then vec(N) (row-major)
    rows_m = np.einsum("nik,nj->nikj", cross_matrices(p), q).reshape(len(p), 3, 9)  # [p]x M q
    rows_n = -np.einsum("ik,nj->nikj", np.eye(3), q).reshape(len(p), 3, 9)  # - N q
    system = np.concatenate([rows_m, rows_n], axis=2).reshape(-1, 18)
    _, singular, vt = np.linalg.svd(system, full_matrices=False)
    if singular[-2] < DEGENERATE * singular[0] or singular[-1] > 1e-3 * singular[-2]:
        return None  # a second solution (a plane), or none fits
    m, n = vt[-1, :9].reshape(3, 3), vt[-1, 9:].reshape(3, 3)
    if abs(np.linalg.det(m)) < 1e-12:
        return None
    skew = n @ np.linalg.inv(m)
    centre = np.array([skew[2, 1] - skew[1, 2], skew[0, 2] - skew[2, 0], skew[1, 0] - skew[0, 1]])
    centre /= 2
    rays = q @ m.T
    sight = p - centre
    rays *= np.sign(np.median(np.einsum("ij,ij->i", rays, sight)))
    cosine = np.einsum("ij,ij->i", rays, sight) / (
        np.linalg.norm(rays, axis=1) * np.linalg.norm(sight, axis=1) + 1e-300
    )
    off = np.arccos(np.clip(cosine, -1.0, 1.0))
    if np.quantile(off, 0.99) > RAY_TOLERANCE_RAD:
        return None
    centre = centre * point_scale + point_mean
    # a driver's own frame: the origin itself, not its float32 rounding (a depth image is read
    # only from a camera at the origin: projection.DepthImage)
    near = AT_ORIGIN * float(np.median(np.linalg.norm(points, axis=1)))
    return np.zeros(3) if np.linalg.norm(centre) <= near else centre
