"""The engine in worker processes (``server.engine_processes``, the second core): a real
``python -m service`` with two workers, beside a server answering in its own process.

The workers answer ``/align`` and ``/detect`` as the service's own engine would, follow every
registration and removal the service has acknowledged before the next answer, send the
engine's errors back as the same status codes, and a worker killed with SIGKILL costs no
request: the service answers in its own process while new workers start. By default a request
that finds no other in the engine is answered in the service's own process, and those that
come while it runs by the workers (``server.idle_in_process``); the workers' own tests turn
that off, so that every request reaches them."""

from __future__ import annotations

import os
import signal
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from service import settings as settings_module
from service.engine.sampling import sample_surface
from service.settings import ServerSettings, Settings
from tests.conftest import empty_server
from tests.frames import box, resting, shoot, spin
from tests.meshes import pybullet_mesh
from tests.servers import ProcessServer, eventually, needs_model

pytestmark = needs_model

PARTS = {"duck": "duck.obj", "mug": "objects/mug.obj"}
RAW = {"Content-Type": "application/octet-stream"}
APART = ((0.0, -1.0), (70.0, 1.0))  # two ducks' turns and places, in their sizes, on a table


def gauge(server, name: str) -> float:
    for line in server.client.get("/metrics").text.splitlines():
        if line.startswith(f"{name} "):
            return float(line.split()[1])
    raise AssertionError(f"no {name} in /metrics")


def register(server, name: str) -> dict:
    pybullet_data = pytest.importorskip("pybullet_data")
    path = Path(pybullet_data.getDataPath()) / PARTS[name]
    answer = server.client.post(
        "/references",
        data={"name": name},
        files={"file": (path.name, path.read_bytes())},
        params={"self_check": "false"},
    )
    assert answer.status_code == 201, answer.text[:500]
    return answer.json()


def posed(name: str, seed: int) -> np.ndarray:
    """The part's surface, resampled, turned and moved: a float32 cloud."""
    rng = np.random.default_rng(seed)
    points = sample_surface(pybullet_mesh(PARTS[name]), 2048, seed + 100)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    rotation = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    return (points @ rotation.T + rng.uniform(-0.2, 0.2, 3)).astype(np.float32)


def align(server, points: np.ndarray, **params):
    return server.client.post("/align", content=points.tobytes(), headers=RAW, params=params)


def workers(server: ProcessServer) -> list[int]:
    """The pids of the service's engine worker processes (its children that spawn_main runs)."""
    pid = server.process.process.pid
    children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    return [
        int(child)
        for child in children
        if b"spawn_main" in Path(f"/proc/{child}/cmdline").read_bytes()
    ]


@pytest.fixture(scope="module")
def servers(tmp_path_factory):
    """Two workers, and the service's own process alone, each with the duck registered."""
    pooled = pooled_server(tmp_path_factory.mktemp("processes"), 2, server__idle_in_process="false")
    alone = empty_server(tmp_path_factory.mktemp("alone"))
    try:
        eventually(lambda: assert_workers_up(pooled), 120, every_s=0.2)
        for server in (pooled, alone):
            register(server, "duck")
        yield pooled, alone
    finally:
        pooled.stop()
        alone.stop()


def pooled_server(data: Path, processes: int, **settings: str) -> ProcessServer:
    """``python -m service`` with ``processes`` engine workers and no seeded gallery."""
    return ProcessServer(
        data / "data",
        data / "service.log",
        model__gallery=str(data / "no-seed.npz"),
        server__engine_processes=str(processes),
        server__log_level="warning",
        **settings,
    )


def assert_workers_up(server, count: int = 2) -> None:
    assert gauge(server, "dpc_engine_processes") == count
    assert gauge(server, "dpc_engine_processes_wanted") == count


def test_the_workers_answer_as_the_services_own_process(servers):
    pooled, alone = servers
    jobs = gauge(pooled, "dpc_engine_process_jobs")
    for seed in range(3):
        points = posed("duck", seed)
        a, b = align(pooled, points), align(alone, points)
        assert a.status_code == b.status_code == 200, (a.text[:300], b.text[:300])
        a, b = a.json(), b.json()
        assert a["label"] == b["label"] == "duck"
        assert a["verdict"] == b["verdict"] and a["confidence"] == pytest.approx(b["confidence"])
        np.testing.assert_allclose(a["rotation"], b["rotation"], atol=1e-6)
        np.testing.assert_allclose(a["translation"], b["translation"], atol=1e-6)
    assert gauge(pooled, "dpc_engine_process_jobs") == jobs + 3  # the workers answered them


def test_a_registration_and_a_removal_reach_the_next_answer(servers):
    pooled, _ = servers
    register(pooled, "mug")
    try:
        answer = align(pooled, posed("mug", 7), candidates="mug")
        assert answer.status_code == 200, answer.text[:300]
        assert answer.json()["label"] == "mug"
    finally:
        assert pooled.client.delete("/references/mug").status_code == 204
    gone = align(pooled, posed("mug", 7), candidates="mug")
    assert gone.status_code == 404, gone.text[:300]  # the engine's error, from a worker
    assert "mug" in gone.json()["detail"]


