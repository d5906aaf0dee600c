"""Whole camera frames (docs/evaluation-protocol.md, "Whole frames"): parts dropped onto a table or
into a bin by pybullet's physics, seen by a depth camera as its driver writes the frame.

    python -m evaluation.frames --family scene --count 4 --seed 0 --out /tmp/frames

Families: ``scene`` (1-6 different registered parts and 0-2 unregistered ones on a table),
``bin`` (3-10 instances of one registered part in a bin, perhaps one other part), ``empty``
(the table or the bin alone) and ``foreign`` (the table or the bin holding only unregistered
parts). Each frame is an organized 640 × 480 depth image (f = 525 px, the principal point at
the image's centre) from 0.6-1.2 m, 40-80° above the table, with the sensor's effects: depth
noise σ = 0.15 % of the distance along each ray, depth quantised to 1 mm, and about half the
pixels missing at depth jumps (> 2 cm between neighbouring pixels).

Parts are simulated as their meshes' convex hulls (pybullet's dynamic meshes are hulls) and
rendered as their meshes. Each part is rescaled to a table's sizes (``part_scale``: a radius
of 3-15 cm) once, by a rule of its mesh alone, so every frame and the gallery hold the same
rescaled mesh: the model frame of a pose is the mesh file's frame times that scale.

Poses follow ``scene = R @ model + t`` into the camera frame (OpenCV's: the camera at the
origin looking along +z, x right, y down), as ``evaluation.camera``.
"""

from __future__ import annotations

import argparse
import io
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image
from scipy.spatial.transform import Rotation

from evaluation.camera import DEPTH_NOISE_SHARE, Camera, cast_rays
from evaluation.scenes import look_at, placed, surface_centroid

FAMILIES = ("scene", "bin", "empty", "foreign")
VGA = Camera(640, 480, 525.0)  # a Kinect or RealSense at VGA
HD = Camera(1280, 720, 1050.0)  # 1280 × 720, the same field across: f scaled by the width

RADIUS_RANGE_M = (0.03, 0.15)  # a part's radius on the table, after rescaling
DISTANCE_M = (0.6, 1.2)  # camera to the target on the table
ELEVATION_DEG = (40.0, 80.0)  # the camera's view above the table's plane
DEPTH_STEP_M = 0.001  # depth quantised to 1 mm
JUMP_M = 0.02  # a depth jump: more than this between neighbouring pixels ...
JUMP_DROP_SHARE = 0.5  # ... where this share of the pixels has no depth
TABLE_SIDES_M = ((1.0, 1.6), (0.7, 1.0))  # the table top's length and width
TABLE_THICKNESS_M = 0.03
FLOOR_DEPTH_M = 0.75  # the floor under the table: the frame's background
FLOOR_HALF_SIDE_M = 3.0
BIN_WALL_M = 0.01  # the bin's wall and floor thickness
SCENE_PARTS = (1, 6)  # scene: registered parts, all different ...
SCENE_FOREIGN = (0, 2)  # ... and unregistered ones
BIN_INSTANCES = (3, 10)
BIN_PART_RADIUS_M = 0.1  # bin: parts up to this radius (a bin of bigger ones spills over)
BIN_OTHER_SHARE = 0.3  # bin: the share of bins holding one other part
FOREIGN_PARTS = (1, 3)
CLUSTER_SPREAD = 0.5  # table: parts dropped within this × the root sum square of their radii
# Physics: a 240 Hz step, settled once every part moves slower than these, or after SETTLE_S.
SETTLE_S = 4.0
SETTLED_SPEED = 0.005  # m/s
SETTLED_SPIN = 0.05  # rad/s
FRICTION = 0.8
DAMPING = 0.5  # linear and angular: parts stop rolling off the table in a second
HULL_VERTICES = 64  # physics: each hull from at most this many of its vertices (spread out)
SUPPORT, NO_DEPTH = 0, 0  # the label image's value off every part; the depth PNG's for none


