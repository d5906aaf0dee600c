"""Property-based: whatever a caller sends, the point readers answer points or ``InvalidPoints``
(a 422), never another exception. JSON values, raw float32 bodies, random files of every
kind, and valid PLY / PCD / NPY / STL / OBJ files with random damage."""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh
from fastapi.exceptions import RequestValidationError
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pypcd4 import Encoding, PointCloud

from service.api.parsers import read_points
from service.api.routes.common import json_object
from service.api.validation import points_from_raw, validate_points
from service.errors import InvalidPoints

FUZZ = settings(
    max_examples=150,
    deadline=None,
    database=None,  # no .hypothesis folder in the tree
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
MIN_POINTS, MAX_POINTS = 3, 10_000

numbers = (
    st.floats(allow_nan=True, allow_infinity=True)
    | st.floats(min_value=-1e3, max_value=1e3)
    | st.integers(min_value=-(2**70), max_value=2**70)
)
scalars = numbers | st.none() | st.booleans() | st.text(max_size=4)
json_values = st.recursive(
    scalars,
    lambda inner: (
        st.lists(inner, max_size=6) | st.dictionaries(st.text(max_size=3), inner, max_size=3)
    ),
    max_leaves=40,
)
triples = st.lists(st.lists(numbers, min_size=3, max_size=3), min_size=0, max_size=60)
near_triples = st.lists(st.lists(scalars, min_size=2, max_size=4), min_size=0, max_size=40)


def checked(points: object) -> None:
    """What the service keeps of accepted points: finite float32 (N, 3) within the limits."""
    assert isinstance(points, np.ndarray) and points.dtype == np.float32
    assert points.ndim == 2 and points.shape[1] == 3
    assert MIN_POINTS <= len(points) <= MAX_POINTS
    assert np.isfinite(points).all()


def accept_or_refuse(read, *args) -> None:
    try:
        points = read(*args)
    except InvalidPoints as refusal:
        assert str(refusal), "a refusal names the problem"
        return
    try:
        checked(validate_points(points, MIN_POINTS, MAX_POINTS))
    except InvalidPoints as refusal:
        assert str(refusal)


@FUZZ
@given(json_values | triples | near_triples)
def test_json_points(value):
    accept_or_refuse(lambda v: v, value)


@FUZZ
@given(st.binary(max_size=400))
def test_raw_float32_bodies(body):
    try:
        points = points_from_raw(body, MIN_POINTS, MAX_POINTS)
    except InvalidPoints:
        return
    checked(points)


@FUZZ
@given(st.lists(st.floats(width=32, allow_nan=True, allow_infinity=True), max_size=90))
def test_raw_float32_values(values):
    body = np.asarray(values, dtype="<f4").tobytes()
    try:
        points = points_from_raw(body, MIN_POINTS, MAX_POINTS)
    except InvalidPoints:
        return
    checked(points)
    np.testing.assert_array_equal(points.reshape(-1), np.asarray(values, dtype=np.float32))


@FUZZ
@given(st.binary(max_size=300) | json_values.map(lambda v: repr(v).encode()))
def test_json_bodies(body):
    try:
        data = json_object(body)
    except RequestValidationError:
        return
    assert isinstance(data, dict)


SUFFIXES = [None, "a.stl", "a.obj", "a.ply", "a.pcd", "a.npy", "upload", "a.txt"]


@FUZZ
@given(st.binary(max_size=1500), st.sampled_from(SUFFIXES))
def test_random_files(data, filename):
    accept_or_refuse(read_points, data, filename, 64, MAX_POINTS)


@FUZZ
@given(
    st.sampled_from(["ply", "pcd", "npy"]),
    st.sampled_from([b"solid ", b"ply\n", b"VERSION 0.7\n", b"\x93NUMPY", b"v 1 2 3\nf 1 2 3\n"]),
    st.binary(max_size=600),
)
def test_random_files_with_a_plausible_start(suffix, start, rest):
    accept_or_refuse(read_points, start + rest, f"a.{suffix}", 64, MAX_POINTS)


def _samples() -> dict[str, bytes]:
    """Valid files of every kind the service reads."""
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    cloud = np.random.default_rng(0).normal(size=(20, 3)).astype(np.float32)

    def exported(thing, file_type: str, **kwargs) -> bytes:
        data = thing.export(file_type=file_type, **kwargs)
        return data.encode() if isinstance(data, str) else data

    npy = io.BytesIO()
    np.save(npy, cloud)

    def pcd(encoding: str) -> bytes:
        buffer = io.BytesIO()
        PointCloud.from_xyz_points(cloud).save(buffer, Encoding(encoding))
        return buffer.getvalue()

    return {
        "a.stl": exported(box, "stl"),
        "b.stl": exported(box, "stl_ascii"),
        "a.obj": exported(box, "obj"),
        "a.ply": exported(box, "ply"),
        "b.ply": exported(box, "ply", encoding="ascii"),
        "c.ply": exported(trimesh.PointCloud(cloud), "ply"),
        "d.ply": exported(trimesh.PointCloud(cloud), "ply", encoding="ascii"),
        "a.pcd": pcd("ascii"),
        "b.pcd": pcd("binary"),
        "c.pcd": pcd("binary_compressed"),
        "a.npy": npy.getvalue(),
    }


SAMPLES = _samples()


@st.composite
def damaged(draw) -> tuple[bytes, str]:
    """A valid file with a few random cuts, flips, insertions or rewritten numbers."""
    name = draw(st.sampled_from(sorted(SAMPLES)))
    data = bytearray(SAMPLES[name])
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["cut", "flip", "insert", "number"]))
        at = draw(st.integers(0, max(0, len(data) - 1)))
        if kind == "cut":
            del data[at:]
        elif kind == "flip" and data:
            data[at] = draw(st.integers(0, 255))
        elif kind == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=8))
        else:  # a number in a header rewritten: counts, sizes, shapes
            digits = [i for i, byte in enumerate(data[:400]) if chr(byte).isdigit()]
            if digits:
                i = draw(st.sampled_from(digits))
                number = draw(st.sampled_from(["0", "-1", "99999999999", "3", "1e9", "nan"]))
                data[i : i + 1] = number.encode()
    renamed = draw(st.sampled_from([name, None, "upload"]))
    return bytes(data), renamed


