"""Training clouds: fresh surface samples of the objects, the rotations, and the triplets.

Every epoch draws a new pool of surface points per object (seeded by the run's
seed, the epoch and the object), and every training cloud is a random subset of
its pool, so the network never sees the same points twice.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from service.engine.normalize import normalize
from service.engine.sampling import sample_surface

PAPER_STEP = np.pi / 24  # the paper's training angles: 0 to pi/2 in pi/24 steps about x, y, z


@dataclass
class DataConfig:
    points: int = 1024  # points per training cloud
    pool: int = 8192  # surface points sampled per object and epoch
    rotations: Literal["paper", "so3"] = (
        "so3"  # "paper": the paper's pi/24 grid about x, y, z; "so3": uniform
    )
    jitter: float = 0.01  # delta of the positive cloud, as a share of the radius
    canonical: bool = True  # rotate inputs into their principal-axes frame first
    shared: float = 0.5  # share of the rotated cloud's points that are the anchor's (paper: 1)
    noise: float = 0.0  # Gaussian noise on the rotated cloud, as a share of the radius


def paper_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation about x, then y, then z by angles on the paper's training grid."""
    angles = rng.integers(0, 13, size=3) * PAPER_STEP
    return Rotation.from_euler("xyz", angles).as_matrix()


def random_rotation(mode: str, rng: np.random.Generator) -> np.ndarray:
    if mode == "paper":
        return paper_rotation(rng)
    if mode == "so3":
        return Rotation.random(random_state=rng).as_matrix()
    raise ValueError(f"unknown rotation mode {mode!r}: use 'paper' or 'so3'")


class TrainingClouds:
    """Anchor, positive and rotated clouds of the objects, as the losses need them."""

    def __init__(self, meshes: dict[str, trimesh.Trimesh], config: DataConfig, seed: int):
        self.names = sorted(meshes)
        self.meshes = meshes
        self.config = config
        self.seed = seed
        self.pools: dict[str, np.ndarray] = {}

    def start_epoch(self, epoch: int) -> None:
        for index, name in enumerate(self.names):
            seed = (self.seed * 1_000_003 + epoch * 1009 + index) % 2**31 + 1
            self.pools[name] = sample_surface(self.meshes[name], self.config.pool, seed)

    def triplet(self, name: str, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
        """(anchor, positive, rotated) network inputs of one cloud, each (N, 3) float32.

        The anchor is the object in its standard pose; the positive moves each anchor
        point by a small random delta; the rotated cloud is the anchor's first
        ``shared_rows`` points turned by a training rotation, completed by other
        surface points (the paper: all of them the anchor's). Each cloud is
        normalised on its own, as the service will. With ``shared < 1`` the pose
        loss also teaches the mapping to ignore which other points were sampled,
        as an independently resampled observation needs; with ``canonical`` and
        all points shared, the rotated input would equal the anchor's exactly.
        """
        pool = self.pools[name]
        count = self.config.points
        chosen = rng.choice(len(pool), size=2 * count - self.shared_rows, replace=False)
        points = pool[chosen[:count]]
        anchor = normalize(points, self.config.canonical)
        jitter = rng.normal(scale=self.config.jitter / np.sqrt(3), size=points.shape)
        positive = (anchor.points + jitter).astype(np.float32)
        view = np.concatenate([points[: self.shared_rows], pool[chosen[count:]]])
        if self.config.noise > 0:
            view = view + rng.normal(scale=self.config.noise * anchor.scale, size=view.shape)
        rotation = random_rotation(self.config.rotations, rng)
        rotated = normalize(view @ rotation.T, self.config.canonical)
        return anchor.points, positive, rotated.points

    @property
    def shared_rows(self) -> int:
        """How many leading rows the anchor and the rotated cloud have in common."""
        return max(1, round(self.config.shared * self.config.points))

    def batch(self, names: list[str], seeds: list) -> tuple[np.ndarray, ...]:
        """Stacked (B, N, 3) anchors, positives and rotated clouds, each cloud drawn with its
        own seed: the same cloud whichever rank, or which batch of a rank, draws it."""
        triplets = [
            self.triplet(name, np.random.default_rng(seed))
            for name, seed in zip(names, seeds, strict=True)
        ]
        return tuple(np.stack(part) for part in zip(*triplets, strict=True))
