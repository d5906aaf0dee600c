"""The evaluation of shared/EVALUATION.md: the engine, its ablations and the two baselines on the
same cases, seen and unseen objects, written to a report.

    python -m evaluation --out docs/evaluation            # the full run (~35 min, 2 cores)
    python -m evaluation --quick --out /tmp/evaluation    # a few objects (~3 min)

Three studies, each on cases built by ``evaluation.cases`` with one seed:

- ``full-gallery``: the engine (refinement on and off, and the ablations) with the shipped
  gallery of every seen object plus every unseen object registered as a user would
  (``evaluation.evaluate_mapping.prepare_engine``), on many cases of every object;
- ``side-by-side``: every system, the baselines included, on a small gallery (a few seen and
  unseen objects; the engine restricted to it with ``candidates``), the same cases for all;
- ``noise``: so3 cases with Gaussian noise of σ = 0 to 4 % of the scale, the engine and the
  baselines on the side-by-side gallery, and the engine on the full gallery.

The default engine is also timed through HTTP (``python -m service`` as a real process) on a
subset of cases. ``evaluation.report`` writes README.md, results.json and the plots.
"""

from __future__ import annotations

import argparse
import itertools
import os
import platform
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from evaluation.cases import Case, make_cases
from evaluation.metrics import (
    add_s,
    alignment_error_normalized,
    alignment_floor,
    diameter,
    geodesic_deg,
)
from service.engine.alignment import to_model_frame
from service.engine.engine import Engine
from service.settings import MODELS_DIR
from training.objects import ObjectSpec, load_manifest, load_object_meshes

ENGINE_SYSTEMS = {  # name -> Engine.align keyword arguments
    "engine": {},
    "engine-no-refine": {"refine": False},
    "engine-paper": {"hypotheses": ("paper",)},
    "engine-mapped": {"hypotheses": ("mapped",)},
    "engine-principal-axes": {"hypotheses": ("principal-axes",)},
}
BASELINES = ("ppf", "fpfh")
NOISE_SHARES = (0.0, 0.005, 0.01, 0.02, 0.04)  # σ per coordinate, share of the scale
REFERENCE_POINTS = 2048
RAW_TYPE = {"content-type": "application/octet-stream"}


@dataclass(frozen=True)
class Plan:
    """What to run: objects and cases per object of each study."""

    seen: int | None  # full-gallery study: this many seen / unseen objects (None: all)
    unseen: int | None
    paper_poses: int  # full gallery, per object: paper poses (of 125) ...
    sparse_poses: int  # ... paper poses of the sparse family, each at every keep share
    random_cases: int  # ... so3 and noisy cases
    partial_cases: int  # ... partial cases
    baseline_seen: int  # side-by-side gallery: this many seen and unseen objects
    baseline_unseen: int
    baseline_paper_poses: int  # side-by-side, per object
    baseline_sparse_poses: int
    baseline_random_cases: int
    noise_objects: int  # noise study: side-by-side objects used (the first few)
    noise_cases: int  # so3 cases per object and noise level
    http_cases: int  # so3 cases sent through HTTP (full gallery)
    keep_shares: tuple[float, ...] = (0.1, 0.3, 0.5, 0.7, 0.9)
    engine_systems: tuple[str, ...] = tuple(ENGINE_SYSTEMS)


FULL = Plan(
    seen=None,
    unseen=None,
    paper_poses=4,
    sparse_poses=1,
    random_cases=2,
    partial_cases=3,
    baseline_seen=4,
    baseline_unseen=2,
    baseline_paper_poses=1,
    baseline_sparse_poses=1,
    baseline_random_cases=1,
    noise_objects=2,
    noise_cases=1,
    http_cases=40,
)
QUICK = Plan(
    seen=3,
    unseen=2,
    paper_poses=2,
    sparse_poses=1,
    random_cases=1,
    partial_cases=1,
    baseline_seen=1,
    baseline_unseen=1,
    baseline_paper_poses=1,
    baseline_sparse_poses=1,
    baseline_random_cases=1,
    noise_objects=1,
    noise_cases=1,
    http_cases=5,
    keep_shares=(0.1, 0.5, 0.9),
)


@dataclass
class Truth:
    """What the metrics need of one registered object."""

    points: np.ndarray  # the reference cloud, model frame
    scale: float
    diameter: float
    split: str


@dataclass
class Study:
    """The cases of one study and the gallery every system in it sees."""

    name: str
    gallery: list[str]
    cases: list[Case]
    systems: tuple[str, ...]


