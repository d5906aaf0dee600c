"""The engine's work, off the event loop: a bounded number at a time, queued briefly, timed.

At most ``limits.max_concurrent_align`` alignments run at once, each in a worker thread; a
request that finds every slot taken waits up to ``limits.queue_timeout_s`` and is then refused
(``Busy``: 503 with ``Retry-After``). Registrations and removals run one at a time in a lane of
their own, so a robot's alignments never queue behind an operator's upload.

Every job has a budget of ``limits.request_timeout_s``. Python cannot stop a thread, so when the
budget runs out the *request* stops waiting (``TimedOut``: 504) and the thread finishes on its
own. Its slot stays taken until it does, so abandoned work still counts against the limit and
a slow spell cannot pile up threads. A write is all or nothing across a timeout: the work calls
``job.commit()`` just before its durable step; a job the request has given up on refuses to
commit (nothing is stored), and a job that has committed is waited for to the end.
"""

from __future__ import annotations

import asyncio
import contextvars
import math
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, TypeVar

T = TypeVar("T")

WRITE_SLOTS = 1  # registrations and removals: one at a time


class Busy(RuntimeError):
    """Every slot was taken for the whole queue timeout (503, with ``Retry-After``)."""

    def __init__(self, message: str, retry_after_s: float):
        super().__init__(message)
        self.headers = {"Retry-After": str(max(1, math.ceil(retry_after_s)))}


class TimedOut(RuntimeError):
    """The work ran past the request's time budget (504); the thread finishes on its own."""


class Abandoned(RuntimeError):
    """Raised in the worker thread by ``Job.commit`` once the request has stopped waiting."""


class Job:
    """The handshake between one piece of work and the request waiting for it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._state = "running"  # -> "committed" (by the work) | "abandoned" (by the request)

    def commit(self) -> None:
        """Called by the work just before its durable step; raises if the request gave up."""
        with self._lock:
            if self._state == "abandoned":
                raise Abandoned("the request timed out before the change was stored")
            self._state = "committed"

    def abandon(self) -> bool:
        """Called by the request when its budget runs out: False if the work has committed."""
        with self._lock:
            if self._state == "committed":
                return False
            self._state = "abandoned"
            return True


class Limiter:
    """Slots for alignments and for writes, the threads that run them, and the time budget."""

    def __init__(self, align_slots: int, queue_timeout_s: float, request_timeout_s: float):
        self.align_slots = align_slots
        self.queue_timeout_s = queue_timeout_s
        self.request_timeout_s = request_timeout_s
        self.writing = 0  # write requests waiting for the lane or in it (a metric)
        self._align = asyncio.Semaphore(align_slots)
        self._write = asyncio.Semaphore(WRITE_SLOTS)
        # as many threads as slots: a job that holds a slot always finds a thread
        self._threads = ThreadPoolExecutor(align_slots + WRITE_SLOTS, thread_name_prefix="engine")

    async def align(self, work: Callable[..., T], *args: Any) -> T:
        """``work(*args)`` in an alignment slot, within the budget."""
        await self._acquire(self._align, self.queue_timeout_s, "alignment")
        return await self._run(self._align, None, work, *args, budget_s=self.request_timeout_s)

    async def write(self, work: Callable[..., T], *args: Any, budget_s: float | None = None) -> T:
        """``work(job, *args)`` in the write lane; ``work`` calls ``job.commit()`` before it
        stores anything. Waiting for the lane counts against the budget (``budget_s``, by
        default the request's: a batch of parts gets one a part)."""
        budget = budget_s or self.request_timeout_s
        self.writing += 1
        try:
            await self._acquire(self._write, budget, "write")
            job = Job()
            return await self._run(self._write, job, work, job, *args, budget_s=budget)
        finally:
            self.writing -= 1

    def close(self) -> None:
        """Stop taking work; threads still running finish on their own."""
        self._threads.shutdown(wait=False, cancel_futures=True)

    async def _acquire(self, slots: asyncio.Semaphore, wait_s: float, kind: str) -> None:
        try:
            async with asyncio.timeout(wait_s):
                await slots.acquire()
        except TimeoutError:
            raise Busy(
                f"the service is busy: every {kind} slot stayed taken for {wait_s:g} s; "
                "retry shortly",
                retry_after_s=max(wait_s, 1.0),
            ) from None

    async def _run(
        self,
        slots: asyncio.Semaphore,
        job: Job | None,
        work: Callable[..., T],
        *args: Any,
        budget_s: float,
    ) -> T:
        """Run in a thread holding an acquired slot; the slot is freed when the thread ends."""
        loop = asyncio.get_running_loop()
        try:  # the request's context (its id, for the logs) goes with the work
            future: Future[T] = self._threads.submit(contextvars.copy_context().run, work, *args)
        except BaseException:
            slots.release()
            raise
        future.add_done_callback(lambda _: _call_soon(loop, slots.release))
        try:
            async with asyncio.timeout(budget_s):
                return await asyncio.shield(asyncio.wrap_future(future))
        except TimeoutError:
            if job is None or job.abandon():
                raise TimedOut(
                    f"the request took longer than its budget of {budget_s:g} s "
                    "and was abandoned (nothing was changed); send fewer points or retry later"
                ) from None
        # the write committed before the budget ran out: its outcome is the answer
        return await asyncio.wrap_future(future)


def _call_soon(loop: asyncio.AbstractEventLoop, callback: Callable[[], Any]) -> None:
    try:
        loop.call_soon_threadsafe(callback)
    except RuntimeError:  # the loop has closed: nobody waits for the slot any more
        pass
