"""Write the README's quick-start files: one real part, and what a cell's sensors give of it.

``python scripts/make_examples.py`` writes into ``examples/``

- ``panda-link5.stl``: link 5 of the Franka Emika Panda arm (``pybullet_data``'s
  ``franka_panda/meshes/visual/link5.obj``, Apache-2.0), decimated to 2,000 faces; the part
  the examples register. Never trained on and not in the shipped gallery;
- ``depth.png``: a 16-bit depth image (millimetres, 0 where no return) of that part resting on
  a table, seen obliquely from about a metre; ``part-mask.png``: the part's pixels (255);
  ``camera.json``: the camera's intrinsics (``fx``, ``fy``, ``cx``, ``cy``, pixels);
- ``scan.ply``: another camera's view of the part alone, binary PLY, in that camera's frame
  (its viewpoint is ``[0, 0, 0]``);
- ``cloud.f32``: 2,048 points resampled on the part's surface in a random pose, raw
  little-endian float32 ``x y z`` (the body of ``POST /align`` as
  ``application/octet-stream``);
- ``truth.json``: the true pose of each (``scene = R @ model + t``) to compare answers with.

Every file comes from the written mesh, so the truth is the pose of ``panda-link5.stl``'s own
frame. Needs the ``train`` extra (``pybullet`` for the mesh) and the ``eval`` extra (Open3D:
decimation and ray casting; its wheel needs Debian's ``libusb-1.0-0``); the service needs
neither to use the files.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

from evaluation.camera import DEPTH_NOISE_SHARE, Camera  # noqa: E402
from evaluation.scenes import (  # noqa: E402
    TABLE_HALF_SIDE_SCALES,
    look_at,
    placed,
    resting_pose,
    stable_poses,
    surface_centroid,
)
from service.engine.normalize import radius  # noqa: E402
from service.engine.sampling import load_mesh, sample_surface  # noqa: E402

SOURCE = "franka_panda/meshes/visual/link5.obj"  # under pybullet_data; Apache-2.0
NAME = "panda-link5"
FACES = 2000
CAMERA = Camera(width=640, height=480, focal=615.0)  # a RealSense-like 640x480 camera
SEED = 3
CLOUD_POINTS = 2048
DISTANCE_SCALES = 5.0  # the camera this many part scales from its centre
ELEVATION_DEG = 45.0  # the depth image's camera looks down at the table at this angle


def decimated(mesh: trimesh.Trimesh, faces: int) -> trimesh.Trimesh:
    """Open3D's quadric decimation of ``mesh`` to about ``faces`` triangles."""
    import open3d as o3d

    full = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(mesh.vertices, np.float64)),
        o3d.utility.Vector3iVector(np.asarray(mesh.faces, np.int32)),
    )
    small = full.simplify_quadric_decimation(faces)
    return trimesh.Trimesh(np.asarray(small.vertices), np.asarray(small.triangles))


