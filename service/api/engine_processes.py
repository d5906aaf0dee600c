"""The engine's alignments and detections in processes of their own, so a second core answers.

One interpreter runs one alignment's Python at a time (its GIL). With
``server.engine_processes`` above 0, ``/align`` and ``/detect`` run in that many worker
processes, spawned once the gallery has loaded. Each worker holds its own model session and its
own copy of the gallery, read from the store. Before every job it reads the store's version (one
small query) and follows what changed, so an answer never trails a change the service has
acknowledged. Until the workers are up, and while a pool that lost a worker is replaced, the job
runs in this process as before: nothing is refused for it. A job that finds no other in the
engine runs here too (``server.idle_in_process``), after the same check of the store's version:
one request at a time, as a cell sends them, pays no hop to a worker and back. Parsing, the time
budget, the console's recent alignments and the metrics stay here
(docs/decisions.md#a-second-core).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import threading
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from service import memory
from service.api import logs, startup
from service.engine import kernels
from service.engine.engine import Engine
from service.errors import StoreUnavailable
from service.gallery.catalog import Catalog
from service.settings import Settings

log = logging.getLogger(__name__)

START_TIMEOUT_S = 600.0  # for the workers to load the model and the gallery


class EngineProcesses:
    """``align`` and ``detect`` as the engine's, run in the worker processes once they are up."""

    def __init__(self, catalog: Catalog, settings: Settings, count: int):
        self.catalog = catalog  # this process's: the work until the workers are up, and alone
        self.settings = settings
        self.count = count
        self.jobs = 0  # jobs the workers answered (a metric)
        self.segments = 0  # ... of which a lone frame's segments searched there (a metric)
        self.failed = False  # the workers could not start: this process answers
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()
        self._closed = False
        self._running = 0  # jobs in the engine now, here or in the workers
        self._seen: int | None = None  # the store's version this process's job last followed

    @property
    def ready(self) -> int:
        """How many worker processes answer jobs now."""
        return self.count if self._pool is not None else 0

    @property
    def wanted(self) -> int:
        """How many worker processes are meant to answer (0 once they could not start)."""
        return 0 if self.failed else self.count

    def start(self) -> None:
        """Spawn the workers and wait until each has loaded the model and the gallery (the
        gallery's loading thread calls it, after this process's own load)."""
        if not self.count or self._closed:
            return
        context = multiprocessing.get_context("spawn")  # no fork of a process with threads
        started = context.Barrier(self.count)  # a job waits until every worker has loaded
        pool = ProcessPoolExecutor(
            self.count, mp_context=context, initializer=_start, initargs=(self.settings, started)
        )
        try:
            pids = {future.result() for future in [pool.submit(_pid) for _ in range(self.count)]}
        except Exception:  # a worker that cannot start: this process answers, as without them
            log.exception("the engine's worker processes did not start; answering in-process")
            pool.shutdown(wait=False, cancel_futures=True)
            self.failed = True
            return
        with self._lock:
            if self._closed:
                pool.shutdown(wait=False, cancel_futures=True)
                return
            self._pool = pool
            self.failed = False
        log.info("engine worker processes ready: %d (pids %s)", self.count, sorted(pids))

    def close(self) -> None:
        with self._lock:
            self._closed = True
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)

    def align(self, *args: Any, **kwargs: Any):
        return self._run("align", args, kwargs)

    def detect(self, *args: Any, **kwargs: Any):
        return self._run("detect", args, kwargs)

    def _run(self, method: str, args: tuple, kwargs: dict):
        pool = self._pool
        with self._lock:
            alone = self._running == 0 and self.settings.server.idle_in_process
            self._running += 1
        try:
            if pool is not None and not alone:
                try:
                    result = pool.submit(_job, method, args, kwargs).result()
                except BrokenProcessPool:  # a worker died (killed, out of memory): start again
                    self._replace(pool)
                else:
                    self.jobs += 1
                    return result
            if pool is not None:  # answered here while the workers are up: as current as theirs
                self._seen = _follow(self.catalog, self._seen)
                if method == "detect":  # the idle workers answer its segments' first asks
                    kwargs = {**kwargs, "submit": self._submitter(pool)}
            return _call(self.catalog.engine, method, args, kwargs)
        finally:
            with self._lock:
                self._running -= 1

    def _submitter(self, pool: ProcessPoolExecutor) -> Callable[..., Future]:
        """An engine's method in the workers, by name, answering a future: ``Engine.detect``'s
        ``submit`` (docs/decisions.md#detect-on-two-cores)."""

        def submit(method: str, *args: Any, **kwargs: Any) -> Future:
            future = pool.submit(_job, method, args, kwargs)
            future.add_done_callback(lambda done: self._answered(done, method))
            return future

        return submit

    def _answered(self, future: Future, method: str) -> None:
        if not future.cancelled() and future.exception() is None:
            with self._lock:
                self.jobs += 1
                self.segments += method == "search_segments"

    def _replace(self, broken: ProcessPoolExecutor) -> None:
        """Drop a pool that lost a worker and start a new one in the background; until it is
        up, this process answers."""
        with self._lock:
            if self._pool is not broken:  # another request's thread got here first
                return
            self._pool = None
        log.error("an engine worker process died; answering in-process while new ones start")
        broken.shutdown(wait=False, cancel_futures=True)
        threading.Thread(target=self.start, name="engine-processes", daemon=True).start()


# --- in each worker process -----------------------------------------------------------------

_catalog: Catalog | None = None
_seen: int | None = None  # the store's version the worker's gallery has followed


def _start(settings: Settings, started: threading.Barrier) -> None:
    """A worker's start: the model, the calibrations and the gallery as the service loads them;
    it ends with the process that spawned it."""
    global _catalog, _seen
    logs.configure(settings.server.log_level, settings.server.log_format)
    memory.fix_mmap_threshold()
    startup.quiet_onnxruntime()
    _watch_parent()
    mapper, store = startup.prepare(settings)
    engine = startup.make_engine(settings, mapper)
    kernels.warm()
    catalog = Catalog(engine, store, settings.gallery.max_references)
    _seen = store.version()
    catalog.load(None, writer=False)  # the service has seeded and refreshed the store
    _catalog = catalog
    started.wait(START_TIMEOUT_S)


def _pid() -> int:
    return os.getpid()


def _job(method: str, args: tuple, kwargs: dict):
    """The engine's ``method`` on the gallery as the store holds it now."""
    global _seen
    _seen = _follow(_catalog, _seen)
    return _call(_catalog.engine, method, args, kwargs)


def _call(engine: Engine, method: str, args: tuple, kwargs: dict):
    """The engine's ``method``, here or in a worker; a frame's detection with the heap's
    thresholds raised (docs/decisions.md#the-heaps-thresholds)."""
    if method not in ("detect", "search_segments"):
        return getattr(engine, method)(*args, **kwargs)
    with memory.frame_heap():
        return getattr(engine, method)(*args, **kwargs)


def _follow(catalog: Catalog, seen: int | None) -> int | None:
    """The catalog brought up to the store's version if it moved since ``seen``; the version
    followed. While the store is down nothing can change: the job answers on what is held."""
    try:
        version = catalog.store.version()
        if version != seen:
            catalog.sync()
        return version
    except StoreUnavailable:
        log.warning("the gallery store cannot be reached; answering on the gallery held")
        return seen


def _watch_parent() -> None:
    """End this worker when the service's process ends, killed or not (no orphan holds the
    store's connections or the memory)."""
    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        parent.join()
        os._exit(0)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()
