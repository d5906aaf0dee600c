"""The camera's own files on ``POST /align`` and ``POST /points``: clouds (PLY, PCD, NPY) and
depth images (16-bit PNG in millimetres, float32 TIFF or NPY in metres) with the camera's
intrinsics and a mask. Each file is written by another tool (trimesh, pypcd4, Open3D, Pillow,
numpy); a damaged file of each kind is answered 422 naming the problem."""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh
from PIL import Image
from pypcd4 import Encoding, PointCloud
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from service.api import uploads
from service.api.depth import depth_points
from service.api.schemas import DepthCamera
from service.engine.sampling import sample_surface
from service.errors import InvalidPoints
from tests.camera import INTRINSICS, depth_image, unproject
from tests.meshes import pybullet_mesh

ROTATION = Rotation.from_euler("xyz", [30, -50, 20], degrees=True).as_matrix()
TRANSLATION = np.array([0.02, -0.01, 0.45])  # about 6 radii in front of the camera


@pytest.fixture(scope="module")
def mug() -> trimesh.Trimesh:
    return pybullet_mesh("objects/mug.obj")


@pytest.fixture(scope="module")
def depth(mug) -> np.ndarray:
    return depth_image(mug, ROTATION, TRANSLATION)


def png16(depth_m: np.ndarray) -> bytes:
    """A 16-bit PNG in millimetres, written by Pillow."""
    buffer = io.BytesIO()
    Image.fromarray(np.rint(depth_m * 1000).astype(np.uint16)).save(buffer, format="PNG")
    return buffer.getvalue()


def image_file(array: np.ndarray, kind: str) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format=kind)
    return buffer.getvalue()


def npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def post_points(service, files, **fields):
    return service.client.post("/points", files=files, data=fields)


def returned(answer) -> np.ndarray:
    assert answer.status_code == 200, answer.text
    points = np.frombuffer(answer.content, dtype="<f4").reshape(-1, 3)
    assert int(answer.headers["X-Points"]) == len(points)
    return points


