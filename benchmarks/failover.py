"""Failover under load, with the real parts: what a line sees when a replica dies and when its
database restarts.

``python -m benchmarks.failover [--clients 2] [--registrars 2] [--json out.json]``

A throwaway PostgreSQL server (``evaluation.postgres``, fsync on) holds a gallery of the shipped
gallery's first ``--references``; two replicas (``python -m service``) share it; nginx stands in
front with the project's ``deploy/nginx.conf`` (``evaluation.proxy``). Through the proxy,
``--clients`` threads send ``/align`` the whole time, ``--pause-s`` after each answer
(2,048-point so3 clouds of the gallery's parts, raw float32, no retry of their own: nginx's
retries only), and ``--registrars`` threads register new parts back to back with
``service.client.Client`` (which sends a call again after a connection error, a 502 or a 503).
Then, in turn:

1. ``--kills`` times: once a replica is in the middle of a registration (its ``/metrics``:
   ``dpc_writes_in_progress``), at a random moment within ``--kill-within-s``, it is killed
   with SIGKILL, and started again on its port ``--down-s`` later: the time until it is
   ready, and until nginx has it answering alignments again (its access log);
2. PostgreSQL is stopped (fast shutdown) and started again ``--db-down-s`` later; while it is
   down one registration is sent without retries, to see what a client that does not retry
   is told; the time until both replicas are ready again.

Afterwards every acknowledged registration is read back from each replica directly: its
``points_sha256`` must be the one sent. Printed: ``/align`` requests and failures (by phase
and status), nginx's retries, latencies, registrations acknowledged and lost, what each failed
attempt was told (status and reason), and the times above. Every count and wait is fixed and
the run stops by itself; nothing leaves loopback.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import random
import tempfile
import threading
import time
from collections import Counter
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np

from evaluation.cases import make_cases
from evaluation.postgres import ThrowawayPostgres
from evaluation.proxy import ThrowawayNginx
from evaluation.served import ServiceProcess
from service.client import Client, ServiceError
from service.gallery.gallery_file import load_gallery
from service.gallery.postgres_store import PostgresStore
from service.settings import Settings
from training.objects import load_manifest, load_object_meshes

RAW = {"Content-Type": "application/octet-stream"}
PHASES = ("steady", "replica-down", "rejoining", "rejoined", "database-down", "recovering", "tail")
# figures.phase "rejoined" also covers the steady spell between two kills


@dataclass
class Figures:
    """What every thread recorded; one lock for all of it."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    phase: str = "steady"
    aligns: list[tuple[str, float, float, int | str]] = field(default_factory=list)
    acknowledged: dict[str, str] = field(default_factory=dict)  # name -> points_sha256 sent
    outcomes: Counter = field(default_factory=Counter)
    retried: list[tuple[str, str]] = field(default_factory=list)  # (phase, "status: detail")
    registration_s: list[float] = field(default_factory=list)  # acknowledged, first attempt
    after_retries: list[str] = field(default_factory=list)  # "502 then identical", ...
    gave_up: list[str] = field(default_factory=list)
    marks: dict[str, float] = field(default_factory=dict)

    def mark(self, phase: str) -> None:
        with self.lock:
            self.phase = phase
            self.marks[phase] = time.time()


def sha(points: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(points, dtype="<f4").tobytes()).hexdigest()


def align_load(
    url: str, clouds: list[bytes], figures: Figures, stop: threading.Event, pause_s: float
) -> None:
    """``/align`` through the proxy, ``pause_s`` after each answer, no retries of its own."""
    with httpx.Client(base_url=url, timeout=60) as client:
        index = 0
        while not stop.is_set():
            began = time.time()
            try:
                status: int | str = client.post(
                    "/align", content=clouds[index % len(clouds)], headers=RAW
                ).status_code
            except httpx.TransportError as error:
                status = type(error).__name__
            with figures.lock:
                figures.aligns.append((figures.phase, began, time.time(), status))
            index += 1
            stop.wait(pause_s)