# --- parts -----------------------------------------------------------------------------------


def mesh_radius(mesh: trimesh.Trimesh) -> float:
    """The largest distance from the surface centroid to a vertex."""
    vertices = np.asarray(mesh.vertices, np.float64)
    return float(np.linalg.norm(vertices - surface_centroid(mesh), axis=1).max())


def part_scale(mesh: trimesh.Trimesh) -> float:
    """The factor that takes a mesh to a table's sizes: its units guessed from its radius
    (over 10: millimetres, as the differential's and the WSG50's; over 2: centimetres, as the
    procedural objects' 2-6 units), then the radius held within ``RADIUS_RANGE_M``."""
    radius = mesh_radius(mesh)
    unit = 0.001 if radius > 10 else 0.01 if radius > 2 else 1.0
    return float(np.clip(radius * unit, *RADIUS_RANGE_M) / radius)


@dataclass
class FramePart:
    """A part as the frames hold it: its mesh rescaled by ``scale`` (the model frame)."""

    name: str
    mesh: trimesh.Trimesh  # the rescaled mesh: the frame's model frame
    scale: float  # rescaled = the mesh file's vertices × scale
    registered: bool
    split: str = ""  # seen / unseen, where the part comes from the manifest

    @property
    def radius(self) -> float:
        return mesh_radius(self.mesh)


def frame_part(name: str, mesh: trimesh.Trimesh, registered: bool, split: str = "") -> FramePart:
    """``mesh`` rescaled by ``part_scale``."""
    scale = part_scale(mesh)
    vertices = np.asarray(mesh.vertices, np.float64) * scale
    rescaled = trimesh.Trimesh(vertices, np.asarray(mesh.faces), process=False)
    return FramePart(name, rescaled, scale, registered, split)


def manifest_parts(registered: list[str] | None = None, foreign: list[str] | None = None):
    """The manifest's parts (training/objects.json) as (registered, unregistered) lists:
    ``foreign`` (default: the evaluation's FOREIGN) kept out, the rest registered, or only
    those named in ``registered``."""
    from evaluation.cases import FOREIGN
    from training.objects import load_manifest, load_object_meshes

    foreign = list(FOREIGN if foreign is None else foreign)
    specs = load_manifest()
    wanted = [s for s in specs if s.name in foreign or registered is None or s.name in registered]
    meshes = load_object_meshes(wanted)
    parts = [frame_part(s.name, meshes[s.name], s.name not in foreign, s.split) for s in wanted]
    return [p for p in parts if p.registered], [p for p in parts if not p.registered]


# --- the supports ----------------------------------------------------------------------------


@dataclass
class Box:
    """A static box of the world (z up): half-extents and centre."""

    half: tuple[float, float, float]
    centre: tuple[float, float, float]

    def mesh(self) -> trimesh.Trimesh:
        box = trimesh.creation.box(2 * np.asarray(self.half))
        box.apply_translation(self.centre)
        return box


def table_boxes(rng: np.random.Generator) -> list[Box]:
    """A table top (its top face on z = 0, centred near the origin) and the floor below."""
    length, width = (rng.uniform(*side) for side in TABLE_SIDES_M)
    shift = rng.uniform(-0.1, 0.1, size=2)
    top = Box((length / 2, width / 2, TABLE_THICKNESS_M / 2), (*shift, -TABLE_THICKNESS_M / 2))
    floor = Box((FLOOR_HALF_SIDE_M, FLOOR_HALF_SIDE_M, 0.01), (0.0, 0.0, -FLOOR_DEPTH_M - 0.01))
    return [top, floor]


