"""``dpc-mn`` says its own flags: a registration under a name that is taken names
``--replace`` (the service's words, "pass replace=true", name its query parameter)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from service.client.cli import FAILED, main


def test_a_taken_name_names_the_replace_flag(service, capsys):
    pybullet_data = pytest.importorskip("pybullet_data")
    duck = Path(pybullet_data.getDataPath()) / "duck.obj"  # other points than the mug's
    command = ["register", str(duck), "--name", "mug", "--url", service.url, "--no-self-check"]
    assert main(command) == FAILED
    said = capsys.readouterr().err
    assert said.startswith("dpc-mn: 409: ") and "--replace" in said and "--name" in said
    assert "replace=true" not in said
    assert main([*command, "--json"]) == FAILED
    error = json.loads(capsys.readouterr().out)["error"]
    assert error["status"] == 409 and "--replace" in error["detail"]