# --- one case --------------------------------------------------------------------------------


def case_record(
    case: Case,
    truths: dict[str, Truth],
    label: str | None,
    rotation: np.ndarray | None,
    translation: np.ndarray | None,
    latency_ms: float,
) -> dict:
    """The metrics of one answer. ADD-S and the rotation error are measured on the true object;
    the alignment error (the service's own figure) on the reference the answer named, beside
    its floor: the true object's reference at the true pose."""
    truth = truths[case.object_name]
    record = {
        "object": case.object_name,
        "set": truth.split,
        "family": case.family,
        "points": len(case.points),
        **{k: v for k, v in case.params.items() if k in ("pose_index", "keep_share")},
        **{k: v for k, v in case.params.items() if k in ("visible_share", "noise_share")},
        "label": label,
        "label_ok": label == case.object_name,
        "latency_ms": latency_ms,
        "align_err_floor": alignment_floor(
            to_model_frame(case.points, case.rotation, case.translation), truth.points, truth.scale
        ),
        "rot_err_deg": None,
        "add_s": None,
        "align_err": None,
    }
    if label is None or rotation is None:
        return record
    named = truths[label]
    record["rot_err_deg"] = geodesic_deg(rotation, case.rotation)
    record["add_s"] = add_s(
        truth.points, rotation, translation, case.rotation, case.translation, truth.diameter
    )
    record["align_err"] = alignment_error_normalized(
        case.points, named.points, rotation, translation, named.scale
    )
    return record


# --- the systems -----------------------------------------------------------------------------


def engine_runner(engine: Engine, system: str, candidates: list[str] | None) -> Callable:
    options = ENGINE_SYSTEMS[system]

    def run(case: Case):
        answer = engine.align(case.points, candidates=candidates, **options)
        return answer.label, answer.rotation, answer.translation

    return run


def baseline_runner(system: str, references: dict[str, np.ndarray]) -> Callable:
    if system == "ppf":
        from evaluation.baselines.ppf import PPFRecognizer as Recognizer
    else:
        from evaluation.baselines.fpfh import FPFHRecognizer as Recognizer
    recognizer = Recognizer(references)

    def run(case: Case):
        camera = case.params.get("camera")
        answer = recognizer.align(case.points, None if camera is None else np.asarray(camera))
        return answer["label"], answer["rotation"], answer["translation"]

    return run


def run_system(run: Callable, system: str, study: Study, truths: dict[str, Truth]) -> list[dict]:
    records = []
    for index, case in enumerate(tqdm(study.cases, desc=f"{study.name}: {system}", leave=False)):
        began = time.perf_counter()
        try:
            label, rotation, translation = run(case)
        except RuntimeError:  # a baseline that finds no pose at all: a failed case
            label, rotation, translation = None, None, None
        latency = (time.perf_counter() - began) * 1e3
        record = case_record(case, truths, label, rotation, translation, latency)
        record.update(study=study.name, system=system, case=index)
        records.append(record)
    return records


def run_study(
    study: Study, engine: Engine, truths: dict[str, Truth], log: Callable[[str], None]
) -> tuple[list[dict], dict]:
    """Every system of ``study`` on every case; returns the records and the seconds taken."""
    candidates = None if set(study.gallery) == set(engine.names()) else study.gallery
    records, seconds = [], {}
    for system in study.systems:
        began = time.perf_counter()
        if system in ENGINE_SYSTEMS:
            run = engine_runner(engine, system, candidates)
        else:
            references = {name: truths[name].points for name in study.gallery}
            run = baseline_runner(system, references)
            seconds[f"{system}_build"] = time.perf_counter() - began
        records.extend(run_system(run, system, study, truths))
        seconds[system] = time.perf_counter() - began
        log(f"  {study.name}: {system} on {len(study.cases)} cases in {seconds[system]:.0f} s")
    return records, seconds


# --- the cases -------------------------------------------------------------------------------


def family_cases(
    meshes: dict, truths: dict[str, Truth], seed: int, paper: int, sparse: int, random: int,
    partial: int, keep_shares: tuple[float, ...],
) -> list[Case]:  # fmt: skip
    scales = {name: truths[name].scale for name in meshes}
    counts = {"paper-poses": paper, "sparse": sparse, "so3": random, "noisy": random}
    counts["partial"] = partial
    cases = []
    for family, count in counts.items():
        if count > 0:
            cases += make_cases(
                family, meshes, scales, REFERENCE_POINTS, seed, count, keep_shares=keep_shares
            )
    return cases


