"""Uploaded files to points: a mesh is sampled on its surface, a cloud is used as is.

Meshes: STL, OBJ, PLY with faces (trimesh). Clouds: PLY without faces (trimesh), PCD (ascii,
binary or binary_compressed: ``service.api.pcd``, pypcd4), NPY of shape (N, 3) (numpy). The
kind is told by the file name's suffix, else by the file's first bytes.
Every unusable file raises ``InvalidPoints`` naming the problem; the points returned are not
yet validated (``service.api.validation.validate_points`` does that).
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass
from pathlib import PurePath

import numpy as np
import trimesh

from service.api import ply
from service.api.clouds import Cloud, organized
from service.api.pcd import read_pcd
from service.engine.sampling import MeshError, load_mesh, sample_surface_faces
from service.engine.units import UNITS
from service.errors import InvalidPoints

SUFFIXES = (".stl", ".obj", ".ply", ".pcd", ".npy")
NPY_MAGIC = b"\x93NUMPY"


@dataclass(frozen=True)
class Upload:
    """What an uploaded file gives a registration: points, and the mesh they were sampled on."""

    points: np.ndarray  # (N, 3), not yet validated
    mesh: trimesh.Trimesh | None = None
    face_index: np.ndarray | None = None  # the face each point was sampled on
    index: np.ndarray | None = None  # an organized cloud's: each point's pixel
    shape: tuple[int, int] | None = None  # ... and its grid (height, width)

    @classmethod
    def of(cls, cloud: Cloud) -> Upload:
        return cls(cloud.points, index=cloud.index, shape=cloud.shape)


def in_metres(
    points: np.ndarray, mesh: trimesh.Trimesh | None, units: str | None
) -> tuple[np.ndarray, trimesh.Trimesh | None]:
    """Points (float32) and the mesh they were sampled on, sent in ``units`` (``m``, ``mm``,
    ``cm``, ``in``; None: as sent), in metres."""
    factor = UNITS[units or "m"]
    if factor == 1.0:
        return points, mesh
    scaled = (np.asarray(points, dtype=np.float64) * factor).astype(np.float32)
    return scaled, None if mesh is None else mesh.copy().apply_scale(factor)


def read_points(
    data: bytes, filename: str | None, mesh_points: int, max_points: int, seed: int = 0
) -> np.ndarray:
    """The points an uploaded file holds: (N, 3), a mesh sampled to ``mesh_points`` points."""
    return read_upload(data, filename, mesh_points, max_points, seed).points


def read_upload(
    data: bytes, filename: str | None, mesh_points: int, max_points: int, seed: int = 0
) -> Upload:
    """An uploaded file's points, with its mesh when it is one; ``max_points`` bounds what a
    file's header may announce before its data is read."""
    if not data:
        raise InvalidPoints("the uploaded file is empty")
    kind = file_kind(data, filename)
    if kind == ".npy":
        return Upload.of(read_npy(data, max_points))
    if kind == ".pcd":
        return Upload.of(read_pcd(data, max_points))
    if kind == ".ply":
        header = ply.read_header(data)
        ply.check_body(header, data)
        if not header.has_faces:
            return Upload(read_ply_cloud(data))
    try:
        mesh = load_mesh(io.BytesIO(data), file_type=kind.lstrip("."))
    except MeshError as error:
        raise InvalidPoints(f"the {kind.lstrip('.').upper()} mesh is unusable: {error}") from error
    points, faces = sample_surface_faces(mesh, mesh_points, seed=seed)
    return Upload(points, mesh, faces)


