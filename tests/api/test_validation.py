"""Every bad-points class of docs/api.md is refused with a message naming it; good points pass."""

import numpy as np
import pytest

from service.api.validation import points_from_raw, validate_points
from service.errors import InvalidPoints
from tests.servers import cloud

LIMITS = {"min_points": 4, "max_points": 100}


def test_a_list_of_triples_becomes_float32():
    points = cloud(10).tolist()
    array = validate_points(points, **LIMITS)
    assert array.shape == (10, 3) and array.dtype == np.float32
    np.testing.assert_allclose(array, np.array(points), rtol=1e-6)


def test_integers_and_arrays_are_numbers():
    integers = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
    assert validate_points(integers, **LIMITS).tolist() == integers
    assert validate_points(np.array(integers), **LIMITS).dtype == np.float32


@pytest.mark.parametrize(
    ("points", "words"),
    [
        ([], "empty"),
        (cloud(3).tolist(), "fewer than the minimum of 4"),
        (cloud(101).tolist(), "more than the maximum of 100"),
        ({"x": 1}, "list of [x, y, z] triples"),
        ("1 2 3", "list of [x, y, z] triples"),
        ([*cloud(5).tolist(), [1.0, 2.0]], "points[5] has 2 values"),
        ([*cloud(5).tolist(), [1.0, 2.0, 3.0, 4.0]], "points[5] has 4 values"),
        ([*cloud(5).tolist(), 7.0], "points[5] is a number"),
        ([*cloud(5).tolist(), [[1.0, 2.0, 3.0]]], "points[5] has 1 value,"),
        ([*cloud(5).tolist(), [1.0, [2.0], 3.0]], "points[5][1] is a list"),
        ([*cloud(5).tolist(), [1.0, "2", 3.0]], "points[5][1] is a string"),
        ([*cloud(5).tolist(), [True, 2.0, 3.0]], "points[5][0] is a boolean"),
        ([*cloud(5).tolist(), [1.0, None, 3.0]], "points[5][1] is null"),
        ([*cloud(5).tolist(), [1.0, 2.0, float("nan")]], "NaN and infinity"),
        ([*cloud(5).tolist(), [1.0, float("-inf"), 3.0]], "NaN and infinity"),
        ([*cloud(5).tolist(), [1e39, 0.0, 0.0]], "too large for a 32-bit float"),
        ([*cloud(5).tolist(), [10**400, 0, 0]], "too large for a 32-bit float"),
        ([*cloud(5).tolist(), [4.47709384069477e37, 0.0, 0.0]], "beyond 1e+18"),  # a 500 once
        ([[1.0, 2.0, 3.0]] * 8, "(nearly) the same"),
        ([[1000.0, 2.0, 3.0]] * 7 + [[1000.0, 2.0, 3.0000001]], "(nearly) the same"),
    ],
)
def test_bad_points_are_named(points, words):
    with pytest.raises(InvalidPoints) as caught:
        validate_points(points, **LIMITS)
    assert words in str(caught.value)


@pytest.mark.parametrize(
    ("array", "words"),
    [
        (np.zeros((10, 2)), "shape (N, 3)"),
        (np.zeros((10, 3), dtype=bool), "must be numbers"),
        (np.zeros((0, 3)), "empty"),
    ],
)
def test_bad_arrays_are_named(array, words):
    with pytest.raises(InvalidPoints, match=words.replace("(", r"\(").replace(")", r"\)")):
        validate_points(array, **LIMITS)


def test_a_small_object_far_away_keeps_its_scale():
    points = (np.random.default_rng(1).normal(size=(20, 3)) * 0.01 + 100.0).tolist()
    assert validate_points(points, **LIMITS).shape == (20, 3)


def test_raw_float32_triples():
    points = np.random.default_rng(2).normal(size=(12, 3)).astype("<f4")
    np.testing.assert_array_equal(points_from_raw(points.tobytes(), **LIMITS), points)


@pytest.mark.parametrize(
    ("body", "words"),
    [
        (b"", "empty"),
        (b"\0" * 13, "13 bytes, not a multiple of 12"),
        (np.zeros((3, 3), "<f4").tobytes(), "fewer than the minimum"),
        (np.zeros((101, 3), "<f4").tobytes(), "more than the maximum"),
        (np.full((5, 3), np.nan, "<f4").tobytes(), "NaN"),
        (np.ones((5, 3), "<f4").tobytes(), "(nearly) the same"),
    ],
)
def test_bad_raw_bodies_are_named(body, words):
    with pytest.raises(InvalidPoints) as caught:
        points_from_raw(body, **LIMITS)
    assert words in str(caught.value)


BIG = {"min_points": 4, "max_points": 300_000}


def test_a_large_cloud_is_shape_checked_as_a_small_one():
    """Every k-th point of a large cloud decides; one near a refusal is checked on every point:
    a line, one place, and a blob whose only other points lie between the sampled ones."""
    rng = np.random.default_rng(3)
    line = np.zeros((40_000, 3))
    line[:, 0] = rng.uniform(0, 1, len(line))
    place = np.full((40_000, 3), 5.0)
    place[1::2] += 1e-9  # between the sampled points, no more extent than float32 keeps
    blob = rng.normal(size=(40_000, 3))
    for points, words in ((line, "one line"), (place, "(nearly) the same")):
        with pytest.raises(InvalidPoints) as caught:
            points_from_raw(points.astype("<f4").tobytes(), **BIG)
        assert words in str(caught.value)
    assert points_from_raw(blob.astype("<f4").tobytes(), **BIG).shape == (40_000, 3)
    # a line except at points the sample skips: the sample sees a line, every point decides
    nearly = line.copy()
    nearly[1::5, 1:] = rng.normal(size=(len(nearly[1::5]), 2))
    assert validate_points(nearly, **BIG).shape == (40_000, 3)
