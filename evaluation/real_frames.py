"""Real depth frames from public robotics data (docs/evaluation-protocol.md, ``real``), posted to
``POST /detect`` as their drivers wrote them, with their parts' models registered.

- ``pcl-milk`` (shipped, tests/data/real/pcl-milk, BSD): PCL's Kinect-class frame of a milk
  carton, a cartoon and a Clorox bottle, an organized PCD; the carton's model is its own
  points, so its pose is the identity.
- ``ycb-video`` (not shipped: GPL-3 repository): frame 000002 of a YCB-Video sequence (Asus
  Xtion, a 16-bit depth PNG in 0.1 mm) with the master chef can's model points and the
  dataset's pose of it, from github.com/xbliuhnu/6DoF-Pose-Visualization (``data/`` and
  ``models/002_master_chef_can``).
- ``apc-shelf`` (not shipped, BSD-2): a frame of the Amazon Picking Challenge 2016 sample scene
  (Intel RealSense F200, depth aligned to colour in 0.1 mm, bits rotated by 3) with the
  pre-scanned model of the chenille stems lying in the bin, from
  github.com/andyzeng/apc-vision-toolbox (``data/sample/scene-0000``,
  ``ros-packages/catkin_ws/src/pose_estimation/src/models/objects``); no reference pose.

    python -m evaluation.real_frames --ycb DIR --apc DIR    # the shipped frame and these
"""

from __future__ import annotations

import argparse
import io
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evaluation.metrics import SUCCESS_ADD_S, add_s, diameter, geodesic_deg

FIXTURES = Path(__file__).resolve().parent.parent / "tests" / "data" / "real"
MODEL_POINTS = 8192  # a model cloud larger than this is registered as a random subset


@dataclass
class RealFrame:
    """A real frame ready to post, the part's model and what is known of its pose."""

    name: str
    sensor: str
    label: str
    model: np.ndarray  # (N, 3) the part's model points, the frame's units
    files: dict  # multipart files of POST /detect
    data: dict  # ... and fields
    rotation: np.ndarray | None = None  # the reference pose, where known
    translation: np.ndarray | None = None


def pcl_milk(folder: Path = FIXTURES / "pcl-milk") -> RealFrame:
    from pypcd4 import PointCloud

    meta = json.loads((folder / "frame.json").read_text())
    model = PointCloud.from_path(folder / meta["model"]).numpy(("x", "y", "z"))
    scene = folder / meta["scene"]
    pose = meta["reference_pose"]
    return RealFrame(
        "pcl-milk", meta["sensor"], meta["label"], model.astype(np.float64),
        {"file": (scene.name, scene.read_bytes())}, {},
        np.array(pose["rotation"], float), np.array(pose["translation"], float),
    )  # fmt: skip


def ycb_video(folder: Path) -> RealFrame:
    """``000002-depth.png``, ``000002-meta.mat`` and ``points.xyz`` (the can) in ``folder``."""
    import scipy.io

    meta = scipy.io.loadmat(folder / "000002-meta.mat")
    camera = meta["intrinsic_matrix"]
    can = list(meta["cls_indexes"].ravel()).index(1)  # YCB class 1: 002_master_chef_can
    pose = meta["poses"][:, :, can]
    data = {
        "fx": camera[0, 0], "fy": camera[1, 1], "cx": camera[0, 2], "cy": camera[1, 2],
        "depth_scale": 1.0 / float(meta["factor_depth"].item()),
    }  # fmt: skip
    depth = (folder / "000002-depth.png").read_bytes()
    return RealFrame(
        "ycb-video", "Asus Xtion Pro Live (YCB-Video), 640 x 480", "master-chef-can",
        np.loadtxt(folder / "points.xyz"), {"file": ("000002-depth.png", depth, "image/png")},
        {k: str(v) for k, v in data.items()}, pose[:, :3], pose[:, 3],
    )  # fmt: skip


