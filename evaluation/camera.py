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


# --- sensor profiles (the calibration's corpus, evaluation.calibration_corpus) ----------------


@dataclass(frozen=True)
class SensorProfile:
    """What a kind of depth camera does to the true distances, beside its noise along the ray.

    ``step``: depth quantised to this (metres, 0: none); at depth jumps (more than ``jump``
    metres between neighbouring pixels) ``jump_drop`` of the pixels are missing, as
    structured-light and stereo cameras drop them; ``flying``: the share of the pixels on a
    part's outline smeared back along their ray by up to ``smear`` metres (a time-of-flight
    camera's mixed pixels); ``dropout``: the share of all pixels missing at random."""

    name: str
    noise_share: float = DEPTH_NOISE_SHARE
    step: float = 0.0
    jump: float = 0.02
    jump_drop: float = 0.0
    flying: float = 0.0
    smear: float = 0.03
    dropout: float = 0.0


PROFILES = {
    "sensor": SensorProfile("sensor"),  # the evaluation's sensor family
    "camera": SensorProfile("camera", step=0.001, jump_drop=0.5),  # the frames' effects
    "tof": SensorProfile("tof", 0.005, 0.001, 0.02, 0.5, flying=0.3, dropout=0.05),
}


def cast_profiled(
    meshes: list[trimesh.Trimesh],
    rng: np.random.Generator,
    profile: SensorProfile,
    camera: Camera = DEFAULT_CAMERA,
) -> DepthPoints:
    """Like ``cast``, with ``profile``'s effects worked on the whole pixel grid."""
    directions = camera.rays()
    distance, mesh_index = cast_rays(meshes, directions)
    measured = distance * (1.0 + profile.noise_share * rng.normal(size=distance.shape))
    z = measured * directions[:, 2]
    if profile.step:
        z = np.round(z / profile.step) * profile.step
    depth = np.where(np.isfinite(z), z, np.nan).reshape(camera.height, camera.width)
    missing = np.zeros(depth.shape, dtype=bool)
    valid = np.isfinite(depth)
    jump, outline = np.zeros_like(missing), np.zeros_like(missing)
    with np.errstate(invalid="ignore"):
        for axis in (0, 1):
            step = np.abs(np.diff(depth, axis=axis)) > profile.jump
            gap = np.diff(valid.astype(np.int8), axis=axis) != 0
            ahead = [slice(None)] * 2
            behind = [slice(None)] * 2
            ahead[axis], behind[axis] = slice(1, None), slice(None, -1)
            for side in (tuple(ahead), tuple(behind)):
                jump[side] |= step
                outline[side] |= gap
    missing |= jump & (rng.random(depth.shape) < profile.jump_drop)
    missing |= rng.random(depth.shape) < profile.dropout
    flying = (outline | jump) & valid & (rng.random(depth.shape) < profile.flying)
    depth[flying] += rng.uniform(0.0, profile.smear, size=int(flying.sum()))
    depth[missing] = np.nan
    depth = depth.ravel()
    keep = np.isfinite(depth)
    points = directions[keep] * (depth[keep] / directions[keep, 2])[:, None]
    return DepthPoints(points, mesh_index[keep], distance[keep])
