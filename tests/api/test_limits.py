"""Limits: slots and the queue (503 + Retry-After), the time budget (504), points, bodies and
the number of references. The limiter alone first, then over HTTP against a real server."""

from __future__ import annotations

import asyncio
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from evaluation.served import seed_store
from service.api.limiter import Abandoned, Busy, Job, Limiter, TimedOut
from service.engine.engine import Engine
from service.engine.mapping import Mapper
from service.settings import GallerySettings, LimitSettings, Settings
from tests.servers import MODEL, Server, cloud, needs_model


def sleeper(seconds: float, value: object = None):
    def work(*args):
        time.sleep(seconds)
        return value

    return work


def run(coroutine):
    return asyncio.run(coroutine)


# --- the limiter alone ------------------------------------------------------------------


def test_a_request_that_finds_every_slot_taken_waits_then_gets_busy():
    async def scenario():
        limiter = Limiter(align_slots=1, queue_timeout_s=0.1, request_timeout_s=5)
        gate = threading.Event()  # the first job holds the slot until the second is refused
        first = asyncio.create_task(limiter.align(lambda: gate.wait(10) and "first"))
        await asyncio.sleep(0.05)
        with pytest.raises(Busy) as busy:
            await limiter.align(sleeper(0, "second"))
        assert not first.done()  # refused while the slot was still taken, not after it
        assert busy.value.headers == {"Retry-After": "1"}
        assert "busy" in str(busy.value)
        gate.set()
        assert await first == "first"
        assert await limiter.align(sleeper(0, "third")) == "third"  # the slot is free again
        limiter.close()

    run(scenario())


def test_requests_within_the_slots_and_queue_all_run():
    async def scenario():
        limiter = Limiter(align_slots=2, queue_timeout_s=2, request_timeout_s=5)
        results = await asyncio.gather(*(limiter.align(sleeper(0.1, i)) for i in range(6)))
        assert results == list(range(6))
        limiter.close()

    run(scenario())


def test_a_timed_out_request_stops_waiting_but_its_thread_keeps_the_slot():
    async def scenario():
        limiter = Limiter(align_slots=1, queue_timeout_s=0.05, request_timeout_s=0.2)
        done = threading.Event()

        def slow():
            time.sleep(0.6)
            done.set()

        with pytest.raises(TimedOut, match="budget of 0.2 s"):
            await limiter.align(slow)
        assert not done.is_set()  # the request stopped waiting before the work ended
        with pytest.raises(Busy):  # the abandoned thread still runs: its slot is taken
            await limiter.align(sleeper(0))
        await asyncio.sleep(0.6)
        assert done.is_set()  # it finished on its own
        assert await limiter.align(sleeper(0, "after")) == "after"
        limiter.close()

    run(scenario())


def test_a_write_abandoned_by_a_timeout_never_commits():
    stored = []

    def register(job, name):
        time.sleep(0.4)  # the slow part, before the durable step
        job.commit()
        stored.append(name)

    async def scenario():
        limiter = Limiter(align_slots=1, queue_timeout_s=1, request_timeout_s=0.1)
        with pytest.raises(TimedOut):
            await limiter.write(register, "late")
        await asyncio.sleep(0.5)
        limiter.close()

    run(scenario())
    assert stored == []


def test_a_write_that_committed_is_waited_for_past_the_budget():
    def register(job, name):
        job.commit()
        time.sleep(0.3)  # after the durable step: the request waits for the outcome
        return name

    async def scenario():
        limiter = Limiter(align_slots=1, queue_timeout_s=1, request_timeout_s=0.1)
        assert await limiter.write(register, "kept") == "kept"
        limiter.close()

    run(scenario())


def test_writes_do_not_queue_behind_alignments():
    gate = threading.Event()  # the alignment may finish only once the write has answered

    async def scenario():
        limiter = Limiter(align_slots=1, queue_timeout_s=0.05, request_timeout_s=5)
        busy = asyncio.create_task(limiter.align(lambda: gate.wait(10)))
        await asyncio.sleep(0.05)
        assert await limiter.write(lambda job: "written") == "written"
        assert not busy.done()
        gate.set()
        assert await busy
        limiter.close()

    run(scenario())


def test_an_abandoned_job_refuses_to_commit():
    job = Job()
    assert job.abandon()
    with pytest.raises(Abandoned):
        job.commit()
    committed = Job()
    committed.commit()
    assert not committed.abandon()


# --- over HTTP ----------------------------------------------------------------------------

MAX_POINTS, MAX_BODY = 5_000, 256 * 1024


