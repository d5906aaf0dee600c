"""The runtime dependencies are complete: in a fresh virtual environment with only what
``pip install -e .`` brings (the README's run command without its ``fast`` extra), plus pytest
and httpx to run them, the tests of what a registration reads and does pass, on numpy's loops
(no numba: ``service.engine.kernels``).

A missing runtime dependency fails only where a lazy import needs it (trimesh reading a text
mesh that is not UTF-8 needs charset_normalizer), which the full test environment hides:
the extras bring it. Slow (45-110 s on 2 busy cores: the install, from pip's cache when it has
the wheels, then the tests).
"""

from __future__ import annotations

import os
import subprocess
import sys
import venv

import pytest

from tests.servers import REPO

pytestmark = pytest.mark.slow

# what the tests in the runtime environment need besides the package itself
TEST_RUNNERS = ("pytest", "httpx")
RUNTIME_TESTS = ("tests/api/test_parsers.py", "tests/api/test_api.py")
# all of the first, test_api's registrations; on SQLite (the PostgreSQL cases would double the
# time, and the full environment runs them)
SELECTED = "(test_parsers or register or reference) and not postgresql"


def run(command: list[str], timeout_s: float) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH")}
    return subprocess.run(
        command, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout_s
    )


def test_registrations_work_with_the_runtime_dependencies_alone(tmp_path):
    home = tmp_path / "runtime-venv"
    venv.EnvBuilder(with_pip=False).create(home)  # this pip installs into it: no ensurepip (6 s)
    python = str(home / "bin" / "python")
    # --no-compile: the installed packages' byte-code is written as the tests import them,
    # not all of it up front (pip's install alone 49 -> 27 s of CPU)
    pip = [sys.executable, "-m", "pip", "--python", python]
    install = [*pip, "install", "-q", "--no-compile", "-e", str(REPO)]
    installed = run([*install, *TEST_RUNNERS], 600)
    assert installed.returncode == 0, installed.stdout[-3000:] + installed.stderr[-3000:]
    for extra in ("torch", "numba"):
        imported = run([python, "-c", f"import {extra}"], 60)
        assert imported.returncode != 0, (
            f"an extra's package came with the runtime install: {extra}"
        )
    pytest_args = ["-q", "-p", "no:cacheprovider", "-k", SELECTED, *RUNTIME_TESTS]
    tests = run([python, "-m", "pytest", *pytest_args], 600)
    summary = tests.stdout[-4000:] + tests.stderr[-2000:]
    assert tests.returncode == 0, summary
    assert " passed" in tests.stdout, summary
    assert " skipped" not in tests.stdout, summary  # a skip would hide a missing package
