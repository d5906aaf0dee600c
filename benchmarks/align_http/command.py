"""``POST /align`` latency and throughput over real HTTP, beside the engine's own time.

``python -m benchmarks.align_http [--references 40 1000] [--json out.json] [--accuracy]``

The default run needs the runtime packages alone (``pip install -e .``: numpy, scipy,
onnxruntime, httpx): no pybullet, open3d or torch. ``--accuracy`` also needs pybullet's meshes
(the ``train`` extra).

**Gallery.** For each size the service runs as a real process (``python -m service``, started
by ``evaluation.served.ServiceProcess``) on a free loopback port with a data directory of its
own, seeded before it starts. 40 references are the first 40 of the shipped gallery
(``models/gallery.npz``); a larger size adds the other shipped ones, then padding references made
from the shipped ones: padding ``i`` is shipped reference ``i mod 45`` turned by a random rotation
and stretched along x, y and z by random factors in 0.7-1.3, the largest at least 1.4 times the
smallest (seeded by ``i``: a distinct shape each, neither a copy in another pose nor the part
resized), computed with the engine's own ``Engine.make_reference`` as a
registration computes it (1-3 s each on a busy 2-core machine). They are cached on disk
(``--padding-cache``, in chunks of 50, so an interrupted run keeps what it computed) under a key
of the model's hash, the engine's settings, the recipe and the shipped points; the run prints how
long the computation took when it had to compute them.

**Clouds.** ``--clouds-per-object`` clouds of each of the first 40 shipped references (of the
first N when a size N under 40 is measured), 2,048 points each, never the registered points:
2,048 of the reference's points drawn at random (with replacement), each moved within the
surface's tangent plane (the reference's stored normals) by Gaussian jitter of one point spacing
(the median distance to the nearest other point); then moved by a random rotation (uniform over
SO(3)) and a translation in a random direction of up to twice the reference's scale, and
shuffled. Seeded by ``--seed``, the reference's index and the cloud's index. Consecutive requests
ask for different parts. Such a cloud stands for an independent sample of the mesh's surface
(the evaluation's ``so3`` family, which needs pybullet's meshes): on 14-20 shipped parts, against
fresh samples of their meshes, the engine's fit and coverage agreed within 0.01 and its median
time within about 10 %. With half a spacing the points drawn twice stay clumped: coverage fell to
0.96 and the mean time rose by a third (by 2.5-3 times before the surroundings' change of
``ce892a6``).

**Measured**, for each size (and, where onnxruntime offers CUDA, for the CUDA execution provider
beside the CPU one: ``--providers``):

- sequential requests, one keep-alive client, raw float32 and JSON bodies (bodies encoded before
  the clock starts): median and p95 latency, the median of each step of the answers'
  ``timings_ms``, and the HTTP overhead (each request's latency minus its answer's total);
  whether the answers are right (label, ADD-S under 0.10 and under 0.02 of the diameter);
- requests per second with 1, 2 and 4 concurrent clients (threads, one client each), both bodies;
- ``Engine.align`` in this process on the same clouds, so the cost of the service is visible;
- ``DELETE /references/{name}`` and ``POST /references`` of that reference again, without the
  registration check (``self_check=false``) and with it (the default: independent renders of the
  new part aligned against the whole gallery);
- the growth from 40 references to the largest size measured: the difference of the medians
  above, and paired: both galleries' services up at once, each cloud sent to one then the other
  (and aligned likewise by an engine of each gallery in this process), the median of the
  per-cloud differences, which a machine whose load changes from minute to minute skews less;
- the classifier's refit for 100 references (after one change, and from scratch).

Every count is fixed and the run stops by itself; nothing leaves loopback. The figures are
printed (targets of issue 12 marked PASS or FAIL, on whatever machine it ran) and, with
``--json``, written. The model comes from ``--model`` / ``--gallery`` or ``DPC_MODEL__PATH`` /
``DPC_MODEL__GALLERY``; other ``DPC_*`` variables (engine settings) reach the served process and
the in-process engine alike.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import importlib.util
import itertools
import json
import multiprocessing
import os
import platform
import shutil
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import httpx
import numpy as np
import onnxruntime as ort
import orjson
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from evaluation.metrics import PRECISE_ADD_S, SUCCESS_ADD_S, add_s, diameter
from evaluation.served import ServiceProcess, seed_store
from service.api.startup import load_calibration
from service.engine.classifier import LinearClassifier, classifier_input, view_gram
from service.engine.engine import Engine
from service.engine.mapping import Mapper
from service.engine.reference import Reference
from service.gallery.gallery_file import load_gallery, save_gallery
from service.settings import EngineSettings, Settings

REPO = Path(__file__).resolve().parent.parent
BASE_REFERENCES = 40  # the gallery the latency targets are stated for
# issue 12's targets (benchmark figures, on a quiet 2-core machine)
TARGET_MS = {"raw": 8.0, "json": 10.0}
TARGET_GROWTH_MS = 1.0
CLOUD_POINTS = 2048
JITTER_SPACINGS = 1.0  # tangential jitter of a resampled point, in point spacings
PADDING_RECIPE = 2  # bump when padding_points changes: the cache key follows it
PADDING_SEED = 1000
PADDING_STRETCH = (0.7, 1.3)
# the largest stretch over the smallest, at least: a nearly even stretch only resizes the part
# (a size variant the engine may take for its base: 16 of 80 clouds were, with no such bound)
PADDING_ANISOTROPY = 1.4
PADDING_CHUNK = 50  # references per cache file
STEPS = (
    "surroundings",
    "normalize",
    "map",
    "classify",
    "hypothesise",
    "verify",
    "refine",
    "decide",
    "measure",
    "total",
)
UNATTRIBUTED = "unattributed"  # an answer's total less the sum of its steps
KINDS = ("raw", "json")
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
    """The median of each step over the answers (a step an answer did not take counts 0), and
    of ``unattributed``: each answer's total less the sum of its steps (time after its last
    step, e.g. the confidence)."""
    timings = [
        {**t, UNATTRIBUTED: t["total"] - sum(v for k, v in t.items() if k != "total")}
        for t in timings
    ]
    keys = [k for k in STEPS[:-1] if any(k in t for t in timings)]
    keys += sorted({k for t in timings for k in t} - {*keys, "total"}) + ["total"]
    return {k: float(np.median([t.get(k, 0.0) for t in timings])) for k in keys}


def mark(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


# --- clouds ----------------------------------------------------------------------------------


@dataclass
class Cloud:
    """One request: ``points`` = R @ (a resample of reference ``label``) + t, shuffled."""

    label: str
    points: np.ndarray  # (M, 3) float32
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    json_body: bytes
    raw_body: bytes

    def body(self, kind: str) -> tuple[bytes, dict[str, str]]:
        return (self.raw_body, RAW_TYPE) if kind == "raw" else (self.json_body, JSON_TYPE)


def point_spacing(points: np.ndarray) -> float:
    """The median distance from a point to its nearest other point."""
    distances, _ = cKDTree(points).query(points, k=2)
    return float(np.median(distances[:, 1]))


def resample(
    points: np.ndarray, normals: np.ndarray | None, count: int, rng: np.random.Generator
) -> np.ndarray:
    """``count`` points of the same surface, none of them one of ``points``: points drawn at
    random and each moved by Gaussian jitter of ``JITTER_SPACINGS`` point spacings, within its
    tangent plane where ``normals`` are known (everywhere otherwise, by a third as much)."""
    points = np.asarray(points, dtype=np.float64)
    spacing = point_spacing(points)
    chosen = rng.integers(0, len(points), count)
    jitter = rng.normal(scale=JITTER_SPACINGS * spacing, size=(count, 3))
    if normals is None:
        jitter /= 3
    else:
        normal = np.asarray(normals, dtype=np.float64)[chosen]
        jitter -= np.sum(jitter * normal, axis=1, keepdims=True) * normal
    return points[chosen] + jitter


def make_clouds(references: list[Reference], clouds_per_object: int, seed: int) -> list[Cloud]:
    """The benchmark's clouds (module docstring): round after round of one cloud of each
    reference, so consecutive requests ask for different parts."""
    clouds = []
    for k in range(clouds_per_object):
        for index, reference in enumerate(references):
            rng = np.random.default_rng([seed, index, k])
            sample = resample(reference.points, reference.normals, CLOUD_POINTS, rng)
            rotation = Rotation.random(random_state=rng).as_matrix()
            direction = rng.normal(size=3)
            translation = (
                direction / np.linalg.norm(direction) * rng.uniform(0, 2) * reference.scale
            )
            points = (sample @ rotation.T + translation)[rng.permutation(CLOUD_POINTS)]
            clouds.append(encode(reference.name, points, rotation, translation))
    return clouds


def encode(label: str, points: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> Cloud:
    points = np.asarray(points, dtype=np.float32)
    # six decimals (a micrometre in metres), as a client that writes its own JSON would send
    json_body = orjson.dumps({"points": np.round(points.astype(np.float64), 6).tolist()})
    return Cloud(label, points, rotation, translation, json_body, points.astype("<f4").tobytes())


# --- padding references ----------------------------------------------------------------------


def padding_points(shipped: list[Reference], index: int) -> tuple[str, np.ndarray]:
    """Padding reference ``index``: shipped reference ``index mod len(shipped)``, turned by a
    random rotation, then stretched along x, y and z by random factors, one at least
    ``PADDING_ANISOTROPY`` times another (a distinct shape, not the part resized)."""
    base = shipped[index % len(shipped)]
    rng = np.random.default_rng([PADDING_SEED, index])
    turn = Rotation.random(random_state=rng).as_matrix()
    stretch = rng.uniform(*PADDING_STRETCH, 3)
    while stretch.max() < PADDING_ANISOTROPY * stretch.min():
        stretch = rng.uniform(*PADDING_STRETCH, 3)
    points = (np.asarray(base.points, dtype=np.float64) @ turn.T) * stretch
    return f"pad-{index:04d}-{base.name}", points.astype(np.float32)


def padding_key(shipped: list[Reference], model_hash: str, engine: EngineSettings) -> str:
    """What the padding references depend on: the recipe, the model, the engine's settings,
    the shipped points and the fields a reference has."""
    described = {
        "recipe": PADDING_RECIPE,
        "model_sha256": model_hash,
        "engine": engine.model_dump(mode="json"),
        "shipped": [r.points_sha256 for r in shipped],
        "fields": [f.name for f in dataclasses.fields(Reference)],
    }
    return hashlib.sha256(json.dumps(described, sort_keys=True).encode()).hexdigest()[:16]


def engine_code_hash() -> str:
    """The engine's source: padding computed by other code is used, with a warning."""
    digest = hashlib.sha256()
    for path in sorted((REPO / "service" / "engine").glob("*.py")):
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