def limited_server(data_dir: Path, budget_s: float) -> Server:
    """One alignment at a time, a short queue, the request budget given; the gallery holds one
    reference, ``base``, written into its store before it starts (a registration computes
    views, a distance field and a symmetry: longer than a tight budget on a busy machine)."""
    engine = Engine(Mapper(MODEL.path, use_cuda=False))
    base = engine.make_reference("base", cloud(400))
    seed_store(data_dir, [base], engine.mapper.model_hash)
    settings = Settings(
        model=MODEL.model_copy(update={"gallery": data_dir / "no-seed.npz"}),
        gallery=GallerySettings(data_dir=data_dir, self_check_poses=0, max_references=2),
        limits=LimitSettings(
            min_points=50,
            max_points=MAX_POINTS,
            max_body_bytes=MAX_BODY,
            max_concurrent_align=1,
            queue_timeout_s=0.3,
            request_timeout_s=budget_s,
        ),
    )
    return Server(settings)


@pytest.fixture(scope="module")
def tight(tmp_path_factory):
    """A budget of 2 s: for what happens when a request runs past it."""
    server = limited_server(tmp_path_factory.mktemp("tight"), 2.0)
    yield server
    server.stop()


@pytest.fixture(scope="module")
def limited(tmp_path_factory):
    """A budget that registrations fit in: for the limits on points, bodies and references."""
    server = limited_server(tmp_path_factory.mktemp("limited"), 60.0)
    yield server
    server.stop()


@needs_model
def test_busy_and_timed_out_answers_over_http(tight, monkeypatch):
    limited = tight
    engine = limited.app.state.catalog.engine
    original, finished = engine.align, threading.Event()

    def slow_align(*args, **kwargs):
        time.sleep(2.5)
        try:
            return original(*args, **kwargs)
        finally:
            finished.set()

    monkeypatch.setattr(engine, "align", slow_align)
    body = {"points": cloud(200).tolist()}
    with ThreadPoolExecutor(2) as pool:
        slow = pool.submit(limited.client.post, "/align", json=body)
        time.sleep(0.2)
        refused = limited.client.post("/align", json=body)
        still_running = not slow.done()
        timed_out = slow.result()
    assert refused.status_code == 503, refused.text
    assert refused.headers["retry-after"] == "1" and "busy" in refused.json()["detail"]
    assert still_running  # refused while the slow alignment held the slot, not after it
    assert timed_out.status_code == 504, timed_out.text
    assert "budget of 2 s" in timed_out.json()["detail"]
    assert finished.wait(60)  # the abandoned alignment finishes on its own and frees its slot
    monkeypatch.setattr(engine, "align", original)
    assert limited.client.post("/align", json=body).status_code == 200


@needs_model
def test_a_registration_that_times_out_stores_nothing(tight, monkeypatch):
    limited = tight
    engine = limited.app.state.catalog.engine
    original = engine.make_reference

    def slow_reference(*args, **kwargs):
        time.sleep(2.6)
        return original(*args, **kwargs)

    monkeypatch.setattr(engine, "make_reference", slow_reference)
    body = {"name": "late", "points": cloud(300).tolist()}
    response = limited.client.post("/references", json=body)
    assert response.status_code == 504, response.text
    time.sleep(2.0)  # the thread has finished by now, and refused to commit
    assert limited.client.get("/references/late").status_code == 404
    monkeypatch.setattr(engine, "make_reference", original)
    assert limited.client.get("/v2/health/ready").status_code == 200


@needs_model
def test_point_body_and_gallery_limits(limited):
    client = limited.client
    few = client.post("/align", json={"points": cloud(49).tolist()})
    assert few.status_code == 422 and "minimum of 50" in few.json()["detail"]
    many = client.post("/align", json={"points": cloud(MAX_POINTS + 1).tolist()})
    assert many.status_code in (413, 422)  # whichever limit the body meets first
    raw = client.post(
        "/align",
        content=cloud(MAX_POINTS + 1).tobytes(),
        headers={"content-type": "application/octet-stream"},
    )
    assert raw.status_code == 422 and "maximum of 5000" in raw.json()["detail"]
    big = client.post(
        "/align",
        content=b"\0" * (MAX_BODY + 12),
        headers={"content-type": "application/octet-stream"},
    )
    assert big.status_code == 413 and "limit" in big.json()["detail"]
    first = client.post("/references", json={"name": "last-one", "points": cloud(300).tolist()})
    assert first.status_code == 201, first.text
    full = client.post("/references", json={"name": "one-more", "points": cloud(300).tolist()})
    assert full.status_code == 409 and "maximum" in full.json()["detail"]
    assert client.delete("/references/last-one").status_code == 204
