"""The evaluation of docs/evaluation-protocol.md: the engine, its ablations and the two
baselines on the same cases, seen and unseen objects, written to a report.

    python -m evaluation --out docs/evaluation            # the full run (see below)
    python -m evaluation --quick --out /tmp/evaluation    # a few objects (~1.5 min)

The full run took 22-35 min on 2 shared cores before the sensor, answer and sensor
side-by-side studies were added; the full plan adds 530 full-gallery cases (417 with a
viewpoint, run again without it; the 216 sensor views also by the 4 ablations) and 40 sensor
views against 8 references for each baseline (the run's time not measured yet).

The studies, each on cases built by ``evaluation.cases`` with one seed:

- ``full-gallery``: the engine (refinement on and off, and the ablations) with the shipped
  gallery of every seen object plus the unseen objects registered as a user would
  (``evaluation.evaluate_mapping.prepare_engine``) but ``FOREIGN``, kept out of the gallery,
  on many cases of every object: the full-cloud families, ``sensor`` views, and the families
  that test knowing when not to answer (``foreign`` on the objects kept out, ``junk``,
  ``units``, ``table``, ``symmetric`` on ``SYMMETRIC_PARTS``). Cases with a viewpoint are also
  run without it (``engine-no-viewpoint``); the ablations run on the full clouds and
  ``sensor`` views only;
- ``side-by-side``: every system, the baselines included, on a small gallery (a few seen and
  unseen objects; the engine restricted to it with ``candidates``), the same cases for all;
- ``sensor-side-by-side``: the engine (with and without the viewpoint) and the baselines on
  ``sensor`` views of a small gallery (the baselines take about a second per reference and
  query), at least 40 identical cases in the full plan;
- ``noise``: so3 cases with Gaussian noise of σ = 0 to 4 % of the scale, the engine and the
  baselines on the side-by-side gallery, and the engine on the full gallery;
- ``frames`` (with HTTP): whole camera frames posted to ``POST /detect`` of a real server, and
  FPFH told the right parts, on the same frames (``evaluation.detect``; alone: ``python -m
  evaluation.detect``).

Every engine answer's verdict, confidence, reasons, points set aside and step timings are
kept per case (``evaluation.records``).

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

from evaluation.cases import ANSWER_FAMILIES, FOREIGN, Case, make_cases, object_scale
from evaluation.detect import FULL_FRAMES, QUICK_FRAMES, FramePlan, run_frames
from evaluation.latency import latency_stats
from evaluation.metrics import ADD_S_POINTS, diameter
from evaluation.records import NO_ANSWER, Answer, Truth, case_record
from service.engine.engine import Engine
from service.engine.sampling import sample_surface
from service.settings import MODELS_DIR
from training.objects import ObjectSpec, load_manifest, load_object_meshes

ENGINE_SYSTEMS = {  # name -> Engine.align keyword arguments
    "engine": {},
    "engine-no-refine": {"refine": False},
    "engine-paper": {"hypotheses": ("paper",)},
    "engine-mapped": {"hypotheses": ("mapped",)},
    "engine-principal-axes": {"hypotheses": ("principal-axes",)},
    "engine-no-viewpoint": {},  # the default engine, never told the viewpoint
}
ABLATIONS = ("engine-no-refine", "engine-paper", "engine-mapped", "engine-principal-axes")
BASELINES = ("ppf", "fpfh")
# Unseen objects kept out of the gallery: the foreign family's parts. Two look like registered
# parts (a block with a round joint; a finger tip beside its finger), two do not.
# units: only parts whose references are in metres. Measured radii: robot links, grippers and
# household objects 0.03-0.9; the procedural blobs 2-6.4 (no unit stated); the millimetre
# meshes (the differential's, the WSG50 finger) 16-75.
METRE_SCALE_MAX = 1.0
# Registered parts with a rotational symmetry, the order of it (0 for a revolution), measured
# on their meshes (tests/evaluation/test_scenes.py checks each): a turn by 360°/order about the
# axis (for a revolution, any turn) moves at most 0.5 % of the surface farther than 3 % of the
# radius off it, and a turn by half that step moves more. Seen and unseen in turn, so that the
# first few are a mix. The differential's shaft and the KUKA flange, round at a glance, are
# half-turn parts: a quarter turn moves a cross hole (9.5 % of the surface) and a notch (1.7 %).
SYMMETRIC_PARTS = {
    "torus": 0,  # seen: a ring (of facets)
    "diff-shaft": 2,  # unseen: a stepped shaft with a cross hole
    "kuka-link-7": 2,  # seen: a flange with a notch
    "toy-cylinder": 2,  # unseen: an elliptic cylinder, a can's half turns
    "lego-brick": 4,  # seen: a square brick with studs, a box's quarter turns
}
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
    sensor_cases: int  # full gallery, per object: sensor views ...
    units_cases: int  # ... millimetre cases (each a full cloud and a sensor view)
    table_cases: int  # ... table scenes
    foreign_objects: int  # objects of FOREIGN used (all are kept out of the gallery)
    foreign_cases: int  # per foreign object (each a full cloud and a sensor view)
    junk_cases: int  # per kind of junk
    symmetric_objects: int  # parts of SYMMETRIC_PARTS used, seen and unseen in turn
    symmetric_groups: int  # per symmetric part: poses, each turned about the axis
    sensor_side_seen: int  # sensor side-by-side gallery: seen and unseen objects
    sensor_side_unseen: int
    sensor_side_cases: int  # sensor views per object of that gallery
    keep_shares: tuple[float, ...] = (0.1, 0.3, 0.5, 0.7, 0.9)
    engine_systems: tuple[str, ...] = ("engine", *ABLATIONS)
    frames: FramePlan | None = None  # the whole-frame study (POST /detect), run with HTTP


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
    sensor_cases=4,
    units_cases=1,
    table_cases=2,
    foreign_objects=len(FOREIGN),
    foreign_cases=3,
    junk_cases=5,
    symmetric_objects=len(SYMMETRIC_PARTS),
    symmetric_groups=2,
    sensor_side_seen=4,
    sensor_side_unseen=4,
    sensor_side_cases=5,
    frames=FULL_FRAMES,
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
    sensor_cases=1,
    units_cases=1,
    table_cases=1,
    foreign_objects=1,
    foreign_cases=1,
    junk_cases=1,
    symmetric_objects=2,
    symmetric_groups=1,
    sensor_side_seen=1,
    sensor_side_unseen=1,
    sensor_side_cases=1,
    keep_shares=(0.1, 0.5, 0.9),
    frames=QUICK_FRAMES,
)


@dataclass
class Study:
    """The cases of one study and the gallery every system in it sees."""

    name: str
    gallery: list[str]
    cases: list[Case]
    systems: tuple[str, ...]


# --- the systems -----------------------------------------------------------------------------


def engine_runner(engine: Engine, system: str, candidates: list[str] | None) -> Callable:
    options = ENGINE_SYSTEMS[system]

    def run(case: Case, viewpoint):
        answer = engine.align(case.points, candidates=candidates, viewpoint=viewpoint, **options)
        return Answer.of_alignment(answer)

    return run


def baseline_runner(system: str, references: dict[str, np.ndarray]) -> Callable:
    if system == "ppf":
        from evaluation.baselines.ppf import PPFRecognizer as Recognizer
    else:
        from evaluation.baselines.fpfh import FPFHRecognizer as Recognizer
    recognizer = Recognizer(references)

    def run(case: Case, viewpoint):
        answer = recognizer.align(case.points, viewpoint)
        return Answer(answer["label"], answer["rotation"], answer["translation"])

    return run


def case_viewpoint(system: str, case: Case) -> np.ndarray | None:
    """Where the camera was, for the systems told it: the sensor's viewpoint of a camera-frame
    cloud, or the partial family's camera (the baselines orient normals toward it)."""
    if system == "engine-no-viewpoint":
        return None
    where = case.params.get("viewpoint")
    if where is None and system in BASELINES:
        where = case.params.get("camera")
    return None if where is None else np.asarray(where, dtype=np.float64)


