"""Do the mapped hypotheses earn their place on single views? Models side by side (issue 11).

    python -m evaluation.views_mapping \\
        --model shipped=models/dpc_mn.onnx \\
        --model full=runs/full/export/dpc_mn.onnx --model views=runs/views/export/dpc_mn.onnx \\
        --cases 4 --engine --json docs/views_mapping.json

Every model meets the same cases: ``sensor`` (what a depth camera sees, ``evaluation.cases``)
and ``so3`` (a full cloud in a uniform pose, so that a regression on full clouds shows), of the
seen and of the unseen objects; and ``view-pairs``, two cameras' views of a part made as
single-view training makes them (``training.data``), the second turned by a uniform rotation
and paired with the first: did a model learn what single-view training asks of it?

Each object's reference is its mesh sampled to 2,048 points with seed 0 (as a registration
samples it), mapped whole by the model (for ``view-pairs``: the first view, mapped as a cloud).
Each case's observation is subsampled to the engine's ``network_points`` with the same draw
for every model. Given the right part, per model, family and object set:

- ``quality``: correspondence quality of the mapped pairs, the share of observed points whose
  2-D nearest reference point lies within 0.05 x scale of the true point
  (``service.engine.correspondences.correspondence_quality``);
- ``mapped``: success of the ``mapped`` hypothesis alone: RANSAC-Kabsch over the mapped pairs
  (``service.engine.registration.ransac`` with the engine's threshold and iterations), then
  ADD-S below 0.1 of the diameter (and below 0.02, ``precise``); with its median rotation
  error and inlier share. ADD-S is symmetry-aware and 0.1 of the diameter is lenient for
  elongated parts, so the same RANSAC over random pairs (each observed point paired with a
  reference point drawn at random) is the floor it must clear: ``random pairs``;
- ``view quality`` / ``view mapped`` (sensor views): the same two against the reference's
  rendered view (``service.engine.views.render``, as a mesh upload's 100 views) whose camera
  direction is nearest the true one, that view's points mapped as a cloud of their own: what
  the pairing gives when both sides are one camera's view, as single-view training teaches
  (an oracle choice of the view: an upper bound of what a view-wise pairing could give);
- ``top1`` / ``top5``: eq. (4)'s classifier over all the references (seen and unseen), fitted
  as the engine fits it (32 augmented full views a reference, ``Engine.view_grid``);
- with ``--engine``: the engine itself, told the right part (``candidates``) and, for a
  sensor view, the viewpoint, refining, with its default hypothesis sources and with the same
  sources less ``mapped``: success of each, how often ``mapped`` won, and the cases it
  rescued (right with it, wrong without) or lost. The engine's references are built as a mesh
  upload's (``Engine.make_reference``), which takes a few seconds an object and model.
"""

from __future__ import annotations

import argparse
import json
import time
import zlib
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from evaluation.cases import Case, make_cases, uniform_rotations
from evaluation.metrics import PRECISE_ADD_S, SUCCESS_ADD_S, add_s, diameter, geodesic_deg
from service.engine.alignment import to_model_frame
from service.engine.classifier import LinearClassifier, classifier_input
from service.engine.correspondences import correspondence_quality, mapped_pairs
from service.engine.engine import Engine
from service.engine.grid import grid
from service.engine.mapping import Mapper
from service.engine.normalize import radius, subsample
from service.engine.registration import ransac
from service.engine.sampling import sample_surface_faces
from service.engine.views import directions, render
from service.settings import MODELS_DIR, EngineSettings
from training.data import DataConfig, TrainingClouds
from training.objects import load_manifest, load_object_meshes

FAMILIES = ("sensor", "so3")
PAIRS = "view-pairs"  # two cameras' views, as single-view training makes them
REFERENCE_POINTS = 2048  # a registration's sample of a mesh
PAIRS_EPOCH = 10_000  # the view pairs' pool: an epoch of the training stream no run reaches
TOP = 5


