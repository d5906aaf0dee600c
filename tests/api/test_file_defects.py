"""The file defects a new user met (issue 33), each refused saying what is wrong: a PLY whose
header declares more vertices than it holds, a short ASCII row, a text file named .npy. The
files are a real part's (pybullet's duck) points written by trimesh and numpy, then damaged as
the user's were; each goes to a real server or to the parser."""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh

from service.api.parsers import read_points
from service.engine.sampling import sample_surface
from service.errors import InvalidPoints
from tests.meshes import pybullet_mesh

HELD, DECLARED = 3000, 9983  # the user's file: 3,000 vertices, a header that says 9,983


@pytest.fixture(scope="module")
def duck() -> np.ndarray:
    return sample_surface(pybullet_mesh("duck.obj"), HELD, seed=3).astype(np.float32)


def ply(points: np.ndarray, encoding: str) -> bytes:
    data = trimesh.PointCloud(points).export(file_type="ply", encoding=encoding)
    return data.encode() if isinstance(data, str) else data


def declaring(data: bytes, count: int) -> bytes:
    """The file with its header's vertex count changed, its rows left as they are."""
    return data.replace(f"element vertex {HELD}\n".encode(), f"element vertex {count}\n".encode())


def refusal(data: bytes, filename: str) -> str:
    with pytest.raises(InvalidPoints) as caught:
        read_points(data, filename, 2048, 10**6)
    return str(caught.value)


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_a_ply_declaring_more_vertices_than_it_holds_is_refused(service, duck, encoding):
    """The ASCII one was answered 200 "match" on its first 3,000 rows."""
    data = declaring(ply(duck, encoding), DECLARED)
    answer = service.client.post("/align", files={"file": ("scan.ply", data)})
    assert answer.status_code == 422, answer.text[:300]
    detail = answer.json()["detail"]
    assert str(DECLARED) in detail and "header" in detail
    if encoding == "ascii":
        assert f"holds {HELD} rows" in detail


def test_a_ply_declaring_fewer_vertices_than_it_holds_is_refused(duck):
    """The mirror case: trimesh would read the first rows and drop the rest unsaid."""
    detail = refusal(declaring(ply(duck, "ascii"), 1000), "scan.ply")
    assert f"holds {HELD} rows" in detail and "1000" in detail


def test_the_files_trimesh_and_numpy_write_are_read_whole(duck):
    for encoding in ("ascii", "binary"):
        read = read_points(ply(duck, encoding), "scan.ply", 2048, 10**6)
        np.testing.assert_allclose(read, duck, atol=1e-7)  # ASCII: 8 decimals
    mesh = trimesh.creation.box()
    for encoding in ("ascii", "binary"):
        data = mesh.export(file_type="ply", encoding=encoding)
        data = data.encode() if isinstance(data, str) else data
        assert read_points(data, "box.ply", 256, 10**6).shape == (256, 3)  # sampled


def test_a_short_ascii_row_is_named(service, duck):
    """numpy's "setting an array element with a sequence" leaked before."""
    lines = ply(duck, "ascii").split(b"\n")
    first_row = lines.index(b"end_header") + 1
    lines[first_row + 41] = b" ".join(lines[first_row + 41].split()[:2])  # vertex 42: x y only
    answer = service.client.post("/align", files={"file": ("scan.ply", b"\n".join(lines))})
    assert answer.status_code == 422, answer.text[:300]
    detail = answer.json()["detail"]
    assert "row 42" in detail and "2 values" in detail and "3 properties (x y z)" in detail
    assert "sequence" not in detail


def test_a_text_file_named_npy_is_not_an_npy_file(service, duck):
    text = "\n".join(" ".join(f"{v:.6f}" for v in row) for row in duck).encode()
    answer = service.client.post("/align", files={"file": ("scan.npy", text)})
    assert answer.status_code == 422, answer.text[:300]
    detail = answer.json()["detail"]
    assert "not an NPY file" in detail
    assert "pickle" not in detail.lower()


def test_a_pickled_npy_array_is_refused_without_suggesting_unsafe_loading():
    buffer = io.BytesIO()
    np.save(buffer, np.array([[1.0, None, 2.0]], dtype=object), allow_pickle=True)
    detail = refusal(buffer.getvalue(), "scan.npy")
    assert "Python objects" in detail and "never loads" in detail
    assert "allow_pickle" not in detail and "pickle.load" not in detail
