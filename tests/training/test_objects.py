"""The object set: the manifest of pybullet_data meshes and the folder loader."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh

pytest.importorskip("pybullet_data")

from service.engine.sampling import sample_surface  # noqa: E402
from training.objects import (  # noqa: E402
    ObjectSpec,
    default_manifest_path,
    load_manifest,
    load_object_meshes,
    objects_from_folder,
)


@pytest.fixture(scope="module")
def manifest() -> list[ObjectSpec]:
    return load_manifest()


def test_default_manifest_sits_beside_the_module():
    path = default_manifest_path()
    assert path.name == "objects.json"
    assert path.parent.name == "training"
    assert json.loads(path.read_text())["source"] == "pybullet_data"


def test_manifest_sizes_and_names(manifest):
    seen = [spec for spec in manifest if spec.split == "seen"]
    unseen = [spec for spec in manifest if spec.split == "unseen"]
    assert len(seen) >= 40
    assert len(unseen) >= 8
    assert len(seen) + len(unseen) == len(manifest)
    names = [spec.name for spec in manifest]
    assert len(set(names)) == len(names)
    for spec in manifest:
        assert re.fullmatch(r"[a-z0-9]+(-[a-z0-9]+)*", spec.name), spec.name
        assert spec.path.is_absolute() and spec.path.is_file()
        assert spec.category and spec.why


def test_split_filter_and_disjoint_splits(manifest):
    seen = load_manifest(split="seen")
    unseen = load_manifest(split="unseen")
    assert {spec.split for spec in seen} == {"seen"}
    assert {spec.split for spec in unseen} == {"unseen"}
    assert len(seen) + len(unseen) == len(manifest)
    assert not {spec.name for spec in seen} & {spec.name for spec in unseen}
    seen_files = {spec.path.resolve() for spec in seen}
    unseen_files = {spec.path.resolve() for spec in unseen}
    assert not seen_files & unseen_files
    assert len(seen_files) == len(seen) and len(unseen_files) == len(unseen)
    with pytest.raises(ValueError, match="split"):
        load_manifest(split="train")


def test_both_splits_mix_categories(manifest):
    for split in ("seen", "unseen"):
        categories = {spec.category for spec in manifest if spec.split == split}
        assert {
            "robot link",
            "gripper part",
            "gear part",
            "household object",
            "random object",
        } <= categories


def test_every_mesh_loads_and_samples_deterministically(manifest):
    meshes = load_object_meshes(manifest)
    assert list(meshes) == [spec.name for spec in manifest]
    for name, mesh in meshes.items():
        assert len(mesh.faces) >= 50, name
        extents = np.asarray(mesh.extents)
        assert extents.min() >= 0.01 * extents.max(), f"{name} is flat"
        first = sample_surface(mesh, 256, seed=0)
        again = sample_surface(mesh, 256, seed=0)
        other = sample_surface(mesh, 256, seed=1)
        assert first.shape == (256, 3) and first.dtype == np.float32
        assert np.isfinite(first).all(), name
        np.testing.assert_array_equal(first, again, err_msg=name)
        assert not np.array_equal(first, other), name


def _write_manifest(tmp_path: Path, objects: list[dict]) -> Path:
    path = tmp_path / "objects.json"
    path.write_text(json.dumps({"source": "test", "objects": objects}))
    return path


@pytest.fixture
def mesh_file(tmp_path) -> Path:
    path = tmp_path / "box.stl"
    trimesh.creation.box(extents=(0.1, 0.2, 0.3)).export(path)
    return path


def _entry(name: str, path: str, split: str = "seen") -> dict:
    return {"name": name, "path": path, "category": "test", "split": split, "why": "a test"}


def test_manifest_with_absolute_and_relative_paths(tmp_path, mesh_file):
    path = _write_manifest(
        tmp_path,
        [_entry("box", str(mesh_file)), _entry("mug", "objects/mug.obj", "unseen")],
    )
    specs = load_manifest(path)
    assert [spec.name for spec in specs] == ["box", "mug"]
    assert specs[0].path == mesh_file
    assert specs[1].path.is_absolute() and specs[1].path.name == "mug.obj"
    assert [spec.name for spec in load_manifest(path, split="unseen")] == ["mug"]


def test_duplicate_name_is_rejected(tmp_path, mesh_file):
    path = _write_manifest(tmp_path, [_entry("box", str(mesh_file)), _entry("box", str(mesh_file))])
    with pytest.raises(ValueError, match=r"duplicate name 'box'"):
        load_manifest(path)


def test_bad_split_is_rejected(tmp_path, mesh_file):
    path = _write_manifest(tmp_path, [_entry("box", str(mesh_file), split="train")])
    with pytest.raises(ValueError, match=r"'box'.*split 'train'"):
        load_manifest(path)


def test_missing_file_is_rejected(tmp_path, mesh_file):
    path = _write_manifest(
        tmp_path, [_entry("box", str(mesh_file)), _entry("ghost", "no/such/mesh.obj")]
    )
    with pytest.raises(ValueError, match=r"'ghost'.*does not exist"):
        load_manifest(path)


def test_missing_field_and_unreadable_manifest_are_rejected(tmp_path, mesh_file):
    path = _write_manifest(tmp_path, [{"name": "box", "split": "seen"}])
    with pytest.raises(ValueError, match="lacks path"):
        load_manifest(path)
    with pytest.raises(ValueError, match="cannot read"):
        load_manifest(tmp_path / "absent.json")
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    with pytest.raises(ValueError, match="cannot read"):
        load_manifest(broken)


def test_objects_from_folder(tmp_path):
    folder = tmp_path / "parts"
    (folder / "sub").mkdir(parents=True)
    trimesh.creation.box(extents=(0.1, 0.2, 0.3)).export(folder / "Big Box.stl")
    trimesh.creation.icosphere(subdivisions=2, radius=0.05).export(folder / "sub" / "ball.obj")
    trimesh.creation.box(extents=(0.3, 0.1, 0.1)).export(folder / "sub" / "big-box.ply")
    (folder / "notes.txt").write_text("not a mesh")

    specs = objects_from_folder(folder, split="unseen")
    assert [spec.name for spec in specs] == ["big-box", "ball", "big-box-2"]
    assert {spec.category for spec in specs} == {"user"}
    assert {spec.split for spec in specs} == {"unseen"}
    assert all(spec.path.is_absolute() and spec.path.is_file() for spec in specs)

    meshes = load_object_meshes(specs)
    assert len(meshes["ball"].faces) == 320
    np.testing.assert_allclose(meshes["big-box"].extents, (0.1, 0.2, 0.3), atol=1e-6)
    assert sample_surface(meshes["big-box-2"], 64, seed=0).shape == (64, 3)

    assert objects_from_folder(tmp_path / "parts" / "sub")[0].split == "seen"
    with pytest.raises(ValueError, match="split"):
        objects_from_folder(folder, split="test")
    with pytest.raises(ValueError, match="not a folder"):
        objects_from_folder(tmp_path / "nowhere")
