"""Write the README's sample cloud: one seen object, resampled, in a known pose.

``python scripts/make_sample.py`` writes

- ``models/sample_cloud.json``: ``{"points": [[x, y, z], ...]}``, the body of ``POST /align``:
  2,048 points sampled on the surface of the manifest's first seen household object (seed 7,
  never the reference's seed 0), moved by a rotation uniform over SO(3) and a translation
  (``scene = R @ model + t``), shuffled, rounded to 5 decimals;
- ``models/sample_cloud_pose.json``: the true label, rotation, translation and 4x4 transform.

Then align it with the running service::

    curl -s -X POST localhost:8000/align -H 'Content-Type: application/json' \\
        --data @models/sample_cloud.json

Needs the training extras (``pybullet`` for its meshes), not the model.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from pypcd4 import Encoding, PointCloud
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

from service.engine.sampling import sample_surface  # noqa: E402
from training.objects import data_root, load_manifest, load_object_meshes  # noqa: E402

POINTS = 2048
SEED = 7
DECIMALS = 5
CURL = (
    "curl -s -X POST localhost:8000/align -H 'Content-Type: application/json' "
    "--data @models/sample_cloud.json"
)


def default_object() -> str:
    """The manifest's first seen household object."""
    for spec in load_manifest(split="seen"):
        if spec.category == "household object":
            return spec.name
    raise SystemExit("the manifest has no seen household object: pass --object")


def mesh_name(path: Path) -> str:
    """The mesh file as the manifest names it: relative to pybullet_data when it lies there."""
    try:
        return f"pybullet_data/{path.relative_to(data_root()).as_posix()}"
    except ValueError:
        return str(path)


def make_sample(name: str, points: int = POINTS, seed: int = SEED) -> tuple[dict, dict]:
    """The request body and the true pose of the sample cloud of object ``name``."""
    specs = {spec.name: spec for spec in load_manifest(split="seen")}
    if name not in specs:
        raise SystemExit(f"{name!r} is not a seen object of the manifest")
    mesh = load_object_meshes([specs[name]])[name]
    rng = np.random.default_rng(seed)
    model = sample_surface(mesh, points, seed).astype(np.float64)
    centred = model - model.mean(axis=0)
    scale = float(np.linalg.norm(centred, axis=1).max())
    rotation = Rotation.random(random_state=rng).as_matrix()
    # in front of a sensor: half a metre along its optical axis, a little off centre
    translation = np.array([0.05, -0.03, 0.5]) + rng.uniform(-1.0, 1.0, 3) * scale
    scene = model @ rotation.T + translation
    scene = np.round(scene[rng.permutation(len(scene))], DECIMALS)
    transform = np.eye(4)
    transform[:3, :3], transform[:3, 3] = rotation, translation
    body = {"points": scene.tolist()}
    pose = {
        "label": name,
        "rotation": rotation.tolist(),
        "translation": translation.tolist(),
        "transform": transform.tolist(),
        "convention": "scene_point = R @ model_point + t",
        "scale": scale,
        "points": points,
        "sampling_seed": seed,
        "mesh": mesh_name(specs[name].path),
    }
    return body, pose


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--object", help="a seen object (default: the first household object)")
    parser.add_argument("--out-dir", type=Path, default=REPO / "models")
    parser.add_argument("--points", type=int, default=POINTS)
    parser.add_argument("--seed", type=int, default=SEED)
    args = parser.parse_args(argv)
    name = args.object or default_object()
    body, pose = make_sample(name, args.points, args.seed)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    cloud_path = args.out_dir / "sample_cloud.json"
    pose_path = args.out_dir / "sample_cloud_pose.json"
    pcd_path = args.out_dir / "sample_cloud.pcd"
    cloud_path.write_text(json.dumps(body, separators=(",", ":")) + "\n")
    pose_path.write_text(json.dumps(pose, indent=2) + "\n")
    points = np.asarray(body["points"], dtype=np.float32)
    PointCloud.from_xyz_points(points).save(pcd_path, Encoding.BINARY)
    print(f"wrote {cloud_path}, {pcd_path} ({len(points)} points of {name!r}) and {pose_path}")
    print("align it with the service running on port 8000:")
    print(f"  {CURL}")


if __name__ == "__main__":
    main()
