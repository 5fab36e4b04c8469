"""A headless browser for the page of `relight serve`: Debian's chromium driven by Playwright through
its system executable (Playwright's own browser downloads are not used). Shared by the browser tests
and the edit-to-frame latency benchmark."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)
WAIT_MS = 30_000
"""How long to wait for the page's first frame."""


@contextlib.contextmanager
def chromium_page(url: str, width: int = 1100, height: int = 700) -> Iterator[Any]:
    """A Playwright page of the system chromium at `url`, once the page shows its first frame.

    Raises:
        FileNotFoundError: /usr/bin/chromium is missing (install Debian's 'chromium' package).
    """
    if not CHROMIUM.is_file():
        raise FileNotFoundError(
            f"{CHROMIUM} is missing: install Debian's 'chromium' package (apt-get install chromium; .ci/run does)"
        )
    from playwright.sync_api import sync_playwright  # a test dependency: imported when a browser is wanted

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=list(CHROMIUM_ARGS))
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            page.goto(url)
            page.wait_for_function("window.relight.displayedVersion >= 0", timeout=WAIT_MS)
            yield page
        finally:
            browser.close()
