"""Sustained load on the service: a fixed rate of /align, with registrations and deletions.

Starts ``python -m service`` on a free loopback port with a fresh data directory and an admin
key (or uses ``--url`` of a running one), sends 2,048-point clouds of the seed gallery's
objects at random poses to ``POST /align`` at ``--rate`` requests a second for ``--duration``
seconds (open loop: a slow answer does not slow the sender; at most ``--max-in-flight`` wait
at once, beyond that a request is counted as dropped), and registers a new reference every
``--write-every`` seconds; once ``--keep`` of them are there, the oldest is read back
(checksum) and deleted, so the gallery churns at a steady size, as in a cell where parts
come and go. At the end it checks that every acknowledged registration was read back byte
for byte and every acknowledged deletion is gone, removes what it registered, and prints:
requests served, answers by status, p50/p99 latency, the achieved rate, and the server's
resident memory, sampled every ``--sample-every`` s: at the start, its level in the
``--window`` seconds after ``--warmup`` seconds (allocator pools, caches and the first refits
fill up) and in the last ``--window`` seconds (medians: one sample swings by tens of MB with
the requests in flight), the growth between the two and the trend after the warm-up.

``--find-max`` ramps the rate instead (x1.5 a step of ``--step-duration`` seconds) until the
service stops keeping up (errors, p99 over ``--p99-budget-ms``, or under 90 % of the rate
achieved) and reports the highest rate it sustained and its maximum throughput: the most
alignments a second it served, which the last, saturated step shows.

    python scripts/load.py --rate 5 --duration 30
    python scripts/load.py --find-max --step-duration 10
    python scripts/load.py --url http://127.0.0.1:8000 --key "$KEY" --pid "$SERVICE_PID"
"""

from __future__ import annotations

import argparse
import asyncio
import hashlib
import json
import os
import secrets
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from evaluation.latency import latency_stats  # noqa: E402
from evaluation.served import ServiceProcess  # noqa: E402
from service.gallery.gallery_file import load_gallery  # noqa: E402 - numpy only, no server code
from service.settings import Settings  # noqa: E402

CLOUD_POINTS = 2048
MAX_DURATION_S = 3600  # bounded, whatever is asked
MAX_RATE = 500.0


# --- the server under load ----------------------------------------------------------------


def own_server(workdir: Path) -> tuple[ServiceProcess, str]:
    """``python -m service`` on loopback with a fresh data directory and an admin key."""
    key = secrets.token_urlsafe(24)
    server = ServiceProcess(
        workdir / "service.log",
        wait=False,
        gallery__data_dir=str(workdir / "data"),
        server__log_level="warning",
        auth__keys=json.dumps({key: "admin"}),
    )
    return server, key


def rss_mib(pid: int | None) -> float | None:
    """Resident memory of a process (Linux /proc), MiB."""
    if pid is None:
        return None
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


# --- what is sent -------------------------------------------------------------------------


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def scene_clouds(gallery: Path, count: int, seed: int = 0) -> list[bytes]:
    """Raw float32 bodies: 2,048 points of a gallery object each, at a random pose."""
    rng = np.random.default_rng(seed)
    if gallery.exists():
        objects = [reference.points for reference in load_gallery(gallery)[0]]
    else:  # no gallery file at hand: boxes
        objects = [new_reference(rng) for _ in range(4)]
    bodies = []
    for index in range(count):
        points = objects[index % len(objects)]
        chosen = rng.choice(len(points), CLOUD_POINTS, replace=len(points) < CLOUD_POINTS)
        scale = float(np.abs(points).max())
        scene = points[chosen] @ random_rotation(rng).T + rng.uniform(-0.5, 0.5, 3) * scale
        scene += rng.normal(scale=0.002 * scale, size=scene.shape)
        bodies.append(scene.astype("<f4").tobytes())
    return bodies


def new_reference(rng: np.random.Generator) -> np.ndarray:
    """1,024 points on the surface of a box of random extents."""
    points = rng.uniform(-1, 1, size=(1024, 3))
    rows, face = np.arange(len(points)), rng.integers(0, 3, len(points))
    points[rows, face] = np.sign(points[rows, face])  # pushed onto one of the six faces
    return (points * rng.uniform(0.05, 0.5, 3)).astype(np.float32)