def noisy_cases(
    meshes: dict, truths: dict[str, Truth], seed: int, count: int, shares: tuple[float, ...]
) -> list[Case]:
    """so3 cases of every object, each at every noise level (σ = share × scale)."""
    scales = {name: truths[name].scale for name in meshes}
    cases = []
    for index, case in enumerate(make_cases("so3", meshes, scales, REFERENCE_POINTS, seed, count)):
        for level, share in enumerate(shares):
            rng = np.random.default_rng([seed, index, level])
            sigma = share * scales[case.object_name]
            points = case.points + rng.normal(scale=sigma, size=case.points.shape)
            params = {**case.params, "noise_share": share}
            cases.append(
                Case(
                    case.object_name,
                    "so3-noise",
                    points.astype(np.float32),
                    case.rotation,
                    case.translation,
                    params,
                )
            )
    return cases


# --- HTTP ------------------------------------------------------------------------------------


def http_latency(
    engine: Engine, cases: list[Case], model: Path, gallery: Path, log: Callable[[str], None]
) -> dict:
    """The default engine as a client sees it: raw float32 bodies to ``POST /align`` of a
    ``python -m service`` process holding the same references as the full-gallery engine."""
    import httpx

    from evaluation.served import ServiceProcess, seed_store

    references = [engine.get(name) for name in engine.names()]
    latencies, right = [], 0
    with tempfile.TemporaryDirectory(prefix="dpc-eval-") as tmp:
        data_dir = Path(tmp) / "data"
        seed_store(data_dir, references, engine.mapper.model_hash)
        log(f"  http: starting the service with {len(references)} references")
        with ServiceProcess(
            data_dir / "service.log",
            300.0,
            gallery__data_dir=str(data_dir),
            model__path=str(model),
            model__gallery=str(gallery),
            server__log_level="warning",
        ) as service:
            with httpx.Client(base_url=service.url, timeout=300.0) as client:
                warm = np.asarray(cases[0].points, "<f4").tobytes()
                client.post("/align", content=warm, headers=RAW_TYPE)
                for case in tqdm(cases, desc="http: engine", leave=False):
                    body = np.asarray(case.points, "<f4").tobytes()
                    began = time.perf_counter()
                    answer = client.post("/align", content=body, headers=RAW_TYPE)
                    latencies.append((time.perf_counter() - began) * 1e3)
                    if answer.status_code != 200:
                        raise RuntimeError(f"/align answered {answer.status_code}: {answer.text}")
                    right += answer.json()["label"] == case.object_name
    return {
        "cases": len(cases),
        "references": len(references),
        "accuracy": right / len(cases),
        "latency_ms": latencies,
        "latency_ms_median": float(np.median(latencies)),
        "latency_ms_p95": float(np.percentile(latencies, 95)),
    }


# --- the run ---------------------------------------------------------------------------------


def machine() -> dict:
    model_name = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model_name = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "cpu_model": model_name,
        "load_average_at_start": list(os.getloadavg()),
    }


def cases_per_family(cases: list[Case]) -> dict[str, int]:
    families = [c.family for c in cases]
    return {family: families.count(family) for family in dict.fromkeys(families)}


def pick(specs: list[ObjectSpec], count: int | None) -> list[ObjectSpec]:
    return list(specs) if count is None else list(specs[:count])


def build_truths(engine: Engine, split_of: dict[str, str]) -> dict[str, Truth]:
    truths = {}
    for name, split in split_of.items():
        reference = engine.entry(name).reference
        points = np.asarray(reference.points, dtype=np.float64)
        truths[name] = Truth(points, float(reference.scale), diameter(points), split)
    return truths