def bin_boxes(radius: float, rng: np.random.Generator) -> tuple[list[Box], float, float]:
    """A bin on the table for parts of ``radius``: its floor and four walls; returns them and
    the inner half-length and half-width."""
    half_x = float(np.clip(3.0 * radius, 0.15, 0.3) * rng.uniform(0.9, 1.1))
    half_y = float(np.clip(2.4 * radius, 0.12, 0.25) * rng.uniform(0.9, 1.1))
    height = float(np.clip(1.2 * radius, 0.06, 0.15))
    t = BIN_WALL_M
    boxes = [
        Box((half_x + t, half_y + t, t / 2), (0.0, 0.0, t / 2)),
        Box((t / 2, half_y + t, height / 2), (half_x + t / 2, 0.0, height / 2)),
        Box((t / 2, half_y + t, height / 2), (-half_x - t / 2, 0.0, height / 2)),
        Box((half_x, t / 2, height / 2), (0.0, half_y + t / 2, height / 2)),
        Box((half_x, t / 2, height / 2), (0.0, -half_y - t / 2, height / 2)),
    ]
    return boxes, half_x, half_y


# --- physics ---------------------------------------------------------------------------------


def hull_vertices(mesh: trimesh.Trimesh, count: int = HULL_VERTICES) -> np.ndarray:
    """At most ``count`` of the convex hull's vertices, spread by farthest-point sampling:
    the shape pybullet simulates (its collision cost grows with the hull's vertices)."""
    vertices = np.asarray(mesh.convex_hull.vertices, np.float64)
    if len(vertices) <= count:
        return vertices
    chosen = [int(np.argmax(np.linalg.norm(vertices - vertices.mean(axis=0), axis=1)))]
    nearest = np.linalg.norm(vertices - vertices[chosen[0]], axis=1)
    for _ in range(count - 1):
        chosen.append(int(np.argmax(nearest)))
        nearest = np.minimum(nearest, np.linalg.norm(vertices - vertices[chosen[-1]], axis=1))
    return vertices[chosen]


def drop_positions(
    radii: list[float], half_x: float, half_y: float, floor: float, rng: np.random.Generator
) -> np.ndarray:
    """Start positions (N, 3): uniform in the box ±``half_x`` × ±``half_y``, each as low above
    ``floor`` as its bounding sphere allows without meeting those placed before."""
    centres: list[np.ndarray] = []
    for radius in radii:
        xy = rng.uniform([-half_x, -half_y], [half_x, half_y])
        z = floor + radius + 0.005
        for other, other_radius in zip(centres, radii, strict=False):
            gap = radius + other_radius + 0.005
            across = np.hypot(*(xy - other[:2]))
            if across < gap:
                z = max(z, other[2] + np.sqrt(gap**2 - across**2))
        centres.append(np.array([*xy, z]))
    return np.array(centres)


def settle(
    parts: list[FramePart], boxes: list[Box], starts: np.ndarray, rng: np.random.Generator
) -> tuple[list[tuple[np.ndarray, np.ndarray]], float]:
    """Drop ``parts`` from ``starts`` in random orientations among the static ``boxes`` and let
    pybullet's physics settle them: each part's (R, t) from its model frame to the world, and
    the seconds simulated."""
    import pybullet as pb  # the train extra; imported here so the module loads without it

    client = pb.connect(pb.DIRECT)
    try:
        pb.setGravity(0, 0, -9.81, physicsClientId=client)
        for box in boxes:
            shape = pb.createCollisionShape(
                pb.GEOM_BOX, halfExtents=list(box.half), physicsClientId=client
            )
            body = pb.createMultiBody(
                0, shape, basePosition=list(box.centre), physicsClientId=client
            )
            pb.changeDynamics(body, -1, lateralFriction=FRICTION, physicsClientId=client)
        bodies, centroids = [], []
        for part, start in zip(parts, starts, strict=True):
            centroid = surface_centroid(part.mesh)
            hull = hull_vertices(part.mesh) - centroid
            shape = pb.createCollisionShape(
                pb.GEOM_MESH, vertices=hull.tolist(), physicsClientId=client
            )
            turn = Rotation.random(random_state=int(rng.integers(2**31))).as_quat()
            body = pb.createMultiBody(
                0.1, shape, basePosition=start.tolist(), baseOrientation=turn.tolist(),
                physicsClientId=client,
            )  # fmt: skip
            pb.changeDynamics(
                body, -1, lateralFriction=FRICTION, rollingFriction=0.002,
                spinningFriction=0.002, linearDamping=DAMPING, angularDamping=DAMPING,
                restitution=0.0, physicsClientId=client,
            )  # fmt: skip
            bodies.append(body)
            centroids.append(centroid)
        for step in range(int(SETTLE_S * 240)):
            pb.stepSimulation(physicsClientId=client)
            if step % 24 == 23:
                speeds = [pb.getBaseVelocity(b, physicsClientId=client) for b in bodies]
                if all(
                    np.linalg.norm(v) < SETTLED_SPEED and np.linalg.norm(w) < SETTLED_SPIN
                    for v, w in speeds
                ):
                    break
        poses = []
        for body, centroid in zip(bodies, centroids, strict=True):
            position, orientation = pb.getBasePositionAndOrientation(body, physicsClientId=client)
            rotation = Rotation.from_quat(orientation).as_matrix()
            poses.append((rotation, np.asarray(position) - rotation @ centroid))
        return poses, (step + 1) / 240
    finally:
        pb.disconnect(physicsClientId=client)


