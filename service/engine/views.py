"""Single-camera views of a reference, rendered at registration.

A depth camera sees one side of a part. To recognise and pose such a view, the engine keeps,
for each of ``count`` camera directions spread evenly over the sphere (a Fibonacci lattice),
which reference points that camera sees, and what recognition and pose need of them: their
centroid, principal frame and radius, and the classifier's features of their grid (eq. 4 then
learns a part's views rather than only its full shape).

The camera of a view sits ``CAMERA_DISTANCE`` scales from the centroid, in the middle of a
cell camera's working range (4 to 8 scales, docs/evaluation-protocol.md). Which points it sees:
- for an uploaded mesh, a depth buffer of a dense sample of its surface (each pixel keeps its
  nearest surface sample; a reference point is seen if it is no deeper than that sample, plus a
  tolerance): a point-based rendering of the mesh itself;
- for an uploaded cloud, the same depth buffer of the cloud itself, its pixels sized by the
  cloud's own spacing (``CLOUD_SPACINGS`` times the median distance between neighbours).
  Measured on the 9 unseen parts registered as 2,048-point clouds, 36 depth-camera views:
  hidden-point removal (``service.engine.visibility``) gave 80.6 % success, the depth buffer at
  1.5, 2, 2.5, 3 and 4 times the median spacing 86.1, 91.7, 100, 97.2 and 88.9 % (registered as
  meshes: 97.2 %). Too fine a buffer lets the far side show through its holes, too coarse a
  one hides what the camera sees.

A cloud's view then keeps, of what its buffer lets through, the points that face its camera:
whose outward normal is within about 73 degrees of the direction to it (cosine ``FACING``).
A depth camera has one point per pixel, so it samples a surface ever more thinly as the
surface turns away, and a buffer of a 2,048-point cloud lets points through at grazing angles
and past the silhouette (28 % of a cloud's view, against the same part's mesh view). Coverage
then asks for points the camera hardly samples, and the view's grid and frame are not what
the camera shows. Measured on the 9 unseen parts registered as clouds (``engine_settings
--registered cloud``), depth views with their viewpoint: right 100 / 97.2 %, precise 86.1 /
97.2 %, answered "match" and right 50 / 83.3 % (without / with; cosines 0, 0.15, 0.3, 0.45:
63.9, 69.4, 83.3, 80.6 % "match"), views of parts on a table 55.6 / 88.9 % "match"; seen
parts' views on a table lost three cases to those parts (97.8 / 94.4 %, each answered
"uncertain"). A mesh's views stay as they are: its dense buffer shows what the camera
samples, and keeping them to what faces the camera too lost full clouds (paper-poses 100 ->
98.9 %) and partial views (97.8 -> 94.8 %) of the seen parts.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from service.engine.normalize import MIN_RELATIVE_RADIUS
from service.engine.principal_axes import principal_axes
from service.engine.tuning import (  # docs/decisions.md#rendered-views
    CAMERA_DISTANCE,
    CLOUD_SPACINGS,
    DEPTH_SPACINGS,
    FACING,
    MAX_BUFFER,
    PIXEL_SPACINGS,
)


def directions(count: int) -> np.ndarray:
    """(count, 3) unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    index = np.arange(count) + 0.5
    z = 1 - 2 * index / count
    azimuth = np.pi * (1 + 5**0.5) * index
    ring = np.sqrt(1 - z**2)
    return np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z], axis=1)


def camera_basis(direction: np.ndarray) -> np.ndarray:
    """(3, 3) rows u, v, d: an orthonormal frame whose third axis is ``direction``."""
    d = direction / np.linalg.norm(direction)
    helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(helper, d)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(d, u), d])