def depth_and_source(
    meshes: list[trimesh.Trimesh], rng: np.random.Generator, camera: Camera = CAMERA
) -> tuple[np.ndarray, np.ndarray]:
    """(height, width) depth in metres along the optical axis (0: no return), with the
    evaluation's depth noise, and the index of the mesh each pixel hit (-1: none)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    ids = [
        scene.add_triangles(
            o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
            o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)),
        )
        for mesh in meshes
    ]
    directions = camera.rays()
    rays = np.hstack([np.zeros_like(directions), directions]).astype(np.float32)
    hits = scene.cast_rays(o3d.core.Tensor(rays))
    distance = hits["t_hit"].numpy().astype(np.float64)
    hit = np.isfinite(distance)
    measured = distance * (1.0 + DEPTH_NOISE_SHARE * rng.normal(size=distance.shape))
    depth = np.where(hit, measured * directions[:, 2], 0.0)
    source = np.where(hit, np.searchsorted(np.asarray(ids), hits["geometry_ids"].numpy()), -1)
    return depth.reshape(camera.height, camera.width), source.reshape(camera.height, camera.width)


def pose(rotation: np.ndarray, translation: np.ndarray) -> dict:
    transform = np.eye(4)
    transform[:3, :3], transform[:3, 3] = rotation, translation
    return {
        "rotation": np.round(rotation, 9).tolist(),
        "translation": np.round(translation, 9).tolist(),
        "transform": np.round(transform, 9).tolist(),
    }


def table_view(mesh: trimesh.Trimesh, scale: float, rng: np.random.Generator):
    """The part resting on a square table, seen from DISTANCE_SCALES scales at ELEVATION_DEG:
    the depth image in millimetres, the part's mask and the part's pose in the camera frame."""
    rest_rotation, rest_translation = resting_pose(mesh, stable_poses(mesh), rng)
    centre = rest_rotation @ surface_centroid(mesh) + rest_translation
    to_camera, position = look_at(
        centre, rng.uniform(0, 2 * np.pi), np.radians(ELEVATION_DEG), DISTANCE_SCALES * scale
    )
    rotation = to_camera @ rest_rotation
    translation = to_camera @ (rest_translation - position)
    half = TABLE_HALF_SIDE_SCALES * scale
    table = trimesh.creation.box((2 * half, 2 * half, 1e-3 * scale))
    table.apply_translation([centre[0], centre[1], -0.5e-3 * scale])
    table = placed(table, to_camera, -to_camera @ position)
    depth, source = depth_and_source([placed(mesh, rotation, translation), table], rng)
    millimetres = np.rint(depth * 1000.0).astype(np.uint16)
    mask = np.where(source == 0, 255, 0).astype(np.uint8)
    return millimetres, mask, rotation, translation


def scan_view(mesh: trimesh.Trimesh, scale: float, rng: np.random.Generator):
    """The part alone in a random pose, its centre on the optical axis DISTANCE_SCALES scales
    away: the camera-frame points of the pixels that see it, and the pose."""
    rotation = Rotation.random(random_state=rng).as_matrix()
    translation = np.array([0.0, 0.0, DISTANCE_SCALES * scale]) - rotation @ surface_centroid(mesh)
    depth, source = depth_and_source([placed(mesh, rotation, translation)], rng)
    rows, columns = np.nonzero(source == 0)
    cx, cy = CAMERA.principal_point
    z = depth[rows, columns]
    x = (columns + 0.5 - cx) * z / CAMERA.focal
    y = (rows + 0.5 - cy) * z / CAMERA.focal
    points = np.stack([x, y, z], axis=1)
    return points[rng.permutation(len(points))].astype(np.float32), rotation, translation


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", type=Path, default=REPO / "examples")
    args = parser.parse_args(argv)
    out = args.out_dir
    out.mkdir(parents=True, exist_ok=True)
    import pybullet_data  # the train extra

    source = load_mesh(Path(pybullet_data.getDataPath()) / SOURCE)
    mesh_path = out / f"{NAME}.stl"
    mesh_path.write_bytes(decimated(source, FACES).export(file_type="stl"))
    mesh = load_mesh(mesh_path)  # the file as the service reads it
    scale = float(radius(sample_surface(mesh, CLOUD_POINTS, 0)))
    rng = np.random.default_rng(SEED)

    depth, mask, depth_rotation, depth_translation = table_view(mesh, scale, rng)
    Image.fromarray(depth).save(out / "depth.png")
    Image.fromarray(mask).save(out / "part-mask.png")
    cx, cy = CAMERA.principal_point
    intrinsics = {"fx": CAMERA.focal, "fy": CAMERA.focal, "cx": cx - 0.5, "cy": cy - 0.5}
    camera = {**intrinsics, "width": CAMERA.width, "height": CAMERA.height, "depth_unit": "mm"}
    (out / "camera.json").write_text(json.dumps(camera, indent=2) + "\n")

    scan, scan_rotation, scan_translation = scan_view(mesh, scale, rng)
    trimesh.PointCloud(scan).export(out / "scan.ply", encoding="binary")

    cloud_rotation = Rotation.random(random_state=rng).as_matrix()
    cloud_translation = np.array([0.1, -0.05, 0.8])
    cloud = sample_surface(mesh, CLOUD_POINTS, SEED) @ cloud_rotation.T + cloud_translation
    (out / "cloud.f32").write_bytes(cloud.astype("<f4").tobytes())

    truth = {
        "part": NAME,
        "mesh": f"pybullet_data/{SOURCE}, decimated to {FACES} faces",
        "scale": scale,
        "convention": "scene_point = R @ model_point + t",
        "depth.png": {
            **pose(depth_rotation, depth_translation),
            "pixels": int(np.count_nonzero(depth)),
            "part_pixels": int(np.count_nonzero(mask)),
        },
        "scan.ply": {**pose(scan_rotation, scan_translation), "points": len(scan)},
        "cloud.f32": {**pose(cloud_rotation, cloud_translation), "points": CLOUD_POINTS},
    }
    (out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    for path in sorted(out.iterdir()):
        print(f"{path}: {path.stat().st_size:,} bytes")


if __name__ == "__main__":
    main()