class Part:
    """What the study needs of one object: its reference cloud and its truth."""

    def __init__(self, name: str, mesh, split: str):
        self.name, self.mesh, self.split = name, mesh, split
        self.points, self.faces = sample_surface_faces(mesh, REFERENCE_POINTS, 0)
        self.points = np.asarray(self.points, dtype=np.float64)
        self.scale = radius(self.points)
        self.diameter = diameter(self.points)
        settings = EngineSettings()  # the rendered views, as Engine.complete renders a mesh's
        surface = trimesh.sample.sample_surface(
            mesh, settings.mesh_surface_points, seed=settings.seed + 1
        )[0]
        self.visible = render(self.points, self.scale, settings.views, surface, mesh.area)
        self.directions = directions(settings.views)

    def nearest_view(self, rotation: np.ndarray, translation: np.ndarray, viewpoint) -> np.ndarray:
        """The points of the rendered view whose camera direction is nearest the true one."""
        camera = np.asarray(rotation).T @ (np.asarray(viewpoint, np.float64) - translation)
        toward = camera - self.points.mean(axis=0)
        return self.points[self.visible[int(np.argmax(self.directions @ toward))]]


class Study:
    """One model: the references mapped by it, eq. (4)'s classifier, and optionally the engine."""

    def __init__(self, model: Path, parts: dict[str, Part], with_engine: bool):
        self.settings = EngineSettings()
        self.engine = Engine(Mapper(model, use_cuda=False), self.settings)
        self.parts = parts
        self.trees = {name: cKDTree(self.engine.map(p.points)) for name, p in parts.items()}
        features = []
        for part in parts.values():  # as Engine.make_reference draws its augmented views
            rng = np.random.default_rng(self.settings.seed)
            views = np.stack(
                [self.engine.view_grid(part.points, rng) for _ in range(self.settings.view_grids)]
            )
            features.append(classifier_input(views, self.settings.grid_blur))
        self.classifier = LinearClassifier.fit(
            list(parts), features, self.settings.classifier_ridge, self.settings.grid_blur
        )
        self.with_engine = with_engine
        if with_engine:
            self.engine.load(
                [
                    self.engine.make_reference(name, p.points, mesh=p.mesh, face_index=p.faces)
                    for name, p in parts.items()
                ]
            )
        without = tuple(s for s in self.settings.hypotheses if s != "mapped")
        self.sources = {"with": (*without, "mapped"), "without": without}

    def record(self, case: Case, seed: int) -> dict:
        settings, part = self.settings, self.parts[case.object_name]
        words = [seed, zlib.crc32(case.family.encode()), zlib.crc32(case.object_name.encode())]
        rng = np.random.default_rng([*words, int(case.params["index"])])  # same for every model
        observed = case.points[subsample(case.points, settings.network_points, rng)]
        observed = observed.astype(np.float64)
        mapped = self.engine.map(observed)
        if case.family == PAIRS:  # the reference is the first camera's view
            reference = case.params["reference"]
            tree = cKDTree(self.engine.map(reference))
        else:  # the whole reference
            reference, tree = part.points, self.trees[part.name]
        paired = mapped_pairs(mapped, tree)
        truth = to_model_frame(observed, case.rotation, case.translation)
        record = {
            "object": part.name,
            "split": part.split,
            "family": case.family,
            "points": len(case.points),
            "quality": correspondence_quality(truth, reference, paired, part.scale),
        }
        threshold = settings.ransac_threshold * part.scale
        rotation, translation, inliers = ransac(
            reference[paired], observed, threshold, settings.ransac_iterations, rng
        )
        record["mapped_add_s"] = add_s(
            part.points, rotation, translation, case.rotation, case.translation, part.diameter
        )
        record["mapped_ok"] = record["mapped_add_s"] < SUCCESS_ADD_S
        record["mapped_precise"] = record["mapped_add_s"] < PRECISE_ADD_S
        record["mapped_rotation_deg"] = geodesic_deg(rotation, case.rotation)
        record["mapped_inliers"] = float(inliers.mean())
        drawn = rng.integers(0, len(reference), size=len(observed))
        rotation, translation, _ = ransac(
            reference[drawn], observed, threshold, settings.ransac_iterations, rng
        )
        error = add_s(part.points, rotation, translation, case.rotation, case.translation, 1.0)
        record["random_pairs_ok"] = error / part.diameter < SUCCESS_ADD_S
        if "viewpoint" in case.params:
            view = part.nearest_view(case.rotation, case.translation, case.params["viewpoint"])
            paired = mapped_pairs(mapped, cKDTree(self.engine.map(view)))
            record["view_quality"] = correspondence_quality(truth, view, paired, part.scale)
            rotation, translation, _ = ransac(
                view[paired], observed, threshold, settings.ransac_iterations, rng
            )
            error = add_s(part.points, rotation, translation, case.rotation, case.translation, 1.0)
            record["view_mapped_ok"] = error / part.diameter < SUCCESS_ADD_S
            record["view_mapped_precise"] = error / part.diameter < PRECISE_ADD_S
            record["view_mapped_rotation_deg"] = geodesic_deg(rotation, case.rotation)
        if case.family == PAIRS:
            return record
        scores = self.classifier.scores(grid(mapped))
        right = self.classifier.labels.index(part.name)
        rank = int((scores > scores[right]).sum())
        record["top1"], record["topk"] = rank == 0, rank < TOP
        if self.with_engine:
            viewpoint = case.params.get("viewpoint")
            for kind, sources in self.sources.items():
                answer = self.engine.align(
                    case.points,
                    candidates=[part.name],
                    hypotheses=sources,
                    viewpoint=None if viewpoint is None else np.asarray(viewpoint),
                )
                error = np.inf
                if answer.rotation is not None and answer.label == part.name:
                    error = add_s(
                        part.points,
                        answer.rotation,
                        answer.translation,
                        case.rotation,
                        case.translation,
                        part.diameter,
                    )
                record[f"engine_{kind}_ok"] = bool(error < SUCCESS_ADD_S)
                record[f"engine_{kind}_precise"] = bool(error < PRECISE_ADD_S)
                record[f"engine_{kind}_source"] = answer.hypothesis
        return record


