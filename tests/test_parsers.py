"""Uploaded files: meshes are sampled, clouds used as is, bad files refused with a reason."""

import io

import numpy as np
import pytest
import trimesh

from service.api.parsers import file_kind, read_points
from service.errors import InvalidPoints

COUNT = 256  # points a mesh is sampled to


@pytest.fixture(scope="module")
def box() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(1.0, 2.0, 3.0))


@pytest.fixture(scope="module")
def cloud() -> np.ndarray:
    return np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)


def export(mesh: trimesh.Trimesh, file_type: str) -> bytes:
    data = mesh.export(file_type=file_type)
    return data.encode() if isinstance(data, str) else data


def on_box_surface(points: np.ndarray) -> bool:
    half = np.array([0.5, 1.0, 1.5])
    inside = np.all(np.abs(points) <= half + 1e-5, axis=1)
    on_a_face = np.any(np.isclose(np.abs(points), half, atol=1e-5), axis=1)
    return bool(np.all(inside & on_a_face))


@pytest.mark.parametrize("file_type", ["stl", "stl_ascii", "obj", "ply"])
def test_a_mesh_is_sampled_on_its_surface(box, file_type):
    suffix = "stl" if file_type.startswith("stl") else file_type
    points = read_points(export(box, file_type), f"part.{suffix}", COUNT)
    assert points.shape == (COUNT, 3)
    assert on_box_surface(points)
    again = read_points(export(box, file_type), f"part.{suffix}", COUNT)
    np.testing.assert_array_equal(points, again)  # the same file gives the same points


def test_a_binary_stl_is_recognised_without_a_suffix(box):
    data = export(box, "stl")
    assert file_kind(data, None) == ".stl"
    assert read_points(data, "upload", COUNT).shape == (COUNT, 3)


# text STLs from CAD tools that write their own code page: trimesh decodes them with
# charset_normalizer, which the runtime dependencies must bring (tests/test_runtime_install.py)
LATIN1_STL = (
    "solid pi\xe8ce\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 0.1 0 0\n"
    "vertex 0 0.1 0\nendloop\nendfacet\nendsolid pi\xe8ce\n".encode("latin-1")
)
BROKEN_STL = b"solid part\n\xff\xfe facet normal 0 0 1\nendsolid\n"


def test_a_text_stl_that_is_not_utf8_is_read():
    points = read_points(LATIN1_STL, "part.stl", COUNT)
    assert points.shape == (COUNT, 3) and np.all(np.abs(points[:, 2]) < 1e-7)


def test_a_malformed_text_stl_is_named():
    with pytest.raises(InvalidPoints) as caught:
        read_points(BROKEN_STL, "part.stl", COUNT)
    assert "STL mesh is unusable" in str(caught.value)
    assert "module" not in str(caught.value)  # not "No module named 'charset_normalizer'"


def test_a_ply_cloud_is_used_as_is(cloud):
    data = trimesh.PointCloud(cloud).export(file_type="ply")
    np.testing.assert_allclose(read_points(data, "scan.ply", COUNT), cloud)


def test_a_ply_cloud_is_recognised_by_content(cloud):
    data = trimesh.PointCloud(cloud).export(file_type="ply")
    assert file_kind(data, "scan.bin") == ".ply"


def pcd(cloud: np.ndarray, data: str, fields: str = "x y z") -> bytes:
    names = fields.split()
    columns = {name: cloud[:, i] for i, name in enumerate("xyz")}
    columns |= {
        name: np.arange(len(cloud), dtype=np.float32) for name in names if name not in columns
    }
    table = np.stack([columns[name] for name in names], axis=1).astype(np.float32)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {fields}\nSIZE {' '.join('4' * len(names))}\nTYPE {' '.join('F' * len(names))}\n"
        f"COUNT {' '.join('1' * len(names))}\nWIDTH {len(table)}\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(table)}\nDATA {data}\n"
    ).encode()
    if data == "ascii":
        return header + "".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in table).encode()
    return header + table.astype("<f4").tobytes()


@pytest.mark.parametrize("data", ["ascii", "binary"])
@pytest.mark.parametrize("fields", ["x y z", "intensity z y x"])
def test_pcd_clouds(cloud, data, fields):
    points = read_points(pcd(cloud, data, fields), "scan.pcd", COUNT)
    np.testing.assert_array_equal(points.astype(np.float32), cloud)


def test_a_float64_binary_pcd(cloud):
    header = (
        "VERSION .7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {len(cloud)}\nHEIGHT 1\nPOINTS {len(cloud)}\nDATA binary\n"
    ).encode()
    data = header + cloud.astype("<f8").tobytes()
    assert file_kind(data, None) == ".pcd"
    np.testing.assert_array_equal(read_points(data, None, COUNT), cloud.astype(np.float64))


def npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=True)
    return buffer.getvalue()


def test_an_npy_cloud(cloud):
    np.testing.assert_array_equal(read_points(npy(cloud), "scan.npy", COUNT), cloud)
    np.testing.assert_array_equal(read_points(npy(cloud), "no-suffix", COUNT), cloud)


def truncated(ply: bytes) -> bytes:
    return ply[: ply.index(b"end_header") + 40]


@pytest.mark.parametrize(
    ("make", "name", "words"),
    [
        (lambda c, b: b"", "a.stl", "empty"),
        (lambda c, b: b"hello world", "a.xyz", "cannot tell what"),
        (lambda c, b: b"solid nothing\nendsolid nothing\n", "a.stl", "STL mesh is unusable"),
        (lambda c, b: b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "a.obj", "no triangles"),
        (lambda c, b: truncated(export(b, "ply")), "a.ply", "PLY mesh is unusable"),
        (lambda c, b: b"ply\nformat ascii 1.0\nelement vertex 3\n", "a.ply", "end_header"),
        (lambda c, b: npy(c[:, :2]), "a.npy", "shape (50, 2), not (N, 3)"),
        (lambda c, b: npy(np.array(["a", "b", "c"] * 2).reshape(2, 3)), "a.npy", "not numbers"),
        (lambda c, b: npy(np.array([[1, None, 2]], dtype=object)), "a.npy", "unreadable"),
        (lambda c, b: npy(c)[:100], "a.npy", "unreadable"),
        (lambda c, b: pcd(c, "ascii").replace(b"FIELDS x y z", b"FIELDS a b c"), "a.pcd", "'x'"),
        (lambda c, b: pcd(c, "binary")[:-10], "a.pcd", "binary PCD data is"),
        (lambda c, b: pcd(c, "ascii").rsplit(b"\n", 2)[0], "a.pcd", "49 rows, the header says 50"),
        (lambda c, b: pcd(c, "ascii").replace(b"\n0", b"\nabc", 1), "a.pcd", "not a number"),
        (lambda c, b: pcd(c, "binary_compressed"), "a.pcd", "binary_compressed is not"),
        (lambda c, b: pcd(c, "ascii").replace(b"TYPE F F F", b"TYPE Q F F"), "a.pcd", "TYPE Q"),
        (lambda c, b: b"VERSION 0.7\nFIELDS x y z\n", "a.pcd", "no DATA line"),
    ],
)
def test_bad_files_are_named(cloud, box, make, name, words):
    with pytest.raises(InvalidPoints) as caught:
        read_points(make(cloud, box), name, COUNT)
    assert words in str(caught.value)
