"""A full disk under the SQLite gallery: a real, small filesystem (a 6 MiB tmpfs, mounted by the
test as root; skipped, saying why, where it cannot be mounted), filled to the last byte.

Registrations, batches and deletions answer 507 naming the full disk; nothing stored changes;
the service stays alive, ready, and aligns, and started again on the full disk serves what it
held; once space is freed a registration is stored. A start that must create the WAL anew on
a full disk stops with one line saying so.
"""

from __future__ import annotations

import errno
import io
import os
import sqlite3
import subprocess
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest

from service.settings import GallerySettings, Settings
from tests.ledger import varied_cloud as cloud
from tests.servers import MODEL, Server, run_service

pytestmark = pytest.mark.skipif(not MODEL.path.exists(), reason=f"no ONNX model at {MODEL.path}")
SIZE = "6m"


@pytest.fixture
def small_disk(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("mounting a small filesystem for the gallery needs root (mount -t tmpfs)")
    mount = tmp_path / "small"
    mount.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={SIZE}", "tmpfs", str(mount)],
        capture_output=True,
        text=True,
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a {SIZE} tmpfs here: {mounted.stderr.strip()}")
    yield mount
    subprocess.run(["umount", "--lazy", str(mount)], check=False)


def server(data_dir: Path) -> Server:
    model = MODEL.model_copy(update={"gallery": data_dir / "no-seed.npz"})
    return Server(Settings(model=model, gallery=GallerySettings(data_dir=data_dir)))


def fill(folder: Path) -> Path:
    """A file that takes every byte left on ``folder``'s filesystem."""
    filler = folder / "filler"
    with open(filler, "wb", buffering=0) as handle:
        for block in (1 << 20, 1 << 16, 1 << 12, 1):
            try:
                while True:
                    handle.write(b"\0" * block)
            except OSError as error:
                assert error.errno == errno.ENOSPC, error
    return filler


def contents(data: Path) -> tuple:
    """Every row, the version and the meta entries of the gallery file, read without writing."""
    uri = f"file:{data / 'gallery.sqlite3'}?mode=ro"
    with closing(sqlite3.connect(uri, uri=True)) as conn:
        return tuple(
            conn.execute(query).fetchall()
            for query in (
                "SELECT * FROM reference ORDER BY name",
                "SELECT version FROM gallery_version",
                "SELECT * FROM meta ORDER BY key",
            )
        )


def body(seed: int, name: str) -> dict:
    return {"name": name, "points": cloud(seed).astype("<f4").tolist()}


def test_a_full_disk_refuses_writes_and_keeps_serving(small_disk):
    data = small_disk / "data"
    first = server(data)
    try:
        api = first.client
        assert api.post("/references?self_check=false", json=body(1, "kept")).status_code == 201
        scene = cloud(1) @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]]).T + 0.1
        filler = fill(small_disk)
        stored = first.app.state.catalog.store.checksums()
        held = contents(data)

        refused = api.post("/references?self_check=false", json=body(2, "new"))
        assert refused.status_code == 507, refused.text
        detail = refused.json()["detail"]
        assert "is full" in detail and "nothing was stored" in detail and str(data) in detail
        replaced = api.post("/references?replace=true", json=body(3, "kept"))
        assert replaced.status_code == 507
        batch = api.post(
            "/references/batch",
            files=[
                ("file", ("a.npy", npy(cloud(4)))),
                ("file", ("b.npy", npy(cloud(5)))),
            ],
        )
        assert batch.status_code == 507
        assert api.delete("/references/kept").status_code == 507
        assert first.app.state.catalog.store.checksums() == stored
        assert [r["name"] for r in api.get("/references").json()["references"]] == ["kept"]
        aligned = api.post("/align", json={"points": scene.tolist()})
        assert aligned.status_code == 200 and aligned.json()["label"] == "kept"
        assert api.get("/v2/health/ready").status_code == 200
    finally:
        first.stop()
    assert contents(data) == held  # as the file holds it once the service has stopped

    again = server(data)  # started again on the full disk: it serves what it held
    try:
        aligned = again.client.post("/align", json={"points": scene.tolist()})
        assert aligned.status_code == 200 and aligned.json()["label"] == "kept"
        assert again.client.post("/references", json=body(2, "new")).status_code == 507
        filler.unlink()  # space again: the next registration is stored
        created = again.client.post("/references?self_check=false", json=body(2, "new"))
        assert created.status_code == 201, created.text
    finally:
        again.stop()
    # that stop could write the WAL back into the file and remove it and its index; a start
    # must make them again, which a full disk refuses: it says so in one line
    fill(small_disk)
    refused = run_service(data, model__gallery=str(data / "no-seed.npz"))
    assert refused.returncode == 2 and "its disk is full" in refused.stderr, refused.stderr


def npy(points: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, points.astype("<f4"))
    return buffer.getvalue()