def register_load(
    url: str,
    worker: int,
    parts: list[np.ndarray],
    figures: Figures,
    stop: threading.Event,
    self_check: bool,
) -> None:
    """New parts registered back to back through the proxy, each retried until acknowledged
    (within the client's bound)."""
    current: list[str] = []  # what the registration in flight was told before its answer

    def told(error: ServiceError, wait_s: float) -> None:
        current.append(str(error.status))
        with figures.lock:
            figures.retried.append((figures.phase, str(error)[:300]))

    with Client(url, retry_for=60, on_retry=told) as client:
        index = 0
        while not stop.is_set():
            name = f"failover-{worker}-{index}"
            points = parts[(worker + index) % len(parts)] * (1 + 0.01 * index)
            began = time.perf_counter()
            current.clear()
            try:
                answer = client.register(name, points, self_check=self_check)
            except ServiceError as error:
                with figures.lock:
                    figures.gave_up.append(f"{name}: {error}")
                index += 1
                continue
            spent = time.perf_counter() - began
            outcome = answer.raw.get("outcome")
            with figures.lock:
                figures.acknowledged[name] = answer.points_sha256
                figures.outcomes[outcome] += 1
                if current:
                    figures.after_retries.append(f"{' then '.join(current)} then {outcome}")
                else:
                    figures.registration_s.append(spent)
            if answer.points_sha256 != sha(points):
                figures.gave_up.append(f"{name}: acknowledged with other points")
            index += 1


def kill_and_rejoin(replicas: dict, replica, proxy, figures: Figures, args) -> dict:
    """The replica in the middle of a registration killed at a random moment of it, and
    started again on its port (in ``replicas``): the times until it is ready and back in
    rotation."""
    deadline = time.monotonic() + 120
    while not (busy := [k for k, r in replicas.items() if holds_registration(r.url)]):
        if time.monotonic() > deadline:
            raise TimeoutError("no replica was registering a part for 120 s")
        time.sleep(0.05)
    name = busy[0]
    time.sleep(random.uniform(0, args.kill_within_s))
    figures.mark("replica-down")
    replicas[name].kill()
    time.sleep(args.down_s)
    figures.mark("rejoining")
    server = replicas[name] = replica(name, replicas[name].port)
    restarted = figures.marks["rejoining"]
    ready_at = wait_for(lambda: ready(server.url), 180, f"replica {name} ready again")
    address = f"127.0.0.1:{server.port}"

    def answering() -> bool:
        return any(
            r.uri == "/align"
            and r.time > restarted
            and r.upstream_statuses[-1:] == ["200"]
            and r.upstreams[-1:] == [address]
            for r in proxy.requests()
        )

    rejoined_at = wait_for(answering, 120, f"nginx sending alignments to replica {name} again")
    figures.mark("rejoined")
    return {
        "replica": name,
        "down_s": args.down_s,
        "restart_to_ready_s": ready_at - restarted,
        "restart_to_rejoined_s": rejoined_at - restarted,
        "kill_to_rejoined_s": rejoined_at - figures.marks["replica-down"],
    }


def holds_registration(url: str) -> bool:
    """Whether the replica is working on a registration (its /metrics)."""
    try:
        text = httpx.get(f"{url}/metrics", timeout=2).text
    except httpx.TransportError:
        return False
    for line in text.splitlines():
        if line.startswith("dpc_writes_in_progress ") and float(line.split()[1]) > 0:
            return True
    return False


def wait_for(check, timeout_s: float, what: str) -> float:
    """Poll ``check()`` until it is true; the time it became so (epoch seconds)."""
    deadline = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what} did not happen in {timeout_s:.0f} s")
        time.sleep(0.1)
    return time.time()


def ready(url: str) -> bool:
    try:
        return httpx.get(f"{url}/v2/health/ready", timeout=2).status_code == 200
    except httpx.TransportError:
        return False


