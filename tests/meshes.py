"""Meshes for the tests: pybullet_data's real ones, and STL files as CAD tools write them."""

from __future__ import annotations

from pathlib import Path

import pytest
import trimesh

from service.engine.sampling import load_mesh


def pybullet_mesh(relative: str) -> trimesh.Trimesh:
    """A mesh of pybullet_data (the train extra), by its path there; the test skips without."""
    pybullet_data = pytest.importorskip("pybullet_data")
    return load_mesh(Path(pybullet_data.getDataPath()) / relative)


# text STLs from CAD tools that write their own code page: trimesh decodes them with
# charset_normalizer, which the runtime dependencies must bring (deploy/test_runtime_install.py)
LATIN1_STL = (
    "solid pi\xe8ce\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 0.1 0 0\n"
    "vertex 0 0.1 0\nendloop\nendfacet\nendsolid pi\xe8ce\n".encode("latin-1")
)
BROKEN_STL = b"solid part\n\xff\xfe facet normal 0 0 1\nendsolid\n"