_worker_engine: Engine | None = None


def _start_worker(model: str, engine_settings: dict) -> None:
    global _worker_engine
    mapper = Mapper(Path(model), 1, 1, False)
    _worker_engine = Engine(mapper, EngineSettings(**engine_settings))


def _make_reference(named: tuple[str, np.ndarray]) -> Reference:
    return _worker_engine.make_reference(*named)


def padding_references(
    engine: Engine,
    shipped: list[Reference],
    count: int,
    cache_dir: Path | None,
    workers: int = 1,
    progress: Callable[[str], None] = print,
) -> tuple[list[Reference], int, float | None]:
    """``count`` padding references (``padding_points``), computed with ``engine`` (or as many
    worker processes with the same model and settings) and cached in ``cache_dir``.

    Returns them, how many were computed (not in the cache) and the seconds that took.
    """
    if count <= 0:
        return [], 0, None
    key = padding_key(shipped, engine.mapper.model_hash, engine.settings)
    code = engine_code_hash()
    chunks = range(0, count, PADDING_CHUNK)
    held: dict[int, list[Reference]] = {}
    for start in chunks:
        held[start] = []
        path = None if cache_dir is None else cache_dir / f"padding-{key}-{start:05d}.npz"
        if path is not None and path.exists():
            references, meta = load_gallery(path)
            if meta.get("key") == key:
                held[start] = references
                if meta.get("engine_code") != code:
                    progress(f"  padding {path.name}: computed by other engine code, used as is")
    missing = [
        start + i
        for start in chunks
        for i in range(len(held[start]), min(PADDING_CHUNK, count - start))
    ]
    if not missing:
        return [r for start in chunks for r in held[start]][:count], 0, None
    progress(f"computing {len(missing)} padding references ({workers} process(es)) ...")
    began = time.perf_counter()
    done = 0
    for index, reference in _compute(engine, shipped, missing, workers):
        start = index - index % PADDING_CHUNK
        held[start].append(reference)
        done += 1
        full = len(held[start]) == min(PADDING_CHUNK, count - start)
        if full and cache_dir is not None:
            cache_dir.mkdir(parents=True, exist_ok=True)
            path = cache_dir / f"padding-{key}-{start:05d}.npz"
            partial_path = path.with_name(path.stem + ".partial.npz")
            save_gallery(partial_path, held[start], {"key": key, "engine_code": code})
            partial_path.replace(path)
        if done % 25 == 0 or done == len(missing):
            elapsed = time.perf_counter() - began
            progress(f"  padding: {done}/{len(missing)} computed in {elapsed:.0f} s")
    seconds = time.perf_counter() - began
    return [r for start in chunks for r in held[start]][:count], len(missing), seconds


