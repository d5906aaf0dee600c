"""The engine's search budget against its accuracy: the same cases under several settings.

    python -m benchmarks.engine_settings \\
        --variant before=screened:32,verify_points:96,icp_iterations:20 \\
        --variant faster=screened:8,icp_iterations:8 --json out.json

Each variant is the default ``EngineSettings`` with the given fields changed; ``default`` (the
shipped settings) always runs first. Every variant answers the same cases of the evaluation's
families (``--families``; default the full clouds, single views, table scenes, foreign parts and
junk) on the evaluation's gallery (the shipped references, the unseen parts registered at run
time, the foreign parts kept out: ``evaluation.evaluate_mapping.prepare_engine``), in this
process, one case at a time, told the viewpoint where the case has one (never, with
``--no-viewpoint``). The references are
computed once: the settings changed here only steer the search (which hypotheses are verified,
screened and refined), never what a registration stores. Per variant and family it prints the
success (right label, ADD-S < 0.1), the precise share (< 0.02), the share answered ``"match"``
and right, the false accepts (``"match"`` on a foreign part or junk), the median latency and the
median of each step; for each family with both, also for its seen and unseen parts apart.
``--registered cloud`` registers the unseen parts as a 2,048-point cloud sampled on their mesh
(a scan, a CAD export's points) instead of the mesh: its views are then rendered from a depth
buffer of those points (``service.engine.views``). The confidence is the shipped
calibration's, fitted under the default settings: a variant that moves the fit and coverage
moves it too (refit with ``python -m evaluation.calibrate`` before shipping other settings).

Needs the ``eval`` and ``train`` extras (pybullet's meshes). Latency figures are only worth
comparing within one run, on a quiet machine.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from evaluation.cases import make_cases
from evaluation.evaluate import (
    FOREIGN,
    Study,
    add_model_points,
    build_truths,
    engine_runner,
    foreign_truths,
    run_system,
)
from evaluation.evaluate_mapping import prepare_engine
from evaluation.latency import median
from evaluation.metrics import summarize
from service.engine.confidence import Calibration
from service.engine.engine import Engine
from service.settings import MODELS_DIR, EngineSettings
from training.objects import load_manifest, load_object_meshes

FAMILIES = ("so3", "noisy", "paper-poses", "partial", "sensor", "table", "foreign", "junk")
PER_OBJECT = {"paper-poses": 4, "so3": 2, "noisy": 2, "partial": 3, "sensor": 4, "table": 2}
FOREIGN_CASES, JUNK_CASES = 3, 5  # as the evaluation's full plan


def parse_variant(text: str) -> tuple[str, dict]:
    """``name=field:value,field:value`` -> (name, {field: value}); values are JSON."""
    name, _, fields = text.partition("=")
    if not name or not fields:
        raise argparse.ArgumentTypeError(f"{text!r}: expected name=field:value[,field:value]")
    changes = {}
    for item in fields.split(","):
        field, _, value = item.partition(":")
        if field not in EngineSettings.model_fields:
            raise argparse.ArgumentTypeError(f"{field!r} is not an engine setting")
        try:
            changes[field] = json.loads(value)
        except json.JSONDecodeError as error:
            raise argparse.ArgumentTypeError(f"{item!r}: the value is not JSON") from error
    EngineSettings(**changes)  # a bad value fails here, naming the field
    return name, changes


def build_cases(families, meshes, foreign_meshes, truths, seed):
    scales = {name: truth.scale for name, truth in truths.items()}
    registered = {name: scales[name] for name in meshes}
    cases = []
    for family in families:
        if family == "foreign":
            cases += make_cases(family, foreign_meshes, scales, 2048, seed, FOREIGN_CASES)
        elif family == "junk":
            cases += make_cases(family, {}, registered, 2048, seed, JUNK_CASES)
        else:
            cases += make_cases(family, meshes, scales, 2048, seed, PER_OBJECT[family])
    return cases


def summary(records: list[dict]) -> dict:
    figures = summarize(records)
    steps = sorted({step for r in records for step in r["timings_ms"]})
    return {
        "cases": figures["cases"],
        "success": figures["success"],
        "precise": figures["precise"],
        "match_and_right": float(np.mean([r["accepted"] and r["success"] for r in records])),
        "false_accepts": int(sum(r["accepted"] and not r["success"] for r in records)),
        "latency_ms_median": figures["latency_ms_median"],
        "steps_ms": {
            step: median([r["timings_ms"].get(step, 0.0) for r in records]) for step in steps
        },
    }


def print_table(report: dict) -> None:
    print(
        f"{'variant':12s} {'family':14s} {'cases':>5s} {'success':>8s} {'precise':>8s}"
        f" {'match+right':>11s} {'false acc.':>10s} {'median ms':>9s}  steps (median ms)"
    )
    for name, families in report["variants"].items():
        for family, s in families.items():
            slow = sorted(s["steps_ms"].items(), key=lambda kv: -kv[1])
            steps = ", ".join(f"{k} {v:.1f}" for k, v in slow if k != "total")
            print(
                f"{name:12s} {family:14s} {s['cases']:5d} {s['success']:8.1%} {s['precise']:8.1%}"
                f" {s['match_and_right']:11.1%} {s['false_accepts']:10d}"
                f" {s['latency_ms_median']:9.1f}  {steps}"
            )


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.engine_settings", description=__doc__.split("\n")[0]
    )
    parser.add_argument(
        "--variant",
        type=parse_variant,
        action="append",
        default=[],
        help="name=field:value[,field:value] (repeatable)",
    )
    parser.add_argument("--families", default=",".join(FAMILIES), help="comma-separated")
    parser.add_argument(
        "--objects", type=int, default=None, help="every n-th object only (seen and unseen alike)"
    )
    parser.add_argument(
        "--registered",
        choices=("mesh", "cloud"),
        default="mesh",
        help="how the unseen parts are registered: their mesh, or a 2,048-point cloud of it",
    )
    parser.add_argument(
        "--no-viewpoint", action="store_true", help="never tell the engine a case's viewpoint"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--model", type=Path, default=MODELS_DIR / "dpc_mn.onnx")
    parser.add_argument("--gallery", type=Path, default=MODELS_DIR / "gallery.npz")
    parser.add_argument("--json", type=Path)
    parser.add_argument(
        "--records",
        type=Path,
        help="write every case's scored answer here (a variant's beside it: NAME-VARIANT.json)",
    )
    args = parser.parse_args(argv)
    args.families = [f for f in args.families.split(",") if f]
    unknown = [f for f in args.families if f not in FAMILIES]
    if unknown:
        parser.error(f"unknown families {unknown}; pick from {FAMILIES}")
    return args


def variant_path(records: Path, name: str) -> Path:
    """Where a variant's records go: beside the default's, named for it."""
    return records.with_name(f"{records.stem}-{name}{records.suffix}")


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    seen, unseen = load_manifest(split="seen"), load_manifest(split="unseen")
    foreign = [s for s in unseen if s.name in FOREIGN]
    unseen = [s for s in unseen if s.name not in FOREIGN]
    engine, _ = prepare_engine(args.model, args.gallery, unseen, args.registered == "mesh")
    references = [engine.get(name) for name in engine.names()]
    split_of = {s.name: "seen" for s in seen} | {s.name: "unseen" for s in unseen}
    truths = build_truths(engine, {n: s for n, s in split_of.items() if n in engine.names()})
    specs = [s for s in seen + unseen if s.name in truths]
    specs = specs[:: args.objects] if args.objects else specs
    meshes = load_object_meshes(specs + foreign)
    foreign_meshes = {s.name: meshes.pop(s.name) for s in foreign}
    truths |= foreign_truths(foreign_meshes)
    add_model_points(truths, {**meshes, **foreign_meshes})  # ADD-S as the evaluation's
    cases = build_cases(args.families, meshes, foreign_meshes, truths, args.seed)
    if args.no_viewpoint:  # a camera-frame cloud answered as if its camera were unknown
        for case in cases:
            case.params.pop("viewpoint", None)
    calibration = args.model.parent / "confidence.json"
    report = {
        "cases": len(cases),
        "families": args.families,
        "registered": args.registered,
        "viewpoint": not args.no_viewpoint,
        "variants": {},
        "settings": {},
    }
    for name, changes in [("default", {}), *args.variant]:
        settings = EngineSettings(**changes)
        variant = Engine(
            engine.mapper, settings, Calibration.load(calibration) if calibration.exists() else None
        )
        variant.load(references)
        study = Study(name, variant.names(), cases, ("engine",))
        run = engine_runner(variant, "engine", study.gallery)
        records = run_system(run, "engine", study, truths)
        report["settings"][name] = changes
        if args.records:  # the default's at the path, each variant's beside it
            path = args.records if name == "default" else variant_path(args.records, name)
            path.write_text(json.dumps(records, indent=0, default=float))
        report["variants"][name] = {
            family: summary([r for r in records if r["family"] == family])
            for family in args.families
        }
        for family in args.families:  # the seen and the unseen parts apart
            for split in ("seen", "unseen"):
                chosen = [r for r in records if r["family"] == family and r["set"] == split]
                if chosen and len(chosen) < sum(r["family"] == family for r in records):
                    report["variants"][name][f"{family}/{split}"] = summary(chosen)
        print(f"{name}: {len(records)} cases", flush=True)
    print_table(report)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    main()
