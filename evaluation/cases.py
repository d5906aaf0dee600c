"""The case families of docs/evaluation-protocol.md, deterministic given a seed.

Each case is an object's mesh resampled with a seed of its own (never seed 0, the
reference's), moved by a known pose ``scene = R @ model + t`` and shuffled. Its ``params``
say what the right answer is: ``expected`` is the object's label, or ``"no_match"``.

Full clouds and the paper's setting:

- ``paper-poses``: rotations about x, y and z by 0, π/10, ..., 4π/10 each (125 poses),
  translation 0, as the paper's test set;
- ``sparse``: the paper's poses keeping a share of the points at random (paper's Fig. 5);
- ``so3``: a rotation uniform over SO(3) and a translation uniform in a ball of radius
  twice the scale;
- ``noisy``: the ``so3`` case of the same index (same pose) plus Gaussian noise of σ = 1 % of
  the scale on every coordinate;
- ``partial``: the ``so3`` case of the same index (same pose), keeping only the points a
  single depth camera looking down the scene's -z axis would see (hidden-point removal).

What a cell's depth camera sends (``evaluation.camera``, ``evaluation.scenes``): a pinhole
camera at the origin looking along +z, 320×240 pixels, f = 300 px, the principal point at
the image's centre; one point per pixel whose ray hits a mesh (Open3D's ray casting), depth
noise σ = 0.15 % of the distance along each ray; the cloud is in the camera frame, so
``params["viewpoint"]`` is [0, 0, 0]:

- ``sensor``: the part in a rotation uniform over SO(3), its centre 4 to 8 scales from the
  camera and anywhere in the middle half of the image; hundreds to thousands of points, as
  the view has them.

Knowing when not to answer (docs/evaluation-protocol.md's second table):

- ``foreign``: for each case index, an so3 full cloud and a ``sensor`` view of a part that
  is not registered (the caller passes meshes kept out of the gallery); expected
  ``no_match``. ``params["view"]`` says which (``full``, ``sensor``);
- ``junk``: clouds of no part (uniform noise in a box, a Gaussian blob, a sphere shell, a
  flat patch), each the size of a registered part drawn at random from ``scales``, 4 to 8
  sizes in front of the camera; expected ``no_match``;
- ``units``: a registered part's so3 full cloud and its ``sensor`` view, both × 1000 (in
  millimetres while the references are in metres); ``rotation`` and ``translation`` are the
  true pose in the cloud's units (``translation`` × 1000, ``params["unit_factor"]``).
  Expected: the label and that pose, or a refusal whose reasons name the units
  (``params["right_refusal"] = "units"``);
- ``table``: a ``sensor``-like view of the part resting on a table in one of its stable
  poses (trimesh's ``compute_stable_poses``), the camera 4 to 8 scales away looking down at
  30-60° to the table, both ray cast, cropped to 2.5 scales around the part, plus 2 % stray
  points in the cloud's bounding box grown by one scale; expected the label and pose;
- ``symmetric``: a symmetric part (``orders``: revolution or n-fold about an axis found on
  the mesh, ``evaluation.scenes.symmetry_axis``) at one pose, turned about its axis by
  several angles (every n-th turn; six random angles for a revolution): the same surface,
  resampled (``view`` ``full``) or seen by the camera (``sensor``). The members of one
  ``params["group"]`` should get one and the same answered pose.
"""

from __future__ import annotations

import itertools
import zlib
from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from evaluation.metrics import place
from evaluation.scenes import (
    JUNK_KINDS,
    PART,
    STRAY,
    TABLE,
    junk_cloud,
    sensor_view,
    stable_poses,
    surface_centroid,
    symmetry_axis,
    table_scene,
    turn_about,
)
from service.engine.normalize import radius
from service.engine.sampling import sample_surface
from service.engine.visibility import visible_points

# the unseen parts kept unregistered: their clouds must be refused
FOREIGN = ("xarm-link-5", "pr2-finger-tip", "realsense-d435i", "random-700")

