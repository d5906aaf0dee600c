"""Whole camera frames for the tests: parts placed by hand on a table or in a bin, ray cast
(Open3D, the eval extra) by a pinhole camera at the origin looking along +z, one point per
pixel, NaN where no ray hits, as an organized frame's driver writes it.

Poses are ``scene = R @ model + t`` in the camera frame; a part's model frame is its mesh's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from evaluation.camera import cast_rays
from evaluation.scenes import look_at
from service.api.clouds import organized
from service.engine.frame import Frame

VGA = (640, 480, 525.0)  # width, height, focal length in pixels


@dataclass
class Shot:
    """A rendered frame: its points per pixel and what each pixel shows."""

    points: np.ndarray  # (H, W, 3) float32, NaN where no depth
    shows: np.ndarray  # (H, W) int: the placed part's index, -1 for the supports or nothing
    poses: list[tuple[np.ndarray, np.ndarray]]  # each placed part's (R, t), camera frame
    camera: tuple[int, int, float]

    @property
    def intrinsics(self) -> dict[str, float]:
        width, height, focal = self.camera
        return {"fx": focal, "fy": focal, "cx": (width - 1) / 2, "cy": (height - 1) / 2}

    def depth_png(self) -> bytes:
        """The frame as a 16-bit depth PNG in millimetres, 0 where no depth."""
        import io

        from PIL import Image

        z = np.nan_to_num(self.points[..., 2], nan=0.0)
        image = Image.fromarray(np.rint(z * 1000).astype(np.uint16))
        buffer = io.BytesIO()
        image.save(buffer, format="PNG")
        return buffer.getvalue()

    def pcd(self, compressed: bool = False) -> bytes:
        """The frame as an organized binary PCD (its grid kept, NaN where no depth)."""
        import io

        from pypcd4 import Encoding, PointCloud

        height, width = self.shows.shape
        cloud = PointCloud.from_xyz_points(self.points.reshape(-1, 3).astype(np.float32))
        cloud.metadata.width, cloud.metadata.height = width, height
        buffer = io.BytesIO()
        encoding = Encoding.BINARY_COMPRESSED if compressed else Encoding.BINARY
        cloud.save(buffer, encoding=encoding)
        return buffer.getvalue()


def without(shot: Shot, missing: np.ndarray) -> Shot:
    """The shot with no point on the ``missing`` pixels (H, W), as an interlaced camera or a
    pattern of dropouts gives it."""
    points = shot.points.copy()
    points[missing] = np.nan
    return Shot(points, np.where(missing, -1, shot.shows), shot.poses, shot.camera)


def registered(shot: Shot, scale: float) -> Shot:
    """The shot as a depth image registered to a colour image ``scale`` times its size gives
    it, unfilled (ROS's ``depth_image_proc`` by default): each pixel's point on the pixel its
    ray lands on there, no point on the others (about one pixel in ``scale`` squared has one,
    in a pattern that drifts across the image)."""
    height, width = shot.shows.shape
    tall, wide = int(np.ceil(height * scale)) + 1, int(np.ceil(width * scale)) + 1
    rows, columns = np.mgrid[0:height, 0:width]
    rows = np.floor(rows * scale + 0.5).astype(int)
    columns = np.floor(columns * scale + 0.5).astype(int)
    points = np.full((tall, wide, 3), np.nan, dtype=np.float32)
    points[rows, columns] = shot.points
    shows = np.full((tall, wide), -1)
    shows[rows, columns] = shot.shows
    return Shot(points, shows, shot.poses, (wide, tall, shot.camera[2] * scale))


def frame_of(shot: Shot) -> Frame:
    """The engine's view of a shot, as POST /detect makes it from its organized PCD."""
    cloud = organized(shot.points, shot.shows.size, "frame")
    return Frame.of(cloud.points, cloud.index, cloud.shape)


def box(sides: tuple[float, float, float], centre: tuple[float, float, float]) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(sides)
    mesh.apply_translation(centre)
    return mesh


def table() -> list[trimesh.Trimesh]:
    """A table top 1.5 m square, its surface at z = 0 (world frame, z up)."""
    return [box((1.5, 1.5, 0.03), (0.0, 0.0, -0.015))]


def bin_walls(inside: float = 0.3, height: float = 0.12, wall: float = 0.01):
    """A bin on the table: a floor (its top at z = 0) and four walls, ``inside`` square."""
    half = inside / 2 + wall / 2
    return [
        *table(),
        box((inside + 2 * wall, wall, height), (0.0, half, height / 2)),
        box((inside + 2 * wall, wall, height), (0.0, -half, height / 2)),
        box((wall, inside, height), (half, 0.0, height / 2)),
        box((wall, inside, height), (-half, 0.0, height / 2)),
    ]


def resting(mesh: trimesh.Trimesh, rotation: np.ndarray, x: float, y: float, z: float = 0.0):
    """The world pose (R, t) of ``mesh`` turned by ``rotation`` with its lowest point at height
    ``z`` above the point (x, y)."""
    turned = np.asarray(mesh.vertices) @ rotation.T
    centre = turned.mean(axis=0)
    return rotation, np.array([x - centre[0], y - centre[1], z - turned[:, 2].min()])


def spin(degrees: float) -> np.ndarray:
    return Rotation.from_euler("z", degrees, degrees=True).as_matrix()


def shoot(
    parts: list[tuple[trimesh.Trimesh, np.ndarray, np.ndarray]],
    supports: list[trimesh.Trimesh],
    camera: tuple[int, int, float] = VGA,
    elevation_deg: float = 60.0,
    azimuth_deg: float = 30.0,
    distance: float = 0.8,
    noise: float = 0.0015,
    seed: int = 0,
) -> Shot:
    """The frame a camera ``distance`` from the table's centre, ``elevation_deg`` above it,
    gives of ``parts`` (mesh, world R, world t) on ``supports``: depth noise of ``noise`` of
    the range, depth in whole millimetres."""
    width, height, focal = camera
    to_camera, position = look_at(
        np.zeros(3), np.radians(azimuth_deg), np.radians(elevation_deg), distance
    )
    poses = [(to_camera @ r, to_camera @ (t - position)) for _, r, t in parts]
    placed = [
        trimesh.Trimesh(np.asarray(m.vertices) @ r.T + t, m.faces, process=False)
        for (m, _, _), (r, t) in zip(parts, poses, strict=True)
    ]
    placed += [
        trimesh.Trimesh((np.asarray(s.vertices) - position) @ to_camera.T, s.faces, process=False)
        for s in supports
    ]
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    cx, cy = (width - 1) / 2, (height - 1) / 2
    rays = np.stack([(u - cx) / focal, (v - cy) / focal, np.ones_like(u)], axis=-1).reshape(-1, 3)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    distance_along, hit = cast_rays(placed, rays)
    rng = np.random.default_rng(seed)
    measured = distance_along * (1 + noise * rng.normal(size=distance_along.shape))
    points = rays * measured[:, None]
    points[:, 2] = np.round(points[:, 2], 3)  # whole millimetres, as a 16-bit depth image
    points = rays * (points[:, 2] / rays[:, 2])[:, None]
    points[hit < 0] = np.nan
    shows = np.where(hit < len(parts), hit, -1)
    return Shot(
        points.reshape(height, width, 3).astype(np.float32),
        shows.reshape(height, width),
        poses,
        camera,
    )
