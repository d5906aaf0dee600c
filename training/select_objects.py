"""List candidate meshes in pybullet_data, with stats and their closest shape pairs.

A helper for curating ``training/objects.json`` (the curated result; this script does not
pick).  It walks the pybullet_data folder, skips files that are obviously not a separate
object or are a copy of another file (mirrors, low-res, collision and VHACD copies, planes,
terrain ...), loads every remaining mesh and prints, per candidate:

    faces, connected pieces, raw bounding-box extents (in the file's own units: metres for most,
    millimetres for the differential and some gripper/bicycle parts, about 6-12 units for the
    random objects, whose URDFs scale them by 0.015), and a flag for meshes that are unusable
    (fail to load, fewer than 50 faces, or flat: smallest extent < 1 % of the largest).

It then compares every pair by a rotation-invariant shape signature of 1024 surface points
(seed 0), centred and divided by their radius:

    * the sorted PCA eigenvalues,
    * a histogram of distances from the centroid,
    * the D2 shape distribution (a histogram of distances between random point pairs),

and prints the closest pairs, so that near-duplicates can be dropped by hand.

    python -m training.select_objects                   # candidates + 40 closest pairs
    python -m training.select_objects --manifest        # only the manifest's objects
    python -m training.select_objects --random-stride 10 --pairs 80
"""

from __future__ import annotations

import argparse
import fnmatch
import itertools
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet_data
from scipy.spatial import cKDTree

from service.engine.sampling import MeshError, load_mesh, sample_surface

MESH_SUFFIXES = (".obj", ".stl", ".ply")
MIN_FACES = 50
FLAT_RATIO = 0.01
POINTS = 1024
SEED = 0
RADIAL_BINS = 16
D2_BINS = 32
D2_PAIRS = 20000

# (glob on the path relative to pybullet_data, reason); the first match wins.
SKIP_RULES: tuple[tuple[str, str], ...] = (
    ("random_urdfs/*", "random object (sampled separately)"),
    ("kiva_shelf/*", "a 2.4 m warehouse shelf: scenery, not a part"),
    ("bicycle/files/all_pedal_parts.stl", "nine separate pieces, not one object"),
    ("bicycle/files/wheel_axels.stl", "two separate bars, not one object"),
    ("*mirror*", "mirror copy"),
    ("*lores*", "low-res copy"),
    ("*lowres*", "low-res copy"),
    ("*lowerscaled*", "scaled copy"),
    ("*vhacd*", "VHACD decomposition"),
    ("*VHACD*", "VHACD decomposition"),
    ("*/collision/*", "collision copy"),
    ("*_collision*", "collision copy"),
    ("*_col.obj", "collision copy"),
    ("*right*", "right-hand copy of a left part"),
    ("*plane*", "ground plane"),
    ("terrain.obj", "terrain"),
    ("roboschool/*", "stadium"),
    ("samurai_monastry.obj", "scenery"),
    ("cloth_z_up.obj", "cloth sheet"),
    ("urdf/mug*", "copy of objects/mug"),
    ("kuka_iiwa/meshes/link_*.stl", "STL copy of the kuka OBJ link"),
    ("laikago/*.stl", "STL copy of a laikago OBJ"),
    ("laikago/chassis_zup.obj", "rotated copy of laikago/chassis.obj"),
    ("laikago/chassis_mod.obj", "modified copy of laikago/chassis.obj"),
    ("laikago/upper_leg_left2.obj", "copy of laikago/upper_leg_left.obj"),
    ("racecar/meshes/*_wheel.obj", "OBJ copy of a racecar STL wheel"),
    ("racecar/meshes/*rear_wheel*", "same as the front wheel"),
    ("bicycle/files/frame_scaled_*", "copy of frame_scaled.stl"),
    ("textured_sphere_smooth.obj", "copy of sphere_smooth.obj"),
    ("tray/tray_textured[24].obj", "copy of tray_textured.obj"),
)

# random_urdfs indices that are not one solid object.
RANDOM_SKIP = {350: "a thin rod plus tiny scattered specks"}


@dataclass
class Candidate:
    path: str  # relative to pybullet_data
    faces: int = 0
    bodies: int = 0  # connected pieces once coincident vertices are merged
    extents: tuple[float, float, float] = (0.0, 0.0, 0.0)
    problem: str = ""
    signature: np.ndarray | None = None
    points: np.ndarray | None = None  # normalised: centred, divided by the radius


def skip_reason(relative: str) -> str:
    for pattern, reason in SKIP_RULES:
        if fnmatch.fnmatchcase(relative, pattern):
            return reason
    return ""


