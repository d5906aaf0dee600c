"""The confidence calibration's corpus: parts nobody trained or tuned on, in groups, seen as a
cell sees them (``python -m evaluation.calibrate``; docs/decisions.md#calibration-that-transfers).

The evaluation's own parts (``training/objects.json``) are the model's and the evaluation's; a
confidence fitted on them is under-confident elsewhere. This corpus takes every other mesh of
``pybullet_data``: its procedurally generated objects (in groups of a hundred by number) and
the links of its robots that the manifest does not hold (a group per robot family), each
brought to a table's size (a radius of 2-15 cm, in metres). A group at a time is registered
beside the shipped gallery (half as meshes, half as 2,048-point clouds), and the engine
answers, for each of its parts:

- ``full``: an so3 cloud, a noisy one and a partial one (``evaluation.cases``);
- ``view``: depth views under each sensor profile (``evaluation.camera.PROFILES``: the
  evaluation's noise; the frames' quantisation and edge dropout; a noisier time-of-flight
  camera with mixed pixels), 4-12 scales away, with and without the viewpoint;
- ``table`` and ``bin``: the part resting on a table, or in a bin, under a profile;
- ``left-out``: an so3 cloud and a view with the part itself left out of the candidates;
- ``foreign``: the next group's parts, not registered; ``junk``: clouds of no part.

Every answer keeps the measures the confidence may use and whether it was right (the right
part, ADD-S < 0.1 of its diameter): a row.
"""

from __future__ import annotations

import re
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from tqdm import tqdm

from evaluation.camera import DEFAULT_CAMERA, PROFILES, cast_profiled
from evaluation.cases import NO_MATCH, Case, make_cases, uniform_rotations
from evaluation.evaluate_mapping import checked
from evaluation.frames import mesh_radius
from evaluation.metrics import succeeds
from evaluation.scenes import VIEWPOINT, placed, stable_poses, surface_centroid, table_scene
from service.engine import confidence
from service.engine.engine import Engine
from service.engine.sampling import MeshError, load_mesh, sample_surface_faces
from training.objects import data_root, load_manifest

RADIUS_M = (0.02, 0.15)  # each part brought to a radius drawn in this range (metres)
VIEW_SCALES = (4.0, 12.0)  # a view's part this many scales from the camera
PER_GROUP = 12  # parts of a group
ROBOT_FAMILIES = {  # the robots' folders, by family
    "laikago": ("laikago",),
    "minitaur": ("quadruped",),
    "legged": ("a1", "aliengo", "mini_cheetah"),
    "racecar": ("racecar", "husky"),
    "bicycle": ("bicycle",),
}  # not the arms': their other files are the manifest's links in other formats
SKIP = re.compile(r"vhacd|collision|_zup|_mod|coll|convex|lores|lowres|scaled", re.IGNORECASE)
ROW_MEASURES = ("fit", "coverage", "runner_up", "alike", "points", "size_ratio", "confidence")


@dataclass(frozen=True)
class CorpusPart:
    name: str
    path: Path
    group: str


def corpus_parts(per_group: int = PER_GROUP, seed: int = 0) -> list[CorpusPart]:
    """The corpus's parts, ``per_group`` of each group at most (drawn with ``seed``): every
    mesh of pybullet_data the manifest does not list."""
    root = data_root()
    listed = {spec.path.resolve() for spec in load_manifest()}
    groups: dict[str, list[Path]] = {}
    for number in range(1000):
        path = root / "random_urdfs" / f"{number:03d}" / f"{number:03d}.obj"
        if path.is_file() and path.resolve() not in listed:
            groups.setdefault(f"random-{number // 100}xx", []).append(path)
    for family, folders in ROBOT_FAMILIES.items():
        stems: dict[str, Path] = {}
        for folder in folders:
            for path in sorted((root / folder).rglob("*")):
                relative = path.relative_to(root).as_posix()
                usable = path.suffix.lower() in (".obj", ".stl") and not SKIP.search(relative)
                if usable and path.resolve() not in listed:
                    stems.setdefault(f"{folder}-{path.stem.lower()}", path)
        groups[family] = list(stems.values())
    rng = np.random.default_rng(seed)
    parts = []
    for group, paths in groups.items():
        chosen = sorted(rng.choice(len(paths), size=min(per_group, len(paths)), replace=False))
        for index in chosen:
            path = paths[index]
            where = path.relative_to(root).with_suffix("").as_posix().replace("/meshes/", "/")
            stem = re.sub(r"[^a-z0-9]+", "-", where.lower())
            parts.append(CorpusPart(f"corpus-{stem}".strip("-"), path, group))
    return parts