def runs_on(system: str, case: Case) -> bool:
    """Which cases a system answers: ``engine-no-viewpoint`` those that have a viewpoint (the
    others it would answer as ``engine``), the ablations the full clouds and sensor views."""
    if system == "engine-no-viewpoint":
        return "viewpoint" in case.params
    if system in ABLATIONS:
        return case.family not in ANSWER_FAMILIES
    return True


def run_system(run: Callable, system: str, study: Study, truths: dict[str, Truth]) -> list[dict]:
    records = []
    cases = [(index, case) for index, case in enumerate(study.cases) if runs_on(system, case)]
    for index, case in tqdm(cases, desc=f"{study.name}: {system}", leave=False):
        viewpoint = case_viewpoint(system, case)
        began = time.perf_counter()
        try:
            answer = run(case, viewpoint)
        except RuntimeError:  # a baseline that finds no pose at all: a failed case
            answer = NO_ANSWER
        latency = (time.perf_counter() - began) * 1e3
        record = case_record(case, truths, answer, latency, viewpoint is not None)
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
        answered = run_system(run, system, study, truths)
        records.extend(answered)
        seconds[system] = time.perf_counter() - began
        log(f"  {study.name}: {system} on {len(answered)} cases in {seconds[system]:.0f} s")
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


def sensor_cases(meshes: dict, truths: dict[str, Truth], seed: int, count: int) -> list[Case]:
    scales = {name: truths[name].scale for name in meshes}
    return make_cases("sensor", meshes, scales, REFERENCE_POINTS, seed, count)