def test_detect_runs_in_the_workers(servers):
    pooled, _ = servers
    jobs = gauge(pooled, "dpc_engine_process_jobs")
    answer = pooled.client.post(
        "/detect", content=posed("duck", 3).tobytes(), headers=RAW, params={"viewpoint": "0,0,-2"}
    )
    assert answer.status_code == 200, answer.text[:300]
    assert [d["label"] for d in answer.json()["detections"]] == ["duck"]
    assert gauge(pooled, "dpc_engine_process_jobs") == jobs + 1


def test_a_killed_worker_costs_no_request(servers):
    pooled, _ = servers
    before = workers(pooled)
    assert len(before) == 2
    os.kill(before[0], signal.SIGKILL)
    for seed in range(3):  # the first finds the pool broken and is answered in-process
        answer = align(pooled, posed("duck", 20 + seed))
        assert answer.status_code == 200, answer.text[:300]
        assert answer.json()["label"] == "duck"
    eventually(lambda: assert_workers_up(pooled), 120, every_s=0.2)
    after = workers(pooled)
    assert len(after) == 2 and before[0] not in after


def test_a_lone_request_is_answered_in_process_and_those_beside_it_by_the_workers(
    tmp_path_factory,
):
    server = pooled_server(tmp_path_factory.mktemp("idle"), 1)
    try:
        eventually(lambda: assert_workers_up(server, 1), 120, every_s=0.2)
        register(server, "duck")
        jobs = gauge(server, "dpc_engine_process_jobs")
        for seed in range(2):  # one at a time: no hop to the worker
            answer = align(server, posed("duck", 40 + seed))
            assert answer.status_code == 200 and answer.json()["label"] == "duck", answer.text
        assert gauge(server, "dpc_engine_process_jobs") == jobs
        # a lone frame is searched here, the first asks of its segments sent to the worker
        answer = server.client.post(
            "/detect",
            content=posed("duck", 3).tobytes(),
            headers=RAW,
            params={"viewpoint": "0,0,-2"},
        )
        assert answer.status_code == 200, answer.text[:300]
        assert [d["label"] for d in answer.json()["detections"]] == ["duck"]

        def asked_ahead() -> float:
            answered = gauge(server, "dpc_engine_process_jobs")
            assert answered > jobs
            return answered

        jobs = eventually(asked_ahead, 10, every_s=0.1)
        assert gauge(server, "dpc_engine_process_segments") == 0  # one segment: none there
        # a lone frame of two ducks apart on a table: two segments, one searched in the worker
        # while the other is here (docs/decisions.md#segments-on-two-cores)
        duck = pybullet_mesh(PARTS["duck"])
        size = float(np.ptp(duck.vertices, axis=0).max())
        placed = [(duck, *resting(duck, spin(turn), x * size, 0.0)) for turn, x in APART]
        floor = [box((6 * size, 6 * size, 0.02 * size), (0.0, 0.0, -0.01 * size))]  # its table
        shot = shoot(placed, floor, distance=5 * size)
        answer = server.client.post("/detect", files={"file": ("frame.pcd", shot.pcd())})
        assert answer.status_code == 200, answer.text[:300]
        assert gauge(server, "dpc_engine_process_segments") >= 1
        ducks = answer.json()["detections"]
        assert [d["label"] for d in ducks] == ["duck", "duck"]
        shown = [set(np.unique(shot.shows.reshape(-1)[d["indices"]])) - {-1} for d in ducks]
        assert sorted(map(sorted, shown)) == [[0], [1]]  # one each
        jobs = eventually(asked_ahead, 10, every_s=0.1)
        start = threading.Barrier(6)

        def together(seed: int):
            start.wait()
            return align(server, posed("duck", 50 + seed))

        with ThreadPoolExecutor(6) as pool:
            answers = list(pool.map(together, range(6)))
        assert all(a.status_code == 200 and a.json()["label"] == "duck" for a in answers)
        assert gauge(server, "dpc_engine_process_jobs") > jobs  # the worker took the others
    finally:
        server.stop()


@pytest.mark.parametrize(
    ("cores", "chosen", "processes", "slots"),
    [(1, None, 0, 2), (2, None, 2, 4), (16, None, 4, 8), (16, 0, 0, 2), (2, 3, 3, 6)],
)
def test_one_worker_a_core_by_default(monkeypatch, cores, chosen, processes, slots):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cores)), raising=False)
    monkeypatch.setattr(settings_module, "CGROUP_CPU", ())  # no container limit
    settings = Settings(server=ServerSettings(engine_processes=chosen))
    assert settings.engine_processes == processes
    assert settings.align_slots == slots  # a job queued behind each one running


@pytest.mark.parametrize(
    ("v2", "v1", "cores"),
    [
        ("200000 100000\n", None, 2),  # cgroup v2: 2 CPUs
        ("150000 100000\n", None, 2),  # 1.5 CPUs: the second is partly usable
        ("max 100000\n", None, 16),  # no limit
        (None, ("100000", "100000"), 1),  # cgroup v1: one CPU
        (None, ("-1", "100000"), 16),
        (None, None, 16),  # neither mounted
    ],
)
def test_a_containers_cpu_limit_caps_the_cores(monkeypatch, tmp_path, v2, v1, cores):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(16)), raising=False)
    files = (tmp_path / "cpu.max", (tmp_path / "quota", tmp_path / "period"))
    if v2 is not None:
        files[0].write_text(v2)
    if v1 is not None:
        files[1][0].write_text(v1[0])
        files[1][1].write_text(v1[1])
    limits = ((files[0], None), files[1])
    assert settings_module.usable_cores(limits) == cores
