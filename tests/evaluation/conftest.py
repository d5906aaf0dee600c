"""Frames shared by the whole-frame tests: real pybullet_data meshes dropped by pybullet's
physics and ray cast by Open3D (evaluation.frames), one scene and one bin frame a session."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.engine.sampling import load_mesh

pytest.importorskip("pybullet")
pytest.importorskip("open3d")
frames = pytest.importorskip("evaluation.frames")

PARTS = {  # name: (mesh in pybullet_data, how its units are guessed)
    "mug": "objects/mug.obj",  # metres
    "diff-ring": "differential/diff_ring.stl",  # millimetres
    "random-000": "random_urdfs/000/000.obj",  # procedural, 2-6 units
    "lego-brick": "lego/lego.obj",
    "duck": "duck.obj",
}
FOREIGN = {"realsense-d435i": "quadruped/microtaur/d435i.stl"}


def _parts(names: dict[str, str], registered: bool) -> list:
    import pybullet_data

    root = Path(pybullet_data.getDataPath())
    return [frames.frame_part(n, load_mesh(root / p), registered) for n, p in names.items()]


@pytest.fixture(scope="session")
def parts():
    return _parts(PARTS, True), _parts(FOREIGN, False)


@pytest.fixture(scope="session")
def scene(parts):
    return frames.make_frame("scene", 3, 0, *parts)


@pytest.fixture(scope="session")
def bin_frame(parts):
    return frames.make_frame("bin", 0, 0, *parts)
