"""``POST /align`` latency and throughput over real HTTP, beside the engine's own time.

``python -m benchmarks.align_http [--references 40 1000] [--accuracy] [--json out.json]``

For each gallery size the service runs as a real process (``python -m service``) on a free
loopback port with a data directory of its own, seeded before it starts straight through
``service.gallery.store.GalleryStore`` (the first 40 references of the shipped gallery; past the
shipped ones, padding references: the procedurally generated objects of pybullet_data that the
object manifest does not use, sampled as a registration samples them, computed once per model
and cached). Against it:

- sequential requests, one keep-alive client, JSON and raw float32 bodies (bodies encoded
  before the clock starts): median and p95 latency, and the median time per engine step from
  the answers' ``timings_ms``;
- requests per second with 1, 2 and 4 concurrent clients (threads, one client each);
- removing and registering one reference (each refits the classifier on the whole gallery);
- ``Engine.align`` in this process on the same clouds, so the HTTP overhead is visible.

The clouds are 2,048-point ``so3`` cases (``evaluation.cases.make_cases``) of the first 40 seen
objects. Every count is fixed and the run stops by itself; nothing leaves loopback. Also the
classifier refit for 100 references (after one change, and from scratch) and, with
``--accuracy``, the share of paper-poses, so3 and sparse cases that succeed (right label and
ADD-S < 0.10) on seen objects and on unseen ones registered through ``POST /references``.

The model comes from ``--model`` / ``--gallery`` or ``DPC_MODEL__PATH`` / ``DPC_MODEL__GALLERY``;
other ``DPC_*`` variables (engine settings) reach the served process and the in-process engine
alike.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import httpx
import numpy as np
import orjson

from evaluation.cases import Case, make_cases
from evaluation.metrics import SUCCESS_ADD_S, add_s, diameter
from evaluation.served import ServiceProcess, seed_store
from service.engine.classifier import LinearClassifier, classifier_input, view_gram
from service.engine.engine import Engine
from service.engine.mapping import Mapper
from service.engine.reference import Reference
from service.engine.sampling import MeshError, load_mesh, sample_surface
from service.gallery.gallery_file import load_gallery, save_gallery
from service.settings import EngineSettings, Settings
from training.objects import data_root, load_manifest, load_object_meshes

REPO = Path(__file__).resolve().parent.parent
BASE_REFERENCES = 40  # the gallery the latency target is stated for
TARGET_MEDIAN_MS = 10.0
TARGET_GROWTH_MS = 2.0
REFERENCE_POINTS = 2048
REFERENCE_SEED = 0  # the shipped gallery's references are the meshes sampled with seed 0
STEPS = ("normalize", "map", "classify", "hypothesise", "verify", "refine", "measure", "total")
ACCURACY_FAMILIES = ("paper-poses", "so3", "sparse")
JSON_TYPE = {"content-type": "application/json"}
RAW_TYPE = {"content-type": "application/octet-stream"}


# --- figures ---------------------------------------------------------------------------------


def latency_stats(values_ms: list[float]) -> dict:
    values = np.asarray(values_ms, dtype=np.float64)
    return {
        "count": len(values),
        "median_ms": float(np.median(values)),
        "p95_ms": float(np.percentile(values, 95)),
        "mean_ms": float(values.mean()),
        "min_ms": float(values.min()),
    }


def step_medians(timings: list[dict[str, float]]) -> dict[str, float]:
    keys = [k for k in STEPS if any(k in t for t in timings)]
    keys += sorted({k for t in timings for k in t} - set(keys))
    return {k: float(np.median([t.get(k, 0.0) for t in timings])) for k in keys}


def mark(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


# --- clouds and references -------------------------------------------------------------------


@dataclass
class Cloud:
    case: Case
    json_body: bytes
    raw_body: bytes


def encode(case: Case) -> Cloud:
    points = np.asarray(case.points, dtype=np.float32)
    # six decimals (a micrometre in metres), as a client that writes its own JSON would send
    json_body = orjson.dumps({"points": np.round(points.astype(np.float64), 6).tolist()})
    return Cloud(case, json_body, points.astype("<f4").tobytes())


def padding_pool() -> list[tuple[str, Path]]:
    """Meshes for padding: pybullet_data's procedurally generated objects (``random_urdfs``)
    that the object manifest does not use, seen or unseen; about 990 distinct shapes."""
    used = {spec.path.resolve() for spec in load_manifest()}
    pool = []
    for folder in sorted((data_root() / "random_urdfs").iterdir()):
        mesh = folder / f"{folder.name}.obj"
        if mesh.is_file() and mesh.resolve() not in used:
            pool.append((f"pad-random-{folder.name}", mesh))
    return pool


def padding_references(
    engine: Engine, count: int, model_hash: str, cache_dir: Path | None
) -> tuple[list[Reference], float | None]:
    """``count`` padding references, registered as the service would (2,048 surface points,
    seed 0), cached per model. Past the pool's size, its meshes again, stretched per axis.

    Returns them and the seconds the computation took (None when they came from the cache).
    """
    if count <= 0:
        return [], None
    cache = None
    if cache_dir is not None:
        cache = cache_dir / f"padding-random-{model_hash[:16]}.npz"
        if cache.exists():
            references, meta = load_gallery(cache)
            if meta.get("model_sha256") == model_hash and len(references) >= count:
                return references[:count], None
    pool = padding_pool()
    rng = np.random.default_rng(1000)
    references: list[Reference] = []
    began = time.perf_counter()
    for lap in itertools.count():
        before = len(references)
        for name, path in pool:
            try:
                points = sample_surface(load_mesh(path), REFERENCE_POINTS, REFERENCE_SEED)
            except MeshError:  # a few generated meshes are unusable (non-finite vertices)
                continue
            if lap:  # another lap of the pool: a distinct shape, not a copy
                points = points * rng.uniform(0.7, 1.3, 3).astype(np.float32)
                name = f"{name}-{lap}"
            references.append(engine.make_reference(name, points))
            if len(references) % 100 == 0:
                print(f"  padding: {len(references)}/{count} references computed", flush=True)
            if len(references) == count:
                break
        if len(references) == count:
            break
        if len(references) == before:
            raise RuntimeError("no usable padding mesh in pybullet_data/random_urdfs")
    seconds = time.perf_counter() - began
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        partial = cache.with_name(cache.stem + ".partial.npz")
        save_gallery(partial, references, {"model_sha256": model_hash})
        partial.replace(cache)
    return references, seconds


def serve(data_dir: Path, args: argparse.Namespace) -> ServiceProcess:
    """The service on the benchmark's model, open (API keys would only add a header check per
    request); other ``DPC_*`` variables of this environment (engine settings) reach it."""
    return ServiceProcess(
        data_dir / "service.log",
        args.ready_timeout,
        inherit=True,
        gallery__data_dir=str(data_dir),
        model__path=str(args.model),
        model__gallery=str(args.gallery),
        server__log_level="warning",
        auth__keys="{}",
    )


# --- measurements ----------------------------------------------------------------------------


def sequential(
    client: httpx.Client, clouds: list[Cloud], requests: int, warmup: int, kind: str
) -> tuple[list[float], list[dict], float]:
    """Latencies (ms), the answers' timings_ms and the share of right labels."""
    latencies, timings, right = [], [], 0
    for index in range(warmup + requests):
        cloud = clouds[index % len(clouds)]
        body, headers = (
            (cloud.json_body, JSON_TYPE) if kind == "json" else (cloud.raw_body, RAW_TYPE)
        )
        began = time.perf_counter()
        answer = client.post("/align", content=body, headers=headers)
        elapsed = (time.perf_counter() - began) * 1e3
        if answer.status_code != 200:
            raise RuntimeError(f"/align answered {answer.status_code}: {answer.text[:300]}")
        if index >= warmup:
            result = answer.json()
            latencies.append(elapsed)
            timings.append(result["timings_ms"])
            right += result["label"] == cloud.case.object_name
    return latencies, timings, right / max(requests, 1)


