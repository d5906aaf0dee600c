"""The web console at /ui and what it reads: the reference's points, the on-demand self-check,
the ring of recent alignments (on while the service is open, off once keys are configured),
and the page itself in a real browser: Debian's Chromium driven by Playwright, no console
errors, a drop registers, a drop aligns and draws, and the README's screenshot.

``DPC_CONSOLE_SCREENSHOT=docs/console.png`` writes the screenshot there as well."""

from __future__ import annotations

import base64
import fnmatch
import hashlib
import io
import os
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from pypcd4 import Encoding, PointCloud
from scipy.spatial.transform import Rotation

from service.api.app import create_app
from service.api.recent import KEPT_POINTS, RecentAlignments
from service.api.schemas import AlignResponse
from service.engine.sampling import sample_surface
from service.settings import AuthSettings, ConsoleSettings, Settings
from tests.meshes import pybullet_mesh
from tests.servers import ADMIN_KEY, REPO

CHROMIUM = Path("/usr/bin/chromium")  # Debian's package; .ci/run installs it
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--headless",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
]


def test_recent_alignments_are_on_while_open_and_off_with_keys():
    assert Settings().recent_alignments == 20
    assert Settings(auth=AuthSettings(keys={ADMIN_KEY: "admin"})).recent_alignments == 0
    chosen = Settings(
        auth=AuthSettings(keys={ADMIN_KEY: "admin"}), console=ConsoleSettings(recent_alignments=5)
    )
    assert chosen.recent_alignments == 5


def test_the_ring_keeps_the_last_ones():
    ring = RecentAlignments(2)
    answer = AlignResponse.model_construct(label="x")
    for count in (10, 11, 12):
        ring.add(np.zeros((count, 3), np.float32), None, "raw", answer)
    assert [len(entry.points) for entry in ring.newest_first()] == [12, 11]
    assert ring.get(1) is None and ring.get(3) is not None
    RecentAlignments(0).add(np.zeros((3, 3), np.float32), None, "raw", answer)
    assert RecentAlignments(0).newest_first() == []


def test_a_camera_frame_is_kept_thinned():
    """20 whole 2,048 x 1,536 frames would hold 755 MB: each is kept as every k-th point."""
    ring = RecentAlignments(1)
    frame = np.arange(2048 * 1536 * 3, dtype=np.float32).reshape(-1, 3)
    ring.add(frame, None, "raw", AlignResponse.model_construct(label="x"))
    (entry,) = ring.newest_first()
    assert KEPT_POINTS // 2 < len(entry.points) <= KEPT_POINTS
    assert (entry.points[1] - entry.points[0] == frame[48] - frame[0]).all()  # every 48th


def test_a_reference_s_points_and_self_check(service):
    client = service.client
    described = client.get("/references/mug").json()
    raw = client.get("/references/mug/points")
    assert raw.headers["content-type"] == "application/octet-stream"
    assert len(raw.content) == described["num_points"] * 12
    assert hashlib.sha256(raw.content).hexdigest() == described["points_sha256"]
    one, two = (client.get("/references/mug/self_check", params={"poses": n}) for n in (1, 2))
    assert one.status_code == two.status_code == 200, (one.text, two.text)
    assert 0 < len(one.json()) < len(two.json())  # one entry or more a pose
    keys = {"label_ok", "rotation_error_deg", "alignment_error_normalized"}
    assert all(keys <= set(check) for check in two.json())
    assert client.get("/references/nothing/points").status_code == 404
    assert client.get("/references/nothing/self_check").status_code == 404
    assert client.get("/references/mug/self_check", params={"poses": 0}).status_code == 422


