"""The tests' one harness: real servers on free loopback ports, and what the tests send them.

``Server(settings)`` serves ``create_app(settings)`` with uvicorn in a thread of this process, so
a test can reach the app it talks to; ``ProcessServer`` runs ``python -m service`` as a child
process instead, for the tests that kill it, restart it or read its logs. Both wait for the
service with ``evaluation.served.wait_ready``, the one wait-until-ready loop, and carry an
``httpx`` client. ``MODEL`` is the model and seed gallery the environment names
(``DPC_MODEL__PATH`` / ``DPC_MODEL__GALLERY`` honoured).
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import httpx
import numpy as np
import pytest
import uvicorn

from evaluation import served
from evaluation.served import REPO, ServiceProcess, eventually, free_port, wait_ready
from service.api.app import create_app
from service.settings import Settings

__all__ = [
    "ADMIN_KEY",
    "MODEL",
    "READ_KEY",
    "REPO",
    "ProcessServer",
    "Server",
    "ServiceProcess",
    "cloud",
    "eventually",
    "free_port",
    "needs_model",
    "run_service",
    "wait_ready",
]

# The tests' servers answer in their own process unless a test asks for worker processes
# (tests/api/test_engine_processes.py): each worker loads the model, seconds a server.
os.environ.setdefault("DPC_SERVER__ENGINE_PROCESSES", "0")
MODEL = Settings().model  # the model and seed gallery the environment names
ADMIN_KEY, READ_KEY = "tests-admin-key-0123", "tests-read-key-4567"  # conftest's keyed_service
needs_model = pytest.mark.skipif(
    not MODEL.path.exists(),
    reason=f"no ONNX model at {MODEL.path} (export one, or set DPC_MODEL__PATH)",
)


def cloud(count: int = 300, seed: int = 0, spread=(0.1, 0.2, 0.3)) -> np.ndarray:
    """``count`` float32 points of a Gaussian blob ``spread`` metres wide along x, y and z: a
    valid cloud of no particular part, the same for the same seed."""
    rng = np.random.default_rng(seed)
    return (rng.normal(size=(count, 3)) * spread).astype(np.float32)


class Server:
    """``create_app(settings)`` served by uvicorn in a thread of this process, with a client.

    Ready once ``/v2/health/ready`` answers 200, or with ``ready=False`` once the service
    answers at all (a test that watches the gallery load, or fail to)."""

    def __init__(
        self, settings: Settings, headers: dict[str, str] | None = None, ready: bool = True
    ):
        self.settings = settings
        self.app = create_app(settings)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        config = uvicorn.Config(self.app, host="127.0.0.1", port=self.port, log_level="warning")
        self._uvicorn = uvicorn.Server(config)
        self._thread = threading.Thread(target=self._uvicorn.run, daemon=True)
        self._thread.start()
        self._connect(headers, ready)

    def _connect(self, headers: dict[str, str] | None, ready: bool) -> None:
        self.client = httpx.Client(base_url=self.url, timeout=60.0, headers=headers)
        try:
            wait_ready(self.url, self.alive, timeout=120.0, live_only=not ready, log=self.log)
        except BaseException:
            self.kill()
            raise

    def alive(self) -> bool:
        return self._thread.is_alive()

    def log(self) -> str:
        return ""  # the app logs to this process's own logging

    def stop(self) -> None:
        self.client.close()
        self._uvicorn.should_exit = True
        self._thread.join(timeout=10)

    kill = stop  # a thread cannot be killed: stopped, as a process would be

    def __enter__(self) -> Server:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


class ProcessServer(Server):
    """``python -m service`` as a child process (``ServiceProcess``), with a client; stderr (the
    logs) goes to ``log_path``. For the tests that kill it with SIGKILL, restart it on the same
    data, or read its logs. ``settings`` as ``ServiceProcess`` takes them."""

    def __init__(self, data_dir: Path, log_path: Path, headers=None, **settings: str):
        settings.setdefault("server__engine_processes", os.environ["DPC_SERVER__ENGINE_PROCESSES"])
        self.process = ServiceProcess(
            log_path, wait=False, gallery__data_dir=str(data_dir), **settings
        )
        self.port, self.url = self.process.port, self.process.url
        self._connect(headers, ready=True)

    def alive(self) -> bool:
        return self.process.alive()

    def log(self) -> str:
        return self.process.log()

    def stop(self) -> None:
        """SIGTERM, as an orchestrator stops it."""
        self.process.stop()
        self.client.close()

    def kill(self) -> None:
        """SIGKILL: as a power cut looks to the process."""
        self.process.kill()
        self.client.close()


def run_service(data_dir: Path, timeout_s: float = 60, **settings: str):
    """``python -m service`` expected to stop at its startup checks: the completed process."""
    return served.run_service(timeout_s, gallery__data_dir=str(data_dir), **settings)