# --- the frame -------------------------------------------------------------------------------


@dataclass
class Instance:
    """One part in a frame and its ground truth."""

    name: str
    registered: bool
    split: str
    scale: float  # the model frame = the mesh file's frame × scale
    rotation: np.ndarray  # (3, 3): scene = R @ model + t, camera frame
    translation: np.ndarray  # (3,)
    pixels: int  # pixels where it is the first surface hit (before any is dropped)
    pixels_alone: int  # the pixels it would cover alone in the same frame
    valid_pixels: int = 0  # of ``pixels``, those that kept a depth

    @property
    def visible_share(self) -> float:
        return self.pixels / self.pixels_alone if self.pixels_alone else 0.0


@dataclass
class Frame:
    """One depth frame: the depth, which instance each pixel shows, and the ground truth."""

    family: str
    index: int
    seed: int
    camera: Camera
    depth: np.ndarray  # (H, W) float32 metres along z, NaN where no depth
    labels: np.ndarray  # (H, W) uint16: 1 + the instance the pixel shows, 0 for none
    instances: list[Instance]
    support: str  # "table" or "bin"
    world_to_camera: np.ndarray  # (3, 3): x_camera = R @ (x_world - position)
    camera_position: np.ndarray  # (3,) world frame
    supports: list[Box] = field(default_factory=list)  # the table, floor and bin, world frame
    seconds: dict = field(default_factory=dict)

    @property
    def stem(self) -> str:
        return f"{self.family}-{self.seed}-{self.index:04d}"

    @property
    def table_plane(self) -> np.ndarray:
        """(4,) the table's top n·x + d = 0 in the camera frame, n toward the camera."""
        normal = self.world_to_camera[:, 2]
        return np.append(normal, normal @ self.world_to_camera @ self.camera_position)

    def world_pose(self, instance: Instance) -> tuple[np.ndarray, np.ndarray]:
        """An instance's pose (R, t) from its model frame to the world frame (z up)."""
        back = self.world_to_camera.T
        return back @ instance.rotation, back @ instance.translation + self.camera_position

    def points(self) -> np.ndarray:
        """(H, W, 3) float32, the camera frame, NaN where no depth."""
        return depth_to_points(self.depth, self.camera)

    def instance_pixels(self, index: int) -> np.ndarray:
        """The pixel indices (row × width + column) where instance ``index`` is seen."""
        return np.flatnonzero(self.labels.ravel() == index + 1)

    def registered_parts(self) -> list[str]:
        """The names of the registered parts the frame holds, sorted."""
        return sorted({i.name for i in self.instances if i.registered})

    def truth(self) -> dict:
        """The ground truth as JSON."""
        return {
            "family": self.family,
            "index": self.index,
            "seed": self.seed,
            "camera": intrinsics(self.camera),
            "support": self.support,
            "world_to_camera": self.world_to_camera.tolist(),
            "camera_position": self.camera_position.tolist(),
            "table_plane": self.table_plane.tolist(),
            "supports": [asdict(box) for box in self.supports],
            "instances": [
                {
                    **{k: v for k, v in asdict(i).items() if k not in ("rotation", "translation")},
                    "rotation": np.asarray(i.rotation).tolist(),
                    "translation": np.asarray(i.translation).tolist(),
                    "visible_share": i.visible_share,
                }
                for i in self.instances
            ],
            "seconds": self.seconds,
        }


