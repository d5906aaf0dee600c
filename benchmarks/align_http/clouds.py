"""The benchmark's requests: clouds of the shipped references, resampled and moved.

``--clouds-per-object`` clouds of each of the first 40 shipped references (of the first N when a
size N under 40 is measured), 2,048 points each, never the registered points: 2,048 of the
reference's points drawn at random (with replacement), each moved within the surface's tangent
plane (the reference's stored normals) by Gaussian jitter of one point spacing (the median
distance to the nearest other point); then moved by a random rotation (uniform over SO(3)) and a
translation in a random direction of up to twice the reference's scale, and shuffled. Seeded by
``--seed``, the reference's index and the cloud's index. Consecutive requests ask for different
parts. Such a cloud stands for an independent sample of the mesh's surface (the evaluation's
``so3`` family, which needs pybullet's meshes): on 14-20 shipped parts, against fresh samples of
their meshes, the engine's fit and coverage agreed within 0.01 and its median time within about
10 %. With half a spacing the points drawn twice stay clumped: coverage fell to 0.96 and the
mean time rose by a third (by 2.5-3 times before the surroundings' change of ``ce892a6``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import orjson
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from service.engine.reference import Reference

CLOUD_POINTS = 2048
JITTER_SPACINGS = 1.0  # tangential jitter of a resampled point, in point spacings
JSON_TYPE = {"content-type": "application/json"}
RAW_TYPE = {"content-type": "application/octet-stream"}


@dataclass
class Cloud:
    """One request: ``points`` = R @ (a resample of reference ``label``) + t, shuffled."""

    label: str
    points: np.ndarray  # (M, 3) float32
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    json_body: bytes
    raw_body: bytes

    def body(self, kind: str) -> tuple[bytes, dict[str, str]]:
        return (self.raw_body, RAW_TYPE) if kind == "raw" else (self.json_body, JSON_TYPE)


def point_spacing(points: np.ndarray) -> float:
    """The median distance from a point to its nearest other point."""
    distances, _ = cKDTree(points).query(points, k=2)
    return float(np.median(distances[:, 1]))


def resample(
    points: np.ndarray, normals: np.ndarray | None, count: int, rng: np.random.Generator
) -> np.ndarray:
    """``count`` points of the same surface, none of them one of ``points``: points drawn at
    random and each moved by Gaussian jitter of ``JITTER_SPACINGS`` point spacings, within its
    tangent plane where ``normals`` are known (everywhere otherwise, by a third as much)."""
    points = np.asarray(points, dtype=np.float64)
    spacing = point_spacing(points)
    chosen = rng.integers(0, len(points), count)
    jitter = rng.normal(scale=JITTER_SPACINGS * spacing, size=(count, 3))
    if normals is None:
        jitter /= 3
    else:
        normal = np.asarray(normals, dtype=np.float64)[chosen]
        jitter -= np.sum(jitter * normal, axis=1, keepdims=True) * normal
    return points[chosen] + jitter


def make_clouds(
    references: list[Reference], clouds_per_object: int, seed: int, count: int = CLOUD_POINTS
) -> list[Cloud]:
    """The benchmark's clouds (module docstring) of ``count`` points each: round after round of
    one cloud of each reference, so consecutive requests ask for different parts."""
    clouds = []
    for k in range(clouds_per_object):
        for index, reference in enumerate(references):
            rng = np.random.default_rng([seed, index, k])
            sample = resample(reference.points, reference.normals, count, rng)
            rotation = Rotation.random(random_state=rng).as_matrix()
            direction = rng.normal(size=3)
            translation = (
                direction / np.linalg.norm(direction) * rng.uniform(0, 2) * reference.scale
            )
            moved = (sample @ rotation.T + translation)[rng.permutation(count)]
            clouds.append(encode(reference.name, moved, rotation, translation))
    return clouds


def encode(label: str, points: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> Cloud:
    points = np.asarray(points, dtype=np.float32)
    # six decimals (a micrometre in metres), as a client that writes its own JSON would send
    json_body = orjson.dumps({"points": np.round(points.astype(np.float64), 6).tolist()})
    return Cloud(label, points, rotation, translation, json_body, points.astype("<f4").tobytes())
