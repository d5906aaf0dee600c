"""What a robot cell's depth camera sends, built from a mesh at a known pose.

- ``sensor_view``: the part alone in front of the camera (docs/evaluation-protocol.md, ``sensor``);
- ``table_scene``: the part resting on a table that the same camera sees obliquely, cropped
  around the part, with stray points (``table``);
- ``junk_cloud``: clouds of no part at all (``junk``);
- ``symmetry_axis``: the axis a symmetric part turns about without changing its surface
  (``symmetric``).

Every pose is ``scene = R @ model + t`` into the camera frame (the camera at the origin,
looking along +z, see ``evaluation.camera``), so the viewpoint of every view is [0, 0, 0].
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from evaluation.camera import (
    DEFAULT_CAMERA,
    DEPTH_NOISE_SHARE,
    Camera,
    SensorProfile,
    cast,
    cast_profiled,
)
from service.engine.normalize import radius
from service.engine.sampling import sample_surface

VIEWPOINT = (0.0, 0.0, 0.0)  # the camera's position in its own frame
TABLE_ELEVATION_DEG = (30.0, 60.0)  # table: the camera looks down at this angle to the table
TABLE_HALF_SIDE_SCALES = 3.0  # table: a square this many scales each side of the part
BIN_HALF_SCALES = 1.6  # a bin's walls stand this many scales each side of its part
CROP_SCALES = 2.5  # table: keep what lies within this many scales of the part's centre
STRAY_SHARE = 0.02  # table: stray points, as a share of the cropped cloud
STRAY_MARGIN_SCALES = 1.0  # ... uniform in the cloud's bounding box grown by this many scales
JUNK_KINDS = ("box-noise", "gaussian-blob", "sphere-shell", "flat-patch")

# Sources of a table scene's points (TableScene.source).
PART, TABLE, STRAY = 0, 1, 2


@dataclass
class SensorView:
    """One depth camera's view of a part: ``points`` = R @ (seen model surface) + t + noise."""

    points: np.ndarray  # (M, 3) float32, camera frame, shuffled
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    viewpoint: np.ndarray  # (3,) where the camera is: the origin
    pixel: tuple[float, float]  # where the part's centre appears in the image


@dataclass
class TableScene(SensorView):
    """A sensor view of the part on its table, cropped around it, plus stray points."""

    source: np.ndarray | None = None  # (M,) PART, TABLE or STRAY for each point
    plane: np.ndarray | None = None  # (4,) the table n·x + d = 0, camera frame, n toward it


def surface_centroid(mesh: trimesh.Trimesh) -> np.ndarray:
    """The area-weighted mean of the surface: where a surface sample's centroid tends to."""
    weights = np.asarray(mesh.area_faces, dtype=np.float64)
    return (np.asarray(mesh.triangles_center) * weights[:, None]).sum(axis=0) / weights.sum()


def surface_covariance(mesh: trimesh.Trimesh) -> np.ndarray:
    """(3, 3) the covariance of the surface about ``surface_centroid``, integrated exactly over
    the triangles: over a triangle (a, b, c) of area A, x x^T integrates to
    A / 12 (a a^T + b b^T + c c^T + s s^T) with s = a + b + c."""
    triangles = np.asarray(mesh.triangles, dtype=np.float64) - surface_centroid(mesh)
    areas = np.asarray(mesh.area_faces, dtype=np.float64)
    summed = triangles.sum(axis=1)
    second = np.einsum("fvi,fvj->fij", triangles, triangles) + np.einsum(
        "fi,fj->fij", summed, summed
    )
    return np.einsum("f,fij->ij", areas / 12, second) / areas.sum()


def placed(mesh: trimesh.Trimesh, rotation: np.ndarray, translation: np.ndarray):
    """A copy of ``mesh`` moved to ``R @ v + t``."""
    vertices = np.asarray(mesh.vertices, np.float64) @ np.asarray(rotation).T + translation
    return trimesh.Trimesh(vertices, np.asarray(mesh.faces), process=False)


