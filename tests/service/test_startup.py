"""Startup checks: ``python -m service`` stops with one line on stderr and exit status 2, no
traceback, for a missing or corrupt model, an unusable data directory, an incompatible
database, or bad settings (every setting whose values form a set among them); the app built
in-process refuses to start the same way. A ``DPC_`` variable that names no setting is warned
about."""

from __future__ import annotations

import asyncio
import json
import shutil
import sqlite3
import subprocess
import sys
import typing

import pytest
from pydantic import BaseModel, ValidationError

from service.__main__ import settings_message
from service.api.app import create_app
from service.api.startup import (
    CHOICES,
    StartupError,
    check_choices,
    prepare,
    setting_variables,
    unknown_variables,
)
from service.engine.hypotheses import SOURCES
from service.engine.mapping import file_sha256
from service.gallery.sqlite_store import FILENAME, SQLiteStore
from service.gallery.store import SCHEMA_VERSION, StoreIncompatible
from service.settings import EngineSettings, GallerySettings, ModelSettings, Settings
from tests.servers import MODEL, needs_model, run_service

pytestmark = needs_model


def release(tmp_path, model_bytes: bytes | None = None, manifest_hash: str | None = None):
    """A model directory: the model (or other bytes), and a manifest naming a hash."""
    folder = tmp_path / "release"
    folder.mkdir()
    model = folder / "dpc_mn.onnx"
    if model_bytes is None:
        shutil.copy(MODEL.path, model)
    else:
        model.write_bytes(model_bytes)
    if manifest_hash is not None:
        manifest = {"files": {"dpc_mn.onnx": {"sha256": manifest_hash}}}
        (folder / "manifest.json").write_text(json.dumps(manifest))
    return model


def refused(result, *words: str) -> str:
    assert result.returncode == 2, (result.returncode, result.stderr[-2000:])
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    assert lines[0].startswith("dpc-mn-service: cannot start: ")
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


def test_a_missing_model(tmp_path):
    result = run_service(tmp_path / "data", model__path=str(tmp_path / "nothing.onnx"))
    refused(result, "no ONNX model", "nothing.onnx", "DPC_MODEL__PATH")


def test_a_model_that_does_not_match_its_manifest(tmp_path):
    model = release(tmp_path, manifest_hash="0" * 64)
    result = run_service(tmp_path / "data", model__path=str(model))
    refused(result, "damaged or not the released one", "manifest.json", "000000000000")


def test_a_model_that_matches_its_manifest_starts(tmp_path):
    model = release(tmp_path, manifest_hash=file_sha256(MODEL.path))
    settings = Settings(
        model=ModelSettings(path=model, gallery=tmp_path / "none.npz"),
        gallery=GallerySettings(data_dir=tmp_path / "data"),
    )
    mapper, store = prepare(settings)
    assert mapper.model_hash == file_sha256(MODEL.path) and store.is_empty()


def test_a_corrupt_model_without_a_manifest(tmp_path):
    model = release(tmp_path, model_bytes=MODEL.path.read_bytes()[:5000])
    result = run_service(tmp_path / "data", model__path=str(model))
    refused(result, "not a usable ONNX model")


def test_a_data_directory_that_is_a_file(tmp_path):
    occupied = tmp_path / "occupied"
    occupied.write_text("not a directory")
    result = run_service(occupied)
    refused(result, "data directory", "not a writable directory", "DPC_GALLERY__DATA_DIR")


def test_a_database_that_is_not_a_database(tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / FILENAME).write_bytes(b"this is not sqlite" * 100)
    result = run_service(tmp_path / "data")
    refused(result, "not a usable SQLite file", FILENAME)


