"""Headless Chromium for the tests and the bench of ``recon view``'s pages.

Debian's ``chromium`` (``make sysdeps`` installs it) driven by Playwright (the ``test`` extra);
never a browser Playwright downloads. WebGL runs on SwiftShader (software), so no GPU is needed.
"""

from __future__ import annotations

import contextlib
import io
import os
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

CHROMIUM = os.environ.get("RECON_CHROMIUM", "/usr/bin/chromium")
FLAGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
# a pixel is part of the silhouette when it differs from the white background by more than this
# (sum over R, G and B): the page's darkest shading stays far above it, anti-aliasing's faintest
# edge blends fall below it
INK = 12


@contextlib.contextmanager
def chromium() -> Iterator:
    """One headless Chromium (a fresh profile in a temporary folder), closed on exit."""
    from playwright.sync_api import sync_playwright

    if not os.path.exists(CHROMIUM):
        raise RuntimeError(f"{CHROMIUM} is missing: `make sysdeps` installs Debian's chromium")
    with tempfile.TemporaryDirectory(prefix="recon-chromium-") as profile, sync_playwright() as p:
        context = p.chromium.launch_persistent_context(
            profile, executable_path=CHROMIUM, headless=True, args=FLAGS
        )
        try:
            yield context
        finally:
            context.close()


@dataclass
class Opened:
    """A page opened in the browser, and what it said while opening."""

    page: object
    console: list[tuple[str, str]] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    requests: list[str] = field(default_factory=list)

    def value(self, expression: str):
        """The value of a JavaScript expression in the page."""
        return self.page.evaluate(expression)  # type: ignore[attr-defined]

    def console_errors(self) -> list[str]:
        """Console messages of type error, and uncaught exceptions."""
        return [text for kind, text in self.console if kind == "error"] + self.errors

    def canvas(self) -> np.ndarray:
        """A screenshot of the page's canvas, (H, W, 3) uint8."""
        from PIL import Image

        png = self.page.locator("canvas").screenshot()  # type: ignore[attr-defined]
        return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))

    def close(self) -> None:
        """Close the page (its tab)."""
        self.page.close()  # type: ignore[attr-defined]


def open_page(
    context, path: str | Path, size: tuple[int, int] = (760, 480), init: str | None = None
) -> Opened:
    """Open the page file ``path`` in a new tab of ``size`` (CSS pixels); wait for its first frame.

    Every request the page makes other than the file itself is recorded and refused. ``init``:
    a script run in the tab before the page's own.
    """
    page = context.new_page()
    if init is not None:
        page.add_init_script(init)
    page.set_viewport_size({"width": size[0], "height": size[1]})
    opened = Opened(page)
    page.on("console", lambda m: opened.console.append((m.type, m.text)))
    page.on("pageerror", lambda e: opened.errors.append(str(e)))
    url = Path(path).resolve().as_uri()

    def route(r):
        if r.request.url == url:
            r.continue_()
        else:
            opened.requests.append(r.request.url)
            r.abort()

    page.route("**/*", route)
    page.goto(url)
    page.wait_for_function("window.reconReady === true || window.reconError !== undefined")
    return opened


def silhouette(image: np.ndarray) -> np.ndarray:
    """The pixels of ``image`` (H, W, 3) that are not the white background, (H, W) bool."""
    return (255 - image.astype(np.int64)).sum(axis=2) > INK


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two masks."""
    return float((a & b).sum() / max(1, (a | b).sum()))
