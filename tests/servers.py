"""Real servers for the hardening tests: the app in a uvicorn thread, or ``python -m service``.

Both listen on a free loopback port with their own data directory and use the model that the
settings name (``DPC_MODEL__PATH`` / ``DPC_MODEL__GALLERY`` honoured, as in test_api).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import uvicorn

from evaluation import served
from evaluation.served import REPO, ServiceProcess, free_port  # noqa: F401 - REPO for tests
from service.api.app import create_app
from service.settings import Settings

MODEL = Settings().model  # the model and seed gallery the environment names
ADMIN_KEY, READ_KEY = "tests-admin-key-0123", "tests-read-key-4567"  # conftest's keyed_service


def wait_ready(client: httpx.Client, alive, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        assert alive(), "the server stopped while starting"
        try:
            health = client.get("/health").json()
            if health["status"] == "ok":
                return
            assert health["status"] == "loading", f"the gallery failed to load: {health}"
        except httpx.TransportError:
            pass
        assert time.monotonic() < deadline, f"the server was not ready in {timeout_s} s"
        time.sleep(0.05)


class ThreadServer:
    """``create_app(settings)`` served by uvicorn in a thread of this process."""

    def __init__(self, settings: Settings, headers: dict[str, str] | None = None):
        self.settings = settings
        self.app = create_app(settings)
        self.port = free_port()
        config = uvicorn.Config(self.app, host="127.0.0.1", port=self.port, log_level="warning")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        self.url = f"http://127.0.0.1:{self.port}"
        self.client = httpx.Client(base_url=self.url, timeout=60.0, headers=headers)
        wait_ready(self.client, self.thread.is_alive)

    def stop(self) -> None:
        self.client.close()
        self.server.should_exit = True
        self.thread.join(timeout=10)


class ProcessServer(ServiceProcess):
    """``python -m service`` as a child process with a client; stderr (the logs) goes to a file."""

    def __init__(self, data_dir: Path, log_path: Path, headers=None, **settings: str):
        super().__init__(log_path, wait=False, gallery__data_dir=str(data_dir), **settings)
        self.client = httpx.Client(base_url=self.url, timeout=60.0, headers=headers)
        try:
            wait_ready(self.client, self.alive)
        except BaseException:
            self.kill()
            raise

    def kill(self) -> None:
        super().kill()
        self.client.close()

    def stop(self) -> None:
        super().stop()
        self.client.close()


def run_service(data_dir: Path, timeout_s: float = 60, **settings: str):
    """``python -m service`` expected to stop at its startup checks: the completed process."""
    return served.run_service(timeout_s, gallery__data_dir=str(data_dir), **settings)