def run(args: argparse.Namespace) -> dict:
    random.seed(args.seed)
    settings = Settings()
    references, meta = load_gallery(settings.model.gallery)
    references = references[: args.references]
    seen = {spec.name: spec for spec in load_manifest(split="seen")}
    names = [r.name for r in references if r.name in seen]
    meshes = load_object_meshes([seen[name] for name in names])
    scales = {r.name: float(r.scale) for r in references}
    cases = make_cases("so3", meshes, scales, n_points=2048, seed=0, poses_per_object=1)
    clouds = [np.asarray(c.points, "<f4").tobytes() for c in cases]
    parts = [np.asarray(c.points, np.float32) for c in cases]
    figures, stop = Figures(), threading.Event()
    report: dict = {
        "config": {**vars(args), "json": str(args.json), "load_average_at_start": os.getloadavg()},
    }
    with ExitStack() as stack:
        if args.keep:
            workdir = Path(tempfile.mkdtemp(prefix="dpc-failover-"))
            print(f"logs in {workdir}", flush=True)
        else:
            workdir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="dpc-failover-")))
        database = stack.enter_context(ThrowawayPostgres(fsync=True))
        url = database.create_database()
        store = PostgresStore(url)
        store.seed(references, meta.get("model_sha256") or meta.get("model_hash"), "failover")
        store.close()
        extra = {
            "gallery__url": url,
            "gallery__connect_timeout_s": str(args.connect_timeout_s),
            "model__gallery": str(workdir / "no-seed.npz"),
            "server__log_level": "warning",
            "auth__keys": "{}",
            **dict(setting.split("=", 1) for setting in args.setting),
        }

        def replica(name: str, port: int | None = None) -> ServiceProcess:
            server = ServiceProcess(
                workdir / f"{name}.log",
                inherit=True,
                wait=False,
                port=port,
                gallery__data_dir=str(workdir / name),
                **extra,
            )
            stack.callback(server.stop)
            return server

        replicas = {"a": replica("a"), "b": replica("b")}
        for server in replicas.values():
            server.wait_ready(180)
        upstreams = [f"127.0.0.1:{server.port}" for server in replicas.values()]
        proxy = stack.enter_context(ThrowawayNginx(upstreams))
        threads = [
            threading.Thread(
                target=align_load, args=(proxy.url, clouds, figures, stop, args.pause_s)
            )
            for _ in range(args.clients)
        ] + [
            threading.Thread(
                target=register_load,
                args=(proxy.url, w, parts, figures, stop, not args.no_self_check),
            )
            for w in range(args.registrars)
        ]
        for thread in threads:
            thread.start()
        try:
            time.sleep(args.steady_s)
            report["replica_kills"] = []
            for kill in range(args.kills):
                figures_of_kill = kill_and_rejoin(replicas, replica, proxy, figures, args)
                print(f"SIGKILL {kill + 1} of {args.kills}:", flush=True)
                report["replica_kills"].append(figures_of_kill)
                print(f"  {figures_of_kill}", flush=True)
                time.sleep(args.steady_s)
            print("PostgreSQL: stopped", flush=True)
            figures.mark("database-down")
            database.stop()
            with Client(proxy.url, retry_for=0) as once:  # what a client that does not retry sees
                try:
                    once.register("failover-probe", parts[0], self_check=False)
                    probe = {"status": 201, "detail": "stored while the database was down?!"}
                except ServiceError as error:
                    probe = {"status": error.status, "detail": error.detail}
            time.sleep(max(0.0, args.db_down_s - (time.time() - figures.marks["database-down"])))
            figures.mark("recovering")
            database.start(fsync=True)
            back = wait_for(
                lambda: all(ready(r.url) for r in replicas.values()), 120, "both replicas ready"
            )
            report["database_restart"] = {
                "down_s": figures.marks["recovering"] - figures.marks["database-down"],
                "start_to_both_ready_s": back - figures.marks["recovering"],
                "registration_without_retry_during_outage": probe,
            }
            print(f"  {report['database_restart']}", flush=True)
            figures.mark("tail")
            time.sleep(args.steady_s)
        finally:
            stop.set()
            for thread in threads:
                thread.join(timeout=180)
        lost = []
        for name, digest in sorted(figures.acknowledged.items()):
            for server in replicas.values():
                answer = httpx.get(f"{server.url}/references/{name}", timeout=30)
                if answer.status_code != 200 or answer.json()["points_sha256"] != digest:
                    lost.append(f"{name} on {server.url}: {answer.status_code}")
        log = proxy.requests()
    report["align"] = align_figures(figures, log)
    report["registrations"] = {
        "acknowledged": len(figures.acknowledged),
        "lost": lost,
        "outcomes": dict(figures.outcomes),
        "gave_up": figures.gave_up,
        "retried_attempts": len(figures.retried),
        "answered_after_retries": dict(Counter(figures.after_retries)),
        "retried_by_phase_and_answer": dict(
            Counter(f"{phase}: {told.split(' (after')[0][:120]}" for phase, told in figures.retried)
        ),
        "seconds_without_retry": percentiles(figures.registration_s),
    }
    report["config"]["load_average_at_end"] = os.getloadavg()
    return report