def test_a_database_from_a_newer_version_stops_startup(tmp_path):
    data = tmp_path / "data"
    SQLiteStore.in_dir(data).set_meta("seeded_from", "")
    newer = str(int(SCHEMA_VERSION) + 1)
    with sqlite3.connect(data / FILENAME) as conn:
        conn.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (newer,))
    conn.close()
    before = (data / FILENAME).read_bytes()
    result = run_service(data)
    refused(result, f"schema version {newer}", "newer", "docs/operations.md")
    with pytest.raises(StoreIncompatible, match="newer"):
        SQLiteStore.in_dir(data)
    with sqlite3.connect(data / FILENAME) as conn:  # nothing written over it
        assert conn.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone() == (
            newer,
        )
    conn.close()
    assert len(before) > 0


def test_bad_settings_never_echo_a_key(tmp_path):
    result = run_service(tmp_path / "data", auth__keys='{"very-secret-key": "superuser"}')
    line = refused(result, "invalid settings", "DPC_AUTH__KEYS")
    assert "very-secret-key" not in result.stderr + result.stdout and "secret" not in line
    result = run_service(tmp_path / "data", auth__keys="very-secret-key")  # not JSON
    refused(result, "invalid settings")
    assert "very-secret-key" not in result.stderr + result.stdout


def test_the_app_in_process_refuses_to_start_too(tmp_path):
    settings = Settings(
        model=ModelSettings(path=tmp_path / "nothing.onnx"),
        gallery=GallerySettings(data_dir=tmp_path / "data"),
    )
    app = create_app(settings)

    async def start() -> None:
        async with app.router.lifespan_context(app):
            pass

    with pytest.raises(StartupError, match="no ONNX model"):
        asyncio.run(start())


# --- settings whose values form a set ---------------------------------------------------


def test_a_misspelt_hypothesis_source_stops_startup(tmp_path):
    """``mapd`` for ``mapped``: it used to start, report ready and answer 500 to every /align."""
    result = run_service(tmp_path / "data", engine__hypotheses='["mapped", "mapd"]')
    line = refused(result, "invalid settings", "DPC_ENGINE__HYPOTHESES", "'mapd'")
    assert all(f"'{source}'" in line for source in SOURCES)  # the engine's names, all of them


@pytest.mark.parametrize("sources", [("mapd",), (), ("mapped", "Paper")])
def test_hypothesis_sources_are_the_engines(tmp_path, sources):
    settings = Settings(engine=EngineSettings(hypotheses=sources))
    with pytest.raises(StartupError, match="DPC_ENGINE__HYPOTHESES") as caught:
        check_choices(settings)
    assert all(f"'{source}'" in str(caught.value) for source in SOURCES)
    for source in SOURCES:  # whatever the engine adds to SOURCES is allowed, alone or together
        check_choices(Settings(engine=EngineSettings(hypotheses=(source,))))
    check_choices(Settings(engine=EngineSettings(hypotheses=SOURCES)))


def literal_settings() -> list[tuple[str, str, tuple]]:
    """(group, field, allowed values) of every setting typed as a fixed set of strings."""
    found = []
    for group, info in Settings.model_fields.items():
        for field, inner in info.annotation.model_fields.items():
            kind = inner.annotation
            if typing.get_origin(kind) is typing.Annotated:
                kind = typing.get_args(kind)[0]
            if typing.get_origin(kind) is typing.Literal:
                found.append((group, field, typing.get_args(kind)))
    return found


ENUMERATED = [("server", "log_level"), ("server", "log_format")]


def test_every_enumerated_setting_is_listed_here_or_in_choices():
    """A new setting of a fixed set of values gets a case in the test below (or CHOICES), and
    a new string setting is either one of those or free text on purpose."""
    assert {(g, f) for g, f, _ in literal_settings()} == set(ENUMERATED)
    free_text = {("server", "host"), ("gallery", "url")}
    for group, info in Settings.model_fields.items():
        for field, inner in info.annotation.model_fields.items():
            if inner.annotation in (str, str | None, tuple[str, ...]):
                assert (group, field) in free_text | set(CHOICES), (group, field)


@pytest.mark.parametrize(("group", "field"), ENUMERATED)
def test_an_enumerated_setting_names_the_variable_and_its_values(monkeypatch, group, field):
    variable = f"DPC_{group}__{field}".upper()
    monkeypatch.setenv(variable, "loud")
    with pytest.raises(ValidationError) as caught:
        Settings()
    message = settings_message(caught.value)
    assert variable in message
    allowed = dict(((g, f), a) for g, f, a in literal_settings())[(group, field)]
    assert all(f"'{value}'" in message for value in allowed), message


