"""Regenerate the README's console screenshot from the shipped service.

``python scripts/screenshot.py`` starts ``python -m service`` (the shipped model, seed gallery and
confidence calibration, a fresh data directory, a free loopback port), opens the web console in
Debian's Chromium (``/usr/bin/chromium``, driven by Playwright, which downloads no browser),
drops ``models/sample_cloud.pcd`` on "Align a cloud", waits for the alignment to be drawn and
writes ``docs/console.png``. The sample is aligned once over HTTP first, so that the timings
shown are a warm service's, not the first call's (onnxruntime's first run takes ~150 ms more).
It stops without writing when the verdict is not ``match``.

``--detect`` writes ``docs/console-detect.png`` instead: one frame of the evaluation's
``scene`` family (``evaluation.frames``: parts dropped on a table by pybullet, a 640 × 480
organized PCD), its registered parts registered as the evaluation registers them, the frame
detected once over HTTP, then dropped on "Detect in a frame" and the first detection picked
out. It stops without writing when no detection is a ``match``. Needs the ``eval`` extra too.

Needs the ``test`` extra (``playwright``) and ``apt-get install chromium``.
"""

from __future__ import annotations

import argparse
import base64
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

from evaluation.served import ServiceProcess  # noqa: E402

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--headless", "--disable-gpu", "--no-first-run"]
SAMPLE = REPO / "models" / "sample_cloud.pcd"
# evaluation.frames' scene frame (family, index, seed): three parts answered match, one
# uncertain, two parts of no registered kind among them
DETECT_FRAME = ("scene", 0, 2)
VIEWPORT = {"width": 1400, "height": 900}
DROP = """([zone, name, data]) => {
    const bytes = Uint8Array.from(atob(data), (c) => c.charCodeAt(0));
    const transfer = new DataTransfer();
    transfer.items.add(new File([bytes], name));
    document.getElementById(zone).dispatchEvent(
        new DragEvent("drop", { dataTransfer: transfer, bubbles: true }));
}"""


@contextmanager
def console(url: str) -> Iterator:
    """A console tab at ``url``, ready; it raises if the page reported an error."""
    from playwright.sync_api import sync_playwright  # the test extra

    with sync_playwright() as driver:
        browser = driver.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        page = browser.new_page(viewport=VIEWPORT)
        errors: list[str] = []
        page.on("console", lambda m: m.type == "error" and errors.append(m.text))
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(f"{url}/ui/")
        page.wait_for_selector("body[data-state=ready]", timeout=60_000)
        yield page
        if errors:
            raise SystemExit(f"the console reported errors: {errors}")
        browser.close()


def drop(page, zone: str, name: str, data: bytes) -> None:
    page.evaluate(DROP, [zone, name, base64.b64encode(data).decode()])


def screenshot(url: str, out: Path, sample: Path = SAMPLE) -> str:
    """Align ``sample`` through the console at ``url`` and write the page to ``out``; the
    verdict shown."""
    file = {"file": (sample.name, sample.read_bytes())}
    warm = httpx.post(f"{url}/align", files=file, timeout=60)
    warm.raise_for_status()
    with console(url) as page:
        drop(page, "align-drop", sample.name, sample.read_bytes())
        page.wait_for_selector("#view[data-drawn=alignment]", timeout=60_000)
        page.wait_for_selector("#recent li", timeout=30_000)
        verdict = page.locator("#verdict").inner_text()
        if verdict != "MATCH":
            raise SystemExit(f"the sample was answered {verdict!r}, not MATCH: nothing written")
        page.screenshot(path=str(out))
    return verdict


def detect_screenshot(url: str, out: Path, chosen: tuple[str, int, int] = DETECT_FRAME) -> str:
    """Detect in an evaluation frame through the console at ``url`` and write the page to
    ``out``; the verdicts listed."""
    from evaluation import frames
    from evaluation.detect import register

    family, index, seed = chosen
    registered, foreign = frames.manifest_parts()
    frame = frames.make_frame(family, index, seed, registered, foreign)
    names = {instance.name for instance in frame.instances if instance.registered}
    with httpx.Client(base_url=url, timeout=300) as client:
        for part in registered:
            if part.name in names:
                register(client, part, replace=True)
        pcd = frames.pcd_bytes(frame, compressed=True)
        client.post("/detect", files={"file": (f"{frame.stem}.pcd", pcd)}).raise_for_status()
    with console(url) as page:
        drop(page, "detect-drop", f"{frame.stem}.pcd", pcd)
        page.wait_for_selector("#view[data-drawn=detection]", timeout=300_000)
        items = page.locator("#detections li.detection")
        verdicts = [item.get_attribute("data-verdict") for item in items.all()]
        if "match" not in verdicts:
            raise SystemExit(f"the frame was answered {verdicts}, no match: nothing written")
        items.first.click()
        page.screenshot(path=str(out))
    return ", ".join(verdicts)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--detect", action="store_true", help="detect in a frame instead")
    parser.add_argument("--out", type=Path, help="docs/console.png, or console-detect.png")
    args = parser.parse_args(argv)
    out = args.out or REPO / "docs" / ("console-detect.png" if args.detect else "console.png")
    if not CHROMIUM.exists():
        raise SystemExit(f"no {CHROMIUM}: apt-get install chromium")
    with (
        tempfile.TemporaryDirectory() as data,
        ServiceProcess(Path(data) / "service.log", gallery__data_dir=data) as service,
    ):
        if args.detect:
            print(f"wrote {out}: the frame answered {detect_screenshot(service.url, out)}")
        else:
            print(f"wrote {out}: the sample answered {screenshot(service.url, out)}")


if __name__ == "__main__":
    main()
