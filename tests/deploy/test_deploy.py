"""The deployment files are valid and agree with the service: the Kubernetes manifests against
the API's schemas (kubernetes-validate), deploy/compose.yaml against the Compose specification
(check-jsonschema), the Dockerfile through hadolint; their probes, port and settings are ones
the service has. The tools come with the test extra; a missing one skips its check, saying so.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from service.api.app import create_app
from service.settings import Settings
from tests.servers import REPO

DEPLOY = REPO / "deploy"
KUBERNETES_VERSION = "1.30.0"  # the oldest release the manifests are meant for


def manifests() -> list[dict]:
    return [
        document
        for path in sorted((DEPLOY / "k8s").glob("*.yaml"))
        for document in yaml.safe_load_all(path.read_text())
        if document
    ]


def tool(name: str) -> str:
    """A command of the test extra: beside this interpreter, else on the PATH."""
    found = Path(sys.executable).parent / name
    path = str(found) if found.exists() else shutil.which(name)
    if path is None:
        pytest.skip(f"{name} is not installed: pip install -e '.[test]'")
    return path


def of_kind(kind: str) -> dict:
    (document,) = [d for d in manifests() if d["kind"] == kind]
    return document


def test_the_kubernetes_manifests_are_valid():
    kubernetes_validate = pytest.importorskip("kubernetes_validate")
    kinds = set()
    for document in manifests():
        kubernetes_validate.validate(document, KUBERNETES_VERSION, strict=True)
        kinds.add(document["kind"])
    expected = {"Deployment", "Service", "HorizontalPodAutoscaler", "Secret"}
    assert expected | {"PodDisruptionBudget"} <= kinds


def test_the_manifests_agree_with_the_service(monkeypatch):
    container = of_kind("Deployment")["spec"]["template"]["spec"]["containers"][0]
    paths = set(create_app(Settings()).openapi()["paths"])
    for probe in ("startupProbe", "livenessProbe", "readinessProbe"):
        assert container[probe]["httpGet"]["path"] in paths, probe
    assert container["readinessProbe"]["httpGet"]["path"] == "/v2/health/ready"
    exposed = re.search(r"^EXPOSE (\d+)$", (REPO / "Dockerfile").read_text(), re.M)
    assert container["ports"][0]["containerPort"] == int(exposed.group(1))
    assert container["resources"]["requests"]["cpu"]  # what the autoscaler measures against
    hpa = of_kind("HorizontalPodAutoscaler")["spec"]
    assert hpa["metrics"][0]["resource"]["name"] == "cpu" and hpa["minReplicas"] >= 2
    secret = of_kind("Secret")["stringData"]
    for name, value in (secret | {e["name"]: e["value"] for e in container["env"]}).items():
        monkeypatch.setenv(name, value)
    settings = Settings()  # as the service reads them: each one parses
    assert settings.gallery.url.startswith("postgresql://") and settings.auth.keys


def test_the_compose_file_follows_the_specification():
    compose = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    assert {"postgres", "replica-a", "replica-b", "proxy"} <= set(compose["services"])
    nginx = (DEPLOY / "nginx.conf").read_text()
    for replica in ("replica-a", "replica-b"):
        assert f"server {replica}:8000" in nginx
        assert "DPC_GALLERY__URL" in compose["services"][replica]["environment"]
    result = subprocess.run(
        [
            tool("check-jsonschema"),
            "--builtin-schema",
            "vendor.compose-spec",
            "deploy/compose.yaml",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_the_dockerfile_passes_hadolint():
    result = subprocess.run(
        [tool("hadolint"), "Dockerfile"], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stdout + result.stderr