def sha(points: np.ndarray) -> str:
    return hashlib.sha256(points.astype("<f4").tobytes()).hexdigest()


# --- the load -----------------------------------------------------------------------------


@dataclass
class Tally:
    statuses: Counter = field(default_factory=Counter)  # "align 200", "register 201", ...
    latencies_ms: list[float] = field(default_factory=list)  # of the alignments answered
    transport_errors: int = 0
    dropped: int = 0  # not sent: --max-in-flight requests were already waiting
    sent: int = 0

    def record(self, kind: str, status: int, began: float) -> None:
        self.statuses[f"{kind} {status}"] += 1
        if kind == "align":
            self.latencies_ms.append((time.perf_counter() - began) * 1e3)


@dataclass
class Writes:
    kept: dict[str, str] = field(default_factory=dict)  # acknowledged, not yet deleted: sha
    deleted: set[str] = field(default_factory=set)  # acknowledged deletions
    unsure: set[str] = field(default_factory=set)  # no answer: either outcome is fine
    checked: dict[str, str] = field(default_factory=dict)  # read back: "ok", "lost", "changed"
    registered: int = 0  # acknowledged registrations


async def align_once(client: httpx.AsyncClient, body: bytes, tally: Tally) -> None:
    began = time.perf_counter()
    try:
        response = await client.post(
            "/align", content=body, headers={"content-type": "application/octet-stream"}
        )
    except httpx.HTTPError:
        tally.transport_errors += 1
        return
    tally.record("align", response.status_code, began)


async def read_back(client: httpx.AsyncClient, name: str, digest: str) -> str:
    """ "ok" if the reference is there byte for byte, else "lost" or "changed"."""
    response = await client.get(f"/references/{name}")
    if response.status_code != 200:
        return "lost"
    return "ok" if response.json().get("points_sha256") == digest else "changed"


async def write_loop(
    client: httpx.AsyncClient,
    every_s: float,
    keep: int,
    until: float,
    writes: Writes,
    tally: Tally,
    tag: str,
) -> None:
    """Register a reference every ``every_s`` seconds; once ``keep`` of them are there, read
    the oldest back (checksum) and delete it, so the gallery churns without growing."""
    rng = np.random.default_rng(1)
    index = 0
    loop = asyncio.get_running_loop()
    start = loop.time()
    while start + (index + 1) * every_s < until:
        await asyncio.sleep(max(0.0, start + (index + 1) * every_s - loop.time()))  # on schedule
        name = f"load-{tag}-{index}"
        points = new_reference(rng)
        index += 1
        began = time.perf_counter()
        try:
            response = await client.post(
                "/references?self_check=false", json={"name": name, "points": points.tolist()}
            )
            tally.record("register", response.status_code, began)
            if response.status_code == 201:
                writes.kept[name] = sha(points)
                writes.registered += 1
        except httpx.HTTPError:
            tally.transport_errors += 1
            writes.unsure.add(name)
        while len(writes.kept) > keep:  # the oldest acknowledged one
            victim, digest = next(iter(writes.kept.items()))
            try:
                writes.checked[victim] = await read_back(client, victim, digest)
                began = time.perf_counter()
                response = await client.delete(f"/references/{victim}")
            except httpx.HTTPError:
                tally.transport_errors += 1
                del writes.kept[victim]
                writes.unsure.add(victim)
                continue
            tally.record("delete", response.status_code, began)
            if response.status_code != 204:
                break  # still there (and still kept): tried again after the next registration
            del writes.kept[victim]
            writes.deleted.add(victim)