def _compute(
    engine: Engine, shipped: list[Reference], indices: list[int], workers: int
) -> Iterator[tuple[int, Reference]]:
    """(index, padding reference) in the order of ``indices``."""
    named = (padding_points(shipped, index) for index in indices)
    if workers <= 1:
        yield from zip(indices, (engine.make_reference(*n) for n in named), strict=True)
        return
    context = multiprocessing.get_context("spawn")  # no onnxruntime threads forked
    initargs = (str(engine.mapper.path), engine.settings.model_dump())
    with ProcessPoolExecutor(workers, context, _start_worker, initargs) as pool:
        yield from zip(indices, pool.map(_make_reference, named), strict=True)


# --- the service -----------------------------------------------------------------------------


def serve(data_dir: Path, args: argparse.Namespace, provider: str) -> ServiceProcess:
    """The service on the benchmark's model, open (API keys would only add a header check per
    request); other ``DPC_*`` variables of this environment (engine settings) reach it."""
    return ServiceProcess(
        data_dir / "service.log",
        args.ready_timeout,
        inherit=True,
        gallery__data_dir=str(data_dir),
        model__path=str(args.model),
        model__gallery=str(args.gallery),
        model__use_cuda=str(provider == "cuda").lower(),
        server__log_level="warning",
        auth__keys="{}",
    )


# --- measurements ----------------------------------------------------------------------------


@dataclass
class Answers:
    """What a run of requests gave: each latency, each answer's steps and pose."""

    latencies: list[float] = dataclasses.field(default_factory=list)
    timings: list[dict[str, float]] = dataclasses.field(default_factory=list)
    poses: list[tuple[Cloud, str, np.ndarray, np.ndarray]] = dataclasses.field(default_factory=list)

    def summary(self, quality: Callable[[list], dict]) -> dict:
        overhead = [lat - t["total"] for lat, t in zip(self.latencies, self.timings, strict=True)]
        return {
            **latency_stats(self.latencies),
            "steps_ms": step_medians(self.timings),
            "overhead_ms": latency_stats(overhead),  # client latency - the answer's total
            **quality(self.poses),
        }