def load_part(part: CorpusPart, rng: np.random.Generator) -> trimesh.Trimesh | None:
    """The part's mesh at a table's size, or None where the file holds no usable mesh."""
    try:
        mesh = load_mesh(part.path)
    except (MeshError, ValueError):
        return None
    if len(mesh.faces) < 12 or mesh.area <= 0:
        return None
    radius = mesh_radius(mesh)
    extents = np.sort(mesh.extents)
    if radius <= 0 or extents[0] < 0.02 * extents[2]:  # a sheet: no pose to find
        return None
    mesh.apply_scale(rng.uniform(*RADIUS_M) / radius)
    return mesh


def _stream(*words) -> np.random.Generator:
    return np.random.default_rng([zlib.crc32(str(word).encode()) for word in words])


def view_case(name: str, mesh, scale: float, profile: str, seed: int, index: int) -> Case:
    """A depth view of the part in a uniform rotation under ``profile``."""
    rng = _stream(seed, "view", name, profile, index)
    rotation = uniform_rotations(1, rng)[0]
    distance = rng.uniform(*VIEW_SCALES) * scale
    pixel = DEFAULT_CAMERA.middle_half_pixel(rng)
    translation = distance * DEFAULT_CAMERA.ray(*pixel) - rotation @ surface_centroid(mesh)
    seen = cast_profiled([placed(mesh, rotation, translation)], rng, PROFILES[profile])
    points = seen.points[rng.permutation(len(seen.points))].astype(np.float32)
    params = {"viewpoint": list(VIEWPOINT), "profile": profile, "view": "sensor"}
    return Case(name, "view", points, rotation, translation, params)


def scene_case(name: str, mesh, scale: float, kind: str, profile: str, seed: int) -> Case:
    """The part resting on a table (``kind`` "table") or in a bin ("bin") under ``profile``."""
    rng = _stream(seed, kind, name, profile)
    walls = rng.uniform(0.6, 1.2) if kind == "bin" else 0.0
    scene = table_scene(mesh, scale, rng, profile=PROFILES[profile], walls=walls)
    params = {"viewpoint": list(VIEWPOINT), "profile": profile, "view": "sensor"}
    return Case(name, kind, scene.points, scene.rotation, scene.translation, params)


def part_cases(name: str, mesh, scale: float, seed: int, views: int = 2) -> list[Case]:
    """Every case of one registered part (see the module's docstring)."""
    meshes, scales = {name: mesh}, {name: scale}
    cases = []
    for family in ("so3", "noisy", "partial"):
        for case in make_cases(family, meshes, scales, 2048, seed, 1):
            case.family, case.params["kind"] = "full", family
            cases.append(case)
    for profile in PROFILES:
        cases += [view_case(name, mesh, scale, profile, seed, i) for i in range(views)]
    try:
        poses = stable_poses(mesh)
    except Exception:  # noqa: BLE001 - trimesh fails on some open meshes: no table for them
        poses = None
    if poses is not None and len(poses[0]):
        for kind, profile in (("table", "camera"), ("bin", "tof"), ("table", "tof")):
            try:
                cases.append(scene_case(name, mesh, scale, kind, profile, seed))
            except (ValueError, IndexError):
                pass
    return [case for case in cases if len(case.points) >= 64]


def row(engine: Engine, case: Case, viewpoint: bool, leave_out: bool, truth=None) -> dict | None:
    """The measures of the engine's answer to ``case`` and whether it was right; None where
    it was refused by size before any search (its confidence is 0 by construction)."""
    candidates = [n for n in engine.names() if n != case.object_name] if leave_out else None
    seen_from = case.params.get("viewpoint") if viewpoint else None
    found = engine.align(
        case.points,
        candidates=candidates,
        viewpoint=None if seen_from is None else np.asarray(seen_from),
    )
    if found.verdict == "no_match" and found.hypothesis == "none":
        return None
    right = bool(
        not leave_out
        and truth is not None
        and case.params.get("expected") != NO_MATCH
        and found.label == case.object_name
        and succeeds(truth, found.rotation, found.translation, case.rotation, case.translation)
    )
    values = confidence.measures(
        found.fit,
        found.coverage,
        found.runner_up,
        found.alike,
        found.points,
        found.size_ratio,
        seen_from is not None,
    )
    return values | {
        "right": right,
        "viewpoint": viewpoint,
        "verdict": found.verdict,
        "shipped": found.confidence,
        "ambiguous": found.ambiguous,
        "in_bin": found.in_bin,  # a "match" from BIN_ACCEPT only
        "doubted": bool(found.look_alikes),  # its look-alikes fit alike: never a "match"
        "hypothesis": found.hypothesis,
        "label": found.label,
    }