def align_figures(figures: Figures, log) -> dict:
    aligns = figures.aligns
    by_phase = {}
    for phase in PHASES:
        mine = [a for a in aligns if a[0] == phase]
        if mine:
            by_phase[phase] = {
                "requests": len(mine),
                "failed": sum(a[3] != 200 for a in mine),
                "latency_ms": percentiles([(a[2] - a[1]) * 1e3 for a in mine]),
            }
    proxied = [r for r in log if r.uri == "/align"]
    return {
        "requests": len(aligns),
        "failed": sum(a[3] != 200 for a in aligns),
        "by_status": dict(Counter(str(a[3]) for a in aligns)),
        "by_phase": by_phase,
        "retried_by_nginx": sum(len(r.upstreams) > 1 for r in proxied),
        "nginx_upstream_answers": dict(Counter(", ".join(r.upstream_statuses) for r in proxied)),
    }


def percentiles(values: list[float]) -> dict:
    if not values:
        return {}
    return {
        "count": len(values),
        "median": float(np.median(values)),
        "p95": float(np.percentile(values, 95)),
        "max": float(np.max(values)),
    }


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--references", type=int, default=40)
    parser.add_argument("--clients", type=int, default=2, help="threads sending /align")
    parser.add_argument(
        "--pause-s", type=float, default=0.1, help="an aligning thread's pause between requests"
    )
    parser.add_argument("--registrars", type=int, default=2, help="threads registering parts")
    parser.add_argument("--steady-s", type=float, default=8.0, help="between the failures")
    parser.add_argument("--kills", type=int, default=2, help="times replica A is killed")
    parser.add_argument(
        "--kill-within-s", type=float, default=1.5, help="into a registration on A, at random"
    )
    parser.add_argument("--down-s", type=float, default=3.0, help="replica A dead this long")
    parser.add_argument("--db-down-s", type=float, default=10.0, help="PostgreSQL down this long")
    parser.add_argument(
        "--connect-timeout-s", type=float, default=5.0, help="DPC_GALLERY__CONNECT_TIMEOUT_S"
    )
    parser.add_argument(
        "--setting",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a replica setting, e.g. engine__view_grids=2 (repeat)",
    )
    parser.add_argument(
        "--no-self-check", action="store_true", help="register without the self-check"
    )
    parser.add_argument("--seed", type=int, default=0, help="of the kills' random moments")
    parser.add_argument("--json", type=Path, help="write the figures here too")
    parser.add_argument("--keep", action="store_true", help="keep the replicas' logs")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    report = run(args)
    print(json.dumps(report, indent=2))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
