"""Uploaded files: meshes are sampled, clouds used as is, bad files refused with a reason.

Every good file is written by another tool (trimesh, numpy, pypcd4; Open3D's PCD files in
test_camera_files, since Open3D is not a runtime dependency); the bad ones are good ones
damaged."""

import io
import re

import numpy as np
import pytest
import trimesh
from pypcd4 import Encoding, PointCloud

from service.api.clouds import organized
from service.api.parsers import file_kind, read_points
from service.errors import InvalidPoints
from tests.meshes import BROKEN_STL, LATIN1_STL
from tests.servers import cloud

COUNT = 256  # points a mesh is sampled to
MAX_POINTS = 1000


@pytest.fixture(scope="module")
def box() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(1.0, 2.0, 3.0))


@pytest.fixture(scope="module")
def scan() -> np.ndarray:
    """50 points in 5 rows of equal depth, as a camera's are: lzf finds something to compress."""
    points = cloud(50, seed=0, spread=1.0)
    points[:, 2] = np.repeat(np.random.default_rng(1).normal(size=5), 10)
    return points


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
    points = read_points(export(box, file_type), f"part.{suffix}", COUNT, MAX_POINTS)
    assert points.shape == (COUNT, 3)
    assert on_box_surface(points)
    again = read_points(export(box, file_type), f"part.{suffix}", COUNT, MAX_POINTS)
    np.testing.assert_array_equal(points, again)  # the same file gives the same points


def test_a_binary_stl_is_recognised_without_a_suffix(box):
    data = export(box, "stl")
    assert file_kind(data, None) == ".stl"
    assert read_points(data, "upload", COUNT, MAX_POINTS).shape == (COUNT, 3)


def test_a_text_stl_that_is_not_utf8_is_read():
    points = read_points(LATIN1_STL, "part.stl", COUNT, MAX_POINTS)
    assert points.shape == (COUNT, 3) and np.all(np.abs(points[:, 2]) < 1e-7)


def test_a_malformed_text_stl_is_named():
    with pytest.raises(InvalidPoints) as caught:
        read_points(BROKEN_STL, "part.stl", COUNT, MAX_POINTS)
    assert "STL mesh is unusable" in str(caught.value)
    assert "module" not in str(caught.value)  # not "No module named 'charset_normalizer'"


def test_a_ply_cloud_is_used_as_is(scan):
    data = trimesh.PointCloud(scan).export(file_type="ply")
    np.testing.assert_allclose(read_points(data, "scan.ply", COUNT, MAX_POINTS), scan)


def test_a_ply_cloud_is_recognised_by_content(scan):
    data = trimesh.PointCloud(scan).export(file_type="ply")
    assert file_kind(data, "scan.bin") == ".ply"


def pcd(cloud: np.ndarray, data: str, fields: str = "x y z") -> bytes:
    """A PCD file written by pypcd4; fields other than x y z count the points."""
    names = fields.split()
    columns = {name: cloud[:, i] for i, name in enumerate("xyz")}
    table = [columns.get(name, np.arange(len(cloud), dtype=np.float32)) for name in names]
    buffer = io.BytesIO()
    PointCloud.from_points(table, names, [np.float32] * len(names)).save(buffer, Encoding(data))
    return buffer.getvalue()


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
@pytest.mark.parametrize("fields", ["x y z", "intensity z y x"])
def test_pcd_clouds(scan, data, fields):
    written = pcd(scan, data, fields)
    assert f"DATA {data}\n".encode() in written
    points = read_points(written, "scan.pcd", COUNT, MAX_POINTS)
    np.testing.assert_allclose(points, scan, atol=1e-9)  # ascii: 10 decimals


def test_a_float64_pcd_without_a_suffix(scan):
    buffer = io.BytesIO()
    PointCloud.from_points(scan.astype(np.float64), ("x", "y", "z"), [np.float64] * 3).save(buffer)
    assert file_kind(buffer.getvalue(), None) == ".pcd"
    points = read_points(buffer.getvalue(), None, COUNT, MAX_POINTS)
    np.testing.assert_array_equal(points, scan.astype(np.float64))


