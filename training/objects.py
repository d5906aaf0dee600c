"""The object set: which meshes the network is trained on, and which are held out.

``training/objects.json`` lists real meshes from the ``pybullet_data`` folder (robot links,
gripper parts, differential gears, household objects and procedurally generated objects), each
marked ``seen`` (trained on) or ``unseen`` (registered later, to measure how the service does on
parts it was never trained on).  ``training/select_objects.py`` prints the candidates and their
near-duplicates that the manifest was curated from.

Any folder of meshes can stand in for the manifest through :func:`objects_from_folder`.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import trimesh

from service.engine.sampling import MeshError, load_mesh

SPLITS = ("seen", "unseen")
FOLDER_SUFFIXES = (".obj", ".stl", ".ply")


@dataclass(frozen=True)
class ObjectSpec:
    """One object of the set: a name, its mesh file and where it belongs."""

    name: str
    path: Path  # absolute
    category: str
    split: str
    why: str


def default_manifest_path() -> Path:
    """``objects.json`` beside this module."""
    return Path(__file__).with_name("objects.json")


def data_root() -> Path:
    """The pybullet_data folder that relative manifest paths are read against."""
    import pybullet_data  # a training dependency only; imported late so the module loads without

    return Path(pybullet_data.getDataPath())


def load_manifest(path: Path | None = None, split: str | None = None) -> list[ObjectSpec]:
    """The objects of a manifest, in its order, optionally only those of one split.

    Relative mesh paths are read against ``pybullet_data.getDataPath()``, absolute ones as
    given.  Raises ``ValueError`` naming the entry for a duplicate name, an unknown split, a
    missing field or a mesh file that does not exist.
    """
    if split is not None and split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS} or None, not {split!r}")
    manifest = Path(path) if path is not None else default_manifest_path()
    try:
        document = json.loads(manifest.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise ValueError(f"cannot read the object manifest {manifest}: {error}") from error
    entries = document.get("objects") if isinstance(document, dict) else None
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"{manifest}: expected {{'objects': [...]}} with at least one object")

    root: Path | None = None
    specs: list[ObjectSpec] = []
    seen_names: set[str] = set()
    for index, entry in enumerate(entries):
        where = f"{manifest}: object #{index}"
        if not isinstance(entry, dict):
            raise ValueError(f"{where} is not an object")
        missing = [key for key in ("name", "path", "split") if not entry.get(key)]
        if missing:
            raise ValueError(f"{where} lacks {', '.join(missing)}")
        name = str(entry["name"])
        where = f"{manifest}: object #{index} ({name!r})"
        if name in seen_names:
            raise ValueError(f"{where}: duplicate name {name!r}")
        seen_names.add(name)
        entry_split = entry["split"]
        if entry_split not in SPLITS:
            raise ValueError(f"{where}: split {entry_split!r} is not one of {SPLITS}")
        mesh_path = Path(entry["path"])
        if not mesh_path.is_absolute():
            if root is None:
                root = data_root()
            mesh_path = root / mesh_path
        if not mesh_path.is_file():
            raise ValueError(f"{where}: mesh file {mesh_path} does not exist")
        specs.append(
            ObjectSpec(
                name=name,
                path=mesh_path,
                category=str(entry.get("category", "")),
                split=entry_split,
                why=str(entry.get("why", "")),
            )
        )
    if split is not None:
        specs = [spec for spec in specs if spec.split == split]
    return specs


def _slug(text: str) -> str:
    slug = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")
    return slug or "object"


def objects_from_folder(folder: Path, split: str = "seen") -> list[ObjectSpec]:
    """Every OBJ/STL/PLY file under ``folder`` (recursive, sorted) as an object of ``split``.

    Names come from the file stems (lowercase-with-dashes), with ``-2``, ``-3`` ... added where
    two files share a stem; the category is ``"user"``.
    """
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, not {split!r}")
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder} is not a folder")
    files = sorted(
        file
        for file in folder.rglob("*")
        if file.is_file() and file.suffix.lower() in FOLDER_SUFFIXES
    )
    specs: list[ObjectSpec] = []
    used: set[str] = set()
    for file in files:
        base = _slug(file.stem)
        name, number = base, 1
        while name in used:
            number += 1
            name = f"{base}-{number}"
        used.add(name)
        relative = file.relative_to(folder).as_posix()
        specs.append(
            ObjectSpec(
                name=name,
                path=file.resolve(),
                category="user",
                split=split,
                why=f"mesh file {relative} from {folder}",
            )
        )
    return specs


def load_object_meshes(specs: Iterable[ObjectSpec]) -> dict[str, trimesh.Trimesh]:
    """Each object's mesh by name, read with :func:`service.engine.sampling.load_mesh`.

    A file that holds no usable mesh raises ``service.engine.sampling.MeshError`` (a ``ValueError``)
    naming the object.
    """
    meshes: dict[str, trimesh.Trimesh] = {}
    for spec in specs:
        try:
            meshes[spec.name] = load_mesh(spec.path)
        except MeshError as error:
            raise MeshError(f"object {spec.name!r} ({spec.path}): {error}") from error
    return meshes