def concurrent(url: str, clouds: list[Cloud], clients: int, total: int, kind: str) -> dict:
    """``total`` requests shared by ``clients`` threads, each with its own keep-alive client."""
    counter = itertools.count()
    latencies: list[float] = []
    failures: list[str] = []
    lock = threading.Lock()
    start = threading.Barrier(clients + 1)

    def worker() -> None:
        try:
            with httpx.Client(base_url=url, timeout=300.0) as client:
                client.get("/v2/health/live")  # open the connection before the clock starts
                start.wait(timeout=60)
                while (index := next(counter)) < total:
                    cloud = clouds[index % len(clouds)]
                    body, headers = (
                        (cloud.json_body, JSON_TYPE)
                        if kind == "json"
                        else (cloud.raw_body, RAW_TYPE)
                    )
                    began = time.perf_counter()
                    answer = client.post("/align", content=body, headers=headers)
                    elapsed = (time.perf_counter() - began) * 1e3
                    with lock:
                        if answer.status_code == 200:
                            latencies.append(elapsed)
                        else:
                            failures.append(f"{answer.status_code}: {answer.text[:200]}")
        except Exception as error:  # a dead client must not go unnoticed or hang the others
            with lock:
                failures.append(repr(error))
            start.abort()

    threads = [threading.Thread(target=worker, daemon=True) for _ in range(clients)]
    for thread in threads:
        thread.start()
    try:
        start.wait(timeout=60)
    except threading.BrokenBarrierError:
        pass  # reported through failures below
    began = time.perf_counter()
    for thread in threads:
        thread.join()
    wall = time.perf_counter() - began
    if failures:
        raise RuntimeError(f"{len(failures)} requests failed, e.g. {failures[0]}")
    return {
        "clients": clients,
        "requests": total,
        "seconds": wall,
        "requests_per_s": total / wall,
        **latency_stats(latencies),
    }