def _shuffled(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return np.ascontiguousarray(points[rng.permutation(len(points))], dtype=np.float32)


def sensor_view(
    mesh: trimesh.Trimesh,
    rotation: np.ndarray,
    distance: float,
    rng: np.random.Generator,
    pixel: tuple[float, float] | None = None,
    camera: Camera = DEFAULT_CAMERA,
    noise_share: float = DEPTH_NOISE_SHARE,
) -> SensorView:
    """The part turned by ``rotation``, its surface centroid ``distance`` from the camera on
    the ray through ``pixel`` (default: uniform in the middle half of the image), seen by
    ``camera``: one point per hit pixel, depth noise σ = ``noise_share`` × the distance along
    each ray, shuffled. ``distance`` is in the mesh's units (the family takes 4-8 scales)."""
    pixel = camera.middle_half_pixel(rng) if pixel is None else pixel
    rotation = np.asarray(rotation, dtype=np.float64)
    centre = distance * camera.ray(*pixel)
    translation = centre - rotation @ surface_centroid(mesh)
    seen = cast([placed(mesh, rotation, translation)], rng, camera, noise_share)
    points = _shuffled(seen.points, rng)
    return SensorView(points, rotation, translation, np.array(VIEWPOINT), tuple(pixel))


# --- the table -------------------------------------------------------------------------------


def stable_poses(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """trimesh's stable resting poses (4×4 transforms onto the plane z = 0) and their
    probabilities, the centre of mass taken as the surface centroid (the meshes are shells)."""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        transforms, probabilities = trimesh.poses.compute_stable_poses(
            mesh, center_mass=surface_centroid(mesh)
        )
    return np.asarray(transforms), np.asarray(probabilities)


def resting_pose(
    mesh: trimesh.Trimesh, poses: tuple[np.ndarray, np.ndarray], rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """A stable pose drawn by its probability, spun about the table's normal (z) at random,
    lowest vertex on z = 0, surface centroid above the origin: (rotation, translation) from
    the model frame to the table frame."""
    transforms, probabilities = poses
    chosen = transforms[rng.choice(len(transforms), p=probabilities / probabilities.sum())]
    spin = Rotation.from_rotvec([0.0, 0.0, rng.uniform(0, 2 * np.pi)]).as_matrix()
    rotation = spin @ chosen[:3, :3]
    lowest = (np.asarray(mesh.vertices, np.float64) @ rotation.T)[:, 2].min()
    above = rotation @ surface_centroid(mesh)
    return rotation, np.array([-above[0], -above[1], -lowest])


def look_at(target: np.ndarray, azimuth: float, elevation: float, distance: float):
    """The camera pose in a z-up frame: at ``distance`` from ``target``, ``elevation`` above
    the horizon, looking at it with the image's y axis down. Returns (R, c) such that a point
    x of that frame is R @ (x - c) in the camera frame."""
    direction = np.array(
        [
            np.cos(elevation) * np.cos(azimuth),
            np.cos(elevation) * np.sin(azimuth),
            np.sin(elevation),
        ]
    )
    position = target + distance * direction
    forward = -direction
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return np.stack([right, down, forward]), position


def _towards_pixel(camera: Camera, pixel: tuple[float, float]) -> np.ndarray:
    """The rotation about the camera that takes the optical axis to the ray through ``pixel``."""
    rotation, _ = Rotation.align_vectors([camera.ray(*pixel)], [[0.0, 0.0, 1.0]])
    return rotation.as_matrix()


def table_scene(
    mesh: trimesh.Trimesh,
    scale: float,
    rng: np.random.Generator,
    poses: tuple[np.ndarray, np.ndarray] | None = None,
    camera: Camera = DEFAULT_CAMERA,
    distance_scales: tuple[float, float] = (4.0, 8.0),
    noise_share: float = DEPTH_NOISE_SHARE,
    profile: SensorProfile | None = None,
    walls: float = 0.0,
) -> TableScene:
    """The part resting on a table in a stable pose (``poses``: ``stable_poses(mesh)``,
    computed when None), seen by ``camera`` from 4-8 scales away, looking down at 30-60° to
    the table, the part's centre anywhere in the middle half of the image. Both the part and
    the table are ray cast; the cloud is cropped to ``CROP_SCALES`` scales around the part's
    centre, and ``STRAY_SHARE`` of stray points are added in its bounding box grown by
    ``STRAY_MARGIN_SCALES`` scales; then shuffled. ``scale`` is the part's (its reference's
    radius). With a ``profile``, the camera is that profile's (``noise_share`` unused); with
    ``walls``, the part lies in a bin: four walls that many scales high, ``BIN_HALF_SCALES``
    each side of it."""
    poses = stable_poses(mesh) if poses is None else poses
    rest_rotation, rest_translation = resting_pose(mesh, poses, rng)
    centre_on_table = rest_rotation @ surface_centroid(mesh) + rest_translation
    elevation = np.radians(rng.uniform(*TABLE_ELEVATION_DEG))
    distance = rng.uniform(*distance_scales) * scale
    to_camera, position = look_at(centre_on_table, rng.uniform(0, 2 * np.pi), elevation, distance)
    pixel = camera.middle_half_pixel(rng)
    to_camera = _towards_pixel(camera, pixel) @ to_camera  # the part off the image's centre
    rotation = to_camera @ rest_rotation
    translation = to_camera @ (rest_translation - position)

    half = TABLE_HALF_SIDE_SCALES * scale
    table = trimesh.creation.box((2 * half, 2 * half, 1e-3 * scale))
    table.apply_translation([centre_on_table[0], centre_on_table[1], -0.5e-3 * scale])
    supports = [table] + bin_walls(centre_on_table, scale, walls)
    supports = [placed(support, to_camera, -to_camera @ position) for support in supports]
    meshes = [placed(mesh, rotation, translation), *supports]
    if profile is None:
        seen = cast(meshes, rng, camera, noise_share)
    else:
        seen = cast_profiled(meshes, rng, profile, camera)

    centre = rotation @ surface_centroid(mesh) + translation
    near = np.linalg.norm(seen.points - centre, axis=1) <= CROP_SCALES * scale
    points, source = seen.points[near], np.where(seen.mesh_index[near] == 0, PART, TABLE)
    strays = int(round(STRAY_SHARE * len(points)))
    low = points.min(axis=0) - STRAY_MARGIN_SCALES * scale
    high = points.max(axis=0) + STRAY_MARGIN_SCALES * scale
    points = np.vstack([points, rng.uniform(low, high, size=(strays, 3))])
    source = np.concatenate([source, np.full(strays, STRAY)])
    order = rng.permutation(len(points))
    normal = to_camera[:, 2]  # the table's +z (toward the camera) in the camera frame
    plane = np.append(normal, -normal @ (-to_camera @ position))
    return TableScene(
        np.ascontiguousarray(points[order], dtype=np.float32),
        rotation,
        translation,
        np.array(VIEWPOINT),
        tuple(pixel),
        source=source[order],
        plane=plane,
    )


def bin_walls(centre: np.ndarray, scale: float, height_scales: float) -> list[trimesh.Trimesh]:
    """Four walls ``height_scales`` scales high round ``centre`` on the table (z = 0), each
    ``BIN_HALF_SCALES`` scales from it; none for a height of 0."""
    if height_scales <= 0:
        return []
    half, height, thick = BIN_HALF_SCALES * scale, height_scales * scale, 0.05 * scale
    walls = []
    for axis, side in ((0, -1), (0, 1), (1, -1), (1, 1)):
        extents = [2 * half, 2 * half, height]
        extents[axis] = thick
        wall = trimesh.creation.box(extents)
        offset = np.array([centre[0], centre[1], height / 2])
        offset[axis] += side * half
        wall.apply_translation(offset)
        walls.append(wall)
    return walls


# --- no part at all --------------------------------------------------------------------------


def junk_cloud(kind: str, size: float, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` points of no part, about ``size`` in radius, centred on the origin:
    uniform noise in a box, a Gaussian blob, a sphere shell or a flat patch (a square of
    table seen from above, slightly rough)."""
    if kind == "box-noise":
        points = rng.uniform(-1.0, 1.0, size=(count, 3)) * size / np.sqrt(3)
    elif kind == "gaussian-blob":
        points = rng.normal(scale=size / 2.5, size=(count, 3))
    elif kind == "sphere-shell":
        directions = rng.normal(size=(count, 3))
        points = size * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    elif kind == "flat-patch":
        points = rng.uniform(-1.0, 1.0, size=(count, 3)) * size / np.sqrt(2)
        points[:, 2] = rng.normal(scale=0.005 * size, size=count)
    else:
        raise ValueError(f"unknown junk kind {kind!r}; pick one of {JUNK_KINDS}")
    return points


# --- symmetry --------------------------------------------------------------------------------


OFF_SURFACE = 0.03  # share of the radius: beyond a faceted mesh's sag, within a notch's depth


def surface_gap(points: np.ndarray, other: np.ndarray) -> float:
    """Mean distance from each of ``points`` to the nearest of ``other``: 0 for the same
    surface (up to the sampling's spacing)."""
    distances, _ = cKDTree(np.asarray(other, np.float64)).query(np.asarray(points, np.float64))
    return float(distances.mean())


def turned_off_surface(
    mesh: trimesh.Trimesh, axis: np.ndarray, angles: Sequence[float], samples: int = 4096
) -> np.ndarray:
    """For each turn by one of ``angles`` (radians) about ``axis`` (through the surface
    centroid), the share of the part's surface it moves farther than ``OFF_SURFACE`` of the
    part's radius from the surface (a dense resample): about 0 for a symmetry, a few percent
    for a notch or a cross hole that the turn moves, which a mean distance (``surface_gap``)
    hardly sees."""
    points = sample_surface(mesh, samples, 1).astype(np.float64)
    tree = cKDTree(sample_surface(mesh, 50 * samples, 2).astype(np.float64))
    centre, scale = surface_centroid(mesh), radius(points)
    shares = []
    for angle in angles:
        rotation, shift = turn_about(axis, angle, centre)
        distances, _ = tree.query(points @ rotation.T + shift)
        shares.append(np.mean(distances > OFF_SURFACE * scale))
    return np.array(shares)


def symmetry_axis(mesh: trimesh.Trimesh, order: int, samples: int = 4096) -> np.ndarray:
    """The principal axis about which a part is symmetric: the unit axis (model frame, through
    the surface centroid) whose turn by 360°/``order`` (``order`` 0: a revolution, tried at
    90°) changes the sampled surface least. A symmetry's axis is a principal axis of the
    surface, exactly: the axes are the mesh's own (``surface_covariance``), not a sample's,
    whose axes were 0.9° off the lego brick's, so that its quarter turns showed another
    surface by up to 1.8° and the answers' spread measured that too."""
    points = sample_surface(mesh, samples, 1).astype(np.float64)
    other = sample_surface(mesh, samples, 2).astype(np.float64)
    centre = surface_centroid(mesh)
    _, axes = np.linalg.eigh(surface_covariance(mesh))
    angle = 2 * np.pi / order if order else np.pi / 2

    def gap(axis: np.ndarray) -> float:
        turn = Rotation.from_rotvec(angle * axis).as_matrix()
        return surface_gap((points - centre) @ turn.T + centre, other)

    return min(axes.T, key=gap)


def turn_about(axis: np.ndarray, angle: float, centre: np.ndarray):
    """The rigid motion (R, t) that turns by ``angle`` (radians) about the line through
    ``centre`` along ``axis``."""
    rotation = Rotation.from_rotvec(angle * np.asarray(axis, np.float64)).as_matrix()
    return rotation, centre - rotation @ centre