def test_a_depth_image_is_the_pinhole_model_of_its_pixels(depth):
    camera = DepthCamera(**INTRINSICS, depth_scale=1.0)
    np.testing.assert_allclose(depth_points(depth, camera, None, 10**6), unproject(depth))
    mask = np.zeros(depth.shape, dtype=bool)
    mask[:, : depth.shape[1] // 2] = True
    kept = depth_points(depth, camera, mask, 10**6)
    np.testing.assert_allclose(kept, unproject(np.where(mask, depth, 0)))


def test_a_depth_image_without_a_depth_says_so(depth):
    """A camera that saw nothing (or a mask that misses every depth) names the image, not an
    empty list of triples."""
    camera = DepthCamera(**INTRINSICS)
    height, width = depth.shape
    with pytest.raises(InvalidPoints, match=rf"\({width}x{height} pixels\) has no pixel with a"):
        depth_points(np.zeros_like(depth), camera, None, 10**6)
    with pytest.raises(InvalidPoints, match="has no pixel with a depth inside the mask"):
        depth_points(depth, camera, np.zeros(depth.shape, dtype=bool), 10**6)


def test_a_png_written_by_open3d_gives_open3d_s_own_cloud(depth, tmp_path):
    o3d = pytest.importorskip("open3d", exc_type=ImportError)  # its wheel needs libusb
    path = str(tmp_path / "depth.png")
    millimetres = np.rint(depth * 1000).astype(np.uint16)
    assert o3d.io.write_image(path, o3d.geometry.Image(millimetres))
    height, width = depth.shape
    intrinsic = o3d.camera.PinholeCameraIntrinsic(
        width, height, INTRINSICS["fx"], INTRINSICS["fy"], INTRINSICS["cx"], INTRINSICS["cy"]
    )
    theirs = o3d.geometry.PointCloud.create_from_depth_image(
        o3d.io.read_image(path), intrinsic, depth_scale=1000.0, depth_trunc=1e6
    )
    ours = depth_points(np.asarray(Image.open(path)), DepthCamera(**INTRINSICS), None, 10**6)
    np.testing.assert_allclose(ours, np.asarray(theirs.points), atol=1e-9)


def test_a_depth_png_over_http_lies_on_the_part(service, mug, depth):
    answer = post_points(service, {"file": ("depth.png", png16(depth))}, **INTRINSICS)
    points = returned(answer)
    assert answer.headers["X-Viewpoint"] == "0,0,0"  # the cloud is in the camera's frame
    assert len(points) == np.count_nonzero(depth)
    model = (points.astype(np.float64) - TRANSLATION) @ ROTATION  # back in the mesh's frame
    distance, _ = cKDTree(sample_surface(mug, 400_000, seed=2)).query(model)
    assert np.percentile(distance, 99) < 0.003  # within a pixel (1.5 mm) and the mm rounding


@pytest.mark.parametrize("kind", ["TIFF", "NPY"])
def test_float_depth_in_metres(service, depth, kind):
    data = npy(depth) if kind == "NPY" else image_file(depth, "TIFF")
    points = returned(post_points(service, {"file": (f"depth.{kind.lower()}", data)}, **INTRINSICS))
    np.testing.assert_allclose(points, unproject(depth), atol=1e-6)


def test_a_mask_and_a_depth_scale(service, depth):
    mask = np.zeros(depth.shape, dtype=np.uint8)
    mask[: depth.shape[0] // 2] = 255
    files = {"file": ("depth.png", png16(depth)), "mask": ("mask.png", image_file(mask, "PNG"))}
    points = returned(post_points(service, files, **INTRINSICS, depth_scale="1"))  # millimetres
    expected = unproject(np.where(mask > 0, np.rint(depth * 1000), 0))
    np.testing.assert_allclose(points, expected, rtol=1e-6)


def clouds(points: np.ndarray, tmp_path) -> dict[str, bytes]:
    """The same cloud as each tool writes it."""
    files = {
        "trimesh.ply": trimesh.PointCloud(points).export(file_type="ply"),
        "numpy.npy": npy(points),
    }
    for encoding in ("ascii", "binary", "binary_compressed"):
        buffer = io.BytesIO()
        PointCloud.from_xyz_points(points).save(buffer, Encoding(encoding))
        files[f"pypcd4-{encoding}.pcd"] = buffer.getvalue()
    try:
        import open3d as o3d
    except ImportError:  # its wheel needs libusb
        return files
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    for encoding in ("ascii", "binary", "binary_compressed"):
        path = tmp_path / f"open3d-{encoding}.pcd"
        ascii_, compressed = encoding == "ascii", encoding == "binary_compressed"
        o3d.io.write_point_cloud(str(path), cloud, write_ascii=ascii_, compressed=compressed)
        files[path.name] = path.read_bytes()
        assert f"DATA {encoding}\n".encode() in files[path.name]
    return files


def test_every_cloud_format_aligns(service, mug, tmp_path):
    """Every tool's file reads back as the very points; one of them is aligned end to end."""
    sample = sample_surface(mug, 2048, seed=3).astype(np.float64) @ ROTATION.T + TRANSLATION
    files = clouds(sample.astype(np.float32), tmp_path)
    for name, data in files.items():
        points = returned(post_points(service, {"file": (name, data)}))
        np.testing.assert_allclose(points, sample, atol=1e-6, err_msg=name)
    scan = files["pypcd4-binary_compressed.pcd"]
    answer = service.client.post(
        "/align", files={"file": ("scan.pcd", scan)}, data={"candidates": ["mug", "bunny"]}
    )
    assert answer.status_code == 200, answer.text
    assert answer.json()["label"] == "mug"
    latest = service.client.get("/alignments").json()["alignments"][0]
    assert latest["source"] == "file scan.pcd" and latest["viewpoint"] is None


def test_a_depth_image_on_align_is_seen_from_the_origin(service, depth):
    files = {"file": ("depth.png", png16(depth))}
    answer = service.client.post("/align", files=files, data={**INTRINSICS, "top_k": "2"})
    assert answer.status_code == 200, answer.text
    assert set(answer.json()) >= {"verdict", "confidence", "reasons", "rotation", "translation"}
    latest = service.client.get("/alignments").json()["alignments"][0]
    assert latest["viewpoint"] == [0, 0, 0] and latest["num_points"] == np.count_nonzero(depth)
    given = {**INTRINSICS, "viewpoint": "0.1,0,0"}  # the caller's viewpoint wins
    assert service.client.post("/align", files=files, data=given).status_code == 200
    assert service.client.get("/alignments").json()["alignments"][0]["viewpoint"] == [0.1, 0, 0]


def damaged(depth: np.ndarray) -> list[tuple[dict, dict, str]]:
    """(files, fields, words of the 422) for a damaged file of each kind, and bad companions."""
    cloud = np.random.default_rng(0).normal(size=(100, 3)).astype(np.float32)
    ply = trimesh.PointCloud(cloud).export(file_type="ply")
    pcd = io.BytesIO()
    PointCloud.from_xyz_points(cloud).save(pcd, Encoding.BINARY)
    png, tiff = png16(depth), image_file(depth, "TIFF")
    eight_bit = image_file((depth > 0).astype(np.uint8), "PNG")
    return [
        ({"file": ("a.ply", ply[: len(ply) // 2])}, {}, "PLY"),
        ({"file": ("a.pcd", pcd.getvalue()[:-7])}, {}, "binary PCD data is"),
        ({"file": ("a.npy", npy(cloud[:, :2]))}, {}, "not (N, 3)"),
        ({"file": ("a.png", png[: len(png) // 2])}, INTRINSICS, "depth image is unreadable"),
        ({"file": ("a.tif", tiff[:200])}, INTRINSICS, "depth image"),
        ({"file": ("a.png", eight_bit)}, INTRINSICS, "16-bit PNG in millimetres"),
        ({"file": ("a.npy", npy(cloud))}, INTRINSICS, "without fx, fy, cx and cy"),
        ({"file": ("a.png", png)}, {}, "intrinsics"),
        ({"file": ("a.png", png)}, {**INTRINSICS, "fx": "-3"}, "fx"),
        ({"file": ("a.png", png)}, {**INTRINSICS, "cy": "nan"}, "cy"),
        (  # intrinsics divided by the image's size, as some libraries give them
            {"file": ("a.png", png)},
            {"fx": "0.9", "fy": "1.2", "cx": "0.5", "cy": "0.5"},
            "fx = 0.9 is no focal length in pixels",
        ),
        ({"file": ("a.png", png)}, {**INTRINSICS, "cx": "1e9"}, "cx = 1e+09 lies far outside"),
        ({"file": ("a.png", png), "mask": ("m.png", eight_bit[:40])}, INTRINSICS, "mask"),
        (
            {
                "file": ("a.png", png),
                "mask": ("m.png", image_file(np.ones((4, 4), np.uint8), "PNG")),
            },
            INTRINSICS,
            "the mask is 4x4",
        ),
        (
            {"file": ("a.pcd", pcd.getvalue())},
            {"fz": "1"},
            "unknown field 'fz'",
        ),
        ({"file": ("a.png", np.zeros(1).tobytes())}, INTRINSICS, "cannot be read"),
        ({"mask": ("m.png", eight_bit)}, INTRINSICS, "upload the cloud as a file field"),
    ]


def test_damaged_files_are_named(service, depth):
    before = service.client.get("/alignments").json()["alignments"][:1]
    for files, fields, words in damaged(depth):
        for route in ("/points", "/align"):
            answer = service.client.post(route, files=files, data=fields)
            assert answer.status_code == 422, (route, words, answer.text)
            assert words in answer.json()["detail"], (route, answer.json()["detail"])
    assert service.client.get("/alignments").json()["alignments"][:1] == before  # none recorded


def organized_cloud(depth: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 camera-frame points of a depth image, NaN where it has no depth."""
    grid = np.full((*depth.shape, 3), np.nan, dtype=np.float32)
    grid[depth > 0] = unproject(depth)
    return grid


def implied_viewpoint(answer) -> np.ndarray | None:
    returned(answer)
    header = answer.headers.get("X-Viewpoint")
    return None if header is None else np.array([float(v) for v in header.split(",")])


def test_an_organized_cloud_implies_where_its_camera_was(service, depth):
    # the points of a camera's pixels lie on rays through the camera: in the driver's frame the
    # origin, carried into a robot's frame the camera there; a plane does not pin it, and a
    # cloud without its pixels says nothing (docs/decisions.md#the-camera-of-an-organized-frame)
    grid = organized_cloud(depth)
    at_origin = implied_viewpoint(post_points(service, {"file": ("frame.npy", npy(grid))}))
    assert at_origin.tolist() == [0.0, 0.0, 0.0]
    turn = Rotation.from_euler("xyz", [10, 70, -40], degrees=True).as_matrix()
    camera = np.array([0.3, -0.8, 1.1])
    moved = (grid.reshape(-1, 3).astype(np.float64) @ turn.T + camera).astype(np.float32)
    seen = implied_viewpoint(
        post_points(service, {"file": ("frame.npy", npy(moved.reshape(grid.shape)))})
    )
    np.testing.assert_allclose(seen, camera, atol=1e-4)
    wall = organized_cloud(np.full_like(depth, 0.5))  # one plane facing the camera
    assert implied_viewpoint(post_points(service, {"file": ("wall.npy", npy(wall))})) is None
    loose = grid.reshape(-1, 3)[np.isfinite(grid.reshape(-1, 3)).all(axis=1)]
    assert implied_viewpoint(post_points(service, {"file": ("loose.npy", npy(loose))})) is None


def test_a_viewpoint_the_request_gives_is_not_solved_for(service, depth, monkeypatch):
    # the camera's centre is solved from an organized file's pixels only where the request
    # does not say where the camera was (the solve reads 1,024 pixels' rays)
    solved = []
    solve = uploads.camera_centre

    def counted(cloud):
        solved.append(len(cloud.points))
        return solve(cloud)

    monkeypatch.setattr(uploads, "camera_centre", counted)
    files = {"file": ("frame.npy", npy(organized_cloud(depth)))}
    for route in ("/align", "/detect"):
        given = service.client.post(route, files=files, data={"viewpoint": "0,0,0"})
        assert given.status_code == 200, given.text
        assert solved == [], route
        implied = service.client.post(route, files=files)
        assert implied.status_code == 200, implied.text
        assert len(solved) == 1, route
        solved.clear()
