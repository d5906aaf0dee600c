"""``service.client`` and the ``dpc-mn`` command against a real server, and the command lines
``python -m service --help`` / ``--port``.

The pose round-trips exactly: the points go as raw float32 and the answer's numbers come back
as the service computed them (the engine's own answer for the same float32 points)."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from pypcd4 import PointCloud
from scipy.spatial.transform import Rotation

from evaluation.served import service_env
from service.client import (
    Client,
    DepthCamera,
    Forbidden,
    InvalidInput,
    NotFound,
    Unauthorized,
    Unreachable,
)
from service.client.cli import main
from service.engine.sampling import sample_surface
from tests.camera import INTRINSICS, depth_image
from tests.meshes import pybullet_mesh
from tests.servers import READ_KEY, REPO, free_port, wait_ready

ROTATION = Rotation.from_euler("zyx", [40, 25, -60], degrees=True).as_matrix()
TRANSLATION = np.array([0.03, -0.02, 0.5])


@pytest.fixture(scope="module")
def client(service):
    with Client(service.url) as client:
        yield client


@pytest.fixture(scope="module")
def scan() -> np.ndarray:
    """The mug seen whole in a known pose, float64: the client sends it as float32."""
    mug = pybullet_mesh("objects/mug.obj")
    return sample_surface(mug, 2048, seed=11).astype(np.float64) @ ROTATION.T + TRANSLATION


def test_a_pose_round_trips_exactly(client, service, scan):
    pose = client.align(scan, candidates=["mug", "bunny"])
    sent = scan.astype(np.float32)  # what travels: little-endian float32
    engine = service.app.state.catalog.engine
    expected = engine.align(sent, ["mug", "bunny"], None, True, viewpoint=None)
    assert pose.label == expected.label == "mug"
    np.testing.assert_array_equal(pose.rotation, expected.rotation)
    np.testing.assert_array_equal(pose.translation, expected.translation)
    assert pose.alignment_error == expected.alignment_error
    assert pose.transform[:3, :3].tolist() == pose.rotation.tolist()
    assert pose.transform[:3, 3].tolist() == pose.translation.tolist()
    assert pose.transform[3].tolist() == [0, 0, 0, 1]
    assert pose.verdict in ("match", "uncertain", "no_match")
    assert pose.raw["label"] == "mug" and "total" in pose.timings_ms
    placed = pose.apply(sample_surface(pybullet_mesh("objects/mug.obj"), 500, seed=1))
    assert np.abs(placed.mean(axis=0) - scan.mean(axis=0)).max() < 0.01  # where the mug is


def test_the_viewpoint_and_the_points_arrive_exactly(client, service, scan):
    viewpoint = [0.1, -0.2, 1 / 3]
    client.align(scan, viewpoint=viewpoint, candidates=["mug"], min_confidence=0.25)
    latest = service.client.get("/alignments").json()["alignments"][0]
    assert latest["viewpoint"] == viewpoint
    points = service.client.get(f"/alignments/{latest['id']}/points").content
    assert points == scan.astype("<f4").tobytes()


def test_register_describe_list_and_delete(client, scan):
    registered = client.register("client-points", scan - scan.mean(axis=0), self_check=False)
    sent = (scan - scan.mean(axis=0)).astype("<f4").tobytes()
    assert registered.points_sha256 == hashlib.sha256(sent).hexdigest()
    assert registered.num_points == 2048 and registered.self_check is None
    assert client.reference("client-points").points_sha256 == registered.points_sha256
    assert client.reference_points("client-points").tobytes() == sent
    assert "client-points" in [reference.name for reference in client.references()]
    client.delete("client-points")
    assert "client-points" not in [reference.name for reference in client.references()]
    with pytest.raises(NotFound, match="client-points"):
        client.delete("client-points")


def test_register_a_mesh_file(client):
    path = Path(pytest.importorskip("pybullet_data").getDataPath()) / "duck.obj"
    reference = client.register("client-duck", path, replace=True)
    assert reference.num_points == 2048 and reference.self_check  # the service's self-check
    assert reference.symmetry["kind"] in ("none", "revolution", "discrete")
    assert isinstance(reference.warnings, list)
    client.delete("client-duck")


def test_align_a_camera_s_files(client, service, scan, tmp_path):
    pcd = tmp_path / "scan.pcd"
    PointCloud.from_xyz_points(scan.astype(np.float32)).save(pcd)
    assert client.align_file(pcd, candidates=["mug"]).label == "mug"
    depth = depth_image(pybullet_mesh("objects/mug.obj"), ROTATION, TRANSLATION)
    png = tmp_path / "depth.png"
    Image.fromarray(np.rint(depth * 1000).astype(np.uint16)).save(png)
    camera = DepthCamera(**INTRINSICS)
    points, viewpoint = client.read_points(png, camera)
    assert viewpoint == [0, 0, 0] and len(points) == np.count_nonzero(depth)
    client.align_file(png, candidates=["mug"], camera=camera, top_k=1)
    assert service.client.get("/alignments").json()["alignments"][0]["viewpoint"] == [0, 0, 0]


def test_errors_carry_the_service_s_detail(client):
    with pytest.raises(NotFound) as unknown:
        client.align(np.random.default_rng(0).normal(size=(100, 3)), candidates=["no-such-part"])
    assert unknown.value.status == 404 and "no-such-part" in unknown.value.detail
    assert unknown.value.request_id
    with pytest.raises(InvalidInput, match="fewer than the minimum"):
        client.align(np.random.default_rng(0).normal(size=(3, 3)))
    with pytest.raises(InvalidInput, match="name"):
        client.register("not a name!", np.random.default_rng(0).normal(size=(100, 3)))
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        client.align(np.zeros((10, 2)))
    with Client(f"http://127.0.0.1:{free_port()}", timeout=2, retry_for=0) as nobody:
        with pytest.raises(Unreachable, match="cannot reach"):
            nobody.references()


def test_the_key_is_sent_as_the_api_expects(keyed_service):
    with Client(keyed_service.url) as anonymous, pytest.raises(Unauthorized, match="API key"):
        anonymous.references()
    with Client(keyed_service.url, api_key=READ_KEY) as reader:
        assert isinstance(reader.references(), list)
        with pytest.raises(Forbidden, match="'admin'"):
            reader.register("x", np.random.default_rng(0).normal(size=(100, 3)))


def run(capsys, *argv: str) -> tuple[int, str, str]:
    """``dpc-mn ARGV`` in this process: the exit status, stdout and stderr."""
    try:
        status = main(list(argv))
    except SystemExit as exit_:  # argparse: --help, usage errors
        status = exit_.code
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def test_the_command_line(service, scan, tmp_path, capsys):
    url = ("--url", service.url)
    cloud = tmp_path / "scan.npy"
    np.save(cloud, scan.astype(np.float32))
    status, out, _ = run(capsys, "register", str(cloud), "--name", "cli-mug", *url, "--json")
    assert status == 0 and json.loads(out)["name"] == "cli-mug"
    status, out, _ = run(capsys, "align", str(cloud), "--candidates", "cli-mug,bunny", *url)
    assert status in (0, 3) and "cli-mug" in out and "rotation" in out
    status, out, _ = run(capsys, "align", str(cloud), "--candidates=cli-mug", "--json", *url)
    answer = json.loads(out)
    assert status == (0 if answer["verdict"] == "match" else 3) and answer["label"] == "cli-mug"
    status, out, _ = run(capsys, "references", *url)
    assert status == 0 and "cli-mug" in out
    assert run(capsys, "delete", "cli-mug", *url)[0] == 0
    status, out, err = run(capsys, "delete", "cli-mug", *url, "--json")
    assert status == 1 and json.loads(out)["error"]["status"] == 404 and "cli-mug" in err
    status, _, err = run(capsys, "align", str(tmp_path / "missing.pcd"), *url)
    assert status == 1 and "missing.pcd" in err
    status, _, err = run(capsys, "health", "--url", f"http://127.0.0.1:{free_port()}")
    assert status == 4 and "cannot reach" in err
    assert run(capsys, "align", "--viewpoint", "1,2", str(cloud))[0] == 2
    for command in ("", "align", "register", "references", "delete", "health", "serve"):
        status, out, _ = run(capsys, *command.split(), "--help")
        assert status == 0 and "usage: dpc-mn" in out, command


def test_the_service_s_command_lines(tmp_path):
    """``python -m service --help`` helps; ``dpc-mn serve --port`` wins over DPC_SERVER__PORT."""
    helped = subprocess.run(
        [sys.executable, "-m", "service", "--help"], cwd=REPO, capture_output=True, text=True
    )
    assert helped.returncode == 0 and "--port" in helped.stdout and "DPC_" in helped.stdout
    port = free_port()
    env = service_env(free_port(), gallery__data_dir=str(tmp_path))  # another port in the env
    command = Path(sys.executable).parent / "dpc-mn"
    process = subprocess.Popen([str(command), "serve", "--port", str(port)], cwd=REPO, env=env)
    try:
        wait_ready(f"http://127.0.0.1:{port}", lambda: process.poll() is None, live_only=True)
    finally:
        process.terminate()
        process.wait(timeout=30)
    assert os.path.exists(tmp_path / "gallery.sqlite3")
