"""Regenerate the README's console screenshot from the shipped service.

``python scripts/screenshot.py`` starts ``python -m service`` (the shipped model, seed gallery and
confidence calibration, a fresh data directory, a free loopback port), opens the web console in
Debian's Chromium (``/usr/bin/chromium``, driven by Playwright, which downloads no browser),
drops ``models/sample_cloud.pcd`` on "Align a cloud", waits for the alignment to be drawn and
writes ``docs/console.png``. The sample is aligned once over HTTP first, so that the timings
shown are a warm service's, not the first call's (onnxruntime's first run takes ~150 ms more).
It stops without writing when the verdict is not ``match``.

Needs the ``test`` extra (``playwright``) and ``apt-get install chromium``.
"""

from __future__ import annotations

import argparse
import base64
import sys
import tempfile
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

from evaluation.served import ServiceProcess  # noqa: E402

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--headless", "--disable-gpu", "--no-first-run"]
SAMPLE = REPO / "models" / "sample_cloud.pcd"
VIEWPORT = {"width": 1400, "height": 900}
DROP = """([zone, name, data]) => {
    const bytes = Uint8Array.from(atob(data), (c) => c.charCodeAt(0));
    const transfer = new DataTransfer();
    transfer.items.add(new File([bytes], name));
    document.getElementById(zone).dispatchEvent(
        new DragEvent("drop", { dataTransfer: transfer, bubbles: true }));
}"""


def screenshot(url: str, out: Path, sample: Path = SAMPLE) -> str:
    """Align ``sample`` through the console at ``url`` and write the page to ``out``; the
    verdict shown."""
    from playwright.sync_api import sync_playwright  # the test extra

    file = {"file": (sample.name, sample.read_bytes())}
    warm = httpx.post(f"{url}/align", files=file, timeout=60)
    warm.raise_for_status()
    with sync_playwright() as driver:
        browser = driver.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        page = browser.new_page(viewport=VIEWPORT)
        errors: list[str] = []
        page.on("console", lambda m: m.type == "error" and errors.append(m.text))
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(f"{url}/ui/")
        page.wait_for_selector("body[data-state=ready]", timeout=60_000)
        data = base64.b64encode(sample.read_bytes()).decode()
        page.evaluate(DROP, ["align-drop", sample.name, data])
        page.wait_for_selector("#view[data-drawn=alignment]", timeout=60_000)
        page.wait_for_selector("#recent li", timeout=30_000)
        verdict = page.locator("#verdict").inner_text()
        if errors:
            raise SystemExit(f"the console reported errors: {errors}")
        if verdict != "MATCH":
            raise SystemExit(f"the sample was answered {verdict!r}, not MATCH: nothing written")
        page.screenshot(path=str(out))
        browser.close()
    return verdict


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "console.png")
    args = parser.parse_args(argv)
    if not CHROMIUM.exists():
        raise SystemExit(f"no {CHROMIUM}: apt-get install chromium")
    with (
        tempfile.TemporaryDirectory() as data,
        ServiceProcess(Path(data) / "service.log", gallery__data_dir=data) as service,
    ):
        verdict = screenshot(service.url, args.out)
    print(f"wrote {args.out}: the sample answered {verdict}")


if __name__ == "__main__":
    main()
