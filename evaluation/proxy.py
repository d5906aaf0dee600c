"""A throwaway nginx in front of replicas, for the failover test and benchmark: the project's own
``deploy/nginx.conf`` (its upstream's balancing and failure settings, its locations and their
retries, unchanged) with the replicas' loopback addresses in place of ``replica-a:8000`` and
``replica-b:8000``, a free loopback port in place of 8080, and its pid, logs and temporary files
in a folder of its own, deleted when it stops. The access log says, for each request, which
replicas nginx tried and what each answered (``$upstream_addr``, ``$upstream_status``).

It needs Debian's ``nginx`` (``apt-get install nginx``); ``Unavailable`` says so without one.
"""

from __future__ import annotations

import re
import shutil
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import httpx

from evaluation.served import REPO, free_port

CONFIG = REPO / "deploy" / "nginx.conf"
INSTALL_HINT = "install nginx (Debian: apt-get install nginx)"
SERVER = re.compile(r"^(\s*)server\s+replica-[a-z]:8000(.*);$", re.MULTILINE)
LOG_LINE = re.compile(r'^(\S+) (\d+) (\S+) (\S+) "([^"]*)" "([^"]*)" (\S+)$')
LOG_FORMAT = (
    "log_format failover '$msec $status $request_method $uri "
    '"$upstream_addr" "$upstream_status" $request_time\';'
)


class Unavailable(RuntimeError):
    """No nginx can be started here; the message says what to install."""


@dataclass(frozen=True)
class Logged:
    """One request as nginx logged it."""

    time: float  # when it was answered, epoch seconds
    status: int
    method: str
    uri: str
    upstreams: list[str]  # every replica tried, in order ("127.0.0.1:PORT")
    upstream_statuses: list[str]  # what each answered ("502", "200", "" where none)
    seconds: float


def render(config: str, upstreams: list[str], port: int, root: Path) -> str:
    """``deploy/nginx.conf`` with these replicas (in the order of its ``server`` lines), this
    port, and its files under ``root``."""
    servers = SERVER.findall(config)
    if len(servers) != len(upstreams):
        raise ValueError(f"{CONFIG} names {len(servers)} replicas; {len(upstreams)} given")
    replaced = iter(upstreams)
    text = SERVER.sub(lambda m: f"{m.group(1)}server {next(replaced)}{m.group(2)};", config)
    text, listens = re.subn(r"listen\s+8080;", f"listen 127.0.0.1:{port};", text)
    if listens != 1:
        raise ValueError(f"{CONFIG} has no 'listen 8080;' to move")
    files = "\n".join(
        f"    {directive} {root / folder};"
        for directive, folder in (
            ("client_body_temp_path", "body"),
            ("proxy_temp_path", "proxy"),
            ("fastcgi_temp_path", "fastcgi"),
            ("uwsgi_temp_path", "uwsgi"),
            ("scgi_temp_path", "scgi"),
        )
    )
    logs = f"    {LOG_FORMAT}\n    access_log {root / 'access.log'} failover;\n{files}\n"
    text = text.replace("http {\n", "http {\n" + logs, 1)
    top = f"pid {root / 'nginx.pid'};\nerror_log {root / 'error.log'} warn;\n"
    return top + text


class ThrowawayNginx:
    """nginx serving ``deploy/nginx.conf`` in front of ``upstreams`` (``host:port`` each)."""

    def __init__(self, upstreams: list[str], config: Path = CONFIG):
        binary = shutil.which("nginx") or next(
            (p for p in ("/usr/sbin/nginx", "/usr/local/sbin/nginx") if Path(p).exists()), None
        )
        if binary is None:
            raise Unavailable(f"no nginx binary: {INSTALL_HINT}")
        self.root = Path(tempfile.mkdtemp(prefix="dpc-nginx-"))
        self.root.chmod(0o755)
        for folder in ("body", "proxy", "fastcgi", "uwsgi", "scgi"):
            (self.root / folder).mkdir(mode=0o777)
            (self.root / folder).chmod(0o777)  # the workers may run as another user (root: nobody)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.config = self.root / "nginx.conf"
        self.config.write_text(render(config.read_text(), upstreams, self.port, self.root))
        command = [binary, "-p", str(self.root), "-c", str(self.config), "-g", "daemon off;"]
        checked = subprocess.run([*command, "-t"], capture_output=True, text=True, timeout=30)
        if checked.returncode != 0:
            self.remove()
            raise Unavailable(f"nginx refused the configuration: {checked.stderr.strip()}")
        self.process = subprocess.Popen(
            command, stdout=subprocess.DEVNULL, stderr=open(self.root / "stderr.log", "wb")
        )
        try:
            self._wait_listening()
        except BaseException:
            self.close()
            raise

    def _wait_listening(self, timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            if self.process.poll() is not None:
                raise Unavailable(f"nginx exited ({self.process.returncode}): {self.errors()}")
            try:
                httpx.get(f"{self.url}/v2/health/live", timeout=2)
                return
            except httpx.TransportError:
                if time.monotonic() > deadline:
                    raise Unavailable(f"nginx did not listen in {timeout_s:.0f} s") from None
                time.sleep(0.05)

    def requests(self) -> list[Logged]:
        """Every request nginx has logged so far."""
        try:
            lines = (self.root / "access.log").read_text().splitlines()
        except FileNotFoundError:
            return []
        logged = []
        for line in lines:
            found = LOG_LINE.match(line)
            if found is None:
                continue
            stamp, status, method, uri, upstreams, statuses, seconds = found.groups()
            logged.append(
                Logged(
                    float(stamp),
                    int(status),
                    method,
                    uri,
                    [u for u in re.split(r"\s*[,:]\s+", upstreams) if u and u != "-"],
                    [s for s in re.split(r"\s*[,:]\s+", statuses) if s],
                    float(seconds),
                )
            )
        return logged

    def errors(self) -> str:
        text = ""
        for name in ("stderr.log", "error.log"):
            try:
                text += (self.root / name).read_text(errors="replace")[-2000:]
            except OSError:
                pass
        return text

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGQUIT)  # graceful: finish what is in flight
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=10)
        self.remove()

    def remove(self) -> None:
        shutil.rmtree(self.root, ignore_errors=True)

    def __enter__(self) -> ThrowawayNginx:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