def sequential(
    client: httpx.Client, clouds: list[Cloud], requests: int, warmup: int, kind: str
) -> Answers:
    answers = Answers()
    for index in range(warmup + requests):
        cloud = clouds[index % len(clouds)]
        body, headers = cloud.body(kind)
        began = time.perf_counter()
        answer = client.post("/align", content=body, headers=headers)
        elapsed = (time.perf_counter() - began) * 1e3
        if answer.status_code != 200:
            raise RuntimeError(f"/align answered {answer.status_code}: {answer.text[:300]}")
        if index >= warmup:
            result = answer.json()
            answers.latencies.append(elapsed)
            answers.timings.append(result["timings_ms"])
            answers.poses.append(
                (
                    cloud,
                    result["label"],
                    np.array(result["rotation"]),
                    np.array(result["translation"]),
                )
            )
    return answers


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
                    body, headers = clouds[index % len(clouds)].body(kind)
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
        "kind": kind,
        "clients": clients,
        "requests": total,
        "seconds": wall,
        "requests_per_s": total / wall,
        **latency_stats(latencies),
    }


def engine_only(engine: Engine, clouds: list[Cloud], requests: int, warmup: int) -> Answers:
    answers = Answers()
    for index in range(warmup + requests):
        cloud = clouds[index % len(clouds)]
        began = time.perf_counter()
        result = engine.align(cloud.points)
        elapsed = (time.perf_counter() - began) * 1e3
        if index >= warmup:
            answers.latencies.append(elapsed)
            answers.timings.append(result.timings_ms)
            answers.poses.append((cloud, result.label, result.rotation, result.translation))
    return answers


class Judge:
    """Whether answers are right: the label, and ADD-S over the diameter of the reference's
    points (symmetry-aware) below ``SUCCESS_ADD_S`` (success) and ``PRECISE_ADD_S`` (precise)."""

    def __init__(self, references: list[Reference]):
        self.points = {r.name: np.asarray(r.points, dtype=np.float64) for r in references}
        self.diameters = {name: diameter(points) for name, points in self.points.items()}
        self.known: dict[tuple, float] = {}  # the answers to one cloud repeat: judged once

    def add_s(self, cloud: Cloud, label: str, rotation: np.ndarray, translation: np.ndarray):
        if label != cloud.label:
            return np.inf
        key = (id(cloud), rotation.tobytes(), translation.tobytes())
        if key not in self.known:
            self.known[key] = add_s(
                self.points[label],
                rotation,
                translation,
                cloud.rotation,
                cloud.translation,
                self.diameters[label],
            )
        return self.known[key]

    def __call__(self, poses: list[tuple[Cloud, str, np.ndarray, np.ndarray]]) -> dict:
        errors = np.array([self.add_s(*pose) for pose in poses])
        right = errors[np.isfinite(errors)]
        return {
            "label_right": float(np.mean([label == cloud.label for cloud, label, *_ in poses])),
            "success": float(np.mean(errors < SUCCESS_ADD_S)),
            "precise": float(np.mean(errors < PRECISE_ADD_S)),
            "median_add_s": float(np.median(right)) if len(right) else None,
        }


def registrations(client: httpx.Client, reference: Reference, repeats: int) -> dict:
    """Remove ``reference`` and register it again, without the registration check and with it
    (the default), ``repeats`` times each: each change refits the classifier on the gallery."""
    body = orjson.dumps({"name": reference.name, "points": reference.points.tolist()})
    removals, plain, checked, passed = [], [], [], []

    def timed(call: Callable[[], httpx.Response], expected: int) -> tuple[float, httpx.Response]:
        began = time.perf_counter()
        answer = call()
        elapsed = (time.perf_counter() - began) * 1e3
        if answer.status_code != expected:
            raise RuntimeError(
                f"{answer.request.method} answered {answer.status_code}: {answer.text}"
            )
        return elapsed, answer

    def register(check: bool) -> Callable[[], httpx.Response]:
        params = {"self_check": str(check).lower()}
        return lambda: client.post("/references", params=params, content=body, headers=JSON_TYPE)

    remove = partial(client.delete, f"/references/{reference.name}")
    for _ in range(repeats):
        for check, times in ((False, plain), (True, checked)):
            removals.append(timed(remove, 204)[0])
            elapsed, answer = timed(register(check), 201)
            times.append(elapsed)
            if check:
                passed += [c["label_ok"] for c in answer.json().get("self_check") or []]
    return {
        "reference": reference.name,
        "remove": latency_stats(removals),
        "register_no_check": latency_stats(plain),
        "register_checked": latency_stats(checked),
        "checks": len(passed),
        "checks_label_right": float(np.mean(passed)) if passed else None,
    }


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


