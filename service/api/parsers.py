"""Uploaded files to points: a mesh is sampled on its surface, a cloud is used as is.

Meshes: STL, OBJ, PLY with faces. Clouds: PLY without faces, PCD (ascii or binary), NPY of
shape (N, 3). The kind is told by the file name's suffix, else by the file's first bytes.
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

from service.engine.sampling import MeshError, load_mesh, sample_surface_faces
from service.errors import InvalidPoints

SUFFIXES = (".stl", ".obj", ".ply", ".pcd", ".npy")
NPY_MAGIC = b"\x93NUMPY"


@dataclass(frozen=True)
class Upload:
    """What an uploaded file gives a registration: points, and the mesh they were sampled on."""

    points: np.ndarray  # (N, 3), not yet validated
    mesh: trimesh.Trimesh | None = None
    face_index: np.ndarray | None = None  # the face each point was sampled on


def read_points(data: bytes, filename: str | None, mesh_points: int, seed: int = 0) -> np.ndarray:
    """The points an uploaded file holds: (N, 3), a mesh sampled to ``mesh_points`` points."""
    return read_upload(data, filename, mesh_points, seed).points


def read_upload(data: bytes, filename: str | None, mesh_points: int, seed: int = 0) -> Upload:
    """An uploaded file's points, with its mesh when it is one."""
    if not data:
        raise InvalidPoints("the uploaded file is empty")
    kind = file_kind(data, filename)
    if kind == ".npy":
        return Upload(read_npy(data))
    if kind == ".pcd":
        return Upload(read_pcd(data))
    if kind == ".ply" and not ply_has_faces(data):
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


def read_npy(data: bytes) -> np.ndarray:
    """An .npy array of shape (N, 3), numbers; never unpickles."""
    try:
        array = np.load(io.BytesIO(data), allow_pickle=False)
    except Exception as error:  # object arrays (need pickle), bad headers, truncated data
        raise InvalidPoints(f"the NPY file is unreadable: {error}") from error
    if not isinstance(array, np.ndarray):
        raise InvalidPoints("the NPY file holds no array")
    if array.ndim != 2 or array.shape[1] != 3:
        raise InvalidPoints(f"the NPY array has shape {array.shape}, not (N, 3)")
    if array.dtype.kind not in "iuf":
        raise InvalidPoints(f"the NPY array holds {array.dtype}, not numbers")
    return array


def ply_has_faces(data: bytes) -> bool:
    """Whether a PLY header declares at least one face (a mesh) rather than only vertices."""
    end = data.find(b"end_header")
    if end < 0:
        raise InvalidPoints("the PLY file has no 'end_header' line")
    header = data[:end].decode("ascii", errors="replace")
    match = re.search(r"^element\s+face\s+(\d+)", header, flags=re.MULTILINE)
    return bool(match) and int(match.group(1)) > 0


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


# PCD: https://pointclouds.org/documentation/tutorials/pcd_file_format.html
PCD_TYPES = {(kind, size): f"{kind.lower()}{size}" for kind in "IU" for size in (1, 2, 4, 8)}
PCD_TYPES |= {("F", 4): "f4", ("F", 8): "f8"}  # TYPE and SIZE to a numpy type code
PCD_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS")