def file_kind(data: bytes, filename: str | None) -> str:
    """``.stl`` | ``.obj`` | ``.ply`` | ``.pcd`` | ``.npy`` by suffix, else by content."""
    suffix = PurePath(filename or "").suffix.lower()
    if suffix in SUFFIXES:
        return suffix
    head = data[:256]
    if head.startswith(NPY_MAGIC):
        return ".npy"
    if head.startswith(b"ply"):
        return ".ply"
    if re.match(rb"\s*(#[^\n]*\n\s*)*VERSION\s", head) or head.startswith(b"# .PCD"):
        return ".pcd"
    if len(data) >= 84 and 84 + 50 * int.from_bytes(data[80:84], "little") == len(data):
        return ".stl"  # binary STL: an 80-byte header, a count, 50 bytes a triangle
    if head.lstrip().startswith(b"solid"):
        return ".stl"
    what = f"'{filename}'" if filename else "the file"
    raise InvalidPoints(
        f"cannot tell what {what} holds: upload a mesh (.stl, .obj, .ply) or a cloud "
        "(.ply, .pcd, .npy) with its suffix in the file name"
    )


def shape_hint(array: np.ndarray) -> str:
    """What to send instead of an array of the shape of two common layouts: more channels
    than x, y, z (XYZRGB, XYZW), or its channels first."""
    if array.ndim in (2, 3) and array.shape[0] == 3:
        return ": its channels come first; send np.moveaxis(array, 0, -1)"
    if array.ndim in (2, 3) and array.shape[-1] > 3:
        return (
            f": if its first three of {array.shape[-1]} channels are x, y and z (XYZRGB, "
            "XYZW), send array[..., :3]"
        )
    return ""


def read_npy(data: bytes, max_points: int) -> Cloud:
    """An .npy array of shape (N, 3), numbers, or an organized frame of shape (H, W, 3) whose
    missing pixels are NaN or infinity; never unpickles."""
    if not data.startswith(NPY_MAGIC):  # numpy would read it as pickled data and say so
        raise InvalidPoints(
            "the file is not an NPY file (it does not start with NPY's magic bytes "
            "'\\x93NUMPY'): write the array with numpy.save, or send the points as PLY or PCD"
        )
    if npy_dtype(data).hasobject:
        raise InvalidPoints(
            "the NPY file is unreadable here: its array holds Python objects, which the service "
            "never loads; save an array of numbers (float32 or float64) of shape (N, 3)"
        )
    try:
        array = np.load(io.BytesIO(data), allow_pickle=False)
    except Exception as error:  # bad headers, truncated data
        raise InvalidPoints(f"the NPY file is unreadable: {error}") from error
    if not isinstance(array, np.ndarray):
        raise InvalidPoints("the NPY file holds no array")
    if array.ndim not in (2, 3) or array.shape[-1] != 3:
        raise InvalidPoints(
            f"the NPY array has shape {array.shape}, not (N, 3) or (H, W, 3)" + shape_hint(array)
        )
    if array.dtype.kind not in "iuf":
        raise InvalidPoints(f"the NPY array holds {array.dtype}, not numbers")
    if array.ndim == 3:
        return organized(array.astype(np.float64, copy=False), max_points, "NPY frame")
    return Cloud(array)


def npy_dtype(data: bytes) -> np.dtype:
    """The dtype an NPY file's header declares, read without reading the array."""
    stream = io.BytesIO(data)
    try:
        major, _ = np.lib.format.read_magic(stream)
        read = np.lib.format.read_array_header_1_0
        if major > 1:
            read = np.lib.format.read_array_header_2_0
        _, _, dtype = read(stream)
    except Exception as error:  # numpy raises ValueError, SyntaxError, ... for a bad header
        raise InvalidPoints(
            f"the NPY file is unreadable: its header is damaged ({error})"
        ) from None
    return dtype


def read_ply_cloud(data: bytes) -> np.ndarray:
    """The vertices of a PLY file without faces."""
    try:
        loaded = trimesh.load(io.BytesIO(data), file_type="ply", process=False)
    except Exception as error:  # trimesh raises many types for unreadable files
        raise InvalidPoints(f"the PLY file is unreadable: {error}") from error
    vertices = getattr(loaded, "vertices", None)
    if vertices is None or len(vertices) == 0:
        raise InvalidPoints("the PLY file holds no vertices")
    return np.asarray(vertices)
