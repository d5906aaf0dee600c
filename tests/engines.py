"""The real engine for the tests that search frames: the shipped model and calibration, and a
gallery of the given meshes, each sampled and registered as ``POST /references`` would."""

from __future__ import annotations

import pytest
import trimesh

from service.engine.confidence import Calibration
from service.engine.engine import Engine
from service.engine.mapping import Mapper
from service.engine.sampling import sample_surface_faces
from service.settings import Settings

SETTINGS = Settings()


def engine_holding(meshes: dict[str, trimesh.Trimesh]) -> Engine:
    """An engine whose gallery holds ``meshes`` (by name), 2,048 surface points each; the test
    is skipped where the shipped model is missing."""
    if not SETTINGS.model.path.exists():
        pytest.skip(f"no ONNX model at {SETTINGS.model.path}")
    engine = Engine(
        Mapper.from_settings(SETTINGS.model),
        SETTINGS.engine,
        Calibration.load(SETTINGS.confidence_path),
    )
    return registered(engine, meshes)


def registered(engine: Engine, meshes: dict[str, trimesh.Trimesh]) -> Engine:
    """``engine`` holding each of ``meshes``, registered from 2,048 points on its faces."""
    references = []
    for name, mesh in meshes.items():
        points, faces = sample_surface_faces(mesh, 2048, 0)
        references.append(engine.make_reference(name, points, mesh=mesh, face_index=faces))
    engine.load(references)
    return engine