def test_an_organised_pcd_drops_its_empty_pixels(scan):
    """An organised cloud (HEIGHT > 1) marks pixels without a return with NaN, as PCL does."""
    grid = np.full((10, 6, 3), np.nan, dtype=np.float32)
    grid.reshape(-1, 3)[::2] = scan[:30]
    saved = PointCloud.from_xyz_points(grid.reshape(-1, 3))
    saved.metadata = saved.metadata.derive(width=6, height=10)
    buffer = io.BytesIO()
    saved.save(buffer, Encoding.BINARY)
    assert b"HEIGHT 10" in buffer.getvalue()
    points = read_points(buffer.getvalue(), "organised.pcd", COUNT, MAX_POINTS)
    np.testing.assert_array_equal(points, scan[:30])


def test_a_pixel_with_any_coordinate_missing_is_dropped():
    """A pixel is valid only if all three of its coordinates are finite."""
    grid = np.arange(4 * 5 * 3, dtype=np.float32).reshape(4, 5, 3)
    grid[0, 1, 2], grid[2, 3, 0], grid[3, 4, 1] = np.nan, np.inf, -np.inf
    cloud = organized(grid, 100, "frame")
    assert cloud.shape == (4, 5)
    np.testing.assert_array_equal(cloud.index, [i for i in range(20) if i not in (1, 13, 19)])
    np.testing.assert_array_equal(cloud.points, grid.reshape(-1, 3)[cloud.index])


def test_a_pixel_at_the_cameras_centre_is_one_without_depth():
    """RealSense's SDK writes a pixel without depth as the point (0, 0, 0): it is skipped as a
    NaN one is; a point with one or two coordinates 0 is kept."""
    grid = np.arange(1, 4 * 5 * 3 + 1, dtype=np.float32).reshape(4, 5, 3)
    grid[0, 1] = 0.0
    grid[2, 3] = [0.0, 0.0, 0.5]
    grid[3, 4] = [0.0, 0.2, 0.0]
    cloud = organized(grid, 100, "frame")
    np.testing.assert_array_equal(cloud.index, [i for i in range(20) if i != 1])
    saying = r"the NPY frame \(5x4 pixels\) has no valid point: every pixel is NaN, infinite or \(0"
    with pytest.raises(InvalidPoints, match=saying):
        read_points(npy(np.zeros((4, 5, 3), np.float32)), "frame.npy", COUNT, MAX_POINTS)


@pytest.mark.parametrize(
    "shape, says",
    [
        ((4, 5, 6), "first three of 6 channels are x, y and z (XYZRGB, XYZW), send array[..., :3]"),
        ((40, 4), "send array[..., :3]"),
        ((3, 4, 5), "its channels come first; send np.moveaxis(array, 0, -1)"),
        ((3, 40), "np.moveaxis"),
    ],
)
def test_an_npy_of_another_layout_says_what_to_send(shape, says):
    array = np.random.default_rng(0).normal(size=shape).astype(np.float32)
    with pytest.raises(InvalidPoints, match=re.escape(says)):
        read_points(npy(array), "frame.npy", COUNT, MAX_POINTS)


def test_a_frame_without_a_valid_pixel_says_so():
    """A camera that saw nothing writes a frame of NaN pixels: the answer names the frame and
    its pixels, not an empty list of triples."""
    grid = np.full((4, 5, 3), np.nan, dtype=np.float32)
    grid[1, 2] = [np.inf, 0.0, 1.0]
    with pytest.raises(InvalidPoints, match=r"the NPY frame \(5x4 pixels\) has no valid point"):
        read_points(npy(grid), "frame.npy", COUNT, MAX_POINTS)
    saved = PointCloud.from_xyz_points(grid.reshape(-1, 3))
    saved.metadata = saved.metadata.derive(width=5, height=4)
    buffer = io.BytesIO()
    saved.save(buffer, Encoding.BINARY)
    with pytest.raises(InvalidPoints, match=r"the PCD \(5x4 pixels\) has no valid point"):
        read_points(buffer.getvalue(), "frame.pcd", COUNT, MAX_POINTS)


