"""Shared fixtures: real meshes from pybullet_data, sampled as the service samples them, and
two real servers for the tests that only add references of their own names."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

from service.engine.sampling import sample_surface
from service.settings import AuthSettings, GallerySettings, Settings
from tests.backends import BACKENDS, Backend
from tests.meshes import pybullet_mesh
from tests.servers import ADMIN_KEY, MODEL, READ_KEY, Server


@pytest.fixture(scope="session")
def duck_points() -> np.ndarray:
    """An asymmetric real object: the duck, 2,048 surface points."""
    return sample_surface(pybullet_mesh("duck.obj"), 2048, 0).astype(np.float64)


@pytest.fixture(scope="session")
def postgres_server():
    """A throwaway PostgreSQL server for the session; the PostgreSQL cases skip without one."""
    from evaluation.postgres import ThrowawayPostgres, Unavailable

    try:
        server = ThrowawayPostgres()
    except Unavailable as error:
        pytest.skip(f"PostgreSQL cases need a server: {error}")
    yield server
    server.close()


@pytest.fixture(scope="module", params=BACKENDS)
def backend(request, tmp_path_factory) -> Backend:
    """Each gallery store backend in turn: SQLite, then PostgreSQL."""
    server = request.getfixturevalue("postgres_server") if request.param == "postgresql" else None
    return Backend(request.param, tmp_path_factory, server)


def empty_server(data_dir: Path, **groups) -> Server:
    """The shipped model, an empty gallery (so it starts at once), a one-render self-check."""
    if not MODEL.path.exists():
        pytest.skip(f"no ONNX model at {MODEL.path}")
    model = MODEL.model_copy(update={"gallery": data_dir / "no-seed.npz"})
    gallery = GallerySettings(data_dir=data_dir, self_check_poses=1)
    return Server(Settings(model=model, gallery=gallery, **groups))


def server_holding(data_dir: Path, meshes: dict, **groups) -> Server:
    """``empty_server`` (its settings' ``groups``) with each of ``meshes`` (trimesh meshes, by
    name) registered through its API as an STL upload, without the self-check."""
    server = empty_server(data_dir, **groups)
    for name, mesh in meshes.items():
        buffer = io.BytesIO()
        mesh.export(buffer, file_type="stl")
        answer = server.client.post(
            "/references",
            data={"name": name},
            files={"file": (f"{name}.stl", buffer.getvalue())},
            params={"self_check": "false"},
        )
        assert answer.status_code == 201, answer.text
    return server


@pytest.fixture(scope="session")
def service(tmp_path_factory):
    """One real server (uvicorn in a thread, the shipped model, open, so keeping recent
    alignments) with two real parts registered through its API, the mug and the bunny of
    pybullet_data, shared by the tests that only add references of their own names."""
    pybullet_data = pytest.importorskip("pybullet_data")
    server = empty_server(tmp_path_factory.mktemp("service"))
    for name, mesh in (("mug", "objects/mug.obj"), ("bunny", "bunny.obj")):
        path = Path(pybullet_data.getDataPath()) / mesh
        answer = server.client.post(
            "/references",
            data={"name": name},
            files={"file": (path.name, path.read_bytes())},
            params={"self_check": "false"},
        )
        assert answer.status_code == 201, answer.text
    yield server
    server.stop()


@pytest.fixture(scope="session")
def keyed_service(tmp_path_factory):
    """A server with an admin and a read key and an empty gallery."""
    keys = AuthSettings(keys={ADMIN_KEY: "admin", READ_KEY: "read"})
    server = empty_server(tmp_path_factory.mktemp("keyed"), auth=keys)
    yield server
    server.stop()
