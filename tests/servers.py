"""Real servers for the hardening tests: the app in a uvicorn thread, or ``python -m service``.

Both listen on a free loopback port with their own data directory and use the model that the
settings name (``DPC_MODEL__PATH`` / ``DPC_MODEL__GALLERY`` honoured, as in test_api).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import uvicorn

from service.app import create_app
from service.settings import Settings

REPO = Path(__file__).resolve().parent.parent
MODEL = Settings().model  # the model and seed gallery the environment names


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


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


def service_env(data_dir: Path, port: int, **settings: str) -> dict[str, str]:
    """The environment of ``python -m service``: ours, minus other DPC_ settings, plus these."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("DPC_")}
    env |= {
        "DPC_MODEL__PATH": str(MODEL.path),
        "DPC_MODEL__GALLERY": str(MODEL.gallery),
        "DPC_GALLERY__DATA_DIR": str(data_dir),
        "DPC_SERVER__PORT": str(port),
        "PYTHONUNBUFFERED": "1",
    }
    return env | {f"DPC_{key.upper()}": value for key, value in settings.items()}


class ProcessServer:
    """``python -m service`` as a child process; stderr (the logs) goes to a file."""

    def __init__(self, data_dir: Path, log_path: Path, headers=None, **settings: str):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = log_path
        self._log = open(log_path, "ab")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "service"],
            cwd=REPO,
            env=service_env(data_dir, self.port, **settings),
            stdout=self._log,
            stderr=self._log,
        )
        self.client = httpx.Client(base_url=self.url, timeout=60.0, headers=headers)
        try:
            wait_ready(self.client, lambda: self.process.poll() is None)
        except BaseException:
            self.kill()
            raise

    @property
    def pid(self) -> int:
        return self.process.pid

    def kill(self) -> None:
        """SIGKILL: as a power cut looks to the process."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGKILL)
        self.process.wait(timeout=10)
        self._close()

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=10)
        self._close()

    def _close(self) -> None:
        self.client.close()
        self._log.close()


def run_service(data_dir: Path, timeout_s: float = 60, **settings: str):
    """``python -m service`` expected to stop at its startup checks: the completed process."""
    return subprocess.run(
        [sys.executable, "-m", "service"],
        cwd=REPO,
        env=service_env(data_dir, free_port(), **settings),
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )
