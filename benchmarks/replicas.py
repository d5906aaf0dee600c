"""Replicas on one PostgreSQL gallery: how soon a change on one replica is served by another,
and what ``/align`` costs with the PostgreSQL store beside SQLite.

``python -m benchmarks.replicas [--changes 100] [--requests 200] [--url postgresql://...]
[--json out.json]``

1. Propagation: two replicas (``python -m service``) on one database holding the first 40
   references of the shipped gallery. ``--changes`` changes in a row, four kinds in turn:
   register a reference on A, delete it on B, register one on B, delete it on A. After each
   acknowledgement the other replica's ``GET /references/{name}`` is asked again and again
   (one keep-alive connection, no pause) until it shows the change: the delay is from the
   acknowledgement to that answer. Once with LISTEN/NOTIFY (the default), once with it off
   (``DPC_GALLERY__LISTEN=false``): the version check every ``poll_s`` alone.
2. ``/align``: a replica on SQLite and one on PostgreSQL with the same references, the same
   2,048-point ``so3`` clouds (``evaluation.cases``), requests alternating between the two so
   that the machine's other load falls on both alike: median and p95 latency of each.

Without ``--url``, a throwaway PostgreSQL server is started (``evaluation.postgres``). The model
and gallery come from ``DPC_MODEL__PATH`` / ``DPC_MODEL__GALLERY`` or the shipped ones. Every
count is fixed and the run stops by itself; nothing leaves loopback.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path

import httpx
import numpy as np

from benchmarks.align_http.clouds import JSON_TYPE, encode
from evaluation.cases import make_cases
from evaluation.latency import latency_stats
from evaluation.postgres import ThrowawayPostgres
from evaluation.served import ServiceProcess, seed_store
from service.gallery.gallery_file import load_gallery
from service.gallery.postgres_store import PostgresStore, redacted
from service.settings import Settings
from training.objects import load_manifest, load_object_meshes

REFERENCES = 40
TARGET_S = 1.0
WORST = ("count", "median_ms", "p95_ms", "max_ms")


def replica(workdir: Path, name: str, **settings: str) -> ServiceProcess:
    return ServiceProcess(
        workdir / f"{name}.log",
        inherit=True,  # engine settings of this environment reach the replicas
        gallery__data_dir=str(workdir / name),
        model__gallery=str(workdir / "no-seed.npz"),  # seeded before they start
        server__log_level="warning",
        auth__keys="{}",
        **settings,
    )


def propagation(
    a: ServiceProcess, b: ServiceProcess, changes: int, clouds: list
) -> dict[str, list[float]]:
    """Seconds from each change's acknowledgement to the other replica serving it, by kind."""
    delays: dict[str, list[float]] = {"register": [], "delete": []}
    with httpx.Client(base_url=a.url, timeout=60) as ca, httpx.Client(base_url=b.url) as cb:
        clients = {"a": ca, "b": cb}
        plan = [("a", "register"), ("b", "delete"), ("b", "register"), ("a", "delete")]
        name = ""
        for index in range(changes):
            source, kind = plan[index % len(plan)]
            target = clients["b" if source == "a" else "a"]
            if kind == "register":
                name = f"prop-{index}"
                body = {"name": name, "points": clouds[index % len(clouds)].tolist()}
                answer = clients[source].post("/references?self_check=false", json=body)
                expected = 200
            else:
                answer = clients[source].delete(f"/references/{name}")
                expected = 404
            acknowledged = time.perf_counter()
            if answer.status_code not in (201, 204):
                raise RuntimeError(f"{kind} answered {answer.status_code}: {answer.text[:300]}")
            while target.get(f"/references/{name}").status_code != expected:
                if time.perf_counter() - acknowledged > 30:
                    raise RuntimeError(f"change {index} ({kind} {name}) not followed in 30 s")
            delays[kind].append(time.perf_counter() - acknowledged)
    return delays