def list_files(root: Path, random_stride: int) -> tuple[list[str], list[tuple[str, str]]]:
    """Candidate paths (relative, sorted) and the skipped ones with their reasons."""
    kept: list[str] = []
    skipped: list[tuple[str, str]] = []
    for file in sorted(root.rglob("*")):
        if not file.is_file() or file.suffix.lower() not in MESH_SUFFIXES:
            continue
        relative = file.relative_to(root).as_posix()
        reason = skip_reason(relative)
        if reason:
            skipped.append((relative, reason))
        else:
            kept.append(relative)
    if random_stride > 0:
        random_dir = root / "random_urdfs"
        for index in range(0, 1000, random_stride):
            file = random_dir / f"{index:03d}" / f"{index:03d}.obj"
            relative = file.relative_to(root).as_posix()
            if index in RANDOM_SKIP:
                skipped.append((relative, RANDOM_SKIP[index]))
            elif file.is_file():
                kept.append(relative)
    return kept, skipped


def signature(points: np.ndarray, seed: int = SEED) -> np.ndarray:
    """Rotation-, translation- and scale-invariant shape descriptor of a point cloud."""
    centred = points.astype(np.float64) - points.mean(axis=0)
    radius = np.linalg.norm(centred, axis=1).max()
    centred /= radius
    eigen = np.sort(np.linalg.eigvalsh(np.cov(centred.T)))[::-1]
    eigen = eigen / eigen.sum()
    radial, _ = np.histogram(np.linalg.norm(centred, axis=1), bins=RADIAL_BINS, range=(0, 1))
    rng = np.random.default_rng(seed)
    first = rng.integers(0, len(centred), D2_PAIRS)
    second = rng.integers(0, len(centred), D2_PAIRS)
    d2, _ = np.histogram(
        np.linalg.norm(centred[first] - centred[second], axis=1), bins=D2_BINS, range=(0, 2)
    )
    return np.concatenate([eigen, radial / len(centred), d2 / D2_PAIRS])


def signature_distance(a: np.ndarray, b: np.ndarray) -> float:
    """L1 over the three parts, the eigenvalues weighted up to count like a histogram."""
    eigen = np.abs(a[:3] - b[:3]).sum() * 2.0
    radial = np.abs(a[3 : 3 + RADIAL_BINS] - b[3 : 3 + RADIAL_BINS]).sum()
    d2 = np.abs(a[3 + RADIAL_BINS :] - b[3 + RADIAL_BINS :]).sum()
    return float(eigen + radial + d2)


def inspect(root: Path, relative: str) -> Candidate:
    candidate = Candidate(relative)
    try:
        mesh = load_mesh(root / relative)
    except MeshError as error:
        candidate.problem = f"load failed: {error}"
        return candidate
    candidate.faces = len(mesh.faces)
    merged = mesh.copy()
    merged.merge_vertices()
    candidate.bodies = int(merged.body_count)
    extents = np.asarray(mesh.extents, dtype=float)
    candidate.extents = tuple(float(value) for value in extents)
    if candidate.faces < MIN_FACES:
        candidate.problem = f"only {candidate.faces} faces"
    elif extents.min() < FLAT_RATIO * extents.max():
        candidate.problem = "flat (degenerate)"
    points = sample_surface(mesh, POINTS, SEED).astype(np.float64)
    candidate.signature = signature(points)
    centred = points - points.mean(axis=0)
    candidate.points = centred / np.linalg.norm(centred, axis=1).max()
    return candidate


def principal_frame(points: np.ndarray) -> np.ndarray:
    """Points expressed in their PCA axes (largest variance first)."""
    _, vectors = np.linalg.eigh(np.cov(points.T))
    return points @ vectors[:, ::-1]


def aligned_chamfer(first: np.ndarray, second: np.ndarray, iterations: int = 15) -> float:
    """Symmetric mean nearest-neighbour distance after aligning the two clouds.

    Starts from the PCA frames under all 8 axis sign flips (so a mirror image counts as the
    same shape), refines each start with a few ICP steps and keeps the best.  Both clouds are
    already centred and of radius 1, so 0.05 means 5 % of the radius; two samplings of one mesh
    (different seeds) give about 0.03.
    """
    a = principal_frame(first)
    b_frame = principal_frame(second)
    tree_a = cKDTree(a)
    best = np.inf
    for signs in itertools.product((1.0, -1.0), repeat=3):
        b = b_frame * np.asarray(signs)
        for _ in range(iterations):
            _, index = tree_a.query(b)
            target = a[index]
            b_mean, t_mean = b.mean(axis=0), target.mean(axis=0)
            u, _, vt = np.linalg.svd((b - b_mean).T @ (target - t_mean))
            rotation = u @ vt
            if np.linalg.det(rotation) < 0:  # keep proper rotations; the flips give mirrors
                u[:, -1] *= -1
                rotation = u @ vt
            b = (b - b_mean) @ rotation + t_mean
        distance = 0.5 * (tree_a.query(b)[0].mean() + cKDTree(b).query(a)[0].mean())
        best = min(best, distance)
    return float(best)


