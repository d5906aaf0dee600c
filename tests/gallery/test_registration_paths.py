"""Registration's faster paths give the same bits as the plain ones: the rendered views' dense
depth buffer and the sorted pixels, the network's single-threaded session and its main one, the
registration check's renders aligned two at a time and one after another. Real meshes of
pybullet_data, the shipped model."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from service.engine import engine as engine_module
from service.engine import views
from service.engine.engine import Engine
from service.engine.mapping import Mapper
from service.engine.normalize import normalize, radius
from service.engine.sampling import sample_surface_faces
from service.settings import EngineSettings
from tests.meshes import pybullet_mesh
from tests.servers import MODEL

pytestmark = pytest.mark.skipif(not MODEL.path.exists(), reason=f"no ONNX model at {MODEL.path}")
MESHES = ("duck.obj", "objects/mug.obj", "cube.obj", "bunny.obj")


@pytest.fixture(scope="module")
def mapper() -> Mapper:
    return Mapper(MODEL.path)


@pytest.mark.parametrize("mesh_file", MESHES)
def test_the_dense_depth_buffer_sees_what_sorting_sees(mesh_file, monkeypatch):
    mesh = pybullet_mesh(mesh_file)
    points = sample_surface_faces(mesh, 2048, 0)[0].astype(np.float64)
    scale = radius(points)
    surface = np.asarray(trimesh.sample.sample_surface(mesh, 12000, seed=1)[0])
    dense = [views.render(points, scale, 100, surface, mesh.area), views.render(points, scale, 100)]
    monkeypatch.setattr(views, "_nearest_in_pixel", views._nearest_sorted)
    plain = [views.render(points, scale, 100, surface, mesh.area), views.render(points, scale, 100)]
    for fast, sorted_ in zip(dense, plain, strict=True):
        assert np.array_equal(fast, sorted_)
        assert 0 < fast.sum() < fast.size  # each view sees some points, not all


def test_the_quiet_session_maps_the_same_bits(mapper):
    rng = np.random.default_rng(3)
    for count in (16, 300, 512, 1024, 2048):
        cloud = normalize(rng.normal(size=(count, 3)) * [1, 2, 3], mapper.canonical).points
        assert np.array_equal(mapper.map(cloud, quiet=True), mapper.map(cloud))


def test_the_check_s_renders_two_at_a_time_answer_as_one_after_another(mapper, monkeypatch):
    engine = Engine(mapper, EngineSettings(view_grids=4))
    mesh = pybullet_mesh("duck.obj")
    points, faces = sample_surface_faces(mesh, 2048, 0)
    duck = engine.make_reference("duck", points, mesh=mesh, face_index=faces)
    engine.load(
        [
            duck,
            engine.make_reference(
                "mug", sample_surface_faces(pybullet_mesh("objects/mug.obj"), 2048, 0)[0]
            ),
        ]
    )
    together = engine.self_check(duck, 3, mesh)
    monkeypatch.setattr(engine_module, "SELF_CHECK_THREADS", 1)
    assert engine.self_check(duck, 3, mesh) == together
    assert [check["render"] for check in together] == ["full", "view", "view", "view"]
