"""``python -m service`` as a child process on a free loopback port: the one way the evaluation,
the benchmarks, the load script and the tests start a real server, wait for it and stop it.
``wait_ready`` is the one wait-until-ready loop (the tests' in-thread servers use it too), built
on ``eventually``, the one polling loop.

Settings go in as keyword arguments named like the environment variables without their prefix
(``gallery__data_dir="..."`` is ``DPC_GALLERY__DATA_DIR``). The model and seed gallery default
to the ones the caller's environment names, so ``DPC_MODEL__PATH`` reaches the server.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import httpx

from service.engine.reference import Reference
from service.gallery.sqlite_store import SQLiteStore
from service.settings import Settings

REPO = Path(__file__).resolve().parent.parent


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def service_env(port: int, inherit: bool = False, **settings: str) -> dict[str, str]:
    """The server's environment: this process's, with its other ``DPC_`` settings kept only if
    ``inherit``; then the model this environment names, the loopback port and ``settings``."""
    model = Settings().model
    env = {k: v for k, v in os.environ.items() if inherit or not k.startswith("DPC_")}
    env |= {
        "DPC_MODEL__PATH": str(model.path),
        "DPC_MODEL__GALLERY": str(model.gallery),
        "DPC_SERVER__HOST": "127.0.0.1",
        "DPC_SERVER__PORT": str(port),
        "PYTHONUNBUFFERED": "1",
    }
    return env | {f"DPC_{key.upper()}": str(value) for key, value in settings.items()}


T = TypeVar("T")
RETRIED = (AssertionError, httpx.TransportError)
GALLERY_FAILED = ("loading the gallery failed", "the gallery store is")  # /v2/health/ready


def eventually(
    check: Callable[[], T],
    timeout: float,
    retried: tuple[type[BaseException], ...] = RETRIED,
    every_s: float = 0.02,
) -> T:
    """``check()``'s value once it returns without raising one of ``retried`` (by default an
    AssertionError, or a refused connection: a server starting), tried every ``every_s`` until
    ``timeout`` seconds have passed; then its last error is raised."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return check()
        except retried:
            if time.monotonic() > deadline:
                raise
        time.sleep(every_s)


class NotReady(AssertionError):
    """The service answers, but not yet that it is ready."""


def wait_ready(
    url: str,
    alive: Callable[[], bool],
    timeout: float = 120.0,
    live_only: bool = False,
    log: Callable[[], str] = str,
) -> None:
    """Until the service at ``url`` is ready (``/v2/health/ready`` answers 200), or with
    ``live_only`` until it answers at all (``/v2/health/live``): the one wait-until-ready loop.
    Raises ``RuntimeError`` with ``log()`` (the log's tail) once ``alive()`` is False or the
    gallery has failed to load, ``TimeoutError`` after ``timeout`` seconds."""
    path = "/v2/health/live" if live_only else "/v2/health/ready"
    with httpx.Client(base_url=url, timeout=5.0) as client:

        def answered() -> None:
            if not alive():
                raise RuntimeError(f"the service exited:\n{log()}")
            answer = client.get(path)
            if answer.status_code == 200:
                return
            detail = answer.json().get("detail") or ""
            if detail.startswith(GALLERY_FAILED):
                raise RuntimeError(f"the gallery did not load: {detail}\n{log()}")
            raise NotReady(detail)

        try:
            eventually(answered, timeout, (NotReady, httpx.TransportError), every_s=0.05)
        except (NotReady, httpx.TransportError) as error:
            raise TimeoutError(
                f"the service was not ready in {timeout:.0f} s ({error!r})\n{log()}"
            ) from None


class ServiceProcess:
    """``python -m service`` with its log in ``log_path``; ready once ``/v2/health/ready`` is 200.

    ``wait=False`` returns at once (call ``wait_ready``); a context manager stops it on exit.
    """

    def __init__(
        self,
        log_path: Path,
        ready_timeout: float = 120.0,
        inherit: bool = False,
        wait: bool = True,
        port: int | None = None,  # default: a free one (a replica started again: its old one)
        **settings: str,
    ):
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = Path(log_path)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self.began = time.perf_counter()
        with open(self.log_path, "ab") as log:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "service"],
                cwd=REPO,
                env=service_env(self.port, inherit, **settings),
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        self.ready_s: float | None = None
        if wait:
            try:
                self.wait_ready(ready_timeout)
            except BaseException:
                self.kill()
                raise

    @property
    def pid(self) -> int:
        return self.process.pid

    def alive(self) -> bool:
        return self.process.poll() is None

    def wait_ready(self, timeout: float = 120.0) -> None:
        """Until ``/v2/health/ready`` answers 200 (``wait_ready``) and the engine's worker
        processes answer (``dpc_engine_processes``); notes how long it took."""
        wait_ready(self.url, self.alive, timeout, log=self.log)
        eventually(self.processes_up, timeout, (NotReady, httpx.TransportError), every_s=0.1)
        self.ready_s = time.perf_counter() - self.began

    def processes_up(self) -> None:
        """Raises NotReady until every engine worker process answers."""
        gauges = {}
        for line in httpx.get(f"{self.url}/metrics", timeout=5).text.splitlines():
            name, _, value = line.partition(" ")
            if name in ("dpc_engine_processes", "dpc_engine_processes_wanted"):
                gauges[name] = float(value)
        ready = gauges.get("dpc_engine_processes", 0)
        if ready < gauges.get("dpc_engine_processes_wanted", 0):
            raise NotReady(f"engine worker processes: {ready:g} of {gauges}")

    def log(self, lines: int = 30) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""

    def stop(self) -> None:
        """SIGTERM, then SIGKILL if it has not ended in 15 s."""
        if self.alive():
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.process.kill()
        self.process.wait(timeout=10)

    def kill(self) -> None:
        """SIGKILL: as a power cut looks to the process."""
        if self.alive():
            self.process.send_signal(signal.SIGKILL)
        self.process.wait(timeout=10)

    def __enter__(self) -> ServiceProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def run_service(timeout_s: float = 60, **settings: str) -> subprocess.CompletedProcess:
    """``python -m service`` expected to stop at its start-up checks: the completed process."""
    return subprocess.run(
        [sys.executable, "-m", "service"],
        cwd=REPO,
        env=service_env(free_port(), **settings),
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


def seed_store(data_dir: Path, references: list[Reference], model_hash: str) -> None:
    """Write the references into a fresh store, marked seeded so the service adds nothing."""
    data_dir.mkdir(parents=True, exist_ok=True)
    SQLiteStore.in_dir(data_dir).seed(references, model_hash, "evaluation.served")
