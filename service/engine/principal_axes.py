"""Principal-axes frames of a cloud, and the pose hypotheses they give.

The eigenvectors of a cloud's covariance turn with the object, so matching the
frames of the observation and of the reference gives a rotation up to the sign
of each axis: four proper (determinant +1) choices.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial.transform import Rotation

from service.engine.tuning import ROUND_SPREADS, ROUND_TURN_DEG

# The four sign patterns of a right-handed frame: diag(s) with det = +1.
PROPER_SIGN_FLIPS = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=np.float64)


def principal_axes(centred: np.ndarray) -> np.ndarray:
    """(3, 3) matrix whose columns are the principal axes, largest variance first, det +1."""
    covariance = centred.T @ centred / max(len(centred), 1)
    _, vectors = np.linalg.eigh(covariance)  # ascending eigenvalues
    axes = vectors[:, ::-1].copy()
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    return axes


@dataclass(frozen=True)
class Frame:
    """A cloud's centroid and principal axes, found once for every hypothesis that uses them."""

    centroid: np.ndarray  # (3,)
    axes: np.ndarray  # (3, 3) columns, largest variance first (``principal_axes``)
    spreads: np.ndarray  # (3,) the standard deviation along each axis

    @classmethod
    def of(cls, points: np.ndarray) -> Frame:
        centroid = points.mean(axis=0)
        centred = points - centroid
        axes = principal_axes(centred)
        spreads = np.sqrt(np.maximum(np.mean((centred @ axes) ** 2, axis=0), 0.0))
        return cls(centroid, axes, spreads)

    @cached_property
    def half_turns(self) -> np.ndarray:
        """(3, 3, 3) the half turns about each principal axis: what the signs of two axes of a
        matched frame flip."""
        return np.stack([2 * np.outer(axis, axis) - np.eye(3) for axis in self.axes.T])

    @cached_property
    def quarter_turns(self) -> np.ndarray:
        """(9, 3, 3) the turns by a quarter, a half and three quarters about each principal
        axis."""
        angles = np.radians([90.0, 180.0, 270.0])
        vectors = angles[None, :, None] * self.axes.T[:, None, :]  # (3 axes, 3 angles, 3)
        return Rotation.from_rotvec(vectors.reshape(-1, 3)).as_matrix()

    @cached_property
    def matched(self) -> np.ndarray:
        """(K, 3, 3) the frames the principal-axes hypotheses carry onto an observation's:
        this frame, and where two spreads are alike (``ROUND_SPREADS``) this frame turned about
        the third axis by every ``ROUND_TURN_DEG``: those two axes are then any two in their
        plane. A pose R turned by T about the axis (model frame) carries the frame T^T A."""
        unique = self.round_axis()
        if unique is None:
            return self.axes[None]
        axis = self.axes[:, unique]
        angles = np.radians(np.arange(ROUND_TURN_DEG, 180.0, ROUND_TURN_DEG))
        turns = Rotation.from_rotvec(angles[:, None] * axis[None]).as_matrix()
        return np.concatenate([self.axes[None], np.transpose(turns, (0, 2, 1)) @ self.axes])

    def round_about(self, k: int) -> bool:
        """Whether the two spreads other than axis ``k``'s differ by at most ``ROUND_SPREADS``
        of the larger: their axes are then any two in their plane."""
        a, b = np.delete(self.spreads, k)
        return abs(a - b) <= ROUND_SPREADS * max(a, b)

    def round_axis(self) -> int | None:
        """The largest or smallest axis the part is round about (``round_about``), if any."""
        return next((k for k in (2, 0) if self.round_about(k)), None)


def flatness(points: np.ndarray) -> float:
    """How flat a cloud is: its smallest principal spread over its largest (0: one plane)."""
    centred = points - points.mean(axis=0)
    variances = np.linalg.eigvalsh(centred.T @ centred / max(len(centred), 1))
    return float(np.sqrt(max(variances[0], 0.0) / max(variances[2], 1e-300)))


def thinness(centred: np.ndarray) -> float:
    """How straight a centred cloud is: its middle principal spread over its largest (0: one
    line)."""
    variances = np.linalg.eigvalsh(centred.T @ centred / max(len(centred), 1))
    return float(np.sqrt(max(variances[1], 0.0) / max(variances[2], 1e-300)))


def bulk_thinness(centred: np.ndarray, share: float = 0.95) -> float:
    """``thinness`` of the ``share`` of points nearest their median where the whole cloud reads
    as a line: one far stray point makes a blob read as one."""
    thin = thinness(centred)
    if thin >= 1e-2 or len(centred) < 20:
        return thin
    distance = np.linalg.norm(centred - np.median(centred, axis=0), axis=1)
    bulk = centred[distance <= np.quantile(distance, share)]
    return max(thin, thinness(bulk - bulk.mean(axis=0)))


def one_line(count: int, thin: float) -> str:
    """Why ``count`` points of ``thinness`` ``thin`` (under ``tuning.LINE``) give no pose."""
    return (
        f"the {count} points lie on one line (across it they spread {thin:.1e} of their "
        "length): a line does not fix the turn about itself, so no part can be posed on it; "
        "send points of the part's surface"
    )


def principal_frame(centred: np.ndarray) -> np.ndarray:
    """Principal axes with each sign chosen so the cloud's third moment along it is positive.

    That makes the frame follow the object (it turns with the object) except where
    the object is nearly symmetric along an axis; the third axis is the cross
    product of the first two, so the frame stays a rotation.
    """
    axes = principal_axes(centred)
    coordinates = centred @ axes
    skew = (coordinates[:, :2] ** 3).mean(axis=0)
    for k in range(2):
        if skew[k] < 0:
            axes[:, k] *= -1
    axes[:, 2] = np.cross(axes[:, 0], axes[:, 1])
    return axes