def engine_only(
    engine: Engine, clouds: list[Cloud], requests: int, warmup: int
) -> tuple[list[float], list[dict]]:
    latencies, timings = [], []
    for index in range(warmup + requests):
        points = np.frombuffer(clouds[index % len(clouds)].raw_body, dtype="<f4").reshape(-1, 3)
        began = time.perf_counter()
        result = engine.align(points)
        elapsed = (time.perf_counter() - began) * 1e3
        if index >= warmup:
            latencies.append(elapsed)
            timings.append(result.timings_ms)
    return latencies, timings


def refit_time(
    references: list[Reference], count: int, repeats: int, engine_settings: EngineSettings
) -> dict:
    """``LinearClassifier.fit`` on ``count`` references' view features (cycled if fewer given):
    from scratch, as a start-up does, and after one change, as a registration or removal does
    (the engine keeps the views' Gram and adds one reference's share to it).

    The features (``classifier_input`` of each reference's view grids) are computed once per
    reference, as the engine caches them.
    """
    blur = engine_settings.grid_blur
    views = engine_settings.view_grids
    ridge = engine_settings.classifier_ridge
    cached = [classifier_input(r.view_grids[:views], blur) for r in references[:count]]
    features = [cached[i % len(cached)] for i in range(count)]
    labels = [f"ref-{i}" for i in range(count)]
    kept = view_gram(features[:-1])  # what the engine holds before the last registration
    scratch, change = [], []
    for _ in range(repeats):
        began = time.perf_counter()
        LinearClassifier.fit(labels, features, ridge, blur)
        scratch.append((time.perf_counter() - began) * 1e3)
        began = time.perf_counter()
        LinearClassifier.fit(labels, features, ridge, blur, kept + view_gram(features[-1:]))
        change.append((time.perf_counter() - began) * 1e3)
    return {
        "references": count,
        "views_per_reference": int(features[0].shape[0]),
        "distinct_references": len(cached),
        "repeats": repeats,
        "median_ms": float(np.median(change)),
        "min_ms": float(np.min(change)),
        "from_scratch_median_ms": float(np.median(scratch)),
    }