def measure(
    size: int,
    provider: str,
    args: argparse.Namespace,
    engine: Engine,
    references: list[Reference],
    model_hash: str,
    clouds: list[Cloud],
    workdir: Path,
) -> dict:
    """Everything measured on one gallery and one execution provider."""
    title = f"[{size} references, {provider}]"
    data_dir = workdir / f"data-{size}-{provider}"
    seed_store(data_dir, references, model_hash)
    judge = Judge(references)
    print(f"{title} starting the service ...", flush=True)
    result: dict = {"references": size, "provider": provider}
    with serve(data_dir, args, provider) as service:
        result["service_ready_s"] = service.ready_s
        with httpx.Client(base_url=service.url, timeout=300.0) as client:
            health = client.get("/health").json()
            if health["references"] != size:
                raise RuntimeError(f"the service holds {health['references']}, not {size}")
            result["providers"] = health["providers"]
            if provider == "cuda" and "CUDAExecutionProvider" not in health["providers"]:
                raise RuntimeError(f"CUDA was asked for; the service uses {health['providers']}")
            # the HTTP stack alone (middleware, one loopback round trip): a GET with no work
            probes = []
            for _ in range(args.requests):
                began = time.perf_counter()
                client.get("/v2/health/live")
                probes.append((time.perf_counter() - began) * 1e3)
            result["http_live"] = latency_stats(probes)
            for kind in KINDS:
                print(f"{title} {args.requests} sequential {kind} requests", flush=True)
                answers = sequential(client, clouds, args.requests, args.warmup, kind)
                result[f"http_{kind}"] = answers.summary(judge)
            result["concurrency"] = []
            for kind in KINDS:
                for clients in args.clients:
                    print(f"{title} {clients} concurrent client(s), {kind}", flush=True)
                    result["concurrency"].append(
                        concurrent(service.url, clouds, clients, args.concurrent_requests, kind)
                    )
            if args.registrations:
                print(f"{title} {args.registrations} x remove + register", flush=True)
                result["registration"] = registrations(client, references[-1], args.registrations)
    print(f"{title} engine in-process", flush=True)
    began = time.perf_counter()
    engine.load(references)
    result["engine_load_s"] = time.perf_counter() - began
    answers = engine_only(engine, clouds, args.requests, args.warmup)
    result["engine"] = answers.summary(judge)
    for kind in KINDS:
        http = result[f"http_{kind}"]
        http["minus_engine_ms"] = http["median_ms"] - result["engine"]["median_ms"]
    engine.load([])
    shutil.rmtree(data_dir, ignore_errors=True)
    result["load_average"] = os.getloadavg()
    return result


def paired_growth(
    small: list[Reference],
    large: list[Reference],
    provider: str,
    args: argparse.Namespace,
    engine: Engine,
    model_hash: str,
    clouds: list[Cloud],
    workdir: Path,
) -> dict:
    """The growth from ``small`` to ``large`` with both galleries up at once: each cloud sent
    (raw body) to one service then to the other, the first in turn, and aligned likewise by an
    engine of each gallery in this process. The median of the per-cloud differences is not
    skewed by the machine's load changing between runs minutes apart, as medians are."""
    title = f"[{len(small)} and {len(large)} references, {provider}]"
    print(f"{title} both services, each cloud to one then the other", flush=True)
    with contextlib.ExitStack() as stack:
        clients = []
        for gallery in (small, large):
            data_dir = workdir / f"paired-{len(gallery)}-{provider}"
            seed_store(data_dir, gallery, model_hash)
            service = stack.enter_context(serve(data_dir, args, provider))
            clients.append(stack.enter_context(httpx.Client(base_url=service.url, timeout=300.0)))

        def post(side: int, cloud: Cloud) -> tuple[float, float]:
            began = time.perf_counter()
            answer = clients[side].post("/align", content=cloud.raw_body, headers=RAW_TYPE)
            elapsed = (time.perf_counter() - began) * 1e3
            if answer.status_code != 200:
                raise RuntimeError(f"/align answered {answer.status_code}: {answer.text[:300]}")
            return elapsed, answer.json()["timings_ms"]["total"]

        http = in_turn(post, clouds, args.requests, args.warmup)
    print(f"{title} both engines in-process, each cloud to one then the other", flush=True)
    engines = [Engine(engine.mapper, engine.settings, engine.calibration) for _ in range(2)]
    for side, gallery in enumerate((small, large)):
        engines[side].load(gallery)

    def align(side: int, cloud: Cloud) -> tuple[float, float]:
        began = time.perf_counter()
        result = engines[side].align(cloud.points)
        return (time.perf_counter() - began) * 1e3, result.timings_ms["total"]

    return {"http_raw": http, "engine": in_turn(align, clouds, args.requests, args.warmup)}


def in_turn(
    one: Callable[[int, Cloud], tuple[float, float]],
    clouds: list[Cloud],
    requests: int,
    warmup: int,
) -> dict:
    """``one(side, cloud)`` -> (latency, the answer's total) for side 0 and side 1 on each
    cloud, the side that goes first alternating; medians of each side and of the differences
    (side 1 - side 0), with their quartiles."""
    pairs = []
    for index in range(warmup + requests):
        cloud = clouds[index % len(clouds)]
        got: list = [None, None]
        for side in (0, 1) if index % 2 == 0 else (1, 0):
            got[side] = one(side, cloud)
        if index >= warmup:
            pairs.append(got)
    values = np.array(pairs)  # (requests, side, latency | total)
    result = {"requests": requests}
    for column, name in enumerate(("latency", "total")):
        growth = values[:, 1, column] - values[:, 0, column]
        result[name] = {
            "median_ms": [float(np.median(values[:, side, column])) for side in (0, 1)],
            "growth_median_ms": float(np.median(growth)),
            "growth_quartiles_ms": [float(q) for q in np.percentile(growth, [25, 75])],
        }
    return result