def intrinsics(camera: Camera) -> dict:
    """A depth image's intrinsics as the service takes them: pixel (column u, row v) from the
    top-left pixel, so the principal point at the image's centre is (W/2 - 0.5, H/2 - 0.5)."""
    return {
        "width": camera.width,
        "height": camera.height,
        "fx": camera.focal,
        "fy": camera.focal,
        "cx": camera.width / 2 - 0.5,
        "cy": camera.height / 2 - 0.5,
        "depth_scale": DEPTH_STEP_M,
    }


def depth_to_points(depth: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W, 3) float32 points of a depth image (z in metres, NaN for none)."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width] + 0.5
    cx, cy = camera.principal_point
    z = depth.astype(np.float64)
    points = np.stack([(u - cx) * z / camera.focal, (v - cy) * z / camera.focal, z], axis=-1)
    return points.astype(np.float32)


def sensor_depth(
    distance: np.ndarray, directions: np.ndarray, camera: Camera, rng: np.random.Generator
) -> np.ndarray:
    """What the sensor reports of the true distances along each pixel's ray (inf: no hit):
    (H, W) depth along z in metres, with noise along the ray (σ = 0.15 % of the distance),
    quantised to 1 mm, NaN where there is none, and about half the pixels at depth jumps
    dropped."""
    measured = distance * (1.0 + DEPTH_NOISE_SHARE * rng.normal(size=distance.shape))
    depth = np.round(measured * directions[:, 2] / DEPTH_STEP_M) * DEPTH_STEP_M
    depth = np.where(np.isfinite(depth), depth, np.nan).reshape(camera.height, camera.width)
    with np.errstate(invalid="ignore"):
        across = np.abs(np.diff(depth, axis=1)) > JUMP_M
        down = np.abs(np.diff(depth, axis=0)) > JUMP_M
    jump = np.zeros(depth.shape, dtype=bool)
    jump[:, 1:] |= across
    jump[:, :-1] |= across
    jump[1:, :] |= down
    jump[:-1, :] |= down
    depth[jump & (rng.random(depth.shape) < JUMP_DROP_SHARE)] = np.nan
    return depth.astype(np.float32)


def pixels_alone(mesh: trimesh.Trimesh, camera: Camera, directions: np.ndarray) -> int:
    """How many pixels ``mesh`` (in the camera frame) covers with nothing in front of it: its
    rays cast alone, only those within its projected bounding box."""
    vertices = np.asarray(mesh.vertices, np.float64)
    ahead = vertices[vertices[:, 2] > 1e-3]
    if len(ahead) == 0:
        return 0
    cx, cy = camera.principal_point
    u = ahead[:, 0] / ahead[:, 2] * camera.focal + cx
    v = ahead[:, 1] / ahead[:, 2] * camera.focal + cy
    columns = np.arange(max(int(u.min()) - 1, 0), min(int(u.max()) + 2, camera.width))
    rows = np.arange(max(int(v.min()) - 1, 0), min(int(v.max()) + 2, camera.height))
    if len(columns) == 0 or len(rows) == 0:
        return 0
    pixels = (rows[:, None] * camera.width + columns[None, :]).ravel()
    _, hit = cast_rays([mesh], directions[pixels])
    return int((hit >= 0).sum())