def read_pcd(data: bytes) -> np.ndarray:
    """The x y z fields of a PCD file, DATA ascii or binary (binary_compressed is refused)."""
    header, offset = _pcd_header(data)
    fields = header["FIELDS"]
    sizes = _pcd_numbers(header, "SIZE", ["4"] * len(fields))
    types = header.get("TYPE", ["F"] * len(fields))
    counts = _pcd_numbers(header, "COUNT", ["1"] * len(fields))
    if not len(fields) == len(sizes) == len(types) == len(counts):
        raise InvalidPoints("the PCD header's FIELDS, SIZE, TYPE and COUNT differ in length")
    for axis in ("x", "y", "z"):
        if axis not in fields:
            raise InvalidPoints(f"the PCD file has no '{axis}' field (FIELDS {' '.join(fields)})")
    if "POINTS" in header:
        (count,) = _pcd_numbers(header, "POINTS", [], minimum=0)
    else:
        (width,) = _pcd_numbers(header, "WIDTH", ["0"], minimum=0)
        (height,) = _pcd_numbers(header, "HEIGHT", ["1"], minimum=0)
        count = width * height
    dtype = []
    for name, size, kind, repeat in zip(fields, sizes, types, counts, strict=True):
        code = PCD_TYPES.get((kind.upper(), size))
        if code is None:
            raise InvalidPoints(f"the PCD field '{name}' has TYPE {kind} SIZE {size}")
        dtype.append((name, "<" + code, (repeat,)) if repeat > 1 else (name, "<" + code))
    try:
        record = np.dtype(dtype)
    except (ValueError, TypeError) as error:  # a field named twice, a record too large
        raise InvalidPoints(f"the PCD header's fields are unusable: {error}") from error
    encoding = header["DATA"][0].lower()
    body = data[offset:]
    if encoding == "ascii":
        table = _pcd_ascii(body, record, count)
        columns = [fields.index(axis) for axis in ("x", "y", "z")]
        starts = np.cumsum([0, *counts])
        return table[:, [starts[c] for c in columns]]
    if encoding == "binary":
        if len(body) < count * record.itemsize:
            raise InvalidPoints(
                f"the binary PCD data is {len(body)} bytes, {count} points need "
                f"{count * record.itemsize}"
            )
        table = np.frombuffer(body, dtype=record, count=count)
        return np.stack([table[axis].astype(np.float64) for axis in ("x", "y", "z")], axis=1)
    raise InvalidPoints(f"PCD DATA {encoding} is not supported: save as ascii or binary")


def _pcd_numbers(
    header: dict[str, list[str]], key: str, default: list[str], minimum: int = 1
) -> list[int]:
    """A header line of whole numbers (one value for POINTS, WIDTH, HEIGHT), or InvalidPoints."""
    values = header.get(key, default)
    single = key in ("POINTS", "WIDTH", "HEIGHT")
    if (
        (single and len(values) != 1)
        or not all(v.isascii() and v.isdigit() for v in values)
        or any(int(v) < minimum for v in values)
    ):
        shown = " ".join(values)[:40]
        raise InvalidPoints(
            f"the PCD header's {key} line is '{shown}': "
            f"{'a whole number' if single else 'whole numbers'} of at least {minimum} expected"
        )
    return [int(v) for v in values]


def _pcd_header(data: bytes) -> tuple[dict[str, list[str]], int]:
    """The header's keys and values, and the offset of the first data byte."""
    header: dict[str, list[str]] = {}
    offset = 0
    while offset < len(data):
        end = data.find(b"\n", offset)
        end = len(data) if end < 0 else end
        line = data[offset:end].decode("ascii", errors="replace").strip()
        offset = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        if key.upper() == "DATA":
            header["DATA"] = values or ["?"]
            if "FIELDS" not in header:
                raise InvalidPoints("the PCD header has no FIELDS line")
            return header, offset
        if key.upper() not in PCD_KEYS:
            raise InvalidPoints(f"the PCD header has an unknown line '{line[:40]}'")
        header[key.upper()] = values
    raise InvalidPoints("the PCD file has no DATA line")


def _pcd_ascii(body: bytes, record: np.dtype, count: int) -> np.ndarray:
    """An ascii PCD body as a float64 table, one row a point, one column a value."""
    width = sum(int(np.prod(record[name].shape or (1,))) for name in record.names)
    rows = [line.split() for line in body.decode("ascii", errors="replace").splitlines()]
    rows = [row for row in rows if row]
    if len(rows) != count:
        raise InvalidPoints(f"the ascii PCD data has {len(rows)} rows, the header says {count}")
    if any(len(row) != width for row in rows):
        raise InvalidPoints(f"an ascii PCD row does not have {width} values")
    try:
        return np.array(rows, dtype=np.float64).reshape(count, width)
    except ValueError as error:
        message = f"the ascii PCD data holds a value that is not a number: {error}"
        raise InvalidPoints(message) from error