def evaluate(
    plan: Plan,
    seed: int = 0,
    model: Path = MODELS_DIR / "dpc_mn.onnx",
    gallery: Path = MODELS_DIR / "gallery.npz",
    http: bool = True,
    log: Callable[[str], None] = print,
) -> dict:
    """Run the plan; returns everything the report needs (records included)."""
    from evaluation.evaluate_mapping import prepare_engine

    began = time.perf_counter()
    started = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    seen_all, unseen_all = load_manifest(split="seen"), load_manifest(split="unseen")
    engine, _ = prepare_engine(model, gallery, unseen_all)
    split_of = {s.name: "seen" for s in seen_all} | {s.name: "unseen" for s in unseen_all}
    split_of = {name: split for name, split in split_of.items() if name in engine.names()}
    truths = build_truths(engine, split_of)

    full_specs = pick(seen_all, plan.seen) + pick(unseen_all, plan.unseen)
    seen_side, unseen_side = seen_all[: plan.baseline_seen], unseen_all[: plan.baseline_unseen]
    side_specs = seen_side + unseen_side
    meshes = load_object_meshes({s.name: s for s in full_specs + side_specs}.values())
    full_meshes = {s.name: meshes[s.name] for s in full_specs}
    side_meshes = {s.name: meshes[s.name] for s in side_specs}
    # the noise study: the first side-by-side objects, seen and unseen in turn
    interleaved = [s for pair in itertools.zip_longest(seen_side, unseen_side) for s in pair if s]
    noise_meshes = {s.name: meshes[s.name] for s in interleaved[: plan.noise_objects]}

    log("building the cases ...")
    studies = [
        Study(
            "full-gallery",
            engine.names(),
            family_cases(
                full_meshes,
                truths,
                seed,
                plan.paper_poses,
                plan.sparse_poses,
                plan.random_cases,
                plan.partial_cases,
                plan.keep_shares,
            ),  # fmt: skip
            plan.engine_systems,
        ),
        Study(
            "side-by-side",
            list(side_meshes),
            family_cases(
                side_meshes,
                truths,
                seed,
                plan.baseline_paper_poses,
                plan.baseline_sparse_poses,
                plan.baseline_random_cases,
                plan.baseline_random_cases,
                plan.keep_shares,
            ),  # fmt: skip
            (*plan.engine_systems, *BASELINES),
        ),
        Study(
            "noise",
            list(side_meshes),
            noisy_cases(noise_meshes, truths, seed, plan.noise_cases, NOISE_SHARES),
            ("engine", *BASELINES),
        ),
        Study(
            "noise-full-gallery",
            engine.names(),
            noisy_cases(full_meshes, truths, seed, plan.noise_cases, NOISE_SHARES),
            ("engine",),
        ),
    ]
    log(f"cases built in {time.perf_counter() - began:.0f} s")

    records, seconds = [], {}
    for study in studies:
        log(f"{study.name}: {len(study.cases)} cases, gallery of {len(study.gallery)}")
        study_records, study_seconds = run_study(study, engine, truths, log)
        records += study_records
        seconds[study.name] = study_seconds

    http_result = None
    if http and plan.http_cases:
        scales = {name: truths[name].scale for name in full_meshes}
        per_object = -(-plan.http_cases // len(full_meshes))
        cases = make_cases("so3", full_meshes, scales, REFERENCE_POINTS, seed + 1, per_object)
        order = sorted(range(len(cases)), key=lambda i: (i % per_object, i))  # interleaved
        began_http = time.perf_counter()
        http_result = http_latency(
            engine, [cases[i] for i in order][: plan.http_cases], model, gallery, log
        )
        seconds["http"] = time.perf_counter() - began_http

    return {
        "machine": machine(),
        "started_utc": started,
        "seconds": time.perf_counter() - began,
        "seconds_per_study": seconds,
        "seed": seed,
        "plan": asdict(plan),
        "model": str(model),
        "model_sha256": engine.mapper.model_hash,
        "engine_settings": engine.settings.model_dump(mode="json"),
        "studies": {
            s.name: {
                "gallery": s.gallery,
                "objects": sorted({c.object_name for c in s.cases}),
                "cases": len(s.cases),
                "cases_per_family": {
                    f: sum(c.family == f for c in s.cases)
                    for f in dict.fromkeys(c.family for c in s.cases)
                },  # fmt: skip
                "systems": list(s.systems),
            }
            for s in studies
        },
        "splits": split_of,
        "http": http_result,
        "records": records,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a few objects and cases (~3 min)")
    parser.add_argument("--out", type=Path, default=Path("docs/evaluation"))
    parser.add_argument("--model", type=Path, default=MODELS_DIR / "dpc_mn.onnx")
    parser.add_argument("--gallery", type=Path, default=MODELS_DIR / "gallery.npz")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-http", action="store_true", help="skip the HTTP latency")
    args = parser.parse_args(argv)

    from evaluation.report import write_report

    plan = QUICK if args.quick else FULL
    result = evaluate(plan, args.seed, args.model, args.gallery, not args.no_http)
    result["command"] = "python -m evaluation" + (" --quick" if args.quick else "")
    write_report(result, args.out)
    print(f"report written to {args.out / 'README.md'} in {result['seconds']:.0f} s")
    return result


if __name__ == "__main__":
    main()