def render(
    family: str,
    index: int,
    seed: int,
    parts: list[FramePart],
    poses: list[tuple[np.ndarray, np.ndarray]],
    boxes: list[Box],
    support: str,
    target: np.ndarray,
    camera: Camera,
    rng: np.random.Generator,
) -> Frame:
    """The camera at a random view of ``target`` (world frame) sees the parts at their world
    ``poses`` and the ``boxes``: the frame with its sensor effects and ground truth."""
    to_camera, position = look_at(
        target,
        rng.uniform(0, 2 * np.pi),
        np.radians(rng.uniform(*ELEVATION_DEG)),
        rng.uniform(*DISTANCE_M),
    )
    in_camera = [
        (to_camera @ rotation, to_camera @ (translation - position))
        for rotation, translation in poses
    ]
    part_meshes = [placed(p.mesh, r, t) for p, (r, t) in zip(parts, in_camera, strict=True)]
    support_meshes = [placed(b.mesh(), to_camera, -to_camera @ position) for b in boxes]
    directions = camera.rays()
    distance, hit = cast_rays(part_meshes + support_meshes, directions)
    labels = np.where((hit >= 0) & (hit < len(parts)), hit + 1, SUPPORT)
    labels = labels.reshape(camera.height, camera.width).astype(np.uint16)
    depth = sensor_depth(distance, directions, camera, rng)
    instances = []
    for number, (part, mesh, (rotation, translation)) in enumerate(
        zip(parts, part_meshes, in_camera, strict=True)
    ):
        seen = labels == number + 1
        instances.append(
            Instance(
                part.name,
                part.registered,
                part.split,
                part.scale,
                rotation,
                translation,
                int(seen.sum()),
                max(pixels_alone(mesh, camera, directions), int(seen.sum())),
                int((seen & np.isfinite(depth)).sum()),
            )
        )
    return Frame(
        family, index, seed, camera, depth, labels, instances, support, to_camera, position, boxes
    )


# --- the families ----------------------------------------------------------------------------


def _some(pool: list[FramePart], count: int, rng: np.random.Generator) -> list[FramePart]:
    chosen = rng.choice(len(pool), size=min(count, len(pool)), replace=False)
    return [pool[int(i)] for i in chosen]


def make_frame(
    family: str,
    index: int,
    seed: int,
    registered: list[FramePart],
    foreign: list[FramePart],
    camera: Camera = VGA,
) -> Frame:
    """Frame ``index`` of ``family``, the same for the same arguments: parts drawn from
    ``registered`` and ``foreign`` (unregistered), dropped, settled and seen."""
    if family not in FAMILIES:
        raise ValueError(f"unknown family {family!r}; pick one of {FAMILIES}")
    rng = np.random.default_rng([seed, FAMILIES.index(family), index])
    began = time.perf_counter()
    on_bin = family == "bin" or (family in ("empty", "foreign") and rng.random() < 0.5)
    if family == "scene":
        parts = _some(registered, int(rng.integers(SCENE_PARTS[0], SCENE_PARTS[1] + 1)), rng)
        parts += _some(foreign, int(rng.integers(SCENE_FOREIGN[0], SCENE_FOREIGN[1] + 1)), rng)
    elif family == "bin":
        small = [p for p in registered if p.radius <= BIN_PART_RADIUS_M] or registered
        part = small[int(rng.integers(len(small)))]
        parts = [part] * int(rng.integers(BIN_INSTANCES[0], BIN_INSTANCES[1] + 1))
        if rng.random() < BIN_OTHER_SHARE:
            others = [p for p in registered + foreign if p.name != part.name]
            parts.append(others[int(rng.integers(len(others)))])
    elif family == "foreign":
        parts = _some(foreign, int(rng.integers(FOREIGN_PARTS[0], FOREIGN_PARTS[1] + 1)), rng)
    else:
        parts = []
    order = rng.permutation(len(parts))
    parts = [parts[int(i)] for i in order]
    radii = [p.radius for p in parts]
    boxes = table_boxes(rng)
    if on_bin:
        bin_walls, half_x, half_y = bin_boxes(max(radii, default=0.08), rng)
        boxes += bin_walls
        spread_x, spread_y, floor = half_x * 0.8, half_y * 0.8, BIN_WALL_M
    else:
        # a cluster a little wider than the parts: they touch and hide each other
        spread = max(0.03, CLUSTER_SPREAD * float(np.sqrt(np.sum(np.square(radii)))))
        spread_x = spread_y = spread
        floor = 0.0
    starts = drop_positions(radii, spread_x, spread_y, floor, rng)
    poses, simulated = settle(parts, boxes, starts, rng) if parts else ([], 0.0)
    settled = time.perf_counter()
    if poses and not on_bin:
        centres = [r @ surface_centroid(p.mesh) + t for p, (r, t) in zip(parts, poses, strict=True)]
        target = np.mean(centres, axis=0)
        target[2] = 0.0
    else:
        target = np.zeros(3)
    target[:2] += rng.uniform(-0.05, 0.05, size=2)
    frame = render(
        family, index, seed, parts, poses, boxes, "bin" if on_bin else "table", target, camera,
        rng,
    )  # fmt: skip
    frame.seconds = {
        "simulated": simulated,
        "physics": settled - began,
        "render": time.perf_counter() - settled,
    }
    return frame