# --- accuracy --------------------------------------------------------------------------------


def accuracy(
    args: argparse.Namespace,
    gallery_refs: list[Reference],
    model_hash: str,
    workdir: Path,
) -> dict:
    """Success (right label, ADD-S < 0.10) per family on seen and on unseen objects, on the
    evaluation's cases of pybullet's meshes (the train extra)."""
    from evaluation.cases import make_cases
    from service.engine.sampling import sample_surface
    from training.objects import load_manifest, load_object_meshes

    seen_specs = load_manifest(split="seen")
    unseen_specs = load_manifest(split="unseen")
    in_gallery = {r.name for r in gallery_refs}
    seen_meshes = load_object_meshes([s for s in seen_specs if s.name in in_gallery])
    unseen_meshes = load_object_meshes([s for s in unseen_specs if s.name not in in_gallery])
    data_dir = workdir / "data-accuracy"
    seed_store(data_dir, gallery_refs, model_hash)
    models = {
        name: sample_surface(mesh, CLOUD_POINTS, 0)  # as the shipped gallery sampled them
        for name, mesh in {**seen_meshes, **unseen_meshes}.items()
    }
    print(f"[accuracy] starting the service with {len(gallery_refs)} references", flush=True)
    result: dict = {"poses_per_object": args.accuracy_poses, "seed": args.seed}
    with (
        serve(data_dir, args, "cpu") as service,
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
                    n_points=CLOUD_POINTS,
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


def judge(client: httpx.Client, case, models: dict, diameters: dict) -> tuple[bool, bool, float]:
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
    runs = report["runs"]
    providers = {r["provider"] for r in runs}
    columns = [
        f"{r['references']}" + (f" {r['provider']}" if len(providers) > 1 else "") for r in runs
    ]
    width = 12
    config = report["config"]
    print()
    print(
        f"POST /align over HTTP: model {config['model']} (sha256 {config['model_sha256'][:12]}), "
        f"{config['cpus']} CPUs, {config['platform']}, onnxruntime {config['onnxruntime']}"
    )
    start, end = config["load_average_at_start"], config["load_average_at_end"]
    print(
        "load average (1, 5, 15 min) at start "
        + ", ".join(f"{v:.2f}" for v in start)
        + "; at end "
        + ", ".join(f"{v:.2f}" for v in end)
    )
    print(
        f"clouds: {config['clouds']} resampled clouds of {config['cloud_objects']} shipped "
        f"references, {CLOUD_POINTS} points, random SO(3) poses; {config['requests']} sequential "
        f"requests per body (after {config['warmup']} warm-up), {config['concurrent_requests']} "
        "per concurrency level and body"
    )
    print()

    def row(title: str, values: list[str], target: str = "", width: int = width) -> None:
        print(f"{title:<38}" + "".join(f"{v:>{width}}" for v in values) + f"   {target}")

    def figure(value: float | None, digits: int = 1) -> str:
        return "-" if value is None else f"{value:.{digits}f}"

    def share(value: float | None) -> str:
        return "-" if value is None else f"{100 * value:.1f}%"

    base = [r for r in runs if r["references"] == BASE_REFERENCES]
    row("references", columns, "target")
    for kind in KINDS:
        target = f"<= {TARGET_MS[kind]:g} ms at {BASE_REFERENCES}"
        if base:
            verdicts = ", ".join(
                f"{r['provider']} {mark(r[f'http_{kind}']['median_ms'] <= TARGET_MS[kind])}"
                for r in base
            )
            target += f": {verdicts}"
        row(
            f"HTTP {kind} median ms", [figure(r[f"http_{kind}"]["median_ms"]) for r in runs], target
        )
        row(f"HTTP {kind} p95 ms", [figure(r[f"http_{kind}"]["p95_ms"]) for r in runs])
        row(
            f"HTTP {kind} overhead median ms",
            [figure(r[f"http_{kind}"]["overhead_ms"]["median_ms"], 2) for r in runs],
            "client latency - answer's total",
        )
        row(
            f"HTTP {kind} - engine (medians) ms",
            [figure(r[f"http_{kind}"]["minus_engine_ms"]) for r in runs],
        )
    row("GET /v2/health/live median ms", [figure(r["http_live"]["median_ms"], 2) for r in runs])
    row("engine in-process median ms", [figure(r["engine"]["median_ms"]) for r in runs])
    row("engine in-process p95 ms", [figure(r["engine"]["p95_ms"]) for r in runs])
    for index, level in enumerate(runs[0]["concurrency"]):
        label = f"{level['kind']}, {level['clients']} client(s)"
        row(
            f"requests/s, {label}",
            [figure(r["concurrency"][index]["requests_per_s"]) for r in runs],
        )
        row(f"  median ms, {label}", [figure(r["concurrency"][index]["median_ms"]) for r in runs])
    for kind in (*KINDS, "engine"):
        where = f"HTTP {kind}" if kind in KINDS else "engine"
        answers = [r[f"http_{kind}"] if kind in KINDS else r["engine"] for r in runs]
        row(f"{where}: right label", [share(a["label_right"]) for a in answers])
        row(f"{where}: ADD-S < {SUCCESS_ADD_S:g}", [share(a["success"]) for a in answers])
        row(f"{where}: ADD-S < {PRECISE_ADD_S:g}", [share(a["precise"]) for a in answers])
        row(
            f"{where}: median ADD-S",
            [figure(a["median_add_s"], 4) for a in answers],
        )
    row("service start to ready s", [figure(r["service_ready_s"], 2) for r in runs])
    row("engine load (entries + refit) s", [figure(r["engine_load_s"], 2) for r in runs])
    if all("registration" in r for r in runs):
        registered = [r["registration"] for r in runs]
        row(
            "DELETE one reference median ms", [figure(g["remove"]["median_ms"]) for g in registered]
        )
        row(
            "POST /references, no check, median ms",
            [figure(g["register_no_check"]["median_ms"]) for g in registered],
        )
        row(
            "POST /references, checked, median ms",
            [figure(g["register_checked"]["median_ms"]) for g in registered],
        )
        row("  its checks: right label", [share(g["checks_label_right"]) for g in registered])
    row("load average (1 min) after", [figure(r["load_average"][0], 2) for r in runs])
    print()
    print("median ms per step (answers' timings_ms: HTTP raw | HTTP json | engine in-process)")
    row("references", columns, width=width + 12)
    steps = list(runs[0]["engine"]["steps_ms"])
    for step in steps:
        row(
            f"  {step}",
            [
                " | ".join(
                    f"{a['steps_ms'].get(step, 0):.1f}"
                    for a in (r["http_raw"], r["http_json"], r["engine"])
                )
                for r in runs
            ],
            width=width + 12,
        )
    for growth in report.get("growth", []):
        print()
        print(
            f"growth {growth['from']} -> {growth['to']} references, {growth['provider']}; "
            f"target <= +{TARGET_GROWTH_MS:g} ms"
        )
        print("  difference of the medians above (runs minutes apart):")
        for key, value in growth["ms"].items():
            print(f"    {key:<24} {value:+8.2f} ms   {mark(value <= TARGET_GROWTH_MS)}")
        paired = growth.get("paired")
        if paired:
            print(
                "  paired: both galleries up at once, each cloud to one then the other "
                f"({paired['engine']['requests']} clouds); median of the differences "
                "[quartiles] (medians of each side)"
            )
            for where, key in (("http raw", "http_raw"), ("engine", "engine")):
                for name in ("latency", "total"):
                    value = paired[key][name]
                    low, high = value["growth_quartiles_ms"]
                    sides = " -> ".join(f"{v:.1f}" for v in value["median_ms"])
                    print(
                        f"    {where + ' ' + name:<24} {value['growth_median_ms']:+8.2f} ms   "
                        f"{mark(value['growth_median_ms'] <= TARGET_GROWTH_MS)}   "
                        f"[{low:+.1f}, {high:+.1f}] ({sides})"
                    )
    refit = report["refit"]
    print()
    print(
        f"classifier refit (LinearClassifier.fit), {refit['references']} references x "
        f"{refit['views_per_reference']} views: after one change median "
        f"{refit['median_ms']:.1f} ms (min {refit['min_ms']:.1f}), from scratch "
        f"{refit['from_scratch_median_ms']:.1f} ms ({refit['repeats']} repeats)"
    )
    padding = report["padding"]
    if padding["references"]:
        if padding["compute_s"] is None:
            print(f"{padding['references']} padding references: from the cache")
        else:
            print(
                f"{padding['references']} padding references: {padding['computed']} computed in "
                f"{padding['compute_s']:.1f} s ({padding['workers']} process(es)), cached in "
                f"{padding['cache']}"
            )
    accuracy_report = report.get("accuracy")
    if accuracy_report:
        print_accuracy(accuracy_report)


def print_accuracy(report: dict) -> None:
    print()
    print(
        f"accuracy (refinement on, gallery of {report['gallery_references']} references, "
        f"{report['poses_per_object']} poses per object and family; success = right label "
        f"and ADD-S < {SUCCESS_ADD_S})"
    )
    print(f"  {'':<22}{'cases':>8}{'recognition':>13}{'success':>10}{'median ADD-S':>14}")
    for key, value in report.items():
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
    registration = report.get("unseen_registration_ms")
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
    parser.add_argument("--clouds-per-object", type=int, default=2, help="clouds per reference")
    parser.add_argument(
        "--registrations",
        type=int,
        default=3,
        help="times one reference is removed and registered again, without and with the check",
    )
    parser.add_argument(
        "--providers",
        choices=("auto", "cpu", "cuda", "both"),
        default="auto",
        help="onnxruntime execution providers to measure (auto: both where onnxruntime offers "
        "CUDA, else the CPU)",
    )
    parser.add_argument("--refit-references", type=int, default=100)
    parser.add_argument("--refit-repeats", type=int, default=5)
    parser.add_argument(
        "--accuracy",
        action="store_true",
        help="also measure success shares on pybullet's meshes (needs the train extra)",
    )
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
    parser.add_argument(
        "--padding-workers", type=int, default=1, help="processes computing padding references"
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
    if args.accuracy and not installed("pybullet_data"):
        parser.error(
            "--accuracy aligns pybullet's meshes: install the train extra "
            "(pip install -e '.[train]'), or leave --accuracy out"
        )
    cuda = "CUDAExecutionProvider" in ort.get_available_providers()
    if args.providers == "auto":
        args.providers = ["cpu", "cuda"] if cuda else ["cpu"]
    else:
        args.providers = ["cpu", "cuda"] if args.providers == "both" else [args.providers]
        if "cuda" in args.providers and not cuda:
            parser.error("onnxruntime offers no CUDA execution provider here (onnxruntime-gpu)")
    return args


def installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def run(args: argparse.Namespace, progress: Callable[[str], None] = print) -> dict:
    settings = Settings()
    settings = settings.model_copy(
        update={"model": settings.model.model_copy(update={"path": args.model})}
    )
    engines = {}
    for provider in args.providers:
        mapper = Mapper(
            args.model,
            settings.model.intra_op_threads,
            settings.model.inter_op_threads,
            provider == "cuda",
            blas_threads=settings.model.blas_threads,
        )
        engines[provider] = Engine(mapper, settings.engine, load_calibration(settings))
    engine = engines[args.providers[0]]
    model_hash = engine.mapper.model_hash
    shipped, meta = load_gallery(args.gallery)
    gallery_hash = meta.get("model_sha256") or meta.get("model_hash")
    if gallery_hash != model_hash:
        progress("the gallery was computed with another model: recomputing its references")
        shipped = [engine.make_reference(r.name, r.points) for r in shipped]
    clouds = make_clouds(
        shipped[: min(BASE_REFERENCES, *args.references)], args.clouds_per_object, args.seed
    )
    needed = max(args.references) - len(shipped)
    padding, computed, padding_s = padding_references(
        engine, shipped, needed, args.padding_cache, args.padding_workers, progress
    )
    report: dict = {
        "config": {
            "model": str(args.model),
            "model_sha256": model_hash,
            "gallery": str(args.gallery),
            "providers": {p: e.mapper.providers for p, e in engines.items()},
            "onnxruntime": ort.__version__,
            "engine_settings": settings.engine.model_dump(mode="json"),
            "calibration": engine.calibration is not None,
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "clouds": len(clouds),
            "cloud_objects": len({c.label for c in clouds}),
            "requests": args.requests,
            "warmup": args.warmup,
            "concurrent_requests": args.concurrent_requests,
            "seed": args.seed,
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "load_average_at_start": os.getloadavg(),  # other work on the machine skews it all
        },
        "targets": {"median_ms": TARGET_MS, "growth_ms": TARGET_GROWTH_MS},
        "padding": {
            "references": len(padding),
            "computed": computed,
            "compute_s": padding_s,
            "workers": args.padding_workers,
            "cache": None if args.padding_cache is None else str(args.padding_cache),
        },
        "runs": [],
    }
    gallery = shipped + padding
    with tempfile.TemporaryDirectory(prefix="dpc-bench-") as tmp:
        for size in args.references:
            references = gallery[:size]
            for provider in args.providers:
                report["runs"].append(
                    measure(
                        size,
                        provider,
                        args,
                        engines[provider],
                        references,
                        model_hash,
                        clouds,
                        Path(tmp),
                    )
                )
        report["growth"] = growth(report["runs"])
        for grown in report["growth"]:
            small, large = gallery[: grown["from"]], gallery[: grown["to"]]
            provider = grown["provider"]
            grown["paired"] = paired_growth(
                small, large, provider, args, engines[provider], model_hash, clouds, Path(tmp)
            )
        report["refit"] = refit_time(
            gallery, args.refit_references, args.refit_repeats, settings.engine
        )
        if args.accuracy:
            report["accuracy"] = accuracy(args, shipped, model_hash, Path(tmp))
    report["config"]["finished_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    report["config"]["load_average_at_end"] = os.getloadavg()
    return report


def growth(runs: list[dict]) -> list[dict]:
    """Per provider, the medians at the largest size measured minus those at the smallest."""
    grown = []
    for provider in dict.fromkeys(r["provider"] for r in runs):
        mine = [r for r in runs if r["provider"] == provider]
        if len(mine) < 2:
            continue
        first, last = mine[0], mine[-1]
        grown.append(
            {
                "provider": provider,
                "from": first["references"],
                "to": last["references"],
                "ms": {
                    "http raw": last["http_raw"]["median_ms"] - first["http_raw"]["median_ms"],
                    "http json": last["http_json"]["median_ms"] - first["http_json"]["median_ms"],
                    "engine": last["engine"]["median_ms"] - first["engine"]["median_ms"],
                },
            }
        )
    return grown


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