def measure_size(
    size: int,
    args: argparse.Namespace,
    engine: Engine,
    gallery_refs: list[Reference],
    padding: list[Reference],
    model_hash: str,
    clouds: list[Cloud],
    workdir: Path,
) -> dict:
    shipped = gallery_refs[:size]
    references = shipped + padding[: size - len(shipped)]
    data_dir = workdir / f"data-{size}"
    seed_store(data_dir, references, model_hash)
    print(f"[{size} references] starting the service ...", flush=True)
    result: dict = {"references": size, "padding_references": len(references) - len(shipped)}
    with serve(data_dir, args) as service:
        result["service_ready_s"] = service.ready_s
        with httpx.Client(base_url=service.url, timeout=300.0) as client:
            health = client.get("/health").json()
            if health["references"] != size:
                raise RuntimeError(f"the service holds {health['references']}, not {size}")
            result["providers"] = health["providers"]
            # the HTTP stack alone (middleware, one loopback round trip): a GET with no work
            probes = []
            for _ in range(args.requests):
                began = time.perf_counter()
                client.get("/v2/health/live")
                probes.append((time.perf_counter() - began) * 1e3)
            result["http_live"] = latency_stats(probes)
            for kind in ("json", "raw"):
                print(f"[{size} references] {args.requests} sequential {kind} requests", flush=True)
                latencies, timings, right = sequential(
                    client, clouds, args.requests, args.warmup, kind
                )
                result[f"http_{kind}"] = {
                    **latency_stats(latencies),
                    "label_right": right,
                    "steps_ms": step_medians(timings),
                }
            result["concurrency"] = []
            for clients in args.clients:
                print(f"[{size} references] {clients} concurrent client(s)", flush=True)
                result["concurrency"].append(
                    concurrent(service.url, clouds, clients, args.concurrent_requests, "json")
                )
            # one removal and one registration: each refits the classifier on the gallery
            victim = references[-1]
            began = time.perf_counter()
            removed = client.delete(f"/references/{victim.name}")
            remove_ms = (time.perf_counter() - began) * 1e3
            began = time.perf_counter()
            added = client.post(
                "/references",
                params={"self_check": "false"},
                content=orjson.dumps({"name": victim.name, "points": victim.points.tolist()}),
                headers=JSON_TYPE,
            )
            register_ms = (time.perf_counter() - began) * 1e3
            if removed.status_code != 204 or added.status_code != 201:
                raise RuntimeError(f"remove/register failed: {removed.text} {added.text}")
            result["remove_one_ms"], result["register_one_ms"] = remove_ms, register_ms
    print(f"[{size} references] engine in-process", flush=True)
    began = time.perf_counter()
    engine.load(references)
    result["engine_load_s"] = time.perf_counter() - began
    latencies, timings = engine_only(engine, clouds, args.requests, args.warmup)
    result["engine"] = {**latency_stats(latencies), "steps_ms": step_medians(timings)}
    for kind in ("json", "raw"):
        http = result[f"http_{kind}"]
        http["overhead_vs_engine_ms"] = http["median_ms"] - result["engine"]["median_ms"]
        http["overhead_vs_timings_ms"] = http["median_ms"] - http["steps_ms"]["total"]
    engine.load([])
    shutil.rmtree(data_dir, ignore_errors=True)
    result["load_average"] = os.getloadavg()
    return result


# --- accuracy --------------------------------------------------------------------------------


