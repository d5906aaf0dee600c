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
from service.api import limiter as limiter_module
from service.api.limiter import Abandoned, Busy, Job, Limiter, TimedOut
from service.engine.engine import Engine
from service.engine.mapping import Mapper
from service.settings import GallerySettings, LimitSettings, Settings
from tests.servers import MODEL, Server, cloud, eventually, needs_model


class Held:
    """Work that holds its slot until the test releases it: ``started`` is set once it runs in
    its worker thread, ``finished`` once it has returned (or raised)."""

    def __init__(self, value: object = None):
        self.value = value
        self.started, self.released, self.finished = (threading.Event() for _ in range(3))

    def __call__(self, *args):
        self.started.set()
        try:
            assert self.released.wait(30), "the test never released the work"
            return self.value
        finally:
            self.finished.set()


async def until(event: threading.Event, timeout: float = 30.0) -> None:
    """Wait for a worker thread's event without blocking the event loop."""
    assert await asyncio.to_thread(event.wait, timeout), "the event never came"


async def once_free(limiter: Limiter, work, timeout: float = 30.0):
    """``limiter.align(work)`` once a slot is free: a slot is given back just after its thread
    returns, so a request right after may still find it taken (``Busy``) for an instant."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return await limiter.align(work)
        except Busy:
            if time.monotonic() > deadline:
                raise


def run(coroutine):
    return asyncio.run(coroutine)


# --- the limiter alone ------------------------------------------------------------------


def test_a_request_that_finds_every_slot_taken_waits_then_gets_busy():
    async def scenario():
        limiter = Limiter(align_slots=1, queue_timeout_s=0.1, request_timeout_s=5)
        held = Held("first")  # holds the slot until the second is refused
        first = asyncio.create_task(limiter.align(held))
        await until(held.started)
        with pytest.raises(Busy) as busy:
            await limiter.align(lambda: "second")
        assert not first.done()  # refused while the slot was still taken, not after it
        assert busy.value.headers == {"Retry-After": "1"}
        assert "busy" in str(busy.value)
        held.released.set()
        assert await first == "first"
        # the slot is given back before the answer is: free again at once
        assert await limiter.align(lambda: "third") == "third"
        limiter.close()

    run(scenario())


def test_requests_within_the_slots_and_queue_all_run():
    """Six requests on two slots: each pair runs at once (a barrier for two passes only when
    both slots are in use together), the others wait in the queue."""
    both = threading.Barrier(2, timeout=30)

    def work(index: int) -> int:
        both.wait()
        return index

    async def scenario():
        limiter = Limiter(align_slots=2, queue_timeout_s=30, request_timeout_s=60)
        results = await asyncio.gather(*(limiter.align(work, i) for i in range(6)))
        assert results == list(range(6))
        limiter.close()

    run(scenario())


def test_a_timed_out_request_stops_waiting_but_its_thread_keeps_the_slot():
    async def scenario():
        limiter = Limiter(align_slots=1, queue_timeout_s=0.05, request_timeout_s=0.2)
        held = Held()  # runs past the budget: released only after the request has given up
        with pytest.raises(TimedOut, match="budget of 0.2 s"):
            await limiter.align(held)
        assert held.started.is_set() and not held.finished.is_set()
        with pytest.raises(Busy):  # the abandoned thread still runs: its slot is taken
            await limiter.align(lambda: None)
        held.released.set()
        await until(held.finished)  # it finishes on its own ...
        assert await once_free(limiter, lambda: "after") == "after"  # ... and frees its slot
        limiter.close()

    run(scenario())


def test_a_write_abandoned_by_a_timeout_never_commits():
    outcome, finished = [], threading.Event()
    released = threading.Event()  # only once the request has timed out

    def register(job, name):
        try:
            assert released.wait(30), "the test never released the write"
            job.commit()  # the durable step's gate: refused once the request has given up
            outcome.append(f"stored {name}")
        except Abandoned:
            outcome.append("refused")
            raise
        finally:
            finished.set()

    async def scenario():
        limiter = Limiter(align_slots=1, queue_timeout_s=1, request_timeout_s=0.1)
        with pytest.raises(TimedOut):
            await limiter.write(register, "late")
        released.set()
        await until(finished)
        limiter.close()

    run(scenario())
    assert outcome == ["refused"]


def test_a_write_that_committed_is_waited_for_past_the_budget(monkeypatch):
    """The write commits, then goes on until the request's budget has run out and the request
    has tried to give up on it: the request waits for its outcome instead of a 504."""

    class Watched(Job):  # the real handshake, telling the write when the request gave up
        def __init__(self):
            super().__init__()
            self.gave_up = threading.Event()

        def abandon(self) -> bool:
            abandoned = super().abandon()
            self.gave_up.set()
            return abandoned

    monkeypatch.setattr(limiter_module, "Job", Watched)

    def register(job, name):
        job.commit()
        assert job.gave_up.wait(30), "the budget never ran out"
        return name

    async def scenario():
        limiter = Limiter(align_slots=1, queue_timeout_s=1, request_timeout_s=0.1)
        assert await limiter.write(register, "kept") == "kept"
        limiter.close()

    run(scenario())


def test_writes_do_not_queue_behind_alignments():
    async def scenario():
        limiter = Limiter(align_slots=1, queue_timeout_s=0.05, request_timeout_s=5)
        held = Held(True)  # the alignment may finish only once the write has answered
        busy = asyncio.create_task(limiter.align(held))
        await until(held.started)
        assert await limiter.write(lambda job: "written") == "written"
        assert not busy.done()
        held.released.set()
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


class HeldCall:
    """A real engine call that waits, once it has started, until the test releases it."""

    def __init__(self, original):
        self.original = original
        self.started, self.released, self.finished = (threading.Event() for _ in range(3))

    def __call__(self, *args, **kwargs):
        self.started.set()
        try:
            assert self.released.wait(60), "the test never released the call"
            return self.original(*args, **kwargs)
        finally:
            self.finished.set()


@needs_model
def test_busy_and_timed_out_answers_over_http(tight, monkeypatch):
    engine = tight.app.state.catalog.engine
    held = HeldCall(engine.align)  # held until after its request has run out of budget
    monkeypatch.setattr(engine, "align", held)
    body = {"points": cloud(200).tolist()}
    with ThreadPoolExecutor(1) as pool:
        slow = pool.submit(tight.client.post, "/align", json=body)
        assert held.started.wait(60), "the first alignment never started"
        refused = tight.client.post("/align", json=body)
        still_running = not slow.done()
        timed_out = slow.result()
    assert refused.status_code == 503, refused.text
    assert refused.headers["retry-after"] == "1" and "busy" in refused.json()["detail"]
    assert still_running  # refused while the slow alignment held the slot, not after it
    assert timed_out.status_code == 504, timed_out.text
    assert "budget of 2 s" in timed_out.json()["detail"]
    assert not held.finished.is_set()  # the request gave up; the alignment still runs
    held.released.set()
    assert held.finished.wait(60)  # the abandoned alignment finishes on its own ...
    monkeypatch.setattr(engine, "align", held.original)

    def answered() -> None:  # ... and frees its slot, an instant after it returns
        assert tight.client.post("/align", json=body).status_code == 200

    eventually(answered, timeout=30)


@needs_model
def test_a_registration_that_times_out_stores_nothing(tight, monkeypatch):
    catalog = tight.app.state.catalog
    held = HeldCall(catalog.engine.make_reference)  # past the budget: released after the 504
    monkeypatch.setattr(catalog.engine, "make_reference", held)
    register, outcome, ended = catalog.register, [], threading.Event()

    def watched_register(*args, **kwargs):  # the real registration; the test sees how it ended
        try:
            result = register(*args, **kwargs)
            outcome.append("stored")
            return result
        except Abandoned:
            outcome.append("refused")
            raise
        finally:
            ended.set()

    monkeypatch.setattr(catalog, "register", watched_register)
    body = {"name": "late", "points": cloud(300).tolist()}
    response = tight.client.post("/references", json=body)
    assert response.status_code == 504, response.text
    assert held.started.is_set() and not ended.is_set()
    held.released.set()
    assert ended.wait(60), "the abandoned registration never ended"
    assert outcome == ["refused"]  # it reached the durable step and was refused there
    assert tight.client.get("/references/late").status_code == 404
    assert tight.client.get("/v2/health/ready").status_code == 200


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