def align_latency(sqlite: ServiceProcess, postgres: ServiceProcess, clouds, requests: int):
    """Latencies (ms) of the same requests to each, alternating which goes first."""
    latencies: dict[str, list[float]] = {"sqlite": [], "postgresql": []}
    servers = {"sqlite": sqlite, "postgresql": postgres}
    clients = {k: httpx.Client(base_url=s.url, timeout=120) for k, s in servers.items()}
    try:
        for index in range(requests + 10):  # the first 10 warm up
            order = ("sqlite", "postgresql") if index % 2 == 0 else ("postgresql", "sqlite")
            cloud = clouds[index % len(clouds)]
            for kind in order:
                began = time.perf_counter()
                answer = clients[kind].post("/align", content=cloud.json_body, headers=JSON_TYPE)
                elapsed = (time.perf_counter() - began) * 1e3
                if answer.status_code != 200:
                    raise RuntimeError(f"/align on {kind}: {answer.status_code} {answer.text}")
                if index >= 10:
                    latencies[kind].append(elapsed)
    finally:
        for client in clients.values():
            client.close()
    return {kind: latency_stats(values) for kind, values in latencies.items()}


def delay_stats(delays: dict[str, list[float]]) -> dict:
    """Median, p95 and worst over every change, and median and worst by kind (ms)."""
    ms = {kind: [1e3 * delay for delay in values] for kind, values in delays.items()}
    every = worst(latency_stats([v for values in ms.values() for v in values], WORST))
    return {
        "changes": every.pop("count"),
        **every,
        "within_target": bool(every["worst_ms"] <= TARGET_S * 1e3),
        "by_kind": {
            kind: worst(latency_stats(v, ("median_ms", "max_ms"))) for kind, v in ms.items() if v
        },
    }


def worst(stats: dict) -> dict:
    """The figures with ``max_ms`` named as this benchmark's reports name it, ``worst_ms``."""
    return {"worst_ms" if key == "max_ms" else key: value for key, value in stats.items()}


def run(args: argparse.Namespace) -> dict:
    settings = Settings()
    references, meta = load_gallery(settings.model.gallery)
    references = references[:REFERENCES]
    model_hash = meta.get("model_sha256") or meta.get("model_hash")
    seen = {spec.name: spec for spec in load_manifest(split="seen")}
    names = [r.name for r in references if r.name in seen]
    meshes = load_object_meshes([seen[name] for name in names])
    scales = {r.name: float(r.scale) for r in references}
    cases = make_cases("so3", meshes, scales, n_points=2048, seed=0, poses_per_object=1)
    clouds = [encode(case) for case in cases]
    points = [np.asarray(case.points, np.float32) for case in cases]
    report: dict = {
        "config": {
            "references": len(references),
            "changes": args.changes,
            "requests": args.requests,
            "load_average_at_start": os.getloadavg(),
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
    }
    with ExitStack() as stack:
        workdir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="dpc-replicas-")))
        server = None if args.url else stack.enter_context(ThrowawayPostgres(fsync=True))

        def database() -> str:
            if args.url:
                return args.url
            return server.create_database()

        for mode, listen in (("notify", "true"), ("poll", "false")):
            url = database()
            store = PostgresStore(url)
            store.seed(references, model_hash, "benchmarks.replicas")
            store.close()
            extra = {"gallery__url": url, "gallery__listen": listen}
            print(
                f"propagation ({mode}) on {redacted(url)}: {args.changes} changes ...", flush=True
            )
            with (
                replica(workdir, f"a-{mode}", **extra) as a,
                replica(workdir, f"b-{mode}", **extra) as b,
            ):
                report[f"propagation_{mode}"] = delay_stats(propagation(a, b, args.changes, points))
            print(f"  {report[f'propagation_{mode}']}", flush=True)

        url = database()
        store = PostgresStore(url)
        store.seed(references, model_hash, "benchmarks.replicas")
        store.close()
        seed_store(workdir / "sqlite", references, model_hash)
        print(f"/align: {args.requests} requests to each store's replica ...", flush=True)
        with (
            replica(workdir, "sqlite") as on_sqlite,
            replica(workdir, "postgresql", gallery__url=url) as on_postgres,
        ):
            report["align"] = align_latency(on_sqlite, on_postgres, clouds, args.requests)
        print(f"  {report['align']}", flush=True)
    return report


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--changes", type=int, default=100)
    parser.add_argument("--requests", type=int, default=200)
    parser.add_argument(
        "--url", help="an existing PostgreSQL database, empty or this benchmark's (else throwaway)"
    )
    parser.add_argument("--json", type=Path, help="write the figures here too")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    report = run(args)
    print(json.dumps(report, indent=2))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