def splat_visible(
    points: np.ndarray,
    surface: np.ndarray,
    camera: np.ndarray,
    spacing: float,
    target: np.ndarray | None = None,
) -> np.ndarray:
    """Which ``points`` a pinhole camera at ``camera`` sees over the dense ``surface`` sample
    (spacing: the sample's typical distance between neighbours; ``target``: the sample's
    centroid, where the camera looks, if the caller has it)."""
    target = surface.mean(axis=0) if target is None else target
    basis = camera_basis(camera - target)
    pixel = PIXEL_SPACINGS * spacing / np.linalg.norm(camera - target)

    def project(cloud: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        relative = (cloud - camera) @ basis.T  # camera looks along -d
        depth = -relative[:, 2]
        toward = np.maximum(depth, 1e-12)
        across, up = (np.floor(relative[:, k] / toward / pixel).astype(np.int64) for k in (0, 1))
        return across, up, depth

    *surface_pixels, surface_depth = project(surface)
    *point_pixels, point_depth = project(points)
    front = _nearest_in_pixel(*surface_pixels, surface_depth, *point_pixels)
    return point_depth <= front + DEPTH_SPACINGS * spacing


def _nearest_in_pixel(
    across: np.ndarray, up: np.ndarray, depth: np.ndarray, at_x: np.ndarray, at_y: np.ndarray
) -> np.ndarray:
    """For each pixel (``at_x``, ``at_y``), the least ``depth`` of the samples in it (the
    samples' pixels: ``across``, ``up``); infinity where there is none. A dense buffer over the
    samples' pixels (a minimum is exact: the same answer as sorting them, several times faster:
    docs/operations.md, "Registration time"), or, where that image would be huge, the packed
    pixels sorted."""
    x0, y0 = across.min(), up.min()
    width, height = int(across.max() - x0 + 1), int(up.max() - y0 + 1)
    if width * height > MAX_BUFFER:
        return _nearest_sorted(across, up, depth, at_x, at_y)
    buffer = np.full(width * height, np.inf)
    np.minimum.at(buffer, (across - x0) * height + (up - y0), depth)
    x, y = at_x - x0, at_y - y0
    inside = (x >= 0) & (x < width) & (y >= 0) & (y < height)
    front = np.full(len(at_x), np.inf)
    front[inside] = buffer[x[inside] * height + y[inside]]
    return front


def _nearest_sorted(
    across: np.ndarray, up: np.ndarray, depth: np.ndarray, at_x: np.ndarray, at_y: np.ndarray
) -> np.ndarray:
    surface_keys = (across << 32) + (up & 0xFFFFFFFF)
    point_keys = (at_x << 32) + (at_y & 0xFFFFFFFF)
    order = np.lexsort((depth, surface_keys))
    keys, first = np.unique(surface_keys[order], return_index=True)
    nearest = depth[order][first]  # per pixel: the nearest surface sample's depth
    slot = np.clip(np.searchsorted(keys, point_keys), 0, len(keys) - 1)
    covered = keys[slot] == point_keys
    return np.where(covered, nearest[slot], np.inf)


def cloud_spacing(points: np.ndarray, tree: cKDTree | None = None) -> float:
    """A cloud's spacing for its own depth buffer: ``CLOUD_SPACINGS`` times the median
    distance from a point to its nearest neighbour (a few points: any positive length;
    ``tree``: a ``cKDTree`` of ``points``, if one is at hand). At least ``MIN_RELATIVE_RADIUS``
    of the cloud's extent: where most points coincide the median is 0, and the buffer's
    pixels, a spacing wide, would number past what its 64-bit keys hold."""
    if len(points) < 2:
        return 1.0
    distance, _ = (tree or cKDTree(points)).query(points, k=2)
    least = MIN_RELATIVE_RADIUS * float(np.ptp(points, axis=0).max())
    return max(CLOUD_SPACINGS * float(np.median(distance[:, 1])), least, 1e-12)


def sample_spacing(points: np.ndarray, area: float) -> float:
    """The typical distance between neighbouring samples of a surface of ``area``."""
    return float(np.sqrt(area / max(len(points), 1)))


def render(
    points: np.ndarray,
    scale: float,
    count: int,
    surface: np.ndarray | None = None,
    area: float | None = None,
    tree: cKDTree | None = None,
) -> np.ndarray:
    """(count, N) which reference points each view's camera sees: against ``surface`` (a dense
    sample of the uploaded mesh, whose ``area`` is known) when given, else against the points
    themselves (``tree``: a ``cKDTree`` of them, if one is at hand)."""
    points = np.asarray(points, dtype=np.float64)
    if surface is None:
        surface, spacing = points, cloud_spacing(points, tree)
    else:
        spacing = sample_spacing(surface, area)
    placed, target = cameras(points, scale, count), surface.mean(axis=0)
    return np.stack([splat_visible(points, surface, c, spacing, target) for c in placed])


def camera_at(centroid: np.ndarray, direction: np.ndarray, scale: float) -> np.ndarray:
    """Where a camera looking along ``-direction`` (unit, one or (K, 3)) at a part of this
    ``scale`` sits: ``CAMERA_DISTANCE`` scales from its ``centroid``."""
    return centroid + direction * CAMERA_DISTANCE * scale


def cameras(points: np.ndarray, scale: float, count: int) -> np.ndarray:
    """(count, 3) where each view's camera sits: ``CAMERA_DISTANCE`` scales from the centroid
    of ``points`` (float64), along ``directions(count)``."""
    return camera_at(points.mean(axis=0), directions(count), scale)


def facing(
    points: np.ndarray, normals: np.ndarray, scale: float, count: int, cosine: float = FACING
) -> np.ndarray:
    """(count, N) which points face each view's camera: the cosine between their outward
    ``normals`` and the direction to the camera (placed as ``render`` places it) is above
    ``cosine``."""
    points = np.asarray(points, dtype=np.float64)
    toward = cameras(points, scale, count)[:, None, :] - points[None]  # (count, N, 3)
    along = np.einsum("kni,ni->kn", toward, np.asarray(normals, dtype=np.float64))
    return along > cosine * np.linalg.norm(toward, axis=2)


@dataclass(frozen=True)
class Views:
    """What recognition and pose need of a reference's single-camera views."""

    directions: np.ndarray  # (K, 3) from the reference's centroid towards each camera
    visible: np.ndarray  # (K, N) bool: the points each camera sees
    centroids: np.ndarray  # (K, 3) of the visible points
    frames: np.ndarray  # (K, 3, 3) their principal axes (columns), largest variance first
    radii: np.ndarray  # (K,) largest distance from the centroid to a visible point

    @classmethod
    def of(cls, points: np.ndarray, visible: np.ndarray) -> Views:
        points = np.asarray(points, dtype=np.float64)
        count = len(visible)
        centroids, frames, radii = np.zeros((count, 3)), np.zeros((count, 3, 3)), np.zeros(count)
        for k, seen in enumerate(visible):
            chosen = points[seen] if seen.sum() >= 3 else points
            centroids[k] = chosen.mean(axis=0)
            frames[k] = principal_axes(chosen - centroids[k])
            radii[k] = np.sqrt(((chosen - centroids[k]) ** 2).sum(axis=1).max())
        return cls(directions(count), visible, centroids, frames, radii)

    @cached_property
    def bases(self) -> np.ndarray:
        """(K, 3, 3) each view's camera frame: rows u, v and its direction (``camera_basis``)."""
        return np.stack([camera_basis(d) for d in self.directions])

    def nearest(self, toward: np.ndarray) -> np.ndarray:
        """(H,) the view whose camera direction is nearest each of ``toward`` (H, 3), camera
        directions in the model frame (not necessarily unit)."""
        return np.argmax(toward @ self.directions.T, axis=1)

    def turned(self, view: int, turns: np.ndarray) -> list[int]:
        """The view a pose turned by each of ``turns`` (K, 3, 3, in the model frame) expects
        to be seen from, where the unturned pose expects ``view`` (-1: the whole part): the
        camera's direction in the model frame turns the other way (N^T d)."""
        if view < 0:
            return [view] * len(turns)
        return self.nearest(np.einsum("nji,j->ni", turns, self.directions[view])).tolist()
