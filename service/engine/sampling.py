"""Meshes to point clouds: read a mesh file and sample its surface, area-weighted.

Shared by training (the object set), the evaluation (resampled test clouds) and
the service (a mesh uploaded to ``POST /references``), so all three sample alike.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

MESH_SUFFIXES = (".obj", ".stl", ".ply", ".off", ".glb", ".gltf", ".dae")


class MeshError(ValueError):
    """A file that does not hold a usable triangle mesh."""


def load_mesh(source: str | Path, file_type: str | None = None) -> trimesh.Trimesh:
    """Read a mesh file (or file object with ``file_type``) as one triangle mesh.

    A scene of several meshes is merged in its own frame, with each node's transform applied.
    """
    try:
        loaded = trimesh.load(source, file_type=file_type, force="mesh", process=False)
    except Exception as error:  # trimesh raises many types for unreadable files
        raise MeshError(f"cannot read the mesh: {error}") from error
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshError("the file holds no triangles")
    if loaded.vertices.ndim != 2 or loaded.vertices.shape[1] != 3:
        # an OBJ's "v 0.5" lines read as vertices of one coordinate
        raise MeshError("the mesh's vertices are not x y z triples")
    if loaded.faces.min() < 0 or loaded.faces.max() >= len(loaded.vertices):
        raise MeshError("a face refers to a vertex the file does not have")
    if not np.isfinite(loaded.vertices).all():
        raise MeshError("the mesh has non-finite vertex coordinates")
    if loaded.area <= 0:
        raise MeshError("the mesh has no surface area")
    return loaded


def sample_surface(mesh: trimesh.Trimesh, count: int, seed: int) -> np.ndarray:
    """``count`` points on the surface, area-weighted, the same for the same seed.

    Returns a (count, 3) float32 array in the mesh's own frame.
    """
    return sample_surface_faces(mesh, count, seed)[0]


def sample_surface_faces(
    mesh: trimesh.Trimesh, count: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """``sample_surface``'s points and the index of the face each lies on."""
    points, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points, dtype=np.float32), np.asarray(faces, dtype=np.intp)
