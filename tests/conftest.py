"""Shared fixtures: real meshes from pybullet_data, sampled as the service samples them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.engine.sampling import load_mesh, sample_surface

REPO = Path(__file__).resolve().parent.parent


def pybullet_mesh(relative: str):
    pybullet_data = pytest.importorskip("pybullet_data")
    return load_mesh(Path(pybullet_data.getDataPath()) / relative)


@pytest.fixture(scope="session")
def duck_points() -> np.ndarray:
    """An asymmetric real object: the duck, 2,048 surface points."""
    return sample_surface(pybullet_mesh("duck.obj"), 2048, 0).astype(np.float64)