def test_a_log_level_in_capitals_is_accepted_and_a_wrong_one_refused(tmp_path, monkeypatch):
    monkeypatch.setenv("DPC_SERVER__LOG_LEVEL", "WARNING")
    assert Settings().server.log_level == "warning"
    result = run_service(tmp_path / "data", server__log_level="verbose")
    refused(result, "DPC_SERVER__LOG_LEVEL", "'info'", "'debug'")


# --- DPC_ variables that name no setting ------------------------------------------------


def test_a_variable_that_names_no_setting_is_warned_about(tmp_path):
    """The warning comes before the checks, so it also explains a start-up that fails."""
    result = run_service(
        tmp_path / "data",
        servr__port="9000",
        engine__topk="5",
        model__path=str(tmp_path / "nothing.onnx"),
    )
    assert result.returncode == 2, result.stderr
    *warnings, last = result.stderr.strip().splitlines()
    assert last.startswith("dpc-mn-service: cannot start: no ONNX model")
    messages = [json.loads(line)["message"] for line in warnings]
    assert len(messages) == 2, messages
    assert "DPC_ENGINE__TOPK" in messages[0] and "DPC_ENGINE__TOP_K?" in messages[0]
    assert "DPC_SERVR__PORT" in messages[1] and "DPC_SERVER__PORT?" in messages[1]
    assert all(json.loads(line)["level"] == "warning" for line in warnings)


def test_only_unknown_variables_are_warned_about():
    known = {name: "1" for name in setting_variables()}
    assert "DPC_SERVER__PORT" in known and "DPC_AUTH" in known and "DPC_ENGINE__TOP_K" in known
    others = {"PATH": "/bin", "DPC_AUTH__KEYS__somekey": "admin", "dpc_server__port": "1"}
    assert unknown_variables(known | others) == []
    warnings = unknown_variables({"DPC_ENGINE__TOPK": "5", "DPC_NOTHING_LIKE_IT": "1"})
    assert len(warnings) == 2 and "DPC_ENGINE__TOP_K?" in warnings[0]
    assert warnings[1].endswith("names no setting and is ignored")


def test_every_group_is_a_model_of_settings():
    """setting_variables walks groups of fields; a setting outside a group would be missed."""
    for info in Settings.model_fields.values():
        assert issubclass(info.annotation, BaseModel)


def test_a_gallery_url_that_is_not_postgresql(tmp_path):
    result = run_service(tmp_path / "data", gallery__url="mysql://user:very-secret@host/db")
    refused(result, "invalid settings", "DPC_GALLERY__URL", "postgresql://")
    assert "very-secret" not in result.stderr + result.stdout


BLAS_CHECK = """
import json, sys
from threadpoolctl import threadpool_info
from service.engine.mapping import Mapper
from service.settings import ModelSettings
Mapper.from_settings(ModelSettings(path=sys.argv[1], blas_threads=int(sys.argv[2])))
print(json.dumps([p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]))
"""


@pytest.mark.parametrize("threads", [1, 2])
def test_a_model_holds_numpy_blas_to_its_setting(threads):
    """numpy's OpenBLAS runs as many threads as ``blas_threads`` once a model is loaded (its
    spinning workers took the cores from onnxruntime's). In a process of its own: OpenBLAS's
    thread count is the process's, and while another test's server runs in a thread of this
    one, OpenBLAS keeps that server's setting (measured: a second model's 2 read back as 1)."""
    found = subprocess.run(
        [sys.executable, "-c", BLAS_CHECK, str(MODEL.path.resolve()), str(threads)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert found.returncode == 0, found.stderr[-2000:]
    blas = json.loads(found.stdout.strip().splitlines()[-1])
    assert blas, "numpy's BLAS is not seen"
    assert all(count == threads for count in blas), blas
