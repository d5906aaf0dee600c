"""Training clouds: fresh surface samples of the objects, the rotations, and the triplets.

Every epoch draws a new pool of surface points per object (seeded by the run's
seed, the epoch and the object), and every training cloud is a random subset of
its pool, so the network never sees the same points twice.

A triplet is either of the whole surface (the anchor and a rotated resample of it) or, with
probability ``single_views``, of what cameras see: the anchor is one camera's view of the pool,
the rotated cloud a second camera's view of the same pool (hidden-point removal,
``service.engine.visibility``), and eq. (2) compares the points both views hold.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from service.engine.normalize import normalize
from service.engine.sampling import sample_surface
from service.engine.visibility import visible_points

PAPER_STEP = np.pi / 24  # the paper's training angles: 0 to pi/2 in pi/24 steps about x, y, z
CAMERA_DISTANCE = (4.0, 8.0)  # single views: the camera this many radii from the centroid


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
    single_views: float = 0.0  # share of triplets that are two cameras' views of the part
    view_angle: float = 60.0  # single views: the second camera within this many degrees
    view_partner: Literal["view", "whole"] = (
        "view"  # single views: the rotated cloud is a second camera's view, or the whole surface
    )


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
        """(anchor, positive, rotated, shared) of one cloud: three (N, 3) float32 network
        inputs and an (N,) bool mask of the rows that are the same surface point in the anchor
        and the rotated cloud (what eq. (2) compares); with probability ``single_views`` a
        pair of camera views (``view_pair``), else the whole surface (``full_pair``)."""
        if self.config.single_views > 0 and rng.random() < self.config.single_views:
            points, view, shared = self.view_pair(name, rng)
        else:
            points, view, shared = self.full_pair(name, rng)
        anchor = normalize(points, self.config.canonical)
        jitter = rng.normal(scale=self.config.jitter / np.sqrt(3), size=points.shape)
        positive = (anchor.points + jitter).astype(np.float32)
        if self.config.noise > 0:
            view = view + rng.normal(scale=self.config.noise * anchor.scale, size=view.shape)
        rotation = random_rotation(self.config.rotations, rng)
        rotated = normalize(view @ rotation.T, self.config.canonical)
        return anchor.points, positive, rotated.points, shared

    def full_pair(self, name: str, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
        """The anchor (the object in its standard pose) and the view to be rotated, in the
        object's frame, and their shared rows: the view is the anchor's first ``shared_rows``
        points completed by other surface points (the paper: all of them the anchor's).
        Each cloud is normalised on its own, as the service will. With ``shared < 1`` the
        pose loss also teaches the mapping to ignore which other points were sampled, as an
        independently resampled observation needs; with ``canonical`` and all points shared,
        the rotated input would equal the anchor's exactly.
        """
        pool = self.pools[name]
        count = self.config.points
        chosen = rng.choice(len(pool), size=2 * count - self.shared_rows, replace=False)
        points = pool[chosen[:count]]
        view = np.concatenate([points[: self.shared_rows], pool[chosen[count:]]])
        shared = np.arange(count) < self.shared_rows
        return points, view, shared

    def view_pair(self, name: str, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
        """What two cameras see of the pool, in the object's frame, and their shared rows.

        The first camera is 4-8 radii from the centroid in a uniformly random direction, the
        second as far (drawn anew) within ``view_angle`` degrees of it; with ``view_partner``
        "whole", the second cloud is of the whole surface instead (what the engine pairs a
        view with: the whole reference). Every pool point gets one random rank; each cloud is
        the ``points`` best-ranked points its camera sees, so each is a uniform subsample of
        its own view and they hold in common the points of the overlap that both kept. Those
        come first, in the same order in both clouds; a view with fewer visible points than
        ``points`` is padded by repeating its own points.
        """
        pool = self.pools[name]
        count = self.config.points
        centroid = pool.mean(axis=0)
        reach = np.linalg.norm(pool - centroid, axis=1).max()
        first = unit_vector(rng)
        second = direction_within(first, self.config.view_angle, rng)
        ranks = rng.permutation(len(pool))  # ranks[i]: pool point i's place in the draw
        kept = []
        for direction in (first, second):
            camera = centroid + direction * rng.uniform(*CAMERA_DISTANCE) * reach
            if direction is second and self.config.view_partner == "whole":
                seen = np.arange(len(pool))
            else:
                seen = np.flatnonzero(visible_points(pool, camera))
            kept.append(seen[np.argsort(ranks[seen], kind="stable")[:count]])
        both = np.intersect1d(kept[0], kept[1])
        both = both[rng.permutation(len(both))]
        clouds = [pad(np.concatenate([both, np.setdiff1d(own, both)]), count, rng) for own in kept]
        shared = np.arange(count) < len(both)
        return pool[clouds[0]], pool[clouds[1]], shared

    @property
    def shared_rows(self) -> int:
        """How many leading rows the anchor and the rotated cloud have in common."""
        return max(1, round(self.config.shared * self.config.points))

    def batch(self, names: list[str], seeds: list) -> tuple[np.ndarray, ...]:
        """Stacked (B, N, 3) anchors, positives and rotated clouds and (B, N) shared rows, each
        cloud drawn with its own seed: the same cloud whichever rank, or which batch of a rank,
        draws it."""
        triplets = [
            self.triplet(name, np.random.default_rng(seed))
            for name, seed in zip(names, seeds, strict=True)
        ]
        return tuple(np.stack(part) for part in zip(*triplets, strict=True))


def unit_vector(rng: np.random.Generator) -> np.ndarray:
    """A direction uniform on the sphere."""
    direction = rng.normal(size=3)
    return direction / np.linalg.norm(direction)


def direction_within(axis: np.ndarray, degrees: float, rng: np.random.Generator) -> np.ndarray:
    """A direction uniform on the spherical cap of ``degrees`` about the unit vector ``axis``."""
    cosine = rng.uniform(np.cos(np.radians(degrees)), 1.0)
    turn = rng.uniform(0.0, 2 * np.pi)
    helper = np.eye(3)[np.argmin(np.abs(axis))]  # the coordinate axis least along ``axis``
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    sine = np.sqrt(1.0 - cosine**2)
    return cosine * axis + sine * (np.cos(turn) * u + np.sin(turn) * v)


def pad(rows: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """``rows`` (at most ``count``) completed to ``count`` by repeating some of them at random."""
    if len(rows) >= count:
        return rows[:count]
    return np.concatenate([rows, rng.choice(rows, size=count - len(rows))])