FULL_CLOUD_FAMILIES = ("paper-poses", "sparse", "so3", "noisy", "partial")
ANSWER_FAMILIES = ("foreign", "junk", "units", "table", "symmetric")  # knowing when not to answer
FAMILIES = (*FULL_CLOUD_FAMILIES, "sensor", *ANSWER_FAMILIES)
NO_MATCH = "no_match"  # params["expected"] of a case with no registered part in it

PAPER_ANGLES = tuple(k * np.pi / 10 for k in range(5))  # 0, π/10, ..., 4π/10
TRAINING_ANGLE_STEP = np.pi / 24  # the paper's training poses: multiples of π/24
KEEP_SHARES = (0.1, 0.3, 0.5, 0.7, 0.9)
DEFAULT_RANDOM_CASES = 25  # so3 / noisy / partial cases per object when none is asked for
TRANSLATION_SCALES = 2.0  # so3 translations lie in a ball of this many scales
NOISE_SCALE_SHARE = 0.01  # noisy: σ per coordinate, as a share of the scale

# The partial family's camera: on the +z axis of the scene frame through the object's
# centroid, this many scales above it, looking down -z. 10 scales is a robot cell's camera
# (0.5-1 m from a 5-10 cm part): nearly orthographic, so a convex part shows about half its
# surface (a sphere 45 %; at 3 scales only a third), a concave one less (0.3-0.45 here).
CAMERA_DISTANCE_SCALES = 10.0
DENSE_FACTOR = 4  # partial: sample this many times n_points before the visibility test
SENSOR_DISTANCE_SCALES = (4.0, 8.0)  # sensor: the part's centre this many scales away
UNIT_FACTOR = 1000.0  # units: the cloud in millimetres, the references in metres
REVOLUTION_TURNS = 6  # symmetric: angles per group for a part of revolution (order 0)


@dataclass
class Case:
    """One test cloud: ``points`` = R @ (resampled model points) + t, shuffled."""

    object_name: str
    family: str
    points: np.ndarray  # (M, 3) float32, in the scene frame, shuffled
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    params: dict = field(default_factory=dict)


def object_scale(points: np.ndarray) -> float:
    """The scale of an object: the radius of its reference cloud (the service's definition)."""
    return radius(np.asarray(points, dtype=np.float64))


def rotation_from_angles(ax: float, ay: float, az: float) -> np.ndarray:
    """Rotate about x by ``ax``, then about y by ``ay``, then about z by ``az`` (fixed axes).

    Returns R = Rz(az) @ Ry(ay) @ Rx(ax), so ``R @ p`` applies the x rotation first.
    """
    cx, sx = np.cos(ax), np.sin(ax)
    cy, sy = np.cos(ay), np.sin(ay)
    cz, sz = np.cos(az), np.sin(az)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    return rz @ ry @ rx


def paper_poses() -> np.ndarray:
    """The paper's 125 test poses as (ax, ay, az) angle triples, each in {0, π/10, ..., 4π/10}."""
    return np.array(list(itertools.product(PAPER_ANGLES, repeat=3)), dtype=np.float64)