class Memory:
    """The server's resident memory, sampled every ``every_s`` seconds while the load runs."""

    def __init__(self, pid: int | None, every_s: float = 10.0):
        self.pid, self.every_s = pid, every_s
        self.samples: list[tuple[float, float]] = []  # (seconds into the run, MiB)
        self._began = time.monotonic()

    async def watch(self, until: float) -> None:
        loop = asyncio.get_running_loop()
        while self.pid is not None:
            self.sample()
            if loop.time() + self.every_s > until:
                return
            await asyncio.sleep(self.every_s)

    def sample(self) -> None:
        if (mib := rss_mib(self.pid)) is not None:
            self.samples.append((round(time.monotonic() - self._began, 1), round(mib, 1)))

    def summary(self, warmup_s: float, window_s: float) -> dict:
        """Start, end and peak; the level after the warm-up and at the end, each the median of
        ``window_s`` seconds of samples (one sample swings by tens of MB with the requests in
        flight and the allocations of a refit), the growth between the two, and the trend
        after the warm-up (least squares)."""
        if not self.samples:
            return {"rss_mib_start": None, "rss_mib_end": None}
        times, mib = np.array(self.samples).T
        settled = times >= warmup_s
        if settled.sum() < 2:
            settled = times >= 0
        first = times[settled][0]
        after_warmup = float(np.median(mib[settled & (times <= first + window_s)]))
        last_window = float(np.median(mib[times >= times[-1] - window_s]))
        slope = np.polyfit(times[settled], mib[settled], 1)[0] if settled.sum() > 1 else 0.0
        return {
            "rss_mib_start": self.samples[0][1],
            "rss_mib_after_warmup": round(after_warmup, 1),
            "rss_mib_last_window": round(last_window, 1),
            "rss_mib_end": self.samples[-1][1],
            "rss_mib_peak": float(mib.max()),
            "rss_window_s": round(window_s, 1),
            "rss_growth_pct": round(100 * (last_window - after_warmup) / after_warmup, 1),
            "rss_trend_mib_per_min": round(float(slope) * 60, 2),
            "rss_samples": self.samples,
        }


