"""A depth camera: a pinhole at the origin looking along +z, one point per pixel whose ray
hits a mesh (Open3D's ``RaycastingScene``), with depth noise along each ray.

The camera frame is OpenCV's: x to the right of the image, y down, z forward; pixel (u, v)
looks along ((u - cx) / f, (v - cy) / f, 1), the ray through the centre of that pixel. Open3D
(the ``eval`` extra; its wheel needs Debian's ``libusb-1.0-0``) is imported when a scene is
cast, so the rest of the evaluation loads without it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

DEPTH_NOISE_SHARE = 0.0015  # σ of the depth noise: 0.15 % of the distance along the ray


@dataclass(frozen=True)
class Camera:
    """A pinhole camera at the origin looking along +z; the principal point is the image's
    centre."""

    width: int = 320
    height: int = 240
    focal: float = 300.0  # pixels

    @property
    def principal_point(self) -> tuple[float, float]:
        return self.width / 2.0, self.height / 2.0

    def ray(self, u: float, v: float) -> np.ndarray:
        """The unit direction through pixel coordinates (u, v)."""
        cx, cy = self.principal_point
        direction = np.array([(u - cx) / self.focal, (v - cy) / self.focal, 1.0])
        return direction / np.linalg.norm(direction)

    def rays(self) -> np.ndarray:
        """(height × width, 3) unit directions through every pixel's centre, row by row."""
        v, u = np.mgrid[0 : self.height, 0 : self.width] + 0.5
        cx, cy = self.principal_point
        directions = np.stack(
            [(u - cx) / self.focal, (v - cy) / self.focal, np.ones_like(u)], axis=-1
        ).reshape(-1, 3)
        return directions / np.linalg.norm(directions, axis=1, keepdims=True)

    def middle_half_pixel(self, rng: np.random.Generator) -> tuple[float, float]:
        """A pixel uniform in the middle half of the image (the central half of each side)."""
        return (
            float(rng.uniform(self.width / 4, 3 * self.width / 4)),
            float(rng.uniform(self.height / 4, 3 * self.height / 4)),
        )


DEFAULT_CAMERA = Camera()


@dataclass
class DepthPoints:
    """What a depth camera measured: one point per hit pixel, in the camera frame."""

    points: np.ndarray  # (M, 3) float64, with the depth noise
    mesh_index: np.ndarray  # (M,) which of the cast meshes each point lies on
    distance: np.ndarray  # (M,) the true distance along the ray, before noise


def cast_rays(meshes: list[trimesh.Trimesh], directions: np.ndarray):
    """Cast a ray from the origin along each of ``directions`` (unit, (K, 3)) at ``meshes``
    (already placed in the camera frame): the distance to the first hit of each (infinity for
    a miss) and which mesh it hit (-1 for a miss)."""
    import open3d as o3d  # the eval extra; imported here so the module loads without it

    scene = o3d.t.geometry.RaycastingScene()
    ids = [
        scene.add_triangles(
            o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
            o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)),
        )
        for mesh in meshes
    ]
    rays = np.hstack([np.zeros_like(directions), directions]).astype(np.float32)
    hits = scene.cast_rays(o3d.core.Tensor(rays))
    distance = hits["t_hit"].numpy().astype(np.float64)
    hit = np.isfinite(distance)
    mesh_index = np.full(len(distance), -1, dtype=np.intp)
    mesh_index[hit] = np.searchsorted(np.asarray(ids), hits["geometry_ids"].numpy()[hit])
    return distance, mesh_index


def cast(
    meshes: list[trimesh.Trimesh],
    rng: np.random.Generator,
    camera: Camera = DEFAULT_CAMERA,
    noise_share: float = DEPTH_NOISE_SHARE,
) -> DepthPoints:
    """Cast one ray per pixel at ``meshes`` (already placed in the camera frame) and keep the
    first hit of each: the points the camera sees, with Gaussian noise of σ = ``noise_share``
    × the distance along the ray."""
    directions = camera.rays()
    distance, mesh_index = cast_rays(meshes, directions)
    hit = mesh_index >= 0
    distance, directions, mesh_index = distance[hit], directions[hit], mesh_index[hit]
    measured = distance * (1.0 + noise_share * rng.normal(size=distance.shape))
    return DepthPoints(directions * measured[:, None], mesh_index, distance)
