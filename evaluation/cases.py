"""The case families of shared/EVALUATION.md, deterministic given a seed.

Each case is an object's mesh resampled with a seed of its own (never seed 0, the
reference's), moved by a known pose ``scene = R @ model + t`` and shuffled:

- ``paper-poses``: rotations about x, y and z by 0, π/10, ..., 4π/10 each (125 poses),
  translation 0, as the paper's test set;
- ``sparse``: the paper's poses keeping a share of the points at random (paper's Fig. 5);
- ``so3``: a rotation uniform over SO(3) and a translation uniform in a ball of radius
  twice the scale;
- ``noisy``: the ``so3`` case of the same index (same pose) plus Gaussian noise of σ = 1 % of
  the scale on every coordinate;
- ``partial``: the ``so3`` case of the same index (same pose), keeping only the points a
  single depth camera looking down the scene's -z axis would see (hidden-point removal).
"""

from __future__ import annotations

import itertools
import zlib
from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from evaluation.metrics import place
from service.engine.normalize import radius
from service.engine.sampling import sample_surface
from service.engine.visibility import visible_points

FAMILIES = ("paper-poses", "sparse", "so3", "noisy", "partial")

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


def make_cases(
    family: str,
    meshes: dict[str, trimesh.Trimesh],
    scales: dict[str, float],
    n_points: int = 2048,
    seed: int = 0,
    poses_per_object: int | None = None,
    keep_shares: tuple[float, ...] = KEEP_SHARES,
) -> list[Case]:
    """The cases of one family for every object in ``meshes``, the same for the same seed.

    ``scales`` holds each object's scale (the radius of its reference cloud, see
    ``object_scale``). ``poses_per_object`` picks a deterministic subset of the 125 paper poses
    (paper-poses, sparse) or sets the number of random poses (so3, noisy, partial; default
    ``DEFAULT_RANDOM_CASES``). A case's random stream depends on (seed, family, object name,
    case index) only, so an object's cases do not change with the other objects present.
    """
    if family not in FAMILIES:
        raise ValueError(f"unknown case family {family!r}; pick one of {FAMILIES}")
    cases: list[Case] = []
    for name, mesh in meshes.items():
        if family in ("paper-poses", "sparse"):
            indices = _paper_pose_indices(name, seed, poses_per_object)
            shares = tuple(keep_shares) if family == "sparse" else None
            cases.extend(_paper_cases(name, mesh, n_points, seed, indices, shares))
        else:
            count = DEFAULT_RANDOM_CASES if poses_per_object is None else poses_per_object
            for case_index in range(count):
                cases.append(
                    _random_case(family, name, mesh, scales[name], n_points, seed, case_index)
                )
    return cases