def accuracy(
    args: argparse.Namespace,
    gallery_refs: list[Reference],
    model_hash: str,
    workdir: Path,
) -> dict:
    """Success (right label, ADD-S < 0.10) per family on seen and on unseen objects."""
    seen_specs = load_manifest(split="seen")
    unseen_specs = load_manifest(split="unseen")
    in_gallery = {r.name for r in gallery_refs}
    seen_meshes = load_object_meshes([s for s in seen_specs if s.name in in_gallery])
    unseen_meshes = load_object_meshes([s for s in unseen_specs if s.name not in in_gallery])
    data_dir = workdir / "data-accuracy"
    seed_store(data_dir, gallery_refs, model_hash)
    models = {
        name: sample_surface(mesh, REFERENCE_POINTS, REFERENCE_SEED)
        for name, mesh in {**seen_meshes, **unseen_meshes}.items()
    }
    print(f"[accuracy] starting the service with {len(gallery_refs)} references", flush=True)
    result: dict = {"poses_per_object": args.accuracy_poses, "seed": args.seed}
    with (
        serve(data_dir, args) as service,
        httpx.Client(base_url=service.url, timeout=300.0) as client,
    ):
        register_ms = []
        for name in unseen_meshes:
            body = orjson.dumps({"name": name, "points": models[name].tolist()})
            began = time.perf_counter()
            answer = client.post(
                "/references", params={"self_check": "false"}, content=body, headers=JSON_TYPE
            )
            register_ms.append((time.perf_counter() - began) * 1e3)
            if answer.status_code != 201:
                raise RuntimeError(f"registering {name} failed: {answer.text}")
        result["gallery_references"] = client.get("/health").json()["references"]
        result["unseen_registration_ms"] = latency_stats(register_ms) if register_ms else None
        for split, meshes in (("seen", seen_meshes), ("unseen", unseen_meshes)):
            scales = {name: float(_radius(models[name])) for name in meshes}
            diameters = {name: diameter(models[name]) for name in meshes}
            for family in ACCURACY_FAMILIES:
                cases = make_cases(
                    family,
                    meshes,
                    scales,
                    n_points=REFERENCE_POINTS,
                    seed=args.seed,
                    poses_per_object=args.accuracy_poses,
                )
                print(f"[accuracy] {split} {family}: {len(cases)} cases", flush=True)

                with ThreadPoolExecutor(args.accuracy_clients) as pool:
                    outcomes = list(
                        pool.map(partial(judge, client, models=models, diameters=diameters), cases)
                    )
                labels = np.array([o[0] for o in outcomes])
                successes = np.array([o[1] for o in outcomes])
                errors = np.array([o[2] for o in outcomes])
                result[f"{split}/{family}"] = {
                    "cases": len(cases),
                    "objects": len(meshes),
                    "recognition": float(labels.mean()),
                    "success": float(successes.mean()),
                    "median_add_s": float(np.median(errors)),
                }
                if family == "sparse":  # the paper's Fig. 5: success against the share kept
                    shares = np.array([case.params["keep_share"] for case in cases])
                    result[f"{split}/{family}"]["success_by_keep_share"] = {
                        f"{share:g}": float(successes[shares == share].mean())
                        for share in sorted(set(shares.tolist()))
                    }
    shutil.rmtree(data_dir, ignore_errors=True)
    return result


def judge(
    client: httpx.Client, case: Case, models: dict, diameters: dict
) -> tuple[bool, bool, float]:
    """Align one case over HTTP: whether the label is right, whether it succeeds, its ADD-S."""
    answer = client.post(
        "/align", content=np.asarray(case.points, "<f4").tobytes(), headers=RAW_TYPE
    )
    if answer.status_code != 200:
        raise RuntimeError(f"/align answered {answer.status_code}: {answer.text[:300]}")
    body = answer.json()
    label_ok = body["label"] == case.object_name
    error = add_s(
        models[case.object_name],
        np.array(body["rotation"]),
        np.array(body["translation"]),
        case.rotation,
        case.translation,
        diameters[case.object_name],
    )
    return label_ok, label_ok and error < SUCCESS_ADD_S, error


def _radius(points: np.ndarray) -> float:
    points = np.asarray(points, dtype=np.float64)
    return float(np.linalg.norm(points - points.mean(axis=0), axis=1).max())


# --- report ----------------------------------------------------------------------------------