def apc_shelf(folder: Path, frame: int = 9) -> RealFrame:
    """``frame-0000NN.depth.png`` (aligned to colour), ``cam.info.txt`` and
    ``creativity_chenille_stems.ply`` in ``folder``."""
    import trimesh
    from PIL import Image

    raw = np.asarray(Image.open(folder / f"frame-{frame:06d}.depth.png")).astype(np.uint32)
    tenths = (((raw << 13) | (raw >> 3)) & 0xFFFF).astype(np.uint16)  # the toolbox's readDepth
    buffer = io.BytesIO()
    Image.fromarray(tenths).save(buffer, format="PNG")
    lines = (folder / "cam.info.txt").read_text().splitlines()
    start = lines.index("# Color camera intrinsic matrix") + 1
    camera = np.array([[float(x) for x in lines[start + k].split()] for k in range(3)])
    model = np.asarray(trimesh.load(folder / "creativity_chenille_stems.ply").vertices, float)
    data = {  # MATLAB's 1-based pixels: the top-left pixel's centre is (1, 1)
        "fx": camera[0, 0], "fy": camera[1, 1], "cx": camera[0, 2] - 1, "cy": camera[1, 2] - 1,
        "depth_scale": 1e-4,
    }  # fmt: skip
    return RealFrame(
        "apc-shelf", "Intel RealSense F200 (APC 2016), 640 x 480", "chenille-stems", model,
        {"file": (f"frame-{frame:06d}.depth.png", buffer.getvalue(), "image/png")},
        {k: str(v) for k, v in data.items()},
    )  # fmt: skip


def register_model(client, frame: RealFrame) -> None:
    model = frame.model
    if len(model) > MODEL_POINTS:
        model = model[np.random.default_rng(0).choice(len(model), MODEL_POINTS, replace=False)]
    answer = client.post(
        "/references",
        json={"name": frame.label, "points": np.asarray(model, float).tolist()},
        params={"replace": "true", "self_check": "false"},
    )
    if answer.status_code not in (200, 201):
        raise RuntimeError(f"registering {frame.label}: {answer.status_code} {answer.text}")


def real_record(client, frame: RealFrame) -> dict:
    """``POST /detect`` of the frame, its model registered: what was answered of the part."""
    register_model(client, frame)
    deadline = time.monotonic() + 300.0
    while True:  # a 503 (every slot busy) is retried, as the answer says
        began = time.perf_counter()
        answer = client.post("/detect", files=frame.files, data=frame.data)
        latency = (time.perf_counter() - began) * 1e3
        if answer.status_code != 503 or time.monotonic() > deadline:
            break
        time.sleep(0.5)
    record = {"frame": frame.name, "sensor": frame.sensor, "label": frame.label}
    if answer.status_code != 200:
        error = f"{answer.status_code}: {answer.text[:300]}"
        return record | {"error": error, "latency_ms": latency}
    body = answer.json()
    mine = [d for d in body["detections"] if d["label"] == frame.label]
    best = max(mine, key=lambda d: d.get("confidence") or 0, default=None)
    others = [d for d in body["detections"] if d is not best and d["verdict"] == "match"]
    record |= {
        "latency_ms": latency,
        "num_points": body["num_points"],
        "detections": len(body["detections"]),
        "other_matches": [d["label"] for d in others],
        "verdict": None if best is None else best["verdict"],
        "confidence": None if best is None else best.get("confidence"),
        "num_points_claimed": None if best is None else best["num_points"],
    }
    if best is not None and frame.rotation is not None:
        error = add_s(
            frame.model, best["rotation"], best["translation"], frame.rotation,
            frame.translation, diameter(frame.model),
        )  # fmt: skip
        record |= {
            "add_s": error,
            "rotation_error_deg": geodesic_deg(best["rotation"], frame.rotation),
            "found": best["verdict"] == "match" and error < SUCCESS_ADD_S,
        }
    return record


def main(argv: list[str] | None = None) -> list[dict]:
    import httpx

    from evaluation.served import ServiceProcess

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ycb", type=Path, help="a folder holding the YCB-Video sample")
    parser.add_argument("--apc", type=Path, help="a folder holding the APC 2016 sample frame")
    parser.add_argument("--apc-frame", type=int, default=9)
    args = parser.parse_args(argv)
    frames = [pcl_milk()]
    if args.ycb:
        frames.append(ycb_video(args.ycb))
    if args.apc:
        frames.append(apc_shelf(args.apc, args.apc_frame))
    import tempfile

    records = []
    with tempfile.TemporaryDirectory(prefix="dpc-real-") as tmp:
        with ServiceProcess(
            Path(tmp) / "service.log", 300.0, gallery__data_dir=tmp, limits__request_timeout_s="300"
        ) as service:
            with httpx.Client(base_url=service.url, timeout=360.0) as client:
                for frame in frames:
                    records.append(real_record(client, frame))
                    print(json.dumps(records[-1]))
    return records


if __name__ == "__main__":
    main()