def uniform_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` rotation matrices uniform over SO(3), shape (n, 3, 3)."""
    return Rotation.random(n, random_state=rng).as_matrix().reshape(n, 3, 3)


def uniform_in_ball(radius: float, rng: np.random.Generator) -> np.ndarray:
    """One point uniform in the ball of ``radius`` about the origin."""
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    return direction * radius * rng.random() ** (1.0 / 3.0)


def _stream(seed: int, family: str, object_name: str, case_index: int) -> np.random.Generator:
    """The random stream of one case, from (seed, family, object, case index)."""
    words = [seed, zlib.crc32(family.encode()), zlib.crc32(object_name.encode()), case_index]
    return np.random.default_rng(np.random.SeedSequence(words))


def _sampling_seed(rng: np.random.Generator) -> int:
    """A mesh-sampling seed that is never 0 (the reference's seed)."""
    return int(rng.integers(1, 2**31 - 1))


def _shuffled(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return np.ascontiguousarray(points[rng.permutation(len(points))], dtype=np.float32)


def _paper_pose_indices(object_name: str, seed: int, poses_per_object: int | None) -> np.ndarray:
    """All 125 pose indices, or a deterministic subset of ``poses_per_object`` of them."""
    if poses_per_object is None or poses_per_object >= 125:
        return np.arange(125)
    rng = _stream(seed, "paper-pose-subset", object_name, 0)
    return np.sort(rng.choice(125, size=poses_per_object, replace=False))


def _paper_cases(
    name: str,
    mesh: trimesh.Trimesh,
    n_points: int,
    seed: int,
    pose_indices: np.ndarray,
    keep_shares: tuple[float, ...] | None,
) -> list[Case]:
    poses = paper_poses()
    family = "paper-poses" if keep_shares is None else "sparse"
    cases = []
    for case_index, (pose_index, share) in enumerate(
        itertools.product(pose_indices, keep_shares or (1.0,))
    ):
        rng = _stream(seed, family, name, case_index)
        angles = poses[pose_index]
        rotation = rotation_from_angles(*angles)
        translation = np.zeros(3)
        model = sample_surface(mesh, n_points, _sampling_seed(rng))
        params = {"pose_index": int(pose_index), "angles": tuple(float(a) for a in angles)}
        if keep_shares is not None:
            keep = max(1, int(round(share * n_points)))
            model = model[rng.choice(n_points, size=keep, replace=False)]
            params["keep_share"] = float(share)
        points = _shuffled(place(model, rotation, translation).astype(np.float32), rng)
        cases.append(Case(name, family, points, rotation, translation, params))
    return cases


def _random_case(
    family: str,
    name: str,
    mesh: trimesh.Trimesh,
    scale: float,
    n_points: int,
    seed: int,
    case_index: int,
) -> Case:
    # so3, noisy and partial share the pose of the same case index: the pose stream is so3's.
    pose_rng = _stream(seed, "so3", name, case_index)
    rotation = uniform_rotations(1, pose_rng)[0]
    translation = uniform_in_ball(TRANSLATION_SCALES * scale, pose_rng)
    sampling_seed = _sampling_seed(pose_rng)
    rng = _stream(seed, family, name, case_index)
    params: dict = {"translation_norm_scales": float(np.linalg.norm(translation) / scale)}
    if family == "partial":
        dense = place(
            sample_surface(mesh, DENSE_FACTOR * n_points, sampling_seed), rotation, translation
        ).astype(np.float32)
        centroid = dense.mean(axis=0).astype(np.float64)
        camera = centroid + np.array([0.0, 0.0, CAMERA_DISTANCE_SCALES * scale])
        seen = visible_points(dense, camera)
        visible = dense[seen]
        if len(visible) > n_points:
            visible = visible[rng.choice(len(visible), size=n_points, replace=False)]
        points = _shuffled(visible, rng)
        params.update(visible_share=float(seen.mean()), camera=tuple(float(c) for c in camera))
    else:
        points = place(sample_surface(mesh, n_points, sampling_seed), rotation, translation).astype(
            np.float32
        )
        if family == "noisy":
            sigma = NOISE_SCALE_SHARE * scale
            points = (points + rng.normal(scale=sigma, size=points.shape)).astype(np.float32)
            params["noise_sigma"] = float(sigma)
        points = _shuffled(points, rng)
    return Case(name, family, points, rotation, translation, params)


def _sensor_case(
    family: str, name: str, mesh: trimesh.Trimesh, scale: float, seed: int, case_index: int
) -> Case:
    """A depth camera's view of the part in a uniform rotation, 4-8 scales away."""
    rng = _stream(seed, family, name, case_index)
    rotation = uniform_rotations(1, rng)[0]
    distance_scales = float(rng.uniform(*SENSOR_DISTANCE_SCALES))
    view = sensor_view(mesh, rotation, distance_scales * scale, rng)
    params = {
        "viewpoint": view.viewpoint.tolist(),
        "distance_scales": distance_scales,
        "pixel": view.pixel,
        "view": "sensor",
    }
    return Case(name, family, view.points, view.rotation, view.translation, params)


def _foreign_cases(name: str, mesh, scale: float, n_points: int, seed: int, index: int):
    """An so3 full cloud and a sensor view of a part that is not registered."""
    full = _random_case("foreign", name, mesh, scale, n_points, seed, index)
    full.params["view"] = "full"
    return [full, _sensor_case("foreign", name, mesh, scale, seed, index)]


def _in_millimetres(case: Case) -> Case:
    """The case × UNIT_FACTOR: the cloud and the true translation in the cloud's units."""
    params = {**case.params, "unit_factor": UNIT_FACTOR, "right_refusal": "units"}
    return Case(
        case.object_name,
        "units",
        (case.points * np.float32(UNIT_FACTOR)).astype(np.float32),
        case.rotation,
        case.translation * UNIT_FACTOR,
        params,
    )


def _units_cases(name: str, mesh, scale: float, n_points: int, seed: int, index: int):
    """A registered part's so3 full cloud and sensor view, both in millimetres."""
    full = _random_case("units", name, mesh, scale, n_points, seed, index)
    full.params["view"] = "full"
    sensor = _sensor_case("units", name, mesh, scale, seed, index)
    return [_in_millimetres(full), _in_millimetres(sensor)]


def _table_case(name: str, mesh, scale: float, poses, seed: int, case_index: int) -> Case:
    rng = _stream(seed, "table", name, case_index)
    scene = table_scene(mesh, scale, rng, poses)
    params = {
        "viewpoint": scene.viewpoint.tolist(),
        "pixel": scene.pixel,
        "view": "sensor",
        "plane": scene.plane.tolist(),
        "part_points": int(np.sum(scene.source == PART)),
        "table_points": int(np.sum(scene.source == TABLE)),
        "stray_points": int(np.sum(scene.source == STRAY)),
    }
    return Case(name, "table", scene.points, scene.rotation, scene.translation, params)


def _junk_case(kind: str, sizes: np.ndarray, n_points: int, seed: int, case_index: int) -> Case:
    """A cloud of no part, the size of a registered part, 4-8 sizes in front of the camera."""
    rng = _stream(seed, "junk", kind, case_index)
    size = float(rng.choice(sizes))
    distance = rng.uniform(*SENSOR_DISTANCE_SCALES) * size
    centre = distance * np.array([*rng.uniform(-0.25, 0.25, 2), 1.0])
    points = junk_cloud(kind, size, n_points, rng) + centre
    params = {"kind": kind, "size": size, "view": "full"}
    return Case(f"junk-{kind}", "junk", _shuffled(points, rng), np.eye(3), centre, params)


def symmetric_turns(order: int, rng: np.random.Generator) -> np.ndarray:
    """The angles (radians) one group turns a part by: every 360°/order (at least three turns,
    the last ones coming round again), or 0 and REVOLUTION_TURNS - 1 random angles for a
    revolution (order 0)."""
    if order == 0:
        return np.concatenate([[0.0], rng.uniform(0.0, 2 * np.pi, REVOLUTION_TURNS - 1)])
    return 2 * np.pi * np.arange(max(order, 3)) / order


def _symmetric_group(
    name: str, mesh, scale: float, order: int, n_points: int, seed: int, group: int
) -> list[Case]:
    """One pose of a symmetric part turned about its axis by several angles, as full clouds
    (resampled) and as sensor views from one camera: the same surface in every member."""
    rng = _stream(seed, "symmetric", name, group)
    axis, centre = symmetry_axis(mesh, order), surface_centroid(mesh)
    rotation = uniform_rotations(1, rng)[0]
    distance = float(rng.uniform(*SENSOR_DISTANCE_SCALES)) * scale
    pixel = None  # the first member's, drawn in the middle half of the image
    cases = []
    for member, angle in enumerate(symmetric_turns(order, rng)):
        turn, shift = turn_about(axis, angle, centre)
        turned = rotation @ turn
        view = sensor_view(mesh, turned, distance, rng, pixel)
        pixel = view.pixel  # every member at the same place in the image
        model = sample_surface(mesh, n_points, _sampling_seed(rng))
        full_points = place(model, turned, view.translation)
        params = {
            "order": order,
            "turn_deg": float(np.degrees(angle)),
            "axis": axis.tolist(),
        }
        for kind, points in (("full", full_points), ("sensor", view.points)):
            extra = {"view": kind, "group": f"{name}/{group}/{kind}"}
            if kind == "sensor":
                extra["viewpoint"] = view.viewpoint.tolist()
            params_member = {**params, **extra, "member": member}
            points = _shuffled(points, rng)
            cases.append(Case(name, "symmetric", points, turned, view.translation, params_member))
    return cases


def make_cases(
    family: str,
    meshes: dict[str, trimesh.Trimesh],
    scales: dict[str, float],
    n_points: int = 2048,
    seed: int = 0,
    poses_per_object: int | None = None,
    keep_shares: tuple[float, ...] = KEEP_SHARES,
    orders: dict[str, int] | None = None,
) -> list[Case]:
    """The cases of one family for every object in ``meshes``, the same for the same seed.

    ``scales`` holds each object's scale (the radius of its reference cloud, see
    ``object_scale``). ``poses_per_object`` picks a deterministic subset of the 125 paper poses
    (paper-poses, sparse) or sets the number of random poses (every other family; default
    ``DEFAULT_RANDOM_CASES``): for foreign and units each gives a full cloud and a sensor view,
    for junk it is the number of clouds of each kind (``meshes`` unused, sizes drawn from
    ``scales``), for symmetric the number of groups of each object of ``orders`` (object name
    -> its symmetry's order, 0 for a revolution; the objects of ``meshes`` not in it are left
    out). A case's random stream depends on (seed, family, object name, case index) only, so
    an object's cases do not change with the other objects present.
    """
    if family not in FAMILIES:
        raise ValueError(f"unknown case family {family!r}; pick one of {FAMILIES}")
    count = DEFAULT_RANDOM_CASES if poses_per_object is None else poses_per_object
    cases: list[Case] = []
    if family == "junk":
        sizes = np.array(sorted(scales.values()))
        for index, kind in itertools.product(range(count), JUNK_KINDS):
            cases.append(_junk_case(kind, sizes, n_points, seed, index))
        meshes = {}
    for name, mesh in meshes.items():
        scale = scales[name]
        if family in ("paper-poses", "sparse"):
            indices = _paper_pose_indices(name, seed, poses_per_object)
            shares = tuple(keep_shares) if family == "sparse" else None
            cases.extend(_paper_cases(name, mesh, n_points, seed, indices, shares))
        elif family in FULL_CLOUD_FAMILIES:
            for index in range(count):
                cases.append(_random_case(family, name, mesh, scale, n_points, seed, index))
        elif family == "sensor":
            cases += [_sensor_case(family, name, mesh, scale, seed, i) for i in range(count)]
        elif family == "foreign":
            for index in range(count):
                cases += _foreign_cases(name, mesh, scale, n_points, seed, index)
        elif family == "units":
            for index in range(count):
                cases += _units_cases(name, mesh, scale, n_points, seed, index)
        elif family == "table":
            poses = stable_poses(mesh)
            cases += [_table_case(name, mesh, scale, poses, seed, i) for i in range(count)]
        elif family == "symmetric" and name in (orders or {}):
            for group in range(count):
                cases += _symmetric_group(name, mesh, scale, orders[name], n_points, seed, group)
    for case in cases:
        expected = NO_MATCH if family in ("foreign", "junk") else case.object_name
        case.params.setdefault("expected", expected)
    return cases