def summarise(records: list[dict]) -> dict:
    def mean(key):
        return float(np.mean([r[key] for r in records]))

    summary = {
        "cases": len(records),
        "points_median": float(np.median([r["points"] for r in records])),
        "quality": mean("quality"),
        "mapped_success": mean("mapped_ok"),
        "mapped_precise": mean("mapped_precise"),
        "random_pairs_success": mean("random_pairs_ok"),
        "mapped_rotation_median_deg": float(np.median([r["mapped_rotation_deg"] for r in records])),
        "mapped_inliers_median": float(np.median([r["mapped_inliers"] for r in records])),
    }
    if "top1" in records[0]:
        summary["top1"], summary[f"top{TOP}"] = mean("top1"), mean("topk")
    if "view_quality" in records[0]:
        summary["view_quality"] = mean("view_quality")
        summary["view_mapped_success"] = mean("view_mapped_ok")
        summary["view_mapped_precise"] = mean("view_mapped_precise")
        summary["view_mapped_rotation_median_deg"] = float(
            np.median([r["view_mapped_rotation_deg"] for r in records])
        )
    if "engine_with_ok" in records[0]:
        with_ok = np.array([r["engine_with_ok"] for r in records])
        without_ok = np.array([r["engine_without_ok"] for r in records])
        summary["engine_success_with_mapped"] = float(with_ok.mean())
        summary["engine_success_without_mapped"] = float(without_ok.mean())
        summary["engine_precise_with_mapped"] = mean("engine_with_precise")
        summary["engine_precise_without_mapped"] = mean("engine_without_precise")
        summary["engine_mapped_won"] = float(
            np.mean([r["engine_with_source"] == "mapped" for r in records])
        )
        summary["engine_rescued_by_mapped"] = int((with_ok & ~without_ok).sum())
        summary["engine_lost_with_mapped"] = int((~with_ok & without_ok).sum())
    return summary


COLUMNS = (
    ("cases", "cases", "{:d}"),
    ("quality", "corr. quality", "{:.1%}"),
    ("mapped_success", "mapped alone", "{:.1%}"),
    ("mapped_precise", "precise", "{:.1%}"),
    ("random_pairs_success", "random pairs", "{:.1%}"),
    ("mapped_rotation_median_deg", "rot. err. median", "{:.1f}"),
    ("view_quality", "view: quality", "{:.1%}"),
    ("view_mapped_success", "view: mapped", "{:.1%}"),
    ("view_mapped_precise", "view: precise", "{:.1%}"),
    ("view_mapped_rotation_median_deg", "view: rot. err.", "{:.1f}"),
    ("top1", "eq.(4) top-1", "{:.1%}"),
    (f"top{TOP}", f"top-{TOP}", "{:.1%}"),
    ("engine_success_without_mapped", "engine w/o mapped", "{:.1%}"),
    ("engine_success_with_mapped", "engine with", "{:.1%}"),
    ("engine_precise_without_mapped", "precise w/o", "{:.1%}"),
    ("engine_precise_with_mapped", "precise with", "{:.1%}"),
    ("engine_mapped_won", "mapped won", "{:.1%}"),
    ("engine_rescued_by_mapped", "rescued", "{:d}"),
    ("engine_lost_with_mapped", "lost", "{:d}"),
)