async def hold_rate(
    client: httpx.AsyncClient,
    bodies: list[bytes],
    rate: float,
    duration_s: float,
    max_in_flight: int,
    tally: Tally,
) -> float:
    """Send at ``rate`` for ``duration_s`` (open loop); returns the seconds it all took."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    in_flight: set[asyncio.Task] = set()
    total = int(rate * duration_s)
    for index in range(total):
        await asyncio.sleep(max(0.0, start + index / rate - loop.time()))
        if len(in_flight) >= max_in_flight:
            tally.dropped += 1
            continue
        task = asyncio.create_task(align_once(client, bodies[index % len(bodies)], tally))
        in_flight.add(task)
        task.add_done_callback(in_flight.discard)
        tally.sent += 1
    if in_flight:
        await asyncio.wait(in_flight, timeout=60)
    return max(loop.time() - start, duration_s)  # the schedule spans duration_s


async def verify(client: httpx.AsyncClient, writes: Writes) -> dict[str, int]:
    """Every acknowledged registration read back identical (during the run, before its
    deletion, or now); every acknowledged deletion gone."""
    for name, digest in writes.kept.items():
        writes.checked[name] = await read_back(client, name, digest)
    outcomes = Counter(writes.checked.values())
    resurrected = 0
    for name in writes.deleted:
        if (await client.get(f"/references/{name}")).status_code != 404:
            resurrected += 1
    return {
        "read_back": outcomes["ok"],
        "lost": outcomes["lost"],
        "changed": outcomes["changed"],
        "resurrected": resurrected,
    }


async def clean_up(client: httpx.AsyncClient, writes: Writes) -> None:
    for name in [*writes.kept, *writes.unsure]:
        await client.delete(f"/references/{name}")


def percentiles(values: list[float]) -> dict[str, float | None]:
    """The median and the 99th percentile, to 0.1 ms; None without values."""
    stats = latency_stats(values, ("p50_ms", "p99_ms"))
    return {key: None if value is None else round(value, 1) for key, value in stats.items()}


def summary(tally: Tally, rate: float, elapsed_s: float) -> dict:
    answered = sum(n for key, n in tally.statuses.items() if key.startswith("align "))
    ok = tally.statuses.get("align 200", 0)
    by_status = Counter()
    for key, n in tally.statuses.items():
        by_status[int(key.split()[1])] += n
    return {
        "target_rate": rate,
        "achieved_rate": round(ok / elapsed_s, 2) if elapsed_s else 0.0,
        "align_sent": tally.sent,
        "align_answered": answered,
        "align_ok": ok,
        "dropped": tally.dropped,
        "transport_errors": tally.transport_errors,
        **percentiles(tally.latencies_ms),
        "statuses": dict(sorted(tally.statuses.items())),
        "errors_4xx": sum(n for s, n in by_status.items() if 400 <= s < 500),
        "errors_5xx": sum(n for s, n in by_status.items() if s >= 500),
        "elapsed_s": round(elapsed_s, 1),
    }


async def run(args: argparse.Namespace, url: str, key: str | None, pid: int | None) -> dict:
    headers = {"Authorization": f"Bearer {key}"} if key else {}
    limits = httpx.Limits(max_connections=args.max_in_flight + 4)
    bodies = scene_clouds(args.gallery, 64)
    async with httpx.AsyncClient(
        base_url=url, headers=headers, timeout=60, limits=limits
    ) as client:
        health = (await client.get("/health")).json()
        memory = Memory(pid, args.sample_every)
        tag = secrets.token_hex(3)
        if args.find_max:
            memory.sample()
            steps = await find_max(client, bodies, args)
            memory.sample()
            result: dict = {"mode": "find-max", "steps": steps}
            passed = [step["target_rate"] for step in steps if step["kept_up"]]
            result["max_sustained_rate"] = max(passed) if passed else None
            # what the service served when the sender asked for more than it could: its maximum
            result["max_throughput"] = max(step["achieved_rate"] for step in steps)
        else:
            tally, writes = Tally(), Writes()
            until = asyncio.get_running_loop().time() + args.duration
            watcher = asyncio.create_task(memory.watch(until))
            writer = asyncio.create_task(
                write_loop(client, args.write_every, args.keep, until, writes, tally, tag)
            )
            elapsed = await hold_rate(
                client, bodies, args.rate, args.duration, args.max_in_flight, tally
            )
            await writer
            await watcher
            memory.sample()  # the end
            result = {"mode": "rate", **summary(tally, args.rate, elapsed)}
            result["references"] = {
                "registered": writes.registered,
                "deleted": len(writes.deleted),
                **await verify(client, writes),
            }
            await clean_up(client, writes)
        result["gallery_references"] = health.get("references")
        result["warmup_s"] = args.warmup
        result |= memory.summary(args.warmup, args.window)
    return result


async def find_max(client: httpx.AsyncClient, bodies: list[bytes], args) -> list[dict]:
    steps, rate = [], args.start_rate
    for _ in range(args.max_steps):
        tally = Tally()
        elapsed = await hold_rate(
            client, bodies, rate, args.step_duration, args.max_in_flight, tally
        )
        step = summary(tally, rate, elapsed)
        step["kept_up"] = bool(
            step["errors_5xx"] == 0
            and step["transport_errors"] == 0
            and step["dropped"] == 0
            and step["p99_ms"] is not None
            and step["p99_ms"] <= args.p99_budget_ms
            and step["achieved_rate"] >= 0.9 * rate
        )
        steps.append(step)
        print(
            f"  rate {rate:7.2f}/s: achieved {step['achieved_rate']:7.2f}/s, p50 "
            f"{step['p50_ms']} ms, p99 {step['p99_ms']} ms, 5xx {step['errors_5xx']}, "
            f"dropped {step['dropped']} -> {'ok' if step['kept_up'] else 'saturated'}",
            flush=True,
        )
        if not step["kept_up"]:
            break
        rate = min(MAX_RATE, rate * 1.5)
    return steps


def report(result: dict) -> None:
    if result["mode"] == "find-max":
        print(
            f"maximum sustained rate: {result['max_sustained_rate']} alignments/s; maximum "
            f"throughput: {result['max_throughput']} alignments/s served"
        )
    else:
        refs = result["references"]
        print(
            f"served {result['align_ok']} of {result['align_sent']} alignments in "
            f"{result['elapsed_s']} s: {result['achieved_rate']}/s (target "
            f"{result['target_rate']}/s), p50 {result['p50_ms']} ms, p99 {result['p99_ms']} ms"
        )
        print(f"answers: {result['statuses']}")
        print(
            f"errors: 4xx {result['errors_4xx']}, 5xx {result['errors_5xx']}, transport "
            f"{result['transport_errors']}, dropped {result['dropped']}"
        )
        print(
            f"references: {refs['registered']} registered, {refs['deleted']} deleted, "
            f"{refs['read_back']} read back identical; lost {refs['lost']}, changed "
            f"{refs['changed']}, resurrected {refs['resurrected']}"
        )
    if result["mode"] == "find-max" and result.get("rss_mib_end") is not None:
        print(
            f"server memory (RSS): {result['rss_mib_start']} MiB at the start, "
            f"{result['rss_mib_end']} at the end"
        )
    elif result.get("rss_mib_after_warmup") is not None:
        print(
            f"server memory (RSS): {result['rss_mib_start']} MiB at the start, "
            f"{result['rss_mib_after_warmup']} in the {result['rss_window_s']:g} s after "
            f"{result['warmup_s']:g} s of warm-up, {result['rss_mib_last_window']} in the last "
            f"{result['rss_window_s']:g} s (medians; last sample {result['rss_mib_end']}, peak "
            f"{result['rss_mib_peak']}): {result['rss_growth_pct']:+} %, trend "
            f"{result['rss_trend_mib_per_min']:+} MiB/min after the warm-up"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", help="a running service (loopback); default: start one")
    parser.add_argument("--key", default=os.environ.get("DPC_LOAD_KEY"), help="an admin key")
    parser.add_argument("--pid", type=int, help="the running service's process id (for RSS)")
    parser.add_argument("--rate", type=float, default=5.0, help="alignments a second")
    parser.add_argument("--duration", type=float, default=30.0, help="seconds")
    parser.add_argument("--write-every", type=float, default=2.0, help="seconds between writes")
    parser.add_argument(
        "--keep", type=int, default=4, help="the load's references kept at once (oldest deleted)"
    )
    parser.add_argument(
        "--warmup", type=float, default=60.0, help="seconds before memory growth is counted"
    )
    parser.add_argument("--sample-every", type=float, default=2.0, help="seconds between RSS")
    parser.add_argument(
        "--window", type=float, default=60.0, help="seconds of RSS samples a level is the median of"
    )
    parser.add_argument("--max-in-flight", type=int, default=32)
    parser.add_argument("--gallery", type=Path, default=Settings().model.gallery)
    parser.add_argument("--find-max", action="store_true", help="ramp the rate to saturation")
    parser.add_argument("--start-rate", type=float, default=2.0)
    parser.add_argument("--step-duration", type=float, default=10.0)
    parser.add_argument("--max-steps", type=int, default=12)
    parser.add_argument("--p99-budget-ms", type=float, default=2000.0)
    parser.add_argument("--json", action="store_true", help="also print the result as JSON")
    args = parser.parse_args(argv)
    args.rate = min(max(args.rate, 0.1), MAX_RATE)
    args.duration = min(max(args.duration, 1.0), MAX_DURATION_S)
    args.warmup = min(max(args.warmup, 0.0), args.duration / 3)
    args.window = min(max(args.window, args.sample_every), (args.duration - args.warmup) / 3)
    args.keep = max(args.keep, 0)
    args.step_duration = min(max(args.step_duration, 1.0), MAX_DURATION_S / args.max_steps)

    if args.url:
        host = httpx.URL(args.url).host
        if host not in ("127.0.0.1", "localhost", "::1"):
            parser.error("--url must be a loopback address: this script is for the bench")
        result = asyncio.run(run(args, args.url, args.key, args.pid))
    else:
        with tempfile.TemporaryDirectory(prefix="dpc-load-") as workdir:
            server, key = own_server(Path(workdir))
            try:
                server.wait_ready()
                result = asyncio.run(run(args, server.url, key, server.pid))
            finally:
                server.stop()
    report(result)
    if args.json:
        print(json.dumps(result))
    if result["mode"] == "rate":
        refs = result["references"]
        failed = result["errors_5xx"] or refs["lost"] or refs["changed"] or refs["resurrected"]
        return 1 if failed else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
