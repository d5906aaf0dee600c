"""What the benchmark times, for each gallery size and execution provider.

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
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import itertools
import os
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import httpx
import numpy as np
import orjson

from benchmarks.align_http.clouds import JSON_TYPE, RAW_TYPE, Cloud
from evaluation.latency import latency_stats, median
from evaluation.metrics import PRECISE_ADD_S, SUCCESS_ADD_S, add_s, diameter
from evaluation.served import ServiceProcess, seed_store
from service.engine.classifier import LinearClassifier, classifier_input, view_gram
from service.engine.engine import Engine
from service.engine.reference import Reference
from service.settings import EngineSettings

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
    return {k: median([t.get(k, 0.0) for t in timings]) for k in keys}


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
        **latency_stats(change, ("median_ms", "min_ms")),
        "from_scratch_median_ms": median(scratch),
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
            "median_ms": [median(values[:, side, column]) for side in (0, 1)],
            "growth_median_ms": median(growth),
            "growth_quartiles_ms": list(latency_stats(growth, ("p25_ms", "p75_ms")).values()),
        }
    return result


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