def table(report: dict) -> str:
    """A Markdown table: one row per model, family and object set."""
    present = {key for groups in report["models"].values() for s in groups.values() for key in s}
    shown = [c for c in COLUMNS if c[0] in present]
    lines = [
        "| model | family | objects | " + " | ".join(c[1] for c in shown) + " |",
        "|---|---|---|" + "---|" * len(shown),
    ]
    for model, groups in report["models"].items():
        for group, summary in groups.items():
            family, split = group.split("/")
            cells = [fmt.format(summary[key]) if key in summary else "" for key, _, fmt in shown]
            lines.append(f"| {model} | {family} | {split} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def view_pair_cases(parts: dict[str, Part], seed: int, count: int) -> list[Case]:
    """``count`` pairs of views of each part made as single-view training makes them
    (``training.data.TrainingClouds.view_pair``, a pool of an epoch no run trains on): the
    second view turned by a uniform rotation is the observation, the first is the reference
    (``params["reference"]``, the object's frame)."""
    config = DataConfig(single_views=1.0)
    clouds = TrainingClouds({name: part.mesh for name, part in parts.items()}, config, seed)
    clouds.start_epoch(PAIRS_EPOCH)
    cases = []
    for name in parts:
        rng = np.random.default_rng([seed, zlib.crc32(name.encode())])
        for index in range(count):
            reference, view, _ = clouds.view_pair(name, rng)
            rotation = uniform_rotations(1, rng)[0]
            params = {"index": index, "reference": reference.astype(np.float64)}
            scene = (view @ rotation.T).astype(np.float32)
            cases.append(Case(name, PAIRS, scene, rotation, np.zeros(3), params))
    return cases


def named_model(text: str) -> tuple[str, Path]:
    name, _, path = text.partition("=")
    if not path:
        raise argparse.ArgumentTypeError("give a model as NAME=PATH")
    return name, Path(path)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--model",
        type=named_model,
        action="append",
        help="NAME=PATH of an ONNX model, once per model (default: the shipped one)",
    )
    parser.add_argument("--manifest", type=Path, default=None, help="objects (default: ours)")
    parser.add_argument("--cases", type=int, default=4, help="cases per object and family")
    parser.add_argument("--objects", type=int, default=None, help="at most this many per set")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--engine", action="store_true", help="also the engine, with and without")
    parser.add_argument("--json", type=Path, default=None, help="write the figures here")
    parser.add_argument("--records", type=Path, default=None, help="and every case's record here")
    args = parser.parse_args(argv)
    models = dict(args.model or [("shipped", MODELS_DIR / "dpc_mn.onnx")])

    began = time.perf_counter()
    parts: dict[str, Part] = {}
    for split in ("seen", "unseen"):
        specs = load_manifest(args.manifest, split=split)[: args.objects]
        for name, mesh in load_object_meshes(specs).items():
            parts[name] = Part(name, mesh, split)
    cases = view_pair_cases(parts, args.seed, args.cases)
    for family in FAMILIES:
        meshes = {name: part.mesh for name, part in parts.items()}
        scales = {name: part.scale for name, part in parts.items()}
        made = make_cases(family, meshes, scales, REFERENCE_POINTS, args.seed, args.cases)
        for index, case in enumerate(made):
            case.params["index"] = index
        cases += made
    print(f"{len(parts)} objects, {len(cases)} cases: {time.perf_counter() - began:.0f} s")

    report = {
        "seed": args.seed,
        "cases_per_object": args.cases,
        "engine": args.engine,
        "models": {},
        "seconds": {},
    }
    records_of = {}
    for model_name, path in models.items():
        start = time.perf_counter()
        study = Study(path, parts, args.engine)
        records = [study.record(case, args.seed) for case in cases]
        records_of[model_name] = records
        groups = {}
        for family in (*FAMILIES, PAIRS):
            for split in ("seen", "unseen"):
                chosen = [r for r in records if r["family"] == family and r["split"] == split]
                if chosen:
                    groups[f"{family}/{split}"] = summarise(chosen)
        report["models"][model_name] = groups
        report["seconds"][model_name] = round(time.perf_counter() - start, 1)
        print(f"{model_name} ({path}): {report['seconds'][model_name]:.0f} s")
    print()
    print(table(report))
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")
    if args.records:
        args.records.write_text(json.dumps(records_of) + "\n")
    return report


if __name__ == "__main__":
    main()
