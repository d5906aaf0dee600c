"""A throwaway PostgreSQL server for the tests and the benchmarks: ``initdb`` into a temporary
folder, started with ``pg_ctl`` on a free loopback port, deleted when stopped.

It needs the server binaries (Debian: ``apt-get install postgresql``; they live in
``/usr/lib/postgresql/<version>/bin``, off the PATH). PostgreSQL refuses to run as root, so
under root the server runs as the ``postgres`` user that package creates. ``Unavailable`` says
what is missing when no server can be started. A server that does not sync its writes (the
tests') keeps its files in memory where there is room (``/dev/shm``): they die with it anyway,
and deleting a few hundred MB of databases from a busy disk took up to 18 s.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import uuid
from pathlib import Path

from evaluation.served import free_port

USER = "dpc"  # the cluster's superuser; connections from loopback are trusted
INSTALL_HINT = "install PostgreSQL's server (Debian: apt-get install postgresql)"
MEMORY_NEEDED = 4 << 30  # free in /dev/shm for a cluster there: the tests' take about 400 MB


class Unavailable(RuntimeError):
    """No PostgreSQL server can be started here; the message says what to install."""


def server_binaries() -> Path | None:
    """The folder holding ``initdb`` and ``pg_ctl``: on the PATH, else Debian's newest."""
    on_path = shutil.which("initdb")
    if on_path and shutil.which("pg_ctl"):
        return Path(on_path).resolve().parent
    versions = sorted(
        Path("/usr/lib/postgresql").glob("*/bin/initdb"),
        key=lambda path: int(path.parent.parent.name) if path.parent.parent.name.isdigit() else 0,
    )
    return versions[-1].parent if versions else None


def in_memory(needed: int = MEMORY_NEEDED) -> Path | None:
    """``/dev/shm`` where it exists with room to spare, else None (the temporary folder)."""
    shared = Path("/dev/shm")
    try:
        return shared if shared.is_dir() and shutil.disk_usage(shared).free > needed else None
    except OSError:
        return None


class ThrowawayPostgres:
    """A running cluster; ``url`` reaches its ``postgres`` database, ``create_database`` more."""

    def __init__(self, fsync: bool = False):
        binaries = server_binaries()
        if binaries is None:
            raise Unavailable(f"no PostgreSQL server binaries (initdb, pg_ctl): {INSTALL_HINT}")
        self.binaries = binaries
        self.runner, owner = _runner()
        self.root = Path(
            tempfile.mkdtemp(prefix="dpc-postgres-", dir=None if fsync else in_memory())
        )
        self.data = self.root / "data"
        self.port = free_port()
        if owner:
            shutil.chown(self.root, owner)
        self.root.chmod(0o700)
        try:
            self._run("initdb", "-D", str(self.data), "-U", USER, "--auth=trust", "--no-sync")
            self.start(fsync)
        except BaseException:
            self.remove()
            raise
        self.url = self.database_url("postgres")

    def start(self, fsync: bool = False) -> None:
        options = (
            f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1"
            f" -c max_connections=300 -c fsync={'on' if fsync else 'off'}"
        )
        log = str(self.root / "server.log")
        self._run("pg_ctl", "-D", str(self.data), "-l", log, "-o", options, "-w", "start")

    def stop(self) -> None:
        """Stop the server (fast shutdown); ``start`` brings it back on the same port."""
        self._run("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "stop")

    def database_url(self, name: str) -> str:
        return f"postgresql://{USER}@127.0.0.1:{self.port}/{name}"

    def create_database(self, prefix: str = "gallery") -> str:
        """A new, empty database; its URL."""
        import psycopg  # the runtime's dependency; imported here so that a missing server
        # binary is reported before a missing driver

        name = f"{prefix}_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(self.url, autocommit=True) as conn:
            # PostgreSQL 15 writes a new database's every block to the WAL by default; copying
            # the template's files is quicker and leaves no WAL for ``close`` to delete
            copy = " STRATEGY = FILE_COPY" if conn.info.server_version >= 150000 else ""
            conn.execute(f'CREATE DATABASE "{name}"{copy}')
        return self.database_url(name)

    def close(self) -> None:
        """Stop the server and delete its files; nothing is written back first (immediate
        shutdown), as the files go."""
        try:
            self._run("pg_ctl", "-D", str(self.data), "-m", "immediate", "-w", "stop")
        finally:
            self.remove()

    def remove(self) -> None:
        shutil.rmtree(self.root, ignore_errors=True)

    def log(self) -> str:
        try:
            return (self.root / "server.log").read_text(errors="replace")[-4000:]
        except OSError:
            return ""

    def _run(self, program: str, *args: str) -> None:
        command = [*self.runner, str(self.binaries / program), *args]
        result = subprocess.run(command, capture_output=True, text=True, timeout=120)
        if result.returncode != 0:
            raise Unavailable(
                f"{program} failed ({result.returncode}): {result.stderr.strip()[-2000:]}\n"
                f"{self.log()}"
            )

    def __enter__(self) -> ThrowawayPostgres:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _runner() -> tuple[list[str], str | None]:
    """The command prefix that runs the server as a user it accepts, and that user: none
    unless root."""
    if os.geteuid() != 0:
        return [], None
    try:
        import pwd

        pwd.getpwnam("postgres")
    except KeyError:
        raise Unavailable(
            "running as root, and there is no 'postgres' user to run the server as: "
            f"{INSTALL_HINT} (it creates that user)"
        ) from None
    runuser = shutil.which("runuser")
    if runuser is None:
        raise Unavailable("running as root without runuser (util-linux) to drop to 'postgres'")
    return [runuser, "-u", "postgres", "--"], "postgres"