def print_report(report: dict) -> None:
    sizes = report["sizes"]
    columns = [str(s["references"]) for s in sizes]
    width = 12
    print()
    config = report["config"]
    print(
        f"POST /align over HTTP: model {config['model']} (sha256 {config['model_sha256'][:12]}), "
        f"{config['cpus']} CPUs, {config['platform']}"
    )
    loads = (config["load_average_at_start"][0], config["load_average_at_end"][0])
    print(f"load average (1 min) at start {loads[0]:.2f}, at end {loads[1]:.2f}")
    print(
        f"clouds: {config['clouds']} so3 clouds of {config['cloud_objects']} seen objects, "
        f"{REFERENCE_POINTS} points; {config['requests']} sequential requests per body "
        f"(after {config['warmup']} warm-up), {config['concurrent_requests']} per concurrency "
        "level (JSON bodies)"
    )
    print()

    def row(title: str, values: list[str], target: str = "", width: int = width) -> None:
        print(f"{title:<36}" + "".join(f"{v:>{width}}" for v in values) + f"   {target}")

    def figure(value: float | None, digits: int = 1) -> str:
        return "-" if value is None else f"{value:.{digits}f}"

    row("references", columns, "target")
    for kind in ("json", "raw"):
        medians = [s[f"http_{kind}"]["median_ms"] for s in sizes]
        base = medians[0]
        row(
            f"HTTP {kind} median ms",
            [figure(v) for v in medians],
            f"<= {TARGET_MEDIAN_MS:g} ms at {columns[0]}: {mark(base <= TARGET_MEDIAN_MS)}",
        )
        row(f"HTTP {kind} p95 ms", [figure(s[f"http_{kind}"]["p95_ms"]) for s in sizes])
    row("GET /v2/health/live median ms", [figure(s["http_live"]["median_ms"], 2) for s in sizes])
    row("engine in-process median ms", [figure(s["engine"]["median_ms"]) for s in sizes])
    row("engine in-process p95 ms", [figure(s["engine"]["p95_ms"]) for s in sizes])
    for kind in ("json", "raw"):
        row(
            f"HTTP {kind} - engine (median) ms",
            [figure(s[f"http_{kind}"]["overhead_vs_engine_ms"]) for s in sizes],
        )
        row(
            f"HTTP {kind} - timings total ms",
            [figure(s[f"http_{kind}"]["overhead_vs_timings_ms"]) for s in sizes],
        )
    for index, level in enumerate(sizes[0]["concurrency"]):
        row(
            f"requests/s, {level['clients']} client(s)",
            [figure(s["concurrency"][index]["requests_per_s"]) for s in sizes],
        )
        row(
            f"  median ms, {level['clients']} client(s)",
            [figure(s["concurrency"][index]["median_ms"]) for s in sizes],
        )
    row(
        "right label (sequential JSON)",
        [figure(100 * s["http_json"]["label_right"]) for s in sizes],
    )
    row("load average (1 min) after", [figure(s["load_average"][0], 2) for s in sizes])
    row("service start to ready s", [figure(s["service_ready_s"], 2) for s in sizes])
    row("engine load (trees + refit) s", [figure(s["engine_load_s"], 2) for s in sizes])
    row("DELETE one reference ms", [figure(s["remove_one_ms"]) for s in sizes])
    row("POST /references one (no check) ms", [figure(s["register_one_ms"]) for s in sizes])
    print()
    print("median ms per step (timings_ms of the sequential JSON answers | engine in-process)")
    row("references", columns, width=width + 6)
    steps = list(sizes[0]["http_json"]["steps_ms"])
    for step in steps:
        row(
            f"  {step}",
            [
                f"{s['http_json']['steps_ms'].get(step, 0):.1f} | "
                f"{s['engine']['steps_ms'].get(step, 0):.1f}"
                for s in sizes
            ],
            width=width + 6,
        )
    growth = report.get("growth")
    if growth:
        print()
        print(f"growth {growth['from']} -> {growth['to']} references (median ms):")
        for key, value in growth["ms"].items():
            print(
                f"  {key:<10} {value:+.2f} ms   target <= {TARGET_GROWTH_MS:g} ms: "
                f"{mark(value <= TARGET_GROWTH_MS)}"
            )
    refit = report["refit"]
    print()
    print(
        f"classifier refit (LinearClassifier.fit), {refit['references']} references x "
        f"{refit['views_per_reference']} views: after one change median "
        f"{refit['median_ms']:.1f} ms (min {refit['min_ms']:.1f}), from scratch "
        f"{refit['from_scratch_median_ms']:.1f} ms ({refit['repeats']} repeats)"
    )
    if padding := report.get("padding_compute_s"):
        print(f"padding references computed in {padding:.1f} s (cached for the next run)")
    accuracy_report = report.get("accuracy")
    if accuracy_report:
        print()
        print(
            f"accuracy (refinement on, gallery of {accuracy_report['gallery_references']} "
            f"references, {accuracy_report['poses_per_object']} poses per object and family; "
            f"success = right label and ADD-S < {SUCCESS_ADD_S})"
        )
        print(f"  {'':<22}{'cases':>8}{'recognition':>13}{'success':>10}{'median ADD-S':>14}")
        for key, value in accuracy_report.items():
            if "/" in key:
                print(
                    f"  {key:<22}{value['cases']:>8}{100 * value['recognition']:>12.1f}%"
                    f"{100 * value['success']:>9.1f}%{value['median_add_s']:>14.4f}"
                )
                if "success_by_keep_share" in value:
                    shares = ", ".join(
                        f"{float(share):.0%}: {100 * success:.0f}%"
                        for share, success in value["success_by_keep_share"].items()
                    )
                    print(f"  {'':<22}success by share kept: {shares}")
        registration = accuracy_report.get("unseen_registration_ms")
        if registration:
            print(
                f"  unseen objects registered via POST /references: median "
                f"{registration['median_ms']:.0f} ms each ({registration['count']})"
            )


