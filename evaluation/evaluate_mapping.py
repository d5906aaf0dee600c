"""What the learned mapping gives on its own, before any refinement (the training issue's check).

    python -m evaluation.evaluate_mapping                  # shipped model, seen + unseen objects
    python -m evaluation.evaluate_mapping --poses 25 --json out.json

On the paper's held-out test poses (0 to 4*pi/10 in pi/10 steps about each axis,
none a training pose) and on independently resampled clouds (never the points of
a reference), it prints per object set:
- recognition accuracy of eq. (4) alone with all points and with 10 % of them, and
  the engine's (size check, eq. (4)'s shortlist, geometric verification, no ICP);
- correspondence quality: share of mapped nearest-neighbour pairs within
  0.05 x radius of the true point, on clean and on noisy (1 % of the scale) clouds;
- rotation error and the paper's normalised alignment error of the pose solved from
  the mapped pairs by the paper's least squares + SVD, by Kabsch with centring, and
  by RANSAC over the pairs, with the alignment error's floor at the true pose.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from evaluation.cases import make_cases
from evaluation.metrics import geodesic_deg
from service.engine.alignment import alignment_error, to_model_frame
from service.engine.confidence import Calibration
from service.engine.correspondences import correspondence_quality, mapped_pairs
from service.engine.engine import Engine
from service.engine.mapping import Mapper
from service.engine.normalize import subsample
from service.engine.registration import kabsch, paper_least_squares, ransac
from service.engine.sampling import sample_surface_faces
from service.gallery.gallery_file import load_gallery
from service.settings import MODELS_DIR, EngineSettings, GallerySettings
from training.objects import load_manifest, load_object_meshes

SOLVERS = ("paper", "kabsch", "ransac")
NOISE = 0.01  # share of the scale, as docs/evaluation-protocol.md's noisy family


def prepare_engine(
    model: Path, gallery: Path, unseen_specs, as_mesh: bool = True
) -> tuple[Engine, dict]:
    """The shipped gallery, plus every unseen object registered as a user would: as its mesh
    (an STL upload), or with ``as_mesh=False`` as the 2,048-point cloud sampled on it, and
    checked as the service checks it (``checked``)."""
    calibration = Path(model).parent / "confidence.json"  # shipped beside the model
    engine = Engine(
        Mapper(model, use_cuda=False),
        EngineSettings(),
        Calibration.load(calibration) if calibration.exists() else None,
    )
    references, _ = load_gallery(gallery)
    references = [engine.complete(reference) for reference in references]
    meshes = load_object_meshes(unseen_specs)
    for spec in unseen_specs:
        points, faces = sample_surface_faces(meshes[spec.name], 2048, 0)
        mesh = meshes[spec.name] if as_mesh else None
        references.append(
            engine.make_reference(
                spec.name, points, mesh=mesh, face_index=faces if as_mesh else None
            )
        )
    engine.load(references)
    checked(engine, [spec.name for spec in unseen_specs], meshes if as_mesh else {})
    return engine, meshes


def checked(engine: Engine, names: list[str], meshes: dict) -> None:
    """Check each of ``names`` as ``POST /references`` does after it is added (its
    registration check, with its mesh where it has one), noting the parts it could not tell
    it from, either way, as its look-alikes."""
    poses = GallerySettings().self_check_poses
    for name in names:
        _, others = engine.registration_check(engine.get(name), poses, meshes.get(name))
        if others:
            engine.annotate(engine.claiming(name, others))


def solve(solver: str, model: np.ndarray, scene: np.ndarray, threshold: float, rng):
    if solver == "paper":
        return paper_least_squares(model, scene)
    if solver == "kabsch":
        return kabsch(model, scene)
    rotation, translation, _ = ransac(model, scene, threshold, 200, rng)
    return rotation, translation


def evaluate_case(engine: Engine, case, rng: np.random.Generator) -> dict:
    settings = engine.settings
    entry = engine.entry(case.object_name)
    reference = entry.reference
    scale = reference.scale
    observed = case.points[subsample(case.points, settings.network_points, rng)].astype(np.float64)
    mapped = engine.map(observed)
    record = {"object": case.object_name}
    record["label_ok"] = engine.recognise(mapped)[0] == case.object_name
    sparse = case.points[subsample(case.points, len(case.points) // 10, rng)]  # 10 % kept
    record["label_ok_10"] = engine.recognise(engine.map(sparse))[0] == case.object_name
    record["engine_ok"] = engine.align(case.points, refine=False).label == case.object_name
    record["engine_ok_10"] = engine.align(sparse, refine=False).label == case.object_name

    truth = to_model_frame(observed, case.rotation, case.translation)
    paired = mapped_pairs(mapped, entry.mapped_tree)
    record["quality"] = correspondence_quality(truth, reference.points, paired, scale)
    noisy = observed + rng.normal(scale=NOISE * scale, size=observed.shape)
    noisy_pairs = mapped_pairs(engine.map(noisy), entry.mapped_tree)
    record["quality_noisy"] = correspondence_quality(truth, reference.points, noisy_pairs, scale)

    tree = entry.point_tree
    record["align_floor"] = alignment_error(observed, tree, case.rotation, case.translation) / scale
    for solver in SOLVERS:
        threshold = settings.ransac_threshold * scale
        rotation, translation = solve(solver, reference.points[paired], observed, threshold, rng)
        record[f"rot_{solver}"] = geodesic_deg(rotation, case.rotation)
        record[f"align_{solver}"] = alignment_error(observed, tree, rotation, translation) / scale
    return record


def summarise(records: list[dict]) -> dict:
    summary = {
        "cases": len(records),
        "recognition_all_points": float(np.mean([r["label_ok"] for r in records])),
        "recognition_10_percent": float(np.mean([r["label_ok_10"] for r in records])),
        "engine_recognition_all_points": float(np.mean([r["engine_ok"] for r in records])),
        "engine_recognition_10_percent": float(np.mean([r["engine_ok_10"] for r in records])),
        "correspondence_quality": float(np.mean([r["quality"] for r in records])),
        "correspondence_quality_noisy": float(np.mean([r["quality_noisy"] for r in records])),
        "alignment_floor_median": float(np.median([r["align_floor"] for r in records])),
    }
    for solver in SOLVERS:
        summary[f"rotation_error_median_{solver}"] = float(
            np.median([r[f"rot_{solver}"] for r in records])
        )
        summary[f"alignment_error_median_{solver}"] = float(
            np.median([r[f"align_{solver}"] for r in records])
        )
    return summary


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, default=MODELS_DIR / "dpc_mn.onnx")
    parser.add_argument("--gallery", type=Path, default=MODELS_DIR / "gallery.npz")
    parser.add_argument("--manifest", type=Path, default=None)
    parser.add_argument("--poses", type=int, default=10, help="paper poses per object (of 125)")
    parser.add_argument("--objects", type=int, default=None, help="at most this many per set")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args(argv)

    sets = {split: load_manifest(args.manifest, split=split) for split in ("seen", "unseen")}
    if args.objects:
        sets = {split: specs[: args.objects] for split, specs in sets.items()}
    engine, _ = prepare_engine(args.model, args.gallery, load_manifest(args.manifest, "unseen"))
    rng = np.random.default_rng(args.seed)
    report = {}
    for split, specs in sets.items():
        meshes = load_object_meshes(specs)
        scales = {name: engine.entry(name).reference.scale for name in meshes}
        cases = make_cases("paper-poses", meshes, scales, 2048, args.seed, args.poses)
        records = [evaluate_case(engine, case, rng) for case in cases]
        report[split] = summarise(records)
        print(f"\n{split} objects ({len(specs)}, {len(cases)} cases)")
        for key, value in report[split].items():
            print(
                f"  {key:36s} {value:.4f}" if isinstance(value, float) else f"  {key:36s} {value}"
            )
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return report


if __name__ == "__main__":
    main()