def group_rows(
    engine: Engine,
    group: str,
    parts: list[tuple[CorpusPart, trimesh.Trimesh]],
    foreign: list[tuple[CorpusPart, trimesh.Trimesh]],
    seed: int,
) -> list[dict]:
    """Register ``parts`` beside what ``engine`` holds, answer every case, unregister them."""
    references, meshes = [], {}  # half registered as meshes, half as clouds
    for number, (part, mesh) in enumerate(parts):
        points, faces = sample_surface_faces(mesh, 2048, 0)
        as_mesh = number % 2 == 0
        if as_mesh:
            meshes[part.name] = mesh
        references.append(
            engine.make_reference(
                part.name,
                points,
                mesh=mesh if as_mesh else None,
                face_index=faces if as_mesh else None,
            )
        )
    engine.add_many(references)
    checked(engine, [part.name for part, _ in parts], meshes)  # as the service registers them
    rows: list[dict] = []
    try:
        for part, mesh in tqdm(parts, desc=group, leave=False):
            truth = engine.get(part.name).points
            scale = engine.get(part.name).scale
            for case in part_cases(part.name, mesh, scale, seed):
                runs = [(False, False)] + ([(True, False)] if "viewpoint" in case.params else [])
                left_out = case.params.get("kind") == "so3" or (
                    case.family == "view" and case.params["profile"] == "camera"
                )
                runs += [("viewpoint" in case.params, True)] if left_out else []
                for viewpoint, leave_out in runs:
                    found = row(engine, case, viewpoint, leave_out, truth)
                    if found is not None:
                        family = "left-out" if leave_out else case.family
                        rows.append(found | _about(case, group, family))
        scales = {part.name: engine.get(part.name).scale for part, _ in parts}
        for part, mesh in foreign:
            scale = float(np.random.default_rng(0).choice(list(scales.values())))
            mesh = mesh.copy()
            mesh.apply_scale(scale / max(mesh_radius(mesh), 1e-12))
            cases = make_cases("foreign", {part.name: mesh}, {part.name: scale}, 2048, seed, 1)
            for case in cases:
                for viewpoint in (False, True) if "viewpoint" in case.params else (False,):
                    found = row(engine, case, viewpoint, False)
                    if found is not None:
                        rows.append(found | _about(case, group, "foreign"))
        for case in make_cases("junk", {}, scales, 2048, seed, 1):
            found = row(engine, case, False, False)
            if found is not None:
                rows.append(found | _about(case, group, "junk"))
    finally:
        for part, _ in parts:
            engine.remove(part.name)
    return rows


def _about(case: Case, group: str, family: str) -> dict:
    return {
        "group": group,
        "family": family,
        "kind": case.params.get("kind", case.family),
        "profile": case.params.get("profile", "sensor" if "viewpoint" in case.params else None),
        "object": case.object_name,
    }


def corpus_rows(engine: Engine, per_group: int = PER_GROUP, seed: int = 0, groups=None):
    """Every group's rows (``groups``: only these), each group registered in turn; the next
    group's parts are its foreign ones."""
    rng = np.random.default_rng(seed)
    loaded: dict[str, list] = {}
    shapes = set()  # a mirrored or resaved copy of a part already in: left out
    for part in corpus_parts(per_group, seed):
        mesh = load_part(part, rng)
        if mesh is None:
            continue
        extents = np.sort(mesh.extents)
        shape = (*np.round(extents / extents[-1], 2), round(mesh.area / extents[-1] ** 2, 1))
        if shape not in shapes:
            shapes.add(shape)
            loaded.setdefault(part.group, []).append((part, mesh))
    names = list(loaded)
    rows = []
    for number, group in enumerate(names):
        if groups and group not in groups:
            continue
        foreign = loaded[names[(number + 1) % len(names)]][:4]
        rows += group_rows(engine, group, loaded[group], foreign, seed)
    return rows