def test_recent_alignments_replay_what_was_sent(service):
    sent = sample_points("bunny.obj").astype("<f4").tobytes()
    answer = service.client.post(
        "/align",
        content=sent,
        params={"viewpoint": "0.5,0,0"},
        headers={"content-type": "application/octet-stream"},
    )
    assert answer.status_code == 200, answer.text
    listed = service.client.get("/alignments").json()
    assert listed["capacity"] == 20
    latest = listed["alignments"][0]
    assert latest["source"] == "raw" and latest["viewpoint"] == [0.5, 0, 0]
    assert service.client.get(f"/alignments/{latest['id']}/points").content == sent
    assert service.client.get(f"/alignments/{latest['id']}").json()["answer"] == answer.json()
    assert service.client.get("/alignments/999999").status_code == 404


def test_with_keys_nothing_is_kept_and_the_console_is_still_served(keyed_service):
    headers = {"Authorization": f"Bearer {ADMIN_KEY}"}
    assert keyed_service.client.get("/alignments").status_code == 401
    assert keyed_service.client.get("/alignments", headers=headers).json() == {
        "capacity": 0,
        "alignments": [],
    }
    missing = keyed_service.client.get("/alignments/1", headers=headers)
    assert (
        missing.status_code == 404 and "DPC_CONSOLE__RECENT_ALIGNMENTS" in missing.json()["detail"]
    )
    page = keyed_service.client.get("/ui/")  # static: no key needed, the page asks for one
    assert page.status_code == 200 and "importmap" in page.text
    assert keyed_service.client.get("/", follow_redirects=False).headers["location"] == "/ui/"
    assert keyed_service.client.get("/ui/vendor/three/LICENSE").text.startswith("The MIT License")


def test_the_console_can_be_turned_off():
    app = create_app(Settings(console=ConsoleSettings(enabled=False)))
    assert not any(getattr(route, "path", "") in ("/ui", "/") for route in app.routes)


def test_every_console_file_ships_in_the_package():
    """The wheel (and so the Docker image) carries what pyproject's package-data names."""
    setuptools = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    shipped = setuptools["package-data"]["service"]
    service = REPO / "service"
    for path in (service / "console").rglob("*"):
        if path.is_file():
            name = path.relative_to(service).as_posix()
            assert any(fnmatch.fnmatch(name, pattern) for pattern in shipped), name


def sample_points(mesh: str, seed: int = 5) -> np.ndarray:
    """A pybullet_data mesh's surface in a random pose, as a scan would give it."""
    rotation = Rotation.random(random_state=seed).as_matrix()
    return sample_surface(pybullet_mesh(mesh), 2048, seed) @ rotation.T + [0.05, -0.02, 0.4]


# The browser


@pytest.fixture(scope="module")
def browser():
    if not CHROMIUM.exists():
        pytest.skip(f"no {CHROMIUM}: apt-get install chromium (.ci/run does)")
    playwright = pytest.importorskip("playwright.sync_api")
    with playwright.sync_playwright() as driver:
        launched = driver.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield launched
        launched.close()


class Page:
    """A console tab that records every console error and uncaught exception."""

    def __init__(self, browser, url: str):
        self.page = browser.new_page(viewport={"width": 1400, "height": 900})
        self.errors: list[str] = []
        self.page.on("console", lambda m: m.type == "error" and self.errors.append(m.text))
        self.page.on("pageerror", lambda error: self.errors.append(str(error)))
        self.page.goto(f"{url}/ui/")

    def drop(self, zone: str, name: str, data: bytes) -> None:
        """A file dropped on a drop zone, as a person drags one from a file manager."""
        self.page.evaluate(
            """([zone, name, data]) => {
                const bytes = Uint8Array.from(atob(data), (c) => c.charCodeAt(0));
                const transfer = new DataTransfer();
                transfer.items.add(new File([bytes], name));
                const drop = new DragEvent("drop", { dataTransfer: transfer, bubbles: true });
                document.getElementById(zone).dispatchEvent(drop);
            }""",
            [zone, name, base64.b64encode(data).decode()],
        )

    def text(self, selector: str) -> str:
        return self.page.locator(selector).inner_text()


