"""Points from a caller, checked: every bad-points class of docs/api.md becomes one
``InvalidPoints``.

The checks run on plain Python lists (what ``orjson.loads`` gives) without a per-point Python
loop, so a 200,000-point body is checked in a few tens of milliseconds.
"""

from __future__ import annotations

from itertools import chain

import numpy as np

from service.engine.normalize import has_extent
from service.engine.principal_axes import bulk_thinness, one_line
from service.engine.tuning import LINE
from service.errors import InvalidPoints

FLOAT32_MAX = float(np.finfo(np.float32).max)
# A coordinate beyond this is refused: the engine squares float32 distances (a cloud's radius,
# its spread), which overflow to infinity past about 1e19 (a registration of a cloud reaching
# 4.5e37 failed with a 500). No sensor measures that far in any unit.
MAX_COORDINATE = 1e18


def validate_points(points: object, min_points: int, max_points: int) -> np.ndarray:
    """Check caller-given points and return them as an (N, 3) float32 array.

    ``points`` is a list of ``[x, y, z]`` lists (parsed JSON) or an array of shape (N, 3).
    Raises ``InvalidPoints`` naming the first problem found.
    """
    if isinstance(points, list | tuple):  # count first: a list over the maximum is not converted
        _check_count(len(points), min_points, max_points)
    array = _as_array(points)
    _check_count(len(array), min_points, max_points)
    return _check_values(array)


def points_from_raw(body: bytes, min_points: int, max_points: int) -> np.ndarray:
    """Little-endian float32 ``x y z`` triples, 12 bytes a point, as an (N, 3) float32 array."""
    if len(body) == 0:
        raise InvalidPoints("the body is empty: send little-endian float32 x y z triples")
    if len(body) % 12:
        raise InvalidPoints(
            f"the body is {len(body)} bytes, not a multiple of 12: send little-endian "
            "float32 x y z triples (12 bytes a point)"
        )
    _check_count(len(body) // 12, min_points, max_points)
    array = np.frombuffer(body, dtype="<f4").reshape(-1, 3)
    return _check_values(array)


def _as_array(points: object) -> np.ndarray:
    """(N, 3) float64 from a list of triples, or an (N, 3) numeric array, or InvalidPoints."""
    if isinstance(points, np.ndarray):
        if points.ndim != 2 or points.shape[1] != 3:
            raise InvalidPoints(f"points must have shape (N, 3), not {points.shape}")
        if points.dtype.kind not in "iuf":
            raise InvalidPoints(f"points must be numbers, not {points.dtype}")
        return points
    if not isinstance(points, list | tuple):
        raise InvalidPoints(f"points must be a list of [x, y, z] triples, not {_kind(points)}")
    if len(points) == 0:
        raise InvalidPoints("points is empty: send a list of [x, y, z] triples")
    if not set(map(type, points)) <= {list, tuple}:
        index = next(i for i, p in enumerate(points) if not isinstance(p, list | tuple))
        raise InvalidPoints(
            f"points[{index}] is {_kind(points[index])}, not a triple of numbers [x, y, z]"
        )
    if set(map(len, points)) != {3}:
        index = next(i for i, p in enumerate(points) if len(p) != 3)
        count = len(points[index])
        raise InvalidPoints(
            f"points[{index}] has {count} value{'s' * (count != 1)}, not three numbers [x, y, z]"
        )
    flat = list(chain.from_iterable(points))
    # bool is a subclass of int, and numpy would read "1.5" as a number: allow exact types only
    if not set(map(type, flat)) <= {int, float}:
        index, axis = next(
            (i, j)
            for i, p in enumerate(points)
            for j, value in enumerate(p)
            if type(value) not in (int, float)
        )
        raise InvalidPoints(
            f"points[{index}][{axis}] is {_kind(points[index][axis])}, not a number"
        )
    try:
        return np.fromiter(flat, dtype=np.float64, count=len(flat)).reshape(-1, 3)
    except OverflowError as error:  # an integer beyond float64
        raise InvalidPoints("a coordinate is too large for a 32-bit float") from error


def _check_count(count: int, min_points: int, max_points: int) -> None:
    if count == 0:
        raise InvalidPoints("points is empty: send a list of [x, y, z] triples")
    if count < min_points:
        raise InvalidPoints(f"{count} points given, fewer than the minimum of {min_points}")
    if count > max_points:
        raise InvalidPoints(
            f"{count} points given, more than the maximum of {max_points}: subsample the cloud"
        )


def _check_values(array: np.ndarray) -> np.ndarray:
    """Finite, within ``MAX_COORDINATE``, not all one point; returns a float32 copy or view."""
    if not np.isfinite(array).all():
        index = int(np.argmin(np.isfinite(array).all(axis=1)))
        raise InvalidPoints(
            f"points[{index}] is {array[index].tolist()}: NaN and infinity are not allowed; "
            "drop invalid points before sending"
        )
    magnitude = float(np.abs(array).max())
    if magnitude > FLOAT32_MAX:
        raise InvalidPoints(f"a coordinate ({magnitude:g}) is too large for a 32-bit float")
    if magnitude > MAX_COORDINATE:
        raise InvalidPoints(
            f"a coordinate ({magnitude:g}) is beyond {MAX_COORDINATE:g}, where the service's "
            "32-bit arithmetic overflows: send the cloud in metres or millimetres"
        )
    points = np.ascontiguousarray(array, dtype=np.float32)
    sample = points[:: -(-len(points) // SHAPE_SAMPLE)]  # every k-th: at most SHAPE_SAMPLE
    if len(sample) < len(points) and _shaped(sample, magnitude, SHAPE_MARGIN):
        return points  # far from either refusal on the sample: the whole cloud is too
    _shaped(points, magnitude, 1.0, refuse=True)
    return points


# The shape checks look at every k-th point of a larger cloud (docs/decisions.md#at-camera-scale);
# a
# cloud this close to a refusal on the sample is checked on every point
SHAPE_SAMPLE = 8192
SHAPE_MARGIN = 10.0


def _shaped(points: np.ndarray, magnitude: float, margin: float, refuse: bool = False) -> bool:
    """Whether ``points`` have ``margin`` times the extent, and the thickness across their
    line, that a refusal needs; with ``refuse``, the refusal instead of False."""
    centred = points - points.mean(axis=0, dtype=np.float64)  # float64
    radius = float(np.sqrt(np.einsum("ij,ij->i", centred, centred).max()))
    if not has_extent(radius / margin, magnitude):
        if refuse:
            raise InvalidPoints(
                f"all points are (nearly) the same (radius {radius:.3g}): the cloud has no "
                "scale to align"
            )
        return False
    if (thin := bulk_thinness(centred)) < margin * LINE:
        if refuse:
            raise InvalidPoints(one_line(len(points), thin))
        return False
    return True


def _kind(value: object) -> str:
    """How a JSON value reads to the caller: 'a string', 'a boolean', 'null', ..."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, dict):
        return "an object"
    if isinstance(value, list | tuple):
        return "a list"
    if isinstance(value, int | float):
        return "a number"
    return type(value).__name__