def make_frames(
    family: str,
    count: int,
    seed: int,
    registered: list[FramePart],
    foreign: list[FramePart],
    camera: Camera = VGA,
) -> list[Frame]:
    return [make_frame(family, i, seed, registered, foreign, camera) for i in range(count)]


# --- files, as a camera driver writes them ---------------------------------------------------


def pcd_bytes(frame: Frame, compressed: bool = False) -> bytes:
    """An organized PCD (WIDTH × HEIGHT, x y z float32, NaN where no depth), binary or
    binary_compressed, as PCL's ``savePCDFileBinary`` writes a camera's cloud."""
    from pypcd4 import Encoding, PointCloud

    cloud = PointCloud.from_xyz_points(frame.points().reshape(-1, 3))
    cloud.metadata.width, cloud.metadata.height = frame.camera.width, frame.camera.height
    buffer = io.BytesIO()
    cloud.save(buffer, Encoding.BINARY_COMPRESSED if compressed else Encoding.BINARY)
    return buffer.getvalue()


def read_pcd(data: bytes) -> np.ndarray:
    """An organized PCD's points as (HEIGHT, WIDTH, 3) float32 (NaN kept in place)."""
    from pypcd4 import PointCloud

    cloud = PointCloud.from_fileobj(io.BytesIO(data))
    points = cloud.numpy(("x", "y", "z")).astype(np.float32)
    return points.reshape(cloud.metadata.height, cloud.metadata.width, 3)


def depth_png_bytes(frame: Frame) -> bytes:
    """The 16-bit depth PNG in millimetres, 0 where no depth."""
    millimetres = np.nan_to_num(frame.depth / DEPTH_STEP_M, nan=NO_DEPTH)
    return _png16(np.round(millimetres).astype(np.uint16))


def read_depth_png(data: bytes) -> np.ndarray:
    """A 16-bit depth PNG in millimetres as (H, W) float32 metres, NaN where 0."""
    millimetres = np.asarray(Image.open(io.BytesIO(data)), dtype=np.float64)
    return np.where(millimetres > 0, millimetres * DEPTH_STEP_M, np.nan).astype(np.float32)