def colours(png: bytes) -> tuple[int, int]:
    """Pixels of the observed points' orange and of the reference's blue in a screenshot."""
    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).reshape(-1, 3).astype(int)
    orange = (pixels[:, 0] > 180) & (pixels[:, 1] > 90) & (pixels[:, 1] < 180) & (pixels[:, 2] < 80)
    blue = (pixels[:, 2] > 180) & (pixels[:, 0] < 110)
    return int(orange.sum()), int(blue.sum())


def test_register_and_align_by_dropping_files(service, browser, tmp_path):
    tab = Page(browser, service.url)
    page = tab.page
    page.wait_for_selector("body[data-state=ready]", timeout=30_000)
    assert tab.text("#health").startswith("ok")
    page.wait_for_selector("#gallery .card[data-name=mug]")

    # a drop registers: the duck's own OBJ file from pybullet_data, named in the form
    duck = Path(pytest.importorskip("pybullet_data").getDataPath()) / "duck.obj"
    page.fill("#register-name", "console-duck")
    tab.drop("register-drop", duck.name, duck.read_bytes())
    page.wait_for_selector("body[data-registered=console-duck]", timeout=60_000)
    page.wait_for_selector("#gallery .card.selected[data-name=console-duck]")
    assert "console-duck" in tab.text("#result") and "Self-check" in tab.text("#result")

    # a drop aligns and draws: the duck in another pose, as pypcd4 writes a PCD
    buffer = io.BytesIO()
    PointCloud.from_xyz_points(sample_points("duck.obj").astype(np.float32)).save(
        buffer, Encoding.BINARY_COMPRESSED
    )
    page.fill("#candidates", "console-duck, mug")
    tab.drop("align-drop", "scan.pcd", buffer.getvalue())
    page.wait_for_selector("#view[data-drawn=alignment]", timeout=60_000)
    view = page.locator("#view")
    assert view.get_attribute("data-label") == "console-duck"
    assert view.get_attribute("data-observed") == "2048"
    assert tab.text("#verdict") in ("MATCH", "UNCERTAIN", "NO MATCH")
    result = tab.text("#result")
    for shown in ("console-duck", "alignment error", "hypothesis", "Timings", "total"):
        assert shown in result, shown
    orange, blue = colours(view.screenshot())
    assert orange > 500 and blue > 500, (orange, blue)  # both clouds are drawn

    page.wait_for_selector("#recent li")
    screenshot = tmp_path / "console.png"
    page.screenshot(path=str(screenshot))
    if os.environ.get("DPC_CONSOLE_SCREENSHOT"):
        shutil.copyfile(screenshot, os.environ["DPC_CONSOLE_SCREENSHOT"])

    # the recent alignments list it; a click replays it, drawn again
    page.evaluate("document.getElementById('view').dataset.drawn = 'none'")
    page.locator("#recent li").first.click()
    page.wait_for_selector("#view[data-drawn=alignment]")
    assert "#" in tab.text("#result") and "align these points again" in tab.text("#result")
    assert tab.errors == []


def test_the_console_sends_the_api_key(keyed_service, browser):
    tab = Page(browser, keyed_service.url)
    page = tab.page
    page.wait_for_selector("#message.error")
    assert "API key" in tab.text("#message")  # nothing was requested without a key
    page.fill("#api-key", ADMIN_KEY)
    page.click("#key-form button")
    page.wait_for_selector("#gallery-count:text('(0)')")
    block = trimesh.creation.box(extents=(0.05, 0.08, 0.12)).export(file_type="stl")
    tab.drop("register-drop", "block.stl", block)
    page.wait_for_selector("body[data-registered=block]", timeout=60_000)
    page.click("#try-pose")  # its own points in a random pose, aligned with the key
    page.wait_for_selector("#view[data-drawn=alignment][data-label=block]", timeout=60_000)
    assert (
        keyed_service.client.get("/references/block", headers={"X-API-Key": ADMIN_KEY}).status_code
        == 200
    )
    assert tab.errors == []