def answer_cases(
    plan: Plan,
    meshes: dict,
    foreign_meshes: dict,
    symmetric_meshes: dict,
    truths: dict[str, Truth],
    seed: int,
) -> list[Case]:
    """The sensor views and the families of knowing when not to answer, for the full gallery:
    sensor, units (those in metres) and table on ``meshes``, foreign on ``foreign_meshes``
    (kept out of the gallery), junk the size of the registered parts, symmetric on
    ``symmetric_meshes``."""
    scales = {name: truth.scale for name, truth in truths.items()}
    registered = {name: t.scale for name, t in truths.items() if name not in foreign_meshes}
    in_metres = {name: m for name, m in meshes.items() if scales[name] < METRE_SCALE_MAX}
    counts = (
        ("sensor", meshes, scales, plan.sensor_cases),
        ("units", in_metres, scales, plan.units_cases),
        ("table", meshes, scales, plan.table_cases),
        ("foreign", foreign_meshes, scales, plan.foreign_cases),
        ("junk", {}, registered, plan.junk_cases),
        ("symmetric", symmetric_meshes, scales, plan.symmetric_groups),
    )
    cases = []
    for family, chosen, sizes, count in counts:
        if count > 0:
            cases += make_cases(
                family, chosen, sizes, REFERENCE_POINTS, seed, count, orders=SYMMETRIC_PARTS
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
    stats = latency_stats(latencies, ("median_ms", "p95_ms"))
    return {
        "cases": len(cases),
        "references": len(references),
        "accuracy": right / len(cases),
        "latency_ms": latencies,
        "latency_ms_median": stats["median_ms"],
        "latency_ms_p95": stats["p95_ms"],
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


def spread(specs: list[ObjectSpec], count: int) -> list[ObjectSpec]:
    """``count`` objects spaced evenly through ``specs`` (a mix of its categories)."""
    if count <= 0:
        return []
    indices = np.unique(np.linspace(0, len(specs) - 1, min(count, len(specs))).round())
    return [specs[int(i)] for i in indices]


def build_truths(engine: Engine, split_of: dict[str, str]) -> dict[str, Truth]:
    truths = {}
    for name, split in split_of.items():
        reference = engine.entry(name).reference
        points = np.asarray(reference.points, dtype=np.float64)
        truths[name] = Truth(points, float(reference.scale), diameter(points), split)
    return truths


def foreign_truths(meshes: dict) -> dict[str, Truth]:
    """What the metrics need of parts kept out of the gallery: their seed-0 reference cloud,
    as a registration would sample it."""
    truths = {}
    for name, mesh in meshes.items():
        points = sample_surface(mesh, REFERENCE_POINTS, 0).astype(np.float64)
        truths[name] = Truth(points, object_scale(points), diameter(points), "unseen")
    return truths


def add_model_points(truths: dict[str, Truth], meshes: dict) -> None:
    """ADD-S on a dense sample of each object's mesh (``ADD_S_POINTS``), for those with one."""
    for name, mesh in meshes.items():
        if name in truths:
            truths[name].model_points = sample_surface(mesh, ADD_S_POINTS, 1).astype(np.float64)


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
    foreign_all = [s for s in unseen_all if s.name in FOREIGN]
    unseen_all = [s for s in unseen_all if s.name not in FOREIGN]  # registered at run time
    engine, _ = prepare_engine(model, gallery, unseen_all)
    split_of = {s.name: "seen" for s in seen_all} | {s.name: "unseen" for s in unseen_all}
    split_of = {name: split for name, split in split_of.items() if name in engine.names()}
    truths = build_truths(engine, split_of)

    full_specs = pick(seen_all, plan.seen) + pick(unseen_all, plan.unseen)
    seen_side, unseen_side = seen_all[: plan.baseline_seen], unseen_all[: plan.baseline_unseen]
    side_specs = seen_side + unseen_side
    sensor_side_specs = spread(seen_all, plan.sensor_side_seen) + spread(
        unseen_all, plan.sensor_side_unseen
    )
    foreign_specs = foreign_all[: plan.foreign_objects]
    symmetric_specs = [s for s in seen_all + unseen_all if s.name in SYMMETRIC_PARTS]
    symmetric_specs = sorted(symmetric_specs, key=lambda s: list(SYMMETRIC_PARTS).index(s.name))
    symmetric_specs = symmetric_specs[: plan.symmetric_objects]
    every = full_specs + side_specs + sensor_side_specs + foreign_specs + symmetric_specs
    meshes = load_object_meshes({s.name: s for s in every}.values())
    truths |= foreign_truths({s.name: meshes[s.name] for s in foreign_specs})
    add_model_points(truths, meshes)
    full_meshes = {s.name: meshes[s.name] for s in full_specs}
    side_meshes = {s.name: meshes[s.name] for s in side_specs}
    # the noise study: the first side-by-side objects, seen and unseen in turn
    interleaved = [s for pair in itertools.zip_longest(seen_side, unseen_side) for s in pair if s]
    noise_meshes = {s.name: meshes[s.name] for s in interleaved[: plan.noise_objects]}
    sensor_side_meshes = {s.name: meshes[s.name] for s in sensor_side_specs}

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
            )  # fmt: skip
            + answer_cases(
                plan,
                full_meshes,
                {s.name: meshes[s.name] for s in foreign_specs},
                {s.name: meshes[s.name] for s in symmetric_specs},
                truths,
                seed,
            ),
            (*plan.engine_systems, "engine-no-viewpoint"),
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
            "sensor-side-by-side",
            list(sensor_side_meshes),
            sensor_cases(sensor_side_meshes, truths, seed, plan.sensor_side_cases),
            ("engine", "engine-no-viewpoint", *BASELINES),
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

    frames = None
    if http and plan.frames is not None:
        began_frames = time.perf_counter()
        frames = run_frames(plan.frames, seed, model, gallery, log)
        seconds["frames"] = time.perf_counter() - began_frames

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
        "foreign": [spec.name for spec in foreign_specs],
        "http": http_result,
        "frames": frames,
        "records": records,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a few objects and cases (~1.5 min)")
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