def _png16(image: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(image.astype(np.uint16)).save(buffer, format="PNG")
    return buffer.getvalue()


def write_frame(frame: Frame, out: Path, compressed: bool = False) -> dict[str, Path]:
    """The frame's files in ``out``: ``STEM.pcd`` (organized), ``STEM-depth.png`` (16-bit,
    millimetres) with ``STEM-camera.json`` (its intrinsics), ``STEM-labels.png`` (16-bit:
    1 + the instance each pixel shows, 0 for none) and ``STEM.json`` (the ground truth)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = {
        "pcd": out / f"{frame.stem}.pcd",
        "depth": out / f"{frame.stem}-depth.png",
        "camera": out / f"{frame.stem}-camera.json",
        "labels": out / f"{frame.stem}-labels.png",
        "truth": out / f"{frame.stem}.json",
    }
    files["pcd"].write_bytes(pcd_bytes(frame, compressed))
    files["depth"].write_bytes(depth_png_bytes(frame))
    files["camera"].write_text(json.dumps(intrinsics(frame.camera), indent=1) + "\n")
    files["labels"].write_bytes(_png16(frame.labels))
    truth = frame.truth() | {"files": {k: p.name for k, p in files.items() if k != "truth"}}
    files["truth"].write_text(json.dumps(truth, indent=1) + "\n")
    return files


def read_frame(truth_path: Path) -> Frame:
    """A frame written by ``write_frame``, from its ``STEM.json``: the depth from its PCD."""
    truth_path = Path(truth_path)
    truth = json.loads(truth_path.read_text())
    folder = truth_path.parent
    meta = truth["camera"]
    camera = Camera(meta["width"], meta["height"], meta["fx"])
    points = read_pcd((folder / truth["files"]["pcd"]).read_bytes())
    labels = np.asarray(Image.open(folder / truth["files"]["labels"]), dtype=np.uint16)
    instances = [
        Instance(
            i["name"],
            i["registered"],
            i["split"],
            i["scale"],
            np.array(i["rotation"]),
            np.array(i["translation"]),
            i["pixels"],
            i["pixels_alone"],
            i["valid_pixels"],
        )  # fmt: skip
        for i in truth["instances"]
    ]
    return Frame(
        truth["family"], truth["index"], truth["seed"], camera, points[..., 2], labels,
        instances, truth["support"], np.array(truth["world_to_camera"]),
        np.array(truth["camera_position"]),
        [Box(tuple(b["half"]), tuple(b["centre"])) for b in truth.get("supports", [])],
        truth.get("seconds", {}),
    )  # fmt: skip


def write_parts(parts: list[FramePart], out: Path) -> Path:
    """Each part's rescaled mesh as ``out/parts/NAME.stl`` (what to register: the frames' model
    frame) and ``out/parts/parts.json`` (name, scale, registered, split)."""
    folder = Path(out) / "parts"
    folder.mkdir(parents=True, exist_ok=True)
    for part in parts:
        part.mesh.export(folder / f"{part.name}.stl")
    listing = [
        {"name": p.name, "scale": p.scale, "registered": p.registered, "split": p.split}
        for p in parts
    ]
    path = folder / "parts.json"
    path.write_text(json.dumps({"parts": listing}, indent=1) + "\n")
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--family", choices=FAMILIES, default="scene")
    parser.add_argument("--count", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--hd", action="store_true", help="1280 × 720 (f = 1050) instead of VGA")
    parser.add_argument("--compressed", action="store_true", help="binary_compressed PCD")
    parser.add_argument(
        "--parts", nargs="*", default=None, help="registered parts to draw from (default: all)"
    )
    args = parser.parse_args(argv)
    registered, foreign = manifest_parts(args.parts)
    used: dict[str, FramePart] = {}
    for index in range(args.count):
        frame = make_frame(
            args.family, index, args.seed, registered, foreign, HD if args.hd else VGA
        )
        write_frame(frame, args.out, args.compressed)
        for instance in frame.instances:
            used[instance.name] = next(p for p in registered + foreign if p.name == instance.name)
        shares = ", ".join(f"{i.name} {i.visible_share:.2f}" for i in frame.instances)
        print(f"{frame.stem}: {len(frame.instances)} instances ({shares or 'none'})")
    write_parts(list(used.values()), args.out)
    print(f"{args.count} frames and the parts they hold in {args.out}")


if __name__ == "__main__":
    main()