def closest_pairs(candidates: list[Candidate], count: int) -> list[tuple[float, float, str, str]]:
    """The ``count`` pairs with the smallest signature distance, with their aligned chamfer."""
    usable = [c for c in candidates if c.signature is not None and not c.problem]
    pairs = []
    for i, first in enumerate(usable):
        for second in usable[i + 1 :]:
            pairs.append((signature_distance(first.signature, second.signature), first, second))
    pairs.sort(key=lambda item: item[0])
    return [(d, aligned_chamfer(a.points, b.points), a.path, b.path) for d, a, b in pairs[:count]]


def farthest_first(candidates: list[Candidate]) -> list[tuple[str, float]]:
    """Candidates ordered so that each is the most unlike the ones before it (by signature).

    Starts from the first candidate; returns (path, distance to the nearest earlier one).
    """
    usable = [c for c in candidates if c.signature is not None and not c.problem]
    if not usable:
        return []
    order = [(usable[0].path, float("inf"))]
    nearest = np.array([signature_distance(usable[0].signature, c.signature) for c in usable])
    chosen = {0}
    while len(chosen) < len(usable):
        index = max((i for i in range(len(usable)) if i not in chosen), key=lambda i: nearest[i])
        chosen.add(index)
        order.append((usable[index].path, float(nearest[index])))
        for i, other in enumerate(usable):
            distance = signature_distance(usable[index].signature, other.signature)
            nearest[i] = min(nearest[i], distance)
    return order


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--random-stride",
        type=int,
        default=25,
        help="also list random_urdfs/NNN for every N-th index (0: none)",
    )
    parser.add_argument("--pairs", type=int, default=40, help="how many closest pairs to print")
    parser.add_argument(
        "--manifest",
        nargs="?",
        const=str(Path(__file__).with_name("objects.json")),
        help="inspect only the objects of this manifest (default training/objects.json)",
    )
    parser.add_argument("--show-skipped", action="store_true", help="list skipped files too")
    args = parser.parse_args(argv)

    root = Path(pybullet_data.getDataPath())
    if args.manifest:
        entries = json.loads(Path(args.manifest).read_text())["objects"]
        paths = [entry["path"] for entry in entries]
        split_of = {entry["path"]: entry["split"] for entry in entries}
        skipped: list[tuple[str, str]] = []
    else:
        paths, skipped = list_files(root, args.random_stride)
        split_of = {}

    if args.show_skipped:
        print(f"# skipped {len(skipped)} files")
        for relative, reason in skipped:
            print(f"skip  {relative:60s} {reason}")

    print(f"# {len(paths)} candidates under {root}")
    print(f"{'path':62s} {'faces':>7s} {'bodies':>6s}  {'extents (file units)':32s} problem")
    candidates = []
    for relative in paths:
        candidate = inspect(root, relative)
        candidates.append(candidate)
        extents = " x ".join(f"{value:.4g}" for value in candidate.extents)
        label = f"[{split_of[relative]}] " if relative in split_of else ""
        print(
            f"{label + relative:62s} {candidate.faces:7d} {candidate.bodies:6d}  "
            f"{extents:32s} {candidate.problem}"
        )

    problems = [c for c in candidates if c.problem]
    print(f"\n# {len(problems)} unusable, {len(candidates) - len(problems)} usable")
    print(f"\n# {args.pairs} closest pairs by shape signature (smaller = more alike)")
    print("# sig: signature distance; chamfer: after PCA alignment, in units of the radius")
    print(f"{'sig':>6s} {'chamfer':>7s}  pair")
    for distance, chamfer, first, second in closest_pairs(candidates, args.pairs):
        print(f"{distance:6.3f} {chamfer:7.3f}  {first:50s} {second}")

    randoms = [c for c in candidates if c.path.startswith("random_urdfs/")]
    if randoms and not args.manifest:
        print("\n# random objects, farthest first (each most unlike those above it)")
        for path, distance in farthest_first(randoms):
            print(f"{distance:6.3f}  {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
