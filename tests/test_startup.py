"""Startup checks: ``python -m service`` stops with one line on stderr and exit status 2, no
traceback, for a missing or corrupt model, an unusable data directory, an incompatible
database, or bad settings; the app built in-process refuses to start the same way."""

from __future__ import annotations

import asyncio
import json
import shutil
import sqlite3

import pytest

from service.api.app import create_app
from service.api.startup import StartupError, prepare
from service.engine.mapping import file_sha256
from service.gallery.sqlite_store import FILENAME, SQLiteStore
from service.gallery.store import SCHEMA_VERSION, StoreIncompatible
from service.settings import GallerySettings, ModelSettings, Settings
from tests.servers import MODEL, run_service

pytestmark = pytest.mark.skipif(not MODEL.path.exists(), reason=f"no ONNX model at {MODEL.path}")


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