def test_a_pcd_of_nan_points_alone_says_so():
    buffer = io.BytesIO()
    PointCloud.from_xyz_points(np.full((6, 3), np.nan, np.float32)).save(buffer, Encoding.BINARY)
    with pytest.raises(InvalidPoints, match="the PCD's 6 points are all NaN"):
        read_points(buffer.getvalue(), "cloud.pcd", COUNT, MAX_POINTS)


def npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=True)
    return buffer.getvalue()


def test_an_npy_cloud(scan):
    np.testing.assert_array_equal(read_points(npy(scan), "scan.npy", COUNT, MAX_POINTS), scan)
    np.testing.assert_array_equal(read_points(npy(scan), "no-suffix", COUNT, MAX_POINTS), scan)


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
        (lambda c, b: pcd(c, "binary").replace(b"POINTS 50", b"POINTS 5000"), "a.pcd", "5000"),
        (lambda c, b: pcd(c, "ascii").rsplit(b"\n", 2)[0], "a.pcd", "49 points, the header"),
        (lambda c, b: pcd(c, "ascii").replace(b"\n0", b"\nabc", 1), "a.pcd", "unreadable"),
        (lambda c, b: pcd(c, "binary_compressed")[:-10], "a.pcd", "compressed PCD data says"),
        (lambda c, b: pcd(c, "ascii").replace(b"TYPE F F F", b"TYPE Q F F"), "a.pcd", "'Q'"),
        (lambda c, b: pcd(c, "ascii").replace(b"SIZE 4 4 4", b"SIZE 4 4"), "a.pcd", "differ"),
        (lambda c, b: pcd(c, "ascii").replace(b"COUNT 1 1 1", b"COUNT 1 1 9999"), "a.pcd", "COUNT"),
        (lambda c, b: b"VERSION 0.7\nFIELDS x y z\n", "a.pcd", "no DATA line"),
    ],
)
def test_bad_files_are_named(scan, box, make, name, words):
    with pytest.raises(InvalidPoints) as caught:
        read_points(make(scan, box), name, COUNT, MAX_POINTS)
    assert words in str(caught.value)


def posted(body: bytes, content_type: str, chunk: int = 65_536):
    """A Starlette request whose body arrives in ``chunk``-byte pieces, as uvicorn hands it on."""
    from starlette.requests import Request

    pieces = iter([body[i : i + chunk] for i in range(0, len(body), chunk)])

    async def receive():
        piece = next(pieces, None)
        return {"type": "http.request", "body": piece or b"", "more_body": piece is not None}

    headers = [(b"content-type", content_type.encode())]
    return Request({"type": "http", "method": "POST", "headers": headers, "path": "/"}, receive)


def test_a_frames_file_is_read_in_memory_never_spooled_to_disk():
    """A camera frame of megabytes is held in memory as it arrives, not written to a temporary
    file in chunks through the thread pool (Starlette's own parser spools past 1 MB), and
    ``read_form`` gives its bytes as sent."""
    import asyncio

    import httpx

    from service.api.uploads import parse_form, read_form

    frame = np.random.default_rng(0).bytes(3_000_000)
    sent = httpx.Request("POST", "http://service/detect", files={"file": ("f.pcd", frame)})
    body, content_type = sent.read(), sent.headers["content-type"]

    async def parsed():
        form = await parse_form(posted(body, content_type), 2, 8)
        try:
            return form["file"]._in_memory, await form["file"].read()
        finally:
            await form.close()

    in_memory, content = asyncio.run(parsed())
    assert in_memory and content == frame
    form = asyncio.run(read_form(posted(body, content_type), ("file",), (), "the frame"))
    assert form.files["file"] == (frame, "f.pcd")