# --- main ------------------------------------------------------------------------------------


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    settings = Settings()
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.align_http",
        description="POST /align latency and throughput over HTTP, beside the engine's time.",
    )
    parser.add_argument("--model", type=Path, default=settings.model.path, help="the ONNX model")
    parser.add_argument(
        "--gallery", type=Path, default=settings.model.gallery, help="the shipped gallery (.npz)"
    )
    parser.add_argument(
        "--references",
        type=int,
        nargs="+",
        default=[BASE_REFERENCES],
        help=f"gallery sizes to measure (a size over {BASE_REFERENCES} also measures "
        f"{BASE_REFERENCES}, the baseline of the growth figure); e.g. --references 1000",
    )
    parser.add_argument("--requests", type=int, default=200, help="sequential requests per body")
    parser.add_argument("--warmup", type=int, default=10, help="warm-up requests, not counted")
    parser.add_argument("--clients", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument(
        "--concurrent-requests", type=int, default=120, help="requests per concurrency level"
    )
    parser.add_argument("--clouds-per-object", type=int, default=2, help="so3 clouds per object")
    parser.add_argument("--refit-references", type=int, default=100)
    parser.add_argument("--refit-repeats", type=int, default=5)
    parser.add_argument("--accuracy", action="store_true", help="also measure success shares")
    parser.add_argument(
        "--accuracy-poses", type=int, default=4, help="poses per object and family (accuracy)"
    )
    parser.add_argument("--accuracy-clients", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--ready-timeout", type=float, default=900.0, help="seconds")
    parser.add_argument(
        "--padding-cache",
        type=Path,
        default=Path(tempfile.gettempdir()) / "dpc_bench_cache",
        help="where computed padding references are kept between runs ('' for nowhere)",
    )
    parser.add_argument("--json", type=Path, help="write the figures here")
    args = parser.parse_args(argv)
    sizes = sorted(set(args.references))
    if any(s < 1 for s in sizes) or args.requests < 1 or args.concurrent_requests < 1:
        parser.error("sizes and request counts must be positive")
    if max(sizes) > BASE_REFERENCES and BASE_REFERENCES not in sizes:
        sizes.insert(0, BASE_REFERENCES)
    args.references = sizes
    if str(args.padding_cache) in ("", "."):
        args.padding_cache = None
    if not args.model.is_file():
        parser.error(f"no ONNX model at {args.model}: pass --model or set DPC_MODEL__PATH")
    if not args.gallery.is_file():
        parser.error(f"no gallery at {args.gallery}: pass --gallery or set DPC_MODEL__GALLERY")
    return args


def run(args: argparse.Namespace, progress: Callable[[str], None] = print) -> dict:
    settings = Settings()
    mapper = Mapper(
        args.model,
        settings.model.intra_op_threads,
        settings.model.inter_op_threads,
        settings.model.use_cuda,
    )
    engine = Engine(mapper, settings.engine)
    model_hash = mapper.model_hash
    gallery_refs, meta = load_gallery(args.gallery)
    gallery_hash = meta.get("model_sha256") or meta.get("model_hash")
    if gallery_hash != model_hash:
        progress("the gallery was computed with another model: recomputing its references")
        gallery_refs = [engine.make_reference(r.name, r.points) for r in gallery_refs]

    seen = {s.name: s for s in load_manifest(split="seen")}
    cloud_names = [r.name for r in gallery_refs if r.name in seen][: min(args.references)]
    meshes = load_object_meshes([seen[name] for name in cloud_names])
    scales = {r.name: float(r.scale) for r in gallery_refs}
    cases = make_cases(
        "so3",
        meshes,
        scales,
        n_points=REFERENCE_POINTS,
        seed=args.seed,
        poses_per_object=args.clouds_per_object,
    )
    # interleave the objects, so consecutive requests ask for different ones
    order = sorted(range(len(cases)), key=lambda i: (i % args.clouds_per_object, i))
    clouds = [encode(cases[i]) for i in order]

    needed = max(args.references) - len(gallery_refs)
    padding, padding_s = padding_references(engine, needed, model_hash, args.padding_cache)

    report: dict = {
        "config": {
            "model": str(args.model),
            "model_sha256": model_hash,
            "gallery": str(args.gallery),
            "providers": mapper.providers,
            "engine_settings": settings.engine.model_dump(mode="json"),
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "clouds": len(clouds),
            "cloud_objects": len(cloud_names),
            "requests": args.requests,
            "warmup": args.warmup,
            "concurrent_requests": args.concurrent_requests,
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "load_average_at_start": os.getloadavg(),  # other work on the machine skews it all
        },
        "targets": {"median_ms": TARGET_MEDIAN_MS, "growth_ms": TARGET_GROWTH_MS},
        "padding_compute_s": padding_s,
        "sizes": [],
    }
    with tempfile.TemporaryDirectory(prefix="dpc-bench-") as tmp:
        workdir = Path(tmp)
        for size in args.references:
            report["sizes"].append(
                measure_size(size, args, engine, gallery_refs, padding, model_hash, clouds, workdir)
            )
        if len(report["sizes"]) > 1:
            first, last = report["sizes"][0], report["sizes"][-1]
            report["growth"] = {
                "from": first["references"],
                "to": last["references"],
                "ms": {
                    "http json": last["http_json"]["median_ms"] - first["http_json"]["median_ms"],
                    "http raw": last["http_raw"]["median_ms"] - first["http_raw"]["median_ms"],
                    "engine": last["engine"]["median_ms"] - first["engine"]["median_ms"],
                },
            }
        report["refit"] = refit_time(
            gallery_refs + padding, args.refit_references, args.refit_repeats, settings.engine
        )
        if args.accuracy:
            report["accuracy"] = accuracy(args, gallery_refs, model_hash, workdir)
    report["config"]["finished_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    report["config"]["load_average_at_end"] = os.getloadavg()
    return report


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    report = run(args)
    print_report(report)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")
        print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
