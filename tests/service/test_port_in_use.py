"""``python -m service`` on a port another process holds stops at once, as its other start-up
checks do: exit status 2 and one line naming the port and the settings that change it (it
exited 3 with uvicorn's errno text, once the model and gallery had loaded)."""

from __future__ import annotations

import socket

import pytest

from tests.servers import MODEL, run_service

pytestmark = pytest.mark.skipif(not MODEL.path.exists(), reason=f"no ONNX model at {MODEL.path}")


def test_a_port_in_use_names_the_port_and_how_to_change_it(tmp_path):
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        result = run_service(tmp_path / "data", server__port=str(port))
    assert result.returncode == 2, (result.returncode, result.stderr[-2000:])
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    assert lines[0].startswith("dpc-mn-service: cannot start: ")
    assert f"port {port} on 127.0.0.1 is in use" in lines[0]
    assert "--port" in lines[0] and "DPC_SERVER__PORT" in lines[0]
    assert not (tmp_path / "data").exists()  # refused before the gallery was opened
