"""Fuzzing the HTTP API with schemathesis, from the service's own OpenAPI document.

Every operation gets a bounded number of generated requests, valid and invalid, sent to a
real server (API keys on, so the auth paths run too): no answer is a 5xx, and every answer
conforms to what the document says (status code, content type, headers, body schema).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

from service.api.app import create_app
from service.settings import AuthSettings, GallerySettings, LimitSettings, Settings
from tests.servers import MODEL, Server, needs_model

schemathesis = pytest.importorskip("schemathesis")
from schemathesis.specs.openapi.checks import positive_data_acceptance  # noqa: E402

ADMIN = "fuzz-admin-key-000"
AUTH = {"Authorization": f"Bearer {ADMIN}"}
EXAMPLES = int(os.environ.get("FUZZ_EXAMPLES", "8"))  # per operation; more for a long run

pytestmark = needs_model


def fuzz_settings(data_dir: Path) -> Settings:
    return Settings(
        model=MODEL,
        gallery=GallerySettings(data_dir=data_dir, reference_points=256, self_check_poses=0),
        limits=LimitSettings(
            min_points=3, max_points=2_000, max_body_bytes=1024 * 1024, request_timeout_s=30
        ),
        auth=AuthSettings(keys={ADMIN: "admin", "fuzz-read-key-000": "read"}),
    )


@pytest.fixture(scope="module")
def fuzzed_server(tmp_path_factory):
    server = Server(fuzz_settings(tmp_path_factory.mktemp("fuzz")))
    yield server
    server.stop()


# the document the server will serve (it depends on the settings, not on a running server)
schema = schemathesis.openapi.from_dict(create_app(fuzz_settings(Path("unused"))).openapi())


@schema.parametrize()
@settings(
    max_examples=EXAMPLES,
    deadline=None,
    database=None,
    suppress_health_check=list(HealthCheck),
)
def test_the_api_holds_to_its_document(case, fuzzed_server):
    case.call_and_validate(
        base_url=fuzzed_server.url,
        headers=AUTH,
        timeout=60,
        # schema-valid points may still be refused (422): fewer than the minimum, all alike
        excluded_checks=[positive_data_acceptance],
    )