@settings(FUZZ, max_examples=300)
@given(damaged())
def test_damaged_files(sample):
    data, filename = sample
    accept_or_refuse(read_points, data, filename, 64, MAX_POINTS)


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_the_undamaged_samples_are_read(name):
    checked(
        validate_points(read_points(SAMPLES[name], name, 64, MAX_POINTS), MIN_POINTS, MAX_POINTS)
    )


def _face_out_of_range() -> bytes:
    """An ASCII PLY box whose first face names vertex 8 of 8 (indices run 0..7)."""
    ply = SAMPLES["b.ply"].decode()
    head, body = ply.split("end_header\n", 1)
    lines = body.splitlines()
    lines[8] = "3 8 1 2"  # the first face line, after the 8 vertex lines
    return (head + "end_header\n" + "\n".join(lines) + "\n").encode()


@pytest.mark.parametrize(
    ("data", "name", "words"),
    [  # what the fuzzing found once
        (_face_out_of_range(), "a.ply", "refers to a vertex"),
        (SAMPLES["a.pcd"].replace(b"SIZE 4 4 4", b"SIZE 1e9 4 4"), "a.pcd", "'1e9'"),
        (SAMPLES["a.pcd"].replace(b"COUNT 1 1 1", b"COUNT 1 -1 1"), "a.pcd", "COUNT: "),
        (SAMPLES["b.pcd"].replace(b"POINTS 20", b"POINTS -1"), "a.pcd", "POINTS: "),
        (SAMPLES["a.pcd"].replace(b"FIELDS x y z", b"FIELDS x x z"), "a.pcd", "'y'"),
        (SAMPLES["b.pcd"].replace(b"FIELDS x y z", b"FIELDS x y x"), "a.pcd", "'z'"),
        (b"v 0\nv 0.5\nv 1\nf 1 2 3\n", "a.obj", "x y z triples"),
    ],
)
def test_what_fuzzing_found(data, name, words):
    with pytest.raises(InvalidPoints, match=words):
        read_points(data, name, 64, MAX_POINTS)
